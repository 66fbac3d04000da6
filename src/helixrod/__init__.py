"""helixrod: a fast, differentiable solver for elastic Kirchhoff rods and helices, in JAX.

Results are quoted in float64: call ``jax.config.update("jax_enable_x64", True)`` before
creating arrays (helixrod never changes global JAX configuration itself).
"""

import importlib.metadata

from ._equilibria import (
    HelixEquilibria as HelixEquilibria,
    helix_equilibria as helix_equilibria,
    helix_residual as helix_residual,
    pure_moment_family as pure_moment_family,
    register_coefficients as register_coefficients,
    straight_family as straight_family,
)
from ._geometry import (
    curvature_torsion as curvature_torsion,
    from_polar as from_polar,
    from_radius_angle as from_radius_angle,
    height_and_turns as height_and_turns,
    helix_angle as helix_angle,
    helix_centreline as helix_centreline,
    pitch_angle as pitch_angle,
    radius_pitch as radius_pitch,
    to_polar as to_polar,
)
from ._constitutive import StrainEnergyRod as StrainEnergyRod
from ._kirchhoff import (
    KirchhoffSolution as KirchhoffSolution,
    first_integrals as first_integrals,
    helix_frame as helix_frame,
    helix_initial_conditions as helix_initial_conditions,
    lab_wrench as lab_wrench,
    solve_static as solve_static,
)
from ._lie import (
    BodyVelocityTerm as BodyVelocityTerm,
    CommutatorFreeRK4 as CommutatorFreeRK4,
    MuntheKaasRK as MuntheKaasRK,
    RodState as RodState,
    hat as hat,
    se3_exp as se3_exp,
    so3_exp as so3_exp,
)
from ._load import LoadedHelices as LoadedHelices, helices_under_load as helices_under_load
from ._rod import Rod as Rod, section_scales as section_scales
# -- inverse spring problem (issue 4) --
from ._data import HelixData as HelixData, synthetic_helix_data as synthetic_helix_data
from ._fit import (
    Bootstrap as Bootstrap,
    Identifiability as Identifiability,
    StiffnessFit as StiffnessFit,
    bootstrap as bootstrap,
    fit_stiffness as fit_stiffness,
    fit_stiffness_linear as fit_stiffness_linear,
)
# -- end issue 4 --
from ._roots import register_roots as register_roots
from ._sweep import (
    Sensitivity as Sensitivity,
    SweepResult as SweepResult,
    load_sweep as load_sweep,
    save_sweep as save_sweep,
    sensitivity as sensitivity,
    sweep as sweep,
)
from . import plot as plot

# -- finite rods (issue 8) --
from ._boundary import (
    AbstractEnd as AbstractEnd,
    BoundaryValueSolution as BoundaryValueSolution,
    Clamped as Clamped,
    Loaded as Loaded,
    Tweezer as Tweezer,
    axial_ends as axial_ends,
    solve_boundary_value as solve_boundary_value,
    wrench_growth_rate as wrench_growth_rate,
)
from ._finite_data import (
    EndResponseData as EndResponseData,
    ShapeData as ShapeData,
    synthetic_end_response_data as synthetic_end_response_data,
    synthetic_shape_data as synthetic_shape_data,
)
from ._response import (
    ResponseCurve as ResponseCurve,
    force_extension as force_extension,
    rotation_response as rotation_response,
)
# -- end issue 8 --

# DNA tweezers and spring mechanics (issue 6)
from . import dna as dna
from ._datasets import SpringExample as SpringExample, load_spring_example as load_spring_example
from ._spring import effective_moduli as effective_moduli, spring_compliance as spring_compliance

try:
    __version__ = importlib.metadata.version("helixrod")
except importlib.metadata.PackageNotFoundError:  # imported from a source tree, not installed
    __version__ = "0+unknown"
