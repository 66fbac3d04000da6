"""Experiment design: which helices (or axial loads) to measure so that a fit determines a
model's parameters best, and whether any set of such measurements can.

The information of a measurement is the Fisher information of its $\\sigma$-normalised
residuals at a nominal rod, $J_i^T J_i$ with $J_i$ the Jacobian of `fit_stiffness`'s forward
model (the same register rule, observables and errors-in-variables weights) with respect to
the free parameters of the model class, each in its scale (`k_scale`, `u_scale`).  A design
of $n$ measurements maximises a criterion of $\\mathcal I = \\sum_{i} J_i^T J_i$ over
$n$-subsets of the candidates: D-optimal $\\log\\det\\mathcal I$ (default; invariant to
reparameterisation), A-optimal $-\\operatorname{tr}\\mathcal I^{-1}$ (the summed scaled
variances), E-optimal $\\lambda_\\min(\\mathcal I)$ (the worst direction); by a greedy start and
Fedorov's exchange (Fedorov 1972; Atkinson, Donev & Tobias, *Optimum Experimental Designs*,
2007), with a ridge of $10^{-9}$ of the mean eigenvalue while the information is still
singular.  The design is local: it is optimal for the nominal rod, the usual compromise of
nonlinear design (design, fit, design again).

Candidates are helices $(\\kappa, \\tau)$ at which the axial force and/or moment are
measured (`observe`), or axial loads $(F, M)$ at which the helix they hold is measured
(`observe=("kappa", "tau")`): each load is replaced by its stable helix of lowest energy
(`helices_under_load`; the lowest-energy one where none is flagged stable, as for the
neutral helices of an isotropic rod), and the information of measuring $(\\kappa, \\tau)$ with covariance
$\\Sigma$ at a controlled load is that of measuring $(F, M)$ with the covariance
$A \\Sigma A^T$, $A = \\partial(F, M)/\\partial(\\kappa, \\tau)$ -- the errors-in-variables
weights of `fit_stiffness` with a negligible load error.
"""

from __future__ import annotations

from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._equilibria import helix_equilibria
from .._load import helices_under_load
from .._rod import PARAMETER_NAMES, Rod, rod_vector
from ._compare import model_options, with_gauge
from ._helix_data import HelixData
from ._models import forward_model
from ._parameters import Parameterisation, resolve_fixed
from ._pipeline import jacobian_and_predictions
from ._report import error_analysis
from ._symmetry import coupling_gauge_free, in_coupling_gauge

CRITERIA = ("D", "A", "E")
OBSERVABLES = (("force", "moment"), ("force",), ("moment",), ("kappa", "tau"))
# The load's own error for shape measurements, relative to the RMS force and moment.
_CONTROL_ERROR = 1e-6


class ExperimentDesign(eqx.Module):
    """The result of `design_experiment`.

    `index` `(n,)`: the chosen candidates (indices into the given arrays, sorted); `kappa`, `tau`
    of the chosen helices (and `force`, `moment` at them, predicted by the nominal rod);
    `names`: the model's free parameters; `stderr`: name -> standard error the design
    would give (`inf` for a parameter it leaves undetermined); `covariance` `(p, p)`;
    `criterion` and its `value` (D: $\\log\\det$, A: $-\\operatorname{tr}\\mathcal I^{-1}$,
    E: $\\lambda_\\min$, of the scaled information; `-inf` where singular); `rank` of the
    design's information and `rank_all` of all candidates together, with `determinable`
    (`rank_all` equals the number of free parameters: some design of these candidates
    determines the model) and `undetermined`, the combinations no design of these
    candidates can determine (null directions of the candidates' whole information, as
    name -> coefficient); `observe`; `dropped`: indices of candidate loads that hold no
    helix in the box (left out; `index` counts the others)."""

    index: np.ndarray
    kappa: jax.Array
    tau: jax.Array
    force: jax.Array
    moment: jax.Array
    names: tuple[str, ...] = eqx.field(static=True)
    stderr: dict
    covariance: jax.Array
    criterion: str = eqx.field(static=True)
    value: float
    rank: int
    rank_all: int
    undetermined: tuple = eqx.field(static=True)
    observe: tuple[str, ...] = eqx.field(static=True)
    dropped: np.ndarray

    @property
    def determinable(self) -> bool:
        """Whether the candidates together determine every free parameter."""
        return self.rank_all == len(self.names)

    def summary(self) -> str:
        """Plain text: the chosen points, the standard errors, what stays undetermined."""
        lines = [
            f"ExperimentDesign ({self.criterion}-optimal, observing {', '.join(self.observe)}): "
            f"{self.index.size} measurements, rank {self.rank} of {len(self.names)}"
        ]
        for name in self.names:
            lines.append(f"  {name:<6} stderr {float(self.stderr[name]):.4g}")
        for combination in self.undetermined:
            lines.append("undetermined by any design of these candidates: " + " ".join(f"{c:+.3f}*{n}" for n, c in combination))
        if self.dropped.size:
            lines.append(f"{self.dropped.size} candidate loads hold no helix in the box: left out")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return self.summary()


