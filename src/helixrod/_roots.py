"""Every root of the register equation $A \\sin 2\\varphi + B \\sin\\varphi + C \\cos\\varphi = 0$.

The register condition of a uniform helix (docs/conventions.md) is $h = \\kappa f(\\varphi)$ with

$$f(\\varphi) = A \\sin 2\\varphi + B \\sin\\varphi + C\\cos\\varphi = \\frac{1}{\\kappa}
\\frac{dW}{d\\varphi},$$

so the registers are the critical points of the energy on the constraint circle.  On the
unit circle $v = (x, y) = (\\cos\\varphi, \\sin\\varphi)$ the energy is, up to a constant, the
quadratic $G(v) = -\\tfrac{A}{2}(x^2 - y^2) - Bx + Cy$, and its critical points solve
$\\nabla G = \\mu v$: the boundary problem of a trust-region step.  For $A \\ge 0$ (else turn
the circle by $\\pi/2$), $x = -B/(\\mu + A)$, $y = C/(\\mu - A)$ and the multiplier solves
the secular equation $B^2/(\\mu + A)^2 + C^2/(\\mu - A)^2 = 1$.  With $\\nu$ the distance of
$\\mu$ to the nearer pole, each register solves one of four problems of the same form

$$\\psi(\\nu) = \\Big(\\frac{Q^2}{\\nu^2} + \\frac{P^2}{(2A + e\\,\\nu)^2}\\Big)^{-1/2} = 1, \\qquad \\nu > 0:$$

* slot 0, the global minimum of $W$ on the circle: $\\mu = -A - \\nu$, $(Q, P, e) = (B, C, +1)$;
* slot 1, the global maximum: $\\mu = A + \\nu$, $(Q, P, e) = (C, B, +1)$;
* slots 2 and 3, the local minimum and maximum of the inner pair, which exists iff $(B, C)$
  lies inside the astroid $|B|^{2/3} + |C|^{2/3} < (2A)^{2/3}$: $\\mu = -A + \\nu$ with
  $(B, C, -1)$ and $\\mu = A - \\nu$ with $(C, B, -1)$, each on its side of the separator
  $\\nu_s = 2A |Q|^{2/3} / (|B|^{2/3} + |C|^{2/3})$ (the tangent register on the astroid).

On each of these branches $\\psi$ is increasing and concave left of its root (Moré &
Sorensen, SIAM J. Sci. Stat. Comput. 4 (1983) 553, for the outer branches; checked
numerically for the inner ones), and explicit lower bounds of every root are known.  So:

* the **fast path** takes `FAST_ITERATIONS` Halley steps on $\\psi = 1$ (cubic convergence;
  one square root and one division a step) from those bounds, and decides the inner pair
  by the sign of the astroid polynomial;
* the points it leaves unconverged or undecided -- a few in $10^4$ of random coefficients:
  next to the astroid's cusps, where a root is nearly triple, or next to a tangency -- are
  gathered a batch at a time and re-solved by the **careful path**: the astroid test by cube
  roots, and Newton steps, which climb monotonically to the root from the left, until they
  converge, then one Newton step on $f(\\varphi)$ itself (a rotation of $(x, y)$).

Elementwise arithmetic only (no eigenvalues, no data-dependent control flow in the fast
path), unchanged on a GPU.  On a CPU in float64 the same algorithm runs as one compiled loop
over the points when numba is installed (`_register_kernel`, called from XLA through its
FFI; `cpu_kernel`): 2-5x faster than XLA's elementwise passes and compiled once per
installation instead of at every first call; this module's XLA program is the reference
it is tested against, and the path everywhere else.  Exact zeros of $B$ or $C$ (the common uncoupled rods) have
closed forms (`_factorable`).  Registers closer than about $10^{-7}$ (relative to the
coefficients) to a tangency cannot be told apart in float64: where the astroid test is
within `TANGENT_TOL` of zero one *tangent* register -- the separator itself, the extremum
of $f$ -- is returned instead of the pair.
"""

from __future__ import annotations

import functools
import importlib.util
import os
import warnings

import jax
import jax.numpy as jnp

from ._compile import jit


# Slots: 0 global minimum of W on the circle, 1 global maximum, 2 the local minimum and
# 3 the local maximum of the inner pair (a tangent register, when there is one, in 2).
NUM_SLOTS = 4

