"""TweezerData: construction, validation, the CSV form and reading a lumicks pylake FdCurve."""

import math
import sys
import textwrap
import types

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from helixrod import dna
from helixrod._fit import TweezerData


def _assert_same(a, b):
    """Equal arrays (NaN where NaN), same dtype."""
    a, b = np.asarray(a), np.asarray(b)
    assert a.dtype == b.dtype
    np.testing.assert_array_equal(a, b)


def _base(**changes):
    """Keyword arguments of a valid 4-point from_arrays call, with `changes` applied."""
    kwargs = {
        "force": [1.0, 2.0, 3.0, 4.0],
        "extension": [100.0, 200.0, 300.0, 400.0],
        "extension_sigma": 5.0,
        "turns": [0.0, 5.0, np.nan, np.nan],
        "torque": [np.nan, np.nan, 0.0, 10.0],
        "n_bp": 1000,
    }
    kwargs.update(changes)
    return kwargs


def _write(tmp_path, text, name="data.csv"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text).lstrip("\n"), encoding="utf-8")
    return path


# -- construction ------------------------------------------------------------------------
def test_exported_in_public_namespace():
    assert dna.TweezerData is TweezerData


def test_from_arrays_string_ids_and_mapping_n_bp():
    data = TweezerData.from_arrays(
        [1.0, 2.0, 3.0, 4.0],
        [10.0, 20.0, 30.0, 40.0],
        extension_sigma=[1.0, 2.0, 3.0, 4.0],
        turns=[1.0, -2.0, np.nan, 3.0],
        torque=[np.nan, np.nan, 5.0, np.nan],
        molecule=["b", "a", "b", "c"],
        n_bp={"a": 1000, "b": 2000, "c": 3000, "unused": 1},
    )
    assert data.molecule_names == ("b", "a", "c")  # order of first appearance
    _assert_same(data.molecule, np.array([0, 1, 0, 2], np.int32))
    _assert_same(data.n_bp, np.array([2000.0, 1000.0, 3000.0]))
    assert data.n_points == 4 and len(data) == 4 and data.n_molecules == 3
    _assert_same(data.torque_controlled, np.array([False, False, True, False]))
    _assert_same(data.turns, np.array([1.0, -2.0, np.nan, 3.0]))
    assert data.force.dtype == jnp.float64 and data.molecule.dtype == jnp.int32
    assert float(data.temperature) == 298.15 and data.temperature.shape == ()
    assert data.force_sigma is None and data.turns_sigma is None and data.measured_torque is None


def test_from_arrays_int_ids_sequence_and_str_keys():
    seq = TweezerData.from_arrays(
        [1.0, 1.0, 1.0], [5.0, 6.0, 7.0], extension_sigma=1.0, torque=0.0, molecule=[7, 3, 7], n_bp=[700, 300]
    )
    assert seq.molecule_names == ("7", "3")
    _assert_same(seq.molecule, np.array([0, 1, 0], np.int32))
    _assert_same(seq.n_bp, np.array([700.0, 300.0]))
    keyed = TweezerData.from_arrays(
        [1.0, 1.0, 1.0], [5.0, 6.0, 7.0], extension_sigma=1.0, torque=0.0, molecule=np.array([7, 3, 7]), n_bp={"3": 300, 7: 700}
    )
    assert keyed.molecule_names == ("7", "3")
    _assert_same(keyed.n_bp, np.array([700.0, 300.0]))


def test_broadcasting_and_defaults():
    # a rotation curve at one force: force, sigmas and molecule are scalars
    data = TweezerData.from_arrays(
        2.5,
        [400.0, 390.0, 350.0],
        extension_sigma=4.0,
        turns=[0.0, 10.0, 20.0],
        force_sigma=0.1,
        turns_sigma=0.01,
        molecule="m1",
        n_bp=5000,
        temperature=293.15,
    )
    _assert_same(data.force, np.full(3, 2.5))
    _assert_same(data.extension_sigma, np.full(3, 4.0))
    _assert_same(data.force_sigma, np.full(3, 0.1))
    _assert_same(data.turns_sigma, np.full(3, 0.01))
    _assert_same(data.torque, np.full(3, np.nan))  # torque=None: no point is torque-controlled
    _assert_same(data.molecule, np.zeros(3, np.int32))
    _assert_same(data.n_bp, np.array([5000.0]))
    assert data.molecule_names == ("m1",) and float(data.temperature) == 293.15
    _assert_same(data.torque_controlled, np.zeros(3, bool))
    _assert_same(data.has_measured_torque, np.zeros(3, bool))
    default = TweezerData.from_arrays([1.0, 2.0], [3.0, 4.0], extension_sigma=1.0, torque=0.0, n_bp=10)
    assert default.molecule_names == ("0",)
    _assert_same(default.turns, np.full(2, np.nan))
    _assert_same(default.torque_controlled, np.ones(2, bool))


