"""Signed distance fields of bodies: sparse narrow-band grids sampled differentiably in torch."""

from torchgarment.sdf.build import SDFGridData, SDFSettings, SignType, build_sdf_grid, exact_signed_distance, winding_number
from torchgarment.sdf.grid import BodySDF

__all__ = [
    "BodySDF",
    "SDFGridData",
    "SDFSettings",
    "SignType",
    "build_sdf_grid",
    "exact_signed_distance",
    "winding_number",
]
