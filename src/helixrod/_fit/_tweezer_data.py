"""Single-molecule tweezer measurements of DNA: `TweezerData`, its CSV form, and reading a
lumicks pylake force-distance curve.

Units (as in `helixrod.dna`): forces in pN, lengths in nm, torques in pN nm, rotations in
turns, temperatures in kelvin.  Sign conventions: positive `turns` overwind the molecule
(the imposed linking-number change $\\Delta Lk$, all of it twist while the axis stays
straight; see `helixrod._dna`), and a positive torque is one that overwinds.
"""

from __future__ import annotations

import csv
import io
import math
import re
from collections.abc import Mapping
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._dna import ROOM_TEMPERATURE
from .._misc import column, finite_scalar, float_dtype, is_concrete
from ._csv import PointError, drop_unknown_columns
from ._units import FORCE_UNITS, LENGTH_UNITS, TORQUE_UNITS

#: Column order of the CSV form (`force`, `extension` and one of `turns`/`torque` are required).
CSV_COLUMNS = (
    "force",
    "extension",
    "turns",
    "torque",
    "extension_sigma",
    "force_sigma",
    "turns_sigma",
    "measured_torque",
    "measured_torque_sigma",
    "molecule",
    "n_bp",
)

# Unit strings accepted on the CSV units line, each with its factor to the internal unit.
_TURNS_UNITS = {"turns": 1.0, "rad": 1.0 / (2.0 * math.pi), "deg": 1.0 / 360.0}
_ID_UNITS = {"-": 1.0, "id": 1.0, "": 1.0}
_BP_UNITS = {"bp": 1.0, "-": 1.0, "": 1.0}
_COLUMN_UNITS = {
    "force": FORCE_UNITS,
    "force_sigma": FORCE_UNITS,
    "extension": LENGTH_UNITS,
    "extension_sigma": LENGTH_UNITS,
    "turns": _TURNS_UNITS,
    "turns_sigma": _TURNS_UNITS,
    "torque": TORQUE_UNITS,
    "measured_torque": TORQUE_UNITS,
    "measured_torque_sigma": TORQUE_UNITS,
    "molecule": _ID_UNITS,
    "n_bp": _BP_UNITS,
}
#: The units `to_csv` writes (the internal ones).
CSV_UNITS = {
    "force": "pN",
    "force_sigma": "pN",
    "extension": "nm",
    "extension_sigma": "nm",
    "turns": "turns",
    "turns_sigma": "turns",
    "torque": "pN nm",
    "measured_torque": "pN nm",
    "measured_torque_sigma": "pN nm",
    "molecule": "id",
    "n_bp": "bp",
}
# Columns whose cells may be empty (NaN: the control is absent, or no torque was measured).
_MAY_BE_EMPTY = ("turns", "torque", "measured_torque", "measured_torque_sigma")
_SHOWN = 10  # offending indices listed in an error message
_TEMPERATURE_COMMENT = re.compile(r"#\s*temperature\s*:(.*)", re.IGNORECASE)
_TEMPERATURE_VALUE = re.compile(r"([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(K|C|degC|\u00b0C)")


def _listed(indices) -> str:
    indices = [int(i) for i in indices]
    more = f" ... ({len(indices)} in all)" if len(indices) > _SHOWN else ""
    return f"{indices[:_SHOWN]}{more}"


def _require_points(ok, message: str):
    """`PointError` naming the points where the boolean array `ok` is False."""
    bad = np.flatnonzero(~np.asarray(ok, bool))
    if bad.size:
        raise PointError(f"TweezerData: {message}; points {_listed(bad)} (counted from 0)", bad)


def _per_point(x, name: str, n: int) -> np.ndarray:
    """`x` as a float64 column of length `n` (a scalar broadcasts), NaN allowed, infinities not."""
    a = np.asarray(x, dtype=float)
    if a.ndim == 0:
        a = np.full(n, float(a))
    if a.shape != (n,):
        raise ValueError(f"TweezerData: {name} must be a scalar or one-dimensional of length {n}, got shape {a.shape}")
    _require_points(~np.isinf(a), f"{name} has infinite values (use NaN where there is no value)")
    return a


