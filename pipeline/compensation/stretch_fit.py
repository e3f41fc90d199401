r"""The stretch correction fitted on several load cases at once: Gauss-Newton on power shares.

The compensation's stretch correction :math:`g(\lambda)` multiplies the law's
table at the spring's own stretch. Fitted on the calibration cylinder's uniaxial
test alone (one knot per test stretch, :func:`~.compensation.calibrate_compensation`
without a volume term), it matches that test and under-corrects every other
deformation: in a bulkier body and in shear, more of the load rides on springs
stretched less than the specimen (docs/design/validation.md,
"What the network's errors are, and why"). With the volume term the calibration
fits :math:`g` on uniaxial tension, uniaxial compression and simple shear in two
planes together; this module holds the pieces of that fit.

**Sensitivity.** For a displacement-controlled test with load parameter
:math:`t` at equilibrium, the reaction's power is
:math:`R\,\dot t = \sum_s f_s\,\dot l_s` (+ the volume term's power). A spring
force is :math:`f_s = g(\lambda_s) f^0_s`, so with :math:`\log g` interpolated
linearly between knots (hat functions :math:`b_k`),
:math:`\partial f_s/\partial \log g_k = b_k(\lambda_s) f_s`, and to first order

.. math::  J_{tk} = \frac{\partial \log R_t}{\partial \log g_k}
           \approx \frac{\sum_s b_k(\lambda_s)\, f_s\, \dot l_s}{\sum_s f_s\, \dot l_s},
           \qquad \dot l_s = \hat{\mathbf d}_s \cdot \mathbf L\, \mathbf d_s,

the share of the test's power carried by springs whose stretch lies near knot
:math:`k`. The spring rates use the affine velocity gradient
:math:`\mathbf L = \dot{\mathbf F}\mathbf F^{-1}` of the test (isochoric, so the
volume term's affine power vanishes) at the solved positions, which include
the non-affine relaxation. The rows sum to 1: scaling every spring by
:math:`\alpha` scales the reaction by :math:`\alpha`. The Jacobian is
approximate (the hat basis stands for the smooth interpolation actually
used, and the relaxation's own change is left out); the residual it corrects
comes from real solves, so the fit converges to the real network's answer.

**Weights.** Each test stands for the strain interval up to it, measured by
the von Mises equivalent (Hencky) strain, :math:`|\ln\lambda|` in uniaxial
loading and :math:`\tfrac{2}{\sqrt3}\operatorname{asinh}(\gamma/2)` in simple
shear, times its mode's weight: the axial mode and the two shear planes weigh
1 : 2 : 2 like the scalar factor (the isotropic average of the five deviatoric
modes of a transversely isotropic specimen). The least-squares objective is
therefore the weighted integral of the squared log error over the modes'
strain ranges, not a count of test points.

**Step.** Levenberg-Marquardt (adaptive :math:`\mu`) on :math:`\delta = \Delta\log g`:
:math:`(J^T W J + \mu\,\mathrm{diag}(J^T W J) + \nu D^T D)\,\delta = J^T W y`,
:math:`y = \log(\text{target}/\text{network})`, with a second-difference
smoothing :math:`D` (weight :math:`\nu`: the normal matrix's mean diagonal) that
keeps knots few springs load from oscillating (with :math:`\nu` a thousand times
smaller and :math:`\mu` 0.1, the first step put +25 % and -32 % on neighbouring
knots and the next tensile test found no equilibrium); the knot at
:math:`\lambda = 1` is held (:math:`g(1) = 1`: the scalar factor owns small
strain).
"""

from __future__ import annotations

import math

import numpy as np

from ..network.forcelaw import spring_force_magnitudes

__all__ = ["MODE_WEIGHTS", "equivalent_strain", "gauss_newton_step", "hat_basis", "power_shares",
           "test_weights", "velocity_gradient"]

