"""``helixrod tweezer-fit``: the rod's stiffness and the molecule's persistence lengths from
tweezer curves (a `TweezerData` CSV file)."""

from __future__ import annotations

import math
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import typer
from rich.markup import escape
from rich.table import Table

from .. import dna, fit_stiffness, profile_likelihood
from ..plot import plot_tweezer_fit
from ._console import command_console
from ._numbers import assignments
from ._paths import input_file, output_file, read_with_notes
from ._report import chi2_warning

_UNITS = {"K": "pN nm^2", "uhat": "1/nm", "persistence_length": "nm", "plectoneme_twist_persistence": "nm", "offset_": "nm"}


def _unit(name: str) -> str:
    return next((unit for prefix, unit in _UNITS.items() if name.startswith(prefix)), "")


def default_fix() -> dict[str, float]:
    """What ``helixrod tweezer-fit`` holds fixed by default: K1 at the bundled example rod's
    (`dna.load_tweezer_example().rod`) and K13 = 0.  Tweezer curves see the rod through its
    response to an axial force and torque, which leaves K1 and K13 open (the register stays
    at phi = 0 for K13 = 0; see `helixrod demo`)."""
    return {"K1": float(dna.load_tweezer_example().rod.K1), "K13": 0.0}


class FixError(ValueError):
    """A bad ``--fix`` specification (the message names the entry)."""


def parse_fix(text: str | None) -> dict[str, float]:
    """The ``--fix`` option: comma-separated ``NAME=VALUE`` entries (``K1=1327.3,K13=0``,
    model parameters too: ``persistence_length=50``); ``none`` fixes nothing; `None` (the
    option not given) is `default_fix()`."""
    if text is None:
        return default_fix()
    if text.strip().lower() == "none":
        return {}
    try:
        return assignments([text], "--fix")
    except typer.BadParameter as error:
        raise FixError(error.message) from None


def fitted_moduli(fit) -> dict[str, tuple[float, float]]:
    """`dna.effective_moduli(fit.rod, fit.rod.uhat)` -- S (pN), C (pN nm^2), g (pN nm) at zero
    load -- with standard errors propagated from the fit's covariance (`StiffnessFit.propagate`),
    by name."""
    values, stderr = fit.propagate(lambda rod, _: jnp.stack(dna.effective_moduli(rod, rod.uhat, throw=False)))
    return {name: (float(v), float(e)) for name, v, e in zip(("S", "C", "g"), np.asarray(values), np.asarray(stderr))}


def fit_tweezer_data(data, fixed: dict[str, float], fit_offsets: bool = True, progress: bool | None = None):
    """The fit of ``helixrod tweezer-fit`` (and of the demo): `fit_stiffness` of the
    `TweezerData` with uhat the B-DNA backbone helix of the bundled example rod, that rod as
    the start, `fixed` held fixed (see `default_fix`) and one bead offset per molecule if
    `fit_offsets`; `progress` as `fit_stiffness`'s."""
    rod = dna.load_tweezer_example().rod
    return fit_stiffness(data, uhat=rod.uhat, init=rod, fix=fixed or None, fit_offsets=fit_offsets, progress=progress)


def print_tweezer_fit(console, fit, data, fixed: dict[str, float]) -> dict[str, tuple[float, float]]:
    """Rich tables of a tweezer `StiffnessFit`: the parameters with standard errors and units
    (the fixed ones too), the fit's quality and convergence, and the zero-load moduli S, C, g
    of the fitted rod.  Returns the moduli (value, stderr) by name."""
    table = Table(title=f"tweezer fit ({fit.method}): reduced chi2 = {float(fit.chi2_reduced):.4g}")
    for col in ("parameter", "value", "stderr", "unit"):
        table.add_column(col, justify="right")
    for name in fit.names:
        v, e = float(fit.params[name]), float(fit.stderr[name])
        table.add_row(name, f"{v:.6g}", f"{e:.3g}", _unit(name))
    for name, value in fixed.items():
        table.add_row(name, f"{value:.6g}", "fixed", _unit(name))
    console.print(table)
    m = int(np.asarray(fit.residuals).shape[0])
    console.print(
        f"cost {float(fit.cost):.6g}, reduced chi2 {float(fit.chi2_reduced):.4g} ({m} residuals, {len(fit.names)} "
        f"free parameters); converged: {fit.ok} ({escape(fit.message)}, {fit.n_steps} steps)",
        soft_wrap=True,
    )
    warning = chi2_warning(fit)
    if warning:
        console.print(f"[yellow]{escape(warning)}[/yellow]", soft_wrap=True)
    for w, e in zip(fit.identifiability.weak, fit.identifiability.weak_stderr):
        combo = " ".join(f"{c:+.3f}*{n}" for n, c in w)
        console.print(f"weakly determined: {combo}  (scaled stderr {e:.3g})", soft_wrap=True)
    moduli = fitted_moduli(fit)
    kT = float(dna.kT(data.temperature))
    mod = Table(title="moduli of the fitted rod at zero load (dna.effective_moduli)")
    for col in ("modulus", "value", "stderr", "unit"):
        mod.add_column(col, justify="right")
    for name, unit, meaning in (("S", "pN", "stretch"), ("C", "pN nm^2", "twist"), ("g", "pN nm", "twist-stretch")):
        v, e = moduli[name]
        mod.add_row(f"{name} ({meaning})", f"{v:.5g}", f"{e:.3g}", unit)
    C, eC = moduli["C"]
    mod.add_row("C/kT (twist persistence)", f"{C / kT:.4g}", f"{eC / kT:.3g}", "nm")
    console.print(mod)
    return moduli


