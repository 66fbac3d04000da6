"""Stress suite: adversarial cases, each against a high-precision (mpmath) reference or an
exact property, with its documented expected behaviour.

Every test states the behaviour it checks (the "contract") and the bound it asserts; the
bounds are the documented accuracies of the README's Validation section, where the
measured maxima are listed too (`pytest tests/test_stress.py -s` prints them).

Cost: every jitted function here is compiled once and shared (fixed batch size `N`); no case
needs `@pytest.mark.slow` (10^4 turns of a helix take a fraction of a second).
"""

from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
import textwrap
import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

import helixrod as hr

EPS = float(np.finfo(np.float64).eps)
N = 64  # batch size of every shared jitted call (padded), so each compiles once
mpmath.mp.dps = 30  # references to ~1e-25: far below every bound checked

ROOTS = jax.jit(hr.register_roots)
EQ = jax.jit(hr.helix_equilibria)
HYPOTHESIS = settings(
    derandomize=True, deadline=None, max_examples=25, suppress_health_check=[HealthCheck.too_slow]
)

# -- the measured catalogue: test name -> (measured maximum, asserted bound) -----------------
CATALOGUE: dict[str, tuple[float, float, bool]] = {}


def record(case: str, measured: float, bound: float, *, at_least: bool = False) -> None:
    """Store a case's measured value and assert it meets the documented bound (an upper bound
    on an error; a lower bound with `at_least`, for what a report must flag as large)."""
    measured = float(measured)
    old = CATALOGUE.get(case, (measured, bound, at_least))[0]
    CATALOGUE[case] = (min(old, measured) if at_least else max(old, measured), bound, at_least)
    if at_least:
        assert measured >= bound, f"{case}: measured {measured:.3g} < documented {bound:.3g}"
    else:
        assert measured <= bound, f"{case}: measured {measured:.3g} > documented {bound:.3g}"


@pytest.fixture(scope="module", autouse=True)
def _print_catalogue():
    yield
    if CATALOGUE:
        print("\n\nstress catalogue (worst measured value, documented bound):")
        for case, (measured, bound, at_least) in CATALOGUE.items():
            print(f"  {case:62s} {measured:10.3g}   {'>=' if at_least else '<='} {bound:.3g}")


# -- references --------------------------------------------------------------------------


def mp_register_roots(A, B, C):
    """Every real root in [0, 2 pi) of A sin 2p + B sin p + C cos p for the exact float64
    values A, B, C: roots of the quartic in t = tan(p/2) (mpmath polyroots, 30 digits), plus
    p = pi when C = 0 (the quartic then drops a degree).  Independent of helixrod."""
    A, B, C = (mpmath.mpf(float(x)) for x in (A, B, C))
    scale = max(abs(A), abs(B), abs(C))
    return list(_mp_roots_normalised(A / scale, B / scale, C / scale))  # same roots


@functools.lru_cache(maxsize=None)
def _mp_roots_normalised(A, B, C):
    coeffs = [-C, 2 * B - 4 * A, 0, 4 * A + 2 * B, C]
    extra = [mpmath.pi] if C == 0 else []
    while coeffs and coeffs[0] == 0:
        coeffs = coeffs[1:]
    if len(coeffs) < 2:
        raise ValueError("every phi is a root")
    if coeffs[-1] == 0:  # t = 0 (p = 0) is a root: divide it out
        extra.append(mpmath.mpf(0))
        coeffs = coeffs[:-1]
        while coeffs and coeffs[-1] == 0:
            coeffs = coeffs[:-1]
    with warnings.catch_warnings():  # mpmath >= 1.4 prefers asc=True; 1.3 lacks it
        warnings.simplefilter("ignore", DeprecationWarning)
        try:
            found = mpmath.polyroots(coeffs, maxsteps=200, extraprec=60) if len(coeffs) > 1 else []
        except mpmath.mp.NoConvergence:  # (near-)double roots converge slowly
            found = mpmath.polyroots(coeffs, maxsteps=1000, extraprec=300)
    tiny = mpmath.mpf(10) ** -12
    roots = [2 * mpmath.atan(mpmath.re(r)) for r in found if abs(mpmath.im(r)) < tiny] + extra
    return tuple(sorted(mpmath.fmod(p + 4 * mpmath.pi, 2 * mpmath.pi) for p in roots))


def mp_f(A, B, C, p):
    p = mpmath.mpf(float(p))
    return A * mpmath.sin(2 * p) + B * mpmath.sin(p) + C * mpmath.cos(p)


def mp_equilibria(params, kappa, tau):
    """(phi, F, M) of every register of the rod `params` = (K1, K2, K3, K13, K23, u1, u2, u3)
    at (kappa, tau), in 30-digit arithmetic from the exact float64 inputs, straight from
    DESIGN.md: A = (K1 - K2) kappa/2, B = K2 u2 + K23 (u3 - tau), C = K13 (tau - u3) - K1 u1;
    u = (kappa sin p, kappa cos p, tau), m = K (u - uhat), mu1 = (m1 u1 + m2 u2)/kappa^2,
    mu2 = m3 - mu1 tau, F = n.a = mu2 |u| and M = m.a = m.u/|u| (the definition; it equals
    mu1 |u| + mu2 tau/|u| at an equilibrium without that form's cancellation as kappa -> 0)."""
    K1, K2, K3, K13, K23, u1h, u2h, u3h = (mpmath.mpf(float(x)) for x in params)
    k, t = (x if isinstance(x, mpmath.mpf) else mpmath.mpf(float(x)) for x in (kappa, tau))
    A = (K1 - K2) * k / 2
    B = K2 * u2h + K23 * (u3h - t)
    C = K13 * (t - u3h) - K1 * u1h
    out = []
    for p in mp_register_roots(A, B, C):
        u = (k * mpmath.sin(p), k * mpmath.cos(p), t)
        v = (u[0] - u1h, u[1] - u2h, u[2] - u3h)
        m = (K1 * v[0] + K13 * v[2], K2 * v[1] + K23 * v[2], K13 * v[0] + K23 * v[1] + K3 * v[2])
        mu1 = (m[0] * u[0] + m[1] * u[1]) / k**2
        mu2 = m[2] - mu1 * t
        norm = mpmath.sqrt(k**2 + t**2)
        out.append((p, mu2 * norm, (m[0] * u[0] + m[1] * u[1] + m[2] * u[2]) / norm))
    return out


def angular(x, y):
    return np.abs(np.angle(np.exp(1j * (np.asarray(x, float) - np.asarray(y, float)))))


def roots(A, B, C):
    """Shared jitted `register_roots` on coefficients padded to N (one compilation)."""
    n = len(A)
    assert n <= N
    pad = lambda x, v: np.concatenate([np.asarray(x, float), np.full(N - n, v)])  # noqa: E731
    return [np.asarray(x)[:n] for x in ROOTS(pad(A, 1.0), pad(B, 0.2), pad(C, 0.3))]


def rods(params):
    """A batch Rod of shape (N,) from a list of parameter 8-tuples (padded with the first)."""
    P = np.asarray(params, float)
    P = np.concatenate([P, np.repeat(P[:1], N - len(P), axis=0)])
    return hr.Rod(P[:, 0], P[:, 1], P[:, 2], P[:, 3], P[:, 4], P[:, 5:8])


def equilibria(params, kappa, tau):
    """Shared jitted `helix_equilibria` on a padded batch of (rod, kappa, tau) triples."""
    n = len(params)
    assert n <= N
    pad = lambda x: np.concatenate([np.asarray(x, float), np.full(N - n, 1.0)])  # noqa: E731
    eq = EQ(rods(params), pad(kappa), pad(tau))
    return jax.tree.map(lambda x: np.asarray(x)[:n], eq)


