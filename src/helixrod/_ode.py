"""helixrod's ODE solves: diffrax's solvers and step-size controllers, stepped by a loop of
helixrod's own in forward mode, which saves from the solver's continuous extension.

`diffrax.diffeqsolve` costs helixrod's programs in three ways that its own loop does not:

* it computes its end time less 100 ULPs by 100 sequential `prevbefore`s, ~2450 HLO
  instructions in every program with a solve, which XLA folds into one constant where the
  end time is a constant (as helixrod's always is) but slowly in a large program: with
  them replaced by the identity, the continuation program of a force-extension curve
  compiled in 2.3-2.8 s against 3.0-3.3 s (fresh processes on 2 cores).  Here the end time
  less 100 ULPs is computed on the host, once.  First calls, cold, fresh processes on 2
  cores alternating with `diffrax.diffeqsolve`'s loop (`benchmarks/bench_first_calls.py`'s
  cases): `solve_static` 0.58-0.71 against 0.86-0.93 s, its `jax.grad` 1.83 against
  2.02-2.12 s, a 50-point force-extension curve 4.44-4.61 against 4.75-5.04 s, one across
  its critical force 4.81-4.82 against 4.97-5.39 s, `solve_boundary_value` 3.36-3.61
  against 3.34-3.56 s; later calls the same (a planar elastica, one core, best of 1500:
  58-61 against 60-61 us);
* it traces the step up to three times (twice more to find which of its outputs are
  static);
* it checks `SaveAt(ts)` (increasing, within the interval) with `equinox.error_if`, whose
  raising mode is a host callback whenever the save points are traced, and JAX keeps no
  program with a host callback in its persistent compilation cache: every process compiled
  `solve_static`'s saving program again (a warm first call of 4.4-5.0 s with 201 saved
  points, 0.41-0.44 s without the check; one core).  helixrod checks the save points itself
  (before the call where they are concrete, `valid_input` where they are traced).

`solve_ode`'s loop is diffrax's (`diffrax._integrate.loop`) for what helixrod uses: an
explicit solver, an adaptive or constant step-size controller that makes no jumps, no
events, the state saved at the end or at increasing points from each accepted step's
interpolation (`interpolation_cls` of the solver), as diffrax saves them.  The steps, the
accepted and rejected counts and the result codes are diffrax's, and so are the saved values,
bitwise in most programs, to round-off (~1e-12 after 1400 steps) where XLA fuses the
arithmetic of the two programs differently (`tests/test_ode.py`).  Each saved point is one
row of one buffer (`_flat`): one update a point and one fill before the solve instead of one
a leaf of the state (with the rod's four leaves that cut the fixed cost of saving by half: a
planar elastica of 24 steps, one core, 66 -> 60 us with one saved point, against 55 us
saving the end only).  Reverse-mode adjoints
(which differentiate diffrax's checkpointed loop) and implicit solvers (whose root finder
diffrax configures from the controller) go to `diffrax.diffeqsolve`.
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def solve_ode(terms, solver, t0, t1, dt0, y0, *, ts, args, stepsize_controller, adjoint, max_steps: int | None):
    """The solve of `diffrax.diffeqsolve(terms, solver, t0, t1, dt0, y0, args=args, ...,
    throw=False)` from the constant times `t0 < t1`, saved at the increasing points `ts` in
    `[t0, t1]` (unchecked; `None`: at `t1` only): `(saved values, result, stats)`, the values
    with a leading axis (one row at `t1` only), `result` a `diffrax.RESULTS`, `stats` the
    step counts `num_steps`, `num_accepted_steps`, `num_rejected_steps` (`max_steps=None`: no
    cap on the steps).  With `adjoint=diffrax.ForwardMode()` and an explicit solver the loop
    is `_forward_loop` (module docstring), otherwise diffrax's."""
    if not _constant_time(t0, "t0") < _constant_time(t1, "t1"):
        raise ValueError(f"solve_ode integrates forward from t0 to t1, got t0={t0}, t1={t1}")
    if not isinstance(adjoint, diffrax.ForwardMode) or isinstance(solver, diffrax.AbstractImplicitSolver):
        saveat = diffrax.SaveAt(t1=True) if ts is None else diffrax.SaveAt(ts=ts)
        sol = diffrax.diffeqsolve(
            terms, solver, t0, t1, dt0, y0, args=args, saveat=saveat, stepsize_controller=stepsize_controller,
            adjoint=adjoint, max_steps=max_steps, throw=False,
        )
        return sol.ys, sol.result, sol.stats
    if isinstance(solver, diffrax.AbstractRungeKutta) and solver.scan_kind is None:
        # What `ForwardMode` does to a Runge-Kutta solver: a loop over the stages that
        # forward mode can differentiate.
        solver = eqx.tree_at(lambda s: s.scan_kind, solver, "lax", is_leaf=lambda x: x is None)
    return _forward_loop(terms, solver, t0, t1, dt0, y0, ts, args, stepsize_controller, max_steps)


def _constant_time(t, name: str) -> float:
    """The value of a time that must be a constant (its dtype, which sets the solve's, stays
    with the caller's object)."""
    try:
        return float(np.asarray(t))
    except (TypeError, jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError):
        raise ValueError(f"solve_ode: {name} must be a constant, got a traced value") from None


