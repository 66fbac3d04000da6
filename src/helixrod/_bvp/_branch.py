"""Branches of equilibria of a finite rod along a load parameter: pseudo-arclength
continuation that passes folds, detects branch points and switches onto the bifurcating
branch (the services of AUTO-07p and BifurcationKit that users of those rely on, for rods).

The unknowns are those of the shooting equations (`_shooting.py`, scaled: forces by
$\\bar K/\\ell^2$, moments by $\\bar K/\\ell$) and the load parameter $\\lambda$, scaled by the
width of the range asked for: $z = (y, \\lambda/\\Lambda)$, $G(z) = 0$ the $6k$ shooting
equations of the end condition `end(lambda)`.  From a point $z_j$ with unit tangent $t_j$
(the null vector of $G_z$, oriented along the branch) the predictor $z_j + \\Delta s\\,t_j$ is
corrected by Newton's method on $G(z) = 0$, $t_j\\cdot(z - z_j) = \\Delta s$ (Keller 1977), the
Jacobian exact (forward mode through the flows, at the ODE tolerance).  The step grows after
easy corrections and halves after failed ones.

Test functions (Seydel, *Practical Bifurcation and Stability Analysis*, 2010, sec. 5.3):

- a **fold** (limit point) where the parameter component of the tangent, $t_\\lambda$,
  changes sign: the branch turns back in $\\lambda$;
- a **branch point** where $\\det\\begin{pmatrix} G_z \\\\ t^T\\end{pmatrix}$ changes sign and
  $t_\\lambda$ does not: another branch crosses (a simple one; a double branch point, as of an
  isotropic rod's two bending planes, leaves the sign unchanged and is reported only by the
  jump of the stability index by two).

Each is located by bisection in the arclength between the two points that bracket it.  At a
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

from .._compile import filter_jit
from .._misc import check_integer, finite_scalar, float_dtype
from .._rod import check_one_rod
from ._bulk import length_scale, stiffness_scale
from ._ends import AbstractEnd, Clamped, unloaded_clamp
from ._options import BoundaryValueOptions, with_settings
from ._shooting import ShootingArgs, shooting_residual
from ._solve import ode_tolerances, solve_boundary_value
from ._stability import stability

#: Special points a branch reports.
SPECIAL_KINDS = ("fold", "branch point")

#: Bisection steps that locate a special point between two points of a branch.
LOCATE_BISECTIONS = 30

#: Newton steps of one corrector.
CORRECTOR_STEPS = 12

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
    `instability_index` (-1 where not defined), `stability_margin`; `special` the folds and
    branch points found, in order; `message` why the branch ended."""

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
    ell = length_scale(rod, length)
    k_scale = stiffness_scale(rod)
    scales = jnp.stack([ell, k_scale / ell**2, k_scale / ell])
    # The flows' Jacobian (`_flows`) is integrated at the ODE tolerance itself: it locates
    # folds and branch points.
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


@filter_jit
def _point(z_pred, row, target, previous, problem, end_at, options):
    """Correct `z_pred` onto the branch under the constraint `row . z = target`, then the
    tangent (oriented by `previous`), the determinant's sign, the nodes and the stability
    there.  Never raises: read `converged`."""
    tolerance = options.atol

    def evaluate(z):
        """The equations, their Jacobian and the pieces at `z`, from one forward-mode pass
        (the program holds one copy of the flows and their derivatives, not three)."""

        def equations(z):
            args = _args(problem, end_at, z[-1] * problem.scale, options)
            g, pieces = shooting_residual(z[:-1], args, options)
            return g, (g, pieces)

        J, (g, pieces) = jax.jacfwd(equations, has_aux=True)(z)
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
    if options.stability_pieces > 0:
        index, margin, _ = stability(problem.rod, problem.length, args.end, N, M0, xs, frames, options)
    else:
        index, margin = jnp.asarray(-1, jnp.int32), jnp.asarray(jnp.nan, z.dtype)
    return dict(
        z=z, converged=converged, steps=steps, tangent=t, sign=sign, force=N, moment0=M0, xs=xs, frames=frames,
        end_position=ends[0][-1], end_frame=ends[1][-1], index=index, margin=margin, jacobian=J,
    )


