"""Shared fixtures' builders: stiffness tables from closed forms for the simulator's tests
(tests/test_simulate.py, test_implicit.py), and a jittered box's spring network (the volume term's and the
corrections' tests).

Importable because pytest's ``pythonpath`` includes ``tests/``.
"""

from __future__ import annotations

import numpy as np
from esmm.pipeline.mesh.synthetic import box_tets
from esmm.pipeline.network.springs import network_from_tets, tet_volumes
from esmm.pipeline.network.tables import StiffnessTables


def jittered_box_network(cells, size, *, jitter: float, seed: int):
    """The spring network of a structured box (*cells* along x, y, z; edges *size* [m]; 6 Kuhn tets per
    cell) whose nodes are moved by uniform draws within ±*jitter* [m] (generator seeded *seed*), every
    tetrahedron oriented positive."""
    b = box_tets(*cells, size)
    rng = np.random.default_rng(seed)
    p = b.points + rng.uniform(-jitter, jitter, b.points.shape)
    t = b.tets.copy()
    v = tet_volumes(p, t)
    t[v < 0] = t[v < 0][:, [0, 2, 1, 3]]
    return network_from_tets(type("M", (), {"points": p, "tets": t})())


def make_tables(kind="nonlinear", lo=0.5, hi=2.0, n=301, mu0=2.0e4):
    """Tables from closed forms; the grid contains lambda = 1 exactly (n = 301 on [0.5, 2]).

    *kind*: "constant" (linear springs), "linear" (mu linear in lambda: linear
    interpolation is exact), "nonlinear" (stiffening, different per direction) or
    "stiffening" (the nonlinear x row in all three directions: isotropic).
    """
    lam = np.linspace(lo, hi, n)
    if kind == "constant":
        mu = np.full((3, n), mu0)
    elif kind == "linear":
        mu = np.vstack([mu0 * (1 + 0.5 * (lam - 1)), mu0 * (1.2 + 0.3 * (lam - 1)), mu0 * (0.8 + 0.9 * (lam - 1))])
    else:
        rows = [mu0 * (1 + 4 * (lam - 1) ** 2), mu0 * (1.3 + 2 * (lam - 1) ** 2),
                mu0 * (0.9 + (lam - 1) ** 2 + 6 * (lam - 1) ** 4)]
        mu = np.vstack([rows[0]] * 3 if kind == "stiffening" else rows)
    stress = mu * (lam - 1)
    h = lam[1] - lam[0]
    energy = np.concatenate([np.zeros((3, 1)), np.cumsum(0.5 * (stress[:, 1:] + stress[:, :-1]) * h, axis=1)], axis=1)
    energy -= energy[:, [int(round((1 - lo) / h))]]
    return StiffnessTables(lam_min=lo, lam_max=hi, n=n, values=mu, stress=stress, energy=energy)
