"""Boundary-value problems of finite Kirchhoff rods, solved by (multiple) shooting.

The rod is clamped at $s = 0$ (position $x_0$, frame $D_0$).  The unknowns are the lab force
$N$ (constant along the rod) and the lab moment $M_0$ at $s = 0$; the moment about any fixed
point is constant too, so the lab moment at any point is $M(s) = M_0 - (x(s) - x_0)\\times N$.
The end condition at $s = L$ (`_ends.py`) gives six equations, and with `segments = k` the
junctions of the pieces $6(k - 1)$ more (`_shooting.py`).

Why multiple shooting.  Where the loaded rod is *spatially unstable* -- the linearised
wrench flow has eigenvalues with real part $\\lambda > 0$, e.g. a helical spring pulled at
fixed end rotation -- errors in the initial wrench grow like $e^{\\lambda L}$ and single
shooting loses its Newton basin and then its precision as $\\lambda L$ grows; pieces of
length $L/k$ bring that to $e^{\\lambda L/k}$.  Measured limits: README and
`benchmarks/bench_finite.py`.

Root solve.  Levenberg--Marquardt steps with Broyden updates (`_root_finder.py`), optionally
along a homotopy (`continuation`) from the unloaded rod to the prescribed end.  Derivatives
are those of the implicit function theorem on the shooting equations,
$\\dot y = -J^{-1}\\partial_\\theta F\\,\\dot\\theta$, with the Jacobian $J$ of the converged
solve: forward mode with the default `diffrax.ForwardMode()`, `diffrax.DirectAdjoint()`
also allows reverse mode.
"""

from __future__ import annotations

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._compile import compile_ahead, jit, once_per_signature
from .._geometry import unloaded_observables
from .._kirchhoff import wrench_growth_rate
from .._lie import is_rotation
from .._misc import finite_scalar, float_dtype, increases_within, increasing_within, is_concrete, no_gradient, replaced, tree_where
from .._rod import check_one_rod
from .._status import RESULTS, SolverError, has_code, promote, raise_if_failed, succeeded
from ._bulk import residual_scales
from ._ends import CLAMPED, LOADED, AbstractEnd, Clamped, EndCondition, as_start, end_condition, unloaded_clamp
from ._options import BoundaryValueOptions, with_settings
from ._rotation import exact_rotation, holds_turns
from ._stability import PIECE_RESOLUTION, stability, stiffness_range, wrench_scale
from ._shooting import (
    ShootingArgs,
    WarmStart,
    buckled_guess,
    default_warm_start,
    free_nodes,
    implicit,
    initial,
    rebase,
    root,
    warm_start_of,
)


class BoundaryValueSolution(eqx.Module):
    """Solution of `solve_boundary_value`.

    Saved at `s` (shape `(p,)`; `saveat=None` saves $s = L$ only): `x` `(p, 3)` centreline and
    `frame` `(p, 3, 3)` (lab), `n`, `m` `(p, 3)` force and moment in the director frame.
    `n0`, `m0` `(3,)`: the wrench at $s = 0$ in the director frame, so that
    `solve_static(rod, n0, m0, L, frame0=start.frame, x0=start.position)` is the solution
    (where single shooting is stable); `force` `(3,)` the lab force $N$ (constant),
    `moment0` the lab moment at $s = 0$; `end_position`, `end_frame`, `end_force`,
    `end_moment` the lab state at $s = L$; `node_position` `(k, 3)`, `node_frame`
    `(k, 3, 3)` the starts of the `segments` pieces (a warm start for another solve).
    Status: `residual` the largest scaled residual of the shooting equations, `tolerance`
    the largest it may be, `result` a `RESULTS` code (the root finder's, `invalid_input`,
    `residual_above_tolerance`, or `other_whole_turns`), `ok` (`result` is successful), `num_steps` root-finder
    iterations (all stages), `valid_input`.

    `rotation`: the total rotation $\\Theta$ of the end about $e_z$, whole turns included --
    the angle of $d_1$ about the tangent from Fuller's reference frame, followed along the
    rod by the stability test (`_rotation.py`; $\\Theta = \\int u_3\\,ds + \\int (e_z\\times
    t)\\cdot t'/(1+t_z)\\,ds$), its value from the end frame: for the ends of `axial_ends`
    (turned about $e_z$) the rotation they are given, $\\Theta_0 = L|\\hat u|$ unloaded.  Two
    solutions that meet the same end frame differ in it by whole turns.  NaN where it is not
    counted: no stability test (`stability_pieces=0`), a failed solve, a tangent within
    ~2.6 degrees of $-e_z$.  Where the end knows its rotation (`rotation=`), a solve that
    converges to other whole turns is flagged (`result` `other_whole_turns`; also under
    `jax.jit` and `vmap`).
    """

    s: Float[Array, " p"]
    x: Float[Array, "p 3"]
    frame: Float[Array, "p 3 3"]
    n: Float[Array, "p 3"]
    m: Float[Array, "p 3"]
    n0: Float[Array, "3"]
    m0: Float[Array, "3"]
    force: Float[Array, "3"]
    moment0: Float[Array, "3"]
    end_position: Float[Array, "3"]
    end_frame: Float[Array, "3 3"]
    end_force: Float[Array, "3"]
    end_moment: Float[Array, "3"]
    node_position: Float[Array, "k 3"]
    node_frame: Float[Array, "k 3 3"]
    residual: Float[Array, ""]
    result: RESULTS
    num_steps: Int[Array, ""]
    valid_input: Bool[Array, ""]
    tolerance: Float[Array, ""]
    instability_index: Int[Array, ""]
    stability_margin: Float[Array, ""]
    unstable_direction: Float[Array, "6"]
    rotation: Float[Array, ""]
    stability_pieces: int = eqx.field(static=True)
    continuation: int = eqx.field(static=True)

    @property
    def ok(self) -> Bool[Array, ""]:
        """Valid input, solver success and residual within tolerance."""
        return self.result == RESULTS.successful

    @property
    def stable(self) -> Bool[Array, ""]:
        """A converged solve whose second variation is positive definite (index 0)."""
        return self.ok & (self.instability_index == 0)

    @property
    def segments(self) -> int:
        """Number of shooting pieces."""
        return self.node_position.shape[-2]

    def warm_start(self) -> WarmStart:
        """This solution as the starting point of another solve with as many pieces."""
        return WarmStart(self.force, self.moment0, self.node_position, self.node_frame)

    def lab_wrench(self) -> tuple[Array, Array]:
        """Lab force and moment at the saved points, `(p, 3)` each."""
        return (
            jnp.einsum("...ij,...j->...i", self.frame, self.n),
            jnp.einsum("...ij,...j->...i", self.frame, self.m),
        )


