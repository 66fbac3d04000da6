"""The bulk (uniform) helix of a finite rod under two axial controls (bulk_helix): every pair
of controls reproduces the other two observables of one helix, each helix checked against
the balance equations (`helix_residual`) and the axial observables computed here from its
twist; bad pairs and failures.  A force and moment given are solved for the twist alone
(the multipliers eliminated), the other pairs for twist and multipliers: the pairs'
agreement checks the one solve against the other."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import BVP_ROD, SPRING, SPRING_TURN as TURN

import helixrod as hr
from helixrod._bvp import AXIAL_CONTROLS, AXIAL_OBSERVABLES

PAIRS = (("force", "moment"), ("force", "rotation"), ("extension", "rotation"))
OBSERVABLES = ("force", "moment", "extension", "rotation")


def test_the_table_of_pairs():
    assert AXIAL_OBSERVABLES == OBSERVABLES
    assert set(AXIAL_CONTROLS) == {"-".join(pair) for pair in PAIRS}


def observables(rod, length, bulk):
    """(F, M, h, Theta) of the uniform helix `bulk.u` of `rod`, from its twist and the
    multipliers: n = mu2 u, F = n . a, M = m . a with a = u/|u|, h = L u3/|u|, Theta = L|u|."""
    u = np.asarray(bulk.u)
    a = u / np.linalg.norm(u)
    n = float(bulk.mu2) * u
    m = np.asarray(rod.moment(bulk.u))
    return np.array([n @ a, m @ a, length * a[2], length * np.linalg.norm(u)])


@pytest.mark.parametrize("rod", [SPRING, BVP_ROD], ids=["spring", "coupled"])
def test_every_pair_reproduces_the_same_helix(rod):
    length = 2 * TURN
    h0, theta0 = (float(a) for a in hr.unloaded_observables(rod, length))
    first = hr.bulk_helix(rod, length, extension=1.1 * h0, rotation=theta0 + 0.3)
    assert bool(first.ok)
    # An equilibrium: m = mu1 u + mu2 e3 (helix_residual), with the observables it reports.
    np.testing.assert_allclose(hr.helix_residual(rod, first.u, first.mu2 * first.u), 0.0, atol=1e-12)
    expected = observables(rod, length, first)
    np.testing.assert_allclose(first.observables, expected, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose([first.extension, first.rotation], [1.1 * h0, theta0 + 0.3], rtol=1e-12)
    assert abs(float(first.force)) > 1e-3 and abs(float(first.moment)) > 1e-3  # loaded
    for pair in PAIRS:
        given = {name: float(expected[OBSERVABLES.index(name)]) for name in pair}
        bulk = hr.bulk_helix(rod, length, **given)
        assert bool(bulk.ok), pair
        np.testing.assert_allclose(bulk.u, first.u, rtol=1e-9, atol=1e-12, err_msg=str(pair))
        np.testing.assert_allclose(bulk.observables, expected, rtol=1e-9, atol=1e-12, err_msg=str(pair))


def test_bad_pairs_raise():
    for given in ({"force": 1.0, "extension": 2.0}, {"moment": 0.1, "extension": 2.0}, {"moment": 0.1, "rotation": 1.0},
                  {"force": 1.0}, {}, {"force": 1.0, "moment": 0.0, "rotation": 1.0}):
        with pytest.raises(ValueError, match="bulk_helix: give one of the pairs"):
            hr.bulk_helix(SPRING, 10.0, **given)
    with pytest.raises(ValueError, match="bulk_helix: length must be finite and > 0"):
        hr.bulk_helix(SPRING, 0.0, force=0.0, moment=0.0)
    with pytest.raises(ValueError, match="bulk_helix: moment must be finite"):
        hr.bulk_helix(SPRING, 10.0, force=0.0, moment=np.nan)
    # A guess is checked as the controls are (a NaN one was a SolverError from the solve).
    with pytest.raises(ValueError, match="bulk_helix: guess u must be finite"):
        hr.bulk_helix(SPRING, 10.0, force=0.0, moment=0.0, guess=((np.nan, 1.0, 0.3), 0.0, 0.0))
    with pytest.raises(ValueError, match="bulk_helix: guess mu2 must be finite"):
        hr.bulk_helix(SPRING, 10.0, force=0.0, moment=0.0, guess=((0.0, 1.0, 0.3), 0.0, np.inf))
    with pytest.raises(ValueError, match=r"bulk_helix: guess must be \(u, mu1, mu2\)"):
        hr.bulk_helix(SPRING, 10.0, force=0.0, moment=0.0, guess=(0.0, 1.0))


def test_throw_false_reports_a_failure_in_ok():
    """An extension longer than the rod has no helix: `ok` is False with throw=False, a
    SolverError with throw=True; a solvable pair is `ok`."""
    length = 2 * TURN
    theta0 = float(hr.unloaded_observables(SPRING, length)[1])
    bad = hr.bulk_helix(SPRING, length, extension=1.5 * length, rotation=theta0, throw=False)
    assert not bool(bad.ok) and hr.RESULTS[bad.result]
    with pytest.raises(hr.SolverError, match="bulk_helix"):
        hr.bulk_helix(SPRING, length, extension=1.5 * length, rotation=theta0)
    good = hr.bulk_helix(SPRING, length, force=0.01, moment=0.0, throw=False)
    assert bool(good.ok) and good.result == hr.RESULTS.successful


def test_the_straight_twisted_rod_at_its_bifurcation():
    """At F = -K1 u3^2 (no moment) helices branch off the straight twisted rod, and the
    balance's Jacobian is singular there: the straight rod is still the answer (the guess
    is the root), under the force-moment pair that exposes it to the user at a plain force
    grid; under force-rotation Newton's step lands on it and then meets the singular
    Jacobian: the error says so."""
    rod = hr.Rod(1.0, 1.0, 0.8, uhat=(0.0, 0.0, 1.0))
    for force in (-1.0, -1.0 + 1e-6, -1.2):
        bulk = hr.bulk_helix(rod, 2.0, force=force, moment=0.0)
        np.testing.assert_allclose(bulk.u, [0.0, 0.0, 1.0], atol=1e-15)
        np.testing.assert_allclose([bulk.extension, bulk.rotation], [2.0, 2.0], atol=1e-15)
    with pytest.raises(hr.SolverError, match="singular Jacobian, a bifurcation of the uniform helices"):
        hr.bulk_helix(rod, 1.0, force=-1.0, rotation=1.0)


def test_an_intrinsically_straight_rod_twisted_is_its_own_bulk_state():
    """An intrinsically straight, untwisted rod (uhat = 0): its unloaded guess u = 0 is no
    helix (the multipliers' 1/|u| is singular, Newton's first step was NaN, every pair
    failed and the curves' bulk columns were NaN); the guess is now the straight rod twisted
    as the controls say, which is the bulk state: u = (0, 0, Theta/L), M = K3 Theta/L."""
    rod = hr.Rod(1.0, 1.5, 0.8)
    for pair in (dict(force=1.0, rotation=3.0), dict(force=1.0, moment=2.4), dict(force=-0.5, rotation=3.0)):
        bulk = hr.bulk_helix(rod, 1.0, **pair)
        np.testing.assert_allclose(bulk.u, [0.0, 0.0, 3.0], atol=1e-12)
        np.testing.assert_allclose([bulk.extension, bulk.rotation, bulk.moment], [1.0, 3.0, 0.8 * 3.0], atol=1e-12)


def test_a_bad_traced_length_is_flagged_in_every_pair():
    for controls in ({"force": 0.02, "moment": 0.01}, {"force": 0.02, "rotation": 31.0}, {"extension": 9.0, "rotation": 31.0}):
        batch = jax.vmap(lambda L: hr.bulk_helix(SPRING, L, throw=False, **controls))(jnp.array([30.0, -1.0, jnp.inf, jnp.nan]))
        assert batch.ok.tolist() == [True, False, False, False], controls
        assert (batch.result == hr.RESULTS.invalid_input).tolist() == [False, True, True, True]
        assert np.all(np.isnan(np.asarray(batch.extension[1:]))) and np.all(np.isnan(np.asarray(batch.u[1:])))
        np.testing.assert_allclose(batch.extension[0], hr.bulk_helix(SPRING, 30.0, **controls).extension, rtol=1e-13)


def test_frozen_root_derivatives_are_the_implicit_functions_to_second_order():
    """`bulk_helix_at(..., newton_derivatives=True)` (a Newton iteration without
    derivatives, then the implicit function theorem to any order): its first derivatives
    in the loads and a stiffness equal those of optimistix's implicit Newton solve, in
    forward and reverse mode, and its second derivatives (forward over forward, reverse
    over forward) central differences of its first."""
    import jax
    import jax.numpy as jnp

    from helixrod._bvp._bulk import bulk_helix_at

    index = np.array([AXIAL_OBSERVABLES.index("force"), AXIAL_OBSERVABLES.index("moment")])
    length = 2 * TURN

    def observed(x, frozen):
        rod = hr.Rod(SPRING.K1, x[2], SPRING.K3, 0.0, 0.0, SPRING.uhat)
        values = jnp.stack([x[0], x[1], 0.0, 0.0])
        if frozen:
            trial = bulk_helix_at(rod, length, index, values, max_steps=32, light=True)
            bulk = bulk_helix_at(rod, length, index, values, (trial.u, trial.mu1, trial.mu2), max_steps=0, newton_derivatives=True)
        else:
            bulk = bulk_helix_at(rod, length, index, values)
        return jnp.stack([bulk.extension, bulk.rotation])

    x = jnp.array([0.3 * float(SPRING.K1) / TURN**2, 0.1 * float(SPRING.K1) / TURN, 1.1 * float(SPRING.K2)])
    first = jax.jit(jax.jacfwd(lambda x: observed(x, True)))
    reference = jax.jit(jax.jacfwd(lambda x: observed(x, False)))(x)
    np.testing.assert_allclose(first(x), reference, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(jax.jit(jax.jacrev(lambda x: observed(x, True)))(x), reference, rtol=1e-9, atol=1e-12)
    second = jax.jit(jax.jacfwd(jax.jacfwd(lambda x: observed(x, True))))(x)
    np.testing.assert_allclose(jax.jit(jax.jacrev(jax.jacfwd(lambda x: observed(x, True))))(x), second, rtol=1e-9, atol=1e-12)
    for i in range(3):
        h = 1e-4 * float(jnp.abs(x[i]))
        step = jnp.zeros(3).at[i].set(h)
        central = (first(x + step) - first(x - step)) / (2 * h)
        np.testing.assert_allclose(second[..., i], central, rtol=1e-5, atol=1e-9 * float(jnp.max(jnp.abs(second))))


def test_force_and_moment_without_multipliers_is_the_five_unknown_solve():
    """Under a known force and moment `bulk_helix_at` solves three equations in u (the
    multipliers eliminated); with the pair traced it solves the five in (u, mu1, mu2).
    Same helix, same multipliers and observables, and the same first and second
    derivatives in the loads and a stiffness (`newton_derivatives`, as the tweezer model
    differentiates it)."""
    import jax
    import jax.numpy as jnp

    from helixrod._bvp._bulk import bulk_helix_at

    index = np.array([OBSERVABLES.index("force"), OBSERVABLES.index("moment")])
    length = 2 * TURN

    def helix(x, index):
        rod = hr.Rod(BVP_ROD.K1, x[2], BVP_ROD.K3, BVP_ROD.K13, BVP_ROD.K23, BVP_ROD.uhat)
        values = jnp.stack([x[0], x[1], 0.0, 0.0])
        trial = bulk_helix_at(rod, length, index, values, max_steps=32, light=True)
        bulk = bulk_helix_at(rod, length, index, values, (trial.u, trial.mu1, trial.mu2), max_steps=0, newton_derivatives=True)
        return jnp.concatenate([bulk.u, jnp.stack([bulk.mu1, bulk.mu2]), bulk.observables])

    reduced = jax.jit(lambda x: helix(x, index))
    general = jax.jit(helix)  # the pair traced: five unknowns
    x = jnp.array([0.3 * float(BVP_ROD.K1) / TURN**2, 0.1 * float(BVP_ROD.K1) / TURN, 1.1 * float(BVP_ROD.K2)])
    np.testing.assert_allclose(reduced(x), general(x, jnp.asarray(index)), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(reduced(x)[5:7], x[:2], rtol=1e-12)  # the loads it was given
    for order in (jax.jacfwd, lambda f: jax.jacfwd(jax.jacfwd(f))):
        expected = order(lambda x: general(x, jnp.asarray(index)))(x)
        np.testing.assert_allclose(order(reduced)(x), expected, rtol=1e-8, atol=1e-10 * float(jnp.max(jnp.abs(expected))))
