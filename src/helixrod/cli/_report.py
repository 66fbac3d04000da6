"""Rich tables of a fit, shared by ``helixrod fit`` and ``helixrod demo``."""

from __future__ import annotations

import numpy as np
from rich import box
from rich.table import Table


def chi2_warning(fit) -> str | None:
    """A warning when the reduced chi2 is far from 1 for its degrees of freedom nu (more than
    5 of its standard deviations sqrt(2/nu) away): the sigmas do not describe the scatter,
    or the model misses something, and the standard errors (which trust the sigmas) are
    unreliable.  `None` otherwise."""
    nu = fit.n_residuals - int(fit.identifiability.rank)
    chi2 = float(fit.chi2_reduced)
    if nu < 1 or not np.isfinite(chi2) or abs(chi2 - 1.0) <= 5.0 * np.sqrt(2.0 / nu):
        return None
    cause = "larger than the sigmas say" if chi2 > 1 else "smaller than the sigmas say (are they overestimated?)"
    return (
        f"warning: reduced chi2 = {chi2:.4g} is far from 1 for {nu} degrees of freedom (expected 1 +- {np.sqrt(2.0 / nu):.2g}): "
        f"the scatter is {cause}, or the model misses something; the standard errors trust the sigmas"
    )


def print_fit(console, fit) -> None:
    """Rich tables of a `StiffnessFit` on `console`: values with standard errors,
    correlations, and the identifiability report."""
    table = Table(title=f"fit_stiffness ({fit.method}): cost = {float(fit.cost):.6g}, reduced chi2 = {float(fit.chi2_reduced):.4g}")
    for col in ("parameter", "value", "stderr", "relative"):
        table.add_column(col, justify="right")
    for name in fit.names:
        v, e = float(fit.params[name]), float(fit.stderr[name])
        rel = f"{abs(e / v):.2%}" if v != 0 and np.isfinite(e) else "-"
        table.add_row(name, f"{v:.6g}", f"{e:.3g}", rel)
    console.print(table)
    warning = chi2_warning(fit)
    if warning:
        console.print(f"[yellow]{warning}[/yellow] (--relative-sigma scales them by it)", soft_wrap=True)
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
        f"converged: {fit.ok} ({fit.message}); {fit.n_agree} of {fit.n_starts} starts reached the best "
        f"minimum; scaled-Jacobian singular values {np.array2string(np.asarray(ident.singular_values), precision=3)}, "
        f"condition number {float(ident.condition_number):.3g}, rank {ident.rank}"
    )
    if ident.weak:
        for w, e in zip(ident.weak, ident.weak_stderr):
            combo = " ".join(f"{c:+.3f}*{n}" for n, c in w)
            console.print(f"weakly determined: {combo}  (scaled stderr {e:.3g})")
        for w, e in zip(ident.determined, ident.determined_stderr):
            combo = " ".join(f"{c:+.3f}*{n}" for n, c in w)
            console.print(f"determined: {combo}  (scaled stderr {e:.3g})")
    else:
        console.print(f"every parameter combination determined to better than {ident.weak_threshold:.0%} (scaled)")
    for s in ident.symmetries:
        console.print(f"symmetry (identical predictions): {s}")
    for note in ident.notes:
        console.print(f"note: {note}")


def print_comparison(console, comparison) -> None:
    """Rich tables of a `ModelComparison`: the models side by side, the likelihood-ratio
    tests of nested pairs, and the recommendation."""
    # A light box: the table fits 80 columns with the longest class name unbroken.
    table = Table(title=f"compare_models: {len(comparison.names)} models, recommended by {comparison.criterion.upper()}",
                  box=box.SIMPLE_HEAD)
    table.add_column("model", justify="left", no_wrap=True)
    for col in ("k", "cost", "chi2/nu", "dAIC", "dBIC", "rank"):  # Akaike weights: in --out
        table.add_column(col, justify="right")
    for name in comparison.names:
        row = comparison.table[name]
        flag = f"{row['rank']}/{row['n_params']}" + ("" if row["identifiable"] else "!") + ("" if row["ok"] else " nc")
        mark = "*" if name == comparison.best else ""
        table.add_row(
            f"{mark}{name}", str(row["n_params"]), f"{row['cost']:.3g}", f"{row['chi2_reduced']:.3g}",
            f"{row['delta_aic']:.3g}", f"{row['delta_bic']:.3g}", flag,
        )
    console.print(table)
    console.print("rank: ! = a parameter undetermined, nc = not converged; * = recommended")
    if comparison.tests:
        tests = Table(title="likelihood-ratio tests (chi2 reference; see ModelComparison.simulate_test)", box=box.SIMPLE_HEAD)
        for col in ("smaller", "larger", "statistic", "df", "p"):
            tests.add_column(col, justify="right")
        for t in comparison.tests:
            tests.add_row(t["smaller"], t["larger"], f"{t['statistic']:.4g}", str(t["df"]), f"{t['p_value']:.3g}")
        console.print(tests)
    console.print(f"recommended: {comparison.best} ({comparison.reason})")
    best = comparison.fits[comparison.best]
    for name in best.names:
        console.print(f"  {name} = {float(best.params[name]):.6g} +- {float(best.stderr[name]):.3g}")
