"""Benchmark: helixrod's tweezer fits, and side by side with lumicks pylake on force-distance data.

Data (synthetic, from `dna.load_tweezer_example().rod`, the truth): 10 molecules of n_bp
~ 7600-8400 (drawn per molecule), bending persistence 48 nm, plectoneme twist persistence
24 nm, each with a bead-height offset (uniform in +-5 nm) and Gaussian extension noise
(sigma 3 nm).  Per molecule 200 points: a force-distance curve at zero torque (a free
swivel, as in optical tweezers: 40 forces log-spaced over 0.1-10 pN and 40 evenly spaced
over 10-40 pN) and hat curves at 0.5, 1 and 2 pN (40 turns each, -30..30).

1. **Global fit** of all 2000 points: `fit_stiffness(data, uhat=rod.uhat, init=rod,
   fix={"K1": rod.K1, "K13": 0}, fit_offsets=True)` -- K2, K3, K23, persistence length,
   plectoneme twist persistence and one offset per molecule.  First call (tracing and
   compilation included) and later calls (best of a few) timed apart; the fitted values
   against the truth in units of their standard errors; reduced chi2.
2. **Force-distance curves, side by side with pylake** (`lumicks.pylake.FdFit`, its default
   solver: scipy least_squares trf with its analytic Jacobian), on identical arrays (pylake
   in micrometres) and the same kT: `ewlc_odijk_distance` (Lp, Lc, St free) on 10-30 pN
   (where its docstring says the model holds) and on the whole range, and `twlc_distance`
   (C = 440 pN nm^2 and Fc = 30.6 pN fixed, started from the Odijk fit of the same points,
   as in pylake's tWLC tutorial) on the whole range.  helixrod on the whole range: K2, the
   persistence length and the offset free, K3 and K23 fixed at the example rod (zero-torque
   data see only the stretch modulus S - g^2/C, so this is the counterpart of pylake's fixed
   C; the plectoneme parameter, which pylake does not have, is fixed too) -- 3 parameters per
   molecule like Odijk's; in full runs also with K2, K3, K23 all free (`helixrod_rod_free`,
   the degenerate directions in its identifiability report).  One molecule, and the 10
   molecules as one global fit (pylake: one FdFit, one data set per molecule with its own
   Lc, which absorbs the offset; helixrod: n_bp known, one offset per molecule).  chi2 =
   sum of squared residuals over the same sigma (3 nm) for both, also restricted to the
   10-30 pN points; the number of fitted parameters; the persistence length and the stretch
   modulus at zero torque (helixrod: S - g^2/C of the fitted rod by `dna.effective_moduli`;
   pylake: St) against the truth; later-call time ratios.

Usage: python benchmarks/bench_tweezer.py [--quick]
(--quick: one later call per helixrod fit, five per pylake fit, and neither the helixrod
10-molecule force-distance fit nor `helixrod_rod_free`; the compilations dominate.)
Writes benchmarks/results/bench_tweezer.json and .png.  A watchdog fails the run after an
hour: jaxlib 0.10.2's batched LAPACK solves once deadlocked the 2000-point fit on 2 cores
(the per-point model now solves its small systems without LAPACK, `_misc.solve_small`).
Timings on a shared, loaded 2-core machine are pessimistic and noisy.
"""

from __future__ import annotations

import argparse
import faulthandler
import json
import sys
import time
import warnings
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import helixrod as hr
from helixrod import dna

sys.path.insert(0, str(Path(__file__).parent))
from _timing import best_time

ROD = dna.load_tweezer_example().rod
PERSISTENCE = 48.0
PLECTONEME = 24.0
SIGMA = 3.0  # nm
N_MOLECULES = 10
HAT_FORCES = (0.5, 1.0, 2.0)
FD_FORCES = np.concatenate([np.geomspace(0.1, 10.0, 40, endpoint=False), np.linspace(10.0, 40.0, 40)])
HAT_TURNS = np.linspace(-30.0, 30.0, 40)
ODIJK_RANGE = (10.0, 30.0)  # pN, pylake's docstring for ewlc_odijk_distance
KT = float(dna.kT(dna.ROOM_TEMPERATURE))
FIX_ROD = {"K1": float(ROD.K1), "K13": 0.0}
# helixrod's force-distance fits (the plectoneme parameter fixed: no point is turned).  At
# zero torque the data see the rod's stretch modulus S - g^2/C (and its nonlinearity), not
# K2, K3 and K23 apart: "helixrod" fixes the twist-side stiffnesses K3, K23 at the example
# rod, as pylake's tWLC fixes C (3 parameters per molecule, like Odijk's Lp, Lc, St);
# "helixrod_rod_free" (full runs) frees all three and shows the degenerate directions.
FD_VARIANTS = {
    "helixrod": ("K2, persistence, offset free; K3, K23 fixed",
                 dict(FIX_ROD, K3=float(ROD.K3), K23=float(ROD.K23), plectoneme_twist_persistence=PLECTONEME)),
    "helixrod_rod_free": ("K2, K3, K23, persistence, offset free", dict(FIX_ROD, plectoneme_twist_persistence=PLECTONEME)),
}


