"""A DNA molecule in a tweezer: the rod's own response plus its thermal fluctuations.

A molecule of $N$ base pairs is held at an axial force $F$ and either turned by a number of
turns $n$ (magnetic tweezers, linking number counted from the torque-free molecule at that
force) or held at a torque $\\Gamma$ (a free swivel is $\\Gamma = 0$: optical-tweezer
force-distance curves).  Three pieces of physics, each written as a free energy per unit
contour length $L_0 = N\\,h_0$ ($h_0$ the rise of the unloaded helix, 0.34 nm for B-DNA), so
that extensions and rotations are its derivatives and the phases compare by it:

1. **The rod itself** (intrinsic, enthalpic): the uniform helix of the rod under the axial
   wrench $(F, \\Gamma)$ (`bulk_helix`, nonlinear in the load), filament length $\\ell$ per
   base pair.  Its Gibbs free energy per base pair is $\\ell\\,[W(u) - F u_3/|u| - \\Gamma|u|]$
   (zero for the unloaded helix); by the envelope theorem its force and torque derivatives
   are minus the extension $\\ell u_3/|u|$ and the rotation $\\ell|u|$.  The rod's twist
   stiffness at constant force $C_0(F)$ (pN nm^2 per unit contour length) is the inverse
   torsional compliance of that helix at $\\Gamma = 0$, so bend-twist coupling of the rod
   enters as $C - g^2/S$ (Gore et al., Nature 442, 836 (2006)).
2. **Bending fluctuations**: the worm-like chain of bending persistence length $A$.  Its
   relative extension $z(F)$ is the inverse of the interpolation of Bouchiat et al.
   (Biophys. J. 76, 409 (1999)), $FA/k_BT = 1/(4(1-z)^2) - 1/4 + z + \\sum_{i=2}^{7} a_i z^i$;
   against the exact infinite-chain WLC (the ground state of the rotor Hamiltonian of
   Marko and Siggia, Macromolecules 28, 8759 (1995)) $z$ is within 0.33 % at 0.005-0.01 pN,
   0.1 % at 0.03 pN, 2.4e-4 at 0.1 pN and 5e-6 from 1 pN up (tests: `test_tweezer`).  The
   stretch of the rod is added to it as in the extensible WLC: extension
   $= L_{int}(F, \\Gamma) - L_0(1 - z)$, which is Odijk's $L_0(1 - \\frac12\\sqrt{k_BT/FA} +
   F/S)$ at high force and for a linear rod.  Free energy per contour length
   $\\int_0^F (1 - z)\\,dF'$, in closed form from the polynomial.
3. **Twist fluctuations** (Moroz and Nelson, PNAS 94, 14418 (1997); Macromolecules 31, 6333
   (1998)): bending fluctuations soften the twist stiffness at constant force to
   $C_{eff} = C_0\\,(1 - c)$, $c = \\frac{C_0}{4Ak_BT}\\sqrt{k_BT/(AF)}$ (about 351 instead of
   410 pN nm^2 at 1 pN for A = 50 nm).  Written as a torsional compliance in series with the
   rod's, $t(F) = 1/C_{eff} - 1/C_0$, with free energy $-\\Gamma^2 t(F)/2$ per contour length;
   its force derivative is the drop of the extension with turns before buckling,
   $\\frac{\\Gamma^2}{2} t'(F) L_0$.  The theory is an expansion in $c$: points with
   $\\Gamma \\ne 0$ and $c > 1/2$ (below ~0.08 pN for DNA) are flagged `outside_model_range`.
4. **Buckling and plectonemes** (Marko, Phys. Rev. E 76, 021926 (2007)): a plectonemic phase
   of zero extension stores linking number with the twist persistence $P$, free energy
   $-\\Gamma^2/(2k_BTP)$ per contour length.  The phases coexist at the torque where the
   free energies are equal; with the extended phase's free energy to second order in
   $\\Gamma$, $-g(F) - \\Gamma^2/(2C_{eff})$ ($g(F)$ = minus the free energy of the extended
   molecule at zero torque: $\\int_0^F z\\,dF'$ plus the rod's stretching energy), this is
   Marko's closed form

   $$\\Gamma_b = \\sqrt{\\frac{2g(F)}{1/(k_BTP) - 1/C_{eff}}}.$$

   With turns imposed, the molecule is extended while its rotation per base pair is below
   that of the extended phase at $\\Gamma_b$ ($r_s$), coexists (torque plateau $\\Gamma_b$,
   extended fraction $x = (r_p - r)/(r_p - r_s)$ with $r_p = h_0\\Gamma_b/(k_BTP)$, so the
   extension falls linearly with turns) and is fully plectonemic (extension 0) beyond $r_p$.
   Under a controlled torque it is extended below $\\Gamma_b$ and plectonemic above.  The
   plectoneme end loops, the multi-plectoneme entropy and the melting of underwound DNA
   above ~0.5 pN are not in the model (negative turns buckle like positive ones).

Rotations are counted from the torque-free molecule at the same force, in both phases.  The
default $P$ = 24 nm is the plectoneme twist persistence Marko (2007) uses for ~0.15 M
monovalent salt; it depends on the buffer: fit it where the data show plectonemes.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._compile import filter_jit
from ._bvp import helix_under_wrench
from ._dna import ROOM_TEMPERATURE, helix_from_bdna
from ._dna import kT as thermal_energy
from ._misc import attainable, float_dtype, inverse_small, is_concrete, require_valid, safe_sqrt
from ._rod import check_one_rod
from ._status import RESULTS, raise_if_failed

#: Coefficients $a_2 \\ldots a_7$ of the WLC interpolation of Bouchiat et al. (1999).
BOUCHIAT_COEFFICIENTS = (-0.5164228, -2.737418, 16.07497, -38.87607, 39.49944, -14.17718)
#: Phases of `TweezerResponse.phase`, by code.
PHASES = ("extended", "coexisting", "plectonemic")
#: Default twist persistence of the plectonemic phase, nm (Marko 2007, ~0.15 M salt).
PLECTONEME_TWIST_PERSISTENCE = 24.0
#: Largest Moroz-Nelson correction c accepted where a torque acts (an expansion in c).
MAX_TWIST_CORRECTION = 0.5

_BISECTIONS = 64
_CHORD_STEPS = 6
_TRIAL_NEWTON_STEPS = 16
_NEWTON_STEP_TOLERANCE = 1e-10  # in the scaled unknowns of helix_under_wrench; two more steps follow
# Stands for an infinite buckling torque or rotation inside the computation (finite: see
# there; within float32's range, 3e38).
NO_BUCKLING = 1e30


# -- the worm-like chain -------------------------------------------------------------------
def _bouchiat_force(z):
    """$FA/k_BT$ of relative extension `z` (dimensionless)."""
    poly = sum(a * z ** (i + 2) for i, a in enumerate(BOUCHIAT_COEFFICIENTS))
    return 0.25 / (1.0 - z) ** 2 - 0.25 + z + poly


def _bouchiat_integral(z):
    """$\\int_0^z FA/k_BT\\,dz'$ in closed form."""
    poly = sum(a * z ** (i + 3) / (i + 3) for i, a in enumerate(BOUCHIAT_COEFFICIENTS))
    return 0.25 / (1.0 - z) - 0.25 - 0.25 * z + 0.5 * z * z + poly


