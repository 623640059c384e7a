"""``A @ x`` for a constant matrix ``A`` whose transpose is stored too, as an autograd function.

The backward pass is ``A^T @ g`` with the stored transpose (a CSR product, no index scatter on the CPU); it is
itself this function, so double backward (Hessian-vector products) works. Used by the sparse cost operators
and by the explicit parametrization map.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from torch.autograd.function import FunctionCtx


class StoredTransposeMatmul(torch.autograd.Function):
    """``A @ x`` for constant ``A`` (R, C) and its stored transpose ``AT`` (C, R), dense or sparse;
    ``x``: (C, d)."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: FunctionCtx, x: torch.Tensor, A: torch.Tensor, AT: torch.Tensor
    ) -> torch.Tensor:
        ctx.A, ctx.AT = A, AT
        return A @ x

    @staticmethod
    def backward(ctx: FunctionCtx, g: torch.Tensor) -> tuple[torch.Tensor, None, None]:  # type: ignore[override]
        # linear, so the backward is itself differentiable (double backward for Hessian-vector products)
        return StoredTransposeMatmul.apply(g.contiguous(), ctx.AT, ctx.A), None, None
