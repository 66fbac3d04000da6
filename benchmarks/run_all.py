"""Every benchmark in one run, and one summary table of speed *with* the error it was
measured at.

Each benchmark script runs in a fresh process (so that compile times and memory are its
own), writes its JSON and PNG to `benchmarks/results/`, and this script reads the JSON back
and condenses it into rows: the case, helixrod's method, error, run time and compile time,
the peer's (numpy / scipy, run side by side in the same process by the benchmark) and the
ratio of run times.  The rows go to `benchmarks/results/summary.md` (the README's
Performance table) and `summary.json`.

    python benchmarks/run_all.py --quick      # a few minutes on 2 cores
    python benchmarks/run_all.py              # the full sizes
    python benchmarks/run_all.py --only equilibria sweep
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

from _machine import cpu_model

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
BENCHMARKS = ("equilibria", "sweep", "kirchhoff", "fit", "finite", "tweezer", "first_calls")


def run(name: str, quick: bool) -> float:
    script = HERE / f"bench_{name}.py"
    start = time.perf_counter()
    cmd = [sys.executable, str(script)] + (["--quick"] if quick else [])
    print(f"\n=== {' '.join(cmd[1:])}", flush=True)
    subprocess.run(cmd, check=True)
    return time.perf_counter() - start


def _load(name):
    path = RESULTS / f"bench_{name}.json"
    return json.loads(path.read_text()) if path.exists() else None


def _row(benchmark, case, method, error, seconds, compile_s, peer, peer_error, peer_seconds, note=""):
    return dict(benchmark=benchmark, case=case, method=method, error=error, seconds=seconds, compile_s=compile_s,
                peer=peer, peer_error=peer_error, peer_seconds=peer_seconds,
                ratio=None if not (seconds and peer_seconds) else peer_seconds / seconds, note=note)


def rows_equilibria(r):
    acc = r["accuracy"]
    out = []
    for n in sorted({x["points"] for x in r["runs"] if x["method"] == "helixrod"}):
        ours = next(x for x in r["runs"] if x["method"] == "helixrod" and x["points"] == n)
        peer = next(x for x in r["runs"] if x["method"] == "numpy" and x["points"] == n)
        out.append(_row("equilibria", f"{n:.0e} helices, every register + wrench + stability", "helix_equilibria (jit)",
                        acc["helixrod"][0], ours["wall_s"], r["compile_s"][str(n)], "numpy eigvals + Newton",
                        acc["numpy"][0], peer["wall_s"],
                        note=f"CPU-time ratio {peer['cpu_s'] / ours['cpu_s']:.1f}x"))
        hand = next((x for x in r["runs"] if x["method"] == "numba" and x["points"] == n), None)
        if hand is not None:
            agree = r.get("agreement", {}).get(str(n), {})
            out.append(_row("equilibria", f"{n:.0e} helices, every register + wrench + stability", "helix_equilibria (jit)",
                            acc["helixrod"][0], ours["wall_s"], r["compile_s"][str(n)], "numba kernel (hand-written)",
                            acc["numba"][0], hand["wall_s"],
                            note=f"{r.get('cores', '?')} core(s); register counts differ at {agree.get('count_differences', '?')} "
                                 f"points, stability at {agree.get('stable_differences', '?')}"))
    sp = next(x for x in r["runs"] if x["method"] == "scipy")
    n = max(x["points"] for x in r["runs"] if x["method"] == "helixrod")
    ours = next(x for x in r["runs"] if x["method"] == "helixrod" and x["points"] == n)
    out.append(_row("equilibria", "per helix, against scipy point by point", "helix_equilibria (jit)", acc["helixrod"][0],
                    ours["wall_s"] / n, None, "scipy brentq per point", acc["scipy"][0], sp["wall_s"] / sp["points"]))
    return out


def rows_sweep(r):
    acc = r["peer_accuracy"]
    peer = {p["points"]: p for p in r["peer"]}
    out = []
    for run_ in r["runs"]:
        if run_["points"] in peer and run_["fields"] in ("wrench", "count"):
            p = peer[run_["points"]]
            out.append(_row("sweep", f"{run_['points']:.1e}-point grid, fields: {run_['fields']}", "sweep (chunked, sharded)",
                            acc["max_dphi"], run_["seconds"], r["compile_s"].get(run_["fields"]), "numpy peer (all fields)",
                            acc["max_dphi"], p["seconds"], note="error: largest phi difference between the two"))
    if "memory" in r:
        m = r["memory"]
        out.append(_row("sweep", f"{m['points']:.0e}-point count-only sweep, fresh process", "sweep", None, m["seconds"],
                        None, "-", None, None, note=f"peak RSS {m['peak_mb']:.0f} MB (after imports {m['baseline_mb']:.0f} MB)"))
    return out


def rows_kirchhoff(r):
    out = []
    for case, h in r["headline"].items():
        if not h:
            continue
        d, ref = h["default"], h["dop853"]
        if d:
            out.append(_row("kirchhoff", case, f"solve_static defaults ({d['method'].replace(' (default)', '')}, tol {d['tol']:.0e})", d["error"],
                            d["wall_s"], d.get("compile_s"), "scipy DOP853, tol 1e-10", ref["error"], ref["wall_s"]))
        f = h.get("fastest_diffrax")
        if f and (not d or f["run"]["method"] != d["method"] or f["run"]["tol"] != d["tol"]):
            run_ = f["run"]
            out.append(_row("kirchhoff", case, f"{run_['method']}, tol {run_['tol']:.0e}", run_["error"], run_["wall_s"],
                            run_.get("compile_s"), "scipy DOP853, tol 1e-10", ref["error"], ref["wall_s"]))
    for case, sv in (r.get("saved") or {}).items():
        out.append(_row("kirchhoff", f"{case}: {sv['count']} saved points (frame, centreline, wrench)",
                        "solve_static defaults, dense output", sv["saved"]["error"], sv["saved"]["cpu_s"], None,
                        "scipy DOP853, tol 1e-10, t_eval", sv["scipy_saved"]["error"], sv["scipy_saved"]["cpu_s"],
                        note=f"CPU time; {sv['saved_over_end']:.2f}x helixrod's end-only solve "
                             f"(scipy: {sv['scipy_saved_over_end']:.2f}x its own)"))
    b = r.get("batched")
    if b:
        out.append(_row("kirchhoff", f"vmap over {b['count']} initial conditions (per solve)", "solve_static, vmap", None,
                        b["vmap_per_solve_s"], None, "loop of jitted solves", None, b["loop_per_solve_s"],
                        note=f"lock-step overhead {b['lockstep_overhead']:.2f}x steps"))
    return out


def rows_fit(r):
    out = []
    rows = r["rows"]
    for n in sorted({x["n"] for x in rows}):
        ours = [x for x in rows if x["n"] == n and x["solver"] == "helixrod LM, 32 starts"]
        peer = [x for x in rows if x["n"] == n and x["solver"] == "scipy trf, 32 starts"]
        for o in ours:
            p = next((x for x in peer if x["noise"] == o["noise"]), None)
            out.append(_row("fit", f"{n} helices, noise {o['noise']}, 32 starts (cost {o['cost']:.6g})", "fit_stiffness LM",
                            o["err"], o["later_s"], o["first_s"] - o["later_s"], "scipy least_squares trf",
                            None if p is None else p["err"], None if p is None else p["later_s"],
                            note="" if p is None else f"peer cost {p['cost']:.6g}"))
    return out


def rows_fit_problems(r):
    """The random-problems study of bench_fit.py (--problems): the default fit against scipy
    trf with restarts at the peer's best success rate, medians of CPU time per fit."""
    s = r["summary"]
    ours, old = s["helixrod default"], s.get("helixrod n_starts=32")
    peer_name = r["peer_at_best"]
    peer = s[peer_name]
    rates = ", ".join(f"{name.replace('scipy trf, ', 'trf ')} {v['success_rate']:.0%} ({v['median_s'] * 1e3:.3g} ms)"
                      for name, v in s.items() if name.startswith("scipy"))
    note = (f"success (global minimum, cost within 1e-6 of the best found): default {ours['success_rate']:.0%} "
            f"({ours['mean_starts']:.1f} starts on average)"
            + ("" if old is None else f", n_starts=32 {old['success_rate']:.0%} ({old['median_s'] * 1e3:.3g} ms)")
            + f"; scipy {rates}; median CPU time per fit, one core; totals {ours['total_s']:.3g} s vs {peer['total_s']:.3g} s")
    return [_row("fit", f"{r['problems']} random problems, 20-200 helices, 1 % noise, uhat known (default fit)",
                 "fit_stiffness defaults (early stop)", None, ours["median_s"], None,
                 f"{peer_name} (compiled JAX model, jacfwd)", None, peer["median_s"], note=note)]


