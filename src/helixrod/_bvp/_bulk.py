"""The uniform (bulk) helix of a finite rod under two axial controls, and the scales of
the shooting equations.

A uniform helix $u$ is an equilibrium under the axial wrench iff $K(u - \\hat u) = \\mu_1 u +
\\mu_2 e_3$ (docs/conventions.md); with two of $(F, M, h/L, \\Theta/L)$ prescribed these are five
equations in $(u, \\mu_1, \\mu_2)$, solved by Newton's method (optimistix, implicit
derivatives) from a guess on the branch wanted -- by default the unloaded helix ($u = \\hat u$,
$\\mu = 0$), so the branch is the one continuously connected to the unloaded spring.  On a
uniform helix $F = \\mu_2|u|$, $M = \\mu_1|u| + \\mu_2 u_3/|u|$, $h = L u_3/|u|$ and $\\Theta = L|u|$.
This is the prediction against which finite rods are compared, and the default guess of
`solve_boundary_value`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float

from .._misc import finite_scalar, float_dtype, newton_iterations, no_gradient, solve_small, solve_small_linear
from .._rod import check_one_rod
from .._status import RESULTS, promote, raise_if_failed
from ._ends import AXIAL_OBSERVABLES, axial_controls


def stiffness_scale(rod) -> Array:
    """Mean diagonal of $\\partial m/\\partial u$ at $\\hat u$ (the stiffness of a `Rod`, or the
    Hessian of a general strain energy); used only to scale residuals (no gradient)."""
    uhat = jax.lax.stop_gradient(jnp.asarray(rod.uhat))
    hessian = jax.jacfwd(no_gradient(rod).moment)(uhat)
    return jnp.trace(hessian) / 3.0


def length_scale(rod, length) -> Array:
    """$\\min(L, 1/|\\hat u|)$: the length over which the intrinsic shape turns by a radian."""
    norm = jnp.linalg.norm(jax.lax.stop_gradient(jnp.asarray(rod.uhat)))
    length = jax.lax.stop_gradient(jnp.asarray(length))
    return jnp.minimum(length, 1.0 / jnp.where(norm > 0, norm, 1.0 / length))


class BulkHelix(eqx.Module):
    """The uniform helix under two axial controls (`bulk_helix`): twist `u` `(3,)` (director
    frame), multipliers `mu1`, `mu2` ($m = \\mu_1 u + \\mu_2 e_3$, $n = \\mu_2 u$), the axial
    `force`, `moment`, `extension` and `rotation` of a piece of length `length`, `result`
    (a `RESULTS` code: the Newton solve, or `residual_above_tolerance` where it stopped off
    a helix with $|u| > 0$) and `ok`."""

    u: Float[Array, "*batch 3"]
    mu1: Float[Array, "*batch"]
    mu2: Float[Array, "*batch"]
    force: Float[Array, "*batch"]
    moment: Float[Array, "*batch"]
    extension: Float[Array, "*batch"]
    rotation: Float[Array, "*batch"]
    result: RESULTS

    @property
    def ok(self):
        """Whether the solve converged to a helix."""
        return self.result == RESULTS.successful

    @property
    def observables(self) -> Float[Array, "*batch 4"]:
        """(force, moment, extension, rotation) stacked, as `AXIAL_OBSERVABLES`."""
        return jnp.stack([self.force, self.moment, self.extension, self.rotation], -1)


def _bulk_residual(z, args):
    rod, index, values, length, scales = args
    k_scale, ell = scales[0], scales[1]
    u, mu1, mu2 = z[:3] / ell, z[3] * k_scale, z[4] * k_scale / ell
    norm = jnp.sqrt(jnp.sum(u * u) + 1e-300)
    e3 = jnp.array([0.0, 0.0, 1.0], u.dtype)
    balance = (rod.moment(u) - mu1 * u - mu2 * e3) / (k_scale / ell)
    f_unit, m_unit = k_scale / ell**2, k_scale / ell
    observed = jnp.stack([mu2 * norm / f_unit, (mu1 * norm + mu2 * u[2] / norm) / m_unit, u[2] / norm, norm * ell])
    target = jnp.stack([values[0] / f_unit, values[1] / m_unit, values[2] / length, values[3] / length * ell])
    controls = (observed - target)[index]
    return jnp.concatenate([balance, controls])


@jax.custom_jvp
def _implicit_root(z, args):
    """The root `z` of `_bulk_residual(z, args) = 0` (given, converged), differentiated in
    `args` by the implicit function theorem, to any order: the rule evaluates the residual
    at this function's own output, so differentiating the rule again moves the root too."""
    return z


@_implicit_root.defjvp
def _implicit_root_jvp(primals, tangents):
    z, args = primals
    _, dargs = tangents
    root = _implicit_root(z, args)
    jacobian = jax.jacfwd(_bulk_residual)(root, args)
    _, moved = jax.jvp(lambda a: _bulk_residual(root, a), (args,), (dargs,))
    return root, -solve_small_linear(jacobian, moved)


