"""Stretch-dependent relaxation rate (``kappa_tau``): the integration against an independent ODE solver,
QLV as its zero, its record, and the discovery naming it on records integrated independently of esmm."""

from __future__ import annotations

import json

import numpy as np
import pytest
from esmm.pipeline.asset.material import storable_effects
from esmm.pipeline.discover import discover
from esmm.pipeline.discover import synthetic as syn
from esmm.pipeline.discover.model import Bounds, Spec, effect_slots, spec_of_effects
from esmm.pipeline.errors import ConfigError
from esmm.pipeline.materials import get_model
from esmm.pipeline.materials.effects import (
    MaterialEffects,
    ViscoelasticEffect,
    qlv_decay,
    qlv_rate_decay,
    qlv_rate_stress,
    qlv_stress,
    relaxation_times,
)
from esmm.pipeline.materials.loading import nominal_stress
from esmm.pipeline.simulate.effects import build_effect_model
from esmm.pipeline.tensile import read
from scipy import signal
from scipy.integrate import solve_ivp

BASE = {"mu": 20e3, "N": 4.0}  # Arruda-Boyce
FAST = dict(model="arruda-boyce", n_starts=2, max_points=200)


# --------------------------------------------------------------------------- the integration
def _smooth_history(t):
    """A stretch history with a ramp, a slow wander and a hold-like plateau, and its neo-Hookean stress."""
    xi = 1.0 + 0.15 * (1.0 - np.cos(np.pi * np.minimum(t, 4.0) / 4.0)) + 0.1 * np.sin(0.5 * t) ** 2
    return xi, 1e4 * (xi - 1.0 / xi**2)


def _maxwell_reference(t_out, g, tau, kappa_tau, history):
    """P = g_inf P_e + sum g_i h_i with dh_i/dt = dP_e/dt - h_i / (tau_i exp(-kappa_tau (xi - 1))) by solve_ivp."""
    g, tau = np.asarray(g), np.asarray(tau)

    def rhs(s, h):
        eps = 1e-6
        dpe = (history(s + eps)[1] - history(s - eps)[1]) / (2 * eps)
        return dpe - h / (tau * np.exp(-kappa_tau * (history(s)[0] - 1.0)))

    pe0 = history(t_out[0])[1]
    sol = solve_ivp(rhs, (t_out[0], t_out[-1]), np.full(tau.size, pe0), method="DOP853", rtol=1e-11,
                    atol=1e-9, t_eval=t_out)
    assert sol.success
    return (1.0 - g.sum()) * history(t_out)[1] + g @ sol.y


def test_rate_recursion_converges_to_the_maxwell_branches_at_second_order():
    g, tau, kt = [0.3, 0.25], [0.7, 5.0], -4.0
    errors = []
    for n in (200, 400, 800):
        t = np.linspace(0.0, 12.0, n + 1)
        xi, pe = _smooth_history(t)
        ref = _maxwell_reference(t, g, tau, kt, _smooth_history)
        errors.append(np.max(np.abs(qlv_rate_stress(t, pe, xi, g, tau, kt) - ref)) / np.max(np.abs(ref)))
    assert errors[-1] < 5e-6
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(rates > 1.9), rates  # halving the step quarters the error


def test_rate_recursion_is_exact_on_a_hold():
    """Stretch and elastic stress held: each branch decays as exp(-t / tau_i(xi)), whatever the step."""
    t = np.concatenate([[0.0], np.cumsum(np.random.default_rng(1).uniform(0.05, 2.0, 40))])
    xi, pe = np.full(t.size, 1.3), np.full(t.size, 5e3)
    pe[0] = 0.0  # a step to the hold at the first interval's end
    xi[0] = 1.3
    g, tau, kt = np.array([0.4]), np.array([2.0]), 3.0
    p = qlv_rate_stress(t, pe, xi, g, tau, kt)
    tau_x = float(relaxation_times(1.3, tau, kt)[0])
    h1 = tau_x / t[1] * -np.expm1(-t[1] / tau_x) * 5e3  # the ramp to the hold, integrated exactly
    expect = 0.6 * 5e3 + 0.4 * h1 * np.exp(-(t[1:] - t[1]) / tau_x)
    np.testing.assert_allclose(p[1:], expect, rtol=1e-12)


