"""The numba peer of helix_equilibria: what a performance-minded user would write by hand.

One compiled loop over the points (`numba.njit`, `prange` over the points when more than
one thread is allowed), each point solved on its own with early exits, and only the work a
point needs:

* the register coefficients, scaled, turned to A >= 0 (as `helixrod._roots`);
* the inner pair decided by the sign of the astroid polynomial, and solved only where it
  exists (~5 % of the points of a typical rod);
* each register by Halley steps on the secular equation of its slot, from the same lower
  bounds as helixrod, stopped as soon as a step is at round-off (2-4 steps), then one
  Newton rotation on f(phi) itself;
* exact zeros of B or C by their closed forms; near-tangent points (|astroid| at
  round-off) by the cube-root test, with one tangent register in slot 2;
* phi by `atan2`, then the axial force and moment and the stability of each register.

Slots and outputs as `helix_equilibria` and the numpy peer: 0 the global minimum of W on
the circle, 1 the global maximum, 2 / 3 the inner local minimum / maximum; unused slots NaN
(valid False).  The benchmark checks counts, stability and phi against `helix_equilibria`.
"""

from __future__ import annotations

import math

import numba
import numpy as np

_TINY = 1e-100
_TANGENT_TOL = 64 * 2.220446049250313e-16
_MAX_STEPS = 64
_FAST_STEPS = 4
_BLOCK = 2048
_TAN_PI_8 = 0.41421356237309503


@numba.njit(cache=True, inline="always", error_model="numpy")
def _secular_root(nu, aa, Q2, P2, e):
    """Halley on psi(nu) = (Q^2/nu^2 + P^2/(2a + e nu)^2)^(-1/2) = 1 from a start left of
    the root, until a step is at round-off; then Newton until it is (slow next to cusps)."""
    for _ in range(_MAX_STEPS):
        d = aa + e * nu
        N = Q2 * d * d + P2 * nu * nu
        dN = 2 * (e * Q2 * d + P2 * nu)
        g = nu * d
        dg = d + e * nu
        H = g - math.sqrt(N)
        D1 = 2 * N * dg - g * dN
        D2 = 8 * e * N * N - 4 * dg * dN * N + 3 * g * dN * dN - 4 * g * (Q2 + P2) * N
        step = -4 * N * H * D1 / (2 * D1 * D1 - H * D2)
        if not (step == step) or nu + step <= 0:
            break
        nu += step
        if abs(step) <= 1e-15 * nu:
            return nu, True
    for _ in range(4 * _MAX_STEPS):
        d = aa + e * nu
        N = Q2 * d * d + P2 * nu * nu
        den = Q2 * d * d * d + e * P2 * nu * nu * nu
        step = N * (math.sqrt(N) - nu * d) / den
        nu += step
        if abs(step) <= 1e-15 * nu:
            return nu, True
    return nu, False


@numba.njit(cache=True, inline="always", error_model="numpy")
def _polish(a, b, c, x, y):
    """One Newton step on f(phi) = 2a x y + b y + c x, as a rotation of (x, y)."""
    f = 2 * a * x * y + b * y + c * x
    fp = 2 * a * (x * x - y * y) + b * x - c * y
    if fp != 0:
        r = -f / fp
        if abs(r) <= 1e-4:
            x, y = x - r * y, y + r * x
    n = 1.0 / math.sqrt(x * x + y * y)
    return x * n, y * n


