"""helix_equilibria against closed forms (Love's open-coiled spring), the balance
equations, finite differences, and the hard corners."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_rods, tree_allclose

import helixrod as hr

equilibria = jax.jit(hr.helix_equilibria)


def love_isotropic(B, C, uhat3, radius, alpha):
    """Axial force and moment of an isotropic, naturally straight-or-twisted wire bent into
    a helix of radius r and pitch angle alpha, from the lab-frame (Frenet) balance
    m' + t x n = 0 with m = B kappa b + C (tau - uhat3) t and n = F e_z (Love, art. 270-271):
    F = (C (tau - uhat3) - B tau) cos(alpha) / r,  M = B kappa cos(alpha) + C (tau - uhat3) sin(alpha)."""
    kappa = np.cos(alpha) ** 2 / radius
    tau = np.sin(alpha) * np.cos(alpha) / radius
    F = (C * (tau - uhat3) - B * tau) * np.cos(alpha) / radius
    M = B * kappa * np.cos(alpha) + C * (tau - uhat3) * np.sin(alpha)
    return kappa, tau, F, M


def test_isotropic_matches_love():
    B, C, uhat3 = 1.3, 0.9, 0.4
    alpha = np.linspace(-1.4, 1.4, 15)
    radius = np.linspace(0.3, 3.0, 15)
    kappa, tau, F, M = love_isotropic(B, C, uhat3, radius, alpha)
    eq = equilibria(hr.Rod(B, B, C, uhat=(0.0, 0.0, uhat3)), kappa, tau)
    assert bool(jnp.all(eq.continuum))
    np.testing.assert_allclose(eq.force[:, 0], F, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(eq.moment[:, 0], M, rtol=1e-12, atol=1e-13)


def test_residual_zero_and_counts(rng):
    kappa = jnp.asarray(rng.uniform(0.01, 4.0, 64))
    tau = jnp.asarray(rng.uniform(-4.0, 4.0, 64))
    for rod in random_rods(rng, 4):
        eq = equilibria(rod, kappa, tau)
        scale = 1 + jnp.nanmax(jnp.abs(eq.m)) + jnp.nanmax(jnp.abs(eq.n))
        res = hr.helix_residual(rod, eq.u, eq.n)
        assert float(jnp.nanmax(jnp.abs(res))) < 1e-12 * float(scale)
        assert bool(jnp.all(eq.count >= 2))
        # m = mu1 u + mu2 e3 and the first integrals
        m_rebuilt = np.asarray(eq.mu1)[..., None] * np.asarray(eq.u) + np.asarray(eq.mu2)[..., None] * np.array([0.0, 0.0, 1.0])
        np.testing.assert_allclose(np.asarray(eq.m)[eq.valid], np.asarray(m_rebuilt)[eq.valid], atol=1e-12)
        np.testing.assert_allclose(eq.I1, jnp.sum(eq.n**2, -1), rtol=1e-12)
        # stable is the sign of d2W/dphi2, which matches a finite difference of W(phi)
        h = 1e-4

        def W(phi):
            u = jnp.stack([kappa[:, None] * jnp.sin(phi), kappa[:, None] * jnp.cos(phi), jnp.broadcast_to(tau[:, None], phi.shape)], -1)
            return rod.energy(u)

        fd = (W(eq.phi + h) - 2 * W(eq.phi) + W(eq.phi - h)) / h**2
        ok = eq.valid & (jnp.abs(eq.d2energy) > 1e-5)
        np.testing.assert_allclose(np.asarray(fd)[ok], np.asarray(eq.d2energy)[ok], rtol=1e-5, atol=1e-6)
        assert bool(jnp.all(eq.stable == (eq.valid & (eq.d2energy > 0))))


def test_axial_force_definition(rng):
    rod = random_rods(rng, 1)[0]
    eq = equilibria(rod, 0.8, 1.1)
    axis = eq.u / jnp.linalg.norm(eq.u, axis=-1, keepdims=True)
    np.testing.assert_allclose(eq.force, jnp.sum(eq.n * axis, -1), rtol=1e-12)
    np.testing.assert_allclose(eq.moment, jnp.sum(eq.m * axis, -1), rtol=1e-12)
    np.testing.assert_allclose(eq.tension, eq.n[..., 2], rtol=1e-12)


def test_shapes_broadcast():
    rod = hr.Rod(1.0, 1.5, 0.8, 0.5, 0.5, (1.0, 0.0, 0.0))
    eq = hr.helix_equilibria(rod, jnp.ones((3, 1)), jnp.ones((1, 5)))
    assert eq.phi.shape == (3, 5, 4) and eq.u.shape == (3, 5, 4, 3) and eq.continuum.shape == (3, 5)
    with pytest.raises(ValueError, match="broadcast"):
        hr.helix_equilibria(rod, jnp.ones(3), jnp.ones(4))


def test_flags_bad_points_without_spoiling_batch():
    rod = hr.Rod(1.0, 1.5, 0.8, 0.5, 0.5, (1.0, 0.0, 0.0))
    kappa = jnp.array([0.5, jnp.nan, -1.0, 0.0, 0.7])
    eq = equilibria(rod, kappa, 1.0)
    assert eq.count.tolist() == [int(eq.count[0]), 0, 0, 0, int(eq.count[4])]
    assert bool(eq.straight[3]) and not bool(eq.straight[1])
    # The same compiled program on the batch with the bad points replaced: the good points
    # are bit for bit the same (another program, e.g. eager mode, may round differently).
    good = equilibria(rod, jnp.array([0.5, 1.0, 1.0, 1.0, 0.7]), 1.0)
    np.testing.assert_array_equal(np.asarray(eq.force)[[0, 4]], np.asarray(good.force)[[0, 4]])


def test_wrench_diverges_as_kappa_to_zero():
    """An intrinsically curved rod cannot be held straight by a finite wrench."""
    rod = hr.Rod(1.0, 1.5, 0.8, uhat=(1.0, 0.0, 0.0))
    kappa = jnp.array([1e-2, 1e-4, 1e-6, 1e-8])
    eq = equilibria(rod, kappa, 0.5)
    growth = np.abs(np.asarray(eq.mu1[:, 0])) * np.asarray(kappa)
    np.testing.assert_allclose(growth, growth[-1], rtol=1e-2)


def test_nearly_isotropic_and_degenerate_quartic():
    """K1 - K2 -> 0 (relative 1e-2 ... 1e-14): four registers on the axes persist; at
    K1 = K2 with couplings the quartic degenerates and two registers remain."""
    for rel in [1e-2, 1e-6, 1e-10, 1e-14]:
        eq = equilibria(hr.Rod(1.0, 1.0 + rel, 0.7), 0.9, 0.3)
        assert int(eq.count) == 4
        np.testing.assert_allclose(np.sort(np.asarray(eq.phi)), np.arange(4) * np.pi / 2, atol=1e-14)
    eq = equilibria(hr.Rod(1.0, 1.0, 0.9, 0.2, -0.1), 0.9, 0.3)
    assert int(eq.count) == 2 and not bool(eq.continuum)
    assert float(jnp.nanmax(jnp.abs(hr.helix_residual(hr.Rod(1.0, 1.0, 0.9, 0.2, -0.1), eq.u, eq.n)))) < 1e-13


def test_extreme_stiffness_ratios_and_scale_equivariance(rng):
    kappa = jnp.asarray(rng.uniform(0.1, 3, 32))
    tau = jnp.asarray(rng.uniform(-3, 3, 32))
    for ratio in [1e-6, 1e6]:
        rod = hr.Rod(1.0, 1.0 + ratio, ratio, 0.0, 0.0, (0.3, -0.2, 0.1))
        eq = equilibria(rod, kappa, tau)
        res = hr.helix_residual(rod, eq.u, eq.n)
        assert float(jnp.nanmax(jnp.abs(res))) < 1e-11 * (1 + ratio)
    rod = random_rods(rng, 1)[0]
    for factor in [1e-27, 1e12]:
        a = equilibria(rod, kappa, tau)
        b = equilibria(rod.scaled(factor), kappa, tau)
        np.testing.assert_allclose(b.force / factor, a.force, rtol=1e-12)
        np.testing.assert_allclose(b.phi, a.phi, atol=1e-13)


def test_gradients_match_central_differences(rng):
    rod = random_rods(rng, 1)[0]

    def forces(K1, kappa, tau):
        r = hr.Rod(K1, rod.K2, rod.K3, rod.K13, rod.K23, rod.uhat)
        eq = hr.helix_equilibria(r, kappa, tau)
        return eq.force[:2], eq.moment[:2]

    args = (rod.K1, jnp.asarray(0.9), jnp.asarray(0.6))
    jac = jax.jacfwd(lambda *a: jnp.concatenate(forces(*a)), argnums=(0, 1, 2))(*args)
    jac_rev = jax.jacrev(lambda *a: jnp.concatenate(forces(*a)), argnums=(0, 1, 2))(*args)
    h = 1e-6
    for i in range(3):
        plus = list(args)
        minus = list(args)
        plus[i] = args[i] + h
        minus[i] = args[i] - h
        fd = (jnp.concatenate(forces(*plus)) - jnp.concatenate(forces(*minus))) / (2 * h)
        np.testing.assert_allclose(jac[i], fd, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(jac_rev[i], jac[i], rtol=1e-12, atol=1e-12)


def test_gradients_finite_at_edges():
    rod = hr.Rod(1.0, 1.5, 0.8, uhat=(0.0, 0.0, 0.0))  # B = C = 0: closed-form branch
    g = jax.grad(lambda k: jnp.nansum(hr.helix_equilibria(rod, k, 0.0).energy))(0.7)
    assert np.isfinite(g)
    iso = hr.Rod(1.0, 1.0, 0.8)
    g = jax.grad(lambda k: jnp.nansum(hr.helix_equilibria(iso, k, 0.3).force))(0.7)
    assert np.isfinite(g)
    g = jax.grad(lambda k: jnp.nansum(hr.helix_equilibria(rod, k, 0.3).force))(0.0)
    assert np.isfinite(g)


def test_vmap_equals_batch_and_no_retrace(rng):
    rod = random_rods(rng, 1)[0]
    kappa = jnp.asarray(rng.uniform(0.1, 2, 8))
    tau = jnp.asarray(rng.uniform(-2, 2, 8))
    batch = equilibria(rod, kappa, tau)
    mapped = jax.vmap(lambda k, t: hr.helix_equilibria(rod, k, t))(kappa, tau)
    np.testing.assert_allclose(mapped.force, batch.force, rtol=1e-13)
    tree_allclose(mapped, batch, rtol=1e-13, atol=1e-13)  # every field

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def f(r, k, t):
        return hr.helix_equilibria(r, k, t).force

    f(rod, kappa, tau)
    f(rod, kappa + 1.0, tau)


def test_canonical_rod_is_equivalent(rng):
    rod = hr.Rod(2.0, 1.0, 0.9, 0.3, -0.2, (0.4, 0.5, -0.3))
    can = rod.canonical()
    assert float(can.K1) <= float(can.K2)
    a = equilibria(rod, 0.8, 0.4)
    b = equilibria(can, 0.8, 0.4)
    np.testing.assert_allclose(np.sort(np.asarray(a.force)[a.valid]), np.sort(np.asarray(b.force)[b.valid]), rtol=1e-12)
    shifted = np.mod(np.asarray(a.phi)[a.valid] + np.pi / 2, 2 * np.pi)
    np.testing.assert_allclose(np.sort(shifted), np.sort(np.asarray(b.phi)[b.valid]), atol=1e-12)


def test_exceptional_families(rng):
    rod = random_rods(rng, 1)[0]
    u, m, n = hr.straight_family(rod, jnp.array([0.0, 2.0]))
    assert float(jnp.abs(hr.helix_residual(rod, u, n)).max()) == 0.0
    u, m, n = hr.pure_moment_family(rod, jnp.array([0.0, 0.3, -0.7]))
    np.testing.assert_allclose(u[0], rod.uhat, atol=1e-14)
    scale = 1 + float(jnp.max(jnp.abs(u))) ** 2
    assert float(jnp.abs(hr.helix_residual(rod, u, n)).max()) < 1e-14 * scale


@pytest.mark.heavy  # compiles the batch four times more, with chunk sizes of its own (~25 s)
def test_cpu_chunks_equal_one_pass(rng, monkeypatch):
    """Large batches run a chunk at a time on a CPU (the last chunk overlapping); values
    and gradients equal one pass to rounding, for a plain and a batched rod."""
    from helixrod import _equilibria

    n = 1000 + 37
    kappa = jnp.asarray(rng.uniform(0.01, 3.0, n)).at[5].set(jnp.nan)
    tau = jnp.asarray(rng.uniform(-3.0, 3.0, n))
    rod = hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
    rods = jax.tree.map(lambda x: jnp.broadcast_to(x, (n,) + jnp.shape(x)), rod)

    def run(rod):
        def loss(rod):
            eq = hr.helix_equilibria(rod, kappa, tau)
            return jnp.sum(jnp.where(eq.valid, eq.force * eq.moment, 0.0)), eq
        return jax.jit(jax.value_and_grad(loss, has_aux=True))(rod)

    monkeypatch.setattr(_equilibria, "_CPU_CHUNK", 10**9)
    monkeypatch.setattr(_equilibria, "_KERNEL_CHUNK", 10**9)
    (_, whole), grad_whole = run(rod)
    monkeypatch.setattr(_equilibria, "_CPU_CHUNK", 128)
    monkeypatch.setattr(_equilibria, "_KERNEL_CHUNK", 128)
    for r in (rod, rods):
        (_, chunked), grad_chunked = run(r)
        np.testing.assert_array_equal(chunked.valid, whole.valid)
        np.testing.assert_array_equal(chunked.stable, whole.stable)
        for name in ("phi", "force", "moment", "energy", "u", "n"):
            np.testing.assert_allclose(getattr(chunked, name), getattr(whole, name), rtol=1e-12, atol=1e-12)
        if r is rod:
            for a, b in zip(jax.tree.leaves(grad_chunked), jax.tree.leaves(grad_whole)):
                np.testing.assert_allclose(a, b, rtol=1e-11)


@pytest.mark.heavy  # two linearisations with chunk sizes of their own (~20 s)
def test_chunked_linearisation_keeps_only_the_inputs(rng, monkeypatch):
    """Linearised over a chunked batch (a fit's Levenberg--Marquardt step), each chunk is
    recomputed in the linear map instead of keeping its intermediates: what the
    linearisation stores is the inputs (kappa, tau: 2 numbers per point; with the compiled
    kernel of the wrench, whose derivative rule is the chunked program, twice: the caller's
    arrays and the flat copies the rule holds), where one pass stores ~60 per point (a
    1e6-helix fit's memory)."""
    from helixrod import _equilibria

    n = 4096
    kappa, tau = jnp.asarray(rng.uniform(0.01, 3.0, n)), jnp.asarray(rng.uniform(-3.0, 3.0, n))
    rod = hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))

    def force(rod):
        return hr.helix_equilibria(rod, kappa, tau, fields=("force", "moment")).force

    stored = {}
    for limit in (10**9, 512):
        monkeypatch.setattr(_equilibria, "_CPU_CHUNK", limit)
        monkeypatch.setattr(_equilibria, "_KERNEL_CHUNK", limit)
        _, linear = jax.linearize(force, rod)
        stored[limit] = sum(x.nbytes for x in jax.tree.leaves(linear)) / (n * 8)
        tangent = jax.tree.map(jnp.ones_like, rod)
        np.testing.assert_allclose(linear(tangent), jax.jvp(force, (rod,), (tangent,))[1], rtol=1e-12, atol=1e-12)
    assert stored[512] < 4.1 and stored[10**9] > 20


