"""The rich console the commands print on."""

from __future__ import annotations

import os

from rich.console import Console

#: Columns of the output when it is not a terminal (a log file, a pipe) and `COLUMNS` does
#: not say: rich's 80 cut the wider tables' numbers with an ellipsis.
LOG_WIDTH = 200


def command_console() -> Console:
    """A console as wide as the terminal; elsewhere (`COLUMNS` unset) `LOG_WIDTH` wide, so
    that a redirected table keeps whole numbers."""
    console = Console()
    if not console.is_terminal and "COLUMNS" not in os.environ:
        return Console(width=LOG_WIDTH)
    return console
