"""The host-driven Gauss--Newton loop (`stepwise_least_squares`) against the loop it copies,
`optimistix.least_squares` on the composed residuals: the same iterates, steps and result
codes, the model evaluated only through the caller's residuals-and-Jacobian function."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from helixrod._fit._solvers import make_solver, with_materialised_jacobian
from helixrod._fit._stepwise import steppable, stepwise_least_squares
from helixrod._status import promote, result_name

T = np.linspace(0.0, 1.0, 40)
DATA = 3.0 * (1 + 0.4 * T) * np.exp(-1.3 * T) + 1e-3 * np.random.default_rng(1).normal(size=T.size)


def residuals(q):
    return 3.0 * (1 + q[0] * T) * jnp.exp(q[1] * T) - DATA


def physical(z):
    """Internal coordinates to the model's values: a nonlinear map, as a fit's bounds give."""
    return jnp.stack([z[0], -jnp.exp(z[1])])


def jacobian_at(q, calls=None):
    if calls is not None:
        calls.append(np.asarray(q))
    return residuals(q), jax.jacfwd(residuals)(q), None


def reference(solver, z0, max_steps):
    """optimistix's own loop, on the residuals with their Jacobian materialised (the
    pipeline's optimistix path): the same linear algebra as the stepwise loop."""
    composed = with_materialised_jacobian(lambda z, _: residuals(physical(z)))
    sol = optx.least_squares(composed, solver, jnp.asarray(z0), max_steps=max_steps, throw=False)
    return sol.value, promote(sol.result), int(sol.stats["num_steps"])


# optimistix's own solvers with tolerances above round-off: at round-off their stopping is
# decided by rounding (see test_fit_solvers), and two exact loops part there.
SOLVERS = {
    "helixrod LM": make_solver("levenberg-marquardt", 1e-10, 1e-12, 1e-2),
    "optimistix LM": optx.LevenbergMarquardt(rtol=1e-7, atol=1e-9),
    "Gauss-Newton": optx.GaussNewton(rtol=1e-7, atol=1e-9),
    "dogleg": optx.Dogleg(rtol=1e-7, atol=1e-9),
}


@pytest.mark.parametrize(("name", "z0"), [(name, (1.0, 0.5)) for name in SOLVERS] + [("helixrod LM", (0.5, -0.5))])
def test_same_iterates_and_minimum_as_optimistix(name, z0):
    """The first steps (each loop cut off after k steps) agree to round-off; once the loss
    changes at round-off only, accepting or rejecting a step is decided by rounding, which
    differs between the two programs: there the loops may stop some steps apart, at the
    same minimum."""
    solver = SOLVERS[name]
    assert steppable(solver)
    for k in (2, 4):
        z, _, _, steps = stepwise_least_squares(jacobian_at, physical, jnp.asarray(z0), solver, k)
        z_ref, _, steps_ref = reference(solver, z0, k)
        assert int(steps) == steps_ref
        np.testing.assert_allclose(np.asarray(z), np.asarray(z_ref), rtol=1e-10, atol=1e-12)
    calls = []
    z, cost, result, steps = stepwise_least_squares(lambda q: jacobian_at(q, calls), physical, jnp.asarray(z0), solver, 100)
    z_ref, result_ref, steps_ref = reference(solver, z0, 100)
    assert result_name(result) == result_name(result_ref) == "successful"
    np.testing.assert_allclose(np.asarray(z), np.asarray(z_ref), rtol=1e-6)
    r = np.asarray(residuals(physical(z)))
    assert float(cost) == pytest.approx(0.5 * r @ r, rel=1e-10)
    # One model evaluation per step, and the one asked for before the last step's verdict.
    assert len(calls) == int(steps) + 1