def test_kappa_tau_zero_is_qlv_bit_for_bit():
    t = np.sort(np.random.default_rng(2).uniform(0.0, 30.0, 500))
    xi, pe = _smooth_history(t)
    g, tau = np.array([0.2, 0.3]), np.array([0.5, 8.0])
    a0, b0 = qlv_decay(t, tau)
    a1, b1 = qlv_rate_decay(t, tau, xi, 0.0)
    assert np.array_equal(a0, a1) and np.array_equal(b0, b1)
    assert np.array_equal(qlv_rate_stress(t, pe, xi, g, tau, 0.0), qlv_stress(t, pe, g, tau))
    v = ViscoelasticEffect((0.2, 0.3), (0.5, 8.0), kappa_tau=-2.0)
    np.testing.assert_allclose(ViscoelasticEffect((0.2, 0.3), (0.5, 8.0)).stress(t, pe, xi),
                               qlv_stress(t, pe, g, tau), rtol=1e-12)
    assert not np.allclose(v.stress(t, pe, xi), qlv_stress(t, pe, g, tau), rtol=1e-3)
    with pytest.raises(ConfigError, match="xi"):
        v.stress(t, pe)


def test_kappa_tau_is_recorded_dropped_and_refused_in_words():
    me = MaterialEffects(ViscoelasticEffect((0.3,), (2.0,), kappa_tau=-4.0))
    assert MaterialEffects.from_dict(json.loads(json.dumps(me.to_dict()))) == me
    back = MaterialEffects.from_toml_table(me.to_toml_table(stress_unit="kPa"), stress_unit="kPa")
    assert back.viscoelastic.kappa_tau == -4.0 and back.viscoelastic.kappa == 0.0
    assert "relaxation_times" in me.state_variables()["prony_h"]
    with pytest.raises(ConfigError, match="not both"):
        ViscoelasticEffect((0.3,), (2.0,), kappa=1.0, kappa_tau=1.0)
    kept, notes = storable_effects(me)
    assert kept.viscoelastic.kappa_tau == 0.0 and "kappa_tau = -4" in notes[0]
    with pytest.raises(ConfigError, match=r"relaxation times \(viscoelastic kappa_tau = -4\)"):
        build_effect_model(me, None, "secant")


def test_the_rate_variant_has_its_own_bounded_slot():
    b = Bounds.from_dict({"tau_min": 0.01, "tau_max": 100.0, "w_ref": 1e3, "xi_max": 1.5})
    [s] = [s for s in effect_slots(Spec(viscoelastic=1, nonlinear_viscoelastic=2), b)
           if s.effect == "nonlinear_viscoelastic"]
    assert s.name == "kappa_tau" and s.lo == -b.kappa_max and s.hi == b.kappa_max == pytest.approx(6.0)
    assert Spec().with_("nonlinear_viscoelastic", 2).viscoelastic == 1
    # a saved rate form is read back as the rate variant (esmm evaluate), the strength form as the other
    assert spec_of_effects(MaterialEffects(ViscoelasticEffect((0.3,), (2.0,), kappa_tau=-4.0))).nonlinear_viscoelastic == 2
    assert spec_of_effects(MaterialEffects(ViscoelasticEffect((0.3,), (2.0,), kappa=-4.0))).nonlinear_viscoelastic == 1


# --------------------------------------------------------------------------- the closed loop
def _record(path, knots_t, knots_x, kappa_tau: float, seed: int, *, dt: float = 0.05):
    """A stretch history piecewise linear through the knots, one Prony term (g 0.4, tau 3 s) whose time follows
    the stretch, integrated by solve_ivp segment by segment; force noise low-pass filtered (2nd-order
    Butterworth at 0.2 of Nyquist) and quantised; written as a raw file at *path*."""
    model = get_model("arruda-boyce")

    def history(s):
        x = np.interp(s, knots_t, knots_x)
        return x, np.asarray(nominal_stress(model, BASE, "uniaxial", np.atleast_1d(x)), float).reshape(np.shape(s))

    g, tau = 0.4, 3.0
    t = np.arange(0.0, knots_t[-1] + 1e-9, dt)
    h_all, h0 = np.empty(t.size), 0.0
    for a, b in zip(knots_t[:-1], knots_t[1:]):
        sel = (t >= a) & (t <= b)

        def rhs(s, h, a=a, b=b):
            x = history(s)[0]
            dpe = (history(min(s + 1e-6, b))[1] - history(max(s - 1e-6, a))[1]) / (min(s + 1e-6, b) - max(s - 1e-6, a))
            return [dpe - h[0] / (tau * np.exp(-kappa_tau * (x - 1.0)))]

        sol = solve_ivp(rhs, (a, b), [h0], method="DOP853", rtol=1e-10, atol=1e-6, t_eval=t[sel], dense_output=True)
        h_all[sel] = sol.y[0]
        h0 = float(sol.sol(b)[0])
    pe = history(t)[1]
    stress = (1.0 - g) * pe + g * h_all
    rng = np.random.default_rng(seed)
    bb, aa = signal.butter(2, 0.2)
    noise = signal.lfilter(bb, aa, rng.standard_normal(t.size + 200))[200:]
    area, gauge = 20e-6, 0.03
    force = stress * area + 0.004 * float(np.max(stress)) * area * noise / np.std(noise)
    force = np.round(force / 1e-4) * 1e-4  # the converter's step
    return read(syn.write_csv(path, {"time": t, "displacement": (history(t)[0] - 1.0) * gauge, "force": force},
                              gauge_length=gauge, area=area))