@jax.custom_jvp
def _wlc_relative_extension(f):
    """Relative extension $z$ at dimensionless force $f = FA/k_BT \\ge 0$ (bisection: the
    interpolation is increasing on [0, 1))."""

    def step(_, bracket):
        lo, hi = bracket
        mid = 0.5 * (lo + hi)
        below = _bouchiat_force(mid) < f
        return jnp.where(below, mid, lo), jnp.where(below, hi, mid)

    lo, hi = jnp.zeros_like(f), jnp.ones_like(f)
    lo, hi = jax.lax.fori_loop(0, _BISECTIONS, step, (lo, hi))
    return 0.5 * (lo + hi)


@_wlc_relative_extension.defjvp
def _wlc_jvp(primals, tangents):
    (f,), (df,) = primals, tangents
    z = _wlc_relative_extension(f)
    slope = jax.grad(lambda y: _bouchiat_force(y))
    return z, df / jnp.vectorize(slope)(z)


def _persistence(persistence_length, owner: str) -> Array:
    """A bending persistence (nm), finite and > 0: concrete values that are not raise
    `ValueError` naming `owner`, traced ones become NaN."""
    A = jnp.asarray(persistence_length, float_dtype())
    ok = jnp.isfinite(A) & (A > 0)
    require_valid(ok, f"{owner}: persistence_length must be finite and > 0 nm", A)
    return jnp.where(ok, A, jnp.nan)


def _pulling_force(force, owner: str) -> Array:
    """A force (pN) on a worm-like chain, finite and >= 0: concrete values that are not
    raise `ValueError` naming `owner` (traced ones are the caller's to make NaN)."""
    force = jnp.asarray(force, float_dtype())
    require_valid(jnp.isfinite(force) & (force >= 0), f"{owner}: force must be finite and >= 0 pN", force)
    return force


def _dimensionless_force(force, persistence_length, temperature):
    return force * persistence_length / thermal_energy(temperature)


def wlc_force(
    relative_extension: ArrayLike, persistence_length: ArrayLike = 50.0, temperature: ArrayLike = ROOM_TEMPERATURE
) -> Array:
    """Force (pN) of an inextensible worm-like chain at relative extension $z$ = extension /
    contour length, bending persistence `persistence_length` (nm): Bouchiat et al. (1999).
    $0 \\le z < 1$: a concrete $z$ outside raises `ValueError`, a traced one gives NaN (as a
    persistence that is not finite and > 0)."""
    z = jnp.asarray(relative_extension, float_dtype())
    ok = (z >= 0) & (z < 1)
    require_valid(ok, "wlc_force: relative_extension must be in [0, 1)", z)
    safe = jnp.where(ok, z, 0.5)
    force = thermal_energy(temperature) / _persistence(persistence_length, "wlc_force") * _bouchiat_force(safe)
    return jnp.where(ok, force, jnp.nan)


