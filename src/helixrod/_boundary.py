"""Boundary-value problems of finite Kirchhoff rods, solved by (multiple) shooting.

The rod is clamped at $s = 0$ (position $x_0$, frame $D_0$).  The unknowns are the lab force
$N$ (constant along the rod) and the lab moment $M_0$ at $s = 0$; the moment about any fixed
point is constant too, so the lab moment at any point is $M(s) = M_0 - (x(s) - x_0)\\times N$.
The end condition at $s = L$ gives six equations:

- `Clamped(position, frame)`: $x(L) = P$, $D(L) = R$;
- `Loaded(force, moment, point)`: $N = F$ and the moment about `point` (a fixed lab point;
  the end $x(L)$ itself when `point` is `None`) equals the given moment -- with a fixed point
  the moment about it is conserved, so this is an initial-value problem in disguise;
- `Tweezer(frame, force)`: $D(L) = R$ and $N = F$, the end position free (a magnetic bead:
  the magnet fixes the bead's orientation and pulls with a known force).

Frames are compared through the Gibbs vector $g(R^TD) = \\mathrm{vee}(A - A^T)/(1 + \\mathrm{tr}A)
= \\tan(\\theta/2)\\,a$, whose only zero is the identity (no spurious root at $\\theta = \\pi$).

Shooting.  With `segments = k` the rod is cut into $k$ equal pieces; the unknowns are
$(N, M_0)$ and the position and frame ($x_j$, $D_j = \\bar D_j \\exp\\hat w_j$) of the start of
pieces $1..k-1$, and the equations are the continuity of position and frame at the $k - 1$
junctions plus the end condition: $6k$ equations in $6k$ unknowns ($k = 1$ is single
shooting).  The wrench needs no junction condition: the geometric integrators keep the lab
force and the moment about a fixed point exactly (to round-off), so the wrench at the start
of each piece is $(N, M_0 - (x_j - x_0)\\times N)$.  The pieces are integrated in parallel
(`vmap`) and the flow of each piece depends, up to a rigid motion, only on its local start
wrench: its $18\\times 6$ Jacobian is computed once per piece (custom JVP), so a Jacobian
costs about six integrations of the whole rod whatever $k$ (and most Newton steps need none:
Broyden updates, `_TrustNewton`).

Why multiple shooting.  Where the loaded rod is *spatially unstable* -- the linearised
wrench flow has eigenvalues with real part $\\lambda > 0$, e.g. a helical spring pulled at
fixed end rotation -- errors in the initial wrench grow like $e^{\\lambda L}$ and single
shooting loses its Newton basin and then its precision as $\\lambda L$ grows; pieces of
length $L/k$ bring that to $e^{\\lambda L/k}$.  Measured limits: README and
`benchmarks/bench_finite.py`.

Root solve.  A damped Newton (Levenberg--Marquardt) iteration written as an optimistix root
finder (`_TrustNewton`), optionally along a homotopy (`continuation`) from the unloaded rod
to the prescribed end.  Derivatives are those of the implicit function theorem on the
shooting equations, $\\dot y = -J^{-1}\\partial_\\theta F\\,\\dot\\theta$, with the Jacobian $J$
of the converged solve: forward mode with the default `diffrax.ForwardMode()`,
`diffrax.DirectAdjoint()` also allows reverse mode.
"""

from __future__ import annotations

import abc
import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._axial import (
    bulk_helix_indexed,
    length_scale,
    no_gradient,
    rz,
    stiffness_scale,
    twist_angle,
    unloaded_observables,
    unloaded_state,
)
from ._kirchhoff import check_one_rod, solve_static
from ._lie import CommutatorFreeRK4, MuntheKaasRK, so3_exp, vee

METHODS = ("levenberg-marquardt", "newton")


def _is_concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(xs))


def _array(x, name, shape_tail, owner):
    a = jnp.asarray(x, jnp.result_type(float))
    if a.shape[a.ndim - len(shape_tail) :] != shape_tail or a.ndim < len(shape_tail):
        raise ValueError(f"{owner}: {name} must have trailing shape {shape_tail}, got {a.shape}")
    if _is_concrete(a) and not np.all(np.isfinite(np.asarray(a))):
        raise ValueError(f"{owner}: {name} must be finite, got {a}")
    return a


def _check_rotation(frame, owner):
    if _is_concrete(frame):
        f = np.asarray(frame)
        gram = np.einsum("...ji,...jk->...ik", f, f) - np.eye(3)
        if np.abs(gram).max(initial=0.0) > 1e-8 or np.any(np.linalg.det(f) < 0):
            raise ValueError(
                f"{owner}: frame must be a rotation (orthonormal columns d1, d2, d3, det +1); "
                f"max |D^T D - I| = {np.abs(gram).max(initial=0.0):.2e}"
            )


def gibbs(R: Array) -> Array:
    """Gibbs vector $\\tan(\\theta/2)\\,a$ of the rotation `R` (by $\\theta$ about $a$); large but
    finite near $\\theta = \\pi$."""
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


# -- boundary conditions --------------------------------------------------------------------

_CLAMPED, _LOADED, _TWEEZER = 0, 1, 2


class _EndData(eqx.Module):
    """Uniform (traced) form of every end condition, so that one compiled program serves
    all three kinds and a `vmap`-ped batch may mix them.  `kind`: 0 clamped, 1 loaded,
    2 tweezer; unused fields are zeros (identity frame)."""

    kind: Int[Array, ""]
    position: Float[Array, "3"]
    frame: Float[Array, "3 3"]
    force: Float[Array, "3"]
    moment: Float[Array, "3"]
    point: Float[Array, "3"]
    about_end: Bool[Array, ""]

    def residual(self, x, frame, force, moment, scales):
        """Scaled residual `(6,)` of the lab end state."""
        ell, f_scale, m_scale = scales[0], scales[1], scales[2]
        point = jnp.where(self.about_end, x, self.point)
        r_position = (x - self.position) / ell
        r_frame = gibbs(self.frame.T @ frame)
        r_force = (force - self.force) / f_scale
        r_moment = (moment + jnp.cross(x - point, force) - self.moment) / m_scale
        first = jnp.where(self.kind == _CLAMPED, r_position, r_force)
        second = jnp.where(self.kind == _LOADED, r_moment, r_frame)
        return jnp.concatenate([first, second])

    def homotopy(self, t, x_free, frame_free):
        """The condition a fraction `t` of the way from the unloaded end (`t = 0`)."""
        turn = rotation_vector(frame_free.T @ self.frame)
        return eqx.tree_at(
            lambda e: (e.position, e.frame, e.force, e.moment),
            self,
            ((1 - t) * x_free + t * self.position, frame_free @ so3_exp(t * turn), t * self.force, t * self.moment),
        )

    def finite(self):
        leaves = (self.position, self.frame, self.force, self.moment, self.point)
        return jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in leaves]))


