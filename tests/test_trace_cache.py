"""The trace cache: a program exported by one process is called by the next without tracing."""

import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from helixrod import _compile, _trace_cache
from helixrod._compile import TracedFunction, compile_ahead, filter_jit, jit, split_arrays

traces = []


@jit(static_argnames="power", trace_cache=True)
def program(x, pair, power=2):
    traces.append(power)  # runs once per trace
    return {"value": jnp.sum(x**power) + pair[0] * pair[1], "shape": x * 2.0}


class Foreign(eqx.Module):
    """A type the cache cannot vouch for (not helixrod's, JAX's or equinox's)."""

    a: jax.Array


@jit(trace_cache=True)
def scaled(module, x):
    return module.a * x


class Doubler:
    """A callable of the user's with a repr that stays the same when its code changes."""

    def __repr__(self):
        return "Doubler()"

    def __call__(self, x):
        return 2.0 * x


@jit(trace_cache=True)
def applied(function, x):
    return function(x)


@jit(trace_cache=True)
def with_callback(x):
    return jax.pure_callback(lambda v: np.asarray(v) + 1.0, jax.ShapeDtypeStruct(x.shape, x.dtype), x)


@jit(static_argnames="function", trace_cache=True)
def applied_by_trace(function, x):
    traces.append("applied_by_trace")
    return function(x)


def _halves(static, arrays):
    model = static.combine(arrays)
    return model["scale"] * model["power_of"](model["x"]) if callable(model["power_of"]) else model["scale"] * model["x"] ** model["power_of"]


halves = jit(_halves, static_argnums=0, trace_cache=True)


@filter_jit(trace_cache=True)
def filtered(x, settings, power=2):
    traces.append(("filtered", power))
    return settings["scale"] * x**power + settings["offset"]


def _new_process():
    """What a later process has: the files, none of this process's programs."""
    _trace_cache._programs.clear()


def test_a_later_process_calls_the_exported_program_without_tracing(exported_programs):
    # A signature no other test calls (JAX's own cache of traces lives as long as the process:
    # met earlier in the same worker, the program would not be traced here).
    x, pair = jnp.arange(4.0), (jnp.asarray(2.0), jnp.asarray(3.0))
    expected = program.__wrapped__(x, pair, power=6)
    traces.clear()
    first = program(x, pair, power=6)
    assert traces == [6] and _trace_cache.counts["exported"] >= 1
    assert len(list(exported_programs.glob("*.export"))) == 1
    _new_process()
    loaded_before = _trace_cache.counts["loaded"]
    later = program(x + 1.0, pair, power=6)  # same signature, new values
    assert traces == [6], "the later process traced the program again"
    assert _trace_cache.counts["loaded"] == loaded_before + 1
    for a, b in ((first, expected), (later, program.__wrapped__(x + 1.0, pair, power=6))):
        assert jax.tree.structure(a) == jax.tree.structure(b)
        for u, v in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
            np.testing.assert_array_equal(np.asarray(u), np.asarray(v))


def test_a_program_compiled_ahead_is_exported_and_found_by_its_call(exported_programs, compilations, monkeypatch):
    # Compiled ahead from specs, the program is exported as a call would export it; its
    # results are committed (`_trace_cache.placement`), and the call compiles nothing.
    monkeypatch.setattr(_compile, "cores", lambda: 2)
    x, pair = jnp.arange(6.0), (jnp.asarray(2.0), jnp.asarray(3.0))
    traces.clear()
    out = compile_ahead(program, jax.ShapeDtypeStruct(x.shape, x.dtype), pair, power=5)
    assert traces == [5] and len(list(exported_programs.glob("*.export"))) == 1
    assert out["shape"].shape == (6,) and out["value"].sharding == _trace_cache.placement()
    result = program(x, pair, power=5)
    assert traces == [5]
    np.testing.assert_allclose(result["value"], np.sum(np.arange(6.0) ** 5) + 6.0, rtol=1e-15)
    assert [thread for thread, name in compilations if name == "program"] == ["helixrod-compile-program"]


def test_a_new_signature_is_a_new_program(exported_programs):
    x, pair = jnp.arange(4.0), (jnp.asarray(2.0), jnp.asarray(3.0))
    program(x, pair, power=2)
    program(x, pair, power=3)  # a static argument
    program(jnp.arange(5.0), pair, power=2)  # a shape
    program(x, (jnp.asarray(2.0), jnp.asarray(3, jnp.int32)), power=2)  # a dtype
    program(x, [jnp.asarray(2.0), jnp.asarray(3.0)], power=2)  # a structure
    assert len(list(exported_programs.glob("*.export"))) == 5


