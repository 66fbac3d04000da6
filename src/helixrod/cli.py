"""Command line: ``helixrod demo`` (more commands arrive with later features)."""

from __future__ import annotations

from pathlib import Path

import typer

app = typer.Typer(add_completion=False, help="helixrod: elastic Kirchhoff rods and helices in JAX.")


@app.callback()
def _main() -> None:
    """helixrod command line."""


@app.command()
def demo(
    out: Path = typer.Option(Path("helixrod_demo"), help="directory for the figures"),
    fits: bool = typer.Option(True, "--fits/--no-fits", help="also run the two example fits (about a minute)"),
) -> None:
    """Equilibria of a coupled, intrinsically curved rod (table, helix hyperboloid, kappa-tau
    atlas), then the inverse spring problem on two bundled synthetic datasets: the example
    spring, and DNA under force and torque (what tweezer data determine, and the fit)."""
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
    # -- the kappa-tau atlas (issue 5) --
    from ._plot import plot_rod_atlas

    path = plot_rod_atlas(rod, out / "atlas.png", n=161)
    console.print(f"wrote {path} (equilibria per helix and the stable branch's force and moment over kappa, tau)")
    if fits:
        demo_fit(console, out)
        demo_dna_fit(console, out)


# -- helixrod sweep (issue 5) ---------------------------------------------------------------
def _numbers(text: str, name: str, sizes: tuple[int, ...]) -> list[float]:
    try:
        values = [float(x) for x in text.split(",")]
    except ValueError:
        raise typer.BadParameter(f"{name} must be comma-separated numbers, got {text!r}") from None
    if len(values) not in sizes:
        raise typer.BadParameter(f"{name} takes {' or '.join(map(str, sizes))} numbers, got {len(values)}")
    return values


def _grid_axis(text: str, name: str):
    import numpy as np

    parts = text.split(":")
    try:
        start, stop, num = float(parts[0]), float(parts[1]), int(parts[2])
    except (ValueError, IndexError):
        raise typer.BadParameter(f"{name} must be start:stop:num, e.g. 0:3:1000, got {text!r}") from None
    if len(parts) != 3 or num < 1:
        raise typer.BadParameter(f"{name} must be start:stop:num with num >= 1, got {text!r}")
    return np.linspace(start, stop, num)


