"""Tests of the brute-force discrete Kirchhoff rod in `discrete_rod.py` (numpy/scipy only),
the independent reference for the library's conjugate-point stability test: its SO(3)
helpers and analytic gradient, its equilibria (elastica, consistency of the three end
conditions) and its second variation against closed-form critical loads.

Measured relative errors of the critical values (bisection on an eigenvalue, O(h^2)):
n = 40: clamped-free -1.3e-4, clamped-sliding -5.1e-4, third clamped-free mode -1.2e-3,
twisted clamped-clamped +3.4e-4; n = 20: four times as large.
"""

import math

import discrete_rod as dr
import numpy as np
import pytest
import scipy.integrate
import scipy.optimize

L = 1.0
X0 = np.zeros(3)
D0 = np.eye(3)
# first positive root of tan x = x, doubled: the twisted clamped-clamped rod's M L / B
TWIST_CRITICAL = 2 * scipy.optimize.brentq(
    lambda x: math.tan(x) - x, 4.4, 4.5, xtol=1e-15
)

K_GENERAL = np.array([[1.0, 0.0, 0.2], [0.0, 1.5, 0.1], [0.2, 0.1, 0.8]])
UHAT_GENERAL = np.array([0.3, -0.2, 0.5])


def _axial(P):
    """Compressive dead force of size P along the straight rod's axis (D0 e3 = e3)."""
    return np.array([0.0, 0.0, -P])


def _eig(K, bc, n, P=0.0, **kw):
    kw.setdefault("frames", dr.straight_frames(D0, L, n))
    return dr.hessian_eigenvalues(K, 0.0, L, n, bc, x0=X0, D0=D0, force=_axial(P), **kw)


def _index(K, bc, n, P=0.0, **kw):
    kw.setdefault("frames", dr.straight_frames(D0, L, n))
    return dr.instability_index(K, 0.0, L, n, bc, x0=X0, D0=D0, force=_axial(P), **kw)


def _random_config(rng, n):
    frames = dr.straight_frames(D0, L, n, 0.4) @ dr.expm_so3(
        0.3 * rng.normal(size=(n, 3))
    )
    return frames, dr.expm_so3(rng.normal(size=3)), rng.normal(size=3)


# -- SO(3) helpers and gradient -------------------------------------------------------------------


def test_so3_helpers(rng):
    w = rng.normal(size=(20, 3))
    w *= (rng.uniform(0, 3.0, size=20) / np.linalg.norm(w, axis=-1))[:, None]
    w[0] = [1e-9, -2e-9, 3e-9]
    R = dr.expm_so3(w)
    np.testing.assert_allclose(
        R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14
    )
    np.testing.assert_allclose(dr.logm_so3(R), w, atol=1e-13)
    near_pi = (
        np.array([0.3, -0.4, 0.5]) / np.linalg.norm([0.3, -0.4, 0.5]) * (np.pi - 1e-7)
    )
    np.testing.assert_allclose(dr.logm_so3(dr.expm_so3(near_pi)), near_pi, atol=1e-8)
    # right Jacobians: expm(w + d) = expm(w) expm(J_r d), log(expm(w) expm(p)) = w + J_r^{-1} p
    eps = 1e-6
    for v in w[:5]:
        Jfd = np.stack(
            [
                dr.logm_so3(dr.expm_so3(v).T @ dr.expm_so3(v + eps * e)) / eps
                for e in np.eye(3)
            ],
            -1,
        )
        np.testing.assert_allclose(Jfd, dr.right_jacobian(v), atol=1e-5)
        np.testing.assert_allclose(
            dr.right_jacobian_inv(v) @ dr.right_jacobian(v), np.eye(3), atol=1e-13
        )


