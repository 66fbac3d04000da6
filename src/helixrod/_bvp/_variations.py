"""Jacobi fields of a piece of rod: how its end moves when its start wrench changes, by equal
classical Runge--Kutta steps of the linearised static Kirchhoff equations beside the
solution.  The stability test builds its transfer matrices from them (`_stability`), and the
shooting solve steers its root finder with them (`flow_variations`, `_shooting`).

Why equal steps of their own rather than derivatives of the adaptive Lie-group integration:
the adaptive steps follow the solution, not its variations (on a straight rod the solution
is exact in one step and the variations are not), and `jax.jvp` of those steps in six
directions differentiates their exponential maps: ~4 us a step against ~0.7 us here, and
about half of the shooting solve's compiled program (measured: its XLA compilation 8.0 ->
4.2 s and tracing 2.7 -> 1.4 s on one core when the root finder's Jacobian came from here).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .._kirchhoff import linearised_rate
from .._lie import hat
from .._rod import Rod
from ._rotation import RotationCount, advance, start_count

#: Steps per unit of (linearised rate + |u|) x length.  Measured on Greenhill's shaft (the
#: stability test, 16 pieces), the relative error of its critical twist at 24 / 20 / 12 / 8
#: steps per radian: -6e-8 / -5e-8 / 2.8e-7 / 1.3e-6 (the Lie-group steps these replaced,
#: differentiated in six directions: 1.8e-7 at 12); with an adaptive integration the
#: variations of a straight rod were 2e-4 off (a clamped twisted rod's critical moment).
STEPS_PER_RADIAN = 12

#: The fewest steps of a piece.
MIN_STEPS = 4

#: The relative error of a critical load found by the stability test at `STEPS_PER_RADIAN`
#: (Greenhill's shaft above); it falls as the fourth power of the steps (x 4.7 at 8).
ERROR_AT_STEPS_PER_RADIAN = 2.8e-7

#: The fewest steps per radian of `steps_per_radian` (the root finder's are as coarse).
FEWEST_STEPS_PER_RADIAN = 4


def steps_per_radian(rtol) -> Array:
    """Steps per radian of Jacobi fields whose error is at most half the relative ODE
    tolerance `rtol` of the solution they vary: `STEPS_PER_RADIAN` (error 2.8e-7) for
    tolerances up to twice that error, fewer for looser ones, as RK4's error $\\propto$
    steps$^{-4}$, down to `FEWEST_STEPS_PER_RADIAN` (error ~2e-5).  A test need not be more
    accurate than the state it tests.  Measured: Greenhill's critical twist 2.8e-7 off at
    `rtol` 1e-10 and 1e-7, 6.3e-7 at 1e-6 (fewer steps), 3.4e-6 at 1e-5 and looser (its
    pieces' `MIN_STEPS`); the stability test of the clamped spring of
    `benchmarks/bench_finite.py` at `rtol` 1e-4 0.38 ms instead of 0.53 ms, its margin the
    same to 1.3e-8."""
    scale = (2.0 * ERROR_AT_STEPS_PER_RADIAN / jnp.asarray(rtol)) ** 0.25
    return jnp.clip(STEPS_PER_RADIAN * scale, FEWEST_STEPS_PER_RADIAN, STEPS_PER_RADIAN)


def variation_steps(rod, n0, m0, length, max_steps: int, per_radian: float = STEPS_PER_RADIAN) -> Int[Array, ""]:
    """The number of equal steps of `piece_variations` for a piece of length `length` with
    local start wrench (`n0`, `m0`): `per_radian` per unit of the fastest rate at which its
    variations turn or grow (`linearised_rate`) plus that of its frame ($|u|$), between
    `MIN_STEPS` and `max_steps`."""
    rate = linearised_rate(rod, n0, m0) + jnp.linalg.norm(rod.twist(m0))
    return jnp.clip(jnp.ceil(per_radian * rate * length), MIN_STEPS, max_steps).astype(jnp.int32)


def _start_directions(dtype) -> tuple[Array, Array]:
    """The six variations of a local start wrench $(\\delta n, \\delta m)$ as the columns of
    their force and moment parts, `(3, 6)` each."""
    eye, zero = jnp.eye(3, dtype=dtype), jnp.zeros((3, 3), dtype)
    return jnp.concatenate([eye, zero], 1), jnp.concatenate([zero, eye], 1)


class PieceVariations(eqx.Module):
    """A piece integrated from the identity pose at the origin (`piece_variations`): its end
    `position` `(3,)`, `frame` `(3, 3)` and lab `moment` `(3,)` (about the end), and the
    variations of its end position `d_position` and spatial rotation `d_rotation` `(3, 6)`
    along the six local start wrenches $(\\delta n, \\delta m)$; `rotation`: the count of
    its end's rotation (`_rotation.RotationCount`) where its lab start frame was given,
    else None."""

    position: Float[Array, "3"]
    frame: Float[Array, "3 3"]
    moment: Float[Array, "3"]
    d_position: Float[Array, "3 6"]
    d_rotation: Float[Array, "3 6"]
    rotation: RotationCount | None = None


def _twist_and_variations(rod, dtype):
    """`f(m, dm)`: the twist $u(m)$ of the rod's inverse law and its variations along the
    columns of `dm` `(3, k)`.  The quadratic energy's law (`Rod`) is linear, $u = \\hat u +
    K^{-1}m$: one compliance matrix, formed once, serves every step (measured, a piece's
    Runge--Kutta steps: 634 -> 427 ns each, the same variations to 4e-16); any other law
    (`StrainEnergyRod`) by forward mode through it."""
    if isinstance(rod, Rod):
        compliance = jax.jacfwd(rod.twist)(jnp.zeros(3, dtype))
        uhat = jnp.asarray(rod.uhat, dtype)
        return lambda m, dm: (uhat + compliance @ m, compliance @ dm)

    def forward(m, dm):
        return jax.vmap(lambda v: jax.jvp(rod.twist, (m,), (v,)), out_axes=(None, 1))(dm.T)

    return forward


def piece_variations(rod, n0, m0, length, steps, frame=None) -> PieceVariations:
    """A piece of length `length` with local start wrench (`n0`, `m0`) and the variations
    of its end along the six start wrenches, by `steps` equal classical Runge--Kutta steps
    of the centreline, frame and Jacobi fields together.

    In the frame of its start (identity pose at the origin) the lab force $N = n_0$ is
    constant and the moment about the current point is $M = m_0 - x\\times N$; a variation
    $(\\delta N, \\delta M_0)$ of the start wrench moves the centreline by $\\delta x$ and
    turns the frame by the spatial rotation $\\delta\\theta$ ($\\delta D = [\\delta\\theta]_\\times D$),
    which obey the linearised equations
    $\\delta x' = \\delta\\theta\\times d_3$, $\\delta\\theta' = D\\,\\partial u/\\partial m\\,
    D^T(\\delta M + M\\times\\delta\\theta)$, $\\delta M = \\delta M_0 - \\delta x\\times N - x\\times\\delta N$
    (from $D' = D\\hat u$, $x' = De_3$ and $u = u(D^TM)$): six fields of six components
    beside the pose, in a loop that XLA compiles into one small kernel.  The frame is not
    kept on $SO(3)$ by the steps: its drift, of the order of the steps' error, is projected
    out at the end.  With the piece's lab start `frame`, the rotation of its frame about
    $e_z$ is counted step by step on the way (`_rotation.advance`)."""
    dtype = jnp.result_type(n0, m0, float)
    N, M0 = n0[:, None], m0[:, None]
    eye = jnp.eye(3, dtype=dtype)
    dN, dM0 = _start_directions(dtype)

    twist_and_variations = _twist_and_variations(rod, dtype)

    def rates(state):
        x, D, dx, dtheta = state
        M = M0 - jnp.cross(x, N, axis=0)
        d_moment = dM0 - jnp.cross(dx, N, axis=0) - jnp.cross(x, dN, axis=0) + jnp.cross(M, dtheta, axis=0)
        u, du = twist_and_variations((D.T @ M)[:, 0], D.T @ d_moment)
        d3 = D[:, 2:3]
        return d3, D @ hat(u), jnp.cross(dtheta, d3, axis=0), D @ du

    h = length / steps

    def step(_, y):
        shifted = lambda a, k: jax.tree.map(lambda yi, ki: yi + a * ki, y, k)  # noqa: E731
        k1 = rates(y)
        k2 = rates(shifted(h / 2, k1))
        k3 = rates(shifted(h / 2, k2))
        k4 = rates(shifted(h, k3))
        return jax.tree.map(lambda yi, a, b, c, d: yi + (h / 6) * (a + 2 * b + 2 * c + d), y, k1, k2, k3, k4)

    start = (jnp.zeros((3, 1), dtype), eye, jnp.zeros((3, 6), dtype), jnp.zeros((3, 6), dtype))
    if frame is None:
        x, D, dx, dtheta = jax.lax.fori_loop(0, steps, step, start)
        count = None
    else:

        def counted_step(i, carry):
            y = step(i, carry[0])
            return y, advance(carry[1], frame @ y[1])

        (x, D, dx, dtheta), count = jax.lax.fori_loop(0, steps, counted_step, (start, start_count(frame)))
    D = D @ (1.5 * eye - 0.5 * D.T @ D)  # one Newton--Schulz step towards the nearest rotation
    x = x[:, 0]
    return PieceVariations(x, D, m0 - jnp.cross(x, n0), dx, dtheta, count)


def flow_variations(rod, wrench, length, max_steps: int, per_radian: float = STEPS_PER_RADIAN) -> Float[Array, "6 18"]:
    """The derivatives of a piece's flow -- its end position, frame (row-major), force and
    moment in the end's director frame, all in the frame of its start, as
    `_shooting.piece_flow` lays them out -- along the six local start wrenches `wrench`
    $(n_0, m_0)$, from its Jacobi fields (`piece_variations`, `variation_steps`):
    $\\delta R = [\\delta\\theta]_\\times R$, $\\delta n = R^T(\\delta N + N\\times\\delta\\theta)$,
    $\\delta m = R^T(\\delta M + M\\times\\delta\\theta)$ with $M = m_0 - x\\times N$ the moment
    about the end and $\\delta M = \\delta m_0 - \\delta x\\times N - x\\times\\delta N$."""
    n0, m0 = wrench[:3], wrench[3:]
    piece = piece_variations(rod, n0, m0, length, variation_steps(rod, n0, m0, length, max_steps, per_radian))
    R, x, dx, dtheta = piece.frame, piece.position, piece.d_position, piece.d_rotation
    dN, dm0 = _start_directions(dx.dtype)
    d_frame = jax.vmap(lambda t: hat(t) @ R, in_axes=1)(dtheta).reshape(6, 9)
    d_force = R.T @ (dN + jnp.cross(n0[:, None], dtheta, axis=0))
    d_moment = dm0 - jnp.cross(dx, n0[:, None], axis=0) - jnp.cross(x[:, None], dN, axis=0)
    d_end_moment = R.T @ (d_moment + jnp.cross(piece.moment[:, None], dtheta, axis=0))
    return jnp.concatenate([dx.T, d_frame, d_force.T, d_end_moment.T], 1)
