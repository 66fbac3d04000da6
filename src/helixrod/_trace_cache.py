"""Traced programs on disk: a later process calls a large program without tracing it again.

The persistent compilation cache (`_cache.py`) saves XLA's compilation, not JAX's tracing and
lowering, which every process repeats before it can even look the program up: for the
shooting solve behind `solve_boundary_value` that is ~2.3 s of Python.  With the cache on, a
program made with `jit(..., trace_cache=True)` or `filter_jit(..., trace_cache=True)`
(`_compile.py`) is, at its first top-level call with a new signature, exported
(`jax.export`: traced and lowered once, as a plain call would) and saved as StableHLO beside
the compiled programs; a later process with the same signature deserialises it
(milliseconds) and compiles it, which the persistent cache answers.  Measured (fresh processes): the warm first call of `solve_boundary_value`
3.7 -> 1.5 s on one core (`benchmarks/bench_first_calls.py`), 3.5 -> 1.5 s on 2 cores; of
the shape fit of `benchmarks/bench_finite.py` (its Jacobian program traces in ~4.6 s)
19.5-20.8 -> 2.1 s on 2 cores, with its saved points free of host callbacks (now the dense
output of `_ode.py`, saved by the shooting solve's own integrations); of `force_extension` (8 points) 7.3-7.8 -> 4.3-4.7 s on 2 cores; of
`solve_static` 1.2 -> 0.47 s on one core.  The export costs the cold process 0.2-0.4 s more
than a plain trace and lowering; a signature lookup costs a later call 0.02-0.08 ms.

What makes a signature, and why a stale file cannot be used: the file's name is a hash of
the program's name, the structure of its arguments (every pytree node and its static data,
e.g. a solve's options), the shapes and dtypes of their arrays, the static arguments, the
versions of JAX, jaxlib and the libraries helixrod traces through, a digest of helixrod's
own source, JAX's float precision and backend, and the compiler options.  Only arguments
built from helixrod's own types (and JAX's, equinox's, diffrax's, optimistix's, lineax's)
are cached: a user's constitutive law, whose code the hash cannot see, always takes the
plain path, as does anything a hash cannot name the same way in two processes (a callable).

Anything that goes wrong (an argument that is not an array, a file that cannot be read or
written) falls back to the plain call, silently.  A program that `jax.export` refuses (a
host callback, e.g. a check that raises at run time, or a custom call such as the register
kernel's) costs the first process of its signature a second trace; the refusal is saved,
and later processes take the plain path at once.  Inside a caller's `jit`, `vmap` or `grad`
the plain call is used (an exported program has no batching rule), and so it is on a
machine whose default backend is not the CPU.  The files (pickled records: the cache
directory is trusted as JAX's own cache of executables is) are safe to delete at any time.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import io
import os
import pickle
from importlib import metadata
from pathlib import Path

import jax
import numpy as np

#: Sub-directory of the compilation cache that holds the exported programs.
SUBDIRECTORY = "helixrod-traces"

#: Top-level packages whose pytree nodes may appear in a cached program's arguments.
KNOWN_PACKAGES = ("helixrod", "jax", "jaxlib", "equinox", "diffrax", "optimistix", "lineax", "numpy", "builtins", "collections")

_LIBRARIES = ("jax", "jaxlib", "equinox", "diffrax", "optimistix", "lineax", "numpy")

#: Environment variables that change what a program traces to.
_ENVIRONMENT = ("EQX_ON_ERROR", "HELIXROD_REGISTER_KERNEL", "HELIXROD_COMPILER_OPTIONS")

_directory: Path | None = None
_programs: dict[str, tuple] = {}  # signature -> (compiled call, output structure)
_signatures: dict[tuple, str] = {}  # (name, structure, leaves, statics, precision) -> signature
_refused: set[str] = set()  # signatures that could not be exported
#: Counts of what the cache did in this process (for the tests and benchmarks).
counts = {"exported": 0, "loaded": 0, "refused": 0}


def enable(directory: str | os.PathLike | None) -> None:
    """Keep exported programs under `directory` / `SUBDIRECTORY` (`None`: stop)."""
    global _directory
    _directory = None if directory is None else Path(directory) / SUBDIRECTORY


def enabled() -> bool:
    """On (`enable`), with `jax.export`'s serialisation available, and no default device
    chosen by the caller (`jax.default_device`: an exported program is placed on the
    first device of the default backend, `_compiled`)."""
    return _directory is not None and jax.config.jax_default_device is None and _serialisation_available()


@functools.cache
def _serialisation_available() -> bool:
    try:  # jax.export's serialisation needs the optional `flatbuffers` package
        from jax._src.export import serialization  # noqa: F401
    except ImportError:
        return False
    return _missing_sentinel() is not None


@functools.cache
def _missing_sentinel():
    """equinox's placeholder in a Module's static data, which a pickled structure must map
    back to the very object (equinox tests it by identity); None where it cannot be found."""
    try:
        from equinox._module._flatten import MISSING
    except ImportError:
        return None
    return MISSING


@functools.cache
def _environment_digest() -> str:
    """Versions of the libraries a program is traced through, and helixrod's source."""
    digest = hashlib.sha256()
    for name in _LIBRARIES:
        try:
            digest.update(f"{name}={metadata.version(name)};".encode())
        except metadata.PackageNotFoundError:
            digest.update(f"{name}=none;".encode())
    root = Path(__file__).parent
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def _vouched(value) -> bool:
    """Whether `value` (static data) is built from types of `KNOWN_PACKAGES` only: the
    digest sees their code, not that of a user's type (whose repr may not change with it)."""
    if isinstance(value, (tuple, list, frozenset, set)):
        return all(_vouched(item) for item in value)
    if isinstance(value, dict):
        return all(_vouched(key) and _vouched(item) for key, item in value.items())
    kind = value if isinstance(value, type) else type(value)
    return getattr(kind, "__module__", "").split(".")[0] in KNOWN_PACKAGES