def compare_with_mp(params, kappa, tau):
    """Max over points of (register error, normwise F error, normwise M error) against
    `mp_equilibria`, after checking the register count.  F and M errors are relative to
    max(|reference|, natural scale), natural scale = max|K_ij| |u| (|u| + |uhat|) for F and
    max|K_ij| (|u| + |uhat|) for M."""
    eq = equilibria(params, kappa, tau)
    worst = np.zeros(3)
    for i, (p, k, t) in enumerate(zip(params, kappa, tau)):
        ref = mp_equilibria(p, k, t)
        valid = eq.valid[i]
        assert valid.sum() == len(ref), (p, k, t, eq.phi[i], [float(r[0]) for r in ref])
        kmax = np.max(np.abs(p[:5]))
        norm_u = np.hypot(k, t)
        reach = norm_u + np.linalg.norm(p[5:])
        for phi, F, M in zip(eq.phi[i][valid], eq.force[i][valid], eq.moment[i][valid]):
            j = int(np.argmin([angular(phi, float(r[0])) for r in ref]))
            rphi, rF, rM = (float(x) for x in ref[j])
            worst[0] = max(worst[0], angular(phi, rphi))
            worst[1] = max(worst[1], abs(F - rF) / max(abs(rF), kmax * norm_u * reach))
            worst[2] = max(worst[2], abs(M - rM) / max(abs(rM), kmax * reach))
    return worst


# A generic coupled, intrinsically curved rod (Chouaieb-Goriely-Maddocks fig. 2 family).
GENERIC = (1.0, 1.5, 0.8, 0.3, -0.2, 0.4, -0.3, 0.2)


# == registers ================================================================================


def _pair_coefficients(p0, gap, A=1.0):
    """Float64 (A, B, C) whose exact (30-digit) register pair sits at p0 -+ gap, rounded."""
    ps = [mpmath.mpf(p0) - mpmath.mpf(gap), mpmath.mpf(p0) + mpmath.mpf(gap)]
    M = mpmath.matrix([[mpmath.sin(p), mpmath.cos(p)] for p in ps])
    B, C = mpmath.lu_solve(M, mpmath.matrix([-A * mpmath.sin(2 * p) for p in ps]))
    return float(A), float(B), float(C)


def _check_near_tangent(A, B, C, case, p0=None, gap=None):
    """The documented behaviour near a tangency (`_roots.py` docstring), against the exact
    roots of the float64 coefficients:

    - every reported register is a root to within 8 eps (|f(phi)| <= 8 eps S,
      S = |A| + |B| + |C|), i.e. backward stable;
    - every exact root r is matched within 8 eps S / |f'(r)| (its condition number; near a
      pair |f'(r)| ~ |f''| g with g half the pair's separation: accuracy ~ eps/gap), or,
      for a pair closer than 1e-7, by one `tangent` register within g + 1e-9;
    - four exact roots all further apart than 2e-7 are always reported as four registers
      (where the exact pair is complex but within eps of a tangency, a `tangent` register
      or a pair may be reported: the backward bound above is what holds then).
    Returns the largest forward error in units of eps S / |f'(r)|, and the largest distance
    to the analytic pair p0 -+ gap the coefficients were rounded from (where the rounded
    problem lost the pair, |f(p0)| <= 4 eps S is checked instead)."""
    phi, _, _, valid, _, tangent = roots(A, B, C)
    worst_fwd, worst_analytic = 0.0, 0.0
    for i in range(len(A)):
        S = abs(A[i]) + abs(B[i]) + abs(C[i])
        ours = phi[i][valid[i]]
        backward = max(abs(float(mp_f(A[i], B[i], C[i], x))) for x in ours) / S
        assert backward <= 8 * EPS, (case, A[i], B[i], C[i], ours, backward)
        ref = mp_register_roots(A[i], B[i], C[i])
        ref_f = np.array([float(r) for r in ref])
        half_gaps = [np.min(angular(ref_f[np.arange(len(ref)) != j], r)) / 2 for j, r in enumerate(ref_f)]
        for r, r_f, g in zip(ref, ref_f, half_gaps):
            err = np.min(angular(ours, r_f))
            if tangent[i].any() and g < 1e-7 and np.argmin(angular(ours, r_f)) == 2:
                assert err <= g + 1e-9, (case, A[i], B[i], C[i], ours, ref_f)
            else:
                slope = abs(float(2 * A[i] * mpmath.cos(2 * r) + B[i] * mpmath.cos(r) - C[i] * mpmath.sin(r)))
                scaled = err * slope / (EPS * S)
                assert scaled <= 8, (case, A[i], B[i], C[i], ours, ref_f, scaled)
                worst_fwd = max(worst_fwd, scaled)
        if len(ref) == 4 and min(half_gaps) >= 1e-7:
            assert not tangent[i].any() and valid[i].sum() == len(ref), (case, A[i], B[i], C[i], ours, ref_f)
        if p0 is not None:
            distance = max(np.min(angular(ours, target)) for target in (p0[i] - gap, p0[i] + gap))
            if distance <= max(2 * gap, 3e-8):
                worst_analytic = max(worst_analytic, distance)
            else:  # the pair did not survive rounding: f(p0) is within eps of zero
                assert gap < 1e-7 and abs(float(mp_f(A[i], B[i], C[i], p0[i]))) <= 4 * EPS * S, (case, p0[i])
    return worst_fwd, worst_analytic


_GAPS = [1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12]


@pytest.mark.parametrize("gap", _GAPS)
def test_near_tangent_pairs(gap):
    """Pairs constructed analytically at p0 -+ gap (30 digits) and rounded to float64.
    Below gap ~ 1e-8 the rounding of B, C (relative eps) moves the pair by ~sqrt(eps): the
    float64 problem then has a pair ~1e-8 apart or none, and its exact roots are the
    reference.  Expected: the contract of `_check_near_tangent`, and the analytic pair
    found within max(2 gap, 3e-8) (sqrt(eps) resolution) unless rounding removed it."""
    p0 = np.linspace(0.05, 6.25, 60)
    A = np.empty_like(p0)
    B = np.empty_like(p0)
    C = np.empty_like(p0)
    for i, p in enumerate(p0):
        A[i], B[i], C[i] = _pair_coefficients(p, gap)
    fwd, analytic = _check_near_tangent(A, B, C, f"near-tangent gap {gap:g}", p0, gap)
    record("registers: near-tangent, |dphi| |f'| / (eps S)", fwd, 8.0)
    record(f"registers: near-tangent gap {gap:.0e}, |phi - p0 -+ gap|", analytic, max(2 * gap, 3e-8))


def test_near_tangent_separator_misses_pair():
    """Regression: the bracketing solver before the secular-equation rewrite returned slot 2 at
    phi = pi (f = 0.695, not a root) here, the near-tangent pair at 2.3618643991 and
    2.3618644144 falling on one side of its bracket separator."""
    A, B, C = np.array([1.0]), np.array([0.7191682652388862]), np.array([-0.6951134908682212])
    _check_near_tangent(A, B, C, "separator")


def test_exact_tangency():
    """Coefficients exactly on the astroid |B|^(2/3) + |C|^(2/3) = (2A)^(2/3):
    (A, B, C) = (62.5, 27, 64) (cos = 3/5, sin = 4/5), in all sign combinations and scaled
    by 2^-60 ... 2^60.  Exact double root.  Expected: one `tangent` register (count 3) within
    sqrt(eps) of the double root (mpmath), and slots 0, 1 to 8 eps."""
    A, B, C = [], [], []
    for sa in (1, -1):
        for sb in (1, -1):
            for sc in (1, -1):
                for k in (-60, 0, 60):
                    A.append(sa * 62.5 * 2.0**k)
                    B.append(sb * 27.0 * 2.0**k)
                    C.append(sc * 64.0 * 2.0**k)
    A, B, C = np.array(A), np.array(B), np.array(C)
    phi, _, _, valid, _, tangent = roots(A, B, C)
    worst_tangent, worst_simple = 0.0, 0.0
    for i in range(len(A)):
        ref = np.array([float(r) for r in mp_register_roots(A[i], B[i], C[i])])
        assert valid[i].tolist() == [True, True, True, False] and tangent[i].tolist() == [False, False, True, False]
        for slot in range(3):
            err = np.min(angular(ref, phi[i, slot]))
            if slot == 2:
                worst_tangent = max(worst_tangent, err)
            else:
                worst_simple = max(worst_simple, err)
    record("registers: exact tangency, tangent register", worst_tangent, np.sqrt(EPS))
    record("registers: exact tangency, simple registers", worst_simple, 8 * EPS)


