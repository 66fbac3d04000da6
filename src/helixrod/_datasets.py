"""Bundled example datasets (synthetic), loaded with one call.

Files live in `helixrod/data/` as CSV: `#` lines carry the provenance and the generating
parameters (`# key: value`), then one header line of column names.  Each file is written by
a script in `examples/` that anyone can rerun to regenerate it bit for bit.
"""

from __future__ import annotations

import importlib.resources
import io

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._fit import HelixData, TweezerData
from ._rod import Rod


def _read(name: str) -> tuple[dict[str, str], dict[str, np.ndarray]]:
    text = importlib.resources.files("helixrod").joinpath("data", name).read_text()
    meta = {}
    for line in text.splitlines():
        if line.startswith("# ") and ": " in line:
            key, value = line[2:].split(": ", 1)
            meta[key.strip()] = value.strip()
    rows = [line for line in text.splitlines() if line.strip() and not line.startswith("#")]
    names = rows[0].split(",")
    table = np.loadtxt(io.StringIO("\n".join(rows[1:])), delimiter=",", ndmin=2)
    return meta, {name: table[:, i] for i, name in enumerate(names)}


def _comments(name: str) -> dict[str, str]:
    """The `# key: value` comment lines of a bundled file, by key."""
    meta = {}
    for line in importlib.resources.files("helixrod").joinpath("data", name).read_text().splitlines():
        if line.startswith("# ") and ": " in line:
            key, value = line[2:].split(": ", 1)
            meta[key.strip()] = value.strip()
    return meta


def _floats(meta, *keys):
    return tuple(float(meta[k]) for k in keys)


class TweezerExample(eqx.Module):
    """A synthetic magnetic/optical-tweezer dataset of DNA (see `load_tweezer_example`).

    Per point (shape `(n,)`): applied `force` (pN) and `moment` (torque, pN nm), measured
    `extension` and `rotation` per base pair (nm, rad) with their standard deviations
    `extension_sigma`, `rotation_sigma`; the backbone-helix `kappa`, `tau` (1/nm) computed from
    the noisy observables by `dna.helix_from_tweezer`, with linearly propagated
    `kappa_sigma`, `tau_sigma` and their correlation `kappa_tau_correlation`.
    `rod` is the generating rod (pN nm^2, 1/nm), `length_per_bp` the backbone filament
    length per base pair (nm), `moduli` the generating rod's `(S, C, g)` at zero load,
    `provenance` the file's header text.
    """

    force: Float[Array, " n"]
    moment: Float[Array, " n"]
    extension: Float[Array, " n"]
    rotation: Float[Array, " n"]
    extension_sigma: Float[Array, " n"]
    rotation_sigma: Float[Array, " n"]
    kappa: Float[Array, " n"]
    tau: Float[Array, " n"]
    kappa_sigma: Float[Array, " n"]
    tau_sigma: Float[Array, " n"]
    kappa_tau_correlation: Float[Array, " n"]
    rod: Rod
    length_per_bp: Float[Array, ""]
    moduli: tuple[Float[Array, ""], Float[Array, ""], Float[Array, ""]]
    provenance: str = eqx.field(static=True)

    def helix_data(self, force_sigma: float = 1e-3, moment_sigma: float = 1e-2):
        """The data as `HelixData` for `fit_stiffness(..., errors_in_variables=True)`:
        applied force (pN) and torque (pN nm) at the observed helices, with the sigmas and
        the correlation of `kappa`, `tau` propagated from the observables' noise.  In this
        synthetic set the force and torque are exact; their (small) sigmas here only keep
        the weights finite, so that the fit's errors come from the observables."""
        return HelixData(
            self.force,
            self.moment,
            self.kappa,
            self.tau,
            force_sigma,
            moment_sigma,
            kappa_sigma=self.kappa_sigma,
            tau_sigma=self.tau_sigma,
            kappa_tau_correlation=self.kappa_tau_correlation,
            units={"force": "pN", "moment": "pN nm", "kappa": "1/nm", "tau": "1/nm", "force_sigma": "pN",
                   "moment_sigma": "pN nm", "kappa_sigma": "1/nm", "tau_sigma": "1/nm", "kappa_tau_correlation": "-"},
        )


