"""Quadratic bending (Bergou et al. 2006, "A quadratic bending model for inextensible surfaces").

For every hinge (an edge ``x0 x1`` shared by the triangles ``(x0, x1, x2)`` and ``(x0, x1, x3)``) the discrete
mean-curvature vector is a fixed linear combination of the four positions with cotangent weights of the REST
triangles::

    K x = (cot a1 + cot b1) x0 + (cot a0 + cot b0) x1 - (cot a0 + cot a1) x2 - (cot b0 + cot b1) x3

(``a0, a1``: rest angles at ``x0, x1`` in the first triangle, ``b0, b1`` in the second). It vanishes on flat
(affine) configurations, and for a small fold of angle ``t`` its length is about ``|e| t``. The energy is::

    E = k / 2 * sum_h c / (A0 + A1) * |K_h x|^2  =  k / 2 * x^T Q x     (per coordinate),   c = 8 / 9

with ``k`` the bending stiffness in N m (joules). Bergou et al. use ``c = 3``; for a fold ``t`` across an edge
``e`` between triangles of heights ``h`` the dihedral is about ``kappa_n h``, and averaging over the edge
directions of an isotropic (near-equilateral) mesh, ``c = 3`` gives ``27/8 * integral of (2H)^2 dA`` for
isometric bending. ``c = 8 / 9`` rescales it so that ``E ~ k / 2 * integral of (2H)^2 dA`` (a cylinder of
radius R: ``k / 2 * area / R^2``; checked in the tests to a few per cent on Triangle meshes; a regular
right-triangle grid gives about 0.9 of it). ``Q`` is constant and PSD (a sum of squares), so the gradient is
``k Q x`` and the Hessian ``k Q (x) I_3``, both exact. The model assumes a flat rest state (zero rest
dihedral angles), which a sewing pattern has.

Rest geometry: the cotangents and areas come from the 2D pattern ``p`` of each triangle when the mesh has one
(every triangle lies in one panel), else from the 3D positions ``x`` (a plain mesh is then treated as if
its rest state were flat). ``Q`` is built once and is not differentiable in ``p``.

Across seams: the hinges are taken from the welded mesh (:meth:`GarmentMesh.welded`), so an edge on a seam
also bends. Its two triangles lie in different panels, whose copies of ``x0`` and ``x1`` are different
vertices; the stencil then has six vertices: the first triangle's weights act on its own copies
``(x0, x1, x2)`` and the second's on ``(x0', x1', x3)``. Each half has weights summing to zero, so the energy
does not depend on how far apart the two panels are (sewing springs close the gap), only on their relative
orientation. Inside a panel the six-vertex stencil is the four-vertex one (the copies coincide).
"""

from __future__ import annotations

import warnings

import torch

from torchgarment.errors import InputError, MeshError
from torchgarment.linalg import compact_csr
from torchgarment.sim.energies.base import EnergyTerm, HessianBlocks
from torchgarment.sim.energies.stretch import check_positions
from torchgarment.structures.garment_mesh import GarmentMesh

DEFAULT_BEND_STIFFNESS = 2.0e-5
"""Default bending stiffness in N m: with 0.15 kg/m^2 the bending length (k / (rho g))^(1/3) is about 2.4 cm,
in the range of light woven cotton."""

HINGE_COEFFICIENT = 8.0 / 9.0
"""``c`` of the hinge weights ``c / (A0 + A1)``: Bergou's 3 times 8/27, so that ``k`` is the continuum bending
stiffness of ``k / 2 * integral of (2H)^2 dA`` on isotropic meshes."""