def wlc_extension(force: ArrayLike, persistence_length: ArrayLike = 50.0, temperature: ArrayLike = ROOM_TEMPERATURE) -> Array:
    """Relative extension $z$ (extension / contour length) of an inextensible worm-like chain
    at `force` (pN), the inverse of `wlc_force`; differentiable (implicit function).
    $F \\ge 0$: a concrete negative or non-finite force raises `ValueError`, a traced one
    gives NaN (a persistence as `wlc_force`)."""
    force = _pulling_force(force, "wlc_extension")
    f = _dimensionless_force(force, _persistence(persistence_length, "wlc_extension"), temperature)
    ok = jnp.isfinite(f) & (f >= 0)
    return jnp.where(ok, _wlc_relative_extension(jnp.where(ok, f, 1.0)), jnp.nan)


def wlc_free_energy(force: ArrayLike, persistence_length: ArrayLike = 50.0, temperature: ArrayLike = ROOM_TEMPERATURE) -> Array:
    """$\\int_0^F z\\,dF'$ (pN, i.e. pN nm per nm of contour): minus the Gibbs free energy per
    contour length of a worm-like chain held at `force`, in closed form from the
    interpolation ($fz - \\int_0^z f\\,dz'$ in units of $k_BT/A$)."""
    force = _pulling_force(force, "wlc_free_energy")
    persistence_length = _persistence(persistence_length, "wlc_free_energy")
    energy_unit = thermal_energy(temperature) / persistence_length
    f = force / energy_unit
    z = wlc_extension(force, persistence_length, temperature)
    return energy_unit * (f * z - _bouchiat_integral(z))


def moroz_nelson_twist_modulus(
    twist_modulus: ArrayLike, force: ArrayLike, persistence_length: ArrayLike = 50.0, temperature: ArrayLike = ROOM_TEMPERATURE
) -> Array:
    """The effective twist modulus (pN nm^2) at constant force of a molecule with intrinsic
    twist modulus $C$ (pN nm^2) and bending persistence $A$ (nm) at `force` (pN):
    $C(1 - \\frac{C}{4Ak_BT}\\sqrt{k_BT/(AF)})$ (Moroz and Nelson 1997, valid while the
    correction is small; NaN where it reaches 1).  $C$ and $F$ finite and > 0: concrete
    values that are not raise `ValueError`, traced ones give NaN."""
    kT = thermal_energy(temperature)
    C = jnp.asarray(twist_modulus, float_dtype())
    force = jnp.asarray(force, float_dtype())
    ok = jnp.isfinite(C) & (C > 0) & jnp.isfinite(force) & (force > 0)
    require_valid(ok, "moroz_nelson_twist_modulus: twist_modulus and force must be finite and > 0", C, force)
    A = _persistence(persistence_length, "moroz_nelson_twist_modulus")
    c = C / (4 * A * kT) * jnp.sqrt(kT / (A * jnp.where(ok, force, 1.0)))
    return jnp.where(ok & (c < 1), C * (1 - c), jnp.nan)


# -- the response --------------------------------------------------------------------------
class TweezerResponse(eqx.Module):
    """The state of molecules in a tweezer (`tweezer_response`); every field per point.

    `extension` (nm) and `torque` (pN nm) and `turns` (from the torque-free molecule at the
    same force) -- one of the last two was imposed, the other is the response; `phase` (a code
    into `PHASES`: 0 extended, 1 coexisting, 2 plectonemic) and `extended_fraction` (the
    fraction of the contour in the extended phase).  The extension in parts (each times the
    extended fraction): `intrinsic_extension`, the rod's uniform helix under $(F, \\Gamma)$;
    `bending_extension` $= -L_0(1 - z)$, the worm-like chain's shortening;
    `twist_extension`, the shortening by twist fluctuations under torque.  At the force:
    `twist_modulus` $C_0$ of the rod at constant force, `effective_twist_modulus` $C_{eff}$
    (Moroz-Nelson), `buckling_torque` $\\Gamma_b > 0$ (inf: no buckling), all per unit
    contour length.  `result`: a `RESULTS` code per point (`invalid_input`,
    `outside_model_range`, or the bulk-helix solver's); `ok`.
    """

    extension: Float[Array, "*batch"]
    torque: Float[Array, "*batch"]
    turns: Float[Array, "*batch"]
    phase: Int[Array, "*batch"]
    extended_fraction: Float[Array, "*batch"]
    intrinsic_extension: Float[Array, "*batch"]
    bending_extension: Float[Array, "*batch"]
    twist_extension: Float[Array, "*batch"]
    twist_modulus: Float[Array, "*batch"]
    effective_twist_modulus: Float[Array, "*batch"]
    buckling_torque: Float[Array, "*batch"]
    result: RESULTS

    @property
    def ok(self):
        """Whether each point was computed within the model (`result` successful)."""
        return self.result == RESULTS.successful


