"""Helix geometry: conversions between curvature/torsion and radius/pitch/angles, and the
centreline.  A helix of curvature $\\kappa \\ge 0$ and torsion $\\tau$ has $|u| = \\sqrt{\\kappa^2
+ \\tau^2}$, radius $r = \\kappa/|u|^2$, reduced pitch $p = \\tau/|u|^2$ (rise $2\\pi p$ per
turn).  The *pitch angle* $\\alpha$ is the angle between the tangent and the plane normal to
the axis ($\\kappa = |u|\\cos\\alpha$, $\\tau = |u|\\sin\\alpha$); the *helix angle*
$\\theta = \\pi/2 - \\alpha$ is the angle between the tangent and the axis.  $\\tau > 0$ is a
right-handed helix."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike


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
