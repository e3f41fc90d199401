"""Virtual tensile test of the spring network and its volumetric compensation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from esmm.pipeline.compensation.calibration import calibrate_compensation
from esmm.pipeline.compensation.virtual_tensile import (
    continuum_stress,
    cylinder_specimen,
    virtual_tensile_test,
)
from esmm.pipeline.errors import ConfigError
from esmm.pipeline.network.forcelaw import spring_forces
from esmm.pipeline.network.springs import affine_elasticity, engineering_constants
from esmm.pipeline.progress import ListReporter


@pytest.fixture(scope="module")
def specimen():
    return cylinder_specimen(radius=5e-3, length=20e-3, size=2.5e-3)


def test_specimen_geometry(specimen):
    X = specimen.network.points
    assert np.allclose(X[specimen.centre], 0.0, atol=1e-12)
    assert np.allclose(X[specimen.rim], [5e-3, 0.0, 0.0], atol=1e-12)
    assert np.all(np.abs(X[specimen.bottom, 2]) < 1e-12)
    assert np.allclose(X[specimen.top, 2], 20e-3)
    # polygonal section: a little below pi R^2
    assert 0.96 * math.pi * 25e-6 < specimen.area <= math.pi * 25e-6
    assert 100 < specimen.n_nodes < 600 and specimen.bottom.size >= 10
    assert specimen.network.problems() == []
    d = specimen.describe()
    assert d["nodes"] == specimen.n_nodes and d["size_m"] == 2.5e-3


def test_specimen_option_errors():
    with pytest.raises(ConfigError, match="size"):
        cylinder_specimen(radius=1e-3, size=2e-3)
    with pytest.raises(ConfigError, match="radius"):
        cylinder_specimen(radius=-1.0)
    with pytest.raises(ConfigError, match="nodes"):
        cylinder_specimen(size=1e-5)


def test_small_strain_modulus_below_the_affine_bound(liver, tables, specimen):
    """The relaxed network is softer than its affine (Cauchy-Born) bound, and close to it."""
    eps = 1e-4
    res = virtual_tensile_test(specimen, tables, stretch=[1 + eps], law="secant")
    E_net = res.stress[0] / eps
    E = liver.youngs_modulus()
    e_aff, nu_aff = engineering_constants(affine_elasticity(specimen.network, modulus=E))
    assert E_net <= e_aff[2] * 1.001
    assert E_net >= 0.85 * e_aff[2]
    # an isotropic edge set with V_ij = sum V_t / 6 has the affine modulus E/6 (Poisson 1/4)
    assert 0.13 < E_net / E < 0.19
    assert 0.2 < nu_aff[2, 0] < 0.3
    # and the lateral contraction follows the network's own Poisson ratio, not 1/2
    lat = 1 - res.lateral_stretch[0]
    assert 0.15 * eps < lat < 0.35 * eps


def test_equilibrium_reactions_and_path_independence(tables, specimen):
    one = virtual_tensile_test(specimen, tables, stretch=[1.2], law="energy")
    many = virtual_tensile_test(specimen, tables, stretch=np.linspace(1.02, 1.2, 10), law="energy")
    assert one.residual < 1e-8 and many.residual < 1e-8
    assert one.stress[0] == pytest.approx(many.stress[-1], rel=1e-6)
    f = spring_forces(one.points, specimen.network, tables, law="energy")
    top = -f[specimen.top, 2].sum()
    bottom = f[specimen.bottom, 2].sum()
    assert top == pytest.approx(bottom, rel=1e-8)
    assert top / specimen.area == pytest.approx(one.stress[0], rel=1e-12)
    # free (lateral) components are in equilibrium
    inner = np.setdiff1d(np.arange(specimen.n_nodes),
                         np.concatenate([specimen.bottom, specimen.top]))
    assert np.abs(f[inner]).max() < 1e-7 * np.abs(f).max()
    # the grips moved the top face to lam * H
    assert np.allclose(one.points[specimen.top, 2], 1.2 * specimen.length)


def test_compression_and_reference(liver, tables, specimen):
    res = virtual_tensile_test(specimen, tables, stretch=[0.97, 0.94], law="secant", material=liver)
    assert np.all(res.stress < 0) and np.all(res.reference < 0)
    np.testing.assert_allclose(res.reference, continuum_stress(liver, [0.97, 0.94]))
    # without compensation the network is several times softer than the tissue
    assert np.all(res.rel_error > 0.7)


def test_stretch_option_errors(tables, specimen):
    with pytest.raises(ConfigError, match="monotonically"):
        virtual_tensile_test(specimen, tables, stretch=[1.1, 1.05])
    with pytest.raises(ConfigError, match="monotonically"):
        virtual_tensile_test(specimen, tables, stretch=[0.9, 1.1])
    with pytest.raises(ConfigError, match="stretch"):
        virtual_tensile_test(specimen, tables, stretch=[])


@pytest.mark.slow
def test_compensation_brings_the_coarse_network_within_5_percent(liver, tables, specimen):
    rep = ListReporter()
    comp, result = calibrate_compensation(tables, specimen, law="secant", material=liver, reporter=rep)
    # uncompensated: the network carries a small fraction of the tissue's stress
    assert result.before.max_abs_rel_error > 0.8
    assert result.scalar.max_abs_rel_error > 0.3
    assert result.after.max_abs_rel_error < 0.02
    assert 5.5 < result.factor < 7.5
    assert comp.volume_factor == result.factor and comp.is_corrected("secant")
    assert not comp.is_corrected("energy")
    rec = comp.metadata["compensation"]
    assert rec["laws"]["secant"]["errors_after"]["max_abs_rel_error"] < 0.02
    assert rec["volume_factor"] == result.factor
    # between the calibration stretches too (odd hundredths are not knots)
    check = virtual_tensile_test(specimen, comp, stretch=[1.05, 1.15, 1.25, 1.29], law="secant",
                                 material=liver)
    assert check.max_abs_rel_error < 0.05
    check = virtual_tensile_test(specimen, comp, stretch=[0.99, 0.95, 0.91], law="secant",
                                 material=liver)
    assert check.max_abs_rel_error < 0.05
    assert any("scalar factor" in s for s in rep.steps)


def test_correction_on_grid_is_smooth_monotone_and_flat_beyond(tables):
    from esmm.pipeline.compensation.calibration import correction_on_grid

    knots = [0.9, 0.95, 1.0, 1.1, 1.2, 1.3]
    g = [3.0, 1.6, 1.0, 1.9, 2.3, 2.25]
    out = correction_on_grid(tables, knots, g)
    lam = tables.lam
    np.testing.assert_allclose(np.interp(knots, lam, out), g, rtol=2e-3)
    assert np.all(out[lam <= 0.9 - 0.05] == out[0]) and np.all(out[lam >= 1.3 + 0.1] == out[-1])
    assert out[0] == pytest.approx(3.0) and out[-1] == pytest.approx(2.25)
    # monotone between monotone knots, no overshoot
    seg = (lam > 0.9) & (lam < 1.0)
    assert np.all(np.diff(out[seg]) <= 0)
    assert out.max() <= 3.0 + 1e-12 and out[(lam > 1.2) & (lam < 1.3)].max() <= 2.3 + 1e-12
    # C1: no jump of the slope anywhere (a piecewise-linear g would jump at the knots)
    slope = np.diff(out) / tables.dlam
    lin_slopes = np.diff(g) / np.diff(knots)
    lin_jump = np.abs(np.diff(lin_slopes)).max()          # what a piecewise-linear g would have
    assert np.abs(np.diff(slope)).max() < 0.2 * lin_jump
