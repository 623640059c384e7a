"""Sparse direct solves: factorizations with a pluggable backend, caches, and CSR assembly from 3x3 blocks.

Every sparse factorization of the project goes through :func:`factorize`. The default backend,
:attr:`SparseBackend.SUPERLU`, is scipy's SuperLU; for symmetric matrices (``symmetric=True``, the default)
the matrix is first permuted symmetrically by METIS' nested dissection of its sparsity graph
(:func:`fill_reducing_permutation`, computed on the graph of the 3x3 blocks and cached per sparsity pattern),
then factorized in that order with no partial pivoting in SuperLU's symmetric mode::

    p = fill_reducing_permutation(A)
    splu(A[p][:, p].tocsc(), permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True})

(nested dissection suits the meshes' planar graphs: factorizations of draped Newton systems 2.1x faster than
in SuperLU's own minimum-degree order at 30K vertices, 2.0x at 15K, 1.3x at 3K; a caller whose matrices share
most of their pattern, a mesh plus contacts that come and go, passes one ordering for all of them,
``factorize(..., ordering=p)``), and with scipy's defaults
(COLAMD ordering, partial pivoting) for ``symmetric=False``. The optional backends ``"pardiso"`` (Intel MKL
Pardiso through PyPI's ``pypardiso``, in MKL's COMPATIBLE reproducibility branch set by
:func:`mkl_reproducible`, so that results are reproducible on several threads), ``"cholespy"`` (a supernodal
Cholesky, SPD matrices only) and ``"cholmod"`` (SuiteSparse CHOLMOD's supernodal Cholesky through ``cvxopt``,
SPD matrices only: 3-4x faster than SuperLU on the simulation's projected Newton Hessians; the analysis of a
factorization that nobody holds any more is reused for the next one of the same sparsity pattern, and so is
its input matrix, whose values alone are rewritten) are imported only when asked for; a missing one raises
:class:`~torchgarment.errors.InputError`.
"""

from __future__ import annotations

import ctypes
import hashlib
import importlib
import importlib.util
import os
import threading
import time
import warnings
import weakref
from collections import OrderedDict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from types import ModuleType
from typing import Callable, Protocol

import numpy as np
import pymetis
import scipy.sparse
import scipy.sparse.linalg
import torch

from torchgarment.errors import InputError, SingularMatrixError
from torchgarment.linalg.iterative import pcg
from torchgarment.options import OptionEnum


class SparseBackend(OptionEnum):
    """Sparse direct solvers :func:`factorize` can use."""

    #: scipy's SuperLU (always available; the default)
    SUPERLU = "superlu"
    #: Intel MKL Pardiso, symmetric indefinite (``mtype=-2``) or nonsymmetric (``mtype=11``); needs
    # ``pypardiso``
    PARDISO = "pardiso"
    #: supernodal Cholesky of an SPD matrix (CPU); needs ``cholespy``
    CHOLESPY = "cholespy"
    #: SuiteSparse CHOLMOD's supernodal Cholesky of an SPD matrix (CPU), through ``cvxopt`` (GPL-3, an
    # optional extra); 3-4x faster than SuperLU on the simulation Hessians; a matrix that is not positive
    # definite raises SingularMatrixError (Newton then regularizes)
    CHOLMOD = "cholmod"

    @property
    def positive_definite_only(self) -> bool:
        """Whether the backend factorizes symmetric positive definite matrices only (a Cholesky)."""
        return self in (SparseBackend.CHOLESPY, SparseBackend.CHOLMOD)

    @classmethod
    def fastest_spd(cls) -> "SparseBackend":
        """The fastest installed backend for symmetric positive definite systems: CHOLMOD when ``cvxopt`` is
        installed (3-4x faster factorizations than SuperLU on the simulation's projected Newton Hessians),
        else SuperLU (as ``scipy.sparse.linalg.spsolve`` takes UMFPACK when scikit-umfpack is installed). What
        a setting of ``"auto"`` resolves to (retargeting's default). Looked up without importing cvxopt
        (settings are built when the command line starts); a broken install fails at the first factorization,
        with :class:`~torchgarment.errors.InputError`."""
        return cls.CHOLMOD if importlib.util.find_spec("cvxopt") is not None else cls.SUPERLU

    def for_indefinite(self) -> "SparseBackend":
        """The backend for symmetric matrices that may be indefinite, such as an adjoint's exact Hessian at an
        equilibrium where springs are compressed: this one, or SuperLU in place of a Cholesky backend (whose
        factorization would fail there; measured: 13 of 16 adjoints of a 5 cm skirt's adjustment)."""
        return SparseBackend.SUPERLU if self.positive_definite_only else self