@app.command(name="sweep")
def sweep_command(
    rod: str = typer.Option("1,1.5,0.8,0.5,0.5", help="K1,K2,K3[,K13,K23]"),
    uhat: str = typer.Option("1,0,0", help="intrinsic twist u1,u2,u3"),
    kappa: str = typer.Option("0:3:1000", help="curvature axis start:stop:num"),
    tau: str = typer.Option("-3:3:1000", help="torsion axis start:stop:num (write --tau=-3:3:1000)"),
    fields: str = typer.Option("force,moment,stable,count", help="comma-separated sweep fields"),
    out: Path | None = typer.Option(None, help="write the result to this .npz (load_sweep reads it)"),
    plot: Path | None = typer.Option(None, help="write the atlas figure (PNG/PDF/SVG)"),
    chunk_size: int | None = typer.Option(None, help="points per chunk (default 65536 per device)"),
    progress: bool | None = typer.Option(None, "--progress/--no-progress", help="progress bar (default: on a terminal)"),
) -> None:
    """Sweep the kappa-tau plane: registers, stability and wrench of every uniform helix."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import time

    import numpy as np
    from rich.console import Console

    from . import Rod, save_sweep, sweep
    from ._plot import SUMMARY_FIELDS, plot_sweep_summary

    console = Console()
    K = _numbers(rod, "--rod", (3, 5))
    the_rod = Rod(*K, uhat=_numbers(uhat, "--uhat", (3,)))
    names = tuple(f.strip() for f in fields.split(",") if f.strip())
    if plot is not None:
        names += tuple(f for f in SUMMARY_FIELDS if f not in names)
    k_axis, t_axis = _grid_axis(kappa, "--kappa"), _grid_axis(tau, "--tau")
    start = time.perf_counter()
    try:
        result = sweep(the_rod, k_axis, t_axis, fields=names, chunk_size=chunk_size, progress=progress)
    except ValueError as error:
        raise typer.BadParameter(str(error)) from None
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


# -- inverse spring problem (issue 4) ------------------------------------------------------
def _parse_floats(text: str, n: int, what: str):
    try:
        values = [float(x) for x in text.replace(" ", "").split(",")]
    except ValueError:
        raise typer.BadParameter(f"{what} must be {n} comma-separated numbers, got {text!r}") from None
    if len(values) != n:
        raise typer.BadParameter(f"{what} must be {n} comma-separated numbers, got {text!r}")
    return values


def print_fit(console, fit) -> None:
    """Rich tables of a `StiffnessFit`: values with standard errors, correlations, and the
    identifiability report."""
    import numpy as np
    from rich.table import Table

    table = Table(title=f"fit_stiffness ({fit.method}): cost = {float(fit.cost):.6g}, reduced chi2 = {float(fit.chi2_reduced):.4g}")
    for col in ("parameter", "value", "stderr", "relative"):
        table.add_column(col, justify="right")
    for name in fit.names:
        v, e = float(fit.params[name]), float(fit.stderr[name])
        rel = f"{abs(e / v):.2%}" if v != 0 and np.isfinite(e) else "-"
        table.add_row(name, f"{v:.6g}", f"{e:.3g}", rel)
    console.print(table)
    corr = Table(title="correlations")
    corr.add_column("")
    for name in fit.names:
        corr.add_column(name, justify="right")
    c = np.asarray(fit.correlation)
    for i, name in enumerate(fit.names):
        corr.add_row(name, *[("" if j > i else "-" if not np.isfinite(c[i, j]) else f"{c[i, j]:+.2f}") for j in range(len(fit.names))])
    console.print(corr)
    ident = fit.identifiability
    console.print(
        f"converged: {fit.success} ({fit.message}); {fit.n_agree} of {fit.n_starts} starts reached the best "
        f"minimum; scaled-Jacobian singular values {np.array2string(np.asarray(ident.singular_values), precision=3)}, "
        f"condition number {float(ident.condition_number):.3g}, rank {ident.rank}"
    )
    if ident.weak:
        for w, e in zip(ident.weak, ident.weak_stderr):
            combo = " ".join(f"{c:+.3f}*{n}" for n, c in w)
            console.print(f"weakly determined: {combo}  (scaled stderr {e:.3g})")
    else:
        console.print(f"every parameter combination determined to better than {ident.weak_threshold:.0%} (scaled)")
    for s in ident.symmetries:
        console.print(f"symmetry (identical predictions): {s}")
    for note in ident.notes:
        console.print(f"note: {note}")


@app.command()
def fit(
    data: Path = typer.Argument(..., help="CSV file (see helixrod.HelixData.from_csv)"),
    uhat: str = typer.Option(None, help="fixed intrinsic twist 'u1,u2,u3' (default 0,0,0)"),
    fit_uhat: bool = typer.Option(False, "--fit-uhat", help="fit the intrinsic twist too"),
    fix: list[str] = typer.Option([], help="hold a parameter fixed, e.g. --fix K13=0 (repeatable)"),
    branch: str = typer.Option("nearest", help="register rule: nearest, stable or min-energy"),
    method: str = typer.Option("levenberg-marquardt", help="levenberg-marquardt, gauss-newton, lbfgs, adam"),
    n_starts: int = typer.Option(32, help="number of (vmapped) starts"),
    seed: int = typer.Option(0, help="seed of the random starts"),
    relative_sigma: bool = typer.Option(False, "--relative-sigma", help="scale errors by the reduced chi2"),
    out: Path = typer.Option(None, help="write the fit as JSON"),
    plot: Path = typer.Option(None, help="write observed vs predicted F and M as PNG"),
) -> None:
    """Fit K1, K2, K3, K13, K23 (and uhat) to measured helices (the inverse spring problem)."""
    import json

    import jax

    jax.config.update("jax_enable_x64", True)
    from rich.console import Console

    from . import HelixData, fit_stiffness

    console = Console()
    fixed = {}
    for item in fix:
        name, _, value = item.partition("=")
        if not value:
            raise typer.BadParameter(f"--fix needs NAME=VALUE, got {item!r}")
        fixed[name.strip()] = float(value)
    try:
        observations = HelixData.from_csv(data)
        result = fit_stiffness(
            observations,
            uhat=None if uhat is None else _parse_floats(uhat, 3, "--uhat"),
            fit_uhat=fit_uhat,
            fix=fixed or None,
            branch=branch,
            method=method,
            n_starts=n_starts,
            key=jax.random.key(seed),
            absolute_sigma=not relative_sigma,
        )
    except ValueError as error:
        console.print(f"[red]error:[/red] {error}")
        raise typer.Exit(code=2) from None
    console.print(f"{len(observations)} helices from {data}")
    print_fit(console, result)
    if out is not None:
        out.write_text(json.dumps(result.to_dict(), indent=2))
        console.print(f"wrote {out}")
    if plot is not None:
        from ._plot import plot_fit

        plot_fit(observations, result, plot)
        console.print(f"wrote {plot}")


def example_data_path() -> Path:
    """The bundled example data set (see examples/make_example_data.py)."""
    return Path(__file__).resolve().parent / "data" / "example_spring.csv"


def demo_fit(console, out: Path) -> None:
    """The inverse spring problem on the bundled example data: for `helixrod demo`."""
    from . import HelixData, fit_stiffness
    from ._plot import plot_fit

    data = HelixData.from_csv(example_data_path())
    console.rule("The inverse spring problem")
    console.print(
        f"{len(data)} noisy helices of that rod (bundled example, examples/make_example_data.py); "
        "fitting K with uhat = (1, 0, 0) known"
    )
    result = fit_stiffness(data, uhat=(1.0, 0.0, 0.0))
    print_fit(console, result)
    out.mkdir(parents=True, exist_ok=True)
    path = plot_fit(data, result, out / "fit.png")
    console.print(f"wrote {path}")


def demo_dna_fit(console, out: Path) -> None:
    """DNA under force and torque: what tweezer data determine, and the fit (pN, nm)."""
    import numpy as np
    from rich.table import Table

    from . import dna, effective_moduli, fit_stiffness
    from ._plot import plot_fit

    example = dna.load_tweezer_example()
    data, true = example.helix_data(), example.rod
    console.rule("DNA under force and torque (synthetic tweezer data, pN and nm)")
    console.print(
        f"{len(data)} helices of the B-DNA backbone: applied force 0.5-40 pN and torque -10..15 pN nm, "
        "measured extension and rotation per base pair -> (kappa, tau) with correlated errors "
        "(dna.load_tweezer_example; generated by examples/make_tweezer_example.py from a rod with "
        "the published moduli S = 1100 pN, C = 410 pN nm^2, g = -90 pN nm). uhat: the relaxed B-DNA helix."
    )
    full = fit_stiffness(data, uhat=true.uhat, errors_in_variables=True, n_starts=8)
    console.print("All five stiffnesses free: what the data determine")
    print_fit(console, full)
    K2 = float(full.params["K2"])
    console.print(
        "Under an axial wrench the register of this rod stays at phi = 0, so the data see K2, K23 and "
        "K3 - K13^2/K1 only: K1 and K13 are not determined. The model with K13 = 0 and isotropic "
        f"bending (K1 = K2, fixed at {K2:.1f}) has three stiffnesses, all determined:"
    )
    fit = fit_stiffness(data, uhat=true.uhat, errors_in_variables=True, fix={"K1": K2, "K13": 0.0}, n_starts=4)
    table = Table(title=f"DNA fit, K1 = K2 and K13 = 0 (pN nm^2): reduced chi2 = {float(fit.chi2_reduced):.3g}")
    for col in ("parameter", "fitted", "stderr", "generating", "deviation"):
        table.add_column(col, justify="right")
    for name in fit.names:
        v, e, t = float(fit.params[name]), float(fit.stderr[name]), float(getattr(true, name))
        table.add_row(name, f"{v:.2f}", f"{e:.2f}", f"{t:.2f}", f"{(v - t) / e:+.2f} sigma")
    console.print(table)
    S, C, g = (float(x) for x in effective_moduli(fit.rod, fit.rod.uhat))
    console.print(
        f"moduli of the fitted rod at zero load: S = {S:.0f} pN, C = {C:.0f} pN nm^2, g = {g:.1f} pN nm "
        f"(published: 1100, 410, -90 +- 20); twist persistence {float(dna.persistence_length(C)):.0f} nm"
    )
    out.mkdir(parents=True, exist_ok=True)
    path = plot_fit(data, fit, out / "dna_fit.png")
    console.print(f"wrote {path}")
    residual = np.asarray(fit.residuals)
    console.print(f"whitened residuals: mean {residual.mean():+.2f}, standard deviation {residual.std():.2f}")


# -- end issue 4 --


# -- finite rods (issue 8) -----------------------------------------------------------------
@app.command(name="force-extension")
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
) -> None:
    """Force-extension curve of a finite clamped rod against the uniform-helix (bulk) formula."""
    import json
    import math
    import time

    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np
    from rich.console import Console
    from rich.table import Table

    from . import Rod, force_extension

    console = Console()
    K = _numbers(rod, "--rod", (3, 5))
    u = _numbers(uhat, "--uhat", (3,))
    norm = math.sqrt(sum(x * x for x in u))
    if norm == 0:
        raise typer.BadParameter("--uhat must not be zero: the length is given in turns of the unloaded helix")
    if not turns > 0:
        raise typer.BadParameter(f"--turns must be > 0, got {turns}")
    if moment is not None and rotation is not None:
        raise typer.BadParameter("give --moment or --rotation, not both")
    try:
        the_rod = Rod(*K, uhat=u)
    except ValueError as error:
        raise typer.BadParameter(str(error)) from None
    length = turns * 2 * math.pi / norm
    force_values = _grid_axis(forces, "--forces")
    held = {"moment": moment} if moment is not None else {"rotation": length * norm + (rotation or 0.0)}
    start = time.perf_counter()
    try:
        curve = force_extension(the_rod, length, force_values, segments=segments, **held)
    except ValueError as error:
        raise typer.BadParameter(str(error)) from None
    seconds = time.perf_counter() - start
    name = "moment" if moment is not None else "rotation"
    other = "rotation" if moment is not None else "moment"
    table = Table(title=f"force-extension, L = {length:.4g} ({turns:g} turns), {name} held")
    for col in ("F", "h", "h bulk", "h - h bulk", other, f"{other} bulk", "ok"):
        table.add_column(col, justify="right")
    for i in range(force_values.size):
        table.add_row(
            f"{float(curve.force[i]):.4g}", f"{float(curve.extension[i]):.6g}", f"{float(curve.bulk_extension[i]):.6g}",
            f"{float(curve.extension[i] - curve.bulk_extension[i]):+.3e}", f"{float(getattr(curve, other)[i]):.6g}",
            f"{float(getattr(curve, 'bulk_' + other)[i]):.6g}", "yes" if bool(curve.ok[i]) else "no",
        )
    console.print(table)
    console.print(f"{force_values.size} points in {seconds:.2f} s (compilation included); "
                  f"{int(np.sum(~np.asarray(curve.ok)))} did not converge")
    if out is not None:
        fields = ("force", "moment", "extension", "rotation", "bulk_force", "bulk_moment", "bulk_extension", "bulk_rotation", "ok")
        out.write_text(json.dumps({"length": length, **{f: np.asarray(getattr(curve, f)).tolist() for f in fields}}, indent=1))
        console.print(f"wrote {out}")
    if plot is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5.5, 4))
        ax.plot(curve.force, curve.extension, "o-", ms=3, label="finite rod (clamped)")
        ax.plot(curve.force, curve.bulk_extension, "--", label="uniform helix (bulk)")
        ax.set_xlabel("axial force F")
        ax.set_ylabel("extension h")
        ax.legend()
        fig.tight_layout()
        fig.savefig(plot, dpi=120)
        console.print(f"wrote {plot}")


# -- end issue 8 --

if __name__ == "__main__":  # pragma: no cover
    app()
