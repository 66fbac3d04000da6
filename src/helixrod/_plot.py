"""Figures (matplotlib, Agg backend, colour-blind-safe Okabe-Ito colours)."""

from __future__ import annotations

import numpy as np

#: The eight colours of Okabe & Ito (2008), distinguishable with every common colour-vision
#: deficiency, as hex strings; categorical colours of every helixrod figure.
OKABE_ITO = ["#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#F0E442", "#000000"]


def plot_hyperboloid(rod, path=None, *, u3_slice=1.5, radii=None, extent=3.0):
    """Helix hyperboloid $h(u) = m_1 u_2 - m_2 u_1 = 0$ of `rod` in 3D, its slice at $u_3$ =
    `u3_slice` with the constraint circles of the given `radii` (curvatures $\\kappa$, default
    (0.6, 1.6)), and the registers (intersections) on each circle, filled when stable.  Axes
    span $[-$`extent`, `extent`$]$ in every twist component (units 1/length).  `path=None`
    returns the `Figure`; otherwise writes it (format by suffix) and returns `path`."""
    import jax.numpy as jnp
    from contourpy import contour_generator
    from matplotlib.figure import Figure

    from ._equilibria import helix_equilibria

    def h(u1, u2, u3):
        u = jnp.stack(jnp.broadcast_arrays(u1, u2, u3), axis=-1)
        m = np.asarray(rod.moment(u))
        return m[..., 0] * u2 - m[..., 1] * u1

    fig = Figure(figsize=(11, 5), layout="constrained")
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    g = np.linspace(-extent, extent, 121)
    U1, U2 = np.meshgrid(g, g)
    # Drawn as its sections h = 0 at stacked u3 (conics), not as a graph u3(u1, u2): that
    # graph is vertical where h does not depend on u3, and a clipped surface of it tears.
    for u3 in np.linspace(-extent, extent, 25):
        for line in contour_generator(g, g, h(U1, U2, u3)).lines(0.0):
            ax3.plot(line[:, 0], line[:, 1], np.full(len(line), u3), color=OKABE_ITO[5], lw=0.9, alpha=0.75)
    for line in contour_generator(g, g, h(U1, U2, u3_slice)).lines(0.0):  # the slice drawn on the right
        ax3.plot(line[:, 0], line[:, 1], np.full(len(line), u3_slice), color=OKABE_ITO[0], lw=2)
    ax3.set_xlim(-extent, extent)
    ax3.set_ylim(-extent, extent)
    ax3.set_zlim(-extent, extent)
    ax3.set_xlabel("$u_1$")
    ax3.set_ylabel("$u_2$")
    ax3.set_zlabel("$u_3$")
    ax3.set_title("helix hyperboloid $m_1u_2 - m_2u_1 = 0$ (sections at fixed $u_3$)")

    ax = fig.add_subplot(1, 2, 2)
    H = h(U1, U2, u3_slice)
    ax.contour(U1, U2, H, levels=[0.0], colors=[OKABE_ITO[0]], linewidths=2)
    radii = (0.6, 1.6) if radii is None else tuple(radii)
    theta = np.linspace(0, 2 * np.pi, 400)
    # Every circle's registers in one call (one compilation for any number of radii of a size).
    eq = helix_equilibria(rod, jnp.asarray(radii, float), jnp.asarray(u3_slice, float))
    for i, r in enumerate(radii):
        colour = OKABE_ITO[1 + i % (len(OKABE_ITO) - 1)]
        ax.plot(r * np.sin(theta), r * np.cos(theta), color=colour, lw=1.5, label=f"$\\kappa = {r:g}$")
        valid = np.asarray(eq.valid[i])
        u = np.asarray(eq.u[i])[valid]
        stable = np.asarray(eq.stable[i])[valid]
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
    return _finish(fig, path)


