"""End-response curves of finite springs and tweezer filaments, against the bulk helix.

A rod of length $L$ in the canonical placement (`axial_ends`) is loaded along its axis by two
controls (`AXIAL_CONTROLS`): force-extension at fixed axial moment (a hooked spring) or at
fixed end rotation (a magnetic tweezer), rotation curves at fixed force (tweezer: torque and
extension against turns) or at fixed extension (a spring twisted between grips), and in
general any sequence of control pairs (`axial_response`).  Each point is one boundary-value
solve; by default the points are solved in order, each warm-started from the previous one
(continuation), inside one compiled `lax.scan` -- a step that does not converge at once, or
turns a prescribed end rotation by more than 1.5 rad, in substeps (`_solve_from`);
`mode="independent"` solves them in parallel (`vmap`), each from the bulk-helix guess --
fine where that guess is good (a load through the axis is an initial-value problem and
needs no continuation).

Observables (`AXIAL_OBSERVABLES`): axial force $F = N\\cdot e_z$, axial moment $M$ (about the
axis), extension $h = (x(L) - x(0))\\cdot e_z$, end rotation $\\Theta$: the unloaded
$\\Theta_0 = L|\\hat u|$ plus the twist about $e_z$ of $D(L)D_0(L)^T$ (the end frame relative
to the unloaded end frame), with the whole turns each point's rod holds, counted along it
by its stability test (`BoundaryValueSolution.rotation`; where not counted, by continuity
along the curve from the bulk prediction at the first point).  The bulk (uniform-helix) prediction at the same
controls follows its own branch by continuation from the unloaded helix; the difference is
the end effect of the clamp, which does not vanish at a clamp but whose share of the
totals falls like $1/L$ (tested in `tests/test_bvp.py`).
"""

from __future__ import annotations

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._compile import committed_placement, compile_ahead, jit, leaf_shapes, once_per_signature
from .._geometry import unloaded_observables, unloaded_state
from .._lie import twist_angle, unwrap_near
from .._misc import check_choice, finite_scalar, float_dtype, is_concrete, no_gradient, replaced, tree_where
from .._progress import ProgressArgument, ProgressReport, batch_size, check_progress, progress_bar, scan_in_batches
from .._rod import check_one_rod
from .._status import RESULTS, raise_if_failed, set_code, succeeded
from ._bulk import BulkHelix, bulk_helix_at
from ._ends import AXIAL_CONTROLS, AXIAL_OBSERVABLES, CONTROL_INDEX, LOADED, EndCondition, axial_controls, axial_end_condition, unloaded_clamp
from ._options import BoundaryValueOptions, with_settings
from ._rotation import holds_turns
from ._shooting import WarmStart, default_warm_start
from ._solve import (
    BoundaryValueSolution,
    automatic_segments,
    fit_guess,
    needed_segments,
    parse_guess,
    resolved_stability,
    solve,
    stability_at_points,
    stability_inputs,
    test_pieces_ahead,
    with_stability,
)

MODES = ("continuation", "independent")


class ResponseCurve(eqx.Module):
    """A response curve of a finite rod and the bulk (uniform-helix) prediction.

    `controls`: the prescribed pair (a key of `AXIAL_CONTROLS`, e.g. `"force-rotation"`),
    `swept` the one that varies along the curve, `held` the other; `length` $L$.  Per point
    (shape `(n,)`): `force`, `moment`, `extension`, `rotation` of the finite rod (controls
    as prescribed, responses as solved; NaN where a solve failed, or where the rod holds
    other whole turns than a prescribed rotation asks for, `other_whole_turns`: a
    `guess` with other turns, or an independent point whose bulk guess has them; module
    docstring for the conventions) and `bulk_force`, `bulk_moment`, `bulk_extension`, `bulk_rotation` of the
    uniform helix with the same two controls (extension and rotation totals over $L$);
    `result` (a `RESULTS` code per point) and `ok`, `bulk_ok`, `residual`, `num_steps`;
    `solutions` the `BoundaryValueSolution` of every point (batched, end state only).

    Stability per point: `stable`, `instability_index`, `stability_margin` (as
    `BoundaryValueSolution`), tested on `options.stability_pieces` pieces and, where that
    does not resolve a converged point's wrench, again on more, as `solve_boundary_value`
    does (concrete inputs; under `jax.jit`/`vmap` such a point keeps index -1);
    `solutions.stability_pieces` is the most any point was tested on.  `critical`: the
    value of the swept control at which the curve first loses stability (between the last
    stable point and the next -- unstable, or failed where the branch ends at a fold --
    located by bisection on the solutions; NaN if it never does, where stability is not
    defined, in `mode="independent"` (its points are no branch to bisect along) or under
    `jax.jit`/`vmap`), and `critical_kind`: `"branch point"` (the branch goes on through it,
    now unstable: a bifurcation, as Euler's), `"fold"` (the branch ends there: no nearby
    equilibrium beyond it), or `"none"`; `critical_force`, `critical_rotation` name it.
    Where the solves fail on the way to the loss (between a stable point whose margin has
    not fallen and later unstable ones) it is not located: NaN, `"none"`; read the
    points' `instability_index`.
    """

    controls: str = eqx.field(static=True)
    swept: str = eqx.field(static=True)
    length: Float[Array, ""]
    force: Float[Array, " n"]
    moment: Float[Array, " n"]
    extension: Float[Array, " n"]
    rotation: Float[Array, " n"]
    bulk_force: Float[Array, " n"]
    bulk_moment: Float[Array, " n"]
    bulk_extension: Float[Array, " n"]
    bulk_rotation: Float[Array, " n"]
    result: RESULTS
    bulk_ok: Bool[Array, " n"]
    residual: Float[Array, " n"]
    num_steps: Int[Array, " n"]
    solutions: BoundaryValueSolution
    critical: Float[Array, ""]
    critical_kind: str = eqx.field(static=True)

    @property
    def ok(self) -> Bool[Array, " n"]:
        """Whether each point's solve succeeded."""
        return self.result == RESULTS.successful

    @property
    def stable(self) -> Bool[Array, " n"]:
        """Whether each point converged to a stable equilibrium."""
        return self.solutions.stable

    @property
    def instability_index(self) -> Int[Array, " n"]:
        """Unstable directions at each point (-1: not defined)."""
        return self.solutions.instability_index

    @property
    def stability_margin(self) -> Float[Array, " n"]:
        """The stability margin at each point (NaN: not defined)."""
        return self.solutions.stability_margin

    @property
    def critical_force(self) -> Float[Array, ""]:
        """`critical` of a curve swept in force."""
        return self._critical("force")

    @property
    def critical_rotation(self) -> Float[Array, ""]:
        """`critical` of a curve swept in rotation."""
        return self._critical("rotation")

    def _critical(self, name):
        if self.swept != name:
            raise ValueError(f"this curve is swept in {self.swept}, not {name}: read critical_{self.swept}")
        return self.critical

    @property
    def held(self) -> str:
        """The control held fixed (the other of `controls`)."""
        first, second = self.controls.split("-")
        return second if self.swept == first else first

    def end_effect(self, name: str) -> Array:
        """Finite minus bulk value of the observable `name` (e.g. `"extension"`)."""
        if name not in AXIAL_OBSERVABLES:
            raise ValueError(f"end_effect: unknown observable {name!r}")
        return getattr(self, name) - getattr(self, "bulk_" + name)


