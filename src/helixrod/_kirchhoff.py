"""The static Kirchhoff equations integrated along the arc length with diffrax.

In local (director-frame) components, with $u$ from the constitutive law $m = \\nabla W(u)$,

$$n' + u\\times n = 0,\\qquad m' + u\\times m + e_3\\times n = 0,$$

and, when asked for, the frame $D' = D\\hat u$ (column $i$ of $D$ is $d_{i+1}$ in lab
coordinates) and the centreline $x' = D e_3$.  First integrals: $I_1 = n\\cdot n$,
$I_2 = m\\cdot n$ and $H = u\\cdot m - W(u) + n_3$.
"""

from __future__ import annotations

from collections.abc import Sequence

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._equilibria import HelixEquilibria
from ._geometry import helix_centreline
from ._lie import BodyVelocityTerm, CommutatorFreeRK4, MuntheKaasRK, RodState, tangent


_OUTPUTS = ("wrench", "frame", "centreline")


class KirchhoffSolution(eqx.Module):
    """Solution of `solve_static`, saved at `s` (leading save axis of length `k`).

    Fields: `s` `(k,)` arc lengths; `n`, `m`, `u` `(k, 3)` force, moment and twist in the
    director frame; `frame` `(k, 3, 3)` (column $i$ is $d_{i+1}$ in lab coordinates) and
    `x` `(k, 3)` the centreline in lab coordinates, each `None` unless requested through
    `outputs`; `first_integrals` `(k, 3)` the values of $(I_1, I_2, H)$ and `drift` their
    change since $s = 0$; `result` the `diffrax.RESULTS` code of the solve;
    `valid_input` False where the input was rejected (only with `throw=False`; the fields
    are NaN there); `num_steps` the number of accepted steps.
    """

    s: Float[Array, " k"]
    n: Float[Array, "k 3"]
    m: Float[Array, "k 3"]
    u: Float[Array, "k 3"]
    frame: Float[Array, "k 3 3"] | None
    x: Float[Array, "k 3"] | None
    first_integrals: Float[Array, "k 3"]
    drift: Float[Array, "k 3"]
    result: diffrax.RESULTS
    valid_input: Bool[Array, ""]
    num_steps: Int[Array, ""]

    @property
    def ok(self) -> Bool[Array, ""]:
        """True where the input was valid and the solve succeeded."""
        return self.valid_input & (self.result == diffrax.RESULTS.successful)

    def lab_wrench(self) -> tuple[Array, Array]:
        """Force and moment in lab coordinates, $(Dn, Dm)$; needs the frame."""
        if self.frame is None:
            raise ValueError("lab_wrench needs the frame: solve with outputs=('frame',)")
        return lab_wrench(self.frame, self.n, self.m)


def lab_wrench(frame: ArrayLike, n: ArrayLike, m: ArrayLike) -> tuple[Array, Array]:
    """Lab components $(D n, D m)$ of a local force and moment; shapes broadcast.

    On an equilibrium the lab force is constant and the lab moment changes as
    $M(s) = M(0) - (x(s) - x(0))\\times N$.
    """
    frame = jnp.asarray(frame)
    return jnp.einsum("...ij,...j->...i", frame, n), jnp.einsum("...ij,...j->...i", frame, m)


def first_integrals(rod, n: ArrayLike, m: ArrayLike) -> Float[Array, "... 3"]:
    """$(I_1, I_2, H) = (n\\cdot n,\\ m\\cdot n,\\ u\\cdot m - W(u) + n_3)$ with $u$ from $m$.

    `n`, `m` have a trailing axis of 3 (local components) and broadcast; `rod` is a `Rod`
    or any constitutive law with `twist` and `energy`.  All three are constant along every
    solution of the static Kirchhoff equations.
    """
    n, m = jnp.broadcast_arrays(jnp.asarray(n), jnp.asarray(m))
    u = rod.twist(m)
    hamiltonian = jnp.sum(u * m, -1) - rod.energy(u) + n[..., 2]
    return jnp.stack([jnp.sum(n * n, -1), jnp.sum(m * n, -1), hamiltonian], -1)


def _body_velocity(s, y: RodState, rod):
    """The body twist $(u, e_3)$ of the director frame: $D' = D\\hat u$, $x' = De_3$."""
    u = rod.twist(y.m)
    return u, jnp.zeros_like(u).at[2].set(1.0)


