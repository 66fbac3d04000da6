"""Register roots against an independent reference: dense scan + mpmath bisection."""

import os
import sys

import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest

from helixrod import register_roots

mpmath.mp.dps = 40

solve = jax.jit(register_roots)


def reference_roots(A, B, C, n=6000):
    """All roots of A sin 2p + B sin p + C cos p on [0, 2 pi): dense sign scan, then mpmath
    bisection on each bracket (40 digits); exact zeros on the grid are roots too."""
    f = lambda p: A * mpmath.sin(2 * p) + B * mpmath.sin(p) + C * mpmath.cos(p)  # noqa: E731
    grid = np.linspace(0.0, 2 * np.pi, n + 1)
    values = A * np.sin(2 * grid) + B * np.sin(grid) + C * np.cos(grid)
    roots = []
    for i in range(n):
        if values[i] == 0:
            roots.append(grid[i])
        elif values[i] * values[i + 1] < 0:
            roots.append(float(mpmath.findroot(f, (grid[i], grid[i + 1]), solver="bisect")))
    return np.array(roots)


def angular_distance(x, y):
    return np.abs(np.angle(np.exp(1j * (x - y))))


def check_against_reference(A, B, C, tol):
    phi, _, _, valid, continuum, _ = (np.asarray(x) for x in solve(A, B, C))
    for i in range(len(A)):
        ref = np.sort(reference_roots(A[i], B[i], C[i]))
        ours = np.sort(phi[i][valid[i]])
        assert len(ours) == len(ref), (A[i], B[i], C[i], ours, ref)
        assert np.max(angular_distance(ours, ref)) <= tol, (A[i], B[i], C[i], ours, ref)


def test_random_coefficients(rng):
    n = 60
    A = rng.normal(size=n) * np.exp(rng.uniform(-3, 3, n))
    B, C = rng.normal(size=n), rng.normal(size=n)
    check_against_reference(A, B, C, 1e-12)


def test_exact_zero_coefficients(rng):
    """Uncoupled rods give B = 0 or C = 0 exactly: roots sit on quadrant edges."""
    n = 40
    A = rng.normal(size=n)
    B, C = rng.normal(size=n), rng.normal(size=n)
    B[:15] = 0.0
    C[15:30] = 0.0
    B[30:] = 0.0
    C[30:] = 0.0
    A[35:] = 0.0  # A = B = C = 0 is the continuum, tested elsewhere: dropped below
    keep = ~((A == 0) & (B == 0) & (C == 0))
    check_against_reference(A[keep], B[keep], C[keep], 1e-12)


def test_slots_are_minimum_maximum_and_pair(rng):
    """Slot 0 is the global minimum of G = -A/2 cos 2p - B cos p + C sin p on the circle,
    slot 1 the global maximum, slot 2 a local minimum, slot 3 a local maximum."""
    n = 400
    A, B, C = rng.normal(size=(3, n))
    phi, cos_phi, sin_phi, valid, _, _ = (np.asarray(x) for x in solve(A, B, C))
    grid = np.linspace(0, 2 * np.pi, 20001)
    G = lambda p: -0.5 * A[:, None] * np.cos(2 * p) - B[:, None] * np.cos(p) + C[:, None] * np.sin(p)  # noqa: E731
    dense = G(grid[None, :])
    at = G(phi)
    assert np.all(at[:, 0] <= dense.min(axis=1) + 1e-12)
    assert np.all(at[:, 1] >= dense.max(axis=1) - 1e-12)
    fprime = 2 * A[:, None] * np.cos(2 * phi) + B[:, None] * np.cos(phi) - C[:, None] * np.sin(phi)
    assert np.all(fprime[:, 0] > 0) and np.all(fprime[:, 1] < 0)
    pair = valid[:, 2]
    assert np.all(fprime[pair, 2] > 0) and np.all(fprime[pair, 3] < 0)
    assert np.all(valid[:, 2] == valid[:, 3])
    np.testing.assert_allclose(cos_phi[valid], np.cos(phi[valid]), atol=2e-15)
    np.testing.assert_allclose(sin_phi[valid], np.sin(phi[valid]), atol=2e-15)


def test_count_matches_astroid(rng):
    n = 2000
    A, B, C = rng.normal(size=(3, n))
    valid = np.asarray(solve(A, B, C)[3])
    inside = np.abs(B) ** (2 / 3) + np.abs(C) ** (2 / 3) < np.abs(2 * A) ** (2 / 3)
    np.testing.assert_array_equal(valid.sum(axis=1), np.where(inside, 4, 2))