def axial_observables(rod, length, sol: BoundaryValueSolution, rotation_hint) -> Array:
    """(F, M, h, Theta) of a solution in the canonical placement (module docstring); the
    whole turns of Theta are those nearest `rotation_hint`."""
    x0 = sol.node_position[0]
    force = sol.force[2]
    moment = (sol.moment0 + jnp.cross(x0, sol.force))[2]
    extension = sol.end_position[2] - x0[2]
    _, frame_ref = unloaded_state(rod, length)
    _, theta0 = unloaded_observables(rod, length)
    rotation = theta0 + unwrap_near(twist_angle(sol.end_frame @ frame_ref.T), rotation_hint - theta0)
    return jnp.stack([force, moment, extension, rotation])


def _no_bulk(dtype) -> BulkHelix:
    nan = jnp.full((), jnp.nan, dtype)
    return BulkHelix(u=jnp.full(3, jnp.nan, dtype), mu1=nan, mu2=nan, force=nan, moment=nan, extension=nan,
                     rotation=nan, result=RESULTS.invalid_input)


def _curve_setup(rod, length):
    """The clamped start, the unloaded end rotation and the unloaded bulk guess of a curve."""
    start = unloaded_clamp(no_gradient(rod))
    _, theta0 = unloaded_observables(rod, length)
    return start, theta0, _unloaded_bulk_guess(rod, jnp.asarray(rod.uhat).dtype, jnp)


def _unloaded_bulk_guess(rod, dtype, xp):
    """The warm start of a curve's first bulk solve, `bulk_helix_at`'s (u, mu1, mu2): the
    unloaded rod (`xp`: `jnp`, or `np` for a carry made on the host)."""
    return xp.asarray(rod.uhat, dtype), xp.zeros((), dtype), xp.zeros((), dtype)


def _observe(rod, length, kind, sol, bulk, v, hint):
    hint = jnp.where(kind == LOADED, hint, v[3])
    obs = jnp.where(sol.ok, axial_observables(rod, length, sol, hint), jnp.nan)
    # Each observable an output of its own: the curve's columns come out of its program,
    # not from slices compiled one by one at its first call.  The bulk prediction too is
    # NaN where the input is invalid (a traced length <= 0: the bulk equations hold for any).
    return tuple(obs), tuple(jnp.where(bulk.ok & sol.valid_input, bulk.observables, jnp.nan))


def _independent_points(rod, length, kind, values, hints, options: BoundaryValueOptions, with_bulk: bool, guess):
    """Independent mode: every point from `guess` (as `solve`; the default guess made from
    the point's bulk helix where that is solved, as in continuation mode), vmapped."""
    start, theta0, unloaded = _curve_setup(rod, length)
    index = jnp.asarray(CONTROL_INDEX)[kind]

    def one(v, hint):
        end = axial_end_condition(rod, length, kind, v)
        bulk = bulk_helix_at(rod, length, index, v, unloaded) if with_bulk else _no_bulk(values.dtype)
        start_from = guess
        if guess is None and with_bulk:
            start_from = no_gradient(default_warm_start(rod, length, start, end, options.segments, "helix", bulk))
        sol = solve(rod, length, start, end, start_from, None, options, test_stability=False)
        if hint is None:
            hint = jnp.where(bulk.ok, bulk.rotation, theta0)
        obs, bulk_obs = _observe(rod, length, kind, sol, bulk, v, hint)
        return obs, bulk_obs, sol, bulk.ok & sol.valid_input

    return jax.vmap(one)(values, hints)


def _continuation_start(rod, length, kind, values, options: BoundaryValueOptions, guess):
    """The carry of continuation mode before the first point (4,): its warm
    start (from `guess` where that solve succeeds, else the default, made from the first
    point's bulk helix: with the whole turns of a rotation held there, which the end frame
    alone does not count), the unloaded bulk guess, the rotation near which its whole
    turns are counted, the controls the warm start was solved at (the first point), and
    whether the last point converged (yes).  The first point with finite controls stands
    in for a first point without (traced: a NaN first control made every later point start
    its substeps from NaN and fail, each flagged `invalid_input`)."""
    first = values[jnp.argmax(jnp.all(jnp.isfinite(values), axis=1))]
    start, theta0, unloaded = _curve_setup(rod, length)
    first_end = axial_end_condition(rod, length, kind, first)
    bulk0 = bulk_helix_at(rod, length, jnp.asarray(CONTROL_INDEX)[kind], first, unloaded)
    guess0 = no_gradient(default_warm_start(rod, length, start, first_end, options.segments, "helix", bulk0))
    if guess is not None:
        solved = no_gradient(solve(rod, length, start, first_end, guess, None, options, test_stability=False))
        guess0 = tree_where(solved.ok, solved.warm_start(), guess0)
    return guess0, unloaded, jnp.where(bulk0.ok, bulk0.rotation, theta0), first, jnp.asarray(True)