def stretch_modulus_free_swivel(rod):
    """The zero-load stretch modulus at zero torque, S - g^2/C (what Odijk's St measures)."""
    S, C, g = (float(x) for x in dna.effective_moduli(rod, rod.uhat))
    return S - g * g / C


TRUTH = {
    "K2": float(ROD.K2), "K3": float(ROD.K3), "K23": float(ROD.K23),
    "persistence_length": PERSISTENCE, "plectoneme_twist_persistence": PLECTONEME,
}


def _response(n_bp, force, *, turns=None, torque=None, length):
    """`tweezer_response` padded to `length` points, so that the F-d and the hat calls share
    one compilation (the control kind is an array inside the jitted function)."""
    n = len(force)
    pad = lambda a: np.concatenate([a, np.full(length - n, a[0])])
    control = {"turns": None if turns is None else pad(turns), "torque": None if torque is None else pad(torque)}
    r = dna.tweezer_response(ROD, pad(n_bp), pad(force), persistence_length=PERSISTENCE,
                             plectoneme_twist_persistence=PLECTONEME, **control)
    assert bool(np.all(np.asarray(r.ok)[:n])), "synthetic data outside the model"
    return np.asarray(r.extension)[:n]


def make_data(rng):
    """Per point: force, turns (NaN at torque-controlled points), torque (NaN at turned
    ones), molecule, noise-free and noisy extension, is-F-d flag; per molecule n_bp, offset."""
    m = N_MOLECULES
    n_bp = rng.integers(7600, 8401, m).astype(float)
    offset = rng.uniform(-5.0, 5.0, m)
    n_fd, n_hat = FD_FORCES.size, len(HAT_FORCES) * HAT_TURNS.size
    fd_F = np.tile(FD_FORCES, m)
    hat_F = np.tile(np.repeat(HAT_FORCES, HAT_TURNS.size), m)
    hat_T = np.tile(HAT_TURNS, len(HAT_FORCES) * m)
    length = max(fd_F.size, hat_F.size)
    fd_ext = _response(np.repeat(n_bp, n_fd), fd_F, torque=np.zeros_like(fd_F), length=length)
    hat_ext = _response(np.repeat(n_bp, n_hat), hat_F, turns=hat_T, length=length)
    parts = {"force": [], "turns": [], "torque": [], "molecule": [], "clean": [], "fd": []}
    for i in range(m):
        f, h = slice(i * n_fd, (i + 1) * n_fd), slice(i * n_hat, (i + 1) * n_hat)
        parts["force"] += [fd_F[f], hat_F[h]]
        parts["turns"] += [np.full(n_fd, np.nan), hat_T[h]]
        parts["torque"] += [np.zeros(n_fd), np.full(n_hat, np.nan)]
        parts["molecule"] += [np.full(n_fd + n_hat, i)]
        parts["clean"] += [fd_ext[f] + offset[i], hat_ext[h] + offset[i]]
        parts["fd"] += [np.ones(n_fd, bool), np.zeros(n_hat, bool)]
    d = {k: np.concatenate(v) for k, v in parts.items()}
    d["extension"] = d["clean"] + SIGMA * rng.normal(size=d["clean"].size)
    d["n_bp"], d["offset"] = n_bp, offset
    return d


def tweezer_data(d, select):
    mol = d["molecule"][select]
    ids = [f"m{i}" for i in mol]
    present = np.unique(mol)
    return dna.TweezerData.from_arrays(
        d["force"][select], d["extension"][select], extension_sigma=SIGMA, turns=d["turns"][select],
        torque=d["torque"][select], molecule=ids, n_bp={f"m{i}": d["n_bp"][i] for i in present},
    )


def time_helixrod(data, fix, repeats):
    run = lambda: hr.fit_stiffness(data, uhat=ROD.uhat, init=ROD, fix=fix, fit_offsets=True)
    t0 = time.perf_counter()
    fit = run()
    first = time.perf_counter() - t0
    later = best_time(lambda: (run(), None)[1], repeats)
    return fit, first, later


