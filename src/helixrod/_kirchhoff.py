"""The static Kirchhoff equations integrated along the arc length with diffrax.

In local (director-frame) components, with $u$ from the constitutive law $m = \\nabla W(u)$,

$$n' + u\\times n = 0,\\qquad m' + u\\times m + e_3\\times n = 0,$$

and, when asked for, the frame $D' = D\\hat u$ (column $i$ of $D$ is $d_{i+1}$ in lab
coordinates) and the centreline $x' = D e_3$.  First integrals: $I_1 = n\\cdot n$,
$I_2 = m\\cdot n$ and $H = u\\cdot m - W(u) + n_3$.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._compile import filter_jit, outside_transformations
from ._equilibria import HelixEquilibria
from ._geometry import helix_centreline, helix_frame
from ._lie import BodyVelocityTerm, CommutatorFreeRK4, MuntheKaasRK, RodState, check_rotation, is_rotation, tangent
from ._misc import (
    as_float, check_integer, differentiated_part, float_dtype, increases_within, increasing_within, is_concrete, no_gradient,
)
from ._rod import check_one_rod
from ._ode import solve_ode
from ._status import RESULTS, promote, raise_if_failed


_OUTPUTS = ("wrench", "frame", "centreline")


class KirchhoffSolution(eqx.Module):
    """Solution of `solve_static`, saved at `s` (leading save axis of length `k`).

    Fields: `s` `(k,)` arc lengths; `n`, `m`, `u` `(k, 3)` force, moment and twist in the
    director frame; `frame` `(k, 3, 3)` (column $i$ is $d_{i+1}$ in lab coordinates) and
    `x` `(k, 3)` the centreline in lab coordinates, each `None` unless requested through
    `outputs`; `first_integrals` `(k, 3)` the values of $(I_1, I_2, H)$ and `drift` their
    change since $s = 0$; `result` a `helixrod.RESULTS` code (the diffrax code of the solve,
    or `invalid_input`), `ok` its success; `valid_input` False where the input was rejected
    (only with `throw=False`; the fields are NaN there); `num_steps` the number of accepted
    steps.
    """

    s: Float[Array, " k"]
    n: Float[Array, "k 3"]
    m: Float[Array, "k 3"]
    u: Float[Array, "k 3"]
    frame: Float[Array, "k 3 3"] | None
    x: Float[Array, "k 3"] | None
    first_integrals: Float[Array, "k 3"]
    drift: Float[Array, "k 3"]
    result: RESULTS
    valid_input: Bool[Array, ""]
    num_steps: Int[Array, ""]

    @property
    def ok(self) -> Bool[Array, ""]:
        """True where the input was valid and the solve succeeded."""
        return self.result == RESULTS.successful

    def lab_wrench(self) -> tuple[Array, Array]:
        """Force and moment in lab coordinates, $(Dn, Dm)$; needs the frame."""
        if self.frame is None:
            raise ValueError("lab_wrench needs the frame: solve with outputs=('frame',)")
        return lab_wrench(self.frame, self.n, self.m)


def lab_wrench(frame: ArrayLike, n: ArrayLike, m: ArrayLike) -> tuple[Array, Array]:
    """Lab components $(D n, D m)$ of a local force and moment; shapes broadcast.

    On an equilibrium the lab force is constant and the lab moment changes as
    $M(s) = M(0) - (x(s) - x(0))\\times N$.
    """
    frame = jnp.asarray(frame)
    return jnp.einsum("...ij,...j->...i", frame, n), jnp.einsum("...ij,...j->...i", frame, m)


def first_integrals(rod, n: ArrayLike, m: ArrayLike) -> Float[Array, "... 3"]:
    """$(I_1, I_2, H) = (n\\cdot n,\\ m\\cdot n,\\ u\\cdot m - W(u) + n_3)$ with $u$ from $m$.

    `n`, `m` have a trailing axis of 3 (local components) and broadcast; `rod` is a `Rod`
    or any constitutive law with `twist` and `energy`.  All three are constant along every
    solution of the static Kirchhoff equations.
    """
    n, m = jnp.broadcast_arrays(jnp.asarray(n), jnp.asarray(m))
    u = rod.twist(m)
    hamiltonian = jnp.sum(u * m, -1) - rod.energy(u) + n[..., 2]
    return jnp.stack([jnp.sum(n * n, -1), jnp.sum(m * n, -1), hamiltonian], -1)


def _body_velocity(s, y: RodState, rod):
    """The body twist $(u, e_3)$ of the director frame: $D' = D\\hat u$, $x' = De_3$."""
    u = rod.twist(y.m)
    return u, jnp.zeros_like(u).at[2].set(1.0)


def _ambient_field(s, y: RodState, rod) -> RodState:
    """$dy/ds$ for the standard (vector-space) solvers."""
    return tangent(y, *_body_velocity(s, y, rod))


def _per_unit_length(field):
    """`field(s, y, args)` of the arc length $s \\in [0, L]$ as the field of $\\sigma = s/L
    \\in [0, 1]$, $dy/d\\sigma = L\\,f(L\\sigma, y)$, with args `(args, L)`.

    Every integration runs over $\\sigma$ so that the end time is the constant 1, not the
    traced length: the loop (`_ode.solve_ode`) computes its end time less 100 ULPs on the host
    and takes only constant times.  (Before that loop, `diffrax.diffeqsolve` computed it by 100
    sequential `prevbefore`s, ~2300 HLO instructions (~1600 after XLA's passes) that XLA folds
    into one constant only when the end time is a constant, and otherwise compiled and ran in
    every program; the unit interval cut them, measured by
    `benchmarks/bench_first_calls.py --sizes` (instructions after XLA's passes): `solve_static`
    4053 -> 2369, with 201 saved points 5047 -> 3365, its `jax.grad` 7217 -> 3737,
    `solve_boundary_value` 15898 -> 14279.)  The controller is scale-invariant, so the steps
    are those over $s$ up to round-off (its first step's heuristic is not, which moves the
    solution within the tolerance)."""

    def scaled(sigma, y, args_and_length):
        args, length = args_and_length
        return jax.tree.map(lambda rate: length * rate, field(length * sigma, y, args))

    return scaled


_body_velocity_per_unit_length = _per_unit_length(_body_velocity)
_ambient_field_per_unit_length = _per_unit_length(_ambient_field)


def _wrench_jacobian(rod, wrench):
    """The $6\\times 6$ Jacobian of the wrench equations $(n', m') = (-u\\times n,\\
    -u\\times m - e_3\\times n)$, $u = u(m)$, at the local wrench `(6,)` = $(n, m)$."""

    def wrench_rate(w):
        state = RodState(w[:3], w[3:])
        rate = tangent(state, *_body_velocity(0.0, state, rod))
        return jnp.concatenate([rate.n, rate.m])

    return jax.jacfwd(wrench_rate)(wrench)


def _spectral_radius_bound(J, squarings: int = 5):
    """Upper bound $\\|J^{2^k}\\|_F^{1/2^k} \\ge \\rho(J)$ (Gelfand), within a few per cent of
    the spectral radius for $k = 5$ even when $J$ is far from normal; matrix products only
    (no eigenvalues: GPU-ready), rescaled at each squaring so that nothing over- or
    underflows."""
    scale = jnp.max(jnp.abs(J))
    nilpotent = ~(scale > 0)
    safe = jnp.where(nilpotent, 1.0, scale)
    A = J / safe
    log_scale = jnp.log(safe)

    def square(_, carry):
        A, log_scale, nilpotent = carry
        A = A @ A
        a = jnp.max(jnp.abs(A))
        a_safe = jnp.where(a > 0, a, 1.0)
        return A / a_safe, 2 * log_scale + jnp.log(a_safe), nilpotent | ~(a > 0)

    # A loop, not unrolled: one squaring in the program, the same values bitwise (HLO
    # instructions after XLA's passes: `solve_static`'s 4093 -> 4037, the shooting solve's
    # 13461 -> 13223, which holds the step cap of several integrations).
    A, log_scale, nilpotent = jax.lax.fori_loop(0, squarings, square, (A, log_scale, nilpotent))
    log_rho = (log_scale + 0.5 * jnp.log(jnp.sum(A * A))) / 2**squarings
    return jnp.where(nilpotent, 0.0, jnp.exp(log_rho))


def _stability_step(rod, n0, m0):
    """Largest step for which the explicit coupling of `CommutatorFreeRK4` keeps round-off
    perturbations bounded, from the Jacobian $J$ of the wrench equations at $s = 0$:
    $\\max(2/\\|J\\|_F,\\ 0.5/\\rho(J))$, $\\rho$ the spectral radius (bounded above by
    `_spectral_radius_bound`).  Near a uniform helix the error estimate vanishes, and
    without a cap the step grows until round-off is amplified (measured: stable for
    $h\\|J\\|_F \\lesssim 3.5$ on spatially stable helices; on the 1000-turn helix of the
    README the frame error is 9e-11 at $h\\rho = 0.8$, 1.3e-9 at 0.9, 1.8e-7 at 0.95).  The
    spectral term matters where $J$ is far from normal (highly twisted, nearly singular
    rods: $\\|J\\|_F/\\rho$ of 1.6e3 and 2.5e4 measured), where $2/\\|J\\|_F$ alone made
    `solve_static` run out of steps (`tests/test_stress.py`)."""

    J = _wrench_jacobian(rod, jax.lax.stop_gradient(jnp.concatenate([n0, m0])))
    norm = jnp.sqrt(jnp.sum(J * J))
    rho = _spectral_radius_bound(J)
    frobenius_step = jnp.where(norm > 0, 2.0 / jnp.where(norm > 0, norm, 1.0), jnp.inf)
    spectral_step = jnp.where(rho > 0, 0.5 / jnp.where(rho > 0, rho, 1.0), jnp.inf)
    return jnp.maximum(frobenius_step, spectral_step)


def linearised_rate(rod, n0, m0) -> Array:
    """An upper bound on the spectral radius of the linearised wrench equations at the local
    wrench (`n0`, `m0`) (`_spectral_radius_bound`): the fastest rate at which variations of
    a solution turn or grow, per unit length (no gradient)."""
    J = _wrench_jacobian(rod, jax.lax.stop_gradient(jnp.concatenate([n0, m0])))
    return _spectral_radius_bound(J)


def _check_options(solver, rtol, atol, steps, max_steps) -> None:
    """`ValueError` naming a bad option of `solve_static`."""
    if not isinstance(solver, diffrax.AbstractSolver):
        raise ValueError(f"solve_static: solver must be a diffrax solver (e.g. CommutatorFreeRK4()), got {solver!r}")
    for name, value in (("rtol", rtol), ("atol", atol)):
        if is_concrete(value) and not (np.all(np.isfinite(np.asarray(value))) and np.all(np.asarray(value) > 0)):
            raise ValueError(f"solve_static: {name} must be finite and > 0, got {value!r}")
    if max_steps is not None:
        check_integer(max_steps, "max_steps", "solve_static")
    if steps is not None and not isinstance(steps, jax.Array):  # a traced count of steps is checked by its caller
        check_integer(steps, "steps", "solve_static")


def _parse_outputs(outputs) -> tuple[bool, bool, bool]:
    """(integrate the frame, store the frame, integrate and store the centreline)."""
    if not isinstance(outputs, str) and not isinstance(outputs, Sequence):
        raise ValueError(f"solve_static: outputs must be a name or a sequence of names from {_OUTPUTS}, got {outputs!r}")
    names = (outputs,) if isinstance(outputs, str) else tuple(outputs)
    unknown = [name for name in names if name not in _OUTPUTS]
    if unknown:
        raise ValueError(f"solve_static: unknown output name(s) {unknown}; choose from {_OUTPUTS}")
    centreline = "centreline" in names
    store_frame = "frame" in names
    return store_frame or centreline, store_frame, centreline


@functools.cache
def default_solver() -> MuntheKaasRK:
    """`solve_static`'s default solver, `MuntheKaasRK(diffrax.Dopri8())`, built once:
    building its tableau at every call cost an eager call ~0.35 ms (measured)."""
    return MuntheKaasRK(diffrax.Dopri8())


def solve_static(
    rod,
    n0: ArrayLike,
    m0: ArrayLike,
    length: ArrayLike,
    *,
    frame0: ArrayLike | None = None,
    x0: ArrayLike | None = None,
    saveat: ArrayLike | None = None,
    interpolate: bool = True,
    outputs: str | Sequence[str] = ("wrench",),
    solver: diffrax.AbstractSolver | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    steps: int | None = None,
    max_steps: int = 100_000,
    adjoint: diffrax.AbstractAdjoint | None = None,
    throw: bool = True,
) -> KirchhoffSolution:
    """Integrate the static Kirchhoff equations from $s = 0$ to $s$ = `length`.

    **Arguments**

    - `rod`: a `Rod`, or any constitutive law with `twist(m)` and `energy(u)` (e.g.
      `StrainEnergyRod`); unbatched (use `jax.vmap` for batches of rods).
    - `n0`, `m0`: force and moment at $s = 0$ in the director frame, shape `(3,)`.
    - `length`: arc length, $> 0$.
    - `frame0`: initial frame, `(3, 3)` rotation with column $i$ = $d_{i+1}$ (default
      identity); `x0`: initial centreline point (default origin).
    - `saveat`: `None` saves at $s$ = `length` only (save axis of length 1); an
      increasing array of $s$ in $[0, \\mathrm{length}]$ saves there.
    - `interpolate`: take the saved points from the solver's continuous extension
      (default; `LieGroupInterpolation` for the geometric solvers: saved frames stay
      rotations, exact on uniform helices), at the cost of dense output rather than of a
      step per saved point; `False` makes steps end on every saved point instead, so that
      the saved values carry the steps' accuracy and their derivatives are those of step
      values (the interpolant of the default solver is of order 5, below its order 8).
    - `outputs`: names from `("wrench", "frame", "centreline")`. Only what is named is
      integrated and stored: the wrench alone is a 6-dimensional system; the centreline
      needs (and integrates, without storing) the frame.
    - `solver`: default `MuntheKaasRK(diffrax.Dopri8())` (8th order, 13 evaluations a
      step); `CommutatorFreeRK4()` (4th order, 4 evaluations a step) is cheaper per step,
      compiles in half the time and is the faster one on uniform helices and at loose
      tolerances.  Both are exact on uniform helices, keep the frame orthonormal and
      conserve $|n|^2$ and $m\\cdot n$ to round-off.  Any diffrax ODE solver also works (it
      then integrates the frame as 9 plain components).  The default was chosen by
      `benchmarks/bench_kirchhoff.py`: on a non-helical solution it reaches the error of
      scipy DOP853 at tolerance 1e-10 in the fewest milliseconds.
    - `rtol`, `atol`: PID step-size tolerances, default `1e-12` in float64 (`1e-6` in
      float32, which cannot meet tighter ones); `steps`: use that many equal steps
      instead (no error control; may be traced, then `max_steps` must cover it).
    - `max_steps` as in `diffrax.diffeqsolve`.
    - `adjoint`: how derivatives are taken.  `None` (default): `jax.grad`, `jax.jacrev`,
      `jax.jacfwd` and `jax.jvp` all differentiate the solution through its forward
      sensitivity equations, integrated with it (diffrax `Dopri8` in ambient coordinates, at
      the same tolerances, one direction per differentiated input) when they are asked
      for.  They are the derivatives of the solution, accurate to about the tolerance
      times the growth of the flow, not of the steps; a failed sensitivity integration
      gives NaN derivatives.  Reverse mode then costs no adjoint of the solver's step,
      whose compilation is slow for the default solver (see the README).  With `steps`
      (equal steps), `None` means `diffrax.RecursiveCheckpointAdjoint()`.  A diffrax
      adjoint (`RecursiveCheckpointAdjoint()` for reverse mode, `ForwardMode()` for
      forward mode) differentiates the steps themselves, as `diffrax.diffeqsolve` does
      (`jax.jacfwd` or `jax.jvp` of fixed `steps` needs `adjoint=diffrax.ForwardMode()`).
    - `throw`: raise on failure (`helixrod.SolverError` when called eagerly, an equinox
      runtime error inside `jax.jit`); with `throw=False` read `result` and `ok`.

    **Errors.** Non-finite `n0`/`m0`, `length <= 0` or non-finite, and bad shapes raise
    `ValueError` for concrete values.  Traced bad values are flagged (`result =
    RESULTS.invalid_input`, `valid_input=False`, fields NaN), which raises with
    `throw=True`; with `throw=False` one bad point never spoils a `vmap`-ped batch.
    Hitting `max_steps` raises with `throw=True` and sets `result` otherwise.

    **Batches.** `jax.vmap(solve_static, ...)` over initial conditions, lengths or rods.
    A vmapped adaptive solve runs in lockstep: every member takes as many steps as the
    slowest (see the README for the measured cost).

    **Spatially unstable states.** The initial-value problem amplifies any error -- the
    steps' own, round-off -- like $e^{\\lambda s}$ where the state is spatially unstable
    ($\\lambda$ = `wrench_growth_rate(rod, n0, m0)` > 0, e.g. the helix $(\\kappa, \\tau) =
    (0.5, 1.5)$ of the README's rod, $\\lambda = 1.21$): the steps stay accurate and `ok`
    stays true, but by $\\lambda L \\approx 30$ the solution has lost most of its digits
    (that helix to $L = 30$: centreline 0.08 off, to $L = 100$: 78 off).  Integrate such
    states over lengths with $\\lambda L$ of a few at most, or solve the boundary-value
    problem with `segments` (`solve_boundary_value`).

    **Example**

    ```python
    rod = helixrod.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
    eq = helixrod.helix_equilibria(rod, 1.0, 0.5)   # wrench_growth_rate of its slot 0: 0
    n0, m0, frame0, x0 = helixrod.helix_initial_conditions(eq)
    sol = helixrod.solve_static(rod, n0[0], m0[0], 100.0, frame0=frame0[0], x0=x0[0],
                                saveat=jnp.linspace(0, 100, 500), outputs="centreline")
    ```
    """
    with_frame, store_frame, with_x = _parse_outputs(outputs)
    solver = default_solver() if solver is None else solver
    geometric = isinstance(solver, (CommutatorFreeRK4, MuntheKaasRK))
    check_one_rod(rod, "solve_static")

    dtype = float_dtype()
    default_tol = 1e-12 if dtype == jnp.float64 else 1e-6
    rtol = default_tol if rtol is None else rtol
    atol = default_tol if atol is None else atol
    n0 = as_float(n0, dtype)
    m0 = as_float(m0, dtype)
    length = as_float(length, dtype)
    if n0.shape != (3,) or m0.shape != (3,) or length.shape != ():
        raise ValueError(
            f"solve_static: n0, m0 need shape (3,) and length a scalar, got {n0.shape}, "
            f"{m0.shape}, {length.shape}; use jax.vmap for batches"
        )
    # The defaults from NumPy: jnp.eye and jnp.zeros would compile eagerly (~0.1 s together).
    frame0 = as_float(np.eye(3) if frame0 is None else frame0, dtype)
    x0 = as_float(np.zeros(3) if x0 is None else x0, dtype)
    if frame0.shape != (3, 3) or x0.shape != (3,):
        raise ValueError(f"solve_static: frame0 needs shape (3, 3) and x0 (3,), got {frame0.shape}, {x0.shape}")
    check_rotation(frame0, "solve_static")
    start_traced = not is_concrete(frame0, x0)
    if is_concrete(x0) and not np.all(np.isfinite(np.asarray(x0))):
        raise ValueError(f"solve_static: x0 must be finite, got {np.asarray(x0)}")
    _check_options(solver, rtol, atol, steps, max_steps)

    if is_concrete(n0, m0) and not np.all(np.isfinite(np.concatenate([np.asarray(n0), np.asarray(m0)]))):
        raise ValueError(f"solve_static: n0 and m0 must be finite, got n0={n0}, m0={m0}")
    if is_concrete(length) and not (np.isfinite(np.asarray(length)) and np.asarray(length) > 0):
        raise ValueError(f"solve_static: length must be finite and > 0, got {length}")
    ts = None if saveat is None else increasing_within(saveat, length, "saveat", "solve_static")
    # The geometric solvers' continuous extension (`LieGroupInterpolation`) keeps saved
    # frames on the group; where it is only the order-1 fallback, steps land on the save
    # points instead.
    dense = interpolate and (not geometric or solver.dense_output)
    if steps is not None:
        if not dense and saveat is not None:
            raise ValueError(
                "solve_static: with fixed `steps` and interpolate=False, or a solver with no "
                "continuous extension, only s = length can be saved; use the adaptive mode, "
                "interpolate=True or MuntheKaasRK(diffrax.Dopri8())"
            )
        if isinstance(steps, int):
            max_steps = max(max_steps, steps)
    # Array tolerances: a new tolerance does not recompile.
    inputs = (rod, n0, m0, length, frame0, x0, ts, as_float(rtol, dtype), as_float(atol, dtype))
    # The fourth entry: whether the start frame or position is traced, and so checked in the
    # program (concrete ones were checked above: the shooting pieces, integrated from the
    # identity pose, trace no check).
    outputs = (with_frame, store_frame, with_x, start_traced)
    solved = None
    if adjoint is None and steps is None and not is_concrete(inputs):
        primal = jax.lax.stop_gradient(inputs)
        if is_concrete(primal):
            # Differentiated outside any `jit` (e.g. an eager `jax.grad`): the flow, which is
            # not differentiated, runs now as a program of its own, which a later process
            # loads without tracing it; only the sensitivities are traced.
            with outside_transformations():
                solved = _flow_of(*primal, solver=solver, max_steps=max_steps, dense=dense, outputs=outputs)
    solution = _integrate(
        *inputs, solved, solver=solver, steps=steps, max_steps=max_steps, adjoint=adjoint, dense=dense, outputs=outputs
    )
    return raise_if_failed(solution, solution.result, "solve_static") if throw else solution


def _start(n0, m0, length, frame0, x0, ts, outputs):
    """`(valid, y0, length, ts)`: the integration's start, its length and save points, with
    invalid traced input (under `vmap`) replaced by a harmless problem and flagged."""
    with_frame, _, with_x, start_traced = outputs
    valid = jnp.all(jnp.isfinite(n0)) & jnp.all(jnp.isfinite(m0)) & jnp.isfinite(length) & (length > 0)
    if start_traced:
        valid = valid & is_rotation(frame0) & jnp.all(jnp.isfinite(x0))
    if ts is not None:
        # Repeats allowed: the shooting pieces integrate the save points clipped to them.
        valid = valid & increases_within(ts, length, strict=False)
    length = jnp.where(valid, length, 1.0)
    if ts is not None:
        ts = jnp.where(valid, ts, jnp.linspace(0.0, 1.0, ts.shape[0], dtype=n0.dtype))
    frame0 = jnp.where(valid, frame0, jnp.eye(3, dtype=frame0.dtype))
    x0 = jnp.where(valid, x0, 0.0)
    y0 = RodState(jnp.where(valid, n0, 0.0), jnp.where(valid, m0, 0.0), frame0 if with_frame else None, x0 if with_x else None)
    return valid, y0, length, ts


@filter_jit(trace_cache=True)
def _flow_of(rod, n0, m0, length, frame0, x0, ts, rtol, atol, *, solver, max_steps, dense, outputs):
    """The flow of `solve_static`'s default path alone (not differentiated), for `_integrate`'s
    `solved`, when `solve_static` is differentiated outside any `jit`: then it is a top-level
    call (`outside_transformations`), which the trace cache exports, so a later process
    traces only the sensitivities.  Measured on the L = 40 gradient of
    `benchmarks/bench_first_calls.py` (one core, fresh processes alternating with the code
    before): first call with a warm cache 1.35-1.40 -> 0.97-1.00 s; cold 5.56-5.73 ->
    5.93-6.00 s (one more program to export and compile); later eager calls 6.6-7.0 ->
    7.2-7.4 ms (best of 30: a second program and its lookup).  Under a caller's `jit` nothing
    changes."""
    _, y0, length, ts = _start(n0, m0, length, frame0, x0, ts, outputs)
    return _undifferentiated_flow(rod, y0, length, ts, rtol, atol, solver=solver, max_steps=max_steps, dense=dense)


def _undifferentiated_flow(rod, y0, length, ts, rtol, atol, *, solver, max_steps, dense):
    """The default path's flow, never differentiated (`_with_sensitivities` is): a plain loop
    with inputs without tangents (a tangent would make JAX trace the loop's JVP, then drop it)."""
    flow = _Flow(solver, None, max_steps, diffrax.ForwardMode(), dense)
    return flow(*no_gradient((rod, y0, length, ts, rtol, atol)))


@filter_jit(trace_cache=True)
def _integrate(rod, n0, m0, length, frame0, x0, ts, rtol, atol, solved, *, solver, steps, max_steps, adjoint, dense, outputs):
    """`solve_static` after its checks, as one program of its own (an eager call is one
    dispatch, compiled with helixrod's options).  `solved`: `None`, or the default path's
    flow from `_flow_of` (integrated outside this program)."""
    _, store_frame, with_x, _ = outputs
    valid, y0, length, ts = _start(n0, m0, length, frame0, x0, ts, outputs)
    if adjoint is None and steps is None:
        if solved is None:
            solved = _undifferentiated_flow(rod, y0, length, ts, rtol, atol, solver=solver, max_steps=max_steps, dense=dense)
        s, ys, result, num_steps = _with_sensitivities(rod, y0, length, ts, rtol, atol, solved, max_steps=max_steps)
    else:
        s, ys, result, num_steps = _Flow(solver, steps, max_steps, adjoint, dense)(rod, y0, length, ts, rtol, atol)
    nan_if_invalid = lambda a: jnp.where(valid, a, jnp.nan)  # noqa: E731
    n, m = nan_if_invalid(ys.n), nan_if_invalid(ys.m)
    integrals = first_integrals(rod, n, m)
    solution = KirchhoffSolution(
        s=s,
        n=n,
        m=m,
        u=rod.twist(m),
        frame=nan_if_invalid(ys.frame) if store_frame else None,
        x=nan_if_invalid(ys.x) if with_x else None,
        first_integrals=integrals,
        drift=integrals - first_integrals(rod, y0.n, y0.m)[None],
        # Fixed steps only: adaptive ones reject a non-finite step (and fail by their own codes).
        result=RESULTS.where(valid, promote(result) if steps is None else _finite_or_flagged(promote(result), ys), RESULTS.invalid_input),
        valid_input=valid,
        num_steps=num_steps,
    )
    return solution


def _finite_or_flagged(result, ys):
    """`result`, or `nonfinite` where a successful integration's states are not finite (fixed
    steps too long for the solver: a Munthe-Kaas step's dexp^{-1} series diverges beyond
    ~2 pi of rotation per step; adaptive steps are capped below that)."""
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(ys)]))
    return RESULTS.where(finite | (result != RESULTS.successful), result, RESULTS.nonfinite)


class _Flow(eqx.Module):
    """The integration of `solve_static` from `y0` over `[0, length]`, saved at `ts` (or at
    `length` when `None`): `(s, ys, result, accepted steps)`."""

    solver: diffrax.AbstractSolver
    steps: object  # None: adaptive; else the number of equal steps (an int or traced)
    max_steps: int = eqx.field(static=True)
    adjoint: diffrax.AbstractAdjoint | None
    dense: bool = eqx.field(static=True)

    def __call__(self, rod, y0: RodState, length, ts, rtol, atol):
        geometric = isinstance(self.solver, (CommutatorFreeRK4, MuntheKaasRK))
        # Over sigma = s / length in [0, 1] (`_per_unit_length`).
        sigma = None if ts is None else ts / length
        if self.steps is not None:
            controller = diffrax.ConstantStepSize()
            dt0 = 1.0 / self.steps
        else:
            step_ts = None if self.dense else sigma
            dtmax = _stability_step(rod, y0.n, y0.m) / length if geometric else None
            controller = diffrax.PIDController(rtol=rtol, atol=atol, step_ts=step_ts, dtmax=dtmax)
            dt0 = None
        term = BodyVelocityTerm(_body_velocity_per_unit_length) if geometric else diffrax.ODETerm(_ambient_field_per_unit_length)
        adjoint = diffrax.RecursiveCheckpointAdjoint() if self.adjoint is None else self.adjoint
        ys, result, stats = solve_ode(
            term, self.solver, 0.0, _one_like(length), dt0, y0, ts=sigma, args=(rod, length),
            stepsize_controller=controller, max_steps=self.max_steps, adjoint=adjoint,
        )
        s = jnp.reshape(length, (1,)) if ts is None else ts
        return s, ys, result, stats["num_accepted_steps"]


def _one_like(length):
    """The end of the unit interval, a constant (not traced) in `length`'s dtype."""
    return np.ones((), dtype=jnp.result_type(length))


@eqx.filter_custom_jvp
def _with_sensitivities(rod, y0, length, ts, rtol, atol, solved, *, max_steps: int):
    """`solved` -- `_Flow(...)(rod, y0, length, ts, rtol, atol)`, integrated by the caller and
    not differentiated -- differentiated by its forward sensitivity equations
    (`_sensitivities`).  The flow is an input, not computed here, so that differentiating
    `solve_static` traces its integration once (in the caller) and the sensitivities'
    once (in the rule): a rule that integrated the flow itself traced it a second time.
    Measured on the L = 40 solve of `benchmarks/bench_first_calls.py` (one core): the trace
    of its `jax.grad` 1.26 -> 1.04 s; fresh processes alternating with the previous code, the
    first call with a warm cache 2.09-2.23 -> 1.86-1.96 s, without a cache 6.68-6.75 ->
    6.51-6.64 s.  The caller's flow, never differentiated, runs as a plain loop
    (`diffrax.ForwardMode`, not the checkpointed loop of reverse mode; the same steps, the
    same numbers): then 1.90-1.97 -> 1.70-1.78 s warm and 6.78-6.93 -> 6.51-6.58 s cold, and
    `solve_static`'s own first call 5.03-5.30 -> 4.95-5.13 s."""
    return solved


@_with_sensitivities.def_jvp
def _with_sensitivities_jvp(primals, tangents, *, max_steps: int):
    # The sensitivities depend on the primals only and the tangent is linear in them, so
    # reverse mode transposes a contraction, not the integration loop: `jax.grad` costs a
    # forward integration of the sensitivities instead of the adjoint of the solver's step.
    rod, y0, length, ts, rtol, atol, _ = primals
    t_rod, t_y0, t_length, t_ts = tangents[:4]
    # Called again (an identity on the flow) so that a derivative of this rule uses this rule too.
    s, ys, result, num_steps = _with_sensitivities(*primals, max_steps=max_steps)
    t_ys = jax.tree.map(jnp.zeros_like, ys)
    diff, rest, t_diff = differentiated_part((rod, y0), (t_rod, t_y0))
    if jax.tree.leaves(t_diff):
        sensitivities = _sensitivities(diff, rest, length, ts, rtol, atol, max_steps)
        direction = ravel_pytree(t_diff)[0]
        t_ys = jax.tree.map(lambda S: jnp.einsum("s...p,p->s...", S, direction), sensitivities)
    t_s = t_ts if ts is not None else (None if t_length is None else t_length[None])
    if t_s is not None:  # a saved point moves with its arc length
        rate = jax.vmap(_ambient_field, in_axes=(0, 0, None))(s, ys, rod)
        t_ys = jax.tree.map(lambda t, r: t + r * t_s.reshape(t_s.shape + (1,) * (r.ndim - 1)), t_ys, rate)
    no_tangent = jax.tree.map(lambda _: None, (result, num_steps))
    return (s, ys, result, num_steps), (t_s, t_ys, *no_tangent)


def _sensitivities(diff, rest, length, ts, rtol, atol, max_steps):
    r"""$\partial y(s)/\partial p$ at the saved points for the flat vector $p$ of the
    differentiated inputs `diff` (of `(rod, y0)`; `rest` the others): the state and its
    sensitivities $S' = f_y S + f_p$, $S(0) = \partial y_0/\partial p$, integrated together
    in ambient coordinates by diffrax's `Dopri8` at the solve's tolerances, saved like the
    solve.  Leaves `(saved, ..., p)`; NaN if the integration failed.  This differentiates the
    solution, not the steps that approximate it: the derivatives agree with those of the
    steps to about the tolerance (`tests/test_kirchhoff.py`)."""
    p, unravel = ravel_pytree(diff)
    basis = jnp.eye(p.size, dtype=p.dtype)
    split = lambda q: eqx.combine(unravel(q), rest)  # noqa: E731

    # The directions ride on the last axis of S: under a caller's vmap that took a batch of
    # gradients 5.3-6.1 -> 4.7-4.9 ms per item (one core).
    def rates(s, state, q):
        y, S = state
        rate = lambda y, q: _ambient_field(s, y, split(q)[0])  # noqa: E731
        return rate(y, q), jax.vmap(lambda Sj, e: jax.jvp(rate, (y, q), (Sj, e))[1], in_axes=(-1, 0), out_axes=-1)(S, basis)

    start = lambda q: split(q)[1]  # noqa: E731
    S0 = jax.vmap(lambda e: jax.jvp(start, (p,), (e,))[1], out_axes=-1)(basis)
    ys, result, _ = solve_ode(
        diffrax.ODETerm(_per_unit_length(rates)), diffrax.Dopri8(), 0.0, _one_like(length), None, (start(p), S0),
        ts=None if ts is None else ts / length, args=(p, length),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol), max_steps=max_steps,
        adjoint=diffrax.ForwardMode(),
    )
    ok = result == diffrax.RESULTS.successful
    return jax.tree.map(lambda S: jnp.where(ok, S, jnp.nan), ys[1])


