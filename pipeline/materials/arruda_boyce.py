r"""Arruda-Boyce eight-chain model (Arruda & Boyce 1993), classic form.

.. math::

    W = \mu N \left[\lambda_r \beta + \ln\frac{\beta}{\sinh\beta}\right] - c,
    \qquad \lambda_r = \sqrt{\frac{I_1}{3N}}, \qquad
    \beta = \mathcal{L}^{-1}(\lambda_r),

with the constant :math:`c = \mu N [\lambda_{r0}\beta_0 + \ln(\beta_0/\sinh\beta_0)]`,
:math:`\lambda_{r0} = 1/\sqrt{N}`, so that :math:`W = 0` in the reference state.

* ``mu`` is :math:`C_R = nk\theta` of Arruda & Boyce (1993) (their Eq. 27,
  :math:`W = C_R N[\ldots]`). It is *not* exactly the initial shear modulus:
  :math:`\mu_0 = \mu\,\beta_0/(3\lambda_{r0}) = \mu(1 + 3/(5N) + 99/(175N^2) + \ldots)`
  (:meth:`ArrudaBoyce.initial_shear_modulus`). With this convention Treloar's
  (1944) uniaxial data give :math:`C_R \approx 0.27` MPa, :math:`N \approx 26`,
  the values of Arruda & Boyce (1993) (checked in tests/test_materials.py).
* ``N`` is the number of rigid links per chain; the chain locks when
  :math:`\lambda_r \to 1`, i.e. :math:`I_1 \to 3N` (``max_I1``). N must
  exceed 1 (at N = 1 the reference state is already locked).

Derivatives (:math:`d\lambda_r/dI_1 = 1/(6N\lambda_r)`, and
:math:`d[\lambda_r\beta + \ln(\beta/\sinh\beta)]/d\lambda_r = \beta`):

.. math::

    W_1 = \frac{\mu\beta}{6\lambda_r},\qquad
    W_{11} = \frac{\mu(\lambda_r\beta' - \beta)}{36N\lambda_r^3},\qquad
    W_2 = 0,

with :math:`\beta' = d\mathcal{L}^{-1}/dx = 1/\mathcal{L}'(\beta)`. As
:math:`N\to\infty`, :math:`W_1 \to \mu/2`: the neo-Hookean model.

References
----------
E. M. Arruda, M. C. Boyce, "A three-dimensional constitutive model for the large
stretch behavior of rubber elastic materials", J. Mech. Phys. Solids 41 (1993)
389-412.
"""

from __future__ import annotations

import functools

import numpy as np

from .base import MaterialModel, Parameter, broadcast_zeros
from .langevin import chain_energy, inverse_langevin, langevin_derivative

__all__ = ["ArrudaBoyce", "energy", "dW", "d2W", "max_I1", "chain_energy_difference"]

#: Steps |r - r0| below this fraction of the distance d = 1 - max(r, r0) to
#: the locking singularity are integrated (Gauss-Legendre, _GL_NODES nodes:
#: error about (h/(4d))**(2n) < 1e-20) instead of differenced; above it the
#: difference loses at most a factor F(r0)/(F(r)-F(r0)) < 3e3 (relative
#: round-off < 1e-12).
_SMALL_STEP = 1e-3
_GL_NODES = 4
_GL_X, _GL_W = np.polynomial.legendre.leggauss(_GL_NODES)


def chain_energy_difference(r, r0):
    r""":math:`F(r) - F(r_0)` with :math:`F(x) = x\beta + \ln(\beta/\sinh\beta)`.

    Since :math:`F' = \mathcal{L}^{-1}`, steps that are small compared with the
    distance to the locking singularity are computed as
    :math:`\int_{r_0}^{r}\mathcal{L}^{-1}(s)\,ds` by Gauss-Legendre quadrature,
    so the result keeps its relative precision near the reference state
    (where the plain difference of two O(1) numbers would lose it); larger
    steps use the plain difference, which is then well conditioned.

    Parameters
    ----------
    r : array_like, shape (...)
        Relative chain stretch, in [0, 1).
    r0 : float or array_like, broadcastable to ``r``
        Reference relative chain stretch.

    Returns
    -------
    ndarray, shape (...)
    """
    r = np.asarray(r, float)
    f0 = chain_energy(r0)  # once, when r0 is a scalar
    r0 = np.broadcast_to(np.asarray(r0, float), r.shape)
    h = r - r0
    dist = 1.0 - np.maximum(r, r0)
    small = np.abs(h) < _SMALL_STEP * dist
    out = np.array(chain_energy(r) - f0, dtype=float, ndmin=1).reshape(r.shape)
    if np.any(small):
        rs, r0s, hs = r[small], r0[small], h[small]
        mid = 0.5 * (rs + r0s)
        nodes = mid[:, None] + 0.5 * hs[:, None] * _GL_X[None, :]
        out[small] = 0.5 * hs * (inverse_langevin(nodes) @ _GL_W)
    return out


