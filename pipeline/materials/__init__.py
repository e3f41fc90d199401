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
``effects``       history effects beyond hyperelasticity (viscoelastic, Mullins, damage,
                  cyclic softening, permanent set): their equations, kernels and the
                  MaterialEffects record the asset and the simulator read
``terms``         strain-energy terms a discovery may add (I2, exponential, Gent, toe, ...)
``composite``     a base model plus terms, named ``"esedf+i2exp"`` (built by :func:`get_model`)
"""

from __future__ import annotations

import importlib

from ..errors import ConfigError
from .base import MaterialModel, Parameter
from .composite import CompositeModel, split_name

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

    A name ``"base+term+..."`` is a registered model plus strain-energy terms
    (:mod:`esmm.pipeline.materials.composite`), e.g. ``"esedf+i2exp"``.

    Raises
    ------
    ConfigError
        Unknown name or term (the message lists the known ones).
    """
    base_name, terms = split_name(str(name).replace(" ", ""))
    key = base_name.replace("_", "-")
    if key not in _REGISTRY:
        raise ConfigError(
            f"unknown material model {name!r}; choose one of {', '.join(MODEL_NAMES)}"
            + (" (plus strain-energy terms joined by '+')" if terms else "")
        )
    if key not in _CACHE:
        module, cls = _REGISTRY[key].split(":")
        mod = importlib.import_module(f"{__name__}.{module}")
        _CACHE[key] = getattr(mod, cls)()
    if not terms:
        return _CACHE[key]
    full = "+".join([key, *terms])
    if full not in _CACHE:
        model = CompositeModel(_CACHE[key], terms)
        _CACHE[full] = _CACHE.setdefault(model.name, model)
    return _CACHE[full]


__all__ = ["MODEL_NAMES", "CompositeModel", "MaterialModel", "Parameter", "get_model"]
