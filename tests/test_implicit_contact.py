"""The floor's contacts within an implicit step (pipeline/simulate/contact.py): the active set and its slides.

Checked against the rule's geometry: a node that crosses the plane is put on it (where its path
crossed it on a sticking floor, along the normal on a frictionless one) and held; a held node the
floor would have to pull (its reaction ``g . n < 0``) is let go; a sticking floor's pulled node
slides first (:class:`Slides`).
"""

from __future__ import annotations

import numpy as np
import pytest
from esmm.pipeline.mesh.synthetic import box_tets
from esmm.pipeline.network.springs import network_from_tets
from esmm.pipeline.simulate.contact import FloorContact, Slides, contact_rounds, on_floor
from esmm.pipeline.simulate.implicit import BackwardEuler
from esmm.pipeline.simulate.implicit_stats import ImplicitStats
from esmm.pipeline.simulate.model import Floor, Grasp
from esmm.pipeline.simulate.simulator import Simulator
from esmm.pipeline.simulate.springterm import build_spring_term
from simkit import make_tables

#: A tilted plane through (0, 0, 0.1): the rule must not assume the floor is z = const.
NORMAL = np.array([0.0, 0.6, 0.8])


def floor(friction):
    return Floor(normal=NORMAL, height=0.1 * 0.8, friction=friction)


def contact_of(fl, active, candidates=None, rounds=None):
    n = active.size
    cand = np.ones(n, bool) if candidates is None else candidates
    return FloorContact(fl, cand, active.copy(), Slides.none(n), contact_rounds(rounds, fl), ImplicitStats())


@pytest.mark.parametrize("friction", ["stick", "slip"])
def test_a_node_crossing_the_plane_is_put_on_it_and_held(friction):
    """Node 0 goes from 3 cm above the plane to 1 cm below it: on a sticking floor it lands where its
    straight path crossed the plane (three quarters of the way), on a frictionless one it is moved
    along the normal; node 1 stays above and free, node 2 (not a candidate) is left below."""
    fl = floor(friction)
    p = np.array([0.0, 0.0, 0.1])                          # on the plane
    t = np.array([1.0, 0.0, 0.0])                          # along it
    x0 = np.array([p + 0.03 * NORMAL, p + 0.05 * NORMAL, p + 0.01 * NORMAL])
    x = np.array([p + 0.02 * t - 0.01 * NORMAL, p + 0.04 * NORMAL, p - 0.01 * NORMAL])
    c = contact_of(fl, np.zeros(3, bool), candidates=np.array([True, True, False]))
    xt = x.copy()
    c.touchdown(x0, xt)
    np.testing.assert_array_equal(c.active, [True, False, False])
    assert c.stats.contact_changes == 1
    expect = x0[0] + 0.75 * (x[0] - x0[0]) if friction == "stick" else x[0] + 0.01 * NORMAL
    np.testing.assert_allclose(xt[0], expect, rtol=0, atol=1e-15)
    assert abs(fl.distance(xt[:1])[0]) < 1e-15
    np.testing.assert_array_equal(xt[1:], x[1:])
    # held from now on: the next step's predictor puts it on the plane again
    xp = xt.copy()
    xp[0] += 0.004 * t - 0.002 * NORMAL
    c.place(xt, xp)
    assert abs(fl.distance(xp[:1])[0]) < 1e-15


def test_a_sticking_node_that_started_below_the_plane_goes_back_to_its_start():
    """On a sticking floor a node whose start was not above the plane (no crossing on its path) is put
    on the plane at its start (it does not slide), moved along the normal."""
    fl = floor("stick")
    x0 = np.array([[0.0, 0.0, 0.05]])
    x = np.array([[0.01, 0.0, 0.04]])
    y = on_floor(fl, x0, x)
    assert fl.distance(x0)[0] < 0
    np.testing.assert_allclose(y[0], x0[0] - fl.distance(x0)[0] * NORMAL, rtol=0, atol=1e-15)


