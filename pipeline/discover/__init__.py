"""Close the loop on measured data: find what the base model misses, add it, report before and after.

``esmm calibrate FILE... --discover`` fits the base model (the ESEDF, or the
model chosen), diagnoses the structure of its residual, adds the effects the
data support (viscoelasticity, Mullins softening, damage; slack and load-cell
offset as measurement artefacts), each judged by AICc *and* by held-out data,
and reports the error before and after. docs/discover.md describes the
method, the JSON schema and the choices made.

Public API
----------
:func:`discover`            run the analysis on :class:`~esmm.pipeline.tensile.TensileTest` objects
:func:`discover_and_save`   the same, and write every output (the CLI's call)
:class:`DiscoverResult`     what was found
:class:`MaterialEffects`    the kept material effects, for the asset and the simulator
:mod:`.synthetic`           a generator of raw test files with hidden effects
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
from .report import discover_and_save, result_to_dict, summary_lines, write_outputs
from .search import DiscoverResult, discover

__all__ = [
    "ARTEFACTS",
    "EFFECT_NAMES",
    "MATERIAL_EFFECTS",
    "DamageEffect",
    "DiscoverResult",
    "MaterialEffects",
    "MullinsEffect",
    "ViscoelasticEffect",
    "discover",
    "discover_and_save",
    "qlv_step",
    "qlv_stress",
    "result_to_dict",
    "summary_lines",
    "write_outputs",
]
