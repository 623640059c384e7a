"""Tests of the finite-difference helpers in torchgarment.testing."""

from __future__ import annotations

import pytest
import torch

from torchgarment.sim.energies.base import HessianBlocks
from torchgarment.testing import check_gradient, check_hessian_blocks, fd_gradient, min_eigenvalue


def _f(x: torch.Tensor) -> torch.Tensor:
    return (torch.sin(x) * x * x).sum() + (x[:, 0] * x[:, 1]).sum()


def _grad_f(x: torch.Tensor) -> torch.Tensor:
    g = torch.cos(x) * x * x + 2 * x * torch.sin(x)
    g[:, 0] += x[:, 1]
    g[:, 1] += x[:, 0]
    return g


class _Quadratic(torch.nn.Module):
    """E = 1/2 sum_{(i,j)} |x_i - x_j|^2 + 1/2 sum_i c_i |x_i|^2 (Hessian known in closed form)."""

    def __init__(self, wrong: float = 1.0) -> None:
        super().__init__()
        self.pairs = torch.tensor([[0, 1], [1, 2], [2, 3], [0, 3]])
        self.c = torch.tensor([1.0, 2.0, 3.0, 4.0], dtype=torch.float64)
        self.wrong = wrong

    def value_and_grad(self, x):
        i, j = self.pairs.T
        d = x[i] - x[j]
        g = torch.zeros_like(x).index_add_(0, i, d).index_add_(0, j, -d) + self.c[:, None] * x
        return 0.5 * (d * d).sum() + 0.5 * (self.c[:, None] * x * x).sum(), g

    def _diag(self):
        deg = torch.zeros(4, dtype=torch.float64).index_add_(0, self.pairs.reshape(-1),
                                                             torch.ones(8, dtype=torch.float64))
        return (self.wrong * (deg + self.c))[:, None, None] * torch.eye(3, dtype=torch.float64)

    def hessian_diagonal(self, x, project_psd=True):
        return self._diag()

    def hessian_blocks(self, x, project_psd=True):
        i, j = self.pairs.T
        eye = torch.eye(3, dtype=torch.float64).expand(4, 3, 3)
        ar = torch.arange(4)
        return HessianBlocks(torch.cat([ar, i, j]), torch.cat([ar, j, i]),
                             torch.cat([self._diag(), -eye, -eye]))


def test_fd_gradient_of_polynomial_is_accurate():
    x = torch.randn(5, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    fd = fd_gradient(_f, x)
    assert fd.shape == x.shape
    assert torch.allclose(fd, _grad_f(x), rtol=1e-8, atol=1e-9)


def test_check_gradient_accepts_right_and_rejects_wrong():
    x = torch.randn(6, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    res = check_gradient(_f, x, _grad_f(x))
    assert res.ok and res.rel_error < 1e-8
    res_auto = check_gradient(_f, x)  # autograd gradient
    assert res_auto.ok
    bad = _grad_f(x)
    bad[2, 1] += 1e-3
    with pytest.raises(AssertionError, match="gradient"):
        check_gradient(_f, x, bad)
    res_bad = check_gradient(_f, x, bad, raise_on_failure=False)
    assert not res_bad.ok and res_bad.max_abs_error == pytest.approx(1e-3, rel=1e-3)
    sampled = check_gradient(_f, x, _grad_f(x), num_samples=5)
    assert sampled.ok


def test_check_hessian_blocks_accepts_right_and_rejects_wrong():
    x = torch.randn(4, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    blocks, diag = check_hessian_blocks(_Quadratic(), x)
    assert blocks.ok and diag.ok and blocks.rel_error < 1e-8
    with pytest.raises(AssertionError, match="hessian"):
        check_hessian_blocks(_Quadratic(wrong=1.01), x)


def test_min_eigenvalue_of_known_matrix():
    q = _Quadratic()
    lam = min_eigenvalue(q.hessian_blocks(None), 4)
    H = q.hessian_blocks(None).to_sparse(4).to_dense()
    assert lam == pytest.approx(float(torch.linalg.eigvalsh(H)[0]))
    assert lam > 0.5  # Laplacian (PSD) + diag(c) with c >= 1
