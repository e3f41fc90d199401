"""The discovery's building blocks beyond the loop: the new material effects and their record, what a
record shows (noise, ruptures, slips, a reading at rest), and the two selection statistics."""

from __future__ import annotations

import json

import numpy as np
import pytest
from esmm.pipeline.discover import synthetic as syn
from esmm.pipeline.discover.records import prepare, rest_reading
from esmm.pipeline.discover.statistics import (
    HeldoutSegment,
    autocorrelation_time,
    heldout_test,
    noise_test,
)
from esmm.pipeline.errors import ConfigError
from esmm.pipeline.materials.effects import (
    CyclicSofteningEffect,
    DamageEffect,
    MaterialEffects,
    PermanentSetEffect,
    ViscoelasticEffect,
    accumulated_energy,
    cyclic_factor,
    damage_factor,
    qlv_stress,
    relaxation_strength,
    set_stretch,
)
from esmm.pipeline.tensile import read
from esmm.pipeline.tensile.events import noise_sd
from scipy import signal

BASE = {"mu": 20e3, "N": 4.0}


# --------------------------------------------------------------------------- effects
def test_cyclic_softening_grows_with_cycles_and_saturates():
    W = np.tile(np.concatenate([np.linspace(0, 100, 50), np.linspace(100, 0, 50)]), 6)
    alpha = accumulated_energy(W)
    assert alpha[-1] == pytest.approx(6 * 200, rel=1e-2)
    f = cyclic_factor(alpha, 0.3, 150.0)
    peaks = f[49::100]
    assert np.all(np.diff(peaks) < 0) and peaks[-1] > 0.7 - 1e-9  # softer every cycle, never beyond d_inf
    assert cyclic_factor(np.array([0.0]), 0.3, 150.0)[0] == 1.0


def test_set_stretch_and_relaxation_strength():
    np.testing.assert_allclose(set_stretch(np.array([1.0, 1.5, 3.0]), 0.2), [1.0, 1.1, 1.4])
    s = relaxation_strength(np.array([1.0, 1.1, 1.5]), -2.0, 0.5)
    np.testing.assert_allclose(s, np.exp(-2.0 * np.array([0.0, 0.1, 0.5])))
    assert relaxation_strength(np.array([2.0]), 5.0, 0.5)[0] == pytest.approx(2.0)  # capped at 1 / sum g


def test_stretch_dependent_relaxation_reduces_to_qlv_and_scales_the_relaxed_part():
    t = np.linspace(0, 20, 401)
    lam = np.minimum(1 + 0.1 * t, 1.5)
    pe = 1e4 * (lam - 1)
    qlv = qlv_stress(t, pe, [0.4], [3.0])
    np.testing.assert_allclose(ViscoelasticEffect((0.4,), (3.0,)).stress(t, pe), qlv)
    v = ViscoelasticEffect((0.4,), (3.0,), kappa=-1.0)
    p = v.stress(t, pe, xi=lam)
    np.testing.assert_allclose(pe - p, np.exp(-(lam - 1)) * (pe - qlv), rtol=1e-12, atol=1e-9)
    with pytest.raises(ConfigError, match="xi"):
        v.stress(t, pe)


def test_material_effects_record_new_fields_round_trip_and_old_records_read():
    me = MaterialEffects(ViscoelasticEffect((0.3,), (2.0,), kappa=-4.0), None, None, {},
                         CyclicSofteningEffect(0.2, 150.0), PermanentSetEffect(0.1))
    assert MaterialEffects.from_dict(json.loads(json.dumps(me.to_dict()))) == me
    back = MaterialEffects.from_toml_table(me.to_toml_table(stress_unit="kPa"), stress_unit="kPa")
    assert back.cyclic_softening.eta == pytest.approx(150.0) and back.viscoelastic.kappa == -4.0
    assert {"prony_h", "xi_max", "alpha"} == set(me.state_variables())
    # a record written before these effects existed reads unchanged (no kappa, the old composition)
    old = {"schema": "esmm.material-effects/1", "composition": "P = QLV[(1 - D) * eta * P_e]",
           "viscoelastic": {"g": [0.4], "tau": [3.0], "g_inf": 0.6}, "intervals": {"viscoelastic.g[0]": [0.3, None]}}
    got = MaterialEffects.from_dict(old)
    assert got.viscoelastic.kappa == 0.0 and got.names == ["viscoelastic"]
    assert got.intervals["viscoelastic.g[0]"][1] == np.inf
    assert MaterialEffects(ViscoelasticEffect((0.4,), (3.0,))).to_dict()["composition"] == old["composition"]
    with pytest.raises(ConfigError, match="d_inf"):
        CyclicSofteningEffect(1.2, 1.0)