def _end_data(kind, position=None, frame=None, force=None, moment=None, point=None):
    # NumPy constants: no eager JAX dispatch per solve (they are traced like JAX arrays).
    dtype = jnp.result_type(float)
    zero = np.zeros(3, dtype)
    return _EndData(
        kind=np.asarray(kind, np.int32),
        position=zero if position is None else position,
        frame=np.eye(3, dtype=dtype) if frame is None else frame,
        force=zero if force is None else force,
        moment=zero if moment is None else moment,
        point=zero if point is None else point,
        about_end=np.asarray(point is None and kind == _LOADED),
    )


class AbstractEnd(eqx.Module):
    """A condition at the end $s = L$ of a rod clamped at $s = 0$ (six scalar equations):
    `Clamped`, `Loaded` or `Tweezer`."""

    @abc.abstractmethod
    def end_data(self) -> _EndData:
        """The condition in the uniform internal form."""


class Clamped(AbstractEnd):
    """Prescribed position and frame: `Clamped(position=(0, 0, 0), frame=identity)`.

    `position` `(3,)` lab point; `frame` `(3, 3)` rotation with column $i$ = $d_{i+1}$ (lab).
    The start condition of every problem, and the end condition of a rod clamped at both
    ends (a spring test: grips that hold the wire ends).  Non-finite values or a frame that
    is not a rotation raise `ValueError` (concrete values).
    """

    position: Float[Array, "3"]
    frame: Float[Array, "3 3"]

    def __init__(self, position: ArrayLike = (0.0, 0.0, 0.0), frame: ArrayLike | None = None):
        position = _array(position, "position", (3,), "Clamped")
        frame = jnp.eye(3, dtype=position.dtype) if frame is None else _array(frame, "frame", (3, 3), "Clamped")
        _check_rotation(frame, "Clamped")
        self.position, self.frame = position, frame

    def end_data(self):
        return _end_data(_CLAMPED, position=self.position, frame=self.frame)


class Loaded(AbstractEnd):
    """Prescribed end load (dead load): `Loaded(force, moment, point=None)`.

    `force` `(3,)`: the lab force $n(L)$ applied to the end; `moment` `(3,)`: the applied
    moment about `point` (a fixed lab point, e.g. on a spring's axis), or about the end
    $x(L)$ itself when `point` is `None` (then it is $m(L)$ in lab components).
    """

    force: Float[Array, "3"]
    moment: Float[Array, "3"]
    point: Float[Array, "3"] | None

    def __init__(self, force: ArrayLike = (0.0, 0.0, 0.0), moment: ArrayLike = (0.0, 0.0, 0.0), point: ArrayLike | None = None):
        self.force = _array(force, "force", (3,), "Loaded")
        self.moment = _array(moment, "moment", (3,), "Loaded")
        self.point = None if point is None else _array(point, "point", (3,), "Loaded")

    def end_data(self):
        return _end_data(_LOADED, force=self.force, moment=self.moment, point=self.point)


class Tweezer(AbstractEnd):
    """Prescribed end frame and end force, free end position: `Tweezer(frame, force)`.

    The magnetic-tweezer set-up: the magnet holds the bead's orientation `frame` `(3, 3)`
    (e.g. the unloaded end frame turned about the axis by the magnet's rotation) and pulls
    with `force` `(3,)` (lab); the torque is a reaction.
    """

    frame: Float[Array, "3 3"]
    force: Float[Array, "3"]

    def __init__(self, frame: ArrayLike, force: ArrayLike):
        self.frame = _array(frame, "frame", (3, 3), "Tweezer")
        self.force = _array(force, "force", (3,), "Tweezer")
        _check_rotation(self.frame, "Tweezer")

    def end_data(self):
        return _end_data(_TWEEZER, frame=self.frame, force=self.force)


# -- solution -------------------------------------------------------------------------------


class BoundaryValueSolution(eqx.Module):
    """Solution of `solve_boundary_value`.

    Saved at `s` (shape `(p,)`; `saveat=None` saves $s = L$ only): `x` `(p, 3)` centreline and
    `frame` `(p, 3, 3)` (lab), `n`, `m` `(p, 3)` force and moment in the director frame.
    `n0`, `m0` `(3,)`: the wrench at $s = 0$ in the director frame, so that
    `solve_static(rod, n0, m0, L, frame0=start.frame, x0=start.position)` is the solution
    (where single shooting is stable); `force` `(3,)` the lab force $N$ (constant),
    `moment0` the lab moment at $s = 0$; `end_position`, `end_frame`, `end_force`,
    `end_moment` the lab state at $s = L$; `node_position` `(k, 3)`, `node_frame`
    `(k, 3, 3)` the starts of the `segments` pieces (a warm start for another solve).
    Status: `residual` the largest scaled residual of the shooting equations, `result` an
    `optimistix.RESULTS` code, `num_steps` root-solver iterations (all stages), `valid_input`,
    and `ok` (valid, converged, residual within `tolerance`).
    """

    s: Float[Array, " p"]
    x: Float[Array, "p 3"]
    frame: Float[Array, "p 3 3"]
    n: Float[Array, "p 3"]
    m: Float[Array, "p 3"]
    n0: Float[Array, "3"]
    m0: Float[Array, "3"]
    force: Float[Array, "3"]
    moment0: Float[Array, "3"]
    end_position: Float[Array, "3"]
    end_frame: Float[Array, "3 3"]
    end_force: Float[Array, "3"]
    end_moment: Float[Array, "3"]
    node_position: Float[Array, "k 3"]
    node_frame: Float[Array, "k 3 3"]
    residual: Float[Array, ""]
    result: optx.RESULTS
    num_steps: Int[Array, ""]
    valid_input: Bool[Array, ""]
    tolerance: Float[Array, ""]

    @property
    def ok(self) -> Bool[Array, ""]:
        """Valid input, solver success and residual within tolerance."""
        return self.valid_input & (self.result == optx.RESULTS.successful) & (self.residual <= self.tolerance)

    @property
    def segments(self) -> int:
        """Number of shooting pieces."""
        return self.node_position.shape[-2]

    def lab_wrench(self) -> tuple[Array, Array]:
        """Lab force and moment at the saved points, `(p, 3)` each."""
        return (
            jnp.einsum("...ij,...j->...i", self.frame, self.n),
            jnp.einsum("...ij,...j->...i", self.frame, self.m),
        )


# -- the shooting equations -----------------------------------------------------------------


class _Options(eqx.Module):
    """Static configuration of a solve (one compilation per configuration)."""

    segments: int = eqx.field(static=True)
    solver: diffrax.AbstractSolver
    max_ode_steps: int = eqx.field(static=True)
    adjoint: diffrax.AbstractAdjoint
    method: str = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    continuation: int = eqx.field(static=True)
    guess_kind: str = eqx.field(static=True)

    def integrate(self, rod, n0, m0, length, ode_tol, **kwargs):
        """`solve_static` with this configuration's integrator, frame and centreline
        integrated, `throw=False` (a failed piece is flagged, never raised)."""
        return solve_static(
            rod, n0, m0, length, outputs=("frame", "centreline"), solver=self.solver, rtol=ode_tol[0],
            atol=ode_tol[1], max_steps=self.max_ode_steps, adjoint=self.adjoint, throw=False, **kwargs,
        )


