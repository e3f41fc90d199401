"""How far to trust a fit: the verdict's rules, the failure tests (rupture, strengths, moduli, censoring),
and the real records of the issue (tendon pulls to failure, foam cycles stopped at a force limit)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from esmm.pipeline.calibrate import failure as F
from esmm.pipeline.calibrate.calibration import calibrate
from esmm.pipeline.materials import get_model
from esmm.pipeline.materials.loading import nominal_stress
from esmm.pipeline.tensile import TensileTest, read

AB = {"mu": 0.3e6, "N": 8.0}


def _test(x, y, *, name="t.csv", time=True, force=None):
    x, y = np.asarray(x, float), np.asarray(y, float)
    return TensileTest(source=Path(name), mode="uniaxial", stretch=x, stress=y,
                       time=np.arange(x.size, dtype=float) * 0.1 if time else None,
                       force=None if force is None else np.asarray(force, float))


def _ab(x, params=AB):
    return nominal_stress(get_model("arruda-boyce"), params, "uniaxial", np.asarray(x, float))


def _noisy(y, frac, seed=0):
    return y + frac * float(np.ptp(y)) * np.random.default_rng(seed).standard_normal(y.size)


# --------------------------------------------------------------------------- verdicts
def test_a_clean_fit_of_the_right_model_is_good():
    x = np.linspace(1.0, 3.0, 400)
    cal = calibrate([_test(x, _noisy(_ab(x), 0.005))], model="arruda-boyce", n_starts=3)
    assert cal.verdict.level == "good", cal.verdict.short()
    assert all(e.identifiable for e in cal.result.estimates)


def test_a_model_that_cannot_follow_the_data_is_unusable():
    """The issue's Sample-1: R² −0.49 was 'ok'. A stress that falls while the stretch rises (no rupture: it
    never drops below half its peak) cannot be fitted by a hyperelastic law: R² below 0.5, unusable."""
    x = np.linspace(1.0, 2.0, 400)
    y = _noisy(1e5 * (1.0 + np.sin(6.0 * (x - 1.0))), 0.002)
    cal = calibrate([_test(x, y)], model="arruda-boyce", n_starts=3)
    assert cal.result.r2 < 0.5
    assert cal.verdict.level == "unusable"
    assert any(r.code == "no_fit" for r in cal.verdict.reasons)
    assert "R²" in cal.verdict.short()


def test_a_wrong_shape_within_reach_is_poor():
    """A concave curve (P = E ln λ) fitted with a stiffening law: the shape is wrong by more than 5 % of the
    range and far beyond the noise, but the model still explains most of the data: poor, not good."""
    x = np.linspace(1.0, 4.0, 400)
    y = _noisy(1e6 * np.log(x) ** 0.5, 0.001)
    cal = calibrate([_test(x, y)], model="arruda-boyce", n_starts=3)
    assert cal.result.r2 >= 0.5 and cal.result.nrmse > 0.05
    assert cal.verdict.level == "poor"
    assert [r.code for r in cal.verdict.reasons if r.level == "poor"][0] == "misfit"


def test_a_noisy_record_of_the_right_model_is_not_blamed_on_the_model():
    """Noise 30 % of the range: R² is low because of the noise, not the model (RMSE ≈ the record's noise)."""
    x = np.linspace(1.0, 3.0, 2000)
    cal = calibrate([_test(x, _noisy(_ab(x), 0.3, seed=4))], model="arruda-boyce", n_starts=3)
    assert cal.result.r2 < 0.5
    assert cal.verdict.noise["t.csv"]["ratio"] < 2.0
    assert cal.verdict.level != "unusable" and any(r.code == "noisy" for r in cal.verdict.reasons)


def test_a_noiseless_curve_is_judged_against_the_machine_accuracy_not_a_vanishing_noise():
    """A digitised or averaged curve (no time column, no sample-to-sample noise): its misfit is measured in
    units of 0.5 % of its RMS stress (a class 0.5 machine), not of a noise estimate of ~1e-9 Pa; the
    ratio is exactly RMSE over that resolution."""
    x = np.linspace(1.0, 2.0, 200)
    y = 1e5 * (x - 1.0) ** 0.5  # concave: a stiffening law misses it a little
    cal = calibrate([_test(x, y, time=False)], model="arruda-boyce", n_starts=3)
    nz = cal.verdict.noise["t.csv"]
    expect = 0.005 * float(np.sqrt(np.mean(y * y)))
    assert nz["sd_Pa"] < 0.05 * expect
    assert nz["resolution_Pa"] == pytest.approx(expect, rel=1e-12)
    assert nz["ratio"] == pytest.approx(cal.result.files[0].rmse / expect, rel=1e-12)
    assert nz["ratio"] > 2.0 and cal.result.nrmse > 0.05
    misfit = [r.text for r in cal.verdict.reasons if r.code == "misfit"]
    assert misfit and "times its resolution" in misfit[0] and "0.5 % of its RMS stress" in misfit[0]


def test_undetermined_parameters_make_a_fit_poor_and_say_which():
    """Small stretches never approach locking: N is not determined (an unbounded interval), and the
    warning carries its unit."""
    x = np.linspace(1.0, 1.05, 300)
    cal = calibrate([_test(x, _noisy(_ab(x), 0.002))], model="arruda-boyce", n_starts=3)
    n = next(e for e in cal.result.estimates if e.name == "N")
    assert not n.identifiable
    assert cal.verdict.level == "poor"
    assert any(r.code == "not_identifiable" and "N" in r.text for r in cal.verdict.reasons)
    w = next(w for w in cal.result.warnings if w.startswith("N is not identifiable"))
    assert w.endswith("(dimensionless)")


# --------------------------------------------------------------------------- failure tests
def _pull_to_failure(n=1200, lam_u=2.0, drop_to=0.02, seed=0):
    """An Arruda-Boyce pull to λ = lam_u, then a break to *drop_to* of the peak and a tail of broken-specimen
    readings; returns (test, index of the ultimate stress)."""
    x_up = np.linspace(1.0, lam_u, n)
    x_dn = lam_u + np.linspace(0.001, 0.2, 200)
    y_up = _ab(x_up)
    y_dn = np.full(x_dn.size, drop_to * y_up[-1])
    rng = np.random.default_rng(seed)
    y = np.concatenate([y_up, y_dn]) + 1e-4 * float(y_up[-1]) * rng.standard_normal(n + 200)
    return _test(np.concatenate([x_up, x_dn]), y), int(np.argmax(y[:n]))


def test_a_rupture_is_cut_and_the_intact_part_is_fitted():
    t, ult = _pull_to_failure()
    cal = calibrate([t], model="arruda-boyce", n_starts=3)
    f = cal.failures[0]
    assert f.kind == "rupture" and f.failed
    assert f.ultimate_index == ult and f.fit_end == ult + 1 and cal.fitted[0].n == ult + 1
    assert f.ultimate_stress == pytest.approx(float(t.stress[ult]))
    assert f.ultimate_stretch == pytest.approx(2.0, abs=2e-3)
    assert f.rupture_stretch > f.ultimate_stretch
    for name, v in AB.items():  # the intact part gives back the material
        assert cal.result.params[name] == pytest.approx(v, rel=0.02)
    assert cal.verdict.level == "good", cal.verdict.short()


def test_a_rupture_left_in_makes_the_fit_unusable():
    t, _ = _pull_to_failure()
    cal = calibrate([t], model="arruda-boyce", n_starts=3, cut_failure=False)
    assert cal.fitted[0].n == t.n
    assert cal.verdict.level == "unusable"
    assert any(r.code == "rupture_left" for r in cal.verdict.reasons)


def test_toe_and_linear_moduli_of_a_bilinear_curve():
    """A toe of slope 2 MPa up to λ 1.06, then 20 MPa up to the break at λ 1.2: the methods give the
    slopes and the breakpoint back."""
    x = np.linspace(1.0, 1.2, 2001)
    e1, e2, xt = 2e6, 20e6, 1.06
    y = np.where(x < xt, e1 * (x - 1.0), e1 * (xt - 1.0) + e2 * (x - xt))
    y = y + 1e3 * np.random.default_rng(1).standard_normal(x.size)
    m = F.loading_moduli(x, y)
    assert m["linear_modulus"] == pytest.approx(e2, rel=0.02)
    assert m["toe_modulus"] == pytest.approx(e1, rel=0.05)
    assert m["toe_end_stretch"] == pytest.approx(xt, abs=0.002)
    concave = F.loading_moduli(x, 1e6 * np.log(x))  # stiffest at the start: no toe
    assert concave["toe_modulus"] is None and concave["linear_from"] == pytest.approx(1.0)


def test_a_stop_at_a_force_limit_is_censored_and_not_averaged():
    x = np.linspace(1.0, 2.5, 800)
    stopped = _test(x, _ab(x), name="stopped.csv")           # ends at its largest stress: a force limit
    broken, _ = _pull_to_failure()
    fs = [F.analyse(stopped), F.analyse(broken)]
    assert [f.kind for f in fs] == ["censored", "rupture"]
    assert fs[0].fit_end == stopped.n and not fs[0].failed
    s = F.group_summary(fs)
    assert (s["failed"], s["censored"]) == (1, 1)
    assert s["stats"]["ultimate_stress"]["n"] == 1
    assert s["stats"]["linear_modulus"]["n"] == 2                      # a modulus is measured before the stop
    assert s["stats"]["ultimate_stress"]["mean"] == pytest.approx(fs[1].ultimate_stress)
    assert s["censored_at"] == [pytest.approx(float(_ab(x)[-1]))]
    relax = _test(np.r_[x, np.full(300, x[-1])], np.r_[_ab(x), _ab(x)[-1] * np.linspace(1, 0.7, 300)])
    assert F.analyse(relax).kind == "none"                     # a hold that relaxes is not a failure


def _instron_stress(path: Path) -> np.ndarray:
    """The machine's own 'Tensile stress' column [Pa] (computed by its software from its diameter)."""
    with open(path, encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    head = next(i for i, r in enumerate(rows) if r and r[0] == "Extension")
    col = rows[head].index("Tensile stress")
    return np.array([float(r[col]) for r in rows[head + 2:] if len(r) > col]) * 1e6


@pytest.mark.parametrize("name, ultimate_MPa", [("failure_incubated_1.csv", 41.87),
                                                ("failure_incubated_2.csv", 99.44),
                                                ("failure_incubated_3.csv", 201.9)])
def test_tendon_pulls_to_failure_report_their_strength(bundled_data, name, ultimate_MPa):
    """The shared Instron records: ruptured, cut, and the ultimate stress equal to the machine's own stress
    column's peak before the rupture (an independent computation from its diameter)."""
    path = bundled_data / "tensile" / "tendon_instron" / name
    f = F.analyse(read(path))
    assert f.kind == "rupture"
    machine = _instron_stress(path)
    assert f.ultimate_stress == pytest.approx(float(np.max(machine[:f.rupture_index])), rel=2e-3)
    assert f.ultimate_stress / 1e6 == pytest.approx(ultimate_MPa, rel=1e-3)
    assert f.fit_end == f.ultimate_index + 1 < f.rupture_index + 1
    assert f.linear_modulus > 0


def test_foam_cycles_stopped_at_the_force_limit_are_censored(bundled_data):
    folder = bundled_data / "tensile" / "foam_cyclic"
    kinds = {p.name: F.analyse(read(p)) for p in sorted(folder.glob("*heel-tension-*_1.csv"))}
    assert kinds["new-heel-tension-1_1.csv"].kind == "rupture"
    assert kinds["worn-heel-tension-4_1.csv"].kind == "rupture"
    censored = [k for k, f in kinds.items() if f.kind == "censored"]
    assert len(censored) == 6
    for k in censored:  # every one stopped at the machine's 75 N limit
        assert kinds[k].ultimate_force == pytest.approx(75.0, abs=1.0)