def filament_and_rise(rod, length_per_bp=None, owner: str | None = None) -> tuple[Array, Array]:
    """The filament length $\\ell$ per base pair (default: the B-DNA backbone of
    `helix_from_bdna`) and the rise $h_0 = \\ell\\,\\hat u_3/|\\hat u|$ of the unloaded helix.
    With an `owner` (a public function's name), concrete values must have both finite and
    > 0 (`ValueError` naming them): a molecule's contour $L_0 = N h_0$ is positive, so the
    backbone helix must rise along its axis ($\\hat u_3 > 0$, right-handed as B-DNA's);
    traced ones are flagged by `response_point`."""
    dtype = float_dtype()
    ell = jnp.asarray(helix_from_bdna()[2] if length_per_bp is None else length_per_bp, dtype)
    uhat = jnp.asarray(rod.uhat, dtype)
    rise = ell * uhat[2] / jnp.linalg.norm(uhat)
    if owner is not None and is_concrete(ell):
        if ell.ndim != 0 or not (np.isfinite(float(ell)) and float(ell) > 0):
            raise ValueError(f"{owner}: length_per_bp must be a finite scalar > 0 nm, got {np.asarray(ell)}")
    if owner is not None and is_concrete(rise) and not (np.isfinite(float(rise)) and float(rise) > 0):
        raise ValueError(
            f"{owner}: the rod's unloaded helix must rise along its axis (uhat[2] > 0: a right-handed backbone "
            f"helix, as B-DNA's), got uhat = {np.asarray(uhat).tolist()}"
        )
    return ell, rise


def _bulk(rod, ell, force, torque, guess=None):
    """The twist $u$ of the rod's helix under (force, torque) and its `RESULTS` code
    (`helix_under_wrench`; its extension and rotation per base pair: `_extension_and_rotation`,
    its Gibbs free energy: `_gibbs`).

    A plain Newton iteration (no derivatives) from the twist `guess` (default the unloaded
    helix) goes first, stopped once its steps are at round-off; where it does not converge
    the point is flagged and the differentiated part runs at zero load, whose root (the
    unloaded helix) is known.  Derivatives are those of the implicit function theorem at
    the frozen root (`newton_derivatives`), to any order -- the twist stiffness is itself a
    derivative, differentiated again by a fit -- with dense solves that never raise when a
    least-squares solver probes with a non-finite tangent."""
    trial, trial_result = helix_under_wrench(
        rod, ell, force, torque, guess, max_steps=_TRIAL_NEWTON_STEPS, light=True,
        step_tolerance=attainable(_NEWTON_STEP_TOLERANCE, jnp.result_type(force)),
    )
    good = (trial_result == RESULTS.successful) & jnp.all(jnp.isfinite(trial))
    root = jnp.where(good, trial, jnp.asarray(rod.uhat))
    u, result = helix_under_wrench(
        rod, ell, jnp.where(good, force, 0.0), jnp.where(good, torque, 0.0), root, max_steps=0, newton_derivatives=True
    )
    return u, RESULTS.where(good, result, RESULTS.residual_above_tolerance)


def _extension_and_rotation(ell, u):
    """The extension $\\ell u_3/|u|$ and rotation $\\ell|u|$ per base pair of a helix of twist `u`."""
    norm = jnp.linalg.norm(u)
    return ell * u[2] / norm, ell * norm


def _gibbs(rod, ell, u, extension, rotation, force, torque):
    """The Gibbs free energy per base pair of the rod's helix of twist `u` (its `extension`
    and `rotation` per base pair, `_extension_and_rotation`) under (force, torque)."""
    return ell * rod.energy(u) - force * extension - torque * rotation


def _valid_point(force, A, P, ell, rise, kT):
    """Whether one point's force, persistences, filament length, rise and $k_BT$ are all
    finite and > 0 (traced)."""
    return jnp.all(jnp.stack([jnp.isfinite(x) & (x > 0) for x in (force, A, P, ell, rise, kT)]))