def _staircase_record(tmp_path, kappa_tau: float, seed: int):
    """A staircase in stretch: ramps at 0.05 /s, 30 s holds at 1.1 ... 1.4 (:func:`_record`)."""
    knots_t, knots_x, t_now = [0.0], [1.0], 0.0
    for lvl in (1.1, 1.2, 1.3, 1.4):
        t_now += (lvl - knots_x[-1]) / 0.05
        knots_t += [t_now, t_now + 30.0]
        knots_x += [lvl, lvl]
        t_now += 30.0
    return [_record(tmp_path / f"staircase_{seed}.csv", knots_t, knots_x, kappa_tau, seed)]


def _two_rates_records(tmp_path, kappa_tau: float, seed: int):
    """Two load-unload cycles to one peak (stretch 1.4), at 0.02 and 0.2 /s, no hold (:func:`_record`)."""
    out = []
    for k, rate in enumerate((0.02, 0.2)):
        top = 0.4 / rate
        out.append(_record(tmp_path / f"rate_{k}_{seed}.csv", [0.0, top, 2 * top], [1.0, 1.4, 1.0], kappa_tau,
                           seed + k, dt=0.002 / rate))
    return out


@pytest.mark.slow
def test_discovery_names_the_rate_form_on_an_independent_record(tmp_path):
    res = discover(_staircase_record(tmp_path, -5.0, seed=4), **FAST)
    assert "nonlinear_viscoelastic" in res.kept, (res.kept, {n: c.reason for n, c in res.candidates.items()})
    assert res.final.spec.nonlinear_viscoelastic == 2
    v = res.material_effects.viscoelastic
    assert v.kappa_tau == pytest.approx(-5.0, rel=0.2) and v.kappa == 0.0


@pytest.mark.slow
def test_discovery_adds_no_rate_form_on_plain_qlv(tmp_path):
    res = discover(_staircase_record(tmp_path, 0.0, seed=5), **FAST)
    assert "viscoelastic" in res.kept
    assert "nonlinear_viscoelastic" not in res.kept, {n: c.reason for n, c in res.candidates.items()}



@pytest.mark.slow
def test_two_rates_to_one_peak_name_the_rate_form_and_add_none_to_plain_qlv(tmp_path):
    """Loadings at two rates to one peak make a stretch-dependent relaxation identifiable
    (``identify._nonlinear``): its rate form is named on records integrated independently of esmm, and
    nothing is added to a plain relaxation recorded the same way."""
    for sub in ("a", "b"):
        (tmp_path / sub).mkdir()
    res = discover(_two_rates_records(tmp_path / "a", -5.0, seed=6), **FAST)
    assert "nonlinear_viscoelastic" in res.kept, (res.kept, {n: c.reason for n, c in res.candidates.items()})
    assert res.final.spec.nonlinear_viscoelastic == 2
    plain = discover(_two_rates_records(tmp_path / "b", 0.0, seed=8), **FAST)
    assert "viscoelastic" in plain.kept
    assert "nonlinear_viscoelastic" not in plain.kept, {n: c.reason for n, c in plain.candidates.items()}


@pytest.mark.parametrize("relaxation_stays", [False, True])
def test_backward_elimination_judges_a_brought_in_relaxation_once_its_container_goes(monkeypatch, relaxation_stays):
    """A stretch-dependent relaxation brings a plain one into the model (``rounds.sync_kept``), which is never
    tested alone; where the backward elimination removes the stretch-dependent one, the plain one is judged
    next, on its own, before what was kept earlier (the judgement itself stubbed: this is the order)."""
    from types import SimpleNamespace as NS

    from esmm.pipeline.discover import rounds

    verdicts = {"nonlinear_viscoelastic": False, "viscoelastic": relaxation_stays, "toe": True}
    calls = []

    def judged(s, name, f):
        calls.append(name)
        left = [n for n in s.kept if n != name]
        reduced = NS(spec=NS(names=lambda: left), cv={"k": NS(nrmse=0.01)})
        return verdicts[name], reduced, {"p": 0.5, "p_replication": 0.01, "resolution_units": 2.0}, 1e-3

    monkeypatch.setattr(rounds, "_judged_without", judged)
    monkeypatch.setattr(rounds, "judged_on", lambda *a: NS(key="k"))
    kept = ["toe", "nonlinear_viscoelastic", "viscoelastic"]
    s = NS(kept=list(kept), kept_round={n: 1 for n in kept}, material=None, artefact=None,
           current=NS(spec=NS(names=lambda: kept), cv={"k": NS(nrmse=0.02)}),
           candidates={n: NS(round=1, kept=True, reason="kept") for n in kept}, crit=NS(min_resolution_units=1.0))
    rounds.backward(s, NS(step=lambda *a: None))
    if relaxation_stays:
        assert calls == ["nonlinear_viscoelastic", "viscoelastic", "toe"]
        assert s.kept == ["toe", "viscoelastic"] and "judged on its own" in s.candidates["viscoelastic"].reason
    else:  # the toe, judged beside both, is judged again once they have gone
        assert calls == ["nonlinear_viscoelastic", "viscoelastic", "toe"]
        assert s.kept == ["toe"] and not s.candidates["viscoelastic"].kept
    # the removal names the check that failed, and only that one
    why = s.candidates["nonlinear_viscoelastic"].reason
    assert "beyond the noise p 0.5 > 0.001" in why and "replicated" not in why and "resolutions" not in why