def _ambient_field(s, y: RodState, rod) -> RodState:
    """$dy/ds$ for the standard (vector-space) solvers."""
    return tangent(y, *_body_velocity(s, y, rod))


def _spectral_radius_bound(J, squarings: int = 5):
    """Upper bound $\\|J^{2^k}\\|_F^{1/2^k} \\ge \\rho(J)$ (Gelfand), within a few per cent of
    the spectral radius for $k = 5$ even when $J$ is far from normal; matrix products only
    (no eigenvalues: GPU-ready), rescaled at each squaring so that nothing over- or
    underflows."""
    scale = jnp.max(jnp.abs(J))
    nilpotent = ~(scale > 0)
    safe = jnp.where(nilpotent, 1.0, scale)
    A = J / safe
    log_scale = jnp.log(safe)
    for _ in range(squarings):
        A = A @ A
        a = jnp.max(jnp.abs(A))
        nilpotent = nilpotent | ~(a > 0)
        a_safe = jnp.where(a > 0, a, 1.0)
        A = A / a_safe
        log_scale = 2 * log_scale + jnp.log(a_safe)
    log_rho = (log_scale + 0.5 * jnp.log(jnp.sum(A * A))) / 2**squarings
    return jnp.where(nilpotent, 0.0, jnp.exp(log_rho))


def _stability_step(rod, n0, m0):
    """Largest step for which the explicit coupling of `CommutatorFreeRK4` keeps round-off
    perturbations bounded, from the Jacobian $J$ of the wrench equations at $s = 0$:
    $\\max(2/\\|J\\|_F,\\ 0.5/\\rho(J))$, $\\rho$ the spectral radius (bounded above by
    `_spectral_radius_bound`).  Near a uniform helix the error estimate vanishes, and
    without a cap the step grows until round-off is amplified (measured: stable for
    $h\\|J\\|_F \\lesssim 3.5$ on spatially stable helices; on the 1000-turn helix of the
    README the frame error is 9e-11 at $h\\rho = 0.8$, 1.3e-9 at 0.9, 1.8e-7 at 0.95).  The
    spectral term matters where $J$ is far from normal (highly twisted, nearly singular
    rods: $\\|J\\|_F/\\rho$ of 1.6e3 and 2.5e4 measured), where $2/\\|J\\|_F$ alone made
    `solve_static` run out of steps (`tests/test_stress.py`)."""

    def wrench_rate(w):
        state = RodState(w[:3], w[3:])
        rate = tangent(state, *_body_velocity(0.0, state, rod))
        return jnp.concatenate([rate.n, rate.m])

    J = jax.jacfwd(wrench_rate)(jax.lax.stop_gradient(jnp.concatenate([n0, m0])))
    norm = jnp.sqrt(jnp.sum(J * J))
    rho = _spectral_radius_bound(J)
    frobenius_step = jnp.where(norm > 0, 2.0 / jnp.where(norm > 0, norm, 1.0), jnp.inf)
    spectral_step = jnp.where(rho > 0, 0.5 / jnp.where(rho > 0, rho, 1.0), jnp.inf)
    return jnp.maximum(frobenius_step, spectral_step)


def check_one_rod(rod, owner: str) -> None:
    """Raise `ValueError` unless `rod` is a single rod (not a batch), read from the shape of
    its `uhat` (or, for a law without one, of its inverse law; without running it)."""
    uhat = getattr(rod, "uhat", None)
    if uhat is not None:
        shape = jnp.shape(uhat)
    else:
        shape = jax.eval_shape(rod.twist, jax.ShapeDtypeStruct((3,), jnp.result_type(float))).shape
    if shape != (3,):
        raise ValueError(f"{owner} takes one rod: jax.vmap over a batch of rods")


def _is_concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(xs))


def _parse_outputs(outputs) -> tuple[bool, bool, bool]:
    """(integrate the frame, store the frame, integrate and store the centreline)."""
    names = (outputs,) if isinstance(outputs, str) else tuple(outputs)
    unknown = [name for name in names if name not in _OUTPUTS]
    if unknown:
        raise ValueError(f"solve_static: unknown output name(s) {unknown}; choose from {_OUTPUTS}")
    centreline = "centreline" in names
    store_frame = "frame" in names
    return store_frame or centreline, store_frame, centreline


