"""The rod state on $SE(3)\\times\\mathbb{R}^6$ and a Lie-group Runge--Kutta solver for it.

The director frame $D = [d_1\\, d_2\\, d_3]$ (columns in lab coordinates) and the centreline
$x$ obey $D' = D\\,\\hat u$, $x' = D e_3$: a right-invariant ODE $g' = g\\,\\xi$ on the
special Euclidean group with the *body velocity* $\\xi = (u, e_3)$.  Stepping with the
exact group exponential keeps $D$ orthonormal to round-off and is exact whenever $u$ is
constant on a step, i.e. on every uniform helix.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._misc import is_concrete


class RodState(eqx.Module):
    """The integrated state of a rod at one arc length (local components).

    `n`, `m`: contact force and moment in the director frame, shape `(3,)`.  `frame`: the
    rotation $D$ whose column $i$ is $d_{i+1}$ in lab coordinates, shape `(3, 3)`, or `None`
    when the frame is not integrated.  `x`: the centreline in lab coordinates, `(3,)`, or
    `None` (it needs the frame).
    """

    n: Float[Array, "3"]
    m: Float[Array, "3"]
    frame: Float[Array, "3 3"] | None = None
    x: Float[Array, "3"] | None = None


def hat(w: Array) -> Array:
    """Skew matrix $\\hat w$ with $\\hat w v = w \\times v$: `w` of shape `(..., 3)` gives
    `(..., 3, 3)`.  Example: `hat(jnp.array([0., 0., 1.])) @ jnp.array([1., 0., 0.])` is
    `(0, 1, 0)` ($e_3 \\times e_1 = e_2$).  Inverse of `vee`."""
    w1, w2, w3 = w[..., 0], w[..., 1], w[..., 2]
    z = jnp.zeros_like(w1)
    return jnp.stack(
        [jnp.stack([z, -w3, w2], -1), jnp.stack([w3, z, -w1], -1), jnp.stack([-w2, w1, z], -1)], -2
    )


def vee(W: Array) -> Array:
    """Inverse of `hat` (antisymmetric part of `W`)."""
    return 0.5 * jnp.stack([W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]], -1)


def _exp_coefficients(theta2):
    """$(\\sin\\theta/\\theta,\\ (1-\\cos\\theta)/\\theta^2,\\ (\\theta-\\sin\\theta)/\\theta^3)$.

    Series below $\\theta = 10^{-2}$ (truncation $< 10^{-16}$) and a double `where` so that
    values and gradients stay finite at $\\theta = 0$.
    """
    small = theta2 < 1e-4
    t2 = jnp.where(small, 1.0, theta2)
    theta = jnp.sqrt(t2)
    half_sinc = jnp.sin(0.5 * theta) / (0.5 * theta)
    a = jnp.sin(theta) / theta
    b = 0.5 * half_sinc * half_sinc  # (1 - cos)/theta^2 without cancellation
    c = (theta - jnp.sin(theta)) / (theta * t2)
    a_s = 1.0 - theta2 / 6.0 + theta2 * theta2 / 120.0
    b_s = 0.5 - theta2 / 24.0 + theta2 * theta2 / 720.0
    c_s = 1.0 / 6.0 - theta2 / 120.0 + theta2 * theta2 / 5040.0
    return jnp.where(small, a_s, a), jnp.where(small, b_s, b), jnp.where(small, c_s, c)


def so3_exp(w: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Rotation matrix $\\exp(\\hat w)$ (by angle $|w|$, radians, about $w/|w|$) by the Rodrigues
    formula, orthonormal to round-off; `w` of shape `(..., 3)` gives `(..., 3, 3)`.  A series
    below $|w| = 10^{-2}$ keeps values and gradients finite at $w = 0$."""
    a, b, _ = _exp_coefficients(jnp.sum(w * w, axis=-1))
    W = hat(w)
    eye = jnp.eye(3, dtype=W.dtype).reshape((1,) * (W.ndim - 2) + (3, 3))
    return eye + a[..., None, None] * W + b[..., None, None] * (W @ W)


