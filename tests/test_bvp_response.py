"""End-response curves of finite springs (force_extension, rotation_response, axial_response)
against the bulk helix, against each other, and point by point.

Compiled programs: the curves of the spring at fixed rotation share one jitted function
(`tweezer_curve`, one trace for all lengths, forces and tolerances); the eager curves with
4 segments and 4 points share another, whatever their pair of controls.  Independent-mode
curves compile programs of their own: those tests are slow.
"""

import dataclasses
import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import SPRING, SPRING_NORM, SPRING_TURN as TURN, tree_allclose
from typer.testing import CliRunner

import helixrod as hr
from helixrod import plot
from helixrod.cli import app

FORCES = jnp.array([0.0, 0.01, 0.02, 0.03])
DEFAULT_OPTIONS = hr.BoundaryValueOptions()


def tweezer_curve(length, forces, options=DEFAULT_OPTIONS):
    """Force-extension of the spring at fixed (unturned) end rotation; one trace for all
    lengths, forces and tolerances (the options' tolerances are arrays, so traced)."""
    return _tweezer_curve(length, forces, options)


@eqx.filter_jit
@eqx.debug.assert_max_traces(max_traces=1)
def _tweezer_curve(length, forces, options):
    return hr.force_extension(SPRING, length, forces, rotation=length * SPRING_NORM, segments=4, options=options)


@pytest.mark.heavy
def test_response_curves_converge_to_the_bulk_helix():
    """The end effect of the clamps on the extension converges to a constant as the rod
    grows (so its share of the total falls like 1/L); the torque tends to the bulk one."""
    lengths = [2 * TURN, 4 * TURN, 8 * TURN, 16 * TURN]
    curves = [tweezer_curve(jnp.asarray(length), FORCES) for length in lengths]
    for c in curves:
        assert bool(jnp.all(c.ok)) and bool(jnp.all(c.bulk_ok))
        np.testing.assert_allclose(c.force, FORCES, atol=1e-12)
        np.testing.assert_allclose(c.rotation, c.length * SPRING_NORM, atol=1e-8)
        np.testing.assert_allclose(c.extension[0], c.bulk_extension[0], atol=1e-9)  # unloaded
    dh = np.array([np.asarray(c.end_effect("extension")) for c in curves])[:, 1:]
    dM = np.array([np.asarray(c.end_effect("moment")) for c in curves])[:, 1:]
    # Extension: the end effect settles (boundary layers decay along the stretched spring).
    assert np.all(np.abs(dh[3] - dh[2]) < 0.25 * np.abs(dh[1] - dh[0]))
    relative = np.abs(dh) / np.array(lengths)[:, None]
    assert np.all(np.diff(relative[1:], axis=0) < 0)
    # Torque: the clamps' share falls like 1/L.
    ratio = dM[3] / dM[2]
    np.testing.assert_allclose(ratio, 0.5, atol=0.1)
    # The bulk prediction is the uniform helix with the same force and rotation per length.
    bulk = hr.bulk_helix(SPRING, lengths[0], force=0.02, rotation=lengths[0] * SPRING_NORM)
    np.testing.assert_allclose(curves[0].bulk_extension[2], bulk.extension, rtol=1e-12)


@pytest.mark.heavy
def test_changing_tolerances_does_not_retrace():
    """The options travel as an argument of the jitted curve: other tolerances reuse its one
    trace (assert_max_traces) and take effect (each solution's tolerance is 10 atol)."""
    length = jnp.asarray(2 * TURN)
    default = tweezer_curve(length, FORCES)
    options = [hr.BoundaryValueOptions(atol=1e-8, ode_rtol=1e-8, ode_atol=1e-8),
               hr.BoundaryValueOptions(atol=1e-12, ode_rtol=1e-12, ode_atol=1e-12)]
    for opts in options:
        curve = tweezer_curve(length, FORCES, opts)  # a second trace would raise
        assert bool(jnp.all(curve.ok))
        np.testing.assert_allclose(curve.solutions.tolerance, 10 * float(opts.atol), rtol=1e-15)
        np.testing.assert_allclose(curve.extension, default.extension, atol=1e-6)
    np.testing.assert_allclose(default.solutions.tolerance, 1e-9, rtol=1e-15)


