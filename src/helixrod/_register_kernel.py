"""The register solve of `_roots` as one compiled CPU loop, called from XLA through its FFI.

On a CPU, XLA runs `_roots`' register solve as a few dozen separate elementwise passes over
each chunk of points (every intermediate array written to memory and read back), and every
point pays for the selects of paths it does not take.  This module compiles the same
algorithm -- the same formulas, starts, step counts, convergence tests and thresholds, so
that it returns the same registers to rounding -- as one loop over the points with numba
(Lam, Pitrou & Seibert, "Numba: a LLVM-based Python JIT compiler", LLVM-HPC 2015), exposed
to XLA as a typed FFI handler (`XLA_FFI_Error* handler(XLA_FFI_CallFrame*)`, the ABI of
``xla/ffi/api/c_api.h``):

* blocks of `_BLOCK` points (their scratch stays in the L1 cache) take a branch-free pass
  that LLVM vectorises: the fast path of the two outer registers of every point;
* the points that pass leaves -- an inner pair, a zero coefficient, a continuum, a
  non-finite input, an undecided astroid test or an unconverged root (~5 % of the points
  of a typical rod) -- are solved one at a time, as `_roots._solve_in_xla` solves them.

Above `_SERIAL_POINTS` points the blocks are shared among numba's threads
(`numba.get_num_threads()`, ``NUMBA_NUM_THREADS``) when numba's threading layer can be
entered from several threads at once (tbb or OpenMP: XLA calls the handler from its own
threads); with numba's fallback layer the kernel runs on one thread.  OpenMP's threads do
not survive a `fork`: start worker processes with "spawn" after using the kernel.

A second handler (`wrench`) serves `helix_equilibria` asked for `WRENCH_FIELDS` (phi,
valid, force, moment, stable) of one rod: the register coefficients, the same register
solve and the fields of `_equilibria._fields_in_xla` (the same formulas) in one pass per
block, the points of the fast path with their wrench in the vectorised loop; XLA's
program otherwise makes a dozen passes over arrays of the points for the fields.

Only the primal values come from here: `_roots` keeps the implicit-function derivative,
`_equilibria` the derivatives of the fields, and every other path (float32, accelerators,
no numba) is JAX's.
numba is optional (``pip install "helixrod[numba]"``); without it, or with
``HELIXROD_REGISTER_KERNEL=0`` in the environment, `_roots` runs its XLA program.  The
handler is compiled once per installation (numba's on-disk cache, next to this file or
in numba's per-user cache directory).
"""

from __future__ import annotations

import ctypes
import math
import sys

import jax
import jax.numpy as jnp
import numba
import numpy as np
from numba import types
from numba.extending import intrinsic

from ._roots import (
    ASYMPTOTIC_TOL, ATAN_COEFFICIENTS, FAST_ITERATIONS, LEFT_TOL, MORE_ITERATIONS, POLISH_LIMIT, ROUNDOFF_TOL, TAN_PI_8,
    TANGENT_TOL, TINY,
)

#: The names XLA knows the handlers by: the registers of coefficients A, B, C (`solve`), and
#: the registers of helices of one rod with their wrench and stability (`wrench`).
TARGET = "helixrod_register_roots"
WRENCH_TARGET = "helixrod_helix_wrench"
#: The fields of `helix_equilibria` that `wrench` computes.
WRENCH_FIELDS = ("phi", "valid", "force", "moment", "stable")
# Points per block of the vectorised pass, and the most points solved on one thread.
_BLOCK = 512
_SERIAL_POINTS = 2 * _BLOCK
_JIT = dict(cache=True, error_model="numpy", inline="always")


# ---------------------------------------------------------------------------------------
# The algorithm, point by point (the formulas of `_roots._solve`; see its docstrings).


@numba.njit(**_JIT)
def _unit(x, y):
    factor = 1.5 - 0.5 * (x * x + y * y)
    return x * factor, y * factor


@numba.njit(**_JIT)
def _halley(nu, aa, Q2, P2, e):
    d = aa + e * nu
    N = Q2 * d * d + P2 * nu * nu
    dN = 2 * (e * Q2 * d + P2 * nu)
    g = nu * d
    dg = d + e * nu
    H = g - math.sqrt(N)
    D1 = 2 * N * dg - g * dN
    D2 = 8 * e * N * N - 4 * dg * dN * N + 3 * g * dN * dN - 4 * g * (Q2 + P2) * N
    den = 2 * D1 * D1 - H * D2
    return (nu * den - 4 * N * H * D1) / den


@numba.njit(**_JIT)
def _newton(nu, aa, Q2, P2, e):
    d = aa + e * nu
    N = Q2 * d * d + P2 * nu * nu
    den = Q2 * d * d * d + e * P2 * nu * nu * nu
    return (nu * den + N * (math.sqrt(N) - nu * d)) / den


