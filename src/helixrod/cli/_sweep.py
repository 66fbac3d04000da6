"""``helixrod sweep``: the kappa-tau plane of a rod (registers, stability, wrench)."""

from __future__ import annotations

import time
from pathlib import Path

import jax
import numpy as np
import typer

from .. import save_sweep, sweep
from .._plot import SUMMARY_FIELDS
from ..plot import plot_sweep_summary
from ._console import command_console
from ._numbers import grid, rod_option
from ._paths import output_file


def sweep_command(
    rod: str = typer.Option("1,1.5,0.8,0.5,0.5", help="K1,K2,K3[,K13,K23]"),
    uhat: str = typer.Option("1,0,0", help="intrinsic twist u1,u2,u3"),
    kappa: str = typer.Option("0:3:1000", help="curvature axis start:stop:num"),
    tau: str = typer.Option("-3:3:1000", help="torsion axis start:stop:num (write --tau=-3:3:1000)"),
    fields: str = typer.Option("force,moment,stable,count", help="comma-separated sweep fields"),
    out: Path | None = typer.Option(None, help="write the result to this .npz (load_sweep reads it)"),
    plot: Path | None = typer.Option(None, help="write the atlas figure (PNG/PDF/SVG)"),
    chunk_size: int | None = typer.Option(None, help="points per chunk (default 65536 per device)"),
    progress: bool | None = typer.Option(
        None, "--progress/--no-progress", metavar="", help="progress bar (default: on a terminal)"
    ),
) -> None:
    """Sweep the kappa-tau plane: registers, stability and wrench of every uniform helix."""
    console = command_console()
    the_rod = rod_option(rod, uhat)
    output_file(out, "--out")
    output_file(plot, "--plot", figure=True)
    names = tuple(f.strip() for f in fields.split(",") if f.strip())
    if plot is not None:
        names += tuple(f for f in SUMMARY_FIELDS if f not in names)
    k_axis, t_axis = grid(kappa, "--kappa"), grid(tau, "--tau")
    start = time.perf_counter()
    try:
        result = sweep(the_rod, k_axis, t_axis, fields=names, chunk_size=chunk_size, progress=progress)
    except ValueError as error:
        raise typer.BadParameter(str(error)) from None
    except MemoryError as error:
        hint = " or ask for fewer fields (--fields count stores one byte per helix)" if names != ("count",) else ""
        raise typer.BadParameter(
            f"the {k_axis.size} x {t_axis.size} grid does not fit in memory ({error}); use a coarser grid{hint}"
        ) from None
    seconds = time.perf_counter() - start
    points = k_axis.size * t_axis.size
    console.print(
        f"swept {points} helices in {seconds:.2f} s ({points / seconds:.3g} points/s, compile included) "
        f"on {len(jax.local_devices())} device(s)"
    )
    if "count" in result:
        values, counts = np.unique(result["count"], return_counts=True)
        console.print("registers per helix: " + ", ".join(f"{v}: {c / points:.1%}" for v, c in zip(values, counts)))
    if out is not None:
        save_sweep(out, result)
        console.print(f"wrote {out}")
    if plot is not None:
        plot_sweep_summary(result, plot)
        console.print(f"wrote {plot}")
