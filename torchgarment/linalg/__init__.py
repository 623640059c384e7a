"""The linear-algebra layer: sparse factorizations, conjugate gradients, Armijo backtracking, CSR assembly.

It depends on torch, numpy, scipy and pymetis only (and on :mod:`torchgarment.errors` and
:mod:`torchgarment.options`); every solver and optimizer of the package builds on it.

* :func:`factorize` -> :class:`Factorization` (``solve(b)``), backends :class:`SparseBackend` (SuperLU by
  default, in the nested-dissection order of :func:`fill_reducing_permutation` for symmetric matrices);
  :class:`FactorizationCache` keeps one factorization per key (a state); :class:`FactorCache` keeps the last
  one as the preconditioner of :func:`pcg` for nearby systems (inexact Newton).
* :func:`pcg`: preconditioned conjugate gradients on torch tensors (or numpy arrays); :func:`minres`:
  preconditioned MINRES for symmetric indefinite systems.
* :func:`armijo_backtracking`: the sufficient-decrease line search.
* :class:`CSRAssembler`: 3x3 vertex blocks -> scipy CSR; :func:`csr_matvec`: its products on a device;
  :func:`compact_csr`: a constant torch CSR with 32-bit indices (faster products).
* :func:`count_linalg`: counts the factorizations and solves (and their seconds) made inside a ``with``
  block (:class:`LinalgCounters`), for benchmarks' per-stage breakdowns.

Example:
    >>> fact = factorize(hessian, what="simulation Hessian")
    >>> dx = fact.solve(-g)
"""

from torchgarment.linalg.iterative import minres, pcg
from torchgarment.linalg.line_search import armijo_backtracking
from torchgarment.linalg.sparse import (
    CSRAssembler,
    FactorCache,
    Factorization,
    FactorizationCache,
    LinalgCounters,
    SparseBackend,
    compact_csr,
    count_linalg,
    csr_matvec,
    factorize,
    fill_reducing_permutation,
)

__all__ = [
    "CSRAssembler",
    "FactorCache",
    "Factorization",
    "FactorizationCache",
    "LinalgCounters",
    "SparseBackend",
    "armijo_backtracking",
    "compact_csr",
    "count_linalg",
    "csr_matvec",
    "factorize",
    "fill_reducing_permutation",
    "minres",
    "pcg",
]