def test_measured_torque_mask_and_all_nan_is_none():
    data = TweezerData.from_arrays(
        **_base(measured_torque=[np.nan, 3.0, 4.0, np.nan], measured_torque_sigma=[np.nan, 0.5, 0.5, np.nan])
    )
    _assert_same(data.has_measured_torque, np.array([False, True, True, False]))
    _assert_same(data.measured_torque_sigma, np.array([np.nan, 0.5, 0.5, np.nan]))
    empty = TweezerData.from_arrays(**_base(measured_torque=np.nan, measured_torque_sigma=1.0))
    assert empty.measured_torque is None and empty.measured_torque_sigma is None
    _assert_same(empty.has_measured_torque, np.zeros(4, bool))


def test_direct_constructor_takes_indices():
    data = TweezerData(
        [1.0, 2.0], [3.0, 4.0], extension_sigma=1.0, torque=0.0, molecule=[1, 0], n_bp=[10.0, 20.0], molecule_names=("x", "y")
    )
    _assert_same(data.molecule, np.array([1, 0], np.int32))
    assert data.n_molecules == 2 and data.molecule_names == ("x", "y")
    scalar = TweezerData([1.0, 2.0], [3.0, 4.0], extension_sigma=1.0, torque=0.0, molecule=[0, 2], n_bp=50.0)
    _assert_same(scalar.n_bp, np.full(3, 50.0))
    assert scalar.molecule_names == ("0", "1", "2")


def test_is_a_pytree_and_builds_under_jit():
    data = TweezerData.from_arrays(**_base(molecule=["a", "a", "b", "b"], n_bp={"a": 100, "b": 200}))

    @eqx.filter_jit
    def total_bp(d):
        return jnp.sum(d.n_bp[d.molecule])

    assert float(total_bp(data)) == 600.0
    # traced inputs are stored unchecked (no ValueError from inside jit)
    f = jax.jit(lambda x: TweezerData(x, jnp.ones(3), extension_sigma=1.0, torque=0.0, n_bp=10.0).force)
    _assert_same(f(jnp.array([1.0, 2.0, 3.0])), np.array([1.0, 2.0, 3.0]))


