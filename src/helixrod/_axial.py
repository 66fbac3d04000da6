"""A finite rod seen as a spring: its unloaded placement, its axis, and the uniform
(bulk) helix under two axial controls.

Placement.  With no load a rod takes its intrinsic shape $u = \\hat u$: the uniform helix of
curvature $\\hat\\kappa = (\\hat u_1^2 + \\hat u_2^2)^{1/2}$, torsion $\\hat\\tau = \\hat u_3$ and
register $\\hat\\varphi = \\operatorname{atan2}(\\hat u_1, \\hat u_2)$.  The *canonical placement*
is the one of `helix_frame` / `helix_centreline`: axis $e_z$ through the origin, $x(0) =
(\\hat r, 0, 0)$.  A straight untwisted rod ($\\hat u = 0$) starts at the origin with the identity
frame (tangent $e_z$).

Axial observables (DESIGN.md conventions, as `spring_compliance`): the axial force
$F = N\\cdot e_z$ (lab force $N$), the axial moment $M$ = the $e_z$ component of the moment about
any point of the axis, the extension $h = (x(L) - x(0))\\cdot e_z$ and the end rotation
$\\Theta$ about the axis.  On a uniform helix $F = \\mu_2|u|$, $M = \\mu_1|u| + \\mu_2 u_3/|u|$,
$h = L u_3/|u|$ and $\\Theta = L|u|$; the unloaded values are $h_0 = L\\hat\\tau/|\\hat u|$ and
$\\Theta_0 = L|\\hat u|$.

Bulk helix.  A uniform helix $u$ is an equilibrium under the axial wrench iff
$K(u - \\hat u) = \\mu_1 u + \\mu_2 e_3$ (DESIGN.md); with two of $(F, M, h/L, \\Theta/L)$
prescribed these are five equations in $(u, \\mu_1, \\mu_2)$, solved here by Newton's method
(optimistix, implicit derivatives) from a guess on the branch wanted -- by default the
unloaded helix ($u = \\hat u$, $\\mu = 0$), so the branch is the one continuously connected to the
unloaded spring.  This is the uniform-helix (bulk) prediction against which finite rods are
compared; `tests/test_boundary.py` checks it against `helix_equilibria`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array

from ._geometry import helix_centreline
from ._kirchhoff import helix_frame

CONTROLS = ("force", "moment", "extension", "rotation")


def no_gradient(tree):
    """`tree` with `stop_gradient` on its floating-point arrays (other leaves untouched)."""
    return jax.tree.map(lambda x: jax.lax.stop_gradient(x) if eqx.is_inexact_array(x) else x, tree)


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


def _safe_sqrt(x):
    """sqrt with a zero (not NaN) derivative at 0 (double `where`)."""
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def _intrinsic(rod):
    """(kappa, tau, phi, |uhat|, |uhat| > 0) of the intrinsic helix, with finite derivatives
    at kappa = 0 and uhat = 0 (tau is replaced by 1 when uhat = 0, where it is unused)."""
    uhat = jnp.asarray(rod.uhat)
    k2 = uhat[0] ** 2 + uhat[1] ** 2
    kappa = _safe_sqrt(k2)
    norm = _safe_sqrt(k2 + uhat[2] ** 2)
    curved = norm > 0
    safe_tau = jnp.where(curved, uhat[2], 1.0)
    bent = k2 > 0
    phi = jnp.where(bent, jnp.arctan2(jnp.where(bent, uhat[0], 0.0), jnp.where(bent, uhat[1], 1.0)), 0.0)
    return kappa, safe_tau, phi, norm, curved


def unloaded_state(rod, s) -> tuple[Array, Array]:
    """Exact centreline point `(..., 3)` and frame `(..., 3, 3)` of the unloaded rod at arc
    length(s) `s` in the canonical placement (module docstring)."""
    kappa, tau, phi, norm, curved = _intrinsic(rod)
    s = jnp.asarray(s, jnp.result_type(float))
    frame = helix_frame(kappa, tau, phi, s)
    x = helix_centreline(kappa, tau, s)
    straight_x = s[..., None] * jnp.array([0.0, 0.0, 1.0], s.dtype)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=s.dtype), frame.shape)
    return jnp.where(curved, x, straight_x), jnp.where(curved, frame, eye)


def unloaded_observables(rod, length) -> tuple[Array, Array]:
    """$(h_0, \\Theta_0) = (L\\hat\\tau/|\\hat u|, L|\\hat u|)$; $(L, 0)$ for $\\hat u = 0$."""
    _, tau, _, norm, curved = _intrinsic(rod)
    safe = jnp.where(curved, norm, 1.0)
    return length * jnp.where(curved, tau / safe, 1.0), length * norm


def rz(angle) -> Array:
    """Rotation by `angle` about $e_z$, shape `angle.shape + (3, 3)`."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    z, o = jnp.zeros_like(c), jnp.ones_like(c)
    return jnp.stack([jnp.stack([c, -s, z], -1), jnp.stack([s, c, z], -1), jnp.stack([z, z, o], -1)], -2)


