"""Sticking energy for pins and belts (Wang et al. 2018, the ``F(x)`` of Eq. 4).

::

    E = k / 2 * sum_i |x_{v_i} - t_i|^2      over the pinned vertices v_i with targets t_i

``k`` is a spring constant in N/m. The targets are an ``nn.Parameter`` (frozen by default): call
``term.targets.requires_grad_(True)`` and ``forward`` is differentiable in them.
"""

from __future__ import annotations

import torch

from torchgarment.errors import InputError
from torchgarment.sim.energies.base import EnergyTerm, HessianBlocks
from torchgarment.sim.energies.stretch import check_positions

DEFAULT_PIN_STIFFNESS = 1.0e4
"""Default pin spring constant in N/m (a pinned vertex 1 mm off its target pulls with 10 N)."""


class Pins(EnergyTerm):
    """Zero-rest-length springs from chosen vertices to fixed targets.

    Attributes:
        indices: buffer (P,) long pinned vertices (a vertex may appear more than once).
        targets: parameter (P, 3) target positions in metres; frozen unless asked.
        stiffness: ``k`` in N/m.
        num_vertices: V.
    """

    name = "pins"
    constant_hessian = True

    def __init__(self, indices: torch.Tensor, targets: torch.Tensor, num_vertices: int, *,
                 stiffness: float = DEFAULT_PIN_STIFFNESS) -> None:
        """Create the pins.

        Args:
            indices: (P,) long vertex indices in [0, V).
            targets: (P, 3) floating target positions in metres (copied into a frozen parameter).
            num_vertices: V.
            stiffness: ``k`` in N/m, > 0.

        Raises:
            InputError: bad shapes, indices out of range, non-finite targets, stiffness <= 0.
        """
        super().__init__()
        if not isinstance(indices, torch.Tensor) or indices.ndim != 1 or indices.dtype != torch.long:
            raise InputError("pin indices must be a long (P,) tensor, got "
                             f"{getattr(indices, 'shape', type(indices))}")
        P = indices.shape[0]
        if (not isinstance(targets, torch.Tensor) or targets.shape != (P, 3)
                or not targets.is_floating_point()):
            raise InputError(f"pin targets must be a floating ({P}, 3) tensor, got "
                             f"{getattr(targets, 'shape', type(targets))}")
        if P and (int(indices.min()) < 0 or int(indices.max()) >= num_vertices):
            raise InputError(f"pin indices outside [0, {num_vertices})")
        if not bool(torch.isfinite(targets).all()):
            raise InputError("pin targets must be finite")
        if not stiffness > 0:
            raise InputError(f"pin stiffness must be positive, got {stiffness}")
        self.stiffness = float(stiffness)
        self.num_vertices = int(num_vertices)
        self.register_buffer("indices", indices.contiguous())
        self.targets = torch.nn.Parameter(targets.detach().clone(), requires_grad=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Energy in joules of positions ``x`` (V, 3); differentiable in ``x`` and ``targets``."""
        check_positions(x, self.num_vertices, self.name)
        d = x[self.indices] - self.targets
        return 0.5 * self.stiffness * (d * d).sum()

    def value_and_grad(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Energy () in joules and analytic gradient (V, 3) in newtons."""
        check_positions(x, self.num_vertices, self.name)
        x = x.detach()
        d = x[self.indices] - self.targets.detach().to(x.dtype)
        g = torch.zeros_like(x).index_put_((self.indices,), self.stiffness * d, accumulate=True)
        return 0.5 * self.stiffness * torch.dot(d.reshape(-1), d.reshape(-1)), g

    def _counts(self, x: torch.Tensor) -> torch.Tensor:
        return torch.zeros(self.num_vertices, dtype=x.dtype, device=x.device).index_put_(
            (self.indices,), torch.ones_like(self.indices, dtype=x.dtype), accumulate=True)

    def hessian_diagonal(self, x: torch.Tensor, project_psd: bool = True) -> torch.Tensor:
        """(V, 3, 3) diagonal blocks ``k * (number of pins at the vertex) * I`` (constant, PSD)."""
        check_positions(x, self.num_vertices, self.name)
        c = self.stiffness * self._counts(x)
        return c[:, None, None] * torch.eye(3, dtype=x.dtype, device=x.device)

    def hessian_blocks(self, x: torch.Tensor, project_psd: bool = True) -> HessianBlocks:
        """Block-COO Hessian: one ``k I`` diagonal block per pin (constant, PSD)."""
        check_positions(x, self.num_vertices, self.name)
        P = self.indices.shape[0]
        vals = (self.stiffness * torch.eye(3, dtype=x.dtype, device=x.device)).expand(P, 3, 3).contiguous()
        return HessianBlocks(self.indices, self.indices.clone(), vals)

    def extra_repr(self) -> str:
        return f"pins={self.indices.shape[0]}, stiffness={self.stiffness} N/m"