def test_K1_minus_K2_to_zero():
    """K2 = K1 (1 + rel), rel = 1e-2 ... 1e-14, for a coupled, curved rod at several helices:
    A -> 0 and the quartic degenerates (the inner pair leaves through the astroid's cusp).
    Expected: register count and registers as the 30-digit reference, phi to 1e-12 and the
    wrench to 1e-12 (normwise; `compare_with_mp`); at rel = 0 exactly, two registers."""
    params, kappa, tau = [], [], []
    for rel in [1e-2, 1e-4, 1e-6, 1e-8, 1e-10, 1e-12, 1e-14, 0.0]:
        for k, t in [(0.5, 0.3), (1.7, -1.2), (3.0, 0.2)]:
            params.append((1.0, 1.0 + rel, 0.8, 0.3, -0.2, 0.4, -0.3, 0.2))
            kappa.append(k)
            tau.append(t)
    worst = compare_with_mp(params, kappa, tau)
    record("registers: K1 - K2 -> 0, |dphi|", worst[0], 1e-12)
    record("registers: K1 - K2 -> 0, wrench (normwise)", max(worst[1:]), 1e-12)


def _love(K, K3, u3h, kappa, tau):
    """Closed form for the isotropic rod (Love): F = |u| (K3 (tau - u3h) - K tau),
    M = (K kappa^2 + K3 (tau - u3h) tau)/|u|, the same for every register."""
    norm = np.hypot(kappa, tau)
    return norm * (K3 * (tau - u3h) - K * tau), (K * kappa**2 + K3 * (tau - u3h) * tau) / norm


_ISO_PATHS = {
    # name: rod parameters as a function of the distance d to the isotropic rod
    # (K = 1.2, K3 = 0.9, uhat3 = 0.3)
    "K2 - K1 = d": lambda d: (1.2, 1.2 + d, 0.9, 0.0, 0.0, 0.0, 0.0, 0.3),
    "K13 = d": lambda d: (1.2, 1.2, 0.9, d, 0.0, 0.0, 0.0, 0.3),
    "uhat1 = d": lambda d: (1.2, 1.2, 0.9, 0.0, 0.0, d, 0.0, 0.3),
    "all at once": lambda d: (1.2, 1.2 * (1 + d), 0.9, 0.3 * d, -0.2 * d, 0.4 * d, -0.3 * d, 0.3),
}