def _continuation_carry(dtype, segments: int, placement=None):
    """The specs (`jax.ShapeDtypeStruct`) of `_continuation_start`'s carry, from the curve's
    float type and `segments`, without tracing it (`tests/test_bvp_response.py` checks them
    against its traced output), placed as its results will be."""
    def spec(*shape):
        return jax.ShapeDtypeStruct(shape, dtype, sharding=placement)

    warm_start = WarmStart(force=spec(3), moment0=spec(3), node_position=spec(segments, 3), node_frame=spec(segments, 3, 3))
    return warm_start, (spec(3), spec(), spec()), spec(), spec(4), jax.ShapeDtypeStruct((), jnp.bool_, sharding=placement)


#: The most solves of one continuation point beyond the substeps its prescribed rotation
#: needs (`_solve_from`).
CONTINUATION_TRIES = 16

#: A failed continuation substep is retried this much shorter, at most `SHRINKS` times
#: per point, and not at all after a point that failed (past a fold, where no substep
#: converges, each point would pay `SHRINKS` more failed solves).  Not a half: halving
#: lands again on a point where a dyadic substep failed (a fold near 2.8 half-turns, on the
#: spring of `tests/test_bvp_response.py`, met by substeps from 2 to 4 half-turns).
SHRINK = 0.4
SHRINKS = 3

#: The largest change of a prescribed end rotation in one continuation substep (radians).
#: The end frame fixes the rotation only modulo a whole turn, and a solve warm-started
#: from the previous point may turn the end the short way once a step nears half a turn.
#: Not a rational multiple of pi, for the same reason as `SHRINK`.
MAX_ROTATION_STEP = 1.5

#: The most rotation substeps of one point (96 rad, some 15 turns, from the last point).
MAX_ROTATION_SUBSTEPS = 64


def _solve_from(rod, length, kind, start, v_from, v, guess, retry, options: BoundaryValueOptions):
    """The solve at controls `v` (4,) warm-started from `guess`, solved at `v_from`: in one
    step where that converges, else in substeps from `v_from` towards `v`, each
    warm-started from the last converged one and `SHRINK` times shorter after a failure
    (a prescribed rotation in substeps of at most `MAX_ROTATION_STEP`), until `v` is
    reached, `SHRINKS` failures (one where not `retry`) or `CONTINUATION_TRIES` solves
    more than the rotation's substeps (at most `MAX_ROTATION_SUBSTEPS`).  Returns `(sol,
    warm start, controls)`: the solution at `v` (its `num_steps` those of all the solves;
    where `v` was not reached, the result of the last failed solve, or `max_steps_reached`
    where none failed), and the last converged state and its controls (the next point's
    start).  One `solve` in a `while_loop`: a point that converges at once costs one solve,
    and the program holds one solve, not one per try."""
    turn = jnp.where(kind == LOADED, 0.0, jnp.abs(v[3] - v_from[3]))
    first = jnp.where(turn > MAX_ROTATION_STEP, MAX_ROTATION_STEP / jnp.maximum(turn, MAX_ROTATION_STEP), 1.0)
    shortest = first * jnp.where(retry, SHRINK**SHRINKS, 1.0)
    most = CONTINUATION_TRIES + jnp.minimum(jnp.ceil(1 / first), MAX_ROTATION_SUBSTEPS).astype(jnp.int32)

    def solved_at(t, guess):
        end = axial_end_condition(rod, length, kind, v_from + t * (v - v_from))
        return solve(rod, length, start, end, guess, None, options, test_stability=False)

    def unfinished(state):
        _, done, step, tries, *_ = state
        return (done < 1) & (step > 0.5 * shortest) & (tries < most)

    def attempt(state):
        guess, done, step, tries, steps, failure, _ = state
        # The last substep lands on `v` exactly, not on a sum of fractions a few ulp short.
        t = jnp.where(done + step >= 1 - 1e-9, 1.0, done + step)
        sol = solved_at(t, guess)
        ok = sol.ok
        guess = tree_where(ok, no_gradient(sol.warm_start()), guess)
        return (guess, jnp.where(ok, t, done), jnp.where(ok, step, SHRINK * step), tries + 1, steps + sol.num_steps,
                RESULTS.where(ok, failure, sol.result), sol)

    # The loop carries a solution: its shapes, without another solve in the program.
    blank = jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), jax.eval_shape(solved_at, 1.0, guess))
    zero = jnp.zeros((), v.dtype)
    state = (guess, zero, first.astype(v.dtype), jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32), RESULTS.max_steps_reached, blank)
    guess, done, _, _, steps, failure, sol = jax.lax.while_loop(unfinished, attempt, state)
    result = RESULTS.where(done >= 1, sol.result, failure)
    # (Not v_from + done (v - v_from) where nothing converged: a NaN control would spoil it.)
    reached = jnp.where(done >= 1, v, jnp.where(done > 0, v_from + done * (v - v_from), v_from))
    return replaced(sol, result=result, num_steps=steps), guess, reached