# Halley steps of the fast path: on random coefficients (normal, or log-uniform over 7
# decades) and on kappa-tau grids, about 7 points in 10^4 are left to the careful path
# (tests/test_roots.py measures it).  Newton steps of the careful path at most: at an
# exact cusp the root is triple and Newton converges linearly (ratio 2/3).
FAST_ITERATIONS = 4
MORE_ITERATIONS = 128
# Points re-solved together by the careful path (a while loop takes as many batches as
# there are unconverged points), on a CPU and on an accelerator (where each batch is a
# round of kernel launches).
_FALLBACK_BATCH = 256
# Points with an inner pair solved together on a CPU (stage 2 of `_solve_in_xla`).
_INNER_BATCH = 1024
_ACCELERATOR_FALLBACK_BATCH = 16384
# Convergence, relative to nu.  A step at round-off; or, in the asymptotic regime, a
# last step small enough that the error it leaves -- about last^4 / before^3 for Halley,
# last^3 / before^2 for Newton -- is below LEFT_TOL.
ROUNDOFF_TOL = 1e-14
ASYMPTOTIC_TOL = 1e-4
LEFT_TOL = 1e-17
# Astroid test |4A^2 - (|B|^(2/3) + |C|^(2/3))^3| below this times 4A^2 -> tangent pair.
TANGENT_TOL = 64 * 2.220446049250313e-16
# Coefficients (scaled to max 1) below this are exact zeros: closed forms, error < 1e-100.
TINY = 1e-100
# The careful path's final rotation is skipped if Newton on f(phi) wants to move further
# than this (then it is not at a simple root: a tangent register).
POLISH_LIMIT = 1e-4

# Per-slot layout of the four secular problems: which coefficient is Q (the pole of the
# root), the branch (e = -1 on the inner pair), and how (x, y) are read from (Q/nu, P/d).
_Q_IS_B = (True, False, True, False)
_INNER = (False, False, True, True)
_SWAP = (False, True, False, True)
_SIGN_U = (1.0, 1.0, -1.0, -1.0)


def _slot(values, batch_ndim: int):
    """A constant per-slot vector (trailing axis of its length) of the rank of the per-slot
    arrays of a batch of `batch_ndim` dimensions (no implicit rank promotion)."""
    return jnp.reshape(jnp.asarray(values), (1,) * batch_ndim + (len(values),))


def _converged(nu, last, before, order):
    """Whether an iteration of convergence `order` (2 Newton, 3 Halley) has converged,
    from its last two steps."""
    last, before = jnp.abs(last) / nu, jnp.abs(before) / nu
    left = last**order / before ** (order - 1)
    return (last <= ROUNDOFF_TOL) | ((last <= ASYMPTOTIC_TOL) & (left <= LEFT_TOL))


