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

**The type of the instability** at $L_c$ (Lyapunov--Schmidt).  The clamped piece is the
equation $F(w) = g$: the start wrench $w = (N, M_0)$ to the end pose $g$; at $L_c$ its
linearisation $B = \\partial(\\delta x, \\delta\\theta)/\\partial(\\delta N, \\delta M_0)$ (end body
coordinates) has a null vector, the start wrench of the Jacobi field (`critical_mode`), and a
left null vector $\\ell$, $\\ell^T B = 0$: by the reciprocity of the second variation, the
Jacobi field's reaction on the end clamp.  The experimenter moves the end by the helix's
axial controls: $c_1$ = extension along its axis ($\\delta x = a$, $\\delta\\theta = 0$), $c_2$ =
rotation about it ($\\delta\\theta = a$, $\\delta x = a\\times r$), in body coordinates $a = u/|u|$
and $r = (e_3\\times u)/|u|^2$ from the axis to the end: the screw axis of the helix, which is
the central axis of its wrench, $r = (m\\times n)/|n|^2$, where $n \\ne 0$, and is defined
where $n = 0$ as well.  $F(w) = g + \\varepsilon c$ is solvable near the helix to first order
only if $\\ell\\cdot c = 0$ (the projection of the equation on the cokernel).  So if
$\\ell\\cdot c \\ne 0$ for a control, the solutions form one curve through the helix, tangent
to the Jacobi field, along which $\\varepsilon$ is stationary: the response to that control
turns back, a **fold** (limit point; the stiffness $c^T D B^{-1} c$ of the piece to it has a
pole at $L_c$).  If $\\ell\\cdot c_1 = \\ell\\cdot c_2 = 0$ the control path stays in the range of
$B$: the family of helices continues through $L_c$ and a second family crosses it, a
**symmetry-breaking** bifurcation (branch point).  That is what a symmetry forces: the
reversal of a helix whose register has $u_1 = 0$ (a rotation by $\\pi$ about the principal
normal at its middle, for a rod with $W(-u_1, u_2, u_3) = W(u)$) maps the controls to
themselves, so an antisymmetric Jacobi field has $\\ell\\cdot c = 0$; the rotations of a
straight twisted rod about its axis make every Jacobi field non-axisymmetric (Greenhill's
shaft, $L_c = 8.9868\\,K/M$, a double conjugate point).  $\\ell$ is paired in the dimensionless
variations $(\\delta x/L_c, \\delta\\theta)$ and the pairings below `BRANCH_TOLERANCE` of the
sizes count as zero.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._compile import committed_placement, compile_ahead, filter_jit, jit, leaf_shapes, once_per_signature
from .._equilibria import helix_equilibria
from .._misc import check_integer, finite_scalar, float_dtype, is_concrete, negative_count, solve_small
from .._lie import hat, se3_exp, so3_exp
from .._progress import ProgressArgument, batch_size, check_progress, progress_bar, scan_in_batches
from .._rod import check_one_rod, check_quadratic_rod
from ._ends import CLAMPED, end_condition
from ._options import check_test_pieces
from ._stability import EXTENSIBILITY, assess, piece_hessian, resolves, stiffness_range


