"""Body-relative garment coordinates for data-driven fitting (issue 15).

Gillies et al. blend absolute vertex positions, so a blended garment moves with the bodies' mean, not with the
customer's surface. Here every garment vertex is attached to one triangle of the body model (the closest
triangle of the mean-body drape on the mean body; all PCA bodies share the topology) and expressed in that
triangle's affine frame on each body::

    x = v0 + a e1 + b e2 + h n        (e1, e2 the triangle's edges from v0, n its unit normal)

``(a, b)`` the unclamped barycentric coordinates of the projection and ``h`` the height over the plane
(:mod:`torchgarment.body.frames`, shared with the deformation transfer). The clothing basis is blended in
these coordinates and decoded on the customer's body, so the garment follows the body's surface and only the
drape's residual is blended.

Shapes: ``x`` (..., V, 3) garment positions and ``body`` (..., B, 3) body vertices in metres, ``faces``
(F, 3), ``tri`` (V,) attachment triangles; leading batch dimensions of ``x`` and ``body`` broadcast.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from torchgarment.body.frames import attach, decode, encode
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
    out = {}
    for side, drapes, bodies in zip(("plus", "minus"), (basis.plus, basis.minus), basis.example_bodies(pca64),
                                    strict=True):
        for i in range(basis.k):
            carried = decode(local, bodies[i], faces, tri)
            d = torch.linalg.vector_norm(drapes[i].detach().cpu().double() - carried, dim=1)
            out[f"{side}_{i}"] = {"mean_mm": 1e3 * float(d.mean()), "hem_mean_mm": 1e3 * float(d[hem].mean())}
    return out
