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

from collections.abc import Callable

import jax
import jax.numpy as jnp
import lineax as lx
import optax
import optimistix as optx

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


def make_solver(name: str, rtol: float = 1e-10, atol: float = 1e-12, learning_rate: float = 1e-2):
    """The optimistix solver of a name in `SOLVERS`: Levenberg--Marquardt (`LevenbergMarquardt`)
    or Gauss--Newton on the residuals, or optax's L-BFGS or Adam on $\\tfrac12\\sum r^2$
    (through `optimistix.OptaxMinimiser`; for comparison)."""
    if name == "levenberg-marquardt":
        return LevenbergMarquardt(rtol=rtol, atol=atol)
    if name == "gauss-newton":
        return optx.GaussNewton(rtol=rtol, atol=atol)
    if name == "lbfgs":
        return optx.OptaxMinimiser(optax.lbfgs(), rtol=rtol, atol=atol)
    if name == "adam":
        return optx.OptaxMinimiser(optax.adam(learning_rate), rtol=rtol, atol=atol)
    raise ValueError(f"solver must be one of {SOLVERS} or an optimistix least-squares solver or minimiser, got {name!r}")