def _flow_one(theta, wrench, options: _Options, ode_tol):
    """Integrate one piece from the identity pose at the origin with local start wrench
    `wrench` (6,): the flat (18,) vector (p, R, n_end, m_end); NaN if the solve failed."""
    rod, piece = theta
    sol = options.integrate(rod, wrench[:3], wrench[3:], piece, ode_tol)
    out = jnp.concatenate([sol.x[-1], sol.frame[-1].reshape(9), sol.n[-1], sol.m[-1]])
    return jnp.where(sol.ok, out, jnp.nan)


def _tangent_part(tree, tangents):
    """(differentiated part of `tree`, the rest, its tangents) for a `filter_custom_jvp`
    tangent pytree with `None` at undifferentiated leaves."""
    is_none = lambda t: t is None  # noqa: E731
    mask = jax.tree.map(lambda t: t is not None, tangents, is_leaf=is_none)
    diff, static = eqx.partition(tree, mask)
    return diff, static, eqx.filter(tangents, mask, is_leaf=is_none)


def _per_piece(fn, xs):
    """`jax.vmap(fn)(xs)` over the pieces (leading axis); a single piece without `vmap`:
    a batched integration loop was measured to cost about twice as much."""
    if xs.shape[0] == 1:
        return jax.tree.map(lambda a: a[None], fn(xs[0]))
    return jax.vmap(fn)(xs)


@eqx.filter_custom_jvp
def _flows(wrench, theta, ode_tol, *, options):
    """Flows of all pieces, `(k, 18)`, from their local start wrenches `(k, 6)`."""
    return _per_piece(lambda w: _flow_one(theta, w, options, ode_tol), wrench)


@_flows.def_jvp
def _flows_jvp(primals, tangents, *, options):
    # The Jacobian with respect to the start wrench depends on primals only: computed once
    # per piece (six tangent integrations, all pieces in parallel) and reused by every
    # tangent direction -- a Jacobian of k pieces costs what one of single shooting does.
    # It is integrated at the Jacobian tolerance `ode_tol[2:]` (`_jacobian_tolerance`: looser
    # inside Newton's iteration, where it only steers the steps; the ODE tolerance itself
    # for the derivatives of the solution, `_implicit`), the flows at `ode_tol[:2]`.
    wrench, theta, ode_tol = primals
    t_wrench, t_theta, _ = tangents

    def jacobian(w):
        basis = jnp.eye(6, dtype=w.dtype)
        one = lambda ww: _flow_one(theta, ww, options, ode_tol[2:])  # noqa: E731
        return jax.vmap(lambda v: jax.jvp(one, (w,), (v,))[1])(basis)

    out = _per_piece(lambda w: _flow_one(theta, w, options, ode_tol), wrench)  # (k, 18)
    jac = _per_piece(jacobian, wrench)  # (k, 6, 18)
    t_out = jnp.zeros_like(out)
    if t_wrench is not None:
        t_out = t_out + jnp.einsum("kij,ki->kj", jac, t_wrench)
    if t_theta is not None and jax.tree.leaves(t_theta):
        diff, static, t_diff = _tangent_part(theta, t_theta)
        flows = lambda d: _per_piece(lambda w: _flow_one(eqx.combine(d, static), w, options, ode_tol), wrench)  # noqa: E731
        t_out = t_out + jax.jvp(flows, (diff,), (t_diff,))[1]
    return out, t_out


class _Args(eqx.Module):
    """Traced data of the shooting equations."""

    rod: object
    length: Array
    start: Clamped
    end: _EndData
    ref_x: Array  # (k-1, 3) reference node positions
    ref_frame: Array  # (k-1, 3, 3) reference node frames
    scales: Array  # (ell, force scale, moment scale)
    ode_tol: Array  # (rtol, atol) of the flows, then (rtol, atol) of their Jacobian


def _nodes(y, args: _Args, k: int):
    N = y[:3] * args.scales[1]
    M0 = y[3:6] * args.scales[2]
    z = y[6:].reshape(k - 1, 6)
    xs = jnp.concatenate([args.start.position[None], args.ref_x + z[:, :3] * args.scales[0]], 0)
    frames = jnp.concatenate([args.start.frame[None], args.ref_frame @ so3_exp(z[:, 3:])], 0)
    return N, M0, xs, frames


def _pieces(y, args: _Args, options: _Options, materialise: bool = True):
    """Start nodes and lab end states of every piece.  `materialise`: differentiate the
    flows through their per-piece Jacobian (`_flows`; for the many directions of a Newton
    step) or directly (for the few directions of a parameter derivative)."""
    k = options.segments
    N, M0, xs, frames = _nodes(y, args, k)
    moments = M0 - jnp.cross(xs - args.start.position, N)
    local = jnp.concatenate([jnp.einsum("kji,j->ki", frames, N), jnp.einsum("kji,kj->ki", frames, moments)], -1)
    theta = (args.rod, args.length / k)
    if materialise:
        flows = _flows(local, theta, args.ode_tol, options=options)
    else:
        flows = _per_piece(lambda w: _flow_one(theta, w, options, args.ode_tol), local)
    p, R, n_end, m_end = flows[:, :3], flows[:, 3:12].reshape(k, 3, 3), flows[:, 12:15], flows[:, 15:]
    x_end = xs + jnp.einsum("kij,kj->ki", frames, p)
    frame_end = frames @ R
    ends = (x_end, frame_end, jnp.einsum("kij,kj->ki", frame_end, n_end), jnp.einsum("kij,kj->ki", frame_end, m_end))
    return (N, M0, xs, frames), ends


def _residual(y, args: _Args, options: _Options, materialise: bool = True):
    """The 6k shooting equations; aux: the nodes and end states."""
    nodes, ends = _pieces(y, args, options, materialise)
    _, _, xs, frames = nodes
    x_end, frame_end, force_end, moment_end = ends
    junction_x = (x_end[:-1] - xs[1:]) / args.scales[0]
    junction_r = gibbs(jnp.swapaxes(frames[1:], -1, -2) @ frame_end[:-1])
    end = args.end.residual(x_end[-1], frame_end[-1], force_end[-1], moment_end[-1], args.scales)
    residual = jnp.concatenate([jnp.concatenate([junction_x, junction_r], -1).reshape(-1), end])
    return residual, (nodes, ends)


class _LMState(eqx.Module):
    y_best: Array
    f_best: Array
    jac_best: Array
    aux_best: object
    cost_best: Array
    damping: Array
    fresh: Array
    refresh: Array
    step: Array


# A Broyden step that reduces |f| by less than this factor asks for a fresh Jacobian.
_SLOW_PROGRESS = 0.1