def test_what_it_cannot_vouch_for_takes_the_plain_path(exported_programs):
    x = jnp.arange(3.0)
    assert float(scaled(Foreign(jnp.asarray(2.0)), x)[2]) == 4.0  # a foreign pytree node
    assert float(applied(jax.tree_util.Partial(Doubler()), x)[2]) == 4.0  # foreign static data in JAX's node
    refused = _trace_cache.counts["refused"]
    assert float(with_callback(x)[0]) == 1.0  # a host callback: jax.export refuses it
    assert _trace_cache.counts["refused"] == refused + 1 and len(list(exported_programs.glob("*.refused"))) == 1
    _new_process()
    _trace_cache._refused.clear()
    assert float(with_callback(x + 1.0)[0]) == 2.0  # a later process reads the refusal: no second attempt
    assert _trace_cache.counts["refused"] == refused + 1
    traces.clear()
    # Inside a caller's transformation the plain program is traced as part of the caller's.
    out = jax.vmap(lambda v: program(v, (v[0], v[1]), power=2)["value"])(jnp.ones((3, 4)))
    np.testing.assert_allclose(np.asarray(out), 5.0)
    assert traces == [2]
    with jax.default_device(jax.devices("cpu")[0]):  # the caller chose the device
        assert float(program(x, (x[0], x[1]), power=2)["value"]) == 5.0
    assert list(exported_programs.glob("*.export")) == []


def test_a_static_half_is_part_of_the_signature(exported_programs):
    x = jnp.arange(3.0)
    arrays, static = split_arrays({"x": x, "scale": jnp.asarray(2.0), "power_of": 3})
    np.testing.assert_array_equal(np.asarray(halves(static, arrays)), 2.0 * np.arange(3.0) ** 3)
    arrays, static = split_arrays({"x": x, "scale": jnp.asarray(2.0), "power_of": 2})
    np.testing.assert_array_equal(np.asarray(halves(static, arrays)), 2.0 * np.arange(3.0) ** 2)
    assert len(list(exported_programs.glob("*.export"))) == 2
    # A callable in the static half: no text names it the same way in another process.
    arrays, static = split_arrays({"x": x, "scale": jnp.asarray(2.0), "power_of": jnp.sin})
    np.testing.assert_allclose(np.asarray(halves(static, arrays)), 2.0 * np.sin(np.arange(3.0)))
    assert len(list(exported_programs.glob("*.export"))) == 2


def test_a_filter_jit_program_keys_its_non_array_leaves(exported_programs):
    x = jnp.arange(3.0)
    settings = {"scale": jnp.asarray(2.0), "offset": 1.0}  # a Python float: static, as filter_jit has it
    traces.clear()
    first = filtered(x, settings, power=3)
    np.testing.assert_array_equal(np.asarray(first), 2.0 * np.arange(3.0) ** 3 + 1.0)
    np.testing.assert_array_equal(np.asarray(filtered(x, {"scale": jnp.asarray(2.0), "offset": 5.0})), 2.0 * np.arange(3.0) ** 2 + 5.0)
    assert len(list(exported_programs.glob("*.export"))) == 2 and traces == [("filtered", 3), ("filtered", 2)]
    _new_process()
    later = filtered(x + 1.0, {"scale": jnp.asarray(3.0), "offset": 1.0}, power=3)
    np.testing.assert_array_equal(np.asarray(later), 3.0 * np.arange(1.0, 4.0) ** 3 + 1.0)
    assert len(traces) == 2 and len(list(exported_programs.glob("*.export"))) == 2


def test_a_function_named_by_its_trace_is_kept_for_a_later_process(exported_programs):
    # A static function argument (`follow_branch`'s load) as a `TracedFunction`: a new
    # lambda with the same body is the same program, in this process and the next.
    x = jnp.arange(3.0)
    scalar = jax.ShapeDtypeStruct((3,), x.dtype)
    offset = jnp.asarray([1.0, 2.0, 3.0])
    traces.clear()
    first = applied_by_trace(TracedFunction(lambda v: 2.0 * v + offset, scalar), x)
    np.testing.assert_array_equal(np.asarray(first), 2.0 * np.arange(3.0) + [1.0, 2.0, 3.0])
    applied_by_trace(TracedFunction(lambda v: 2.0 * v + offset, scalar), x + 1.0)
    assert traces == ["applied_by_trace"] and len(list(exported_programs.glob("*.export"))) == 1
    _new_process()
    loaded = _trace_cache.counts["loaded"]
    later = applied_by_trace(TracedFunction(lambda v: 2.0 * v + offset, scalar), x + 2.0)
    np.testing.assert_array_equal(np.asarray(later), 2.0 * np.arange(2.0, 5.0) + [1.0, 2.0, 3.0])
    assert traces == ["applied_by_trace"] and _trace_cache.counts["loaded"] == loaded + 1
    # Another constant is another program.
    other = applied_by_trace(TracedFunction(lambda v: 2.0 * v + offset + 1.0, scalar), x)
    np.testing.assert_array_equal(np.asarray(other), 2.0 * np.arange(3.0) + [2.0, 3.0, 4.0])
    assert len(list(exported_programs.glob("*.export"))) == 2
    # A custom derivative rule prints by its name only: the function is named by identity,
    # its repr keeps the cache away.
    doubled = jax.custom_jvp(lambda v: 2.0 * v)
    doubled.defjvp(lambda primals, tangents: (2.0 * primals[0], 2.0 * tangents[0]))
    np.testing.assert_array_equal(np.asarray(applied_by_trace(TracedFunction(doubled, scalar), x)), 2.0 * np.arange(3.0))
    assert len(list(exported_programs.glob("*.export"))) == 2


