"""The contract every simulation energy term follows.

A term is a ``torch.nn.Module`` whose ``forward(x)`` returns the scalar energy (joules) of garment positions
``x: (V, 3)`` (metres), built from differentiable torch operations so that autograd gives dE/dx and, through
the term's parameters (e.g. the 2D rest positions ``p``), d/dp of anything computed from it. Solvers do not
use autograd in their inner loop: each term also provides analytic, vectorized first and second derivatives.

* ``value_and_grad(x) -> (E, g)``: energy () and gradient (V, 3), analytic, no autograd graph.
* ``hessian_diagonal(x) -> (V, 3, 3)``: the 3x3 diagonal blocks of the Hessian (Jacobi preconditioning).
* ``hessian_blocks(x, project_psd) -> HessianBlocks``: block-COO (rows, cols, (K, 3, 3) values) of the full
  Hessian, with per-element blocks projected to positive semi-definite when asked (projected Newton).

The total Hessian is the sum over terms; blocks with the same (row, col) are summed when assembled.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class HessianBlocks:
    """A block-sparse symmetric matrix in COO form over vertices.

    Attributes:
        rows: (K,) long vertex indices of the block rows.
        cols: (K,) long vertex indices of the block columns.
        values: (K, 3, 3) blocks; duplicates of one (row, col) are summed.
    """

    rows: torch.Tensor
    cols: torch.Tensor
    values: torch.Tensor

    @staticmethod
    def cat(parts: "list[HessianBlocks]") -> "HessianBlocks":
        """Concatenate several block lists (their sum as a matrix)."""
        return HessianBlocks(
            torch.cat([p.rows for p in parts]), torch.cat([p.cols for p in parts]),
            torch.cat([p.values for p in parts])
        )

    def to_sparse(self, num_vertices: int) -> torch.Tensor:
        """Assemble a (3V, 3V) torch sparse COO matrix (coalesced)."""
        k = self.rows.shape[0]
        r = (3 * self.rows)[:, None, None] + torch.arange(3, device=self.rows.device)[None, :, None]
        c = (3 * self.cols)[:, None, None] + torch.arange(3, device=self.rows.device)[None, None, :]
        idx = torch.stack([r.expand(k, 3, 3).reshape(-1), c.expand(k, 3, 3).reshape(-1)])
        n = 3 * num_vertices
        return torch.sparse_coo_tensor(idx, self.values.reshape(-1), (n, n),
                                       check_invariants=False).coalesce()


class EnergyTerm(torch.nn.Module):
    """Base class of simulation energy terms (see the module docstring for the contract)."""

    #: short name used in metrics and logs, e.g. "stretch"
    name: str = "energy"
    #: True when the Hessian does not depend on ``x`` (quadratic or linear energies: sewing, bending, pins,
    #: gravity); :class:`~torchgarment.sim.scene.SimModel` then computes the term's Hessian diagonal once and
    #: reuses it (keyed on the term's stiffness, buffers and parameters) instead of every solver iteration.
    constant_hessian: bool = False
    #: True when the Hessian can change a lot from one solver iteration to the next (barriers and contact,
    # whose : stiffness grows like 1/distance^2); GD-Chebyshev refreshes such terms' diagonal every iteration
    # and may : reuse the others' (elastic terms change slowly) for
    # ``SolveSettings.elastic_diagonal_interval`` iterations.
    volatile_hessian: bool = False
    #: rows (long) whose Hessian diagonal the last :meth:`accumulate_value_grad_hessian_diagonal` call with a
    #: diagonal touched; None = possibly every row (terms with sparse derivatives set it)
    last_hessian_rows: torch.Tensor | None = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def reset_cache(self) -> None:
        """Forget what earlier evaluations left behind that can change later results' last bits (the body
        barrier's lazy sampling references), so that a new solve repeats an earlier one bit for bit. Terms
        without such state do nothing."""

    def value_and_grad(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Energy () and analytic gradient (V, 3). The default uses autograd; terms override it."""
        with torch.enable_grad():
            xr = x.detach().requires_grad_(True)
            e = self.forward(xr)
            (g,) = torch.autograd.grad(e, xr)
        return e.detach(), g

    def hessian_diagonal(self, x: torch.Tensor, project_psd: bool = True) -> torch.Tensor:  # pragma: no cover
        raise NotImplementedError

    def value_grad_hessian_diagonal(
        self, x: torch.Tensor, project_psd: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Energy, gradient and Hessian diagonal blocks in one call; terms that can share work override it."""
        E, g = self.value_and_grad(x)
        return E, g, self.hessian_diagonal(x, project_psd)

    def accumulate_value_grad_hessian_diagonal(
        self, x: torch.Tensor, g: torch.Tensor, h: torch.Tensor | None, project_psd: bool = True
    ) -> torch.Tensor:
        """Add the gradient to ``g`` (V, 3) and, unless ``h`` is None, the Hessian diagonal blocks to ``h``
        (V, 3, 3), in place; return the energy (). Terms whose derivatives are sparse (a barrier acting on a
        few vertices) override it to touch only those rows."""
        if h is None:
            E, gt = self.value_and_grad(x)
        else:
            E, gt, ht = self.value_grad_hessian_diagonal(x, project_psd)
            h.add_(ht)
        g.add_(gt)
        return E

    def state_key(self) -> tuple:
        """A key that changes whenever the term's stiffness, buffers or parameters change (in place or
        replaced); used to cache derived data such as a constant Hessian diagonal."""
        tensors = [*self.parameters(recurse=False), *self.buffers(recurse=False)]
        return (getattr(self, "stiffness", None),
                tuple((t.data_ptr(), t._version, tuple(t.shape), t.dtype, t.device) for t in tensors))

    def hessian_blocks(self, x: torch.Tensor, project_psd: bool = True) -> HessianBlocks:  # pragma: no cover
        raise NotImplementedError