class _TrustNewton(optx.AbstractRootFinder):
    """Newton's method for square systems with Levenberg--Marquardt damping and Broyden
    updates, as an optimistix root finder.

    Each step evaluates `fn` at the trial point of the previous one and accepts it if it
    lowers $\\tfrac12|f|^2$ (then the damping $\\lambda$ shrinks tenfold) or rejects it (the
    step is retried from the best point with $\\lambda$ ten times larger); the step solves
    $(J^TJ + \\lambda\\,\\mathrm{diag}J^TJ)\\,\\delta = -J^Tf$, Newton's step as $\\lambda\\to 0$
    (`damped=False`: plain Newton steps, always accepted).  The Jacobian $J$ is a full
    linearisation of `fn` (`_jacobian_tolerance`) at the first point, after a step that
    reduced $|f|$ by less than a factor `_SLOW_PROGRESS` and after a step rejected with a
    secant Jacobian; otherwise the previous one with Broyden's
    rank-one secant update $J \\leftarrow J + (\\Delta f - J\\Delta y)\\Delta y^T/|\\Delta y|^2$,
    so that most steps cost one evaluation of `fn` (one integration of the rod) instead of
    seven.  Terminates when $\\max|f| <$ `atol` at the best point, which it returns.
    Written here rather than using `optimistix.LevenbergMarquardt` because a least-squares
    solver is differentiated through its normal equations (reverse mode through the
    integrator) and evaluates `fn` more than once per step (a larger compiled program).
    """

    rtol: float
    atol: float
    norm: object = optx.max_norm
    damped: bool = True

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        zeros = lambda s: jnp.zeros(s.shape, s.dtype)  # noqa: E731
        return _LMState(
            y_best=y,
            f_best=jnp.full(f_struct.shape, jnp.inf, f_struct.dtype),
            jac_best=jnp.zeros((f_struct.size, y.size), y.dtype),
            aux_best=jax.tree.map(zeros, aux_struct),
            cost_best=jnp.array(jnp.inf, y.dtype),
            damping=jnp.array(1e-6 if self.damped else 0.0, y.dtype),
            fresh=jnp.array(False),
            refresh=jnp.array(True),
            step=jnp.array(0),
        )

    def step(self, fn, y, args, options, state: _LMState, tags):
        def linearised():
            f, lin, aux = jax.linearize(lambda z: fn(z, args), y, has_aux=True)
            return f, aux, jax.vmap(lin, out_axes=-1)(jnp.eye(y.size, dtype=y.dtype))

        def secant():
            f, aux = fn(y, args)
            dy, df = y - state.y_best, f - state.f_best
            dy2 = jnp.sum(dy * dy)
            update = jnp.outer(df - state.jac_best @ dy, dy) / jnp.where(dy2 > 0, dy2, 1.0)
            good = (dy2 > 0) & jnp.all(jnp.isfinite(update))
            return f, aux, jnp.where(good, state.jac_best + update, state.jac_best)

        f, aux, jac = jax.lax.cond(state.refresh, linearised, secant)
        cost = 0.5 * jnp.sum(f * f)
        finite = jnp.all(jnp.isfinite(jac)) & jnp.isfinite(cost)
        accept = finite & (cost < state.cost_best) if self.damped else finite
        slow = ~(cost < _SLOW_PROGRESS**2 * state.cost_best)
        pick = lambda a, b: jax.tree.map(lambda x, z: jnp.where(accept, x, z), a, b)  # noqa: E731
        y_best, f_best, aux_best = pick((y, f, aux), (state.y_best, state.f_best, state.aux_best))
        # A linearisation belongs to its point; a secant update (also from a rejected
        # point) improves the Jacobian wherever the iteration stands.
        take = jnp.where(state.refresh, accept, finite)
        jac_best = jnp.where(take, jac, state.jac_best)
        fresh = jnp.where(take, state.refresh, state.fresh)
        cost_best = jnp.where(accept, cost, state.cost_best)
        if self.damped:
            damping = jnp.where(accept, jnp.maximum(state.damping / 10, 1e-12), state.damping * 10)
            jtj = jac_best.T @ jac_best
            lhs = jtj + damping * jnp.diag(jnp.maximum(jnp.diag(jtj), 1e-300))
            delta = jnp.linalg.solve(lhs, jac_best.T @ f_best)
        else:
            damping = jnp.where(accept, state.damping, jnp.inf)
            delta = jnp.linalg.solve(jac_best, f_best)
        delta = jnp.where(jnp.all(jnp.isfinite(delta)), delta, 0.0)
        # Relinearise after slow progress, or after a rejected step taken with a secant
        # Jacobian (a rejected step with an exact one only needs more damping).
        refresh = jnp.where(accept, slow, ~fresh)
        new_state = _LMState(y_best, f_best, jac_best, aux_best, cost_best, damping, fresh, refresh, state.step + 1)
        return y_best - delta, new_state, aux

    def terminate(self, fn, y, args, options, state: _LMState, tags):
        converged = self.norm(state.f_best) < self.atol
        stuck = state.damping > 1e12
        result = optx.RESULTS.where(stuck & ~converged, optx.RESULTS.nonlinear_divergence, optx.RESULTS.successful)
        return converged | stuck, result

    def postprocess(self, fn, y, aux, args, options, state: _LMState, tags, result):
        return state.y_best, state.aux_best, {}


def _root(y0, args: _Args, options: _Options, rtol, atol):
    """Solve the shooting equations (no derivatives: see `_implicit`).  Returns the root,
    the pieces there (aux), the result code and the number of steps."""
    fn = lambda y, a: _residual(y, a, options)  # noqa: E731
    solver = _TrustNewton(rtol=rtol, atol=atol, damped=options.method != "newton")
    y0, args = no_gradient((y0, args))
    sol = optx.root_find(fn, solver, y0, args, has_aux=True, max_steps=options.max_steps, throw=False)
    return sol.value, sol.aux, sol.result, sol.stats["num_steps"]


@eqx.filter_custom_jvp
def _implicit(y, pieces, args, *, options):
    """The root `y` of the shooting equations at `args` and the `pieces` there, with the
    derivatives of the implicit function theorem: $\\dot y = -J^{-1}\\,\\partial_\\theta F\\,
    \\dot\\theta$ and $\\dot P = P_y\\dot y + \\partial_\\theta P\\,\\dot\\theta$, with the Jacobians
    $J = F_y$ and $P_y$ integrated at the ODE tolerance itself (the root solve steers with
    looser ones) and one forward-mode pass through the flows for $\\partial_\\theta$.  (Not
    `optimistix.ImplicitAdjoint`: its linear solve raises on a non-finite input, so one failed point would abort a
    differentiated batch; here a failed point gets NaN derivatives.)"""
    return y, pieces


@_implicit.def_jvp
def _implicit_jvp(primals, tangents, *, options):
    y, pieces, args = primals
    t_args = tangents[2]
    if t_args is None or not jax.tree.leaves(t_args):
        return (y, pieces), jax.tree.map(jnp.zeros_like, (y, pieces))
    exact = eqx.tree_at(lambda a: a.ode_tol, args, jnp.concatenate([args.ode_tol[:2], args.ode_tol[:2]]))
    _, lin = jax.linearize(lambda z: _residual(z, exact, options), y)
    jac, pieces_jac = jax.vmap(lin, out_axes=-1)(jnp.eye(y.size, dtype=y.dtype))
    diff, static, t_diff = _tangent_part(args, t_args)
    residual = lambda d: _residual(y, eqx.combine(d, static), options, materialise=False)  # noqa: E731
    _, (b, t_pieces) = jax.jvp(residual, (diff,), (t_diff,))
    good = jnp.all(jnp.isfinite(jac))
    safe = jnp.where(good, jac, jnp.eye(y.size, dtype=y.dtype))
    t_y = jnp.where(good, -jnp.linalg.solve(safe, b), jnp.nan)
    t_pieces = jax.tree.map(lambda a, t: t + a @ t_y, pieces_jac, t_pieces)
    return (y, pieces), (t_y, t_pieces)


