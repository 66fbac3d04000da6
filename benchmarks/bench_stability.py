"""Stability of finite rods: what the conjugate-point test costs a solve, how accurately its
margin locates critical loads, and the stability atlas of clamped helices against an
independent brute-force discrete second variation.

1. The cost of the test: `solve_boundary_value` with the default stability test
   (`stability_pieces=16`) against the plain solve (`stability_pieces=0`), later calls
   (compilation apart) and first calls, on three problems: a cantilever under a side load
   (Rod(1, 1, 0.8), L = 1, Loaded((5, 0, 0))), an Euler column below its critical load
   (Loaded((0, 0, -2)), P_c = pi^2/4) and a helical spring between clamps (Rod(1, 1, 0.77,
   uhat=(0, 1, 0.3)), L = 30, `axial_ends` stretched to 1.05 h0 at its unloaded rotation).
   The target is a ratio of at most 2 (wall time; CPU time, all threads, also shown).  The three problems share one compiled program per
   variant (every end is one uniform `EndCondition`); the caches are cleared before each first
   call, so that each first call includes its compilation.
2. Critical loads: the root of `stability_margin` (scipy brentq over solves from
   `guess="helix"`, which keeps the straight branch) against closed forms, straight rod of
   bending stiffness B = 1, L = 1: clamped-free pi^2 B/(4 L^2), clamped-sliding (Tweezer,
   end frame held) pi^2 B/L^2, and Greenhill's clamped-clamped twisted shaft M_c = 8.98682 B/L
   (the root of tan(t/2) = t/2; Rod(1, 1, 4), so that the end twist M L / C stays below pi).
3. The atlas: `stability_atlas` of Rod(1, 1.5, 0.8, uhat=(0, 1, 0.3)) on a 100 x 100 grid,
   kappa in [0.2, 2], tau in [-1, 1], L = 5, with and without critical lengths; then at
   ~20 sampled (point, slot) pairs with a valid register the brute-force discrete test of
   `tests/discrete_rod.py` (numpy/scipy, n_seg = 30 rigid segments, Newton equilibrium from
   the helix, finite-difference Hessian projected on the end constraint): the index against
   the number of negative eigenvalues, the sign of the margin against that of the smallest
   eigenvalue, the critical length against a bisection of the discrete smallest eigenvalue
   in L (for the samples unstable at L), and the brute-force time per sample, extrapolated
   to the whole grid.  The atlas's default `pieces=16` leaves helices whose wrench it does
   not resolve undefined (index -1); the samples are also tested by an atlas with 64 pieces
   (and at 0.97 L and 1.03 L, to flag a sample that lies next to a conjugate point, where
   the O(h^2) discretisation error of the brute force can move it across).

Run on 2 CPU cores shared with other jobs: timings are noisy and pessimistic.

jaxlib 0.10.2 deadlocked XLA's CPU thread pool on 2 cores (concurrency-optimised thunk
scheduler) when the atlas's batched LAPACK calls shared one program with other loops: a
10 x 10 grid hung in every try.  The atlas now uses no LAPACK call but one eigh per helix
(`_misc.inverse_small`, `determinant_small`) and computes its critical lengths in a program
of their own; this script runs with XLA's default flags (a watchdog still fails a hung run).
It sets OPENBLAS_NUM_THREADS=1 (unless set): jaxlib's LAPACK kernels (scipy's OpenBLAS)
already fan a batch over XLA's pool, and OpenBLAS's own threads, which spin while they wait,
doubled the atlas's CPU time at the same wall time on a quiet machine.  Part 1 reports CPU
time besides wall time: on a loaded machine the wall time of the test's solve swung between
7 and 96 ms.

    python benchmarks/bench_stability.py [--quick]     # --quick: 20 x 20 atlas, 5 samples
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import faulthandler  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import pathlib  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy.linalg  # noqa: E402
import scipy.optimize  # noqa: E402

import helixrod as hr  # noqa: E402
from _timing import best_cpu_time, best_time  # noqa: E402

HERE = pathlib.Path(__file__).parent
RESULTS = HERE / "results"
sys.path.insert(0, str(HERE.parent / "tests"))
from discrete_rod import equilibrium, expm_so3, hat, hessian_eigenvalues  # noqa: E402

ATLAS_ROD = hr.Rod(1.0, 1.5, 0.8, uhat=(0.0, 1.0, 0.3))
ATLAS_LENGTH = 5.0
N_SEG = 30


# -- 1. the cost of the test ------------------------------------------------------------------


def cost_problems():
    straight = hr.Rod(1.0, 1.0, 0.8)
    spring = hr.Rod(1.0, 1.0, 0.77, uhat=(0.0, 1.0, 0.3))
    length = 30.0
    h0, theta0 = (float(a) for a in hr.unloaded_observables(spring, length))
    start, end = hr.axial_ends(spring, length, extension=1.05 * h0, rotation=theta0)
    return {
        "cantilever, side load 5": (straight, 1.0, dict(end=hr.Loaded((5.0, 0.0, 0.0)))),
        "Euler column, P = 2 < P_c": (straight, 1.0, dict(end=hr.Loaded((0.0, 0.0, -2.0)))),
        "spring L = 30, clamps, h = 1.05 h0": (spring, length, dict(start=start, end=end)),
    }


def bench_cost(repeats):
    rows = []
    for name, (rod, length, kwargs) in cost_problems().items():
        row = dict(problem=name)
        for label, pieces in (("plain", 0), ("stability", None)):
            def run(pieces=pieces, rod=rod, length=length, kwargs=kwargs):
                return hr.solve_boundary_value(rod, length, stability_pieces=pieces, **kwargs)

            jax.clear_caches()  # the three problems share one program (one uniform end condition): compile each
            t0 = time.perf_counter()
            sol = jax.block_until_ready(run())
            row[f"{label}_first_s"] = time.perf_counter() - t0
            row[f"{label}_s"] = best_time(lambda: run().force, repeats)
            row[f"{label}_cpu_s"] = best_cpu_time(lambda: run().force, repeats)
            if pieces is None:
                row.update(index=int(sol.instability_index), margin=float(sol.stability_margin),
                           pieces=int(sol.stability_pieces), segments=int(sol.segments))
            row[f"{label}_ok"] = bool(sol.ok)
        row["ratio"] = row["stability_s"] / row["plain_s"]
        row["cpu_ratio"] = row["stability_cpu_s"] / row["plain_cpu_s"]
        rows.append(row)
        print(f"  {name:36s} plain {row['plain_s'] * 1e3:8.2f} ms  with test {row['stability_s'] * 1e3:8.2f} ms  "
              f"ratio {row['ratio']:5.2f} (CPU time {row['cpu_ratio']:5.2f})  "
              f"| first calls {row['plain_first_s']:5.1f} s / {row['stability_first_s']:5.1f} s  "
              f"| index {row['index']}, margin {row['margin']:.3g}, {row['pieces']} pieces, {row['segments']} segments")
    return rows


# -- 2. critical loads ------------------------------------------------------------------------


def bench_critical():
    straight, shaft = hr.Rod(1.0, 1.0, 0.8), hr.Rod(1.0, 1.0, 4.0)
    greenhill = 2 * scipy.optimize.brentq(lambda x: math.tan(x) - x, 4.0, 4.6)
    cases = [
        ("clamped-free, pi^2 B/(4L^2)", straight, lambda P: hr.Loaded((0.0, 0.0, -P)), math.pi**2 / 4),
        ("clamped-sliding, pi^2 B/L^2", straight, lambda P: hr.Tweezer(np.eye(3), (0.0, 0.0, -P)), math.pi**2),
        ("Greenhill, 8.98682 B/L", shaft,
         lambda M: hr.Clamped((0.0, 0.0, 1.0), hr.so3_exp(jnp.array([0.0, 0.0, M / 4.0]))), greenhill),
    ]
    rows = []
    for name, rod, end, exact in cases:
        calls = [0]

        def margin(p, rod=rod, end=end, calls=calls):
            calls[0] += 1
            return float(hr.solve_boundary_value(rod, 1.0, end=end(p), guess="helix", throw=False).stability_margin)

        margin(0.5 * exact)  # compile
        calls[0] = 0
        t0 = time.perf_counter()
        found = scipy.optimize.brentq(margin, 0.8 * exact, 1.2 * exact, xtol=1e-13)
        wall = time.perf_counter() - t0
        err = found / exact - 1
        rows.append(dict(case=name, exact=exact, found=found, rel_error=err, solves=calls[0], wall_s=wall))
        print(f"  {name:30s} exact {exact:.8f}  from the margin {found:.8f}  rel. error {err:+.1e}  "
              f"({calls[0]} solves, {wall:.2f} s)")
    return rows


# -- 3. the atlas against the brute-force discrete rod ------------------------------------------


def helix_end(u, length):
    """End frame and position of the uniform helix of twist u from the origin, identity frame."""
    screw = np.zeros((4, 4))
    screw[:3, :3] = hat(u)
    screw[2, 3] = 1.0
    E = scipy.linalg.expm(screw * length)
    return E[:3, :3], E[:3, 3]


def discrete_test(rod, n, u, length, n_seg=N_SEG):
    """Eigenvalues of the discrete second variation of the helix (body force n, twist u)
    clamped over `length` by its own ends, and the multiplier (lab end force) found."""
    K, uhat = np.asarray(rod.K), np.asarray(rod.uhat)
    h = length / n_seg
    frames = expm_so3(((np.arange(n_seg) + 0.5) * h)[:, None] * u)
    D_L, x_L = helix_end(u, length)
    zero, eye = np.zeros(3), np.eye(3)
    frames, N, _ = equilibrium(K, uhat, length, n_seg, "clamped", zero, eye, end_frame=D_L, end_position=x_L,
                               frames_guess=frames, force_guess=n)
    lam = hessian_eigenvalues(K, uhat, length, n_seg, "clamped", frames, zero, eye, end_frame=D_L, end_position=x_L,
                              multiplier=N)
    return lam, N


def discrete_index(lam):
    return int(np.sum(lam < -1e-8 * np.max(np.abs(lam))))


def discrete_critical_length(rod, n, u, guess):
    """The length where the discrete smallest eigenvalue changes sign, bracketed around `guess`."""
    smallest = lambda L: discrete_test(rod, n, u, L)[0][0]  # noqa: E731
    return scipy.optimize.brentq(smallest, 0.85 * guess, 1.15 * guess, xtol=1e-10)


def atlas_grid(size):
    return jnp.meshgrid(jnp.linspace(0.2, 2.0, size), jnp.linspace(-1.0, 1.0, size), indexing="ij")


def sample_pairs(valid, count, rng):
    """`count` (point, slot) pairs with a valid register, spread evenly over the slots in use."""
    flat = valid.reshape(-1, 4)
    slots = [s for s in range(4) if flat[:, s].any()]
    picks = []
    for j, s in enumerate(slots):
        want = count // len(slots) + (j < count % len(slots))
        points = np.flatnonzero(flat[:, s])
        picks += [(int(p), s) for p in rng.choice(points, size=min(want, points.size), replace=False)]
    return picks


def bench_atlas(size, samples, repeats):
    kappa, tau = atlas_grid(size)
    out = dict(grid=[size, size], length=ATLAS_LENGTH, n_seg=N_SEG)
    atlases = {}
    for label, critical in (("index only", False), ("with critical length", True)):
        def run(critical=critical):
            return hr.stability_atlas(ATLAS_ROD, kappa, tau, ATLAS_LENGTH, critical_length=critical)

        t0 = time.perf_counter()
        atlases[label] = jax.block_until_ready(run())
        first = time.perf_counter() - t0
        wall = best_time(lambda: run().instability_index, repeats)
        out[label] = dict(first_s=first, wall_s=wall, per_point_s=wall / (size * size))
        print(f"  atlas {size} x {size}, {label:22s} first call {first:6.1f} s, later {wall:7.2f} s "
              f"({wall / (size * size) * 1e3:.2f} ms per grid point)")
    atlas = atlases["with critical length"]
    valid, index = np.asarray(atlas.valid), np.asarray(atlas.instability_index)
    margin, critical = np.asarray(atlas.stability_margin), np.asarray(atlas.critical_length)
    assert np.array_equal(index, np.asarray(atlases["index only"].instability_index))
    n_valid = int(valid.sum())
    undefined = [int((valid[..., s] & (index[..., s] < 0)).sum()) for s in range(4)]
    out.update(valid_per_slot=[int(v) for v in valid.reshape(-1, 4).sum(0)], undefined_per_slot=undefined,
               stable=int((valid & (index == 0)).sum()), unstable=int((index > 0).sum()))
    print(f"  valid registers per slot {out['valid_per_slot']}; index undefined (16 pieces do not resolve the wrench) "
          f"per slot {undefined}; stable {out['stable']}, unstable {out['unstable']}")

    # The samples, and a 64-piece atlas of them at L and at L(1 +- 3%).
    eq = hr.helix_equilibria(ATLAS_ROD, kappa, tau)
    picks = sample_pairs(valid, samples, np.random.default_rng(0))
    pk = np.array([np.asarray(kappa).reshape(-1)[p] for p, _ in picks])
    pt = np.array([np.asarray(tau).reshape(-1)[p] for p, _ in picks])
    slot = np.array([s for _, s in picks])
    fine = {f: hr.stability_atlas(ATLAS_ROD, pk, pt, f * ATLAS_LENGTH, critical_length=False, pieces=64)
            for f in (1.0, 0.97, 1.03)}
    fine_index = {f: np.asarray(a.instability_index)[np.arange(len(picks)), slot] for f, a in fine.items()}
    fine_margin = np.asarray(fine[1.0].stability_margin)[np.arange(len(picks)), slot]
    n_all, u_all = np.asarray(eq.n).reshape(-1, 4, 3), np.asarray(eq.u).reshape(-1, 4, 3)
    rows, times, crit_times = [], [], []
    for j, (p, s) in enumerate(picks):
        n, u = n_all[p, s], u_all[p, s]
        i16, m16, lc = int(index.reshape(-1, 4)[p, s]), float(margin.reshape(-1, 4)[p, s]), float(critical.reshape(-1, 4)[p, s])
        i64 = int(fine_index[1.0][j])
        near = not (fine_index[0.97][j] == i64 == fine_index[1.03][j])
        t0 = time.perf_counter()
        try:
            lam, N = discrete_test(ATLAS_ROD, n, u, ATLAS_LENGTH)
            brute, lam0, drift = discrete_index(lam), float(lam[0]), float(np.linalg.norm(N - n) / max(np.linalg.norm(n), 1.0))
        except RuntimeError:
            brute, lam0, drift = None, math.nan, math.nan
        times.append(time.perf_counter() - t0)
        row = dict(kappa=float(pk[j]), tau=float(pt[j]), slot=s, index=i16, index_64=i64, margin=m16,
                   margin_64=float(fine_margin[j]), critical_length=lc,
                   brute_index=brute, brute_smallest=lam0, multiplier_drift=drift, near_conjugate_point=near,
                   brute_s=times[-1])
        if brute is not None and 0 < lc < ATLAS_LENGTH:
            t0 = time.perf_counter()
            try:
                row["brute_critical_length"] = discrete_critical_length(ATLAS_ROD, n, u, lc)
                row["critical_rel_diff"] = row["brute_critical_length"] / lc - 1
            except (RuntimeError, ValueError):
                row["brute_critical_length"] = None
            crit_times.append(time.perf_counter() - t0)
        rows.append(row)
        agree = "" if brute is None else ("=" if brute == (i16 if i16 >= 0 else i64) else "DIFFERS")
        lc_text = f", L_c {lc:.4f} vs brute {row['brute_critical_length']:.4f}" if row.get("brute_critical_length") else ""
        print(f"    kappa {pk[j]:.3f} tau {pt[j]:+.3f} slot {s}: index {i16:2d} (64 pieces {i64}) brute {brute} {agree}"
              f"{' [next to a conjugate point]' if near else ''}; margin {m16:+.3g} (64 pieces {row['margin_64']:+.3g}), "
              f"brute smallest {lam0:+.3g}{lc_text}"
              f"  ({times[-1]:.2f} s)")
    ok = [r for r in rows if r["brute_index"] is not None]
    defined = [r for r in ok if r["index"] >= 0]
    same16 = sum(r["index"] == r["brute_index"] for r in defined)
    same64 = sum(r["index_64"] == r["brute_index"] for r in ok)
    clear = [r for r in ok if not r["near_conjugate_point"]]
    same_clear = sum(r["index_64"] == r["brute_index"] for r in clear)
    signs = sum(np.sign(r["margin"]) == np.sign(r["brute_smallest"]) for r in defined)
    signs64 = sum(np.sign(r["margin_64"]) == np.sign(r["brute_smallest"]) for r in ok)
    crits = [abs(r["critical_rel_diff"]) for r in rows if r.get("critical_rel_diff") is not None]
    t_index = float(np.mean(times))
    out.update(samples=rows, brute_failed=len(rows) - len(ok), index_agree_16=[same16, len(defined)],
               index_agree_64=[same64, len(ok)], index_agree_64_clear=[same_clear, len(clear)],
               margin_sign_agree=[int(signs), len(defined)], margin_sign_agree_64=[int(signs64), len(ok)],
               critical_rel_diff_max=max(crits) if crits else None, brute_index_s=t_index,
               brute_critical_s=float(np.mean(crit_times)) if crit_times else None,
               brute_grid_index_s=t_index * n_valid,
               # the atlas's scheme for a critical length: 64 lengths, 24 bisections
               brute_grid_critical_s=t_index * n_valid * (64 + 24))
    print(f"  index: atlas (16 pieces, where defined) = brute force at {same16}/{len(defined)} samples; 64-piece atlas = "
          f"brute force at {same64}/{len(ok)} ({same_clear}/{len(clear)} away from a conjugate point); "
          f"sign of the margin at {signs}/{len(defined)} (64 pieces: {signs64}/{len(ok)}); "
          f"brute force failed at {len(rows) - len(ok)}")
    if crits:
        print(f"  critical length: largest |relative difference| {max(crits):.1e} over {len(crits)} samples "
              f"(brute force n_seg = {N_SEG}, O(h^2))")
    atlas_s = out["with critical length"]["wall_s"]
    atlas_index_s = out["index only"]["wall_s"]
    print(f"  brute force: {t_index:.3f} s per index ({N_SEG} segments), {out['brute_critical_s'] or math.nan:.2f} s per "
          f"bracketed critical length; for the {n_valid} valid registers of the grid: ~{out['brute_grid_index_s']:.0f} s "
          f"for the indices (atlas {atlas_index_s:.1f} s: {out['brute_grid_index_s'] / atlas_index_s:.0f}x), "
          f"~{out['brute_grid_critical_s']:.0f} s with critical lengths by the atlas's scheme "
          f"(atlas {atlas_s:.1f} s: {out['brute_grid_critical_s'] / atlas_s:.0f}x)")
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="20 x 20 atlas, 5 brute-force samples, fewer repeats")
    parser.add_argument("--repeats", type=int, default=None)
    parser.add_argument("--grid", type=int, default=None, help="atlas grid size (default 100; 20 with --quick)")
    parser.add_argument("--samples", type=int, default=None, help="brute-force samples (default 20; 5 with --quick)")
    args = parser.parse_args()
    faulthandler.dump_traceback_later(3600, exit=True)  # a hang (module docstring) fails the run instead of blocking it
    repeats = args.repeats or (3 if args.quick else 7)
    size = args.grid or (20 if args.quick else 100)
    samples = args.samples or (5 if args.quick else 20)
    start = time.perf_counter()
    results = {}
    print("1. the cost of the stability test of one solve (later calls; first calls incl. compilation)")
    results["cost"] = bench_cost(repeats)
    print("2. critical loads from the root of stability_margin (guess='helix') vs closed forms")
    results["critical"] = bench_critical()
    print(f"3. stability atlas, {size} x {size} (kappa, tau), L = {ATLAS_LENGTH}, vs the brute-force discrete rod")
    results["atlas"] = bench_atlas(size, samples, max(1, min(repeats, 2 if size <= 40 else 1)))
    print("\nsummary")
    print(f"  {'case':46s} {'ratio':>8s}")
    for r in results["cost"]:
        print(f"  {'test/plain solve: ' + r['problem']:46s} {r['ratio']:8.2f}  (CPU time {r['cpu_ratio']:.2f})")
    for r in results["critical"]:
        print(f"  {'critical load rel. error: ' + r['case']:46s} {r['rel_error']:+8.0e}")
    a = results["atlas"]
    print(f"  {'atlas with / without critical length':46s} {a['with critical length']['wall_s'] / a['index only']['wall_s']:8.2f}")
    print(f"  {'brute force / atlas, indices of the grid':46s} {a['brute_grid_index_s'] / a['index only']['wall_s']:8.0f}")
    print(f"  {'brute force / atlas, with critical lengths':46s} {a['brute_grid_critical_s'] / a['with critical length']['wall_s']:8.0f}")
    RESULTS.mkdir(exist_ok=True)
    payload = dict(device=str(jax.devices()[0]), quick=args.quick, results=results, total_s=time.perf_counter() - start,
                   xla_flags=os.environ.get("XLA_FLAGS", ""),
                   note="2 CPU cores shared with other jobs while measured: timings are noisy and pessimistic")
    path = RESULTS / "bench_stability.json"
    path.write_text(json.dumps(payload, indent=1))
    print(f"saved {path} ({payload['total_s']:.0f} s in all)")


if __name__ == "__main__":
    main()