def helixrod_summary(fit, first, later, repeats, d, select, truth_chi2):
    r = np.asarray(fit.residuals)
    F = d["force"][select]
    in_range = (F >= ODIJK_RANGE[0]) & (F <= ODIJK_RANGE[1])
    params = {k: float(v) for k, v in fit.params.items()}
    stderr = {k: float(v) for k, v in fit.stderr.items()}
    ident = fit.identifiability
    out = {
        "first_s": first, "later_s": later, "compile_s": max(first - later, 0.0), "repeats": repeats,
        "ok": bool(fit.ok), "n_steps": int(fit.n_steps), "n_points": int(r.size), "n_params": len(fit.names),
        "chi2": float(np.sum(r**2)), "chi2_reduced": float(fit.chi2_reduced), "chi2_truth": truth_chi2,
        "chi2_odijk_range": float(np.sum(r[in_range] ** 2)), "n_points_odijk_range": int(in_range.sum()),
        "params": params, "stderr": stderr, "condition_number": float(ident.condition_number),
        "weak": [{"direction": {str(n): float(c) for n, c in w}, "stderr": float(e)}
                 for w, e in zip(ident.weak, ident.weak_stderr)],
    }
    z = {k: (params[k] - v) / stderr[k] for k, v in TRUTH.items() if k in params}
    for i in np.unique(d["molecule"][select]):
        name = f"offset_m{i}"
        if name in params:
            z[name] = (params[name] - d["offset"][i]) / stderr[name]
    out["z"] = z
    out["rel_err"] = {k: abs(params[k] - v) / abs(v) for k, v in TRUTH.items() if k in params}
    out["Lp"] = params["persistence_length"]
    out["S_free"] = stretch_modulus_free_swivel(fit.rod)
    return out


# -- pylake ---------------------------------------------------------------------------------
def pylake_fit(lk, kind, F, ext_nm, mol, n_bp, init=None):
    """One FdFit of `kind` ("odijk" or "twlc"), one data set per molecule (own Lc)."""
    model = lk.ewlc_odijk_distance("DNA") if kind == "odijk" else lk.twlc_distance("DNA")
    fit = lk.FdFit(model)
    molecules = np.unique(mol)
    single = molecules.size == 1
    for i in molecules:
        sel = mol == i
        params = None if single else {"DNA/Lc": f"DNA/Lc_{i}"}
        fit.add_data(f"m{i}", F[sel], ext_nm[sel] * 1e-3, params=params)
    fit["kT"].value = KT
    if init is not None:
        fit.update_params(init)
    else:
        for i in molecules:  # the contour length the experimenter knows, as the start
            fit["DNA/Lc" if single else f"DNA/Lc_{i}"].value = n_bp[i] * 0.34e-3
    if kind == "twlc":
        fit["DNA/C"].value, fit["DNA/C"].fixed = 440.0, True
        fit["DNA/Fc"].value, fit["DNA/Fc"].fixed = 30.6, True
    fit.fit()
    return model, fit


def pylake_prediction(model, fit, F, mol):
    """Predicted extension (nm) of each point from the fitted parameters."""
    out = np.empty(F.size)
    names = fit.params.keys()
    for i in np.unique(mol):
        sel = mol == i
        values = {str(k): float(fit.params[k].value) for k in names}
        if f"DNA/Lc_{i}" in values:
            values["DNA/Lc"] = values[f"DNA/Lc_{i}"]
        out[sel] = np.asarray(model(F[sel], values)) * 1e3
    return out


def time_pylake(lk, kind, F, ext_nm, mol, n_bp, repeats, init=None):
    t0 = time.perf_counter()
    model, fit = pylake_fit(lk, kind, F, ext_nm, mol, n_bp, init)
    first = time.perf_counter() - t0
    later = best_time(lambda: (pylake_fit(lk, kind, F, ext_nm, mol, n_bp, init), None)[1], repeats)
    return model, fit, first, later


