"""Observations of finite rods: end responses and centreline shapes, and synthetic data.

`EndResponseData`: a rod of known length (and, at fit time, known intrinsic shape) loaded
along its axis as `axial_ends` describes; two quantities are controlled (exact) and two
are measured (with standard deviations).  `ShapeData`: sampled centreline points
$x(s_i)$ (e.g. from an image) of a rod clamped at a known pose under known end conditions,
possibly several images under different loads.
"""

from __future__ import annotations

from collections.abc import Sequence

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._boundary import _CLAMPED, _LOADED, _TWEEZER, AbstractEnd, Clamped, _EndData, _Options, solve_boundary_value
from ._lie import CommutatorFreeRK4
from ._response import _curve

OBSERVABLES = ("force", "moment", "extension", "rotation")
#: Controlled pair -> (end kind, indices of the controls, indices of the responses) in OBSERVABLES.
CONTROLS = {
    "force-moment": (_LOADED, (0, 1), (2, 3)),
    "force-rotation": (_TWEEZER, (0, 3), (2, 1)),
    "extension-rotation": (_CLAMPED, (2, 3), (0, 1)),
}


def _column(x, name, owner, n=None):
    a = np.asarray(x, dtype=float)
    if n is not None and a.ndim == 0:
        a = np.full(n, float(a))
    if a.ndim != 1 or (n is not None and a.shape != (n,)):
        raise ValueError(f"{owner}: {name} must be one-dimensional{'' if n is None else f' of length {n}'}, got shape {a.shape}")
    bad = np.flatnonzero(~np.isfinite(a))
    if bad.size:
        raise ValueError(f"{owner}: {name} has non-finite values in rows {bad[:20].tolist()}")
    return a


def _positive_scalar(x, name, owner):
    v = float(np.asarray(x, dtype=float))
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"{owner}: {name} must be finite and > 0, got {v}")
    return v


def _segments(segments, owner):
    if isinstance(segments, bool) or not isinstance(segments, (int, np.integer)) or segments < 1:
        raise ValueError(f"{owner}: segments must be an integer >= 1, got {segments!r}")
    return int(segments)


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
        if controls not in CONTROLS:
            raise ValueError(f"{owner}: controls must be one of {tuple(CONTROLS)}, got {controls!r}")
        length = _positive_scalar(length, "length", owner)
        columns = {n: _column(v, n, owner) for n, v in zip(OBSERVABLES, (force, moment, extension, rotation))}
        sizes = {n: c.shape[0] for n, c in columns.items()}
        if len(set(sizes.values())) != 1 or 0 in sizes.values():
            raise ValueError(f"{owner}: columns must have one common, non-zero length, got {sizes}")
        n = sizes["force"]
        sigmas = dict(zip(OBSERVABLES, (force_sigma, moment_sigma, extension_sigma, rotation_sigma)))
        _, _, responses = CONTROLS[controls]
        sigma = []
        for i in responses:
            name = OBSERVABLES[i]
            if sigmas[name] is None:
                raise ValueError(f"{owner}: {name} is measured with controls={controls!r}: give {name}_sigma")
            col = _column(sigmas[name], f"{name}_sigma", owner, n)
            if np.any(col <= 0):
                raise ValueError(f"{owner}: {name}_sigma must be > 0; rows {np.flatnonzero(col <= 0)[:20].tolist()} are not")
            sigma.append(col)
        dtype = jnp.result_type(float)
        self.length = jnp.asarray(length, dtype)
        for name in OBSERVABLES:
            setattr(self, name, jnp.asarray(columns[name], dtype))
        self.sigma = jnp.asarray(np.stack(sigma, 1), dtype)
        self.controls = controls
        self.segments = _segments(segments, owner)

    def __len__(self) -> int:
        return int(self.force.shape[0])

    @property
    def values(self) -> Float[Array, "n 4"]:
        """The columns stacked as `(n, 4)` = (force, moment, extension, rotation)."""
        return jnp.stack([self.force, self.moment, self.extension, self.rotation], -1)

    @property
    def responses(self) -> tuple[str, str]:
        """Names of the two measured columns."""
        return tuple(OBSERVABLES[i] for i in CONTROLS[self.controls][2])


