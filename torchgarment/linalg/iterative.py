"""Preconditioned conjugate gradients on torch tensors."""

from __future__ import annotations

from typing import Callable

import torch

from torchgarment.errors import NonConvergenceError

#: ``v -> K v``, same shape as ``v``.
MatVec = Callable[[torch.Tensor], torch.Tensor]
#: ``r -> M^-1 r``, same shape as ``r``.
Preconditioner = Callable[[torch.Tensor], torch.Tensor]


def pcg(
    matvec: MatVec, b: torch.Tensor, preconditioner: Preconditioner | None, rtol: float, max_iterations: int,
    *, x0: torch.Tensor | None = None, stop_at_negative_curvature: bool = False,
) -> tuple[torch.Tensor, int, float]:
    """Preconditioned conjugate gradients for ``K y = b`` with ``K`` symmetric positive definite.

    Args:
        matvec: ``v -> K v`` for ``v`` of ``b``'s shape.
        b: the right-hand side, any shape (e.g. (V, 3) or (n,)); the inner products run over all entries.
        preconditioner: ``r -> M^-1 r`` (e.g. block Jacobi, or a sparse factorization of a nearby matrix);
            None: no preconditioning.
        rtol: stop when ``|r| <= rtol |b|`` (the recursively updated residual).
        max_iterations: iteration budget.
        x0: warm start of ``b``'s shape (default zero).
        stop_at_negative_curvature: return the iterate reached so far at a direction with ``p^T K p <= 0``
            instead of raising (Steihaug's rule; for inexact solves that accept an approximate answer).

    Returns:
        ``(y, iterations, |r| / |b|)``; the caller checks convergence.

    Raises:
        NonConvergenceError: non-positive curvature ``p^T K p <= 0`` (``K`` is not positive definite), unless
            ``stop_at_negative_curvature``.
    """

    def apply(r: torch.Tensor) -> torch.Tensor:
        return r.clone() if preconditioner is None else preconditioner(r)

    y = torch.zeros_like(b) if x0 is None else x0.detach().to(b.dtype).clone()
    bn = float(torch.linalg.vector_norm(b))
    if bn == 0.0:
        return torch.zeros_like(b), 0, 0.0
    r = b - matvec(y) if x0 is not None and bool(y.any()) else b.clone()
    z = apply(r)
    p = z.clone()
    rz = float(torch.sum(r * z))
    rn = float(torch.linalg.vector_norm(r))
    k = 0
    while k < max_iterations and rn > rtol * bn:
        kp = matvec(p)
        pkp = float(torch.sum(p * kp))
        if not pkp > 0.0:
            if stop_at_negative_curvature:
                break
            raise NonConvergenceError(
                f"CG met non-positive curvature p^T K p = {pkp:.3g} at iteration {k + 1}: the matrix is not "
                f"positive definite (a saddle or an unconverged state); use a sparse direct solve")
        k += 1
        a = rz / pkp
        y.add_(p, alpha=a)
        r.add_(kp, alpha=-a)
        rn = float(torch.linalg.vector_norm(r))
        z = apply(r)
        rz_new = float(torch.sum(r * z))
        p.mul_(rz_new / rz).add_(z)
        rz = rz_new
    return y, k, rn / bn
