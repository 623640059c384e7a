"""torchgarment.linalg: sparse factorizations against dense solves, singular matrices, the keyed cache, PCG
against a dense solve and at negative curvature, Armijo backtracking, CSR assembly from 3x3 blocks."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import types
from dataclasses import dataclass

import numpy as np
import pytest
import scipy.sparse
import scipy.sparse.linalg
import torch

from torchgarment.errors import InputError, NonConvergenceError, SingularMatrixError
from torchgarment.linalg import (
    CSRAssembler,
    FactorCache,
    FactorizationCache,
    SparseBackend,
    armijo_backtracking,
    compact_csr,
    count_linalg,
    factorize,
    fill_reducing_permutation,
    minres,
    pcg,
)


def _spd(n: int = 30, seed: int = 0) -> scipy.sparse.csr_matrix:
    """A sparse SPD matrix: a 1D Laplacian plus a random sparse symmetric part and a diagonal."""
    rng = np.random.default_rng(seed)
    lap = scipy.sparse.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    r = scipy.sparse.random(n, n, density=0.05, random_state=seed)
    return (lap + 0.1 * (r + r.T) + scipy.sparse.diags(1.0 + rng.random(n))).tocsr()


@pytest.mark.parametrize("symmetric", [True, False])
def test_factorize_matches_a_dense_solve(symmetric: bool) -> None:
    a = _spd()
    b = np.random.default_rng(1).standard_normal((30, 3))
    fact = factorize(a, symmetric=symmetric)
    assert fact.shape == (30, 30) and fact.backend is SparseBackend.SUPERLU
    np.testing.assert_allclose(fact.solve(b), np.linalg.solve(a.toarray(), b), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(fact.solve(b[:, 0]), np.linalg.solve(a.toarray(), b[:, 0]), rtol=1e-10,
                               atol=1e-12)
    shifted = factorize(a, symmetric=symmetric, shift=0.5)
    assert shifted.shift == 0.5
    np.testing.assert_allclose(shifted.solve(b), np.linalg.solve(a.toarray() + 0.5 * np.eye(30), b),
                               rtol=1e-10)
    ns = (a + scipy.sparse.random(30, 30, density=0.05, random_state=3)).tocsc()
    np.testing.assert_allclose(factorize(ns, symmetric=False).solve(b[:, 0], transpose=True),
                               np.linalg.solve(ns.toarray().T, b[:, 0]), rtol=1e-10, atol=1e-12)


def test_the_symmetric_superlu_call_is_unchanged() -> None:
    """The default reproduces the project's SuperLU call bit for bit: the nested-dissection permutation, then
    SuperLU's symmetric mode in that order."""
    a = _spd(60, seed=4)
    b = np.random.default_rng(2).standard_normal(60)
    p = fill_reducing_permutation(a)
    lu = scipy.sparse.linalg.splu(a.tocsr()[p][:, p].tocsc(), permc_spec="NATURAL", diag_pivot_thresh=0.0,
                                  options={"SymmetricMode": True})
    expected = np.empty(60)
    expected[p] = lu.solve(b[p])
    assert np.array_equal(factorize(a).solve(b), expected)


def _grid_laplacian(k: int, block: int) -> scipy.sparse.csr_matrix:
    """The 5-point Laplacian of a k x k grid (plus I), each entry a ``block`` x ``block`` identity block."""
    one = scipy.sparse.diags([-np.ones(k - 1), 2.0 * np.ones(k), -np.ones(k - 1)], [-1, 0, 1])
    lap = scipy.sparse.kronsum(one, one) + scipy.sparse.identity(k * k)
    return scipy.sparse.kron(lap, scipy.sparse.identity(block)).tocsr()


