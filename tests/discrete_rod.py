"""An independent, brute-force discrete model of an elastic Kirchhoff rod (inextensible,
unshearable), written with numpy/scipy only, to cross-check the library's conjugate-point
stability test.  Nothing here imports helixrod.

Conventions (the library's):

* arclength ``s`` in ``[0, L]``; director frame ``D(s)`` in SO(3) with columns ``d1, d2, d3``;
  the tangent is ``d3``, ``x' = D e3``;
* strain ``u`` in the director frame, ``D' = D [u]_x``;
* energy density ``W(u) = 1/2 (u - uhat)^T K (u - uhat)``, ``K`` symmetric positive definite;
* clamped at ``s = 0``: ``x(0) = x0``, ``D(0) = D0``; at ``s = L`` one of

  - ``"clamped"``: ``x(L)`` and ``D(L)`` prescribed;
  - ``"tweezer"``: ``D(L)`` prescribed, ``x(L)`` free, dead force ``F`` at the end
    (potential ``-F . x(L)``);
  - ``"loaded"``: ``x(L)`` and ``D(L)`` free, dead force ``F`` at the end, no moment.

Discretisation.  ``n`` rigid segments of length ``h = L/n`` with frames ``D_i``
(``i = 0..n-1``), segment ``i`` covering ``[i h, (i+1) h]`` (its frame stands for the
midpoint ``s_i = (i + 1/2) h``).  The frames form the chain ``D0, D_0, ..., D_{n-1}[, D(L)]``
and each consecutive pair ``(A, B)`` carries one strain sample

    u = vee(log(A^T B)) / l,    energy  l W(u),

with ``l = h`` between two segments and ``l = h/2`` for the half segments that attach the
boundary frames (``D0`` always, ``D(L)`` when it is prescribed; with a free end frame there is
no end term).  The end point is ``x(L) = x0 + h sum_i D_i e3``; the discrete energy is
``E = sum_k l_k W(u_k) - F . x(L)``.

Unknowns are rotation vectors ``w_i`` with ``D_i = Dbar_i expm([w_i]_x)``.  The gradient is
analytic (right Jacobians of the SO(3) exponential and logarithm); the Hessian is the central
finite difference of that gradient at ``w = 0`` (exponential coordinates centred on the
configuration), so at an equilibrium it is the intrinsic second variation.  For
``"clamped"`` the end-position constraint enters through the Lagrangian
``E - N . (x(L) - x_L)``: its gradient is the one of the ``"tweezer"`` energy with force
``N``, and the second variation is the Hessian of the Lagrangian projected onto the null
space ``Z`` of the constraint Jacobian, ``Z^T H Z``.

Degenerate constraint.  When the rod is straight and ``|x_L - x0| = L`` (no shortening), the
axial row of the constraint Jacobian vanishes identically (an inextensible rod cannot change
its end-to-end distance to first order), so the constraint Jacobian has rank 2 and the axial
component of ``N`` (the tension) is not determined by the equilibrium equations.  Here the
null space is taken with the numerical rank (dimension ``3n - 2``) and the undetermined
tension is kept at the value passed in (``force_guess`` in :func:`equilibrium`, default 0),
which is the classical linearised convention (e.g. the twisted clamped-clamped rod buckles
at ``M L / B = 8.9868`` at zero tension).
"""

import numpy as np
import scipy.linalg
import scipy.optimize

__all__ = [
    "centreline",
    "constraint_jacobian",
    "critical_value",
    "energy",
    "equilibrium",
    "expm_so3",
    "gradient",
    "hat",
    "hessian",
    "hessian_eigenvalues",
    "instability_index",
    "logm_so3",
    "natural_frames",
    "right_jacobian",
    "right_jacobian_inv",
    "rotation_about_axis",
    "straight_frames",
    "vee",
]

BCS = ("clamped", "tweezer", "loaded")

# -- SO(3) helpers (vectorised over leading axes) ----------------------------------------------


