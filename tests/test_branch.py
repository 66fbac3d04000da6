"""Branch following (`_bvp/_branch.py`) against closed forms derived here and independent solves.

- Euler column, clamped at s = 0, dead compressive load P at the free end, bending stiffnesses
  K1 = 1 < K2 = 1.5, L = 1: the straight branch has simple branch points at
  $P = \\pi^2 K_i/(4L^2)$ (the Jacobi equation of `tests/test_stability.py`), the index rising
  by one at each; the bifurcating branch of the first is the post-buckled elastica in the
  softer plane: with $k = \\sin(\\alpha/2)$ of the tip angle $\\alpha$, $K(k) = L\\sqrt{P/K_1}$,
  the tip moves sideways by $2k\\sqrt{K_1/P}$ to the height $\\sqrt{K_1/P}\\,(2E(k) - K(k))$
  (Love, sec. 263), and it is stable (supercritical pitchfork).
- A buckled strip between clamps (chord 0.9 L, stiff out of its plane) whose end clamp turns
  in the plane: the stable first mode reaches a fold (snap-through) and the branch comes back
  unstable; checked by solves from the stable side just before and just after the fold.
"""

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize
import scipy.special

import helixrod
from helixrod._lie import so3_exp

L = 1.0


def compressive(P):
    return helixrod.Loaded(force=jnp.stack([0.0 * P, 0.0 * P, -P]))


@pytest.fixture(scope="module")
def euler():
    rod = helixrod.Rod(1.0, 1.5, 0.8)
    straight = helixrod.follow_branch(rod, L, compressive, (1.0, 4.0))
    return rod, straight


@pytest.mark.heavy
def test_straight_column_branch_points_and_index(euler):
    rod, straight = euler
    assert straight.message.startswith("reached the end")
    assert float(straight.parameter[-1]) == pytest.approx(4.0, rel=1e-12)
    points = straight.points("branch point")
    assert len(points) == 2 and not straight.points("fold")
    first, second = (float(p.parameter) for p in points)
    # Located by the determinant's sign, the Jacobian from Jacobi fields (measured 2.8e-9
    # and 1.3e-9; the adaptive integration's forward-mode Jacobian placed them 2.1e-3 and
    # 7.4e-4 off, and the stability index's threshold the second 3.8e-6 off).
    assert first == pytest.approx(np.pi**2 / 4, rel=2e-8)
    assert second == pytest.approx(1.5 * np.pi**2 / 4, rel=2e-8)
    index = np.asarray(straight.instability_index)
    P = np.asarray(straight.parameter)
    assert np.array_equal(index, (P > first).astype(int) + (P > second).astype(int))
    # Every point is the straight column: N = (0, 0, -P), no moment.
    np.testing.assert_allclose(np.asarray(straight.force)[:, 2], -P, rtol=1e-10)
    assert np.max(np.abs(np.asarray(straight.moment0))) < 1e-9
    # On one piece the test does not resolve the load (index -1 everywhere, before): each
    # point is tested again on the pieces its wrench asks, as `solve_boundary_value` does.
    coarse = helixrod.follow_branch(rod, L, compressive, (1.0, 4.0), stability_pieces=1)
    coarse_index = np.asarray(coarse.instability_index)
    P = np.asarray(coarse.parameter)
    assert np.array_equal(coarse_index, (P > first).astype(int) + (P > second).astype(int))


