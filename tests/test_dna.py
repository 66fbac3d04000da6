"""helixrod.dna against hand values: thermal energy and persistence lengths, the B-DNA
helix, observables <-> helix round trips and changes relative to B-DNA, and bad input
(raised when concrete, NaN when traced)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from helixrod import dna


# -- units -------------------------------------------------------------------------------
def test_kT_and_persistence_lengths():
    # k_B T at 298.15 K: 1.380649e-23 J/K * 298.15 K = 4.1164049935e-21 J (exact decimal).
    assert float(dna.kT(298.15)) == pytest.approx(4.1164049935, rel=1e-14)
    assert float(dna.kT(293.15, unit="J")) == pytest.approx(4.0473725435e-21, rel=1e-14)
    assert dna.PN_NM == pytest.approx(1e-21, rel=1e-15)
    # Twist modulus 410 pN nm^2 at 25 C is a twist persistence of 99.60 nm.
    assert float(dna.persistence_length(410.0)) == pytest.approx(410.0 / 4.1164049935, rel=1e-14)
    assert float(dna.stiffness_from_persistence(50.0, 310.15)) == pytest.approx(50 * 1.380649e-2 * 310.15, rel=1e-14)
    x = jnp.array([50.0, 100.0])
    np.testing.assert_allclose(dna.persistence_length(dna.stiffness_from_persistence(x)), x, rtol=1e-15)
    assert float(dna.turns_to_radians(dna.radians_to_turns(1.25))) == pytest.approx(1.25, rel=1e-15)
    with pytest.raises(ValueError, match="temperature"):
        dna.kT(-3.0)
    with pytest.raises(ValueError, match="unit"):
        dna.kT(300.0, unit="kcal")


# -- B-DNA helix -------------------------------------------------------------------------
def test_bdna_geometry_hand_values():
    kappa, tau, ell = (float(x) for x in dna.helix_from_bdna())
    # By hand: p = 0.34*10.5/(2 pi) = 0.568183 nm, r^2 + p^2 = 1.322832 nm^2,
    # kappa = 1/1.322832, tau = 0.568183/1.322832, ell = sqrt(0.34^2 + (2 pi/10.5)^2).
    assert kappa == pytest.approx(0.755954, abs=1e-6)
    assert tau == pytest.approx(0.429520, abs=1e-6)
    assert ell == pytest.approx(0.688245, abs=1e-6)
    p = 0.34 * 10.5 / (2 * math.pi)
    assert kappa == pytest.approx(1 / (1 + p * p), rel=1e-14)
    assert tau == pytest.approx(p / (1 + p * p), rel=1e-14)
    # Per base pair: rise 0.34 nm and twist 360/10.5 = 34.2857 degrees.
    rise, rotation = (float(x) for x in dna.tweezer_from_helix(kappa, tau))
    assert rise == pytest.approx(0.34, rel=1e-14)
    assert math.degrees(rotation) == pytest.approx(360 / 10.5, rel=1e-14)
    back = dna.bdna_from_helix(*dna.helix_from_bdna(rise=0.28, bp_per_turn=11.0, radius=0.9))
    np.testing.assert_allclose([float(b) for b in back], [0.28, 11.0, 0.9], rtol=1e-14)
    with pytest.raises(ValueError, match="rise"):
        dna.helix_from_bdna(rise=-0.34)
    # Traced: the bad point is NaN, the good one untouched.
    k, t, ell = jax.jit(dna.helix_from_bdna)(jnp.array([0.34, -0.34]))
    assert np.isfinite(k[0]) and np.isnan(k[1]) and np.isnan(ell[1])
    assert np.isnan(jax.jit(dna.kT)(jnp.array([300.0, -1.0]))[1])


# -- observables <-> helix -----------------------------------------------------------------
def test_observables_round_trip(rng):
    kappa = rng.uniform(0.05, 2.0, 50)
    tau = rng.uniform(-2.0, 2.0, 50)
    length = rng.uniform(0.1, 100.0, 50)
    h, theta = dna.observables_from_helix(kappa, tau, length)
    norm = np.hypot(kappa, tau)
    np.testing.assert_allclose(h, length * tau / norm, rtol=1e-14)
    np.testing.assert_allclose(theta, length * norm, rtol=1e-14)
    k2, t2 = dna.helix_from_observables(h, theta, length)
    np.testing.assert_allclose(k2, kappa, rtol=1e-12)
    np.testing.assert_allclose(t2, tau, rtol=1e-12, atol=1e-14)
    # Totals of n_bp base pairs are n_bp times the per-bp values, and invert.
    e1, r1 = dna.tweezer_from_helix(kappa, tau)
    e5, r5 = dna.tweezer_from_helix(kappa, tau, n_bp=5000)
    np.testing.assert_allclose(e5, 5000 * e1, rtol=1e-14)
    np.testing.assert_allclose(r5, 5000 * r1, rtol=1e-14)
    k3, t3 = dna.helix_from_tweezer(e5, r5, n_bp=5000)
    np.testing.assert_allclose(k3, kappa, rtol=1e-12)
    np.testing.assert_allclose(t3, tau, rtol=1e-12, atol=1e-14)


def test_changes_relative_to_bdna():
    # The B-DNA helix itself has no change.
    dh, dlk = dna.changes_from_helix(*dna.helix_from_bdna()[:2], n_bp=1000)
    assert abs(float(dh)) < 1e-12 and abs(float(dlk)) < 1e-12
    # 5 kbp stretched by 20 nm and overwound by 3 turns: by hand, h = 5000*0.34 + 20 nm,
    # Theta = 2 pi (5000/10.5 + 3), on a filament of 5000*ell.
    kappa, tau = dna.helix_from_changes(20.0, 3.0, n_bp=5000)
    ell = float(dna.helix_from_bdna()[2])
    h, theta = dna.observables_from_helix(kappa, tau, 5000 * ell)
    assert float(h) == pytest.approx(1720.0, rel=1e-13)
    assert float(theta) == pytest.approx(2 * math.pi * (5000 / 10.5 + 3), rel=1e-13)
    dh, dlk = dna.changes_from_helix(kappa, tau, n_bp=5000)
    assert float(dh) == pytest.approx(20.0, rel=1e-10)
    assert float(dlk) == pytest.approx(3.0, rel=1e-10)


def test_observables_bad_input():
    with pytest.raises(ValueError, match="extension"):
        dna.helix_from_observables(2.0, 1.0, 1.5)  # longer than the filament
    with pytest.raises(ValueError, match="rotation > 0"):
        dna.helix_from_observables(0.5, -1.0, 1.0)
    # Traced: flagged as NaN, never raised, neighbours untouched; gradients finite.
    k, t = jax.jit(dna.helix_from_observables)(jnp.array([0.5, 2.0]), jnp.array([1.0, 1.0]), 1.5)
    assert np.isfinite(k[0]) and np.isnan(k[1]) and np.isnan(t[1])
    g = jax.grad(lambda h: dna.helix_from_observables(h, 1.0, 1.0)[0])(0.3)
    assert np.isfinite(g)


def test_non_physical_parameters_raise_or_give_nan():
    kappa0, tau0, ell = dna.helix_from_bdna()
    concrete = (
        (lambda: dna.persistence_length(-410.0), "persistence_length: stiffness must be finite and > 0"),
        (lambda: dna.stiffness_from_persistence(0.0), "stiffness_from_persistence: length must be finite and > 0"),
        (lambda: dna.bdna_from_helix(0.0, 0.0, 1.0), "bdna_from_helix: need a helix"),
        (lambda: dna.bdna_from_helix(kappa0, tau0, -ell), "bdna_from_helix: need a helix"),
        (lambda: dna.tweezer_from_helix(kappa0, tau0, n_bp=-5), "tweezer_from_helix: n_bp and length_per_bp"),
        (lambda: dna.helix_from_tweezer(1.0, 1.0, n_bp=0), "helix_from_tweezer: n_bp and length_per_bp"),
        (lambda: dna.wlc_force(0.5, -50.0), "wlc_force: persistence_length must be finite and > 0"),
        (lambda: dna.wlc_extension(1.0, 0.0), "wlc_extension: persistence_length"),
        (lambda: dna.wlc_free_energy(1.0, np.inf), "wlc_free_energy: persistence_length"),
        (lambda: dna.moroz_nelson_twist_modulus(400.0, 1.0, -1.0), "moroz_nelson_twist_modulus: persistence_length"),
        (lambda: dna.moroz_nelson_twist_modulus(-400.0, 1.0), "moroz_nelson_twist_modulus: twist_modulus and force"),
        (lambda: dna.moroz_nelson_twist_modulus(400.0, -1.0), "moroz_nelson_twist_modulus: twist_modulus and force"),
        (lambda: dna.observables_from_helix(0.0, 0.0, 10.0), "observables_from_helix: need a helix"),
        (lambda: dna.observables_from_helix(kappa0, tau0, -10.0), "observables_from_helix: need a helix"),
        (lambda: dna.tweezer_from_helix(0.0, 0.0, 100), "observables_from_helix: need a helix"),
        (lambda: dna.changes_from_helix(kappa0, tau0, -5), "changes_from_helix: n_bp and length_per_bp"),
        (lambda: dna.helix_from_changes(0.0, 0.0, np.nan), "helix_from_changes: n_bp and length_per_bp"),
    )
    for call, message in concrete:
        with pytest.raises(ValueError, match=message):
            call()
    # Traced: NaN at the bad point, its neighbour untouched.
    force = jax.vmap(lambda A: dna.wlc_force(0.5, A))(jnp.array([50.0, -50.0]))
    np.testing.assert_allclose(force[0], dna.wlc_force(0.5, 50.0), rtol=1e-15)
    assert np.isnan(force[1])
    h, _ = jax.vmap(lambda n: dna.tweezer_from_helix(kappa0, tau0, n_bp=n))(jnp.array([10.0, -5.0]))
    np.testing.assert_allclose(h[0], 3.4, rtol=1e-12)  # ten rises of 0.34 nm
    assert np.isnan(h[1])
    rise = jax.vmap(lambda k: dna.bdna_from_helix(k, 0.0 * k, ell)[0])(jnp.array([0.0, kappa0]))
    assert np.isnan(rise[0]) and np.isfinite(rise[1])
    change, _ = jax.vmap(lambda n: dna.changes_from_helix(1.01 * kappa0, tau0, n_bp=n))(jnp.array([100.0, -100.0]))
    assert change[0] == dna.changes_from_helix(1.01 * kappa0, tau0, n_bp=100.0)[0] and np.isnan(change[1])
    modulus = jax.vmap(lambda C: dna.moroz_nelson_twist_modulus(C, 1.0))(jnp.array([400.0, -400.0]))
    assert modulus[0] == dna.moroz_nelson_twist_modulus(400.0, 1.0) and np.isnan(modulus[1])
