"""Conditions at the ends of a finite rod, and the axial controls of spring and tweezer
tests.

The rod is clamped at $s = 0$; the condition at $s = L$ is six scalar equations:

- `Clamped(position, frame)`: $x(L) = P$, $D(L) = R$;
- `Loaded(force, moment, point)`: the lab force $N = F$ and the moment about `point` (a
  fixed lab point; the end $x(L)$ itself when `point` is `None`) -- with a fixed point the
  moment about it is conserved, so this is an initial-value problem in disguise; or
  `Loaded(force, moment, hook=r)`: the force acting at the point $x(L) + D(L)r$ rigidly
  attached to the end (a spring's hook, a bead's centre), $m(L) = (D(L)r)\\times F + M$;
- `Tweezer(frame, force)`: $D(L) = R$ and $N = F$, the end position free (a magnetic bead:
  the magnet fixes the bead's orientation and pulls with a known force).

Each is turned into one uniform, traced form, `EndCondition` (its `kind` a traced integer),
so that one compiled program serves every kind and a `vmap`-ped batch may mix them.  Frames
are compared through the Gibbs vector of $R^TD$, whose only zero is the identity.

Axial controls.  A spring or a tweezer filament in the canonical placement (`unloaded_state`:
axis $e_z$ through the origin) is loaded along its axis by two of the four observables
`AXIAL_OBSERVABLES` = (force $F$, moment $M$, extension $h$, rotation $\\Theta$); `AXIAL_CONTROLS`
is the one table of the three pairs (which end kind, which two are controlled, which two
respond), used by `axial_ends`, the response curves and the end-response data.
"""

from __future__ import annotations

import abc
import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._compile import jit
from .._geometry import unloaded_observables, unloaded_state
from .._lie import check_rotation, gibbs, rotation_vector, rotation_z, so3_exp
from .._misc import finite_array, finite_scalar, float_dtype

CLAMPED, LOADED, TWEEZER = 0, 1, 2

#: The axial observables, in the order of every `(..., 4)` array of them.
AXIAL_OBSERVABLES = ("force", "moment", "extension", "rotation")


class AxialControl(NamedTuple):
    """An axial test: the end `kind`, and indices into `AXIAL_OBSERVABLES` of the two
    `controls` (prescribed) and the two `responses` (solved for, in the order reported)."""

    kind: int
    controls: tuple[int, int]
    responses: tuple[int, int]


#: The three axial tests by name: a spring on hooks (force and moment prescribed), a
#: magnetic tweezer (force and rotation), a spring between grips (extension and rotation).
AXIAL_CONTROLS = {
    "force-moment": AxialControl(LOADED, (0, 1), (2, 3)),
    "force-rotation": AxialControl(TWEEZER, (0, 3), (2, 1)),
    "extension-rotation": AxialControl(CLAMPED, (2, 3), (0, 1)),
}
#: `CONTROL_INDEX[kind]`: the indices of the two controls of each end kind.
CONTROL_INDEX = np.array([next(c.controls for c in AXIAL_CONTROLS.values() if c.kind == k) for k in range(3)])


def axial_controls(**values) -> tuple[str, dict]:
    """The name in `AXIAL_CONTROLS` of the pair of keyword arguments that are not `None`,
    and those values; `ValueError` for any other combination."""
    given = {n: v for n, v in values.items() if v is not None}
    name = "-".join(n for n in AXIAL_OBSERVABLES if n in given)
    if name not in AXIAL_CONTROLS:
        pairs = [" and ".join(p.split("-")) for p in AXIAL_CONTROLS]
        raise ValueError(f"give one of the pairs {pairs}, got {list(given) or 'nothing'}")
    return name, given


class AbstractEnd(eqx.Module):
    """A condition at the end $s = L$ of a rod clamped at $s = 0$ (six scalar equations):
    `Clamped`, `Loaded`, `Tweezer`, or their uniform form `EndCondition`."""

    @abc.abstractmethod
    def condition(self) -> "EndCondition":
        """The condition in the uniform form shared by every kind."""


