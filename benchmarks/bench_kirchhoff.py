"""Work-precision of `solve_static` against scipy `solve_ivp`, and vmapped throughput.

Problems: (a) a 100-turn uniform helix (exact reference `helix_frame`/`helix_centreline`),
(b) a non-helical solution (reference: scipy DOP853 at rtol = atol = 1e-13).  Error: the
largest absolute error of the frame and of the centreline at s = L.  Wall time: best of
`--repeats` runs after compilation (compile time reported apart).  scipy integrates the
same 18-dimensional system (n, m, D, x) with a numpy right-hand side.

    python benchmarks/bench_kirchhoff.py [--quick]
    python benchmarks/bench_kirchhoff.py --saved-only [--one-core]   # the saved-point rows alone

`--saved-only` writes results/bench_kirchhoff_saved[_one_core].json; `--one-core` pins the
process to one core (XLA then runs no operation of a program concurrently with another).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

import helixrod as hr  # noqa: E402
from _machine import cpu_model  # noqa: E402
from _timing import best_cpu_time, best_time  # noqa: E402

ROD = hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
RESULTS = pathlib.Path(__file__).parent / "results"


def problems():
    kappa, tau = 1.0, 0.5
    eq = hr.helix_equilibria(ROD, kappa, tau)
    n0, m0, frame0, x0 = (np.asarray(a[0]) for a in hr.helix_initial_conditions(eq))
    length = 100 * 2 * np.pi / np.hypot(kappa, tau)
    helix = dict(
        name="helix, 100 turns", n0=n0, m0=m0, frame0=frame0, x0=x0, length=length,
        frame=np.asarray(hr.helix_frame(kappa, tau, eq.phi[0], length)),
        x=np.asarray(hr.helix_centreline(kappa, tau, length)),
    )
    n1 = n0 + np.array([0.05, -0.1, 0.08])
    m1 = m0 + np.array([0.1, 0.05, -0.07])
    frame1 = np.asarray(hr.so3_exp(jnp.array([0.3, -0.2, 0.5])))
    perturbed = dict(name="non-helical, L = 40", n0=n1, m0=m1, frame0=frame1, x0=np.zeros(3), length=40.0)
    ref = scipy_solve(perturbed, "DOP853", 1e-13)
    perturbed.update(frame=ref["frame"], x=ref["x"])
    return [helix, perturbed]


def scipy_rhs(rod=ROD):
    K = np.asarray(rod.K)
    uhat = np.asarray(rod.uhat)
    K_inv = np.linalg.inv(K)
    e3 = np.array([0.0, 0.0, 1.0])

    def rhs(s, y):
        n, m, D = y[:3], y[3:6], y[6:15].reshape(3, 3)
        u = uhat + K_inv @ m
        uhat_matrix = np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
        return np.concatenate(
            [-np.cross(u, n), -np.cross(u, m) - np.cross(e3, n), (D @ uhat_matrix).ravel(), D[:, 2]]
        )

    return rhs


def scipy_solve(problem, method, tol):
    y0 = np.concatenate([problem["n0"], problem["m0"], problem["frame0"].ravel(), problem["x0"]])
    out = solve_ivp(scipy_rhs(), (0.0, problem["length"]), y0, method=method, rtol=tol, atol=tol)
    y = out.y[:, -1]
    return dict(frame=y[6:15].reshape(3, 3), x=y[15:], steps=out.t.size - 1, nfev=out.nfev)


def error(problem, frame, x):
    return float(max(np.abs(np.asarray(frame) - problem["frame"]).max(), np.abs(np.asarray(x) - problem["x"]).max()))


def diffrax_runs(problem, solvers, tols, repeats):
    rows = []
    for name, solver in solvers.items():

        @jax.jit
        def run(n0, m0, frame0, x0, length, tol, solver=solver):
            sol = hr.solve_static(
                ROD, n0, m0, length, frame0=frame0, x0=x0, outputs=("frame", "centreline"),
                solver=solver, rtol=tol, atol=tol, max_steps=200_000,
            )
            return sol.frame[-1], sol.x[-1], sol.num_steps

        args = [jnp.asarray(problem[k]) for k in ("n0", "m0", "frame0", "x0", "length")]
        start = time.perf_counter()
        run.lower(*args, 1e-8).compile()
        compile_s = time.perf_counter() - start
        for tol in tols:
            frame, x, steps = run(*args, tol)
            wall = best_time(lambda: run(*args, tol), repeats)
            rows.append(dict(method=name, library="diffrax", tol=tol, error=error(problem, frame, x),
                             wall_s=wall, compile_s=compile_s, steps=int(steps)))
            print(f"  {name:10s} tol={tol:7.0e}  err={rows[-1]['error']:9.2e}  {wall * 1e3:9.3f} ms  "
                  f"steps={int(steps):6d}  (compile {compile_s:.1f} s)")
    return rows


def scipy_runs(problem, methods, tols, repeats):
    rows = []
    for method in methods:
        for tol in tols:
            out = scipy_solve(problem, method, tol)
            wall = best_time(lambda: scipy_solve(problem, method, tol)["x"], repeats)
            rows.append(dict(method=method, library="scipy", tol=tol, error=error(problem, out["frame"], out["x"]),
                             wall_s=wall, steps=out["steps"]))
            print(f"  {method:10s} tol={tol:7.0e}  err={rows[-1]['error']:9.2e}  {wall * 1e3:9.3f} ms  steps={out['steps']:6d}")
    return rows


DEFAULT = "RKMK-Dopri8 (default)"
DEFAULT_TOL = 1e-12  # solve_static's default rtol = atol in float64


def headline(rows):
    """`solve_static` at its defaults (solver and tolerance) against scipy DOP853 at tol
    1e-10, and the fastest diffrax run with an error no worse than DOP853's."""
    target = [r for r in rows if r["method"] == "DOP853" and r["tol"] == 1e-10]
    if not target:
        return None
    target = target[0]
    default = next((r for r in rows if r["method"] == DEFAULT and r["tol"] == DEFAULT_TOL), None)
    best_any = min((r for r in rows if r["library"] == "diffrax" and r["error"] <= target["error"]), key=lambda r: r["wall_s"], default=None)
    fastest = None if best_any is None else dict(run=best_any, speedup=target["wall_s"] / best_any["wall_s"])
    if default is None:
        return dict(dop853=target, default=None, speedup=None, fastest_diffrax=fastest)
    return dict(dop853=target, default=default, speedup=target["wall_s"] / default["wall_s"],
                default_error_no_worse=default["error"] <= target["error"], fastest_diffrax=fastest)


