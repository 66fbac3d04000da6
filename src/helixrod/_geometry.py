"""Helix geometry: conversions between curvature/torsion and radius/pitch/angles, and the
centreline.  A helix of curvature $\\kappa \\ge 0$ and torsion $\\tau$ has $|u| = \\sqrt{\\kappa^2
+ \\tau^2}$, radius $r = \\kappa/|u|^2$, reduced pitch $p = \\tau/|u|^2$ (rise $2\\pi p$ per
turn).  The *pitch angle* $\\alpha$ is the angle between the tangent and the plane normal to
the axis ($\\kappa = |u|\\cos\\alpha$, $\\tau = |u|\\sin\\alpha$); the *helix angle*
$\\theta = \\pi/2 - \\alpha$ is the angle between the tangent and the axis.  $\\tau > 0$ is a
right-handed helix."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._lie import rotation_z
from ._misc import float_dtype, safe_sqrt


def radius_pitch(kappa: ArrayLike, tau: ArrayLike) -> tuple[Array, Array]:
    """Radius $r$ and reduced pitch $p$ of the helix of curvature $\\kappa$ and torsion $\\tau$:
    $(r, p) = (\\kappa, \\tau)/(\\kappa^2+\\tau^2)$; the rise per turn is $2\\pi p$.

    Arrays broadcast; with $\\kappa$, $\\tau$ in 1/length, $r$ and $p$ are lengths ($p < 0$ for
    a left-handed helix).  Example: `radius_pitch(1.0, 0.0)` is `(1.0, 0.0)`, a unit ring.
    Inverse: `curvature_torsion`.
    """
    kappa, tau = jnp.asarray(kappa), jnp.asarray(tau)
    norm2 = kappa**2 + tau**2
    return kappa / norm2, tau / norm2


def curvature_torsion(radius: ArrayLike, pitch: ArrayLike) -> tuple[Array, Array]:
    """Curvature and torsion $(\\kappa, \\tau) = (r, p)/(r^2 + p^2)$ (1/length) of the helix of
    radius $r$ and reduced pitch $p$ (lengths; rise $2\\pi p$ per turn).  Arrays broadcast.
    Inverse of `radius_pitch`."""
    radius, pitch = jnp.asarray(radius), jnp.asarray(pitch)
    norm2 = radius**2 + pitch**2
    return radius / norm2, pitch / norm2


def from_polar(norm_u: ArrayLike, pitch_angle: ArrayLike) -> tuple[Array, Array]:
    """$(\\kappa, \\tau) = |u| (\\cos\\alpha, \\sin\\alpha)$ from $|u|$ (1/length) and the pitch
    angle $\\alpha$ (radians, module docstring).  Arrays broadcast.  Inverse of `to_polar`."""
    norm_u, pitch_angle = jnp.asarray(norm_u), jnp.asarray(pitch_angle)
    return norm_u * jnp.cos(pitch_angle), norm_u * jnp.sin(pitch_angle)


def to_polar(kappa: ArrayLike, tau: ArrayLike) -> tuple[Array, Array]:
    """$(|u|, \\alpha)$: the twist rate $|u| = \\sqrt{\\kappa^2 + \\tau^2}$ (1/length; the frame turns
    by $|u|$ per unit length about the axis) and the pitch angle
    $\\alpha = \\operatorname{atan2}(\\tau, \\kappa) \\in [-\\pi/2, \\pi/2]$ for $\\kappa \\ge 0$
    (radians).  Arrays broadcast.  Inverse of `from_polar`."""
    kappa, tau = jnp.asarray(kappa), jnp.asarray(tau)
    return jnp.hypot(kappa, tau), jnp.arctan2(tau, kappa)


def pitch_angle(kappa: ArrayLike, tau: ArrayLike) -> Array:
    """Pitch angle $\\alpha = \\operatorname{atan2}(\\tau, \\kappa)$ (radians): the angle between the
    tangent and the plane normal to the axis; 0 for a ring, $\\pm\\pi/2$ for a straight rod,
    negative for a left-handed helix.  Arrays broadcast."""
    return jnp.arctan2(jnp.asarray(tau), jnp.asarray(kappa))


def helix_angle(kappa: ArrayLike, tau: ArrayLike) -> Array:
    """Helix angle $\\theta = \\pi/2 - \\alpha = \\operatorname{atan2}(\\kappa, \\tau)$ (radians): the
    angle between the tangent and the helix axis (the complement of `pitch_angle`).  Arrays
    broadcast."""
    return jnp.arctan2(jnp.asarray(kappa), jnp.asarray(tau))


def from_radius_angle(radius: ArrayLike, pitch_angle: ArrayLike) -> tuple[Array, Array]:
    """Curvature and torsion $(\\kappa, \\tau) = (\\cos^2\\alpha, \\sin\\alpha\\cos\\alpha)/r$ of the
    helix of radius $r$ (length) and pitch angle $\\alpha$ (radians), as for a coiled spring
    of coil radius $r$.  Arrays broadcast."""
    radius, pitch_angle = jnp.asarray(radius), jnp.asarray(pitch_angle)
    c, s = jnp.cos(pitch_angle), jnp.sin(pitch_angle)
    return c * c / radius, s * c / radius


def height_and_turns(kappa: ArrayLike, tau: ArrayLike, length: ArrayLike) -> tuple[Array, Array]:
    """Axial height $h = L\\tau/|u|$ (length; negative for a left-handed helix) and number of
    turns $L|u|/2\\pi$ of a helix of contour (arc) length $L$ = `length`.  Arrays broadcast.
    Example: `height_and_turns(0.0, 1.0, 2 * pi)` is `(2 pi, 1)`, a straight twisted rod."""
    kappa, tau, length = jnp.asarray(kappa), jnp.asarray(tau), jnp.asarray(length)
    norm_u = jnp.hypot(kappa, tau)
    return length * tau / norm_u, length * norm_u / (2 * jnp.pi)


def helix_centreline(kappa: ArrayLike, tau: ArrayLike, s: ArrayLike) -> Array:
    """Centreline $x(s)$ of the helix with axis $e_z$, starting at $(r, 0, 0)$.

    $x(s) = (r\\cos(|u|s), r\\sin(|u|s), p|u|s)$; arc length is $s$ for any $(\\kappa,\\tau)$.
    Shapes broadcast; the result has a trailing axis of 3.
    """
    kappa, tau, s = jnp.asarray(kappa), jnp.asarray(tau), jnp.asarray(s)
    r, p = radius_pitch(kappa, tau)
    w = jnp.hypot(kappa, tau) * s
    return jnp.stack([r * jnp.cos(w), r * jnp.sin(w), p * w], axis=-1)


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
    return rotation_z(norm_u * s) @ frame0


# -- the unloaded rod -----------------------------------------------------------------------


def intrinsic_helix(rod):
    """$(\\hat\\kappa, \\hat\\tau, \\hat\\varphi, |\\hat u|, |\\hat u| > 0)$ of the unloaded rod's helix
    $u = \\hat u$, with finite derivatives at $\\hat\\kappa = 0$ and $\\hat u = 0$ ($\\hat\\tau$ is
    replaced by 1 when $\\hat u = 0$, where it is unused)."""
    uhat = jnp.asarray(rod.uhat)
    k2 = uhat[0] ** 2 + uhat[1] ** 2
    kappa = safe_sqrt(k2)
    norm = safe_sqrt(k2 + uhat[2] ** 2)
    curved = norm > 0
    safe_tau = jnp.where(curved, uhat[2], 1.0)
    bent = k2 > 0
    phi = jnp.where(bent, jnp.arctan2(jnp.where(bent, uhat[0], 0.0), jnp.where(bent, uhat[1], 1.0)), 0.0)
    return kappa, safe_tau, phi, norm, curved


def unloaded_state(rod, s: ArrayLike) -> tuple[Array, Array]:
    """Centreline point `(..., 3)` and frame `(..., 3, 3)` at arc length(s) `s` of the
    unloaded rod in its *canonical placement*: its intrinsic helix placed as `helix_frame`
    and `helix_centreline` place it (axis $e_z$ through the origin, $x(0) = (\\hat r, 0, 0)$);
    a straight untwisted rod ($\\hat u = 0$) starts at the origin with the identity frame
    (tangent $e_z$).  Exact; differentiable at $\\hat\\kappa = 0$ and $\\hat u = 0$."""
    kappa, tau, phi, norm, curved = intrinsic_helix(rod)
    s = jnp.asarray(s, float_dtype())
    frame = helix_frame(kappa, tau, phi, s)
    x = helix_centreline(kappa, tau, s)
    straight_x = s[..., None] * jnp.array([0.0, 0.0, 1.0], s.dtype).reshape((1,) * s.ndim + (3,))
    eye = jnp.broadcast_to(jnp.eye(3, dtype=s.dtype), frame.shape)
    return jnp.where(curved, x, straight_x), jnp.where(curved, frame, eye)


def unloaded_observables(rod, length: ArrayLike) -> tuple[Array, Array]:
    """Axial extension and end rotation of the unloaded rod of length $L$:
    $(h_0, \\Theta_0) = (L\\hat\\tau/|\\hat u|, L|\\hat u|)$; $(L, 0)$ for $\\hat u = 0$."""
    _, tau, _, norm, curved = intrinsic_helix(rod)
    safe = jnp.where(curved, norm, 1.0)
    return length * jnp.where(curved, tau / safe, 1.0), length * norm