@dataclass
class LinalgCounters:
    """Sparse direct work counted while :func:`count_linalg` is active (every :func:`factorize` and
    :meth:`Factorization.solve` of the process, failed factorizations included).

    Attributes:
        factorizations: calls of :func:`factorize`. factorization_seconds: their wall seconds (ordering,
            analysis and numeric factorization).
        solves: calls of :meth:`Factorization.solve` (one forward and one backward substitution each, for
            a right-hand side (n,) or a block (n, k)). solve_seconds: their wall seconds.
    """

    factorizations: int = 0
    factorization_seconds: float = 0.0
    solves: int = 0
    solve_seconds: float = 0.0

    def add(self, other: "LinalgCounters") -> None:
        """Add ``other``'s counts and seconds to these."""
        self.factorizations += other.factorizations
        self.factorization_seconds += other.factorization_seconds
        self.solves += other.solves
        self.solve_seconds += other.solve_seconds

    def as_dict(self) -> dict[str, float]:
        """The counters as a JSON-ready dict."""
        return asdict(self)


_COUNTERS: list[LinalgCounters] = []
_COUNTERS_LOCK = threading.Lock()


@contextmanager
def count_linalg() -> Iterator[LinalgCounters]:
    """Count the factorizations and solves made in this process inside the ``with`` block.

    Process-wide, not per thread: autograd may run a backward (an adjoint's solve) on a device thread of its
    own. Blocks nest: an inner block's work is also counted by every enclosing one. The overhead is two clock
    reads per call.

    Example:
        >>> with count_linalg() as c:
        ...     factorize(a).solve(b)
        >>> c.factorizations, c.solves
        (1, 1)
    """
    counters = LinalgCounters()
    with _COUNTERS_LOCK:
        _COUNTERS.append(counters)
    try:
        yield counters
    finally:
        with _COUNTERS_LOCK:
            del _COUNTERS[next(i for i, c in enumerate(_COUNTERS) if c is counters)]


def _record(factorizations: int, solves: int, seconds: float) -> None:
    if not _COUNTERS:
        return
    with _COUNTERS_LOCK:
        for c in _COUNTERS:
            c.factorizations += factorizations
            c.factorization_seconds += seconds if factorizations else 0.0
            c.solves += solves
            c.solve_seconds += seconds if solves else 0.0


class Factorization:
    """A factorized sparse square matrix ``A`` (n, n), float64, on the CPU; :meth:`solve` applies ``A^-1``.

    Attributes:
        shape: ``(n, n)``.
        backend: the :class:`SparseBackend` that factorized it.
        shift: the diagonal shift ``s`` it was made with (the factorized matrix is ``A + s I``).
        what: the matrix's name in error messages.
        matrix: the factorized matrix ``A + s I`` (scipy sparse, float64), e.g. for residual checks.
    """

    def __init__(self, solve: Callable[[np.ndarray, bool], np.ndarray], shape: tuple[int, int],
                 backend: SparseBackend, shift: float = 0.0, what: str = "matrix",
                 matrix: scipy.sparse.spmatrix | None = None) -> None:
        self._solve = solve
        self.matrix = matrix
        self.shape = (int(shape[0]), int(shape[1]))
        self.backend = backend
        self.shift = float(shift)
        self.what = what

    def solve(self, b: np.ndarray, *, transpose: bool = False) -> np.ndarray:
        """``A^-1 b`` (``A^-T b`` with ``transpose``) for ``b`` (n,) or (n, k) float64; the same shape.

        Raises:
            SingularMatrixError: the solve returned NaN or infinite values (a numerically singular ``A``).
        """
        t0 = time.perf_counter()
        y = self._solve(np.asarray(b, dtype=np.float64), transpose)
        _record(0, 1, time.perf_counter() - t0)
        if not np.all(np.isfinite(y)):
            raise SingularMatrixError(f"the {self.what} is singular: its sparse solve returned non-finite "
                                      f"values")
        return y


Solve = Callable[[np.ndarray, bool], np.ndarray]
"""``(b, transpose) -> A^-1 b`` (or ``A^-T b``)."""


class _Kept:
    """The last ``kept`` values by key (least recently used dropped first), shared by threads under a
    re-entrant lock (a garbage collection inside it may put a value back, see :func:`_release_analysis`)."""

    def __init__(self, kept: int) -> None:
        self.kept = int(kept)
        self._items: OrderedDict = OrderedDict()
        self._lock = threading.RLock()

    def get(self, key: tuple) -> object | None:
        """The value of ``key`` (now the most recently used), or None."""
        with self._lock:
            hit = self._items.get(key)
            if hit is not None:
                self._items.move_to_end(key)
            return hit

    def pop(self, key: tuple) -> object | None:
        """Take the value of ``key`` out (the caller owns it until it puts it back), or None."""
        with self._lock:
            return self._items.pop(key, None)

    def put(self, key: tuple, value: object) -> None:
        """Keep ``value`` as the most recently used; drop the oldest beyond ``kept``."""
        with self._lock:
            self._items[key] = value
            self._items.move_to_end(key)
            while len(self._items) > self.kept:
                self._items.popitem(last=False)

    def clear(self) -> None:  # noqa: D102
        with self._lock:
            self._items.clear()

    def __len__(self) -> int:
        return len(self._items)


