"""Objectives of intersection-free garment retargeting (Huang et al. 2025, section 3.4).

Every term is a simulation :class:`~torchgarment.sim.energies.base.EnergyTerm` (:class:`RetargetEnergy`) over
the retargeting state ``y`` (N + 1, 3): the garment positions ``x = y[:N]`` and, in the last row, the
inflation parameter ``t = y[N, 0]`` (Step 2 interpolates the avatar and the skeleton with it, Step 3 holds it
at 1; the row's other two entries are unused and stay 0), see :func:`make_state` / :func:`split_state`.
``forward(y)`` is the weighted value (differentiable by autograd in ``x`` and ``t``),
:meth:`RetargetEnergy.energy` the unweighted one of ``(x, t)``, and ``hessian_blocks(y)`` the 3x3 vertex
blocks of the Hessian with every per-element Hessian positive semi-definite, the t-couplings in the blocks of
vertex N (column 0). They are composed by a :class:`~torchgarment.sim.scene.SimModel` and minimised by the
shared projected Newton (:func:`~torchgarment.retarget.solver.projected_newton`). The shape terms are sums of
squared residuals, so their per-element Hessians are Gauss-Newton ``2 w J^T J`` (PSD by construction, exact
where the residuals vanish, i.e. at the source shape; cheaper than an eigen-projection of the full Hessian);
the barrier's come from ipctk with per-pair PSD clamping:

* :class:`SurfaceShape` L_surf: deformation difference of adjacent triangles on the vector joining their
  opposite vertices, area weighted (eq. 2). Per-pair 12 x 12 Gauss-Newton Hessians from closed-form
  residual Jacobians (PSD by construction).
* :class:`Positional` L_pos: barycentric coordinate of boundary vertices along their nearest bone; the
  skeleton joints are ``(1 - t) J_source + t J_target`` (eq. 3). Per-vertex 4 x 4 blocks over (x_i, t).
* :class:`Attachment` L_attach: a separate piece of the garment (a pocket, a collar) keeps its place on the
  piece under it (not in the paper, whose garments are one piece). Per-vertex 12 x 12 Gauss-Newton Hessians.
* :class:`Fit` L_fit: squared avatar SDF at the fit vertices (eq. 4, lumped areas), Gauss-Newton Hessian.
* :class:`CurveShape` L_curve: discrete curvature and torsion of polylines (eq. 5 and the torsion term).
* :class:`Contact` L_contact: IPC barrier of garment-avatar and garment-self pairs, the avatar being
  ``(1 - t) V_shrunk + t V_full`` (:class:`~torchgarment.sim.contact.MovingObstacleContact`); ipctk's per-pair
  PSD-clamped Hessians, chained to (x, t).

Lengths are in the units of ``x``; the pipeline runs in a canonical frame where the avatar is 1.7 units tall
(human scale in metres), so the paper's constants (dhat = 2 mm) apply unchanged.

Surface-shape invariance: with the triangle basis ``[e1, e2, n / sqrt|n|]`` (``n = e1 x e2``) the deformation
of a triangle maps source to current exactly for any similarity (rotation, translation, uniform scale), so
L_surf vanishes under every similarity, and under every affine map for pairs whose four vertices are coplanar
(e.g. a flat panel). A general 3D affine map of a curved surface has no triangle-local representative out of
the plane, so there L_surf is only small, not zero (the component of the opposite-vertex vector along the
normal is mapped by the normal's scaling, not by the unknown affine map).
"""

from __future__ import annotations

import math
from typing import Callable

import ipctk
import numpy as np
import torch
from torch import nn

from torchgarment.errors import InputError, MeshError
from torchgarment.sim.contact import BroadPhase, MovingObstacleContact
from torchgarment.sim.energies.base import EnergyTerm, HessianBlocks
from torchgarment.structures.garment_mesh import GarmentMesh
from torchgarment.structures.mesh_checks import face_areas

# ---------------------------------------------------------------------------------------------- mesh helpers


def adjacent_triangle_pairs(faces: np.ndarray) -> np.ndarray:
    """Pairs of triangles sharing an interior edge as vertex quadruples (the mesh's hinges,
    :attr:`GarmentMesh.hinges <torchgarment.structures.garment_mesh.GarmentMesh.hinges>`).

    Args:
        faces: (F, 3) int triangles.

    Returns:
        (P, 6) int64 rows ``(v1, v2, v3, v4, f1, f2)``: ``f1 = (v1, v2, v3)`` up to rotation and
        ``f2`` holds ``v2, v1, v4``; the shared edge is ``v1 v2``. Edges of one face or of 3+ faces are left
        out.
    """
    mesh = _topology(faces)
    return torch.cat([mesh.hinges, mesh.hinge_faces], dim=1).numpy()


def _topology(faces: np.ndarray) -> GarmentMesh:
    """A GarmentMesh holding only the connectivity ``faces`` (F, 3) (positions zero), for its lazy
    topology."""
    f = torch.as_tensor(np.asarray(faces, dtype=np.int64))
    return GarmentMesh(torch.zeros(int(f.max()) + 1 if f.numel() else 0, 3, dtype=torch.float64), f)


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Closed boundary loops of a triangle mesh, each an ordered vertex array (first vertex not repeated), in
    face orientation, longest first (:attr:`GarmentMesh.boundary_loops <torchgarment.structures.garment_mesh.
    GarmentMesh.boundary_loops>`).

    Args:
        faces: (F, 3) int triangles (consistently oriented).

    Raises:
        MeshError: a boundary passes through a vertex twice (non-manifold vertex).
    """
    return [loop.numpy() for loop in _topology(faces).boundary_loops]


def vertex_areas(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(N,) lumped (one third of the incident triangle areas) vertex areas."""
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    fa = 0.5 * torch.linalg.cross(v1 - v0, v2 - v0, dim=-1).norm(dim=-1)
    out = torch.zeros(vertices.shape[0], dtype=vertices.dtype, device=vertices.device)
    for k in range(3):
        out.index_add_(0, faces[:, k], fa / 3.0)
    return out