def test_a_damage_floor_is_what_damage_leaves_and_is_recorded():
    """1 - D = b + (1 - b) exp(-((xi - onset)/s)^k): 1 below the onset, b far beyond it, the Weibull damage
    (b = 0) bit for bit, and the floor through discover.json and params.toml (absent where it is 0)."""
    xi = np.array([0.9, 1.1, 1.2, 1.5, 3.0, 50.0])
    plain = damage_factor(xi, 1.1, 0.2, 1.5)
    np.testing.assert_array_equal(damage_factor(xi, 1.1, 0.2, 1.5, 0.0), plain)
    got = damage_factor(xi, 1.1, 0.2, 1.5, 0.6)
    np.testing.assert_allclose(got, 0.6 + 0.4 * plain, rtol=1e-15)
    assert got[0] == got[1] == 1.0 and got[-1] == pytest.approx(0.6) and plain[-1] == pytest.approx(0.0)
    me = MaterialEffects(damage=DamageEffect(1.1, 0.2, 1.5, 0.6))
    assert MaterialEffects.from_dict(json.loads(json.dumps(me.to_dict()))) == me
    assert MaterialEffects.from_toml_table(me.to_toml_table()).damage.floor == 0.6
    assert "floor" not in MaterialEffects(damage=DamageEffect(1.1, 0.2, 1.5)).to_toml_table()["damage"]
    with pytest.raises(ConfigError, match="floor"):
        DamageEffect(1.1, 0.2, 1.5, 1.0)
    # a saved floor is read back as damage's variant 4, with its own bounded slot (esmm evaluate refits it)
    from esmm.pipeline.discover.model import VARIANTS, Bounds, effect_slots, spec_of_effects

    spec = spec_of_effects(me)
    assert spec.damage == 4 and spec_of_effects(MaterialEffects(damage=DamageEffect(1.1, 0.2, 1.5))).damage == 3
    b = Bounds.from_dict({"tau_min": 0.01, "tau_max": 100.0, "w_ref": 1e3, "xi_max": 1.5})
    [floor] = [s for s in effect_slots(spec, b) if s.name == "floor"]
    assert (floor.effect, floor.lo, floor.hi) == ("damage", 0.0, 0.95)
    assert VARIANTS["damage"] == (3,)  # not searched (docs/design/discovery.md, the effects' table)


# --------------------------------------------------------------------------- records
def test_noise_estimate_is_model_free():
    rng = np.random.default_rng(0)
    t = np.linspace(0, 10, 5000)
    signal = 1e4 * (np.sin(t) + 0.3 * t**2)  # smooth, large
    assert noise_sd(signal + 7.0 * rng.standard_normal(t.size)) == pytest.approx(7.0, rel=0.05)
    assert noise_sd(np.round(signal, -1)) > 0  # quantised: the quantisation noise, not zero


def _records(tmp_path, protocols, truth, **kw):
    paths = syn.write_set(tmp_path, protocols, truth, seed=1, **kw)
    return prepare([read(p) for p in paths])


def test_rupture_is_cut_and_slips_are_found(tmp_path):
    truth = syn.Truth("arruda-boyce", BASE, grip_slip=((0.5, 1.5e-3),))
    pr = syn.monotonic(0.05, 1.8, name="ramp")
    [rec] = _records(tmp_path / "slip", [pr], truth, noise=0.002)
    assert len(rec.slips) == 1 and abs(rec.x[rec.slips[0]] - 1.4) < 0.02
    assert not rec.cut
    # a break: write the same ramp with the force falling to zero for its last 20 %
    ch = syn.simulate(pr, syn.Truth("arruda-boyce", BASE), noise=0.002)
    k = int(0.8 * ch["force"].size)
    ch["force"][k:] = 0.001 * ch["force"][k:]
    path = syn.write_csv(tmp_path / "broken.csv", ch, gauge_length=0.03, area=20e-6)
    [rec] = prepare([read(path)])
    assert rec.cut and abs(rec.cut["index"] - k) <= 1 and rec.test.n == rec.cut["index"]