def _digest(*arrays: np.ndarray) -> bytes:
    """A 16-byte hash of the bytes of ``arrays`` (a cache key's part)."""
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        h.update(np.ascontiguousarray(a).data)
    return h.digest()


_ORDERINGS = _Kept(8)


def _pattern_key(a: scipy.sparse.csr_matrix) -> tuple:
    """A key of the sparsity pattern of ``a`` (CSR with sorted indices): its size and a hash of its index
    arrays."""
    return (int(a.shape[0]), int(a.nnz), a.indptr.dtype.str, a.indices.dtype.str,
            _digest(a.indptr, a.indices))


def _sorted_csr(matrix: scipy.sparse.spmatrix) -> scipy.sparse.csr_matrix:
    a = matrix.tocsr()
    if not a.has_sorted_indices:
        a = a.sorted_indices()  # a copy: the caller's matrix (and index arrays it may share) stay as they are
    return a


def fill_reducing_permutation(matrix: scipy.sparse.spmatrix) -> np.ndarray:
    """(n,) int64 permutation ``p`` such that ``A[p][:, p]`` factorizes with little fill: METIS' nested
    dissection of the sparsity graph of ``A + A^T``.

    The graph is that of the 3x3 blocks when ``n`` is a multiple of 3 (the simulation's unknowns are a
    vertex's x, y and z: a third of the nodes, and a vertex's three unknowns stay together), else that of the
    entries.
    The ordering depends only on the sparsity pattern; the last few are cached by a hash of it, so the
    Newton iterations of one solve, whose Hessians share a pattern, compute it once. METIS is deterministic:
    the same pattern always gives the same ordering.
    """
    a = _sorted_csr(matrix)
    return _nested_dissection(a, _pattern_key(a))


def _nested_dissection(a: scipy.sparse.csr_matrix, key: tuple) -> np.ndarray:
    """:func:`fill_reducing_permutation` of ``a`` (CSR, sorted indices) whose :func:`_pattern_key` is
    ``key``."""
    n = int(a.shape[0])
    hit = _ORDERINGS.get(key)
    if hit is not None:
        return hit
    b = 3 if n % 3 == 0 else 1
    m = n // b
    if m <= 1:
        perm = np.arange(n, dtype=np.int64)
    else:
        rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(a.indptr)) // b
        cols = a.indices.astype(np.int64) // b
        off = rows != cols
        g = scipy.sparse.coo_matrix((np.ones(int(off.sum()), dtype=np.int8), (rows[off], cols[off])),
                                    shape=(m, m)).tocsr()
        g = (g + g.T).tocsr()  # the symmetric pattern, duplicates summed away
        g.sort_indices()
        order, _ = pymetis.nested_dissection(adjacency=pymetis.CSRAdjacency(
            g.indptr.astype(np.int64), g.indices.astype(np.int64)))
        order = np.asarray(order, dtype=np.int64)
        perm = (b * order[:, None] + np.arange(b, dtype=np.int64)[None, :]).reshape(-1)
    perm.setflags(write=False)
    _ORDERINGS.put(key, perm)
    return perm


