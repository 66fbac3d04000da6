"""Figures (helixrod.plot): every figure renders a PNG, path=None returns the Figure without
changing matplotlib's backend, and missing fields are named."""

from pathlib import Path

import numpy as np
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


def test_sensitivity_figure_leaves_out_zero_parameters_and_names_the_register(tmp_path):
    """An elasticity theta dF/dtheta / F is identically zero at theta = 0: by default such
    parameters get no (blank) panel; asked for by name, the panel says so.  The figure names
    the register slot it shows."""
    rod = hr.Rod(1.0, 1.5, 0.8, K13=0.2, uhat=(0.5, 0.0, 0.3))  # K23 = 0, uhat2 = 0
    sens = hr.sensitivity(rod, [0.5, 1.0, 1.5], [-1.0, 0.0, 1.0, 2.0], progress=False)
    assert sens.of("K23")[np.isfinite(sens.of("K23"))].max(initial=0.0) == 0.0
    fig = plot.plot_sensitivity(sens)
    titles = [ax.get_title() for ax in fig.axes if ax.get_visible() and ax.get_title()]
    assert len(titles) == len(sens.wrt) - 2 and not any("K_{23}" in t or "hat u_2" in t for t in titles)
    assert fig._suptitle.get_text() == "register slot 0 (global minimum of W on the circle)"
    fig = plot.plot_sensitivity(sens, parameters=("K23", "K1"), slot=1)
    titles = [ax.get_title() for ax in fig.axes if ax.get_visible() and ax.get_title()]
    assert titles[0].endswith("= 0: elasticity 0") and "= 0" not in titles[1]
    assert "slot 1 (global maximum)" in fig._suptitle.get_text()
    assert plot.plot_sensitivity(sens, quantity="d_force").axes  # derivatives keep every parameter
    with pytest.raises(ValueError, match="not among"):
        plot.plot_sensitivity(sens, parameters=("K9",))
    with pytest.raises(ValueError, match="slot must be"):
        plot.plot_sensitivity(sens, slot=4)


def test_bad_figure_arguments_are_named(sens):
    for quantity in ("force", "phi", "d_forces"):
        with pytest.raises(ValueError, match="plot_sensitivity: quantity must be one with a parameter axis"):
            plot.plot_sensitivity(sens, quantity=quantity)
    with pytest.raises(ValueError, match="plot_sensitivity: parameters is empty"):
        plot.plot_sensitivity(sens, parameters=[])
    for kappa, tau in ((1.0, np.nan), (np.inf, 0.5), (0.0, 0.5)):
        with pytest.raises(ValueError, match="plot_helix needs a finite kappa > 0 and a finite tau"):
            plot.plot_helix(kappa, tau)
    with pytest.raises(ValueError, match="plot_helix draws one helix"):
        plot.plot_helix(np.array([1.0, 2.0]), 0.5)
    for options in ({"turns": 0}, {"turns": -1.0}, {"samples": 1}, {"samples": 2.5}):
        with pytest.raises(ValueError, match="plot_helix needs turns > 0 and an integer samples >= 2"):
            plot.plot_helix(1.0, 0.5, **options)
    with pytest.raises(ValueError, match="plot_stability_atlas: slot must be 0, 1, 2 or 3"):
        plot.plot_stability_atlas(None, slot=1.5)


def test_stability_atlas_figure_shows_undefined_points_as_such():
    """Points whose critical length is not defined (NaN: no register, or not resolved) are
    grey on the right panel -- not white, which says stable up to max_length -- and the L_c
    = L contour does not run along their edge; an atlas without critical lengths says so."""
    import matplotlib.pyplot as plt
    from types import SimpleNamespace

    kappa, tau = np.meshgrid(np.linspace(0.2, 2.0, 4), np.linspace(-1.0, 1.0, 4), indexing="ij")
    critical = np.full((4, 4, 4), np.inf)
    critical[0, :2, 0] = np.nan  # not resolved
    critical[3, :, 0] = 3.0  # unstable at L = 5
    kind = np.where(np.isnan(critical), -1, np.where(np.isfinite(critical), 2, 0))
    fields = dict(
        kappa=kappa, tau=tau, length=5.0, max_length=20.0, valid=np.ones((4, 4, 4), bool),
        instability_index=np.where(np.isnan(critical), -1, np.where(critical < 5.0, 1, 0)),
        pointwise_stable=np.ones((4, 4, 4), bool), critical_length=critical, instability_type=kind,
    )
    fig = plot.plot_stability_atlas(SimpleNamespace(**fields))
    right = fig.axes[1]
    labels = [t.get_text() for t in right.get_legend().get_texts()]
    assert "no register, or not resolved" in labels
    grey = [m for m in right.collections if type(m).__name__ == "QuadMesh" and np.ma.count(m.get_array()) == 2]
    assert len(grey) == 1  # the two undefined points, in their own mesh
    assert "white: stable up to 20" in right.get_title()
    plt.close(fig)
    fields.update(critical_length=np.full((4, 4, 4), np.nan), instability_type=np.zeros((4, 4, 4), int))
    fig = plot.plot_stability_atlas(SimpleNamespace(**fields))
    assert fig.axes[1].get_title() == "critical lengths not computed (critical_length=False)"
    plt.close(fig)