# -- initial guesses ------------------------------------------------------------------------


def _placement(rod, start: Clamped):
    """Rigid motion (R_g, x_g) taking the canonical placement to the actual start clamp."""
    x_c, frame_c = unloaded_state(rod, 0.0)
    R_g = start.frame @ frame_c.T
    return R_g, start.position - R_g @ x_c


def _free_nodes(rod, length, start, k, twist=0.0, stretch=0.0):
    """Nodes (x, D) at s = jL/k, j = 0..k: the unloaded shape, twisted by `twist` and
    stretched by `stretch` about its axis in proportion to s."""
    R_g, x_g = _placement(rod, start)
    s = jnp.arange(k + 1) * (length / k)
    x_c, frame_c = unloaded_state(rod, s)
    t = s / length
    turn = rz(t * twist)
    x_c = jnp.einsum("kij,kj->ki", turn, x_c) + (t * stretch)[:, None] * jnp.array([0.0, 0.0, 1.0])
    return x_c @ R_g.T + x_g, R_g @ (turn @ frame_c)


def _axial_guess(rod, length, start, end: _EndData, guess_kind: str):
    """(N, M0, twist, stretch): initial wrench and axial deformation of the nodes, from the
    uniform helix with the end's axial extension (or force) and rotation."""
    R_g, x_g = _placement(rod, start)
    axis = R_g[:, 2]
    h0, theta0 = unloaded_observables(rod, length)
    x_free, frame_free = unloaded_state(rod, length)
    x_free, frame_free = R_g @ x_free + x_g, R_g @ frame_free
    loaded, tweezer = end.kind == _LOADED, end.kind == _TWEEZER
    # Loaded: exact wrench (moment about a fixed point is conserved; about the end, the
    # unloaded end is the lever arm).
    point = jnp.where(end.about_end, x_free, end.point)
    loaded_m0 = end.moment - jnp.cross(start.position - point, end.force)
    twist = jnp.where(loaded, 0.0, twist_angle(R_g.T @ end.frame @ frame_free.T @ R_g))
    stretch_clamped = (end.position - start.position) @ axis - h0
    index = jnp.where(tweezer, jnp.array([0, 3]), jnp.array([2, 3]))
    values = jnp.stack([end.force @ axis, 0.0 * h0, h0 + stretch_clamped, theta0 + twist])
    if guess_kind == "helix":
        bulk = bulk_helix_indexed(rod, length, index, values, max_steps=24, light=True)
        force = jnp.where(bulk.ok, bulk.force, 0.0)
        moment = jnp.where(bulk.ok, bulk.moment, 0.0)
        stretch_tweezer = jnp.where(bulk.ok, bulk.extension - h0, 0.0)
    else:
        force, moment, stretch_tweezer = 0.0 * h0, 0.0 * h0, 0.0 * h0
    N = jnp.where(loaded | tweezer, end.force, force * axis)
    M0 = jnp.where(loaded, loaded_m0, moment * axis - jnp.cross(start.position - x_g, N))
    stretch = jnp.where(loaded, 0.0, jnp.where(tweezer, stretch_tweezer, stretch_clamped))
    return N, M0, twist, stretch


def _trajectory_nodes(rod, length, start, N, M0, k, options: _Options, ode_tol):
    """Nodes at s = jL/k from integrating the start wrench (N, M0) (the single-shooting
    trajectory of a guess); the unloaded nodes where that integration fails."""
    sol = options.integrate(
        rod, start.frame.T @ N, start.frame.T @ M0, length, ode_tol, frame0=start.frame, x0=start.position,
        saveat=jnp.arange(k + 1) * (length / k),
    )
    x_free, frame_free = _free_nodes(rod, length, start, k)
    good = sol.ok & jnp.all(jnp.isfinite(sol.x)) & jnp.all(jnp.isfinite(sol.frame))
    return jnp.where(good, sol.x, x_free), jnp.where(good, sol.frame, frame_free)


def _initial(rod, length, start, end, guess, options: _Options, scales, ode_tol):
    """Initial unknown vector and reference nodes."""
    k = options.segments
    if options.continuation > 0:
        x_nodes, frame_nodes = _free_nodes(rod, length, start, k)
        N = M0 = jnp.zeros(3)
    elif guess is None:
        N, M0, twist, stretch = _axial_guess(rod, length, start, end, options.guess_kind)
        x_nodes, frame_nodes = _free_nodes(rod, length, start, k, twist, stretch)
    elif isinstance(guess, BoundaryValueSolution):
        N, M0 = guess.force, guess.moment0
        x_nodes = jnp.concatenate([guess.node_position, guess.end_position[None]])
        frame_nodes = guess.node_frame
    else:
        N, M0 = start.frame @ guess[0], start.frame @ guess[1]
        if k > 1:
            x_nodes, frame_nodes = _trajectory_nodes(rod, length, start, N, M0, k, options, ode_tol)
        else:
            x_nodes, frame_nodes = _free_nodes(rod, length, start, k)
    y = jnp.concatenate([N / scales[1], M0 / scales[2], jnp.zeros(6 * (k - 1))])
    return y, x_nodes[1:k], frame_nodes[1:k]


# -- the solver -----------------------------------------------------------------------------


def _rebase(y, args: _Args, k: int) -> tuple[Array, _Args]:
    """Move the node unknowns into the reference nodes (keeps node rotations small)."""
    _, _, xs, frames = _nodes(y, args, k)
    return y.at[6:].set(0.0), eqx.tree_at(lambda a: (a.ref_x, a.ref_frame), args, (xs[1:], frames[1:]))


# The Jacobian that steers Newton's iteration is integrated at no tighter than this.
_JACOBIAN_ODE_TOL = 1e-6


def _jacobian_tolerance(ode_tol):
    """ODE (rtol, atol) of the Jacobian that steers Newton's iteration: looser than the
    flows' own.  The Jacobian only sets the step (its error makes convergence linear with a
    rate of about its relative error, and Broyden updates recover most of that), while the
    residual -- and so the root -- keeps the full ODE tolerance.  On the spring of
    `benchmarks/bench_finite.py` its six tangent integrations take 25 steps (the stability
    cap of the step) instead of 58 at 1e-8 and 179 at 1e-10."""
    return jnp.maximum(ode_tol, _JACOBIAN_ODE_TOL)


_NOT_SOLVED = (
    "solve_boundary_value: the shooting equations were not solved (invalid input, no "
    "convergence, or residual above tolerance); try continuation=, more segments=, a "
    "better guess=, or throw=False to inspect `result` and `residual`"
)