class EndCondition(AbstractEnd):
    """Any end condition in one traced form: `kind` (0 clamped, 1 loaded, 2 tweezer) and
    the data of every kind -- `position` `(3,)`, `frame` `(3, 3)`, `force` `(3,)`, `moment`
    `(3,)`, `point` `(3,)`, `hook` `(3,)` (director components) and `about_end` (the force
    of a `Loaded` end acts at the point `hook` rigidly attached to the end, the end itself
    for zero, and its moment is about the end; else its line passes through the fixed
    `point`); fields a kind does not use are zero (identity frame); `rotation`: the end's
    total rotation $\\Theta$ about the axis of the canonical placement, whole turns included,
    where it is known (`axial_ends`, the response curves; NaN elsewhere): the frame holds it
    only up to whole turns, and the default guess turns the rod by as much.  Built by
    `Clamped(...).condition()` and the like, or by `axial_end_condition` with a traced kind;
    a stack of them (leading axis) is what `jax.vmap` maps over for a batch of mixed ends."""

    kind: Int[Array, ""]
    position: Float[Array, "3"]
    frame: Float[Array, "3 3"]
    force: Float[Array, "3"]
    moment: Float[Array, "3"]
    point: Float[Array, "3"]
    hook: Float[Array, "3"]
    about_end: Bool[Array, ""]
    rotation: Float[Array, ""]

    def condition(self) -> "EndCondition":
        return self

    def residual(self, x, frame, force, moment, scales):
        """Scaled residual `(6,)` of the lab end state (position, frame, force, moment)."""
        ell, f_scale, m_scale = scales[0], scales[1], scales[2]
        point = jnp.where(self.about_end, x + frame @ self.hook, self.point)
        r_position = (x - self.position) / ell
        r_frame = gibbs(self.frame.T @ frame)
        r_force = (force - self.force) / f_scale
        r_moment = (moment + jnp.cross(x - point, force) - self.moment) / m_scale
        first = jnp.where(self.kind == CLAMPED, r_position, r_force)
        second = jnp.where(self.kind == LOADED, r_moment, r_frame)
        return jnp.concatenate([first, second])

    def homotopy(self, t, x_free, frame_free, unloaded_rotation) -> "EndCondition":
        """The condition a fraction `t` of the way from the unloaded end (`t = 0`, at
        `x_free`, `frame_free`).  Where the condition knows its total `rotation`, the end
        turns about $e_z$ by that fraction of its rotation from `unloaded_rotation` (the
        unloaded end's, $\\Theta_0$), whole turns included -- a twisted spring is reached by
        twisting it, not by the nearest frame with fewer turns -- and by the same fraction of
        what remains (nothing, for the ends of `axial_ends`); else the frame turns the short
        way."""
        turning = jnp.where(jnp.isfinite(self.rotation), self.rotation - unloaded_rotation, 0.0)
        remaining = rotation_vector((rotation_z(turning) @ frame_free).T @ self.frame)
        spin = rotation_z(t * turning)
        return eqx.tree_at(
            lambda e: (e.position, e.frame, e.force, e.moment),
            self,
            (
                spin @ ((1 - t) * x_free + t * rotation_z(-turning) @ self.position),
                spin @ frame_free @ so3_exp(t * remaining),
                t * self.force,
                t * self.moment,
            ),
        )

    def finite(self) -> Bool[Array, ""]:
        """Whether every value of the condition is finite (`rotation`, a hint, may be NaN)."""
        leaves = (self.position, self.frame, self.force, self.moment, self.point, self.hook)
        return jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in leaves]))


def end_condition(kind, position=None, frame=None, force=None, moment=None, point=None, rotation=None, hook=None) -> EndCondition:
    """An `EndCondition` of a (concrete) `kind` with zeros for the fields it does not use
    (`rotation`: NaN, not known)."""
    # NumPy constants: no eager JAX dispatch per solve (they are traced like JAX arrays).
    dtype = float_dtype()
    zero = np.zeros(3, dtype)
    leaves = (
        np.asarray(kind, np.int32),
        zero if position is None else position,
        np.eye(3, dtype=dtype) if frame is None else frame,
        zero if force is None else force,
        zero if moment is None else moment,
        zero if point is None else point,
        zero if hook is None else hook,
        np.asarray(point is None and kind == LOADED),
        np.asarray(np.nan, dtype) if rotation is None else rotation,
    )
    # From its leaves in field order: equinox's initialiser (~20 us) was a tenth of the
    # Python time of an eager solve, and the fields need no conversion or check.
    return jax.tree.unflatten(_condition_structure(), leaves)


@functools.cache
def _condition_structure():
    """The pytree structure of an `EndCondition` (its nine fields are its leaves)."""
    zero = np.zeros(3)
    return jax.tree.structure(EndCondition(np.int32(0), zero, np.eye(3), zero, zero, zero, zero, np.bool_(False), np.float64(np.nan)))


