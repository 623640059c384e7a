"""Cost functions of pattern adjustment (Wang et al. 2018, section 6, Eq. 11-16).

Every cost is an ``nn.Module`` with ``forward(x, p)`` -> scalar, where ``x`` (V, 3) is the garment on the
target body (metres) and ``p`` (V, 2) the pattern (metres); autograd gives ``df/dx`` and ``df/dp``. Each
holds its coefficient ``weight`` (``δ`` of the paper, 1/m^2) and is a least-squares sum::

    forward(x, p) = weight / 2 * |residuals(x, p)|^2

(:meth:`residuals` is exposed for Gauss-Newton). The reference quantities of the base garment ``x̄`` draped
on the base body and of the base pattern ``p̄`` are computed once at construction.
"""

from __future__ import annotations

import math
import warnings

import torch

from torchgarment.adjust.linear_map import StoredTransposeMatmul
from torchgarment.errors import InputError
from torchgarment.structures.garment_mesh import GarmentMesh

_NORM_EPS2 = 1e-24
"""Added under square roots of vector norms (m^2) so their gradients stay finite at zero."""


def _norm(v: torch.Tensor) -> torch.Tensor:
    return (v.pow(2).sum(-1) + _NORM_EPS2).sqrt()


def _csr(indptr: torch.Tensor, indices: torch.Tensor, values: torch.Tensor,
         shape: tuple[int, int]) -> torch.Tensor:
    with warnings.catch_warnings():  # "sparse CSR support is in beta"
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(indptr, indices, values, size=shape, check_invariants=False)