def solve_static(
    rod,
    n0: ArrayLike,
    m0: ArrayLike,
    length: ArrayLike,
    *,
    frame0: ArrayLike | None = None,
    x0: ArrayLike | None = None,
    saveat: ArrayLike | None = None,
    outputs: str | Sequence[str] = ("wrench",),
    solver: diffrax.AbstractSolver | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    steps: int | None = None,
    max_steps: int = 100_000,
    adjoint: diffrax.AbstractAdjoint = diffrax.RecursiveCheckpointAdjoint(),
    throw: bool = True,
) -> KirchhoffSolution:
    """Integrate the static Kirchhoff equations from $s = 0$ to $s$ = `length`.

    **Arguments**

    - `rod`: a `Rod`, or any constitutive law with `twist(m)` and `energy(u)` (e.g.
      `StrainEnergyRod`); unbatched (use `jax.vmap` for batches of rods).
    - `n0`, `m0`: force and moment at $s = 0$ in the director frame, shape `(3,)`.
    - `length`: arc length, $> 0$.
    - `frame0`: initial frame, `(3, 3)` rotation with column $i$ = $d_{i+1}$ (default
      identity); `x0`: initial centreline point (default origin).
    - `saveat`: `None` saves at $s$ = `length` only (save axis of length 1); an
      increasing array of $s$ in $[0, \\mathrm{length}]$ saves there.
    - `outputs`: names from `("wrench", "frame", "centreline")`. Only what is named is
      integrated and stored: the wrench alone is a 6-dimensional system; the centreline
      needs (and integrates, without storing) the frame.
    - `solver`: default `MuntheKaasRK(diffrax.Dopri8())` (8th order, 13 evaluations a
      step); `CommutatorFreeRK4()` (4th order, 4 evaluations a step) is cheaper per step,
      compiles in half the time and is the faster one on uniform helices and at loose
      tolerances.  Both are exact on uniform helices, keep the frame orthonormal and
      conserve $|n|^2$ and $m\\cdot n$ to round-off.  Any diffrax ODE solver also works (it
      then integrates the frame as 9 plain components).  The default was chosen by
      `benchmarks/bench_kirchhoff.py`: on a non-helical solution it reaches the error of
      scipy DOP853 at tolerance 1e-10 in the fewest milliseconds.
    - `rtol`, `atol`: PID step-size tolerances, default `1e-12` in float64 (`1e-6` in
      float32, which cannot meet tighter ones); `steps`: use that many equal steps
      instead (no error control; may be traced, then `max_steps` must cover it).
    - `max_steps`, `adjoint` (default `RecursiveCheckpointAdjoint`, reverse mode; use
      `diffrax.ForwardMode()` for `jax.jacfwd`), `throw` as in `diffrax.diffeqsolve`.

    **Errors.** Non-finite `n0`/`m0`, `length <= 0` or non-finite, and bad shapes raise
    `ValueError` for concrete values.  Traced values raise an `equinox` runtime error when
    `throw=True`; with `throw=False` a bad point is flagged (`valid_input=False`, fields
    NaN) so that one bad point never spoils a `vmap`-ped batch.  Hitting `max_steps`
    raises with `throw=True` and sets `result` otherwise.

    **Batches.** `jax.vmap(solve_static, ...)` over initial conditions, lengths or rods.
    A vmapped adaptive solve runs in lockstep: every member takes as many steps as the
    slowest (see the README for the measured cost).

    **Example**

    ```python
    eq = helixrod.helix_equilibria(rod, 0.5, 1.5)
    n0, m0, frame0, x0 = helixrod.helix_initial_conditions(eq)
    sol = helixrod.solve_static(rod, n0[0], m0[0], 100.0, frame0=frame0[0], x0=x0[0],
                                saveat=jnp.linspace(0, 100, 500), outputs="centreline")
    ```
    """
    with_frame, store_frame, with_x = _parse_outputs(outputs)
    solver = MuntheKaasRK(diffrax.Dopri8()) if solver is None else solver
    geometric = isinstance(solver, (CommutatorFreeRK4, MuntheKaasRK))
    check_one_rod(rod, "solve_static")

    dtype = jnp.result_type(float)
    default_tol = 1e-12 if dtype == jnp.float64 else 1e-6
    rtol = default_tol if rtol is None else rtol
    atol = default_tol if atol is None else atol
    n0 = jnp.asarray(n0, dtype)
    m0 = jnp.asarray(m0, dtype)
    length = jnp.asarray(length, dtype)
    if n0.shape != (3,) or m0.shape != (3,) or length.shape != ():
        raise ValueError(
            f"solve_static: n0, m0 need shape (3,) and length a scalar, got {n0.shape}, "
            f"{m0.shape}, {length.shape}; use jax.vmap for batches"
        )
    frame0 = jnp.eye(3, dtype=dtype) if frame0 is None else jnp.asarray(frame0, dtype)
    x0 = jnp.zeros(3, dtype) if x0 is None else jnp.asarray(x0, dtype)
    if frame0.shape != (3, 3) or x0.shape != (3,):
        raise ValueError(f"solve_static: frame0 needs shape (3, 3) and x0 (3,), got {frame0.shape}, {x0.shape}")

    finite = jnp.all(jnp.isfinite(n0)) & jnp.all(jnp.isfinite(m0))
    good_length = jnp.isfinite(length) & (length > 0)
    if _is_concrete(n0, m0) and not np.all(np.isfinite(np.concatenate([np.asarray(n0), np.asarray(m0)]))):
        raise ValueError(f"solve_static: n0 and m0 must be finite, got n0={n0}, m0={m0}")
    if _is_concrete(length) and not (np.isfinite(np.asarray(length)) and np.asarray(length) > 0):
        raise ValueError(f"solve_static: length must be finite and > 0, got {length}")
    valid = finite & good_length
    if throw:
        n0 = eqx.error_if(n0, ~finite, "solve_static: n0 and m0 must be finite")
        length = eqx.error_if(length, ~good_length, "solve_static: length must be finite and > 0")
    else:
        n0 = jnp.where(valid, n0, 0.0)
        m0 = jnp.where(valid, m0, 0.0)
        length = jnp.where(valid, length, 1.0)

    if saveat is None:
        ts = None
        save = diffrax.SaveAt(t1=True)
    else:
        ts = jnp.asarray(saveat, dtype)
        if ts.ndim != 1 or ts.shape[0] < 1:
            raise ValueError(f"solve_static: saveat must be a 1-d array of arc lengths, got shape {ts.shape}")
        if _is_concrete(ts, length):
            tsn, ln = np.asarray(ts), float(np.asarray(length))
            if np.any(np.diff(tsn) <= 0) or tsn[0] < 0 or tsn[-1] > ln:
                raise ValueError(f"solve_static: saveat must increase strictly within [0, {ln}], got {tsn}")
        if not throw:
            ts = jnp.where(valid, ts, jnp.linspace(0.0, 1.0, ts.shape[0], dtype=dtype))
        save = diffrax.SaveAt(ts=ts)

    if steps is not None:
        if geometric and saveat is not None:
            raise ValueError(
                "solve_static: with fixed `steps` the geometric solver saves only at s = length "
                "(its frames between steps would be interpolated); use the adaptive mode"
            )
        controller = diffrax.ConstantStepSize()
        dt0 = length / steps
        if isinstance(steps, int):
            max_steps = max(max_steps, steps)
    else:
        # The geometric solver's saved frames must be step values, not interpolants.
        step_ts = ts if (geometric and ts is not None) else None
        dtmax = _stability_step(rod, n0, m0) if geometric else None
        # Array tolerances: a new tolerance does not recompile.
        controller = diffrax.PIDController(
            rtol=jnp.asarray(rtol, dtype), atol=jnp.asarray(atol, dtype), step_ts=step_ts, dtmax=dtmax
        )
        dt0 = None

    y0 = RodState(
        n0,
        m0,
        frame0 if with_frame else None,
        x0 if with_x else None,
    )
    term = BodyVelocityTerm(_body_velocity) if geometric else diffrax.ODETerm(_ambient_field)
    sol = diffrax.diffeqsolve(
        term,
        solver,
        0.0,
        length,
        dt0,
        y0,
        args=rod,
        saveat=save,
        stepsize_controller=controller,
        max_steps=max_steps,
        adjoint=adjoint,
        throw=throw,
    )
    ys = sol.ys
    nan_if_invalid = lambda a: jnp.where(valid, a, jnp.nan)  # noqa: E731
    n, m = nan_if_invalid(ys.n), nan_if_invalid(ys.m)
    integrals = first_integrals(rod, n, m)
    return KirchhoffSolution(
        s=sol.ts,
        n=n,
        m=m,
        u=rod.twist(m),
        frame=nan_if_invalid(ys.frame) if store_frame else None,
        x=nan_if_invalid(ys.x) if with_x else None,
        first_integrals=integrals,
        drift=integrals - first_integrals(rod, n0, m0),
        result=sol.result,
        valid_input=valid,
        num_steps=sol.stats["num_accepted_steps"],
    )


