"""``python -m helixrod.cli``: the ``helixrod`` command line."""

from . import app

app()