def _continuation_points(rod, length, kind, values, count, options: BoundaryValueOptions, carry):
    """Continuation mode: the first `count` points in order, each warm-started from the last
    converged state (a loop from `carry`; in substeps where one step does not converge,
    `_solve_from`); returns the carry after the last and the outputs (zeros beyond
    `count`).  `count` is traced: one program solves a curve's points and, in its first
    slot, a bisection's single trials (`_first_loss_of_stability`)."""
    start, _, _ = _curve_setup(rod, length)
    index = jnp.asarray(CONTROL_INDEX)[kind]

    def step(carry, v):
        guess, bulk_guess, hint, v_from, last_ok = carry
        sol, guess, v_from = _solve_from(rod, length, kind, start, v_from, v, guess, last_ok, options)
        bulk = bulk_helix_at(rod, length, index, v, bulk_guess)
        obs, bulk_obs = _observe(rod, length, kind, sol, bulk, v, hint)
        # A failed point does not spoil the warm start of the next one.
        bulk_guess = tree_where(bulk.ok, no_gradient((bulk.u, bulk.mu1, bulk.mu2)), bulk_guess)
        hint = jnp.where(sol.ok, obs[3], hint)
        return (guess, bulk_guess, hint, v_from, sol.ok), (obs, bulk_obs, sol, bulk.ok & sol.valid_input)

    blank = jax.tree.map(lambda a: jnp.zeros(values.shape[:1] + a.shape, a.dtype), jax.eval_shape(step, carry, values[0])[1])

    def point(i, state):
        carry, outs = state
        carry, out = step(carry, values[i])
        return carry, jax.tree.map(lambda o, v: o.at[i].set(v), outs, out)

    return jax.lax.fori_loop(0, count, point, (carry, blank))


# A curve is solved by these programs: its points in independent mode, or in continuation
# mode the start (small: compiled to run once, in 0.4-0.5 s) and the continuation scan.  In
# one program with the scan, the start (a third of its operations: the default warm start,
# the first bulk solve) lengthened the scan's compilation from 2.4-3.0 s to 4.1 s, and with
# the start apart the scan compiles (`_compile_side_by_side`, from the specs of the carry)
# while the start is traced and compiled on the calling thread.  While progress is shown,
# the same programs solve host-side batches of points (continuation: the carry passes from
# batch to batch).
_independent = jit(_independent_points, static_argnames="with_bulk", trace_cache=True)
_continuation_first = jit(_continuation_start, run_once=True, trace_cache=True)
_continuation = jit(_continuation_points, trace_cache=True)


def _curve(rod, length, kind, values, options: BoundaryValueOptions, mode: str, hints=None, with_bulk: bool = True, guess=None):
    """Solve every point of a curve; `values` `(n, 4)` = (F, M, h, Theta) per point.  `hints`
    `(n,)`: rotations near which to count whole turns (independent mode; default the bulk
    prediction's); `with_bulk=False` (independent mode): no bulk prediction.  `guess` (as
    `solve`): the start of every point (independent mode) or of the first (continuation;
    the default guess where that solve fails).  The solutions are not tested for
    stability: `_tested` does that, in a program of its own."""
    if mode == "independent":
        return _independent(rod, length, kind, values, hints, options, with_bulk, guess)
    carry = _continuation_first(rod, length, kind, values, options, guess)
    return _continuation(rod, length, kind, values, _count(values), options, carry)[1]


def _count(values):
    """The number of points of `values` as the programs' traced count (`_continuation_points`)."""
    return np.int32(values.shape[0])


def _point_ends(rod, length, kind, values) -> EndCondition:
    """The end condition of each point at its controls `values` `(n, 4)` (stacked)."""
    return jax.vmap(lambda v: axial_end_condition(rod, length, kind, v))(values)


def _stability_of_points(rod, length, kind, values, N, M0, xs, frames, end_frames, result, count, options: BoundaryValueOptions):
    """The stability test of the first `count` points' solutions (their `N`, `M0`, nodes,
    end frame and `result`) at their controls `values` `(n, 4)` (`stability_at_points`)."""
    ends = _point_ends(rod, length, kind, values)
    return stability_at_points(rod, length, ends, N, M0, xs, frames, end_frames, result, count, options)


# A program of its own: a curve's solves (whose continuation the test does not steer) and
# their tests compile side by side at a first call (`_compile_side_by_side`).
_points_stability = jit(_stability_of_points, trace_cache=True)
_ends_of_points = jit(_point_ends, run_once=True)
# One point's end (a bisection's trial): evaluated operation by operation it compiled a
# dozen one-operation programs at a curve's first loss of stability.
_end_of_point = jit(axial_end_condition, run_once=True)


def _segments_along(rod, length, kind, values) -> int:
    """`segments="auto"` for a curve: the most shooting pieces any of its points' default
    guesses asks for (`needed_segments`: its spatial growth), on the host."""
    start = unloaded_clamp(rod)
    return max(needed_segments(rod, length, start, _end_of_point(rod, length, kind, v), None, "helix")[0] for v in values)


def _point(tree, i):
    """Point `i` of a batch of solutions (or ends) held on the host (NumPy: no program
    compiled per field, as JAX's slicing would)."""
    return jax.tree.map(lambda a: a[i], tree)


def _resolved(rod, length, kind, values, sols: BoundaryValueSolution, options: BoundaryValueOptions) -> BoundaryValueSolution:
    """The curve's solutions `sols` (concrete, tested on `options.stability_pieces` pieces)
    with each converged point whose test did not resolve its wrench (index -1) tested again
    on more pieces, one by one, as `solve_boundary_value` does (`resolved_stability`);
    `stability_pieces` the most any point was tested on."""
    if sols.stability_pieces == 0:
        return sols
    unresolved = np.flatnonzero(succeeded(sols.result) & (np.asarray(sols.instability_index) < 0))
    if not unresolved.size:
        return sols
    # On the host: each point's arrays sliced by JAX would compile a program per field.
    points, ends = jax.device_get((sols, _ends_of_points(rod, length, kind, values)))
    fields = ("instability_index", "stability_margin", "unstable_direction", "rotation")
    tests = {name: np.array(getattr(points, name)) for name in fields}
    pieces = sols.stability_pieces
    test_pieces_ahead(rod, length, [(_point(ends, i), _point(points, i)) for i in unresolved], options)
    for i in unresolved:
        tested = jax.device_get(resolved_stability(rod, length, _point(ends, i), _point(points, i), options))
        for name in fields:
            tests[name][i] = getattr(tested, name)
        pieces = max(pieces, tested.stability_pieces)
    return replaced(sols, **{name: jnp.asarray(value) for name, value in tests.items()}, stability_pieces=pieces)


