"""Branches of equilibria of a finite rod along a load parameter: pseudo-arclength
continuation that passes folds, detects branch points and switches onto the bifurcating
branch (the services of AUTO-07p and BifurcationKit that users of those rely on, for rods).

The unknowns are those of the shooting equations (`_shooting.py`, scaled: forces by
$\\bar K/\\ell^2$, moments by $\\bar K/\\ell$) and the load parameter $\\lambda$, scaled by the
width of the range asked for: $z = (y, \\lambda/\\Lambda)$, $G(z) = 0$ the $6k$ shooting
equations of the end condition `end(lambda)`.  From a point $z_j$ with unit tangent $t_j$
(the null vector of $G_z$, oriented along the branch) the predictor $z_j + \\Delta s\\,t_j$ is
corrected by Newton's method on $G(z) = 0$, $t_j\\cdot(z - z_j) = \\Delta s$ (Keller 1977), the
Jacobian from the Jacobi fields of the pieces in equal Runge--Kutta steps
(`JACOBIAN_STEPS_PER_RADIAN`; the residual keeps the ODE tolerance, and so the branch).  The
step grows after easy corrections and halves after failed ones.

Test functions (Seydel, *Practical Bifurcation and Stability Analysis*, 2010, sec. 5.3):

- a **fold** (limit point) where the parameter component of the tangent, $t_\\lambda$,
  changes sign: the branch turns back in $\\lambda$;
- a **branch point** where $\\det\\begin{pmatrix} G_z \\\\ t^T\\end{pmatrix}$ changes sign and
  $t_\\lambda$ does not: another branch crosses (a simple one; a double branch point, as of an
  isotropic rod's two bending planes, leaves the sign unchanged and is reported only by the
  jump of the stability index by two).

Each is located by bisection in the arclength between the two points that bracket it, on the
sign of its test function.  Forward-mode derivatives of the adaptive integration, which the
corrector used before, are not accurate where a piece is straight (the adaptive steps follow
the solution, exact there in one step, not its variations): they placed the branch points of
`tests/test_branch.py`'s Euler column 2.1e-3 and 7.4e-4 off, the Jacobi fields 2.8e-9 and
1.3e-9.  At a
branch point the kernel of $G_z$ is two-dimensional; its direction orthogonal to the branch's
tangent (from the SVD) is the tangent of the bifurcating branch, stored with the point:
`follow_branch(..., switch=point)` continues along it.  Every point carries the stability of
the equilibrium (`_stability.py`): stability is exchanged at folds and branch points.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._compile import TracedFunction, committed_placement, compile_ahead, jit, leaf_shapes, once_per_signature
from .._misc import check_integer, finite_scalar, float_dtype
from .._rod import check_one_rod
from .._status import RESULTS
from ._bulk import residual_scales
from ._ends import AbstractEnd, Clamped, as_start, unloaded_clamp
from ._options import BoundaryValueOptions, with_settings
from ._shooting import ShootingArgs, linearised_equations, residual_and_flows
from ._solve import as_warm_start, ode_tolerances, resolved_test, solve_boundary_value, stability_of_nodes

#: Special points a branch reports.
SPECIAL_KINDS = ("fold", "branch point")

#: Bisection steps that locate a special point between two points of a branch.
LOCATE_BISECTIONS = 30

#: Newton steps of one corrector.
CORRECTOR_STEPS = 12

#: Equal Runge--Kutta steps per radian of the Jacobi fields behind the corrector's Jacobian,
#: its tangent and the determinant's sign (`linearised_equations`).
JACOBIAN_STEPS_PER_RADIAN = 48

#: A first point whose bordered Jacobian has a singular value below this fraction of its
#: largest is not isolated (a continuum of equilibria, round-off from exactly singular:
#: measured on a straight shaft between clamps its length apart, 4e-19 and 7e-19).
NOT_ISOLATED = 1e-12

#: Largest angle (cosine) between consecutive tangents: a sharper turn is a jump to another
#: branch and the step is halved.
SMALLEST_COSINE = 0.9


class SpecialPoint(eqx.Module):
    """A fold or a branch point of a `Branch`: its `kind`, the load `parameter` there, the
    lab `force` and `moment0` there, `after` (it lies between points `after` and `after + 1`
    of the branch), and for branch points the tangent `direction` of the bifurcating branch
    (continue along it with `follow_branch(..., switch=point)`)."""

    kind: str = eqx.field(static=True)
    parameter: Float[Array, ""]
    after: int = eqx.field(static=True)
    force: Float[Array, "3"]
    moment0: Float[Array, "3"]
    state: Float[Array, " d"]
    direction: Float[Array, " d"]
    node_position: Float[Array, "k 3"]
    node_frame: Float[Array, "k 3 3"]


class Branch(eqx.Module):
    """Result of `follow_branch`: per point (leading axis `n`, in the order of the branch)
    the load `parameter`, the arclength `arclength` (scaled unknowns), the lab `force`,
    `moment0` (at $s = 0$), the start wrench `n0`, `m0` in the director frame (a `guess=` for
    `solve_boundary_value` at that parameter), `end_position`, `end_frame`, the shooting
    nodes `node_position` `(n, k, 3)`, `node_frame`, and the stability:
    `instability_index` (-1 where not defined), `stability_margin`, and the end's total
    `rotation` about $e_z$ with the whole turns the rod holds (as
    `BoundaryValueSolution.rotation`; NaN where not tested); `special` the folds and branch
    points found, in order; `message` why the branch ended."""

    parameter: Float[Array, " n"]
    arclength: Float[Array, " n"]
    force: Float[Array, "n 3"]
    moment0: Float[Array, "n 3"]
    n0: Float[Array, "n 3"]
    m0: Float[Array, "n 3"]
    end_position: Float[Array, "n 3"]
    end_frame: Float[Array, "n 3 3"]
    node_position: Float[Array, "n k 3"]
    node_frame: Float[Array, "n k 3 3"]
    instability_index: Int[Array, " n"]
    stability_margin: Float[Array, " n"]
    rotation: Float[Array, " n"]
    special: tuple[SpecialPoint, ...]
    message: str = eqx.field(static=True)

    @property
    def stable(self):
        """Points whose second variation is positive definite."""
        return self.instability_index == 0

    def points(self, kind: str) -> tuple[SpecialPoint, ...]:
        """The special points of one kind (`"fold"` or `"branch point"`)."""
        if kind not in SPECIAL_KINDS:
            raise ValueError(f"Branch.points: kind must be one of {SPECIAL_KINDS}, got {kind!r}")
        return tuple(p for p in self.special if p.kind == kind)


class _Problem(eqx.Module):
    """The traced data of a branch's equations at fixed reference nodes."""

    rod: object
    length: Array
    start: Clamped
    ref_x: Array
    ref_frame: Array
    scale: Array  # the parameter's scale Lambda