@pytest.mark.heavy
def test_force_extension_command(tmp_path, monkeypatch):
    """`helixrod force-extension` (tests/test_cli.py has the other commands); its eager 4-segment
    curve is the compiled program of the next test."""
    out = tmp_path / "curve.json"
    args = ["force-extension", "--turns", "2", "--forces", "0:0.03:4", "--segments", "4", "--out", str(out),
            "--plot", str(tmp_path / "curve.png")]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "force-extension" in result.output and "rotation held" in result.output
    assert (tmp_path / "curve.png").stat().st_size > 10_000
    curve = json.loads(out.read_text())
    direct = tweezer_curve(jnp.asarray(2 * TURN), jnp.linspace(0.0, 0.03, 4))
    np.testing.assert_allclose(curve["extension"], direct.extension, atol=1e-9)
    # The figure: each response against the bulk, and below it finite - bulk (the end effects).
    fig = plot.plot_response(direct)
    labels = [ax.get_ylabel() for ax in fig.axes]
    assert labels == ["extension $h$", "axial moment $M$", "extension: finite $-$ bulk", "axial moment: finite $-$ bulk"]
    line = fig.axes[2].get_lines()[0]
    np.testing.assert_allclose(line.get_ydata(), np.asarray(direct.extension) - np.asarray(direct.bulk_extension))
    bad = CliRunner().invoke(app, ["force-extension", "--uhat", "0,0,0"])
    assert bad.exit_code != 0 and "must not be zero" in bad.output
    for turns in ("inf", "nan", "0"):
        bad = CliRunner().invoke(app, ["force-extension", "--turns", turns])
        assert bad.exit_code != 0 and "--turns must be finite and > 0" in " ".join(bad.output.split()), turns
    # Rows that fail keep the force that was asked, say why, and what to try.
    long = CliRunner().invoke(app, ["force-extension", "--turns", "20", "--forces", "0:0.5:4", "--segments", "4"])
    assert long.exit_code == 0, long.output
    text = " ".join(long.output.split())
    assert "F = 0.5 did not converge: The maximum number of steps" in text and "try --segments 8" in text
    # A point that converged to other whole turns than the rotation held says so, not "did
    # not converge" (the curve of the first command, its second point flagged by hand).
    from helixrod.cli import _force_extension
    from helixrod._status import set_code

    def flagged(*args, **kwargs):
        curve = hr.force_extension(*args, **kwargs)
        return eqx.tree_at(lambda c: c.result, curve, set_code(curve.result, jnp.arange(4) == 1, hr.RESULTS.other_whole_turns))

    monkeypatch.setattr(_force_extension, "force_extension", flagged)
    turned = CliRunner().invoke(app, args[:-4])
    assert turned.exit_code == 0, turned.output
    text = " ".join(turned.output.split())
    assert "F = 0.01 holds other whole turns: The solve converged" in text and "try --segments" not in text
    assert "0 did not converge, 1 hold other whole turns than the rotation held" in text
    # The stability of each point, and a fold that ends the branch: the points beyond it did
    # not converge for want of an equilibrium, not of shooting pieces (a fold placed by hand).
    # Standard JSON (no Infinity or NaN constants): a point of no critical force is "nan".
    curve = json.loads(out.read_text(), parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))
    assert curve["instability_index"] == [0, 0, 0, 0] and curve["critical_kind"] == "none"
    assert curve["critical_force"] == "nan"
    assert "stable" in result.output and "loses stability" not in result.output

    def folded(*args, **kwargs):
        curve = hr.force_extension(*args, **kwargs)
        curve = eqx.tree_at(lambda c: (c.result, c.critical), curve,
                            (set_code(curve.result, jnp.arange(4) == 3, hr.RESULTS.max_steps_reached), jnp.asarray(0.025)))
        return dataclasses.replace(curve, critical_kind="fold")

    monkeypatch.setattr(_force_extension, "force_extension", folded)
    ended = CliRunner().invoke(app, args[:-4])
    assert ended.exit_code == 0, ended.output
    text = " ".join(ended.output.split())
    assert "loses stability at F = 0.025: a fold: the branch ends there" in text
    assert "F = 0.03 did not converge (beyond the fold)" in text and "try --segments" not in text


