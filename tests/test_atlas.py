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


@pytest.mark.heavy
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


def test_the_atlas_is_the_same_in_any_units(atlas):
    """Index, margin and stability are dimensionless and the critical length a length: the
    atlas of the same rods in SI units (stiffness 1e-28 N m^2, lengths of 1e-9 m) is the
    atlas in the rod's own units (it was 'not resolved' everywhere: the matrix exponential's
    range check saw the units of K^-1)."""
    c, l = 1e-28, 1e-9
    rod = helixrod.Rod(c * ROD.K1, c * ROD.K2, c * ROD.K3, uhat=ROD.uhat / l)
    scaled = helixrod.stability_atlas(rod, atlas.kappa / l, atlas.tau / l, 5.0 * l)
    np.testing.assert_array_equal(scaled.instability_index, atlas.instability_index)
    np.testing.assert_array_equal(scaled.stable, atlas.stable)
    np.testing.assert_allclose(scaled.stability_margin, atlas.stability_margin, rtol=1e-7)
    np.testing.assert_allclose(scaled.critical_length / l, atlas.critical_length, rtol=1e-6)  # its bisection


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
    with pytest.raises(ValueError, match="pieces must be at most 1024"):
        helixrod.stability_atlas(ROD, 1.0, 0.5, 5.0, pieces=10**6)
    with pytest.raises(ValueError, match="kappa is empty"):
        helixrod.stability_atlas(ROD, jnp.zeros(0), jnp.zeros(0), 5.0)
    # Traced inputs: a clear error, not one from deep inside (a ConcretizationTypeError under
    # vmap over lengths; critical_length=False answered a negative length as a positive one).
    for critical in (True, False):
        with pytest.raises(ValueError, match="needs concrete inputs"):
            jax.vmap(lambda L: helixrod.stability_atlas(ROD, 1.0, 0.5, L, critical_length=critical).stable)(jnp.array([5.0, -5.0]))
    with pytest.raises(ValueError, match="needs concrete inputs"):
        jax.jit(lambda k: helixrod.stability_atlas(ROD, k, 0.5, 5.0).stable)(jnp.ones(2))


@pytest.mark.heavy
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
    assert np.array_equal(saved["instability_type"], np.asarray(direct.instability_type))
    kind = np.asarray(direct.instability_type)
    assert f"fold: {int((kind == 1).sum())}, symmetry-breaking: {int((kind == 2).sum())}" in result.output
    bad = CliRunner().invoke(app, ["stability", "--length", "-1"])
    assert bad.exit_code == 2 and "length" in bad.output


def _uniform_pose(rod, m, s):
    """(position, frame) at arc length `s` of the uniform helix with body moment `m` started at
    the origin with the identity frame: its screw motion."""
    u = np.asarray(rod.twist(m))
    screw = np.zeros((4, 4))
    screw[:3, :3] = [[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]]
    screw[2, 3] = 1.0
    end = np.asarray(jax.scipy.linalg.expm(jnp.asarray(screw) * s))
    return end[:3, 3], end[:3, :3]


@pytest.mark.parametrize("force", [0.0, 0.3, -0.3])
def test_greenhill_twisted_shaft_is_a_symmetry_breaking_loss_of_stability(force):
    from helixrod._bvp._atlas import SYMMETRY_BREAKING, _critical_point

    # A straight isotropic rod twisted by M (kappa = 0 is no register of helix_equilibria):
    # clamped at both ends it buckles where tan(t/2) = t/2, t = M L / B = 8.98682 (Greenhill)
    # without a force -- a double conjugate point, which the determinant only touches -- and
    # under tension or compression elsewhere; by its rotational symmetry about the axis the
    # mode is never axisymmetric: symmetry-breaking, whatever the force.
    rod = helixrod.Rod(1.0, 1.0, 0.7)
    root = 2 * 4.493409457909064  # first positive root of tan(x) = x, doubled
    critical = jax.jit(lambda n, m: _critical_point(rod, n, m, 10.0, 30))
    for moment in (2.0,) if force > 0 else (1.0, 2.0):  # under tension M = 1 is stable up to 10
        length, kind, mode = critical(jnp.array([0.0, 0.0, force]), jnp.array([0.0, 0.0, moment]))
        assert int(kind) == SYMMETRY_BREAKING
        assert np.isfinite(float(length)) and abs(float(mode[2])) < 1e-8 and abs(float(mode[5])) < 1e-8
        if force == 0.0:
            assert float(length) * moment / root == pytest.approx(1.0, abs=2e-7)  # measured 1.3e-8, 4.8e-8
        else:  # tension stabilises, compression destabilises
            assert (float(length) * moment > root) == (force > 0)


