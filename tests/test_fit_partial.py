"""Partial observations (the reference report's question: what can be learnt without the
moment?): force-only and moment-only helix data, per-point masks, and what such fits
determine, against closed forms.

Closed forms used (derived in the docstrings below, checked here against `helix_equilibria`):

- An uncoupled rod ($K_{13} = K_{23} = 0$, $\\hat u = 0$, $K_1 < K_2$) has its registers at
  $\\varphi = 0, \\pi/2, \\pi, 3\\pi/2$, and its stable ones bend about the softer axis
  ($\\varphi = \\pi/2$): there $F = |u|\\,\\tau (K_3 - K_1)$ and $M = (K_1\\kappa^2 + K_3\\tau^2)/|u|$,
  so force-only data determine $K_3 - K_1$ alone, moment-only data $K_1$ and $K_3$, and
  neither sees $K_2$.
- For any rod, $K \\to K + cI$ with $K\\hat u$ held fixed changes no force: the equilibrium
  $K(u - \\hat u) = \\mu u + \\lambda e_3$ holds with $\\mu + c$ and the same $\\lambda$, register
  and $F = \\lambda |u|$, while $M = \\mu|u| + \\lambda\\tau/|u|$ shifts by $c|u|$.
"""

import jax
import numpy as np
import pytest
from helpers import FIT_POINTS, fit_grid

import helixrod as hr

UNCOUPLED = hr.Rod(1.0, 1.6, 1.3)