def mean_incident_edge_length(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(N,) average length of the edges at each vertex."""
    e = torch.as_tensor(
        np.unique(np.sort(np.asarray(ipctk.edges(faces.cpu().numpy().astype(np.int32))), 1), axis=0),
        device=vertices.device,
        dtype=torch.long,
    )
    ln = (vertices[e[:, 0]] - vertices[e[:, 1]]).norm(dim=-1)
    s = torch.zeros(vertices.shape[0], dtype=vertices.dtype, device=vertices.device)
    c = torch.zeros_like(s)
    for k in range(2):
        s.index_add_(0, e[:, k], ln)
        c.index_add_(0, e[:, k], torch.ones_like(ln))
    return s / c.clamp_min(1)


# ---------------------------------------------------------------------------------------------- Hessian
# helpers


def element_hessians(fn: Callable[..., torch.Tensor], z: torch.Tensor, *consts: torch.Tensor) -> torch.Tensor:
    """Per-element Hessians (E, d, d) of a batched element function ``fn(z (E, d), *consts) -> (E,)``.

    Elements are independent, so d double-backward passes of the summed gradient give every element's Hessian
    at once (cheaper than vmap over a functorch hessian).
    """
    z = z.detach().clone().requires_grad_(True)
    with torch.enable_grad():
        v = fn(z, *consts)
        (g,) = torch.autograd.grad(v.sum(), z, create_graph=True)
        cols = [
            torch.autograd.grad(g[:, j].sum(), z, retain_graph=j + 1 < z.shape[1], allow_unused=True)[0]
            for j in range(z.shape[1])
        ]
    cols = [torch.zeros_like(z) if c is None else c for c in cols]
    return torch.stack(cols, dim=2).detach()


def element_gauss_newton(
    res_fn: Callable[..., torch.Tensor], z: torch.Tensor, weights: torch.Tensor, *consts: torch.Tensor
) -> torch.Tensor:
    """Gauss-Newton Hessians ``2 w J^T J`` (E, d, d) of ``sum_e w_e |r_e|^2`` for residuals
    ``res_fn(z, *consts)`` of shape (E,) or (E, R); PSD by construction. One backward pass per residual
    component."""
    z = z.detach().clone().requires_grad_(True)
    with torch.enable_grad():
        r = res_fn(z, *consts)
        r = r[:, None] if r.ndim == 1 else r
        rows = [
            torch.autograd.grad(r[:, i].sum(), z, retain_graph=i + 1 < r.shape[1])[0]
            for i in range(r.shape[1])
        ]
    j = torch.stack(rows, dim=1).detach()  # (E, R, d)
    return 2.0 * weights[:, None, None] * (j.transpose(1, 2) @ j)


def project_psd(h: torch.Tensor) -> torch.Tensor:
    """Clamp the negative eigenvalues of a batch of symmetric matrices (E, d, d) to zero."""
    h = 0.5 * (h + h.transpose(-1, -2))
    lam, q = torch.linalg.eigh(h)
    return (q * lam.clamp_min(0.0).unsqueeze(-2)) @ q.transpose(-1, -2)


def element_blocks(h: torch.Tensor, idx: torch.Tensor) -> HessianBlocks:
    """Element Hessians (E, 3k, 3k) over the vertices ``idx`` (E, k) as 3x3 vertex blocks (E k^2 of them)."""
    e, k = idx.shape
    vals = h.reshape(e, k, 3, k, 3).permute(0, 1, 3, 2, 4).reshape(e * k * k, 3, 3)
    rows = idx[:, :, None].expand(e, k, k).reshape(-1)
    cols = idx[:, None, :].expand(e, k, k).reshape(-1)
    return HessianBlocks(rows, cols, vals)


def vertex_dofs(idx: torch.Tensor) -> torch.Tensor:
    """(E, k) vertex indices -> (E, 3k) unknown indices ``3 v + c``."""
    ar = torch.arange(3, device=idx.device)
    return (3 * idx[:, :, None] + ar).reshape(idx.shape[0], -1)


def _t_tensor(t: torch.Tensor | float, ref: torch.Tensor) -> torch.Tensor:
    return t if isinstance(t, torch.Tensor) else torch.tensor(float(t), dtype=ref.dtype, device=ref.device)


def make_state(x: torch.Tensor, t: torch.Tensor | float) -> torch.Tensor:
    """The retargeting state (N + 1, 3): garment positions ``x`` (N, 3) and the row ``(t, 0, 0)``."""
    tt = _t_tensor(t, x).to(x.dtype).reshape(1)
    return torch.cat([x, torch.cat([tt, tt.new_zeros(2)])[None]], dim=0)


def split_state(y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Garment positions (N, 3) and the inflation parameter (0-d) of a state ``y`` (N + 1, 3) (views)."""
    return y[:-1], y[-1, 0]


class RetargetEnergy(EnergyTerm):
    """Base of the retargeting terms: an :class:`EnergyTerm` over the state ``y`` (N + 1, 3) (module
    docstring).

    Subclasses implement :meth:`energy` (unweighted value of ``x`` (N, 3) and ``t``, differentiable by
    autograd) and :meth:`unweighted_blocks` (its PSD Hessian as vertex blocks over N + 1 vertices, the t
    entries in vertex N's column/row 0). ``uses_t`` says whether the value depends on ``t``.

    Args:
        weight: the term's weight (>= 0) in the objective: ``forward(y) = weight * energy(x, t)``.
    """

    name = "term"
    uses_t = False

    def __init__(self, weight: float = 1.0) -> None:
        super().__init__()
        if not (math.isfinite(weight) and weight >= 0):
            raise InputError(f"the weight of a retargeting term must be a non-negative number, got {weight}")
        self.weight = float(weight)

    def energy(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        """Unweighted value () of garment positions ``x`` (N, 3) and inflation ``t`` (0-d)."""
        raise NotImplementedError

    def unweighted_blocks(self, x: torch.Tensor, t: torch.Tensor, project_psd: bool) -> HessianBlocks:
        """PSD Hessian blocks of :meth:`energy` over N + 1 vertices (the t entries in vertex N's row and
        column 0)."""
        raise NotImplementedError  # pragma: no cover - abstract

    def forward(self, y: torch.Tensor) -> torch.Tensor:
        """Weighted value () of the state ``y`` (N + 1, 3)."""
        x, t = split_state(y)
        return self.weight * self.energy(x, t)

    def value(self, y: torch.Tensor) -> float:
        """Unweighted value of the state ``y`` (diagnostics; +inf where a barrier is)."""
        with torch.no_grad():
            return float(self.energy(*split_state(y.detach())))

    def hessian_blocks(self, y: torch.Tensor, project_psd: bool = True) -> HessianBlocks:
        """Weighted Hessian blocks over N + 1 vertices. The shape terms' blocks are Gauss-Newton (PSD whatever
        ``project_psd`` says); the barrier's are PSD-clamped per pair when ``project_psd``."""
        x, t = split_state(y.detach())
        b = self.unweighted_blocks(x, t, project_psd)
        return HessianBlocks(b.rows, b.cols, self.weight * b.values)

    def hessian_diagonal(self, y: torch.Tensor, project_psd: bool = True) -> torch.Tensor:
        """(N + 1, 3, 3) diagonal blocks of :meth:`hessian_blocks`."""
        b = self.hessian_blocks(y, project_psd)
        out = torch.zeros(y.shape[0], 3, 3, dtype=y.dtype, device=y.device)
        d = b.rows == b.cols
        return out.index_add_(0, b.rows[d], b.values[d])

    def per_element(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:  # pragma: no cover - optional
        """Per-element values (for diagnostics)."""
        raise NotImplementedError


def _empty_blocks(x: torch.Tensor) -> HessianBlocks:
    z = torch.zeros(0, dtype=torch.long, device=x.device)
    return HessianBlocks(z, z.clone(), torch.zeros(0, 3, 3, dtype=x.dtype, device=x.device))


# ---------------------------------------------------------------------------------------------- L_surf


def _tri_basis(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) columns [b - a, c - a, n / sqrt|n|] of a triangle (n = e1 x e2)."""
    e1, e2 = b - a, c - a
    n = torch.linalg.cross(e1, e2, dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-300).sqrt()
    return torch.stack([e1, e2, n], dim=-1)


def _surf_pair(z: torch.Tensor, k1: torch.Tensor, k2: torch.Tensor) -> torch.Tensor:
    """(P,) l_surf of pairs: z (P, 12) = v1, v2, v3, v4; k_i (P, 3) = B_i^s^-1 xhat."""
    v = z.reshape(-1, 4, 3)
    b1 = _tri_basis(v[:, 0], v[:, 1], v[:, 2])
    b2 = _tri_basis(v[:, 1], v[:, 0], v[:, 3])
    r = (b1 @ k1[..., None] - b2 @ k2[..., None])[..., 0]
    return (r * r).sum(-1)


class SurfaceShape(RetargetEnergy):
    """L_surf = sum over adjacent triangle pairs of (source area of both) * |tau_1 xhat - tau_2 xhat|^2.

    ``xhat`` is the unit source vector between the two opposite vertices and ``tau_i`` the deformation of
    triangle i (see the module docstring for its basis). Zero at the source shape.

    Args:
        source_vertices: (N, 3) source garment positions.
        faces: (F, 3) long garment triangles.
        weight: the term's weight.
    """

    name = "surf"

    def __init__(self, source_vertices: torch.Tensor, faces: torch.Tensor, weight: float = 1.0) -> None:
        super().__init__(weight)
        pairs = adjacent_triangle_pairs(faces.cpu().numpy())
        if pairs.shape[0] == 0:
            raise MeshError("the garment has no pair of adjacent triangles")
        dev, dt = source_vertices.device, source_vertices.dtype
        p = torch.as_tensor(pairs, device=dev)
        vs = source_vertices.detach()
        v1, v2, v3, v4 = (vs[p[:, k]] for k in range(4))
        b1 = _tri_basis(v1, v2, v3)
        b2 = _tri_basis(v2, v1, v4)
        x = v4 - v3
        xl = x.norm(dim=-1, keepdim=True)
        if (
            bool((xl <= 0).any())
            or bool((torch.linalg.det(b1).abs() <= 0).any())
            or bool((torch.linalg.det(b2).abs() <= 0).any())
        ):
            raise MeshError("the source garment has degenerate triangles (zero area) next to a shared edge")
        xhat = x / xl
        k1 = torch.linalg.solve(b1, xhat)
        k2 = torch.linalg.solve(b2, xhat)
        fa = 0.5 * torch.linalg.cross(
            vs[faces[:, 1]] - vs[faces[:, 0]], vs[faces[:, 2]] - vs[faces[:, 0]], dim=-1
        ).norm(dim=-1)
        w = fa[p[:, 4]] + fa[p[:, 5]]
        self.register_buffer("quads", p[:, :4].contiguous())
        self.register_buffer("pair_faces", p[:, 4:].contiguous())
        self.register_buffer("k1", k1.to(dt))
        self.register_buffer("k2", k2.to(dt))
        self.register_buffer("weights", w.to(dt))
        self.num_faces = int(faces.shape[0])

    def per_element(self, x: torch.Tensor, t: torch.Tensor | None = None) -> torch.Tensor:
        """(P,) unweighted l_surf of every adjacent pair."""
        z = x[self.quads].reshape(-1, 12)
        return _surf_pair(z, self.k1, self.k2)

    def energy(self, x: torch.Tensor, t: torch.Tensor | None = None) -> torch.Tensor:  # noqa: D102
        return (self.weights * self.per_element(x)).sum()

    def triangle_distortion(self, x: torch.Tensor) -> torch.Tensor:
        """(F,) per-triangle distortion: mean unweighted l_surf of the pairs a triangle belongs to."""
        le = self.per_element(x).detach()
        s = torch.zeros(self.num_faces, dtype=x.dtype, device=x.device)
        c = torch.zeros_like(s)
        for k in range(2):
            s.index_add_(0, self.pair_faces[:, k], le)
            c.index_add_(0, self.pair_faces[:, k], torch.ones_like(le))
        return s / c.clamp_min(1)

    def residual_jacobian(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Residuals r = tau_1 xhat - tau_2 xhat (P, 3) and their Jacobians (P, 3, 12) in closed form."""
        v = x.detach()[self.quads]  # (P, 4, 3)
        k1, k2 = self.k1, self.k2
        eye = torch.eye(3, dtype=x.dtype, device=x.device)

        def normal_part(
            a: torch.Tensor, b: torch.Tensor, c: torch.Tensor
        ) -> tuple[torch.Tensor, torch.Tensor]:
            # ntilde = n / sqrt|n|, n = (b - a) x (c - a); d ntilde / d(a, b, c) as (P, 3, 9)
            e1, e2 = b - a, c - a
            n = torch.linalg.cross(e1, e2, dim=-1)
            ln = n.norm(dim=-1).clamp_min(1e-300)
            nh = n / ln[:, None]
            dn_dnt = (eye - 0.5 * nh[:, :, None] * nh[:, None, :]) / ln.sqrt()[:, None, None]
            dn_de1 = -_skew(e2)
            dn_de2 = _skew(e1)
            j1 = dn_dnt @ dn_de1
            j2 = dn_dnt @ dn_de2
            return n / ln.sqrt()[:, None], torch.cat([-(j1 + j2), j1, j2], dim=2)

        v1, v2, v3, v4 = v[:, 0], v[:, 1], v[:, 2], v[:, 3]
        nt1, jn1 = normal_part(v1, v2, v3)  # wrt (v1, v2, v3)
        nt2, jn2 = normal_part(v2, v1, v4)  # wrt (v2, v1, v4)
        r = (
            k1[:, 0:1] * (v2 - v1)
            + k1[:, 1:2] * (v3 - v1)
            + k1[:, 2:3] * nt1
            - k2[:, 0:1] * (v1 - v2)
            - k2[:, 1:2] * (v4 - v2)
            - k2[:, 2:3] * nt2
        )
        P = v.shape[0]
        J = torch.zeros(P, 3, 12, dtype=x.dtype, device=x.device)
        a0, a1, b0, b1 = k1[:, 0], k1[:, 1], k2[:, 0], k2[:, 1]
        # linear parts: coefficient of v1, v2, v3, v4 times the identity
        c = torch.stack([-a0 - a1 - b0, a0 + b0 + b1, a1, -b1], dim=1)  # (P, 4)
        J += torch.einsum("pk,ij->pikj", c, eye).reshape(P, 3, 12)
        J[:, :, 0:9] += k1[:, 2, None, None] * jn1
        jn2s = k2[:, 2, None, None] * jn2
        J[:, :, 3:6] -= jn2s[:, :, 0:3]
        J[:, :, 0:3] -= jn2s[:, :, 3:6]
        J[:, :, 9:12] -= jn2s[:, :, 6:9]
        return r, J

    def unweighted_blocks(
        self, x: torch.Tensor, t: torch.Tensor | None = None, project_psd: bool = True
    ) -> HessianBlocks:
        """Gauss-Newton Hessian ``2 w J^T J`` per pair (PSD by construction; exact at the source shape, where
        the residuals vanish)."""
        _, J = self.residual_jacobian(x)
        h = 2.0 * self.weights[:, None, None] * (J.transpose(1, 2) @ J)
        return element_blocks(h, self.quads)


def _skew(a: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) matrices with ``_skew(a) @ b = a x b``."""
    z = torch.zeros_like(a[..., 0])
    return torch.stack(
        [
            torch.stack([z, -a[..., 2], a[..., 1]], -1),
            torch.stack([a[..., 2], z, -a[..., 0]], -1),
            torch.stack([-a[..., 1], a[..., 0], z], -1),
        ],
        -2,
    )


# ---------------------------------------------------------------------------------------------- L_pos


def nearest_bone(points: torch.Tensor, joints: torch.Tensor, bones: torch.Tensor) -> torch.Tensor:
    """(P,) index of the bone (segment) closest to each point."""
    a, b = joints[bones[:, 0]], joints[bones[:, 1]]  # (B, 3)
    ab = b - a
    u = ((points[:, None, :] - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-300)
    u = u.clamp(0.0, 1.0)
    d = (points[:, None, :] - (a + u[..., None] * ab)).norm(dim=-1)
    return d.argmin(dim=1)


def _pos_residual(z: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """(K,) w - w_s of vertices: z (K, 4) = (x, t); c (K, 13) = a_s, b_s, a_t, b_t, w_s."""
    x, t = z[:, :3], z[:, 3:4]
    a = c[:, 0:3] + t * (c[:, 6:9] - c[:, 0:3])
    b = c[:, 3:6] + t * (c[:, 9:12] - c[:, 3:6])
    ab = b - a
    return ((x - a) * ab).sum(-1) / (ab * ab).sum(-1) - c[:, 12]


def _pos_vertex(z: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """(K,) l_pos of vertices: z (K, 4) = (x, t); c (K, 13) = a_s, b_s, a_t, b_t, w_s."""
    x, t = z[:, :3], z[:, 3:4]
    a = c[:, 0:3] + t * (c[:, 6:9] - c[:, 0:3])
    b = c[:, 3:6] + t * (c[:, 9:12] - c[:, 3:6])
    ab = b - a
    w = ((x - a) * ab).sum(-1) / (ab * ab).sum(-1)
    return (w - c[:, 12]) ** 2


def usable_bones(
    source_joints: torch.Tensor, target_joints: torch.Tensor, bones: torch.Tensor
) -> torch.Tensor:
    """(U,) long indices of the bones (B, 2) of positive length in both skeletons (joints (J, 3)): a bone of
    (near) zero length in either (e.g. a root bone) has no barycentric coordinate and no line."""
    ls = (source_joints[bones[:, 1]] - source_joints[bones[:, 0]]).norm(dim=-1)
    lt = (target_joints[bones[:, 1]] - target_joints[bones[:, 0]]).norm(dim=-1)
    return torch.nonzero((ls > 1e-4 * ls.max()) & (lt > 1e-4 * lt.max())).reshape(-1)


def loop_winds_around_a_bone(points: torch.Tensor, joints: torch.Tensor, bones: torch.Tensor) -> bool:
    """Whether a closed loop of points (L, 3) winds around the bone nearest to most of them (a cuff, a hem,
    a waistband's rim: |winding number| >= 1/2 about the bone's line) rather than lying beside it (a patch
    pocket's rim: about 0). Bones: (B, 2) joint pairs of positive length."""
    nb = nearest_bone(points, joints, bones)
    bone = int(torch.mode(nb).values)
    a, b = joints[bones[bone, 0]], joints[bones[bone, 1]]
    axis = (b - a) / (b - a).norm()
    d = points - a
    d = d - (d @ axis)[:, None] * axis
    other = torch.eye(3, dtype=points.dtype, device=points.device)[int(axis.abs().argmin())]
    u = torch.linalg.cross(axis, other, dim=-1)
    u = u / u.norm()
    ang = torch.atan2(d @ torch.linalg.cross(axis, u, dim=-1), d @ u)
    step = torch.remainder(torch.roll(ang, -1) - ang + math.pi, 2 * math.pi) - math.pi
    return bool(abs(float(step.sum())) >= math.pi)


class Positional(RetargetEnergy):
    """L_pos = sum over boundary vertices of (mean source edge length) * (w_source - w)^2.

    ``w`` is the (unclamped) barycentric coordinate of the vertex projected on the line of its nearest source
    bone (among the bones of positive length in both skeletons), whose joints move as
    ``(1 - t) J_source + t J_target``.

    Args:
        source_vertices: (N, 3) source garment positions.
        faces: (F, 3) long triangles.
        source_joints / target_joints: (J, 3) skeleton joints (same bones).
        bones: (B, 2) long joint pairs.
        vertices: (K,) long constrained vertices; default: the garment boundary.
        weight: the term's weight.
    """

    name = "pos"
    uses_t = True

    def __init__(
        self,
        source_vertices: torch.Tensor,
        faces: torch.Tensor,
        source_joints: torch.Tensor,
        target_joints: torch.Tensor,
        bones: torch.Tensor,
        vertices: torch.Tensor | None = None,
        weight: float = 1.0,
    ) -> None:
        super().__init__(weight)
        if vertices is None:
            loops = boundary_loops(faces.cpu().numpy())
            vertices = torch.as_tensor(
                np.unique(np.concatenate(loops)) if loops else np.zeros(0, np.int64),
                device=source_vertices.device,
            )
        vs = source_vertices.detach()
        self.register_buffer("vertices", vertices.long())
        if bones.shape[0] == 0:
            raise InputError("the skeleton has no bones")
        usable = usable_bones(source_joints, target_joints, bones)
        if usable.numel() == 0:
            raise InputError("the skeletons have no bone of positive length")
        bone = (
            usable[nearest_bone(vs[self.vertices], source_joints, bones[usable])]
            if len(self.vertices)
            else torch.zeros(0, dtype=torch.long, device=vs.device)
        )
        ja, jb = bones[bone, 0], bones[bone, 1]
        a_s, b_s, a_t, b_t = source_joints[ja], source_joints[jb], target_joints[ja], target_joints[jb]
        ab = b_s - a_s
        w_s = ((vs[self.vertices] - a_s) * ab).sum(-1) / (ab * ab).sum(-1)
        self.register_buffer("consts", torch.cat([a_s, b_s, a_t, b_t, w_s[:, None]], dim=1).to(vs.dtype))
        self.register_buffer("weights", mean_incident_edge_length(vs, faces)[self.vertices])
        self.register_buffer("bone", bone)

    def _z(self, x: torch.Tensor, t: torch.Tensor | float) -> torch.Tensor:
        t = _t_tensor(t, x)
        return torch.cat([x[self.vertices], t.expand(len(self.vertices), 1)], dim=1)

    def energy(self, x: torch.Tensor, t: torch.Tensor | float) -> torch.Tensor:  # noqa: D102
        if len(self.vertices) == 0:
            return x.sum() * 0.0
        return (self.weights * _pos_vertex(self._z(x, t), self.consts)).sum()

    def unweighted_blocks(
        self, x: torch.Tensor, t: torch.Tensor | float, project_psd: bool = True
    ) -> HessianBlocks:
        """Gauss-Newton 4 x 4 blocks over (x_i, t), placed on the vertex pair (i, N) (t in N's first
        entry)."""
        if len(self.vertices) == 0:
            return _empty_blocks(x)
        h4 = element_gauss_newton(
            _pos_residual, self._z(x.detach(), _t_tensor(t, x).detach()), self.weights, self.consts
        )
        k = len(self.vertices)
        h = h4.new_zeros(k, 6, 6)
        h[:, :4, :4] = h4
        idx = torch.stack([self.vertices, torch.full_like(self.vertices, x.shape[0])], dim=1)
        return element_blocks(h, idx)


# ---------------------------------------------------------------------------------------------- L_attach


def _tri_frame(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) orthonormal columns [e1, n x e1, n] of triangles (e1 along b - a, n the unit normal)."""
    e1 = b - a
    e1 = e1 / e1.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    n = torch.linalg.cross(b - a, c - a, dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    return torch.stack([e1, torch.linalg.cross(n, e1, dim=-1), n], dim=-1)


def _attach_residual(z: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """(K, 3) residuals ``x - sum_j b_j p_j - F(p) o`` of attached vertices: z (K, 12) = x, p0, p1, p2 (the
    anchor triangle); c (K, 6) = the barycentric coordinates b of the anchor and the offset o in the
    triangle's frame F (:func:`_tri_frame`)."""
    v = z.reshape(-1, 4, 3)
    p0, p1, p2 = v[:, 1], v[:, 2], v[:, 3]
    anchor = c[:, 0:1] * p0 + c[:, 1:2] * p1 + c[:, 2:3] * p2
    return v[:, 0] - anchor - (_tri_frame(p0, p1, p2) @ c[:, 3:6, None])[..., 0]


def layer_anchors(
    vertices: torch.Tensor, faces: torch.Tensor, max_distance: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Where each separate piece of a garment lies on the larger pieces: a patch pocket on the shirt, a
    collar on the neckline, a sleeve left unwelded next to its armhole.

    The pieces are the connected components of ``faces``, ranked by area. Every vertex of a piece within
    ``max_distance`` of a larger piece is anchored to its closest point there (libigl's point-mesh query);
    the largest piece has no anchors.

    Args:
        vertices: (N, 3) garment positions (any length unit). faces: (F, 3) long triangles.
        max_distance: largest vertex-to-piece distance that anchors (units of ``vertices``).

    Returns:
        ``(vertex, anchor_face, barycentric)``: (K,) long anchored vertices, (K, 3) long the anchor
        triangles' vertices and (K, 3) the anchor points' barycentric coordinates in them (K = 0 for a
        garment in one piece).
    """
    import igl
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    v = vertices.detach().to("cpu", torch.float64).numpy()
    f = faces.detach().cpu().numpy().astype(np.int64)
    n = v.shape[0]
    empty = (torch.zeros(0, dtype=torch.long), torch.zeros(0, 3, dtype=torch.long),
             torch.zeros(0, 3, dtype=torch.float64))
    if f.shape[0] == 0:
        return empty
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    face_label = label[f[:, 0]]
    area = face_areas(torch.as_tensor(v), torch.as_tensor(f)).numpy()
    piece_area = np.bincount(face_label, weights=area, minlength=label.max() + 1)
    pieces = [int(c) for c in np.argsort(-piece_area, kind="stable") if piece_area[c] > 0]
    # anchors only on triangles with a normal (a degenerate one has no frame)
    usable = area > 1e-12 * max(float(np.median(area)), 1e-300)
    out_v, out_f, out_b = [], [], []
    for rank, piece in enumerate(pieces[1:], start=1):
        base = f[np.isin(face_label, pieces[:rank]) & usable]
        pv = np.unique(f[face_label == piece])
        if base.shape[0] == 0 or pv.shape[0] == 0:
            continue
        sq, tri, closest = igl.point_mesh_squared_distance(np.ascontiguousarray(v[pv]), v, base)
        keep = np.sqrt(np.asarray(sq)) <= max_distance
        if not keep.any():
            continue
        tri_v = base[np.asarray(tri)[keep]]
        a, b, c, p = v[tri_v[:, 0]], v[tri_v[:, 1]], v[tri_v[:, 2]], np.asarray(closest)[keep]
        e0, e1, ep = b - a, c - a, p - a
        d00, d01, d11 = (e0 * e0).sum(1), (e0 * e1).sum(1), (e1 * e1).sum(1)
        d20, d21 = (ep * e0).sum(1), (ep * e1).sum(1)
        den = d00 * d11 - d01 * d01
        w1 = (d11 * d20 - d01 * d21) / den
        w2 = (d00 * d21 - d01 * d20) / den
        out_v.append(pv[keep])
        out_f.append(tri_v)
        out_b.append(np.stack([1.0 - w1 - w2, w1, w2], axis=1))
    if not out_v:
        return empty
    return (torch.as_tensor(np.concatenate(out_v)), torch.as_tensor(np.concatenate(out_f)),
            torch.as_tensor(np.concatenate(out_b)))


class Attachment(RetargetEnergy):
    """L_attach = sum over attached vertices of A_i |x_i - a_i - F_i o_i|^2 / ell^2: the garment's separate
    pieces stay where they lie on the larger ones.

    The surface and curve terms are blind to a rigid motion of a whole piece, and the positional term holds
    only the boundary's coordinate along a bone, so a patch pocket, a collar or a hood that is its own piece
    could slide around the body at no cost. Each vertex ``i`` of such a layer is anchored
    (:func:`layer_anchors`) to the closest point ``a_i`` of the piece under it (fixed barycentric coordinates
    in one triangle, so the anchor moves with that cloth), and keeps its source offset ``o_i`` from it in the
    triangle's orthonormal frame ``F_i`` (edge, in-plane normal to it, unit normal). Invariant to rigid
    motions of the garment as a whole; zero at the source shape. Lumped source vertex areas ``A_i``,
    normalised by ``ell`` (the fit's length) as the fit term is: one ell of slide costs like a unit
    distortion of the same area. Per-vertex 12 x 12 Gauss-Newton Hessians over the vertex and its anchor
    triangle.

    Args:
        source_vertices: (N, 3) source garment; faces: (F, 3) long; max_distance: see :func:`layer_anchors`.
        length: ell > 0 (units of the vertices). weight: the term's weight.

    Attributes:
        vertices: (K,) attached vertices. anchors: (K, 3) their anchor triangles.
    """

    name = "attach"

    def __init__(
        self,
        source_vertices: torch.Tensor,
        faces: torch.Tensor,
        max_distance: float,
        length: float,
        weight: float = 1.0,
    ) -> None:
        super().__init__(weight)
        if not (math.isfinite(max_distance) and max_distance >= 0 and length > 0):
            raise InputError(f"attachment: max_distance must be >= 0 and length > 0, got {max_distance}, "
                             f"{length}")
        vs = source_vertices.detach()
        dev, dt = vs.device, vs.dtype
        idx, tri, bary = layer_anchors(vs, faces, max_distance)
        idx, tri, bary = idx.to(dev), tri.to(dev), bary.to(device=dev, dtype=dt)
        p = vs[tri]  # (K, 3, 3)
        anchor = (bary[:, :, None] * p).sum(1)
        frame = _tri_frame(p[:, 0], p[:, 1], p[:, 2])
        offset = (frame.transpose(-1, -2) @ (vs[idx] - anchor)[..., None])[..., 0]  # (K, 3) in the frame
        self.register_buffer("vertices", idx)
        self.register_buffer("anchors", tri)
        self.register_buffer("consts", torch.cat([bary, offset], dim=1))
        self.register_buffer("weights", vertex_areas(vs, faces)[idx] / length**2)

    def _z(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([x[self.vertices][:, None], x[self.anchors]], dim=1).reshape(-1, 12)

    def residuals(self, x: torch.Tensor) -> torch.Tensor:
        """(K, 3) each attached vertex's miss of its place on the piece under it (units of ``x``)."""
        return _attach_residual(self._z(x), self.consts)

    def energy(self, x: torch.Tensor, t: torch.Tensor | None = None) -> torch.Tensor:  # noqa: D102
        if len(self.vertices) == 0:
            return x.sum() * 0.0
        r = self.residuals(x)
        return (self.weights * (r * r).sum(-1)).sum()

    def unweighted_blocks(
        self, x: torch.Tensor, t: torch.Tensor | None = None, project_psd: bool = True
    ) -> HessianBlocks:
        """Gauss-Newton blocks ``2 w J^T J`` over each vertex and its anchor triangle."""
        if len(self.vertices) == 0:
            return _empty_blocks(x)
        h = element_gauss_newton(_attach_residual, self._z(x.detach()), self.weights, self.consts)
        return element_blocks(h, torch.cat([self.vertices[:, None], self.anchors], dim=1))


# ---------------------------------------------------------------------------------------------- L_fit


class Fit(RetargetEnergy):
    """L_fit = sum over fit vertices of A_i ((D(x_i) - g_i) / ell)^2, D the avatar's signed distance.

    The integral of eq. 4 with lumped source vertex areas ``A_i``; divided by ``ell^2`` (``fit_length``, 1 cm
    at human scale by default in the pipeline) so that the weight reads as "one ell of gap costs like a unit
    distortion of the same area". The target gap ``g_i`` is ``offset`` (the pipeline uses dhat), or with
    ``source_gap`` the vertex's own gap on the source avatar when that is larger. ``offset`` puts the fit's
    optimum just outside the barrier's activation distance instead of on the avatar surface (the paper's D^2),
    so that the fit does not push the garment into the barrier (the visible difference is dhat, 2 mm at
    human scale); ``source_gap`` keeps the source's tightness (the paper's aim for the term, section 3.4.4):
    loose parts stay loose, and a layer (a pocket over a shirt) keeps its height above the cloth under it
    instead of being pulled onto it.
    Gauss-Newton Hessian ``2 A_i / ell^2 grad D grad D^T`` (PSD).

    Args:
        sdf: a callable with ``value_and_gradient(x) -> (D (K,), grad (K, 3))`` and differentiable ``sdf(x)``
            (a :class:`~torchgarment.sdf.grid.BodySDF`).
        source_vertices: (N, 3); faces: (F, 3) long; mask: (N,) bool fit vertices; fit_length: ell > 0.
        offset: the smallest target gap (>= 0). weight: the term's weight.
        source_gap: optional (N,) each vertex's distance to the source avatar (the pipeline's
            ``fit_target="source-gap"``); None targets ``offset`` everywhere.

    Attributes:
        targets: (K,) the fit vertices' target gaps ``g_i``.
    """

    name = "fit"

    def __init__(
        self,
        sdf: nn.Module,
        source_vertices: torch.Tensor,
        faces: torch.Tensor,
        mask: torch.Tensor,
        fit_length: float,
        offset: float = 0.0,
        weight: float = 1.0,
        source_gap: torch.Tensor | None = None,
    ) -> None:
        super().__init__(weight)
        if not fit_length > 0:
            raise InputError(f"fit_length must be positive, got {fit_length}")
        if not (math.isfinite(offset) and offset >= 0):
            raise InputError(f"fit offset must be >= 0, got {offset}")
        self.offset = float(offset)
        self.sdf = sdf
        idx = torch.nonzero(mask.to(torch.bool), as_tuple=False).reshape(-1)
        self.register_buffer("vertices", idx)
        self.register_buffer("weights", vertex_areas(source_vertices.detach(), faces)[idx] / fit_length**2)
        targets = torch.full((idx.numel(),), self.offset, dtype=source_vertices.dtype,
                             device=source_vertices.device)
        if source_gap is not None:
            n = source_vertices.shape[0]
            if source_gap.shape != (n,) or not bool(torch.isfinite(source_gap).all()):
                raise InputError(f"source_gap must be a finite ({n},) tensor, got {tuple(source_gap.shape)}")
            targets = torch.maximum(targets, source_gap.detach().to(targets)[idx])
        self.register_buffer("targets", targets)

    def energy(self, x: torch.Tensor, t: torch.Tensor | None = None) -> torch.Tensor:  # noqa: D102
        if len(self.vertices) == 0:
            return x.sum() * 0.0
        d = self.sdf(x[self.vertices].to(self.sdf.dtype)).to(x.dtype) - self.targets.to(x.dtype)
        return (self.weights * d * d).sum()

    def unweighted_blocks(
        self, x: torch.Tensor, t: torch.Tensor | None = None, project_psd: bool = True
    ) -> HessianBlocks:
        """Gauss-Newton 3 x 3 vertex blocks ``2 A_i / ell^2 grad D grad D^T``."""
        if len(self.vertices) == 0:
            return _empty_blocks(x)
        _, g = self.sdf.value_and_gradient(x.detach()[self.vertices].to(self.sdf.dtype))
        g = g.to(x.dtype)
        h = 2.0 * self.weights[:, None, None] * g[:, :, None] * g[:, None, :]
        return element_blocks(h, self.vertices[:, None])


# ---------------------------------------------------------------------------------------------- L_curve


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True)


def _curvature(z: torch.Tensor) -> torch.Tensor:
    """(T,) alpha = -e_{i-1}^ . e_i^ of vertex triples z (T, 9)."""
    v = z.reshape(-1, 3, 3)
    return -(_unit(v[:, 1] - v[:, 0]) * _unit(v[:, 2] - v[:, 1])).sum(-1)


def _torsion(z: torch.Tensor) -> torch.Tensor:
    """(Q, 2) (beta, gamma) of vertex quadruples z (Q, 12): edges e_{i-1}, e_i, e_{i+1}."""
    v = z.reshape(-1, 4, 3)
    ep, ei, en = _unit(v[:, 1] - v[:, 0]), _unit(v[:, 2] - v[:, 1]), _unit(v[:, 3] - v[:, 2])
    pn = en - (ei * en).sum(-1, keepdim=True) * ei
    pp = -ep + (ei * ep).sum(-1, keepdim=True) * ei
    beta = (pn * pp).sum(-1)
    gamma = (torch.linalg.cross(pn, pp, dim=-1) * ei).sum(-1)
    return torch.stack([beta, gamma], dim=-1)


def _curv_res(z: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return _curvature(z) - target


def _tors_res(z: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return _torsion(z) - target


def polyline_elements(curves: list[np.ndarray], closed: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Vertex triples (curvature) and quadruples (torsion) of polylines.

    With ``closed`` every curve is a loop (a repeated first index at the end is dropped); otherwise open
    polylines (curvature at interior vertices, torsion at interior edges).

    Returns:
        (T, 3) int64 triples and (Q, 4) int64 quadruples.
    """
    tri, quad = [], []
    for c in curves:
        c = np.asarray(c, dtype=np.int64).reshape(-1)
        if closed and c.shape[0] > 3 and c[0] == c[-1]:
            c = c[:-1]
        m = c.shape[0]
        if m < 3:
            continue
        if closed:
            i = np.arange(m)
            tri.append(np.stack([c[(i - 1) % m], c[i], c[(i + 1) % m]], 1))
            if m >= 4:
                quad.append(np.stack([c[(i - 1) % m], c[i], c[(i + 1) % m], c[(i + 2) % m]], 1))
        else:
            tri.append(np.stack([c[:-2], c[1:-1], c[2:]], 1))
            if m >= 4:
                quad.append(np.stack([c[:-3], c[1:-2], c[2:-1], c[3:]], 1))
    t = np.concatenate(tri) if tri else np.zeros((0, 3), np.int64)
    q = np.concatenate(quad) if quad else np.zeros((0, 4), np.int64)
    return t, q


class CurveShape(RetargetEnergy):
    """L_curve = L_curvature + L_torsion over closed loops (boundaries) and extra curves.

    Curvature ``alpha_i = -e^_{i-1} . e^_i`` per vertex, torsion ``(beta_i, gamma_i)`` per edge (the paper's
    projected-edge dot and triple products), each compared with the source value and weighted by the mean
    source length of the adjacent edges. Invariant to rotation, translation and uniform scale; not to
    anisotropic scale.

    Args:
        source_vertices: (N, 3); curves: vertex index arrays (loops; a repeated first index is dropped).
        closed: treat the curves as closed loops (the paper's boundaries and seam loops) or open polylines.
        weight: the term's weight.
    """

    name = "curve"

    def __init__(
        self, source_vertices: torch.Tensor, curves: list, closed: bool = True, weight: float = 1.0
    ) -> None:
        super().__init__(weight)
        vs = source_vertices.detach()
        n = vs.shape[0]
        cs = []
        for c in curves:
            a = np.asarray(c.cpu() if isinstance(c, torch.Tensor) else c, dtype=np.int64).reshape(-1)
            if a.size and (a.min() < 0 or a.max() >= n):
                raise InputError(f"a curve indexes vertices outside [0, {n})")
            cs.append(a)
        tri, quad = polyline_elements(cs, closed)
        dev = vs.device
        tri_t = torch.as_tensor(tri, device=dev)
        quad_t = torch.as_tensor(quad, device=dev)
        for name, e in (("triples", tri_t), ("quads", quad_t)):
            self.register_buffer(name, e)
        seg = lambda i, j: (vs[j] - vs[i]).norm(dim=-1)  # noqa: E731
        if len(tri_t) and bool(
            (seg(tri_t[:, 0], tri_t[:, 1]) <= 0).any() | (seg(tri_t[:, 1], tri_t[:, 2]) <= 0).any()
        ):
            raise InputError("a curve has two consecutive coincident vertices")
        wt = (
            0.5 * (seg(tri_t[:, 0], tri_t[:, 1]) + seg(tri_t[:, 1], tri_t[:, 2]))
            if len(tri_t)
            else vs.new_zeros(0)
        )
        wq = (
            0.5 * (seg(quad_t[:, 0], quad_t[:, 1]) + seg(quad_t[:, 1], quad_t[:, 2]))
            if len(quad_t)
            else vs.new_zeros(0)
        )
        self.register_buffer("w_curv", wt)
        self.register_buffer("w_tors", wq)
        self.register_buffer(
            "alpha_s", _curvature(vs[tri_t].reshape(-1, 9)) if len(tri_t) else vs.new_zeros(0)
        )
        self.register_buffer(
            "bg_s", _torsion(vs[quad_t].reshape(-1, 12)) if len(quad_t) else vs.new_zeros(0, 2)
        )

    def energy(self, x: torch.Tensor, t: torch.Tensor | None = None) -> torch.Tensor:  # noqa: D102
        e = x.sum() * 0.0
        if len(self.triples):
            a = _curvature(x[self.triples].reshape(-1, 9))
            e = e + (self.w_curv * (a - self.alpha_s) ** 2).sum()
        if len(self.quads):
            bg = _torsion(x[self.quads].reshape(-1, 12))
            e = e + (self.w_tors[:, None] * (bg - self.bg_s) ** 2).sum()
        return e

    def unweighted_blocks(
        self, x: torch.Tensor, t: torch.Tensor | None = None, project_psd: bool = True
    ) -> HessianBlocks:
        """Gauss-Newton blocks of the curvature triples and the torsion quadruples."""
        xd = x.detach()
        parts = [_empty_blocks(x)]
        if len(self.triples):
            hb = element_gauss_newton(_curv_res, xd[self.triples].reshape(-1, 9), self.w_curv, self.alpha_s)
            parts.append(element_blocks(hb, self.triples))
        if len(self.quads):
            hb = element_gauss_newton(_tors_res, xd[self.quads].reshape(-1, 12), self.w_tors, self.bg_s)
            parts.append(element_blocks(hb, self.quads))
        return HessianBlocks.cat(parts)


# ---------------------------------------------------------------------------------------------- L_contact


class _ContactFn(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx: torch.autograd.function.FunctionCtx,
        x: torch.Tensor,
        t: torch.Tensor,  # noqa: D102
        ipc: MovingObstacleContact,
    ) -> torch.Tensor:
        e, gx, gt = ipc.value_grad(x, float(t.detach()))
        ctx.save_for_backward(
            torch.as_tensor(gx, dtype=x.dtype, device=x.device),
            torch.as_tensor(gt, dtype=x.dtype, device=x.device),
        )
        return torch.as_tensor(e, dtype=x.dtype, device=x.device)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(
        ctx: torch.autograd.function.FunctionCtx,  # noqa: D102
        g: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, None]:
        gx, gt = ctx.saved_tensors
        return g * gx, g * gt, None


class Contact(RetargetEnergy):
    """L_contact: IPC barrier over garment-self and garment-avatar pairs, the avatar ``shrunk + t (full -
    shrunk)``.

    The term wraps a :class:`~torchgarment.sim.contact.MovingObstacleContact` (:attr:`ipc`: the collision
    mesh, culling, CCD step bound, stiffness, intersection and distance queries). ipctk evaluates the barrier
    on squared distances, ``b = -(d^2 - dhat^2)^2 ln(d^2 / dhat^2)`` (the IPC convention), a monotone
    reparametrisation of the paper's ``-(d - dhat)^2 ln(d / dhat)`` with the same support (0, dhat) and the
    same blow-up at 0; the adaptive stiffness absorbs the different scale. With ``avatar_shrunk`` None the
    avatar is fixed at ``full`` (Step 3, multi-layer).

    Args:
        garment_rest: (N, 3) garment rest positions (adjacency). garment_faces: (F, 3) long.
        avatar_full: (A, 3) avatar at t = 1. avatar_faces: (G, 3) long. avatar_shrunk: (A, 3) at t = 0 or
            None.
        dhat: activation distance. stiffness: initial kappa.
        broad_phase: :class:`~torchgarment.sim.contact.BroadPhase` or an ipctk class name ("LBVH", ...).
        cull_radius: see :class:`~torchgarment.sim.contact.MovingObstacleContact`.
    """

    name = "contact"
    volatile_hessian = True

    def __init__(
        self,
        garment_rest: torch.Tensor,
        garment_faces: torch.Tensor,
        avatar_full: torch.Tensor,
        avatar_faces: torch.Tensor,
        avatar_shrunk: torch.Tensor | None,
        dhat: float,
        stiffness: float = 1.0,
        broad_phase: BroadPhase | str = BroadPhase.LBVH,
        cull_radius: float | None = None,
    ) -> None:
        super().__init__(1.0)
        self.ipc = MovingObstacleContact(
            garment_rest,
            garment_faces,
            avatar_full,
            avatar_faces,
            avatar_shrunk,
            dhat,
            stiffness=stiffness,
            broad_phase=broad_phase,
            cull_radius=cull_radius,
        )
        self.uses_t = self.ipc.uses_t

    @property
    def stiffness(self) -> float:
        """The barrier stiffness kappa of :attr:`ipc`."""
        return self.ipc.stiffness

    def energy(self, x: torch.Tensor, t: torch.Tensor | float) -> torch.Tensor:  # noqa: D102
        t = _t_tensor(t, x)
        if torch.is_grad_enabled() and (x.requires_grad or t.requires_grad):
            return _ContactFn.apply(x, t, self.ipc)
        return torch.as_tensor(self.ipc.value(x, float(t)), dtype=x.dtype, device=x.device)

    def unweighted_blocks(
        self, x: torch.Tensor, t: torch.Tensor | float, project_psd: bool = True
    ) -> HessianBlocks:
        """ipctk's per-pair (PSD-clamped when ``project_psd``) Hessian chained to (x, t) as vertex blocks."""
        hxx, hxt, htt = self.ipc.hessian(x, float(t), project_psd)
        n = self.ipc.num_garment
        dev, dt = x.device, x.dtype
        h = hxx.tobsr(blocksize=(3, 3))
        rows = np.repeat(np.arange(n), np.diff(h.indptr))
        parts = [
            HessianBlocks(
                torch.as_tensor(rows, dtype=torch.long, device=dev),
                torch.as_tensor(h.indices.astype(np.int64), device=dev),
                torch.as_tensor(h.data, dtype=dt, device=dev).reshape(-1, 3, 3),
            )
        ]
        if self.uses_t:
            col = hxt.reshape(-1, 3)
            vi = np.nonzero(np.any(col != 0.0, axis=1))[0]
            bxt = np.zeros((vi.shape[0], 3, 3))
            bxt[:, :, 0] = col[vi]
            vt = torch.as_tensor(vi, dtype=torch.long, device=dev)
            last = torch.full_like(vt, n)
            btt = np.zeros((1, 3, 3))
            btt[0, 0, 0] = htt
            parts += [
                HessianBlocks(vt, last, torch.as_tensor(bxt, dtype=dt, device=dev)),
                HessianBlocks(last, vt, torch.as_tensor(bxt.transpose(0, 2, 1).copy(), dtype=dt, device=dev)),
                HessianBlocks(
                    torch.tensor([n], device=dev),
                    torch.tensor([n], device=dev),
                    torch.as_tensor(btt, dtype=dt, device=dev),
                ),
            ]
        return HessianBlocks.cat(parts)
