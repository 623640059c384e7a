"""Krylov solvers on torch tensors or numpy arrays (each algorithm once, both array types): preconditioned
conjugate gradients (:func:`pcg`, symmetric positive definite systems) and preconditioned MINRES
(:func:`minres`, symmetric indefinite systems)."""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from torchgarment.errors import NonConvergenceError

Array = torch.Tensor | np.ndarray
#: ``v -> K v``, same shape and type as ``v``.
MatVec = Callable[[Array], Array]
#: ``r -> M^-1 r``, same shape and type as ``r``.
Preconditioner = Callable[[Array], Array]


def _start(b: Array, preconditioner: Preconditioner | None,
           x0: Array | None) -> tuple["_TorchOps | _NumpyOps", Preconditioner, Array, float]:
    """What both Krylov solvers start with: the array operations of ``b``'s type, ``r -> M^-1 r`` (the
    identity without a preconditioner), the start iterate and ``|b|``."""
    ops = _NUMPY if isinstance(b, np.ndarray) else _TORCH

    def apply(r: Array) -> Array:
        return ops.copy(r) if preconditioner is None else preconditioner(r)

    return ops, apply, ops.zeros_like(b) if x0 is None else ops.start(x0, b), ops.norm(b)


def pcg(
    matvec: MatVec, b: Array, preconditioner: Preconditioner | None, rtol: float, max_iterations: int,
    *, x0: Array | None = None, stop_at_negative_curvature: bool = False,
) -> tuple[Array, int, float]:
    """Preconditioned conjugate gradients for ``K y = b`` with ``K`` symmetric positive definite.

    The same recurrences run on torch tensors (any device; inner products ``sum(u * v)``, fused axpy) or on
    float64 numpy arrays (BLAS ``dot`` and the ``x += a p`` updates of ``scipy.sparse.linalg.cg``, so a
    numpy solve reproduces scipy's iterates bit for bit).

    Args:
        matvec: ``v -> K v`` for ``v`` of ``b``'s shape and type.
        b: the right-hand side, any shape (e.g. (V, 3) or (n,)); the inner products run over all entries.
        preconditioner: ``r -> M^-1 r`` (e.g. block Jacobi, or a sparse factorization of a nearby matrix);
            None: no preconditioning.
        rtol: stop when ``|r| <= rtol |b|`` (the recursively updated residual).
        max_iterations: iteration budget.
        x0: warm start of ``b``'s shape and type (default zero).
        stop_at_negative_curvature: return the iterate reached so far at a direction with ``p^T K p <= 0``
            instead of raising (Steihaug's rule; for inexact solves that accept an approximate answer).

    Returns:
        ``(y, iterations, |r| / |b|)`` with ``y`` of ``b``'s type; the caller checks convergence.

    Raises:
        NonConvergenceError: non-positive curvature ``p^T K p <= 0`` (``K`` is not positive definite), unless
            ``stop_at_negative_curvature``.
    """
    ops, apply, y, bn = _start(b, preconditioner, x0)
    if bn == 0.0:
        return ops.zeros_like(b), 0, 0.0
    r = b - matvec(y) if x0 is not None and bool(y.any()) else ops.copy(b)
    z = apply(r)
    p = ops.copy(z)
    rz = ops.dot(r, z)
    rn = ops.norm(r)
    k = 0
    while k < max_iterations and rn > rtol * bn:
        kp = matvec(p)
        pkp = ops.dot(p, kp)
        if not pkp > 0.0:
            if stop_at_negative_curvature:
                break
            raise NonConvergenceError(
                f"CG met non-positive curvature p^T K p = {pkp:.3g} at iteration {k + 1}: the matrix is not "
                f"positive definite (a saddle or an unconverged state); use a sparse direct solve")
        k += 1
        a = rz / pkp
        ops.axpy_(y, a, p)
        ops.axpy_(r, -a, kp)
        rn = ops.norm(r)
        z = apply(r)
        rz_new = ops.dot(r, z)
        ops.scale_add_(p, rz_new / rz, z)
        rz = rz_new
    return y, k, rn / bn


def minres(
    matvec: MatVec, b: Array, preconditioner: Preconditioner | None, rtol: float, max_iterations: int,
    *, x0: Array | None = None,
) -> tuple[Array, int, float]:
    """Preconditioned MINRES (Paige and Saunders 1975) for ``K y = b`` with ``K`` symmetric, possibly
    indefinite (a saddle or an unconverged state, where :func:`pcg` meets non-positive curvature).

    Each iterate minimizes the residual's ``M^-1``-norm over the Krylov space, so the residual never grows and
    an iterate stopped by the budget is a usable approximation; the recurrences are those of
    ``scipy.sparse.linalg.minres``. The recurrences track the preconditioned residual, which can reach its
    target while the true one is still above it (with a block-Jacobi preconditioner of a stiff garment: 2.5x
    above, on the skirt's adjoint); so where they stop on their estimate, the true residual is computed and,
    while it is larger than ``rtol |b|``, MINRES restarts from its iterate with the estimate's target lowered
    by the missing factor (each check costs one product more).

    Args:
        matvec: ``v -> K v`` for ``v`` of ``b``'s shape and type.
        b: the right-hand side, any shape.
        preconditioner: ``r -> M^-1 r`` with ``M`` symmetric positive definite (e.g. block Jacobi with
            non-definite blocks replaced by their clamped diagonal); None: no preconditioning.
        rtol: stop when the true residual ``|K y - b|`` falls to ``rtol |b|``.
        max_iterations: iteration budget (over the restarts).
        x0: warm start of ``b``'s shape and type (default zero).

    Returns:
        ``(y, iterations, |K y - b| / |b|)``: the true relative residual.

    Raises:
        NonConvergenceError: the preconditioner is not positive definite (``r^T M^-1 r < 0``).
    """
    ops, apply, x, bn = _start(b, preconditioner, x0)
    if bn == 0.0:
        return ops.zeros_like(b), 0, 0.0
    r = ops.copy(b)
    if x0 is not None:
        ops.axpy_(r, -1.0, matvec(x))
    rn, k, goal = ops.norm(r), 0, rtol * bn
    while rn > goal and k < max_iterations:
        z = apply(r)
        beta1 = ops.dot(r, z)
        if beta1 < 0.0:
            raise NonConvergenceError("MINRES needs a positive definite preconditioner")
        if beta1 == 0.0:
            break
        beta1 = beta1 ** 0.5
        # the target of the preconditioned estimate: scipy's rtol |b|_{M^-1} from zero; else the estimate
        # lowered by the factor that the true residual misses
        target = rtol * beta1 if (k == 0 and x0 is None) else beta1 * goal / rn
        steps = _minres_run(matvec, apply, ops, x, r, z, beta1, target, max_iterations - k)
        k += steps
        r = ops.copy(b)
        ops.axpy_(r, -1.0, matvec(x))
        rn, last = ops.norm(r), rn
        if not rn < last:  # no progress (round-off at the attainable accuracy): stop
            break
    return x, k, rn / bn