@pytest.mark.parametrize("friction", ["stick", "slip"])
def test_a_held_node_the_floor_would_pull_is_released(friction):
    """After a solve: the floor's reaction on node 0 pulls (``g . n < 0``), on node 1 it pushes. On a
    frictionless floor node 0 leaves at once; on a sticking one it first slides (held along the normal
    only), node 1 stays held in place either way."""
    fl = floor(friction)
    c = contact_of(fl, np.array([True, True, False]))
    g = np.array([-2.0 * NORMAL, 3.0 * NORMAL + [1.0, 0.0, 0.0], [5.0, 5.0, 5.0]])
    x = np.zeros((3, 3))
    changed, moved = c.update(g, x, final=False)
    assert changed and not moved
    held, normal = c.holds()
    if friction == "slip":
        np.testing.assert_array_equal(c.active, [False, True, False])
        assert c.stats.contact_changes == 1 and c.stats.slides == 0
        np.testing.assert_array_equal(normal, [False, True, False])       # frictionless: the normal only
        assert not held.any()
    else:
        np.testing.assert_array_equal(c.active, [True, True, False])
        assert c.stats.slides == 1 and c.stats.contact_changes == 0
        np.testing.assert_array_equal(held, [False, True, False])
        np.testing.assert_array_equal(normal, [True, False, False])
        # still pulled after its slide: it leaves
        changed, _ = c.update(g, x, final=False)
        assert changed
        np.testing.assert_array_equal(c.active, [False, True, False])
        assert c.stats.contact_changes == 1


def test_without_rounds_a_sticking_contact_is_let_go_without_sliding():
    fl = floor("stick")
    c = contact_of(fl, np.array([True, True]), rounds=0)
    changed, _ = c.update(np.array([-NORMAL, NORMAL]), np.zeros((2, 3)), final=True)
    assert changed and c.stats.slides == 0
    np.testing.assert_array_equal(c.active, [False, True])


def test_rounds_by_the_floor():
    assert contact_rounds(None, None) == 0
    assert contact_rounds(None, floor("slip")) == 1
    assert contact_rounds(None, floor("stick")) == 3
    assert contact_rounds(3, floor("slip")) == 3


def test_the_step_starts_from_the_last_steps_contacts_among_the_candidates():
    """Candidates: integrated, not fixed, not grasped; the active set: last step's contacts among them."""
    net = network_from_tets(box_tets(3, 2, 2, (0.03, 0.02, 0.02)))
    fixed = np.flatnonzero(net.points[:, 0] < 1e-9)
    term = build_spring_term(net, make_tables())
    fl = Floor.under(net.points, (0, 0, -9.81), friction="stick")
    sim = Simulator(term, net.points, net.mass, fixed=fixed, gravity=(0, 0, -9.81), floor=fl, stepper=BackwardEuler())
    bottom = np.flatnonzero(net.points[:, 2] < 1e-9)
    grasped = bottom[~np.isin(bottom, fixed)][-1:]
    sim.attach(Grasp(nodes=grasped, offsets=np.zeros((1, 3)), wp_t=np.array([0.0, 1.0]),
                     wp_x=np.repeat(net.points[grasped], 2, axis=0)), check_step=False)
    sim.state.contact[bottom] = 1
    c = FloorContact.begin(sim.model, sim.state, sim.control, rounds=None, stats=ImplicitStats())
    expect = np.zeros(net.n_nodes, bool)
    expect[bottom] = True
    expect[fixed] = False
    expect[grasped] = False
    np.testing.assert_array_equal(c.active, expect)
    assert not c.candidates[fixed].any() and not c.candidates[grasped].any()
    assert c.rounds == 3 and not c.slides.sliding.any()


