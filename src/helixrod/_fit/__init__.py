"""The inverse problem: stiffness (and intrinsic twist) from helices, end responses and
shapes -- data, forward models, parameterisation, the fit pipeline, the error analysis,
the closed-form linear fit and the bootstrap."""

from ._bootstrap import Bootstrap as Bootstrap, bootstrap as bootstrap
from ._compare import MODEL_CLASSES as MODEL_CLASSES, ModelComparison as ModelComparison, compare_models as compare_models
from ._design import ExperimentDesign as ExperimentDesign, design_experiment as design_experiment
from ._finite_data import (
    EndResponseData as EndResponseData,
    ShapeData as ShapeData,
    synthetic_end_response_data as synthetic_end_response_data,
    synthetic_shape_data as synthetic_shape_data,
)
from ._helix_data import HelixData as HelixData, synthetic_helix_data as synthetic_helix_data
from ._linear import fit_stiffness_linear as fit_stiffness_linear
from ._linearity import LinearityCheck as LinearityCheck, linearity_check as linearity_check
from ._models import (
    AbstractForwardModel as AbstractForwardModel,
    EndResponseModel as EndResponseModel,
    HelixModel as HelixModel,
    ShapeModel as ShapeModel,
    forward_model as forward_model,
)
from ._pipeline import SOLVERS as SOLVERS, StiffnessFit as StiffnessFit, fit_stiffness as fit_stiffness
from ._profile import ProfileLikelihood as ProfileLikelihood, profile_likelihood as profile_likelihood
from ._report import ErrorAnalysis as ErrorAnalysis, Identifiability as Identifiability, error_analysis as error_analysis
from ._tweezer_data import TweezerData as TweezerData
from ._tweezer_model import TweezerModel as TweezerModel
