"""Finite rods: `solve_boundary_value` and `force_extension` against scipy `solve_bvp`, the
cost of a shape fit and of its Jacobian (forward vs reverse mode), and where single
shooting fails.

Problems (the spring of the README: isotropic wire K1 = K2 = 1, K3 = 1/1.3, intrinsic helix
uhat = (0, 1, 0.3), canonical placement):

1. clamped-clamped, 3 turns, extension 1.1 h0, end turned by 0.5 rad;
2. a 50-point force-extension curve at fixed end rotation (magnetic tweezer), 3 turns;
3. a fit of K1, K2, K3, K13, K23 to two noisy centrelines (25 points each) of a coupled rod;
4. single vs multiple shooting on a spring stretched at fixed rotation, 2-40 turns.

Errors are against helixrod at tolerance 1e-12, itself checked against scipy at its tightest
tolerance.  helixrod runs twice per tolerance: as called by default, which also tests the
stability of the solution (`stability_pieces=16`: the conjugate-point test, which scipy does not
do), and the solve alone (`stability_pieces=0`: the same work as `solve_bvp`).  scipy integrates the same 18 unknowns (n, m, D, x) with a numpy right-hand side
and the same boundary conditions, started from the unloaded helix (one solve) or from the
previous point (the curve).  Wall times: best of `--repeats` later calls (compilation
apart).

    python benchmarks/bench_finite.py [--quick] [--parts clamped,curve]
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.integrate import solve_bvp  # noqa: E402

import helixrod as hr  # noqa: E402
from _timing import best_time  # noqa: E402

RESULTS = pathlib.Path(__file__).parent / "results"
SPRING = hr.Rod(1.0, 1.0, 1 / 1.3, uhat=(0.0, 1.0, 0.3))
NORM = math.hypot(1.0, 0.3)
TURN = 2 * math.pi / NORM
NSAVE = 41
PARTS = ("clamped", "curve", "fit", "adjoint", "shooting")
# helixrod as called by default (with its stability test on 16 pieces) and the solve alone.
HELIXROD_VARIANTS = {"helixrod": 16, "helixrod-solve": 0}


# -- the scipy peer -------------------------------------------------------------------------


def scipy_rhs(rod):
    K_inv, uhat = np.linalg.inv(np.asarray(rod.K)), np.asarray(rod.uhat)
    e3 = np.array([0.0, 0.0, 1.0])

    def fun(s, y):
        n, m, D = y[:3], y[3:6], y[6:15].reshape(3, 3, -1)
        u = uhat[:, None] + K_inv @ m
        hat = np.zeros((3, 3, u.shape[1]))
        hat[0, 1], hat[0, 2], hat[1, 0], hat[1, 2], hat[2, 0], hat[2, 1] = -u[2], u[1], u[2], -u[0], -u[1], u[0]
        return np.concatenate([
            -np.cross(u.T, n.T).T,
            (-np.cross(u.T, m.T) - np.cross(e3, n.T)).T,
            np.einsum("ijs,jks->iks", D, hat).reshape(9, -1),
            D[:, 2],
        ])

    return fun


def scipy_bc(start, kind, P=None, R=None, F=None):
    D0, x0 = np.asarray(start.frame), np.asarray(start.position)

    def bc(ya, yb):
        Db = yb[6:15].reshape(3, 3)
        A = R.T @ Db
        rot = 0.5 * np.array([A[2, 1] - A[1, 2], A[0, 2] - A[2, 0], A[1, 0] - A[0, 1]])
        first = yb[15:] - P if kind == "clamped" else Db @ yb[:3] - F
        return np.concatenate([ya[6:15] - D0.ravel(), ya[15:] - x0, first, rot])

    return bc


def unloaded_guess(rod, length, mesh):
    s = np.linspace(0.0, length, mesh)
    x, frame = (np.asarray(a) for a in hr.unloaded_state(rod, jnp.asarray(s)))
    return s, np.concatenate([np.zeros((6, mesh)), frame.reshape(mesh, 9).T, x.T])


# -- 1. one clamped-clamped solve -------------------------------------------------------------


def clamped_problem():
    length = 3 * TURN
    h0, theta0 = (float(a) for a in hr.unloaded_observables(SPRING, length))
    start, end = hr.axial_ends(SPRING, length, extension=1.1 * h0, rotation=theta0 + 0.5)
    return length, start, end


def bench_clamped(tols, scipy_tols, repeats):
    length, start, end = clamped_problem()
    s = jnp.linspace(0.0, length, NSAVE)

    def run(tol, pieces=16):
        sol = hr.solve_boundary_value(SPRING, length, start=start, end=end, saveat=s, atol=tol, ode_rtol=tol, ode_atol=tol,
                                      stability_pieces=pieces)
        return sol

    t0 = time.perf_counter()
    ref = jax.block_until_ready(run(1e-12))
    compile_s = time.perf_counter() - t0
    ref_x, ref_force = np.asarray(ref.x), np.asarray(ref.force)
    rows = []
    for library, pieces in HELIXROD_VARIANTS.items():
        for tol in tols:
            sol = run(tol, pieces)
            wall = best_time(lambda: run(tol, pieces).x, repeats)
            err = float(np.abs(np.asarray(sol.x) - ref_x).max())
            rows.append(dict(library=library, tol=tol, error=err, wall_s=wall, steps=int(sol.num_steps),
                             force_error=float(np.abs(np.asarray(sol.force) - ref_force).max())))
            print(f"  {library:13s} tol={tol:7.0e}  err={err:9.2e}  {wall * 1e3:9.2f} ms  (root steps {int(sol.num_steps)})")
    fun = scipy_rhs(SPRING)
    bc = scipy_bc(start, "clamped", P=np.asarray(end.position), R=np.asarray(end.frame))
    s0, y0 = unloaded_guess(SPRING, length, 60)
    for tol in scipy_tols:
        out = solve_bvp(fun, bc, s0, y0, tol=tol, max_nodes=200_000)
        wall = best_time(lambda: solve_bvp(fun, bc, s0, y0, tol=tol, max_nodes=200_000).y, max(1, repeats // 2))
        y = out.sol(np.asarray(s))
        err = float(np.abs(y[15:].T - ref_x).max())
        force_err = float(np.abs(y[6:15, 0].reshape(3, 3) @ y[:3, 0] - ref_force).max())
        rows.append(dict(library="scipy", tol=tol, error=err, wall_s=wall, nodes=int(out.x.size), success=bool(out.success),
                         force_error=force_err))
        print(f"  scipy    tol={tol:7.0e}  err={err:9.2e}  {wall * 1e3:9.2f} ms  (nodes {out.x.size}, success {out.success})")
    print(f"  (first helixrod call incl. compilation: {compile_s:.1f} s)")
    return dict(rows=rows, compile_s=compile_s, headline=headline(rows))


def headline(rows):
    """For each scipy run and helixrod variant: the fastest helixrod run at an error no
    larger, and the ratio."""
    out = []
    for r in (r for r in rows if r["library"] == "scipy"):
        for library in HELIXROD_VARIANTS:
            ok = [h for h in rows if h["library"] == library and h["error"] <= r["error"]]
            if ok:
                best = min(ok, key=lambda h: h["wall_s"])
                out.append(dict(library=library, scipy_tol=r["tol"], scipy_error=r["error"], scipy_s=r["wall_s"], helixrod_tol=best["tol"],
                                helixrod_error=best["error"], helixrod_s=best["wall_s"], speedup=r["wall_s"] / best["wall_s"]))
    return out


# -- 2. a 50-point force-extension curve --------------------------------------------------------


def bench_curve(count, tols, scipy_tols, repeats):
    length = 3 * TURN
    _, theta0 = (float(a) for a in hr.unloaded_observables(SPRING, length))
    forces = jnp.linspace(0.0, 0.05, count)

    def run(tol, pieces=16):
        options = hr.BoundaryValueOptions(stability_pieces=pieces)
        return hr.force_extension(SPRING, length, forces, rotation=theta0, options=options, atol=tol, ode_rtol=tol, ode_atol=tol)

    t0 = time.perf_counter()
    ref = jax.block_until_ready(run(1e-12))
    compile_s = time.perf_counter() - t0
    assert bool(jnp.all(ref.ok))
    ref_h = np.asarray(ref.extension)
    rows = []
    for library, pieces in HELIXROD_VARIANTS.items():
        for tol in tols:
            c = run(tol, pieces)
            wall = best_time(lambda: run(tol, pieces).extension, repeats)
            err = float(np.abs(np.asarray(c.extension) - ref_h).max())
            rows.append(dict(library=library, tol=tol, error=err, wall_s=wall, ok=bool(jnp.all(c.ok))))
            print(f"  {library:13s} tol={tol:7.0e}  err={err:9.2e}  {wall * 1e3:9.2f} ms for {count} points")
    start, _ = hr.axial_ends(SPRING, length, force=0.0, rotation=theta0)
    fun = scipy_rhs(SPRING)
    R = np.asarray(hr.axial_ends(SPRING, length, force=0.0, rotation=theta0)[1].frame)
    e3 = np.array([0.0, 0.0, 1.0])

    def scipy_curve(tol):
        s, y = unloaded_guess(SPRING, length, 60)
        h, ok = [], True
        for f in np.asarray(forces):
            out = solve_bvp(fun, scipy_bc(start, "tweezer", R=R, F=f * e3), s, y, tol=tol, max_nodes=200_000)
            ok = ok and out.success
            s, y = out.x, out.y  # warm start: continuation
            h.append(out.y[17, -1] - out.y[17, 0])
        return np.array(h), ok

    for tol in scipy_tols:
        t0 = time.perf_counter()
        h, ok = scipy_curve(tol)
        wall = time.perf_counter() - t0
        err = float(np.abs(h - ref_h).max())
        rows.append(dict(library="scipy", tol=tol, error=err, wall_s=wall, success=bool(ok)))
        print(f"  scipy    tol={tol:7.0e}  err={err:9.2e}  {wall * 1e3:9.2f} ms for {count} points (all converged: {ok})")
    print(f"  (first helixrod call incl. compilation: {compile_s:.1f} s)")
    curve = dict(force=np.asarray(ref.force).tolist(), extension=ref_h.tolist(), bulk_extension=np.asarray(ref.bulk_extension).tolist(),
                 moment=np.asarray(ref.moment).tolist(), bulk_moment=np.asarray(ref.bulk_moment).tolist())
    return dict(rows=rows, compile_s=compile_s, headline=headline(rows), curve=curve, length=length)


# -- 3. a shape fit, and the adjoint ------------------------------------------------------------

FIT_ROD = hr.Rod(1.0, 1.4, 0.8, K13=0.15, K23=-0.1, uhat=(0.3, 0.9, 0.35))


def shape_data():
    length = 6.0
    s = jnp.linspace(0.0, length, 25)
    ends = [hr.Loaded((0.02, 0.0, 0.05), (0.0, 0.03, 0.0)), hr.Loaded((-0.03, 0.02, 0.0), (0.02, 0.0, -0.02))]
    return hr.synthetic_shape_data(FIT_ROD, length, s, ends, 2e-3, jax.random.key(3)), ends


def bench_fit(repeats):
    data, ends = shape_data()
    init = hr.Rod(1.3, 1.3, 1.0, uhat=FIT_ROD.uhat)
    t0 = time.perf_counter()
    fit = hr.fit_stiffness(data, uhat=FIT_ROD.uhat, init=init, rtol=1e-8, atol=1e-10)
    first = time.perf_counter() - t0
    later = best_time(lambda: hr.fit_stiffness(data, uhat=FIT_ROD.uhat, init=init, rtol=1e-8, atol=1e-10).cost, repeats)
    truth = dict(zip(("K1", "K2", "K3", "K13", "K23"), (1.0, 1.4, 0.8, 0.15, -0.1)))
    z = {n: (float(fit.params[n]) - v) / float(fit.stderr[n]) for n, v in truth.items()}
    print(f"  fit of 5 stiffnesses to 2 x 25 points: first call {first:.1f} s, later {later:.2f} s, "
          f"{fit.n_steps} LM steps, reduced chi2 {fit.chi2_reduced:.3f}; (fit - truth)/stderr = "
          + ", ".join(f"{n} {v:+.2f}" for n, v in z.items()))
    return dict(first_s=first, later_s=later, steps=fit.n_steps, chi2_reduced=fit.chi2_reduced, z=z,
                params={n: float(v) for n, v in fit.params.items()}, stderr={n: float(v) for n, v in fit.stderr.items()})


def bench_adjoints(repeats):
    """Jacobian of the shape residuals (100 x 3 coordinates) with respect to 5 stiffnesses."""
    data, ends = shape_data()
    s = data.s
    names = ("K1", "K2", "K3", "K13", "K23")

    def residuals(k, adjoint):
        rod = hr.Rod(k[0], k[1], k[2], k[3], k[4], uhat=FIT_ROD.uhat)
        out = []
        for j, end in enumerate(ends):
            sol = hr.solve_boundary_value(rod, data.length, start=data.start, end=end, saveat=s, adjoint=adjoint, throw=False)
            out.append(((sol.x - data.points[j]) / data.sigma[j][:, None]).reshape(-1))
        return jnp.concatenate(out)

    k0 = jnp.array([1.0, 1.4, 0.8, 0.15, -0.1])
    rows = {}
    for label, transform, adjoint in (
        ("jacfwd, ForwardMode (default)", jax.jacfwd, diffrax.ForwardMode()),
        ("jacfwd, DirectAdjoint", jax.jacfwd, diffrax.DirectAdjoint()),
        ("jacrev, DirectAdjoint", jax.jacrev, diffrax.DirectAdjoint()),
    ):
        fn = jax.jit(transform(lambda k, a=adjoint: residuals(k, a)))
        t0 = time.perf_counter()
        J = jax.block_until_ready(fn(k0))
        first = time.perf_counter() - t0
        wall = best_time(lambda: fn(k0), repeats)
        rows[label] = dict(first_s=first, wall_s=wall, J=np.asarray(J))
        print(f"  {label:30s} first call {first:6.1f} s, later {wall * 1e3:8.1f} ms")
    base = rows["jacfwd, ForwardMode (default)"]["J"]
    for label, r in rows.items():
        r["max_abs_diff_vs_default"] = float(np.abs(r.pop("J") - base).max())
    return dict(rows=rows, parameters=list(names), residuals=int(base.shape[0]))


# -- 4. where single shooting fails ----------------------------------------------------------------


def growth_rate(rod, length, h_ratio):
    """`wrench_growth_rate` at the bulk helix with the same extension and (unturned) rotation."""
    h0, theta0 = (float(a) for a in hr.unloaded_observables(rod, length))
    bulk = hr.bulk_helix(rod, length, extension=h_ratio * h0, rotation=theta0)
    return float(hr.wrench_growth_rate(rod, bulk.mu2 * bulk.u, rod.moment(bulk.u)))


def bench_shooting(turns_list, h_ratios, segment_choices):
    rows = []
    for h_ratio in h_ratios:
        lam = growth_rate(SPRING, TURN, h_ratio)
        for turns in turns_list:
            length = turns * TURN
            h0, theta0 = (float(a) for a in hr.unloaded_observables(SPRING, length))
            start, end = hr.axial_ends(SPRING, length, extension=h_ratio * h0, rotation=theta0)
            row = dict(h_ratio=h_ratio, turns=turns, length=length, lambda_=lam, lambda_L=lam * length)
            for k in segment_choices:
                t0 = time.perf_counter()
                sol = hr.solve_boundary_value(SPRING, length, start=start, end=end, segments=k, throw=False)
                ok = bool(sol.ok)
                wall = time.perf_counter() - t0
                row[f"ok_{k}"] = ok
                if ok:
                    row[f"wall_{k}"] = best_time(
                        lambda k=k: hr.solve_boundary_value(SPRING, length, start=start, end=end, segments=k, throw=False).force, 2
                    )
                    row[f"residual_{k}"] = float(sol.residual)
                else:
                    row[f"wall_{k}"] = wall
            rows.append(row)
            print(f"  h/h0={h_ratio:4.2f} lambda={lam:6.3f} turns={turns:3d} lambda*L={lam * length:6.1f}  "
                  + "  ".join(f"k={k}: {'ok ' if row[f'ok_{k}'] else 'FAIL'} {row[f'wall_{k}'] * 1e3:7.1f} ms" for k in segment_choices))
    return rows


def plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(17, 4.6))
    for ax, key, title in ((axes[0], "clamped", "clamped-clamped solve (3 turns)"), (axes[1], "curve", "50-point force-extension curve")):
        for lib, style in (("helixrod", "-o"), ("helixrod-solve", "-^"), ("scipy", "--s")):
            sel = sorted((r for r in results[key]["rows"] if r["library"] == lib), key=lambda r: r["tol"])
            ax.loglog([r["wall_s"] for r in sel], [max(r["error"], 1e-16) for r in sel], style, label=lib)
            for r in sel:
                ax.annotate(f"{r['tol']:.0e}", (r["wall_s"], max(r["error"], 1e-16)), fontsize=7)
        ax.set_xlabel("wall time [s] (compilation excluded)")
        ax.set_ylabel("max error (centreline / extension)")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    c = results["curve"]["curve"]
    ax = axes[2]
    ax.plot(c["force"], c["extension"], label="finite rod (clamped ends)")
    ax.plot(c["force"], c["bulk_extension"], "--", label="uniform helix (bulk)")
    ax.set_xlabel("axial force F")
    ax.set_ylabel("extension h")
    ax.set_title(f"end rotation held, L = {results['curve']['length']:.1f}")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="fewer tolerances, lengths and repeats; no adjoint comparison")
    parser.add_argument("--repeats", type=int, default=None)
    parser.add_argument("--parts", default=",".join(PARTS),
                        help=f"comma-separated subset of {', '.join(PARTS)}; the others keep their results from the saved JSON")
    args = parser.parse_args()
    parts = set(args.parts.split(","))
    if not parts <= set(PARTS):
        parser.error(f"--parts: unknown {sorted(parts - set(PARTS))}; choose from {', '.join(PARTS)}")
    repeats = args.repeats or (3 if args.quick else 7)
    tols = [1e-6, 1e-8, 1e-10] if args.quick else [1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11]
    scipy_tols = [1e-4, 1e-6, 1e-8] if args.quick else [1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8]
    saved = RESULTS / "bench_finite.json"
    results = json.loads(saved.read_text())["results"] if parts != set(PARTS) and saved.exists() else {}
    if "clamped" in parts:
        print("1. clamped-clamped solve, 3 turns (41 saved points)")
        results["clamped"] = bench_clamped(tols, scipy_tols, repeats)
    if "curve" in parts:
        print("2. force-extension curve, 50 points, end rotation held")
        results["curve"] = bench_curve(50, tols, scipy_tols[:2] if args.quick else scipy_tols[:4], repeats)
    if "fit" in parts:
        print("3. shape fit (2 images x 25 points, 5 stiffnesses) and its Jacobian")
        results["fit"] = bench_fit(max(1, repeats // 2))
    if "adjoint" in parts and not args.quick:  # the adjoint choice: three more compilations of ~25-50 s each
        results["adjoint"] = bench_adjoints(repeats)
    if "shooting" in parts:
        print("4. single vs multiple shooting, spring stretched at fixed end rotation")
        turns = [2, 5, 10, 20] if args.quick else [2, 3, 5, 7, 10, 15, 20, 30, 40]
        results["shooting"] = bench_shooting(turns, [1.1, 1.5], [1, 4, 16])
    for key in ("clamped", "curve"):
        for h in results.get(key, {}).get("headline", []):
            print(f"  {key}: scipy tol {h['scipy_tol']:.0e} (err {h['scipy_error']:.1e}, {h['scipy_s'] * 1e3:.1f} ms) vs {h['library']} "
                  f"tol {h['helixrod_tol']:.0e} (err {h['helixrod_error']:.1e}, {h['helixrod_s'] * 1e3:.2f} ms): {h['speedup']:.0f}x")
    RESULTS.mkdir(exist_ok=True)
    payload = dict(device=str(jax.devices()[0]), quick=args.quick, results=results,
                   note="2 CPU cores shared with other jobs while measured: timings are noisy and pessimistic")
    saved.write_text(json.dumps(payload, indent=1))
    if "clamped" in results and "curve" in results:
        plot(results, RESULTS / "bench_finite.png")
    print(f"saved {RESULTS / 'bench_finite.json'} and .png")


if __name__ == "__main__":
    main()