def gibbs(R: Array) -> Array:
    """Gibbs vector $\\tan(\\theta/2)\\,a$ of the rotation `R` (by $\\theta$ about $a$): zero only
    at the identity (no spurious root at $\\theta = \\pi$, unlike the rotation vector's
    sine); large but finite near $\\theta = \\pi$.  `(..., 3, 3)` gives `(..., 3)`."""
    den = 1.0 + jnp.trace(R, axis1=-2, axis2=-1)
    safe = jnp.where(den > 1e-8, den, 1e-8)
    return vee(R - jnp.swapaxes(R, -1, -2)) / safe[..., None]


def rotation_vector(R: Array) -> Array:
    """$\\theta a$ with $R = \\exp(\\theta\\hat a)$, $0 \\le \\theta < \\pi$ (inverse of `so3_exp`)."""
    g = gibbs(R)
    norm2 = jnp.sum(g * g, -1)
    small = norm2 < 1e-24
    norm = jnp.sqrt(jnp.where(small, 1.0, norm2))
    factor = jnp.where(small, 2.0, 2.0 * jnp.arctan(norm) / norm)
    return factor[..., None] * g


def rotation_z(angle: ArrayLike) -> Array:
    """Rotation by `angle` (radians) about $e_z$, shape `angle.shape + (3, 3)`."""
    angle = jnp.asarray(angle)
    c, s = jnp.cos(angle), jnp.sin(angle)
    z, o = jnp.zeros_like(c), jnp.ones_like(c)
    return jnp.stack([jnp.stack([c, -s, z], -1), jnp.stack([s, c, z], -1), jnp.stack([z, z, o], -1)], -2)


def twist_angle(R: Array) -> Array:
    """Twist angle $\\varphi$ about $e_z$ of the rotation `R` in $(-\\pi, \\pi]$: the swing-twist
    split $R = S\\,R_z(\\varphi)$, with $S$ the smallest rotation that takes $e_z$ to $t = Re_z$,
    so $\\varphi$ is the angle about $t$ from $Se_x$ to $Re_x$ ($2\\operatorname{atan2}(q_z, q_w)$
    with $q$ the unit quaternion of `R`).  Computed from those two vectors, whose products
    are of order one: the quaternion form from the entries of `R`, $2\\operatorname{atan2}(R_{10}
    - R_{01}, 1 + \\operatorname{tr}R)$, divides two quantities of order $q_w^2$ and lost the
    angle near half a turn (measured: 0.019 rad on a spring's end frame solved to 1e-8,
    `tests/test_lie.py`).  Not defined where $t = -e_z$ (the split is not)."""
    d1, t = R[..., :, 0], R[..., :, 2]
    tx, ty, tz = t[..., 0], t[..., 1], t[..., 2]
    apart = jnp.maximum(1.0 + tz, jnp.finfo(R.dtype).eps)
    swung = jnp.stack([1.0 - tx * tx / apart, -tx * ty / apart, -tx], -1)  # S e_x
    return jnp.arctan2(jnp.sum(d1 * jnp.cross(t, swung), -1), jnp.sum(d1 * swung, -1))


def unwrap_near(angle: ArrayLike, hint: ArrayLike, xp=jnp) -> Array:
    """`angle + 2 pi k` with the integer `k` that brings it nearest to `hint`, in the array
    namespace `xp` (`numpy` for host values: eager `jnp.round` compiles a program)."""
    return angle + 2.0 * np.pi * xp.round((hint - angle) / (2.0 * np.pi))


def se3_exp(w: Float[Array, "3"], v: Float[Array, "3"]) -> tuple[Array, Array]:
    """Group exponential on $SE(3)$ of the body twist $(w, v)$ (rotation and translation
    rates times a step, shape `(3,)` each, director-frame components): rotation $R$
    `(3, 3)` = `so3_exp(w)` and translation $Vv$ `(3,)`, with $\\theta = |w|$ and
    $V = I + \\frac{1-\\cos\\theta}{\\theta^2}\\hat w + \\frac{\\theta-\\sin\\theta}{\\theta^3}\\hat w^2$.
    For a rod, $(w, v) = h\\,(u, e_3)$ moves the frame and centreline by arc length $h$
    exactly when $u$ is constant."""
    a, b, c = _exp_coefficients(jnp.sum(w * w, axis=-1))
    wv = jnp.cross(w, v)
    wwv = jnp.cross(w, wv)
    W = hat(w)
    R = jnp.eye(3, dtype=W.dtype) + a * W + b * (W @ W)
    return R, v + b * wv + c * wwv