def response_point(rod, ell, rise, force, control, torque_controlled, persistence_length, plectoneme_twist, kT):
    """One base pair's extension, rotation and state at `force` under `control` (a torque if
    `torque_controlled`, else a rotation per base pair in radians); helper of
    `tweezer_response` and of the tweezer fit model, unbatched and traced.  `torque_controlled`
    is a traced boolean or a Python bool; `True` as a Python bool skips the iteration that
    turned points need (one solve of the rod instead of `_CHORD_STEPS`), and with `control`
    the Python number 0 (a free swivel) the solve at zero torque is the answer.

    Returns `(extension_per_bp, rotation_per_bp, torque, phase, fraction, parts, moduli,
    result)` with `parts = (intrinsic, bending, twist)` per base pair and `moduli =
    (C0, C_eff, buckling_torque)`; the values are computed (finite where possible) also
    where `result` flags the point, so a fit sees a smooth cost."""
    dtype = float_dtype()
    A, P = persistence_length, plectoneme_twist
    free_swivel = torque_controlled is True and isinstance(control, (int, float)) and control == 0
    controlled = jnp.asarray(torque_controlled)
    control = jnp.asarray(control, dtype)
    good_input = _valid_point(force, A, P, ell, rise, kT) & jnp.isfinite(control)
    F = jnp.where(good_input, force, 1.0)
    control = jnp.where(good_input, control, 0.0)

    # The rod at zero torque, and its torsional compliance there (one tangent).
    def rotation_at(torque):
        u, result = _bulk(rod, ell, F, torque)
        return _extension_and_rotation(ell, u)[1], (u, result)

    zero = jnp.zeros((), dtype)
    rotation0, compliance, (root0, result0) = jax.jvp(rotation_at, (zero,), (jnp.ones_like(zero),), has_aux=True)
    # Outside the tangent in the torque (which only the compliance needs).
    extension0 = _extension_and_rotation(ell, root0)[0]
    gibbs0 = _gibbs(rod, ell, root0, extension0, rotation0, F, zero)
    C0 = rise / compliance

    # Twist fluctuations (Moroz-Nelson) as a series compliance t(F) and its force derivative.
    c = C0 / (4 * A * kT) * jnp.sqrt(kT / (A * F))
    c_safe = jnp.minimum(c, MAX_TWIST_CORRECTION)
    series = c_safe / (C0 * (1 - c_safe))
    series_slope = -c_safe / (2 * F) / (C0 * (1 - c_safe) ** 2)
    C_eff = 1.0 / (1.0 / C0 + series)

    # Bending fluctuations: extension and free energy per contour length.
    unit = kT / A
    z = _wlc_relative_extension(F / unit)
    wlc_gibbs = F - unit * (F / unit * z - _bouchiat_integral(z))  # integral of (1 - z) dF
    stretch_energy = -(gibbs0 / rise + wlc_gibbs)  # g(F) > 0

    # Buckling torque (Marko 2007); NO_BUCKLING where the plectoneme is the stiffer phase.
    # Every branch stays finite (also those a `where` discards): reverse-mode derivatives
    # through the fit multiply by zero cotangents there, and 0 * inf would be NaN.
    plectoneme_modulus = kT * P
    softer = 1.0 / plectoneme_modulus - 1.0 / C_eff
    buckles = softer > 0
    buckling = jnp.where(
        buckles, safe_sqrt(2 * jnp.maximum(stretch_energy, 0.0) / jnp.where(buckles, softer, 1.0)), NO_BUCKLING
    )

    # Rotation per base pair of the extended phase at the buckling torque, to the same
    # (second) order as the coexistence condition, and of the plectonemic phase.
    sign = jnp.where(control < 0, -1.0, 1.0)
    plateau = sign * jnp.where(buckles, buckling, 0.0)
    r_s = jnp.where(buckles, rise * buckling / C_eff, NO_BUCKLING)
    r_p = jnp.where(buckles, rise * buckling / plectoneme_modulus, 2 * NO_BUCKLING)

    # The extended phase's torque: given, or by chord steps on its rotation (slope rise/C_eff,
    # converging like the rod's nonlinearity, a few % per step, each Newton solve started
    # from the last); the last solve is the answer.  `torque_controlled=True` (a Python
    # bool) needs no steps: one solve at the held torque.
    r = jnp.abs(control)
    target = jnp.minimum(r, r_s) * sign
    beyond_plateau = controlled & (jnp.abs(control) >= buckling)
    held = jnp.where(beyond_plateau, plateau, control)

    def extended_at(torque, guess):
        u, result = _bulk(rod, ell, F, torque, guess)
        extension, rotation = _extension_and_rotation(ell, u)
        return u, extension, rotation - rotation0 + rise * torque * series, result

    if free_swivel:
        torque_extended, intrinsic, rotation_extended, result_extended = zero, extension0, zero, result0
    elif torque_controlled is True:
        _, intrinsic, rotation_extended, result_extended = extended_at(held, root0)
        torque_extended = held
    else:

        def chord(_, state):
            torque, guess = state[0], state[-1]
            u, extension, rotation, result = extended_at(torque, guess)
            step = torque + (target - rotation) * C_eff / rise
            return jnp.where(controlled, held, step), torque, extension, rotation, result, u

        start = jnp.where(controlled, held, target * C_eff / rise)
        initial = (start, start, zero, zero, result0, root0)
        _, torque_extended, intrinsic, rotation_extended, result_extended, _ = jax.lax.fori_loop(
            0, _CHORD_STEPS, chord, initial
        )
    bending = -rise * (1 - z)
    twist = rise * 0.5 * torque_extended**2 * series_slope

    # Phases.
    coexisting = ~controlled & (r > r_s) & (r < r_p)
    plectonemic = jnp.where(controlled, beyond_plateau, r >= r_p)
    fraction = jnp.where(coexisting, (r_p - r) / jnp.where(coexisting, r_p - r_s, 1.0), 1.0)
    fraction = jnp.where(plectonemic, 0.0, fraction)
    phase = jnp.where(plectonemic, 2, jnp.where(coexisting, 1, 0))
    torque = jnp.where(
        controlled,
        control,
        jnp.where(plectonemic, sign * plectoneme_modulus * r / rise, jnp.where(coexisting, plateau, torque_extended)),
    )
    rotation = jnp.where(
        controlled,
        jnp.where(plectonemic, rise * control / plectoneme_modulus, rotation_extended),
        control,
    )
    parts = tuple(fraction * p for p in (intrinsic, bending, twist))
    extension = parts[0] + parts[1] + parts[2]

    twisted = control != 0  # a torque acts (turns or a torque imposed)
    result = RESULTS.where(result_extended == RESULTS.successful, result0, result_extended)
    result = RESULTS.where(twisted & (c > MAX_TWIST_CORRECTION), RESULTS.outside_model_range, result)
    result = RESULTS.where(good_input & jnp.isfinite(extension), result, RESULTS.invalid_input)
    return extension, rotation, torque, phase, fraction, parts, (C0, C_eff, buckling), result


