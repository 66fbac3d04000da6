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
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optax
import optimistix as optx

from .._misc import jacobian_forward

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


class LevenbergMarquardt(optx.AbstractGaussNewton):
    """Levenberg--Marquardt (optimistix's damped Newton descent with a QR solve) with the
    round-off acceptance of `RoundoffTrustRegion`."""

    rtol: float
    atol: float
    norm: Callable
    descent: optx.DampedNewtonDescent
    search: RoundoffTrustRegion
    verbose: Callable

    def __init__(self, rtol: float, atol: float, norm: Callable = optx.max_norm, verbose: Callable | None = None):
        self.rtol = rtol
        self.atol = atol
        self.norm = norm
        self.descent = optx.DampedNewtonDescent(linear_solver=lx.QR())
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