def _stack_ends(end) -> _EndData:
    ends = [end] if isinstance(end, AbstractEnd) else list(end)
    if not ends or not all(isinstance(e, AbstractEnd) for e in ends):
        raise ValueError("ShapeData: end must be a Clamped, Loaded or Tweezer, or a sequence of them (one per image)")
    datas = [e.end_data() for e in ends]
    return jax.tree.map(lambda *a: jnp.stack(a), *datas)


class ShapeData(eqx.Module):
    """Centreline points of a finite rod under known end conditions.

    - `length` $L > 0$; `s` `(p,)` arc lengths of the sampled points, increasing in $[0, L]$.
    - `points`: lab positions `(p, 3)`, or `(m, p, 3)` for `m` images under different loads.
    - `end`: the end condition (`Clamped`, `Loaded` or `Tweezer`), or a sequence of `m` of
      them, one per image; `start`: the clamp at $s = 0$ (default: origin, identity frame).
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
    end: _EndData
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
        length = _positive_scalar(length, "length", owner)
        s = _column(s, "s", owner)
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
        dtype = jnp.result_type(float)
        self.length = jnp.asarray(length, dtype)
        self.s = jnp.asarray(s, dtype)
        self.points = jnp.asarray(pts, dtype)
        self.sigma = jnp.asarray(sig, dtype)
        self.start = start
        self.end = ends
        self.segments = _segments(segments, owner)

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
    if controls not in CONTROLS:
        raise ValueError(f"synthetic_end_response_data: controls must be one of {tuple(CONTROLS)}, got {controls!r}")
    kind, control_index, response_index = CONTROLS[controls]
    first = _column(first, "first", "synthetic_end_response_data")
    second = _column(second, "second", "synthetic_end_response_data", first.shape[0])
    dtype = jnp.result_type(float)
    values = np.zeros((first.shape[0], 4))
    values[:, control_index[0]] = first
    values[:, control_index[1]] = second
    options = _Options(
        segments=_segments(segments, "synthetic_end_response_data"), solver=CommutatorFreeRK4(), max_ode_steps=16_384,
        adjoint=diffrax.ForwardMode(), method="levenberg-marquardt", max_steps=64, continuation=0, guess_kind="helix",
    )
    tolerances = jnp.asarray([1e-11, 1e-11, 1e-11, 1e-11], dtype)
    obs, _, sols, _ = _curve(rod, jnp.asarray(length, dtype), jnp.asarray(kind), jnp.asarray(values, dtype), tolerances, options, "independent")
    obs, ok = np.asarray(obs), np.asarray(sols.ok)
    if not ok.all():
        raise ValueError(f"synthetic_end_response_data: points {np.flatnonzero(~ok)[:20].tolist()} did not converge")
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
        exact = exact + sig * np.asarray(jax.random.normal(key, exact.shape))
    values[:, response_index[0]] = exact[:, 0]
    values[:, response_index[1]] = exact[:, 1]
    sigmas = {OBSERVABLES[i] + "_sigma": sig[j] for j, i in enumerate(response_index)}
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
    ends = [end] if isinstance(end, AbstractEnd) else list(end)
    start = Clamped() if start is None else start
    noise = float(noise)
    if not (np.isfinite(noise) and noise >= 0):
        raise ValueError(f"synthetic_shape_data: noise must be finite and >= 0, got {noise}")
    points = []
    for e in ends:
        sol = solve_boundary_value(rod, length, start=start, end=e, saveat=s, segments=segments, rtol=1e-11, atol=1e-11, ode_rtol=1e-11, ode_atol=1e-11)
        points.append(np.asarray(sol.x))
    points = np.stack(points)
    sigma = noise if noise > 0 else 1e-3 * float(length)
    if noise > 0:
        points = points + noise * np.asarray(jax.random.normal(key, points.shape))
    return ShapeData(length, s, points, ends, sigma=sigma, start=start, segments=segments)
