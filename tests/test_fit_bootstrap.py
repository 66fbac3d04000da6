"""bootstrap: parametric replicates of a helix fit bracket it, and their spread agrees with
the Gauss-Newton standard errors (the fit: the configuration of tests/test_fit_pipeline.py)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import EIV_UHAT, eiv_helix_data, fit_grid, random_rods

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


def test_parametric_replicates_with_errors_in_variables_spread_as_the_standard_errors():
    """With errors in variables the parametric replicates redraw each (F, M) pair with its
    effective covariance (the errors of kappa and tau propagated), so their spread matches
    the fit's standard errors (200 replicates: ~5 % sampling error of a spread); drawn with
    the sigmas of F and M alone it was about half of them.  Every replicate holds the
    weights of the fit's solution."""
    data = eiv_helix_data()
    fit = hr.fit_stiffness(data, uhat=EIV_UHAT)
    assert fit.ok, fit.message
    for kind in ("parametric", "cases"):
        boot = hr.bootstrap(data, fit, 200, jax.random.key(5), kind=kind, progress=False)
        assert bool(np.all(np.asarray(boot.ok)))
        ratio = np.array([float(boot.std[name]) / float(fit.stderr[name]) for name in fit.names])
        assert np.all((0.75 < ratio) & (ratio < 1.3)), (kind, ratio)


def test_bootstrap_arguments_are_checked_before_refitting():
    """A fractional count, an integer seed for a key and a percentage for a level raise
    ValueErrors that name them (they were truncated, or failed inside JAX or NumPy)."""
    rng = np.random.default_rng(0)
    kappa, tau = rng.uniform(0.3, 2.5, 12), rng.uniform(-2.0, 2.0, 12)
    data = hr.synthetic_helix_data(hr.Rod(1.0, 1.5, 0.8), kappa, tau, 0.01, jax.random.key(0))
    fit = hr.fit_stiffness(data, uhat=(0.0, 0.0, 0.0), n_starts=2)
    with pytest.raises(ValueError, match="bootstrap: n must be an integer >= 2, got 2.5"):
        hr.bootstrap(data, fit, 2.5, jax.random.key(0))
    with pytest.raises(ValueError, match="bootstrap: key must be one JAX random key"):
        hr.bootstrap(data, fit, 4, 5)
    boot = hr.bootstrap(data, fit, 4, jax.random.key(0))
    with pytest.raises(ValueError, match=r"interval: level must be in \(0, 1\)"):
        boot.interval(95)