def test_python_lists_are_arrays():
    rod = hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
    listed = hr.helix_equilibria(rod, [0.5, 1.0], [[1.0], [1.5]])
    arrays = hr.helix_equilibria(rod, np.array([0.5, 1.0]), np.array([[1.0], [1.5]]))
    np.testing.assert_array_equal(listed.count, arrays.count)
    np.testing.assert_array_equal(listed.force, arrays.force)
    with pytest.raises(ValueError, match="kappa must be real numbers"):
        hr.helix_equilibria(rod, ["a"], [1.0])


def test_eager_chunked_calls_compile_once(monkeypatch):
    """Called eagerly above the chunk size, a second call of the same shape compiles nothing
    (the chunk loop is one jitted program, not a loop over a fresh closure per call)."""
    from helixrod import _equilibria

    monkeypatch.setattr(_equilibria, "_CPU_CHUNK", 1024)
    monkeypatch.setattr(_equilibria, "_KERNEL_CHUNK", 1024)
    rod = hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
    kappa, tau = jnp.linspace(0.1, 3.0, 3000), jnp.linspace(-3.0, 3.0, 3000)
    compiles, listening = [], [False]
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, duration, **kw: compiles.append(event) if listening[0] and "backend_compile" in event else None
    )
    first = hr.helix_equilibria(rod, kappa, tau)
    listening[0] = True
    second = hr.helix_equilibria(rod, kappa, tau)
    listening[0] = False
    assert compiles == []
    np.testing.assert_array_equal(first.phi, second.phi)