@pytest.mark.parametrize("gap", [1e-2, 1e-4, 1e-6])
def test_near_tangent_pairs(gap):
    """Coefficients built so that the inner pair sits at p0 +- gap: f = A sin2p + ... with
    f(p0 +- gap) = 0 imposed analytically (A = 1, solve the 2x2 system for B, C)."""
    p0 = np.linspace(0.3, 6.0, 9)
    A = np.ones_like(p0)
    B = np.empty_like(p0)
    C = np.empty_like(p0)
    for i, p in enumerate(p0):
        ps = np.array([p - gap, p + gap])
        M = np.stack([np.sin(ps), np.cos(ps)], axis=1)
        B[i], C[i] = np.linalg.solve(M, -np.sin(2 * ps))
    phi, _, _, valid, _, tangent = (np.asarray(x) for x in solve(A, B, C))
    for i, p in enumerate(p0):
        ours = phi[i][valid[i]]
        for target in (p - gap, p + gap):
            # Accuracy near a double root is limited to ~eps / gap.
            assert np.min(angular_distance(ours, target)) <= max(1e-12, 4e-16 / gap)


def test_gradient_matches_central_differences(rng):
    A, B, C = 0.7, -0.2, 0.3

    def slot_phi(x, s):
        return register_roots(x[0], x[1], x[2])[0][s]

    x0 = jnp.array([A, B, C])
    for s in range(4):
        g = jax.grad(slot_phi)(x0, s)
        h = 1e-6
        fd = np.array([(slot_phi(x0.at[i].add(h), s) - slot_phi(x0.at[i].add(-h), s)) / (2 * h) for i in range(3)])
        np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)


def test_fallback_agrees_with_fast_path(rng):
    """Points the fast path leaves unconverged are re-solved with many more Newton steps;
    where the fast path did converge, the long solve gives the same roots.  On coefficients
    with ratios up to ~1e7 the fast path converges at > 99% of points."""
    from helixrod import _roots

    n = 3000
    A, B, C = (rng.normal(size=n) * np.exp(rng.uniform(-8, 8, n)) for _ in range(3))
    fast = [np.asarray(x) for x in jax.jit(_roots._solve)(A, B, C)]
    long = [np.asarray(x) for x in jax.jit(lambda a, b, c: _roots._solve(a, b, c, careful=True))(A, B, C)]
    # (..., converged, complete); four slots are always complete.
    assert fast[-2].mean() > 0.99 and long[-2].all() and fast[-1].all()
    both = fast[3] & fast[-2][:, None]
    assert np.max(np.where(both, angular_distance(fast[0], long[0]), 0)) < 1e-14
    merged = [np.asarray(x) for x in solve(A, B, C)]
    np.testing.assert_array_equal(merged[3], long[3])
    assert np.max(np.where(merged[3], angular_distance(merged[0], long[0]), 0)) < 1e-14


def test_outer_stage_matches_the_four_slot_solve(rng):
    """The first stage on a CPU solves only the two outer slots and marks the points that
    have (or may have) an inner pair incomplete; its slots equal those of the four-slot
    solve, and every point with a valid inner slot is marked, on random coefficients and
    on exact zeros (the closed forms)."""
    from helixrod import _roots

    n = 3000
    A, B, C = (rng.normal(size=n) * np.exp(rng.uniform(-4, 4, n)) for _ in range(3))
    B[:300] = 0.0
    C[300:600] = 0.0
    outer = [np.asarray(x) for x in jax.jit(lambda a, b, c: _roots._solve(a, b, c, slots=(0, 1)))(A, B, C)]
    full = [np.asarray(x) for x in jax.jit(_roots._solve)(A, B, C)]
    phi, valid, complete = outer[0], outer[3], outer[-1]
    assert phi.shape == (n, 2)
    np.testing.assert_array_equal(valid, full[3][:, :2])
    converged = outer[-2] & full[-2]
    assert np.max(np.where(valid & converged[:, None], angular_distance(phi, full[0][:, :2]), 0)) < 1e-14
    assert not np.any(complete & full[3][:, 2])
    assert 0.05 < 1 - complete.mean() < 0.95