class QuadraticBending(EnergyTerm):
    """Constant-Hessian bending energy over hinge stencils.

    Attributes:
        stencils: buffer (H, 6) long ``[x0, x1, x2, x0', x1', x3]``.
        weights: buffer (H, 6) cotangent weights (unitless).
        coeffs: buffer (H,) ``c / (A0 + A1)`` in 1/m^2 (``c = 8/9``, see the module docstring).
        stiffness: ``k`` in N m.
        num_vertices: V.
    """

    name = "bend"
    constant_hessian = True

    def __init__(
        self,
        stencils: torch.Tensor,
        weights: torch.Tensor,
        coeffs: torch.Tensor,
        num_vertices: int,
        *,
        stiffness: float = DEFAULT_BEND_STIFFNESS,
    ) -> None:
        """Create the term from hinge stencils (see :meth:`hinge_stencils`).

        Args:
            stencils: (H, n) long vertex indices. weights: (H, n) weights. coeffs: (H,) non-negative factors.
            num_vertices: V. stiffness: ``k`` in N m, > 0.

        Raises:
            InputError: inconsistent shapes, indices out of range, negative coefficients, stiffness <= 0.
        """
        super().__init__()
        if stencils.ndim != 2 or weights.shape != stencils.shape or coeffs.shape != stencils.shape[:1] \
                or stencils.dtype != torch.long:
            raise InputError(f"bending stencils (H, n) long, weights (H, n) and coeffs (H,) must agree, got "
                             f"{tuple(stencils.shape)}, {tuple(weights.shape)}, {tuple(coeffs.shape)}")
        if stencils.numel() and (int(stencils.min()) < 0 or int(stencils.max()) >= num_vertices):
            raise InputError(f"bending stencils index vertices outside [0, {num_vertices})")
        if coeffs.numel() and not bool((coeffs >= 0).all() and torch.isfinite(coeffs).all()
                                       and torch.isfinite(weights).all()):
            raise InputError("bending weights must be finite and coefficients non-negative "
                             "(degenerate rest triangles?)")
        if not stiffness > 0:
            raise InputError(f"bending stiffness must be positive, got {stiffness}")
        self.stiffness = float(stiffness)
        self.num_vertices = int(num_vertices)
        self.register_buffer("stencils", stencils.contiguous())
        self.register_buffer("weights", weights.contiguous())
        self.register_buffer("coeffs", coeffs.contiguous())
        # Q = sum_h c_h w_h w_h^T as a coalesced COO (scalar, V x V)
        n = stencils.shape[1]
        rows = stencils[:, :, None].expand(-1, n, n).reshape(-1)
        cols = stencils[:, None, :].expand(-1, n, n).reshape(-1)
        vals = (coeffs[:, None, None] * weights[:, :, None] * weights[:, None, :]).reshape(-1)
        Q = torch.sparse_coo_tensor(torch.stack([rows, cols]), vals, (num_vertices, num_vertices),
                                    check_invariants=False).coalesce()
        self.register_buffer("q_indices", Q.indices().contiguous())
        self.register_buffer("q_values", Q.values().contiguous())
        diag = torch.zeros(num_vertices, dtype=vals.dtype, device=vals.device)
        on = Q.indices()[0] == Q.indices()[1]
        diag[Q.indices()[0, on]] = Q.values()[on]
        self.register_buffer("q_diagonal", diag)
        self._csr: dict[tuple, torch.Tensor] = {}

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_mesh(
        cls, mesh: GarmentMesh, *, stiffness: float = DEFAULT_BEND_STIFFNESS, across_seams: bool = True
    ) -> "QuadraticBending":
        """Bending over every interior edge of ``mesh`` (and, if ``across_seams``, every seam edge)."""
        stencils, weights, coeffs = cls.hinge_stencils(mesh, across_seams=across_seams)
        return cls(stencils, weights, coeffs, mesh.num_vertices, stiffness=stiffness)

    @staticmethod
    def hinge_stencils(
        mesh: GarmentMesh, *, across_seams: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Six-vertex hinge stencils with cotangent weights from the rest triangles.

        Returns:
            stencils (H, 6) long ``[x0, x1, x2, x0', x1', x3]``, weights (H, 6), coeffs (H,)
            ``c / (A0 + A1)``.

        Raises:
            MeshError: a rest triangle of a hinge is degenerate.
        """
        faces = mesh.faces
        if across_seams and mesh.seam_pairs.shape[0] > 0:
            welded, imap = mesh.welded()
            fw = imap[faces]
            keep = (fw[:, 0] != fw[:, 1]) & (fw[:, 1] != fw[:, 2]) & (fw[:, 0] != fw[:, 2])
            orig_face = torch.nonzero(keep, as_tuple=False).flatten()
            if orig_face.shape[0] != welded.num_faces or not bool((fw[keep] == welded.faces).all()):
                raise MeshError("welded mesh faces do not match the garment faces (unexpected welding order)")
            hw, hf = welded.hinges, welded.hinge_faces
            f0, f1 = faces[orig_face[hf[:, 0]]], faces[orig_face[hf[:, 1]]]

            def pick(f: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
                col = (imap[f] == w[:, None]).to(torch.int8).argmax(dim=1, keepdim=True)
                return f.gather(1, col)[:, 0]

            stencils = torch.stack([pick(f0, hw[:, 0]), pick(f0, hw[:, 1]), pick(f0, hw[:, 2]),
                                    pick(f1, hw[:, 0]), pick(f1, hw[:, 1]), pick(f1, hw[:, 3])], dim=1)
        else:
            h = mesh.hinges
            stencils = torch.stack([h[:, 0], h[:, 1], h[:, 2], h[:, 0], h[:, 1], h[:, 3]], dim=1)
        if mesh.p is not None:
            rest = torch.cat([mesh.p, torch.zeros_like(mesh.p[:, :1])], dim=1)
        else:
            rest = mesh.x
        weights, A0, A1 = hinge_weights(rest.detach(), stencils)
        tiny = torch.finfo(rest.dtype).tiny
        if stencils.shape[0] and bool((torch.minimum(A0, A1) <= tiny).any()):
            raise MeshError("bending: a hinge has a degenerate rest triangle")
        return stencils, weights, HINGE_COEFFICIENT / (A0 + A1)

    # ------------------------------------------------------------------ evaluation
    def _q(self, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
        key = (dtype, device)
        if key not in self._csr:
            V = self.num_vertices
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # "sparse CSR support is in beta"
                coo = torch.sparse_coo_tensor(self.q_indices.to(device),
                                              self.q_values.to(device=device, dtype=dtype),
                                              (V, V), is_coalesced=True)
                self._csr[key] = compact_csr(coo.to_sparse_csr())
        return self._csr[key]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Energy in joules of positions ``x`` (V, 3); differentiable in ``x``."""
        check_positions(x, self.num_vertices, self.name)
        kx = (self.weights.to(x.dtype)[:, :, None] * x[self.stencils]).sum(dim=1)  # (H, 3)
        return 0.5 * self.stiffness * (self.coeffs.to(x.dtype) * (kx * kx).sum(dim=1)).sum()

    def value_and_grad(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Energy () in joules and analytic gradient ``k Q x`` (V, 3) in newtons."""
        check_positions(x, self.num_vertices, self.name)
        x = x.detach()
        qx = self._q(x.dtype, x.device) @ x
        E = 0.5 * self.stiffness * torch.dot(x.reshape(-1), qx.reshape(-1))
        return E, qx.mul_(self.stiffness)

    def hessian_diagonal(self, x: torch.Tensor, project_psd: bool = True) -> torch.Tensor:
        """(V, 3, 3) diagonal blocks ``k Q_ii I`` (constant, PSD)."""
        check_positions(x, self.num_vertices, self.name)
        d = (self.stiffness * self.q_diagonal).to(x.dtype)
        return d[:, None, None] * torch.eye(3, dtype=x.dtype, device=x.device)

    def hessian_blocks(self, x: torch.Tensor, project_psd: bool = True) -> HessianBlocks:
        """Block-COO Hessian ``k Q_ij I`` over the nonzeros of ``Q`` (constant, PSD)."""
        check_positions(x, self.num_vertices, self.name)
        v = (self.stiffness * self.q_values).to(x.dtype)
        return HessianBlocks(self.q_indices[0], self.q_indices[1],
                             v[:, None, None] * torch.eye(3, dtype=x.dtype, device=x.device))

    def extra_repr(self) -> str:
        return f"hinges={self.stencils.shape[0]}, stiffness={self.stiffness} N m"


def hinge_weights(rest: torch.Tensor,
                  stencils: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Bergou et al. 2006 cotangent weights of six-vertex hinge stencils ``[x0, x1, x2, x0', x1', x3]``.

    With ``a0, a1`` the rest angles at ``x0, x1`` of triangle ``(x0, x1, x2)`` and ``b0, b1`` those at ``x0',
    x1'`` of ``(x0', x1', x3)``, the weights are ``[cot a1, cot a0, -(cot a0 + cot a1), cot b1, cot b0,
    -(cot b0 + cot b1)]``; inside a panel (``x0' = x0``, ``x1' = x1``) the four-vertex kernel is
    ``[w0 + w3, w1 + w4, w2, w5]``, which vanishes on every flat (isometric) embedding.

    Args:
        rest: (V, 3) rest positions (metres; a 2D pattern padded with z = 0). stencils: (H, 6) long.

    Returns:
        weights (H, 6) (dimensionless), areas (H,) and (H,) of the two rest triangles (square metres).
    """
    ca0, ca1, A0 = _cotangents(rest[stencils[:, 0]], rest[stencils[:, 1]], rest[stencils[:, 2]])
    cb0, cb1, A1 = _cotangents(rest[stencils[:, 3]], rest[stencils[:, 4]], rest[stencils[:, 5]])
    return torch.stack([ca1, ca0, -(ca0 + ca1), cb1, cb0, -(cb0 + cb1)], dim=1), A0, A1


def _cotangents(a: torch.Tensor, b: torch.Tensor,
                c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Cotangents of the angles at ``a`` and ``b`` of triangles (a, b, c) (each (H, 3)), and their areas."""
    ab, ac, bc = b - a, c - a, c - b
    cross = torch.linalg.vector_norm(torch.linalg.cross(ab, ac, dim=1), dim=1)
    safe = cross.clamp_min(torch.finfo(a.dtype).tiny)
    cot_a = (ab * ac).sum(dim=1) / safe
    cot_b = (-ab * bc).sum(dim=1) / safe
    return cot_a, cot_b, 0.5 * cross