def print_profiles(console, fit, profiles) -> None:
    """A rich table of profile-likelihood intervals beside the normal-approximation ones."""
    table = Table(title="95 % intervals: profile likelihood and value +- 1.96 stderr")
    for col in ("parameter", "value", "profile lower", "profile upper", "normal lower", "normal upper", "unit"):
        table.add_column(col, justify="right")
    normal = fit.interval(0.95)
    for name, p in profiles.items():
        lo, hi = p.interval
        table.add_row(name, f"{float(fit.params[name]):.6g}", f"{lo:.6g}", f"{hi:.6g}", f"{normal[name][0]:.6g}",
                      f"{normal[name][1]:.6g}", _unit(name))
    console.print(table)


def _fail(console, message: str):
    console.print(f"[red]error:[/red] {escape(message)}", soft_wrap=True)
    raise typer.Exit(code=2)


def tweezer_fit_command(
    data: Path = typer.Argument(..., help="tweezer data, CSV with a units line (see helixrod.dna.TweezerData.from_csv)"),
    n_bp: float = typer.Option(None, "--n-bp", help="base pairs of every molecule (overrides the file's n_bp column)"),
    fix: str = typer.Option(
        None,
        help="parameters held fixed, NAME=VALUE,... (rod K1 K2 K3 K13 K23 in pN nm^2; persistence_length, "
        "plectoneme_twist_persistence, offset_<molecule> in nm), or 'none'. Default: K1 fixed at the bundled "
        "example rod's K1 and K13=0, since tweezer curves do not determine all five stiffnesses; a --fix "
        "replaces this default (repeat K1=...,K13=0 to keep them)",
    ),
    fit_offsets: bool = typer.Option(True, "--fit-offsets/--no-fit-offsets", metavar="", help="fit one bead-height offset per molecule"),
    profile: list[str] = typer.Option(
        None,
        help="a free parameter whose 95 % profile-likelihood interval to print (repeatable; refits with it held "
        "at 21 values over +-4 stderr; see helixrod.profile_likelihood)",
    ),
    plot: Path = typer.Option(None, help="write the figure (plot.plot_tweezer_fit; PNG/PDF/SVG by suffix)"),
    out: Path = typer.Option(None, help="write the fit as JSON"),
    strict: bool = typer.Option(False, "--strict", metavar="", help="an unknown CSV column is an error (default: ignored with a note)"),
    progress: bool | None = typer.Option(
        None, "--progress/--no-progress", metavar="", help="progress bar (default: on a terminal)"
    ),
) -> None:
    """Fit the rod's stiffness (K2, K3, K23 by default), the bending persistence and the
    plectoneme twist persistence (and bead offsets) to tweezer curves: force-extension
    curves, hat curves, measured torques.  uhat is the B-DNA backbone helix and the start the
    rod of the bundled example (dna.load_tweezer_example).  Prints the parameters with
    standard errors and the zero-load moduli S, C, g of the fitted rod."""
    console = command_console()
    try:
        fixed = parse_fix(fix)
    except FixError as error:
        _fail(console, str(error))
    for name in profile or ():
        if name in fixed:
            _fail(console, f"--profile {name}: that parameter is held fixed (--fix); profile a free one")
        if name in ("uhat1", "uhat2", "uhat3"):
            _fail(console, f"--profile {name}: uhat is held at the B-DNA helix; profile a free parameter")
    if n_bp is not None and not (math.isfinite(n_bp) and n_bp > 0):
        _fail(console, f"--n-bp must be a positive number of base pairs, got {n_bp:g}")
    try:
        input_file(data, "DATA")
        output_file(out, "--out")
        output_file(plot, "--plot", figure=True)
    except typer.BadParameter as error:
        _fail(console, error.message)
    try:
        observations = read_with_notes(console, lambda: dna.TweezerData.from_csv(data, n_bp=n_bp, strict=strict))
    except (OSError, UnicodeDecodeError) as error:
        _fail(console, f"cannot read {data}: {error}")
    except ValueError as error:
        _fail(console, str(error))
    try:
        fit = fit_tweezer_data(observations, fixed, fit_offsets, progress)
    except ValueError as error:
        _fail(console, str(error))
    by_torque = np.asarray(observations.torque_controlled)
    console.print(
        f"{observations.n_points} points of {observations.n_molecules} "
        f"molecule{'s' if observations.n_molecules != 1 else ''} from {escape(str(data))}: "
        f"{int(by_torque.sum())} torque-controlled, {int((~by_torque).sum())} turns-controlled, "
        f"{int(np.asarray(observations.has_measured_torque).sum())} with a measured torque; "
        f"{float(observations.temperature):.2f} K",
        soft_wrap=True,
    )
    moduli = print_tweezer_fit(console, fit, observations, fixed)
    # Which parameters are free is known after the fit (its molecules' offsets): an unknown
    # name fails after the results that need no profile are written, not before.
    unknown = [name for name in profile or () if name not in fit.names]
    profiles = {name: profile_likelihood(fit, name) for name in profile or () if name in fit.names}
    if profiles:
        print_profiles(console, fit, profiles)
    if out is not None:
        fit.save(out, {
            "moduli": {name: {"value": v, "stderr": e} for name, (v, e) in moduli.items()},
            "profile_intervals": {name: [float(x) for x in p.interval] for name, p in profiles.items()},
            "fixed": fixed,
            "data": str(data),
        })
        console.print(f"wrote {escape(str(out))}")
    if plot is not None:
        plot_tweezer_fit(fit, observations, plot)
        console.print(f"wrote {escape(str(plot))}")
    if unknown:
        _fail(console, f"--profile {', '.join(unknown)}: not a free parameter of the fit; free: {', '.join(fit.names)}")
