"""End conditions of finite rods: Clamped, Loaded, Tweezer, their uniform form EndCondition
(one traced form for every kind), and the axial
controls of spring and tweezer tests (axial_ends).

References: exact uniform helices and the transport of a moment between points.  (Solves
with these ends, vmapped batches of mixed kinds included: tests/test_bvp_solve.py, where
they share one compiled configuration.)"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import SPRING, SPRING_TURN as TURN, tree_allclose

import helixrod as hr
from helixrod._bvp import stack_ends


def test_axial_ends_follow_the_spring_conventions():
    """Unloaded controls give the unloaded helix's ends exactly, in every kind (solved:
    tests/test_bvp_solve.py::test_unloaded_axial_ends_solve_to_the_unloaded_helix)."""
    length = 2.5 * TURN
    h0, theta0 = (float(a) for a in hr.unloaded_observables(SPRING, length))
    start, _ = hr.axial_ends(SPRING, length, force=0.0, moment=0.0)
    np.testing.assert_allclose(start.position, hr.helix_centreline(1.0, 0.3, 0.0), atol=1e-15)
    for kw in ({"extension": h0, "rotation": theta0}, {"force": 0.0, "rotation": theta0}):
        _, end = hr.axial_ends(SPRING, length, **kw)
        np.testing.assert_allclose(end.frame, hr.helix_frame(1.0, 0.3, 0.0, length), atol=1e-14)
        if "extension" in kw:
            np.testing.assert_allclose(end.position, hr.helix_centreline(1.0, 0.3, length), atol=1e-13)


def test_axial_ends_kinds_and_turns():
    """force-moment -> Loaded about the axis, force-rotation -> Tweezer, extension-rotation ->
    Clamped; the end frame is the unloaded one turned about e_z by Theta - Theta0, and the
    grips move along e_z by h - h0."""
    length = 2.5 * TURN
    h0, theta0 = (float(a) for a in hr.unloaded_observables(SPRING, length))
    x_end, frame_end = (np.asarray(a) for a in hr.unloaded_state(SPRING, length))
    turn = 0.7
    c, s = np.cos(turn), np.sin(turn)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    _, hooks = hr.axial_ends(SPRING, length, force=0.02, moment=-0.01)
    assert isinstance(hooks, hr.Loaded)
    np.testing.assert_array_equal(hooks.force, [0.0, 0.0, 0.02])
    np.testing.assert_array_equal(hooks.moment, [0.0, 0.0, -0.01])
    np.testing.assert_array_equal(hooks.point, np.zeros(3))  # on the axis
    _, magnet = hr.axial_ends(SPRING, length, force=0.02, rotation=theta0 + turn)
    assert isinstance(magnet, hr.Tweezer)
    np.testing.assert_allclose(magnet.frame, Rz @ frame_end, atol=1e-14)
    np.testing.assert_array_equal(magnet.force, [0.0, 0.0, 0.02])
    _, grips = hr.axial_ends(SPRING, length, extension=h0 + 0.5, rotation=theta0 + turn)
    assert isinstance(grips, hr.Clamped)
    np.testing.assert_allclose(grips.frame, Rz @ frame_end, atol=1e-14)
    np.testing.assert_allclose(grips.position, Rz @ x_end + [0.0, 0.0, 0.5], atol=1e-13)
    # A straight untwisted rod starts at the origin with the identity frame.
    start, _ = hr.axial_ends(hr.Rod(1.0, 1.0, 0.8), 3.0, force=0.1, moment=0.0)
    np.testing.assert_array_equal(start.position, np.zeros(3))
    np.testing.assert_array_equal(start.frame, np.eye(3))


def test_each_kind_in_the_uniform_form():
    """`condition()` puts every kind in one form (`kind`, zeros for unused fields), and its
    residual vanishes exactly on the end state the kind prescribes: the moment about a fixed
    point P of a load with moment m about the end x is m + (x - P) x F."""
    rng = np.random.default_rng(3)
    x, F, m_end, P = (jnp.asarray(rng.normal(size=3)) for _ in range(4))
    R = hr.so3_exp(jnp.asarray(rng.normal(size=3)))
    other = hr.so3_exp(jnp.asarray(rng.normal(size=3)))
    scales = jnp.array([2.0, 3.0, 5.0])
    clamped = hr.Clamped(x, R).condition()
    assert int(clamped.kind) == 0 and not bool(clamped.about_end)
    np.testing.assert_array_equal(clamped.position, x)
    np.testing.assert_array_equal(clamped.frame, R)
    np.testing.assert_array_equal(clamped.force, np.zeros(3))
    np.testing.assert_allclose(clamped.residual(x, R, F, m_end, scales), 0.0, atol=1e-15)  # any load
    about_end = hr.Loaded(F, m_end).condition()
    assert int(about_end.kind) == 1 and bool(about_end.about_end)
    np.testing.assert_array_equal(about_end.frame, np.eye(3))
    np.testing.assert_allclose(about_end.residual(x, other, F, m_end, scales), 0.0, atol=1e-15)  # any frame
    about_point = hr.Loaded(F, m_end + jnp.cross(x - P, F), point=P).condition()
    assert int(about_point.kind) == 1 and not bool(about_point.about_end)
    np.testing.assert_array_equal(about_point.point, P)
    np.testing.assert_allclose(about_point.residual(x, other, F, m_end, scales), 0.0, atol=1e-14)
    # A hook attached to the end (director components r): the force acts at x + D r, so the
    # moment about the end is (D r) x F plus the applied one, in any frame D.
    r = jnp.asarray(rng.normal(size=3))
    hooked = hr.Loaded(F, m_end, hook=r).condition()
    assert int(hooked.kind) == 1 and bool(hooked.about_end)
    np.testing.assert_array_equal(hooked.hook, r)
    np.testing.assert_allclose(hooked.residual(x, other, F, m_end + jnp.cross(other @ r, F), scales), 0.0, atol=1e-14)
    assert float(jnp.abs(hooked.residual(x, R, F, m_end + jnp.cross(other @ r, F), scales)).max()) > 1e-3
    tweezer = hr.Tweezer(R, F).condition()
    assert int(tweezer.kind) == 2
    np.testing.assert_array_equal(tweezer.moment, np.zeros(3))
    np.testing.assert_allclose(tweezer.residual(x + 1.0, R, F, m_end, scales), 0.0, atol=1e-15)  # any position
    # Off the prescribed state: the scaled differences (position by scales[0], force by [1]).
    r = clamped.residual(x + jnp.array([2.0, 0.0, 0.0]), R, F, m_end, scales)
    np.testing.assert_allclose(r, [1.0, 0, 0, 0, 0, 0], atol=1e-15)
    r = tweezer.residual(x, R, F + jnp.array([0.0, 0.0, 3.0]), m_end, scales)
    np.testing.assert_allclose(r, [0, 0, 1.0, 0, 0, 0], atol=1e-15)
    assert tweezer.condition() is tweezer  # the uniform form is its own condition
    # Built from its leaves (`end_condition`, no initialiser): the Module its initialiser builds.
    for cond in (clamped, about_end, about_point, hooked, tweezer):
        rebuilt = hr.EndCondition(*(getattr(cond, f.name) for f in dataclasses.fields(cond)))
        assert jax.tree.structure(rebuilt) == jax.tree.structure(cond)
        tree_allclose(rebuilt, cond, rtol=0, atol=0)


def test_stack_ends_stacks_the_uniform_forms():
    """stack_ends: one EndCondition with a leading axis over ends of mixed kinds, each slice
    the end's own uniform form (a vmapped solve over it: tests/test_bvp_solve.py, slow)."""
    R = hr.so3_exp(jnp.array([0.3, -0.2, 0.5]))
    ends = [hr.Clamped((1.0, 2.0, 3.0), R), hr.Loaded((0.1, 0.0, 0.2), (0.0, 0.3, 0.0)),
            hr.Loaded((0.1, 0.0, 0.2), (0.0, 0.3, 0.0), point=(0.0, 0.0, 1.0)), hr.Tweezer(R, (0.0, 0.0, 0.5))]
    stacked = stack_ends(ends)
    assert isinstance(stacked, hr.EndCondition) and stacked.kind.tolist() == [0, 1, 1, 2]
    assert stacked.about_end.tolist() == [False, True, False, False] and stacked.frame.shape == (4, 3, 3)
    for i, end in enumerate(ends):
        tree_allclose(jax.tree.map(lambda a: a[i], stacked), end.condition(), rtol=0, atol=0)


