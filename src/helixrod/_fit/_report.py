"""What data determine: covariance, standard errors and the identifiability report, from
the Jacobian of the normalised residuals at a fit."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import equinox as eqx
import numpy as np
from jaxtyping import ArrayLike, Float

from .._misc import chi2_survival

# A residual whose derivative exceeds this multiple of the typical (median) one is an exact
# constraint in the error analysis.
_STIFF_ROW = 1e8


class Identifiability(eqx.Module):
    """What the data determine.  `scales` are the units the parameters are measured in for
    the scaled Jacobian $J D$ (`K_scale` for stiffnesses, `u_scale` for twists);
    `singular_values` of $J D$ (descending; `inf` for a direction pinned by a residual of
    unbounded sensitivity, a register at a tangency or cusp, see `notes`); `condition_number`
    the ratio of the largest finite one to the smallest;
    `weak`: the right singular vectors whose scaled standard error $1/s_k$ exceeds
    `weak_threshold`, each as a mapping name -> coefficient (entries below 0.05 dropped) with
    its scaled standard error in `weak_stderr` (`inf` for an exact null direction);
    `determined` and `determined_stderr` the others, in the same form: what partial data
    pin down when single parameters are not (e.g. force-only helix data of an uncoupled
    rod determine $K_3 - K_1$ alone); `rank`
    the numerical rank; `symmetries` the exact frame symmetries that apply (identical
    predictions), and `notes` on near-symmetries and on residuals left out of or
    constraining the error analysis.  `null_directions` `(k, p)`: the exact null directions
    (unit vectors in the scaled parameters; `weak` lists them rounded), along which the
    data say nothing: a quantity that changes along one is undetermined
    (`StiffnessFit.propagate`); None for a report read from a file that has none."""

    names: tuple[str, ...] = eqx.field(static=True)
    scales: Float[np.ndarray, " p"]
    singular_values: Float[np.ndarray, " p"]
    condition_number: float
    rank: int
    weak: tuple = eqx.field(static=True)
    weak_stderr: tuple = eqx.field(static=True)
    weak_threshold: float = eqx.field(static=True)
    symmetries: tuple[str, ...] = eqx.field(static=True)
    notes: tuple[str, ...] = eqx.field(static=True)
    determined: tuple = eqx.field(static=True, default=())
    determined_stderr: tuple = eqx.field(static=True, default=())
    null_directions: Float[np.ndarray, "k p"] | None = None

    def to_dict(self) -> dict:
        """Plain-Python form (JSON-serialisable)."""
        return {
            "scales": np.asarray(self.scales).tolist(),
            "singular_values": np.asarray(self.singular_values).tolist(),
            "condition_number": float(self.condition_number),
            "rank": int(self.rank),
            "weak": [dict(w) for w in self.weak],
            "weak_stderr": list(self.weak_stderr),
            "weak_threshold": float(self.weak_threshold),
            "symmetries": list(self.symmetries),
            "notes": list(self.notes),
            "determined": [dict(w) for w in self.determined],
            "determined_stderr": list(self.determined_stderr),
            "null_directions": None if self.null_directions is None else np.asarray(self.null_directions).tolist(),
        }

    @classmethod
    def from_dict(cls, names, d: dict, weak_threshold: float = 0.1) -> Identifiability:
        """The report of `to_dict` back (for a saved fit)."""
        return cls(
            names=tuple(names),
            scales=np.asarray(d["scales"], float),
            singular_values=np.asarray(d["singular_values"], float),
            condition_number=float(d["condition_number"]),
            rank=int(d["rank"]),
            weak=tuple(tuple(w.items()) for w in d["weak"]),
            weak_stderr=tuple(float(e) for e in d["weak_stderr"]),
            weak_threshold=float(d.get("weak_threshold", weak_threshold)),
            symmetries=tuple(d["symmetries"]),
            notes=tuple(d["notes"]),
            determined=tuple(tuple(w.items()) for w in d.get("determined", [])),
            determined_stderr=tuple(float(e) for e in d.get("determined_stderr", [])),
            null_directions=None if d.get("null_directions") is None else np.asarray(d["null_directions"], float).reshape(-1, len(names)),
        )


class ErrorAnalysis(eqx.Module):
    """The result of `error_analysis`: `covariance` and `correlation` `(p, p)` in the order
    of the names, `stderr` by name (`inf` for a parameter with a share in a null
    direction), `cost` $= \\tfrac12\\sum r^2$, `chi2_reduced` $= 2\\,$cost$/(m - \\mathrm{rank})$,
    and the `identifiability` report."""

    covariance: Float[np.ndarray, "p p"]
    correlation: Float[np.ndarray, "p p"]
    stderr: dict
    cost: float
    chi2_reduced: float
    identifiability: Identifiability


#: Below this chi2 p-value (sigmas trusted) the report notes that the fit does not describe
#: the data: 1e-6 is a 4.9-sigma tail, which a correct model with correct sigmas gives
#: once in a million fits.
POOR_FIT_P_VALUE = 1e-6


def error_analysis(
    jacobian: ArrayLike,
    residuals: ArrayLike,
    values: Mapping[str, float],
    scales: ArrayLike,
    *,
    absolute_sigma: bool = True,
    weak_threshold: float = 0.1,
    symmetries: Sequence[str] = (),
    notes: Sequence[str] = (),
) -> ErrorAnalysis:
    """Covariance, standard errors and the identifiability report of a least-squares fit
    from the Jacobian `(m, p)` of its $\\sigma$-normalised residuals `(m,)` with respect to
    the parameters `values` (name -> value, `p` of them, in the Jacobian's column order),
    each measured in units of `scales` `(p,)` for the report.

    Standard errors are $\\sqrt{\\mathrm{diag}\\,(J^TJ)^{-1}}$ (sigma trusted,
    `absolute_sigma=True`), or that times the reduced $\\chi^2$ when `absolute_sigma=False`.
    Fewer residuals than parameters leave at least $p - m$ exact null directions.  A row
    whose derivative is more than $10^8$ times the typical one (a point whose register sits
    at, or within rounding of, a tangency or a cusp, where the implicit-function derivative
    is unbounded) is treated as an exact constraint -- the limit of its weight -- because an
    SVD resolves singular values only down to eps times the largest: kept in, one such row
    makes every other direction look null.  Rows with non-finite derivatives carry no
    information and are dropped; both are named in `notes`.  With `absolute_sigma`, a
    $\\chi^2 = 2\\,$cost whose p-value is below `POOR_FIT_P_VALUE` is noted too.
    `symmetries`: descriptions of exact symmetries of the model, carried into the report.
    """
    names = tuple(values)
    q = np.array([float(values[n]) for n in names])
    J = np.asarray(jacobian, float)
    r = np.asarray(residuals, float)
    scales = np.asarray(scales, float)
    if J.ndim != 2 or r.shape != J.shape[:1] or J.shape[1] != len(names) or scales.shape != (len(names),):
        raise ValueError(
            f"error_analysis: the Jacobian must be (m, p) with m residuals and p = {len(names)} values and "
            f"scales; got jacobian {J.shape}, residuals {r.shape}, scales {scales.shape}"
        )
    if not weak_threshold > 0:
        raise ValueError(f"error_analysis: weak_threshold must be > 0, got {weak_threshold}")
    m, p = J.shape
    Js = J * scales
    notes = list(notes)
    finite_rows = np.all(np.isfinite(Js), axis=1)
    row_norm = np.linalg.norm(np.where(finite_rows[:, None], Js, 0.0), axis=1)
    typical = float(np.median(row_norm[finite_rows])) if finite_rows.any() else 0.0
    stiff = finite_rows & (row_norm > _STIFF_ROW * typical) if typical > 0 else np.zeros(m, bool)
    if (~finite_rows).any():
        notes.append(f"residuals {np.flatnonzero(~finite_rows).tolist()} have non-finite derivatives: left out of the error bars")
    n_constrained = 0
    free_basis = np.eye(p)
    if stiff.any():
        # The full right factor (p x p) is needed for the free directions; the left one is
        # thin unless there are fewer stiff rows than parameters.
        _, s_c, Vt_c = np.linalg.svd(Js[stiff], full_matrices=int(stiff.sum()) < p)
        n_constrained = int(np.sum(s_c > 1e-10 * s_c[0]))
        free_basis = Vt_c[n_constrained:].T
        notes.append(
            f"residuals {np.flatnonzero(stiff).tolist()} are more than {_STIFF_ROW:.0e} times as sensitive as "
            "the others (a register at a tangency or cusp: the linearisation is not valid there); "
            f"they are treated as exact constraints on {n_constrained} direction(s)"
        )
    J_free = Js[finite_rows & ~stiff] @ free_basis
    # Only the right singular vectors are used: the full left factor (m x m) only when m < p.
    _, s, Vt_free = np.linalg.svd(J_free, full_matrices=J_free.shape[0] < J_free.shape[1])
    s = np.concatenate([s, np.zeros(free_basis.shape[1] - s.size)])  # m < p: exact null directions
    Vt = Vt_free @ free_basis.T
    s_max = s[0] if s.size and s[0] > 0 else 1.0
    null = s <= 1e-10 * s_max
    rank = n_constrained + int(np.sum(~null))
    inv_s2 = np.where(null, 0.0, 1.0 / np.where(null, 1.0, s) ** 2)
    cov_scaled = (Vt.T * inv_s2) @ Vt
    cov = cov_scaled * np.outer(scales, scales)
    cost = 0.5 * float(r @ r)
    dof = m - rank
    chi2_reduced = 2 * cost / dof if dof > 0 else np.nan
    if not absolute_sigma:
        cov = cov * chi2_reduced
    elif dof > 0 and np.isfinite(cost):
        p_value = chi2_survival(2 * cost, dof)
        if p_value < POOR_FIT_P_VALUE:
            notes.append(
                f"the fit does not describe the data within their sigmas: chi2 = {2 * cost:.4g} for {dof} degrees of "
                f"freedom (reduced {chi2_reduced:.3g}, p = {p_value:.2g}); a local minimum (try another init= or more "
                "n_starts=), a model that does not fit, or sigmas that are too small (absolute_sigma=False scales "
                "the error bars by the scatter)"
            )
    var = np.diag(cov).copy()
    undetermined = np.any(np.abs(Vt[null]) > 1e-6, axis=0) if null.any() else np.zeros(p, bool)
    var[undetermined] = np.inf
    stderr = np.sqrt(var)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.sqrt(np.diag(cov))
        corr = cov / np.outer(d, d)
    corr[undetermined, :] = np.nan
    corr[:, undetermined] = np.nan
    weak, weak_err, determined, determined_err = [], [], [], []
    errors = np.where(null, np.inf, 1.0 / np.where(null, 1.0, s))
    if not absolute_sigma:
        errors = np.where(np.isfinite(errors), errors * np.sqrt(chi2_reduced), errors)
    # Each direction with its largest component positive; read as Python floats (NumPy's
    # scalars one by one: 198 -> 184 us the analysis of a 60 x 5 Jacobian).
    if Vt.size:
        Vt_signed = Vt * np.sign(Vt[np.arange(Vt.shape[0]), np.argmax(np.abs(Vt), axis=1)])[:, None]
    else:  # no parameters
        Vt_signed = Vt
    for err, row in zip(errors.tolist(), Vt_signed.tolist()):
        combination = tuple((name, round(value, 4)) for name, value in zip(names, row) if abs(value) >= 0.05)
        (weak if err > weak_threshold else determined).append(combination)
        (weak_err if err > weak_threshold else determined_err).append(err)
    qd = dict(zip(names, q))
    if "K1" in qd and "K2" in qd:
        i1, i2 = names.index("K1"), names.index("K2")
        diff_err = np.sqrt(max(cov[i1, i1] + cov[i2, i2] - 2 * cov[i1, i2], 0.0))
        if abs(qd["K1"] - qd["K2"]) < 2 * diff_err:
            notes.append(
                "K1 and K2 agree within 2 standard errors: near K1 = K2 the bending axes, and with "
                "them the split of the couplings between K13 and K23 (and uhat1, uhat2), are poorly "
                "determined; the labels d1 (softer) and d2 may swap between data sets"
            )
    ident = Identifiability(
        names=names,
        scales=scales,
        singular_values=np.concatenate([np.full(n_constrained, np.inf), s]),
        condition_number=(float(s[0] / s[-1]) if s[-1] > 0 else float("inf")) if s.size else 1.0,
        rank=rank,
        weak=tuple(weak),
        weak_stderr=tuple(weak_err),
        weak_threshold=weak_threshold,
        symmetries=tuple(symmetries),
        notes=tuple(notes),
        determined=tuple(determined),
        determined_stderr=tuple(determined_err),
        null_directions=Vt[null],
    )
    return ErrorAnalysis(
        covariance=cov,
        correlation=corr,
        stderr=dict(zip(names, stderr)),
        cost=cost,
        chi2_reduced=chi2_reduced,
        identifiability=ident,
    )