def _turns_counted(kind, values, obs: tuple, sols: BoundaryValueSolution, concrete: bool):
    """The curve's observables `obs` and solutions with each point's whole turns as counted
    along its rod (`sols.rotation`, by the stability test): a responding rotation (a
    `Loaded` end) takes the whole turns nearest the count, where counted, instead of those
    nearest its hint (the count is $\\psi(L) - \\psi(0)$, `_rotation.py`, which for a tilted
    end differs from the curve's $\\Theta$ by the tilt's second order: the turns only); a
    point whose rotation is prescribed but whose solution holds other whole turns is
    flagged `other_whole_turns`, its observables NaN.  On the host for a concrete curve (no
    one-operation programs to compile)."""
    xp = np if concrete else jnp
    rotation, observed = xp.asarray(sols.rotation), xp.asarray(obs[3])
    counted, loaded = xp.isfinite(rotation), xp.asarray(kind) == LOADED
    nearest = unwrap_near(observed, rotation, xp)
    obs = (*obs[:3], jnp.asarray(xp.where(counted & loaded, nearest, observed)))
    other = counted & ~loaded & ~holds_turns(rotation, xp.asarray(values)[:, 3])
    if concrete and not other.any():
        return obs, sols
    obs = tuple(jnp.where(other, jnp.nan, column) for column in obs)
    return obs, replaced(sols, result=set_code(sols.result, other, RESULTS.other_whole_turns))


def _tested(rod, length, kind, values, sols: BoundaryValueSolution, options: BoundaryValueOptions) -> BoundaryValueSolution:
    """The curve's solutions `sols` with their stability tested on `options.stability_pieces`
    pieces (untested, as solved, where that is 0)."""
    if options.stability_pieces == 0:
        return sols
    tested = _points_stability(rod, length, kind, values, *stability_inputs(sols), _count(values), options)
    return with_stability(sols, tested, options.stability_pieces)


def _curve_signature(rod, length, kind, values, options, mode, hints, with_bulk, guess):
    shapes = leaf_shapes((rod, length, kind, values, options, hints, guess))
    return (jax.tree.structure((rod, options, hints, guess)), mode, with_bulk, shapes)


@once_per_signature(_curve_signature)
def _compile_side_by_side(rod, length, kind, values, options, mode, hints, with_bulk, guess) -> bool:
    """At the first curve of its kind: start compiling its solves (`_independent`, or the
    continuation scan `_continuation` from the specs of its start's carry) and their
    stability test (`_points_stability`, from the solves' output structure), each on a
    thread of its own (`compile_ahead`); a continuation's start (`_continuation_first`) is
    compiled by its call meanwhile.  The README's 50-point force-extension curve, fresh
    processes on 2 cores, three alternating pairs each: first call 5.19-5.57 s against
    5.67-5.87 s for the code before this and the Jacobi fields' compliance matrix
    (`_variations.py`), in a quiet hour; against the start inside the scan's program with
    the same Jacobi fields, in a noisier hour, the whole process 8.4-10.7 s against
    9.8-11.7 s, its CPU time 13.0-16.3 s against 15.0-17.9 s."""
    if mode == "independent":
        solved = compile_ahead(_independent, rod, length, kind, values, hints, options, with_bulk, guess)
    else:
        carry = _continuation_carry(values.dtype, options.segments, committed_placement((rod, length, kind, values, options, guess)))
        solved = compile_ahead(_continuation, rod, length, kind, values, _count(values), options, carry)
        solved = None if solved is None else solved[1]
    if solved is None:  # nothing compiles beside the call (traced, one core)
        return False
    if options.stability_pieces > 0:
        compile_ahead(_points_stability, rod, length, kind, values, *stability_inputs(solved[2]), _count(values), options)
    return True


def _curve_in_batches(rod, length, kind, values, options, mode, hints, with_bulk, guess, report: ProgressReport):
    """`_curve` in batches of points, advancing `report` after each (the same results)."""
    n = values.shape[0]
    size = batch_size(n)

    def tested(batch, out):
        obs, bulk_obs, sols, bulk_ok = out
        return obs, bulk_obs, _tested(rod, length, kind, batch, sols, options), bulk_ok

    if mode == "independent":
        def solve_batch(_, batch):
            return None, tested(batch[0], _independent(rod, length, kind, *batch, options, with_bulk, guess))

        return scan_in_batches(solve_batch, None, (values, hints), n, size, report)[1]
    carry = _continuation_first(rod, length, kind, values, options, guess)

    def solve_batch(carry, batch):
        carry, out = _continuation(rod, length, kind, batch, _count(batch), options, carry)
        return carry, tested(batch, out)

    return scan_in_batches(solve_batch, carry, values, n, size, report)[1]


def _point_values(name, given, owner):
    """The `(n, 4)` control values of each point, and the name of the swept control."""
    dtype = float_dtype()
    arrays = {}
    for n, v in given.items():
        a = jnp.asarray(v, dtype)
        if a.ndim > 1:
            raise ValueError(f"{owner}: {n} must be a scalar or 1-d array, got shape {a.shape}")
        if is_concrete(a) and not np.all(np.isfinite(np.asarray(a))):
            raise ValueError(f"{owner}: {n} must be finite")
        arrays[n] = a
    try:
        (size,) = jnp.broadcast_shapes(*(a.shape for a in arrays.values()), (1,))
    except ValueError:
        raise ValueError(f"{owner}: the controls do not broadcast: {[a.shape for a in arrays.values()]}") from None
    if size < 1:
        raise ValueError(f"{owner}: no points")
    # Given values are stacked on the host (no programs to compile at a first call).
    xp = np if is_concrete(*arrays.values()) else jnp
    columns = [xp.broadcast_to(arrays.get(n, xp.zeros((), dtype)), (size,)) for n in AXIAL_OBSERVABLES]
    swept = next((n for n in name.split("-") if arrays[n].ndim == 1), name.split("-")[0])
    return jnp.asarray(xp.stack(columns, -1)), swept


