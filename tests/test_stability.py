"""Stability of finite rods (`_bvp/_stability.py`) against closed forms derived here and an
independent brute-force second variation (`tests/discrete_rod.py`, numpy/scipy only).

Closed forms (straight rod, bending stiffness B, length L, clamped at s = 0):

- dead compressive end load P, free end (clamped-free): the Jacobi equation $B\\psi'' + P\\psi = 0$,
  $\\psi(0) = 0$, $\\psi'(L) = 0$ has a solution first at $P = \\pi^2 B / (4L^2)$, then at
  $(2j+1)^2$ times that; with $K_1 \\ne K_2$ each bending plane on its own;
- the end frame held, the end free to slide sideways (clamped-sliding): $\\psi(0) = \\psi(L) =
  0$ gives $P = \\pi^2 B/L^2$;
- both ends clamped, no shortening, twisted by a moment M (Greenhill): the lateral deflection
  $w = y + iz$ obeys $Bw'''' - iMw''' = 0$; with $w = w' = 0$ at both ends the determinant
  vanishes when $e^{i\\theta}(1 - i\\theta/2) = 1 + i\\theta/2$, $\\theta = ML/B$, i.e.
  $\\tan(\\theta/2) = \\theta/2$: $\\theta = 8.98682$; the mode and its rotation by 90° about the
  axis make it a double one (the index jumps by 2);
- both ends clamped, brought together along their common axis to a chord $h < L$: the first
  buckled mode is the planar inflexional elastica, a full period of the pendulum
  $B\\theta'' = -P\\sin\\theta$ (Love, sec. 263): with $m = \\sin^2(\\alpha/2)$ of its largest
  angle $\\alpha$, $L\\sqrt{P/B} = 4K(m)$ and $h/L = 2E(m)/K(m) - 1$.
"""

import warnings

import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest
import scipy.integrate
import scipy.optimize
import scipy.special

import helixrod
from helixrod._bvp._stability import piece_transfer
from helixrod._bvp._variations import FEWEST_STEPS_PER_RADIAN, STEPS_PER_RADIAN, PieceVariations, steps_per_radian
from discrete_rod import centreline, equilibrium, hessian_eigenvalues

L = 1.0


def margin(rod, end, **kwargs):
    """The margin of the state the bulk guess leads to (the straight one, here): the default
    solve would leave an unstable state for a buckled one."""
    return float(helixrod.solve_boundary_value(rod, L, end=end, guess="helix", throw=False, **kwargs).stability_margin)


def critical(fn, lo, hi):
    return scipy.optimize.brentq(fn, lo, hi, xtol=1e-13)


@pytest.mark.heavy
def test_euler_clamped_free():
    rod = helixrod.Rod(1.0, 1.0, 0.8)
    p_c = np.pi**2 / 4
    load = lambda P: helixrod.Loaded(force=(0.0, 0.0, -P))  # noqa: E731
    assert critical(lambda P: margin(rod, load(P)), 0.5 * p_c, 1.5 * p_c) == pytest.approx(p_c, rel=1e-6)
    below = helixrod.solve_boundary_value(rod, L, end=load(0.9 * p_c))
    above = helixrod.solve_boundary_value(rod, L, end=load(1.1 * p_c), guess="helix")
    assert bool(below.stable) and int(below.instability_index) == 0
    # The straight state is still an equilibrium above the load, now unstable in two planes.
    assert bool(above.ok) and not bool(above.stable) and int(above.instability_index) == 2
    # Smooth: linear in the load near the critical one, as the Rayleigh quotient is.
    margins = [margin(rod, load(f * p_c)) for f in (0.8, 0.9, 1.0, 1.1)]
    assert np.allclose(np.diff(margins), np.diff(margins)[0], rtol=1e-3)


@pytest.mark.heavy
def test_column_with_a_rigid_extension():
    """A cantilever whose compressive dead load acts at the tip of a rigid bar of length a
    continuing its end (`Loaded(hook=(0, 0, a))`).  Its buckled deflection is
    w = w_tip (1 - cos ks), k^2 = P/B, and the tip's w(L) + a w'(L) = w_tip gives
    tan(kL) = 1/(ka) (a = 0: Euler's pi^2/4); for a = 0.5, kL tan(kL) = 2."""
    rod = helixrod.Rod(1.0, 1.0, 0.8)
    a = 0.5
    k = scipy.optimize.brentq(lambda k: a * k * np.tan(k * L) - 1.0, 1e-6, np.pi / (2 * L) - 1e-9)
    p_c = k**2
    load = lambda P: helixrod.Loaded(force=(0.0, 0.0, -P), hook=(0.0, 0.0, a))  # noqa: E731
    assert critical(lambda P: margin(rod, load(P)), 0.5 * p_c, 1.5 * p_c) == pytest.approx(p_c, rel=1e-6)  # measured 1e-8
    assert p_c < 0.5 * np.pi**2 / 4  # the bar halves the load


