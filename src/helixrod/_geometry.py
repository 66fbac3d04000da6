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
    """$(r, p) = (\\kappa, \\tau)/(\\kappa^2+\\tau^2)$; the rise per turn is $2\\pi p$."""
    kappa, tau = jnp.asarray(kappa), jnp.asarray(tau)
    norm2 = kappa**2 + tau**2
    return kappa / norm2, tau / norm2


def curvature_torsion(radius: ArrayLike, pitch: ArrayLike) -> tuple[Array, Array]:
    """Inverse of `radius_pitch`: $(\\kappa, \\tau) = (r, p)/(r^2 + p^2)$."""
    radius, pitch = jnp.asarray(radius), jnp.asarray(pitch)
    norm2 = radius**2 + pitch**2
    return radius / norm2, pitch / norm2


def from_polar(norm_u: ArrayLike, pitch_angle: ArrayLike) -> tuple[Array, Array]:
    """$(\\kappa, \\tau) = |u| (\\cos\\alpha, \\sin\\alpha)$ from $|u|$ and the pitch angle."""
    norm_u, pitch_angle = jnp.asarray(norm_u), jnp.asarray(pitch_angle)
    return norm_u * jnp.cos(pitch_angle), norm_u * jnp.sin(pitch_angle)


def to_polar(kappa: ArrayLike, tau: ArrayLike) -> tuple[Array, Array]:
    """$(|u|, \\alpha)$ with the pitch angle $\\alpha = \\operatorname{atan2}(\\tau, \\kappa)$."""
    kappa, tau = jnp.asarray(kappa), jnp.asarray(tau)
    return jnp.hypot(kappa, tau), jnp.arctan2(tau, kappa)


def pitch_angle(kappa: ArrayLike, tau: ArrayLike) -> Array:
    """Angle between the tangent and the plane normal to the axis."""
    return jnp.arctan2(jnp.asarray(tau), jnp.asarray(kappa))


def helix_angle(kappa: ArrayLike, tau: ArrayLike) -> Array:
    """Angle between the tangent and the helix axis, $\\pi/2 - \\alpha$."""
    return jnp.arctan2(jnp.asarray(kappa), jnp.asarray(tau))


def from_radius_angle(radius: ArrayLike, pitch_angle: ArrayLike) -> tuple[Array, Array]:
    """$(\\kappa, \\tau) = (\\cos^2\\alpha, \\sin\\alpha\\cos\\alpha)/r$ from radius and pitch angle."""
    radius, pitch_angle = jnp.asarray(radius), jnp.asarray(pitch_angle)
    c, s = jnp.cos(pitch_angle), jnp.sin(pitch_angle)
    return c * c / radius, s * c / radius


def height_and_turns(kappa: ArrayLike, tau: ArrayLike, length: ArrayLike) -> tuple[Array, Array]:
    """Axial height $L\\tau/|u|$ and number of turns $L|u|/2\\pi$ of a helix of contour length L."""
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