def test_a_sliding_contact_stops_where_it_slips_or_creeps_to_the_farther():
    """:meth:`Slides.slip`: a stopping slide ends at the farther of where the node slips to (the first zero
    of its reaction along the slide with the other nodes where the held solve left them) and where it
    creeps to (its reaction's zero, linear along the slide). Node 0's springs never press it into the
    floor along its slide: it slips the whole way; node 1's press it a tenth of the way along and it
    creeps farther; node 2's press it three quarters of the way along, past where it creeps to."""
    n = 4
    contact = np.array([True, True, True, False])
    sl = Slides.none(n)
    x_held = np.zeros((n, 3))
    x_held[3] = [0.0, 0.0, 1.0]
    x = x_held.copy()
    sl.update(np.array([-1.0, -2.0, -1.0, 0.0]), x, contact, final=False)
    np.testing.assert_array_equal(sl.sliding, [True, True, True, False])
    slide = np.array([[0.004, 0.0, 0.0], [0.0, 0.002, 0.0], [0.0, 0.0, 0.0]])
    slide[2] = [0.001, 0.001, 0.0]
    x_slid = x_held.copy()
    x_slid[:3] = slide
    x_slid[3] = [0.0, 0.0, 1.002]
    along = np.array([0.004, 0.002, 0.001])        # each slide's length along its first nonzero axis
    frozen = []

    def reaction(y):
        frozen.append(y[3].copy())
        s = y[:3].max(axis=1) / along                # the fraction of each slide
        return np.array([-1.0 - 2.0 * s[0], -2.0 + 20.0 * s[1], -1.0 + (4.0 / 3.0) * s[2], 0.0])

    lam = np.array([3.0, 1.0, 4.0, 0.0])            # all pushed at the slides' ends
    x = x_slid.copy()
    leave, changed, started = sl.update(lam, x, contact, final=False, reaction=reaction)
    assert changed and started == 0 and not leave.any() and sl.moved
    np.testing.assert_array_equal(frozen, [[0.0, 0.0, 1.0]] * len(frozen))   # the others where they were held
    s = np.array([1.0, 2.0 / 3.0, 0.75])            # slip; creep (2/(2+1)) past its slip (0.1); slip
    np.testing.assert_allclose(x[:3], s[:, None] * slide, atol=1e-15)
    np.testing.assert_allclose(x[3], [0.0, 0.0, 1.0 + s.mean() * 0.002])    # the field taken back by the mean s
    assert not sl.sliding.any()


def test_a_slide_that_slips_to_its_end_moves_nothing():
    """Where every stopping node slips the whole way, the slide solve's solution stands: nothing moves and,
    no other contact changing, the step is not solved again."""
    contact = np.array([True, True])
    sl = Slides.none(2)
    x = np.zeros((2, 3))
    sl.update(np.array([-1.0, 2.0]), x, contact, final=False)
    x[0] = [0.003, 0.0, 0.0]
    before = x.copy()
    leave, changed, started = sl.update(np.array([0.5, 2.0]), x, contact, final=False,
                                        reaction=lambda y: np.array([-1.0, 2.0]))
    assert not changed and not sl.moved and not leave.any() and started == 0
    np.testing.assert_array_equal(x, before)
    assert not sl.sliding.any()


def test_the_floor_reads_the_slip_from_the_step_residual_along_its_normal():
    """:meth:`FloorContact.update` hands :meth:`Slides.slip` the reaction ``g . n`` of the residual it is
    given (the tilted plane's normal): a node whose reaction along its slide, the other nodes held,
    stays negative is stuck where the slide ended, and the step is not solved again."""
    fl = floor("stick")
    c = contact_of(fl, np.array([True, True]))
    p = np.array([0.0, 0.0, 0.1])
    t = np.array([1.0, 0.0, 0.0])
    x = np.array([p, p + 0.01 * t])
    g = np.array([-1.0 * NORMAL, 2.0 * NORMAL])
    changed, moved = c.update(g, x, final=False)
    assert changed and not moved and c.slides.sliding[0] and c.stats.slides == 1
    x[0] = p + 0.003 * t                                  # the slide solve: pushed at its end
    seen = []

    def residual(y):
        seen.append(y[0] @ t)
        return np.array([-0.5 * NORMAL + 0.3 * t, 2.0 * NORMAL])      # pulled all along the slide

    changed, moved = c.update(np.array([0.5 * NORMAL, 2.0 * NORMAL]), x, final=False, residual=residual)
    assert not changed and not moved and not c.slides.sliding.any()
    np.testing.assert_allclose(x[0], p + 0.003 * t)
    np.testing.assert_allclose(seen, 0.003 * np.arange(1, 9) / 8, atol=1e-15)   # sampled along the slide
    np.testing.assert_array_equal(c.active, [True, True])