@pytest.mark.heavy
def test_buckled_cantilever_by_default():
    """Above the Euler load the straight state is unstable; the default solve pushes along
    its unstable direction onto the buckled elastica: with $k = \\sin(\\alpha/2)$ of the tip
    angle $\\alpha$, $K(k) = L\\sqrt{P/B}$, the tip moves sideways by $2k\\sqrt{B/P}$ and
    lies at $z = \\sqrt{B/P}\\,(2E(k) - K(k))$ (complete elliptic integrals)."""
    rod = helixrod.Rod(1.0, 1.0, 0.8)
    for factor in (1.1, 1.5):
        P = factor * np.pi**2 / 4
        sol = helixrod.solve_boundary_value(rod, L, end=helixrod.Loaded(force=(0.0, 0.0, -P)))
        k = float(mpmath.findroot(lambda k: mpmath.ellipk(k**2) - np.sqrt(P) * L, (0.01, 0.999), solver="anderson"))
        z = float((2 * mpmath.ellipe(k**2) - mpmath.ellipk(k**2)) / np.sqrt(P))
        # Neutral, not unstable: the buckled isotropic rod may turn about the load line.
        assert bool(sol.stable) and abs(float(sol.stability_margin)) < 1e-6
        assert np.hypot(*np.asarray(sol.end_position[:2])) == pytest.approx(2 * k / np.sqrt(P), abs=1e-8)
        assert float(sol.end_position[2]) == pytest.approx(z, abs=1e-8)


def test_index_rises_one_per_mode_of_an_anisotropic_rod():
    rod = helixrod.Rod(1.0, 2.0, 0.8)  # critical loads p_c (1, 2, 9, 18, 25, ...)
    p_c = np.pi**2 / 4
    for factor, index in [(0.5, 0), (1.5, 1), (5.0, 2), (12.0, 3), (20.0, 4)]:
        end = helixrod.Loaded(force=(0.0, 0.0, -factor * p_c))
        sol = helixrod.solve_boundary_value(rod, L, end=end, guess="helix", throw=False)
        assert int(sol.instability_index) == index, factor


def test_euler_clamped_sliding():
    rod = helixrod.Rod(1.0, 1.0, 0.8)
    end = lambda P: helixrod.Tweezer(np.eye(3), (0.0, 0.0, -P))  # noqa: E731
    p_c = np.pi**2
    assert critical(lambda P: margin(rod, end(P)), 0.5 * p_c, 1.5 * p_c) == pytest.approx(p_c, rel=1e-6)


def test_greenhill_twisted_shaft():
    # C = 4 B: the critical twist angle M L / C stays within half a turn of the guess.
    rod = helixrod.Rod(1.0, 1.0, 4.0)
    half = scipy.optimize.brentq(lambda x: np.tan(x) - x, 4.0, 4.6)
    theta_c = 2 * half  # 8.98682
    end = lambda M: helixrod.Clamped((0.0, 0.0, L), helixrod.so3_exp(np.array([0.0, 0.0, M * L / 4.0])))  # noqa: E731
    assert critical(lambda M: margin(rod, end(M)), 8.0, 10.0) == pytest.approx(theta_c, rel=1e-6)
    above = helixrod.solve_boundary_value(rod, L, end=end(1.05 * theta_c), guess="helix")
    assert int(above.instability_index) == 2


