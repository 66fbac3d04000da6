"""Progress of long work (`_progress.py`): a callable `progress` sees `done` rise to `total`
after each host-side batch, the results are those of the single call bit for bit, nothing
is printed when stdout is not a terminal (as under pytest), and a bad `progress` is a
`ValueError` that names it.

Sizes are those of the other tests of each function (the 24 helices of the fit tests,
tests/test_bvp_response.py, tests/test_atlas.py, helpers.sweep_atlas).  With progress shown
a job is cut into batches of a compiled program of its own, so each check compiles its
function twice; those of 20 s or more are heavy.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import SPRING, SPRING_NORM, SWEEP_KAPPA, SWEEP_ROD, SWEEP_TAU, tree_allclose
from helpers import SPRING_TURN as TURN
from typer.testing import CliRunner

import helixrod as hr
from helixrod._progress import batch_size, check_progress, progress_bar
from helixrod.cli import app, example_data_path

FIT_OPTIONS = dict(uhat=(1.0, 0.0, 0.0))  # the example's, as `helixrod demo` fits it
FORCES = jnp.array([0.0, 0.01, 0.02, 0.03])
ATLAS_ROD = hr.Rod(1.0, 1.5, 0.8, uhat=(0.0, 1.0, 0.3))


class Recorder:
    """A `progress` callback that keeps every `(done, total)` it is given."""

    def __init__(self):
        self.calls = []

    def __call__(self, done, total):
        self.calls.append((done, total))

    def check(self, total, batches=None):
        done = [d for d, _ in self.calls]
        assert self.calls and all(t == total for _, t in self.calls), self.calls
        assert all(b > a for a, b in zip(done, done[1:])) and done[-1] == total, self.calls
        if batches is not None:
            assert len(done) == batches, self.calls


def same(a, b):
    """Equal bit for bit (NaN where NaN)."""
    return tree_allclose(a, b, rtol=0.0, atol=0.0)


# -- the helper ----------------------------------------------------------------------------


def test_progress_bar_modes(capsys):
    record = Recorder()
    with progress_bar("job", 5, record, owner="job") as report:
        assert report.shown
        report.advance(2)
        report.advance(0)  # nothing done: no call
        report.advance(3)
    record.check(5, batches=2)
    for quiet in (None, False):  # None: stdout is not a terminal under pytest
        with progress_bar("job", 5, quiet, owner="job") as report:
            assert not report.shown
            report.advance(5)
    assert capsys.readouterr().out == ""
    with progress_bar("a long job", 3, True, owner="job") as report:
        report.advance(3)
    assert "a long job" in capsys.readouterr().out
    assert check_progress(np.bool_(True), "job") is True
    for bad in ("yes", 1, 0.5, [True]):
        with pytest.raises(ValueError, match="job: progress must be"):
            check_progress(bad, "job")
    # Batches: at most 20, two units at least (a vmap of width one rounds differently).
    assert [batch_size(n) for n in (1, 2, 3, 16, 40, 41, 1000)] == [1, 2, 2, 2, 2, 3, 50]


# -- sweep ---------------------------------------------------------------------------------


def test_sweep_progress():
    """2014 points in chunks of 512: the program of helpers.sweep_atlas, four chunks."""
    fields = hr.SweepResult.FIELDS  # the compiled program of helpers.sweep_atlas
    off = hr.sweep(SWEEP_ROD, SWEEP_KAPPA, SWEEP_TAU, fields=fields, chunk_size=512, progress=False)
    record = Recorder()
    on = hr.sweep(SWEEP_ROD, SWEEP_KAPPA, SWEEP_TAU, fields=fields, chunk_size=512, progress=record)
    record.check(SWEEP_KAPPA.size * SWEEP_TAU.size, batches=4)
    for name in fields:
        np.testing.assert_array_equal(on[name], off[name])
    with pytest.raises(ValueError, match="sweep: progress"):
        hr.sweep(SWEEP_ROD, SWEEP_KAPPA, SWEEP_TAU, progress="yes")
    with pytest.raises(ValueError, match="sensitivity: progress"):
        hr.sensitivity(SWEEP_ROD, SWEEP_KAPPA, SWEEP_TAU, progress="yes")


def test_sweep_is_silent_off_a_terminal(capsys):
    hr.sweep(SWEEP_ROD, SWEEP_KAPPA, SWEEP_TAU, fields=hr.SweepResult.FIELDS, chunk_size=512)
    assert capsys.readouterr().out == ""


# -- fits and bootstraps -------------------------------------------------------------------


@pytest.fixture(scope="module")
def helix_fit():
    """Two starts on the bundled 24-helix example (no compile to read it), progress off."""
    data = hr.HelixData.from_csv(example_data_path())
    return data, hr.fit_stiffness(data, **FIT_OPTIONS, n_starts=2, progress=False)


def without_problem(fit):
    return dataclasses.replace(fit, problem=None)  # the model, solver: not results


def test_fit_stiffness_progress(helix_fit, capsys):
    """Two starts: one batch (the program of the single call), then the error analysis."""
    data, off = helix_fit
    record = Recorder()
    on = hr.fit_stiffness(data, **FIT_OPTIONS, n_starts=2, progress=record)
    record.check(3, batches=2)
    assert same(without_problem(on), without_problem(off))
    quiet = hr.fit_stiffness(data, **FIT_OPTIONS, n_starts=2)  # progress=None
    assert capsys.readouterr().out == ""
    assert same(without_problem(quiet), without_problem(off))
    with pytest.raises(ValueError, match="fit_stiffness: progress"):
        hr.fit_stiffness(data, **FIT_OPTIONS, progress="yes")
    with pytest.raises(ValueError, match="bootstrap: progress"):
        hr.bootstrap(data, off, 2, jax.random.key(4), progress="yes")


@pytest.mark.heavy
def test_bootstrap_progress(helix_fit, capsys):
    """Two replicates: one batch, the program of the single call; five in batches of two,
    the last padded: the replicates of the single call bit for bit."""
    data, fit = helix_fit
    for n, calls in ((2, [(2, 2)]), (5, [(2, 5), (4, 5), (5, 5)])):
        off = hr.bootstrap(data, fit, n, jax.random.key(4), kind="parametric")  # progress=None
        assert capsys.readouterr().out == ""
        record = Recorder()
        on = hr.bootstrap(data, fit, n, jax.random.key(4), kind="parametric", progress=record)
        assert record.calls == calls
        assert same(on, off)


@pytest.mark.heavy
def test_batched_starts_equal_the_single_call(helix_fit):
    """Five starts in batches of two, the last padded (both batchings): the fit of the single
    call bit for bit."""
    data, _ = helix_fit
    for batching in ("map", "vmap"):
        off = hr.fit_stiffness(data, **FIT_OPTIONS, n_starts=5, batching=batching, progress=False)
        record = Recorder()
        on = hr.fit_stiffness(data, **FIT_OPTIONS, n_starts=5, batching=batching, progress=record)
        assert record.calls == [(2, 6), (4, 6), (5, 6), (6, 6)]
        assert same(without_problem(on), without_problem(off))


# -- response curves -----------------------------------------------------------------------


def test_response_curve_progress_arguments():
    length = 2 * TURN
    for curve in (
        lambda p: hr.force_extension(SPRING, length, FORCES, progress=p),
        lambda p: hr.rotation_response(SPRING, length, FORCES, force=0.01, progress=p),
        lambda p: hr.axial_response(SPRING, length, force=FORCES, moment=0.0, progress=p),
    ):
        with pytest.raises(ValueError, match="progress must be"):
            curve("yes")
    # Traced inputs: the batches would run at trace time, so a bar or callback is refused.
    with pytest.raises(ValueError, match="needs concrete inputs"):
        jax.jit(lambda f: hr.force_extension(SPRING, length, f, progress=True))(FORCES)


@pytest.mark.heavy
@pytest.mark.parametrize("mode", ["continuation", "independent"])
def test_response_curve_progress(mode, capsys):
    """The 4-segment, 4-point curves of tests/test_bvp_response.py (one program for the three
    functions per mode): in batches of two points, continuation carrying its warm start
    across, the curves of the single call (bit for bit in continuation)."""
    length = 2 * TURN
    theta0 = length * SPRING_NORM
    curves = {
        "force_extension": lambda p: hr.force_extension(SPRING, length, FORCES, rotation=theta0, segments=4, mode=mode, progress=p),
        "rotation_response": lambda p: hr.rotation_response(
            SPRING, length, theta0 + jnp.array([-0.5, 0.0, 0.5, 1.0]), force=0.01, segments=4, mode=mode, progress=p
        ),
        "axial_response": lambda p: hr.axial_response(
            SPRING, length, force=FORCES, rotation=theta0, segments=4, mode=mode, progress=p
        ),
    }
    for name, curve in curves.items():
        off = curve(None)
        assert capsys.readouterr().out == "", name
        record = Recorder()
        on = curve(record)
        record.check(4, batches=2)
        assert bool(jnp.any(off.ok)), name
        if mode == "continuation":
            assert same(on, off), name
        else:
            # A vmap of two points rounds differently from one of four: round-off (positions
            # of up to ~3.6 to ~1e-13 absolute, a few hundred ULPs of the largest), and the
            # stability margin (an eigenvalue of a stiff Hessian) to ~1e-9 relative.
            margin = lambda c: c.solutions.stability_margin  # noqa: E731
            np.testing.assert_allclose(margin(on), margin(off), rtol=1e-8)
            assert tree_allclose(eqx.tree_at(margin, on, margin(off)), off, rtol=1e-12, atol=1e-13), name


# -- the stability atlas -------------------------------------------------------------------


@pytest.mark.heavy
def test_stability_atlas_progress(capsys):
    """Four points of the atlas of tests/test_atlas.py, 16 helices in chunks of at most 6:
    three chunks of 6 (as few as that allows, of equal width; the last padded by two), in
    batches of two whole chunks (the last padded by a chunk); the atlas of the single call
    bit for bit."""
    kappa = jnp.array([1.4, 1.6, 1.8, 2.0])
    off = hr.stability_atlas(ATLAS_ROD, kappa, -0.5, 5.0, chunk_size=6)
    assert capsys.readouterr().out == ""
    record = Recorder()
    on = hr.stability_atlas(ATLAS_ROD, kappa, -0.5, 5.0, chunk_size=6, progress=record)
    assert record.calls == [(12, 16), (16, 16)]
    assert same(on, off)
    with pytest.raises(ValueError, match="stability_atlas: progress"):
        hr.stability_atlas(ATLAS_ROD, kappa, -0.5, 5.0, progress="yes")


# -- the command line ----------------------------------------------------------------------


@pytest.mark.parametrize("command", ["sweep", "fit", "force-extension", "stability", "tweezer-fit"])
def test_commands_take_progress(command):
    result = CliRunner().invoke(app, [command, "--help"])
    assert result.exit_code == 0 and "--progress" in result.output and "--no-progress" in result.output