def _known_nodes(treedef) -> bool:
    """Whether every node of `treedef` and its static data are `_vouched` and have a text
    that names them the same way in every process (no object addresses)."""
    if " at 0x" in str(treedef):
        return False
    stack = [treedef]
    while stack:
        node = stack.pop()
        data = node.node_data()
        if data is not None and not (_vouched(data[0]) and _vouched(data[1])):
            return False
        stack.extend(node.children())
    return True


def _static_text(statics: dict) -> str | None:
    """The static arguments as text that names them the same way in every process, or None
    where it cannot: an object address in a repr (a callable), or a value that is not
    `_vouched`, also inside a `StaticHalf` (`_compile.split_arrays`)."""
    for value in statics.values():
        treedef = getattr(value, "treedef", None)
        if isinstance(treedef, jax.tree_util.PyTreeDef):
            if not (_known_nodes(treedef) and _vouched(list(getattr(value, "leaves", ())))):
                return None
        elif not _vouched(value):
            return None
    text = repr(sorted(statics.items()))
    return None if " at 0x" in text else text


def _leaf_signature(leaf) -> tuple | None:
    """(shape, dtype, weak type) of an array leaf (or of a `jax.ShapeDtypeStruct` standing
    for one); None for anything else."""
    if isinstance(leaf, (jax.Array, jax.ShapeDtypeStruct)):
        return (leaf.shape, leaf.dtype.name, leaf.weak_type)
    if isinstance(leaf, (np.ndarray, np.generic)):
        return (leaf.shape, leaf.dtype.name, False)
    if isinstance(leaf, (bool, int, float, complex)):  # weakly typed, of the precision JAX runs in
        return ((), type(leaf).__name__, True)
    return None


class _Pickler(pickle.Pickler):
    def persistent_id(self, obj):
        return "equinox-missing" if obj is _missing_sentinel() else None


class _Unpickler(pickle.Unpickler):
    def persistent_load(self, pid):
        if pid != "equinox-missing":
            raise pickle.UnpicklingError(f"unknown persistent id {pid!r}")
        return _missing_sentinel()


def _dumps(obj) -> bytes:
    out = io.BytesIO()
    _Pickler(out, protocol=pickle.HIGHEST_PROTOCOL).dump(obj)
    return out.getvalue()


def _loads(data: bytes):
    return _Unpickler(io.BytesIO(data)).load()


@functools.cache
def _parameters(plain) -> inspect.Signature:
    return inspect.signature(plain)


#: The entry of the static arguments that holds the static half of a call split by a
#: function (`cached_call`'s `static_argnames` a callable).
FILTERED = "filtered"


def _split(arguments: dict, static_argnames):
    """(dynamic arguments, static arguments) of a call: by name, or by the function
    `static_argnames` (`_compile.split_arrays` for an `equinox.filter_jit` program: the
    array leaves against the rest), whose static half is the one entry `FILTERED`."""
    if callable(static_argnames):
        arrays, static = static_argnames(arguments)
        return arrays, {FILTERED: static}
    statics = {key: value for key, value in arguments.items() if key in static_argnames}
    return {key: value for key, value in arguments.items() if key not in static_argnames}, statics


def _call(plain, dynamic: dict, statics: dict):
    if FILTERED in statics:
        return plain(**statics[FILTERED].combine(dynamic))
    return plain(**dynamic, **statics)


def cached_call(plain, fallback, name: str, static_argnames, compiler_options: dict, args, kwargs):
    """`plain(*args, **kwargs)` (a `jax.jit` function, or with `static_argnames` a function
    that splits the arguments, an `equinox.filter_jit` one; top-level call) through the
    exported program of its signature, compiled with `compiler_options`, when the cache
    holds one or can make one; else `fallback(*args, **kwargs)` (the same program)."""
    found = program_for(plain, name, static_argnames, compiler_options, args, kwargs)
    if found is None:
        return fallback(*args, **kwargs)
    (call, out_tree), leaves = found
    return jax.tree.unflatten(out_tree, call(*leaves))