class SpringExample(eqx.Module):
    """A synthetic load test of a steel open-coiled helical spring (see `load_spring_example`).

    Per point: axial `force` (N) and axial `moment` (N mm) applied, measured `deflection`
    (change of the axial length, mm) and end `rotation` (change, rad) with standard
    deviations `deflection_sigma`, `rotation_sigma`.  Spring data (floats): Young's and shear
    moduli `E`, `G` (N/mm^2 = MPa), wire diameter `wire_diameter`, mean coil diameter
    `coil_diameter`, number of active coils `coils`, free `pitch` per coil (mm), and `rod`,
    the wire as a `Rod` (N mm^2, 1/mm) whose intrinsic twist is the unloaded helix.
    """

    force: Float[Array, " n"]
    moment: Float[Array, " n"]
    deflection: Float[Array, " n"]
    rotation: Float[Array, " n"]
    deflection_sigma: Float[Array, " n"]
    rotation_sigma: Float[Array, " n"]
    E: float = eqx.field(static=True)
    G: float = eqx.field(static=True)
    wire_diameter: float = eqx.field(static=True)
    coil_diameter: float = eqx.field(static=True)
    coils: float = eqx.field(static=True)
    pitch: float = eqx.field(static=True)
    rod: Rod
    provenance: str = eqx.field(static=True)

    @property
    def length(self) -> float:
        """Wire length of the active coils, $L = n\\sqrt{(\\pi D)^2 + \\text{pitch}^2}$ (mm)."""
        return self.coils * float(np.hypot(np.pi * self.coil_diameter, self.pitch))


def _provenance(meta):
    return "\n".join(f"{k}: {v}" for k, v in meta.items())


def load_tweezer_example() -> TweezerExample:
    """The bundled synthetic DNA tweezer dataset (`data/dna_tweezer_example.csv`).

    **Synthetic.** Generated by `examples/make_tweezer_example.py` from a uniform-helix model
    of the B-DNA backbone (rise 0.34 nm, 10.5 bp per turn, radius 1 nm): a rod with
    $K_1 = K_2$, $K_{13} = 0$, bend-twist coupling $K_{23}$ and intrinsic twist at the B-DNA
    helix, whose zero-load moduli (`dna.effective_moduli`) were set to published values of
    DNA: stretch modulus S = 1100 pN, twist modulus C = 410 pN nm^2 (twist persistence
    100 nm; Bryant et al., Nature 424, 338 (2003)), twist-stretch coupling g = -90 pN nm
    (Gore et al., Nature 442, 836 (2006)).  Forces 0.5-40 pN (log-spaced) x torques
    -10...15 pN nm; Gaussian noise on the per-bp extension (1e-4 nm) and rotation (2e-5 rad).
    The full provenance, including what the model cannot represent (the bending persistence
    of ~50 nm, the entropic elasticity at low force, buckling), is in `.provenance`.
    """
    meta, c = _read("dna_tweezer_example.csv")
    K1, K2, K3, K13, K23, u1, u2, u3 = _floats(meta, "K1", "K2", "K3", "K13", "K23", "uhat1", "uhat2", "uhat3")
    S, C, g = _floats(meta, "S", "C", "g")
    return TweezerExample(
        force=jnp.asarray(c["force"]),
        moment=jnp.asarray(c["moment"]),
        extension=jnp.asarray(c["extension_per_bp"]),
        rotation=jnp.asarray(c["rotation_per_bp"]),
        extension_sigma=jnp.asarray(c["extension_sigma"]),
        rotation_sigma=jnp.asarray(c["rotation_sigma"]),
        kappa=jnp.asarray(c["kappa"]),
        tau=jnp.asarray(c["tau"]),
        kappa_sigma=jnp.asarray(c["kappa_sigma"]),
        tau_sigma=jnp.asarray(c["tau_sigma"]),
        kappa_tau_correlation=jnp.asarray(c["kappa_tau_correlation"]),
        rod=Rod(K1, K2, K3, K13, K23, (u1, u2, u3)),
        length_per_bp=jnp.asarray(float(meta["length_per_bp"]), jnp.result_type(float)),
        moduli=tuple(jnp.asarray(x, jnp.result_type(float)) for x in (S, C, g)),
        provenance=_provenance(meta),
    )


