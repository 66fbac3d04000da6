"""The command line's files: inputs that must exist and outputs checked before any
computation (their folder exists, a figure's suffix is one matplotlib writes), so that a
long run never ends in an error that loses its result.  Every problem is a usage error
(`typer.BadParameter`: one message, exit code 2, no traceback).  A reader's warnings are
printed as notes (`read_with_notes`)."""

from __future__ import annotations

import functools
import os
import warnings
from pathlib import Path

import typer


@functools.cache
def figure_suffixes() -> tuple[str, ...]:
    """The file suffixes matplotlib can write (".png", ".pdf", ".svg", ...)."""
    from matplotlib.figure import Figure

    return tuple(sorted("." + s for s in Figure().canvas.get_supported_filetypes()))


def input_file(path: Path | None, option: str) -> Path | None:
    """`path` if it is a readable file (`None` passes)."""
    if path is None:
        return None
    if not path.is_file():
        raise typer.BadParameter(f"{option}: no such file: {path}")
    if not os.access(path, os.R_OK):
        raise typer.BadParameter(f"{option}: cannot read {path}")
    return path


def output_file(path: Path | None, option: str, *, figure: bool = False) -> Path | None:
    """`path` if a file can be written there: its folder exists and is writable, it is not a
    folder, and a figure's suffix is one matplotlib writes (`None` passes)."""
    if path is None:
        return None
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise typer.BadParameter(f"{option}: the folder {folder} does not exist (create it first)")
    if not os.access(folder, os.W_OK):
        raise typer.BadParameter(f"{option}: cannot write in {folder}")
    if path.is_dir():
        raise typer.BadParameter(f"{option}: {path} is a folder; give a file name")
    if figure and path.suffix.lower() not in figure_suffixes():
        raise typer.BadParameter(f"{option}: cannot write a figure as {path.suffix or 'a file without a suffix'}; "
                                 f"use one of {', '.join(figure_suffixes())}")
    return path


def output_folder(path: Path, option: str) -> Path:
    """`path` as a folder, created (with its parents) if missing."""
    if path.exists() and not path.is_dir():
        raise typer.BadParameter(f"{option}: {path} exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise typer.BadParameter(f"{option}: cannot create the folder {path} ({error.strerror})") from None
    if not os.access(path, os.W_OK):
        raise typer.BadParameter(f"{option}: cannot write in {path}")
    return path


def read_with_notes(console, read):
    """`read()` (a data file's reader) with its warnings -- columns ignored, say -- printed
    on `console` as notes instead of Python's warning lines."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", UserWarning)
        result = read()
    for warning in caught:
        console.print(f"[yellow]note:[/yellow] {warning.message}", soft_wrap=True)
    return result
