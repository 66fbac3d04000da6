"""Whether a fit's error bars may be trusted: the cost along each error bar's line.

A fit's standard errors, covariance and the report come from the Jacobian at the minimum:
they describe the cost as the quadratic $\\tfrac12\\Delta\\chi^2 = \\tfrac12\\,\\delta^T J^T J
\\delta$.  Along the line $\\delta_i(t) = t\\,\\Sigma e_i/\\sigma_i$ -- parameter $i$ moved by $t$
standard errors and every other parameter by what the covariance says it follows with
(the linear approximation of the profile of $i$) -- that quadratic is exactly
$\\Delta\\chi^2 = t^2$.  `linearity_check` evaluates the fit's own cost there, at $t = \\pm k$
(sigmas of errors in variables held at the fit's: `fit_cost_at`): the model's residuals at
$2p$ points, no refits.  Where it is far from $k^2$ the likelihood is not the ellipsoid the
error bars describe within their own range (a curved valley, a bound, a kink of the model)
and the profile likelihood (`profile_likelihood`) or the bootstrap says what the interval
is.  A screen, not a verdict: the profile, which refits the other parameters, never lies
above the line, so a valley that curves away from the line is flagged although its profile
may still be the quadratic (an isotropic fit of 24 helices: its K3 8.3 on the line at $\\pm
2\\sigma$, 4.4 and 4.0 on the profile; its K13 11.8 on the line, 7.7 and 4.0 on the profile);
and a cost that happens to follow $t^2$ along the line is not
flagged (Bates & Watts, *Nonlinear Regression Analysis and Its Applications*, Wiley 1988,
ch. 7, measure the same by curvatures).  A negative $\\Delta\\chi^2$ means a lower cost on
the line: the fit is not the minimum there (another register, another minimum).

Measured (2026-12-07) on force-extension data of one DNA molecule (30 points at zero
torque, K2, K3, K23 and the persistence length free), whose fit reported $K_2 = 578 \\pm 9$
against a true 1327: $\\Delta\\chi^2 = 1378$ at $+2\\sigma$ of $K_2$ (flagged); on the
bundled tweezer example's global fit (errors in variables) every line gives 0.0004 at
$\\pm 0.02\\sigma$ to 1e-3, and at $\\pm 2\\sigma$ $K_2, K_3, K_{23}$, the persistence length
and the offsets 3.89-4.12, while the plectoneme's twist persistence is flagged (25.6 at
$-2\\sigma$, 3.4 at $+2\\sigma$): below it by more than ~1.4 standard errors the cost rises
steeply -- an asymmetric likelihood, whose profile is the honest interval.
"""

from __future__ import annotations

import equinox as eqx
import numpy as np
from jaxtyping import Bool, Float

from ._pipeline import StiffnessFit, fit_cost_at

#: A parameter's line is flagged where its $\\Delta\\chi^2$ at $\\pm k$ standard errors is
#: outside $[k^2/F, F k^2]$ (F = `LINEARITY_FACTOR`), or not finite (the line leaves the
#: model's domain).
LINEARITY_FACTOR = 2.0


class LinearityCheck(eqx.Module):
    """The result of `linearity_check`: `names` of the free parameters; `delta_chi2` `(p, 2)`
    the fit's $\\Delta\\chi^2$ at $-k$ and $+k$ standard errors along each parameter's
    line (NaN for a parameter whose standard error is not finite: it is undetermined, the
    report says so); `expected` $= k^2$ (what the error bars predict); `nonlinear` `(p,)`
    where it is outside $[k^2/2, 2k^2]$ or not finite (the line left the model's domain);
    `flagged` the names of those; `summary()` says which case each is."""

    names: tuple[str, ...] = eqx.field(static=True)
    delta_chi2: Float[np.ndarray, "p 2"]
    expected: float
    nonlinear: Bool[np.ndarray, " p"]

    @property
    def flagged(self) -> tuple[str, ...]:
        """The parameters whose error bars the cost does not bear out."""
        return tuple(n for n, bad in zip(self.names, self.nonlinear) if bad)

    def summary(self) -> str:
        """A table of the check, one parameter per line."""
        lines = [f"Delta chi2 at -{np.sqrt(self.expected):g} and +{np.sqrt(self.expected):g} standard errors "
                 f"(the error bars say {self.expected:g}):"]
        for name, (lo, hi), bad in zip(self.names, self.delta_chi2, self.nonlinear):
            lines.append(f"  {name:30s} {lo:10.4g} {hi:10.4g}" + (f"   {_verdict(lo, hi)}" if bad else ""))
        return "\n".join(lines)


def _verdict(lo: float, hi: float) -> str:
    """What a flagged line's $\\Delta\\chi^2$ at $\\mp k$ says."""
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return "the line leaves the model's domain: profile_likelihood"
    if min(lo, hi) < 0:
        return "lower cost on the line: the fit is not the minimum along it"
    return "not the error bars' quadratic: check with profile_likelihood"


def linearity_check(fit: StiffnessFit, k: float = 2.0) -> LinearityCheck:
    """Whether `fit`'s error bars describe its cost within $\\pm k$ standard errors (module
    docstring): the fit's $\\Delta\\chi^2$ at $\\pm k$ along each free parameter's line
    $\\Sigma e_i/\\sigma_i$, against the $k^2$ the covariance predicts; $2p$ evaluations of the
    model's residuals, no refits.  With `absolute_sigma=False` the covariance's scale (the
    reduced $\\chi^2$) is taken out first, so the expectation is $k^2$ either way.

    **Example**

    ```python
    rod = helixrod.Rod(1.0, 1.5, 0.8, K13=0.2, K23=-0.1, uhat=(0.8, 0.6, 0.3))
    rng = np.random.default_rng(0)
    data = helixrod.synthetic_helix_data(rod, rng.uniform(0.3, 2.5, 60), rng.uniform(-1.5, 2.0, 60), 0.01, jax.random.key(1))
    fit = helixrod.fit_stiffness(data, uhat=rod.uhat)
    check = helixrod.linearity_check(fit)
    check.flagged          # () where the error bars hold; else profile those parameters
    print(check.summary())
    ```
    """
    if fit.problem is None:
        raise ValueError(
            "linearity_check needs the problem of a fit from fit_stiffness in this session "
            "(a fit_stiffness_linear result or a StiffnessFit.load-ed one has none)"
        )
    k = float(k)
    if not (np.isfinite(k) and k > 0):
        raise ValueError(f"linearity_check: k must be finite and > 0, got {k}")
    names = fit.names
    q = np.array([float(fit.params[n]) for n in names])
    covariance = np.asarray(fit.covariance, float)
    if not fit.absolute_sigma and np.isfinite(fit.chi2_reduced) and fit.chi2_reduced > 0:
        covariance = covariance / fit.chi2_reduced
    stderr = np.sqrt(np.diag(covariance))
    determined = np.array([np.isfinite(float(fit.stderr[n])) and s > 0 for n, s in zip(names, stderr)])
    best = fit_cost_at(fit, q)
    delta = np.full((len(names), 2), np.nan)
    for i in np.flatnonzero(determined):
        line = covariance[:, i] / stderr[i]
        for j, side in enumerate((-1.0, 1.0)):
            delta[i, j] = 2.0 * (fit_cost_at(fit, q + side * k * line) - best)
    expected = k * k
    inside = (delta >= expected / LINEARITY_FACTOR) & (delta <= LINEARITY_FACTOR * expected)
    nonlinear = determined & ~np.all(inside, axis=1)
    return LinearityCheck(names=names, delta_chi2=delta, expected=expected, nonlinear=nonlinear)