def _criterion(information, kind: str) -> float:
    p = information.shape[0]
    w = np.linalg.eigvalsh(information)
    if w[0] <= 1e-12 * max(w[-1], 1e-300):
        return -np.inf
    if kind == "D":
        return float(np.sum(np.log(w)))
    if kind == "A":
        return float(-np.sum(1.0 / w))
    return float(w[0]) if p else 0.0


def _select(blocks, n: int, kind: str, max_sweeps: int = 20) -> np.ndarray:
    """Greedy selection of `n` blocks `(c, p, p)`, then Fedorov exchanges until no swap of a
    chosen and an unchosen candidate improves the criterion."""
    c, p, _ = blocks.shape
    total = blocks.sum(0)
    ridge = 1e-9 * max(float(np.trace(total)) / max(p, 1), 1e-300) * np.eye(p)
    chosen: list[int] = []
    information = np.zeros((p, p))

    def score(matrix):
        value = _criterion(matrix, kind)
        return value if np.isfinite(value) else _criterion(matrix + ridge, kind) - 1e6

    for _ in range(n):
        rest = np.setdiff1d(np.arange(c), chosen)
        values = [score(information + blocks[j]) for j in rest]
        best = int(rest[int(np.argmax(values))])
        chosen.append(best)
        information = information + blocks[best]
    current = score(information)
    for _ in range(max_sweeps):
        improved = False
        for position in range(n):
            rest = np.setdiff1d(np.arange(c), chosen)
            if not rest.size:
                break
            base = information - blocks[chosen[position]]
            values = np.array([score(base + blocks[j]) for j in rest])
            j = int(np.argmax(values))
            if values[j] > current + 1e-12 * max(abs(current), 1.0):
                information = base + blocks[rest[j]]
                chosen[position] = int(rest[j])
                current = values[j]
                improved = True
        if not improved:
            break
    return np.sort(np.asarray(chosen))


def _scale(values, sigma, what: str):
    rms = lambda x: float(np.sqrt(np.mean(np.square(x)))) or 1.0  # noqa: E731
    if isinstance(sigma, (tuple, list)):
        if len(sigma) != 2 or not all(np.isfinite(s) and s > 0 for s in sigma):
            raise ValueError(f"design_experiment: sigma must be a relative level > 0 or two absolute sigmas > 0 of {what}, got {sigma!r}")
        return float(sigma[0]), float(sigma[1])
    sigma = float(sigma)
    if not (np.isfinite(sigma) and sigma > 0):
        raise ValueError(f"design_experiment: sigma must be > 0, got {sigma}")
    return sigma * rms(values[0]), sigma * rms(values[1])


