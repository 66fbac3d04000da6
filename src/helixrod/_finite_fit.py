"""Stiffness fits through the boundary-value solver: the finite-rod forward models of
`fit_stiffness`.

The parameterisation (positive-definite internal coordinates), the multistart
Levenberg--Marquardt solver, the covariance and the identifiability report are those of
`helixrod._fit`; only the forward model differs, plugged in through `_Spec.model`:

- `EndResponseData`: each point is a `solve_boundary_value` solve of the rod (length $L$,
  canonical placement, `axial_ends` conditions set by the two controls), all points in
  parallel (`vmap`), each from the bulk-helix guess; residuals are the two measured
  responses minus the predictions, over their sigmas.
- `ShapeData`: one solve per image, saved at the sampled arc lengths; residuals are the
  centreline coordinates minus the points, over sigma.

Derivatives: forward mode throughout -- `jax.jacfwd` of the residuals pushes one tangent per
free parameter through the implicit function theorem of the shooting root (one linear
solve with the shooting Jacobian, which the root solve has) and through the flows of the
pieces (diffrax `ForwardMode`).  Reverse mode (`jax.jacrev`, with `diffrax.DirectAdjoint`)
gives the same Jacobian but was slower for 5-8 parameters (`benchmarks/bench_finite.py`).

No frame symmetry applies: the clamp fixes the director frame in the lab, so relabelling
$d_1, d_2$ or reading the rod end for end changes the predictions.  A clamped-clamped shape
without a measured load does not fix the scale of $K$ (scaling $K$ scales the wrench, not
the shape): the identifiability report then shows that null direction.
"""

from __future__ import annotations

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._boundary import _Options as _SolveOptions, _solve
from ._finite_data import CONTROLS, EndResponseData, ShapeData
from ._fit import (
    PARAM_NAMES,
    StiffnessFit,
    _as_vector,
    _closest_in_orbit,
    _full_vector,
    _full_vectors,
    _internal_from_physical,
    _multistart,
    _Options,
    _perturbed_starts,
    _Problem,
    _resolve_fixed,
    _rod_from_vector,
    _Spec,
    _summarise,
)
from ._lie import CommutatorFreeRK4
from ._response import _curve
from ._rod import Rod

FINITE_DATA = (EndResponseData, ShapeData)
#: Tolerances of the forward model: root (rtol, atol) and integration (rtol, atol).
MODEL_TOLERANCES = (1e-10, 1e-10, 1e-10, 1e-10)


def _solve_options(segments: int) -> _SolveOptions:
    return _SolveOptions(
        segments=segments, solver=CommutatorFreeRK4(), max_ode_steps=16_384, adjoint=diffrax.ForwardMode(),
        method="levenberg-marquardt", max_steps=64, continuation=0, guess_kind="helix",
    )


@dataclasses.dataclass(frozen=True)
class _EndResponseModel:
    """Residuals of end-response data (hashable: part of the static fit spec)."""

    kind: int
    responses: tuple[int, int]
    segments: int

    def predict(self, p_full, arrays):
        rod = _rod_from_vector(p_full)
        obs, _, _, _ = _curve(
            rod, arrays["length"], jnp.asarray(self.kind, jnp.int32), arrays["values"], arrays["tolerances"],
            _solve_options(self.segments), "independent", hints=arrays["values"][:, 3],
        )
        return obs[:, list(self.responses)]

    def residuals_from(self, prediction, arrays):
        return ((prediction - arrays["observed"]) / arrays["sigma"]).T.reshape(-1)

    def __call__(self, p_full, arrays):
        return self.residuals_from(self.predict(p_full, arrays), arrays)


@dataclasses.dataclass(frozen=True)
class _ShapeModel:
    """Residuals of centreline data (hashable: part of the static fit spec)."""

    segments: int

    def predict(self, p_full, arrays):
        rod = _rod_from_vector(p_full)
        options = _solve_options(self.segments)

        def one(end):
            sol = _solve(rod, arrays["length"], arrays["start"], end, None, arrays["s"], arrays["tolerances"], options)
            return jnp.where(sol.ok, sol.x, jnp.nan)

        return jax.vmap(one)(arrays["end"])

    def residuals_from(self, prediction, arrays):
        return ((prediction - arrays["points"]) / arrays["sigma"][..., None]).reshape(-1)

    def __call__(self, p_full, arrays):
        return self.residuals_from(self.predict(p_full, arrays), arrays)


