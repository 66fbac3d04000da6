from typer.testing import CliRunner

from helixrod.cli import app


def test_demo_writes_figure(tmp_path):
    result = CliRunner().invoke(app, ["demo", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert "Uniform helical equilibria" in result.output
    assert (tmp_path / "hyperboloid.png").stat().st_size > 10_000
    assert (tmp_path / "atlas.png").stat().st_size > 10_000  # issue 5: the kappa-tau atlas
