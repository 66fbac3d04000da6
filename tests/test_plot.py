"""Figures (helixrod.plot): every figure renders a PNG, path=None returns the Figure without
changing matplotlib's backend, and missing fields are named."""

from pathlib import Path

import pytest
from helpers import SWEEP_KAPPA as KAPPA, SWEEP_ROD as ROD, SWEEP_TAU as TAU, sweep_atlas, sweep_sensitivity

import helixrod as hr
from helixrod import plot


@pytest.fixture(scope="module")
def atlas():
    return sweep_atlas()


@pytest.fixture(scope="module")
def sens():
    return sweep_sensitivity()


def test_every_figure_renders(atlas, sens, tmp_path):
    paths = [
        plot.plot_atlas(atlas, tmp_path / "atlas.png"),
        plot.plot_stable_wrench(atlas, tmp_path / "wrench.png"),
        plot.plot_sensitivity(sens, tmp_path / "sens.png", parameters=("K13", "uhat1")),
        plot.plot_helix(1.0, 0.5, tmp_path / "helix.png"),
        plot.plot_sweep_summary(atlas, tmp_path / "summary.png"),
    ]  # plot_hyperboloid: below, and with a path by the demo (tests/test_cli.py)
    for p in paths:
        assert Path(p).stat().st_size > 10_000
        assert Path(p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="stable_force"):
        plot.plot_stable_wrench(hr.SweepResult(ROD, KAPPA, TAU, {"count": atlas["count"]}))


def test_hyperboloid_figure_without_a_path():
    """helixrod.plot's contract: path=None returns the Figure, and no backend is changed
    (plot_hyperboloid used to require a path and switch matplotlib to Agg)."""
    import matplotlib
    from matplotlib.figure import Figure

    backend = matplotlib.get_backend()
    fig = plot.plot_hyperboloid(hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0)), radii=(1.0, 3.0))
    assert isinstance(fig, Figure) and len(fig.axes) == 2
    assert matplotlib.get_backend() == backend