class Clamped(AbstractEnd):
    """Prescribed position and frame: `Clamped(position=(0, 0, 0), frame=identity, *,
    rotation=None)`.

    `position` `(3,)` lab point; `frame` `(3, 3)` rotation with column $i$ = $d_{i+1}$ (lab).
    The start condition of every problem, and the end condition of a rod clamped at both
    ends (a spring test: grips that hold the wire ends).  `rotation` (optional, as
    `axial_ends` sets it): the total end rotation $\\Theta$ about the axis of the canonical
    placement, whole turns included, which the frame holds only up to whole turns -- the
    default guess of a solve turns the rod by as much.  Non-finite values or a frame that is
    not a rotation raise `ValueError` (concrete values).
    """

    position: Float[Array, "3"]
    frame: Float[Array, "3 3"]
    rotation: Float[Array, ""] | None

    def __init__(self, position: ArrayLike = (0.0, 0.0, 0.0), frame: ArrayLike | None = None, *, rotation: ArrayLike | None = None):
        position = finite_array(position, "position", "Clamped", (3,))
        frame = jnp.eye(3, dtype=position.dtype) if frame is None else finite_array(frame, "frame", "Clamped", (3, 3))
        check_rotation(frame, "Clamped")
        self.position, self.frame = position, frame
        self.rotation = None if rotation is None else finite_scalar(rotation, "rotation", "Clamped")

    def condition(self) -> EndCondition:
        return end_condition(CLAMPED, position=self.position, frame=self.frame, rotation=self.rotation)


def as_start(start: Clamped) -> Clamped:
    """A `Clamped` as the start of a rod: its `rotation` (an end's hint) dropped, so that
    every start of one position and frame is the same argument of a compiled program."""
    return start if start.rotation is None else eqx.tree_at(lambda c: c.rotation, start, None)


class Loaded(AbstractEnd):
    """Prescribed end load (dead load): `Loaded(force, moment, point=None, *, hook=None)`.

    `force` `(3,)`: the lab force $n(L)$ applied to the end; `moment` `(3,)`: the applied
    moment about `point` (a fixed lab point, e.g. on a spring's axis: the force's line is
    held through it), or about the end $x(L)$ itself when `point` is `None` (then it is
    $m(L)$ in lab components).  `hook` `(3,)` (instead of `point`): the force acts at the
    point $x(L) + D(L)r$ ($r$ = `hook`) rigidly attached to the end, $r$ in the end's
    director components (a spring's hook, a bead's centre), so that $m(L) = (D(L)r)\\times
    F + M$ ($M$ = `moment`): a conservative load (with `moment` zero) whose stability is the
    one the stability test computes (with `point`, each state is tested as held by a rigid
    hook of its own geometry).
    """

    force: Float[Array, "3"]
    moment: Float[Array, "3"]
    point: Float[Array, "3"] | None
    hook: Float[Array, "3"] | None

    def __init__(
        self, force: ArrayLike = (0.0, 0.0, 0.0), moment: ArrayLike = (0.0, 0.0, 0.0), point: ArrayLike | None = None, *,
        hook: ArrayLike | None = None,
    ):
        self.force = finite_array(force, "force", "Loaded", (3,))
        self.moment = finite_array(moment, "moment", "Loaded", (3,))
        if point is not None and hook is not None:
            raise ValueError("Loaded: give point= (a fixed line of the force) or hook= (a point attached to the end), not both")
        self.point = None if point is None else finite_array(point, "point", "Loaded", (3,))
        self.hook = None if hook is None else finite_array(hook, "hook", "Loaded", (3,))

    def condition(self) -> EndCondition:
        return end_condition(LOADED, force=self.force, moment=self.moment, point=self.point, hook=self.hook)


class Tweezer(AbstractEnd):
    """Prescribed end frame and end force, free end position: `Tweezer(frame, force, *,
    rotation=None)`.

    The magnetic-tweezer set-up: the magnet holds the bead's orientation `frame` `(3, 3)`
    (e.g. the unloaded end frame turned about the axis by the magnet's rotation) and pulls
    with `force` `(3,)` (lab); the torque is a reaction.  `rotation` (optional): the magnet's
    total rotation $\\Theta$ with its whole turns, as `Clamped`'s.
    """

    frame: Float[Array, "3 3"]
    force: Float[Array, "3"]
    rotation: Float[Array, ""] | None

    def __init__(self, frame: ArrayLike, force: ArrayLike, *, rotation: ArrayLike | None = None):
        self.frame = finite_array(frame, "frame", "Tweezer", (3, 3))
        self.force = finite_array(force, "force", "Tweezer", (3,))
        check_rotation(self.frame, "Tweezer")
        self.rotation = None if rotation is None else finite_scalar(rotation, "rotation", "Tweezer")

    def condition(self) -> EndCondition:
        return end_condition(TWEEZER, frame=self.frame, force=self.force, rotation=self.rotation)