def test_uncoupled_closed_forms_and_the_trace_shift(rng):
    kappa, tau = fit_grid(rng)
    eq = hr.helix_equilibria(UNCOUPLED, kappa, tau)
    norm = np.hypot(kappa, tau)
    stable_phi = np.asarray(eq.phi)[np.asarray(eq.stable)]
    np.testing.assert_allclose(np.mod(stable_phi, np.pi), np.pi / 2, atol=1e-12)
    np.testing.assert_allclose(eq.force[:, 0], norm * tau * (1.3 - 1.0), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(eq.moment[:, 0], (kappa**2 + 1.3 * tau**2) / norm, rtol=1e-12)
    # The trace shift on a generic rod, every register.
    rod = hr.Rod(0.8, 1.7, 1.2, K13=0.3, K23=-0.2, uhat=(0.4, -0.3, 0.5))
    c = 0.37
    K = np.array([[0.8, 0, 0.3], [0, 1.7, -0.2], [0.3, -0.2, 1.2]])
    uhat = np.linalg.solve(K + c * np.eye(3), K @ np.array([0.4, -0.3, 0.5]))
    shifted = hr.Rod(0.8 + c, 1.7 + c, 1.2 + c, K13=0.3, K23=-0.2, uhat=uhat)
    a, b = hr.helix_equilibria(rod, kappa, tau), hr.helix_equilibria(shifted, kappa, tau)
    np.testing.assert_allclose(b.phi, a.phi, atol=1e-10)
    np.testing.assert_allclose(b.force, a.force, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(b.valid, a.valid)
    expected = np.where(a.valid, c * norm[:, None], np.nan)
    np.testing.assert_allclose(b.moment - a.moment, expected, rtol=1e-10, atol=1e-12)


def test_force_only_and_moment_only_fits_determine_what_they_should(rng):
    kappa, tau = fit_grid(rng)
    uncoupled = {"K13": 0.0, "K23": 0.0}
    exact = hr.synthetic_helix_data(UNCOUPLED, kappa, tau, 0.0, jax.random.key(0), observe="force")
    assert exact.observed == ("force",) and "moment not observed" in repr(exact)
    force_only = hr.HelixData(exact.force, None, kappa, tau, force_sigma=1e-3)  # exact, weighted as 1e-3
    fit = hr.fit_stiffness(force_only, fix=uncoupled, n_starts=4)
    assert fit.ok and fit.cost < 1e-20 and fit.n_residuals == FIT_POINTS
    p = {n: float(v) for n, v in fit.params.items()}
    assert abs((p["K3"] - p["K1"]) - 0.3) < 1e-8
    assert all(np.isinf(float(fit.stderr[n])) for n in fit.names)  # no single stiffness is determined
    ident = fit.identifiability
    assert ident.rank == 1
    (combination,) = ident.determined
    assert dict(combination) == pytest.approx({"K1": 0.7071, "K3": -0.7071}, abs=2e-4)
    assert "determined: +0.707*K1 -0.707*K3" in fit.summary()
    # Moment only: K1 and K3 exactly, K2 not at all.
    moment_only = hr.synthetic_helix_data(UNCOUPLED, kappa, tau, 0.0, jax.random.key(0), observe=("moment",))
    fit = hr.fit_stiffness(moment_only, fix=uncoupled, n_starts=4)
    assert fit.ok and fit.cost < 1e-20
    assert float(fit.params["K1"]) == pytest.approx(1.0, abs=1e-8) and float(fit.params["K3"]) == pytest.approx(1.3, abs=1e-8)
    assert np.isfinite(float(fit.stderr["K1"])) and np.isfinite(float(fit.stderr["K3"])) and np.isinf(float(fit.stderr["K2"]))


@pytest.mark.heavy
def test_masked_points_residuals_and_bootstrap(rng):
    """Half the points force-only, half moment-only: the residuals are the observed ones,
    the cost is recomputed from the predictions, and the bootstrap runs on the masks."""
    kappa, tau = fit_grid(rng)
    rod = hr.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
    full = hr.synthetic_helix_data(rod, kappa, tau, 0.01, jax.random.key(2))
    force, moment = np.asarray(full.force).copy(), np.asarray(full.moment).copy()
    half = np.arange(FIT_POINTS) % 2 == 0
    force[half], moment[~half] = np.nan, np.nan
    data = hr.HelixData(force, moment, kappa, tau, full.force_sigma, full.moment_sigma)
    np.testing.assert_array_equal(data.force_observed, ~half)
    fit = hr.fit_stiffness(data, uhat=rod.uhat, init=rod, n_starts=2)
    assert fit.ok and fit.n_residuals == FIT_POINTS
    by_hand = np.concatenate([
        (np.asarray(fit.predicted["force"]) - force)[~half] / np.asarray(full.force_sigma)[~half],
        (np.asarray(fit.predicted["moment"]) - moment)[half] / np.asarray(full.moment_sigma)[half],
    ])
    np.testing.assert_allclose(fit.residuals, by_hand, rtol=1e-10, atol=1e-12)
    assert float(fit.cost) == pytest.approx(0.5 * float(by_hand @ by_hand), rel=1e-10)
    for kind in ("cases", "parametric"):
        boot = hr.bootstrap(data, fit, 8, jax.random.key(3), kind=kind)
        assert np.asarray(boot.ok).sum() >= 6
        for name in fit.names:
            assert np.isfinite(float(boot.std[name]))


def test_partial_csv_and_errors(tmp_path, rng):
    kappa, tau = fit_grid(rng)
    data = hr.synthetic_helix_data(UNCOUPLED, kappa, tau, 0.01, jax.random.key(1), observe="force")
    path = tmp_path / "force_only.csv"
    text = data.to_csv(path)
    assert text.splitlines()[1].startswith("force,kappa,tau,force_sigma")  # no moment columns
    back = hr.HelixData.from_csv(path)
    assert back.observed == ("force",)
    np.testing.assert_array_equal(back.force, data.force)
    # Empty cells: a quantity not measured at that point.
    rows = "force,moment,kappa,tau,force_sigma,moment_sigma\n1.0,,1.0,0.5,0.1,\n,2.0,1.0,0.6,,0.2\n"
    (tmp_path / "mixed.csv").write_text(rows)
    mixed = hr.HelixData.from_csv(tmp_path / "mixed.csv")
    np.testing.assert_array_equal(mixed.force_observed, [True, False])
    np.testing.assert_array_equal(mixed.moment_observed, [False, True])
    (tmp_path / "bad.csv").write_text("force,moment,kappa,tau,force_sigma,moment_sigma\n1.0,2.0,,0.5,0.1,0.1\n")
    with pytest.raises(ValueError, match=r"bad.csv:2: empty cells in \['kappa'\]"):
        hr.HelixData.from_csv(tmp_path / "bad.csv")
    with pytest.raises(ValueError, match="neither force nor moment is given"):
        hr.HelixData(None, None, [1.0], [0.5])
    with pytest.raises(ValueError, match=r"rows \[1\] observe neither force nor moment"):
        hr.HelixData([1.0, np.nan], [2.0, np.nan], [1.0, 1.0], [0.5, 0.5])
    with pytest.raises(ValueError, match="non-finite"):
        hr.HelixData([1.0, np.inf], [2.0, 1.0], [1.0, 1.0], [0.5, 0.5])
    # A sigma is read only where its quantity is observed.
    ok = hr.HelixData([1.0, np.nan], [2.0, 3.0], [1.0, 1.0], [0.5, 0.5], force_sigma=[0.1, np.nan], moment_sigma=0.1)
    assert ok.observed == ("force", "moment")
    with pytest.raises(ValueError, match=r"force_sigma must be > 0; rows \[0\]"):
        hr.HelixData([1.0, np.nan], [2.0, 3.0], [1.0, 1.0], [0.5, 0.5], force_sigma=[-0.1, 1.0])
    with pytest.raises(ValueError, match="observe must name"):
        hr.synthetic_helix_data(UNCOUPLED, kappa, tau, 0.01, jax.random.key(1), observe=("torque",))