@numba.njit(**_JIT)
def _converged(nu, last, before, halley):
    last, before = abs(last) / nu, abs(before) / nu
    left = last * last * last / (before * before) if halley else last * last / before
    return (last <= ROUNDOFF_TOL) | ((last <= ASYMPTOTIC_TOL) & (left <= LEFT_TOL))


@numba.njit(**_JIT)
def _fast_root(start, aa, Q2, P2, e):
    """`FAST_ITERATIONS` Halley steps; the root and whether it passed every test."""
    before_last, last_nu, nu = start, start, start
    for _ in range(FAST_ITERATIONS):
        before_last, last_nu, nu = last_nu, nu, _halley(nu, aa, Q2, P2, e)
    d = aa + e * nu
    rising = Q2 * d * d * d + e * P2 * nu * nu * nu > 0
    done = _converged(nu, nu - last_nu, last_nu - before_last, True) & rising & (nu > 0) & (d > 0)
    return nu, done


@numba.njit(**_JIT)
def _careful_root(start, aa, Q2, P2, e):
    """Newton steps until converged (at most `MORE_ITERATIONS`)."""
    nu, last, before = start, np.nan, np.nan
    for _ in range(MORE_ITERATIONS):
        if _converged(nu, last, before, False):
            break
        new = _newton(nu, aa, Q2, P2, e)
        nu, last, before = new, new - nu, last
    return nu


@numba.njit(**_JIT)
def _xy(swap, sign_u, nu, aa, Q, P, e):
    d = aa + e * nu
    inv = 1 / (nu * d)
    U = sign_u * Q * d * inv
    V = -P * nu * inv
    return _unit(V, U) if swap else _unit(U, V)


@numba.njit(**_JIT)
def _prepare(A, B, C):
    """Finite stand-in, scale, quarter turn: (finite, continuum, turn, a, b, c)."""
    finite = math.isfinite(A) & math.isfinite(B) & math.isfinite(C)
    A = A if finite else 0.5
    B = B if finite else 0.5
    C = C if finite else 0.5
    scale = max(max(abs(A), abs(B)), abs(C))
    continuum = scale == 0
    inv_scale = 1 / (1.0 if continuum else scale)
    a, b, c = A * inv_scale, B * inv_scale, C * inv_scale
    turn = a < 0
    return finite, continuum, turn, abs(a), (-c if turn else b), (b if turn else c)