def test_the_test_is_as_accurate_as_the_solve_asks():
    """The stability test's Jacobi fields take fewer steps at a looser ODE tolerance
    (`_variations.steps_per_radian`): Greenhill's critical twist from the margin's zero at
    `ode_rtol` 1e-5 is still within that tolerance of the closed form, with 4-12 steps per
    radian from the loosest to the tightest tolerance, monotone."""
    rod = helixrod.Rod(1.0, 1.0, 4.0)
    theta_c = 2 * scipy.optimize.brentq(lambda x: np.tan(x) - x, 4.0, 4.6)
    end = lambda M: helixrod.Clamped((0.0, 0.0, L), helixrod.so3_exp(np.array([0.0, 0.0, M * L / 4.0])))  # noqa: E731
    loose = dict(atol=1e-5, ode_rtol=1e-5, ode_atol=1e-5)
    assert critical(lambda M: margin(rod, end(M), **loose), 8.0, 10.0) == pytest.approx(theta_c, rel=1e-5)
    per_radian = np.asarray(steps_per_radian(np.logspace(-12, 0, 13)))
    assert per_radian[0] == STEPS_PER_RADIAN and per_radian[-1] == FEWEST_STEPS_PER_RADIAN == 4
    assert np.all(np.diff(per_radian) <= 0) and 4 < float(steps_per_radian(1e-6)) < STEPS_PER_RADIAN


def test_piece_transfer_is_the_linearised_map():
    """`piece_transfer`, written out, against `jax.jacfwd` of the linear map it stands for
    (the node and wrench variations at a piece's start to those at its end), at a general
    frame, wrench and piece."""
    rng = np.random.default_rng(3)
    frame = np.asarray(helixrod.so3_exp(rng.normal(size=3)))
    N, M_a, compliance = rng.normal(size=3), rng.normal(size=3), 1e-3
    piece = PieceVariations(rng.normal(size=3), np.eye(3), rng.normal(size=3), rng.normal(size=(3, 6)), rng.normal(size=(3, 6)))
    r, dp, drot = frame @ piece.position, frame @ piece.d_position, frame @ piece.d_rotation

    def linear(v):
        dx, dth, dN, dM = v[:3], v[3:6], v[6:9], v[9:]
        dw = jnp.concatenate([frame.T @ (dN + jnp.cross(N, dth)), frame.T @ (dM + jnp.cross(M_a, dth))])
        dx_b = dx + jnp.cross(dth, r) + dp @ dw + compliance * dN
        dth_b = dth + drot @ dw
        dM_b = dM - jnp.cross(dx_b - dx, N) - jnp.cross(r, dN)
        return jnp.concatenate([dx_b, dth_b, dN, dM_b])

    expected = jax.jacfwd(linear)(jnp.zeros(12))
    np.testing.assert_allclose(piece_transfer(frame, N, M_a, piece, compliance), expected, rtol=0, atol=1e-14)


@pytest.mark.heavy
def test_matches_a_discrete_second_variation():
    """A straight, twisted rod with anisotropy and bend-twist coupling under a compressive
    tweezer force: the critical force of the conjugate-point test and of the brute-force
    discrete Hessian (n = 40 segments, O(h^2)) agree, as do the indices on either side."""
    rod = helixrod.Rod(1.0, 1.6, 0.9, K13=0.2, uhat=(0.0, 0.0, 0.5))
    K, uhat = np.asarray(rod.K), np.asarray(rod.uhat)
    start = tuple(np.asarray(a) for a in helixrod.unloaded_state(rod, 0.0))  # the canonical placement
    end_frame = np.asarray(helixrod.unloaded_state(rod, L)[1])
    n = 40
    mid = (np.arange(n) + 0.5) * (L / n)

    def discrete(P):
        end = helixrod.Tweezer(end_frame, (0.0, 0.0, -P))
        sol = helixrod.solve_boundary_value(rod, L, end=end, guess="helix", saveat=mid)
        force = np.array([0.0, 0.0, -P])
        frames, _, _ = equilibrium(K, uhat, L, n, "tweezer", *start, end_frame=end_frame, force=force, frames_guess=np.asarray(sol.frame))
        return hessian_eigenvalues(K, uhat, L, n, "tweezer", frames, *start, end_frame=end_frame, force=force)

    ours = critical(lambda P: margin(rod, helixrod.Tweezer(end_frame, (0.0, 0.0, -P))), 8.0, 12.0)
    theirs = critical(lambda P: discrete(P)[0], 8.0, 12.0)
    assert ours == pytest.approx(theirs, rel=2e-3)
    for P in (0.9 * ours, 1.1 * ours, 1.5 * ours):
        end = helixrod.Tweezer(end_frame, (0.0, 0.0, -P))
        sol = helixrod.solve_boundary_value(rod, L, end=end, guess="helix", throw=False)
        assert int(sol.instability_index) == int(np.sum(discrete(P) < 0)), P