@pytest.mark.parametrize("path", list(_ISO_PATHS))
def test_isotropic_limit(path):
    """The fully isotropic rod approached along several paths, d = 1e-2 ... 1e-14, and d = 0.
    Expected: `continuum` exactly at d = 0 (one representative register) and never for d > 0;
    every register's F and M within 2 d (relative to the natural scale) of Love's closed
    form, so the limit is continuous; against mpmath to 1e-12 for d > 0.  Also the radial
    path K1 = K2 with couplings, tau -> uhat3 (B = C = 0 at tau = uhat3: a continuum)."""
    ds = [1e-2, 1e-5, 1e-8, 1e-11, 1e-14]
    helices = [(0.6, 0.9), (1.5, -0.4), (2.0, 1.7)]
    params = [_ISO_PATHS[path](d) for d in ds + [0.0] for _ in helices]
    kappa = [k for _ in ds + [0.0] for k, _ in helices]
    tau = [t for _ in ds + [0.0] for _, t in helices]
    eq = equilibria(params, kappa, tau)
    n_d = len(ds) * len(helices)
    assert not eq.continuum[:n_d].any() and eq.continuum[n_d:].all()
    assert (eq.count[n_d:] == 1).all() and (eq.count[:n_d] >= 2).all()
    worst = 0.0
    for i, (k, t) in enumerate(zip(kappa, tau)):
        d = ds[i // len(helices)] if i < n_d else 0.0
        F, M = _love(1.2, 0.9, 0.3, k, t)
        scale = 1.2 * np.hypot(k, t) * (np.hypot(k, t) + 0.3)
        dev = max(np.max(np.abs(eq.force[i][eq.valid[i]] - F)) / scale, np.max(np.abs(eq.moment[i][eq.valid[i]] - M)) / scale)
        assert dev <= 2 * d + 4 * EPS, (path, d, k, t, dev)
        worst = max(worst, dev / max(d, EPS))
    record("registers: isotropic limit, |(F, M) - Love| / d", worst, 2.0)
    mp_worst = compare_with_mp(params[:n_d], kappa[:n_d], tau[:n_d])
    record("registers: isotropic limit (d > 0) vs mpmath, |dphi|", mp_worst[0], 1e-12)
    record("registers: isotropic limit (d > 0) vs mpmath, wrench", max(mp_worst[1:]), 1e-12)


def test_isotropic_radial_path():
    """K1 = K2 with couplings (A = 0, B = K23 (u3 - tau), C = K13 (tau - u3)) along
    tau = uhat3 + d, d -> 0.  For d != 0 the registers are fixed (tan phi = -C/B) and the
    wrench is smooth in d.  Expected: two registers for d != 0 matching mpmath (phi to
    1e-12, wrench to 1e-12), `continuum` exactly at d = 0 and only there."""
    ds = [1e-2, -1e-4, 1e-6, -1e-9, 1e-12, -1e-15, 0.0]
    rod = (1.2, 1.2, 0.9, 0.3, -0.2, 0.0, 0.0, 0.3)
    eq = equilibria([rod] * len(ds), [0.8] * len(ds), [0.3 + d for d in ds])
    assert eq.continuum.tolist() == [False] * (len(ds) - 1) + [True]
    assert eq.count.tolist() == [2] * (len(ds) - 1) + [1]
    mp_worst = compare_with_mp([rod] * 6, [0.8] * 6, [0.3 + d for d in ds[:-1]])
    record("registers: K1 = K2, tau -> uhat3 vs mpmath, |dphi|", mp_worst[0], 1e-12)
    record("registers: K1 = K2, tau -> uhat3 vs mpmath, wrench", max(mp_worst[1:]), 1e-12)


def test_continuum_wrench():
    """A `continuum` point: every register of the family is an equilibrium with the same
    energy.  Fully isotropic rod: one axial force and moment for the whole family.  K1 = K2
    with couplings at tau = uhat3 (B = C = 0): m3 = kappa (K13 sin phi + K23 cos phi) varies
    with phi, so the wrench does too (F in [-0.554, -0.061] for the rod below), and slot 0
    reports the member phi = 0, as documented (found by this suite: the docstring used to
    promise one wrench)."""
    for params, one_wrench in [((1.2, 1.2, 0.9, 0.0, 0.0, 0.0, 0.0, 0.3), True), ((1.2, 1.2, 0.9, 0.3, -0.2, 0.0, 0.0, 0.3), False)]:
        rod = hr.Rod(*params[:5], uhat=params[5:])
        kappa, tau = 0.8, 0.3
        eq = equilibria([params], [kappa], [tau])
        assert eq.continuum[0] and eq.phi[0, 0] == 0.0
        phi = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        u = np.stack([kappa * np.sin(phi), kappa * np.cos(phi), np.full_like(phi, tau)], -1)
        m = np.asarray(rod.moment(u))
        mu1 = (m[:, 0] * u[:, 0] + m[:, 1] * u[:, 1]) / kappa**2
        mu2 = m[:, 2] - mu1 * tau
        assert np.max(np.abs(hr.helix_residual(rod, u, mu2[:, None] * u))) < 1e-15
        energy = np.asarray(rod.energy(u))
        np.testing.assert_allclose(energy, eq.energy[0, 0], rtol=0, atol=1e-15)
        F = mu2 * np.hypot(kappa, tau)
        np.testing.assert_allclose(F[0], eq.force[0, 0], rtol=0, atol=1e-14)
        assert (np.ptp(F) < 1e-14) == one_wrench


def test_kappa_to_zero():
    """kappa = 1e-2 ... 1e-10 and 1e-100 for a curved coupled rod and a naturally straight
    coupled one (both wrenches diverge like 1/kappa: a coupled rod bends when twisted) and an
    uncoupled straight one (finite limit).  Expected: the reference's registers, phi to
    1e-12, F relative to max(|reference|, natural scale) to 1e-12, and M too for the
    uncoupled rod (for the others see `test_moment_cancellation_small_kappa`); `straight`
    only at kappa = 0 exactly, no register there."""
    ks = [1e-2, 1e-4, 1e-6, 1e-8, 1e-10, 1e-100]
    coupled_straight = (1.0, 1.5, 0.8, 0.3, -0.2, 0.0, 0.0, 0.2)
    uncoupled_straight = (1.0, 1.5, 0.8, 0.0, 0.0, 0.0, 0.0, 0.2)
    params = [GENERIC] * len(ks) + [coupled_straight] * len(ks)
    worst = compare_with_mp(params, ks * 2, [0.7] * (2 * len(ks)))
    straight = compare_with_mp([uncoupled_straight] * len(ks), ks, [0.7] * len(ks))
    record("registers: kappa -> 0, |dphi|", max(worst[0], straight[0]), 1e-12)
    record("registers: kappa -> 0, F (relative)", max(worst[1], straight[1]), 1e-12)
    record("registers: kappa -> 0, M of the uncoupled straight rod", straight[2], 1e-12)
    eq = equilibria([GENERIC, GENERIC], [0.0, 1e-10], [0.7, 0.7])
    assert eq.straight.tolist() == [True, False] and eq.count.tolist() == [0, 2]


def test_moment_cancellation_small_kappa():
    """The axial moment M of curved and coupled rods as kappa -> 0 (1e-4 ... 1e-10): expected,
    like F, within 1e-12 of mpmath relative to max(|M|, natural scale), and dM/dkappa at
    kappa = 1e-10 by forward and reverse mode within 1e-6 of a 30-digit central difference."""
    cases = list(EDGES.values())  # the inputs of test_gradients_finite_at_the_edges: one compilation
    i = list(EDGES).index("kappa = 1e-10")
    args = (jnp.asarray([c[0] for c in cases]), jnp.asarray([c[1] for c in cases]), jnp.asarray([c[2] for c in cases]))
    phi = np.asarray(equilibria(*[[c[j] for c in cases] for j in range(3)]).phi[i])
    h = mpmath.mpf("1e-14")
    plus, minus = mp_equilibria(GENERIC, mpmath.mpf("1e-10") + h, 0.7), mp_equilibria(GENERIC, mpmath.mpf("1e-10") - h, 0.7)
    for mode in (_JACFWD, _JACREV):
        dM = np.asarray(mode(*args)[1])[i, 1]
        for slot in np.flatnonzero(np.isfinite(phi)):
            j = int(np.argmin([angular(phi[slot], float(r[0])) for r in plus]))
            exact = float((plus[j][2] - minus[j][2]) / (2 * h))
            assert abs(dM[slot] - exact) <= 1e-6 * max(abs(exact), 1.0), (mode, slot, dM[slot], exact)
    ks = [1e-4, 1e-6, 1e-8, 1e-10]
    coupled_straight = (1.0, 1.5, 0.8, 0.3, -0.2, 0.0, 0.0, 0.2)
    worst = compare_with_mp([GENERIC] * len(ks) + [coupled_straight] * len(ks), ks * 2, [0.7] * 8)
    assert worst[2] <= 1e-12, worst


def test_kappa_below_sqrt_tiny():
    """kappa = 1e-160 and 1e-300: the wrench (~1/kappa) is representable.  Expected: finite
    values matching mpmath, or the point flagged (no valid register)."""
    eq = equilibria([GENERIC, GENERIC], [1e-160, 1e-300], [0.7, 0.7])
    for i in range(2):
        v = eq.valid[i]
        assert not v.any() or (np.all(np.isfinite(eq.force[i][v])) and np.all(np.isfinite(eq.moment[i][v])))
    worst = compare_with_mp([GENERIC, GENERIC], [1e-160, 1e-300], [0.7, 0.7])
    assert max(worst) <= 1e-12


def test_tau_to_zero_rings():
    """Rings: tau = 0, -+1e-300, -+1e-12, 1e-6 for a generic rod, and the closed form for
    the naturally straight uncoupled rod (registers on the axes; slot phi = 0 is
    u = (0, kappa, 0): F = 0, M = K2 kappa; phi = pi/2: F = 0, M = K1 kappa).
    Expected: reference registers and wrench to 1e-12; closed forms to 4 eps."""
    taus = [0.0, 1e-300, -1e-300, 1e-12, -1e-12, 1e-6]
    worst = compare_with_mp([GENERIC] * len(taus), [0.9] * len(taus), taus)
    record("registers: tau -> 0 rings, |dphi|", worst[0], 1e-12)
    record("registers: tau -> 0 rings, wrench", max(worst[1:]), 1e-12)
    K1, K2, kappa = 0.7, 1.9, 1.3
    eq = equilibria([(K1, K2, 0.8, 0.0, 0.0, 0.0, 0.0, 0.0)], [kappa], [0.0])
    v = eq.valid[0]
    assert v.sum() == 4
    expected_M = np.where(np.abs(np.cos(eq.phi[0][v])) > 0.5, K2 * kappa, K1 * kappa)
    err = max(np.max(np.abs(eq.force[0][v])), np.max(np.abs(eq.moment[0][v] - expected_M)))
    record("registers: straight uncoupled ring, closed form", err, 4 * EPS)


def test_norm_u_large_and_small():
    """|u| = 1e-12 ... 1e12 at fixed uhat against mpmath (phi to 1e-12, wrench normwise to
    1e-12), and the exact length-scale symmetry: (kappa, tau, uhat) -> s (kappa, tau, uhat)
    leaves the registers unchanged and scales mu1 by 1, F by s^2, M by s -- bit for bit for
    s a power of two (2^-40 ... 2^40)."""
    scales = [1e-12, 1e-8, 1e-4, 1.0, 1e4, 1e8, 1e12]
    worst = compare_with_mp([GENERIC] * len(scales), [0.8 * s for s in scales], [-0.6 * s for s in scales])
    record("registers: |u| = 1e-12 ... 1e12, |dphi|", worst[0], 1e-12)
    record("registers: |u| = 1e-12 ... 1e12, wrench", max(worst[1:]), 1e-12)
    powers = [2.0**k for k in range(-40, 41, 8)]
    K = GENERIC[:5]
    u = np.array(GENERIC[5:])
    params = [K + tuple(s * u) for s in powers]
    eq = equilibria(params, [0.8 * s for s in powers], [-0.6 * s for s in powers])
    ref = powers.index(1.0)
    for i, s in enumerate(powers):
        np.testing.assert_array_equal(eq.phi[i], eq.phi[ref])
        np.testing.assert_array_equal(eq.force[i], s * s * eq.force[ref])
        np.testing.assert_array_equal(eq.moment[i], s * eq.moment[ref])
    record("registers: length scale 2^k, bitwise", 0.0, 0.0)


# == scales ===================================================================================


def test_stiffness_ratios():
    """K2/K1 and K3/K1 from 1e-6 to 1e6 (couplings at 0.3 and -0.2 of their positive-definite
    limit sqrt(K_i K3)).  Expected: reference register count, phi to 1e-12, wrench to 1e-12
    relative to the largest stiffness (normwise backward stable)."""
    ratios = [1e-6, 1e-3, 1.0, 1e3, 1e6]
    params, kappa, tau = [], [], []
    for a in ratios:
        for g in ratios:
            K1, K2, K3 = 1.0, a, g
            params.append((K1, K2, K3, 0.3 * np.sqrt(K1 * K3), -0.2 * np.sqrt(K2 * K3), 0.4, -0.3, 0.2))
            kappa.append(1.1)
            tau.append(0.7)
    worst = compare_with_mp(params, kappa, tau)
    record("scales: stiffness ratios 1e-6 ... 1e6, |dphi|", worst[0], 1e-12)
    record("scales: stiffness ratios 1e-6 ... 1e6, wrench", max(worst[1:]), 1e-12)


@HYPOTHESIS
@given(
    k=st.integers(-90, 0),
    ratio=st.floats(1e-6, 1e6),
    coupling=st.floats(-0.9, 0.9),
    kappa=st.floats(1e-3, 10.0),
    tau=st.floats(-10.0, 10.0),
)
def test_scale_equivariance_powers_of_two(k, ratio, coupling, kappa, tau):
    """Stiffness scaled by 2^k, k = -90 ... 0 (8e-28 ... 1 N m^2): registers, validity and
    stability bit for bit unchanged, F and M exactly 2^k times (no rounding in either)."""
    base = (1.0, ratio, 0.7, coupling * np.sqrt(0.7) * 0.7, 0.2 * np.sqrt(0.7 * ratio), 0.5, -0.1, 0.3)
    s = 2.0**k
    scaled = tuple(s * x for x in base[:5]) + base[5:]
    eq = equilibria([base, scaled], [kappa, kappa], [tau, tau])
    np.testing.assert_array_equal(eq.phi[1], eq.phi[0])
    np.testing.assert_array_equal(eq.stable[1], eq.stable[0])
    np.testing.assert_array_equal(eq.force[1], s * eq.force[0])
    np.testing.assert_array_equal(eq.moment[1], s * eq.moment[0])
    record("scales: K x 2^k (k = -90 ... 0), bitwise", 0.0, 0.0)


def test_scale_equivariance_decimal():
    """Stiffness scaled by 10^-27 ... 10^0 (pN nm^2 to N m^2), where K s is rounded:
    expected registers within 1e-14 (absolute) and F, M within 1e-14 relative to the
    wrench's natural scale; identical validity and stability."""
    factors = [10.0**-k for k in range(0, 28, 3)]
    params = [tuple(f * x for x in GENERIC[:5]) + GENERIC[5:] for f in factors]
    kappa, tau = [0.9] * len(factors), [0.4] * len(factors)
    eq = equilibria(params, kappa, tau)
    worst_phi, worst_w = 0.0, 0.0
    scale = max(abs(x) for x in GENERIC[:5]) * np.hypot(0.9, 0.4) * (np.hypot(0.9, 0.4) + np.linalg.norm(GENERIC[5:]))
    for i, f in enumerate(factors):
        np.testing.assert_array_equal(eq.valid[i], eq.valid[0])
        np.testing.assert_array_equal(eq.stable[i], eq.stable[0])
        v = eq.valid[0]
        worst_phi = max(worst_phi, np.max(angular(eq.phi[i][v], eq.phi[0][v])))
        worst_w = max(worst_w, np.max(np.abs(eq.force[i][v] / f - eq.force[0][v])) / scale)
        worst_w = max(worst_w, np.max(np.abs(eq.moment[i][v] / f - eq.moment[0][v])) / scale)
    record("scales: K x 10^-27 ... 1, |dphi|", worst_phi, 1e-14)
    record("scales: K x 10^-27 ... 1, wrench", worst_w, 1e-14)


# == the static Kirchhoff ODE ==================================================================


@eqx.filter_jit
def _ode(rod, n0, m0, length, frame0, x0):
    """Shared adaptive `solve_static` (default solver and tolerances, throw=False)."""
    sol = hr.solve_static(rod, n0, m0, length, frame0=frame0, x0=x0, outputs=("frame", "centreline"), throw=False)
    return sol.frame[-1], sol.x[-1], sol.drift[-1], sol.first_integrals[0], sol.num_steps, sol.result


def _exact_helix(kappa, tau, phi, length):
    """Frame and centreline of the uniform helix at s = length: the rotation angle |u| L and
    its sine and cosine in 30 digits (float64 would lose eps |u| L), the fixed initial frame
    from `helix_frame` at s = 0."""
    k, t, L = (mpmath.mpf(float(x)) for x in (kappa, tau, length))
    norm = mpmath.sqrt(k * k + t * t)
    w = norm * L
    c, s = float(mpmath.cos(w)), float(mpmath.sin(w))
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    frame = rz @ np.asarray(hr.helix_frame(kappa, tau, phi, 0.0))
    r = float(k / norm**2)
    return frame, np.array([r * c, r * s, float(t / norm * L)])


def _integrate_helix(params, kappa, tau, slot, length):
    """Integrate the equilibrium `slot` of (kappa, tau) and return (frame error, centreline
    error, |D^T D - I|, first-integral drift relative to their scale, steps, result)."""
    rod = hr.Rod(*params[:5], uhat=params[5:])
    eq = equilibria([params], [kappa], [tau])
    assert eq.valid[0, slot]
    n0, m0, frame0, x0 = (np.asarray(a)[0, slot] for a in hr.helix_initial_conditions(jax.tree.map(jnp.asarray, eq)))
    frame, x, drift, integrals, steps, result = _ode(rod, n0, m0, jnp.asarray(length), frame0, x0)
    exact_frame, exact_x = _exact_helix(kappa, tau, eq.phi[0, slot], length)
    frame = np.asarray(frame)
    return (
        np.max(np.abs(frame - exact_frame)),
        np.max(np.abs(np.asarray(x) - exact_x)),
        np.max(np.abs(frame.T @ frame - np.eye(3))),
        np.max(np.abs(np.asarray(drift)) / (1 + np.abs(np.asarray(integrals)))),
        int(steps),
        result,
    )


README_ROD = (1.0, 1.5, 0.8, 0.5, 0.5, 1.0, 0.0, 0.0)  # spatially stable at (1, 0.5), slot 0


def test_ode_thousand_turns():
    """10^3 turns (L = 5620) of the helix kappa = 1, tau = 0.5 of the README rod, default
    tolerances.  Expected: frame within 1e-9 and centreline within 1e-12 L of the exact
    helix, D orthonormal to 1e-12, first integrals conserved to 1e-12 (relative)."""
    length = 1000 * 2 * np.pi / np.hypot(1.0, 0.5)
    frame, x, orth, drift, steps, result = _integrate_helix(README_ROD, 1.0, 0.5, 0, length)
    assert result == hr.RESULTS.successful
    record("ODE: 1e3 turns, frame", frame, 1e-9)
    record("ODE: 1e3 turns, centreline / L", x / length, 1e-12)
    record("ODE: 1e3 turns, |D^T D - I|", orth, 1e-12)
    record("ODE: 1e3 turns, first-integral drift", drift, 1e-12)


def test_ode_ten_thousand_turns():
    """10^4 turns (L = 56 200, ~69 000 steps, a fraction of a second).  The frame error grows
    like L^2 (a slow drift of the wrench shifts the turning rate): expected frame within 5e-8,
    centreline within 5e-12 L, D orthonormal to 1e-12, first integrals to 1e-12."""
    length = 10_000 * 2 * np.pi / np.hypot(1.0, 0.5)
    frame, x, orth, drift, steps, result = _integrate_helix(README_ROD, 1.0, 0.5, 0, length)
    assert result == hr.RESULTS.successful
    record("ODE: 1e4 turns, frame", frame, 5e-8)
    record("ODE: 1e4 turns, centreline / L", x / length, 5e-12)
    record("ODE: 1e4 turns, |D^T D - I|", orth, 1e-12)
    record("ODE: 1e4 turns, first-integral drift", drift, 1e-12)


def test_ode_near_straight():
    """Near-straight twisted rods: helices kappa = 1e-3, 1e-6, 1e-9 at tau = 1 of an
    uncoupled naturally straight rod (finite wrench), L = 100, and the exactly straight
    twisted rod (u = (0, 0, tau), n = (0, 0, T): frame R_z(tau s), x = (0, 0, s)).
    Expected: frame and centreline within 1e-12 of the exact solution."""
    rod_params = (1.0, 1.5, 0.8, 0.0, 0.0, 0.0, 0.0, 0.3)
    worst = 0.0
    for kappa in (1e-3, 1e-6, 1e-9):
        frame, x, orth, drift, steps, result = _integrate_helix(rod_params, kappa, 1.0, 0, 100.0)
        assert result == hr.RESULTS.successful
        worst = max(worst, frame, x / 100.0, orth)
    rod = hr.Rod(*rod_params[:5], uhat=rod_params[5:])
    tau, length = 2.0, 100.0
    m0 = rod.moment(jnp.array([0.0, 0.0, tau]))
    frame, x, drift, _, steps, result = _ode(rod, jnp.array([0.0, 0.0, 1.5]), m0, jnp.asarray(length), jnp.eye(3), jnp.zeros(3))
    assert result == hr.RESULTS.successful
    exact_frame, _ = _exact_helix(0.0, tau, 0.0, length)  # R_z(tau L) @ helix_frame(0, tau, 0, 0)
    exact_frame = exact_frame @ np.asarray(hr.helix_frame(0.0, tau, 0.0, 0.0)).T
    worst = max(worst, np.max(np.abs(np.asarray(frame) - exact_frame)), np.max(np.abs(np.asarray(x) - [0, 0, length])) / length)
    record("ODE: near-straight and straight twisted rods", worst, 1e-12)


def test_ode_highly_twisted():
    """tau = 100 and 1000 at kappa = 1 (10 turns), on the spatially stable registers of a
    coupled curved rod and an uncoupled one.  The wrench Jacobian is far from normal here;
    expected: the solve succeeds within the default max_steps and matches the exact helix
    to 1e-10 (frame) and 1e-12 L (centreline)."""
    worst, steps_max = 0.0, 0
    for params, tau, slot in [(README_ROD, 100.0, 1), ((1.0, 1.5, 0.8, 0.0, 0.0, 0.0, 0.0, 0.3), 100.0, 0),
                              ((1.0, 1.5, 0.8, 0.0, 0.0, 0.0, 0.0, 0.3), 1000.0, 1)]:
        length = 10 * 2 * np.pi / np.hypot(1.0, tau)
        frame, x, orth, drift, steps, result = _integrate_helix(params, 1.0, tau, slot, length)
        assert result == hr.RESULTS.successful, (params, tau, steps)
        worst = max(worst, frame, x / length)
        steps_max = max(steps_max, steps)
    record("ODE: highly twisted (tau = 1e2, 1e3), frame and x / L", worst, 1e-10)


def test_ode_nearly_singular_stiffness():
    """K nearly singular: Schur complement S = K3 - K13^2/K1 - K23^2/K2 = 1e-2 and 1e-4 (K3 ~
    0.53), spatially stable register, 10 turns.  The wrench equations are stiff (spectral
    radius ~ 1/S): the explicit default solver needs ~1/S steps.  Expected: within 1e-10 of
    the exact helix for S >= 1e-4; for S = 1e-8 the documented failure -- the step budget
    (max_steps = 100 000) runs out and `result` says so (an error with throw=True)."""
    schur0 = 0.36 + 0.5**2 / 1.5
    length = 10 * 2 * np.pi / np.hypot(1.0, 0.5)
    worst = 0.0
    for S in (1e-2, 1e-4):
        frame, x, orth, drift, steps, result = _integrate_helix((1.0, 1.5, schur0 + S, 0.6, 0.5, 0.0, 0.0, 0.0), 1.0, 0.5, 1, length)
        assert result == hr.RESULTS.successful, (S, steps)
        worst = max(worst, frame, x / length)
    record("ODE: nearly singular K (S = 1e-2, 1e-4), frame and x / L", worst, 1e-10)
    *_, steps, result = _integrate_helix((1.0, 1.5, schur0 + 1e-8, 0.6, 0.5, 0.0, 0.0, 0.0), 1.0, 0.5, 1, length)
    assert result == hr.RESULTS.max_steps_reached


# == fits ======================================================================================
# Every 12-point fit below shares one compilation (five stiffnesses free, uhat fixed: its
# values are traced); the single-point fit compiles once more.

N_FIT, STARTS = 12, 32
FIT_ROD = hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))


