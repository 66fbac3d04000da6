"""Regenerate src/helixrod/data/dna_tweezer_curves.csv: synthetic tweezer curves of DNA.

SYNTHETIC data, written in the form instruments give (`dna.TweezerData`, CSV with a units
line) for three molecules of 7100, 8000 and 8900 bp:

- magnetic-tweezer hat curves (extension against turns) at 0.3, 0.7, 1.5 and 3 pN, turns
  -40..40 in steps of 2;
- a magnetic-torque-tweezer set at 2 pN, turns -40..40 in steps of 2, with the torque
  measured as well (noise 2 pN nm);
- an optical-tweezer force-extension curve with a free swivel (torque 0), 41 forces
  log-spaced from 0.05 to 40 pN.

The generating model is `dna.tweezer_response` (the rod's own nonlinear helix, worm-like-chain
bending fluctuations, Moroz-Nelson twist softening, Marko's plectonemes; `helixrod._tweezer`)
with the rod of `dna.load_tweezer_example()` (its zero-load S = 1100 pN, C = 410 pN nm^2,
g = -90 pN nm are the published values cited in that file), bending persistence 48 nm and
plectoneme twist persistence 24 nm, and one bead-height offset per molecule added to all its
extensions.  Noise, per point, independent:

- extension: sigma_h^2 = sigma_track^2 + 2 kT gamma (dh/dF)^2 / T_avg -- the mean over T_avg of
  the Brownian motion of a bead (drag gamma = 6 pi eta R) held by the molecule, whose spring
  constant is the inverse compliance dF/dh of the molecule at that point (an Ornstein-Uhlenbeck
  process of variance kT/k and correlation time gamma/k: the variance of its mean over
  T_avg >> gamma/k is 2 kT gamma / (k^2 T_avg)).  It grows as the force falls (dh/dF ~ L/(4
  sqrt(A F^3/kT)) on the worm-like chain) and where plectonemes form, plus a tracking floor;
  dh/dF by central differences of the generating model at the recorded force.
- force: the recorded force is the set value; the true one is it times (1 + 0.02 N(0, 1))
  (force calibration, 2 %); `force_sigma` = 0.02 F is in the file, so a fit can use errors in
  variables.  Turns are exact (no `turns_sigma`).
- measured torque: the model torque at the true force plus 2 pN nm N(0, 1).

Run:  python examples/make_tweezer_curves_example.py [--out PATH]
"""

from __future__ import annotations

import argparse
import pathlib

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import numpy as np

from helixrod import dna

MOLECULES = ("mol1", "mol2", "mol3")
N_BP = (7100.0, 8000.0, 8900.0)
OFFSETS = (3.0, -2.5, 4.0)  # nm, bead-height offset of each molecule
PERSISTENCE_LENGTH = 48.0  # nm, bending persistence
PLECTONEME_TWIST = 24.0  # nm (dna.PLECTONEME_TWIST_PERSISTENCE, Marko 2007)
HAT_FORCES = (0.3, 0.7, 1.5, 3.0)  # pN
TORQUE_FORCE = 2.0  # pN, the magnetic-torque-tweezer set
TURNS = np.linspace(-40.0, 40.0, 41)
FD_FORCES = np.geomspace(0.05, 40.0, 41)  # pN, optical tweezers, torque 0
FORCE_CALIBRATION = 0.02  # relative sigma of every recorded force
TORQUE_SIGMA = 2.0  # pN nm, measured torque
VISCOSITY = 0.89e-9  # pN s / nm^2 (0.89 mPa s: water at 25 C)
# Instruments: bead radius (nm), averaging time per point (s), tracking floor (nm).
MAGNETIC = {"radius": 500.0, "average": 10.0, "floor": 1.0}
OPTICAL = {"radius": 500.0, "average": 2.0, "floor": 0.5}
FD_STEP = 1e-4  # relative force step of the central difference dh/dF
SEED = 20070821

