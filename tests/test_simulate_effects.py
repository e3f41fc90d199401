"""Material effects in the simulator (QLV viscoelasticity, Mullins softening, damage).

Expected values come from the discovery's own reference functions
(``esmm.pipeline.materials.effects``: ``qlv_step``, ``mullins_factor``,
``damage_factor``, ``equivalent_stretch``), from closed forms (QLV ramp-and-hold
response, static sag of a linear network) or from independent quadrature.
"""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
from esmm.pipeline.materials.effects import (
    DamageEffect,
    MaterialEffects,
    MullinsEffect,
    ViscoelasticEffect,
    damage_factor,
    equivalent_stretch,
    mullins_factor,
    qlv_step,
)
from esmm.pipeline.network.springs import SpringNetwork, network_from_tets
from esmm.pipeline.network.tables import StiffnessTables
from esmm.pipeline.simulate import kernels as K
from esmm.pipeline.simulate.history import History
from esmm.pipeline.simulate.model import Grasp
from esmm.pipeline.simulate.run import simulate_network
from esmm.pipeline.simulate.scene import scene_from_dict
from esmm.pipeline.simulate.simulator import Simulator
from esmm.pipeline.simulate.springterm import build_spring_term
from esmm.pipeline.simulate.stepper import stable_step

VISCO = ViscoelasticEffect((0.3, 0.25), (0.03, 0.3))


from esmm.pipeline.mesh.synthetic import box_tets  # noqa: E402  (shared structured box)


def make_tables(kind="nonlinear", mu0=2.0e4, lo=0.5, hi=2.0, n=301):
    """Tables from closed forms on a grid through lambda = 1 (the energy row is unused here)."""
    lam = np.linspace(lo, hi, n)
    if kind == "constant":
        mu = np.full((3, n), mu0)
    elif kind == "linear":
        mu = np.vstack([mu0 * (1 + 0.5 * (lam - 1))] * 3)
    else:                        # stiffening, different per direction
        mu = np.vstack([mu0 * (1 + 4 * (lam - 1) ** 2), mu0 * (1.3 + 2 * (lam - 1) ** 2),
                        mu0 * (0.9 + (lam - 1) ** 2 + 6 * (lam - 1) ** 4)])
    return StiffnessTables(lam_min=lo, lam_max=hi, n=n, values=mu, stress=mu * (lam - 1), energy=np.zeros((3, n)))


def short_scene(**over):
    g = {"radius": "8 mm", "release_time": "0.2 s",
         "waypoints": [{"time": "0 s", "distance": "0 mm"}, {"time": "0.1 s", "distance": "3 mm"}]}
    return scene_from_dict({"scene": {"duration": "0.3 s", "frame_rate": 30, "gravity": [0, 0, 0]},
                            "damping": {"dashpot": "0.2 ms", "velocity_decay": "0.05 s"},
                            "integrator": {"threads": 1}, "grasper": g, **over}, source="test")


def one_spring(L0=0.01, volume=1e-6, cos2=(0.2, 0.3, 0.5)):
    p = np.array([[0.0, 0.0, 0.0], [L0, 0.0, 0.0]])
    return SpringNetwork(points=p, springs=[[0, 1]], rest_length=[L0], volume=[volume],
                         volume_weight=[volume / L0**2], cos2=[cos2], mass=[1e-3, 1e-3],
                         surface_faces=np.zeros((0, 3)))


def chain(n=4, L0=0.005, volume=1e-7, mass=1e-6):
    """n collinear springs along x: under end loads every spring has the same stretch."""
    p = np.zeros((n + 1, 3))
    p[:, 0] = np.arange(n + 1) * L0
    springs = [[k, k + 1] for k in range(n)]
    return SpringNetwork(points=p, springs=springs, rest_length=[L0] * n, volume=[volume] * n,
                         volume_weight=[volume / L0**2] * n, cos2=[(1 / 3, 1 / 3, 1 / 3)] * n,
                         mass=[mass] * (n + 1), surface_faces=np.zeros((0, 3)))


def material_energy(tables, lam):
    """W_d(lam): the integral from 1 of the material stress as the tables define it (piecewise
    linear), by 2-point Gauss-Legendre on every piece (exact for linear pieces), shape (3,)."""
    grid = np.linspace(tables.lam_min, tables.lam_max, tables.n)
    a, b = sorted((1.0, float(lam)))
    knots = np.unique(np.concatenate([[a, b], grid[(grid > a) & (grid < b)]]))
    lo, hi = knots[:-1], knots[1:]
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    xs = np.concatenate([mid - half / math.sqrt(3), mid + half / math.sqrt(3)])
    vals = np.array([np.interp(xs, grid, tables.material_stress[d]) for d in range(3)])
    total = (vals * np.concatenate([half, half])).sum(axis=1)
    return total if lam >= 1.0 else -total


