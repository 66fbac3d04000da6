"""HelixData: the CSV round trip (units, comments) and the documented errors of the
constructor and of from_csv."""

import jax
import numpy as np
import pytest
from helpers import fit_grid, random_rods

import helixrod as hr


def test_csv_round_trip(tmp_path, rng):
    kappa, tau = fit_grid(rng)
    rod = random_rods(rng, 1)[0]
    data = hr.synthetic_helix_data(rod, kappa, tau, 0.05, jax.random.key(5), units={"force": "pN", "kappa": "1/nm"})
    path = tmp_path / "d.csv"
    data.to_csv(path, comment="test data")
    back = hr.HelixData.from_csv(path)
    for name in ("force", "moment", "kappa", "tau", "force_sigma", "moment_sigma", "register"):
        np.testing.assert_array_equal(np.asarray(getattr(back, name)), np.asarray(getattr(data, name)))
    assert back.units["force"] == "pN" and back.units["kappa"] == "1/nm"
    text = path.read_text().splitlines()
    assert text[2].startswith("force,moment,kappa,tau") and text[3].startswith("pN,")


def test_bad_inputs_give_documented_errors(tmp_path):
    ok = dict(force=[1.0, 2.0], moment=[0.5, 0.1], kappa=[1.0, 0.5], tau=[0.2, -0.3])
    with pytest.raises(ValueError, match="mismatched lengths"):
        hr.HelixData(**{**ok, "tau": [0.1]})
    with pytest.raises(ValueError, match=r"non-finite.*rows \[1\]"):
        hr.HelixData(**{**ok, "moment": [0.5, np.inf]})
    assert not bool(hr.HelixData(**{**ok, "moment": [0.5, np.nan]}).moment_observed[1])  # NaN: not measured
    with pytest.raises(ValueError, match=r"force_sigma must be > 0; rows \[0\]"):
        hr.HelixData(**ok, force_sigma=[0.0, 1.0])
    with pytest.raises(ValueError, match="kappa must be > 0"):
        hr.HelixData(**{**ok, "kappa": [-1.0, 0.5]})
    with pytest.raises(ValueError, match="convention"):
        hr.HelixData(**ok, convention="lab")
    flipped = hr.HelixData(**ok, convention="advance")
    np.testing.assert_array_equal(np.asarray(flipped.force), [1.0, -2.0])
    path = tmp_path / "bad.csv"
    path.write_text("force,moment,kappa,tau,force_sigma,moment_sigma\nN,N m,1/m,1/m,N,N m\n1,1,1,1,1,1\n1,inf,1,1,1,1\n")
    with pytest.raises(ValueError, match=r"lines \[4\]"):
        hr.HelixData.from_csv(path)
    path.write_text("force,moment,kappa,tau\n1,1,1,1\n")
    with pytest.raises(ValueError, match="force_sigma and moment_sigma"):
        hr.HelixData.from_csv(path)
    assert len(hr.HelixData.from_csv(path, force_sigma=0.1, moment_sigma=0.1)) == 1


def test_csv_units_are_converted_or_kept_as_labels(tmp_path):
    """SI units on the units line are converted to pN, pN nm, 1/nm and rad (the fitted K in
    pN nm^2); the rod's own scales (labels) are kept; mixing the two, or an angle in an
    unknown unit, is a named error; a UTF-8 byte-order mark is dropped."""
    rows = "1e-12,2e-21,1e9,-5e8,1e-13,1e-22,90\n3e-12,1e-21,2e9,5e8,1e-13,1e-22,45\n"
    header = "force,moment,kappa,tau,force_sigma,moment_sigma,register\n"
    si = tmp_path / "si.csv"
    si.write_text("\ufeff" + header + "N,N m,1/m,1/m,N,N m,deg\n" + rows, encoding="utf-8")
    data = hr.HelixData.from_csv(si)
    np.testing.assert_allclose(data.force, [1.0, 3.0], rtol=1e-14)
    np.testing.assert_allclose(data.moment, [2.0, 1.0], rtol=1e-14)
    np.testing.assert_allclose(data.kappa, [1.0, 2.0], rtol=1e-14)
    np.testing.assert_allclose(data.tau, [-0.5, 0.5], rtol=1e-14)
    np.testing.assert_allclose(data.force_sigma, [0.1, 0.1], rtol=1e-14)
    np.testing.assert_allclose(data.register, [np.pi / 2, np.pi / 4], rtol=1e-14)
    assert data.units == {"force": "pN", "moment": "pN nm", "kappa": "1/nm", "tau": "1/nm", "force_sigma": "pN",
                          "moment_sigma": "pN nm", "register": "rad"}
    labels = tmp_path / "labels.csv"
    labels.write_text(header + "K1/L^2,K1/L,1/L,1/L,K1/L^2,K1/L,rad\n" + rows)
    kept = hr.HelixData.from_csv(labels)
    np.testing.assert_array_equal(kept.force, [1e-12, 3e-12])
    assert kept.units["moment"] == "K1/L"
    mixed = tmp_path / "mixed.csv"
    mixed.write_text(header + "N,K1/L,1/m,1/m,N,N m,rad\n" + rows)
    with pytest.raises(ValueError, match=r"mixed.csv:2: the units line mixes physical units .* with labels"):
        hr.HelixData.from_csv(mixed)
    grads = tmp_path / "grads.csv"
    grads.write_text(header + "N,N m,1/m,1/m,N,N m,grad\n" + rows)
    with pytest.raises(ValueError, match="unknown unit 'grad' for column register"):
        hr.HelixData.from_csv(grads)


