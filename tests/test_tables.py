"""Stiffness tables: grid, values against the material, exact potentials, HDF5, per-spring tables."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from esmm.pipeline.asset.tables import read_tables, write_per_spring, write_tables
from esmm.pipeline.errors import AssetError, ConfigError, InputError
from esmm.pipeline.materials.loading import nominal_stress
from esmm.pipeline.materials.material import Material
from esmm.pipeline.network.tables import (
    LAWS,
    build_tables,
    per_spring_table,
    spring_factors,
)


def test_grid_covers_compression_and_tension_below_locking(liver, tables):
    lo, hi = liver.stretch_range(None)
    assert lo < tables.lam_min < 0.75 and 1.33 < tables.lam_max < hi
    # stretch 1 is a grid node: both laws give exactly no force at rest
    k = (1.0 - tables.lam_min) / tables.dlam
    assert abs(k - round(k)) < 1e-9
    assert abs(tables.force_function(1.0, law="energy")).max() < 1e-9
    assert np.all(tables.force_function(1.0, law="secant") == 0.0)
    assert tables.isotropic and tables.n == 1024 and tables.default_law == "secant"
    assert np.all(tables.correction == 1.0) and tables.volume_factor == 1.0


def test_interpolated_mu_e_matches_material(liver, tables):
    rng = np.random.default_rng(1)
    lam = rng.uniform(tables.lam_min, tables.lam_max, 400)
    direct = liver.mu_e(lam)
    interp = tables.mu_e(lam)
    assert interp.shape == (3, 400)
    np.testing.assert_allclose(interp[0], direct, rtol=2e-4)
    # nodes are the material's values exactly
    np.testing.assert_allclose(tables.values[0], liver.mu_e(tables.lam), rtol=1e-12)


def test_pinned_mu_e_of_the_paper_liver(tables):
    # E = mu_e(1) of the ESEDF liver fit, and the paper's Fig. 5a reference values
    # mu_e(1.1) ~ 0.029 MPa, mu_e(1.3) ~ 0.123 MPa (docs/design/model.md).
    mu = tables.mu_e(np.array([0.9, 1.0, 1.1, 1.2, 1.3]))[0] / 1e6
    np.testing.assert_allclose(mu, [0.035843, 0.0149231, 0.0291758, 0.0675516, 0.123324], rtol=2e-4)
    assert abs(mu[2] / 0.029 - 1) < 0.01 and abs(mu[4] / 0.123 - 1) < 0.005


def test_stress_and_energy_match_material(liver, tables):
    lam = np.linspace(tables.lam_min + 0.01, tables.lam_max - 0.01, 97)
    P = nominal_stress(liver.model_obj, liver.params, "uniaxial", lam)
    np.testing.assert_allclose(tables.force_function(lam, law="energy")[2], P, rtol=1e-3, atol=1e-3)
    W = liver.uniaxial_energy(lam)
    np.testing.assert_allclose(tables.potential(lam, law="energy")[1], W, rtol=1e-4, atol=1e-6)
    # mu_e = 2 W / (lam - 1)^2 holds between the tabulated energy and mu_e rows
    off = np.abs(tables.lam - 1) > 0.02
    np.testing.assert_allclose(2 * tables.energy[0, off] / (tables.lam[off] - 1) ** 2,
                               tables.values[0, off], rtol=1e-4)


@pytest.mark.parametrize("law", LAWS)
def test_potential_is_exact_integral_of_force(tables, law):
    # inside and outside the grid (0.55, 1.45 are off it); central differences away from the
    # grid ends, where the force has a kink in slope
    lam = np.concatenate([np.linspace(0.55, 1.45, 181), [1.0]])
    lam = lam[(np.abs(lam - tables.lam_min) > 1e-4) & (np.abs(lam - tables.lam_max) > 1e-4)]
    h = 1e-6
    dphi = (tables.potential(lam + h, law=law) - tables.potential(lam - h, law=law)) / (2 * h)
    f = tables.force_function(lam, law=law)
    scale = np.abs(f).max()
    assert np.abs(dphi - f).max() < 1e-6 * scale
    for end in (tables.lam_min, tables.lam_max):  # continuous across the grid ends
        a, b = tables.potential(np.array([end - 1e-10, end + 1e-10]), law=law)[0]
        assert abs(a - b) < 1e-6 * scale * 1e-3
        fa, fb = tables.force_function(np.array([end - 1e-10, end + 1e-10]), law=law)[0]
        assert abs(fa - fb) < 1e-6 * scale
    assert np.all(tables.potential(1.0, law=law) == 0.0)
    # tangent is the derivative of the force (away from grid nodes)
    lam2 = tables.lam_min + (np.arange(5, tables.n - 5, 37) + 0.5) * tables.dlam
    df = (tables.force_function(lam2 + 1e-7, law=law) - tables.force_function(lam2 - 1e-7, law=law)) / 2e-7
    np.testing.assert_allclose(tables.tangent_function(lam2, law=law), df, rtol=1e-5)


def test_out_of_range_rule(tables):
    hi, lo = tables.lam_max, tables.lam_min
    # mu_e held at its end values
    assert np.all(tables.mu_e(hi + 0.2) == tables.values[:, -1])
    assert np.all(tables.mu_e(lo - 0.2) == tables.values[:, 0])
    # stress continued with the end segment's slope (a straight line)
    s = tables.force_function(np.array([hi, hi + 0.1, hi + 0.2]), law="energy")[0]
    slope = (tables.stress[0, -1] - tables.stress[0, -2]) / tables.dlam
    np.testing.assert_allclose(np.diff(s), [0.1 * slope, 0.1 * slope], rtol=1e-9)
    assert slope > 0
    s = tables.force_function(np.array([lo - 0.2, lo - 0.1, lo]), law="energy")[0]
    assert np.diff(s)[0] > 0 and np.isclose(np.diff(s)[0], np.diff(s)[1])


def test_build_tables_options_and_errors(liver):
    t = build_tables(liver, n=101, lam_min=0.8, lam_max=1.3, law="energy")
    assert t.n == 101 and t.lam_min == 0.8 and t.lam_max <= 1.3 and t.default_law == "energy"
    assert t.lam_max > 1.3 - 2 * t.dlam
    with pytest.raises(ConfigError, match="n:"):
        build_tables(liver, n=2)
    with pytest.raises(ConfigError, match="admissible"):
        build_tables(liver, lam_max=1.4)
    with pytest.raises(ConfigError, match="admissible"):
        build_tables(liver, lam_min=0.6)
    with pytest.raises(ConfigError, match="lam_min"):
        build_tables(liver, lam_min=1.2)
    with pytest.raises(ConfigError, match="law"):
        build_tables(liver, law="spring")


def test_anisotropic_material_gives_three_rows(liver):
    mat = Material(model="esedf", params=dict(liver.params), name="aniso",
                   directions={"x": {"A1": 2 * liver.params["A1"]}})
    t = build_tables(mat, n=64)
    assert not t.isotropic
    lam = t.lam
    np.testing.assert_allclose(t.values[0], mat.mu_e(lam, "x"), rtol=1e-12)
    np.testing.assert_allclose(t.values[1], mat.mu_e(lam, "y"), rtol=1e-12)
    assert np.all(t.values[0] > t.values[1])
    np.testing.assert_array_equal(t.values[1], t.values[2])


class _SofteningModel:
    """W(I1) = mu log(I1 - 2): the uniaxial stress falls at large stretch."""

    def dW(self, I1, I2, params):
        w1 = params["mu"] / (np.asarray(I1) - 2.0)
        return w1, 0.0 * w1


class _SofteningMaterial:
    name = "softening test material"
    is_isotropic = True
    model_obj = _SofteningModel()
    params = {"mu": 1000.0}

    def params_for(self, direction=None):
        return self.params

    def stretch_range(self, direction=None):
        return (0.0, np.inf)

    def uniaxial_energy(self, lam, direction=None):
        lam = np.asarray(lam, float)
        return 1000.0 * np.log(lam**2 + 2 / lam - 2)

    def mu_e(self, lam, direction=None):
        lam = np.asarray(lam, float)
        with np.errstate(invalid="ignore", divide="ignore"):
            out = 2 * self.uniaxial_energy(lam) / (lam - 1) ** 2
        return np.where(np.abs(lam - 1) < 1e-9, 3000.0, out)


def test_softening_material_narrows_the_default_grid_and_refuses_a_given_one():
    # P = W' of W = mu ln(lam^2 + 2/lam - 2) peaks where d/dlam[(2 lam - 2/lam^2)/(lam^2 + 2/lam - 2)] = 0
    lam = np.linspace(1.0, 2.0, 200001)
    p = (2 * lam - 2 / lam**2) / (lam**2 + 2 / lam - 2)
    peak = lam[np.argmax(p)]
    t = build_tables(_SofteningMaterial(), n=200)
    assert np.all(np.diff(t.stress[0]) > 0)
    assert peak - 0.05 < t.lam_max < peak       # ends just inside the peak, not at the default 2
    grid = t.metadata["grid"]
    assert "stops increasing" in grid["why"]["lam_max"] and "stops increasing" in grid["warning"]
    assert grid["why"]["lam_min"].startswith("the bound 0.5")
    with pytest.raises(InputError, match="stops increasing"):     # a grid the user gave is not changed
        build_tables(_SofteningMaterial(), n=200, lam_min=0.5, lam_max=2.0)
    t = build_tables(_SofteningMaterial(), n=50, lam_min=0.8, lam_max=1.2)   # a given grid where it stiffens
    assert np.all(np.diff(t.stress[0]) > 0) and t.metadata["grid"]["why"] == {"lam_min": "given",
                                                                               "lam_max": "given"}


#: The fit of the Budday et al. (2017) basal ganglia data that ``esmm calibrate --by specimen`` writes
#: (params.toml, in MPa): the chain count N at 2e7 puts the locking stretch at about 7 900.
BRAIN_FIT = {"mu": 1.6129306952624201e-15 * 1e6, "N": 20727568.702826597, "A1": 0.49506550023784673e6,
             "A2": 15.834950390136049e6, "f": 0.0019}


def test_a_lock_far_beyond_the_tissue_ends_the_grid_at_stretch_2():
    """A fit whose locking stretch lies thousands away gets the grid [0.5, 2]: fine enough to calibrate
    the compensation near 1 (the grid to its lock left no point between 1 and 1.3)."""
    from esmm.pipeline.compensation.calibration import calibration_stretches

    brain = Material(model="esedf", params=BRAIN_FIT, name="brain fit")
    assert brain.stretch_range(None)[1] > 5000
    t = build_tables(brain)
    assert t.lam_min == 0.5 and 1.99 < t.lam_max <= 2.0 and t.dlam < 0.0015
    assert "locks only at 7886" in t.metadata["grid"]["why"]["lam_max"]
    assert "warning" not in t.metadata["grid"]
    assert calibration_stretches(t) == (0.9, 1.3)
    np.testing.assert_allclose(t.stress[0], nominal_stress(brain.model_obj, brain.params_for(None), "uniaxial",
                                                           t.lam), rtol=1e-12)


def test_a_lock_inside_the_bounds_still_ends_the_grid(liver, tables):
    lo, hi = liver.stretch_range(None)
    assert hi < 2.0 and tables.lam_max == pytest.approx(hi - 0.02 * (hi - 1), rel=1e-3)
    assert tables.metadata["grid"]["why"]["lam_max"].startswith("2% inside the material's locking stretch")


def test_compensation_rows_and_material_recovery(tables):
    g = 1.0 + 0.5 * (tables.lam - 1.0) ** 2
    t = tables.with_compensation(6.0, correction={"secant": g}, record={"note": "test"})
    assert t.volume_factor == 6.0 and t.is_corrected("secant") and not t.is_corrected("energy")
    np.testing.assert_allclose(t.values, tables.values * g, rtol=1e-15)
    np.testing.assert_allclose(t.material_values, tables.values, rtol=1e-14)
    np.testing.assert_array_equal(t.stress, tables.stress)
    lam = np.array([0.8, 1.2])
    np.testing.assert_allclose(t.mu_e(lam), tables.mu_e(lam), rtol=1e-12)
    assert t.metadata["compensation"] == {"note": "test"}
    back = t.without_compensation()
    np.testing.assert_allclose(back.values, tables.values, rtol=1e-14)
    assert back.volume_factor == 1.0 and "compensation" not in back.metadata
    with pytest.raises(ValueError, match="correction"):
        tables.with_compensation(2.0, correction={"secant": -g})


def test_hdf5_round_trip(tmp_path, tables):
    g = np.linspace(0.9, 1.4, tables.n)
    t = tables.with_compensation(5.5, correction={"energy": g}, record={"law": "energy", "x": [1, 2]})
    path = tmp_path / "t.h5"
    with h5py.File(path, "w") as f:
        write_tables(f.create_group("tables"), t)
    with h5py.File(path, "r") as f:
        grp = f["tables"]
        assert grp.attrs["esmm_type"] == "stiffness_tables" and grp.attrs["esmm_version"] == 1
        assert grp["mu_e"].attrs["units"] == "Pa" and grp["lam"].shape == (tables.n,)
        assert "porcine liver" in grp.attrs["material_toml"]
        back = read_tables(grp)
    for name in ("values", "stress", "energy", "correction"):
        np.testing.assert_array_equal(getattr(back, name), getattr(t, name))
    assert back.volume_factor == 5.5 and back.metadata["compensation"]["x"] == [1, 2]
    assert (back.lam_min, back.lam_max, back.n) == (t.lam_min, t.lam_max, t.n)
    # a material read back from the TOML text is the same material
    np.testing.assert_allclose(back.material_stress, tables.stress, rtol=1e-13)
    # rewriting over an existing group works
    with h5py.File(path, "a") as f:
        write_tables(f["tables"], tables)
        assert read_tables(f["tables"]).volume_factor == 1.0


def test_hdf5_errors(tmp_path, tables):
    path = tmp_path / "bad.h5"
    with h5py.File(path, "w") as f:
        write_tables(f.create_group("a"), tables)
        f["a"].attrs["esmm_version"] = 99
        write_tables(f.create_group("b"), tables)
        del f["b"]["stress"]
        f.create_group("c").attrs["esmm_type"] = "network"
    with h5py.File(path, "r") as f:
        with pytest.raises(AssetError, match="version 99"):
            read_tables(f["a"])
        with pytest.raises(AssetError, match="damaged"):
            read_tables(f["b"])
        with pytest.raises(AssetError, match="not a stiffness-table group"):
            read_tables(f["c"])


class _Net:
    def __init__(self, s, rng):
        self.volume_weight = rng.uniform(1e-4, 1e-3, s)
        c = rng.uniform(0, 1, (s, 3))
        self.cos2 = c / c.sum(axis=1, keepdims=True)
        self.rest_length = rng.uniform(1e-3, 3e-3, s)


def test_per_spring_table_and_chunked_write(tmp_path, tables):
    rng = np.random.default_rng(3)
    net = _Net(1000, rng)
    t = tables.with_compensation(6.2)
    a = spring_factors(t, net)
    np.testing.assert_allclose(a, 6.2 * net.volume_weight[:, None] * net.cos2)
    k = per_spring_table(t, net)
    assert k.shape == (1000, t.n) and k.dtype == np.float32
    j = 400
    np.testing.assert_allclose(k[:, j], a @ t.values[:, j], rtol=1e-6)
    path = tmp_path / "k.h5"
    with h5py.File(path, "w") as f:
        write_per_spring(f, t, net, chunk_springs=300)
    with h5py.File(path, "r") as f:
        ds = f["k_per_spring"]
        assert ds.shape == (1000, t.n) and ds.compression == "gzip" and ds.chunks is not None
        assert ds.chunks[0] * ds.chunks[1] * 4 <= 1 << 18
        assert ds.attrs["units"] == "N/m" and ds.attrs["volume_factor"] == 6.2
        np.testing.assert_array_equal(ds[()], k)