# ---------------------------------------------------------------------------
# one spring: the kernel against the discovery's reference functions
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("law, floor", [("secant", 0.0), ("energy", 0.0), ("energy", 0.55)])
def test_one_spring_history_matches_reference(law, floor):
    tables = make_tables()                                   # anisotropic, stiffening
    cos2 = np.array([0.2, 0.3, 0.5])
    net = one_spring(cos2=tuple(cos2))
    fx = MaterialEffects(VISCO, MullinsEffect(2.5, 300.0, 0.2), DamageEffect(1.25, 0.15, 2.0, floor))
    model = build_spring_term(net, tables, law=law, effects=fx)
    assert model.n_directions == 3
    st = model.effects.new_state(1)
    w = 1e-6 / 0.01 * cos2                                     # c V cos2 / L0 [m2]
    lams = [1.05, 1.2, 1.32, 1.1, 0.97, 0.85, 1.0, 1.18, 1.3, 1.38, 1.2]
    dts = [0.004, 0.01, 0.002, 0.05, 0.02, 0.1, 0.003, 0.01, 0.2, 0.001, 0.03]
    h = np.zeros(2)
    pold, wmax, ximax = 0.0, 0.0, 1.0
    for lam, dt in zip(lams, dts):
        x = net.points.copy()
        x[1, 0] = 0.01 * lam
        f = model.forces(x, state=st, mode=K.FX_STEP, dt=dt)
        fe = float(w @ tables.force_function(lam, law=law))
        W = float(cos2 @ material_energy(tables, lam))
        wmax, ximax = max(wmax, W), max(ximax, float(equivalent_stretch(lam**2 + 2 / lam)))
        p = fe * float(mullins_factor(W, wmax, 2.5, 300.0, 0.2)) * float(damage_factor(ximax, 1.25, 0.15, 2.0, floor))
        h, F = qlv_step(h, pold, p, dt, np.array(VISCO.g), np.array(VISCO.tau))
        pold = p
        assert f[1, 0] == pytest.approx(-F, rel=1e-6, abs=1e-12), lam   # tension pulls node 1 back
        np.testing.assert_allclose(st.h[:, 0], h, rtol=1e-6, atol=1e-12)
        assert st.wmax[0] == pytest.approx(wmax, rel=1e-6) and st.ximax[0] == pytest.approx(ximax, rel=1e-5)
    assert st.ximax[0] > 1.25 and st.wmax[0] > 0               # damage and Mullins were both active


def test_modes_peek_relaxed_settle():
    tables = make_tables("linear")
    net = one_spring()
    model = build_spring_term(net, tables, effects=MaterialEffects(VISCO))
    st = model.effects.new_state(1)
    x = net.points.copy()
    x[1, 0] = 0.012
    fe = build_spring_term(net, tables).forces(x)
    # From the virgin state, with no time elapsed, the response is instantaneous: G(0) = 1.
    np.testing.assert_allclose(model.forces(x), fe, rtol=1e-13)
    before = st.copy()
    f_peek = model.forces(x, state=st, mode=K.FX_PEEK, dt=0.01)
    assert np.array_equal(st.h, before.h) and np.array_equal(st.pold, before.pold)      # unchanged
    f_step = model.forces(x, state=st, mode=K.FX_STEP, dt=0.01)
    np.testing.assert_array_equal(f_peek, f_step)
    # Long-term: g_inf times the elastic force, whatever the history.
    np.testing.assert_allclose(model.forces(x, state=st, mode=K.FX_RELAXED), VISCO.g_inf * fe, rtol=1e-13)
    model.forces(x, state=st, mode=K.FX_SETTLE)
    assert np.all(st.h == 0.0) and st.pold[0] == pytest.approx(-fe[1, 0])
    # Settled: holding the stretch keeps the long-term force (nothing left to relax).
    np.testing.assert_allclose(model.forces(x, state=st, mode=K.FX_STEP, dt=1.0), VISCO.g_inf * fe, rtol=1e-13)


