"""The :class:`BodySDF` module: a sparse narrow-band signed distance grid sampled by trilinear interpolation.

See :mod:`torchgarment.sdf.build` for the layout. Sampling rules for a query point ``x`` (metres):

* inside the grid box, in an allocated brick: trilinear interpolation of the fine nodes (voxel ``h``);
  exact up to interpolation error wherever ``|phi| <= band``;
* inside the grid box, elsewhere: trilinear interpolation of the coarse nodes (spacing ``brick * h``).
  The sign is right (``band`` is at least the interpolation error bound ``sqrt(3)/2 * (brick + 1) * h``);
  the magnitude is within that bound of the true distance;
* outside the grid box (at least ``band + brick * h`` away from the mesh): ``phi(p) + |x - p|`` where ``p``
  is the projection of ``x`` onto the box, a continuous upper estimate with a nonzero gradient.

The interpolant is continuous everywhere; its gradient is piecewise smooth (it jumps across cell faces).

:class:`SDFSampling` ``QUADRATIC`` (see :meth:`BodySDF.with_sampling`) instead returns the trilinear
interpolant box-filtered over one voxel, ``phi_q(x) = mean of phi over the cube x + [-h/2, h/2]^3``: the
triquadratic B-spline of the node values, continuously differentiable (C1) inside the fine bricks, so that a
barrier built on it has a continuous force. It is evaluated exactly with 8 trilinear samples (the midpoint
rule on the two linear pieces per axis) and its gradient is the exact derivative of that formula; it keeps the
trilinear Lipschitz bound (an average of a Lipschitz function) and is exact where ``phi`` is linear (flat
parts of the body).
"""

from __future__ import annotations

import copy
import os
import zipfile
from typing import TYPE_CHECKING

import numpy as np
import torch

from torchgarment.errors import InputError
from torchgarment.io.atomic import atomic_path
from torchgarment.options import OptionEnum
from torchgarment.sdf import grid_kernels
from torchgarment.sdf.build import SDFGridData, SDFSettings, build_sdf_grid, check_mesh

if TYPE_CHECKING:
    from torch.autograd.function import FunctionCtx

if TYPE_CHECKING:  # pragma: no cover
    from torchgarment.body.body import Body

_FORMAT_VERSION = 1

class SDFSampling(OptionEnum):
    """How :class:`BodySDF` interpolates its nodes.

    ``TRILINEAR``: C0, gradient jumps across voxel faces (cheapest: one 8-corner gather per point).
    ``QUADRATIC``: the trilinear interpolant box-filtered over one voxel (triquadratic B-spline of the nodes),
    C1 in the fine bricks; 8 trilinear samples per point.
    """

    TRILINEAR = "trilinear"
    QUADRATIC = "quadratic"


_BLOCK = 32768
"""Points per block of a query (see :meth:`BodySDF._query`)."""

# Corner c of a cell is (c >> 2 & 1, c >> 1 & 1, c & 1): node offset i * (B+1)^2 + j * (B+1) + k in a brick.
_CORNERS = [(i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1)]


def _block_values(values: np.ndarray, blocks: np.ndarray, n: int) -> np.ndarray:
    """Gather the ``n**3`` nodes of each block of a dense node array.

    Args:
        values: (m0, m1, m2) node values.
        blocks: (S, 3) int64 index of the first node of each block.
        n: nodes per block edge.

    Returns:
        (S, n**3) values in C order of the local node offsets.
    """
    r = np.arange(n)
    loc = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)  # (n^3, 3)
    g = blocks[:, None, :] + loc[None]
    return values[g[..., 0], g[..., 1], g[..., 2]]


