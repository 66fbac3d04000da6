"""Saved points of a diffrax solve without `diffrax.SaveAt(ts)`: taken from the solver's
continuous extension after each accepted step, as diffrax does, by a step-size controller.

`diffrax.diffeqsolve` checks `SaveAt(ts)` (increasing, within the interval) with
`equinox.error_if`, whose raising mode is a host callback whenever the save points are
traced, and JAX keeps no program with a host callback in its persistent compilation
cache: every process compiled `solve_static`'s saving program again (a warm first call of
4.4-5.0 s with 201 saved points, 0.41-0.44 s since; one core).  helixrod checks the save points
itself (before the call where they are concrete, `valid_input` where they are traced).

The saving needs the step's continuous extension and whether the step is accepted.  The
solver sees the first, the step-size controller the second; and diffrax keeps or discards
the solver's state with the step by a select of the whole state, which copies buffers
written inside the step (measured: 201 saved points 123 us against 92 us with diffrax's
saving, a planar elastica of 24 steps, one core).  So `_PassingSolver` hands the step's
interpolation data on with its error estimate (the one output diffrax passes from the
solver to the controller, as `(error, dense_info)`), and `_SavingController` strips it,
asks the wrapped controller, and saves from the accepted steps into a buffer in its own
state, which diffrax carries as it is.  The values are those of diffrax's saving: the
same interpolation at the same points.  The buffer holds each point's state as one row
(`_flat`), one update per point and one fill before the solve instead of one per leaf
of the state: with the rod's four leaves that cut the fixed cost of saving by half (a
planar elastica of 24 steps, one core: 66 -> 60 us with one saved point, against 55 us
saving the end only).
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


class _PassingSolver(diffrax.AbstractAdaptiveSolver, diffrax.AbstractWrappedSolver):
    """`solver`, whose error estimate also carries the step's `dense_info`."""

    solver: diffrax.AbstractSolver

    @property
    def term_structure(self):
        return self.solver.term_structure

    @property
    def interpolation_cls(self):
        return self.solver.interpolation_cls

    @property
    def term_compatible_contr_kwargs(self):
        return self.solver.term_compatible_contr_kwargs

    def order(self, terms):
        return self.solver.order(terms)

    def strong_order(self, terms):
        return self.solver.strong_order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms)

    @property
    def scan_kind(self):
        return getattr(self.solver, "scan_kind", None)

    def init(self, terms, t0, t1, y0, args):
        return self.solver.init(terms, t0, t1, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        y1, y_error, dense_info, solver_state, result = self.solver.step(terms, t0, t1, y0, args, solver_state, made_jump)
        return y1, (y_error, dense_info), dense_info, solver_state, result

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)


class _SavingController(diffrax.AbstractStepSizeController):
    """`controller`, which also saves the solution at the increasing points `ts` from each
    accepted step's interpolation (`interpolation_cls` of the solver), with
    `_PassingSolver`.  Its state: `(controller's state, index of the next point, saved
    values)`, the values (a row of `_flat(y)` per point) `inf` where no step reached (a
    failed solve), as diffrax leaves them."""

    controller: diffrax.AbstractStepSizeController
    ts: Float[Array, " points"]
    interpolation_cls: type = eqx.field(static=True)

    def wrap(self, direction):
        return _SavingController(self.controller.wrap(direction), self.ts * direction, self.interpolation_cls)

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        tnext, state = self.controller.init(terms, t0, t1, y0, dt0, args, func, error_order)
        row = _flat(y0)
        return tnext, (state, jnp.asarray(0), jnp.broadcast_to(_infinite_like(row), self.ts.shape + row.shape))

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state):
        y_error, dense_info = y_error
        state, index, buffers = controller_state
        keep, tprev, tnext, made_jump, state, result = self.controller.adapt_step_size(
            t0, t1, y0, y1_candidate, args, y_error, error_order, state
        )
        interpolation = self.interpolation_cls(t0=t0, t1=t1, **dense_info)
        count = self.ts.shape[0]

        def passed(carry):
            i, _ = carry
            return keep & (i < count) & (self.ts[jnp.minimum(i, count - 1)] <= t1)

        def save(carry):
            i, saved = carry
            return i + 1, saved.at[i].set(_flat(interpolation.evaluate(self.ts[i])))

        index, buffers = jax.lax.while_loop(passed, save, (index, buffers))
        return keep, tprev, tnext, made_jump, (state, index, buffers), result


