"""The stability atlas of finite helices: which uniform helices stay stable when a piece of
length $L$ of them is held between two clamps by its own wrench.

Every uniform helical equilibrium $(\\kappa, \\tau, \\varphi)$ of a rod (`helix_equilibria`) is
also an equilibrium of any finite piece of it whose ends are clamped where the helix puts them:
the wrench is the helix's.  Whether that finite helix is *stable* is the open question of
the reference report, and it is not the `stable` of `helix_equilibria` (a local minimum of
$W$ on the circle of registers, a pointwise property): here it is the second variation of
the whole clamped piece (`_stability.py`), which also feels the force and the moment the
helix carries.  A short piece is always stable (the second variation of a short rod is
dominated by its positive bending and twisting terms); the critical length $L_c$ is the
shortest at which it is not -- the first conjugate point of the helix -- and the index counts
the unstable directions at the length asked for.

A uniform helix needs no integration.  With $\\delta D = D[\\xi]$, $\\delta x = D\\eta$ and the
body wrench variations $(\\delta n, \\delta m)$, the linearised Kirchhoff equations

$$\\eta' = \\xi\\times e_3 - u\\times\\eta,\\quad \\xi' = \\delta u - u\\times\\xi,\\quad
\\delta n' = -\\delta u\\times n - u\\times\\delta n,\\quad
\\delta m' = -\\delta u\\times m - u\\times\\delta m - e_3\\times\\delta n,$$

$\\delta u = (\\partial u/\\partial m)\\,\\delta m$, have constant coefficients on the helix, so a
piece of length $h$ maps body variations by $e^{Ah}$, and the lab variations of the test
(`_stability.py`) are $\\delta x = D\\eta$, $\\delta\\theta = D\\xi$, $\\delta N = D(\\xi\\times n +
\\delta n)$, $\\delta M = D(\\xi\\times m + \\delta m)$ with $D(s) = e^{s[u]}$: every piece's
transfer matrix is a matrix exponential and two rotations (`uniform_transfers`; checked
against the integrated test in `tests/test_atlas.py`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._equilibria import helix_equilibria
from .._misc import check_integer, determinant_small, finite_scalar, float_dtype
from .._lie import hat, so3_exp
from .._rod import check_one_rod
from ._ends import CLAMPED, end_condition
from ._stability import EXTENSIBILITY, assess, stiffness_range


class StabilityAtlas(eqx.Module):
    """Result of `stability_atlas`: per point of the $(\\kappa, \\tau)$ grid and register slot
    (shape `batch + (4,)`, slots as `helix_equilibria`): `valid` (the register exists),
    `stable` (the clamped helix of length `length` is stable), `instability_index`
    (unstable directions; -1 where not defined: invalid slot, or the pieces of the test do
    not resolve the wrench -- raise `pieces`), `stability_margin` (NaN where not defined),
    `critical_length` (the shortest length at which the clamped helix loses stability,
    within `max_length`; `inf` where it is stable up to `max_length`, NaN where not
    computed or defined); `pointwise_stable` the `stable` of `helix_equilibria` (a local
    minimum of $W$ on the circle of registers), for comparison; `kappa`, `tau` (`batch`),
    `length`, `max_length`."""

    kappa: Float[Array, "*batch"]
    tau: Float[Array, "*batch"]
    length: Float[Array, ""]
    max_length: Float[Array, ""]
    valid: Bool[Array, "*batch 4"]
    pointwise_stable: Bool[Array, "*batch 4"]
    instability_index: Int[Array, "*batch 4"]
    stability_margin: Float[Array, "*batch 4"]
    critical_length: Float[Array, "*batch 4"]

    @property
    def stable(self) -> Bool[Array, "*batch 4"]:
        """Valid slots whose clamped helix of length `length` is stable."""
        return self.valid & (self.instability_index == 0)


def _body_variation_matrix(rod, n, m):
    """The 12 x 12 matrix $A$ of the linearised equations in body variations
    $(\\eta, \\xi, \\delta n, \\delta m)$ along the uniform helix with body wrench (n, m)
    (module docstring)."""
    u = rod.twist(m)
    e3 = jnp.zeros(3, n.dtype).at[2].set(1.0)
    du_dm = jax.jacfwd(rod.twist)(m)

    def rate(v):
        eta, xi, dn, dm = v[:3], v[3:6], v[6:9], v[9:]
        du = du_dm @ dm
        return jnp.concatenate([
            jnp.cross(xi, e3) - jnp.cross(u, eta),
            du - jnp.cross(u, xi),
            -jnp.cross(du, n) - jnp.cross(u, dn),
            -jnp.cross(du, m) - jnp.cross(u, dm) - jnp.cross(e3, dn),
        ])

    return jax.jacfwd(rate)(jnp.zeros(12, n.dtype))


def uniform_transfers(rod, n, m, length, pieces: int):
    """Transfer matrices `(pieces, 12, 12)` (as `piece_transfer`) of the pieces of a clamped
    uniform helix with body wrench (n, m) starting at the identity frame, the lab force and
    the end position."""
    h = length / pieces
    u = rod.twist(m)
    T_body = _body_transfer(rod, n, m, h)  # with the integrated test's tiny extensibility
    frames = jax.vmap(lambda j: so3_exp(u * (j * h)))(jnp.arange(pieces + 1))

    def lab(D0, D1):
        return jax.scipy.linalg.block_diag(D1, D1, D1, D1) @ T_body @ jax.scipy.linalg.block_diag(D0, D0, D0, D0).T

    transfers = jax.vmap(lab)(frames[:-1], frames[1:])
    # The centreline's end: the helix's screw motion, from the same exponential.
    se3 = jnp.zeros((4, 4), n.dtype).at[:3, :3].set(hat(u)).at[3 - 1, 3].set(1.0)
    end_position = _expm(se3 * length)[:3, 3]
    return transfers, n, end_position


#: Lengths sampled in (0, max_length] for the first sign change of the conjugate-point
#: determinant, before bisection.
CRITICAL_SAMPLES = 64


#: Fixed scaling and squaring of `_expm`: exact to round-off for $\\|A\\|_1 \\le$ `EXPM_RANGE`.
EXPM_SQUARINGS, EXPM_TERMS, EXPM_RANGE = 16, 12, 600.0


def _expm(A):
    """$e^A$ by a Taylor polynomial of $A/2^{16}$ and 16 squarings: no data-dependent loop
    (`jax.scipy.linalg.expm` chooses its squarings from the norm, a loop that, batched,
    was measured to stall); NaN beyond `EXPM_RANGE`."""
    scaled = A / 2.0**EXPM_SQUARINGS
    eye = jnp.eye(A.shape[-1], dtype=A.dtype)
    E = eye
    for k in range(EXPM_TERMS, 0, -1):  # Horner: I + X/1 (I + X/2 (I + ...))
        E = eye + scaled @ E / k
    for _ in range(EXPM_SQUARINGS):
        E = E @ E
    return jnp.where(jnp.sum(jnp.abs(A), axis=0).max() <= EXPM_RANGE, E, jnp.nan)


def _to_lab(n, m, sign=1.0):
    """Body variations (eta, xi, dn, dm) to the test's (dx, dtheta, dN, dM) at the identity
    frame (module docstring); `sign=-1` the inverse (I + L with L^2 = 0: its inverse is I - L)."""
    zero, eye = jnp.zeros((3, 3), n.dtype), jnp.eye(3, dtype=n.dtype)
    n_, m_ = -sign * hat(n), -sign * hat(m)
    return jnp.block([[eye, zero, zero, zero], [zero, eye, zero, zero], [zero, n_, eye, zero], [zero, m_, zero, eye]])


def _with_extensibility(rod, T, s):
    """`T` with the tiny extensibility of the integrated test (`piece_transfer`)."""
    return T.at[:3, 6:9].add(EXTENSIBILITY * s**3 / stiffness_range(rod)[1] * jnp.eye(3, dtype=T.dtype))


def _body_transfer(rod, n, m, s):
    """Transfer matrix of a piece of length `s` in body coordinates at its two ends (lab
    ones for a start at the identity frame, up to the end's rotation)."""
    T = _to_lab(n, m) @ _expm(_body_variation_matrix(rod, n, m) * s) @ _to_lab(n, m, -1.0)
    return _with_extensibility(rod, T, s)


def _critical_length(rod, n, m, max_length, bisections: int):
    """The first zero in (0, `max_length`] of the conjugate-point determinant
    $\\det\\partial(x, \\theta)(s)/\\partial(N, M_0)$ of the clamped helix (Manning, Rogers &
    Maddocks 1998: the isoperimetric conjugate points, the multiplier $N$ varied with $M_0$);
    `inf` if it has none there.  Zeros of even multiplicity, which need a symmetry, leave
    the sign unchanged and are missed (the index at `length` still counts them); and where
    the helix is spatially unstable (`wrench_growth_rate` $\\lambda > 0$) the determinant's
    entries grow like $e^{\\lambda s}$ and its sign loses precision at long lengths (measured:
    lengths near 19 of a `max_length` of 20 moved by 1-5 % between two ways of evaluating
    it, those below 12 not at all) -- the index at `length` is the robust answer."""
    sign = lambda s: jnp.sign(determinant_small(_body_transfer(rod, n, m, s)[:6, 6:]))  # noqa: E731
    lengths = max_length * jnp.arange(1, CRITICAL_SAMPLES + 1) / CRITICAL_SAMPLES
    # The samples by powers of one step's exponential (the flow is a one-parameter group).
    to_lab, step = _to_lab(n, m), _expm(_body_variation_matrix(rod, n, m) * lengths[0])
    to_body = _to_lab(n, m, -1.0)

    def sample(E, s):
        E = E @ step
        return E, jnp.sign(determinant_small(_with_extensibility(rod, to_lab @ E @ to_body, s)[:6, 6:]))

    _, signs = jax.lax.scan(sample, jnp.eye(12, dtype=n.dtype), lengths)
    first_sign = sign(max_length * 1e-3 / CRITICAL_SAMPLES)
    changed = signs != first_sign
    j = jnp.argmax(changed)
    lo = jnp.where(j > 0, lengths[jnp.maximum(j - 1, 0)], 0.0)
    hi = lengths[j]

    def bisect(bracket, _):
        lo, hi = bracket
        mid = 0.5 * (lo + hi)
        same = sign(mid) == first_sign
        return (jnp.where(same, mid, lo), jnp.where(same, hi, mid)), None

    (lo, hi), _ = jax.lax.scan(bisect, (lo, hi), None, length=bisections)
    return jnp.where(jnp.any(changed), 0.5 * (lo + hi), jnp.inf)


def _clamped_helix_stability(rod, n, m, length, pieces: int):
    """(index, margin) of the helix with body wrench (n, m) clamped over `length` (its start
    at the origin with identity frame: the test is invariant under rigid motions, and the
    lab wrench at the start is the body one)."""
    transfers, N, end_position = uniform_transfers(rod, n, m, length, pieces)
    index, margin, _ = assess(rod, length, end_condition(CLAMPED), N, transfers, end_position, jnp.linalg.norm(m))
    return index, margin


@eqx.filter_jit
def _atlas(rod, kappa, tau, length, pieces: int, chunk_size: int):
    eq = helix_equilibria(rod, kappa, tau)
    shape = eq.valid.shape
    n = jnp.where(eq.valid[..., None], eq.n, 0.0).reshape(-1, 3)
    m = jnp.where(eq.valid[..., None], eq.m, 0.0).reshape(-1, 3)
    index, margin = jax.lax.map(lambda w: _clamped_helix_stability(rod, *w, length, pieces), (n, m), batch_size=chunk_size)
    valid = eq.valid.reshape(-1)
    index = jnp.where(valid, index, -1).reshape(shape)
    margin = jnp.where(valid, margin, jnp.nan).reshape(shape)
    return eq.valid, eq.stable, index, margin, n, m


@eqx.filter_jit
def _critical_lengths(rod, n, m, valid, max_length, bisections: int, chunk_size: int):
    # A program of its own: compiled into `_atlas`, beside the batched eigh of the index, it
    # deadlocked XLA's CPU thread pool (jaxlib 0.10.2, 2 cores, concurrency-optimised
    # scheduler) on a 10 x 10 grid; apart, neither does.
    critical = jax.lax.map(lambda w: _critical_length(rod, *w, max_length, bisections), (n, m), batch_size=chunk_size)
    return jnp.where(valid, critical.reshape(valid.shape), jnp.nan)


def stability_atlas(
    rod,
    kappa: ArrayLike,
    tau: ArrayLike,
    length: ArrayLike,
    *,
    critical_length: bool = True,
    max_length: ArrayLike | None = None,
    bisections: int = 24,
    pieces: int = 16,
    chunk_size: int = 256,
) -> StabilityAtlas:
    """Stability of every uniform helix $(\\kappa, \\tau)$ (all registers) when a piece of
    length `length` of it is held between clamps by its own wrench (module docstring).

    - `rod`: one `Rod`; `kappa`, `tau`: broadcasting arrays (e.g. a `meshgrid`).
    - `critical_length`: also find the shortest length at which each clamped helix loses
      stability: the first zero of the conjugate-point determinant in $(0,$ `max_length`$]$
      (default `4 * length`), bracketed on 64 lengths and refined by `bisections` halvings.
    - `pieces`: pieces of each test (`BoundaryValueOptions.stability_pieces`); where they do
      not resolve a helix's wrench its index is -1: raise them.
    - `chunk_size`: helices tested at once (memory).

    Returns a `StabilityAtlas`.  Compiled once per grid shape and settings.

    **Example**

    ```python
    rod = helixrod.Rod(1.0, 1.5, 0.8, uhat=(0.0, 1.0, 0.3))
    kappa, tau = jnp.meshgrid(jnp.linspace(0.2, 2.0, 40), jnp.linspace(-1.0, 1.0, 40))
    atlas = helixrod.stability_atlas(rod, kappa, tau, 10.0)
    atlas.stable[..., 0], atlas.critical_length[..., 0]
    ```
    """
    owner = "stability_atlas"
    check_one_rod(rod, owner)
    dtype = float_dtype()
    kappa, tau = (jnp.asarray(a, dtype) for a in (kappa, tau))
    for name, a in (("kappa", kappa), ("tau", tau)):
        if not np.all(np.isfinite(np.asarray(a))):
            raise ValueError(f"{owner}: {name} must be finite")
    try:
        kappa, tau = jnp.broadcast_arrays(kappa, tau)
    except ValueError:
        raise ValueError(f"{owner}: kappa {kappa.shape} and tau {tau.shape} do not broadcast") from None
    length = finite_scalar(length, "length", owner, positive=True)
    max_length = 4 * length if max_length is None else finite_scalar(max_length, "max_length", owner, positive=True)
    bisections = check_integer(bisections, "bisections", owner)
    pieces = check_integer(pieces, "pieces", owner)
    chunk_size = check_integer(chunk_size, "chunk_size", owner)
    valid, pointwise, index, margin, n, m = _atlas(rod, kappa, tau, jnp.asarray(length, dtype), pieces, chunk_size)
    if critical_length:
        critical = _critical_lengths(rod, n, m, valid, jnp.asarray(max_length, dtype), bisections, chunk_size)
    else:
        critical = jnp.full(valid.shape, jnp.nan, dtype)
    return StabilityAtlas(
        kappa=kappa, tau=tau, length=jnp.asarray(length, dtype), max_length=jnp.asarray(max_length, dtype),
        valid=valid, pointwise_stable=pointwise, instability_index=index, stability_margin=margin,
        critical_length=critical,
    )
