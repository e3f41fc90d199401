"""The reused factor's matrix in one compiled pass (pipeline/simulate/assembly.py) against the sparse sums.

:class:`BoundAssembly` must give what ``StepSystem.matrix(x, bound=True)`` gives (the springs'
definite tangent, the volume term's per-tet bound, the dashpots over h, the masses, the identity on
fixed dofs), on the same CSR pattern, so that a run's factor keeps its symbolic analysis; and a model
whose tets are not all springs' node pairs falls back to the sums.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from esmm.pipeline.network.springs import tet_volumes
from esmm.pipeline.network.volume import VolumeSpec
from esmm.pipeline.simulate.assembly import BoundAssembly
from esmm.pipeline.simulate.factorcache import FactorCache
from esmm.pipeline.simulate.implicit_stats import ImplicitStats, Threads
from esmm.pipeline.simulate.volumeterm import build_volume_term
from test_implicit_system import moving_slab


@pytest.mark.parametrize("volume", [False, True])
@pytest.mark.parametrize("definite", [False, True])
def test_the_compiled_assembly_is_the_sparse_sum(volume, definite):
    sim, system = moving_slab(volume=volume, definite=definite)
    x = system.x0 + 2e-3 * np.random.default_rng(3).standard_normal(system.x0.shape)   # some springs compressed
    expect = system.matrix(x, bound=True).tocsr()
    expect.sort_indices()
    asm = BoundAssembly.of(sim.model)
    assert asm is not None and (asm.volume is not None) == volume
    got = asm.matrix(system, x)
    assert np.array_equal(got.indptr, expect.indptr) and np.array_equal(got.indices, expect.indices)
    np.testing.assert_allclose(got.data, expect.data, rtol=0, atol=1e-12 * np.abs(expect.data).max())
    fixed = np.repeat(~sim.model.movable, 3)
    dense = got.toarray()
    assert np.array_equal(dense[fixed][:, fixed], np.eye(fixed.sum()))
    assert not dense[fixed][:, ~fixed].any()


def test_tets_that_are_not_springs_fall_back_to_the_sums():
    """A volume term on other tets than the springs' (here: a tet joining nodes no spring joins)."""
    sim, system = moving_slab(volume=True)
    model = sim.model
    p = model.rest
    far = np.argsort(np.linalg.norm(p - p[0], axis=1))[[0, -1, -2, -5]]
    if tet_volumes(p, far[None, :])[0] < 0:
        far = far[[1, 0, 2, 3]]
    tets = np.concatenate([model.terms[-1].elements.tets, far[None, :]])
    model = dataclasses.replace(model, volume=build_volume_term(p, tets, VolumeSpec(2e5), lam_max=2.0))
    system = dataclasses.replace(system, model=model)
    assert BoundAssembly.of(model) is None
    cache = FactorCache("factor", "bound", True, Threads(), ImplicitStats())
    A = cache._matrix(system, system.x0)
    np.testing.assert_array_equal(A.toarray(), system.matrix(system.x0, bound=True).toarray())