def batched(problem, count, repeats, tol):
    """vmap over `count` perturbed initial conditions vs a loop of single solves."""
    key = jax.random.PRNGKey(0)
    dn, dm = 0.05 * jax.random.normal(key, (2, count, 3))
    n0 = jnp.asarray(problem["n0"]) + dn
    m0 = jnp.asarray(problem["m0"]) + dm
    length = 20.0

    def one(n, m):
        sol = hr.solve_static(ROD, n, m, length, outputs=("frame", "centreline"), rtol=tol, atol=tol)
        return sol.x[-1], sol.num_steps

    single = jax.jit(one)
    many = jax.jit(jax.vmap(one))
    jax.block_until_ready(single(n0[0], m0[0]))
    jax.block_until_ready(many(n0, m0))
    loop_count = min(count, 100)
    start = time.perf_counter()
    steps = [int(single(n0[i], m0[i])[1]) for i in range(loop_count)]
    loop_per_solve = (time.perf_counter() - start) / loop_count
    vmap_total = best_time(lambda: many(n0, m0), repeats)
    _, vsteps = many(n0, m0)
    vsteps = np.asarray(vsteps)
    out = dict(
        count=count, tol=tol, loop_per_solve_s=loop_per_solve, vmap_per_solve_s=vmap_total / count,
        vmap_total_s=vmap_total, mean_steps=float(vsteps.mean()), max_steps=int(vsteps.max()),
        lockstep_overhead=float(vsteps.max() / vsteps.mean()), loop_mean_steps=float(np.mean(steps)),
    )
    print(f"  vmap x{count}: {vmap_total * 1e3:.1f} ms total, {out['vmap_per_solve_s'] * 1e6:.1f} us/solve; "
          f"loop {loop_per_solve * 1e6:.1f} us/solve; steps mean {out['mean_steps']:.0f} max {out['max_steps']} "
          f"(lockstep does max/mean = {out['lockstep_overhead']:.2f}x the work)")
    return out


def plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(6 * len(results), 4.5))
    for ax, (name, rows) in zip(np.atleast_1d(axes), results.items()):
        for method in dict.fromkeys(r["method"] for r in rows):
            sel = sorted((r for r in rows if r["method"] == method), key=lambda r: r["tol"])
            style = "--" if sel[0]["library"] == "scipy" else "-"
            ax.loglog([r["wall_s"] for r in sel], [max(r["error"], 1e-16) for r in sel], style, marker="o", label=method)
        ax.set_xlabel("wall time per solve [s] (compile excluded)")
        ax.set_ylabel("max error of frame and centreline at s = L")
        ax.set_title(name)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def saved_points(problem, count, repeats):
    """The cost of saving: `solve_static` at its defaults saving the frame, centreline and
    wrench at `count` evenly spaced points (the continuous extension of the Lie-group
    steps) against saving at the end only, and scipy DOP853 (tol 1e-10) with and without
    `t_eval` (its dense output); errors at the saved points against a DOP853 reference
    at tol 1e-14.  CPU times: the best of `repeats` calls, in four rounds alternating the
    two."""
    length, rod = problem["length"], problem.get("rod", ROD)
    rhs = scipy_rhs(rod)
    ts = np.linspace(0.0, length, count)
    y0 = np.concatenate([problem["n0"], problem["m0"], problem["frame0"].ravel(), problem["x0"]])
    ref = solve_ivp(rhs, (0.0, length), y0, method="DOP853", rtol=1e-14, atol=1e-14, t_eval=ts).y.T
    args = [jnp.asarray(problem[k]) for k in ("n0", "m0", "frame0", "x0")]
    out, runs = {}, {}
    for label, saveat in (("end", None), ("saved", jnp.asarray(ts))):

        @jax.jit
        def run(n0, m0, frame0, x0, saveat=saveat):
            sol = hr.solve_static(rod, n0, m0, length, frame0=frame0, x0=x0, saveat=saveat,
                                  outputs=("wrench", "frame", "centreline"))
            return sol.n, sol.frame, sol.x

        n, frame, x = run(*args)
        rows = ref if saveat is not None else ref[-1:]
        err = float(max(np.abs(np.asarray(n) - rows[:, :3]).max(), np.abs(np.asarray(frame).reshape(-1, 9) - rows[:, 6:15]).max(),
                        np.abs(np.asarray(x) - rows[:, 15:]).max()))
        out[label], runs[label] = dict(cpu_s=np.inf, wall_s=np.inf, error=err), run
    # The two in alternating rounds (the machine's noise, tens of microseconds here, then
    # falls on both alike), the best of each.
    for _ in range(4):
        for label, run in runs.items():
            out[label]["cpu_s"] = min(out[label]["cpu_s"], best_cpu_time(lambda run=run: run(*args), repeats))
            out[label]["wall_s"] = min(out[label]["wall_s"], best_time(lambda run=run: run(*args), repeats))
    for label, t_eval in (("scipy_end", None), ("scipy_saved", ts)):
        solve = lambda t_eval=t_eval: solve_ivp(rhs, (0.0, length), y0, method="DOP853", rtol=1e-10, atol=1e-10, t_eval=t_eval).y  # noqa: E731
        y = solve().T
        rows = ref if t_eval is not None else ref[-1:]
        err = float(max(np.abs(y[-rows.shape[0]:, :3] - rows[:, :3]).max(), np.abs(y[-rows.shape[0]:, 6:] - rows[:, 6:]).max()))
        out[label] = dict(cpu_s=best_cpu_time(solve, max(1, repeats // 3)), error=err)
    out.update(count=count, saved_over_end=out["saved"]["cpu_s"] / out["end"]["cpu_s"],
               scipy_saved_over_end=out["scipy_saved"]["cpu_s"] / out["scipy_end"]["cpu_s"],
               speedup_vs_scipy=out["scipy_saved"]["cpu_s"] / out["saved"]["cpu_s"])
    print(f"  {count} saved points: {out['saved']['cpu_s'] * 1e3:.3f} ms (err {out['saved']['error']:.1e}) against "
          f"{out['end']['cpu_s'] * 1e3:.3f} ms at the end only (err {out['end']['error']:.1e}): {out['saved_over_end']:.2f}x; "
          f"scipy DOP853 {out['scipy_saved']['cpu_s'] * 1e3:.1f} ms (err {out['scipy_saved']['error']:.1e}), "
          f"{out['scipy_saved_over_end']:.2f}x its end-only solve; helixrod {out['speedup_vs_scipy']:.0f}x faster")
    return out


def planar_elastica():
    """A planar elastica (bending about d2 only, force in the d1-d3 plane), L = 5."""
    rod = hr.Rod(1.0, 1.5, 0.8)
    return dict(name="planar elastica, L = 5", rod=rod, n0=np.array([0.5, 0.0, -1.0]), m0=np.array([0.0, 0.8, 0.0]),
                frame0=np.eye(3), x0=np.zeros(3), length=5.0)


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="fewer tolerances, solvers and batch members")
    parser.add_argument("--saved-only", action="store_true", help="only the saved-point rows")
    parser.add_argument("--one-core", action="store_true", help="pin the process to one core")
    args = parser.parse_args()
    if args.one_core:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    if args.saved_only:
        saves = {}
        for problem in (problems()[1], planar_elastica()):
            print(f"saved points ({problem['name']})")
            saves[problem["name"]] = saved_points(problem, 201, 20 if args.quick else 50)
        RESULTS.mkdir(exist_ok=True)
        path = RESULTS / f"bench_kirchhoff_saved{'_one_core' if args.one_core else ''}.json"
        path.write_text(json.dumps(dict(device=str(jax.devices()[0]), machine=dict(cpu=cpu_model(), cpus=os.cpu_count()),
                                        one_core=args.one_core, saved=saves), indent=1))
        print(f"saved {path}")
        return
    repeats = 2 if args.quick else 5
    tols = [1e-6, 1e-8, 1e-10, 1e-12] if args.quick else [1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12]
    solvers = {DEFAULT: hr.MuntheKaasRK(diffrax.Dopri8()), "CF4": hr.CommutatorFreeRK4(), "Tsit5": diffrax.Tsit5(),
               "Dopri5": diffrax.Dopri5(), "Dopri8": diffrax.Dopri8()}
    if not args.quick:
        solvers["Kvaerno5"] = diffrax.Kvaerno5()
    scipy_methods = ["DOP853", "RK45", "LSODA"]
    results, headlines = {}, {}
    for problem in problems():
        print(problem["name"])
        rows = diffrax_runs(problem, solvers, tols, repeats)
        rows += scipy_runs(problem, scipy_methods, tols, 1 if args.quick else 3)
        results[problem["name"]] = rows
        headlines[problem["name"]] = headline(rows)
        h = headlines[problem["name"]]
        if h and h["default"]:
            print(f"  headline: scipy DOP853 tol 1e-10 err {h['dop853']['error']:.1e} in {h['dop853']['wall_s'] * 1e3:.1f} ms; "
                  f"default solve_static (tol {h['default']['tol']:.0e}) err {h['default']['error']:.1e} in "
                  f"{h['default']['wall_s'] * 1e3:.2f} ms: {h['speedup']:.0f}x faster, error "
                  f"{'no worse' if h['default_error_no_worse'] else 'WORSE'}")
        if h and h["fastest_diffrax"]:
            f = h["fastest_diffrax"]
            print(f"  fastest diffrax run at that error: {f['run']['method']} tol {f['run']['tol']:.0e}, "
                  f"{f['run']['wall_s'] * 1e3:.2f} ms: {f['speedup']:.0f}x faster")
    saves = {}
    for problem in (problems()[1], planar_elastica()):
        print(f"saved points ({problem['name']})")
        saves[problem["name"]] = saved_points(problem, 201, 20 if args.quick else 50)
    print("batched (non-helical, L = 20)")
    batch = batched(problems()[1], 200 if args.quick else 1000, repeats, 1e-8)
    RESULTS.mkdir(exist_ok=True)
    payload = dict(device=str(jax.devices()[0]), machine=dict(cpu=cpu_model(), cpus=os.cpu_count()), quick=args.quick, results=results, headline=headlines, batched=batch, saved=saves,
                   note="2 shared CPU cores: timings are noisy and pessimistic")
    (RESULTS / "bench_kirchhoff.json").write_text(json.dumps(payload, indent=1))
    plot(results, RESULTS / "bench_kirchhoff.png")
    print(f"saved {RESULTS / 'bench_kirchhoff.json'} and .png")


if __name__ == "__main__":
    main()