def _fit_values(fit):
    return np.array([float(fit.params[n]) for n in ("K1", "K2", "K3", "K13", "K23")])


def test_fit_nearly_unidentifiable():
    """K13 = 0 and uhat1 = 0 with helices where the registers stay on the axes (phi = 0, pi:
    no inner pair for kappa < |B|/|K1 - K2|): F and M never see K1.  Expected: the fit still
    describes the data (reduced chi^2 ~ 1) and the report says K1 is not determined -- a
    weak direction dominated by K1 and a K1 standard error larger than 10 K2."""
    rng = np.random.default_rng(7)
    kappa, tau = rng.uniform(0.2, 1.2, N_FIT), rng.uniform(-1.5, 0.5, N_FIT)
    rod = hr.Rod(1.0, 1.5, 0.8, K13=0.0, K23=0.3, uhat=(0.0, 0.5, 0.2))
    assert (np.asarray(hr.helix_equilibria(rod, kappa, tau).count) == 2).all()
    data = hr.synthetic_helix_data(rod, kappa, tau, 0.01, jax.random.key(1))
    fit = hr.fit_stiffness(data, uhat=(0.0, 0.5, 0.2), n_starts=STARTS)
    assert fit.ok and 0.3 < float(fit.chi2_reduced) < 3
    k1_directions = [dict(w).get("K1", 0.0) for w in fit.identifiability.weak]
    assert max(np.abs(k1_directions), default=0.0) > 0.99
    record("fits: unidentifiable K1, reported stderr(K1) / K2", float(fit.stderr["K1"]) / 1.5, 10.0, at_least=True)


