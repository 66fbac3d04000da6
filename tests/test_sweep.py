"""sweep / sensitivity / save-load: against helix_equilibria point by point, central
differences, the register-count theory, and in subprocesses for memory and device-count
independence.  (Figures: tests/test_plot.py; the command: tests/test_cli.py.)"""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    N_REF, SENS_KAPPA, SENS_TAU, SWEEP_KAPPA, SWEEP_ROD, SWEEP_TAU, reference, sweep_atlas, sweep_sensitivity,
)

import helixrod as hr

FIELDS, POINT_FIELDS, REGISTER_FIELDS = hr.SweepResult.FIELDS, hr.SweepResult.POINT_FIELDS, hr.SweepResult.REGISTER_FIELDS

ROD, KAPPA, TAU = SWEEP_ROD, SWEEP_KAPPA, SWEEP_TAU
SRC = str(Path(hr.__file__).resolve().parents[1])


@pytest.fixture(scope="module")
def atlas():
    return sweep_atlas()


def test_shapes_and_dtypes(atlas):
    assert atlas.fields == FIELDS
    for name in REGISTER_FIELDS:
        assert atlas[name].shape == (KAPPA.size, TAU.size, 4)
        assert atlas[name].dtype == REGISTER_FIELDS[name]
    for name in POINT_FIELDS:
        assert atlas[name].shape == (KAPPA.size, TAU.size)
        assert atlas[name].dtype == POINT_FIELDS[name]


def test_equals_helix_equilibria_at_sampled_points(atlas, rng):
    i = rng.integers(0, KAPPA.size, N_REF)
    j = rng.integers(0, TAU.size, N_REF)
    eq = reference(ROD, KAPPA[i], TAU[j])
    for name in ("phi", "force", "moment", "tension", "energy"):
        np.testing.assert_allclose(atlas[name][i, j], np.asarray(getattr(eq, name)), rtol=1e-13, atol=1e-13)
    for name in ("valid", "stable"):
        np.testing.assert_array_equal(atlas[name][i, j], np.asarray(getattr(eq, name)))
    np.testing.assert_array_equal(atlas["count"][i, j], np.asarray(eq.count))
    np.testing.assert_array_equal(atlas["continuum"][i, j], np.asarray(eq.continuum))
    np.testing.assert_array_equal(atlas["straight"][i, j], np.asarray(eq.straight))


def test_counts_and_stable_branch(atlas):
    count, stable_count = atlas["count"], atlas["stable_count"]
    helical = KAPPA > 0
    assert set(np.unique(count[helical])) <= {2, 3, 4}
    assert {2, 4} <= set(np.unique(count[helical]))  # this rod has both regions
    assert np.all(count[~helical] == 0) and np.all(atlas["straight"][~helical])
    np.testing.assert_array_equal(count, atlas["valid"].sum(-1))
    np.testing.assert_array_equal(stable_count, atlas["stable"].sum(-1))
    # Registers alternate minimum / maximum around the circle: half of them are stable
    # (a fold, count 3, has one minimum, one maximum and the degenerate one).
    np.testing.assert_array_equal(stable_count[helical], np.where(count[helical] == 4, 2, 1))
    # Stable branch = stable register of least energy, recomputed here with numpy.
    energy = np.where(atlas["stable"], atlas["energy"], np.inf)
    best = np.argmin(energy, axis=-1)[..., None]
    for name in ("phi", "force", "moment"):
        expect = np.take_along_axis(atlas[name], best, -1)[..., 0]
        expect = np.where(stable_count > 0, expect, np.nan)
        np.testing.assert_array_equal(atlas[f"stable_{name}"], expect)
    assert np.all(np.isnan(atlas["stable_force"][~helical]))


def test_continuum_of_isotropic_rod():
    rod = hr.Rod(1.0, 1.0, 0.7, uhat=(0.0, 0.0, 0.3))
    r = hr.sweep(rod, [0.5, 1.0], [-1.0, 2.0], fields=FIELDS, chunk_size=512, progress=False)  # reuses the compile
    assert np.all(r["continuum"]) and np.all(r["count"] == 1)
    assert np.all(np.isnan(r["stable_force"]))  # neutral family: no stable register
    assert np.all(np.isfinite(r["force"][..., 0]))


def test_bad_arguments():
    with pytest.raises(ValueError, match="unknown field.*'nope'.*valid fields are.*'stable_force'"):
        hr.sweep(ROD, KAPPA, TAU, fields=("force", "nope"))
    with pytest.raises(ValueError, match="1-D"):
        hr.sweep(ROD, np.ones((2, 2)), TAU)
    with pytest.raises(ValueError, match="single rod"):
        hr.sweep(hr.Rod(jnp.ones(2), 2.0, 1.0), KAPPA, TAU)
    with pytest.raises(ValueError, match="chunk_size"):
        hr.sweep(ROD, KAPPA, TAU, chunk_size=0)
    with pytest.raises(ValueError, match="unknown parameter 'K4'"):
        hr.sensitivity(ROD, KAPPA, TAU, wrt=("K4",))
    with pytest.raises(ValueError, match="devices must name at least one device"):
        hr.sweep(ROD, KAPPA, TAU, devices=[])
    sens = hr.sensitivity(ROD, [1.0], [0.5], wrt=("K1",))
    with pytest.raises(ValueError, match=r"'K2' is not among the parameters differentiated, wrt = \('K1',\)"):
        sens.of("K2")
    with pytest.raises(ValueError, match="no output 'nope'"):
        sens.of("K1", "nope")


