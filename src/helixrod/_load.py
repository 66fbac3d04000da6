"""The reverse question: which uniform helices does a given axial wrench hold?"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._compile import filter_jit
from ._equilibria import helix_equilibria
from ._misc import attainable, is_concrete
from ._roots import NUM_SLOTS
from ._rod import Rod, check_quadratic_rod


class LoadedHelices(eqx.Module):
    """Uniform helices held by one axial wrench; fixed size, padded, `valid` marks rows.

    `kappa`, `tau`, `phi`, `slot` (the `helix_equilibria` slot: 0 global minimum of the
    energy on the circle, ...), `force`, `moment` (as recomputed at the solution), `energy`,
    `stable`; all NaN / False in unused rows.  `count` is the number of helices found;
    `valid_input` False where the wrench was not finite (traced: concrete ones raise), its
    count 0 not a finding.
    """

    kappa: Float[Array, " k"]
    tau: Float[Array, " k"]
    phi: Float[Array, " k"]
    slot: Int[Array, " k"]
    force: Float[Array, " k"]
    moment: Float[Array, " k"]
    energy: Float[Array, " k"]
    stable: Bool[Array, " k"]
    valid: Bool[Array, " k"]
    count: Int[Array, ""]
    valid_input: Bool[Array, ""]


def helices_under_load(
    rod: Rod,
    force: ArrayLike,
    moment: ArrayLike,
    *,
    kappa_max: float,
    tau_range: tuple[float, float],
    grid: int = 64,
    newton_steps: int = 25,
    max_solutions: int = 16,
    rtol: float = 1e-10,
) -> LoadedHelices:
    """All uniform helices with axial force `force` and axial moment `moment` inside the box
    $0 < \\kappa \\le$ `kappa_max`, $\\tau \\in$ `tau_range` (the spring formula read backwards).

    Method: every register branch of `helix_equilibria` is evaluated on a `grid` x `grid`
    lattice of the box; each cell over which both $F - F_0$ and $M - M_0$ change sign on
    one branch seeds a Newton solve of $(F, M)(\\kappa, \\tau) = (F_0, M_0)$ on that branch
    (Jacobian by forward-mode autodiff through the register root), and converged,
    distinct solutions are returned.  A solution is found reliably when the box contains
    it and the lattice resolves it (two solutions on one branch closer than a cell can
    merge: raise `grid`).  Scalar `force`, `moment`; `jax.vmap` for many.  jit-safe.

    `newton_steps`: Newton steps from each seed (the first `4 max_solutions` seeds); a
    solution counts when $|F - F_0|$ and $|M - M_0|$ are at most `rtol` times the scale of
    the load (the larger of $|F_0|$ and the box's mean $|F|$, and so for $M$); at most
    `max_solutions` are returned (if `valid` is full, raise it: others may have been left
    out).
    """
    check_quadratic_rod(rod, "helices_under_load")
    if grid < 2 or max_solutions < 1:
        raise ValueError("grid must be >= 2 and max_solutions >= 1")
    tau_lo, tau_hi = float(tau_range[0]), float(tau_range[1])
    if not all(math.isfinite(x) for x in (float(kappa_max), tau_lo, tau_hi)):
        raise ValueError(f"helices_under_load: kappa_max and tau_range must be finite; got {kappa_max}, {tau_range}")
    if not (kappa_max > 0 and tau_hi > tau_lo):
        raise ValueError(f"need kappa_max > 0 and tau_range[1] > tau_range[0]; got {kappa_max}, {tau_range}")
    dtype = jnp.result_type(float)
    F0 = jnp.asarray(force, dtype)
    M0 = jnp.asarray(moment, dtype)
    if F0.ndim or M0.ndim:
        raise ValueError("force and moment must be scalars (use jax.vmap for many)")
    if is_concrete(F0, M0) and not (np.isfinite(float(F0)) and np.isfinite(float(M0))):
        raise ValueError(f"helices_under_load: force and moment must be finite; got {float(F0)}, {float(M0)}")
    box = jnp.asarray([kappa_max, tau_lo, tau_hi], dtype)
    return _under_load(rod, F0, M0, box, grid, newton_steps, max_solutions, rtol)


@filter_jit
def _under_load(rod, F0, M0, box, grid, newton_steps, max_solutions, rtol):
    # One compiled program per (grid, newton_steps, max_solutions): the box is traced.
    dtype = F0.dtype
    kappa_max, tau_lo, tau_hi = box[0], box[1], box[2]
    ks = jnp.linspace(kappa_max / grid, kappa_max, grid, dtype=dtype)
    ts = jnp.linspace(tau_lo, tau_hi, grid, dtype=dtype)
    eq = helix_equilibria(rod, ks[:, None], ts[None, :], fields=("force", "moment"))
    scale_f = jnp.maximum(jnp.abs(F0), jnp.nanmean(jnp.abs(eq.force)))
    scale_m = jnp.maximum(jnp.abs(M0), jnp.nanmean(jnp.abs(eq.moment)))
    rf = (eq.force - F0) / scale_f
    rm = (eq.moment - M0) / scale_m

    def corners(x):
        return jnp.stack([x[:-1, :-1], x[1:, :-1], x[:-1, 1:], x[1:, 1:]], axis=0)

    cf, cm = corners(rf), corners(rm)
    both_valid = jnp.all(corners(eq.valid), axis=0)
    straddle = (
        (jnp.nanmin(cf, 0) <= 0) & (jnp.nanmax(cf, 0) >= 0) & (jnp.nanmin(cm, 0) <= 0) & (jnp.nanmax(cm, 0) >= 0)
    )
    candidate = (both_valid & straddle).reshape(-1)
    n_candidates = 4 * max_solutions
    (idx,) = jnp.nonzero(candidate, size=n_candidates, fill_value=-1)
    used = idx >= 0
    idx = jnp.where(used, idx, 0)
    cells = grid - 1
    i, rest = jnp.divmod(idx, cells * NUM_SLOTS)
    j, slot = jnp.divmod(rest, NUM_SLOTS)
    k0 = 0.5 * (ks[i] + ks[i + 1])
    t0 = 0.5 * (ts[j] + ts[j + 1])

    reported = ("phi", "force", "moment", "energy", "stable")

    def residual(x):
        # The wrench of each point's own slot, relative to the target, and the fields
        # reported; one batch, no vmap (tracing the register solve once per batch, not once
        # per point, is what keeps the first call short).
        eq = helix_equilibria(rod, x[:, 0], x[:, 1], fields=reported)
        f, mo = (jnp.take_along_axis(v, slot[:, None], axis=1)[:, 0] for v in (eq.force, eq.moment))
        return jnp.stack([(f - F0) / scale_f, (mo - M0) / scale_m], axis=-1), eq

    def newton_step(_, state):
        # Evaluates at x (what is reported once the steps are done), then steps: the
        # newton_steps + 1 evaluations share one register solve in the program (a separate
        # evaluation after the loop made the first call ~a third longer).  Every point is
        # its own 2 x 2 system: two forward-mode directions give all the Jacobians at once.
        x, _ = state
        r, linear, eq = jax.linearize(residual, x, has_aux=True)
        unit_k = jnp.zeros_like(x).at[:, 0].set(1.0)
        jacobian = jnp.stack([linear(unit_k), linear(1.0 - unit_k)], axis=-1)
        det = jacobian[:, 0, 0] * jacobian[:, 1, 1] - jacobian[:, 0, 1] * jacobian[:, 1, 0]
        dk = (jacobian[:, 1, 1] * r[:, 0] - jacobian[:, 0, 1] * r[:, 1]) / det
        dt = (jacobian[:, 0, 0] * r[:, 1] - jacobian[:, 1, 0] * r[:, 0]) / det
        dx = jnp.stack([dk, dt], axis=-1)
        # A non-finite step is skipped; a step out of the box keeps half the way to the wall.
        new = x - jnp.where(jnp.all(jnp.isfinite(dx), axis=-1, keepdims=True), dx, 0.0)
        new = jnp.stack(
            [
                jnp.clip(new[:, 0], 0.5 * x[:, 0], kappa_max * 1.5),
                jnp.clip(new[:, 1], tau_lo - (tau_hi - tau_lo), tau_hi + (tau_hi - tau_lo)),
            ],
            axis=-1,
        )
        return new, (x, r, eq)

    x0 = jnp.stack([k0, t0], axis=-1)
    evaluated = jax.eval_shape(residual, x0)
    empty = jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), (x0, *evaluated))
    _, (x, r, sol) = jax.lax.fori_loop(0, newton_steps + 1, newton_step, (x0, empty))
    ok = jnp.max(jnp.abs(r), axis=-1) <= attainable(rtol, dtype)
    inside = (x[:, 0] > 0) & (x[:, 0] <= kappa_max * (1 + 1e-12)) & (x[:, 1] >= tau_lo) & (x[:, 1] <= tau_hi)
    good = used & ok & inside
    # Drop duplicates: the same slot at the same (kappa, tau) found from several cells.
    scale_x = jnp.array([kappa_max, tau_hi - tau_lo], dtype)
    close = jnp.all(jnp.abs((x[:, None, :] - x[None, :, :]) / scale_x[None, None, :]) < 1e-7, axis=-1)
    same = close & (slot[:, None] == slot[None, :]) & good[:, None] & good[None, :]
    earlier = jnp.tril(same, k=-1)
    good = good & ~jnp.any(earlier, axis=1)
    (rows,) = jnp.nonzero(good, size=max_solutions, fill_value=-1)
    valid = rows >= 0
    rows = jnp.where(valid, rows, 0)
    kk, tt, ss = x[rows, 0], x[rows, 1], slot[rows]

    def pick(field):
        return jnp.take_along_axis(field, slot[:, None], axis=1)[rows, 0]

    nan = jnp.nan
    return LoadedHelices(
        kappa=jnp.where(valid, kk, nan),
        tau=jnp.where(valid, tt, nan),
        phi=jnp.where(valid, pick(sol.phi), nan),
        slot=jnp.where(valid, ss, -1),
        force=jnp.where(valid, pick(sol.force), nan),
        moment=jnp.where(valid, pick(sol.moment), nan),
        energy=jnp.where(valid, pick(sol.energy), nan),
        stable=valid & pick(sol.stable),
        valid=valid,
        count=jnp.sum(valid),
        valid_input=jnp.isfinite(F0) & jnp.isfinite(M0),
    )
