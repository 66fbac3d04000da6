"""compare_models: the reference report's four classes side by side.  The generating class
is recommended on clear cases; the likelihood-ratio statistic of a regular nested pair is
chi^2 with the right degrees of freedom over many simulated (vmapped) data sets, and the
simulated null distribution corrects an irregular pair; bad options are named."""

import json

import jax
import numpy as np
import pytest
from helpers import fit_grid
from scipy import stats
from typer.testing import CliRunner

import helixrod as hr
from helixrod.cli import app

CLASS_RODS = {
    "isotropic": hr.Rod(1.0, 1.0, 1.3),
    "isotropic-coupled": hr.Rod(1.0, 1.0, 1.3, K13=0.3),
    "general": hr.Rod(1.0, 1.6, 1.3, K13=0.2, K23=0.3),
}


@pytest.mark.heavy
def test_the_generating_class_is_recommended(rng):
    kappa, tau = fit_grid(rng)
    for name, rod in CLASS_RODS.items():
        data = hr.synthetic_helix_data(rod, kappa, tau, 0.01, jax.random.key(1))
        comparison = hr.compare_models(data, n_starts=4)
        assert comparison.best == name, comparison.summary()
        assert comparison.names[0] == "isotropic" and comparison.names[-1] == "general"
        row = comparison.table[name]
        assert row["ok"] and row["identifiable"] and abs(row["chi2_reduced"] - 1) < 0.6
        assert row["result"] == "successful"
        assert comparison.table[name]["delta_bic"] == 0.0
        # A model nested in another never ends above it (it starts from the nested fit).
        for test in comparison.tests:
            assert test["statistic"] >= 0
            assert comparison.table[test["larger"]]["cost"] <= comparison.table[test["smaller"]]["cost"] * (1 + 1e-9)
        weights = [comparison.table[n]["akaike_weight"] for n in comparison.names]
        assert sum(weights) == pytest.approx(1.0)
        if name == "isotropic":  # the tie K2 = K1 in the profile likelihood: K2 moves with K1
            fit = comparison.fits[name]
            assert fit.names == ("K1", "K3") and float(fit.rod.K2) == float(fit.rod.K1)
            low, high = hr.profile_likelihood(fit, "K1", points=7).interval
            estimate, stderr = float(fit.params["K1"]), float(fit.stderr["K1"])
            assert low < estimate < high and (high - low) == pytest.approx(2 * 1.96 * stderr, rel=0.1)
    # An uncoupled anisotropic rod: its stable helices bend about the softer axis only, so
    # K2 never enters the data -- the table says so, and the isotropic class is recommended.
    data = hr.synthetic_helix_data(hr.Rod(1.0, 1.6, 1.3), kappa, tau, 0.01, jax.random.key(1))
    comparison = hr.compare_models(data, ["isotropic", "anisotropic"], n_starts=4)
    assert comparison.best == "isotropic"
    assert not comparison.table["anisotropic"]["identifiable"] and comparison.table["anisotropic"]["rank"] == 2
    assert "recommended: isotropic" in comparison.summary()
    assert json.loads(json.dumps(comparison.to_dict()))["best"] == "isotropic"


def test_coupling_gauge_needs_a_free_frame(rng):
    """K23 = 0 is a gauge of the isotropic-coupled class only where the frame may turn about
    d3: a fixed uhat with an in-plane part pins it, and the class then frees both couplings
    (it had cost 35 000 for data of its own class, and general was recommended)."""
    kappa, tau = rng.uniform(0.3, 2.5, 40), rng.uniform(-2.0, 2.0, 40)
    uhat = (0.4, 0.0, 0.2)
    data = hr.synthetic_helix_data(hr.Rod(1.0, 1.0, 0.8, K13=0.2, K23=0.25, uhat=uhat), kappa, tau, 0.01, jax.random.key(2))
    comparison = hr.compare_models(data, ["isotropic", "isotropic-coupled"], uhat=uhat, n_starts=4)
    fit = comparison.fits["isotropic-coupled"]
    assert comparison.best == "isotropic-coupled" and fit.names == ("K1", "K3", "K13", "K23")
    assert fit.chi2_reduced < 2.0


