import collections
import os
import tempfile

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

# The CLI tests run commands in this process, and a command turns on the persistent
# compilation cache (the CLI's default) for the rest of the process.  Keep that cache per
# test process and run, not the user's ~/.cache/helixrod: a CI worker aborted (a fatal
# error inside jax's compilation_cache.get_executable_and_time) reading back an executable
# that another checkout's test run had cached there; with a fresh directory nothing foreign
# is read.
os.environ["HELIXROD_CACHE_DIR"] = tempfile.mkdtemp(prefix=f"helixrod-cache-{os.environ.get('PYTEST_XDIST_WORKER', 'main')}-")


def pytest_configure(config):
    # With `--dist loadfile` (pyproject's addopts) a file is one unit of work; xdist's default
    # order (most tests first) puts the notebooks -- one test each, but the longest units --
    # last, so the run ends with one worker on a long notebook.  Keep the order set below.
    if getattr(config.option, "dist", "no") in ("loadfile", "loadscope"):
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(config, items):
    """Longest units first: the notebooks, then the test files with most tests (xdist's own
    default order); the order within a file is unchanged."""
    files = collections.Counter(item.path for item in items)
    first = {}
    for index, item in enumerate(items):
        first.setdefault(item.path, index)
    items.sort(key=lambda item: (item.path.suffix != ".ipynb", -files[item.path], first[item.path]))


@pytest.fixture
def rng():
    return np.random.default_rng(20261122)
