"""helixrod._misc: the gradient-safe square root, the plain Newton iteration, and the
argument checks (raise for bad concrete values, pass traced values through), against
numpy and closed forms."""

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import helixrod as hr
from helixrod import _misc


def test_safe_sqrt_values_and_zero_gradient_at_zero():
    x = jnp.array([4.0, 2.25, 1e-300, 0.0, -0.0, -1.0])
    np.testing.assert_array_equal(_misc.safe_sqrt(x), np.sqrt(np.maximum(np.asarray(x), 0.0)))
    grad = jax.grad(_misc.safe_sqrt)
    assert float(grad(0.0)) == 0.0  # finite (jnp.sqrt's derivative is inf there)
    assert float(grad(-1.0)) == 0.0
    assert float(grad(4.0)) == pytest.approx(0.25, rel=1e-15)
    assert np.isfinite(jax.grad(lambda x: _misc.safe_sqrt(x * x))(0.0))
    assert not np.isfinite(jax.grad(jnp.sqrt)(0.0))  # the reason for the helper


def test_newton_iterations_finds_a_known_root_and_skips_non_finite_steps():
    # x0^2 + x1^2 = 4, x0 = x1: the root (sqrt 2, sqrt 2) (quadratic convergence from (1, 0.5)).
    def residual(x):
        return jnp.stack([x[0] ** 2 + x[1] ** 2 - 4.0, x[0] - x[1]])

    root = _misc.newton_iterations(residual, jnp.array([1.0, 0.5]), 8)
    np.testing.assert_allclose(root, np.sqrt([2.0, 2.0]), rtol=1e-15)
    # A singular Jacobian (x^2 - 2 at x = 0) gives a non-finite step: skipped, x stays put.
    stuck = _misc.newton_iterations(lambda x: x * x - 2.0, jnp.zeros(1), 5)
    np.testing.assert_array_equal(stuck, [0.0])
    # project(new, old) follows every step: |x| keeps the iterate on the positive branch.
    positive = _misc.newton_iterations(lambda x: x * x - 2.0, -jnp.ones(1), 10, project=lambda new, old: jnp.abs(new))
    np.testing.assert_allclose(positive, [np.sqrt(2.0)], rtol=1e-15)
    # Traceable: the same under jit.
    np.testing.assert_allclose(jax.jit(lambda x0: _misc.newton_iterations(residual, x0, 8))(jnp.array([1.0, 0.5])), root, rtol=1e-15)


