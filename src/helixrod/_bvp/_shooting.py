"""The shooting equations of a finite rod: per-piece flows with a materialised Jacobian,
the residual, the root solve, its implicit derivatives, and the initial guesses.

With `segments = k` the rod is cut into $k$ equal pieces; the unknowns are the lab force
$N$, the lab moment $M_0$ at $s = 0$ and the position and frame ($x_j$, $D_j = \\bar D_j
\\exp\\hat w_j$) of the start of pieces $1..k-1$, and the equations are the continuity of
position and frame at the $k - 1$ junctions plus the end condition: $6k$ equations in $6k$
unknowns ($k = 1$ is single shooting).  The wrench needs no junction condition: the
geometric integrators keep the lab force and the moment about a fixed point exactly (to
round-off), so the wrench at the start of each piece is $(N, M_0 - (x_j - x_0)\\times N)$.
The pieces are integrated in parallel (`vmap`) and the flow of each piece depends, up to a
rigid motion, only on its local start wrench: its $18\\times 6$ Jacobian is computed once per
piece, so a Jacobian costs about six integrations of the whole rod whatever $k$ (and most
root-finder steps need none: Broyden updates).  The root finder steers by the Jacobi fields
of each piece, integrated by equal Runge--Kutta steps (`shooting_jacobian`); the
derivatives of a solution come from `jax.jvp` of the adaptive integration itself, at the
ODE tolerance (`implicit`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float

from .._geometry import unloaded_observables, unloaded_state
from .._lie import RodState, gibbs, rotation_z, so3_exp, tangent, twist_angle
from .._misc import differentiated_part, no_gradient, solve_small_linear
from ._bulk import bulk_helix_at
from ._ends import CONTROL_INDEX, LOADED, TWEEZER, Clamped, EndCondition
from ._options import BoundaryValueOptions
from ._root_finder import LevenbergMarquardtBroyden
from ._variations import flow_variations


def piece_flow(theta, wrench, options: BoundaryValueOptions, ode_tol, ts=None):
    """Integrate one piece from the identity pose at the origin with local start wrench
    `wrench` (6,): the flat (18,) vector (p, R, n_end, m_end); NaN if the solve failed.
    With `ts` `(p,)`, increasing local arc lengths within the piece (repeats allowed): the
    states there instead, `(p, 18)`, by the dense output of the same integration."""
    rod, piece = theta
    sol = options.integrate(rod, wrench[:3], wrench[3:], piece, ode_tol, saveat=ts)
    out = jnp.concatenate([sol.x, sol.frame.reshape(-1, 9), sol.n, sol.m], -1)
    return jnp.where(sol.ok, out[-1] if ts is None else out, jnp.nan)


def flow_and_jacobian(theta, wrench, options: BoundaryValueOptions, ode_tol, theta_of=None, ts_of=None):
    """One piece's flow (`piece_flow`: end position, frame, force and moment in the start
    frame) and its derivatives `(6, 18)` along the six local start wrenches; `theta` = (rod,
    piece length), `ode_tol` = (rtol, atol) of the tangent integrations.  With `theta_of` (a
    function from a flat vector to (rod, piece length)), `theta` is such a vector `(P,)`
    and the derivatives along its entries follow the six: `(6 + P, 18)` from one
    integration.  With `ts_of` (a function from the piece length to local arc lengths
    `(p,)`, `piece_flow`'s `ts`), the states there and their derivatives, `(p, 18)` and
    `(6 + P, p, 18)`."""
    if theta_of is None:
        theta_of, theta = (lambda _, fixed=theta: fixed), jnp.zeros(0, wrench.dtype)

    def one(w, q):
        rod_and_piece = theta_of(q)
        return piece_flow(rod_and_piece, w, options, ode_tol, None if ts_of is None else ts_of(rod_and_piece[1]))

    basis = jnp.eye(6 + theta.size, dtype=wrench.dtype)
    flows, jacobian = jax.vmap(lambda e: jax.jvp(one, (wrench, theta), (e[:6], e[6:])))(basis)
    return flows[0], jacobian


def flow_jacobian(theta, wrench, options: BoundaryValueOptions, ode_tol, theta_of=None):
    """The derivatives of `flow_and_jacobian` alone."""
    return flow_and_jacobian(theta, wrench, options, ode_tol, theta_of)[1]


def per_piece(fn, xs):
    """`jax.vmap(fn)(xs)` over the pieces (the leading axis of every leaf of `xs`); a single
    piece without `vmap`: a batched integration loop was measured to cost about twice as
    much."""
    if jax.tree.leaves(xs)[0].shape[0] == 1:
        return jax.tree.map(lambda a: a[None], fn(jax.tree.map(lambda a: a[0], xs)))
    return jax.vmap(fn)(xs)


@eqx.filter_custom_jvp
def _flows(wrench, theta, ode_tol, *, options):
    """Flows of all pieces, `(k, 18)`, from their local start wrenches `(k, 6)`."""
    return per_piece(lambda w: piece_flow(theta, w, options, ode_tol), wrench)


@_flows.def_jvp
def _flows_jvp(primals, tangents, *, options):
    # The Jacobian with respect to the start wrench depends on primals only: computed once
    # per piece (six tangent integrations at the ODE tolerance, all pieces in parallel) and
    # reused by every tangent direction -- a Jacobian of k pieces costs what one of single
    # shooting does.
    wrench, theta, ode_tol = primals
    t_wrench, t_theta, _ = tangents
    out = per_piece(lambda w: piece_flow(theta, w, options, ode_tol), wrench)  # (k, 18)
    jac = per_piece(lambda w: flow_jacobian(theta, w, options, ode_tol), wrench)  # (k, 6, 18)
    t_out = jnp.zeros_like(out)
    if t_wrench is not None:
        t_out = t_out + jnp.einsum("kij,ki->kj", jac, t_wrench)
    if t_theta is not None and jax.tree.leaves(t_theta):
        diff, static, t_diff = differentiated_part(theta, t_theta)
        flows = lambda d: per_piece(lambda w: piece_flow(eqx.combine(d, static), w, options, ode_tol), wrench)  # noqa: E731
        t_out = t_out + jax.jvp(flows, (diff,), (t_diff,))[1]
    return out, t_out


@eqx.filter_custom_jvp
def _given_flows(wrench, theta, flows, jacobian):
    """`flows` `(k, 18)`, already integrated from `wrench` `(k, 6)` with parameters `theta`
    `(P,)`, differentiated in both by their Jacobian `(k, 6 + P, 18)` (`flow_jacobian`): a
    linearisation of the shooting equations with no integration in it
    (`shooting_jacobian`, `implicit`)."""
    return flows


@_given_flows.def_jvp
def _given_flows_jvp(primals, tangents):
    wrench, theta, flows, jacobian = primals
    t_wrench, t_theta = tangents[:2]
    t_flows = jnp.zeros_like(flows)
    if t_wrench is not None:
        t_flows = t_flows + jnp.einsum("kij,ki->kj", jacobian[:, :6], t_wrench)
    if t_theta is not None:
        t_flows = t_flows + jnp.einsum("kij,i->kj", jacobian[:, 6:], t_theta)
    return flows, t_flows


class ShootingArgs(eqx.Module):
    """Traced data of the shooting equations."""

    rod: object
    length: Array
    start: Clamped
    end: EndCondition
    ref_x: Array  # (k-1, 3) reference node positions
    ref_frame: Array  # (k-1, 3, 3) reference node frames
    scales: Array  # (ell, force scale, moment scale)
    ode_tol: Array  # (rtol, atol) of the flows


def nodes_of(y, args: ShootingArgs, k: int):
    """(N, M0, start positions `(k, 3)`, start frames `(k, 3, 3)`) of the pieces at `y`."""
    N = y[:3] * args.scales[1]
    M0 = y[3:6] * args.scales[2]
    z = y[6:].reshape(k - 1, 6)
    xs = jnp.concatenate([args.start.position[None], args.ref_x + z[:, :3] * args.scales[0]], 0)
    frames = jnp.concatenate([args.start.frame[None], args.ref_frame @ so3_exp(z[:, 3:])], 0)
    return N, M0, xs, frames


def _local_wrenches(y, args: ShootingArgs, k: int):
    """The nodes of the pieces at `y` (`nodes_of`) and each piece's start wrench `(k, 6)` in
    its own frame."""
    N, M0, xs, frames = nodes_of(y, args, k)
    moments = M0[None] - jnp.cross(xs - args.start.position[None], N[None])
    local = jnp.concatenate([jnp.einsum("kji,j->ki", frames, N), jnp.einsum("kji,kj->ki", frames, moments)], -1)
    return (N, M0, xs, frames), local


def _pieces(y, args: ShootingArgs, options: BoundaryValueOptions, materialise: bool = True, flows_of=None, saveat=None):
    """Start nodes and lab end states of every piece, the flows `(k, 18)` and the local
    states at `saveat` `(k, p, 18)` (`saved_states`; None where `saveat` is None).
    `materialise`: differentiate the flows through their per-piece Jacobian (`_flows`; for
    the many directions of a Newton step) or directly (for the few directions of a
    parameter derivative); `flows_of`: the flows as a function of the local start wrenches
    instead (`_given_flows`); `saveat` (not differentiated): each piece's integration also
    saves at the points, by its dense output."""
    k = options.segments
    nodes, local = _local_wrenches(y, args, k)
    N, M0, xs, frames = nodes
    piece = args.length / k
    theta = (args.rod, piece)
    saved = None
    if flows_of is not None:
        flows = flows_of(local)
    elif saveat is not None:

        def one(wrench_and_index):
            wrench, j = wrench_and_index
            return piece_flow(theta, wrench, options, args.ode_tol, end_and_saved_times(saveat, piece, j))

        states = per_piece(one, (local, jnp.arange(k)))  # (k, p + 1, 18): the end last
        flows, saved = states[:, -1], states[:, :-1]
    elif materialise:
        flows = _flows(local, theta, args.ode_tol, options=options)
    else:
        flows = per_piece(lambda w: piece_flow(theta, w, options, args.ode_tol), local)
    p, R, n_end, m_end = flows[:, :3], flows[:, 3:12].reshape(k, 3, 3), flows[:, 12:15], flows[:, 15:]
    x_end = xs + jnp.einsum("kij,kj->ki", frames, p)
    frame_end = frames @ R
    ends = (x_end, frame_end, jnp.einsum("kij,kj->ki", frame_end, n_end), jnp.einsum("kij,kj->ki", frame_end, m_end))
    return (N, M0, xs, frames), ends, flows, saved


def residual_and_flows(y, args: ShootingArgs, options: BoundaryValueOptions, materialise: bool = True, flows_of=None, saveat=None):
    """The 6k shooting equations; aux: ((nodes, ends), flows, saved) (`_pieces`)."""
    nodes, ends, flows, saved = _pieces(y, args, options, materialise, flows_of, saveat)
    _, _, xs, frames = nodes
    x_end, frame_end, force_end, moment_end = ends
    junction_x = (x_end[:-1] - xs[1:]) / args.scales[0]
    junction_r = gibbs(jnp.swapaxes(frames[1:], -1, -2) @ frame_end[:-1])
    end = args.end.residual(x_end[-1], frame_end[-1], force_end[-1], moment_end[-1], args.scales)
    residual = jnp.concatenate([jnp.concatenate([junction_x, junction_r], -1).reshape(-1), end])
    return residual, ((nodes, ends), flows, saved)


def shooting_residual(y, args: ShootingArgs, options: BoundaryValueOptions, materialise: bool = True):
    """The 6k shooting equations; aux: the nodes and end states."""
    residual, (pieces, *_) = residual_and_flows(y, args, options, materialise)
    return residual, pieces


# Steps per radian of the Jacobi fields that steer the root finder (`flow_variations`):
# coarse, because a Jacobian only sets the steps.  Measured on the clamped spring and the
# 50-point curve of `benchmarks/bench_finite.py` (tolerances 1e-8 and 1e-10): 12, 6, 4 and 3
# steps per radian took the same root-finder steps (5 and 6; 197 and 246 for the curve), 2
# one more; the curve's solves alone 53-57 ms at 12, 25-37 ms at 4.
STEERING_STEPS_PER_RADIAN = 4


def shooting_jacobian(y, args: ShootingArgs, options: BoundaryValueOptions, flows):
    """The Jacobian of the shooting equations at `y` that steers the root finder, `(6k,
    6k)`, and that of the pieces (nodes, ends; last axis `6k`), given the `flows` `(k, 18)`
    already integrated at `y`: only the flows' derivatives are integrated, as Jacobi fields
    by equal Runge--Kutta steps (`linearised_equations` at `STEERING_STEPS_PER_RADIAN`), not
    the flows again, whatever the ODE tolerance: a Jacobian only sets the steps (its error
    makes convergence linear with a rate of about its relative error, and Broyden updates
    recover most of that), while the residual -- and so the root -- keeps the full ODE
    tolerance."""
    equations = linearised_equations(y, args, options, flows, STEERING_STEPS_PER_RADIAN)
    return _jacobian_columns(lambda z: equations(z, args), y)


def linearised_equations(y, args: ShootingArgs, options: BoundaryValueOptions, flows, per_radian: float):
    """The shooting equations linearised at `y`, as a function `(z, args) -> (residual,
    pieces)` that integrates nothing: the `flows` `(k, 18)` already integrated at `y` and
    their derivatives along the pieces' start wrenches, integrated here once as Jacobi fields
    (`flow_variations`, `per_radian` equal steps per radian).  Its value at `y` is the
    residual of the flows; its derivatives in `z`, and in anything of `args` that the flows
    do not depend on (the end condition), are the equations' Jacobian to the Jacobi fields'
    accuracy."""
    k = options.segments
    rod, piece = args.rod, args.length / k
    _, local = _local_wrenches(y, args, k)
    jacobian = per_piece(lambda w: flow_variations(rod, w, piece, options.max_ode_steps, per_radian), local)  # (k, 6, 18)
    no_theta = jnp.zeros(0, y.dtype)

    def equations(z, args):
        r, (pieces, *_) = residual_and_flows(z, args, options, flows_of=lambda w: _given_flows(w, no_theta, flows, jacobian))
        return r, pieces

    return equations


def _jacobian_columns(residual, y):
    """The Jacobians of both outputs of `residual(y)` (an integration-free linearisation
    through `_given_flows`), one column per entry of `y` on the last axis."""
    _, lin = jax.linearize(residual, y)
    return jax.vmap(lin, out_axes=-1)(jnp.eye(y.size, dtype=y.dtype))


def root(y0, args: ShootingArgs, options: BoundaryValueOptions, saveat=None):
    """Solve the shooting equations (no derivatives: see `implicit`).  Returns the root,
    the pieces (nodes, ends), the flows and the local states at `saveat` there
    (`_pieces`), the largest scaled residual, the result code and the number of steps.
    Each step integrates the flows once, saving at `saveat` by the dense output of that
    integration (so the states at the root need no integration of their own); a fresh
    Jacobian integrates only their derivatives (`shooting_jacobian`)."""
    fn = lambda y, a: residual_and_flows(y, a, options, materialise=False, saveat=saveat)  # noqa: E731
    jacobian = lambda y, a, aux: shooting_jacobian(y, a, options, aux[1])[0]  # noqa: E731
    solver = LevenbergMarquardtBroyden(atol=options.atol, damped=options.method != "newton", jacobian=jacobian)
    y0, args, saveat = no_gradient((y0, args, saveat))
    sol = optx.root_find(fn, solver, y0, args, has_aux=True, max_steps=options.max_steps, throw=False)
    residual = jnp.max(jnp.abs(sol.stats["residual"]))
    pieces, flows, saved = sol.aux
    return sol.value, pieces, flows, saved, residual, sol.result, sol.stats["num_steps"]


def saved_local_times(saveat, piece, j):
    """The arc lengths `saveat` local to piece `j` (of length `piece`), clipped to it: points
    outside the piece land on its ends, where `saved_states` never selects them."""
    return jnp.clip(saveat - j * piece, 0.0, piece)


def end_and_saved_times(saveat, piece, j):
    """`saved_local_times`, then the piece's end: one integration gives both the states at
    the saved points and the flow."""
    return jnp.append(saved_local_times(saveat, piece, j), piece)


def saved_states(nodes, states, saveat, piece):
    """(x, frame, n, m) at `saveat` `(p,)` (lab centreline and frame, director-frame wrench)
    from the pieces' start `nodes` (`nodes_of`) and their local states at every saved point
    `(k, p, 18)` (`piece_flow` at `saved_local_times`): each point from the piece it lies in."""
    _, _, xs, frames = nodes
    which = jnp.clip(jnp.floor(saveat / piece).astype(jnp.int32), 0, xs.shape[0] - 1)
    local = states[which, jnp.arange(saveat.shape[0])]
    x = xs[which] + jnp.einsum("pij,pj->pi", frames[which], local[:, :3])
    frame = frames[which] @ local[:, 3:12].reshape(-1, 3, 3)
    return x, frame, local[:, 12:15], local[:, 15:]


@eqx.filter_custom_jvp
def implicit(y, pieces, flows, saved, args, saveat, *, options):
    """The root `y` of the shooting equations at `args`, the `pieces` there and the states
    at `saveat` (`saved_states` of the local states `saved` that the root finder's last
    integration saved, `root`; None where `saveat` is None), with the derivatives of
    the implicit function theorem: $\\dot y = -J^{-1}\\,\\partial_\\theta F\\,\\dot\\theta$ and
    $\\dot P = P_y\\dot y + \\partial_\\theta P\\,\\dot\\theta$ (the states likewise), with the
    Jacobians $J = F_y$, $P_y$, $\\partial_\\theta F$ and $\\partial_\\theta P$ from the `flows`
    there and their derivatives along the six start wrenches and every differentiated scalar
    of the rod and the length, integrated together at the ODE tolerance itself (the root
    solve steers with looser ones; `flow_and_jacobian`), the states at the saved points and
    their derivatives by the dense output of that same integration: one integration of each
    piece, whatever the number of tangent directions.  (Not `optimistix.ImplicitAdjoint`:
    its linear solve raises on a non-finite input, so one failed point would abort a
    differentiated batch; here a failed point gets NaN derivatives.  Nor a derivative of
    the saved states' own integration: a differentiated copy of the integrator the more in
    the program: a `jax.jacfwd` of a solve with 25 saved points compiled in 11.5 s of XLA
    with it, 7.7 s without; the shape fit of `benchmarks/bench_finite.py` 17.7-18.0 -> 14.5-15.3 s
    at its first call, 74-79 -> 53-55 ms later, 2 cores.)"""
    observed = None if saveat is None else saved_states(pieces[0], saved, saveat, args.length / options.segments)
    return y, pieces, observed


@implicit.def_jvp
def _implicit_jvp(primals, tangents, *, options):
    y, pieces, flows, saved, args, saveat = primals
    t_args, t_saveat = tangents[4], tangents[5]
    if t_args is None or not jax.tree.leaves(t_args):
        out = implicit(y, pieces, flows, saved, args, saveat, options=options)
        t_out = jax.tree.map(jnp.zeros_like, out)
    else:
        out, t_out = _implicit_tangents(y, pieces, flows, args, saveat, t_args, options)
    if saveat is not None and t_saveat is not None:  # a saved point moves along the rod
        rates = _state_rates(out[2], args.rod)
        t_observed = jax.tree.map(lambda t, rate: t + rate * t_saveat.reshape((-1,) + (1,) * (rate.ndim - 1)), t_out[2], rates)
        t_out = (t_out[0], t_out[1], t_observed)
    return out, t_out


def _implicit_tangents(y, pieces, flows, args, saveat, t_args, options: BoundaryValueOptions):
    k = options.segments
    diff, rest, t_diff = differentiated_part(args, t_args)
    # The flows depend on the arguments through the start wrenches and through the rod and
    # the length only: their Jacobian along those scalars is integrated with the wrench one.
    q, unravel = ravel_pytree((diff.rod, diff.length))
    # Nothing of the rod or the length differentiated (only the ends): an empty vector, of
    # the solution's type (ravel_pytree makes it float32, and jvp then meets float64 tangents).
    q = q.astype(y.dtype)

    def theta_of(q):
        rod, length = unravel(q)
        return eqx.combine(rod, rest.rod), eqx.combine(length, rest.length) / k

    _, local = _local_wrenches(y, args, k)
    if saveat is None:
        jacobian = per_piece(lambda w: flow_jacobian(q, w, options, args.ode_tol, theta_of), local)  # (k, 6 + P, 18)
        saved = None
    else:
        # The saved points and the piece's end in one integration (the end last).
        def one(wrench_and_index):
            wrench, j = wrench_and_index
            ts_of = lambda piece: end_and_saved_times(saveat, piece, j)  # noqa: E731
            return flow_and_jacobian(q, wrench, options, args.ode_tol, theta_of, ts_of)

        states, state_jacobian = per_piece(one, (local, jnp.arange(k)))  # (k, p + 1, 18), (k, 6 + P, p + 1, 18)
        jacobian = state_jacobian[:, :, -1]
        saved = (states[:, :-1].reshape(k, -1), state_jacobian[:, :, :-1].reshape(k, state_jacobian.shape[1], -1))

    def residual(z, d):
        theta = ravel_pytree((d.rod, d.length))[0]
        given = lambda w: _given_flows(w, theta, flows, jacobian)  # noqa: E731
        a = eqx.combine(d, rest)
        r, (pieces, *_) = residual_and_flows(z, a, options, flows_of=given)
        observed = None
        if saved is not None:
            nodes, local_z = _local_wrenches(z, a, k)
            observed = saved_states(nodes, _given_flows(local_z, theta, *saved).reshape(k, -1, 18), saveat, a.length / k)
        return r, (pieces, observed)

    (_, (_, observed)), (b, t_rest) = jax.jvp(lambda d: residual(y, d), (diff,), (t_diff,))
    jac, rest_jac = _jacobian_columns(lambda z: residual(z, diff), y)
    good = jnp.all(jnp.isfinite(jac))
    safe = jnp.where(good, jac, jnp.eye(y.size, dtype=y.dtype))
    # Linear in the tangent `b` (`solve_small_linear`): reverse mode transposes this rule, and
    # `solve_small`'s joint elimination of [A | b] is not linear in b.
    t_y = jnp.where(good, -solve_small_linear(safe, b), jnp.nan)
    t_pieces, t_observed = jax.tree.map(lambda a, t: t + a @ t_y, rest_jac, t_rest)
    return (y, pieces, observed), (t_y, t_pieces, t_observed)


def _state_rates(observed, rod):
    """d/ds of the saved (x, frame, n, m): the static Kirchhoff equations' velocity
    (`tangent` of the body twist $(u, e_3)$) at each point."""

    def rates(x, frame, n, m):
        velocity = tangent(RodState(n, m, frame, x), rod.twist(m), jnp.asarray([0.0, 0.0, 1.0], n.dtype))
        return velocity.x, velocity.frame, velocity.n, velocity.m

    return jax.vmap(rates)(*observed)


def rebase(y, args: ShootingArgs, k: int) -> tuple[Array, ShootingArgs]:
    """Move the node unknowns into the reference nodes (keeps node rotations small)."""
    _, _, xs, frames = nodes_of(y, args, k)
    return y.at[6:].set(0.0), eqx.tree_at(lambda a: (a.ref_x, a.ref_frame), args, (xs[1:], frames[1:]))


# -- initial guesses ------------------------------------------------------------------------


class WarmStart(eqx.Module):
    """A start from a previous solution of the same number of pieces: the lab force, the
    lab moment at $s = 0$ and the start position and frame of each piece."""

    force: Float[Array, "3"]
    moment0: Float[Array, "3"]
    node_position: Float[Array, "k 3"]
    node_frame: Float[Array, "k 3 3"]


def _placement(rod, start: Clamped):
    """Rigid motion (R_g, x_g) taking the canonical placement to the actual start clamp."""
    x_c, frame_c = unloaded_state(rod, 0.0)
    R_g = start.frame @ frame_c.T
    return R_g, start.position - R_g @ x_c


def free_nodes(rod, length, start, k, twist=0.0, stretch=0.0):
    """Nodes (x, D) at s = jL/k, j = 0..k: the unloaded shape, twisted by `twist` and
    stretched by `stretch` about its axis in proportion to s."""
    R_g, x_g = _placement(rod, start)
    s = jnp.arange(k + 1) * (length / k)
    x_c, frame_c = unloaded_state(rod, s)
    t = s / length
    turn = rotation_z(t * twist)
    e3 = jnp.array([[0.0, 0.0, 1.0]])
    x_c = jnp.einsum("kij,kj->ki", turn, x_c) + (t * stretch)[:, None] * e3
    return x_c @ R_g.T + x_g[None], jnp.einsum("ij,kjl->kil", R_g, turn @ frame_c)


def _axial_guess(rod, length, start, end: EndCondition, guess_kind: str, bulk=None):
    """(N, M0, twist, stretch): initial wrench and axial deformation of the nodes, from the
    uniform helix with the end's axial extension (or force) and rotation -- the end's
    `rotation` where it is known (whole turns included), else its frame's twist, within half a
    turn of the unloaded end's -- or `bulk`: that helix already solved at the end's controls
    (e.g. a response curve's own prediction)."""
    R_g, x_g = _placement(rod, start)
    axis = R_g[:, 2]
    h0, theta0 = unloaded_observables(rod, length)
    x_free, frame_free = unloaded_state(rod, length)
    x_free, frame_free = R_g @ x_free + x_g, R_g @ frame_free
    loaded, tweezer = end.kind == LOADED, end.kind == TWEEZER
    # Loaded: exact wrench (moment about a fixed point is conserved; at the end or a hook
    # attached to it, the unloaded end's is the lever arm).
    point = jnp.where(end.about_end, x_free + frame_free @ end.hook, end.point)
    loaded_m0 = end.moment - jnp.cross(start.position - point, end.force)
    wrapped = twist_angle(R_g.T @ end.frame @ frame_free.T @ R_g)
    twist = jnp.where(loaded, 0.0, jnp.where(jnp.isfinite(end.rotation), end.rotation - theta0, wrapped))
    stretch_clamped = (end.position - start.position) @ axis - h0
    # A loaded end needs no bulk solve; the clamped controls stand in for its index.
    index = jnp.asarray(CONTROL_INDEX)[jnp.where(loaded, 0, end.kind)]
    values = jnp.stack([end.force @ axis, 0.0 * h0, h0 + stretch_clamped, theta0 + twist])
    if guess_kind == "helix":
        if bulk is None:
            bulk = bulk_helix_at(rod, length, index, values, max_steps=24, light=True)
        force = jnp.where(bulk.ok, bulk.force, 0.0)
        moment = jnp.where(bulk.ok, bulk.moment, 0.0)
        stretch_tweezer = jnp.where(bulk.ok, bulk.extension - h0, 0.0)
    else:
        force, moment, stretch_tweezer = 0.0 * h0, 0.0 * h0, 0.0 * h0
    N = jnp.where(loaded | tweezer, end.force, force * axis)
    M0 = jnp.where(loaded, loaded_m0, moment * axis - jnp.cross(start.position - x_g, N))
    stretch = jnp.where(loaded, 0.0, jnp.where(tweezer, stretch_tweezer, stretch_clamped))
    return N, M0, twist, stretch


def default_warm_start(rod, length, start, end: EndCondition, k: int, guess_kind: str, bulk=None) -> WarmStart:
    """The default guess (`_axial_guess`, `bulk` as there, and the nodes it deforms) as a
    `WarmStart`."""
    N, M0, twist, stretch = _axial_guess(rod, length, start, end, guess_kind, bulk)
    xs, frames = free_nodes(rod, length, start, k, twist, stretch)
    return WarmStart(N, M0, xs[:k], frames[:k])


def _trajectory_nodes(rod, length, start, N, M0, k, options: BoundaryValueOptions, ode_tol):
    """Nodes at s = jL/k from integrating the start wrench (N, M0) (the single-shooting
    trajectory of a guess); the unloaded nodes where that integration fails."""
    sol = options.integrate(
        rod, start.frame.T @ N, start.frame.T @ M0, length, ode_tol, frame0=start.frame, x0=start.position,
        saveat=jnp.arange(k + 1) * (length / k),
    )
    x_free, frame_free = free_nodes(rod, length, start, k)
    good = sol.ok & jnp.all(jnp.isfinite(sol.x)) & jnp.all(jnp.isfinite(sol.frame))
    return jnp.where(good, sol.x, x_free), jnp.where(good, sol.frame, frame_free)


def warm_start_of(rod, length, start, end, guess, options: BoundaryValueOptions, guess_kind: str, ode_tol) -> WarmStart:
    """`guess` -- `None` (the default guess of `guess_kind`), a `WarmStart`, or a pair
    `(n0, m0)` of start wrenches (director frame) -- as a `WarmStart` of
    `options.segments` pieces.  Eager callers convert their guess with it before `solve`, so
    that every guess reaches the large solve program in the same form (one compilation)."""
    k = options.segments
    if isinstance(guess, WarmStart):
        return guess
    if guess is None:
        return default_warm_start(rod, length, start, end, k, guess_kind)
    N, M0 = start.frame @ guess[0], start.frame @ guess[1]
    if k > 1:
        x_nodes, frame_nodes = _trajectory_nodes(rod, length, start, N, M0, k, options, ode_tol)
    else:
        x_nodes, frame_nodes = free_nodes(rod, length, start, k)
    return WarmStart(N, M0, x_nodes[:k], frame_nodes[:k])


def initial(rod, length, start, end, guess, options: BoundaryValueOptions, guess_kind: str, scales, ode_tol):
    """Initial unknown vector and reference nodes (`guess` as `warm_start_of`; the unloaded
    rod under `continuation`)."""
    k = options.segments
    if options.continuation > 0:
        x_nodes, frame_nodes = free_nodes(rod, length, start, k)
        N = M0 = jnp.zeros(3)
    else:
        warm = warm_start_of(rod, length, start, end, guess, options, guess_kind, ode_tol)
        N, M0, x_nodes, frame_nodes = warm.force, warm.moment0, warm.node_position, warm.node_frame
    y = jnp.concatenate([N / scales[1], M0 / scales[2], jnp.zeros(6 * (k - 1))])
    return y, x_nodes[1:k], frame_nodes[1:k]


def _complete_elliptic(m: float) -> tuple[float, float]:
    """(K(m), E(m)), the complete elliptic integrals of parameter m in [0, 1), by the
    arithmetic-geometric mean (Abramowitz & Stegun 17.6)."""
    # E = K (1 - sum_n 2^(n-1) c_n^2), c_0^2 = m, c_(n+1) = (a_n - b_n) / 2.
    a, b, total, power = 1.0, float(np.sqrt(1.0 - m)), 0.5 * m, 1.0
    while abs(a - b) > 1e-15 * a:
        a, b, c = 0.5 * (a + b), float(np.sqrt(a * b)), 0.5 * (a - b)
        total += power * c * c
        power *= 2.0
    K = np.pi / (2.0 * a)
    return K, K * (1.0 - total)


def buckled_guess(rod, length, start: Clamped, end: EndCondition, bending: float):
    """The start wrench `(n0, m0)` (director frame) of the first buckled mode of a rod whose
    clamped ends are brought closer than its length, or `None` where they are not.

    The planar inflexional elastica of bending stiffness `bending` between parallel clamps
    (Love, *Treatise*, sec. 263): with $k^2 = m$, its chord is $L(2E(m)/K(m) - 1)$, its
    compressive force $P = B(4K(m)/L)^2$ and the moment at a clamp $B\\,2k\\sqrt{P/B}$; it bends
    about the start frame's softest axis $d_1$ (the first stiffness is the smallest).  A
    guess, not a solution: exact for an intrinsically straight isotropic rod with parallel
    clamps, and a symmetry-breaking start for any other rod (concrete inputs)."""
    chord = np.asarray(end.position - start.position, float)
    ratio = float(np.linalg.norm(chord)) / float(length)
    if not (-0.99 < ratio < 1.0 - 1e-9):
        return None
    axis = chord / max(np.linalg.norm(chord), 1e-300)
    lo, hi = 0.0, 1.0 - 1e-15  # 2E/K - 1 falls from 1 to -1 on [0, 1)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        K, E = _complete_elliptic(mid)
        lo, hi = (mid, hi) if 2.0 * E / K - 1.0 > ratio else (lo, mid)
    K, _ = _complete_elliptic(0.5 * (lo + hi))
    force = bending * (4.0 * K / float(length)) ** 2
    frame = np.asarray(start.frame, float)
    about = frame[:, 0] - (frame[:, 0] @ axis) * axis
    if np.linalg.norm(about) < 1e-6:
        about = frame[:, 1] - (frame[:, 1] @ axis) * axis
    about = about / np.linalg.norm(about)
    N = -force * axis
    M0 = bending * 2.0 * np.sqrt(0.5 * (lo + hi)) * np.sqrt(force / bending) * about
    dtype = np.asarray(start.frame).dtype
    return (jnp.asarray(frame.T @ N, dtype), jnp.asarray(frame.T @ M0, dtype))
