import jax
import jax.numpy as jnp
import numpy as np

import helixrod as hr


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
