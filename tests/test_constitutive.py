"""StrainEnergyRod (a general convex strain energy): the quadratic energy reproduces `Rod`,
implicit derivatives of the inverse law, and solve_static with a quartic energy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import KIRCHHOFF_ROD as ROD, N1

import helixrod as hr


@pytest.mark.heavy  # Newton inside every stage: ~10 s, most of it compiling
def test_strain_energy_rod():
    K = ROD.K
    quadratic = hr.StrainEnergyRod(lambda v: 0.5 * v @ K @ v, uhat=ROD.uhat)
    m = jnp.array([0.3, -0.2, 0.5])
    np.testing.assert_allclose(quadratic.twist(m), ROD.twist(m), atol=1e-14)
    # Implicit derivative of the Newton solve: du/dm = K^-1.
    np.testing.assert_allclose(jax.jacfwd(quadratic.twist)(m), np.linalg.inv(np.asarray(K)), atol=1e-12)
    quartic = hr.StrainEnergyRod(lambda v: 0.5 * v @ K @ v + 0.2 * (v @ v) ** 2, uhat=ROD.uhat)
    u = jnp.array([[0.4, 0.9, 1.3], [-0.5, 0.2, 0.1]])
    np.testing.assert_allclose(quartic.twist(quartic.moment(u)), u, atol=1e-13)
    np.testing.assert_allclose(quartic.moment(u[0]), jax.grad(lambda x: quartic.energy(x))(u[0]), atol=1e-14)
    sol = hr.solve_static(quartic, N1, m, 6.0, saveat=jnp.linspace(0.0, 6.0, 4))
    assert bool(sol.ok)
    assert float(jnp.abs(sol.drift).max()) < 1e-9
    assert float(jnp.abs(sol.m[-1] - m).max()) > 1e-2  # it moved
