"""Benchmark: fit_stiffness against scipy.optimize.least_squares on the same problem.

Data: helices of the Chouaieb-Goriely-Maddocks rod (K1 = 1, K2 = 1.5, K3 = 0.8,
K13 = K23 = 0.5, uhat = (1, 0, 0) known) at their minimum-energy registers, with Gaussian
noise on F and M.  Both solvers fit the five stiffnesses from the same start (the isotropic
least-squares rod that fit_stiffness uses as its first start), with the same
parameterisation (log K1, log K2, log Schur complement, K13, K23), the same "nearest
register" rule and the same sigma-normalised residuals.  The peer's forward model is numpy:
registers from the eigenvalues of the companion matrix of the quartic in tan(phi/2)
(batched), and scipy least_squares(method="trf", jac="2-point").  helixrod: optimistix
Levenberg-Marquardt with one start (n_starts=1, like the peer) and with the default 32
vmapped starts; first call (tracing + compilation + run) and later calls (median of 3)
timed apart.  optax L-BFGS and Adam at one size for comparison.

Usage: python benchmarks/bench_fit.py [--quick]
Writes benchmarks/results/bench_fit.json and .png.  Timings on a shared, loaded 2-core
machine are pessimistic and noisy.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import helixrod as hr  # noqa: E402

ROD = hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
TRUTH = np.array([1.0, 1.5, 0.8, 0.5, 0.5])
UHAT = np.array([1.0, 0.0, 0.0])


def numpy_wrench(K, kappa, tau):
    """Every register's (F, M) for stiffness K = (K1, K2, K3, K13, K23), numpy only."""
    K1, K2, K3, K13, K23 = K
    u1h, u2h, u3h = UHAT
    A = 0.5 * (K1 - K2) * kappa
    B = K2 * u2h + K23 * (u3h - tau)
    C = K13 * (tau - u3h) - K1 * u1h
    # P(t) = -C t^4 + (2B - 4A) t^3 + (4A + 2B) t + C, t = tan(phi/2).
    a4 = -C
    coeffs = np.stack([(2 * B - 4 * A) / a4, np.zeros_like(A), (4 * A + 2 * B) / a4, C / a4], axis=-1)
    n = kappa.shape[0]
    comp = np.zeros((n, 4, 4))
    comp[:, 0, :] = -coeffs
    comp[:, 1, 0] = comp[:, 2, 1] = comp[:, 3, 2] = 1.0
    t = np.linalg.eigvals(comp)
    real = np.abs(t.imag) <= 1e-7 * (1 + np.abs(t.real))
    t = t.real
    phi = 2 * np.arctan(t)
    k, ta = kappa[:, None], tau[:, None]
    u1, u2 = k * np.sin(phi), k * np.cos(phi)
    v1, v2, v3 = u1 - u1h, u2 - u2h, ta - u3h
    m1, m2, m3 = K1 * v1 + K13 * v3, K2 * v2 + K23 * v3, K13 * v1 + K23 * v2 + K3 * v3
    mu1 = (m1 * u1 + m2 * u2) / (k * k)
    mu2 = m3 - mu1 * ta
    norm = np.sqrt(k * k + ta * ta)
    return mu2 * norm, mu1 * norm + mu2 * ta / norm, real


def isotropic_start(data):
    """The peer's start: the isotropic rod (K1 = K2 = B, K3 = C, uhat = 0) that fits the
    data by weighted linear least squares -- Love's formulas F = |u| tau (C - B),
    M = (B kappa^2 + C tau^2)/|u| are linear in B and C."""
    k, t = np.asarray(data.kappa), np.asarray(data.tau)
    norm = np.hypot(k, t)
    sF, sM = np.asarray(data.force_sigma), np.asarray(data.moment_sigma)
    A = np.concatenate([np.stack([-norm * t, norm * t], 1) / sF[:, None], np.stack([k * k / norm, t * t / norm], 1) / sM[:, None]])
    b = np.concatenate([np.asarray(data.force) / sF, np.asarray(data.moment) / sM])
    (B, C), *_ = np.linalg.lstsq(A, b, rcond=None)
    floor = max(abs(B), abs(C), 1e-300) * 1e-2
    return max(B, floor), max(C, floor)


