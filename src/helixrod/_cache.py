"""The persistent compilation cache: XLA programs compiled once are kept on disk and loaded
by later processes instead of compiled again.

helixrod's first calls are dominated by XLA compilation (tens of seconds for a fit on 2
cores); JAX's persistent cache stores the compiled executables keyed by the program, the
backend and the JAX version, so a second process that runs the same call loads them.  JAX
does not store executables that contain host callbacks, so a program with a raising
runtime check (`equinox.error_if`) is compiled again in every process.  The tracing and
lowering that precede the lookup are not cached by JAX; for helixrod's largest programs
(`solve_static`'s, the shooting solve of `solve_boundary_value`, the fits' Jacobian
program, the response curves' program) the same directory also keeps their exported form
(`_trace_cache.py`), so that a later process skips them too.  The cache is a directory of
files that is safe to delete at any time.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import jax

from . import _trace_cache

#: Environment variable naming the cache directory (overrides the per-user default).
CACHE_ENVIRONMENT_VARIABLE = "HELIXROD_CACHE_DIR"


def default_cache_directory() -> Path:
    """`$HELIXROD_CACHE_DIR` if set, else `$XDG_CACHE_HOME/helixrod/jax` (`~/.cache/helixrod/jax`
    without XDG_CACHE_HOME)."""
    if os.environ.get(CACHE_ENVIRONMENT_VARIABLE):
        return Path(os.environ[CACHE_ENVIRONMENT_VARIABLE]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base).expanduser() / "helixrod" / "jax"


def enable_compilation_cache(path: str | os.PathLike | None = None, *, min_compile_seconds: float = 0.0) -> Path:
    """Turn on JAX's persistent compilation cache in `path` (default
    `default_cache_directory()`, created if missing) for every program that took at least
    `min_compile_seconds` to compile, and the exported programs of `_trace_cache.py` (in
    its sub-directory `helixrod-traces`); returns the directory.  This changes global JAX
    configuration (`jax_compilation_cache_dir` and the cache thresholds) for the whole
    process, which helixrod otherwise never does: the command line calls it, a library user
    opts in.  Call it before the first compilation you want cached.

    By default every program is kept, the small ones too: a call's eager steps and small
    programs compile in 5-20 ms each and load in less, and a warm first call has dozens of
    them.  Measured (one core, fresh processes, the cases of
    `benchmarks/bench_first_calls.py`), warm first calls with a threshold of 0.2 s against
    none: `fit_stiffness` 1.15-1.19 -> 0.83-0.85 s, `solve_boundary_value` 1.58-1.59 ->
    1.40-1.41 s, the bundled tweezer example's fit 3.45-3.53 -> 2.82-2.85 s, `jax.grad`
    through `solve_static` 1.82-1.88 -> 1.68-1.74 s, the others within 0.05 s; cold first
    calls unchanged; that cache 15 files, 356 kB, for the gradient."""
    directory = default_cache_directory() if path is None else Path(path).expanduser()
    if directory.exists() and not directory.is_dir():
        raise ValueError(f"enable_compilation_cache: {directory} exists and is not a directory")
    if not (min_compile_seconds >= 0):
        raise ValueError(f"enable_compilation_cache: min_compile_seconds must be >= 0, got {min_compile_seconds}")
    directory.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(directory))
    if not os.access(directory, os.W_OK):
        # Read what is there, write nothing: JAX warned once per program it failed to write.
        warnings.warn(f"enable_compilation_cache: {directory} is not writable: programs are read from it, none are written")
        min_compile_seconds = float("inf")
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_seconds))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    _trace_cache.enable(directory)
    return directory
