"""Signed distance fields of bodies: sparse narrow-band grids sampled differentiably in torch."""

from torchgarment.sdf.build import SDFGridData, SDFSettings, SignType, build_sdf_grid, exact_signed_distance, winding_number
from torchgarment.sdf.cache import cached_sdf, sdf_cache_dir, sdf_cache_key
from torchgarment.sdf.grid import BodySDF, SDFSampling

__all__ = [
    "BodySDF",
    "SDFGridData",
    "SDFSampling",
    "SDFSettings",
    "SignType",
    "build_sdf_grid",
    "cached_sdf",
    "exact_signed_distance",
    "sdf_cache_dir",
    "sdf_cache_key",
    "winding_number",
]
