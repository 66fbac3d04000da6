"""`fit_stiffness`: one pipeline for every kind of data.

data -> forward model (`forward_model`) -> parameterisation (which parameters are free, in
which internal coordinates) -> starts -> minimise every start (one compiled call; for a
forward model that is a solve of its own, a Gauss--Newton-type solver driven step by step
around the model's one compiled program, `_stepwise`) -> the best start, canonical in its
symmetry orbit -> Jacobian and predictions at it -> error analysis -> `StiffnessFit`.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Mapping
from pathlib import Path
from statistics import NormalDist

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float

from .._compile import compile_ahead, filter_jit, jit, once_per_signature, split_arrays
from .._misc import check_integer, check_key, chi2_survival, is_concrete, json_record, json_text, write_atomically
from .._progress import ProgressArgument, batch_size, check_progress, padded_batch, progress_bar, scan_in_batches
from .._rod import PARAMETER_NAMES, Rod, rod_from_vector, rod_vector
from .._status import RESULTS, message, promote, raise_if_failed, result_from_name, result_name, succeeded
from ._models import AbstractForwardModel, forward_model
from ._parameters import Parameterisation, extra_start, resolve_fixed, start_vector
from ._report import POOR_FIT_P_VALUE, ErrorAnalysis, Identifiability, error_analysis
from ._solvers import SOLVERS, final_residuals, make_solver, with_materialised_jacobian
from ._stepwise import HELD_WEIGHTS_ROUNDS, compile_steps_ahead, steppable, stepwise_least_squares
from ._symmetry import canonical, closest_in_orbit, symmetries

BATCHING = ("map", "vmap")
#: The `format` entry of the JSON files of `StiffnessFit.save`.
SAVE_FORMAT = "helixrod.StiffnessFit/1"


class FitProblem(eqx.Module):
    """What a fit solved: the forward model (with its data), the parameterisation, the
    solver and its step budget (what `bootstrap` refits with), and which program of the
    model's Jacobian its error analysis ran (`jacobian_and_predictions`'s `once`), which
    later evaluations at other parameters (`fit_cost_at`) find compiled."""

    model: AbstractForwardModel
    parameterisation: Parameterisation
    solver: optx.AbstractLeastSquaresSolver | optx.AbstractMinimiser
    max_steps: int = eqx.field(static=True)
    jacobian_once: bool = eqx.field(static=True, default=False)


class StiffnessFit(eqx.Module):
    """Result of `fit_stiffness` (or `fit_stiffness_linear`).

    `rod`: the fitted `Rod`, in the canonical gauge ($K_1 \\le K_2$ where that is a symmetry)
    with fixed parameters at their fixed values.  `params`, `stderr`: mappings name -> value
    for the free parameters (names from "K1", "K2", "K3", "K13", "K23", "uhat1", "uhat2",
    "uhat3"), in the order of `names`; `covariance`, `correlation` in the same order.
    Standard errors are $\\sqrt{\\mathrm{diag}\\,(J^TJ)^{-1}}$ with $J$ the Jacobian of the
    $\\sigma$-normalised residuals (sigma trusted, `absolute_sigma=True`), or that times the
    reduced $\\chi^2$ = `2 cost / (m - p)` when `absolute_sigma=False`; a parameter with
    a share in a null direction of $J$ has `inf` (the covariance is the pseudo-inverse: it
    has no variance along a null direction, `identifiability.null_directions`, where
    `stderr` and `propagate` give `inf`); they describe the cost by its quadratic at the
    minimum: `linearity_check` says where the cost does not bear that out within a few
    standard errors (then `profile_likelihood`).  `cost` = $\\tfrac12\\sum r^2$ as scipy;
    `residuals` normalised, of the observations only (helix data: the F residuals of the
    points with a measured force, then the M residuals of those with a measured moment,
    then registers if fitted).  `predicted`: the model's predictions of the observed quantities
    by name -- helix data: `force`, `moment`, `register`, `slot` (the register slot of
    `helix_equilibria` used per point) and `stable` (whether that register is; the report
    notes points matched to unstable ones), with errors in variables also
    `residual_covariance` (n, 3: var F, cov FM, var M of the effective covariance that
    whitens each point's pair); end responses: the two measured responses;
    shapes: `points`; tweezer data: `extension` (with the offsets), `torque`, `phase`, `ok`
    (false at points the model flags, e.g. outside its range: the report notes them),
    `extension_sigma` (and `residual_sigma` with errors in variables); the linear fit:
    `moment` vectors.  Convergence: `result` (a `RESULTS`
    code of the best start), `ok`, `message`, `n_steps` (of the best start), `n_starts`,
    `n_agree` (starts that reached the best minimum, up to the symmetries), `start_costs`.
    `identifiability`: see `Identifiability`.  `method`: the solver's name.  The numbers
    are host values, computed once per fit: NumPy arrays and `float64` scalars (the rod's
    are JAX arrays, as every `Rod`'s).
    """

    rod: Rod
    names: tuple[str, ...] = eqx.field(static=True)
    params: dict
    stderr: dict
    covariance: Float[np.ndarray, "p p"]
    correlation: Float[np.ndarray, "p p"]
    cost: float
    chi2_reduced: float
    residuals: Float[np.ndarray, " m"]
    predicted: dict
    result: RESULTS
    n_steps: int
    n_starts: int
    n_agree: int
    start_costs: np.ndarray
    identifiability: Identifiability
    method: str = eqx.field(static=True)
    absolute_sigma: bool = eqx.field(static=True)
    problem: FitProblem | None = eqx.field(repr=False)

    @property
    def ok(self) -> bool:
        """Whether the best start converged (to a finite cost)."""
        return bool(succeeded(self.result))

    @property
    def message(self) -> str:
        """"converged", or why not."""
        if self.ok:
            return "converged"
        return f"best start did not report convergence: {message(self.result)} ({self.method}, {self.n_steps} steps)"

    @property
    def n_residuals(self) -> int:
        """The number of normalised residuals (observations) $m$."""
        return int(self.residuals.shape[0])

    @property
    def log_likelihood(self) -> float:
        """The Gaussian log-likelihood at the fit, up to the constant $-\\sum\\log(\\sqrt{2\\pi}
        \\sigma_i)$: $-\\tfrac12\\sum r^2$ with trusted sigmas (`absolute_sigma=True`); with
        sigmas known only up to a common scale, maximised over it: $-\\tfrac m2
        \\log(\\sum r^2/m) - \\tfrac m2$."""
        chi2 = 2 * float(self.cost)
        if self.absolute_sigma:
            return -0.5 * chi2
        m = self.n_residuals
        return -0.5 * m * np.log(chi2 / m) - 0.5 * m

    @property
    def n_parameters(self) -> int:
        """Free parameters counted by the information criteria (plus the common sigma scale
        when `absolute_sigma=False`)."""
        return len(self.names) + (0 if self.absolute_sigma else 1)

    @property
    def aic(self) -> float:
        """Akaike's information criterion $2k - 2\\log L$ (Akaike 1974); compare fits of the
        same data (same sigmas): lower is better."""
        return 2 * self.n_parameters - 2 * self.log_likelihood

    @property
    def bic(self) -> float:
        """The Bayesian (Schwarz 1978) information criterion $k\\log m - 2\\log L$."""
        return self.n_parameters * float(np.log(self.n_residuals)) - 2 * self.log_likelihood

    def propagate(self, function):
        """Values and standard errors of derived quantities: `function(rod, params)` (the
        fitted `Rod` and the mapping of every free parameter's value, traced) returns a
        pytree of arrays; returns `(values, stderr)` of the same structure, the errors by
        first-order propagation of `covariance` through `jax.jacfwd` (the delta method);
        `inf` for a quantity that changes along a null direction of the fit
        (`identifiability.null_directions`: the data do not determine it, and the
        covariance, a pseudo-inverse, has no variance there).
        E.g. a tweezer fit's S, C, g along the force range:
        `fit.propagate(lambda rod, p: dna.tweezer_moduli(rod, forces,
        persistence_length=p["persistence_length"]))`.  Each call compiles a program of its
        own (the function is new to it), traced once for values and Jacobian and compiled to
        run once (`_compile.RUN_ONCE_OPTIONS`): that example (30 forces, one core) 14 -> 6 s."""
        if self.problem is None:
            raise ValueError("propagate needs the problem of a fit from fit_stiffness in this session (a fit_stiffness_linear result or a StiffnessFit.load-ed one has none)")
        param = self.problem.parameterisation
        q = jnp.asarray([float(self.params[n]) for n in self.names])
        fixed_extra = {e.name: v for e, v in zip(param.extra, param.extra_values) if e.name not in param.extra_free}

        def derived(qq):
            values = dict(zip(self.names, [qq[i] for i in range(len(self.names))]))
            return function(param.rod(qq), {**fixed_extra, **values})

        ident = self.identifiability
        null = np.zeros((0, q.size)) if ident.null_directions is None else np.asarray(ident.null_directions)

        @jit(run_once=True)  # a new program each call
        def propagated(qq, cov, scales, null):
            jacobian, values = jax.jacfwd(lambda x: (derived(x),) * 2, has_aux=True)(qq)

            def stderr(j):
                variance = jnp.maximum(jnp.einsum("...i,ij,...j->...", j, cov, j), 0.0)
                # The report's parameters, in which the null directions are unit vectors.
                scaled = j * scales.reshape((1,) * (j.ndim - 1) + scales.shape)
                along = jnp.abs(scaled @ null.T)
                undetermined = jnp.any(along > 1e-6 * jnp.linalg.norm(scaled, axis=-1, keepdims=True), axis=-1)
                return jnp.where(undetermined, jnp.inf, jnp.sqrt(variance))

            return values, jax.tree.map(stderr, jacobian)

        return propagated(q, jnp.asarray(self.covariance), jnp.asarray(ident.scales, q.dtype), jnp.asarray(null, q.dtype))

    def interval(self, level: float = 0.95) -> dict[str, tuple[float, float]]:
        """Normal-approximation confidence intervals value ± z stderr, by name."""
        if not 0 < level < 1:
            raise ValueError(f"interval: level must be in (0, 1) (0.95 for 95 %), got {level}")
        z = NormalDist().inv_cdf(0.5 + level / 2)
        return {n: (float(self.params[n] - z * self.stderr[n]), float(self.params[n] + z * self.stderr[n])) for n in self.names}

    def summary(self) -> str:
        """A plain-text report: convergence, each free parameter with its standard error,
        the fit's quality (cost, reduced chi2, AIC, BIC), the weakly determined directions,
        symmetries and notes (also `repr(fit)`)."""
        if not is_concrete(self.cost, self.params):
            return eqx.tree_pformat(self)
        lines = [
            f"StiffnessFit ({self.method}): {self.message}; {int(self.n_steps)} steps, "
            f"{int(self.n_agree)} of {int(self.n_starts)} starts at the best minimum"
        ]
        width = max([9, *(len(n) for n in self.names)])
        lines.append(f"  {'parameter':<{width}}  {'value':>13}  {'stderr':>11}")
        for name in self.names:
            lines.append(f"  {name:<{width}}  {float(self.params[name]):>13.7g}  {float(self.stderr[name]):>11.4g}")
        lines.append(
            f"cost {float(self.cost):.6g} ({self.n_residuals} residuals, {len(self.names)} free parameters), "
            f"reduced chi2 {float(self.chi2_reduced):.4g}, AIC {self.aic:.6g}, BIC {self.bic:.6g}"
            + ("" if self.absolute_sigma else " (sigmas scaled by the fit)")
        )
        ident = self.identifiability
        for w, e in zip(ident.weak, ident.weak_stderr):
            combo = " ".join(f"{c:+.3f}*{n}" for n, c in w)
            lines.append(f"weakly determined: {combo} (scaled stderr {e:.3g})")
        if ident.weak:  # then say what the data do pin down
            for w, e in zip(ident.determined, ident.determined_stderr):
                combo = " ".join(f"{c:+.3f}*{n}" for n, c in w)
                lines.append(f"determined: {combo} (scaled stderr {e:.3g})")
        lines += [f"symmetry: {x}" for x in ident.symmetries] + [f"note: {x}" for x in ident.notes]
        return "\n".join(lines)

    def __repr__(self) -> str:
        return self.summary()

    def save(self, path, extra: Mapping | None = None) -> None:
        """Write the fit as JSON (no pickles), atomically: `to_dict` plus the residuals,
        predictions, start costs and result code, everything `StiffnessFit.load` needs, and
        the JSON-serialisable entries of `extra` beside them (e.g. what the command line
        derived from the fit; `load` ignores them).  The fit problem (model, data, solver)
        is not saved: a loaded fit has no `propagate`, `profile_likelihood` or `bootstrap`."""
        record = {
            "format": SAVE_FORMAT,
            **self.to_dict(),
            "result": result_name(self.result),
            "residuals": np.asarray(self.residuals).tolist(),
            "predicted": {k: np.asarray(v).tolist() for k, v in self.predicted.items()},
            "start_costs": np.asarray(self.start_costs).tolist(),
        }
        clash = sorted(set(extra or {}) & set(record))
        if clash:
            raise ValueError(f"StiffnessFit.save: extra entries {clash} would overwrite the fit's own")
        record.update(extra or {})
        text = json_text(record)
        write_atomically(path, lambda f: f.write(text), binary=False)

    @classmethod
    def load(cls, path) -> StiffnessFit:
        """A fit written by `save`."""
        try:
            record = json_record(Path(path).read_text())
        except json.JSONDecodeError as error:
            raise ValueError(f"StiffnessFit.load: {path} is not JSON ({error})") from None
        if not isinstance(record, dict) or record.get("format") != SAVE_FORMAT:
            raise ValueError(f"StiffnessFit.load: {path} is not a fit written by StiffnessFit.save (no format {SAVE_FORMAT!r})")
        names = tuple(record["names"])
        rod = rod_from_vector(np.array([record["rod"][n] for n in PARAMETER_NAMES], float), checked=True)
        return cls(
            rod=rod,
            names=names,
            params={n: np.float64(record["params"][n]) for n in names},
            stderr={n: np.float64(record["stderr"][n]) for n in names},
            covariance=np.asarray(record["covariance"], float).reshape(len(names), len(names)),
            correlation=np.asarray(record["correlation"], float).reshape(len(names), len(names)),
            cost=float(record["cost"]),
            chi2_reduced=float(record["chi2_reduced"]),
            residuals=np.asarray(record["residuals"], float),
            predicted={k: np.asarray(v) for k, v in record["predicted"].items()},
            result=result_from_name(record["result"]),
            n_steps=int(record["n_steps"]),
            n_starts=int(record["n_starts"]),
            n_agree=int(record["n_agree"]),
            start_costs=np.asarray(record["start_costs"], float),
            identifiability=Identifiability.from_dict(names, record["identifiability"]),
            method=record["method"],
            absolute_sigma=bool(record["absolute_sigma"]),
            problem=None,
        )

    def to_dict(self) -> dict:
        """Plain-Python summary (JSON-serialisable)."""
        return {
            "method": self.method,
            "names": list(self.names),
            "params": {n: float(v) for n, v in self.params.items()},
            "stderr": {n: float(v) for n, v in self.stderr.items()},
            "rod": {n: float(v) for n, v in zip(PARAMETER_NAMES, np.asarray(rod_vector(self.rod)))},
            "covariance": np.asarray(self.covariance).tolist(),
            "correlation": np.asarray(self.correlation).tolist(),
            "cost": float(self.cost),
            "chi2_reduced": float(self.chi2_reduced),
            "aic": float(self.aic),
            "bic": float(self.bic),
            "absolute_sigma": self.absolute_sigma,
            "success": self.ok,
            "message": self.message,
            "n_steps": int(self.n_steps),
            "n_starts": int(self.n_starts),
            "n_agree": int(self.n_agree),
            "identifiability": self.identifiability.to_dict(),
        }


def assemble(
    rod: Rod, analysis: ErrorAnalysis, values: Mapping[str, float], residuals, predicted, *, result, method: str,
    absolute_sigma: bool, n_steps: int = 0, start_costs=None, n_agree: int = 1, problem: FitProblem | None = None,
) -> StiffnessFit:
    """A `StiffnessFit` from the error analysis at the fitted values (the one constructor of
    the fits of this package)."""
    start_costs = np.asarray([analysis.cost] if start_costs is None else start_costs, float)
    return StiffnessFit(
        rod=rod,
        names=tuple(values),
        params={n: np.float64(v) for n, v in values.items()},
        stderr=analysis.stderr,
        covariance=analysis.covariance,
        correlation=analysis.correlation,
        cost=analysis.cost,
        chi2_reduced=analysis.chi2_reduced,
        residuals=np.asarray(residuals),
        predicted={k: np.asarray(v) for k, v in predicted.items()},
        result=result,
        n_steps=int(n_steps),
        n_starts=int(start_costs.shape[0]),
        n_agree=int(n_agree),
        start_costs=start_costs,
        identifiability=analysis.identifiability,
        method=method,
        absolute_sigma=absolute_sigma,
        problem=problem,
    )


def evaluate(q, model: AbstractForwardModel, param: Parameterisation):
    """The model's residuals and predictions at the free physical values `q`."""
    return model.residuals(param.rod(q), param.extra_vector(q))


def minimise(z0, model: AbstractForwardModel, param: Parameterisation, solver, max_steps: int):
    """One local solve from internal coordinates `z0`: (z, cost, result, steps), the cost
    $\\tfrac12\\sum r^2$ at z (`inf` where not finite).  Pure, vmappable.  A least-squares
    solver sees the residuals with their Jacobian materialised (`with_materialised_jacobian`)
    and the cost is that of the residuals it ends with (`final_residuals`): the model is
    not evaluated again."""

    def fn(z, args):
        model, param = args
        return evaluate(param.physical(z), model, param)[0]

    args = (model, param)
    if isinstance(solver, optx.AbstractLeastSquaresSolver):
        materialised = with_materialised_jacobian(fn, through_loops=model.forward_mode_only)
        sol = optx.least_squares(materialised, solver, z0, args, max_steps=max_steps, throw=False)
        r = final_residuals(sol)
    else:
        cost = lambda z, a: 0.5 * jnp.sum(fn(z, a) ** 2)  # noqa: E731
        sol = optx.minimise(cost, solver, z0, args, max_steps=max_steps, throw=False)
        r = None
    if r is None:
        r = evaluate(param.physical(sol.value), model, param)[0]
    cost = 0.5 * jnp.sum(r * r)
    return sol.value, jnp.where(jnp.isfinite(cost), cost, jnp.inf), promote(sol.result), sol.stats["num_steps"]


@filter_jit
def _multistart(z0s, model, param, solver, max_steps: int, batching: str):
    """Local solves from every start; returns z, cost, result, steps, the full physical
    vector and the free physical values per start.

    `batching="vmap"` solves all starts in lock step; `"map"` (`jax.lax.map`) one after
    another.  "map" is the default because it is faster here: under `vmap` the register
    solver's data-dependent `lax.cond` (robust re-solve of unconverged brackets, in
    `_roots.py`) becomes a `select` that runs the robust path on every point of every
    start, and the batched while loop runs until the slowest start stops."""

    one = lambda z0: _start_solved(z0, model, param, solver, max_steps)  # noqa: E731
    if batching == "vmap":
        return jax.vmap(one)(z0s)
    return jax.lax.map(one, z0s)


def _start_solved(z0, model, param, solver, max_steps: int):
    """One start of `_multistart`: z, cost, result, steps, the full physical vector and the
    free physical values."""
    z, cost, result, steps = minimise(z0, model, param, solver, max_steps)
    result = RESULTS.where(jnp.isfinite(cost) | (result != RESULTS.successful), result, RESULTS.cost_not_finite)
    q = param.physical(z)
    return z, cost, result, steps, param.full(q), q


@filter_jit
def _starts_until_agreement(z0s, count, least, prior_best, model, param, solver, max_steps: int):
    """What `_multistart` returns for the first `count` of the starts `z0s`, solved one
    after another until at least `least` are solved and `ADAPTIVE_AGREE` of them -- with the
    best cost of earlier starts, `prior_best` (inf: none), counting as one -- reach the best
    cost (within `AGREED_COST` relative), and how many were solved; the rows of the others
    are left as they were (not solved: the caller drops them).  The early stop inside the
    program saves the starts a fixed batch solves after two agree; parameters and
    symmetries are compared on the host (`_agreement`), which calls again where they
    differ."""
    # The rows spelled out: their shapes from `jax.eval_shape` of a start traced the solve
    # once more (0.1 s of a process's first fit; its warm first call 0.6 -> 0.7 s).
    n, dtype = z0s.shape[0], z0s.dtype
    q = jax.eval_shape(param.physical, z0s[0])
    p = jax.eval_shape(param.full, q)
    rows = (
        jnp.zeros_like(z0s), jnp.full(n, jnp.inf, dtype), jax.tree.map(lambda v: jnp.full(n, v), RESULTS.successful),
        jnp.zeros(n, jnp.int32), jnp.zeros((n,) + p.shape, p.dtype), jnp.zeros((n,) + q.shape, q.dtype),
    )

    def agreed(state):
        i, rows = state
        costs = jnp.where(jnp.arange(z0s.shape[0]) < i, rows[1], jnp.inf)
        best = jnp.minimum(jnp.min(costs), prior_best)
        near = lambda c: jnp.abs(c - best) <= AGREED_COST * (1.0 + best)  # noqa: E731
        members = jnp.sum(near(costs)) + near(prior_best)
        return jnp.isfinite(best) & (members >= ADAPTIVE_AGREE)

    def going(state):
        i, _ = state
        return (i < count) & ((i < least) | ~agreed(state))

    def solve_next(state):
        i, rows = state
        out = _start_solved(z0s[i], model, param, solver, max_steps)
        return i + 1, jax.tree.map(lambda a, v: a.at[i].set(v.astype(a.dtype)), rows, out)

    solved, rows = jax.lax.while_loop(going, solve_next, (jnp.zeros((), jnp.int32), rows))
    return rows, solved


def _stepwise_multistart(z0s, model, param, solver, max_steps: int, report):
    """What `_multistart` returns, for a forward model that is a solve of its own
    (`forward_mode_only`): the starts one after another, each driven step by step
    (`stepwise_least_squares`) with the residuals and Jacobian of `jacobian_and_predictions`,
    the one compiled copy of the model (the start scan and the error analysis use it too)."""

    arrays, static = split_arrays((model, param))
    _compile_side_by_side(static, arrays, np.asarray(z0s[0]), model, param, solver)

    def jacobian_at(q):
        J, (r, predicted) = _split_jacobian_and_predictions(static, q, arrays)
        return r, J, model.moving_sigmas(predicted)

    solved = []
    for z0 in z0s:
        z, cost, result, steps = stepwise_least_squares(jacobian_at, param.physical, z0, solver, max_steps)
        if succeeded(result) and not np.isfinite(float(cost)):
            result = RESULTS.cost_not_finite
        q, p = _physical_values(z, param)
        solved.append((z, cost, result, steps, p, q))
        report.advance(1)
    # On the host: `_best_start` reads them there (a stack of device arrays is a small
    # program of its own, a compilation or a cache lookup on a process's first fit).
    return jax.tree.map(lambda *a: np.stack([np.asarray(x) for x in a]), *solved)


def _fit_signature(static, arrays, z0, model, param, solver):
    return (static, tuple((a.shape, a.dtype) for a in jax.tree.leaves(arrays)), z0.shape, z0.dtype)


@once_per_signature(_fit_signature)
def _compile_side_by_side(static, arrays, z0, model, param, solver) -> bool:
    """At the first stepwise fit of its kind: start compiling the model's program
    (`_split_jacobian_and_predictions`) and the solver's step programs, each on a thread of
    its own (`compile_ahead`, the steps from the output structure of the model's program),
    so that the steps compile while the model does."""
    z = jax.ShapeDtypeStruct(z0.shape, z0.dtype)
    specs = compile_ahead(_split_jacobian_and_predictions, static, jax.eval_shape(param.physical, z), arrays)
    if specs is None:  # nothing compiles beside the call (traced, one core)
        return False
    J, (r, predicted) = specs
    compile_steps_ahead(solver, param.physical, z, r, J, model.moving_sigmas(predicted))
    return True


@filter_jit
def _physical_values(z, param: Parameterisation):
    """The free physical values `q` at internal coordinates `z` and the full physical vector."""
    q = param.physical(z)
    return q, param.full(q)


def jacobian_and_predictions(q, model: AbstractForwardModel, param: Parameterisation, *, once: bool = False):
    """Jacobian of the normalised residuals with respect to the free physical parameters,
    the residuals and the predictions, in one compiled program (`_split_jacobian_and_predictions`).
    `once`: for an evaluation that no other in the fit shares (the error analysis of a fit
    the solver did not drive through this program): the program compiled to run once
    (`_compile.RUN_ONCE_OPTIONS`; a 60-helix fit's, on one core: 2.2 -> 0.8 s of XLA
    compilation, 0.4 -> 0.5 ms a call)."""
    arrays, static = split_arrays((model, param))
    return (_jacobian_and_predictions_once if once else _split_jacobian_and_predictions)(static, q, arrays)


def fit_cost_at(fit: StiffnessFit, q) -> float:
    """The cost $\\tfrac12\\sum r^2$ of `fit`'s problem (its observed residuals) at the free
    physical values `q` (in the order of `fit.names`), by the program of the model's
    Jacobian its error analysis compiled; NaN where the model is not defined there.  Sigmas
    that move with the parameters (errors in variables, `moving_sigmas`) are held at the
    fit's own: the fit is the fixed point of Orear's iteration, the minimum of the cost at
    its own sigmas, and its Jacobian holds them (with them moving, the bundled tweezer
    example's cost along its error bars' lines was not even symmetric at 0.02 standard
    errors)."""
    problem = fit.problem
    param = problem.parameterisation
    # In the precision the program was compiled for (its fixed values').
    q = np.asarray(q, np.asarray(param.fixed_values).dtype)
    _, (r, predicted) = jacobian_and_predictions(q, problem.model, param, once=problem.jacobian_once)
    moving = problem.model.moving_sigmas(predicted)
    if moving is not None:
        r = np.asarray(r) * np.asarray(moving) / np.asarray(fit.predicted["residual_sigma"])
    observed = problem.model.observed_residuals()
    r = np.asarray(r) if observed is None else np.asarray(r)[observed]
    cost = 0.5 * float(r @ r)
    return cost if np.isfinite(cost) else float("nan")


def _jacobian_and_predictions_of(static, q, arrays):
    model, param = static.combine(arrays)
    return model.jacobian_and_predictions(q, param)


#: `jacobian_and_predictions` with `(model, param)` given as `split_arrays` halves, split
#: once by a caller that evaluates it at many points `q` (a fit's steps).
_split_jacobian_and_predictions = jit(_jacobian_and_predictions_of, static_argnums=0, trace_cache=True)
_jacobian_and_predictions_once = jit(_jacobian_and_predictions_of, static_argnums=0, run_once=True, trace_cache=True)


def _solver(solver, rtol, atol, learning_rate):
    if isinstance(solver, str):
        for name, value in (("rtol", rtol), ("atol", atol), ("learning_rate", learning_rate)):
            if value is not None and not (np.isfinite(float(value)) and float(value) > 0):
                raise ValueError(f"fit_stiffness: {name} must be finite and > 0, got {value}")
        return solver, make_solver(
            solver, 1e-10 if rtol is None else float(rtol), 1e-12 if atol is None else float(atol),
            1e-2 if learning_rate is None else float(learning_rate),
        )
    if not isinstance(solver, (optx.AbstractLeastSquaresSolver, optx.AbstractMinimiser)):
        raise ValueError(
            f"solver must be one of {SOLVERS} or an optimistix least-squares solver or minimiser, "
            f"got {type(solver).__name__}"
        )
    if rtol is not None or atol is not None or learning_rate is not None:
        raise ValueError("rtol=, atol= and learning_rate= apply to solvers given by name; set them on the solver object")
    return type(solver).__name__, solver


def fit_stiffness(
    data,
    *,
    uhat: ArrayLike | None = None,
    fit_uhat: bool = False,
    fix: Mapping[str, float] | None = None,
    isotropic: bool = False,
    init: Rod | Mapping[str, float] | None = None,
    solver="levenberg-marquardt",
    n_starts: int | None = None,
    key: Array | None = None,
    absolute_sigma: bool = True,
    rtol: float | None = None,
    atol: float | None = None,
    max_steps: int = 256,
    learning_rate: float | None = None,
    weak_threshold: float = 0.1,
    batching: str = "map",
    branch: str | None = None,
    use_register: bool | None = None,
    errors_in_variables: bool | None = None,
    fit_offsets: bool | None = None,
    throw: bool = False,
    progress: ProgressArgument = None,
) -> StiffnessFit:
    """Fit the stiffness $K$ (and optionally $\\hat u$) of a rod to data.

    Minimises $\\tfrac12\\sum r^2$ over the free parameters, with $r$ the $\\sigma$-normalised
    residuals of the forward model of the data (`helixrod._fit._models`):

    - `HelixData`: the axial force and moment of one register per measured helix;
    - `EndResponseData`: the two measured end responses (force, moment, extension,
      rotation) of a finite rod of known length, each point a `solve_boundary_value` solve;
    - `ShapeData`: centreline points of a finite rod under known end loads;
    - `dna.TweezerData`: extension (and torque) of tethered molecules against force and
      turns or torque (`tweezer_response`), with the model's persistence lengths (and bead
      offsets) as parameters beside the rod's.

    Finite-rod models are differentiated through the shooting root in forward mode (the
    same parameterisation, solver, covariance and identifiability report).

    - `uhat`: the intrinsic twist, held fixed (default (0, 0, 0)); or `fit_uhat=True`.
    - `fix`: mapping name -> value of parameters held fixed (names as in `PARAMETER_NAMES`), e.g.
      `{"K13": 0, "K23": 0}` for the uncoupled model, `{"K2": ..}`.
    - `isotropic`: bending isotropic, $K_2 = K_1$: one free parameter `"K1"` for both
      (`params` has no `"K2"`; the fitted rod has it).  The model classes of
      `compare_models` are `isotropic` and `fix` patterns.
    - `init`: a `Rod` or mapping for the first start; default: an isotropic rod that fits
      the data by linear least squares (helices: Love's formulas; shapes: a rough scale,
      refined by the cost at 0.01 to 100 times its stiffnesses, `START_SCAN_FACTORS`,
      before the fit).  Starts 2..`n_starts`
      are random perturbations of it (log-normal stiffnesses, random couplings and
      twists), drawn from `key` (default `jax.random.key(0)`).  An explicit `n_starts`
      solves exactly that many, in one jitted call: `batching="map"` (default,
      `jax.lax.map`, faster on CPU with the present register solver) or `"vmap"` (all
      starts in lock step).  The default for finite rods and tweezer data is 1 start;
      their models are solves of their own, and with a Gauss--Newton-type solver
      (Levenberg--Marquardt, Gauss--Newton, dogleg) the starts are solved one after
      another, each step's residuals and Jacobian from the one compiled program of the
      model that the error analysis uses (`batching` does not apply): the first call
      compiles the model once instead of twice, and each step pays a round trip to
      Python (measured with the model's `jax.jacfwd` Jacobian in both: a tweezer
      force-distance fit's 8 steps in 6.0-6.7 ms stepwise, 5.0-5.8 ms in optimistix's
      compiled loop; with the README's shape fit, first calls 76 -> 27 s and later calls
      62-68 -> 70-75 ms against the previous release).  The default for
      helices (`n_starts=None`) stops early: the same sequence of up to 32 starts is
      solved one after another with at most 48 steps each, 6 a call of one compiled
      program (which skips its last start where two already agree), until two starts
      agree on the best minimum (cost within 1e-6 relative, parameters within 1e-4 of their
      scales, up to the symmetries; a start cut short by the 48 steps counts if it
      agrees); the best start, if cut short, is then solved on with the full
      `max_steps`.  If no two starts agree after all 32, all 32 are solved again with the
      full `max_steps` (as `n_starts=32`).  Deterministic for a given `key`;
      `n_starts`, `start_costs` and `n_agree` count the starts solved.
    - `solver`: an optimistix least-squares solver (e.g. `optimistix.LevenbergMarquardt(rtol,
      atol)`) or minimiser of $\\tfrac12\\sum r^2$ (e.g. `optimistix.OptaxMinimiser(optax.adam(
      1e-2), rtol, atol)`; helix data only: finite-rod and tweezer models take least-squares solvers),
      or a name from `SOLVERS` (default `"levenberg-marquardt"`), built with `rtol`
      (default 1e-10), `atol` (1e-12) and, for `"adam"`, `learning_rate` (1e-2).
      `max_steps` (>= 1) per start.
    - `absolute_sigma`: True (default) trusts the sigmas; False scales the covariance by
      the reduced $\\chi^2$ (use when the sigmas are only relative weights).
    - `weak_threshold` (> 0): the scaled standard error above which a direction of the
      parameters is reported as weakly determined (`Identifiability.weak`).
    - Tweezer data only: `fit_offsets` -- fit one bead-height offset per molecule
      (default off; the command line's `tweezer-fit` turns it on).
    - Helix data only: `branch` -- which register a point is matched to: `"nearest"`
      (the register whose (F, M) is closest to the observation in sigma units),
      `"stable"` (the nearest stable one), `"min-energy"` (slot 0, the global energy
      minimum on the circle); default `"nearest"` when every point has both force and
      moment, else `"stable"` (with one observable the nearest register can be any that
      fits it, and an undetermined stiffness looks determined); `use_register` -- match
      the observed registers (`data.register`): the branch becomes the register nearest in
      angle, and, if
      `data.register_sigma` is given, the angle is a residual too (default: on when the
      data carry `register_sigma`); `errors_in_variables` -- propagate `data.kappa_sigma`,
      `tau_sigma` (and `kappa_tau_correlation`) to first order into an effective 2x2
      covariance of (F, M) at each register; the residual pair is whitened by it (default:
      on when the data carry `kappa_sigma` or `tau_sigma`).  The covariance moves with
      $K$ and the Jacobian holds it fixed, so the starts are solved with it held at that
      of the first start, and the best one again with that of its solution until the
      solution moves by less than `HELD_WEIGHTS_TOLERANCE` standard errors: the fixed
      point of Orear's iteration (Am. J. Phys. 50 (1982) 912), where the gradient with the
      weights of the solution held is zero (`n_steps` counts the steps of every solve).
    - `throw`: raise `SolverError` if the best start did not converge (default `False`:
      read `ok`, `result`, `message`).
    - `progress`: `None` (default) shows a rich progress bar when stdout is a terminal,
      `True`/`False` force it on or off, and a callable is called as
      `progress(done, total)` instead of a bar, with `total = n_starts + 1` (32 + 1 for the
      default of helices): one unit per start solved (the default's early stop jumps to
      the last start), one for the error analysis.  While progress is shown the starts are
      solved in up to 20 host-side batches of one compiled program (the last padded), and
      the bar moves between them, never inside the optimisation; the fit is the same.

    Fewer residuals than free parameters (a single data point gives two) is allowed: the
    fit reproduces the data and the report says what is left open -- `identifiability.rank`
    at most the number of residuals, the null directions in `weak` with `inf` standard
    errors, and `inf` for every parameter with a share in them.

    Raises `ValueError` for bad options.  Not itself jit-able (it returns Python summaries);
    the solves inside are jitted and reuse compilations across calls of equal shapes.

    **Example**

    ```python
    rod = helixrod.Rod(1.0, 1.5, 0.8, K13=0.2, K23=-0.1, uhat=(0.8, 0.6, 0.3))  # the truth
    rng = np.random.default_rng(0)
    kappa, tau = rng.uniform(0.3, 2.5, 60), rng.uniform(-1.5, 2.0, 60)          # 60 helices
    data = helixrod.synthetic_helix_data(rod, kappa, tau, 0.01, jax.random.key(1))
    fit = helixrod.fit_stiffness(data, uhat=rod.uhat)
    fit.params["K1"], fit.stderr["K1"], fit.identifiability.weak
    ```
    """
    options = dict(branch=branch, use_register=use_register, errors_in_variables=errors_in_variables, fit_offsets=fit_offsets)
    model = forward_model(data, **{name: value for name, value in options.items() if value is not None})
    method, solver = _solver(solver, rtol, atol, learning_rate)
    if model.forward_mode_only and not isinstance(solver, optx.AbstractLeastSquaresSolver):
        raise ValueError(
            f"fit_stiffness: solver {method!r} is not available for {type(data).__name__} (its forward model "
            "is differentiated in forward mode only); use 'levenberg-marquardt' or 'gauss-newton'"
        )
    adaptive = n_starts is None and model.default_starts > 1
    n_starts = model.default_starts if n_starts is None else check_integer(n_starts, "n_starts", "fit_stiffness")
    if key is not None:
        check_key(key, "fit_stiffness")
    if not weak_threshold > 0:
        raise ValueError(f"fit_stiffness: weak_threshold must be > 0, got {weak_threshold}")
    check_integer(max_steps, "max_steps", "fit_stiffness")
    if batching not in BATCHING:
        raise ValueError(f"batching must be 'map' or 'vmap', got {batching!r}")
    check_progress(progress, "fit_stiffness")
    extra = model.parameters
    fixed = resolve_fixed(uhat, fit_uhat, fix, extra, init, isotropic)
    u_fixed = [fixed.get(f"uhat{i}", 0.0) for i in (1, 2, 3)]
    B, C = model.isotropic_start(u_fixed)
    p0 = start_vector(init, fixed, np.array([B, B, C, 0.0, 0.0, *u_fixed]), [e.name for e in extra])
    extra0 = extra_start(init, fixed, extra)
    if isotropic:
        p0[1] = p0[0]  # an init's K2 gives way to the tie
    parameterisation = lambda p: Parameterisation(  # noqa: E731
        fixed, float(np.sqrt(p[0] * p[1])), model.twist_scale(p), extra, extra0, isotropic
    )
    param = parameterisation(p0)
    n_starts = int(n_starts)
    with progress_bar("fit_stiffness: starts", n_starts + 1, progress, owner="fit_stiffness") as report:
        scanned = init is None and model.scan_start
        if scanned:
            report.describe("fit_stiffness: start scan")
            p0 = _scanned_start(p0, model, param)
            param = parameterisation(p0)
            report.describe("fit_stiffness: starts")
        z0s = param.starts(param.internal(p0), n_starts, key)
        stepwise = model.forward_mode_only and steppable(solver)
        # Moving weights (errors in variables) held at those of the first start: every start
        # then solves one least-squares problem, whose Jacobian its cost agrees with.
        moving, holds = model, not stepwise and model.holds_weights
        if holds:
            model = model.with_weights_held(_evaluated(_physical_values(z0s[0], param)[0], model, param)[1])
        agreement = None
        if stepwise:
            solved = _stepwise_multistart(z0s, model, param, solver, int(max_steps), report)
        elif adaptive:
            plausible = _plausible_cost(model, param, absolute_sigma)
            solved, agreement = _adaptive_multistart(z0s, model, param, solver, int(max_steps), batching, report, plausible)
            report.advance(n_starts - report.done)  # the starts left out by the early stop
        elif report.shown:
            solve = lambda _, batch: (None, _multistart(batch, model, param, solver, int(max_steps), batching))  # noqa: E731
            _, solved = scan_in_batches(solve, None, jnp.asarray(z0s), n_starts, batch_size(n_starts), report)
        else:  # one call: nothing is slower for want of a bar
            solved = _multistart(jnp.asarray(z0s), model, param, solver, int(max_steps), batching)
        if agreement is None:
            agreement = _agreement(solved[4], solved[1], model, param, solved[2])
        if holds:
            solved, model, agreement = _held_weights_iteration(
                solved, agreement, moving, model, param, solver, int(max_steps), batching
            )
        report.describe("fit_stiffness: error analysis")
        # The model's Jacobian program: the one the start scan or the steps compiled, else one to run once.
        once = not (scanned or stepwise)
        fit = _best_start(
            solved, agreement, model, param, solver, method, int(max_steps), absolute_sigma, weak_threshold, once=once
        )
        report.advance(1)
    return raise_if_failed(fit, fit.result, "fit_stiffness: the best start did not converge") if throw else fit


#: Factors of the free stiffnesses of the default first start tried by the start scan of a
#: model with `scan_start` (four decades, two points each).
START_SCAN_FACTORS = tuple(float(f) for f in np.logspace(-2.0, 2.0, 9))


def _scanned_start(p0, model: AbstractForwardModel, param: Parameterisation) -> np.ndarray:
    """The full start vector `p0` with its free stiffnesses scaled by the factor of
    `START_SCAN_FACTORS` of lowest cost (`p0` itself where no factor gives a finite one).
    The model's default start (`isotropic_start`) is a rough estimate; a local fit from a
    start some decades off may stop at a local minimum (the README's spring fit: from
    the estimate 10.5, ten times the true stiffness, at chi2 ~ 2e7; from a tenth of it, at
    the truth).  Each cost is an evaluation of `jacobian_and_predictions`, the program the
    error analysis needs anyway: no other compilation."""
    free = [i for i, name in enumerate(PARAMETER_NAMES[:3]) if name not in param.fixed_names]
    if not free:
        return p0
    observed = model.observed_residuals()
    best, best_cost = p0, np.inf
    for factor in START_SCAN_FACTORS:
        p = np.array(p0, float)
        p[free] *= factor
        _, (r, _) = jacobian_and_predictions(param.physical(jnp.asarray(param.internal(p))), model, param)
        r = np.asarray(r) if observed is None else np.asarray(r)[observed]
        cost = 0.5 * float(r @ r)
        if np.isfinite(cost) and cost < best_cost:
            best, best_cost = p, cost
    return best


#: The default multistart (`n_starts=None`) of a model with several default starts: the
#: starts, in their order, solved with at most `SCREEN_STEPS` steps each, `ADAPTIVE_BATCH`
#: a call of one compiled program (`_starts_until_agreement`), which stops early once
#: `ADAPTIVE_AGREE` starts agree on the best minimum after at least `ADAPTIVE_LEAST` of its
#: starts (the best then solved on with `max_steps` more steps if it was cut short); if none
#: do after every default start, all of them are solved again with the full step budget.
#: At least `ADAPTIVE_LEAST` in every call, not only the first: a later start may be better
#: than the two that agree (a symmetric noise-free fit of `tests/test_fit_symmetry.py` had
#: starts 5 and 7 agree on cost 5.0e-3, start 8 reach 3.3e-3 and start 15 the global 0).
#: `ADAPTIVE_LEAST`: two starts may agree on a local minimum whose cost is within a few per
#: cent of the global one (a mirror image of it under the noise).  Emulated from the costs
#: of 32 starts solved with `SCREEN_STEPS` on the random problems of `benchmarks/bench_fit.py`
#: (indices 0-99; 30-129): whole batches of 6 (before) reached the global minimum in 100 %
#: (100 %) of them with 7.2 (7.3) starts on average; at least 5 a call in 100 % (99 %) with
#: 6.4 (6.4); at least 4 in 99 % (98 %) with 5.7 (5.7).  The one miss of at least 5 in 130
#: problems (index 123): starts 0 and 4 agree on cost 69.689, start 5 reaches 69.635.
ADAPTIVE_BATCH = 6
ADAPTIVE_AGREE = 2
ADAPTIVE_LEAST = 5
SCREEN_STEPS = 48
#: Starts agree on a minimum where their costs are within this, relative to 1 + the cost
#: (and their parameters within `AGREED_PARAMETERS` of their scales, up to the symmetries).
AGREED_COST = 1e-6
AGREED_PARAMETERS = 1e-4


def _plausible_cost(model, param, absolute_sigma: bool):
    """`cost -> bool`: whether a best cost is consistent with the data's sigmas, its
    $\\chi^2$ p-value at least `POOR_FIT_P_VALUE` (the report's "does not describe the data"
    threshold); always true where the sigmas are not trusted or the model does not know
    its number of observations."""
    m = model.observation_count()
    dof = 0 if m is None else m - len(param.names)
    if not absolute_sigma or dof <= 0:
        return lambda cost: True
    return lambda cost: bool(np.isfinite(cost)) and chi2_survival(2.0 * float(cost), dof) >= POOR_FIT_P_VALUE


def _adaptive_multistart(z0s, model, param, solver, max_steps: int, batching: str, report, plausible=lambda cost: True):
    """The starts `z0s` (NumPy) solved in order with early stopping (`ADAPTIVE_BATCH`,
    `ADAPTIVE_LEAST`, `SCREEN_STEPS`, `ADAPTIVE_AGREE`; `batching="vmap"`: in whole batches
    of `ADAPTIVE_BATCH`, in lock step): what `_multistart` returns, of the starts solved.
    A start cut short by the screening budget counts where it agrees with the best; the
    best start, if cut short, is then solved on from where it stopped with the full budget.
    Starts that agree on a best cost that is not `plausible` (a minimum that does not
    describe the data: two starts may agree on a wrong one) do not stop it.  Also returns
    their `_agreement` where it was found on the starts as returned (else None)."""
    total = int(z0s.shape[0])
    size = min(ADAPTIVE_BATCH, total)
    screen = min(SCREEN_STEPS, max_steps)
    parts, done, agreed, least = [], 0, None, min(ADAPTIVE_LEAST, size)
    while done < total:
        batch, count = padded_batch(z0s, done, size), min(size, total - done)
        if batching == "map":
            # (An array, as the counts: a Python number is a static argument, a program each.)
            prior = np.asarray(min((float(np.min(part[1])) for part in parts), default=np.inf), np.asarray(z0s).dtype)
            out, solved_now = _starts_until_agreement(batch, np.int32(count), np.int32(least), prior, model, param, solver, screen)
            count = int(solved_now)
        else:  # in lock step: the whole batch
            out = _multistart(batch, model, param, solver, screen, batching)
        parts.append(jax.tree.map(lambda a, k=count: np.asarray(a)[:k], out))
        report.advance(count)
        done += count
        solved = jax.tree.map(lambda *a: np.concatenate(a), *parts)
        agreement = _agreement(solved[4], solved[1], model, param, solved[2])
        best, agree, _ = agreement
        if agree >= ADAPTIVE_AGREE:
            if plausible(solved[1][best]):
                break
            agreed = agreed or (solved, agreement)
            least = size  # an implausible agreement: no early stops after it (whole batches)
    else:
        if agreed is not None:
            # No start found a minimum that describes the data: the model does not, and the
            # first agreement stands (as without the check).
            solved, agreement = agreed
            best = agreement[0]
        elif screen < max_steps:  # no two starts agreed within the screening budget: all with the full one
            return _multistart(z0s, model, param, solver, max_steps, batching), None
        else:
            return solved, agreement
    if screen < max_steps and not succeeded(solved[2])[best]:
        z, cost, result, steps, p, q = _multistart(solved[0][best:best + 1], model, param, solver, max_steps, batching)
        # LM accepts steps at round-off, so the same minimum may come back a little higher.
        if bool(np.isfinite(cost[0])) and cost[0] <= solved[1][best] + 1e-6 * (1 + solved[1][best]):
            update = (z, cost, result, steps + solved[3][best], p, q)
            solved = jax.tree.map(lambda a, u: _replace_row(a, best, np.asarray(u)[0]), solved, update)
            agreement = None
    return solved, agreement


def _replace_row(a, i, row):
    a = np.array(a)
    a[i] = row
    return a


#: Orear's iteration of a fit with held weights (`_held_weights_iteration`) stops once a
#: solve with the weights of the last point moved it by at most this many standard errors
#: (read from the cost it gained: $\tfrac12 \delta^2$ in units of the reduced $\chi^2$
#: where that exceeds 1), or after `HELD_WEIGHTS_ROUNDS` solves.
HELD_WEIGHTS_TOLERANCE = 1e-3


def _held_weights_iteration(solved, agreement, moving, held, param, solver, max_steps: int, batching: str):
    """Orear's iteration from the best of the starts `solved`, solved by the model `held`
    (`AbstractForwardModel.with_weights_held`; returned as it is if the best start
    failed): the weights of the model `moving` at the solution are held and the best start
    solved on with them, until the solve no longer moves it (`HELD_WEIGHTS_TOLERANCE`).
    Its fixed point minimises the cost with the weights of the point itself, where the
    gradient of the cost with its weights held is zero (Orear, Am. J. Phys. 50 (1982) 912);
    a solve with moving weights stops short of it, its Jacobian not being that of its cost.
    Where the weights move strongly with the parameters (a model far from the data, whose
    chosen registers change with the weights) the iteration may not settle: then the
    result is `RESULTS.weights_not_settled`.  Returns the starts with the best one's row
    replaced (its steps summed over the solves), the model with the weights of the final
    point held (its residuals are those of the moving model there) and the agreement
    (`_agreement`) with the new canonical point."""
    best, agree, _ = agreement
    z, cost, result, steps, p, q = jax.tree.map(lambda a: np.asarray(a)[best], solved)
    if not (succeeded(result) and np.isfinite(cost)):
        return solved, held, agreement  # nothing to iterate from
    observed = moving.observed_residuals()
    for _ in range(HELD_WEIGHTS_ROUNDS):
        r, predicted = _evaluated(q, moving, param)
        held = moving.with_weights_held(predicted)
        r = np.asarray(r) if observed is None else np.asarray(r)[observed]
        own_cost = 0.5 * float(r @ r)  # with the weights of the point itself
        out = _multistart(jnp.asarray(z)[None], held, param, solver, max_steps, batching)
        z, cost, result, more, p, q = jax.tree.map(lambda a: np.asarray(a)[0], out)
        steps = steps + more
        gain = own_cost - float(cost)  # about half the square of the move, in standard errors
        reduced_chi2 = 2 * own_cost / max(r.size - z.size, 1)
        if not (succeeded(result) and np.isfinite(cost)) or 2 * gain <= HELD_WEIGHTS_TOLERANCE**2 * max(1.0, reduced_chi2):
            break
    else:
        result = RESULTS.weights_not_settled
    held = moving.with_weights_held(_evaluated(q, moving, param)[1])
    solved = jax.tree.map(lambda a, row: _replace_row(a, best, row), solved, (z, cost, result, steps, p, q))
    return solved, held, (best, agree, _canonical_point(p, param, moving.frame_observed))


def _evaluated(q, model: AbstractForwardModel, param: Parameterisation):
    """`evaluate` compiled to run once (`_compile.RUN_ONCE_OPTIONS`: a few calls a fit; the
    DNA helices: 0.46 -> 0.21 s of XLA compilation): the residuals and predictions at the
    free physical values `q`."""
    arrays, static = split_arrays((model, param))
    return _evaluated_once(static, q, arrays)


@functools.partial(jit, static_argnums=0, run_once=True)
def _evaluated_once(static, q, arrays):
    model, param = static.combine(arrays)
    return evaluate(q, model, param)


def _canonical_point(p, param: Parameterisation, frame_observed: bool) -> np.ndarray:
    """The canonical member of the symmetry orbit of the full physical vector `p`
    (`canonical`), or `p` itself where no symmetry applies."""
    return canonical(p, param, frame_observed) if symmetries(param, frame_observed) else np.asarray(p, float)


def _agreement(p_all, cost, model, param, results):
    """The best of the starts with full physical vectors `p_all`, costs `cost` (non-finite:
    failed) and `results`, its canonical member and how many starts reached the best
    minimum up to the symmetries: (best, count, p_best).  Of the starts at the best minimum
    a converged one is preferred: the one of lowest cost may have been cut short while its
    steps were at round-off."""
    p_all, cost = np.asarray(p_all, float), np.where(np.isfinite(cost), cost, np.inf)
    converged = succeeded(results)
    best = int(np.argmin(cost))
    frame_observed = model.frame_observed
    symmetric = bool(symmetries(param, frame_observed))  # else every orbit is the point itself
    scale = param.scales(PARAMETER_NAMES)

    def at_minimum_of(best):
        p_best = _canonical_point(p_all[best], param, frame_observed)
        if not np.isfinite(cost[best]):
            return p_best, []
        near = np.flatnonzero(np.abs(cost - cost[best]) <= AGREED_COST * (1 + cost[best]))
        p_near = closest_in_orbit(p_all[near], p_best, param, frame_observed) if symmetric else p_all[near]
        return p_best, [int(i) for i in near[np.max(np.abs(p_near - p_best) / scale, axis=-1) <= AGREED_PARAMETERS]]

    p_best, members = at_minimum_of(best)
    done = [i for i in members if converged[i]]
    if not converged[best] and done:
        best = min(done, key=lambda i: cost[i])
        p_best, members = at_minimum_of(best)
    return best, len(members), p_best


def _flagged_points(predicted) -> list[str]:
    """Notes on data points the fit matched where a measured one is unlikely to be: flagged
    by the forward model (`predicted["ok"]` false, as a tweezer model's points outside its
    range: their residuals use the values the model computes there), or matched to a
    register that is not stable (`predicted["stable"]` false: the nearest register, a local
    maximum or saddle of the energy on the circle, can absorb noise -- and so fit a
    stiffness that only such registers feel, with error bars that do not see the choice)."""
    if not isinstance(predicted, Mapping):
        return []

    def points(mask):
        bad = np.flatnonzero(mask)
        return bad.size, f"points {bad[:10].tolist()}{' ...' if bad.size > 10 else ''}"

    notes = []
    if predicted.get("ok") is not None and not np.all(predicted["ok"]):
        count, which = points(~np.asarray(predicted["ok"], bool))
        notes.append(
            f"{count} of {np.size(predicted['ok'])} data points are flagged by the model at the fit (predicted['ok'] "
            f"false, e.g. outside its range; {which}): their residuals use the values it computes there"
        )
    if predicted.get("stable") is not None and not np.all(predicted["stable"]):
        count, which = points(~np.asarray(predicted["stable"], bool))
        notes.append(
            f"{count} of {np.size(predicted['stable'])} helices are matched to registers that are not stable "
            f"({which}): if the data are of stable helices, fit with branch='stable' (a nearest unstable register can "
            "absorb noise, and the error bars do not see that choice)"
        )
    return notes


def _best_start(solved, agreement, model, param, solver, method, max_steps, absolute_sigma, weak_threshold, *, once):
    """The `StiffnessFit` of the best of the solved starts (what `_multistart` returns),
    with `agreement` (`_agreement`: the best start, how many agree with it, its canonical
    member of its symmetry orbit) and the error analysis at it (`once`: by
    `jacobian_and_predictions` compiled to run once)."""
    _, cost, results, steps, p_all, q_all = solved
    cost, steps, p_all, q_all = (np.asarray(a) for a in (cost, steps, p_all, q_all))
    frame_observed = model.frame_observed
    best, agree, p_best = agreement
    q = np.concatenate([[p_best[PARAMETER_NAMES.index(n)] for n in param.free], q_all[best, len(param.free):]])
    J, (r, predicted) = jacobian_and_predictions(q, model, param, once=once)
    observed = model.observed_residuals()
    if observed is not None:
        J, r = J[observed], r[observed]
    analysis = error_analysis(
        J, r, dict(zip(param.names, q)), param.scales(param.names), absolute_sigma=absolute_sigma,
        weak_threshold=weak_threshold, symmetries=[text for text, _ in symmetries(param, frame_observed)],
        notes=_flagged_points(predicted),
    )
    result = jax.tree.map(lambda v: np.asarray(np.asarray(v)[best]), results)  # a 0-d array: `RESULTS[result]` reads it
    if not np.isfinite(analysis.cost):
        result = RESULTS.cost_not_finite
    return assemble(
        rod_from_vector(p_best, checked=True), analysis, dict(zip(param.names, q)), r, predicted, result=result,
        method=method, absolute_sigma=absolute_sigma, n_steps=int(steps[best]), start_costs=cost, n_agree=agree,
        problem=FitProblem(model, param, solver, max_steps, jacobian_once=once),
    )