def test_critical_mode_and_the_axial_controls(atlas):
    from helixrod._bvp._atlas import _axial_controls, _body_transfer

    eq = helixrod.helix_equilibria(ROD, atlas.kappa, atlas.tau)
    found = np.argwhere(np.isfinite(np.asarray(atlas.critical_length)))
    assert len(found) > 5
    kinds = np.asarray(atlas.instability_type)
    assert set(kinds[np.isinf(np.asarray(atlas.critical_length))]) == {0}
    assert set(kinds[~np.asarray(atlas.valid)]) == {-1}
    for idx in map(tuple, found):
        n, m, length = eq.n[idx], eq.m[idx], float(atlas.critical_length[idx])
        B = np.asarray(_body_transfer(ROD, n, m, length)[:6, 6:])
        mode = np.asarray(atlas.critical_mode[idx])
        wrench = mode * np.r_[np.full(3, 1.0 / length), np.ones(3)]
        assert np.linalg.norm(mode) == pytest.approx(1.0)
        # The mode is the null vector of B (its smallest singular value is ~1e-5 of the largest:
        # the tiny extensibility differs between one piece and the count's many).
        scaled = np.diag(np.r_[np.full(3, 1.0 / length), np.ones(3)]) @ B @ np.diag(np.r_[np.full(3, length**-2), np.full(3, 1.0 / length)])
        right = np.linalg.svd(scaled)[2][-1]
        assert abs(right @ mode) == pytest.approx(1.0, abs=1e-3)  # both (L dN, dM0); measured >= 0.9997
        assert np.linalg.norm(B @ wrench) < 1e-2 * np.linalg.norm(B) * np.linalg.norm(wrench)
        # The controls' axis is the central axis of the helix's wrench.
        nn, mm = np.asarray(n), np.asarray(m)
        axis, r = nn / np.linalg.norm(nn), np.cross(mm, nn) / (nn @ nn)
        controls = np.asarray(_axial_controls(ROD, m, length))
        sign = np.sign(controls[0, :3] @ axis)
        assert np.allclose(sign * controls, [np.r_[axis / length, 0, 0, 0], np.r_[np.cross(axis, r) / length, axis]], atol=1e-9)


def test_instability_type_follows_the_symmetry_of_the_jacobi_field(atlas):
    from helixrod._bvp._atlas import FOLD, SYMMETRY_BREAKING, _body_transfer

    # ROD has W(-u1, u2, u3) = W(u): a helix with u1 = 0 is mapped onto itself by the rotation
    # by pi about its principal normal at the middle (which reverses it), and each simple
    # Jacobi field is symmetric or antisymmetric under it.  The axial controls are symmetric:
    # an antisymmetric field cannot be driven by them (symmetry-breaking), a symmetric one is
    # (fold).  The field from numpy's SVD of B, not from the atlas.
    eq = helixrod.helix_equilibria(ROD, atlas.kappa, atlas.tau)
    kinds = []
    for idx in map(tuple, np.argwhere(np.isfinite(np.asarray(atlas.critical_length)))):
        n, m, length = eq.n[idx], eq.m[idx], float(atlas.critical_length[idx])
        u = np.asarray(ROD.twist(m))
        assert abs(u[0]) < 1e-12
        B = np.asarray(_body_transfer(ROD, n, m, length)[:6, 6:]) @ np.diag(np.r_[np.full(3, length**-2), np.full(3, 1.0 / length)])
        wrench = np.linalg.svd(B)[2][-1] * np.r_[np.full(3, length**-2), np.full(3, 1.0 / length)]

        def jacobi(s):
            frame = _uniform_pose(ROD, m, s)[1]
            v = np.asarray(_body_transfer(ROD, n, m, s)[:6, 6:]) @ wrench
            return np.concatenate([frame @ v[:3], frame @ v[3:]])

        middle, frame = _uniform_pose(ROD, m, length / 2)
        normal = frame @ np.cross(u, [0.0, 0.0, 1.0])
        normal /= np.linalg.norm(normal)
        flip = 2 * np.outer(normal, normal) - np.eye(3)
        s = 0.3 * length
        assert np.allclose(middle + flip @ (_uniform_pose(ROD, m, s)[0] - middle), _uniform_pose(ROD, m, length - s)[0], atol=1e-9)
        field = np.array([jacobi(s) for s in np.linspace(0.1, 0.9, 5) * length])
        image = np.array([np.concatenate([flip @ jacobi(length - s)[:3], flip @ jacobi(length - s)[3:]]) for s in np.linspace(0.1, 0.9, 5) * length])
        symmetric = np.abs(field - image).max() < 0.05 * np.abs(field).max()
        antisymmetric = np.abs(field + image).max() < 0.05 * np.abs(field).max()
        assert symmetric != antisymmetric
        assert int(atlas.instability_type[idx]) == (FOLD if symmetric else SYMMETRY_BREAKING)
        kinds.append(int(atlas.instability_type[idx]))
    assert FOLD in kinds and SYMMETRY_BREAKING in kinds