def act(y: RodState, w: Array, v: Array) -> RodState:
    r"""Move the rod state by the body twist $(w, v)$: $g \mapsto g\exp(w, v)$.

    With $(R, p)$ = `se3_exp(w, v)` the frame becomes $DR$, the centreline $x + Dp$ and the
    local wrench follows the lab-fixed wrench (coadjoint action): $n \mapsto R^T n$,
    $m \mapsto R^T(m - p\times n)$.  For a constant twist this is the exact solution of
    the Kirchhoff equations over the step, and it conserves $|n|^2$ and $m\cdot n$.
    """
    # se3_exp written out with cross products, R = I + a W + b W^2 and R^T = I - a W + b W^2
    # (W = hat(w)), and the rows of D W = w x (rows of D) reversed: only elementwise
    # arithmetic, which XLA fuses (3 x 3 matrix products are separate library calls on a CPU,
    # and this runs at every stage of every step and at every saved point).
    a, b, c = _exp_coefficients(jnp.sum(w * w, axis=-1))
    wv = jnp.cross(w, v)
    p = v + b * wv + c * jnp.cross(w, wv)

    def rotate_back(z):
        wz = jnp.cross(w, z)
        return z - a * wz + b * jnp.cross(w, wz)

    n = rotate_back(y.n)
    m = rotate_back(y.m - jnp.cross(p, y.n))
    if y.frame is None:
        return RodState(n, m, None, None)
    DW = jnp.cross(y.frame, w[None])
    frame = y.frame + a * DW + b * jnp.cross(DW, w[None])
    x = None if y.x is None else y.x + jnp.sum(y.frame * p[None], axis=-1)
    return RodState(n, m, frame, x)


def tangent(y: RodState, w: Array, v: Array) -> RodState:
    r"""The velocity $dy/ds$ produced by the body twist $(w, v)$ (derivative of `act`)."""
    dn = -jnp.cross(w, y.n)
    dm = -jnp.cross(w, y.m) - jnp.cross(v, y.n)
    frame = None if y.frame is None else jnp.cross(y.frame, w[None])  # D hat(w), as in `act`
    x = None if y.x is None else jnp.sum(y.frame * v[None], axis=-1)
    return RodState(dn, dm, frame, x)


class BodyVelocityTerm(diffrax.AbstractTerm):
    r"""ODE term $y' = y\,\xi(s, y)$ given by its body twist: `velocity(s, y, args)`
    returns $(w, v)$ (rotation and translation rates in the director frame), e.g.
    $(u, e_3)$ for a Kirchhoff rod.  Used with `CommutatorFreeRK4`."""

    velocity: Callable

    def vf(self, t, y, args):
        return self.velocity(t, y, args)

    def contr(self, t0, t1, **kwargs):
        return t1 - t0

    def prod(self, vf, control):
        return jax.tree.map(lambda a: control * a, vf)


def _combine(coefficients, ks):
    return jax.tree.map(lambda *leaves: sum(c * leaf for c, leaf in zip(coefficients, leaves)), *ks)


