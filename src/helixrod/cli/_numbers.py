"""The one parser of number specs on the command line.

Three kinds of spec: named values ``NAME=VALUE[,NAME=VALUE...]`` (`assignments`: ``--fix
K13=0,K23=0``), comma-separated numbers, a required count of them (`numbers`: ``--rod
1,1.5,0.8[,0.5,0.5]`` takes 3 or 5, ``--uhat u1,u2,u3`` takes 3), and a grid axis
``start:stop:num`` (`grid`: ``--kappa 0:3:1000``, ``--forces 0:0.05:21``), ``num`` points
from ``start`` to ``stop`` inclusive; and the rod of ``--rod`` and ``--uhat`` (`rod_option`).
A bad spec raises `typer.BadParameter` naming the option (exit code 2, the message in
typer's error box).
"""

from __future__ import annotations

import numpy as np
import typer


def numbers(text: str, name: str, count: int | tuple[int, ...]) -> list[float]:
    """The comma-separated numbers of `text` (given to option `name`, e.g. ``"--rod"``);
    `count`: how many are required (one count, or a tuple of the allowed counts)."""
    sizes = (count,) if isinstance(count, int) else tuple(count)
    try:
        values = [float(x) for x in text.split(",")]
    except ValueError:
        raise typer.BadParameter(f"{name} must be comma-separated numbers, got {text!r}") from None
    if len(values) not in sizes:
        raise typer.BadParameter(f"{name} takes {' or '.join(map(str, sizes))} numbers, got {len(values)}")
    return values


def rod_option(rod_text: str, uhat_text: str):
    """The `Rod` of ``--rod K1,K2,K3[,K13,K23]`` and ``--uhat u1,u2,u3``; a stiffness that is not
    positive definite is a usage error naming ``--rod``."""
    from .. import Rod

    stiffness = numbers(rod_text, "--rod", (3, 5))
    uhat = numbers(uhat_text, "--uhat", 3)
    try:
        return Rod(*stiffness, uhat=uhat)
    except ValueError as error:
        raise typer.BadParameter(f"--rod {rod_text} --uhat {uhat_text}: {error}") from None


def grid(text: str, name: str) -> np.ndarray:
    """The grid axis ``start:stop:num`` of `text` (given to option `name`):
    ``np.linspace(start, stop, num)``, `num` >= 1."""
    parts = text.split(":")
    try:
        start, stop, num = float(parts[0]), float(parts[1]), int(parts[2])
    except (ValueError, IndexError):
        raise typer.BadParameter(f"{name} must be start:stop:num, e.g. 0:3:1000, got {text!r}") from None
    if len(parts) != 3 or num < 1:
        raise typer.BadParameter(f"{name} must be start:stop:num with num >= 1, got {text!r}")
    if not (np.isfinite(start) and np.isfinite(stop)):
        raise typer.BadParameter(f"{name}: start and stop must be finite, got {text!r}")
    return np.linspace(start, stop, num)


def assignments(entries, name: str) -> dict[str, float]:
    """The ``NAME=VALUE`` entries of `entries` (strings, each possibly comma-separated; given
    to option `name`, e.g. ``"--fix"``) as a mapping; `typer.BadParameter` naming the bad
    entry (not NAME=VALUE, a value that is not a finite number, a name given twice)."""
    values: dict[str, float] = {}
    for text in entries:
        for entry in text.split(","):
            key, sep, value = (part.strip() for part in entry.partition("="))
            if not sep or not key:
                raise typer.BadParameter(f"{name} entry {entry.strip()!r} is not NAME=VALUE (e.g. {name} K13=0)")
            try:
                number = float(value)
            except ValueError:
                raise typer.BadParameter(f"{name} entry {entry.strip()!r}: {value!r} is not a number") from None
            if not np.isfinite(number):
                raise typer.BadParameter(f"{name} entry {entry.strip()!r}: the value must be finite")
            if key in values:
                raise typer.BadParameter(f"{name} names {key} twice")
            values[key] = number
    return values