def test_a_shear_record_is_cut_at_its_rupture_too():
    """A simple-shear pull to failure is cut where the stress breaks, as a tension record is; a shear cycle
    (the stress falling as the shear goes back) is not a rupture."""
    from pathlib import Path

    from esmm.pipeline.discover.records import cut_at_rupture
    from esmm.pipeline.tensile.data import TensileTest

    rng = np.random.default_rng(4)
    n = 2000
    gamma = np.linspace(0.0, 0.5, n)
    stress = 3e3 * gamma + 3.0 * rng.standard_normal(n)
    k = 1700
    stress[k:] = 40.0 + 3.0 * rng.standard_normal(n - k)  # the broken specimen: the load cell's offset
    t = TensileTest(source=Path("shear.csv"), mode="simple_shear", stretch=gamma, stress=stress,
                    time=np.arange(n) * 0.01)
    cut, what = cut_at_rupture(t)
    assert what and abs(what["index"] - k) <= 1 and cut.n == what["index"]
    back = np.concatenate([gamma, gamma[::-1]])
    cycle = TensileTest(source=Path("cycle.csv"), mode="simple_shear", stretch=back,
                        stress=3e3 * back + 3.0 * rng.standard_normal(2 * n), time=np.arange(2 * n) * 0.01)
    assert cut_at_rupture(cycle)[1] == {}


def test_reading_at_rest_is_the_offset(tmp_path):
    truth = syn.Truth("arruda-boyce", BASE, sensor_offset={"force": 0.02})
    [rec] = _records(tmp_path, [syn.load_unload(0.05, 1.4)], truth, rest=30, noise=0.002)
    assert rest_reading(rec) * 20e-6 == pytest.approx(0.02, abs=3e-4)


def _at_rest_record(rng, noise: str, offset: float):
    """A machine record: 600 samples at rest, a load-unload cycle to stretch 1.5, the elastic stress (peak
    about 40 kPa) plus a load-cell *offset* [Pa] and noise of 0.2 % of the peak: Butterworth-filtered
    (``"filtered"``) or 1/f over the whole band (``"pink"``), quantised to 16 bits of a 100 kPa span."""
    from pathlib import Path

    from esmm.pipeline.tensile.data import TensileTest

    lam = np.concatenate([np.ones(600), np.linspace(1.0, 1.5, 1500), np.linspace(1.5, 1.0, 1500)])
    n = lam.size
    stress = 20e3 * (lam - lam ** -2)
    if noise == "filtered":
        b, a = signal.butter(2, 0.1)
        e = signal.lfilter(b, a, rng.standard_normal(n + 500))[500:]
    else:
        f = np.fft.rfftfreq(2 * n)
        e = np.fft.irfft((rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size))
                         / np.sqrt(np.maximum(f, f[1])))[:n]
    y = stress + offset + 0.002 * np.max(stress) * e / e.std()
    q = 100e3 / 2 ** 16
    t = TensileTest(source=Path("rest.csv"), mode="uniaxial", stretch=lam, stress=q * np.round(y / q),
                    time=np.arange(n) * 0.02)
    [rec] = prepare([t])
    return rec


@pytest.mark.slow
@pytest.mark.parametrize("noise", ["filtered", "pink"])
def test_a_tared_zero_is_not_read_as_an_offset(noise):
    """Without an offset, the reading at rest under correlated noise is the tared zero (0.0) in all but about
    the level's share of records (three binomial SDs over 100 draws); the mean of the samples at rest itself
    is not zero in any of them."""
    rng = np.random.default_rng(11)
    readings = [rest_reading(_at_rest_record(rng, noise, 0.0)) for _ in range(100)]
    assert sum(r != 0.0 for r in readings) <= 100 * (0.05 + 3 * np.sqrt(0.05 * 0.95 / 100))


@pytest.mark.parametrize("noise", ["filtered", "pink"])
def test_an_offset_is_measured_at_rest(noise):
    """An offset of 2 % of the peak is the reading at rest, within the noise's share of it."""
    rng = np.random.default_rng(12)
    for _ in range(5):
        rec = _at_rest_record(rng, noise, -800.0)
        assert rest_reading(rec) == pytest.approx(-800.0, abs=200.0)


def test_one_reading_at_rest_is_judged_by_the_records_noise():
    """A record whose crosshead moves from its second sample has one reading at rest: an offset far beyond the
    record's noise (and its resolution) is measured there, a reading within it is the tared zero."""
    from pathlib import Path

    from esmm.pipeline.tensile.data import TensileTest

    rng = np.random.default_rng(13)
    lam = np.concatenate([[1.0], np.linspace(1.001, 1.5, 1500), np.linspace(1.5, 1.0, 1500)])
    stress = 20e3 * (lam - lam ** -2)
    for offset, measured in ((-800.0, True), (0.0, False)):
        y = stress + offset + 20.0 * rng.standard_normal(lam.size)
        [rec] = prepare([TensileTest(source=Path("one.csv"), mode="uniaxial", stretch=lam, stress=y,
                                     time=np.arange(lam.size) * 0.02)])
        got = rest_reading(rec)
        assert (got == pytest.approx(offset, abs=100.0)) if measured else got == 0.0