def _axial_stiffness(rod, n, m, length, epsilon=1e-5):
    """The stiffness of the clamped helix of `length` to its two axial controls: the change of
    the work-conjugate end reaction per control, by central differences of
    `solve_boundary_value` with the end moved along each control (the axis: the central axis
    of the wrench)."""
    from scipy.spatial.transform import Rotation

    nn, mm = np.asarray(n), np.asarray(m)
    axis, r = nn / np.linalg.norm(nn), np.cross(mm, nn) / (nn @ nn)
    position, frame = _uniform_pose(rod, m, length)
    stiffness = []
    for dx, dtheta in ((axis, np.zeros(3)), (np.cross(axis, r), axis)):
        reaction = []
        for e in (epsilon, -epsilon):
            end = helixrod.Clamped(position + frame @ (e * dx), Rotation.from_rotvec(frame @ (e * dtheta)).as_matrix() @ frame)
            sol = helixrod.solve_boundary_value(rod, length, start=helixrod.Clamped(), end=end, guess=(n, m), throw=False)
            assert bool(sol.ok)
            reaction.append(np.asarray(sol.force) @ (frame @ dx) + np.asarray(sol.end_moment) @ (frame @ dtheta))
        stiffness.append((reaction[0] - reaction[1]) / (2 * epsilon))
    return np.array(stiffness)


@pytest.mark.slow  # 32 boundary-value solves: ~1 min on 2 busy cores
def test_a_fold_is_a_pole_of_the_axial_stiffness():
    from helixrod._bvp._atlas import FOLD, SYMMETRY_BREAKING

    # At a fold the response to a control turns back: its compliance vanishes, the stiffness
    # has a pole at L_c, so its jump across L_c grows like 1/delta; at a branch point the
    # helices' response is smooth through L_c and the jump shrinks like delta.  Measured by
    # boundary-value solves, independent of the classification.
    atlas = helixrod.stability_atlas(ROD, jnp.array([1.6, 1.8]), -0.5, 5.0)
    eq = helixrod.helix_equilibria(ROD, atlas.kappa, atlas.tau)
    assert [int(k) for k in atlas.instability_type[:, 0]] == [FOLD, SYMMETRY_BREAKING]
    growth = []
    for i in range(2):
        critical = float(atlas.critical_length[i, 0])
        jumps = [
            np.abs(_axial_stiffness(ROD, eq.n[i, 0], eq.m[i, 0], (1 + d) * critical) - _axial_stiffness(ROD, eq.n[i, 0], eq.m[i, 0], (1 - d) * critical))
            for d in (0.02, 0.005)
        ]
        growth.append(np.max(jumps[1] / jumps[0]))
    # measured: fold 5.6 (c2; 4.1 for c1), branch point 0.25
    assert growth[0] > 3.0 and growth[1] < 0.5


@pytest.mark.heavy
def test_a_first_atlas_compiles_its_critical_lengths_beside_the_index_once(compilations, monkeypatch):
    """The critical lengths' program compiles on a thread of its own at the first atlas of a
    signature, from the specs of the wrenches the index program will give it (placed as
    the grid is: a grid put on a device gives placed wrenches), and the calls find it; the
    next atlas of that signature starts nothing."""
    from helixrod import _compile

    monkeypatch.setattr(_compile, "cores", lambda: 2)  # as on a machine of several cores
    kappa, tau = jnp.meshgrid(jnp.linspace(0.4, 2.0, 3), jnp.linspace(-1.0, 1.0, 2))  # no other atlas has 24 helices
    for grid in ((kappa, tau), jax.device_put((kappa, tau), jax.devices()[0])):
        compilations.clear()
        first = helixrod.stability_atlas(ROD, *grid, 5.0)
        ours = [(thread, name) for thread, name in compilations if name == "_critical_lengths"]
        assert ours == [("helixrod-compile-_critical_lengths", "_critical_lengths")], ours
    compilations.clear()
    again = helixrod.stability_atlas(ROD, kappa, tau, 5.0)
    assert compilations == []
    np.testing.assert_array_equal(np.asarray(again.critical_length), np.asarray(first.critical_length))
    assert np.isfinite(np.asarray(first.critical_length)).any()