def _args(problem: _Problem, end_at, lam, options: BoundaryValueOptions) -> ShootingArgs:
    rod, length = problem.rod, problem.length
    scales = residual_scales(rod, length)
    ode_tol = ode_tolerances(options, problem.length.dtype)
    end = end_at(lam).condition()
    return ShootingArgs(rod, length, problem.start, end, problem.ref_x, problem.ref_frame, scales, ode_tol)


def _tangent(J, previous):
    """The unit null vector of `J` `(6k, 6k + 1)` with a positive component along
    `previous`, and the sign of the determinant of the bordered Jacobian."""
    bordered = jnp.concatenate([J, previous[None]], 0)
    rhs = jnp.zeros(J.shape[1], J.dtype).at[-1].set(1.0)
    t = jnp.linalg.solve(bordered, rhs)
    t = t / jnp.linalg.norm(t)
    sign, _ = jnp.linalg.slogdet(jnp.concatenate([J, t[None]], 0))
    return t, sign


@jit(static_argnames="end_at", trace_cache=True)
def _point(z_pred, row, target, previous, problem, end_at, options):
    """Correct `z_pred` onto the branch under the constraint `row . z = target`, then the
    tangent (oriented by `previous`), the determinant's sign, the nodes and the end
    condition there (its stability is `solve_boundary_value`'s program of its own,
    `stability_of_nodes`, compiled once for both).  Never raises: read `converged`."""
    tolerance = options.atol

    def evaluate(z):
        """The equations, their Jacobian and the pieces at `z`: the flows integrated once,
        their derivatives as Jacobi fields (`linearised_equations`)."""
        args_at = lambda z: _args(problem, end_at, z[-1] * problem.scale, options)  # noqa: E731
        args = args_at(z)
        g, (pieces, flows, _) = residual_and_flows(z[:-1], args, options)
        equations = linearised_equations(z[:-1], args, options, flows, JACOBIAN_STEPS_PER_RADIAN)
        J = jax.jacfwd(lambda v: equations(v[:-1], args_at(v))[0])(z)
        return g, J, pieces

    def unfinished(state):
        z, i, size = state[0], state[1], state[2]
        return (i < CORRECTOR_STEPS) & (size > tolerance) & jnp.all(jnp.isfinite(z))

    def newton(state):
        z, i = state[0], state[1]
        g, J, pieces = evaluate(z)
        b = jnp.concatenate([g, (row @ z - target)[None]])
        # A point already on the branch takes no step: at a branch point the bordered
        # Jacobian is singular whatever the row (the kernel of G_z is two-dimensional).
        done = jnp.max(jnp.abs(b)) <= 0.1 * tolerance
        A = jnp.concatenate([J, row[None]], 0)
        dz = jnp.where(done, 0.0, jnp.linalg.solve(jnp.where(done, jnp.eye(z.size, dtype=z.dtype), A), b))
        size = jnp.where(done, 0.0, jnp.maximum(jnp.max(jnp.abs(g)), jnp.max(jnp.abs(dz))))
        return z - dz, i + 1, size, g, J, pieces

    # The Jacobian, residual and pieces returned are those of the last Newton iterate, before
    # its step: on convergence that step is below the tolerance.
    shapes = jax.eval_shape(evaluate, z_pred)
    state = (z_pred, jnp.asarray(0), jnp.asarray(jnp.inf, z_pred.dtype), *jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), shapes))
    z, steps, _, g, J, pieces = jax.lax.while_loop(unfinished, newton, state)
    (N, M0, xs, frames), ends = pieces
    args = _args(problem, end_at, z[-1] * problem.scale, options)
    residual = jnp.max(jnp.abs(g))
    converged = (steps > 0) & jnp.all(jnp.isfinite(z)) & jnp.isfinite(residual) & (residual <= 10 * tolerance) & jnp.all(jnp.isfinite(J))
    t, sign = _tangent(jnp.where(converged, J, 0.0), previous)
    return dict(
        z=z, converged=converged, steps=steps, tangent=t, sign=sign, force=N, moment0=M0, xs=xs, frames=frames,
        end_position=ends[0][-1], end_frame=ends[1][-1], end=args.end, jacobian=J,
    )