def program_for(plain, name: str, static_argnames, compiler_options: dict, args, kwargs):
    """The program a top-level call `plain(*args, **kwargs)` goes through (as `cached_call`)
    and the call's array leaves: `((compiled call, output structure), leaves)`; None where
    the call takes the plain path.  An array leaf may be a `jax.ShapeDtypeStruct`, for a
    program compiled ahead of its call (`_compile.py`)."""
    try:
        bound = _parameters(plain).bind(*args, **kwargs)
    except (TypeError, ValueError):
        return None
    bound.apply_defaults()
    try:
        dynamic, statics = _split(dict(bound.arguments), static_argnames)
    except TypeError:  # an unhashable static leaf: the plain call says what it makes of it
        return None
    leaves, treedef = jax.tree.flatten(dynamic)
    avals = tuple(_leaf_signature(leaf) for leaf in leaves)
    if any(a is None for a in avals):
        return None
    try:  # this process's index of the signatures it has met (hashing the text costs more)
        seen = (name, treedef, avals, tuple(sorted(statics.items())), jax.config.jax_enable_x64)
        signature = _signatures.get(seen)
    except TypeError:  # an unhashable static argument
        seen = signature = None
    if signature is None:
        static_text = _static_text(statics)
        if static_text is None or not _known_nodes(treedef):
            return None
        text = "|".join([
            name, str(treedef), repr(avals), static_text, _environment_digest(),
            str(jax.config.jax_enable_x64), jax.default_backend(), repr(sorted(compiler_options.items())),
            repr([os.environ.get(v) for v in _ENVIRONMENT]),
        ])
        signature = hashlib.sha256(text.encode()).hexdigest()
        if seen is not None:
            _signatures[seen] = signature
    program = _programs.get(signature)
    if program is None:
        if signature in _refused or (_directory / f"{signature}.refused").exists():
            _refused.add(signature)
            return None
        program = _load(signature, name, compiler_options) or _export(signature, name, plain, treedef, statics, leaves, compiler_options)
    return None if program is None else (program, leaves)


def _load(signature: str, name: str, compiler_options: dict):
    path = _directory / f"{signature}.export"
    try:
        record = _loads(path.read_bytes())
        exported = jax.export.deserialize(record["exported"])
        out_tree = _loads(record["out_tree"])
    except Exception:  # a missing, partial or foreign file: export again
        return None
    program = (_compiled(exported, compiler_options, name), out_tree)
    _programs[signature] = program
    counts["loaded"] += 1
    return program


def _export(signature: str, name: str, plain, treedef, statics: dict, leaves, compiler_options: dict):
    """Export, save and compile the program of `signature`; None where `jax.export` refuses
    it (a host callback, a custom call such as the register kernel's): the refusal is saved
    too, so that later processes take the plain path at once (this one traces the program
    again for it, once: compiling the flat program it has traced instead would store a
    compilation that the plain path of later processes cannot find)."""
    out_trees = []

    def flat(*flat_leaves):
        out = _call(plain, jax.tree.unflatten(treedef, flat_leaves), statics)
        out_leaves, out_tree = jax.tree.flatten(out)
        out_trees.append(out_tree)
        return out_leaves

    avals = [leaf if isinstance(leaf, jax.ShapeDtypeStruct) else jax.typeof(leaf) for leaf in leaves]
    shapes = [jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=getattr(a, "weak_type", False)) for a in avals]
    try:
        exported = jax.export.export(jax.jit(flat))(*shapes)
        record = {"exported": exported.serialize(), "out_tree": _dumps(out_trees[-1])}
    except Exception:
        if out_trees:  # traced, then refused (else the trace failed: the plain call raises its error)
            _refused.add(signature)
            counts["refused"] += 1
            _write(_directory / f"{signature}.refused", b"")
        return None
    _write(_directory / f"{signature}.export", _dumps(record))
    program = (_compiled(exported, compiler_options, name), out_trees[-1])
    _programs[signature] = program
    counts["exported"] += 1
    return program


def _compiled(exported, compiler_options: dict, name: str):
    """The exported program as a `jax.jit` function on the default device, named after the
    function it was traced from (`name`: what JAX's logs, profiles and XLA's dumps show).
    Its placement is fixed: left open, an argument already placed by an earlier program
    (committed) and one made from NumPy (not) lowered to two programs, compiled twice
    (measured: the shape fit's Jacobian, 13 s each)."""

    def program(*leaves):
        return exported.call(*leaves)

    program.__name__ = program.__qualname__ = name.rsplit(".", 1)[-1]
    return jax.jit(program, in_shardings=placement(), compiler_options=compiler_options or None)


def placement():
    """Where an exported program runs, its arguments and results lie: the first device of
    the default backend (its results are committed there)."""
    return jax.sharding.SingleDeviceSharding(jax.devices()[0])


def _write(path: Path, data: bytes) -> None:
    """`data` to `path` atomically (a reader sees the whole file or none); an unwritable
    cache costs the next process a trace, nothing else."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(f".{os.getpid()}.partial")
        partial.write_bytes(data)
        partial.replace(path)
    except OSError:
        pass