VALIDATION = [
    ({"extension": [[1.0, 2.0, 3.0, 4.0]]}, r"extension must be one-dimensional"),
    ({"extension": []}, r"no data points"),
    ({"force": [1.0, 2.0, 3.0]}, r"force must be one-dimensional of length 4"),
    ({"turns": [0.0, 1.0]}, r"turns must be a scalar or one-dimensional of length 4"),
    ({"extension": [1.0, np.nan, 3.0, 4.0]}, r"extension has non-finite values in rows \[1\]"),
    ({"force": [1.0, 2.0, np.inf, 4.0]}, r"force has non-finite values in rows \[2\]"),
    ({"extension_sigma": [1.0, 1.0, 1.0, np.nan]}, r"extension_sigma has non-finite values in rows \[3\]"),
    ({"turns": [0.0, np.inf, np.nan, np.nan]}, r"turns has infinite values.*points \[1\]"),
    ({"force": [1.0, 0.0, -1.0, 4.0]}, r"force must be > 0.*points \[1, 2\]"),
    ({"extension_sigma": [1.0, 1.0, 0.0, 1.0]}, r"extension_sigma must be > 0.*points \[2\]"),
    ({"force_sigma": [0.1, -0.1, 0.1, 0.1]}, r"force_sigma must be > 0.*points \[1\]"),
    ({"turns_sigma": 0.0}, r"turns_sigma must be > 0.*points \[0, 1, 2, 3\]"),
    ({"torque": [1.0, np.nan, 0.0, 10.0]}, r"both turns and torque.*points \[0\]"),
    ({"turns": [0.0, np.nan, np.nan, np.nan]}, r"neither turns nor torque.*points \[1\]"),
    ({"measured_torque": [np.nan, 1.0, np.nan, np.nan]}, r"measured_torque_sigma is missing.*points \[1\]"),
    ({"measured_torque": [np.nan, 1.0, 2.0, np.nan], "measured_torque_sigma": [1.0, 1.0, np.nan, 1.0]}, r"missing \(NaN\).*points \[2\]"),
    ({"measured_torque": [np.nan, 1.0, 2.0, np.nan], "measured_torque_sigma": [1.0, 0.0, 1.0, 1.0]}, r"measured_torque_sigma must be > 0.*points \[1\]"),
    ({"measured_torque_sigma": 1.0}, r"measured_torque_sigma given without measured_torque"),
    ({"n_bp": 0}, r"n_bp must be > 0.*molecules \[0\]"),
    ({"n_bp": np.nan}, r"n_bp has non-finite values"),
    ({"molecule": ["a", "b", "a", "b"], "n_bp": [100, -5]}, r"n_bp must be > 0.*molecules \[1\]"),
    ({"molecule": ["a", "b", "a", "b"], "n_bp": [100, 200, 300]}, r"one value per molecule \(2"),
    ({"molecule": ["a", "b", "a", "c"], "n_bp": {"a": 1, "b": 2}}, r"n_bp has no entry for molecules \['c'\]"),
    ({"molecule": ["a", "b"]}, r"one id per point \(4\), got 2"),
    ({"molecule": [1, "1", 1, 1]}, r"distinct molecule ids with the same name"),
    ({"temperature": 0.0}, r"temperature \(kelvin\) must be finite and > 0"),
    ({"temperature": -3.0}, r"temperature \(kelvin\) must be finite and > 0"),
]


@pytest.mark.parametrize(("changes", "match"), VALIDATION)
def test_validation_errors(changes, match):
    with pytest.raises(ValueError, match=match):
        TweezerData.from_arrays(**_base(**changes))


def test_validation_molecule_index_out_of_range():
    with pytest.raises(ValueError, match=r"molecule index out of range 0\.\.1.*points \[2\]"):
        TweezerData([1.0, 1.0, 1.0], [1.0, 2.0, 3.0], extension_sigma=1.0, torque=0.0, molecule=[0, 1, 2], n_bp=[10.0, 20.0])
    with pytest.raises(ValueError, match=r"molecule index out of range.*points \[0\]"):
        TweezerData([1.0], [1.0], extension_sigma=1.0, torque=0.0, molecule=[-1], n_bp=[10.0])
    with pytest.raises(ValueError, match=r"molecule_names must be 2 strings"):
        TweezerData([1.0], [1.0], extension_sigma=1.0, torque=0.0, n_bp=[10.0, 20.0], molecule_names=("a",))


def test_validation_lists_only_the_first_points():
    force = np.ones(30)
    force[5:] = -1.0
    with pytest.raises(ValueError, match=r"points \[5, 6, 7, 8, 9, 10, 11, 12, 13, 14\] \.\.\. \(25 in all\)"):
        TweezerData.from_arrays(force, np.ones(30), extension_sigma=1.0, torque=0.0, n_bp=10)


# -- CSV -----------------------------------------------------------------------------------
def _mixed():
    return TweezerData.from_arrays(
        [0.5, 0.5, 2.0, 2.0, 1.0, 3.0],
        [1200.25, 1100.0 / 3.0, 1500.0, 1490.5, 800.0, 1e3 * math.pi],
        extension_sigma=[5.0, 5.5, 6.0, 6.5, 7.0, 7.5],
        turns=[0.0, 12.5, np.nan, -3.0, np.nan, np.nan],
        torque=[np.nan, np.nan, 0.0, np.nan, 15.0, -7.25],
        force_sigma=[0.01, 0.02, 0.03, 0.04, 0.05, 0.06],
        turns_sigma=0.1,
        measured_torque=[np.nan, 9.5, np.nan, -2.0, 14.0, np.nan],
        measured_torque_sigma=[np.nan, 0.5, np.nan, 0.25, 1.0, np.nan],
        molecule=["mol A", "mol A", "mol,B", "mol A", "mol,B", "mol,B"],
        n_bp={"mol A": 4200, "mol,B": 10_000},
        temperature=293.15,
    )


