"""Linear response of a uniform helical equilibrium: the helix as a spring.

A uniform helix of contour length $L$ and twist vector $u$ has axial extension
$h = L u_3/|u|$ and end rotation $\\Theta = L|u|$ (the director frame turns about the axis
$a = u/|u|$ at the rate $|u|$).  On the register branch through $u$ the axial wrench
$(F, M)$ of `helix_equilibria` is a smooth function of $(\\kappa, \\tau)$, so near $u$ the
uniform helices form a two-parameter family that can be labelled either by $(\\kappa, \\tau)$
or by $(F, M)$.  The compliance is the chain rule through that family,

$$\\frac{\\partial(h, \\Theta)}{\\partial(F, M)} =
  \\frac{\\partial(h, \\Theta)}{\\partial(\\kappa, \\tau)}
  \\Big[\\frac{\\partial(F, M)}{\\partial(\\kappa, \\tau)}\\Big]^{-1},$$

where $\\partial(F, M)/\\partial(\\kappa, \\tau)$ is forward-mode autodiff through
`helix_equilibria` (the register moves with $(\\kappa, \\tau)$ by the implicit function
theorem on the register equation, see `helixrod._roots`).

Uniform helices are the stationary points of $L W(u) - F h - M \\Theta$ over
$(\\kappa, \\tau, \\varphi)$ (the register condition is $\\partial W/\\partial\\varphi = 0$), so
$(F, M)$ is work-conjugate to $(h, \\Theta)$ and the compliance is symmetric (Maxwell
reciprocity) for every rod; the tests check this on random anisotropic, coupled rods.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._compile import jit
from ._equilibria import helix_equilibria
from ._geometry import height_and_turns
from ._misc import is_concrete
from ._rod import Rod

# A register is recognised when the phi of `u` matches a root to this angle (radians).
_REGISTER_TOLERANCE = 1e-6


def _wrench_all_slots(rod: Rod, x):
    """(F, M) of every register slot at (kappa, tau) = x, shape (4, 2); registers as aux."""
    eq = helix_equilibria(rod, x[0], x[1])
    return jnp.stack([eq.force, eq.moment], axis=-1), (eq.phi, eq.valid, eq.continuum)


def _observables(x, length):
    height, turns = height_and_turns(x[0], x[1], length)
    return jnp.stack([height, 2 * jnp.pi * turns])


def _single_compliance(rod: Rod, u, length):
    """Compliance and a flag `ok` for one unbatched rod and one twist vector."""
    x = jnp.stack([jnp.hypot(u[0], u[1]), u[2]])
    # One pass: the Jacobian of every slot's wrench (registers move by the implicit function
    # theorem inside helix_equilibria), with the registers themselves as aux.
    jac_all, (phis, valid, continuum) = jax.jacfwd(lambda y: _wrench_all_slots(rod, y), has_aux=True)(x)
    # Which register slot is u on?  Angular distance to every valid root (a discrete
    # choice: no gradient flows through it).
    frozen = jax.lax.stop_gradient(u)
    delta = jax.lax.stop_gradient(phis) - jnp.arctan2(frozen[0], frozen[1])
    gap = jnp.where(valid, jnp.abs(jnp.arctan2(jnp.sin(delta), jnp.cos(delta))), jnp.inf)
    slot = jnp.where(continuum, 0, jnp.argmin(gap))
    on_register = (gap[slot] <= _REGISTER_TOLERANCE) | continuum
    wrench_jac = jac_all[slot]
    obs_jac = jax.jacfwd(_observables)(x, length)
    finite = jnp.all(jnp.isfinite(wrench_jac)) & jnp.all(jnp.isfinite(obs_jac))
    det = wrench_jac[0, 0] * wrench_jac[1, 1] - wrench_jac[0, 1] * wrench_jac[1, 0]
    ok = on_register & (x[0] > 0) & finite & (det != 0) & jnp.isfinite(length) & (length > 0)
    safe_jac = jnp.where(ok, wrench_jac, jnp.eye(2, dtype=wrench_jac.dtype))
    compliance = obs_jac @ jnp.linalg.inv(safe_jac)
    return jnp.where(ok, compliance, jnp.nan), ok


# Compiled once per padded batch size and shared by every call (eager calls of any batch
# up to 128 reuse one executable: compiling helix_equilibria twice over is the slow part).
_compliance_kernel = jit(jax.vmap(_single_compliance))


def _padded_size(n: int) -> int:
    return 128 if n <= 128 else -(-n // 1024) * 1024


def _broadcast_rod(rod: Rod, batch, size):
    nb = rod.K1.ndim

    def grow(x):
        flat = jnp.broadcast_to(x, batch + x.shape[nb:]).reshape((-1,) + x.shape[nb:])
        return jnp.concatenate([flat, jnp.broadcast_to(flat[:1], (size - flat.shape[0],) + flat.shape[1:])])

    return jax.tree_util.tree_map(grow, rod)


def _batched_compliance(rod: Rod, u, length):
    dtype = jnp.result_type(float)
    u = jnp.asarray(u, dtype)
    length = jnp.asarray(length, dtype)
    if u.ndim == 0 or u.shape[-1] != 3:
        raise ValueError(f"u must have a trailing axis of length 3, got shape {u.shape}")
    try:
        batch = jnp.broadcast_shapes(u.shape[:-1], length.shape, rod.K1.shape)
    except ValueError:
        raise ValueError(
            f"u batch {u.shape[:-1]}, length {length.shape} and rod batch {rod.K1.shape} do not broadcast"
        ) from None
    count = math.prod(batch)
    if count == 0:
        return jnp.zeros(batch + (2, 2), dtype), jnp.zeros(batch, bool), u
    # Pad eager calls to a bucket size (rows repeat the first point); traced calls inline.
    size = _padded_size(count) if is_concrete(rod, u, length) else count

    def pad(x, tail):
        flat = jnp.broadcast_to(x, batch + tail).reshape((-1,) + tail)
        return jnp.concatenate([flat, jnp.broadcast_to(flat[:1], (size - count,) + tail)])

    compliance, ok = _compliance_kernel(_broadcast_rod(rod, batch, size), pad(u, (3,)), pad(length, ()))
    return compliance[:count].reshape(batch + (2, 2)), ok[:count].reshape(batch), u


_MESSAGE = (
    "spring_compliance: u is not a uniform helical equilibrium of the rod with kappa > 0 "
    "(no register of helix_equilibria at its phi), the equilibrium is degenerate, or length <= 0"
)


def spring_compliance(
    rod: Rod, u: ArrayLike, length: ArrayLike, *, throw: bool = True
) -> Float[Array, "*batch 2 2"]:
    """Compliance $\\partial(h, \\Theta)/\\partial(F, M)$ of a helical spring at equilibrium `u`.

    `u` (trailing axis 3, local components) must be a uniform helical equilibrium of `rod`:
    $\\kappa = \\sqrt{u_1^2 + u_2^2} > 0$, $\\tau = u_3$ and its register
    $\\varphi = \\operatorname{atan2}(u_1, u_2)$ one of the roots of `helix_equilibria`
    (matched to 1e-6 rad; any $\\varphi$ on a `continuum`).  `length` is the contour length $L$.
    Returns the 2x2 matrix

    $$\\begin{pmatrix} \\partial h/\\partial F & \\partial h/\\partial M \\\\
    \\partial\\Theta/\\partial F & \\partial\\Theta/\\partial M \\end{pmatrix}$$

    of the extension $h = L\\tau/|u|$ and the end rotation $\\Theta = L|u|$ (frame rotation
    about the axis, radians) with respect to the axial force $F$ and axial moment $M$
    (the `force`, `moment` of `helix_equilibria`), at fixed $L$, following the register
    branch through `u`.  Units: length/force, length/moment, 1/force, 1/moment.  The
    matrix is symmetric (Maxwell reciprocity; see the module docstring).

    For an isotropic wire it is the classical open-coiled spring (Love, *Mathematical Theory
    of Elasticity*, §270-271): at the unloaded helix of radius $r$ and pitch angle $\\alpha$,
    with bending stiffness $B$ and torsional stiffness $C$,
    $\\partial h/\\partial F = L r^2 (\\cos^2\\alpha/C + \\sin^2\\alpha/B)$,
    $\\partial h/\\partial M = L r \\sin\\alpha\\cos\\alpha (1/C - 1/B)$,
    $\\partial\\Theta/\\partial M = L(\\sin^2\\alpha/C + \\cos^2\\alpha/B)$; for a closed coil
    ($\\alpha = 0$, $n$ turns of diameter $D$ of wire of diameter $d$) $1/(\\partial h/\\partial F)$
    is the spring rate $G d^4/(8 D^3 n)$.

    Shapes: `u` batch, `length` and the rod's batch broadcast; result `batch + (2, 2)`.
    jit/vmap/grad-safe.  A `u` that is not an equilibrium, $\\kappa = 0$, a degenerate
    equilibrium (tangent register, where the branch turns) or `length <= 0` gives NaN;
    with `throw=True` (default) that is an error (`eqx.error_if`) -- pass `throw=False`
    under `jax.vmap` and read the NaNs, so one bad point does not spoil a batch.

    **Example**

    ```python
    rod = helixrod.Rod(1.0, 1.0, 0.8, uhat=(0.0, 0.9, 0.4))   # unloaded helix = uhat
    helixrod.spring_compliance(rod, rod.uhat, length=10.0)
    ```
    """
    compliance, ok, _ = _batched_compliance(rod, u, length)
    if throw:
        compliance = eqx.error_if(compliance, ~ok, _MESSAGE)
    return compliance


def effective_moduli(
    rod: Rod, u: ArrayLike, *, throw: bool = True
) -> tuple[Float[Array, "*batch"], Float[Array, "*batch"], Float[Array, "*batch"]]:
    """Stretch, twist and twist-stretch moduli $(S, C, g)$ of the helix at equilibrium `u`.

    The linear response about the equilibrium, per unit *axial* length, is written as in
    the single-molecule literature (Gore et al., Nature 442, 836 (2006)):

    $$\\delta F = S\\,\\varepsilon + g\\,\\omega, \\qquad \\delta M = g\\,\\varepsilon + C\\,\\omega,$$

    with the relative extension $\\varepsilon = \\delta h / h$ and the rotation per axial
    length $\\omega = \\delta\\Theta / h$ ($h = L\\tau/|u|$ the axial length at `u`).  Hence
    $\\begin{pmatrix} S & g \\\\ g & C \\end{pmatrix} = h\\,\\mathsf{C}^{-1}$ with $\\mathsf{C}$ the
    `spring_compliance`; it does not depend on $L$.  The energy per axial length is
    $\\tfrac12 S\\varepsilon^2 + g\\varepsilon\\omega + \\tfrac12 C\\omega^2$.  Units: $S$ force,
    $g$ force x length, $C$ force x length^2 (pN, pN nm, pN nm^2 for DNA in nm and pN).

    Sign convention: $\\Theta$ grows when the helix winds further about its axis (for
    $\\tau > 0$, a right-handed helix, in the right-handed sense), so $g < 0$ means
    *overwinding under tension*: at constant moment $\\omega = -g\\,\\varepsilon/C > 0$.

    For an isotropic wire (bending stiffness $B$, torsional $C_w$) at its unloaded helix of
    radius $r$ and pitch angle $\\alpha$: $S = \\sin\\alpha(\\cos^2\\alpha\\,C_w +
    \\sin^2\\alpha\\,B)/r^2$, $g = \\sin^2\\alpha\\cos\\alpha\\,(C_w - B)/r$,
    $C = \\sin\\alpha(\\sin^2\\alpha\\,C_w + \\cos^2\\alpha\\,B)$.

    Requires $\\tau \\ne 0$ (a flat ring has no axial length).  Shapes and error handling as
    `spring_compliance`.
    """
    compliance, ok, u = _batched_compliance(rod, u, 1.0)
    height = u[..., 2] / jnp.linalg.norm(u, axis=-1)
    ok = ok & (height != 0)
    safe = jnp.where(ok[..., None, None], compliance, jnp.eye(2, dtype=compliance.dtype))
    stiffness = jnp.where(ok[..., None, None], height[..., None, None] * jnp.linalg.inv(safe), jnp.nan)
    if throw:
        stiffness = eqx.error_if(stiffness, ~ok, _MESSAGE.replace("spring_compliance", "effective_moduli") + " (or tau = 0)")
    return stiffness[..., 0, 0], stiffness[..., 1, 1], 0.5 * (stiffness[..., 0, 1] + stiffness[..., 1, 0])
