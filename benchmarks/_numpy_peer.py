"""The numpy peer of helix_equilibria: batched companion-matrix eigenvalues of the register
quartic, Newton polish, then wrench, energy and stability -- what a careful numpy user
would write.  Shared by the benchmarks (bench_sweep.py, and the equilibria benchmark).

Slots as helix_equilibria: 0 the global minimum of W on the circle, 1 the global maximum,
2 / 3 the inner local minimum / maximum; unused slots NaN (valid False).
"""

from __future__ import annotations

import numpy as np

# Generic rotation of the circle, so that no register sits at t = tan(psi/2) = infinity
# (the quartic in t loses its leading coefficient when phi0 + pi is a register).
_PHI0 = 0.31415926535897
_REAL_TOL = 1e-6


def register_quartic(A, B, C, phi0=_PHI0):
    """Coefficients (highest first, shape (N, 5)) of P(t) with f(phi0 + psi) = P(t)/(1+t^2)^2,
    t = tan(psi/2), f = A sin 2phi + B sin phi + C cos phi."""
    c1, s1, c2, s2 = np.cos(phi0), np.sin(phi0), np.cos(2 * phi0), np.sin(2 * phi0)
    a, b = A * c2, A * s2  # a sin 2psi + b cos 2psi + c sin psi + d cos psi
    c, d = B * c1 - C * s1, B * s1 + C * c1
    return np.stack([b - d, 2 * c - 4 * a, -6 * b, 4 * a + 2 * c, b + d], axis=-1)


def numpy_helix_equilibria(K1, K2, K3, K13, K23, uhat, kappa, tau, newton_steps=2):
    """Every register of the helices (kappa, tau) (1-D arrays, kappa > 0) of one rod.

    Returns a dict of (N, 4) arrays: phi, valid, force, moment, stable (and energy)."""
    kappa = np.asarray(kappa, float)
    tau = np.asarray(tau, float)
    u1h, u2h, u3h = (float(x) for x in uhat)
    A = 0.5 * (K1 - K2) * kappa
    B = K2 * u2h + K23 * (u3h - tau)
    C = K13 * (tau - u3h) - K1 * u1h
    coeffs = register_quartic(A, B, C)
    monic = coeffs[:, 1:] / coeffs[:, :1]
    n = kappa.size
    companion = np.zeros((n, 4, 4))
    companion[:, 0, :] = -monic
    companion[:, 1, 0] = companion[:, 2, 1] = companion[:, 3, 2] = 1.0
    roots = np.linalg.eigvals(companion)
    valid = np.abs(roots.imag) <= _REAL_TOL * (1 + np.abs(roots.real))
    phi = np.mod(_PHI0 + 2 * np.arctan(roots.real), 2 * np.pi)
    a, b, c = A[:, None], B[:, None], C[:, None]
    for _ in range(newton_steps):
        s, co = np.sin(phi), np.cos(phi)
        f = 2 * a * s * co + b * s + c * co
        fp = 2 * a * (co * co - s * s) + b * co - c * s
        phi = phi - f / np.where(fp == 0, 1.0, fp)
    s, co = np.sin(phi), np.cos(phi)
    fp = 2 * a * (co * co - s * s) + b * co - c * s
    k, t = kappa[:, None], tau[:, None]
    v1, v2, v3 = k * s - u1h, k * co - u2h, t - u3h
    m1 = K1 * v1 + K13 * v3
    m2 = K2 * v2 + K23 * v3
    m3 = K13 * v1 + K23 * v2 + K3 * v3
    mu1 = (m1 * k * s + m2 * k * co) / (k * k)
    mu2 = m3 - mu1 * t
    norm_u = np.sqrt(k * k + t * t)
    force = mu2 * norm_u
    moment = mu1 * norm_u + mu2 * t / norm_u
    energy = 0.5 * (v1 * m1 + v2 * m2 + v3 * m3)
    stable = valid & (k * fp > 0)  # d2W/dphi2 = kappa f'(phi)

    # Slots: order the valid roots by energy; lowest -> 0, highest -> 1, the middle two
    # (when four) -> 2 (the stable one) and 3.
    key = np.where(valid, energy, np.inf)
    order = np.argsort(key, axis=1)
    count = valid.sum(axis=1)
    rows = np.arange(n)[:, None]
    ranked = {name: x[rows, order] for name, x in
              (("phi", np.mod(phi, 2 * np.pi)), ("force", force), ("moment", moment), ("energy", energy),
               ("stable", stable), ("valid", valid))}
    last = np.maximum(count - 1, 0)
    # With four registers the middle two are a local min and max; with three (a fold)
    # the middle one is the degenerate register.
    mid_stable_first = (count == 4) & ranked["stable"][:, 2] & ~ranked["stable"][:, 1]
    pick = np.stack(
        [np.zeros(n, int), last, np.where(mid_stable_first, 2, 1), np.where(mid_stable_first, 1, 2)], axis=1
    )
    out = {name: x[rows, pick] for name, x in ranked.items()}
    slot_used = np.stack([count >= 1, count >= 2, count >= 3, count >= 4], axis=1)
    out["valid"] = slot_used
    out["stable"] = out["stable"] & slot_used
    for name in ("phi", "force", "moment", "energy"):
        out[name] = np.where(slot_used, out[name], np.nan)
    return out