def _bifurcating_direction(J, tangent):
    """The unit vector of the two-dimensional kernel of `J` at a branch point orthogonal to
    the branch's `tangent`: from the two smallest right singular vectors."""
    _, _, vh = jnp.linalg.svd(J, full_matrices=True)
    candidates = vh[-2:]
    orthogonal = candidates - (candidates @ tangent)[:, None] * tangent[None]
    best = orthogonal[jnp.argmax(jnp.linalg.norm(orthogonal, axis=1))]
    return best / jnp.linalg.norm(best)


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
    - `parameter`: `(first, last)`: the branch starts at `first` (from `solve_boundary_value`
      with `guess=`) heading towards `last`, and ends where it leaves the interval between
      them (the last point exactly at its end), after `max_points`, or where the step falls
      below `min_step`.
    - `switch`: a branch point (`SpecialPoint`) of an earlier branch: start there instead and
      follow the bifurcating branch, in `direction` (+1 or -1: its two halves).
    - `step`, `max_step`, `min_step`: arclength steps in the scaled unknowns (forces in
      units of $\\bar K/\\ell^2$ and moments of $\\bar K/\\ell$, as the residual scales of
      `BoundaryValueOptions.atol`; the parameter in units of the width of the interval).
    - `options`, `segments`, `stability_pieces`: as `solve_boundary_value` (the stability of
      every point costs about a solve; `stability_pieces=0` turns it off).

    Returns a `Branch`.  Eager (a Python loop over compiled steps): one compilation per
    `end` function and options.

    **Example** (the post-buckled Euler column, no hand-made guess)

    ```python
    rod = helixrod.Rod(1.0, 1.5, 0.8)
    load = lambda P: helixrod.Loaded(force=jnp.stack([0.0, 0.0, -P]))
    straight = helixrod.follow_branch(rod, 1.0, load, (1.0, 4.0))
    (bp,) = straight.points("branch point")          # P = pi^2/4
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
    probe = end(jnp.asarray(first, float_dtype()))
    if not isinstance(probe, AbstractEnd):
        raise ValueError(f"{owner}: end({first}) must return Clamped, Loaded or Tweezer, got {type(probe).__name__}")
    dtype = float_dtype()
    scale = abs(last - first)
    lo, hi = min(first, last), max(first, last)
    k = options.segments

    def problem_at(xs, frames):
        return _Problem(rod, jnp.asarray(length, dtype), start, xs[1:], frames[1:], jnp.asarray(scale, dtype))

    if switch is None:
        sol = solve_boundary_value(rod, length, start=start, end=probe, guess=guess, options=options)
        if sol.segments != k:
            raise ValueError(f"{owner}: the first solve used {sol.segments} segments; give segments=")
        args = _args(problem_at(sol.node_position, sol.node_frame), end, jnp.asarray(first, dtype), options)
        z = jnp.concatenate([sol.force / args.scales[1], sol.moment0 / args.scales[2], jnp.zeros(6 * (k - 1)), jnp.asarray([first / scale])])
        heading = jnp.zeros_like(z).at[-1].set(np.sign(last - first))
        problem = problem_at(sol.node_position, sol.node_frame)
    else:
        if not isinstance(switch, SpecialPoint) or switch.kind != "branch point":
            raise ValueError(f"{owner}: switch must be a branch point of a Branch (Branch.points('branch point'))")
        if switch.state.shape[0] != 6 * k + 1:
            raise ValueError(f"{owner}: switch comes from a branch of another number of segments")
        z, heading = switch.state, float(direction) * switch.direction
        problem = problem_at(switch.node_position, switch.node_frame)
        problem = eqx.tree_at(lambda p: p.scale, problem, jnp.asarray(scale, dtype))
        # The state is relative to the nodes of the branch it was found on; restart from its own.
        z = z.at[6:-1].set(0.0).at[-1].set(float(switch.parameter) / scale)

    here = _point(z, heading, heading @ z, heading, problem, end, options)
    if not bool(here["converged"]):
        raise ValueError(f"{owner}: the first point is not an equilibrium (residual above tolerance)")
    if switch is not None:
        # At the branch point the tangent and the determinant's sign are not defined: leave
        # along the bifurcating direction, and compare signs from the next point on.
        here = dict(here, tangent=heading, sign=jnp.zeros(()))
    records = [here]
    arclength = [0.0]
    special = []
    message = f"reached max_points={max_points}"
    ds = float(step)
    inside = lambda lam: lo - 1e-12 * scale <= lam <= hi + 1e-12 * scale  # noqa: E731

    def rebased(record, problem):
        if k == 1:
            return record, problem
        problem = problem_at(record["xs"], record["frames"])
        return dict(record, z=record["z"].at[6:-1].set(0.0)), problem

    def corrected(record, problem, distance):
        z_pred = record["z"] + distance * record["tangent"]
        t = record["tangent"]
        return _point(z_pred, t, t @ z_pred, t, problem, end, options)

    def locate(record, problem, distance, test):
        a, b = 0.0, distance
        best = None
        for _ in range(LOCATE_BISECTIONS):
            mid = 0.5 * (a + b)
            trial = corrected(record, problem, mid)
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
            row = jnp.zeros_like(secant).at[-1].set(1.0)
            target = jnp.asarray(bound / scale, secant.dtype)  # an array: a Python float would be static (a new compilation)
            new = _point(current["z"] + fraction * secant, row, target, current["tangent"], problem, end, options)
            if not bool(new["converged"]):
                message = f"could not land on the end of the interval at {bound:.6g}"
                break
        fold = np.sign(float(new["tangent"][-1])) * np.sign(float(current["tangent"][-1])) < 0
        crossed = float(new["sign"]) * float(current["sign"]) < 0
        # Located by the stability index where it changes (the stability test integrates the
        # variations in equal steps, 1e-8 accurate; the adaptive Jacobian of the test
        # functions is not, on straight pieces), else by the test function.
        by_index = int(new["index"]) != int(current["index"]) and min(int(new["index"]), int(current["index"])) >= 0
        step_taken = float(jnp.linalg.norm(new["z"] - current["z"]))
        for kind, found in (("fold", fold), ("branch point", crossed and not fold)):
            if not found:
                continue
            if by_index and min(int(new["index"]), int(current["index"])) == 0:
                # The margin's zero, not the index's threshold (`NEUTRAL`) below it.
                point = locate(current, problem, step_taken, lambda r: bool(float(r["margin"]) > 0))
            elif by_index:
                point = locate(current, problem, step_taken, lambda r: int(r["index"]))
            elif kind == "fold":
                point = locate(current, problem, step_taken, lambda r: np.sign(float(r["tangent"][-1])))
            else:
                point = locate(current, problem, step_taken, lambda r: np.sign(float(r["sign"])))
            if point is None:
                continue
            direction_out = (
                _bifurcating_direction(point["jacobian"], point["tangent"]) if kind == "branch point" else jnp.zeros_like(point["z"])
            )
            special.append(SpecialPoint(
                kind=kind, parameter=point["z"][-1] * scale, after=len(records) - 1, force=point["force"],
                moment0=point["moment0"], state=point["z"], direction=direction_out, node_position=point["xs"],
                node_frame=point["frames"],
            ))
        new, problem = rebased(new, problem)
        records.append(new)
        arclength.append(arclength[-1] + step_taken)
        if ending:
            message = f"reached the end of the interval at {float(new['z'][-1]) * scale:.6g}"
            break
        if int(new["steps"]) <= 4:
            ds = min(1.5 * ds, max_step)

    stack = lambda name: jnp.stack([r[name] for r in records])  # noqa: E731
    frames0 = start.frame
    force, moment0 = stack("force"), stack("moment0")
    return Branch(
        parameter=stack("z")[:, -1] * scale,
        arclength=jnp.asarray(arclength, dtype),
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
        special=tuple(special),
        message=message,
    )
