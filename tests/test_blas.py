"""OpenBLAS on one thread where the linear algebra is small (pipeline/blas.py)."""

from types import SimpleNamespace

import numpy as np
import pytest
from esmm.pipeline.blas import single_threaded_blas
from esmm.pipeline.simulate.simulator import Simulator

threadpoolctl = pytest.importorskip("threadpoolctl")


def _blas_threads() -> list[int]:
    return [i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"]


def test_single_threaded_blas_sets_one_thread_and_restores():
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):     # as on a 2-core machine
        before = _blas_threads()
        assert before and max(before) == 2
        with single_threaded_blas():
            assert _blas_threads() == [1] * len(before)
        assert _blas_threads() == before


def test_simulator_steps_with_one_blas_thread():
    seen = []

    def advance(model, state, control, nsteps, *, record=None):
        seen.append(_blas_threads())
        return np.zeros((nsteps, 3))

    sim = SimpleNamespace(stepper=SimpleNamespace(advance=advance), model=None, state=None, control=None)
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        Simulator.advance(sim, 3)                     # the method itself, on a stand-in session
        assert max(_blas_threads()) == 2
    assert seen and set(seen[0]) == {1}