@pytest.mark.heavy
def test_switch_onto_the_post_buckled_elastica(euler):
    rod, straight = euler
    (bp, _) = straight.points("branch point")
    # The bifurcating direction: the start moment about the softer axis alone (z = scaled
    # start force, start moment, parameter; one segment).
    np.testing.assert_allclose(np.abs(np.asarray(bp.direction)), np.eye(7)[3], atol=1e-6)
    buckled = helixrod.follow_branch(rod, L, compressive, (1.0, 4.0), switch=bp)
    mirror = helixrod.follow_branch(rod, L, compressive, (1.0, 4.0), switch=bp, direction=-1)
    P = np.asarray(buckled.parameter)
    assert buckled.message.startswith("reached the end") and P[-1] == pytest.approx(4.0) and P.size > 5
    assert np.all(np.diff(P) > 0) and np.all(np.asarray(buckled.stable))
    tip = np.asarray(buckled.end_position)
    # The branch point is found to ~3e-9 relative (`test_straight_column_branch_points_and_index`
    # asserts 2e-8): a load within 1e-7 of the critical one is the straight column.
    k = np.array([scipy.optimize.brentq(lambda k: scipy.special.ellipk(k**2) - L * np.sqrt(p), 0, 1 - 1e-15) if p > np.pi**2 / 4 * (1 + 1e-7) else 0.0 for p in P])
    # Next to the branch point the shooting Jacobian is nearly singular and the deflection
    # ~ sqrt(P - P_c) amplifies the solve's tolerance.
    away = P > 1.001 * np.pi**2 / 4
    height = (2 * scipy.special.ellipe(k**2) - scipy.special.ellipk(k**2)) / np.sqrt(P)
    np.testing.assert_allclose(np.abs(tip[:, 1]), 2 * k / np.sqrt(P), atol=1e-6)
    np.testing.assert_allclose(np.abs(tip[away, 1]), (2 * k / np.sqrt(P))[away], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(tip[away, 2], height[away], rtol=1e-6, atol=1e-9)
    assert np.max(np.abs(tip[:, 0])) < 1e-8  # in the softer plane
    # The other half of the pitchfork: the mirror image.
    other = np.asarray(mirror.end_position)
    assert np.all(np.sign(other[1:, 1]) == -np.sign(tip[1, 1]))
    # A point of the branch as a guess: solve_boundary_value stays on it.
    i = P.size // 2
    again = helixrod.solve_boundary_value(rod, L, end=compressive(jnp.asarray(P[i])), guess=(buckled.n0[i], buckled.m0[i]))
    np.testing.assert_allclose(np.asarray(again.end_position), tip[i], atol=1e-9)
    np.testing.assert_allclose(float(again.rotation), float(buckled.rotation[i]), atol=1e-9)  # the same turns


@pytest.mark.heavy
def test_buckled_strip_turned_in_its_plane_folds():
    rod = helixrod.Rod(1.0, 10.0, 5.0)
    turned = lambda a: helixrod.Clamped(jnp.stack([0.0 * a, 0.0 * a, 0.9 + 0.0 * a]), so3_exp(jnp.stack([a, 0.0 * a, 0.0 * a])))  # noqa: E731
    flat = helixrod.solve_boundary_value(rod, L, end=turned(jnp.asarray(0.0)))
    branch = helixrod.follow_branch(rod, L, turned, (0.0, 3.0), guess=flat, max_step=1.0)
    (fold,) = branch.points("fold")
    a_fold = float(fold.parameter)
    assert 0.3 < a_fold < 1.0 and not branch.points("branch point")
    a = np.asarray(branch.parameter)
    index = np.asarray(branch.instability_index)
    # Up to the fold, then back: stable before it, one unstable direction after.
    assert a.max() <= a_fold + 1e-9 and branch.message.startswith("reached the end") and a[-1] == pytest.approx(0.0, abs=1e-12)
    before = np.arange(a.size) <= fold.after
    assert np.all(index[before] == 0) and np.all(index[~before] == 1)
    # Independently: from the last stable point, a solve just short of the fold converges
    # to a stable state nearby; just beyond it there is none nearby.
    j = fold.after
    guess = (branch.n0[j], branch.m0[j])
    near = helixrod.solve_boundary_value(rod, L, end=turned(jnp.asarray(a_fold * (1 - 1e-3))), guess=guess, throw=False)
    assert bool(near.stable) and float(jnp.linalg.norm(near.force - fold.force)) < 0.05 * float(jnp.linalg.norm(fold.force))
    beyond = helixrod.solve_boundary_value(rod, L, end=turned(jnp.asarray(a_fold * (1 + 1e-3))), guess=guess, throw=False)
    assert not bool(beyond.ok) or float(jnp.linalg.norm(beyond.force - fold.force)) > 0.05 * float(jnp.linalg.norm(fold.force))


def test_the_first_point_is_newtons_from_the_default_guess_where_that_is_stable(monkeypatch, compilations):
    """From the default guess the first point is the corrector's, with no solve of
    `solve_boundary_value`, where it lands on a stable equilibrium (its guess and stability
    test the very programs a solve then finds compiled); beyond the first critical load the
    straight column it lands on is unstable, and the branch starts where
    `solve_boundary_value` lands from that guess: the buckled column, stable."""
    from helixrod._bvp import _branch

    rod = helixrod.Rod(1.0, 1.5, 0.8)
    solves = []

    def recorded(*args, **kwargs):
        solves.append(kwargs["end"])
        return helixrod.solve_boundary_value(*args, **kwargs)

    monkeypatch.setattr(_branch, "solve_boundary_value", recorded)
    below = helixrod.follow_branch(rod, L, compressive, (1.0, 1.5), stability_pieces=8)
    assert solves == [] and np.all(np.asarray(below.instability_index) == 0)
    np.testing.assert_allclose(below.force[0], [0.0, 0.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(below.end_position[0], [0.0, 0.0, L], atol=1e-12)  # straight
    compilations.clear()
    helixrod.solve_boundary_value(rod, L, end=compressive(jnp.asarray(1.25)), stability_pieces=8)
    assert not {"as_warm_start", "_stability_where_solved"} & {name for _, name in compilations}
    beyond = helixrod.follow_branch(rod, L, compressive, (3.0, 3.2), stability_pieces=8)
    assert len(solves) == 1
    direct = helixrod.solve_boundary_value(rod, L, end=compressive(jnp.asarray(3.0)), stability_pieces=8)
    assert bool(direct.stable) and int(beyond.instability_index[0]) == 0
    assert float(jnp.linalg.norm(direct.end_position[:2])) > 0.3  # buckled
    np.testing.assert_allclose(beyond.end_position[0], direct.end_position, atol=1e-6)
    np.testing.assert_allclose(beyond.moment0[0], direct.moment0, atol=1e-6)


def test_bad_arguments_are_named():
    rod = helixrod.Rod(1.0, 1.5, 0.8)
    with pytest.raises(ValueError, match="end must be a function"):
        helixrod.follow_branch(rod, L, helixrod.Loaded(force=(0.0, 0.0, -1.0)), (1.0, 2.0))
    with pytest.raises(ValueError, match="two different values"):
        helixrod.follow_branch(rod, L, compressive, (1.0, 1.0))
    with pytest.raises(ValueError, match="must return Clamped, Loaded or Tweezer"):
        helixrod.follow_branch(rod, L, lambda P: P, (1.0, 2.0))
    with pytest.raises(ValueError, match="step must be positive"):
        helixrod.follow_branch(rod, L, compressive, (1.0, 2.0), step=-1.0)
    with pytest.raises(ValueError, match="switch must be a branch point"):
        helixrod.follow_branch(rod, L, compressive, (1.0, 2.0), switch="here")


@pytest.mark.heavy
def test_a_first_point_that_is_not_isolated_is_named():
    """A straight twisted shaft between clamps exactly its length apart: every axial force
    balances it (inextensible), so its equilibria form a continuum, not a branch; the solve
    finds one, and follow_branch says why it cannot follow them."""
    rod = helixrod.Rod(1.0, 1.0, 0.8)

    def turned(angle):
        return helixrod.Clamped(jnp.array([0.0, 0.0, 1.0]), so3_exp(jnp.stack([0.0 * angle, 0.0 * angle, angle])), rotation=angle)

    assert bool(helixrod.solve_boundary_value(rod, 1.0, end=turned(0.5)).ok)
    with pytest.raises(ValueError, match="the equilibria at the first point are not isolated"):
        helixrod.follow_branch(rod, 1.0, turned, (0.5, 14.0))


@pytest.mark.heavy
def test_a_first_branch_compiles_its_corrector_beside_the_first_solve(compilations, monkeypatch):
    """The corrector step (`_point`) compiles on a thread of its own from the specs of its
    state, and the points' stability test on another from the corrector's output structure,
    while the first point's guess is made (one compilation of each, on their threads; a test
    of 10 pieces that no other test compiles); every point is tested."""
    from helixrod import _compile

    monkeypatch.setattr(_compile, "cores", lambda: 2)  # as on a machine of several cores
    branch = helixrod.follow_branch(helixrod.Rod(1.0, 1.5, 0.8), L, compressive, (1.0, 3.0), stability_pieces=10)
    names = ("_point", "_stability_where_solved")
    ours = sorted((thread, name) for thread, name in compilations if name in names)
    assert ours == [(f"helixrod-compile-{name}", name) for name in names], ours
    index = np.asarray(branch.instability_index)
    assert index[0] == 0 and index[-1] == 1 and np.all(index >= 0)  # past pi^2/4 K1, before pi^2/4 K2
    # The load named by its trace: a new function of the same load compiles nothing again.
    compilations.clear()
    again = helixrod.follow_branch(
        helixrod.Rod(1.0, 1.5, 0.8), L, lambda P: compressive(P), (1.0, 2.0), stability_pieces=10
    )
    assert [name for _, name in compilations if name in names] == []
    assert np.all(np.asarray(again.instability_index) == 0)
