"""error_analysis: covariance, standard errors and the identifiability report from a
Jacobian, against numpy's closed form for linear least squares, and its corner cases."""

import numpy as np
from scipy.optimize import curve_fit

import helixrod as hr

STIFFNESS = ("K1", "K2", "K3", "K13", "K23")


def _error_analysis(J):
    values = dict(zip(STIFFNESS, (1.0, 1.5, 0.8, 0.3, 0.2)))
    return hr.error_analysis(J, np.zeros(J.shape[0]), values, np.ones(5), absolute_sigma=True, weak_threshold=0.1)


def test_error_analysis_with_fewer_residuals_than_parameters(rng):
    """One data point gives 2 residuals for 5 stiffnesses: the report runs (it raised an
    IndexError before) and says rank 2, three exact null directions, every stderr infinite."""
    analysis = _error_analysis(rng.normal(size=(2, 5)))
    stderr, ident = analysis.stderr, analysis.identifiability
    assert ident.rank == 2 and ident.weak_stderr.count(np.inf) == 3
    assert all(np.isinf(float(v)) for v in stderr.values())


def test_error_analysis_with_an_unboundedly_sensitive_residual(rng):
    """A residual at a register tangency/cusp has a huge derivative (4.6e16 measured in
    tests/test_stress.py).  Kept in the SVD it made every other direction look null (rank 1,
    all stderr inf); as an exact constraint the error bars are the limit of the weighted
    ones: compared with the same row weighted 1e5 (below the constraint threshold)."""
    J = rng.normal(size=(24, 5))
    row = rng.normal(size=5)
    constrained, weighted = _error_analysis(np.vstack([J, 1e16 * row])), _error_analysis(np.vstack([J, 1e5 * row]))
    ident, plain = constrained.identifiability, weighted.identifiability
    assert ident.rank == 5 and np.isinf(float(ident.singular_values[0])) and "exact constraints" in ident.notes[0]
    assert plain.rank == 5 and not any("exact constraints" in n for n in plain.notes)
    for name in STIFFNESS:
        np.testing.assert_allclose(float(constrained.stderr[name]), float(weighted.stderr[name]), rtol=1e-6)


def test_error_analysis_of_linear_least_squares_matches_numpy_and_curve_fit(rng):
    """y = a + b x + c x^2 with noise sigma: the covariance is inv(J^T J) of the normalised
    Jacobian J = X / sigma (sigma trusted), or that times the reduced chi^2 (sigma relative:
    scipy's curve_fit with absolute_sigma=False); the report's scales (units of the
    parameters) change the report, not the covariance."""
    x = np.linspace(-1.0, 2.0, 40)
    sigma = 0.1 * (1 + x**2)
    y = 0.5 - 1.2 * x + 0.3 * x**2 + sigma * rng.normal(size=x.size)
    X = np.stack([np.ones_like(x), x, x**2], 1)
    J = X / sigma[:, None]
    beta = np.linalg.lstsq(J, y / sigma, rcond=None)[0]
    r = J @ beta - y / sigma
    values = dict(zip(("a", "b", "c"), beta))
    scales = np.array([2.0, 0.5, 3.0])
    trusted = hr.error_analysis(J, r, values, scales, absolute_sigma=True)
    relative = hr.error_analysis(J, r, values, scales, absolute_sigma=False)
    cov = np.linalg.inv(J.T @ J)
    chi2_reduced = float(r @ r) / (x.size - 3)
    np.testing.assert_allclose(trusted.covariance, cov, rtol=1e-10)
    np.testing.assert_allclose(relative.covariance, cov * chi2_reduced, rtol=1e-10)
    np.testing.assert_allclose([float(trusted.stderr[n]) for n in values], np.sqrt(np.diag(cov)), rtol=1e-10)
    np.testing.assert_allclose(trusted.correlation, cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov))), rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose([trusted.cost, trusted.chi2_reduced], [0.5 * float(r @ r), chi2_reduced], rtol=1e-12)
    # scipy's curve_fit on the same model and data.
    popt, pcov_abs = curve_fit(lambda x, a, b, c: a + b * x + c * x**2, x, y, sigma=sigma, absolute_sigma=True)
    _, pcov_rel = curve_fit(lambda x, a, b, c: a + b * x + c * x**2, x, y, sigma=sigma, absolute_sigma=False)
    np.testing.assert_allclose(popt, beta, rtol=1e-7)
    np.testing.assert_allclose(trusted.covariance, pcov_abs, rtol=1e-6)
    np.testing.assert_allclose(relative.covariance, pcov_rel, rtol=1e-6)
    # The report: singular values of J D (D the scales), full rank, no weak direction.
    ident = trusted.identifiability
    np.testing.assert_allclose(ident.singular_values, np.linalg.svd(J * scales, compute_uv=False), rtol=1e-12)
    assert ident.rank == 3 and ident.names == ("a", "b", "c") and ident.symmetries == ()
    s = np.linalg.svd(J * scales, compute_uv=False)
    np.testing.assert_allclose(ident.condition_number, s[0] / s[-1], rtol=1e-12)
    # Weak directions: those with scaled standard error 1/s_k above the threshold (0.1).
    np.testing.assert_allclose(ident.weak_stderr, 1 / s[1 / s > 0.1], rtol=1e-12)
    assert len(ident.weak) == int(np.sum(1 / s > 0.1))


def test_a_fit_that_misses_the_data_says_so(rng):
    """With the sigmas trusted, a chi2 whose p-value is below `POOR_FIT_P_VALUE` is noted
    (the README's spring fit stopped at chi2 ~ 2e7 for 115 degrees of freedom and looked
    converged); a chi2 at its expectation, or the sigmas scaled by the fit, is not."""
    J = rng.normal(size=(120, 5))
    values = dict(zip(STIFFNESS, (1.0, 1.5, 0.8, 0.3, 0.2)))
    # chi2 = 159.5 for 115 degrees of freedom: p = 0.0038 (scipy.stats.chi2.sf)
    fine = hr.error_analysis(J, np.full(120, np.sqrt(159.5 / 120)), values, np.ones(5))
    assert not any("does not describe" in n for n in fine.identifiability.notes)
    # chi2 = 200: p = 1.6e-6; chi2 = 205: p = 5.0e-7 (just past the 1e-6 line)
    assert not any("does not describe" in n for n in hr.error_analysis(J, np.full(120, np.sqrt(200 / 120)), values, np.ones(5)).identifiability.notes)
    poor = hr.error_analysis(J, np.full(120, np.sqrt(205 / 120)), values, np.ones(5)).identifiability.notes
    assert any("does not describe the data" in n and "115 degrees of freedom" in n for n in poor)
    scaled = hr.error_analysis(J, np.full(120, 10.0), values, np.ones(5), absolute_sigma=False)
    assert not any("does not describe" in n for n in scaled.identifiability.notes)


def test_error_analysis_of_no_parameters():
    """No parameters: no covariance, no directions, the cost of the residuals."""
    analysis = hr.error_analysis(np.zeros((3, 0)), np.ones(3), {}, np.ones(0))
    assert analysis.identifiability.weak == analysis.identifiability.determined == ()
    assert analysis.covariance.shape == (0, 0) and analysis.cost == 1.5