def test_fit_outlier():
    """One point of 12 off by 30 sigma in F.  Least squares is not robust, and does not claim
    to be: expected the outlier to stand out as the largest normalised residual (> 10) with a
    reduced chi^2 > 10; downweighting it (sigma x 1e6, same shapes: no recompilation)
    recovers the truth within 3 standard errors (so does the clean data)."""
    rng = np.random.default_rng(8)
    kappa, tau = rng.uniform(0.3, 2.5, N_FIT), rng.uniform(-1.5, 2.0, N_FIT)
    data = hr.synthetic_helix_data(FIT_ROD, kappa, tau, 0.01, jax.random.key(2))
    force = np.asarray(data.force).copy()
    force[5] += 30 * float(data.force_sigma[5])
    bad = hr.HelixData(force, data.moment, kappa, tau, data.force_sigma, data.moment_sigma)
    fit = hr.fit_stiffness(bad, uhat=(1.0, 0.0, 0.0), n_starts=STARTS)
    r = np.abs(np.asarray(fit.residuals))
    assert np.argmax(r) == 5
    record("fits: outlier (30 sigma), its normalised residual", r[5], 10.0, at_least=True)
    record("fits: outlier (30 sigma), reduced chi^2", float(fit.chi2_reduced), 10.0, at_least=True)
    sigma = np.asarray(data.force_sigma).copy()
    sigma[5] *= 1e6
    down = hr.fit_stiffness(hr.HelixData(force, data.moment, kappa, tau, sigma, data.moment_sigma), uhat=(1.0, 0.0, 0.0), n_starts=STARTS)
    truth = np.array([1.0, 1.5, 0.8, 0.5, 0.5])
    stderr = np.array([float(down.stderr[n]) for n in ("K1", "K2", "K3", "K13", "K23")])
    record("fits: outlier downweighted, |fit - truth| / stderr", np.max(np.abs(_fit_values(down) - truth) / stderr), 3.0)


def test_fit_single_point():
    """One helix, two residuals, five stiffnesses.  Expected (documented in fit_stiffness):
    the fit runs, reproduces the point (cost < 1e-20), reports rank 2 with three exact null
    directions, and every standard error is infinite -- no false certainty, no exception."""
    data = hr.synthetic_helix_data(FIT_ROD, [0.8], [0.5], 0.0, jax.random.key(0))
    fit = hr.fit_stiffness(data, uhat=(1.0, 0.0, 0.0), n_starts=4)
    assert fit.ok and fit.identifiability.rank == 2
    assert fit.identifiability.weak_stderr.count(np.inf) == 3
    assert all(np.isinf(float(v)) for v in fit.stderr.values())
    record("fits: single point, cost", float(fit.cost), 1e-20)


def _boundary_helices():
    """Helices on the boundary of FIT_ROD's four-register region (the astroid):
    (K1 - K2) kappa = -(|B|^(2/3) + |C|^(2/3))^(3/2) with B, C at tau; tau = 2 is a cusp
    (C = 0: a triple register)."""
    tau = np.linspace(-1.5, 2.0, N_FIT)
    B = 1.5 * 0.0 + 0.5 * (0.0 - tau)
    C = 0.5 * (tau - 0.0) - 1.0 * 1.0
    return (np.abs(B) ** (2 / 3) + np.abs(C) ** (2 / 3)) ** 1.5 / 0.5, tau


def test_fit_all_points_on_a_branch_boundary():
    """Noise-free F, M of the stable register (slot 0) at 12 helices on the boundary of the
    four-register region, one of them at a cusp where the register derivative is unbounded.
    Expected: the truth is recovered (to 1e-8 of the largest stiffness, the package's
    noise-free accuracy) and the error bars stay finite: the cusp residual
    is reported as an exact constraint (before the fix of `_fit._summarise` it made every
    direction look null: rank 1, all standard errors infinite)."""
    kappa, tau = _boundary_helices()
    eq = hr.helix_equilibria(FIT_ROD, kappa, tau)
    F, M = np.asarray(eq.force[:, 0]), np.asarray(eq.moment[:, 0])
    data = hr.HelixData(F, M, kappa, tau, 0.01 * np.sqrt(np.mean(F**2)), 0.01 * np.sqrt(np.mean(M**2)))
    fit = hr.fit_stiffness(data, uhat=(1.0, 0.0, 0.0), n_starts=STARTS)
    assert fit.ok and fit.identifiability.rank == 5
    assert all(np.isfinite(float(v)) for v in fit.stderr.values())
    # The package's noise-free accuracy (tests/test_fit_pipeline.py): 1e-8 of the largest stiffness.
    record("fits: stable branch on the astroid, |fit - truth| / K2", np.max(np.abs(_fit_values(fit) - [1.0, 1.5, 0.8, 0.5, 0.5])) / 1.5, 1e-8)