@pytest.mark.parametrize("bc", dr.BCS)
def test_gradient_matches_energy_differences(rng, bc):
    n = 7
    frames, end_frame, force = _random_config(rng, n)
    w = 0.2 * rng.normal(size=(n, 3))
    load = None if bc == "clamped" else force
    g = dr.gradient(K_GENERAL, UHAT_GENERAL, L, frames, D0, bc, end_frame, load, w=w)
    eps = 1e-6
    dw = eps * np.eye(3 * n).reshape(3 * n, n, 3)

    def E(ws):
        return dr.energy(
            K_GENERAL,
            UHAT_GENERAL,
            L,
            frames @ dr.expm_so3(ws),
            D0,
            bc,
            end_frame,
            load,
            X0,
        )

    gfd = ((E(w + dw) - E(w - dw)) / (2 * eps)).reshape(n, 3)
    np.testing.assert_allclose(g, gfd, atol=1e-8 * np.abs(g).max())


def test_constraint_jacobian(rng):
    n = 6
    frames, _, _ = _random_config(rng, n)
    eps = 1e-6
    dw = eps * np.eye(3 * n).reshape(3 * n, n, 3)
    xp = dr.centreline(frames @ dr.expm_so3(dw), L, X0)[:, -1]
    xm = dr.centreline(frames @ dr.expm_so3(-dw), L, X0)[:, -1]
    np.testing.assert_allclose(
        dr.constraint_jacobian(frames, L), ((xp - xm) / (2 * eps)).T, atol=1e-9
    )


# -- equilibria ----------------------------------------------------------------------------------


def _elastica_tip(F, B):
    """Tip of the planar cantilever elastica (clamped along e3 at 0, dead force F e1 at L) by
    shooting: B theta'' = -F cos(theta), theta(0) = 0, theta'(L) = 0; tangent (sin, 0, cos)."""

    def rhs(s, y):
        return [y[1], -F / B * math.cos(y[0]), math.sin(y[0]), math.cos(y[0])]

    def end(k0):
        return scipy.integrate.solve_ivp(
            rhs, (0, L), [0, k0, 0, 0], rtol=1e-12, atol=1e-13
        ).y[:, -1]

    k0 = scipy.optimize.brentq(lambda k: end(k)[1], 0.0, F * L / B, xtol=1e-14)
    y = end(k0)
    return np.array([y[2], 0.0, y[3]])


def test_cantilever_elastica():
    """Large deflection of a clamped-free rod under a lateral dead force, F L^2 / B = 1."""
    B, F, n = 1.0, 1.0, 40
    K = np.diag([B, B, 0.7])
    frames, N, nodes = dr.equilibrium(
        K, 0.0, L, n, "loaded", X0, D0, force=[F, 0.0, 0.0]
    )
    assert N is None and nodes.shape == (n + 1, 3)
    np.testing.assert_allclose(nodes[0], X0)
    tip = _elastica_tip(F, B)  # about (0.3018, 0, 0.9435)
    np.testing.assert_allclose(nodes[-1], tip, atol=1e-3)
    # small load: linear beam theory F L^3 / (3 B)
    _, _, nodes = dr.equilibrium(K, 0.0, L, n, "loaded", X0, D0, force=[1e-4, 0.0, 0.0])
    assert nodes[-1][0] == pytest.approx(1e-4 * L**3 / (3 * B), rel=1e-3)
    assert (
        dr.instability_index(
            K, 0.0, L, n, "loaded", frames, X0, D0, force=[F, 0.0, 0.0]
        )
        == 0
    )


def test_clamped_recovers_tweezer_force(rng):
    """A tweezer equilibrium under force F is a clamped equilibrium (same ends) with N = F;
    the clamped (projected) problem is at least as stable."""
    n = 30
    F = np.array([0.8, -0.5, -1.0])
    DL = dr.expm_so3(np.array([0.3, 0.2, 0.4]))
    args = (K_GENERAL, UHAT_GENERAL, L, n)
    frames, N, nodes = dr.equilibrium(*args, "tweezer", X0, D0, end_frame=DL, force=F)
    assert N is None
    guess = frames @ dr.expm_so3(0.05 * rng.normal(size=(n, 3)))
    frames_c, N_c, nodes_c = dr.equilibrium(
        *args,
        "clamped",
        X0,
        D0,
        end_frame=DL,
        end_position=nodes[-1],
        frames_guess=guess,
    )
    np.testing.assert_allclose(N_c, F, atol=1e-8)
    np.testing.assert_allclose(frames_c, frames, atol=1e-9)
    np.testing.assert_allclose(nodes_c, nodes, atol=1e-9)
    lam_t = dr.hessian_eigenvalues(
        *args, "tweezer", frames, X0, D0, end_frame=DL, force=F
    )
    lam_c = dr.hessian_eigenvalues(
        *args,
        "clamped",
        frames_c,
        X0,
        D0,
        end_frame=DL,
        end_position=nodes[-1],
        multiplier=N_c,
    )
    assert lam_t.shape == (3 * n,) and lam_c.shape == (3 * n - 3,)
    assert lam_c[0] >= lam_t[0] - 1e-9  # Cauchy interlacing