def _thermal_energy_of(temperature, owner: str) -> Array:
    """$k_BT$ (pN nm) at a scalar `temperature` (kelvin, traced or not): a concrete one must
    be finite and > 0 (`ValueError` naming `owner`); a traced one that is not gives NaN,
    which flags every point (`response_point`)."""
    temperature = jnp.asarray(temperature, float_dtype())
    if temperature.ndim != 0:
        raise ValueError(f"{owner}: temperature must be a scalar (kelvin), got shape {temperature.shape}")
    if is_concrete(temperature) and not (np.isfinite(float(temperature)) and float(temperature) > 0):
        raise ValueError(f"{owner}: temperature must be finite and > 0 kelvin, got {float(temperature)}")
    return thermal_energy(temperature)


@filter_jit
def _responses(rod, ell, rise, force, control, by_torque: bool, n_bp, persistence_length, plectoneme_twist, kT):
    """`response_point` per point, scaled to whole molecules; `control=None`: a free swivel."""

    def one(F, x, N, A, P):
        per_bp = 0.0 if x is None else x if by_torque else 2 * jnp.pi * x / N  # a torque, or radians per bp
        ext, rot, torque, phase, fraction, parts, moduli, result = response_point(
            rod, ell, rise, F, per_bp, by_torque, A, P, kT
        )
        result = RESULTS.where(jnp.isfinite(N) & (N > 0), result, RESULTS.invalid_input)
        good = result == RESULTS.successful
        masked = lambda x: jnp.where(good, x, jnp.nan)
        return (
            masked(ext * N), masked(rot * N), masked(torque), phase, masked(fraction),
            tuple(masked(p * N) for p in parts),
            (masked(moduli[0]), masked(moduli[1]), masked(jnp.where(moduli[2] >= NO_BUCKLING, jnp.inf, moduli[2]))),
            result,
        )

    return jax.vmap(one)(force, control, n_bp, persistence_length, plectoneme_twist)