def test_csv_round_trip(tmp_path):
    data = _mixed()
    path = tmp_path / "mixed.csv"
    text = data.to_csv(path, comment="made by test_csv_round_trip")
    assert path.read_text(encoding="utf-8") == text
    lines = text.splitlines()
    header = lines.index("force,extension,turns,torque,extension_sigma,force_sigma,turns_sigma,measured_torque,measured_torque_sigma,molecule,n_bp")
    assert lines[header + 1] == "pN,nm,turns,pN nm,nm,pN,turns,pN nm,pN nm,id,bp"
    assert "# temperature: 293.15 K" in lines and "# made by test_csv_round_trip" in lines
    assert lines[header + 2].split(",")[2:4] == ["0.0", ""]  # NaN torque: an empty cell
    back = TweezerData.from_csv(path)
    for name in ("force", "force_sigma", "turns", "turns_sigma", "torque", "extension", "extension_sigma",
                 "measured_torque", "measured_torque_sigma", "molecule", "n_bp", "temperature"):
        _assert_same(getattr(back, name), getattr(data, name))
    assert back.molecule_names == ("mol A", "mol,B")
    assert back.to_csv(comment="made by test_csv_round_trip") == text
    _assert_same(back.torque_controlled, np.array([False, False, True, False, True, True]))
    _assert_same(back.has_measured_torque, np.array([False, True, False, True, True, False]))


def test_csv_round_trip_minimal_drops_empty_columns(tmp_path):
    data = TweezerData.from_arrays([1.0, 2.0], [300.0, 310.0], extension_sigma=2.0, torque=0.0, n_bp=1000)
    text = data.to_csv(tmp_path / "fd.csv")
    assert "force,extension,torque,extension_sigma,molecule,n_bp" in text.splitlines()
    back = TweezerData.from_csv(tmp_path / "fd.csv")
    _assert_same(back.turns, np.full(2, np.nan))
    _assert_same(back.extension, data.extension)
    assert back.molecule_names == ("0",) and back.measured_torque is None and back.force_sigma is None


def test_csv_docstring_example(tmp_path):
    doc = TweezerData.__doc__
    block = doc[doc.index("::\n") + 3 :]
    example = "\n".join(line[8:] for line in block.splitlines() if line.startswith("        "))
    data = TweezerData.from_csv(_write(tmp_path, example))
    assert data.molecule_names == ("a", "b")
    np.testing.assert_allclose(data.extension, [1520.0, 1440.0, 3100.0], rtol=1e-14)
    _assert_same(data.n_bp, np.array([6000.0, 10000.0]))
    _assert_same(data.torque_controlled, np.array([False, False, True]))
    np.testing.assert_allclose(float(data.temperature), 293.15, rtol=1e-14)


UNIT_SETS = [
    # force, extension (and its sigma), turns, torque; factor of each to pN, nm, turns, pN nm
    (("N", 1e12), ("\u00b5m", 1e3), ("deg", 1 / 360), ("N m", 1e21)),
    (("fN", 1e-3), ("\u03bcm", 1e3), ("rad", 1 / (2 * math.pi)), ("Nm", 1e21)),
    (("nN", 1e3), ("um", 1e3), ("turns", 1.0), ("pN um", 1e3)),
    ((" pN ", 1.0), ("mm", 1e6), ("deg", 1 / 360), ("pN\u00b7nm", 1.0)),
    (("pN", 1.0), ("m", 1e9), ("rad", 1 / (2 * math.pi)), ("N*m", 1e21)),
    (("pN", 1.0), (" nm", 1.0), ("turns", 1.0), ("pN*nm", 1.0)),
    (("pN", 1.0), ("nm", 1.0), ("turns", 1.0), ("pNnm", 1.0)),
]