@functools.partial(jax.jit, static_argnames="throw")
def _solve(rod, length, start, end: _EndData, guess, saveat, tolerances, options: _Options, throw: bool = False):
    dtype = jnp.result_type(float)
    rtol, atol = tolerances[0], tolerances[1]
    valid = jnp.isfinite(length) & (length > 0) & end.finite()
    valid = valid & jnp.all(jnp.isfinite(start.position)) & jnp.all(jnp.isfinite(start.frame))
    if isinstance(guess, tuple):
        valid = valid & jnp.all(jnp.isfinite(guess[0])) & jnp.all(jnp.isfinite(guess[1]))
    # Invalid input (under vmap): solve a harmless problem, return NaN.
    length = jnp.where(valid, length, 1.0)
    harmless_start = Clamped(*unloaded_state(no_gradient(rod), 0.0))
    start = jax.tree.map(lambda a, b: jnp.where(valid, a, b), start, harmless_start)
    end = jax.tree.map(lambda a, b: jnp.where(valid, a, b), end, _end_data(_LOADED, point=jnp.zeros(3, dtype)))
    k = options.segments
    ell = length_scale(rod, length)
    k_scale = stiffness_scale(rod)
    scales = jnp.stack([ell, k_scale / ell**2, k_scale / ell])
    ode_tol = jnp.concatenate([tolerances[2:4], _jacobian_tolerance(tolerances[2:4])])

    y0, ref_x, ref_frame = no_gradient(_initial(rod, length, start, end, guess, options, scales, ode_tol))
    args = _Args(rod, length, start, end, ref_x, ref_frame, scales, ode_tol)
    steps = jnp.zeros((), jnp.int32)
    result = optx.RESULTS.successful
    if options.continuation > 0:
        frozen = no_gradient(args)
        x_free, frame_free = (a[-1] for a in _free_nodes(frozen.rod, frozen.length, frozen.start, 1))

        def step(carry, t):
            y, ref_x, ref_frame, result, steps = carry
            end_t = frozen.end.homotopy(t, x_free, frame_free)
            args_t = eqx.tree_at(lambda a: (a.end, a.ref_x, a.ref_frame), frozen, (end_t, ref_x, ref_frame))
            y, _, _, n = _root(y, args_t, options, rtol, atol)
            y, args_t = _rebase(y, args_t, k)
            return (y, args_t.ref_x, args_t.ref_frame, result, steps + n), None

        ts = jnp.arange(1, options.continuation, dtype=dtype) / options.continuation
        (y0, ref_x, ref_frame, result, steps), _ = jax.lax.scan(step, (y0, ref_x, ref_frame, result, steps), ts)
        args = eqx.tree_at(lambda a: (a.ref_x, a.ref_frame), args, (ref_x, ref_frame))

    # Intermediate homotopy steps need not converge: only the last solve counts.
    y, aux, result, n = _root(y0, args, options, rtol, atol)
    steps = steps + n
    y, (nodes, ends) = _implicit(y, aux, args, options=options)
    (N, M0, xs, frames), (x_end, frame_end, force_end, moment_end) = nodes, ends
    junction_x = (x_end[:-1] - xs[1:]) / scales[0]
    junction_r = gibbs(jnp.swapaxes(frames[1:], -1, -2) @ frame_end[:-1])
    end_r = args.end.residual(x_end[-1], frame_end[-1], force_end[-1], moment_end[-1], scales)
    residual = jnp.max(jnp.abs(jnp.concatenate([junction_x.reshape(-1), junction_r.reshape(-1), end_r])))
    residual = jax.lax.stop_gradient(jnp.where(jnp.isfinite(residual) & valid, residual, jnp.inf))

    out = _observe(args, options, N, M0, xs, frames, saveat, x_end[-1], frame_end[-1])
    nan = lambda a: jnp.where(valid, a, jnp.nan)  # noqa: E731
    sol = BoundaryValueSolution(
        s=out[0],
        x=nan(out[1]),
        frame=nan(out[2]),
        n=nan(out[3]),
        m=nan(out[4]),
        n0=nan(args.start.frame.T @ N),
        m0=nan(args.start.frame.T @ M0),
        force=nan(N),
        moment0=nan(M0),
        end_position=nan(x_end[-1]),
        end_frame=nan(frame_end[-1]),
        end_force=nan(force_end[-1]),
        end_moment=nan(moment_end[-1]),
        node_position=nan(xs),
        node_frame=nan(frames),
        residual=residual,
        result=result,
        num_steps=jnp.asarray(steps, jnp.int32),
        valid_input=valid,
        tolerance=jnp.asarray(10 * atol, dtype),
    )
    if throw:
        sol = eqx.tree_at(lambda s: s.residual, sol, eqx.error_if(sol.residual, ~sol.ok, _NOT_SOLVED))
    return sol


def _observe(args: _Args, options: _Options, N, M0, xs, frames, saveat, x_last, frame_last):
    """(s, x, frame, n, m) at `saveat` (None: at s = L, from the pieces already computed)."""
    k = options.segments
    if saveat is None:
        n_last = frame_last.T @ N
        m_last = frame_last.T @ (M0 - jnp.cross(x_last - args.start.position, N))
        return (args.length[None], x_last[None], frame_last[None], n_last[None], m_last[None])
    piece = args.length / k
    moments = M0 - jnp.cross(xs - args.start.position, N)

    def one(j):
        # Save times outside the piece are clipped to its ends (repeated save times are
        # allowed) and never selected below.
        local = jnp.clip(saveat - j * piece, 0.0, piece)
        sol = options.integrate(
            args.rod, frames[j].T @ N, frames[j].T @ moments[j], piece, args.ode_tol, frame0=frames[j], x0=xs[j],
            saveat=local,
        )
        return sol.x, sol.frame, sol.n, sol.m

    x, frame, n, m = _per_piece(one, jnp.arange(k))
    which = jnp.clip(jnp.floor(saveat / piece).astype(jnp.int32), 0, k - 1)
    idx = jnp.arange(saveat.shape[0])
    return saveat, x[which, idx], frame[which, idx], n[which, idx], m[which, idx]


