"""The kappa-tau atlas: every uniform helical equilibrium over a grid, streamed in chunks,
sharded over devices, and its forward-mode sensitivities to the rod's parameters.

Everything here is built on the public `helix_equilibria`: a chunk is one call of it on a
flat batch of grid points, jitted once and reused for every chunk.  Only the requested
fields are returned by the jitted function, so XLA removes the work of the others (dead
code elimination; `benchmarks/bench_sweep.py` measures it).
"""

from __future__ import annotations

import collections.abc
import functools
import json
import zipfile
from collections.abc import Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ._compile import jit
from ._equilibria import helix_equilibria
from ._misc import write_atomically
from ._progress import ProgressArgument, check_progress, progress_bar
from ._rod import PARAMETER_NAMES, Rod, check_quadratic_rod, rod_from_vector, rod_vector

#: Per-register fields (shape ``(len(kappa), len(tau), 4)``), with their numpy dtypes.
REGISTER_FIELDS = {
    "phi": np.float64,
    "valid": np.bool_,
    "force": np.float64,
    "moment": np.float64,
    "tension": np.float64,
    "energy": np.float64,
    "stable": np.bool_,
}
#: Per-point fields (shape ``(len(kappa), len(tau))``).
POINT_FIELDS = {
    "count": np.int8,
    "stable_count": np.int8,
    "continuum": np.bool_,
    "straight": np.bool_,
    "stable_phi": np.float64,
    "stable_force": np.float64,
    "stable_moment": np.float64,
}
FIELDS = tuple(REGISTER_FIELDS) + tuple(POINT_FIELDS)
DEFAULT_FIELDS = ("force", "moment", "stable", "count")
# Points per device in one chunk: large enough to amortise dispatch, small enough that a
# chunk's temporaries stay at tens of MB (measured in tests/test_sweep.py).
_POINTS_PER_DEVICE = 1 << 16
# On an accelerator each chunk is a round of kernel launches and a transfer: larger
# chunks (measured on an H100, benchmarks/bench_device.py).
_POINTS_PER_ACCELERATOR = 1 << 22
_AXIS = "points"


def _check_fields(fields) -> tuple[str, ...]:
    if isinstance(fields, str):
        fields = (fields,)
    fields = tuple(fields)
    unknown = [f for f in fields if f not in FIELDS]
    if unknown:
        raise ValueError(f"sweep: unknown field(s) {unknown}; valid fields are {list(FIELDS)}")
    if not fields:
        raise ValueError(f"sweep: no fields requested; valid fields are {list(FIELDS)}")
    return tuple(dict.fromkeys(fields))  # unique, in the order asked


def _check_axis(name, x, caller="sweep") -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 1 or x.size == 0:
        raise ValueError(f"{caller}: {name} must be a non-empty 1-D grid axis, got shape {x.shape}")
    return x  # non-finite values are points flagged as no helix (tests/test_stress.py)


def _check_rod(rod, caller="sweep") -> None:
    check_quadratic_rod(rod, caller)
    if jnp.shape(rod.K1) != ():
        raise ValueError(f"{caller}: rod must be a single rod (batch shape ()), got batch shape {jnp.shape(rod.K1)}")