def test_angle_against_mpmath(rng):
    """phi from (cos, sin) by the octant reduction and polynomial of `_roots._angle`, against
    40-digit atan2 of the same float64 pair: random angles, the axes and diagonals (the
    octant boundaries) with their neighbours, signed zeros, and angles just below 2 pi."""
    from helixrod import _roots

    special = np.concatenate([np.arange(16) * np.pi / 8, np.arange(16) * np.pi / 8 + 1e-9, [2 * np.pi - 1e-12]])
    angles = np.concatenate([rng.uniform(0, 2 * np.pi, 4000), special, np.nextafter(special, -1)])
    c, s = np.cos(angles), np.sin(angles)
    c = np.concatenate([c, [1.0, -1.0, 0.0, -0.0]])
    s = np.concatenate([s, [-0.0, -0.0, 1.0, -1.0]])
    phi = np.asarray(jax.jit(_roots._angle)(c, s))
    ref = np.array([float(mpmath.atan2(y, x) % (2 * mpmath.pi)) for x, y in zip(c, s)])
    assert np.all((phi >= 0) & (phi < 2 * np.pi))
    assert np.max(angular_distance(phi, ref)) <= 9e-16


def astroid_points(rng, n, offset):
    """Coefficients (A, B, C) = (1, 2 cos^3 t, 2 sin^3 t) (1 + offset): on the astroid,
    where the inner pair is born, moved inside (offset < 0) or outside by `offset`."""
    t = rng.uniform(0, 2 * np.pi, n)
    return np.ones(n), 2 * np.cos(t) ** 3 * (1 + offset), 2 * np.sin(t) ** 3 * (1 + offset)


def test_cpu_kernel_matches_the_xla_program(rng):
    """On a CPU with numba (the test extra), `register_roots` runs the compiled register
    kernel; it solves what `_roots`' XLA program solves (used on accelerators, in float32
    and without numba): the same slots, flags and registers to rounding, on random
    coefficients over 16 decades of ratios, exact zeros and the continuum, negative A,
    non-finite inputs, both sides of the astroid near it, and the cusps."""
    from helixrod import _roots

    kernel = _roots.cpu_kernel()
    assert kernel is not None, "numba (in the test extra) and HELIXROD_REGISTER_KERNEL unset"
    n = 20000
    A, B, C = (rng.normal(size=n) * np.exp(rng.uniform(-18, 18, n)) for _ in range(3))
    B[:500], C[500:1000], A[1000:1200] = 0.0, 0.0, 0.0
    A[1200:1300] = B[1200:1300] = C[1200:1300] = 0.0
    A[1300:1310], B[1310:1320], C[1320:1330] = np.nan, np.inf, -np.inf
    for lo, offset in ((2000, -1e-6), (3000, 1e-6), (4000, -1e-3), (5000, 1e-3)):
        A[lo:lo + 1000], B[lo:lo + 1000], C[lo:lo + 1000] = astroid_points(rng, 1000, offset)
    cusps = slice(6000, 6400)  # (B, C) near (+-2, 0) and (0, +-2): a nearly triple root
    A[cusps] = 1.0
    B[cusps] = rng.choice([-2.0, 2.0], 400) * (1 - 10.0 ** rng.uniform(-12, -3, 400))
    C[cusps] = rng.normal(size=400) * 1e-6
    B[6200:6400], C[6200:6400] = C[6200:6400], B[6200:6400]
    A[6400:8000] *= -np.sign(A[6400:8000])

    ours = [np.asarray(x) for x in jax.jit(kernel.solve)(A, B, C)]
    xla = [np.asarray(x) for x in jax.jit(_roots._solve_in_xla)(A, B, C)]
    cos_k, sin_k, valid_k, continuum_k, tangent_k = ours
    _, cos_x, sin_x, valid_x, continuum_x, tangent_x = xla
    np.testing.assert_array_equal(valid_k, valid_x)
    np.testing.assert_array_equal(continuum_k, continuum_x)
    np.testing.assert_array_equal(tangent_k, tangent_x)
    assert not valid_k[1300:1330].any() and continuum_k[1200:1300].all()
    assert (valid_k[2000:3000, 2:].all() and not valid_k[3000:4000, 2:].any())
    # Registers next to a tangency (a nearly double root, 1e-3 apart at offset 1e-6) are
    # conditioned like eps / 1e-3, next to a cusp (a nearly triple root) like eps^(1/3).
    tol = np.full(n, 1e-13)
    tol[2000:4000] = 1e-11
    tol[cusps] = 1e-8
    for ours_, theirs in ((cos_k, cos_x), (sin_k, sin_x)):
        assert np.all(np.isfinite(ours_))
        err = np.where(valid_k, np.abs(ours_ - theirs), 0.0).max(axis=1)
        assert np.all(err <= tol), (np.argmax(err / tol), err.max())
    # Every register is a root of f, by either program.
    phi = np.arctan2(sin_k, cos_k)
    with np.errstate(invalid="ignore"):  # the non-finite points, masked below
        f = A[:, None] * np.sin(2 * phi) + B[:, None] * np.sin(phi) + C[:, None] * np.cos(phi)
    scale = np.maximum.reduce([np.abs(A), np.abs(B), np.abs(C)])[:, None]
    ok = valid_k & ~continuum_k[:, None]
    assert np.max(np.abs(np.where(ok, f / np.where(ok, scale, 1.0), 0.0))) < 1e-13