@pytest.mark.parametrize("bc", dr.BCS)
def test_hessian_symmetric_and_positive_unloaded(rng, bc):
    """At the natural shape (anisotropic, coupled K, curved and twisted uhat) the Newton solve
    returns it from a perturbed guess, and the Hessian is symmetric and positive definite."""
    n = 30
    frames, DL = dr.natural_frames(UHAT_GENERAL, L, n, D0)
    xL = dr.centreline(frames, L, X0)[-1]
    guess = frames @ dr.expm_so3(0.1 * rng.normal(size=(n, 3)))
    kw = {"end_frame": DL, "end_position": xL, "force": np.zeros(3)}
    sol, N, _ = dr.equilibrium(
        K_GENERAL, UHAT_GENERAL, L, n, bc, X0, D0, frames_guess=guess, **kw
    )
    np.testing.assert_allclose(sol, frames, atol=1e-10)
    if bc == "clamped":
        np.testing.assert_allclose(N, 0.0, atol=1e-8)
    H, asym = dr.hessian(
        K_GENERAL, UHAT_GENERAL, L, n, bc, sol, X0, D0, multiplier=N, **kw
    )
    assert asym < 1e-8
    assert H.shape == ((3 * n - 3,) * 2 if bc == "clamped" else (3 * n,) * 2)
    lam = np.linalg.eigvalsh(H)
    assert lam[0] > 0.0
    assert (
        dr.instability_index(
            K_GENERAL, UHAT_GENERAL, L, n, bc, sol, X0, D0, multiplier=N, **kw
        )
        == 0
    )
    # straight, isotropic, unloaded: positive as well
    K = np.diag([1.0, 1.0, 0.7])
    H, asym = dr.hessian(
        K,
        0.0,
        L,
        n,
        bc,
        dr.straight_frames(D0, L, n),
        X0,
        D0,
        end_frame=D0,
        end_position=[0, 0, L],
        force=np.zeros(3),
        multiplier=np.zeros(3),
    )
    assert asym < 1e-8 and np.linalg.eigvalsh(H)[0] > 0.0


# -- Euler critical loads ------------------------------------------------------------------------


def test_clamped_free_isotropic():
    """Clamped-free ("loaded") under a compressive dead force: P_c = pi^2 B / (4 L^2), two
    lateral directions; discretisation error O(h^2)."""
    B = 1.0
    K = np.diag([B, B, 0.7])
    pc = math.pi**2 * B / (4 * L**2)
    errors = []
    for n in (20, 40):
        p = dr.critical_value(
            lambda P, n=n: _eig(K, "loaded", n, P)[0], 0.5 * pc, 2 * pc
        )
        errors.append(p / pc - 1)
    assert abs(errors[1]) < 1e-3  # measured -1.3e-4
    assert errors[0] / errors[1] == pytest.approx(4.0, rel=0.05)
    n = 40
    assert _index(K, "loaded", n, 0.97 * pc) == 0
    assert _index(K, "loaded", n, 1.03 * pc) == 2


