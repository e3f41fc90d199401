r"""A base model plus strain-energy terms: the elastic law a discovery may build.

.. math::

    W(I_1, I_2) = W_\text{base}(I_1, I_2) + \sum_j W_j(I_1, I_2),

with the terms of :mod:`esmm.pipeline.materials.terms`. The name of a composite
model is the base's name followed by the terms, joined by ``+``
(``"esedf+i2exp"``, ``"esedf+toe+mooney"``); :func:`esmm.pipeline.materials.get_model`
builds it from that name, so a material file (``model = "esedf+i2exp"``) reads
back, and everything that works from a model's energy — loading modes, μ_e and
the network's stiffness tables, the Drucker check, the asset — works unchanged.
Derivatives add up; the model locks where its first part locks.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import ConfigError
from .base import MaterialModel
from .terms import TERM_NAMES, TERMS, Term

__all__ = ["CompositeModel", "composite_name", "split_name"]


def split_name(name: str) -> tuple[str, tuple[str, ...]]:
    """``"esedf+i2exp+toe"`` -> ``("esedf", ("i2exp", "toe"))`` (lower case, spaces removed)."""
    parts = [p.strip() for p in str(name).lower().split("+")]
    return parts[0], tuple(parts[1:])


def composite_name(base: str, terms) -> str:
    """The registry name of *base* plus *terms* (terms in library order, each once)."""
    ordered = [t for t in TERM_NAMES if t in set(terms)]
    return "+".join([base, *ordered])


class CompositeModel(MaterialModel):
    """*base* plus the strain-energy *terms* (module docstring).

    Parameters
    ----------
    base : MaterialModel
    terms : sequence of str
        Names in :data:`esmm.pipeline.materials.terms.TERMS`.

    Raises
    ------
    ConfigError
        Unknown or repeated term, or a term parameter that clashes with the base's.
    """

    def __init__(self, base: MaterialModel, terms):
        unknown = [t for t in terms if t not in TERMS]
        if unknown:
            raise ConfigError(f"unknown strain-energy term {unknown[0]!r}; the terms are {', '.join(TERM_NAMES)}")
        if len(set(terms)) != len(tuple(terms)):
            raise ConfigError(f"a strain-energy term is repeated in {'+'.join(terms)!r}")
        self.base = base
        self.terms: tuple[Term, ...] = tuple(TERMS[t] for t in TERM_NAMES if t in set(terms))
        self.name = composite_name(base.name, [t.name for t in self.terms])
        params = list(base.parameters)
        for t in self.terms:
            clash = [p.name for p in t.parameters if p.name in base.parameter_names]
            if clash:
                raise ConfigError(f"term {t.name!r}: parameter {clash[0]!r} clashes with model {base.name!r}")
            params += list(t.parameters)
        self.parameters = tuple(params)
        self.equation = " + ".join([base.equation] + [t.equation for t in self.terms])
        self.not_parameters = dict(base.not_parameters)
        # every term is written with numpy operations that broadcast over its parameters
        self.array_parameters = base.array_parameters

    # the sum of the parts ------------------------------------------------------
    def _split(self, p: dict[str, float]):
        base = {k: p[k] for k in self.base.parameter_names}
        return base, [{q.name: p[q.name] for q in t.parameters} for t in self.terms]

    def _energy(self, I1, I2, **p):
        b, tp = self._split(p)
        w = self.base.energy(I1, I2, b)
        for t, q in zip(self.terms, tp):
            w = w + t.energy(I1, I2, **q)
        return w

    def _dW(self, I1, I2, **p):
        b, tp = self._split(p)
        w1, w2 = self.base.dW(I1, I2, b)
        for t, q in zip(self.terms, tp):
            a1, a2 = t.dW(I1, I2, **q)
            w1, w2 = w1 + a1, w2 + a2
        return w1, w2

    def _d2W(self, I1, I2, **p):
        b, tp = self._split(p)
        w11, w12, w22 = self.base.d2W(I1, I2, b)
        for t, q in zip(self.terms, tp):
            a, c, d = t.d2W(I1, I2, **q)
            w11, w12, w22 = w11 + a, w12 + c, w22 + d
        return w11, w12, w22

    def _max_I1(self, **p):
        b, tp = self._split(p)
        m = self.base.max_I1(b)
        for t, q in zip(self.terms, tp):
            if t.max_I1 is not None:
                m = min(m, float(t.max_I1(**q)))
        return m if math.isfinite(m) else np.inf

    def _check_extra(self, params: dict[str, float], *, where: str) -> None:
        self.base._check_extra({k: params[k] for k in self.base.parameter_names}, where=where)