def _molecule_indices(x, m: int | None, n: int) -> np.ndarray:
    a = np.asarray(x)
    if a.ndim == 0:
        a = np.full(n, a)
    if a.shape != (n,):
        raise ValueError(f"TweezerData: molecule must be a scalar or one-dimensional of length {n}, got shape {a.shape}")
    if a.dtype.kind == "f" and np.all(np.isfinite(a)) and np.all(a == np.round(a)):
        a = a.astype(np.int64)
    if a.dtype.kind not in "iu":
        raise ValueError(f"TweezerData: molecule must hold integer molecule indices, got dtype {a.dtype} (use from_arrays for ids)")
    if m is not None:
        _require_points((a >= 0) & (a < m), f"molecule index out of range 0..{m - 1} (there are {m} molecules)")
    return a


class TweezerData(eqx.Module):
    """Force, extension and rotation of DNA molecules in magnetic or optical tweezers.

    Each point is one equilibrium state of one molecule under one control.  Per point
    (shape `(n,)`, floats in the default JAX dtype):

    - `force` -- the applied stretching force, pN (a control; finite and > 0);
      `force_sigma` its standard deviation, or `None`.
    - `turns` -- imposed rotation (magnetic tweezers), turns, counted from the torque-free
      molecule at that force: the imposed linking-number change $\\Delta Lk$, positive =
      overwinding.  NaN at torque-controlled points.  `turns_sigma` or `None`.
    - `torque` -- controlled torque, pN nm, positive = overwinding; 0 is a free swivel (the
      optical-tweezer force-extension case).  NaN at turns-controlled points.
    - `extension` -- measured end-to-end extension along the force, nm (finite), with
      standard deviation `extension_sigma` (> 0).
    - `measured_torque` -- torque measured in the molecule, pN nm, same sign convention
      (positive for an overwound molecule), NaN where not recorded; `None` when no point has
      one.  `measured_torque_sigma` (> 0 where `measured_torque` is finite; NaN or > 0
      elsewhere) is `None` exactly when `measured_torque` is.
    - `molecule` -- int32 index `0..m-1` of the molecule measured.

    Per molecule (shape `(m,)`): `n_bp`, its length in base pairs (> 0; a float).
    `molecule_names` (static, a tuple of `m` strings) names them; `temperature` is a scalar
    array, kelvin (> 0).  Each point has exactly one control: exactly one of `turns`,
    `torque` is finite (`torque_controlled` says which).

    Construct with `TweezerData.from_arrays` (molecule ids, broadcasting),
    `TweezerData.from_csv` or `TweezerData.from_pylake`; the constructor itself takes the
    stored form (`molecule` as indices, `n_bp` per molecule, `molecule_names`).  Scalars
    broadcast to every point.  Bad concrete input raises `ValueError` naming the field, the
    problem and the first offending point indices (counted from 0); traced input is stored
    unchecked.

    **CSV form** (`from_csv`, `to_csv`): `#` lines are comments, except that
    `# temperature: 293.15 K` (or `20 C`, `20 degC`) gives the temperature.  The first other
    line is the header, a subset of `force, extension, turns, torque, extension_sigma,
    force_sigma, turns_sigma, measured_torque, measured_torque_sigma, molecule, n_bp` in any
    order; the next line gives the unit of each column (required; converted on reading);
    then one point per line.  An empty `turns` or `torque` cell means that control is absent
    at the point; an empty `measured_torque` cell means no torque was measured::

        # temperature: 20 C
        force,extension,turns,torque,extension_sigma,molecule,n_bp
        pN,um,turns,pN nm,nm,id,bp
        1.0,1.52,0,,5,a,6000
        1.0,1.44,15,,5,a,6000
        3.0,3.10,,0,5,b,10000
    """

    force: Float[Array, " n"]
    force_sigma: Float[Array, " n"] | None
    turns: Float[Array, " n"]
    turns_sigma: Float[Array, " n"] | None
    torque: Float[Array, " n"]
    extension: Float[Array, " n"]
    extension_sigma: Float[Array, " n"]
    measured_torque: Float[Array, " n"] | None
    measured_torque_sigma: Float[Array, " n"] | None
    molecule: Int[Array, " n"]
    n_bp: Float[Array, " m"]
    temperature: Float[Array, ""]
    molecule_names: tuple[str, ...] = eqx.field(static=True)

    def __init__(
        self,
        force: ArrayLike,
        extension: ArrayLike,
        *,
        extension_sigma: ArrayLike,
        turns: ArrayLike | None = None,
        torque: ArrayLike | None = None,
        force_sigma: ArrayLike | None = None,
        turns_sigma: ArrayLike | None = None,
        measured_torque: ArrayLike | None = None,
        measured_torque_sigma: ArrayLike | None = None,
        molecule: ArrayLike = 0,
        n_bp: ArrayLike,
        molecule_names: tuple[str, ...] | None = None,
        temperature: ArrayLike = ROOM_TEMPERATURE,
    ):
        """The stored form: `molecule` holds indices into `n_bp` (one value per molecule; a
        scalar with `molecule_names` of length `m`, or for molecules `0..max(molecule)`),
        `molecule_names` defaults to `("0", "1", ...)`.  `turns=None` (`torque=None`) means
        no point is turns- (torque-) controlled.  Prefer `from_arrays`."""
        owner = "TweezerData"
        fdt = float_dtype()
        n_ext = np.ndim(extension)
        if n_ext != 1:
            raise ValueError(f"{owner}: extension must be one-dimensional (one value per point), got shape {np.shape(extension)}")
        n = int(np.shape(extension)[0])
        if n == 0:
            raise ValueError(f"{owner}: no data points")
        if measured_torque_sigma is not None and measured_torque is None:
            raise ValueError(f"{owner}: measured_torque_sigma given without measured_torque")
        per_point = {
            "force": force,
            "extension": extension,
            "extension_sigma": extension_sigma,
            "force_sigma": force_sigma,
            "turns_sigma": turns_sigma,
            "turns": turns,
            "torque": torque,
            "measured_torque": measured_torque,
            "measured_torque_sigma": measured_torque_sigma,
        }
        if not is_concrete(per_point, molecule, n_bp, temperature):
            self._store_traced(per_point, molecule, n_bp, molecule_names, temperature, n)
            return
        arrays = {}
        for name in ("force", "extension", "extension_sigma", "force_sigma", "turns_sigma"):
            if per_point[name] is not None:
                arrays[name] = column(per_point[name], name, owner, n)
        for name in ("turns", "torque"):
            x = per_point[name]
            arrays[name] = _per_point(np.nan if x is None else x, name, n)
        for name in ("measured_torque", "measured_torque_sigma"):
            x = per_point[name]
            arrays[name] = None if x is None else _per_point(x, name, n)
        _require_points(arrays["force"] > 0, "force must be > 0 (the pulling force, pN)")
        for name in ("extension_sigma", "force_sigma", "turns_sigma"):
            if name in arrays:
                _require_points(arrays[name] > 0, f"{name} must be > 0")
        has_turns, has_torque = ~np.isnan(arrays["turns"]), ~np.isnan(arrays["torque"])
        _require_points(~(has_turns & has_torque), "both turns and torque are given (each point has exactly one control)")
        _require_points(has_turns | has_torque, "neither turns nor torque is given (each point has exactly one control)")
        mt, mts = arrays["measured_torque"], arrays["measured_torque_sigma"]
        if mt is not None:
            measured = ~np.isnan(mt)
            if mts is None:
                _require_points(~measured, "measured_torque is given but measured_torque_sigma is missing")
            else:
                _require_points(~(measured & np.isnan(mts)), "measured_torque_sigma is missing (NaN) where measured_torque is given")
                _require_points(np.isnan(mts) | (mts > 0), "measured_torque_sigma must be > 0")
            if not measured.any():
                arrays["measured_torque"] = arrays["measured_torque_sigma"] = None
        nb = np.asarray(n_bp, dtype=float)
        if nb.ndim == 0:
            if molecule_names is not None:
                m = len(molecule_names)
            else:
                m = int(np.max(_molecule_indices(molecule, None, n))) + 1
            m = max(m, 1)
            nb = np.full(m, float(nb))
        nb = column(nb, "n_bp", owner)
        m = nb.shape[0]
        if m == 0:
            raise ValueError(f"{owner}: n_bp is empty (no molecules)")
        mol = _molecule_indices(molecule, m, n)
        bad = np.flatnonzero(~(nb > 0))
        if bad.size:
            raise ValueError(f"{owner}: n_bp must be > 0 (base pairs); molecules {_listed(bad)} are not")
        names = tuple(str(i) for i in range(m)) if molecule_names is None else tuple(molecule_names)
        if len(names) != m or not all(isinstance(s, str) for s in names):
            raise ValueError(f"{owner}: molecule_names must be {m} strings (one per n_bp entry), got {molecule_names!r}")
        if len(set(names)) != m:
            raise ValueError(f"{owner}: molecule_names must be distinct, got {names!r}")
        self.temperature = finite_scalar(temperature, "temperature (kelvin)", owner, positive=True)
        for name in per_point:
            a = arrays.get(name)
            setattr(self, name, None if a is None else jnp.asarray(a, fdt))
        self.molecule = jnp.asarray(mol, jnp.int32)
        self.n_bp = jnp.asarray(nb, fdt)
        self.molecule_names = names

    def _store_traced(self, per_point, molecule, n_bp, molecule_names, temperature, n):
        """Unchecked storage for traced inputs (inside `jit`/`vmap`)."""
        fdt = float_dtype()
        for name, x in per_point.items():
            if x is None and name in ("turns", "torque"):
                x = jnp.nan
            setattr(self, name, None if x is None else jnp.broadcast_to(jnp.asarray(x, fdt), (n,)))
        self.molecule = jnp.broadcast_to(jnp.asarray(molecule, jnp.int32), (n,))
        nb = jnp.atleast_1d(jnp.asarray(n_bp, fdt))
        if molecule_names is not None:
            nb = jnp.broadcast_to(nb, (len(molecule_names),))
        self.n_bp = nb
        self.molecule_names = tuple(molecule_names) if molecule_names is not None else tuple(str(i) for i in range(nb.shape[0]))
        self.temperature = jnp.asarray(temperature, fdt)

    # -- derived -----------------------------------------------------------------------
    @property
    def n_points(self) -> int:
        """Number of data points $n$."""
        return int(self.force.shape[0])

    def __len__(self) -> int:
        return self.n_points

    @property
    def n_molecules(self) -> int:
        """Number of molecules $m$."""
        return len(self.molecule_names)

    @property
    def torque_controlled(self) -> Bool[Array, " n"]:
        """True at the points whose control is a torque (`torque` finite), False at those
        whose control is the number of turns."""
        return jnp.isfinite(self.torque)

    @property
    def has_measured_torque(self) -> Bool[Array, " n"]:
        """True where a torque was measured (all False when `measured_torque` is `None`)."""
        if self.measured_torque is None:
            return jnp.zeros(self.force.shape, bool)
        return jnp.isfinite(self.measured_torque)

    # -- construction ------------------------------------------------------------------
    @classmethod
    def from_arrays(
        cls,
        force: ArrayLike,
        extension: ArrayLike,
        *,
        extension_sigma: ArrayLike,
        turns: ArrayLike | None = None,
        torque: ArrayLike | None = None,
        force_sigma: ArrayLike | None = None,
        turns_sigma: ArrayLike | None = None,
        measured_torque: ArrayLike | None = None,
        measured_torque_sigma: ArrayLike | None = None,
        molecule=None,
        n_bp,
        temperature: ArrayLike = ROOM_TEMPERATURE,
    ) -> TweezerData:
        """Data from per-point arrays (units pN, nm, turns, pN nm, kelvin; see the class).

        `extension` fixes the number of points $n$ (one-dimensional); every other per-point
        argument is a scalar (broadcast) or has length $n$.  `turns=None` means no point is
        turns-controlled (all NaN), `torque=None` none torque-controlled; e.g. an
        optical-tweezer force-extension curve is `torque=0.0`.  `molecule`: one id (for all
        points) or a sequence of ids per point (ints or strings; default: one molecule
        named `"0"`), numbered in order of first appearance; `molecule_names` holds
        `str(id)`.  `n_bp`: a scalar (every molecule), a sequence (one per molecule, in order
        of first appearance), or a mapping id -> n_bp (keys the ids or their `str`; every
        molecule must be present, other keys are ignored).
        """
        owner = "TweezerData.from_arrays"
        if np.ndim(extension) != 1:
            raise ValueError(f"{owner}: extension must be one-dimensional (one value per point), got shape {np.shape(extension)}")
        n = int(np.shape(extension)[0])
        if molecule is None:
            ids = ["0"] * n
        elif isinstance(molecule, (str, bytes, int, np.generic)) or np.ndim(molecule) == 0:
            ids = [_plain(molecule)] * n
        else:
            ids = [_plain(i) for i in molecule]
            if len(ids) != n:
                raise ValueError(f"{owner}: molecule must be one id or one id per point ({n}), got {len(ids)} ids")
        first: dict = {}
        index = np.array([first.setdefault(i, len(first)) for i in ids], dtype=np.int32)
        names = tuple(str(i) for i in first)
        if len(set(names)) != len(names):
            raise ValueError(f"{owner}: distinct molecule ids with the same name {names!r}")
        m = len(first)
        if isinstance(n_bp, Mapping):
            values, missing = [], []
            for i in first:
                if i in n_bp:
                    values.append(n_bp[i])
                elif str(i) in n_bp:
                    values.append(n_bp[str(i)])
                else:
                    missing.append(i)
            if missing:
                raise ValueError(
                    f"{owner}: n_bp has no entry for molecules {missing!r} (a mapping must give every molecule; "
                    f"molecules: {list(first)!r})"
                )
            nb = np.asarray(values, dtype=float)
        elif np.ndim(n_bp) == 0:
            nb = np.full(m, float(np.asarray(n_bp, dtype=float)))
        else:
            nb = np.asarray(n_bp, dtype=float)
            if nb.shape != (m,):
                raise ValueError(
                    f"{owner}: n_bp must be a scalar, a mapping id -> n_bp, or one value per molecule "
                    f"({m}: {list(names)}, in order of first appearance), got shape {nb.shape}"
                )
        return cls(
            force,
            extension,
            extension_sigma=extension_sigma,
            turns=turns,
            torque=torque,
            force_sigma=force_sigma,
            turns_sigma=turns_sigma,
            measured_torque=measured_torque,
            measured_torque_sigma=measured_torque_sigma,
            molecule=index,
            n_bp=nb,
            molecule_names=names,
            temperature=temperature,
        )

    @classmethod
    def from_pylake(
        cls,
        fdcurve,
        *,
        n_bp,
        extension_sigma: ArrayLike,
        force_sigma: ArrayLike | None = None,
        molecule=None,
        temperature: ArrayLike = ROOM_TEMPERATURE,
        drop_invalid: bool = False,
    ) -> TweezerData:
        """Torque-free points (torque 0: a free swivel) from a lumicks pylake `FdCurve`.

        Reads the curve's primary force and distance channels (`fdcurve.f`, `fdcurve.d`;
        by pylake's default the total force on trap 2 and distance 1).  Units come from the
        channel labels when they end in a unit in parentheses (pylake labels them
        `"Force (pN)"` and `"Distance (μm)"`), else pN and µm are assumed; distances are
        converted to nm.  `molecule` is one id for the whole curve (default: the curve's
        name, or `"0"` when it has none); `n_bp` as in `from_arrays`; `extension_sigma`
        (nm) and `force_sigma` (pN) are scalars or one value per point of the curve.

        Points with a non-finite force or distance, force <= 0, or distance <= 0 (pylake
        marks failed bead tracking by a zero distance, see `FdCurve.with_offset`) raise
        `ValueError`, unless `drop_invalid=True` drops them.  Needs lumicks-pylake
        (`pip install "helixrod[tweezers]"`).
        """
        owner = "TweezerData.from_pylake"
        try:
            from lumicks.pylake.fdcurve import FdCurve
        except ImportError as e:
            raise ImportError(f'{owner} needs lumicks.pylake: pip install "helixrod[tweezers]"') from e
        if not isinstance(fdcurve, FdCurve):
            raise TypeError(f"{owner}: expected a lumicks.pylake FdCurve, got {type(fdcurve).__name__}")
        force_channel, distance_channel = fdcurve.f, fdcurve.d
        f = np.asarray(force_channel.data, dtype=float) * _label_factor(force_channel, FORCE_UNITS, "pN", "force", owner)
        d = np.asarray(distance_channel.data, dtype=float) * _label_factor(
            distance_channel, LENGTH_UNITS, "\u00b5m", "distance", owner
        )
        if f.ndim != 1 or f.shape != d.shape:
            raise ValueError(f"{owner}: force and distance channels differ in shape: {f.shape} and {d.shape}")
        if f.size == 0:
            raise ValueError(f"{owner}: the curve has no data points")
        problems = {
            "non-finite force": ~np.isfinite(f),
            "non-finite distance": ~np.isfinite(d),
            "force <= 0": np.isfinite(f) & ~(f > 0),
            "distance <= 0 (failed tracking)": np.isfinite(d) & ~(d > 0),
        }
        bad = np.logical_or.reduce(list(problems.values()))
        n = f.size
        if molecule is None:
            name = getattr(fdcurve, "name", "")
            molecule = name if isinstance(name, str) and name else "0"
        if bad.any():
            if not drop_invalid:
                found = "; ".join(f"{k} at points {_listed(np.flatnonzero(v))}" for k, v in problems.items() if v.any())
                raise ValueError(f"{owner}: {found} (counted from 0; pass drop_invalid=True to drop them)")
            keep = ~bad
            if not keep.any():
                raise ValueError(f"{owner}: no valid points left after drop_invalid")

            def kept(x):
                return x if x is None or np.ndim(x) == 0 or np.shape(x) != (n,) else np.asarray(x)[keep]

            f, d = f[keep], d[keep]
            extension_sigma, force_sigma = kept(extension_sigma), kept(force_sigma)
        return cls.from_arrays(
            f,
            d,
            extension_sigma=extension_sigma,
            torque=0.0,
            force_sigma=force_sigma,
            molecule=molecule,
            n_bp=n_bp,
            temperature=temperature,
        )

    # -- CSV ----------------------------------------------------------------------------
    @classmethod
    def from_csv(
        cls,
        path: str | Path,
        *,
        n_bp=None,
        temperature: ArrayLike | None = None,
        extension_sigma: ArrayLike | None = None,
        strict: bool = False,
    ) -> TweezerData:
        """Read the CSV form (see the class docstring; `to_csv` writes it).

        Header: a subset of `CSV_COLUMNS` in any order; `force`, `extension` and at least one
        of `turns`, `torque` are required, `extension_sigma` unless given as an argument,
        `n_bp` (constant within each molecule) unless given as an argument (as in
        `from_arrays`, a mapping keyed by the molecule ids as written).  Arguments override
        columns.  Units line (required, one cell per column; surrounding whitespace ignored,
        case significant): force and `force_sigma` in `pN, fN, nN, N`; `extension`,
        `extension_sigma` in `nm, um, µm, mm, m`; `turns`, `turns_sigma` in `turns, rad,
        deg`; `torque`, `measured_torque`, `measured_torque_sigma` in `pN nm, pN*nm, pN·nm,
        pNnm, pN um, N m, N*m, Nm`; `molecule` `-`, `id` or empty; `n_bp` `bp`, `-` or
        empty.  Cells: empty in `turns`, `torque`, `measured_torque`,
        `measured_torque_sigma` means no value; other numeric cells must be finite numbers;
        `molecule` cells are ids (strings; default: one molecule `"0"`).  The temperature is
        the argument, else a `# temperature: ... K` (or `C`, `degC`) comment, else 298.15 K.
        Columns of other names are ignored with a warning (`strict=True`: an error).  Errors
        name the file and line (counted from 1).
        """
        path = Path(path)
        rows = []
        comment_temperature = None
        for lineno, line in enumerate(path.read_text(encoding="utf-8-sig").splitlines(), start=1):
            stripped = line.strip()
            if not stripped:
                continue
            if stripped.startswith("#"):
                t = _temperature_comment(stripped, path, lineno)
                if t is not None:
                    if comment_temperature is not None and t[0] != comment_temperature[0]:
                        raise ValueError(
                            f"{path}:{lineno}: temperature comment ({t[0]} K) contradicts line "
                            f"{comment_temperature[1]} ({comment_temperature[0]} K)"
                        )
                    comment_temperature = t
                continue
            rows.append((lineno, line))
        if not rows:
            raise ValueError(f"{path}: no header line")
        rows = drop_unknown_columns(path, rows, CSV_COLUMNS, strict=strict)
        header_line = rows[0][0]
        names = [c.strip() for c in next(csv.reader([rows[0][1]]))]
        if len(set(names)) != len(names):
            raise ValueError(f"{path}:{header_line}: repeated column names {names}")
        missing = [c for c in ("force", "extension") if c not in names]
        if missing:
            raise ValueError(f"{path}:{header_line}: missing required columns {missing}")
        if "turns" not in names and "torque" not in names:
            raise ValueError(f"{path}:{header_line}: needs a turns or a torque column (the control of each point)")
        if "extension_sigma" not in names and extension_sigma is None:
            raise ValueError(f"{path}:{header_line}: no extension_sigma column and no extension_sigma argument")
        if "n_bp" not in names and n_bp is None:
            raise ValueError(f"{path}:{header_line}: no n_bp column and no n_bp argument")
        if len(rows) < 2:
            raise ValueError(f"{path}:{header_line}: missing units line after the header (e.g. {_example_units(names)!r})")
        units_line, units_text = rows[1]
        units = next(csv.reader([units_text]))
        if len(units) != len(names):
            raise ValueError(f"{path}:{units_line}: units line has {len(units)} cells, header has {len(names)}")
        if _is_number(units[names.index("force")]):
            raise ValueError(
                f"{path}:{units_line}: missing units line: expected the unit of each column after the header "
                f"(e.g. {_example_units(names)!r}), got a data row"
            )
        factors = {}
        for name, cell in zip(names, units):
            unit, table = cell.strip(), _COLUMN_UNITS[name]
            if unit not in table:
                raise ValueError(f"{path}:{units_line}: unknown unit {unit!r} for column {name}; allowed: {list(table)}")
            factors[name] = table[unit]
        body = rows[2:]
        if not body:
            raise ValueError(f"{path}: no data rows")
        values = {name: np.empty(len(body)) for name in names if name != "molecule"}
        ids = []
        for r, (lineno, line) in enumerate(body):
            cells = next(csv.reader([line]))
            if len(cells) != len(names):
                raise ValueError(f"{path}:{lineno}: {len(cells)} cells, expected {len(names)} ({', '.join(names)})")
            for name, cell in zip(names, cells):
                cell = cell.strip()
                if name == "molecule":
                    if not cell:
                        raise ValueError(f"{path}:{lineno}: empty molecule id")
                    ids.append(cell)
                    continue
                if not cell:
                    if name not in _MAY_BE_EMPTY:
                        raise ValueError(f"{path}:{lineno}: empty cell in column {name} (a number is required)")
                    values[name][r] = np.nan
                    continue
                try:
                    v = float(cell)
                except ValueError:
                    raise ValueError(f"{path}:{lineno}: not a number in column {name}: {cell!r}") from None
                if math.isinf(v) or (math.isnan(v) and name not in _MAY_BE_EMPTY):
                    raise ValueError(f"{path}:{lineno}: non-finite value {cell!r} in column {name}")
                values[name][r] = v * factors[name]
        lines = [lineno for lineno, _ in body]
        molecule = ids if "molecule" in names else None
        if n_bp is None:
            bad = np.flatnonzero(~(values["n_bp"] > 0))
            if bad.size:
                raise ValueError(f"{path}: lines {_listed([lines[r] for r in bad])}: n_bp must be > 0 (base pairs)")
            n_bp = {}
            where: dict = {}
            for r, key in enumerate(ids if molecule is not None else ["0"] * len(body)):
                where.setdefault(key, []).append(r)
            for key, rs in where.items():
                v = values["n_bp"][rs]
                if np.any(v != v[0]):
                    distinct = sorted({float(x) for x in v})
                    raise ValueError(
                        f"{path}: n_bp differs within molecule {key!r}: values {distinct} on lines {[lines[i] for i in rs][:_SHOWN]}"
                    )
                n_bp[key] = float(v[0])
        if temperature is None and comment_temperature is not None:
            temperature, lineno = comment_temperature
            if not temperature > 0:
                raise ValueError(f"{path}:{lineno}: temperature {temperature} K is not > 0")
        elif temperature is None:
            temperature = ROOM_TEMPERATURE
        try:
            return cls.from_arrays(
                values["force"],
                values["extension"],
                extension_sigma=values["extension_sigma"] if extension_sigma is None else extension_sigma,
                turns=values.get("turns"),
                torque=values.get("torque"),
                force_sigma=values.get("force_sigma"),
                turns_sigma=values.get("turns_sigma"),
                measured_torque=values.get("measured_torque"),
                measured_torque_sigma=values.get("measured_torque_sigma"),
                molecule=molecule,
                n_bp=n_bp,
                temperature=temperature,
            )
        except PointError as e:
            raise ValueError(f"{path}: lines {_listed([lines[p] for p in e.points])}: {e}") from None
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None

    def to_csv(self, path: str | Path | None = None, *, comment: str | None = None) -> str:
        """Write the CSV form in the internal units (header, units line `pN,nm,turns,pN
        nm,...`, a `# temperature: ... K` comment; NaN as empty cells; values with 17
        significant digits), which `from_csv` reads back exactly.  A `turns` or `torque`
        column with no value is left out.  Returns the text; writes it to `path` when given.
        Molecules are numbered on reading in order of first appearance, so the indices come
        back unchanged when they first appear in order `0, 1, ...` (as from every `from_*`)."""
        for name in self.molecule_names:
            if not name or name != name.strip() or "\n" in name or "\r" in name or name.startswith("#"):
                raise ValueError(f"TweezerData.to_csv: molecule name {name!r} would not survive the CSV form")
        columns = {
            "force": self.force,
            "extension": self.extension,
            "turns": self.turns if bool(jnp.any(jnp.isfinite(self.turns))) else None,
            "torque": self.torque if bool(jnp.any(jnp.isfinite(self.torque))) else None,
            "extension_sigma": self.extension_sigma,
            "force_sigma": self.force_sigma,
            "turns_sigma": self.turns_sigma,
            "measured_torque": self.measured_torque,
            "measured_torque_sigma": self.measured_torque_sigma,
        }
        columns = {k: np.asarray(v, dtype=float) for k, v in columns.items() if v is not None}
        names = [*columns, "molecule", "n_bp"]
        molecule, n_bp = np.asarray(self.molecule), np.asarray(self.n_bp, dtype=float)
        out = io.StringIO()
        out.write("# helixrod TweezerData: force pN, extension nm, turns (positive = overwinding), torque pN nm\n")
        out.write("# an empty turns or torque cell: that control is absent at the point\n")
        if comment:
            for line in comment.splitlines():
                out.write(f"# {line}\n")
        out.write(f"# temperature: {float(self.temperature)!r} K\n")
        writer = csv.writer(out, lineterminator="\n")
        writer.writerow(names)
        writer.writerow([CSV_UNITS[n] for n in names])
        for i in range(self.n_points):
            cells = ["" if math.isnan(v) else repr(v) for v in (float(c[i]) for c in columns.values())]
            writer.writerow([*cells, self.molecule_names[molecule[i]], repr(float(n_bp[molecule[i]]))])
        text = out.getvalue()
        if path is not None:
            Path(path).write_text(text, encoding="utf-8")
        return text