def test_clamped_free_anisotropic():
    """K1 < K2: index 1 between pi^2 K1 / 4 and pi^2 K2 / 4, 2 up to 9 pi^2 K1 / 4, then 3."""
    K1, K2, n = 1.0, 2.0, 40
    K = np.diag([K1, K2, 0.7])
    p1, p2, p3 = (math.pi**2 * k / (4 * L**2) for k in (K1, K2, 9 * K1))
    for k, pk, lo, hi in ((0, p1, 0.5, 1.5), (1, p2, 0.75, 1.5), (2, p3, 0.8, 1.1)):
        p = dr.critical_value(
            lambda P, k=k: _eig(K, "loaded", n, P)[k], lo * pk, hi * pk
        )
        assert p == pytest.approx(pk, rel=2e-3)  # measured -1.3e-4, -1.3e-4, -1.2e-3
    assert _index(K, "loaded", n, 0.97 * p1) == 0
    assert _index(K, "loaded", n, 1.03 * p1) == 1
    assert _index(K, "loaded", n, 0.97 * p2) == 1
    assert _index(K, "loaded", n, 1.03 * p2) == 2
    assert _index(K, "loaded", n, 0.97 * p3) == 2
    assert _index(K, "loaded", n, 1.03 * p3) == 3


def test_clamped_sliding():
    """ "tweezer" with D(L) = D(0): clamped-sliding, P_c = pi^2 B / L^2."""
    B, n = 1.0, 40
    K = np.diag([B, B, 0.7])
    pc = math.pi**2 * B / L**2
    p = dr.critical_value(
        lambda P: _eig(K, "tweezer", n, P, end_frame=D0)[0], 0.5 * pc, 2 * pc
    )
    assert p == pytest.approx(pc, rel=2e-3)  # measured -5.1e-4
    assert _index(K, "tweezer", n, 0.97 * pc, end_frame=D0) == 0
    assert _index(K, "tweezer", n, 1.03 * pc, end_frame=D0) == 2


# -- twisted clamped-clamped rod ---------------------------------------------------------------


def _twisted(K, n, angle):
    """The straight rod twisted by `angle` between clamps at distance L (no shortening): the
    guess is the exact equilibrium, zero tension (the tension is undetermined, see the module)."""
    frames = dr.straight_frames(D0, L, n, angle / L)
    DL = dr.rotation_about_axis(D0, angle)
    kw = {"end_frame": DL, "end_position": np.array([0.0, 0.0, L])}
    frames, N, nodes = dr.equilibrium(
        K, 0.0, L, n, "clamped", X0, D0, frames_guess=frames, **kw
    )
    return frames, N, nodes, kw


def test_twisted_clamped_clamped():
    """Loses stability at M L / B = 8.9868 (2 x first root of tan x = x), M = K3 angle / L,
    with index 2 (the two buckling planes of the isotropic rod) just above."""
    B, K3, n = 1.0, 0.7, 40
    K = np.diag([B, B, K3])
    angle_c = TWIST_CRITICAL * B / K3  # about 12.8 rad: two turns
    frames, N, nodes, kw = _twisted(K, n, 0.9 * angle_c)
    np.testing.assert_allclose(N, 0.0, atol=1e-12)
    np.testing.assert_allclose(nodes[:, :2], 0.0, atol=1e-14)
    # the discrete strain is the uniform twist, hence the lab moment K3 angle / L along e3
    strain = dr.logm_so3(np.swapaxes(frames[:-1], -1, -2) @ frames[1:]) / (L / n)
    np.testing.assert_allclose(
        strain, np.broadcast_to([0, 0, 0.9 * angle_c / L], strain.shape), atol=1e-12
    )

    def smallest(angle):
        frames, N, _, kw = _twisted(K, n, angle)
        return dr.hessian_eigenvalues(
            K, 0.0, L, n, "clamped", frames, X0, D0, multiplier=N, **kw
        )[0]

    angle = dr.critical_value(smallest, 0.5 * angle_c, 1.5 * angle_c)
    assert K3 * angle / L * L / B == pytest.approx(
        TWIST_CRITICAL, rel=2e-3
    )  # measured +3.4e-4
    for factor, index in ((0.97, 0), (1.03, 2)):
        frames, N, _, kw = _twisted(K, n, factor * angle_c)
        assert (
            dr.instability_index(
                K, 0.0, L, n, "clamped", frames, X0, D0, multiplier=N, **kw
            )
            == index
        )