def axial_response(
    rod,
    length: ArrayLike,
    *,
    force: ArrayLike | None = None,
    moment: ArrayLike | None = None,
    extension: ArrayLike | None = None,
    rotation: ArrayLike | None = None,
    mode: str = "continuation",
    rotation_hint: ArrayLike | None = None,
    bulk: bool = True,
    guess: BoundaryValueSolution | tuple[ArrayLike, ArrayLike] | None = None,
    options: BoundaryValueOptions | None = None,
    segments: int | str | None = None,
    method: str | None = None,
    atol: float | None = None,
    max_steps: int | None = None,
    ode_rtol: float | None = None,
    ode_atol: float | None = None,
    adjoint: diffrax.AbstractAdjoint | None = None,
    throw: bool = False,
    progress: ProgressArgument = None,
) -> ResponseCurve:
    """The axial response of a finite rod at a sequence of control pairs: two of `force`,
    `moment`, `extension`, `rotation` (scalars or `(n,)` arrays, broadcast; the pairs of
    `axial_ends`), each point solved by `solve_boundary_value` in the canonical placement.

    `mode`: `"continuation"` (default; in order, each solve warm-started from the previous,
    in substeps where a step fails or turns a prescribed rotation by more than 1.5 rad;
    `num_steps` counts the root steps of all of a point's solves)
    or `"independent"` (vmapped solves from the bulk guess).  A responding rotation
    (force and moment held) holds the whole turns counted along each point's rod
    (`BoundaryValueSolution.rotation`); where they are not counted (no stability test,
    `stability_pieces=0`, or a tangent along $-e_z$), those nearest the previous point's
    (continuation) or the bulk prediction's (independent mode), or with `rotation_hint`
    `(n,)` (independent mode) nearest these values; `bulk=False` skips the bulk prediction
    (its fields NaN).  `guess`: where to start -- a
    `BoundaryValueSolution` (e.g. a buckled state found by `solve_boundary_value` or
    `follow_branch`) or a pair `(n0, m0)` of start wrenches (director frame): the first
    point's start in continuation mode (the default guess where that fails), every point's
    in independent mode.  `options` and the keywords after it: as `solve_boundary_value`;
    `segments="auto"` takes the most shooting pieces any point's default guess asks for
    (`needed_segments`, its spatial growth; eager calls only): a stretched spring that single
    shooting loses (the README's, 3 turns, from F = 0.6 on) is solved to F = 1 on 5.
    `throw`: raise `SolverError` if any point fails (default `False`: failed points have
    `ok = False` and NaN observables).  jit/vmap safe.  Derivatives: forward mode
    (`jax.jacfwd`, `jvp`) in either mode; reverse mode (`jax.grad`, `jacrev`, with
    `adjoint=diffrax.DirectAdjoint()`) in `mode="independent"` only -- continuation's
    substeps are a loop of dynamic length, which JAX cannot differentiate in reverse.

    `progress`: `None` (default) shows a rich progress bar of the points solved when stdout
    is a terminal (and the inputs are concrete, not traced), `True`/`False` force it on or
    off, and a callable is called as `progress(done, total)` (points solved, `n`) instead
    of a bar.  While progress is shown the points are solved in up to 20 host-side batches
    of one compiled program (the last padded), and the bisection for `critical` comes
    after the last point.  Continuation passes its warm start from batch to batch and
    gives the curve of the single call bit for bit; in independent mode the narrower
    vmap rounds differently (round-off in the responses; the stability margin, an
    eigenvalue of a stiff Hessian, to ~1e-9 relative).  Under `jax.jit` or `vmap` only
    `None` and `False` are allowed.
    """
    owner = "axial_response"
    auto = automatic_segments(segments, owner)
    try:
        name, given = axial_controls(force=force, moment=moment, extension=extension, rotation=rotation)
    except ValueError as error:
        raise ValueError(f"{owner}: {error}") from None
    values, swept = _point_values(name, given, owner)
    return _response(
        rod, length, name, values, swept, mode=mode, rotation_hint=rotation_hint, bulk=bulk, owner=owner, guess=guess, auto_segments=auto,
        throw=throw, progress=progress, options=with_settings(
            options, segments=None if auto else segments, method=method, atol=atol, max_steps=max_steps, ode_rtol=ode_rtol,
            ode_atol=ode_atol, adjoint=adjoint,
        ),
    )