# --------------------------------------------------------------------------- statistics
def test_autocorrelation_time_of_an_ar1_series():
    rng = np.random.default_rng(2)
    phi, n = 0.8, 200_000
    e = rng.standard_normal(n)
    x = np.empty(n)
    x[0] = e[0]
    for i in range(1, n):
        x[i] = phi * x[i - 1] + e[i]
    assert autocorrelation_time(x) == pytest.approx((1 + phi) / (1 - phi), rel=0.1)
    assert autocorrelation_time(rng.standard_normal(10_000)) == pytest.approx(1.0, abs=0.2)


def test_noise_test_penalises_parameters_not_samples():
    rng = np.random.default_rng(3)
    r0 = [rng.standard_normal(400)]
    same = noise_test(r0, [0.999 * r0[0]], [1.0], 2)  # fitting noise: Δχ² ~ 1, penalty 2 ln 400
    assert same["dbic"] > 0
    better = noise_test([r0[0] + 3.0], r0, [1.0], 2)  # a systematic misfit of 3 σ removed
    assert better["dbic"] < 0 and better["dchi2"] == pytest.approx(400 * 9, rel=0.1)



def test_a_candidate_without_parameters_must_change_the_fit():
    """Δk = 0 (an offset held at its reading at rest): a fit the same to 1e-9 noise variances is the current
    model and does not pass; one that removes a misfit does."""
    rng = np.random.default_rng(3)
    r0 = [rng.standard_normal(400)]
    assert noise_test(r0, [r0[0] * (1 - 1e-12)], [1.0], 0)["dbic"] > 0
    assert noise_test([r0[0] + 0.5], r0, [1.0], 0)["dbic"] < 0  # Δχ² about 100


def _ar_noise(rng, n: int, phi: float) -> np.ndarray:
    """Unit-variance AR(1) noise (scipy.signal), its transient dropped."""
    e = signal.lfilter([1.0], [1.0, -phi], rng.standard_normal(n + 500))[500:]
    return e * np.sqrt(1.0 - phi * phi)


def test_heldout_test_signs_and_size():
    rng = np.random.default_rng(4)
    y = rng.standard_normal(2000)
    truth = np.zeros(2000)
    y = truth + 0.1 * rng.standard_normal(2000)
    p0, p1 = truth + 0.5, truth  # the current model biased by 5 noise SDs, the candidate right
    good = heldout_test([HeldoutSegment("f", y, p0, p1, 10.0, 0.1)])
    assert good["p"] < 1e-12 and good["noise_units"] == pytest.approx(25.0, rel=0.05)
    bad = heldout_test([HeldoutSegment("f", y, p1, p0, 10.0, 0.1)])
    assert bad["p"] > 0.999 and bad["noise_units"] < 0
    same = heldout_test([HeldoutSegment("f", y, p1, p1 + 1e-9, 10.0, 0.1)])
    assert 0.01 < same["p"] < 0.99 and abs(same["noise_units"]) < 1e-3


@pytest.mark.parametrize("phi", [0.0, 0.9])
def test_heldout_test_is_calibrated_under_correlated_noise(phi):
    """At the null's boundary (two predictions equally wrong, on either side of the truth) both one-sided
    statistics reject at 5 % in 5 % of 600 records within binomial error, white or AR(1) noise (the noise
    test given the noise model's σ and correlation length, the replication check from the data alone);
    the same statistic with an independent-samples variance rejects far more often under AR(1) noise."""
    rng = np.random.default_rng(12)
    n, a = 1000, 0.05
    length = -1.0 / np.log(phi) if phi else 0.0
    hits, hits_rep, naive = 0, 0, 0
    for _ in range(600):
        y = 0.1 * _ar_noise(rng, n, phi)
        segs = [HeldoutSegment("f", y[:500], np.full(500, a), np.full(500, -a), 1.0, 0.1, 0.1, length),
                HeldoutSegment("f", y[500:], np.full(500, a), np.full(500, -a), 1.0, 0.1, 0.1, length)]
        h = heldout_test(segs)
        hits += h["p"] <= 0.05
        hits_rep += h["p_replication"] <= 0.05
        d = (a - y) ** 2 - (-a - y) ** 2
        naive += d.mean() / (d.std(ddof=1) / np.sqrt(n)) >= 1.645
    assert 13 <= hits <= 48, hits  # binomial(600, 0.05): 30 +- 3 sd
    assert 13 <= hits_rep <= 48, hits_rep
    if phi:
        assert naive > 100, naive