@jit(static_argnames="segments")
def _state_of(rod, length, force, moment0, parameter, segments: int):
    """The state of a branch at a solution: its start wrench in the units of the residual
    (`residual_scales`), the node corrections zero, the scaled parameter."""
    _, force_unit, moment_unit = residual_scales(rod, length)
    corrections = jnp.zeros(6 * (segments - 1), force.dtype)
    return jnp.concatenate([force / force_unit, moment0 / moment_unit, corrections, parameter[None]])


def _point_signature(rod, length, start, end_at, options, k: int):
    shapes = leaf_shapes((rod, length, start, options))
    return jax.tree.structure((rod, start, options)), shapes, committed_placement((rod, length, start)), end_at, k, float_dtype()


@once_per_signature(_point_signature)
def _compile_point_ahead(rod, length, start, end_at, options, k: int) -> bool:
    """At the first branch of its kind: start compiling the corrector step (`_point`, from
    the specs of its state and reference nodes) and the points' stability test
    (`stability_of_nodes`, from the corrector's output structure), each on a thread of its
    own (`compile_ahead`), while the first point's guess is made.  With the loop's
    bookkeeping in NumPy, the README's Euler column (`Rod(1, 2, 0.8)`, P from 1 to 12, 39
    points; fresh processes on 2 cores, alternating): first call 11.4-11.6 -> 7.2-7.4 s
    (the corrector beside the first solve), later calls unchanged (best of seven 123-125
    against 124-134 ms), the same branch."""
    placement = committed_placement((rod, length, start))
    spec = lambda *shape: jax.ShapeDtypeStruct(shape, float_dtype(), sharding=placement)  # noqa: E731
    state = spec(6 * k + 1)
    problem = _Problem(rod, spec(), start, spec(k - 1, 3), spec(k - 1, 3, 3), spec())
    record = compile_ahead(_point, state, state, spec(), state, problem, end_at, options)
    if record is not None and options.stability_pieces > 0:
        compile_ahead(
            stability_of_nodes, rod, problem.length, record["end"], record["force"], record["moment0"], record["xs"],
            record["frames"], record["end_frame"], RESULTS.successful, options,
        )
    return record is not None


