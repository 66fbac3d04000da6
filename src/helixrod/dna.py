"""helixrod.dna: DNA tweezer units, the B-DNA backbone helix, and single-molecule moduli.

A single-molecule experiment applies an axial force $F$ (pN) and torque $M$ (pN nm) to a
DNA molecule and measures its extension (nm) and rotation (turns).  Modelling the backbone
as a uniform elastic helix (a `helixrod.Rod` whose intrinsic twist is the B-DNA helix),
this module converts between those observables and the helix $(\\kappa, \\tau)$, and gives
the linear moduli the field quotes -- stretch modulus $S$, twist modulus $C$, twist-stretch
coupling $g$ -- for any rod (`effective_moduli`).  Units: pN, nm, pN nm, radians; see the
module `helixrod._dna` docstring for the conventions.  Every function broadcasts its array
arguments elementwise; where inputs are checked (temperatures, helix geometry, tweezer
observables) bad concrete values raise `ValueError` and traced ones give NaN.

**Example**

```python
import jax.numpy as jnp
from helixrod import dna
kappa0, tau0, ell = dna.helix_from_bdna()           # 1/nm, 1/nm, nm per bp
dna.persistence_length(410.0)                       # twist modulus 410 pN nm^2 -> ~100 nm
data = dna.load_tweezer_example()
S, C, g = dna.effective_moduli(data.rod, data.rod.uhat)
hat = dna.tweezer_response(data.rod, 8000, 1.0, turns=jnp.linspace(-40, 40, 81))  # thermal
```

`tweezer_response` adds the thermal fluctuations a tweezer sees to the rod's own response
(worm-like chain, Moroz-Nelson twist softening, Marko's plectonemes; `helixrod._tweezer`),
and `TweezerData` holds what instruments record, fitted with `helixrod.fit_stiffness`.
"""

from ._datasets import TweezerExample as TweezerExample, load_tweezer_example as load_tweezer_example
from ._datasets import TweezerCurvesExample as TweezerCurvesExample, load_tweezer_curves_example as load_tweezer_curves_example
from ._dna import (
    BOLTZMANN_CONSTANT as BOLTZMANN_CONSTANT,
    NANOMETRE as NANOMETRE,
    PICONEWTON as PICONEWTON,
    PN_NM as PN_NM,
    ROOM_TEMPERATURE as ROOM_TEMPERATURE,
    bdna_from_helix as bdna_from_helix,
    changes_from_helix as changes_from_helix,
    helix_from_bdna as helix_from_bdna,
    helix_from_changes as helix_from_changes,
    helix_from_observables as helix_from_observables,
    helix_from_tweezer as helix_from_tweezer,
    kT as kT,
    observables_from_helix as observables_from_helix,
    persistence_length as persistence_length,
    radians_to_turns as radians_to_turns,
    stiffness_from_persistence as stiffness_from_persistence,
    turns_to_radians as turns_to_radians,
    tweezer_from_helix as tweezer_from_helix,
)
from ._fit import TweezerData as TweezerData
from ._spring import effective_moduli as effective_moduli
from ._tweezer import (
    PHASES as PHASES,
    PLECTONEME_TWIST_PERSISTENCE as PLECTONEME_TWIST_PERSISTENCE,
    TweezerModuli as TweezerModuli,
    TweezerResponse as TweezerResponse,
    moroz_nelson_twist_modulus as moroz_nelson_twist_modulus,
    tweezer_moduli as tweezer_moduli,
    tweezer_response as tweezer_response,
    wlc_extension as wlc_extension,
    wlc_force as wlc_force,
    wlc_free_energy as wlc_free_energy,
)