@jit(run_once=True)
def unloaded_clamp(rod) -> Clamped:
    """The clamp at s = 0 of the unloaded rod in its canonical placement (`unloaded_state`):
    a program of its own, compiled to run once (evaluated operation by operation, ~25
    one-operation programs, 0.5-1 s of a first call)."""
    return Clamped(*unloaded_state(rod, 0.0))


def axial_ends(
    rod,
    length: ArrayLike,
    *,
    force: ArrayLike | None = None,
    moment: ArrayLike | None = None,
    extension: ArrayLike | None = None,
    rotation: ArrayLike | None = None,
) -> tuple[Clamped, AbstractEnd]:
    """Start and end conditions of a spring (or tweezer) test along the axis of the rod.

    The start is the canonical placement of the unloaded rod: its intrinsic helix
    ($\\hat\\kappa$, $\\hat\\tau$, register $\\hat\\varphi$ from $\\hat u$) placed as
    `helix_frame`/`helix_centreline` place it, axis $e_z$ through the origin (a straight
    untwisted rod: origin, identity frame).  The end is set by two axial controls
    (`AXIAL_CONTROLS`):

    - `force`, `moment` -> `Loaded(F e_z, M e_z, point=0)`: axial force and moment along the
      axis line (a spring loaded through hooks on its axis; an initial-value problem);
    - `force`, `rotation` -> `Tweezer(R_z(Θ - Θ0) D0(L), F e_z)`: the magnetic tweezer -- end
      frame turned about the axis, axial pull, end position free;
    - `extension`, `rotation` -> `Clamped(R_z(Θ - Θ0) x0(L) + (h - h0) e_z, R_z(Θ - Θ0) D0(L))`:
      grips moved along and turned about the axis.

    $x_0(L)$, $D_0(L)$ are the unloaded end; `extension` $h$ is the axial end-to-end distance
    and `rotation` $\\Theta$ the total end rotation about the axis, as in `spring_compliance`
    (unloaded: $h_0 = L\\hat\\tau/|\\hat u|$, $\\Theta_0 = L|\\hat u|$, so `rotation=Θ0` means
    "not turned"; $F$ along $e_z$, a pull for $\\hat\\tau > 0$).  Scalars, traced allowed.

    The end frame holds $\\Theta$ only up to whole turns; the end carries $\\Theta$ itself too
    (`rotation`), so that the default guess of a solve turns the rod by as many turns.
    """
    try:
        name, given = axial_controls(force=force, moment=moment, extension=extension, rotation=rotation)
    except ValueError as error:
        raise ValueError(f"axial_ends: {error}") from None
    length = finite_scalar(length, "length", "axial_ends", positive=True)
    values = {n: finite_scalar(v, n, "axial_ends") for n, v in given.items()}
    start = unloaded_clamp(rod)
    kind = AXIAL_CONTROLS[name].kind
    end = axial_end_condition(rod, length, kind, [values.get(n, 0.0) for n in AXIAL_OBSERVABLES])
    if kind == LOADED:
        return start, Loaded(end.force, end.moment, point=end.point)
    if kind == TWEEZER:
        return start, Tweezer(end.frame, end.force, rotation=end.rotation)
    return start, Clamped(end.position, end.frame, rotation=end.rotation)


def axial_end_condition(rod, length, kind, values) -> EndCondition:
    """The end condition of `axial_ends` for a (possibly traced) `kind` (`CLAMPED`:
    extension and rotation; `LOADED`: force and moment; `TWEEZER`: force and rotation) and
    `values` = (force, moment, extension, rotation); entries the kind does not control are
    ignored."""
    dtype = float_dtype()
    force, moment, extension, rotation = (jnp.asarray(v, dtype) for v in values)
    x_end, frame_end = unloaded_state(rod, length)
    h0, theta0 = unloaded_observables(rod, length)
    e3 = jnp.array([0.0, 0.0, 1.0], dtype)
    turn = rotation_z(rotation - theta0)
    kind = jnp.asarray(kind, jnp.int32)
    loaded = kind == LOADED
    return EndCondition(
        kind=kind,
        position=turn @ x_end + (extension - h0) * e3,
        frame=jnp.where(loaded, jnp.eye(3, dtype=dtype), turn @ frame_end),
        force=force * e3,
        moment=moment * e3,
        point=jnp.zeros(3, dtype),
        hook=jnp.zeros(3, dtype),
        about_end=jnp.asarray(False),
        rotation=jnp.where(loaded, jnp.nan, rotation),
    )


def stack_ends(ends) -> EndCondition:
    """One `EndCondition` stacked over a sequence of ends (leading axis), for `jax.vmap`."""
    conditions = [e.condition() for e in ends]
    return jax.tree.map(lambda *a: jnp.stack(a), *conditions)