@pytest.mark.heavy
def test_wrong_branch_is_flagged_and_matches_the_discrete_index():
    """A cantilever under a large side load: the bulk guess alone lands on the branch bent
    back against the load; both tests call it unstable with two unstable directions, and
    the physical branch (the default) stable."""
    rod = helixrod.Rod(1.0, 1.0, 0.8)
    K, uhat = np.asarray(rod.K), np.asarray(rod.uhat)
    n, P = 40, 12.0
    force = np.array([P, 0.0, 0.0])
    for guess, index, tip_x in (("helix", 2, -0.47), (None, 0, 0.83)):
        sol = helixrod.solve_boundary_value(rod, L, end=helixrod.Loaded(force), guess=guess, saveat=(np.arange(n) + 0.5) / n)
        assert int(sol.instability_index) == index
        assert float(sol.end_position[0]) == pytest.approx(tip_x, abs=0.01)
        frames, _, _ = equilibrium(K, uhat, L, n, "loaded", np.zeros(3), np.eye(3), force=force, frames_guess=np.asarray(sol.frame))
        assert centreline(frames, L, np.zeros(3))[-1][0] == pytest.approx(tip_x, abs=0.01)
        lam = hessian_eigenvalues(K, uhat, L, n, "loaded", frames, np.zeros(3), np.eye(3), force=force)
        assert int(np.sum(lam < 0)) == index


def _elastica_tip(load):
    """Tip (x, z) of a clamped cantilever of unit length and stiffness, straight along z,
    under a dead load `load` along x.  With $\\psi$ the angle of the tangent from z,
    $\\psi'' = -P\\cos\\psi$, $\\psi(0) = 0$, $\\psi'(1) = 0$; its first integral
    $\\psi'^2 = 2P(\\sigma_1 - \\sin\\psi)$, $\\sigma_1 = \\sin\\psi(1)$, and
    $\\sin\\psi = \\sigma_1(1 - t^2)$ give the smooth integrals
    $1 = c\\int_0^1 dt/w$, $x = c\\int_0^1 \\sigma_1(1 - t^2)\\,dt/w$, $z = c$, with
    $c = \\sqrt{2\\sigma_1/P}$ and $w = \\sqrt{1 - \\sigma_1^2(1 - t^2)^2}$."""
    P = float(load)

    def integral(f, sigma):
        w = lambda t: np.sqrt(1 - sigma**2 * (1 - t**2) ** 2)  # noqa: E731
        with warnings.catch_warnings():
            # At the bracket's end (sigma -> 1) 1/w grows like 1/t and quad runs out of
            # subdivisions; there only the sign of the integral - 1 matters (it is large).
            if sigma > 1 - 1e-6:
                warnings.simplefilter("ignore", scipy.integrate.IntegrationWarning)
            value = scipy.integrate.quad(lambda t: f(sigma, t) / w(t), 0.0, 1.0, epsabs=1e-13, epsrel=1e-13, limit=200)[0]
        return np.sqrt(2 * sigma / P) * value

    sigma = scipy.optimize.brentq(lambda q: integral(lambda q, t: 1.0, q) - 1.0, 1e-12, 1 - 1e-15, xtol=1e-16)
    return integral(lambda q, t: q * (1 - t**2), sigma), np.sqrt(2 * sigma / P)


@pytest.mark.slow
def test_large_deflection_cantilever_from_the_defaults():
    """Side loads P L^2 / B from 0.5 to 20 from the default settings: every solve ok, stable
    and on the physical branch (the elliptic-integral tip).  (The bulk guess alone fails at
    7 of 40 loads and lands on the bent-back branch at 16.)"""
    rod = helixrod.Rod(1.0, 1.0, 0.8)
    for P in np.linspace(0.5, 20.0, 40):
        sol = helixrod.solve_boundary_value(rod, L, end=helixrod.Loaded((P, 0.0, 0.0)))
        assert bool(sol.stable), P
        x, z = _elastica_tip(P)
        assert np.allclose(np.asarray(sol.end_position), [x, 0.0, z], atol=1e-8), P


