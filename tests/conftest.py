import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")


@pytest.fixture
def rng():
    return np.random.default_rng(20261122)


def random_rods(rng, n):
    """Random canonical, coupled, intrinsically curved rods (positive definite)."""
    import helixrod

    rods = []
    while len(rods) < n:
        K1 = rng.uniform(0.3, 2.0)
        K2 = K1 * rng.uniform(1.0, 3.0)
        K3 = rng.uniform(0.3, 2.0)
        K13, K23 = rng.normal(scale=0.4, size=2)
        if K3 - K13**2 / K1 - K23**2 / K2 <= 0.05:
            continue
        rods.append(helixrod.Rod(K1, K2, K3, K13, K23, rng.normal(scale=0.8, size=3)))
    return rods