def _bifurcating_direction(J, tangent):
    """The unit vector of the two-dimensional kernel of `J` at a branch point orthogonal to
    the branch's `tangent`: from the two smallest right singular vectors (NumPy, on the
    host, as the rest of the branch's bookkeeping)."""
    _, _, vh = np.linalg.svd(np.asarray(J), full_matrices=True)
    candidates = vh[-2:]
    orthogonal = candidates - (candidates @ tangent)[:, None] * tangent[None]
    best = orthogonal[np.argmax(np.linalg.norm(orthogonal, axis=1))]
    return best / np.linalg.norm(best)


def follow_branch(
    rod,
    length,
    end,
    parameter,
    *,
    start: Clamped | None = None,
    guess=None,
    switch: SpecialPoint | None = None,
    direction: float = 1.0,
    step: float = 0.05,
    max_step: float = 0.25,
    min_step: float = 1e-6,
    max_points: int = 200,
    options: BoundaryValueOptions | None = None,
    segments: int | None = None,
    stability_pieces: int | None = None,
) -> Branch:
    """Follow a branch of equilibria of a finite rod as a load parameter varies, through
    folds, reporting folds and branch points (module docstring).

    **Arguments**

    - `rod`, `length`, `start`: as `solve_boundary_value`.
    - `end`: a function of the load parameter returning the end condition (`Clamped`,
      `Loaded`, `Tweezer`), traceable by JAX, e.g. `lambda P: helixrod.Loaded(force=jnp.stack([0.0, 0.0, -P]))`.
    - `parameter`: `(first, last)`: the branch starts at `first` heading towards `last`, and
      ends where it leaves the interval between them (the last point exactly at its end),
      after `max_points`, or where the step falls below `min_step`.  The first point is the
      equilibrium that `solve_boundary_value` finds with `guess=`; from the default guess,
      first Newton's corrector from it, kept where it converges to a stable equilibrium
      (as `solve_boundary_value` keeps its solve from that guess), which spares the first
      call the solve's programs.
    - `switch`: a branch point (`SpecialPoint`) of an earlier branch: start there instead and
      follow the bifurcating branch, in `direction` (+1 or -1: its two halves).
    - `step`, `max_step`, `min_step`: arclength steps in the scaled unknowns (forces in
      units of $\\bar K/\\ell^2$ and moments of $\\bar K/\\ell$, as the residual scales of
      `BoundaryValueOptions.atol`; the parameter in units of the width of the interval).
    - `options`, `segments`, `stability_pieces`: as `solve_boundary_value` (the stability of
      every point costs about a solve, and where these pieces do not resolve a point's
      wrench it is tested again on more, as there; `stability_pieces=0` turns it off).

    Returns a `Branch`.  Eager (a Python loop over compiled steps): one compilation per
    load and options; two `end` functions that trace to the same operations and constants
    are one load (`_compile.TracedFunction`), and with the compilation cache on a later
    process loads the compiled steps.

    **Example** (the post-buckled Euler column, no hand-made guess)

    ```python
    rod = helixrod.Rod(1.0, 1.5, 0.8)
    load = lambda P: helixrod.Loaded(force=jnp.stack([0.0, 0.0, -P]))
    straight = helixrod.follow_branch(rod, 1.0, load, (1.0, 4.0))
    bp = straight.points("branch point")[0]          # P = pi^2/4 (K1's; K2's is at 1.5 pi^2/4)
    buckled = helixrod.follow_branch(rod, 1.0, load, (1.0, 4.0), switch=bp)
    ```
    """
    owner = "follow_branch"
    check_one_rod(rod, owner)
    if not callable(end):
        raise ValueError(f"{owner}: end must be a function of the load parameter returning an end condition")
    try:
        first, last = (float(finite_scalar(v, "parameter", owner)) for v in parameter)
    except TypeError:
        raise ValueError(f"{owner}: parameter must be a pair (first, last)") from None
    if first == last:
        raise ValueError(f"{owner}: parameter must be two different values, got {first} twice")
    if direction not in (1, -1, 1.0, -1.0):
        raise ValueError(f"{owner}: direction must be +1 or -1, got {direction!r}")
    for name, value in (("step", step), ("max_step", max_step), ("min_step", min_step)):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"{owner}: {name} must be positive, got {value!r}")
    max_points = check_integer(max_points, "max_points", owner, minimum=2)
    length = finite_scalar(length, "length", owner, positive=True)
    options = with_settings(options, segments=segments, stability_pieces=stability_pieces)
    if start is None:
        start = unloaded_clamp(rod)
    if not isinstance(start, Clamped):
        raise ValueError(f"{owner}: start must be Clamped, got {type(start).__name__}")
    start = as_start(start)
    probe = end(jnp.asarray(first, float_dtype()))
    if not isinstance(probe, AbstractEnd):
        raise ValueError(f"{owner}: end({first}) must return Clamped, Loaded or Tweezer, got {type(probe).__name__}")
    dtype = float_dtype()
    # Named by its trace: a new lambda of the same load finds the compiled corrector, and
    # the trace cache keeps it for a later process (its warm first call: `_point` traced
    # and lowered in ~1.6 s of the 2.6 s, measured on 2 cores).
    end_at = TracedFunction(end, jax.ShapeDtypeStruct((), dtype))
    scale = abs(last - first)
    lo, hi = min(first, last), max(first, last)
    k = options.segments

    def problem_at(xs, frames):
        # The nodes as host arrays: uncommitted, as the specs `_point` was compiled ahead
        # for (a solve's results are committed where the trace cache ran its program).
        return _Problem(rod, jnp.asarray(length, dtype), start, np.asarray(xs)[1:], np.asarray(frames)[1:], jnp.asarray(scale, dtype))

    # The loop's bookkeeping runs on the host, in NumPy, on each step's results: in jnp
    # each small operation was a program compiled at the first call (~80 of them, ~1.4 s).
    def solve_point(z_pred, row, target, previous, problem, with_stability=True):
        record = _point(z_pred, row, np.asarray(target, dtype), previous, problem, end_at, options)
        # What the loop reads, on the host; the rest stays put until a point is kept.
        host = jax.device_get({name: record[name] for name in ("z", "tangent", "sign", "steps", "converged")})
        index, margin, rotation = np.asarray(-1, np.int32), np.asarray(np.nan, dtype), np.asarray(np.nan, dtype)
        if with_stability and options.stability_pieces > 0 and host["converged"]:
            inputs = (record["force"], record["moment0"], record["xs"], record["frames"], record["end_frame"], RESULTS.successful)
            tested = stability_of_nodes(rod, problem.length, record["end"], *inputs, options)
            # More pieces where these do not resolve the wrench, as `solve_boundary_value` takes.
            tested, _ = resolved_test(rod, problem.length, record["end"], inputs, tested, options, record["end_position"], tested[4])
            index, margin, rotation = jax.device_get((tested[0], tested[1], tested[3]))
        return dict(record, **host, index=index, margin=margin, rotation=rotation)

    def rebased(record, problem):
        if k == 1:
            return record, problem
        problem = problem_at(record["xs"], record["frames"])
        z = record["z"].copy()
        z[6:-1] = 0.0
        return dict(record, z=z), problem

    def first_point(force, moment0, problem):
        """The corrected point at `first` from a start wrench, its node corrections zero."""
        z = np.asarray(_state_of(rod, jnp.asarray(length, dtype), force, moment0, jnp.asarray(first / scale, dtype), k))
        heading = np.zeros_like(z)
        heading[-1] = np.sign(last - first)
        return solve_point(z, heading, heading @ z, heading, problem), heading

    if switch is not None:
        if not isinstance(switch, SpecialPoint) or switch.kind != "branch point":
            raise ValueError(f"{owner}: switch must be a branch point of a Branch (Branch.points('branch point'))")
        if switch.state.shape[0] != 6 * k + 1:
            raise ValueError(f"{owner}: switch comes from a branch of another number of segments")

    _compile_point_ahead(rod, jnp.asarray(length, dtype), start, end_at, options, k)
    if switch is not None:
        z, heading = np.array(switch.state, dtype), float(direction) * np.asarray(switch.direction, dtype)
        problem = problem_at(switch.node_position, switch.node_frame)
        problem = eqx.tree_at(lambda p: p.scale, problem, jnp.asarray(scale, dtype))
        # The state is relative to the nodes of the branch it was found on; restart from its own.
        z[6:-1] = 0.0
        z[-1] = float(switch.parameter) / scale
        here = solve_point(z, heading, heading @ z, heading, problem)
    else:
        here = None
        if guess is None and options.continuation == 0:
            # Newton's corrector from the default guess (exact for a Loaded end about a fixed
            # point), kept where it lands on a stable equilibrium, as `solve_boundary_value`
            # keeps its solve from that guess: the first call compiles no solve of its own.
            warm = as_warm_start(rod, length, start, type(probe).condition(probe), None, options, "helix")  # as the solve calls it
            problem = problem_at(warm.node_position, warm.node_frame)
            trial, heading = first_point(warm.force, warm.moment0, problem)
            if bool(trial["converged"]) and (int(trial["index"]) == 0 or options.stability_pieces == 0):
                here, problem = rebased(trial, problem)
        if here is None:
            sol = solve_boundary_value(rod, length, start=start, end=probe, guess=guess, options=options)
            if sol.segments != k:
                raise ValueError(f"{owner}: the first solve used {sol.segments} segments; give segments=")
            problem = problem_at(sol.node_position, sol.node_frame)
            here, heading = first_point(sol.force, sol.moment0, problem)
    if not bool(here["converged"]):
        # An equilibrium that is not isolated: the bordered Jacobian is singular (a second null
        # direction), so no branch through it is a curve the corrector can follow.
        J = np.asarray(here["jacobian"])
        if np.all(np.isfinite(J)):
            singular = np.linalg.svd(np.concatenate([J, np.asarray(heading)[None]], 0), compute_uv=False)
            if singular[-1] <= NOT_ISOLATED * singular[0]:
                raise ValueError(
                    f"{owner}: the equilibria at the first point are not isolated (the branch's equations have a "
                    "second null direction there: e.g. a straight inextensible rod between clamps exactly its length "
                    "apart, whose axial force is undetermined); bring the ends closer or load the end (Loaded, Tweezer)"
                )
        raise ValueError(f"{owner}: Newton's corrector did not converge at the first point (residual above tolerance)")
    if switch is not None:
        # At the branch point the tangent and the determinant's sign are not defined: leave
        # along the bifurcating direction, and compare signs from the next point on.
        here = dict(here, tangent=heading, sign=np.zeros((), dtype))
    records = [here]
    arclength = [0.0]
    special = []
    message = f"reached max_points={max_points}"
    ds = float(step)
    inside = lambda lam: lo - 1e-12 * scale <= lam <= hi + 1e-12 * scale  # noqa: E731

    def corrected(record, problem, distance, with_stability=True):
        z_pred = record["z"] + distance * record["tangent"]
        t = record["tangent"]
        return solve_point(z_pred, t, t @ z_pred, t, problem, with_stability)

    def locate(record, problem, distance, test):
        a, b = 0.0, distance
        best = None
        for _ in range(LOCATE_BISECTIONS):
            mid = 0.5 * (a + b)
            trial = corrected(record, problem, mid, with_stability=False)  # a special point holds no stability
            if not bool(trial["converged"]):
                b = mid
                continue
            best = trial
            if test(trial) == test(record):
                a = mid
            else:
                b = mid
        return best

    while len(records) < max_points:
        current = records[-1]
        new = corrected(current, problem, ds)
        turn = float(new["tangent"] @ current["tangent"])
        if not bool(new["converged"]) or turn < SMALLEST_COSINE:
            ds *= 0.5
            if ds < min_step:
                message = f"step below min_step={min_step} at parameter {float(current['z'][-1]) * scale:.6g}"
                break
            continue
        lam = float(new["z"][-1]) * scale
        ending = not inside(lam)
        if ending:
            bound = hi if lam > hi else lo
            secant = new["z"] - current["z"]
            fraction = (bound / scale - float(current["z"][-1])) / float(secant[-1])
            row = np.zeros_like(secant)
            row[-1] = 1.0
            new = solve_point(current["z"] + fraction * secant, row, bound / scale, current["tangent"], problem)
            if not bool(new["converged"]):
                message = f"could not land on the end of the interval at {bound:.6g}"
                break
        fold = np.sign(float(new["tangent"][-1])) * np.sign(float(current["tangent"][-1])) < 0
        crossed = float(new["sign"]) * float(current["sign"]) < 0
        # Each located by its test function (module docstring), not by the stability test:
        # on the Euler column of `benchmarks/bench_first_calls.py` the margin's zero (12
        # steps a radian) lies 1.2e-8 off the first branch point, the index's threshold
        # (`NEUTRAL`) 3.3e-6 off the second; the test functions 2.8e-9 and 7.7e-10.
        step_taken = float(np.linalg.norm(new["z"] - current["z"]))
        for kind, found in (("fold", fold), ("branch point", crossed and not fold)):
            if not found:
                continue
            if kind == "fold":
                point = locate(current, problem, step_taken, lambda r: np.sign(float(r["tangent"][-1])))
            else:
                point = locate(current, problem, step_taken, lambda r: np.sign(float(r["sign"])))
            if point is None:
                continue
            direction_out = (
                _bifurcating_direction(point["jacobian"], point["tangent"]) if kind == "branch point" else np.zeros_like(point["z"])
            )
            special.append(SpecialPoint(
                kind=kind, parameter=jnp.asarray(point["z"][-1] * scale), after=len(records) - 1,
                force=jnp.asarray(point["force"]), moment0=jnp.asarray(point["moment0"]), state=jnp.asarray(point["z"]),
                direction=jnp.asarray(direction_out), node_position=jnp.asarray(point["xs"]), node_frame=jnp.asarray(point["frames"]),
            ))
        new, problem = rebased(new, problem)
        records.append(new)
        arclength.append(arclength[-1] + step_taken)
        if ending:
            message = f"reached the end of the interval at {float(new['z'][-1]) * scale:.6g}"
            break
        if int(new["steps"]) <= 4:
            ds = min(1.5 * ds, max_step)

    stack = lambda name: np.stack([np.asarray(r[name]) for r in records])  # noqa: E731
    frames0 = np.asarray(start.frame)
    force, moment0 = stack("force"), stack("moment0")
    fields = dict(
        parameter=stack("z")[:, -1] * scale,
        arclength=np.asarray(arclength, dtype),
        force=force,
        moment0=moment0,
        n0=force @ frames0,
        m0=moment0 @ frames0,
        end_position=stack("end_position"),
        end_frame=stack("end_frame"),
        node_position=stack("xs"),
        node_frame=stack("frames"),
        instability_index=stack("index"),
        stability_margin=stack("margin"),
        rotation=stack("rotation"),
    )
    return Branch(**{name: jnp.asarray(value) for name, value in fields.items()}, special=tuple(special), message=message)