SOURCES = {
    "rod_source": "the rod of dna.load_tweezer_example() (data/dna_tweezer_example.csv, examples/make_tweezer_example.py): "
    "K1 = K2, K13 = 0, bend-twist coupling K23, intrinsic twist at the B-DNA backbone helix "
    "(dna.helix_from_bdna: rise 0.34 nm, 10.5 bp/turn, radius 1 nm), whose zero-load moduli are:",
    "S_source": "1100 pN, stretch modulus as used by Gore et al. Nature 442, 836 (2006)",
    "C_source": "410 pN nm^2 = 100 nm x kT, Bryant et al. Nature 424, 338 (2003) (C(0) = 4.1e2 pN nm^2)",
    "g_source": "-90 pN nm, Gore et al. Nature 442, 836 (2006) (g = -90 +- 20 pN nm)",
    "persistence_length_source": "48 nm: a typical value of the bending persistence of dsDNA near 0.1-0.15 M "
    "monovalent salt (not taken from a particular measurement; lumicks pylake's default is 50 nm)",
    "plectoneme_twist_persistence_source": "24 nm, the plectoneme twist persistence Marko (Phys. Rev. E 76, 021926 "
    "(2007)) uses for ~0.15 M monovalent salt (dna.PLECTONEME_TWIST_PERSISTENCE)",
    "offsets_source": "bead-height offsets of a few nm (bead size and attachment), chosen; one per molecule, added to "
    "every extension of that molecule",
    "model": "dna.tweezer_response: the rod's own helix under (F, torque) + worm-like chain (Bouchiat et al. 1999) + "
    "Moroz-Nelson twist softening + Marko (2007) two-phase plectonemes; temperature 298.15 K",
    "not_modelled": "melting of underwound DNA above ~0.5 pN (negative turns buckle like positive ones), plectoneme "
    "end loops and multiple plectonemes, the bead's contact with the surface, drift, a calibration error common "
    "to all points of a bead or magnet height; the same three molecules are shown in both instruments",
}


def design():
    """The points: per molecule the four hats, the torque set, the force-extension curve, as
    blocks of 41 points `(molecule, force, turns or None, torque or None, instrument)`."""
    blocks = []
    for m in range(len(MOLECULES)):
        for force in HAT_FORCES:
            blocks.append((m, np.full(TURNS.size, force), TURNS, None, "magnetic"))
        blocks.append((m, np.full(TURNS.size, TORQUE_FORCE), TURNS, None, "torque"))
        blocks.append((m, FD_FORCES, None, np.zeros(FD_FORCES.size), "optical"))
    return blocks


def block_response(rod, n_bp, force, turns, torque, persistence_length=PERSISTENCE_LENGTH, plectoneme_twist=PLECTONEME_TWIST):
    """`dna.tweezer_response` of one block (every block has 41 points: one compilation)."""
    return dna.tweezer_response(
        rod, n_bp, jnp.asarray(force), turns=None if turns is None else jnp.asarray(turns),
        torque=None if torque is None else jnp.asarray(torque), persistence_length=persistence_length,
        plectoneme_twist_persistence=plectoneme_twist, throw=True,
    )


def block_compliance(rod, n_bp, force, turns, torque, **kw):
    """dh/dF (nm/pN) of a block at its forces, by central differences of the model."""
    up = block_response(rod, n_bp, force * (1 + FD_STEP), turns, torque, **kw).extension
    down = block_response(rod, n_bp, force * (1 - FD_STEP), turns, torque, **kw).extension
    return np.asarray(up - down) / (2 * FD_STEP * force)


def brownian_sigma(compliance, instrument, kT):
    """Extension sigma (nm) of the mean over the averaging time: sqrt(floor^2 + 2 kT gamma
    (dh/dF)^2 / T_avg), gamma = 6 pi eta R."""
    p = OPTICAL if instrument == "optical" else MAGNETIC
    gamma = 6 * np.pi * VISCOSITY * p["radius"]
    return np.sqrt(p["floor"] ** 2 + 2 * kT * gamma * np.asarray(compliance) ** 2 / p["average"])


def generate(rod=None):
    """The synthetic `TweezerData` and its comment text (deterministic)."""
    rod = dna.load_tweezer_example().rod if rod is None else rod
    kT = float(dna.kT())
    rng = np.random.default_rng(SEED)
    columns = {k: [] for k in ("force", "extension", "turns", "torque", "extension_sigma", "force_sigma",
                               "measured_torque", "measured_torque_sigma", "molecule")}
    for m, force, turns, torque, instrument in design():
        n = force.size
        true_force = force * (1 + FORCE_CALIBRATION * rng.standard_normal(n))
        ext_noise, torque_noise = rng.standard_normal(n), rng.standard_normal(n)
        true = block_response(rod, N_BP[m], true_force, turns, torque)
        sigma = brownian_sigma(block_compliance(rod, N_BP[m], force, turns, torque), instrument, kT)
        columns["force"].append(force)
        columns["extension"].append(np.asarray(true.extension) + OFFSETS[m] + sigma * ext_noise)
        columns["turns"].append(np.full(n, np.nan) if turns is None else turns)
        columns["torque"].append(np.full(n, np.nan) if torque is None else torque)
        columns["extension_sigma"].append(sigma)
        columns["force_sigma"].append(FORCE_CALIBRATION * force)
        measured = instrument == "torque"
        columns["measured_torque"].append(np.asarray(true.torque) + TORQUE_SIGMA * torque_noise if measured else np.full(n, np.nan))
        columns["measured_torque_sigma"].append(np.full(n, TORQUE_SIGMA if measured else np.nan))
        columns["molecule"] += [MOLECULES[m]] * n
    arrays = {k: (v if k == "molecule" else np.concatenate(v)) for k, v in columns.items()}
    data = dna.TweezerData.from_arrays(
        arrays.pop("force"), arrays.pop("extension"), **arrays, n_bp=dict(zip(MOLECULES, N_BP)),
        temperature=dna.ROOM_TEMPERATURE,
    )
    return data, comment_text(rod)