def _observe(args: ShootingArgs, N, M0, saveat, observed, x_last, frame_last):
    """(s, x, frame, n, m) at `saveat` (`observed`: the states there, `implicit`), or where
    `saveat` is None at s = L, from the end of the last piece."""
    if saveat is None:
        n_last = frame_last.T @ N
        m_last = frame_last.T @ (M0 - jnp.cross(x_last - args.start.position, N))
        return (args.length[None], x_last[None], frame_last[None], n_last[None], m_last[None])
    return (saveat, *observed)


def ode_tolerances(options: BoundaryValueOptions, dtype):
    """(rtol, atol) of the flows."""
    return jnp.stack([options.ode_rtol, options.ode_atol]).astype(dtype)


# Compiled with the full options, not to run once: it runs at every eager solve, 61-65
# against 91-99 us (its compilation, 0.62 against 0.30 s, runs beside the solve's at a
# first call: that call's time within the noise, 3.97-4.63 against 3.87-4.73 s).
@jit(static_argnames="guess_kind")
def as_warm_start(rod, length, start: Clamped, end: EndCondition, guess, options: BoundaryValueOptions, guess_kind="helix"):
    """`guess` (as `solve`) as a `WarmStart` (`warm_start_of`), in a program of its own: an
    eager caller passes every guess to `solve` in this one form, so the large solve program
    is compiled once for all of them (not once for the default guess, once for a start
    wrench and once for a warm start).  Not for `continuation > 0` (its start is the
    unloaded rod)."""
    options = options.for_dtype(float_dtype())
    return no_gradient(warm_start_of(rod, length, start, end, guess, options, guess_kind, ode_tolerances(options, float_dtype())))


def _stability_where_solved(rod, length, end: EndCondition, N, M0, xs, frames, end_frame, result, options: BoundaryValueOptions):
    """`stability` on `options.stability_pieces` pieces, undefined (index -1, NaN margin,
    no push, NaN rotation, not chained) where the solve did not succeed; the rotation it
    counts made exact with the solve's start and `end_frame` (`exact_rotation`)."""
    index, margin, push, counted, chained = stability(rod, length, end, N, M0, xs, frames, options)
    defined = result == RESULTS.successful
    rotation = jnp.where(defined, exact_rotation(frames[0], end_frame, counted), jnp.nan)
    return jnp.where(defined, index, -1), jnp.where(defined, margin, jnp.nan), jnp.where(defined, push, 0.0), rotation, defined & chained


def turns_flagged(result, rotation, end: EndCondition):
    """`result` (one solve's, traced or not), `other_whole_turns` where the `rotation` its
    rod holds has other whole turns than `end` asks for (where both are known)."""
    return RESULTS.where(holds_turns(rotation, end.rotation), result, RESULTS.other_whole_turns)


def stability_inputs(sol) -> tuple:
    """What the stability test reads of a solution (or of a batch of them, or of their
    `jax.ShapeDtypeStruct`s): `(N, M0, node positions, node frames, end frame, result)`."""
    return sol.force, sol.moment0, sol.node_position, sol.node_frame, sol.end_frame, sol.result


def with_stability(sol, tested, pieces: int):
    """`sol` with the stability test's `(index, margin, push, rotation, ...)` on `pieces`
    pieces (`replaced`)."""
    index, margin, push, rotation = tested[:4]
    return replaced(
        sol, instability_index=index, stability_margin=margin, unstable_direction=push, rotation=rotation, stability_pieces=pieces
    )


def stability_at_points(rod, length, ends: EndCondition, N, M0, xs, frames, end_frames, result, count, options: BoundaryValueOptions):
    """The stability test of many solutions of one rod (`restability`'s, one after another
    along the leading axis of `ends` and the solutions' arrays) -- of the first `count`
    (traced: one program tests a curve's points and, in its first slot, a bisection's single
    trials), the others left undefined (index -1, NaN margin and rotation, no push):
    `(index, margin, push, rotation, chained)` per point.  A loop, not `vmap`: batched, the test ran
    no faster (a 50-point curve's 37-40 ms either way) and its program traced in 0.75 s
    instead of 0.30 s and compiled in 2.5 s of CPU instead of 1.8 s; the same results to
    1e-9."""
    points = (ends, N, M0, xs, frames, end_frames, result)
    n, dtype = N.shape[0], N.dtype
    untested = (
        jnp.full(n, -1, jnp.int32), jnp.full(n, jnp.nan, dtype), jnp.zeros((n, 6), dtype), jnp.full(n, jnp.nan, dtype), jnp.zeros(n, bool)
    )

    def one(i, tested):
        point = jax.tree.map(lambda a: a[i], points)
        return jax.tree.map(lambda t, v: t.at[i].set(v), tested, _stability_where_solved(rod, length, *point, options))

    return jax.lax.fori_loop(0, count, one, untested)