def test_checks_raise_with_the_name_for_bad_concrete_values():
    with pytest.raises(ValueError, match="owner: length must be finite and > 0, got 0.0"):
        _misc.finite_scalar(0.0, "length", "owner", positive=True)
    with pytest.raises(ValueError, match="owner: length must be finite, got nan"):
        _misc.finite_scalar(np.nan, "length", "owner")
    with pytest.raises(ValueError, match=r"owner: length must be a scalar, got shape \(2,\)"):
        _misc.finite_scalar([1.0, 2.0], "length", "owner")
    assert float(_misc.finite_scalar(2, "length", "owner", positive=True)) == 2.0
    with pytest.raises(ValueError, match=r"owner: force must have trailing shape \(3,\), got \(2,\)"):
        _misc.finite_array([1.0, 2.0], "force", "owner", (3,))
    with pytest.raises(ValueError, match="owner: force must be finite"):
        _misc.finite_array([[1.0, 2.0, np.inf]], "force", "owner", (3,))
    assert _misc.finite_array(np.ones((4, 3)), "force", "owner", (3,)).shape == (4, 3)
    for bad in ("abc", [1.0, "x", 2.0]):
        with pytest.raises(ValueError, match="owner: force must be numbers, got"):
            _misc.finite_array(bad, "force", "owner", (3,))
    for bad in (0, True, 1.5, "2"):
        with pytest.raises(ValueError, match="owner: segments must be an integer >= 1"):
            _misc.check_integer(bad, "segments", "owner")
    assert _misc.check_integer(np.int64(3), "segments", "owner") == 3
    assert _misc.check_integer(0, "continuation", "owner", minimum=0) == 0
    with pytest.raises(ValueError, match="owner: method must be one of"):
        _misc.check_choice("bisection", ("newton",), "method", "owner")
    with pytest.raises(ValueError, match=r"owner: saveat must be finite and increase strictly within \[0, 2.0\]"):
        _misc.increasing_within([0.0, 1.5, 1.0], 2.0, "saveat", "owner")
    with pytest.raises(ValueError, match="owner: saveat must be finite and increase strictly within"):
        _misc.increasing_within([0.0, 2.5], 2.0, "saveat", "owner")
    with pytest.raises(ValueError, match="owner: saveat must be finite and increase strictly within"):
        _misc.increasing_within([-0.1, 1.0], 2.0, "saveat", "owner")
    with pytest.raises(ValueError, match="owner: saveat must be finite and increase strictly within"):
        _misc.increasing_within([0.0, np.nan], 2.0, "saveat", "owner")
    # The traced test: the same rule, one verdict per point of a batch.
    batch = jnp.array([[0.0, 1.0], [0.0, np.nan], [1.0, 0.5], [0.0, 2.5]])
    assert jax.vmap(lambda s: _misc.increases_within(s, 2.0))(batch).tolist() == [True, False, False, False]
    with pytest.raises(ValueError, match="owner: saveat must be a 1-d array"):
        _misc.increasing_within(np.ones((2, 2)), 2.0, "saveat", "owner")
    np.testing.assert_array_equal(_misc.increasing_within([0.0, 2.0 * (1 + 1e-13)], 2.0, "saveat", "owner", slack=1e-12),
                                  [0.0, 2.0 * (1 + 1e-13)])
    with pytest.raises(ValueError, match=r"owner: sigma has non-finite values in rows \[1\]"):
        _misc.column([1.0, np.nan], "sigma", "owner")
    np.testing.assert_array_equal(_misc.column(0.5, "sigma", "owner", n=3), [0.5, 0.5, 0.5])


def test_checks_pass_traced_values_through():
    @jax.jit
    def checked(x, v, s):
        return (
            _misc.finite_scalar(x, "length", "owner", positive=True),
            _misc.finite_array(v, "force", "owner", (3,)),
            _misc.increasing_within(s, x, "saveat", "owner"),
        )

    # Values that raise when concrete go through untouched (the entry points flag them).
    x, v, s = checked(-1.0, jnp.array([jnp.inf, 0.0, 0.0]), jnp.array([3.0, 1.0]))
    assert float(x) == -1.0 and np.isinf(v[0]) and np.asarray(s).tolist() == [3.0, 1.0]
    # ... but shapes are static and still checked while tracing.
    with pytest.raises(ValueError, match="trailing shape"):
        checked(1.0, jnp.zeros(2), jnp.array([0.0, 1.0]))
    assert _misc.is_concrete(1.0, jnp.ones(2)) and not jax.jit(lambda x: jnp.asarray(_misc.is_concrete(x)))(1.0)


def test_no_gradient_stops_floating_point_leaves_only():
    def f(x):
        tree = _misc.no_gradient({"x": x, "count": 3})
        assert tree["count"] == 3
        return tree["x"] * x

    assert float(jax.grad(f)(2.0)) == 2.0  # d/dx (c x) with c = x held fixed


