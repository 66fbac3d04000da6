"""The stability atlas of clamped helices (`_bvp/_atlas.py`) against the independent
brute-force discrete rod (`tests/discrete_rod.py`, numpy/scipy only).

A uniform helix of twist u started at the origin with the identity frame has frames
D(s) = expm(s [u]_x) and centreline x(s) = int_0^s D e3 (the screw motion
expm(s [[u]_x, e3; 0, 0])); its body force n is the lab force.  The discrete rod of n_seg rigid
segments (frames at the segment midpoints) is clamped at both ends where the helix puts them,
its equilibrium found by Newton from the helix (multiplier guess n), and the number of
negative eigenvalues of its projected Hessian is the index; the critical length is where its
smallest eigenvalue changes sign as the length grows (O(h^2) from the continuum one:
~2e-3 relative at 30 segments).  The points lie away from the conjugate points at L = 5,
where the discretisation could move the discrete index by one.
"""

import functools

import numpy as np
import pytest
import scipy.linalg
import scipy.optimize

import helixrod
from discrete_rod import equilibrium, expm_so3, hat, hessian_eigenvalues

ROD = helixrod.Rod(1.0, 1.5, 0.8, uhat=(0.0, 1.0, 0.3))
LENGTH = 5.0
N_SEG = 30

# (kappa, tau, register slot) and the index expected at L = 5 (checked below against both).
# Their conjugate points (the atlas's index against length): the first two points have none
# within 20; the third has its first at 5.68 (stable, just short of it); the fourth at 4.27
# and the next beyond 5.25 (index 1); the fifth at 2.63 and ~4.4, the next beyond 5.25
# (index 2).  None lies within 5% of L = 5.
POINTS = [
    (1.2, 0.5, 0, 0),
    (1.0, -0.8, 0, 0),
    (1.8, 0.9, 0, 0),
    (2.0, -0.3, 0, 1),
    (0.4, 0.0, 1, 2),
]
CRITICAL = 3  # the point whose critical length is compared


def helix(kappa, tau, slot):
    eq = helixrod.helix_equilibria(ROD, kappa, tau)
    assert bool(eq.valid[slot])
    return np.asarray(eq.n[slot]), np.asarray(eq.u[slot])


def discrete_eigenvalues(n, u, length, n_seg=N_SEG):
    """Ascending eigenvalues of the discrete second variation of the helix (body force n,
    twist u) clamped over `length`, and the multiplier of its discrete equilibrium."""
    K, uhat = np.asarray(ROD.K), np.asarray(ROD.uhat)
    frames = expm_so3(((np.arange(n_seg) + 0.5) * (length / n_seg))[:, None] * u)
    screw = np.zeros((4, 4))
    screw[:3, :3], screw[2, 3] = hat(u), 1.0
    end = scipy.linalg.expm(screw * length)
    ends = dict(end_frame=end[:3, :3], end_position=end[:3, 3])
    zero, eye = np.zeros(3), np.eye(3)
    frames, N, _ = equilibrium(K, uhat, length, n_seg, "clamped", zero, eye, frames_guess=frames, force_guess=n, **ends)
    return hessian_eigenvalues(K, uhat, length, n_seg, "clamped", frames, zero, eye, multiplier=N, **ends), N


@pytest.fixture(scope="module")
def atlas():
    kappa, tau = (np.array([p[i] for p in POINTS]) for i in (0, 1))
    return helixrod.stability_atlas(ROD, kappa, tau, LENGTH)


@pytest.mark.heavy
def test_index_is_the_number_of_negative_discrete_eigenvalues(atlas):
    for j, (kappa, tau, slot, expected) in enumerate(POINTS):
        n, u = helix(kappa, tau, slot)
        lam, N = discrete_eigenvalues(n, u, LENGTH)
        # The discrete equilibrium is the helix's, up to the discretisation.
        assert np.linalg.norm(N - n) < 0.05 * np.linalg.norm(n)
        negative = int(np.sum(lam < -1e-8 * np.max(np.abs(lam))))
        assert bool(atlas.valid[j, slot])
        assert int(atlas.instability_index[j, slot]) == negative == expected, (kappa, tau, slot)
        assert np.sign(float(atlas.stability_margin[j, slot])) == np.sign(lam[0])
        assert bool(atlas.stable[j, slot]) == (negative == 0)
    expected = [p[3] for p in POINTS]
    assert 0 in expected and max(expected) >= 1


def test_critical_length_is_where_the_discrete_rod_loses_stability(atlas):
    kappa, tau, slot, _ = POINTS[CRITICAL]
    n, u = helix(kappa, tau, slot)
    critical = float(atlas.critical_length[CRITICAL, slot])
    assert 0.0 < critical < LENGTH

    @functools.cache
    def smallest(length):
        return discrete_eigenvalues(n, u, length)[0][0]

    # Bracketed without the atlas: stable at L/2 (and so shorter), unstable at L.
    assert smallest(0.5 * LENGTH) > 0 > smallest(LENGTH)
    discrete = scipy.optimize.brentq(smallest, 0.5 * LENGTH, LENGTH, xtol=1e-6)
    assert critical == pytest.approx(discrete, rel=1e-2)
