import pytest
from typer.testing import CliRunner

from helixrod.cli import app


def test_demo_writes_figure(tmp_path):
    result = CliRunner().invoke(app, ["demo", "--no-fits", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert "Uniform helical equilibria" in result.output
    assert (tmp_path / "hyperboloid.png").stat().st_size > 10_000
    assert (tmp_path / "atlas.png").stat().st_size > 10_000  # issue 5: the kappa-tau atlas


@pytest.mark.slow
def test_demo_with_fits(tmp_path):
    """The whole demo, as a newcomer runs it: the example spring fit and the DNA fit too."""
    result = CliRunner().invoke(app, ["demo", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert "K1 and K13 are not determined" in result.output
    for name in ("fit.png", "dna_fit.png"):
        assert (tmp_path / name).stat().st_size > 10_000


def test_hyperboloid_figure_without_a_path():
    """helixrod.plot's contract: path=None returns the Figure, and no backend is changed
    (plot_hyperboloid used to require a path and switch matplotlib to Agg)."""
    import matplotlib
    from matplotlib.figure import Figure

    import helixrod as hr
    from helixrod import plot

    backend = matplotlib.get_backend()
    fig = plot.plot_hyperboloid(hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0)), radii=(1.0, 3.0))
    assert isinstance(fig, Figure) and len(fig.axes) == 2
    assert matplotlib.get_backend() == backend
