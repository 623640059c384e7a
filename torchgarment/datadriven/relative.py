"""Body-relative garment coordinates for data-driven fitting (issue 15).

Gillies et al. blend absolute vertex positions, so a blended garment moves with the bodies' mean, not with the
customer's surface. Here every garment vertex is attached to one triangle of the body model (the closest
triangle of the mean-body drape on the mean body; all PCA bodies share the topology) and expressed in that
triangle's affine frame on each body::

    x = v0 + a e1 + b e2 + h n        (e1, e2 the triangle's edges from v0, n its unit normal)

``(a, b)`` the unclamped barycentric coordinates of the projection and ``h`` the height over the plane
(the frame of :mod:`torchgarment.adjust.transfer`, in torch and batched). The clothing basis is blended in
these coordinates and decoded on the customer's body, so the garment follows the body's surface and only the
drape's residual is blended.

Shapes: ``x`` (..., V, 3) garment positions and ``body`` (..., B, 3) body vertices in metres, ``faces``
(F, 3), ``tri`` (V,) attachment triangles; leading batch dimensions of ``x`` and ``body`` broadcast.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from torchgarment.options import OptionEnum

if TYPE_CHECKING:
    from torchgarment.datadriven.basis import ClothingBasis
    from torchgarment.datadriven.pca import BodyPCA


class BasisFrame(OptionEnum):
    """Coordinates in which a clothing basis is blended."""

    ABSOLUTE = "absolute"
    """Vertex positions (Gillies et al. 2004)."""
    BODY = "body"
    """Body-relative coordinates (see the module docstring)."""


def attach(x: torch.Tensor, body: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(V,) long index of the body triangle closest to each garment vertex (exact, AABB tree)."""
    from torchgarment.sdf import MeshProximity

    tree = MeshProximity(body.detach().cpu().double().numpy(), faces.detach().cpu().numpy())
    return torch.as_tensor(tree.closest_triangles(x.detach().cpu().double().numpy()), device=x.device)


def _frames(body: torch.Tensor, faces: torch.Tensor, tri: torch.Tensor
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(v0, e1, e2, n) of the attachment triangles, each (..., V, 3)."""
    f = faces[tri]  # (V, 3)
    v0 = body[..., f[:, 0], :]
    e1 = body[..., f[:, 1], :] - v0
    e2 = body[..., f[:, 2], :] - v0
    n = torch.linalg.cross(e1, e2)
    n = n / torch.linalg.vector_norm(n, dim=-1, keepdim=True).clamp_min(1e-300)
    return v0, e1, e2, n


def encode(x: torch.Tensor, body: torch.Tensor, faces: torch.Tensor, tri: torch.Tensor) -> torch.Tensor:
    """(..., V, 3) coordinates ``(a, b, h)`` of ``x`` in the frames of its triangles on ``body``."""
    v0, e1, e2, n = _frames(body, faces, tri)
    d = x - v0
    h = (d * n).sum(-1)
    d = d - h[..., None] * n
    g11, g12, g22 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    r1, r2 = (d * e1).sum(-1), (d * e2).sum(-1)
    det = (g11 * g22 - g12 * g12).clamp_min(1e-300)
    return torch.stack([(g22 * r1 - g12 * r2) / det, (g11 * r2 - g12 * r1) / det, h], dim=-1)


def decode(local: torch.Tensor, body: torch.Tensor, faces: torch.Tensor, tri: torch.Tensor) -> torch.Tensor:
    """(..., V, 3) positions of coordinates ``(a, b, h)`` in the frames of their triangles on ``body``."""
    v0, e1, e2, n = _frames(body, faces, tri)
    return v0 + local[..., 0:1] * e1 + local[..., 1:2] * e2 + local[..., 2:3] * n


def branch_deviation(basis: ClothingBasis, pca: BodyPCA, hem_fraction: float = 0.1
                     ) -> dict[str, dict[str, float]]:
    """How far each example drape of a clothing basis is from the mean drape carried onto its body
    (body-relative coordinates on the mean body, decoded on the example body): a drape on the mean drape's
    equilibrium branch differs from it only by the body change's effect; a hem that swung onto another branch
    differs by centimetres at the hem.

    Args:
        basis: the clothing basis. pca: its body model. hem_fraction: the lowest this fraction of the mean
            drape's vertices is "the hem".

    Returns:
        Per drape (``plus_i``, ``minus_i``): ``mean_mm`` over all vertices and ``hem_mean_mm`` over the hem.
    """
    pca64 = pca.to(device="cpu", dtype=torch.float64)
    faces = pca64.faces.long()
    mean = basis.mean.detach().cpu().double()
    tri = attach(mean, pca64.mean, faces)
    local = encode(mean, pca64.mean, faces, tri)
    hem = mean[:, 1] <= torch.quantile(mean[:, 1], hem_fraction)
    c = (basis.steps.double() / pca64.sigmas[: basis.k]).tolist()
    out = {}
    for i in range(basis.k):
        for sign, drapes in ((1.0, basis.plus), (-1.0, basis.minus)):
            carried = decode(local, pca64.sample_body(i, sign * c[i]), faces, tri)
            d = torch.linalg.vector_norm(drapes[i].detach().cpu().double() - carried, dim=1)
            out[f"{'plus' if sign > 0 else 'minus'}_{i}"] = {"mean_mm": 1e3 * float(d.mean()),
                                                              "hem_mean_mm": 1e3 * float(d[hem].mean())}
    return out