def _superlu(a: scipy.sparse.spmatrix, symmetric: bool, ordering: np.ndarray | None) -> Solve:
    # symmetric: nested dissection (or the given ordering), then SuperLU's symmetric mode in that order (no
    # pivoting); else scipy's defaults (COLAMD, partial pivoting)
    p = (fill_reducing_permutation(a) if ordering is None else ordering) if symmetric else None
    m = a.tocsr()[p][:, p].tocsc() if p is not None else a.tocsc()
    mode: dict = (dict(permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
                  if symmetric else {})
    lu = scipy.sparse.linalg.splu(m, **mode)

    def solve(b: np.ndarray, transpose: bool) -> np.ndarray:
        trans = "T" if transpose else "N"
        if p is None:
            return lu.solve(b, trans=trans)
        y = lu.solve(np.ascontiguousarray(b[p]), trans=trans)
        out = np.empty_like(y)
        out[p] = y
        return out

    return solve


_MKL_CBWR_BRANCH, _MKL_CBWR_COMPATIBLE, _MKL_CBWR_SUCCESS = 1, 3, 0  # mkl_cbwr.h


def mkl_reproducible(lib: ctypes.CDLL) -> int:
    """Put the MKL library ``lib`` (pypardiso's ``mkl_rt``) in conditional numerical reproducibility, branch
    COMPATIBLE, unless the user's ``MKL_CBWR`` chose a mode: without it two pardiso factorizations of one
    matrix on several threads differ in the last bits (2 of 8 repeated solves at 2 threads).

    Set through MKL's service function on that library, never through the ``MKL_CBWR`` environment variable:
    every child process would inherit the variable, and torch's own MKL reads it too (its dgemm rounds
    differently under it), so a batch's Ray workers, started after a pardiso solve, draped other bits than the
    process that started them.

    Returns:
        MKL's branch now (3: COMPATIBLE). Warns when MKL ran before in this process and can no longer change.
    """
    get, put = lib.MKL_CBWR_Get, lib.MKL_CBWR_Set
    get.restype = put.restype = ctypes.c_int
    get.argtypes = put.argtypes = [ctypes.c_int]
    branch = get(_MKL_CBWR_BRANCH)
    if os.environ.get("MKL_CBWR") or branch == _MKL_CBWR_COMPATIBLE:
        return branch
    status = put(_MKL_CBWR_COMPATIBLE)
    if status != _MKL_CBWR_SUCCESS:
        warnings.warn(f"MKL's reproducible mode could not be set (MKL_CBWR_Set returned {status}: MKL ran "
                      "before in this process), so pardiso solves on several threads may differ in the last "
                      "bits between runs; start Python with MKL_CBWR=COMPATIBLE", RuntimeWarning,
                      stacklevel=3)
    return get(_MKL_CBWR_BRANCH)


def _pardiso(a: scipy.sparse.spmatrix, symmetric: bool, ordering: np.ndarray | None) -> Solve:
    del ordering  # pardiso orders by itself (METIS inside MKL)
    pypardiso = _import_backend("pypardiso", SparseBackend.PARDISO)
    solver = pypardiso.PyPardisoSolver(mtype=-2 if symmetric else 11)
    mkl_reproducible(solver.libmkl)  # before the solver's first MKL call
    # the symmetric types read the upper triangle only (CSR, sorted)
    m = scipy.sparse.triu(a, format="csr") if symmetric else a.tocsr()
    m.sort_indices()
    try:
        solver.factorize(m)
    except (pypardiso.pardiso_wrapper.PyPardisoError, ValueError) as exc:
        raise RuntimeError(str(exc)) from exc

    def solve(b: np.ndarray, transpose: bool) -> np.ndarray:
        if transpose and not symmetric:
            raise InputError("the pardiso backend has no transposed solve of a nonsymmetric matrix; "
                             "use superlu")
        return solver.solve(m, b)

    return solve


def _cholespy(a: scipy.sparse.spmatrix, symmetric: bool, ordering: np.ndarray | None) -> Solve:
    del ordering  # cholespy orders by itself (CHOLMOD's AMD)
    cholespy = _import_backend("cholespy", SparseBackend.CHOLESPY)
    if not symmetric:
        raise InputError("the cholespy backend factorizes symmetric positive definite matrices only")
    c = a.tocsc()
    c.sort_indices()
    n = c.shape[0]
    try:
        chol = cholespy.CholeskySolverD(n, torch.from_numpy(c.indptr.astype(np.int32)),
                                        torch.from_numpy(c.indices.astype(np.int32)),
                                        torch.from_numpy(c.data.astype(np.float64)), cholespy.MatrixType.CSC)
    except ValueError as exc:
        raise RuntimeError(str(exc)) from exc

    def solve(b: np.ndarray, transpose: bool) -> np.ndarray:  # A is symmetric: A^-T = A^-1
        rhs = torch.from_numpy(np.ascontiguousarray(b.reshape(n, -1)))
        out = torch.zeros_like(rhs)
        chol.solve(rhs, out)
        return out.numpy().reshape(b.shape)

    return solve


_CHOLMOD_ANALYSES = _Kept(2)
_CHOLMOD_INPUTS = _Kept(2)


def _release_analysis(key: tuple, factor: object) -> None:
    """Keep the CHOLMOD factor of a factorization that nobody uses any more, for the next factorization of
    the same sparsity pattern (its analysis is what it saves); at most 2 are kept."""
    _CHOLMOD_ANALYSES.put(key, factor)


def _cholmod_input(cvxopt: ModuleType, pattern: scipy.sparse.csr_matrix,
                   key: tuple) -> tuple[object, np.ndarray]:
    """``(m, gather)``: a cvxopt sparse matrix of the lower triangle of ``pattern`` (CSR, sorted indices)
    whose :func:`_pattern_key` is ``key``, and the positions in ``pattern.data`` of its values in ``m``'s
    column-major order. The caller owns ``m`` until it puts it back into :data:`_CHOLMOD_INPUTS`; a
    matrix of the same pattern then needs only ``m.V = pattern.data[gather]``, not cvxopt's triplet sort (29
    of a factorization's 190 ms at 10K vertices)."""
    hit = _CHOLMOD_INPUTS.pop(key)
    if hit is not None:
        return hit
    n = int(pattern.shape[0])
    rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(pattern.indptr))
    cols = pattern.indices.astype(np.int64)
    low = np.flatnonzero(rows >= cols)  # CHOLMOD reads one triangle of a symmetric matrix
    # column-major, as cvxopt stores it: scipy's counting sort to CSC keeps the row order within a column
    # (positions + 1 as the values, so that none is a zero)
    csc = scipy.sparse.coo_matrix((low + 1, (rows[low], cols[low])), shape=(n, n)).tocsc()
    gather = csc.data - 1
    m = cvxopt.spmatrix(cvxopt.matrix(pattern.data[gather]), cvxopt.matrix(csc.indices.astype(np.int64)),
                        cvxopt.matrix(np.repeat(np.arange(n, dtype=np.int64), np.diff(csc.indptr))), (n, n))
    return m, gather