def _plain(x):
    """A molecule id as a plain Python value (NumPy scalars unwrapped, so they hash and
    print like Python ones)."""
    if isinstance(x, np.ndarray) and x.ndim == 0:
        x = x[()]
    return x.item() if isinstance(x, np.generic) else x


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _example_units(names) -> str:
    return ",".join(CSV_UNITS[n] for n in names)


def _temperature_comment(line: str, path: Path, lineno: int):
    """`(kelvin, lineno)` from a `# temperature: 293.15 K` / `20 C` / `20 degC` comment, None
    for any other comment."""
    match = _TEMPERATURE_COMMENT.fullmatch(line)
    if match is None:
        return None
    value = _TEMPERATURE_VALUE.fullmatch(match.group(1).strip())
    if value is None:
        raise ValueError(
            f"{path}:{lineno}: cannot read the temperature comment {line!r}; write e.g. "
            "'# temperature: 293.15 K' or '# temperature: 20 C'"
        )
    t = float(value.group(1))
    return (t if value.group(2) == "K" else t + 273.15), lineno


def _label_factor(channel, table: dict, default: str, what: str, owner: str) -> float:
    """Factor to the internal unit from a pylake channel label such as `"Distance (μm)"`
    (the `default` unit when the label names none)."""
    labels = getattr(channel, "labels", None) or {}
    label = str(labels.get("y", ""))
    match = re.search(r"\(([^()]*)\)\s*$", label)
    if match is None:
        return table[default]
    unit = match.group(1).strip()
    if unit not in table:
        raise ValueError(f"{owner}: the {what} channel is labelled {label!r}; unit {unit!r} is not one of {list(table)}")
    return table[unit]
