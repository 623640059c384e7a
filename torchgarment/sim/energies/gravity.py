"""Gravitational potential energy of lumped vertex masses.

::

    E = -g * sum_i m_i (d . x_i)          (d: unit "down", default -Y; g = 9.81 m/s^2)

Vertex masses are one third of the rest area of each adjacent triangle times the areal density (kg/m^2).
The rest areas come from the 2D pattern ``p`` when the mesh has one, else from the 3D positions. The
energy is linear: constant gradient, zero Hessian.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from torchgarment.errors import InputError
from torchgarment.sim.energies.base import EnergyTerm, HessianBlocks
from torchgarment.sim.energies.stretch import check_positions
from torchgarment.structures.garment_mesh import GarmentMesh

DEFAULT_DENSITY = 0.15
"""Default areal density in kg/m^2 (a light-to-medium woven cotton, 150 g/m^2)."""

STANDARD_GRAVITY = 9.81
"""Gravitational acceleration in m/s^2."""


def vertex_masses(mesh: GarmentMesh, density: float = DEFAULT_DENSITY) -> torch.Tensor:
    """(V,) lumped vertex masses in kg: density times a third of the adjacent rest triangle areas.

    Raises:
        InputError: density <= 0.
    """
    if not density > 0:
        raise InputError(f"areal density must be positive, got {density}")
    area = mesh.rest_face_areas.abs() if mesh.p is not None else mesh.face_areas
    area = area.detach()
    m = torch.zeros(mesh.num_vertices, dtype=area.dtype, device=area.device)
    m.index_add_(0, mesh.faces.reshape(-1), (area / 3.0).repeat_interleave(3))
    return density * m


class Gravity(EnergyTerm):
    """Gravity on vertex masses.

    Attributes:
        masses: buffer (V,) in kg.
        gravity: ``g`` in m/s^2.
        direction: buffer (3,) unit vector pointing down.
    """

    name = "gravity"
    constant_hessian = True

    def __init__(
        self, masses: torch.Tensor, *, gravity: float = STANDARD_GRAVITY,
        direction: Sequence[float] | torch.Tensor = (0.0, -1.0, 0.0),
    ) -> None:
        """Create the term.

        Args:
            masses: (V,) non-negative vertex masses in kg.
            gravity: acceleration ``g`` in m/s^2 (>= 0).
            direction: (3,) direction of gravity (normalised here).

        Raises:
            InputError: bad shapes, negative masses or gravity, zero direction.
        """
        super().__init__()
        if not isinstance(masses, torch.Tensor) or masses.ndim != 1 or not masses.is_floating_point():
            raise InputError("masses must be a floating (V,) tensor, got "
                             f"{getattr(masses, 'shape', type(masses))}")
        if masses.numel() and not bool((masses >= 0).all() and torch.isfinite(masses).all()):
            raise InputError("vertex masses must be finite and non-negative")
        if not gravity >= 0:
            raise InputError(f"gravity must be non-negative, got {gravity}")
        d = torch.as_tensor(direction, dtype=masses.dtype, device=masses.device).detach().clone()
        if d.shape != (3,) or not bool(torch.linalg.vector_norm(d) > 0):
            raise InputError(f"gravity direction must be a non-zero 3-vector, got {direction}")
        self.gravity = float(gravity)
        self.num_vertices = int(masses.shape[0])
        self.register_buffer("masses", masses.detach().clone())
        self.register_buffer("direction", d / torch.linalg.vector_norm(d))
        self._force_key: tuple | None = None
        self._force_cache: torch.Tensor | None = None

    @classmethod
    def from_mesh(cls, mesh: GarmentMesh, *, density: float = DEFAULT_DENSITY,
                  gravity: float = STANDARD_GRAVITY,
                  direction: Sequence[float] | torch.Tensor = (0.0, -1.0, 0.0)) -> "Gravity":
        """Gravity with masses from the rest areas of ``mesh`` (see :func:`vertex_masses`)."""
        return cls(vertex_masses(mesh, density), gravity=gravity, direction=direction)

    def _force(self, x: torch.Tensor) -> torch.Tensor:
        """(V, 3) gravity force ``m_i g d`` (the negative gradient); cached per dtype and device (do not
        modify)."""
        m, dvec = self.masses, self.direction
        key = (x.dtype, x.device, m.data_ptr(), m._version, dvec.data_ptr(), dvec._version, self.gravity)
        if key != self._force_key:
            m = m.to(device=x.device, dtype=x.dtype)
            self._force_cache = (self.gravity * m)[:, None] * dvec.to(device=x.device, dtype=x.dtype)[None, :]
            self._force_key = key
        assert self._force_cache is not None
        return self._force_cache

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Energy in joules of positions ``x`` (V, 3); differentiable in ``x``."""
        check_positions(x, self.num_vertices, self.name)
        return -(self.gravity * self.masses.to(x.dtype) * (x @ self.direction.to(x.dtype))).sum()

    def value_and_grad(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Energy () in joules and the constant gradient ``-m_i g d`` (V, 3)."""
        check_positions(x, self.num_vertices, self.name)
        f = self._force(x.detach())
        return -torch.dot(f.reshape(-1), x.detach().reshape(-1)), f.neg()

    def hessian_diagonal(self, x: torch.Tensor, project_psd: bool = True) -> torch.Tensor:
        """(V, 3, 3) zeros: the energy is linear."""
        check_positions(x, self.num_vertices, self.name)
        return torch.zeros(self.num_vertices, 3, 3, dtype=x.dtype, device=x.device)

    def hessian_blocks(self, x: torch.Tensor, project_psd: bool = True) -> HessianBlocks:
        """No blocks: the Hessian is zero."""
        check_positions(x, self.num_vertices, self.name)
        empty = torch.zeros(0, dtype=torch.long, device=x.device)
        return HessianBlocks(empty, empty.clone(), torch.zeros(0, 3, 3, dtype=x.dtype, device=x.device))

    def extra_repr(self) -> str:
        return f"mass={float(self.masses.sum()):.4g} kg, g={self.gravity} m/s^2"