def _response(
    rod, length, name, values, swept, *, mode, options, owner, throw, progress, rotation_hint=None, bulk=True, guess=None,
    auto_segments=False,
):
    check_choice(mode, MODES, "mode", owner)
    progress = check_progress(progress, owner)
    check_one_rod(rod, owner)
    length = finite_scalar(length, "length", owner, positive=True)
    guess, guess_kind = parse_guess(guess, owner)
    if guess_kind != "helix":
        raise ValueError(f"{owner}: guess must be None, a BoundaryValueSolution or (n0, m0)")
    if guess is not None:  # (no clamp program to compile without a guess)
        guess = fit_guess(guess, options.segments, unloaded_clamp(rod))
    hints = None
    if rotation_hint is not None or not bulk:
        if mode != "independent":
            raise ValueError(f"{owner}: rotation_hint= and bulk=False apply to mode='independent'")
        # Without a bulk prediction, turns are counted near the given (or control) rotations.
        hint = values[:, 3] if rotation_hint is None else jnp.asarray(rotation_hint, values.dtype)
        hints = jnp.broadcast_to(hint, values.shape[:1])
    kind = jnp.asarray(AXIAL_CONTROLS[name].kind, jnp.int32)
    concrete = is_concrete(rod, length, values, hints, guess, options)
    if auto_segments:
        if not concrete:
            raise ValueError(f"{owner}: segments='auto' needs concrete inputs (not under jax.jit or vmap)")
        options = dataclasses.replace(options, segments=_segments_along(rod, length, kind, values))
        if guess is not None:
            guess = fit_guess(guess, options.segments, unloaded_clamp(rod))
    if not concrete and progress not in (None, False):
        raise ValueError(
            f"{owner}: progress= reports between host-side batches of points and needs concrete inputs, "
            "not traced ones (under jax.jit, vmap or grad): leave it None or False there"
        )
    n = values.shape[0]
    with progress_bar(owner, n, progress, owner=owner, auto=concrete and n > 1) as report:
        # The points of one call of the curve's programs, which its bisection calls again.
        size = batch_size(n) if report.shown else n
        if report.shown:
            obs, bulk_obs, sols, bulk_ok = _curve_in_batches(
                rod, length, kind, values, options, mode, hints, bool(bulk), guess, report
            )
        else:  # one call: nothing is slower for want of a bar
            if concrete:
                _compile_side_by_side(rod, length, kind, values, options, mode, hints, bool(bulk), guess)
            obs, bulk_obs, sols, bulk_ok = _curve(rod, length, kind, values, options, mode, hints, bool(bulk), guess)
            sols = _tested(rod, length, kind, values, sols, options)
    if concrete:
        sols = _resolved(rod, length, kind, values, sols, options)
    obs, sols = _turns_counted(kind, values, obs, sols, concrete)
    curve = ResponseCurve(
        controls=name,
        swept=swept,
        length=length,
        **dict(zip(AXIAL_OBSERVABLES, obs)),
        **{"bulk_" + observable: column for observable, column in zip(AXIAL_OBSERVABLES, bulk_obs)},
        result=sols.result,
        bulk_ok=bulk_ok,
        residual=sols.residual,
        num_steps=sols.num_steps,
        solutions=sols,
        critical=jnp.asarray(jnp.nan, values.dtype),
        critical_kind="none",
    )
    if is_concrete(curve) and mode == "continuation":
        critical, kind = _first_loss_of_stability(rod, length, kind, values, swept, sols, options, size)
        curve = eqx.tree_at(lambda c: c.critical, curve, jnp.asarray(critical, values.dtype))
        curve = dataclasses.replace(curve, critical_kind=kind)
    return raise_if_failed(curve, curve.result, owner) if throw else curve


#: Bisection steps that locate a loss of stability between two points of a curve.
CRITICAL_BISECTIONS = 40


#: A stable point followed by a failed one marks a fold only where the margin of the
#: bisection's last stable trial has fallen below this fraction of that point's: at a fold
#: it goes to zero (like the square root of the distance to it); a solve that failed for
#: another reason leaves it where it was.
FOLD_MARGIN = 1e-2

#: The most stable -> failed steps of a curve examined for a fold (each costs a bisection).
FOLD_CANDIDATES = 3


def _losses_of_stability(sols: BoundaryValueSolution, values) -> tuple[np.ndarray, np.ndarray]:
    """On the host: (the points of a concrete curve that failed with finite controls, the
    stable points followed by an unstable or a failed one)."""
    ok = succeeded(sols.result)
    index = np.asarray(sols.instability_index)
    stable, unstable = ok & (index == 0), ok & (index > 0)
    failed = ~ok & np.all(np.isfinite(np.asarray(values)), axis=1)
    return failed, np.flatnonzero(stable[:-1] & (unstable[1:] | failed[1:]))


def _trial(rod, length, kind, v, good, v_good, size: int, options: BoundaryValueOptions):
    """A bisection's trial: the solution at controls `v`, continued from the concrete
    solution `good` at `v_good` (`_solve_from`), with its stability resolved as the curve's
    points' is -- by the curve's own programs, in the first of their `size` slots (no
    program of one point to compile at the first loss of stability of a first curve).
    Returned on the host."""
    values = np.zeros((size, 4), v.dtype)
    values[0] = v
    carry = (good.warm_start(), _unloaded_bulk_guess(rod, v.dtype, np), np.zeros((), v.dtype), np.asarray(v_good), np.bool_(True))
    one = np.int32(1)
    sols = _continuation(rod, length, kind, values, one, options, carry)[1][2]
    if options.stability_pieces > 0:
        tested = _points_stability(rod, length, kind, values, *stability_inputs(sols), one, options)
        sols = with_stability(sols, tested, options.stability_pieces)
    trial = _point(jax.device_get(sols), 0)
    if int(trial.instability_index) < 0 and bool(succeeded(trial.result)):  # (rare: not resolved)
        trial = jax.device_get(resolved_stability(rod, length, _end_of_point(rod, length, kind, v), trial, options))
    return trial


def _first_loss_of_stability(rod, length, kind, values, swept, sols, options, size: int):
    """(critical value of the swept control, kind) of the first loss of stability of a
    continuation curve -- a stable point followed by an unstable one, or by a failed one
    where the branch ends at a fold -- by bisection: each trial solve is continued from the
    stable side (`_trial`, whose programs solved the curve in calls of `size` points).  A
    branch point if the last unstable trial converged next to the stable side, a fold if
    it did not converge or jumped away (no equilibrium nearby beyond it).  Points whose
    stability is not defined (index -1: an end loaded by a moment) lose none."""
    # On the host: no one-operation programs to compile.
    sols, values = jax.device_get(sols), np.asarray(values)
    failed, candidates = _losses_of_stability(sols, values)
    column = AXIAL_OBSERVABLES.index(swept)
    distance = lambda s, t: float(np.linalg.norm(np.concatenate([s.force - t.force, s.moment0 - t.moment0])))  # noqa: E731
    # Every stable -> unstable step, and the first few stable -> failed ones.
    candidates = candidates[~failed[candidates + 1] | (np.cumsum(failed[candidates + 1]) <= FOLD_CANDIDATES)]
    for i in candidates:
        good, bad = _point(sols, i), _point(sols, i + 1)
        a, b = values[i], values[i + 1]
        first = distance(good, bad)
        for _ in range(CRITICAL_BISECTIONS):
            mid = 0.5 * (a + b)
            trial = _trial(rod, length, kind, mid, good, a, size, options)
            if bool(succeeded(trial.result)) and float(trial.stability_margin) > 0:
                a, good = mid, trial
            else:
                b, bad = mid, trial
        if failed[i + 1] and not float(good.stability_margin) < FOLD_MARGIN * float(sols.stability_margin[i]):
            continue  # the failure was not the end of the branch
        close = bool(succeeded(bad.result)) and distance(good, bad) < 1e-3 * max(first, 1e-300)
        return float(0.5 * (a[column] + b[column])), "branch point" if close else "fold"
    return np.nan, "none"