def solve_boundary_value(
    rod,
    length: ArrayLike,
    *,
    start: Clamped | None = None,
    end: AbstractEnd,
    guess: BoundaryValueSolution | tuple[ArrayLike, ArrayLike] | str | None = None,
    saveat: ArrayLike | None = None,
    segments: int = 1,
    continuation: int = 0,
    method: str = "levenberg-marquardt",
    rtol: float = 1e-10,
    atol: float = 1e-10,
    max_steps: int = 64,
    ode_rtol: float = 1e-10,
    ode_atol: float = 1e-10,
    solver: diffrax.AbstractSolver | None = None,
    max_ode_steps: int = 16_384,
    adjoint: diffrax.AbstractAdjoint | None = None,
    throw: bool = True,
) -> BoundaryValueSolution:
    """Equilibrium of a finite rod clamped at $s = 0$ with a condition at $s = L$.

    **Arguments**

    - `rod`: a `Rod` (or any constitutive law usable by `solve_static`); unbatched.
    - `length`: $L > 0$.
    - `start`: `Clamped(position, frame)` at $s = 0$; default: the canonical placement of the
      unloaded rod (its intrinsic helix with axis $e_z$ through the origin, see
      `axial_ends`).
    - `end`: `Clamped`, `Loaded` or `Tweezer` (module docstring); `axial_ends` builds the
      common spring and tweezer conditions.
    - `guess`: `None` (default) -- the uniform helix with the end's axial extension and
      rotation (or force and rotation) from the bulk equations, exact for a `Loaded` end
      about a fixed point; `"zero"` -- the unloaded rod; a `BoundaryValueSolution` (warm
      start, e.g. the previous point of a curve); or a pair `(n0, m0)` of start wrenches in
      the director frame.  The rotation of a frame condition is known only modulo a full
      turn: to turn an end by more than half a turn from the guess, continue in the
      rotation (`rotation_response`) or warm-start.
    - `saveat`: increasing arc lengths in $[0, L]$ at which to return the centreline, frame
      and wrench (default: $s = L$ only).
    - `segments`: number of shooting pieces $k$ (1: single shooting).  Use more for long
      rods in spatially unstable states (module docstring; README for measured limits).
    - `continuation`: number of homotopy steps from the unloaded rod to the prescribed end
      (0: none; each step is warm-started from the previous).
    - `method`: `"levenberg-marquardt"` (default; robust) or `"newton"` (optimistix Newton:
      cheapest from a good guess).
    - `rtol`, `atol`: root tolerances on the scaled residual (positions in units of
      $\\ell = \\min(L, 1/|\\hat u|)$, forces of $\\bar K/\\ell^2$, moments of $\\bar K/\\ell$,
      frames by the Gibbs vector; $\\bar K$ the mean bending/twisting stiffness);
      `max_steps` per root solve.
    - `ode_rtol`, `ode_atol`, `solver` (default `CommutatorFreeRK4()`, or `MuntheKaasRK`),
      `max_ode_steps`: the integration of each piece.
    - `adjoint`: diffrax adjoint of the integrations: `diffrax.ForwardMode()` (default;
      `jax.jvp`/`jax.jacfwd` through the solve) or `diffrax.DirectAdjoint()` (also
      `jax.grad`/`jax.jacrev`, slower to compile and run).  Derivatives are those of the
      implicit function theorem on the shooting equations.
    - `throw`: raise on failure (`eqx.error_if`); with `throw=False` read `ok`, `result`,
      `residual` -- use it under `jax.vmap`, where an invalid point gives NaN fields and
      `valid_input = False` without spoiling the batch.

    **Errors.** Bad shapes, non-finite concrete values, `length <= 0`, a frame that is not a
    rotation, unknown `method` or `guess`, `segments < 1` raise `ValueError`.

    **Example**

    ```python
    rod = helixrod.Rod(1.0, 1.0, 0.77, uhat=(0.0, 1.0, 0.3))       # a helical spring
    start, end = helixrod.axial_ends(rod, 30.0, extension=12.0, rotation=30 * 1.044)
    sol = helixrod.solve_boundary_value(rod, 30.0, start=start, end=end, segments=4,
                                        saveat=jnp.linspace(0, 30, 200))
    sol.force, sol.x            # reaction force; centreline
    ```
    """
    if solver is None:
        solver = CommutatorFreeRK4()
    if not isinstance(solver, (CommutatorFreeRK4, MuntheKaasRK)):
        raise ValueError(
            "solve_boundary_value: solver must be CommutatorFreeRK4 or MuntheKaasRK: the shooting "
            "equations rely on their exact conservation of the lab wrench"
        )
    adjoint = diffrax.ForwardMode() if adjoint is None else adjoint
    if not isinstance(adjoint, (diffrax.ForwardMode, diffrax.DirectAdjoint)):
        raise ValueError(
            "solve_boundary_value: adjoint must be diffrax.ForwardMode() or diffrax.DirectAdjoint() "
            f"(Newton's method needs forward-mode derivatives of the flow), got {type(adjoint).__name__}"
        )
    if method not in METHODS:
        raise ValueError(f"solve_boundary_value: method must be one of {METHODS}, got {method!r}")
    if isinstance(segments, bool) or not isinstance(segments, (int, np.integer)) or segments < 1:
        raise ValueError(f"solve_boundary_value: segments must be an integer >= 1, got {segments!r}")
    if isinstance(continuation, bool) or not isinstance(continuation, (int, np.integer)) or continuation < 0:
        raise ValueError(f"solve_boundary_value: continuation must be an integer >= 0, got {continuation!r}")
    check_one_rod(rod, "solve_boundary_value")
    if not isinstance(end, AbstractEnd):
        raise ValueError(f"solve_boundary_value: end must be Clamped, Loaded or Tweezer, got {type(end).__name__}")
    if start is None:
        start = Clamped(*unloaded_state(rod, 0.0))
    if not isinstance(start, Clamped):
        raise ValueError(f"solve_boundary_value: start must be Clamped, got {type(start).__name__}")
    for name, cond in (("start", start), ("end", end)):
        if any(leaf.ndim > 2 or (leaf.ndim == 2 and leaf.shape != (3, 3)) for leaf in jax.tree.leaves(cond)):
            raise ValueError(f"solve_boundary_value: {name} must be unbatched (jax.vmap over conditions)")
    dtype = jnp.result_type(float)
    length = jnp.asarray(length, dtype)
    if length.shape != ():
        raise ValueError(f"solve_boundary_value: length must be a scalar, got shape {length.shape}")
    if _is_concrete(length) and not (np.isfinite(float(length)) and float(length) > 0):
        raise ValueError(f"solve_boundary_value: length must be finite and > 0, got {float(length)}")
    guess_kind = "helix"
    if isinstance(guess, str):
        if guess not in ("helix", "zero"):
            raise ValueError(f"solve_boundary_value: guess must be None, 'helix', 'zero', a solution or (n0, m0); got {guess!r}")
        guess_kind, guess = guess, None
    elif isinstance(guess, BoundaryValueSolution):
        if guess.segments != segments:
            guess = (guess.n0, guess.m0)
    elif guess is not None:
        try:
            n0, m0 = (jnp.asarray(g, dtype) for g in guess)
        except (TypeError, ValueError):
            raise ValueError("solve_boundary_value: guess must be None, 'helix', 'zero', a solution or (n0, m0)") from None
        if n0.shape != (3,) or m0.shape != (3,):
            raise ValueError(f"solve_boundary_value: guess (n0, m0) needs shapes (3,), got {n0.shape}, {m0.shape}")
        if _is_concrete(n0, m0) and not (np.all(np.isfinite(np.asarray(n0))) and np.all(np.isfinite(np.asarray(m0)))):
            raise ValueError("solve_boundary_value: guess (n0, m0) must be finite")
        guess = (n0, m0)
    if saveat is not None:
        saveat = jnp.asarray(saveat, dtype)
        if saveat.ndim != 1 or saveat.shape[0] < 1:
            raise ValueError(f"solve_boundary_value: saveat must be a 1-d array of arc lengths, got shape {saveat.shape}")
        if _is_concrete(saveat, length):
            sn = np.asarray(saveat)
            if np.any(np.diff(sn) <= 0) or sn[0] < 0 or sn[-1] > float(length) * (1 + 1e-12):
                raise ValueError(f"solve_boundary_value: saveat must increase strictly within [0, {float(length)}]")
    options = _Options(
        segments=int(segments),
        solver=solver,
        max_ode_steps=int(max_ode_steps),
        adjoint=adjoint,
        method=method,
        max_steps=int(max_steps),
        continuation=int(continuation),
        guess_kind=guess_kind,
    )
    tolerances = jnp.asarray([rtol, atol, ode_rtol, ode_atol], dtype)
    return _solve(rod, length, start, end.end_data(), guess, saveat, tolerances, options, throw=bool(throw))