def test_register_kernel_can_be_turned_off(tmp_path):
    """`HELIXROD_REGISTER_KERNEL=0` keeps the registers in XLA (read at import): the
    same equilibria as with the kernel."""
    import subprocess
    import sys

    code = (
        "import jax; jax.config.update('jax_enable_x64', True)\n"
        "import numpy as np, helixrod as hr\n"
        "from helixrod import _roots\n"
        "assert _roots.cpu_kernel() is None\n"
        "rod = hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))\n"
        "eq = hr.helix_equilibria(rod, np.linspace(0.1, 3, 50)[:, None], np.linspace(-3, 3, 40))\n"
        f"np.save({str(tmp_path / 'phi.npy')!r}, np.asarray(eq.phi))\n"
    )
    env = dict(os.environ, HELIXROD_REGISTER_KERNEL="0")
    subprocess.run([sys.executable, "-c", code], check=True, env=env, timeout=600)
    import helixrod as hr

    rod = hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
    eq = hr.helix_equilibria(rod, np.linspace(0.1, 3, 50)[:, None], np.linspace(-3, 3, 40))
    xla = np.load(tmp_path / "phi.npy")
    np.testing.assert_array_equal(np.isnan(xla), np.isnan(np.asarray(eq.phi)))
    assert np.nanmax(angular_distance(xla, np.asarray(eq.phi))) < 1e-13


def test_register_kernel_is_found_from_inside_a_trace():
    """The kernel's first use may come while JAX traces a caller's program (the check it
    runs then must not be staged into that program): found, no warning."""
    import warnings

    from helixrod import _roots

    _roots.cpu_kernel.cache_clear()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        phi = jax.jit(lambda a: register_roots(a, 0.3, -0.4)[0])(1.0)
    assert _roots.cpu_kernel() is not None
    assert np.isfinite(np.asarray(phi)[:2]).all()


def test_second_derivatives_match_central_differences():
    """Second derivatives (a tweezer fit's Jacobian of derivatives) take the implicit-function
    rule twice (the compiled kernel itself has no derivative): the Hessian of a register
    equals central differences of its gradient, for every slot of a point with four."""
    x0 = jnp.array([0.7, -0.2, 0.3])
    for s in range(4):
        def slot_phi(x, s=s):
            return register_roots(x[0], x[1], x[2])[0][s]

        hessian = jax.jit(jax.hessian(slot_phi))(x0)
        gradient = jax.jit(jax.grad(slot_phi))
        h = 1e-5
        fd = np.stack([(gradient(x0.at[i].add(h)) - gradient(x0.at[i].add(-h))) / (2 * h) for i in range(3)])
        np.testing.assert_allclose(hessian, fd, rtol=1e-6, atol=1e-7)