def _equilibrium_fields(rod: Rod, kappa, tau, fields: tuple[str, ...]) -> dict:
    """The requested fields at flat points (kappa, tau), shape (n,) each."""
    branch = [f for f in ("stable_phi", "stable_force", "stable_moment") if f in fields]
    # Only what they are made of: with the compiled kernel, fields among phi, valid, force,
    # moment and stable (the default sweep's) are one pass of it instead of XLA's program.
    needed = {name for name in fields if name in REGISTER_FIELDS} | {
        field for name, field in (("count", "valid"), ("stable_count", "stable"), ("continuum", "continuum"),
                                  ("straight", "straight")) if name in fields
    }
    if branch:
        needed |= {"stable", "energy"} | {name.removeprefix("stable_") for name in branch}
    eq = helix_equilibria(rod, kappa, tau, fields=tuple(sorted(needed)))
    out = {}
    for name in fields:
        if name in REGISTER_FIELDS:
            out[name] = getattr(eq, name)
    if "count" in fields:
        out["count"] = jnp.sum(eq.valid, axis=-1, dtype=jnp.int8)
    if "stable_count" in fields:
        out["stable_count"] = jnp.sum(eq.stable, axis=-1, dtype=jnp.int8)
    if "continuum" in fields:
        out["continuum"] = eq.continuum
    if "straight" in fields:
        out["straight"] = eq.straight
    if branch:
        # The stable branch: the stable register of least energy (the global minimum of W
        # on the constraint circle whenever it is a strict minimum).  NaN where no register
        # is stable: straight, invalid, continuum (a neutral family) points.
        energy = jnp.where(eq.stable, eq.energy, jnp.inf)
        best = jnp.argmin(energy, axis=-1)[..., None]
        has = jnp.any(eq.stable, axis=-1)
        for name in branch:
            value = jnp.take_along_axis(getattr(eq, name.removeprefix("stable_")), best, axis=-1)[..., 0]
            out[name] = jnp.where(has, value, jnp.nan)
    return out


def _mesh(devices) -> Mesh:
    return Mesh(np.asarray(devices), (_AXIS,))