def test_fit_observed_on_the_fold_register():
    """The same boundary helices observed on the fold register itself (the double root, F and
    M from mpmath).  The observed branch exists only on one side of each point, so the
    nearest-register residual is discontinuous at the truth and Levenberg-Marquardt cannot
    meet its convergence test.  Expected: the fit says so (`success` False, the message
    names the solver); the estimate stays within 10% of the truth.  Its Gauss-Newton
    standard errors are not to be trusted there (the linearisation fails at a fold: measured
    up to 3.6 standard errors off, on K3)."""
    kappa, tau = _boundary_helices()
    params = (1.0, 1.5, 0.8, 0.5, 0.5, 1.0, 0.0, 0.0)
    F, M = [], []
    for k, t in zip(kappa, tau):
        A = (params[0] - params[1]) * k / 2
        B = params[4] * (params[7] - t)
        C = params[3] * (t - params[7]) - params[0] * params[5]
        ref = mp_equilibria(params, k, t)
        slopes = [abs(float(2 * A * mpmath.cos(2 * p) + B * mpmath.cos(p) - C * mpmath.sin(p))) for p, _, _ in ref]
        _, f, m = ref[int(np.argmin(slopes))]  # the (near-)double root: smallest |f'|
        F.append(float(f))
        M.append(float(m))
    F, M = np.array(F), np.array(M)
    data = hr.HelixData(F, M, kappa, tau, 0.01 * np.sqrt(np.mean(F**2)), 0.01 * np.sqrt(np.mean(M**2)))
    fit = hr.fit_stiffness(data, uhat=(1.0, 0.0, 0.0), n_starts=STARTS)
    assert not fit.ok and "did not report convergence" in fit.message
    truth = np.array(params[:5])
    record("fits: fold register, |fit - truth| / truth", np.max(np.abs(_fit_values(fit) - truth) / truth), 0.1)


# == gradients, float32, non-finite inputs =====================================================


def _wrench(theta, kappa, tau):
    """(F, M, phi) of every slot as a function of the rod parameters, kappa and tau."""
    rod = hr.Rod(theta[0], theta[1], theta[2], theta[3], theta[4], theta[5:8])
    eq = hr.helix_equilibria(rod, kappa, tau)
    return jnp.stack([eq.force, eq.moment, eq.phi])


_JACFWD = jax.jit(jax.vmap(jax.jacfwd(_wrench, argnums=(0, 1, 2))))
_JACREV = jax.jit(jax.vmap(jax.jacrev(_wrench, argnums=(0, 1, 2))))
_NANSUM_GRAD = jax.jit(jax.vmap(jax.grad(lambda th, k, t: jnp.nansum(_wrench(th, k, t)), argnums=(0, 1, 2))))

# (rod parameters, kappa, tau): the edges of the domain.
EDGES = {
    "straight (kappa = 0)": (GENERIC, 0.0, 0.7),
    "kappa = 1e-10": (GENERIC, 1e-10, 0.7),
    "ring (tau = 0)": (GENERIC, 0.9, 0.0),
    "isotropic continuum": ((1.2, 1.2, 0.9, 0.0, 0.0, 0.0, 0.0, 0.3), 0.8, 0.5),
    "K1 = K2 with couplings": ((1.2, 1.2, 0.9, 0.3, -0.2, 0.4, -0.3, 0.2), 0.8, 0.5),
    "K1 = K2, tau = uhat3 (continuum)": ((1.2, 1.2, 0.9, 0.3, -0.2, 0.0, 0.0, 0.3), 0.8, 0.3),
    "B = 0 (uncoupled)": ((1.0, 1.5, 0.8, 0.0, 0.0, 0.4, 0.0, 0.2), 0.8, 0.5),
    "C = 0 (uncoupled)": ((1.0, 1.5, 0.8, 0.0, 0.0, 0.0, 0.4, 0.2), 0.8, 0.5),
    "exact tangency (A, B, C) = (-62.5, 27, 64)": ((2.0, 127.0, 2100.0, 64.0, -27.0, 0.0, 0.0, 0.0), 1.0, 1.0),
    "cusp (triple register)": ((1.0, 1.5, 0.8, 0.5, 0.5, 1.0, 0.0, 0.0), 2.0, 2.0),
    "|u| = 1e8": (GENERIC, 0.8e8, -0.6e8),
    "|u| = 1e-8": (GENERIC, 0.8e-8, -0.6e-8),
    "K x 1e-27": (tuple(1e-27 * x for x in GENERIC[:5]) + GENERIC[5:], 0.9, 0.4),
    "stiffness ratio 1e6": ((1.0, 1e6, 1e3, 0.3 * np.sqrt(1e3), 0.0, 0.4, -0.3, 0.2), 1.1, 0.7),
}


def test_gradients_finite_at_the_edges():
    """d(F, M, phi)/d(K, uhat, kappa, tau) by jacfwd and jacrev at the edges of the domain
    (`EDGES`).  Expected: finite wherever the value is finite (the implicit-function
    derivative at a tangent register is that of the extremum: finite by convention); jacfwd
    = jacrev to 1e-10 relative; the gradient of a NaN-ignoring loss (nansum) finite
    everywhere, including kappa = 0 where no register exists."""
    cases = list(EDGES.values())
    theta = jnp.asarray([c[0] for c in cases])
    kappa = jnp.asarray([c[1] for c in cases])
    tau = jnp.asarray([c[2] for c in cases])
    eq = equilibria([c[0] for c in cases], [c[1] for c in cases], [c[2] for c in cases])
    values = np.stack([eq.force, eq.moment, eq.phi], axis=1)
    fwd = [np.asarray(j) for j in _JACFWD(theta, kappa, tau)]
    rev = [np.asarray(j) for j in _JACREV(theta, kappa, tau)]
    worst = 0.0
    for i, name in enumerate(EDGES):
        finite = np.isfinite(values[i])
        assert finite.any() == (name != "straight (kappa = 0)"), name
        compared = finite.copy()
        if name == "kappa = 1e-10":  # M loses eps/kappa: test_moment_cancellation_small_kappa
            compared[1] = False
        for jf, jr in zip(fwd, rev):
            assert np.all(np.isfinite(jf[i][finite])) and np.all(np.isfinite(jr[i][finite])), name
            f, r = jf[i][compared], jr[i][compared]
            scale = np.maximum(np.abs(f), 1.0)
            worst = max(worst, np.max(np.abs(f - r) / scale, initial=0.0))
    record("gradients: jacfwd vs jacrev at the edges (relative)", worst, 1e-10)
    for g in _NANSUM_GRAD(theta, kappa, tau):
        assert np.all(np.isfinite(np.asarray(g)))


@pytest.mark.heavy
def test_solve_static_gradient_at_zero_rotation():
    """solve_static through u = 0 (a straight, untwisted rod under tension: the group
    exponential at zero angle, where sin(theta)/theta needs care), forward mode, 4 fixed
    steps.  Expected: finite derivatives of the end point with respect to n0, m0 and the
    length, and the closed form x(L) = (0, 0, L), dx/dL = (0, 0, 1)."""
    rod = hr.Rod(1.0, 1.5, 0.8)

    def end(n0, m0, length):
        return hr.solve_static(rod, n0, m0, length, outputs="centreline", steps=4, adjoint=diffrax.ForwardMode()).x[-1]

    n0, m0, L = jnp.array([0.0, 0.0, 2.0]), jnp.zeros(3), jnp.asarray(3.0)
    jac = jax.jit(jax.jacfwd(end, argnums=(0, 1, 2)))(n0, m0, L)
    assert all(np.all(np.isfinite(np.asarray(j))) for j in jac)
    err = np.max(np.abs(np.asarray(jac[2]) - [0.0, 0.0, 1.0]))
    record("gradients: dx(L)/dL at u = 0", err, 1e-14)