def test_wrench_kernel_matches_the_xla_program(rng):
    """`helix_equilibria` asked for fields among phi, valid, force, moment and stable of
    one float64 rod runs the compiled kernel of the wrench (one pass, the registers and
    their wrench per block); it returns what XLA's program returns, to rounding: coupled
    rods with intrinsic curvature, an isotropic rod (a continuum at tau = uhat3), kappa = 0,
    negative and non-finite inputs, a tiny kappa; under `jax.vmap` over rods and over
    points; and derivatives through it are XLA's program's (the kernel has none)."""
    import helixrod as hr
    from helixrod import _equilibria

    wrench = ("phi", "valid", "force", "moment", "stable")
    n = 3000
    kappa, tau = rng.uniform(0.01, 3.0, n), rng.uniform(-3.0, 3.0, n)
    kappa[:8] = [0.0, -1.0, np.nan, np.inf, 0.5, 1.0, 1e-200, 0.7]
    tau[:8] = [1.0, 1.0, 1.0, 1.0, np.nan, np.inf, 0.3, 0.2]
    kappa, tau = jnp.asarray(kappa), jnp.asarray(tau)
    rods = [
        hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.2, -0.1)),
        hr.Rod(0.7, 2.1, 1.3, K13=-0.3, K23=0.6, uhat=(-0.4, 0.9, 0.5)),
        hr.Rod(1.0, 1.0, 1.0, uhat=(0.0, 0.0, 0.2)),
    ]
    xla = jax.jit(lambda rod, k, t: _equilibria._fields_in_xla(rod, k, t, wrench))
    for rod in rods:
        assert _equilibria._wrench_kernel(rod, kappa, wrench) is not None
        ours, theirs = hr.helix_equilibria(rod, kappa, tau, fields=wrench), xla(rod, kappa, tau)
        np.testing.assert_array_equal(ours.valid, theirs.valid)
        np.testing.assert_array_equal(ours.stable, theirs.stable)
        assert ours.u is None and ours.energy is None
        for name in ("force", "moment"):
            np.testing.assert_allclose(getattr(ours, name), getattr(theirs, name), rtol=1e-12, atol=1e-12)
        assert np.nanmax(angular_distance(np.asarray(ours.phi), np.asarray(theirs.phi))) < 1e-13
    continuum = hr.helix_equilibria(rods[2], 0.5, 0.2, fields=wrench)
    assert np.asarray(continuum.valid).tolist() == [True, False, False, False] and not np.asarray(continuum.stable).any()
    # vmap over rods (the kernel's rows) and over points.
    params = jnp.asarray([[r.K1, r.K2, r.K3, r.K13, r.K23, *r.uhat] for r in rods])
    as_rod = lambda p: hr.Rod(p[0], p[1], p[2], p[3], p[4], p[5:8])  # noqa: E731
    mapped = jax.vmap(lambda p: hr.helix_equilibria(as_rod(p), kappa, tau, fields=wrench).force)(params)
    for row, rod in zip(np.asarray(mapped), rods):
        np.testing.assert_allclose(row, xla(rod, kappa, tau).force, rtol=1e-12, atol=1e-12)
    points = jax.vmap(lambda k, t: hr.helix_equilibria(rods[0], k, t, fields=wrench).moment)(kappa[:50], tau[:50])
    np.testing.assert_allclose(points, xla(rods[0], kappa[:50], tau[:50]).moment, rtol=1e-12, atol=1e-12)
    # Derivatives: those of XLA's program.
    k, t = kappa[8:200], tau[8:200]
    loss = lambda fields_of: lambda rod: jnp.nansum(fields_of(rod).force * fields_of(rod).moment)  # noqa: E731
    ours = jax.grad(loss(lambda rod: hr.helix_equilibria(rod, k, t, fields=wrench)))(rods[1])
    theirs = jax.grad(loss(lambda rod: _equilibria._fields_in_xla(rod, k, t, wrench)))(rods[1])
    for a, b in zip(jax.tree.leaves(ours), jax.tree.leaves(theirs)):
        np.testing.assert_allclose(a, b, rtol=1e-11)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="huge pages are Linux's")
def test_register_kernel_advises_large_results_to_take_huge_pages():
    """The kernel asks Linux for huge pages on results of 4 MB or more before it writes
    them (XLA maps a large result afresh at every call; one page fault per 4 KB page cost
    10^7 points 0.36 s): the mapping carries the advice (`hg` in its `VmFlags`), a small
    one does not.  The advice itself, not whether huge pages are free, is what is tested."""
    import mmap
    import re

    pytest.importorskip("numba")
    from helixrod import _register_kernel

    def advised(array):
        address, inside = array.ctypes.data, False
        with open("/proc/self/smaps") as smaps:
            for line in smaps:
                mapping = re.match(r"([0-9a-f]+)-([0-9a-f]+) ", line)
                if mapping:
                    inside = int(mapping[1], 16) <= address < int(mapping[2], 16)
                elif inside and line.startswith("VmFlags:"):
                    return "hg" in line.split()[1:]
        raise AssertionError("the array's mapping is not in /proc/self/smaps")

    for size, expected in ((8 << 20, True), (1 << 20, False)):
        mapping = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)  # a mapping of its own, as XLA's
        array = np.frombuffer(mapping, np.float64)
        _register_kernel._advise_huge_pages(array)
        assert advised(array) == expected
        del array
        mapping.close()