@numba.njit(cache=True, error_model="numpy")
def _point(A, B, C, cos_out, sin_out, valid, tangent):
    """The registers of one point into cos_out, sin_out, valid, tangent (length 4).
    Returns whether the point is a continuum (A = B = C = 0)."""
    for s in range(4):
        valid[s] = False
        tangent[s] = False
    scale = max(abs(A), abs(B), abs(C))
    if scale == 0:
        cos_out[0], sin_out[0], valid[0] = 1.0, 0.0, True
        return True
    a, b, c = A / scale, B / scale, C / scale
    turn = a < 0
    if turn:
        a, b, c = -a, -c, b
    if abs(b) <= _TINY or abs(c) <= _TINY:
        sb = -1.0 if b < 0 else 1.0
        sc = -1.0 if c < 0 else 1.0
        if abs(c) <= abs(b):  # c = 0: roots 0, pi and cos phi = -b / 2a
            q = -b / (2 * a) if a > 0 else 2.0
            pair = abs(q) < 1
            r = math.sqrt(max(1 - q * q, 0.0))
            cos_out[0], sin_out[0] = sb, 0.0
            cos_out[1], sin_out[1] = (q, sc * r) if pair else (-sb, 0.0)
            cos_out[2], sin_out[2] = -sb, 0.0
            cos_out[3], sin_out[3] = q, -sc * r
        else:  # b = 0: roots pi/2, 3 pi/2 and sin phi = -c / 2a
            q = -c / (2 * a) if a > 0 else 2.0
            pair = abs(q) < 1
            r = math.sqrt(max(1 - q * q, 0.0))
            cos_out[0], sin_out[0] = (sb * r, q) if pair else (0.0, -sc)
            cos_out[1], sin_out[1] = 0.0, sc
            cos_out[2], sin_out[2] = -sb * r, q
            cos_out[3], sin_out[3] = 0.0, -sc
        valid[0] = valid[1] = True
        valid[2] = valid[3] = pair
    else:
        b2, c2, a2 = b * b, c * c, a * a
        astroid = (b2 + c2 - 4 * a2) ** 3 + 108 * a2 * b2 * c2
        near = False
        if abs(astroid) > _TANGENT_TOL:
            pair = astroid < 0
        else:
            cb, cc = np.cbrt(b), np.cbrt(c)
            sq = cb * cb + cc * cc
            gap = 4 * a2 - sq * sq * sq
            near = abs(gap) <= _TANGENT_TOL * 4 * a2
            pair = gap > 0 and not near
        aa = 2 * a
        r_low = max(abs(b), abs(c)) + 0.41421356 * min(abs(b), abs(c))
        slots = 4 if pair else 2
        for s in range(slots):
            Q, P = (b, c) if s % 2 == 0 else (c, b)
            inner = s >= 2
            e = -1.0 if inner else 1.0
            if inner:
                nu0 = abs(Q) / math.sqrt(max(1 - P * P / (aa - abs(Q)) ** 2, 1e-300))
            else:
                nu0 = max(abs(Q), r_low - aa)
            nu, _ = _secular_root(nu0, aa, Q * Q, P * P, e)
            d = aa + e * nu
            U = (-1.0 if inner else 1.0) * Q / nu
            V = -P / d
            x, y = (V, U) if s % 2 == 1 else (U, V)
            cos_out[s], sin_out[s] = _polish(a, b, c, x, y)
            valid[s] = True
        if near:
            n = 1.0 / math.sqrt(cb * cb + cc * cc)
            cos_out[2], sin_out[2] = -cb * n, -cc * n
            valid[2] = True
            tangent[2] = True
    if turn:
        for s in range(4):
            cos_out[s], sin_out[s] = -sin_out[s], cos_out[s]
    return False


@numba.njit(cache=True, inline="always", error_model="numpy")
def _halley_fixed(nu, aa, Q2, P2):
    """`_FAST_STEPS` Halley steps on an outer branch (e = +1), branch-free so that the loop
    over points vectorises; returns nu and the last two steps."""
    last = before = 1e300
    for _ in range(_FAST_STEPS):
        d = aa + nu
        N = Q2 * d * d + P2 * nu * nu
        dN = 2 * (Q2 * d + P2 * nu)
        g = nu * d
        dg = d + nu
        H = g - math.sqrt(N)
        D1 = 2 * N * dg - g * dN
        D2 = 8 * N * N - 4 * dg * dN * N + 3 * g * dN * dN - 4 * g * (Q2 + P2) * N
        step = -4 * N * H * D1 / (2 * D1 * D1 - H * D2)
        before = last
        last = step
        nu = nu + step
    return nu, last, before


