"""Finite-difference checks for gradients and Hessians, used by the test suite (and handy for new terms).

All differences are central, ``(f(x + eps e) - f(x - eps e)) / (2 eps)``, evaluated in float64 (inputs are
converted). Errors are norm-wise: ``max |analytic - fd| <= rtol * max |fd| + atol``; each check returns a
:class:`CheckResult` and, by default, raises ``AssertionError`` with the numbers when it fails.

Example::

    from torchgarment.testing import check_gradient, check_hessian_blocks
    check_gradient(lambda x: term(x), x, grad=term.value_and_grad(x)[1])
    check_hessian_blocks(term, x)
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from torchgarment.errors import InputError

if TYPE_CHECKING:
    from torchgarment.sim.energies.base import HessianBlocks


@dataclass
class CheckResult:
    """Outcome of a finite-difference comparison.

    Attributes:
        max_abs_error: ``max |analytic - fd|`` over the compared entries.
        scale: ``max |fd|`` (the reference magnitude).
        rel_error: ``max_abs_error / scale`` (``max_abs_error`` when ``scale`` is 0).
        ok: whether ``max_abs_error <= rtol * scale + atol``.
        what: what was compared.
    """

    max_abs_error: float
    scale: float
    rel_error: float
    ok: bool
    what: str

    def __str__(self) -> str:
        return (f"{self.what}: max abs error {self.max_abs_error:.3e}, scale {self.scale:.3e}, "
                f"relative {self.rel_error:.3e} ({'ok' if self.ok else 'FAILED'})")


def _compare(analytic: torch.Tensor, fd: torch.Tensor, rtol: float, atol: float, what: str,
             raise_on_failure: bool) -> CheckResult:
    if analytic.shape != fd.shape:
        raise InputError(f"{what}: analytic shape {tuple(analytic.shape)} != finite-difference shape "
                         f"{tuple(fd.shape)}")
    err = float((analytic.double() - fd.double()).abs().max()) if fd.numel() else 0.0
    if not (err == err):  # NaN
        err = float("inf")
    scale = float(fd.abs().max()) if fd.numel() else 0.0
    rel = err / scale if scale > 0 else err
    res = CheckResult(err, scale, rel, err <= rtol * scale + atol, what)
    if raise_on_failure and not res.ok:
        raise AssertionError(f"{res} (rtol {rtol:g}, atol {atol:g})")
    return res


def _entries(n: int, num_samples: int | None, seed: int) -> torch.Tensor:
    if num_samples is None or num_samples >= n:
        return torch.arange(n)
    gen = torch.Generator().manual_seed(seed)
    return torch.randperm(n, generator=gen)[:num_samples]


def fd_gradient(
    fn: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor, *, eps: float = 1e-6,
    entries: torch.Tensor | None = None,
) -> torch.Tensor:
    """Central-difference gradient of a scalar function, in float64.

    Args:
        fn: maps a tensor shaped like ``x`` to a scalar tensor.
        x: the point (any shape; converted to float64).
        eps: step.
        entries: flat indices to differentiate (default: all).

    Returns:
        (len(entries),) partial derivatives, or a float64 tensor shaped like ``x`` when ``entries`` is None.
    """
    x0 = x.detach().to(torch.float64)
    flat = x0.reshape(-1)
    idx = torch.arange(flat.numel()) if entries is None else entries
    out = torch.empty(idx.numel(), dtype=torch.float64)
    with torch.no_grad():
        for n, k in enumerate(idx.tolist()):
            xp = flat.clone()
            xp[k] += eps
            xm = flat.clone()
            xm[k] -= eps
            out[n] = (float(fn(xp.view_as(x0))) - float(fn(xm.view_as(x0)))) / (2.0 * eps)
    return out.view_as(x0) if entries is None else out


def check_gradient(
    fn: Callable[[torch.Tensor], torch.Tensor],
    x: torch.Tensor,
    grad: torch.Tensor | None = None,
    *,
    eps: float = 1e-6,
    rtol: float = 1e-6,
    atol: float = 0.0,
    num_samples: int | None = None,
    seed: int = 0,
    raise_on_failure: bool = True,
) -> CheckResult:
    """Compare a gradient with central differences of ``fn``.

    Args:
        fn: scalar function of a tensor shaped like ``x``.
        x: the point (converted to float64).
        grad: the gradient to check, shaped like ``x``; None = autograd of ``fn`` at ``x``.
        eps: finite-difference step. rtol, atol: tolerances (see the module docstring).
        num_samples: compare only this many random entries (None: all).
        seed: seed of the entry sample.
        raise_on_failure: raise AssertionError when the check fails.
    """
    x64 = x.detach().to(torch.float64)
    if grad is None:
        with torch.enable_grad():
            xr = x64.clone().requires_grad_(True)
            (grad,) = torch.autograd.grad(fn(xr), xr)
    if grad.shape != x64.shape:
        raise InputError(f"gradient shape {tuple(grad.shape)} differs from x shape {tuple(x64.shape)}")
    idx = _entries(x64.numel(), num_samples, seed)
    fd = fd_gradient(fn, x64, eps=eps, entries=idx)
    return _compare(grad.detach().reshape(-1)[idx], fd, rtol, atol, "gradient", raise_on_failure)


def fd_hessian_columns(
    grad_fn: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor, columns: torch.Tensor, *,
    eps: float = 1e-6
) -> torch.Tensor:
    """Central differences of a gradient: columns ``columns`` of the Hessian, float64 (N, len(columns))."""
    x0 = x.detach().to(torch.float64)
    flat = x0.reshape(-1)
    out = torch.empty(flat.numel(), columns.numel(), dtype=torch.float64)
    with torch.no_grad():
        for n, k in enumerate(columns.tolist()):
            xp = flat.clone()
            xp[k] += eps
            xm = flat.clone()
            xm[k] -= eps
            gp = grad_fn(xp.view_as(x0)).reshape(-1).double()
            gm = grad_fn(xm.view_as(x0)).reshape(-1).double()
            out[:, n] = (gp - gm) / (2.0 * eps)
    return out


def check_hessian_blocks(
    term: torch.nn.Module,
    x: torch.Tensor,
    *,
    eps: float = 1e-6,
    rtol: float = 1e-6,
    atol: float = 0.0,
    num_columns: int | None = None,
    seed: int = 0,
    raise_on_failure: bool = True,
) -> tuple[CheckResult, CheckResult]:
    """Compare a term's unprojected Hessian with central differences of its analytic gradient.

    Assembles ``term.hessian_blocks(x, project_psd=False)`` (dense, so keep meshes small) and checks the
    sampled columns against differences of ``term.value_and_grad``; then checks the diagonal blocks of
    ``term.hessian_diagonal(x, project_psd=False)`` against the same differences.

    Args:
        term: an EnergyTerm (or SimModel-like object) with ``value_and_grad``, ``hessian_blocks`` and
            ``hessian_diagonal`` accepting ``project_psd``.
        x: (V, 3) positions (converted to float64).
        eps, rtol, atol: see :func:`check_gradient`.
        num_columns: number of random columns of the 3V x 3V Hessian to check (None: all).
        seed: seed of the column sample.
        raise_on_failure: raise AssertionError when a check fails.

    Returns:
        ``(blocks, diagonal)`` check results.
    """
    x64 = x.detach().to(torch.float64)
    V = x64.shape[0]
    cols = _entries(3 * V, num_columns, seed)
    fd = fd_hessian_columns(lambda y: term.value_and_grad(y)[1], x64, cols, eps=eps)
    H = term.hessian_blocks(x64, project_psd=False).to_sparse(V).to_dense()
    r1 = _compare(H[:, cols], fd, rtol, atol, "hessian blocks", raise_on_failure)
    # diagonal blocks: entry (3v + a, 3v + b) for the sampled column 3v + b
    D = term.hessian_diagonal(x64, project_psd=False)
    v, b = cols // 3, cols % 3
    rows = 3 * v[None, :] + torch.arange(3)[:, None]  # (3, C)
    fd_diag = fd[rows, torch.arange(cols.numel())[None, :].expand(3, -1)]
    an_diag = D.double()[v, :, b].T  # (3, C): D[v_c][a, b_c]
    r2 = _compare(an_diag, fd_diag, rtol, atol, "hessian diagonal", raise_on_failure)
    return r1, r2


def directional_derivatives(f: Callable[[torch.Tensor], float], q0: torch.Tensor, grad: torch.Tensor, *,
                            directions: int = 2, h: float = 1e-5,
                            seed: int = 0) -> list[tuple[float, float]]:
    """Analytic and central-difference directional derivatives of a scalar function along random unit
    directions (for functions too costly for :func:`check_gradient`'s per-entry differences, e.g. a whole
    simulate-then-evaluate objective).

    Args:
        f: ``q -> f(q)``; it must restore any state it depends on (e.g. a solver's warm start) itself.
        q0: the point, any shape. grad: ``df/dq`` at ``q0``, shaped like ``q0``.
        directions: how many random directions. h: the difference step along a unit direction.
        seed: of the directions.

    Returns:
        ``[(grad . v, (f(q0 + h v) - f(q0 - h v)) / 2h), ...]``, one pair per direction.
    """
    gen = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(directions):
        v = torch.randn(q0.shape, generator=gen, dtype=torch.float64).to(q0.dtype)
        v = v / torch.linalg.vector_norm(v)
        fd = (f(q0 + h * v) - f(q0 - h * v)) / (2.0 * h)
        out.append((float((grad * v).sum()), fd))
    return out


def min_eigenvalue(blocks: HessianBlocks, num_vertices: int) -> float:
    """Smallest eigenvalue of the assembled (dense) block matrix, for PSD checks on small meshes."""
    H = blocks.to_sparse(num_vertices).to_dense().double()
    H = 0.5 * (H + H.T)
    return float(torch.linalg.eigvalsh(H)[0])