@pytest.mark.heavy
def test_rotation_response_agrees_with_force_extension():
    """Both curve functions solve the same problems (they share one compiled program with the
    command above): the
    same (force, rotation) point agrees; the torque grows with the turn and follows the bulk
    helix; a spring twisted between grips at fixed extension too."""
    length = 2 * TURN
    theta0 = length * SPRING_NORM
    turns = theta0 + jnp.array([-0.5, 0.0, 0.5, 1.0])
    twisted = hr.rotation_response(SPRING, length, turns, force=0.01, segments=4)
    pulled = hr.force_extension(SPRING, length, jnp.array([0.0, 0.005, 0.01, 0.02]), rotation=theta0, segments=4)
    assert bool(jnp.all(twisted.ok)) and bool(jnp.all(pulled.ok))
    np.testing.assert_allclose(twisted.rotation, turns, atol=1e-9)
    np.testing.assert_allclose(twisted.force, 0.01, atol=1e-12)
    np.testing.assert_allclose(twisted.extension[1], pulled.extension[2], atol=1e-9)
    np.testing.assert_allclose(twisted.moment[1], pulled.moment[2], atol=1e-10)
    assert np.all(np.diff(np.asarray(twisted.moment)) > 0)
    np.testing.assert_allclose(twisted.moment, twisted.bulk_moment, rtol=0, atol=1e-3 * float(jnp.abs(twisted.moment).max()))
    h0 = length * 0.3 / SPRING_NORM
    gripped = hr.rotation_response(SPRING, length, turns, extension=1.05 * h0, segments=4)
    assert bool(jnp.all(gripped.ok))
    np.testing.assert_allclose(gripped.extension, 1.05 * h0, atol=1e-9)
    np.testing.assert_allclose(gripped.force, gripped.bulk_force, rtol=0.1)
    assert np.all(np.diff(np.asarray(gripped.moment)) > 0)
    # A first point three whole turns past the unloaded end: the curve starts from the bulk
    # helix with those turns, its interior nodes turned as far (the end frame alone does not
    # count them), and finds the twisted spring the bulk predicts (before: an untwisted one,
    # its moment ~0, reported at the rotation asked for).
    longer = 5 * TURN
    held = longer * SPRING_NORM + 3 * 2 * np.pi + jnp.array([0.0, 0.5, 1.0, 1.5])
    turned = hr.rotation_response(SPRING, longer, held, force=0.01, segments=4)
    assert bool(jnp.all(turned.ok))
    np.testing.assert_allclose(turned.moment, turned.bulk_moment, rtol=0.01)
    np.testing.assert_allclose(turned.extension, turned.bulk_extension, rtol=0.01)
    # A single solve finds that spring from the bulk helix's wrench (from the default guess,
    # which aims at it too, `solve_boundary_value` goes on to a stable state: this one is not).
    start, end = hr.axial_ends(SPRING, longer, force=0.01, rotation=float(held[0]))
    bulk = hr.bulk_helix(SPRING, longer, force=0.01, rotation=float(held[0]))
    e3 = jnp.array([0.0, 0.0, 1.0])
    guess = (start.frame.T @ (bulk.force * e3), start.frame.T @ (bulk.moment * e3))
    single = hr.solve_boundary_value(SPRING, longer, start=start, end=end, segments=4, guess=guess)
    axial_moment = single.moment0[2] + jnp.cross(single.node_position[0], single.force)[2]
    np.testing.assert_allclose(axial_moment, turned.moment[0], rtol=1e-8)
    np.testing.assert_allclose(turned.solutions.rotation, held, atol=1e-9)  # the turns each rod holds
    # From the default guess the solve looks for a stable state with those turns, finds none
    # (its fallbacks found ones with fewer: the untwisted spring) and reports the twisted
    # spring, unstable, rather than a stable state of other turns.
    default = hr.solve_boundary_value(SPRING, longer, start=start, end=end, segments=4)
    assert bool(default.ok) and int(default.instability_index) > 0
    assert float(default.rotation) == pytest.approx(float(held[0]), abs=1e-9)
    np.testing.assert_allclose(default.force, single.force, atol=1e-8)
    # Its stability: on the curve's 16 pieces, each a chain of the sub-pieces its wrench asks
    # (before the chains, 16 pieces did not resolve it: tested again on 64); the single solve
    # tests it again on the 64 its wrench asks: the same unstable spring (a plectoneme is nearer).
    assert turned.solutions.stability_pieces == DEFAULT_OPTIONS.stability_pieces and single.stability_pieces == 64
    assert int(turned.instability_index[0]) == int(single.instability_index) > 0
    # (margins -92.0 on the 16 chained pieces, -89.4 on 64: the metric's discretisation)
    np.testing.assert_allclose(turned.stability_margin[0], single.stability_margin, rtol=0.05)


def test_response_curve_flags_a_bad_point_without_spoiling_the_others():
    length = jnp.asarray(2 * TURN)
    clean = tweezer_curve(length, FORCES)
    bad = tweezer_curve(length, FORCES.at[1].set(jnp.nan))
    assert not bool(bad.ok[1]) and bool(jnp.isnan(bad.extension[1]))
    keep = np.array([0, 2, 3])
    assert bool(jnp.all(bad.ok[keep]))
    np.testing.assert_allclose(bad.extension[keep], clean.extension[keep], atol=1e-9)
    # A bad first point: the continuation starts at the first good one (from the bad one,
    # every later point's substeps started at NaN and all were flagged invalid_input).
    first = tweezer_curve(length, FORCES.at[0].set(jnp.nan))
    assert np.asarray(first.ok).tolist() == [False, True, True, True]
    assert np.asarray(first.solutions.valid_input).tolist() == [False, True, True, True]
    np.testing.assert_allclose(first.extension[1:], clean.extension[1:], atol=1e-9)