@numba.njit(cache=True, error_model="numpy")
def _point(A, B, C, cos_out, sin_out, valid, tangent, continuum_out, i, cs, sn, ok):
    """Every register of one point, as `_roots._solve_in_xla` finds it, into row i (`cs`, `sn`,
    `ok`: scratch of 4 slots each)."""
    finite, continuum, turn, a, b, c = _prepare(A, B, C)
    cs[:] = 0.0
    sn[:] = 0.0
    ok[:] = False
    tan2 = False
    if continuum:
        for s in range(4):
            cos_out[i, s], sin_out[i, s], valid[i, s], tangent[i, s] = 1.0, 0.0, s == 0, False
        continuum_out[i] = True
        return
    if (abs(b) <= TINY) | (abs(c) <= TINY):
        # `_roots._factorable`.
        sign_b = -1.0 if b < 0 else 1.0
        sign_c = -1.0 if c < 0 else 1.0
        c_zero = abs(c) <= abs(b)
        q = (-b if c_zero else -c) / (2 * (a if a > 0 else 1.0))
        pair = (a > 0) & (abs(q) < 1)
        r = math.sqrt(max(1 - q * q, 0.0))
        rb, rc = sign_b * r, sign_c * r
        if c_zero:
            cs[0], cs[1], cs[2], cs[3] = sign_b, (q if pair else -sign_b), -sign_b, q
            sn[0], sn[1], sn[2], sn[3] = 0.0, (rc if pair else 0.0), 0.0, -rc
        else:
            cs[0], cs[1], cs[2], cs[3] = (rb if pair else 0.0), 0.0, -rb, 0.0
            sn[0], sn[1], sn[2], sn[3] = (q if pair else -sign_c), sign_c, q, -sign_c
        ok[0], ok[1], ok[2], ok[3] = True, True, pair, pair
    else:
        a2, b2, c2 = a * a, b * b, c * c
        aa = 2 * a
        abs_b, abs_c = abs(b), abs(c)
        r_low = max(abs_b, abs_c) + 0.41421356 * min(abs_b, abs_c)
        w = b2 + c2 - 4 * a2
        astroid = w * w * w + 108 * a2 * b2 * c2
        pair = astroid < -TANGENT_TOL
        done = abs(astroid) > TANGENT_TOL
        for s in range(4 if pair else 2):
            Q, P, absQ = (b, c, abs_b) if s % 2 == 0 else (c, b, abs_c)
            if s >= 2:
                room = 1 - P * P / ((aa - absQ) * (aa - absQ))
                nu, converged = _fast_root(absQ / math.sqrt(max(room, 1e-300)), aa, Q * Q, P * P, -1.0)
                cs[s], sn[s] = _xy(s == 3, -1.0, nu, aa, Q, P, -1.0)
            else:
                nu, converged = _fast_root(max(absQ, r_low - aa), aa, Q * Q, P * P, 1.0)
                cs[s], sn[s] = _xy(s == 1, 1.0, nu, aa, Q, P, 1.0)
            done &= converged
        if done:
            ok[0], ok[1], ok[2], ok[3] = True, True, pair, pair
        else:
            # The careful path (`_roots._solve(..., careful=True)`).
            cb, cc = np.cbrt(b), np.cbrt(c)
            sq = cb * cb + cc * cc
            gap = 4 * a2 - sq * sq * sq
            near = abs(gap) <= TANGENT_TOL * 4 * a2
            pair = (gap > 0) & (not near)
            tan2 = near & (a > 0)
            for s in range(4):
                Q, P, absQ = (b, c, abs_b) if s % 2 == 0 else (c, b, abs_c)
                inner = s >= 2
                if inner:
                    e = -1.0 if pair else 1.0
                    gap_q = aa - absQ if pair else 1.0
                    room = 1 - P * P / (gap_q * gap_q)
                    start = absQ / math.sqrt(max(room, 1e-300)) if pair else max(absQ, r_low - aa)
                else:
                    e, start = 1.0, max(absQ, r_low - aa)
                nu = _careful_root(start, aa, Q * Q, P * P, e) if (pair or not inner) else start
                x, y = _xy(s % 2 == 1, -1.0 if inner else 1.0, nu, aa, Q, P, e)
                is_tangent = tan2 & (s == 2)
                if is_tangent:
                    tnorm = 1 / math.sqrt(cb * cb + cc * cc)
                    x, y = -cb * tnorm, -cc * tnorm
                f = 2 * a * x * y + b * y + c * x
                fp = 2 * a * (x * x - y * y) + b * x - c * y
                rotation = -f / (1.0 if fp == 0 else fp)
                if not ((abs(rotation) <= POLISH_LIMIT) and not is_tangent):
                    rotation = 0.0
                cs[s], sn[s] = _unit(x - rotation * y, y + rotation * x)
            ok[0], ok[1], ok[2], ok[3] = True, True, pair | tan2, pair
    for s in range(4):
        x, y = cs[s], sn[s]
        cos_out[i, s] = -y if turn else x
        sin_out[i, s] = x if turn else y
        valid[i, s] = ok[s] & finite
        tangent[i, s] = (s == 2) & tan2 & finite
    continuum_out[i] = False


@numba.njit(**_JIT)
def _outer_pair(A, B, C):
    """The fast path of the two outer registers (cos, sin of slot 0, of slot 1), and
    whether the point needs nothing more (`simple`: no inner pair, no zero coefficient, no
    continuum, finite, decided astroid test, both roots converged).  Selects only."""
    finite, continuum, turn, a, b, c = _prepare(A, B, C)
    factorable = (abs(b) <= TINY) | (abs(c) <= TINY)
    b = 1.0 if factorable else b
    c = 1.0 if factorable else c
    abs_b, abs_c = abs(b), abs(c)
    a2, b2, c2 = a * a, b * b, c * c
    w = b2 + c2 - 4 * a2
    astroid = w * w * w + 108 * a2 * b2 * c2
    aa = 2 * a
    r_low = max(abs_b, abs_c) + 0.41421356 * min(abs_b, abs_c)
    nu0, done0 = _fast_root(max(abs_b, r_low - aa), aa, b2, c2, 1.0)
    nu1, done1 = _fast_root(max(abs_c, r_low - aa), aa, c2, b2, 1.0)
    x0, y0 = _xy(False, 1.0, nu0, aa, b, c, 1.0)
    x1, y1 = _xy(True, 1.0, nu1, aa, c, b, 1.0)
    simple = finite & (not continuum) & (not factorable) & (astroid > TANGENT_TOL) & done0 & done1
    return (-y0 if turn else x0), (x0 if turn else y0), (-y1 if turn else x1), (x1 if turn else y1), simple