def test_moving_sigmas_are_held_across_steps_and_solved_again_to_orears_fixed_point():
    """Errors in variables (effective variance, Orear 1982): each residual over a sigma
    that moves with the parameters through the model's slope, the Jacobian holding it
    fixed.  The loop ends at the fixed point of least squares with the weights of its own
    solution -- found here independently by scipy's least squares iterated with fixed
    weights -- where the fixed-weight gradient vanishes."""
    from scipy.optimize import least_squares

    sigma_y, sigma_x = 1e-2, 0.05

    def model(q):
        return 3.0 * (1 + q[0] * T) * jnp.exp(q[1] * T)

    def sigma_of(q):
        slope = 3.0 * jnp.exp(q[1] * T) * (q[0] + q[1] * (1 + q[0] * T))  # d model / d T
        return jnp.sqrt(sigma_y**2 + (slope * sigma_x) ** 2)

    calls = []

    def moving_jacobian_at(q):
        calls.append(np.asarray(q))
        sigma = sigma_of(q)
        held = lambda q: (model(q) - DATA) / jax.lax.stop_gradient(sigma_of(q))  # noqa: E731
        return (model(q) - DATA) / sigma, jax.jacfwd(held)(q), sigma

    solver = SOLVERS["helixrod LM"]
    z, cost, result, steps = stepwise_least_squares(moving_jacobian_at, physical, jnp.asarray([1.0, 0.5]), solver, 200)
    assert result_name(result) == "successful"
    # One model evaluation per step and the one asked for before the last verdict, as
    # without moving sigmas: each solution's sigmas come from the evaluation accepted there.
    assert len(calls) == int(steps) + 1
    q = np.asarray(physical(z))
    r, J, sigma = (np.asarray(a) for a in moving_jacobian_at(jnp.asarray(q)))
    assert np.max(np.abs(J.T @ r)) < 1e-8 * np.linalg.norm(J, axis=0).max() * np.linalg.norm(r)
    assert float(cost) == pytest.approx(0.5 * r @ r, rel=1e-8)

    q_ref = np.array([0.4, -1.3])
    for _ in range(50):
        weights = np.asarray(sigma_of(jnp.asarray(q_ref)))
        fixed = lambda q, w=weights: (np.asarray(model(jnp.asarray(q))) - DATA) / w  # noqa: E731
        q_next = least_squares(fixed, q_ref, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15).x
        done = np.max(np.abs(q_next - q_ref)) < 1e-14
        q_ref = q_next
        if done:
            break
    np.testing.assert_allclose(q, q_ref, rtol=1e-7)
    # Not the minimum of the cost with moving weights: the held weights are what differ.
    moving = least_squares(lambda q: np.asarray((model(jnp.asarray(q)) - DATA) / sigma_of(jnp.asarray(q))), q_ref, method="lm").x
    assert np.max(np.abs(moving - q_ref) / np.abs(q_ref)) > 1e-6


def test_moving_sigmas_that_do_not_settle_are_flagged():
    """Two observations +1 and -1 of one value q with sigmas exp(2q) and exp(-2q): with the
    weights of a point q the least-squares value is -tanh(4q), whose slope at the fixed
    point q = 0 is -4, so Orear's iteration leaves it and alternates between q ~ +-1.  The
    loop stops after `HELD_WEIGHTS_ROUNDS` solves and says so."""
    from helixrod._fit._stepwise import HELD_WEIGHTS_ROUNDS

    y = np.array([1.0, -1.0])
    calls = []

    def sigma_of(q):
        return jnp.exp(jnp.array([2.0, -2.0]) * q[0])

    def moving_jacobian_at(q):
        calls.append(float(q[0]))
        held = lambda q, s=sigma_of(q): (q[0] - y) / s  # noqa: E731
        return held(q), jax.jacfwd(held)(q), sigma_of(q)

    z, cost, result, steps = stepwise_least_squares(
        moving_jacobian_at, lambda z: z, jnp.asarray([0.3]), SOLVERS["helixrod LM"], 10_000
    )
    assert result_name(result) == "weights_not_settled"
    assert int(steps) < 10_000
    # It alternated: the last solutions are near +-tanh(4 q) = -+q, q ~ 0.9993.
    assert abs(abs(float(z[0])) - 0.99933) < 1e-3
    solutions = [q for q in calls if abs(abs(q) - 0.99933) < 1e-3]
    assert len(solutions) >= HELD_WEIGHTS_ROUNDS - 2 and {np.sign(q) for q in solutions} == {1.0, -1.0}


def test_max_steps_reached_is_reported_as_optimistix_does():
    solver = SOLVERS["helixrod LM"]
    z, cost, result, steps = stepwise_least_squares(jacobian_at, physical, jnp.asarray([2.0, 1.5]), solver, 2)
    z_ref, result_ref, steps_ref = reference(solver, (2.0, 1.5), 2)
    assert result_name(result) == result_name(result_ref) == "nonlinear_max_steps_reached"
    assert int(steps) == steps_ref == 2
    np.testing.assert_allclose(np.asarray(z), np.asarray(z_ref), rtol=1e-12)
    assert np.isfinite(float(cost))


def test_a_nonfinite_start_is_flagged_without_evaluating_the_model():
    calls = []
    z, cost, result, steps = stepwise_least_squares(
        lambda q: jacobian_at(q, calls), physical, jnp.asarray([np.nan, 0.0]), SOLVERS["helixrod LM"], 10
    )
    assert result_name(result) == "nonfinite" and float(cost) == np.inf and int(steps) == 0 and not calls


def test_a_model_that_fails_at_the_start_ends_not_successful():
    nan_jacobian = lambda q: (jnp.full(T.size, jnp.nan), jnp.full((T.size, 2), jnp.nan), None)
    z, cost, result, steps = stepwise_least_squares(nan_jacobian, physical, jnp.asarray([0.0, 0.0]), SOLVERS["helixrod LM"], 10)
    sol = optx.least_squares(lambda z, _: jnp.full(T.size, jnp.nan) * z[0], SOLVERS["helixrod LM"], jnp.zeros(2), max_steps=10, throw=False)
    assert result_name(result) == result_name(promote(sol.result)) != "successful"
    assert float(cost) == np.inf


