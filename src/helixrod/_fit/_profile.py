"""Profile-likelihood intervals of a fit: refit with one parameter held at a grid of values.

For a parameter $\\theta$ the profile $\\Delta\\chi^2(\\theta) = 2\\,[\\mathrm{cost}(\\theta) -
\\mathrm{cost}_{best}]$ minimises the cost over every other free parameter; the interval of
level $1-\\alpha$ is where $\\Delta\\chi^2 \\le \\chi^2_{1, 1-\\alpha}$ (3.84 at 95 %; Wilks'
theorem, as in pylake's profile likelihoods and Raue et al., Bioinformatics 25, 1923 (2009)).
Unlike value ± z stderr it follows a nonlinear or bounded likelihood (a persistence length
or a stiffness that must stay positive).  All refits of one profile run in one compiled call
(the held value is traced), each started at the fit, one after another (`jax.lax.map`, as the
fit's default multistart).  Vmapped, the lock-step solver of the tweezer model compiled for
minutes: the README's DNA profile (21 refits) took 560 s on a busy core, against 189 s
(84 s on a second call) one after another.
"""

from __future__ import annotations

from statistics import NormalDist

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._compile import filter_jit
from .._rod import PARAMETER_NAMES, rod_vector
from .._status import RESULTS
from ._parameters import Parameterisation
from ._pipeline import StiffnessFit, minimise


class ProfileLikelihood(eqx.Module):
    """The profile of one parameter (`profile_likelihood`): the held `values`, `delta_chi2`
    at each (NaN where the refit failed), `result` per refit, the fitted `best` value, and
    `interval` (lower, upper) at `level`, where the profile crosses `threshold`; an end is
    `-inf`/`inf` when the profile stays below it on that side of the grid (widen `span`),
    NaN when a refit failed on that side before it crossed (unknown, not unbounded)."""

    name: str = eqx.field(static=True)
    values: Float[Array, " k"]
    delta_chi2: Float[Array, " k"]
    result: RESULTS
    best: float
    level: float
    threshold: float
    interval: tuple[float, float]


@filter_jit
def _profile_refits(values, z0, model, param, solver, max_steps: int, indices: tuple[int, ...], in_extra: bool):
    def one(value):
        if in_extra:
            held = eqx.tree_at(lambda p: p.extra_values, param, param.extra_values.at[jnp.asarray(indices)].set(value))
        else:
            held = eqx.tree_at(lambda p: p.fixed_values, param, param.fixed_values.at[jnp.asarray(indices)].set(value))
        _, cost, result, _ = minimise(z0, model, held, solver, max_steps)
        return cost, result

    return jax.lax.map(one, values)


def profile_likelihood(
    fit: StiffnessFit, name: str, values=None, *, level: float = 0.95, span: float = 4.0, points: int = 21
) -> ProfileLikelihood:
    """The profile likelihood of the free parameter `name` of `fit` (from `fit_stiffness`):
    refits with `name` held at each of `values` (default: `points` values over the fit ±
    `span` standard errors, kept positive for a positive parameter), and the interval at
    `level` from the crossings of $\\chi^2_{1,level}$ (linear interpolation between grid
    points).  Same model, data, solver and other fixed parameters as the fit."""
    if fit.problem is None:
        raise ValueError("profile_likelihood needs the problem of a fit from fit_stiffness in this session (a fit_stiffness_linear result or a StiffnessFit.load-ed one has none)")
    if name not in fit.names:
        raise ValueError(f"profile_likelihood: {name!r} is not a free parameter of the fit; free: {fit.names}")
    if not 0 < level < 1:
        raise ValueError(f"profile_likelihood: level must be in (0, 1), got {level}")
    problem = fit.problem
    param: Parameterisation = problem.parameterisation
    best = float(fit.params[name])
    if values is None:
        stderr = float(fit.stderr[name])
        if not np.isfinite(stderr) or stderr <= 0:
            raise ValueError(f"profile_likelihood: the standard error of {name} is {stderr}; give values=")
        lo, hi = best - span * stderr, best + span * stderr
        positive = name in ("K1", "K2", "K3") or any(e.name == name and e.positive for e in param.extra)
        if positive and lo <= 0:
            lo = best / 10
        values = np.linspace(lo, hi, int(points))
    values = np.asarray(values, float)
    if values.ndim != 1 or values.size < 2 or not np.all(np.isfinite(values)):
        raise ValueError("profile_likelihood: values must be a 1-D array of at least two finite numbers")

    # The reduced parameterisation: `name` fixed (its value traced), everything else as fitted.
    fixed = dict(param.fixed)
    fixed.update({e.name: float(v) for e, v in zip(param.extra, np.asarray(param.extra_values)) if e.name not in param.extra_free})
    fixed[name] = best
    if param.isotropic and name == "K1":  # the tie K2 = K1 holds K2 with it
        fixed["K2"] = best
    # The tie K2 = K1 of an isotropic fit stays (held K1 fixes both; `Parameterisation`).
    held = Parameterisation(
        fixed, float(param.k_scale), float(param.u_scale), param.extra,
        dict(fixed, **{n: float(fit.params[n]) for n in param.extra_free if n != name}), param.isotropic,
    )
    p_fit = np.asarray(rod_vector(fit.rod))
    extra_fit = np.asarray(param.extra_vector(jnp.asarray([float(fit.params[n]) for n in param.names])))
    z0 = jnp.asarray(held.internal(p_fit, extra_fit))
    in_extra = name not in PARAMETER_NAMES
    if in_extra:
        indices = ([e.name for e in param.extra].index(name),)
    else:
        indices = (0, 1) if param.isotropic and name == "K1" else (PARAMETER_NAMES.index(name),)
    cost, result = _profile_refits(jnp.asarray(values), z0, problem.model, held, problem.solver, problem.max_steps, indices, in_extra)
    ok = np.asarray(result == RESULTS.successful) & np.isfinite(np.asarray(cost))
    delta = np.where(ok, 2 * (np.asarray(cost) - float(fit.cost)), np.nan)
    threshold = NormalDist().inv_cdf(0.5 + level / 2) ** 2  # chi^2 with one degree of freedom
    return ProfileLikelihood(
        name=name,
        values=jnp.asarray(values),
        delta_chi2=jnp.asarray(delta),
        result=result,
        best=best,
        level=float(level),
        threshold=float(threshold),
        interval=_crossings(values, delta, best, threshold),
    )


def _crossings(values, delta, best, threshold) -> tuple[float, float]:
    order = np.argsort(values)
    v, d = values[order], delta[order]
    ends = []
    for side in (-1, 1):
        grid = v[v < best][::-1] if side < 0 else v[v > best]
        prof = d[v < best][::-1] if side < 0 else d[v > best]
        inner_v, inner_d = best, 0.0
        crossing = -np.inf if side < 0 else np.inf
        for value, dd in zip(grid, prof):
            if not np.isfinite(dd):  # a failed refit: where the profile crosses is unknown
                crossing = np.nan
                break
            if dd >= threshold:
                crossing = inner_v + (threshold - inner_d) * (value - inner_v) / (dd - inner_d)
                break
            inner_v, inner_d = value, max(dd, 0.0)
        ends.append(float(crossing))
    return ends[0], ends[1]