_FLOAT32_SCRIPT = textwrap.dedent(
    """
    import json, sys
    import numpy as np, jax
    import helixrod as hr
    assert not jax.config.jax_enable_x64
    inp = json.loads(sys.stdin.read())
    P = np.asarray(inp["params"], np.float32)
    rod = hr.Rod(P[:, 0], P[:, 1], P[:, 2], P[:, 3], P[:, 4], P[:, 5:8])
    eq = jax.jit(hr.helix_equilibria)(rod, np.asarray(inp["kappa"], np.float32), np.asarray(inp["tau"], np.float32))
    out = {"dtype": str(eq.force.dtype)}
    for name in ("phi", "valid", "force", "moment"):
        out[name] = np.asarray(getattr(eq, name)).tolist()
    # 10 turns of the README helix (kappa, tau) = (1, 0.5), slot 0, default tolerances.
    readme = hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
    helix = hr.helix_equilibria(readme, 1.0, 0.5)
    n0, m0, frame0, x0 = (a[0] for a in hr.helix_initial_conditions(helix))
    length = np.float32(10 * 2 * np.pi / np.hypot(1.0, 0.5))
    sol = hr.solve_static(readme, n0, m0, length, frame0=frame0, x0=x0, outputs=("frame", "centreline"))
    out.update(ode_dtype=str(sol.x.dtype), ode_phi=float(helix.phi[0]), ode_length=float(length),
               ode_frame=np.asarray(sol.frame[-1], float).tolist(), ode_x=np.asarray(sol.x[-1], float).tolist(),
               ode_ok=bool(sol.ok), ode_steps=int(sol.num_steps))
    print(json.dumps(out))
    """
)


@pytest.mark.heavy
def test_float32_accuracy(rng):
    """float32 mode (x64 off, in a subprocess: the test session runs in float64): 64 random
    coupled, curved rods at random helices, compared with float64 on the same (float32)
    inputs.  Expected: same register count everywhere; phi within 32 eps32 (3.8e-6) and F, M
    within 16 eps32 (1.9e-6) normwise -- float32 loses nothing beyond its own precision
    away from tangencies (near one the eps/gap rule applies with eps32).  `solve_static` in
    float32 (10 turns of the README helix, default solver and float32 tolerances, 1e-6):
    frame within 2e-3, centreline within 1e-4 L."""
    from helpers import random_rods

    rods_ = random_rods(rng, N)
    P = np.array([[float(r.K1), float(r.K2), float(r.K3), float(r.K13), float(r.K23), *np.asarray(r.uhat)] for r in rods_])
    P = P.astype(np.float32).astype(float)
    kappa = rng.uniform(0.05, 3.0, N).astype(np.float32).astype(float)
    tau = rng.uniform(-3.0, 3.0, N).astype(np.float32).astype(float)
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    proc = subprocess.run(
        [sys.executable, "-c", _FLOAT32_SCRIPT],
        input=json.dumps({"params": P.tolist(), "kappa": kappa.tolist(), "tau": tau.tolist()}),
        capture_output=True, text=True, env=env, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout)
    assert out["dtype"] == "float32"
    eq = EQ(hr.Rod(P[:, 0], P[:, 1], P[:, 2], P[:, 3], P[:, 4], P[:, 5:8]), kappa, tau)
    valid64, valid32 = np.asarray(eq.valid), np.array(out["valid"])
    np.testing.assert_array_equal(valid32.sum(1), valid64.sum(1))
    both = valid64 & valid32
    eps32 = float(np.finfo(np.float32).eps)
    dphi = angular(np.array(out["phi"])[both], np.asarray(eq.phi)[both])
    norm = np.hypot(kappa, tau)
    scale = (np.max(np.abs(P[:, :5]), 1) * norm * (norm + np.linalg.norm(P[:, 5:], axis=1)))[:, None]
    dF = np.abs(np.array(out["force"]) - np.asarray(eq.force)) / np.maximum(np.abs(np.asarray(eq.force)), scale)
    dM = np.abs(np.array(out["moment"]) - np.asarray(eq.moment)) / np.maximum(np.abs(np.asarray(eq.moment)), scale / norm[:, None])
    record("float32: |dphi| / eps32", np.max(dphi) / eps32, 32.0)
    record("float32: wrench (normwise) / eps32", max(np.max(dF[both]), np.max(dM[both])) / eps32, 16.0)
    assert out["ode_dtype"] == "float32" and out["ode_ok"]
    frame, x = _exact_helix(1.0, 0.5, out["ode_phi"], out["ode_length"])
    record("float32: solve_static 10 turns, frame", np.max(np.abs(np.array(out["ode_frame"]) - frame)), 2e-3)
    record("float32: solve_static 10 turns, centreline / L", np.max(np.abs(np.array(out["ode_x"]) - x)) / out["ode_length"], 1e-4)


_NONFINITE_COEFFICIENTS = np.array(
    [
        [1.0, np.nan, 1.0, np.inf, 0.3, -np.inf] + [1.0] * (N - 6),
        [0.2, 0.2, np.nan, 0.2, 0.1, 0.2] + [0.2] * (N - 6),
        [0.3, 0.3, 0.3, 0.3, np.inf, 0.3] + [0.3] * (N - 6),
    ]
)
def test_register_roots_flags_nonfinite_coefficients():
    """Non-finite A, B or C: expected no valid slot (as `helix_equilibria` does for
    non-finite kappa, tau), never NaN or arbitrary angles marked valid."""
    valid = roots(*_NONFINITE_COEFFICIENTS)[3]
    bad = ~np.all(np.isfinite(_NONFINITE_COEFFICIENTS), axis=0)
    assert not valid[bad].any(), valid[bad]


def test_nonfinite_inputs_flagged_not_propagated():
    """NaN and inf in kappa, tau (batch and vmap) and in a `sweep` axis.  Expected: the bad
    points are flagged (no valid register, count 0) and every other point is bit for bit
    what it is in a batch without them (also in `register_roots`, whose flagging of
    non-finite coefficients is `test_register_roots_flags_nonfinite_coefficients`; vmapped
    `solve_static` with throw=False: tests/test_kirchhoff.py::
    test_vmap_equals_loop_and_flags_bad_points); a non-finite stiffness is a `ValueError`
    naming the rule; non-finite data a `ValueError` naming the rows."""
    params = [GENERIC] * 8
    kappa = np.array([0.5, np.nan, 0.7, np.inf, 0.9, 1.1, -np.inf, 1.3])
    tau = np.array([0.3, 0.3, np.nan, 0.3, -np.inf, np.inf, 0.3, 0.3])
    bad = ~(np.isfinite(kappa) & np.isfinite(tau))
    eq = equilibria(params, kappa, tau)
    clean = equilibria(params, np.where(bad, 1.0, kappa), np.where(bad, 1.0, tau))
    assert not eq.valid[bad].any() and np.isnan(eq.force[bad]).all()
    for name in ("phi", "force", "moment", "valid", "stable"):
        np.testing.assert_array_equal(getattr(eq, name)[~bad], getattr(clean, name)[~bad])
    rod = hr.Rod(*GENERIC[:5], uhat=GENERIC[5:])
    mapped = jax.jit(jax.vmap(lambda k, t: hr.helix_equilibria(rod, k, t).force))
    with_bad, without = np.asarray(mapped(kappa, tau)), np.asarray(mapped(np.where(bad, 1.0, kappa), np.where(bad, 1.0, tau)))
    np.testing.assert_array_equal(with_bad[~bad], without[~bad])
    assert np.isnan(with_bad[bad]).all()

    got_roots = roots(*_NONFINITE_COEFFICIENTS)
    keep = np.all(np.isfinite(_NONFINITE_COEFFICIENTS), axis=0)
    clean_roots = roots(*(np.where(keep, x, 1.0) for x in _NONFINITE_COEFFICIENTS))
    for got, want in zip(got_roots, clean_roots):
        np.testing.assert_array_equal(got[keep], want[keep])

    atlas = hr.sweep(rod, np.array([0.5, np.nan, 1.0]), np.array([0.3, np.inf, -0.4]), fields=("count", "force"))
    clean_atlas = hr.sweep(rod, np.array([0.5, 0.7, 1.0]), np.array([0.3, 0.1, -0.4]), fields=("count", "force"))
    assert atlas["count"][1].tolist() == [0, 0, 0] and atlas["count"][:, 1].tolist() == [0, 0, 0]
    np.testing.assert_array_equal(atlas["force"][[0, 2]][:, [0, 2]], clean_atlas["force"][[0, 2]][:, [0, 2]])

    with pytest.raises(ValueError, match="finite and positive definite"):
        hr.Rod(1.0, np.nan, 0.8)
    with pytest.raises(ValueError, match=r"rows \[1\]"):
        hr.HelixData([1.0, 2.0], [1.0, np.inf], [0.5, 0.6], [0.1, 0.2])