def test_replication_check_rejects_an_improvement_small_next_to_the_misfit_left():
    """A candidate that moves the prediction by a tenth of a smooth misfit it leaves: far beyond the noise
    (the noise test passes), but not replicated across the held-out segments."""
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 1.0, 2000)
    truth = np.zeros_like(t)
    misfit = 0.05 * np.sin(2 * np.pi * 3 * t)  # what both models miss, smooth
    y = truth + 1e-3 * rng.standard_normal(t.size)
    p0 = truth + misfit + 0.006
    p1 = truth + misfit + 0.001 * np.cos(2 * np.pi * 5 * t)
    segs = [HeldoutSegment("f", y[i:i + 400], p0[i:i + 400], p1[i:i + 400], 1.0, 1e-3, 1e-3, 0.0)
            for i in range(0, 2000, 400)]
    h = heldout_test(segs)
    assert h["p"] < 1e-6 and h["p_replication"] > 0.05




def test_set_stretch_with_an_exponent_and_its_record():
    """λ_s = 1 + f (λ_max − 1)^q against hand values; the exponent round-trips, and a proportional set (q = 1)
    is written as before (no exponent key), so records written before the exponent read unchanged."""
    np.testing.assert_allclose(set_stretch(np.array([1.0, 1.5, 3.0]), 0.2, 2.0), [1.0, 1.05, 1.8])
    me = MaterialEffects(None, None, None, {}, None, PermanentSetEffect(0.1, 1.7))
    assert MaterialEffects.from_dict(json.loads(json.dumps(me.to_dict()))) == me
    assert MaterialEffects.from_toml_table(me.to_toml_table()).permanent_set.exponent == 1.7
    plain = MaterialEffects(None, None, None, {}, None, PermanentSetEffect(0.1))
    assert "exponent" not in plain.to_dict()["permanent_set"] and "exponent" not in plain.to_toml_table()["permanent_set"]
    assert MaterialEffects.from_dict(plain.to_dict()).permanent_set.exponent == 1.0
    with pytest.raises(ConfigError, match="exponent"):
        PermanentSetEffect(0.1, 5.0)


def test_a_set_that_grows_faster_than_the_prestrain_is_named_alone():
    """Cycles to rising peaks of a neo-Hookean strip with a residual stretch 1 + 0.15 (λ_max − 1)²
    (the population generator's formula, Dorfmann & Ogden 2004): the permanent set is kept in its variant
    with an exponent, near 2, and nothing else; with the proportional set alone a relaxation and a damage
    were kept instead."""
    from pathlib import Path

    from esmm.pipeline.discover import discover
    from esmm.pipeline.tensile.data import TensileTest
    from population import history as H
    from population.laws import ISOTROPIC

    law = ISOTROPIC["neo_hookean"](mu=20e3)
    peaks = (1.2, 1.35, 1.5, 1.65, 1.8)
    legs = [np.linspace(1.0, peaks[0], 200)]
    for a, b in zip(peaks, peaks[1:] + (None,)):
        legs.append(np.linspace(a, 1.0, 200)[1:])
        if b is not None:
            legs.append(np.linspace(1.0, b, 200)[1:])
    x = np.concatenate(legs)
    t = np.arange(x.size) * 0.05
    p = H.permanent_set(x, lambda v: law.stress(v, "uniaxial"), f=0.15, q=2.0)
    y = p + 0.003 * float(p.max()) * np.random.default_rng(4).standard_normal(x.size)
    rec = TensileTest(source=Path("set.csv"), mode="uniaxial", stretch=x, stress=y, time=t)
    from esmm.pipeline.materials.terms import TERMS
    res = discover([rec], model="arruda-boyce", n_starts=2, max_points=400, nested=False)
    assert [n for n in res.kept if n not in TERMS] == ["permanent_set"], {n: c.reason for n, c in res.candidates.items()}
    ps = res.material_effects.permanent_set
    assert ps.exponent == pytest.approx(2.0, abs=0.3) and ps.fraction == pytest.approx(0.15, rel=0.3)
