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

Each piece must be free of conjugate points.  That holds when its length $h$ is short against
the scales of the wrench, $h\\,(\\sqrt{|N|/K_{min}} + \\max |m|/K_{min}) \\le 1$ (the first
conjugate point of a clamped piece is at $2\\pi$ in the first of these and at $\\approx 9$ in the
second); where it does not hold the result is flagged unresolved (index $-1$, margin NaN) and
`solve_boundary_value` retries with more pieces.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._lie import hat
from .._misc import inverse_small, lowest_eigenpair, no_gradient, solve_small, symmetric_eigenvalue_min
from ._ends import LOADED, TWEEZER, EndCondition
from ._rotation import counted_rotation
from ._options import BoundaryValueOptions
from ._shooting import per_piece
from ._variations import PieceVariations, piece_variations, variation_steps

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

    def linear(v):
        dx, dth, dN, dM = v[:3], v[3:6], v[6:9], v[9:]
        # The local start wrench is (D_a^T N, D_a^T M_a): turning the frame turns it back.
        dw = jnp.concatenate([frame_a.T @ (dN + jnp.cross(N, dth)), frame_a.T @ (dM + jnp.cross(M_a, dth))])
        dx_b = dx + jnp.cross(dth, r) + dp @ dw + compliance * dN
        dth_b = dth + drot @ dw
        dM_b = dM - jnp.cross(dx_b - dx, N) - jnp.cross(r, dN)  # moment about the moved end
        return jnp.concatenate([dx_b, dth_b, dN, dM_b])

    return jax.jacfwd(linear)(jnp.zeros(12, N.dtype))


def piece_hessian(T) -> Float[Array, "12 12"]:
    """The Hessian of a piece's energy in its (start, end) node variations, from $T$."""
    A, B, C, D = T[:6, :6], T[:6, 6:], T[6:, :6], T[6:, 6:]
    B_inv = inverse_small(B)
    return jnp.block([[B_inv @ A, -B_inv], [C - D @ B_inv @ A, D @ B_inv]])


def second_variation(rod, length, end: EndCondition, N, end_position, transfers, end_frame=None):
    """The rod's Hessian in its free node variations, assembled from the pieces' `(p, 12,
    12)` transfer matrices, with the load's (`end_frame`: the end's, where a `Loaded` end's
    hook needs it); scaled to the dimensionless form of the module docstring and
    symmetrised.  `(6p, 6p)`; the fixed slots of the last node are decoupled
    with a large diagonal (their eigenvalues lie far above the soft ones).  Also returns
    the mask of free slots."""
    p = transfers.shape[0]
    pieces = jax.vmap(piece_hessian)(transfers).reshape(p, 2, 6, 2, 6)
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