@pytest.mark.heavy  # compiles the curve vmapped over lengths
def test_a_bad_length_in_a_batch_of_curves_is_flagged_bulk_prediction_too():
    forces = jnp.linspace(0.0, 0.02, 4)

    def curve(length):
        c = hr.force_extension(SPRING, length, forces, progress=False)
        return c.extension, c.ok, c.bulk_extension, c.bulk_ok

    extension, ok, bulk, bulk_ok = jax.vmap(curve)(jnp.array([6.0, -1.0, jnp.nan, 12.0]))
    assert ok.tolist() == bulk_ok.tolist() == [[True] * 4, [False] * 4, [False] * 4, [True] * 4]
    assert np.all(np.isnan(np.asarray(bulk[1:3]))) and np.all(np.isnan(np.asarray(extension[1:3])))
    single = hr.force_extension(SPRING, 12.0, forces)
    np.testing.assert_allclose(extension[3], single.extension, rtol=1e-9)
    np.testing.assert_allclose(bulk[3], single.bulk_extension, rtol=1e-12)


# -- axial_response: any sequence of control pairs ------------------------------------------

POINT_FIELDS = ("force", "moment", "extension", "rotation", "bulk_force", "bulk_moment", "bulk_extension",
                "bulk_rotation", "ok", "bulk_ok")


def point(curve, i):
    """The fields of point `i` of a curve, as a dict (for tree_allclose)."""
    return {name: getattr(curve, name)[i] for name in POINT_FIELDS}


@pytest.mark.parametrize(
    "mode, segments",
    [
        ("continuation", 4),  # the eager program of the test above: no compilation of its own
        pytest.param("independent", 1, marks=pytest.mark.slow),  # compiles the vmapped curve (~15 s)
    ],
)
def test_axial_response_with_both_controls_varying_equals_force_extension(mode, segments):
    """Force and rotation both varying along one curve: each point equals that point of
    force_extension at its (held) rotation, in either mode (the same compiled program for
    both functions)."""
    length = 2 * TURN
    theta0 = length * SPRING_NORM
    forces = jnp.array([0.005, 0.01, 0.02, 0.03])
    # Half a turn from the unloaded end too, where the end frame's twist was read to 1e-3.
    # (Each step turns the end by less than half a turn: by more, continuation may turn it
    # the short way, onto other whole turns -- flagged, as the next test shows.)
    rotations = theta0 + jnp.array([0.0, 1.5, np.pi, 0.6])
    both = hr.axial_response(SPRING, length, force=forces, rotation=rotations, mode=mode, segments=segments)
    assert both.controls == "force-rotation" and both.swept == "force" and both.held == "rotation"
    assert bool(jnp.all(both.ok)) and bool(jnp.all(both.bulk_ok))
    np.testing.assert_allclose(both.force, forces, atol=1e-12)
    np.testing.assert_allclose(both.rotation, rotations, atol=1e-9)
    np.testing.assert_allclose(both.solutions.rotation, rotations, atol=1e-9)  # the turns each rod holds
    for i in range(4):
        held = hr.force_extension(SPRING, length, forces, rotation=rotations[i], mode=mode, segments=segments)
        tree_allclose(point(both, i), point(held, i), rtol=0, atol=1e-9)
    # The responses move with both controls: not a trivially constant curve.
    assert float(jnp.ptp(both.moment)) > 1e-3 and float(jnp.ptp(both.extension)) > 1e-2


def test_a_curve_point_holding_other_whole_turns_is_flagged():
    """A curve warm-started from a rod that holds other whole turns than its first point
    asks for stays on that rod's turns (the end frames cannot tell them apart): each point
    is flagged `other_whole_turns` with NaN observables, its solution kept, and counts the
    turns it does hold."""
    length = 2 * TURN
    theta0 = length * SPRING_NORM
    start, end = hr.axial_ends(SPRING, length, force=0.01, rotation=theta0)
    untwisted = hr.solve_boundary_value(SPRING, length, start=start, end=end, segments=4)
    assert float(untwisted.rotation) == pytest.approx(theta0, abs=1e-9)
    offsets = jnp.array([0.0, 0.3, -0.3, 0.6])
    curve = hr.rotation_response(SPRING, length, theta0 + 2 * np.pi + offsets, force=0.01, segments=4, guess=untwisted)
    assert not bool(jnp.any(curve.ok)) and bool(jnp.all(jnp.isnan(curve.moment)))
    assert bool(jnp.all(curve.result == hr.RESULTS.other_whole_turns))
    assert bool(jnp.all(curve.solutions.instability_index == 0))
    np.testing.assert_allclose(curve.solutions.rotation, theta0 + offsets, atol=1e-9)



