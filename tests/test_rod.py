import jax
import jax.numpy as jnp
import numpy as np
import pytest

import helixrod as hr


def test_constitutive_law_and_inverse(rng):
    rod = hr.Rod(1.0, 2.0, 0.8, 0.3, -0.2, (0.1, 0.2, 0.3))
    u = jnp.asarray(rng.normal(size=(10, 3)))
    m = rod.moment(u)
    v, K = np.asarray(u) - np.asarray(rod.uhat), np.asarray(rod.K)
    np.testing.assert_allclose(m, v @ K.T, rtol=1e-14)
    np.testing.assert_allclose(rod.twist(m), u, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(rod.energy(u), 0.5 * np.einsum("ni,ij,nj->n", v, K, v), rtol=1e-14)
    np.testing.assert_allclose(jax.vmap(jax.grad(rod.energy))(u), m, rtol=1e-13)


@pytest.mark.parametrize(
    "args",
    [(-1.0, 1.0, 1.0), (1.0, 0.0, 1.0), (1.0, 1.0, 0.1, 0.5, 0.0), (1.0, np.nan, 1.0), (1.0, 1.0, np.inf)],
)
def test_invalid_stiffness_is_a_clear_error(args):
    with pytest.raises(ValueError, match="positive definite"):
        hr.Rod(*args)


def test_traced_invalid_stiffness_raises():
    f = jax.jit(lambda k: hr.helix_equilibria(hr.Rod(k, 1.0, 1.0), 0.5, 0.5).force)
    f(1.0)
    with pytest.raises(Exception, match="positive definite"):
        f(-1.0).block_until_ready()


def test_material_constructors():
    E, nu, r = 200e9, 0.3, 1e-3
    rod = hr.Rod.circular(E, r, nu=nu)
    I = np.pi * r**4 / 4
    np.testing.assert_allclose([rod.K1, rod.K2, rod.K3], [E * I, E * I, E / (2 * 1.3) * 2 * I], rtol=1e-14)
    ell = hr.Rod.elliptical(E, 2e-3, 1e-3, G=80e9)
    assert float(ell.K1) < float(ell.K2)
    np.testing.assert_allclose(ell.dimensionless()["a"], 4.0, rtol=1e-14)
    with pytest.raises(ValueError, match="exactly one"):
        hr.Rod.circular(E, r)
    scales = hr.section_scales(E, I, np.pi * r**2, 7800.0)
    np.testing.assert_allclose(scales["length"], r / 2, rtol=1e-14)


def test_uhat_shape_error():
    with pytest.raises(ValueError, match="trailing axis of length 3"):
        hr.Rod(1.0, 1.0, 1.0, uhat=(1.0, 2.0))


def test_a_rod_of_constants_inside_jit_is_checked_while_tracing():
    """Numbers inside a jitted function are checked in Python (a ValueError at trace time),
    and the program carries no runtime check: no host callback, which would keep it out of
    the persistent compilation cache.  Traced stiffnesses keep the runtime check."""
    x = jnp.ones(3)
    text = jax.jit(lambda u: hr.Rod(1.0, 1.5, 0.8, K13=0.1).energy(u)).lower(x).as_text()
    assert "callback" not in text
    with pytest.raises(ValueError, match="positive definite"):
        jax.jit(lambda u: hr.Rod(-1.0, 1.0, 1.0).energy(u))(x)
    traced = jax.jit(lambda K1, u: hr.Rod(K1, 1.5, 0.8).energy(u)).lower(1.0, x).as_text()
    assert "callback" in traced


def test_repr_shows_the_values():
    assert repr(hr.Rod(1.0, 1.5, 0.8, K13=0.5, uhat=(1.0, 0.0, 0.25))) == (
        "Rod(K1=1, K2=1.5, K3=0.8, K13=0.5, K23=0, uhat=(1, 0, 0.25))"
    )
    batch = repr(hr.Rod(jnp.array([1.0, 2.0]), 3.0, 1.5))
    assert batch.startswith("Rod(batch (2,), K1=[1., 2.], K2=[3., 3.]") and "\n" not in batch
    traced = jax.jit(lambda k: jnp.asarray(len(repr(hr.Rod(k, 3.0, 1.5)))))(1.0)
    assert int(traced) > 0  # under jit: equinox's shapes-and-dtypes form, no error