@numba.njit(cache=True, inline="always", error_model="numpy")
def _atan2_positive(y, x):
    """atan2(y, x) in [0, 2 pi) for a unit (x, y), branch-free: a polynomial of the reduced
    argument |t| <= tan(pi/8), so that the loop over points vectorises (numba's atan2 is a
    scalar library call without Intel's SVML)."""
    ax, ay = abs(x), abs(y)
    low = ay <= _TAN_PI_8 * ax
    high = ax <= _TAN_PI_8 * ay
    num = ay if low else (-ax if high else ay - ax)
    den = ax if low else (ay if high else ay + ax)
    t = num / den
    z = t * t
    poly = _ATAN[10]
    for j in range(9, -1, -1):
        poly = poly * z + _ATAN[j]
    alpha = (0.0 if low else (0.5 * math.pi if high else 0.25 * math.pi)) + (t + t * z * poly)
    right = alpha if y >= 0 else 2 * math.pi - alpha
    left = math.pi - alpha if y >= 0 else math.pi + alpha
    return right if x >= 0 else left


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _kernel(K1, K2, K3, K13, K23, u1h, u2h, u3h, kappa, tau, phi, valid, force, moment, stable):
    n = kappa.shape[0]
    blocks = (n + _BLOCK - 1) // _BLOCK
    for j in numba.prange(blocks):
        lo, hi = j * _BLOCK, min(n, (j + 1) * _BLOCK)
        # Scratch for a block of points, allocated once per block (it stays in L1).
        cos_all = np.empty((_BLOCK, 4))
        sin_all = np.empty((_BLOCK, 4))
        tangent_all = np.zeros((_BLOCK, 4), np.bool_)
        redo = np.empty(_BLOCK, np.uint8)
        cos0, sin0, cos1, sin1 = np.empty(_BLOCK), np.empty(_BLOCK), np.empty(_BLOCK), np.empty(_BLOCK)
        c_s, s_s, phi_s, force_s, moment_s = np.empty(_BLOCK), np.empty(_BLOCK), np.empty(_BLOCK), np.empty(_BLOCK), np.empty(_BLOCK)
        ok_s, t_s, stable_s = np.empty(_BLOCK, np.uint8), np.empty(_BLOCK, np.uint8), np.empty(_BLOCK, np.uint8)
        # Pass 1, vectorised: the two outer registers of every point by fixed Halley steps
        # (selects, no branches, and contiguous scratch rows, so that LLVM vectorises it).
        for i in range(lo, hi):
            r = i - lo
            k, t = kappa[i], tau[i]
            A = 0.5 * (K1 - K2) * k
            B = K2 * u2h + K23 * (u3h - t)
            C = K13 * (t - u3h) - K1 * u1h
            scale = max(abs(A), max(abs(B), abs(C)))
            inv = 1.0 / max(scale, 1e-300)
            a0, b0, c0 = A * inv, B * inv, C * inv
            turn = a0 < 0
            a = abs(a0)
            b = -c0 if turn else b0
            c = b0 if turn else c0
            b2, c2, a2 = b * b, c * c, a * a
            w = b2 + c2 - 4 * a2
            astroid = w * w * w + 108 * a2 * b2 * c2
            aa = 2 * a
            ab, ac = abs(b), abs(c)
            r_low = max(ab, ac) + 0.41421356 * min(ab, ac)
            nu0, last0, before0 = _halley_fixed(max(ab, r_low - aa), aa, b2, c2)
            nu1, last1, before1 = _halley_fixed(max(ac, r_low - aa), aa, c2, b2)
            l0, l1 = abs(last0), abs(last1)
            ok0 = (l0 <= 1e-14 * nu0) | ((l0 <= 1e-4 * nu0) & (l0 * l0 * l0 <= 1e-17 * before0 * before0 * nu0))
            ok1 = (l1 <= 1e-14 * nu1) | ((l1 <= 1e-4 * nu1) & (l1 * l1 * l1 <= 1e-17 * before1 * before1 * nu1))
            fine = ok0 & ok1 & (astroid > _TANGENT_TOL) & (scale > 0) & (ab > _TINY) & (ac > _TINY) & (nu0 > 0) & (nu1 > 0)
            redo[r] = 0 if fine else 1
            x0, y0 = b / nu0, -c / (aa + nu0)
            y1, x1 = c / nu1, -b / (aa + nu1)
            n0 = 1.5 - 0.5 * (x0 * x0 + y0 * y0)
            n1 = 1.5 - 0.5 * (x1 * x1 + y1 * y1)
            x0, y0, x1, y1 = x0 * n0, y0 * n0, x1 * n1, y1 * n1
            cos0[r] = -y0 if turn else x0
            sin0[r] = x0 if turn else y0
            cos1[r] = -y1 if turn else x1
            sin1[r] = x1 if turn else y1
        for i in range(lo, hi):
            r = i - lo
            cos_all[r, 0], sin_all[r, 0], cos_all[r, 1], sin_all[r, 1] = cos0[r], sin0[r], cos1[r], sin1[r]
            valid[i, 0] = valid[i, 1] = True
            valid[i, 2] = valid[i, 3] = False
        # Pass 2, scalar: the points with an inner pair, near a tangency or a cusp, or with
        # a zero coefficient, solved in full.
        for i in range(lo, hi):
            r = i - lo
            if redo[r]:
                k, t = kappa[i], tau[i]
                A = 0.5 * (K1 - K2) * k
                B = K2 * u2h + K23 * (u3h - t)
                C = K13 * (t - u3h) - K1 * u1h
                _point(A, B, C, cos_all[r], sin_all[r], valid[i], tangent_all[r])
        # Pass 3, vectorised (slot by slot): phi, the axial wrench and stability.
        for s in range(4):
            for i in range(lo, hi):
                r = i - lo
                ok_s[r] = valid[i, s]
                c_s[r] = cos_all[r, s]
                s_s[r] = sin_all[r, s]
                t_s[r] = tangent_all[r, s]
            for i in range(lo, hi):
                r = i - lo
                k, t = kappa[i], tau[i]
                A = 0.5 * (K1 - K2) * k
                B = K2 * u2h + K23 * (u3h - t)
                C = K13 * (t - u3h) - K1 * u1h
                continuum = (A == 0) & (B == 0) & (C == 0)
                norm_u = math.sqrt(k * k + t * t)
                c, sn = c_s[r], s_s[r]
                v1, v2, v3 = k * sn - u1h, k * c - u2h, t - u3h
                m1 = K1 * v1 + K13 * v3
                m2 = K2 * v2 + K23 * v3
                m3 = K13 * v1 + K23 * v2 + K3 * v3
                mu1 = (m1 * sn + m2 * c) / k
                mu2 = m3 - mu1 * t
                d2 = k * (2 * A * (c * c - sn * sn) + B * c - C * sn)
                ok = ok_s[r] != 0
                phi_s[r] = _atan2_positive(sn, c) if ok else np.nan
                force_s[r] = mu2 * norm_u if ok else np.nan
                moment_s[r] = (m1 * k * sn + m2 * k * c + m3 * t) / norm_u if ok else np.nan
                stable_s[r] = 1 if ok & (d2 > 0) & (t_s[r] == 0) & ~continuum else 0
            for i in range(lo, hi):
                r = i - lo
                phi[i, s], force[i, s], moment[i, s], stable[i, s] = phi_s[r], force_s[r], moment_s[r], stable_s[r] != 0


