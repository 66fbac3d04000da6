"""The command line (helixrod.cli): the demo and `helixrod sweep` on small inputs, their files
and output against the library, and errors.

Two commands are tested next to the library tests whose compiled programs they reuse (each
would cost 10-20 s of compilation here): `helixrod force-extension` in
tests/test_bvp_response.py (the eager 4-segment curve) and `helixrod fit` in
tests/test_fit_pipeline.py (the 24-point fit)."""

import numpy as np
import pytest
from helpers import SWEEP_ROD, reference
from typer.testing import CliRunner

import helixrod as hr
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


def test_cli_sweep(tmp_path):
    args = ["sweep", "--rod", "1,1.7,0.9,0.3,-0.2", "--uhat", "0.8,0.3,0.4", "--kappa", "0:3:20", "--tau", "-3:3:30",
            "--fields", ",".join(hr.SweepResult.FIELDS), "--chunk-size", "512",
            "--out", str(tmp_path / "a.npz"), "--plot", str(tmp_path / "a.png"), "--no-progress"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "swept 600 helices" in result.output
    back = hr.load_sweep(tmp_path / "a.npz")
    assert back["count"].shape == (20, 30)
    expect = reference(SWEEP_ROD, back.kappa[::4, None], back.tau[None, ::3])  # 5 x 10 points
    np.testing.assert_array_equal(back["count"][::4, ::3], expect.count)
    assert (tmp_path / "a.png").stat().st_size > 10_000
    bad = CliRunner().invoke(app, ["sweep", "--fields", "force,nope"])
    assert bad.exit_code != 0 and "valid fields" in bad.output


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["sweep", "--rod", "-1,1,1"], "--rod -1,1,1 --uhat 1,0,0: Rod: stiffness must be finite and positive definite"),
        (["force-extension", "--rod", "1,-1,1"], "Rod: stiffness must be finite and positive definite"),
        (["sweep", "--out", "NOFOLDER/x.npz"], "--out: the folder NOFOLDER does not exist"),
        (["sweep", "--plot", "atlas.txt"], "--plot: cannot write a figure as .txt; use one of"),
        (["sweep", "--out", "."], "--out: . is a folder; give a file name"),
        (["force-extension", "--plot", "curve"], "cannot write a figure as a file without a suffix"),
        (["fit", "missing.csv"], "DATA: no such file: missing.csv"),
        (["fit", "EXAMPLE", "--plot", "fit.docx"], "--plot: cannot write a figure as .docx"),
        (["demo", "--out", "AFILE"], "--out: AFILE exists and is not a folder"),
        (["sweep", "--kappa", "nan:3:5"], "--kappa: start and stop must be finite"),
        (["sweep", "--tau=-3:inf:5"], "--tau: start and stop must be finite"),
    ],
)
def test_user_errors_are_usage_errors_before_any_computation(tmp_path, args, message):
    """Exit code 2, the problem and its fix in typer's error box, no traceback -- raised
    before anything is computed (so a long run never ends by losing its result)."""
    from helixrod.cli import example_data_path

    (tmp_path / "AFILE").write_text("")
    args = [str(example_data_path()) if a == "EXAMPLE" else a for a in args]
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(tmp_path)
        result = CliRunner().invoke(app, args)
    assert result.exit_code == 2, result.output
    text = " ".join(result.output.replace("│", " ").split())
    assert message in text, text
    assert "Traceback" not in result.output and isinstance(result.exception, SystemExit)
    assert "wrote" not in text and sorted(p.name for p in tmp_path.iterdir()) == ["AFILE"]


def test_sweep_too_large_for_memory_says_what_to_ask_for(tmp_path):
    result = CliRunner().invoke(app, ["sweep", "--kappa", "0:3:300000", "--tau=-3:3:300000"])
    assert result.exit_code == 2, result.output
    text = " ".join(result.output.replace("│", " ").split())
    assert "grid does not fit in memory" in text and "--fields count" in text and "Traceback" not in result.output


def test_help_shows_no_value_for_plain_flags():
    """A flag takes no value: its help row shows no `<bool>` type (typer 0.29 prints one
    unless the option has an empty metavar), --help's own row included."""
    for command in (["--help"], ["fit", "--help"], ["tweezer-fit", "--help"], ["demo", "--help"], ["stability", "--help"],
                    ["sweep", "--help"], ["force-extension", "--help"]):
        result = CliRunner(env={"COLUMNS": "200"}).invoke(app, command)
        assert result.exit_code == 0, result.output
        assert "--help" in result.output
        flagged = [line for line in result.output.splitlines() if "<bool>" in line]
        assert flagged == [], (command, flagged)


def test_tables_keep_whole_numbers_when_not_on_a_terminal(monkeypatch):
    """Redirected output (a log) is not cut to rich's 80 columns: a wide table keeps its
    numbers whole, with no ellipsis."""
    from helixrod.cli._console import LOG_WIDTH, command_console

    monkeypatch.delenv("COLUMNS", raising=False)
    assert command_console().width == LOG_WIDTH  # pytest's output is not a terminal
    monkeypatch.setenv("COLUMNS", "90")
    assert command_console().width == 90
