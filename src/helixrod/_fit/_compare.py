"""Model selection: the reference report's four classes of rods (or any `fix=` patterns)
fitted to one data set, side by side, with information criteria and likelihood-ratio
tests between nested classes.

The classes (Durickovic 2008, the inverse spring problem): `"isotropic"` -- $K_1 = K_2$, no
bend-twist coupling (2 stiffnesses); `"anisotropic"` -- $K_1, K_2, K_3$, no coupling (3);
`"isotropic-coupled"` -- $K_1 = K_2$ with a coupling (3: with isotropic bending the frame
can be turned about $d_3$ until the coupling lies in $K_{13}$, so $K_{23} = 0$ is a choice
of gauge, not a restriction -- where the turn is free: it turns $(\\hat u_1, \\hat u_2)$ and
the register too, so with an observed register or a fixed $\\hat u$ that has an in-plane
part the class frees both couplings, 4); `"general"` -- all five.  When $\\hat u$ is fitted, the
isotropic class fixes $\\hat u_2 = 0$ the same way (`with_gauge`).  Nested pairs are read off the
constraints: a model is nested in another when it keeps every constraint of the other.

Likelihood-ratio tests (Wilks 1938): $\\Lambda = 2(\\log L_\\text{large} - \\log L_\\text{small})$,
$\\chi^2$-distributed with $p_\\text{large} - p_\\text{small}$ degrees of freedom when the smaller
model holds and sits in the interior of the larger one with its extra parameters locally
identifiable.  Two cases of the four classes are not regular and their p-values are only
indicative: without an observed register, $K_1 = K_2$ is the fixed point of the quarter-turn
frame symmetry, and $K_{13} = K_{23} = 0$ (with $\\hat u_{1,2} = 0$) that of the end-for-end
flips, so the predictions are even in the extra parameters there.  Information criteria:
Akaike (1974), Schwarz (1978); Akaike weights $\\propto e^{-\\Delta\\mathrm{AIC}/2}$
(Burnham & Anderson 2002).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._compile import filter_jit
from .._misc import check_integer, check_key, chi2_survival
from .._rod import rod_vector
from .._status import RESULTS, result_name
from ._helix_data import HelixData
from ._pipeline import StiffnessFit, fit_stiffness, minimise
from ._symmetry import coupling_gauge_free

#: The model classes of the reference report, as `fit_stiffness` options.
MODEL_CLASSES = {
    "isotropic": {"isotropic": True, "fix": {"K13": 0.0, "K23": 0.0}},
    "anisotropic": {"fix": {"K13": 0.0, "K23": 0.0}},
    "isotropic-coupled": {"isotropic": True, "fix": {"K23": 0.0}},
    "general": {},
}
CRITERIA = ("bic", "aic")
_SPEC_KEYS = ("fix", "isotropic")


class ModelComparison(eqx.Module):
    """The result of `compare_models`.

    `names`: the models in the order fitted (fewest free parameters first); `fits`: name ->
    `StiffnessFit`; `table`: name -> {"n_params", "n_residuals", "cost", "chi2_reduced",
    "log_likelihood", "aic", "bic", "delta_aic", "delta_bic", "akaike_weight", "rank",
    "identifiable" (every free parameter determined: full rank, finite standard errors),
    "ok" (converged), "result" (the name of the fit's `RESULTS` code)}; `tests`: the
    likelihood-ratio tests of nested pairs, each {"smaller", "larger", "statistic", "df",
    "p_value"}; `best`: the recommended model -- the lowest `criterion` among the
    converged, identifiable fits (among all converged fits when none is identifiable);
    `criterion`: "bic" or "aic"; `reason`: why `best`."""

    names: tuple[str, ...] = eqx.field(static=True)
    fits: dict
    table: dict = eqx.field(static=True)
    tests: tuple = eqx.field(static=True)
    best: str = eqx.field(static=True)
    criterion: str = eqx.field(static=True)
    reason: str = eqx.field(static=True)

    def simulate_test(self, smaller: str, larger: str, n: int = 200, key: Array | None = None) -> SimulatedTest:
        """The likelihood-ratio test of `smaller` in `larger` against its simulated null
        distribution (a parametric bootstrap, Efron & Tibshirani 1993, ch. 16): `n` data sets
        drawn around the predictions of the `smaller` fit with the data's sigmas (with
        errors in variables, that fit's effective covariances, held in the refits), each
        refitted by both models in vmapped calls (the smaller from its fit, the larger from
        both fits, keeping the lower cost; local refits: where the larger model has distant
        minima they miss, the simulated statistics fall short and the p-value is too small).  Valid where the $\\chi^2$ reference is not
        (a smaller model at a symmetry fixed point, on a boundary).  Helix data only
        (`bootstrap`'s replicates); `key` default `jax.random.key(0)`."""
        pair = next((t for t in self.tests if t["smaller"] == smaller and t["larger"] == larger), None)
        if pair is None:
            pairs = [(t["smaller"], t["larger"]) for t in self.tests]
            raise ValueError(f"simulate_test: {smaller!r} is not nested in {larger!r} here; nested pairs: {pairs}")
        n = check_integer(n, "n", "simulate_test", minimum=2)
        small, large = self.fits[smaller], self.fits[larger]
        key = jax.random.key(0) if key is None else check_key(key, "simulate_test")
        models = small.problem.model.replicates("parametric", int(n), key, small.predicted)
        costs, oks = [], []
        # The larger model starts from both fits: the smaller one's may be a stationary point
        # of the larger model (a symmetry fixed point, K1 = K2 say) that a local solver never leaves.
        for fit, starts in ((small, (small,)), (large, (small, large))):
            param = fit.problem.parameterisation
            best_cost = None
            for start in starts:
                z0 = jnp.asarray(param.internal(np.asarray(rod_vector(start.rod)), np.asarray(param.extra_values)))
                cost, result = _replicate_costs(z0, models, param, fit.problem.solver, fit.problem.max_steps)
                cost = np.where(np.asarray(result == RESULTS.successful), np.asarray(cost), np.inf)
                best_cost = cost if best_cost is None else np.minimum(best_cost, cost)
            costs.append(best_cost)
            oks.append(np.isfinite(best_cost))
        m = small.n_residuals
        if small.absolute_sigma:
            samples = 2.0 * (costs[0] - costs[1])
        else:
            samples = m * np.log(costs[0] / costs[1])
        ok = oks[0] & oks[1]
        samples = np.where(ok, np.maximum(samples, 0.0), np.nan)
        good = samples[ok]
        p_value = float((1 + np.sum(good >= pair["statistic"])) / (1 + good.size)) if good.size else float("nan")
        return SimulatedTest(
            smaller=smaller, larger=larger, statistic=pair["statistic"], df=pair["df"], samples=jnp.asarray(samples),
            ok=jnp.asarray(ok), p_value=p_value, p_value_chi2=pair["p_value"],
        )

    def summary(self) -> str:
        """A plain-text table of the models, the tests and the recommendation (also `repr`)."""
        width = max(len(n) for n in self.names)
        lines = [
            f"{'model':<{width}}  {'k':>2}  {'cost':>11}  {'chi2_red':>8}  {'AIC':>11}  {'dAIC':>7}  "
            f"{'BIC':>11}  {'dBIC':>7}  {'weight':>6}  identifiable"
        ]
        for n in self.names:
            row = self.table[n]
            flag = "yes" if row["identifiable"] else f"no (rank {row['rank']})"
            flag += "" if row["ok"] else f", not converged ({row['result']})"
            lines.append(
                f"{n:<{width}}  {row['n_params']:>2}  {row['cost']:>11.5g}  {row['chi2_reduced']:>8.4g}  {row['aic']:>11.6g}  "
                f"{row['delta_aic']:>7.3g}  {row['bic']:>11.6g}  {row['delta_bic']:>7.3g}  {row['akaike_weight']:>6.3f}  {flag}"
            )
        for t in self.tests:
            lines.append(
                f"likelihood ratio {t['smaller']} in {t['larger']}: {t['statistic']:.4g} on {t['df']} df, p = {t['p_value']:.3g}"
            )
        lines.append(f"recommended: {self.best} ({self.reason})")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return self.summary()

    def to_dict(self) -> dict:
        """Plain-Python form (JSON-serialisable): the table, the tests, the recommendation and
        each fit's `to_dict`."""
        return {
            "names": list(self.names),
            "table": {n: dict(self.table[n]) for n in self.names},
            "tests": [dict(t) for t in self.tests],
            "best": self.best,
            "criterion": self.criterion,
            "reason": self.reason,
            "fits": {n: self.fits[n].to_dict() for n in self.names},
        }


class SimulatedTest(eqx.Module):
    """A likelihood-ratio test with its simulated null distribution
    (`ModelComparison.simulate_test`): the observed `statistic`, its `df`, the simulated
    `samples` `(n,)` (NaN where a refit failed; `ok`), the simulated `p_value` (with the
    usual +1 correction, Davison & Hinkley 1997) and the $\\chi^2$ one, `p_value_chi2`."""

    smaller: str = eqx.field(static=True)
    larger: str = eqx.field(static=True)
    statistic: float
    df: int = eqx.field(static=True)
    samples: Array
    ok: Array
    p_value: float
    p_value_chi2: float


@filter_jit
def _replicate_costs(z0, models, param, solver, max_steps: int):
    def one(model):
        _, cost, result, _ = minimise(z0, model, param, solver, max_steps)
        return cost, result

    return jax.vmap(one)(models)


def model_options(name, spec) -> dict:
    """The `fit_stiffness` options (`fix`, `isotropic`) of a model given as a class name of
    `MODEL_CLASSES` or as such a mapping; `ValueError` otherwise."""
    if isinstance(spec, str):
        if spec not in MODEL_CLASSES:
            raise ValueError(f"unknown model class {spec!r}; classes are {tuple(MODEL_CLASSES)}")
        spec = MODEL_CLASSES[spec]
    if not isinstance(spec, Mapping) or any(k not in _SPEC_KEYS for k in spec):
        raise ValueError(
            f"model {name!r} must be a class name {tuple(MODEL_CLASSES)} or a mapping with "
            f"keys {_SPEC_KEYS} (e.g. {{'fix': {{'K13': 0}}, 'isotropic': True}}), got {spec!r}"
        )
    return {"fix": {k: float(v) for k, v in dict(spec.get("fix") or {}).items()}, "isotropic": bool(spec.get("isotropic", False))}


def with_gauge(options: dict, fit_uhat: bool, frame_observed: bool) -> dict:
    """`options` with $\\hat u_2 = 0$ fixed where it is a gauge: an isotropic, uncoupled rod
    whose $\\hat u$ is fitted and whose frame the data do not observe (turning the frame
    about $d_3$ turns $(\\hat u_1, \\hat u_2)$ and changes no prediction)."""
    fix = options["fix"]
    uncoupled = fix.get("K13") == 0.0 and fix.get("K23") == 0.0
    if options["isotropic"] and uncoupled and fit_uhat and not frame_observed and "uhat2" not in fix:
        return {**options, "fix": {**fix, "uhat2": 0.0}}
    return options


def _in_plane_twist_pinned(fit_options: Mapping, fix: Mapping) -> bool:
    """Whether the fits hold an in-plane intrinsic twist $(\\hat u_1, \\hat u_2) \\ne 0$
    fixed (`uhat=`, or `fix=` of uhat1/uhat2 with `fit_uhat=True`)."""
    if fit_options.get("fit_uhat"):
        return any(float(fix.get(n, 0.0)) != 0.0 for n in ("uhat1", "uhat2"))
    uhat = fit_options.get("uhat")
    in_plane = (0.0, 0.0) if uhat is None else tuple(float(x) for x in np.asarray(uhat, float).ravel()[:2])
    return any(x != 0.0 for x in in_plane) or any(float(fix.get(n, 0.0)) != 0.0 for n in ("uhat1", "uhat2"))


def _constraints(spec: dict) -> frozenset:
    out = {("fix", k, float(v)) for k, v in (spec.get("fix") or {}).items()}
    return frozenset(out | ({("isotropic",)} if spec.get("isotropic") else set()))


def compare_models(
    data,
    models: Sequence[str] | Mapping[str, str | Mapping] | None = None,
    *,
    criterion: str = "bic",
    **fit_options,
) -> ModelComparison:
    """Fit several model classes to `data` and compare them.

    `models`: `None` (the four classes of the reference report, `MODEL_CLASSES`), a
    sequence of class names, or a mapping name -> class name or `{"fix": {...},
    "isotropic": bool}` (any `fix=` pattern, e.g. `{"K3 known": {"fix": {"K3": 2.0}}}`).
    `fit_options` go to every `fit_stiffness` call (e.g. `uhat=`, `n_starts=`, `key=`,
    `branch=`); a `fix=` among them applies to every model, under each model's own.  For
    helix data without observed registers the default branch is `"stable"`: with
    `"nearest"`, a model with more registers could match each point to whichever one fits
    its noise, which favours the larger model in every comparison.
    Models are fitted from the fewest free parameters up, and each one's first start is
    the best fit of the models nested in it, so a larger model never ends above a smaller
    one it contains (the likelihood-ratio statistics are then non-negative).

    `criterion`: `"bic"` (default; consistent: picks the true class as the data grow) or
    `"aic"` (better predictions, may overfit).  Compare only models fitted to the same data
    with the same sigmas.  Returns a `ModelComparison`; `ValueError` for unknown classes
    or options.  The p-values of pairs at a symmetry fixed point are not $\\chi^2$ (module
    docstring); `ModelComparison.simulate_test` gives them from the simulated null
    distribution.
    """
    if criterion not in CRITERIA:
        raise ValueError(f"compare_models: criterion must be one of {CRITERIA}, got {criterion!r}")
    for name in ("init", "isotropic"):
        if name in fit_options:
            raise ValueError(f"compare_models: {name}= is set per model (each model starts from the models nested in it)")
    if models is None:
        models = tuple(MODEL_CLASSES)
    if isinstance(models, str):
        raise ValueError("compare_models: models must be a sequence or mapping of models, not one string")
    named = {str(m): m for m in models} if not isinstance(models, Mapping) else {str(n): s for n, s in models.items()}
    specs = {n: model_options(n, s) for n, s in named.items()}
    if len(specs) < 2:
        raise ValueError(f"compare_models: needs two models at least, got {list(specs)}")
    if isinstance(data, HelixData) and data.register_sigma is None:
        # "nearest" would let a larger model match each point to whichever of its registers
        # fits the noise, which biases every comparison towards it.
        fit_options.setdefault("branch", "stable")
    common_fix = dict(fit_options.pop("fix", None) or {})
    frame_observed = isinstance(data, HelixData) and data.register_sigma is not None
    if not coupling_gauge_free(_in_plane_twist_pinned(fit_options, common_fix), frame_observed):
        # The class's K23 = 0 is no gauge here: it frees both couplings (module docstring).
        for n, s in named.items():
            if isinstance(s, str) and s == "isotropic-coupled":
                specs[n] = {**specs[n], "fix": {k: v for k, v in specs[n]["fix"].items() if k != "K23"}}
    options = {
        n: with_gauge({"isotropic": s["isotropic"], "fix": {**common_fix, **s["fix"]}}, bool(fit_options.get("fit_uhat")), frame_observed)
        for n, s in specs.items()
    }
    constraints = {n: _constraints(o) for n, o in options.items()}
    nested_in = {a: [b for b in specs if b != a and constraints[b] < constraints[a]] for a in specs}

    fits: dict[str, StiffnessFit] = {}
    for name in sorted(specs, key=lambda n: -len(constraints[n])):  # the most constrained first
        inner = [m for m in fits if name in nested_in[m]]
        best_inner = min(inner, key=lambda m: float(fits[m].cost), default=None)
        init = None if best_inner is None else fits[best_inner].rod
        fits[name] = fit_stiffness(data, init=init, **options[name], **fit_options)
    names = tuple(fits)
    table = _table(fits, names)
    tests = []
    for small in names:
        for large in nested_in[small]:
            df = len(fits[large].names) - len(fits[small].names)
            if df <= 0:
                continue
            statistic = max(2.0 * (fits[large].log_likelihood - fits[small].log_likelihood), 0.0)
            tests.append({
                "smaller": small, "larger": large, "statistic": float(statistic), "df": int(df),
                "p_value": chi2_survival(statistic, df),
            })
    candidates = [n for n in names if table[n]["ok"] and table[n]["identifiable"]]
    if candidates:
        reason = f"lowest {criterion.upper()} of the converged fits that determine every parameter"
    else:
        candidates = [n for n in names if table[n]["ok"]] or list(names)
        reason = f"lowest {criterion.upper()}; no model has every parameter determined by these data"
    best = min(candidates, key=lambda n: table[n][criterion])
    return ModelComparison(
        names=names, fits=fits, table=table, tests=tuple(tests), best=best, criterion=criterion, reason=reason
    )


def _table(fits: Mapping[str, StiffnessFit], names) -> dict:
    aic = {n: float(fits[n].aic) for n in names}
    bic = {n: float(fits[n].bic) for n in names}
    finite_aic = [v for v in aic.values() if np.isfinite(v)]
    finite_bic = [v for v in bic.values() if np.isfinite(v)]
    aic0 = min(finite_aic) if finite_aic else np.nan
    bic0 = min(finite_bic) if finite_bic else np.nan
    weights = {n: np.exp(-0.5 * (aic[n] - aic0)) if np.isfinite(aic[n]) else 0.0 for n in names}
    total = sum(weights.values()) or 1.0
    table = {}
    for n in names:
        fit = fits[n]
        stderr = np.array([float(fit.stderr[p]) for p in fit.names])
        table[n] = {
            "n_params": len(fit.names),
            "n_residuals": fit.n_residuals,
            "cost": float(fit.cost),
            "chi2_reduced": float(fit.chi2_reduced),
            "log_likelihood": float(fit.log_likelihood),
            "aic": aic[n],
            "bic": bic[n],
            "delta_aic": aic[n] - aic0,
            "delta_bic": bic[n] - bic0,
            "akaike_weight": float(weights[n] / total),
            "rank": int(fit.identifiability.rank),
            "identifiable": bool(int(fit.identifiability.rank) == len(fit.names) and np.all(np.isfinite(stderr))),
            "ok": bool(fit.ok),
            "result": result_name(fit.result),
        }
    return table
