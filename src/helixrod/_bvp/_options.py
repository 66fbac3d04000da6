"""The configuration of a boundary-value solve, checked when it is built."""

from __future__ import annotations

import dataclasses
import functools

import diffrax
import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._kirchhoff import solve_static
from .._lie import CommutatorFreeRK4, MuntheKaasRK
from .._misc import as_float, attainable, check_choice, check_integer, is_concrete

#: The most pieces of a stability test: its Hessian is dense, (6p)^2 numbers (302 MB at
#: 1024 pieces); more ran out of memory inside XLA.
MAX_TEST_PIECES = 1024


def check_test_pieces(value, name: str, owner: str, minimum: int) -> int:
    """`value` as an `int`, or `ValueError` unless it is an integer in [`minimum`,
    `MAX_TEST_PIECES`]: the pieces of a stability test."""
    value = check_integer(value, name, owner, minimum=minimum)
    if value > MAX_TEST_PIECES:
        raise ValueError(f"{owner}: {name} must be at most {MAX_TEST_PIECES} (a dense Hessian of 6 per piece), got {value}")
    return value


#: Root-finder steps: damped (Levenberg--Marquardt) or plain Newton steps.
METHODS = ("levenberg-marquardt", "newton")


def _tolerance(name: str):
    """The converter of a tolerance field (`as_float`): a JAX array (traced or not) as it
    is, anything else as a NumPy float64 array, which costs no device dispatch (building the
    options of an eager call took ~0.3 ms with `jnp.asarray`); the solve converts it to its
    own dtype (`BoundaryValueOptions.for_dtype`) and `__check_init__` checks its shape and
    value."""

    def convert(value) -> Array | np.ndarray:
        try:
            return as_float(value)
        except (TypeError, ValueError):
            raise ValueError(f"BoundaryValueOptions: {name} must be a number, got {value!r}") from None

    return convert


