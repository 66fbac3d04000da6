"""design_experiment: designed measurements beat uniform ones, the design's standard errors
are those a fit of such data reports, and the structural identifiability table of the
README (which model classes uniform-helix measurements can determine, with which
observables) agrees with the numerical rank at random rods of each class."""

import numpy as np
import pytest

import helixrod as hr

KAPPA, TAU = (a.ravel() for a in np.meshgrid(np.linspace(0.1, 3.0, 12), np.linspace(-3.0, 3.0, 13)))


def _random_rod(rng, model, uhat):
    K1 = rng.uniform(0.5, 1.5)
    K2 = K1 if model.startswith("isotropic") else K1 * rng.uniform(1.2, 2.0)
    K13 = rng.uniform(0.1, 0.3) if model in ("isotropic-coupled", "general") else 0.0
    K23 = rng.uniform(0.1, 0.3) if model == "general" else 0.0
    u = rng.uniform(0.1, 0.4, 3) if uhat else np.zeros(3)
    if model == "isotropic":
        u[1] = 0.0  # the gauge of an isotropic, uncoupled rod
    return hr.Rod(K1, K2, rng.uniform(0.6, 2.0), K13=K13, K23=K23, uhat=u)


# (model, fit_uhat) -> rank of all the information of each observable set, of how many
# free parameters.  Force-only data always miss the direction K -> K + cI (K uhat fixed);
# an uncoupled rod with uhat = 0 never shows K2 (its stable helices bend about d1).
STRUCTURE = {
    ("isotropic", False): ({"force": 1, "moment": 2, "both": 2}, 2),
    ("anisotropic", False): ({"force": 1, "moment": 2, "both": 2}, 3),
    ("isotropic-coupled", False): ({"force": 2, "moment": 3, "both": 3}, 3),
    ("general", False): ({"force": 4, "moment": 5, "both": 5}, 5),
    ("isotropic", True): ({"force": 3, "moment": 4, "both": 4}, 4),
    ("anisotropic", True): ({"force": 5, "moment": 6, "both": 6}, 6),
    ("isotropic-coupled", True): ({"force": 5, "moment": 6, "both": 6}, 6),
    ("general", True): ({"force": 7, "moment": 8, "both": 8}, 8),
}
OBSERVE = {"force": ("force",), "moment": ("moment",), "both": ("force", "moment")}


@pytest.mark.heavy
def test_structural_identifiability_table(rng):
    for (model, fit_uhat), (ranks, p) in STRUCTURE.items():
        rod = _random_rod(rng, model, fit_uhat)
        for which, rank in ranks.items():
            design = hr.design_experiment(rod, (KAPPA, TAU), 12, model=model, observe=OBSERVE[which], fit_uhat=fit_uhat)
            assert (design.rank_all, len(design.names)) == (rank, p), (model, fit_uhat, which, design.undetermined)
            assert design.determinable == (rank == p)
            if which == "force":  # the trace shift is among the undetermined directions
                shift = [dict(c) for c in design.undetermined if {"K1", "K3"} <= set(dict(c))]
                assert shift and shift[0]["K1"] == pytest.approx(shift[0]["K3"], abs=0.05)


@pytest.mark.heavy
def test_designs_beat_uniform_grids_and_match_the_fit(rng):
    uniform = np.linspace(0, KAPPA.size - 1, 10).round().astype(int)
    for _ in range(3):
        K1 = rng.uniform(0.5, 1.5)
        rod = hr.Rod(K1, K1 * rng.uniform(1.2, 2.5), rng.uniform(0.6, 2.0), K13=rng.uniform(-0.3, 0.3), K23=rng.uniform(-0.3, 0.3))
        sigma = (0.01, 0.01)
        for criterion in ("D", "A"):
            grid = hr.design_experiment(rod, (KAPPA[uniform], TAU[uniform]), uniform.size, sigma=sigma, criterion=criterion)
            design = hr.design_experiment(rod, (KAPPA, TAU), 10, sigma=sigma, criterion=criterion)
            if criterion == "D":
                assert design.value > grid.value
                logdet = lambda d: np.linalg.slogdet(np.asarray(d.covariance))[1]  # noqa: E731
                assert logdet(design) < logdet(grid)
            else:
                variance = lambda d: sum(float(d.stderr[n]) ** 2 for n in d.names)  # noqa: E731 (one scale: K only)
                assert design.value > grid.value and variance(design) < variance(grid)
    # The design's errors are those fit_stiffness reports for data at the chosen helices.
    data = hr.HelixData(design.force, design.moment, design.kappa, design.tau, 0.01, 0.01)
    fit = hr.fit_stiffness(data, init=rod, n_starts=1)
    for name in design.names:
        assert float(fit.stderr[name]) == pytest.approx(float(design.stderr[name]), rel=1e-6)


