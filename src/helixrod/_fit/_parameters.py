"""Which parameters a fit frees, and the internal coordinates its optimiser works in.

The optimiser works in dimensionless internal coordinates that keep $K$ positive definite:
$\\log K_1$, $\\log K_2$ and, with $K_3$ free, $\\log S$ with the Schur complement
$S = K_3 - K_{13}^2/K_1 - K_{23}^2/K_2$ (a Cholesky factor with log diagonal; $K_{13}$,
$K_{23}$ enter linearly); with $K_3$ fixed the normalised couplings $(K_{13}/\\sqrt{K_1K_3},
K_{23}/\\sqrt{K_2K_3})$ are mapped into the unit disc.  Stiffnesses are measured in units of
`k_scale`, twists in units of `u_scale`.  Standard errors and the identifiability report are
computed in the physical parameters at the solution.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from .._misc import float_dtype, host_method, random_normal
from .._rod import PARAMETER_NAMES, Rod, check_rod_vector, rod_from_vector

STIFFNESS_NAMES = PARAMETER_NAMES[:5]
TWIST_NAMES = PARAMETER_NAMES[5:]


class ModelParameter(eqx.Module):
    """A parameter of a forward model besides the rod's (e.g. a persistence length): its
    `name`, default `start` value, `scale`, whether it is `positive` (then fitted in log
    coordinates) and whether it is fixed at `start` unless `fix=` or `init=` says otherwise
    (`fixed_by_default`)."""

    name: str = eqx.field(static=True)
    start: float = eqx.field(static=True)
    scale: float = eqx.field(static=True)
    positive: bool = eqx.field(static=True)
    fixed_by_default: bool = eqx.field(static=True, default=False)


class Parameterisation(eqx.Module):
    """The free parameters of a fit -- the rod's (`free`, in `PARAMETER_NAMES` order), then
    the forward model's own (`extra_free`, in the model's order; `names` is both) -- the
    values of the fixed ones, and the scales of the internal coordinates.  The names are
    static (one compilation per choice), the values traced (refits of other values reuse
    it).  Internal coordinates and physical values `q` list the rod's free parameters first."""

    free: tuple[str, ...] = eqx.field(static=True)
    isotropic: bool = eqx.field(static=True)  # K2 = K1 (tied: K2 is neither free nor fixed)
    fixed_names: tuple[str, ...] = eqx.field(static=True)
    fixed_values: ArrayLike
    k_scale: ArrayLike
    u_scale: ArrayLike
    extra: tuple[ModelParameter, ...] = eqx.field(static=True)
    extra_free: tuple[str, ...] = eqx.field(static=True)
    extra_values: ArrayLike  # every model parameter: the fixed values, or the start of free ones

    def __init__(
        self,
        fixed: Mapping[str, float],
        k_scale: float,
        u_scale: float,
        extra: tuple[ModelParameter, ...] = (),
        extra_values: Mapping[str, float] | None = None,
        isotropic: bool = False,
    ):
        dtype = float_dtype()
        self.isotropic = bool(isotropic) and "K1" not in fixed
        self.free = tuple(n for n in PARAMETER_NAMES if n not in fixed and not (self.isotropic and n == "K2"))
        self.fixed_names = tuple(n for n in PARAMETER_NAMES if n in fixed)
        # NumPy: read on the host by every fit step outside the compiled programs, and
        # placed on the device by the call of each program (four eager transfers a fit less).
        self.fixed_values = np.asarray([float(fixed.get(n, 0.0)) for n in PARAMETER_NAMES], dtype)
        self.k_scale = np.asarray(k_scale, dtype)
        self.u_scale = np.asarray(u_scale, dtype)
        self.extra = tuple(extra)
        self.extra_free = tuple(e.name for e in self.extra if e.name not in fixed)
        values = {} if extra_values is None else dict(extra_values)
        values.update({k: v for k, v in fixed.items() if k in {e.name for e in self.extra}})
        self.extra_values = np.asarray([float(values.get(e.name, e.start)) for e in self.extra], dtype)

    @property
    def names(self) -> tuple[str, ...]:
        """Every free parameter: the rod's, then the model's."""
        return self.free + self.extra_free

    def extra_vector(self, q) -> Array:
        """Every model parameter (in the model's order) from the free physical values `q`."""
        lookup = dict(zip(self.extra_free, [q[len(self.free) + i] for i in range(len(self.extra_free))]))
        return jnp.stack(
            [jnp.asarray(lookup.get(e.name, self.extra_values[i]), float_dtype()) for i, e in enumerate(self.extra)]
        ) if self.extra else jnp.zeros((0,), float_dtype())

    @property
    def fixed(self) -> dict[str, float]:
        """The fixed parameters by name (concrete values)."""
        values = np.asarray(self.fixed_values)
        return {n: float(values[PARAMETER_NAMES.index(n)]) for n in self.fixed_names}

    @host_method
    def scales(self, names) -> np.ndarray:
        """The scale of each parameter in `names` (`k_scale`, `u_scale` or a model
        parameter's own)."""
        k, u = float(self.k_scale), float(self.u_scale)
        own = {e.name: e.scale for e in self.extra}
        return np.array([own[n] if n in own else k if n in STIFFNESS_NAMES else u for n in names])

    def _fixed_lookup(self):
        return {n: self.fixed_values[PARAMETER_NAMES.index(n)] for n in self.fixed_names}

    def full(self, q) -> Array:
        """The physical 8-vector from the free physical values `q` (in `free` order)."""
        fixed = self._fixed_lookup()
        lookup = dict(zip(self.free, [q[i] for i in range(len(self.free))]))
        if self.isotropic:
            lookup["K2"] = lookup["K1"]
        dtype = float_dtype()
        return jnp.stack([jnp.asarray(lookup[n] if n in lookup else fixed[n], dtype) for n in PARAMETER_NAMES])

    def rod(self, q) -> Rod:
        """The rod with free physical values `q` (no positive-definiteness check: the
        internal coordinates guarantee it)."""
        return rod_from_vector(self.full(q))

    def physical(self, z) -> Array:
        """The free physical values from internal coordinates `z`."""
        fixed = self._fixed_lookup()
        zs = dict(zip(self.free, [z[i] for i in range(len(self.free))]))
        ks, us = self.k_scale, self.u_scale
        val = {}
        for n in ("K1", "K2"):
            val[n] = ks * jnp.exp(jnp.clip(zs[n], -40.0, 40.0)) if n in zs else fixed.get(n)
        if self.isotropic:
            val["K2"] = val["K1"]
        K1, K2 = val["K1"], val["K2"]
        if "K3" in zs:
            for n in ("K13", "K23"):
                val[n] = ks * zs[n] if n in zs else fixed[n]
            val["K3"] = ks * jnp.exp(jnp.clip(zs["K3"], -40.0, 40.0)) + val["K13"] ** 2 / K1 + val["K23"] ** 2 / K2
        else:
            K3 = fixed["K3"]
            free_c = [n for n in ("K13", "K23") if n in zs]
            diag = {"K13": K1, "K23": K2}
            room = 1.0
            for n in ("K13", "K23"):
                if n not in zs:
                    val[n] = fixed[n]
                    room = room - fixed[n] ** 2 / (diag[n] * K3)
            room = jnp.sqrt(jnp.maximum(room, 1e-12))
            if free_c:
                g = room * _disc(jnp.stack([zs[n] for n in free_c]))
                for i, n in enumerate(free_c):
                    val[n] = g[i] * jnp.sqrt(diag[n] * K3)
            val["K3"] = K3
        for n in TWIST_NAMES:
            val[n] = us * zs[n] if n in zs else fixed[n]
        rod_part = [jnp.asarray(val[n], float_dtype()) for n in self.free]
        return jnp.stack(rod_part + self._extra_physical(z))

    def _extra_physical(self, z):
        own = {e.name: e for e in self.extra}
        out = []
        for i, name in enumerate(self.extra_free):
            e, w = own[name], z[len(self.free) + i]
            out.append(jnp.asarray(e.scale * jnp.exp(jnp.clip(w, -40.0, 40.0)) if e.positive else e.scale * w, float_dtype()))
        return out

    @host_method
    def internal(self, p_full, extra_full=None) -> np.ndarray:
        """Inverse of `physical` from a full physical vector of the rod and, if the model has
        parameters, every model parameter (NumPy; for initial values; default: their starts)."""
        extra_full = np.asarray(self.extra_values if extra_full is None else extra_full, float)
        p = dict(zip(PARAMETER_NAMES, np.asarray(p_full, float)))
        ks, us = float(self.k_scale), float(self.u_scale)
        z = {}
        if self.isotropic:
            p["K2"] = p["K1"]
        for n in ("K1", "K2"):
            z[n] = np.log(p[n] / ks)
        if "K3" in self.free:
            z["K13"], z["K23"] = p["K13"] / ks, p["K23"] / ks
            schur = p["K3"] - p["K13"] ** 2 / p["K1"] - p["K23"] ** 2 / p["K2"]
            z["K3"] = np.log(max(schur, 1e-12 * p["K3"]) / ks)
        else:
            free_c = [n for n in ("K13", "K23") if n in self.free]
            diag = {"K13": p["K1"], "K23": p["K2"]}
            room = 1.0 - sum(p[n] ** 2 / (diag[n] * p["K3"]) for n in ("K13", "K23") if n not in self.free)
            room = np.sqrt(max(room, 1e-12))
            g = np.array([p[n] / np.sqrt(diag[n] * p["K3"]) / room for n in free_c])
            norm2 = float(np.sum(g * g))
            if norm2 >= 1:
                g = g * 0.99 / np.sqrt(norm2)
                norm2 = 0.99**2
            w = g / np.sqrt(1 - norm2)
            for i, n in enumerate(free_c):
                z[n] = w[i]
        for n in TWIST_NAMES:
            z[n] = p[n] / us
        for e, value in zip(self.extra, extra_full):
            if e.name in self.extra_free:
                z[e.name] = np.log(value / e.scale) if e.positive else value / e.scale
        return np.array([z[n] for n in self.names])

    @host_method
    def starts(self, z_base, n: int, key) -> np.ndarray:
        """`n` starts: `z_base`, then random perturbations suited to each coordinate
        (log-normal stiffnesses, normal couplings and twists) drawn from `key` (`None`:
        `jax.random.key(0)`).  One start draws nothing."""
        if n == 1:
            return np.asarray(z_base, dtype=float)[None, :]
        spread = np.array([{"K1": 0.7, "K2": 0.7, "K3": 0.5}.get(name, 0.5) for name in self.free] + [0.2] * len(self.extra_free))
        shape = (n, len(self.names))
        noise = _default_noise(shape, float_dtype()) if key is None else _noise(key, shape)
        return z_base[None, :] + spread * noise


