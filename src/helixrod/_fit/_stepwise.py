"""An optimistix Gauss--Newton-type solve driven from Python, one step at a time, around
a model program compiled once.

For a forward model whose evaluation is itself a solve (a finite rod's shooting equations,
a tweezer response), `optimistix.least_squares` inside `jax.jit` compiles the model's
Jacobian once more inside its loop, besides the program of residuals and Jacobian that the
start scan and the error analysis use: measured on the README's shape fit (its model then
linearised), 31 s and 36 s of XLA compilation (and 6 s and 18 s of tracing) for the two
copies.  Here the solver's own `init`, `step` and `terminate` run in a small compiled
program, and at every step the residuals and Jacobian come from the one model program,
evaluated by the caller at the point the solver asks for.  A Gauss--Newton-type step
(`optimistix.AbstractGaussNewton`: Gauss--Newton, Levenberg--Marquardt, dogleg) evaluates
its function only there, at `state.y_eval`, and reads its value and linear map: it sees
the model as its affine expansion about that point, exact in all it reads.  The loop is
`optimistix`'s own (`optimistix._iterate`): the same steps, termination and result codes
(to round-off: the two programs round differently, and where the loss changes at round-off
only, accepting a step is decided by rounding).  Each step costs a round trip to Python;
the next point's model evaluation is asked for before the step's `terminate` is read, so
that it runs while Python waits (a tweezer fit's 8 steps: 7.3-8.4 ms -> 6.0-6.7 ms,
against 5.0-5.8 ms in optimistix's compiled loop).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._compile import compile_ahead, filter_jit, jit, split_arrays
from .._status import RESULTS, promote, succeeded

_TAGS: frozenset = frozenset()


def steppable(solver) -> bool:
    """Whether `stepwise_least_squares` can drive `solver` (it evaluates its function only
    at `state.y_eval`)."""
    return isinstance(solver, optx.AbstractGaussNewton)


def _affine(z, args):
    """The model's affine expansion about `z_eval`: residuals `r` and Jacobian `J` there."""
    r, J, z_eval = args
    return r + J @ (z - z_eval), None


def _fresh_state(solver, z, args):
    f_struct = jax.ShapeDtypeStruct(args[0].shape, args[0].dtype)
    return solver.init(_affine, z, args, {}, f_struct, None, _TAGS)


@functools.partial(jit, static_argnums=0)
def _start(static, arrays, z0, r, J):
    """The solver's initial state (its array leaves) at `z0`; `r`, `J` give the shapes."""
    solver, _ = static.combine(arrays)
    return eqx.filter(_fresh_state(solver, z0, (r, J, z0)), eqx.is_array)


def _reweighted(r, J, sigma, held):
    """Residuals and Jacobian over the sigmas `held` instead of their own `sigma` (`None`:
    unchanged); a row whose ratio is not a positive number keeps its own."""
    if sigma is None:
        return r, J
    ratio = sigma / held
    ratio = jnp.where(jnp.isfinite(ratio) & (ratio > 0), ratio, 1.0)
    return r * ratio, J * ratio[:, None]


@functools.partial(jit, static_argnums=0)
def _step(static, arrays, z, dynamic, r, J_physical, sigma, held):
    """One solver step from `z` and the state's arrays `dynamic`, with the residuals `r` and
    their Jacobian `J_physical` in the physical values at `dynamic.y_eval`, reweighted from
    their moving sigmas `sigma` to the sigmas `held` (`_reweighted`): (next z, next state's
    arrays, terminate, result, the physical values of the next point to evaluate) as
    `optimistix`'s loop body (termination judged at `z` with the new state).  `static` and
    `arrays` are the two halves of `(solver, physical)`."""
    solver, physical = static.combine(arrays)
    z_eval = dynamic.y_eval
    r, J_physical = _reweighted(r, J_physical, sigma, held)
    args = (r, J_physical @ jax.jacfwd(physical)(z_eval), z_eval)
    # The static half (a traced linear map's jaxpr) made in this trace: the same for every call.
    static_state = eqx.filter(_fresh_state(solver, z, args), eqx.is_array, inverse=True)
    state = eqx.combine(dynamic, static_state)
    z_next, state, _ = solver.step(_affine, z, args, {}, state, _TAGS)
    terminate, result = solver.terminate(_affine, z, args, {}, state, _TAGS)
    result = optx.RESULTS.where(jnp.all(jnp.isfinite(z)), result, optx.RESULTS.nonfinite)
    return z_next, eqx.filter(state, eqx.is_array), terminate, promote(result), physical(state.y_eval)


#: Largest relative change of the moving sigmas between two solves at which a stepwise fit
#: stops solving again (`stepwise_least_squares`).
SIGMA_TOLERANCE = 1e-6

#: The most solves of Orear's iteration (errors in variables: weights held, then solved
#: again with those of the solution), here and in `fit_stiffness`'s compiled path; where
#: the weights have not settled by then, the result is `RESULTS.weights_not_settled`.
HELD_WEIGHTS_ROUNDS = 20


def compile_steps_ahead(solver, physical, z, residuals, jacobian, sigma) -> None:
    """Start compiling the programs of `stepwise_least_squares`'s steps (`compile_ahead`)
    for internal coordinates like `z` and a model whose residuals, Jacobian and moving sigmas
    will be like `residuals`, `jacobian` and `sigma` (`jax.ShapeDtypeStruct`s of a model
    program compiling ahead, or None for sigma), placed as the loop places them: beside the
    model's compilation, not after it."""
    arrays, static = split_arrays((solver, physical))
    z = jax.ShapeDtypeStruct(z.shape, z.dtype, sharding=residuals.sharding)  # `place` in the loop
    dynamic = compile_ahead(_start, static, arrays, z, residuals, jacobian)
    if dynamic is not None:
        compile_ahead(_step, static, arrays, z, dynamic, residuals, jacobian, sigma, sigma)


