"""Sewing springs (Wang et al. 2018, Eq. 5, the sewing case): zero-rest-length springs across seams.

::

    E = sum_s  Y_sew / 2 * |x_i - x_j|^2      over the seam pairs (i, j)

``Y_sew`` is a spring constant in newtons per metre. The Hessian is constant: ``Y_sew I`` blocks, PSD.
"""

from __future__ import annotations

import torch

from torchgarment.errors import InputError
from torchgarment.sim.energies.base import EnergyTerm, HessianBlocks
from torchgarment.sim.energies.stretch import PairOperator, check_positions
from torchgarment.structures.garment_mesh import GarmentMesh

DEFAULT_SEW_STIFFNESS = 1.0e3
"""Default sewing spring constant in N/m (a 1 cm gap pulls with 10 N)."""


class SewingSprings(EnergyTerm):
    """Zero-rest-length springs joining the seam vertex pairs.

    Attributes:
        pairs: buffer (S, 2) long seam pairs.
        stiffness: ``Y_sew`` in N/m.
        num_vertices: V.
    """

    name = "sew"
    constant_hessian = True

    def __init__(self, pairs: torch.Tensor, num_vertices: int, *,
                 stiffness: float = DEFAULT_SEW_STIFFNESS) -> None:
        """Create the springs.

        Args:
            pairs: (S, 2) long vertex pairs (may be empty).
            num_vertices: V, the number of garment vertices.
            stiffness: ``Y_sew`` in N/m, > 0.

        Raises:
            InputError: bad shapes, indices out of range, a pair joining a vertex to itself, stiffness <= 0.
        """
        super().__init__()
        if (not isinstance(pairs, torch.Tensor) or pairs.ndim != 2 or pairs.shape[1] != 2
                or pairs.dtype != torch.long):
            raise InputError("seam pairs must be a long (S, 2) tensor, got "
                             f"{getattr(pairs, 'shape', type(pairs))}")
        if not stiffness > 0:
            raise InputError(f"sewing stiffness must be positive, got {stiffness}")
        if pairs.numel():
            if int(pairs.min()) < 0 or int(pairs.max()) >= num_vertices:
                raise InputError(f"seam pairs index vertices outside [0, {num_vertices})")
            if bool((pairs[:, 0] == pairs[:, 1]).any()):
                raise InputError("a seam pair joins a vertex to itself")
        self.stiffness = float(stiffness)
        self.num_vertices = int(num_vertices)
        self.register_buffer("pairs", pairs.contiguous())
        self._ops = PairOperator(pairs[:, 0].contiguous(), pairs[:, 1].contiguous(), self.num_vertices)
        self._count: torch.Tensor | None = None  # seam pairs per vertex (float64), built on first use

    @classmethod
    def from_mesh(cls, mesh: GarmentMesh, *, stiffness: float = DEFAULT_SEW_STIFFNESS) -> "SewingSprings":
        """Springs on ``mesh.seam_pairs``."""
        return cls(mesh.seam_pairs, mesh.num_vertices, stiffness=stiffness)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Energy in joules of positions ``x`` (V, 3); differentiable in ``x``."""
        check_positions(x, self.num_vertices, self.name)
        d = x[self.pairs[:, 0]] - x[self.pairs[:, 1]]
        return 0.5 * self.stiffness * (d * d).sum()

    def value_and_grad(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Energy () in joules and analytic gradient (V, 3) in newtons."""
        check_positions(x, self.num_vertices, self.name)
        d = self._ops.diff(x.detach())
        E = 0.5 * self.stiffness * torch.dot(d.reshape(-1), d.reshape(-1))
        return E, self._ops.scatter(self.stiffness * d)

    def _block(self, x: torch.Tensor) -> torch.Tensor:
        S = self.pairs.shape[0]
        return (self.stiffness * torch.eye(3, dtype=x.dtype, device=x.device)).expand(S, 3, 3).contiguous()

    def hessian_diagonal(self, x: torch.Tensor, project_psd: bool = True) -> torch.Tensor:
        """(V, 3, 3) diagonal blocks ``Y_sew * (number of seam pairs at the vertex) * I`` (always PSD)."""
        check_positions(x, self.num_vertices, self.name)
        if self._count is None or self._count.device != x.device:
            count = torch.zeros(self.num_vertices, dtype=torch.float64, device=x.device)
            count.index_add_(0, self.pairs.reshape(-1).to(x.device),
                             torch.ones(self.pairs.numel(), dtype=torch.float64, device=x.device))
            self._count = count
        d = (self.stiffness * self._count).to(x.dtype)
        h = torch.zeros(self.num_vertices, 9, dtype=x.dtype, device=x.device)
        h[:, 0::4] = d.unsqueeze(1)
        return h.view(self.num_vertices, 3, 3)

    def hessian_blocks(self, x: torch.Tensor, project_psd: bool = True) -> HessianBlocks:
        """Block-COO Hessian (constant, PSD: ``project_psd`` changes nothing)."""
        check_positions(x, self.num_vertices, self.name)
        return self._ops.hessian_blocks(self._block(x))

    def extra_repr(self) -> str:
        return f"pairs={self.pairs.shape[0]}, stiffness={self.stiffness} N/m"