class BoundaryValueOptions(eqx.Module):
    """How `solve_boundary_value` (and the response curves and finite-rod fits built on it)
    solves: one compilation per configuration of the static fields; the tolerances are
    arrays, so changing them does not recompile.

    - `segments`: shooting pieces $k$ (1: single shooting; more for long rods in spatially
      unstable states, `wrench_growth_rate`).
    - `continuation`: homotopy steps from the unloaded rod to the prescribed end (0: none).
    - `method`: `"levenberg-marquardt"` (damped steps; robust) or `"newton"` (plain
      Newton steps; cheapest from a good guess), both with Broyden updates.
    - `max_steps`: root-finder iterations per solve.
    - `atol`: root tolerance on the largest scaled residual (positions in units of
      $\\ell = \\min(L, 1/|\\hat u|)$, forces of $\\bar K/\\ell^2$, moments of $\\bar K/\\ell$, frames by
      the Gibbs vector; $\\bar K$ the mean bending/twisting stiffness); a solve is `ok` when
      that residual is at most `10 atol`.
    - `ode_rtol`, `ode_atol`, `solver` (`CommutatorFreeRK4()` or `MuntheKaasRK(...)`: the
      shooting equations rely on their exact conservation of the lab wrench),
      `max_ode_steps`: the integration of each piece; the stability test's Jacobi fields
      follow `ode_rtol` too (fewer steps where it is looser than ~6e-7).
    - `stability_pieces`: pieces of the stability test of the solution (`_stability.py`;
      rounded up to a multiple of `segments`; 0: no stability test, `instability_index`
      -1); each piece must be short against the wrench, and `solve_boundary_value` doubles
      them where it is not.
    - `adjoint`: `diffrax.ForwardMode()` (`jax.jvp`/`jax.jacfwd` through the solve) or
      `diffrax.DirectAdjoint()` (also `jax.grad`/`jax.jacrev`, slower to compile and run).

    Bad values raise `ValueError` here, when the options are built.
    """

    segments: int = eqx.field(static=True, default=1)
    continuation: int = eqx.field(static=True, default=0)
    method: str = eqx.field(static=True, default="levenberg-marquardt")
    max_steps: int = eqx.field(static=True, default=64)
    atol: Array = eqx.field(converter=_tolerance("atol"), default=1e-10)
    ode_rtol: Array = eqx.field(converter=_tolerance("ode_rtol"), default=1e-10)
    ode_atol: Array = eqx.field(converter=_tolerance("ode_atol"), default=1e-10)
    solver: diffrax.AbstractSolver = CommutatorFreeRK4()
    max_ode_steps: int = eqx.field(static=True, default=16_384)
    adjoint: diffrax.AbstractAdjoint = diffrax.ForwardMode()
    stability_pieces: int = eqx.field(static=True, default=16)

    def __check_init__(self):
        owner = "BoundaryValueOptions"
        check_integer(self.segments, "segments", owner)
        check_integer(self.continuation, "continuation", owner, minimum=0)
        check_integer(self.max_steps, "max_steps", owner)
        check_integer(self.max_ode_steps, "max_ode_steps", owner)
        check_test_pieces(self.stability_pieces, "stability_pieces", owner, minimum=0)
        check_choice(self.method, METHODS, "method", owner)
        for name in ("atol", "ode_rtol", "ode_atol"):
            value = getattr(self, name)
            if jnp.shape(value) != ():
                raise ValueError(f"{owner}: {name} must be a scalar, got shape {jnp.shape(value)}")
            if is_concrete(value) and not (np.isfinite(float(value)) and float(value) > 0):
                raise ValueError(f"{owner}: {name} must be finite and > 0, got {float(value)}")
        if not isinstance(self.solver, (CommutatorFreeRK4, MuntheKaasRK)):
            raise ValueError(
                f"{owner}: solver must be CommutatorFreeRK4 or MuntheKaasRK: the shooting "
                "equations rely on their exact conservation of the lab wrench"
            )
        if not isinstance(self.adjoint, (diffrax.ForwardMode, diffrax.DirectAdjoint)):
            raise ValueError(
                f"{owner}: adjoint must be diffrax.ForwardMode() or diffrax.DirectAdjoint() "
                f"(Newton's method needs forward-mode derivatives of the flow), got {type(self.adjoint).__name__}"
            )

    def for_dtype(self, dtype) -> BoundaryValueOptions:
        """These options with every tolerance raised to what a solve in `dtype` can reach
        (`_misc.attainable`)."""
        floor = attainable(0.0, dtype)
        raise_to = lambda x: jnp.maximum(jnp.asarray(x, dtype), floor)
        return eqx.tree_at(lambda o: (o.atol, o.ode_rtol, o.ode_atol), self, tuple(raise_to(x) for x in (self.atol, self.ode_rtol, self.ode_atol)))

    def integrate(self, rod, n0, m0, length, ode_tol, **kwargs):
        """`solve_static` with this configuration's integrator, frame and centreline
        integrated, `throw=False` (a failed piece is flagged, never raised); `ode_tol` =
        (rtol, atol)."""
        return solve_static(
            rod, n0, m0, length, outputs=("frame", "centreline"), solver=self.solver, rtol=ode_tol[0],
            atol=ode_tol[1], max_steps=self.max_ode_steps, adjoint=self.adjoint, throw=False, **kwargs,
        )


#: `BoundaryValueOptions()`, built once (options are immutable).
DEFAULT_OPTIONS = BoundaryValueOptions()


def with_settings(options: BoundaryValueOptions | None, **settings) -> BoundaryValueOptions:
    """`options` (default `BoundaryValueOptions()`) with the settings that are not `None`
    replaced -- the keyword arguments of the entry points.  The default options with
    hashable settings (numbers, strings, solver objects) are built once per distinct
    settings (`_default_with`): building and checking them took ~0.1 ms of every eager
    call."""
    if options is not None and not isinstance(options, BoundaryValueOptions):
        raise ValueError(f"options must be a BoundaryValueOptions, got {type(options).__name__}")
    given = {name: value for name, value in settings.items() if value is not None}
    if not given:
        return DEFAULT_OPTIONS if options is None else options
    if options is None:
        # The type is part of the key: `segments=True` must not find `segments=1`.
        key = tuple(sorted((name, type(value), value) for name, value in given.items()))
        try:
            return _default_with(key)
        except TypeError:  # an unhashable setting (an array): built afresh
            options = DEFAULT_OPTIONS
    return dataclasses.replace(options, **given)


@functools.lru_cache(maxsize=64)
def _default_with(key: tuple) -> BoundaryValueOptions:
    """`DEFAULT_OPTIONS` with the settings of `key` ((name, type, value) triples); options
    are immutable, so one object serves every call with the same settings."""
    return dataclasses.replace(DEFAULT_OPTIONS, **{name: value for name, _, value in key})