def test_save_load_round_trip(atlas, tmp_path):
    path = tmp_path / "atlas.npz"
    hr.save_sweep(path, atlas)
    back = hr.load_sweep(path)
    assert back.fields == atlas.fields
    for name in atlas:
        np.testing.assert_array_equal(back[name], atlas[name])
        assert back[name].dtype == atlas[name].dtype
    np.testing.assert_array_equal(back.kappa, KAPPA)
    np.testing.assert_array_equal(back.tau, TAU)
    for k in ("K1", "K2", "K3", "K13", "K23", "uhat"):
        np.testing.assert_array_equal(np.asarray(getattr(back.rod, k)), np.asarray(getattr(ROD, k)))


@pytest.fixture(scope="module")
def sens():
    return sweep_sensitivity()


def test_sensitivity_matches_central_differences(sens):
    names = ("K1", "K2", "K3", "K13", "K23", "uhat1", "uhat2", "uhat3")
    assert sens.wrt == names
    base = np.array([1.0, 1.7, 0.9, 0.3, -0.2, 0.8, 0.3, 0.4])
    kappa, tau = SENS_KAPPA[:, None], SENS_TAU[None, :]

    def at(p):
        eq = reference(hr.Rod(p[0], p[1], p[2], p[3], p[4], p[5:8]), kappa, tau)
        return eq.force, eq.moment, eq.phi

    checked = 0
    for k, name in enumerate(names):
        h = 1e-6
        plus, minus = base.copy(), base.copy()
        plus[k] += h
        minus[k] -= h
        (fp, mp, pp), (fm, mm, pm) = at(plus), at(minus)
        ok = np.isfinite(pp) & np.isfinite(pm) & np.isfinite(sens["phi"])
        dphi = np.angle(np.exp(1j * (pp - pm))) / (2 * h)  # wrap across 0 = 2 pi
        for key, fd in (("d_force", (fp - fm) / (2 * h)), ("d_moment", (mp - mm) / (2 * h)), ("d_phi", dphi)):
            ad = sens[key][..., k]
            np.testing.assert_allclose(ad[ok], fd[ok], rtol=1e-6, atol=1e-7, err_msg=f"{key}/{name}")
        elasticity = base[k] * sens["d_force"][..., k] / sens["force"]
        np.testing.assert_allclose(sens["force_elasticity"][..., k][ok], elasticity[ok], rtol=1e-14)
        checked += ok.sum()
    assert checked >= 8 * 9 * 2  # at least two registers per point for every parameter
    assert np.all(np.isnan(sens["d_force"][~np.isfinite(sens["phi"])]))


@pytest.mark.slow
def test_devices_and_memory_in_subprocess():
    """Two host devices: identical bits on 1 and 2 devices (same points per device), equal to
    rounding across chunk sizes; peak
    memory of a 10^6-point sweep (the 10^7-point count-only figure is in the benchmark)."""
    script = textwrap.dedent(
        """
        import json, resource, jax, numpy as np
        def peak_kb():  # VmHWM: ru_maxrss would inherit pytest's size across fork + exec
            for line in open("/proc/self/status"):
                if line.startswith("VmHWM:"):
                    return int(line.split()[1])
            return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        jax.config.update("jax_enable_x64", True)
        import helixrod as hr
        rod = hr.Rod(1.0, 1.7, 0.9, K13=0.3, K23=-0.2, uhat=(0.8, 0.3, 0.4))
        fields = ("phi", "force", "stable_moment", "count")
        before = peak_kb()
        # The 2-device runs share chunk_size 2 x 65536 (the default), 65536 points per device.
        big = hr.sweep(rod, np.linspace(0, 3, 1000), np.linspace(-3, 3, 1000), fields=fields, progress=False)
        peak = peak_kb()
        k, t = np.linspace(0, 3, 61), np.linspace(-3, 3, 67)
        one = hr.sweep(rod, k, t, fields=fields, devices=jax.devices()[:1], chunk_size=65536, progress=False)
        two = hr.sweep(rod, k, t, fields=fields, chunk_size=2 * 65536, progress=False)
        small = hr.sweep(rod, k, t, fields=fields, devices=jax.devices()[:1], chunk_size=1000, progress=False)
        same = all(np.array_equal(one[f], two[f], equal_nan=True) for f in fields)
        # Another chunk size is another XLA program (other fusions, other FMA contractions):
        # equal to rounding, not to the bit.
        close = all(np.allclose(one[f], small[f], rtol=1e-13, atol=1e-13, equal_nan=True) for f in fields)
        print(json.dumps({"devices": len(jax.devices()), "same": same, "close": close, "before_mb": before / 1024,
                          "peak_mb": peak / 1024, "counts": np.unique(big["count"]).tolist()}))
        """
    )
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", PYTHONPATH=SRC)
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout.strip().splitlines()[-1])
    print(report)
    assert report["devices"] == 2
    assert report["same"] and report["close"]
    assert set(report["counts"]) <= {0, 2, 3, 4}
    assert report["peak_mb"] < 1200, report


def test_save_is_atomic_and_keeps_the_name(atlas, tmp_path):
    path = tmp_path / "atlas"  # no suffix: written under exactly this name
    hr.save_sweep(path, atlas)
    assert path.exists() and not (tmp_path / "atlas.npz").exists()
    before = path.read_bytes()

    class Interrupted(Exception):
        pass

    def failing(file):
        file.write(b"partial")
        raise Interrupted

    from helixrod._misc import write_atomically

    with pytest.raises(Interrupted):
        write_atomically(path, failing)
    assert path.read_bytes() == before  # the old file is whole
    assert [p.name for p in tmp_path.iterdir()] == ["atlas"]  # no temporary left behind
    np.testing.assert_array_equal(hr.load_sweep(path)[atlas.fields[0]], atlas[atlas.fields[0]])