def _flat_layout(data: SDFGridData) -> tuple[np.ndarray, np.ndarray, int]:
    """One flat node array in which every cell, fine or coarse, is read with the same 8 corner offsets.

    The fine bricks come first (row ``k`` at ``k * (B+1)^3``). The coarse grid follows, cut into "coarse
    bricks" of ``B^3`` coarse cells stored exactly like fine bricks (``(B+1)^3`` nodes in C order, shared
    faces stored twice, padded by edge values past the grid), so that the corners of a coarse cell are also at
    offsets ``i * (B+1)^2 + j * (B+1) + k`` from its first corner.

    Returns:
        ``(nodes, cell_base, fine_end)``: nodes (L,) float64; cell_base (n0 * n1 * n2,) int64, for every brick
        (= coarse cell) in C order the position in ``nodes`` of its fine node (0, 0, 0) when the brick is
        allocated, else of its coarse corner (0, 0, 0); fine_end = K * (B+1)^3, so the brick is allocated
        exactly where ``cell_base < fine_end``.
    """
    B = int(data.brick)
    Bp3 = (B + 1) ** 3
    nb = np.asarray(data.brick_index.shape, dtype=np.int64)
    K = int(data.bricks.shape[0])
    sb = -(-nb // B)  # coarse bricks per axis
    pad = [(0, int(s * B + 1 - (n + 1))) for s, n in zip(sb, nb)]
    coarse = np.pad(np.asarray(data.coarse, dtype=np.float64), pad, mode="edge")
    sidx = np.stack(np.meshgrid(*[np.arange(s) for s in sb], indexing="ij"), axis=-1).reshape(-1, 3)
    coarse_bricks = _block_values(coarse, sidx * B, B + 1)  # (S, (B+1)^3)
    nodes = np.concatenate([np.asarray(data.bricks, dtype=np.float64).reshape(-1), coarse_bricks.reshape(-1)])

    cells = np.stack(np.meshgrid(*[np.arange(n) for n in nb], indexing="ij"), axis=-1).reshape(-1, 3)
    s_of = cells // B
    s_flat = (s_of[:, 0] * sb[1] + s_of[:, 1]) * sb[2] + s_of[:, 2]
    loc = cells - s_of * B
    fine_end = K * Bp3
    coarse_base = fine_end + s_flat * Bp3 + (loc[:, 0] * (B + 1) + loc[:, 1]) * (B + 1) + loc[:, 2]
    bid = np.asarray(data.brick_index, dtype=np.int64).reshape(-1)
    cell_base = np.where(bid >= 0, bid * Bp3, coarse_base)
    return nodes, cell_base, fine_end


class _Sample(torch.autograd.Function):
    """``phi(x)`` with the analytic gradient of the interpolant as backward (first order only)."""

    @staticmethod
    def forward(ctx: FunctionCtx, x: torch.Tensor, sdf: "BodySDF") -> torch.Tensor:  # type: ignore[override]
        phi, grad = sdf._query(x, with_grad=True)
        ctx.save_for_backward(grad)
        return phi

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: FunctionCtx, grad_phi: torch.Tensor) -> tuple[torch.Tensor, None]:  # type: ignore[override]
        (grad,) = ctx.saved_tensors
        return grad * grad_phi[:, None], None