# -- axial (spring and tweezer) conditions --------------------------------------------------

_PAIRS = {
    ("force", "moment"): _LOADED,
    ("force", "rotation"): _TWEEZER,
    ("extension", "rotation"): _CLAMPED,
}


def axial_ends(
    rod,
    length: ArrayLike,
    *,
    force: ArrayLike | None = None,
    moment: ArrayLike | None = None,
    extension: ArrayLike | None = None,
    rotation: ArrayLike | None = None,
) -> tuple[Clamped, AbstractEnd]:
    """Start and end conditions of a spring (or tweezer) test along the axis of the rod.

    The start is the canonical placement of the unloaded rod: its intrinsic helix
    ($\\hat\\kappa$, $\\hat\\tau$, register $\\hat\\varphi$ from $\\hat u$) placed as
    `helix_frame`/`helix_centreline` place it, axis $e_z$ through the origin (a straight
    untwisted rod: origin, identity frame).  The end is set by two axial controls:

    - `force`, `moment` -> `Loaded(F e_z, M e_z, point=0)`: axial force and moment along the
      axis line (a spring loaded through hooks on its axis; an initial-value problem);
    - `force`, `rotation` -> `Tweezer(R_z(Θ - Θ0) D0(L), F e_z)`: the magnetic tweezer -- end
      frame turned about the axis, axial pull, end position free;
    - `extension`, `rotation` -> `Clamped(R_z(Θ - Θ0) x0(L) + (h - h0) e_z, R_z(Θ - Θ0) D0(L))`:
      grips moved along and turned about the axis.

    $x_0(L)$, $D_0(L)$ are the unloaded end; `extension` $h$ is the axial end-to-end distance
    and `rotation` $\\Theta$ the total end rotation about the axis, as in `spring_compliance`
    (unloaded: $h_0 = L\\hat\\tau/|\\hat u|$, $\\Theta_0 = L|\\hat u|$, so `rotation=Θ0` means
    "not turned"; $F$ along $e_z$, a pull for $\\hat\\tau > 0$).  Scalars, traced allowed.
    """
    given = {n: v for n, v in (("force", force), ("moment", moment), ("extension", extension), ("rotation", rotation)) if v is not None}
    pair = tuple(given)
    if pair not in _PAIRS:
        raise ValueError(f"axial_ends: give one of the pairs {[' and '.join(p) for p in _PAIRS]}, got {list(pair) or 'nothing'}")
    dtype = jnp.result_type(float)
    length = jnp.asarray(length, dtype)
    values = {n: jnp.asarray(v, dtype) for n, v in given.items()}
    for n, v in {**values, "length": length}.items():
        if v.shape != ():
            raise ValueError(f"axial_ends: {n} must be a scalar, got shape {v.shape} (use jax.vmap)")
        if _is_concrete(v) and not np.isfinite(float(v)):
            raise ValueError(f"axial_ends: {n} must be finite, got {float(v)}")
    if _is_concrete(length) and not float(length) > 0:
        raise ValueError(f"axial_ends: length must be > 0, got {float(length)}")
    start = Clamped(*unloaded_state(rod, 0.0))
    end = axial_end_data(rod, length, _PAIRS[pair], [values.get(n, 0.0) for n in ("force", "moment", "extension", "rotation")])
    kind = _PAIRS[pair]
    if kind == _LOADED:
        return start, Loaded(end.force, end.moment, point=end.point)
    if kind == _TWEEZER:
        return start, Tweezer(end.frame, end.force)
    return start, Clamped(end.position, end.frame)


def axial_end_data(rod, length, kind, values) -> _EndData:
    """The end condition of `axial_ends` in internal form, for a (possibly traced) `kind`
    (0 clamped: extension and rotation; 1 loaded: force and moment; 2 tweezer: force and
    rotation) and `values` = (force, moment, extension, rotation)."""
    dtype = jnp.result_type(float)
    force, moment, extension, rotation = (jnp.asarray(v, dtype) for v in values)
    x_end, frame_end = unloaded_state(rod, length)
    h0, theta0 = unloaded_observables(rod, length)
    e3 = jnp.array([0.0, 0.0, 1.0], dtype)
    turn = rz(rotation - theta0)
    kind = jnp.asarray(kind, jnp.int32)
    loaded = kind == _LOADED
    return _EndData(
        kind=kind,
        position=turn @ x_end + (extension - h0) * e3,
        frame=jnp.where(loaded, jnp.eye(3, dtype=dtype), turn @ frame_end),
        force=force * e3,
        moment=moment * e3,
        point=jnp.zeros(3, dtype),
        about_end=jnp.asarray(False),
    )


def wrench_growth_rate(rod, n: ArrayLike, m: ArrayLike) -> Array:
    """Spatial growth rate $\\lambda$ of perturbations of a uniform helix: the largest real
    part of the eigenvalues of the $6\\times 6$ Jacobian of the static Kirchhoff equations
    $(n', m') = (-u\\times n,\\ -u\\times m - e_3\\times n)$, $u = u(m)$, at the constant local
    wrench `(n, m)` (e.g. `helix_equilibria(...).n`, `.m`, or `bulk_helix`).

    $\\lambda > 0$ (a spatially unstable helix) means that errors in a shooting guess grow like
    $e^{\\lambda L}$: from the bulk guess single shooting was measured to converge up to
    $\\lambda L \\approx 3$ and to fail beyond $\\approx 4$ (README), so use
    `segments >= lambda * L / 3`.  `n`, `m` `(..., 3)` broadcast; uses `jnp.linalg.eigvals`
    (CPU).  Not differentiable.
    """
    n, m = jnp.broadcast_arrays(jnp.asarray(n, jnp.result_type(float)), jnp.asarray(m, jnp.result_type(float)))
    e3 = jnp.array([0.0, 0.0, 1.0], n.dtype)

    def rate(w):
        u = rod.twist(w[3:])
        return jnp.concatenate([-jnp.cross(u, w[:3]), -jnp.cross(u, w[3:]) - jnp.cross(e3, w[:3])])

    wrench = jax.lax.stop_gradient(jnp.concatenate([n, m], -1)).reshape(-1, 6)
    jac = jax.vmap(jax.jacfwd(rate))(wrench)
    growth = jnp.max(jnp.real(jnp.linalg.eigvals(jac)), axis=-1)
    return growth.reshape(n.shape[:-1])