class StabilityAtlas(eqx.Module):
    """Result of `stability_atlas`: per point of the $(\\kappa, \\tau)$ grid and register slot
    (shape `batch + (4,)`, slots as `helix_equilibria`): `valid` (the register exists),
    `stable` (the clamped helix of length `length` is stable), `instability_index`
    (unstable directions; -1 where not defined: invalid slot, or the pieces of the test do
    not resolve the wrench -- raise `pieces`), `stability_margin` (NaN where not defined),
    `critical_length` (the shortest length at which the clamped helix loses stability,
    within `max_length`; `inf` where it is stable up to `max_length`, NaN where not
    computed or defined: not asked for, or the sample step `max_length / 64` does not
    resolve the wrench); `instability_type` the type of that loss of stability (module
    docstring; names in `INSTABILITY_TYPES`): 0 none (stable up to `max_length`, or not
    computed), 1 fold (limit point of the response to the axial controls), 2
    symmetry-breaking (branch point), -1 not defined (invalid slot, or `critical_length`
    NaN); `critical_mode` (`batch + (4, 6)`) the buckling mode: the start-wrench variation
    $(\\delta N, \\delta M_0)$ of the Jacobi field at `critical_length`, as the unit vector
    $(L_c\\,\\delta N, \\delta M_0)/|\\cdot|$ (sign arbitrary; NaN where there is no critical
    length); `pointwise_stable` the `stable` of `helix_equilibria` (a local
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
    instability_type: Int[Array, "*batch 4"]
    critical_mode: Float[Array, "*batch 4 6"]

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
    # The centreline's end: the helix's screw motion (in closed form: any number of turns).
    end_position = se3_exp(u * length, jnp.zeros(3, n.dtype).at[2].set(length))[1]
    return transfers, n, end_position


#: Lengths sampled in (0, max_length] for the first conjugate point, before bisection.
CRITICAL_SAMPLES = 64

#: Names of the `instability_type` codes 0, 1, 2 of `StabilityAtlas` (-1: not defined).
INSTABILITY_TYPES = ("none", "fold", "symmetry-breaking")
NONE, FOLD, SYMMETRY_BREAKING = range(3)

#: The axial controls lie in the range of $B$ (a symmetry-breaking loss of stability) where
#: their pairings with the unit left null vector are below this, relative to their size:
#: far above the round-off of a symmetric pairing (~1e-10), far below a fold's (~1e-2).
BRANCH_TOLERANCE = 1e-4

#: Inverse iterations for the Jacobi field at the critical length: the smallest eigenvalue
#: of the last Schur complement, after the bisections, lies ~1e-6 or more below the next.
NULL_ITERATIONS = 3


#: Fixed scaling and squaring of `_expm`: exact to round-off for $\\|A\\|_1 \\le$ `EXPM_RANGE`.
EXPM_SQUARINGS, EXPM_TERMS, EXPM_RANGE = 16, 12, 600.0


def _expm(A):
    """$e^A$ by a Taylor polynomial of $A/2^{16}$ and 16 squarings: no data-dependent loop
    (`jax.scipy.linalg.expm` chooses its squarings from the norm, a loop that, batched,
    was measured to stall); NaN beyond `EXPM_RANGE`.  For `_body_variation_matrix`, whose
    blocks carry units, through `_variation_exponential`."""
    scaled = A / 2.0**EXPM_SQUARINGS
    eye = jnp.eye(A.shape[-1], dtype=A.dtype)
    E = eye
    for k in range(EXPM_TERMS, 0, -1):  # Horner: I + X/1 (I + X/2 (I + ...))
        E = eye + scaled @ E / k
    for _ in range(EXPM_SQUARINGS):
        E = E @ E
    return jnp.where(jnp.sum(jnp.abs(A), axis=0).max() <= EXPM_RANGE, E, jnp.nan)


def _variation_exponential(rod, A, s, length_scale):
    """$e^{As}$ of the body variation matrix `A` (`_body_variation_matrix`), computed in
    variables made dimensionless by `length_scale` and the rod's mean stiffness $\\bar K$
    (positions over the length, forces over $\\bar K/\\ell^2$, moments over $\\bar K/\\ell$:
    a similarity, $e^{As} = D^{-1}e^{DAD^{-1}s}D$), so that `_expm`'s range is one of
    dimensionless rates: in raw units $\\partial u/\\partial m = K^{-1}$ alone exceeded it
    for a rod in SI units, and every helix came out not resolved."""
    k_mean = stiffness_range(rod)[1]
    ones = jnp.ones(3, A.dtype)
    d = jnp.concatenate([ones / length_scale, ones, ones * length_scale**2 / k_mean, ones * length_scale / k_mean])
    E = _expm(d[:, None] * A / d[None, :] * s)
    return E * d[None, :] / d[:, None]


def _to_lab(n, m, sign=1.0):
    """Body variations (eta, xi, dn, dm) to the test's (dx, dtheta, dN, dM) at the identity
    frame (module docstring); `sign=-1` the inverse (I + L with L^2 = 0: its inverse is I - L)."""
    zero, eye = jnp.zeros((3, 3), n.dtype), jnp.eye(3, dtype=n.dtype)
    n_, m_ = -sign * hat(n), -sign * hat(m)
    return jnp.block([[eye, zero, zero, zero], [zero, eye, zero, zero], [zero, n_, eye, zero], [zero, m_, zero, eye]])


def _with_extensibility(rod, T, s):
    """`T` with the tiny extensibility of the integrated test (`piece_transfer`)."""
    return T.at[:3, 6:9].add(EXTENSIBILITY * s**3 / stiffness_range(rod)[1] * jnp.eye(3, dtype=T.dtype))


def _body_transfer(rod, n, m, s, exponential=None):
    """Transfer matrix of a piece of length `s` in body coordinates at its two ends (lab
    ones for a start at the identity frame, up to the end's rotation); `exponential`:
    $e^{As}$ of `_body_variation_matrix`, where the caller has it."""
    if exponential is None:
        exponential = _variation_exponential(rod, _body_variation_matrix(rod, n, m), s, s)
    T = _to_lab(n, m) @ exponential @ _to_lab(n, m, -1.0)
    return _with_extensibility(rod, T, s)


def _node_blocks(transfer, scale):
    """The blocks (H_aa, H_ab, H_bb) of the Hessian of a piece with body `transfer` matrix
    (`_body_transfer`) in its two nodes' body variations (`piece_hessian`; the symmetric part,
    as `second_variation`), the node positions scaled by `scale` (a congruence: the inertia
    is unchanged, the pivots balanced)."""
    weight = jnp.concatenate([jnp.full(3, scale), jnp.ones(3, transfer.dtype)])
    H = piece_hessian(transfer) * jnp.tile(weight, 2)[:, None] * jnp.tile(weight, 2)[None, :]
    H = 0.5 * (H + H.T)
    return H[:6, :6], H[:6, 6:], H[6:, 6:]


def _conjugate_point(rod, n, m, max_length, bisections: int):
    """(length, mode, reaction) of the clamped helix with body wrench (n, m): its first
    conjugate point in (0, `max_length`] (Manning, Rogers & Maddocks 1998: the isoperimetric
    conjugate points, where $\\det\\partial(x, \\theta)(s)/\\partial(N, M_0) = 0$), `inf` if it
    has none there, NaN where the sample step does not resolve the wrench; the unit start
    wrench $(L\\,\\delta N, \\delta M_0)$ of its Jacobi field and the field's unit reaction on the end
    clamp, paired with the end's $(\\delta x / L, \\delta\\theta)$.

    Counted, not sought as a sign change of that determinant, because a symmetry makes its
    zeros double (a straight twisted rod of isotropic bending: the determinant is a squared
    modulus and touches zero at Greenhill's length).  The index of the clamped piece of length
    $(k + 1)\\Delta + r$ ($\\Delta$ = `max_length / CRITICAL_SAMPLES`) is that of the broken
    extremal of `_stability.py` on $k + 1$ pieces of $\\Delta$ and one of $r$, whose block
    tridiagonal Hessian has every piece alike in body coordinates.  Its block $LDL^T$
    elimination is a Riccati recursion: $S_1 = P$, $S_{j+1} = P - Q^T S_j^{-1} Q$ ($P$ the
    node block, $Q$ the coupling), and the index is the sum of the negative eigenvalues of the
    $S_j$ (Sylvester).  The first $S_j$ with a negative eigenvalue brackets the conjugate
    point; bisection on $r$ of the same count refines it.  There the last $S_k$ is singular:
    its null vector, back-substituted ($\\zeta_j = -S_j^{-1}Q\\zeta_{j+1}$), is the Jacobi field
    at the nodes; its start wrench is the mode, its reaction on the end clamp the left null
    vector $\\ell$ of $B$ (module docstring)."""
    step = max_length / CRITICAL_SAMPLES
    resolved = resolves(rod, step, n, jnp.linalg.norm(m))
    A = _body_variation_matrix(rod, n, m)

    def transfer(s, exponential=None):
        return _body_transfer(rod, n, m, s, _variation_exponential(rod, A, s, step) if exponential is None else exponential)

    transfer_step = transfer(step)
    H_aa, Q, H_bb = _node_blocks(transfer_step, step)
    node = H_bb + H_aa

    def sample(G, _):
        S = node - G  # the Schur complement at node j: clamped length (j + 1) step
        return Q.T @ solve_small(S, Q), (negative_count(S), S)

    _, (counts, schur) = jax.lax.scan(sample, jnp.zeros((6, 6), n.dtype), None, length=CRITICAL_SAMPLES - 1)
    changed = counts > 0
    k = jnp.argmax(changed)
    G = node - schur[k]  # the correction at the last free node

    def last_schur(last_transfer):
        return H_bb + _node_blocks(last_transfer, step)[0] - G

    # Bisection on r in (0, step): the exponential at the midpoint is the one at the lower
    # end times that of the half-width, e^{A step / 2^(j+1)} at halving j, all squared up
    # from the smallest -- one product a halving instead of an exponential (its 28 products).
    smallest = _variation_exponential(rod, A, step / 2.0**bisections, step)
    _, halves = jax.lax.scan(lambda E, _: (E @ E, E), smallest, None, length=bisections)

    def bisect(bracket, half):
        lo, hi, exponential_lo = bracket
        mid = 0.5 * (lo + hi)
        exponential_mid = exponential_lo @ half
        before = negative_count(last_schur(transfer(mid, exponential_mid))) == 0
        return (jnp.where(before, mid, lo), jnp.where(before, hi, mid), jnp.where(before, exponential_mid, exponential_lo)), None

    start = (jnp.zeros((), n.dtype), step, jnp.eye(12, dtype=n.dtype))
    (lo, hi, _), _ = jax.lax.scan(bisect, start, halves, reverse=True)  # the largest half first
    r = 0.5 * (lo + hi)
    transfer_r = transfer(r)
    found = jnp.any(changed)
    length = jnp.where(found, (k + 1) * step + r, jnp.inf)
    length = jnp.where(resolved, length, jnp.nan)

    # The Jacobi field at the nodes, scaled (dx / step, dtheta): the null vector of the last
    # Schur complement, then back along the others (those beyond node k left as they are).
    last = _null_vector(last_schur(transfer_r))

    def back(zeta, j):
        earlier = -solve_small(schur[j], Q @ zeta)
        return jnp.where(j < k, earlier, zeta), None

    first, _ = jax.lax.scan(back, last, jnp.arange(CRITICAL_SAMPLES - 1), reverse=True)
    weight = jnp.concatenate([jnp.full(3, step), jnp.ones(3, n.dtype)])
    # The start wrench that bends the first piece into it (B^{-1} of that piece), as
    # (L dN, dM0): both parts moments.
    wrench = solve_small(transfer_step[:6, 6:], weight * first)
    mode = jnp.concatenate([length * wrench[:3], wrench[3:]])
    mode = mode / jnp.linalg.norm(mode)
    # Its reaction on the end clamp, paired with (dx / step, dtheta), then (dx / L, dtheta).
    reaction = _node_blocks(transfer_r, step)[1].T @ last * jnp.concatenate([jnp.full(3, length / step), jnp.ones(3, n.dtype)])
    return length, mode, reaction / jnp.linalg.norm(reaction)


def _critical_point(rod, n, m, max_length, bisections: int):
    """(critical length, instability type, critical mode) of the clamped helix with body
    wrench (n, m) (`_conjugate_point`; module docstring): type 0 where it has no conjugate
    point within `max_length`, -1 where not resolved; the mode NaN where there is none."""
    length, mode, reaction = _conjugate_point(rod, n, m, max_length, bisections)
    controls = _axial_controls(rod, m, length)
    pairing = jnp.abs(controls @ reaction) / jnp.linalg.norm(controls, axis=1)
    kind = jnp.where(jnp.all(pairing < BRANCH_TOLERANCE), SYMMETRY_BREAKING, FOLD)
    kind = jnp.where(jnp.isfinite(length), kind, jnp.where(jnp.isnan(length), -1, NONE))
    return length, kind.astype(jnp.int32), jnp.where(jnp.isfinite(length), mode, jnp.nan)


def _axial_controls(rod, m, length):
    """The two axial controls of the end, (dx / length, dtheta) in its body coordinates
    `(2, 6)`: extension along the helix axis and rotation about it (module docstring)."""
    u = rod.twist(m)
    e3 = jnp.zeros(3, m.dtype).at[2].set(1.0)
    size = jnp.linalg.norm(u)
    straight = size == 0
    axis = jnp.where(straight, e3, u / jnp.where(straight, 1.0, size))
    # From the axis to the end: the screw axis of the helix's motion (velocity e3, angular
    # velocity u) -- where the force is not zero, the central axis of its wrench.
    r = jnp.where(straight, 0.0, jnp.cross(e3, u) / jnp.where(straight, 1.0, size**2))
    zero = jnp.zeros(3, m.dtype)
    return jnp.stack([jnp.concatenate([axis / length, zero]), jnp.concatenate([jnp.cross(axis, r) / length, axis])])


def _null_vector(S):
    """The unit vector spanning (nearly) the null space of a (nearly) singular small symmetric
    matrix, by inverse iteration (each solve amplifies the direction of the eigenvalue nearest
    zero by its inverse); a shift of round-off size keeps an exactly singular one finite."""
    S = S + 1e-14 * jnp.max(jnp.abs(S)) * jnp.eye(S.shape[-1], dtype=S.dtype)
    v = jnp.array([0.9, -0.7, 0.6, 0.8, -0.5, 0.4], S.dtype)  # generic: no symmetry's zero

    def iterate(_, v):
        v = solve_small(S, v)
        return v / jnp.linalg.norm(v)

    return jax.lax.fori_loop(0, NULL_ITERATIONS, iterate, v)


def _clamped_helix_stability(rod, n, m, length, pieces: int):
    """(index, margin) of the helix with body wrench (n, m) clamped over `length` (its start
    at the origin with identity frame: the test is invariant under rigid motions, and the
    lab wrench at the start is the body one)."""
    transfers, N, end_position = uniform_transfers(rod, n, m, length, pieces)
    resolved = resolves(rod, length / pieces, N, jnp.linalg.norm(m))
    index, margin, _ = assess(rod, length, end_condition(CLAMPED), N, jax.vmap(piece_hessian)(transfers), end_position, resolved)
    return index, margin


def _registers(rod, kappa, tau):
    """The registers of the grid: `valid`, `stable` (`batch + (4,)`) and the body wrenches
    `n`, `m` of every helix, flat `(4 * kappa.size, 3)` (zero where not valid)."""
    eq = helix_equilibria(rod, kappa, tau)
    n = jnp.where(eq.valid[..., None], eq.n, 0.0).reshape(-1, 3)
    m = jnp.where(eq.valid[..., None], eq.m, 0.0).reshape(-1, 3)
    return eq.valid, eq.stable, n, m


def _in_whole_chunks(test, n, m, chunk_size: int):
    """`test(n_i, m_i)` of every helix in vmaps of `chunk_size` helices one after another
    (`lax.map`), the last chunk padded with zero wrenches (results dropped).  `lax.map` would
    test the helices past the last whole chunk in a vmap of their own, a second copy of the
    test in the program: the atlas of a 20 x 20 grid (1600 helices, chunks of 256) compiled
    its two programs in 1.8 and 5.6 s with it, 0.9 and 3.2 s without."""
    total = n.shape[0]
    padding = -total % chunk_size
    n, m = (jnp.concatenate([a, jnp.zeros((padding,) + a.shape[1:], a.dtype)]) for a in (n, m))
    tested = jax.lax.map(lambda w: test(*w), (n, m), batch_size=chunk_size)
    return jax.tree.map(lambda a: a[:total], tested)


def _indices(rod, n, m, length, pieces: int, chunk_size: int):
    return _in_whole_chunks(lambda n, m: _clamped_helix_stability(rod, n, m, length, pieces), n, m, chunk_size)


def _critical_points(rod, n, m, max_length, bisections: int, chunk_size: int):
    return _in_whole_chunks(lambda n, m: _critical_point(rod, n, m, max_length, bisections), n, m, chunk_size)


# Three programs.  The registers hold the register kernel's custom call, which `jax.export`
# refuses, so the tests are programs of their own that the trace cache keeps: the warm first
# call of the 20 x 20 atlas of `benchmarks/bench_first_calls.py` no longer traces them
# (~2.5 s of Python on 2 cores).  The critical lengths apart from the index: compiled into
# one program beside the index's batched eigh, they deadlocked XLA's CPU thread pool
# (jaxlib 0.10.2, 2 cores, concurrency-optimised scheduler) on a 10 x 10 grid; apart,
# neither does.  So no LAPACK call in the critical lengths either.
_registers_of = filter_jit(_registers)
_indices_of = jit(_indices, static_argnames=("pieces", "chunk_size"), trace_cache=True)


@jit(static_argnames=("bisections", "chunk_size"), trace_cache=True)
def _critical_lengths(rod, n, m, max_length, bisections: int, chunk_size: int):
    return _critical_points(rod, n, m, max_length, bisections, chunk_size)


def _atlas_signature(rod, grid, max_length, bisections: int, chunk_size: int):
    return jax.tree.structure(rod), leaf_shapes((rod, grid, max_length)), committed_placement((rod, grid)), bisections, chunk_size


@once_per_signature(_atlas_signature)
def _compile_side_by_side(rod, grid, max_length, bisections: int, chunk_size: int) -> bool:
    """At the first atlas of its kind: start compiling the critical lengths' program on a
    thread of its own (`compile_ahead`, for the body wrenches that `_registers_of` will give it
    from the arguments `grid` of its call, placed as they place them), while the index
    program is traced, compiled and run.  Measured on the
    20 x 20 atlas of `benchmarks/bench_first_calls.py` (2 cores, fresh processes
    alternating): first call 4.5-5.3 s (median 4.9) against 5.6-7.3 s (median 6.1)."""
    wrenches = jax.ShapeDtypeStruct((4 * grid[1].size, 3), max_length.dtype, sharding=committed_placement((rod, grid)))
    return compile_ahead(_critical_lengths, rod, wrenches, wrenches, max_length, bisections, chunk_size) is not None


@jit
def _defined_where_valid(valid, index, margin, critical, kind, mode):
    """The tests' flat results in the grid's shape `valid.shape` (`batch + (4,)`), marked
    not defined (-1, NaN) where the slot is not valid; `critical`, `kind` and `mode` None
    where not computed (not defined anywhere).  One program, not a dozen of one operation."""
    shape = valid.shape
    index = jnp.where(valid, index.reshape(shape), -1)
    margin = jnp.where(valid, margin.reshape(shape), jnp.nan)
    if critical is None:
        critical = jnp.full(shape, jnp.nan, margin.dtype)
        kind = jnp.where(valid, NONE, -1).astype(jnp.int32)
        mode = jnp.full(shape + (6,), jnp.nan, margin.dtype)
    else:
        critical = jnp.where(valid, critical.reshape(shape), jnp.nan)
        kind = jnp.where(valid, kind.reshape(shape), -1)
        mode = jnp.where(valid[..., None], mode.reshape(shape + (6,)), jnp.nan)
    return index, margin, critical, kind, mode


def _test_helices(rod, kappa, tau, length, max_length, critical_length: bool, bisections, pieces, chunk_size, report):
    """valid, pointwise stable, index, margin, critical length, type and mode of the grid
    (`kappa`, `tau` of one shape); in one call of each program, or, where `report` is shown,
    in host-side batches of helices, advancing it after each.

    The helices are tested in chunks of equal width, at most `chunk_size` and as few as
    that allows (`_in_whole_chunks` pads the last; 1600 helices in chunks of 256: 7 of
    229, not 6 of 256 and 64 in a vmap of their own), and a batch is a whole number of
    those chunks (the last batch padded): every helix is then tested in a vmap of the same
    width either way, so the results are the same bit for bit (the width changes the
    rounding of the stability margin, by 1e-8 relative, measured)."""
    total = 4 * kappa.size  # every register of every point
    chunk_size = -(-total // -(-total // chunk_size))
    if not report.shown:
        if critical_length:
            _compile_side_by_side(rod, (kappa, tau, length), max_length, bisections, chunk_size)
        valid, pointwise, n, m = _registers_of(rod, kappa, tau)
        index, margin = _indices_of(rod, n, m, length, pieces, chunk_size)
        if critical_length:
            critical, kind, mode = _critical_lengths(rod, n, m, max_length, bisections, chunk_size)
    else:
        valid, pointwise, n, m = _registers_of(rod, kappa, tau)

        def test(_, wrench):
            out = _indices_of(rod, *wrench, length, pieces, chunk_size)
            if critical_length:
                out += _critical_lengths(rod, *wrench, max_length, bisections, chunk_size)
            return None, out

        chunks = -(-n.shape[0] // chunk_size)
        size = batch_size(chunks) * chunk_size  # whole chunks: the last batch padded
        out = scan_in_batches(test, None, (n, m), n.shape[0], size, report)[1]
        index, margin = out[:2]
        if critical_length:
            critical, kind, mode = out[2:]
    if not critical_length:
        critical = kind = mode = None
    return (valid, pointwise) + _defined_where_valid(valid, index, margin, critical, kind, mode)


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
    progress: ProgressArgument = None,
) -> StabilityAtlas:
    """Stability of every uniform helix $(\\kappa, \\tau)$ (all registers) when a piece of
    length `length` of it is held between clamps by its own wrench (module docstring).

    - `rod`: one `Rod`; `kappa`, `tau`: broadcasting arrays (e.g. a `meshgrid`).
    - `critical_length`: also find the shortest length at which each clamped helix loses
      stability: its first conjugate point in $(0,$ `max_length`$]$ (default `4 * length`),
      counted with its multiplicity on 64 lengths and refined by `bisections` halvings
      (NaN where that step does not resolve the wrench, as `pieces` for the index), the
      type of the instability there (fold or symmetry-breaking, with respect to the axial
      controls of the end) and its mode.
    - `pieces`: pieces of each test (`BoundaryValueOptions.stability_pieces`); where they do
      not resolve a helix's wrench its index is -1: raise them.
    - `chunk_size`: the most helices tested at once (memory); they go in as few chunks of
      one width as that allows.
    - `progress`: `None` (default) shows a rich progress bar of the helices tested when
      stdout is a terminal and there is more than one chunk, `True`/`False` force it on or
      off, and a callable is called as `progress(done, total)` instead of a bar (`total`
      = 4 `kappa.size` after broadcasting: every register of every point).  While progress
      is shown the helices are tested in up to 20 host-side batches of whole chunks (one
      compiled program, the last batch padded), with the same results bit for bit; else
      in one call.

    Returns a `StabilityAtlas`.  Compiled once per grid shape and settings.  Its inputs
    must be concrete (it tests the grid in host-side chunks, as `sweep`): under `jax.jit`,
    `vmap` or `grad` it raises `ValueError`; call it once per rod or length.

    **Example**

    ```python
    rod = helixrod.Rod(1.0, 1.5, 0.8, uhat=(0.0, 1.0, 0.3))
    kappa, tau = jnp.meshgrid(jnp.linspace(0.2, 1.0, 40), jnp.linspace(-0.5, 0.5, 40))
    atlas = helixrod.stability_atlas(rod, kappa, tau, 5.0)
    atlas.stable[..., 0], atlas.critical_length[..., 0]
    ```
    """
    owner = "stability_atlas"
    check_quadratic_rod(rod, owner)  # its helices are `helix_equilibria`'s
    check_one_rod(rod, owner)
    if not is_concrete(rod, kappa, tau, length, max_length):
        raise ValueError(
            f"{owner} needs concrete inputs, not traced ones (under jax.jit, vmap or grad): it tests its grid in "
            "host-side chunks; call it once per rod or length"
        )
    dtype = float_dtype()
    kappa, tau = (jnp.asarray(a, dtype) for a in (kappa, tau))
    for name, a in (("kappa", kappa), ("tau", tau)):
        if a.size == 0:
            raise ValueError(f"{owner}: {name} is empty (no helix to test)")
        if not np.all(np.isfinite(np.asarray(a))):
            raise ValueError(f"{owner}: {name} must be finite")
    try:
        kappa, tau = jnp.broadcast_arrays(kappa, tau)
    except ValueError:
        raise ValueError(f"{owner}: kappa {kappa.shape} and tau {tau.shape} do not broadcast") from None
    length = finite_scalar(length, "length", owner, positive=True)
    max_length = 4 * length if max_length is None else finite_scalar(max_length, "max_length", owner, positive=True)
    bisections = check_integer(bisections, "bisections", owner)
    pieces = check_test_pieces(pieces, "pieces", owner, minimum=1)
    chunk_size = check_integer(chunk_size, "chunk_size", owner)
    check_progress(progress, owner)
    helices = 4 * kappa.size
    with progress_bar(owner, helices, progress, owner=owner, auto=helices > chunk_size) as report:
        fields = _test_helices(
            rod, kappa, tau, jnp.asarray(length, dtype), jnp.asarray(max_length, dtype), bool(critical_length),
            bisections, pieces, chunk_size, report,
        )
    valid, pointwise, index, margin, critical, kind, mode = fields
    return StabilityAtlas(
        kappa=kappa, tau=tau, length=jnp.asarray(length, dtype), max_length=jnp.asarray(max_length, dtype),
        valid=valid, pointwise_stable=pointwise, instability_index=index, stability_margin=margin,
        critical_length=critical, instability_type=kind, critical_mode=mode,
    )
