"""``helixrod force-extension``: a finite rod's force-extension curve against the bulk helix."""

from __future__ import annotations

import math
import time
from pathlib import Path

import jax
import numpy as np
import typer
from rich.table import Table

from .. import RESULTS, force_extension
from .._misc import json_text, write_atomically
from .._status import has_code
from ..plot import plot_response
from ._console import command_console
from ._numbers import grid, rod_option
from ._paths import output_file

#: The curve's fields written by ``--out`` (with the rod's ``length``).
CURVE_FIELDS = ("force", "moment", "extension", "rotation", "bulk_force", "bulk_moment", "bulk_extension", "bulk_rotation", "ok",
                "instability_index", "stability_margin")

#: What a loss of stability means for the points beyond it (`ResponseCurve.critical_kind`).
CRITICAL_MEANING = {
    "fold": "a fold: the branch ends there, and the points beyond have no equilibrium near it",
    "branch point": "a branch point: the branch goes on beyond it, unstable",
}


def force_extension_command(
    rod: str = typer.Option("1,1,0.7692307692", help="K1,K2,K3[,K13,K23]"),
    uhat: str = typer.Option("0,1,0.3", help="intrinsic twist u1,u2,u3 (the unloaded helix)"),
    turns: float = typer.Option(5.0, help="rod length in turns of the unloaded helix"),
    forces: str = typer.Option("0:0.05:21", help="axial forces start:stop:num"),
    moment: float = typer.Option(None, help="hold this axial moment (a spring on hooks)"),
    rotation: float = typer.Option(
        None, help="hold the end rotation, in radians beyond the unloaded one (magnetic tweezer; default 0)"
    ),
    segments: int = typer.Option(1, help="shooting pieces (more for long, stretched rods)"),
    out: Path | None = typer.Option(None, help="write the curve as JSON"),
    plot: Path | None = typer.Option(None, help="write extension against force (finite and bulk) as PNG"),
    progress: bool | None = typer.Option(
        None, "--progress/--no-progress", metavar="", help="progress bar (default: on a terminal)"
    ),
) -> None:
    """Force-extension curve of a finite clamped rod against the uniform-helix (bulk) formula."""
    console = command_console()
    the_rod = rod_option(rod, uhat)
    output_file(out, "--out")
    output_file(plot, "--plot", figure=True)
    u = [float(x) for x in the_rod.uhat]
    norm = math.sqrt(sum(x * x for x in u))
    if norm == 0:
        raise typer.BadParameter("--uhat must not be zero: the length is given in turns of the unloaded helix")
    if not (math.isfinite(turns) and turns > 0):
        raise typer.BadParameter(f"--turns must be finite and > 0, got {turns}")
    if moment is not None and rotation is not None:
        raise typer.BadParameter("give --moment or --rotation, not both")
    length = turns * 2 * math.pi / norm
    force_values = grid(forces, "--forces")
    held = {"moment": moment} if moment is not None else {"rotation": length * norm + (rotation or 0.0)}
    start = time.perf_counter()
    try:
        curve = force_extension(the_rod, length, force_values, segments=segments, progress=progress, **held)
    except ValueError as error:
        raise typer.BadParameter(str(error)) from None
    seconds = time.perf_counter() - start
    name = "moment" if moment is not None else "rotation"
    other = "rotation" if moment is not None else "moment"
    table = Table(title=f"force-extension, L = {length:.4g} ({turns:g} turns), {name} held")
    for col in ("F", "h", "h bulk", "h - h bulk", other, f"{other} bulk", "ok", "stable"):
        table.add_column(col, justify="right")
    index = np.asarray(curve.instability_index)
    for i in range(force_values.size):
        ok = bool(curve.ok[i])
        stable = "-" if not ok or index[i] < 0 else "yes" if index[i] == 0 else f"no ({index[i]})"
        table.add_row(
            f"{float(force_values[i]):.4g}", f"{float(curve.extension[i]):.6g}", f"{float(curve.bulk_extension[i]):.6g}",
            f"{float(curve.extension[i] - curve.bulk_extension[i]):+.3e}", f"{float(getattr(curve, other)[i]):.6g}",
            f"{float(getattr(curve, 'bulk_' + other)[i]):.6g}", "yes" if ok else "no", stable,
        )
    console.print(table)
    critical = float(curve.critical)
    beyond = np.zeros(force_values.size, bool)  # the points past a fold that ends the branch
    if np.isfinite(critical):
        console.print(f"loses stability at F = {critical:.6g}: {CRITICAL_MEANING[curve.critical_kind]}", soft_wrap=True)
        if curve.critical_kind == "fold":
            beyond = (np.asarray(force_values) - critical) * (float(force_values[0]) - critical) < 0
    turned = has_code(curve.result, RESULTS.other_whole_turns)  # converged, to other whole turns
    failed = np.flatnonzero(~np.asarray(curve.ok))
    for i in failed[:10]:  # the requested force, and why its solve failed
        reason = RESULTS[jax.tree.map(lambda code, i=i: code[i], curve.result)]
        what = "holds other whole turns" if turned[i] else "did not converge" + (" (beyond the fold)" if beyond[i] else "")
        console.print(f"F = {float(force_values[i]):.4g} {what}: {reason}", soft_wrap=True)
    if (~turned[failed] & ~beyond[failed]).any():
        console.print(f"a long or stretched rod may need more shooting pieces: try --segments {2 * segments}", soft_wrap=True)
    summary = f"{int((~turned[failed]).sum())} did not converge"
    if turned.any():
        summary += f", {int(turned.sum())} hold other whole turns than the rotation held"
    console.print(f"{force_values.size} points in {seconds:.2f} s (compilation included); {summary}")
    if out is not None:
        fields = {f: np.asarray(getattr(curve, f)).tolist() for f in CURVE_FIELDS}
        text = json_text({"length": length, **fields, "critical_force": critical, "critical_kind": curve.critical_kind})
        write_atomically(out, lambda f: f.write(text), binary=False)
        console.print(f"wrote {out}")
    if plot is not None:
        plot_response(curve, plot)
        console.print(f"wrote {plot}")