def test_fields_compute_only_what_is_asked(monkeypatch):
    """`fields` returns the asked fields (and `valid`) with the values of the full result,
    the others `None`, in one pass and in the chunked loop (chunks of 1024 here, so that
    3000 points take three); an eager second call with the same fields compiles nothing;
    unknown names are a ValueError naming the valid ones."""
    from helixrod import _equilibria

    rod = hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
    kappa, tau = jnp.linspace(0.1, 3.0, 3000), jnp.linspace(-3.0, 3.0, 3000)
    full = hr.helix_equilibria(rod, kappa, tau)
    asked = ("phi", "force", "stable", "continuum")
    for chunk in (None, 1024):
        if chunk:
            monkeypatch.setattr(_equilibria, "_CPU_CHUNK", chunk)
            monkeypatch.setattr(_equilibria, "_KERNEL_CHUNK", chunk)
        some = hr.helix_equilibria(rod, kappa, tau, fields=asked)
        for name in asked + ("valid",):
            np.testing.assert_allclose(np.asarray(getattr(some, name), float), np.asarray(getattr(full, name), float),
                                       rtol=1e-14, atol=1e-14)
        assert some.moment is None and some.u is None and some.energy is None
        np.testing.assert_array_equal(some.count, full.count)
    compiles, listening = [], [False]
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, duration, **kw: compiles.append(event) if listening[0] and "backend_compile" in event else None
    )
    listening[0] = True
    hr.helix_equilibria(rod, kappa, tau, fields=list(reversed(asked)))
    listening[0] = False
    assert compiles == []
    one = hr.helix_equilibria(rod, 0.5, 1.5, fields="force")
    assert one.force.shape == (4,) and one.phi is None
    with pytest.raises(ValueError, match="unknown field.*'forces'.*valid fields"):
        hr.helix_equilibria(rod, kappa, tau, fields=("forces",))
