"""Signed distance fields of bodies: sparse narrow-band grids sampled differentiably in torch.

Re-exports :class:`BodySDF` (the sampled field, ``BodySDF.from_body`` / ``BodySDF.cached``) with its
:class:`SDFSettings` and :class:`SDFSampling`, the grid builder :func:`build_sdf_grid` (:class:`SDFGridData`,
:class:`SignType`), the exact queries :func:`exact_signed_distance`, :func:`winding_number` and
:class:`MeshProximity` (closest points and signed distances, the tree built once) with
:func:`closest_points_on_triangles` (point-triangle pairs), and the disk cache
:func:`cached_sdf`, :func:`sdf_cache_dir`, :func:`sdf_cache_key`, :func:`sdf_cache_path`.
"""

from torchgarment.sdf.build import (
    MeshProximity,
    SDFGridData,
    SDFSettings,
    SignType,
    build_sdf_grid,
    exact_signed_distance,
    winding_number,
)
from torchgarment.sdf.cache import cached_sdf, sdf_cache_dir, sdf_cache_key, sdf_cache_path
from torchgarment.sdf.grid import BodySDF, SDFSampling
from torchgarment.sdf.proximity import closest_points_on_triangles

__all__ = [
    "BodySDF",
    "MeshProximity",
    "SDFGridData",
    "SDFSampling",
    "SDFSettings",
    "SignType",
    "build_sdf_grid",
    "cached_sdf",
    "closest_points_on_triangles",
    "exact_signed_distance",
    "sdf_cache_dir",
    "sdf_cache_key",
    "sdf_cache_path",
    "winding_number",
]
