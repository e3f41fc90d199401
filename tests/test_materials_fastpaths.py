"""The fast paths of the material evaluation compute what the plain forms compute, bit for bit.

The discovery's fit evaluates the elastic law and the QLV recursion thousands of
times on the same samples; what it reuses (the path's kinematics, the QLV
factors) and what is compiled (the inverse Langevin's and the recursion's
loops) must give the numbers the straightforward evaluation gives, to the last
bit, so that a fit's path does not depend on them.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from esmm.pipeline.materials import get_model
from esmm.pipeline.materials.base import broadcast_zeros
from esmm.pipeline.materials.effects import qlv_decay, qlv_stress
from esmm.pipeline.materials.loading import MODES, energy_density, nominal_stress, path_kinematics


def _qlv_reference(t, pe, g, tau):
    """The QLV recursion as one plain loop (the module docstring's update, exp and expm1 of the C library)."""
    n, m = len(t), len(g)
    ginf = 1.0 - float(np.sum(g))
    h = [pe[0]] * m
    out = [pe[0]]
    for k in range(1, n):
        dt, dp = t[k] - t[k - 1], pe[k] - pe[k - 1]
        acc = ginf * pe[k]
        for i in range(m):
            if dt > 0.0:
                x = dt / tau[i]
                b = -math.expm1(-x) / x if x > 1e-12 else 1.0 - 0.5 * x
                h[i] = math.exp(-x) * h[i] + b * dp
            else:
                h[i] = h[i] + dp
            acc += g[i] * h[i]
        out.append(acc)
    return np.array(out)


def test_qlv_recursion_gives_the_plain_loops_bits_and_reuses_its_factors():
    rng = np.random.default_rng(3)
    t = np.sort(rng.uniform(0.0, 50.0, 400))
    t[100:103] = t[100]  # repeated times (no advance)
    t[200] = t[199] + 1e-14  # an advance with Δ/τ below 1e-12
    pe = np.cumsum(rng.standard_normal(t.size)) * 1e3
    g, tau = np.array([0.3, 0.25, 0.1]), np.array([0.05, 2.0, 40.0])
    ref = _qlv_reference(t, pe, g, tau)
    got = qlv_stress(t, pe, g, tau)
    assert np.array_equal(got, ref)
    decay = qlv_decay(t, tau)
    for pe2 in (pe, 2.0 * pe + 1.0):
        assert np.array_equal(qlv_stress(t, pe2, g, tau, decay=decay), qlv_stress(t, pe2, g, tau))
    p, h = qlv_stress(t, pe, g, tau, return_state=True)
    assert h.shape == (3,) and np.array_equal(p, ref)


@pytest.mark.parametrize("model", ["esedf", "arruda-boyce", "esedf+i2exp+toe+mooney", "esedf+gent+i2log"])
@pytest.mark.parametrize("mode", MODES)
def test_stress_and_energy_on_a_kept_path_are_the_plain_ones(model, mode):
    m = get_model(model)
    params = m.defaults()
    params.update({"mu": 3e4, "N": 6.0, "A1": 1e4, "A2": 5e4, "f": 0.3})
    x = np.linspace(-0.4, 0.4, 97) if mode == "simple_shear" else np.linspace(0.7, 1.6, 97)
    kin = path_kinematics(mode, x)
    with np.errstate(all="ignore"):
        assert np.array_equal(nominal_stress(m, params, mode, x, kinematics=kin), nominal_stress(m, params, mode, x),
                              equal_nan=True)
        assert np.array_equal(energy_density(m, params, mode, x, kinematics=kin), energy_density(m, params, mode, x),
                              equal_nan=True)


def test_broadcast_zeros_has_the_broadcast_shape():
    assert broadcast_zeros(np.ones(5), np.ones(5)).shape == (5,)
    assert broadcast_zeros(np.ones((4, 1)), np.ones(3)).shape == (4, 3)
    assert broadcast_zeros(3.0, np.ones(2)).shape == (2,)
    assert broadcast_zeros(3.0, 3.0).shape == ()


@pytest.mark.parametrize("model", ["esedf", "arruda-boyce", "esedf+mooney+i2exp+i1exp+yeoh",
                                   "esedf+gent+i2log+fibreexp+toe", "arruda-boyce+toe+gent"])
@pytest.mark.parametrize("mode", MODES)
def test_parameter_arrays_give_each_rows_scalar_result(model, mode):
    """array_parameters: m parameter sets as (m, 1) arrays give, row by row, the scalar parameters' stress."""
    m = get_model(model)
    assert m.array_parameters
    rng = np.random.default_rng(11)
    base = m.defaults()
    base.update({"mu": 3e4, "N": 6.0, "A1": 1e4, "A2": 5e4, "f": 0.3})
    sets = []
    for j in range(6):
        p = {k: v * (1.0 + 0.1 * rng.standard_normal()) for k, v in base.items()}
        p["N"] = base["N"] * (1.0 + 0.05 * j)
        sets.append(p)
    if "mu" in base and "f" in base:
        sets[2]["mu"] = 0.0  # a row without the matrix term (ESEDF), beside rows with it
        sets[3]["f"] = 1.0
    x = np.linspace(-0.4, 0.4, 97) if mode == "simple_shear" else np.linspace(0.7, 1.6, 97)
    stacked = {k: np.array([p[k] for p in sets])[:, None] for k in base}
    kin = path_kinematics(mode, x)
    with np.errstate(all="ignore"):
        rows = nominal_stress(m, stacked, mode, x, kinematics=kin)
        each = np.stack([nominal_stress(m, p, mode, x) for p in sets])
    assert rows.shape == (6, x.size)
    assert np.array_equal(rows, each, equal_nan=True)
    assert np.isfinite(each).sum() > 0.5 * each.size
