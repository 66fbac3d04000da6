"""Finite rods: boundary-value solves, response curves, fits through the integrator.

Independent references: the initial-value solver (`solve_static`), exact uniform helices
(`helix_frame`, `helix_centreline`, `helix_residual`), scipy `solve_bvp` on a numpy right-hand
side, central differences.  To keep the default run short, the solves share a few compiled
programs: every eager `solve_boundary_value` call below has 9 save points and a `(n0, m0)`
guess (one compilation for all end types), and the curve tests share one jitted function.
Fits (one compilation each, ~1 min) are marked slow.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_bvp

import helixrod as hr

# A coupled, anisotropic rod whose intrinsic shape is a helix with a generic register.
ROD = hr.Rod(1.0, 1.4, 0.8, K13=0.15, K23=-0.1, uhat=(0.3, 0.9, 0.35))
# A spring (isotropic wire, nu = 0.3) for the response curves.
SPRING = hr.Rod(1.0, 1.0, 1 / 1.3, uhat=(0.0, 1.0, 0.3))
SPRING_NORM = float(np.hypot(1.0, 0.3))
TURN = 2 * np.pi / SPRING_NORM
NSAVE = 9


def solve(rod, length, start, end, guess, **kw):
    """Eager solve with the shared configuration (9 save points, a wrench guess)."""
    return hr.solve_boundary_value(
        rod, length, start=start, end=end, guess=guess, saveat=jnp.linspace(0.0, length, NSAVE), **kw
    )


def ivp(rod, n0, m0, length, start, tol=1e-10):
    return hr.solve_static(
        rod, n0, m0, length, frame0=start.frame, x0=start.position, saveat=jnp.linspace(0.0, length, NSAVE),
        outputs=("frame", "centreline"), rtol=tol, atol=tol,
    )


def loaded_helix(rod, force, moment):
    """A uniform helix of `rod` under an axial wrench (bulk equations), checked to be an
    equilibrium by `helix_residual`; returns kappa, tau, phi, n, m (local)."""
    bulk = hr.bulk_helix(rod, 1.0, force=force, moment=moment)
    assert bool(bulk.ok)
    u = bulk.u
    n = bulk.mu2 * u
    np.testing.assert_allclose(hr.helix_residual(rod, u, n), 0.0, atol=1e-12)
    norm = float(jnp.linalg.norm(u))
    np.testing.assert_allclose([bulk.force, bulk.moment], [force, moment], rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(n @ u / norm, force, rtol=1e-12)  # F = n . a
    np.testing.assert_allclose(rod.moment(u) @ u / norm, moment, rtol=1e-10, atol=1e-14)  # M = m . a
    return float(jnp.hypot(u[0], u[1])), float(u[2]), float(jnp.arctan2(u[0], u[1])), n, rod.moment(u)


# -- boundary-value solves ------------------------------------------------------------------


def test_loaded_end_reproduces_the_initial_value_solution():
    """Integrate from a wrench, read the end load, solve the BVP from a wrong guess."""
    start = hr.Clamped((0.2, -0.1, 0.3), hr.so3_exp(jnp.array([0.3, -0.2, 0.5])))
    n1, m1 = jnp.array([0.05, -0.1, 0.08]), jnp.array([0.1, 0.05, -0.07])
    length = 4.0
    ref = ivp(ROD, n1, m1, length, start, tol=1e-12)
    N, M = ref.lab_wrench()
    point = jnp.array([1.0, 2.0, -0.5])
    ends = [
        hr.Loaded(N[-1], M[-1]),  # moment about the end itself
        hr.Loaded(N[-1], M[-1] + jnp.cross(ref.x[-1] - point, N[-1]), point=point),  # about a fixed point
    ]
    for end in ends:
        sol = solve(ROD, length, start, end, (n1 + 0.03, m1 - 0.03), atol=1e-12, ode_rtol=1e-12, ode_atol=1e-12)
        assert bool(sol.ok), sol.result
        if end.point is not None:
            # About a fixed point the shooting equations are linear (the moment about it is
            # conserved): with the Newton Jacobian integrated at 1e-6 (`_jacobian_tolerance`)
            # each step gains about six digits, so two steps, a round-off correction at
            # atol = 1e-12, and the check.
            assert int(sol.num_steps) <= 4
        np.testing.assert_allclose(sol.n0, n1, atol=1e-10)
        np.testing.assert_allclose(sol.m0, m1, atol=1e-9)
        np.testing.assert_allclose(sol.x, ref.x, atol=1e-9)
        np.testing.assert_allclose(sol.frame, ref.frame, atol=1e-9)
        np.testing.assert_allclose(sol.end_force, N[-1], atol=1e-10)
        np.testing.assert_allclose(sol.x[0], start.position, atol=1e-15)


def test_rod_cut_from_a_uniform_helix_is_that_helix():
    """A piece of a loaded uniform helix, with the helix's own end conditions, is the helix,
    for every kind of end condition and for single and multiple shooting."""
    kappa, tau, phi, n, m = loaded_helix(ROD, 0.05, 0.02)
    length = 9.0
    s = jnp.linspace(0.0, length, NSAVE)
    exact_x, exact_frame = hr.helix_centreline(kappa, tau, s), hr.helix_frame(kappa, tau, phi, s)
    start = hr.Clamped(exact_x[0], exact_frame[0])
    D = exact_frame[-1]
    ends = {
        "clamped": hr.Clamped(exact_x[-1], D),
        "loaded": hr.Loaded(D @ n, D @ m),
        "tweezer": hr.Tweezer(D, D @ n),
    }
    guess = (n + 0.01, m - 0.01)
    for name, end in ends.items():
        for segments in ((1, 3) if name == "clamped" else (1,)):
            sol = solve(ROD, length, start, end, guess, segments=segments)
            assert bool(sol.ok), (name, segments, sol.result)
            np.testing.assert_allclose(sol.x, exact_x, atol=1e-8, err_msg=name)
            np.testing.assert_allclose(sol.frame, exact_frame, atol=1e-8, err_msg=name)
            np.testing.assert_allclose(sol.n, jnp.broadcast_to(n, sol.n.shape), atol=1e-9, err_msg=name)
            np.testing.assert_allclose(sol.m, jnp.broadcast_to(m, sol.m.shape), atol=1e-9, err_msg=name)


def scipy_clamped(rod, length, start, end, mesh=81, tol=1e-9):
    """scipy solve_bvp on the 18 unknowns (n, m, D row-major, x), from the unloaded helix."""
    K, uhat = np.asarray(rod.K), np.asarray(rod.uhat)
    K_inv = np.linalg.inv(K)
    e3 = np.array([0.0, 0.0, 1.0])

    def fun(s, y):
        n, m, D = y[:3], y[3:6], y[6:15].reshape(3, 3, -1)
        u = uhat[:, None] + K_inv @ m
        dn = -np.cross(u.T, n.T).T
        dm = (-np.cross(u.T, m.T) - np.cross(e3, n.T)).T
        hat = np.zeros((3, 3, u.shape[1]))
        hat[0, 1], hat[0, 2], hat[1, 0], hat[1, 2], hat[2, 0], hat[2, 1] = -u[2], u[1], u[2], -u[0], -u[1], u[0]
        dD = np.einsum("ijs,jks->iks", D, hat).reshape(9, -1)
        return np.concatenate([dn, dm, dD, D[:, 2]])

    P, R, D0, x0 = (np.asarray(a) for a in (end.position, end.frame, start.frame, start.position))

    def bc(ya, yb):
        Db = yb[6:15].reshape(3, 3)
        A = R.T @ Db
        return np.concatenate([ya[6:15] - D0.ravel(), ya[15:] - x0, yb[15:] - P, 0.5 * np.array([A[2, 1] - A[1, 2], A[0, 2] - A[2, 0], A[1, 0] - A[0, 1]])])

    s = np.linspace(0.0, length, mesh)
    x_free, frame_free = (np.asarray(a) for a in hr.unloaded_state(rod, jnp.asarray(s)))
    y = np.concatenate([np.zeros((6, mesh)), frame_free.reshape(mesh, 9).T, x_free.T])
    out = solve_bvp(fun, bc, s, y, tol=tol, max_nodes=20_000)
    assert out.success, out.message
    return out


def test_clamped_clamped_satisfies_its_conditions_and_matches_scipy():
    length = 1.2 * TURN
    h0, theta0 = (float(a) for a in hr.unloaded_observables(ROD, length))
    start, end = hr.axial_ends(ROD, length, extension=1.08 * h0, rotation=theta0 + 0.4)
    sol = solve(ROD, length, start, end, (jnp.zeros(3), jnp.zeros(3)))
    assert bool(sol.ok), sol.result
    # The conditions ...
    np.testing.assert_allclose(sol.x[0], start.position, atol=1e-14)
    np.testing.assert_allclose(sol.frame[0], start.frame, atol=1e-14)
    np.testing.assert_allclose(sol.end_position, end.position, atol=1e-9)
    np.testing.assert_allclose(sol.end_frame, end.frame, atol=1e-9)
    # ... hold for an equilibrium: integrating its start wrench gives the same rod.
    ref = ivp(ROD, sol.n0, sol.m0, length, start)
    np.testing.assert_allclose(sol.x, ref.x, atol=1e-8)
    # scipy's collocation solver, from the unloaded helix, finds the same solution.
    out = scipy_clamped(ROD, length, start, end)
    y = out.sol(np.asarray(sol.s))
    np.testing.assert_allclose(sol.x, y[15:].T, atol=1e-6)
    np.testing.assert_allclose(sol.n0, y[:3, 0], atol=1e-6)
    np.testing.assert_allclose(sol.m0, y[3:6, 0], atol=1e-6)
    frames = y[6:15].T.reshape(-1, 3, 3)
    np.testing.assert_allclose(sol.frame, frames, atol=1e-6)


def test_axial_ends_follow_the_spring_conventions():
    """Unloaded controls give the unloaded helix exactly (n = m = 0), in every kind."""
    length = 2.5 * TURN
    h0, theta0 = (float(a) for a in hr.unloaded_observables(SPRING, length))
    np.testing.assert_allclose([h0, theta0], [length * 0.3 / SPRING_NORM, length * SPRING_NORM], rtol=1e-14)
    start, free = hr.axial_ends(SPRING, length, force=0.0, moment=0.0)
    np.testing.assert_allclose(start.position, hr.helix_centreline(1.0, 0.3, 0.0), atol=1e-15)
    for kw in ({"extension": h0, "rotation": theta0}, {"force": 0.0, "rotation": theta0}):
        _, end = hr.axial_ends(SPRING, length, **kw)
        np.testing.assert_allclose(end.frame, hr.helix_frame(1.0, 0.3, 0.0, length), atol=1e-14)
        if "extension" in kw:
            np.testing.assert_allclose(end.position, hr.helix_centreline(1.0, 0.3, length), atol=1e-13)
    # The placement is differentiable at the edges: straight (kappa = 0) and straight untwisted rods.
    for uhat in ((0.0, 0.0, 0.0), (0.0, 0.0, 0.5)):
        def placement(u):
            rod = hr.Rod(1.0, 1.0, 0.8, uhat=u)
            x, frame = hr.unloaded_state(rod, 2.0)
            return jnp.concatenate([x, frame.ravel(), jnp.stack(hr.unloaded_observables(rod, 2.0))])

        np.testing.assert_allclose(placement(jnp.asarray(uhat))[:3], (0.0, 0.0, 2.0), atol=1e-15)
        assert bool(jnp.all(jnp.isfinite(jax.jacfwd(placement)(jnp.asarray(uhat)))))
    for end in (free, hr.axial_ends(SPRING, length, force=0.0, rotation=theta0)[1]):
        sol = solve(SPRING, length, start, end, (jnp.full(3, 0.01), jnp.full(3, -0.01)))
        assert bool(sol.ok)
        np.testing.assert_allclose(sol.n0, 0.0, atol=1e-10)
        np.testing.assert_allclose(sol.m0, 0.0, atol=1e-10)
        np.testing.assert_allclose(sol.x, hr.helix_centreline(1.0, 0.3, sol.s), atol=1e-9)


def test_wrench_growth_rate_against_a_numpy_jacobian():
    """Eigenvalues of the linearised wrench flow by central differences of an independent
    numpy right-hand side; a stretched spring at fixed rotation is spatially unstable, a
    compressed one is not."""
    K_inv, uhat = np.linalg.inv(np.asarray(SPRING.K)), np.asarray(SPRING.uhat)

    def rhs(w):
        n, m = w[:3], w[3:]
        u = uhat + K_inv @ m
        return np.concatenate([-np.cross(u, n), -np.cross(u, m) - np.cross([0.0, 0.0, 1.0], n)])

    length = 2 * TURN
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


# -- response curves ------------------------------------------------------------------------

FORCES = jnp.array([0.0, 0.01, 0.02, 0.03])


@eqx.filter_jit
@eqx.debug.assert_max_traces(max_traces=1)
def tweezer_curve(length, forces):
    """Force-extension of the spring at fixed (unturned) end rotation; one trace for all."""
    return hr.force_extension(SPRING, length, forces, rotation=length * SPRING_NORM, segments=4)


def test_response_curves_converge_to_the_bulk_helix():
    """The end effect of the clamps on the extension converges to a constant as the rod
    grows (so its share of the total falls like 1/L); the torque tends to the bulk one."""
    lengths = [2 * TURN, 4 * TURN, 8 * TURN, 16 * TURN]
    curves = [tweezer_curve(jnp.asarray(length), FORCES) for length in lengths]
    for c in curves:
        assert bool(jnp.all(c.ok)) and bool(jnp.all(c.bulk_ok))
        np.testing.assert_allclose(c.force, FORCES, atol=1e-12)
        np.testing.assert_allclose(c.rotation, c.length * SPRING_NORM, atol=1e-8)
        np.testing.assert_allclose(c.extension[0], c.bulk_extension[0], atol=1e-9)  # unloaded
    dh = np.array([np.asarray(c.end_effect("extension")) for c in curves])[:, 1:]
    dM = np.array([np.asarray(c.end_effect("moment")) for c in curves])[:, 1:]
    # Extension: the end effect settles (boundary layers decay along the stretched spring).
    assert np.all(np.abs(dh[3] - dh[2]) < 0.25 * np.abs(dh[1] - dh[0]))
    relative = np.abs(dh) / np.array(lengths)[:, None]
    assert np.all(np.diff(relative[1:], axis=0) < 0)
    # Torque: the clamps' share falls like 1/L.
    ratio = dM[3] / dM[2]
    np.testing.assert_allclose(ratio, 0.5, atol=0.1)
    # The bulk prediction is the uniform helix with the same force and rotation per length.
    bulk = hr.bulk_helix(SPRING, lengths[0], force=0.02, rotation=lengths[0] * SPRING_NORM)
    np.testing.assert_allclose(curves[0].bulk_extension[2], bulk.extension, rtol=1e-12)


def test_force_extension_command(tmp_path):
    from typer.testing import CliRunner

    from helixrod.cli import app

    out = tmp_path / "curve.json"
    args = ["force-extension", "--turns", "2", "--forces", "0:0.03:4", "--segments", "4", "--out", str(out)]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "force-extension" in result.output and "rotation held" in result.output
    import json

    curve = json.loads(out.read_text())
    direct = tweezer_curve(jnp.asarray(2 * TURN), jnp.linspace(0.0, 0.03, 4))
    np.testing.assert_allclose(curve["extension"], direct.extension, atol=1e-9)
    bad = CliRunner().invoke(app, ["force-extension", "--uhat", "0,0,0"])
    assert bad.exit_code != 0 and "must not be zero" in bad.output


def test_rotation_response_agrees_with_force_extension():
    """Both curve functions solve the same problems (they share one compiled program with the
    CLI test): the same (force, rotation) point agrees; the torque grows with the turn and
    follows the bulk helix; a spring twisted between grips at fixed extension too."""
    length = 2 * TURN
    theta0 = length * SPRING_NORM
    turns = theta0 + jnp.array([-0.5, 0.0, 0.5, 1.0])
    twisted = hr.rotation_response(SPRING, length, turns, force=0.01, segments=4)
    pulled = hr.force_extension(SPRING, length, jnp.array([0.0, 0.005, 0.01, 0.02]), rotation=theta0, segments=4)
    assert bool(jnp.all(twisted.ok)) and bool(jnp.all(pulled.ok))
    np.testing.assert_allclose(twisted.rotation, turns, atol=1e-9)
    np.testing.assert_allclose(twisted.force, 0.01, atol=1e-12)
    np.testing.assert_allclose(twisted.extension[1], pulled.extension[2], atol=1e-9)
    np.testing.assert_allclose(twisted.moment[1], pulled.moment[2], atol=1e-10)
    assert np.all(np.diff(np.asarray(twisted.moment)) > 0)
    np.testing.assert_allclose(twisted.moment, twisted.bulk_moment, rtol=0, atol=1e-3 * float(jnp.abs(twisted.moment).max()))
    h0 = length * 0.3 / SPRING_NORM
    gripped = hr.rotation_response(SPRING, length, turns, extension=1.05 * h0, segments=4)
    assert bool(jnp.all(gripped.ok))
    np.testing.assert_allclose(gripped.extension, 1.05 * h0, atol=1e-9)
    np.testing.assert_allclose(gripped.force, gripped.bulk_force, rtol=0.1)
    assert np.all(np.diff(np.asarray(gripped.moment)) > 0)


def test_response_curve_flags_a_bad_point_without_spoiling_the_others():
    length = jnp.asarray(2 * TURN)
    clean = tweezer_curve(length, FORCES)
    bad = tweezer_curve(length, FORCES.at[1].set(jnp.nan))
    assert not bool(bad.ok[1]) and bool(jnp.isnan(bad.extension[1]))
    keep = np.array([0, 2, 3])
    assert bool(jnp.all(bad.ok[keep]))
    np.testing.assert_allclose(bad.extension[keep], clean.extension[keep], atol=1e-9)


# -- derivatives ----------------------------------------------------------------------------


def test_gradients_through_the_boundary_value_solve_match_central_differences():
    length = 1.5 * TURN
    h0, theta0 = (float(a) for a in hr.unloaded_observables(SPRING, length))
    tight = dict(atol=1e-12, ode_rtol=1e-12, ode_atol=1e-12)

    def outputs(K3, extension):
        rod = eqx.tree_at(lambda r: r.K3, SPRING, jnp.asarray(K3))  # an array: no recompilation
        start, end = hr.axial_ends(rod, length, extension=extension, rotation=theta0 + 0.2)
        sol = solve(rod, length, start, end, (jnp.zeros(3), jnp.zeros(3)), **tight)
        return jnp.concatenate([sol.force, sol.moment0, sol.x[NSAVE // 2]])

    x = (jnp.asarray(0.77), jnp.asarray(1.1 * h0))
    J = jax.jit(jax.jacfwd(outputs, argnums=(0, 1)))(*x)
    for i, eps in enumerate((1e-4, 1e-4)):
        plus = list(x)
        minus = list(x)
        plus[i] = plus[i] + eps
        minus[i] = minus[i] - eps
        fd = (outputs(*plus) - outputs(*minus)) / (2 * eps)
        np.testing.assert_allclose(J[i], fd, rtol=1e-6, atol=1e-9 * float(jnp.abs(fd).max()))
        assert float(jnp.abs(fd).max()) > 1e-3  # the derivative is not trivially zero


# -- errors ---------------------------------------------------------------------------------


def test_bad_input_raises_clear_errors():
    start, end = hr.axial_ends(SPRING, 10.0, force=0.01, moment=0.0)
    with pytest.raises(ValueError, match="length must be finite and > 0"):
        hr.solve_boundary_value(SPRING, -1.0, end=end)
    with pytest.raises(ValueError, match="length must be finite"):
        hr.solve_boundary_value(SPRING, jnp.nan, end=end)
    with pytest.raises(ValueError, match="end must be Clamped, Loaded or Tweezer"):
        hr.solve_boundary_value(SPRING, 10.0, end=(1.0, 2.0))
    with pytest.raises(ValueError, match="start must be Clamped"):
        hr.solve_boundary_value(SPRING, 10.0, start=end, end=end)
    with pytest.raises(ValueError, match="method"):
        hr.solve_boundary_value(SPRING, 10.0, end=end, method="bisection")
    with pytest.raises(ValueError, match="segments"):
        hr.solve_boundary_value(SPRING, 10.0, end=end, segments=0)
    with pytest.raises(ValueError, match="guess"):
        hr.solve_boundary_value(SPRING, 10.0, end=end, guess="bulk")
    with pytest.raises(ValueError, match="guess .n0, m0. needs shapes"):
        hr.solve_boundary_value(SPRING, 10.0, end=end, guess=(jnp.zeros(2), jnp.zeros(3)))
    with pytest.raises(ValueError, match="saveat must increase"):
        hr.solve_boundary_value(SPRING, 10.0, end=end, saveat=jnp.array([0.0, 5.0, 4.0]))
    with pytest.raises(ValueError, match="saveat must increase strictly within"):
        hr.solve_boundary_value(SPRING, 10.0, end=end, saveat=jnp.array([0.0, 11.0]))
    with pytest.raises(ValueError, match="adjoint"):
        import diffrax

        hr.solve_boundary_value(SPRING, 10.0, end=end, adjoint=diffrax.RecursiveCheckpointAdjoint())
    with pytest.raises(ValueError, match="one rod"):
        hr.solve_boundary_value(hr.Rod(jnp.ones(2), 1.0, 1.0), 10.0, end=end)
    with pytest.raises(ValueError, match="frame must be a rotation"):
        hr.Clamped((0.0, 0.0, 0.0), 2 * jnp.eye(3))
    with pytest.raises(ValueError, match="position must have trailing shape"):
        hr.Clamped((0.0, 0.0))
    with pytest.raises(ValueError, match="force must be finite"):
        hr.Loaded((jnp.inf, 0.0, 0.0))
    with pytest.raises(ValueError, match="frame must be a rotation"):
        hr.Tweezer(-jnp.eye(3), (0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="one of the pairs"):
        hr.axial_ends(SPRING, 10.0, force=1.0, extension=2.0)
    with pytest.raises(ValueError, match="moment must be a scalar"):
        hr.axial_ends(SPRING, 10.0, force=1.0, moment=jnp.zeros(2))
    with pytest.raises(ValueError, match="give moment= or rotation=, not both"):
        hr.force_extension(SPRING, 10.0, FORCES, moment=0.0, rotation=1.0)
    with pytest.raises(ValueError, match="forces must be finite"):
        hr.force_extension(SPRING, 10.0, FORCES.at[0].set(jnp.nan))
    with pytest.raises(ValueError, match="exactly one of force= or extension="):
        hr.rotation_response(SPRING, 10.0, jnp.ones(3))
    with pytest.raises(ValueError, match="mode"):
        hr.force_extension(SPRING, 10.0, FORCES, mode="parallel")
    with pytest.raises(ValueError, match="controls must be one of"):
        hr.EndResponseData(1.0, [1.0], [1.0], [1.0], [1.0], controls="force-extension")
    with pytest.raises(ValueError, match="give rotation_sigma"):
        hr.EndResponseData(1.0, [1.0], [1.0], [1.0], [1.0], controls="force-moment", extension_sigma=0.1)
    with pytest.raises(ValueError, match="non-finite values in rows \\[1\\]"):
        hr.EndResponseData(1.0, [1.0, np.nan], [1.0, 1.0], [1.0, 1.0], [1.0, 1.0], controls="force-rotation",
                           extension_sigma=0.1, moment_sigma=0.1)
    with pytest.raises(ValueError, match="s must increase"):
        hr.ShapeData(1.0, [0.0, 0.5, 0.4], np.zeros((3, 3)), end, sigma=0.1)
    with pytest.raises(ValueError, match="points must have shape"):
        hr.ShapeData(1.0, [0.0, 0.5, 1.0], np.zeros((2, 3)), end, sigma=0.1)
    with pytest.raises(ValueError, match="sigma must be finite and > 0"):
        hr.ShapeData(1.0, [0.0, 0.5, 1.0], np.zeros((3, 3)), end, sigma=0.0)
    data = hr.ShapeData(1.0, [0.0, 0.5, 1.0], np.zeros((3, 3)), end, sigma=0.1)
    with pytest.raises(ValueError, match="applies to HelixData only"):
        hr.fit_stiffness(data, branch="stable")
    with pytest.raises(ValueError, match="not available for finite-rod data"):
        hr.fit_stiffness(data, solver="adam")
    with pytest.raises(ValueError, match="HelixData, EndResponseData or ShapeData"):
        hr.fit_stiffness({"force": [1.0]})


def test_failed_solve_raises_with_throw_and_reports_without():
    """A clamped-clamped spring stretched far beyond its length has no solution."""
    length = 1.0 * TURN
    start, end = hr.axial_ends(SPRING, length, extension=2 * length, rotation=length * SPRING_NORM)
    sol = solve(SPRING, length, start, end, (jnp.zeros(3), jnp.zeros(3)), throw=False)
    assert not bool(sol.ok) and float(sol.residual) > 1e-3
    with pytest.raises(Exception, match="shooting equations were not solved"):
        jax.block_until_ready(solve(SPRING, length, start, end, (jnp.zeros(3), jnp.zeros(3))))


# -- fits (slow: one compilation each) --------------------------------------------------------


@pytest.mark.slow
def test_end_response_fit_recovers_the_generating_rod():
    rod = hr.Rod(1.0, 1.3, 0.8, uhat=(0.5, 0.9, 0.3))
    norm = float(jnp.linalg.norm(rod.uhat))
    length = 2 * 2 * np.pi / norm
    force = np.repeat(np.linspace(0.005, 0.03, 3), 3)
    rotation = length * norm + np.tile([-1.0, 0.0, 1.0], 3)
    data = hr.synthetic_end_response_data(rod, length, "force-rotation", force, rotation, 1e-3, jax.random.key(1))
    fit = hr.fit_stiffness(data, uhat=rod.uhat, fix={"K13": 0.0, "K23": 0.0}, rtol=1e-8, atol=1e-10)
    assert fit.ok, fit.message
    assert fit.identifiability.symmetries == ()
    truth = {"K1": 1.0, "K2": 1.3, "K3": 0.8}
    for name, value in truth.items():
        assert abs(float(fit.params[name]) - value) < 4 * float(fit.stderr[name]), (name, fit.params[name], fit.stderr[name])
    assert 0.2 < fit.chi2_reduced < 3.0
    assert set(fit.predicted) == {"extension", "moment"}
    # residuals: (extension, then moment) minus observed, over sigma
    n = len(data)
    np.testing.assert_allclose(fit.predicted["moment"], data.moment + fit.residuals[n:] * data.sigma[:, 1], rtol=1e-12)


@pytest.mark.slow
def test_shape_fit_recovers_the_generating_rod():
    rod = hr.Rod(1.0, 1.4, 0.8, K13=0.15, K23=-0.1, uhat=(0.3, 0.9, 0.35))
    length = 6.0
    s = jnp.linspace(0.0, length, 25)
    ends = [hr.Loaded((0.02, 0.0, 0.05), (0.0, 0.03, 0.0)), hr.Loaded((-0.03, 0.02, 0.0), (0.02, 0.0, -0.02))]
    data = hr.synthetic_shape_data(rod, length, s, ends, 2e-3, jax.random.key(3))
    fit = hr.fit_stiffness(data, uhat=rod.uhat, init=hr.Rod(1.3, 1.3, 1.0, uhat=rod.uhat), rtol=1e-8, atol=1e-10)
    assert fit.ok, fit.message
    truth = dict(zip(("K1", "K2", "K3", "K13", "K23"), (1.0, 1.4, 0.8, 0.15, -0.1)))
    for name, value in truth.items():
        assert abs(float(fit.params[name]) - value) < 4 * float(fit.stderr[name]), (name, fit.params[name], fit.stderr[name])
    assert 0.5 < fit.chi2_reduced < 1.5
    assert fit.predicted["points"].shape == data.points.shape


@pytest.mark.slow
def test_reverse_mode_with_direct_adjoint_matches_forward_mode():
    import diffrax

    length = 1.5 * TURN
    h0, theta0 = (float(a) for a in hr.unloaded_observables(SPRING, length))

    def outputs(K3, adjoint):
        rod = eqx.tree_at(lambda r: r.K3, SPRING, K3)
        start, end = hr.axial_ends(rod, length, extension=1.1 * h0, rotation=theta0)
        sol = hr.solve_boundary_value(rod, length, start=start, end=end, segments=2, adjoint=adjoint, throw=False)
        return jnp.concatenate([sol.force, sol.end_moment])

    forward = jax.jit(jax.jacfwd(lambda k: outputs(k, diffrax.ForwardMode())))(0.77)
    reverse = jax.jit(jax.jacrev(lambda k: outputs(k, diffrax.DirectAdjoint())))(0.77)
    np.testing.assert_allclose(reverse, forward, rtol=1e-8, atol=1e-9 * float(jnp.abs(forward).max()))


@pytest.mark.slow
def test_multiple_shooting_reaches_where_single_shooting_fails():
    """A spring stretched at fixed end rotation is spatially unstable (eigenvalues of the
    linearised wrench flow with real part lambda > 0): single shooting fails at 10 turns,
    five pieces solve it and satisfy the end conditions."""
    length = 10 * TURN
    h0, theta0 = (float(a) for a in hr.unloaded_observables(SPRING, length))
    start, end = hr.axial_ends(SPRING, length, extension=1.1 * h0, rotation=theta0)
    single = hr.solve_boundary_value(SPRING, length, start=start, end=end, throw=False)
    multiple = hr.solve_boundary_value(SPRING, length, start=start, end=end, segments=5, throw=False)
    assert not bool(single.ok)
    assert bool(multiple.ok)
    np.testing.assert_allclose(multiple.end_position, end.position, atol=1e-8)
    np.testing.assert_allclose(multiple.end_frame, end.frame, atol=1e-8)