def to_K(z, ks):
    K1, K2 = ks * np.exp(z[0]), ks * np.exp(z[1])
    K13, K23 = ks * z[3], ks * z[4]
    return np.array([K1, K2, ks * np.exp(z[2]) + K13**2 / K1 + K23**2 / K2, K13, K23])


def scipy_fit(data, z0, ks):
    from scipy.optimize import least_squares

    F, M = np.asarray(data.force), np.asarray(data.moment)
    sF, sM = np.asarray(data.force_sigma), np.asarray(data.moment_sigma)
    kappa, tau = np.asarray(data.kappa), np.asarray(data.tau)

    def residuals(z):
        Fp, Mp, real = numpy_wrench(to_K(z, ks), kappa, tau)
        rF, rM = (Fp - F[:, None]) / sF[:, None], (Mp - M[:, None]) / sM[:, None]
        d = np.where(real, rF**2 + rM**2, np.inf)
        j = np.argmin(d, axis=1)[:, None]
        return np.concatenate([np.take_along_axis(rF, j, 1)[:, 0], np.take_along_axis(rM, j, 1)[:, 0]])

    t0 = time.perf_counter()
    sol = least_squares(residuals, z0, method="trf", jac="2-point", xtol=1e-12, ftol=1e-12, gtol=1e-12)
    elapsed = time.perf_counter() - t0
    return elapsed, float(sol.cost), to_K(sol.x, ks), int(sol.nfev)


def scipy_multistart(data, z0, ks, n, noise, n_starts=32):
    """The peer from the same 32 starts as fit_stiffness (same key, same spreads)."""
    spread = np.array([0.7, 0.7, 0.5, 0.5, 0.5])
    starts = z0 + spread * np.array(jax.random.normal(jax.random.key(0), (n_starts, 5)))
    starts[0] = z0
    total, best = 0.0, (np.inf, None)
    for z in starts:
        elapsed, cost, K, _ = scipy_fit(data, z, ks)
        total += elapsed
        if cost < best[0]:
            best = (cost, K)
    return dict(n=n, noise=noise, solver="scipy trf, 32 starts", first_s=total, later_s=total, cost=float(best[0]), err=param_error(best[1]))


def helixrod_fit(data, **kw):
    t0 = time.perf_counter()
    fit = hr.fit_stiffness(data, uhat=UHAT, **kw)
    return time.perf_counter() - t0, fit


