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

Only the primal values come from here: `_roots` keeps the implicit-function derivative,
`phi` (`_roots._angle`) and every other path (float32, accelerators, no numba) in JAX.
numba is optional (``pip install "helixrod[numba]"``); without it, or with
``HELIXROD_REGISTER_KERNEL=0`` in the environment, `_roots` runs its XLA program.  The
handler is compiled once per installation (numba's on-disk cache, next to this file or
in numba's per-user cache directory).
"""

from __future__ import annotations

import ctypes
import math

import jax
import jax.numpy as jnp
import numba
import numpy as np
from numba import types
from numba.extending import intrinsic

from ._roots import ASYMPTOTIC_TOL, FAST_ITERATIONS, LEFT_TOL, MORE_ITERATIONS, POLISH_LIMIT, ROUNDOFF_TOL, TANGENT_TOL, TINY

#: The name XLA knows the handler by.
TARGET = "helixrod_register_roots"
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
def _solve_block(lo, hi, A, B, C, cos_out, sin_out, valid, tangent, continuum_out):
    """Points lo ... hi - 1 (at most `_BLOCK`) of the flat arrays into the outputs."""
    cos0, sin0 = np.empty(_BLOCK), np.empty(_BLOCK)
    cos1, sin1 = np.empty(_BLOCK), np.empty(_BLOCK)
    simple = np.empty(_BLOCK, np.bool_)
    cs, sn, ok = np.empty(4), np.empty(4), np.empty(4, np.bool_)
    # Branch-free (selects only), so that LLVM vectorises it: the fast path of the two
    # outer registers, and whether the point needs nothing more.
    for i in range(lo, hi):
        finite, continuum, turn, a, b, c = _prepare(A[i], B[i], C[i])
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
        r = i - lo
        cos0[r] = -y0 if turn else x0
        sin0[r] = x0 if turn else y0
        cos1[r] = -y1 if turn else x1
        sin1[r] = x1 if turn else y1
        simple[r] = finite & (not continuum) & (not factorable) & (astroid > TANGENT_TOL) & done0 & done1
    for i in range(lo, hi):
        r = i - lo
        if simple[r]:
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
# The XLA FFI handler: reads the call frame's buffers and calls `_solve_points`.


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
def _arguments(frame_address):
    """The call frame's buffers as arrays, and whether XLA asks to execute: registration
    first calls the handler for its metadata (the FFI version it was built for)."""
    frame = numba.carray(frame_address, (15,), dtype=np.int64)
    if frame[1] != 0:
        base = _words(frame[1], 4)
        if (base[1] & 0xFFFFFFFF) == _EXTENSION_METADATA:
            metadata = base[3]
            version = numba.carray(_pointer(metadata + 24), (2,), dtype=np.int32)
            version[0], version[1] = _API_MAJOR, _API_MINOR
            numba.carray(_pointer(metadata + 32), (1,), dtype=np.uint32)[0] = 0
    # Executed: this module's own calls, 3 arguments and 5 results (anything else is left alone).
    execute = frame[1] == 0 and (frame[4] & 0xFFFFFFFF) == _STAGE_EXECUTE and frame[7] == 3 and frame[12] == 5
    args = _words(frame[9], 3) if execute else np.zeros(3, np.int64)
    rets = _words(frame[14], 5) if execute else np.zeros(5, np.int64)
    n = 0
    if execute:
        first = _words(args[0], 6)
        dims = _words(first[5], first[4])
        n = 1
        for k in range(first[4]):
            n *= dims[k]
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


def _serial_handler(frame_address):
    execute, A, B, C, cos_out, sin_out, valid, tangent, continuum = _arguments(frame_address)
    if execute:
        _solve_serial(A, B, C, cos_out, sin_out, valid, tangent, continuum)
    return _pointer(0)


def _parallel_handler(frame_address):
    execute, A, B, C, cos_out, sin_out, valid, tangent, continuum = _arguments(frame_address)
    if execute:
        _solve_parallel(A, B, C, cos_out, sin_out, valid, tangent, continuum)
    return _pointer(0)


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
_handler = numba.cfunc(types.voidptr(types.voidptr), cache=True)(_parallel_handler if PARALLEL else _serial_handler)
jax.ffi.register_ffi_target(TARGET, jax.ffi.pycapsule(ctypes.cast(_handler.address, ctypes.c_void_p)), platform="cpu")


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
    if not ok:
        raise RuntimeError("the register kernel's results failed its check (an XLA FFI it was not written for?)")


def solve(A, B, C):
    """`(cos_phi, sin_phi, valid, continuum, tangent)` of flat float64 arrays A, B, C of
    shape (n,): per-slot outputs (n, 4), `continuum` (n,); as `_roots._solve_in_xla`."""
    n = A.shape[0]
    per_slot = jax.ShapeDtypeStruct((n, 4), jnp.float64)
    flags = jax.ShapeDtypeStruct((n, 4), jnp.bool_)
    shapes = (per_slot, per_slot, flags, jax.ShapeDtypeStruct((n,), jnp.bool_), flags)
    return jax.ffi.ffi_call(TARGET, shapes, vmap_method="broadcast_all")(A, B, C)
