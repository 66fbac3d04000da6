"""helixrod's compiler options: passed to its own top-level programs, never to a caller's."""

import gc
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import helixrod as hr
from helixrod import _compile


def _route_with(monkeypatch, options):
    monkeypatch.setattr(_compile, "COMPILER_OPTIONS", options)
    monkeypatch.setattr(jax, "default_backend", lambda: "cpu")  # the options' backend, on any machine
    return _compile.jit(lambda x: jnp.sin(x) * 2.0), _compile.filter_jit(lambda x: jnp.cos(x) + 1.0)


def test_options_go_to_top_level_calls_only(monkeypatch):
    # An option XLA does not know fails the compile: it shows which calls carry the options.
    sine, cosine = _route_with(monkeypatch, {"xla_helixrod_no_such_option": True})
    x = jnp.linspace(0.0, 1.0, 5)
    for fn, expected, slope in ((sine, 2.0 * np.sin(x), 2.0 * np.cos(x)), (cosine, np.cos(x) + 1.0, -np.sin(x))):
        with pytest.raises(Exception, match="No such compile option"):
            fn(x)
        # Inside a caller's transformation: the caller's program, compiled with its options.
        np.testing.assert_allclose(jax.jit(lambda y: fn(y) + 1.0)(x), expected + 1.0, rtol=1e-15)
        np.testing.assert_allclose(jax.vmap(fn)(x), expected, rtol=1e-15)
        np.testing.assert_allclose(jax.grad(lambda y: fn(y).sum())(x), slope, rtol=1e-15, atol=1e-16)


def test_options_stay_off_other_backends(monkeypatch):
    # The options name CPU settings: where the default backend is not the CPU (an H200 with
    # jaxlib 0.11.2 failed every top-level program), a top-level call is the plain program.
    sine, cosine = _route_with(monkeypatch, {"xla_helixrod_no_such_option": True})
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    x = jnp.linspace(0.0, 1.0, 5)
    np.testing.assert_allclose(sine(x), 2.0 * np.sin(np.asarray(x)), rtol=1e-15)
    np.testing.assert_allclose(cosine(x), np.cos(np.asarray(x)) + 1.0, rtol=1e-15)


def test_no_options_is_the_plain_jit(monkeypatch):
    plain_jit, plain_filter = _route_with(monkeypatch, {})
    x = jnp.linspace(0.0, 1.0, 5)
    np.testing.assert_allclose(plain_jit(x), 2.0 * np.sin(np.asarray(x)), rtol=1e-15)
    np.testing.assert_allclose(plain_filter(x), np.cos(np.asarray(x)) + 1.0, rtol=1e-15)


def test_a_top_level_call_traces_without_the_garbage_collector_and_restores_it():
    # The collector's passes over every object of the process cost a first call's tracing a
    # fifth of its time; it is paused for the call and left as the caller had it, also when
    # the call raises.
    seen = []

    def traced(x):
        seen.append(gc.isenabled())
        if x.shape == (2,):
            raise ValueError("bad shape")
        return 2.0 * x

    for program in (_compile.jit(traced), _compile.filter_jit(traced)):
        seen.clear()
        assert gc.isenabled()
        np.testing.assert_array_equal(program(jnp.ones(3)), 2.0)
        with pytest.raises(ValueError, match="bad shape"):
            program(jnp.ones(2))
        assert seen == [False, False] and gc.isenabled()
        gc.disable()
        try:
            program(jnp.ones(4))
            assert seen == [False, False, False] and not gc.isenabled()  # the caller's choice stands
        finally:
            gc.enable()
        # Inside a caller's transformation the caller's trace runs as the caller set it.
        np.testing.assert_array_equal(jax.jit(program)(jnp.ones(5)), 2.0)
        assert seen[-1] is True and gc.isenabled()