class SparseRows(torch.nn.Module):
    """A constant sparse linear map ``y = A x`` (R, V) with a fixed number ``k`` of entries per row.

    Built from ``cols`` (R, k) long and ``vals`` (R, k); applied to (V, d) tensors. Faster than gathering
    ``x[cols]`` on the CPU because the backward pass is a CSR product with the stored transpose instead of
    an index scatter.
    """

    A: torch.Tensor
    AT: torch.Tensor

    def __init__(self, cols: torch.Tensor, vals: torch.Tensor, num_columns: int) -> None:
        super().__init__()
        R, k = cols.shape
        dev = cols.device
        rows = torch.arange(R, device=dev).repeat_interleave(k)
        c = cols.reshape(-1)
        v = vals.reshape(-1)
        self.register_buffer("A", _csr(torch.arange(0, R * k + 1, k, device=dev), c, v, (R, num_columns)),
                             persistent=False)
        order = torch.argsort(c * R + rows)
        counts = torch.bincount(c, minlength=num_columns)
        indptr = torch.cat([torch.zeros(1, dtype=torch.long, device=dev), torch.cumsum(counts, 0)])
        self.register_buffer("AT", _csr(indptr, rows[order], v[order], (num_columns, R)), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(R, d) ``A x`` for ``x`` (V, d)."""
        A, AT = self.A, self.AT
        if A.dtype != x.dtype:
            A, AT = A.to(x.dtype), AT.to(x.dtype)
        return StoredTransposeMatmul.apply(x, A, AT)


def _check(x: torch.Tensor, p: torch.Tensor | None, V: int, who: str) -> None:
    if x.ndim != 2 or x.shape != (V, 3):
        raise InputError(f"{who}: x must be ({V}, 3), got {tuple(x.shape)}")
    if p is not None and (p.ndim != 2 or p.shape != (V, 2)):
        raise InputError(f"{who}: p must be ({V}, 2), got {tuple(p.shape)}")


class _LeastSquaresCost(torch.nn.Module):
    """Base: ``forward = weight / 2 * |residuals|^2``."""

    def __init__(self, weight: float) -> None:
        super().__init__()
        self.weight = float(weight)

    def residuals(self, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def forward(self, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """Value () of the weighted cost for garment ``x`` (V, 3) and pattern ``p`` (V, 2)."""
        return 0.5 * self.weight * self.residuals(x, p).pow(2).sum()


class DistanceCost(_LeastSquaresCost):
    """Eq. 11: ``C_dis = weight / 2 * sum_i (phi(x_i) - phī(x̄_i))^2`` (looseness per vertex).

    Attributes:
        sdf: the target body's signed distance module (``sdf(x) -> (V,)``, differentiable in ``x``).
        base_distance: buffer (V,), ``phī(x̄_i)`` of the base garment on the base body (metres).
    """

    base_distance: torch.Tensor

    def __init__(self, target_sdf: torch.nn.Module, base_distance: torch.Tensor, weight: float = 1.0) -> None:
        """Args: target_sdf: SDF of the target body. base_distance: (V,) base looseness. weight: ``δ_dis``."""
        super().__init__(weight)
        if base_distance.ndim != 1:
            raise InputError(f"base_distance must be (V,), got {tuple(base_distance.shape)}")
        self.sdf = target_sdf
        self.register_buffer("base_distance", base_distance.detach().clone())

    @classmethod
    def from_garment(cls, x_base: torch.Tensor, base_sdf: torch.nn.Module, target_sdf: torch.nn.Module,
                     weight: float = 1.0, scale: float = 1.0) -> "DistanceCost":
        """The cost with ``phī(x̄)`` sampled from ``base_sdf`` at the base garment ``x_base`` (V, 3), times
        ``scale`` (the fit scale, :func:`~torchgarment.adjust.fit.fit_scale`: the looseness kept in
        proportion to the body's height; 1 keeps it as measured)."""
        if not (math.isfinite(scale) and scale > 0):
            raise InputError(f"DistanceCost: scale must be a positive number, got {scale}")
        with torch.no_grad():
            phi = base_sdf(x_base.to(dtype=_sdf_dtype(base_sdf, x_base)))
        return cls(target_sdf, phi.to(x_base.dtype) * scale, weight)

    def residuals(self, x: torch.Tensor, p: torch.Tensor | None = None) -> torch.Tensor:
        """(V,) ``phi(x_i) - phī(x̄_i)`` (metres)."""
        _check(x, p, self.base_distance.shape[0], "DistanceCost")
        phi = self.sdf(x.to(_sdf_dtype(self.sdf, x))).to(x.dtype)
        return phi - self.base_distance.to(x.dtype)


def _sdf_dtype(sdf: torch.nn.Module, x: torch.Tensor) -> torch.dtype:
    dt = getattr(sdf, "dtype", None)
    return dt if isinstance(dt, torch.dtype) else x.dtype


def hinge_kernel(p: torch.Tensor, hinges: torch.Tensor) -> torch.Tensor:
    """Bergou et al. 2006 edge kernel ``K`` (H, 4) of hinges ``[v0, v1, v2, v3]`` from the rest pattern.

    With ``α0, α1`` the angles at ``v0, v1`` of triangle ``(v0, v1, v2)`` and ``β0, β1`` those of
    ``(v1, v0, v3)``: ``K = [cot α1 + cot β1, cot α0 + cot β0, -(cot α0 + cot α1), -(cot β0 + cot β1)]``.
    ``sum_k K_k x_k`` vanishes on any flat (isometric) embedding and is ``-|e| (m_A + m_B)`` otherwise, with
    ``m`` the unit in-plane normals of the two triangles pointing away from the edge.

    The same weights as :func:`~torchgarment.sim.energies.bend.hinge_weights` (to 1e-15), computed here in the
    plane with one cross product per angle: calling that function instead changes the cost's rounding, and
    the adjustment runs amplify a 1e-16 change of this constant into objective changes of up to 18 % after 32
    iterations (measured on the README's Table 1), so this formula is kept to keep published results.

    Args:
        p: (V, 2) rest positions (metres). hinges: (H, 4) long.

    Returns:
        (H, 4) dimensionless constants.
    """

    def cot(o: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:  # angle at o
        u, v = a - o, b - o
        cross = (u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]).abs()
        return (u * v).sum(-1) / cross

    x0, x1, x2, x3 = (p[hinges[:, k]] for k in range(4))
    ca0, ca1 = cot(x0, x1, x2), cot(x1, x0, x2)
    cb0, cb1 = cot(x0, x1, x3), cot(x1, x0, x3)
    return torch.stack([ca1 + cb1, ca0 + cb0, -(ca0 + ca1), -(cb0 + cb1)], dim=1)


def _hinge_normals(x: torch.Tensor, hinges: torch.Tensor) -> torch.Tensor:
    """(H, 3) average of the two unit triangle normals of every hinge."""
    x0, x1, x2, x3 = (x[hinges[:, k]] for k in range(4))
    na = torch.linalg.cross(x1 - x0, x2 - x0, dim=-1)
    nb = torch.linalg.cross(x0 - x1, x3 - x1, dim=-1)
    return 0.5 * (na / _norm(na)[:, None] + nb / _norm(nb)[:, None])


class SmoothnessCost(_LeastSquaresCost):
    """Eq. 12-13: ``C_smo = weight / 2 * sum_e (|L_e x| - s_e |L_e x̄|)^2`` over the hinge edges.

    ``L_e x = sum_k K_ek x_ek`` with the Bergou kernel :func:`hinge_kernel` of the base pattern ``p̄`` (a
    constant, as in the paper), ``s_e = sign((L_e x . n_e)(L_e x̄ . n̄_e))`` (+1 when both are convex or both
    concave; piecewise constant, treated as a constant in the gradient; +1 at a zero product), ``n_e`` the
    average of the two triangle normals. Hinges only exist inside panels (seams are springs, not edges).

    Attributes:
        hinges: buffer (H, 4) long. kernel: buffer (H, 4). base_norm: buffer (H,), ``|L_e x̄|``.
        base_sign: buffer (H,), ``sign(L_e x̄ . n̄_e)``.
    """

    hinges: torch.Tensor
    kernel: torch.Tensor
    base_norm: torch.Tensor
    base_sign: torch.Tensor
    hinge_faces: torch.Tensor
    faces: torch.Tensor

    def __init__(self, base_mesh: GarmentMesh, weight: float = 1.0) -> None:
        """Args: base_mesh: base pattern ``p`` and base garment ``x`` (on the base body).
        weight: ``δ_smo``."""
        super().__init__(weight)
        if base_mesh.p is None:
            raise InputError("SmoothnessCost needs a pattern mesh (base_mesh.p is None)")
        h = base_mesh.hinges
        K = hinge_kernel(base_mesh.p.detach(), h)
        xb = base_mesh.x.detach()
        lx = (K[:, :, None] * xb[h]).sum(1)
        self.register_buffer("hinges", h.clone())
        self.register_buffer("hinge_faces", base_mesh.hinge_faces.clone())
        self.register_buffer("faces", base_mesh.faces.clone())
        self.register_buffer("kernel", K)
        self.register_buffer("base_norm", _norm(lx))
        self.register_buffer("base_sign", _sign((lx * _hinge_normals(xb, h)).sum(-1)))
        self.num_vertices = base_mesh.num_vertices
        self.operator = SparseRows(h, K, base_mesh.num_vertices)

    def edge_vectors(self, x: torch.Tensor) -> torch.Tensor:
        """(H, 3) ``L_e x`` (metres)."""
        return self.operator(x)

    def hinge_normals(self, x: torch.Tensor) -> torch.Tensor:
        """(H, 3) average of the two unit face normals of every hinge (from per-face normals)."""
        f = self.faces
        n = torch.linalg.cross(x[f[:, 1]] - x[f[:, 0]], x[f[:, 2]] - x[f[:, 0]], dim=-1)
        n = n / _norm(n)[:, None]
        return 0.5 * (n[self.hinge_faces[:, 0]] + n[self.hinge_faces[:, 1]])

    def residuals(self, x: torch.Tensor, p: torch.Tensor | None = None) -> torch.Tensor:
        """(H,) ``|L_e x| - s_e |L_e x̄|`` (metres)."""
        _check(x, p, self.num_vertices, "SmoothnessCost")
        lx = self.edge_vectors(x)
        with torch.no_grad():
            s = _sign((lx * self.hinge_normals(x)).sum(-1)) * self.base_sign.to(x.dtype)
        return _norm(lx) - s * self.base_norm.to(x.dtype)


def _sign(v: torch.Tensor) -> torch.Tensor:
    return torch.where(v < 0, -torch.ones_like(v), torch.ones_like(v))


class StretchingCost(_LeastSquaresCost):
    """Eq. 14: ``C_str = weight / 2 * sum_e (|x_i - x_j| / |p_i - p_j| - |x̄_i - x̄_j| / |p̄_i - p̄_j|)^2``.

    The stretch ratio of every mesh edge on the target body should match its ratio on the base body.

    Attributes:
        edges: buffer (E, 2) long. base_ratio: buffer (E,).
    """

    edges: torch.Tensor
    base_ratio: torch.Tensor

    def __init__(self, base_mesh: GarmentMesh, weight: float = 1.0) -> None:
        """Args: base_mesh: base pattern ``p`` and base garment ``x``. weight: ``δ_str``."""
        super().__init__(weight)
        if base_mesh.p is None:
            raise InputError("StretchingCost needs a pattern mesh (base_mesh.p is None)")
        e = base_mesh.edges
        self.register_buffer("edges", e.clone())
        ones = torch.ones(e.shape[0], 1, dtype=base_mesh.dtype, device=e.device)
        self.difference = SparseRows(e, torch.cat([ones, -ones], 1), base_mesh.num_vertices)
        self.register_buffer("base_ratio", self.ratios(base_mesh.x.detach(), base_mesh.p.detach()))
        self.num_vertices = base_mesh.num_vertices

    def ratios(self, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """(E,) stretch ratios ``|x_i - x_j| / |p_i - p_j|``."""
        return _norm(self.difference(x)) / _norm(self.difference(p))

    def residuals(self, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """(E,) ratio differences (dimensionless)."""
        _check(x, p, self.num_vertices, "StretchingCost")
        return self.ratios(x, p) - self.base_ratio.to(x.dtype)


DEFAULT_BOUNDARY_POSITION_WEIGHT = 4.0
"""``u_i`` of Eq. 16 at pattern-boundary vertices (1 inside); the paper only says "greater"."""


class PositionalCost(_LeastSquaresCost):
    """Eq. 16: ``C_pos = weight / 2 * sum_i u_i |x_i - x̃_i|^2`` with ``x̃`` from Eq. 15 (:mod:`.transfer`).

    Attributes:
        target: buffer (V, 3), the transferred garment ``x̃``. vertex_weight: buffer (V,), ``u_i``.
    """

    target: torch.Tensor
    vertex_weight: torch.Tensor

    def __init__(self, target: torch.Tensor, vertex_weight: torch.Tensor | None = None,
                 weight: float = 1.0) -> None:
        """Args: target: (V, 3) transferred positions. vertex_weight: (V,) ``u_i`` (default 1).
        weight: ``δ_pos``."""
        super().__init__(weight)
        if target.ndim != 2 or target.shape[1] != 3:
            raise InputError(f"target must be (V, 3), got {tuple(target.shape)}")
        u = torch.ones(target.shape[0], dtype=target.dtype, device=target.device) if vertex_weight is None \
            else vertex_weight.detach().to(target.dtype)
        if u.shape != (target.shape[0],) or bool((u < 0).any()):
            raise InputError(f"vertex_weight must be ({target.shape[0]},) and >= 0")
        self.register_buffer("target", target.detach().clone())
        self.register_buffer("vertex_weight", u.clone())

    @classmethod
    def for_mesh(cls, mesh: GarmentMesh, target: torch.Tensor, weight: float = 1.0,
                 boundary_weight: float = DEFAULT_BOUNDARY_POSITION_WEIGHT) -> "PositionalCost":
        """``u_i = boundary_weight`` on the panels' boundary vertices (seams, hems), 1 elsewhere."""
        u = torch.ones(mesh.num_vertices, dtype=target.dtype, device=target.device)
        u[mesh.boundary_edges.reshape(-1).to(target.device)] = float(boundary_weight)
        return cls(target, u, weight)

    def residuals(self, x: torch.Tensor, p: torch.Tensor | None = None) -> torch.Tensor:
        """(V, 3) ``sqrt(u_i) (x_i - x̃_i)`` (metres)."""
        _check(x, p, self.target.shape[0], "PositionalCost")
        return self.vertex_weight.to(x.dtype).sqrt()[:, None] * (x - self.target.to(x.dtype))


class LinePlacementCost(_LeastSquaresCost):
    """Placement of a garment's construction lines (issue 18; not in the paper):
    ``C_place = weight / 2 * sum_l (mean_{i in l} x_i,y - y*_l)^2``.

    Per construction line ``l`` the mean height of its corner vertices against its target height ``y*_l``
    (:func:`torchgarment.adjust.fit.line_targets`: as high above the target body's nearest landmark plane as
    the line sat above the base body's). The transfer of Eq. 15 follows the body's surface, the landmark
    planes do not (they move by 2-3 cm relative to it between chart sizes), so a grader's waist, hip and bust
    lines would follow the surface to the wrong place without it.

    With ``line_weight`` (L,) each line's squared residual is multiplied by its entry: the objective weights a
    line by how much girth a misplacement loses there (see
    :attr:`~torchgarment.adjust.fit.LineTargets.girth_slope`).

    Attributes:
        vertices: buffer (M,) long, the corner vertices of every line.
        line_of: buffer (M,) long, the line of each.
        targets: buffer (L,), ``y*_l`` (metres).
        counts: buffer (L,), the number of corner vertices of each line.
        line_weight: buffer (L,), the lines' relative weights (ones by default).
    """

    vertices: torch.Tensor
    line_of: torch.Tensor
    targets: torch.Tensor
    counts: torch.Tensor
    line_weight: torch.Tensor

    def __init__(self, vertices: torch.Tensor, line_of: torch.Tensor, targets: torch.Tensor,
                 num_vertices: int, weight: float = 1.0, line_weight: torch.Tensor | None = None) -> None:
        """Args: vertices: (M,) corner vertex indices. line_of: (M,) line index in ``[0, L)``. targets: (L,)
        heights (metres). num_vertices: V of the garment. weight: coefficient (1/m^2). line_weight: (L,)
        finite, >= 0 relative weights of the lines (default ones).

        Raises:
            InputError: inconsistent shapes, indices out of range, a line without vertices, or bad line
                weights.
        """
        super().__init__(weight)
        vertices = torch.as_tensor(vertices, dtype=torch.long).reshape(-1)
        line_of = torch.as_tensor(line_of, dtype=torch.long).reshape(-1)
        L = targets.shape[0] if targets.ndim == 1 else -1
        if L < 0 or line_of.shape != vertices.shape:
            raise InputError(f"LinePlacementCost: vertices and line_of must be (M,) and targets (L,), got "
                             f"{tuple(vertices.shape)}, {tuple(line_of.shape)}, {tuple(targets.shape)}")
        if vertices.numel() and (int(vertices.min()) < 0 or int(vertices.max()) >= num_vertices):
            raise InputError(f"LinePlacementCost: vertex indices must be in [0, {num_vertices})")
        if line_of.numel() and (int(line_of.min()) < 0 or int(line_of.max()) >= L):
            raise InputError(f"LinePlacementCost: line indices must be in [0, {L})")
        counts = torch.bincount(line_of, minlength=L)
        if bool((counts == 0).any()):
            raise InputError(f"LinePlacementCost: every one of the {L} lines needs vertices")
        self.num_vertices = int(num_vertices)
        self.register_buffer("vertices", vertices.clone())
        self.register_buffer("line_of", line_of.clone())
        self.register_buffer("targets", targets.detach().clone())
        self.register_buffer("counts", counts.to(targets.dtype))
        lw = torch.ones_like(targets) if line_weight is None else torch.as_tensor(line_weight).to(targets)
        if lw.shape != (L,) or not bool(torch.isfinite(lw).all()) or bool((lw < 0).any()):
            raise InputError(f"LinePlacementCost: line_weight must be ({L},) finite and >= 0")
        self.register_buffer("line_weight", lw.detach().clone())

    def heights(self, x: torch.Tensor) -> torch.Tensor:
        """(L,) each line's mean corner height (metres) in the garment ``x`` (V, 3)."""
        _check(x, None, self.num_vertices, "LinePlacementCost")
        s = torch.zeros(self.targets.shape[0], dtype=x.dtype, device=x.device)
        return s.index_add(0, self.line_of, x[self.vertices, 1]) / self.counts.to(x.dtype)

    def residuals(self, x: torch.Tensor, p: torch.Tensor | None = None) -> torch.Tensor:
        """(L,) height minus target (metres), times the square root of the line's weight."""
        _check(x, p, self.num_vertices, "LinePlacementCost")
        return (self.heights(x) - self.targets.to(x.dtype)) * self.line_weight.to(x.dtype).sqrt()