def bulk_helix_at(
    rod,
    length,
    index,
    values,
    guess=None,
    *,
    max_steps: int = 64,
    light: bool = False,
    newton_derivatives: bool = False,
    step_tolerance: float | None = None,
) -> BulkHelix:
    """`bulk_helix` with the two controls given by (possibly traced) indices `index` into
    `AXIAL_OBSERVABLES` and a length-4 array of `values` (entries not indexed are ignored).

    `light=True`: a plain `max_steps`-step Newton iteration without derivatives (small to
    compile; for initial guesses), stopped early once a step of the scaled unknowns is below
    `step_tolerance` if that is given.  `newton_derivatives=True`: that iteration and two
    more Newton steps, then the root differentiated by the implicit function theorem to any
    order (`_implicit_root`) with dense solves that never raise: for callers that
    differentiate twice or under solvers that probe with non-finite tangents.  (Before,
    the two steps were differentiated, which gives the same first and second derivatives
    -- the Newton map is stationary at a root -- through the residual's third
    derivatives: on one core the bundled tweezer fit's model program traced in 4.1 s
    instead of 2.9 s and compiled in 6.0 s instead of 5.4 s, its later calls 0.49 s
    instead of 0.33 s.)
    Default: optimistix Newton with implicit derivatives."""
    dtype = float_dtype()
    length = jnp.asarray(length, dtype)
    k_scale = stiffness_scale(rod)
    ell = length_scale(rod, length)
    if guess is None:
        guess = (jnp.asarray(rod.uhat, dtype), jnp.zeros((), dtype), jnp.zeros((), dtype))
    u0, m10, m20 = (jax.lax.stop_gradient(jnp.asarray(g, dtype)) for g in guess)
    z0 = jnp.concatenate([u0 * ell, jnp.stack([m10 / k_scale, m20 * ell / k_scale])])
    args = (rod, jnp.asarray(index), jnp.asarray(values, dtype), length, jnp.stack([k_scale, ell]))
    if light or newton_derivatives:
        frozen = no_gradient(args)
        z = newton_iterations(lambda z: _bulk_residual(z, frozen), z0, max_steps, tolerance=step_tolerance)
        result = RESULTS.successful
        if newton_derivatives:
            def newton_step(_, z):
                return z - solve_small(jax.jacfwd(_bulk_residual)(z, frozen), _bulk_residual(z, frozen))

            z = _implicit_root(jax.lax.fori_loop(0, 2, newton_step, z), args)
    else:
        sol = optx.root_find(
            _bulk_residual, optx.Newton(rtol=1e-12, atol=1e-12), z0, args, max_steps=max_steps, throw=False
        )
        z = sol.value
        result = promote(sol.result)
    u, mu1, mu2 = z[:3] / ell, z[3] * k_scale, z[4] * k_scale / ell
    norm = jnp.linalg.norm(u)
    residual = jnp.max(jnp.abs(_bulk_residual(z, args)))
    helix = (residual < 1e-8) & (norm > 0) & jnp.all(jnp.isfinite(z))
    safe = jnp.where(norm > 0, norm, 1.0)
    return BulkHelix(
        u=u,
        mu1=mu1,
        mu2=mu2,
        force=mu2 * norm,
        moment=mu1 * norm + mu2 * u[2] / safe,
        extension=length * u[2] / safe,
        rotation=length * norm,
        result=RESULTS.where(helix | (result != RESULTS.successful), result, RESULTS.residual_above_tolerance),
    )


def bulk_helix(
    rod,
    length: ArrayLike,
    *,
    force: ArrayLike | None = None,
    moment: ArrayLike | None = None,
    extension: ArrayLike | None = None,
    rotation: ArrayLike | None = None,
    guess: tuple[ArrayLike, ArrayLike, ArrayLike] | None = None,
    max_steps: int = 64,
    throw: bool = True,
) -> BulkHelix:
    """The uniform helix of a piece of length `length` with two axial controls prescribed,
    the same pairs as `axial_ends`: `force` and `moment`, `force` and `rotation`, or
    `extension` and `rotation` (extension and rotation are totals over `length`; scalars).

    `guess`: `(u, mu1, mu2)` on the branch wanted (default the unloaded helix, $u = \\hat u$).
    jit, vmap and jvp safe (implicit derivatives).  `throw`: raise `SolverError` if the
    Newton solve fails; with `throw=False` read `result` and `ok`.

    **Example**

    ```python
    spring = helixrod.Rod(1.0, 1.0, 0.77, uhat=(0.0, 1.0, 0.3))
    bulk = helixrod.bulk_helix(spring, 30.0, force=0.02, moment=0.0)
    bulk.extension, bulk.rotation, bulk.u
    ```
    """
    try:
        name, given = axial_controls(force=force, moment=moment, extension=extension, rotation=rotation)
    except ValueError as error:
        raise ValueError(f"bulk_helix: {error}") from None
    check_one_rod(rod, "bulk_helix")
    length = finite_scalar(length, "length", "bulk_helix", positive=True)
    values = jnp.stack([finite_scalar(given.get(n, 0.0), n, "bulk_helix") for n in AXIAL_OBSERVABLES])
    index = jnp.array([AXIAL_OBSERVABLES.index(n) for n in name.split("-")])
    bulk = bulk_helix_at(rod, length, index, values, guess, max_steps=max_steps)
    return raise_if_failed(bulk, bulk.result, "bulk_helix") if throw else bulk