def parameters(rod):
    """The generating parameters by the names of the tweezer fit (`fit_stiffness` with
    `fit_offsets=True`) and the rod's intrinsic twist."""
    values = {n: float(getattr(rod, n)) for n in ("K1", "K2", "K3", "K13", "K23")}
    values.update({f"uhat{i + 1}": float(rod.uhat[i]) for i in range(3)})
    values["persistence_length"] = PERSISTENCE_LENGTH
    values["plectoneme_twist_persistence"] = PLECTONEME_TWIST
    values.update({f"offset_{name}": off for name, off in zip(MOLECULES, OFFSETS)})
    return values


def comment_text(rod):
    S, C, g = (float(x) for x in dna.load_tweezer_example().moduli)  # effective_moduli of that rod, stored there
    params = parameters(rod)
    mt, ot = MAGNETIC, OPTICAL
    lines = {
        "title": "synthetic DNA tweezer curves: magnetic-tweezer hats, magnetic-torque-tweezer torques, optical-tweezer force-extension (helixrod)",
        "SYNTHETIC": f"not measured data; generated by examples/make_tweezer_curves_example.py (numpy seed {SEED})",
        "molecules": ", ".join(f"{n} {b:g} bp" for n, b in zip(MOLECULES, N_BP)),
        "hats": f"magnetic tweezers, forces {', '.join(f'{f:g}' for f in HAT_FORCES)} pN, turns -40..40 step 2",
        "torque_set": f"magnetic torque tweezers, force {TORQUE_FORCE:g} pN, turns -40..40 step 2, torque measured",
        "force_extension": "optical tweezers, free swivel (torque 0), 41 forces log-spaced 0.05-40 pN",
        **SOURCES,
        "moduli": f"S = {S!r} pN, C = {C!r} pN nm^2, g = {g!r} pN nm (dna.effective_moduli of the rod at zero load, "
        "as stored in data/dna_tweezer_example.csv)",
        "extension_noise": (
            "Gaussian, sigma_h = sqrt(floor^2 + 2 kT gamma (dh/dF)^2 / T_avg), gamma = 6 pi eta R: the mean over T_avg "
            "of the bead's Brownian motion on the molecule's spring dF/dh; dh/dF by central differences of the model "
            f"(relative step {FD_STEP:g}) at the recorded force; eta = {VISCOSITY * 1e9:g} mPa s (water at 25 C); "
            f"magnetic: R = {mt['radius']:g} nm, T_avg = {mt['average']:g} s, floor {mt['floor']:g} nm; "
            f"optical: R = {ot['radius']:g} nm, T_avg = {ot['average']:g} s, floor {ot['floor']:g} nm; the sigma is the "
            "extension_sigma column"
        ),
        "force_noise": (
            f"true force = recorded force x (1 + {FORCE_CALIBRATION:g} N(0,1)), independent per point (force "
            "calibration); force_sigma column = that sigma"
        ),
        "turns_noise": "none (turns exact)",
        "torque_noise": f"Gaussian, sigma {TORQUE_SIGMA:g} pN nm, on the model torque at the true force",
        "parameters": " ".join(params),
        **{k: repr(v) for k, v in params.items()},
    }
    return "\n".join(f"{k}: {v}" for k, v in lines.items())


def main(out: pathlib.Path):
    data, comment = generate()
    text = data.to_csv(out, comment=comment)
    print(f"wrote {data.n_points} points of {data.n_molecules} molecules to {out} ({len(text)} characters)")
    sigma = np.asarray(data.extension_sigma)
    print(f"extension sigma {sigma.min():.2f}..{sigma.max():.2f} nm")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = pathlib.Path(__file__).resolve().parents[1] / "src" / "helixrod" / "data" / "dna_tweezer_curves.csv"
    parser.add_argument("--out", type=pathlib.Path, default=default)
    main(parser.parse_args().out)
