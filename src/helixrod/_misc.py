"""Small helpers shared by every part of the package: concreteness, gradient-safe
elementary functions, and the argument checks that entry points run before tracing.

Checks run on concrete values only: a traced value cannot be inspected, and the entry
points flag it inside the program instead (a result code, or NaN), so that one bad point
never spoils a `vmap`-ped batch.
"""

from __future__ import annotations

import functools
import json
import math
import os
import stat
import sys
import tempfile
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from ._compile import jit


def is_concrete(*trees) -> bool:
    """True when no leaf of `trees` is a tracer (the values can be read in Python)."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(trees))


def as_float(x, dtype=None):
    """`x` as an array of `dtype`: a JAX array, or anything holding a tracer, through
    `jnp.asarray` (`dtype=None`: its own); anything else (Python numbers, lists, NumPy
    arrays) as a NumPy array (`dtype=None`: float64), which a compiled program takes with
    its call.  `jnp.asarray` of a Python float or a NumPy array runs a conversion of its
    own on the device (measured 56 and 73 us each, most of an eager call's overhead where a
    function converts several)."""
    if isinstance(x, jax.Array) or any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(x)):
        return jnp.asarray(x, dtype)
    return np.asarray(x, float if dtype is None else dtype)


def float_dtype():
    """The default floating dtype (float64 with `jax_enable_x64`, else float32, with a
    warning the first time: `FLOAT32_WARNING`)."""
    dtype = jnp.result_type(float)
    if dtype == jnp.float32:
        _warn_of_float32()
    return dtype


#: The warning of the first computation in float32 (JAX's default): helixrod does not change
#: JAX's configuration, and without it a user who forgot it gets float64's claims silently
#: unmet (stability verdicts near a threshold, tolerances; the float32 review of 2026-12-07).
FLOAT32_WARNING = (
    "helixrod is computing in float32 because jax_enable_x64 is off (JAX's default). Its tolerances, "
    "accuracies and tests are float64's: in float32 the solves' tolerances are raised to 100 epsilons "
    "(1.2e-5) and stability verdicts near a threshold may be wrong. Call "
    "jax.config.update('jax_enable_x64', True) before creating arrays."
)


@functools.cache
def _warn_of_float32() -> None:
    # Point at the caller's code: the first frame outside helixrod and the libraries it
    # calls through (JAX traces helixrod's functions from its own frames).
    package = os.path.dirname(os.path.abspath(__file__))
    frame, level = sys._getframe(1), 2
    while frame is not None and (frame.f_code.co_filename.startswith(package) or "site-packages" in frame.f_code.co_filename):
        frame, level = frame.f_back, level + 1
    warnings.warn(FLOAT32_WARNING, UserWarning, stacklevel=level if frame is not None else 2)


#: The smallest tolerance a solve is asked for, in machine epsilons of its precision.
TOLERANCE_EPSILONS = 100


def attainable(tolerance: float, dtype) -> float:
    """`tolerance` raised to at least `TOLERANCE_EPSILONS` machine epsilons of `dtype`
    (float32: 1.2e-5), which a solve in that precision can reach; in float64 helixrod's
    tolerances are far above that floor and unchanged.  (A float64 tolerance asked of a
    float32 solve is never met: it fails, or finds nothing, for want of digits.)"""
    return max(float(tolerance), TOLERANCE_EPSILONS * float(jnp.finfo(dtype).eps))


def safe_sqrt(x: ArrayLike) -> Array:
    """$\\sqrt{x}$ for $x \\ge 0$ with a zero (not infinite or NaN) derivative at 0 and 0 for
    $x \\le 0$ (double `where`)."""
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


class host_method:
    """A method of an `equinox.Module` that is called on the host only -- never passed as a
    callable into `jax.jit` or another transformation: bound with `functools.partial`.
    equinox binds every other method read from a module as a `BoundMethod`, itself a module
    (so that it can be a pytree), built at each access: measured 18.9 us a call against
    1.5 us here, and a default helix fit reads ten such methods (~4 % of its time)."""

    def __init__(self, function):
        self.function = function
        functools.update_wrapper(self, function)

    def __get__(self, instance, owner=None):
        return self.function if instance is None else functools.partial(self.function, instance)


def replaced(module, **changes):
    """`dataclasses.replace(module, **changes)` for an `equinox.Module` whose new field values
    are of the kinds its fields hold (a program's results in place of others), without
    running the Module's `__init__` again: a shallow copy with the fields set, as JAX's
    unflattening makes Modules.  Measured on a `BoundaryValueSolution` (25 fields): 6 us
    against 66 us.  Made by `object.__new__`, not `copy.copy`: equinox's `Module.__new__`
    registers every new instance as being initialised until its `__init__` returns, so a
    copy made through it stayed registered -- kept alive for the life of the process (every
    eager solve and curve leaked its solution, ~48 kB a call) and writable, not frozen."""
    new = object.__new__(type(module))
    new.__dict__.update(module.__dict__)
    for name, value in changes.items():
        object.__setattr__(new, name, value)
    return new


def tree_where(condition, on_true, on_false):
    """`jnp.where(condition, a, b)` leaf by leaf of two pytrees of one structure (a scalar
    `condition`, traced or not, choosing between whole states)."""
    return jax.tree.map(lambda a, b: jnp.where(condition, a, b), on_true, on_false)


def no_gradient(tree):
    """`tree` with `stop_gradient` on its floating-point arrays (other leaves untouched)."""
    return jax.tree.map(lambda x: jax.lax.stop_gradient(x) if eqx.is_inexact_array(x) else x, tree)


def differentiated_part(tree, tangents):
    """(differentiated part of `tree`, the rest, its tangents) for a `filter_custom_jvp`
    tangent pytree with `None` at undifferentiated leaves; `eqx.combine` joins the first
    two again."""
    is_none = lambda t: t is None  # noqa: E731
    mask = jax.tree.map(lambda t: t is not None, tangents, is_leaf=is_none)
    diff, static = eqx.partition(tree, mask)
    return diff, static, eqx.filter(tangents, mask, is_leaf=is_none)


def require_valid(ok, message: str, *values) -> None:
    """Raise `ValueError(message)` (with the indices of the first bad points) when concrete
    inputs break `ok`; traced inputs are not raised on (the caller returns NaN there, so
    one bad point in a batch spoils nothing else)."""
    if is_concrete(ok, *values):
        bad = ~np.asarray(ok)
        if bad.any():
            where = "" if bad.ndim == 0 else f" (at indices {np.argwhere(bad)[:5].tolist()})"
            raise ValueError(message + where)


def check_integer(value, name: str, owner: str, minimum: int = 1) -> int:
    """`value` as an `int`, or `ValueError` unless it is an integer (not a bool) >= `minimum`."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{owner}: {name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def check_key(key, owner: str):
    """`key`, or `ValueError` unless it is one JAX random key (`jax.random.key(seed)`, or a
    legacy `jax.random.PRNGKey(seed)`): an integer seed or a batch of keys failed inside
    JAX's sampler with a message about PRNG key data."""
    dtype = getattr(key, "dtype", None)
    typed = dtype is not None and jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key) and jnp.shape(key) == ()
    legacy = dtype is not None and dtype == jnp.uint32 and jnp.shape(key) == (2,)
    if not (typed or legacy):
        raise ValueError(f"{owner}: key must be one JAX random key, e.g. jax.random.key(0), got {key!r:.60}")
    return key