def design_experiment(
    rod: Rod,
    candidates,
    n: int,
    *,
    model="general",
    observe=("force", "moment"),
    sigma=0.01,
    criterion: str = "D",
    fit_uhat: bool = False,
    kappa_max: float | None = None,
    tau_range: tuple[float, float] | None = None,
) -> ExperimentDesign:
    """Choose `n` of the `candidates` that determine the parameters of `model` best.

    - `rod`: the nominal rod (the design is optimal for it; its $\\hat u$ is held fixed
      unless `fit_uhat=True`).
    - `candidates`: helices, a pair `(kappa, tau)` or a mapping with `"kappa"`, `"tau"`
      (1-D, broadcast); or axial loads, a mapping with `"force"`, `"moment"` together with
      `kappa_max`, `tau_range` (the box `helices_under_load` searches).
    - `model`: a class of `MODEL_CLASSES` (`"isotropic"`, `"anisotropic"`,
      `"isotropic-coupled"`, `"general"`) or `{"fix": {...}, "isotropic": bool}`.
    - `observe`: at helices, `("force", "moment")`, `("force",)` or `("moment",)`; at loads
      `("kappa", "tau")` (the default there).
    - `sigma`: measurement errors -- a relative level (of the RMS of each observable over
      the candidates; default 0.01) or two absolute sigmas.
    - `criterion`: `"D"` (default), `"A"` or `"E"` (module docstring).

    The register of each helix is the one of lowest energy on the circle (slot 0 of
    `helix_equilibria`, as `synthetic_helix_data`); a load's helix is its stable one of
    lowest energy.  Returns an `ExperimentDesign`; `ValueError` for bad options or
    `n` larger than the number of usable candidates.
    """
    if criterion not in CRITERIA:
        raise ValueError(f"design_experiment: criterion must be one of {CRITERIA}, got {criterion!r}")
    spec = with_gauge(model_options(model if isinstance(model, str) else "model", model), fit_uhat, False)
    by_load = isinstance(candidates, Mapping) and ("force" in candidates or "moment" in candidates)
    if by_load:
        if observe == ("force", "moment"):
            observe = ("kappa", "tau")
        if kappa_max is None or tau_range is None:
            raise ValueError("design_experiment: load candidates need kappa_max= and tau_range= (the box of helices_under_load)")
    observe = (observe,) if isinstance(observe, str) else tuple(observe)
    allowed = (("kappa", "tau"),) if by_load else OBSERVABLES[:3]
    if observe not in allowed:
        raise ValueError(f"design_experiment: observe must be one of {allowed} for {'loads' if by_load else 'helices'}, got {observe!r}")
    kappa, tau, force, moment, kept, dropped = _candidate_helices(rod, candidates, by_load, kappa_max, tau_range)
    if isinstance(n, bool) or not 1 <= int(n) <= kappa.size:
        raise ValueError(f"design_experiment: n must be in 1..{kappa.size} (the usable candidates), got {n}")
    if by_load:
        s_kappa, s_tau = _scale((kappa, tau), sigma, "kappa and tau")
        s_force, s_moment = _scale((force, moment), _CONTROL_ERROR, "")
        data = HelixData(force, moment, kappa, tau, s_force, s_moment, kappa_sigma=s_kappa, tau_sigma=s_tau)
    else:
        s_force, s_moment = _scale((force, moment), sigma, "force and moment")
        data = HelixData(
            force if "force" in observe else None, moment if "moment" in observe else None, kappa, tau, s_force, s_moment
        )
    fitted = forward_model(data, branch="nearest", errors_in_variables=by_load)  # the exact (F, M): the register measured
    p_nominal = np.asarray(rod_vector(rod), float)
    if model == "isotropic-coupled":
        if coupling_gauge_free(not fit_uhat and bool(np.any(p_nominal[5:7] != 0)), False):
            # The same rod (for K1 = K2, which the class check below asks) with its coupling
            # turned into K13; the candidates' registers turn with it.
            p_nominal = in_coupling_gauge(p_nominal)
        else:  # the class's K23 = 0 is no gauge here: both couplings free (`compare_models`)
            spec = {**spec, "fix": {k: v for k, v in spec["fix"].items() if k != "K23"}}
    uhat = None if fit_uhat else p_nominal[5:]
    fixed = resolve_fixed(uhat, fit_uhat, spec["fix"], isotropic=spec["isotropic"])
    p = dict(zip(PARAMETER_NAMES, p_nominal))
    size = max(abs(p["K1"]), abs(p["K2"]), abs(p["K3"]))
    outside = [f"{k} = {p[k]:.6g} (the class has {v:.6g})" for k, v in fixed.items() if k in p and abs(p[k] - v) > 1e-12 * max(size, abs(v), 1e-300)]
    if spec["isotropic"] and abs(p["K1"] - p["K2"]) > 1e-12 * size:
        outside.append(f"K1 = {p['K1']:.6g} != K2 = {p['K2']:.6g} (the class has K1 = K2)")
    if outside:
        raise ValueError(f"design_experiment: the nominal rod is not in the model class: {'; '.join(outside)}")
    param = Parameterisation(fixed, float(np.sqrt(p["K1"] * p["K2"])), float(np.median(np.hypot(kappa, tau))), (), None, spec["isotropic"])
    q = jnp.asarray([p[name] for name in param.free])
    J, _ = jacobian_and_predictions(q, fitted, param)
    scales = param.scales(param.names)
    Js = np.asarray(J) * scales
    rows = Js.reshape(2, kappa.size, -1)  # (F, M) rows per candidate (zero where not observed)
    blocks = np.einsum("rci,rcj->cij", rows, rows)
    chosen = _select(blocks, int(n), criterion)
    information = blocks[chosen].sum(0)
    J = np.asarray(J)
    analysis = error_analysis(
        J[np.concatenate([chosen, chosen + kappa.size])], np.zeros(2 * chosen.size), dict(zip(param.names, np.asarray(q))), scales
    )
    whole = error_analysis(J, np.zeros(J.shape[0]), dict(zip(param.names, np.asarray(q))), scales)
    null = tuple(w for w, e in zip(whole.identifiability.weak, whole.identifiability.weak_stderr) if not np.isfinite(e))
    return ExperimentDesign(
        index=kept[chosen], kappa=jnp.asarray(kappa[chosen]), tau=jnp.asarray(tau[chosen]), force=jnp.asarray(force[chosen]),
        moment=jnp.asarray(moment[chosen]), names=param.names, stderr=analysis.stderr, covariance=analysis.covariance,
        criterion=criterion, value=_criterion(information, criterion), rank=int(analysis.identifiability.rank),
        rank_all=int(whole.identifiability.rank), undetermined=null, observe=observe, dropped=dropped,
    )


