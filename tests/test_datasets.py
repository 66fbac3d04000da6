"""The bundled datasets: the synthetic DNA tweezer example (its generating rod, noise, and a
fit that recovers it) and the example steel spring, against closed forms recomputed here."""

import math

import jax
import numpy as np
import pytest
from helpers import classical_compliance

import helixrod as hr
from helixrod import dna


def test_tweezer_example_loads_and_matches_its_model():
    data = dna.load_tweezer_example()
    n = data.force.shape[0]
    assert n >= 50 and float(data.force.min()) == pytest.approx(0.5) and float(data.force.max()) == pytest.approx(40.0)
    assert "SYNTHETIC" in data.provenance and "Gore" in data.provenance and "Bryant" in data.provenance
    # The generating rod has the published moduli (recomputed, not read back).
    S, C, g = (float(x) for x in dna.effective_moduli(data.rod, data.rod.uhat))
    assert (S, C, g) == pytest.approx((1100.0, 410.0, -90.0), rel=1e-9)
    assert float(dna.persistence_length(C)) == pytest.approx(99.6, abs=0.1)
    # kappa, tau are the observables converted by helix_from_tweezer.
    k, t = dna.helix_from_tweezer(data.extension, data.rotation, length_per_bp=data.length_per_bp)
    np.testing.assert_allclose(k, data.kappa, rtol=1e-12)
    np.testing.assert_allclose(t, data.tau, rtol=1e-12)
    # Noise as stated.  The generating rod has K13 = 0 and uhat1 = 0, so its register stays at
    # phi = 0 and Love's relations (with the K23 coupling) give the wrench in closed form:
    # bending m2 = M cos a - F r sin a, twisting m3 = M sin a + F r cos a.
    rod = data.rod
    k0, t0 = float(rod.uhat[1]), float(rod.uhat[2])
    k, t = np.asarray(data.kappa), np.asarray(data.tau)
    bend = float(rod.K2) * (k - k0) + float(rod.K23) * (t - t0)
    twist = float(rod.K23) * (k - k0) + float(rod.K3) * (t - t0)
    norm = np.hypot(k, t)
    sa, ca, r = t / norm, k / norm, k / norm**2
    force = (twist * ca - bend * sa) / r
    moment = bend * ca + twist * sa
    # Applied minus model wrench at the observed helix, mapped back by the compliance of one
    # base pair, is the observation noise.
    u = np.stack([np.zeros_like(k), k, t], -1)
    dload = np.stack([np.asarray(data.force) - force, np.asarray(data.moment) - moment], -1)
    c = np.asarray(hr.spring_compliance(rod, u, data.length_per_bp))
    dobs = np.einsum("nij,nj->ni", c, dload)
    z = dobs / np.stack([data.extension_sigma, data.rotation_sigma], -1)
    assert 0.7 < z[:, 0].std() < 1.3 and 0.7 < z[:, 1].std() < 1.3
    assert np.all(np.abs(z) < 5)


@pytest.mark.heavy
def test_tweezer_fit_recovers_generating_rod():
    """fit_stiffness on the tweezer dataset (errors in variables, with the kappa-tau
    correlation) recovers the generating K2, K3, K23 within the reported errors, with a
    reduced chi2 near 1; the whitened residuals equal an independent numpy computation
    (central differences for dF/d(kappa, tau), explicit 2x2 covariance and Cholesky)."""
    example = dna.load_tweezer_example()
    data, rod = example.helix_data(), example.rod
    fit = hr.fit_stiffness(data, uhat=rod.uhat, errors_in_variables=True, fix={"K1": float(rod.K2), "K13": 0.0}, n_starts=2)
    assert fit.names == ("K2", "K3", "K23")
    for name in fit.names:
        assert abs(float(fit.params[name]) - float(getattr(rod, name))) < 3 * float(fit.stderr[name]), name
        assert float(fit.stderr[name]) < 0.01 * abs(float(getattr(rod, name)))
    assert 0.6 < float(fit.chi2_reduced) < 1.4

    k, t = np.asarray(data.kappa), np.asarray(data.tau)
    wrench = jax.jit(lambda kk, tt: (lambda e: (e.force[:, 0], e.moment[:, 0]))(hr.helix_equilibria(fit.rod, kk, tt)))
    F, M = (np.asarray(x) for x in wrench(k, t))
    h = 1e-7
    dk = [(np.asarray(a) - np.asarray(b)) / (2 * h * k) for a, b in zip(wrench(k * (1 + h), t), wrench(k * (1 - h), t))]
    dt = [(np.asarray(a) - np.asarray(b)) / (2 * h * np.abs(t)) for a, b in zip(wrench(k, t + h * np.abs(t)), wrench(k, t - h * np.abs(t)))]
    ks, ts, rho = (np.asarray(x) for x in (data.kappa_sigma, data.tau_sigma, data.kappa_tau_correlation))
    sigma = np.array([[ks**2, rho * ks * ts], [rho * ks * ts, ts**2]]).transpose(2, 0, 1)
    J = np.stack([np.stack([dk[0], dt[0]], -1), np.stack([dk[1], dt[1]], -1)], 1)
    cov = J @ sigma @ J.transpose(0, 2, 1) + np.stack([np.diag([sf**2, sm**2]) for sf, sm in zip(np.asarray(data.force_sigma), np.asarray(data.moment_sigma))])
    err = np.stack([F - np.asarray(data.force), M - np.asarray(data.moment)], -1)
    white = np.linalg.solve(np.linalg.cholesky(cov), err[..., None])[..., 0]
    n = len(data)
    np.testing.assert_allclose(np.asarray(fit.residuals), np.concatenate([white[:, 0], white[:, 1]]), rtol=1e-5, atol=1e-6)
    assert n == 78


def test_spring_example_loads_and_matches_classical():
    data = hr.load_spring_example()
    assert "SYNTHETIC" in data.provenance
    r, alpha = data.coil_diameter / 2, math.atan2(data.pitch, math.pi * data.coil_diameter)
    EI = data.E * math.pi * data.wire_diameter**4 / 64
    GJ = data.G * math.pi * data.wire_diameter**4 / 32
    want = classical_compliance(EI, GJ, r, alpha, data.length)
    np.testing.assert_allclose(hr.spring_compliance(data.rod, data.rod.uhat, data.length), want, rtol=1e-9)
    pred = want @ np.stack([np.asarray(data.force), np.asarray(data.moment)])
    z = np.stack([(data.deflection - pred[0]) / data.deflection_sigma, (data.rotation - pred[1]) / data.rotation_sigma])
    assert 0.5 < z.std() < 1.5 and np.all(np.abs(z) < 5)