def test_continuation_takes_long_steps_in_substeps():
    """A step too long to converge from the previous point, or one that turns the end by
    whole turns, is taken in substeps (`_solve_from`).  Before, whole-turn steps of a
    prescribed rotation found the end frame unchanged and stayed on the first point's
    turns (flagged `other_whole_turns`), and moment steps of -0.3 failed from -0.6 on.
    Checked: every point holds the turns asked for (counted along its rod), and points
    reached along other sequences of substeps are the same states."""
    length = 2 * TURN
    theta0 = length * SPRING_NORM
    turns = jnp.array([0.0, 1.0, 2.0, 3.0])
    whole = hr.rotation_response(SPRING, length, theta0 + 2 * np.pi * turns, force=0.01, segments=4)
    assert bool(jnp.all(whole.ok))
    np.testing.assert_allclose(whole.solutions.rotation, theta0 + 2 * np.pi * turns, atol=1e-9)
    assert np.all(np.diff(np.asarray(whole.moment)) > 0.4)  # twisted further each turn, not flagged
    other = hr.rotation_response(SPRING, length, theta0 + 2 * np.pi * jnp.array([0.0, 0.5, 2.0, 3.0]), force=0.01, segments=4)
    for name in ("moment", "extension"):
        np.testing.assert_allclose(getattr(whole, name)[2:], getattr(other, name)[2:], atol=1e-9)
    # Substeps cost solves: the points taken in one step cost one.
    assert int(whole.solutions.num_steps[0]) < 10 < int(whole.solutions.num_steps[1])

    moments = jnp.array([0.0, -0.3, -0.6, -0.9])
    pulled = hr.axial_response(SPRING, length, force=0.02, moment=moments, segments=4)
    assert bool(jnp.all(pulled.ok))
    np.testing.assert_allclose(pulled.moment, moments, atol=1e-12)
    reordered = hr.axial_response(SPRING, length, force=0.02, moment=jnp.array([0.0, -0.45, -0.9, -0.6]), segments=4)
    for name in ("rotation", "extension"):
        np.testing.assert_allclose(getattr(pulled, name)[2:], getattr(reordered, name)[jnp.array([3, 2])], atol=1e-9)
    # Its end is loaded by a moment: stability is not defined (index -1), so none is lost.
    # (Before, those points counted as unstable: a "branch point" at M = -1e-13.)
    assert np.array_equal(pulled.instability_index, [0, -1, -1, -1])
    assert np.isnan(float(pulled.critical)) and pulled.critical_kind == "none"



@pytest.mark.heavy
def test_a_point_its_substeps_do_not_reach_is_not_a_success(monkeypatch):
    """Where a point's substeps run out before reaching it, none of them failing (here with
    the budget cut to two solves: a whole turn needs five substeps), the point is reported
    failed (`max_steps_reached`), its last substep's state kept as the next point's start
    with its controls.  (`_solve_from` traced afresh with the budget patched.)"""
    from helixrod._bvp import _response
    from helixrod._bvp._ends import TWEEZER

    length = 2 * TURN
    theta0 = length * SPRING_NORM
    start, end = hr.axial_ends(SPRING, length, force=0.01, rotation=theta0)
    solved = hr.solve_boundary_value(SPRING, length, start=start, end=end, segments=4)
    options = hr.BoundaryValueOptions(segments=4)
    v_from = jnp.array([0.01, 0.0, 0.0, theta0])
    v = v_from.at[3].add(2 * np.pi)
    monkeypatch.setattr(_response, "CONTINUATION_TRIES", 1)
    monkeypatch.setattr(_response, "MAX_ROTATION_SUBSTEPS", 1)
    clamp = _response._curve_setup(SPRING, length)[0]
    step = jax.jit(lambda v_from, v, guess: _response._solve_from(
        SPRING, length, TWEEZER, clamp, v_from, v, guess, jnp.asarray(True), options))
    sol, _, reached = step(v_from, v, solved.warm_start())
    assert not bool(sol.ok) and int(sol.result._value) == int(hr.RESULTS.max_steps_reached._value)
    np.testing.assert_allclose(reached[3] - theta0, 2 * _response.MAX_ROTATION_STEP, rtol=1e-12)  # two substeps
    assert int(sol.num_steps) > 0

