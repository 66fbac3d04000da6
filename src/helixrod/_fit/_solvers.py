"""The solvers `fit_stiffness` knows by name, and helixrod's Levenberg--Marquardt.

optimistix's `LevenbergMarquardt` accepts a step only when the loss falls by a fraction of
the reduction its quadratic model predicts.  At the minimum both are at the level of
floating-point round-off -- for models whose predictions are much larger than their
residuals (a 3 um extension measured to 3 nm) the loss is noisy at ~1e-13 relative, more
than the predicted reduction of a converged step -- so it rejects step after step, shrinking
the trust region by 4 each time until the step is below the tolerance: measured on an
80-point tweezer fit, 4 accepted steps and 22 rejected ones.  `LevenbergMarquardt` here
also accepts a step whose predicted and actual changes of the loss are both below
`ROUNDOFF` times the loss, after which the Cauchy termination sees the converged step.

Its damped steps come from the normal equations (`NormalDampedNewtonDescent`), not from
lineax's QR of the damped least-squares problem: the same steps in a few operations on a
matrix of the size of the parameters, where a QR (three LAPACK calls at every step) took
~2 us of a step's ~10-25 us in a helix fit.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
import optimistix as optx

from .._misc import jacobian_forward, solve_small

#: The solvers `fit_stiffness` knows by name (for the command line; or pass an optimistix
#: least-squares solver or minimiser, e.g. `optimistix.OptaxMinimiser(optax.adam(1e-2), ...)`).
SOLVERS = ("levenberg-marquardt", "gauss-newton", "lbfgs", "adam")
#: Relative change of the loss below which a trust-region step counts as converged.
ROUNDOFF = 1e-10


class RoundoffTrustRegion(optx.ClassicalTrustRegion):
    """`optimistix.ClassicalTrustRegion` that also accepts a step when its predicted
    reduction and its actual change of the loss are both below `ROUNDOFF` times the loss
    (shrinking the trust radius as for a rejected step)."""

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        _, accept, result, new_state = super().step(first_step, y, y_eval, f_info, f_eval_info, state)
        predicted = self.predict_reduction(jax.tree.map(jnp.subtract, y_eval, y), f_info)
        loss, loss_eval = f_info.as_min(), f_eval_info.as_min()
        noise = ROUNDOFF * jnp.abs(loss)
        at_roundoff = ~accept & (-predicted <= noise) & (loss_eval - loss <= noise)
        # The radius still shrinks as for a rejected step: where the model's own noise keeps
        # the Gauss-Newton step above the tolerance, successive round-off steps get smaller
        # and the Cauchy termination is reached.
        return new_state.step_size, accept | at_roundoff, result, new_state


#: The smallest damping of `NormalDampedNewtonDescent`, relative to the smallest diagonal
#: entry of $J^TJ$.  Without a floor, the step of a Jacobian with an exact null direction
#: (fewer observations than parameters, force-only data; in the test, a repeated column)
#: was NaN once the trust region had grown to a step size of 1e20 (its component along the
#: null direction 1.3e-7 at 1e10, the step's norm 1.2); with it, 9.5e-5 at any step size,
#: where the cost does not see it.  Relative to the largest entry instead, a fit with one
#: residual 1e8 times as sensitive as the others (a register at a cusp,
#: `tests/test_stress.py`) was damped in every other direction and ran out of steps.
NORMAL_DAMPING_FLOOR = 1e-12


class _NormalEquations(eqx.Module):
    gram: jax.Array
    gradient: jax.Array


class NormalDampedNewtonDescent(optx.AbstractDescent):
    """The damped Newton (Levenberg--Marquardt) step $\\delta = -(J^TJ + \\lambda I)^{-1}J^Tr$,
    $\\lambda$ = 1 / step size (as `optimistix.DampedNewtonDescent`), from the normal
    equations: $J^TJ$ and $J^Tr$ formed once per accepted point (`query`) and each trial's
    small system solved by `solve_small` (no LAPACK call), with $\\lambda$ at least
    `NORMAL_DAMPING_FLOOR` times the smallest diagonal entry of $J^TJ$.  Forming $J^TJ$
    squares the condition number of the step, not of the fit: its residuals, cost and
    error analysis are computed from $J$ itself.  Measured on `benchmarks/bench_fit.py`'s
    30 random helix problems (one core, process time per default fit, two alternating
    runs each): median 4.30-4.45 ms with lineax's QR, 4.08-4.15 ms here, every problem at
    its global minimum either way."""

    def init(self, y, f_info_struct) -> _NormalEquations:
        n = y.shape[0]
        return _NormalEquations(jnp.zeros((n, n), y.dtype), jnp.zeros(n, y.dtype))

    def query(self, y, f_info, state) -> _NormalEquations:
        J = f_info.jac.as_matrix()
        return _NormalEquations(J.T @ J, J.T @ f_info.residual)

    def step(self, step_size, state: _NormalEquations):
        gram, gradient = state.gram, state.gradient
        tiny, huge = jnp.finfo(gradient.dtype).eps, jnp.finfo(gradient.dtype).max
        damping = jnp.where(step_size > tiny, 1 / jnp.where(step_size > tiny, step_size, 1.0), huge)
        damping = jnp.maximum(damping, NORMAL_DAMPING_FLOOR * jnp.min(jnp.diagonal(gram)))
        system = gram + damping * jnp.eye(gradient.shape[0], dtype=gradient.dtype)
        return -solve_small(system, gradient), optx.RESULTS.successful


class LevenbergMarquardt(optx.AbstractGaussNewton):
    """Levenberg--Marquardt (optimistix's Gauss--Newton loop with the damped Newton steps
    of `NormalDampedNewtonDescent`) with the round-off acceptance of
    `RoundoffTrustRegion`."""

    rtol: float
    atol: float
    norm: Callable
    descent: NormalDampedNewtonDescent
    search: RoundoffTrustRegion
    verbose: Callable

    def __init__(self, rtol: float, atol: float, norm: Callable = optx.max_norm, verbose: Callable | None = None):
        self.rtol = rtol
        self.atol = atol
        self.norm = norm
        self.descent = NormalDampedNewtonDescent()
        self.search = RoundoffTrustRegion()
        self.verbose = _quiet if verbose is None else verbose


def _quiet(**_):
    pass


@functools.lru_cache(maxsize=64)
def make_solver(name: str, rtol: float = 1e-10, atol: float = 1e-12, learning_rate: float = 1e-2):
    """The optimistix solver of a name in `SOLVERS`: Levenberg--Marquardt (`LevenbergMarquardt`)
    or Gauss--Newton on the residuals, or optax's L-BFGS or Adam on $\\tfrac12\\sum r^2$
    (through `optimistix.OptaxMinimiser`; for comparison).  Solvers are immutable: one object
    per choice is built once and shared (building one costs ~0.1 ms, ~1 % of a small fit)."""
    if name == "levenberg-marquardt":
        return LevenbergMarquardt(rtol=rtol, atol=atol)
    if name == "gauss-newton":
        return optx.GaussNewton(rtol=rtol, atol=atol)
    if name == "lbfgs":
        return optx.OptaxMinimiser(optax.lbfgs(), rtol=rtol, atol=atol)
    if name == "adam":
        return optx.OptaxMinimiser(optax.adam(learning_rate), rtol=rtol, atol=atol)
    raise ValueError(f"solver must be one of {SOLVERS} or an optimistix least-squares solver or minimiser, got {name!r}")


def with_materialised_jacobian(fn: Callable, through_loops: bool = False) -> Callable:
    """`fn(z, args)` (residuals) whose forward derivative in `z` is its Jacobian, computed
    once (`jacobian_forward`: one linearisation, all directions in one batch; with
    `through_loops`, `jax.jacfwd`, for residuals computed by loops) and then multiplied.

    An optimistix Gauss--Newton step linearises `fn` and applies the linear map in three
    places -- the Jacobian of the QR solve (all directions), the predicted reduction of the
    trust region (one) and `RoundoffTrustRegion`'s own prediction (one) -- and each is a
    trace, and a compiled copy, of the forward-mode program.  For the finite-rod models
    that is a shooting solve's tangent integrations: the README's shape fit compiled three
    copies of them.  Here the copies are matrix products, and the state carried between
    steps is the matrix instead of the linearisation's intermediates.  Costs the Jacobian
    (all directions) at rejected trial points too, where one direction was enough."""

    @eqx.filter_custom_jvp
    def materialised(z, args):
        return fn(z, args)

    @materialised.def_jvp
    def _jvp(primals, tangents):
        z, args = primals
        t_z, t_args = tangents
        if jax.tree.leaves(t_args):
            raise NotImplementedError("with_materialised_jacobian: differentiable in z only, not in args")
        if t_z is None:
            value = fn(z, args)
            return value, jnp.zeros_like(value)
        jacobian, value = jacobian_forward(lambda zz: (fn(zz, args),) * 2, z, has_aux=True, through_loops=through_loops)
        return value, jacobian @ t_z

    return materialised


def final_residuals(solution: optx.Solution):
    """The residuals at `solution.value` kept by a Gauss--Newton-type least-squares solver
    (optimistix's `f_info` of its last accepted point), or `None` where the solver keeps
    none (then evaluate them anew)."""
    info = getattr(solution.state, "f_info", None)
    return getattr(info, "residual", None)