@pytest.mark.parametrize(("force_unit", "length_unit", "turns_unit", "torque_unit"), UNIT_SETS)
def test_csv_unit_conversion(tmp_path, force_unit, length_unit, turns_unit, torque_unit):
    # internal values (pN, nm, turns, pN nm) and the same values written in the file's units
    force = np.array([0.25, 1.5, 4.0])
    force_sigma = np.array([0.01, 0.02, 0.05])
    extension = np.array([512.5, 1034.0, 3300.0])
    extension_sigma = np.array([3.0, 4.0, 5.5])
    turns = np.array([-7.5, np.nan, 20.0])
    turns_sigma = np.array([0.05, 0.05, 0.1])
    torque = np.array([np.nan, 12.5, np.nan])
    measured = np.array([-9.0, np.nan, 25.0])
    measured_sigma = np.array([0.5, np.nan, 1.5])
    (fu, ff), (lu, lf), (tu, tf), (qu, qf) = force_unit, length_unit, turns_unit, torque_unit

    def cell(v, factor):
        return "" if np.isnan(v) else repr(float(v / factor))

    lines = [
        "force,force_sigma,extension,extension_sigma,turns,turns_sigma,torque,measured_torque,measured_torque_sigma,n_bp",
        f"{fu},{fu},{lu},{lu},{tu},{tu},{qu},{qu},{qu},bp",
    ]
    for i in range(3):
        lines.append(",".join([
            cell(force[i], ff), cell(force_sigma[i], ff), cell(extension[i], lf), cell(extension_sigma[i], lf),
            cell(turns[i], tf), cell(turns_sigma[i], tf), cell(torque[i], qf), cell(measured[i], qf),
            cell(measured_sigma[i], qf), "8000",
        ]))
    data = TweezerData.from_csv(_write(tmp_path, "\n".join(lines) + "\n"))
    for name, expected in [
        ("force", force), ("force_sigma", force_sigma), ("extension", extension), ("extension_sigma", extension_sigma),
        ("turns", turns), ("turns_sigma", turns_sigma), ("torque", torque), ("measured_torque", measured),
        ("measured_torque_sigma", measured_sigma),
    ]:
        np.testing.assert_allclose(np.asarray(getattr(data, name)), expected, rtol=1e-12, atol=0, err_msg=name)
    _assert_same(data.n_bp, np.array([8000.0]))


