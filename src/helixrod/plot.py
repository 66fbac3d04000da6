"""Figures of helixrod (matplotlib): ``from helixrod import plot``.

Every function takes ``path=None``: with a path the figure is written and the path
returned, otherwise the ``matplotlib.figure.Figure`` is returned.
"""

from ._plot import (
    OKABE_ITO as OKABE_ITO,
    plot_atlas as plot_atlas,
    plot_fit as plot_fit,
    plot_helix as plot_helix,
    plot_hyperboloid as plot_hyperboloid,
    plot_model_comparison as plot_model_comparison,
    plot_response as plot_response,
    plot_rod_atlas as plot_rod_atlas,
    plot_sensitivity as plot_sensitivity,
    plot_stability_atlas as plot_stability_atlas,
    plot_stable_wrench as plot_stable_wrench,
    plot_sweep_summary as plot_sweep_summary,
    plot_tweezer_fit as plot_tweezer_fit,
    plot_tweezer_moduli as plot_tweezer_moduli,
)
