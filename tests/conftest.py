import collections
import logging
import os
import tempfile

import jax
import numpy as np
import pytest

from helixrod import _compile

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

# Compiling for the test clock.  Most of the quick tier is XLA compiling programs that then
# run for milliseconds, so it compiles with little optimisation: LLVM's backend at level 0
# without its expensive passes (JAX's `jax_disable_most_optimizations`), and the tests' own
# programs (their `jax.jit`, `vmap`, `grad`, eager `jvp` around helixrod's functions) with
# helixrod's `COMPILER_OPTIONS`, as helixrod's top-level programs are.  Measured on one
# core: `helix_equilibria` of 4096 points compiles in 1.9 s instead of 8.9 s;
# tests/test_equilibria.py runs in 118 s instead of 293 s.  Same HLO, no fast math:
# results differ in rounding only.  A run that selects heavy or slow tests (CI's second
# tier, `-m ""`) compiles with XLA's defaults, as users do: some of its checks compare two
# programs bit for bit, or follow a branch from a nearly singular point, where rounding
# shows; `HELIXROD_TEST_XLA_DEFAULTS=1` asks for the defaults in any run.
# XLA reads XLA_FLAGS once, at its first compile: set for that compile and restored, it
# stays out of the subprocesses the tests start (the CLI, the cache, the notebooks' kernels).
XLA_DEFAULTS_VARIABLE = "HELIXROD_TEST_XLA_DEFAULTS"


def _selects_long_tests(config) -> bool:
    """Whether the run's marker expression (`-m`) can select a heavy or a slow test."""
    try:
        from _pytest.mark.expression import Expression
    except ImportError:  # pragma: no cover - pytest moved it: compile with the defaults
        return True
    markexpr = config.option.markexpr
    if not markexpr:
        return True
    expression = Expression.compile(markexpr)
    return any(expression.evaluate(lambda name, mark=mark, **_: name == mark) for mark in ("heavy", "slow"))


def pytest_configure(config):
    if os.environ.get(XLA_DEFAULTS_VARIABLE, "0").strip() == "1" or _selects_long_tests(config):
        return
    jax.config.update("jax_disable_most_optimizations", True)
    user_flags = os.environ.get("XLA_FLAGS")
    test_flags = " ".join(f"--{name}={str(value).lower()}" for name, value in _compile.COMPILER_OPTIONS.items())
    os.environ["XLA_FLAGS"] = f"{user_flags or ''} {test_flags}".strip()
    jax.block_until_ready(jax.jit(lambda x: x + 1)(np.zeros(1)))
    if user_flags is None:
        del os.environ["XLA_FLAGS"]
    else:
        os.environ["XLA_FLAGS"] = user_flags


# The CLI tests run commands in this process, and a command would turn on the persistent
# compilation cache (the CLI's default) for the rest of the process.  It stays off
# (HELIXROD_CACHE=0): CI workers aborted inside XLA's (de)serialisation of an executable,
# once reading back one that another checkout's run had cached in ~/.cache/helixrod
# (compilation_cache.get_executable_and_time) and once writing one into a fresh per-process
# directory (put_executable_and_time, from test_fit_design after test_fit_compare's
# `helixrod fit --compare`).  tests/test_cache.py checks the cache in subprocesses; a
# directory of this run's own is kept for anything that still turns it on.
os.environ["HELIXROD_CACHE"] = "0"
os.environ["HELIXROD_CACHE_DIR"] = tempfile.mkdtemp(prefix=f"helixrod-cache-{os.environ.get('PYTEST_XDIST_WORKER', 'main')}-")


def pytest_collection_modifyitems(config, items):
    """Longest units first: the notebooks, then the test files with most tests; the order
    within a file is unchanged.  xdist's work stealing hands each worker a contiguous run of
    this order, so the tests of a file mostly share one worker (and its compiled programs),
    and the long notebooks do not end the run on one worker."""
    for item in items:
        if item.path.suffix == ".ipynb":
            item.add_marker(pytest.mark.heavy)
    files = collections.Counter(item.path for item in items)
    first = {}
    for index, item in enumerate(items):
        first.setdefault(item.path, index)
    items.sort(key=lambda item: (item.path.suffix != ".ipynb", -files[item.path], first[item.path]))


# A worker lost inside native code gets its test run once more on a fresh worker: workers
# died, rarely, with an abort or a segmentation fault inside XLA's compiler
# (backend_compile_and_load) with the persistent cache off -- once in CI, once in a local
# full run, in test_fit_design, which passes alone and in its neighbours' company.  A second
# crash of the same test fails it, as any crash did before.
CRASH_RERUNS = 1
_crashes = collections.Counter()


def pytest_handlecrashitem(crashitem, report, sched):
    _crashes[crashitem] += 1
    if _crashes[crashitem] <= CRASH_RERUNS:
        sched.mark_test_pending(crashitem)
        report.outcome = "rerun"


def pytest_report_teststatus(report, config):
    if report.outcome == "rerun":
        return "rerun", "R", ("RERUN", {"yellow": True})
    return None


def pytest_terminal_summary(terminalreporter):
    if _crashes:
        terminalreporter.write_sep("=", "tests whose worker crashed (run again on a fresh worker)", yellow=True)
        for nodeid, count in _crashes.items():
            terminalreporter.write_line(f"{nodeid}: {count} crash(es)")


@pytest.fixture
def rng():
    return np.random.default_rng(20261122)


@pytest.fixture
def exported_programs(tmp_path):
    """The trace cache on in `tmp_path` for one test (the directory of its exported programs),
    and this process's programs, refusals and counts as they were after it."""
    from helixrod import _trace_cache

    saved = dict(_trace_cache.counts)
    _trace_cache.enable(tmp_path)
    try:
        yield tmp_path / _trace_cache.SUBDIRECTORY
    finally:
        _trace_cache.enable(None)
        _trace_cache._programs.clear()
        _trace_cache._refused.clear()
        _trace_cache.counts.update(saved)


@pytest.fixture
def compilations():
    """The compilations of the test, as (thread name, message) of JAX's compile log (on in
    every thread: `jax.log_compiles` as a context is the calling thread's only)."""
    records = []

    class Keep(logging.Handler):
        def emit(self, record):
            message = record.getMessage()
            if message.startswith("Finished XLA compilation of jit("):
                records.append((record.threadName, message.split("jit(", 1)[1].split(")", 1)[0]))

    handler, logger = Keep(), logging.getLogger("jax")
    logger.addHandler(handler)
    jax.config.update("jax_log_compiles", True)
    try:
        yield records
    finally:
        jax.config.update("jax_log_compiles", False)
        logger.removeHandler(handler)