def _cholmod(a: scipy.sparse.spmatrix, symmetric: bool, ordering: np.ndarray | None) -> Solve:
    _import_backend("cvxopt", SparseBackend.CHOLMOD)
    cvxopt = importlib.import_module("cvxopt")
    cholmod = importlib.import_module("cvxopt.cholmod")
    if not symmetric:
        raise InputError("the cholmod backend factorizes symmetric positive definite matrices only; use "
                         "superlu")
    n = a.shape[0]
    pattern = _sorted_csr(a)
    key = _pattern_key(pattern)
    m, gather = entry = _cholmod_input(cvxopt, pattern, key)
    m.V = cvxopt.matrix(np.ascontiguousarray(pattern.data[gather], dtype=np.float64))
    # the analysis (symbolic factorization, in the nested-dissection order of the SuperLU path: 1.4x faster
    # than CHOLMOD's own AMD order at 30K vertices) depends on the sparsity pattern and the ordering only.
    # numeric() overwrites its factor in place, so a factor is reused only once the factorization that held it
    # is gone (then the result is the same to the bit as a fresh analysis; about a fifth of a factorization at
    # 30K vertices)
    akey = key if ordering is None else key + (_digest(ordering),)
    factor = _CHOLMOD_ANALYSES.pop(akey)
    try:
        if factor is None:
            order = _nested_dissection(pattern, key) if ordering is None else ordering
            factor = cholmod.symbolic(m, p=cvxopt.matrix(order.tolist(), tc="i"))
        cholmod.numeric(m, factor)
    except ArithmeticError as exc:  # "not positive definite"
        raise RuntimeError(f"not positive definite ({exc})") from exc
    finally:
        _CHOLMOD_INPUTS.put(key, entry)

    def solve(b: np.ndarray, transpose: bool) -> np.ndarray:  # A is symmetric: A^-T = A^-1
        out = cvxopt.matrix(np.ascontiguousarray(b.reshape(n, -1), dtype=np.float64))
        cholmod.solve(factor, out)
        return np.asarray(out).reshape(b.shape)

    weakref.finalize(solve, _release_analysis, akey, factor).atexit = False  # nothing to keep at exit
    return solve


def _import_backend(module: str, backend: SparseBackend) -> ModuleType:
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise InputError(f"the sparse backend {backend.value!r} needs the package {module!r} "
                         f"(pip install {module}); or use backend='superlu'") from exc


_BACKENDS = {SparseBackend.SUPERLU: _superlu, SparseBackend.PARDISO: _pardiso,
             SparseBackend.CHOLESPY: _cholespy, SparseBackend.CHOLMOD: _cholmod}


def _checked_ordering(ordering: np.ndarray, n: int) -> np.ndarray:
    """``ordering`` as int64 after checking that it is a permutation of ``0 .. n-1`` (InputError if not)."""
    p = np.asarray(ordering)
    ok = p.shape == (n,) and p.dtype.kind in "iu"
    if ok and n > 0:
        ok = 0 <= int(p.min()) and int(p.max()) < n and int(np.bincount(p, minlength=n).max()) == 1
    if not ok:
        raise InputError(f"factorize: ordering must be a permutation of 0..{n - 1} (integers, shape ({n},)), "
                         f"got shape {p.shape} and dtype {p.dtype}")
    return p.astype(np.int64, copy=False)


