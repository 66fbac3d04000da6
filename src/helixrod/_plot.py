"""Figures (matplotlib, Agg backend, colour-blind-safe Okabe-Ito colours)."""

from __future__ import annotations

import numpy as np

OKABE_ITO = ["#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#F0E442", "#000000"]


def plot_hyperboloid(rod, path, *, u3_slice=1.5, radii=None, extent=3.0):
    """Helix hyperboloid $h(u) = m_1 u_2 - m_2 u_1 = 0$ in 3D, its slice at $u_3$ =
    `u3_slice` with constraint circles of the given `radii` (curvatures), and the
    registers (intersections) on each circle.  Writes a PNG to `path`."""
    import matplotlib

    matplotlib.use("Agg")
    import jax.numpy as jnp
    import matplotlib.pyplot as plt

    from ._equilibria import helix_equilibria

    def h(u1, u2, u3):
        u = jnp.stack(jnp.broadcast_arrays(u1, u2, u3), axis=-1)
        m = np.asarray(rod.moment(u))
        return m[..., 0] * u2 - m[..., 1] * u1

    fig = plt.figure(figsize=(11, 5))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    g = np.linspace(-extent, extent, 121)
    # The hyperboloid is linear in u3 at fixed (u1, u2): solve for u3 to draw it.
    U1, U2 = np.meshgrid(g, g)
    h0 = h(U1, U2, 0.0)
    h1 = h(U1, U2, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        U3 = -h0 / (h1 - h0)
    U3[np.abs(U3) > extent] = np.nan
    ax3.plot_surface(U1, U2, U3, color=OKABE_ITO[5], alpha=0.55, linewidth=0, antialiased=True)
    ax3.set_xlabel("$u_1$")
    ax3.set_ylabel("$u_2$")
    ax3.set_zlabel("$u_3$")
    ax3.set_title("helix hyperboloid $m_1u_2 - m_2u_1 = 0$")

    ax = fig.add_subplot(1, 2, 2)
    H = h(U1, U2, u3_slice)
    ax.contour(U1, U2, H, levels=[0.0], colors=[OKABE_ITO[0]], linewidths=2)
    radii = (0.6, 1.6) if radii is None else radii
    theta = np.linspace(0, 2 * np.pi, 400)
    for i, r in enumerate(radii):
        colour = OKABE_ITO[1 + i]
        ax.plot(r * np.sin(theta), r * np.cos(theta), color=colour, lw=1.5, label=f"$\\kappa = {r:g}$")
        eq = helix_equilibria(rod, jnp.asarray(r), jnp.asarray(u3_slice))
        valid = np.asarray(eq.valid)
        u = np.asarray(eq.u)[valid]
        stable = np.asarray(eq.stable)[valid]
        ax.scatter(u[stable, 0], u[stable, 1], s=60, color=colour, edgecolor="k", zorder=5)
        ax.scatter(u[~stable, 0], u[~stable, 1], s=60, facecolor="white", edgecolor=colour, zorder=5, lw=2)
        ax3.plot(r * np.sin(theta), r * np.cos(theta), u3_slice + 0 * theta, color=colour, lw=2)
    ax.set_aspect("equal")
    ax.set_xlim(-extent, extent)
    ax.set_ylim(-extent, extent)
    ax.set_xlabel("$u_1$")
    ax.set_ylabel("$u_2$")
    ax.set_title(f"slice $u_3 = {u3_slice:g}$: registers (filled: stable)")
    ax.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


# -- inverse spring problem (issue 4) ------------------------------------------------------
def plot_fit(data, fit, path):
    """Observed against predicted axial force and moment of a `StiffnessFit` (error bars:
    the data's sigmas; the diagonal is a perfect fit), and the normalised residuals.
    Writes a PNG to `path`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    n = len(data)
    r = np.asarray(fit.residuals)
    for ax, obs, pred, sig, label, colour in (
        (axes[0], data.force, fit.predicted_force, data.force_sigma, "axial force $F$", OKABE_ITO[0]),
        (axes[1], data.moment, fit.predicted_moment, data.moment_sigma, "axial moment $M$", OKABE_ITO[1]),
    ):
        obs, pred, sig = np.asarray(obs), np.asarray(pred), np.asarray(sig)
        ax.errorbar(pred, obs, yerr=sig, fmt="o", ms=4, color=colour, ecolor="0.6", lw=1)
        lo, hi = min(obs.min(), pred.min()), max(obs.max(), pred.max())
        ax.plot([lo, hi], [lo, hi], "k--", lw=1)
        ax.set_xlabel(f"predicted {label}")
        ax.set_ylabel(f"observed {label}")
    axes[2].plot(np.arange(n), r[:n], "o", ms=4, color=OKABE_ITO[0], label="force")
    axes[2].plot(np.arange(n), r[n : 2 * n], "s", ms=4, color=OKABE_ITO[1], label="moment")
    axes[2].axhline(0, color="k", lw=1)
    axes[2].set_xlabel("data point")
    axes[2].set_ylabel("residual / sigma")
    axes[2].legend()
    fig.suptitle(f"fit_stiffness: cost = {float(fit.cost):.4g}, reduced chi2 = {float(fit.chi2_reduced):.3g}")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