def _arctan_coefficients():
    """P of degree 10 with arctan(t) = t + t z P(z), z = t^2, |t| <= tan(pi/8): Chebyshev
    interpolation of (arctan(t) - t) / (t z) in z."""
    z_max = _TAN_PI_8**2
    def g(z):
        t = np.sqrt(z)
        small = z < 1e-4
        series = -1 / 3 + z / 5 - z * z / 7 + z**3 / 9
        return np.where(small, series, (np.arctan(t) - t) / np.where(small, 1.0, t * z))
    cheb = np.polynomial.Chebyshev.interpolate(g, 10, domain=[0.0, z_max])
    return np.ascontiguousarray(cheb.convert(kind=np.polynomial.Polynomial).coef)


_ATAN = _arctan_coefficients()


def numba_helix_equilibria(K1, K2, K3, K13, K23, uhat, kappa, tau):
    """Every register of the helices (kappa, tau) (1-D float64 arrays, kappa > 0) of one rod.

    Returns a dict of (N, 4) arrays: phi, valid, force, moment, stable.  Runs on
    `numba.get_num_threads()` threads (`numba.set_num_threads` to change it)."""
    kappa = np.ascontiguousarray(kappa, np.float64)
    tau = np.ascontiguousarray(tau, np.float64)
    n = kappa.shape[0]
    out = dict(phi=np.empty((n, 4)), valid=np.empty((n, 4), np.bool_), force=np.empty((n, 4)),
               moment=np.empty((n, 4)), stable=np.empty((n, 4), np.bool_))
    u1h, u2h, u3h = (float(x) for x in uhat)
    _kernel(float(K1), float(K2), float(K3), float(K13), float(K23), u1h, u2h, u3h, kappa, tau,
            out["phi"], out["valid"], out["force"], out["moment"], out["stable"])
    return out