CSV_HEAD = "# a comment\nforce,extension,turns,extension_sigma,n_bp\n"
CSV_ERRORS = [
    (CSV_HEAD + "pN,nm,kN,nm,bp\n1,2,3,4,5\n", r"data\.csv:3: unknown unit 'kN' for column turns; allowed: \['turns', 'rad', 'deg'\]"),
    (CSV_HEAD + "PN,nm,turns,nm,bp\n1,2,3,4,5\n", r"data\.csv:3: unknown unit 'PN' for column force"),
    (CSV_HEAD + "pN,nm,turns,nm,kbp\n1,2,3,4,5\n", r"data\.csv:3: unknown unit 'kbp' for column n_bp"),
    ("force,extension,turns,extension_sigma,bp\n", r"data\.csv:1: unknown columns \['bp'\]; allowed: \['force', 'extension'"),
    (CSV_HEAD + "1,2,3,4,5\n2,3,4,5,6\n", r"data\.csv:3: missing units line"),
    (CSV_HEAD, r"data\.csv:2: missing units line"),
    (CSV_HEAD + "pN,nm,turns,nm\n1,2,3,4,5\n", r"data\.csv:3: units line has 4 cells, header has 5"),
    (CSV_HEAD + "pN,nm,turns,nm,bp\n1,2,3,4,5\n1,abc,3,4,5\n", r"data\.csv:5: not a number in column extension: 'abc'"),
    (CSV_HEAD + "pN,nm,turns,nm,bp\n1,2,3,4,5\n\nnan,2,3,4,5\n", r"data\.csv:6: non-finite value 'nan' in column force"),
    (CSV_HEAD + "pN,nm,turns,nm,bp\n1,2,inf,4,5\n", r"data\.csv:4: non-finite value 'inf' in column turns"),
    (CSV_HEAD + "pN,nm,turns,nm,bp\n1,2,3,,5\n", r"data\.csv:4: empty cell in column extension_sigma"),
    (CSV_HEAD + "pN,nm,turns,nm,bp\n1,2,3,4,5\n1,2,3,4\n", r"data\.csv:5: 4 cells, expected 5"),
    (CSV_HEAD + "pN,nm,turns,nm,bp\n1,2,3,4,5\n-1,2,3,4,5\n", r"data\.csv: lines \[5\]: .*force must be > 0"),
    (CSV_HEAD + "pN,nm,turns,nm,bp\n1,2,,4,5\n", r"data\.csv: lines \[4\]: .*neither turns nor torque"),
    (CSV_HEAD + "pN,nm,turns,nm,bp\n1,2,3,4,5\n1,2,3,4,-5\n", r"data\.csv: lines \[5\]: n_bp must be > 0"),
    ("# temperature: -300 C\n" + CSV_HEAD + "pN,nm,turns,nm,bp\n1,2,3,4,5\n", r"data\.csv:1: temperature -26\.8.* K is not > 0"),
    ("force,extension,extension_sigma,n_bp\npN,nm,nm,bp\n1,2,3,4\n", r"data\.csv:1: needs a turns or a torque column"),
    ("force,turns,extension_sigma,n_bp\npN,turns,nm,bp\n1,2,3,4\n", r"data\.csv:1: missing required columns \['extension'\]"),
    ("force,extension,turns,n_bp\npN,nm,turns,bp\n1,2,3,4\n", r"data\.csv:1: no extension_sigma column"),
    ("force,extension,turns,extension_sigma\npN,nm,turns,nm\n1,2,3,4\n", r"data\.csv:1: no n_bp column"),
    ("force,force,turns,extension_sigma,n_bp\n", r"data\.csv:1: repeated column names"),
    ("# temperature: warm\n" + CSV_HEAD + "pN,nm,turns,nm,bp\n1,2,3,4,5\n", r"data\.csv:1: cannot read the temperature comment"),
    ("# temperature: 290 K\n# temperature: 300 K\n" + CSV_HEAD + "pN,nm,turns,nm,bp\n1,2,3,4,5\n", r"data\.csv:2: temperature comment \(300\.0 K\) contradicts line 1"),
    ("# only comments\n", r"data\.csv: no header line"),
    (CSV_HEAD + "pN,nm,turns,nm,bp\n", r"data\.csv: no data rows"),
]


@pytest.mark.parametrize(("text", "match"), CSV_ERRORS)
def test_csv_errors_name_the_line(tmp_path, text, match):
    path = tmp_path / "data.csv"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ValueError, match=match):
        TweezerData.from_csv(path, strict=True)  # strict: an unknown column is an error


def test_csv_unknown_columns_are_ignored_with_a_warning(tmp_path):
    path = _write(tmp_path, "force,extension,bead,turns,extension_sigma,n_bp\npN,nm,-,turns,nm,bp\n1,2,b7,3,4,5\n")
    with pytest.warns(UserWarning, match=r"data\.csv:1: ignoring columns \['bead'\]"):
        data = TweezerData.from_csv(path)
    np.testing.assert_allclose(np.asarray(data.turns), [3.0])
    bad = _write(tmp_path, "force,extension,bead,turns,extension_sigma,n_bp\npN,nm,-,turns,nm,bp\n1,2,3,4,5\n")
    with pytest.warns(UserWarning), pytest.raises(ValueError, match=r"data\.csv:3: 5 cells, expected 6"):
        TweezerData.from_csv(bad)


def test_csv_empty_molecule_id(tmp_path):
    path = _write(tmp_path, "force,extension,torque,extension_sigma,molecule\npN,nm,pN nm,nm,id\n1,2,0,1,a\n1,2,0,1,\n")
    with pytest.raises(ValueError, match=r":4: empty molecule id"):
        TweezerData.from_csv(path, n_bp=10)


