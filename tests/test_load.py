import jax
import jax.numpy as jnp
import numpy as np
import pytest

import helixrod as hr


@pytest.mark.heavy
def test_round_trip_with_helix_equilibria():
    rod = hr.Rod(1.0, 1.5, 0.8, 0.5, 0.5, (1.0, 0.0, 0.0))
    for kappa, tau in [(0.9, 0.7), (2.0, -1.2)]:
        eq = hr.helix_equilibria(rod, kappa, tau)
        for s in np.flatnonzero(np.asarray(eq.valid))[:2]:
            sol = hr.helices_under_load(rod, eq.force[s], eq.moment[s], kappa_max=3.0, tau_range=(-3.0, 3.0))
            assert int(sol.count) >= 1
            dist = np.hypot(np.asarray(sol.kappa) - kappa, np.asarray(sol.tau) - tau)
            hit = np.nanargmin(dist)
            assert dist[hit] < 1e-9 and int(sol.slot[hit]) == s
            v = np.asarray(sol.valid)
            np.testing.assert_allclose(np.asarray(sol.force)[v], float(eq.force[s]), rtol=1e-8, atol=1e-9)
            np.testing.assert_allclose(np.asarray(sol.moment)[v], float(eq.moment[s]), rtol=1e-8, atol=1e-9)


def test_bad_box_is_an_error():
    rod = hr.Rod(1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="kappa_max"):
        hr.helices_under_load(rod, 1.0, 1.0, kappa_max=-1.0, tau_range=(0.0, 1.0))
    for box in ((np.inf, (0.0, 1.0)), (1.0, (0.0, np.nan))):
        with pytest.raises(ValueError, match="kappa_max and tau_range must be finite"):
            hr.helices_under_load(rod, 1.0, 1.0, kappa_max=box[0], tau_range=box[1])
    with pytest.raises(ValueError, match="force and moment must be finite"):
        hr.helices_under_load(rod, np.nan, 1.0, kappa_max=1.0, tau_range=(0.0, 1.0))


def test_a_bad_wrench_in_a_batch_is_flagged_not_a_finding():
    rod = hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
    found = jax.vmap(lambda F: hr.helices_under_load(rod, F, 0.81, kappa_max=3.0, tau_range=(-3.0, 3.0)))(jnp.array([-0.49, jnp.nan]))
    alone = hr.helices_under_load(rod, -0.49, 0.81, kappa_max=3.0, tau_range=(-3.0, 3.0))
    assert found.valid_input.tolist() == [True, False] and bool(alone.valid_input)
    assert int(found.count[0]) == int(alone.count) > 0 and int(found.count[1]) == 0