@pytest.mark.heavy
def test_a_curve_ending_at_a_fold_reports_it():
    """The spring twisted under F = 0.2: its twisted branch folds back near 2.8 half-turns
    past the unloaded end, and the points beyond fail (no equilibrium nearby).  The curve
    reports the fold there (stable point -> failed point, the margin falling to zero), at
    the rotation where `follow_branch`, which passes the fold by pseudo-arclength
    continuation, finds the parameter turning back.  (Before, a failed point after a
    stable one was no loss of stability: `critical` NaN.)"""
    length = 2 * TURN
    theta0 = length * SPRING_NORM
    curve = hr.rotation_response(SPRING, length, theta0 + np.pi * jnp.array([2.7, 2.75, 2.85, 2.9]), force=0.2, segments=4)
    assert np.array_equal(curve.ok, [True, True, False, False]) and np.array_equal(curve.instability_index[:2], [0, 0])
    assert curve.critical_kind == "fold"
    end = lambda rotation: hr.axial_ends(SPRING, length, force=0.2, rotation=rotation)[1]  # noqa: E731
    branch = hr.follow_branch(SPRING, length, end, (theta0 + 2.7 * np.pi, theta0 + 2.9 * np.pi), segments=4)
    (fold,) = branch.points("fold")
    assert float(curve.critical) == pytest.approx(float(fold.parameter), rel=1e-8)  # measured 1.5e-10
    assert 2.75 * np.pi < float(curve.critical) - theta0 < 2.85 * np.pi

@pytest.mark.heavy
def test_independent_points_start_from_their_bulk_helix():
    """In independent mode each point starts from the default guess made from its own bulk
    helix (as a continuation's first point): a spring held three whole turns past its
    unloaded end is the twisted spring the bulk predicts (before: untwisted, its moment ~0);
    near the unloaded end, the continuation curve's points.  (The 4-point, 4-segment
    independent program of tests/test_progress.py.)"""
    longer = 5 * TURN
    theta0 = longer * SPRING_NORM
    held = theta0 + 3 * 2 * np.pi + jnp.array([0.0, 0.5, 1.0, 1.5])
    turned = hr.rotation_response(SPRING, longer, held, force=0.01, segments=4, mode="independent")
    assert bool(jnp.all(turned.ok))
    np.testing.assert_allclose(turned.moment, turned.bulk_moment, rtol=0.01)
    np.testing.assert_allclose(turned.extension, turned.bulk_extension, rtol=0.01)
    near = theta0 + jnp.array([-0.5, 0.0, 0.5, 1.0])
    independent = hr.rotation_response(SPRING, longer, near, force=0.01, segments=4, mode="independent")
    continued = hr.rotation_response(SPRING, longer, near, force=0.01, segments=4)
    for name in ("moment", "extension", "rotation"):
        np.testing.assert_allclose(getattr(independent, name), getattr(continued, name), rtol=0, atol=1e-8)


@pytest.mark.slow  # compiles the independent-mode curve without bulk (~15 s on 2 busy cores)
def test_axial_response_rotation_hint_and_no_bulk():
    """Force and moment held (a Loaded end: the rotation responds), independent points.
    The reported rotation holds the whole turns counted along each rod, whatever the hint;
    without a count (no stability test) `rotation_hint` picks them (nearest the hint);
    `bulk=False` leaves the bulk fields NaN; neither changes the solutions, which equal the
    continuation curve's (the eager 4-segment program above).  Both options apply to
    mode='independent' only."""
    length = 2 * TURN
    forces = jnp.array([0.0, 0.01, 0.02, 0.03])
    reference = hr.axial_response(SPRING, length, force=forces, moment=0.0, segments=4)
    assert reference.controls == "force-moment" and bool(jnp.all(reference.ok))
    hints = reference.bulk_rotation
    near = hr.axial_response(SPRING, length, force=forces, moment=0.0, mode="independent", rotation_hint=hints, bulk=False)
    counted = hr.axial_response(SPRING, length, force=forces, moment=0.0, mode="independent",
                                rotation_hint=hints + 2 * np.pi, bulk=False)
    turned = hr.axial_response(SPRING, length, force=forces, moment=0.0, mode="independent",
                               rotation_hint=hints + 2 * np.pi, bulk=False, options=hr.BoundaryValueOptions(stability_pieces=0))
    np.testing.assert_allclose(counted.rotation, reference.rotation, rtol=0, atol=1e-9)
    for curve in (near, turned):
        assert bool(jnp.all(curve.ok)) and not bool(jnp.any(curve.bulk_ok))
        assert bool(jnp.all(jnp.isnan(curve.bulk_extension))) and bool(jnp.all(jnp.isnan(curve.bulk_rotation)))
        np.testing.assert_allclose(curve.force, forces, atol=1e-12)
        for name in ("moment", "extension"):
            np.testing.assert_allclose(getattr(curve, name), getattr(reference, name), rtol=0, atol=1e-9)
    np.testing.assert_allclose(near.rotation, reference.rotation, rtol=0, atol=1e-9)
    np.testing.assert_allclose(turned.rotation, reference.rotation + 2 * np.pi, rtol=0, atol=1e-9)
    np.testing.assert_allclose(turned.rotation - near.rotation, 2 * np.pi, rtol=0, atol=1e-12)
    assert float(jnp.ptp(near.rotation)) > 0.01  # the rotation responds to the force
    with pytest.raises(ValueError, match="apply to mode='independent'"):
        hr.axial_response(SPRING, length, force=forces, moment=0.0, rotation_hint=hints)
    with pytest.raises(ValueError, match="apply to mode='independent'"):
        hr.axial_response(SPRING, length, force=forces, moment=0.0, bulk=False)


