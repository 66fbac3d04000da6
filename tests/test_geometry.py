"""Helix geometry: conversions, the centreline, the exact helix frame, and the unloaded
rod's canonical placement -- against closed forms and automatic derivatives."""

import jax
import jax.numpy as jnp
import numpy as np
from helpers import KIRCHHOFF_EQ as EQ, SPRING, SPRING_NORM, SPRING_TURN

import helixrod as hr

# The helix of tests/test_kirchhoff.py: (kappa, tau) = (1, 0.5), slot 0.
KAPPA, TAU, PHI = 1.0, 0.5, EQ.phi[0]


def test_round_trips(rng):
    kappa = jnp.asarray(rng.uniform(0.01, 3, 20))
    tau = jnp.asarray(rng.uniform(-3, 3, 20))
    np.testing.assert_allclose(hr.curvature_torsion(*hr.radius_pitch(kappa, tau)), (kappa, tau), rtol=1e-13)
    np.testing.assert_allclose(hr.from_polar(*hr.to_polar(kappa, tau)), (kappa, tau), rtol=1e-13, atol=1e-15)
    r, _ = hr.radius_pitch(kappa, tau)
    np.testing.assert_allclose(hr.from_radius_angle(r, hr.pitch_angle(kappa, tau)), (kappa, tau), rtol=1e-12)
    np.testing.assert_allclose(hr.helix_angle(kappa, tau) + hr.pitch_angle(kappa, tau), np.pi / 2, rtol=1e-14)


def test_centreline_is_unit_speed_with_given_curvature_torsion():
    kappa, tau = 0.7, -0.4
    s = jnp.linspace(0.0, 5.0, 7)
    d1 = jax.vmap(jax.jacfwd(lambda x: hr.helix_centreline(kappa, tau, x)))(s)
    d2 = jax.vmap(jax.jacfwd(jax.jacfwd(lambda x: hr.helix_centreline(kappa, tau, x))))(s)
    d3 = jax.vmap(jax.jacfwd(jax.jacfwd(jax.jacfwd(lambda x: hr.helix_centreline(kappa, tau, x)))))(s)
    np.testing.assert_allclose(jnp.linalg.norm(d1, axis=-1), 1.0, rtol=1e-14)
    np.testing.assert_allclose(jnp.linalg.norm(d2, axis=-1), kappa, rtol=1e-13)
    torsion = jnp.einsum("ni,ni->n", jnp.cross(d1, d2), d3) / kappa**2
    np.testing.assert_allclose(torsion, tau, rtol=1e-12)
    height, turns = hr.height_and_turns(kappa, tau, 10.0)
    x = hr.helix_centreline(kappa, tau, jnp.array([0.0, 10.0]))
    np.testing.assert_allclose(x[1, 2] - x[0, 2], height, rtol=1e-13)
    np.testing.assert_allclose(turns, 10.0 * np.hypot(kappa, tau) / (2 * np.pi), rtol=1e-14)


def test_helix_frame_solves_frame_equation():
    s = 0.7
    D = hr.helix_frame(KAPPA, TAU, PHI, s)
    dD = jax.jacfwd(lambda t: hr.helix_frame(KAPPA, TAU, PHI, t))(s)
    u1, u2, u3 = np.asarray(EQ.u[0])
    np.testing.assert_allclose(dD, D @ np.array([[0, -u3, u2], [u3, 0, -u1], [-u2, u1, 0]]), atol=1e-13)
    np.testing.assert_allclose(D[:, 2], jax.jacfwd(lambda t: hr.helix_centreline(KAPPA, TAU, t))(s), atol=1e-13)
    np.testing.assert_allclose(D.T @ D, np.eye(3), atol=1e-15)


def test_unloaded_placement_and_observables():
    """The unloaded spring's extension and rotation in closed form; the placement is
    differentiable at the edges: straight (kappa = 0) and straight untwisted rods."""
    length = 2.5 * SPRING_TURN
    h0, theta0 = (float(a) for a in hr.unloaded_observables(SPRING, length))
    np.testing.assert_allclose([h0, theta0], [length * 0.3 / SPRING_NORM, length * SPRING_NORM], rtol=1e-14)
    for uhat in ((0.0, 0.0, 0.0), (0.0, 0.0, 0.5)):
        def placement(u):
            rod = hr.Rod(1.0, 1.0, 0.8, uhat=u)
            x, frame = hr.unloaded_state(rod, 2.0)
            return jnp.concatenate([x, frame.ravel(), jnp.stack(hr.unloaded_observables(rod, 2.0))])

        np.testing.assert_allclose(placement(jnp.asarray(uhat))[:3], (0.0, 0.0, 2.0), atol=1e-15)
        assert bool(jnp.all(jnp.isfinite(jax.jacfwd(placement)(jnp.asarray(uhat)))))