# -- inverse spring problem ----------------------------------------------------------------
def plot_fit(data, fit, path=None):
    """Observed against predicted axial force and moment of a `StiffnessFit` (error bars:
    the data's sigmas of F and M; the diagonal is a perfect fit), and the normalised
    residuals (whitened pairs for an errors-in-variables fit).  `path=None` returns the
    matplotlib `Figure`; otherwise writes it (PNG/PDF/SVG by suffix) and returns `path`."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13, 4.2), layout="constrained")
    axes = fig.subplots(1, 3)
    r = np.asarray(fit.residuals)
    start = 0
    for ax, name, label, colour, marker in (
        (axes[0], "force", "axial force $F$", OKABE_ITO[0], "o"),
        (axes[1], "moment", "axial moment $M$", OKABE_ITO[1], "s"),
    ):
        seen = np.flatnonzero(np.asarray(getattr(data, f"{name}_observed")))
        if not seen.size:  # partial data: this quantity was not measured
            ax.text(0.5, 0.5, f"{label}\nnot measured", ha="center", va="center", transform=ax.transAxes)
            ax.set_axis_off()
            continue
        obs, pred = np.asarray(getattr(data, name))[seen], np.asarray(fit.predicted[name])[seen]
        sig = np.asarray(getattr(data, f"{name}_sigma"))[seen]
        ax.errorbar(pred, obs, yerr=sig, fmt="o", ms=4, color=colour, ecolor="0.6", lw=1)
        lo, hi = min(obs.min(), pred.min()), max(obs.max(), pred.max())
        ax.plot([lo, hi], [lo, hi], "k--", lw=1)
        ax.set_xlabel(f"predicted {label}")
        ax.set_ylabel(f"observed {label}")
        axes[2].plot(seen, r[start : start + seen.size], marker, ms=4, color=colour, label=name)
        start += seen.size
    axes[2].axhline(0, color="k", lw=1)
    axes[2].set_xlabel("data point")
    axes[2].set_ylabel("residual / sigma")
    axes[2].legend()
    fig.suptitle(f"fit_stiffness: cost = {float(fit.cost):.4g}, reduced chi2 = {float(fit.chi2_reduced):.3g}")
    return _finish(fig, path)


# -- finite rods --------------------------------------------------------------------------
_AXIAL_LABELS = {
    "force": "axial force $F$",
    "moment": "axial moment $M$",
    "extension": "extension $h$",
    "rotation": "end rotation $\\Theta$",
}


def plot_model_comparison(comparison, path=None):
    """A `ModelComparison` (from `compare_models`): the differences in AIC and BIC from the
    best model (bars; hatched where the data leave a parameter undetermined, the
    recommended model outlined) and the reduced chi2 of each fit (1 is the expected value)."""
    from matplotlib.figure import Figure

    names = list(comparison.names)
    rows = [comparison.table[n] for n in names]
    fig = Figure(figsize=(11, 3.8), layout="constrained")
    axes = fig.subplots(1, 2)
    x = np.arange(len(names))
    for offset, key, label, colour in ((-0.2, "delta_aic", "$\\Delta$AIC", OKABE_ITO[0]), (0.2, "delta_bic", "$\\Delta$BIC", OKABE_ITO[1])):
        values = np.array([r[key] for r in rows], float)
        bars = axes[0].bar(x + offset, np.maximum(values, 1e-2), 0.4, color=colour, label=label)
        for bar, row, name in zip(bars, rows, names):
            if not row["identifiable"]:
                bar.set_hatch("//")
            if name == comparison.best:
                bar.set_edgecolor("k")
                bar.set_linewidth(1.5)
    axes[0].set_yscale("log")
    axes[0].set_ylabel("difference from the best model")
    axes[0].set_xticks(x, names, rotation=15)
    axes[0].legend(title="hatched: not all determined")
    axes[1].bar(x, [r["chi2_reduced"] for r in rows], 0.5, color=OKABE_ITO[2])
    axes[1].axhline(1.0, color="k", lw=1, ls="--")
    axes[1].set_yscale("log")
    axes[1].set_ylabel("reduced $\\chi^2$")
    axes[1].set_xticks(x, names, rotation=15)
    fig.suptitle(f"compare_models: recommended {comparison.best} (lowest {comparison.criterion.upper()})")
    return _finish(fig, path)


def plot_response(curve, path=None):
    """A `ResponseCurve` of a finite rod against the bulk (uniform-helix) prediction: the
    swept control (`curve.swept`) on $x$, one panel per responding observable on $y$
    (those of `curve.controls` not prescribed, e.g. extension and moment for a
    force-extension curve at fixed rotation), the finite rod as points, the bulk as a
    dashed line, and below each the difference finite $-$ bulk (the end effects); points
    that did not converge are missing (NaN).  The title gives $L$ and
    the held control (`curve.held`).  `path=None` returns the matplotlib `Figure`;
    otherwise writes it (PNG/PDF/SVG by suffix) and returns `path`."""
    from ._bvp import AXIAL_CONTROLS, AXIAL_OBSERVABLES

    responses = [AXIAL_OBSERVABLES[i] for i in AXIAL_CONTROLS[curve.controls].responses]
    x = np.asarray(getattr(curve, curve.swept), dtype=float)
    fig, axes = _figure(len(responses), 2, height=3.0)
    for ax, below, name in zip(axes, axes[len(responses):], responses):
        finite, bulk = (np.asarray(getattr(curve, n), dtype=float) for n in (name, "bulk_" + name))
        ax.plot(x, finite, "o-", ms=3, color=OKABE_ITO[0], label="finite rod")
        ax.plot(x, bulk, "--", color=OKABE_ITO[1], label="uniform helix (bulk)")
        ax.set_ylabel(_AXIAL_LABELS[name])
        # The end effects: small beside the response itself, invisible in the panel above.
        below.plot(x, finite - bulk, "o-", ms=3, color=OKABE_ITO[0])
        below.axhline(0.0, color=OKABE_ITO[7], lw=0.8)
        below.set_xlabel(_AXIAL_LABELS[curve.swept])
        below.set_ylabel(f"{_AXIAL_LABELS[name].split(' $')[0]}: finite $-$ bulk")
    axes[0].legend()
    held = np.asarray(getattr(curve, curve.held), dtype=float)
    lo, hi = np.nanmin(held), np.nanmax(held)
    if np.isclose(lo, hi, rtol=1e-9, atol=1e-12):
        held_text = f"{curve.held} held at {hi:.4g}"
    else:
        held_text = f"{curve.held} from {held[0]:.4g} to {held[-1]:.4g}"
    failed = int(np.sum(~np.asarray(curve.ok)))
    title = f"finite rod ($L = {float(curve.length):.4g}$) against the uniform helix, {held_text}"
    fig.suptitle(title + (f" ({failed} points did not converge)" if failed else ""))
    return _finish(fig, path)


# -- the kappa-tau atlas ------------------------------------------------------------------
# These figures use matplotlib's object-oriented API (`matplotlib.figure.Figure`), never
# pyplot, so they neither need nor change a backend (safe in notebooks and threads).
# Each takes `path=None`: with a path the figure is written (PNG/PDF/SVG by suffix) and
# the path returned, otherwise the `Figure` is returned.  Categorical colours are
# Okabe-Ito; continuous maps are cividis (sequential) or PuOr (diverging), both readable
# with colour-vision deficiency.

_COUNT_CLASSES = (
    # (label, colour) for: no register, continuum, 2 registers, 3 (tangent), 4 registers.
    ("no helix ($\\kappa = 0$)", "#DDDDDD"),
    ("continuum", OKABE_ITO[2]),
    ("2 registers, 1 stable", OKABE_ITO[5]),
    ("3 registers (fold)", OKABE_ITO[7]),
    ("4 registers, 2 stable", OKABE_ITO[4]),
)


def _figure(ncols=1, nrows=1, *, width=4.6, height=3.8, projection=None):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width * ncols, height * nrows), layout="constrained")
    kw = {} if projection is None else {"projection": projection}
    axes = [fig.add_subplot(nrows, ncols, i + 1, **kw) for i in range(nrows * ncols)]
    return fig, axes


def _finish(fig, path):
    if path is None:
        return fig
    fig.savefig(path, dpi=150)
    return path


def _need(result, *names):
    missing = [n for n in names if n not in result]
    if missing:
        raise ValueError(f"this figure needs the sweep fields {list(names)}; missing {missing} (pass fields=... to sweep)")


def _count_class(result):
    count = np.asarray(result["count"])
    cls = np.select([count == 0, count == 1, count == 2, count == 3, count == 4], [0, 1, 2, 3, 4], 0)
    if "continuum" in result:
        cls = np.where(np.asarray(result["continuum"]), 1, cls)
    return cls


def _draw_atlas(ax, result):
    from matplotlib.colors import BoundaryNorm, ListedColormap
    from matplotlib.patches import Patch

    cls = _count_class(result)
    cmap = ListedColormap([c for _, c in _COUNT_CLASSES])
    norm = BoundaryNorm(np.arange(-0.5, 5.5), cmap.N)
    ax.pcolormesh(result.tau, result.kappa, cls, cmap=cmap, norm=norm, shading="nearest", rasterized=True)
    if "stable_count" in result:
        # Outline the multistable region (two stable registers at one helix).
        multi = (np.asarray(result["stable_count"]) >= 2).astype(float)
        if 0 < multi.mean() < 1:
            ax.contour(result.tau, result.kappa, multi, levels=[0.5], colors=[OKABE_ITO[1]], linewidths=1.2)
    present = sorted(set(np.unique(cls).tolist()))
    handles = [Patch(facecolor=_COUNT_CLASSES[i][1], edgecolor="k", lw=0.4, label=_COUNT_CLASSES[i][0]) for i in present]
    if "stable_count" in result and (np.asarray(result["stable_count"]) >= 2).any():
        handles.append(Patch(facecolor="none", edgecolor=OKABE_ITO[1], label="bistable boundary"))
    ax.legend(handles=handles, loc="upper left", fontsize=7, framealpha=0.9)
    ax.set_xlabel("torsion $\\tau$")
    ax.set_ylabel("curvature $\\kappa$")
    ax.set_title("equilibria per helix")


def _robust_limit(values, q=98.0):
    finite = np.abs(values[np.isfinite(values)])
    return float(np.percentile(finite, q)) if finite.size else 1.0


def _draw_map(fig, ax, x, y, values, title, label, *, diverging=True, zero_line=True):
    from matplotlib.colors import Normalize

    values = np.asarray(values, dtype=float)
    lim = _robust_limit(values) or 1.0
    if diverging:
        norm, cmap = Normalize(-lim, lim), "PuOr_r"
    else:
        finite = values[np.isfinite(values)]
        norm, cmap = Normalize(np.min(finite) if finite.size else 0, lim), "cividis"
    mesh = ax.pcolormesh(x, y, values, cmap=cmap, norm=norm, shading="nearest", rasterized=True)
    pass  # NaN cells stay transparent (white background)
    if zero_line and np.nanmin(values) < 0 < np.nanmax(values):
        ax.contour(x, y, np.nan_to_num(values), levels=[0.0], colors="k", linewidths=0.8)
        ax.plot([], [], color="k", lw=0.8, label=f"${label.strip('$')} = 0$")
        ax.legend(loc="upper left", fontsize=7, framealpha=0.9)
    fig.colorbar(mesh, ax=ax, label=label, extend="both")
    ax.set_title(title)
    ax.set_xlabel("torsion $\\tau$")
    ax.set_ylabel("curvature $\\kappa$")


def plot_atlas(result, path=None):
    """Equilibrium-count atlas of a `sweep` result over the $(\\tau, \\kappa)$ plane: the
    number of registers per helix (Okabe-Ito classes), the bistable region (two stable
    registers) outlined.  Needs the field `count` (`stable_count`, `continuum` used when
    present)."""
    _need(result, "count")
    fig, (ax,) = _figure()
    _draw_atlas(ax, result)
    return _finish(fig, path)


def plot_stable_wrench(result, path=None):
    """Axial force $F$ and moment $M$ of the stable branch (the stable register of least
    energy) over the $(\\tau, \\kappa)$ plane, colour clipped at the 98th percentile of
    $|F|$, $|M|$ (both diverge like $1/\\kappa$ for a curved rod); black: $F = 0$, $M = 0$.
    Needs the fields `stable_force`, `stable_moment`."""
    _need(result, "stable_force", "stable_moment")
    fig, axes = _figure(2)
    _draw_map(fig, axes[0], result.tau, result.kappa, result["stable_force"], "stable branch: axial force", "$F$")
    _draw_map(fig, axes[1], result.tau, result.kappa, result["stable_moment"], "stable branch: axial moment", "$M$")
    return _finish(fig, path)


def plot_sensitivity(sens, path=None, *, quantity="force_elasticity", slot=0, parameters=None):
    """Maps of one `sensitivity` output (default the force elasticity
    $(\\theta/F)\\,\\partial F/\\partial\\theta$) of register `slot` (0: the global energy
    minimum of $W$ on the circle, 1: the maximum, 2/3: the inner pair) for each parameter
    in `parameters`.  By default every parameter of `sens.wrt`, less, for an elasticity,
    those whose value is zero: $\\theta\\,\\partial F/\\partial\\theta$ vanishes there, and
    its panel would be blank (plot `d_force` or `d_moment` for them).  A zero parameter
    asked for by name is drawn, and its panel says so."""
    per_parameter = [name for name in sens if name.startswith("d_") or name.endswith("_elasticity")]
    if quantity not in per_parameter:
        raise ValueError(f"plot_sensitivity: quantity must be one with a parameter axis, one of {per_parameter}; got {quantity!r}")
    if slot not in range(4):
        raise ValueError(f"slot must be 0, 1, 2 or 3 (the register), got {slot!r}")
    elasticity = quantity.endswith("_elasticity")
    zero = {name for name in sens.wrt if elasticity and _parameter_value(sens.rod, name) == 0}
    if parameters is None:
        parameters = tuple(name for name in sens.wrt if name not in zero) or sens.wrt
    parameters = tuple(parameters)
    unknown = [name for name in parameters if name not in sens.wrt]
    if unknown:
        raise ValueError(f"parameters {unknown} are not among the sensitivity's wrt {list(sens.wrt)}")
    if not parameters:
        raise ValueError("plot_sensitivity: parameters is empty; name at least one of " + str(list(sens.wrt)))
    ncols = min(4, len(parameters))
    nrows = -(-len(parameters) // ncols)
    fig, axes = _figure(ncols, nrows, width=3.6, height=3.0)
    symbol = {"force_elasticity": "(\\theta/F)\\,\\partial F/\\partial\\theta",
              "moment_elasticity": "(\\theta/M)\\,\\partial M/\\partial\\theta",
              "d_force": "\\partial F/\\partial\\theta", "d_moment": "\\partial M/\\partial\\theta",
              "d_phi": "\\partial\\varphi/\\partial\\theta"}.get(quantity, quantity)
    for ax, name in zip(axes, parameters):
        values = sens.of(name, quantity)[..., slot]
        title = f"$\\theta = {_tex_parameter(name)}$" + (" = 0: elasticity 0" if name in zero else "")
        _draw_map(fig, ax, sens.tau, sens.kappa, values, title, f"${symbol}$")
    for ax in axes[len(parameters):]:
        ax.set_visible(False)
    fig.suptitle(f"register slot {slot} ({REGISTER_SLOTS[slot]})", fontsize=9)
    return _finish(fig, path)


#: What each register slot of `HelixEquilibria` and `sweep` holds.
REGISTER_SLOTS = ("global minimum of W on the circle", "global maximum", "inner local minimum", "inner local maximum")


def _parameter_value(rod, name):
    """The value of one `sensitivity` parameter (`K1` ... `K23`, `uhat1` ... `uhat3`) of an unbatched rod."""
    if name.startswith("uhat"):
        return float(np.asarray(rod.uhat)[int(name[-1]) - 1])
    return float(np.asarray(getattr(rod, name)))


def _tex_parameter(name):
    if name.startswith("uhat"):
        return f"\\hat u_{name[-1]}"
    return f"K_{{{name[1:]}}}"


def plot_helix(kappa, tau, path=None, *, turns=3.0, samples=600):
    """The centreline of the helix of curvature `kappa` > 0 and torsion `tau` in 3D
    (`helix_centreline`, axis $e_z$), `turns` turns long, coloured by arc length, with
    its axis dashed."""
    import jax.numpy as jnp
    from matplotlib import colormaps

    from ._geometry import helix_centreline

    if np.ndim(kappa) or np.ndim(tau):
        raise ValueError(f"plot_helix draws one helix: kappa and tau must be scalars, got shapes {np.shape(kappa)}, {np.shape(tau)}")
    if not (np.isfinite(kappa) and kappa > 0 and np.isfinite(tau)):
        raise ValueError(f"plot_helix needs a finite kappa > 0 and a finite tau, got {kappa}, {tau}")
    if not (np.isfinite(turns) and turns > 0) or isinstance(samples, bool) or int(samples) != samples or samples < 2:
        raise ValueError(f"plot_helix needs turns > 0 and an integer samples >= 2, got {turns}, {samples}")
    samples = int(samples)
    norm_u = float(np.hypot(kappa, tau))
    s = np.linspace(0.0, turns * 2 * np.pi / norm_u, samples)
    x = np.asarray(helix_centreline(jnp.asarray(kappa, float), jnp.asarray(tau, float), jnp.asarray(s)))
    fig, (ax,) = _figure(width=4.8, height=4.8, projection="3d")
    colours = colormaps["cividis"](np.linspace(0, 1, samples - 1))
    for i in range(0, samples - 1, 3):
        ax.plot(x[i : i + 4, 0], x[i : i + 4, 1], x[i : i + 4, 2], color=colours[i], lw=2.2)
    ax.plot([0, 0], [0, 0], [x[0, 2], x[-1, 2]], ls="--", color=OKABE_ITO[7], lw=1)
    r = float(kappa) / norm_u**2
    span = max(r, abs(x[-1, 2] - x[0, 2]) / 2)
    mid = 0.5 * (x[0, 2] + x[-1, 2])
    ax.set_xlim(-span, span)
    ax.set_ylim(-span, span)
    ax.set_zlim(mid - span, mid + span)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("$x$")
    ax.set_ylabel("$y$")
    ax.set_zlabel("$z$")
    ax.set_title(f"helix $\\kappa = {kappa:g}$, $\\tau = {tau:g}$ (radius {r:.3g}, pitch {2 * np.pi * float(tau) / norm_u**2:.3g})", fontsize=9)
    return _finish(fig, path)


def plot_sweep_summary(result, path=None):
    """The count atlas of a `sweep` result, with the stable-branch force and moment maps
    beside it when the result holds `stable_force` and `stable_moment`."""
    _need(result, "count")
    wrench = "stable_force" in result and "stable_moment" in result
    fig, axes = _figure(3 if wrench else 1)
    _draw_atlas(axes[0], result)
    if wrench:
        _draw_map(fig, axes[1], result.tau, result.kappa, result["stable_force"], "stable branch: axial force", "$F$")
        _draw_map(fig, axes[2], result.tau, result.kappa, result["stable_moment"], "stable branch: axial moment", "$M$")
    return _finish(fig, path)


#: The fields `plot_sweep_summary` draws.
SUMMARY_FIELDS = ("count", "stable_count", "continuum", "stable_force", "stable_moment")


def plot_rod_atlas(rod, path=None, *, kappa=(0.0, 3.0), tau=(-3.0, 3.0), n=241, progress=False):
    """Sweep `rod` over an `n` x `n` grid of the `kappa` x `tau` ranges and draw
    `plot_sweep_summary` (count atlas, stable-branch force and moment).  Used by
    `helixrod demo`."""
    from ._sweep import sweep

    result = sweep(rod, np.linspace(*kappa, n), np.linspace(*tau, n), fields=SUMMARY_FIELDS, progress=progress)
    return plot_sweep_summary(result, path)


# -- tweezer curves ---------------------------------------------------------------------------
def _groups(*keys):
    """Indices of the points of each distinct combination of `keys` (arrays of equal
    length), in order of first appearance."""
    out: dict = {}
    for i, key in enumerate(zip(*keys)):
        out.setdefault(key, []).append(i)
    return [(k, np.asarray(v)) for k, v in out.items()]


def _signed_residuals(fit, data_values, predicted, start, count):
    """`(data - fit) / sigma` at `count` points: minus the fit's normalised residuals
    `fit.residuals[start:start + count]` (prediction minus data over sigma, the sigmas with
    errors in variables where the fit used them); `None` where the fit has no such residuals."""
    r = np.asarray(getattr(fit, "residuals", np.zeros(0)), dtype=float)
    if r.shape[0] < start + count:
        return None
    return -r[start : start + count]


def plot_tweezer_fit(fit, data, path=None):
    """A `StiffnessFit` of `TweezerData` in tweezer coordinates, one column per kind of curve
    present, the curves above and the residuals (data minus fit over the point's sigma, as in
    the fit: with errors in variables where the fit used them) below:

    - extension against force of the torque-controlled points (a free swivel: the
      force-extension curve), one colour per molecule (and torque), logarithmic force axis;
    - hat curves, extension against turns, one colour per force and one marker per molecule;
    - measured torque against turns where a torque was measured.

    Points are the data with error bars (their sigmas: `extension_sigma`,
    `measured_torque_sigma`), lines the fit's predictions at the data points
    (`fit.predicted["extension"]`, `fit.predicted["torque"]`, in the order of the data), so the
    lines join the points of one curve.  `path=None` returns the matplotlib `Figure`;
    otherwise writes it (PNG/PDF/SVG by suffix) and returns `path`."""
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    force = np.asarray(data.force, dtype=float)
    extension = np.asarray(data.extension, dtype=float)
    sigma = np.asarray(data.extension_sigma, dtype=float)
    turns, torque = np.asarray(data.turns, dtype=float), np.asarray(data.torque, dtype=float)
    by_torque = np.asarray(data.torque_controlled, dtype=bool)
    measured = np.asarray(data.has_measured_torque, dtype=bool)
    molecule = np.asarray(data.molecule)
    names = data.molecule_names
    n = extension.shape[0]
    ext_fit = np.asarray(fit.predicted["extension"], dtype=float)
    if ext_fit.shape != (n,):
        raise ValueError(f"plot_tweezer_fit: fit.predicted['extension'] has shape {ext_fit.shape}, the data {n} points")
    ext_res = _signed_residuals(fit, extension, ext_fit, 0, n)
    if ext_res is None:
        ext_res = (extension - ext_fit) / sigma
    columns = [kind for kind, present in (("fd", by_torque.any()), ("hat", (~by_torque).any()), ("torque", measured.any())) if present]
    fig = Figure(figsize=(4.8 * len(columns), 6.2), layout="constrained")
    axes = fig.subplots(2, len(columns), sharex="col", squeeze=False, gridspec_kw={"height_ratios": [3, 1]})
    markers = "osD^vP*X"
    residual_label = "(data $-$ fit) / $\\sigma$ (dimensionless)"

    def curve(ax, rax, idx, x, y, yfit, err, res, colour, marker, label=None):
        order = idx[np.argsort(x[idx], kind="stable")]
        ax.errorbar(x[order], y[order], yerr=err[order], fmt=marker, ms=3.5, color=colour, ecolor="0.7",
                    elinewidth=0.8, mfc="white" if marker != "o" else colour, label=label)
        ax.plot(x[order], yfit[order], "-", color=colour, lw=1.2)
        rax.plot(x[order], res[order], marker, ms=3, color=colour, mfc="white" if marker != "o" else colour)

    for col, kind in enumerate(columns):
        ax, rax = axes[0, col], axes[1, col]
        rax.axhline(0.0, color="k", lw=0.8)
        if kind == "fd":
            idx = np.flatnonzero(by_torque)
            groups = _groups(molecule[idx], torque[idx])
            for g, ((m, t), members) in enumerate(groups):
                label = names[m] + (f", torque {t:g} pN nm" if t != 0 else "")
                curve(ax, rax, idx[members], force, extension, ext_fit, sigma, ext_res, OKABE_ITO[g % 8], "o", label)
            if force[idx].max() > 10 * force[idx].min():
                ax.set_xscale("log")
            ax.set_ylabel("extension (nm)")
            ax.set_title("force-extension (torque-controlled points)")
            rax.set_xlabel("force (pN)")
            ax.legend(fontsize=7, title="molecule", title_fontsize=7)
        elif kind == "hat":
            idx = np.flatnonzero(~by_torque)
            levels = sorted({float(f"{f:.4g}") for f in force[idx]})
            rounded = np.array([float(f"{f:.4g}") for f in force[idx]])
            for (m, f), members in _groups(molecule[idx], rounded):
                colour = OKABE_ITO[levels.index(f) % 8]
                curve(ax, rax, idx[members], turns, extension, ext_fit, sigma, ext_res, colour, markers[m % len(markers)])
            handles = [Line2D([], [], color=OKABE_ITO[i % 8], marker="o", lw=1.2, ms=4, label=f"{f:g} pN") for i, f in enumerate(levels)]
            if len(names) > 1:
                handles += [Line2D([], [], color="0.3", marker=markers[i % len(markers)], ls="none", mfc="white" if i else "0.3",
                                   ms=4, label=name) for i, name in enumerate(names)]
            ax.legend(handles=handles, fontsize=7, ncols=2, title="force, molecule", title_fontsize=7)
            ax.set_ylabel("extension (nm)")
            ax.set_title("hat curves (turns-controlled points)")
            rax.set_xlabel("turns (positive = overwound)")
        else:
            idx = np.flatnonzero(measured)
            tq = np.asarray(data.measured_torque, dtype=float)
            tq_sigma = np.asarray(data.measured_torque_sigma, dtype=float)
            tq_fit = np.asarray(fit.predicted["torque"], dtype=float)
            res = np.full(n, np.nan)
            signed = _signed_residuals(fit, tq[idx], tq_fit[idx], n, idx.size)
            res[idx] = (tq[idx] - tq_fit[idx]) / tq_sigma[idx] if signed is None else signed
            x = np.where(by_torque, np.nan, turns)
            rounded = np.array([float(f"{f:.4g}") for f in force])
            for g, ((m, f), members) in enumerate(_groups(molecule[idx], rounded[idx])):
                curve(ax, rax, idx[members], x, tq, tq_fit, tq_sigma, res, OKABE_ITO[g % 8], "o", f"{names[m]}, {f:g} pN")
            ax.set_ylabel("torque (pN nm)")
            ax.set_title("measured torque")
            rax.set_xlabel("turns (positive = overwound)")
            ax.legend(fontsize=7, title="molecule, force", title_fontsize=7)
        rax.set_ylabel(residual_label, fontsize=8)
    chi2 = float(getattr(fit, "chi2_reduced", np.nan))
    molecules = f"{len(names)} molecule{'s' if len(names) != 1 else ''}"
    fig.suptitle(f"tweezer fit: {n} points of {molecules}, reduced $\\chi^2$ = {chi2:.3g}")
    return _finish(fig, path)


def plot_tweezer_moduli(moduli, path=None, *, stderr=None, twlc=None):
    """The moduli of a molecule along the force range (`dna.tweezer_moduli`) in the
    single-molecule literature's terms, four panels against force (logarithmic axis): the
    stretch modulus S; the twist modulus C, at constant force $C - g^2/S$ and with the
    Moroz-Nelson softening; the twist-stretch coupling g; the buckling torque.

    `stderr`: the standard errors of the same fields (a `TweezerModuli`, e.g. from
    `fit.propagate(lambda rod, p: dna.tweezer_moduli(rod, forces, ...))`), drawn as
    +-1 sigma bands.  `twlc`: the twistable worm-like chain's phenomenological coupling
    to draw beside the rod's, `(g0, g1, Fc)` in pN nm, nm and pN as pylake's `twlc_distance`
    uses them, $g(F) = g_0 + g_1 \\max(F, F_c)$ (Gross et al., Nature Phys. 7, 731 (2011)).
    `path=None` returns the matplotlib `Figure`; otherwise writes it and returns `path`."""
    force = np.asarray(moduli.force, dtype=float)
    if force.ndim != 1 or force.size < 2:
        raise ValueError("plot_tweezer_moduli: needs moduli at two or more forces (a 1-D force array)")
    fig, axes = _figure(2, 2, width=4.4, height=3.4)
    axes = np.asarray(axes).reshape(-1)
    panels = (
        ("stretch modulus S (pN)", (("stretch_modulus", "S of the rod's helix"),)),
        ("twist modulus (pN nm$^2$)", (("twist_modulus", "C"), ("twist_modulus_at_constant_force", "$C - g^2/S$ (constant force)"),
                                       ("effective_twist_modulus", "$C_{eff}$ (Moroz-Nelson)"))),
        ("twist-stretch coupling g (pN nm)", (("twist_stretch_coupling", "g of the rod (mechanistic)"),)),
        ("buckling torque (pN nm)", (("buckling_torque", "Marko (2007)"),)),
    )
    for ax, (label, fields) in zip(axes, panels):
        for i, (field, name) in enumerate(fields):
            value = np.asarray(getattr(moduli, field), dtype=float)
            colour = OKABE_ITO[i % 8]
            ax.plot(force, value, "-", color=colour, lw=1.4, label=name)
            if stderr is not None:
                err = np.asarray(getattr(stderr, field), dtype=float)
                ax.fill_between(force, value - err, value + err, color=colour, alpha=0.25, lw=0)
        ax.set_xscale("log")
        ax.set_xlabel("force (pN)")
        ax.set_ylabel(label)
    if twlc is not None:
        g0, g1, fc = (float(x) for x in twlc)
        axes[2].plot(force, g0 + g1 * np.maximum(force, fc), "--", color=OKABE_ITO[3], lw=1.4,
                     label=f"tWLC $g_0 + g_1\\max(F, F_c)$ ({g0:g} pN nm, {g1:g} nm, {fc:g} pN)")
    for ax in axes:
        ax.legend(fontsize=7)
    fig.suptitle("the molecule's moduli along the force range" + (" ($\\pm 1\\sigma$)" if stderr is not None else ""))
    return _finish(fig, path)


_STABILITY_CLASSES = (
    # (label, colour) for: no register / not resolved, stable, index 1, index >= 2.
    ("no register, or not resolved", "#DDDDDD"),
    ("stable", OKABE_ITO[2]),
    ("unstable, 1 direction", OKABE_ITO[0]),
    ("unstable, 2 or more", OKABE_ITO[5]),
)


def plot_stability_atlas(atlas, path=None, *, slot=0):
    """A `StabilityAtlas` over the $(\\tau, \\kappa)$ plane for one register `slot` (0: the
    global minimum of $W$ on the circle, as `helix_equilibria`): left, whether the helix of
    length $L$ clamped by its own wrench is stable (and how many unstable directions it
    has), with the pointwise criterion of `helix_equilibria` (a minimum of $W$ on the
    circle) outlined; right, the critical length at which it first loses stability, on a
    log scale, white where it stays stable up to `max_length`, grey where it is not defined
    (no register, or not resolved: NaN), marked by the type of that loss of stability
    (`instability_type`: o fold, x symmetry-breaking); empty, and titled so, for an atlas
    computed with `critical_length=False`."""
    from matplotlib.colors import BoundaryNorm, ListedColormap, LogNorm
    from matplotlib.patches import Patch

    if slot not in range(4):
        raise ValueError(f"plot_stability_atlas: slot must be 0, 1, 2 or 3 (the register), got {slot!r}")
    tau, kappa = np.asarray(atlas.tau, float), np.asarray(atlas.kappa, float)
    if tau.ndim != 2:
        raise ValueError(f"plot_stability_atlas: needs a 2-d (kappa, tau) grid, got shape {tau.shape}")
    index = np.asarray(atlas.instability_index[..., slot])
    valid = np.asarray(atlas.valid[..., slot]) & (index >= 0)
    cls = np.where(~valid, 0, np.where(index == 0, 1, np.where(index == 1, 2, 3)))
    fig, axes = _figure(2)
    cmap = ListedColormap([c for _, c in _STABILITY_CLASSES])
    axes[0].pcolormesh(tau, kappa, cls, cmap=cmap, norm=BoundaryNorm(np.arange(-0.5, 4.5), cmap.N), shading="nearest", rasterized=True)
    pointwise = np.asarray(atlas.pointwise_stable[..., slot]).astype(float)
    handles = [Patch(facecolor=_STABILITY_CLASSES[i][1], edgecolor="k", lw=0.4, label=_STABILITY_CLASSES[i][0]) for i in sorted(set(np.unique(cls).tolist()))]
    if 0 < pointwise.mean() < 1:
        axes[0].contour(tau, kappa, pointwise, levels=[0.5], colors="k", linewidths=1.0, linestyles="--")
        handles.append(Patch(facecolor="none", edgecolor="k", ls="--", label="edge of pointwise stability"))
    axes[0].legend(handles=handles, loc="upper left", fontsize=7, framealpha=0.9)
    axes[0].set_title(f"clamped helix of length $L = {float(atlas.length):.4g}$, register slot {slot}")
    critical = np.asarray(atlas.critical_length[..., slot], float)
    kind = np.asarray(atlas.instability_type[..., slot])
    # Not asked for: NaN everywhere with no point flagged undefined (-1).
    computed = bool(np.any(~np.isnan(critical)) or np.any(kind == -1))
    undefined = np.isnan(critical)
    type_handles = []
    if computed and undefined.any():
        grey = _STABILITY_CLASSES[0][1]
        axes[1].pcolormesh(tau, kappa, np.where(undefined, 1.0, np.nan), cmap=ListedColormap([grey]), shading="nearest", rasterized=True)
        type_handles.append(Patch(facecolor=grey, edgecolor="k", lw=0.4, label=_STABILITY_CLASSES[0][0]))
    finite = critical[np.isfinite(critical) & (critical > 0)]
    if finite.size:
        mesh = axes[1].pcolormesh(tau, kappa, np.where(np.isfinite(critical), critical, np.nan), cmap="cividis",
                                  norm=LogNorm(finite.min(), max(finite.max(), finite.min() * 1.01)), shading="nearest", rasterized=True)
        fig.colorbar(mesh, ax=axes[1], label="critical length $L_c$")
        if finite.min() < float(atlas.length) < finite.max():
            # Undefined points are masked: no contour along their edge.
            levels = np.ma.masked_invalid(np.where(np.isposinf(critical), 1e300, critical))
            axes[1].contour(tau, kappa, levels, levels=[float(atlas.length)], colors=[OKABE_ITO[1]], linewidths=1.2)
    # The type of that loss of stability, a marker per grid point (codes of INSTABILITY_TYPES).
    for code, style, label in ((1, dict(marker="o", facecolors="none", edgecolors="k"), "fold"), (2, dict(marker="x", c="k"), "symmetry-breaking")):
        where = kind == code
        if where.any():
            type_handles.append(axes[1].scatter(tau[where], kappa[where], s=12, linewidths=0.8, label=label, **style))
    if type_handles:
        axes[1].legend(handles=type_handles, loc="upper left", fontsize=7, framealpha=0.9)
    if computed:
        axes[1].set_title(f"first loss of stability (white: stable up to {float(atlas.max_length):.4g})")
    else:
        axes[1].set_title("critical lengths not computed (critical_length=False)")
    for ax in axes:
        ax.set_xlabel("torsion $\\tau$")
        ax.set_ylabel("curvature $\\kappa$")
    return _finish(fig, path)
