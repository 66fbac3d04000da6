"""Observations of helices under an axial wrench: `HelixData`, its CSV form, and
`synthetic_helix_data`.

Conventions (docs/conventions.md): `force` is $F = n\\cdot a$ and `moment` is $M = m\\cdot a$ along the
helix axis $a = u/|u|$, $u = (\\kappa\\sin\\varphi, \\kappa\\cos\\varphi, \\tau)$.  Because
$a\\cdot d_3 = \\tau/|u|$, the axis points the way the helix advances only for $\\tau > 0$:
for a left-handed helix ($\\tau < 0$) a pull is $F < 0$.  Data measured along the direction of
advance (pull positive whatever the handedness) must be multiplied by
$\\operatorname{sign}\\tau$ first; `HelixData(..., convention="advance")` does it.
Neither $F$ nor $M$ depends on the choice of the director frame (they are scalars along
the axis), so the data carry no sign convention beyond this one; the register $\\varphi$ does
(it is measured from $d_2$ towards $d_1$, docs/conventions.md), which is why an observed register
breaks the frame symmetries of the fit.
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._equilibria import helix_equilibria
from .._misc import check_key, is_concrete, random_normal, random_split, real_array, write_atomically
from .._rod import Rod, check_quadratic_rod
from ._csv import PointError, drop_unknown_columns
from ._units import ANGLE_UNITS, DIMENSIONLESS_UNITS, FORCE_UNITS, INVERSE_LENGTH_UNITS, TORQUE_UNITS

# The unit tables of each column's physical units (sigmas share their column's).
_PHYSICAL = {
    "force": FORCE_UNITS, "moment": TORQUE_UNITS, "kappa": INVERSE_LENGTH_UNITS, "tau": INVERSE_LENGTH_UNITS,
}
_INTERNAL_UNITS = {"force": "pN", "moment": "pN nm", "kappa": "1/nm", "tau": "1/nm", "register": "rad"}


def _unit_factors(units: dict[str, str], where: str) -> tuple[dict[str, float], dict[str, str]]:
    """Conversion factors of a units line to the internal units, and the units after it:
    physical units of force, moment, kappa and tau convert (all stated ones or none: labels
    stay labels; '-' or an empty cell is not stated), the register's rad or deg always,
    the correlation is dimensionless."""
    base = lambda name: name.removesuffix("_sigma")
    unstated = [n for n, u in units.items() if base(n) in _PHYSICAL and u in ("", "-")]
    physical = {n: u for n, u in units.items() if base(n) in _PHYSICAL and u in _PHYSICAL[base(n)]}
    labels = [n for n in units if base(n) in _PHYSICAL and n not in physical and n not in unstated]
    if physical and labels:
        raise ValueError(
            f"{where}: the units line mixes physical units ({', '.join(f'{n} {units[n]}' for n in physical)}) with "
            f"labels that are not ({', '.join(f'{n} {units[n]!r}' for n in labels)}); give every column in physical units "
            f"(force: {', '.join(FORCE_UNITS)}; moment: {', '.join(TORQUE_UNITS)}; kappa, tau: 1/nm, 1/um, 1/m, ...) or none"
        )
    scaled = [n for n, u in physical.items() if _PHYSICAL[base(n)][u] != 1.0]
    if scaled and unstated:
        raise ValueError(
            f"{where}: {', '.join(scaled)} would be converted to pN and nm, but the units of {', '.join(unstated)} "
            "are not stated ('-'); state every column's unit"
        )
    factors, converted = {}, {}
    for name, unit in units.items():
        kind = base(name)
        if name in physical:
            factors[name], converted[name] = _PHYSICAL[kind][unit], _INTERNAL_UNITS[kind]
        elif kind == "register":
            if unit in ("", "-"):  # unstated: a sigma in its register's unit, else radians
                unit = units.get("register", "rad") if name == "register_sigma" else "rad"
                unit = "rad" if unit in ("", "-") else unit
            if unit not in ANGLE_UNITS:
                raise ValueError(f"{where}: unknown unit {unit!r} for column {name}; allowed: {list(ANGLE_UNITS)}")
            factors[name], converted[name] = ANGLE_UNITS[unit], "rad"
        elif kind == "kappa_tau_correlation":
            if unit not in DIMENSIONLESS_UNITS:
                raise ValueError(f"{where}: {name} is dimensionless; its unit must be one of {list(DIMENSIONLESS_UNITS)}, got {unit!r}")
            factors[name], converted[name] = 1.0, unit
        else:
            factors[name], converted[name] = 1.0, unit
    return factors, converted


#: Column order of the CSV form; the first four are required.
CSV_COLUMNS = (
    "force",
    "moment",
    "kappa",
    "tau",
    "force_sigma",
    "moment_sigma",
    "kappa_sigma",
    "tau_sigma",
    "kappa_tau_correlation",
    "register",
    "register_sigma",
)
_OPTIONAL = ("kappa_sigma", "tau_sigma", "kappa_tau_correlation", "register", "register_sigma")
# Cells that may be empty (or 'nan'): the quantity was not measured at that point.
_MAY_BE_EMPTY = ("force", "moment", "force_sigma", "moment_sigma")


def measured(values: Array) -> Array:
    """The mask of the measured entries of a data column (a missing value is NaN)."""
    return ~jnp.isnan(values)


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


class HelixData(eqx.Module):
    """Measured uniform helices: axial force and moment at given curvature and torsion.

    Fields (each shape `(n,)`, float64): `force` $F$, `moment` $M$, `kappa` $\\kappa > 0$,
    `tau` $\\tau$, and the standard deviations `force_sigma`, `moment_sigma` (a scalar
    broadcasts to every point).

    Partial observations: `force=None` or `moment=None` when that quantity was not
    measured at all (e.g. force-only data: the moment is hard to measure), and NaN at the
    points where it was not measured; `force_observed`, `moment_observed` are the masks.
    The fit, its error bars, the identifiability report and the bootstrap then use what
    is observed; a sigma is read only where its quantity is observed (NaN elsewhere is
    fine).  Every point must observe at least one of the two.  Optional (`None` when absent): `kappa_sigma`, `tau_sigma`
    (errors in the abscissae, used by `fit_stiffness(..., errors_in_variables=True)`) and
    `kappa_tau_correlation` (their correlation coefficient, in $[-1, 1]$; e.g. $\\kappa$ and
    $\\tau$ computed from the same two noisy observables),
    `register` $\\varphi$ of each helix if it was observed, and `register_sigma`
    (then the fit also matches $\\varphi$).  `units` maps column names to unit strings,
    carried to CSV as given (this constructor never converts; `from_csv` converts physical
    units on a units line to pN, pN nm, 1/nm and rad, so data written in, e.g., N come back
    in pN, with their units saying so).

    Units must be consistent: with force in [F] and twists in [1/L], moments are in [F L]
    and the fitted stiffnesses in [F L^2].

    `convention`: `"axis"` (default) -- `force`, `moment` are along $a = u/|u|$ as in
    docs/conventions.md; `"advance"` -- they were measured along the direction in which the helix
    advances (pull positive for either handedness), and are multiplied by
    $\\operatorname{sign}\\tau$ here.

    Bad input raises `ValueError` naming the problem: mismatched lengths, non-finite
    entries (reported by row number, counted from 0), $\\sigma \\le 0$, $\\kappa \\le 0$
    ($\\kappa = 0$ is a straight rod, which has no register), $\\tau = 0$ with
    `convention="advance"`.
    """

    force: Float[Array, " n"]
    moment: Float[Array, " n"]
    kappa: Float[Array, " n"]
    tau: Float[Array, " n"]
    force_sigma: Float[Array, " n"]
    moment_sigma: Float[Array, " n"]
    kappa_sigma: Float[Array, " n"] | None
    tau_sigma: Float[Array, " n"] | None
    kappa_tau_correlation: Float[Array, " n"] | None
    register: Float[Array, " n"] | None
    register_sigma: Float[Array, " n"] | None
    unit_labels: tuple = eqx.field(static=True)

    def __init__(
        self,
        force: ArrayLike | None,
        moment: ArrayLike | None,
        kappa: ArrayLike,
        tau: ArrayLike,
        force_sigma: ArrayLike = 1.0,
        moment_sigma: ArrayLike = 1.0,
        *,
        kappa_sigma: ArrayLike | None = None,
        tau_sigma: ArrayLike | None = None,
        kappa_tau_correlation: ArrayLike | None = None,
        register: ArrayLike | None = None,
        register_sigma: ArrayLike | None = None,
        units: dict | None = None,
        convention: str = "axis",
    ):
        if force is None and moment is None:
            raise ValueError("HelixData: neither force nor moment is given: there is nothing to fit")
        absent = np.full(np.size(np.asarray(kappa)), np.nan)  # a quantity not measured at any point
        columns = {
            "force": absent if force is None else force, "moment": absent if moment is None else moment,
            "kappa": kappa, "tau": tau,
        }
        arrays = {}
        for name, x in columns.items():
            a = real_array(x, name, "HelixData")
            if a.ndim != 1:
                raise ValueError(f"HelixData: {name} must be one-dimensional, got shape {a.shape}")
            arrays[name] = a
        lengths = {name: a.shape[0] for name, a in arrays.items()}
        if len(set(lengths.values())) != 1:
            raise ValueError(f"HelixData: mismatched lengths {lengths}")
        n = lengths["force"]
        if n == 0:
            raise ValueError("HelixData: no data points")
        sigmas = {"force_sigma": force_sigma, "moment_sigma": moment_sigma}
        optional = {
            "kappa_sigma": kappa_sigma,
            "tau_sigma": tau_sigma,
            "kappa_tau_correlation": kappa_tau_correlation,
            "register": register,
            "register_sigma": register_sigma,
        }
        for name, x in {**sigmas, **optional}.items():
            if x is None:
                continue
            a = real_array(x, name, "HelixData")
            if a.ndim == 0:
                a = np.full(n, float(a))
            if a.shape != (n,):
                raise ValueError(f"HelixData: {name} must be a scalar or have length {n}, got shape {a.shape}")
            arrays[name] = a
        if register_sigma is not None and register is None:
            raise ValueError("HelixData: register_sigma given without register")
        if kappa_tau_correlation is not None and (kappa_sigma is None or tau_sigma is None):
            raise ValueError("HelixData: kappa_tau_correlation needs both kappa_sigma and tau_sigma")
        observed = {name: ~np.isnan(arrays[name]) for name in ("force", "moment")}
        neither = np.flatnonzero(~observed["force"] & ~observed["moment"])
        if neither.size:
            raise PointError(
                f"HelixData: rows {neither[:20].tolist()} observe neither force nor moment (NaN in both): "
                "drop them, they carry no information", neither
            )
        # A quantity and its sigma are read only where the quantity is observed.
        read = {"force": observed["force"], "moment": observed["moment"],
                "force_sigma": observed["force"], "moment_sigma": observed["moment"]}
        bad_rows = {}
        for name, a in arrays.items():
            rows = np.flatnonzero(read.get(name, True) & ~np.isfinite(a))
            if rows.size:
                bad_rows[name] = rows.tolist()
        if bad_rows:
            rows = sorted({r for v in bad_rows.values() for r in v})
            raise PointError(
                f"HelixData: non-finite (NaN or infinite) values in rows {rows[:20]}"
                + (" ..." if len(rows) > 20 else "")
                + f" (columns: {', '.join(f'{k} rows {v[:5]}' for k, v in bad_rows.items())})",
                rows,
            )
        for name in ("force_sigma", "moment_sigma", "kappa_sigma", "tau_sigma", "register_sigma"):
            where = read.get(name, True)
            if name in arrays and np.any(where & ~(arrays[name] > 0)):
                rows = np.flatnonzero(where & ~(arrays[name] > 0))
                raise PointError(f"HelixData: {name} must be > 0; rows {rows[:20].tolist()} are not", rows)
        if "kappa_tau_correlation" in arrays and np.any(np.abs(arrays["kappa_tau_correlation"]) > 1):
            rows = np.flatnonzero(np.abs(arrays["kappa_tau_correlation"]) > 1)
            raise PointError(f"HelixData: kappa_tau_correlation must be in [-1, 1]; rows {rows[:20].tolist()} are not", rows)
        if np.any(arrays["kappa"] <= 0):
            rows = np.flatnonzero(arrays["kappa"] <= 0)
            raise PointError(
                f"HelixData: kappa must be > 0 (kappa < 0 is not a curvature; kappa = 0 is a "
                f"straight rod, which has no register); rows {rows[:20].tolist()} are not", rows
            )
        if convention == "advance":
            if np.any(arrays["tau"] == 0):
                raise ValueError("HelixData: convention='advance' needs tau != 0 (a ring has no direction of advance)")
            s = np.sign(arrays["tau"])
            arrays["force"] = arrays["force"] * s
            arrays["moment"] = arrays["moment"] * s
        elif convention != "axis":
            raise ValueError(f"HelixData: convention must be 'axis' or 'advance', got {convention!r}")
        dtype = jnp.result_type(float)
        for name in CSV_COLUMNS:
            setattr(self, name, jnp.asarray(arrays[name], dtype) if name in arrays else None)
        self.unit_labels = tuple(sorted((str(k), str(v)) for k, v in (units or {}).items()))

    @property
    def units(self) -> dict[str, str]:
        """Unit strings by column name (as given, or read from a CSV units line)."""
        return dict(self.unit_labels)

    @property
    def force_observed(self) -> Array:
        """Mask `(n,)` of the points whose force was measured."""
        return measured(self.force)

    @property
    def moment_observed(self) -> Array:
        """Mask `(n,)` of the points whose moment was measured."""
        return measured(self.moment)

    @property
    def observed(self) -> tuple[str, ...]:
        """The quantities measured at one point at least: a subset of `("force", "moment")`."""
        masks = {"force": self.force_observed, "moment": self.moment_observed}
        return tuple(name for name, mask in masks.items() if bool(np.any(np.asarray(mask))))

    def __len__(self) -> int:
        return int(self.force.shape[0])

    @property
    def size(self) -> int:
        """Number of data points."""
        return len(self)

    def __repr__(self) -> str:
        columns = ("force", "moment", "kappa", "tau", "register")
        if not is_concrete(*(getattr(self, c) for c in columns)):
            return eqx.tree_pformat(self)
        units = self.units

        def span(name):
            values = np.asarray(getattr(self, name))
            seen = values[~np.isnan(values)]
            if not seen.size:
                return f"{name} not observed"
            unit = f" {units[name]}" if name in units else ""
            part = "" if seen.size == values.size else f" (at {seen.size} points)"
            return f"{name} {seen.min():.4g}..{seen.max():.4g}{unit}{part}"

        present = [c for c in columns if getattr(self, c) is not None]
        sigmas = [c for c in ("force", "moment", "kappa", "tau", "register") if getattr(self, f"{c}_sigma") is not None]
        return f"HelixData({len(self)} points: {', '.join(span(c) for c in present)}; sigmas of {', '.join(sigmas)})"

    # -- CSV ----------------------------------------------------------------------------
    @classmethod
    def from_csv(
        cls,
        path: str | Path,
        *,
        force_sigma: ArrayLike | None = None,
        moment_sigma: ArrayLike | None = None,
        convention: str = "axis",
        strict: bool = False,
    ) -> "HelixData":
        """Read data written by `to_csv` (or by hand).

        Format: lines starting with `#` are comments.  The first other line is the header,
        a comma-separated subset of `force, moment, kappa, tau, force_sigma, moment_sigma,
        kappa_sigma, tau_sigma, kappa_tau_correlation, register, register_sigma` in any order
        (`kappa`, `tau` and one of `force`, `moment` are required; the sigma columns may
        instead be given as arguments, which then override).  An empty (or `nan`) cell of
        `force` or `moment`, or of its sigma, means not measured at that point.  The next line
        may be a units line: same columns, unit strings; it is recognised by its `kappa` and
        `tau` cells, which are not numbers (in a data row they are).  Physical units (force pN, fN,
        nN, N; moment pN nm, N m, ...; curvature and torsion 1/nm, 1/um, 1/m, ...; register
        rad or deg) are converted to pN, pN nm, 1/nm and rad, so the fitted stiffness is in
        pN nm^2; labels that are not physical units (`K1/L^2, K1/L, 1/L, 1/L` for data in
        the rod's own scales) are kept as given, and mixing the two is an error.  Then one
        data row per helix; an empty cell in another column is not
        allowed (drop the column instead).  Columns of other names are ignored with a
        warning (`strict=True`: an error).  Errors name the file line (counted from 1).
        """
        path = Path(path)
        text = path.read_text(encoding="utf-8-sig")  # a byte-order mark (Excel's "CSV UTF-8") is dropped
        lines = [(i + 1, line) for i, line in enumerate(text.splitlines()) if line.strip() and not line.lstrip().startswith("#")]
        if not lines:
            raise ValueError(f"{path}: no header line")
        lines = drop_unknown_columns(path, lines, CSV_COLUMNS, strict=strict)
        header_line, header = lines[0]
        names = [c.strip() for c in next(csv.reader([header]))]
        missing = [c for c in ("kappa", "tau") if c not in names]
        if "force" not in names and "moment" not in names:
            missing.append("force or moment")
        if missing:
            raise ValueError(f"{path}:{header_line}: missing required columns {missing}")
        if len(set(names)) != len(names):
            raise ValueError(f"{path}:{header_line}: repeated column names {names}")
        body = lines[1:]
        units = {}
        if body:
            first = next(csv.reader([body[0][1]]))
            # A units line states kappa's and tau's units; a data row has their numbers (a
            # data row may begin with an empty cell: a force not measured there, and one with
            # a typo elsewhere is a data row with an error, not a units line).
            lookup = dict(zip(names, first))
            if not any(_is_number(lookup.get(n, "0")) for n in ("kappa", "tau")):
                if len(first) != len(names):
                    raise ValueError(f"{path}:{body[0][0]}: units line has {len(first)} cells, header has {len(names)}")
                numbers = [n for n, u in lookup.items() if _is_number(u) and u.strip() not in DIMENSIONLESS_UNITS]
                if numbers:
                    raise ValueError(
                        f"{path}:{body[0][0]}: neither a units line (numbers in {numbers}) nor a data row (kappa and "
                        f"tau are not numbers): {first}"
                    )
                units = {n: u.strip() for n, u in lookup.items()}
                body = body[1:]
        values = np.empty((len(body), len(names)))
        for r, (lineno, line) in enumerate(body):
            cells = next(csv.reader([line]))
            if len(cells) != len(names):
                raise ValueError(f"{path}:{lineno}: {len(cells)} cells, expected {len(names)} ({', '.join(names)})")
            empty = [n for n, c in zip(names, cells) if not c.strip()]
            if any(n not in _MAY_BE_EMPTY for n in empty):
                raise ValueError(
                    f"{path}:{lineno}: empty cells in {[n for n in empty if n not in _MAY_BE_EMPTY]}; only "
                    f"{', '.join(_MAY_BE_EMPTY)} may be empty (not measured at that point)"
                )
            try:
                values[r] = [float(c) if c.strip() else np.nan for c in cells]
            except ValueError:
                raise ValueError(f"{path}:{lineno}: not a number in {cells}") from None
        if units:
            factors, units = _unit_factors(units, f"{path}:{lines[1][0]}")
            values = values * np.array([factors[n] for n in names])
        absent = np.isnan(values) & np.isin(names, _MAY_BE_EMPTY)[None, :]  # 'nan' as written by to_csv
        bad = ~np.all(np.isfinite(values) | absent, axis=1)
        if bad.any():
            file_lines = [body[r][0] for r in np.flatnonzero(bad)]
            raise ValueError(
                f"{path}: non-finite (NaN or infinite) values on lines {file_lines[:20]} "
                f"(data rows {np.flatnonzero(bad)[:20].tolist()}, counted from 0)"
            )
        col = {n: values[:, i] for i, n in enumerate(names)}
        fs = force_sigma if force_sigma is not None else col.get("force_sigma")
        ms = moment_sigma if moment_sigma is not None else col.get("moment_sigma")
        needed = [f"{n}_sigma" for n, given in (("force", fs), ("moment", ms)) if n in col and given is None]
        if needed:
            raise ValueError(f"{path}: {' and '.join(needed)} needed (as columns or arguments)")
        fs, ms = (1.0 if x is None else x for x in (fs, ms))  # of a quantity not measured: never read
        try:
            return cls(
                col.get("force"),
                col.get("moment"),
                col["kappa"],
                col["tau"],
                fs,
                ms,
                kappa_sigma=col.get("kappa_sigma"),
                tau_sigma=col.get("tau_sigma"),
                kappa_tau_correlation=col.get("kappa_tau_correlation"),
                register=col.get("register"),
                register_sigma=col.get("register_sigma"),
                units=units,
                convention=convention,
            )
        except PointError as error:
            # The checks count data rows from 0; the file's lines are what the user sees.
            lines = [body[r][0] for r in error.points[:20]]
            raise ValueError(f"{path}: {error} (file lines {lines}; data rows counted from 0)") from None
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from None

    def to_csv(self, path: str | Path | None = None, *, comment: str | None = None) -> str:
        """Write the data as CSV (header line, units line, one row per helix; values with
        17 significant digits, so a round trip is exact).  Returns the text; writes it to
        `path` when given."""
        unmeasured = [f"{q}{suffix}" for q in ("force", "moment") if q not in self.observed for suffix in ("", "_sigma")]
        names = [n for n in CSV_COLUMNS if getattr(self, n) is not None and n not in unmeasured]
        out = io.StringIO()
        out.write("# helixrod HelixData: F = n.a and M = m.a along the helix axis a = u/|u| (docs/conventions.md)\n")
        if comment:
            for line in comment.splitlines():
                out.write(f"# {line}\n")
        writer = csv.writer(out, lineterminator="\n")
        writer.writerow(names)
        writer.writerow([self.units.get(n, "-") or "-" for n in names])
        cols = np.stack([np.asarray(getattr(self, n)) for n in names], axis=1)
        for row in cols:
            writer.writerow(["" if np.isnan(v) else repr(float(v)) for v in row])  # empty: not measured
        text = out.getvalue()
        if path is not None:
            write_atomically(path, lambda f: f.write(text), binary=False)
        return text


def _noise_scale(x, noise):
    return noise * (np.sqrt(np.mean(np.square(x))) if np.size(x) else 1.0)


def synthetic_helix_data(
    rod: Rod,
    kappa: ArrayLike,
    tau: ArrayLike,
    noise: float | tuple[float, float],
    key: Array,
    *,
    branch: str = "min-energy",
    observe: tuple[str, ...] = ("force", "moment"),
    units: dict | None = None,
) -> HelixData:
    """Simulated measurements of `rod` at the helices `(kappa, tau)` (1-D, broadcast).

    The exact axial force and moment of one register per helix (`branch`: `"min-energy"`,
    slot 0 of `helix_equilibria`, the global energy minimum on the circle; `"random"`, a
    valid register drawn uniformly with `key`) plus Gaussian noise of standard deviation
    `noise` times the root-mean-square of the exact values (a pair `(sigma_F, sigma_M)` sets
    absolute deviations instead).  The data's sigmas are the noise levels used; `noise = 0`
    gives exact data with sigma = the RMS values (unit relative weights), so fits work
    unchanged.  The registers are stored in `register` (with no `register_sigma`, so a fit
    ignores them unless asked).  `observe`: the quantities measured, `("force", "moment")`
    (default), `("force",)` or `("moment",)`; the other one is `None` (partial data).  Not
    jit-able (it returns validated `HelixData`).
    """
    check_quadratic_rod(rod, "synthetic_helix_data")
    check_key(key, "synthetic_helix_data")
    observe = (observe,) if isinstance(observe, str) else tuple(observe)
    if not observe or any(q not in ("force", "moment") for q in observe):
        raise ValueError(f"observe must name 'force' and/or 'moment', got {observe!r}")
    kappa = jnp.asarray(kappa, jnp.result_type(float))
    tau = jnp.asarray(tau, jnp.result_type(float))
    kappa, tau = jnp.broadcast_arrays(jnp.atleast_1d(kappa), jnp.atleast_1d(tau))
    eq = helix_equilibria(rod, kappa, tau)
    key_branch, key_f, key_m = random_split(key, 3)
    if branch == "min-energy":
        slot = jnp.zeros(kappa.shape, int)
    elif branch == "random":
        logits = jnp.where(eq.valid, 0.0, -jnp.inf)
        slot = jax.random.categorical(key_branch, logits, axis=-1)
    else:
        raise ValueError(f"branch must be 'min-energy' or 'random', got {branch!r}")

    def pick(x):
        return np.asarray(jnp.take_along_axis(x, slot[:, None], axis=1)[:, 0])

    F, M, phi = pick(eq.force), pick(eq.moment), pick(eq.phi)
    if not (np.all(np.isfinite(F)) and np.all(np.isfinite(M))):
        raise ValueError("synthetic_helix_data: some helices have no register (kappa must be > 0 and finite)")
    if isinstance(noise, tuple):
        # The deviation of a quantity not observed is not used (any positive value will do).
        sigma_f = float(noise[0]) if "force" in observe else 1.0
        sigma_m = float(noise[1]) if "moment" in observe else 1.0
        zero = all(float(noise[i]) == 0 for i, q in enumerate(("force", "moment")) if q in observe)
    else:
        sigma_f, sigma_m = _noise_scale(F, float(noise)), _noise_scale(M, float(noise))
        zero = float(noise) == 0
    if zero:
        sigma_f, sigma_m = _noise_scale(F, 1.0), _noise_scale(M, 1.0)
        F_obs, M_obs = F, M
    else:
        if sigma_f <= 0 or sigma_m <= 0 or not (math.isfinite(sigma_f) and math.isfinite(sigma_m)):
            raise ValueError(
                f"noise must be >= 0 and finite, and a pair (sigma_F, sigma_M) > 0 for each quantity observed "
                f"(0 for all of them: exact data), got {noise}"
            )
        F_obs = F + sigma_f * np.asarray(random_normal(key_f, F.shape))
        M_obs = M + sigma_m * np.asarray(random_normal(key_m, M.shape))
    return HelixData(
        F_obs if "force" in observe else None, M_obs if "moment" in observe else None, np.asarray(kappa),
        np.asarray(tau), sigma_f, sigma_m, register=phi, units=units,
    )