# -- errors ---------------------------------------------------------------------------------


def test_bad_curve_arguments_raise_clear_errors():
    with pytest.raises(ValueError, match="give moment= or rotation=, not both"):
        hr.force_extension(SPRING, 10.0, FORCES, moment=0.0, rotation=1.0)
    with pytest.raises(ValueError, match="forces must be finite"):
        hr.force_extension(SPRING, 10.0, FORCES.at[0].set(jnp.nan))
    with pytest.raises(ValueError, match="exactly one of force= or extension="):
        hr.rotation_response(SPRING, 10.0, jnp.ones(3))
    with pytest.raises(ValueError, match="mode"):
        hr.force_extension(SPRING, 10.0, FORCES, mode="parallel")
    with pytest.raises(ValueError, match="axial_response: give one of the pairs"):
        hr.axial_response(SPRING, 10.0, force=FORCES, extension=1.0)
    with pytest.raises(ValueError, match="the controls do not broadcast"):
        hr.axial_response(SPRING, 10.0, force=FORCES, rotation=jnp.ones(3))
    with pytest.raises(ValueError, match="unknown observable"):
        tweezer_curve(jnp.asarray(2 * TURN), FORCES).end_effect("torque")


@pytest.mark.heavy
def test_a_first_curve_compiles_its_solves_and_their_test_side_by_side_once(compilations, monkeypatch):
    """A curve's continuation scan and the stability test of its solves are programs of
    their own (the test does not steer the continuation), compiled each on a thread of its
    own at the first curve of a signature, from the specs of the values they will be called
    with (the scan's carry from `_continuation_carry`, not traced), while the call compiles
    the scan's start: the calls find those compilations.  A curve of its own size (no other test solves 7 points); the test's
    results equal those of single solves."""
    from helixrod import _compile

    monkeypatch.setattr(_compile, "cores", lambda: 2)  # as on a machine of several cores
    forces = jnp.linspace(0.0, 0.03, 7)
    curve = hr.force_extension(SPRING, 2 * TURN, forces, moment=0.0, segments=4)
    names = ("_continuation_points", "_stability_of_points")
    ours = sorted((thread, name) for thread, name in compilations if name in names + ("_continuation_start",))
    assert ours == [("MainThread", "_continuation_start")] + [(f"helixrod-compile-{name}", name) for name in names], ours
    assert bool(jnp.all(curve.ok)) and curve.solutions.stability_pieces == DEFAULT_OPTIONS.stability_pieces
    start, end = hr.axial_ends(SPRING, 2 * TURN, force=float(forces[-1]), moment=0.0)
    single = hr.solve_boundary_value(SPRING, 2 * TURN, start=start, end=end, segments=4)
    np.testing.assert_allclose(curve.stability_margin[-1], single.stability_margin, rtol=1e-6)
    assert int(curve.instability_index[-1]) == int(single.instability_index)


@pytest.mark.heavy
def test_a_first_loss_of_stability_compiles_nothing_more(compilations, monkeypatch):
    """The 3-turn spring pulled at zero end moment loses its stability near F = 0.0924
    (index 0 -> 1).  Its later points' wrenches need more than 16 pieces of the old test's
    length: each piece is a chain of sub-pieces now, and the curve's 16-piece test resolves
    them all (before, each was tested again on 32, 64 or 128 pieces, one program each).  The
    bisection's trials run on the curve's own programs, in their first slot (before, a
    single solve and test of their own: the first curve across its critical force took
    11.0 s on 2 cores): the bisection compiles nothing, not even one-operation programs.
    Trial solves from the curve's last stable point on either side of the critical force:
    stable below it, index 1 above."""
    from helixrod import _compile
    from helixrod._bvp import _response

    monkeypatch.setattr(_compile, "cores", lambda: 2)
    bisection = _response._first_loss_of_stability
    during = []

    def watched(*args):
        before = len(compilations)
        try:
            return bisection(*args)
        finally:
            during.extend(compilations[before:])

    monkeypatch.setattr(_response, "_first_loss_of_stability", watched)
    length = 3 * TURN
    curve = hr.force_extension(SPRING, length, jnp.linspace(0.01, 0.2, 8))
    assert curve.critical_kind == "branch point" and np.array_equal(curve.instability_index[:5], [0, 0, 0, 0, 1])
    assert bool(jnp.all(curve.ok)) and curve.solutions.stability_pieces == DEFAULT_OPTIONS.stability_pieces
    critical = float(curve.critical)
    assert 0.0919 < critical < 0.0929  # (measured 0.092423)
    assert during == [], during
    stable_point = jax.tree.map(lambda a: a[3], curve.solutions)
    for factor, index in ((1 - 1e-5, 0), (1 + 1e-5, 1)):
        start, end = hr.axial_ends(SPRING, length, force=factor * critical, moment=0.0)
        single = hr.solve_boundary_value(SPRING, length, start=start, end=end, guess=stable_point)
        assert bool(single.ok) and int(single.instability_index) == index


