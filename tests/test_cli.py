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