def test_equivalent_stretch_in_the_kernel_matches_reference():
    tables = make_tables("constant")
    net = one_spring()
    fx = MaterialEffects(damage=DamageEffect(1.0, 0.5, 1.0))
    model = build_spring_term(net, tables, effects=fx)
    for lam in (0.45, 0.6, 0.8123, 0.95, 1.0, 1.3):      # below the grid, on and between nodes
        st = model.effects.new_state(1)
        x = net.points.copy()
        x[1, 0] = 0.01 * lam
        model.forces(x, state=st, mode=K.FX_STEP, dt=1e-3)
        assert st.ximax[0] == pytest.approx(float(equivalent_stretch(lam**2 + 2 / lam)), rel=1e-5)


# ---------------------------------------------------------------------------
# stability bounds with effects
# ---------------------------------------------------------------------------

def test_mullins_reloading_tangent_is_bounded():
    tables = make_tables("constant", mu0=1e5)
    net = one_spring(cos2=(1 / 3, 1 / 3, 1 / 3))
    lam1 = 1.3
    W1 = 1e5 * (lam1 - 1) ** 2 / 2
    mu = MullinsEffect(2.0, 0.05 * W1, 0.0)                    # a sharp transition back to the primary curve
    model = build_spring_term(net, tables, effects=MaterialEffects(mullins=mu))
    plain = build_spring_term(net, tables)
    st = model.effects.new_state(1)
    st.wmax[0] = W1
    lam = np.linspace(1.0, lam1, 3001)
    F = np.empty_like(lam)
    for k, la in enumerate(lam):
        x = net.points.copy()
        x[1, 0] = 0.01 * la
        F[k] = -model.forces(x, state=st, mode=K.FX_PEEK)[1, 0]
    slope = np.diff(F) / np.diff(lam * 0.01)                  # dF/dL [N/m]
    cells = np.minimum(((lam[:-1] - model.lam_min) * model.inv_h).astype(int), model.last_cell)
    w = model.sd[1, 0] * model.sd[0, 0]                       # sum_d w_d / L0
    bound = w * model.cell_bound[cells, 0]
    elastic = w * plain.cell_bound[cells, 0]
    assert slope.max() > 3 * elastic.max()                    # the reloading is much stiffer than elastic ...
    assert np.all(slope <= bound * (1 + 1e-9))                # ... and the bound covers it
    assert slope.max() > 0.2 * bound[np.argmax(slope)]        # without being useless


def test_visco_history_forces_enter_the_frame_bound():
    tables = make_tables("constant", mu0=1e5)
    net = network_from_tets(box_tets(3, 2, 2, (0.03, 0.02, 0.02)))
    model = build_spring_term(net, tables, effects=MaterialEffects(VISCO))
    sim = Simulator(model, net.points, net.mass, fixed=np.flatnonzero(net.points[:, 0] < 1e-9))
    assert sim.history_stiffness(0.05).max() == 0.0           # no history yet
    # Stretch the box by 20 %, commit a step, then let it spring back: the history carries force.
    x = net.points * np.array([1.2, 1.0, 1.0])
    model.forces(x, state=sim.fx_state, mode=K.FX_STEP, dt=1e-4)
    extra = sim.history_stiffness(0.05)
    assert extra.max() > 0
    base = stable_step(model, sim.mass, free=sim.free, x=sim.x, window=0.05)
    with_hist = stable_step(model, sim.mass, free=sim.free, x=sim.x, window=0.05, extra_stiffness=extra)
    assert with_hist.dt < base.dt
    # whole-table bound: kappa includes 2 sum(g) max|f| / lam_min per unit weight
    assert np.all(model.kappa > build_spring_term(net, tables).kappa)


# ---------------------------------------------------------------------------
# the simulator: relaxation, Mullins, equilibrium, state
# ---------------------------------------------------------------------------

def _bar():
    net = network_from_tets(box_tets(10, 2, 2, (0.03, 0.006, 0.006)))
    p = net.points
    return net, np.flatnonzero(p[:, 0] < 1e-9), np.flatnonzero(p[:, 0] > 0.03 - 1e-9)