def energy(I1, I2, mu, N):
    """W [Pa] of the classic Arruda-Boyce model (see the module docstring)."""
    r = np.sqrt(np.asarray(I1, float) / (3.0 * N))
    r0 = np.sqrt(3.0 / (3.0 * N))  # same rounding as r, so W(3) == 0 exactly
    if np.ndim(r0) == 0 and _MEMO_SIZES[0] <= r.size <= _MEMO_SIZES[1]:
        diff = _chain_difference_memo(float(r0), r.shape, r.tobytes())
    else:
        diff = chain_energy_difference(r, r0)
    return mu * N * diff + 0.0 * np.asarray(I2, float)


#: array sizes whose chain-energy differences are remembered (a fitter's samples; not tables or scalars)
_MEMO_SIZES = (32, 65536)


@functools.lru_cache(maxsize=16)
def _chain_difference_memo(r0: float, shape: tuple, data: bytes) -> np.ndarray:
    """:func:`chain_energy_difference` of the stretches *data* (read-only; the most recent 16 kept).

    A fitter's finite-difference steps in μ (and in other models' or terms'
    parameters) meet the same relative chain stretches again; only a step in
    N changes them.
    """
    out = chain_energy_difference(np.frombuffer(data, dtype=float).reshape(shape), r0)
    out.flags.writeable = False
    return out


def dW(I1, I2, mu, N):
    """(W1, W2) [Pa]: W1 = μ β / (6 λ_r), W2 = 0."""
    I1 = np.asarray(I1, float)
    r = np.sqrt(I1 / (3.0 * N))
    beta = inverse_langevin(r)
    # beta / r -> 3 as r -> 0 (series branch of L^-1 keeps the ratio exact)
    ratio = np.where(r > 0.0, beta / np.where(r > 0.0, r, 1.0), 3.0)
    w1 = mu * ratio / 6.0
    return w1, broadcast_zeros(I1, I2)


def d2W(I1, I2, mu, N):
    """(W11, W12, W22) [Pa]: W11 = μ (λ_r β' − β) / (36 N λ_r³), W12 = W22 = 0."""
    I1 = np.asarray(I1, float)
    r = np.sqrt(I1 / (3.0 * N))
    beta = inverse_langevin(r)
    dbeta = 1.0 / langevin_derivative(beta)
    rs = np.where(r > 0.0, r, 1.0)
    w11 = np.where(r > 0.0, mu * (rs * dbeta - beta) / (36.0 * N * rs**3), mu / (10.0 * N))
    z = broadcast_zeros(I1, I2)
    return w11 + z, z, z


def max_I1(mu, N):
    """Locking: W is finite for I1 < 3N."""
    return 3.0 * N


class ArrudaBoyce(MaterialModel):
    r"""Arruda-Boyce eight-chain model: :math:`W = \mu N[\lambda_r\beta + \ln(\beta/\sinh\beta)] - c`.

    ``mu`` = :math:`C_R` [Pa] (chain modulus nkθ), ``N`` = links per chain
    (locking at :math:`I_1 = 3N`). See :mod:`esmm.pipeline.materials.arruda_boyce`.
    """

    name = "arruda-boyce"
    array_parameters = True
    equation = "W = mu*N*[lr*beta + ln(beta/sinh(beta))] - c,  lr = sqrt(I1/(3N)),  beta = Linv(lr)"
    parameters = (
        Parameter("mu", "stress", 1.0e5, 0.0, 1.0e10,
                  "chain modulus C_R = n k theta (initial shear modulus for large N)",
                  directional=True),
        Parameter("N", "dimensionless", 10.0, 1.000001, 1.0e8,
                  "rigid links per chain; locking at I1 = 3N (must exceed 1)"),
    )

    def _energy(self, I1, I2, *, mu, N):
        return energy(I1, I2, mu, N)

    def _dW(self, I1, I2, *, mu, N):
        return dW(I1, I2, mu, N)

    def _d2W(self, I1, I2, *, mu, N):
        return d2W(I1, I2, mu, N)

    def _max_I1(self, *, mu, N):
        return max_I1(mu, N)