#: `stability_of_nodes(rod, length, end, N, M0, xs, frames, end_frame, result, options)`:
#: `(index, margin, push, rotation, chained)` of the equilibrium with lab start wrench (`N`, `M0`),
#: shooting nodes `xs`, `frames` and end frame (`stability_inputs`), undefined where
#: `result` is not a success.  A
#: program of its own: the solve and the test compile side by side at a first call
#: (`_compile_side_by_side`), a finer test needs no new solve, nor a compilation of one,
#: and a caller with the same types and options (`follow_branch`) finds it compiled, or
#: compiles it ahead (`compile_ahead`).
stability_of_nodes = jit(_stability_where_solved, trace_cache=True)


def restability(rod, length, end: EndCondition, sol, options: BoundaryValueOptions):
    """`(sol with its stability tested on options.stability_pieces pieces, chained)`
    (`stability`'s flag: whether its pieces needed chains; on the device).  Measured per
    call (the default cantilever): the program's dispatch 12 us with these arguments against
    56 us with the whole solution in and out, and `replaced` 6 us against 66 us for
    `dataclasses.replace`, which runs the solution's `__init__` again."""
    tested = stability_of_nodes(rod, length, end, *stability_inputs(sol), options)
    return with_stability(sol, tested, options.stability_pieces), tested[4]


# A program of its own, compiled to run once (one per call of `solve_boundary_value`), as
# `unloaded_clamp` is: evaluated operation by operation each compiled one-operation programs.
@jit(run_once=True)
def _bending_stiffness(rod):
    """$\\partial m_1/\\partial u_1$ at the intrinsic twist."""
    return jax.jacfwd(no_gradient(rod).moment)(jnp.asarray(rod.uhat))[0, 0]


def solve_with_warm_start(rod, length, start: Clamped, end: EndCondition, guess, saveat, options: BoundaryValueOptions, guess_kind="helix"):
    """`(solution, chained)`: `solve`, with the guess first made a `WarmStart`
    (`as_warm_start`; not under continuation, which starts from the unloaded rod, nor for a
    guess that is one), and the stability test (`options.stability_pieces`) as a program of
    its own (`restability`; `chained` its flag, None untested), the two compiled side by
    side at the first call (`_compile_side_by_side`)."""
    converts = options.continuation == 0 and not isinstance(guess, WarmStart)
    _compile_side_by_side(rod, length, start, end, guess, saveat, options, guess_kind, converts)
    if converts:
        guess = as_warm_start(rod, length, start, end, guess, options, guess_kind)
    sol = solve(rod, length, start, end, guess, saveat, options, guess_kind, test_stability=False)
    return restability(rod, length, end, sol, options) if options.stability_pieces > 0 else (sol, None)


def _solve_signature(rod, length, start, end, guess, saveat, options, guess_kind, converts: bool):
    """What the programs of `solve_with_warm_start` are compiled for: its options, guess,
    arguments' structure and saved points' shape."""
    # A guess made a warm start and a warm start given (a retry's) meet the same solve.
    form = "warm start" if converts or isinstance(guess, WarmStart) else jax.tree.structure(guess)
    return (jax.tree.structure((rod, start, end, options)), guess_kind, form, None if saveat is None else jnp.shape(saveat), float_dtype())


@once_per_signature(_solve_signature)
def _compile_side_by_side(rod, length, start, end, guess, saveat, options, guess_kind, converts: bool) -> bool:
    """At the first eager call of its kind: start compiling its programs -- the guess made a
    warm start, the solve without the stability test and the stability test --
    each on a thread of its own (`compile_ahead`: each traced here, from the output
    structure of the one before).  On 2 cores the first call of the cantilever of
    `benchmarks/bench_first_calls.py` took 4.1-4.9 s against 5.2-6.2 s with the one program
    of solve and test before (an empty compilation cache; 4.1-4.3 s against 5.6-5.9 s
    without one; fresh processes alternating)."""
    if converts:
        guess = compile_ahead(as_warm_start, rod, length, start, end, guess, options, guess_kind)
        if guess is None:  # nothing to compile beside the call (traced, one core)
            return False
    sol = compile_ahead(solve, rod, length, start, end, guess, saveat, options, guess_kind, test_stability=False)
    if sol is None:
        return False
    if options.stability_pieces > 0:
        compile_ahead(stability_of_nodes, rod, length, end, *stability_inputs(sol), options)
    return True