def test_step_stretch_relaxes_like_the_fitted_relaxation_function():
    """A bar stretched by 10 % in 2 ms and held: the reaction relaxes as G(t)."""
    net, left, right = _bar()
    tables = make_tables(mu0=2e6)
    tr, strain, T = 0.002, 0.1, 0.55
    tip0 = net.points[right].mean(axis=0)
    path = np.array([tip0, tip0 + [strain * 0.03, 0, 0]])

    def sim_for(effects):
        m = build_spring_term(net, tables, effects=effects, dashpot=1e-4)
        s = Simulator(m, net.points, net.mass, fixed=left, mass_damping=300.0)
        s.attach(Grasp(nodes=right, offsets=net.points[right] - tip0, wp_t=np.array([0.0, tr]), wp_x=path))
        return s

    # The elastic (instantaneous) reaction at the held stretch: static equilibrium of the plain network.
    el = Simulator(build_spring_term(net, tables), net.points, net.mass, fixed=left)
    el.attach(Grasp(nodes=right, offsets=net.points[right] - tip0, wp_t=np.array([0.0]), wp_x=path[1:]))
    el.relax(rtol=1e-12)
    f_inst = -el.grasper_force()[0]
    assert f_inst > 0

    sim = sim_for(MaterialEffects(VISCO))
    n = int(T / sim.dt)
    rec = sim.advance(n)
    t = np.arange(n) * sim.dt
    ratio = -rec[:, 0] / f_inst
    g, tau, ginf = np.array(VISCO.g), np.array(VISCO.tau), VISCO.g_inf
    ramp = ginf + (g * tau / tr * (np.exp(-(t[:, None] - tr) / tau) - np.exp(-t[:, None] / tau))).sum(axis=1)
    G = VISCO.relaxation(t - tr / 2)
    sel = t >= 0.02                                            # after the bar's elastic waves have died out
    assert np.abs(ratio[sel] / ramp[sel] - 1).max() < 0.01     # the exact QLV ramp-hold response
    assert np.abs(ratio[sel] / G[sel] - 1).max() < 0.02        # the fitted relaxation function
    assert ratio[-1] < 0.52 and ratio[np.searchsorted(t, 0.02)] > 0.8      # it did relax a lot
    # Long-term: the relaxed equilibrium carries g_inf of the elastic reaction.
    sim.relax(rtol=1e-12)
    assert -sim.grasper_force()[0] == pytest.approx(ginf * f_inst, rel=1e-6)


def test_mullins_reload_below_the_maximum_is_softer_by_eta():
    net = chain()
    tables = make_tables("linear", mu0=2e5)
    L = 4 * 0.005
    lam1, lam2 = 1.3, 1.15
    W = lambda lam: float(np.full(3, 1 / 3) @ material_energy(tables, lam))   # noqa: E731
    mu = MullinsEffect(2.0, 0.3 * W(lam1), 0.1)
    model = build_spring_term(net, tables, effects=MaterialEffects(mullins=mu))
    sim = Simulator(model, net.points, net.mass, fixed=[0], mass_damping=2000.0)
    # load to lam1, unload to 1, reload to 1.4 (back on the primary path beyond lam1)
    knots_t = np.array([0.0, 0.15, 0.3, 0.51])
    knots_s = np.array([1.0, lam1, 1.0, 1.42])
    tip0 = net.points[-1]
    sim.attach(Grasp(nodes=np.array([4]), offsets=np.zeros((1, 3)), wp_t=knots_t,
                     wp_x=tip0 + np.outer((knots_s - 1) * L, [1, 0, 0])))
    n = int(0.51 / sim.dt)
    rec = sim.advance(n)
    t = np.arange(n) * sim.dt
    stretch = np.interp(t, knots_t, knots_s)
    force = rec[:, 0]                                          # the chain pulls the grasper back: < 0 ...
    fe = -np.array([float(model.sd[1, 0] * tables.force_function(s, law="secant")[0]) for s in (lam2,)])[0]

    def at(s, phase):
        k = np.flatnonzero((stretch > s - 1e-3) & (stretch < s + 1e-3) & phase)
        return force[k].mean(), stretch[k].mean()

    first, s1 = at(lam2, t < 0.15)
    reload, s2 = at(lam2, t > 0.3)
    eta = float(mullins_factor(W(lam2), W(lam1), mu.r, mu.m, mu.beta))
    assert eta < 0.8
    assert first == pytest.approx(fe, rel=5e-3)               # primary path: the elastic force
    assert reload / first == pytest.approx(eta, rel=5e-3)     # reloading: softened by eta
    beyond, _ = at(1.4, t > 0.3)                               # past lam1: back on the primary curve
    fe14 = -float(model.sd[1, 0] * tables.force_function(1.4, law="secant")[0])
    assert beyond == pytest.approx(fe14, rel=5e-3)