# scipy tolerances of the finite-rod rows (the JSON and bench_finite.py's output have them all).
FINITE_TABLE_TOLS = (1e-4, 1e-6)


def rows_finite(r):
    res = r.get("results", {})
    cases = {"clamped": ("clamped-clamped spring, 3 turns, 41 points", "solve_boundary_value"),
             "curve": ("50-point force-extension curve", "force_extension (warm starts)")}
    # Rows before the split into the default and the solve alone have no "library".
    variants = {"helixrod": "with its stability test (16 pieces)", "helixrod-solve": "the solve alone (stability_pieces=0)"}
    out = []
    for key, (case, method) in cases.items():
        part = res.get(key)
        for h in (part or {}).get("headline", []):
            if h["scipy_tol"] not in FINITE_TABLE_TOLS:
                continue
            library = h.get("library", "helixrod")
            what = f"{method}, tol {h['helixrod_tol']:.0e}" + (f", {variants[library]}" if "library" in h else "")
            out.append(_row("finite", case, what, h["helixrod_error"], h["helixrod_s"],
                            part.get("compile_s"), f"scipy solve_bvp, tol {h['scipy_tol']:.0e}", h["scipy_error"],
                            h["scipy_s"], note="equal accuracy: the cheapest helixrod run with error <= scipy's"))
    fit = res.get("fit")
    if fit:
        out.append(_row("finite", "shape fit: 5 stiffnesses from 2 noisy centrelines x 25 points", "fit_stiffness (ShapeData)",
                        None, fit["later_s"], fit["first_s"], "-", None, None,
                        note=f"reduced chi2 {fit['chi2_reduced']:.2f}; fit within {max(abs(z) for z in fit['z'].values()):.1f} stderr of the truth"))
    return out