def _secular_solve(nu, aa, Q2, P2, e, needed, careful):
    """Solve psi(nu) = 1 for each slot, from starts left of every root.  Every argument but
    `aa` ($2a$, per point) and `careful` is a tuple with one entry per slot: the start
    `nu`, $Q^2$, $P^2$, the branch `e` (the Python float 1.0 on an outer slot, so that its
    arithmetic folds away, or a per-point +-1) and whether the slot is `needed`.

    The slots are separate arrays, not a trailing axis: XLA's CPU loops then run over
    contiguous points with no broadcast index arithmetic, ~3x faster on the fast path.

    Fast path: `FAST_ITERATIONS` Halley steps.  Careful path: Newton steps until every
    `needed` slot has converged (at most `MORE_ITERATIONS`).  Each step ends with its
    division, so that XLA keeps nu itself in memory between steps: written as nu + step,
    the sum nu_0 + step_1 + ... + step_k is refolded into every later step, each then
    reading all earlier steps.  Returns nu and whether each slot converged (tuples)."""

    def newton(nu, Q2, P2, e):
        # psi - 1 = (nu d - sqrt N) / sqrt N with d = 2a + e nu, N = Q^2 d^2 + P^2 nu^2.
        d = aa + e * nu
        N = Q2 * d * d + P2 * nu * nu
        den = Q2 * d * d * d + e * P2 * nu * nu * nu
        return (nu * den + N * (jnp.sqrt(N) - nu * d)) / den

    def halley(nu, Q2, P2, e):
        # With g = nu d, s = sqrt N: psi - 1 = H / s (H = g - s), psi' = D1 / (2 s N),
        # psi'' = D2 / (4 s N^2), and the Halley step -2 h psi' / (2 psi'^2 - h psi'')
        # is -4 N H D1 / (2 D1^2 - H D2).
        d = aa + e * nu
        N = Q2 * d * d + P2 * nu * nu
        dN = 2 * (e * Q2 * d + P2 * nu)
        g = nu * d
        dg = d + e * nu
        H = g - jnp.sqrt(N)
        D1 = 2 * N * dg - g * dN
        D2 = 8 * e * N * N - 4 * dg * dN * N + 3 * g * dN * dN - 4 * g * (Q2 + P2) * N
        den = 2 * D1 * D1 - H * D2
        return (nu * den - 4 * N * H * D1) / den

    if not careful:
        roots, done = [], []
        for nu_s, Q2_s, P2_s, e_s in zip(nu, Q2, P2, e):
            history = [nu_s]
            for _ in range(FAST_ITERATIONS):
                history.append(halley(history[-1], Q2_s, P2_s, e_s))
            root, last, before = history[-1], history[-1] - history[-2], history[-2] - history[-3]
            # Halley is not monotone: next to a tangency it can cross the separator to the
            # other root of the pair.  A root of this slot's branch has psi' > 0 there.
            d = aa + e_s * root
            rising = Q2_s * d * d * d + e_s * P2_s * root * root * root > 0
            roots.append(root)
            done.append(_converged(root, last, before, 3) & rising & (root > 0) & (d > 0))
        return tuple(roots), tuple(done)

    def active(nu, last, before):
        return tuple(n & ~_converged(*x, 2) for n, x in zip(needed, zip(nu, last, before)))

    def unfinished(carry):
        k, *state = carry
        busy = active(*state)
        return (k < MORE_ITERATIONS) & functools.reduce(jnp.logical_or, (jnp.any(x) for x in busy))

    def body(carry):
        # Converged slots stop moving, so that a point's result does not depend on the
        # batch it is solved in.
        k, nu, last, before = carry
        moving = active(nu, last, before)
        new = tuple(newton(*x) for x in zip(nu, Q2, P2, e))
        return (
            k + 1,
            tuple(jnp.where(m, n1, n0) for m, n1, n0 in zip(moving, new, nu)),
            tuple(jnp.where(m, n1 - n0, l) for m, n1, n0, l in zip(moving, new, nu, last)),
            tuple(jnp.where(m, l, b) for m, l, b in zip(moving, last, before)),
        )

    # No steps yet: NaN, which no convergence test passes (an infinite step before the
    # first would make the asymptotic test pass after one step).
    nan = tuple(jnp.full_like(x, jnp.nan) for x in nu)
    _, nu, last, before = jax.lax.while_loop(unfinished, body, (0, tuple(nu), nan, nan))
    return nu, tuple(_converged(*x, 2) for x in zip(nu, last, before))


def _unit(x, y):
    """(x, y) scaled to unit length, for |(x, y)| within ~1e-8 of 1: one Newton step for
    the inverse square root from 1 (error ~ (|v|^2 - 1)^2), with no division."""
    factor = 1.5 - 0.5 * (x * x + y * y)
    return x * factor, y * factor


_ALL_SLOTS = tuple(range(NUM_SLOTS))