def _swept_values(values, name, what):
    values = jnp.asarray(values, float_dtype())
    if values.ndim != 1 or values.shape[0] < 1:
        raise ValueError(f"{name}: {what} must be a non-empty 1-d array, got shape {values.shape}")
    if is_concrete(values) and not np.all(np.isfinite(np.asarray(values))):
        raise ValueError(f"{name}: {what} must be finite")
    return values


def force_extension(
    rod,
    length: ArrayLike,
    forces: ArrayLike,
    *,
    moment: ArrayLike | None = None,
    rotation: ArrayLike | None = None,
    mode: str = "continuation",
    guess: BoundaryValueSolution | tuple[ArrayLike, ArrayLike] | None = None,
    options: BoundaryValueOptions | None = None,
    segments: int | str | None = None,
    method: str | None = None,
    atol: float | None = None,
    max_steps: int | None = None,
    ode_rtol: float | None = None,
    ode_atol: float | None = None,
    adjoint: diffrax.AbstractAdjoint | None = None,
    throw: bool = False,
    progress: ProgressArgument = None,
) -> ResponseCurve:
    """Force-extension curve of a finite rod of length `length`, axial `forces` `(n,)`.

    Held fixed: the axial `moment` (default 0: a spring loaded through hooks on its axis,
    free to turn; a `Loaded` end about the axis) or the end `rotation` $\\Theta$ (total, as
    `axial_ends`; a magnetic tweezer, `Tweezer` end).  Returns a `ResponseCurve` with the
    extension (and the moment or rotation) of the finite rod and of the bulk helix.

    `mode`: `"continuation"` (default; in order, each solve warm-started from the
    previous -- sort `forces` from small to large) or `"independent"` (vmapped solves from
    the bulk guess).  `guess` as `axial_response`.  `options` and the keywords after it: as
    `solve_boundary_value`; `throw` and `progress` (a progress bar or callback over the
    points) as `axial_response`, and its derivatives (reverse mode in independent mode
    only).  jit/vmap safe (e.g. `jax.vmap`
    over lengths); unconverged points have `ok = False` and NaN observables.

    **Example**

    ```python
    rod = helixrod.Rod(1.0, 1.0, 0.77, uhat=(0.0, 1.0, 0.3))
    curve = helixrod.force_extension(rod, 60.0, jnp.linspace(0.0, 0.05, 50))
    curve.extension, curve.bulk_extension
    ```
    """
    owner = "force_extension"
    auto = automatic_segments(segments, owner)
    if moment is not None and rotation is not None:
        raise ValueError(f"{owner}: give moment= or rotation=, not both")
    forces = _swept_values(forces, owner, "forces")
    if rotation is None:
        held = {"moment": finite_scalar(0.0 if moment is None else moment, "moment", owner)}
    else:
        held = {"rotation": finite_scalar(rotation, "rotation", owner)}
    name, given = axial_controls(force=forces, **held)
    values, _ = _point_values(name, given, owner)
    return _response(
        rod, length, name, values, "force", mode=mode, auto_segments=auto, owner=owner, throw=throw, progress=progress, guess=guess, options=with_settings(
            options, segments=None if auto else segments, method=method, atol=atol, max_steps=max_steps, ode_rtol=ode_rtol,
            ode_atol=ode_atol, adjoint=adjoint,
        ),
    )


def rotation_response(
    rod,
    length: ArrayLike,
    rotations: ArrayLike,
    *,
    force: ArrayLike | None = None,
    extension: ArrayLike | None = None,
    mode: str = "continuation",
    guess: BoundaryValueSolution | tuple[ArrayLike, ArrayLike] | None = None,
    options: BoundaryValueOptions | None = None,
    segments: int | str | None = None,
    method: str | None = None,
    atol: float | None = None,
    max_steps: int | None = None,
    ode_rtol: float | None = None,
    ode_atol: float | None = None,
    adjoint: diffrax.AbstractAdjoint | None = None,
    throw: bool = False,
    progress: ProgressArgument = None,
) -> ResponseCurve:
    """Torque (and extension or force) against the end rotation of a finite rod.

    `rotations` `(n,)`: total end rotations $\\Theta$ about the axis (as `axial_ends`;
    $\\Theta_0 = L|\\hat u|$ is the unloaded end).  Held fixed (exactly one): the axial
    `force` (magnetic tweezer: torque and extension against turns, `Tweezer` end) or the
    `extension` $h$ (a spring twisted between grips: torque and axial force, `Clamped`
    end).  Other arguments (`progress` included) as `force_extension`; continuation in the
    rotation counts the whole turns of the end.
    """
    owner = "rotation_response"
    auto = automatic_segments(segments, owner)
    if (force is None) == (extension is None):
        raise ValueError(f"{owner}: give exactly one of force= or extension=")
    rotations = _swept_values(rotations, owner, "rotations")
    if force is not None:
        held = {"force": finite_scalar(force, "force", owner)}
    else:
        held = {"extension": finite_scalar(extension, "extension", owner)}
    name, given = axial_controls(rotation=rotations, **held)
    values, _ = _point_values(name, given, owner)
    return _response(
        rod, length, name, values, "rotation", mode=mode, auto_segments=auto, owner=owner, throw=throw, progress=progress, guess=guess, options=with_settings(
            options, segments=None if auto else segments, method=method, atol=atol, max_steps=max_steps, ode_rtol=ode_rtol,
            ode_atol=ode_atol, adjoint=adjoint,
        ),
    )
