"""Helpers shared by the test files: the one comparison helper for pytrees, random rods,
and the rods, states and solve configurations that several test files use.

Test files import from here (`from helpers import ...`; pytest puts `tests/` on the path).
The shared solve configurations matter for the run time: JAX caches a compiled program per
process, and `--dist loadfile` runs each file in one process, so a configuration used by
two files compiles in both (see the comments at each of them).
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import helixrod as hr

# -- comparisons ------------------------------------------------------------------------------


def tree_allclose(a, b, *, rtol=1e-12, atol=0.0, equal_nan=True):
    """Assert that the pytrees `a` and `b` have the same structure (equal tree definitions,
    so equal static fields too) and close leaves: floating-point leaves by
    `np.testing.assert_allclose(rtol=, atol=, equal_nan=)`, every other leaf (integers,
    booleans, result codes) exactly; a failure names the leaf by its key path.  Returns
    True, so `assert tree_allclose(...)` reads naturally."""
    leaves_a, tree_a = jax.tree_util.tree_flatten_with_path(a)
    leaves_b, tree_b = jax.tree.flatten(b)
    assert tree_a == tree_b, f"the pytrees differ in structure:\n  {tree_a}\n  {tree_b}"
    for (path, x), y in zip(leaves_a, leaves_b):
        where = jax.tree_util.keystr(path) or "(root)"
        x, y = np.asarray(x), np.asarray(y)
        assert x.shape == y.shape, f"{where}: shapes {x.shape} and {y.shape} differ"
        if np.issubdtype(x.dtype, np.inexact) or np.issubdtype(y.dtype, np.inexact):
            np.testing.assert_allclose(x, y, rtol=rtol, atol=atol, equal_nan=equal_nan, err_msg=where)
        else:
            np.testing.assert_array_equal(x, y, err_msg=where)
    return True


def parameter_vector(rod):
    """The parameters of `rod` as a NumPy vector (K1, K2, K3, K13, K23, uhat1, uhat2, uhat3)."""
    return np.concatenate([[float(rod.K1), float(rod.K2), float(rod.K3), float(rod.K13), float(rod.K23)], np.asarray(rod.uhat)])


# -- random rods ------------------------------------------------------------------------------


def random_rods(rng, n):
    """Random canonical, coupled, intrinsically curved rods (positive definite)."""
    rods = []
    while len(rods) < n:
        K1 = rng.uniform(0.3, 2.0)
        K2 = K1 * rng.uniform(1.0, 3.0)
        K3 = rng.uniform(0.3, 2.0)
        K13, K23 = rng.normal(scale=0.4, size=2)
        if K3 - K13**2 / K1 - K23**2 / K2 <= 0.05:
            continue
        rods.append(hr.Rod(K1, K2, K3, K13, K23, rng.normal(scale=0.8, size=3)))
    return rods


# -- the classical open-coiled spring (test_spring, test_datasets) ----------------------------


def classical_compliance(B, Cw, radius, alpha, length):
    """Castigliano for an isotropic wire: U = L (T^2/2Cw + Mb^2/2B) with the twisting moment
    T = P r cos a + Q sin a and bending moment Mb = Q cos a - P r sin a (Love §270)."""
    s, c = math.sin(alpha), math.cos(alpha)
    cross = length * radius * s * c * (1 / Cw - 1 / B)
    return np.array([[length * radius**2 * (c * c / Cw + s * s / B), cross], [cross, length * (s * s / Cw + c * c / B)]])


# -- the static Kirchhoff equations (test_kirchhoff, test_lie, test_geometry, test_constitutive) --

KIRCHHOFF_ROD = hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
# (kappa, tau) = (1, 0.5), slot 0: a spatially stable helix (the linearised wrench flow has
# purely imaginary eigenvalues), so round-off is not amplified exponentially along s.
KIRCHHOFF_EQ = hr.helix_equilibria(KIRCHHOFF_ROD, 1.0, 0.5)
N0, M0, FRAME0, X0 = (a[0] for a in hr.helix_initial_conditions(KIRCHHOFF_EQ))
# A non-helical solution: the helix wrench perturbed.
N1 = N0 + jnp.array([0.05, -0.1, 0.08])
M1 = M0 + jnp.array([0.1, 0.05, -0.07])
ROT1 = np.asarray(hr.so3_exp(jnp.array([0.3, -0.2, 0.5])))


@eqx.filter_jit
def solve_fixed(n0, m0, frame0, x0, length, steps, solver=hr.CommutatorFreeRK4()):
    """`steps` fixed steps of `solver` on `KIRCHHOFF_ROD` (frame and centreline), jitted."""
    return hr.solve_static(
        KIRCHHOFF_ROD, n0, m0, length, frame0=frame0, x0=x0, outputs=("frame", "centreline"), steps=steps,
        max_steps=4096, solver=solver,
    )


# -- finite rods (test_bvp_*, test_kirchhoff, test_cli) ----------------------------------------

# A coupled, anisotropic rod whose intrinsic shape is a helix with a generic register.
BVP_ROD = hr.Rod(1.0, 1.4, 0.8, K13=0.15, K23=-0.1, uhat=(0.3, 0.9, 0.35))
# A spring (isotropic wire, nu = 0.3) for the response curves.
SPRING = hr.Rod(1.0, 1.0, 1 / 1.3, uhat=(0.0, 1.0, 0.3))
SPRING_NORM = float(np.hypot(1.0, 0.3))
SPRING_TURN = 2 * np.pi / SPRING_NORM
# Every eager `solve` below has 9 save points and a `(n0, m0)` guess: one compilation per
# process for all end types (and one more for each other number of segments).
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


# -- sweeps (test_sweep, test_plot, test_cli) ---------------------------------------------------

SWEEP_ROD = hr.Rod(1.0, 1.7, 0.9, K13=0.3, K23=-0.2, uhat=(0.8, 0.3, 0.4))
SWEEP_KAPPA = np.concatenate([[0.0], np.linspace(0.05, 3.0, 37)])
SWEEP_TAU = np.linspace(-3.0, 3.0, 53)
SENS_KAPPA = np.array([0.4, 1.1, 2.3])
SENS_TAU = np.array([-1.2, 0.5, 1.7])

# One compiled reference for every test: flat batches of N_REF points.
N_REF = 64
_equilibria = jax.jit(hr.helix_equilibria)


def reference(rod, kappa, tau):
    """`helix_equilibria` point by point (one jitted program of N_REF points, padded)."""
    kappa, tau = np.broadcast_arrays(np.asarray(kappa, float), np.asarray(tau, float))
    n = kappa.size
    pad = lambda x: jnp.asarray(np.pad(x.ravel(), (0, N_REF - n), mode="edge"))  # noqa: E731
    eq = _equilibria(rod, pad(kappa), pad(tau))
    return jax.tree_util.tree_map(lambda x: np.asarray(x)[:n].reshape(kappa.shape + x.shape[1:]), eq)


def sweep_atlas():
    """Every field of SWEEP_ROD over SWEEP_KAPPA x SWEEP_TAU; chunk_size 512 over 2014
    points: four chunks, the last one padded."""
    return hr.sweep(SWEEP_ROD, SWEEP_KAPPA, SWEEP_TAU, fields=hr.SweepResult.FIELDS, chunk_size=512, progress=False)


def sweep_sensitivity():
    """Sensitivities of SWEEP_ROD at SENS_KAPPA x SENS_TAU."""
    return hr.sensitivity(SWEEP_ROD, SENS_KAPPA, SENS_TAU, progress=False)


# -- helix fits (test_fit_*) --------------------------------------------------------------------

# Every 24-point fit with the five stiffnesses free and uhat fixed shares one compilation
# (the values of uhat are traced) within a process.
FIT_POINTS = 24


def fit_grid(rng):
    """FIT_POINTS random helices (kappa, tau) of the fit tests."""
    return rng.uniform(0.2, 2.5, FIT_POINTS), rng.uniform(-2.0, 2.0, FIT_POINTS)


#: The helices with errors in variables of the fit tests: generating stiffnesses (K1, K2,
#: K3, K13, K23), intrinsic twist, and the sigmas of kappa, tau, F and M.
EIV_TRUTH, EIV_UHAT, EIV_SIGMAS = (1.0, 1.5, 0.8, 0.5, 0.5), (1.0, 0.0, 0.0), (0.02, 0.02, 0.01, 0.01)


def eiv_helix_data(n=30, seed=0):
    """`n` helices of the rod `EIV_TRUTH`, every value of (kappa, tau, F, M) drawn with its
    sigma of `EIV_SIGMAS`, carried by the data (errors in variables on by default)."""
    rng = np.random.default_rng(seed)
    kappa, tau = rng.uniform(0.3, 2.0, n), rng.uniform(-1.5, 1.5, n)
    eq = hr.helix_equilibria(hr.Rod(*EIV_TRUTH, EIV_UHAT), kappa, tau)
    ks, ts, sf, sm = EIV_SIGMAS
    noise = rng.normal(size=(4, n))
    return hr.HelixData(
        np.asarray(eq.force[:, 0]) + sf * noise[0], np.asarray(eq.moment[:, 0]) + sm * noise[1],
        kappa + ks * noise[2], tau + ts * noise[3], force_sigma=sf, moment_sigma=sm,
        kappa_sigma=np.full(n, ks), tau_sigma=np.full(n, ts),
    )
