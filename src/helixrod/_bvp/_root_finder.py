"""The root finder of the shooting equations: Levenberg--Marquardt steps on a Jacobian
kept up to date by Broyden's secant updates, as an optimistix root finder."""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array

from .._misc import solve_small, tree_where

# A Broyden step that reduces |f| by less than this factor asks for a fresh Jacobian.
SLOW_PROGRESS = 0.1


class _State(eqx.Module):
    y_best: Array
    f_best: Array
    jac_best: Array
    aux_best: object
    cost_best: Array
    damping: Array
    fresh: Array
    refresh: Array
    step: Array


class LevenbergMarquardtBroyden(optx.AbstractRootFinder):
    """Newton's method for square systems with Levenberg--Marquardt damping and Broyden
    updates.

    Each step evaluates `fn` at the trial point of the previous one and accepts it if it
    lowers $\\tfrac12|f|^2$ (then the damping $\\lambda$ shrinks tenfold) or rejects it (the
    step is retried from the best point with $\\lambda$ ten times larger); the step solves
    $(J^TJ + \\lambda\\,\\mathrm{diag}J^TJ)\\,\\delta = -J^Tf$, Newton's step as $\\lambda\\to 0$
    (`damped=False`: plain Newton steps, always accepted).  The Jacobian $J$ is a fresh
    one (`jacobian`) at the first point, after a step that reduced $|f|$ by less than a
    factor `SLOW_PROGRESS` and after a step rejected with a secant Jacobian; otherwise the
    previous one with Broyden's rank-one secant update
    $J \\leftarrow J + (\\Delta f - J\\Delta y)\\Delta y^T/|\\Delta y|^2$, so that most steps cost one
    evaluation of `fn` (one integration of the rod) instead of seven.  `jacobian(y, args,
    aux)` is the fresh Jacobian at `y`, given `fn`'s aux there (the shooting equations pass
    the flows already integrated, `shooting_jacobian`, so `fn` is evaluated once per step,
    outside the choice between a fresh and a secant Jacobian).  Terminates when
    $\\max|f| <$ `atol` at the best point, which it returns; the residual there is
    `sol.stats["residual"]`.  The shooting residuals are scaled to order one, so there is
    no relative tolerance (`rtol` is 0: optimistix's interface asks for one).

    Written here rather than using `optimistix.LevenbergMarquardt` because a least-squares
    solver is differentiated through its normal equations (reverse mode through the
    integrator) and evaluates `fn` more than once per step (a larger compiled program).
    """

    atol: float
    jacobian: Callable
    norm: object = optx.max_norm
    damped: bool = True
    rtol: ClassVar[float] = 0.0

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        zeros = lambda s: jnp.zeros(s.shape, s.dtype)  # noqa: E731
        return _State(
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

    def step(self, fn, y, args, options, state: _State, tags):
        def secant(f):
            dy, df = y - state.y_best, f - state.f_best
            dy2 = jnp.sum(dy * dy)
            update = jnp.outer(df - state.jac_best @ dy, dy) / jnp.where(dy2 > 0, dy2, 1.0)
            good = (dy2 > 0) & jnp.all(jnp.isfinite(update))
            return jnp.where(good, state.jac_best + update, state.jac_best)

        f, aux = fn(y, args)
        jac = jax.lax.cond(state.refresh, lambda: self.jacobian(y, args, aux), lambda: secant(f))
        cost = 0.5 * jnp.sum(f * f)
        finite = jnp.all(jnp.isfinite(jac)) & jnp.isfinite(cost)
        accept = finite & (cost < state.cost_best) if self.damped else finite
        slow = ~(cost < SLOW_PROGRESS**2 * state.cost_best)
        y_best, f_best, aux_best = tree_where(accept, (y, f, aux), (state.y_best, state.f_best, state.aux_best))
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
            delta = solve_small(lhs, jac_best.T @ f_best)
        else:
            damping = jnp.where(accept, state.damping, jnp.inf)
            delta = solve_small(jac_best, f_best)
        delta = jnp.where(jnp.all(jnp.isfinite(delta)), delta, 0.0)
        # Relinearise after slow progress, or after a rejected step taken with a secant
        # Jacobian (a rejected step with an exact one only needs more damping).
        refresh = jnp.where(accept, slow, ~fresh)
        new_state = _State(y_best, f_best, jac_best, aux_best, cost_best, damping, fresh, refresh, state.step + 1)
        return y_best - delta, new_state, aux

    def terminate(self, fn, y, args, options, state: _State, tags):
        converged = self.norm(state.f_best) < self.atol
        stuck = state.damping > 1e12
        result = optx.RESULTS.where(stuck & ~converged, optx.RESULTS.nonlinear_divergence, optx.RESULTS.successful)
        return converged | stuck, result

    def postprocess(self, fn, y, aux, args, options, state: _State, tags, result):
        return state.y_best, state.aux_best, {"residual": state.f_best}