def _infinite_like(row):
    """`inf` in `row`'s shape, computed from `row` rather than filled as a constant.  A
    constant fill is a kernel with no input, one more ready at the start of the program
    (seven for `solve_static` with saved points); with more ready kernels than XLA's CPU
    runtime runs in one thread (and any buffer above 512 bytes) it hands half of them to
    its thread pool, and the caller then waits for a thread on another core: two context
    switches a call, whose cost on a 2-core machine varied from process to process.
    Measured on a planar elastica with 201 saved points (2 cores, fresh processes): 86-152
    us a call over 8 processes with the constant, 89-91 us with this fill (65 us saving
    the end only, 89-95 us pinned to one core either way)."""
    return jnp.where(jnp.isfinite(row), jnp.inf + 0.0 * row, jnp.inf)


def _flat(y):
    """The state `y` as one row: each saved point is one row of one buffer, written by one
    update (not one a leaf), and the buffer is filled once before the loop."""
    return jnp.concatenate([jnp.ravel(leaf) for leaf in jax.tree.leaves(y)])


def _unflat(rows, like):
    """Rows of `_flat(y)` as states shaped like `like`, with a leading axis (in the rows'
    dtype, which is diffrax's: it promotes every leaf of the state with the times)."""
    leaves, structure = jax.tree.flatten(like)
    ends = np.cumsum([np.size(leaf) for leaf in leaves])
    return jax.tree.unflatten(structure, [
        rows[:, end - np.size(leaf) : end].reshape(rows.shape[:1] + np.shape(leaf))
        for leaf, end in zip(leaves, ends)
    ])


def diffeqsolve_saving(terms, solver, t0, t1, dt0, y0, *, ts, stepsize_controller, adjoint, **kwargs):
    """`diffrax.diffeqsolve(terms, solver, t0, t1, dt0, y0, ...)` saving at the increasing
    points `ts` in `[t0, t1]` (`None`: at `t1` only), unchecked: `(saved points, saved
    values, solution)`.  With `adjoint=diffrax.ForwardMode()` and an explicit solver the
    saving is `_SavingController`'s (its loop over the points is not
    reverse-differentiable); other adjoints, which may differentiate the steps in reverse
    mode, and implicit solvers (whose root finder diffrax configures through the solver's
    fields) get `diffrax.SaveAt(ts=ts)`."""
    if ts is None or not isinstance(adjoint, diffrax.ForwardMode) or isinstance(solver, diffrax.AbstractImplicitSolver):
        saveat = diffrax.SaveAt(t1=True) if ts is None else diffrax.SaveAt(ts=ts)
        sol = diffrax.diffeqsolve(
            terms, solver, t0, t1, dt0, y0, saveat=saveat, stepsize_controller=stepsize_controller, adjoint=adjoint,
            **kwargs,
        )
        return sol.ts, sol.ys, sol
    if isinstance(solver, diffrax.AbstractRungeKutta) and solver.scan_kind is None:
        # What `ForwardMode` does to a Runge-Kutta solver (a loop over the stages that
        # forward mode can differentiate); it cannot see it through the wrapper.
        solver = eqx.tree_at(lambda s: s.scan_kind, solver, "lax", is_leaf=lambda x: x is None)
    controller = _SavingController(stepsize_controller, ts, solver.interpolation_cls)
    sol = diffrax.diffeqsolve(
        terms, _PassingSolver(solver), t0, t1, dt0, y0, saveat=diffrax.SaveAt(controller_state=True),
        stepsize_controller=controller, adjoint=adjoint, **kwargs,
    )
    return ts, _unflat(sol.controller_state[2], y0), sol
