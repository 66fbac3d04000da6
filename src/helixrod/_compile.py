"""How helixrod's programs are compiled: every program it compiles on its own (an entry
point's jitted core) goes through `jit` or `filter_jit` here, which pass `COMPILER_OPTIONS`
to XLA when called at the top level.  Under a caller's `jax.jit`, `vmap` or `grad` the same
function is the plain `jax.jit` (JAX accepts compiler options on top-level programs only),
and is compiled as part of the caller's program with the caller's options.

XLA's CPU backend writes each fused loop with its MLIR "fusion emitters" (the default in
jaxlib 0.10) or with its classic LLVM IR emitters.  helixrod's programs are long chains of
scalar arithmetic and selects (the register root, the Lie-group steps), and for them the
classic emitters compile about twice as fast and run as fast or faster.  Measured with
jaxlib 0.10.2 on one core: the register root of 64 points compiles in 3.6 s instead of
6.7 s; `helix_equilibria` first calls (1e4 points) 4.5 s instead of 7.2 s and runs 249 instead
of 388 ns per point, (1e6 points) 4.8 s instead of 10.5 s at the same speed.  jaxlib 0.11
has no classic emitters and no such option (on an H200 machine with jaxlib 0.11.2 every
top-level program failed with "No such compile option"), so it is passed with jaxlib 0.10
only, and only where JAX's default backend is the CPU, whose setting it names; elsewhere
every program is the plain `jax.jit`.  `HELIXROD_COMPILER_OPTIONS=0` in the environment
(read at import) turns it off.

One more setting cannot be passed per program: XLA's CPU backend compiles a `while` loop
whose operations touch at most `xla_cpu_small_while_loop_byte_threshold` bytes (1 kB by
default) into a single kernel; a larger loop runs each fused operation of its body as a
separate task ("thunk"), and once any buffer of the body exceeds 512 bytes (a few saved
points, a Jacobian) the body's tasks are scheduled concurrently on the thread pool, at a
cost of microseconds per iteration.  helixrod's solvers are loops of hundreds of small
operations per step, so that overhead dominates them.  `request_small_loop_kernels` raises
the threshold to `SMALL_LOOP_BYTES` (1 MB) through ``XLA_FLAGS``, which XLA reads once, at
the first compilation of the process: it is called when helixrod is imported and applies
only if nothing has been compiled before.  Measured with jaxlib 0.10.2 on 2 cores (later
calls, fresh processes): `solve_static` (L = 40, eager) 11.1 -> 3.0 ms; with 201 saved
points 5.4 -> 0.71 ms against 2.6 -> 0.79 ms at the end only; `solve_boundary_value` 24.6 ->
16.9 ms; `helices_under_load` 6.1 -> 4.2 ms; `helix_equilibria` (1e4 points) 3.4 -> 2.6 ms;
`fit_stiffness` unchanged; first calls unchanged.  It is process-wide: the loops of
the caller's own programs compile the same way.  It is left alone when ``XLA_FLAGS``
already sets ``xla_backend_extra_options``, and `HELIXROD_COMPILER_OPTIONS=0` turns it off.

A last process-wide setting: jaxlib 0.10.2's CPU backend hands chains of elementwise
operations (and reductions) on larger arrays to YNNPACK "library fusions", each a call into
the library instead of a loop XLA writes itself.  For helixrod's batched arithmetic that is
several times slower: `request_dot_library_fusions` leaves YNNPACK the dots alone.
Measured on 2 cores (fresh processes, the flag against none): `jax.jit(jax.grad(...))` of
the forces of `helix_equilibria` at 10^5 points 19.4-21.4 -> 4.8-4.9 ms; a vmapped batch of
1000 `solve_static` solves 300-302 -> 152-154 us a solve; `helices_under_load` 2.31-2.36 ->
1.75-1.79 ms; `fit_stiffness` (60 helices) 5.7-6.7 -> 5.1-5.4 ms; one `solve_static` and
`solve_boundary_value` unchanged within noise.  Like the loop threshold it is process-wide
and left alone when ``XLA_FLAGS`` already names it.

A top-level call of a program made here pauses Python's cyclic garbage collector while it
runs (and restores it as the caller had it, also on an error).  A first call traces its
program: hundreds of thousands of short-lived Python objects, whose allocation triggers the
collector's full passes over every object of the process (JAX's, diffrax's, ...), and none of
it is cyclic garbage worth collecting there.  Measured (one core, fresh processes
alternating with the code before, empty caches): the collector took 0.23-0.25 s of
`solve_boundary_value`'s first call (287 passes), whose tracing went 1.11-1.19 -> 0.88-1.01 s;
the tweezer example's fit (`benchmarks/bench_first_calls.py`) 12.09-12.15 -> 11.32-11.51 s,
its tracing 3.37-3.43 -> 2.45-2.65 s, peak memory 0.52 -> 0.53 GB.  A later call dispatches a
compiled program and returns: pausing costs it three calls (read, off, on), 0.065 us in all.

Programs compiled side by side: `compile_ahead` traces and lowers a program on the calling
thread and hands XLA's compilation to a thread of its own; an array argument may be a
`jax.ShapeDtypeStruct` for a value that another program of the call has yet to compute
(the specs of one program's results are those of the next one's arguments).  XLA releases
Python's lock while it compiles, and much of its work on one program (its HLO passes) runs
on one core, so an entry point whose first call compiles several programs gets them side by
side on a machine of several cores; each program's own call then finds its compilation in
JAX's caches.  Measured: `solve_boundary_value`'s solve and stability test, compiled side by
side (`_bvp/_solve.py`), first call of the cantilever of `benchmarks/bench_first_calls.py`
on 2 cores 5.2-6.2 -> 4.1-4.9 s (fresh processes alternating, an empty compilation cache).
On one core nothing is started.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import hashlib
import inspect
import os
import threading
from importlib import metadata

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _trace_cache


def _version(text: str) -> tuple[int, ...]:
    parts = []
    for piece in text.split(".")[:3]:
        digits = "".join(ch for ch in piece if ch.isdigit())
        parts.append(int(digits) if digits else 0)
    return tuple(parts)


#: Environment variable: set to ``0`` to compile with XLA's defaults (no `COMPILER_OPTIONS`).
OPTIONS_ENVIRONMENT_VARIABLE = "HELIXROD_COMPILER_OPTIONS"


def _jaxlib_version() -> tuple[int, ...]:
    try:
        return _version(metadata.version("jaxlib"))
    except metadata.PackageNotFoundError:
        return (0,)


def _settings_apply(environ=os.environ) -> bool:
    """Whether helixrod's XLA settings apply: not with `HELIXROD_COMPILER_OPTIONS=0`, and
    only on the jaxlib releases they were measured with (an option XLA does not know is a
    compile error)."""
    if environ.get(OPTIONS_ENVIRONMENT_VARIABLE, "1").strip() == "0":
        return False
    return _jaxlib_version() >= (0, 10)


def _compiler_options() -> dict[str, bool]:
    # jaxlib 0.11 dropped XLA's classic CPU emitters and the option with them (jaxlib 0.11.2:
    # "No such compile option" as a compiler option, "Unknown flag in XLA_FLAGS" and an abort
    # as a flag), so the option goes to the 0.10 releases only.
    return {"xla_cpu_use_fusion_emitters": False} if _settings_apply() and _jaxlib_version() < (0, 11) else {}


#: XLA options of every program helixrod compiles on its own (see the module docstring).
COMPILER_OPTIONS: dict[str, bool] = _compiler_options()

#: XLA options of a program run once per call of its entry point (`jit(..., run_once=True)`:
#: a fit's error analysis): `COMPILER_OPTIONS` at XLA's lowest optimisation level (LLVM at
#: level 0, without its expensive passes: what JAX's `jax_disable_most_optimizations` sets
#: for every program), where compiling costs seconds and running milliseconds.  Like
#: `COMPILER_OPTIONS`, on the releases measured only.
RUN_ONCE_OPTIONS: dict[str, bool | int] = (
    {**COMPILER_OPTIONS, "xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}
    if COMPILER_OPTIONS else {}
)

#: Byte threshold below which XLA's CPU backend compiles a `while` loop into one kernel.
SMALL_LOOP_BYTES = 1 << 20


def request_small_loop_kernels(environ=os.environ) -> bool:
    """Ask XLA (through ``XLA_FLAGS`` in `environ`) to compile `while` loops of up to
    `SMALL_LOOP_BYTES` into single kernels (see the module docstring).  Returns whether the
    flag was added: not when `HELIXROD_COMPILER_OPTIONS=0`, when jaxlib is older than the
    release it was measured with, or when ``XLA_FLAGS`` already sets XLA's backend extra
    options (the user's choice stands).  XLA reads the flag at the process's first
    compilation; after that it has no effect."""
    setting = f"xla_cpu_small_while_loop_byte_threshold={SMALL_LOOP_BYTES}"
    return _settings_apply(environ) and _add_xla_flag(environ, "xla_backend_extra_options", setting)


def _add_xla_flag(environ, name: str, value: str) -> bool:
    """Append ``--name=value`` to ``XLA_FLAGS`` in `environ` unless it already names `name`
    (the user's choice stands); whether it was added."""
    flags = environ.get("XLA_FLAGS", "")
    if name in flags:
        return False
    environ["XLA_FLAGS"] = f"{flags} --{name}={value}".strip()
    return True


#: The library fusions XLA's CPU backend may hand to YNNPACK (jaxlib 0.10.2: dots,
#: elementwise chains and reductions by default): dots only.
LIBRARY_FUSIONS = "dot"


def request_dot_library_fusions(environ=os.environ) -> bool:
    """Ask XLA's CPU backend (through ``XLA_FLAGS``) to hand only dots to its YNNPACK library
    fusions, not chains of elementwise operations (see the module docstring).  Returns whether
    the flag was added: on jaxlib 0.10.2 up to 0.11 only (the release it was measured with;
    an unknown flag in ``XLA_FLAGS`` aborts the process), not when
    `HELIXROD_COMPILER_OPTIONS=0`, and not when ``XLA_FLAGS`` already sets it."""
    measured = (0, 10, 2) <= _jaxlib_version() < (0, 11)
    return _settings_apply(environ) and measured and _add_xla_flag(environ, "xla_cpu_experimental_ynn_fusion_type", LIBRARY_FUSIONS)


try:  # No public JAX function tells whether a trace is active.
    from jax._src.core import trace_state_clean as _trace_state_clean
except ImportError:  # pragma: no cover - depends on the JAX release
    _trace_state_clean = None

try:  # ... nor leaves it for a computation on concrete values.
    from jax._src.core import eval_context as _eval_context
except ImportError:  # pragma: no cover - depends on the JAX release
    _eval_context = contextlib.nullcontext


def outside_transformations():
    """A context in which a call on concrete values (no tracers) is a top-level call, though
    a transformation is active (e.g. the primal part of an eager `jax.grad`, made concrete
    by `jax.lax.stop_gradient`): a `jit` or `filter_jit` of this module then compiles with
    its options and goes through the trace cache, as when called alone.  Without JAX's
    private context (a later JAX) it does nothing: the call takes the plain path."""
    return _eval_context()


def _at_top_level() -> bool:
    # Without the private function (moved or renamed in a later JAX) every call takes the
    # plain path.
    return _trace_state_clean is not None and _trace_state_clean()


def _compiles_for_cpu() -> bool:
    # The options name CPU settings, for the CPU only.  On a machine whose default
    # backend is a GPU, a program asked for on the CPU (`jax.default_device`) takes the plain
    # path too: compiled with XLA's defaults, correct, only slower to compile.
    return jax.default_backend() == "cpu"


#: Threads compiling programs ahead of their call (`compile_ahead`), by the function that
#: calls them: `[(signature, thread), ...]` (`_call_signature`).
_compiling: dict = {}


def _call_signature(args, kwargs) -> tuple:
    """What a program is compiled for, as far as `compile_ahead` tells two apart: the
    arguments' structure and their leaves' (shape, dtype), or the leaf itself where it is
    no array (a static argument)."""
    leaves, structure = jax.tree.flatten((args, kwargs))

    def part(leaf):
        if isinstance(leaf, (jax.Array, np.ndarray, np.generic, jax.ShapeDtypeStruct, int, float, complex)):
            return _shape_of(leaf)
        try:
            hash(leaf)
        except TypeError:
            return id(leaf)
        return leaf

    return structure, tuple(part(leaf) for leaf in leaves)


def _with_options(plain, tuned, options, traced_once=None):
    """`tuned` (compiled with `options`) at the top level on the CPU, else `plain`; with
    `traced_once` = (name, static argument names or `split_arrays`), a top-level call on the
    CPU goes through the trace cache (`_trace_cache.py`) when it is on.  The function
    returned has a `compile_ahead` method (`compile_ahead`)."""
    if not options and traced_once is None:
        return plain

    @functools.wraps(plain)
    def call(*args, **kwargs):
        if not _at_top_level():
            return plain(*args, **kwargs)
        if _compiling:
            _finish_compiling(call)
        cpu = _compiles_for_cpu()
        fallback = tuned if options and cpu else plain
        # The collector paused for the call (module docstring); left as the caller had it.
        collecting = gc.isenabled()
        gc.disable()
        try:
            if traced_once is not None and cpu and _trace_cache.enabled():
                name, static_argnames = traced_once
                return _trace_cache.cached_call(
                    plain, fallback, name, static_argnames, options if fallback is tuned else {}, args, kwargs
                )
            return fallback(*args, **kwargs)
        finally:
            if collecting:
                gc.enable()

    def ahead(*args, **kwargs):
        fallback = tuned if options else plain
        if not (_at_top_level() and _compiles_for_cpu() and hasattr(fallback, "trace")) or cores() < 2:
            return None
        # One compilation of a program at a time; one left running by a caller that raised
        # before its call does not keep another signature from compiling ahead.
        signature = _call_signature(args, kwargs)
        if any(running == signature and thread.is_alive() for running, thread in _compiling.get(call, ())):
            return None
        collecting = gc.isenabled()
        gc.disable()
        try:
            found = None
            if traced_once is not None and _trace_cache.enabled():
                name, static_argnames = traced_once
                found = _trace_cache.program_for(plain, name, static_argnames, options, args, kwargs)
            if found is not None:
                (program, out_tree), leaves = found
                traced = program.trace(*leaves)
                structure = jax.tree.unflatten(out_tree, traced.out_info)
                placement = _trace_cache.placement()
            else:
                traced = fallback.trace(*args, **kwargs)
                structure = traced.out_info
                placement = committed_placement((args, kwargs))
            lowered = traced.lower()
            structure = jax.tree.map(lambda a: _placed(a, placement), structure)
        except Exception:  # noqa: BLE001 - the call itself raises what is wrong, where it is
            return None
        finally:
            if collecting:
                gc.enable()
        thread = threading.Thread(target=_compile_quietly, args=(lowered,), name=f"helixrod-compile-{plain.__name__}")
        _compiling.setdefault(call, []).append((signature, thread))
        thread.start()
        return structure

    call.compile_ahead = ahead
    return call


@functools.cache
def cores() -> int:
    """The CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def compile_ahead(fun, *args, **kwargs):
    """Start compiling the program of `fun` (a `jit` of this module) for these arguments
    on a thread of its own, and return its output structure (`jax.ShapeDtypeStruct`
    leaves); an array argument may be a `jax.ShapeDtypeStruct` (a value another program
    has yet to compute).  The program is traced and lowered here, on the caller's thread
    (Python); XLA's compilation runs beside the caller, which meanwhile traces and compiles
    its other programs: on a machine of several cores, an entry point's first call whose
    programs compile side by side takes about as long as the longest compilation instead
    of their sum.  The next top-level call of `fun` waits for the compilation and finds it
    (JAX's caches are keyed by the program, which these specs reproduce); with different
    arguments it compiles its own, as it would have.  For first calls only: with the
    program compiled, this traces and lowers it again for nothing (JAX's caches make that
    fast, not free).  Returns None, starting nothing, where `fun` would not compile a
    top-level program of its own (inside a caller's transformation, not on the CPU), for a
    function of `filter_jit`, while a compilation of `fun` for the same arguments' types
    is running, where tracing fails (the call raises that error itself), and on one core
    (`cores`), where nothing runs beside the caller."""
    ahead = getattr(fun, "compile_ahead", None)
    return None if ahead is None else ahead(*args, **kwargs)


def once_per_signature(signature):
    """Decorator of a function that starts compiling an entry point's programs side by side
    (`compile_ahead`) and returns whether it started them: it runs at the first call of each
    `signature(*args)` (a hashable key of what the programs are compiled for), and again at
    the next call where it could not start them (inside a caller's transformation, on one
    core); once started, the calls with that signature find the programs in JAX's caches
    and it does nothing (calling `compile_ahead` again would trace and lower them for
    nothing)."""

    def decorate(start):
        started = set()

        @functools.wraps(start)
        def at_first_call(*args):
            key = signature(*args)
            if key not in started and start(*args):
                started.add(key)

        return at_first_call

    return decorate


def leaf_shapes(tree) -> tuple:
    """(shape, dtype) of every leaf of `tree`, JAX's promotion applied: the part of a
    `once_per_signature` key that says which arrays the programs are compiled for."""
    return tuple(_shape_of(a) for a in jax.tree.leaves(tree))


def _shape_of(leaf) -> tuple:
    """(shape, dtype) of an array-like leaf, JAX's promotion applied."""
    return jnp.shape(leaf), jnp.result_type(leaf)


def committed_placement(tree):
    """The placement of a program's results: that of a committed array argument (an array
    placed by `jax.device_put` or by a program whose arguments were, or the
    `jax.ShapeDtypeStruct` of one), else None (JAX leaves them uncommitted).  A program's
    signature includes whether its arguments are committed: a result spec without the
    placement would compile a program that the call with the result does not find."""
    for leaf in jax.tree.leaves(tree):
        if isinstance(leaf, jax.Array) and leaf.committed:
            return leaf.sharding
        if isinstance(leaf, jax.ShapeDtypeStruct) and leaf.sharding is not None:
            return leaf.sharding
    return None


def _placed(spec, placement):
    return jax.ShapeDtypeStruct(spec.shape, spec.dtype, sharding=placement, weak_type=getattr(spec, "weak_type", False))


def _compile_quietly(lowered) -> None:
    # An error here is raised again by the call, which compiles the program itself.
    try:
        lowered.compile()
    except Exception:  # noqa: BLE001
        pass


def _finish_compiling(call) -> None:
    """Wait for the compilations of `call`'s programs started by `compile_ahead`."""
    for _, thread in _compiling.pop(call, ()):
        thread.join()


def jit(fun=None, /, *, run_once: bool = False, trace_cache: bool = False, **kwargs):
    """`jax.jit` with `COMPILER_OPTIONS` (with `run_once`, `RUN_ONCE_OPTIONS`) at the top
    level on the CPU; usable as `@jit`, `@jit(static_argnames=...)` or `jit(fun, ...)`.
    `trace_cache`: top-level calls go through `_trace_cache.py` when the compilation cache
    is on (a large program that takes seconds to trace)."""
    if fun is None:
        return functools.partial(jit, run_once=run_once, trace_cache=trace_cache, **kwargs)
    options = RUN_ONCE_OPTIONS if run_once else COMPILER_OPTIONS
    traced_once = (f"{fun.__module__}.{fun.__qualname__}", _static_names(fun, kwargs)) if trace_cache else None
    return _with_options(jax.jit(fun, **kwargs), jax.jit(fun, compiler_options=options, **kwargs), options, traced_once)


def _static_names(fun, jit_kwargs) -> tuple[str, ...]:
    """The names of the static arguments of `jax.jit(fun, **jit_kwargs)`."""
    names = jit_kwargs.get("static_argnames", ())
    numbers = jit_kwargs.get("static_argnums", ())
    names = (names,) if isinstance(names, str) else tuple(names)
    numbers = (numbers,) if isinstance(numbers, int) else tuple(numbers)
    parameters = list(inspect.signature(fun).parameters)
    return names + tuple(parameters[i] for i in numbers)


def filter_jit(fun=None, /, *, trace_cache: bool = False, **kwargs):
    """`equinox.filter_jit` with `COMPILER_OPTIONS` at the top level; usable as `jit`
    (`trace_cache` as there)."""
    if fun is None:
        return functools.partial(filter_jit, trace_cache=trace_cache, **kwargs)
    tuned = eqx.filter_jit(fun, compiler_options=COMPILER_OPTIONS, **kwargs)
    traced_once = (f"{fun.__module__}.{fun.__qualname__}", split_arrays) if trace_cache else None
    return _with_options(eqx.filter_jit(fun, **kwargs), tuned, COMPILER_OPTIONS, traced_once)


class StaticHalf:
    """The non-array half of a pytree (`split_arrays`) as a `jax.jit` static argument,
    hashed and compared by its structure and leaves: equal halves find the same compiled
    program, as `equinox.filter_jit` arranges by splitting its arguments at every call."""

    def __init__(self, tree):
        self.leaves, self.treedef = jax.tree.flatten(tree)
        self._hash = hash((self.treedef, tuple(self.leaves)))

    def __hash__(self):
        return self._hash

    def __eq__(self, other):
        return isinstance(other, StaticHalf) and self.treedef == other.treedef and self.leaves == other.leaves

    def __repr__(self):  # the same text in every process (a key of `_trace_cache.py`)
        return f"StaticHalf({self.treedef}, {self.leaves!r})"

    def combine(self, arrays):
        """The whole pytree again, from its array half."""
        return eqx.combine(arrays, jax.tree.unflatten(self.treedef, self.leaves))


def split_arrays(tree):
    """`tree` as its array half and its `StaticHalf`: split once, for a program called many
    times with the same non-array half (a solver's steps), which then runs as a plain
    `jax.jit` (``static_argnums`` the `StaticHalf`).  `equinox.filter_jit` splits at every
    call instead; measured on a tweezer fit's model and on its solver step, ~0.2 ms a call."""
    arrays, static = eqx.partition(tree, eqx.is_array)
    return arrays, StaticHalf(static)


class TracedFunction:
    """A function of arrays as a static argument of a program (`jit`'s `static_argnames`),
    named by what it traces to: its jaxpr at `specs` (`jax.ShapeDtypeStruct`s of its
    arguments), the structure of its output, and the values of the arrays it closes over.

    A plain function is a static argument by identity: a new `lambda` with the same body at
    each call compiles the program again, and no text names it the same way in two
    processes, so the trace cache (`_trace_cache.py`) cannot keep a program that calls it.
    Two functions that trace to the same jaxpr with the same constants compute the same
    thing on those arguments, so the program traced with one serves the other: this
    object hashes, compares and prints (`repr`, the trace cache's key) by a digest of that
    trace.  Where the trace cannot be named that way -- it fails, or its text holds an object
    address (a custom derivative rule, a host callback) -- it falls back to the function's
    identity, and its `repr` (the function's own) keeps the trace cache away."""

    def __init__(self, fun, *specs):
        self.fun = fun
        self.digest = _trace_digest(fun, specs)

    def __call__(self, *args):
        return self.fun(*args)

    def __hash__(self):
        return hash(self.digest) if self.digest is not None else hash(self.fun)

    def __eq__(self, other):
        if not isinstance(other, TracedFunction):
            return NotImplemented
        if self.digest is None or other.digest is None:
            return self.fun is other.fun
        return self.digest == other.digest

    def __repr__(self):
        return f"TracedFunction({self.digest})" if self.digest is not None else repr(self.fun)


def _trace_digest(fun, specs) -> str | None:
    try:
        closed, out_shapes = jax.make_jaxpr(fun, return_shape=True)(*specs)
    except Exception:  # noqa: BLE001 - the program's own trace raises it where it matters
        return None
    text = f"{closed.jaxpr}\n{jax.tree.structure(out_shapes)}\n{[(s.shape, s.dtype.name) for s in specs]}"
    if " at 0x" in text or not _named_by_text(closed.jaxpr):
        return None
    digest = hashlib.sha256(text.encode())
    for constant in closed.consts:
        constant = np.asarray(constant)
        digest.update(f"{constant.shape}{constant.dtype.name}".encode())
        digest.update(np.ascontiguousarray(constant).tobytes())
    return digest.hexdigest()


# A `jit` inside the function holds its mesh, which is callable and named by its text.
_MESHES = (jax.sharding.Mesh, jax.sharding.AbstractMesh)


def _named_by_text(jaxpr) -> bool:
    """Whether the text of `jaxpr` says all it computes: no operation holds a function (a
    custom derivative rule, printed by its name only; a host callback), also in the jaxprs
    nested in its operations."""
    stack = [jaxpr]
    while stack:
        for equation in stack.pop().eqns:
            for value in equation.params.values():
                for item in value if isinstance(value, (tuple, list)) else (value,):
                    inner = getattr(item, "jaxpr", item)  # a closed jaxpr's own
                    if hasattr(inner, "eqns"):
                        stack.append(inner)
                    elif (callable(item) or hasattr(item, "call_wrapped")) and not isinstance(item, _MESHES):
                        return False
    return True