def _solve(A, B, C, careful=False, slots=_ALL_SLOTS):
    """Primal solve of the slots `slots` (a tuple of slot indices: all four, the outer
    pair (0, 1) or the inner pair (2, 3); the careful path solves all four).  Returns phi,
    cos phi, sin phi, valid (each ... x len(slots)), continuum, tangent (bool per slot: the
    slot is a double root), converged (per point: the slots asked for, and whether the
    inner pair exists) and complete (per point: no register outside the slots asked for;
    with the outer slots only, False where an inner pair exists or may exist)."""
    dtype = jnp.result_type(A, B, C, float)
    A, B, C = (jnp.asarray(x, dtype) for x in (A, B, C))
    A, B, C = jnp.broadcast_arrays(A, B, C)
    finite = jnp.isfinite(A) & jnp.isfinite(B) & jnp.isfinite(C)
    A, B, C = (jnp.where(finite, x, 0.5) for x in (A, B, C))
    scale = jnp.maximum(jnp.maximum(jnp.abs(A), jnp.abs(B)), jnp.abs(C))
    continuum = scale == 0
    inv_scale = 1 / jnp.where(continuum, 1.0, scale)
    a, b, c = A * inv_scale, B * inv_scale, C * inv_scale

    # Work with a >= 0: f(phi + pi/2) has coefficients (-a, -c, b).
    turn = a < 0
    a, b, c = jnp.abs(a), jnp.where(turn, -c, b), jnp.where(turn, b, c)

    # Exact (or negligible) zeros of b or c put roots exactly on the axes, where a secular
    # pole meets its root; those cases have closed forms, and the iteration below solves a
    # harmless stand-in for them.
    factorable = (jnp.abs(b) <= TINY) | (jnp.abs(c) <= TINY)
    sign_b = jnp.where(b < 0, -1.0, 1.0)
    sign_c = jnp.where(c < 0, -1.0, 1.0)
    b_it = jnp.where(factorable, 1.0, b)
    c_it = jnp.where(factorable, 1.0, c)
    b2, c2, a2 = b_it * b_it, c_it * c_it, a * a

    # The inner pair exists iff (b, c) is inside the astroid.  At the separator the
    # secular function is (|b|^(2/3) + |c|^(2/3))^3 / 4a^2: below 1 a pair, 1 a tangent
    # register.  The fast path reads the sign of the same test in polynomial form and
    # leaves points near its zero set (and near the cusps, where it flattens) undecided.
    if careful:
        cb, cc = jnp.cbrt(b_it), jnp.cbrt(c_it)
        s = cb * cb + cc * cc
        gap = 4 * a2 - s * s * s
        near = jnp.abs(gap) <= TANGENT_TOL * 4 * a2
        pair = (gap > 0) & ~near
        tangent_point = near & (a > 0)
        decided = jnp.ones_like(pair)
    else:
        astroid = (b2 + c2 - 4 * a2) ** 3 + 108 * a2 * b2 * c2
        pair = astroid < -TANGENT_TOL
        decided = jnp.abs(astroid) > TANGENT_TOL
        tangent_point = jnp.zeros_like(pair)

    # Per slot: Q (the pole of the root), P, the branch e, and how (x, y) are read from
    # (Q/nu, P/d); see the module docstring.
    inner_sign = jnp.where(pair, -1.0, 1.0)
    abs_b, abs_c = jnp.abs(b_it), jnp.abs(c_it)
    aa = 2 * a
    # Starts left of every root.  Outer branches: |Q|, and sqrt(b^2 + c^2) - 2a (here with
    # a lower bound of the square root).  Inner: at the root P^2/(2a - nu)^2 exceeds its
    # value at nu = |Q|, so Q^2/nu^2 is below 1 - P^2/(2a - |Q|)^2.
    r_low = jnp.maximum(abs_b, abs_c) + 0.41421356 * jnp.minimum(abs_b, abs_c)
    Qs, Ps, Q2s, P2s, es, starts, needed = [], [], [], [], [], [], []
    for slot in slots:
        Q, P, Q2, P2, absQ = (b_it, c_it, b2, c2, abs_b) if _Q_IS_B[slot] else (c_it, b_it, c2, b2, abs_c)
        if _INNER[slot]:
            e = inner_sign
            inner_room = 1 - P * P / jnp.square(jnp.where(pair, aa - absQ, 1.0))
            start = jnp.where(pair, absQ / jnp.sqrt(jnp.maximum(inner_room, 1e-300)), jnp.maximum(absQ, r_low - aa))
            needed.append(pair)
        else:
            e = 1.0
            start = jnp.maximum(absQ, r_low - aa)
            needed.append(jnp.ones_like(pair))
        for values, value in ((Qs, Q), (Ps, P), (Q2s, Q2), (P2s, P2), (es, e), (starts, start)):
            values.append(value)
    nus, done = _secular_solve(tuple(starts), aa, tuple(Q2s), tuple(P2s), tuple(es), tuple(needed), careful)
    all_done = functools.reduce(jnp.logical_and, (d | ~n for d, n in zip(done, needed)))
    converged = (all_done & decided) | factorable | continuum

    # The register from nu: (x, y) from Q/nu and P/d, one division for both.
    xs, ys = [], []
    for slot, nu, Q, P, e in zip(slots, nus, Qs, Ps, es):
        d = aa + e * nu
        inv = 1 / (nu * d)
        U = _SIGN_U[slot] * Q * d * inv
        V = -P * nu * inv
        x, y = _unit(V, U) if _SWAP[slot] else _unit(U, V)
        xs.append(x), ys.append(y)
    x, y = jnp.stack(xs, axis=-1), jnp.stack(ys, axis=-1)
    tangent = _slot(tuple(slot == 2 for slot in slots), a.ndim) & tangent_point[..., None]
    if careful:
        # A tangent register (slot 2) is the separator, direction -(cbrt b, cbrt c).
        tx, ty = -cb[..., None], -cc[..., None]
        tnorm = jax.lax.rsqrt(tx * tx + ty * ty)
        x = jnp.where(tangent, tx * tnorm, x)
        y = jnp.where(tangent, ty * tnorm, y)
        # One Newton step on f(phi) itself, as a rotation by -f/f': full accuracy where
        # Newton on nu stopped short of round-off (a root close to a tangency).
        a_, b_, c_ = a[..., None], b_it[..., None], c_it[..., None]
        f = 2 * a_ * x * y + b_ * y + c_ * x
        fp = 2 * a_ * (x * x - y * y) + b_ * x - c_ * y
        rotation = -f / jnp.where(fp == 0, 1.0, fp)
        rotation = jnp.where((jnp.abs(rotation) <= POLISH_LIMIT) & ~tangent, rotation, 0.0)
        x, y = _unit(x - rotation * y, y + rotation * x)
    always = jnp.ones_like(pair)
    per_slot_valid = (always, always, pair | tangent_point, pair)
    valid = jnp.stack([per_slot_valid[slot] for slot in slots], axis=-1)

    f_cos, f_sin, f_valid = _factorable(a, b, c, sign_b, sign_c)
    complete = jnp.where(factorable, ~f_valid[..., 2], ~pair & decided) if 2 not in slots else always
    f_cos, f_sin, f_valid = (x[..., slots] for x in (f_cos, f_sin, f_valid))
    pick = factorable[..., None]
    cos_phi = jnp.where(pick, f_cos, x)
    sin_phi = jnp.where(pick, f_sin, y)
    valid = jnp.where(pick, f_valid, valid)
    tangent = tangent & ~pick

    # Undo the quarter turn taken to make a >= 0: phi = phi' + pi/2.
    turn = turn[..., None]
    cos_phi, sin_phi = jnp.where(turn, -sin_phi, cos_phi), jnp.where(turn, cos_phi, sin_phi)
    # The continuum keeps one representative register, phi = 0, in slot 0.
    only_first = jnp.asarray([slot == 0 for slot in slots])
    cont = continuum[..., None]
    valid = jnp.where(cont, only_first, valid)
    tangent = tangent & ~cont
    cos_phi = jnp.where(cont, 1.0, cos_phi)
    sin_phi = jnp.where(cont, 0.0, sin_phi)
    # Non-finite coefficients: no register (the finite stand-in solved above is masked, and
    # stays finite so that gradients through masked slots stay finite too).
    valid = valid & finite[..., None]
    converged = converged | ~finite
    complete = complete | continuum | ~finite
    return _angle(cos_phi, sin_phi), cos_phi, sin_phi, valid, continuum & finite, tangent & valid, converged, complete