@pytest.mark.heavy  # compiles helices_under_load over the candidate loads (~20 s)
def test_load_candidates():
    rod = hr.Rod(1.0, 1.6, 1.3, K13=0.2, K23=0.3)
    force, moment = (a.ravel() for a in np.meshgrid(np.linspace(-1.0, 1.0, 6), np.linspace(0.2, 2.0, 6)))
    force, moment = np.append(force, 50.0), np.append(moment, 0.0)  # a load no helix in the box holds
    design = hr.design_experiment(rod, {"force": force, "moment": moment}, 8, kappa_max=6.0, tau_range=(-6.0, 6.0))
    assert design.observe == ("kappa", "tau") and design.determinable and design.rank == 5
    assert force.size - 1 in design.dropped and not set(design.index) & set(design.dropped)
    # The chosen helices hold the chosen loads.
    np.testing.assert_allclose(design.force, force[design.index], rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(design.moment, moment[design.index], rtol=1e-8, atol=1e-10)
    assert "rank 5 of 5" in design.summary()


def test_isotropic_coupled_nominal_rods_in_and_out_of_the_gauge(rng):
    """The isotropic-coupled class's K23 = 0 is a gauge where the frame may turn: a nominal
    rod with K23 != 0 (and uhat = 0) is designed for as the same rod turned into it (it was
    "not in the model class"); with an in-plane uhat the class frees both couplings."""
    candidates = (rng.uniform(0.3, 2.5, 12), rng.uniform(-2.0, 2.0, 12))
    turned = hr.design_experiment(hr.Rod(1.0, 1.0, 0.8, K13=0.2, K23=0.25), candidates, 6, model="isotropic-coupled")
    gauge = hr.design_experiment(hr.Rod(1.0, 1.0, 0.8, K13=float(np.hypot(0.2, 0.25))), candidates, 6, model="isotropic-coupled")
    assert turned.names == gauge.names == ("K1", "K3", "K13")
    np.testing.assert_allclose([turned.stderr[n] for n in turned.names], [gauge.stderr[n] for n in gauge.names], rtol=1e-8)
    pinned = hr.design_experiment(hr.Rod(1.0, 1.0, 0.8, K13=0.2, K23=0.25, uhat=(0.4, 0.0, 0.2)), candidates, 6, model="isotropic-coupled")
    assert pinned.names == ("K1", "K3", "K13", "K23")


def test_bad_options():
    rod = hr.Rod(1.0, 1.6, 1.3, K13=0.2, K23=0.3)
    force, moment = np.linspace(-1.0, 1.0, 6), np.linspace(0.2, 2.0, 6)
    with pytest.raises(ValueError, match="need kappa_max= and tau_range="):
        hr.design_experiment(rod, {"force": force, "moment": moment}, 4)
    with pytest.raises(ValueError, match="not in the model class"):
        hr.design_experiment(rod, (KAPPA, TAU), 4, model="anisotropic")
    with pytest.raises(ValueError, match=r"n must be in 1\.\.156"):
        hr.design_experiment(rod, (KAPPA, TAU), 200)
    with pytest.raises(ValueError, match="criterion must be one of"):
        hr.design_experiment(rod, (KAPPA, TAU), 4, criterion="G")
    with pytest.raises(ValueError, match="observe must be one of"):
        hr.design_experiment(rod, (KAPPA, TAU), 4, observe=("kappa", "tau"))
    with pytest.raises(ValueError, match="kappa must be > 0"):
        hr.design_experiment(rod, (np.array([0.0, 1.0]), np.array([1.0, 1.0])), 1)
