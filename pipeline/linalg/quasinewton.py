r"""Limited-memory BFGS on the implicit step's residual, with the reused factor as its first inverse.

The implicit step solves :math:`\mathbf g(\mathbf x) = 0` (:mod:`esmm.pipeline.simulate.implicit_system`).
Newton's iteration with conjugate gradients costs, per update, a tangent
assembly and several products and preconditioner solves. The quasi-Newton
iteration (Liu, Bouaziz & Kavan 2017, "Quasi-Newton methods for real-time
simulation of hyperelastic materials", ACM TOG 36(3)) takes one solve with
the reused factor :math:`P` and one residual per iteration, and learns the
curvature :math:`P` misses from the residuals' changes:

.. math::

    \mathbf d_k = -H_k \mathbf g_k, \qquad
    H_{k+1} = V_k^T H_k V_k + \rho_k \mathbf s_k \mathbf s_k^T, \quad
    V_k = I - \rho_k \mathbf y_k \mathbf s_k^T, \quad
    \rho_k = 1/(\mathbf y_k^T \mathbf s_k),

:math:`\mathbf s_k = \mathbf x_{k+1} - \mathbf x_k`,
:math:`\mathbf y_k = \mathbf g_{k+1} - \mathbf g_k`, :math:`H_0 = \Pi`
the constrained preconditioner (factor and capacitance,
:class:`~.linsolve.Constraints`), the last *m* pairs kept (Nocedal & Wright
2006, Algorithm 7.4: the two-loop recursion). :math:`H_{k+1}` satisfies the
secant equation :math:`H_{k+1}\mathbf y_k = \mathbf s_k`; on a quadratic
with :math:`H_0 = A^{-1}` the first direction is Newton's.

The step length along :math:`\mathbf d` is chosen from the residual alone
(the step's incremental potential is not evaluated; with the dashpots the
residual is not exactly a gradient): :math:`\varphi'(s) = \mathbf g(\mathbf
x + s\mathbf d)\cdot\mathbf d`, and the step is the zero of the secant
through :math:`\varphi'(0)` and :math:`\varphi'(1)` (:func:`secant_step`;
exact on a quadratic): shorter than the direction where the full step
overshoots, longer where it still descends. The residual at that step is the
secant's model of it, not a second force pass, except where a decision rests
on it (:class:`esmm.pipeline.simulate.implicit_iteration.QuasiNewton`). The longer step matters: with the
volume term's bound in the factor (:math:`P \succeq A` on the volume part) the
direction is much shorter than Newton's update, and both the iteration's speed
and its stopping test (the update's length) need the step Newton would take.
docs/design/simulator.md, "The iteration: quasi-Newton on a reused factor", has the
fallback to Newton.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

#: Pairs kept (Liu et al. 2017 keep 5-7; not varied: a solve rarely takes as many iterations).
MEMORY = 8
#: Shortest step the secant rule takes, as a fraction of the direction.
MIN_STEP = 0.1


@dataclass
class LBFGSMemory:
    """The last *memory* curvature pairs ``(s, y, 1/y.s)`` of one solve."""

    memory: int = MEMORY
    pairs: list = field(default_factory=list)

    def clear(self) -> None:
        self.pairs.clear()

    def __len__(self) -> int:
        return len(self.pairs)

    def direction(self, b: np.ndarray, h0: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """``H b`` by the two-loop recursion (*b* = minus the residual; *h0* applies the first inverse)."""
        q = np.array(b, dtype=np.float64, copy=True)
        alphas = []
        for s, y, rho in reversed(self.pairs):
            a = rho * float(s @ q)
            alphas.append(a)
            q -= a * y
        r = h0(q)
        for (s, y, rho), a in zip(self.pairs, reversed(alphas)):
            r += s * (a - rho * float(y @ r))
        return r

    def project(self, project: Callable[[np.ndarray], np.ndarray]) -> None:
        """Each pair's step *s* replaced by ``project(s)`` (into new constraints' null space), its
        curvature recomputed; the pairs whose curvature is then no longer positive forgotten."""
        kept = []
        for s, y, _ in self.pairs:
            s = project(s)
            sy = float(s @ y)
            if sy > 1e-12 * float(np.linalg.norm(s) * np.linalg.norm(y)):
                kept.append((s, y, 1.0 / sy))
        self.pairs = kept

    def update(self, s: np.ndarray, y: np.ndarray) -> bool:
        """Keep the pair when its curvature is positive (``y.s > 1e-12 |y||s|``); whether it was kept."""
        sy = float(s @ y)
        if not sy > 1e-12 * float(np.linalg.norm(s) * np.linalg.norm(y)):
            return False
        self.pairs.append((s, y, 1.0 / sy))
        if len(self.pairs) > self.memory:
            self.pairs.pop(0)
        return True


def secant_step(dphi0: float, dphi1: float, *, max_step: float) -> float:
    """The step along a direction from the residual's slopes ``phi'(0) < 0`` and ``phi'(1)``.

    The zero of the secant through them, ``phi'(0) / (phi'(0) - phi'(1))`` (the
    minimum along the direction on a quadratic): below 1 when the full step
    overshoots (``phi'(1) > 0``; at least :data:`MIN_STEP`), beyond 1 when it
    still descends (at most *max_step*; *max_step* too when the slope did not
    rise), 1 when ``phi'(1) = 0``.
    """
    if dphi1 == 0.0:
        return 1.0
    if dphi1 > 0.0:
        return float(min(1.0, max(MIN_STEP, dphi0 / (dphi0 - dphi1))))
    if dphi1 <= dphi0:
        return float(max_step)
    return float(min(max_step, dphi0 / (dphi0 - dphi1)))
