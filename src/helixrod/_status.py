"""One status convention for every iterative result: a `RESULTS` code and `ok`.

Every solver result of helixrod (`KirchhoffSolution`, `BoundaryValueSolution`, `BulkHelix`,
`ResponseCurve`, `StiffnessFit`, `Bootstrap`) carries `result`, an item of `RESULTS` (an
equinox enumeration that extends diffrax's and optimistix's codes, so theirs pass through
unchanged), and `ok` = `result == RESULTS.successful`.  Every iterative entry point takes
`throw=`: with `throw=True` a failure raises `SolverError` (a `RuntimeError`) when the call
runs eagerly, and an equinox runtime error with the same message inside `jax.jit`; with
`throw=False` the caller reads `result` -- under `vmap` one failed point never spoils the
others.  Bad input (shapes, types, concrete non-finite values) is a `ValueError` before
anything runs.
"""

from __future__ import annotations

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from ._misc import is_concrete


class RESULTS(diffrax.RESULTS):  # pyright: ignore[reportGeneralTypeIssues]
    """Result codes of helixrod's solvers (diffrax's and optimistix's codes included).

    `RESULTS[item]` is the message of a (concrete, scalar) code; `RESULTS.promote(code)`
    converts a diffrax or optimistix code."""

    invalid_input = (
        "The input was rejected (non-finite values, a length <= 0, or a frame that is not a "
        "rotation); its fields are NaN."
    )
    residual_above_tolerance = "The solver stopped, but the residual is above its tolerance."
    cost_not_finite = "The cost of the best start is not finite."
    outside_model_range = (
        "The point is outside the model's range of validity (a torque acts at a force too "
        "low for the twist-fluctuation theory, whose correction is no longer small)."
    )
    weights_not_settled = (
        "The weights of errors in variables did not settle: each solve with the weights of "
        "the last point moved it again (Orear's iteration did not converge), as where the "
        "model is far from the data (a large reduced chi2)."
    )
    other_whole_turns = (
        "The solve converged to an equilibrium that meets the end frame but holds other whole "
        "turns than the end's total rotation asks for (another state of the same frames)."
    )


class SolverError(RuntimeError):
    """A solver did not succeed and was asked to raise (`throw=True`)."""


def promote(result) -> RESULTS:
    """A diffrax or optimistix result code as a `RESULTS` code (unchanged if it is one)."""
    return result if isinstance(result, RESULTS) else RESULTS.promote(result)


def message(result) -> str:
    """The message of a concrete scalar code ("" for success)."""
    # As an array: a code indexed from a NumPy array holds a NumPy scalar, which equinox
    # does not look up ("unknown").
    return RESULTS[jax.tree.map(np.asarray, result)]


def result_name(result) -> str:
    """The name of a concrete scalar code (`"successful"`, `"max_steps_reached"`, ...), as
    saved files record it."""
    for name, item in RESULTS._name_to_item.items():
        if bool(item == result):
            return name
    raise ValueError(f"not a RESULTS code: {result!r}")


def result_from_name(name: str) -> RESULTS:
    """The code of a name given by `result_name`."""
    try:
        return RESULTS._name_to_item[name]
    except KeyError:
        raise ValueError(f"unknown result code {name!r}; known: {', '.join(RESULTS._name_to_item)}") from None


def _code(result) -> np.ndarray:
    (value,) = jax.tree.leaves(result)
    return np.asarray(value)


def set_code(result, where, item):
    """`result` (codes of any shape, traced or not) with `item` where `where` is true
    (`RESULTS.where` takes one scalar predicate)."""
    return jax.tree.map(lambda code: jnp.where(where, jnp.asarray(_code(item), code.dtype), code), result)


def has_code(result, item) -> np.ndarray:
    """`result == item` for concrete codes, compared on the host (`succeeded`)."""
    return np.asarray(_code(result) == _code(item))


def succeeded(result) -> np.ndarray:
    """`ok_of` for concrete codes, compared on the host: no device dispatch (~35 us each,
    which added up in the status checks of an eager call)."""
    return has_code(result, RESULTS.successful)


def raise_if_failed(tree, result, what: str, hint: str = ""):
    """The `throw=True` behaviour: `tree` unchanged if every code in `result` is successful.

    Concrete codes (an eager call): `SolverError` naming `what`, the message and, for a
    batch, the failed points.  Traced codes: `tree` threaded through `eqx.error_if`, so the
    program raises when it runs (the message of the first failed code)."""
    if not is_concrete(result):
        return result.error_if(tree, result != RESULTS.successful)
    failed = ~succeeded(result)
    if not failed.any():
        return tree
    if failed.ndim == 0:
        raise SolverError(f"{what}: {RESULTS[result]}{hint}")
    where = np.argwhere(failed)
    first = tuple(int(i) for i in where[0])
    text = RESULTS[jax.tree.map(lambda v: v[first], result)]
    raise SolverError(
        f"{what}: {where.shape[0]} of {failed.size} points failed (first at index "
        f"{first if len(first) > 1 else first[0]}: {text}){hint}"
    )


def ok_of(result):
    """`result == RESULTS.successful` (a boolean array of the shape of the codes)."""
    return result == RESULTS.successful