def _noise(key, shape: tuple[int, int]) -> np.ndarray:
    """Standard normal perturbations of the starts from `key`, none for the first."""
    noise = np.array(random_normal(key, shape))
    noise[0] = 0.0
    return noise


@functools.lru_cache(maxsize=64)
def _default_noise(shape: tuple[int, int], dtype) -> np.ndarray:
    """`_noise` from the default key, `jax.random.key(0)`, drawn once per shape and dtype
    (the key and the draw cost ~50 us, ~1 % of a default helix fit); read-only."""
    noise = _noise(jax.random.key(0), shape)
    noise.setflags(write=False)
    return noise


def _disc(w):
    return w / jnp.sqrt(1.0 + jnp.sum(w * w))


def resolve_fixed(
    uhat, fit_uhat: bool, fix, extra: tuple[ModelParameter, ...] = (), init=None, isotropic: bool = False
) -> dict[str, float]:
    """The fixed parameters by name from `uhat=`, `fit_uhat=` and `fix=` (checked), and the
    model parameters fixed by default (unless `fix` or an `init` mapping names them).  With
    `isotropic` ($K_2 = K_1$), a fixed K1 or K2 fixes both."""
    fixed = {}
    own = {e.name: e for e in extra}
    names = PARAMETER_NAMES + tuple(own)
    if fix:
        for name, value in dict(fix).items():
            if name not in names:
                raise ValueError(f"fix: unknown parameter {name!r}; names are {names}")
            value = float(value)
            if not np.isfinite(value) or (name in own and own[name].positive and value <= 0):
                raise ValueError(f"fix: {name} must be finite{' and > 0' if name in own and own[name].positive else ''}, got {value}")
            fixed[name] = value
    named_in_init = set(init) if isinstance(init, Mapping) else set()
    for e in extra:
        if e.fixed_by_default and e.name not in fixed and e.name not in named_in_init:
            fixed[e.name] = e.start
    if fit_uhat and uhat is not None:
        raise ValueError("give either uhat= (fixed intrinsic twist) or fit_uhat=True, not both")
    if not fit_uhat:
        uh = np.zeros(3) if uhat is None else np.asarray(uhat, float)
        if uh.shape != (3,) or not np.all(np.isfinite(uh)):
            raise ValueError(f"uhat must be three finite numbers, got {uhat!r}")
        for i, n in enumerate(TWIST_NAMES):
            if uhat is not None and n in fixed and fixed[n] != float(uh[i]):
                raise ValueError(f"fix: {n} = {fixed[n]} contradicts uhat= {np.asarray(uhat, float).tolist()}; give one of them")
            fixed.setdefault(n, float(uh[i]))
    if isotropic:
        if "K1" in fixed and "K2" in fixed and fixed["K1"] != fixed["K2"]:
            raise ValueError(f"isotropic=True (K2 = K1) but fix gives K1 = {fixed['K1']} and K2 = {fixed['K2']}")
        if "K1" in fixed or "K2" in fixed:
            fixed["K1"] = fixed["K2"] = fixed.get("K1", fixed.get("K2"))
    for n in ("K1", "K2", "K3"):
        if n in fixed and not fixed[n] > 0:
            raise ValueError(f"fix: {n} must be > 0, got {fixed[n]}")
    if "K3" in fixed and "K1" in fixed and "K2" in fixed:
        schur = fixed["K3"] - fixed.get("K13", 0.0) ** 2 / fixed["K1"] - fixed.get("K23", 0.0) ** 2 / fixed["K2"]
        if "K13" in fixed and "K23" in fixed and schur <= 0:
            raise ValueError("fix: the fixed stiffnesses are not positive definite")
    if all(n in fixed for n in names):
        raise ValueError("nothing to fit: every parameter is fixed")
    return fixed