def pylake_summary(kind, label, model, fit, first, later, repeats, F, ext_nm, mol, truth_S):
    resid = (pylake_prediction(model, fit, F, mol) - ext_nm) / SIGMA
    in_range = (F >= ODIJK_RANGE[0]) & (F <= ODIJK_RANGE[1])
    p = fit.params
    values = {str(k): float(p[k].value) for k in p}
    stderr = {str(k): (None if p[k].stderr is None else float(p[k].stderr)) for k in p}
    return {
        "model": "ewlc_odijk_distance" if kind == "odijk" else "twlc_distance", "range": label,
        "first_s": first, "later_s": later, "repeats": repeats, "n_points": int(F.size), "n_params": int(np.sum(p.fitted)),
        "chi2": float(np.sum(resid**2)), "chi2_odijk_range": float(np.sum(resid[in_range] ** 2)),
        "n_points_odijk_range": int(in_range.sum()), "params": values, "stderr": stderr,
        "Lp": values["DNA/Lp"], "S_free": values["DNA/St"],
        "Lp_rel_err": abs(values["DNA/Lp"] - PERSISTENCE) / PERSISTENCE, "S_rel_err": abs(values["DNA/St"] - truth_S) / truth_S,
    }


def side_by_side(lk, d, select, repeats, variants, truth_S):
    """helixrod and pylake on the F-d points `select` (torque 0) of one or more molecules."""
    F, ext, mol = d["force"][select], d["extension"][select], d["molecule"][select]
    truth_chi2 = float(np.sum(((d["clean"][select] - ext) / SIGMA) ** 2))
    out = {"molecules": int(np.unique(mol).size), "n_points": int(F.size), "chi2_truth": truth_chi2, "pylake": []}
    odijk = (F >= ODIJK_RANGE[0]) & (F <= ODIJK_RANGE[1])
    everything = np.ones_like(F, bool)
    fits = {}
    for kind, label, mask, init in (("odijk", "10-30 pN", odijk, None), ("odijk", "0.1-40 pN", everything, None),
                                    ("twlc", "0.1-40 pN", everything, "odijk 0.1-40 pN")):
        start = None if init is None else fits[init][1]
        model, fit, first, later = time_pylake(lk, kind, F[mask], ext[mask], mol[mask], d["n_bp"], repeats * 5, start)
        fits[f"{kind} {label}"] = (model, fit)
        row = pylake_summary(kind, label, model, fit, first, later, repeats * 5, F[mask], ext[mask], mol[mask], truth_S)
        if init is not None:
            row["note"] = f"started from the pylake fit '{init}' (not timed)"
        out["pylake"].append(row)
        print(f"  pylake {row['model']:>20} {label:>10}: first {first:.4f} s, later {later:.4f} s, chi2 {row['chi2']:.1f} "
              f"({row['n_points']} points, {row['n_params']} params), Lp {row['Lp']:.2f} nm, St {row['S_free']:.0f} pN")
    for variant in variants:
        label, fix = FD_VARIANTS[variant]
        fit, first, later = time_helixrod(tweezer_data(d, select), fix, repeats)
        h = helixrod_summary(fit, first, later, repeats, d, select, truth_chi2)
        h.update(free=label, range="0.1-40 pN", Lp_rel_err=abs(h["Lp"] - PERSISTENCE) / PERSISTENCE,
                 S_rel_err=abs(h["S_free"] - truth_S) / truth_S)
        h["later_ratio_over_pylake"] = {f"{row['model']} {row['range']}": later / row["later_s"] for row in out["pylake"]}
        out[variant] = h
        print(f"  {variant} ({label}), 0.1-40 pN: first {first:.2f} s, later {later:.3f} s, ok {h['ok']} "
              f"({h['n_steps']} steps), chi2 {h['chi2']:.1f} ({h['n_points']} points, {h['n_params']} params; "
              f"{h['chi2_odijk_range']:.1f} on the {h['n_points_odijk_range']} points at 10-30 pN), Lp {h['Lp']:.2f} nm, "
              f"S - g^2/C {h['S_free']:.0f} pN, K2 {h['params']['K2']:.0f}")
        if variant == "helixrod":
            out["_fits"] = (fit, fits)
    out.setdefault("_fits", (None, fits))
    return out