def test_only_gauss_newton_type_solvers_are_steppable():
    assert not steppable(optx.BFGS(rtol=1e-8, atol=1e-8))
    assert not steppable(make_solver("lbfgs", 1e-8, 1e-8, 1e-2))
    assert steppable(make_solver("gauss-newton", 1e-8, 1e-8, 1e-2))


@pytest.mark.heavy
def test_a_tweezer_fit_takes_the_same_steps_as_the_optimistix_loop(monkeypatch):
    """`fit_stiffness` of a forward model that is a solve of its own (a tweezer response)
    drives the solver stepwise; with the stepwise path turned off the pipeline runs
    optimistix's loop in one compiled program: the same fit, start by start (the last steps,
    at round-off, may differ in number: the two programs round differently)."""
    import helixrod as hr
    from helixrod import dna
    from helixrod._fit import _pipeline

    rod = dna.load_tweezer_example().rod
    forces = np.geomspace(0.1, 30.0, 24)
    clean = dna.tweezer_response(rod, 8000, forces, torque=0.0, persistence_length=48.0).extension
    extension = np.asarray(clean) + 3.0 * np.random.default_rng(2).normal(size=forces.size)
    data = dna.TweezerData.from_arrays(forces, extension, extension_sigma=3.0, torque=np.zeros(forces.size), n_bp=8000)
    fix = {"K1": float(rod.K1), "K13": 0.0, "K3": float(rod.K3), "K23": float(rod.K23), "plectoneme_twist_persistence": 24.0}
    fit = lambda: hr.fit_stiffness(data, uhat=rod.uhat, init=rod, fix=fix, n_starts=2)
    stepwise = fit()
    monkeypatch.setattr(_pipeline, "steppable", lambda solver: False)
    looped = fit()
    assert stepwise.ok and looped.ok
    np.testing.assert_array_equal(np.asarray(stepwise.start_costs) > 0, True)
    np.testing.assert_allclose(np.asarray(stepwise.start_costs), np.asarray(looped.start_costs), rtol=1e-9)
    assert abs(int(stepwise.n_steps) - int(looped.n_steps)) <= 3
    for name in stepwise.params:
        assert float(stepwise.params[name]) == pytest.approx(float(looped.params[name]), rel=1e-8), name


def _fit_compiling(jacobian_at, max_steps):
    """A stepwise fit of the test model with `jacobian_at`, and JAX's log messages of its
    compilations."""
    import logging

    records = []

    class Keep(logging.Handler):
        def emit(self, record):
            records.append(record.getMessage())

    handler, logger = Keep(), logging.getLogger("jax")
    logger.addHandler(handler)
    solver = make_solver("levenberg-marquardt", 1e-10, 1e-12, 1e-2)
    try:
        with jax.log_compiles(True):
            _, _, result, steps = stepwise_least_squares(jacobian_at, physical, jnp.asarray([1.0, 0.5]), solver, max_steps)
    finally:
        logger.removeHandler(handler)
    assert int(steps) > 2 and result_name(result) == "successful"
    return records


def _compilations(records, name):
    return sum(f"Compiling jit({name})" in message for message in records)


def test_one_compiled_step_whatever_device_placement_the_model_returns():
    """A model whose results come committed to a device (a program exported by the trace
    cache returns such) and a start that is not: the step is compiled once, not again for
    the inputs' changed placement."""
    t = T[:37]  # shapes of its own: the step is compiled here, whatever ran before

    def committed_jacobian_at(q):
        model = lambda q: 3.0 * (1 + q[0] * t) * jnp.exp(q[1] * t) - DATA[:37]  # noqa: E731
        return jax.device_put((model(q), jax.jacfwd(model)(q)), jax.devices()[0]) + (None,)

    records = _fit_compiling(committed_jacobian_at, 20)
    assert _compilations(records, "_step") == 1, [m for m in records if "_step" in m]


def test_one_compiled_model_whatever_placement_the_steps_return():
    """A model program that returns uncommitted results (a plain `jax.jit`, the trace cache
    off): the points the steps hand it stay uncommitted as its start was, and it is compiled
    once (committing the steps' inputs had it compiled again at the second point: the shape
    fit's Jacobian program, 12-14 s of XLA each)."""
    t = T[:33]  # shapes of their own: compiled here, whatever ran before

    @jax.jit
    def plain_model(q):
        model = lambda q: 3.0 * (1 + q[0] * t) * jnp.exp(q[1] * t) - DATA[:33]  # noqa: E731
        return model(q), jax.jacfwd(model)(q), None

    records = _fit_compiling(plain_model, 100)
    assert _compilations(records, "plain_model") == 1, [m for m in records if "plain_model" in m]
    assert _compilations(records, "_step") == 1, [m for m in records if "_step" in m]