def test_a_damaged_file_is_exported_again(exported_programs):
    x, pair = jnp.arange(4.0), (jnp.asarray(2.0), jnp.asarray(3.0))
    program(x, pair, power=4)
    (path,) = exported_programs.glob("*.export")
    path.write_bytes(b"not a program")
    _new_process()
    exported = _trace_cache.counts["exported"]
    out = program(x, pair, power=4)
    assert float(out["value"]) == float(np.sum(np.arange(4.0) ** 4) + 6.0)
    assert _trace_cache.counts["exported"] == exported + 1 and path.stat().st_size > 100


SCRIPT = textwrap.dedent(
    """
    import sys, json, logging, jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    import helixrod as hr
    from helixrod import _trace_cache
    compiled = []
    class Keep(logging.Handler):
        def emit(self, record):
            if record.getMessage().startswith("Finished XLA compilation of jit(solve)"):
                compiled.append(record.threadName)
    logging.getLogger("jax").addHandler(Keep())
    jax.config.update("jax_log_compiles", True)
    hr.enable_compilation_cache(sys.argv[1])
    sol = hr.solve_boundary_value(hr.Rod(1.0, 1.5, 0.8), 1.0, end=hr.Loaded(force=(0.0, 0.0, -3.0)))
    print(json.dumps(dict(counts=_trace_cache.counts, force=np.asarray(sol.force).tolist(), index=int(sol.instability_index),
                          x=np.asarray(sol.end_position).tolist(), ok=bool(sol.ok), compiled=compiled)))
    """
)


@pytest.mark.heavy
def test_solve_boundary_value_in_a_later_process(tmp_path):
    """The shooting solve, exported by a first process, is loaded by a second that finds
    the same (buckled, stable) state."""
    import json

    runs = []
    for _ in range(2):
        out = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path)], capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, out.stderr[-3000:]
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    first, second = runs
    assert first["counts"]["exported"] >= 1 and first["counts"]["loaded"] == 0
    # The first compiles the exported solve once, beside its other programs where there
    # are cores for it (the persistent cache answers the second's, on its thread too).
    thread = "helixrod-compile-solve" if _compile.cores() > 1 else "MainThread"
    assert first["compiled"] == second["compiled"] == [thread]
    assert second["counts"]["loaded"] >= 1 and second["counts"]["exported"] == 0
    assert first["ok"] and second["ok"] and first["index"] == second["index"] == 0
    np.testing.assert_allclose(second["force"], first["force"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(second["x"], first["x"], rtol=0, atol=1e-12)


@pytest.mark.heavy
def test_the_atlas_and_the_branch_are_kept(exported_programs):
    """The programs behind the warm first calls of `stability_atlas` (its index and critical
    lengths, apart from the registers' custom call) and of `follow_branch` (the stability
    test and the corrector, whose load is named by its trace; its first point, stable from
    the default guess, needs no solve of `solve_boundary_value`) are exported, none
    refused: a later process loads them instead of tracing them."""
    import helixrod

    spring = helixrod.Rod(1.0, 1.0, 1 / 1.3, uhat=(0.0, 1.0, 0.3))
    exported = _trace_cache.counts["exported"]
    grid = (jnp.array([0.5, 1.1]), jnp.array([0.2, -0.3]))
    atlas = helixrod.stability_atlas(spring, *grid, 5.0, bisections=6, progress=False)
    assert _trace_cache.counts["exported"] == exported + 2
    _trace_cache.enable(None)  # the same atlas by the plain programs
    plain = helixrod.stability_atlas(spring, *grid, 5.0, bisections=6, progress=False)
    _trace_cache.enable(exported_programs.parent)
    for name in ("instability_index", "stability_margin", "critical_length", "instability_type"):
        np.testing.assert_array_equal(np.asarray(getattr(atlas, name)), np.asarray(getattr(plain, name)))
    exported = _trace_cache.counts["exported"]
    load = lambda P: helixrod.Loaded(force=jnp.stack([0.0 * P, 0.0 * P, -P]))  # noqa: E731
    branch = helixrod.follow_branch(helixrod.Rod(1.0, 1.5, 0.8), 1.0, load, (1.0, 2.0), stability_pieces=6)
    assert _trace_cache.counts["exported"] == exported + 2
    assert np.all(np.asarray(branch.instability_index) == 0)
    assert list(exported_programs.glob("*.refused")) == []
