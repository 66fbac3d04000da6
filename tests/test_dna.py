"""helixrod.dna, spring_compliance and effective_moduli against hand values, the classical
open-coiled spring (energy method, derived independently below), mpmath derivatives of
Love's exact helix relations, Maxwell reciprocity, and the bundled datasets."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest
from conftest import random_rods

import helixrod as hr
from helixrod import dna

PITCH_ANGLES = [5.0, 20.0, 45.0, 70.0, 85.0]  # degrees


# -- units -------------------------------------------------------------------------------
def test_kT_and_persistence_lengths():
    # k_B T at 298.15 K: 1.380649e-23 J/K * 298.15 K = 4.1164049935e-21 J (exact decimal).
    assert float(dna.kT(298.15)) == pytest.approx(4.1164049935, rel=1e-14)
    assert float(dna.kT(293.15, unit="J")) == pytest.approx(4.0473725435e-21, rel=1e-14)
    assert dna.PN_NM == pytest.approx(1e-21, rel=1e-15)
    # Twist modulus 410 pN nm^2 at 25 C is a twist persistence of 99.60 nm.
    assert float(dna.persistence_length(410.0)) == pytest.approx(410.0 / 4.1164049935, rel=1e-14)
    assert float(dna.stiffness_from_persistence(50.0, 310.15)) == pytest.approx(50 * 1.380649e-2 * 310.15, rel=1e-14)
    x = jnp.array([50.0, 100.0])
    np.testing.assert_allclose(dna.persistence_length(dna.stiffness_from_persistence(x)), x, rtol=1e-15)
    assert float(dna.turns_to_radians(dna.radians_to_turns(1.25))) == pytest.approx(1.25, rel=1e-15)
    with pytest.raises(ValueError, match="temperature"):
        dna.kT(-3.0)
    with pytest.raises(ValueError, match="unit"):
        dna.kT(300.0, unit="kcal")


# -- B-DNA helix -------------------------------------------------------------------------
def test_bdna_geometry_hand_values():
    kappa, tau, ell = (float(x) for x in dna.helix_from_bdna())
    # By hand: p = 0.34*10.5/(2 pi) = 0.568183 nm, r^2 + p^2 = 1.322832 nm^2,
    # kappa = 1/1.322832, tau = 0.568183/1.322832, ell = sqrt(0.34^2 + (2 pi/10.5)^2).
    assert kappa == pytest.approx(0.755954, abs=1e-6)
    assert tau == pytest.approx(0.429520, abs=1e-6)
    assert ell == pytest.approx(0.688245, abs=1e-6)
    p = 0.34 * 10.5 / (2 * math.pi)
    assert kappa == pytest.approx(1 / (1 + p * p), rel=1e-14)
    assert tau == pytest.approx(p / (1 + p * p), rel=1e-14)
    # Per base pair: rise 0.34 nm and twist 360/10.5 = 34.2857 degrees.
    rise, rotation = (float(x) for x in dna.tweezer_from_helix(kappa, tau))
    assert rise == pytest.approx(0.34, rel=1e-14)
    assert math.degrees(rotation) == pytest.approx(360 / 10.5, rel=1e-14)
    back = dna.bdna_from_helix(*dna.helix_from_bdna(rise=0.28, bp_per_turn=11.0, radius=0.9))
    np.testing.assert_allclose([float(b) for b in back], [0.28, 11.0, 0.9], rtol=1e-14)
    with pytest.raises(ValueError, match="rise"):
        dna.helix_from_bdna(rise=-0.34)
    # Traced: the bad point is NaN, the good one untouched.
    k, t, ell = jax.jit(dna.helix_from_bdna)(jnp.array([0.34, -0.34]))
    assert np.isfinite(k[0]) and np.isnan(k[1]) and np.isnan(ell[1])
    assert np.isnan(jax.jit(dna.kT)(jnp.array([300.0, -1.0]))[1])


# -- observables <-> helix -----------------------------------------------------------------
def test_observables_round_trip(rng):
    kappa = rng.uniform(0.05, 2.0, 50)
    tau = rng.uniform(-2.0, 2.0, 50)
    length = rng.uniform(0.1, 100.0, 50)
    h, theta = dna.observables_from_helix(kappa, tau, length)
    norm = np.hypot(kappa, tau)
    np.testing.assert_allclose(h, length * tau / norm, rtol=1e-14)
    np.testing.assert_allclose(theta, length * norm, rtol=1e-14)
    k2, t2 = dna.helix_from_observables(h, theta, length)
    np.testing.assert_allclose(k2, kappa, rtol=1e-12)
    np.testing.assert_allclose(t2, tau, rtol=1e-12, atol=1e-14)
    # Totals of n_bp base pairs are n_bp times the per-bp values, and invert.
    e1, r1 = dna.tweezer_from_helix(kappa, tau)
    e5, r5 = dna.tweezer_from_helix(kappa, tau, n_bp=5000)
    np.testing.assert_allclose(e5, 5000 * e1, rtol=1e-14)
    np.testing.assert_allclose(r5, 5000 * r1, rtol=1e-14)
    k3, t3 = dna.helix_from_tweezer(e5, r5, n_bp=5000)
    np.testing.assert_allclose(k3, kappa, rtol=1e-12)
    np.testing.assert_allclose(t3, tau, rtol=1e-12, atol=1e-14)


def test_changes_relative_to_bdna():
    # The B-DNA helix itself has no change.
    dh, dlk = dna.changes_from_helix(*dna.helix_from_bdna()[:2], n_bp=1000)
    assert abs(float(dh)) < 1e-12 and abs(float(dlk)) < 1e-12
    # 5 kbp stretched by 20 nm and overwound by 3 turns: by hand, h = 5000*0.34 + 20 nm,
    # Theta = 2 pi (5000/10.5 + 3), on a filament of 5000*ell.
    kappa, tau = dna.helix_from_changes(20.0, 3.0, n_bp=5000)
    ell = float(dna.helix_from_bdna()[2])
    h, theta = dna.observables_from_helix(kappa, tau, 5000 * ell)
    assert float(h) == pytest.approx(1720.0, rel=1e-13)
    assert float(theta) == pytest.approx(2 * math.pi * (5000 / 10.5 + 3), rel=1e-13)
    dh, dlk = dna.changes_from_helix(kappa, tau, n_bp=5000)
    assert float(dh) == pytest.approx(20.0, rel=1e-10)
    assert float(dlk) == pytest.approx(3.0, rel=1e-10)


def test_observables_bad_input():
    with pytest.raises(ValueError, match="extension"):
        dna.helix_from_observables(2.0, 1.0, 1.5)  # longer than the filament
    with pytest.raises(ValueError, match="rotation > 0"):
        dna.helix_from_observables(0.5, -1.0, 1.0)
    # Traced: flagged as NaN, never raised, neighbours untouched; gradients finite.
    k, t = jax.jit(dna.helix_from_observables)(jnp.array([0.5, 2.0]), jnp.array([1.0, 1.0]), 1.5)
    assert np.isfinite(k[0]) and np.isnan(k[1]) and np.isnan(t[1])
    g = jax.grad(lambda h: dna.helix_from_observables(h, 1.0, 1.0)[0])(0.3)
    assert np.isfinite(g)


# -- the classical open-coiled spring ------------------------------------------------------
def classical_compliance(B, Cw, radius, alpha, length):
    """Castigliano for an isotropic wire: U = L (T^2/2Cw + Mb^2/2B) with the twisting moment
    T = P r cos a + Q sin a and bending moment Mb = Q cos a - P r sin a (Love §270)."""
    s, c = math.sin(alpha), math.cos(alpha)
    cross = length * radius * s * c * (1 / Cw - 1 / B)
    return np.array([[length * radius**2 * (c * c / Cw + s * s / B), cross], [cross, length * (s * s / Cw + c * c / B)]])


def wire(alpha, radius=1.3, E=2.0, nu=0.3, d=0.1):
    kappa0, tau0 = (float(x) for x in hr.from_radius_angle(radius, alpha))
    rod = hr.Rod.circular(E, d / 2, nu=nu, uhat=(0.0, kappa0, tau0))
    return rod, float(rod.K1), float(rod.K3)


@pytest.mark.parametrize("degrees", PITCH_ANGLES)
def test_compliance_and_moduli_match_classical_spring(degrees):
    alpha = math.radians(degrees)
    radius, length = 1.3, 17.0
    rod, B, Cw = wire(alpha, radius)
    got = np.asarray(hr.spring_compliance(rod, rod.uhat, length))
    want = classical_compliance(B, Cw, radius, alpha, length)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=0)
    s, c = math.sin(alpha), math.cos(alpha)
    S, C, g = (float(x) for x in hr.effective_moduli(rod, rod.uhat))
    # From (S, g; g, C) = h C^-1 with h = L sin a (derivation in effective_moduli's doc).
    assert S == pytest.approx(s * (c * c * Cw + s * s * B) / radius**2, rel=1e-9)
    assert C == pytest.approx(s * (s * s * Cw + c * c * B), rel=1e-9)
    assert g == pytest.approx(s * s * c * (Cw - B) / radius, rel=1e-9)
    assert g < 0  # steel (Cw < B): a stretched spring winds up


def test_closed_coil_spring_rate():
    # Flat rings (pitch angle 0): n turns of diameter D, wire diameter d, k = G d^4/(8 D^3 n).
    E, nu, d, D, n = 206e3, 0.3, 2.0, 20.0, 8.0
    G = E / (2 * (1 + nu))
    rod = hr.Rod.circular(E, d / 2, nu=nu, uhat=(0.0, 2 / D, 0.0))
    compliance = np.asarray(hr.spring_compliance(rod, rod.uhat, n * math.pi * D))
    assert 1 / compliance[0, 0] == pytest.approx(G * d**4 / (8 * D**3 * n), rel=1e-12)
    assert compliance[0, 1] == pytest.approx(0.0, abs=1e-14)  # no coupling at zero pitch
    # ... and the open-coil rate tends to it like alpha^2.
    errors = []
    for alpha in (1e-2, 1e-3):
        rod, B, Cw = wire(alpha, radius=D / 2, E=E, nu=nu, d=d)
        L = n * math.pi * D / math.cos(alpha)
        c = np.asarray(hr.spring_compliance(rod, rod.uhat, L))
        errors.append(abs(1 / c[0, 0] / (G * d**4 / (8 * D**3 * n)) - 1))
    assert errors[1] < 1e-5 and errors[0] / errors[1] == pytest.approx(100, rel=1e-3)


def love_wrench(A, C, kappa0, tau0, kappa, tau):
    """Love's exact relations for an isotropic rod (register phi = 0) at the helix (kappa,
    tau): A(kappa - kappa0) = M cos a - F r sin a, C(tau - tau0) = M sin a + F r cos a."""
    norm = mpmath.sqrt(kappa**2 + tau**2)
    s, c, r = tau / norm, kappa / norm, kappa / norm**2
    bend, twist = A * (kappa - kappa0), C * (tau - tau0)
    return (twist * c - bend * s) / r, bend * c + twist * s


def test_loaded_compliance_matches_mpmath_derivatives_of_love():
    mpmath.mp.dps = 40
    A, C, kappa0, tau0, L = 1.0, 0.77, 0.9, 0.45, 3.0
    rod = hr.Rod(A, A, C, uhat=(0.0, kappa0, tau0))
    points = [(0.7, 0.6), (1.1, 0.2), (0.95, -0.3)]
    u = jnp.array([[0.0, k, t] for k, t in points])
    got = np.asarray(hr.spring_compliance(rod, u, L))
    for (k, t), c_got in zip(points, got):
        k, t = mpmath.mpf(k), mpmath.mpf(t)
        wrench = mpmath.matrix(2, 2)
        obs = mpmath.matrix(2, 2)
        for j, (dk, dt) in enumerate(((1, 0), (0, 1))):
            wrench[0, j] = mpmath.diff(lambda x: love_wrench(A, C, kappa0, tau0, k + dk * x, t + dt * x)[0], 0)
            wrench[1, j] = mpmath.diff(lambda x: love_wrench(A, C, kappa0, tau0, k + dk * x, t + dt * x)[1], 0)
            obs[0, j] = mpmath.diff(lambda x: L * (t + dt * x) / mpmath.hypot(k + dk * x, t + dt * x), 0)
            obs[1, j] = mpmath.diff(lambda x: L * mpmath.hypot(k + dk * x, t + dt * x), 0)
        want = np.array((obs * wrench**-1).tolist(), dtype=float)
        np.testing.assert_allclose(c_got, want, rtol=1e-9, atol=1e-12 * np.abs(want).max())


def test_reciprocity_on_constructed_equilibria(rng):
    """Anisotropic, coupled, curved rods: the compliance is symmetric (Maxwell reciprocity:
    uniform helices are the stationary points of L W - F h - M Theta).  The equilibria are
    built without helix_equilibria: pick u, K and multipliers, set m = mu1 u + mu2 e3 (the
    equilibrium condition) and uhat = u - K^-1 m."""
    rods, us = [], []
    for base in random_rods(rng, 6):
        u = np.array([*rng.normal(size=2), rng.uniform(-1.5, 1.5)])
        mu1, mu2 = rng.normal(scale=0.5, size=2)
        m = mu1 * u + np.array([0.0, 0.0, mu2])
        uhat = u - np.linalg.solve(np.asarray(base.K), m)
        rods.append(hr.Rod(base.K1, base.K2, base.K3, base.K13, base.K23, uhat))
        us.append(u)
    rod = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *rods)
    c = np.asarray(hr.spring_compliance(rod, jnp.asarray(np.array(us)), 2.0))
    assert np.all(np.isfinite(c))
    np.testing.assert_allclose(c[:, 0, 1], c[:, 1, 0], rtol=1e-9, atol=1e-12 * np.abs(c).max())
    # The compliance is positive definite only on stable branches; its inverse, the
    # tangent stiffness, is what effective_moduli rescales: check that relation too.
    S, C, g = hr.effective_moduli(rod, jnp.asarray(np.array(us)))
    h = np.array([u[2] / np.linalg.norm(u) for u in us])
    stiffness = h[:, None, None] * np.linalg.inv(c / 2.0)
    np.testing.assert_allclose(np.stack([S, g, g, C], -1).reshape(-1, 2, 2), stiffness, rtol=1e-9)


def test_spring_errors_are_flagged():
    # An equilibrium by construction: m = mu1 u + mu2 e3, uhat = u - K^-1 m.
    K = np.array([[1.0, 0.0, 0.5], [0.0, 1.5, 0.5], [0.5, 0.5, 0.8]])
    good = jnp.array([0.4, 0.8, 0.7])
    uhat = np.asarray(good) - np.linalg.solve(K, 0.3 * np.asarray(good) + np.array([0.0, 0.0, -0.2]))
    rod = hr.Rod(1.0, 1.5, 0.8, 0.5, 0.5, uhat)
    bad = good.at[0].add(0.3)  # off every register
    with pytest.raises(eqx.EquinoxRuntimeError, match="not a uniform helical equilibrium"):
        hr.spring_compliance(rod, bad, 1.0)
    # Batch with throw=False: the bad point is NaN, the good one is untouched.
    out = hr.spring_compliance(rod, jnp.stack([good, bad, jnp.zeros(3)]), 1.0, throw=False)
    assert np.all(np.isfinite(out[0])) and np.all(np.isnan(out[1])) and np.all(np.isnan(out[2]))
    with pytest.raises(ValueError, match="trailing axis"):
        hr.spring_compliance(rod, jnp.zeros(2), 1.0)
    # A flat ring has no axial length: moduli undefined.
    ring = hr.Rod(1.0, 1.0, 0.7, uhat=(0.0, 1.0, 0.0))
    S, C, g = hr.effective_moduli(ring, ring.uhat, throw=False)
    assert np.isnan(S) and np.isnan(C) and np.isnan(g)


@pytest.mark.slow  # compiles second derivatives of helix_equilibria (~1 min on 2 busy cores)
def test_moduli_jit_and_derivative():
    # d S / d Cw of an isotropic wire = sin a cos^2 a / r^2 (differentiate the closed form).
    alpha, radius = math.radians(30.0), 1.0
    kappa0, tau0 = (float(x) for x in hr.from_radius_angle(radius, alpha))

    @jax.jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def stretch(Cw):
        rod = hr.Rod(1.0, 1.0, Cw, uhat=jnp.array([0.0, kappa0, tau0]))
        return hr.effective_moduli(rod, rod.uhat, throw=False)[0]

    s, c = math.sin(alpha), math.cos(alpha)
    assert float(stretch(0.8)) == pytest.approx(s * (c * c * 0.8 + s * s) / radius**2, rel=1e-9)
    stretch(0.9)  # no retrace
    dS = float(jax.jacfwd(stretch)(0.8))
    assert dS == pytest.approx(math.sin(alpha) * math.cos(alpha) ** 2 / radius**2, rel=1e-9)


# -- datasets ------------------------------------------------------------------------------
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