@jit(static_argnames=("guess_kind", "test_stability"), trace_cache=True)
def solve(
    rod, length, start: Clamped, end: EndCondition, guess, saveat, options: BoundaryValueOptions, guess_kind="helix", test_stability=True
):
    """The solve behind `solve_boundary_value` (checked inputs; never raises: read
    `result`).  `guess`: `None` (the default guess of `guess_kind`), a `WarmStart` of as
    many pieces, or `(n0, m0)`.  `test_stability=False`: without the stability test
    (`stability_pieces` 0 in the solution; `restability` tests it)."""
    dtype = float_dtype()
    options = options.for_dtype(dtype)
    valid = jnp.isfinite(length) & (length > 0) & end.finite()
    valid = valid & jnp.all(jnp.isfinite(start.position)) & jnp.all(jnp.isfinite(start.frame))
    # Frames checked by `check_rotation` where concrete; traced ones here (a reflected or
    # scaled frame was solved, ok, with a wrong answer).
    valid = valid & is_rotation(start.frame) & is_rotation(end.frame)
    if isinstance(guess, tuple):
        valid = valid & jnp.all(jnp.isfinite(guess[0])) & jnp.all(jnp.isfinite(guess[1]))
    elif isinstance(guess, WarmStart):
        valid = valid & jnp.all(jnp.isfinite(guess.force)) & jnp.all(jnp.isfinite(guess.moment0))
    if saveat is not None:
        valid = valid & increases_within(saveat, length, SAVEAT_SLACK)
    # Invalid input (under vmap): solve a harmless problem, return NaN.
    length = jnp.where(valid, length, 1.0)
    if saveat is not None:
        saveat = jnp.where(valid, saveat, jnp.linspace(0.0, 1.0, saveat.shape[0], dtype=saveat.dtype))
    harmless_start = unloaded_clamp(no_gradient(rod))
    start = tree_where(valid, start, harmless_start)
    end = tree_where(valid, end, end_condition(LOADED, point=jnp.zeros(3, dtype)))
    k = options.segments
    scales = residual_scales(rod, length)
    ode_tol = ode_tolerances(options, dtype)

    y0, ref_x, ref_frame = no_gradient(initial(rod, length, start, end, guess, options, guess_kind, scales, ode_tol))
    args = ShootingArgs(rod, length, start, end, ref_x, ref_frame, scales, ode_tol)
    steps = jnp.zeros((), jnp.int32)
    if options.continuation > 0:
        frozen = no_gradient(args)
        x_free, frame_free = (a[-1] for a in free_nodes(frozen.rod, frozen.length, frozen.start, 1))
        unloaded_rotation = unloaded_observables(frozen.rod, frozen.length)[1]

        def step(carry, t):
            y, ref_x, ref_frame, steps = carry
            end_t = frozen.end.homotopy(t, x_free, frame_free, unloaded_rotation)
            args_t = eqx.tree_at(lambda a: (a.end, a.ref_x, a.ref_frame), frozen, (end_t, ref_x, ref_frame))
            y, *_, n = root(y, args_t, options)
            y, args_t = rebase(y, args_t, k)
            return (y, args_t.ref_x, args_t.ref_frame, steps + n), None

        ts = jnp.arange(1, options.continuation, dtype=dtype) / options.continuation
        (y0, ref_x, ref_frame, steps), _ = jax.lax.scan(step, (y0, ref_x, ref_frame, steps), ts)
        args = eqx.tree_at(lambda a: (a.ref_x, a.ref_frame), args, (ref_x, ref_frame))

    # Intermediate homotopy steps need not converge: only the last solve counts.
    y, pieces, flows, saved, residual, result, n = root(y0, args, options, saveat)
    steps = steps + n
    y, (nodes, ends), observed = implicit(y, pieces, flows, saved, args, saveat, options=options)
    (N, M0, xs, frames), (x_end, frame_end, force_end, moment_end) = nodes, ends
    residual = jax.lax.stop_gradient(jnp.where(jnp.isfinite(residual) & valid, residual, jnp.inf))
    tolerance = jnp.asarray(10 * options.atol, dtype)
    result = promote(result)
    result = RESULTS.where(
        (result == RESULTS.successful) & ~(residual <= tolerance), RESULTS.residual_above_tolerance, result
    )
    result = RESULTS.where(valid, result, RESULTS.invalid_input)

    out = _observe(args, N, M0, saveat, observed, x_end[-1], frame_end[-1])
    tested = test_stability and options.stability_pieces > 0
    if tested:
        index, margin, push, rotation, _ = _stability_where_solved(rod, length, end, N, M0, xs, frames, frame_end[-1], result, options)
        result = turns_flagged(result, rotation, end)
    else:
        index, margin, push = jnp.asarray(-1, jnp.int32), jnp.asarray(jnp.nan, dtype), jnp.zeros(6, dtype)
        rotation = jnp.asarray(jnp.nan, dtype)
    nan = lambda a: jnp.where(valid, a, jnp.nan)  # noqa: E731
    return BoundaryValueSolution(
        s=out[0],
        x=nan(out[1]),
        frame=nan(out[2]),
        n=nan(out[3]),
        m=nan(out[4]),
        n0=nan(args.start.frame.T @ N),
        m0=nan(args.start.frame.T @ M0),
        force=nan(N),
        moment0=nan(M0),
        end_position=nan(x_end[-1]),
        end_frame=nan(frame_end[-1]),
        end_force=nan(force_end[-1]),
        end_moment=nan(moment_end[-1]),
        node_position=nan(xs),
        node_frame=nan(frames),
        residual=residual,
        result=result,
        num_steps=jnp.asarray(steps, jnp.int32),
        valid_input=valid,
        tolerance=tolerance,
        instability_index=index,
        stability_margin=margin,
        unstable_direction=push,
        rotation=rotation,
        stability_pieces=options.stability_pieces if tested else 0,
        continuation=options.continuation,
    )


_TURNS_HINT = (
    "; twist it there along a curve (`rotation_response`), warm-start from a solution with those turns, "
    "or use throw=False to take this one"
)

#: Relative slack of the last saved arc length beyond L (the round-off of a `linspace` to L).
SAVEAT_SLACK = 1e-12

_HINT = "; try continuation=, more segments=, a better guess=, or throw=False to inspect `result` and `residual`"