# -- uniform helices ---------------------------------------------------------------------


def helix_initial_conditions(eq: HelixEquilibria) -> tuple[Array, Array, Array, Array]:
    """Initial state `(n0, m0, frame0, x0)` of each uniform helix in `eq` (from
    `helix_equilibria`) so that `solve_static(rod, n0, m0, L, frame0=frame0, x0=x0)`
    reproduces it: the frame and centreline then equal `helix_frame(kappa, tau, phi, s)`
    and `helix_centreline(kappa, tau, s)`.  Shapes follow `eq` (per register; invalid
    slots are NaN).  A register whose linearised wrench flow has an eigenvalue with positive
    real part is spatially unstable: round-off then grows like $e^{\\lambda s}$ in any
    integration, and the helix is reproduced only over lengths of a few $1/\\lambda$."""
    kappa = jnp.hypot(eq.u[..., 0], eq.u[..., 1])
    tau = eq.u[..., 2]

    return eq.n, eq.m, helix_frame(kappa, tau, eq.phi, 0.0), helix_centreline(kappa, tau, 0.0)


def wrench_growth_rate(rod, n: ArrayLike, m: ArrayLike) -> Array:
    """Spatial growth rate $\\lambda$ of perturbations of a uniform helix: the largest real
    part of the eigenvalues of the $6\\times 6$ Jacobian of the static Kirchhoff equations
    $(n', m') = (-u\\times n,\\ -u\\times m - e_3\\times n)$, $u = u(m)$, at the constant local
    wrench `(n, m)` (e.g. `helix_equilibria(...).n`, `.m`, or `bulk_helix`).

    $\\lambda > 0$ (a spatially unstable helix) means that errors in a shooting guess grow like
    $e^{\\lambda L}$: from the bulk guess single shooting was measured to converge up to
    $\\lambda L \\approx 3$ and to fail beyond $\\approx 4$ (README), so use
    `segments >= lambda * L / 3` in `solve_boundary_value`.  `n`, `m` `(..., 3)` broadcast;
    uses `jnp.linalg.eigvals` (CPU).  Not differentiable.
    """
    n, m = jnp.broadcast_arrays(jnp.asarray(n, float_dtype()), jnp.asarray(m, float_dtype()))
    wrench = jax.lax.stop_gradient(jnp.concatenate([n, m], -1)).reshape(-1, 6)
    jac = jax.vmap(lambda w: _wrench_jacobian(rod, w))(wrench)
    growth = jnp.max(jnp.real(jnp.linalg.eigvals(jac)), axis=-1)
    return growth.reshape(n.shape[:-1])
