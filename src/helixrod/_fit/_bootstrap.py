"""Bootstrap replicates of a fit: resampled or redrawn data, refitted in one vmapped call
(or, while progress is shown, in host-side batches of one compiled vmapped call)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._compile import filter_jit
from .._misc import check_integer, check_key
from .._progress import ProgressArgument, batch_size, check_progress, progress_bar, scan_in_batches
from .._rod import PARAMETER_NAMES, rod_vector
from .._status import RESULTS, raise_if_failed, succeeded
from ._pipeline import StiffnessFit, minimise
from ._symmetry import closest_in_orbit

KINDS = ("cases", "parametric")


class Bootstrap(eqx.Module):
    """Bootstrap replicates of a fit.  `samples`: mapping name -> array (n,) (replicates
    that failed to converge are NaN); `result` per replicate (a `RESULTS` code) and `ok`;
    `std` by name; `interval(level)` percentile intervals by name.  Replicates are mapped to
    the member of their symmetry orbit nearest the original fit, so a discrete symmetry
    never splits the distribution."""

    names: tuple[str, ...] = eqx.field(static=True)
    samples: dict
    result: RESULTS
    kind: str = eqx.field(static=True)

    @property
    def ok(self) -> Array:
        """Whether each replicate converged (to a finite cost)."""
        return self.result == RESULTS.successful

    @property
    def std(self) -> dict:
        """Standard deviation of the replicates (converged ones) by parameter name."""
        return {n: jnp.asarray(np.nanstd(np.asarray(v), ddof=1)) for n, v in self.samples.items()}

    def interval(self, level: float = 0.95) -> dict[str, tuple[float, float]]:
        """Percentile interval `(lower, upper)` holding `level` of the replicates, by name."""
        if not 0 < level < 1:
            raise ValueError(f"interval: level must be in (0, 1) (0.95 for 95 %), got {level}")
        lo, hi = 50 * (1 - level), 50 * (1 + level)
        return {n: (float(np.nanpercentile(v, lo)), float(np.nanpercentile(v, hi))) for n, v in self.samples.items()}


@filter_jit
def _refits(z0, models, param, solver, max_steps: int):
    def one(model):
        z, cost, result, _ = minimise(z0, model, param, solver, max_steps)
        finite = jnp.isfinite(cost)
        result = RESULTS.where(finite | (result != RESULTS.successful), result, RESULTS.cost_not_finite)
        q = param.physical(z)
        return param.full(q), q, result

    return jax.vmap(one)(models)


def bootstrap(
    data, fit: StiffnessFit, n: int, key: Array, *, kind: str = "cases", throw: bool = False,
    progress: ProgressArgument = None,
) -> Bootstrap:
    """`n` bootstrap refits of `fit` on resampled `data`, vmapped, each started at `fit`.

    `kind="cases"` resamples data points with replacement (no trust in sigma needed);
    `"parametric"` redraws the observations around the fitted predictions with the data's
    sigmas.  Same model, options and solver as `fit` (helix data); with errors in
    variables each replicate holds the weights of `fit`'s solution (its effective
    covariances, resampled with their points), one least-squares problem per replicate.
    Returns a `Bootstrap`; `throw=True` raises `SolverError` if a replicate fails
    (default: it is NaN and flagged).

    `progress`: `None` (default) shows a rich progress bar of the replicates when stdout is
    a terminal, `True`/`False` force it on or off, and a callable is called as
    `progress(done, total)` (replicates refitted, `n`) instead of a bar.  While progress is
    shown the replicates are refitted in up to 20 host-side batches (one compiled program,
    the last batch padded); the replicates are the same either way.
    """
    if fit.problem is None:
        raise ValueError("bootstrap needs the problem of a fit from fit_stiffness in this session (a fit_stiffness_linear result or a StiffnessFit.load-ed one has none)")
    if kind not in KINDS:
        raise ValueError(f"kind must be 'cases' or 'parametric', got {kind!r}")
    n = check_integer(n, "n", "bootstrap", minimum=2)
    check_key(key, "bootstrap")
    check_progress(progress, "bootstrap")
    problem = fit.problem
    model = problem.model.with_data(data)
    if model.holds_weights:  # errors in variables: the weights of the fit's solution, held
        model = model.with_weights_held(fit.predicted)
    param = problem.parameterisation
    models = model.replicates(kind, int(n), key, fit.predicted)
    p_fit = np.asarray(rod_vector(fit.rod))
    extra_fit = np.asarray(param.extra_vector(jnp.asarray([float(fit.params[n]) for n in param.names])))
    z0 = jnp.asarray(param.internal(p_fit, extra_fit))
    with progress_bar("bootstrap", int(n), progress, owner="bootstrap") as report:
        if report.shown:
            refit = lambda _, batch: (None, _refits(z0, batch, param, problem.solver, problem.max_steps))  # noqa: E731
            _, (p, q, results) = scan_in_batches(refit, None, models, int(n), batch_size(n), report)
        else:  # one call: nothing is slower for want of a bar
            p, q, results = _refits(z0, models, param, problem.solver, problem.max_steps)
    p, q = np.array(p), np.array(q)
    ok = succeeded(results)
    p = closest_in_orbit(p, p_fit, param, model.frame_observed)
    p[~ok] = np.nan
    q[~ok] = np.nan
    own = {name: q[:, len(param.free) + i] for i, name in enumerate(param.extra_free)}
    samples = {
        name: jnp.asarray(own[name] if name in own else p[:, PARAMETER_NAMES.index(name)]) for name in fit.names
    }
    boot = Bootstrap(names=fit.names, samples=samples, result=results, kind=kind)
    return raise_if_failed(boot, boot.result, "bootstrap: replicates did not converge") if throw else boot
