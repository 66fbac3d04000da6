"""Command line: ``helixrod demo`` (more commands arrive with later features)."""

from __future__ import annotations

from pathlib import Path

import typer

app = typer.Typer(add_completion=False, help="helixrod: elastic Kirchhoff rods and helices in JAX.")


@app.callback()
def _main() -> None:
    """helixrod command line."""


@app.command()
def demo(out: Path = typer.Option(Path("helixrod_demo"), help="directory for the figures")) -> None:
    """Equilibria of a coupled, intrinsically curved rod, and a PNG of its helix hyperboloid."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np
    from rich.console import Console
    from rich.table import Table

    from . import Rod, helix_equilibria
    from ._plot import plot_hyperboloid

    console = Console()
    rod = Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
    console.print(
        "Rod: K1 = 1, K2 = 3/2, K3 = 0.8, K13 = K23 = 1/2, uhat = (1, 0, 0) "
        "(the rod of Chouaieb, Goriely & Maddocks, PNAS 2006, fig. 2)"
    )
    points = [(1.0, 1.5), (3.0, 1.5), (1.0, 0.0), (0.5, -1.0)]
    kappa = jnp.array([k for k, _ in points])
    tau = jnp.array([t for _, t in points])
    eq = helix_equilibria(rod, kappa, tau)
    table = Table(title="Uniform helical equilibria")
    for col in ("kappa", "tau", "slot", "phi", "F", "M", "n3", "W", "stable"):
        table.add_column(col, justify="right")
    for i, (k, t) in enumerate(points):
        for s in range(4):
            if bool(eq.valid[i, s]):
                table.add_row(
                    f"{k:g}", f"{t:g}", str(s), f"{float(eq.phi[i, s]):.4f}", f"{float(eq.force[i, s]):+.4f}",
                    f"{float(eq.moment[i, s]):+.4f}", f"{float(eq.tension[i, s]):+.4f}",
                    f"{float(eq.energy[i, s]):.4f}", "yes" if bool(eq.stable[i, s]) else "no",
                )
    console.print(table)
    console.print("F, M: axial force and moment; n3: tension; W: energy density; slot 0 is the global minimum of W on the circle.")
    counts = np.asarray(eq.count)
    console.print(f"registers per helix: {dict(zip([f'{k:g},{t:g}' for k, t in points], counts.tolist()))}")
    out.mkdir(parents=True, exist_ok=True)
    path = plot_hyperboloid(rod, out / "hyperboloid.png", u3_slice=1.5, radii=(1.0, 3.0), extent=4.0)
    console.print(f"wrote {path}")


if __name__ == "__main__":  # pragma: no cover
    app()