def stepwise_least_squares(jacobian_at: Callable, physical: Callable, z0, solver, max_steps: int):
    """Minimise $\\tfrac12|r|^2$ over internal coordinates `z` from `z0` with the
    Gauss--Newton-type `solver` (`steppable`), at most `max_steps` steps.
    `jacobian_at(q)` returns the residuals, their Jacobian and their moving sigmas `(r,
    dr/dq, sigma)` at the physical values `q = physical(z)` (a compiled program's concrete
    output; `physical` a differentiable map, a pytree such as an `equinox.Module`'s method,
    compiled into the step).  Returns what `optimistix.least_squares` would -- the solution
    `z`, the cost $\\tfrac12|r|^2$ there (`inf` where not finite), a `RESULTS` code and the
    number of steps -- with the model evaluated once per step, by `jacobian_at` (and once
    more, at the point the solver would have tried next, when it stops before `max_steps`).

    Moving sigmas (`AbstractForwardModel.moving_sigmas`, `None` where there are none; the
    Jacobian holds them fixed) are held at those of the start across the steps, so that the
    solver's cost and Jacobian agree; once it stops, the sigmas at its solution (from the
    evaluation it accepted there) are compared with those held and, if they differ by more
    than `SIGMA_TOLERANCE` (relative), the solver starts again from the solution with them
    (Orear's iteration of effective variances; steps count towards `max_steps`), at most
    `HELD_WEIGHTS_ROUNDS` solves in all (then `RESULTS.weights_not_settled`)."""
    z = z0 if isinstance(z0, jax.Array) else jax.device_put(np.asarray(z0))  # a transfer, not a program
    if not np.all(np.isfinite(np.asarray(z))):
        return z, np.float64(np.inf), RESULTS.nonfinite, np.int32(0)
    arrays, static = split_arrays((solver, physical))
    r, J, sigma = jacobian_at(_physical_at(physical, z))
    # Every input of `_step` placed as the model's results are, at every step.  JAX compiles
    # a program again for inputs placed differently (committed to a device or not): an
    # exported program's call (the trace cache) returns committed results where the start is
    # not (`_step` was compiled twice in a tweezer fit's first call, 0.34 s of XLA each); a
    # plain one returns uncommitted results, and committing the step's inputs then made the
    # points it returns committed, so that the model program, first called at the uncommitted
    # start, was compiled again at the second point (the shape fit's, 12-14 s of XLA each).
    device = next(iter(r.devices())) if isinstance(r, jax.Array) and r.committed else None
    place = (lambda tree: tree) if device is None else functools.partial(jax.device_put, device=device)
    z, r, J = place((z, r, J))
    held, residuals = sigma, None
    at_z = (z, r, J, sigma)  # the model's evaluation at the solver's current point
    dynamic = _start(static, arrays, z, r, J)
    terminate, result, steps, solves = False, RESULTS.successful, 0, 1
    while steps < max_steps:
        z, dynamic, r, J, sigma, held = place((z, dynamic, r, J, sigma, held))
        fed = (dynamic.y_eval, r, J, sigma)
        z, dynamic, terminate, result, q_eval = _step(static, arrays, z, dynamic, r, J, sigma, held)
        steps += 1
        if steps < max_steps:
            # Asked for before `terminate` is read: JAX dispatches asynchronously, so the
            # model runs while Python waits on the step.  Wasted after the last step.
            r, J, sigma = jacobian_at(q_eval)
        terminate = bool(terminate)
        if held is not None and np.array_equal(np.asarray(z), np.asarray(fed[0])):
            at_z = fed  # the step accepted the point evaluated for it
        if terminate and held is not None and succeeded(result) and steps < max_steps:
            if not np.array_equal(np.asarray(at_z[0]), np.asarray(z)):
                # At the host's copy of z: placed as the start was, so `_physical_at` runs
                # the program it compiled there (a committed z would compile it again).
                at_z = (z, *jacobian_at(_physical_at(physical, np.asarray(z))))
            _, r, J, sigma = at_z
            if _moved(sigma, held):
                if solves == HELD_WEIGHTS_ROUNDS:
                    result = RESULTS.weights_not_settled
                    break
                held, solves = sigma, solves + 1
                z, r, J = place((z, r, J))
                dynamic = _start(static, arrays, z, r, J)
                continue
            residuals = r  # with the sigmas of the solution, as the fit's report sees them
        if terminate or not succeeded(result):
            break
    if succeeded(result) and not terminate:
        result = RESULTS.nonlinear_max_steps_reached
    if residuals is None:
        residuals = dynamic.f_info.residual  # at the last accepted point, z
    # In NumPy: a handful of one-operation programs, each a compilation or a cache lookup
    # on a process's first fit, for a sum.
    residuals = np.asarray(residuals)
    cost = 0.5 * float(np.sum(residuals * residuals))
    return z, np.float64(cost if np.isfinite(cost) else np.inf), result, np.int32(steps)


def _moved(sigma, held) -> bool:
    """Whether the moving sigmas `sigma` differ from `held` by more than `SIGMA_TOLERANCE`
    (relative) where both are finite."""
    sigma, held = np.asarray(sigma), np.asarray(held)
    both = np.isfinite(sigma) & np.isfinite(held) & (held > 0)
    return bool(np.any(np.abs(sigma[both] - held[both]) > SIGMA_TOLERANCE * held[both]))


@filter_jit
def _physical_at(physical, z):
    return physical(z)
