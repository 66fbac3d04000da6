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


def test_helix_solvers_name_the_law_they_need():
    """The helix solvers find the registers of the quadratic energy in closed form: a
    general law gets a clear error naming the function (not an AttributeError from inside)."""
    rod = hr.StrainEnergyRod(lambda v: 0.5 * v @ v + 0.1 * v[0] ** 4, uhat=(1.0, 0.0, 0.0))
    calls = {
        "helix_equilibria": lambda: hr.helix_equilibria(rod, 1.0, 0.5),
        "helices_under_load": lambda: hr.helices_under_load(rod, 0.1, 0.1, kappa_max=2.0, tau_range=(-1.0, 1.0)),
        "straight_family": lambda: hr.straight_family(rod, 0.1),
        "pure_moment_family": lambda: hr.pure_moment_family(rod, 0.1),
        "synthetic_helix_data": lambda: hr.synthetic_helix_data(rod, [1.0], [0.5], 0.01, jax.random.key(0)),
        "sweep": lambda: hr.sweep(rod, np.linspace(0.1, 1.0, 3), np.linspace(-1.0, 1.0, 3)),
        "stability_atlas": lambda: hr.stability_atlas(rod, [0.5], [0.3], 5.0),
    }
    for name, call in calls.items():
        with pytest.raises(ValueError, match=f"{name}: rod must be a helixrod.Rod, got StrainEnergyRod"):
            call()


@pytest.mark.heavy  # a Newton solve of the inverse law inside every stage: ~20 s compiling
def test_strain_energy_rod_in_the_finite_rod_solver():
    """A `StrainEnergyRod` goes through the programs of `solve_boundary_value` (whose
    arguments are arrays: the energy is part of the rod's structure) and, for the quadratic
    energy, gives the `Rod`'s equilibrium, stability and bulk helix."""
    rod = hr.Rod(1.0, 1.0, 1 / 1.3, uhat=(0.0, 1.0, 0.3))
    K = rod.K
    law = hr.StrainEnergyRod(lambda v: 0.5 * v @ K @ v, uhat=rod.uhat)
    length = 8.0
    theta0 = float(hr.unloaded_observables(rod, length)[1])
    solved = []
    for r in (rod, law):
        start, end = hr.axial_ends(r, length, extension=4.0, rotation=theta0 + 0.3)
        sol = hr.solve_boundary_value(r, length, start=start, end=end)
        bulk = hr.bulk_helix(r, length, force=0.05, rotation=theta0)
        solved.append((sol, bulk))
    (sol_rod, bulk_rod), (sol_law, bulk_law) = solved
    assert bool(sol_law.ok) and int(sol_law.instability_index) == int(sol_rod.instability_index) == 0
    np.testing.assert_allclose(sol_law.force, sol_rod.force, atol=1e-9)
    np.testing.assert_allclose(sol_law.stability_margin, sol_rod.stability_margin, rtol=1e-7)
    np.testing.assert_allclose(bulk_law.extension, bulk_rod.extension, rtol=1e-10)
