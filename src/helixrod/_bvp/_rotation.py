"""The total rotation of a solved rod's end about the axis, whole turns included.

An end frame fixes the end's rotation about the axis $e_z$ of the canonical placement
(`axial_ends`) only modulo a full turn; the whole turns a solution holds are a property of
the whole rod.  They are counted by following the director $d_1$ along the rod against a
reference that depends on the tangent alone: $r(t) = Q(t)\\,e_x$, with $Q(t)$ the rotation
by the smallest angle that takes $e_z$ to $t$ (the frame of Fuller's writhe formula:
F. B. Fuller, *Proc. Natl. Acad. Sci. USA* 75, 3557 (1978)),

$$ r(t) = \\Big(1 - \\frac{t_x^2}{1 + t_z},\\; -\\frac{t_x t_y}{1 + t_z},\\; -t_x\\Big), $$

and the angle $\\psi(s)$ about $t$ from $r(t(s))$ to $d_1(s)$, unwrapped along $s$:

$$ \\Theta = \\psi(L) - \\psi(0), $$

the twist and Fuller's writhe together ($2\\pi(\\mathrm{Tw} + \\mathrm{Wr})$ up to a constant).
Since $Q(R_z t) = R_z Q(t) R_z^{T}$, turning the end frame by $\\varphi$ about $e_z$ adds
$\\varphi$ to $\\psi(L)$: two equilibria that meet the same end frame differ in $\\Theta$ by
whole turns exactly, and for a uniform helix about $e_z$ (whose frame turns with the azimuth
of its tangent) $\\Theta$ is the rotation of its end about the axis -- the unloaded rod in the
canonical placement has $\\Theta = \\Theta_0 = L|\\hat u|$, the convention of `axial_ends`.

The stability test counts it on the way (`_variations.piece_variations` with a start frame):
each of its Runge--Kutta steps turns the frame by at most ~1/12 rad, and the angle's steps
are unwrapped one by one (`advance`).  $r$ is singular where the tangent points along
$-e_z$: a rod whose tangent comes within `POLE_DISTANCE` of that direction, or one whose
angle takes a step of more than `LARGEST_STEP`, has no count (NaN).  The count fixes the
whole turns only; the value is then read from the end frame itself (`exact_rotation`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._lie import twist_angle, unwrap_near

#: The largest change of the angle between two steps that is trusted (radians).
LARGEST_STEP = 1.0

#: The least $1 + t_z$ (the tangent's distance from $-e_z$, squared over 2) with a count.
POLE_DISTANCE = 1e-3


def reference_angle(frame: Float[Array, "... 3 3"]) -> tuple[Array, Array]:
    """The angle about the tangent $d_3$ from Fuller's reference $r(d_3)$ to $d_1$, for lab
    frames `(..., 3, 3)` (columns $d_1, d_2, d_3$), in $(-\\pi, \\pi]$ -- the twist of the
    frame about $e_z$ (`twist_angle`, whose swing is $Q$) -- and $1 + t_z$."""
    return twist_angle(frame), 1.0 + frame[..., 2, 2]


class RotationCount(eqx.Module):
    """The angle $\\psi$ followed along a piece: the `angle` at the last frame, the `total`
    of its unwrapped steps, the `largest` step and the least $1 + t_z$ (`pole`)."""

    angle: Float[Array, ""]
    total: Float[Array, ""]
    largest: Float[Array, ""]
    pole: Float[Array, ""]


def start_count(frame: Float[Array, "3 3"]) -> RotationCount:
    """The count at a piece's lab start `frame`."""
    angle, pole = reference_angle(frame)
    zero = jnp.zeros_like(angle)
    return RotationCount(angle, zero, zero, pole)


def advance(count: RotationCount, frame: Float[Array, "3 3"]) -> RotationCount:
    """The count one step on, at the lab `frame`."""
    angle, pole = reference_angle(frame)
    step = unwrap_near(angle - count.angle, 0.0)
    return RotationCount(angle, count.total + step, jnp.maximum(count.largest, jnp.abs(step)), jnp.minimum(count.pole, pole))


def counted_rotation(counts: RotationCount) -> Float[Array, ""]:
    """$\\Theta$ from the counts of the pieces of a rod in sequence (any leading axes), NaN
    where they do not count it (a tangent near $-e_z$, too large a step, non-finite)."""
    total = jnp.sum(counts.total)
    trusted = jnp.isfinite(total) & (jnp.max(counts.largest) <= LARGEST_STEP) & (jnp.min(counts.pole) >= POLE_DISTANCE)
    return jnp.where(trusted, total, jnp.nan)


def exact_rotation(start_frame, end_frame, counted) -> Float[Array, ""]:
    """$\\Theta = \\psi(L) - \\psi(0)$ from the exact start and end frames, its whole turns
    those nearest the `counted` rotation (NaN where that is)."""
    return unwrap_near(reference_angle(end_frame)[0] - reference_angle(start_frame)[0], counted)


def holds_turns(rotation, asked) -> jax.Array:
    """Whether a solution's `rotation` holds the whole turns of the `asked` total rotation:
    within half a turn of it, or either unknown (NaN)."""
    return ~(abs(rotation - asked) >= jnp.pi)  # NumPy in, NumPy out