def test_long_term_sag_is_elastic_sag_over_g_inf():
    net = network_from_tets(box_tets(6, 2, 2, (0.06, 0.02, 0.02)))
    tables = make_tables("constant", mu0=5e7)
    fixed = np.flatnonzero(net.points[:, 0] < 1e-9)
    sags = []
    for fx in (None, MaterialEffects(VISCO)):
        sim = Simulator(build_spring_term(net, tables, effects=fx), net.points, net.mass, fixed=fixed,
                        gravity=(0, 0, -9.81))
        sim.relax(rtol=1e-10)
        sags.append(-sim.displacement()[:, 2].min())
    assert 1e-6 < sags[0] < 1e-4                                # < 0.2 % of the length: ~linear
    assert sags[1] / sags[0] == pytest.approx(1 / VISCO.g_inf, rel=2e-3)     # geometrically ~linear


def _box_sim(threads=1):
    net = network_from_tets(box_tets(4, 3, 3, (0.04, 0.03, 0.03)))
    tables = make_tables()
    fx = MaterialEffects(VISCO, MullinsEffect(2.0, 50.0, 0.1), DamageEffect(1.05, 0.2, 1.5))
    model = build_spring_term(net, tables, effects=fx, dashpot=2e-4)
    sim = Simulator(model, net.points, net.mass, fixed=np.flatnonzero(net.points[:, 0] < 1e-9),
                    gravity=(0, 0, -9.81), mass_damping=5.0, threads=threads)
    tgt = int(np.argmax(net.points[:, 0] + net.points[:, 2]))
    sim.attach(Grasp(nodes=np.array([tgt]), offsets=np.zeros((1, 3)), wp_t=np.array([0.0, 0.02, 0.04]),
                     wp_x=net.points[tgt] + np.array([[0, 0, 0], [0.004, 0, 0.008], [0.0, 0, 0.002]])))
    return sim


def test_state_survives_snapshot_and_restore():
    sim = _box_sim()
    sim.advance(150)
    snap = sim.snapshot()
    r1 = sim.advance(300).copy()
    x1, st1 = sim.x.copy(), sim.fx_state.copy()
    assert np.abs(st1.h).max() > 0 and st1.wmax.max() > 0 and st1.ximax.max() > 1.05
    sim.restore(snap)
    assert not np.array_equal(sim.fx_state.h, st1.h)
    r2 = sim.advance(300)
    np.testing.assert_array_equal(r1, r2)
    np.testing.assert_array_equal(sim.x, x1)
    for a, b in zip(sim.fx_state.arrays(), st1.arrays()):
        np.testing.assert_array_equal(a, b)
    assert sim.fx_state.t == st1.t