def test_csv_first_row_units_and_file_lines(tmp_path):
    header = "force,moment,kappa,tau,force_sigma,moment_sigma\n"
    # A first data row that begins with an empty cell (no force measured) is data, not units.
    path = tmp_path / "a.csv"
    path.write_text(header + ",1.0,0.5,0.3,0.1,0.1\n2.0,1.5,0.6,0.4,0.1,0.1\n")
    data = hr.HelixData.from_csv(path)
    assert len(data) == 2 and data.units == {} and np.isnan(data.force[0]) and data.moment[0] == 1.0
    path.write_text(header + ",,1,1,1,1\n2.0,1.5,0.6,0.4,0.1,0.1\n")
    with pytest.raises(ValueError, match="observe neither force nor moment"):
        hr.HelixData.from_csv(path)
    # A first data row with text in it (a typo, "NA") is a data row with an error that names
    # its line, not a units line (which would lose the row and take its numbers for units).
    for row in ("NA,0.5,1.2,0.3,0.01,0.01", "1.0x,0.5,1.2,0.3,0.01,0.01", "1.0,0.5,1.2x,0.3,0.01,0.01"):
        path.write_text(header + row + "\n1.0,0.5,1.1,0.3,0.01,0.01\n")
        with pytest.raises(ValueError, match=r"a.csv:2: not a number"):
            hr.HelixData.from_csv(path)
    path.write_text(header + "1.0,0.5,1.2x,0.3y,0.01,0.01\n1.0,0.5,1.1,0.3,0.01,0.01\n")
    with pytest.raises(ValueError, match=r"a.csv:2: neither a units line \(numbers in \['force', 'moment'"):
        hr.HelixData.from_csv(path)
    # The checks of the values name the file's lines (comments and blank lines counted).
    path.write_text("# a comment\n" + header + "\n1.0,1.0,0.5,0.3,0.1,0.1\n2.0,1.5,-1,0.4,0.1,0.1\n")
    with pytest.raises(ValueError, match=r"kappa must be > 0.*rows \[1\] are not \(file lines \[5\]"):
        hr.HelixData.from_csv(path)
    # An unstated register sigma is in its register's unit.
    path.write_text("force,moment,kappa,tau,force_sigma,moment_sigma,register,register_sigma\n"
                    "pN,pN nm,1/nm,1/nm,pN,pN nm,deg,-\n1.0,1.0,0.5,0.3,0.1,0.1,90,1\n")
    data = hr.HelixData.from_csv(path)
    np.testing.assert_allclose([data.register[0], data.register_sigma[0]], [np.pi / 2, np.pi / 180], rtol=1e-12)


def test_csv_extra_columns_are_ignored_with_a_warning_or_strict_errors(tmp_path):
    path = tmp_path / "extra.csv"
    path.write_text("force,moment,kappa,tau,temperature,force_sigma,moment_sigma\n1,2,1,0.5,298,0.1,0.1\n")
    with pytest.warns(UserWarning, match=r"extra.csv:1: ignoring columns \['temperature'\]"):
        data = hr.HelixData.from_csv(path)
    np.testing.assert_array_equal(data.force_sigma, [0.1])
    with pytest.raises(ValueError, match=r"extra.csv:1: unknown columns \['temperature'\]"):
        hr.HelixData.from_csv(path, strict=True)