def test_solve_small_derivatives_in_the_matrix_to_second_order_match_lapack(rng):
    """`solve_small`'s own derivative rule (solves with the same elimination) against
    `jnp.linalg.solve` differentiated by JAX: first derivatives in both modes, second
    derivatives (forward over forward, reverse over forward), under `vmap`, with a matrix
    that needs row swaps."""
    A0 = rng.normal(size=(5, 5))
    A0[0, 0] = 1e-3  # a pivot search that swaps rows
    b0 = rng.normal(size=5)
    directions = rng.normal(size=(3, 5, 5))

    def solution(solve):
        def of(t):  # the matrix and the right-hand side along a curve through (A0, b0)
            A = A0 + t[0] * directions[0] + t[1] ** 2 * directions[1] + jnp.sin(t[2]) * directions[2]
            return solve(A, jnp.cos(t[0]) * b0 + t[1] * A0[:, 1])
        return of

    t0 = jnp.array([0.3, -0.2, 0.5])
    ours, lapack = solution(_misc.solve_small), solution(jnp.linalg.solve)
    # Each derivative compiled as one program: run operation by operation, the unrolled
    # elimination's hundreds of operations compiled one by one (~35 s).
    np.testing.assert_allclose(jax.jit(jax.jacfwd(ours))(t0), jax.jit(jax.jacfwd(lapack))(t0), rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(jax.jit(jax.jacrev(ours))(t0), jax.jit(jax.jacfwd(lapack))(t0), rtol=1e-11, atol=1e-12)
    second = jax.jit(jax.jacfwd(jax.jacfwd(lapack)))(t0)
    np.testing.assert_allclose(jax.jit(jax.jacfwd(jax.jacfwd(ours)))(t0), second, rtol=1e-10, atol=1e-11)
    np.testing.assert_allclose(jax.jit(jax.jacrev(jax.jacfwd(ours)))(t0), second, rtol=1e-10, atol=1e-11)
    points = t0[None, :] + 0.1 * jnp.asarray(rng.normal(size=(4, 3)))
    np.testing.assert_allclose(jax.jit(jax.vmap(jax.jacfwd(ours)))(points), jax.jit(jax.vmap(jax.jacfwd(lapack)))(points), rtol=1e-11, atol=1e-12)
    # Several right-hand sides, and the inverse.
    np.testing.assert_allclose(
        jax.jit(jax.jacfwd(_misc.inverse_small))(jnp.asarray(A0)), jax.jit(jax.jacfwd(jnp.linalg.inv))(jnp.asarray(A0)), rtol=1e-10, atol=1e-10
    )


def test_three_by_three_systems_in_closed_form_match_lapack_to_second_order(rng):
    """3 x 3 systems are solved by the adjugate (no pivoting): against `jnp.linalg.solve` on a
    matrix that partial pivoting would reorder and on one of condition ~1e8, with matrix
    right-hand sides, first and second derivatives through both solves (the derivative rule's
    tangent solve is `solve_small_linear`, closed form too), and a singular matrix (not
    finite, as LAPACK's)."""
    solve_small, solve_linear = jax.jit(_misc.solve_small), jax.jit(_misc.solve_small_linear)
    U, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    for A in (np.array([[1e-9, 2.0, 1.0], [1.0, 1.0, 0.0], [3.0, 0.0, 1.0]]), U @ np.diag([1.0, 1e-4, 1e-8]) @ U.T):
        B = rng.normal(size=(3, 2))
        expected = np.linalg.solve(A, B)
        tolerance = 1e-15 * np.linalg.cond(A) * np.abs(expected).max()
        np.testing.assert_allclose(solve_small(A, B), expected, atol=tolerance)
        np.testing.assert_allclose(solve_linear(A, B), expected, atol=tolerance)
    A0, b0, direction = rng.normal(size=(3, 3)), rng.normal(size=3), rng.normal(size=(3, 3))

    def curve(solve):
        return lambda t: solve(A0 + t[0] * direction + t[1] ** 2 * A0.T, jnp.cos(t[1]) * b0)

    t0 = jnp.array([0.2, -0.3])
    for order in (jax.jacfwd, lambda f: jax.jacfwd(jax.jacfwd(f)), lambda f: jax.jacrev(jax.jacfwd(f))):
        np.testing.assert_allclose(
            jax.jit(order(curve(_misc.solve_small)))(t0), jax.jit(order(curve(jnp.linalg.solve)))(t0), rtol=1e-10, atol=1e-11
        )
    assert not np.all(np.isfinite(np.asarray(solve_small(np.ones((3, 3)), np.ones(3)))))


def test_solve_small_matches_lapack_and_pivots(rng):
    # Jitted, as inside the models that use it (eagerly, each unrolled step of the
    # elimination is compiled on its own: ~30 s of this test).
    solve_small = jax.jit(_misc.solve_small)

    for n in (1, 2, 5, 6):
        A = rng.normal(size=(n, n)) + n * np.eye(n)
        b = rng.normal(size=n)
        np.testing.assert_allclose(solve_small(A, b), np.linalg.solve(A, b), rtol=1e-12, atol=1e-14)
    # A zero leading pivot needs a row exchange.
    A = np.array([[0.0, 2.0, 1.0], [1.0, 1.0, 0.0], [3.0, 0.0, 1.0]])
    b = np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(solve_small(A, b), np.linalg.solve(A, b), rtol=1e-13)
    # Batched, and differentiable: d(A^-1 b)/db = A^-1.
    batch = rng.normal(size=(7, 4, 4)) + 4 * np.eye(4)
    rhs = rng.normal(size=(7, 4))
    np.testing.assert_allclose(jax.vmap(solve_small)(batch, rhs), np.linalg.solve(batch, rhs[..., None])[..., 0], rtol=1e-12)
    np.testing.assert_allclose(jax.jacfwd(solve_small, argnums=1)(batch[0], rhs[0]), np.linalg.inv(batch[0]), rtol=1e-12)
    np.testing.assert_allclose(jax.jacrev(solve_small, argnums=1)(batch[0], rhs[0]), np.linalg.inv(batch[0]), rtol=1e-12)
    assert not np.all(np.isfinite(np.asarray(solve_small(jnp.zeros((2, 2)), jnp.ones(2)))))


def test_small_inverse_determinant_and_matrix_right_hand_sides_match_lapack(rng):
    solve_small, inverse_small, determinant_small = (
        jax.jit(fn) for fn in (_misc.solve_small, _misc.inverse_small, _misc.determinant_small)
    )
    for n in (1, 3, 6, 12):
        A = rng.normal(size=(n, n))
        B = rng.normal(size=(n, 4))
        np.testing.assert_allclose(solve_small(A, B), np.linalg.solve(A, B), rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(inverse_small(A), np.linalg.inv(A), rtol=1e-10, atol=1e-12)
        assert float(determinant_small(A)) == pytest.approx(np.linalg.det(A), rel=1e-12)
    # The sign of the determinant follows the row exchanges.
    swap = np.array([[0.0, 1.0], [1.0, 0.0]])
    assert float(determinant_small(swap)) == -1.0
    assert float(determinant_small(np.diag([2.0, -3.0, 0.5]))) == pytest.approx(-3.0, rel=1e-15)


def test_elimination_unrolled_and_looped_agree(rng, monkeypatch):
    """Up to `UNROLLED_SIZE` unknowns the elimination is unrolled, above it a loop over its
    steps (a smaller program): the same arithmetic either way -- solutions, determinant,
    the linear form and derivatives (forward, and reverse through the loop's transpose) of a
    system that needs row swaps."""
    n = _misc.UNROLLED_SIZE + 2
    A = rng.normal(size=(n, n))
    A[0, 0] = 1e-3  # a pivot search that swaps rows
    b = rng.normal(size=(n, 2))

    def results():
        def of(A, b):
            return (_misc.solve_small(A, b), _misc.determinant_small(A), _misc.solve_small_linear(A, b),
                    jax.jacfwd(_misc.solve_small)(A, b[:, 0]), jax.jacrev(_misc.solve_small)(A, b[:, 0]))
        return jax.jit(of)(A, b), str(jax.make_jaxpr(of)(A, b))

    looped, program = results()
    assert "scan" in program  # fori_loop's form
    monkeypatch.setattr(_misc, "UNROLLED_SIZE", n)
    unrolled, program = results()
    assert "scan" not in program and "while" not in program
    for a, u in zip(jax.tree.leaves(looped), jax.tree.leaves(unrolled)):
        np.testing.assert_allclose(a, u, rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(looped[0], np.linalg.solve(A, b), rtol=1e-12)


def test_lowest_eigenpair_matches_eigh(rng):
    """Count below a shift, lowest eigenvalue and its vector against `numpy.linalg.eigh`, on
    random symmetric matrices, ones with a double lowest eigenvalue, ones with a huge
    decoupled diagonal entry in the last row (the stability Hessian's fixed slots: the
    eigenpair must stay accurate relative to the rest, not to that entry; a 3x3 one with an
    exactly zero pivot at the computed eigenvalue once had its vector wrong in the 6th
    digit) and graded ones; degenerate ones; and under `vmap`."""
    lowest_eigenpair = jax.jit(_misc.lowest_eigenpair)
    # Five sizes (each a compile), prime to the four kinds: every size meets every kind twice.
    sizes = (2, 3, 8, 24, 59)
    for trial in range(40):
        n = sizes[trial % len(sizes)]
        A = rng.normal(size=(n, n))
        A = A + A.T
        if trial % 4 == 1:  # last, as in the Hessian: the reduction then leaves it decoupled
            k = n - 1
            A[k, :] = A[:, k] = 0.0
            A[k, k] = 1e12 * np.abs(A).max()
        elif trial % 4 == 2:
            Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
            w = np.sort(rng.normal(size=n))
            w[1] = w[0]
            A = Q @ np.diag(w) @ Q.T
            A = 0.5 * (A + A.T)
        elif trial % 4 == 3:
            A = 1e-8 * A + np.diag(np.linspace(0.0, 10.0, n))
        w = np.linalg.eigvalsh(A)
        if trial % 4 == 1:  # decoupled: the spectrum of the rest, and the huge entry
            w = np.sort(np.append(np.linalg.eigvalsh(np.delete(np.delete(A, k, 0), k, 1)), A[k, k]))
        soft = np.abs(w[w < 1e9]).max()  # the scale of the spectrum without a huge entry
        shift = float(rng.normal())
        count, lowest, vector = lowest_eigenpair(A, shift)
        assert int(count) == int(np.sum(w < shift)), trial
        assert float(lowest) == pytest.approx(w[0], abs=1e-13 * soft), trial
        v = np.asarray(vector)
        assert np.linalg.norm(v) == pytest.approx(1.0, abs=1e-12)
        assert np.linalg.norm(A @ v - w[0] * v) <= 1e-12 * soft, trial
    # Degenerate: the zero matrix (a zero pivot in every row; any unit vector will do) and 1x1.
    count, lowest, vector = lowest_eigenpair(np.zeros((8, 8)), 0.5)
    assert int(count) == 8 and float(lowest) == 0.0 and np.linalg.norm(vector) == pytest.approx(1.0, abs=1e-12)
    count, lowest, vector = _misc.lowest_eigenpair(np.array([[-2.0]]), 0.0)
    assert (int(count), np.asarray(vector).tolist()) == (1, [1.0]) and float(lowest) == pytest.approx(-2.0, rel=1e-15)
    batch = np.stack([np.diag([3.0, 1.0, 2.0]), np.diag([-1.0, 5.0, 4.0])])
    counts, lows, _ = jax.vmap(_misc.lowest_eigenpair, in_axes=(0, None))(batch, 0.0)
    assert counts.tolist() == [0, 1] and np.allclose(lows, [1.0, -1.0], rtol=1e-15, atol=0)
    # The vector only below the shift: zero where no eigenvalue lies below it, else the same
    # vector, alone and under vmap (where both sides of its cond run).
    only_below = jax.jit(functools.partial(_misc.lowest_eigenpair, vector_only_below=True))
    A = rng.normal(size=(24, 24))
    A = A + A.T
    w = np.linalg.eigvalsh(A)
    for shift in (w[0] - 1.0, w[0] + 1e-3):
        count, lowest, vector = only_below(A, shift)
        reference = lowest_eigenpair(A, shift)
        assert int(count) == int(reference[0]) and float(lowest) == float(reference[1])
        expected = np.asarray(reference[2]) if int(count) > 0 else np.zeros(24)
        np.testing.assert_array_equal(np.asarray(vector), expected)
    _, _, vectors = jax.vmap(only_below, in_axes=(0, None))(batch, 0.0)
    np.testing.assert_array_equal(np.asarray(vectors[0]), np.zeros(3))
    assert abs(float(vectors[1][0])) == pytest.approx(1.0, abs=1e-12)


def test_symmetric_eigenvalue_min_matches_eigvalsh(rng):
    for _ in range(20):
        S = rng.normal(size=(3, 3))
        S = S + S.T
        assert float(_misc.symmetric_eigenvalue_min(S)) == pytest.approx(np.linalg.eigvalsh(S)[0], rel=1e-12, abs=1e-12)
    assert float(_misc.symmetric_eigenvalue_min(2.0 * np.eye(3))) == 2.0  # all three equal
    assert float(_misc.symmetric_eigenvalue_min(np.diag([1.0, 2.0, 2.0]))) == pytest.approx(1.0, rel=1e-14)
    # A double smallest eigenvalue: the documented ~1e-8 of the arccos near its end.
    assert float(_misc.symmetric_eigenvalue_min(np.diag([1.0, 1.0, 2.0]))) == pytest.approx(1.0, rel=1e-7)


@pytest.mark.parametrize("through_loops", [False, True])
def test_jacobian_forward_of_a_loop_against_the_closed_form(through_loops):
    """f(x) = (x0^(1/3) by Newton in a `while` loop, x0 x1^2): both ways of forming the
    Jacobian (linearised, or `jacfwd` for derivatives through loops) give the closed form,
    with the auxiliary output passed through."""

    def cube_root(a):
        step = lambda y: y - (y**3 - a) / (3 * y**2)  # noqa: E731
        return jax.lax.while_loop(lambda y: jnp.abs(y**3 - a) > 1e-14 * a, step, jnp.ones_like(a) + a / 3)

    def fn(x):
        value = jnp.stack([cube_root(x[0]), x[0] * x[1] ** 2])
        return value, 2 * value

    x = jnp.array([5.0, 1.5])
    jacobian, aux = _misc.jacobian_forward(fn, x, has_aux=True, through_loops=through_loops)
    expected = np.array([[5.0 ** (-2 / 3) / 3, 0.0], [1.5**2, 2 * 5.0 * 1.5]])
    np.testing.assert_allclose(jacobian, expected, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(aux, 2 * np.array([5.0 ** (1 / 3), 5.0 * 1.5**2]), rtol=1e-14)
    plain = _misc.jacobian_forward(lambda x: fn(x)[0], x, through_loops=through_loops)
    np.testing.assert_array_equal(plain, jacobian)


def test_chi2_survival_matches_mpmath_and_scipy():
    """The host's chi-squared survival function (the reports' p-values) against mpmath's
    regularised upper incomplete gamma at 40 digits, across the series and the continued
    fraction and from 1 to 2e6 degrees of freedom, and scipy at a few points; edges."""
    import mpmath
    import scipy.stats

    mpmath.mp.dps = 40
    tolerance = {1: 1e-14, 3: 1e-14, 10: 2e-14, 57: 5e-14, 400: 5e-13, 10_000: 5e-11, 2_000_000: 5e-9}
    for dof, rtol in tolerance.items():
        for factor in (1e-6, 0.01, 0.5, 0.99, 1.0, 1.01, 2.0, 5.0, 30.0):
            x = dof * factor
            exact = float(mpmath.gammainc(mpmath.mpf(dof) / 2, mpmath.mpf(x) / 2, mpmath.inf, regularized=True))
            if exact == 0.0:  # below the smallest double
                assert _misc.chi2_survival(x, dof) < 1e-300
            else:
                assert _misc.chi2_survival(x, dof) == pytest.approx(exact, rel=rtol, abs=0), (dof, factor)
    for x, dof in ((3.84, 1), (12.5, 7), (250.0, 200)):
        assert _misc.chi2_survival(x, dof) == pytest.approx(scipy.stats.chi2.sf(x, dof), rel=1e-12)
    assert _misc.chi2_survival(0.0, 4) == 1.0 and _misc.chi2_survival(np.inf, 4) == 0.0
    assert np.isnan(_misc.chi2_survival(np.nan, 4))
    with pytest.raises(ValueError, match="dof must be > 0"):
        _misc.chi2_survival(1.0, 0)


def test_as_float_keeps_host_values_on_the_host_and_traced_values_traced():
    """Host inputs stay NumPy (no conversion program of their own on the device); JAX
    arrays, and anything holding a tracer, go through `jnp.asarray`."""
    host = _misc.as_float([1, 2], jnp.float64)
    assert isinstance(host, np.ndarray) and host.dtype == np.float64
    assert isinstance(_misc.as_float(jnp.ones(2, jnp.float32), jnp.float64), jax.Array)
    assert _misc.as_float(jnp.ones(2, jnp.float32), jnp.float64).dtype == jnp.float64
    # Without a dtype a JAX array keeps its own and a host value becomes float64.
    assert _misc.as_float(jnp.ones(2, jnp.float32)).dtype == jnp.float32
    assert _misc.as_float(3).dtype == np.float64 and isinstance(_misc.as_float(3), np.ndarray)

    def total(x):
        mixed = _misc.as_float([x, 2.0], jnp.float64)
        assert isinstance(mixed, jax.core.Tracer)
        return jnp.sum(mixed * mixed)

    assert float(jax.grad(total)(3.0)) == 6.0


def test_host_and_device_inputs_give_the_same_solve():
    rod = hr.Rod(1.0, 1.5, 0.8)
    host = hr.solve_static(rod, [0.5, 0.1, -1.0], [0.1, 0.8, 0.2], 5.0, outputs=("wrench", "frame", "centreline"))
    device = hr.solve_static(rod, jnp.array([0.5, 0.1, -1.0]), jnp.array([0.1, 0.8, 0.2]), jnp.asarray(5.0),
                             frame0=jnp.eye(3), x0=jnp.zeros(3), outputs=("wrench", "frame", "centreline"))
    for a, b in ((host.n, device.n), (host.frame, device.frame), (host.x, device.x)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_replaced_is_dataclasses_replace_without_init():
    class Pair(eqx.Module):
        a: jax.Array
        b: jax.Array
        label: int = eqx.field(static=True)

        def __check_init__(self):
            calls.append(self.label)

    calls = []
    pair = Pair(jnp.arange(3.0), jnp.ones(2), 1)
    new = _misc.replaced(pair, b=jnp.zeros(2), label=7)
    expected = dataclasses.replace(pair, b=jnp.zeros(2), label=7)
    assert calls == [1, 7]  # the Module's own checks ran for `pair` and `dataclasses.replace`, not for `replaced`
    assert jax.tree.structure(new) == jax.tree.structure(expected) and new.label == 7
    for u, v in zip(jax.tree.leaves(new), jax.tree.leaves(expected)):
        np.testing.assert_array_equal(u, v)
    assert pair.label == 1 and np.all(np.asarray(pair.b) == 1.0)  # the original is untouched
    # Frozen, and freed when dropped: a copy made through equinox's `Module.__new__` stayed
    # registered as being initialised (writable, and alive for the life of the process).
    with pytest.raises(dataclasses.FrozenInstanceError):
        new.a = None
    import gc
    import weakref

    ref = weakref.ref(new)
    del new
    gc.collect()
    assert ref() is None


def test_tree_where_chooses_whole_trees_per_condition():
    new, old = (jnp.arange(3.0), {"m": jnp.eye(2)}), (jnp.zeros(3), {"m": jnp.zeros((2, 2))})
    for flag, expected in ((True, new), (False, old)):
        for u, v in zip(jax.tree.leaves(_misc.tree_where(flag, new, old)), jax.tree.leaves(expected)):
            np.testing.assert_array_equal(u, v)
    # Traced and batched: each point of a batch chooses its own tree.
    flags = jnp.array([True, False])
    batched = jax.vmap(lambda f: _misc.tree_where(f, new, old))(flags)
    np.testing.assert_array_equal(batched[0], np.stack([np.arange(3.0), np.zeros(3)]))
    np.testing.assert_array_equal(batched[1]["m"], np.stack([np.eye(2), np.zeros((2, 2))]))


def test_json_text_is_standard_json_and_reads_back():
    import json
    import math

    record = {"stderr": {"K1": math.inf, "K2": 0.5}, "values": [1.0, -math.inf, math.nan], "name": "fit", "n": 3}
    text = _misc.json_text(record)
    strict = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))
    assert strict["stderr"]["K1"] == "inf" and strict["values"][1:] == ["-inf", "nan"]
    back = _misc.json_record(text)
    assert back["stderr"] == {"K1": math.inf, "K2": 0.5} and back["name"] == "fit" and back["n"] == 3
    assert back["values"][:2] == [1.0, -math.inf] and math.isnan(back["values"][2])
    # Files written before (Python's Infinity and NaN constants) read too.
    assert _misc.json_record(json.dumps(record))["stderr"]["K1"] == math.inf


def test_write_atomically_gives_the_permissions_of_a_plain_write(tmp_path):
    """A new file gets the umask's permissions (not the temporary file's private 0600);
    a replaced one keeps its own."""
    import os
    import stat

    from helixrod._misc import write_atomically

    old = os.umask(0o022)
    try:
        fresh = tmp_path / "fresh.json"
        write_atomically(fresh, lambda f: f.write(b"{}"))
        assert stat.S_IMODE(fresh.stat().st_mode) == 0o644
        kept = tmp_path / "kept.json"
        kept.write_bytes(b"old")
        kept.chmod(0o640)
        write_atomically(kept, lambda f: f.write(b"new"))
        assert stat.S_IMODE(kept.stat().st_mode) == 0o640 and kept.read_bytes() == b"new"
    finally:
        os.umask(old)


def test_host_method_binds_like_a_method_without_a_module_per_access():
    """`host_method`: the same result as the plain method, bound by `functools.partial`
    (equinox builds a `BoundMethod` module at each access of a plain one); the class
    attribute is the function itself, and an abstract method stays abstract."""
    import abc

    class Scaled(eqx.Module):
        x: np.ndarray

        def plain(self, k):
            return self.x * k

        @_misc.host_method
        def on_host(self, k):
            """Scaled by k."""
            return self.x * k

    class Base(eqx.Module):
        @_misc.host_method
        @abc.abstractmethod
        def value(self) -> float:
            """The value."""

    class Concrete(Base):
        @_misc.host_method
        def value(self) -> float:
            return 2.0

    a = Scaled(np.arange(3.0))
    np.testing.assert_array_equal(a.on_host(2.0), a.plain(2.0))
    assert isinstance(a.on_host, functools.partial) and not isinstance(a.on_host, eqx.Module)
    assert isinstance(a.plain, eqx.Module)  # (what host_method avoids)
    assert Scaled.on_host(a, 3.0).tolist() == [0.0, 3.0, 6.0] and Scaled.on_host.__doc__ == "Scaled by k."
    assert Base.__abstractmethods__ == frozenset({"value"}) and not Concrete.__abstractmethods__
    with pytest.raises(TypeError):
        Base()
    assert Concrete().value() == 2.0


def test_default_starts_are_those_of_the_default_key_drawn_once():
    """The default fit's starts (`key=None`) are those of `jax.random.key(0)`, drawn once
    per shape: the cached draw is read-only and the starts are a new array each call."""
    from helixrod._fit._parameters import Parameterisation

    param = Parameterisation({"uhat1": 1.0, "uhat2": 0.0, "uhat3": 0.0}, 1.0, 1.0)
    z = np.array([0.1, 0.2, -0.3, 0.05, 0.0])
    default, explicit = param.starts(z, 6, None), param.starts(z, 6, jax.random.key(0))
    np.testing.assert_array_equal(default, explicit)
    np.testing.assert_array_equal(default[0], z)
    default[1] = 99.0
    np.testing.assert_array_equal(param.starts(z, 6, None), explicit)
    assert not np.array_equal(param.starts(z, 6, jax.random.key(1)), explicit)
