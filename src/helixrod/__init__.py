"""helixrod: a fast, differentiable solver for elastic Kirchhoff rods and helices, in JAX.

Results are quoted in float64: call ``jax.config.update("jax_enable_x64", True)`` before
creating arrays (helixrod does not change JAX's configuration).  On import, before anything
is compiled, it asks XLA's CPU backend to compile loops of up to 1 MB into single kernels
and to hand only dots to its YNNPACK library fusions (``XLA_FLAGS``; see `helixrod._compile`;
``HELIXROD_COMPILER_OPTIONS=0`` turns both off).
"""

from importlib import metadata as _metadata

from . import _compile

_compile.request_small_loop_kernels()
_compile.request_dot_library_fusions()

from . import dna as dna, plot as plot
from ._bvp import (
    INSTABILITY_TYPES as INSTABILITY_TYPES,
    AbstractEnd as AbstractEnd,
    BoundaryValueOptions as BoundaryValueOptions,
    BoundaryValueSolution as BoundaryValueSolution,
    Branch as Branch,
    BulkHelix as BulkHelix,
    Clamped as Clamped,
    EndCondition as EndCondition,
    Loaded as Loaded,
    ResponseCurve as ResponseCurve,
    SpecialPoint as SpecialPoint,
    StabilityAtlas as StabilityAtlas,
    Tweezer as Tweezer,
    axial_ends as axial_ends,
    axial_response as axial_response,
    bulk_helix as bulk_helix,
    follow_branch as follow_branch,
    force_extension as force_extension,
    rotation_response as rotation_response,
    solve_boundary_value as solve_boundary_value,
    stability_atlas as stability_atlas,
)
from ._cache import enable_compilation_cache as enable_compilation_cache
from ._constitutive import StrainEnergyRod as StrainEnergyRod
from ._datasets import SpringExample as SpringExample, load_spring_example as load_spring_example
from ._equilibria import (
    HelixEquilibria as HelixEquilibria,
    helix_equilibria as helix_equilibria,
    helix_residual as helix_residual,
    pure_moment_family as pure_moment_family,
    straight_family as straight_family,
)
from ._fit import (
    MODEL_CLASSES as MODEL_CLASSES,
    Bootstrap as Bootstrap,
    EndResponseData as EndResponseData,
    ErrorAnalysis as ErrorAnalysis,
    ExperimentDesign as ExperimentDesign,
    HelixData as HelixData,
    Identifiability as Identifiability,
    LinearityCheck as LinearityCheck,
    ModelComparison as ModelComparison,
    ProfileLikelihood as ProfileLikelihood,
    ShapeData as ShapeData,
    StiffnessFit as StiffnessFit,
    bootstrap as bootstrap,
    compare_models as compare_models,
    design_experiment as design_experiment,
    error_analysis as error_analysis,
    fit_stiffness as fit_stiffness,
    fit_stiffness_linear as fit_stiffness_linear,
    linearity_check as linearity_check,
    profile_likelihood as profile_likelihood,
    synthetic_end_response_data as synthetic_end_response_data,
    synthetic_helix_data as synthetic_helix_data,
    synthetic_shape_data as synthetic_shape_data,
)
from ._geometry import (
    curvature_torsion as curvature_torsion,
    from_polar as from_polar,
    from_radius_angle as from_radius_angle,
    height_and_turns as height_and_turns,
    helix_angle as helix_angle,
    helix_centreline as helix_centreline,
    helix_frame as helix_frame,
    pitch_angle as pitch_angle,
    radius_pitch as radius_pitch,
    to_polar as to_polar,
    unloaded_observables as unloaded_observables,
    unloaded_state as unloaded_state,
)
from ._kirchhoff import (
    KirchhoffSolution as KirchhoffSolution,
    first_integrals as first_integrals,
    helix_initial_conditions as helix_initial_conditions,
    lab_wrench as lab_wrench,
    solve_static as solve_static,
    wrench_growth_rate as wrench_growth_rate,
)
from ._lie import CommutatorFreeRK4 as CommutatorFreeRK4, MuntheKaasRK as MuntheKaasRK, so3_exp as so3_exp
from ._load import LoadedHelices as LoadedHelices, helices_under_load as helices_under_load
from ._rod import PARAMETER_NAMES as PARAMETER_NAMES, Rod as Rod, section_scales as section_scales
from ._roots import register_roots as register_roots
from ._spring import effective_moduli as effective_moduli, spring_compliance as spring_compliance
from ._status import RESULTS as RESULTS, SolverError as SolverError
from ._sweep import (
    Sensitivity as Sensitivity,
    SweepResult as SweepResult,
    load_sweep as load_sweep,
    save_sweep as save_sweep,
    sensitivity as sensitivity,
    sweep as sweep,
)

try:
    __version__ = _metadata.version("helixrod")
except _metadata.PackageNotFoundError:  # imported from a source tree, not installed
    __version__ = "0+unknown"
