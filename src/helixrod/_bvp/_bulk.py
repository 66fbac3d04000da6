"""The uniform (bulk) helix of a finite rod under two axial controls, and the scales of
the shooting equations.

A uniform helix $u$ is an equilibrium under the axial wrench iff $K(u - \\hat u) = \\mu_1 u +
\\mu_2 e_3$ (docs/conventions.md); with two of $(F, M, h/L, \\Theta/L)$ prescribed these are five
equations in $(u, \\mu_1, \\mu_2)$, solved by Newton's method (optimistix, implicit
derivatives) from a guess on the branch wanted -- by default the unloaded helix ($u = \\hat u$,
$\\mu = 0$), so the branch is the one continuously connected to the unloaded spring.  On a
uniform helix $F = \\mu_2|u|$, $M = \\mu_1|u| + \\mu_2 u_3/|u|$, $h = L u_3/|u|$ and $\\Theta = L|u|$.
This is the prediction against which finite rods are compared, and the default guess of
`solve_boundary_value`.  Under a given force and moment the multipliers are explicit,
$\\mu_2 = F/|u|$ and $\\mu_1 = (M - F u_3/|u|^2)/|u|$, and the balance is three equations in
$u$ alone (`_wrench_residual`).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float

from .._misc import attainable, finite_array, finite_scalar, float_dtype, is_concrete, newton_iterations, no_gradient, solve_small, solve_small_linear
from .._rod import check_one_rod
from .._status import RESULTS, has_code, promote, raise_if_failed
from ._ends import AXIAL_OBSERVABLES, axial_controls

_FORCE, _MOMENT = AXIAL_OBSERVABLES.index("force"), AXIAL_OBSERVABLES.index("moment")
_ROTATION = AXIAL_OBSERVABLES.index("rotation")


def _twisted_if_straight(u0, twist):
    """The guess `u0`, or where it is zero (the unloaded state of an intrinsically straight,
    untwisted rod: no helix, the multipliers' $1/|u|$ singular, Newton's first step NaN)
    the straight rod twisted by `twist` about $d_3$ -- the bulk state itself wherever the
    controls hold it straight."""
    e3 = jnp.zeros(3, u0.dtype).at[2].set(1.0)
    return jnp.where(jnp.all(u0 == 0), twist * e3, u0)

#: The largest scaled residual of a guess taken as the root where Newton's solve failed there.
AT_ROOT = 1e-14


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


def residual_scales(rod, length) -> Array:
    """$(\\ell, \\bar K/\\ell^2, \\bar K/\\ell)$ (`length_scale`, `stiffness_scale`): the units of
    length, force and moment in which the shooting residual is measured (`ShootingArgs.scales`)."""
    ell = length_scale(rod, length)
    k_scale = stiffness_scale(rod)
    return jnp.stack([ell, k_scale / ell**2, k_scale / ell])


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


def _wrench_residual(x, args):
    """The balance $K(u - \\hat u) - \\mu_1 u - \\mu_2 e_3$ of the uniform helix of twist
    $u = x/\\ell$ under axial force $F$ and moment $M$, the multipliers eliminated (module
    docstring), in units of the stiffness scale per $\\ell$."""
    rod, force, moment, scales = args
    k_scale, ell = scales[0], scales[1]
    u = x / ell
    squared = jnp.sum(u * u) + 1e-300
    mu1, mu2 = _multipliers(u, squared, jnp.sqrt(squared), force, moment)
    e3 = jnp.array([0.0, 0.0, 1.0], u.dtype)
    return (rod.moment(u) - mu1 * u - mu2 * e3) / (k_scale / ell)


def _multipliers(u, squared, norm, force, moment):
    """$(\\mu_1, \\mu_2)$ of the uniform helix of twist `u` ($|u|^2$ `squared`, $|u|$ `norm`)
    under axial `force` and `moment` (module docstring)."""
    return (moment - force * u[2] / squared) / norm, force / norm


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


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _implicit_root(residual, z, args):
    """The root `z` of `residual(z, args) = 0` (given, converged), differentiated in
    `args` by the implicit function theorem, to any order: the rule evaluates the residual
    at this function's own output, so differentiating the rule again moves the root too."""
    return z


