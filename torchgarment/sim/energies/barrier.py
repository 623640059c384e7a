"""Log barrier keeping the garment outside the body (Wang et al. 2018, Eq. 4).

::

    E = -mu * sum_i log(phi(x_i))          phi: the body's signed distance (metres, negative inside)

``mu`` is in joules (the paper uses 0.01). The force on a vertex is ``mu grad phi / phi``: it grows without
bound as the vertex approaches the body. Where ``phi <= 0`` the energy is ``+inf`` (never NaN); the gradient
and Hessian there are evaluated as if ``phi = offset`` (finite, pushing outward), but solvers must not accept
such states: use :meth:`BodyBarrier.max_step` to stay feasible and :meth:`BodyBarrier.project_feasible` to
repair an infeasible start (the paper projects penetrating vertices onto the body surface).

Hessian: per vertex ``mu (g g^T) / phi^2 - mu Hess(phi) / phi``. The second part is dropped: the trilinear
SDF's second derivatives are piecewise (mixed partials only, jumping across cells) and near the surface
``Hess(phi)`` of a convex body part is PSD, so the dropped term would mostly reduce stiffness. What remains is
always PSD, so projection changes nothing. (With a planar SDF, ``Hess(phi) = 0`` and the blocks are exact.)

The SDF is any module with ``forward(x) -> phi`` (differentiable) and ``value_and_gradient(x) -> (phi, grad)``,
typically a :class:`~torchgarment.sdf.BodySDF`.
"""

from __future__ import annotations

import math

import torch

from torchgarment.errors import InputError
from torchgarment.sim.energies.base import EnergyTerm, HessianBlocks
from torchgarment.sim.energies.stretch import check_positions

DEFAULT_BARRIER_MU = 0.01
"""Default barrier weight ``mu`` in joules (Wang et al. 2018)."""

DEFAULT_OFFSET = 1.0e-3
"""Default minimum clearance in metres that :meth:`BodyBarrier.project_feasible` restores (raised to a quarter
voxel for coarse SDFs)."""

SDF_LIPSCHITZ = math.sqrt(3.0)
"""Lipschitz bound of a trilinear interpolant of exact distances (each partial derivative is at most 1)."""


