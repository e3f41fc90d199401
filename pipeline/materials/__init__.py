"""Material models of esmm: strain-energy functions, loading modes, materials.

Registry
--------
:func:`get_model` returns a model instance by name; :data:`MODEL_NAMES` lists
the names. Adding a model is one small module (a :class:`MaterialModel`
subclass with its parameter specifications, equation in the docstring) plus
one line in :data:`_REGISTRY` below.

Modules
-------
``base``          Parameter, MaterialModel
``langevin``      exact inverse Langevin function and the eight-chain term
``arruda_boyce``  classic Arruda-Boyce model ("arruda-boyce")
``esedf``         the ESMM paper's rule-of-mixtures model ("esedf")
``loading``       homogeneous incompressible deformations, nominal stress, μ_e
``stability``     Drucker stability check
``material``      Material (model + parameters + directions), TOML in/out
``effects``       history effects beyond hyperelasticity (viscoelastic, Mullins, damage):
                  their equations, kernels and the MaterialEffects record the asset and the
                  simulator read
"""

from __future__ import annotations

import importlib

from ..errors import ConfigError
from .base import MaterialModel, Parameter

#: name -> "module:ClassName" (one line per model)
_REGISTRY: dict[str, str] = {
    "esedf": "esedf:ESEDF",
    "arruda-boyce": "arruda_boyce:ArrudaBoyce",
}

#: The registered model names.
MODEL_NAMES: tuple[str, ...] = tuple(_REGISTRY)

_CACHE: dict[str, MaterialModel] = {}


def get_model(name: str) -> MaterialModel:
    """The material model registered as *name* (case-insensitive; ``_`` = ``-``).

    Raises
    ------
    ConfigError
        Unknown name (the message lists the known ones).
    """
    key = str(name).strip().lower().replace("_", "-")
    if key not in _REGISTRY:
        raise ConfigError(
            f"unknown material model {name!r}; choose one of {', '.join(MODEL_NAMES)}"
        )
    if key not in _CACHE:
        module, cls = _REGISTRY[key].split(":")
        mod = importlib.import_module(f"{__name__}.{module}")
        _CACHE[key] = getattr(mod, cls)()
    return _CACHE[key]


__all__ = ["MODEL_NAMES", "MaterialModel", "Parameter", "get_model"]
