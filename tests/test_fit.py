"""The inverse spring problem: HelixData, fit_stiffness, fit_stiffness_linear, bootstrap.

Every fit here shares one compiled configuration (24 points, the five stiffnesses free,
uhat fixed -- its values are traced, so a new uhat does not recompile)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_rods

import helixrod as hr
from helixrod import _fit

N_POINTS = 24


def _grid(rng):
    return rng.uniform(0.2, 2.5, N_POINTS), rng.uniform(-2.0, 2.0, N_POINTS)


def _vector(rod):
    return np.concatenate([[float(rod.K1), float(rod.K2), float(rod.K3), float(rod.K13), float(rod.K23)], np.asarray(rod.uhat)])


# -- symmetries: derived in _fit's docstring, checked on helix_equilibria directly ----------


def test_every_frame_symmetry_leaves_predictions_unchanged(rng):
    rod = random_rods(rng, 1)[0]
    kappa, tau = _grid(rng)
    p = _vector(rod)
    images = [_fit._apply(e, p) for _, _, e in _fit._all_elements()]
    P = np.stack(images)
    rods = hr.Rod(*(P[:, i, None] for i in range(5)), uhat=P[:, None, 5:])
    eq = jax.jit(hr.helix_equilibria)(rods, kappa[None, :], tau[None, :])
    F = np.sort(np.where(eq.valid, eq.force, np.inf), axis=-1)
    M = np.sort(np.where(eq.valid, eq.moment, np.inf), axis=-1)
    assert np.all(np.asarray(eq.count) >= 2)
    for i in range(1, 8):
        np.testing.assert_allclose(F[i], F[0], rtol=1e-11, atol=1e-12)
        np.testing.assert_allclose(M[i], M[0], rtol=1e-11, atol=1e-12)
    # ... and they are not trivial: the images are different rods.
    assert len({tuple(np.round(q, 12)) for q in images}) == 8


# -- recovery -------------------------------------------------------------------------------


def test_noise_free_recovery_and_linear_fit_agree(rng):
    kappa, tau = _grid(rng)
    for rod in random_rods(rng, 3):
        data = hr.synthetic_helix_data(rod, kappa, tau, 0.0, jax.random.key(0))
        fit = hr.fit_stiffness(data, uhat=rod.uhat)
        assert fit.success and fit.cost < 1e-20, (fit.cost, fit.message)
        assert fit.identifiability.symmetries == ()  # generic fixed uhat breaks them all
        truth = _vector(rod)
        np.testing.assert_allclose(_vector(fit.rod), truth, rtol=0, atol=1e-8 * np.abs(truth[:5]).max())
        assert fit.n_agree >= 1 and fit.n_starts == 32
        # The same helices with full local vectors: closed-form linear fit, same rod.
        eq = hr.helix_equilibria(rod, kappa, tau)
        lin = hr.fit_stiffness_linear(eq.u[:, 0], eq.m[:, 0], uhat=rod.uhat)
        np.testing.assert_allclose(_vector(lin.rod), _vector(fit.rod), rtol=0, atol=1e-8 * truth[:5].max())
        lin_u = hr.fit_stiffness_linear(eq.u[:, 0], eq.m[:, 0], fit_uhat=True)
        np.testing.assert_allclose(_vector(lin_u.rod), truth, rtol=0, atol=1e-9 * np.abs(truth).max())


def test_symmetric_case_reports_symmetry_and_null_direction(rng):
    """uhat1 = uhat2 = 0: the frame symmetries apply and are reported; the fit lies on the
    truth's orbit.  K1 = K2 with couplings: a continuous rotation of the frame, so the fit
    may turn all of the coupling into K23 -- and then the minimum-energy registers bend
    about d2 only and K1 is not seen at all: both are reported as null directions
    (infinite standard errors), never as false certainty."""
    kappa, tau = _grid(rng)
    rod = hr.Rod(0.8, 1.4, 1.1, K13=0.25, K23=-0.15, uhat=(0.0, 0.0, 0.3))
    data = hr.synthetic_helix_data(rod, kappa, tau, 0.0, jax.random.key(1))
    fit = hr.fit_stiffness(data, uhat=rod.uhat)
    syms = fit.identifiability.symmetries
    assert len(syms) == 7 and any("end for end" in s for s in syms)
    orbit = [_fit._apply(e, _vector(rod)) for _, _, e in _fit._all_elements()]
    err = min(np.max(np.abs(_vector(fit.rod) - q)) for q in orbit)
    assert fit.cost < 1e-20 and err < 1e-8
    # canonical gauge: K1 <= K2 and the couplings non-negative
    assert fit.params["K1"] <= fit.params["K2"] and fit.params["K13"] >= 0 and fit.params["K23"] >= 0

    iso = hr.Rod(1.0, 1.0, 1.3, K13=0.3, K23=0.2, uhat=(0.0, 0.0, 0.3))
    data = hr.synthetic_helix_data(iso, kappa, tau, 0.0, jax.random.key(2))
    fit = hr.fit_stiffness(data, uhat=iso.uhat)
    ident = fit.identifiability
    assert fit.cost < 1e-16
    assert ident.rank < 5 or ident.condition_number > 1e6
    weak = [dict(w) for w in ident.weak]
    assert any("K13" in w for w in weak)
    assert not (np.isfinite(float(fit.stderr["K13"])) and float(fit.stderr["K13"]) < 1.0)
    assert any("K1 and K2 agree" in note for note in ident.notes)
    # what is determined is still determined: |(K13, K23)|
    np.testing.assert_allclose(np.hypot(fit.params["K13"], fit.params["K23"]), np.hypot(0.3, 0.2), rtol=1e-6)


@pytest.mark.slow
def test_interval_calibration(rng):
    """Over 240 synthetic data sets (vmapped refits from the truth; the globalisation is
    tested above), the 95% Gauss-Newton intervals cover the true stiffnesses 92-98% of the
    time."""
    kappa, tau = _grid(rng)
    rod = hr.Rod(0.9, 1.6, 1.2, K13=0.2, K23=0.1, uhat=(0.5, -0.2, 0.3))
    exact = hr.synthetic_helix_data(rod, kappa, tau, 0.0, jax.random.key(0))
    n_sets = 240
    sF, sM = 0.01 * float(exact.force_sigma[0]), 0.01 * float(exact.moment_sigma[0])
    kf, km = jax.random.split(jax.random.key(7))
    fit0 = hr.fit_stiffness(exact, uhat=rod.uhat, n_starts=1, init=rod)
    problem, opts = fit0.spec, fit0.options
    data = hr.HelixData(exact.force, exact.moment, kappa, tau, sF, sM)
    arrays = _fit._data_arrays(data, problem)
    batch = {k: jnp.broadcast_to(v, (n_sets,) + v.shape) for k, v in arrays.items()}
    batch["force"] = exact.force + sF * jax.random.normal(kf, (n_sets, N_POINTS))
    batch["moment"] = exact.moment + sM * jax.random.normal(km, (n_sets, N_POINTS))
    z0 = jnp.asarray(_fit._internal_from_physical(_vector(rod), problem))
    p, stderr, ok = _fit._refit_batch(z0, batch, problem.spec, opts)
    assert bool(jnp.all(ok))
    truth = _vector(rod)[:5]
    covered = np.abs(np.asarray(p)[:, :5] - truth) <= 1.959964 * np.asarray(stderr)
    coverage = covered.mean()
    assert 0.92 <= coverage <= 0.98, (coverage, covered.mean(axis=0))
    assert np.all(covered.mean(axis=0) >= 0.88)


def test_bootstrap_brackets_fit(rng):
    kappa, tau = _grid(rng)
    rod = random_rods(rng, 1)[0]
    data = hr.synthetic_helix_data(rod, kappa, tau, 0.02, jax.random.key(3))
    fit = hr.fit_stiffness(data, uhat=rod.uhat)
    boot = hr.bootstrap(data, fit, 16, jax.random.key(4), kind="parametric")
    assert float(jnp.mean(boot.success)) >= 0.9
    for name in fit.names:
        lo, hi = boot.interval(0.95)[name]
        assert lo <= float(fit.params[name]) <= hi
        # parametric bootstrap spread agrees with the Gauss-Newton stderr within sampling error
        ratio = float(boot.std[name]) / float(fit.stderr[name])
        assert 0.4 < ratio < 2.0, (name, ratio)


# -- data and errors --------------------------------------------------------------------------


def test_csv_round_trip(tmp_path, rng):
    kappa, tau = _grid(rng)
    rod = random_rods(rng, 1)[0]
    data = hr.synthetic_helix_data(rod, kappa, tau, 0.05, jax.random.key(5), units={"force": "pN", "kappa": "1/nm"})
    path = tmp_path / "d.csv"
    data.to_csv(path, comment="test data")
    back = hr.HelixData.from_csv(path)
    for name in ("force", "moment", "kappa", "tau", "force_sigma", "moment_sigma", "register"):
        np.testing.assert_array_equal(np.asarray(getattr(back, name)), np.asarray(getattr(data, name)))
    assert back.units["force"] == "pN" and back.units["kappa"] == "1/nm"
    text = path.read_text().splitlines()
    assert text[2].startswith("force,moment,kappa,tau") and text[3].startswith("pN,")


def test_bad_inputs_give_documented_errors(tmp_path):
    ok = dict(force=[1.0, 2.0], moment=[0.5, 0.1], kappa=[1.0, 0.5], tau=[0.2, -0.3])
    with pytest.raises(ValueError, match="mismatched lengths"):
        hr.HelixData(**{**ok, "tau": [0.1]})
    with pytest.raises(ValueError, match=r"non-finite.*rows \[1\]"):
        hr.HelixData(**{**ok, "moment": [0.5, np.nan]})
    with pytest.raises(ValueError, match=r"force_sigma must be > 0; rows \[0\]"):
        hr.HelixData(**ok, force_sigma=[0.0, 1.0])
    with pytest.raises(ValueError, match="kappa must be > 0"):
        hr.HelixData(**{**ok, "kappa": [-1.0, 0.5]})
    with pytest.raises(ValueError, match="convention"):
        hr.HelixData(**ok, convention="lab")
    flipped = hr.HelixData(**ok, convention="advance")
    np.testing.assert_array_equal(np.asarray(flipped.force), [1.0, -2.0])
    data = hr.HelixData(**ok)
    with pytest.raises(ValueError, match="branch"):
        hr.fit_stiffness(data, branch="closest")
    with pytest.raises(ValueError, match="method"):
        hr.fit_stiffness(data, method="newton")
    with pytest.raises(ValueError, match="either uhat"):
        hr.fit_stiffness(data, uhat=(0, 0, 0), fit_uhat=True)
    with pytest.raises(ValueError, match="unknown parameter"):
        hr.fit_stiffness(data, fix={"K4": 1.0})
    with pytest.raises(ValueError, match="positive definite"):
        hr.fit_stiffness(data, init={"K1": 1.0, "K2": 1.0, "K3": 0.01, "K13": 1.0})
    path = tmp_path / "bad.csv"
    path.write_text("force,moment,kappa,tau,force_sigma,moment_sigma\nN,N m,1/m,1/m,N,N m\n1,1,1,1,1,1\n1,nan,1,1,1,1\n")
    with pytest.raises(ValueError, match=r"lines \[4\]"):
        hr.HelixData.from_csv(path)
    path.write_text("force,moment,kappa,tau\n1,1,1,1\n")
    with pytest.raises(ValueError, match="force_sigma and moment_sigma"):
        hr.HelixData.from_csv(path)
    assert len(hr.HelixData.from_csv(path, force_sigma=0.1, moment_sigma=0.1)) == 1
    with pytest.raises(ValueError, match=r"shape \(n, 3\)"):
        hr.fit_stiffness_linear(np.ones((3, 2)), np.ones((3, 2)))


def test_cli_fit_example(tmp_path):
    """`helixrod fit` on the bundled example (24 points: shares the compiled fit above)."""
    from typer.testing import CliRunner

    from helixrod.cli import app, example_data_path

    out, png = tmp_path / "fit.json", tmp_path / "fit.png"
    result = CliRunner().invoke(app, ["fit", str(example_data_path()), "--uhat", "1,0,0", "--out", str(out), "--plot", str(png)])
    assert result.exit_code == 0, result.output
    assert "K13" in result.output and "correlations" in result.output
    import json

    summary = json.loads(out.read_text())
    truth = {"K1": 1.0, "K2": 1.5, "K3": 0.8, "K13": 0.5, "K23": 0.5}
    for name, value in truth.items():  # 1% noise: within 5 standard errors
        assert abs(summary["params"][name] - value) <= 5 * summary["stderr"][name]
    assert png.stat().st_size > 10_000
    bad = CliRunner().invoke(app, ["fit", str(example_data_path()), "--uhat", "1,0"])
    assert bad.exit_code != 0


def _error_analysis(J):
    spec = _fit._Problem(
        _fit._Spec(
            free=_fit._STIFFNESS, fixed_names=(), branch="nearest", use_register=True, fit_register=False, errors_in_variables=False
        ),
        fixed=(),
        k_scale=1.0,
        u_scale=1.0,
    )
    q = np.array([1.0, 1.5, 0.8, 0.3, 0.2])
    return _fit._summarise(J, np.zeros(J.shape[0]), q, _fit._STIFFNESS, spec, absolute_sigma=True, weak_threshold=0.1)


def test_error_analysis_with_fewer_residuals_than_parameters(rng):
    """One data point gives 2 residuals for 5 stiffnesses: the report runs (it raised an
    IndexError before) and says rank 2, three exact null directions, every stderr infinite."""
    _, stderr, _, _, _, _, ident = _error_analysis(rng.normal(size=(2, 5)))
    assert ident.rank == 2 and ident.weak_stderr.count(np.inf) == 3
    assert all(np.isinf(float(v)) for v in stderr.values())


def test_error_analysis_with_an_unboundedly_sensitive_residual(rng):
    """A residual at a register tangency/cusp has a huge derivative (4.6e16 measured in
    tests/test_stress.py).  Kept in the SVD it made every other direction look null (rank 1,
    all stderr inf); as an exact constraint the error bars are the limit of the weighted
    ones: compared with the same row weighted 1e5 (below the constraint threshold)."""
    J = rng.normal(size=(24, 5))
    row = rng.normal(size=5)
    _, limit, _, _, _, _, ident = _error_analysis(np.vstack([J, 1e16 * row]))
    _, weighted, _, _, _, _, plain = _error_analysis(np.vstack([J, 1e5 * row]))
    assert ident.rank == 5 and np.isinf(float(ident.singular_values[0])) and "exact constraints" in ident.notes[0]
    assert plain.rank == 5 and not any("exact constraints" in n for n in plain.notes)
    for name in _fit._STIFFNESS:
        np.testing.assert_allclose(float(limit[name]), float(weighted[name]), rtol=1e-6)