@pytest.mark.heavy
def test_cantilever_where_the_bulk_guess_fails():
    rod = helixrod.Rod(1.0, 1.0, 0.8)
    for P in (7.0, 14.0):
        direct = helixrod.solve_boundary_value(rod, L, end=helixrod.Loaded((P, 0.0, 0.0)), guess="helix", throw=False)
        sol = helixrod.solve_boundary_value(rod, L, end=helixrod.Loaded((P, 0.0, 0.0)))
        assert not (bool(direct.ok) and bool(direct.stable))
        assert bool(sol.stable) and sol.continuation > 0
        x, z = _elastica_tip(P)
        assert np.allclose(np.asarray(sol.end_position), [x, 0.0, z], atol=1e-8)


def test_undefined_stability_is_flagged():
    rod = helixrod.Rod(1.0, 1.0, 0.8)
    # A dead end moment is not conservative: no second variation to test.
    sol = helixrod.solve_boundary_value(rod, L, end=helixrod.Loaded(moment=(0.1, 0.0, 0.0)))
    assert bool(sol.ok) and int(sol.instability_index) == -1 and np.isnan(float(sol.stability_margin))
    assert not bool(sol.stable)
    off = helixrod.solve_boundary_value(rod, L, end=helixrod.Loaded(force=(0.1, 0.0, 0.0)), stability_pieces=0)
    assert bool(off.ok) and int(off.instability_index) == -1


def clamped_elastica(h):
    """(compressive force P, clamp moment) of the first buckled mode between parallel
    clamps at chord `h` (module docstring), B = 1: the clamp moment is
    $B\\theta'(0) = 2\\sqrt{m P B}$ (the pendulum's energy at $\\theta = 0$)."""
    m = scipy.optimize.brentq(lambda m: 2 * scipy.special.ellipe(m) / scipy.special.ellipk(m) - 1 - h / L, 0, 1 - 1e-15)
    P = (4 * scipy.special.ellipk(m) / L) ** 2
    return P, 2 * np.sqrt(m * P)


@pytest.mark.heavy
def test_clamped_ends_brought_together_buckle_by_default_and_turn():
    """Every built-in guess keeps the rod straight, which cannot shorten; the default now
    buckles it into its first mode (in its softer plane), exact against the elliptic
    integrals; a rotation curve at that end-shortening runs from it with `guess=`."""
    rod = helixrod.Rod(1.0, 1.3, 0.8)
    sol = helixrod.solve_boundary_value(rod, L, end=helixrod.Clamped((0.0, 0.0, 0.8)), saveat=np.linspace(0, L, 41))
    assert bool(sol.stable)
    assert -float(sol.force[2]) == pytest.approx(clamped_elastica(0.8)[0], rel=1e-8)
    assert np.max(np.abs(np.asarray(sol.x)[:, 1])) > 0.1 and np.max(np.abs(np.asarray(sol.x)[:, 0])) < 1e-8
    curve = helixrod.rotation_response(rod, L, np.linspace(0.0, 1.0, 5), extension=0.8, guess=sol)
    assert np.all(np.asarray(curve.ok)) and np.all(np.asarray(curve.stable))
    assert float(curve.moment[0]) == pytest.approx(0.0, abs=1e-8) and np.all(np.diff(np.asarray(curve.moment)) > 0)


def test_unstable_planar_elastica_is_left_for_a_stable_state():
    """An isotropic rod (twist softer than bending) brought to 0.4 L between clamps: the planar
    first mode is an equilibrium with an unstable direction (and a neutral one: it can turn
    about its chord while twisting back); the default solve leaves it for a stable state."""
    rod = helixrod.Rod(1.0, 1.0, 0.8)
    end = helixrod.Clamped((0.0, 0.0, 0.4))
    P, moment = clamped_elastica(0.4)
    planar = helixrod.solve_boundary_value(rod, L, end=end, guess=((0.0, 0.0, -P), (moment, 0.0, 0.0)), throw=False)
    assert bool(planar.ok) and int(planar.instability_index) >= 1
    found = helixrod.solve_boundary_value(rod, L, end=end)
    assert bool(found.stable) and abs(-float(found.force[2]) - P) > 1e-3 * P


