"""Uniform helical equilibria: every register of the helix of curvature kappa, torsion tau.

Conventions (docs/conventions.md): $u = (\\kappa\\sin\\varphi, \\kappa\\cos\\varphi, \\tau)$ in the director
frame, $m = K(u - \\hat u)$, and a uniform helix is an equilibrium iff $n = \\mu_2 u$,
$m = \\mu_1 u + \\mu_2 e_3$ (reference report, eqs. 70-79).  The register condition
$h = m_1 u_2 - m_2 u_1 = \\kappa (A \\sin 2\\varphi + B \\sin\\varphi + C\\cos\\varphi)$ with
$A = (K_1 - K_2)\\kappa/2$, $B = K_2\\hat u_2 + K_{23}(\\hat u_3 - \\tau)$,
$C = K_{13}(\\tau - \\hat u_3) - K_1 \\hat u_1$ is solved by `helixrod._roots`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ._compile import jit
from ._misc import as_float, float_dtype
from ._roots import cpu_kernel, register_roots
from ._rod import Rod, check_quadratic_rod, rod_vector


class HelixEquilibria(eqx.Module):
    """All uniform helical equilibria at given $(\\kappa, \\tau)$.

    Per-register fields have shape `batch + (4,)` (vectors `batch + (4, 3)`), where
    `batch = broadcast(kappa, tau, rod batch)`.  Slots: 0 the global minimum of the energy
    on the constraint circle (always stable), 1 the global maximum, 2 and 3 the local
    minimum and maximum of the inner pair when it exists.  `valid` marks the slots in use;
    every field is NaN in unused slots.

    Fields: `phi` register in $[0, 2\\pi)$; `u`, `m`, `n` twist, moment and force in the
    director frame; `force` $F = n\\cdot a$ and `moment` $M = m\\cdot a$ along the helix axis
    $a = u/|u|$ (for $\\tau > 0$, $F > 0$ pulls); `tension` $n_3$; `energy` $W(u)$;
    `d2energy` $d^2W/d\\varphi^2$ on the circle; `stable` ($d^2W/d\\varphi^2 > 0$); the
    multipliers `mu1`, `mu2`; first integrals `I1` $= |n|^2$ and `I2` $= m\\cdot n$;
    `tangent` (a double register, reported once, with $d^2W/d\\varphi^2 = 0$, not stable).

    Per-point fields (shape `batch`): `continuum` -- $W$ is constant on the circle (the
    fully isotropic rod, or $K_1 = K_2$ at a $\\tau$ where $B = C = 0$): every register is an
    equilibrium, with the same energy; slot 0 holds $\\varphi = 0$ as the representative, and
    no register is called stable (the family is neutral).  The axial force and moment are
    the same for every register of the family only when the rod has no bend-twist
    coupling ($K_{13} = K_{23} = 0$, the fully isotropic rod); with coupling, $m_3$ and so
    the wrench vary with $\\varphi$ along the family, and slot 0 reports the member
    $\\varphi = 0$.
    `straight` -- $\\kappa = 0$: no register is defined, every slot is invalid; see
    `straight_family` and the $1/\\kappa$ divergence of the wrench of a curved rod.
    """

    phi: Float[Array, "*batch 4"]
    valid: Bool[Array, "*batch 4"]
    u: Float[Array, "*batch 4 3"]
    m: Float[Array, "*batch 4 3"]
    n: Float[Array, "*batch 4 3"]
    force: Float[Array, "*batch 4"]
    moment: Float[Array, "*batch 4"]
    tension: Float[Array, "*batch 4"]
    energy: Float[Array, "*batch 4"]
    d2energy: Float[Array, "*batch 4"]
    stable: Bool[Array, "*batch 4"]
    mu1: Float[Array, "*batch 4"]
    mu2: Float[Array, "*batch 4"]
    I1: Float[Array, "*batch 4"]
    I2: Float[Array, "*batch 4"]
    tangent: Bool[Array, "*batch 4"]
    continuum: Bool[Array, "*batch"]
    straight: Bool[Array, "*batch"]

    @property
    def count(self) -> Array:
        """Number of valid registers per point (2, 3 or 4; 1 for a continuum, 0 if straight)."""
        return jnp.sum(self.valid, axis=-1)


def register_coefficients(rod: Rod, kappa: ArrayLike, tau: ArrayLike):
    """The coefficients $(A, B, C)$ of $h/\\kappa = A\\sin 2\\varphi + B\\sin\\varphi + C\\cos\\varphi$."""
    kappa, tau = jnp.asarray(kappa), jnp.asarray(tau)
    uh = rod.uhat
    A = 0.5 * (rod.K1 - rod.K2) * kappa
    B = rod.K2 * uh[..., 1] + rod.K23 * (uh[..., 2] - tau)
    C = rod.K13 * (tau - uh[..., 2]) - rod.K1 * uh[..., 0]
    return jnp.broadcast_arrays(A, B, C)


def _check_inputs(kappa, tau):
    """The broadcast shape of `kappa` and `tau` (arrays, or NumPy-converted sequences)."""
    for name, x in (("kappa", kappa), ("tau", tau)):
        dtype = x.dtype if hasattr(x, "dtype") else jnp.result_type(x)
        if not np.issubdtype(dtype, np.number) or np.issubdtype(dtype, np.complexfloating):
            raise ValueError(f"{name} must be real numbers, got dtype {dtype}")
    try:
        return jnp.broadcast_shapes(jnp.shape(kappa), jnp.shape(tau))
    except ValueError:
        raise ValueError(
            f"kappa and tau do not broadcast: shapes {jnp.shape(kappa)} and {jnp.shape(tau)}"
        ) from None


def helix_equilibria(rod: Rod, kappa: ArrayLike, tau: ArrayLike, *, fields: Sequence[str] | None = None) -> HelixEquilibria:
    """Every uniform helical equilibrium of curvature `kappa` and torsion `tau`.

    `kappa` ($\\ge 0$) and `tau` broadcast against each other and against the rod's batch
    shape; units are those of the rod's twists (1/length).  Pure, and safe under
    `jax.jit`, `jax.vmap` and `jax.grad`: register derivatives come from the implicit
    function theorem, and gradients stay finite wherever values are finite.

    Points that cannot have a helix are flagged, never raised on, so that one bad point
    does not spoil a batch: `kappa < 0` or non-finite inputs give `valid = False` in every
    slot; `kappa = 0` sets `straight`.

    `fields` (names of `HelixEquilibria` fields) computes only those, and `valid`; the
    others are `None`.  Under `jax.jit` XLA drops unused fields anyway, except in the
    chunked loop a CPU runs over more than 32 768 points (262 144 with the compiled
    register kernel, `pip install "helixrod[numba]"`), where asking for fewer fields
    is what makes it fast (`phi, force, moment, stable` of 10^6 points: about 1.5x) and
    keeps the memory of the rest from being allocated.  With the compiled kernel, fields
    among `phi, valid, force, moment, stable` of one float64 rod on a CPU are computed by
    it in one pass over the points, at any size (about 2x faster than XLA's program at
    1e4 ... 1e6 points); their derivatives, and every other field, by XLA's program.
    Unknown names: `ValueError`.

    **Example**

    ```python
    rod = helixrod.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
    eq = helixrod.helix_equilibria(rod, 0.5, 1.5)
    eq.phi[eq.valid], eq.force[eq.valid], eq.stable[eq.valid]
    ```
    """
    check_quadratic_rod(rod, "helix_equilibria")
    kappa, tau = (x if hasattr(x, "dtype") else np.asarray(x) for x in (kappa, tau))
    fields = _check_fields(fields)
    shape = _check_inputs(kappa, tau)
    dtype = float_dtype()
    batch = rod.K1.shape
    try:
        shape = jnp.broadcast_shapes(shape, batch)
    except ValueError:
        raise ValueError(
            f"kappa, tau (broadcast shape {shape}) do not broadcast against the rod's batch "
            f"shape {batch}"
        ) from None
    size = math.prod(shape)
    kappa, tau = (_points(x, dtype, shape, size) for x in (kappa, tau))
    if batch:
        rod = jax.tree.map(
            lambda x: jnp.broadcast_to(x, shape + x.shape[len(batch) :]).reshape((size,) + x.shape[len(batch) :]),
            rod,
        )
    on_cpu = jax.default_backend() == "cpu"
    limit = _KERNEL_CHUNK if on_cpu and dtype == jnp.float64 and cpu_kernel() is not None else _CPU_CHUNK
    chunked = size > limit and on_cpu
    if _wrench_kernel(rod, kappa, fields) is not None:
        # The kernel runs over any number of points in cache-sized blocks of its own; the
        # chunks are for the derivatives, which XLA's program computes.
        eq = _wrench_by_kernel(rod, kappa, tau, fields=fields, limit=limit if chunked else None)
    elif chunked:
        eq = _equilibria_chunked(rod, kappa, tau, limit=limit, fields=fields)
    else:
        eq = _equilibria_flat(rod, kappa, tau, fields)
    if shape == (size,):
        return eq
    return jax.tree.map(lambda x: x.reshape(shape + x.shape[1:]), eq)


def _points(x, dtype, shape, size):
    """`x` broadcast to `shape` and flattened to `(size,)`; host values stay NumPy arrays
    (`as_float`): an eager call with NumPy input converted and reshaped each on the device
    before, and reshaped every field of the result even where the shape was already
    right (0.97 ms a call for 1000 points, most of it these small operations)."""
    x = as_float(x, dtype)
    xp = np if isinstance(x, np.ndarray) else jnp
    return xp.broadcast_to(x, shape).reshape(size)


# Points per chunk on a CPU.  The per-point pipeline is a few dozen elementwise passes;
# over a whole large batch each intermediate array streams through main memory, over a
# chunk it stays in cache.  Best of 4e3 ... 1e5 points on 2 cores: 2e4 ... 5e4, ~30%
# faster than one pass over 1e6 points (benchmarks/bench_equilibria.py).  On an
# accelerator every chunk would be a round of kernel launches: one pass.
_CPU_CHUNK = 32768
# With the compiled register kernel (`_roots.cpu_kernel`), whose own blocks stay in cache,
# only the fields are left to XLA: 1e5 points in one pass took 40-55 ns a point against
# 87-96 in chunks of 32768 (2 cores); from 1e6 on, chunks of 32768 ... 262144 were within
# the machine's noise of each other and of one pass.  (The kernel of the wrench,
# `_wrench_by_kernel`, needs no chunks; its derivatives, XLA's program, use these.)
_KERNEL_CHUNK = 262144


@jit(static_argnames=("limit", "fields"))
def _equilibria_chunked(rod: Rod, kappa, tau, limit: int, fields: tuple[str, ...]) -> HelixEquilibria:
    """`_equilibria_flat` in chunks of at most `limit` points (one compiled program per
    shape, limit and fields: called eagerly, a loop over a fresh closure would compile
    every call).  A field computed in the loop is computed whether or not the caller uses
    it (XLA does not remove a while loop's unused results): hence `fields`."""
    size = kappa.shape[0]
    if rod.K1.ndim:
        return _map_chunks(lambda r, k, t: _fields_in_xla(r, k, t, fields), (rod, kappa, tau), size, limit)
    return _map_chunks(lambda k, t: _fields_in_xla(rod, k, t, fields), (kappa, tau), size, limit)


def _map_chunks(fn, args, size, limit):
    """`fn(*args)` on flat arrays (leading axis `size` > `limit`), in equal chunks of at most
    `limit` points, each chunk's results written in place.  Values equal those of one pass
    up to rounding (another program may contract other FMAs)."""
    count = -(-size // limit)
    # Equal chunks, rounded up to a multiple of 1024 (odd sizes measured up to 1.6x slower);
    # the last chunk overlaps its predecessor.
    chunk = min(-(-size // (count * 1024)) * 1024, limit)

    def chunk_at(start):
        return jax.tree.map(lambda x: jax.lax.dynamic_slice_in_dim(x, start, chunk), args)

    shapes = jax.eval_shape(lambda: fn(*chunk_at(0)))
    out = jax.tree.map(lambda s: jnp.zeros((size,) + s.shape[1:], s.dtype), shapes)

    def body(i, out):
        start = jnp.minimum(i * chunk, size - chunk)
        values = jax.checkpoint(fn, prevent_cse=False)(*chunk_at(start))
        return jax.tree.map(lambda o, v: jax.lax.dynamic_update_slice_in_dim(o, v, start, 0), out, values)

    return jax.lax.fori_loop(0, count, body, out)


@jit(static_argnames="fields")
def _equilibria_flat(rod: Rod, kappa, tau, fields: tuple[str, ...]) -> HelixEquilibria:
    """`helix_equilibria` on flat `kappa`, `tau` of shape (n,) (rod unbatched or (n,)),
    with only `fields` (and `valid`) set, by XLA's program; one program (an eager call is
    one dispatch, and one entry of the persistent cache)."""
    return _fields_in_xla(rod, kappa, tau, fields)


def _wrench_kernel(rod: Rod, kappa, fields: tuple[str, ...]):
    """The compiled CPU kernel (`_roots.cpu_kernel`) where it computes what is asked for:
    fields among its `WRENCH_FIELDS` (phi, valid, force, moment, stable), of float64
    helices of one `Rod` (unbatched, or batched by `jax.vmap`), on a CPU; else None."""
    if jax.default_backend() != "cpu" or jnp.result_type(kappa) != jnp.float64 or not isinstance(rod, Rod):
        return None
    if rod.K1.ndim != 0 or math.prod(jnp.shape(kappa)) == 0:
        return None
    kernel = cpu_kernel()
    return kernel if kernel is not None and set(fields) <= set(kernel.WRENCH_FIELDS) else None


@jit(static_argnames=("fields", "limit"))
def _wrench_by_kernel(rod: Rod, kappa, tau, fields: tuple[str, ...], limit: int | None) -> HelixEquilibria:
    """`_equilibria_flat`'s values from the compiled kernel: one pass over the points, the
    registers and their wrench in each cache-sized block, where XLA's program makes a
    dozen passes over arrays of the points.  Their derivatives are those of XLA's program
    (the kernel has none), in chunks of `limit` points as `_equilibria_chunked` (None: one
    pass; checkpointed, so that a linearisation keeps the inputs, not each chunk's
    intermediates): under `jax.jvp`, `jax.grad` and the fits' Jacobians the values come
    from XLA's program too, equal to rounding.  One program (an eager call is one dispatch)."""

    @jax.custom_jvp
    def by_kernel(rod, kappa, tau):
        values = cpu_kernel().wrench(kappa, tau, rod_vector(rod))
        return HelixEquilibria(**{name: values[name] if name in fields else None for name in FIELDS})

    @by_kernel.defjvp
    def by_kernel_jvp(primals, tangents):
        if limit is None:
            return jax.jvp(lambda r, k, t: _fields_in_xla(r, k, t, fields), primals, tangents)
        chunked = jax.checkpoint(lambda r, k, t: _equilibria_chunked(r, k, t, limit=limit, fields=fields))
        return jax.jvp(chunked, primals, tangents)

    return by_kernel(rod, kappa, tau)


def _fields_in_xla(rod: Rod, kappa, tau, fields: tuple[str, ...]) -> HelixEquilibria:
    """`_equilibria_flat` by XLA's program (the reference of the compiled kernel, and the
    path of other fields, float32, accelerators, batched rods and derivatives)."""
    A, B, C = register_coefficients(rod, kappa, tau)
    good = jnp.isfinite(kappa) & jnp.isfinite(tau) & (kappa >= 0)
    straight = good & (kappa == 0)
    helical = good & (kappa > 0)
    # Outside the domain solve a harmless problem and mask it.
    A = jnp.where(helical, A, 1.0)
    B = jnp.where(helical, B, 0.0)
    C = jnp.where(helical, C, 0.0)
    phi, cos_phi, sin_phi, valid, continuum, tangent = register_roots(A, B, C)
    valid = valid & helical[..., None]
    continuum = continuum & helical

    # Component by component (no 3-vectors until the outputs, which XLA drops if unused).
    kappa_safe = jnp.where(helical, kappa, 1.0)
    k = kappa_safe[..., None]
    t = tau[..., None]
    norm_u = jnp.hypot(kappa_safe, tau)[..., None]
    # The rod with an axis for the register slots, so that its laws broadcast over them.
    # (An unbatched rod's components are scalars and broadcast as they are.)
    slot_rod = rod if rod.K1.ndim == 0 else jax.tree.map(lambda x: jnp.expand_dims(x, rod.K1.ndim), rod)
    u1, u2, u3 = k * sin_phi, k * cos_phi, jnp.broadcast_to(t, cos_phi.shape)
    uh = slot_rod.uhat
    v1, v2, v3 = u1 - uh[..., 0], u2 - uh[..., 1], u3 - uh[..., 2]
    m1 = slot_rod.K1 * v1 + slot_rod.K13 * v3
    m2 = slot_rod.K2 * v2 + slot_rod.K23 * v3
    m3 = slot_rod.K13 * v1 + slot_rod.K23 * v2 + slot_rod.K3 * v3
    # mu1 = (m1 u1 + m2 u2) / kappa^2, written without kappa^2 (which underflows for
    # kappa below ~1e-154 while the wrench, ~1/kappa, is still representable).
    mu1 = (m1 * sin_phi + m2 * cos_phi) / k
    mu2 = m3 - mu1 * t
    m_dot_u = m1 * u1 + m2 * u2 + m3 * u3
    force = mu2 * norm_u
    # M = m.a directly: mu1 |u| + mu2 tau/|u| is the same in exact arithmetic, but its two
    # terms (~1/kappa each for a curved or coupled rod) cancel as kappa -> 0.
    moment = m_dot_u / norm_u
    u = jnp.stack([u1, u2, u3], axis=-1)
    m = jnp.stack([m1, m2, m3], axis=-1)
    n = mu2[..., None] * u
    energy = 0.5 * (v1 * m1 + v2 * m2 + v3 * m3)
    cos2 = cos_phi * cos_phi - sin_phi * sin_phi
    d2energy = k * (2 * A[..., None] * cos2 + B[..., None] * cos_phi - C[..., None] * sin_phi)
    d2energy = jnp.where(tangent, 0.0, d2energy)
    stable = valid & ~tangent & ~continuum[..., None] & (d2energy > 0)

    def masked(x):
        mask = valid.reshape(valid.shape + (1,) * (x.ndim - valid.ndim))
        return jnp.where(mask, x, jnp.nan)

    values = dict(
        phi=masked(phi),
        valid=valid,
        u=masked(u),
        m=masked(m),
        n=masked(n),
        force=masked(force),
        moment=masked(moment),
        tension=masked(mu2 * u3),
        energy=masked(energy),
        d2energy=masked(d2energy),
        stable=stable,
        mu1=masked(mu1),
        mu2=masked(mu2),
        I1=masked(force * force),
        I2=masked(mu2 * m_dot_u),
        tangent=tangent & valid,
        continuum=continuum,
        straight=straight,
    )
    return HelixEquilibria(**{name: value if name in fields else None for name, value in values.items()})


FIELDS = tuple(f.name for f in dataclasses.fields(HelixEquilibria))


def _check_fields(fields) -> tuple[str, ...]:
    """The requested fields with `valid`, in the class's order (one compiled program per set)."""
    if fields is None:
        return FIELDS
    if isinstance(fields, str):
        fields = (fields,)
    fields = set(fields)
    unknown = sorted(fields - set(FIELDS))
    if unknown:
        raise ValueError(f"helix_equilibria: unknown field(s) {unknown}; valid fields are {list(FIELDS)}")
    return tuple(name for name in FIELDS if name in fields or name == "valid")


def helix_residual(rod: Rod, u: ArrayLike, n: ArrayLike) -> Float[Array, "... 6"]:
    """The six balance equations of a uniform helix, zero at an equilibrium.

    With constant local components the static Kirchhoff equations
    $n' + u\\times n = 0$, $m' + u\\times m + e_3\\times n = 0$ reduce to
    $(u \\times n,\\; u\\times m + e_3 \\times n)$ with $m = K(u - \\hat u)$ (eqs. 70a-f of the
    reference report).  `u`, `n` have a trailing axis of 3; the result a trailing 6.
    """
    u = jnp.asarray(u)
    n = jnp.asarray(n)
    if u.shape[-1:] != (3,) or n.shape[-1:] != (3,):
        raise ValueError(f"u and n need a trailing axis of 3, got shapes {u.shape} and {n.shape}")
    m = rod.moment(u)
    e3_cross_n = jnp.stack([-n[..., 1], n[..., 0], jnp.zeros_like(n[..., 2])], axis=-1)
    return jnp.concatenate([jnp.cross(u, n), jnp.cross(u, m) + e3_cross_n], axis=-1)


def straight_family(rod: Rod, tension: ArrayLike):
    """The straight, untwisted exceptional family $u = 0$ (reference report, section 3.5).

    The rod is held straight by the constant moment $m = -K\\hat u$ and any axial tension.
    Returns `(u, m, n)` in the director frame with `n = (0, 0, tension)`.
    """
    check_quadratic_rod(rod, "straight_family")
    tension = jnp.asarray(tension, jnp.result_type(float))
    zero = jnp.zeros_like(tension)
    shape = jnp.broadcast_shapes(tension.shape, rod.K1.shape) + (3,)
    u = jnp.zeros(shape, tension.dtype)
    n = jnp.broadcast_to(jnp.stack([zero, zero, tension], axis=-1), shape)
    return u, rod.moment(u), n


def pure_moment_family(rod: Rod, mu1: ArrayLike):
    """The force-free exceptional family $n = 0$, $m = \\mu_1 u$ (reference report, 3.5).

    $K(u - \\hat u) = \\mu_1 u$ gives $u = (K - \\mu_1 I)^{-1} K \\hat u$: helices bent and
    twisted by a pure moment along their axis.  $\\mu_1 = 0$ is the unstressed shape
    $u = \\hat u$.  Returns `(u, m, n)`; $\\mu_1$ at an eigenvalue of $K$ gives non-finite
    values (the family passes through infinity there).
    """
    check_quadratic_rod(rod, "pure_moment_family")
    mu1 = jnp.asarray(mu1, jnp.result_type(float))
    shape = jnp.broadcast_shapes(mu1.shape, rod.K1.shape)
    K = jnp.broadcast_to(rod.K, shape + (3, 3))
    uhat = jnp.broadcast_to(rod.uhat, shape + (3,))
    eye = jnp.eye(3, dtype=K.dtype).reshape((1,) * len(shape) + (3, 3))
    shifted = K - jnp.broadcast_to(mu1, shape)[..., None, None] * eye
    u = jnp.linalg.solve(shifted, (K @ uhat[..., None]))[..., 0]
    m = rod.moment(u)
    return u, m, jnp.zeros_like(u)