def test_run_once_programs_take_their_own_options(monkeypatch):
    # A program run once per call of its entry point (a fit's error analysis) is compiled at
    # XLA's lowest optimisation level: its own options, at the top level only.
    monkeypatch.setattr(jax, "default_backend", lambda: "cpu")
    monkeypatch.setattr(_compile, "RUN_ONCE_OPTIONS", {"xla_helixrod_no_such_option": True})
    once, usual = _compile.jit(lambda x: jnp.sin(x) * 2.0, run_once=True), _compile.jit(lambda x: jnp.sin(x) * 3.0)
    x = jnp.linspace(0.0, 1.0, 5)
    with pytest.raises(Exception, match="No such compile option"):
        once(x)
    np.testing.assert_allclose(usual(x), 3.0 * np.sin(np.asarray(x)), rtol=1e-15)
    np.testing.assert_allclose(jax.jit(lambda y: once(y) + 1.0)(x), 2.0 * np.sin(np.asarray(x)) + 1.0, rtol=1e-15)


def test_run_once_options_are_the_lowest_level_of_the_usual_ones():
    expected = {**_compile.COMPILER_OPTIONS, "xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}
    assert _compile.RUN_ONCE_OPTIONS == (expected if _compile.COMPILER_OPTIONS else {})
    # XLA knows them: the program compiles and computes what the plain one does.
    once = _compile.jit(lambda x: jnp.exp(x) - x, run_once=True)
    x = jnp.linspace(-1.0, 1.0, 7)
    np.testing.assert_allclose(once(x), np.exp(np.asarray(x)) - np.asarray(x), rtol=1e-15)


# XLA's default compilation, whatever the test run's own settings (tests/conftest.py):
# what a caller's `jax.jit` gets.
XLA_DEFAULTS = {"xla_backend_optimization_level": 3, "xla_llvm_disable_expensive_passes": False}
XLA_DEFAULTS.update({name: not value for name, value in _compile.COMPILER_OPTIONS.items()})


@pytest.mark.heavy  # compiles two entry points with XLA's full optimisation (~22 s)
def test_entry_points_agree_at_top_level_and_under_a_callers_jit():
    """helixrod's top-level programs (its `COMPILER_OPTIONS`) against the same functions
    inside a caller's program compiled with XLA's defaults."""
    rod = hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
    kappa, tau = jnp.linspace(0.1, 2.0, 7), jnp.linspace(-1.5, 1.5, 7)
    top = hr.helix_equilibria(rod, kappa, tau, fields=("phi", "force", "stable"))
    nested = jax.jit(
        lambda k, t: hr.helix_equilibria(rod, k, t, fields=("phi", "force", "stable")), compiler_options=XLA_DEFAULTS
    )(kappa, tau)
    np.testing.assert_allclose(top.phi, nested.phi, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(top.force, nested.force, rtol=1e-13, atol=1e-14)
    np.testing.assert_array_equal(top.stable, nested.stable)
    n0, m0 = jnp.array([0.1, -0.2, 0.5]), jnp.array([0.3, 0.2, 0.9])
    top = hr.solve_static(rod, n0, m0, 5.0)
    nested = jax.jit(lambda n: hr.solve_static(rod, n, m0, 5.0), compiler_options=XLA_DEFAULTS)(n0)
    # Two programs, two roundings of an adaptive solve at tolerance 1e-12.
    np.testing.assert_allclose(top.m, nested.m, rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("setting", ["0", "1"])
def test_environment_variable_turns_the_options_off(setting):
    code = "from helixrod._compile import COMPILER_OPTIONS; print(sorted(COMPILER_OPTIONS))"
    env = dict(os.environ, **{_compile.OPTIONS_ENVIRONMENT_VARIABLE: setting})
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    expected = "[]" if setting == "0" else str(sorted(_compile._compiler_options()))
    assert out.stdout.strip() == expected


@pytest.mark.parametrize(("release", "options", "small_loops"),
                         [("0.9.2", {}, False), ("0.10.2", {"xla_cpu_use_fusion_emitters": False}, True), ("0.11.2", {}, True)])
def test_options_follow_the_jaxlib_release(monkeypatch, release, options, small_loops):
    # jaxlib 0.11 has no classic emitters: its XLA refuses the option (an abort from XLA_FLAGS).
    monkeypatch.setattr(_compile.metadata, "version", lambda name: release)
    monkeypatch.delenv(_compile.OPTIONS_ENVIRONMENT_VARIABLE, raising=False)
    assert _compile._compiler_options() == options
    assert _compile._settings_apply() is small_loops


def test_small_loop_request_respects_the_environment():
    flag = f"xla_cpu_small_while_loop_byte_threshold={_compile.SMALL_LOOP_BYTES}"
    environ = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert _compile.request_small_loop_kernels(environ)
    assert environ["XLA_FLAGS"] == f"--xla_force_host_platform_device_count=2 --xla_backend_extra_options={flag}"
    empty = {}
    assert _compile.request_small_loop_kernels(empty) and empty["XLA_FLAGS"] == f"--xla_backend_extra_options={flag}"
    users = {"XLA_FLAGS": "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=0"}
    assert not _compile.request_small_loop_kernels(dict(users))
    off = {_compile.OPTIONS_ENVIRONMENT_VARIABLE: "0"}
    assert not _compile.request_small_loop_kernels(off) and "XLA_FLAGS" not in off


# A loop whose carry (512 doubles, 4 kB) is above XLA's default threshold (1 kB) and below
# helixrod's: one kernel (a call marked `xla_cpu_small_call`) once helixrod is imported.
_LOOP_PROGRAM = """
import helixrod, jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
loop = lambda x: jax.lax.fori_loop(0, jnp.int32(x[0] > -1) * 10, lambda i, c: jnp.sin(c) * 1.1, x)
print("xla_cpu_small_call" in jax.jit(loop).lower(jnp.ones(512)).compile().as_text())
"""


@pytest.mark.parametrize("setting", ["0", "1"])
def test_import_compiles_small_loops_into_one_kernel(setting):
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env[_compile.OPTIONS_ENVIRONMENT_VARIABLE] = setting
    env["JAX_PLATFORMS"] = "cpu"  # a CPU setting: the CPU's program also on a machine with a GPU
    out = subprocess.run([sys.executable, "-c", _LOOP_PROGRAM], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ("True" if setting == "1" else "False")


@pytest.mark.parametrize(("release", "added"), [("0.10.1", False), ("0.10.2", True), ("0.11.2", False)])
def test_dot_library_fusion_request_follows_the_release_and_the_environment(monkeypatch, release, added):
    # An unknown flag in XLA_FLAGS aborts the process: only the release it was measured with.
    monkeypatch.setattr(_compile.metadata, "version", lambda name: release)
    environ = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert _compile.request_dot_library_fusions(environ) is added
    expected = "--xla_force_host_platform_device_count=2" + (" --xla_cpu_experimental_ynn_fusion_type=dot" if added else "")
    assert environ["XLA_FLAGS"] == expected
    users = {"XLA_FLAGS": "--xla_cpu_experimental_ynn_fusion_type=dot,eltwise"}
    assert not _compile.request_dot_library_fusions(users) and users["XLA_FLAGS"].endswith("dot,eltwise")
    off = {_compile.OPTIONS_ENVIRONMENT_VARIABLE: "0"}
    assert not _compile.request_dot_library_fusions(off) and "XLA_FLAGS" not in off


# Elementwise arithmetic and a reduction over a (4000, 14) array: XLA's CPU backend of jaxlib
# 0.10.2 hands it to a YNNPACK library fusion by default; not once helixrod is imported.
_ELEMENTWISE_PROGRAM = """
import helixrod, jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
f = lambda x: jnp.sum(jnp.sin(x) * jnp.cos(x) + x * x, axis=1)
print("ynn_fusion" in jax.jit(f).lower(jnp.ones((4000, 14))).compile().as_text())
"""


@pytest.mark.skipif(not (0, 10, 2) <= _compile._jaxlib_version() < (0, 11), reason="the flag of jaxlib 0.10.2")
@pytest.mark.parametrize("setting", ["0", "1"])
def test_import_leaves_only_dots_to_library_fusions(setting):
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env[_compile.OPTIONS_ENVIRONMENT_VARIABLE] = setting
    env["JAX_PLATFORMS"] = "cpu"
    out = subprocess.run([sys.executable, "-c", _ELEMENTWISE_PROGRAM], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ("False" if setting == "1" else "True")


def test_a_program_compiled_ahead_is_found_by_its_call(compilations, monkeypatch):
    # Compiled on a thread of its own from the specs of its arguments (one of them a
    # value still to be computed: a spec), then called with values: nothing compiles again,
    # and a second program fed with the first's results finds its own compilation too.
    monkeypatch.setattr(_compile, "cores", lambda: 2)
    def scaled_sine(x, scale):
        return {"y": jnp.sin(x) * scale, "total": jnp.sum(x)}

    def shifted(y, total):
        return y + total

    first, second = _compile.jit(scaled_sine), _compile.jit(shifted)
    x = jnp.linspace(0.0, 1.0, 7)
    out = _compile.compile_ahead(first, jax.ShapeDtypeStruct(x.shape, x.dtype), 2.0)
    assert jax.tree.structure(out) == jax.tree.structure({"y": 0, "total": 0})
    assert (out["y"].shape, out["y"].dtype, out["total"].shape) == ((7,), x.dtype, ())
    assert _compile.compile_ahead(first, x, 2.0) is None  # one compilation of a program at a time
    assert _compile.compile_ahead(second, out["y"], out["total"]) is not None
    result = first(x, 2.0)
    total = second(result["y"], result["total"])
    np.testing.assert_allclose(total, 2.0 * np.sin(np.asarray(x)) + np.sum(np.asarray(x)), rtol=1e-15)
    ours = [(thread, name) for thread, name in compilations if name in ("scaled_sine", "shifted")]
    assert sorted(ours) == [("helixrod-compile-scaled_sine", "scaled_sine"), ("helixrod-compile-shifted", "shifted")]


def test_results_of_committed_arguments_are_specified_committed(compilations, monkeypatch):
    # A program's results are committed to a device when an argument is (JAX's rule), and
    # whether arguments are committed is part of a program's signature: the specs say so.
    monkeypatch.setattr(_compile, "cores", lambda: 2)
    def doubled(x):
        return 2.0 * x

    def plus_one(y):
        return y + 1.0

    first, second = _compile.jit(doubled), _compile.jit(plus_one)
    x = jax.device_put(jnp.arange(3.0), jax.devices()[0])
    out = _compile.compile_ahead(first, x)
    assert out.sharding == x.sharding
    _compile.compile_ahead(second, out)
    np.testing.assert_array_equal(second(first(x)), 2.0 * np.arange(3.0) + 1.0)
    assert sorted(name for thread, name in compilations if name in ("doubled", "plus_one")) == ["doubled", "plus_one"]
    assert all(thread.startswith("helixrod-compile-") for thread, name in compilations if name in ("doubled", "plus_one"))


def test_nothing_is_compiled_ahead_where_the_call_would_not_compile_it(monkeypatch):
    monkeypatch.setattr(_compile, "cores", lambda: 2)

    def failing(x):
        if x.shape == (2,):
            raise ValueError("bad shape")
        return x

    program = _compile.jit(failing)
    # Tracing fails: nothing starts, and the call raises its own error.
    assert _compile.compile_ahead(program, jax.ShapeDtypeStruct((2,), jnp.float32)) is None
    with pytest.raises(ValueError, match="bad shape"):
        program(jnp.ones(2, jnp.float32))
    # Inside a caller's transformation the program is part of the caller's.
    seen = []
    jax.jit(lambda y: seen.append(_compile.compile_ahead(program, y)) or y)(jnp.ones(3))
    assert seen == [None]
    # equinox's filter_jit programs, and plain functions, have no ahead-of-call compilation.
    assert _compile.compile_ahead(_compile.filter_jit(failing), jnp.ones(3)) is None
    assert _compile.compile_ahead(failing, jnp.ones(3)) is None
    # On one core nothing would compile beside the caller.
    monkeypatch.setattr(_compile, "cores", lambda: 1)
    assert _compile.compile_ahead(program, jnp.ones(3)) is None
    assert program not in _compile._compiling


def test_a_compilation_left_running_does_not_stop_the_next(compilations, monkeypatch):
    """A program compiled ahead for a call that never came (its caller raised first) leaves
    its thread running; the next first call of another signature still compiles beside its
    caller, and each call finds its program."""
    monkeypatch.setattr(_compile, "cores", lambda: 2)

    def abandoned(x):
        return jnp.cos(x) * 7.0 - x

    program = _compile.jit(abandoned)
    assert _compile.compile_ahead(program, jax.ShapeDtypeStruct((5,), jnp.float32)) is not None
    assert _compile.compile_ahead(program, jax.ShapeDtypeStruct((6,), jnp.float32)) is not None
    for n in (6, 5):
        x = jnp.linspace(0.0, 1.0, n, dtype=jnp.float32)
        np.testing.assert_allclose(program(x), np.cos(np.asarray(x)) * 7.0 - np.asarray(x), rtol=1e-6)
    threads = sorted(thread for thread, name in compilations if name == "abandoned")
    assert threads == ["helixrod-compile-abandoned"] * 2, threads
    assert program not in _compile._compiling


def test_cores_are_those_the_process_may_run_on():
    expected = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert _compile.cores() == expected >= 1


def test_a_traced_function_is_named_by_what_it_computes():
    scalar = jax.ShapeDtypeStruct((), jnp.float64)
    named = lambda f: _compile.TracedFunction(f, scalar)  # noqa: E731
    third, next_up = 1.0 / 3.0, float(np.nextafter(1.0 / 3.0, 1.0))
    table, other_table = jnp.asarray([1.0, 2.0]), jnp.asarray([1.0, 2.5])
    same = named(lambda p: jnp.sin(p) * third), named(lambda p: jnp.sin(p) * third)
    assert same[0] == same[1] and hash(same[0]) == hash(same[1]) and repr(same[0]) == repr(same[1])
    assert "0x" not in repr(same[0])
    assert named(lambda p: jnp.sin(p) * third) != named(lambda p: jnp.sin(p) * next_up)  # one ulp
    assert named(lambda p: p * table) != named(lambda p: p * other_table)  # closed-over arrays
    assert named(lambda p: jnp.stack([p, p])) != named(lambda p: (p, p))  # output structure
    assert _compile.TracedFunction(jnp.sin, jax.ShapeDtypeStruct((2,), jnp.float64)) != named(jnp.sin)  # shapes
    # What the text cannot name: a custom derivative rule, a host callback, a failing trace.
    doubled = jax.custom_jvp(lambda p: 2.0 * p)
    doubled.defjvp(lambda primals, tangents: (2.0 * primals[0], 2.0 * tangents[0]))
    callback = lambda p: jax.pure_callback(np.cos, scalar, p)  # noqa: E731
    broken = lambda p: p.no_such_attribute  # noqa: E731
    nested = lambda p: jax.lax.cond(p > 0, doubled, jnp.sin, p)  # noqa: E731
    for fun in (doubled, callback, broken, nested):
        a, b = named(fun), named(fun)
        assert a.digest is None and a == b and a != named(lambda p: fun(p)) and repr(a) == repr(fun)
    # Nested programs and branches without such rules are named.
    assert named(lambda p: jax.jit(jnp.sin)(p)).digest is not None
    assert named(lambda p: jax.lax.cond(p > 0, jnp.sin, jnp.cos, p)).digest is not None
    assert float(same[0](0.5)) == np.sin(0.5) / 3.0