@pytest.mark.parametrize(
    ("comment", "kelvin"),
    [("# temperature: 293.15 K", 293.15), ("# temperature: 20 C", 20 + 273.15), ("#Temperature:25degC", 25 + 273.15),
     ("# temperature: 3.1e2 K", 310.0), ("# temperature: 37 \u00b0C", 37 + 273.15), ("# no temperature here", 298.15)],
)
def test_csv_temperature_comment(tmp_path, comment, kelvin):
    path = _write(tmp_path, f"{comment}\nforce,extension,torque,extension_sigma\npN,nm,pN nm,nm\n1,2,0,1\n")
    data = TweezerData.from_csv(path, n_bp=100)
    assert float(data.temperature) == pytest.approx(kelvin, rel=1e-15)
    assert float(TweezerData.from_csv(path, n_bp=100, temperature=300.0).temperature) == 300.0


def test_csv_n_bp_inconsistent_within_molecule(tmp_path):
    path = _write(
        tmp_path,
        """
        force,extension,turns,extension_sigma,molecule,n_bp
        pN,nm,turns,nm,-,bp
        1,100,0,1,a,1000
        1,100,0,1,b,2000
        1,100,1,1,a,1001
        1,100,2,1,a,1000
        """,
    )
    with pytest.raises(ValueError, match=r"n_bp differs within molecule 'a': values \[1000\.0, 1001\.0\] on lines \[3, 5, 6\]"):
        TweezerData.from_csv(path)
    # an argument overrides the column
    data = TweezerData.from_csv(path, n_bp={"a": 10, "b": 20})
    _assert_same(data.n_bp, np.array([10.0, 20.0]))


def test_csv_arguments_and_molecule_ids(tmp_path):
    path = _write(
        tmp_path,
        """
        molecule,torque,extension,force
        ,pN nm,um,pN
        7,0,1.5,1
        x,0,2.5,2
        7,,3.5,3
        """,
    )
    with pytest.raises(ValueError, match=r"lines \[5\]: .*neither turns nor torque"):
        TweezerData.from_csv(path, n_bp=100, extension_sigma=2.0)
    path = _write(tmp_path, path.read_text().replace("7,,3.5,3", "7,1,3.5,3"))
    data = TweezerData.from_csv(path, n_bp={"7": 700, "x": 800}, extension_sigma=[1.0, 2.0, 3.0])
    assert data.molecule_names == ("7", "x")
    _assert_same(data.molecule, np.array([0, 1, 0], np.int32))
    _assert_same(data.n_bp, np.array([700.0, 800.0]))
    _assert_same(data.extension, np.array([1500.0, 2500.0, 3500.0]))
    _assert_same(data.extension_sigma, np.array([1.0, 2.0, 3.0]))


def test_to_csv_rejects_names_that_do_not_survive():
    data = TweezerData.from_arrays([1.0], [2.0], extension_sigma=1.0, torque=0.0, molecule=" a", n_bp=10)
    with pytest.raises(ValueError, match=r"molecule name ' a' would not survive"):
        data.to_csv()


# -- lumicks pylake ----------------------------------------------------------------------
def _bluelake_file(path, force, distance, name="fd1"):
    """A minimal Bluelake HDF5 file (format 2) with one FD curve: the force channel `Force LF/Force 2`
    and the distance channel `Distance/Distance 1`, the channels an FdCurve reads by default."""
    h5py = pytest.importorskip("h5py")
    lk = pytest.importorskip("lumicks.pylake")
    timestamps = 1_000_000_000 + 1000 * np.arange(len(force), dtype=np.int64)
    compound = np.dtype([("Timestamp", np.int64), ("Value", float)])
    with h5py.File(path, "w") as h5:
        h5.attrs["Bluelake version"] = "test"
        h5.attrs["File format version"] = 2
        for group, channel, values in [("Force LF", "Force 2", force), ("Distance", "Distance 1", distance)]:
            h5.require_group(group)[channel] = np.array(list(zip(timestamps, values)), compound)
            h5[group][channel].attrs["Kind"] = b"TimeSeries"
        curve = h5.require_group("FD Curve").create_dataset(name, data="{}")
        curve.attrs["Start time (ns)"] = timestamps[0]
        curve.attrs["Stop time (ns)"] = timestamps[-1] + 1
    return lk.File(str(path)).fdcurves[name]


