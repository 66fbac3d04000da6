"""helixrod._lie: rotations against scipy.spatial.transform.Rotation (independent of the
package), and the convergence order of the Lie-group integrators on the Kirchhoff
equations (log-log slope against a fine solution)."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import KIRCHHOFF_ROD, M1, N1, ROT1, solve_fixed
from scipy.spatial.transform import Rotation

import helixrod as hr
from helixrod._lie import gibbs, hat, rotation_vector, rotation_z, so3_exp, twist_angle, unwrap_near


def random_rotation_vectors(rng, n, max_angle=np.pi):
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return axes * rng.uniform(0.0, max_angle, n)[:, None]


def test_so3_exp_matches_scipy(rng):
    w = random_rotation_vectors(rng, 200, max_angle=3 * np.pi)  # |w| > pi too
    small = random_rotation_vectors(rng, 20, max_angle=1e-2) * np.logspace(-12, 0, 20)[:, None]  # the series
    w = np.concatenate([w, small, np.zeros((1, 3))])
    R = np.asarray(hr.so3_exp(jnp.asarray(w)))
    np.testing.assert_allclose(R, Rotation.from_rotvec(w).as_matrix(), rtol=0, atol=2e-15)
    np.testing.assert_allclose(np.einsum("nji,njk->nik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=2e-15)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    # Differentiable at w = 0: d exp(hat w)/dw_i = hat(e_i), the generators.
    J = np.asarray(jax.jacfwd(hr.so3_exp)(jnp.zeros(3)))
    np.testing.assert_allclose(np.moveaxis(J, -1, 0), np.asarray(hat(jnp.eye(3))), atol=1e-15)


def test_gibbs_and_rotation_vector_match_scipy(rng):
    w = random_rotation_vectors(rng, 200, max_angle=np.pi - 1e-2)
    R = Rotation.from_rotvec(w)
    q = R.as_quat()  # (x, y, z, w), w >= 0 for angles < pi
    np.testing.assert_allclose(gibbs(jnp.asarray(R.as_matrix())), q[:, :3] / q[:, 3:], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(rotation_vector(jnp.asarray(R.as_matrix())), R.as_rotvec(), rtol=1e-12, atol=1e-15)
    # The identity, and rotations within rounding of it.
    eye = jnp.eye(3)
    np.testing.assert_array_equal(gibbs(eye), np.zeros(3))
    np.testing.assert_array_equal(rotation_vector(eye), np.zeros(3))
    tiny = np.array([[1e-13, -2e-13, 3e-13]])
    np.testing.assert_allclose(rotation_vector(jnp.asarray(Rotation.from_rotvec(tiny).as_matrix())), tiny, rtol=1e-3, atol=1e-28)


def test_rotation_vector_near_a_half_turn(rng):
    """Angles within 1e-2 ... 1e-4 of pi (0 <= theta < pi: the vector's direction flips at
    pi, so compare the rotations it represents, and the angle)."""
    axes = random_rotation_vectors(rng, 30, max_angle=1.0)
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    for gap in (1e-2, 1e-3, 1e-4):
        R = Rotation.from_rotvec(axes * (np.pi - gap)).as_matrix()
        v = np.array(rotation_vector(jnp.asarray(R)))  # a writable copy for scipy
        np.testing.assert_allclose(np.linalg.norm(v, axis=1), np.pi - gap, rtol=0, atol=1e-9)
        np.testing.assert_allclose(Rotation.from_rotvec(v).as_matrix(), R, rtol=0, atol=1e-9)
        np.testing.assert_allclose(np.asarray(hr.so3_exp(jnp.asarray(v))), R, rtol=0, atol=1e-9)


def test_rotation_z_and_twist_angle_match_scipy(rng):
    angle = rng.uniform(-3 * np.pi, 3 * np.pi, 100)
    np.testing.assert_allclose(rotation_z(jnp.asarray(angle)), Rotation.from_euler("z", angle[:, None]).as_matrix(), atol=2e-15)
    # Swing-twist: a turn by a about e_z composed with a swing about an axis normal to e_z
    # (either order) has twist a, wrapped to (-pi, pi].
    a = rng.uniform(-np.pi + 1e-6, np.pi, 100)
    swing = np.concatenate([rng.normal(scale=0.8, size=(100, 2)), np.zeros((100, 1))], 1)
    S, Z = Rotation.from_rotvec(swing), Rotation.from_euler("z", a[:, None])
    for R in (S * Z, Z * S):
        np.testing.assert_allclose(twist_angle(jnp.asarray(R.as_matrix())), a, rtol=0, atol=1e-12)
    # General rotations: 2 atan2(q_z, q_w) of scipy's unit quaternion.
    R = Rotation.from_rotvec(random_rotation_vectors(rng, 100))
    q = R.as_quat()
    expected = np.angle(np.exp(2j * np.arctan2(q[:, 2], q[:, 3])))
    np.testing.assert_allclose(twist_angle(jnp.asarray(R.as_matrix())), expected, rtol=0, atol=1e-12)
    assert float(twist_angle(rotation_z(np.pi))) == pytest.approx(np.pi, abs=1e-15)  # (-pi, pi]


def test_unwrap_near(rng):
    angle = rng.uniform(-10.0, 10.0, 200)
    hint = rng.uniform(-50.0, 50.0, 200)
    out = np.asarray(unwrap_near(angle, hint))
    turns = (out - angle) / (2 * np.pi)
    np.testing.assert_allclose(turns, np.round(turns), atol=1e-12)  # whole turns added
    assert np.all(np.abs(out - hint) <= np.pi + 1e-12)  # the nearest to the hint
    np.testing.assert_allclose(out, hint + np.angle(np.exp(1j * (angle - hint))), atol=1e-12)


@pytest.mark.parametrize(
    "solver, counts, order",
    [
        (hr.CommutatorFreeRK4(), [16, 32, 64, 128], 4),
        # Its 13 unrolled stages take ~40 s to compile on 2 busy cores.
        pytest.param(hr.MuntheKaasRK(diffrax.Dopri8()), [6, 9, 13, 18], 8, marks=pytest.mark.slow),
    ],
)
def test_convergence_order(solver, counts, order):
    length = 4.0
    ref = solve_fixed(N1, M1, ROT1, jnp.zeros(3), length, jnp.asarray(1024), solver)
    errors = []
    for count in counts:
        sol = solve_fixed(N1, M1, ROT1, jnp.zeros(3), length, jnp.asarray(count), solver)
        errors.append(max(float(jnp.abs(sol.x - ref.x).max()), float(jnp.abs(sol.frame - ref.frame).max())))
    slope = -np.polyfit(np.log(counts), np.log(errors), 1)[0]
    assert order - 0.4 < slope < order + 1.0, (slope, errors)


def _scipy_state(length):
    """The state at arc length `length` from (N1, M1, ROT1, 0) by scipy's DOP853 at
    2.5e-14 (its floor is 100 eps: it raised a smaller rtol to that with a warning; an
    independent right-hand side: tests/test_kirchhoff.py's)."""
    from test_kirchhoff import scipy_reference

    n, m, D, x = scipy_reference(KIRCHHOFF_ROD, N1, M1, ROT1, np.zeros(3), np.array([0.0, length]), rtol=2.5e-14)
    return n[-1], m[-1], D[-1], x[-1]


@pytest.mark.parametrize(
    "solver, steps, slope",
    [(hr.CommutatorFreeRK4(), [0.4, 0.2, 0.1, 0.05], 4), (hr.MuntheKaasRK(diffrax.Dopri8()), [0.8, 0.6, 0.45, 0.34], 6)],
)
def test_dense_output_order(solver, steps, slope):
    """The continuous extension of one step (`LieGroupInterpolation`) inside the step, at
    r = 0.37, against scipy: its local error falls as h^4 for CF4 (an order-3 extension)
    and as h^6 for Munthe-Kaas on Dopri8 (diffrax's Dopri8 interpolation, of the same order
    on a plain ODE).  At r = 1 it meets the step's own end: to O(h^5) for CF4 (the two
    exponentials of the step against one), to round-off for Munthe-Kaas."""
    from helixrod._kirchhoff import _body_velocity
    from helixrod._lie import BodyVelocityTerm, LieGroupInterpolation, RodState

    term = BodyVelocityTerm(_body_velocity)
    y0 = RodState(jnp.asarray(N1), jnp.asarray(M1), jnp.asarray(ROT1), jnp.zeros(3))

    @jax.jit
    def dense(h, r):
        state = solver.init(term, 0.0, h, y0, KIRCHHOFF_ROD)
        y1, _, info, _, _ = solver.step(term, 0.0, h, y0, KIRCHHOFF_ROD, state, True)
        return LieGroupInterpolation(t0=jnp.zeros_like(h), t1=h, **info).evaluate(r * h), y1

    errors, gaps = [], []
    for h in steps:
        y, _ = dense(jnp.asarray(h), 0.37)
        n, m, D, x = _scipy_state(0.37 * h)
        errors.append(max(np.abs(y.n - n).max(), np.abs(y.m - m).max(), np.abs(y.frame - D).max(), np.abs(y.x - x).max()))
        end, y1 = dense(jnp.asarray(h), 1.0)
        gaps.append(max(float(jnp.abs(end.frame - y1.frame).max()), float(jnp.abs(end.x - y1.x).max())))
        gram = jnp.einsum("ji,jk->ik", y.frame, y.frame) - jnp.eye(3)
        assert float(jnp.abs(gram).max()) < 1e-14
        # The group action conserves |n|^2 and m.n exactly: the interpolant does too.
        np.testing.assert_allclose([y.n @ y.n, y.m @ y.n], [N1 @ N1, M1 @ N1], rtol=1e-13)
    fitted = np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert slope - 0.3 < fitted < slope + 0.6, (fitted, errors)
    if slope == 4:
        assert np.polyfit(np.log(steps), np.log(gaps), 1)[0] > 4.5, gaps
    else:
        assert max(gaps) < 1e-13, gaps


def test_saved_points_exact_on_a_helix_between_steps():
    """Saved points between steps are exact on a uniform helix (the twist is constant):
    three fixed CF4 steps over two turns, saved at 40 points, give the closed-form frame and
    centreline; a solver without a continuous extension refuses fixed steps with saves."""
    from helpers import FRAME0, KIRCHHOFF_EQ, M0, N0, X0

    kappa, tau = 1.0, 0.5
    length = 2 * 2 * np.pi / np.hypot(kappa, tau)
    s = jnp.linspace(0.0, length, 40)
    sol = hr.solve_static(KIRCHHOFF_ROD, N0, M0, length, frame0=FRAME0, x0=X0, saveat=s, steps=3,
                          outputs=("frame", "centreline"), solver=hr.CommutatorFreeRK4())
    np.testing.assert_allclose(sol.frame, hr.helix_frame(kappa, tau, KIRCHHOFF_EQ.phi[0], s), rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol.x, hr.helix_centreline(kappa, tau, s), rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol.n, jnp.broadcast_to(N0, sol.n.shape), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="no continuous extension"):
        hr.solve_static(KIRCHHOFF_ROD, N0, M0, length, saveat=s, steps=3, solver=hr.MuntheKaasRK(diffrax.Tsit5()))


def test_twist_angle_holds_its_accuracy_near_half_a_turn():
    """The twist of a frame half a turn about the axis, with a swing and the off-orthogonal
    round-off of an integrated frame (1e-10): the quaternion form of the entries lost it
    (2 atan2(R10 - R01, 1 + tr R) divides two quantities of order q_w^2), measured on a
    spring's end frame 0.019 rad off; the split by the swung e_x keeps it to that round-off."""
    rng = np.random.default_rng(3)
    for twist in (np.pi - 1e-8, np.pi + 1e-8, np.pi / 3):
        exact = so3_exp(jnp.array([0.02, -0.01, 0.0])) @ rotation_z(twist)  # swing after twist
        frame = exact + 1e-10 * rng.normal(size=(3, 3))
        expected = twist - 2 * np.pi * np.round(twist / (2 * np.pi))
        got = float(twist_angle(frame))
        assert abs((got - expected + np.pi) % (2 * np.pi) - np.pi) < 1e-8
