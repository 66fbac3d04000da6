"""Boundary-value solves of finite rods (solve_boundary_value, BoundaryValueOptions).

Independent references: the initial-value solver (`solve_static`), exact uniform helices
(`helix_frame`, `helix_centreline`, `helix_residual`), scipy `solve_bvp` on a numpy right-hand
side, central differences.  To keep the default run short, the solves share a few compiled
programs: every eager `solve` call below has 9 save points and a `(n0, m0)` guess
(`helpers.solve`: one compilation for all end types, one more with 3 segments, and, slow,
one for a vmapped batch of mixed end kinds).
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    BVP_ROD as ROD, NSAVE, SPRING, SPRING_NORM, SPRING_TURN as TURN, ivp, loaded_helix, solve, tree_allclose,
)
from scipy.integrate import solve_bvp

import helixrod as hr
from helixrod import _compile
from helixrod._bvp import stack_ends
from helixrod._bvp._options import with_settings


@pytest.mark.heavy
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
            # conserved): with the Newton Jacobian from Jacobi fields accurate to ~1e-5
            # (`_shooting.STEERING_STEPS_PER_RADIAN`) each step gains about five digits, so
            # two or three steps, a round-off correction at atol = 1e-12, and the check.
            assert int(sol.num_steps) <= 4
        np.testing.assert_allclose(sol.n0, n1, atol=1e-10)
        np.testing.assert_allclose(sol.m0, m1, atol=1e-9)
        np.testing.assert_allclose(sol.x, ref.x, atol=1e-9)
        np.testing.assert_allclose(sol.frame, ref.frame, atol=1e-9)
        np.testing.assert_allclose(sol.end_force, N[-1], atol=1e-10)
        np.testing.assert_allclose(sol.x[0], start.position, atol=1e-15)


@pytest.mark.heavy
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


@pytest.mark.heavy
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


def test_unloaded_axial_ends_solve_to_the_unloaded_helix():
    """Unloaded controls give the unloaded helix exactly (n = m = 0), in every kind."""
    length = 2.5 * TURN
    theta0 = float(hr.unloaded_observables(SPRING, length)[1])
    start, free = hr.axial_ends(SPRING, length, force=0.0, moment=0.0)
    for end in (free, hr.axial_ends(SPRING, length, force=0.0, rotation=theta0)[1]):
        sol = solve(SPRING, length, start, end, (jnp.full(3, 0.01), jnp.full(3, -0.01)))
        assert bool(sol.ok)
        np.testing.assert_allclose(sol.n0, 0.0, atol=1e-10)
        np.testing.assert_allclose(sol.m0, 0.0, atol=1e-10)
        np.testing.assert_allclose(sol.x, hr.helix_centreline(1.0, 0.3, sol.s), atol=1e-9)


def test_axial_ends_carry_the_whole_turns_to_the_default_guess(compilations):
    """The end frame holds the rotation only up to whole turns; `axial_ends` also gives the
    end its total rotation, and the default guess turns the rod by as much: a spring held
    one turn past its unloaded end under a pull is the twisted spring the bulk predicts
    (stable), where the frame alone gives the untwisted one (also an equilibrium)."""
    length = 5 * TURN
    rotation = length * SPRING_NORM + 2 * np.pi
    start, end = hr.axial_ends(SPRING, length, force=0.05, rotation=rotation)
    assert float(end.rotation) == pytest.approx(rotation, rel=1e-15)
    bulk = hr.bulk_helix(SPRING, length, force=0.05, rotation=rotation)
    turned = hr.solve_boundary_value(SPRING, length, start=start, end=end)
    frame_only = hr.solve_boundary_value(SPRING, length, start=start, end=hr.Tweezer(end.frame, end.force))
    axial_moment = lambda sol: float(sol.moment0[2] + jnp.cross(sol.node_position[0], sol.force)[2])  # noqa: E731
    assert bool(turned.stable) and bool(frame_only.stable)
    assert axial_moment(turned) == pytest.approx(float(bulk.moment), rel=1e-3)
    assert abs(axial_moment(frame_only)) < 0.05 * float(bulk.moment)  # untwisted: the clamps alone
    # Each solution counts the whole turns it holds (the same end frame, a turn apart).
    assert float(turned.rotation) == pytest.approx(rotation, abs=1e-9)
    assert float(frame_only.rotation) == pytest.approx(rotation - 2 * np.pi, abs=1e-9)
    # Warm-started from the untwisted spring, the solve stays there: converged, but not to
    # the turns the end asks for -- flagged, and with throw=True an error that says so.
    stayed = hr.solve_boundary_value(SPRING, length, start=start, end=end, guess=frame_only, throw=False)
    assert int(stayed.result._value) == int(hr.RESULTS.other_whole_turns._value) and not bool(stayed.ok)
    assert float(stayed.rotation) == pytest.approx(rotation - 2 * np.pi, abs=1e-9)
    with pytest.raises(hr.SolverError, match=r"other whole turns.*holds 5\.00 turns, the end asks for 6\.00"):
        hr.solve_boundary_value(SPRING, length, start=start, end=end, guess=frame_only)
    with pytest.raises(ValueError, match="rotation must be finite"):
        hr.Tweezer(end.frame, end.force, rotation=jnp.nan)
    # A start's rotation (an end's hint) plays no part: the same solve, no new program.
    as_start = hr.Clamped(start.position, start.frame, rotation=1.0)
    compilations.clear()
    again = hr.solve_boundary_value(SPRING, length, start=as_start, end=end)
    np.testing.assert_array_equal(again.force, turned.force)
    assert compilations == []


@pytest.mark.heavy
def test_other_whole_turns_are_flagged_under_jit_and_vmap():
    """Inside a compiled program the solve flags a state with other whole turns than its
    end asks for itself (an eager call does so after its fallbacks): a vmapped batch of
    two guesses, the untwisted and the twisted spring at the end frame of the twisted one,
    flags the first only."""
    length = 5 * TURN
    rotation = length * SPRING_NORM + 2 * np.pi
    start, end = hr.axial_ends(SPRING, length, force=0.05, rotation=rotation)
    untwisted = hr.solve_boundary_value(SPRING, length, start=start, end=hr.Tweezer(end.frame, end.force))
    twisted = hr.solve_boundary_value(SPRING, length, start=start, end=end)
    n0, m0 = (jnp.stack([getattr(untwisted, name), getattr(twisted, name)]) for name in ("n0", "m0"))
    solve_from = jax.jit(jax.vmap(lambda n, m: hr.solve_boundary_value(SPRING, length, start=start, end=end, guess=(n, m), throw=False)))
    both = solve_from(n0, m0)
    assert int(both.result._value[0]) == int(hr.RESULTS.other_whole_turns._value) and bool(both.ok[1])
    np.testing.assert_allclose(both.rotation, [rotation - 2 * np.pi, rotation], atol=1e-9)
    np.testing.assert_allclose(both.force[1], twisted.force, atol=1e-9)



def test_a_hooked_end_is_held_by_the_line_through_its_hook():
    """A force acting at a hook rigidly attached to the end (`Loaded(hook=)`: the spring's
    unloaded end to its axis) holds the rod in the state whose force line passes through
    the hook's place there: the fixed-line condition through that point solves to the same
    state (to 1e-9).  Along a load the two differ: the hook leaves the axis (0.12 at F = 0.05
    on 2 turns) and the extension of the fixed-line spring is 1 % shorter."""
    length = 2 * TURN
    x0, frame0 = hr.unloaded_state(SPRING, jnp.asarray(length))
    hook = frame0.T @ jnp.array([-x0[0], -x0[1], 0.0])
    hooked = hr.solve_boundary_value(SPRING, length, end=hr.Loaded(force=(0.0, 0.0, 0.05), hook=hook), segments=4)
    place = hooked.end_position + hooked.end_frame @ hook
    held = hr.solve_boundary_value(SPRING, length, end=hr.Loaded(force=(0.0, 0.0, 0.05), point=place), segments=4)
    np.testing.assert_allclose(held.end_position, hooked.end_position, atol=1e-9)
    np.testing.assert_allclose(held.end_frame, hooked.end_frame, atol=1e-9)
    np.testing.assert_allclose(held.moment0, hooked.moment0, atol=1e-9)
    assert int(hooked.instability_index) == int(held.instability_index) == 0
    on_axis = hr.solve_boundary_value(SPRING, length, end=hr.Loaded(force=(0.0, 0.0, 0.05), point=(0.0, 0.0, 0.0)), segments=4)
    assert float(jnp.linalg.norm(place[:2])) > 0.1
    assert 0.005 < float(1 - on_axis.end_position[2] / hooked.end_position[2]) < 0.02

def test_the_end_rotation_is_the_twist_and_fuller_writhe_integrals():
    """A solution's `rotation` against the integrals it sums (`_rotation.py`): along the
    rod integrated again from its start wrench (`solve_static`, 4001 points, trapezoids),
    $\\Theta = \\int u_3\\,ds + \\int (e_z\\times t)\\cdot t'/(1 + t_z)\\,ds$ -- the twist and the
    connection of Fuller's reference frame -- for a spring held 0, 1 and 1.3 turns past its
    unloaded end; unloaded, $\\Theta_0 = L|\\hat u|$ (the convention of `axial_ends`)."""
    length = 5 * TURN
    theta0 = length * SPRING_NORM
    s = np.linspace(0.0, length, 4001)
    for extra in (0.0, 2 * np.pi, 2 * np.pi + 2.0):
        start, end = hr.axial_ends(SPRING, length, force=0.05, rotation=theta0 + extra)
        sol = hr.solve_boundary_value(SPRING, length, start=start, end=end)
        assert bool(sol.stable)
        path = hr.solve_static(SPRING, sol.n0, sol.m0, length, frame0=start.frame, x0=start.position, saveat=s, outputs=("frame",))
        frames, twists = np.asarray(path.frame), np.asarray(jax.vmap(SPRING.twist)(path.m))
        tangents = frames[:, :, 2]
        turning = np.einsum("sij,sj->si", frames, np.cross(twists, [0.0, 0.0, 1.0]))  # t' = D (u x e3)
        connection = np.cross([0.0, 0.0, 1.0], tangents)
        integrals = np.trapezoid(twists[:, 2], s) + np.trapezoid(np.sum(connection * turning, 1) / (1 + tangents[:, 2]), s)
        assert float(sol.rotation) == pytest.approx(integrals, abs=1e-6)
        assert float(sol.rotation) == pytest.approx(theta0 + extra, abs=1e-9)


def test_a_first_call_compiles_its_programs_side_by_side_once(compilations, monkeypatch):
    """An eager first call compiles the guess, the solve and its stability test each on a
    thread of its own, from specs of the values they will be called with: the calls find
    those compilations (a spec that missed would compile the program twice).  A signature
    no other test uses, of all three: 12 pieces of the test, 4 saved points."""
    monkeypatch.setattr(_compile, "cores", lambda: 2)  # as on a machine of several cores
    rod, length = hr.Rod(1.0, 1.5, 0.8), 1.0
    sol = hr.solve_boundary_value(
        rod, length, end=hr.Loaded(force=(0.0, 0.0, -3.0)), saveat=jnp.linspace(0.0, length, 4), stability_pieces=12
    )
    ours = [(thread, name) for thread, name in compilations if name in ("as_warm_start", "solve", "_stability_where_solved")]
    assert sorted(ours) == [(f"helixrod-compile-{name}", name) for name in ("_stability_where_solved", "as_warm_start", "solve")], ours
    # Under 3 pN the straight cantilever (critical load pi^2/4) has buckled: the direct
    # solve found the straight state, unstable, and the retries pushed from it (warm starts
    # of its one piece: the same programs, compiled once) found the buckled one.
    assert bool(sol.ok) and int(sol.instability_index) == 0 and sol.stability_pieces == 12
    assert float(np.linalg.norm(np.asarray(sol.end_position)[:2])) > 0.3


@pytest.mark.slow  # compiles the vmapped solve (~20 s on 2 busy cores); the single solves share `solve`
def test_vmapped_solve_over_mixed_end_kinds_equals_single_solves():
    """A stack of the four kinds of end (clamped, loaded about the end and about a point,
    tweezer) of a piece of a loaded uniform helix, solved in one vmapped call, equals the
    single solves point for point -- and the helix."""
    kappa, tau, phi, n, m = loaded_helix(ROD, 0.05, 0.02)
    length = 9.0
    s = jnp.linspace(0.0, length, NSAVE)
    exact_x, exact_frame = hr.helix_centreline(kappa, tau, s), hr.helix_frame(kappa, tau, phi, s)
    start = hr.Clamped(exact_x[0], exact_frame[0])
    D, P = exact_frame[-1], jnp.array([0.5, -1.0, 2.0])
    ends = [
        hr.Clamped(exact_x[-1], D),
        hr.Loaded(D @ n, D @ m),
        hr.Loaded(D @ n, D @ m + jnp.cross(exact_x[-1] - P, D @ n), point=P),
        hr.Tweezer(D, D @ n),
    ]
    guess = (n + 0.01, m - 0.01)
    stacked = stack_ends(ends)
    assert isinstance(stacked, hr.EndCondition) and stacked.kind.tolist() == [0, 1, 1, 2]
    batch = jax.vmap(lambda end: solve(ROD, length, start, end, guess, throw=False))(stacked)
    assert bool(jnp.all(batch.ok))
    for i, end in enumerate(ends):
        single = solve(ROD, length, start, end, guess)
        point = jax.tree.map(lambda a: a[i], batch)
        # The margin is an eigenvalue of a Hessian with entries ~5e7: vmap's round-off in them
        # moves it by ~6e-9 (5e-10 relative), as documented for the response curves.
        np.testing.assert_allclose(point.stability_margin, single.stability_margin, rtol=1e-8)
        same = lambda sol: eqx.tree_at(lambda t: t.stability_margin, sol, jnp.zeros(()))  # noqa: E731
        tree_allclose(same(point), same(single), rtol=0, atol=1e-10)
        np.testing.assert_allclose(batch.x[i], exact_x, atol=1e-8)
        np.testing.assert_allclose(batch.frame[i], exact_frame, atol=1e-8)


# -- options ---------------------------------------------------------------------------------


def test_options_reject_bad_values():
    for kwargs, match in [
        ({"segments": 0}, "segments must be an integer >= 1"),
        ({"segments": 2.0}, "segments must be an integer"),
        ({"continuation": -1}, "continuation must be an integer >= 0"),
        ({"max_steps": 0}, "max_steps must be an integer >= 1"),
        ({"method": "bisection"}, "method must be one of"),
        ({"solver": diffrax.Tsit5()}, "solver must be CommutatorFreeRK4 or MuntheKaasRK"),
        ({"adjoint": diffrax.RecursiveCheckpointAdjoint()}, "adjoint must be diffrax.ForwardMode"),
        ({"atol": 0.0}, "atol must be finite and > 0"),
        ({"ode_rtol": np.nan}, "ode_rtol must be finite and > 0"),
        ({"ode_atol": jnp.ones(2)}, "ode_atol must be a scalar"),
        ({"ode_rtol": np.ones(3)}, "ode_rtol must be a scalar"),
        ({"atol": "tight"}, "atol must be a number, got 'tight'"),
        ({"stability_pieces": 10**6}, "stability_pieces must be at most 1024"),  # a dense Hessian: out of memory
    ]:
        with pytest.raises(ValueError, match="BoundaryValueOptions: " + match):
            hr.BoundaryValueOptions(**kwargs)
    # Through the entry points' keywords too, and for something that is not options.
    start, end = hr.axial_ends(SPRING, 10.0, force=0.01, moment=0.0)
    with pytest.raises(ValueError, match="BoundaryValueOptions: atol"):
        hr.solve_boundary_value(SPRING, 10.0, end=end, atol=-1.0)
    with pytest.raises(ValueError, match="options must be a BoundaryValueOptions"):
        hr.solve_boundary_value(SPRING, 10.0, end=end, options={"segments": 2})


def test_option_tolerances_are_host_scalars_or_traced_arrays():
    """Concrete tolerances are kept as NumPy float64 scalars (building options dispatches
    nothing to the device), JAX arrays -- traced ones included -- as they are; the default
    options are one shared instance."""
    options = hr.BoundaryValueOptions(atol=1e-8, ode_rtol=np.float32(1e-6))
    assert isinstance(options.atol, np.ndarray) and options.atol.dtype == np.float64 and float(options.atol) == 1e-8
    assert options.ode_rtol.dtype == np.float64 and float(options.ode_rtol) == pytest.approx(1e-6)
    given = jnp.asarray(1e-9)
    assert hr.BoundaryValueOptions(atol=given).atol is given
    traced = jax.jit(lambda t: jnp.asarray(hr.BoundaryValueOptions(ode_atol=t).ode_atol * 2))(3e-7)
    assert float(traced) == pytest.approx(6e-7)
    assert with_settings(None) is with_settings(None, segments=None)
    assert with_settings(None, atol=1e-7).atol == 1e-7 and with_settings(None) == hr.BoundaryValueOptions()
    # The default options with the same hashable settings are built once; the settings'
    # types are part of the key, and unhashable or invalid settings are built (and checked)
    # every time.
    assert with_settings(None, atol=1e-7, segments=2) is with_settings(None, segments=2, atol=1e-7)
    assert with_settings(None, segments=2) is not with_settings(None, segments=3)
    assert with_settings(None, segments=2).segments == 2 and with_settings(None, segments=3).segments == 3
    with_settings(None, segments=1)
    with pytest.raises(ValueError, match="segments must be an integer"):
        with_settings(None, segments=True)
    for _ in range(2):
        with pytest.raises(ValueError, match="atol must be finite"):
            with_settings(None, atol=-1.0)
    assert float(with_settings(None, atol=jnp.asarray(1e-6)).atol) == 1e-6


@pytest.mark.heavy
def test_keywords_override_the_options():
    """`options=` with a keyword: the keyword replaces that field, the others stay (the
    clamped helix of the test above, with the 3-segment configuration compiled there)."""
    kappa, tau, phi, n, m = loaded_helix(ROD, 0.05, 0.02)
    length = 9.0
    s = jnp.linspace(0.0, length, NSAVE)
    exact_x, exact_frame = hr.helix_centreline(kappa, tau, s), hr.helix_frame(kappa, tau, phi, s)
    start, end = hr.Clamped(exact_x[0], exact_frame[0]), hr.Clamped(exact_x[-1], exact_frame[-1])
    options = hr.BoundaryValueOptions(segments=1, atol=1e-11)
    sol = solve(ROD, length, start, end, (n + 0.01, m - 0.01), options=options, segments=3)
    assert sol.segments == 3 and sol.node_position.shape == (3, 3)
    np.testing.assert_allclose(sol.tolerance, 10 * 1e-11, rtol=1e-15)  # atol from the options
    assert bool(sol.ok) and float(sol.residual) <= 1e-10
    np.testing.assert_allclose(sol.x, exact_x, atol=1e-8)
    assert options.segments == 1  # the options themselves are unchanged


# -- derivatives ----------------------------------------------------------------------------


@pytest.mark.heavy
def test_saved_states_differentiate_along_the_rod_the_length_and_the_saved_points():
    """The states at saved points carry the derivatives of the integration that saves them
    (`implicit`): along a stiffness, the length (which moves the pieces' saved points), a
    saved point itself (the Kirchhoff rates there) and the load, on one and three pieces."""
    rod0 = hr.Rod(1.0, 1.4, 0.8, K13=0.15, K23=-0.1, uhat=(0.3, 0.9, 0.35))
    tight = dict(atol=1e-12, ode_rtol=1e-12, ode_atol=1e-12, stability_pieces=0, throw=False)

    def outputs(p, segments):
        K3, length, s_moved, force = p
        rod = eqx.tree_at(lambda r: r.K3, rod0, K3)
        saveat = jnp.stack([0.0, 0.3 * length, s_moved, 0.9 * length])
        end = hr.Loaded((0.02 + force, 0.0, 0.05), (0.0, 0.03, 0.0))
        sol = hr.solve_boundary_value(rod, length, end=end, saveat=saveat, segments=segments, **tight)
        return jnp.concatenate([sol.x.ravel(), sol.frame.ravel(), sol.n.ravel(), sol.m.ravel(), sol.force])

    p0 = jnp.array([0.8, 6.0, 3.1, 0.01])
    for segments in (1, 3):
        f = jax.jit(lambda p: outputs(p, segments))
        J = jax.jit(jax.jacfwd(lambda p: outputs(p, segments)))(p0)
        eps = 1e-5
        fd = np.stack([(f(p0.at[i].add(eps)) - f(p0.at[i].add(-eps))) / (2 * eps) for i in range(4)], 1)
        # Central differences of values accurate to ~1e-12: ~1e-7 of noise.
        np.testing.assert_allclose(J, fd, rtol=1e-6, atol=2e-7)
        assert float(np.abs(fd[:, 2]).max()) > 0.1  # the saved point's own derivative is exercised


@pytest.mark.heavy
def test_gradients_through_the_boundary_value_solve_match_central_differences():
    length = 1.5 * TURN
    h0, theta0 = (float(a) for a in hr.unloaded_observables(SPRING, length))
    tight = dict(atol=1e-12, ode_rtol=1e-12, ode_atol=1e-12)
    # The differences are taken of solves 100x tighter: the derivatives are those of the
    # solution, and at the same tolerance the saved point's discretisation error (~2e-11,
    # smooth in K3) moved the differences by up to ~1e-8 (2e-6 relative), depending on the
    # step sequence; 100x tighter they agree to ~1e-10.
    tighter = dict(atol=1e-13, ode_rtol=1e-14, ode_atol=1e-14)  # arrays: no recompilation

    def outputs(K3, extension, tolerances=tight):
        rod = eqx.tree_at(lambda r: r.K3, SPRING, jnp.asarray(K3))  # an array: no recompilation
        start, end = hr.axial_ends(rod, length, extension=extension, rotation=theta0 + 0.2)
        sol = solve(rod, length, start, end, (jnp.zeros(3), jnp.zeros(3)), **tolerances)
        return jnp.concatenate([sol.force, sol.moment0, sol.x[NSAVE // 2]])

    x = (jnp.asarray(0.77), jnp.asarray(1.1 * h0))
    J = jax.jit(jax.jacfwd(outputs, argnums=(0, 1)))(*x)
    for i, eps in enumerate((1e-4, 1e-4)):
        plus = list(x)
        minus = list(x)
        plus[i] = plus[i] + eps
        minus[i] = minus[i] - eps
        fd = (outputs(*plus, tighter) - outputs(*minus, tighter)) / (2 * eps)
        np.testing.assert_allclose(J[i], fd, rtol=1e-6, atol=1e-8 * float(jnp.abs(fd).max()))
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
    for bad in ([0.0, 5.0, 4.0], [0.0, 11.0], [np.nan], [0.0, np.inf]):
        with pytest.raises(ValueError, match="saveat must be finite and increase strictly within"):
            hr.solve_boundary_value(SPRING, 10.0, end=end, saveat=jnp.array(bad))
    with pytest.raises(ValueError, match="adjoint"):
        hr.solve_boundary_value(SPRING, 10.0, end=end, adjoint=diffrax.RecursiveCheckpointAdjoint())
    with pytest.raises(ValueError, match="one rod"):
        hr.solve_boundary_value(hr.Rod(jnp.ones(2), 1.0, 1.0), 10.0, end=end)


@pytest.mark.heavy  # compiles the differentiated solve
def test_derivatives_through_the_ends_alone_and_eager_derivatives_with_turns():
    """d(force)/d(extension) with nothing of the rod differentiated (the ends' derivative
    alone), under jit and eagerly, and eager d(force)/d(K3) of a spring whose ends carry
    their total rotation: central differences agree."""
    length, rotation = 10.0, 10.64

    def pulled(extension):
        start, end = hr.axial_ends(SPRING, length, extension=extension, rotation=rotation)
        return hr.solve_boundary_value(SPRING, length, start=start, end=end, throw=False).force[2]

    def stiffer(K3):
        rod = hr.Rod(1.0, 1.0, K3, uhat=(0.0, 1.0, 0.3))
        start, end = hr.axial_ends(rod, length, extension=3.017, rotation=rotation)
        return hr.solve_boundary_value(rod, length, start=start, end=end, throw=False).force[2]

    h = 1e-6
    for f, x in ((pulled, 3.017), (stiffer, float(SPRING.K3))):
        central = (f(x + h) - f(x - h)) / (2 * h)
        np.testing.assert_allclose(jax.jacfwd(f)(x), central, rtol=1e-6)
    np.testing.assert_allclose(jax.jit(jax.jacfwd(pulled))(3.017), jax.jacfwd(pulled)(3.017), rtol=1e-12)


@pytest.mark.heavy  # compiles the vmapped solve
def test_traced_save_points_that_are_not_arc_lengths_of_the_rod_flag_their_point():
    """NaN, decreasing or outside [0, L]: flagged `invalid_input`, NaN fields; the others
    as solved alone."""
    rod, length = hr.Rod(1.0, 2.0, 0.8), 1.0
    end = hr.Loaded(force=(1e-3, 0.0, 0.0))

    def one(s1):
        sol = hr.solve_boundary_value(rod, length, end=end, saveat=jnp.stack([s1, 0.6]), throw=False)
        return sol.x, sol.ok, sol.valid_input, sol.result == hr.RESULTS.invalid_input

    x, ok, valid, invalid = jax.vmap(one)(jnp.array([0.5, jnp.nan, 0.9, -0.5, 0.6]))
    assert ok.tolist() == valid.tolist() == [True, False, False, False, False]
    assert invalid.tolist() == [False, True, True, True, True]
    assert np.all(np.isnan(np.asarray(x[1:])))
    alone = hr.solve_boundary_value(rod, length, end=end, saveat=jnp.array([0.5, 0.6]))
    np.testing.assert_allclose(x[0], alone.x, atol=1e-12)


@pytest.mark.heavy  # compiles the vmapped solve
def test_traced_frames_that_are_not_rotations_flag_their_point():
    """A traced start or end frame that is not a rotation (scaled, reflected) is flagged
    `invalid_input` with NaN fields, as `check_rotation` refuses a concrete one (it was
    solved, ok, with a wrong answer: a scaled start frame gave 4x the good point's force);
    the good point is as solved alone."""
    rod, length = SPRING, TURN
    h0, theta0 = (float(a) for a in hr.unloaded_observables(rod, length))
    start, end = hr.axial_ends(rod, length, extension=1.05 * h0, rotation=theta0 + 0.1)
    reflect = jnp.diag(jnp.array([1.0, 1.0, -1.0]))

    def one(start_frame, end_frame):
        sol = hr.solve_boundary_value(rod, length, start=hr.Clamped(start.position, start_frame),
                                      end=hr.Clamped(end.position, end_frame), throw=False)
        return sol.force, sol.ok, sol.result == hr.RESULTS.invalid_input

    starts = jnp.stack([start.frame, 0.5 * start.frame, start.frame @ reflect, start.frame])
    ends = jnp.stack([end.frame, end.frame, end.frame, end.frame @ reflect])
    force, ok, invalid = jax.vmap(one)(starts, ends)
    assert ok.tolist() == [True, False, False, False] and invalid.tolist() == [False, True, True, True]
    assert np.all(np.isnan(np.asarray(force[1:])))
    np.testing.assert_allclose(force[0], hr.solve_boundary_value(rod, length, start=start, end=end).force, atol=1e-10)
    with pytest.raises(ValueError, match="rotation"):
        hr.Clamped(start.position, 0.5 * start.frame)


def test_failed_solve_raises_with_throw_and_reports_without():
    """A clamped-clamped spring stretched far beyond its length has no solution."""
    length = 1.0 * TURN
    start, end = hr.axial_ends(SPRING, length, extension=2 * length, rotation=length * SPRING_NORM)
    sol = solve(SPRING, length, start, end, (jnp.zeros(3), jnp.zeros(3)), throw=False)
    assert not bool(sol.ok) and float(sol.residual) > 1e-3
    with pytest.raises(Exception, match="shooting equations were not solved"):
        jax.block_until_ready(solve(SPRING, length, start, end, (jnp.zeros(3), jnp.zeros(3))))


def test_failure_is_a_solver_error_naming_the_result():
    """The same failure: `SolverError` (a RuntimeError) naming the result's message and the
    hint (the traced case: tests/test_status.py)."""
    length = 1.0 * TURN
    start, end = hr.axial_ends(SPRING, length, extension=2 * length, rotation=length * SPRING_NORM)
    sol = solve(SPRING, length, start, end, (jnp.zeros(3), jnp.zeros(3)), throw=False)
    message = hr.RESULTS[sol.result]
    assert message  # not successful
    with pytest.raises(hr.SolverError, match="shooting equations were not solved") as error:
        solve(SPRING, length, start, end, (jnp.zeros(3), jnp.zeros(3)))
    assert message in str(error.value) and "throw=False" in str(error.value)
    assert isinstance(error.value, RuntimeError)


# -- slow -----------------------------------------------------------------------------------


@pytest.mark.heavy  # (~35 s; it was slow-only, and reverse mode broke unseen for a day)
def test_reverse_mode_with_direct_adjoint_matches_forward_mode():
    """`jax.jacrev` with `DirectAdjoint` equals `jax.jacfwd`: the implicit tangent of the
    shooting solve is linear in its right-hand side (`solve_small_linear`), so reverse mode
    can transpose it (with `solve_small`: "nonlinear div can't be transposed")."""
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
    linearised wrench flow with real part lambda > 0): single shooting from the bulk guess
    fails at 10 turns, five pieces solve it and satisfy the end conditions.  (The default
    guess falls back to homotopy continuation where the direct solve fails, and that
    reaches the same state with one piece.)"""
    length = 10 * TURN
    h0, theta0 = (float(a) for a in hr.unloaded_observables(SPRING, length))
    start, end = hr.axial_ends(SPRING, length, extension=1.1 * h0, rotation=theta0)
    single = hr.solve_boundary_value(SPRING, length, start=start, end=end, guess="helix", throw=False)
    multiple = hr.solve_boundary_value(SPRING, length, start=start, end=end, segments=5, throw=False)
    fallback = hr.solve_boundary_value(SPRING, length, start=start, end=end, throw=False)
    assert not bool(single.ok)
    for sol in (multiple, fallback):
        assert bool(sol.ok) and bool(sol.stable)
        np.testing.assert_allclose(sol.end_position, end.position, atol=1e-8)
        np.testing.assert_allclose(sol.end_frame, end.frame, atol=1e-8)
    assert fallback.continuation > 0 and fallback.segments == 1
    np.testing.assert_allclose(fallback.force, multiple.force, atol=1e-8)


@pytest.mark.heavy
def test_homotopy_continuation_and_the_fallbacks_that_use_it():
    """The homotopy path compiles and solves (its root finder's LAPACK solve lost its typed
    FFI call in XLA's conversion of that program, jaxlib 0.10.2: 'No registered
    implementation for untyped custom call to lapack_dgetrf_ffi'); so do the eager defaults
    that fall back to it: a point-loaded column past Euler's load, whose only state is the
    straight one (reported unstable), and a straight rod twisted by more than pi."""
    rod = hr.Rod(1.0, 1.5, 0.8)
    homotopy = hr.solve_boundary_value(rod, 1.0, end=hr.Loaded(force=jnp.array([0.0, 0.0, -1.0])), continuation=4)
    np.testing.assert_allclose(homotopy.force, [0.0, 0.0, -1.0], atol=1e-12)
    column = hr.solve_boundary_value(rod, 1.0, end=hr.Loaded(force=[0.0, 0.0, -3.0], point=[0.0, 0.0, 1.0]), throw=False)
    assert bool(column.ok) and int(column.instability_index) == 1
    start, end = hr.axial_ends(rod, 1.0, force=1.0, rotation=4.5)
    twisted = hr.solve_boundary_value(rod, 1.0, start=start, end=end)
    assert int(twisted.instability_index) == 0
    np.testing.assert_allclose(twisted.rotation, 4.5, atol=1e-9)
    np.testing.assert_allclose(twisted.moment0[2], 0.8 * 4.5, rtol=1e-9)  # K3 times the twist


_FLOAT32_SOLVE = """
import json, jax, jax.numpy as jnp
import helixrod as hr
spring = hr.Rod(1.0, 1.0, 1 / 1.3, uhat=(0.0, 1.0, 0.3))
start, end = hr.axial_ends(spring, 30.0, extension=12.0, rotation=30.0 * 1.044 + 0.5)
sol = hr.solve_boundary_value(spring, 30.0, start=start, end=end, segments=4)
print(json.dumps({"dtype": str(sol.force.dtype), "force": sol.force.tolist(), "ok": bool(sol.ok)}))
"""


_FLOAT32_HELPERS = """
import json, warnings, jax, jax.numpy as jnp
import helixrod as hr
from helixrod import dna
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    rod = hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
    held = hr.helices_under_load(rod, -0.49, 0.81, kappa_max=3.0, tau_range=(-3.0, 3.0))
    bulk = hr.bulk_helix(hr.Rod(1.0, 1.0, 1 / 1.3, uhat=(0.0, 1.0, 0.3)), 30.0, force=0.02, moment=0.05, throw=False)
    example = dna.load_tweezer_example().rod
    hat = dna.tweezer_response(example, 8000, 1.0, turns=jnp.array([-20.0, 0.0, 5.0, 20.0]))
    moduli = dna.tweezer_moduli(example, jnp.array([1.0, 10.0, 40.0]))
print(json.dumps({
    "warnings": [str(w.message) for w in caught if "float32" in str(w.message)], "dtype": str(bulk.extension.dtype),
    "held": int(held.valid.sum()), "bulk_ok": bool(bulk.ok), "bulk": float(bulk.extension),
    "hat": hat.extension.tolist(), "hat_ok": bool(hat.ok.all()), "S": moduli.stretch_modulus.tolist(),
}))
"""


@pytest.mark.heavy
def test_float32_reaches_its_own_tolerances_and_says_it_is_float32():
    """With x64 off (a subprocess) the solves with tolerances of their own ask float32 for
    what it can give (100 epsilons, `_misc.attainable`): helices_under_load found nothing
    (its 1e-10 on a float32 residual), bulk_helix and the tweezer model failed or gave NaN;
    now they agree with float64 to float32's precision.  One warning says float32 is in use."""
    import json
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    proc = subprocess.run([sys.executable, "-c", _FLOAT32_HELPERS], capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["dtype"] == "float32" and len(out["warnings"]) == 1 and "jax_enable_x64" in out["warnings"][0]
    example = hr.dna.load_tweezer_example().rod
    assert out["held"] == int(hr.helices_under_load(hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0)), -0.49, 0.81,
                                                    kappa_max=3.0, tau_range=(-3.0, 3.0)).valid.sum()) == 4
    bulk = hr.bulk_helix(hr.Rod(1.0, 1.0, 1 / 1.3, uhat=(0.0, 1.0, 0.3)), 30.0, force=0.02, moment=0.05)
    assert out["bulk_ok"] and out["bulk"] == pytest.approx(float(bulk.extension), rel=1e-5)
    hat = hr.dna.tweezer_response(example, 8000, 1.0, turns=jnp.array([-20.0, 0.0, 5.0, 20.0]))
    assert out["hat_ok"]
    np.testing.assert_allclose(out["hat"], hat.extension, rtol=1e-5)
    np.testing.assert_allclose(out["S"], hr.dna.tweezer_moduli(example, jnp.array([1.0, 10.0, 40.0])).stretch_modulus, rtol=1e-5)


@pytest.mark.heavy
def test_the_readme_spring_solves_in_float32():
    """With x64 off (a subprocess: the session runs in float64) the README's spring converges:
    the tolerances are raised to 100 float32 epsilons (`BoundaryValueOptions.for_dtype`) and
    the reaction agrees with float64 to float32's precision of the solve (1e-4)."""
    import json
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    proc = subprocess.run([sys.executable, "-c", _FLOAT32_SOLVE], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["dtype"] == "float32" and out["ok"]
    spring = hr.Rod(1.0, 1.0, 1 / 1.3, uhat=(0.0, 1.0, 0.3))
    start, end = hr.axial_ends(spring, 30.0, extension=12.0, rotation=30.0 * 1.044 + 0.5)
    reference = hr.solve_boundary_value(spring, 30.0, start=start, end=end, segments=4)
    np.testing.assert_allclose(out["force"], reference.force, rtol=1e-4, atol=1e-4 * float(jnp.linalg.norm(reference.force)))
    assert hr.BoundaryValueOptions().for_dtype(jnp.float64).atol == hr.BoundaryValueOptions().atol


@pytest.mark.heavy  # a 2-segment shooting program of its own: ~15 s to compile
def test_automatic_segments_follow_the_guess_growth_and_need_concrete_inputs():
    """`segments="auto"`: as many shooting pieces as the guess's spatial growth asks
    (`needed_segments`, more than one here), the twisted spring of 5 turns held one turn past
    its unloaded end under F = 0.1 solved stable with the bulk helix's moment; a traced
    input or another word is a clear error."""
    from helixrod._bvp._solve import needed_segments

    length = 5 * 2 * np.pi / np.hypot(1.0, 0.3)
    turned = float(hr.unloaded_observables(SPRING, length)[1]) + 2 * np.pi
    start, end = hr.axial_ends(SPRING, length, force=0.1, rotation=turned)
    sol = hr.solve_boundary_value(SPRING, length, start=start, end=end, segments="auto")
    needed, growth, _ = needed_segments(SPRING, length, start.condition(), end.condition(), None, "helix")
    assert sol.segments == needed >= 2 and growth > 3.0
    assert bool(sol.ok) and int(sol.instability_index) == 0
    bulk = hr.bulk_helix(SPRING, length, force=0.1, rotation=turned)
    np.testing.assert_allclose(float(sol.moment0[2]), float(bulk.moment), rtol=1e-3)
    np.testing.assert_allclose(float(sol.rotation), turned, rtol=1e-9)
    with pytest.raises(ValueError, match="concrete inputs"):
        jax.jit(lambda L: hr.solve_boundary_value(SPRING, L, end=end, segments="auto").force)(length)
    with pytest.raises(ValueError, match="'auto'"):
        hr.solve_boundary_value(SPRING, length, end=end, segments="many")


@pytest.mark.heavy  # a 5-segment continuation program of its own: ~10 s to compile
def test_a_stretched_spring_falls_back_to_more_segments():
    """The README's spring of 3 turns pulled by F = 1 (tweezer end, turned 0.5 rad past its
    unloaded end): single shooting from the bulk guess lands on an unstable state, and so do
    its pushes and its homotopy on one piece; the defaults then continue on the pieces the
    guess's spatial growth asks for (`needed_segments`, 5) to a stable state that meets the
    end's frame, force and whole turns."""
    from helixrod._bvp._solve import needed_segments

    length = 3 * 2 * np.pi / np.hypot(1.0, 0.3)
    turned = float(hr.unloaded_observables(SPRING, length)[1]) + 0.5
    start, end = hr.axial_ends(SPRING, length, force=1.0, rotation=turned)
    direct = hr.solve_boundary_value(SPRING, length, start=start, end=end, guess="helix", throw=False)
    assert bool(direct.ok) and int(direct.instability_index) > 0
    sol = hr.solve_boundary_value(SPRING, length, start=start, end=end)
    needed = needed_segments(SPRING, length, start.condition(), end.condition(), None, "helix")[0]
    assert sol.segments == needed == 5 and sol.continuation > 0
    assert bool(sol.ok) and bool(sol.stable) and int(sol.instability_index) == 0
    np.testing.assert_allclose(sol.force, [0.0, 0.0, 1.0], atol=1e-8)
    np.testing.assert_allclose(sol.end_frame, end.frame, atol=1e-8)
    np.testing.assert_allclose(float(sol.rotation), turned, atol=1e-8)
    assert float(direct.end_position[2]) < 1.0 < 14.0 < float(sol.end_position[2]) < length