def test_what_passed_beside_a_removed_candidate_is_judged_again_down_to_the_last(monkeypatch):
    """The elimination ends on a model in which every kept candidate passes given the others: a relaxation
    that passed beside a toe is judged again once the toe goes, and, the last one left, against the base law
    (the judgement stubbed: it passes only while the toe is in)."""
    from types import SimpleNamespace as NS

    from esmm.pipeline.discover import rounds

    calls = []

    def judged(s, name, f):
        calls.append(name)
        left = [n for n in s.kept if n != name]
        reduced = NS(spec=NS(names=lambda: left), cv={"k": NS(nrmse=0.01)})
        ok = name == "viscoelastic" and "toe" in s.kept
        return ok, reduced, {"p": 0.5, "p_replication": 0.01, "resolution_units": 2.0}, 1e-3

    monkeypatch.setattr(rounds, "_judged_without", judged)
    monkeypatch.setattr(rounds, "judged_on", lambda *a: NS(key="k"))
    kept = ["toe", "viscoelastic"]
    steps = []
    s = NS(kept=list(kept), kept_round={"toe": 1, "viscoelastic": 2}, material=None, artefact=None,
           current=NS(spec=NS(names=lambda: kept), cv={"k": NS(nrmse=0.02)}),
           candidates={n: NS(round=r, kept=True, reason="kept") for n, r in (("toe", 1), ("viscoelastic", 2))},
           crit=NS(min_resolution_units=1.0))
    rounds.backward(s, NS(step=steps.append))
    assert calls == ["viscoelastic", "toe", "viscoelastic"] and s.kept == []
    assert "given the base law alone" in s.candidates["viscoelastic"].reason
    assert steps[-1] == "removed viscoelastic: on its own it does not pass"


def test_a_removal_names_every_held_out_check_that_fails():
    """The backward elimination's reason names what failed: the noise test, the replication check, the size
    requirement, or (all three passing) the pre-screen."""
    from esmm.pipeline.discover.rounds import failed_checks

    h = {"p": 1e-5, "p_replication": 0.2, "resolution_units": 0.4}
    assert failed_checks(h, 1e-3, 1.0) == ("replicated across the held-out segments p 0.2 > 0.05; "
                                           "0.4 squared resolutions per sample < 1")
    assert failed_checks({**h, "p": 0.01}, 1e-3, 0.3).startswith("beyond the noise p 0.01 > 0.001; replicated")
    assert "pre-screen" in failed_checks({"p": 0.0, "p_replication": 0.0, "resolution_units": 5.0}, 1e-3, 1.0)


def test_a_nested_pair_is_checked_at_the_rank_of_its_better_fit():
    """Strain-energy terms first, then the rest by fitted improvement; a plain relaxation is checked just before
    the stretch-dependent one that outranks it (simpler first), not the stretch-dependent one moved down
    behind candidates that fit worse than it."""
    from types import SimpleNamespace as T

    from esmm.pipeline.discover.rounds import elastic_first

    def order(*pairs):
        return [t.name for t in elastic_first([T(name=n, dbic=d) for n, d in pairs])]

    assert order(("nonlinear_viscoelastic", -100.0), ("sensor_offset", -90.0), ("yeoh", -5.0),
                 ("mullins", -50.0), ("viscoelastic", -10.0)) == \
        ["yeoh", "viscoelastic", "nonlinear_viscoelastic", "sensor_offset", "mullins"]
    assert order(("viscoelastic", -100.0), ("sensor_offset", -90.0), ("nonlinear_viscoelastic", -10.0)) == \
        ["viscoelastic", "sensor_offset", "nonlinear_viscoelastic"]
    assert order(("nonlinear_viscoelastic", -100.0), ("sensor_offset", -90.0)) == \
        ["nonlinear_viscoelastic", "sensor_offset"]
