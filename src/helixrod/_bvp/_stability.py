"""Stability of a solved finite rod: the index and a margin of its second variation.

The test is Morse's broken-extremal reduction of the conjugate-point count (the form of it for
rods: Manning, Rogers & Maddocks 1998, *Proc. R. Soc. A* 454, 3047; Manning 2009, "Conjugate
points revisited and Neumann--Neumann problems", *SIAM Rev.* 51, 193).  Cut the rod into
$p$ pieces at nodes $g_j = (x_j, D_j)$, $j = 0..p$.  Where each piece is short enough to hold
no conjugate point of its own, the equilibrium between two given nodes is locally unique and
a strict minimum of the piece's energy, and the energy of the rod becomes a function
$E(g_1, \\dots, g_p)$ of the free nodes.  Its Hessian at the equilibrium has exactly as many
negative eigenvalues as the second variation of the rod -- the number of conjugate points, each
counted with its multiplicity, with the inextensibility and end constraints included -- and is
singular exactly where the rod has a Jacobi field that meets its end conditions.  So

- `instability_index` = the number of negative eigenvalues (unstable directions; those
  within `NEUTRAL` of zero are neutral: a continuous symmetry of the loaded rod, e.g. an
  isotropic cantilever buckled under an axial dead load, which may turn about the load
  line, gives an exact zero, and such a state is stable with margin ~0);
- `stability_margin` = the smallest eigenvalue, made dimensionless ($L^2/\\bar K$) in the
  metric $\\sum_j h\\,(|\\delta\\theta_j|^2 + |\\delta x_j|^2/L^2)$ of the node variations, a
  discretisation of $\\int_0^L (|\\delta\\theta|^2 + |\\delta x|^2/L^2)\\,ds$: smooth along a load
  path and zero where stability is lost.  (For an isotropic straight cantilever of bending
  stiffness $B$ under a compressive dead load $P$ it is about
  $\\tfrac{\\pi^2}{4}(1 - P/P_c)$.)  The zero is exact, its value elsewhere depends mildly on
  the number of pieces.

The Hessian comes from the Jacobi fields of each piece (`piece_variations`).  Variations of a
piece's start node $(\\delta x_a, \\delta\\theta_a)$ (spatial rotation $\\delta D = [\\delta\\theta]_\\times D$)
and of its lab wrench $(\\delta N, \\delta M_a)$ (moment about $x_a$) map linearly to those at its
end, $T = \\begin{pmatrix} A & B \\\\ C & D\\end{pmatrix}$; since $\\partial E/\\partial g_b = w_b$ and
$\\partial E/\\partial g_a = -w_a$ (the wrench paired with $(\\delta x, \\delta\\theta)$), the piece's
Hessian in its two nodes is
$\\begin{pmatrix} B^{-1}A & -B^{-1} \\\\ C - DB^{-1}A & DB^{-1} \\end{pmatrix}$.
The rod's Hessian assembles these over the free nodes and adds that of the load potential.
Its antisymmetric part -- the Lie-group connection terms, proportional to the gradient --
cancels at an equilibrium, and the symmetric part is used.

End conditions (every one conservative): `Clamped` -- the last node is fixed; `Tweezer` -- its
position is free, its frame fixed, the dead force contributes $-F\\cdot x_p$ (no Hessian);
`Loaded` -- both free, the dead force acting at a point $x_p + D_p r$ rigidly attached to the
end (its `hook`; for a fixed `point`, where the load's line passes closest to the end in
this state; the end itself for neither), potential $-F\\cdot(x_p + D_p r)$, and **no applied
moment**: a dead moment is not conservative on
$SO(3)$, so the stability of an end loaded by a moment is not defined here (index $-1$,
margin NaN).

Each piece must be free of conjugate points, and its Jacobi fields well conditioned.  Both
hold when its length $h$ is short against the scales of the wrench,
$h\\,(\\sqrt{|N|/K_{min}} + \\max |m|/K_{min}) \\le 1$ (the first conjugate point of a clamped
piece is at $2\\pi$ in the first of these and at $\\approx 9$ in the second).  Where a piece is
longer than that for its wrench it is integrated as a chain of equal sub-pieces that are not
(`sub_pieces_needed`), and the chain's inner nodes are eliminated as it goes (`condensed`):
the Schur complement onto the piece's two nodes is the piece's exact Hessian, and by
Haynsworth's inertia additivity the rod's index is that of the assembled Hessian plus the
negative eigenvalues of the eliminated blocks -- Morse's count on the finer pieces, with the
margin and the direction of the coarser ones.  A chain whose eliminated blocks are not all
positive (a conjugate point inside one piece: a state far from stable) or that would need
more than `MAX_SUB_PIECES` sub-pieces is flagged unresolved (index $-1$, margin NaN), and
`solve_boundary_value` retries with more pieces.  Before the chains, a pulled 3-turn spring
needed tests on 32, 64 and 128 pieces along its curve, a program each: the first curve
across its critical force took 11.0 s on 2 cores.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._lie import hat
from .._misc import inverse_small, lowest_eigenpair, no_gradient, symmetric_elimination, symmetric_eigenvalue_min
from ._ends import LOADED, TWEEZER, EndCondition
from ._rotation import RotationCount, counted_rotation, start_count
from ._options import BoundaryValueOptions
from ._shooting import per_piece
from ._variations import PieceVariations, piece_variations, steps_per_radian, variation_steps

#: Extensibility of the pieces of the test, relative to their bending compliance: a
#: regularisation of straight pieces (`piece_transfer`) far below any physical stretch.
EXTENSIBILITY = 1e-5

#: Dimensionless eigenvalues within NEUTRAL (p/16)^2 of zero (p pieces) are neutral, not
#: unstable: a symmetry of the problem (an isotropic rod buckled under a load along its
#: clamp's axis can turn about it; an isotropic elastica between parallel clamps can turn
#: about its chord while twisting back) gives an exact zero that round-off would otherwise
#: count either way.  Its computed value grows with the pieces, as the conditioning of the
#: short pieces' B: measured on that elastica (end shortening 0.1-0.3 L), |error| up to
#: 1.0e-6 at 16 pieces, 1.3e-5 at 64, 3.7e-4 at 128.
NEUTRAL = 1e-5

#: The size of `unstable_direction`: the largest node rotation (radians) it produces.
UNSTABLE_STEP = 0.3

#: The largest dimensionless piece length $h(\\sqrt{|N|/K_{min}} + \\max|m|/K_{min})$ trusted.
PIECE_RESOLUTION = 1.0

#: The most sub-pieces of one piece of the test (`stability`): 16 pieces of 16 resolve as
#: much as 256 pieces did.
MAX_SUB_PIECES = 16


def stiffness_range(rod) -> tuple[Array, Array]:
    """(smallest eigenvalue, mean diagonal) of the stiffness $\\partial m/\\partial u$ at $\\hat u$."""
    uhat = jax.lax.stop_gradient(jnp.asarray(rod.uhat))
    hessian = jax.jacfwd(no_gradient(rod).moment)(uhat)
    hessian = 0.5 * (hessian + hessian.T)
    return symmetric_eigenvalue_min(hessian), jnp.trace(hessian) / 3.0


def piece_transfer(frame_a, N, M_a, variations: PieceVariations, compliance) -> Float[Array, "12 12"]:
    """The transfer matrix $T$ of one piece (module docstring) in lab components: variations
    (dx, dtheta, dN, dM) at its start to those at its end, from the piece's `variations`
    along the six local start wrenches (`piece_variations`).  `compliance`: the tiny
    extensibility (`EXTENSIBILITY` of the piece's bending compliance $h^3/\\bar K$) that
    keeps $B$ invertible where a piece is straight: there an inextensible piece's end cannot
    move along its axis to first order, whatever the axial force."""
    r = frame_a @ variations.position
    dp = frame_a @ variations.d_position  # (3, 6)
    drot = frame_a @ variations.d_rotation
    zero, eye = jnp.zeros((3, 3), N.dtype), jnp.eye(3, dtype=N.dtype)
    row = lambda *blocks: jnp.concatenate(blocks, axis=1)  # noqa: E731
    # Columns (dx, dtheta, dN, dM) at the start.  The local start wrench is
    # (D_a^T N, D_a^T M_a): turning the frame by dtheta turns it back, its variation is
    # D_a^T (dN + N x dtheta, dM + M_a x dtheta).  Written out, not `jax.jacfwd` of the
    # linear map: the same matrix to round-off, 10-25 us less of a 16-piece test.
    wrench = jnp.concatenate([row(zero, frame_a.T @ hat(N), frame_a.T, zero), row(zero, frame_a.T @ hat(M_a), zero, frame_a.T)])
    moved = row(zero, -hat(r), compliance * eye, zero) + dp @ wrench  # dx_b - dx
    dth_b = row(zero, eye, zero, zero) + drot @ wrench
    # The moment about the moved end: dM - (dx_b - dx) x N - r x dN.
    dM_b = row(zero, zero, -hat(r), eye) + hat(N) @ moved
    return jnp.concatenate([row(eye, zero, zero, zero) + moved, dth_b, row(zero, zero, eye, zero), dM_b])


def piece_hessian(T) -> Float[Array, "12 12"]:
    """The Hessian of a piece's energy in its (start, end) node variations, from $T$."""
    A, B, C, D = T[:6, :6], T[:6, 6:], T[6:, :6], T[6:, 6:]
    B_inv = inverse_small(B)
    return jnp.block([[B_inv @ A, -B_inv], [C - D @ B_inv @ A, D @ B_inv]])


def second_variation(rod, length, end: EndCondition, N, end_position, hessians, end_frame=None):
    """The rod's Hessian in its free node variations, assembled from the pieces' `(p, 12,
    12)` Hessians (`piece_hessian`, or a chain's, `condensed`), with the load's (`end_frame`:
    the end's, where a `Loaded` end's hook needs it); scaled to the dimensionless form of the module docstring and
    symmetrised.  `(6p, 6p)`; the fixed slots of the last node are decoupled
    with a large diagonal (their eigenvalues lie far above the soft ones).  Also returns
    the mask of free slots."""
    p = hessians.shape[0]
    pieces = hessians.reshape(p, 2, 6, 2, 6)
    # Block-tridiagonal in the p + 1 nodes: piece j adds its Hessian to nodes (j, j + 1).
    # (Placed by index: built as sums of Kronecker-like products with identity matrices it
    # cost ~2x as long, measured on its own at 16 pieces.)
    j = jnp.arange(p)
    H = jnp.zeros((p + 1, 6, p + 1, 6), N.dtype)
    for a, b in ((0, 0), (0, 1), (1, 0), (1, 1)):
        H = H.at[j + a, :, j + b, :].add(pieces[:, a, :, b, :])
    H = H.reshape(6 * (p + 1), 6 * (p + 1))
    # A Loaded end: the dead force acts at the point r from the end, carried by its frame:
    # where its line of action (through `point`) passes closest to the end.
    to_point = end.point - end_position
    direction = end.force / jnp.where(jnp.any(end.force != 0), jnp.linalg.norm(end.force), 1.0)
    hook = (jnp.eye(3, dtype=N.dtype) if end_frame is None else end_frame) @ end.hook
    r = jnp.where(end.about_end, hook, to_point - (to_point @ direction) * direction)
    H = H.at[-3:, -3:].add(jnp.where(end.kind == LOADED, -hat(end.force) @ hat(r), 0.0))
    H = H[6:, 6:]  # the start node is clamped
    free_x = (end.kind == TWEEZER) | (end.kind == LOADED)
    free = jnp.concatenate([jnp.ones(6 * (p - 1), bool), jnp.full(3, free_x), jnp.full(3, end.kind == LOADED)])
    k_mean = stiffness_range(rod)[1]
    h = length / p
    # Variations (x / L, theta) in the metric h per node; energy in units of K_mean / L^2.
    scale = jnp.tile(jnp.concatenate([jnp.full(3, length), jnp.ones(3, N.dtype)]), p)
    H = (length**2 / (k_mean * h)) * scale[:, None] * H * scale[None, :]
    H = 0.5 * (H + H.T)
    H = jnp.where(free[:, None] & free[None, :], H, 0.0)
    H = H + jnp.diag(jnp.where(free, 0.0, 1e6 * (1.0 + jnp.max(jnp.abs(H)))))
    return H, free


def condensed(S, P):
    """The Hessian `(12, 12)` of a chain of pieces in its end nodes (a, d) from its Hessian in
    (a, c), `S`, and the Hessian of one more piece in (c, d), `P` (both symmetric), with node
    c eliminated: the Schur complement of c's block $S_{cc} + P_{cc}$; and the number of
    that block's negative eigenvalues (`symmetric_elimination`).  By Haynsworth's inertia
    additivity the chain's index is the sum of those counts over its eliminated nodes plus
    the index of the result."""
    whole = jnp.zeros((18, 18), S.dtype).at[:12, :12].add(S).at[6:, 6:].add(P)
    node = np.zeros(18, bool)
    node[6:12] = True
    whole, negatives = symmetric_elimination(whole, node)
    ends = np.flatnonzero(~node)
    return whole[np.ix_(ends, ends)], negatives


def wrench_scale(k_min, force, largest_moment):
    """The inverse length $\\sqrt{|N|/K_{min}} + \\max|m|/K_{min}$ of a wrench of lab force
    `force` $= |N|$ and moments at most `largest_moment` along the rod: pieces resolve it where
    their length times it is at most `PIECE_RESOLUTION` (module docstring).  The one form
    of the rule, for arrays and, on the host, for floats."""
    sqrt = np.sqrt if isinstance(force, (float, np.floating)) else jnp.sqrt
    return sqrt(force / k_min) + largest_moment / k_min


def sub_pieces_needed(h, start_moment, force, k_min) -> Array:
    """The sub-pieces a piece of length `h` needs to resolve its wrench (`wrench_scale`):
    along it $|m(s)| \\le |m_a| + |N|\\,s$ (inextensible), so `start_moment` $|m_a|$ and
    the lab `force` $|N|$ bound its moments."""
    return jnp.maximum(jnp.ceil(h * wrench_scale(k_min, force, start_moment + force * h) / PIECE_RESOLUTION), 1.0)


def stability(rod, length, end: EndCondition, N, M0, xs, frames, options: BoundaryValueOptions):
    """(instability_index, stability_margin, unstable_direction, rotation, chained) of the
    equilibrium with lab force `N`, lab moment `M0` at the start and shooting nodes `xs`
    `(k, 3)`, `frames` `(k, 3, 3)`, on `options.stability_pieces` pieces (rounded up to a
    multiple of k), their Jacobi fields as accurate as `options.ode_rtol` asks
    (`steps_per_radian`).  Each piece is integrated as a chain of as many equal sub-pieces as its
    wrench needs (`sub_pieces_needed`, at most `MAX_SUB_PIECES`), whose inner nodes are
    eliminated as it goes (`condensed`): one program resolves every load.  Index -1 and NaN
    margin where the stability is not defined (a `Loaded` end with an applied moment), a
    piece would need more sub-pieces or holds a conjugate point of its own (an inner node's
    negative count: a state far from stable, which more pieces resolve), or the
    integration failed.  `unstable_direction` `(6,)`: the change of the lab start wrench
    (N, M0) that moves the rod along its most unstable direction (zero unless unstable).
    `rotation`: the end's total rotation about $e_z$ (`_rotation.py`) as counted on the
    pieces' way, to their integration's accuracy (NaN where not counted; `exact_rotation`
    makes it exact).  `chained`: whether any piece was integrated as a chain (its wrench asks
    for more pieces: the index is exact, the margin and direction are the coarser pieces').
    No derivatives."""
    rod, length, end, N, M0, xs, frames = no_gradient((rod, length, end, N, M0, xs, frames))
    k = xs.shape[0]
    q = -(-options.stability_pieces // k)
    p, h = k * q, length / (k * q)
    x0 = xs[0]
    k_min, k_mean = stiffness_range(rod)
    force = jnp.linalg.norm(N)
    # Node positions over h: the pivots of the elimination balanced (a congruence).
    weight = jnp.tile(jnp.concatenate([jnp.full(3, h), jnp.ones(3, N.dtype)]), 2)
    # The Jacobi fields as accurate as the solution they vary (`steps_per_radian`).
    per_radian = steps_per_radian(options.ode_rtol)

    def hessian(frame, moment, piece, piece_length):
        # Symmetrised before the elimination, as the assembled Hessian is (a sum of the
        # pieces'): the integration's small asymmetry of the axial blocks, whose tiny
        # extensibility makes them huge, otherwise enters the Schur complements (measured:
        # 6 unstable directions instead of 8 on a pulled spring, chains of 4 sub-pieces).
        H = piece_hessian(piece_transfer(frame, N, moment, piece, EXTENSIBILITY * piece_length**3 / k_mean))
        H = weight[:, None] * H * weight[None, :]
        return 0.5 * (H + H.T)

    def chained_piece(node, _):
        x, frame = node
        needed = sub_pieces_needed(h, jnp.linalg.norm(M0 - jnp.cross(x - x0, N)), force, k_min)
        count = jnp.minimum(needed, MAX_SUB_PIECES).astype(jnp.int32)
        sub_length = h / count

        def chain(i, carry):
            (x, frame), S, negatives, rotation = carry
            moment = M0 - jnp.cross(x - x0, N)
            local = jnp.concatenate([frame.T @ N, frame.T @ moment])
            steps = variation_steps(rod, local[:3], local[3:], sub_length, options.max_ode_steps, per_radian)
            piece = piece_variations(rod, local[:3], local[3:], sub_length, steps, frame)
            P = hessian(frame, moment, piece, sub_length)
            # The first sub-piece starts the chain (a branch: most pieces are one sub-piece).
            # (Each Hessian formed here, not vmapped after the loop for the pieces of one
            # sub-piece: that copy made the program 20 % larger, for ~0.05 ms a test.)
            S, pivot_negatives = jax.lax.cond(i == 0, lambda: (P, jnp.zeros((), jnp.int32)), lambda: condensed(S, P))
            rotation = RotationCount(
                piece.rotation.angle, rotation.total + piece.rotation.total,
                jnp.maximum(rotation.largest, piece.rotation.largest), jnp.minimum(rotation.pole, piece.rotation.pole),
            )
            return (x + frame @ piece.position, frame @ piece.frame), S, negatives + pivot_negatives, rotation

        start = (node, jnp.zeros((12, 12), N.dtype), jnp.zeros((), jnp.int32), start_count(frame))
        end_node, S, negatives, rotation = jax.lax.fori_loop(0, count, chain, start)
        resolved = (needed <= MAX_SUB_PIECES) & (negatives == 0)
        return end_node, (S, resolved, count > 1, rotation, end_node)

    _, (hessians, resolved, chained, rotations, ends) = per_piece(
        lambda i: jax.lax.scan(chained_piece, (xs[i], frames[i]), None, length=q), jnp.arange(k)
    )
    flat = lambda a: a.reshape((p,) + a.shape[2:])  # noqa: E731
    hessians = flat(hessians) / (weight[:, None] * weight[None, :])[None]
    end_position, end_frame = ends[0][-1, -1], ends[1][-1, -1]
    tested = assess(rod, length, end, N, hessians, end_position, jnp.all(resolved), end_frame)
    return (*tested, counted_rotation(rotations), jnp.any(chained))


def assess(rod, length, end: EndCondition, N, hessians, end_position, resolved, end_frame=None):
    """(instability_index, stability_margin, unstable_direction) from the pieces' Hessians
    `(p, 12, 12)` (as `stability`); `resolved`: whether the pieces resolve the wrench
    (`resolves`); `end_frame` as `second_variation`."""
    p = hessians.shape[0]
    H, free = second_variation(rod, length, end, N, end_position, hessians, end_frame)
    defined_H = jnp.all(jnp.isfinite(H))
    # Only the bottom of the spectrum is needed: the count below the neutral band, the
    # lowest eigenvalue and, where unstable, its vector (NaN-free input: a failed
    # integration is masked below).
    H = jnp.where(defined_H, H, jnp.eye(H.shape[0], dtype=H.dtype))
    index, margin, vector = lowest_eigenpair(H, -NEUTRAL * (p / 16) ** 2, vector_only_below=True)
    # The most unstable direction as the start-wrench change that produces it to first
    # order (the first free node's variation through the first piece's B^{-1}, which is minus
    # its Hessian's coupling of its two nodes), scaled to a
    # largest node rotation (or displacement / L) of `UNSTABLE_STEP`.
    mode = jnp.where(free, vector, 0.0).reshape(p, 6) * jnp.concatenate([jnp.full(3, length), jnp.ones(3)])[None, :]
    size = jnp.maximum(jnp.max(jnp.abs(mode[:, 3:])), jnp.max(jnp.abs(mode[:, :3])) / length)
    mode = UNSTABLE_STEP * mode / jnp.where(size > 0, size, 1.0)
    push = -hessians[0, :6, 6:] @ mode[0]
    moment_free = ~((end.kind == LOADED) & (jnp.linalg.norm(end.moment) > 0))
    defined = moment_free & resolved & defined_H
    push = jnp.where(defined & (index > 0) & jnp.all(jnp.isfinite(push)), push, 0.0)
    return jnp.where(defined, index, -1), jnp.where(defined, margin, jnp.nan), push


def resolves(rod, h, N, largest_moment) -> Array:
    """Whether pieces of length `h` resolve the wrench of lab force `N` and largest moment
    `largest_moment` along them (`wrench_scale`)."""
    return h * wrench_scale(stiffness_range(rod)[0], jnp.linalg.norm(N), largest_moment) <= PIECE_RESOLUTION