def test_a_node_let_go_after_its_slide_lands_where_it_left_the_plane():
    """A node that slid 4 mm and was let go (still pulled), then ends the step below the plane, is put
    where it left the plane, not where it was held at the step's start (which would undo its slide);
    a node that never left is put where its path from the step's start crossed the plane."""
    fl = floor("stick")
    p = np.array([0.0, 0.0, 0.1])
    t = np.array([1.0, 0.0, 0.0])
    c = contact_of(fl, np.array([True, False]))
    x0 = np.array([p, p + 0.02 * NORMAL])
    x = x0.copy()
    c.update(np.array([-1.0 * NORMAL, np.zeros(3)]), x, final=False)
    assert c.slides.sliding[0]
    x[0] = p + 0.004 * t                                   # the slide solve: still pulled
    changed, _ = c.update(np.array([-0.5 * NORMAL, np.zeros(3)]), x, final=False)
    assert changed and not c.active.any()
    x[0] = p + 0.006 * t - 0.001 * NORMAL                  # the step's end: both below the plane
    x[1] = p + 0.002 * t - 0.02 * NORMAL
    c.touchdown(x0, x)
    np.testing.assert_array_equal(c.active, [True, True])
    np.testing.assert_allclose(x[0], p + 0.004 * t, atol=1e-15)
    np.testing.assert_allclose(x[1], p + 0.001 * t, atol=1e-15)   # half way along its path


def test_a_sliding_contact_stops_where_the_floor_pushes_again():
    """:class:`Slides` on three held nodes: one pulled slides, then stops where its reaction, linear
    along the slide, is zero; one pulled again after sliding leaves; a pressed one stays held."""
    n = 4
    contact = np.array([True, True, True, False])
    sl = Slides.none(n)
    x_held = np.zeros((n, 3))
    x_held[3] = [0.0, 0.0, 1.0]
    lam = np.array([-1.0, -2.0, 3.0, 0.0])
    x = x_held.copy()
    leave, changed, started = sl.update(lam, x, contact, final=False)
    assert changed and started == 2 and not leave.any()
    np.testing.assert_array_equal(sl.sliding, [True, True, False, False])
    # the slide solve: node 0 moved 4 mm along x and is pushed (+3), node 1 is still pulled, node 3 rose
    x_slid = x_held.copy()
    x_slid[0] = [0.004, 0.0, 0.0]
    x_slid[1] = [0.0, 0.002, 0.0]
    x_slid[3] = [0.0, 0.0, 1.002]
    x = x_slid.copy()
    leave, changed, started = sl.update(np.array([3.0, -0.5, 3.0, 0.0]), x, contact, final=False)
    assert changed and started == 0
    np.testing.assert_array_equal(leave, [False, True, False, False])
    s = -1.0 / (-1.0 - 3.0)                                     # its reaction's zero: a quarter of the way
    np.testing.assert_allclose(x[0], [s * 0.004, 0.0, 0.0])
    np.testing.assert_allclose(x[3], [0.0, 0.0, 1.0 + s * 0.002])       # the field taken back by s
    np.testing.assert_array_equal(sl.sliding, [False, False, False, False])
    # slid once this step: pulled again, it stays held; the final check moves nothing
    x_before = x.copy()
    leave, changed, started = sl.update(np.array([-1.0, 0.0, 3.0, 0.0]), x, contact & ~leave, final=True)
    assert not changed and started == 0 and not leave.any()
    np.testing.assert_array_equal(x, x_before)