def tweezer_response(
    rod,
    n_bp: ArrayLike,
    force: ArrayLike,
    *,
    turns: ArrayLike | None = None,
    torque: ArrayLike | None = None,
    persistence_length: ArrayLike = 50.0,
    plectoneme_twist_persistence: ArrayLike = PLECTONEME_TWIST_PERSISTENCE,
    temperature: float = ROOM_TEMPERATURE,
    length_per_bp: float | None = None,
    throw: bool = False,
) -> TweezerResponse:
    """Extension, torque and phase of DNA molecules of `n_bp` base pairs at `force` (pN),
    turned by `turns` (magnetic tweezers: counted from the torque-free molecule at that
    force, positive = overwound) or held at `torque` (pN nm; 0 = a free swivel).  Give one
    of `turns` and `torque`.  The physics is in the module docstring (`helixrod._tweezer`):
    the rod's own nonlinear response, worm-like-chain bending fluctuations of persistence
    `persistence_length` (nm), Moroz-Nelson twist softening, and Marko's two-phase model of
    plectonemes with twist persistence `plectoneme_twist_persistence` (nm).

    `rod`: stiffnesses in pN nm^2 and twists in 1/nm, its `uhat` the backbone helix (e.g.
    `dna.load_tweezer_example().rod`; right-handed, $\\hat u_3 > 0$); `length_per_bp`: the
    filament length per base pair (default: the B-DNA backbone of `helix_from_bdna`);
    `temperature` (kelvin) a scalar.  The other array arguments broadcast elementwise (one
    point each); jit, vmap and differentiable in the rod and every parameter.  Concrete
    invalid values (a force, base-pair count, persistence or temperature that is not
    finite and > 0, non-finite turns or torque) raise `ValueError`; traced ones flag their
    points `invalid_input`.  `throw=True` raises `SolverError` if a point fails; otherwise read `result`
    and `ok` (a failed or out-of-range point is NaN, the others are untouched).

    **Example**

    ```python
    rod = dna.load_tweezer_example().rod
    hat = dna.tweezer_response(rod, 8000, 1.0, turns=jnp.linspace(-40, 40, 81))
    hat.extension, hat.torque, hat.phase
    ```
    """
    check_one_rod(rod, "tweezer_response")
    if (turns is None) == (torque is None):
        raise ValueError("tweezer_response: give exactly one of turns= and torque=")
    dtype = float_dtype()
    by_torque = torque is not None
    control = jnp.asarray(torque if by_torque else turns, dtype)
    arrays = [jnp.asarray(x, dtype) for x in (n_bp, force, control, persistence_length, plectoneme_twist_persistence)]
    try:
        shape = jnp.broadcast_shapes(*(a.shape for a in arrays))
    except ValueError:
        shapes = ", ".join(f"{n} {a.shape}" for n, a in zip(("n_bp", "force", "control", "persistence_length", "plectoneme_twist_persistence"), arrays))
        raise ValueError(f"tweezer_response: shapes do not broadcast: {shapes}") from None
    n, F, x, A, P = (jnp.broadcast_to(a, shape).reshape(-1) for a in arrays)
    if is_concrete(n, F, x, A, P):
        for name, values, positive in (("n_bp", n, True), ("force", F, True), ("turns" if not by_torque else "torque", x, False), ("persistence_length", A, True), ("plectoneme_twist_persistence", P, True)):
            bad = ~np.isfinite(np.asarray(values)) | ((np.asarray(values) <= 0) if positive else False)
            if bad.any():
                rule = "finite and > 0" if positive else "finite"
                raise ValueError(f"tweezer_response: {name} must be {rule} (bad at flat indices {np.flatnonzero(bad)[:5].tolist()})")
    kT = _thermal_energy_of(temperature, "tweezer_response")
    ell, rise = filament_and_rise(rod, length_per_bp, "tweezer_response")
    if x.size == 0:
        empty = jnp.zeros(shape, dtype)
        none = jax.tree.map(lambda code: jnp.broadcast_to(code, shape), RESULTS.successful)
        return TweezerResponse(*([empty] * 3), jnp.zeros(shape, jnp.int32), *([empty] * 7), none)
    free_swivel = by_torque and is_concrete(x) and not np.any(np.asarray(x))
    ext, rot, tq, phase, fraction, parts, moduli, result = _responses(
        rod, ell, rise, F, None if free_swivel else x, by_torque, n, A, P, kT
    )
    turns_out = rot / (2 * jnp.pi) if by_torque else x
    shaped = lambda a: a.reshape(shape)
    response = TweezerResponse(
        extension=shaped(ext),
        torque=shaped(tq),
        turns=shaped(turns_out),
        phase=shaped(phase),
        extended_fraction=shaped(fraction),
        intrinsic_extension=shaped(parts[0]),
        bending_extension=shaped(parts[1]),
        twist_extension=shaped(parts[2]),
        twist_modulus=shaped(moduli[0]),
        effective_twist_modulus=shaped(moduli[1]),
        buckling_torque=shaped(moduli[2]),
        result=jax.tree.map(shaped, result),
    )
    return raise_if_failed(response, response.result, "tweezer_response") if throw else response


class TweezerModuli(eqx.Module):
    """The moduli of the molecule at each `force` (pN), in the single-molecule
    literature's terms (`tweezer_moduli`): the rod's own `stretch_modulus` S (pN),
    `twist_modulus` C (pN nm^2) and `twist_stretch_coupling` g (pN nm) of its helix under
    the force ($\\delta F = S\\varepsilon + g\\omega$, $\\delta M = g\\varepsilon + C\\omega$ per unit
    axial length, as `effective_moduli`; g < 0: overwinding under tension), the twist
    modulus at constant force `twist_modulus_at_constant_force` $C - g^2/S$ and the
    Moroz-Nelson `effective_twist_modulus` with the bending fluctuations of
    `persistence_length` (these two per unit contour length $L_0$, as the tweezer response
    counts twist: $(C - g^2/S)\\,h_0/h$), and the `buckling_torque` (pN nm) of Marko's
    model."""

    force: Float[Array, " k"]
    stretch_modulus: Float[Array, " k"]
    twist_modulus: Float[Array, " k"]
    twist_stretch_coupling: Float[Array, " k"]
    twist_modulus_at_constant_force: Float[Array, " k"]
    effective_twist_modulus: Float[Array, " k"]
    buckling_torque: Float[Array, " k"]