def extra_start(init, fixed: dict[str, float], extra: tuple[ModelParameter, ...]) -> dict[str, float]:
    """Start values of the model parameters: `init` entries (a mapping) over their defaults,
    fixed values imposed; `ValueError` for a positive one that is not."""
    values = {e.name: e.start for e in extra}
    if isinstance(init, Mapping):
        values.update({n: float(v) for n, v in init.items() if n in values})
    values.update({n: v for n, v in fixed.items() if n in values})
    for e in extra:
        if not np.isfinite(values[e.name]) or (e.positive and values[e.name] <= 0):
            raise ValueError(f"init: {e.name} must be finite{' and > 0' if e.positive else ''}, got {values[e.name]}")
    return values


def start_vector(init, fixed: dict[str, float], default, model_names=()) -> np.ndarray:
    """Full physical vector of the rod from `init` (a Rod, a mapping or None; entries named
    in `model_names` are the model's, see `extra_start`) over `default`, with the fixed
    values imposed; `ValueError` unless it is a valid rod.  Without `init`, fixed couplings
    too strong for the default's diagonal are made room for by the free stiffnesses
    (`_room_for_couplings`)."""
    p = dict(zip(PARAMETER_NAMES, default))
    if isinstance(init, Rod):
        p.update(zip(PARAMETER_NAMES, [float(getattr(init, n)) for n in PARAMETER_NAMES[:5]] + [float(u) for u in np.asarray(init.uhat)]))
    elif isinstance(init, Mapping):
        for n, v in init.items():
            if n in model_names:
                continue
            if n not in PARAMETER_NAMES:
                raise ValueError(f"init: unknown parameter {n!r}")
            p[n] = float(v)
    elif init is not None:
        raise ValueError("init must be a Rod, a mapping of parameter values, or None")
    p.update({n: v for n, v in fixed.items() if n in p})
    if init is None:
        p = _room_for_couplings(p, fixed)
    v = np.array([p[n] for n in PARAMETER_NAMES], float)
    check_rod_vector(v)
    return v


