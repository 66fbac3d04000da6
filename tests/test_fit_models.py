"""Forward models of fit_stiffness (helixrod._fit._models) and how the pipeline takes
solvers: the helix model's residuals and predictions against helix_equilibria evaluated
here, the data types and options each model accepts, and optimistix solver objects.

The helix fits have the configuration of tests/test_fit_pipeline.py (24 points, the five
stiffnesses free, uhat fixed: one compilation); the minimiser fit is small (3 points, one
start, a few steps)."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
import pytest
from helpers import EIV_SIGMAS, EIV_TRUTH, EIV_UHAT, SPRING, eiv_helix_data, fit_grid, random_rods

import helixrod as hr

ADAM = optx.OptaxMinimiser(optax.adam(1e-2), rtol=1e-8, atol=1e-8)


@pytest.fixture(scope="module")
def noisy():
    """Noisy helix data of a random rod, and its default fit."""
    rng = np.random.default_rng(11)
    kappa, tau = fit_grid(rng)
    rod = random_rods(rng, 1)[0]
    data = hr.synthetic_helix_data(rod, kappa, tau, 0.02, jax.random.key(7))
    return rod, data, hr.fit_stiffness(data, uhat=rod.uhat)


@pytest.mark.heavy
def test_helix_residuals_are_the_normalised_errors_of_the_chosen_registers(noisy):
    """residuals = ((F_pred - F)/sigma_F, (M_pred - M)/sigma_M) with F_pred, M_pred those of
    helix_equilibria of the fitted rod at the register slot the model chose (the one nearest
    the observation in sigma units, the default branch)."""
    rod, data, fit = noisy
    assert fit.ok, fit.message
    assert set(fit.predicted) == {"force", "moment", "register", "slot", "stable"}
    slot = np.asarray(fit.predicted["slot"])
    eq = hr.helix_equilibria(fit.rod, data.kappa, data.tau)  # the shapes of synthetic_helix_data: compiled
    rows = np.arange(len(data))
    assert np.all(np.asarray(eq.valid)[rows, slot])
    F, M, phi = (np.asarray(a)[rows, slot] for a in (eq.force, eq.moment, eq.phi))
    np.testing.assert_allclose(fit.predicted["force"], F, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(fit.predicted["moment"], M, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(fit.predicted["register"], phi, rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(fit.predicted["stable"], np.asarray(eq.stable)[rows, slot])
    F_obs, M_obs = np.asarray(data.force), np.asarray(data.moment)
    sF, sM = np.asarray(data.force_sigma), np.asarray(data.moment_sigma)
    expected = np.concatenate([(F - F_obs) / sF, (M - M_obs) / sM])
    np.testing.assert_allclose(fit.residuals, expected, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(fit.cost, 0.5 * np.sum(expected**2), rtol=1e-9)
    # The chosen slot is the nearest register in sigma units.
    dist = np.where(np.asarray(eq.valid), ((np.asarray(eq.force) - F_obs[:, None]) / sF[:, None]) ** 2
                    + ((np.asarray(eq.moment) - M_obs[:, None]) / sM[:, None]) ** 2, np.inf)
    np.testing.assert_array_equal(slot, np.argmin(dist, axis=1))


@pytest.mark.heavy
def test_solver_objects(noisy):
    """An optimistix least-squares solver object gives the same fit as the default alias
    (helixrod's Levenberg-Marquardt, which differs from optimistix's only in accepting steps
    at round-off): the same cost to round-off, and parameters within 1e-6 of their standard
    errors -- where the cost is flat to round-off, where the two stop differs by machine
    (2.7e-9 in K2, 1.6e-9 relative, on one AMD EPYC machine; below 1e-9 on others); a
    minimiser is accepted for helix data; rtol= with an object is an error."""
    rod, data, fit = noisy
    same = hr.fit_stiffness(data, uhat=rod.uhat, solver=optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12))
    assert same.method == "LevenbergMarquardt" and fit.method == "levenberg-marquardt"
    np.testing.assert_allclose(float(same.cost), float(fit.cost), rtol=1e-12)
    for name in fit.names:
        assert abs(float(same.params[name]) - float(fit.params[name])) < 1e-6 * float(fit.stderr[name])
        np.testing.assert_allclose(float(same.stderr[name]), float(fit.stderr[name]), rtol=1e-6)
    np.testing.assert_allclose(same.residuals, fit.residuals, rtol=0, atol=1e-6)
    small = hr.HelixData(data.force[:3], data.moment[:3], data.kappa[:3], data.tau[:3], data.force_sigma[:3],
                         data.moment_sigma[:3])
    adam = hr.fit_stiffness(small, uhat=rod.uhat, solver=ADAM, n_starts=1, max_steps=8)
    assert adam.method == "OptaxMinimiser" and adam.n_steps == 8 and np.isfinite(adam.cost)
    assert adam.result == hr.RESULTS.nonlinear_max_steps_reached and "OptaxMinimiser, 8 steps" in adam.message
    assert len(adam.residuals) == 6 and set(adam.predicted) == {"force", "moment", "register", "slot", "stable"}
    with pytest.raises(ValueError, match="apply to solvers given by name"):
        hr.fit_stiffness(data, solver=optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12), rtol=1e-8)
    with pytest.raises(ValueError, match="apply to solvers given by name"):
        hr.fit_stiffness(data, solver=ADAM, learning_rate=0.1)
    with pytest.raises(ValueError, match="an optimistix least-squares solver or minimiser, got Newton"):
        hr.fit_stiffness(data, solver=optx.Newton(rtol=1e-8, atol=1e-8))  # a root finder


def test_data_types_and_options_of_the_models():
    end = hr.axial_ends(SPRING, 10.0, force=0.01, moment=0.0)[1]
    shape = hr.ShapeData(1.0, [0.0, 0.5, 1.0], np.zeros((3, 3)), end, sigma=0.1)
    response = hr.EndResponseData(10.0, [0.01, 0.02], [0.0, 0.0], [1.0, 1.0], [1.0, 1.0], controls="force-moment",
                                  extension_sigma=0.1, rotation_sigma=0.1)
    for data in (shape, response):
        with pytest.raises(ValueError, match=f"branch= does not apply to {type(data).__name__}"):
            hr.fit_stiffness(data, branch="stable")
        with pytest.raises(ValueError, match=f"errors_in_variables= does not apply to {type(data).__name__}"):
            hr.fit_stiffness(data, errors_in_variables=True)
        with pytest.raises(ValueError, match=f"fit_offsets= does not apply to {type(data).__name__}"):
            hr.fit_stiffness(data, fit_offsets=True)
    with pytest.raises(ValueError, match="fit_offsets= does not apply to HelixData"):
        hr.fit_stiffness(hr.HelixData([1.0], [1.0], [1.0], [1.0]), fit_offsets=True)
        for solver in ("adam", "lbfgs", ADAM):
            with pytest.raises(ValueError, match=f"is not available for {type(data).__name__} "):
                hr.fit_stiffness(data, solver=solver)
    tweezer = hr.dna.TweezerData.from_arrays([1.0, 2.0], [2300.0, 2400.0], extension_sigma=2.0, torque=0.0, n_bp=8000)
    with pytest.raises(ValueError, match="is not available for TweezerData "):
        hr.fit_stiffness(tweezer, solver="adam")
    for bad in ({"force": [1.0]}, np.ones((3, 4)), None):
        with pytest.raises(ValueError, match="data must be a HelixData, EndResponseData, ShapeData or TweezerData, got"):
            hr.fit_stiffness(bad)
    helix = hr.HelixData(force=[1.0, 2.0], moment=[0.5, 0.1], kappa=[1.0, 0.5], tau=[0.2, -0.3])
    with pytest.raises(ValueError, match="use_register=True but the data have no register column"):
        hr.fit_stiffness(helix, use_register=True)
    with pytest.raises(ValueError, match="errors_in_variables=True needs kappa_sigma"):
        hr.fit_stiffness(helix, errors_in_variables=True)


def test_summary_save_and_load(noisy, tmp_path):
    """`repr(fit)` is the summary table; `save` / `StiffnessFit.load` round-trip every value
    of it through JSON; a file that is not a saved fit is a named error."""
    _, data, fit = noisy
    text = fit.summary()
    assert repr(fit) == text and text.startswith("StiffnessFit (levenberg-marquardt): converged")
    for name in fit.names:
        assert f"{float(fit.params[name]):.7g}" in text and f"{float(fit.stderr[name]):.4g}" in text
    assert f"AIC {fit.aic:.6g}" in text and f"reduced chi2 {float(fit.chi2_reduced):.4g}" in text
    path = tmp_path / "fit.json"
    fit.save(path)
    back = hr.StiffnessFit.load(path)
    assert back.summary() == text and back.names == fit.names and back.ok and back.problem is None
    np.testing.assert_array_equal(back.covariance, fit.covariance)
    np.testing.assert_array_equal(back.residuals, fit.residuals)
    np.testing.assert_array_equal(back.predicted["force"], fit.predicted["force"])
    assert back.identifiability.to_dict() == fit.identifiability.to_dict()
    assert repr(back.rod) == repr(fit.rod) and (back.aic, back.bic) == (fit.aic, fit.bic)
    # A fit's numbers are host values (NumPy), fitted or read back; its rod is a JAX rod.
    for f in (fit, back):
        assert all(isinstance(a, np.ndarray) for a in (f.covariance, f.correlation, f.residuals, f.start_costs))
        assert all(isinstance(v, np.float64) for v in (*f.params.values(), *f.stderr.values()))
        assert isinstance(f.identifiability.singular_values, np.ndarray) and isinstance(f.rod.K1, jax.Array)
    with pytest.raises(ValueError, match="propagate needs the problem of a fit from fit_stiffness in this session"):
        back.propagate(lambda rod, p: rod.K1)
    (tmp_path / "other.json").write_text('{"a": 1}')
    with pytest.raises(ValueError, match="not a fit written by StiffnessFit.save"):
        hr.StiffnessFit.load(tmp_path / "other.json")
    (tmp_path / "broken.json").write_text("{")
    with pytest.raises(ValueError, match="is not JSON"):
        hr.StiffnessFit.load(tmp_path / "broken.json")
    # The data print their size and ranges, not array shapes.
    assert repr(data).startswith(f"HelixData({len(data)} points: force ") and "sigmas of force, moment" in repr(data)


def test_errors_in_variables_default_follows_the_data():
    """On when the data carry kappa or tau sigmas (the bundled DNA helices do), off when not,
    and an explicit choice wins."""
    from helixrod._fit import forward_model

    with_sigmas = hr.dna.load_tweezer_example().helix_data()
    assert forward_model(with_sigmas).errors_in_variables is True
    assert forward_model(with_sigmas, errors_in_variables=False).errors_in_variables is False
    plain = hr.HelixData(with_sigmas.force, with_sigmas.moment, with_sigmas.kappa, with_sigmas.tau,
                         with_sigmas.force_sigma, with_sigmas.moment_sigma)
    assert forward_model(plain).errors_in_variables is False


def test_reduced_chi2_warning():
    import types

    from helixrod.cli._report import chi2_warning

    fit = lambda chi2, m=100, rank=5: types.SimpleNamespace(
        chi2_reduced=chi2, n_residuals=m, identifiability=types.SimpleNamespace(rank=rank))
    assert chi2_warning(fit(1.2)) is None and chi2_warning(fit(0.8)) is None  # within 5 sd (0.145 each)
    assert "far from 1 for 95 degrees of freedom" in chi2_warning(fit(5e4)) and "larger than" in chi2_warning(fit(5e4))
    assert "smaller than the sigmas say" in chi2_warning(fit(0.1))
    assert chi2_warning(fit(9.0, m=5, rank=5)) is None  # no degrees of freedom


def test_errors_in_variables_fit_is_orears_fixed_point():
    """Errors in variables whiten each (F, M) pair by an effective covariance from the
    model's slopes along kappa and tau, which move with K while the Jacobian holds them
    fixed (Orear 1982).  The fit ends at the fixed point of least squares with the weights
    of its own solution: found here independently by scipy's least squares with fixed
    weights (slopes by central differences, the 2x2 whitening in NumPy), iterated from
    the generating rod.  The fit's residuals are those with its solution's own weights."""
    from scipy.optimize import least_squares

    data, uhat, n = eiv_helix_data(), EIV_UHAT, 30
    ks, ts, sf, sm = EIV_SIGMAS
    fit = hr.fit_stiffness(data, uhat=uhat)
    assert fit.ok, fit.message
    slot = np.asarray(fit.predicted["slot"])
    k, t = np.asarray(data.kappa), np.asarray(data.tau)
    wrench = jax.jit(lambda K, kk, tt: (lambda e: jnp.stack([e.force, e.moment]))(hr.helix_equilibria(hr.Rod(*K, uhat), kk, tt)))
    rows = np.arange(n)

    def predicted(K, kk=k, tt=t):
        return np.asarray(wrench(jnp.asarray(K), kk, tt))[:, rows, slot]

    def whitening(K):
        h = 1e-6
        dk = (predicted(K, k + h, t) - predicted(K, k - h, t)) / (2 * h)
        dt = (predicted(K, k, t + h) - predicted(K, k, t - h)) / (2 * h)
        J = np.stack([dk.T, dt.T], -1)  # (n, 2 wrench, 2 variables)
        cov = J @ np.diag([ks**2, ts**2]) @ J.transpose(0, 2, 1) + np.diag([sf**2, sm**2])
        return np.linalg.inv(np.linalg.cholesky(cov))

    def whitened(K, W):
        err = (predicted(K) - np.stack([np.asarray(data.force), np.asarray(data.moment)])).T
        r = np.einsum("nij,nj->ni", W, err)
        return np.concatenate([r[:, 0], r[:, 1]])

    K = np.array(EIV_TRUTH)
    for _ in range(30):
        W = whitening(K)
        K_next = least_squares(lambda K: whitened(K, W), K, method="lm", xtol=1e-14, ftol=1e-14, gtol=1e-14).x
        done = np.max(np.abs(K_next - K)) < 1e-12
        K = K_next
        if done:
            break
    fitted = np.array([float(fit.params[name]) for name in ("K1", "K2", "K3", "K13", "K23")])
    stderr = np.array([float(fit.stderr[name]) for name in ("K1", "K2", "K3", "K13", "K23")])
    assert np.max(np.abs(fitted - K) / stderr) < 5e-4  # 0.005 with the weights moving in the solve
    np.testing.assert_allclose(np.asarray(fit.residuals), whitened(fitted, whitening(fitted)), rtol=1e-6, atol=1e-7)
    # The moving model's Jacobian holds the weights of the point itself: no step left.
    from helixrod._fit import forward_model
    from helixrod._fit._pipeline import jacobian_and_predictions

    moving = forward_model(data)
    assert fit.problem.model.held_covariance is not None and moving.held_covariance is None
    J, (r, _) = jacobian_and_predictions(np.asarray(fitted), moving, fit.problem.parameterisation)
    step = np.linalg.lstsq(np.asarray(J), -np.asarray(r), rcond=None)[0]
    assert np.max(np.abs(step) / stderr) < 5e-4


def test_errors_in_variables_weights_that_do_not_settle_are_flagged():
    """A model far from the data (the coupled rod's helices fitted without couplings:
    reduced chi2 ~ 1e3) has no fixed point of Orear's iteration near its fit: each solve
    with the weights of the last point moves it again (here back and forth between two
    points).  The fit says so instead of reporting convergence."""
    fit = hr.fit_stiffness(eiv_helix_data(), uhat=EIV_UHAT, fix={"K13": 0.0, "K23": 0.0})
    assert not fit.ok
    assert bool(fit.result == hr.RESULTS.weights_not_settled)
    assert "did not settle" in fit.message
    assert float(fit.chi2_reduced) > 100