def _minres_run(matvec: MatVec, apply: Preconditioner, ops: "_TorchOps | _NumpyOps", x: Array, r1: Array,
                y: Array, beta1: float, target: float, budget: int) -> int:
    """One MINRES run from ``x`` (updated in place) with residual ``r1 = b - K x`` (read only) and ``y = M^-1
    r1``, ``beta1 = |r1|_{M^-1} > 0``, until the estimated preconditioned residual reaches ``target`` or
    ``budget`` iterations; returns the iterations taken."""
    k = 0
    r2 = ops.copy(r1)
    old_b, beta, dbar, epsln, phibar = 0.0, beta1, 0.0, 0.0, beta1
    cs, sn = -1.0, 0.0
    w, w2 = ops.zeros_like(x), ops.zeros_like(x)
    tiny = float(np.finfo(np.float64).eps)
    while k < budget and phibar > target:
        k += 1
        v = ops.copy(y)
        ops.scale_(v, 1.0 / beta)
        y = matvec(v)
        if k >= 2:
            ops.axpy_(y, -beta / old_b, r1)
        alfa = ops.dot(v, y)
        ops.axpy_(y, -alfa / beta, r2)
        r1, r2 = r2, y
        y = apply(r2)
        old_b, beta = beta, ops.dot(r2, y)
        if beta < 0.0:
            raise NonConvergenceError("MINRES needs a positive definite preconditioner")
        beta = beta ** 0.5
        old_eps = epsln
        delta = cs * dbar + sn * alfa
        gbar = sn * dbar - cs * alfa
        epsln = sn * beta
        dbar = -cs * beta
        gamma = max(float(np.hypot(gbar, beta)), tiny)
        cs, sn = gbar / gamma, beta / gamma
        phi = cs * phibar
        phibar = sn * phibar
        w1, w2 = w2, w
        w = ops.copy(v)
        ops.axpy_(w, -old_eps, w1)
        ops.axpy_(w, -delta, w2)
        ops.scale_(w, 1.0 / gamma)
        ops.axpy_(x, phi, w)
    return k


class _TorchOps:
    """Array operations of :func:`pcg` on torch tensors."""

    @staticmethod
    def zeros_like(b: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(b)

    @staticmethod
    def start(x0: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return x0.detach().to(b.dtype).clone()

    @staticmethod
    def copy(v: torch.Tensor) -> torch.Tensor:
        return v.clone()

    @staticmethod
    def norm(v: torch.Tensor) -> float:
        return float(torch.linalg.vector_norm(v))

    @staticmethod
    def dot(u: torch.Tensor, v: torch.Tensor) -> float:
        return float(torch.sum(u * v))

    @staticmethod
    def axpy_(y: torch.Tensor, a: float, x: torch.Tensor) -> None:
        y.add_(x, alpha=a)

    @staticmethod
    def scale_add_(p: torch.Tensor, beta: float, z: torch.Tensor) -> None:
        p.mul_(beta).add_(z)

    @staticmethod
    def scale_(v: torch.Tensor, a: float) -> None:
        v.mul_(a)


class _NumpyOps:
    """Array operations of :func:`pcg` on float64 numpy arrays (scipy's ``cg`` arithmetic)."""

    @staticmethod
    def zeros_like(b: np.ndarray) -> np.ndarray:
        return np.zeros_like(b)

    @staticmethod
    def start(x0: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.array(x0, dtype=b.dtype)

    @staticmethod
    def copy(v: np.ndarray) -> np.ndarray:
        return v.copy()

    @staticmethod
    def norm(v: np.ndarray) -> float:
        return float(np.linalg.norm(v))

    @staticmethod
    def dot(u: np.ndarray, v: np.ndarray) -> float:
        return float(np.dot(u.ravel(), v.ravel()))

    @staticmethod
    def axpy_(y: np.ndarray, a: float, x: np.ndarray) -> None:
        y += a * x

    @staticmethod
    def scale_add_(p: np.ndarray, beta: float, z: np.ndarray) -> None:
        p *= beta
        p += z

    @staticmethod
    def scale_(v: np.ndarray, a: float) -> None:
        v *= a


_TORCH, _NUMPY = _TorchOps(), _NumpyOps()
