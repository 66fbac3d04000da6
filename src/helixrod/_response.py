"""End-response curves of finite springs and tweezer filaments, against the bulk helix.

A rod of length $L$ in the canonical placement (`axial_ends`) is loaded along its axis by two
controls, one held fixed and one swept: force-extension at fixed axial moment (a hooked
spring) or at fixed end rotation (a magnetic tweezer), and rotation curves at fixed force
(tweezer: torque and extension against turns) or at fixed extension (a spring twisted
between grips).  Each point is a `solve_boundary_value` solve; by default the points are
solved in order, each warm-started from the previous one (continuation), inside one
compiled `lax.scan`; `mode="independent"` solves them in parallel (`vmap`), each from the
bulk-helix guess -- fine where that guess is good (a load through the axis is an
initial-value problem and needs no continuation).

Observables (`_axial` docstring): axial force $F = N\\cdot e_z$, axial moment $M$ (about the
axis), extension $h = (x(L) - x(0))\\cdot e_z$, end rotation $\\Theta$: the unloaded
$\\Theta_0 = L|\\hat u|$ plus the twist about $e_z$ of $D(L)D_0(L)^T$ (the end frame relative
to the unloaded end frame), its whole turns counted by continuity along the curve (from the
bulk prediction at the first point).  The bulk (uniform-helix) prediction at the same
controls follows its own branch by continuation from the unloaded helix; the difference is
the end effect of the clamp, which does not vanish at a clamp but whose share of the
totals falls like $1/L$ (tested in `tests/test_boundary.py`).
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._axial import BulkHelix, bulk_helix_indexed, no_gradient, twist_angle, unloaded_observables, unloaded_state, unwrap_near
from ._boundary import (
    _CLAMPED,
    _LOADED,
    _TWEEZER,
    METHODS,
    BoundaryValueSolution,
    Clamped,
    _axial_guess,
    _free_nodes,
    _Options,
    _solve,
    axial_end_data,
)
from ._kirchhoff import check_one_rod
from ._lie import CommutatorFreeRK4

# Index of the two controls of each kind in (force, moment, extension, rotation).
_CONTROL_INDEX = {_CLAMPED: (2, 3), _LOADED: (0, 1), _TWEEZER: (0, 3)}


class ResponseCurve(eqx.Module):
    """A response curve of a finite rod and the bulk (uniform-helix) prediction.

    `swept`, `held`: names of the swept and the fixed control; `length` $L$.  Per point
    (shape `(n,)`): `force`, `moment`, `extension`, `rotation` of the finite rod (controls
    as prescribed, responses as solved; module docstring for the conventions) and
    `bulk_force`, `bulk_moment`, `bulk_extension`, `bulk_rotation` of the uniform helix with
    the same two controls (extension and rotation totals over $L$); `ok` (the solve
    converged), `bulk_ok`, `residual`, `num_steps`; `solutions` the `BoundaryValueSolution`
    of every point (batched, end state only).
    """

    swept: str = eqx.field(static=True)
    held: str = eqx.field(static=True)
    length: Float[Array, ""]
    force: Float[Array, " n"]
    moment: Float[Array, " n"]
    extension: Float[Array, " n"]
    rotation: Float[Array, " n"]
    bulk_force: Float[Array, " n"]
    bulk_moment: Float[Array, " n"]
    bulk_extension: Float[Array, " n"]
    bulk_rotation: Float[Array, " n"]
    ok: Bool[Array, " n"]
    bulk_ok: Bool[Array, " n"]
    residual: Float[Array, " n"]
    num_steps: Int[Array, " n"]
    solutions: BoundaryValueSolution

    def end_effect(self, name: str) -> Array:
        """Finite minus bulk value of the observable `name` (e.g. `"extension"`)."""
        if name not in ("force", "moment", "extension", "rotation"):
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


def _pseudo_solution(rod, length, start, end, options: _Options) -> BoundaryValueSolution:
    """The default guess of the first point as a warm-start `BoundaryValueSolution`."""
    k = options.segments
    N, M0, twist, stretch = _axial_guess(rod, length, start, end, options.guess_kind)
    xs, frames = _free_nodes(rod, length, start, k, twist, stretch)
    nan3, nan33 = jnp.full((1, 3), jnp.nan), jnp.full((1, 3, 3), jnp.nan)
    zero = jnp.zeros(())
    return BoundaryValueSolution(
        s=length[None], x=nan3, frame=nan33, n=nan3, m=nan3, n0=N * jnp.nan, m0=N * jnp.nan,
        force=N, moment0=M0, end_position=xs[k], end_frame=frames[k], end_force=N, end_moment=N * jnp.nan,
        node_position=xs[:k], node_frame=frames[:k], residual=zero, result=optx.RESULTS.successful,
        num_steps=jnp.zeros((), jnp.int32), valid_input=jnp.asarray(True), tolerance=zero,
    )


@eqx.filter_jit
def _curve(rod, length, kind, values, tolerances, options: _Options, mode: str, hints=None):
    """Solve every point of a curve; `values` `(n, 4)` = (F, M, h, Theta) per point.
    `hints` `(n,)`: rotations near which to count whole turns (independent mode; default
    the bulk rotation)."""
    start = Clamped(*unloaded_state(no_gradient(rod), 0.0))
    start = jax.tree.map(jnp.asarray, start)
    index = jnp.asarray(
        jnp.where(kind == _LOADED, jnp.array(_CONTROL_INDEX[_LOADED]),
                  jnp.where(kind == _TWEEZER, jnp.array(_CONTROL_INDEX[_TWEEZER]), jnp.array(_CONTROL_INDEX[_CLAMPED])))
    )
    _, theta0 = unloaded_observables(rod, length)
    unloaded = (jnp.asarray(rod.uhat), jnp.zeros(()), jnp.zeros(()))

    def observe(sol, bulk, v, hint):
        hint = jnp.where(kind == _LOADED, hint, v[3])
        obs = axial_observables(rod, length, sol, hint)
        obs = jnp.where(sol.ok, obs, jnp.nan)
        bulk_obs = jnp.stack([bulk.force, bulk.moment, bulk.extension, bulk.rotation])
        return obs, jnp.where(bulk.ok, bulk_obs, jnp.nan)

    if mode == "independent":

        def one(v, hint):
            end = axial_end_data(rod, length, kind, v)
            sol = _solve(rod, length, start, end, None, None, tolerances, options)
            if hint is None:
                bulk = bulk_helix_indexed(rod, length, index, v, unloaded)
                hint = jnp.where(bulk.ok, bulk.rotation, theta0)
            else:  # turns counted from the hints: no bulk prediction needed (fits)
                nan = jnp.full((), jnp.nan, values.dtype)
                bulk = BulkHelix(u=jnp.full(3, jnp.nan, values.dtype), mu1=nan, mu2=nan, force=nan, moment=nan,
                                 extension=nan, rotation=nan, ok=jnp.asarray(False))
            obs, bulk_obs = observe(sol, bulk, v, hint)
            return obs, bulk_obs, sol, bulk.ok

        obs, bulk_obs, sols, bulk_ok = jax.vmap(one)(values, hints)
    else:
        first_end = axial_end_data(rod, length, kind, values[0])
        guess0 = no_gradient(_pseudo_solution(rod, length, start, first_end, options))
        bulk0 = bulk_helix_indexed(rod, length, index, values[0], unloaded)
        hint0 = jnp.where(bulk0.ok, bulk0.rotation, theta0)

        def step(carry, v):
            guess, bulk_guess, hint = carry
            end = axial_end_data(rod, length, kind, v)
            sol = _solve(rod, length, start, end, guess, None, tolerances, options)
            bulk = bulk_helix_indexed(rod, length, index, v, bulk_guess)
            obs, bulk_obs = observe(sol, bulk, v, hint)
            # A failed point does not spoil the warm start of the next one.
            keep = lambda new, old, ok: jax.tree.map(lambda a, b: jnp.where(ok, a, b), new, old)  # noqa: E731
            guess = keep(no_gradient(sol), guess, sol.ok)
            bulk_guess = keep(no_gradient((bulk.u, bulk.mu1, bulk.mu2)), bulk_guess, bulk.ok)
            hint = jnp.where(sol.ok, obs[3], hint)
            return (guess, bulk_guess, hint), (obs, bulk_obs, sol, bulk.ok)

        _, (obs, bulk_obs, sols, bulk_ok) = jax.lax.scan(step, (guess0, unloaded, hint0), values)
    return obs, bulk_obs, sols, bulk_ok


def _response(rod, length, kind, values, swept, held, *, segments, mode, method, rtol, atol, ode_rtol, ode_atol, max_steps, adjoint, name):
    if mode not in ("continuation", "independent"):
        raise ValueError(f"{name}: mode must be 'continuation' or 'independent', got {mode!r}")
    if method not in METHODS:
        raise ValueError(f"{name}: method must be one of {METHODS}, got {method!r}")
    if isinstance(segments, bool) or not isinstance(segments, (int, np.integer)) or segments < 1:
        raise ValueError(f"{name}: segments must be an integer >= 1, got {segments!r}")
    check_one_rod(rod, name)
    dtype = jnp.result_type(float)
    length = jnp.asarray(length, dtype)
    if length.shape != ():
        raise ValueError(f"{name}: length must be a scalar, got shape {length.shape}")
    if not isinstance(length, jax.core.Tracer) and not (np.isfinite(float(length)) and float(length) > 0):
        raise ValueError(f"{name}: length must be finite and > 0, got {float(length)}")
    adjoint = diffrax.ForwardMode() if adjoint is None else adjoint
    options = _Options(
        segments=int(segments),
        solver=CommutatorFreeRK4(),
        max_ode_steps=16_384,
        adjoint=adjoint,
        method=method,
        max_steps=int(max_steps),
        continuation=0,
        guess_kind="helix",
    )
    tolerances = jnp.asarray([rtol, atol, ode_rtol, ode_atol], dtype)
    obs, bulk_obs, sols, bulk_ok = _curve(rod, length, jnp.asarray(kind, jnp.int32), values, tolerances, options, mode)
    return ResponseCurve(
        swept=swept,
        held=held,
        length=length,
        force=obs[:, 0],
        moment=obs[:, 1],
        extension=obs[:, 2],
        rotation=obs[:, 3],
        bulk_force=bulk_obs[:, 0],
        bulk_moment=bulk_obs[:, 1],
        bulk_extension=bulk_obs[:, 2],
        bulk_rotation=bulk_obs[:, 3],
        ok=sols.ok,
        bulk_ok=bulk_ok,
        residual=sols.residual,
        num_steps=sols.num_steps,
        solutions=sols,
    )


def _sweep_values(values, name, what):
    dtype = jnp.result_type(float)
    values = jnp.asarray(values, dtype)
    if values.ndim != 1 or values.shape[0] < 1:
        raise ValueError(f"{name}: {what} must be a non-empty 1-d array, got shape {values.shape}")
    if not isinstance(values, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(values))):
        raise ValueError(f"{name}: {what} must be finite")
    return values


def _held(value, name, what):
    value = jnp.asarray(value, jnp.result_type(float))
    if value.shape != ():
        raise ValueError(f"{name}: {what} must be a scalar, got shape {value.shape}")
    if not isinstance(value, jax.core.Tracer) and not np.isfinite(float(value)):
        raise ValueError(f"{name}: {what} must be finite, got {float(value)}")
    return value


def force_extension(
    rod,
    length: ArrayLike,
    forces: ArrayLike,
    *,
    moment: ArrayLike | None = None,
    rotation: ArrayLike | None = None,
    segments: int = 1,
    mode: str = "continuation",
    method: str = "levenberg-marquardt",
    rtol: float = 1e-10,
    atol: float = 1e-10,
    ode_rtol: float = 1e-10,
    ode_atol: float = 1e-10,
    max_steps: int = 64,
    adjoint: diffrax.AbstractAdjoint | None = None,
) -> ResponseCurve:
    """Force-extension curve of a finite rod of length `length`, axial `forces` `(n,)`.

    Held fixed: the axial `moment` (default 0: a spring loaded through hooks on its axis,
    free to turn; a `Loaded` end about the axis) or the end `rotation` $\\Theta$ (total, as
    `axial_ends`; a magnetic tweezer, `Tweezer` end).  Returns a `ResponseCurve` with the
    extension (and the moment or rotation) of the finite rod and of the bulk helix.

    `mode`: `"continuation"` (default; in order, each solve warm-started from the
    previous -- sort `forces` from small to large) or `"independent"` (vmapped solves from
    the bulk guess).  `segments`, `method`, tolerances, `max_steps`, `adjoint`: as
    `solve_boundary_value`.  jit/vmap safe (e.g. `jax.vmap` over lengths); unconverged
    points have `ok = False` and NaN observables.

    **Example**

    ```python
    rod = helixrod.Rod(1.0, 1.0, 0.77, uhat=(0.0, 1.0, 0.3))
    curve = helixrod.force_extension(rod, 60.0, jnp.linspace(0.0, 0.05, 50))
    curve.extension, curve.bulk_extension
    ```
    """
    name = "force_extension"
    if moment is not None and rotation is not None:
        raise ValueError(f"{name}: give moment= or rotation=, not both")
    forces = _sweep_values(forces, name, "forces")
    n = forces.shape[0]
    zero = jnp.zeros(n, forces.dtype)
    if rotation is None:
        held = _held(0.0 if moment is None else moment, name, "moment")
        values = jnp.stack([forces, zero + held, zero, zero], -1)
        kind, held_name = _LOADED, "moment"
    else:
        held = _held(rotation, name, "rotation")
        values = jnp.stack([forces, zero, zero, zero + held], -1)
        kind, held_name = _TWEEZER, "rotation"
    return _response(
        rod, length, kind, values, "force", held_name, segments=segments, mode=mode, method=method, rtol=rtol,
        atol=atol, ode_rtol=ode_rtol, ode_atol=ode_atol, max_steps=max_steps, adjoint=adjoint, name=name,
    )


def rotation_response(
    rod,
    length: ArrayLike,
    rotations: ArrayLike,
    *,
    force: ArrayLike | None = None,
    extension: ArrayLike | None = None,
    segments: int = 1,
    mode: str = "continuation",
    method: str = "levenberg-marquardt",
    rtol: float = 1e-10,
    atol: float = 1e-10,
    ode_rtol: float = 1e-10,
    ode_atol: float = 1e-10,
    max_steps: int = 64,
    adjoint: diffrax.AbstractAdjoint | None = None,
) -> ResponseCurve:
    """Torque (and extension or force) against the end rotation of a finite rod.

    `rotations` `(n,)`: total end rotations $\\Theta$ about the axis (as `axial_ends`;
    $\\Theta_0 = L|\\hat u|$ is the unloaded end).  Held fixed (exactly one): the axial
    `force` (magnetic tweezer: torque and extension against turns, `Tweezer` end) or the
    `extension` $h$ (a spring twisted between grips: torque and axial force, `Clamped`
    end).  Other arguments as `force_extension`; continuation in the rotation counts the
    whole turns of the end.
    """
    name = "rotation_response"
    if (force is None) == (extension is None):
        raise ValueError(f"{name}: give exactly one of force= or extension=")
    rotations = _sweep_values(rotations, name, "rotations")
    n = rotations.shape[0]
    zero = jnp.zeros(n, rotations.dtype)
    if force is not None:
        held = _held(force, name, "force")
        values = jnp.stack([zero + held, zero, zero, rotations], -1)
        kind, held_name = _TWEEZER, "force"
    else:
        held = _held(extension, name, "extension")
        values = jnp.stack([zero, zero, zero + held, rotations], -1)
        kind, held_name = _CLAMPED, "extension"
    return _response(
        rod, length, kind, values, "rotation", held_name, segments=segments, mode=mode, method=method, rtol=rtol,
        atol=atol, ode_rtol=ode_rtol, ode_atol=ode_atol, max_steps=max_steps, adjoint=adjoint, name=name,
    )
