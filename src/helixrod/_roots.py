"""Every root of the register equation $A \\sin 2\\varphi + B \\sin\\varphi + C \\cos\\varphi = 0$.

The register condition of a uniform helix (DESIGN.md) is $h = \\kappa f(\\varphi)$ with

$$f(\\varphi) = A \\sin 2\\varphi + B \\sin\\varphi + C\\cos\\varphi = \\frac{1}{\\kappa}
\\frac{dW}{d\\varphi},$$

so the registers are the critical points of the energy on the constraint circle.  On the
unit circle $v = (\\cos\\varphi, \\sin\\varphi)$ the energy is, up to a constant, the quadratic
$G(v) = -\\tfrac{A}{2}(x^2 - y^2) - Bx + Cy$, and its critical points solve
$(H - \\lambda I) v = -g$ with $H = \\mathrm{diag}(-A, A)$, $g = (-B, C)$ -- the boundary
problem of a trust-region step.  For $A \\ge 0$ (else turn the circle by $\\pi/2$) the
secular function $B^2/(\\lambda+A)^2 + C^2/(\\lambda-A)^2 = 1$ gives, with no search:

* exactly one root with $\\lambda < -A$: the global minimum of $W$ on the circle, in the
  quadrant $(\\operatorname{sgn} B, -\\operatorname{sgn} C)$;
* exactly one root with $\\lambda > A$: the global maximum, in quadrant
  $(-\\operatorname{sgn} B, \\operatorname{sgn} C)$;
* two more (one local minimum, one local maximum) in quadrant
  $(-\\operatorname{sgn} B, -\\operatorname{sgn} C)$ iff $(B, C)$ lies inside the astroid
  $|B|^{2/3} + |C|^{2/3} < (2A)^{2/3}$, separated by the direction
  $(-\\operatorname{sgn} B\\,|B|^{1/3}, -\\operatorname{sgn} C\\,|C|^{1/3})$ -- the
  tangent (double) register on the astroid itself.

So every register sits alone in a known bracket.  In each quadrant the substitution
$t = \\tan(\\psi/2) \\in [0, 1]$ turns $f$ into the quartic
$P(t) = -C_k t^4 + (2B_k - 4A_k) t^3 + (4A_k + 2B_k) t + C_k$, solved by bracketed
Newton iteration a fixed number of times: elementwise arithmetic only (no eigenvalues,
no data-dependent loops), run a cache-sized chunk of points at a time, unchanged on a
GPU.  Exact zeros of $B$ or $C$ (the common uncoupled rods) are read as a tiny positive
number, the limit from above, so every root still has its own bracket.

Registers closer than about $\\sqrt{\\epsilon}$ (relative to the coefficients) to a tangency
cannot be told apart in floating point; where the astroid test is within `_TANGENT_TOL`
of zero one *tangent* register (the extremum of $f$) is returned instead of the pair.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from ._chunks import map_chunks

# Slots: 0 global minimum of W on the circle, 1 global maximum, 2 the local minimum and
# 3 the local maximum of the inner pair (a tangent register, when there is one, in 2).
NUM_SLOTS = 4

# Iteration budget per bracket.  The fast path localises by bisection
# and polishes by Newton; measured on random coefficients with ratios up to 1e7 it
# reaches full precision everywhere (tests/test_roots.py).  Brackets it leaves
# unconverged (near-cusp and near-tangent coefficients) are gathered and re-solved by
# the robust path: bisection to the last bit, then Newton.
_FAST_BISECTIONS = 6
_FAST_NEWTON = 5
_ROBUST_BISECTIONS = 64
_ROBUST_NEWTON = 2
# A bracket counts as converged when the last Newton step moved t by less than this.
_STEP_TOL = 1e-10
# Astroid test |D| below this (coefficients scaled to max 1) -> tangent pair.
_TANGENT_TOL = 64 * 2.220446049250313e-16


def _rotate_coeffs(a, b, c, k):
    """Coefficients of $f(k\\pi/2 + \\psi)$: each quarter turn maps (A,B,C) -> (-A,-C,B)."""
    k = k % 4
    A = jnp.where(k % 2 == 0, a, -a)
    B = jnp.select([k == 0, k == 1, k == 2], [b, -c, -b], c)
    C = jnp.select([k == 0, k == 1, k == 2], [c, b, -c], -b)
    return A, B, C


def _rotate_vector(x, y, k):
    """Turn (x, y) by -k quarter turns (into the frame of quadrant k)."""
    k = k % 4
    X = jnp.select([k == 0, k == 1, k == 2], [x, y, -x], -y)
    Y = jnp.select([k == 0, k == 1, k == 2], [y, -x, -y], x)
    return X, Y


def _quadrant(sx, sy):
    """Index k of the quadrant [k pi/2, (k+1) pi/2] with cos, sin of signs (sx, sy)."""
    return jnp.where(sy > 0, jnp.where(sx > 0, 0, 1), jnp.where(sx > 0, 3, 2))


def _poly(t, A, B, C):
    c3 = 2 * B - 4 * A
    c1 = 4 * A + 2 * B
    p = ((-C * t + c3) * t * t + c1) * t + C
    dp = (-4 * C * t + 3 * c3) * t * t + c1
    d2p = (-12 * C * t + 6 * c3) * t
    return p, dp, d2p


def _bracketed_newton(A, B, C, lo, hi, p_lo, p_hi, t, robust):
    """Root of P in [lo, hi], where P(lo) = p_lo and P(hi) = p_hi have opposite signs.

    Bisection first, then Newton; a Newton step that would leave the bracket is replaced
    by an Illinois false-position step (Newton overshoots a root next to a bracket end
    where P is concave; the chord does not, and halving the value kept at a stale end
    stops the chord from creeping), and that by bisection if it degenerates.
    Returns the root and whether the last step was below `_STEP_TOL`.
    """
    sign_lo = jnp.sign(p_lo)

    def bisect(_, state):
        lo, hi, p_lo, p_hi = state
        mid = 0.5 * (lo + hi)
        p_mid = _poly(mid, A, B, C)[0]
        below = jnp.sign(p_mid) == sign_lo
        return (
            jnp.where(below, mid, lo),
            jnp.where(below, hi, mid),
            jnp.where(below, p_mid, p_lo),
            jnp.where(below, p_hi, p_mid),
        )

    state = (lo, hi, p_lo, p_hi)
    state = jax.lax.fori_loop(0, _ROBUST_BISECTIONS if robust else _FAST_BISECTIONS, bisect, state)
    lo, hi, p_lo, p_hi = state
    t = jnp.clip(t, lo, hi)
    last_below = jnp.zeros(jnp.shape(t), dtype=bool)
    last_above = jnp.zeros(jnp.shape(t), dtype=bool)
    step = jnp.full(jnp.shape(t), jnp.inf, dtype=t.dtype)

    def newton(_, state):
        t, lo, hi, p_lo, p_hi, last_below, last_above, step = state
        p, dp, _ = _poly(t, A, B, C)
        below = jnp.sign(p) == sign_lo
        lo, p_lo = jnp.where(below, t, lo), jnp.where(below, p, p_lo)
        hi, p_hi = jnp.where(below, hi, t), jnp.where(below, p_hi, p)
        p_hi = jnp.where(below & last_below, 0.5 * p_hi, p_hi)
        p_lo = jnp.where(~below & last_above, 0.5 * p_lo, p_lo)
        last_below, last_above = below, ~below
        t_newton = t - p / jnp.where(dp == 0, 1.0, dp)
        newton_ok = (dp != 0) & (t_newton >= lo) & (t_newton <= hi)
        chord = p_hi - p_lo
        t_chord = lo - p_lo * (hi - lo) / jnp.where(chord == 0, 1.0, chord)
        chord_ok = (chord != 0) & (t_chord >= lo) & (t_chord <= hi)
        t_safe = jnp.where(chord_ok, t_chord, 0.5 * (lo + hi))
        t_next = jnp.where(p == 0, t, jnp.where(newton_ok, t_newton, t_safe))
        step = jnp.where(p == 0, 0.0, jnp.abs(t_next - t))
        return t_next, lo, hi, p_lo, p_hi, last_below, last_above, step

    state = (t, lo, hi, p_lo, p_hi, last_below, last_above, step)
    state = jax.lax.fori_loop(0, _ROBUST_NEWTON if robust else _FAST_NEWTON, newton, state)
    t, lo, hi, p_lo, p_hi, last_below, last_above, step = state
    converged = (step <= _STEP_TOL) | (hi - lo <= _STEP_TOL)
    return t, converged


def _extremum(A, B, C, t, steps=4):
    """Newton on P'(t) = 0 from t (used for a tangent register, a simple root of P')."""
    for _ in range(steps):
        _, dp, d2p = _poly(t, A, B, C)
        t = t - dp / jnp.where(d2p == 0, 1.0, d2p)
    return jnp.clip(t, 0.0, 1.0)


def _solve(A, B, C, robust=False):
    """Primal solve.  Returns phi, cos phi, sin phi, valid (each ... x 4), continuum,
    tangent (bool per slot: slot is a double root)."""
    dtype = jnp.result_type(A, B, C, float)
    A, B, C = (jnp.asarray(x, dtype) for x in (A, B, C))
    A, B, C = jnp.broadcast_arrays(A, B, C)
    scale = jnp.maximum(jnp.maximum(jnp.abs(A), jnp.abs(B)), jnp.abs(C))
    continuum = scale == 0
    scale = jnp.where(continuum, 1.0, scale)
    a, b, c = A / scale, B / scale, C / scale

    # Work with a >= 0: f(phi + pi/2) has coefficients (-a, -c, b).
    turn = a < 0
    a, b, c = jnp.where(turn, -a, a), jnp.where(turn, -c, b), jnp.where(turn, b, c)

    # An exact zero of B or C (uncoupled rods) puts roots exactly on quadrant edges, where
    # brackets meet; those cases have closed forms (`_factorable`).  The bracket path
    # below sees them as +0 so that it stays finite, and its result is replaced.
    factorable = (b == 0) | (c == 0)
    sb, sc = jnp.where(b >= 0, 1.0, -1.0), jnp.where(c >= 0, 1.0, -1.0)
    # Inside the astroid |b|^(2/3) + |c|^(2/3) < (2a)^(2/3), in polynomial form.
    b2, c2, a2 = b * b, c * c, a * a
    astroid = (b2 + c2 - 4 * a2) ** 3 + 108 * a2 * b2 * c2
    near_astroid = jnp.abs(astroid) <= _TANGENT_TOL

    k_min = _quadrant(sb, -sc)
    k_max = _quadrant(-sb, sc)
    k_in = _quadrant(-sb, -sc)

    # Separator of the inner quadrant (the tangent point on the astroid) and the sign
    # of f there; every slot's bracket is then known.
    Ai, Bi, Ci = _rotate_coeffs(a, b, c, k_in)
    ratio = jnp.cbrt(jnp.abs(c) / jnp.where(b == 0, 1.0, jnp.abs(b)))
    X, Y = _rotate_vector(-sb, -sc * ratio, k_in)
    t_star = Y / (jnp.sqrt(X * X + Y * Y) + X)
    p_star, _, d2p_star = _poly(t_star, Ai, Bi, Ci)
    s_edge = jnp.sign(Ci)
    # On the astroid itself (and near its cusps, where the polynomial test flattens out)
    # the sign of f at the separator decides: opposite to the edges -> a resolved pair.
    resolved = (p_star != 0) & (jnp.sign(p_star) == -s_edge)
    inner_pair = (astroid < -_TANGENT_TOL) | (near_astroid & resolved)
    inner_tangent = near_astroid & ~resolved
    # Near a tangency the pair straddles t_star at +-sqrt(-2 P / P''): start there.
    half_gap = jnp.sqrt(jnp.maximum(-2 * p_star / jnp.where(d2p_star == 0, 1.0, d2p_star), 0.0))

    # All four brackets as one batch (trailing axis 4: the global minimum, the global
    # maximum, the left and the right root of the inner pair), so that the iteration is
    # written once.  P(0) = C_k and P(1) = 4 B_k; the outer brackets start from their chord.
    k = jnp.stack([k_min, k_max, k_in, k_in], axis=-1)
    Ak, Bk, Ck = _rotate_coeffs(a[..., None], b[..., None], c[..., None], k)
    zeros = jnp.zeros_like(Ak)
    ones = jnp.ones_like(Ak)
    ts = t_star[..., None]
    ps = p_star[..., None]
    left = jnp.array([True, True, True, False])
    right = jnp.array([True, True, False, True])
    lo = jnp.where(left, 0.0, ts) + zeros
    hi = jnp.where(right, 1.0, ts) + zeros
    p_lo = jnp.where(left, Ck, ps)
    p_hi = jnp.where(right, 4 * Bk, ps)
    hg = half_gap[..., None]
    t_chord = Ck / (Ck - 4 * Bk)
    t0 = jnp.where(
        jnp.arange(4) < 2, t_chord, jnp.where(left, jnp.clip(ts - hg, 0.0, ts), jnp.clip(ts + hg, ts, 1.0))
    )
    t, ok = _bracketed_newton(Ak, Bk, Ck, lo, hi, p_lo, p_hi, t0, robust)
    t_lo, t_hi = t[..., 2], t[..., 3]
    # f runs from s_edge through -s_edge back to s_edge, so f' < 0 at t_lo iff s_edge > 0:
    # the stable (local minimum, f' > 0) root of the pair goes to slot 2.
    t_stable = jnp.where(s_edge < 0, t_lo, t_hi)
    t_unstable = jnp.where(s_edge < 0, t_hi, t_lo)
    t_stable = jnp.where(inner_tangent, _extremum(Ai, Bi, Ci, t_star), t_stable)
    t = jnp.stack([t[..., 0], t[..., 1], t_stable, t_unstable], axis=-1)
    inner_ok = (ok[..., 2] & ok[..., 3]) | ~inner_pair
    converged = (ok[..., 0] & ok[..., 1] & inner_ok) | factorable | continuum
    ones = jnp.ones_like(a)
    valid = jnp.stack([ones > 0, ones > 0, inner_pair | inner_tangent, inner_pair], axis=-1)
    tangent = jnp.zeros_like(valid).at[..., 2].set(inner_tangent)

    t2 = t * t
    cos_psi = (1 - t2) / (1 + t2)
    sin_psi = 2 * t / (1 + t2)
    k = k % 4
    cos_phi = jnp.select([k == 0, k == 1, k == 2], [cos_psi, -sin_psi, -cos_psi], sin_psi)
    sin_phi = jnp.select([k == 0, k == 1, k == 2], [sin_psi, cos_psi, -sin_psi], -cos_psi)

    f_cos, f_sin, f_valid, f_tangent = _factorable(a, b, c)
    pick = factorable[..., None]
    cos_phi = jnp.where(pick, f_cos, cos_phi)
    sin_phi = jnp.where(pick, f_sin, sin_phi)
    valid = jnp.where(pick, f_valid, valid)
    tangent = jnp.where(pick, f_tangent, tangent)

    # Undo the quarter turn taken to make a >= 0: phi = phi' + pi/2.
    turn = turn[..., None]
    cos_phi, sin_phi = jnp.where(turn, -sin_phi, cos_phi), jnp.where(turn, cos_phi, sin_phi)
    # The continuum keeps one representative register, phi = 0, in slot 0.
    only_first = jnp.arange(NUM_SLOTS) == 0
    cont = continuum[..., None]
    valid = jnp.where(cont, only_first, valid)
    tangent = tangent & ~cont
    cos_phi = jnp.where(cont, 1.0, cos_phi)
    sin_phi = jnp.where(cont, 0.0, sin_phi)
    return _angle(cos_phi, sin_phi), cos_phi, sin_phi, valid, continuum, tangent, converged


def _solve_all(A, B, C):
    """Fast path everywhere; the few points it leaves unconverged are gathered (to a
    static budget, `size // 64 + 16`) and re-solved by the robust path, or, when there
    are more of them, the robust path runs on the whole batch."""
    A, B, C = jnp.broadcast_arrays(*(jnp.asarray(x, jnp.result_type(A, B, C, float)) for x in (A, B, C)))
    shape = A.shape
    n = A.size
    A, B, C = A.reshape(n), B.reshape(n), C.reshape(n)
    *fast, converged = map_chunks(_solve, (A, B, C), n)
    budget = n // 64 + 16
    if n <= budget:
        robust = _solve(A, B, C, robust=True)[:-1]
        out = tuple(jnp.where(_expand(converged, f), f, r) for f, r in zip(fast, robust))
        return tuple(x.reshape(shape + x.shape[1:]) for x in out)
    bad = ~converged
    n_bad = jnp.sum(bad)

    def gathered():
        (idx,) = jnp.nonzero(bad, size=budget, fill_value=0)
        redo = _solve(A[idx], B[idx], C[idx], robust=True)[:-1]
        # Unused budget slots point at index 0 with its fast result, so they rewrite it
        # unchanged unless index 0 itself was bad (then it is in idx too, same value).
        keep = bad[idx]
        return tuple(
            f.at[idx].set(jnp.where(_expand(keep, r), r, f[idx])) for f, r in zip(fast, redo)
        )

    def everywhere():
        robust = map_chunks(functools.partial(_solve, robust=True), (A, B, C), n)[:-1]
        return tuple(jnp.where(_expand(bad, f), r, f) for f, r in zip(fast, robust))

    out = jax.lax.cond(
        n_bad == 0,
        lambda: tuple(fast),
        lambda: jax.lax.cond(n_bad <= budget, gathered, everywhere),
    )
    return tuple(x.reshape(shape + x.shape[1:]) for x in out)


def _expand(mask, like):
    return mask.reshape(mask.shape + (1,) * (like.ndim - mask.ndim))


def _angle(cos_phi, sin_phi):
    """phi in [0, 2 pi) from its cosine and sine, with one arctan of an argument in [-1, 1]."""
    steep = jnp.abs(sin_phi) > jnp.abs(cos_phi)
    num = jnp.where(steep, cos_phi, sin_phi)
    den = jnp.where(steep, sin_phi, cos_phi)
    base = jnp.arctan(num / jnp.where(den == 0, 1.0, den))
    phi = jnp.where(
        steep,
        jnp.where(sin_phi > 0, 0.5 * jnp.pi, 1.5 * jnp.pi) - base,
        jnp.where(cos_phi > 0, jnp.where(base < 0, 2 * jnp.pi, 0.0), jnp.pi) + base,
    )
    return jnp.where(phi >= 2 * jnp.pi, phi - 2 * jnp.pi, phi)


def _factorable(a, b, c):
    """Closed-form registers when b = 0 or c = 0 (a >= 0), in the slot order of `_solve`.

    c = 0: $f = \\sin\\varphi\\,(2a\\cos\\varphi + b)$: roots 0 and pi (energies
    $G = -a/2 \\mp b$) and, if $|b| < 2a$, the pair $\\cos\\varphi = -b/2a$, which are the
    (equal) maxima of $G = -\\tfrac a2 \\cos 2\\varphi - b\\cos\\varphi + c\\sin\\varphi$.
    b = 0: $f = \\cos\\varphi\\,(2a\\sin\\varphi + c)$: roots pi/2 and 3pi/2 and, if
    $|c| < 2a$, the pair $\\sin\\varphi = -c/2a$, the (equal) minima.  Ties go the way of
    the limit from positive b, c.
    """
    safe_a = jnp.where(a > 0, a, 1.0)
    c_zero = c == 0
    q = jnp.where(c_zero, -b, -c) / (2 * safe_a)
    pair = (a > 0) & (jnp.abs(q) < 1)
    r = jnp.sqrt(jnp.maximum(1 - q * q, 0.0))
    one, zero = jnp.ones_like(q), jnp.zeros_like(q)
    # c = 0: axis roots (+-1, 0); the lower-energy one is phi = 0 when b >= 0.
    s_b = jnp.where(b >= 0, 1.0, -1.0)
    cz_cos = jnp.stack([s_b, jnp.where(pair, q, -s_b), -s_b, q], -1)
    cz_sin = jnp.stack([zero, jnp.where(pair, r, zero), zero, -r], -1)
    # b = 0: axis roots (0, +-1); the higher-energy one is phi = pi/2 when c >= 0.
    s_c = jnp.where(c >= 0, 1.0, -1.0)
    bz_cos = jnp.stack([jnp.where(pair, r, zero), zero, -r, zero], -1)
    bz_sin = jnp.stack([jnp.where(pair, q, -s_c), s_c, q, -s_c], -1)
    pick = c_zero[..., None]
    cos_phi = jnp.where(pick, cz_cos, bz_cos)
    sin_phi = jnp.where(pick, cz_sin, bz_sin)
    valid = (jnp.arange(4) < 2) | pair[..., None]
    return cos_phi, sin_phi, valid, jnp.zeros_like(valid)


@jax.custom_jvp
def _registers(A, B, C):
    return _solve_all(A, B, C)


@_registers.defjvp
def _registers_jvp(primals, tangents):
    A, B, C = primals
    dA, dB, dC = tangents
    out = _solve_all(A, B, C)
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


@functools.partial(jax.jit, inline=True)
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
