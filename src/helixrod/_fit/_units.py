"""Physical units on the CSV units lines of the data files: each accepted unit string with
its factor to helixrod's tweezer units (pN, nm, pN nm, rad), shared by `HelixData` and
`TweezerData`."""

from __future__ import annotations

import math

FORCE_UNITS = {"pN": 1.0, "fN": 1e-3, "nN": 1e3, "N": 1e12}
LENGTH_UNITS = {"nm": 1.0, "um": 1e3, "\u00b5m": 1e3, "\u03bcm": 1e3, "mm": 1e6, "m": 1e9}
TORQUE_UNITS = {
    "pN nm": 1.0,
    "pN*nm": 1.0,
    "pN\u00b7nm": 1.0,
    "pNnm": 1.0,
    "pN um": 1e3,
    "N m": 1e21,
    "N*m": 1e21,
    "Nm": 1e21,
}
INVERSE_LENGTH_UNITS = {
    spelling.format(unit): 1.0 / factor
    for unit, factor in LENGTH_UNITS.items()
    for spelling in ("1/{}", "{}^-1", "{}-1")
}
ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180.0}
DIMENSIONLESS_UNITS = {"": 1.0, "-": 1.0, "1": 1.0}
