"""fit_stiffness_linear (the closed-form fit from full local vectors) against numpy's
weighted linear least squares on a design matrix built here, and its errors.  (Its
agreement with fit_stiffness on noise-free helices: tests/test_fit_pipeline.py.)"""

import numpy as np
import pytest
from helpers import random_rods

import helixrod as hr

STIFFNESS = ("K1", "K2", "K3", "K13", "K23")


def design(v, sigma):
    """Rows m1, m2, m3 of every point of m = K v over the columns K1, K2, K3, K13, K23."""
    z = np.zeros(len(v))
    rows = [np.stack([v[:, 0], z, z, v[:, 2], z], 1), np.stack([z, v[:, 1], z, z, v[:, 2]], 1),
            np.stack([z, z, v[:, 2], v[:, 0], v[:, 1]], 1)]
    return np.concatenate([r / sigma for r in rows])


def test_matches_numpy_weighted_least_squares(rng):
    rod = random_rods(rng, 1)[0]
    u = rng.normal(size=(30, 3))
    sigma = 0.05
    m = np.asarray(rod.moment(u)) + sigma * rng.normal(size=u.shape)
    fit = hr.fit_stiffness_linear(u, m, m_sigma=sigma, uhat=rod.uhat)
    A = design(u - np.asarray(rod.uhat), sigma)
    b = np.concatenate([m[:, 0], m[:, 1], m[:, 2]]) / sigma
    theta = np.linalg.solve(A.T @ A, A.T @ b)
    covariance = np.linalg.inv(A.T @ A)
    assert fit.names == STIFFNESS and fit.method == "linear" and fit.ok
    np.testing.assert_allclose([float(fit.params[n]) for n in STIFFNESS], theta, rtol=1e-10)
    np.testing.assert_allclose([float(fit.stderr[n]) for n in STIFFNESS], np.sqrt(np.diag(covariance)), rtol=1e-8)
    np.testing.assert_allclose(fit.covariance, covariance, rtol=1e-8, atol=1e-12 * np.abs(covariance).max())
    np.testing.assert_allclose(fit.cost, 0.5 * np.sum((A @ theta - b) ** 2), rtol=1e-10)
    np.testing.assert_allclose(fit.predicted["moment"], np.asarray(fit.rod.moment(u)), rtol=1e-12)
    # Noise of 0.05 on 90 moment components: the truth within 4 standard errors.
    truth = np.array([float(getattr(rod, n)) for n in STIFFNESS])
    assert np.all(np.abs(theta - truth) < 4 * np.sqrt(np.diag(covariance)))


def test_bad_input():
    with pytest.raises(ValueError, match=r"shape \(n, 3\)"):
        hr.fit_stiffness_linear(np.ones((3, 2)), np.ones((3, 2)))
    with pytest.raises(ValueError, match=r"non-finite values in rows \[1\]"):
        hr.fit_stiffness_linear(np.array([[1.0, 0, 0], [np.nan, 0, 0]]), np.ones((2, 3)))
    with pytest.raises(ValueError, match="m_sigma must be > 0"):
        hr.fit_stiffness_linear(np.ones((2, 3)), np.ones((2, 3)), m_sigma=0.0)
    with pytest.raises(ValueError, match="either uhat"):
        hr.fit_stiffness_linear(np.ones((2, 3)), np.ones((2, 3)), uhat=(0, 0, 0), fit_uhat=True)
