r"""ESEDF: the equivalent strain-energy density function of the ESMM paper.

A rule of mixtures of an Arruda-Boyce eight-chain matrix and an isotropized
fibre term (the paper's Eqs. 2-4), as implemented here:

.. math::

    W_T = (1-f)\,W_{iso}(I_1) + f\,W_{aniso}(\bar I_4),

    W_{iso} = \mu N\left[\lambda_r\beta + \ln\frac{\beta}{\sinh\beta}\right] - c,
    \quad \lambda_r = \sqrt{I_1/(3N)},\ \beta = \mathcal{L}^{-1}(\lambda_r),

    W_{aniso} = A_1(\bar I_4 - 1) + A_2(\bar I_4 - 1)^2,
    \quad \bar I_4 = \tfrac{1}{8}\sum_{k=1}^{8} \mathbf a_k\cdot\mathbf C\,\mathbf a_k
    = \frac{I_1}{3},

where :math:`\mathbf a_k = (\pm1,\pm1,\pm1)/\sqrt3` are the eight-chain
directions (the "isotropized" fibre invariant: the average of the fibre
invariant :math:`I_4` over the eight directions is exactly :math:`I_1/3` for any
C; in the paper's notation :math:`I_{1i} = I_1`, :math:`\bar I_4 = I_{1i}/3`),
and :math:`c` makes :math:`W_{iso} = 0` in the reference state. The paper's
isotropized third invariant :math:`I_{3i}` is 1 in every incompressible
deformation, so the terms in it vanish; the paper's ``b`` and ``C`` enter only
through those terms and are therefore not parameters of this (incompressible)
model. docs/design/model.md gives the evidence for this reading: it reproduces the
reference values μ_e(1.1) ≈ 0.029 MPa and μ_e(1.3) ≈ 0.123 MPa of the paper's
porcine-liver fit to 0.5 %.

Units: ``mu``, ``A1``, ``A2`` are stresses [Pa]; ``N``, ``f`` dimensionless.

Derivatives (:math:`W_2 = 0`, the model depends on :math:`I_1` only):

.. math::

    W_1 = (1-f)\frac{\mu\beta}{6\lambda_r} + \frac{f}{3}\left[A_1 + 2A_2(\bar I_4-1)\right],
    \qquad
    W_{11} = (1-f)\frac{\mu(\lambda_r\beta'-\beta)}{36N\lambda_r^3} + \frac{2fA_2}{9}.

Small-strain shear modulus :math:`\mu_0 = 2W_1(3) = (1-f)\mu\beta_0/(3\lambda_{r0}) + 2fA_1/3`,
Young's modulus :math:`E = 3\mu_0`.
"""

from __future__ import annotations

import numpy as np

from . import arruda_boyce as ab
from .base import MaterialModel, Parameter, broadcast_zeros

__all__ = ["ESEDF", "energy", "dW", "d2W", "max_I1"]


def energy(I1, I2, mu, N, A1, A2, f):
    """W_T [Pa] (see the module docstring)."""
    I1 = np.asarray(I1, float)
    q = (I1 - 3.0) / 3.0  # isotropized fibre invariant minus one
    w = f * (A1 * q + A2 * q * q)
    w = _with_matrix(w, mu, f, lambda: (1.0 - f) * ab.energy(I1, I2, mu, N))
    return w + 0.0 * np.asarray(I2, float)


def dW(I1, I2, mu, N, A1, A2, f):
    """(W1, W2) [Pa]."""
    I1 = np.asarray(I1, float)
    q = (I1 - 3.0) / 3.0
    w1 = f * (A1 + 2.0 * A2 * q) / 3.0
    w1 = _with_matrix(w1, mu, f, lambda: (1.0 - f) * ab.dW(I1, I2, mu, N)[0])
    z = broadcast_zeros(I1, I2)
    return w1 + z, z


