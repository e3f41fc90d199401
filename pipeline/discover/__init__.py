"""Close the loop on measured data: find what the base model misses, add it, report before and after.

``esmm calibrate FILE... --discover`` fits the base model (the ESEDF, or the
model chosen), diagnoses the structure of its residual, adds the effects the
data support (viscoelasticity, Mullins softening, damage; slack and load-cell
offset as measurement artefacts), each judged by AICc *and* by held-out data,
and reports the error before and after. ``esmm evaluate`` predicts new files
with what a calibration or a discovery saved. docs/design/discovery.md describes the
method and the choices made, docs/reference/outputs.md the JSON schemas.

Public API
----------
:func:`discover`            run the analysis on :class:`~esmm.pipeline.tensile.TensileTest` objects
:func:`discover_and_save`   the same, and write every output (the CLI's call)
:class:`DiscoverResult`     what was found
:class:`MaterialEffects`    the kept material effects, for the asset and the simulator
:func:`evaluate`            predict new files with a saved fit (:func:`load_fit`), without refitting
:mod:`.synthetic`           a generator of raw test files with hidden effects

Modules, bottom-up
------------------
``covariates``  segments, rates, holds, cycles of a record; thinning
``model``       the extended model (base + effects) and its least-squares problem
``statistics``  runs test, effective sample sizes, AICc/BIC, error measures
``estimates``   parameters with 95 % intervals
``diagnose``    the residual's structure and the candidates it points to
``initialise``  starting values of an effect's parameters
``fitted``      a fitted model; fitting one model from another
``heldout``     held-out schemes and errors
``search``      the greedy search (:func:`discover`)
``report``      outputs
``evaluate``    prediction of new files with a saved fit
"""

from ..materials.effects import (
    ARTEFACTS,
    EFFECT_NAMES,
    MATERIAL_EFFECTS,
    DamageEffect,
    MaterialEffects,
    MullinsEffect,
    ViscoelasticEffect,
    qlv_step,
    qlv_stress,
)
from .evaluate import Evaluation, SavedFit, evaluate, load_fit
from .report import discover_and_save, result_to_dict, summary_lines, write_outputs
from .search import DiscoverResult, discover

__all__ = [
    "ARTEFACTS",
    "EFFECT_NAMES",
    "MATERIAL_EFFECTS",
    "DamageEffect",
    "DiscoverResult",
    "Evaluation",
    "MaterialEffects",
    "MullinsEffect",
    "SavedFit",
    "ViscoelasticEffect",
    "discover",
    "discover_and_save",
    "evaluate",
    "load_fit",
    "qlv_step",
    "qlv_stress",
    "result_to_dict",
    "summary_lines",
    "write_outputs",
]
