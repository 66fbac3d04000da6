"""The stability atlas of clamped finite helices (`_bvp/_atlas.py`): its matrix-exponential
test against the integrated test of `solve_boundary_value` on the same clamped helix, and its
critical length against the index (and the boundary-value solve) on either side."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import helixrod

ROD = helixrod.Rod(1.0, 1.5, 0.8, uhat=(0.0, 1.0, 0.3))


def clamped_helix(rod, n, m, length):
    """`solve_boundary_value` of the uniform helix with body wrench (n, m) clamped over
    `length`, started at the origin with the identity frame, from its own wrench."""
    u = np.asarray(rod.twist(m))
    screw = np.zeros((4, 4))
    screw[:3, :3] = [[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]]
    screw[2, 3] = 1.0
    end = jax.scipy.linalg.expm(jnp.asarray(screw) * length)
    return helixrod.solve_boundary_value(
        rod, length, start=helixrod.Clamped(), end=helixrod.Clamped(end[:3, 3], end[:3, :3]), guess=(n, m), throw=False
    )


@pytest.fixture(scope="module")
def atlas():
    kappa, tau = jnp.meshgrid(jnp.linspace(0.4, 2.0, 6), jnp.linspace(-1.0, 1.0, 5))
    return helixrod.stability_atlas(ROD, kappa, tau, 5.0)


def test_matches_the_integrated_test_of_a_boundary_value_solve(atlas):
    eq = helixrod.helix_equilibria(ROD, atlas.kappa, atlas.tau)
    index = np.asarray(atlas.instability_index)
    defined = np.argwhere(np.asarray(atlas.valid) & (index >= 0))
    picks = [tuple(defined[i]) for i in np.linspace(0, len(defined) - 1, 6).astype(int)]
    assert any(index[p] > 0 for p in picks) and any(index[p] == 0 for p in picks)
    for idx in picks:
        sol = clamped_helix(ROD, eq.n[idx], eq.m[idx], 5.0)
        assert bool(sol.ok)
        assert int(sol.instability_index) == int(index[idx])
        assert float(sol.stability_margin) == pytest.approx(float(atlas.stability_margin[idx]), rel=1e-5, abs=1e-6)


def test_critical_length_agrees_with_the_index(atlas):
    defined = np.asarray(atlas.valid & (atlas.instability_index >= 0))
    index = np.asarray(atlas.instability_index)[defined]
    critical = np.asarray(atlas.critical_length)[defined]
    assert (index > 0).any() and (index == 0).any()
    # Unstable at L = 5 exactly where the first conjugate point lies before it.
    assert np.array_equal(index > 0, critical < 5.0)
    assert np.array_equal(np.asarray(atlas.stable)[defined], index == 0)


def test_critical_length_is_where_the_boundary_value_solve_loses_stability(atlas):
    eq = helixrod.helix_equilibria(ROD, atlas.kappa, atlas.tau)
    critical = np.where(np.asarray(atlas.valid), np.asarray(atlas.critical_length), np.inf)
    idx = np.unravel_index(np.argmin(np.where(critical > 2.0, critical, np.inf)), critical.shape)
    length = float(critical[idx])
    assert np.isfinite(length)
    below = clamped_helix(ROD, eq.n[idx], eq.m[idx], 0.99 * length)
    above = clamped_helix(ROD, eq.n[idx], eq.m[idx], 1.01 * length)
    assert bool(below.stable) and int(above.instability_index) >= 1


def test_bad_input():
    with pytest.raises(ValueError, match="kappa"):
        helixrod.stability_atlas(ROD, jnp.array([np.nan]), 0.5, 5.0)
    with pytest.raises(ValueError, match="length"):
        helixrod.stability_atlas(ROD, 1.0, 0.5, -1.0)
    with pytest.raises(ValueError, match="broadcast"):
        helixrod.stability_atlas(ROD, jnp.ones(3), jnp.ones(4), 5.0)


def test_cli_stability(tmp_path):
    from typer.testing import CliRunner

    from helixrod.cli import app

    out, plot = tmp_path / "atlas.npz", tmp_path / "atlas.png"
    args = ["stability", "--length", "5", "--kappa", "0.4:2:6", "--tau=-1:1:5", "--out", str(out), "--plot", str(plot)]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "stable:" in result.output and plot.stat().st_size > 0
    saved = np.load(out)
    kappa, tau = jnp.meshgrid(jnp.linspace(0.4, 2.0, 6), jnp.linspace(-1.0, 1.0, 5), indexing="ij")
    direct = helixrod.stability_atlas(ROD, kappa, tau, 5.0)
    assert np.array_equal(saved["instability_index"], np.asarray(direct.instability_index))
    bad = CliRunner().invoke(app, ["stability", "--length", "-1"])
    assert bad.exit_code == 2 and "length" in bad.output
