"""``helixrod fit``: the inverse spring problem on measured helices (a CSV file)."""

from __future__ import annotations

from pathlib import Path

import jax
import typer

from .. import MODEL_CLASSES, HelixData, compare_models, fit_stiffness
from .._misc import json_text, write_atomically
from ..plot import plot_fit, plot_model_comparison
from ._console import command_console
from ._numbers import assignments, numbers
from ._paths import input_file, output_file, read_with_notes
from ._report import print_comparison, print_fit


def example_data_path() -> Path:
    """The bundled example data set (see examples/make_example_data.py)."""
    return Path(__file__).resolve().parents[1] / "data" / "example_spring.csv"


def fit(
    data: Path = typer.Argument(..., help="CSV file (see helixrod.HelixData.from_csv)"),
    uhat: str = typer.Option(None, help="fixed intrinsic twist 'u1,u2,u3' (default 0,0,0)"),
    fit_uhat: bool = typer.Option(False, "--fit-uhat", metavar="", help="fit the intrinsic twist too"),
    fix: list[str] = typer.Option([], help="hold a parameter fixed, e.g. --fix K13=0 (repeatable)"),
    branch: str = typer.Option(
        None, help="register rule: nearest, stable or min-energy (default: nearest when every point has F and M, else stable; "
        "stable with --compare)",
    ),
    method: str = typer.Option("levenberg-marquardt", help="levenberg-marquardt, gauss-newton, lbfgs, adam"),
    n_starts: int | None = typer.Option(
        None, help="number of starts (default: up to 32 for helices, stopping early once two agree on the best minimum; "
        "1 for finite rods)",
    ),
    seed: int = typer.Option(0, help="seed of the random starts"),
    relative_sigma: bool = typer.Option(False, "--relative-sigma", metavar="", help="scale errors by the reduced chi2"),
    errors_in_variables: bool = typer.Option(
        None, "--errors-in-variables/--no-errors-in-variables",
        metavar="", help="propagate the kappa, tau sigmas of the data into the force and moment residuals (default: on when the data carry them)",
    ),
    compare: bool = typer.Option(
        False, "--compare", metavar="", help="fit the model classes of --models side by side (AIC, BIC, likelihood-ratio tests)"
    ),
    models: str = typer.Option(
        ",".join(MODEL_CLASSES), help=f"with --compare: comma-separated classes among {', '.join(MODEL_CLASSES)}"
    ),
    strict: bool = typer.Option(False, "--strict", metavar="", help="an unknown CSV column is an error (default: ignored with a note)"),
    out: Path = typer.Option(None, help="write the fit (or the comparison) as JSON"),
    plot: Path = typer.Option(None, help="write observed vs predicted F and M (or the comparison) as PNG"),
    progress: bool | None = typer.Option(
        None, "--progress/--no-progress", metavar="", help="progress bar (default: on a terminal)"
    ),
) -> None:
    """Fit K1, K2, K3, K13, K23 (and uhat) to measured helices (the inverse spring problem)."""
    console = command_console()
    fixed = assignments(fix, "--fix")
    input_file(data, "DATA")
    output_file(out, "--out")
    output_file(plot, "--plot", figure=True)
    classes = [m.strip() for m in models.split(",") if m.strip()]
    options = dict(
        uhat=None if uhat is None else numbers(uhat, "--uhat", 3),
        fit_uhat=fit_uhat,
        fix=fixed or None,
        solver=method,
        n_starts=n_starts,
        key=jax.random.key(seed),
        absolute_sigma=not relative_sigma,
        errors_in_variables=errors_in_variables,
        progress=progress,
    )
    if branch is not None:
        options["branch"] = branch
    try:
        observations = read_with_notes(console, lambda: HelixData.from_csv(data, strict=strict))
        result = compare_models(observations, classes, **options) if compare else fit_stiffness(observations, **options)
    except ValueError as error:
        console.print(f"[red]error:[/red] {error}")
        raise typer.Exit(code=2) from None
    console.print(f"{len(observations)} helices from {data} (observed: {', '.join(observations.observed)})")
    if compare:
        print_comparison(console, result)
        if out is not None:
            text = json_text(result.to_dict())
            write_atomically(out, lambda f: f.write(text), binary=False)
            console.print(f"wrote {out}")
        if plot is not None:
            plot_model_comparison(result, plot)
            console.print(f"wrote {plot}")
        return
    print_fit(console, result)
    if out is not None:
        result.save(out)
        console.print(f"wrote {out}")
    if plot is not None:
        plot_fit(observations, result, plot)
        console.print(f"wrote {plot}")
