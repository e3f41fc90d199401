"""Per-spring corrections (pipeline/network/corrections.py): the objective's gradient against finite
differences, the linear solve against a direct one, and a fit that recovers known multipliers."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse.linalg as spl
from esmm.pipeline.network.corrections import (
    CorrectionObjective,
    LinearLoad,
    LinearNetwork,
    fit_corrections,
    linear_errors,
)
from esmm.pipeline.network.volume import VolumeSpec
from simkit import jittered_box_network


@pytest.fixture(scope="module")
def box():
    net = jittered_box_network((4, 3, 3), (0.04, 0.03, 0.03), jitter=1.5e-3, seed=3)
    return replace(net, volume_term=VolumeSpec(2.0e5))


def held_and_loads(net):
    x = net.points[:, 0]
    held = np.flatnonzero(x <= x.min() + 1e-9 + 2e-3)
    tip = np.flatnonzero(x >= x.max() - 2e-3)[:4]
    loads = [LinearLoad("g-z", gravity=np.array([0.0, 0.0, -9.81])),
             LinearLoad("g+y", gravity=np.array([0.0, 9.81, 0.0])),
             LinearLoad("pull", patch=tip, displacement=np.tile([0.0, 0.0, 1e-3], (tip.size, 1))),
             LinearLoad("push", patch=tip, displacement=np.tile([0.0, -1e-3, 0.0], (tip.size, 1)))]
    return held, loads


def many_loads(net):
    """Enough cases to determine every loaded spring: gravity along x too, pulls of three more patches."""
    held, loads = held_and_loads(net)
    x = net.points
    patches = {"mid": np.flatnonzero(np.abs(x[:, 0] - 0.02) < 3e-3)[:3],
               "top": np.flatnonzero(x[:, 2] >= x[:, 2].max() - 2e-3)[-3:],
               "far": np.flatnonzero(x[:, 0] >= x[:, 0].max() - 2e-3)[-3:]}
    for name, P in patches.items():
        for d in np.eye(3) * 1e-3:
            loads.append(LinearLoad(name, patch=P, displacement=np.tile(d, (P.size, 1))))
    return held, loads + [LinearLoad("g+x", gravity=np.array([9.81, 0.0, 0.0]))]


def responses(lin, theta, loads):
    fac = lin.factor(theta)
    out = []
    for ld in loads:
        u, R, _ = lin.solve(fac, ld)
        out.append((u.reshape(-1, 3), R))
    return out


def test_patch_solve_equals_a_direct_solve(box, tables):
    held, loads = held_and_loads(box)
    lin = LinearNetwork(box, tables, held)
    theta = np.random.default_rng(0).normal(0.0, 0.3, box.n_springs)
    u, R, _ = lin.solve(lin.factor(theta), loads[2])
    K = lin.matrix(theta)
    mask = np.zeros((box.n_nodes, 3), bool)
    mask[held] = mask[loads[2].patch] = True
    m = mask.ravel()
    x = np.zeros(3 * box.n_nodes)
    x[(3 * loads[2].patch[:, None] + np.arange(3)).ravel()] = loads[2].displacement.ravel()
    x[~m] = spl.spsolve(K[~m][:, ~m].tocsc(), -(K[~m][:, m] @ x[m]))
    np.testing.assert_allclose(u, x, atol=1e-12 * np.abs(x).max())
    on_body = -(K @ x).reshape(-1, 3)           # no gravity in this case: the reaction is -K u on the patch
    np.testing.assert_allclose(R, on_body[loads[2].patch].sum(axis=0), rtol=1e-9)


def test_gradient_matches_finite_differences(box, tables):
    held, loads = held_and_loads(box)
    lin = LinearNetwork(box, tables, held)
    rng = np.random.default_rng(1)
    truth = responses(lin, rng.normal(0.0, 0.2, box.n_springs), loads)
    obj = CorrectionObjective(lin, loads, truth, alpha=1e-3, gamma=1e-2, beta=0.5)
    theta = rng.normal(0.0, 0.1, box.n_springs)
    J, g = obj(theta)
    for s in rng.choice(box.n_springs, 8, replace=False):
        h = 1e-6
        e = np.zeros_like(theta)
        e[s] = h
        fd = (obj(theta + e)[0] - obj(theta - e)[0]) / (2 * h)
        assert g[s] == pytest.approx(fd, rel=1e-5, abs=1e-10 * abs(J))
    d = rng.normal(size=theta.size)          # a whole direction too
    h = 1e-6
    fd = (obj(theta + h * d)[0] - obj(theta - h * d)[0]) / (2 * h)
    assert g @ d == pytest.approx(fd, rel=1e-6)


@pytest.mark.slow
def test_fit_recovers_known_multipliers(box, tables):
    """A reference made by the same network with springs scaled by known factors: the fit finds a network
    whose responses are the reference's, and the factors where the loads strain the springs."""
    held, loads = many_loads(box)
    lin = LinearNetwork(box, tables, held)
    rng = np.random.default_rng(2)
    truth_theta = np.log(rng.uniform(0.6, 1.6, box.n_springs))
    truth = responses(lin, truth_theta, loads)
    obj = CorrectionObjective(lin, loads, truth, alpha=0.0, gamma=0.0, beta=1.0)
    w = obj.w
    before = [linear_errors(u, R, ref, w) for (u, R), ref in zip(responses(lin, 0 * truth_theta, loads), truth,
                                                                   strict=True)]
    theta, res = fit_corrections(obj, bound=4.0, max_iter=300)
    after = [linear_errors(u, R, ref, w) for (u, R), ref in zip(responses(lin, theta, loads), truth, strict=True)]
    assert max(b[0] for b in before) > 0.05          # the unfitted network is clearly off
    assert max(a[0] for a in after) < 0.01 * max(b[0] for b in before)
    assert max(a[1] for a in after[2:]) < 0.01 * max(b[1] for b in before[2:])
    # the factors themselves, on the springs that carry the loads (the energy-weighted error)
    energy = sum((lin.k0 * np.exp(truth_theta)) * (lin.B @ u.ravel()) ** 2 for u, _ in truth)
    top = energy > np.quantile(energy, 0.5)
    err = np.abs(theta - truth_theta)[top]
    assert np.median(err) < 0.05 * np.median(np.abs(truth_theta[top]))


def test_without_held_nodes_is_refused(box, tables):
    from esmm.pipeline.errors import ConfigError

    with pytest.raises(ConfigError, match="^held"):
        LinearNetwork(box, tables, [])


def test_smoothing_operator_vanishes_on_a_uniform_field_only(box):
    from esmm.pipeline.network.corrections import smoothing_operator

    D = smoothing_operator(box)
    np.testing.assert_allclose(D @ np.full(box.n_springs, 0.7), 0.0, atol=1e-12)
    bump = np.zeros(box.n_springs)
    bump[5] = 1.0
    assert (D @ bump)[5] > 0.5            # a lone spring differs from its neighbours' mean
