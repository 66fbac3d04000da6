"""Single-molecule units and the B-DNA backbone helix: from pN, nm and turns to kappa, tau.

Units: forces in pN, lengths in nm, moments (torques) in pN nm, stiffnesses in pN nm^2,
twists (kappa, tau, |u|) in 1/nm, rotations in radians unless a name says `turns`.

Conventions for the observables of a helix of contour (filament) length $L$
(`helixrod.height_and_turns`): the extension is $h = L\\tau/|u|$ and the end rotation
$\\Theta = L|u|$, the angle by which the director frame turns about the helix axis
$a = u/|u|$ from one end to the other.  For a right-handed helix ($\\tau > 0$) both are
positive and a larger $\\Theta$ means *overwound*.  A base pair of DNA is modelled by a
fixed filament length $\\ell$ of the backbone helix (inextensible rod), so per base pair
$h_{bp} = \\ell\\tau/|u|$ (the rise) and $\\Theta_{bp} = \\ell|u| = 2\\pi/(\\text{bp per turn})$
(the helical twist).  The linking-number change of a torsionally constrained molecule whose
axis stays straight (no plectonemes, so the writhe is zero) is
$\\Delta Lk = \\Delta\\Theta/2\\pi$ turns.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from ._geometry import curvature_torsion, height_and_turns
from ._misc import require_valid

# -- units and constants (plain Python floats: no module-level jnp arrays) -------------
BOLTZMANN_CONSTANT = 1.380649e-23
"""$k_B$ in J/K (exact, SI 2019)."""
PICONEWTON = 1e-12
"""1 pN in newtons."""
NANOMETRE = 1e-9
"""1 nm in metres."""
PN_NM = PICONEWTON * NANOMETRE
"""1 pN nm in joules (1e-21 J)."""
ROOM_TEMPERATURE = 298.15
"""Default temperature, kelvin (25 °C)."""


def kT(temperature: ArrayLike = ROOM_TEMPERATURE, unit: str = "pN nm") -> Array:
    """Thermal energy $k_B T$ at `temperature` (kelvin): in pN nm (default) or "J".

    $k_B T$ = 4.116 pN nm at 298.15 K, 4.047 pN nm at 293.15 K.
    """
    temperature = jnp.asarray(temperature, jnp.result_type(float))
    ok = jnp.isfinite(temperature) & (temperature > 0)
    require_valid(ok, "kT: temperature must be finite and > 0 kelvin", temperature)
    energy_joule = jnp.where(ok, BOLTZMANN_CONSTANT * temperature, jnp.nan)
    if unit == "J":
        return energy_joule
    if unit == "pN nm":
        return energy_joule / PN_NM
    raise ValueError(f'kT: unit must be "pN nm" or "J", got {unit!r}')


def persistence_length(stiffness: ArrayLike, temperature: ArrayLike = ROOM_TEMPERATURE) -> Array:
    """Persistence length $A = B/k_BT$ (nm) of a bending or twist stiffness $B$ (pN nm^2).

    The same relation gives the bending persistence from the bending stiffness and the
    twist persistence $C_{tw} = C/k_BT$ from the twist modulus.  A stiffness must be finite
    and > 0: concrete values that are not raise `ValueError`, traced ones give NaN.
    """
    stiffness = jnp.asarray(stiffness, jnp.result_type(float))
    ok = _finite_positive(stiffness)
    require_valid(ok, "persistence_length: stiffness must be finite and > 0 pN nm^2", stiffness)
    return jnp.where(ok, stiffness, jnp.nan) / kT(temperature)


def stiffness_from_persistence(length: ArrayLike, temperature: ArrayLike = ROOM_TEMPERATURE) -> Array:
    """Stiffness $B = k_BT\\,A$ (pN nm^2) of a persistence length $A$ (nm); inverse of
    `persistence_length`.  A length must be finite and > 0 (as `persistence_length`)."""
    length = jnp.asarray(length, jnp.result_type(float))
    ok = _finite_positive(length)
    require_valid(ok, "stiffness_from_persistence: length must be finite and > 0 nm", length)
    return kT(temperature) * jnp.where(ok, length, jnp.nan)


# -- the B-DNA backbone helix ----------------------------------------------------------
def helix_from_bdna(
    rise: ArrayLike = 0.34, bp_per_turn: ArrayLike = 10.5, radius: ArrayLike = 1.0
) -> tuple[Array, Array, Array]:
    """Curvature, torsion and filament length per base pair of a DNA backbone helix.

    A helix of radius `radius` (nm) that rises `rise` nm per base pair and makes one turn
    every `bp_per_turn` base pairs has reduced pitch $p = \\text{rise}\\cdot\\text{bp per
    turn}/2\\pi$, so $(\\kappa, \\tau) = (r, p)/(r^2 + p^2)$ (1/nm, `curvature_torsion`), and
    its filament is $\\ell = \\sqrt{\\text{rise}^2 + (2\\pi r/\\text{bp per turn})^2}$ nm long
    per base pair.  B-DNA defaults: $\\kappa$ = 0.755954, $\\tau$ = 0.429520 1/nm,
    $\\ell$ = 0.688245 nm.  Right-handed: $\\tau > 0$.  Inverse: `bdna_from_helix`.
    """
    dtype = jnp.result_type(float)
    rise, bp_per_turn, radius = (jnp.asarray(x, dtype) for x in (rise, bp_per_turn, radius))
    ok = (rise > 0) & (bp_per_turn > 0) & (radius > 0) & jnp.isfinite(rise * bp_per_turn * radius)
    require_valid(ok, "helix_from_bdna: rise, bp_per_turn and radius must be finite and > 0", rise, bp_per_turn, radius)
    pitch = rise * bp_per_turn / (2 * jnp.pi)
    kappa, tau = curvature_torsion(radius, pitch)
    length_per_bp = jnp.hypot(rise, 2 * jnp.pi * radius / bp_per_turn)
    return tuple(jnp.where(ok, x, jnp.nan) for x in (kappa, tau, length_per_bp))


def bdna_from_helix(kappa: ArrayLike, tau: ArrayLike, length_per_bp: ArrayLike) -> tuple[Array, Array, Array]:
    """Inverse of `helix_from_bdna`: `(rise, bp_per_turn, radius)` in nm and base pairs.

    rise $= \\ell\\tau/|u|$, base pairs per turn $= 2\\pi/(\\ell|u|)$, radius $= \\kappa/|u|^2$.
    Needs a helix ($|u| > 0$, finite) and $\\ell > 0$: concrete inputs that break this raise
    `ValueError`, traced ones give NaN.
    """
    kappa, tau, length_per_bp = _checked_helix(kappa, tau, length_per_bp, "bdna_from_helix", "length_per_bp")
    rise, turns_per_bp = height_and_turns(kappa, tau, length_per_bp)
    radius = kappa / (kappa**2 + tau**2)
    return rise, 1.0 / turns_per_bp, radius


# -- observables <-> helix ---------------------------------------------------------------
def observables_from_helix(kappa: ArrayLike, tau: ArrayLike, length: ArrayLike) -> tuple[Array, Array]:
    """Extension $h = L\\tau/|u|$ and end rotation $\\Theta = L|u|$ (radians) of a helix of
    contour length $L$ = `length` (`height_and_turns`).  Needs a helix ($\\kappa, \\tau$ finite,
    not both 0: a straight untwisted filament has no axis) and $L$ finite and > 0: concrete
    inputs that break this raise `ValueError`, traced ones give NaN."""
    height, turns = height_and_turns(*_checked_helix(kappa, tau, length, "observables_from_helix", "length"))
    return height, 2 * jnp.pi * turns


def helix_from_observables(extension: ArrayLike, rotation: ArrayLike, length: ArrayLike) -> tuple[Array, Array]:
    """Inverse of `observables_from_helix`: $(\\kappa, \\tau)$ from extension $h$, end
    rotation $\\Theta$ (radians) and contour length $L$.

    $|u| = \\Theta/L$, $\\tau = h|u|/L$, $\\kappa = |u|\\sqrt{1 - (h/L)^2}$.  Needs $\\Theta > 0$
    and $|h| < L$ (an inextensible filament cannot be longer than its contour);
    concrete inputs that break this raise `ValueError`, traced ones give NaN.
    """
    dtype = jnp.result_type(float)
    extension, rotation, length = (jnp.asarray(x, dtype) for x in (extension, rotation, length))
    ratio = extension / length
    ok = (length > 0) & (rotation > 0) & (jnp.abs(ratio) < 1) & jnp.isfinite(ratio * rotation)
    require_valid(
        ok,
        "helix_from_observables: need length > 0, rotation > 0 and |extension| < length",
        extension,
        rotation,
        length,
    )
    norm_u = rotation / length
    # Double where keeps the sqrt and its gradient finite at |h| = L.
    safe = jnp.where(ok, 1.0 - ratio**2, 1.0)
    kappa = jnp.where(ok, norm_u * jnp.sqrt(safe), jnp.nan)
    tau = jnp.where(ok, norm_u * ratio, jnp.nan)
    return kappa, tau


def _finite_positive(x):
    return jnp.isfinite(x) & (x > 0)


def _checked_helix(kappa, tau, length, owner: str, length_name: str):
    """`(kappa, tau, length)` as float arrays, a helix ($\\kappa, \\tau$ finite, not both 0)
    and a length finite and > 0: concrete values that are not raise `ValueError` naming
    `owner`, traced ones make kappa and tau NaN."""
    dtype = jnp.result_type(float)
    kappa, tau, length = (jnp.asarray(x, dtype) for x in (kappa, tau, length))
    ok = _finite_positive(jnp.hypot(kappa, tau)) & _finite_positive(length)
    require_valid(ok, f"{owner}: need a helix (kappa, tau finite, not both 0) and {length_name} > 0", kappa, tau, length)
    return jnp.where(ok, kappa, jnp.nan), jnp.where(ok, tau, jnp.nan), length


def _contour(n_bp, length_per_bp, owner: str):
    """The contour length of `n_bp` base pairs of `length_per_bp` (default B-DNA's), both
    finite and > 0 (`ValueError` naming `owner` for concrete ones; NaN for traced ones)."""
    n_bp = jnp.asarray(n_bp, jnp.result_type(float))
    ell = helix_from_bdna()[2] if length_per_bp is None else jnp.asarray(length_per_bp, jnp.result_type(float))
    ok = _finite_positive(n_bp) & _finite_positive(ell)
    require_valid(ok, f"{owner}: n_bp and length_per_bp must be finite and > 0", n_bp, ell)
    return jnp.where(ok, n_bp * ell, jnp.nan)


def tweezer_from_helix(
    kappa: ArrayLike, tau: ArrayLike, n_bp: ArrayLike = 1, *, length_per_bp: ArrayLike | None = None
) -> tuple[Array, Array]:
    """Extension (nm) and rotation (rad) of a molecule of `n_bp` base pairs whose backbone
    helix is $(\\kappa, \\tau)$; `n_bp = 1` (default) gives per-base-pair values.

    `length_per_bp` is the backbone filament length per base pair, held fixed (default:
    the B-DNA value of `helix_from_bdna()`).
    """
    return observables_from_helix(kappa, tau, _contour(n_bp, length_per_bp, "tweezer_from_helix"))


def helix_from_tweezer(
    extension: ArrayLike, rotation: ArrayLike, n_bp: ArrayLike = 1, *, length_per_bp: ArrayLike | None = None
) -> tuple[Array, Array]:
    """$(\\kappa, \\tau)$ (1/nm) of the backbone helix from the total extension (nm) and total
    rotation (rad) of a molecule of `n_bp` base pairs (`n_bp = 1`: per-base-pair values).
    Inverse of `tweezer_from_helix`.  The backbone helix alone, without thermal
    fluctuations: a measured extension is shortened by them (~15 % at 1 pN), so fit measured
    tweezer curves with `TweezerData` and `tweezer_response` instead."""
    return helix_from_observables(extension, rotation, _contour(n_bp, length_per_bp, "helix_from_tweezer"))


def _reference(reference):
    if reference is None:
        return helix_from_bdna()
    return tuple(jnp.asarray(x, jnp.result_type(float)) for x in reference)


def changes_from_helix(
    kappa: ArrayLike,
    tau: ArrayLike,
    n_bp: ArrayLike = 1,
    *,
    reference: tuple[ArrayLike, ArrayLike, ArrayLike] | None = None,
) -> tuple[Array, Array]:
    """Extension change $\\Delta h$ (nm) and linking-number change $\\Delta Lk$ (turns) of a
    molecule of `n_bp` base pairs, relative to the `reference` helix.

    `reference` = `(kappa0, tau0, length_per_bp)` (default `helix_from_bdna()`); the
    filament length per base pair is that of the reference.  $\\Delta Lk = \\Delta\\Theta/2\\pi$
    assumes a straight axis (writhe 0).  Positive $\\Delta Lk$ is overwinding.
    """
    kappa0, tau0, length_per_bp = _reference(reference)
    length = _contour(n_bp, length_per_bp, "changes_from_helix")
    h, theta = observables_from_helix(kappa, tau, length)
    h0, theta0 = observables_from_helix(kappa0, tau0, length)
    return h - h0, (theta - theta0) / (2 * jnp.pi)


def helix_from_changes(
    extension_change: ArrayLike,
    linking_number_change: ArrayLike,
    n_bp: ArrayLike = 1,
    *,
    reference: tuple[ArrayLike, ArrayLike, ArrayLike] | None = None,
) -> tuple[Array, Array]:
    """Inverse of `changes_from_helix`: $(\\kappa, \\tau)$ from the extension change (nm) and
    linking-number change (turns) of `n_bp` base pairs relative to the `reference` helix."""
    kappa0, tau0, length_per_bp = _reference(reference)
    length = _contour(n_bp, length_per_bp, "helix_from_changes")
    h0, theta0 = observables_from_helix(kappa0, tau0, length)
    extension = h0 + jnp.asarray(extension_change)
    rotation = theta0 + 2 * jnp.pi * jnp.asarray(linking_number_change)
    return helix_from_observables(extension, rotation, length)


def radians_to_turns(angle: ArrayLike) -> Array:
    """Radians to turns (divide by $2\\pi$)."""
    return jnp.asarray(angle) / (2 * math.pi)


def turns_to_radians(turns: ArrayLike) -> Array:
    """Turns to radians (multiply by $2\\pi$)."""
    return 2 * math.pi * jnp.asarray(turns)