def rows_tweezer(r):
    out = []
    g = r.get("global_fit")
    if g:
        z = g["z"]
        rod_z = max(abs(v) for k, v in z.items() if not k.startswith("offset_"))
        off_z = max((abs(v) for k, v in z.items() if k.startswith("offset_")), default=0.0)
        out.append(_row("tweezer", f"global fit, {g['molecules']} molecules x {g['points_per_molecule']} points "
                        f"(F-d + hats at 0.5/1/2 pN), {g['n_params']} parameters", "fit_stiffness LM (TweezerData)",
                        max(g["rel_err"].values()), g["later_s"], g["compile_s"], "-", None, None,
                        note=f"reduced chi2 {g['chi2_reduced']:.2f}; K2, K3, K23, persistence, plectoneme within "
                        f"{rod_z:.1f} stderr of the truth, offsets within {off_z:.1f}; error: largest relative error of those five"))
    for key, label in (("fd_single", "1 molecule"), ("fd_global", "global")):
        part = r.get(key)
        if not part:
            continue
        peers = part["pylake"] if key == "fd_single" else part["pylake"][:1]  # global: against Odijk at 10-30 pN only
        for variant in ("helixrod", "helixrod_rod_free"):
            h = part.get(variant)
            if not h:
                continue
            case = (f"F-d curve at torque 0, {label}: {part['molecules']} x {part['n_points'] // part['molecules']} points; "
                    f"helixrod free: {h['free']}")
            for p in peers if variant == "helixrod" else peers[:1]:
                note = (f"error: persistence length; chi2 (sigma 3 nm) at 10-30 pN: helixrod {h['chi2_odijk_range']:.0f}, "
                        f"pylake {p['chi2_odijk_range']:.0f} ({h['n_points_odijk_range']} points); pylake over its own "
                        f"{p['n_points']} points {p['chi2']:.0f}, helixrod over {h['n_points']} {h['chi2']:.0f} (truth "
                        f"{part['chi2_truth']:.0f}); stretch modulus at zero torque {h['S_free']:.0f} vs {p['S_free']:.0f} pN "
                        f"(truth {r['truth']['S_free']:.0f})")
                if not h["ok"]:
                    note += f"; helixrod not converged ({h['n_steps']} steps)"
                if h.get("weak"):
                    note += f"; {len(h['weak'])} weak direction(s) reported"
                out.append(_row("tweezer", case, f"fit_stiffness, 0.1-40 pN, {h['n_params']} params", h["Lp_rel_err"],
                                h["later_s"], h["compile_s"], f"pylake FdFit {p['model']}, {p['range']}, {p['n_params']} params",
                                p["Lp_rel_err"], p["later_s"], note=note))
    return out