@pytest.mark.parametrize("block", [1, 3])
def test_fill_reducing_permutation_keeps_blocks_and_cuts_fill(block: int) -> None:
    """A permutation that keeps each vertex's 3 unknowns together (3 | n), is cached per sparsity pattern
    (not per values), and factorizes a grid Laplacian with less fill than the natural order; factorize's
    solves in that order match a dense solve, transposed and with several right-hand sides too."""
    k = 24 if block == 3 else 31  # n = 1,728 (blocks) and 961 (not a multiple of 3: the entries' graph)
    a = _grid_laplacian(k, block)
    n = a.shape[0]
    p = fill_reducing_permutation(a)
    assert p.dtype == np.int64 and np.array_equal(np.sort(p), np.arange(n))
    if block == 3:
        assert np.array_equal(p.reshape(-1, 3) - p.reshape(-1, 3)[:, :1], np.tile([0, 1, 2], (n // 3, 1)))
        assert np.all(p.reshape(-1, 3)[:, 0] % 3 == 0)
    assert fill_reducing_permutation(2.0 * a) is p  # same pattern, other values: the cached ordering

    def fill(m: scipy.sparse.spmatrix) -> int:
        lu = scipy.sparse.linalg.splu(m.tocsc(), permc_spec="NATURAL", diag_pivot_thresh=0.0,
                                      options={"SymmetricMode": True})
        return lu.L.nnz + lu.U.nnz

    assert fill(a[p][:, p]) < 0.6 * fill(a)
    rhs = np.random.default_rng(0).standard_normal((n, 2))
    ns = a + scipy.sparse.diags(np.linspace(0.0, 0.1, n - 1), 1)  # a nonsymmetric part for the transpose
    dense = np.linalg.solve(a.toarray(), rhs)
    fact = factorize(a)
    np.testing.assert_allclose(fact.solve(rhs), dense, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(fact.solve(rhs[:, 1]), dense[:, 1], rtol=1e-10, atol=1e-12)
    # SuperLU's symmetric mode on a nonsymmetric matrix without pivoting: still an LU of it (diagonally
    # dominant), so the transposed solve is checked on the same code path
    np.testing.assert_allclose(factorize(ns).solve(rhs, transpose=True), np.linalg.solve(ns.toarray().T, rhs),
                               rtol=1e-10, atol=1e-12)


def test_fill_reducing_permutation_of_tiny_matrices() -> None:
    for n in (0, 1, 3):
        assert np.array_equal(fill_reducing_permutation(scipy.sparse.identity(n, format="csr")), np.arange(n))


def test_fill_reducing_permutation_leaves_an_unsorted_input_alone() -> None:
    """The pattern is hashed in sorted form without sorting the caller's matrix in place (its index arrays
    may be shared, e.g. with :class:`CSRAssembler`'s cached pattern)."""
    a = _grid_laplacian(6, 3)
    rev = scipy.sparse.csr_matrix((a.data.copy(), a.indices.copy(), a.indptr.copy()), shape=a.shape)
    for r in range(a.shape[0]):  # each row's entries in reverse order: the same matrix, unsorted
        lo, hi = rev.indptr[r], rev.indptr[r + 1]
        rev.indices[lo:hi], rev.data[lo:hi] = rev.indices[lo:hi][::-1].copy(), rev.data[lo:hi][::-1].copy()
    rev.has_sorted_indices = False
    indices, data = rev.indices.copy(), rev.data.copy()
    assert fill_reducing_permutation(rev) is fill_reducing_permutation(a)
    assert np.array_equal(rev.indices, indices) and np.array_equal(rev.data, data)


def test_cholmod_backend_matches_a_dense_solve_and_rejects_what_it_cannot_factorize() -> None:
    pytest.importorskip("cvxopt")
    a = _spd(60, seed=5)
    b = np.random.default_rng(6).standard_normal((60, 2))
    fact = factorize(a, backend="cholmod", shift=0.25)
    assert fact.backend is SparseBackend.CHOLMOD and fact.shift == 0.25
    dense = np.linalg.solve(a.toarray() + 0.25 * np.eye(60), b)
    np.testing.assert_allclose(fact.solve(b), dense, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(fact.solve(b[:, 1], transpose=True), dense[:, 1], rtol=1e-10, atol=1e-12)
    # two factorizations stay independent (each has its own analysis and factor)
    other = factorize(2.0 * a, backend="cholmod")
    np.testing.assert_allclose(fact.solve(b), dense, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(other.solve(b), np.linalg.solve(2.0 * a.toarray(), b), rtol=1e-10, atol=1e-12)
    # an indefinite matrix is not factorized (Newton regularizes on this error); nor is a nonsymmetric one
    with pytest.raises(SingularMatrixError, match="not positive definite"):
        factorize(a - 10.0 * scipy.sparse.identity(60), backend="cholmod")
    with pytest.raises(InputError, match="symmetric positive definite"):
        factorize(a, backend="cholmod", symmetric=False)


def test_cholmod_reuses_an_analysis_only_once_its_factorization_is_gone() -> None:
    """A CHOLMOD factorization of a sparsity pattern seen before reuses the analysis of one that nobody holds
    any more, and its answers are the same to the bit as with a fresh analysis; a factorization still held is
    never overwritten by a later one of the same pattern."""
    pytest.importorskip("cvxopt")
    import gc

    from torchgarment.linalg import sparse as sparse_mod

    a = _spd(80, seed=11)
    b = np.random.default_rng(12).standard_normal(80)
    sparse_mod._CHOLMOD_ANALYSES.clear()
    fresh = [factorize(s * a, backend="cholmod").solve(b) for s in (1.0, 3.0)]  # each freed at once
    gc.collect()
    assert len(sparse_mod._CHOLMOD_ANALYSES) == 1  # one pattern, one analysis kept
    kept = factorize(a, backend="cholmod")  # takes the kept analysis
    assert len(sparse_mod._CHOLMOD_ANALYSES) == 0
    y = kept.solve(b)
    assert np.array_equal(y, fresh[0])
    later = factorize(3.0 * a, backend="cholmod")  # kept is alive: a new analysis, kept's factor untouched
    assert np.array_equal(later.solve(b), fresh[1]) and np.array_equal(kept.solve(b), y)
    del kept, later
    gc.collect()
    assert len(sparse_mod._CHOLMOD_ANALYSES) == 1  # bounded: one per pattern
    np.testing.assert_allclose(fresh[0], np.linalg.solve(a.toarray(), b), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("backend", ["superlu", "cholmod"])
def test_factorize_in_a_given_ordering(backend: str) -> None:
    """``ordering`` replaces METIS' ordering of the matrix's own pattern: the answers are those of a dense
    solve in any permutation (here the ordering of a sub-pattern, the case it is for, and a random one), and
    CHOLMOD keeps its analysis per pattern and ordering (a kept analysis is never used in another order)."""
    import gc

    if backend == "cholmod":
        pytest.importorskip("cvxopt")
    from torchgarment.linalg import sparse as sparse_mod

    n = 90
    a = _spd(n, seed=31)
    lap = scipy.sparse.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1], format="csr")
    b = np.random.default_rng(32).standard_normal(n)
    dense = np.linalg.solve(a.toarray(), b)
    orders = [fill_reducing_permutation(lap), np.random.default_rng(33).permutation(n)]
    sparse_mod._CHOLMOD_ANALYSES.clear()
    for p in orders:
        np.testing.assert_allclose(factorize(a, backend=backend, ordering=p).solve(b), dense, rtol=1e-10,
                                   atol=1e-12)
    gc.collect()
    assert len(sparse_mod._CHOLMOD_ANALYSES) == (2 if backend == "cholmod" else 0)  # one per ordering
    for p in orders:  # each takes the analysis of its own ordering
        np.testing.assert_allclose(factorize(a, backend=backend, ordering=p).solve(b), dense, rtol=1e-10,
                                   atol=1e-12)
    np.testing.assert_allclose(factorize(a, backend=backend).solve(b), dense, rtol=1e-10, atol=1e-12)
    for bad in (orders[1][:-1], np.zeros(n, dtype=np.int64), orders[1] + 1, orders[1].astype(float)):
        with pytest.raises(InputError, match="ordering must be a permutation"):
            factorize(a, backend=backend, ordering=bad)


def test_cholmod_reuses_its_input_matrix_per_pattern() -> None:
    """CHOLMOD's input (cvxopt's sparse lower triangle, sorted from triplets) is built once per sparsity
    pattern; later matrices of the pattern (another format, an explicit zero, after a failed factorization)
    only write their values into it, with the same answers to the bit as a freshly built input."""
    pytest.importorskip("cvxopt")
    from torchgarment.linalg import sparse as sparse_mod

    a = _spd(90, seed=21).tocsr()
    b = np.random.default_rng(22).standard_normal(90)
    z = a.copy()  # the same pattern with one off-diagonal pair stored as explicit zeros
    rows = np.repeat(np.arange(90), np.diff(z.indptr))
    i, j = next((r, c) for r, c in zip(rows, z.indices) if r < c)
    z.data[((rows == i) & (z.indices == j)) | ((rows == j) & (z.indices == i))] = 0.0
    matrices = [a, 2.0 * a.tocsc(), z, a.tocoo()]
    fresh = []
    for m in matrices:
        sparse_mod._CHOLMOD_INPUTS.clear()
        fresh.append(factorize(m, backend="cholmod").solve(b))
    sparse_mod._CHOLMOD_INPUTS.clear()
    reused = [factorize(matrices[0], backend="cholmod").solve(b)]
    (built,) = sparse_mod._CHOLMOD_INPUTS._items.values()  # the input the first factorization built
    reused += [factorize(m, backend="cholmod").solve(b) for m in matrices[1:]]
    assert len(sparse_mod._CHOLMOD_INPUTS) == 1
    assert next(iter(sparse_mod._CHOLMOD_INPUTS._items.values())) is built  # taken again, not rebuilt
    assert all(np.array_equal(x, y) for x, y in zip(fresh, reused))
    with pytest.raises(SingularMatrixError, match="not positive definite"):
        factorize(a - 100.0 * scipy.sparse.identity(90, format="csr"), backend="cholmod")
    assert np.array_equal(factorize(a, backend="cholmod").solve(b), fresh[0])  # the pool survives a failure
    np.testing.assert_allclose(fresh[1], np.linalg.solve(2.0 * a.toarray(), b), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(fresh[2], np.linalg.solve(z.toarray(), b), rtol=1e-10, atol=1e-12)


def test_singular_matrix_raises() -> None:
    a = scipy.sparse.csr_matrix(np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1.0]]))
    with pytest.raises(SingularMatrixError, match="stiffness matrix is singular"):
        factorize(a, what="stiffness matrix").solve(np.ones(3))
    assert issubclass(SingularMatrixError, NonConvergenceError)
    with pytest.raises(InputError, match="expected one of"):
        factorize(a, backend="umfpack")


def test_count_linalg_counts_factorizations_and_solves_in_nested_blocks() -> None:
    a = _spd()
    singular = scipy.sparse.csr_matrix(np.array([[1.0, 1.0], [1.0, 1.0]]))
    with count_linalg() as outer:
        fact = factorize(a)
        with count_linalg() as inner:
            fact.solve(np.ones(30))
            fact.solve(np.ones((30, 4)))  # a block of right-hand sides is one solve
            with pytest.raises(SingularMatrixError):
                factorize(singular)  # a failed factorization is work done too
        cache = FactorCache()
        cache.store(fact)
        with count_linalg() as preconditioned:  # PCG applies the stored factorization once per iteration
            assert cache.solve((a + scipy.sparse.diags(0.01 * np.ones(30))).tocsr(), np.ones(30), 1e-10,
                               50) is not None
    factorize(a).solve(np.ones(30))  # outside every block: not counted
    assert (inner.factorizations, inner.solves) == (1, 2)
    assert preconditioned.factorizations == 0 and preconditioned.solves >= 2
    # the outer block also counts the inner blocks' work
    assert outer.factorizations == 2 and outer.solves == 2 + preconditioned.solves
    assert outer.factorization_seconds >= inner.factorization_seconds > 0
    assert outer.solve_seconds >= inner.solve_seconds > 0
    total = inner.as_dict()
    inner.add(inner)
    assert inner.as_dict() == {k: 2 * v for k, v in total.items()}


def test_cache_refactorizes_only_on_a_new_key() -> None:
    cache = FactorizationCache()
    a = _spd()
    builds = []

    def build() -> scipy.sparse.csr_matrix:
        builds.append(1)
        return a

    k1 = torch.zeros(4, 3, dtype=torch.float64)
    f1 = cache.factorize(k1, build)
    assert cache.factorize(k1.clone(), build) is f1 and cache.factorizations == 1 and len(builds) == 1
    f2 = cache.factorize(k1 + 1.0, build)
    assert f2 is not f1 and cache.factorizations == 2
    cache.clear()
    cache.factorize(k1 + 1.0, build)
    assert cache.factorizations == 3 and len(builds) == 3


def test_factor_cache_solves_nearby_systems_by_pcg() -> None:
    a = _spd()
    cache = FactorCache()
    assert cache.solve(a, np.ones(30), 1e-8, 20) is None  # nothing stored yet
    cache.store(factorize(a))
    near = (a + scipy.sparse.diags(0.01 * np.ones(30))).tocsr()
    y = cache.solve(near, np.ones(30), 1e-10, 50)
    np.testing.assert_allclose(y, np.linalg.solve(near.toarray(), np.ones(30)), rtol=1e-8)
    assert cache.pcg_solves == 1 and cache.factorizations == 1


def test_factor_cache_takes_a_budget_stopped_solve_within_accept_rtol() -> None:
    """A PCG solve stopped by its budget short of rtol is returned when its relative residual is at most
    accept_rtol (an inexact Newton step), and refused (None: factorize afresh) when it is not. Taking it drops
    the factorization, so the next system is factorized afresh; a solve that reaches rtol keeps it."""
    a = _spd()
    near = (a + scipy.sparse.diags(np.linspace(0.0, 3.0, 30))).tocsr()  # far enough to need several updates
    b = np.random.default_rng(2).standard_normal(30)
    lu = factorize(a)
    _, k, res = pcg(lambda v: near @ v, b, lu.solve, 1e-12, 2)  # the budget of maxiter=3 (see solve)
    assert k == 2 and 1e-6 < res < 0.5  # stopped by the budget, short of 1e-12
    cache = FactorCache()
    cache.store(lu)
    assert cache.solve(near, b, 1e-12, 3) is None  # without accept_rtol: a fresh factorization is needed
    assert cache.solve(near, b, 1e-12, 3, accept_rtol=0.5 * res) is None
    y = cache.solve(near, b, 1e-12, 3, accept_rtol=2.0 * res)
    assert y is not None and cache.pcg_solves == 1 and cache.factorizations == 1
    assert np.linalg.norm(near @ y - b) <= 2.0 * res * np.linalg.norm(b)
    assert float(y @ b) > 0  # a descent direction of 1/2 y^T K y - b^T y from zero
    assert cache.factorization is None  # the drifted preconditioner is dropped
    assert cache.solve(a, b, 1e-8, 3, accept_rtol=0.5) is None  # even for its own matrix: factorize afresh
    cache.store(lu)
    y = cache.solve(a, b, 1e-8, 3, accept_rtol=0.5)  # reaches rtol: taken, and the factorization kept
    assert y is not None and cache.factorization is lu and cache.pcg_solves == 2


def test_pcg_on_numpy_reproduces_scipy_cg_bit_for_bit() -> None:
    """The numpy path of pcg runs scipy.sparse.linalg.cg's arithmetic (the reused-factorization Newton solves
    of the drape depended on it): same iterate, same convergence decision within the same budget."""
    a = _spd(60, seed=3)
    near = (a + scipy.sparse.diags(0.05 * np.ones(60))).tocsr()
    lu = factorize(a)
    b = np.random.default_rng(1).standard_normal(60)
    m = scipy.sparse.linalg.LinearOperator((60, 60), matvec=lu.solve, dtype=np.float64)
    for maxiter, rtol in ((50, 1e-10), (3, 1e-12)):
        ref, info = scipy.sparse.linalg.cg(near, b, rtol=rtol, atol=0.0, maxiter=maxiter, M=m)
        y, k, res = pcg(lambda v: near @ v, b, lu.solve, rtol, maxiter - 1)
        assert (info == 0) == (res <= rtol)
        if info == 0:
            assert np.array_equal(y, ref)
        assert isinstance(y, np.ndarray)


def test_pcg_matches_a_dense_solve_and_raises_at_negative_curvature() -> None:
    a = torch.from_numpy(_spd(40, seed=5).toarray())
    b = torch.randn(40, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    inv_diag = 1.0 / torch.diagonal(a)
    y, k, res = pcg(lambda v: a @ v, b, lambda r: inv_diag * r, 1e-12, 200)
    torch.testing.assert_close(y, torch.linalg.solve(a, b), rtol=1e-9, atol=1e-10)
    assert 0 < k <= 40 and res <= 1e-12
    y2, k2, _ = pcg(lambda v: a @ v, b, None, 1e-12, 200, x0=y)  # warm start at the answer
    assert k2 <= 1
    indefinite = torch.diag(torch.tensor([1.0, -1.0, 2.0], dtype=torch.float64))
    rhs = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)  # p^T K p = -1 at the first direction
    with pytest.raises(NonConvergenceError, match="non-positive curvature"):
        pcg(lambda v: indefinite @ v, rhs, None, 1e-10, 10)
    _, k3, res3 = pcg(lambda v: indefinite @ v, rhs, None, 1e-10, 10, stop_at_negative_curvature=True)
    assert k3 == 0 and res3 == 1.0
    z, k0, r0 = pcg(lambda v: a @ v, torch.zeros(40, dtype=torch.float64), None, 1e-10, 10)
    assert k0 == 0 and r0 == 0.0 and not bool(z.any())


def _indefinite(n: int = 60, seed: int = 7) -> np.ndarray:
    """A symmetric indefinite matrix: the SPD one shifted by its median eigenvalue."""
    a = _spd(n, seed).toarray()
    return a - np.median(np.linalg.eigvalsh(a)) * np.eye(n) - 0.01 * np.eye(n)


def test_minres_solves_indefinite_systems_where_cg_meets_negative_curvature() -> None:
    a = _indefinite()
    assert np.linalg.eigvalsh(a).min() < 0 < np.linalg.eigvalsh(a).max()
    b = np.random.default_rng(2).standard_normal(a.shape[0])
    exact = np.linalg.solve(a, b)
    _, _, res_cg = pcg(lambda v: a @ v, b, None, 1e-12, 500, stop_at_negative_curvature=True)
    assert res_cg > 0.1  # CG stops at the first direction of negative curvature
    inv_absdiag = 1.0 / np.abs(np.diag(a))  # an SPD preconditioner
    for array in (np.asarray, torch.from_numpy):
        mat, rhs = array(a), array(b)
        y, k, res = minres(lambda v: mat @ v, rhs, lambda r: array(inv_absdiag) * r, 1e-12, 500)
        assert res <= 1e-9 and 0 < k <= 500
        np.testing.assert_allclose(np.asarray(y), exact, rtol=1e-7, atol=1e-9 * np.abs(exact).max())
    # against scipy's MINRES (same recurrences), unpreconditioned, on a budget: the residual never grows
    residuals = []
    for budget in (5, 10, 20, 40):
        y, k, res = minres(lambda v: a @ v, b, None, 1e-14, budget)
        ref, _ = scipy.sparse.linalg.minres(a, b, rtol=1e-14, maxiter=budget)
        np.testing.assert_allclose(y, ref, rtol=1e-8, atol=1e-10 * np.abs(ref).max())
        residuals.append(res)
    assert residuals == sorted(residuals, reverse=True) and residuals[-1] < residuals[0]
    # warm start at the answer: nothing to do; zero right-hand side: zero
    y, k, res = minres(lambda v: a @ v, b, None, 1e-10, 100, x0=exact)
    assert k <= 1 and res <= 1e-9
    z, k0, r0 = minres(lambda v: a @ v, np.zeros_like(b), None, 1e-10, 10)
    assert k0 == 0 and r0 == 0.0 and not z.any()
    with pytest.raises(NonConvergenceError, match="positive definite preconditioner"):
        minres(lambda v: a @ v, b, lambda r: -r, 1e-10, 10)


def test_minres_meets_rtol_on_the_true_residual_with_a_badly_scaled_preconditioner() -> None:
    """MINRES's recurrences track the preconditioned residual; with a diagonal preconditioner over scales of
    e^-4..e^4 they reached their target at a true residual 60-300x above rtol (the skirt's adjoint, 2.5x on
    another machine); the solve now restarts from its iterate until the true residual meets rtol."""
    base = _indefinite()
    b = np.random.default_rng(2).standard_normal(base.shape[0])
    for seed in range(3):
        d = np.exp(np.random.default_rng(seed).uniform(-4.0, 4.0, base.shape[0]))
        a = d[:, None] * base * d[None, :]
        inv = 1.0 / np.abs(np.diag(a))
        for array in (np.asarray, torch.from_numpy):
            mat, rhs, pre = array(a), array(b), array(inv)
            y, k, res = minres(lambda v: mat @ v, rhs, lambda r: pre * r, 1e-10, 2000)
            true = float(np.linalg.norm(a @ np.asarray(y) - b) / np.linalg.norm(b))
            assert res <= 1e-10 and k < 2000, (seed, res, k)
            assert res == pytest.approx(true, rel=1e-3)  # the returned residual is the true one


def test_armijo_accepts_and_shrinks() -> None:
    f = lambda a: (a - 0.1) ** 2  # noqa: E731 - f(0) = 0.01, slope -0.2
    ls = {"armijo_c": 1e-4, "backtrack": 0.5}
    alpha, value, ok = armijo_backtracking(f, 0.01, -0.2, 1.0, **ls, max_backtracks=20)
    assert ok and alpha == 0.125 and value == f(0.125)
    assert armijo_backtracking(f, 0.01, -0.2, 0.1, **ls, max_backtracks=20)[:2] == (0.1, 0.0)
    tried = []

    def bad(a: float) -> float:
        tried.append(a)
        return float("nan") if a > 0.3 else 1.0

    alpha, value, ok = armijo_backtracking(bad, 0.0, -1.0, 1.0, **ls, max_backtracks=3)
    assert not ok and tried == [1.0, 0.5, 0.25] and alpha == 0.25 and value == 1.0
    tried.clear()
    *_, ok = armijo_backtracking(bad, 0.0, -1.0, 1.0, armijo_c=1e-4, backtrack=0.5, max_backtracks=50,
                                 min_alpha=0.2)
    assert not ok and tried == [1.0, 0.5, 0.25]
    # slack accepts a step that does not decrease within round-off
    assert armijo_backtracking(lambda a: 1.0 + 1e-17, 1.0, -1e-20, 1.0, armijo_c=0.5, backtrack=0.5,
                               max_backtracks=1, slack=1e-15)[2]


@dataclass
class _Blocks:
    rows: torch.Tensor
    cols: torch.Tensor
    values: torch.Tensor


def test_assembler_matches_a_dense_sum() -> None:
    gen = torch.Generator().manual_seed(3)
    rows = torch.tensor([0, 1, 2, 0, 2, 1, 0])
    cols = torch.tensor([0, 1, 2, 1, 0, 1, 0])  # (1, 1) and (0, 0) twice: summed
    vals = torch.randn(7, 3, 3, dtype=torch.float64, generator=gen)
    dense = torch.zeros(9, 9, dtype=torch.float64)
    for r, c, v in zip(rows.tolist(), cols.tolist(), vals):
        dense[3 * r:3 * r + 3, 3 * c:3 * c + 3] += v
    asm = CSRAssembler(3)
    np.testing.assert_allclose(asm.assemble(_Blocks(rows, cols, vals)).toarray(), dense.numpy(), rtol=1e-15)
    # the cached pattern is reused for new values and rebuilt for a new pattern
    np.testing.assert_allclose(asm.assemble(_Blocks(rows, cols, 2 * vals)).toarray(), 2 * dense.numpy())
    one = asm.assemble(_Blocks(rows[:1], cols[:1], vals[:1])).toarray()
    np.testing.assert_allclose(one[:3, :3], vals[0].numpy())
    assert np.count_nonzero(one[3:]) == 0


def test_assembler_pattern_is_canonical_and_shared_across_assemblers() -> None:
    """Random blocks (duplicates, empty block rows) give the dense sum in canonical CSR (sorted, no
    duplicate entries); a second assembler with the same block rows and columns takes the first one's pattern
    (the same read-only arrays) instead of sorting again, and other blocks get their own."""
    gen = torch.Generator().manual_seed(5)
    nv, k = 40, 300
    rows = torch.randint(0, nv - 5, (k,), generator=gen)  # the last 5 block rows stay empty
    cols = torch.randint(0, nv, (k,), generator=gen)
    vals = torch.randn(k, 3, 3, dtype=torch.float64, generator=gen)
    dense = torch.zeros(3 * nv, 3 * nv, dtype=torch.float64)
    for r, c, v in zip(rows.tolist(), cols.tolist(), vals):
        dense[3 * r:3 * r + 3, 3 * c:3 * c + 3] += v
    first = CSRAssembler(nv)
    a = first.assemble(_Blocks(rows, cols, vals))
    np.testing.assert_allclose(a.toarray(), dense.numpy(), rtol=1e-14, atol=1e-15)
    assert a.has_canonical_format and a.nnz == 9 * len(set(zip(rows.tolist(), cols.tolist())))
    second = CSRAssembler(nv)
    b = second.assemble(_Blocks(rows.clone(), cols.clone(), vals))
    assert np.array_equal(b.data, a.data)
    assert all(getattr(second, k) is getattr(first, k) for k in ("_indices", "_indptr", "_slot"))
    assert np.shares_memory(b.indices, a.indices) and not b.indices.flags.writeable
    transposed = CSRAssembler(nv)
    other = transposed.assemble(_Blocks(cols, rows, vals.transpose(1, 2)))  # the transpose: another pattern
    assert transposed._indices is not first._indices
    np.testing.assert_allclose(other.toarray(), dense.numpy().T, rtol=1e-14, atol=1e-15)


def test_missing_backend_is_an_input_error(monkeypatch: pytest.MonkeyPatch) -> None:
    import importlib

    real = importlib.import_module

    def fake(name: str, package: str | None = None) -> types.ModuleType:
        if name in ("pypardiso", "cholespy", "cvxopt"):
            raise ImportError(name)
        return real(name, package)

    monkeypatch.setattr(importlib, "import_module", fake)
    monkeypatch.delenv("MKL_CBWR", raising=False)
    for backend in ("pardiso", "cholespy", "cholmod"):
        with pytest.raises(InputError, match="pip install"):
            factorize(_spd(), backend=backend)
    # the pardiso path once set MKL_CBWR here, before the import: every later child process of the test run
    # (a batch's Ray workers) inherited it, and torch's MKL rounded differently in them
    assert "MKL_CBWR" not in os.environ


class _FakeMKL:
    """``MKL_CBWR_Get`` / ``MKL_CBWR_Set`` of an MKL library, recording the calls."""

    def __init__(self, branch: int, status: int = 0) -> None:
        self.branch, self.status, self.sets = branch, status, []

        def get(option: int) -> int:
            assert option == 1  # MKL_CBWR_BRANCH
            return self.branch

        def put(branch: int) -> int:
            self.sets.append(branch)
            if self.status == 0:
                self.branch = branch
            return self.status

        self.MKL_CBWR_Get, self.MKL_CBWR_Set = get, put


def test_mkl_reproducible_sets_the_compatible_branch_through_the_library(monkeypatch: pytest.MonkeyPatch):
    from torchgarment.linalg.sparse import mkl_reproducible

    monkeypatch.delenv("MKL_CBWR", raising=False)
    off = _FakeMKL(branch=1)  # MKL_CBWR_BRANCH_OFF
    assert mkl_reproducible(off) == 3 and off.sets == [3]
    assert mkl_reproducible(off) == 3 and off.sets == [3]  # already set: no second call
    assert "MKL_CBWR" not in os.environ
    used = _FakeMKL(branch=1, status=-8)  # MKL ran before: the mode can no longer change
    with pytest.warns(RuntimeWarning, match="MKL_CBWR=COMPATIBLE"):
        assert mkl_reproducible(used) == 1
    monkeypatch.setenv("MKL_CBWR", "AUTO")  # the user's choice stands
    chosen = _FakeMKL(branch=2)
    assert mkl_reproducible(chosen) == 2 and chosen.sets == []


def test_pardiso_solves_in_the_compatible_branch_and_leaves_the_environment_alone(tmp_path):
    """With pypardiso installed: a fresh process factorizes with pardiso at 2 threads, twice with the same
    bits, in MKL's COMPATIBLE branch, with no MKL_CBWR in its environment afterwards."""
    pytest.importorskip("pypardiso")
    script = tmp_path / "pardiso.py"
    script.write_text(textwrap.dedent("""
        import os, numpy as np, scipy.sparse, torch
        from torchgarment.linalg import factorize
        import pypardiso
        torch.set_num_threads(2)
        n = 3000
        rng = np.random.default_rng(0)
        a = scipy.sparse.random(n, n, density=2e-3, random_state=rng, format="csr")
        a = (a + a.T + 20.0 * scipy.sparse.identity(n)).tocsr()
        b = rng.standard_normal(n)
        y = [factorize(a, backend="pardiso").solve(b) for _ in range(2)]
        lib = pypardiso.PyPardisoSolver().libmkl
        print(lib.MKL_CBWR_Get(1), "MKL_CBWR" in os.environ, np.array_equal(y[0], y[1]),
              float(np.linalg.norm(a @ y[0] - b) / np.linalg.norm(b)) < 1e-10)
    """))
    env = {k: v for k, v in os.environ.items() if k != "MKL_CBWR"}
    out = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["3", "False", "True", "True"], out.stdout


def test_csr_matvec_is_the_matrix_product():
    from torchgarment.linalg import csr_matvec

    rng = np.random.default_rng(4)
    h = scipy.sparse.random(40, 40, density=0.2, random_state=rng, format="coo")
    v = torch.from_numpy(rng.standard_normal(40))
    y = csr_matvec(h, torch.device("cpu"))(v)
    assert y.dtype == torch.float64 and torch.allclose(y, torch.from_numpy(h.tocsr() @ v.numpy()), atol=1e-14)


def test_compact_csr_gives_the_same_products_with_32_bit_indices():
    import warnings

    gen = torch.Generator().manual_seed(0)
    dense = torch.randn(40, 30, dtype=torch.float64, generator=gen)
    dense[dense.abs() < 1.0] = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "sparse CSR support is in beta"
        wide = dense.to_sparse_csr()
    small = compact_csr(wide)
    assert wide.crow_indices().dtype == torch.int64
    assert small.crow_indices().dtype == torch.int32 and small.col_indices().dtype == torch.int32
    for rhs in (torch.randn(30, 3, dtype=torch.float64, generator=gen),
                torch.randn(30, 7, dtype=torch.float64, generator=gen)):
        assert torch.equal(small @ rhs, wide @ rhs)
    assert compact_csr(small) is small
    with pytest.raises(InputError):
        compact_csr(dense)
