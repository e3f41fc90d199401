r"""The tissue as a nearly incompressible continuum: W = W_iso(Ī1) + U(J).

An esmm material model is an incompressible strain energy :math:`W(I_1, I_2)`
(docs/design/model.md, "Material models"). The continuum reference of ``esmm validate`` uses its
standard compressible extension (Flory's split),

.. math::

    \Psi(\mathbf F) = W(\bar I_1, 3) + U(J), \qquad
    \bar I_1 = J^{-2/3}\,\mathrm{tr}(\mathbf F^T\mathbf F),\qquad
    U(J) = \tfrac{K}{2}(J-1)^2 ,

so that in every isochoric deformation (J = 1) the energy is the material's
own :math:`W(I_1)` and its homogeneous stresses are those of
:mod:`esmm.pipeline.materials.loading`. :class:`IsochoricMaterial` is the
isochoric part as a felupe constitutive material (the volumetric part and
the pressure live in felupe's mixed formulation, :mod:`.continuum`):

.. math::

    \mathbf P &= W_1\,\frac{\partial \bar I_1}{\partial \mathbf F}
               = 2 W_1 J^{-2/3}\left(\mathbf F - \tfrac{I_1}{3}\mathbf F^{-T}\right)

    \mathbb A &= W_{11}\,\mathbf D\otimes\mathbf D + 2 W_1 J^{-2/3}\Big[
        \mathbf 1\overset{ik}{\otimes}\mathbf 1
        - \tfrac23\left(\mathbf F\otimes\mathbf F^{-T} + \mathbf F^{-T}\otimes\mathbf F\right)
        + \tfrac{I_1}{3}\,\mathbf F^{-T}\overset{il}{\otimes}\mathbf F^{-T}
        + \tfrac{2 I_1}{9}\,\mathbf F^{-T}\otimes\mathbf F^{-T}\Big]

with :math:`\mathbf D = \partial\bar I_1/\partial\mathbf F` and :math:`W_1, W_{11}` the
material module's analytic derivatives (``MaterialModel.dW``/``d2W``) at
:math:`\bar I_1`; the bracket is felupe's own Neo-Hooke elasticity with μ = 1.
Models whose energy depends on :math:`I_2` are refused (none is registered).

:func:`bulk_modulus` is the rule for K: a multiple of the largest *tangent*
shear modulus of the material over the stretches the load cases use, not of
the small-strain one (the ESEDF stiffens 37-fold by λ = 1.3, so a penalty
sized at λ = 1 is not incompressible there).
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from ..materials.loading import stress_tangent

__all__ = ["DEFAULT_BULK_RATIO", "DEFAULT_STRETCH_RANGE", "IsochoricMaterial", "bulk_modulus",
           "tangent_shear_modulus"]

#: K over the largest tangent shear modulus: effective Poisson ratio >= 0.4995 over the range.
DEFAULT_BULK_RATIO = 1000.0
#: The stretches over which the tangent is taken: the compensation's calibration range.
DEFAULT_STRETCH_RANGE = (0.9, 1.3)


def tangent_shear_modulus(material, *, stretch_range=DEFAULT_STRETCH_RANGE, n: int = 201) -> float:
    """Largest tangent shear modulus of incompressible uniaxial loading over *stretch_range* [Pa].

    ``max dP/dλ / 3`` on *n* stretches (an incompressible solid's tangent
    Young's modulus is three times its tangent shear modulus), clipped to just
    inside the material's admissible range (locking).

    Parameters
    ----------
    material : Material
    stretch_range : (float, float)
    n : int
    """
    lo, hi = (float(v) for v in stretch_range)
    if not (0 < lo < 1 < hi):
        raise ConfigError(f"stretch_range: need 0 < low < 1 < high, got ({lo:g}, {hi:g})",
                          parameter="stretch_range")
    a, b = material.stretch_range()
    lo, hi = max(lo, a + 1e-3 * (1 - a)), min(hi, b - 1e-3 * (b - 1)) if np.isfinite(b) else hi
    lam = np.linspace(lo, hi, n)
    et = np.asarray(stress_tangent(material.model_obj, material.params_for(None), "uniaxial", lam))
    return float(np.nanmax(et)) / 3.0


def bulk_modulus(material, *, ratio: float = DEFAULT_BULK_RATIO, stretch_range=DEFAULT_STRETCH_RANGE) -> float:
    """Bulk modulus K of the continuum reference [Pa]: *ratio* times the largest tangent shear modulus.

    Parameters
    ----------
    material : Material
    ratio : float
        K / μ_t,max (default 1000: effective Poisson ratio ``(3K − 2μ)/(6K + 2μ)``
        at least 0.4995 at every stretch of the range).
    stretch_range : (float, float)
        Uniaxial stretches the load cases use (:func:`tangent_shear_modulus`).
    """
    if not (np.isfinite(ratio) and ratio > 0):
        raise ConfigError(f"bulk_ratio: must be a positive number, got {ratio!r}", parameter="bulk_ratio")
    return float(ratio) * tangent_shear_modulus(material, stretch_range=stretch_range)


def check_continuum(material) -> None:
    """Refuse a material the continuum reference cannot represent (anisotropic, or depending on I2)."""
    if not material.is_isotropic:
        raise ConfigError(
            f"material {material.name or material.model!r} has per-direction parameters: the continuum "
            "reference represents isotropic materials only (the network's fibre directions have no "
            "continuum counterpart in the isotropized ESEDF); validate with an isotropic material")
    i1 = np.array([3.0, 3.05, 3.2])
    _, w2 = material.model_obj.dW(i1, i1, material.params_for(None))
    if np.any(np.asarray(w2) != 0.0):
        raise ConfigError(f"material model {material.model!r} depends on I2: the continuum reference "
                          "implements W(I1) models only")


def _det_inv_t(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """det F and F^-T for F of shape (3, 3, ...)."""
    c = np.empty_like(F)  # cofactor matrix: F^-T = cof(F) / det F
    for i in range(3):
        for j in range(3):
            i1, i2 = (i + 1) % 3, (i + 2) % 3
            j1, j2 = (j + 1) % 3, (j + 2) % 3
            c[i, j] = F[i1, j1] * F[i2, j2] - F[i1, j2] * F[i2, j1]
    J = np.einsum("i...,i...->...", F[0], c[0])
    return J, c / J


class IsochoricMaterial:
    """The isochoric part ``W(Ī1)`` of an esmm material as a felupe constitutive material.

    felupe's solid bodies call ``gradient([F, statevars])`` -> ``[P, statevars]``
    and ``hessian([F, statevars])`` -> ``[A]`` with F of shape (3, 3, q, c)
    (quadrature points, cells); the formulas are in the module docstring.

    Parameters
    ----------
    material : Material
        Isotropic, W(I1) (:func:`check_continuum`).
    """

    def __init__(self, material, *, bulk: float | None = None):
        check_continuum(material)
        self.material = material
        self.bulk = None if bulk is None else float(bulk)
        self._model = material.model_obj
        self._params = material.params_for(None)
        self.x = [np.eye(3), np.zeros(0)]   # felupe's probe input

    def _invariants(self, F):
        J, iFT = _det_inv_t(F)
        a = np.cbrt(J) ** -2
        I1 = np.einsum("ij...,ij...->...", F, F)
        return J, iFT, a, I1

    def energy(self, F: np.ndarray) -> np.ndarray:
        """W(Ī1) [Pa], shape ``F.shape[2:]`` (NaN beyond locking)."""
        _, _, a, I1 = self._invariants(F)
        i1 = a * I1
        return np.asarray(self._model.energy(i1, np.full_like(i1, 3.0), self._params))

    def gradient(self, x, **kwargs):
        """``[P, statevars]``: the first Piola-Kirchhoff stress of the isochoric part [Pa]."""
        F, statevars = x[0], x[-1]
        J, iFT, a, I1 = self._invariants(F)
        w1, _ = self._model.dW(a * I1, np.full_like(I1, 3.0), self._params)
        P = (2.0 * w1 * a) * (F - (I1 / 3.0) * iFT)
        if self.bulk is not None:
            P = P + (self.bulk * (J - 1.0) * J) * iFT
        return [P, statevars]

    def hessian(self, x, **kwargs):
        """``[A]``: dP/dF of the isochoric part, shape (3, 3, 3, 3, ...) [Pa]."""
        F = x[0]
        J, iFT, a, I1 = self._invariants(F)
        i1 = a * I1
        w1, _ = self._model.dW(i1, np.full_like(i1, 3.0), self._params)
        w11, _, _ = self._model.d2W(i1, np.full_like(i1, 3.0), self._params)
        eye = np.eye(3)
        D = 2.0 * a * (F - (I1 / 3.0) * iFT)
        A = np.einsum("ik,jl->ijkl", eye, eye)[(...,) + (None,) * (F.ndim - 2)] * np.ones(F.shape[2:])
        FxiF = np.einsum("ij...,kl...->ijkl...", F, iFT)
        A = A - (2.0 / 3.0) * (FxiF + np.einsum("klij...->ijkl...", FxiF))
        A = A + (I1 / 3.0) * np.einsum("il...,kj...->ijkl...", iFT, iFT)
        A = A + (2.0 * I1 / 9.0) * np.einsum("ij...,kl...->ijkl...", iFT, iFT)
        A = (2.0 * w1 * a) * A + w11 * np.einsum("ij...,kl...->ijkl...", D, D)
        if self.bulk is not None:   # U = K (J - 1)^2 / 2, as felupe's NeoHooke
            K = self.bulk
            A = A + (K * J * (2.0 * J - 1.0)) * np.einsum("ij...,kl...->ijkl...", iFT, iFT) \
                - (K * J * (J - 1.0)) * np.einsum("il...,kj...->ijkl...", iFT, iFT)
        return [A]
