"""Regenerate src/helixrod/data/dna_tweezer_example.csv: a synthetic DNA tweezer dataset.

The model: the backbone of B-DNA as a uniform elastic helix (an inextensible Kirchhoff rod)
whose unstressed shape is the B-DNA helix of `dna.helix_from_bdna()` (rise 0.34 nm, 10.5 bp
per turn, radius 1 nm), with register phi = 0, i.e. uhat = (0, kappa0, tau0).  With
K13 = 0 and uhat1 = 0 the register stays at phi = 0 under any axial wrench, so the response
depends on K2 (bending about the binormal), K3 (twist) and K23 only, through the 2x2 energy
method (Castigliano) for the open-coiled spring: with N = [[r c, s], [-r s, c]] (s, c = sin,
cos of the pitch angle) mapping (F, M) to the (twist, binormal bending) moments,

    [[S, g], [g, C]] = s N^-1 [[K3, K23], [K23, K2]] N^-T     (per unit axial length)

so K_eff = N [[S, g], [g, C]] N^T / s gives the rod that has any prescribed (S, C, g) at zero
load.  The script checks the result against `dna.effective_moduli` (autodiff through
`helix_equilibria`), then solves every (F, M) of the grid for its helix with
`helices_under_load`, and adds Gaussian noise to the per-bp extension and rotation.

Run:  python examples/make_tweezer_example.py [--out PATH]
"""

from __future__ import annotations

import argparse
import pathlib

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import helixrod as hr  # noqa: E402
from helixrod import dna  # noqa: E402

# Published linear moduli of B-DNA used as targets (each with its source).
STRETCH_MODULUS = 1100.0  # pN; Gore et al. Nature 442, 836 (2006) use S ~ 1100 pN
TWIST_MODULUS = 410.0  # pN nm^2; Bryant et al. Nature 424, 338 (2003): C = 4.1e2 pN nm^2
TWIST_STRETCH = -90.0  # pN nm; Gore et al. Nature 442, 836 (2006): g = -90 +- 20 pN nm
BENDING_PERSISTENCE = 50.0  # nm; e.g. Bustamante et al. Science 265, 1599 (1994)

FORCES = np.geomspace(0.5, 40.0, 13)  # pN
TORQUES = np.array([-10.0, -5.0, 0.0, 5.0, 10.0, 15.0])  # pN nm
EXTENSION_SIGMA = 1e-4  # nm per bp (0.5 nm on a 5 kbp molecule)
ROTATION_SIGMA = 2e-5  # rad per bp (0.1 rad = 0.016 turns on a 5 kbp molecule)
SEED = 20060727


def generating_rod():
    kappa0, tau0, ell = dna.helix_from_bdna()
    norm_u = jnp.hypot(kappa0, tau0)
    r = kappa0 / norm_u**2
    s, c = tau0 / norm_u, kappa0 / norm_u
    N = jnp.array([[r * c, s], [-r * s, c]])
    moduli = jnp.array([[STRETCH_MODULUS, TWIST_STRETCH], [TWIST_STRETCH, TWIST_MODULUS]])
    K_eff = N @ moduli @ N.T / s  # (twist, binormal bending)
    K3, K23, K2 = K_eff[0, 0], K_eff[0, 1], K_eff[1, 1]
    rod = hr.Rod(K2, K2, K3, 0.0, K23, jnp.stack([0.0, kappa0, tau0]))
    return rod, ell


def solve_helices(rod):
    kappa0, tau0 = float(rod.uhat[1]), float(rod.uhat[2])
    F, M = np.meshgrid(FORCES, TORQUES, indexing="ij")
    F, M = F.ravel(), M.ravel()

    def one(f, m):
        sol = hr.helices_under_load(
            rod, f, m, kappa_max=1.3 * kappa0, tau_range=(0.7 * tau0, 1.4 * tau0), grid=24, max_solutions=4
        )
        # The branch through the unstressed helix: slot 0 (stable), nearest to uhat.
        dist = jnp.where(sol.valid & (sol.slot == 0), jnp.hypot(sol.kappa - kappa0, sol.tau - tau0), jnp.inf)
        i = jnp.argmin(dist)
        return sol.kappa[i], sol.tau[i], jnp.isfinite(dist[i])

    kappa, tau, found = jax.jit(jax.vmap(one))(jnp.asarray(F), jnp.asarray(M))
    if not bool(jnp.all(found)):
        raise RuntimeError("no helix found for some loads")
    return F, M, np.asarray(kappa), np.asarray(tau)