@_implicit_root.defjvp
def _implicit_root_jvp(residual, primals, tangents):
    z, args = primals
    _, dargs = tangents
    root = _implicit_root(residual, z, args)
    jacobian = jax.jacfwd(residual)(root, args)
    _, moved = jax.jvp(lambda a: residual(root, a), (args,), (dargs,))
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
    Default: optimistix Newton with implicit derivatives.

    With `index` known to be (force, moment) -- not traced -- the solve is
    `helix_under_wrench`'s, in $u$ alone; the multipliers follow from $u$ and the loads.
    (Measured on the bundled tweezer fit, whose model solves it per point and then
    differentiated it to third order, against the five unknowns: its program's tracing
    2.8 -> 2.55 s, XLA compilation 5.7 -> 4.5 s, a later call of it 18 -> 7 ms, the fit's
    first call 10.7-11.3 -> 8.6-8.8 s, one process each on 2 cores; the same fit to
    1e-14.)"""
    dtype = float_dtype()
    length = jnp.asarray(length, dtype)
    if guess is None:
        guess = (jnp.asarray(rod.uhat, dtype), jnp.zeros((), dtype), jnp.zeros((), dtype))
    values = jnp.asarray(values, dtype)
    # Invalid traced input (under vmap): solved at a harmless length, flagged, NaN.
    valid = jnp.isfinite(length) & (length > 0) & jnp.all(jnp.isfinite(values[jnp.asarray(index)]))
    length = jnp.where(valid, length, 1.0)
    modes = dict(max_steps=max_steps, light=light, newton_derivatives=newton_derivatives, step_tolerance=step_tolerance)
    if _is_force_and_moment(index):
        u, result = helix_under_wrench(rod, length, values[0], values[1], guess[0], **modes)
        norm = jnp.linalg.norm(u)
        safe = jnp.where(norm > 0, norm, 1.0)
        mu1, mu2 = _multipliers(u, safe**2, safe, values[0], values[1])
    else:
        k_scale = stiffness_scale(rod)
        ell = length_scale(rod, length)
        u0, m10, m20 = (jax.lax.stop_gradient(jnp.asarray(g, dtype)) for g in guess)
        # A straight guess twisted as the controls say (the rotation, else the moment over a stiffness).
        index_array = jnp.asarray(index)
        twist = jnp.where(
            jnp.any(index_array == _ROTATION), values[_ROTATION] / length,
            jnp.where(jnp.any(index_array == _MOMENT), values[_MOMENT] / k_scale, 0.0),
        )
        u0 = _twisted_if_straight(u0, jax.lax.stop_gradient(twist))
        z0 = jnp.concatenate([u0 * ell, jnp.stack([m10 / k_scale, m20 * ell / k_scale])])
        args = (rod, jnp.asarray(index), values, length, jnp.stack([k_scale, ell]))
        z, result = _root(_bulk_residual, z0, args, **modes)
        result = _checked(result, _bulk_residual, z, args, z[:3])
        u, mu1, mu2 = z[:3] / ell, z[3] * k_scale, z[4] * k_scale / ell
        norm = jnp.linalg.norm(u)
        safe = jnp.where(norm > 0, norm, 1.0)
    nan_if_invalid = lambda a: jnp.where(valid, a, jnp.nan)  # noqa: E731
    return BulkHelix(
        u=nan_if_invalid(u),
        mu1=nan_if_invalid(mu1),
        mu2=nan_if_invalid(mu2),
        force=nan_if_invalid(mu2 * norm),
        moment=nan_if_invalid(mu1 * norm + mu2 * u[2] / safe),
        extension=nan_if_invalid(length * u[2] / safe),
        rotation=nan_if_invalid(length * norm),
        result=RESULTS.where(valid, result, RESULTS.invalid_input),
    )


def helix_under_wrench(
    rod,
    length,
    force,
    moment,
    guess=None,
    *,
    max_steps: int = 64,
    light: bool = False,
    newton_derivatives: bool = False,
    step_tolerance: float | None = None,
) -> tuple[Float[Array, "3"], RESULTS]:
    """The twist $u$ of the uniform helix of a piece of length `length` under axial `force`
    and `moment` (`bulk_helix_at` of that pair: three equations in $u$, the multipliers
    eliminated), from the twist `guess` (default $\\hat u$), and its `RESULTS` code;
    the modes as `bulk_helix_at`'s.  Only $u$ carries derivatives: a caller that needs
    little else (the tweezer model, which a fit differentiates to second order) traces
    nothing more."""
    dtype = float_dtype()
    k_scale = stiffness_scale(rod)
    ell = length_scale(rod, jnp.asarray(length, dtype))
    u0 = jax.lax.stop_gradient(jnp.asarray(rod.uhat if guess is None else guess, dtype))
    u0 = _twisted_if_straight(u0, jax.lax.stop_gradient(jnp.asarray(moment, dtype) / k_scale))
    args = (rod, jnp.asarray(force, dtype), jnp.asarray(moment, dtype), jnp.stack([k_scale, ell]))
    x, result = _root(
        _wrench_residual, u0 * ell, args,
        max_steps=max_steps, light=light, newton_derivatives=newton_derivatives, step_tolerance=step_tolerance,
    )
    return x / ell, _checked(result, _wrench_residual, x, args, x)


def _checked(result, residual, z, args, x):
    """`result`, or `residual_above_tolerance` where a successful solve stopped off a helix
    with $|u| > 0$ (twist `x` scaled).  A check, not a prediction: evaluated without
    derivatives (under a fit's nested forward modes every derivative of the residual would
    be traced and thrown away)."""
    z, x = jax.lax.stop_gradient((z, x))
    imbalance = jnp.max(jnp.abs(residual(z, no_gradient(args))))
    helix = (imbalance < attainable(1e-8, z.dtype)) & (jnp.sum(x * x) > 0) & jnp.all(jnp.isfinite(z))
    return RESULTS.where(helix | (result != RESULTS.successful), result, RESULTS.residual_above_tolerance)


def _is_force_and_moment(index) -> bool:
    """Whether the controls `index` are known (not traced) to be the force and the moment."""
    return is_concrete(index) and np.asarray(index).tolist() == [_FORCE, _MOMENT]


def _root(residual, z0, args, *, max_steps, light, newton_derivatives, step_tolerance):
    """The root of `residual(z, args)` from `z0` and a `RESULTS` code, as `bulk_helix_at`'s
    modes solve it."""
    if light or newton_derivatives:
        frozen = no_gradient(args)
        z = newton_iterations(lambda z: residual(z, frozen), z0, max_steps, tolerance=step_tolerance)
        if newton_derivatives:
            def newton_step(_, z):
                dz = solve_small(jax.jacfwd(residual)(z, frozen), residual(z, frozen))
                return z - jnp.where(jnp.all(jnp.isfinite(dz)), dz, 0.0)  # a singular Jacobian: no step

            z = _implicit_root(residual, jax.lax.fori_loop(0, 2, newton_step, z), args)
        return z, RESULTS.successful
    tolerance = attainable(1e-12, z0.dtype)
    sol = optx.root_find(residual, optx.Newton(rtol=tolerance, atol=tolerance), z0, args, max_steps=max_steps, throw=False)
    # A guess that is already the root where the Jacobian is singular (a bifurcation point:
    # the straight twisted rod at F = -K1 u3^2) makes Newton's first linear solve fail; the
    # guess is the answer there.
    result = promote(sol.result)
    at_root = jnp.abs(residual(z0, no_gradient(args))) <= attainable(AT_ROOT, z0.dtype)
    failed_at_root = (result != RESULTS.successful) & jnp.all(at_root)
    return jnp.where(failed_at_root, z0, sol.value), RESULTS.where(failed_at_root, RESULTS.successful, result)


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
    if guess is not None:
        try:
            u, mu1, mu2 = guess
        except (TypeError, ValueError):
            raise ValueError("bulk_helix: guess must be (u, mu1, mu2)") from None
        guess = (finite_array(u, "guess u", "bulk_helix", (3,)), finite_scalar(mu1, "guess mu1", "bulk_helix"),
                 finite_scalar(mu2, "guess mu2", "bulk_helix"))
    index = jnp.array([AXIAL_OBSERVABLES.index(n) for n in name.split("-")])
    bulk = bulk_helix_at(rod, length, index, values, guess, max_steps=max_steps)
    if not throw:
        return bulk
    singular = is_concrete(bulk.result) and bool(has_code(bulk.result, RESULTS.singular))
    return raise_if_failed(bulk, bulk.result, "bulk_helix", _SINGULAR_HINT if singular else "")


_SINGULAR_HINT = (
    "\n(Here: Newton's method met a singular Jacobian, a bifurcation of the uniform helices -- e.g. the straight "
    "twisted rod at F = -K1 u3^2, where helices branch off it; give guess=(u, mu1, mu2) on the branch wanted, "
    "or move the controls off the bifurcation.)"
)