def solve_boundary_value(
    rod,
    length: ArrayLike,
    *,
    start: Clamped | None = None,
    end: AbstractEnd,
    guess: BoundaryValueSolution | tuple[ArrayLike, ArrayLike] | str | None = None,
    saveat: ArrayLike | None = None,
    options: BoundaryValueOptions | None = None,
    segments: int | str | None = None,
    continuation: int | None = None,
    method: str | None = None,
    atol: float | None = None,
    max_steps: int | None = None,
    ode_rtol: float | None = None,
    ode_atol: float | None = None,
    solver: diffrax.AbstractSolver | None = None,
    max_ode_steps: int | None = None,
    adjoint: diffrax.AbstractAdjoint | None = None,
    stability_pieces: int | None = None,
    throw: bool = True,
) -> BoundaryValueSolution:
    """Equilibrium of a finite rod clamped at $s = 0$ with a condition at $s = L$.

    **Arguments**

    - `rod`: a `Rod` (or any constitutive law usable by `solve_static`); unbatched.
    - `length`: $L > 0$.
    - `start`: `Clamped(position, frame)` at $s = 0$; default: the canonical placement of the
      unloaded rod (its intrinsic helix with axis $e_z$ through the origin, see
      `axial_ends`).
    - `end`: `Clamped`, `Loaded` or `Tweezer` (or their uniform form `EndCondition`);
      `axial_ends` builds the common spring and tweezer conditions.
    - `guess`: `None` (default) -- the uniform helix with the end's axial extension and
      rotation (or force and rotation) from the bulk equations, exact for a `Loaded` end
      about a fixed point; `"zero"` -- the unloaded rod; a `BoundaryValueSolution` (warm
      start, e.g. the previous point of a curve); or a pair `(n0, m0)` of start wrenches in
      the director frame.  The rotation of a frame condition is known only modulo a full
      turn: to turn an end by more than half a turn from the guess, continue in the
      rotation (`rotation_response`) or warm-start.
    - `saveat`: increasing arc lengths in $[0, L]$ at which to return the centreline, frame
      and wrench (default: $s = L$ only).
    - `options`: a `BoundaryValueOptions` (shooting pieces, homotopy steps, root finder,
      tolerances, integrator, adjoint; default `BoundaryValueOptions()`); each of
      `segments`, `continuation`, `method`, `atol`, `max_steps`, `ode_rtol`, `ode_atol`,
      `solver`, `max_ode_steps`, `adjoint`, `stability_pieces` given here replaces that
      field.  Use more
      `segments` for long rods in spatially unstable states (`wrench_growth_rate`), or
      `segments="auto"`: $\\lceil\\lambda L/3\\rceil$ pieces from the growth rate $\\lambda$ of
      the guess (eager calls only).
      Derivatives (`jax.jvp`/`jax.jacfwd`; `jax.grad` with `adjoint=diffrax.DirectAdjoint()`)
      are those of the implicit function theorem on the shooting equations.
    - `throw`: raise `SolverError` when the solve fails (an equinox runtime error inside
      `jax.jit`); with `throw=False` read `ok`, `result`, `residual` -- use it under
      `jax.vmap`, where an invalid point gives NaN fields and `valid_input = False` without
      spoiling the batch.

    **Errors.** Bad shapes, non-finite concrete values, `length <= 0`, a frame that is not a
    rotation, bad options, an unknown `guess` raise `ValueError`.

    **Example**

    ```python
    rod = helixrod.Rod(1.0, 1.0, 0.77, uhat=(0.0, 1.0, 0.3))       # a helical spring
    start, end = helixrod.axial_ends(rod, 30.0, extension=12.0, rotation=30 * 1.044)
    sol = helixrod.solve_boundary_value(rod, 30.0, start=start, end=end, segments=4,
                                        saveat=jnp.linspace(0, 30, 200))
    sol.force, sol.x            # reaction force; centreline
    ```
    """
    owner = "solve_boundary_value"
    auto = automatic_segments(segments, owner)
    options = with_settings(
        options, segments=None if auto else segments, continuation=continuation, method=method, atol=atol, max_steps=max_steps,
        ode_rtol=ode_rtol, ode_atol=ode_atol, solver=solver, max_ode_steps=max_ode_steps, adjoint=adjoint,
        stability_pieces=stability_pieces,
    )
    check_one_rod(rod, owner)
    if not isinstance(end, AbstractEnd):
        raise ValueError(f"{owner}: end must be Clamped, Loaded or Tweezer, got {type(end).__name__}")
    if start is None:
        start = unloaded_clamp(rod)
    if not isinstance(start, Clamped):
        raise ValueError(f"{owner}: start must be Clamped, got {type(start).__name__}")
    start = as_start(start)
    end = type(end).condition(end)  # not `end.condition()`: equinox binds a method as a Module (~20 us)
    for name, cond in (("start", start), ("end", end)):
        if any(jnp.ndim(leaf) > 2 or (jnp.ndim(leaf) == 2 and jnp.shape(leaf) != (3, 3)) for leaf in jax.tree.leaves(cond)):
            raise ValueError(f"{owner}: {name} must be unbatched (jax.vmap over conditions)")
    length = finite_scalar(length, "length", owner, positive=True)
    default_guess = guess is None
    guess, guess_kind = parse_guess(guess, owner)
    if saveat is not None:
        saveat = increasing_within(saveat, length, "saveat", owner, slack=SAVEAT_SLACK)
    if auto:
        if not is_concrete(rod, length, start, end, guess):
            raise ValueError(f"{owner}: segments='auto' needs concrete inputs (not under jax.jit or vmap)")
        segments_needed, _, (n0, m0) = needed_segments(rod, length, start, end, guess, guess_kind)
        pieces = options.stability_pieces and max(options.stability_pieces, pieces_for_rate(wrench_rate(rod, n0, m0), length))
        options = dataclasses.replace(options, segments=segments_needed, stability_pieces=min(pieces, MAX_STABILITY_PIECES))
    guess = fit_guess(guess, options.segments, start)
    sol, chained = solve_with_warm_start(rod, length, start, end, guess, saveat, options, guess_kind)
    # One program made every field: two of them say whether they are concrete (the residual
    # carries no derivative; the force does, under an eager jax.jvp or jax.jacfwd).
    if not (is_concrete(sol.residual, sol.force) and jnp.ndim(sol.residual) == 0):
        # Traced: flagged here (an eager call flags after its fallbacks, `_physical`).
        sol = replaced(sol, result=turns_flagged(sol.result, sol.rotation, end))
        return raise_if_failed(sol, sol.result, f"{owner}: the shooting equations were not solved", _HINT) if throw else sol
    sol, ok = _physical(sol, chained, rod, length, start, end, default_guess, saveat, options, guess_kind)
    if throw and not ok:
        if has_code(sol.result, RESULTS.other_whole_turns):
            held = float(sol.rotation)
            raise SolverError(
                f"{owner}: {RESULTS[sol.result]} It holds {held / (2 * np.pi):.2f} turns, the end asks for "
                f"{float(end.rotation) / (2 * np.pi):.2f}{_TURNS_HINT}"
            )
        raise_if_failed(sol, sol.result, f"{owner}: the shooting equations were not solved", _hint(sol, rod, length, start, end, guess, guess_kind))
    return sol


