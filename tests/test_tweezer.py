"""A DNA molecule in a tweezer (`helixrod._tweezer`): the worm-like chain against the exact
infinite chain (the rotor ground state), the stiff-rod and Odijk limits (lumicks pylake),
Moroz-Nelson softening from the rod's own moduli, Marko's closed forms for buckling and
the plateau, derivatives against central differences, bad input and flagged points; the
tweezer fit recovers its generating parameters (slow)."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import quad
from scipy.linalg import eigh_tridiagonal
from scipy.optimize import brentq

import helixrod as hr
from helixrod import _tweezer as tw
from helixrod import dna

ROD = dna.load_tweezer_example().rod
KT = float(dna.kT())
A = 50.0
RISE = float(dna.helix_from_bdna()[2] * ROD.uhat[2] / jnp.linalg.norm(ROD.uhat))


def exact_wlc(f, lmax=600):
    """Relative extension of the infinite worm-like chain at f = FA/kT: minus the derivative
    of the ground-state energy of H = -(1/2) Laplacian - f cos(theta) on the sphere, in the
    Legendre basis (Marko and Siggia 1995), by a central difference."""
    l = np.arange(lmax)
    diagonal = l * (l + 1) / 2.0
    off = -(l[:-1] + 1) / np.sqrt((2 * l[:-1] + 1) * (2 * l[:-1] + 3))

    def energy(x):
        return eigh_tridiagonal(diagonal, x * off, select="i", select_range=(0, 0))[0][0]

    h = 1e-5 * max(f, 1e-3)
    return -(energy(f + h) - energy(f - h)) / (2 * h)


def bouchiat_inverse(f):
    coefficients = (0, 0) + tw.BOUCHIAT_COEFFICIENTS
    force = lambda z: 0.25 / (1 - z) ** 2 - 0.25 + z + sum(a * z**i for i, a in enumerate(coefficients))
    return brentq(lambda z: force(z) - f, 0.0, 1 - 1e-12, xtol=1e-15)


def test_wlc_against_the_exact_chain():
    forces = np.array([0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 60.0])
    z = np.asarray(tw.wlc_extension(forces, A))
    exact = np.array([exact_wlc(F * A / KT) for F in forces])
    error = np.abs(z / exact - 1)
    assert np.all(error <= 5e-3)  # measured 2.8e-3 at 0.01 pN
    assert np.all(error[forces >= 0.3] <= 1e-4)  # measured 4e-5 at 0.3 pN, 5e-6 from 1 pN
    # Inverse of the interpolation, and its free energy is the integral of z.
    np.testing.assert_allclose(tw.wlc_force(z, A), forces, rtol=1e-12)
    for F in (0.1, 2.0, 20.0):
        integral = quad(lambda x: bouchiat_inverse(x * A / KT), 0.0, F, epsabs=1e-12)[0]
        np.testing.assert_allclose(tw.wlc_free_energy(F, A), integral, rtol=1e-9)
    slope = jax.grad(lambda F: tw.wlc_extension(F, A))(2.0)
    central = (tw.wlc_extension(2.0 + 1e-5, A) - tw.wlc_extension(2.0 - 1e-5, A)) / 2e-5
    np.testing.assert_allclose(slope, central, rtol=1e-7)
    # Outside their domain: concrete values raise, traced ones are NaN beside good ones.
    with pytest.raises(ValueError, match="wlc_extension: force must be finite and >= 0"):
        tw.wlc_extension(-1.0)
    with pytest.raises(ValueError, match="wlc_free_energy: force must be finite and >= 0"):
        tw.wlc_free_energy(-1.0)
    with pytest.raises(ValueError, match=r"wlc_force: relative_extension must be in \[0, 1\)"):
        tw.wlc_force(1.2)
    z = jax.vmap(tw.wlc_extension)(jnp.array([2.0, -1.0]))
    assert z[0] == tw.wlc_extension(2.0) and np.isnan(z[1])
    f = jax.vmap(tw.wlc_force)(jnp.array([0.5, 1.0]))
    assert f[0] == tw.wlc_force(0.5) and np.isnan(f[1])


def test_a_stiff_rod_is_the_inextensible_chain():
    stiff = ROD.scaled(1e6)
    forces = jnp.array([0.3, 1.0, 5.0, 20.0])
    response = tw.tweezer_response(stiff, 5000, forces, torque=0.0, persistence_length=A)
    exact = np.array([exact_wlc(F * A / KT) for F in np.asarray(forces)])
    np.testing.assert_allclose(response.extension / (5000 * RISE), exact, rtol=1e-4)
    assert bool(jnp.all(response.ok)) and bool(jnp.all(response.phase == 0))


def test_free_swivel_matches_pylake_odijk_in_its_range():
    odijk = pytest.importorskip("lumicks.pylake.fitting.detail.model_implementation").ewlc_odijk_distance
    S, C, g = (float(x) for x in dna.effective_moduli(ROD, ROD.uhat))
    stretch_at_zero_torque = S - g**2 / C
    forces = np.array([10.0, 15.0, 20.0, 30.0])
    n_bp = 8000
    response = tw.tweezer_response(ROD, n_bp, forces, torque=0.0, persistence_length=A)
    peer = odijk(forces, A, n_bp * RISE, stretch_at_zero_torque, KT)
    # The difference is Odijk's asymptotic WLC against the exact one and the rod's own
    # nonlinearity (F/S ~ 3 %, its square ~ 1e-3): measured 3.2e-4 at most.
    np.testing.assert_allclose(response.extension, peer, rtol=1e-3)


def test_moroz_nelson_softening_of_the_rods_own_twist_modulus():
    np.testing.assert_allclose(tw.moroz_nelson_twist_modulus(410.0, 1.0, 50.0), 351.0, rtol=2e-3)
    S, C, g = (float(x) for x in dna.effective_moduli(ROD, ROD.uhat))
    response = tw.tweezer_response(ROD, 1000, jnp.array([0.5, 1.0, 4.0]), turns=0.0, persistence_length=A)
    # The rod's twist modulus at constant force, C - g^2/S at zero load (a helix per unit
    # axial length; its force dependence is the rod's nonlinearity, < 2 % here).
    np.testing.assert_allclose(response.twist_modulus, C - g**2 / S, rtol=2e-2)
    np.testing.assert_allclose(
        response.effective_twist_modulus, tw.moroz_nelson_twist_modulus(response.twist_modulus, jnp.array([0.5, 1.0, 4.0]), A),
        rtol=1e-12,
    )


@pytest.mark.heavy
def test_buckling_torque_and_plateau_follow_marko():
    F, P, n_bp = 1.0, 24.0, 8000
    turns = jnp.linspace(-40.0, 40.0, 161)
    hat = tw.tweezer_response(ROD, n_bp, F, turns=turns, persistence_length=A, plectoneme_twist_persistence=P)
    assert bool(jnp.all(hat.ok))
    # Marko's closed form with g(F) from an independent quadrature of the chain and the
    # rod's linear stretch energy at zero torque.
    S, C, g = (float(x) for x in dna.effective_moduli(ROD, ROD.uhat))
    wlc = quad(lambda x: bouchiat_inverse(x * A / KT), 0.0, F, epsabs=1e-12)[0]
    g_F = wlc + F**2 / (2 * (S - g**2 / C))
    C_eff = float(hat.effective_twist_modulus[0])
    marko = np.sqrt(2 * g_F / (1 / (KT * P) - 1 / C_eff))
    np.testing.assert_allclose(hat.buckling_torque, marko, rtol=1e-3)
    coexisting = np.asarray(hat.phase == 1)
    assert coexisting.sum() > 20 and np.all(np.asarray(hat.phase)[np.abs(np.asarray(turns)) < 10] == 0)
    # Plateau: the torque is the buckling torque and the extension falls linearly with turns.
    np.testing.assert_allclose(np.abs(hat.torque[coexisting]), hat.buckling_torque[coexisting], rtol=1e-9)
    right = coexisting & (np.asarray(turns) > 0)
    slope = np.polyfit(np.asarray(turns)[right], np.asarray(hat.extension)[right], 1, full=True)
    assert slope[1][0] < 1e-12 * float(jnp.max(hat.extension)) ** 2 * right.sum()
    # Beyond the plateau every turn goes to the plectoneme: zero extension.
    beyond = tw.tweezer_response(ROD, n_bp, F, turns=400.0, persistence_length=A)
    assert int(beyond.phase) == 2 and float(beyond.extension) == 0.0
    # Under a controlled torque above the plateau the molecule is plectonemic too.
    held = tw.tweezer_response(ROD, n_bp, F, torque=jnp.array([0.5, 1.5]) * float(hat.buckling_torque[0]))
    assert held.phase.tolist() == [0, 2]


@pytest.mark.heavy
def test_twist_stretch_coupling_tilts_the_hat():
    # g < 0 (overwinding under tension): the extension peaks at positive turns.
    turns = jnp.linspace(-6.0, 6.0, 121)
    hat = tw.tweezer_response(ROD, 8000, 2.0, turns=turns, persistence_length=A)
    assert float(turns[jnp.argmax(hat.extension)]) > 0


@pytest.mark.heavy
def test_derivatives_match_central_differences():
    def extension(K2, persistence, turns):
        rod = hr.Rod(ROD.K1, K2, ROD.K3, ROD.K13, ROD.K23, ROD.uhat)
        return tw.tweezer_response(rod, 8000, 1.0, turns=turns, persistence_length=persistence).extension

    x = (float(ROD.K2), 48.0, 5.0)
    grads = jax.grad(extension, argnums=(0, 1, 2))(*x)
    for i, h in enumerate((1.0, 1e-3, 1e-3)):
        up, down = list(x), list(x)
        up[i] += h
        down[i] -= h
        central = (extension(*up) - extension(*down)) / (2 * h)
        np.testing.assert_allclose(grads[i], central, rtol=1e-5)


def test_bad_input_and_flagged_points():
    with pytest.raises(ValueError, match="exactly one of turns= and torque="):
        tw.tweezer_response(ROD, 1000, 1.0)
    with pytest.raises(ValueError, match="force must be finite and > 0"):
        tw.tweezer_response(ROD, 1000, jnp.array([1.0, -1.0]), torque=0.0)
    with pytest.raises(ValueError, match="n_bp must be finite and > 0"):
        tw.tweezer_response(ROD, 0, 1.0, torque=0.0)
    with pytest.raises(ValueError, match="do not broadcast"):
        tw.tweezer_response(ROD, 1000, jnp.ones(3), turns=jnp.ones(2))
    # Traced: a bad point is flagged and NaN, the others are untouched.
    forces = jnp.array([1.0, jnp.nan, 2.0])
    batch = jax.jit(lambda f: tw.tweezer_response(ROD, 1000, f, turns=3.0))(forces)
    assert batch.ok.tolist() == [True, False, True]
    assert bool(jnp.isnan(batch.extension[1]))
    alone = tw.tweezer_response(ROD, 1000, 2.0, turns=3.0)
    np.testing.assert_allclose(batch.extension[2], alone.extension, rtol=1e-12)
    # Twisted at a force too low for the twist-fluctuation theory: outside its range.
    low = tw.tweezer_response(ROD, 1000, jnp.array([0.02, 0.02]), turns=jnp.array([0.0, 2.0]))
    assert low.ok.tolist() == [True, False]
    assert "range of validity" in hr.RESULTS[jax.tree.map(lambda code: code[1], low.result)]
    with pytest.raises(hr.SolverError, match="1 of 2 points failed"):
        tw.tweezer_response(ROD, 1000, jnp.array([0.02, 0.02]), turns=jnp.array([0.0, 2.0]), throw=True)


def test_bad_molecules_parameters_and_empty_input():
    # A base-pair count that is not finite and > 0 flags its point under vmap, both controls.
    batch = jax.vmap(lambda n: tw.tweezer_response(ROD, n, 1.0, turns=3.0))(jnp.array([8000.0, -8000.0, jnp.nan, 0.0]))
    assert batch.ok.tolist() == [True, False, False, False]
    assert np.all(np.isnan(np.asarray(batch.extension[1:])))
    np.testing.assert_allclose(batch.extension[0], tw.tweezer_response(ROD, 8000, 1.0, turns=3.0).extension, rtol=1e-12)
    # The filament: a length per base pair > 0 and a helix that rises along its axis.
    for bad in (-0.688, 0.0, np.nan):
        with pytest.raises(ValueError, match="length_per_bp must be a finite scalar > 0"):
            tw.tweezer_response(ROD, 8000, 1.0, torque=0.0, length_per_bp=bad)
    left = hr.Rod(ROD.K1, ROD.K2, ROD.K3, ROD.K13, ROD.K23, uhat=(0.0, 0.755954, -0.42952))
    with pytest.raises(ValueError, match="must rise along its axis"):
        tw.tweezer_response(left, 8000, 1.0, torque=0.0)
    with pytest.raises(ValueError, match="temperature must be a scalar"):
        tw.tweezer_response(ROD, 8000, 1.0, turns=3.0, temperature=jnp.array([300.0, 310.0]))
    with pytest.raises(ValueError, match="temperature must be finite and > 0"):
        tw.tweezer_response(ROD, 8000, 1.0, turns=3.0, temperature=-1.0)
    # Empty input: an empty response.
    for control in ({"torque": 0.0}, {"turns": jnp.ones((0,))}):
        empty = tw.tweezer_response(ROD, 8000, jnp.ones((0,)), **control)
        assert empty.extension.shape == (0,) and empty.ok.shape == (0,)


@pytest.mark.slow
def test_tweezer_fit_recovers_the_generating_parameters():
    rng = np.random.default_rng(1)
    forces = np.geomspace(0.05, 40, 60)
    turns = np.tile(np.linspace(-30, 30, 31), 3)
    hat_forces = np.repeat([0.5, 1.0, 2.0], 31)
    n_bp, sigma = 8000, 5.0
    fd = tw.tweezer_response(ROD, n_bp, forces, torque=0.0, persistence_length=48.0)
    hat = tw.tweezer_response(ROD, n_bp, hat_forces, turns=turns, persistence_length=48.0)
    extension = np.concatenate([fd.extension, hat.extension]) + sigma * rng.normal(size=forces.size + hat_forces.size)
    data = dna.TweezerData.from_arrays(
        np.concatenate([forces, hat_forces]), extension, extension_sigma=sigma,
        turns=np.concatenate([np.full(forces.size, np.nan), turns]),
        torque=np.concatenate([np.zeros(forces.size), np.full(hat_forces.size, np.nan)]), n_bp=n_bp,
    )
    fit = hr.fit_stiffness(data, uhat=ROD.uhat, init=ROD, fix={"K13": 0.0, "K1": float(ROD.K1)})
    assert fit.ok and 0.6 < fit.chi2_reduced < 1.4
    truth = {"K2": ROD.K2, "K3": ROD.K3, "K23": ROD.K23, "persistence_length": 48.0, "plectoneme_twist_persistence": 24.0}
    for name, value in truth.items():
        assert abs(float(fit.params[name]) - float(value)) < 3 * float(fit.stderr[name]), name


@pytest.mark.heavy
def test_moduli_along_the_force_range():
    forces = jnp.array([1e-3, 1.0, 10.0, 40.0])
    moduli = dna.tweezer_moduli(ROD, forces, persistence_length=A)
    S, C, g = (float(x) for x in dna.effective_moduli(ROD, ROD.uhat))
    # At vanishing force: the zero-load moduli of effective_moduli (an independent path,
    # through helix_equilibria and spring_compliance).
    np.testing.assert_allclose(
        [moduli.stretch_modulus[0], moduli.twist_modulus[0], moduli.twist_stretch_coupling[0]], [S, C, g], rtol=1e-5
    )
    # The twist modulus at constant force (a tangent of the rotation, per unit contour length)
    # is C - g^2/S of the compliance (per unit axial length) times the stretch h/h0.
    stretch = tw.tweezer_response(ROD, 1, forces, torque=0.0).intrinsic_extension / RISE
    np.testing.assert_allclose(
        moduli.twist_modulus_at_constant_force * stretch,
        moduli.twist_modulus - moduli.twist_stretch_coupling**2 / moduli.stretch_modulus, rtol=1e-9,
    )
    np.testing.assert_allclose(
        moduli.effective_twist_modulus[1:],
        tw.moroz_nelson_twist_modulus(moduli.twist_modulus_at_constant_force[1:], forces[1:], A), rtol=1e-12,
    )
    assert bool(jnp.isnan(moduli.effective_twist_modulus[0]))  # below the theory's range
    # The coupling weakens with force (the rod's nonlinearity), and the buckling torque grows.
    assert np.all(np.diff(np.asarray(moduli.twist_stretch_coupling)) > 0)
    assert np.all(np.diff(np.asarray(moduli.buckling_torque[1:])) > 0)
    # The figure: four panels with units, error bands, and tWLC's g(F) beside the rod's.
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from helixrod import plot

    stderr = jax.tree.map(lambda x: 0.01 * jnp.abs(x), moduli)
    fig = plot.plot_tweezer_moduli(moduli, stderr=stderr, twlc=(-637.0, 17.0, 30.6))
    FigureCanvasAgg(fig).draw()
    assert [ax.get_ylabel().split(" (")[-1] for ax in fig.axes] == ["pN)", "pN nm$^2$)", "pN nm)", "pN nm)"]
    assert all(ax.get_xlabel() == "force (pN)" and ax.get_xscale() == "log" for ax in fig.axes)
    rod_line, twlc_line = fig.axes[2].get_lines()
    np.testing.assert_allclose(twlc_line.get_ydata(), -637.0 + 17.0 * np.maximum(np.asarray(forces), 30.6))
    np.testing.assert_allclose(rod_line.get_ydata(), moduli.twist_stretch_coupling)
    with pytest.raises(ValueError, match="two or more forces"):
        plot.plot_tweezer_moduli(jax.tree.map(lambda x: x[:1], moduli))


@pytest.mark.heavy
def test_traced_filament_torque_and_temperature():
    """Traced values the eager checks cannot see flag their points; a free swivel's bad
    base-pair count too."""
    traced = jax.jit(lambda ell: tw.tweezer_response(ROD, 8000, jnp.array([1.0, 2.0]), torque=0.0, length_per_bp=ell).ok)
    assert traced(-0.688).tolist() == [False, False] and traced(0.688).tolist() == [True, True]
    batch = jax.vmap(lambda n: tw.tweezer_response(ROD, n, 1.0, torque=0.0))(jnp.array([8000.0, -8000.0]))
    assert batch.ok.tolist() == [True, False]
    at = lambda T: tw.tweezer_response(ROD, 8000, 1.0, turns=3.0, temperature=T)  # noqa: E731
    value, ok = jax.vmap(lambda T: (at(T).extension, at(T).ok))(jnp.array([300.0, -300.0]))
    np.testing.assert_allclose(value[0], at(300.0).extension, rtol=1e-12)
    assert ok.tolist() == [True, False]


@pytest.mark.heavy
def test_moduli_of_bad_forces_and_parameters():
    with pytest.raises(ValueError, match="force must be finite and > 0"):
        dna.tweezer_moduli(ROD, jnp.array([jnp.inf, 1.0]))
    for name in ("persistence_length", "plectoneme_twist_persistence"):
        with pytest.raises(ValueError, match=f"{name} must be finite and > 0"):
            dna.tweezer_moduli(ROD, 1.0, **{name: -10.0})
        with pytest.raises(ValueError, match=f"{name} must be a scalar or one per force"):
            dna.tweezer_moduli(ROD, jnp.array([1.0, 2.0]), **{name: jnp.ones(3)})
    with pytest.raises(ValueError, match="length_per_bp must be a finite scalar > 0"):
        dna.tweezer_moduli(ROD, 1.0, length_per_bp=0.0)
    # Traced: a bad force is NaN in every field (not another force's values), the others
    # untouched, and derivatives at the good ones finite.
    moduli = jax.vmap(lambda F: dna.tweezer_moduli(ROD, F))(jnp.array([1.0, jnp.nan, -1.0, jnp.inf]))
    alone = dna.tweezer_moduli(ROD, 1.0)
    for field in ("stretch_modulus", "twist_modulus", "twist_stretch_coupling", "twist_modulus_at_constant_force",
                  "effective_twist_modulus", "buckling_torque"):
        values = np.asarray(getattr(moduli, field))[:, 0]
        np.testing.assert_allclose(values[0], getattr(alone, field)[0], rtol=1e-12, err_msg=field)
        assert np.all(np.isnan(values[1:])), field
    slope = jax.grad(lambda A: jnp.nansum(jax.vmap(lambda F: dna.tweezer_moduli(ROD, F, persistence_length=A).effective_twist_modulus[0])(jnp.array([1.0, -1.0]))))(50.0)
    assert np.isfinite(float(slope)) and float(slope) > 0  # stiffer chains soften twist less
    # One persistence per force: each point as its own call.
    pair = dna.tweezer_moduli(ROD, jnp.array([1.0, 2.0]), persistence_length=jnp.array([40.0, 50.0]))
    for i, (F, A_i) in enumerate(((1.0, 40.0), (2.0, 50.0))):
        single = dna.tweezer_moduli(ROD, F, persistence_length=A_i)
        np.testing.assert_allclose(pair.effective_twist_modulus[i], single.effective_twist_modulus[0], rtol=1e-12)


def test_free_swivel_matches_pylake_twlc_with_constant_coupling():
    # Gross et al.'s twistable WLC with g(F) = g0 (g1 = 0): the compliance C/(SC - g^2) is the
    # rod's at zero torque, so in Odijk's range it is the same curve as the rod's.
    twlc = pytest.importorskip("lumicks.pylake.fitting.detail.model_implementation").twlc_distance
    S, C, g = (float(x) for x in dna.effective_moduli(ROD, ROD.uhat))
    forces = np.array([10.0, 20.0, 30.0])
    response = tw.tweezer_response(ROD, 8000, forces, torque=0.0, persistence_length=A)
    peer = twlc(forces, A, 8000 * RISE, S, C, g, 0.0, 100.0, KT)
    np.testing.assert_allclose(response.extension, peer, rtol=1e-3)


def test_a_realistic_1_pN_measurement_is_a_pulling_force():
    # A 5 kbp molecule measured at 1451 nm with the bead not turned: the thermal model reads
    # it as a pull of about 1 pN (the uniform-helix model alone read F = -149 pN).
    def extension(force):
        return float(tw.tweezer_response(ROD, 5000, force, torque=0.0, persistence_length=A).extension) - 1451.0

    force = brentq(extension, 0.2, 5.0, xtol=1e-10)
    assert 0.8 < force < 1.2


@pytest.mark.slow
def test_tweezer_error_bars_are_calibrated():
    # Parametric bootstrap (data redrawn around the fitted model with the data's sigmas,
    # refitted in one vmapped call): the spread of the refits is the fit's standard error,
    # and 95 % of the refits lie within its 95 % interval.
    rng = np.random.default_rng(5)
    forces = np.concatenate([np.geomspace(0.1, 30, 30), np.repeat([0.5, 1.5], 21)])
    turns = np.concatenate([np.full(30, np.nan), np.tile(np.linspace(-25, 25, 21), 2)])
    torque = np.where(np.isnan(turns), 0.0, np.nan)
    exact = np.where(
        np.isnan(turns),
        np.asarray(tw.tweezer_response(ROD, 8000, forces, torque=0.0, persistence_length=48.0).extension),
        np.asarray(tw.tweezer_response(ROD, 8000, forces, turns=np.nan_to_num(turns), persistence_length=48.0).extension),
    )
    sigma = 4.0
    data = dna.TweezerData.from_arrays(
        forces, exact + sigma * rng.normal(size=forces.size), extension_sigma=sigma, turns=turns, torque=torque, n_bp=8000
    )
    fixed = {"K1": float(ROD.K1), "K13": 0.0, "K23": float(ROD.K23)}
    fit = hr.fit_stiffness(data, uhat=ROD.uhat, init=ROD, fix=fixed)
    assert fit.ok
    boot = hr.bootstrap(data, fit, 200, jax.random.key(2), kind="parametric")
    assert float(jnp.mean(boot.ok)) > 0.95
    for name in fit.names:
        samples = np.asarray(boot.samples[name])
        samples = samples[np.isfinite(samples)]
        spread = np.std(samples, ddof=1)
        assert 0.75 < spread / float(fit.stderr[name]) < 1.3, name
        centre = float(fit.params[name])
        covered = np.mean(np.abs(samples - centre) <= 1.96 * float(fit.stderr[name]))
        assert 0.9 < covered < 0.99, (name, covered)


@pytest.mark.heavy
def test_the_static_paths_agree_with_the_general_one():
    """Free swivels (one solve), torque-controlled points (no iteration) and the traced
    general path (the chord iteration) give the same response and derivatives."""
    ell, rise = tw.filament_and_rise(ROD)
    kT = jnp.asarray(KT)

    def point(force, control, controlled):
        out = tw.response_point(ROD, ell, rise, force, control, controlled, jnp.asarray(48.0), jnp.asarray(24.0), kT)
        return jnp.stack([out[0], out[1], out[2], *out[6]])

    def with_derivative(f, force):
        return f(force), jax.jacfwd(f)(force)

    @jax.jit
    def general(force, control):  # the control and its kind traced
        return with_derivative(lambda F: point(F, control, jnp.asarray(True)), force)

    @functools.partial(jax.jit, static_argnums=1)
    def static(force, control):  # a Python number and True
        return with_derivative(lambda F: point(F, control, True), force)

    for torque in (0.0, 5.0):
        general_value, d_general = general(jnp.asarray(2.0), jnp.asarray(torque))
        static_value, d_static = static(jnp.asarray(2.0), torque)
        np.testing.assert_allclose(static_value, general_value, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(d_static, d_general, rtol=1e-9, atol=1e-12)
    # tweezer_response takes the free-swivel path for concrete zero torques, the general one
    # under jit.
    forces = jnp.geomspace(0.1, 40.0, 7)
    eager = tw.tweezer_response(ROD, 8000, forces, torque=0.0)
    traced = jax.jit(lambda f: tw.tweezer_response(ROD, 8000, f, torque=jnp.zeros_like(f)))(forces)
    np.testing.assert_allclose(eager.extension, traced.extension, rtol=1e-12)
    np.testing.assert_allclose(eager.twist_modulus, traced.twist_modulus, rtol=1e-12)


def test_errors_in_variables_sigma_is_the_slopes_in_quadrature():
    """The effective extension sigma of a tweezer model with force and turns errors (the
    slopes are tangents of the model's own evaluation): sqrt(s_e^2 + (dz/dF s_F)^2 +
    (dz/dn s_n)^2) with the slopes of `dna.tweezer_response` by central differences; a
    torque-controlled point (zero torque: a force-extension point) takes no turns term.
    Expected to 1e-7 relative (the differences' truncation)."""
    from helixrod._fit import forward_model

    force = np.array([0.8, 1.0, 1.5, 3.0, 10.0])
    turns = np.array([-5.0, 2.0, 8.0, np.nan, np.nan])
    torque = np.array([np.nan, np.nan, np.nan, 0.0, 0.0])
    force_sigma, turns_sigma, n_bp = np.array([0.02, 0.03, 0.05, 0.1, 0.2]), 0.1, 8000.0
    data = dna.TweezerData.from_arrays(
        force, np.full(5, 2000.0), extension_sigma=3.0, turns=turns, torque=torque, force_sigma=force_sigma,
        turns_sigma=turns_sigma, n_bp=n_bp,
    )
    model = forward_model(data)
    assert model.errors_in_variables
    _, predicted = eqx.filter_jit(lambda m, rod, extra: m.residuals(rod, extra))(model, ROD, jnp.array([48.0, 24.0, 0.0]))

    def extension(F, control, by_torque):
        control = {"torque": control} if by_torque else {"turns": control}
        return float(tw.tweezer_response(ROD, n_bp, F, persistence_length=48.0, **control).extension)

    for i in range(5):
        by_torque = bool(np.isfinite(torque[i]))
        control = torque[i] if by_torque else turns[i]
        h_force, h_turns = 1e-4 * force[i], 1e-3
        slope_force = (extension(force[i] + h_force, control, by_torque) - extension(force[i] - h_force, control, by_torque)) / (2 * h_force)
        variance = 9.0 + (slope_force * force_sigma[i]) ** 2
        if not by_torque:
            slope_turns = (extension(force[i], control + h_turns, False) - extension(force[i], control - h_turns, False)) / (2 * h_turns)
            variance += (slope_turns * turns_sigma) ** 2
        assert variance > 9.0 * (1 + 1e-3)  # the slopes matter here
        np.testing.assert_allclose(predicted["extension_sigma"][i], np.sqrt(variance), rtol=1e-7)


def _mixed_data_with_control_sigmas(n_free):
    """`n_free` free-swivel points and six turned points at 1 pN on two molecules, two of
    them with a measured torque, with force and turns sigmas (errors in variables)."""
    forces = np.concatenate([np.geomspace(0.3, 20.0, n_free), np.full(6, 1.0)])
    turns = np.concatenate([np.full(n_free, np.nan), np.linspace(-20.0, 20.0, 6)])
    torque = np.where(np.isnan(turns), 0.0, np.nan)
    extension = np.where(
        np.isnan(turns),
        np.asarray(tw.tweezer_response(ROD, 8000, forces, torque=0.0).extension),
        np.asarray(tw.tweezer_response(ROD, 8000, forces, turns=np.nan_to_num(turns)).extension),
    ) + 3.0 * np.random.default_rng(3).normal(size=forces.size)
    measured = np.full(forces.size, np.nan)
    measured[[n_free + 1, n_free + 4]] = (-8.0, 8.0)
    return dna.TweezerData.from_arrays(
        forces, extension, extension_sigma=4.0, turns=turns, torque=torque, force_sigma=0.03 * forces,
        turns_sigma=0.1, measured_torque=measured, measured_torque_sigma=2.0,
        molecule=[0] * n_free + [0, 1] * 3, n_bp=[8000, 8000],
    )


@pytest.mark.heavy
def test_errors_in_variables_jacobian_in_one_forward_pass_is_the_nested_one():
    """The tweezer model's Jacobian takes the slopes of errors in variables as columns of its
    own forward pass; differentiating its residuals, whose slopes are a forward pass of
    their own, gives the same Jacobian, residuals and sigmas (force and turns sigmas, free
    and turned points, measured torques)."""
    from helixrod._fit import forward_model
    from helixrod._fit._models import AbstractForwardModel
    from helixrod._fit._parameters import Parameterisation

    model = forward_model(_mixed_data_with_control_sigmas(5), fit_offsets=True)
    assert model.errors_in_variables and model.control_kind == "mixed"
    fixed = {"K1": float(ROD.K1), "K13": 0.0, **{f"uhat{i + 1}": float(ROD.uhat[i]) for i in range(3)}}
    extra = {"persistence_length": 48.0, "plectoneme_twist_persistence": 24.0, "offset_0": 1.0, "offset_1": -1.0}
    param = Parameterisation(fixed, float(ROD.K2), 1.0, model.parameters, extra)
    q = jnp.array([float(ROD.K2), float(ROD.K3), float(ROD.K23), 48.0, 24.0, 1.0, -1.0])
    J, (r, predicted) = jax.jit(lambda q: model.jacobian_and_predictions(q, param))(q)
    J0, (r0, predicted0) = jax.jit(lambda q: AbstractForwardModel.jacobian_and_predictions(model, q, param))(q)
    assert J.shape == (11 + 2, 7)
    np.testing.assert_allclose(r, r0, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(J, J0, rtol=1e-10, atol=1e-12 * float(jnp.max(jnp.abs(J0))))
    for name in ("extension_sigma", "residual_sigma", "extension", "torque"):
        np.testing.assert_allclose(predicted[name], predicted0[name], rtol=1e-12, err_msg=name)
    # The sigmas moved: the slopes weigh in (force sigmas everywhere, turns sigmas on turned points).
    assert np.all(np.asarray(predicted["extension_sigma"]) > 4.0)


@pytest.mark.parametrize("exported", [False, True], ids=["plain", "trace cache"])
def test_a_first_tweezer_fit_compiles_its_programs_side_by_side_once(exported, compilations, monkeypatch, request):
    """A stepwise fit's first call of its signature compiles the model's program and the
    solver's start and step programs each on a thread of its own, from the specs of the
    values they will be called with: the calls find those compilations (a spec that missed,
    e.g. placed otherwise, would compile the program twice).  Plain programs, and the
    trace cache's exported ones (whose results are committed to a device).  Free-swivel
    curves of their own sizes (no other test fits 9 or 10 points), force sigmas: errors in
    variables."""
    from helixrod import _compile

    if exported:
        request.getfixturevalue("exported_programs")
    monkeypatch.setattr(_compile, "cores", lambda: 2)  # as on a machine of several cores
    n = 10 if exported else 9
    forces = np.geomspace(0.3, 20.0, n)
    extension = np.asarray(tw.tweezer_response(ROD, 8000, forces, torque=0.0, persistence_length=48.0).extension)
    data = dna.TweezerData.from_arrays(
        forces, extension + 2.0 * np.random.default_rng(4).normal(size=n), extension_sigma=2.0, torque=0.0,
        force_sigma=0.02 * forces, n_bp=8000,
    )
    fix = {"K1": float(ROD.K1), "K13": 0.0, "K23": float(ROD.K23), "K3": float(ROD.K3)}
    fit = hr.fit_stiffness(data, uhat=ROD.uhat, init=ROD, fix=fix)
    names = ("_jacobian_and_predictions_of", "_start", "_step")
    ours = sorted((thread, name) for thread, name in compilations if name in names)
    assert ours == [(f"helixrod-compile-{name}", name) for name in names], ours
    assert fit.ok and abs(float(fit.params["persistence_length"]) - 48.0) < 3 * float(fit.stderr["persistence_length"])


@pytest.mark.heavy
def test_a_fit_notes_the_points_its_model_flags():
    """Points twisted at forces below the twist-fluctuation theory's range enter a fit with
    the values the model computes there; the report says which."""
    forces = np.array([0.03, 0.05, 0.5, 1.0, 2.0, 4.0])
    turns = np.array([5.0, 5.0, 5.0, np.nan, np.nan, np.nan])
    free = tw.tweezer_response(ROD, 8000, forces, torque=0.0)
    data = dna.TweezerData.from_arrays(
        forces, np.asarray(free.extension), extension_sigma=5.0, turns=turns, torque=np.where(np.isnan(turns), 0.0, np.nan), n_bp=8000
    )
    fixed = {name: float(getattr(ROD, name)) for name in ("K1", "K2", "K3", "K13", "K23")}
    fit = hr.fit_stiffness(data, uhat=ROD.uhat, init=ROD, fix={**fixed, "persistence_length": 50.0, "plectoneme_twist_persistence": 24.0}, fit_offsets=True)
    assert fit.predicted["ok"].tolist() == [False, False, True, True, True, True]
    assert "2 of 6 data points are flagged by the model at the fit" in fit.summary() and "points [0, 1]" in fit.summary()
