"""fit_stiffness on helices (the inverse spring problem): noise-free recovery and the
closed-form linear fit, the command `helixrod fit`, the calibration of its intervals (slow),
and bad options.

Every fit here shares one compiled configuration (24 points, the five stiffnesses free,
uhat fixed -- its values are traced, so a new uhat does not recompile), `helixrod fit` on the
bundled example included; so do the fits of tests/test_fit_symmetry.py, test_fit_bootstrap.py
and test_fit_models.py."""

import json

import jax
import numpy as np
import pytest
from helpers import FIT_POINTS, fit_grid, parameter_vector, random_rods
from typer.testing import CliRunner

import helixrod as hr
from helixrod.cli import app, example_data_path


def test_noise_free_recovery_and_linear_fit_agree(rng):
    kappa, tau = fit_grid(rng)
    for rod in random_rods(rng, 3):
        data = hr.synthetic_helix_data(rod, kappa, tau, 0.0, jax.random.key(0))
        fit = hr.fit_stiffness(data, uhat=rod.uhat)
        assert fit.ok and fit.cost < 1e-20, (fit.cost, fit.message)
        assert fit.identifiability.symmetries == ()  # generic fixed uhat breaks them all
        truth = parameter_vector(rod)
        np.testing.assert_allclose(parameter_vector(fit.rod), truth, rtol=0, atol=1e-8 * np.abs(truth[:5]).max())
        assert fit.n_agree >= 1 and 1 <= fit.n_starts <= 32 and fit.start_costs.shape == (fit.n_starts,)  # early stop
        # The same helices with full local vectors: closed-form linear fit, same rod.
        eq = hr.helix_equilibria(rod, kappa, tau)
        lin = hr.fit_stiffness_linear(eq.u[:, 0], eq.m[:, 0], uhat=rod.uhat)
        np.testing.assert_allclose(parameter_vector(lin.rod), parameter_vector(fit.rod), rtol=0, atol=1e-8 * truth[:5].max())
        lin_u = hr.fit_stiffness_linear(eq.u[:, 0], eq.m[:, 0], fit_uhat=True)
        np.testing.assert_allclose(parameter_vector(lin_u.rod), truth, rtol=0, atol=1e-9 * np.abs(truth).max())


def test_cli_fit_example(tmp_path):
    """`helixrod fit` on the bundled example (24 points: shares the compiled fit above;
    tests/test_cli.py has the other commands)."""
    out, png = tmp_path / "fit.json", tmp_path / "fit.png"
    result = CliRunner().invoke(app, ["fit", str(example_data_path()), "--uhat", "1,0,0", "--out", str(out), "--plot", str(png)])
    assert result.exit_code == 0, result.output
    assert "K13" in result.output and "correlations" in result.output
    summary = json.loads(out.read_text())
    truth = {"K1": 1.0, "K2": 1.5, "K3": 0.8, "K13": 0.5, "K23": 0.5}
    for name, value in truth.items():  # 1% noise: within 5 standard errors
        assert abs(summary["params"][name] - value) <= 5 * summary["stderr"][name]
    assert png.stat().st_size > 10_000
    assert hr.StiffnessFit.load(out).summary().startswith("StiffnessFit (levenberg-marquardt): converged")
    bad = CliRunner().invoke(app, ["fit", str(example_data_path()), "--uhat", "1,0"])
    assert bad.exit_code != 0


@pytest.mark.slow
def test_interval_calibration(rng):
    """Over 240 synthetic data sets (single-start refits from the truth; the globalisation
    is tested above), the 95% Gauss-Newton intervals cover the true stiffnesses 92-98% of
    the time."""
    kappa, tau = fit_grid(rng)
    rod = hr.Rod(0.9, 1.6, 1.2, K13=0.2, K23=0.1, uhat=(0.5, -0.2, 0.3))
    exact = hr.synthetic_helix_data(rod, kappa, tau, 0.0, jax.random.key(0))
    n_sets = 240
    sF, sM = 0.01 * float(exact.force_sigma[0]), 0.01 * float(exact.moment_sigma[0])
    kf, km = jax.random.split(jax.random.key(7))
    forces = np.asarray(exact.force[None] + sF * jax.random.normal(kf, (n_sets, FIT_POINTS)))
    moments = np.asarray(exact.moment[None] + sM * jax.random.normal(km, (n_sets, FIT_POINTS)))
    p, stderr = [], []
    for F, M in zip(forces, moments):
        fit = hr.fit_stiffness(hr.HelixData(F, M, kappa, tau, sF, sM), uhat=rod.uhat, n_starts=1, init=rod)
        assert fit.ok, fit.message
        p.append(parameter_vector(fit.rod)[:5])
        stderr.append([float(fit.stderr[n]) for n in fit.names])
    truth = parameter_vector(rod)[:5]
    covered = np.abs(np.asarray(p) - truth) <= 1.959964 * np.asarray(stderr)
    coverage = covered.mean()
    assert 0.92 <= coverage <= 0.98, (coverage, covered.mean(axis=0))
    assert np.all(covered.mean(axis=0) >= 0.88)