def _check_chi2(rod, larger, smaller, df, kappa, tau):
    data = hr.synthetic_helix_data(rod, kappa, tau, 0.01, jax.random.key(1))
    comparison = hr.compare_models(data, {"held": smaller, larger: larger}, n_starts=2)
    simulated = comparison.simulate_test("held", larger, n=300, key=jax.random.key(7))
    samples = np.asarray(simulated.samples)[np.asarray(simulated.ok)]
    assert simulated.df == df and samples.size >= 290
    assert abs(samples.mean() - df) < 4 * np.sqrt(2 * df / samples.size), samples.mean()
    assert stats.kstest(samples, stats.chi2(df).cdf).pvalue > 1e-3
    assert 0 < simulated.p_value <= 1 and simulated.p_value_chi2 == comparison.tests[0]["p_value"]


@pytest.mark.heavy
def test_likelihood_ratio_is_chi2_on_a_regular_pair(rng):
    """K3 held at its true value inside the isotropic class: 1 df."""
    kappa, tau = fit_grid(rng)
    _check_chi2(CLASS_RODS["isotropic"], "isotropic", {"isotropic": True, "fix": {"K13": 0, "K23": 0, "K3": 1.3}}, 1, kappa, tau)


@pytest.mark.slow
def test_likelihood_ratio_two_df_and_an_irregular_pair(rng):
    kappa, tau = fit_grid(rng)
    # K3 and K13 held inside the isotropic-coupled class (K13 away from the symmetry point 0).
    smaller = {"isotropic": True, "fix": {"K23": 0, "K3": 1.3, "K13": 0.3}}
    _check_chi2(CLASS_RODS["isotropic-coupled"], "isotropic-coupled", smaller, 2, kappa, tau)
    # Irregular: the uncoupled class inside the general one sits at the fixed point of the
    # end-for-end flips (K13 = K23 = 0); the statistic is far from chi^2 with 2 df.
    data = hr.synthetic_helix_data(hr.Rod(1.0, 1.6, 1.3), kappa, tau, 0.01, jax.random.key(1))
    comparison = hr.compare_models(data, ["anisotropic", "general"], n_starts=2)
    simulated = comparison.simulate_test("anisotropic", "general", n=100, key=jax.random.key(8))
    samples = np.asarray(simulated.samples)[np.asarray(simulated.ok)]
    assert stats.kstest(samples, stats.chi2(2).cdf).pvalue < 1e-3


def test_bad_options_and_the_command_line(tmp_path, rng):
    kappa, tau = fit_grid(rng)
    data = hr.synthetic_helix_data(CLASS_RODS["isotropic"], kappa, tau, 0.01, jax.random.key(1))
    with pytest.raises(ValueError, match="unknown model class 'cubic'"):
        hr.compare_models(data, ["isotropic", "cubic"])
    with pytest.raises(ValueError, match="needs two models"):
        hr.compare_models(data, ["isotropic"])
    with pytest.raises(ValueError, match="must be a class name"):
        hr.compare_models(data, {"mine": {"fixed": {"K3": 1.0}}, "general": "general"})
    with pytest.raises(ValueError, match="init= is set per model"):
        hr.compare_models(data, init=CLASS_RODS["isotropic"])
    with pytest.raises(ValueError, match="criterion must be one of"):
        hr.compare_models(data, criterion="r2")
    comparison = hr.compare_models(data, ["isotropic", "anisotropic"], n_starts=2)
    with pytest.raises(ValueError, match="is not nested in"):
        comparison.simulate_test("anisotropic", "isotropic")
    # helixrod fit --compare, with its JSON and figure.
    path = tmp_path / "helices.csv"
    data.to_csv(path)
    out, plot = tmp_path / "comparison.json", tmp_path / "comparison.png"
    result = CliRunner().invoke(
        app, ["fit", str(path), "--compare", "--models", "isotropic,anisotropic", "--n-starts", "2", "--out", str(out), "--plot", str(plot)]
    )
    assert result.exit_code == 0, result.output
    assert "recommended: isotropic" in result.output
    assert json.loads(out.read_text())["best"] == "isotropic" and plot.stat().st_size > 0
    result = CliRunner().invoke(app, ["fit", str(path), "--compare", "--models", "isotropic,cubic"])
    assert result.exit_code == 2 and "unknown model class 'cubic'" in result.output