class LieGroupInterpolation(diffrax.AbstractLocalInterpolation):
    r"""Dense output of one Lie-group step from $t_0$ to $t_1$: $y(t) = y_0\exp\theta(r)$,
    $r = (t - t_0)/(t_1 - t_0)$, with $\theta(r) = h\sum_i b_i(r)\,k_i$ in the Lie algebra
    $\mathfrak{se}(3)$: `k` the stage velocities (shape `(stages, 2, 3)`: rotation and
    translation parts), $h = t_1 - t_0$, and the weights $b_i(r) = \sum_{j\ge 1}$
    `weights[i, j-1]` $r^j$ of the method's continuous extension.

    It is the continuous extension of the Runge--Kutta method that the solver applies to
    $\theta' = \mathrm{dexp}^{-1}_{-\theta}\,\xi(y_0\exp\theta)$, so the saved frames
    stay rotations and the saved wrenches conserve $|n|^2$ and $m\cdot n$ like the steps,
    and it is exact whenever the twist is constant on the step (then $\theta(r) =
    r\,h\,\xi$).  Saving at $s$ thus costs one group exponential, not a step that ends
    there.  A step only stacks its stage velocities; the weights are evaluated where a
    point is saved."""

    t0: Array
    t1: Array
    y0: RodState
    k: Float[Array, "stages 2 3"]
    weights: Float[Array, "stages p"]

    def evaluate(self, t0, t1=None, left=True):
        del left
        if t1 is not None:
            return jax.tree.map(jnp.subtract, self.evaluate(t1), self.evaluate(t0))
        h = self.t1 - self.t0
        r = jnp.where(h == 0, 0.0, (t0 - self.t0) / jnp.where(h == 0, 1.0, h))
        # Horner over the powers of r for every stage weight, then a weighted sum of the
        # stages: elementwise, so that XLA fuses it into a few kernels.
        b = self.weights[:, -1]
        for j in range(self.weights.shape[1] - 2, -1, -1):
            b = self.weights[:, j] + r * b
        b = (h * r) * b
        w, v = jnp.sum(b[:, None, None] * self.k, axis=0)
        return act(self.y0, w, v)


def _dense_info(y0, matrix, ks):
    """`LieGroupInterpolation` fields from the stage velocities `ks` (shape `(stages, 2, 3)`,
    (w, v) in the algebra) and the continuous extension's weights `matrix` (stage x power
    of r).  Stages whose weights are all zero (four of Dopri8's fourteen) are left out:
    every saved point would otherwise multiply them by zero.  They are cut as runs of
    consecutive stages (two slices for Dopri8): a step that saves builds its interpolation
    inside the integrator's loop, where every slice of a stage was a kernel of its own
    (twenty for Dopri8, a fifth of that loop's kernels)."""
    used = [i for i, row in enumerate(matrix) if any(c != 0 for c in row)]
    runs = [[used[0]]]
    for i in used[1:]:
        if i == runs[-1][-1] + 1:
            runs[-1].append(i)
        else:
            runs.append([i])
    k = jnp.concatenate([ks[run[0] : run[-1] + 1] for run in runs]) if len(runs) > 1 else ks[runs[0][0] : runs[0][-1] + 1]
    return dict(y0=y0, k=k, weights=jnp.asarray([matrix[j] for j in used], dtype=ks.dtype))


# The third-order continuous extension of the classical RK4 weights, b_i(r) = sum_j
# matrix[i][j] r^(j+1): b_1 = r - 3r^2/2 + 2r^3/3, b_2 = b_3 = r^2 - 2r^3/3,
# b_4 = -r^2/2 + 2r^3/3 (sum b_i c_i = r^2/2, sum b_i c_i^2 = r^3/3, sum b_i a_ij c_j = r^3/6).
_RK4_DENSE = ((1.0, -1.5, 2 / 3), (0.0, 1.0, -2 / 3), (0.0, 1.0, -2 / 3), (0.0, -0.5, 2 / 3))


