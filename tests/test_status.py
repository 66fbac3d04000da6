"""helixrod._status: RESULTS extends diffrax's and optimistix's codes, SolverError, and the
throw= behaviour of `raise_if_failed` (eager: SolverError naming the failure; traced: an
error when the program runs)."""

import re

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import helixrod as hr
from helixrod._status import ok_of, raise_if_failed, succeeded


def codes(mask, if_true, if_false):
    """A batch of result codes (`where` takes a scalar predicate: vmapped, as in a batch of
    solves)."""
    return jax.vmap(lambda m: if_true._enumeration.where(m, if_true, if_false))(mask)


def test_results_promote_optimistix_and_diffrax_codes():
    for code, name in [
        (optx.RESULTS.successful, "successful"),
        (optx.RESULTS.max_steps_reached, "max_steps_reached"),
        (optx.RESULTS.nonlinear_divergence, "nonlinear_divergence"),
        (diffrax.RESULTS.max_steps_reached, "max_steps_reached"),
        (diffrax.RESULTS.event_occurred, "event_occurred"),
    ]:
        promoted = hr.RESULTS.promote(code)
        assert isinstance(promoted, type(hr.RESULTS.successful)) and promoted._enumeration is hr.RESULTS
        assert bool(promoted == getattr(hr.RESULTS, name)), name
        assert hr.RESULTS[promoted] == code._enumeration[code]  # the message passes through
    assert hr.RESULTS[hr.RESULTS.successful] == ""
    assert "rejected" in hr.RESULTS[hr.RESULTS.invalid_input]
    # Batched codes promote elementwise.
    batch = codes(jnp.array([True, False]), diffrax.RESULTS.successful, diffrax.RESULTS.max_steps_reached)
    assert (hr.RESULTS.promote(batch) == hr.RESULTS.successful).tolist() == [True, False]


def test_solver_error_is_a_runtime_error():
    assert issubclass(hr.SolverError, RuntimeError)
    with pytest.raises(RuntimeError, match="boom"):
        raise hr.SolverError("boom")


def test_raise_if_failed_eager():
    tree = {"x": jnp.arange(3.0)}
    assert raise_if_failed(tree, hr.RESULTS.successful, "my solve") is tree
    ok_batch = codes(jnp.ones(4, bool), hr.RESULTS.successful, hr.RESULTS.invalid_input)
    assert raise_if_failed(tree, ok_batch, "my solve") is tree
    message = hr.RESULTS[hr.RESULTS.max_steps_reached]
    with pytest.raises(hr.SolverError, match="^" + re.escape(f"my solve: {message}; a hint") + "$"):
        raise_if_failed(tree, hr.RESULTS.max_steps_reached, "my solve", "; a hint")
    # A batch: how many failed, and the first failed index with its message.
    failed = jnp.array([False, True, False, True])
    batch = codes(failed, hr.RESULTS.invalid_input, hr.RESULTS.successful)
    text = re.escape(f"my solve: 2 of 4 points failed (first at index 1: {hr.RESULTS[hr.RESULTS.invalid_input]})")
    with pytest.raises(hr.SolverError, match="^" + text + "$"):
        raise_if_failed(tree, batch, "my solve")
    grid = jax.vmap(codes, in_axes=(0, None, None))(jnp.array([[False, False], [False, True]]), hr.RESULTS.cost_not_finite,
                                                    hr.RESULTS.successful)
    with pytest.raises(hr.SolverError, match=re.escape("1 of 4 points failed (first at index (1, 1): The cost")):
        raise_if_failed(tree, grid, "my solve")


def test_succeeded_reads_concrete_codes_on_the_host():
    """`succeeded` agrees with the device comparison `ok_of` for every code, one or a batch."""
    every = [getattr(hr.RESULTS, name) for name in ("successful", "max_steps_reached", "invalid_input", "residual_above_tolerance")]
    for code in every:
        assert isinstance(succeeded(code), np.ndarray) and bool(succeeded(code)) == bool(ok_of(code))
    batch = codes(jnp.array([True, False, True]), hr.RESULTS.successful, hr.RESULTS.nonlinear_divergence)
    assert succeeded(batch).tolist() == ok_of(batch).tolist() == [True, False, True]


def test_message_of_a_code_read_from_a_numpy_batch():
    """A code indexed out of a batch held in NumPy (as a fit's starts are) has its message,
    not equinox's "unknown" for a NumPy scalar."""
    from helixrod._status import message

    batch = jax.tree.map(np.asarray, codes(jnp.array([True, False]), hr.RESULTS.successful, hr.RESULTS.nonlinear_max_steps_reached))
    second = jax.tree.map(lambda v: v[1], batch)
    assert message(second) == message(hr.RESULTS.nonlinear_max_steps_reached) != "unknown"
    assert "maximum number of steps" in message(second)


def test_raise_if_failed_traced_raises_when_the_program_runs():
    @jax.jit
    def run(ok, x):
        result = hr.RESULTS.where(ok, hr.RESULTS.successful, hr.RESULTS.residual_above_tolerance)
        return raise_if_failed(2.0 * x, result, "my solve")

    assert float(run(True, 1.5)) == 3.0
    with pytest.raises(Exception, match=re.escape(hr.RESULTS[hr.RESULTS.residual_above_tolerance])):
        jax.block_until_ready(run(False, 1.5))
