"""``helixrod stability``: which finite helices, clamped by their own wrench, are stable."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import typer

from ._console import command_console
from ._numbers import grid, rod_option
from ._paths import output_file


def stability_command(
    length: float = typer.Option(..., help="length L of each clamped helix"),
    rod: str = typer.Option("1,1.5,0.8", help="K1,K2,K3[,K13,K23]"),
    uhat: str = typer.Option("0,1,0.3", help="intrinsic twist u1,u2,u3"),
    kappa: str = typer.Option("0.2:2:60", help="curvature axis start:stop:num"),
    tau: str = typer.Option("-1:1:60", help="torsion axis start:stop:num (write --tau=-1:1:60)"),
    critical: bool = typer.Option(True, "--critical/--no-critical", metavar="", help="also find each helix's critical length"),
    max_length: float | None = typer.Option(None, help="longest critical length looked for (default 4 L)"),
    pieces: int = typer.Option(16, help="pieces of each stability test (raise where the wrench is not resolved)"),
    slot: int = typer.Option(0, help="register slot of the figure (0: the global minimum of W on the circle)"),
    out: Path | None = typer.Option(None, help="write the atlas to this .npz (numpy.load reads it)"),
    plot: Path | None = typer.Option(None, help="write the atlas figure (PNG/PDF/SVG)"),
    progress: bool | None = typer.Option(
        None, "--progress/--no-progress", metavar="", help="progress bar (default: on a terminal)"
    ),
) -> None:
    """Stability atlas: each uniform helix of the grid, of length L, clamped at both ends by its own wrench."""
    import jax.numpy as jnp

    from .. import stability_atlas
    from .. import INSTABILITY_TYPES
    from .._misc import write_atomically
    from ..plot import plot_stability_atlas

    console = command_console()
    the_rod = rod_option(rod, uhat)
    output_file(out, "--out")
    output_file(plot, "--plot", figure=True)
    if not 0 <= slot < 4:
        raise typer.BadParameter(f"--slot must be 0, 1, 2 or 3, got {slot}")
    k_axis, t_axis = grid(kappa, "--kappa"), grid(tau, "--tau")
    k_grid, t_grid = jnp.meshgrid(jnp.asarray(k_axis), jnp.asarray(t_axis), indexing="ij")
    start = time.perf_counter()
    try:
        atlas = stability_atlas(
            the_rod, k_grid, t_grid, length, critical_length=critical, max_length=max_length, pieces=pieces, progress=progress
        )
    except ValueError as error:
        raise typer.BadParameter(str(error)) from None
    seconds = time.perf_counter() - start
    valid = np.asarray(atlas.valid)
    index = np.asarray(atlas.instability_index)
    defined = valid & (index >= 0)
    console.print(f"tested {int(valid.sum())} helices (all registers) of length {length:g} in {seconds:.2f} s (compile included)")
    console.print(
        f"stable: {int((defined & (index == 0)).sum())}, unstable: {int((defined & (index > 0)).sum())}, "
        f"not resolved: {int((valid & (index < 0)).sum())}" + (" (raise --pieces)" if (valid & (index < 0)).any() else "")
    )
    if critical:
        kind = np.asarray(atlas.instability_type)
        counts = ", ".join(f"{name}: {int((kind == code).sum())}" for code, name in enumerate(INSTABILITY_TYPES))
        console.print(f"instability at the critical length -- {counts}, not defined: {int((valid & (kind < 0)).sum())}")
    pointwise = np.asarray(atlas.pointwise_stable)
    console.print(
        f"pointwise-stable registers (minimum of W on the circle) unstable as clamped helices: "
        f"{int((defined & pointwise & (index > 0)).sum())} of {int((defined & pointwise).sum())}"
    )
    if out is not None:
        fields = {name: np.asarray(getattr(atlas, name)) for name in ("kappa", "tau", "valid", "pointwise_stable", "instability_index", "stability_margin", "critical_length", "instability_type", "critical_mode")}
        fields.update(length=np.asarray(atlas.length), max_length=np.asarray(atlas.max_length))
        write_atomically(out, lambda file: np.savez(file, **fields))
        console.print(f"wrote {out}")
    if plot is not None:
        plot_stability_atlas(atlas, plot, slot=slot)
        console.print(f"wrote {plot}")