def _program_sizes() -> dict:
    """`bench_first_calls.py --sizes`: {label: {"commit": ..., "cases": {case: sizes}}}."""
    path = RESULTS / "bench_program_sizes.json"
    return json.loads(path.read_text())["labels"] if path.exists() else {}


def _cold_target(case: str) -> int:
    """Issue 20's target for a case's cold first call: 15 s for the gradient through
    `solve_static` and the shape fit, 5 s for every other entry point."""
    return 15 if case.startswith("jax.grad") or "shape data" in case else 5


def rows_first_calls(r):
    out = []
    sizes = _program_sizes()
    for case, by in r["results"].items():
        ours, warm, default = by["options"], by["warm"], by["xla-default"]
        where = ", one core" if r.get("one_core") else ""
        where += f" of {r['machine']}" if r.get("machine") else ""
        out.append(_row("first calls", f"{case}, fresh process{where}",
                        "first call, helixrod's compiler options, empty cache", None, ours["first_wall_s"], None,
                        "first call, XLA's default options, empty cache", None, default["first_wall_s"],
                        note=f"second process with the cache: {warm['first_wall_s']:.2g} s (target <= 1.5 s; cold <= {_cold_target(case)} s); "
                        f"later calls {1e3 * ours['later_wall_s']:.3g} ms vs {1e3 * default['later_wall_s']:.3g} ms; "
                        f"peak RSS {ours['peak_rss_gb']:.2f} vs {default['peak_rss_gb']:.2f} GB"
                        + (f"; JAX_DISABLE_MOST_OPTIMIZATIONS=1: first call {by['low-opt']['first_wall_s']:.2g} s, "
                           f"later calls {1e3 * by['low-opt']['later_wall_s']:.3g} ms" if "low-opt" in by else "")
                        + "".join(f"; {label} ({entry['commit']}): {c['programs']} programs, {c['hlo_ops']} HLO instructions "
                                  f"({c['hlo_ops_optimized']} after XLA's passes), the largest {c['largest']['hlo_ops']}"
                                  for label, entry in sizes.items() if (c := entry["cases"].get(case)))))
    return out


