"""How fast a true Newton iteration converges at the steps after the grasper lets go, per tangent.

docs/design/realtime.md ("Where the split's step still goes: the release") reads its figures from
this script. It runs the default scene without its bed (the release's contacts apart) on an asset
and, at each step named, before the stepper's own solve, solves the step's system by Newton's
iteration from the same predictor: the matrix ``M/h^2 + (alpha M + C)/h + K(x)`` taken at every
iterate, a direct LU solve, a halving line search on the residual's norm. Four tangents:
the springs made definite or not, the volume term's pressure stiffness kept or not. It prints the
residual's norm at each iterate, the smallest eigenvalue of the full matrix, and the stepper's own
quasi-Newton iterations on that step::

    python scripts/release_newton.py ASSET.h5 61,62

(the default scene: 90 steps of 1/30 s, the grasper lets go after step 59). The grasp is off at
those steps, so the step's only constraints are the fixed nodes (their rows the identity).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np
import scipy.sparse.linalg as sla
from esmm.pipeline.asset import read_asset
from esmm.pipeline.simulate.implicit_iteration import StepSolver
from esmm.pipeline.simulate.run import simulate_network
from esmm.pipeline.simulate.scene import load_scene
from esmm.pipeline.simulate.volumeterm import VolumeTerm

#: (label, springs definite, the volume term's pressure stiffness kept)
TANGENTS = (("both dropped", True, False), ("springs kept", False, False),
            ("pressure kept", True, True), ("both kept", False, True))


def newton(system, x: np.ndarray, *, definite: bool, tol: float, max_its: int = 40) -> list[float]:
    """The residual norms of Newton's iteration from *x* on *system* with the tangent *definite* says."""
    tangent_of = dataclasses.replace(system, definite=definite)
    _, g = system.residual(x)
    norms = [system.norm(g)]
    while norms[-1] > tol and len(norms) <= max_its:
        b = -g.ravel().copy()
        b[system.fixed_dof] = 0.0
        dx = sla.spsolve(tangent_of.matrix(x, bound=False).tocsc(), b).reshape(-1, 3)
        s = 1.0
        for _ in range(8):
            xt = x + s * dx
            _, gt = system.residual(xt)
            nt = system.norm(gt)
            if nt < norms[-1]:
                break
            s *= 0.5
        x, g = xt, gt
        norms.append(nt)
    return norms


def probe(system, x: np.ndarray, tol: float) -> list[str]:
    """One line per tangent (:data:`TANGENTS`) and one for the full matrix's smallest eigenvalue."""
    lines = []
    exact = VolumeTerm.tangent
    try:
        for label, definite, pressure in TANGENTS:
            VolumeTerm.tangent = (lambda self, y, v=None, *, definite=False, _p=pressure:
                                  exact(self, y, v, definite=not _p))
            norms = newton(system, x.copy(), definite=definite, tol=tol)
            lines.append(f"  {label}: {len(norms) - 1} iterations, " + " ".join(f"{v:.2g}" for v in norms))
        VolumeTerm.tangent = exact
        A = dataclasses.replace(system, definite=False).matrix(x, bound=False)
        low = sla.eigsh(A, k=1, sigma=-1e9, which="LM", return_eigenvectors=False)[0]
        lines.append(f"  full matrix: smallest eigenvalue {low:.4g}; mass term's diagonal at most "
                     f"{float(np.max(system.mass_dof)):.3g}")
    finally:
        VolumeTerm.tangent = exact
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("asset", type=Path)
    ap.add_argument("steps", help="comma-separated step indices (0-based)")
    args = ap.parse_args(argv)
    steps = {int(s) for s in args.steps.split(",")}
    asset = read_asset(args.asset)
    scene = dataclasses.replace(load_scene("default"), floor=None)
    solve, count = StepSolver.solve, [0]

    def probed(self, system, x):
        k = count[0]
        count[0] += 1
        if k not in steps:
            return solve(self, system, x)
        tol, _ = system.tolerances(self.rtol, self.xtol)
        print(f"step {k}:", *probe(system, x, tol), sep="\n")
        before = self.stats.quasi_newton
        out = solve(self, system, x)
        print(f"  the stepper's quasi-Newton iterations: {self.stats.quasi_newton - before}")
        return out

    StepSolver.solve = probed
    try:
        with tempfile.TemporaryDirectory() as d:
            simulate_network(asset.network, asset.tables, scene, Path(d) / "run")
    finally:
        StepSolver.solve = solve
    return 0


if __name__ == "__main__":
    sys.exit(main())