def twist_angle(R) -> Array:
    """Twist angle about $e_z$ of the rotation `R` in $(-\\pi, \\pi]$ (swing-twist split,
    $2\\operatorname{atan2}(q_z, q_w)$ with $q$ the unit quaternion of `R`)."""
    return 2.0 * jnp.arctan2(R[..., 1, 0] - R[..., 0, 1], 1.0 + jnp.trace(R, axis1=-2, axis2=-1))


def unwrap_near(angle, hint) -> Array:
    """`angle + 2 pi k` with the integer `k` that brings it nearest to `hint`."""
    return angle + 2.0 * jnp.pi * jnp.round((hint - angle) / (2.0 * jnp.pi))


class BulkHelix(eqx.Module):
    """Uniform helix under axial controls: twist `u` (3,), multipliers `mu1`, `mu2`, axial
    `force`, `moment`, `extension` and `rotation` of a length-`length` piece, and `ok` (the
    Newton solve converged to a helix with $|u| > 0$)."""

    u: Array
    mu1: Array
    mu2: Array
    force: Array
    moment: Array
    extension: Array
    rotation: Array
    ok: Array


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


def bulk_helix_indexed(rod, length, index, values, guess=None, *, max_steps: int = 64, light: bool = False) -> BulkHelix:
    """`bulk_helix` with the two controls given by (possibly traced) indices into
    `CONTROLS` and a length-4 array of values (entries not indexed are ignored).

    `light=True`: a plain `max_steps`-step Newton iteration without derivatives (small to
    compile; for initial guesses)."""
    dtype = jnp.result_type(float)
    length = jnp.asarray(length, dtype)
    k_scale = stiffness_scale(rod)
    ell = length_scale(rod, length)
    if guess is None:
        guess = (jnp.asarray(rod.uhat, dtype), jnp.zeros((), dtype), jnp.zeros((), dtype))
    u0, m10, m20 = (jax.lax.stop_gradient(jnp.asarray(g, dtype)) for g in guess)
    z0 = jnp.concatenate([u0 * ell, jnp.stack([m10 / k_scale, m20 * ell / k_scale])])
    args = (rod, jnp.asarray(index), jnp.asarray(values, dtype), length, jnp.stack([k_scale, ell]))
    if light:
        args = no_gradient(args)

        def newton(_, z):
            step = jnp.linalg.solve(jax.jacfwd(_bulk_residual)(z, args), _bulk_residual(z, args))
            return jnp.where(jnp.all(jnp.isfinite(step)), z - step, z)

        z = jax.lax.fori_loop(0, max_steps, newton, z0)
        converged = True
    else:
        sol = optx.root_find(
            _bulk_residual, optx.Newton(rtol=1e-12, atol=1e-12), z0, args, max_steps=max_steps, throw=False
        )
        z = sol.value
        converged = sol.result == optx.RESULTS.successful
    u, mu1, mu2 = z[:3] / ell, z[3] * k_scale, z[4] * k_scale / ell
    norm = jnp.linalg.norm(u)
    residual = jnp.max(jnp.abs(_bulk_residual(z, args)))
    ok = converged & (residual < 1e-8) & (norm > 0) & jnp.all(jnp.isfinite(z))
    safe = jnp.where(norm > 0, norm, 1.0)
    return BulkHelix(
        u=u,
        mu1=mu1,
        mu2=mu2,
        force=mu2 * norm,
        moment=mu1 * norm + mu2 * u[2] / safe,
        extension=length * u[2] / safe,
        rotation=length * norm,
        ok=ok,
    )


def bulk_helix(rod, length, names: tuple[str, str], values, guess=None, *, max_steps: int = 64) -> BulkHelix:
    """The uniform helix with the two axial controls `names` (from `CONTROLS`) equal to
    `values` (a length-2 array; extension and rotation are totals over `length`).

    `guess`: `(u, mu1, mu2)` on the branch wanted (default the unloaded helix).  jit, vmap and
    jvp safe (implicit derivatives); a failed solve gives `ok = False`.
    """
    unknown = [n for n in names if n not in CONTROLS]
    if unknown or len(names) != 2 or names[0] == names[1]:
        raise ValueError(f"bulk_helix: two distinct controls from {CONTROLS} needed, got {names}")
    values = jnp.asarray(values, jnp.result_type(float))
    full = jnp.zeros(4, values.dtype)
    for i, name in enumerate(names):
        full = full.at[CONTROLS.index(name)].set(values[i])
    index = jnp.array([CONTROLS.index(n) for n in names])
    return bulk_helix_indexed(rod, length, index, full, guess, max_steps=max_steps)