def fit_guess(guess, segments: int, start: Clamped):
    """A `WarmStart` of another number of pieces as its start wrench `(n0, m0)`."""
    if isinstance(guess, WarmStart) and guess.node_position.shape[0] != segments:
        return (start.frame.T @ guess.force, start.frame.T @ guess.moment0)
    return guess


def parse_guess(guess, owner: str):
    """(guess for `solve` -- pass it through `fit_guess` --, guess kind) from a user's
    `guess=`: `None`, `"helix"`, `"zero"`, a `BoundaryValueSolution` or a pair `(n0, m0)` of
    start wrenches (director frame)."""
    if isinstance(guess, str):
        if guess not in ("helix", "zero"):
            raise ValueError(f"{owner}: guess must be None, 'helix', 'zero', a solution or (n0, m0); got {guess!r}")
        return None, guess
    if guess is None:
        return None, "helix"
    if isinstance(guess, BoundaryValueSolution):
        if jnp.ndim(guess.residual) != 0:
            raise ValueError(f"{owner}: guess must be one solution, not a batch of them")
        return guess.warm_start(), "helix"
    try:
        n0, m0 = (jnp.asarray(g, float_dtype()) for g in guess)
    except (TypeError, ValueError):
        raise ValueError(f"{owner}: guess must be None, 'helix', 'zero', a solution or (n0, m0)") from None
    if n0.shape != (3,) or m0.shape != (3,):
        raise ValueError(f"{owner}: guess (n0, m0) needs shapes (3,), got {n0.shape}, {m0.shape}")
    if is_concrete(n0, m0) and not (np.all(np.isfinite(np.asarray(n0))) and np.all(np.isfinite(np.asarray(m0)))):
        raise ValueError(f"{owner}: guess (n0, m0) must be finite")
    return (n0, m0), "helix"


#: Spatial growth (lambda L) one shooting piece is trusted with (`wrench_growth_rate`: from
#: the bulk guess single shooting converged up to lambda L ~ 3 and failed beyond ~ 4).
GROWTH_PER_SEGMENT = 3.0


@jit(static_argnames="guess_kind")
def _guess_wrench(rod, length, start, end, guess_kind):
    warm = default_warm_start(rod, length, start, end, 1, guess_kind)
    return start.frame.T @ warm.force, start.frame.T @ warm.moment0


def automatic_segments(segments, owner: str) -> bool:
    """Whether an entry point's `segments` keyword asks for `"auto"` (`needed_segments`);
    `ValueError` naming `owner` for another word (an integer or None goes on to
    `with_settings`)."""
    if not isinstance(segments, str):
        return False
    if segments != "auto":
        raise ValueError(f"{owner}: segments must be an integer >= 1 or 'auto', got {segments!r}")
    return True


def needed_segments(rod, length, start, end, guess, guess_kind):
    """Shooting pieces for `segments="auto"`, $\\lceil\\lambda L / 3\\rceil$, $\\lambda L$ and
    the guess's local start wrench `(n0, m0)`, with $\\lambda$ the spatial growth rate
    (`wrench_growth_rate`) of that wrench (concrete)."""
    if guess is None:
        n0, m0 = _guess_wrench(rod, length, start, end, guess_kind)
    elif isinstance(guess, WarmStart):
        n0, m0 = start.frame.T @ guess.force, start.frame.T @ guess.moment0
    else:
        n0, m0 = guess
    growth = float(wrench_growth_rate(rod, n0, m0)) * float(length)
    segments = max(1, int(np.ceil(growth / GROWTH_PER_SEGMENT))) if np.isfinite(growth) else 1
    return segments, growth, (n0, m0)


def _hint(sol, rod, length, start, end, guess, guess_kind) -> str:
    """`_HINT`, with the pieces the guess's spatial growth asks for where they are more."""
    needed, growth, _ = needed_segments(rod, length, start, end, guess, guess_kind)
    if needed <= sol.segments:
        return _HINT
    return (
        f"; errors in the guess grow like exp(lambda L) along the rod, lambda L = {growth:.1f} "
        f"(wrench_growth_rate): use segments={needed} or more (now {sol.segments}; or segments='auto'), "
        "continuation=, a better guess=, or throw=False to inspect `result` and `residual`"
    )


#: Homotopy steps tried, in turn, when the default guess fails or finds an unstable state.
FALLBACK_CONTINUATION = (16,)

#: The most pieces of a stability test (doubled from `stability_pieces` until resolved).
MAX_STABILITY_PIECES = 256


# A program of its own, compiled to run once: evaluated operation by operation, the
# stiffness's derivative and eigenvalue compiled ~15 one-operation programs (~0.3 s) at
# the first curve whose test needed more pieces.
@jit(run_once=True)
def _smallest_stiffness(rod):
    """The smallest eigenvalue of the stiffness at $\\hat u$ (`stiffness_range`)."""
    return stiffness_range(rod)[0]


