"""The supernodal multifrontal LDL^T (esmm.pipeline.linalg.supernodal) against independent solvers.

Every check is against something computed another way: scipy's sparse direct
solver (spsolve) for the solutions, SuperLU's L in the same order for the fill,
column-by-column solves for the multi-right-hand-side kernel, the one-thread
factor for the two-thread one.
"""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spl
from esmm.pipeline.blas import single_threaded_blas
from esmm.pipeline.linalg.linsolve import MixedFactor, SparseFactor
from esmm.pipeline.linalg.newton import ldlt, node_ordering
from esmm.pipeline.linalg.supernodal import LDLT, Analysis, ZeroPivot


def block_laplacian(n: int, seed: int) -> sp.csr_matrix:
    """An SPD matrix with the networks' structure: 3x3 blocks on the edges of an n^3 grid with
    diagonals (a spring network), random positive weights and directions, plus a mass term."""
    rng = np.random.default_rng(seed)
    idx = np.arange(n ** 3).reshape(n, n, n)
    pairs = []
    for d in [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (0, 1, 1), (1, 0, 1)]:
        a = idx[:n - d[0], :n - d[1], :n - d[2]].ravel()
        b = idx[d[0]:, d[1]:, d[2]:].ravel()
        pairs.append(np.stack([a, b], 1))
    ij = np.concatenate(pairs)
    u = rng.standard_normal((len(ij), 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    k = rng.uniform(0.5, 2.0, len(ij))
    blocks = k[:, None, None] * u[:, :, None] * u[:, None, :] + 0.05 * k[:, None, None] * np.eye(3)
    rows, cols, vals = [], [], []
    for (a, b), B in zip(ij, blocks):
        for r, c, s in ((a, a, 1), (b, b, 1), (a, b, -1), (b, a, -1)):
            rr, cc = np.meshgrid(np.arange(3) + 3 * r, np.arange(3) + 3 * c, indexing="ij")
            rows.append(rr.ravel())
            cols.append(cc.ravel())
            vals.append(s * B.ravel())
    N = 3 * n ** 3
    K = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(N, N))
    return (K + sp.diags(rng.uniform(0.01, 0.1, N))).tocsr()


@pytest.fixture(scope="module")
def spd():
    return block_laplacian(6, seed=1)


@pytest.mark.parametrize("order", ["natural", "nested", "random"])
def test_solve_matches_spsolve(spd, order):
    N = spd.shape[0]
    perm = {"natural": np.arange(N), "nested": node_ordering(spd),
            "random": np.random.default_rng(2).permutation(N)}[order]
    b = np.random.default_rng(3).standard_normal(N)
    ref = spl.spsolve(spd.tocsc(), b)
    x = LDLT.of(spd, perm=perm).solve(b)
    assert np.linalg.norm(x - ref) <= 1e-10 * np.linalg.norm(ref)


def test_fill_equals_superlu_in_the_same_order(spd):
    """The symbolic factorization is exact: L has as many entries as SuperLU's L without pivoting."""
    an = Analysis.of(spd, node_ordering(spd))
    lu = ldlt(spd, an.perm)
    assert an.nnz == lu.L.nnz
    assert an.nnz < spd.shape[0] ** 2 / 4           # nested dissection: far from dense


def test_several_right_hand_sides_equal_one_at_a_time(spd):
    fac = LDLT.of(spd, perm=node_ordering(spd))
    B = np.random.default_rng(4).standard_normal((spd.shape[0], 7))
    X = fac.solve(B)
    for q in range(B.shape[1]):
        np.testing.assert_allclose(X[:, q], fac.solve(B[:, q]), rtol=1e-12, atol=1e-14)


def test_single_precision_is_a_preconditioner(spd):
    fac = LDLT.of(spd, perm=node_ordering(spd), dtype=np.float32)
    assert fac.dtype == np.float32
    b = np.random.default_rng(5).standard_normal(spd.shape[0])
    x = fac.solve(b)
    assert x.dtype == np.float64
    assert np.linalg.norm(spd @ x - b) < 1e-3 * np.linalg.norm(b)


def test_analysis_is_reused_for_the_same_pattern_only(spd):
    an = Analysis.of(spd, node_ordering(spd))
    other = spd.copy()
    other.data = other.data * np.random.default_rng(6).uniform(0.5, 1.5, other.nnz)
    other = (other + other.T) / 2
    fac = LDLT.of(other, an)
    assert fac.analysis is an
    b = np.random.default_rng(7).standard_normal(spd.shape[0])
    np.testing.assert_allclose(fac.solve(b), spl.spsolve(other.tocsc(), b), rtol=1e-9, atol=1e-12)
    fewer = other.tolil()
    fewer[0, 3] = fewer[3, 0] = 0.0
    fewer = sp.csr_matrix(fewer)
    fewer.eliminate_zeros()
    fac2 = LDLT.of(fewer, an)
    assert fac2.analysis is not an and not an.matches(fewer)
    np.testing.assert_allclose(fac2.solve(b), spl.spsolve(fewer.tocsc(), b), rtol=1e-9, atol=1e-12)


def test_quasi_definite_saddle_point():
    """[[A, B^T], [B, -C]] with A, C positive definite: an LDL^T in any order (Vanderbei 1995)."""
    rng = np.random.default_rng(8)
    A = block_laplacian(4, seed=9)
    m = 40
    B = sp.random(m, A.shape[0], density=0.05, random_state=10, format="csr")
    C = sp.diags(rng.uniform(0.1, 1.0, m))
    K = sp.bmat([[A, B.T], [B, -C]], format="csr")
    b = rng.standard_normal(K.shape[0])
    x = LDLT.of(K, perm=rng.permutation(K.shape[0])).solve(b)
    ref = spl.spsolve(K.tocsc(), b)
    assert np.linalg.norm(x - ref) <= 1e-9 * np.linalg.norm(ref)


def test_disconnected_and_diagonal_rows():
    """Fixed nodes give rows with the diagonal alone: roots of their own in the elimination forest."""
    A = sp.block_diag([block_laplacian(3, seed=11), sp.identity(6), block_laplacian(2, seed=12)], format="csr")
    b = np.arange(A.shape[0], dtype=float)
    np.testing.assert_allclose(LDLT.of(A, perm=node_ordering(A)).solve(b), spl.spsolve(A.tocsc(), b),
                               rtol=1e-10, atol=1e-12)


def test_zero_pivot_is_refused():
    A = sp.csr_matrix(np.array([[0.0, 1.0], [1.0, 0.0]]))
    with pytest.raises(ZeroPivot, match="pivot"):
        LDLT.of(A, perm=np.arange(2))


def test_two_threads_solve_the_same(spd):
    fac = LDLT.of(spd, perm=node_ordering(spd))
    B = np.random.default_rng(13).standard_normal((spd.shape[0], 3))
    one = fac.solve(B)
    fac.threads = 2
    np.testing.assert_allclose(fac.solve(B), one, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(fac.solve(B[:, 0]), one[:, 0], rtol=1e-10, atol=1e-13)


def test_the_two_parts_are_whole_subtrees_under_their_ancestors(spd):
    """What makes the two-thread sweeps race-free: a supernode of a part updates only rows of its own
    part or of the shared ancestors (its rows below its columns belong to its ancestors)."""
    an = Analysis.of(spd, node_ordering(spd))
    col_part = np.repeat(an.part, np.diff(an.start))
    nc = np.diff(an.start)
    for s in range(nc.size):
        below = an.rows[an.row_ptr[s] + nc[s]:an.row_ptr[s + 1]]
        if an.part[s] >= 0:
            assert set(col_part[below]) <= {an.part[s], -1}
        else:
            assert set(col_part[below]) <= {-1}
    work = np.diff(an.block_ptr)
    share = [work[an.part == g].sum() / work.sum() for g in (0, 1)]
    assert min(share) > 0.2                          # both threads have work


def saddle_point_matrix():
    """[[A, B^T], [B, -C]] with A, C positive definite, and a random order (test_quasi_definite_saddle_point)."""
    rng = np.random.default_rng(8)
    A = block_laplacian(4, seed=9)
    m = 40
    B = sp.random(m, A.shape[0], density=0.05, random_state=10, format="csr")
    K = sp.bmat([[A, B.T], [B, -sp.diags(rng.uniform(0.1, 1.0, m))]], format="csr")
    return K, rng.permutation(K.shape[0])


def two_thread_cases():
    """Matrices and orders whose trees split in different ways: two parts under a few ancestors (a grid
    in nested dissection, a saddle point in a random order), several trees (no ancestor at all: a
    diagonal), a chain (one part holds a leaf, the other is empty, the rest are ancestors)."""
    spd = block_laplacian(6, seed=1)
    disconnected = sp.block_diag([block_laplacian(3, seed=11), sp.identity(6), block_laplacian(2, seed=12)],
                                 format="csr")
    n = 300
    chain = sp.diags([-np.ones(n - 1), np.full(n, 2.5), -np.ones(n - 1)], [-1, 0, 1], format="csr")
    diagonal = sp.diags(np.arange(1.0, 51.0), format="csr")
    return {"nested": (spd, node_ordering(spd)), "saddle": saddle_point_matrix(),
            "disconnected": (disconnected, node_ordering(disconnected)), "chain": (chain, np.arange(n)),
            "diagonal": (diagonal, np.arange(50))}


@pytest.mark.parametrize("case", ["nested", "saddle", "disconnected", "chain", "diagonal"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_two_thread_factor_equals_one_thread(case, dtype):
    """The two-thread numeric phase does each front's arithmetic as the one-thread one does (the same
    children, extend-added in the same order): the same factor, bit for bit, when OpenBLAS runs on one
    thread in both (an OpenBLAS on several threads may round its matrix products differently)."""
    A, perm = two_thread_cases()[case]
    an = Analysis.of(A, perm)
    with single_threaded_blas():
        one = LDLT.of(A, an, dtype=dtype)
        two = LDLT.of(A, an, dtype=dtype, threads=2)
    assert two.threads == 2 and one.threads == 1
    np.testing.assert_array_equal(two.blk, one.blk)
    np.testing.assert_array_equal(two.dinv, one.dinv)
    if dtype == np.float64:
        b = np.random.default_rng(14).standard_normal(A.shape[0])
        ref = spl.spsolve(A.tocsc(), b)
        for fac in (LDLT.of(A, an, dtype=dtype, threads=2), two):
            assert np.linalg.norm(fac.solve(b) - ref) <= 1e-10 * np.linalg.norm(ref)


def test_the_two_thread_cases_split_as_named():
    """The cases above cover the splits they are meant to: both parts and ancestors, no ancestor, an
    empty part."""
    sizes = {k: np.diff(Analysis.of(A, perm).part_ptr) for k, (A, perm) in two_thread_cases().items()}
    assert all(sizes[k].min() > 0 for k in ("nested", "saddle", "disconnected"))
    assert sizes["diagonal"][2] == 0 and min(sizes["diagonal"][:2]) > 0
    assert sizes["chain"][1] == 0 and sizes["chain"][0] > 0 and sizes["chain"][2] > 0


@pytest.mark.parametrize("where", [0, 1, 2])
def test_two_thread_factor_refuses_a_bad_pivot(where):
    """A zero pivot in either part (a leaf's first column: its pivot is A's diagonal entry), a non-finite
    one in the ancestors; the pattern kept (the same analysis)."""
    A, perm = two_thread_cases()["nested"]
    an = Analysis.of(A, perm)
    col = int(an.perm[an.start[an.by_part[an.part_ptr[where]]]])     # the region's first column
    bad = A.copy()
    bad.data[bad.indptr[col] + np.flatnonzero(bad.indices[bad.indptr[col]:bad.indptr[col + 1]] == col)] = \
        0.0 if where < 2 else np.nan
    assert an.matches(bad)
    with pytest.raises(ZeroPivot, match=f"column {col}\\b"):
        LDLT.of(bad, an, threads=2)


def test_the_stepper_factors_take_one_thread_setting_for_both_phases():
    """linsolve's factors pass *threads* to the factorization and keep it for their solves."""
    A, perm = two_thread_cases()["nested"]
    b = np.random.default_rng(15).standard_normal(A.shape[0])
    one = SparseFactor.of(A, perm)
    two = SparseFactor.of(A, perm, threads=2, analysis=one.analysis)
    assert (one.ldl.threads, two.ldl.threads) == (1, 2) and two.analysis is one.analysis
    np.testing.assert_allclose(two.solve(b), one.solve(b), rtol=1e-10, atol=1e-13)
    n = A.shape[0] // 3
    B = sp.random(n, A.shape[0], density=0.02, random_state=16, format="csr")
    w = np.random.default_rng(17).uniform(0.5, 2.0, n)
    mixed = [MixedFactor.of_parts(A, B, w, threads=th) for th in (1, 2)]
    assert [f.ldl.threads for f in mixed] == [1, 2]
    ref = spl.spsolve((A + B.T @ sp.diags(w) @ B).tocsc(), b)
    for f in mixed:
        assert np.linalg.norm(f.solve(b) - ref) <= 1e-9 * np.linalg.norm(ref)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("threads", [1, 2])
def test_the_two_halves_of_a_solve_are_the_solve_bit_for_bit(spd, dtype, threads):
    """``backward(dinv * forward(b))`` does the solve's operations in the solve's order: the same
    bits, on one thread and on two."""
    fac = LDLT.of(spd, perm=node_ordering(spd), dtype=dtype, threads=threads)
    b = np.random.default_rng(21).standard_normal(spd.shape[0])
    y = fac.forward(b)
    assert y.dtype == dtype
    y *= fac.dinv
    np.testing.assert_array_equal(fac.backward(y), fac.solve(b))


@pytest.mark.parametrize("order", ["nested", "random"])
def test_columns_are_the_forward_half_of_unit_vectors_on_their_paths(spd, order):
    """``L^-1 P e_j`` swept over the path of j's supernode to the root only equals the whole forward
    sweep of e_j (which is zero elsewhere), and the triangular solve of an independent solver."""
    N = spd.shape[0]
    perm = node_ordering(spd) if order == "nested" else np.random.default_rng(22).permutation(N)
    fac = LDLT.of(spd, perm=perm)
    dofs = np.array([0, 5, 17, N - 1, N // 2])
    R, Y = fac.columns(dofs)
    assert np.all(np.diff(R) > 0)
    if order == "nested":
        assert R.size < N                  # a path, not the whole factor
    for q, j in enumerate(dofs):
        e = np.zeros(N)
        e[j] = 1.0
        full = fac.forward(e)
        np.testing.assert_allclose(Y[:, q], full[R], rtol=0, atol=1e-12)
        out = np.ones(N, bool)
        out[R] = False
        assert not np.any(full[out])
    # independently: L y = P e, L the unit lower factor of P A P^T in the factor's (postordered) order
    perm = fac.analysis.perm
    Ap = spd[perm][:, perm].toarray()
    Lref = np.linalg.cholesky(Ap)
    Lunit = Lref / np.diag(Lref)
    for q, j in enumerate(dofs):
        e = np.zeros(N)
        e[np.flatnonzero(perm == j)[0]] = 1.0
        ref = np.linalg.solve(Lunit, e)
        assert np.abs(ref[R] - Y[:, q]).max() <= 1e-10 * np.abs(ref).max()
        out = np.ones(N, bool)
        out[R] = False
        assert np.abs(ref[out]).max(initial=0.0) <= 1e-12 * np.abs(ref).max()