def _before(t1: np.ndarray, ulps: int) -> np.ndarray:
    """`t1` less `ulps` ULPs (`equinox.internal.prevbefore` applied `ulps` times): where a
    step's end lands above it, the step is clipped to end at `t1` (diffrax's rule)."""
    t = t1
    for _ in range(ulps):
        t = -np.finfo(t.dtype).tiny if t == 0 else np.nextafter(t, -np.inf, dtype=t.dtype)
    return np.asarray(t, t1.dtype)


def _forward_loop(terms, solver, t0, t1, dt0, y0, ts, args, controller, max_steps):
    """`solve_ode` with an explicit solver in forward mode: diffrax's loop without its
    events, progress meter and jumps (module docstring)."""
    timelikes = [t0, t1] + [x for x in (dt0, ts) if x is not None]
    with jax.numpy_dtype_promotion("standard"):
        dtype = jnp.result_type(*timelikes)
        if not jnp.issubdtype(dtype, jnp.floating):
            dtype = jnp.result_type(float)

        def promote(leaf):
            return jnp.asarray(leaf, jnp.result_type(leaf, dtype))

        y0 = jax.tree.map(promote, y0)
    t_end = _before(np.asarray(t1, dtype), 100)
    t0, t1 = jnp.asarray(t0, dtype), jnp.asarray(t1, dtype)
    dt0 = None if dt0 is None else jnp.asarray(dt0, dtype)
    ts = None if ts is None else jnp.asarray(ts).astype(dtype)
    error_order = solver.error_order(terms)
    tnext, controller_state = controller.init(terms, t0, t1, y0, dt0, args, solver.func, error_order)
    tnext = jnp.minimum(tnext, t1)
    solver_state = solver.init(terms, t0, tnext, y0, args)
    count = 0 if ts is None else ts.shape[0]
    row = _flat(y0)
    saved = jnp.broadcast_to(_infinite_like(row), (count,) + row.shape)
    zero = jnp.asarray(0)  # diffrax's counters: JAX's default integer, weakly typed
    RESULTS = diffrax.RESULTS

    def unfinished(state):
        _, tprev, _, _, _, result, steps, *_ = state
        going = (tprev < t1) & (result == RESULTS.successful)
        return going if max_steps is None else going & (steps < max_steps)

    def step(state):
        y, tprev, tnext, solver_state, controller_state, result, steps, accepted, rejected, index, saved = state
        y1, y_error, dense_info, solver_state1, solver_result = solver.step(
            terms, tprev, tnext, y, args, solver_state, False
        )
        # A NaN error (a vector field evaluated out of its domain) rejects the step.
        y_error = jax.tree.map(lambda e: jnp.where(jnp.isnan(e), jnp.inf, e), y_error)
        keep, tprev1, tnext1, made_jump, controller_state, controller_result = controller.adapt_step_size(
            tprev, tnext, y, y1, args, y_error, error_order, controller_state
        )
        if made_jump is not False:
            raise NotImplementedError("solve_ode: step-size controllers that make jumps (jump_ts) are not supported")
        tprev1 = jnp.minimum(tprev1, t1)
        tnext1 = jnp.where(tnext1 > t_end, jnp.where(keep, t1, tprev1 + 0.5 * (t1 - tprev1)), tnext1)
        y = jax.tree.map(lambda new, old: jnp.where(keep, new, old), y1, y)
        solver_state = jax.tree.map(lambda new, old: jnp.where(keep, new, old), solver_state1, solver_state)
        solver_result = RESULTS.where(keep, solver_result, RESULTS.successful)
        result = RESULTS.where(result == RESULTS.successful, solver_result, result)
        result = RESULTS.where(result == RESULTS.successful, controller_result, result)
        if count:
            interpolation = solver.interpolation_cls(t0=tprev, t1=tnext, **dense_info)

            def passed(carry):
                i, _ = carry
                return keep & (i < count) & (ts[jnp.minimum(i, count - 1)] <= tnext)

            def save(carry):
                i, saved = carry
                return i + 1, saved.at[i].set(_flat(interpolation.evaluate(ts[i])))

            index, saved = jax.lax.while_loop(passed, save, (index, saved))
        return (y, tprev1, tnext1, solver_state, controller_state, result, steps + 1,
                accepted + jnp.where(keep, 1, 0), rejected + jnp.where(keep, 0, 1), index, saved)

    state = (y0, t0, tnext, solver_state, controller_state, RESULTS.successful, zero, zero, zero, zero, saved)
    y, tprev, _, _, _, result, steps, accepted, rejected, _, saved = jax.lax.while_loop(unfinished, step, state)
    result = RESULTS.where((tprev < t1) & (result == RESULTS.successful), RESULTS.max_steps_reached, result)
    ys = jax.tree.map(lambda leaf: leaf[None], y) if ts is None else _unflat(saved, y0)
    stats = dict(num_steps=steps, num_accepted_steps=accepted, num_rejected_steps=rejected, max_steps=max_steps)
    return ys, result, stats


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