def _solve_all(A, B, C):
    """Every register of a batch: `(phi, cos_phi, sin_phi, valid, continuum, tangent)`, by
    the compiled CPU kernel where there is one (`cpu_kernel`), else by `_solve_in_xla`."""
    A, B, C = jnp.broadcast_arrays(*(jnp.asarray(x, jnp.result_type(A, B, C, float)) for x in (A, B, C)))
    shape = A.shape
    n = A.size
    A, B, C = A.reshape(n), B.reshape(n), C.reshape(n)
    on_cpu = jax.default_backend() == "cpu"
    kernel = cpu_kernel() if on_cpu and n > 0 and A.dtype == jnp.float64 else None
    if kernel is not None:
        cos_phi, sin_phi, valid, continuum, tangent = kernel.solve(A, B, C)
        out = (_angle(cos_phi, sin_phi), cos_phi, sin_phi, valid, continuum, tangent)
    else:
        out = _solve_in_xla(A, B, C)
    return tuple(x.reshape(shape + x.shape[1:]) for x in out)


def _solve_in_xla(A, B, C):
    """`_solve_all` of flat arrays (n,) by XLA's program, in up to three stages, each on
    the points the one before left (gathered a batch at a time, so that their cost follows
    their number):

    1. on a CPU, the fast path of the two outer registers of every point (helix_equilibria
       hands it cache-sized chunks): about 95 % of the points of a typical rod have no
       inner pair, and solving four slots everywhere would double the work;
    2. the fast path of the inner pair on the points that have (or may have) one,
       `_INNER_BATCH` at a time; on an accelerator, of all four slots on every point in
       one pass;
    3. the careful path on the points left unconverged, `_FALLBACK_BATCH` at a time."""
    n = A.shape[0]
    on_cpu = jax.default_backend() == "cpu"
    if n > 0 and on_cpu:
        *outer, converged, complete = _solve(A, B, C, slots=(0, 1))
        out = tuple(_pad_slots(x) for x in outer[:4]) + (outer[4], _pad_slots(outer[5]), converged)
        out = _resolve_where(~complete, out, _inner_stage, A, B, C, min(n, _INNER_BATCH))
    else:
        out = _solve(A, B, C)[:-1]
    if n > 0:
        batch = min(n, _FALLBACK_BATCH if on_cpu else _ACCELERATOR_FALLBACK_BATCH)
        *out, converged = out
        out = _resolve_where(~converged, tuple(out), _careful_stage, A, B, C, batch)
    else:
        out = out[:-1]
    return out