def load_spring_example() -> SpringExample:
    """The bundled synthetic steel-spring load test (`data/steel_spring_example.csv`).

    **Synthetic.** Generated by `examples/make_spring_example.py` from the classical linear
    open-coiled spring formulas (energy method; Wahl, *Mechanical Springs*; Love §270-271)
    for a steel wire (E = 206 GPa, G = 79.3 GPa, typical handbook values for spring
    steel) of diameter 2 mm coiled to a mean diameter of 20 mm, 8 active coils, 5 mm pitch
    per coil; axial forces 0-8 N and axial moments -40, 0, 40 N mm; Gaussian noise
    0.02 mm on the deflection and 0.005 rad on the rotation.  See `.provenance`.
    """
    meta, c = _read("steel_spring_example.csv")
    E, G, d, D, n, pitch = _floats(meta, "E", "G", "wire_diameter", "coil_diameter", "coils", "pitch")
    K1, K2, K3, u1, u2, u3 = _floats(meta, "K1", "K2", "K3", "uhat1", "uhat2", "uhat3")
    return SpringExample(
        force=jnp.asarray(c["force"]),
        moment=jnp.asarray(c["moment"]),
        deflection=jnp.asarray(c["deflection"]),
        rotation=jnp.asarray(c["rotation"]),
        deflection_sigma=jnp.asarray(c["deflection_sigma"]),
        rotation_sigma=jnp.asarray(c["rotation_sigma"]),
        E=E,
        G=G,
        wire_diameter=d,
        coil_diameter=D,
        coils=n,
        pitch=pitch,
        rod=Rod(K1, K2, K3, uhat=(u1, u2, u3)),
        provenance=_provenance(meta),
    )


class TweezerCurvesExample(eqx.Module):
    """Synthetic tweezer curves of three DNA molecules (see `load_tweezer_curves_example`).

    `data`: the points as `TweezerData` (forces pN, extensions nm, turns, torques pN nm;
    `extension_sigma`, `force_sigma`, measured torques with their sigma); `rod`: the
    generating rod (pN nm^2, 1/nm; that of `load_tweezer_example`); `parameters`: every
    generating value by the names of `fit_stiffness(data, ..., fit_offsets=True)` -- `K1`
    ... `K23`, `uhat1` ... `uhat3`, `persistence_length` and `plectoneme_twist_persistence`
    (nm), `offset_<molecule>` (nm); `provenance`: the file's header text.
    """

    data: TweezerData
    rod: Rod
    parameters: dict
    provenance: str = eqx.field(static=True)


def load_tweezer_curves_example() -> TweezerCurvesExample:
    """The bundled synthetic tweezer curves of DNA (`data/dna_tweezer_curves.csv`).

    **Synthetic.** Generated by `examples/make_tweezer_curves_example.py` with
    `dna.tweezer_response` (the rod's own helix, worm-like chain, Moroz-Nelson twist
    softening, Marko's plectonemes) for three molecules of 7100, 8000 and 8900 bp:
    magnetic-tweezer hat curves (extension against turns, -40..40) at 0.3, 0.7, 1.5 and
    3 pN; a magnetic-torque-tweezer set at 2 pN with the torque measured (noise 2 pN nm);
    an optical-tweezer force-extension curve at zero torque from 0.05 to 40 pN -- 738
    points.  Generating values: the rod of `load_tweezer_example` (zero-load S = 1100 pN,
    C = 410 pN nm^2, g = -90 pN nm, published values), bending persistence 48 nm (a typical
    value), plectoneme twist persistence 24 nm (Marko 2007), bead-height offsets of a few
    nm per molecule.  Noise: Brownian extension noise of a bead averaged over the
    measurement, $\\sigma_h^2 = \\sigma_{track}^2 + 2k_BT\\gamma(\\partial h/\\partial F)^2/T$
    (growing as the force falls), 2 % force calibration (in `force_sigma`), exact turns.
    Every value and its source is in `.provenance`; fit it with
    `helixrod.fit_stiffness(example.data, uhat=example.rod.uhat, init=example.rod,
    fix={"K1": ..., "K13": 0}, fit_offsets=True)` or ``helixrod tweezer-fit``.
    """
    name = "dna_tweezer_curves.csv"
    meta = _comments(name)
    with importlib.resources.as_file(importlib.resources.files("helixrod").joinpath("data", name)) as path:
        data = TweezerData.from_csv(path)
    parameters = {key: float(meta[key]) for key in meta["parameters"].split()}
    K = [parameters[k] for k in ("K1", "K2", "K3", "K13", "K23")]
    rod = Rod(*K, uhat=tuple(parameters[f"uhat{i}"] for i in (1, 2, 3)))
    generic = ("helixrod TweezerData", "an empty turns or torque cell")  # the lines `to_csv` writes
    provenance = "\n".join(f"{k}: {v}" for k, v in meta.items() if k not in generic)
    return TweezerCurvesExample(data=data, rod=rod, parameters=parameters, provenance=provenance)
