"""Speed and accuracy of `helix_equilibria` (every register + wrench + stability, float64)
against its peers, in one process:

* the numpy peer (`_numpy_peer.numpy_helix_equilibria`): batched companion-matrix
  eigenvalues of the register quartic, two Newton steps, wrench and stability -- what a
  careful numpy user would write;
* the numba peer (`_numba_peer.numba_helix_equilibria`): a hand-written compiled kernel of
  the same job (vectorised passes, the inner pair solved only where it exists, early
  exits), checked here against `helix_equilibria` point by point (register count and
  stability everywhere, phi), on all cores and, with `--one-core`, on one;
* scipy point by point: a sign scan of f(phi) on 64 intervals and `scipy.optimize.brentq`
  on each bracket, then the same wrench (on a subset: it is slow).

Accuracy of all three against a 40-digit mpmath reference on a sample of points; compile
time measured apart (`jax.jit(f).lower(...).compile()`); wall and CPU time (XLA may use
both cores; numpy's batched `eigvals` and scipy run on one).

    python benchmarks/bench_equilibria.py --quick     # 1e4 ... 1e6 points
    python benchmarks/bench_equilibria.py             # 1e4 ... 1e7 points
    python benchmarks/bench_equilibria.py --quick --one-core   # pinned to one core

Writes benchmarks/results/bench_equilibria.json and .png.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

if "--one-core" in sys.argv:
    # Before numba starts its threads: one thread in every thread that calls it (helixrod's
    # register kernel runs on XLA's threads, which numba.set_num_threads does not reach).
    os.environ["NUMBA_NUM_THREADS"] = "1"

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import mpmath  # noqa: E402
import numba  # noqa: E402
import numpy as np  # noqa: E402
from scipy.optimize import brentq  # noqa: E402

import helixrod as hr  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from _machine import cpu_model  # noqa: E402
from _numba_peer import numba_helix_equilibria  # noqa: E402
from _numpy_peer import numpy_helix_equilibria  # noqa: E402

RESULTS = Path(__file__).parent / "results"
ROD_ARGS = dict(K1=1.0, K2=1.5, K3=0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))  # Chouaieb-Goriely-Maddocks fig. 2
ROD = hr.Rod(**ROD_ARGS)
FIELDS = ("phi", "valid", "force", "moment", "stable")


def points(n, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(0.01, 3.0, n), rng.uniform(-3.0, 3.0, n)


@jax.jit
def helixrod_fields(kappa, tau):
    eq = hr.helix_equilibria(ROD, kappa, tau, fields=FIELDS)
    return {name: getattr(eq, name) for name in FIELDS}


def scipy_pointwise(kappa, tau, intervals=64):
    """Every register of each helix by a sign scan and brentq, then the wrench; slots sorted
    by energy as in the numpy peer (only phi, force, moment, stable are compared)."""
    K1, K2, K3, K13, K23 = (ROD_ARGS[k] for k in ("K1", "K2", "K3", "K13", "K23"))
    u1h, u2h, u3h = ROD_ARGS["uhat"]
    grid = np.linspace(0.0, 2 * np.pi, intervals + 1)
    out = []
    for k, t in zip(kappa, tau):
        A = 0.5 * (K1 - K2) * k
        B = K2 * u2h + K23 * (u3h - t)
        C = K13 * (t - u3h) - K1 * u1h

        def f(p, A=A, B=B, C=C):
            return A * np.sin(2 * p) + B * np.sin(p) + C * np.cos(p)

        values = f(grid)
        roots = [brentq(f, grid[i], grid[i + 1], xtol=1e-15, rtol=8.9e-16)
                 for i in range(intervals) if values[i] * values[i + 1] < 0]
        rows = []
        for p in roots:
            s, c = np.sin(p), np.cos(p)
            v1, v2, v3 = k * s - u1h, k * c - u2h, t - u3h
            m1, m2, m3 = K1 * v1 + K13 * v3, K2 * v2 + K23 * v3, K13 * v1 + K23 * v2 + K3 * v3
            mu1 = (m1 * s + m2 * c) / k
            mu2 = m3 - mu1 * t
            norm = np.hypot(k, t)
            energy = 0.5 * (v1 * m1 + v2 * m2 + v3 * m3)
            fp = 2 * A * np.cos(2 * p) + B * np.cos(p) - C * np.sin(p)
            rows.append((energy, p, mu2 * norm, mu1 * norm + mu2 * t / norm, k * fp > 0))
        out.append(sorted(rows))
    return out


def mpmath_reference(kappa, tau, scan=4000):
    """40-digit registers (dense scan + bisection) and their axial force."""
    mpmath.mp.dps = 40
    K1, K2, K3, K13, K23 = (mpmath.mpf(ROD_ARGS[k]) for k in ("K1", "K2", "K3", "K13", "K23"))
    u1h, u2h, u3h = (mpmath.mpf(x) for x in ROD_ARGS["uhat"])
    grid = np.linspace(0.0, 2 * np.pi, scan + 1)
    refs = []
    for k, t in zip(kappa, tau):
        k, t = mpmath.mpf(k), mpmath.mpf(t)
        A = (K1 - K2) * k / 2
        B = K2 * u2h + K23 * (u3h - t)
        C = K13 * (t - u3h) - K1 * u1h
        f = lambda p: A * mpmath.sin(2 * p) + B * mpmath.sin(p) + C * mpmath.cos(p)  # noqa: E731
        values = float(A) * np.sin(2 * grid) + float(B) * np.sin(grid) + float(C) * np.cos(grid)
        rows = []
        for i in range(scan):
            if values[i] * values[i + 1] < 0:
                p = mpmath.findroot(f, (mpmath.mpf(grid[i]), mpmath.mpf(grid[i + 1])), solver="anderson")
                s, c = mpmath.sin(p), mpmath.cos(p)
                v1, v2, v3 = k * s - u1h, k * c - u2h, t - u3h
                m1, m2, m3 = K1 * v1 + K13 * v3, K2 * v2 + K23 * v3, K13 * v1 + K23 * v2 + K3 * v3
                mu1 = (m1 * s + m2 * c) / k
                mu2 = m3 - mu1 * t
                rows.append((float(p), float(mu2 * mpmath.sqrt(k * k + t * t))))
        refs.append(rows)
    return refs


def angle_error(x, y):
    return np.abs(np.angle(np.exp(1j * (x - y))))


def errors_against(refs, found):
    """Max |dphi| and max relative dF over the reference registers; `found` is a list of
    (phi array, force array) per point.  A missed or extra register counts as infinite."""
    dphi, dforce = 0.0, 0.0
    for ref, (phi, force) in zip(refs, found):
        if len(ref) != len(phi):
            return float("inf"), float("inf")
        for p, F in ref:
            i = int(np.argmin(angle_error(phi, p)))
            dphi = max(dphi, float(angle_error(phi[i], p)))
            dforce = max(dforce, abs(force[i] - F) / max(1.0, abs(F)))
    return dphi, dforce


def timed(fn, repeats):
    best_wall, best_cpu = np.inf, np.inf
    for _ in range(repeats):
        c0, w0 = time.process_time(), time.perf_counter()
        fn()
        best_wall = min(best_wall, time.perf_counter() - w0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    return best_wall, best_cpu


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1e4 ... 1e6 points")
    parser.add_argument("--one-core", action="store_true", help="pin the process (XLA and numba) to one core")
    opts = parser.parse_args()
    if opts.one_core:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
        numba.set_num_threads(1)
    cores = len(os.sched_getaffinity(0))
    sizes = [10_000, 100_000, 1_000_000] if opts.quick else [10_000, 100_000, 1_000_000, 10_000_000]
    n_scipy = 300 if opts.quick else 2000
    n_ref = 100 if opts.quick else 400
    repeats = 3
    report = dict(
        machine=dict(platform=platform.platform(), cpus=os.cpu_count(), cpu=cpu_model(), devices=[str(d) for d in jax.local_devices()],
                     jax=jax.__version__, numpy=np.__version__),
        rod=ROD_ARGS, runs=[], accuracy={}, compile_s={}, cores=cores, agreement={}, flops_per_point={},
    )

    # Accuracy against the 40-digit reference, on the same sample for every method.
    k, t = points(n_ref, seed=1)
    refs = mpmath_reference(k, t)
    eq = {name: np.asarray(x) for name, x in helixrod_fields(jnp.asarray(k), jnp.asarray(t)).items()}
    peer = numpy_helix_equilibria(**ROD_ARGS, kappa=k, tau=t)
    hand = numba_helix_equilibria(**ROD_ARGS, kappa=k, tau=t)
    sp = scipy_pointwise(k, t)
    report["accuracy"] = acc = {
        "helixrod": errors_against(refs, [(eq["phi"][i][eq["valid"][i]], eq["force"][i][eq["valid"][i]]) for i in range(n_ref)]),
        "numpy": errors_against(refs, [(peer["phi"][i][peer["valid"][i]], peer["force"][i][peer["valid"][i]]) for i in range(n_ref)]),
        "numba": errors_against(refs, [(hand["phi"][i][hand["valid"][i]], hand["force"][i][hand["valid"][i]]) for i in range(n_ref)]),
        "scipy": errors_against(refs, [(np.array([r[1] for r in rows]), np.array([r[2] for r in rows])) for rows in sp]),
    }
    print(f"accuracy against 40-digit mpmath on {n_ref} helices (max |dphi|, max relative dF):")
    for name, (dphi, dforce) in acc.items():
        print(f"  {name:>9}: {dphi:.1e}  {dforce:.1e}")

    # Compile time apart from run time, for each size (one executable per shape).
    print(f"{cores} core(s); {'method':>9} {'points':>10} {'wall s':>9} {'cpu s':>8} {'points/s':>10} {'vs numpy':>9} {'vs numba':>9}")
    for n in sizes:
        k, t = points(n)
        kj, tj = jnp.asarray(k), jnp.asarray(t)
        start = time.perf_counter()
        compiled = helixrod_fields.lower(kj, tj).compile()
        report["compile_s"][n] = time.perf_counter() - start
        cost = compiled.cost_analysis()
        cost = cost[0] if isinstance(cost, list) else cost
        report["flops_per_point"][n] = cost.get("flops", float("nan")) / n
        ours = {name: np.asarray(x) for name, x in compiled(kj, tj).items()}
        hand = numba_helix_equilibria(**ROD_ARGS, kappa=k, tau=t)
        both = ours["valid"] & hand["valid"]
        report["agreement"][n] = agree = dict(
            count_differences=int(np.sum(ours["valid"].sum(-1) != hand["valid"].sum(-1))),
            stable_differences=int(np.sum(ours["stable"] != hand["stable"])),
            max_dphi=float(np.max(angle_error(ours["phi"][both], hand["phi"][both]))),
        )
        # helixrod and the numba peer interleaved, best of enough calls to reach steady
        # state (a 1e4-point call takes ~1 ms; the machine's noise is tens of percent).
        rounds = max(5, min(50, 1_000_000 // n))
        wall = cpu = hand_wall = hand_cpu = np.inf
        for _ in range(rounds):
            w, c = timed(lambda: jax.block_until_ready(compiled(kj, tj)), 1)
            wall, cpu = min(wall, w), min(cpu, c)
            w, c = timed(lambda: numba_helix_equilibria(**ROD_ARGS, kappa=k, tau=t), 1)
            hand_wall, hand_cpu = min(hand_wall, w), min(hand_cpu, c)
        peer_wall, peer_cpu = timed(lambda: numpy_helix_equilibria(**ROD_ARGS, kappa=k, tau=t), 1 if n >= 10_000_000 else repeats)
        for name, w, c in (("numpy", peer_wall, peer_cpu), ("numba", hand_wall, hand_cpu), ("helixrod", wall, cpu)):
            report["runs"].append(dict(method=name, points=n, wall_s=w, cpu_s=c, points_per_s=n / w,
                                       speedup_vs_numpy=peer_wall / w, cpu_ratio_vs_numpy=peer_cpu / c,
                                       speedup_vs_numba=hand_wall / w))
            print(f"{'':>11} {name:>9} {n:>10} {w:>9.4f} {c:>8.4f} {n / w:>10.3g} {peer_wall / w:>8.1f}x {hand_wall / w:>8.2f}x")
        print(f"{'':>11} compile {report['compile_s'][n]:.2f} s; per-core ratio to numpy (CPU time) {peer_cpu / cpu:.1f}x; "
              f"XLA counts {report['flops_per_point'][n]:.0f} flops per point; against numba: {agree}")
    k, t = points(n_scipy, seed=2)
    wall, cpu = timed(lambda: scipy_pointwise(k, t), 1)
    numpy_rate = next(r["points_per_s"] for r in report["runs"] if r["method"] == "numpy" and r["points"] == sizes[-1])
    report["runs"].append(dict(method="scipy", points=n_scipy, wall_s=wall, cpu_s=cpu, points_per_s=n_scipy / wall,
                               speedup_vs_numpy=(n_scipy / wall) / numpy_rate))
    print(f"{'scipy':>9} {n_scipy:>10} {wall:>9.4f} {cpu:>8.4f} {n_scipy / wall:>10.3g} {(n_scipy / wall) / numpy_rate:>8.3f}x")
    RESULTS.mkdir(exist_ok=True)
    stem = "bench_equilibria_one_core" if opts.one_core else "bench_equilibria"
    (RESULTS / f"{stem}.json").write_text(json.dumps(report, indent=2))
    plot(report, RESULTS / f"{stem}.png")
    print(f"wrote {RESULTS / stem}.json and .png")
    return report


def plot(report, path):
    from matplotlib.figure import Figure

    from helixrod.plot import OKABE_ITO

    fig = Figure(figsize=(6.4, 4.2), layout="constrained")
    ax = fig.add_subplot()
    for i, name in enumerate(("helixrod", "numpy", "numba", "scipy")):
        runs = [r for r in report["runs"] if r["method"] == name]
        dphi = report["accuracy"][name][0]
        ax.loglog([r["points"] for r in runs], [r["points_per_s"] for r in runs], "o-", color=OKABE_ITO[i],
                  label=f"{name} (max |dphi| {dphi:.0e})")
    ax.set_xlabel("helices (kappa, tau) per call")
    ax.set_ylabel("helices per second (every register, wrench, stability)")
    ax.set_title(f"helix_equilibria throughput, float64, CPU ({report['cores']} core(s))")
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    fig.savefig(path, dpi=150)


if __name__ == "__main__":
    main()