def wrench_rate(rod, force, moments) -> float:
    """`wrench_scale` of a wrench of lab `force` `(3,)` and moments `(..., 3)` along the rod
    (concrete; on the host)."""
    force, moments = np.asarray(force), np.asarray(moments)
    largest = float(np.max(np.linalg.norm(moments.reshape(-1, 3), axis=-1)))
    return float(wrench_scale(float(_smallest_stiffness(rod)), float(np.linalg.norm(force)), largest))


def pieces_for_rate(rate: float, length) -> int:
    """Pieces of the stability test that resolve a wrench of scale `rate` (`wrench_rate`),
    with a margin of 1.25: a power of two."""
    return int(2 ** np.ceil(np.log2(max(1.0, 1.25 * rate * float(length) / PIECE_RESOLUTION))))


def equilibrium_rate(rod, force, moment0, node_position, end_position) -> float:
    """`wrench_rate` of an equilibrium: lab force `force`, lab moment `moment0` at s = 0 and
    the moments it makes about its shooting nodes and its end (the lab moment about a point
    moves with the point)."""
    force, moment0, node_position, end_position = jax.device_get((force, moment0, node_position, end_position))
    points = np.concatenate([node_position, np.asarray(end_position)[None]])
    moments = np.asarray(moment0)[None] - np.cross(points - node_position[0][None], np.asarray(force)[None])
    return wrench_rate(rod, force, moments)


def _moment_loaded(end: EndCondition) -> bool:
    """Whether a concrete end is loaded by a moment (whose stability is not defined)."""
    kind, moment = jax.device_get((end.kind, end.moment))
    return int(kind) == LOADED and bool(np.any(moment != 0))


def _finer_pieces(pieces: int, needed: int) -> int:
    """The pieces of the next test of an equilibrium whose test on `pieces` did not resolve
    its wrench: twice as many, or as many as the wrench asks (`needed`), at most
    `MAX_STABILITY_PIECES`."""
    return min(max(2 * pieces, needed), MAX_STABILITY_PIECES)


def resolved_test(rod, length, end: EndCondition, inputs: tuple, tested: tuple, options: BoundaryValueOptions, end_position, chained=None):
    """`(test, pieces)`: the stability test `tested` = (index, margin, push, ...) of one
    concrete equilibrium at `end` (`inputs` = its `stability_inputs`, its end at
    `end_position`) on `options.stability_pieces` pieces, and again while that does not
    resolve its wrench (a converged point of index -1, or one whose pieces needed chains --
    `chained`, the test's flag, which bounds the moments along each piece; None: not known
    -- and are longer than `PIECE_RESOLUTION` for its wrench, `equilibrium_rate`: the chains
    give its index, the margin and direction are those of pieces too coarse for its modes):
    on twice the pieces or as many as the wrench asks (`pieces_for_rate`), up to
    `MAX_STABILITY_PIECES` (`stability_of_nodes`); not where the end is loaded by a moment,
    whose stability is not defined.  (A curve's points and its bisection's trials keep the
    curve's pieces: one program for all of them.)"""
    pieces = options.stability_pieces
    while 0 < pieces < MAX_STABILITY_PIECES:
        result, index, chained = jax.device_get((inputs[-1], tested[0], chained))
        # The common case in one read: a resolved test of pieces that needed no chains (the
        # wrench's pieces read on the host cost ~60 us a solve).
        if int(index) >= 0 and chained is not None and not bool(chained):
            break
        if not bool(succeeded(result)) or _moment_loaded(end):
            break
        # Also where the pieces' chains resolved the index: the margin and direction are
        # then those of the coarser pieces (at 150 critical loads of a column the direction
        # of 16 chained pieces had cosine 0.43 with that of 128 pieces; of 32: 0.91).
        rate = equilibrium_rate(rod, inputs[0], inputs[1], inputs[2], end_position)
        if int(index) >= 0 and rate * float(length) <= pieces * PIECE_RESOLUTION:
            break
        pieces = _finer_pieces(pieces, pieces_for_rate(rate, length))
        tested = stability_of_nodes(rod, length, end, *inputs, dataclasses.replace(options, stability_pieces=pieces))
        chained = tested[4]
    return tested, pieces


def test_pieces_ahead(rod, length, points, options: BoundaryValueOptions) -> None:
    """Start compiling, side by side (`compile_ahead`), the finer stability tests that
    `resolved_stability` will run first for each of `points` -- pairs `(end, sol)` of
    concrete solutions whose test on `options.stability_pieces` pieces did not resolve
    their wrench: on as many pieces as `resolved_test` takes first (one program for each
    count).  Tested one after another, the first curve of a pulled spring (3 turns, forces
    to 0.5) compiled its tests on 32, 64 and 128 pieces one after the other (before the
    test's chains of sub-pieces resolved them all on 16: now a point whose piece holds a
    conjugate point of its own comes here)."""
    counts = {}
    for end, sol in points:
        rate = equilibrium_rate(rod, sol.force, sol.moment0, sol.node_position, sol.end_position)
        counts.setdefault(_finer_pieces(options.stability_pieces, pieces_for_rate(rate, length)), (end, sol))
    if len(counts) > 1:  # (one count: its call compiles it as soon)
        for pieces, (end, sol) in counts.items():
            compile_ahead(stability_of_nodes, rod, length, end, *stability_inputs(sol), dataclasses.replace(options, stability_pieces=pieces))


def resolved_stability(
    rod, length, end: EndCondition, sol: BoundaryValueSolution, options: BoundaryValueOptions, chained=None
) -> BoundaryValueSolution:
    """`sol` (one concrete solution at `end`, tested on `options.stability_pieces` pieces;
    `chained` as `resolved_test`) with its test resolved (`resolved_test`)."""
    tested = (sol.instability_index, sol.stability_margin, sol.unstable_direction)
    tested, pieces = resolved_test(rod, length, end, stability_inputs(sol), tested, options, sol.end_position, chained)
    return sol if pieces == options.stability_pieces else with_stability(sol, tested, pieces)