def test_bad_end_conditions_raise_clear_errors():
    with pytest.raises(ValueError, match="frame must be a rotation"):
        hr.Clamped((0.0, 0.0, 0.0), 2 * jnp.eye(3))
    with pytest.raises(ValueError, match="position must have trailing shape"):
        hr.Clamped((0.0, 0.0))
    with pytest.raises(ValueError, match="force must be finite"):
        hr.Loaded((jnp.inf, 0.0, 0.0))
    with pytest.raises(ValueError, match="not both"):
        hr.Loaded((0.0, 0.0, 1.0), point=(0.0, 0.0, 0.0), hook=(1.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="hook must be finite"):
        hr.Loaded((0.0, 0.0, 1.0), hook=(jnp.nan, 0.0, 0.0))
    with pytest.raises(ValueError, match="frame must be a rotation"):
        hr.Tweezer(-jnp.eye(3), (0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="one of the pairs"):
        hr.axial_ends(SPRING, 10.0, force=1.0, extension=2.0)
    with pytest.raises(ValueError, match="moment must be a scalar"):
        hr.axial_ends(SPRING, 10.0, force=1.0, moment=jnp.zeros(2))


def test_the_homotopy_twists_an_end_by_its_whole_turns():
    """The homotopy fallback's path to a gripped spring turned 3.3 turns past its unloaded
    end: the end turns about the axis by the fraction t of all of it (the short way, without
    the end's `rotation`: by the fraction of 0.3 turns), and arrives at the condition."""
    from helixrod._lie import rotation_z, twist_angle

    length = 5 * TURN
    theta0 = float(hr.unloaded_observables(SPRING, length)[1])
    h0 = float(hr.unloaded_observables(SPRING, length)[0])
    turned = theta0 + 2 * np.pi * 3.3
    end = hr.axial_ends(SPRING, length, extension=1.1 * h0, rotation=turned)[1].condition()
    free = hr.axial_ends(SPRING, length, extension=h0, rotation=theta0)[1].condition()
    arrived = end.homotopy(1.0, free.position, free.frame, theta0)
    np.testing.assert_allclose(arrived.frame, end.frame, atol=1e-12)
    np.testing.assert_allclose(arrived.position, end.position, atol=1e-12)
    for t in (0.25, 0.5):
        along = end.homotopy(t, free.position, free.frame, theta0)
        np.testing.assert_allclose(along.frame, rotation_z(t * (turned - theta0)) @ free.frame, atol=1e-12)
        short = dataclasses.replace(end, rotation=jnp.asarray(jnp.nan)).homotopy(t, free.position, free.frame, theta0)
        assert float(twist_angle(short.frame @ free.frame.T)) == pytest.approx(t * 2 * np.pi * 0.3, abs=1e-9)