def factorize(matrix: scipy.sparse.spmatrix, *, backend: "str | SparseBackend" = SparseBackend.SUPERLU,
              symmetric: bool = True, shift: float = 0.0, what: str = "matrix",
              ordering: np.ndarray | None = None) -> Factorization:
    """Factorize the sparse square matrix ``matrix + shift I`` (n, n).

    Args:
        matrix: scipy sparse (n, n), converted to float64.
        backend: a :class:`SparseBackend` or its name.
        symmetric: ``matrix`` is symmetric: SuperLU's symmetric mode in the nested-dissection order of
            :func:`fill_reducing_permutation`, no pivoting (see the module docstring); False: scipy's general
            ``splu(A)`` (COLAMD, pivoting).
        shift: diagonal shift ``s`` added as ``A + s I`` (in ``A``'s units) when nonzero.
        what: the matrix's name in error messages (e.g. ``"simulation Hessian"``).
        ordering: (n,) int64 fill-reducing permutation of a symmetric factorization by SuperLU or CHOLMOD,
            in place of METIS' nested dissection of this matrix's pattern (:func:`fill_reducing_permutation`).
            For a sequence of matrices whose patterns differ by a few entries (a fixed mesh plus contacts
            that come and go), the ordering of the fixed part serves them all and is computed once; CHOLMOD's
            analysis is then kept per pattern and ordering. pardiso and cholespy order by themselves and
            ignore it.

    Returns:
        A :class:`Factorization`; its ``shift`` records ``shift``.

    Raises:
        SingularMatrixError: the factorization failed (an exactly singular pivot).
        InputError: an unknown or missing backend, a non-square matrix, or an ``ordering`` that is not a
            permutation of ``0 .. n-1``.
    """
    kind = SparseBackend.resolve(backend)
    if matrix.shape[0] != matrix.shape[1]:
        raise InputError(f"factorize needs a square matrix, got shape {matrix.shape}")
    n = int(matrix.shape[0])
    if ordering is not None:
        ordering = _checked_ordering(ordering, n)
    a = matrix if matrix.dtype == np.float64 else matrix.astype(np.float64)
    if shift != 0.0:
        # in CSR, the assembler's format and the backends' input (SuperLU permutes rows first, CHOLMOD reads
        # sorted CSR): no round trip through CSC
        a = a.tocsr() + float(shift) * scipy.sparse.identity(n, format="csr", dtype=np.float64)
    t0 = time.perf_counter()
    try:
        solve = _BACKENDS[kind](a, symmetric, ordering)
    except RuntimeError as exc:  # SuperLU: "Factor is exactly singular"; a Cholesky: not positive definite
        _record(1, 0, time.perf_counter() - t0)
        kind_of = ("singular" if kind in (SparseBackend.SUPERLU, SparseBackend.PARDISO)
                   else "singular or not positive definite")
        raise SingularMatrixError(f"the {what} is {kind_of}: its sparse factorization failed "
                                  f"({exc})") from exc
    _record(1, 0, time.perf_counter() - t0)
    return Factorization(solve, (n, n), kind, shift, what, a)


class FactorizationCache:
    """One factorization kept while its key (e.g. the state the matrix was assembled at) does not change.

    Args:
        backend: the :class:`SparseBackend` of the factorizations. symmetric: see :func:`factorize`.
        what: the matrix's name in error messages.

    Attributes:
        factorizations: how many times :meth:`factorize` built and factorized a matrix.
    """

    def __init__(self, backend: "str | SparseBackend" = SparseBackend.SUPERLU, *, symmetric: bool = True,
                 what: str = "matrix") -> None:
        self.backend = SparseBackend.resolve(backend)
        self.symmetric = bool(symmetric)
        self.what = what
        self.factorizations = 0
        self._key: torch.Tensor | None = None
        self._factorization: Factorization | None = None

    def factorize(self, key: torch.Tensor, build: Callable[[], scipy.sparse.spmatrix]) -> Factorization:
        """The factorization of ``build()``, refactorized only when ``key`` differs (``torch.equal``) from the
        key of the cached one.

        Raises:
            SingularMatrixError: the new matrix is singular (the cache then holds nothing).
        """
        if (self._factorization is not None and self._key is not None and self._key.shape == key.shape
                and bool(torch.equal(self._key, key))):
            return self._factorization
        self._factorization, self._key = None, None
        matrix = build()
        self.factorizations += 1
        fact = factorize(matrix, backend=self.backend, symmetric=self.symmetric, what=self.what)
        self._factorization, self._key = fact, key.detach().clone()
        return fact

    def clear(self) -> None:
        """Forget the cached factorization (the counter stays)."""
        self._factorization, self._key = None, None