def param_error(K):
    """Max relative error, modulo the one symmetry left with uhat = (1, 0, 0) fixed:
    reading the rod end for end about d2, K23 -> -K23 (identical predictions)."""
    K = np.asarray(K, float)
    mirror = K * np.array([1, 1, 1, 1, -1])
    return float(min(np.max(np.abs(K - TRUTH) / TRUTH), np.max(np.abs(mirror - TRUTH) / TRUTH)))


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    sizes = [20, 200] if args.quick else [20, 100, 1000, 10000]
    noises = [0.01] if args.quick else [0.001, 0.01, 0.05]
    rng = np.random.default_rng(0)
    rows = []
    print(f"{'n':>6} {'noise':>6} {'solver':>22} {'first s':>9} {'later s':>9} {'cost':>12} {'max rel err':>11}")
    for n in sizes:
        kappa = rng.uniform(0.3, 2.5, n)
        tau = rng.uniform(-1.5, 2.0, n)
        for noise in noises:
            data = hr.synthetic_helix_data(ROD, kappa, tau, noise, jax.random.key(n))
            B, C = isotropic_start(data)
            ks = B
            z0 = np.array([0.0, 0.0, np.log(C / ks), 0.0, 0.0])
            for label, kw in (("helixrod LM, 1 start", dict(n_starts=1)), ("helixrod LM, 32 starts", dict(n_starts=32))):
                first, fit = helixrod_fit(data, **kw)
                later = float(np.median([helixrod_fit(data, **kw)[0] for _ in range(3)]))
                K = [float(fit.params[k]) for k in ("K1", "K2", "K3", "K13", "K23")]
                rows.append(dict(n=n, noise=noise, solver=label, first_s=first, later_s=later, cost=float(fit.cost), err=param_error(K)))
                print(f"{n:6d} {noise:6.3f} {label:>22} {first:9.3f} {later:9.4f} {fit.cost:12.6g} {rows[-1]['err']:11.3g}")
            elapsed, cost, K, nfev = scipy_fit(data, z0, ks)
            rows.append(dict(n=n, noise=noise, solver="scipy trf 2-point", first_s=elapsed, later_s=elapsed, cost=cost, err=param_error(K), nfev=nfev))
            print(f"{n:6d} {noise:6.3f} {'scipy trf 2-point':>22} {elapsed:9.3f} {elapsed:9.4f} {cost:12.6g} {rows[-1]['err']:11.3g}")
            row = scipy_multistart(data, z0, ks, n, noise)
            rows.append(row)
            print(f"{n:6d} {noise:6.3f} {row['solver']:>22} {row['first_s']:9.3f} {row['later_s']:9.4f} {row['cost']:12.6g} {row['err']:11.3g}")
    # optimistix vs optax at one size
    n = 100
    kappa, tau = rng.uniform(0.3, 2.5, n), rng.uniform(-1.5, 2.0, n)
    data = hr.synthetic_helix_data(ROD, kappa, tau, 0.01, jax.random.key(1))
    for method, kw in (("gauss-newton", {}), ("lbfgs", dict(max_steps=500)), ("adam", dict(max_steps=2000, learning_rate=2e-2))):
        first, fit = helixrod_fit(data, solver=method, n_starts=1, **kw)
        later = float(np.median([helixrod_fit(data, solver=method, n_starts=1, **kw)[0] for _ in range(3)]))
        K = [float(fit.params[k]) for k in ("K1", "K2", "K3", "K13", "K23")]
        rows.append(dict(n=n, noise=0.01, solver=f"helixrod {method}", first_s=first, later_s=later, cost=float(fit.cost), err=param_error(K)))
        print(f"{n:6d} {0.01:6.3f} {'helixrod ' + method:>22} {first:9.3f} {later:9.4f} {fit.cost:12.6g} {rows[-1]['err']:11.3g}")

    out = Path(__file__).resolve().parent / "results"
    out.mkdir(exist_ok=True)
    (out / "bench_fit.json").write_text(json.dumps({"quick": args.quick, "rows": rows}, indent=2))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for label, colour in (
        ("helixrod LM, 1 start", "#0072B2"),
        ("helixrod LM, 32 starts", "#009E73"),
        ("scipy trf 2-point", "#D55E00"),
        ("scipy trf, 32 starts", "#CC79A7"),
    ):
        for noise, marker in zip(noises, "os^"):
            sel = [r for r in rows if r["solver"] == label and r["noise"] == noise]
            axes[0].loglog([r["n"] for r in sel], [r["later_s"] for r in sel], marker=marker, color=colour, label=f"{label}, noise {noise}")
            axes[1].loglog([r["n"] for r in sel], [max(r["err"], 1e-16) for r in sel], marker=marker, color=colour)
    axes[0].set_xlabel("data points")
    axes[0].set_ylabel("time to solution (later calls) [s]")
    axes[1].set_xlabel("data points")
    axes[1].set_ylabel("max relative stiffness error")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "bench_fit.png", dpi=120)
    print(f"wrote {out / 'bench_fit.json'} and .png")


if __name__ == "__main__":
    main()