def test_condensed_is_a_schur_complement_that_keeps_the_inertia():
    """`condensed` (the elimination of a chain's inner node) against numpy: the Schur
    complement of the node's block in the assembled (a, c, d) matrix, and Haynsworth's
    inertia additivity -- the negative eigenvalues of the whole equal those of the node's
    block plus those of the result -- on random symmetric blocks of mixed inertia."""
    from helixrod._bvp._stability import condensed

    rng = np.random.default_rng(7)
    for shift in (-3.0, 0.0, 3.0):
        S, P = (a + a.T + shift * np.eye(12) for a in rng.normal(size=(2, 12, 12)))
        whole = np.zeros((18, 18))
        whole[:12, :12] += S
        whole[6:, 6:] += P
        order = [*range(6), *range(12, 18), *range(6, 12)]  # (a, d, c)
        whole = whole[np.ix_(order, order)]
        pivot = whole[12:, 12:]
        expected = whole[:12, :12] - whole[:12, 12:] @ np.linalg.solve(pivot, whole[12:, :12])
        result, negatives = condensed(jnp.asarray(S), jnp.asarray(P))
        np.testing.assert_allclose(result, expected, rtol=1e-10, atol=1e-10)
        assert int(negatives) == int(np.sum(np.linalg.eigvalsh(pivot) < 0))
        assert int(np.sum(np.linalg.eigvalsh(whole) < 0)) == int(negatives) + int(np.sum(np.linalg.eigvalsh(expected) < 0))


@pytest.mark.heavy
def test_chains_of_sub_pieces_resolve_what_more_pieces_did():
    """The 3-turn spring pulled to F = 0.31 (past its critical force, on the branch the
    curve follows: index 8) needs up to 5 sub-pieces in each of the 16 pieces of the test.
    Before, 16 and 32 pieces did not resolve it (index -1) and 64, 128, 256 gave 8: the
    chained test gives 8 on 16 pieces too (the curve's test); its margins are those of the coarser
    pieces (-297 on 16, -276 on 64, -275.5 on 256: the metric's discretisation; further from
    stability they part more, -309 on 16 against -502 on 128 at F = 0.5).  Its margin is that
    of the exact 16-piece Hessian (the inner nodes eliminated exactly): with twice the
    sub-pieces it moves by the integration's error only."""
    import jax
    import jax.numpy as jnp

    from helixrod._bvp import _stability
    from helixrod._bvp._solve import stability_inputs

    spring = helixrod.Rod(1.0, 1.0, 1 / 1.3, uhat=(0.0, 1.0, 0.3))
    length = 3 * 2 * np.pi / np.hypot(1.0, 0.3)
    curve = helixrod.force_extension(spring, length, np.linspace(0.01, 0.31, 11))
    assert bool(jnp.all(curve.ok)) and int(curve.instability_index[-1]) == 8 and int(curve.instability_index[0]) == 0
    last = jax.tree.map(lambda a: a[-1], curve.solutions)
    start, end = helixrod.axial_ends(spring, length, force=0.31, moment=0.0)
    tested = {}
    for pieces in (64, 256):  # (a single solve tests on at least the pieces its wrench asks: 64)
        single = helixrod.solve_boundary_value(spring, length, start=start, end=end, guess=last, stability_pieces=pieces)
        assert single.stability_pieces == pieces
        tested[pieces] = (int(single.instability_index), float(single.stability_margin))
    assert all(index == 8 for index, _ in tested.values()), tested
    assert tested[64][1] == pytest.approx(tested[256][1], rel=0.01)
    # At the default 16 pieces the chains fix the index, and the solve tests it again on the
    # pieces its wrench asks for the margin and direction of its mode.
    default = helixrod.solve_boundary_value(spring, length, start=start, end=end, guess=last)
    assert default.stability_pieces == 64 and int(default.instability_index) == 8
    assert float(default.stability_margin) == pytest.approx(tested[64][1], rel=1e-9)

    options = helixrod.BoundaryValueOptions()
    N, M0, xs, frames = stability_inputs(last)[:4]
    condition = type(end).condition(end)

    def test():  # traced afresh at each call
        return jax.jit(lambda: _stability.stability(spring, length, condition, N, M0, xs, frames, options)[:2])()

    index, margin = test()
    assert int(index) == 8 and float(margin) == pytest.approx(tested[256][1], rel=0.1)
    assert int(curve.instability_index[-1]) == 8 and float(curve.stability_margin[-1]) == pytest.approx(float(margin), rel=1e-6)
    needed = _stability.sub_pieces_needed
    try:
        _stability.sub_pieces_needed = lambda *args: 2 * needed(*args)
        doubled = test()
    finally:
        _stability.sub_pieces_needed = needed
    assert int(doubled[0]) == 8
    assert float(doubled[1]) == pytest.approx(float(margin), rel=1e-6)