def d2W(I1, I2, mu, N, A1, A2, f):
    """(W11, W12, W22) [Pa]."""
    I1 = np.asarray(I1, float)
    z = broadcast_zeros(I1, I2)
    w11 = 2.0 * f * A2 / 9.0 + z
    w11 = _with_matrix(w11, mu, f, lambda: (1.0 - f) * ab.d2W(I1, I2, mu, N)[0])
    return w11, z, z


def max_I1(mu, N, A1, A2, f):
    """Locking of the eight-chain matrix at I1 = 3N (the fibre term is finite)."""
    return np.where(_matrix_active(mu, f), 3.0 * N, np.inf) if np.ndim(mu) or np.ndim(f) else \
        (3.0 * N if _matrix_active(mu, f) else np.inf)


def _matrix_active(mu, f):
    """The matrix term exists (and locks) only when (1 - f) * mu > 0 (per row for parameter arrays)."""
    return (1.0 - f) * mu > 0.0


def _with_matrix(w, mu, f, matrix):
    """*w* plus the matrix term ``matrix()`` where the matrix is active.

    With parameter arrays (one parameter set per row, see
    :attr:`~esmm.pipeline.materials.base.MaterialModel.array_parameters`) each
    row gets what the scalar form gives it: the sum where active, *w* alone
    where not.
    """
    active = _matrix_active(mu, f)
    if np.all(active):
        return w + matrix()
    if not np.any(active):
        return w
    return np.where(active, w + matrix(), w)


class ESEDF(MaterialModel):
    r"""ESMM equivalent strain energy: :math:`W_T = (1-f)W_{AB}(I_1) + f[A_1(\bar I_4-1) + A_2(\bar I_4-1)^2]`, :math:`\bar I_4 = I_1/3`.

    Parameters (SI): ``mu`` [Pa] Arruda-Boyce chain modulus C_R, ``N`` links per
    chain, ``A1`` [Pa] and ``A2`` [Pa] fibre moduli, ``f`` fibre fraction.
    Defaults are the paper's porcine-liver fit. See
    :mod:`esmm.pipeline.materials.esedf` and docs/design/model.md.
    """

    name = "esedf"
    array_parameters = True
    equation = (
        "W = (1-f)*{mu*N*[lr*beta + ln(beta/sinh(beta))] - c} + f*[A1*(I4-1) + A2*(I4-1)^2],"
        "  I4 = I1/3,  lr = sqrt(I1/(3N)),  beta = Linv(lr)"
    )
    not_parameters = {
        k: "in the reading implemented here the paper's b and C belong to terms in the isotropized "
           "third invariant I3i, which vanish in incompressible deformation (docs/design/model.md); "
           "keep the value under [material.reported]"
        for k in ("b", "C")
    }
    parameters = (
        Parameter("mu", "stress", 2.973, 0.0, 1.0e10,
                  "Arruda-Boyce matrix chain modulus C_R"),
        Parameter("N", "dimensionless", 1.1074, 1.000001, 1.0e8,
                  "rigid links per matrix chain; locking at I1 = 3N (must exceed 1)"),
        Parameter("A1", "stress", 3.9106e6, 0.0, 1.0e11,
                  "linear fibre modulus (coefficient of I4-1, I4 = I1/3)", directional=True),
        Parameter("A2", "stress", 451.9193e6, 0.0, 1.0e12,
                  "quadratic fibre modulus (coefficient of (I4-1)^2)", directional=True),
        Parameter("f", "dimensionless", 0.0019, 0.0, 1.0,
                  "fibre fraction of the rule of mixtures (only f*A1, f*A2 are identifiable)",
                  fit=False),
    )

    def _energy(self, I1, I2, *, mu, N, A1, A2, f):
        return energy(I1, I2, mu, N, A1, A2, f)

    def _dW(self, I1, I2, *, mu, N, A1, A2, f):
        return dW(I1, I2, mu, N, A1, A2, f)

    def _d2W(self, I1, I2, *, mu, N, A1, A2, f):
        return d2W(I1, I2, mu, N, A1, A2, f)

    def _max_I1(self, *, mu, N, A1, A2, f):
        return max_I1(mu, N, A1, A2, f)
