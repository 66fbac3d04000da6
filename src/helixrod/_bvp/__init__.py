"""Finite rods: end conditions, boundary-value solves by (multiple) shooting, and the
axial response curves of springs and tweezer filaments."""

from ._atlas import (
    INSTABILITY_TYPES as INSTABILITY_TYPES,
    StabilityAtlas as StabilityAtlas,
    stability_atlas as stability_atlas,
)
from ._branch import Branch as Branch, SpecialPoint as SpecialPoint, follow_branch as follow_branch
from ._bulk import BulkHelix as BulkHelix, bulk_helix as bulk_helix, bulk_helix_at as bulk_helix_at, helix_under_wrench as helix_under_wrench
from ._ends import (
    AXIAL_CONTROLS as AXIAL_CONTROLS,
    AXIAL_OBSERVABLES as AXIAL_OBSERVABLES,
    AbstractEnd as AbstractEnd,
    Clamped as Clamped,
    EndCondition as EndCondition,
    Loaded as Loaded,
    Tweezer as Tweezer,
    as_start as as_start,
    axial_ends as axial_ends,
    stack_ends as stack_ends,
)
from ._options import BoundaryValueOptions as BoundaryValueOptions
from ._response import (
    ResponseCurve as ResponseCurve,
    axial_response as axial_response,
    force_extension as force_extension,
    rotation_response as rotation_response,
)
from ._solve import BoundaryValueSolution as BoundaryValueSolution, solve_boundary_value as solve_boundary_value
