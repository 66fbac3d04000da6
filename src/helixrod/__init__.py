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
from ._load import LoadedHelices as LoadedHelices, helices_under_load as helices_under_load
from ._rod import Rod as Rod, section_scales as section_scales
from ._roots import register_roots as register_roots

# DNA tweezers and spring mechanics (issue 6)
from . import dna as dna
from ._datasets import SpringExample as SpringExample, load_spring_example as load_spring_example
from ._spring import effective_moduli as effective_moduli, spring_compliance as spring_compliance

__version__ = importlib.metadata.version("helixrod")