# -- uniform helices ---------------------------------------------------------------------


def helix_frame(kappa: ArrayLike, tau: ArrayLike, phi: ArrayLike, s: ArrayLike) -> Float[Array, "... 3 3"]:
    """Exact director frame of the uniform helix $u = (\\kappa\\sin\\varphi, \\kappa\\cos\\varphi, \\tau)$
    placed as `helix_centreline` places it (axis $e_z$, $x(0) = (r, 0, 0)$).

    $D(s) = R_z(|u| s)\\, D_0$ with $D_0$ the rotation taking the local axis $u/|u|$ to
    $e_z$ and $e_3$ to the tangent $(0, \\kappa, \\tau)/|u|$; then $D' = D\\hat u$ and
    $\\int_0^s D e_3 = $ `helix_centreline(kappa, tau, s) - helix_centreline(kappa, tau, 0)`.
    Shapes broadcast; the result has trailing `(3, 3)`.
    """
    kappa, tau, phi, s = jnp.broadcast_arrays(*(jnp.asarray(a, jnp.result_type(float)) for a in (kappa, tau, phi, s)))
    norm_u = jnp.hypot(kappa, tau)
    zero, one = jnp.zeros_like(kappa), jnp.ones_like(kappa)
    # Local orthonormal basis (e3, b2, b3) with b2 along the bending part of u ...
    local = jnp.stack(
        [
            jnp.stack([zero, zero, one], -1),
            jnp.stack([jnp.sin(phi), jnp.cos(phi), zero], -1),
            jnp.stack([-jnp.cos(phi), jnp.sin(phi), zero], -1),
        ],
        -1,
    )
    # ... and its lab images: the tangent, the axis component normal to it, e_x.
    lab = jnp.stack(
        [
            jnp.stack([zero, kappa / norm_u, tau / norm_u], -1),
            jnp.stack([zero, -tau / norm_u, kappa / norm_u], -1),
            jnp.stack([one, zero, zero], -1),
        ],
        -1,
    )
    frame0 = lab @ jnp.swapaxes(local, -1, -2)
    angle = norm_u * s
    c, sn = jnp.cos(angle), jnp.sin(angle)
    rz = jnp.stack(
        [jnp.stack([c, -sn, zero], -1), jnp.stack([sn, c, zero], -1), jnp.stack([zero, zero, one], -1)], -2
    )
    return rz @ frame0


def helix_initial_conditions(eq: HelixEquilibria) -> tuple[Array, Array, Array, Array]:
    """Initial state `(n0, m0, frame0, x0)` of each uniform helix in `eq` (from
    `helix_equilibria`) so that `solve_static(rod, n0, m0, L, frame0=frame0, x0=x0)`
    reproduces it: the frame and centreline then equal `helix_frame(kappa, tau, phi, s)`
    and `helix_centreline(kappa, tau, s)`.  Shapes follow `eq` (per register; invalid
    slots are NaN).  A register whose linearised wrench flow has an eigenvalue with positive
    real part is spatially unstable: round-off then grows like $e^{\\lambda s}$ in any
    integration, and the helix is reproduced only over lengths of a few $1/\\lambda$."""
    kappa = jnp.hypot(eq.u[..., 0], eq.u[..., 1])
    tau = eq.u[..., 2]

    return eq.n, eq.m, helix_frame(kappa, tau, eq.phi, 0.0), helix_centreline(kappa, tau, 0.0)
