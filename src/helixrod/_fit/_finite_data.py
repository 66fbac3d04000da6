"""Observations of finite rods: end responses and centreline shapes, and synthetic data.

`EndResponseData`: a rod of known length (and, at fit time, known intrinsic shape) loaded
along its axis as `axial_ends` describes; two quantities are controlled (exact) and two
are measured (with standard deviations).  `ShapeData`: sampled centreline points
$x(s_i)$ (e.g. from an image) of a rod clamped at a known pose under known end conditions,
possibly several images under different loads.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._bvp import (
    AXIAL_CONTROLS,
    AXIAL_OBSERVABLES,
    AbstractEnd,
    BoundaryValueOptions,
    Clamped,
    EndCondition,
    as_start,
    axial_response,
    solve_boundary_value,
    stack_ends,
)
from .._misc import check_integer, check_key, column, finite_scalar, float_dtype, random_normal


class EndResponseData(eqx.Module):
    """End responses of a finite rod of known length under axial loads.

    Columns (each `(n,)`): `force` $F$, `moment` $M$, `extension` $h$, `rotation` $\\Theta$ in
    the conventions of `axial_ends` (axial force and moment about the axis; axial
    end-to-end distance; total end rotation, the unloaded rod having $h_0 = L\\hat\\tau/|\\hat u|$,
    $\\Theta_0 = L|\\hat u|$).  `controls` names the two controlled (exact) columns:

    - `"force-moment"`: a spring hooked on its axis (force and moment applied, extension and
      rotation measured);
    - `"force-rotation"`: a magnetic tweezer (force and magnet turns applied, extension and
      torque measured);
    - `"extension-rotation"`: a spring between grips (displacement and turn applied, force
      and torque measured).

    The two measured columns need standard deviations (`*_sigma`, scalar or `(n,)`, > 0);
    sigmas of controlled columns are not used.  `length` $L > 0$.  `segments`: shooting
    pieces of the forward model (`solve_boundary_value`).  Bad input raises `ValueError`.
    """

    length: Float[Array, ""]
    force: Float[Array, " n"]
    moment: Float[Array, " n"]
    extension: Float[Array, " n"]
    rotation: Float[Array, " n"]
    sigma: Float[Array, "n 2"]
    controls: str = eqx.field(static=True)
    segments: int = eqx.field(static=True)

    def __init__(
        self,
        length: ArrayLike,
        force: ArrayLike,
        moment: ArrayLike,
        extension: ArrayLike,
        rotation: ArrayLike,
        *,
        controls: str,
        force_sigma: ArrayLike | None = None,
        moment_sigma: ArrayLike | None = None,
        extension_sigma: ArrayLike | None = None,
        rotation_sigma: ArrayLike | None = None,
        segments: int = 1,
    ):
        owner = "EndResponseData"
        if controls not in AXIAL_CONTROLS:
            raise ValueError(f"{owner}: controls must be one of {tuple(AXIAL_CONTROLS)}, got {controls!r}")
        length = float(finite_scalar(length, "length", owner, positive=True))
        columns = {n: column(v, n, owner) for n, v in zip(AXIAL_OBSERVABLES, (force, moment, extension, rotation))}
        sizes = {n: c.shape[0] for n, c in columns.items()}
        if len(set(sizes.values())) != 1 or 0 in sizes.values():
            raise ValueError(f"{owner}: columns must have one common, non-zero length, got {sizes}")
        n = sizes["force"]
        sigmas = dict(zip(AXIAL_OBSERVABLES, (force_sigma, moment_sigma, extension_sigma, rotation_sigma)))
        sigma = []
        for i in AXIAL_CONTROLS[controls].responses:
            name = AXIAL_OBSERVABLES[i]
            if sigmas[name] is None:
                raise ValueError(f"{owner}: {name} is measured with controls={controls!r}: give {name}_sigma")
            col = column(sigmas[name], f"{name}_sigma", owner, n)
            if np.any(col <= 0):
                raise ValueError(f"{owner}: {name}_sigma must be > 0; rows {np.flatnonzero(col <= 0)[:20].tolist()} are not")
            sigma.append(col)
        dtype = float_dtype()
        self.length = jnp.asarray(length, dtype)
        for name in AXIAL_OBSERVABLES:
            setattr(self, name, jnp.asarray(columns[name], dtype))
        self.sigma = jnp.asarray(np.stack(sigma, 1), dtype)
        self.controls = controls
        self.segments = check_integer(segments, "segments", owner)

    def __len__(self) -> int:
        return int(self.force.shape[0])

    @property
    def values(self) -> Float[Array, "n 4"]:
        """The columns stacked as `(n, 4)` = (force, moment, extension, rotation)."""
        return jnp.stack([self.force, self.moment, self.extension, self.rotation], -1)

    @property
    def responses(self) -> tuple[str, str]:
        """Names of the two measured columns."""
        return tuple(AXIAL_OBSERVABLES[i] for i in AXIAL_CONTROLS[self.controls].responses)


def _stack_ends(end) -> EndCondition:
    ends = [end] if isinstance(end, AbstractEnd) else list(end)
    if not ends or not all(isinstance(e, AbstractEnd) for e in ends):
        raise ValueError("ShapeData: end must be a Clamped, Loaded or Tweezer, or a sequence of them (one per image)")
    return stack_ends(ends)


class ShapeData(eqx.Module):
    """Centreline points of a finite rod under known end conditions.

    - `length` $L > 0$; `s` `(p,)` arc lengths of the sampled points, increasing in $[0, L]$.
    - `points`: lab positions `(p, 3)`, or `(m, p, 3)` for `m` images under different loads.
    - `end`: the end condition (`Clamped`, `Loaded` or `Tweezer`), or a sequence of `m` of
      them, one per image (stored as one `EndCondition` stacked over the images); `start`:
      the clamp at $s = 0$ (default: origin, identity frame).
    - `sigma`: standard deviation of each coordinate of each point (isotropic noise): a
      scalar, `(p,)` or `(m, p)`.
    - `segments`: shooting pieces of the forward model.

    Bad input (shapes, non-finite values, `sigma <= 0`, `s` outside $[0, L]$ or not
    increasing) raises `ValueError`.
    """

    length: Float[Array, ""]
    s: Float[Array, " p"]
    points: Float[Array, "m p 3"]
    sigma: Float[Array, "m p"]
    start: Clamped
    end: EndCondition
    segments: int = eqx.field(static=True)

    def __init__(
        self,
        length: ArrayLike,
        s: ArrayLike,
        points: ArrayLike,
        end: AbstractEnd | Sequence[AbstractEnd],
        *,
        sigma: ArrayLike,
        start: Clamped | None = None,
        segments: int = 1,
    ):
        owner = "ShapeData"
        length = float(finite_scalar(length, "length", owner, positive=True))
        s = column(s, "s", owner)
        if np.any(np.diff(s) <= 0) or s[0] < 0 or s[-1] > length * (1 + 1e-12):
            raise ValueError(f"{owner}: s must increase strictly within [0, length={length}]")
        pts = np.asarray(points, dtype=float)
        if pts.ndim == 2:
            pts = pts[None]
        if pts.ndim != 3 or pts.shape[1:] != (s.shape[0], 3):
            raise ValueError(f"{owner}: points must have shape (p, 3) or (m, p, 3) with p = {s.shape[0]}, got {np.shape(points)}")
        if not np.all(np.isfinite(pts)):
            bad = np.argwhere(~np.all(np.isfinite(pts), axis=-1))
            raise ValueError(f"{owner}: non-finite points at (image, point) {bad[:10].tolist()}")
        m = pts.shape[0]
        ends = _stack_ends(end)
        count = ends.kind.shape[0]
        if count == 1 and m > 1:
            ends = jax.tree.map(lambda a: jnp.broadcast_to(a, (m,) + a.shape[1:]), ends)
        elif count != m:
            raise ValueError(f"{owner}: {count} end conditions for {m} images")
        sig = np.asarray(sigma, dtype=float)
        try:
            sig = np.broadcast_to(sig, (m, s.shape[0]))
        except ValueError:
            raise ValueError(f"{owner}: sigma must be a scalar, (p,) or (m, p), got shape {np.shape(sigma)}") from None
        if not np.all(np.isfinite(sig)) or np.any(sig <= 0):
            raise ValueError(f"{owner}: sigma must be finite and > 0")
        start = Clamped() if start is None else start
        if not isinstance(start, Clamped):
            raise ValueError(f"{owner}: start must be Clamped, got {type(start).__name__}")
        dtype = float_dtype()
        self.length = jnp.asarray(length, dtype)
        self.s = jnp.asarray(s, dtype)
        self.points = jnp.asarray(pts, dtype)
        self.sigma = jnp.asarray(sig, dtype)
        self.start = as_start(start)
        self.end = ends
        self.segments = check_integer(segments, "segments", owner)

    def __len__(self) -> int:
        return int(self.points.shape[0] * self.points.shape[1])

    @property
    def images(self) -> int:
        """Number of images (load cases)."""
        return int(self.points.shape[0])


def synthetic_end_response_data(
    rod,
    length: ArrayLike,
    controls: str,
    first: ArrayLike,
    second: ArrayLike,
    noise: float | tuple[float, float],
    key: Array,
    *,
    segments: int = 1,
) -> EndResponseData:
    """Simulated end-response measurements of `rod` (length `length`).

    `controls` as `EndResponseData`; `first`, `second` `(n,)` the values of the two
    controls (e.g. force and moment for `"force-moment"`).  The responses are solved with
    `solve_boundary_value` (each point from the bulk-helix guess) and get Gaussian noise of
    standard deviation `noise` times their root-mean-square (or absolute `(sigma1, sigma2)`),
    which are the sigmas of the data.  Points that do not converge raise `ValueError`.
    """
    owner = "synthetic_end_response_data"
    check_key(key, owner)
    if controls not in AXIAL_CONTROLS:
        raise ValueError(f"{owner}: controls must be one of {tuple(AXIAL_CONTROLS)}, got {controls!r}")
    test = AXIAL_CONTROLS[controls]
    response_index = test.responses
    first = column(first, "first", owner)
    second = column(second, "second", owner, first.shape[0])
    given = {AXIAL_OBSERVABLES[test.controls[0]]: first, AXIAL_OBSERVABLES[test.controls[1]]: second}
    options = BoundaryValueOptions(segments=check_integer(segments, "segments", owner), atol=1e-11, ode_rtol=1e-11, ode_atol=1e-11,
                                   stability_pieces=0)
    curve = axial_response(rod, length, **given, mode="independent", options=options, progress=False)
    ok = np.asarray(curve.ok)
    if not ok.all():
        raise ValueError(f"{owner}: points {np.flatnonzero(~ok)[:20].tolist()} did not converge")
    obs = np.stack([np.asarray(getattr(curve, n)) for n in AXIAL_OBSERVABLES], -1)
    values = np.zeros((first.shape[0], 4))
    values[:, test.controls[0]] = first
    values[:, test.controls[1]] = second
    exact = obs[:, list(response_index)]
    if isinstance(noise, tuple):
        sig = np.array([float(noise[0]), float(noise[1])])
    else:
        sig = float(noise) * np.sqrt(np.mean(exact**2, axis=0))
    if np.any(sig < 0) or not np.all(np.isfinite(sig)):
        raise ValueError(f"synthetic_end_response_data: noise must be finite and >= 0, got {noise}")
    zero = np.all(sig == 0)
    if zero:
        sig = np.sqrt(np.mean(exact**2, axis=0))
    else:
        exact = exact + sig * np.asarray(random_normal(key, exact.shape))
    values[:, response_index[0]] = exact[:, 0]
    values[:, response_index[1]] = exact[:, 1]
    sigmas = {AXIAL_OBSERVABLES[i] + "_sigma": sig[j] for j, i in enumerate(response_index)}
    return EndResponseData(length, *values.T, controls=controls, segments=segments, **sigmas)


def synthetic_shape_data(
    rod,
    length: ArrayLike,
    s: ArrayLike,
    end: AbstractEnd | Sequence[AbstractEnd],
    noise: float,
    key: Array,
    *,
    start: Clamped | None = None,
    segments: int = 1,
) -> ShapeData:
    """Simulated centreline points of `rod` at arc lengths `s` under the end condition(s)
    `end` (one per image), clamped at `start` (default origin, identity), with isotropic
    Gaussian noise of standard deviation `noise` (absolute, length units; 0 gives exact
    points with `sigma = 1e-3 L`).  Solved with `solve_boundary_value` (default guess)."""
    check_key(key, "synthetic_shape_data")
    ends = [end] if isinstance(end, AbstractEnd) else list(end)
    start = Clamped() if start is None else start
    noise = float(noise)
    if not (np.isfinite(noise) and noise >= 0):
        raise ValueError(f"synthetic_shape_data: noise must be finite and >= 0, got {noise}")
    points = []
    for e in ends:
        sol = solve_boundary_value(rod, length, start=start, end=e, saveat=s, segments=segments, atol=1e-11, ode_rtol=1e-11, ode_atol=1e-11)
        points.append(np.asarray(sol.x))
    points = np.stack(points)
    sigma = noise if noise > 0 else 1e-3 * float(length)
    if noise > 0:
        points = points + noise * np.asarray(random_normal(key, points.shape))
    return ShapeData(length, s, points, ends, sigma=sigma, start=start, segments=segments)