@filter_jit
def _moduli(rod, ell, rise, force, A, P, kT):
    """S, C, g, C0, C_eff and the buckling torque at each of `force` with persistence `A`
    and plectoneme twist persistence `P` (`tweezer_moduli`; one each per force), in one
    compiled program (evaluated operation by operation, four forces took 20-30 s).  NaN
    throughout at a point whose input is invalid (`_valid_point`), computed at a harmless
    force there so that derivatives stay finite elsewhere."""

    def at(force, A, P):
        valid = _valid_point(force, A, P, ell, rise, kT)
        F = jnp.where(valid, force, 1.0)
        A, P = jnp.where(valid, A, 1.0), jnp.where(valid, P, 1.0)

        def observables(wrench):
            values = jnp.stack(_extension_and_rotation(ell, _bulk(rod, ell, wrench[0], wrench[1])[0]))
            return values, values

        wrench = jnp.stack([F, jnp.zeros((), F.dtype)])
        # d(h, Theta)/d(F, M) per base pair, and (h, Theta) from the same solve.
        compliance, (height, _) = jax.jacfwd(observables, has_aux=True)(wrench)
        stiffness = height * inverse_small(compliance)  # per unit axial length (effective_moduli)
        S, C, g = stiffness[0, 0], stiffness[1, 1], 0.5 * (stiffness[0, 1] + stiffness[1, 0])
        _, _, _, _, _, _, (C0, C_eff, buckling), _ = response_point(
            rod, ell, rise, F, 0.0, True, A, P, kT
        )
        in_range = C0 / (4 * A * kT) * jnp.sqrt(kT / (A * F)) <= MAX_TWIST_CORRECTION
        C_eff = jnp.where(in_range, C_eff, jnp.nan)
        buckling = jnp.where(in_range, jnp.where(buckling >= NO_BUCKLING, jnp.inf, buckling), jnp.nan)
        return tuple(jnp.where(valid, x, jnp.nan) for x in (S, C, g, C0, C_eff, buckling))

    return jax.vmap(at)(force, A, P)


def tweezer_moduli(
    rod,
    force: ArrayLike,
    *,
    persistence_length: ArrayLike = 50.0,
    plectoneme_twist_persistence: ArrayLike = PLECTONEME_TWIST_PERSISTENCE,
    temperature: float = ROOM_TEMPERATURE,
    length_per_bp: float | None = None,
) -> TweezerModuli:
    """S, C, g of the rod's helix along the force range, the twist modulus at constant
    force, its Moroz-Nelson softening and the buckling torque (`TweezerModuli`), at each of
    `force` (pN, a 1-D array or a scalar).  The rod's g(F), C(F), S(F) follow from its
    stiffnesses through the nonlinear helix (beside twistable-WLC fits' phenomenological
    g0 + g1 F).  The twist softening and the buckling torque are NaN below the range of the
    Moroz-Nelson theory (its correction above 1/2).  Differentiable in the rod and the
    parameters: with a tweezer fit, error bars come from `StiffnessFit.propagate`.

    `persistence_length` and `plectoneme_twist_persistence` (nm): scalars or one per force;
    `temperature` (kelvin) a scalar.  Concrete values that are not finite and > 0 (forces,
    persistences, temperature, `length_per_bp`, the rod's rise) raise `ValueError`; traced
    ones give NaN in every field of their point."""
    owner = "tweezer_moduli"
    check_one_rod(rod, owner)
    dtype = float_dtype()
    force = jnp.atleast_1d(jnp.asarray(force, dtype))
    if force.ndim != 1:
        raise ValueError(f"{owner}: force must be a scalar or 1-D, got shape {force.shape}")
    parameters = {}
    for name, value in (("persistence_length", persistence_length), ("plectoneme_twist_persistence", plectoneme_twist_persistence)):
        value = jnp.asarray(value, dtype)
        if value.ndim > 1 or (value.ndim == 1 and value.shape != force.shape):
            raise ValueError(f"{owner}: {name} must be a scalar or one per force {force.shape}, got shape {value.shape}")
        parameters[name] = jnp.broadcast_to(value, force.shape)
    for name, value in (("force", force), *parameters.items()):
        if is_concrete(value):
            bad = ~(np.isfinite(np.asarray(value)) & (np.asarray(value) > 0))
            if bad.any():
                raise ValueError(f"{owner}: {name} must be finite and > 0 (bad at indices {np.flatnonzero(bad)[:5].tolist()})")
    kT = _thermal_energy_of(temperature, owner)
    ell, rise = filament_and_rise(rod, length_per_bp, owner)
    A, P = parameters["persistence_length"], parameters["plectoneme_twist_persistence"]

    S, C, g, C0, C_eff, buckling = _moduli(rod, ell, rise, force, A, P, kT)
    return TweezerModuli(force, S, C, g, C0, C_eff, buckling)