def plot(path, d, single, single_fit, pylake_fits):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    F, ext, mol = d["force"][single], d["extension"][single], d["molecule"][single]
    clean = d["clean"][single]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    axes[0].errorbar(F, ext, yerr=SIGMA, fmt="o", ms=3, color="k", label="data (molecule 0, torque 0)")
    curves = []
    if single_fit is not None:
        curves.append(("helixrod fit_stiffness, 0.1-40 pN", np.asarray(single_fit.predicted["extension"]), "#0072B2", "-"))
    colours = {"odijk 10-30 pN": ("#D55E00", "--"), "odijk 0.1-40 pN": ("#E69F00", ":"), "twlc 0.1-40 pN": ("#CC79A7", "-.")}
    for key, (model, fit) in pylake_fits.items():
        curves.append((f"pylake {key}" + (" (extrapolated)" if "10-30" in key else ""), pylake_prediction(model, fit, F, mol),
                       *colours[key]))
    for label, pred, colour, style in curves:
        axes[0].plot(F, pred, style, color=colour, label=label)
        axes[1].plot(F, pred - clean, style, color=colour, label=label)
    axes[1].axhline(0.0, color="k", lw=0.5)
    axes[1].axvspan(*ODIJK_RANGE, color="0.9", zorder=0)
    for ax in axes:
        ax.set_xscale("log")
        ax.set_xlabel("force [pN]")
    axes[0].set_ylabel("extension [nm]")
    axes[1].set_ylabel("fit minus noise-free truth [nm]")
    axes[1].set_ylim(-30, 30)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true", help="one later call per fit, no helixrod 10-molecule F-d fit")
    args = parser.parse_args()
    repeats = 1 if args.quick else 3
    start = time.perf_counter()
    faulthandler.dump_traceback_later(3600, exit=True)  # a hang (see the docstring) fails run_all instead of blocking it
    warnings.filterwarnings("ignore", category=DeprecationWarning)
    import lumicks.pylake as lk

    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    d = make_data(rng)
    generate_s = time.perf_counter() - t0
    truth_S = stretch_modulus_free_swivel(ROD)
    print(f"data: {d['force'].size} points, {N_MOLECULES} molecules, n_bp {d['n_bp'].min():.0f}-{d['n_bp'].max():.0f}; "
          f"generated in {generate_s:.1f} s (tweezer_response, compile included)")

    # 1. global fit
    everything = np.ones(d["force"].size, bool)
    data = tweezer_data(d, everything)
    fit, first, later = time_helixrod(data, FIX_ROD, repeats)
    truth_chi2 = float(np.sum(((d["clean"] - d["extension"]) / SIGMA) ** 2))
    glob = helixrod_summary(fit, first, later, repeats, d, everything, truth_chi2)
    glob.update(molecules=N_MOLECULES, points_per_molecule=int(d["force"].size // N_MOLECULES))
    zs = glob["z"]
    off_z = max(abs(v) for k, v in zs.items() if k.startswith("offset_"))
    print(f"global fit, {glob['n_points']} points, {glob['n_params']} params: first {first:.1f} s, later {later:.2f} s, "
          f"ok {glob['ok']}, {glob['n_steps']} steps, reduced chi2 {glob['chi2_reduced']:.3f}")
    for k, value in TRUTH.items():
        print(f"  {k:>30}: {glob['params'][k]:10.3f} +- {glob['stderr'][k]:8.3f} (truth {value:9.3f}, z {zs[k]:+.2f})")
    print(f"  offsets: max |z| {off_z:.2f}")

    # 2. force-distance, side by side
    fd = d["fd"]
    single = fd & (d["molecule"] == 0)
    print(f"force-distance, molecule 0 ({int(single.sum())} points), truth S - g^2/C = {truth_S:.1f} pN:")
    one = side_by_side(lk, d, single, repeats, ["helixrod"] + ([] if args.quick else ["helixrod_rod_free"]), truth_S)
    single_fit, single_pylake = one.pop("_fits")
    print(f"force-distance, {N_MOLECULES} molecules ({int(fd.sum())} points), global:")
    many = side_by_side(lk, d, fd, repeats, [] if args.quick else ["helixrod"], truth_S)
    many.pop("_fits", None)

    out = Path(__file__).resolve().parent / "results"
    out.mkdir(exist_ok=True)
    report = {
        "quick": args.quick,
        "truth": dict(TRUTH, K1=FIX_ROD["K1"], K13=0.0, S_free=truth_S, sigma_nm=SIGMA, kT=KT),
        "design": {"molecules": N_MOLECULES, "fd_forces": FD_FORCES.tolist(), "hat_forces": list(HAT_FORCES),
                   "hat_turns": HAT_TURNS.tolist(), "n_bp": d["n_bp"].tolist(), "offsets_nm": d["offset"].tolist()},
        "generate_s": generate_s,
        "global_fit": glob,
        "fd_single": one,
        "fd_global": many,
    }
    report["elapsed_s"] = time.perf_counter() - start
    (out / "bench_tweezer.json").write_text(json.dumps(report, indent=1))
    plot(out / "bench_tweezer.png", d, single, single_fit, single_pylake)
    print(f"wrote {out / 'bench_tweezer.json'} and .png ({report['elapsed_s']:.0f} s in all)")


if __name__ == "__main__":
    main()