#: Environment variable: ``0`` keeps the register solve in XLA on a CPU (no numba kernel).
KERNEL_ENVIRONMENT_VARIABLE = "HELIXROD_REGISTER_KERNEL"


@functools.cache
def cpu_kernel():
    """The module of the compiled CPU register kernel (`_register_kernel`), or None where
    numba is not installed, the kernel fails its check (with a warning), or
    `KERNEL_ENVIRONMENT_VARIABLE` is ``0``.  Decided once, at the first float64 register
    solve on a CPU."""
    if os.environ.get(KERNEL_ENVIRONMENT_VARIABLE, "1").strip() == "0":
        return None
    if importlib.util.find_spec("numba") is None:
        return None
    try:
        from . import _register_kernel

        _register_kernel.check()
    except Exception as error:  # a numba that does not work with this numpy or CPU
        warnings.warn(f"helixrod: the compiled register kernel is unavailable ({error!r}); "
                      "registers are solved by XLA", RuntimeWarning, stacklevel=2)
        return None
    return _register_kernel


def _inner_stage(A, B, C, old):
    """The outer slots of `old` (phi, cos, sin, valid, continuum, tangent, converged) with
    the inner pair solved by the fast path."""
    phi, cos_phi, sin_phi, valid, _, tangent, converged, _ = _solve(A, B, C, slots=(2, 3))
    with_outer = lambda previous, inner: jnp.concatenate([previous[..., :2], inner], axis=-1)  # noqa: E731
    o_phi, o_cos, o_sin, o_valid, o_continuum, o_tangent, o_converged = old
    return (with_outer(o_phi, phi), with_outer(o_cos, cos_phi), with_outer(o_sin, sin_phi), with_outer(o_valid, valid),
            o_continuum, with_outer(o_tangent, tangent), o_converged & converged)


def _careful_stage(A, B, C, old):
    """Every slot by the careful path (`old` is not needed)."""
    return _solve(A, B, C, careful=True)[:-2]


def _pad_slots(x):
    """Per-slot values of the outer slots, padded to all four with unused slots (zeros,
    flags False)."""
    fill = jnp.zeros(x.shape[:-1] + (NUM_SLOTS - x.shape[-1],), x.dtype)
    return jnp.concatenate([x, fill], axis=-1)


def _resolve_where(mask, values, solver, A, B, C, batch):
    """`values` (a tuple of per-point arrays, leading axis n) with the points of `mask`
    replaced by `solver(A, B, C, values)` of those points, gathered `batch` at a time in
    a while loop (as many rounds as there are masked points)."""
    n = A.shape[0]
    count = jnp.sum(mask)
    (order,) = jnp.nonzero(mask, size=n, fill_value=0)

    def unfinished(carry):
        return carry[0] * batch < count

    def resolve(carry):
        k, values = carry
        idx = jax.lax.dynamic_slice(order, (k * batch,), (batch,))
        old = tuple(v[idx] for v in values)
        redo = solver(A[idx], B[idx], C[idx], old)
        # Slots past the last masked point hold index 0, or (at the end of `order`) repeat
        # masked points: either way they rewrite a value with itself.
        keep = mask[idx]
        values = tuple(v.at[idx].set(jnp.where(_expand(keep, r), r, o)) for v, r, o in zip(values, redo, old))
        return k + 1, values

    return jax.lax.while_loop(unfinished, resolve, (0, values))[1]