@functools.lru_cache(maxsize=64)
def _chunk_function(point_fn: Callable, devices: tuple, chunk: int) -> Callable:
    """Jitted `(rod, kappa_axis, tau_axis, n_tau, last, offset) -> dict` evaluating the
    grid points `offset ... offset + chunk - 1` (row-major over (kappa, tau); indices past
    `last` are clipped to it; `n_tau` is the true length of the padded tau axis), sharded over `devices`: each device builds and solves its own slice of
    indices, so nothing but the results crosses between devices or to the host."""
    mesh = _mesh(devices)
    local = chunk // len(devices)

    def per_device(rod, kappa_axis, tau_axis, n_tau, last, offset):
        start = offset + jax.lax.axis_index(_AXIS) * local
        index = jnp.minimum(start + jnp.arange(local, dtype=start.dtype), last)
        return point_fn(rod, kappa_axis[index // n_tau], tau_axis[index % n_tau])

    sharded = jax.shard_map(
        per_device,
        mesh=mesh,
        in_specs=(PartitionSpec(),) * 6,
        out_specs=PartitionSpec(_AXIS),
        # The register root's custom_jvp returns float0 tangents for its boolean outputs
        # without the varying-axis annotation shard_map's type check asks for.
        check_vma=False,
    )
    replicated = NamedSharding(mesh, PartitionSpec())
    return jit(sharded, in_shardings=replicated, out_shardings=NamedSharding(mesh, PartitionSpec(_AXIS)))


def _stream(point_fn, rod, kappa, tau, trailing: Mapping, chunk_size, progress, devices, description) -> dict:
    """Evaluate `point_fn` over the grid in fixed-size chunks; returns numpy arrays of
    shape `(len(kappa), len(tau)) + trailing[name][0]` and dtype `trailing[name][1]`."""
    devices = tuple(jax.local_devices() if devices is None else devices)
    if not devices:
        raise ValueError(f"{description}: devices must name at least one device (default: jax.local_devices())")
    n_dev = len(devices)
    total = kappa.size * tau.size
    if chunk_size is None:
        # Small grids: the next power of two, so that similar sizes share one compile.
        per_device = _POINTS_PER_DEVICE if devices[0].platform == "cpu" else _POINTS_PER_ACCELERATOR
        chunk = min(per_device * n_dev, max(256, 1 << (total - 1).bit_length()))
    else:
        chunk = int(chunk_size)
        if chunk < 1:
            raise ValueError(f"chunk_size must be a positive integer, got {chunk_size}")
    chunk = -(-chunk // n_dev) * n_dev  # a whole number of points per device
    fn = _chunk_function(point_fn, devices, chunk)
    replicated = NamedSharding(_mesh(devices), PartitionSpec())
    index_dtype = jnp.int64 if total >= 2**31 - chunk else jnp.int32
    if total >= 2**31 - chunk and not jax.config.jax_enable_x64:
        raise ValueError("sweep: grids of 2**31 points or more need jax_enable_x64")
    # The axes travel padded to a power of two (their true lengths as values), so grids of
    # similar size share one compiled function.
    args = jax.device_put(
        (rod, _padded(kappa), _padded(tau), jnp.asarray(tau.size, index_dtype), jnp.asarray(total - 1, index_dtype)),
        replicated,
    )
    out = {
        name: np.empty((kappa.size, tau.size) + tuple(shape), dtype=dtype) for name, (shape, dtype) in trailing.items()
    }
    flat = {name: a.reshape((total,) + a.shape[2:]) for name, a in out.items()}
    starts = range(0, total, chunk)

    def collect(start, result, report):
        stop = min(start + chunk, total)
        for name, a in result.items():
            flat[name][start:stop] = np.asarray(a)[: stop - start]
        report.advance(stop - start)

    with progress_bar(description, total, progress, owner=description, auto=len(starts) > 1) as report:
        pending = None
        for start in starts:
            # Dispatch the next chunk before copying out the last: device and host overlap.
            result = fn(*args, jnp.asarray(start, index_dtype))
            if pending is not None:
                collect(*pending, report)
            pending = (start, result)
        collect(*pending, report)
    return out


def _padded(axis: np.ndarray) -> jax.Array:
    size = max(256, 1 << (axis.size - 1).bit_length())
    return jnp.asarray(np.pad(axis, (0, size - axis.size), mode="edge"))


class SweepResult(collections.abc.Mapping):
    """The result of `sweep`: a read-only mapping of field name to numpy array, plus the
    `rod`, the grid axes `kappa` and `tau`, and `fields` (the names, in order).
    Per-register fields have shape `(len(kappa), len(tau), 4)`, per-point fields
    `(len(kappa), len(tau))`; `result["force"][i, j]` belongs to `(kappa[i], tau[j])`.
    The fields a sweep can return: `SweepResult.REGISTER_FIELDS`, `SweepResult.POINT_FIELDS`
    (name -> numpy dtype) and all of them, `SweepResult.FIELDS`."""

    REGISTER_FIELDS = REGISTER_FIELDS
    POINT_FIELDS = POINT_FIELDS
    FIELDS = FIELDS

    def __init__(self, rod: Rod, kappa: np.ndarray, tau: np.ndarray, arrays: Mapping[str, np.ndarray]):
        self.rod = rod
        self.kappa = kappa
        self.tau = tau
        self._arrays = dict(arrays)

    @property
    def fields(self) -> tuple[str, ...]:
        return tuple(self._arrays)

    def __getitem__(self, name):
        return self._arrays[name]

    def __iter__(self):
        return iter(self._arrays)

    def __len__(self):
        return len(self._arrays)

    def __repr__(self):
        shapes = ", ".join(f"{k}: {v.dtype}{list(v.shape)}" for k, v in self._arrays.items())
        return f"SweepResult(kappa[{self.kappa.size}], tau[{self.tau.size}]; {shapes})"


def sweep(
    rod: Rod,
    kappa: Sequence[float] | np.ndarray,
    tau: Sequence[float] | np.ndarray,
    *,
    fields: Sequence[str] = DEFAULT_FIELDS,
    chunk_size: int | None = None,
    progress: ProgressArgument = None,
    devices: Sequence[jax.Device] | None = None,
) -> SweepResult:
    """Every uniform helical equilibrium of `rod` over the grid `kappa` x `tau`.

    `kappa` and `tau` are 1-D grid axes (1/length, like the rod's twists); point `(i, j)`
    is the helix of curvature `kappa[i]` and torsion `tau[j]`.  Returns a `SweepResult`,
    a mapping of numpy arrays holding only the requested `fields`:

    per register, shape `(len(kappa), len(tau), 4)`, slots as in `HelixEquilibria`
    (0 global minimum of $W$ on the circle, 1 global maximum, 2/3 inner local
    minimum/maximum; NaN/False in unused slots):
      `phi`, `valid`, `force` ($F = n\\cdot a$), `moment` ($M = m\\cdot a$), `tension`,
      `energy`, `stable`;
    per point, shape `(len(kappa), len(tau))`:
      `count` (int8: number of valid registers, 2, 3 or 4 for $\\kappa > 0$; 1 for a
      continuum, 0 straight or invalid), `stable_count` (int8), `continuum`, `straight`,
      and the **stable branch** `stable_phi`, `stable_force`, `stable_moment`: the stable
      register of least energy, i.e. the global minimum of $W$ on the constraint circle
      (NaN where no register is stable: $\\kappa = 0$, a continuum, invalid input).

    Only the requested fields are computed: the jitted chunk returns nothing else, so XLA
    drops the arithmetic of the others.  Unknown names raise `ValueError`.

    **Streaming.**  The grid is evaluated in chunks of `chunk_size` points (default
    65536 per CPU device, 4194304 per accelerator), one compiled function reused for every chunk (the last is padded
    by repeating the final point, and trimmed), so memory is the output arrays plus one
    chunk of temporaries.

    **Progress.**  `progress=None` (default) shows a rich progress bar when there is more
    than one chunk and stdout is a terminal; `True`/`False` force it on or off; a callable
    is called as `progress(done, total)` (grid points) after each chunk, instead of a bar.

    **Devices.**  Each chunk is split evenly over `devices` (default
    `jax.local_devices()`) with a `NamedSharding` over a 1-D mesh; every device builds its
    own slice of grid points from the two axes, so only results move.  The results do
    not depend on the number of devices (bit for bit).

    **Many hosts.**  The atlas is embarrassingly parallel, so with `jax.distributed` the
    simplest correct recipe splits the `kappa` axis over processes, each sweeping its rows
    on its own local devices:

    ```python
    jax.distributed.initialize()            # on every host (env vars or arguments)
    rows = np.array_split(kappa, jax.process_count())[jax.process_index()]
    part = helixrod.sweep(rod, rows, tau)   # uses this host's devices only
    helixrod.save_sweep(f"atlas-{jax.process_index()}.npz", part)
    ```

    and the parts are concatenated along axis 0 (in process order) afterwards, or
    gathered in memory with `jax.experimental.multihost_utils.process_allgather`.

    **Example**

    ```python
    rod = helixrod.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
    atlas = helixrod.sweep(rod, np.linspace(0, 3, 301), np.linspace(-3, 3, 601))
    atlas["count"].shape, atlas["force"].shape      # (301, 601), (301, 601, 4)
    ```
    """
    fields = _check_fields(fields)
    _check_rod(rod)
    check_progress(progress, "sweep")
    kappa = _check_axis("kappa", kappa)
    tau = _check_axis("tau", tau)
    trailing = {
        name: (((4,), REGISTER_FIELDS[name]) if name in REGISTER_FIELDS else ((), POINT_FIELDS[name]))
        for name in fields
    }
    point_fn = _equilibrium_point_fn(fields)
    arrays = _stream(point_fn, rod, kappa, tau, trailing, chunk_size, progress, devices, "sweep")
    return SweepResult(rod, kappa, tau, arrays)


@functools.lru_cache(maxsize=64)
def _equilibrium_point_fn(fields: tuple[str, ...]) -> Callable:
    # Cached so that the same fields give the same function object, hence one compile.
    return functools.partial(_equilibrium_fields, fields=fields)


# -- save / load --------------------------------------------------------------------------

def save_sweep(path, result: SweepResult) -> None:
    """Write a `SweepResult` to an `.npz` file: every field under `field/<name>`, the grid
    axes `kappa`, `tau`, the rod as `rod` = (K1, K2, K3, K13, K23, uhat1, uhat2, uhat3),
    and a JSON `meta` string (format version, field names, rod keys).  No pickles.  The file
    is written to a temporary file beside `path` and renamed over it (an interrupted write
    leaves a previous file whole); `path` is used as given (no `.npz` is appended)."""
    meta = {"format": "helixrod.sweep", "version": 1, "fields": list(result.fields), "rod_keys": list(PARAMETER_NAMES)}
    arrays = {f"field/{name}": result[name] for name in result.fields}
    rod = np.asarray(rod_vector(result.rod), np.float64)
    write_atomically(
        path, lambda file: np.savez(file, kappa=result.kappa, tau=result.tau, rod=rod, meta=np.asarray(json.dumps(meta)), **arrays)
    )


def load_sweep(path) -> SweepResult:
    """Read a file written by `save_sweep` and return the `SweepResult` (fields, grid axes and
    rod as saved).  Raises `ValueError` for a file that is not a helixrod sweep; never
    unpickles."""
    not_a_sweep = f"load_sweep: {path} is not a helixrod sweep file (written by save_sweep or helixrod sweep --out)"
    try:
        archive = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise
    except ValueError:  # numpy's reading of any other file: "contains pickled data"
        raise ValueError(f"{not_a_sweep}: not a NumPy .npz archive") from None
    except (OSError, EOFError, zipfile.BadZipFile) as error:  # truncated, unreadable
        raise ValueError(f"{not_a_sweep}: {error}") from None
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise ValueError(f"{not_a_sweep}: a single array, not an archive")
    with archive as data:
        try:
            meta = json.loads(str(data["meta"]))
        except (KeyError, ValueError, json.JSONDecodeError):
            raise ValueError(f"{not_a_sweep}: no readable 'meta' entry") from None
        if not isinstance(meta, dict) or meta.get("format") != "helixrod.sweep":
            raise ValueError(not_a_sweep)
        try:
            p = data["rod"]
            arrays = {name: data[f"field/{name}"] for name in meta["fields"]}
            kappa, tau = data["kappa"], data["tau"]
        except (KeyError, ValueError, EOFError, zipfile.BadZipFile) as error:
            raise ValueError(f"load_sweep: {path} is damaged ({error})") from None
        rod = rod_from_vector(p, checked=True)
        return SweepResult(rod, kappa, tau, arrays)


# -- sensitivities ------------------------------------------------------------------------

#: Parameters `sensitivity` can differentiate with respect to ("uhat" = all three).
PARAMETERS = PARAMETER_NAMES


def _check_wrt(wrt) -> tuple[str, ...]:
    if isinstance(wrt, str):
        wrt = (wrt,)
    names = []
    for w in wrt:
        if w == "uhat":
            names += ["uhat1", "uhat2", "uhat3"]
        elif w in PARAMETER_NAMES:
            names.append(w)
        else:
            raise ValueError(f"sensitivity: unknown parameter {w!r}; valid are {list(PARAMETER_NAMES)} and 'uhat'")
    if not names:
        raise ValueError("sensitivity: wrt is empty")
    return tuple(dict.fromkeys(names))


def _sensitivity_fields(rod: Rod, kappa, tau, wrt: tuple[str, ...]) -> dict:
    base = jnp.concatenate([jnp.stack([rod.K1, rod.K2, rod.K3, rod.K13, rod.K23]), rod.uhat])
    which = jnp.asarray([PARAMETER_NAMES.index(w) for w in wrt])

    def quantities(theta):
        p = base.at[which].set(theta)
        eq = helix_equilibria(rod_from_vector(p), kappa, tau)
        return eq.force, eq.moment, eq.phi

    theta = base[which]
    (force, moment, phi), (d_force, d_moment, d_phi) = _value_and_jacfwd(quantities, theta)
    valid = jnp.isfinite(phi)[..., None]
    d_force, d_moment, d_phi = (jnp.where(valid, d, jnp.nan) for d in (d_force, d_moment, d_phi))
    theta = theta.reshape((1,) * force.ndim + theta.shape)
    return {
        "force": force,
        "moment": moment,
        "phi": phi,
        "d_force": d_force,
        "d_moment": d_moment,
        "d_phi": d_phi,
        "force_elasticity": theta * d_force / force[..., None],
        "moment_elasticity": theta * d_moment / moment[..., None],
    }


def _value_and_jacfwd(f, x):
    """Values and Jacobians (trailing axis = len(x)) by one jvp per basis direction."""
    basis = jnp.eye(x.shape[0], dtype=x.dtype)
    values = f(x)
    tangents = jax.vmap(lambda v: jax.jvp(f, (x,), (v,))[1], out_axes=-1)(basis)
    return values, tangents


@functools.lru_cache(maxsize=64)
def _sensitivity_point_fn(wrt: tuple[str, ...]) -> Callable:
    return functools.partial(_sensitivity_fields, wrt=wrt)


class Sensitivity(collections.abc.Mapping):
    """The result of `sensitivity`: a read-only mapping of numpy arrays over the grid.

    `force`, `moment`, `phi`: shape `(len(kappa), len(tau), 4)` (as in `sweep`);
    `d_force`, `d_moment`, `d_phi`: derivatives, shape `(len(kappa), len(tau), 4, P)`, the
    last axis running over `wrt`; `force_elasticity`, `moment_elasticity`: the normalised
    sensitivities $(\\theta/F)\\,\\partial F/\\partial\\theta$, same shape.  `wrt`,
    `kappa`, `tau`, `rod` as given.  `self.of("K13", "d_force")` picks one parameter."""

    def __init__(self, rod, kappa, tau, wrt, arrays):
        self.rod, self.kappa, self.tau, self.wrt = rod, kappa, tau, wrt
        self._arrays = dict(arrays)

    def of(self, parameter: str, name: str = "force_elasticity") -> np.ndarray:
        """The slice of output `name` (a derivative or elasticity field) for one parameter
        of `wrt`: shape `(len(kappa), len(tau), 4)`, one value per register slot."""
        if parameter not in self.wrt:
            raise ValueError(f"sensitivity: {parameter!r} is not among the parameters differentiated, wrt = {self.wrt}")
        if name not in self._arrays:
            raise ValueError(f"sensitivity: no output {name!r}; outputs are {list(self._arrays)}")
        return self._arrays[name][..., self.wrt.index(parameter)]

    def __getitem__(self, name):
        return self._arrays[name]

    def __iter__(self):
        return iter(self._arrays)

    def __len__(self):
        return len(self._arrays)


def sensitivity(
    rod: Rod,
    kappa: Sequence[float] | np.ndarray,
    tau: Sequence[float] | np.ndarray,
    wrt: Sequence[str] = ("K1", "K2", "K3", "K13", "K23", "uhat"),
    *,
    chunk_size: int | None = None,
    progress: ProgressArgument = None,
    devices: Sequence[jax.Device] | None = None,
) -> Sensitivity:
    """Derivatives of the axial force, axial moment and register of every equilibrium on
    the grid `kappa` x `tau` (1-D axes, as in `sweep`) with respect to the rod's
    parameters `wrt` (names from `K1, K2, K3, K13, K23, uhat1, uhat2, uhat3`; `"uhat"`
    means all three components).

    Forward-mode autodiff (one `jax.jvp` per parameter, vmapped) through
    `helix_equilibria`, whose register derivative is the implicit function theorem at the
    root: $\\partial\\varphi/\\partial\\theta = -(\\partial f/\\partial\\theta)/f'(\\varphi)$.
    The slot of each register is held fixed (a derivative follows one register); it is
    infinite at a tangent (fold) register.  Also returns the elasticities
    $(\\theta/F)\\,\\partial F/\\partial\\theta$ and $(\\theta/M)\\,\\partial M/\\partial\\theta$
    (infinite where $F$ or $M$ vanishes, zero for a parameter that is zero).  Invalid
    slots are NaN.  Streams, shards and shows `progress` exactly as `sweep` (`chunk_size`,
    `devices` as there).  Returns a `Sensitivity`.
    """
    wrt = _check_wrt(wrt)
    _check_rod(rod, "sensitivity")
    check_progress(progress, "sensitivity")
    kappa = _check_axis("kappa", kappa, "sensitivity")
    tau = _check_axis("tau", tau, "sensitivity")
    p = len(wrt)
    trailing = {
        "force": ((4,), np.float64),
        "moment": ((4,), np.float64),
        "phi": ((4,), np.float64),
        "d_force": ((4, p), np.float64),
        "d_moment": ((4, p), np.float64),
        "d_phi": ((4, p), np.float64),
        "force_elasticity": ((4, p), np.float64),
        "moment_elasticity": ((4, p), np.float64),
    }
    with np.errstate(divide="ignore", invalid="ignore"):
        arrays = _stream(
            _sensitivity_point_fn(wrt), rod, kappa, tau, trailing, chunk_size, progress, devices, "sensitivity"
        )
    return Sensitivity(rod, kappa, tau, wrt, arrays)