def check_choice(value, choices, name: str, owner: str):
    """`value`, or `ValueError` unless it is one of `choices`."""
    if value not in choices:
        raise ValueError(f"{owner}: {name} must be one of {tuple(choices)}, got {value!r}")
    return value


def finite_array(x: ArrayLike, name: str, owner: str, shape_tail: tuple[int, ...] = ()) -> Array:
    """`x` as a float array with trailing shape `shape_tail` (`as_float`: a NumPy array
    unless `x` is a JAX array); `ValueError` for another shape or for non-finite concrete
    values."""
    try:
        a = as_float(x, float_dtype())
    except (TypeError, ValueError) as error:
        raise ValueError(f"{owner}: {name} must be numbers, got {x!r} ({error})") from None
    if a.ndim < len(shape_tail) or a.shape[a.ndim - len(shape_tail) :] != shape_tail:
        raise ValueError(f"{owner}: {name} must have trailing shape {shape_tail}, got {a.shape}")
    if is_concrete(a) and not np.all(np.isfinite(np.asarray(a))):
        raise ValueError(f"{owner}: {name} must be finite, got {a}")
    return a


def finite_scalar(x: ArrayLike, name: str, owner: str, *, positive: bool = False) -> Array:
    """`x` as a float scalar (`as_float`); `ValueError` for another shape, or for a concrete
    value that is not finite (or, with `positive=True`, not > 0)."""
    a = as_float(x, float_dtype())
    if a.shape != ():
        raise ValueError(f"{owner}: {name} must be a scalar, got shape {a.shape} (use jax.vmap for batches)")
    if is_concrete(a):
        v = float(a)
        if not np.isfinite(v) or (positive and not v > 0):
            raise ValueError(f"{owner}: {name} must be finite{' and > 0' if positive else ''}, got {v}")
    return a