def test_the_continuation_carry_specs_are_those_of_its_start():
    """`_continuation_carry` (the specs the scan compiles ahead for, without tracing its
    start) against the traced output of `_continuation_start`: from the default guess on
    one segment, and on three from it, a warm start (a solution's) and a start wrench."""
    from helixrod._bvp._response import _continuation_carry, _continuation_start
    from helixrod._bvp._shooting import WarmStart
    from helixrod._bvp._ends import TWEEZER

    values = jnp.array([[0.01, 0.0, 0.0, 2 * TURN], [0.02, 0.0, 0.0, 2 * TURN]])
    for segments in (1, 3):
        options = hr.BoundaryValueOptions(segments=segments)
        warm_start = WarmStart(jnp.zeros(3), jnp.zeros(3), jnp.zeros((segments, 3)), jnp.zeros((segments, 3, 3)))
        for guess in (None, warm_start, (jnp.zeros(3), jnp.zeros(3)))[: 1 if segments == 1 else 3]:
            traced = jax.eval_shape(_continuation_start, SPRING, 2 * TURN, TWEEZER, values, options, guess)
            specs = _continuation_carry(values.dtype, segments)
            assert jax.tree.structure(traced) == jax.tree.structure(specs)
            for a, b in zip(jax.tree.leaves(traced), jax.tree.leaves(specs)):
                assert (a.shape, a.dtype, a.weak_type) == (b.shape, b.dtype, b.weak_type)


@pytest.mark.heavy
def test_a_straight_rod_twisted_in_either_mode():
    """A straight rod twisted at fixed force: independent points start from its bulk state
    (the straight twisted rod; it was NaN, and points past half a turn landed on other whole
    turns), so both modes give the prescribed rotation, M = K3 Theta / L, and the bulk
    prediction beside it."""
    rod = hr.Rod(1.0, 1.5, 0.8)
    rotations = jnp.array([3.0, 4.5, 6.0])
    for mode in ("independent", "continuation"):
        curve = hr.rotation_response(rod, 1.0, rotations, force=1.0, mode=mode)
        assert bool(jnp.all(curve.ok)), mode
        np.testing.assert_allclose(curve.moment, 0.8 * rotations, rtol=1e-9)
        np.testing.assert_allclose(curve.bulk_moment, 0.8 * rotations, rtol=1e-12)


@pytest.mark.heavy  # 5- and 4-segment curve programs of their own: ~15 s to compile
def test_a_curve_on_automatic_segments_reaches_a_stretched_spring():
    """`segments="auto"` for a curve: the most shooting pieces its points' guesses ask for
    (`needed_segments`). The README's spring of 3 turns, end turned 0.5 rad past its
    unloaded end, pulled to F = 1 (single shooting fails from F = 0.6 on): every point
    stable on 5 pieces, the same curve as on 4 given ones; a traced input or another word
    is a clear error."""
    length = 3 * 2 * np.pi / np.hypot(1.0, 0.3)
    turned = float(hr.unloaded_observables(SPRING, length)[1]) + 0.5
    forces = jnp.linspace(0.05, 1.0, 20)
    auto = hr.force_extension(SPRING, length, forces, rotation=turned, segments="auto")
    given = hr.force_extension(SPRING, length, forces, rotation=turned, segments=4)
    assert auto.solutions.segments == 5 and given.solutions.segments == 4
    assert bool(jnp.all(auto.ok)) and np.all(np.asarray(auto.instability_index) == 0)
    np.testing.assert_allclose(auto.extension, given.extension, atol=1e-8)
    assert 14.0 < float(auto.extension[-1]) < length
    with pytest.raises(ValueError, match="concrete inputs"):
        jax.jit(lambda f: hr.force_extension(SPRING, length, f, rotation=turned, segments="auto").extension)(forces)
    with pytest.raises(ValueError, match="'auto'"):
        hr.force_extension(SPRING, length, forces, rotation=turned, segments="many")
