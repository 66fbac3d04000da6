"""helixrod's ODE loop (`_ode.solve_ode`): the steps, counts and saved values diffrax's own
loop and saving give, through rejected steps, failed solves, `vmap` and
forward-mode derivatives, and no host callback in `solve_static`'s program."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import KIRCHHOFF_ROD, M0, N0, tree_allclose

import helixrod as hr
from helixrod._ode import solve_ode

TS = jnp.linspace(0.0, 6.0, 41)


def van_der_pol(t, y, mu):
    x, v = y
    return jnp.stack([v, mu * (1.0 - x**2) * v - x])


def solve(ts, mu, y0, *, ours: bool, max_steps=4096):
    """Dopri5 on a stiff-ish Van der Pol oscillator (many rejected steps), saved at `ts`."""
    kwargs = dict(
        args=mu, stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-8), max_steps=max_steps,
        adjoint=diffrax.ForwardMode(),
    )
    term, solver = diffrax.ODETerm(van_der_pol), diffrax.Dopri5()
    if ours:
        ys, result, stats = solve_ode(term, solver, 0.0, 6.0, 0.01, y0, ts=ts, **kwargs)
        return ys, stats["num_rejected_steps"], result
    sol = diffrax.diffeqsolve(term, solver, 0.0, 6.0, 0.01, y0, saveat=diffrax.SaveAt(ts=ts), throw=False, **kwargs)
    return sol.ys, sol.stats["num_rejected_steps"], sol.result


Y0 = jnp.array([2.0, 0.0])


def test_the_values_of_diffrax_saving_through_rejected_steps():
    ours, rejected, result = jax.jit(lambda ts: solve(ts, 6.0, Y0, ours=True))(TS)
    theirs, rejected_theirs, _ = jax.jit(lambda ts: solve(ts, 6.0, Y0, ours=False))(TS)
    assert int(rejected) == int(rejected_theirs) > 10 and result == diffrax.RESULTS.successful
    np.testing.assert_array_equal(np.asarray(ours), np.asarray(theirs))
    # Save points at the ends and several within one step.
    crowded = jnp.concatenate([jnp.zeros(1), jnp.linspace(1.0, 1.001, 7), jnp.full(1, 6.0)])
    np.testing.assert_array_equal(
        np.asarray(jax.jit(lambda ts: solve(ts, 6.0, Y0, ours=True))(crowded)[0]),
        np.asarray(jax.jit(lambda ts: solve(ts, 6.0, Y0, ours=False))(crowded)[0]),
    )


def test_a_failed_solve_leaves_the_unreached_points_at_infinity_as_diffrax_does():
    ours, _, result = solve(TS, 6.0, Y0, ours=True, max_steps=20)
    theirs, _, _ = solve(TS, 6.0, Y0, ours=False, max_steps=20)
    assert result == diffrax.RESULTS.max_steps_reached
    assert np.isinf(np.asarray(ours)[-1]).all() and np.isfinite(np.asarray(ours)[0]).all()
    np.testing.assert_array_equal(np.asarray(ours), np.asarray(theirs))


def test_a_state_of_several_shapes_and_dtypes_is_saved_as_diffrax_saves_it():
    """The saved points are kept as rows of one buffer: a pytree state of a scalar, a
    matrix and a float32 vector comes back shaped and typed as diffrax's saving gives it."""

    def field(t, y, mu):
        x, v = y["xv"][0], y["xv"][1]
        return dict(xv=jnp.stack([v, mu * (1.0 - x**2) * v - x]), rotation=y["rotation"] * v,
                    slow=jnp.full(3, x, jnp.float32), scalar=-y["scalar"])

    y0 = dict(xv=Y0, rotation=jnp.eye(2), slow=jnp.arange(3, dtype=jnp.float32), scalar=jnp.asarray(1.0))
    kwargs = dict(args=3.0, stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-8),
                  adjoint=diffrax.ForwardMode(), max_steps=4096)
    ours, _, _ = solve_ode(diffrax.ODETerm(field), diffrax.Dopri5(), 0.0, 6.0, 0.01, y0, ts=TS, **kwargs)
    theirs = diffrax.diffeqsolve(diffrax.ODETerm(field), diffrax.Dopri5(), 0.0, 6.0, 0.01, y0,
                                 saveat=diffrax.SaveAt(ts=TS), throw=False, **kwargs).ys
    for name in y0:
        assert ours[name].shape == theirs[name].shape == TS.shape + y0[name].shape
        assert ours[name].dtype == theirs[name].dtype
        np.testing.assert_array_equal(np.asarray(ours[name]), np.asarray(theirs[name]))


def test_vmap_and_forward_mode_derivatives():
    mus = jnp.array([0.5, 3.0, 6.0])
    batched = jax.vmap(lambda mu: solve(TS, mu, Y0, ours=True)[0])(mus)
    for mu, ys in zip(mus, batched):
        np.testing.assert_array_equal(np.asarray(ys), np.asarray(solve(TS, mu, Y0, ours=False)[0]))
    jacobian = jax.jacfwd(lambda y0: solve(TS, 3.0, y0, ours=True)[0])(Y0)
    np.testing.assert_allclose(jacobian, jax.jacfwd(lambda y0: solve(TS, 3.0, y0, ours=False)[0])(Y0), rtol=0, atol=1e-12)


def test_solve_static_with_saved_points_carries_no_host_callback():
    """Its program can be kept by JAX's persistent compilation cache (a host callback
    would keep it out: diffrax checks `SaveAt(ts)` with one), in the default solve and in
    its derivative."""
    solve_static = lambda ts: hr.solve_static(KIRCHHOFF_ROD, N0, M0, 6.0, saveat=ts, outputs=("frame",), throw=False).frame  # noqa: E731
    assert "callback" not in jax.jit(solve_static).lower(TS).as_text()
    assert "callback" not in jax.jit(jax.jacfwd(lambda ts: solve_static(ts)[-1])).lower(TS).as_text()