@pytest.mark.slow        # the threaded kernel under libgomp on a shared machine: seconds
def test_threaded_trajectory_with_effects_matches_serial():
    import numba

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("needs 2 threads")
    a, b = _box_sim(1), _box_sim(2)
    ra, rb = a.advance(200), b.advance(200)
    np.testing.assert_allclose(b.x, a.x, rtol=0, atol=1e-15 * np.abs(a.x).max() * 10)
    np.testing.assert_allclose(rb, ra, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(b.fx_state.h, a.fx_state.h, rtol=1e-9, atol=1e-18)


# ---------------------------------------------------------------------------
# whole runs
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def slab():
    net = network_from_tets(box_tets(6, 3, 2, (0.06, 0.03, 0.015)))
    return net.with_fixed(np.flatnonzero(net.points[:, 0] < 1e-9))


def test_equilibrium_start_with_viscoelasticity_has_no_transient(tmp_path, slab):
    sc = scene_from_dict({"scene": {"duration": "0.2 s", "start": "equilibrium"}, "grasper": {"enabled": False},
                          "integrator": {"threads": 1}}, source="test")
    res = simulate_network(slab, make_tables(mu0=2e5), sc, tmp_path, effects=MaterialEffects(VISCO))
    with History(res.history) as h:
        u0, u1 = h.displacement(0), h.displacement(h.n_frames - 1)
    assert np.abs(u0).max() > 1e-6                               # it sags under gravity ...
    assert np.abs(u1 - u0).max() < 1e-4 * np.abs(u0).max()       # ... and stays there (relaxed history)


def test_run_records_the_effects_used(tmp_path, slab):
    fx = MaterialEffects(VISCO, MullinsEffect(2.0, 100.0, 0.0))
    res = simulate_network(slab, make_tables(mu0=2e5), short_scene(), tmp_path / "on", effects=fx)
    s = json.loads((tmp_path / "on" / "summary.json").read_text())
    assert s["effects"]["final_state"]["effects"] == ["viscoelastic", "mullins"]
    assert s["effects"]["viscoelastic"]["g"] == list(VISCO.g) and s["effects"]["g_inf"] == VISCO.g_inf
    assert s["effects"]["final_state"]["max_energy_density_Pa"] > 0
    assert s["effects_available"] == ["viscoelastic", "mullins"]
    with History(res.history) as h:
        assert json.loads(h.attrs["effects"])["mullins"]["r"] == 2.0
        t_on, f_on = h.forces()
    # switched off by the scene: the plain elastic run, recorded as such
    off = simulate_network(slab, make_tables(mu0=2e5), short_scene().with_overrides(effects="none"), tmp_path / "off",
                           effects=fx)
    assert off.summary.effects is None and off.summary.effects_available == ["viscoelastic", "mullins"]
    with History(off.history) as h:
        assert "effects" not in h.attrs
        t_off, f_off = h.forces()
    # While pulling, QLV relaxes the reaction: a smaller force than the elastic one at the same time.
    k = np.searchsorted(t_on, 0.099)
    j = np.searchsorted(t_off, t_on[k])
    assert 0 < np.linalg.norm(f_on[k]) < 0.97 * np.linalg.norm(f_off[j])


def test_effects_from_a_material_table():
    from esmm.pipeline.simulate.effects import effects_of_material

    mat = SimpleNamespace(name="fit", stress_unit="kPa", metadata={"effects": {
        "viscoelastic": {"reference": "instantaneous", "g": [0.2], "tau": ["50 ms"]},
        "mullins": {"r": 3.0, "m": 1.5, "beta": 0.0}}})
    fx = effects_of_material(mat)
    assert fx.viscoelastic.tau == (0.05,) and fx.mullins.m == pytest.approx(1500.0)
    assert effects_of_material(SimpleNamespace(metadata={})) is None
    assert math.isclose(build_spring_term(one_spring(), make_tables(), effects=fx).effects.g_inf, 0.8)


def test_effects_the_kernels_do_not_advance_are_refused_not_dropped():
    """Stretch-dependent relaxation (kappa != 0) was applied as plain QLV without a word; cyclic softening
    was already refused. Both are one ConfigError line; kappa = 0 builds."""
    from esmm.pipeline.errors import ConfigError
    from esmm.pipeline.materials.effects import CyclicSofteningEffect

    net, tb = one_spring(), make_tables()
    nl = MaterialEffects(viscoelastic=ViscoelasticEffect(g=(0.3,), tau=(0.1,), kappa=-3.2))
    with pytest.raises(ConfigError, match=r"cannot apply stretch-dependent relaxation \(viscoelastic kappa = -3.2\)"):
        build_spring_term(net, tb, effects=nl)
    cyc = MaterialEffects(cyclic_softening=CyclicSofteningEffect(d_inf=0.2, eta=1e3))
    with pytest.raises(ConfigError, match="cannot apply 'cyclic_softening'"):
        build_spring_term(net, tb, effects=cyc)
    qlv = MaterialEffects(viscoelastic=ViscoelasticEffect(g=(0.3,), tau=(0.1,)))
    assert build_spring_term(net, tb, effects=qlv).effects.g_inf == pytest.approx(0.7)


# ---------------------------------------------------------------------------
# the effects travel: params.toml -> asset -> simulator
# ---------------------------------------------------------------------------

EFFECTS_TOML = """
[material.effects.viscoelastic]
reference = "instantaneous"
g = [0.3, 0.25]
tau = ["30 ms", "0.3 s"]
[material.effects.mullins]
r = 2.0
m = "1.5 kPa"
beta = 0.1
[material.effects.damage]
onset = 1.4
scale = 0.2
shape = 2.0
"""


@pytest.fixture()
def fit_material(tmp_path):
    from esmm.pipeline.materials.material import load_material

    p = tmp_path / "params.toml"
    p.write_text(load_material("porcine_liver_paper").to_toml() + EFFECTS_TOML, encoding="utf-8")
    return load_material(str(p))


def _asset(tmp_path, material):
    from esmm.pipeline.asset import write_asset
    from esmm.pipeline.network.tables import build_tables

    net = network_from_tets(box_tets(3, 2, 2, (0.03, 0.02, 0.02)))
    net = net.with_fixed(np.flatnonzero(net.points[:, 0] < 1e-9))
    return write_asset(tmp_path / "a.h5", net, material=material, tables=build_tables(material))


def test_asset_carries_the_effects(tmp_path, fit_material):
    import h5py
    from esmm.pipeline.asset import read_asset, validate_asset

    path = _asset(tmp_path, fit_material)
    assert validate_asset(path) == []
    a = read_asset(path)
    assert a.effects.names == ["viscoelastic", "mullins", "damage"]
    assert a.effects.viscoelastic.tau == (0.03, 0.3) and a.effects.mullins.m == pytest.approx(1500.0)
    assert a.summary()["effects"]["damage"]["onset"] == 1.4
    with h5py.File(path) as f:
        g = f["/material/effects"]
        assert g.attrs["esmm_type"] == "material_effects" and g.attrs["esmm_version"] == 1
        assert g["viscoelastic/tau"].attrs["units"] == "s" and g["mullins/m"].attrs["units"] == "Pa"
        np.testing.assert_array_equal(g["viscoelastic/g"][()], [0.3, 0.25])
    # the simulator reads them
    from esmm.pipeline.simulate.run import read_asset_for_simulation

    *_, fx = read_asset_for_simulation(path, with_effects=True)
    assert fx.names == ["viscoelastic", "mullins", "damage"]


def test_effects_an_asset_cannot_store_are_said_not_dropped(tmp_path):
    """Cyclic softening, permanent set and kappa were dropped at writing without a word (prepare said they
    were 'applied by esmm simulate'), and an asset with only the first two failed 'esmm info'. The
    asset stores what the simulator applies; the rest comes back as notes, which prepare warns with."""
    from esmm.pipeline.asset import read_asset, validate_asset
    from esmm.pipeline.asset.material import storable_effects
    from esmm.pipeline.materials.effects import CyclicSofteningEffect, PermanentSetEffect
    from esmm.pipeline.materials.material import load_material

    fx = MaterialEffects(ViscoelasticEffect((0.3,), (2.0,), kappa=-4.0), None, None, {},
                         CyclicSofteningEffect(0.2, 150.0), PermanentSetEffect(0.1))
    kept, notes = storable_effects(fx)
    assert kept.names == ["viscoelastic"] and kept.viscoelastic.kappa == 0.0
    assert [n.split(" ")[0] for n in notes] == ["cyclic_softening", "permanent_set", "the"]
    assert "kappa = -4" in notes[2]
    assert storable_effects(MaterialEffects(cyclic_softening=CyclicSofteningEffect(0.2, 150.0)))[0] is None
    base = load_material("porcine_liver_paper")
    p = tmp_path / "params.toml"
    p.write_text(base.to_toml() + "[material.effects.cyclic_softening]\nd_inf = 0.2\neta = 150.0\n",
                 encoding="utf-8")
    path = _asset(tmp_path, load_material(str(p)))
    assert validate_asset(path) == [] and read_asset(path).effects is None


def test_a_damage_floor_travels_to_the_asset_and_the_simulator(tmp_path, fit_material):
    """A damage with a floor (the fraction of the stress it leaves) is stored, read back and applied; an asset
    without one is written as before and reads a floor of 0."""
    import h5py
    from esmm.pipeline.asset import read_asset, validate_asset
    from esmm.pipeline.materials.material import load_material
    from esmm.pipeline.simulate.run import read_asset_for_simulation

    p = tmp_path / "params.toml"
    p.write_text(load_material("porcine_liver_paper").to_toml() + EFFECTS_TOML + "floor = 0.6\n", encoding="utf-8")
    path = _asset(tmp_path, load_material(str(p)))
    assert validate_asset(path) == []
    assert read_asset(path).effects.damage.floor == 0.6
    *_, got = read_asset_for_simulation(path, with_effects=True)
    assert got.damage.factor(np.array([50.0]))[0] == pytest.approx(0.6)
    (tmp_path / "old").mkdir()
    old = _asset(tmp_path / "old", fit_material)
    with h5py.File(old) as f:  # an asset without a floor is written as before
        assert "floor" not in f["/material/effects/damage"]
    assert read_asset(old).effects.damage.floor == 0.0


def test_asset_without_effects_has_none(tmp_path):
    from esmm.pipeline.asset import read_asset
    from esmm.pipeline.materials.material import load_material

    path = _asset(tmp_path, load_material("porcine_liver_paper"))
    a = read_asset(path)
    assert a.effects is None and a.summary()["effects"] is None


def test_edited_effects_are_reported(tmp_path, fit_material):
    import h5py
    from esmm.pipeline.asset import validate_asset
    from esmm.pipeline.asset.hdf5 import seal

    path = _asset(tmp_path, fit_material)
    with h5py.File(path, "r+") as f:                  # a consistent re-seal: only the content check can see it
        ds = f["/material/effects/viscoelastic/tau"]
        ds[...] = [0.03, 3.0]
        seal(f)
    problems = validate_asset(path)
    assert any("disagrees with /material/toml" in p and "tau" in p for p in problems), problems
    with h5py.File(path, "r+") as f:
        f["/material/effects/viscoelastic/g"][...] = [0.9, 0.5]          # sum > 1
        seal(f)
    assert any("weights g must be >= 0 with sum <= 1" in p for p in validate_asset(path))


@pytest.mark.slow
def test_end_to_end_discover_prepare_info_simulate(run_cli, tmp_path):
    """A synthetic viscoelastic tensile set -> discover -> prepare a liver -> info -> simulate."""
    from esmm.pipeline.discover import synthetic as syn

    truth = syn.Truth("arruda-boyce", {"mu": 20e3, "N": 4.0}, viscoelastic={"g": [0.4, 0.2], "tau": [1.0, 20.0]})
    files = syn.write_set(tmp_path / "data", [syn.load_unload(0.01, 1.5), syn.load_unload(0.1, 1.5)], truth, seed=1)
    code, out, err = run_cli("calibrate", *files, "--discover", "--model", "arruda-boyce", "--starts", "2",
                             "--out", tmp_path / "fit")
    assert code == 0, err
    assert "[material.effects.viscoelastic]" in (tmp_path / "fit" / "params.toml").read_text()
    stl = __import__("pathlib").Path(__file__).resolve().parents[1] / "data" / "meshes" / "ts_liver_3mm_closed.stl"
    # (--no-compensate: the compensation's virtual tensile test is orthogonal to the effects and slow)
    code, out, err = run_cli("prepare", stl, "--config", "coarse", "--material", tmp_path / "fit" / "params.toml",
                             "--no-compensate", "-o", tmp_path / "liver.h5")
    assert code == 0, err
    assert "material effects viscoelastic: written to /material/effects" in out + err
    code, out, err = run_cli("info", tmp_path / "liver.h5", "--json")
    assert code == 0, err
    info = json.loads(out)
    assert info["valid"] and info["summary"]["effects"]["names"] == ["viscoelastic"]
    g = info["summary"]["effects"]["viscoelastic"]["g"]
    assert len(g) == 2 and abs(sum(g) - 0.6) < 0.05          # the hidden truth: g = 0.4 + 0.2
    code, out, err = run_cli("simulate", tmp_path / "liver.h5", "--duration", "0.2 s", "--threads", "1",
                             "--out", tmp_path / "sim")
    assert code == 0, err
    assert "material effects: viscoelastic" in out
    s = json.loads((tmp_path / "sim" / "summary.json").read_text())
    assert s["effects"]["final_state"]["effects"] == ["viscoelastic"]
    assert s["effects"]["viscoelastic"]["tau"] == info["summary"]["effects"]["viscoelastic"]["tau"]


def test_tables_with_a_fit_material_carry_its_effects(tmp_path, fit_material):
    """esmm tables ASSET --material params.toml: the rewritten asset has the new material's effects."""
    from esmm.pipeline.asset import read_asset, update_asset_tables, validate_asset
    from esmm.pipeline.materials.material import load_material
    from esmm.pipeline.network.tables import build_tables

    path = _asset(tmp_path, load_material("porcine_liver_paper"))
    assert read_asset(path).effects is None
    update_asset_tables(path, build_tables(fit_material), material=fit_material)
    assert validate_asset(path) == []
    assert read_asset(path).effects.names == ["viscoelastic", "mullins", "damage"]


def test_prepare_refuses_malformed_effects_before_meshing(run_cli, tmp_path):
    from esmm.pipeline.materials.material import load_material

    p = tmp_path / "bad.toml"
    p.write_text(load_material("porcine_liver_paper").to_toml()
                 + '[material.effects.viscoelastic]\ng = [0.7, 0.6]\ntau = ["1 s", "2 s"]\n', encoding="utf-8")
    stl = __import__("pathlib").Path(__file__).resolve().parents[1] / "data" / "meshes" / "ts_liver_3mm_closed.stl"
    code, out, err = run_cli("prepare", stl, "--config", "coarse", "--material", p, "--no-compensate",
                             "-o", tmp_path / "x.h5")
    assert code == 2 and "sum <= 1" in err and "Traceback" not in err
    assert not (tmp_path / "x.h5").exists()
