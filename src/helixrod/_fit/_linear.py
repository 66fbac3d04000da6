"""The closed-form fit of the stiffness from full local twist and moment vectors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from .._rod import rod_from_vector
from .._status import RESULTS
from ._parameters import STIFFNESS_NAMES, TWIST_NAMES
from ._pipeline import StiffnessFit, assemble
from ._report import error_analysis


def fit_stiffness_linear(
    u: ArrayLike,
    m: ArrayLike,
    *,
    m_sigma: ArrayLike = 1.0,
    uhat: ArrayLike | None = None,
    fit_uhat: bool = False,
    absolute_sigma: bool = True,
    weak_threshold: float = 0.1,
) -> StiffnessFit:
    """Closed-form weighted least squares for $K$ (and $\\hat u$) from full local vectors.

    With $u_i$ and $m_i$ known (shape `(n, 3)`, director frame, e.g. from a simulation or a
    measurement of the register), $m = K(u - \\hat u)$ is linear in $(K_1, K_2, K_3, K_{13},
    K_{23})$ for fixed $\\hat u$ (default 0), and with `fit_uhat=True` linear in $K$ and
    $c = K\\hat u$ ($m = Ku - c$); then $\\hat u = K^{-1}c$ with standard errors by the delta
    method.  `m_sigma`: standard deviation of each moment component (scalar, `(n,)` or
    `(n, 3)`).  Returns a `StiffnessFit` (`method="linear"`, one "start"); no frame symmetry
    applies because the vectors fix the frame.  The natural initialiser of `fit_stiffness`:
    `fit_stiffness(data, init=fit_stiffness_linear(u, m).rod)`.
    """
    u = np.asarray(u, float)
    m = np.asarray(m, float)
    if u.ndim != 2 or u.shape[-1] != 3 or m.shape != u.shape:
        raise ValueError(f"u and m must both have shape (n, 3), got {u.shape} and {m.shape}")
    sig = np.broadcast_to(np.asarray(m_sigma, float).reshape(np.shape(m_sigma) + (1,) * (np.ndim(m_sigma) == 1)), u.shape)
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(m))):
        rows = np.flatnonzero(~np.all(np.isfinite(u) & np.isfinite(m), axis=1))
        raise ValueError(f"fit_stiffness_linear: non-finite values in rows {rows[:20].tolist()}")
    if np.any(~(sig > 0)):
        raise ValueError("fit_stiffness_linear: m_sigma must be > 0")
    if fit_uhat and uhat is not None:
        raise ValueError("give either uhat= or fit_uhat=True, not both")
    uh = np.zeros(3) if uhat is None else np.asarray(uhat, float)
    v = u if fit_uhat else u - uh
    n = u.shape[0]
    z = np.zeros(n)
    one = np.ones(n)
    # Columns: K1, K2, K3, K13, K23 [, c1, c2, c3]; rows: m1, m2, m3 of every point.
    rows1 = [v[:, 0], z, z, v[:, 2], z]
    rows2 = [z, v[:, 1], z, z, v[:, 2]]
    rows3 = [z, z, v[:, 2], v[:, 0], v[:, 1]]
    if fit_uhat:
        rows1 += [-one, z, z]
        rows2 += [z, -one, z]
        rows3 += [z, z, -one]
    A = np.concatenate([np.stack(rows1, 1) / sig[:, :1], np.stack(rows2, 1) / sig[:, 1:2], np.stack(rows3, 1) / sig[:, 2:]])
    b = np.concatenate([m[:, 0] / sig[:, 0], m[:, 1] / sig[:, 1], m[:, 2] / sig[:, 2]])
    theta, *_ = np.linalg.lstsq(A, b, rcond=None)
    r = A @ theta - b

    def to_params(th):
        K1, K2, K3, K13, K23 = th[0], th[1], th[2], th[3], th[4]
        if not fit_uhat:
            return th[:5]
        Kmat = jnp.array([[K1, 0.0, K13], [0.0, K2, K23], [K13, K23, K3]])
        return jnp.concatenate([th[:5], jnp.linalg.solve(Kmat, th[5:])])

    params_vec = np.asarray(to_params(jnp.asarray(theta)))
    names = STIFFNESS_NAMES + (TWIST_NAMES if fit_uhat else ())
    # Delta method: J_params = J_theta @ inv(d params / d theta).
    D = np.asarray(jax.jacfwd(to_params)(jnp.asarray(theta)))
    J = A @ np.linalg.inv(D)
    full = np.concatenate([params_vec[:5], params_vec[5:] if fit_uhat else uh])
    k_scale = float(np.sqrt(abs(full[0] * full[1])))
    u_scale = float(np.median(np.linalg.norm(u, axis=1)))
    scales = np.array([k_scale if n in STIFFNESS_NAMES else u_scale for n in names])
    values = dict(zip(names, params_vec))
    # The vectors fix the frame: no symmetry applies.
    analysis = error_analysis(J, r, values, scales, absolute_sigma=absolute_sigma, weak_threshold=weak_threshold)
    rod = rod_from_vector(full, checked=True)
    predicted = {"moment": np.asarray(rod.moment(u))}
    return assemble(rod, analysis, values, r, predicted, result=RESULTS.successful, method="linear",
                    absolute_sigma=absolute_sigma)