#: Weight of each mode in the fit (the axial mode, tension and compression, and the two shear planes).
MODE_WEIGHTS = {"tension": 1.0, "compression": 1.0, "xy": 2.0, "xz": 2.0}
#: Levenberg-Marquardt damping to start from (relative to the normal matrix's diagonal; the fit divides
#: it by 3 after a step that lowers the error and multiplies it by 4 after one that does not), and the
#: smoothing (relative to the normal matrix's mean diagonal).
DAMPING = 1.0
SMOOTHING = 1.0


def equivalent_strain(mode: str, amount) -> np.ndarray:
    """Von Mises equivalent Hencky strain of uniaxial stretch (tension, compression) or simple shear (xy, xz)."""
    a = np.asarray(amount, dtype=np.float64)
    if mode in ("tension", "compression"):
        return np.abs(np.log(a))
    return 2.0 / math.sqrt(3.0) * np.arcsinh(a / 2.0)


def test_weights(mode: str, amounts) -> np.ndarray:
    """Each test's weight: its mode's weight times the equivalent-strain interval up to it from the previous test."""
    e = equivalent_strain(mode, amounts)
    return MODE_WEIGHTS[mode] * np.diff(np.concatenate([[0.0], e]))


def velocity_gradient(mode: str, amount: float) -> np.ndarray:
    """L = dF/dt F^-1 per unit load parameter: uniaxial stretch of an incompressible body along z, or simple shear."""
    L = np.zeros((3, 3))
    if mode in ("tension", "compression"):
        lam = float(amount)
        L[0, 0] = L[1, 1] = -0.5 / lam
        L[2, 2] = 1.0 / lam
        return L
    a, b = {"xy": (0, 1), "xz": (0, 2)}[mode]
    L[a, b] = 1.0                      # F = I + gamma e_a e_b: dF F^-1 = e_a e_b (a != b)
    return L


def hat_basis(lam: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """Linear-interpolation weights of *lam* on ascending *knots*, constant beyond the ends, shape (s, k)."""
    k = knots.size
    x = np.clip(lam, knots[0], knots[-1])
    i = np.clip(np.searchsorted(knots, x, side="right") - 1, 0, k - 2)
    t = (x - knots[i]) / (knots[i + 1] - knots[i])
    B = np.zeros((lam.size, k))
    rows = np.arange(lam.size)
    B[rows, i] = 1.0 - t
    B[rows, i + 1] += t
    return B


def power_shares(points: np.ndarray, network, tables, law: str, L: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """Row of the Jacobian (module doc): each knot's share of the springs' power under *L* at *points*, shape (k,)."""
    s = np.asarray(network.springs)
    d = points[s[:, 1]] - points[s[:, 0]]
    length = np.sqrt(np.einsum("ij,ij->i", d, d))
    rate = np.einsum("ij,jk,ik->i", d, L, d) / length
    power = spring_force_magnitudes(points, network, tables, law=law) * rate
    total = float(power.sum())
    if not (math.isfinite(total) and total != 0.0):   # negative in compression: the ratio stands
        return np.zeros(knots.size)
    return hat_basis(length / np.asarray(network.rest_length), knots).T @ power / total


def gauss_newton_step(J: np.ndarray, y: np.ndarray, w: np.ndarray, held: int, *,
                      damping: float = DAMPING) -> np.ndarray:
    """The damped, smoothed least-squares step in log g (module doc); knot *held* does not move.

    *damping* is the Levenberg-Marquardt parameter (relative to the normal matrix's diagonal).
    """
    k = J.shape[1]
    keep = np.arange(k) != held
    Jw = J[:, keep] * w[:, None]
    A = J[:, keep].T @ Jw
    D = np.diff(np.eye(k), 2, axis=0)[:, keep]
    scale = float(np.trace(A)) / max(1, A.shape[0])
    M = A + damping * np.diag(np.diag(A)) + SMOOTHING * scale * (D.T @ D) + 1e-12 * scale * np.eye(A.shape[0])
    step = np.zeros(k)
    step[keep] = np.linalg.solve(M, Jw.T @ y)
    return step