def _physical(sol, chained, rod, length, start, end, default_guess, saveat, options, guess_kind) -> tuple[BoundaryValueSolution, bool]:
    """The eager defaults that make a solve land on the physical state: more stability
    pieces where the test does not resolve the wrench (`chained`: the flag of `sol`'s test,
    `restability`), and, from the default guess, when
    the direct solve converges to an unstable equilibrium, a solve pushed to either side
    along its most unstable direction; when that fails too, or the direct solve did: for an
    intrinsically straight rod between clamps brought closer than its length, the first
    buckled mode (`buckled_guess`), then homotopy continuation from the unloaded rod
    (`FALLBACK_CONTINUATION`), and last, where the guess's spatial growth asks for more
    shooting pieces (`needed_segments`), that continuation on that many pieces.  Where the
    end knows its total rotation (`rotation`, e.g. from `axial_ends`), a state is accepted
    only if it holds those whole turns (its `rotation`, as the stability test counts it); a
    converged solution that does not is returned with result `other_whole_turns`.  Returns
    the solution and whether it succeeded."""
    asked = None

    def verdict(trial, chained=None) -> tuple[tuple[bool, int, bool], bool | None]:
        """(succeeded, instability index, holds the asked whole turns) of a solution, and
        its test's `chained` flag, in one transfer from the device for the common case (each
        read cost 5-20 us; the checks of an eager call made seven)."""
        nonlocal asked
        wanted = end.rotation if asked is None else 0.0
        result, index, rotation, wanted, chained = jax.device_get(
            (trial.result, trial.instability_index, trial.rotation, wanted, chained)
        )
        asked = np.asarray(wanted) if asked is None else asked
        ok = bool(succeeded(result))
        held = not np.isfinite(asked) or bool(holds_turns(np.asarray(rotation), asked))
        return (ok, int(index), held), (None if chained is None else bool(chained))

    def resolved(trial, chained):
        """`trial` with its stability resolved (`resolved_stability`: only where it
        converged and its test did not resolve the wrench) and its verdict."""
        judged, chained = verdict(trial, chained)
        if judged[0] and (judged[1] < 0 or chained is None or chained):
            retested = resolved_stability(rod, length, end, trial, options, chained)
            if retested is not trial:
                trial, judged = retested, verdict(retested)[0]
        return trial, judged

    def flagged(chosen, judged):
        if judged[0] and not judged[2]:
            return replaced(chosen, result=RESULTS.other_whole_turns), False
        return chosen, judged[0]

    def solved(guess, options):
        return resolved(*solve_with_warm_start(rod, length, start, end, guess, saveat, options, guess_kind))

    def acceptable(judged) -> bool:
        ok, index, held = judged
        return ok and index <= 0 and held

    def settled(trial, judged):
        """`trial`, or where it converged to an unstable state, a solve pushed from it to
        either side along its most unstable direction, by two sizes; None if neither is
        acceptable."""
        if acceptable(judged):
            return trial, judged
        if not judged[0]:
            return None
        # In NumPy: JAX would compile each of these operations eagerly (~0.1 s).
        frame, push = np.asarray(start.frame), np.asarray(trial.unstable_direction)
        dtype = trial.force.dtype
        for sign in (1.0, -1.0, 4.0, -4.0):
            N = np.asarray(trial.force) + sign * push[:3]
            M0 = np.asarray(trial.moment0) + sign * push[3:]
            # Single shooting needs no nodes: the pushed wrench is a warm start as it is, with
            # no program to convert it (`as_warm_start` compiled for a wrench, 0.3-0.4 s).
            guess = (
                WarmStart(N.astype(dtype), M0.astype(dtype), trial.node_position, trial.node_frame)
                if options.segments == 1 else (frame.T @ N, frame.T @ M0)
            )
            pushed, pushed_judged = solved(guess, options)
            if acceptable(pushed_judged):
                return pushed, pushed_judged
        return None

    sol, judged = resolved(sol, chained)
    if not default_guess or options.continuation > 0 or acceptable(judged):
        return flagged(sol, judged)
    found = settled(sol, judged)
    if found is not None:
        return flagged(*found)
    bending = float(_bending_stiffness(rod))
    straight = not np.any(np.asarray(rod.uhat)[:2] != 0)
    buckled = buckled_guess(rod, length, start, end, bending) if straight and int(end.kind) == CLAMPED else None
    if buckled is not None:
        found = settled(*solved(buckled, options))
        if found is not None:
            return flagged(*found)
    for steps in FALLBACK_CONTINUATION:
        homotopy = dataclasses.replace(options, continuation=steps)
        trial, trial_judged = solved(None, homotopy)
        # A converged state before a failed one; the asked whole turns before other ones.
        better = trial_judged[0] and (not judged[0] or (trial_judged[2] and not judged[2]))
        if acceptable(trial_judged) or better:
            sol, judged = trial, trial_judged
        if acceptable(judged):
            break
    # Last, where the guess's spatial growth asks for more shooting pieces than these
    # (`needed_segments`, as `segments="auto"`): errors of the start wrench grow like
    # exp(lambda L) along one piece, and single shooting of a stretched spring lands on an
    # unstable state or none.  Continuation from the unloaded rod on that many pieces (their
    # direct solve from the guess found other whole turns on the spring of
    # `tests/test_bvp_solve.py`).
    needed = 1 if acceptable(judged) else needed_segments(rod, length, start, end, None, guess_kind)[0]
    if needed > options.segments:
        for steps in FALLBACK_CONTINUATION:
            trial, trial_judged = solved(None, dataclasses.replace(options, segments=needed, continuation=steps))
            if acceptable(trial_judged):
                sol, judged = trial, trial_judged
                break
    return flagged(sol, judged)