def _rod_solve(solver, controller, dt0, *, ours: bool, max_steps=4096):
    """The rod's own integration (`solve_static`'s term over the unit interval, saved at the end)."""
    from helixrod._kirchhoff import _body_velocity_per_unit_length
    from helixrod._lie import BodyVelocityTerm, RodState

    y0 = RodState(N0 + jnp.array([0.1, -0.2, 0.3]), M0, jnp.eye(3), jnp.zeros(3))
    term = BodyVelocityTerm(_body_velocity_per_unit_length)
    kwargs = dict(args=(KIRCHHOFF_ROD, jnp.asarray(40.0)), stepsize_controller=controller, max_steps=max_steps,
                  adjoint=diffrax.ForwardMode())
    if ours:
        ys, result, stats = solve_ode(term, solver, 0.0, np.ones(()), dt0, y0, ts=None, **kwargs)
    else:
        sol = diffrax.diffeqsolve(term, solver, 0.0, np.ones(()), dt0, y0, throw=False, **kwargs)
        ys, result, stats = sol.ys, sol.result, sol.stats
    return ys, result, {name: stats[name] for name in ("num_steps", "num_accepted_steps", "num_rejected_steps")}


def test_the_rods_steps_end_and_counts_are_diffraxs():
    """The geometric solvers, adaptive (first step chosen by the controller, a largest step)
    and constant steps, saved at the end only, without a cap on the steps (`max_steps=None`)
    and cut short by `max_steps`: the
    same counts and result codes as `diffrax.diffeqsolve` and the same states."""
    cases = [
        (hr.MuntheKaasRK(diffrax.Dopri8()), diffrax.PIDController(rtol=1e-9, atol=1e-11, dtmax=0.05), None, 4096),
        (hr.CommutatorFreeRK4(), diffrax.PIDController(rtol=1e-6, atol=1e-8), None, 4096),
        (hr.CommutatorFreeRK4(), diffrax.ConstantStepSize(), 1 / 37, 4096),
        (hr.MuntheKaasRK(diffrax.Dopri8()), diffrax.PIDController(rtol=1e-9, atol=1e-11), None, None),
        (hr.MuntheKaasRK(diffrax.Dopri8()), diffrax.PIDController(rtol=1e-12, atol=1e-12), None, 5),
    ]
    for solver, controller, dt0, max_steps in cases:
        ours = jax.jit(lambda: _rod_solve(solver, controller, dt0, ours=True, max_steps=max_steps))()
        theirs = jax.jit(lambda: _rod_solve(solver, controller, dt0, ours=False, max_steps=max_steps))()
        # The same steps and counts; the states to round-off (XLA may fuse the arithmetic of
        # the two programs differently: 4e-12 after the 1383 steps of the second case).
        assert tree_allclose(ours[1:], theirs[1:])
        assert int(ours[2]["num_steps"]) >= 5 and tree_allclose(ours[0], theirs[0], rtol=1e-10)
    assert ours[1] == diffrax.RESULTS.max_steps_reached


def test_times_must_be_constant_and_increasing():
    term = diffrax.ODETerm(van_der_pol)
    kwargs = dict(ts=None, args=1.0, stepsize_controller=diffrax.PIDController(rtol=1e-6, atol=1e-6),
                  adjoint=diffrax.ForwardMode(), max_steps=64)
    with pytest.raises(ValueError, match="t0 to t1"):
        solve_ode(term, diffrax.Dopri5(), 1.0, 0.0, None, Y0, **kwargs)
    with pytest.raises(ValueError, match="t1 must be a constant"):
        jax.jit(lambda t1: solve_ode(term, diffrax.Dopri5(), 0.0, t1, None, Y0, **kwargs)[0])(1.0)


def test_steps_that_land_on_the_saved_points_as_diffraxs():
    """A controller that makes the steps land on the saved points (`step_ts`, what
    `solve_static(..., interpolate=False)` asks for): the same steps and values as diffrax's
    loop with `SaveAt(ts)`; and through `solve_static`, the saved values of the
    interpolated solve to its tolerance, with a step ending at each point."""
    ts = jnp.linspace(0.0, 6.0, 13)
    controller = diffrax.PIDController(rtol=1e-8, atol=1e-8, step_ts=ts)
    kwargs = dict(args=3.0, stepsize_controller=controller, max_steps=4096, adjoint=diffrax.ForwardMode())
    ours, result, stats = jax.jit(lambda: solve_ode(diffrax.ODETerm(van_der_pol), diffrax.Dopri5(), 0.0, 6.0, 0.01, Y0, ts=ts, **kwargs))()
    sol = jax.jit(lambda: diffrax.diffeqsolve(diffrax.ODETerm(van_der_pol), diffrax.Dopri5(), 0.0, 6.0, 0.01, Y0,
                                              saveat=diffrax.SaveAt(ts=ts), throw=False, **kwargs))()
    assert result == diffrax.RESULTS.successful and int(stats["num_steps"]) == int(sol.stats["num_steps"])
    assert tree_allclose(ours, sol.ys, rtol=1e-12)
    s = jnp.linspace(0.0, 6.0, 9)
    landed = hr.solve_static(KIRCHHOFF_ROD, N0, M0, 6.0, saveat=s, interpolate=False)
    interpolated = hr.solve_static(KIRCHHOFF_ROD, N0, M0, 6.0, saveat=s)
    assert int(landed.num_steps) > int(interpolated.num_steps)
    np.testing.assert_allclose(landed.m, interpolated.m, atol=1e-9)
