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
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

import numpy as np
import torch

from torchgarment.errors import InputError
from torchgarment.io.atomic import atomic_path
from torchgarment.sdf.build import SDFGridData, SDFSettings, build_sdf_grid, check_mesh

if TYPE_CHECKING:  # pragma: no cover
    from torchgarment.body.body import Body

_FORMAT_VERSION = 1

# Corner offsets of a cell in C order: corner c = (c >> 2 & 1, c >> 1 & 1, c & 1).
_CORNERS = [(i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1)]


def _trilinear(vals: list[torch.Tensor], t: torch.Tensor, with_grad: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Trilinear interpolation of 8 corner values and its derivative w.r.t. the local coordinates.

    Args:
        vals: 8 tensors (N,), corner values in the order of ``_CORNERS``.
        t: (N, 3) local coordinates in [0, 1].
        with_grad: also return the derivative.

    Returns:
        value (N,) and, when ``with_grad``, d value / d t (N, 3) (else None).
    """
    tx, ty, tz = t.unbind(-1)
    c000, c001, c010, c011, c100, c101, c110, c111 = vals
    # Interpolate along z, then y, then x.
    c00 = c000 + (c001 - c000) * tz
    c01 = c010 + (c011 - c010) * tz
    c10 = c100 + (c101 - c100) * tz
    c11 = c110 + (c111 - c110) * tz
    c0 = c00 + (c01 - c00) * ty
    c1 = c10 + (c11 - c10) * ty
    value = c0 + (c1 - c0) * tx
    if not with_grad:
        return value, None
    dx = c1 - c0
    dy = (c01 - c00) + ((c11 - c10) - (c01 - c00)) * tx
    d0 = (c001 - c000) + ((c011 - c010) - (c001 - c000)) * ty
    d1 = (c101 - c100) + ((c111 - c110) - (c101 - c100)) * ty
    dz = d0 + (d1 - d0) * tx
    return value, torch.stack([dx, dy, dz], dim=-1)


class BodySDF(torch.nn.Module):
    """Signed distance field of a body (metres, negative inside), sparse narrow band + coarse far field.

    Build with :meth:`from_mesh` or :meth:`from_body`; sample with ``sdf(x)`` (differentiable through
    autograd) or :meth:`value_and_gradient` (analytic gradient, no graph). Buffers move with
    ``.to(device, dtype)``; queries must be on the SDF's device and are computed in the SDF's dtype.

    Attributes:
        voxel_size: fine spacing in metres.
        brick: brick edge in voxels (coarse spacing is ``brick * voxel_size``).
        band: narrow-band half-width in metres.
        origin: buffer (3,), position of node (0, 0, 0).
        coarse: buffer (n0 + 1, n1 + 1, n2 + 1), coarse node values.
        brick_index: buffer (n0, n1, n2) int64, row of ``bricks`` per brick, -1 where not allocated.
        bricks: buffer (K, brick + 1, brick + 1, brick + 1), fine node values.
    """

    origin: torch.Tensor
    coarse: torch.Tensor
    brick_index: torch.Tensor
    bricks: torch.Tensor

    def __init__(self, data: SDFGridData, *, device: torch.device | str | None = None, dtype: torch.dtype = torch.float64):
        super().__init__()
        self.voxel_size = float(data.voxel_size)
        self.brick = int(data.brick)
        self.band = float(data.band)
        self.num_exact = int(data.num_exact)
        kw = dict(device=device, dtype=dtype)
        self.register_buffer("origin", torch.as_tensor(np.asarray(data.origin), **kw))
        self.register_buffer("coarse", torch.as_tensor(np.asarray(data.coarse), **kw))
        self.register_buffer("brick_index", torch.as_tensor(np.asarray(data.brick_index, dtype=np.int64), device=device))
        self.register_buffer("bricks", torch.as_tensor(np.asarray(data.bricks), **kw))

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
    def from_body(cls, body: "Body", settings: SDFSettings | None = None) -> "BodySDF":
        """Build the SDF of a :class:`~torchgarment.body.body.Body` on the body's device and dtype."""
        return cls.from_mesh(body.vertices, body.faces, settings, device=body.device, dtype=body.dtype)

    # ------------------------------------------------------------------ properties
    @property
    def device(self) -> torch.device:
        return self.bricks.device

    @property
    def dtype(self) -> torch.dtype:
        return self.bricks.dtype

    @property
    def num_bricks(self) -> int:
        return int(self.bricks.shape[0])

    @property
    def shape(self) -> tuple[int, int, int]:
        """Number of bricks (= coarse cells) per axis."""
        return tuple(int(n) for n in self.brick_index.shape)

    @property
    def bounds(self) -> torch.Tensor:
        """(2, 3) min and max corners of the grid box in metres."""
        size = torch.tensor(self.shape, device=self.device, dtype=self.dtype) * (self.brick * self.voxel_size)
        return torch.stack([self.origin, self.origin + size])

    def nbytes(self) -> int:
        """Memory held by the buffers, in bytes."""
        return sum(b.numel() * b.element_size() for b in self.buffers())

    # ------------------------------------------------------------------ sampling
    def _sample(self, x: torch.Tensor, with_grad: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        if not isinstance(x, torch.Tensor) or x.shape[-1:] != (3,):
            raise InputError(f"SDF query points must be a tensor of shape (..., 3), got {getattr(x, 'shape', type(x))}")
        if x.device != self.device:
            raise InputError(f"SDF query points are on {x.device}, the SDF is on {self.device}; move one with .to()")
        batch = x.shape[:-1]
        x = x.reshape(-1, 3).to(self.dtype)
        h, B = self.voxel_size, self.brick
        nb = self.brick_index.shape
        n_fine = torch.tensor([n * B for n in nb], device=x.device, dtype=x.dtype)

        u = (x - self.origin) / h  # fine grid coordinates
        uc = torch.minimum(torch.clamp(u, min=0.0), n_fine)  # projection onto the box
        off = (u - uc) * h  # (N, 3) metres, zero inside the box
        sq = (off * off).sum(-1)
        outside = sq > 0
        out_dist = torch.where(outside, torch.sqrt(torch.where(outside, sq, torch.ones_like(sq))), torch.zeros_like(sq))

        # Fine cell and brick.
        cell = torch.minimum(torch.floor(uc.detach()), n_fine - 1).long()  # (N, 3)
        bcoord = torch.div(cell, B, rounding_mode="floor")
        local = cell - bcoord * B
        bid = self.brick_index[bcoord[:, 0], bcoord[:, 1], bcoord[:, 2]]
        in_brick = bid >= 0
        # Coarse cell (same as the brick) and local coordinates.
        tc = uc / B - bcoord.to(x.dtype)
        tf = uc - cell.to(x.dtype)

        Bp = B + 1
        base_f = bid.clamp(min=0) * Bp**3 + (local[:, 0] * Bp + local[:, 1]) * Bp + local[:, 2]
        flat_f = self.bricks.reshape(-1)
        nc1, nc2 = nb[1] + 1, nb[2] + 1
        base_c = (bcoord[:, 0] * nc1 + bcoord[:, 1]) * nc2 + bcoord[:, 2]
        flat_c = self.coarse.reshape(-1)
        vf = [flat_f[base_f + (i * Bp + j) * Bp + k] for i, j, k in _CORNERS]
        vc = [flat_c[base_c + (i * nc1 + j) * nc2 + k] for i, j, k in _CORNERS]
        phi_f, g_f = _trilinear(vf, tf, with_grad)
        phi_c, g_c = _trilinear(vc, tc, with_grad)
        phi = torch.where(in_brick, phi_f, phi_c) + out_dist
        if not with_grad:
            return phi.reshape(batch), None
        grad = torch.where(in_brick[:, None], g_f / h, g_c / (B * h))
        # d/dx of phi(p(x)) + |x - p(x)|: clamped coordinates do not move p.
        inside_box = (u >= 0) & (u <= n_fine)
        grad = torch.where(inside_box, grad, torch.zeros_like(grad))
        grad = grad + torch.where(outside[:, None], off / out_dist.clamp(min=torch.finfo(x.dtype).tiny)[:, None], torch.zeros_like(off))
        return phi.reshape(batch), grad.reshape(*batch, 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Signed distance at points, differentiable w.r.t. ``x`` through autograd.

        Args:
            x: (..., 3) positions in metres on the SDF's device (cast to the SDF's dtype).

        Returns:
            (...) signed distances in metres, negative inside.
        """
        return self._sample(x, with_grad=False)[0]

    @torch.no_grad()
    def value_and_gradient(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Signed distance and its analytic gradient (of the trilinear interpolant), without autograd.

        Args:
            x: (..., 3) positions in metres on the SDF's device.

        Returns:
            ``(phi, grad)``: (...) signed distances in metres and (..., 3) gradients d phi / d x (unitless).
        """
        phi, grad = self._sample(x.detach(), with_grad=True)
        return phi, grad

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
        cls, path: str | os.PathLike, *, device: torch.device | str | None = None, dtype: torch.dtype = torch.float64
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
        except (OSError, KeyError, ValueError) as e:
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
            f"shape={self.shape}, dtype={self.dtype}, device={self.device}"
        )