class BodySDF(torch.nn.Module):
    """Signed distance field of a body (metres, negative inside), sparse narrow band + coarse far field.

    Build with :meth:`from_mesh`, :meth:`from_body` or :meth:`cached` (disk cache); sample with ``sdf(x)``
    (differentiable through autograd, first order) or :meth:`value_and_gradient` (analytic gradient, no
    graph). Buffers move with ``.to(device, dtype)``; queries must be on the SDF's device and are computed in
    the SDF's dtype.

    Sampling cost: one lookup is integer arithmetic, one read of the brick table and ONE gather of the 8
    corner values from the flat node array ``nodes`` (fine bricks and coarse cells share the same corner
    offsets, see :func:`_flat_layout`), then a trilinear interpolation whose gradient reuses the same values.
    The gather is bound by memory latency once the touched bricks exceed the CPU caches (a 2.5 mm body grid
    holds 100 MB in float64, 50 MB in float32), so float32 and spatially coherent queries are the fastest.

    Attributes:
        voxel_size: fine spacing in metres.
        sampling: the :class:`SDFSampling` of queries (``TRILINEAR`` on construction; see
            :meth:`with_sampling`).
        use_kernels: CPU queries run as one Warp kernel each (:mod:`torchgarment.sdf.grid_kernels`: the torch
            path's arithmetic, equal to it within a few units in the last place, several times faster at a
            drape's sizes); False: the torch path.
        brick: brick edge in voxels (coarse spacing is ``brick * voxel_size``).
        band: narrow-band half-width in metres.
        origin: buffer (3,), position of node (0, 0, 0).
        coarse: buffer (n0 + 1, n1 + 1, n2 + 1), coarse node values.
        brick_index: buffer (n0, n1, n2) int64, row of ``bricks`` per brick, -1 where not allocated.
        nodes: buffer (L,), the fine bricks (flattened) followed by the coarse grid cut into bricks.
        bricks: (K, brick + 1, brick + 1, brick + 1) view of the fine node values in ``nodes``.
    """

    origin: torch.Tensor
    coarse: torch.Tensor
    brick_index: torch.Tensor
    nodes: torch.Tensor
    cell_base: torch.Tensor
    corner_offsets: torch.Tensor
    box_min: torch.Tensor
    cell_sizes: torch.Tensor
    box_max: torch.Tensor
    cell_max: torch.Tensor
    brick_strides: torch.Tensor
    node_strides: torch.Tensor
    use_kernels: bool = True  # (a class default: SDFs pickled before the kernels existed load with it)

    def __init__(self, data: SDFGridData, *, device: torch.device | str | None = None,
                 dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        if not dtype.is_floating_point:
            raise InputError(f"BodySDF dtype must be a floating dtype, got {dtype}")
        self.voxel_size = float(data.voxel_size)
        self.sampling = SDFSampling.TRILINEAR
        self.use_kernels = True
        self.brick = int(data.brick)
        self.band = float(data.band)
        self.num_exact = int(data.num_exact)
        self.num_fine_nodes = int(np.asarray(data.bricks).size)
        B, Bp = self.brick, self.brick + 1
        nb = tuple(int(n) for n in np.asarray(data.brick_index).shape)
        nodes, cell_base, fine_end = _flat_layout(data)
        # int32 indices are faster; int64 only for grids of more than 2^31 nodes.
        index_dtype = torch.int32 if nodes.size < 2**31 - 1 else torch.int64
        self._fine_end = fine_end
        kw = dict(device=device, dtype=dtype)
        ik = dict(device=device, dtype=index_dtype)
        self.register_buffer("origin", torch.as_tensor(np.asarray(data.origin), **kw))
        self.register_buffer("coarse", torch.as_tensor(np.asarray(data.coarse), **kw))
        self.register_buffer("brick_index",
                             torch.as_tensor(np.asarray(data.brick_index, dtype=np.int64), device=device))
        self.register_buffer("nodes", torch.as_tensor(nodes, **kw))
        # Derived lookup tables (rebuilt from the data, not part of the state dict).
        self.register_buffer("cell_base", torch.as_tensor(cell_base, **ik), persistent=False)
        offsets = [(i * Bp + j) * Bp + k for i, j, k in _CORNERS]
        self.register_buffer("corner_offsets", torch.tensor(offsets, **ik)[:, None], persistent=False)
        # Per-axis constants as (3, 1) columns for the coordinate-major (3, N) arrays of _query.
        self.register_buffer("box_min", torch.zeros(3, 1, **kw), persistent=False)
        self.register_buffer("box_max", torch.tensor([[n * B] for n in nb], **kw), persistent=False)
        self.register_buffer("cell_max", torch.tensor([[n * B - 1] for n in nb], **ik), persistent=False)
        self.register_buffer("brick_strides", torch.tensor([[nb[1] * nb[2]], [nb[2]], [1]], **ik),
                             persistent=False)
        self.register_buffer("node_strides", torch.tensor([[Bp * Bp], [Bp], [1]], **ik), persistent=False)
        # shifts replace // for 2^k bricks
        self._brick_shift = B.bit_length() - 1 if B & (B - 1) == 0 else None
        self.register_buffer("cell_sizes", torch.tensor([self.voxel_size, B * self.voxel_size], **kw),
                             persistent=False)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_mesh(
        cls,
        vertices: torch.Tensor | np.ndarray,
        faces: torch.Tensor | np.ndarray,
        settings: SDFSettings | None = None,
        *,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> "BodySDF":
        """Build the SDF of a triangle mesh.

        Args:
            vertices: (V, 3) positions in metres.
            faces: (F, 3) vertex indices.
            settings: grid settings (default :class:`SDFSettings()`: 2.5 mm voxels, 2 cm band).
            device: device of the buffers.
            dtype: floating dtype of the buffers and of the queries.

        Raises:
            MeshError: empty mesh or non-finite vertices.
        """
        v = vertices.detach().cpu().numpy() if isinstance(vertices, torch.Tensor) else vertices
        f = faces.detach().cpu().numpy() if isinstance(faces, torch.Tensor) else faces
        v, f = check_mesh(v, f)
        return cls(build_sdf_grid(v, f, settings), device=device, dtype=dtype)

    @classmethod
    def cached(
        cls,
        vertices: torch.Tensor | np.ndarray,
        faces: torch.Tensor | np.ndarray,
        settings: SDFSettings | None = None,
        *,
        cache_dir: str | os.PathLike | None = None,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> "BodySDF":
        """:meth:`from_mesh` through the disk cache (:func:`torchgarment.sdf.cache.cached_sdf`).

        Args:
            vertices: (V, 3) positions in metres.
            faces: (F, 3) vertex indices.
            settings: grid settings (default :class:`SDFSettings()`).
            cache_dir: folder of the entries; default ``$TORCHGARMENT_CACHE/sdf`` or
                ``~/.cache/torchgarment/sdf``.
            device: device of the buffers.
            dtype: floating dtype of the buffers and of the queries.

        Raises:
            MeshError: empty mesh or non-finite vertices.
        """
        from torchgarment.sdf.cache import cached_sdf  # the cache module imports this one

        return cached_sdf(vertices, faces, settings, cache_dir=cache_dir, device=device, dtype=dtype)

    @classmethod
    def from_body(cls, body: "Body", settings: SDFSettings | None = None) -> "BodySDF":
        """Build the SDF of a :class:`~torchgarment.body.body.Body` on the body's device and dtype."""
        return cls.from_mesh(body.vertices, body.faces, settings, device=body.device, dtype=body.dtype)

    # ------------------------------------------------------------------ properties
    @property
    def device(self) -> torch.device:
        return self.nodes.device

    @property
    def dtype(self) -> torch.dtype:
        return self.nodes.dtype

    @property
    def num_bricks(self) -> int:
        return self.num_fine_nodes // (self.brick + 1) ** 3

    @property
    def shape(self) -> tuple[int, int, int]:
        """Number of bricks (= coarse cells) per axis."""
        return tuple(int(n) for n in self.brick_index.shape)

    @property
    def bounds(self) -> torch.Tensor:
        """(2, 3) min and max corners of the grid box in metres."""
        size = torch.tensor(self.shape, device=self.device, dtype=self.dtype) * (self.brick * self.voxel_size)
        return torch.stack([self.origin, self.origin + size])

    @property
    def bricks(self) -> torch.Tensor:
        """(K, brick + 1, brick + 1, brick + 1) fine node values (a view of ``nodes``)."""
        Bp = self.brick + 1
        return self.nodes[: self.num_fine_nodes].view(-1, Bp, Bp, Bp)

    def nbytes(self) -> int:
        """Memory held by the buffers, in bytes."""
        return sum(b.numel() * b.element_size() for b in self.buffers())

    def __getstate__(self) -> dict:
        """The module's state for pickling and deep copies, without the query kernels' Warp arrays and
        recorded launches (:mod:`torchgarment.sdf.grid_kernels`; rebuilt on the next query)."""
        state = super().__getstate__()
        state.pop("_warp_constants", None)
        return state

    def with_sampling(self, sampling: SDFSampling | str) -> "BodySDF":
        """A view of this SDF (sharing every buffer) that interpolates with ``sampling``.

        Raises:
            InputError: unknown sampling.
        """
        sampling = SDFSampling.resolve(sampling)
        view = copy.copy(self)  # shallow: nn.Module dicts are copied below so the two stay independent
        view.__dict__ = dict(self.__dict__)
        for key in ("_parameters", "_buffers", "_modules", "_non_persistent_buffers_set"):
            if key in view.__dict__:
                view.__dict__[key] = copy.copy(self.__dict__[key])
        view.sampling = sampling
        return view

    # ------------------------------------------------------------------ sampling
    def _check(self, x: torch.Tensor) -> torch.Tensor:
        """Validate query points and return them as an (N, 3) tensor in the SDF's dtype."""
        if not isinstance(x, torch.Tensor) or x.shape[-1:] != (3,):
            raise InputError("SDF query points must be a tensor of shape (..., 3), got "
                             f"{getattr(x, 'shape', type(x))}")
        if x.device != self.device:
            raise InputError(f"SDF query points are on {x.device}, the SDF is on {self.device}; move one "
                             "with .to()")
        x = x.reshape(-1, 3).to(self.dtype)
        if not bool(torch.isfinite(x.sum())):  # one reduction; also trips on sums beyond the dtype's range
            raise InputError("SDF query points contain NaN or inf (or coordinates near the dtype's range)")
        return x

    def _query(self, x: torch.Tensor, with_grad: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Interpolated distance (N,) and, when ``with_grad``, its gradient (N, 3) at checked points x (N, 3).

        Large queries run in blocks of ``_BLOCK`` points: the temporaries stay small enough to be cached
        (about 1.5x faster at 100K points than one block). On the CPU one Warp kernel computes the same
        arithmetic instead (:mod:`torchgarment.sdf.grid_kernels`) unless ``use_kernels`` is False.
        """
        if self.use_kernels and grid_kernels.supported(self, x):
            phi, grad = grid_kernels.query(self, x, self.sampling is SDFSampling.QUADRATIC)
            return phi, grad if with_grad else None
        if self.sampling is SDFSampling.QUADRATIC:
            return self._query_quadratic(x, with_grad)
        return self._query_trilinear(x, with_grad)

    def _query_quadratic(self, x: torch.Tensor, with_grad: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        """:meth:`_query` of the box-filtered interpolant (:attr:`SDFSampling.QUADRATIC`).

        Per axis, with ``u = (x - origin) / h = m + s`` (``m`` the nearest node, ``|s| <= 1/2``), the interval
        ``[u - 1/2, u + 1/2]`` holds one breakpoint ``m`` of the piecewise-linear interpolant, so its mean is
        ``(1/2 - s) f((u - 1/2 + m) / 2) + (1/2 + s) f((u + 1/2 + m) / 2)`` exactly; in 3D the tensor product
        of the two-point rules gives 8 trilinear samples. Differentiating that formula (weights and sample
        points both move with ``u``) gives the gradient, consistent with the value everywhere.
        """
        h = self.voxel_size
        u = (x - self.origin) / h  # (N, 3)
        m = torch.floor(u + 0.5)
        s = u - m
        a = torch.stack([(u - 0.5 + m) * 0.5, (u + 0.5 + m) * 0.5])  # (2, N, 3) sample coordinates per axis
        w = torch.stack([0.5 - s, 0.5 + s])  # (2, N, 3) weights per axis
        # The 8 samples: corner c = (i, j, k) takes axis 0 from a[i], axis 1 from a[j], axis 2 from a[k].
        idx = torch.tensor(_CORNERS, device=x.device)  # (8, 3)
        upper = idx[:, None, :].bool()  # (8, 1, 3)
        pts = torch.where(upper, a[1][None], a[0][None])  # (8, N, 3)
        wc = torch.where(upper, w[1][None], w[0][None])  # (8, N, 3)
        n = x.shape[0]
        f, g = self._query_trilinear((pts * h + self.origin).reshape(-1, 3), with_grad)
        f = f.view(8, n)
        wprod = wc.prod(dim=2)  # (8, N)
        phi = (wprod * f).sum(0)
        if not with_grad:
            return phi, None
        g = g.view(8, n, 3)
        sign = (idx * 2 - 1).to(x.dtype)[:, None, :]  # (8, 1, 3): d w / d u = -1 for i = 0, +1 for i = 1
        # d wprod / d u_d = sign_d * product of the other two weights
        others = torch.stack([wc[..., 1] * wc[..., 2], wc[..., 0] * wc[..., 2], wc[..., 0] * wc[..., 1]],
                             dim=2)
        grad = ((sign * others) * f[..., None]).sum(0) / h + 0.5 * (wprod[..., None] * g).sum(0)
        return phi, grad

    def _query_trilinear(self, x: torch.Tensor, with_grad: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        """:meth:`_query` of the trilinear interpolant."""
        n = x.shape[0]
        if n <= _BLOCK:
            phi, grad = self._query_block(x, with_grad)
            return phi, None if grad is None else grad.T.contiguous()
        phi = x.new_empty(n)
        grad = x.new_empty(n, 3) if with_grad else None
        for i in range(0, n, _BLOCK):
            p, g = self._query_block(x[i : i + _BLOCK], with_grad)
            phi[i : i + _BLOCK] = p
            if grad is not None:
                grad[i : i + _BLOCK] = g.T
        return phi, grad

    def _query_block(self, x: torch.Tensor, with_grad: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        """:meth:`_query` on one block; the gradient is returned coordinate-major, (3, N).

        Works on coordinate-major (3, N) and corner-major (8, N) arrays so that every elementwise step reads
        contiguous rows; the far-field term is skipped when every point is inside the grid box.
        """
        h, B = self.voxel_size, self.brick
        idt = self.cell_max.dtype
        n = x.shape[0]
        # (3, N) fine grid coordinates
        u = torch.sub(x.T, self.origin[:, None], out=x.new_empty(3, n)).div_(h)
        uc = torch.clamp(u, min=self.box_min, max=self.box_max)  # projection onto the box
        cell = torch.minimum(uc.to(idt), self.cell_max)  # uc >= 0: truncation is floor
        if self._brick_shift is not None:
            bcoord = cell >> self._brick_shift  # brick = coarse cell
            local = cell & (B - 1)
        else:
            bcoord = torch.div(cell, B, rounding_mode="floor")
            local = cell - bcoord * B
        bflat = (bcoord * self.brick_strides).sum(0, dtype=idt)
        base = self.cell_base.index_select(0, bflat)
        fine = base < self._fine_end
        base = torch.where(fine, base + (local * self.node_strides).sum(0, dtype=idt), base)
        vals = self.nodes.index_select(0, (self.corner_offsets + base).view(-1)).view(2, 2, 2, n)
        # Local coordinates in the fine cell, or in the coarse cell outside allocated bricks.
        t = torch.where(fine, uc - cell, uc / B - bcoord)  # (3, N)
        tx, ty, tz = t[0], t[1], t[2]

        # Trilinear interpolation along z, y, then x; the derivatives reuse the same differences.
        z = torch.empty((2, 2, 2, n), dtype=x.dtype, device=x.device)  # [value | d/dz, i, j]
        dz = torch.sub(vals[:, :, 1], vals[:, :, 0], out=z[1])
        cz = torch.mul(dz, tz, out=z[0]).add_(vals[:, :, 0])
        if not with_grad:
            dy = cz[:, 1] - cz[:, 0]  # (2, N) [i]
            cy = (dy * ty).add_(cz[:, 0])
            phi = ((cy[1] - cy[0]) * tx).add_(cy[0])
            grad = None
        else:
            dy = z[:, :, 1] - z[:, :, 0]  # (2, 2, N) [value | d/dz, i]
            y = torch.empty((3, 2, n), dtype=x.dtype, device=x.device)  # [value | d/dz | d/dy, i]
            torch.mul(dy, ty, out=y[:2]).add_(z[:, :, 0])
            y[2] = dy[0]
            dx = y[:, 1] - y[:, 0]  # (3, N)
            r = (dx * tx).add_(y[:, 0])  # (3, N): value, d/dz, d/dy
            phi = r[0]
            grad = torch.stack([dx[0], r[2], r[1]]).div_(torch.where(fine, self.cell_sizes[0],
                                                                     self.cell_sizes[1]))

        # Outside the box: phi(p) + |x - p|, p the projection of x onto the box.
        inside = u == uc
        if bool(inside.all()):
            return phi, grad
        off = (u - uc).mul_(h)  # (3, N) metres, zero inside the box
        dist = (off * off).sum(0).sqrt_()
        phi = phi + dist
        if not with_grad:
            return phi, None
        # d/dx of phi(p(x)) + |x - p(x)|: a clamped coordinate does not move p and only the distance term
        # acts.
        grad = torch.where(inside, grad, off.div_(dist.clamp(min=torch.finfo(x.dtype).tiny)))
        return phi, grad

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Signed distance at points, differentiable w.r.t. ``x`` through autograd (first derivatives only).

        Args:
            x: (..., 3) positions in metres on the SDF's device (cast to the SDF's dtype).

        Returns:
            (...) signed distances in metres, negative inside.

        Raises:
            InputError: wrong shape, another device, or non-finite points.
        """
        batch = x.shape[:-1] if isinstance(x, torch.Tensor) else None
        xf = self._check(x)
        if torch.is_grad_enabled() and xf.requires_grad:
            phi = _Sample.apply(xf, self)
        else:
            phi = self._query(xf, with_grad=False)[0]
        return phi.reshape(batch)

    @torch.no_grad()
    def value_and_gradient(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Signed distance and its analytic gradient (of the interpolant, see :attr:`sampling`), without
        autograd.

        Args:
            x: (..., 3) positions in metres on the SDF's device.

        Returns:
            ``(phi, grad)``: (...) signed distances in metres and (..., 3) gradients d phi / d x (unitless).

        Raises:
            InputError: wrong shape, another device, or non-finite points.
        """
        batch = x.shape[:-1] if isinstance(x, torch.Tensor) else None
        phi, grad = self._query(self._check(x.detach() if isinstance(x, torch.Tensor) else x), with_grad=True)
        return phi.reshape(batch), grad.reshape(*batch, 3)

    # ------------------------------------------------------------------ persistence
    def to_data(self) -> SDFGridData:
        """The grid as numpy arrays (float64)."""
        return SDFGridData(
            origin=self.origin.detach().cpu().double().numpy(),
            voxel_size=self.voxel_size,
            brick=self.brick,
            band=self.band,
            coarse=self.coarse.detach().cpu().double().numpy(),
            brick_index=self.brick_index.detach().cpu().numpy().astype(np.int32),
            bricks=self.bricks.detach().cpu().double().numpy(),
            num_exact=self.num_exact,
        )

    def save(self, path: str | os.PathLike) -> None:
        """Write the grid to a ``.npz`` file atomically (values stored in the SDF's dtype)."""
        d = self.to_data()
        store = np.float32 if self.dtype == torch.float32 else np.float64
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(
                    fh,
                    format_version=np.int64(_FORMAT_VERSION),
                    origin=d.origin,
                    voxel_size=np.float64(d.voxel_size),
                    brick=np.int64(d.brick),
                    band=np.float64(d.band),
                    num_exact=np.int64(d.num_exact),
                    coarse=d.coarse.astype(store),
                    brick_index=d.brick_index,
                    bricks=d.bricks.astype(store),
                )

    @classmethod
    def load(
        cls, path: str | os.PathLike, *, device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float64
    ) -> "BodySDF":
        """Read a grid written by :meth:`save`.

        Raises:
            InputError: the file is missing, not an SDF archive, or of another format version.
        """
        try:
            with np.load(path) as z:
                version = int(z["format_version"])
                if version != _FORMAT_VERSION:
                    raise InputError(f"{path}: SDF format version {version}, expected {_FORMAT_VERSION}")
                data = SDFGridData(
                    origin=z["origin"],
                    voxel_size=float(z["voxel_size"]),
                    brick=int(z["brick"]),
                    band=float(z["band"]),
                    coarse=z["coarse"],
                    brick_index=z["brick_index"],
                    bricks=z["bricks"],
                    num_exact=int(z["num_exact"]),
                )
        except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as e:
            if isinstance(e, InputError):
                raise
            raise InputError(f"{path}: not a readable BodySDF archive ({e})") from e
        nb = data.brick_index.shape
        B = data.brick
        if (
            data.coarse.shape != tuple(n + 1 for n in nb)
            or data.bricks.shape[1:] != (B + 1,) * 3
            or data.brick_index.max(initial=-1) >= data.bricks.shape[0]
        ):
            raise InputError(f"{path}: inconsistent BodySDF array shapes")
        return cls(data, device=device, dtype=dtype)

    def extra_repr(self) -> str:
        return (
            f"voxel_size={self.voxel_size}, band={self.band}, brick={self.brick}, bricks={self.num_bricks}, "
            f"shape={self.shape}, sampling={self.sampling.value}, dtype={self.dtype}, device={self.device}"
        )