def test_from_pylake_real_fdcurve(tmp_path):
    force = np.array([0.5, 1.0, 5.0, 20.0])
    distance_um = np.array([2.1, 2.5, 2.9, 3.3])
    fd = _bluelake_file(tmp_path / "fd.h5", force, distance_um)
    from lumicks.pylake.fdcurve import FdCurve

    assert isinstance(fd, FdCurve) and fd.d.labels["y"] == "Distance (\u03bcm)"
    data = TweezerData.from_pylake(fd, n_bp=10_000, extension_sigma=3.0, force_sigma=0.05, temperature=296.0)
    np.testing.assert_allclose(data.extension, [2100.0, 2500.0, 2900.0, 3300.0], rtol=1e-15)
    _assert_same(data.force, force)
    _assert_same(data.torque, np.zeros(4))
    _assert_same(data.turns, np.full(4, np.nan))
    _assert_same(data.torque_controlled, np.ones(4, bool))
    _assert_same(data.force_sigma, np.full(4, 0.05))
    assert data.molecule_names == ("fd1",) and float(data.temperature) == 296.0
    _assert_same(data.n_bp, np.array([10_000.0]))
    renamed = TweezerData.from_pylake(fd, n_bp={"lambda": 48_502}, extension_sigma=3.0, molecule="lambda")
    assert renamed.molecule_names == ("lambda",)


def test_from_pylake_drop_invalid(tmp_path):
    force = np.array([1.0, np.nan, 2.0, -0.5, 3.0, 4.0])
    distance_um = np.array([1.0, 1.1, 0.0, 1.3, 1.4, np.inf])
    fd = _bluelake_file(tmp_path / "fd.h5", force, distance_um)
    with pytest.raises(ValueError, match=r"non-finite force at points \[1\].*force <= 0 at points \[3\].*drop_invalid=True"):
        TweezerData.from_pylake(fd, n_bp=100, extension_sigma=1.0)
    sigma = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    data = TweezerData.from_pylake(fd, n_bp=100, extension_sigma=sigma, drop_invalid=True)
    _assert_same(data.force, np.array([1.0, 3.0]))
    np.testing.assert_allclose(data.extension, [1000.0, 1400.0], rtol=1e-15)
    _assert_same(data.extension_sigma, np.array([1.0, 5.0]))


def test_from_pylake_channel_labels_and_type(tmp_path):
    pytest.importorskip("lumicks.pylake")
    from lumicks.pylake.channel import Slice, TimeSeries
    from lumicks.pylake.fdcurve import FdCurve

    timestamps = np.arange(3, dtype=np.int64) * 10 + 100

    def curve(distance_label):
        # FdCurve reads its default channels from `file.downsampled_force2` and `file.distance1`
        source = types.SimpleNamespace(
            downsampled_force2=Slice(TimeSeries(np.array([1.0, 2.0, 3.0]), timestamps), labels={"y": "Force (pN)"}),
            distance1=Slice(TimeSeries(np.array([100.0, 200.0, 300.0]), timestamps), labels={"y": distance_label}),
        )
        return FdCurve(file=source, start=100, stop=200, name="")

    data = TweezerData.from_pylake(curve("Distance (nm)"), n_bp=10, extension_sigma=1.0)
    _assert_same(data.extension, np.array([100.0, 200.0, 300.0]))
    assert data.molecule_names == ("0",)
    with pytest.raises(ValueError, match=r"unit 'px' is not one of"):
        TweezerData.from_pylake(curve("Distance (px)"), n_bp=10, extension_sigma=1.0)
    with pytest.raises(TypeError, match=r"expected a lumicks.pylake FdCurve"):
        TweezerData.from_pylake(object(), n_bp=10, extension_sigma=1.0)


def test_from_pylake_without_pylake(monkeypatch):
    monkeypatch.setitem(sys.modules, "lumicks.pylake.fdcurve", None)  # makes the import fail
    with pytest.raises(ImportError, match=r'pip install "helixrod\[tweezers\]"'):
        TweezerData.from_pylake(object(), n_bp=10, extension_sigma=1.0)