def _candidate_helices(rod, candidates, by_load: bool, kappa_max, tau_range):
    """The candidates as helices `(kappa, tau)` (1-D) with their axial force and moment on
    the register measured, the indices of the candidates they are, and those of the loads
    that hold no helix."""
    if by_load:
        if "force" not in candidates or "moment" not in candidates:
            raise ValueError("design_experiment: load candidates need both 'force' and 'moment'")
        force, moment = np.broadcast_arrays(np.atleast_1d(np.asarray(candidates["force"], float)),
                                            np.atleast_1d(np.asarray(candidates["moment"], float)))
        if force.ndim != 1 or not (np.all(np.isfinite(force)) and np.all(np.isfinite(moment))):
            raise ValueError("design_experiment: candidate loads must be finite 1-D arrays")
        held = jax.vmap(lambda F, M: helices_under_load(rod, F, M, kappa_max=kappa_max, tau_range=tau_range))(
            jnp.asarray(force), jnp.asarray(moment)
        )
        valid, stable = np.asarray(held.valid), np.asarray(held.valid & held.stable)
        # Where none is flagged stable (e.g. the neutral helices of an isotropic rod), any.
        usable = np.where(stable.any(axis=1, keepdims=True), stable, valid)
        energy = np.where(usable, np.asarray(held.energy), np.inf)
        pick = np.argmin(energy, axis=1)
        ok = np.isfinite(energy[np.arange(force.size), pick])
        take = lambda x: np.asarray(x)[np.arange(force.size), pick][ok]  # noqa: E731
        return take(held.kappa), take(held.tau), take(held.force), take(held.moment), np.flatnonzero(ok), np.flatnonzero(~ok)
    if isinstance(candidates, Mapping):
        if "kappa" not in candidates or "tau" not in candidates:
            raise ValueError("design_experiment: candidates must have 'kappa' and 'tau' (helices) or 'force' and 'moment' (loads)")
        candidates = (candidates["kappa"], candidates["tau"])
    if not isinstance(candidates, (tuple, list)) or len(candidates) != 2:
        raise ValueError("design_experiment: candidates must be (kappa, tau), or a mapping of helices or of loads")
    kappa, tau = np.broadcast_arrays(np.atleast_1d(np.asarray(candidates[0], float)), np.atleast_1d(np.asarray(candidates[1], float)))
    if kappa.ndim != 1 or not (np.all(np.isfinite(kappa)) and np.all(np.isfinite(tau))):
        raise ValueError("design_experiment: candidate kappa and tau must be finite 1-D arrays")
    if np.any(kappa <= 0):
        raise ValueError(f"design_experiment: candidate kappa must be > 0; rows {np.flatnonzero(kappa <= 0)[:20].tolist()} are not")
    # The register of lowest energy on the circle (slot 0), as synthetic_helix_data.
    eq = helix_equilibria(rod, jnp.asarray(kappa), jnp.asarray(tau))
    force, moment = np.asarray(eq.force[:, 0]), np.asarray(eq.moment[:, 0])
    return kappa.copy(), tau.copy(), force, moment, np.arange(kappa.size), np.zeros(0, int)
