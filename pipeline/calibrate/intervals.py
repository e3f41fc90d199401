"""Confidence intervals of a least-squares fit: the policy shared by calibrate and discover.

The covariance is :math:`s^2 (J^T J)^{-1}` at the optimum in the optimiser's
coordinates, computed as the pseudo-inverse on the subspace the data identify:
directions of parameter space whose relative singular value is below
:data:`NULL_RTOL` are not seen by the data, and a quantity with more than
:data:`NULL_WEIGHT` of its (normalised) gradient in them is unbounded. The
covariance is inflated by :math:`(1+ρ)/(1-ρ)` for the lag-1 autocorrelation ρ of
the residuals (:func:`lag1`), because the samples of a machine record are not
independent (docs/design/calibration.md, "Confidence intervals").
"""

from __future__ import annotations

import numpy as np

#: relative singular value below which a direction of parameter space is not identified
NULL_RTOL = 1e-7
#: share of a gradient in the unidentified directions that makes a quantity unbounded
NULL_WEIGHT = 1e-2
#: a quantity is flagged "not identifiable" when its 95 % interval is wider than this
#: factor (upper/lower, positive and log-space quantities) ...
WIDE_LOG_FACTOR = 10.0
#: ... or than this many times its value (linear ones)
WIDE_REL_WIDTH = 1.0


def lag1(r: np.ndarray) -> float:
    """Lag-1 autocorrelation of a residual sequence (non-finite values dropped; 0 for fewer than 3)."""
    r = np.asarray(r, float)
    r = r[np.isfinite(r)]
    if r.size < 3:
        return 0.0
    r = r - r.mean()
    den = float(r @ r)
    return 0.0 if den == 0 else float(r[:-1] @ r[1:] / den)


def identified_covariance(J: np.ndarray, s2: float, inflation: float) -> tuple[np.ndarray, np.ndarray]:
    """Covariance on the identified subspace, and the unidentified directions.

    Parameters
    ----------
    J : ndarray, shape (n, p)
        Jacobian of the normalised residual at the optimum.
    s2 : float
        Residual variance.
    inflation : float
        Serial-correlation inflation ``(1+ρ)/(1-ρ)``.

    Returns
    -------
    cov : ndarray, shape (p, p)
    null : ndarray, shape (q, p)
        Rows spanning the directions the data do not see (q may be 0).

    Raises
    ------
    numpy.linalg.LinAlgError
        The singular value decomposition did not converge.
    """
    _, sv, Vt = np.linalg.svd(J, full_matrices=False)
    null = sv <= NULL_RTOL * sv.max() if sv.size and sv.max() > 0 else np.ones_like(sv, bool)
    keep = ~null
    cov = (Vt[keep].T / sv[keep] ** 2) @ Vt[keep] * s2 * inflation
    return cov, Vt[null]


def unbounded(grad: np.ndarray, null: np.ndarray) -> bool:
    """Whether a quantity with gradient *grad* has weight in the unidentified directions *null*."""
    gn = float(np.linalg.norm(grad)) or 1.0
    return bool(null.size and float(np.sum((null @ grad) ** 2)) / gn**2 > NULL_WEIGHT)