def _expand(mask, like):
    return mask.reshape(mask.shape + (1,) * (like.ndim - mask.ndim))


# tan(pi/8), and arctan(t) = t + t z P(z), z = t^2, on |t| <= tan(pi/8): P of degree 10
# interpolated at Chebyshev nodes of z in 50-digit arithmetic (mpmath); the float64
# evaluation is within 3.2e-17 of arctan there (checked against mpmath, tests/test_roots.py).
TAN_PI_8 = 0.41421356237309503
ATAN_COEFFICIENTS = (
    -0.3333333333333333,
    0.1999999999999552,
    -0.14285714284666542,
    0.11111111015256361,
    -0.09090904578123903,
    0.07692183190826087,
    -0.06664511447381948,
    0.0585814891280221,
    -0.0508544973794026,
    0.03923165829558719,
    -0.01917688711906226,
)


def _angle(cos_phi, sin_phi):
    """phi in [0, 2 pi) from its cosine and sine: one division and a polynomial.

    The angle alpha in [0, pi/2] of (|cos|, |sin|) is j pi/4 plus the arctangent of
    $t = \\tan(\\alpha - j\\pi/4)$, $|t| \\le \\tan(\\pi/8)$, with j the nearest multiple
    (the rotated pair has the same ratio without its $\\sqrt2$).  Arithmetic only: in place
    of XLA's `arctan` it made `helix_equilibria` (phi, force, moment, stable) ~20% faster
    on 2 CPU cores and ~2x on an H100 (measured, `benchmarks/`)."""
    ax, ay = jnp.abs(cos_phi), jnp.abs(sin_phi)
    low = ay <= TAN_PI_8 * ax
    high = ax <= TAN_PI_8 * ay
    num = jnp.where(low, ay, jnp.where(high, -ax, ay - ax))
    den = jnp.where(low, ax, jnp.where(high, ay, ay + ax))
    t = num / jnp.where(den > 0, den, 1.0)
    z = t * t
    poly = ATAN_COEFFICIENTS[-1]
    for coefficient in ATAN_COEFFICIENTS[-2::-1]:
        poly = poly * z + coefficient
    alpha = jnp.where(low, 0.0, jnp.where(high, 0.5 * jnp.pi, 0.25 * jnp.pi)) + (t + t * z * poly)
    upper = sin_phi >= 0
    phi = jnp.where(
        cos_phi >= 0,
        jnp.where(upper, alpha, 2 * jnp.pi - alpha),
        jnp.where(upper, jnp.pi - alpha, jnp.pi + alpha),
    )
    return jnp.where(phi >= 2 * jnp.pi, phi - 2 * jnp.pi, phi)