def real_array(x: ArrayLike, name: str, owner: str) -> np.ndarray:
    """`x` as a float64 NumPy array; `ValueError` naming it for complex numbers (NumPy would
    drop their imaginary parts with a warning) or entries that are not numbers."""
    try:
        a = np.asarray(x)
        if not np.iscomplexobj(a):
            return np.asarray(a, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{owner}: {name} must be numbers, got {x!r:.80}") from None
    raise ValueError(f"{owner}: {name} must be real numbers, got complex values")


def column(x: ArrayLike, name: str, owner: str, n: int | None = None) -> np.ndarray:
    """A one-dimensional float64 NumPy column (a scalar broadcasts to length `n` when `n` is
    given); `ValueError` for another shape or non-finite entries, naming the rows."""
    a = real_array(x, name, owner)
    if n is not None and a.ndim == 0:
        a = np.full(n, float(a))
    if a.ndim != 1 or (n is not None and a.shape != (n,)):
        raise ValueError(f"{owner}: {name} must be one-dimensional{'' if n is None else f' of length {n}'}, got shape {a.shape}")
    bad = np.flatnonzero(~np.isfinite(a))
    if bad.size:
        raise ValueError(f"{owner}: {name} has non-finite values in rows {bad[:20].tolist()}")
    return a


def increasing_within(s: ArrayLike, length: ArrayLike, name: str, owner: str, slack: float = 0.0) -> Array:
    """Arc lengths `s` (1-d, non-empty) that are finite and increase strictly within
    $[0, L(1 + slack)]$; checked when both are concrete (`increases_within` is the traced
    test)."""
    s = as_float(s, float_dtype())
    if s.ndim != 1 or s.shape[0] < 1:
        raise ValueError(f"{owner}: {name} must be a 1-d array of arc lengths, got shape {s.shape}")
    if is_concrete(s, length) and not bool(increases_within(np.asarray(s), float(np.asarray(length)), slack, xp=np)):
        raise ValueError(f"{owner}: {name} must be finite and increase strictly within [0, {float(np.asarray(length))}]")
    return s


def increases_within(s, length, slack: float = 0.0, xp=jnp, strict: bool = True):
    """Whether arc lengths `s` (1-d, non-empty) are finite and increase strictly (`strict`;
    else repeats allowed) within $[0, L(1 + slack)]$ (`xp`: the array namespace, `jax.numpy`
    for traced values)."""
    steps = xp.diff(s)
    increasing = xp.all(steps > 0) if strict else xp.all(steps >= 0)
    return xp.all(xp.isfinite(s)) & increasing & (s[0] >= 0) & (s[-1] <= length * (1 + slack))


def jacobian_forward(fn, x: Array, *, has_aux: bool = False, through_loops: bool = False):
    """`jax.jacfwd(fn, has_aux=has_aux)(x)` for a flat `x` (the Jacobian's last axis is
    x's).  By default by one `jax.linearize` and the linear map applied to the unit vectors:
    the same values, but `jacfwd` traces `fn`'s whole forward-mode program under `vmap`, and
    this traces `fn` once and batches only its linear part, which for helixrod's helix
    models (a register solve with loops whose derivative is one implicit-function formula)
    is a fraction of it: the fit's Jacobian program (60 helices) traced in 1.3-1.6 s instead
    of 2.9-3.8 s (measured on a loaded 2-core machine).

    `through_loops=True` is `jax.jacfwd` itself, for an `fn` whose derivative runs through
    `while` loops (ODE integrations: the finite-rod and tweezer models).  Linearising splits
    the forward-mode program into its primal and tangent halves, and a `while` loop with
    tangents in its carry cannot be split: JAX keeps the primal loop and runs it once more,
    whole, inside the tangent half.  Measured (one program, loaded 2-core machine), the
    README's shape fit: trace 17.9 -> 11.0 s, XLA compilation 51.5 -> 32.9 s, a call
    8.6 -> 7.1 ms; a tweezer force-distance fit of 80 points: 4.3 -> 2.6 s, 7.8 -> 4.6 s,
    0.96 -> 0.69 ms; 200 points with hat curves: 8.9 -> 8.1 s, 25.2 -> 16.3 s,
    19.0 -> 10.1 ms; the same Jacobians to 1e-14."""
    if through_loops:
        return jax.jacfwd(fn, has_aux=has_aux)(x)
    if has_aux:
        _, linear, aux = jax.linearize(fn, x, has_aux=True)
    else:
        _, linear = jax.linearize(fn, x)
    basis = jnp.eye(x.shape[0], dtype=x.dtype)
    jacobian = jax.tree.map(lambda leaf: jnp.moveaxis(leaf, 0, -1), jax.vmap(linear)(basis))
    return (jacobian, aux) if has_aux else jacobian


#: Systems of up to this many unknowns are eliminated unrolled (each step its own
#: operations, which fuse with their neighbours), larger ones in a loop over the steps, whose
#: program holds one step.  Measured on one core, fresh processes: the stability test's
#: 6 x 6 systems as a loop, `solve_boundary_value`'s first call ~0.7-1 s shorter (its
#: program 14602 -> 13461 HLO instructions after XLA's passes), its later calls unchanged,
#: the same results bitwise; the tweezer model's 5 x 5 Newton steps (per point of a vmapped
#: model) as a loop, the bundled example's fit compiled in 7.7-8.3 s instead of 9.4-10.2 s,
#: but its later calls took 0.34-0.41 s instead of 0.27-0.28 s: they stay unrolled.
UNROLLED_SIZE = 5


def _steps(n: int, step, carry):
    """`step(k, carry)` for k = 0, ..., n - 1: unrolled up to `UNROLLED_SIZE`, else a loop."""
    if n <= UNROLLED_SIZE:
        for k in range(n):
            carry = step(k, carry)
        return carry
    return jax.lax.fori_loop(0, n, step, carry)


def _eliminate(M: Array) -> tuple[Array, Array, Array, Array]:
    """Gaussian elimination with partial pivoting on the first n columns of `M` `(n, n + k)`
    (a matrix, or a matrix and right-hand sides), in jnp operations (`_steps`): `(orders,
    factors, reduced, parity)`, the row order and the multipliers of each of the n
    eliminations (`(n, n)` each), the reduced `M` (upper-triangular in its first n columns)
    and the parity (+1/-1) of the row permutation."""
    n = M.shape[0]
    rows = jnp.arange(n)

    def step(k, carry):
        M, orders, factors, parity = carry
        # The first largest |entry| of column k on or below the diagonal (NaN first, as argmax).
        pivot = jnp.argmax(jnp.where(rows >= k, jnp.abs(M[:, k]), -1.0)).astype(rows.dtype)
        order = jnp.where(rows == k, pivot, jnp.where(rows == pivot, k, rows))
        parity = jnp.where(pivot == k, parity, -parity)
        M = M[order]
        factor = jnp.where(rows > k, M[:, k] / M[k, k], 0.0)
        M = M - factor[:, None] * M[k][None, :]
        return M, orders.at[k].set(order), factors.at[k].set(factor), parity

    init = (M, jnp.zeros((n, n), rows.dtype), jnp.zeros((n, n), M.dtype), jnp.ones((), M.dtype))
    M, orders, factors, parity = _steps(n, step, init)
    return orders, factors, M, parity


def _back_substitute(U: Array, c: Array) -> Array:
    """$U^{-1} c$ for the upper-triangular `U` of `_eliminate` (linear in `c`: reverse mode
    transposes it)."""
    n = U.shape[0]

    def step(i, x):
        k = n - 1 - i
        return x.at[k].set((c[k] - U[k] @ x) / U[k, k])

    return _steps(n, step, jnp.zeros_like(c))


def _as_columns(solve):
    """`solve(A, b)` of `(n, k)` right-hand sides for `b` `(n,)` or `(n, k)`."""

    @functools.wraps(solve)
    def solve_any(A, b):
        A, b = jnp.asarray(A), jnp.asarray(b)
        return solve(A, b.reshape(A.shape[-1], -1)).reshape(b.shape)

    return solve_any


def _solve_jvp(solve, tangent_solve):
    """The derivative rule $dx = A^{-1}(db - dA\\,x)$ of `solve`, with `tangent_solve` for
    the tangents."""

    def rule(primals, tangents):
        A, b = (jnp.asarray(p) for p in primals)
        dA, db = (jnp.asarray(t) for t in tangents)
        x = solve(A, b)
        n = A.shape[-1]
        return x, tangent_solve(A, db - (dA @ x.reshape(n, -1)).reshape(x.shape))

    return rule


@jax.custom_jvp
@_as_columns
def solve_small_linear(A: Array, b: Array) -> Array:
    """$A^{-1} b$ as `solve_small`, written linear in `b`: A's eliminations, then the same
    on b.  For right-hand sides that are tangents: reverse mode transposes it (not the
    joint elimination of `[A | b]`), and under `vmap` over b alone (the tangents of
    `jax.jacfwd`) A's part is not batched, so that each tangent costs a substitution."""
    if A.shape[-1] == 3:
        return _solve_three(A, b)
    orders, factors, U, _ = _eliminate(A)

    def step(k, b):
        b = b[orders[k]]
        return b - factors[k][:, None] * b[k][None, :]

    return _back_substitute(U, _steps(A.shape[-1], step, b))


def _solve_three(A, b):
    """$A^{-1} b$ of a 3 x 3 system by the adjugate: the columns of $\\det(A)\\,A^{-1}$ are the
    cross products of A's rows (Cramer's rule), $\\det A = a_0 \\cdot (a_1 \\times a_2)$."""
    scaled_inverse = jnp.stack([jnp.cross(A[1], A[2]), jnp.cross(A[2], A[0]), jnp.cross(A[0], A[1])], axis=1)
    return scaled_inverse @ b / jnp.dot(A[0], scaled_inverse[:, 0])


@jax.custom_jvp
@_as_columns
def solve_small(A: Array, b: Array) -> Array:
    """$A^{-1} b$ for one small square system (n <= ~12; `b` `(n,)` or `(n, k)`; batch with
    `vmap`) by Gaussian elimination with partial pivoting in jnp operations (unrolled up to
    `UNROLLED_SIZE` unknowns, else a loop).

    Used for the many tiny per-point systems inside vmapped models instead of
    `jnp.linalg.solve`, whose LAPACK calls (getrf/trsm through XLA's FFI) deadlocked in
    jaxlib 0.10.2 on 2 CPU cores when a batch of them ran under the concurrency-optimised
    scheduler (seen in a 2000-point tweezer fit and in a 100 x 100 stability atlas); pure
    arithmetic also fuses with its neighbours.  A singular matrix gives inf/NaN as
    `jnp.linalg.solve` would.

    Differentiable in both modes and to any order, by $dx = A^{-1}(db - dA\\,x)$ with the
    tangents solved by `solve_small_linear` (itself differentiated the same way): the
    elimination of A is shared by all tangents and never differentiated op by op.
    Measured on a 5 x 5 solve's second derivatives (1 x 8 tangents, 738 points, one core):
    4.5-4.8 -> 2.2 ms, XLA compilation 2.8-2.9 -> 1.8 s; the bundled tweezer example's fit
    1.15 -> 0.82 s.  Undifferentiated it eliminates `[A | b]` in one pass, as before.

    3 x 3 systems (the bulk helix under a force and moment, `helix_under_wrench`) are solved
    in closed form, by the adjugate (`_solve_three`): a third of the operations and no
    pivoting's selects.  The tweezer example's fit, whose model solves them differentiated
    to second order: its program 7 796 -> 6 020 operations (StableHLO), XLA compilation
    3.1 -> 2.3 s, the fit's first call 4.3-5.1 -> 3.5-4.6 s on 2 cores (three alternating
    pairs), later calls unchanged, the same Jacobian to 1e-14."""
    if A.shape[-1] == 3:
        return _solve_three(A, b)
    reduced = _eliminate(jnp.concatenate([A, b], axis=1))[2]
    n = A.shape[-1]
    return _back_substitute(reduced[:, :n], reduced[:, n:])


solve_small.defjvp(_solve_jvp(solve_small, solve_small_linear))
solve_small_linear.defjvp(_solve_jvp(solve_small_linear, solve_small_linear))


def inverse_small(A: ArrayLike) -> Array:
    """$A^{-1}$ of one small square matrix, as `solve_small` (no LAPACK call)."""
    A = jnp.asarray(A)
    return solve_small(A, jnp.eye(A.shape[-1], dtype=A.dtype))


def determinant_small(A: ArrayLike) -> Array:
    """$\\det A$ of one small square matrix by the elimination of `solve_small` (no LAPACK
    call)."""
    _, _, U, parity = _eliminate(jnp.asarray(A))
    return parity * jnp.prod(jnp.diagonal(U))


def symmetric_eigenvalue_min(A: ArrayLike) -> Array:
    """The smallest eigenvalue of one symmetric 3 x 3 matrix in closed form (the
    trigonometric solution of the characteristic cubic; Smith 1961, *Commun. ACM* 4, 168):
    no LAPACK call.  Round-off ~1e-8 relative where the smallest eigenvalue is double (the
    arccos near its end); a scale, not a spectrum."""
    A = jnp.asarray(A)
    q = jnp.trace(A) / 3.0
    off = A[0, 1] ** 2 + A[0, 2] ** 2 + A[1, 2] ** 2
    p = jnp.sqrt((jnp.sum((jnp.diagonal(A) - q) ** 2) + 2.0 * off) / 6.0)
    safe_p = jnp.where(p > 0, p, 1.0)
    S = (A - q * jnp.eye(3, dtype=A.dtype)) / safe_p
    r = jnp.clip(jnp.dot(S[0], jnp.cross(S[1], S[2])) / 2.0, -1.0, 1.0)
    phi = jnp.arccos(r) / 3.0
    return jnp.where(p > 0, q + 2.0 * p * jnp.cos(phi + 2.0 * jnp.pi / 3.0), q)


def _sturm_count(d: Array, e2: Array, shift: Array, pivmin: Array) -> Array:
    """Eigenvalues below `shift` of the symmetric tridiagonal matrix of diagonal `d` and
    squared subdiagonal `e2` (`e2[0]` = 0): the negative pivots of its $LDL^T$ factorisation
    at `shift` (Sturm's count, monotone in `shift`; a pivot within `pivmin` of zero counts as
    negative, as in LAPACK's `dstebz`)."""

    def pivot(q, entries):
        di, e2i = entries
        q = di - shift - e2i / q
        q = jnp.where(jnp.abs(q) < pivmin, -pivmin, q)
        return q, q < 0

    _, negative = jax.lax.scan(pivot, jnp.ones((), d.dtype), (d, e2))
    return jnp.sum(negative).astype(jnp.int32)


def _shifted_tridiagonal_solve(d: Array, lower: Array, upper: Array, b: Array, pivmin: Array) -> Array:
    """$x = T^{-1} b$ for the symmetric tridiagonal $T$ of diagonal `d` and off-diagonals
    `lower` (`lower[0]` = 0) and `upper` (`upper[-1]` = 0) by its $LDL^T$ factorisation, for
    inverse iteration at a shift next to the lowest eigenvalue, where $T$ is nearly
    positive semidefinite and needs no pivoting.  A pivot that comes out (nearly) zero is
    replaced by eps times its own row's entries, not the whole matrix's: JAX's
    `tridiagonal_solve(perturb_singular=True)` scales it by the largest entry, and the
    stability Hessian's huge decoupled slots then made the vector wrong in its 6th digit
    (a 3x3 case of `tests/test_misc.py`).  The floor is at least sqrt(`pivmin`), so that
    the solution of an all-zero row stays far from overflow (and its reciprocal a normal
    number: XLA's CPU backend flushes subnormals to zero)."""
    eps = jnp.finfo(d.dtype).eps
    pivmin = jnp.sqrt(pivmin)

    def eliminate(carry, row):
        q_before, z_before = carry
        di, li, ui, bi = row
        multiplier = li / q_before
        q = di - multiplier * li
        floor = eps * (jnp.abs(di) + jnp.abs(li) + jnp.abs(ui)) + pivmin
        q = jnp.where(jnp.abs(q) < floor, jnp.where(q < 0, -floor, floor), q)
        z = bi - multiplier * z_before
        return (q, z), (q, z)

    one = jnp.ones((), d.dtype)
    _, (q, z) = jax.lax.scan(eliminate, (one, jnp.zeros((), d.dtype)), (d, lower, upper, b))

    def substitute(x_after, row):
        qi, zi, ui = row
        x = (zi - ui * x_after) / qi
        return x, x

    _, x = jax.lax.scan(substitute, jnp.zeros((), d.dtype), (q, z, upper), reverse=True)
    return x


#: At most this many bisection steps for the lowest eigenvalue (each halves the interval;
#: they stop once it is within a few eps of the eigenvalue).
_MAX_BISECTIONS = 256


def symmetric_elimination(S: ArrayLike, eliminate: np.ndarray) -> tuple[Array, Array]:
    """The symmetric elimination of the rows and columns `eliminate` (a NumPy mask) of a small
    symmetric matrix `S`: `S` with the Schur complement of their block in the others' (their
    own rows and columns left zero), and the number of that block's negative eigenvalues, by
    Sylvester's law of inertia (the signs of its pivots; largest remaining diagonal first;
    pure arithmetic, no LAPACK call).  A zero pivot is skipped, its row left as it is: where
    a block's remaining diagonal is all zero (singular, or indefinite as [[0, 1], [1, 0]])
    the count misses its eigenvalues there and the complement is not its Schur complement --
    never met by the stability test's node blocks, positive or flagged."""
    steps = int(np.count_nonzero(eliminate))  # (a concrete mask)
    S, eliminate = jnp.asarray(S), jnp.asarray(eliminate)
    size = S.shape[-1]
    rows = jnp.arange(size)

    def step(_, carry):
        S, remaining, count = carry
        p = jnp.argmax(jnp.where(remaining, jnp.abs(jnp.diagonal(S)), -1.0))
        column = S[:, p]
        pivot = column[p]
        S = S - jnp.where(pivot == 0, 0.0, jnp.outer(column, column) / jnp.where(pivot == 0, 1.0, pivot))
        return S, remaining & (rows != p), count + (pivot < 0)

    # A loop, not unrolled: one copy of the elimination in the program.
    S, _, count = jax.lax.fori_loop(0, steps, step, (S, eliminate, jnp.zeros((), jnp.int32)))
    return S, count


def negative_count(S: ArrayLike) -> Array:
    """The number of negative eigenvalues of a small symmetric matrix (`symmetric_elimination`
    of all its rows)."""
    S = jnp.asarray(S)
    return symmetric_elimination(S, np.ones(S.shape[-1], bool))[1]


def lowest_eigenpair(A: ArrayLike, shift: ArrayLike, vector_only_below: bool = False) -> tuple[Array, Array, Array]:
    """(number of eigenvalues below `shift`, the lowest eigenvalue, a unit eigenvector of it)
    of one symmetric matrix `A` `(n, n)`, without its full eigendecomposition.

    `A` is reduced to tridiagonal form $A = QTQ^T$ (LAPACK `sytrd`, $\\tfrac43 n^3$ flops);
    the count and the eigenvalue come from Sturm counts on $T$ (`_sturm_count`; bisection
    to a few eps of the eigenvalue), the eigenvector from two steps of inverse iteration on $T$
    mapped back by $Q$'s Householder reflectors.  Both are backward stable: errors of order
    eps $\\|A\\|$, as `jnp.linalg.eigh`'s, which computes every eigenpair and took 3x as long
    for $n = 96$.  Rows that are decoupled from the others and come last (the stability
    Hessian's fixed slots, with a huge diagonal) stay decoupled through the reduction, so a
    huge entry there does not spoil the rest.  For a multiple lowest eigenvalue the vector is
    one of its eigenspace.  `vector_only_below=True`: the vector only where an eigenvalue
    lies below `shift`, zero (not computed: a `lax.cond`, both sides under `vmap`)
    elsewhere -- the stability test needs it only where the equilibrium is unstable."""
    A = jnp.asarray(A)
    n = A.shape[-1]
    reflectors, d, e, taus = jax.lax.linalg.tridiagonal(A, lower=True)
    zero = jnp.zeros(1, d.dtype)
    lower, upper = jnp.concatenate([zero, e]), jnp.concatenate([e, zero])  # T's off-diagonals, padded
    e2 = lower * lower
    pivmin = jnp.finfo(d.dtype).tiny * jnp.maximum(1.0, jnp.max(e2))
    shift = jnp.asarray(shift, d.dtype)
    count = _sturm_count(d, e2, shift, pivmin)
    # The lowest eigenvalue lies above Gershgorin's bound and below the smallest diagonal
    # entry (a Rayleigh quotient): a far tighter interval than Gershgorin's where a few
    # entries are huge (the stability Hessian's fixed slots).
    eps = jnp.finfo(d.dtype).eps
    radius = jnp.abs(lower) + jnp.abs(upper)
    lo, hi = jnp.min(d - radius), jnp.min(d)
    slack = 2.0 * eps * jnp.maximum(jnp.abs(lo), jnp.abs(hi)) + pivmin
    lo, hi = lo - slack, hi + slack
    # The count at `shift` brackets it too, for nothing: a stable Hessian's interval starts
    # at ~0 instead of far below (Gershgorin's bound of the spring's 96 x 96 stability
    # Hessian in `benchmarks/bench_finite.py` is -2e7, its lowest eigenvalue 10.35: 73 -> 56
    # bisections).
    inside = (lo < shift) & (shift < hi)
    lo = jnp.where(inside & (count == 0), shift, lo)
    hi = jnp.where(inside & (count >= 1), shift, hi)

    def wide(state):
        lo, hi, steps = state
        return (hi - lo > 2.0 * eps * jnp.maximum(jnp.abs(lo), jnp.abs(hi)) + pivmin) & (steps < _MAX_BISECTIONS)

    def bisect(state):
        lo, hi, steps = state
        mid = 0.5 * (lo + hi)
        found = _sturm_count(d, e2, mid, pivmin) >= 1
        return jnp.where(found, lo, mid), jnp.where(found, mid, hi), steps + 1

    lo, hi, _ = jax.lax.while_loop(wide, bisect, (lo, hi, jnp.zeros((), jnp.int32)))
    lowest = 0.5 * (lo + hi)

    def vector():
        # Inverse iteration from a start with no special symmetry.
        x = 1.0 + 0.1 * jnp.sin(jnp.arange(n, dtype=d.dtype))
        for _ in range(2):
            x = _shifted_tridiagonal_solve(d - lowest, lower, upper, x, pivmin)
            x = x / jnp.max(jnp.abs(x))
            x = x / jnp.linalg.norm(x)

        index = jnp.arange(n)

        def reflect(k, x):
            # Q = H_0 H_1 ... H_{n-2}, H_i = I - tau_i v_i v_i^T, v_i = (0.., 1 at i+1, reflectors[i+2:, i]).
            i = n - 2 - k
            v = jnp.where(index > i + 1, reflectors[:, i], 0.0) + (index == i + 1)
            return x - taus[i] * v * (v @ x)

        return x if n == 1 else jax.lax.fori_loop(0, n - 1, reflect, x)

    if not vector_only_below:
        return count, lowest, vector()
    return count, lowest, jax.lax.cond(count > 0, vector, lambda: jnp.zeros(n, d.dtype))


def chi2_survival(statistic: float, dof: float) -> float:
    """$P(X \\ge$ `statistic`$)$ for $X \\sim \\chi^2$(`dof`): the regularised upper incomplete
    gamma function $Q(a, x)$ at $a$ = `dof`/2, $x$ = `statistic`/2, in double precision on
    the host, by its power series for $x < a + 1$ and Legendre's continued fraction
    (modified Lentz) otherwise (Press et al., *Numerical Recipes*, 3rd ed., section 6.2).
    For the reports, which are numpy on the host: `jax.scipy.stats.chi2.sf` compiled
    ~0.3 s of XLA programs at a fit's first call.  Against mpmath (`tests/test_misc.py`):
    within 2e-14 relative up to `dof` = 57, 2e-13 at 400, 1e-11 at 1e4 and 1e-9 at 2e6
    (there the exponent of the prefactor $x^a e^{-x}/\\Gamma(a)$ is ~1e7)."""
    if not dof > 0:
        raise ValueError(f"chi2_survival: dof must be > 0, got {dof}")
    a, x = 0.5 * float(dof), 0.5 * float(statistic)
    if math.isnan(x):
        return math.nan
    if x <= 0.0:
        return 1.0
    if math.isinf(x):
        return 0.0
    prefactor = math.exp(-x + a * math.log(x) - math.lgamma(a))
    eps, tiny = 1e-16, 1e-300
    iterations = 10_000 + int(20 * math.sqrt(a))
    if x < a + 1.0:
        term = total = 1.0 / a
        denominator = a
        for _ in range(iterations):
            denominator += 1.0
            term *= x / denominator
            total += term
            if abs(term) < abs(total) * eps:
                break
        return max(0.0, 1.0 - total * prefactor)
    b = x + 1.0 - a
    c, d = 1.0 / tiny, 1.0 / b
    fraction = d
    for i in range(1, iterations):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        fraction *= d * c
        if abs(d * c - 1.0) < eps:
            break
    return prefactor * fraction


#: How `json_text` writes the non-finite floats that JSON has no numbers for.
_NON_FINITE = {"inf": math.inf, "-inf": -math.inf, "nan": math.nan}


def json_text(record, indent: int = 1) -> str:
    """`record` (dicts, lists and numbers) as standard JSON text (RFC 8259): its non-finite
    floats as the strings "inf", "-inf" and "nan" -- Python's `json` would write `Infinity`
    and `NaN`, which strict readers (jq, JavaScript) reject; `json_record` reads them back."""

    def encode(x):
        if isinstance(x, float) and not math.isfinite(x):
            return "nan" if math.isnan(x) else ("inf" if x > 0 else "-inf")
        if isinstance(x, dict):
            return {k: encode(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [encode(v) for v in x]
        return x

    return json.dumps(encode(record), indent=indent, allow_nan=False)


def json_record(text: str):
    """The record of `json_text` (its "inf", "-inf" and "nan" strings as floats; files with
    JSON's non-standard `Infinity` and `NaN` read too).  `json.JSONDecodeError` if not JSON."""

    def decode(x):
        if isinstance(x, str):
            return _NON_FINITE.get(x, x)
        if isinstance(x, dict):
            return {k: decode(v) for k, v in x.items()}
        if isinstance(x, list):
            return [decode(v) for v in x]
        return x

    return decode(json.loads(text))


def write_atomically(path, write, *, binary: bool = True) -> None:
    """Write a file through `write(file)` into a temporary file beside `path`, then rename
    it over `path`: an interrupted or failed write leaves an existing file whole.  The
    name is used exactly as given (no suffix added).  The file gets the permissions of the
    one it replaces, or those of a new file under the process's umask (the temporary file
    is private until then)."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    try:
        mode = stat.S_IMODE(os.stat(path).st_mode)
    except FileNotFoundError:
        umask = os.umask(0)
        os.umask(umask)
        mode = 0o666 & ~umask
    handle, temporary = tempfile.mkstemp(dir=folder, prefix=".", suffix=".part")
    try:
        with os.fdopen(handle, "wb" if binary else "w") as file:
            write(file)
        os.chmod(temporary, mode)
        os.replace(temporary, path)
    except BaseException:
        if os.path.exists(temporary):
            os.remove(temporary)
        raise


def newton_iterations(residual, x0, steps: int, project=None, tolerance=None):
    """At most `steps` plain Newton steps $x \\leftarrow x - J(x)^{-1} f(x)$ on a small square
    system (a non-finite step is skipped), each optionally followed by `project(new, old)`; no
    derivatives through the iteration (for initial guesses and seeds that a caller checks
    afterwards).  Without `tolerance` all `steps` run; with it the iteration stops once
    every component of a step is below `tolerance` (under `vmap`: once all points have)."""

    if steps == 0:  # nothing to trace (a loop of no steps is traced and transformed all the same)
        return x0

    def step(x):
        dx = solve_small(jax.jacfwd(residual)(x), residual(x))
        dx = jnp.where(jnp.all(jnp.isfinite(dx)), dx, 0.0)
        new = x - dx
        return (new if project is None else project(new, x)), jnp.max(jnp.abs(dx))

    if tolerance is None:
        return jax.lax.fori_loop(0, steps, lambda _, x: step(x)[0], x0)

    def unfinished(state):
        i, _, size = state
        return (i < steps) & (size > tolerance)

    def advance(state):
        i, x, _ = state
        return (i + 1, *step(x))

    start = (jnp.zeros((), jnp.int32), x0, jnp.full((), jnp.inf, jnp.result_type(x0)))
    return jax.lax.while_loop(unfinished, advance, start)[1]


#: `jax.random.normal(key, shape)`, `jax.random.randint(key, shape, low, high)` and
#: `jax.random.split(key, num)` (shape, num static) compiled to run once: called eagerly,
#: JAX compiles them with XLA's full optimisation (the normal draws of a fit's starts: 0.24
#: -> 0.08 s on one core, a split 0.11 -> 0.05 s; the same draws and keys).  For the draws
#: helixrod makes once per call (starts, replicates, synthetic data).
random_normal = jit(jax.random.normal, static_argnums=1, run_once=True)
random_integers = jit(jax.random.randint, static_argnums=1, run_once=True)
random_split = jit(jax.random.split, static_argnums=1, run_once=True)