def _room_for_couplings(p: dict[str, float], fixed: dict[str, float]) -> dict[str, float]:
    """`p` (by name) positive definite by its free stiffnesses where fixed couplings make
    the default start indefinite (`fix={"K13": 0.8}` beside an isotropic estimate of K3 =
    0.07): a free K3 becomes its Schur complement's old value plus what the couplings take,
    $K_3 = S + K_{13}^2/K_1 + K_{23}^2/K_2$; with K3 fixed, free K1 and K2 grow by a
    common factor until the complement is half of K3.  Unchanged where it is positive
    definite already or nothing free can help (the check then names the values)."""
    K1, K2, K3, K13, K23 = (p[n] for n in STIFFNESS_NAMES)
    if not (K1 > 0 and K2 > 0 and K3 > 0) or K3 - K13**2 / K1 - K23**2 / K2 > 0:
        return p
    p = dict(p)
    if "K3" not in fixed:
        p["K3"] = K3 + K13**2 / K1 + K23**2 / K2
        return p
    free = [(n, c) for n, c in (("K1", K13), ("K2", K23)) if n not in fixed]
    taken_fixed = sum(c**2 / p[n] for n, c in (("K1", K13), ("K2", K23)) if n in fixed)
    taken_free = sum(c**2 / p[n] for n, c in free)
    if free and taken_free > 0 and taken_fixed < 0.5 * K3:
        factor = taken_free / (0.5 * K3 - taken_fixed)
        for n, _ in free:
            p[n] *= factor
    return p