def test_bad_options_give_documented_errors():
    data = hr.HelixData(force=[1.0, 2.0], moment=[0.5, 0.1], kappa=[1.0, 0.5], tau=[0.2, -0.3])
    with pytest.raises(ValueError, match="branch"):
        hr.fit_stiffness(data, branch="closest")
    with pytest.raises(ValueError, match="solver"):
        hr.fit_stiffness(data, solver="newton")
    with pytest.raises(ValueError, match="either uhat"):
        hr.fit_stiffness(data, uhat=(0, 0, 0), fit_uhat=True)
    with pytest.raises(ValueError, match=r"fix: uhat1 = 2.0 contradicts uhat= \[1.0, 0.0, 0.0\]"):
        hr.fit_stiffness(data, uhat=(1, 0, 0), fix={"uhat1": 2.0})
    with pytest.raises(ValueError, match="unknown parameter"):
        hr.fit_stiffness(data, fix={"K4": 1.0})
    with pytest.raises(ValueError, match="positive definite"):
        hr.fit_stiffness(data, init={"K1": 1.0, "K2": 1.0, "K3": 0.01, "K13": 1.0})
    for steps in (0, 2.5, True, "64"):
        with pytest.raises(ValueError, match="max_steps must be an integer >= 1"):
            hr.fit_stiffness(data, max_steps=steps)
    with pytest.raises(ValueError, match="n_starts must be an integer >= 1, got 2.5"):
        hr.fit_stiffness(data, n_starts=2.5)
    with pytest.raises(ValueError, match="key must be one JAX random key"):
        hr.fit_stiffness(data, key=3)
    with pytest.raises(ValueError, match="rtol must be finite and > 0"):
        hr.fit_stiffness(data, rtol=-1.0)
    with pytest.raises(ValueError, match="weak_threshold must be > 0"):
        hr.fit_stiffness(data, weak_threshold=-1.0)
    for bad in ([1 + 1j, 2.0], ["a", 2.0]):
        with pytest.raises(ValueError, match="HelixData: force must be"):
            hr.HelixData(force=bad, moment=[0.5, 0.1], kappa=[1.0, 0.5], tau=[0.2, -0.3])
    with pytest.raises(ValueError, match="key must be one JAX random key"):
        hr.synthetic_helix_data(hr.Rod(1.0, 1.5, 0.8), [1.0], [0.5], 0.01, 1)
    # The deviation of a quantity not observed is not used.
    force_only = hr.synthetic_helix_data(hr.Rod(1.0, 1.5, 0.8), [1.0], [0.5], (0.01, 0.0), jax.random.key(0), observe=("force",))
    assert bool(np.all(np.isnan(np.asarray(force_only.moment)))) and float(force_only.force_sigma[0]) == 0.01


def test_cli_fit_bad_fix_is_a_usage_error(tmp_path):
    runner = CliRunner()
    for entry, message in (("K13=abc", "'abc' is not a number"), ("K13", "is not NAME=VALUE"), ("K13=0,K13=1", "names K13 twice")):
        result = runner.invoke(app, ["fit", str(example_data_path()), "--fix", entry])
        assert result.exit_code == 2, result.output
        assert message in " ".join(result.output.split())


def test_fixed_couplings_beside_the_default_start():
    """A fixed coupling too strong for the default start's isotropic diagonal: the free
    stiffnesses make room for it (a free K3 keeps the estimate as its Schur complement;
    with K3 fixed, free K1 and K2 grow) instead of an error about a rod nobody gave."""
    from helixrod._fit._parameters import start_vector

    default = np.array([0.53, 0.53, 0.07, 0.0, 0.0, 0.0, 0.0, 0.0])
    p = start_vector(None, {"K13": 0.8}, default)
    np.testing.assert_allclose(p[2] - p[3] ** 2 / p[0], 0.07, rtol=1e-12)
    p = start_vector(None, {"K3": 0.5, "K13": 0.6, "K23": 0.3}, default)
    assert p[2] - p[3] ** 2 / p[0] - p[4] ** 2 / p[1] > 0 and p[0] == p[1] > 0.53
    with pytest.raises(ValueError, match="positive definite"):  # fixed values that leave no room
        start_vector(None, {"K1": 1.0, "K2": 1.0, "K3": 0.5, "K13": 0.8}, default)
    rng = np.random.default_rng(0)
    kappa, tau = rng.uniform(0.3, 2.5, 30), rng.uniform(-2.0, 2.0, 30)
    data = hr.synthetic_helix_data(hr.Rod(1.0, 1.5, 0.8, K13=0.8), kappa, tau, 0.01, jax.random.key(2))
    fit = hr.fit_stiffness(data, fix={"K13": 0.8})
    assert fit.ok and fit.chi2_reduced < 2.0