class BodyBarrier(EnergyTerm):
    """``-mu sum log phi(x_i)`` on a body signed distance field.

    Attributes:
        sdf: the signed distance module.
        mu: barrier weight in joules.
        offset: clearance in metres restored by :meth:`project_feasible`; also the ``phi`` used for the
            gradient of infeasible vertices.
        lipschitz: assumed Lipschitz constant of ``phi`` (for the safe-step certificate of :meth:`max_step`).
        segment_samples: points sampled along a long vertex path in :meth:`max_step`.
        num_vertices: V.
    """

    name = "body_barrier"

    def __init__(
        self,
        sdf: torch.nn.Module,
        num_vertices: int,
        *,
        mu: float = DEFAULT_BARRIER_MU,
        offset: float | None = None,
        lipschitz: float = SDF_LIPSCHITZ,
        segment_samples: int = 8,
        bisection_steps: int = 12,
        project_iterations: int = 8,
    ) -> None:
        """Create the barrier.

        Args:
            sdf: module with ``forward`` and ``value_and_gradient`` (a BodySDF).
            num_vertices: V.
            mu: barrier weight in joules, > 0.
            offset: clearance in metres, > 0; None means ``max(1 mm, voxel_size / 4)``.
            lipschitz: Lipschitz bound of ``phi`` (>= 1).
            segment_samples: samples per vertex path checked by :meth:`max_step` (>= 1).
            bisection_steps: bisection steps of :meth:`max_step`.
            project_iterations: Newton steps along ``grad phi`` in :meth:`project_feasible`.

        Raises:
            InputError: an SDF without the needed methods, or out-of-range settings.
        """
        super().__init__()
        if not callable(sdf) or not hasattr(sdf, "value_and_gradient"):
            raise InputError(f"the body barrier needs an SDF module with value_and_gradient, got {type(sdf).__name__}")
        if not mu > 0:
            raise InputError(f"barrier mu must be positive, got {mu}")
        if offset is None:
            offset = max(DEFAULT_OFFSET, 0.25 * float(getattr(sdf, "voxel_size", 0.0)))
        if not offset > 0:
            raise InputError(f"barrier offset must be positive, got {offset}")
        if not lipschitz >= 1.0 or segment_samples < 1 or bisection_steps < 0 or project_iterations < 1:
            raise InputError("barrier settings out of range: lipschitz >= 1, segment_samples >= 1, "
                             "bisection_steps >= 0, project_iterations >= 1")
        self.sdf = sdf
        self.num_vertices = int(num_vertices)
        self.mu = float(mu)
        self.offset = float(offset)
        self.lipschitz = float(lipschitz)
        self.segment_samples = int(segment_samples)
        self.bisection_steps = int(bisection_steps)
        self.project_iterations = int(project_iterations)

    # ------------------------------------------------------------------ sampling
    def _phi(self, x: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return self.sdf(x).to(x.dtype)

    def _phi_grad(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        phi, g = self.sdf.value_and_gradient(x)
        return phi.to(x.dtype), g.to(x.dtype)

    # ------------------------------------------------------------------ energy
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Energy in joules of positions ``x`` (V, 3), ``+inf`` if a vertex has ``phi <= 0``; differentiable."""
        check_positions(x, self.num_vertices, self.name)
        phi = self.sdf(x).to(x.dtype)
        ok = phi > 0
        safe = torch.where(ok, phi, torch.ones_like(phi))
        e = torch.where(ok, -self.mu * torch.log(safe), torch.full_like(phi, math.inf))
        return e.sum()

    def _evaluate(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        check_positions(x, self.num_vertices, self.name)
        phi, gphi = self._phi_grad(x.detach())
        ok = phi > 0
        safe = torch.where(ok, phi, torch.full_like(phi, self.offset))
        E = -self.mu * torch.log(safe).sum()
        if not bool(ok.all()):
            E = torch.full_like(E, math.inf)
        return E, phi, safe, gphi

    def value_and_grad(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Energy () in joules and analytic gradient ``-mu grad phi / phi`` (V, 3) in newtons."""
        E, _, safe, gphi = self._evaluate(x)
        return E, gphi * (-self.mu / safe).unsqueeze(1)

    def value_grad_hessian_diagonal(
        self, x: torch.Tensor, project_psd: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Energy, gradient and Hessian diagonal blocks sharing one SDF evaluation."""
        E, _, safe, gphi = self._evaluate(x)
        return E, gphi * (-self.mu / safe).unsqueeze(1), self._blocks(safe, gphi)

    def _blocks(self, safe: torch.Tensor, gphi: torch.Tensor) -> torch.Tensor:
        s = (self.mu / (safe * safe)).sqrt().unsqueeze(1) * gphi  # sqrt(mu) g / phi
        return s.unsqueeze(2) * s.unsqueeze(1)

    def hessian_diagonal(self, x: torch.Tensor, project_psd: bool = True) -> torch.Tensor:
        """(V, 3, 3) blocks ``mu g g^T / phi^2`` (PSD; the ``Hess(phi)`` part is dropped)."""
        _, _, safe, gphi = self._evaluate(x)
        return self._blocks(safe, gphi)

    def hessian_blocks(self, x: torch.Tensor, project_psd: bool = True) -> HessianBlocks:
        """The V diagonal blocks of :meth:`hessian_diagonal` (the barrier couples no two vertices)."""
        ar = torch.arange(self.num_vertices, device=x.device)
        return HessianBlocks(ar, ar.clone(), self.hessian_diagonal(x, project_psd))

    # ------------------------------------------------------------------ feasibility
    @torch.no_grad()
    def max_step(self, x: torch.Tensor, dx: torch.Tensor) -> float:
        """Largest ``alpha`` in (0, 1] (up to bisection) such that every path ``x_i + t dx_i``, ``t <= alpha``,
        stays outside the body (``phi > 0``).

        A path is certified safe when it is shorter than ``phi(x_i) / L`` (``L``: :attr:`lipschitz`); longer
        paths are sampled at :attr:`segment_samples` points, and each piece between consecutive samples
        ``a, b`` is certified by ``|b - a| < (phi(a) + phi(b)) / L``. The result is 1.0 when the full step is
        certified, else the largest certified ``alpha`` found by bisection (never below the conservative
        ``min_i phi(x_i) / (L |dx_i|)``, scaled by 0.999).

        Args:
            x: (V, 3) feasible positions (every ``phi > 0``).
            dx: (V, 3) step.

        Raises:
            InputError: ``x`` is not feasible (use :meth:`project_feasible` first) or ``dx`` has the wrong shape.
        """
        check_positions(x, self.num_vertices, self.name)
        check_positions(dx, self.num_vertices, self.name + " step")
        x, dx = x.detach(), dx.detach().to(x.dtype)
        phi0 = self._phi(x)
        if not bool((phi0 > 0).all()):
            raise InputError(f"{int((phi0 <= 0).sum())} vertices are inside the body (phi <= 0); "
                             f"call project_feasible first")
        length = torch.linalg.vector_norm(dx, dim=1)
        moving = length > 0
        safe = torch.full_like(phi0, math.inf)
        safe[moving] = phi0[moving] / (self.lipschitz * length[moving])  # alpha below which a path is safe
        cand = torch.nonzero(safe < 1.0, as_tuple=False).flatten()
        if cand.numel() == 0:
            return 1.0
        x_c, dx_c, phi_c, len_c, safe_c = x[cand], dx[cand], phi0[cand], length[cand], safe[cand]
        n = self.segment_samples
        t = torch.arange(1, n + 1, dtype=x.dtype, device=x.device) / n

        def certified(alpha: float) -> bool:
            m = safe_c < alpha
            if not bool(m.any()):
                return True
            pts = x_c[m, None, :] + (alpha * t)[None, :, None] * dx_c[m, None, :]
            phis = self._phi(pts.reshape(-1, 3)).view(-1, n)
            if not bool((phis > 0).all()):
                return False
            prev = torch.cat([phi_c[m, None], phis[:, :-1]], dim=1)
            piece = (alpha / n) * len_c[m, None]
            return bool((self.lipschitz * piece < prev + phis).all())

        if certified(1.0):
            return 1.0
        lo, hi = 0.999 * float(safe_c.min()), 1.0
        for _ in range(self.bisection_steps):
            mid = 0.5 * (lo + hi)
            if certified(mid):
                lo = mid
            else:
                hi = mid
        return lo

    @torch.no_grad()
    def project_feasible(self, x: torch.Tensor) -> torch.Tensor:
        """Positions with every vertex at least about :attr:`offset` outside the body.

        Vertices with ``phi < offset`` move along ``grad phi / |grad phi|`` by ``offset - phi``, repeated
        :attr:`project_iterations` times since the interpolated gradient is approximate. Others are unchanged.

        Args:
            x: (V, 3) positions in metres.

        Returns:
            (V, 3) new positions (``x`` is not modified).

        Raises:
            InputError: some vertices are still inside the body afterwards (e.g. a zero SDF gradient).
        """
        check_positions(x, self.num_vertices, self.name)
        y = x.detach().clone()
        for _ in range(self.project_iterations):
            phi, g = self._phi_grad(y)
            bad = torch.nonzero(phi < self.offset, as_tuple=False).flatten()
            if bad.numel() == 0:
                return y
            gb = g[bad]
            gn = torch.linalg.vector_norm(gb, dim=1, keepdim=True)
            step = (self.offset - phi[bad]).unsqueeze(1) * gb / gn.clamp_min(torch.finfo(y.dtype).tiny)
            y[bad] += step
        phi = self._phi(y)
        inside = int((phi <= 0).sum())
        if inside:
            raise InputError(f"project_feasible: {inside} vertices are still inside the body after "
                             f"{self.project_iterations} projection steps")
        return y

    def extra_repr(self) -> str:
        return f"mu={self.mu} J, offset={self.offset} m"
