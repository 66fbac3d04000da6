"""The persistent compilation cache: programs compiled in one process are loaded by the next."""

import os
import subprocess
import sys
import textwrap

import jax
import pytest

import helixrod as hr
from helixrod._cache import CACHE_ENVIRONMENT_VARIABLE, default_cache_directory

SCRIPT = textwrap.dedent(
    """
    import sys, jax, jax.numpy as jnp
    import helixrod as hr
    hr.enable_compilation_cache(sys.argv[1], min_compile_seconds=0.0)
    hits = []
    jax.monitoring.register_event_listener(lambda event, **kw: hits.append(event) if "cache_hits" in event else None)
    f = jax.jit(lambda x: jnp.sin(x) @ jnp.cos(x).T + 17.0)
    f(jnp.ones((3, 3))).block_until_ready()
    print("hits", len(hits))
    """
)


def test_a_second_process_loads_the_compiled_program(tmp_path):
    cache = tmp_path / "cache"
    runs = [subprocess.run([sys.executable, "-c", SCRIPT, str(cache)], capture_output=True, text=True, timeout=120) for _ in range(2)]
    for run in runs:
        assert run.returncode == 0, run.stderr
    assert runs[0].stdout.split()[-1] == "0" and int(runs[1].stdout.split()[-1]) >= 1, [r.stdout for r in runs]
    assert any(cache.iterdir())


def test_default_directory_and_errors(tmp_path, monkeypatch):
    monkeypatch.setenv(CACHE_ENVIRONMENT_VARIABLE, str(tmp_path / "mine"))
    assert default_cache_directory() == tmp_path / "mine"
    monkeypatch.delenv(CACHE_ENVIRONMENT_VARIABLE)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_directory() == tmp_path / "xdg" / "helixrod" / "jax"
    afile = tmp_path / "file"
    afile.write_text("")
    with pytest.raises(ValueError, match="exists and is not a directory"):
        hr.enable_compilation_cache(afile)
    with pytest.raises(ValueError, match="min_compile_seconds must be >= 0"):
        hr.enable_compilation_cache(tmp_path / "x", min_compile_seconds=-1)
    previous = jax.config.jax_compilation_cache_dir
    previous_threshold = jax.config.jax_persistent_cache_min_compile_time_secs
    try:
        assert hr.enable_compilation_cache(tmp_path / "new") == tmp_path / "new"
        assert jax.config.jax_compilation_cache_dir == str(tmp_path / "new") and (tmp_path / "new").is_dir()
        assert jax.config.jax_persistent_cache_min_compile_time_secs == 0.0  # small programs kept too
        # A directory that cannot be written is read, and nothing is written (JAX warned once
        # per program it failed to write: ~90 warnings for one curve).
        monkeypatch.setattr(hr._cache.os, "access", lambda path, mode: False)
        with pytest.warns(UserWarning, match="is not writable: programs are read from it, none are written"):
            hr.enable_compilation_cache(tmp_path / "new")
        assert jax.config.jax_persistent_cache_min_compile_time_secs == float("inf")
    finally:
        jax.config.update("jax_compilation_cache_dir", previous)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", previous_threshold)
    assert os.environ.get(CACHE_ENVIRONMENT_VARIABLE) is None
