"""spring_compliance and effective_moduli against the classical open-coiled spring (energy
method, derived independently in tests/helpers.py), the closed-coil spring rate, mpmath
derivatives of Love's exact helix relations, and Maxwell reciprocity."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest
from helpers import classical_compliance, random_rods

import helixrod as hr

PITCH_ANGLES = [5.0, 20.0, 45.0, 70.0, 85.0]  # degrees


# -- the classical open-coiled spring ------------------------------------------------------
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