@numba.njit(**_JIT)
def _solve_block(lo, hi, A, B, C, cos_out, sin_out, valid, tangent, continuum_out):
    """Points lo ... hi - 1 (at most `_BLOCK`) of the flat arrays into the outputs."""
    cos0, sin0 = np.empty(_BLOCK), np.empty(_BLOCK)
    cos1, sin1 = np.empty(_BLOCK), np.empty(_BLOCK)
    simple = np.empty(_BLOCK)
    cs, sn, ok = np.empty(4), np.empty(4), np.empty(4, np.bool_)
    # Branch-free (selects only), so that LLVM vectorises it: the fast path of the two
    # outer registers, and whether the point needs nothing more.  Indexed from 0 (views of
    # the block): an index from `lo` may be negative as far as LLVM knows, and the
    # wraparound test numba then adds keeps the loop scalar.
    block_A, block_B, block_C = A[lo:hi], B[lo:hi], C[lo:hi]
    for r in range(hi - lo):
        cos0[r], sin0[r], cos1[r], sin1[r], fast = _outer_pair(block_A[r], block_B[r], block_C[r])
        simple[r] = 1.0 if fast else 0.0
    for i in range(lo, hi):
        r = i - lo
        if simple[r] != 0:
            cos_out[i, 0], cos_out[i, 1], cos_out[i, 2], cos_out[i, 3] = cos0[r], cos1[r], 0.0, 0.0
            sin_out[i, 0], sin_out[i, 1], sin_out[i, 2], sin_out[i, 3] = sin0[r], sin1[r], 0.0, 0.0
            valid[i, 0], valid[i, 1], valid[i, 2], valid[i, 3] = True, True, False, False
            tangent[i, 0], tangent[i, 1], tangent[i, 2], tangent[i, 3] = False, False, False, False
            continuum_out[i] = False
        else:
            _point(A[i], B[i], C[i], cos_out, sin_out, valid, tangent, continuum_out, i, cs, sn, ok)


