"""The implicit step's quasi-Newton iteration (pipeline/linalg/quasinewton.py) against the theory of
L-BFGS on quadratics: Newton's step with the exact first inverse, the secant equation, termination in
n iterations with exact line searches, and the secant step's exactness."""

import numpy as np
import pytest
from esmm.pipeline.linalg.quasinewton import MIN_STEP, LBFGSMemory, secant_step


def spd(n, seed=0, cond=1e3):
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return Q @ np.diag(np.geomspace(1.0, cond, n)) @ Q.T


def test_without_pairs_the_direction_is_the_first_inverse_applied():
    A = spd(8)
    b = np.random.default_rng(1).normal(size=8)
    d = LBFGSMemory().direction(b, lambda r: np.linalg.solve(A, r))
    np.testing.assert_allclose(d, np.linalg.solve(A, b), rtol=1e-12)       # Newton's step


def test_the_newest_pair_satisfies_the_secant_equation():
    A = spd(10, seed=2)
    rng = np.random.default_rng(3)
    mem = LBFGSMemory(memory=4)
    for _ in range(6):                                   # more pairs than kept: the oldest are dropped
        s = rng.normal(size=10)
        assert mem.update(s, A @ s)
    assert len(mem) == 4
    s, y, _ = mem.pairs[-1]
    for h0 in (lambda r: r.copy(), lambda r: r / np.diag(A)):          # whatever the first inverse
        np.testing.assert_allclose(mem.direction(y, h0), s, rtol=1e-9)


def test_a_pair_of_non_positive_curvature_is_not_kept():
    mem = LBFGSMemory()
    s = np.array([1.0, 0.0])
    assert not mem.update(s, -s)
    assert not mem.update(s, np.array([0.0, 1.0]))       # y.s = 0
    assert len(mem) == 0


def test_lbfgs_with_exact_steps_minimizes_a_quadratic_in_n_iterations():
    """BFGS with exact line searches on a quadratic terminates in n iterations (Nocedal & Wright 2006,
    Theorem 6.4, and its equivalence with preconditioned CG); with memory >= n, so does L-BFGS. The
    secant step is the exact line search there. Here with the diagonal as the first inverse, as the
    reused factor is an approximate one."""
    n = 12
    A = spd(n, seed=4, cond=1e2)
    b = np.random.default_rng(5).normal(size=n)
    x = np.zeros(n)
    mem = LBFGSMemory(memory=n)
    D = np.diag(A)
    g = A @ x - b
    x_true = np.linalg.solve(A, b)
    errors = []
    for _ in range(n):
        d = mem.direction(-g, lambda r: r / D)
        assert -g @ d > 0                                # a descent direction
        g1 = A @ (x + d) - b
        t = secant_step(g @ d, g1 @ d, max_step=1e6)
        x_new = x + t * d
        g_new = A @ x_new - b
        assert abs(g_new @ d) <= 1e-8 * abs(g @ d)       # the step is the exact minimum along d
        mem.update(x_new - x, g_new - g)
        x, g = x_new, g_new
        errors.append(np.linalg.norm(x - x_true) / np.linalg.norm(x_true))
    assert errors[-2] > 1e-4 and errors[-1] < 1e-9         # not before the n-th iteration; at it, exact


@pytest.mark.parametrize("s_star", [0.3, 1.0, 2.5, 7.0])
def test_secant_step_is_the_minimum_of_a_parabola(s_star):
    """phi'(s) = a (s - s*): the secant through s = 0 and 1 returns s* (shorter or longer than 1)."""
    a = 3.0
    assert secant_step(a * (0 - s_star), a * (1 - s_star), max_step=8.0) == pytest.approx(s_star)


def test_secant_step_limits():
    assert secant_step(-1.0, 100.0, max_step=8.0) == MIN_STEP          # a huge overshoot: the shortest step
    assert secant_step(-1.0, -0.99, max_step=8.0) == 8.0               # nearly flat slope: the longest
    assert secant_step(-1.0, -2.0, max_step=8.0) == 8.0                # steeper: no secant zero ahead
    assert secant_step(-1.0, 0.0, max_step=8.0) == 1.0


def test_projected_pairs_live_in_the_new_null_space():
    """After new constraints the pairs are carried with their steps projected (the curvature recomputed;
    a pair whose curvature is no longer positive dropped): with a first inverse into the null space,
    every direction is in it, and the kept pair's secant equation holds there."""
    A = spd(6, seed=6)
    rng = np.random.default_rng(7)
    mem = LBFGSMemory(memory=4)
    for _ in range(3):
        s = rng.normal(size=6)
        mem.update(s, A @ s)
    mem.update(np.eye(6)[0], A[:, 0])                    # a step along the dof to be held only

    def project(z):
        out = np.array(z, copy=True)
        out[0] = 0.0                                     # dof 0 held
        return out

    mem.project(project)
    assert len(mem) == 3                                 # the pair along dof 0 has no curvature left
    for s, y, rho in mem.pairs:
        assert s[0] == 0.0 and rho == pytest.approx(1.0 / (s @ y))
    d = mem.direction(rng.normal(size=6), lambda r: project(np.linalg.solve(A, r)))
    assert d[0] == 0.0