class CommutatorFreeRK4(diffrax.AbstractAdaptiveSolver):
    r"""Commutator-free Lie-group Runge--Kutta method of order 4 (CF4) for `RodState`.

    The fourth-order method of Celledoni, Marthinsen and Owren (Future Gener. Comput. Syst.
    19, 2003) for $y' = y\,\xi(y)$ with $SE(3)$ acting on the rod state by `act`: stages
    $Y_2 = y_0 e^{hK_1/2}$, $Y_3 = y_0 e^{hK_2/2}$, $Y_4 = Y_2 e^{h(K_3 - K_1/2)}$,
    $K_i = \xi(Y_i)$, and the update
    $y_1 = y_0\, e^{h(3K_1+2K_2+2K_3-K_4)/12}\, e^{h(-K_1+2K_2+2K_3+3K_4)/12}$.  Only
    exponentials are needed (no commutators, no $\mathrm{dexp}^{-1}$).

    * Exact when the twist is constant, so a uniform helix is reproduced to round-off at
      any step size; the frame stays orthonormal and $|n|^2$, $m\cdot n$ are conserved to
      round-off on every solution.  The wrench is moved by the group too, so the
      wrench-only system is still 6-dimensional.
    * First-same-as-last: $K_5 = \xi(y_1)$ is the next step's $K_1$ and gives the embedded
      third-order estimate $h(K_4 - K_5)/6$ (mapped to a state velocity by `tangent`) for
      adaptive step sizes: 4 evaluations of $\xi$ per step.
    * Dense output (`LieGroupInterpolation`) of order 3, exact for a constant twist: the
      RK4 continuous extension applied to the stage velocities in the algebra, each
      corrected by its first $\mathrm{dexp}^{-1}$ term, $K_i + \frac12[\theta_i, K_i]$
      ($\theta_i$ the stage's point $y_0\exp\theta_i$): the commutator-free stages agree
      with the RK4 stages of the $\theta$ equation to $O(h^3)$, which is what order 3
      needs.  At $r = 1$ it meets $y_1$ to $O(h^5)$.

    The term must be a `BodyVelocityTerm`.
    """

    term_structure: ClassVar = BodyVelocityTerm
    interpolation_cls: ClassVar[Callable[..., LieGroupInterpolation]] = LieGroupInterpolation
    dense_output: ClassVar[bool] = True

    def order(self, terms):
        return 4

    def init(self, terms, t0, t1, y0, args):
        return terms.vf(t0, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        h = t1 - t0
        k1 = jax.lax.cond(made_jump, lambda: terms.vf(t0, y0, args), lambda: solver_state)

        def move(y, coefficients, ks):
            return act(y, *_combine([h * c for c in coefficients], ks))

        y2 = move(y0, (0.5,), (k1,))
        k2 = terms.vf(t0 + 0.5 * h, y2, args)
        k3 = terms.vf(t0 + 0.5 * h, move(y0, (0.5,), (k2,)), args)
        k4 = terms.vf(t1, move(y2, (1.0, -0.5), (k3, k1)), args)
        ks = (k1, k2, k3, k4)
        y_half = move(y0, (3 / 12, 2 / 12, 2 / 12, -1 / 12), ks)
        y1 = move(y_half, (-1 / 12, 2 / 12, 2 / 12, 3 / 12), ks)
        k5 = terms.vf(t1, y1, args)
        y_error = tangent(y1, *_combine((h / 6, -h / 6), (k4, k5)))
        thetas = (None, _combine((0.5 * h,), (k1,)), _combine((0.5 * h,), (k2,)), _combine((h,), (k3,)))
        corrected = [k1] + [_combine((1.0, 0.5), (k, _bracket(theta, k))) for theta, k in zip(thetas[1:], ks[1:])]
        stages = jnp.stack([jnp.stack(k) for k in corrected])
        return y1, y_error, _dense_info(y0, _RK4_DENSE, stages), k5, diffrax.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return tangent(y0, *terms.vf(t0, y0, args))


def _bracket(a, b):
    """Lie bracket on se(3): $[(w_1, v_1), (w_2, v_2)] = (w_1\\times w_2,\\ w_1\\times v_2 - w_2\\times v_1)$."""
    return jnp.cross(a[0], b[0]), jnp.cross(a[0], b[1]) - jnp.cross(b[0], a[1])


# dexp^{-1}_{-theta}(k) = sum_j B_j (-1)^j ad_theta^j k / j!  (Bernoulli numbers; odd j > 1 vanish)
_DEXPINV = ((1, 0.5), (2, 1 / 12), (4, -1 / 720), (6, 1 / 30240))


def _dexpinv(theta, k):
    r"""$\mathrm{dexp}^{-1}_{-\theta}(k)$ to $O(|\theta|^7)$: the body-frame form needed when
    $g = g_0 \exp\theta$ solves $g' = g\,k$ ($\theta' = \mathrm{dexp}^{-1}_{-\theta} k$).

    In Horner form, $k + \mathrm{ad}(c_1 k + \mathrm{ad}(c_2 k + \mathrm{ad}^2(c_4 k +
    \mathrm{ad}^2(c_6 k))))$: every bracket is used once, so XLA fuses the chain without
    recomputing shared terms."""
    (_, c1), (_, c2), (_, c4), (_, c6) = _DEXPINV
    ad = lambda x: _bracket(theta, x)  # noqa: E731
    plus = lambda x, c: jax.tree.map(lambda a, b: a + c * b, x, k)  # noqa: E731
    t = jax.tree.map(lambda a: c6 * a, k)
    t = plus(ad(ad(t)), c4)
    t = plus(ad(ad(t)), c2)
    t = plus(ad(t), c1)
    return plus(ad(t), 1.0)


class MuntheKaasRK(diffrax.AbstractAdaptiveSolver):
    r"""Runge--Kutta--Munthe-Kaas method on $SE(3)$ built on an explicit diffrax tableau.

    `MuntheKaasRK(diffrax.Dopri8())` integrates $y' = y\,\xi(y)$ by writing the step as
    $y_0\exp\theta$ and applying the Butcher tableau of the given solver to
    $\theta' = \mathrm{dexp}^{-1}_{-\theta}\,\xi(y_0\exp\theta)$ (the series is truncated
    after $\mathrm{ad}^6$, enough for order 8).  It keeps the order of the tableau, is exact
    for constant $\xi$ (then every bracket vanishes), keeps the frame orthonormal and
    conserves $|n|^2$ and $m\cdot n$ like `CommutatorFreeRK4`, and estimates its error from
    the tableau's embedded method in the Lie algebra.  Use with a `BodyVelocityTerm`.

    Dense output (`LieGroupInterpolation`): the tableau's own continuous extension (its
    polynomial weights, for `Dopri8`) applied to the corrected stage velocities, i.e. the
    dense output of the $\theta$ equation, mapped by the exponential.  For `Dopri8` that
    is diffrax's interpolation, whose local error falls as $h^6$ (order 5, measured in
    `tests/test_lie.py`), as it does for diffrax's own `Dopri8` dense output.  A tableau
    without polynomial weights gets $\theta(r) = r\,\theta(1)$, exact for a constant twist
    but of order 1 otherwise (`dense_output = False`: `solve_static` then lands steps on
    the save points).
    """

    # The tableau as tuples of floats: hashable static data.
    a_lower: tuple[tuple[float, ...], ...] = eqx.field(static=True)
    b_sol: tuple[float, ...] = eqx.field(static=True)
    b_error: tuple[float, ...] = eqx.field(static=True)
    c: tuple[float, ...] = eqx.field(static=True)
    tableau_order: int = eqx.field(static=True)
    # Weights of the tableau's continuous extension, stage x power of r (r^1, r^2, ...).
    dense_weights: tuple[tuple[float, ...], ...] = eqx.field(static=True)
    dense_output: bool = eqx.field(static=True)
    term_structure: ClassVar = BodyVelocityTerm
    interpolation_cls: ClassVar[Callable[..., LieGroupInterpolation]] = LieGroupInterpolation

    def __init__(self, solver: diffrax.AbstractSolver = diffrax.Dopri8()):
        tableau = getattr(type(solver), "tableau", None)
        if tableau is None or tableau.implicit:
            raise ValueError(f"MuntheKaasRK needs an explicit Runge-Kutta solver, got {type(solver).__name__}")
        floats = lambda a: tuple(float(x) for x in a)  # noqa: E731
        self.a_lower = tuple(floats(row) for row in tableau.a_lower)
        self.b_sol, self.b_error, self.c = floats(tableau.b_sol), floats(tableau.b_error), floats(tableau.c)
        self.tableau_order = solver.order(None)
        # diffrax's polynomial interpolations give y0 + sum_i polyval(row_i, r) r k_i.
        rows = getattr(type(solver).interpolation_cls, "eval_coeffs", None)
        if rows is not None and len(rows) == len(self.c) + 1:
            self.dense_weights = tuple(floats(row[::-1]) for row in rows)
            self.dense_output = True
        else:
            self.dense_weights = tuple((float(b),) for b in self.b_sol)
            self.dense_output = False

    def order(self, terms):
        return self.tableau_order

    def init(self, terms, t0, t1, y0, args):
        return None

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        h = t1 - t0
        stages = len(self.b_sol)
        # The stages as a loop over the tableau's rows, not unrolled: one copy of the stage
        # (an exponential, the vector field, dexp^{-1}) in the program instead of one per
        # stage.  Measured (one core, fresh processes, against the unrolled stages): the
        # default solve's XLA compilation 3.4 -> 0.65 s, `solve_static`'s first call (L = 40)
        # 4.0 -> 1.1 s; later calls faster too, 1.86 -> 1.62 ms there and 0.39 -> 0.36 ms on
        # the non-helical solve of `benchmarks/bench_kirchhoff.py`.  Under `vmap` (1000 solves
        # in lockstep) 300-317 us a solve against 204 with XLA's YNNPACK elementwise fusions,
        # which ran each stage's combination as a library call; 152-168 us without them
        # (`_compile.request_dot_library_fusions`).
        rows = np.zeros((stages - 1, stages))
        for i, row in enumerate(self.a_lower):
            rows[i, : len(row)] = row
        rows, c = jnp.asarray(rows, dtype=h.dtype), jnp.asarray(self.c, dtype=h.dtype)

        def theta_of(weights, ks):
            # Multiplied and summed, not a dot: XLA fuses it into the stage (with dots of the
            # traced rows, library calls on a CPU, that solve took 0.50 ms, not 0.36).
            combined = jnp.sum(weights[:, None, None] * ks, axis=0)
            return h * combined[0], h * combined[1]

        def stage(i, ks):
            theta = theta_of(rows[i], ks)
            k = terms.vf(t0 + c[i] * h, act(y0, *theta), args)
            return ks.at[i + 1].set(jnp.stack(_dexpinv(theta, k)))

        k = terms.vf(t0, y0, args)
        ks = jnp.zeros((stages, 2, 3), dtype=h.dtype).at[0].set(jnp.stack(k))
        ks = jax.lax.fori_loop(0, stages - 1, stage, ks)  # dexpinv-corrected stage velocities
        y1 = act(y0, *theta_of(jnp.asarray(self.b_sol, dtype=h.dtype), ks))
        y_error = tangent(y1, *theta_of(jnp.asarray(self.b_error, dtype=h.dtype), ks))
        return y1, y_error, _dense_info(y0, self.dense_weights, ks), None, diffrax.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return tangent(y0, *terms.vf(t0, y0, args))


def rotation_tolerance(dtype) -> float:
    """The largest $|D^TD - I|$ of a frame taken as a rotation: 1e-8 in float64, 1e3
    machine epsilons in a lower precision."""
    return max(1e-8, 1e3 * float(np.finfo(dtype if np.issubdtype(dtype, np.floating) else np.float64).eps))


def is_rotation(frame) -> Array:
    """Whether one traced `frame` `(3, 3)` is a rotation (`check_rotation`'s test): finite,
    orthonormal within `rotation_tolerance`, $\\det D > 0$."""
    frame = jnp.asarray(frame)
    error = jnp.max(jnp.abs(frame.T @ frame - jnp.eye(3, dtype=frame.dtype)))
    determinant = jnp.dot(frame[:, 0], jnp.cross(frame[:, 1], frame[:, 2]))  # in closed form: no LU in the program
    return jnp.all(jnp.isfinite(frame)) & (error <= rotation_tolerance(frame.dtype)) & (determinant > 0)


def check_rotation(frame: ArrayLike, owner: str) -> None:
    """`ValueError` naming `owner` unless a concrete `frame` (`(..., 3, 3)`, columns d1, d2,
    d3) is a rotation: $|D^TD - I| \\le$ `rotation_tolerance` and $\\det D > 0$.  Traced
    frames pass (`is_rotation` tests them where a solve flags its point)."""
    if not is_concrete(frame):
        return
    f = np.asarray(frame)
    tolerance = rotation_tolerance(f.dtype)
    gram = np.einsum("...ji,...jk->...ik", f, f) - np.eye(3)
    error = np.abs(gram).max(initial=0.0)
    if not np.isfinite(error) or error > tolerance or np.any(np.linalg.det(f) < 0):
        raise ValueError(
            f"{owner}: frame must be a rotation (orthonormal columns d1, d2, d3, det +1); "
            f"max |D^T D - I| = {error:.2e}"
        )