@numba.njit(cache=True, error_model="numpy")
def _solve_serial(A, B, C, cos_out, sin_out, valid, tangent, continuum_out):
    n = A.shape[0]
    for j in range((n + _BLOCK - 1) // _BLOCK):
        _solve_block(j * _BLOCK, min(n, (j + 1) * _BLOCK), A, B, C, cos_out, sin_out, valid, tangent, continuum_out)


@numba.njit(cache=True, error_model="numpy", parallel=True)
def _solve_parallel(A, B, C, cos_out, sin_out, valid, tangent, continuum_out):
    n = A.shape[0]
    if n <= _SERIAL_POINTS:  # a fit's few helices: no threads to start and join
        _solve_serial(A, B, C, cos_out, sin_out, valid, tangent, continuum_out)
        return
    for j in numba.prange((n + _BLOCK - 1) // _BLOCK):
        _solve_block(j * _BLOCK, min(n, (j + 1) * _BLOCK), A, B, C, cos_out, sin_out, valid, tangent, continuum_out)


# ---------------------------------------------------------------------------------------
# The registers with their wrench and stability, of one rod: `helix_equilibria` with the
# fields `WRENCH_FIELDS` (the formulas of `_equilibria._fields_in_xla`).

# arctan's polynomial of `_roots._angle` (constants, so that its Horner steps unroll).
_P0, _P1, _P2, _P3, _P4, _P5, _P6, _P7, _P8, _P9, _P10 = ATAN_COEFFICIENTS


@numba.njit(**_JIT)
def _angle(cos_phi, sin_phi):
    """`_roots._angle`: phi in [0, 2 pi) from its cosine and sine (selects only)."""
    ax, ay = abs(cos_phi), abs(sin_phi)
    low = ay <= TAN_PI_8 * ax
    high = ax <= TAN_PI_8 * ay
    num = ay if low else (-ax if high else ay - ax)
    den = ax if low else (ay if high else ay + ax)
    t = num / (den if den > 0 else 1.0)
    z = t * t
    poly = ((((((((((_P10 * z + _P9) * z + _P8) * z + _P7) * z + _P6) * z + _P5) * z + _P4) * z + _P3) * z + _P2) * z
             + _P1) * z + _P0)
    alpha = (0.0 if low else (0.5 * math.pi if high else 0.25 * math.pi)) + (t + t * z * poly)
    upper = sin_phi >= 0
    right = (alpha if upper else 2 * math.pi - alpha)
    left = (math.pi - alpha if upper else math.pi + alpha)
    phi = right if cos_phi >= 0 else left
    return phi - 2 * math.pi if phi >= 2 * math.pi else phi


@numba.njit(**_JIT)
def _wrench(c, sn, k, t, norm_u, A, B, C, tangent, rod):
    """phi, axial force, axial moment and d2W/dphi2 of the register (cos `c`, sin `sn`) of
    the helix (`k` > 0, `t`; `norm_u` = |(k, t)|) of `rod` (coefficients A, B, C)."""
    K1, K2, K3, K13, K23, h1, h2, h3 = rod[0], rod[1], rod[2], rod[3], rod[4], rod[5], rod[6], rod[7]
    u1, u2, u3 = k * sn, k * c, t
    v1, v2, v3 = u1 - h1, u2 - h2, u3 - h3
    m1 = K1 * v1 + K13 * v3
    m2 = K2 * v2 + K23 * v3
    m3 = K13 * v1 + K23 * v2 + K3 * v3
    mu1 = (m1 * sn + m2 * c) / k
    mu2 = m3 - mu1 * t
    d2 = 0.0 if tangent else k * (2 * A * (c * c - sn * sn) + B * c - C * sn)
    return _angle(c, sn), mu2 * norm_u, (m1 * u1 + m2 * u2 + m3 * u3) / norm_u, d2


@numba.njit(**_JIT)
def _helix(kappa, tau, rod):
    """The helix's register coefficients A, B, C (a harmless problem outside the domain,
    masked), kappa (1 outside), |u| (as jnp.hypot, no overflow) and whether it is helical."""
    K1, K2, K13, K23, h1, h2, h3 = rod[0], rod[1], rod[3], rod[4], rod[5], rod[6], rod[7]
    helical = math.isfinite(kappa) & math.isfinite(tau) & (kappa > 0)
    A = 0.5 * (K1 - K2) * kappa if helical else 1.0
    B = K2 * h2 + K23 * (h3 - tau) if helical else 0.0
    C = K13 * (tau - h3) - K1 * h1 if helical else 0.0
    k = kappa if helical else 1.0
    big, small = max(k, abs(tau)), min(k, abs(tau))
    ratio = small / big if big > 0 else 0.0
    return A, B, C, k, big * math.sqrt(1 + ratio * ratio), helical


@numba.njit(cache=True, error_model="numpy")
def _wrench_block(lo, hi, kappa, tau, rod, phi_o, valid_o, force_o, moment_o, stable_o):
    """Points lo ... hi - 1 (at most `_BLOCK`): registers, phi, force, moment, stability.
    The points the fast path settles (two outer registers) in one branch-free loop with
    their wrench (LLVM vectorises it); the others one at a time (`_point`).  Indexed from 0
    on views of the block (as `_solve_block`), flags through float scratch (a boolean
    store kept the loop scalar: measured 171 against 31 ns a point on one core)."""
    count = hi - lo
    kappa, tau = kappa[lo:hi], tau[lo:hi]
    phi_o, valid_o, force_o = phi_o[4 * lo:4 * hi], valid_o[4 * lo:4 * hi], force_o[4 * lo:4 * hi]
    moment_o, stable_o = moment_o[4 * lo:4 * hi], stable_o[4 * lo:4 * hi]
    simple, d2 = np.empty(_BLOCK), np.empty(2 * _BLOCK)
    cs, sn, ok = np.empty(4), np.empty(4), np.empty(4, np.bool_)
    cos_r, sin_r = np.empty((1, 4)), np.empty((1, 4))
    valid_r, tangent_r, continuum_r = np.empty((1, 4), np.bool_), np.empty((1, 4), np.bool_), np.empty(1, np.bool_)
    nan = np.nan
    for i in range(count):
        A, B, C, k, norm_u, helical = _helix(kappa[i], tau[i], rod)
        c0, s0, c1, s1, fast = _outer_pair(A, B, C)
        phi0, force0, moment0, d0 = _wrench(c0, s0, k, tau[i], norm_u, A, B, C, False, rod)
        phi1, force1, moment1, d1 = _wrench(c1, s1, k, tau[i], norm_u, A, B, C, False, rod)
        j = 4 * i
        phi_o[j], phi_o[j + 1], phi_o[j + 2], phi_o[j + 3] = phi0, phi1, nan, nan
        force_o[j], force_o[j + 1], force_o[j + 2], force_o[j + 3] = force0, force1, nan, nan
        moment_o[j], moment_o[j + 1], moment_o[j + 2], moment_o[j + 3] = moment0, moment1, nan, nan
        d2[2 * i], d2[2 * i + 1] = d0, d1
        simple[i] = 1.0 if fast & helical else 0.0
    for i in range(count):
        j = 4 * i
        valid_o[j], valid_o[j + 1], valid_o[j + 2], valid_o[j + 3] = True, True, False, False
        stable_o[j], stable_o[j + 1], stable_o[j + 2], stable_o[j + 3] = d2[2 * i] > 0, d2[2 * i + 1] > 0, False, False
    for i in range(count):
        if simple[i] != 0:
            continue
        A, B, C, k, norm_u, helical = _helix(kappa[i], tau[i], rod)
        _point(A, B, C, cos_r, sin_r, valid_r, tangent_r, continuum_r, 0, cs, sn, ok)
        continuum = continuum_r[0] & helical
        for s in range(4):
            j = 4 * i + s
            valid = valid_r[0, s] & helical
            tangent = tangent_r[0, s]
            phi, force, moment, d2s = _wrench(cos_r[0, s], sin_r[0, s], k, tau[i], norm_u, A, B, C, tangent, rod)
            phi_o[j] = phi if valid else nan
            force_o[j] = force if valid else nan
            moment_o[j] = moment if valid else nan
            valid_o[j] = valid
            stable_o[j] = valid & (not tangent) & (not continuum) & (d2s > 0)


@numba.njit(cache=True, error_model="numpy")
def _wrench_serial(kappa, tau, rods, phi, valid, force, moment, stable):
    """The wrench of every row (a rod and its points; several under `jax.vmap`)."""
    rows = rods.shape[0] // 8
    points = kappa.shape[0] // max(rows, 1)
    for row in range(rows):
        rod, first = rods[8 * row:8 * row + 8], row * points
        for b in range((points + _BLOCK - 1) // _BLOCK):
            lo = first + b * _BLOCK
            _wrench_block(lo, min(first + points, lo + _BLOCK), kappa, tau, rod, phi, valid, force, moment, stable)


@numba.njit(cache=True, error_model="numpy", parallel=True)
def _wrench_parallel(kappa, tau, rods, phi, valid, force, moment, stable):
    """`_wrench_serial` with the blocks of a row of more than `_SERIAL_POINTS` points
    shared among numba's threads."""
    rows = rods.shape[0] // 8
    points = kappa.shape[0] // max(rows, 1)
    if points <= _SERIAL_POINTS:
        _wrench_serial(kappa, tau, rods, phi, valid, force, moment, stable)
        return
    for row in range(rows):
        rod, first = rods[8 * row:8 * row + 8], row * points
        for b in numba.prange((points + _BLOCK - 1) // _BLOCK):
            lo = first + b * _BLOCK
            _wrench_block(lo, min(first + points, lo + _BLOCK), kappa, tau, rod, phi, valid, force, moment, stable)


# ---------------------------------------------------------------------------------------
# The XLA FFI handlers: read the call frame's buffers and call the loops above.


@intrinsic
def _pointer(typingctx, address):
    """The integer `address` as a void pointer."""

    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], context.get_value_type(types.voidptr))

    return types.voidptr(types.int64), codegen


@numba.njit(**_JIT)
def _words(address, count):
    return numba.carray(_pointer(address), (count,), dtype=np.int64)


# Offsets in 8-byte words (x86-64 / aarch64 layout of c_api.h's structs): in
# XLA_FFI_CallFrame, extension_start 1, stage 4, args.size 7, args.args 9, rets.size 12,
# rets.rets 14; in XLA_FFI_Buffer, data 3, rank 4, dims 5; in XLA_FFI_Extension_Base, type 1;
# in XLA_FFI_Metadata_Extension, metadata 3; in XLA_FFI_Metadata, api_version.major_version
# at byte 24 (int32, minor at 28), traits at byte 32 (uint32).
_EXTENSION_METADATA = 1
_STAGE_EXECUTE = 3
_API_MAJOR, _API_MINOR = 0, 1


@numba.njit(**_JIT)
def _buffer(address, count, dtype):
    """The data of the XLA_FFI_Buffer at `address` (none at address 0) as `count` items."""
    data = _words(address, 4)[3] if address != 0 else 0
    return numba.carray(_pointer(data), (count,), dtype=dtype)


@numba.njit(**_JIT)
def _frame(frame_address, n_args, n_rets):
    """The call frame's argument and result buffer addresses, and whether XLA asks to
    execute this module's call (`n_args` arguments, `n_rets` results; anything else is left
    alone): registration first calls the handler for its metadata (the FFI version it was
    built for)."""
    frame = numba.carray(frame_address, (15,), dtype=np.int64)
    if frame[1] != 0:
        base = _words(frame[1], 4)
        if (base[1] & 0xFFFFFFFF) == _EXTENSION_METADATA:
            metadata = base[3]
            version = numba.carray(_pointer(metadata + 24), (2,), dtype=np.int32)
            version[0], version[1] = _API_MAJOR, _API_MINOR
            numba.carray(_pointer(metadata + 32), (1,), dtype=np.uint32)[0] = 0
    execute = frame[1] == 0 and (frame[4] & 0xFFFFFFFF) == _STAGE_EXECUTE and frame[7] == n_args and frame[12] == n_rets
    args = _words(frame[9], n_args) if execute else np.zeros(n_args, np.int64)
    rets = _words(frame[14], n_rets) if execute else np.zeros(n_rets, np.int64)
    return execute, args, rets


@numba.njit(**_JIT)
def _size(execute, address):
    """The number of items of the XLA_FFI_Buffer at `address` (0 unless `execute`)."""
    if not execute:
        return 0
    buffer = _words(address, 6)
    dims = _words(buffer[5], buffer[4])
    n = 1
    for k in range(buffer[4]):
        n *= dims[k]
    return n


@numba.njit(**_JIT)
def _arguments(frame_address):
    """`solve`'s buffers as arrays (3 arguments, 5 results), and whether to execute."""
    execute, args, rets = _frame(frame_address, 3, 5)
    n = _size(execute, args[0])
    return (
        execute,
        _buffer(args[0], n, np.float64),
        _buffer(args[1], n, np.float64),
        _buffer(args[2], n, np.float64),
        _buffer(rets[0], 4 * n, np.float64).reshape((n, 4)),
        _buffer(rets[1], 4 * n, np.float64).reshape((n, 4)),
        _buffer(rets[2], 4 * n, np.bool_).reshape((n, 4)),
        _buffer(rets[4], 4 * n, np.bool_).reshape((n, 4)),
        _buffer(rets[3], n, np.bool_),
    )


@numba.njit(**_JIT)
def _wrench_arguments(frame_address):
    """`wrench`'s buffers as flat arrays (kappa, tau, the rods; phi, valid, force, moment,
    stable), and whether to execute."""
    execute, args, rets = _frame(frame_address, 3, 5)
    n = _size(execute, args[0])
    return (
        execute,
        _buffer(args[0], n, np.float64),
        _buffer(args[1], n, np.float64),
        _buffer(args[2], _size(execute, args[2]), np.float64),
        _buffer(rets[0], 4 * n, np.float64),
        _buffer(rets[1], 4 * n, np.bool_),
        _buffer(rets[2], 4 * n, np.float64),
        _buffer(rets[3], 4 * n, np.float64),
        _buffer(rets[4], 4 * n, np.bool_),
    )


# Huge pages for the results: XLA's allocator maps a large result afresh at every call, and
# the kernel's first write to each 4 KB page is a page fault (10^7 points: 1.04 GB of
# results, 254 000 faults, 0.36 s of system time on 2 cores, more than the kernel's gap to
# the numba peer, whose NumPy arrays take huge pages: NumPy advises them for arrays of 4 MB
# or more).  The same advice, where Linux takes it (transparent huge pages `madvise` or
# `always`), before the kernel touches them.
_HUGE_PAGE_BYTES = 1 << 22
_MADV_HUGEPAGE = 14

if sys.platform.startswith("linux"):
    # Linked by name (a ctypes function would be an address, which numba cannot cache).
    _madvise = types.ExternalFunction("madvise", types.intc(types.uintp, types.uintp, types.intc))

    @numba.njit(**_JIT)
    def _advise_huge_pages(array):
        if array.nbytes >= _HUGE_PAGE_BYTES:
            start = (array.ctypes.data + 4095) & ~np.uintp(4095)
            end = (array.ctypes.data + array.nbytes) & ~np.uintp(4095)
            _madvise(start, end - start, _MADV_HUGEPAGE)  # advice: its failure changes nothing

else:

    @numba.njit(**_JIT)
    def _advise_huge_pages(array):
        pass


@numba.njit(cache=True, parallel=True)
def _start_threads(x):
    total = 0.0
    for i in numba.prange(x.shape[0]):
        total += x[i]
    return total


def _thread_safe_layer() -> bool:
    """Whether numba's threading layer (started here, chosen by numba's own rules) can be
    entered from several threads at once: XLA may call the handler from any of its
    threads, and numba's fallback layer ("workqueue") aborts the process on concurrent
    entry."""
    _start_threads(np.zeros(1))
    return numba.threading_layer() in ("tbb", "omp")


PARALLEL = _thread_safe_layer()
_solve_points = _solve_parallel if PARALLEL else _solve_serial
_wrench_points = _wrench_parallel if PARALLEL else _wrench_serial


def _solve_handler(frame_address):
    execute, A, B, C, cos_out, sin_out, valid, tangent, continuum = _arguments(frame_address)
    if execute:
        for result in (cos_out, sin_out):
            _advise_huge_pages(result)
        for flags in (valid, tangent):
            _advise_huge_pages(flags)
        _advise_huge_pages(continuum)  # 1-d, the flags 2-d: numba loops over tuples of one type only
        _solve_points(A, B, C, cos_out, sin_out, valid, tangent, continuum)
    return _pointer(0)


def _wrench_handler(frame_address):
    execute, kappa, tau, rods, phi, valid, force, moment, stable = _wrench_arguments(frame_address)
    if execute:
        for result in (phi, force, moment):
            _advise_huge_pages(result)
        for flags in (valid, stable):
            _advise_huge_pages(flags)
        _wrench_points(kappa, tau, rods, phi, valid, force, moment, stable)
    return _pointer(0)


_solve_cfunc = numba.cfunc(types.voidptr(types.voidptr), cache=True)(_solve_handler)
_wrench_cfunc = numba.cfunc(types.voidptr(types.voidptr), cache=True)(_wrench_handler)
for _target, _compiled in ((TARGET, _solve_cfunc), (WRENCH_TARGET, _wrench_cfunc)):
    jax.ffi.register_ffi_target(_target, jax.ffi.pycapsule(ctypes.cast(_compiled.address, ctypes.c_void_p)), platform="cpu")


def check():
    """Raise RuntimeError unless the handler reads and writes XLA's buffers as this module
    expects (a changed FFI layout would give garbage, not an error): registers of a few
    points checked in NumPy -- roots of f, counted as the astroid says, the continuum and a
    non-finite point flagged."""
    A = np.array([1.0, -0.7, 0.3, 1.0, 0.0, np.nan, 2.0, 1e-3])
    B = np.array([0.3, 0.2, -1.0, 0.0, 0.0, 1.0, -1.1, 0.5])
    C = np.array([-0.4, 0.9, 0.2, 0.5, 0.0, 1.0, 0.7, -2.0])
    with jax.ensure_compile_time_eval():  # also when first asked for inside a trace
        cos_phi, sin_phi, valid, continuum, _ = (np.asarray(x) for x in jax.jit(solve)(A, B, C))
    phi = np.arctan2(sin_phi, cos_phi)
    f = A[:, None] * np.sin(2 * phi) + B[:, None] * np.sin(phi) + C[:, None] * np.cos(phi)
    with np.errstate(invalid="ignore"):
        inside = np.abs(B) ** (2 / 3) + np.abs(C) ** (2 / 3) < np.abs(2 * A) ** (2 / 3)
    expected = np.where(inside, 4, 2)
    expected[4], expected[5] = 1, 0
    ok = (
        np.array_equal(valid.sum(axis=1), expected)
        and np.array_equal(continuum, np.arange(8) == 4)
        and np.all(np.abs(np.where(valid, f, 0.0)) < 1e-13)
        and np.all(np.abs(np.where(valid, cos_phi**2 + sin_phi**2 - 1.0, 0.0)) < 1e-14)
    )
    if not ok or not _wrench_checks():
        raise RuntimeError("the register kernel's results failed its check (an XLA FFI it was not written for?)")


def _wrench_checks() -> bool:
    """Whether `wrench` returns equilibria: at its valid registers m1 u2 = m2 u1 and the
    force mu2 |u| (NumPy), none at kappa = 0."""
    kappa, tau = np.array([0.5, 1.0, 2.0, 0.0]), np.array([1.5, -0.3, 0.7, 1.0])
    rod = np.array([1.0, 1.5, 0.8, 0.5, 0.5, 1.0, 0.0, 0.0])
    with jax.ensure_compile_time_eval():
        out = {name: np.asarray(x) for name, x in jax.jit(wrench)(kappa, tau, rod).items()}
    k, t, phi = kappa[:, None], tau[:, None], out["phi"]
    u = np.stack([k * np.sin(phi), k * np.cos(phi), np.broadcast_to(t, phi.shape)], axis=-1)
    K = np.array([[1.0, 0.0, 0.5], [0.0, 1.5, 0.5], [0.5, 0.5, 0.8]])
    m = (u - rod[5:]) @ K
    mu1 = (m[..., 0] * u[..., 0] + m[..., 1] * u[..., 1]) / (k * k)
    force = (m[..., 2] - mu1 * t) * np.hypot(k, t)
    valid = out["valid"]
    with np.errstate(invalid="ignore"):
        balanced = np.abs(m[..., 0] * u[..., 1] - m[..., 1] * u[..., 0]) < 1e-12
        forces = np.abs(force - out["force"]) < 1e-12 * (1 + np.abs(force))
    return bool(valid[:3, :2].all() and not valid[3].any() and balanced[valid].all() and forces[valid].all())


def solve(A, B, C):
    """`(cos_phi, sin_phi, valid, continuum, tangent)` of flat float64 arrays A, B, C of
    shape (n,): per-slot outputs (n, 4), `continuum` (n,); as `_roots._solve_in_xla`."""
    n = A.shape[0]
    per_slot = jax.ShapeDtypeStruct((n, 4), jnp.float64)
    flags = jax.ShapeDtypeStruct((n, 4), jnp.bool_)
    shapes = (per_slot, per_slot, flags, jax.ShapeDtypeStruct((n,), jnp.bool_), flags)
    return jax.ffi.ffi_call(TARGET, shapes, vmap_method="broadcast_all")(A, B, C)


def wrench(kappa, tau, rod_vector):
    """`WRENCH_FIELDS` of the helices (`kappa`, `tau`: flat float64 arrays (n,)) of one rod
    (`rod_vector`: its 8 parameters, `_rod.rod_vector`), as `_equilibria._fields_in_xla`
    computes them: a dict name -> (n, 4) array."""
    n = kappa.shape[0]
    value, flag = jax.ShapeDtypeStruct((n, 4), jnp.float64), jax.ShapeDtypeStruct((n, 4), jnp.bool_)
    call = jax.ffi.ffi_call(WRENCH_TARGET, (value, flag, value, value, flag), vmap_method="broadcast_all")
    return dict(zip(WRENCH_FIELDS, call(kappa, tau, rod_vector)))
