"""The simulator's volume term (pipeline/simulate/volumeterm.py) against the numpy reference and analytic truth."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from esmm.pipeline.network.volume import VolumeSpec, bulk_modulus
from esmm.pipeline.simulate import kernels as K
from esmm.pipeline.simulate.simulator import Simulator
from esmm.pipeline.simulate.springterm import build_spring_term
from esmm.pipeline.simulate.stepper import stable_step
from esmm.pipeline.simulate.volumeterm import build_volume_term, shape_change
from simkit import jittered_box_network

KAPPA = 4.0e5   # Pa: ~80 times the liver's small-strain shear modulus


@pytest.fixture(scope="module")
def box():
    return jittered_box_network((5, 4, 3), (0.05, 0.04, 0.03), jitter=1.5e-3, seed=7)


@pytest.fixture(scope="module")
def vol(box, tables):
    return build_volume_term(box.points, box.tets, VolumeSpec(KAPPA), lam_max=tables.lam_max)


def shaken(box, scale=5e-4, seed=0):
    return box.points + scale * np.random.default_rng(seed).standard_normal(box.points.shape)


def test_kernel_matches_reference_serial_and_threaded(box, vol, tables):
    x = shaken(box)
    ref = vol.elements.forces(x)
    f = vol.forces(x)
    np.testing.assert_allclose(f, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    springs = build_spring_term(box, tables)
    fs = springs.forces(x)
    z = np.zeros_like(x)
    for chunks in (1, 2, 3, 7):         # one chunk: the scatter; more: the gathering passes (run serially here)
        g = np.zeros_like(x)
        K.forces_serial(x, z, g, z, springs.kernel(), None, springs.layout(chunks), vol.kernel())
        np.testing.assert_allclose(g - fs, ref, rtol=0, atol=1e-11 * np.abs(ref).max())


def test_force_pass_adds_the_volume_term(box, vol, tables):
    springs = build_spring_term(box, tables)
    x = shaken(box)
    v = np.zeros_like(x)
    fe = np.zeros_like(x)
    both = np.empty_like(x)
    K.forces_serial(x, v, both, fe, springs.kernel(), None, springs.layout(1), vol.kernel())
    expect = springs.forces(x) + vol.elements.forces(x)
    np.testing.assert_allclose(both, expect, rtol=0, atol=1e-12 * np.abs(expect).max())
    par = np.empty_like(x)
    K.forces_parallel(x, v, par, fe, springs.kernel(), None, springs.layout(3), vol.kernel())
    np.testing.assert_allclose(par, expect, rtol=0, atol=1e-12 * np.abs(expect).max())


@pytest.mark.parametrize("effects", [False, True])
def test_springs_beside_the_volume_term_on_two_threads_give_the_same_sum_bit_for_bit(box, vol, tables, effects):
    """The implicit stepper's two-thread force pass (the springs on one thread, the volume term on the
    other): the same numbers as the two passes one after the other, with dashpots, with material
    effects in each mode (the effect state committed the same way too), and through the stepper's
    own force pass on one and on two threads."""
    from esmm.pipeline.materials.effects import MaterialEffects, MullinsEffect, ViscoelasticEffect
    from esmm.pipeline.simulate.implicit import BackwardEuler
    from esmm.pipeline.simulate.implicit_system import forces

    fx = MaterialEffects(ViscoelasticEffect((0.3,), (0.05,)), MullinsEffect(2.0, 2.0, 0.1)) if effects else None
    springs = build_spring_term(box, tables, dashpot=2e-4, effects=fx)
    x, v = shaken(box), 1e-3 * np.random.default_rng(3).standard_normal(box.points.shape)
    fe = np.random.default_rng(4).standard_normal(box.points.shape)
    modes = (K.FX_PEEK, K.FX_STEP, K.FX_PEEK) if effects else (K.FX_PEEK,)
    s1, s2 = (springs.new_state() for _ in range(2))
    for mode in modes:
        one = springs.forces(x, v, fext=fe, state=s1, mode=mode, dt=1e-3) + vol.forces(x)
        two = springs.forces(x, v, fext=fe, state=s2, mode=mode, dt=1e-3, beside=vol.kernel())
        np.testing.assert_array_equal(two, one)
        if effects:
            for name in ("h", "pold", "wmax", "ximax"):
                np.testing.assert_array_equal(getattr(s2, name), getattr(s1, name))
    sim = Simulator(springs, box.points, box.mass, gravity=(0, 0, -9.81), volume=vol,
                    stepper=BackwardEuler(step=1 / 30))
    f1, f2 = (forces(sim.model, sim.state, x, v, 1e-3, threads=t) for t in (1, 2))
    np.testing.assert_array_equal(f2, f1)
    assert np.abs(f1 - sim.model.springs.forces(x, v, fext=sim.model.fext, state=sim.state.effects,
                                                dt=1e-3)).max() > 0   # the volume term is in it


def test_tangent_is_minus_the_force_jacobian(box, vol):
    x = shaken(box, 2e-3)
    Kt = vol.tangent(x)
    assert isinstance(Kt, sp.csr_matrix) and Kt.shape == (3 * box.n_nodes,) * 2
    assert abs(Kt - Kt.T).max() <= 1e-12 * abs(Kt).max()
    h = 1e-8
    rng = np.random.default_rng(4)
    for _ in range(5):
        d = rng.standard_normal(x.shape)
        num = -(vol.forces(x + h * d) - vol.forces(x - h * d)).ravel() / (2 * h)
        np.testing.assert_allclose(Kt @ d.ravel(), num, rtol=0, atol=3e-6 * np.abs(num).max())


def test_no_net_force_torque_and_rigid_motion(box, vol):
    x = shaken(box, 2e-3)
    f = vol.forces(x)
    s = np.abs(f).sum()
    assert np.abs(f.sum(axis=0)).max() < 1e-12 * s
    assert np.abs(np.cross(x - x.mean(axis=0), f).sum(axis=0)).max() < 1e-12 * s * 0.05
    th = 1.1
    R = np.array([[1, 0, 0], [0, np.cos(th), -np.sin(th)], [0, np.sin(th), np.cos(th)]])
    xr = box.points @ R.T + [0.3, 0.0, -0.1]
    assert np.abs(vol.forces(xr)).max() < 1e-9 * s / box.n_nodes


def test_stability_bound_covers_springs_plus_volume(box, vol, tables):
    springs = build_spring_term(box, tables)
    m = box.mass
    from esmm.pipeline.network.forcelaw import tangent_stiffness

    for x in (box.points, shaken(box, 1e-3)):
        Kt = (tangent_stiffness(x, box, tables) + vol.tangent(x)).toarray()
        Mi = 1.0 / np.sqrt(np.repeat(m, 3))
        w2 = np.linalg.eigvalsh(Mi[:, None] * Kt * Mi[None, :]).max()
        b = stable_step([springs, vol], m, x=x, window=0.05, safety=1.0)
        assert b.omega_max**2 >= w2
        assert b.omega_max**2 < 8 * w2
    whole = stable_step([springs, vol], m, safety=1.0)
    assert whole.omega_max >= b.omega_max


def test_relaxed_box_keeps_its_volume_and_the_switch_works(box, vol, tables):
    springs = build_spring_term(box, tables)
    fixed = np.flatnonzero(box.points[:, 0] < 1e-3 + box.points[:, 0].min())
    out = {}
    for name, v in (("off", None), ("on", vol)):
        sim = Simulator(springs, box.points, box.mass, fixed=fixed, gravity=(0, 0, -9.81) , volume=v)
        assert len(sim.model.terms) == (1 if v is None else 2)
        sim.relax(rtol=1e-6, max_iter=400_000)
        out[name] = shape_change(box.points, box.tets, sim.x, (0, 0, -9.81))
        # the Python-level forces agree with the compiled pass: the relaxed state is balanced
        f = sim.forces()
        assert np.abs(f[sim.free]).max() < 1e-5 * np.abs(sim.fext).max()
    assert abs(out["on"]["volume_ratio"] - 1) < 0.1 * abs(out["off"]["volume_ratio"] - 1)
    assert out["on"]["inverted_tets"] == 0


def test_energy_is_conserved_with_the_volume_term(box, vol, tables):
    springs = build_spring_term(box, tables, law="energy")
    fixed = np.flatnonzero(box.points[:, 0] < 1e-3 + box.points[:, 0].min())
    from esmm.pipeline.network.forcelaw import spring_energy

    def total(sim):
        return (sim.kinetic_energy() + sim.gravity_energy() + spring_energy(sim.x, box, tables, law="energy")
                + vol.energy(sim.x))

    errs = []
    for frac in (0.4, 0.2):
        sim = Simulator(springs, box.points, box.mass, fixed=fixed, gravity=(0, 0, -9.81), volume=vol)
        sim.set_time_step(frac * sim.bound.dt_critical)
        e0 = total(sim)
        es = []
        for _ in range(40):
            sim.advance(max(1, int(2e-3 / sim.dt)))
            es.append(total(sim))
        ke = max(sim.kinetic_energy(), 1e-30)
        errs.append(np.abs(np.array(es) - e0).max())
        assert errs[-1] < 0.02 * (abs(sim.gravity_energy()) + ke)
    assert errs[1] < 0.75 * errs[0]          # first order in dt


def test_threaded_trajectory_equals_serial(box, vol, tables):
    springs = build_spring_term(box, tables)
    fixed = np.flatnonzero(box.points[:, 0] < 1e-3 + box.points[:, 0].min())
    runs = []
    for threads in (1, 2):
        sim = Simulator(springs, box.points, box.mass, fixed=fixed, gravity=(0, 0, -9.81), volume=vol,
                        threads=threads)
        sim.advance(300)
        runs.append(sim.x.copy())
    np.testing.assert_allclose(runs[1], runs[0], rtol=0, atol=1e-13)


def test_gravity_keeps_the_volume_within_one_percent_with_the_term_and_not_without(box, tables):
    """Issue 11's target on a cantilever that sags by more than half its height: |dV/V| < 1 % and no inverted
    tet with the volume term the asset gets (the bulk rule), more than 1 % without it."""
    vol = build_volume_term(box.points, box.tets, bulk_modulus(tables), lam_max=tables.lam_max)
    springs = build_spring_term(box, tables)
    fixed = np.flatnonzero(box.points[:, 0] < 1e-3 + box.points[:, 0].min())
    out = {}
    for name, v in (("off", None), ("on", vol)):
        sim = Simulator(springs, box.points, box.mass, fixed=fixed, gravity=(0, 0, -9.81), volume=v)
        sim.relax(rtol=1e-6, max_iter=400_000)
        out[name] = shape_change(box.points, box.tets, sim.x, (0, 0, -9.81))
    assert out["on"]["sag_max_m"] > 0.5 * np.ptp(box.points[:, 2])      # a large deformation
    assert abs(out["on"]["volume_ratio"] - 1) < 0.01 and out["on"]["inverted_tets"] == 0
    assert abs(out["off"]["volume_ratio"] - 1) > 0.01


@pytest.mark.slow
@pytest.mark.parametrize("factor_matrix,iteration", [("bound", "quasi-newton"), ("exact", "quasi-newton"),
                                                     ("mixed", "quasi-newton"), ("bound", "newton")])
def test_implicit_stepper_takes_the_volume_term_at_the_frame_step(box, tables, factor_matrix, iteration):
    """The implicit stepper sums every term's forces and tangent (docs/design/simulator.md, "Scheme"): with the volume
    term it is stable at 1/30 s, settles on the same equilibrium as FIRE and keeps the volume within 1 %,
    whether its preconditioner factors the volume term's per-tet bound (the default), its tangent or the
    saddle point of its parts, and whether its solves iterate by quasi-Newton (the default) or Newton."""
    from esmm.pipeline.simulate.implicit import BackwardEuler

    vol = build_volume_term(box.points, box.tets, bulk_modulus(tables), lam_max=tables.lam_max)
    springs = build_spring_term(box, tables)
    fixed = np.flatnonzero(box.points[:, 0] < 1e-3 + box.points[:, 0].min())
    ref = Simulator(springs, box.points, box.mass, fixed=fixed, gravity=(0, 0, -9.81), volume=vol)
    ref.relax(rtol=1e-6, max_iter=400_000)
    stepper = BackwardEuler(step=1 / 30, factor_matrix=factor_matrix, iteration=iteration)
    sim = Simulator(springs, box.points, box.mass, fixed=fixed, gravity=(0, 0, -9.81), volume=vol,
                    mass_damping=1 / 0.15, stepper=stepper)
    assert len(sim.model.terms) == 2
    sim.set_time_step(1 / 30, bound=stepper.bound(sim.model, sim.control), t0=0.0)
    sim.advance(90)                                            # 3 s: ~20 decay times of the mass damping
    assert np.all(np.isfinite(sim.x))
    sag = np.linalg.norm(ref.x - box.points, axis=1).max()
    assert np.linalg.norm(sim.x - ref.x, axis=1).max() < 0.02 * sag
    shape = shape_change(box.points, box.tets, sim.x, (0, 0, -9.81))
    assert abs(shape["volume_ratio"] - 1) < 0.01 and shape["inverted_tets"] == 0
    rep = stepper.report()
    assert rep["unconverged"] == 0                            # every step met the tolerance
    if iteration == "newton":
        assert rep["newton"] / rep["steps"] < 4               # Newton with the volume tangent: few iterations
    else:
        assert rep["quasi_newton"] > 0


def test_implicit_factor_of_the_volume_bound_has_less_fill(box, tables):
    """The reused factor with the volume term's per-tet bound (default) has less fill than the factor of
    Newton's matrix itself (whose volume blocks reach two tets away), on the same state; the saddle point
    of its parts (the "mixed" factor, Newton's matrix too) lies between."""
    from esmm.pipeline.simulate.implicit import BackwardEuler

    vol = build_volume_term(box.points, box.tets, bulk_modulus(tables), lam_max=tables.lam_max)
    springs = build_spring_term(box, tables)
    fill = {}
    for fm in ("bound", "exact", "mixed"):
        stepper = BackwardEuler(step=1 / 30, factor_matrix=fm)
        sim = Simulator(springs, box.points, box.mass, fixed=np.arange(4), volume=vol, stepper=stepper)
        sim.set_time_step(1 / 30, bound=stepper.bound(sim.model, sim.control), t0=0.0)
        stepper.prepare(sim.model, sim.state, sim.control)
        fill[fm] = stepper.report()["factor_nnz"]
    assert fill["bound"] < 0.8 * fill["exact"]
    assert fill["bound"] < fill["mixed"] < fill["exact"]


@pytest.mark.parametrize("single", [False, True])
def test_mixed_factor_solves_newtons_matrix(box, vol, tables, single):
    """The saddle-point factor of ``A + B^T diag(w) B`` (the springs' matrix and the volume term's parts, at
    a shaken state, fixed dofs' columns of B zero) solves that matrix: to round-off in float64, to the
    float32 factor's ~1e-4 (a preconditioner) in float32; one and three right-hand sides; the parts of
    one term or of two (stacked rows, each node's next to its dofs)."""
    from esmm.pipeline.linalg.linsolve import MixedFactor

    x = shaken(box)
    springs = build_spring_term(box, tables)
    free = np.ones(3 * box.n_nodes)
    free[:12] = 0.0                                   # four fixed nodes: identity rows
    Fd = sp.diags(free)
    A = (Fd @ springs.tangent(x, definite=True) @ Fd + sp.diags(0.5 * free + (1 - free))).tocsr()
    B, w = vol.tangent_parts(x)
    B = (B @ Fd).tocsr()
    K = (A + B.T @ sp.diags(w) @ B).tocsr()
    assert abs(K - (A + Fd @ vol.tangent(x, definite=True) @ Fd)).max() < 1e-9 * abs(K).max()
    rng = np.random.default_rng(3)
    b = rng.standard_normal((3 * box.n_nodes, 3))
    tol = 1e-3 if single else 1e-10
    stacked = (sp.vstack([B, B]).tocsr(), np.concatenate([0.25 * w, 0.75 * w]))    # two terms' parts
    for fac in (MixedFactor.of_parts(A, B, w, single=single), MixedFactor.of_parts(A, *stacked, single=single)):
        for rhs in (b[:, 0], b):
            y = fac.solve(rhs)
            assert y.shape == rhs.shape
            assert np.linalg.norm(K @ y - rhs) <= tol * np.linalg.norm(rhs)
