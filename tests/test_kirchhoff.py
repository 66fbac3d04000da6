"""Static Kirchhoff equations (solve_static, first integrals, wrench_growth_rate): helices
stay helices, conservation, scipy, gradients, the linearised wrench flow against numpy.
The exact helix frame is tested in tests/test_geometry.py, the integrators' order in
tests/test_lie.py."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    FRAME0, KIRCHHOFF_EQ, KIRCHHOFF_ROD, M0, M1, N0, N1, ROT1, SPRING, SPRING_TURN, X0, solve_fixed, tree_allclose,
)
from scipy.integrate import solve_ivp

import helixrod as hr
from helixrod import _trace_cache

ROD, EQ = KIRCHHOFF_ROD, KIRCHHOFF_EQ
KAPPA, TAU, PHI = 1.0, 0.5, EQ.phi[0]
TURN = 2 * np.pi / np.hypot(KAPPA, TAU)
LENGTH1 = 12.0


def scipy_reference(rod, n0, m0, frame0, x0, ts, rtol=1e-13):
    """Independent numpy right-hand side: n, m, D (9, row-major), x; DOP853."""
    K = np.asarray(rod.K)
    uhat = np.asarray(rod.uhat)

    def rhs(s, y):
        n, m, D = y[:3], y[3:6], y[6:15].reshape(3, 3)
        u = uhat + np.linalg.solve(K, m)
        dn = -np.cross(u, n)
        dm = -np.cross(u, m) - np.cross([0.0, 0.0, 1.0], n)
        dD = np.stack([np.cross(D @ u, D[:, i]) for i in range(3)], axis=1)  # d_i' = (D u) x d_i
        return np.concatenate([dn, dm, dD.ravel(), D[:, 2]])

    y0 = np.concatenate([n0, m0, np.asarray(frame0).ravel(), x0])
    out = solve_ivp(rhs, (0.0, ts[-1]), y0, method="DOP853", rtol=rtol, atol=rtol, t_eval=ts)
    y = out.y.T
    return y[:, :3], y[:, 3:6], y[:, 6:15].reshape(-1, 3, 3), y[:, 15:]


@jax.jit
def solve_full(n0, m0, frame0, x0, length, saveat, tol):
    """Adaptive geometric solve; everything traced, so the tests share one compilation."""
    return hr.solve_static(
        ROD, n0, m0, length, frame0=frame0, x0=x0, saveat=saveat, outputs=("frame", "centreline"), rtol=tol, atol=tol
    )


def test_helix_stays_a_helix_over_100_turns():
    length = 100 * TURN
    s = jnp.linspace(0.0, length, 5)
    sol = solve_full(N0, M0, FRAME0, X0, length, s, 1e-8)
    assert bool(sol.ok)
    np.testing.assert_allclose(sol.n, jnp.broadcast_to(N0, sol.n.shape), rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol.m, jnp.broadcast_to(M0, sol.m.shape), rtol=0, atol=1e-12)
    exact_frame = hr.helix_frame(KAPPA, TAU, PHI, s)
    exact_x = hr.helix_centreline(KAPPA, TAU, s)
    np.testing.assert_allclose(sol.frame, exact_frame, rtol=0, atol=1e-10)
    np.testing.assert_allclose(sol.x, exact_x, rtol=0, atol=1e-9)
    gram = jnp.einsum("kji,kjl->kil", sol.frame, sol.frame) - jnp.eye(3)[None]
    assert float(jnp.abs(gram).max()) < 1e-13
    assert float(jnp.abs(sol.drift).max()) < 1e-12


def test_highly_twisted_helix_within_max_steps():
    """kappa = 1, tau = 100, slot 1 (spatially stable).  The wrench Jacobian J is far from
    normal there (|J|_F / rho(J) ~ 1.6e3): the former step cap 2/|J|_F alone needed ~5.7e5
    steps for 10 turns and hit max_steps; with the spectral cap 0.5/rho it takes ~1.7e3."""
    eq = hr.helix_equilibria(ROD, 1.0, 100.0)
    n0, m0, frame0, x0 = (a[1] for a in hr.helix_initial_conditions(eq))
    length = 10 * 2 * np.pi / np.hypot(1.0, 100.0)
    s = jnp.linspace(0.0, length, 5)
    sol = solve_full(n0, m0, frame0, x0, length, s, 1e-8)
    assert bool(sol.ok) and int(sol.num_steps) < 5000
    np.testing.assert_allclose(sol.frame, hr.helix_frame(1.0, 100.0, eq.phi[1], s), rtol=0, atol=1e-10)
    np.testing.assert_allclose(sol.x, hr.helix_centreline(1.0, 100.0, s), rtol=0, atol=1e-12)


def test_helix_exact_with_fixed_steps():
    # Exact for constant u at any step within the stability bound: 60 steps for 10 turns
    # (h |u| ~ 1).  Round-off on the neutral modes grows polynomially, hence 1e-12.
    length = 10 * TURN
    sol = solve_fixed(N0, M0, FRAME0, X0, length, jnp.asarray(60))
    np.testing.assert_allclose(sol.frame[0], hr.helix_frame(KAPPA, TAU, PHI, length), rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol.x[0], hr.helix_centreline(KAPPA, TAU, length), rtol=0, atol=1e-11)


def test_agrees_with_scipy_and_conserves_integrals():
    ts = np.linspace(0.0, LENGTH1, 5)
    sol = solve_full(N1, M1, ROT1, jnp.ones(3), LENGTH1, ts, 1e-11)
    n, m, D, x = scipy_reference(ROD, N1, M1, ROT1, np.ones(3), ts)
    assert float(jnp.abs(sol.n - N1[None]).max()) > 0.1  # genuinely non-helical
    for ours, ref in ((sol.n, n), (sol.m, m), (sol.frame, D), (sol.x, x)):
        np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-8)
    # |n|^2 and m.n are conserved by construction, H to the tolerance.
    assert float(jnp.abs(sol.drift[:, :2]).max()) < 1e-12
    assert float(jnp.abs(sol.drift[:, 2]).max()) < 1e-9
    # The lab force is constant and the lab moment obeys M' = -d3 x N.
    N, M = sol.lab_wrench()
    np.testing.assert_allclose(N, jnp.broadcast_to(N[0], N.shape), atol=1e-12)
    np.testing.assert_allclose(M, M[0][None] - jnp.cross(sol.x - sol.x[0][None], N[0][None]), atol=1e-9)


def test_standard_solver_agrees():
    ts = np.array([0.0, LENGTH1 / 2, LENGTH1])
    sol = hr.solve_static(
        ROD, N1, M1, LENGTH1, frame0=ROT1, saveat=ts, outputs=("frame", "centreline"),
        solver=diffrax.Tsit5(), rtol=1e-10, atol=1e-10,
    )
    n, m, D, x = scipy_reference(ROD, N1, M1, ROT1, np.zeros(3), ts)
    np.testing.assert_allclose(sol.frame, D, atol=1e-7)
    np.testing.assert_allclose(sol.x, x, atol=1e-7)
    np.testing.assert_allclose(sol.m, m, atol=1e-7)


def test_wrench_only_integrates_six_components():
    sol = hr.solve_static(ROD, N1, M1, 3.0, rtol=1e-10, atol=1e-10)
    assert sol.frame is None and sol.x is None
    assert sol.n.shape == (1, 3) and sol.s.shape == (1,)
    full = solve_full(N1, M1, ROT1, jnp.zeros(3), 3.0, jnp.linspace(0.0, 3.0, 5), 1e-10)
    np.testing.assert_allclose(sol.m[0], full.m[-1], atol=1e-9)
    np.testing.assert_allclose(sol.n[0], full.n[-1], atol=1e-9)


@jax.jit
def _tip(m0, length):
    sol = hr.solve_static(ROD, N1, m0, length, outputs="centreline", rtol=1e-12, atol=1e-12)
    assert sol.frame is None  # the frame is integrated for x, not stored
    return sol.x[-1]


@pytest.mark.slow  # reverse- and forward-mode compilation of the solve: ~1 min on 2 busy cores
def test_gradients_match_central_differences():
    m0, length = M1, jnp.asarray(3.0)
    jac_rev = jax.jacrev(_tip, argnums=(0, 1))(m0, length)
    tip_fwd = lambda m, l: hr.solve_static(  # noqa: E731
        ROD, N1, m, l, outputs="centreline", rtol=1e-12, atol=1e-12, adjoint=diffrax.ForwardMode()
    ).x[-1]
    jac_fwd = jax.jacfwd(tip_fwd, argnums=(0, 1))(m0, length)
    h = 1e-5
    fd_m = np.stack([(_tip(m0 + h * e, length) - _tip(m0 - h * e, length)) / (2 * h) for e in np.eye(3)], -1)
    fd_l = (_tip(m0, length + h) - _tip(m0, length - h)) / (2 * h)
    for jac in (jac_rev, jac_fwd):
        np.testing.assert_allclose(jac[0], fd_m, atol=1e-6)
        np.testing.assert_allclose(jac[1], fd_l, atol=1e-6)


def _saved_state(params, adjoint=None, tol=1e-12):
    """The saved frame, centreline and wrench of a solve as a function of every
    differentiable input: the rod's five stiffnesses and intrinsic twist, n0, m0, a rotation
    vector of frame0, x0, and the length, with the saved points at fixed fractions of it
    (so that they move with it)."""
    K, uhat, n0, m0, w, x0, length = (params[:5], params[5:8], params[8:11], params[11:14], params[14:17],
                                      params[17:20], params[20])
    rod = hr.Rod(*K, uhat=uhat)
    sol = hr.solve_static(
        rod, n0, m0, length, frame0=hr.so3_exp(w), x0=x0, saveat=length * jnp.array([0.3, 0.7, 1.0]),
        outputs=("frame", "centreline"), rtol=tol, atol=tol, adjoint=adjoint,
    )
    return jnp.concatenate([sol.n.ravel(), sol.m.ravel(), sol.frame.ravel(), sol.x.ravel()])


def test_default_derivatives_are_the_sensitivities_of_the_solution():
    """The default derivatives (forward sensitivity equations, `jax.jacrev` and
    `jax.jacfwd`) of every saved quantity with respect to all 21 inputs.  Expected: both
    modes agree to round-off with each other and, to the tolerance times the flow's growth,
    with fourth-order central differences of the solve at tolerance 1e-13 (relative to the
    largest entry)."""
    params = jnp.concatenate([
        jnp.array([1.0, 1.5, 0.8, 0.5, 0.5, 1.0, 0.0, 0.0]), N1, M1, jnp.array([0.3, -0.2, 0.5]),
        jnp.array([0.1, 0.2, -0.3]), jnp.array([3.0]),
    ])
    rev = jax.jit(jax.jacrev(_saved_state))(params)
    fwd = jax.jit(jax.jacfwd(_saved_state))(params)
    np.testing.assert_allclose(rev, fwd, rtol=0, atol=1e-12 * np.max(np.abs(fwd)))
    value = jax.jit(lambda p: _saved_state(p, tol=1e-13))
    h, basis = 2e-4, np.eye(params.size)
    fd = np.stack([
        (8 * (value(params + h * e) - value(params - h * e)) - (value(params + 2 * h * e) - value(params - 2 * h * e)))
        / (12 * h) for e in basis
    ], -1)
    scale = np.max(np.abs(fd))
    assert scale > 1.0
    np.testing.assert_allclose(rev, fd, rtol=0, atol=1e-8 * scale)


def test_default_second_derivatives_match_differences_of_the_gradient():
    """The Hessian `jax.jacfwd(jax.grad(f))` of a scalar of the end state with respect to a
    stiffness, n0 and the length: the forward-over-reverse derivative of the default
    sensitivity rule, which differentiates itself again.  Expected: central differences of
    `jax.grad(f)` (step 1e-5, solves at tolerance 1e-12) to 1e-6 of the largest entry."""

    def f(p):
        rod = hr.Rod(p[0], 1.5, 0.8, 0.5, 0.5, (1.0, 0.0, 0.0))
        sol = hr.solve_static(rod, p[1:4], M1, p[4], outputs="centreline", rtol=1e-12, atol=1e-12)
        return jnp.sum(sol.m[-1] ** 2) + jnp.sum(sol.x[-1] * jnp.array([0.3, -0.2, 0.5]))

    p = jnp.concatenate([jnp.array([1.0]), N1, jnp.array([2.5])])
    hessian = np.asarray(jax.jit(jax.jacfwd(jax.grad(f)))(p))
    gradient, h = jax.jit(jax.grad(f)), 1e-5
    fd = np.stack([(gradient(p + h * e) - gradient(p - h * e)) / (2 * h) for e in np.eye(p.size)], -1)
    scale = np.max(np.abs(fd))
    assert scale > 1.0
    np.testing.assert_allclose(hessian, fd, rtol=0, atol=1e-6 * scale)
    np.testing.assert_allclose(hessian, hessian.T, rtol=0, atol=1e-9 * scale)


def test_an_eager_gradient_runs_the_flow_as_a_program_of_its_own(exported_programs):
    """An eager `jax.grad` (no caller's `jit`): the flow, which is not differentiated, runs
    as a top-level program (`_kirchhoff._flow_of`), which the trace cache exports so that a
    later process calls it without tracing; only the sensitivities are traced.  Expected:
    one exported program, and the gradient of `jax.jit(jax.grad(...))` to round-off."""
    end_moment = lambda n0: jnp.sum(hr.solve_static(ROD, n0, M1, 2.0).m[-1] ** 2)  # noqa: E731
    exported = _trace_cache.counts["exported"]
    eager = jax.grad(end_moment)(N1)
    assert _trace_cache.counts["exported"] == exported + 1
    assert len(list(exported_programs.glob("*.export"))) == 1
    np.testing.assert_allclose(eager, jax.jit(jax.grad(end_moment))(N1), rtol=1e-13, atol=0)


def test_default_gradient_under_vmap_flags_a_bad_point():
    """`jax.vmap(jax.grad(...))` of an end moment over three n0, the middle one NaN.
    Expected: the bad point is flagged (`valid_input=False`) and the good points' gradients
    are finite and equal their unbatched ones (to 1e-10: vectorised arithmetic rounds
    differently)."""

    def end_moment(n0):
        sol = hr.solve_static(ROD, n0, M1, 2.0, throw=False)
        return jnp.sum(sol.m[-1] ** 2), sol.valid_input

    batch = jnp.stack([N1, N1.at[0].set(jnp.nan), N0])
    grads, valid = jax.vmap(jax.grad(end_moment, has_aux=True))(batch)
    np.testing.assert_array_equal(valid, [True, False, True])
    for i in (0, 2):
        single = jax.grad(lambda n: end_moment(n)[0])(batch[i])
        np.testing.assert_allclose(grads[i], single, rtol=1e-10, atol=1e-12)
        assert np.all(np.isfinite(np.asarray(grads[i])))


@jax.jit
def _solve_flagged(n0, length):
    return hr.solve_static(ROD, n0, M1, length, outputs="frame", throw=False)


def test_vmap_equals_loop_and_flags_bad_points():
    scales = jnp.array([0.0, 0.5, 1.0, 0.3, 0.7])
    batch_n = N0[None] + scales[:, None] * (N1 - N0)[None]
    batch_n = batch_n.at[3, 0].set(jnp.nan)
    lengths = jnp.array([2.0, 2.0, 2.0, 2.0, -1.0])
    batched = jax.vmap(_solve_flagged)(batch_n, lengths)
    np.testing.assert_array_equal(batched.valid_input, [True, True, True, False, False])
    np.testing.assert_array_equal(batched.ok, [True, True, True, False, False])
    assert bool(jnp.all(jnp.isnan(batched.m[3:])))
    for i in range(3):
        single = _solve_flagged(batch_n[i], lengths[i])
        np.testing.assert_allclose(batched.frame[i], single.frame, atol=1e-12)
        np.testing.assert_allclose(batched.m[i], single.m, atol=1e-12)
        tree_allclose(jax.tree.map(lambda a: a[i], batched), single, rtol=0, atol=1e-12)  # every field


def test_bad_input_is_an_error():
    with pytest.raises(ValueError, match="finite"):
        hr.solve_static(ROD, jnp.array([jnp.nan, 0, 0]), M1, 1.0)
    with pytest.raises(ValueError, match="length"):
        hr.solve_static(ROD, N1, M1, 0.0)
    with pytest.raises(ValueError, match="unknown output"):
        hr.solve_static(ROD, N1, M1, 1.0, outputs=("frames",))
    with pytest.raises(ValueError, match="shape"):
        hr.solve_static(ROD, N1[:2], M1, 1.0)
    with pytest.raises(ValueError, match="x0 must be finite"):
        hr.solve_static(ROD, N1, M1, 1.0, x0=[np.inf, 0.0, 0.0])
    for option, message in (
        ({"steps": 0}, "steps must be an integer >= 1"), ({"steps": 2.5}, "steps must be an integer >= 1"),
        ({"max_steps": -1}, "max_steps must be an integer >= 1"), ({"rtol": -1e-3}, "rtol must be finite and > 0"),
        ({"atol": np.nan}, "atol must be finite and > 0"), ({"outputs": None}, "outputs must be a name or a sequence"),
        ({"solver": "dopri8"}, "solver must be a diffrax solver"),
    ):
        with pytest.raises(ValueError, match=message):
            hr.solve_static(ROD, N1, M1, 1.0, **option)


def test_max_steps():
    with pytest.raises(Exception, match="max_steps"):
        hr.solve_static(ROD, N1, M1, LENGTH1, max_steps=3)
    sol = hr.solve_static(ROD, N1, M1, LENGTH1, max_steps=3, throw=False)
    assert sol.result == hr.RESULTS.max_steps_reached
    assert not bool(sol.ok)


def test_first_integrals_closed_form():
    n, m = jnp.array([0.3, -0.2, 1.1]), jnp.array([0.5, 0.4, -0.3])
    u = ROD.uhat + np.linalg.solve(np.asarray(ROD.K), m)
    W = 0.5 * (u - ROD.uhat) @ np.asarray(ROD.K) @ (u - ROD.uhat)
    np.testing.assert_allclose(hr.first_integrals(ROD, n, m), [n @ n, m @ n, u @ m - W + n[2]], rtol=1e-14)


def test_wrench_growth_rate_against_a_numpy_jacobian():
    """Eigenvalues of the linearised wrench flow by central differences of an independent
    numpy right-hand side; a stretched spring at fixed rotation is spatially unstable, a
    compressed one is not."""
    K_inv, uhat = np.linalg.inv(np.asarray(SPRING.K)), np.asarray(SPRING.uhat)

    def rhs(w):
        n, m = w[:3], w[3:]
        u = uhat + K_inv @ m
        return np.concatenate([-np.cross(u, n), -np.cross(u, m) - np.cross([0.0, 0.0, 1.0], n)])

    length = 2 * SPRING_TURN
    h0, theta0 = (float(a) for a in hr.unloaded_observables(SPRING, length))
    rates = []
    for ratio in (0.9, 1.1, 1.5):
        bulk = hr.bulk_helix(SPRING, length, extension=ratio * h0, rotation=theta0)
        n, m = np.asarray(bulk.mu2 * bulk.u), np.asarray(SPRING.moment(bulk.u))
        w = np.concatenate([n, m])
        eps = 1e-6
        J = np.stack([(rhs(w + eps * e) - rhs(w - eps * e)) / (2 * eps) for e in np.eye(6)], 1)
        expected = np.linalg.eigvals(J).real.max()
        rate = float(hr.wrench_growth_rate(SPRING, n, m))
        np.testing.assert_allclose(rate, expected, atol=1e-7)
        rates.append(rate)
    assert abs(rates[0]) < 1e-6 and rates[1] > 0.05 and rates[2] > rates[1]


def test_frame_must_be_a_rotation():
    rod = hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
    for frame in (2 * np.eye(3), np.diag([1.0, 1.0, -1.0])):
        with pytest.raises(ValueError, match="solve_static: frame must be a rotation"):
            hr.solve_static(rod, np.zeros(3), np.zeros(3), 1.0, frame0=frame)


def test_a_traced_start_frame_or_position_that_is_bad_flags_its_point():
    frames = jnp.stack([jnp.eye(3), 2 * jnp.eye(3), jnp.diag(jnp.array([1.0, 1.0, -1.0])), jnp.eye(3)])
    starts = jnp.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [jnp.nan, 0.0, 0.0]])
    sol = jax.vmap(lambda f, x: hr.solve_static(ROD, N1, M1, 2.0, frame0=f, x0=x, outputs=("frame", "centreline"), throw=False))(frames, starts)
    assert sol.valid_input.tolist() == [True, False, False, False] and sol.ok.tolist() == [True, False, False, False]
    assert bool(jnp.all(jnp.isnan(sol.x[1:]))) and (sol.result == hr.RESULTS.invalid_input).tolist() == [False, True, True, True]
    single = hr.solve_static(ROD, N1, M1, 2.0, outputs=("frame", "centreline"))
    np.testing.assert_allclose(sol.x[0], single.x, atol=1e-12)


def test_fixed_steps_too_long_for_the_solver_are_not_a_success():
    """Munthe-Kaas steps of ~13 rad on a helix: its dexp^-1 series diverges and the states
    are not finite; flagged `nonfinite`, not returned as a success."""
    length = 40.0
    sol = hr.solve_static(ROD, N0, M0, length, frame0=FRAME0, x0=X0, steps=3, outputs="centreline", throw=False)
    assert not bool(sol.ok) and bool(sol.result == hr.RESULTS.nonfinite)