def _factorable(a, b, c, sign_b, sign_c):
    """Closed-form registers when b = 0 or c = 0 (a >= 0), in slot order; `sign_b`,
    `sign_c` (+-1) choose among tied registers the way of the limit from that side.

    c = 0: $f = \\sin\\varphi\\,(2a\\cos\\varphi + b)$: roots 0 and pi (energies
    $G = -a/2 \\mp b$) and, if $|b| < 2a$, the pair $\\cos\\varphi = -b/2a$, which are the
    (equal) maxima of $G = -\\tfrac a2 \\cos 2\\varphi - b\\cos\\varphi + c\\sin\\varphi$; a small
    $c$ makes the one with $\\operatorname{sgn}\\sin\\varphi = \\operatorname{sgn} c$ the global one.
    b = 0: $f = \\cos\\varphi\\,(2a\\sin\\varphi + c)$: roots pi/2 and 3pi/2 and, if
    $|c| < 2a$, the pair $\\sin\\varphi = -c/2a$, the (equal) minima; a small $b$ makes the one
    with $\\operatorname{sgn}\\cos\\varphi = \\operatorname{sgn} b$ the global one.
    """
    c_zero = (jnp.abs(c) <= jnp.abs(b))[..., None]
    safe_a = jnp.where(a > 0, a, 1.0)
    q = (jnp.where(c_zero[..., 0], -b, -c) / (2 * safe_a))[..., None]
    pair = (a[..., None] > 0) & (jnp.abs(q) < 1)
    r = jnp.sqrt(jnp.maximum(1 - q * q, 0.0))
    sign_b, sign_c = sign_b[..., None], sign_c[..., None]
    rb, rc = sign_b * r, sign_c * r
    # Slot by slot with selects (elementwise, so XLA fuses them; stacking per-point arrays
    # would materialise four more arrays).
    slot = jnp.reshape(jnp.arange(NUM_SLOTS), (1,) * a.ndim + (NUM_SLOTS,))

    def by_slot(s0, s1, s2, s3):
        return jnp.where(slot == 0, s0, jnp.where(slot == 1, s1, jnp.where(slot == 2, s2, s3)))

    # c = 0: axis roots (+-1, 0), the lower-energy one phi = 0 when b >= 0, and the pair.
    # b = 0: axis roots (0, +-1), the higher-energy one phi = pi/2 when c >= 0, and the pair.
    cos_phi = jnp.where(
        c_zero,
        by_slot(sign_b, jnp.where(pair, q, -sign_b), -sign_b, q),
        by_slot(jnp.where(pair, rb, 0.0), 0.0, -rb, 0.0),
    )
    sin_phi = jnp.where(
        c_zero,
        by_slot(0.0, jnp.where(pair, rc, 0.0), 0.0, -rc),
        by_slot(jnp.where(pair, q, -sign_c), sign_c, q, -sign_c),
    )
    valid = (slot < 2) | pair
    return cos_phi, sin_phi, valid


@jax.custom_jvp
def _registers(A, B, C):
    return _solve_all(A, B, C)


@_registers.defjvp
def _registers_jvp(primals, tangents):
    A, B, C = primals
    dA, dB, dC = tangents
    # Through `_registers` itself, so that a derivative of this rule (a second derivative)
    # takes the implicit-function rule again: the compiled CPU kernel has no derivative.
    out = _registers(A, B, C)
    phi, cos_phi, sin_phi, valid, continuum, tangent = out
    A, B, C, dA, dB, dC = (jnp.asarray(x, phi.dtype)[..., None] for x in (A, B, C, dA, dB, dC))
    sin2 = 2 * sin_phi * cos_phi
    cos2 = cos_phi * cos_phi - sin_phi * sin_phi
    # Simple root of f: implicit function theorem, dphi = -(df/dtheta) / f'(phi).
    df = sin2 * dA + sin_phi * dB + cos_phi * dC
    fp = 2 * A * cos2 + B * cos_phi - C * sin_phi
    # Tangent register (root of f'): dphi = -(df'/dtheta) / f''(phi).
    dfp = 2 * cos2 * dA + cos_phi * dB - sin_phi * dC
    fpp = -4 * A * sin2 - B * sin_phi - C * cos_phi
    num = jnp.where(tangent, dfp, df)
    den = jnp.where(tangent, fpp, fp)
    moving = valid & ~continuum[..., None] & (den != 0)
    dphi = jnp.where(moving, -num / jnp.where(moving, den, 1.0), 0.0)
    zero_bool = jax.tree_util.tree_map(
        lambda x: jnp.zeros(x.shape, jax.dtypes.float0), (valid, continuum, tangent)
    )
    return out, (dphi, -sin_phi * dphi, cos_phi * dphi) + zero_bool


@jit(inline=True)
def register_roots(A, B, C):
    """All roots of $A \\sin 2\\varphi + B \\sin\\varphi + C\\cos\\varphi = 0$ on $[0, 2\\pi)$.

    Returns `(phi, cos_phi, sin_phi, valid, continuum, tangent)`; per-slot arrays have a
    trailing axis of 4: slot 0 is the global minimum of the energy on the circle
    ($W = \\kappa\\int f$), slot 1 the global maximum, slots 2 and 3 the local minimum and
    local maximum of the inner pair when it exists (`valid` marks the slots in use).  `continuum` marks $A = B = C = 0$ (every
    $\\varphi$ is a root; slot 0 holds $\\varphi = 0$).  `tangent` marks a double root,
    reported once, in slot 2.  Differentiable: $d\\varphi$ by the implicit function theorem.
    """
    return _registers(A, B, C)