def _model_and_arrays(data, dtype):
    tolerances = jnp.asarray(MODEL_TOLERANCES, dtype)
    if isinstance(data, EndResponseData):
        kind, _, responses = CONTROLS[data.controls]
        model = _EndResponseModel(kind, tuple(responses), data.segments)
        values = data.values
        arrays = {
            "length": data.length,
            "values": values,
            "observed": values[:, list(responses)],
            "sigma": data.sigma,
            "tolerances": tolerances,
        }
        return model, arrays
    model = _ShapeModel(data.segments)
    arrays = {
        "length": data.length,
        "s": data.s,
        "points": data.points,
        "sigma": data.sigma,
        "start": data.start,
        "end": data.end,
        "tolerances": tolerances,
    }
    return model, arrays


def _end_response_init(data: EndResponseData, uhat):
    """Isotropic rod $K = \\mathrm{diag}(B, B, C)$ from the bulk-helix equations at each
    point (end effects neglected): with $|u| = \\Theta/L$, $u_3 = h\\Theta/L^2$, the multipliers
    $\\mu_2 = F/|u|$, $\\mu_1 = (M - \\mu_2 u_3/|u|)/|u|$ and the register aligned with
    $\\hat u$, $B(\\kappa - \\hat\\kappa) = \\mu_1\\kappa$ and $C(u_3 - \\hat u_3) = \\mu_1 u_3 + \\mu_2$:
    linear least squares for $B$ and $C$.  Returns (B, C), or None if ill-posed."""
    L = float(data.length)
    F, M, h, theta = (np.asarray(getattr(data, n)) for n in ("force", "moment", "extension", "rotation"))
    norm = theta / L
    u3 = h * theta / L**2
    kappa = np.sqrt(np.maximum(norm**2 - u3**2, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        mu2 = F / norm
        mu1 = (M - mu2 * u3 / norm) / norm
    kappa_hat = float(np.hypot(uhat[0], uhat[1]))
    a_b, b_b = kappa - kappa_hat, mu1 * kappa
    a_c, b_c = u3 - uhat[2], mu1 * u3 + mu2
    out = []
    for a, b in ((a_b, b_b), (a_c, b_c)):
        good = np.isfinite(a) & np.isfinite(b)
        denom = float(np.sum(a[good] ** 2))
        if not good.any() or denom <= 0:
            return None
        out.append(float(np.sum(a[good] * b[good]) / denom))
    B, C = out
    if not (np.isfinite(B) and np.isfinite(C)) or B <= 0 or C <= 0:
        return None
    return B, C


def _shape_scale(data: ShapeData) -> float:
    """A stiffness that bends the rod by about a radian under the end loads:
    $|M|L + |F|L^2/2$ (1 when no load is prescribed)."""
    L = float(data.length)
    force = np.max(np.linalg.norm(np.asarray(data.end.force), axis=-1))
    moment = np.max(np.linalg.norm(np.asarray(data.end.moment), axis=-1))
    scale = moment * L + 0.5 * force * L**2
    return float(scale) if scale > 0 and np.isfinite(scale) else 1.0


@eqx.filter_jit
def _jacobian_and_predictions(q, arrays, spec: _Spec):
    """Jacobian of the normalised residuals with respect to the free physical parameters,
    the residuals and the predictions, in one compiled program."""

    def residuals(qq):
        p_full = _full_vector(qq, spec, arrays)
        prediction = spec.model.predict(p_full, arrays)
        r = spec.model.residuals_from(prediction, arrays)
        return r, (r, prediction)

    return jax.jacfwd(residuals, has_aux=True)(q)


def fit_finite(
    data,
    *,
    uhat,
    fit_uhat,
    fix,
    init,
    method,
    n_starts,
    key,
    absolute_sigma,
    rtol,
    atol,
    max_steps,
    learning_rate,
    weak_threshold,
) -> StiffnessFit:
    """`fit_stiffness` for `EndResponseData` and `ShapeData` (see `fit_stiffness`)."""
    if method not in ("levenberg-marquardt", "gauss-newton"):
        raise ValueError(
            f"fit_stiffness: method={method!r} is not available for finite-rod data (the forward model "
            "is differentiated in forward mode); use 'levenberg-marquardt' or 'gauss-newton'"
        )
    n_starts = 1 if n_starts is None else int(n_starts)
    if n_starts < 1:
        raise ValueError(f"n_starts must be >= 1, got {n_starts}")
    free, fixed = _resolve_fixed(uhat, fit_uhat, fix)
    dtype = jnp.result_type(float)
    u_fixed = np.array([fixed.get(n, 0.0) for n in PARAM_NAMES[5:]])
    if isinstance(data, EndResponseData):
        guess = _end_response_init(data, u_fixed)
        B, C = guess if guess is not None else (1.0, 1.0)
    else:
        B = C = _shape_scale(data)
    default = np.array([B, B, C, 0.0, 0.0, *u_fixed])
    p0 = _as_vector(init, fixed, default)
    k_scale = float(np.sqrt(p0[0] * p0[1]))
    u_norm = float(np.linalg.norm(p0[5:]))
    u_scale = u_norm if u_norm > 0 else 1.0 / float(data.length)
    model, model_arrays = _model_and_arrays(data, dtype)
    spec = _Spec(
        free=free,
        fixed_names=tuple(n for n in PARAM_NAMES if n in fixed),
        branch="nearest",
        use_register=False,
        fit_register=False,
        errors_in_variables=False,
        model=model,
    )
    problem = _Problem(spec, tuple(sorted(fixed.items())), k_scale, u_scale)
    opts = _Options(method, float(rtol), float(atol), int(max_steps), float(learning_rate))
    arrays = {
        "fixed_values": jnp.asarray([fixed.get(n, 0.0) for n in PARAM_NAMES], dtype),
        "k_scale": jnp.asarray(k_scale, dtype),
        "u_scale": jnp.asarray(u_scale, dtype),
        **model_arrays,
    }
    z_base = _internal_from_physical(p0, problem)
    key = jax.random.key(0) if key is None else key
    z0s = _perturbed_starts(z_base, problem, n_starts, key)
    z, cost, ok, steps = (np.asarray(x) for x in _multistart(jnp.asarray(z0s), arrays, spec, opts, "map"))
    best = int(np.argmin(np.where(np.isfinite(cost), cost, np.inf)))
    p_all = np.asarray(_full_vectors(jnp.asarray(z), arrays, spec))
    p_best = p_all[best]
    scale = np.array([k_scale] * 5 + [u_scale] * 3)
    agree = sum(
        1
        for i in range(len(cost))
        if np.isfinite(cost[i])
        and abs(cost[i] - cost[best]) <= 1e-6 * (1 + cost[best])
        and np.max(np.abs(_closest_in_orbit(p_all[i], p_best, problem) - p_best) / scale) <= 1e-4
    )
    q = np.array([p_best[PARAM_NAMES.index(n)] for n in free])
    J, (r, predicted) = _jacobian_and_predictions(jnp.asarray(q), arrays, spec)
    slot = jnp.zeros(0, jnp.int32)
    params, errs, cov, corr, cost_best, chi2r, ident = _summarise(
        J, r, q, free, problem, absolute_sigma=absolute_sigma, weak_threshold=weak_threshold
    )
    predicted = np.asarray(predicted)
    if isinstance(data, EndResponseData):
        predictions = {name: jnp.asarray(predicted[:, j]) for j, name in enumerate(data.responses)}
    else:
        predictions = {"points": jnp.asarray(predicted)}
    success = bool(ok[best]) and bool(np.isfinite(cost_best))
    message = "converged" if success else f"best start did not report convergence ({method}, {int(steps[best])} steps)"
    empty = jnp.zeros(0)
    return StiffnessFit(
        rod=Rod(*p_best[:5], uhat=p_best[5:]),
        names=free,
        params=params,
        stderr=errs,
        covariance=cov,
        correlation=corr,
        cost=cost_best,
        chi2_reduced=chi2r,
        residuals=jnp.asarray(r),
        slot=slot,
        predicted_force=predictions.get("force", empty),
        predicted_moment=predictions.get("moment", empty),
        success=success,
        message=message,
        n_steps=int(steps[best]),
        n_starts=len(cost),
        n_agree=agree,
        start_costs=jnp.asarray(cost),
        identifiability=ident,
        method=method,
        absolute_sigma=absolute_sigma,
        spec=problem,
        options=opts,
        predicted=predictions,
    )