class FactorCache:
    """The last factorization of a sequence of nearby systems (Newton iterations), reused as the
    preconditioner of :func:`~torchgarment.linalg.pcg` on the next ones (inexact Newton): a fresh
    factorization is needed only when PCG does not reach its tolerance within its budget (or, with
    ``accept_rtol``, on the system after one where it did not).

    Attributes:
        factorization: the stored :class:`Factorization` (or anything with ``solve(b)`` and ``shape``), or
            None.
        shift: the diagonal shift it was made with.
        factorizations, pcg_solves: counters.
    """

    def __init__(self) -> None:
        self.factorization: Factorization | None = None
        self.shift = 0.0
        self.factorizations = 0
        self.pcg_solves = 0

    def store(self, factorization: Factorization, shift: float = 0.0) -> None:
        """Keep ``factorization`` (of ``H + shift I``) for the next systems."""
        self.factorization, self.shift = factorization, float(shift)
        self.factorizations += 1

    def solve(self, h: scipy.sparse.spmatrix, rhs: np.ndarray, rtol: float, maxiter: int,
              accept_rtol: float | None = None) -> np.ndarray | None:
        """``y`` (n,) with ``(H + shift I) y ~ rhs`` to relative residual ``rtol`` by PCG preconditioned with
        the stored factorization; None when there is none of this size or PCG does not get there within
        ``maxiter`` iterations (or meets non-positive curvature).

        ``accept_rtol`` (>= ``rtol``; None: ``rtol``): an iterate at which PCG stopped short of ``rtol`` (its
        budget spent, or non-positive curvature met) is still returned when its relative residual is at most
        this (an inexact Newton step with forcing term ``accept_rtol``), so the work already spent on a step
        that is good enough is not thrown away. The factorization is then dropped: it has become a weak
        preconditioner, and the next system would spend about a factorization's time in CG for a worse
        step, so it factorizes afresh instead."""
        n = h.shape[0]
        fact = self.factorization
        if fact is None or tuple(fact.shape) != (n, n):
            return None
        a = h + self.shift * scipy.sparse.identity(n, format="csr") if self.shift > 0 else h
        b = np.asarray(rhs, dtype=np.float64)
        # maxiter - 1 updates: scipy's cg (which this replaced) tests convergence before each of its maxiter
        # updates, so its last update is never accepted; the same budget keeps every Newton iterate unchanged
        try:
            out, _, res = pcg(lambda v: a @ v, b, fact.solve, rtol, maxiter - 1,
                              stop_at_negative_curvature=True)
        except SingularMatrixError:
            return None
        limit = rtol if accept_rtol is None else max(rtol, accept_rtol)
        if not res <= limit or not np.all(np.isfinite(out)):
            return None
        if not res <= rtol:  # taken within accept_rtol: the next system gets a fresh factorization
            self.factorization = None
        self.pcg_solves += 1
        return out


def csr_matvec(h: scipy.sparse.spmatrix, device: torch.device) -> Callable[[torch.Tensor], torch.Tensor]:
    """``v -> h v`` for flat float64 tensors ``v`` (n,) on ``device``: scipy's CSR product on the CPU (several
    times faster there than torch's sparse CSR), a torch sparse CSR copy of ``h`` on other devices.

    Args:
        h: (n, n) scipy sparse matrix (converted to float64 CSR once).
        device: where the products run.
    """
    hc = scipy.sparse.csr_matrix(h, dtype=np.float64)
    if device.type == "cpu":
        return lambda v: torch.from_numpy(hc @ v.numpy())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "sparse CSR support is in beta"
        mat = torch.sparse_csr_tensor(torch.from_numpy(hc.indptr.astype(np.int64)),
                                      torch.from_numpy(hc.indices.astype(np.int64)),
                                      torch.from_numpy(np.ascontiguousarray(hc.data)),
                                      size=hc.shape).to(device)
    return lambda v: (mat @ v.unsqueeze(1)).squeeze(1)


def compact_csr(matrix: torch.Tensor) -> torch.Tensor:
    """The torch sparse CSR ``matrix`` with 32-bit row pointers and column indices when they fit (else as
    it is), for constant matrices multiplied many times (a simulator's incidence and bending matrices).

    torch's CPU products convert 64-bit CSR indices to 32 bits (MKL's) on every call: at 30K vertices that
    copy took 50-140 us of a 0.25-0.7 ms product (``README.md``, "The parts of an iteration"). The products'
    results are the same to the bit. Not for matrices that autograd differentiates through.
    """
    if matrix.layout != torch.sparse_csr:
        raise InputError(f"compact_csr needs a sparse CSR tensor, got layout {matrix.layout}")
    crow, col = matrix.crow_indices(), matrix.col_indices()
    if crow.dtype == torch.int32 or max(matrix.shape[0], matrix.shape[1], col.numel()) >= 2 ** 31 - 1:
        return matrix
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "sparse CSR support is in beta"
        return torch.sparse_csr_tensor(crow.to(torch.int32), col.to(torch.int32), matrix.values(),
                                       size=matrix.shape, check_invariants=False)


class BlockMatrix(Protocol):
    """A block-sparse matrix in COO form over vertices (e.g.
    :class:`~torchgarment.sim.energies.base.HessianBlocks`).

    ``rows, cols``: (K,) long block indices; ``values``: (K, 3, 3) blocks, duplicates summed.
    """

    rows: torch.Tensor
    cols: torch.Tensor
    values: torch.Tensor


