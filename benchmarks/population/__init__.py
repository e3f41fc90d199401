"""An independent population of tensile-test records for benchmarking esmm's discovery.

Written from the literature, not from esmm (it imports nothing of esmm and shares no code with
it): hyperelastic base laws (:mod:`.laws`, :mod:`.fibres`), protocols as labs run them
(:mod:`.protocols`), material effects and measurement artefacts in published forms
(:mod:`.relaxation`, :mod:`.history`, :mod:`.effects`), a testing machine's acquisition chain
(:mod:`.acquisition`, :mod:`.machine`) and the export formats of testing software
(:mod:`.exports`). :func:`generate` writes a seeded population of case folders, each with a
``truth.json`` (:mod:`.cases`).

Importable with ``benchmarks/`` on ``sys.path`` (pytest's ``pythonpath`` includes it).
"""

from .cases import GENERATOR_VERSION, generate, make_case, plan
from .effects import ARTEFACTS, CLASSES, MATERIAL

__all__ = ["ARTEFACTS", "CLASSES", "GENERATOR_VERSION", "MATERIAL", "generate", "make_case", "plan"]