def main(out: pathlib.Path):
    rod, ell = generating_rod()
    S, C, g = (float(x) for x in dna.effective_moduli(rod, rod.uhat))
    print(f"generating rod: K1=K2={float(rod.K2):.3f}, K3={float(rod.K3):.3f}, K23={float(rod.K23):.3f} pN nm^2")
    print(f"zero-load moduli (effective_moduli): S={S:.6f} pN, C={C:.6f} pN nm^2, g={g:.6f} pN nm")
    for name, got, want in (("S", S, STRETCH_MODULUS), ("C", C, TWIST_MODULUS), ("g", g, TWIST_STRETCH)):
        assert abs(got - want) <= 1e-9 * abs(want), (name, got, want)

    F, M, kappa, tau = solve_helices(rod)
    eq = hr.helix_equilibria(rod, kappa, tau)
    assert np.allclose(np.asarray(eq.force[:, 0]), F, rtol=1e-9, atol=1e-9)
    assert np.allclose(np.asarray(eq.moment[:, 0]), M, rtol=1e-9, atol=1e-9)
    ext, rot = (np.asarray(x) for x in dna.tweezer_from_helix(kappa, tau, length_per_bp=ell))

    rng = np.random.default_rng(SEED)
    ext_noisy = ext + EXTENSION_SIGMA * rng.standard_normal(ext.shape)
    rot_noisy = rot + ROTATION_SIGMA * rng.standard_normal(rot.shape)
    k_obs, t_obs = (np.asarray(x) for x in dna.helix_from_tweezer(ext_noisy, rot_noisy, length_per_bp=ell))

    # Linear propagation of the observable noise to (kappa, tau).
    def to_helix(x):
        return jnp.stack(dna.helix_from_observables(x[0], x[1], ell))

    J = jax.vmap(jax.jacfwd(to_helix))(jnp.stack([ext_noisy, rot_noisy], -1))
    cov_obs = jnp.diag(jnp.array([EXTENSION_SIGMA**2, ROTATION_SIGMA**2]))
    cov = np.asarray(J @ cov_obs @ jnp.swapaxes(J, -1, -2))
    k_sig, t_sig = np.sqrt(cov[:, 0, 0]), np.sqrt(cov[:, 1, 1])
    corr = cov[:, 0, 1] / (k_sig * t_sig)

    # Twist-stretch coupling along the torque-free path (what Gore et al. measured).
    free = M == 0
    u_free = np.asarray(eq.u[free, 0])
    S_f, C_f, g_f = (np.asarray(x) for x in dna.effective_moduli(rod, u_free))
    print("force [pN]   S [pN]    C [pN nm^2]   g [pN nm]   (torque-free path)")
    for f, a, b, c in zip(F[free], S_f, C_f, g_f):
        print(f"{f:9.3f} {a:9.2f} {b:12.2f} {c:11.3f}")

    meta = {
        "title": "synthetic DNA magnetic/optical tweezer data from a uniform-helix rod model (helixrod)",
        "SYNTHETIC": "not measured data; generated by examples/make_tweezer_example.py",
        "units": "force pN; moment pN nm; extension_per_bp nm; rotation_per_bp rad; kappa, tau 1/nm",
        "model": "backbone of B-DNA = uniform Kirchhoff helix; rise 0.34 nm, 10.5 bp/turn, radius 1 nm (helix_from_bdna)",
        "rotation": "end rotation per bp = frame rotation about the axis, l*|u|; extension per bp = l*tau/|u|",
        "S_source": "1100 pN, stretch modulus as used by Gore et al. Nature 442, 836 (2006)",
        "C_source": "410 pN nm^2 = 100 nm x kT, Bryant et al. Nature 424, 338 (2003) (C(0) = 4.1e2 pN nm^2)",
        "g_source": "-90 pN nm, Gore et al. Nature 442, 836 (2006) (g = -90 +- 20 pN nm)",
        "not_modelled": (
            "bending persistence ~50 nm (Bustamante et al. Science 265, 1599 (1994)): a uniform helix has "
            "no axis bending, so thermal (entropic, worm-like-chain) elasticity below ~5 pN, plectonemic "
            "buckling at positive torque and melting at negative torque are absent; only the enthalpic "
            "response of an unbuckled molecule is represented"
        ),
        "noise": f"Gaussian, sigma {EXTENSION_SIGMA} nm/bp on extension and {ROTATION_SIGMA} rad/bp on rotation; "
        f"force and torque exact; seed {SEED}",
        "kappa_tau": "from the noisy observables by dna.helix_from_tweezer; sigmas and correlation by linear propagation",
        "K1": repr(float(rod.K1)),
        "K2": repr(float(rod.K2)),
        "K3": repr(float(rod.K3)),
        "K13": repr(float(rod.K13)),
        "K23": repr(float(rod.K23)),
        "uhat1": repr(float(rod.uhat[0])),
        "uhat2": repr(float(rod.uhat[1])),
        "uhat3": repr(float(rod.uhat[2])),
        "length_per_bp": repr(float(ell)),
        "S": repr(S),
        "C": repr(C),
        "g": repr(g),
    }
    columns = {
        "force": F,
        "moment": M,
        "extension_per_bp": ext_noisy,
        "rotation_per_bp": rot_noisy,
        "extension_sigma": np.full_like(F, EXTENSION_SIGMA),
        "rotation_sigma": np.full_like(F, ROTATION_SIGMA),
        "kappa": k_obs,
        "tau": t_obs,
        "kappa_sigma": k_sig,
        "tau_sigma": t_sig,
        "kappa_tau_correlation": corr,
    }
    lines = [f"# {k}: {v}" for k, v in meta.items()]
    lines.append(",".join(columns))
    table = np.stack(list(columns.values()), axis=1)
    lines += [",".join(repr(float(x)) for x in row) for row in table]
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {len(F)} points to {out}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = pathlib.Path(__file__).resolve().parents[1] / "src" / "helixrod" / "data" / "dna_tweezer_example.csv"
    parser.add_argument("--out", type=pathlib.Path, default=default)
    main(parser.parse_args().out)
