"""The default multistart of helix fits: starts solved one after another with early stopping
once two agree on the best minimum (`_pipeline._adaptive_multistart`)."""

import jax
import numpy as np
import pytest
from helpers import parameter_vector

import helixrod as hr
from helixrod._fit import _pipeline


def _problem(seed, n=40, noise=0.01):
    """A random rod as in `benchmarks/bench_fit.py --problems` (uhat known, K1 <= K2,
    couplings), n random helices, noise on F and M."""
    rng = np.random.default_rng(seed)
    K1 = float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))))
    K2 = K1 * float(np.exp(rng.uniform(0.0, np.log(3.0))))
    K3 = float(np.exp(rng.uniform(np.log(0.4), np.log(1.6))))
    while True:
        c13, c23 = rng.uniform(-0.6, 0.6, 2)
        K13, K23 = float(c13 * np.sqrt(K1 * K3)), float(c23 * np.sqrt(K2 * K3))
        if K3 - K13**2 / K1 - K23**2 / K2 > 0.2 * K3:
            break
    uhat = (float(rng.uniform(0.5, 1.5)), float(rng.normal(0, 0.3)), float(rng.normal(0, 0.3)))
    rod = hr.Rod(K1, K2, K3, K13=K13, K23=K23, uhat=uhat)
    kappa, tau = rng.uniform(0.3, 2.5, n), rng.uniform(-1.5, 2.0, n)
    return rod, hr.synthetic_helix_data(rod, kappa, tau, noise, jax.random.key(seed))


@pytest.mark.parametrize("seed", [1000, 1004, 1007])
def test_early_stop_finds_the_full_runs_minimum(seed):
    rod, data = _problem(seed)
    fit = hr.fit_stiffness(data, uhat=rod.uhat)
    full = hr.fit_stiffness(data, uhat=rod.uhat, n_starts=32)
    assert fit.ok and full.ok
    assert full.n_starts == 32 and full.start_costs.shape == (32,)
    assert _pipeline.ADAPTIVE_LEAST <= fit.n_starts < 32 and fit.start_costs.shape == (fit.n_starts,)
    assert fit.n_agree >= _pipeline.ADAPTIVE_AGREE
    assert abs(float(fit.cost) - float(full.cost)) <= 1e-9 * float(full.cost)
    scale = np.abs(parameter_vector(full.rod)[:5]).max()
    np.testing.assert_allclose(parameter_vector(fit.rod), parameter_vector(full.rod), rtol=0, atol=1e-6 * scale)
    # Deterministic: the same fit again.
    again = hr.fit_stiffness(data, uhat=rod.uhat)
    assert again.n_starts == fit.n_starts and float(again.cost) == float(fit.cost)


def test_early_stop_recovers_noise_free_truth():
    for seed in (2000, 2001):
        rod, data = _problem(seed, noise=0.0)
        fit = hr.fit_stiffness(data, uhat=rod.uhat)
        assert fit.ok and fit.cost < 1e-20 and fit.n_starts < 32
        truth = parameter_vector(rod)
        np.testing.assert_allclose(parameter_vector(fit.rod), truth, rtol=0, atol=1e-8 * np.abs(truth[:5]).max())


def test_explicit_n_starts_runs_exactly_that_many():
    rod, data = _problem(1000)
    for n in (1, 5):
        fit = hr.fit_stiffness(data, uhat=rod.uhat, n_starts=n)
        assert fit.n_starts == n and fit.start_costs.shape == (n,)


def test_progress_reaches_the_total_after_an_early_stop():
    rod, data = _problem(1000)
    calls = []
    fit = hr.fit_stiffness(data, uhat=rod.uhat, progress=lambda done, total: calls.append((done, total)))
    assert fit.n_starts < 32
    assert calls[-1] == (33, 33) and all(t == 33 for _, t in calls)
    assert [d for d, _ in calls] == sorted(d for d, _ in calls)


def test_a_converged_start_at_the_best_minimum_is_preferred():
    """Of two starts at the same minimum (cost within round-off), the reported one is the
    converged one, even where the other's cost is lower by round-off."""
    rod, data = _problem(1000)
    fit = hr.fit_stiffness(data, uhat=rod.uhat, n_starts=1)
    model, param = fit.problem.model, fit.problem.parameterisation
    p = parameter_vector(fit.rod)
    p_all = np.stack([p, p, p * 1.5])
    cost = float(fit.cost) * np.array([1.0, 1.0 + 1e-12, 2.0])
    codes = jax.vmap(lambda ok: hr.RESULTS.where(ok, hr.RESULTS.successful, hr.RESULTS.max_steps_reached))
    results = codes(jax.numpy.array([False, True, True]))
    best, count, p_best = _pipeline._agreement(p_all, cost, model, param, results)
    assert best == 1 and count == 2
    np.testing.assert_allclose(p_best, p)
    # Without a converged start at the minimum, the lowest cost stays the best.
    results = codes(jax.numpy.array([False, False, True]))
    assert _pipeline._agreement(p_all, cost, model, param, results)[:2] == (0, 2)


def test_the_compiled_early_stop_counts_agreeing_costs(compilations):
    """`_starts_until_agreement` solves starts in order until `least` are solved and two of
    them (the earlier calls' best cost counting as one) reach the best cost, within `count`:
    identical starts reach identical costs."""
    rod, data = _problem(1000)
    fit = hr.fit_stiffness(data, uhat=rod.uhat, n_starts=1)
    problem = fit.problem
    param = problem.parameterisation
    z0 = np.asarray(param.starts(param.internal(parameter_vector(fit.rod)), 1, jax.random.key(0))[0])
    z0s = np.stack([z0] * 6)

    def solved(count, least, prior=np.inf):
        rows, n = _pipeline._starts_until_agreement(
            z0s, np.int32(count), np.int32(least), np.asarray(prior), problem.model, param, problem.solver,
            _pipeline.SCREEN_STEPS,
        )
        return int(n), np.asarray(rows[1])

    n, costs = solved(6, 0)
    assert n == 2 and costs[0] == costs[1] and np.all(np.isinf(costs[2:]))
    compiled = len(compilations)  # the counts and the prior are arrays: one program for all
    assert solved(6, 4)[0] == 4 and solved(3, 5)[0] == 3
    assert solved(6, 0, prior=float(costs[0]))[0] == 1  # agrees with an earlier call's best
    assert solved(6, 0, prior=0.5 * float(costs[0]))[0] == 6  # never reaches it
    assert len(compilations) == compiled