_PATTERNS = _Kept(4)


def _block_pattern(n: int, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(slot, indices, indptr)`` of 3x3 blocks at block ``rows``, ``cols`` (K,) int64 in an (n, n) CSR
    matrix: ``indptr`` (n + 1,) and ``indices`` (nnz,) the CSR pattern (sorted, duplicates merged), ``slot``
    (9K,) the data position of every block entry in (K, 3, 3) order. All three are read-only.

    Sorts the K block keys only: the entries of a block row ``r`` with ``m`` distinct blocks fill the scalar
    rows ``3r + a`` in the same block order, 3 columns per block, so each entry's position follows from its
    block's rank."""
    nv = n // 3
    ub, inv = np.unique(rows * nv + cols, return_inverse=True)
    br, bc = ub // nv, ub % nv
    cnt = np.bincount(br, minlength=nv)  # distinct blocks per block row
    start = np.zeros(nv + 1, dtype=np.int64)
    np.cumsum(cnt, out=start[1:])
    ar = np.arange(3, dtype=np.int64)
    itype = np.int32 if n < 2**31 else np.int64
    indptr = np.empty(n + 1, dtype=itype)
    indptr[:-1] = (9 * start[:-1, None] + 3 * cnt[:, None] * ar[None, :]).reshape(-1)
    indptr[-1] = 9 * ub.shape[0]
    rank = np.arange(ub.shape[0], dtype=np.int64) - start[br]  # a block's place in its block row
    pos = ((9 * start[br] + 3 * rank)[:, None, None] + (3 * cnt[br])[:, None, None] * ar[None, :, None]
           + ar[None, None, :])  # (U, 3, 3): block entry (a, b) -> data position
    indices = np.empty(9 * ub.shape[0], dtype=itype)
    col = 3 * bc[:, None, None] + ar[None, None, :]  # (U, 1, 3): the columns of a block's entries
    indices[pos.reshape(-1)] = np.broadcast_to(col, pos.shape).reshape(-1)
    slot = pos.reshape(-1, 9)[inv.reshape(-1)].reshape(-1)
    for a in (slot, indices, indptr):
        a.setflags(write=False)
    return slot, indices, indptr


class CSRAssembler:
    """Assembles 3x3 blocks (a :class:`BlockMatrix`) into a scipy CSR matrix (3V, 3V), float64, on the CPU.

    The COO -> CSR permutation is computed once per sparsity pattern and reused while the block rows and
    columns stay the same (they do for the elastic terms; contact terms may change them), so assembly is one
    ``np.bincount`` per iteration. The last few patterns are also kept across assemblers, keyed by a hash of
    the block rows and columns: the solves of an adjustment's outer iterations, each with its own
    assemblers, then sort the garment's pattern once.
    """

    def __init__(self, num_vertices: int) -> None:
        self.n = 3 * int(num_vertices)
        self._rows: torch.Tensor | None = None
        self._cols: torch.Tensor | None = None
        self._slot: np.ndarray | None = None
        self._indptr: np.ndarray | None = None
        self._indices: np.ndarray | None = None

    def _build_pattern(self, rows: torch.Tensor, cols: torch.Tensor) -> None:
        r = np.ascontiguousarray(rows.detach().cpu().numpy(), dtype=np.int64)
        c = np.ascontiguousarray(cols.detach().cpu().numpy(), dtype=np.int64)
        key = (self.n, r.shape[0], _digest(r, c))
        hit = _PATTERNS.get(key)
        if hit is None:
            hit = _block_pattern(self.n, r, c)
            _PATTERNS.put(key, hit)
        self._slot, self._indices, self._indptr = hit
        self._rows, self._cols = rows.detach().clone(), cols.detach().clone()

    def assemble(self, blocks: BlockMatrix) -> scipy.sparse.csr_matrix:
        """The summed matrix (3V, 3V) of ``blocks`` (``rows``, ``cols`` (K,), ``values`` (K, 3, 3)) as CSR."""
        same = (
            self._rows is not None
            and self._rows.shape == blocks.rows.shape
            and bool(torch.equal(self._rows, blocks.rows.to(self._rows.device)))
            and bool(torch.equal(self._cols, blocks.cols.to(self._cols.device)))
        )
        if not same:
            self._build_pattern(blocks.rows, blocks.cols)
        vals = blocks.values.detach().to(device="cpu", dtype=torch.float64).numpy().reshape(-1)
        data = np.bincount(self._slot, weights=vals, minlength=self._indices.shape[0])
        return scipy.sparse.csr_matrix((data, self._indices, self._indptr), shape=(self.n, self.n))