EXTRACT = {"equilibria": rows_equilibria, "sweep": rows_sweep, "kirchhoff": rows_kirchhoff, "fit": rows_fit, "finite": rows_finite, "tweezer": rows_tweezer, "first_calls": rows_first_calls}


def _fmt(x, kind):
    if x is None:
        return "-"
    if kind == "error":
        return f"{x:.1e}"
    if kind == "time":
        return f"{x * 1e6:.3g} µs" if x < 1e-3 else f"{x * 1e3:.3g} ms" if x < 1 else f"{x:.3g} s"
    if kind == "ratio":
        return f"**{x:.3g}x**"
    return str(x)


#: What the header says of runs whose JSON files do not record their machine (runs before
#: these records; the README's text names the machine of each).
EARLIER_MACHINE = "machines their JSON files do not record"


def run_machine(report) -> str | None:
    """The CPU a benchmark's JSON says it ran on, if it records one."""
    machine = report.get("machine")
    if isinstance(machine, dict):
        return machine.get("cpu")
    if isinstance(machine, str):  # "2 cores (model name)"
        found = re.search(r"\((.*)\)", machine)
        return found.group(1) if found else machine
    return None


def machines_text(machines: dict[str, str | None]) -> str:
    """`machines` (benchmark -> CPU or None) as the header's account of where each ran."""
    by_cpu: dict[str, list[str]] = {}
    for name, cpu in machines.items():
        by_cpu.setdefault(cpu or EARLIER_MACHINE, []).append(name.replace("_", " "))
    return "; ".join(f"{', '.join(names)} on {cpu}" for cpu, names in by_cpu.items())


def markdown(rows, machine):
    lines = [
        f"Measured by `benchmarks/run_all.py` on {machine}. Times are wall clock of later calls (compiled); "
        "compile time apart; the peer ran side by side in the same process. Errors: against the exact or "
        "high-precision reference of each benchmark (see its script).",
        "",
        "| benchmark | case | helixrod | error | time | compile | peer | peer error | peer time | speed-up | note |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for x in rows:
        lines.append(
            f"| {x['benchmark']} | {x['case']} | {x['method']} | {_fmt(x['error'], 'error')} | {_fmt(x['seconds'], 'time')} | "
            f"{_fmt(x['compile_s'], 'time')} | {x['peer']} | {_fmt(x['peer_error'], 'error')} | "
            f"{_fmt(x['peer_seconds'], 'time')} | {_fmt(x['ratio'], 'ratio')} | {x['note']} |"
        )
    return "\n".join(lines) + "\n"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes: a few minutes on 2 cores")
    parser.add_argument("--only", nargs="*", choices=BENCHMARKS, help="run only these (the summary uses every JSON present)")
    parser.add_argument("--summary-only", action="store_true", help="do not run anything: summarise the JSON files present")
    opts = parser.parse_args()
    elapsed = {}
    if not opts.summary_only:
        for name in opts.only or BENCHMARKS:
            if (HERE / f"bench_{name}.py").exists():
                elapsed[name] = run(name, opts.quick)
    rows, machines = [], {}
    for name in BENCHMARKS:
        report = _load(name)
        if report is not None:
            rows += EXTRACT[name](report)
            machines[name] = run_machine(report)
        if name == "fit" and (RESULTS / "bench_fit_problems.json").exists():
            rows += rows_fit_problems(json.loads((RESULTS / "bench_fit_problems.json").read_text()))
    machine = f"{os.cpu_count()} CPU cores, float64, {platform.system()} ({machines_text(machines)}; summarised on {cpu_model()})"
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "summary.json").write_text(json.dumps(dict(machine=machine, quick=opts.quick, elapsed_s=elapsed, rows=rows), indent=1))
    table = markdown(rows, machine)
    (RESULTS / "summary.md").write_text(table)
    print("\n" + table)
    if elapsed:
        print("benchmark wall times: " + ", ".join(f"{k} {v:.0f} s" for k, v in elapsed.items()))


if __name__ == "__main__":
    main()