def stability(rod, length, end: EndCondition, N, M0, xs, frames, options: BoundaryValueOptions):
    """(instability_index, stability_margin, unstable_direction, rotation) of the
    equilibrium with lab force `N`, lab moment `M0` at the start and shooting nodes `xs`
    `(k, 3)`, `frames` `(k, 3, 3)`, on `options.stability_pieces` pieces (rounded up to a
    multiple of k).  Index -1 and NaN margin where the stability is not defined (a `Loaded`
    end with an applied moment), the pieces do not resolve the wrench, or the integration
    failed.  `unstable_direction` `(6,)`: the change of the lab start wrench (N, M0) that
    moves the rod along its most unstable direction (zero unless unstable).  `rotation`:
    the end's total rotation about $e_z$ (`_rotation.py`) as counted on the pieces' way, to
    their integration's accuracy (NaN where not counted; `exact_rotation` makes it exact).
    No derivatives."""
    rod, length, end, N, M0, xs, frames = no_gradient((rod, length, end, N, M0, xs, frames))
    k = xs.shape[0]
    q = -(-options.stability_pieces // k)
    p, h = k * q, length / (k * q)
    x0 = xs[0]
    compliance = EXTENSIBILITY * h**3 / stiffness_range(rod)[1]

    def sub_piece(node, _):
        # The pieces of one shooting piece in sequence: each starts where the last ended.
        x, frame = node
        moment = M0 - jnp.cross(x - x0, N)
        local = jnp.concatenate([frame.T @ N, frame.T @ moment])
        steps = variation_steps(rod, local[:3], local[3:], h, options.max_ode_steps)
        piece = piece_variations(rod, local[:3], local[3:], h, steps, frame)
        end_node = (x + frame @ piece.position, frame @ piece.frame)
        return end_node, (frame, moment, piece, jnp.linalg.norm(local[3:]), end_node)

    _, (starts, moments, pieces, start_moments, ends) = per_piece(
        lambda i: jax.lax.scan(sub_piece, (xs[i], frames[i]), None, length=q), jnp.arange(k)
    )
    # The transfer matrices of all pieces at once, outside the sequential loop.
    flat = lambda a: a.reshape((p,) + a.shape[2:])  # noqa: E731
    starts, moments, pieces = flat(starts), flat(moments), jax.tree.map(flat, pieces)
    transfers = jax.vmap(lambda frame, moment, piece: piece_transfer(frame, N, moment, piece, compliance))(starts, moments, pieces)
    largest_moment = jnp.maximum(jnp.max(start_moments), jnp.max(jnp.linalg.norm(pieces.moment, axis=-1)))
    end_position, end_frame = ends[0][-1, -1], ends[1][-1, -1]
    return (*assess(rod, length, end, N, transfers, end_position, largest_moment, end_frame), counted_rotation(pieces.rotation))


def assess(rod, length, end: EndCondition, N, transfers, end_position, largest_moment, end_frame=None):
    """(instability_index, stability_margin, unstable_direction) from the pieces' transfer
    matrices `(p, 12, 12)` (as `stability`); `largest_moment`: the largest moment along the
    rod (whether the pieces resolve the wrench); `end_frame` as `second_variation`."""
    p = transfers.shape[0]
    h = length / p
    H, free = second_variation(rod, length, end, N, end_position, transfers, end_frame)
    defined_H = jnp.all(jnp.isfinite(H))
    # Only the bottom of the spectrum is needed: the count below the neutral band, the
    # lowest eigenvalue and, where unstable, its vector (NaN-free input: a failed
    # integration is masked below).
    H = jnp.where(defined_H, H, jnp.eye(H.shape[0], dtype=H.dtype))
    index, margin, vector = lowest_eigenpair(H, -NEUTRAL * (p / 16) ** 2, vector_only_below=True)
    # The most unstable direction as the start-wrench change that produces it to first
    # order (the first free node's variation through the first piece's B^{-1}), scaled to a
    # largest node rotation (or displacement / L) of `UNSTABLE_STEP`.
    mode = jnp.where(free, vector, 0.0).reshape(p, 6) * jnp.concatenate([jnp.full(3, length), jnp.ones(3)])[None, :]
    size = jnp.maximum(jnp.max(jnp.abs(mode[:, 3:])), jnp.max(jnp.abs(mode[:, :3])) / length)
    mode = UNSTABLE_STEP * mode / jnp.where(size > 0, size, 1.0)
    push = solve_small(transfers[0, :6, 6:], mode[0])
    k_min = stiffness_range(rod)[0]
    resolved = h * (jnp.sqrt(jnp.linalg.norm(N) / k_min) + largest_moment / k_min) <= PIECE_RESOLUTION
    moment_free = ~((end.kind == LOADED) & (jnp.linalg.norm(end.moment) > 0))
    defined = moment_free & resolved & defined_H
    push = jnp.where(defined & (index > 0) & jnp.all(jnp.isfinite(push)), push, 0.0)
    return jnp.where(defined, index, -1), jnp.where(defined, margin, jnp.nan), push
