"""bootstrap: parametric replicates of a helix fit bracket it, and their spread agrees with
the Gauss-Newton standard errors (the fit: the configuration of tests/test_fit_pipeline.py)."""

import jax
import jax.numpy as jnp
import pytest
from helpers import fit_grid, random_rods

import helixrod as hr


@pytest.mark.heavy
def test_bootstrap_brackets_fit(rng):
    kappa, tau = fit_grid(rng)
    rod = random_rods(rng, 1)[0]
    data = hr.synthetic_helix_data(rod, kappa, tau, 0.02, jax.random.key(3))
    fit = hr.fit_stiffness(data, uhat=rod.uhat)
    boot = hr.bootstrap(data, fit, 16, jax.random.key(4), kind="parametric")
    assert float(jnp.mean(boot.ok)) >= 0.9
    for name in fit.names:
        lo, hi = boot.interval(0.95)[name]
        assert lo <= float(fit.params[name]) <= hi
        # parametric bootstrap spread agrees with the Gauss-Newton stderr within sampling error
        ratio = float(boot.std[name]) / float(fit.stderr[name])
        assert 0.4 < ratio < 2.0, (name, ratio)