def hat(w):
    """The skew matrix ``[w]_x`` of vectors ``w`` (..., 3) -> (..., 3, 3)."""
    w = np.asarray(w, dtype=float)
    z = np.zeros(w.shape[:-1])
    return np.stack(
        [
            np.stack([z, -w[..., 2], w[..., 1]], -1),
            np.stack([w[..., 2], z, -w[..., 0]], -1),
            np.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


def vee(S):
    """Inverse of :func:`hat` applied to the skew part of ``S`` (..., 3, 3) -> (..., 3)."""
    S = np.asarray(S, dtype=float)
    return 0.5 * np.stack(
        [
            S[..., 2, 1] - S[..., 1, 2],
            S[..., 0, 2] - S[..., 2, 0],
            S[..., 1, 0] - S[..., 0, 1],
        ],
        -1,
    )


def _coefficients(t):
    """``sin t / t``, ``(1 - cos t) / t^2``, ``(t - sin t) / t^3`` with series for small t."""
    t = np.asarray(t, dtype=float)
    small = t < 1e-4
    ts = np.where(small, 1.0, t)
    t2 = t * t
    a = np.where(small, 1 - t2 / 6 + t2 * t2 / 120, np.sin(ts) / ts)
    b = np.where(small, 0.5 - t2 / 24 + t2 * t2 / 720, (1 - np.cos(ts)) / ts**2)
    c = np.where(small, 1 / 6 - t2 / 120 + t2 * t2 / 5040, (ts - np.sin(ts)) / ts**3)
    return a, b, c


def expm_so3(w):
    """Rodrigues' formula: ``expm([w]_x)`` for rotation vectors ``w`` (..., 3)."""
    w = np.asarray(w, dtype=float)
    a, b, _ = _coefficients(np.linalg.norm(w, axis=-1))
    W = hat(w)
    return np.eye(3) + a[..., None, None] * W + b[..., None, None] * (W @ W)


def logm_so3(R):
    """Principal rotation vector ``vee(log R)`` (angle in ``[0, pi]``) of rotations (..., 3, 3)."""
    R = np.asarray(R, dtype=float)
    v = vee(R)  # sin(t) * axis
    s = np.linalg.norm(v, axis=-1)
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    t = np.arctan2(s, c)
    a, _, _ = _coefficients(t)
    out = v / a[..., None]
    near_pi = t > np.pi - 1e-3
    if np.any(near_pi):
        # (R + R^T)/2 - cos t I = (1 - cos t) axis axis^T: take its largest column, sign from v.
        Sym = 0.5 * (R + np.swapaxes(R, -1, -2)) - c[..., None, None] * np.eye(3)
        k = np.argmax(np.diagonal(Sym, axis1=-2, axis2=-1), axis=-1)
        col = np.take_along_axis(Sym, k[..., None, None], axis=-1)[..., 0]
        axis = col / np.linalg.norm(col, axis=-1, keepdims=True)
        sign = np.where(np.sum(axis * v, axis=-1) < 0, -1.0, 1.0)
        out = np.where(near_pi[..., None], (sign * t)[..., None] * axis, out)
    return out


def right_jacobian(w):
    """``J_r(w)`` with ``expm(w + d) = expm(w) expm(J_r(w) d) + O(d^2)``."""
    w = np.asarray(w, dtype=float)
    _, b, c = _coefficients(np.linalg.norm(w, axis=-1))
    W = hat(w)
    return np.eye(3) - b[..., None, None] * W + c[..., None, None] * (W @ W)


def right_jacobian_inv(w):
    """``J_r(w)^{-1}``: ``log(expm(w) expm(p)) = w + J_r(w)^{-1} p + O(p^2)``."""
    w = np.asarray(w, dtype=float)
    t = np.linalg.norm(w, axis=-1)
    small = t < 1e-4
    ts = np.where(small, 1.0, t)
    t2 = t * t
    e = np.where(
        small,
        1 / 12 + t2 / 720 + t2 * t2 / 30240,
        1 / ts**2 - (1 + np.cos(ts)) / (2 * ts * np.sin(ts)),
    )
    W = hat(w)
    return np.eye(3) + 0.5 * W + e[..., None, None] * (W @ W)


def rotation_about_axis(D, angle, axis=2):
    """``D`` turned by ``angle`` about its own director ``d_axis`` (body-frame rotation)."""
    w = np.zeros(np.shape(angle) + (3,))
    w[..., axis] = angle
    return np.asarray(D, dtype=float) @ expm_so3(w)


# -- configurations -----------------------------------------------------------------------------


def straight_frames(D0, L, n, twist_rate=0.0):
    """Segment frames (n, 3, 3) of the straight rod along ``D0 e3`` twisted uniformly at
    ``twist_rate`` (frame ``i`` at ``s_i = (i + 1/2) L/n``): ``D_i = D0 Rz(twist_rate s_i)``.
    The twist is integrated, so any total angle (several turns) is represented."""
    h = L / n
    s = (np.arange(n) + 0.5) * h
    return rotation_about_axis(np.asarray(D0, float), twist_rate * s)


def natural_frames(uhat, L, n, D0):
    """The discrete natural (stress-free) shape: segment frames (n, 3, 3) with every strain
    sample equal to ``uhat``, and the end frame ``D(L)`` that continues it by a half segment.
    Returns ``(frames, end_frame)``."""
    h = L / n
    uhat = np.asarray(uhat, float)
    half, full = expm_so3(0.5 * h * uhat), expm_so3(h * uhat)
    frames = np.empty((n, 3, 3))
    frames[0] = np.asarray(D0, float) @ half
    for i in range(1, n):
        frames[i] = frames[i - 1] @ full
    return frames, frames[-1] @ half


def centreline(frames, L, x0):
    """Centreline nodes (n+1, 3): ``x_0 = x0``, ``x_{i+1} = x_i + h D_i e3``."""
    frames = np.asarray(frames, float)
    h = L / frames.shape[-3]
    steps = h * frames[..., :, :, 2]
    x0 = np.broadcast_to(np.asarray(x0, float), steps.shape[:-2] + (3,))
    return np.concatenate(
        [x0[..., None, :], x0[..., None, :] + np.cumsum(steps, axis=-2)], axis=-2
    )


# -- energy and gradient ------------------------------------------------------------------------


def _check(K, uhat, bc, end_frame):
    if bc not in BCS:
        raise ValueError(f"bc must be one of {BCS}, got {bc!r}")
    K = np.asarray(K, float)
    if K.shape != (3, 3) or not np.allclose(K, K.T):
        raise ValueError("K must be a symmetric 3x3 matrix")
    if bc in ("clamped", "tweezer") and end_frame is None:
        raise ValueError(f"bc={bc!r} needs end_frame")
    return K, np.broadcast_to(np.asarray(uhat, float), (3,))


def _chain(frames, D0, end_frame):
    """Frames of the strain chain (..., n+1 or n+2, 3, 3) and the sample lengths in units of h."""
    frames = np.asarray(frames, float)
    batch = frames.shape[:-3]
    parts = [np.broadcast_to(np.asarray(D0, float), batch + (1, 3, 3)), frames]
    n = frames.shape[-3]
    lengths = np.ones(n)  # pairs (D0, D_0), (D_0, D_1), ..., (D_{n-2}, D_{n-1})
    lengths[0] = 0.5
    if end_frame is not None:
        parts.append(np.broadcast_to(np.asarray(end_frame, float), batch + (1, 3, 3)))
        lengths = np.append(lengths, 0.5)
    return np.concatenate(parts, axis=-3), lengths


def _end_frame(bc, end_frame):
    return None if bc == "loaded" else end_frame


def energy(K, uhat, L, frames, D0, bc, end_frame=None, force=None, x0=None):
    """Discrete energy ``sum_k l_k W(u_k) - F . x(L)`` of segment frames (..., n, 3, 3).
    For ``"clamped"`` this is the elastic energy only (``force`` ignored)."""
    K, uhat = _check(K, uhat, bc, end_frame)
    frames = np.asarray(frames, float)
    n = frames.shape[-3]
    h = L / n
    chain, lengths = _chain(frames, D0, _end_frame(bc, end_frame))
    theta = logm_so3(np.swapaxes(chain[..., :-1, :, :], -1, -2) @ chain[..., 1:, :, :])
    ell = h * lengths
    e = (theta / ell[:, None]) - uhat
    elastic = 0.5 * np.sum(ell * np.einsum("...i,ij,...j->...", e, K, e), axis=-1)
    if bc == "clamped" or force is None:
        return elastic
    x0 = np.zeros(3) if x0 is None else np.asarray(x0, float)
    xL = x0 + h * np.sum(frames[..., :, :, 2], axis=-2)
    return elastic - xL @ np.asarray(force, float)


def gradient(K, uhat, L, frames, D0, bc, end_frame=None, force=None, w=None):
    """Analytic gradient (..., n, 3) of the discrete energy with respect to the rotation
    vectors ``w`` of ``D_i = frames_i expm([w_i]_x)`` (at ``w = 0`` when ``w`` is None).
    ``force`` is the dead end force (``"tweezer"``, ``"loaded"``) or, for ``"clamped"``, the
    multiplier ``N``: the result is then the gradient of the Lagrangian ``E - N . x(L)``."""
    K, uhat = _check(K, uhat, bc, end_frame)
    frames = np.asarray(frames, float)
    if w is not None:
        w = np.asarray(w, float)
        frames = frames @ expm_so3(w)
    n = frames.shape[-3]
    h = L / n
    chain, lengths = _chain(frames, D0, _end_frame(bc, end_frame))
    A, B = chain[..., :-1, :, :], chain[..., 1:, :, :]
    R = np.swapaxes(A, -1, -2) @ B
    theta = logm_so3(R)
    ell = h * lengths
    m = ((theta / ell[:, None]) - uhat) @ K  # K symmetric: the moment K (u - uhat)
    # d(sum l W)/d theta = m; theta(A exp(pA), B exp(pB)) = theta + J_r^{-1}(theta)(pB - R^T pA)
    gB = np.einsum("...ji,...j->...i", right_jacobian_inv(theta), m)
    gA = -np.einsum("...ij,...j->...i", R, gB)
    # chain index k holds D0 (k = 0), segment frames (k = 1..n), end frame (k = n+1)
    g = gB[..., :n, :].copy()  # pair k-1 -> k: frame k-1 is B
    g[..., : n - 1, :] += gA[..., 1:n, :]  # pair k -> k+1 with both frames free
    if gA.shape[-2] == n + 1:  # pair (D_{n-1}, D(L))
        g[..., n - 1, :] += gA[..., n, :]
    if force is not None:
        # -F . h D_i e3, d(D_i e3) = D_i (p_i x e3)  ->  gradient -h e3 x (D_i^T F)
        f_body = np.einsum("...ji,j->...i", frames, np.asarray(force, float))
        g -= h * np.cross(np.array([0.0, 0.0, 1.0]), f_body)
    if w is not None:
        g = np.einsum("...ji,...j->...i", right_jacobian(w), g)
    return g


def constraint_jacobian(frames, L):
    """Jacobian (3, 3n) of ``x(L)`` with respect to ``w`` at ``w = 0``: block ``-h D_i [e3]_x``."""
    frames = np.asarray(frames, float)
    n = frames.shape[0]
    h = L / n
    blocks = -h * frames @ hat(np.array([0.0, 0.0, 1.0]))  # (n, 3, 3)
    return np.transpose(blocks, (1, 0, 2)).reshape(3, 3 * n)


def _gradient_jacobian(K, uhat, L, frames, D0, bc, end_frame, force, step):
    """Central finite differences (3n, 3n) of the analytic gradient at ``w = 0``; column ``j``
    is ``d g / d w_j``.  All ``2 * 3n`` perturbed gradients in one vectorised call."""
    n = frames.shape[0]
    dof = 3 * n
    dw = step * np.eye(dof).reshape(dof, n, 3)
    w = np.concatenate([dw, -dw])
    g = gradient(K, uhat, L, frames, D0, bc, end_frame, force, w=w).reshape(2, dof, dof)
    return ((g[0] - g[1]) / (2 * step)).T


# -- equilibrium --------------------------------------------------------------------------------


def equilibrium(
    K,
    uhat,
    L,
    n,
    bc,
    x0,
    D0,
    end_frame=None,
    end_position=None,
    force=None,
    frames_guess=None,
    force_guess=None,
    *,
    tol=1e-11,
    maxiter=50,
    step=1e-5,
    max_rotation=0.5,
):
    """Discrete equilibrium by Newton's method on the gradient of the (Lagrangian) energy.

    Each iteration linearises the analytic gradient at ``w = 0`` (finite-difference Jacobian),
    solves (least squares, so a rank-deficient constraint is fine) and moves the frames,
    ``D_i <- D_i expm([dw_i]_x)`` (rotation steps capped at ``max_rotation`` rad).  For
    ``"clamped"`` the unknowns also include the multiplier ``N`` (the lab force at the end) and
    the equations ``x(L) = end_position``; a component of ``N`` that the equations do not
    determine stays at ``force_guess`` (default 0).

    The guess is ``frames_guess`` (n, 3, 3); by default the straight rod along ``D0 e3`` with
    the natural twist ``uhat[2]`` integrated (:func:`straight_frames`).

    Returns ``(frames, N, nodes)``: frames (n, 3, 3), ``N`` (3,) for ``"clamped"`` (None
    otherwise) and the centreline nodes (n+1, 3).  Raises RuntimeError without convergence.
    """
    K, uhat = _check(K, uhat, bc, end_frame)
    x0 = np.asarray(x0, float)
    D0 = np.asarray(D0, float)
    if frames_guess is None:
        frames = straight_frames(D0, L, n, uhat[2])
    else:
        frames = np.array(frames_guess, dtype=float)
        if frames.shape != (n, 3, 3):
            raise ValueError(f"frames_guess must have shape {(n, 3, 3)}")
    clamped = bc == "clamped"
    if clamped:
        if end_position is None:
            raise ValueError('bc="clamped" needs end_position')
        end_position = np.asarray(end_position, float)
        N = np.zeros(3) if force_guess is None else np.array(force_guess, dtype=float)
    else:
        N = None
    load = N if clamped else force
    for _ in range(maxiter):
        load = N if clamped else force
        # typical size of a gradient entry (a moment times a rotation): |K|/L + |F| L
        scale = np.linalg.norm(K, 2) / L + (
            0.0 if load is None else np.linalg.norm(load) * L
        )
        g = gradient(K, uhat, L, frames, D0, bc, end_frame, load).reshape(-1)
        H = _gradient_jacobian(K, uhat, L, frames, D0, bc, end_frame, load, step)
        if clamped:
            c = centreline(frames, L, x0)[-1] - end_position
            A = constraint_jacobian(frames, L)
            res = np.concatenate([g, c])
            ok = np.max(np.abs(g)) < tol * scale and np.max(np.abs(c)) < tol * L
            # d/dw (g - A^T dN): the FD Jacobian H already contains -N's part; dN enters as -A^T
            J = np.block([[H, -A.T], [A, np.zeros((3, 3))]])
        else:
            res = g
            ok = np.max(np.abs(g)) < tol * scale
            J = H
        if ok:
            break
        delta = np.linalg.lstsq(J, -res, rcond=1e-12)[0]
        dw = delta[: 3 * n].reshape(n, 3)
        big = np.max(np.linalg.norm(dw, axis=-1))
        if big > max_rotation:
            delta *= max_rotation / big
            dw = delta[: 3 * n].reshape(n, 3)
        frames = frames @ expm_so3(dw)
        if clamped:
            N = N + delta[3 * n :]
    else:
        raise RuntimeError(
            f"equilibrium: no convergence in {maxiter} Newton iterations"
        )
    return frames, N, centreline(frames, L, x0)


# -- second variation ---------------------------------------------------------------------------


def hessian(
    K,
    uhat,
    L,
    n,
    bc,
    frames,
    x0,
    D0,
    end_frame=None,
    end_position=None,
    force=None,
    multiplier=None,
    *,
    step=1e-5,
    rank_rtol=1e-9,
):
    """The (projected) Hessian of the discrete energy at the configuration ``frames``.

    Central finite differences (step ``step``) of the analytic gradient in exponential
    coordinates centred on ``frames``.  For ``"clamped"`` it is the Hessian of the Lagrangian
    ``E - multiplier . x(L)`` projected on an orthonormal basis ``Z`` of the null space of the
    constraint Jacobian (numerical rank with ``rank_rtol``): ``Z^T H Z``.

    Returns ``(H_sym, asymmetry)``: the symmetrised matrix and
    ``max|H - H^T| / max|H|`` of the unsymmetrised one (finite-difference accuracy at an
    equilibrium).  ``end_position`` and ``x0`` do not enter the second variation; they are
    accepted for a uniform signature.
    """
    K, uhat = _check(K, uhat, bc, end_frame)
    frames = np.asarray(frames, float)
    if frames.shape != (n, 3, 3):
        raise ValueError(f"frames must have shape {(n, 3, 3)}")
    if bc == "clamped":
        if multiplier is None:
            raise ValueError('bc="clamped" needs the multiplier')
        load = np.asarray(multiplier, float)
    else:
        load = force
    H = _gradient_jacobian(K, uhat, L, frames, D0, bc, end_frame, load, step)
    asym = np.max(np.abs(H - H.T)) / np.max(np.abs(H))
    H = 0.5 * (H + H.T)
    if bc == "clamped":
        A = constraint_jacobian(frames, L)
        _, s, Vt = np.linalg.svd(A)
        rank = int(np.sum(s > rank_rtol * s[0]))
        Z = Vt[rank:].T
        H = Z.T @ H @ Z
        H = 0.5 * (H + H.T)
    return H, asym


def hessian_eigenvalues(
    K,
    uhat,
    L,
    n,
    bc,
    frames,
    x0,
    D0,
    end_frame=None,
    end_position=None,
    force=None,
    multiplier=None,
    **kwargs,
):
    """Ascending eigenvalues (numpy array) of :func:`hessian` (``scipy.linalg.eigh``)."""
    H, _ = hessian(
        K,
        uhat,
        L,
        n,
        bc,
        frames,
        x0,
        D0,
        end_frame,
        end_position,
        force,
        multiplier,
        **kwargs,
    )
    return scipy.linalg.eigh(H, eigvals_only=True)


def instability_index(*args, rtol=1e-8, **kwargs):
    """Number of negative eigenvalues of :func:`hessian_eigenvalues` (same arguments): those
    below ``-rtol * max|eigenvalue|``."""
    lam = hessian_eigenvalues(*args, **kwargs)
    return int(np.sum(lam < -rtol * np.max(np.abs(lam))))


def critical_value(smallest, lo, hi, *, xtol=1e-10):
    """A root of ``smallest(p)`` (e.g. the k-th eigenvalue as a function of a load parameter)
    in ``[lo, hi]`` by Brent's method; ``smallest(lo)`` and ``smallest(hi)`` must differ in sign."""
    return scipy.optimize.brentq(smallest, lo, hi, xtol=xtol)
