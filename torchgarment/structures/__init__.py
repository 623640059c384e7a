"""Mesh data structures: the garment mesh, its pattern layout and generic triangle-mesh checks.

Re-exports :class:`GarmentMesh` (sewn or plain 3D garment mesh with lazily derived topology and geometry),
:class:`MeshLayout` (the (panel, edge) -> vertices table of a mesh made by ``mesh_pattern``),
:func:`seam_weld_index` (the welded vertex of every vertex of a sewn mesh), :func:`welded_faces` (the
faces that survive the weld) and the
triangle-mesh checks of :mod:`torchgarment.structures.mesh_checks`: :func:`check_mesh`, :func:`edge_table`,
:func:`face_areas`, :func:`find_boundary_edges`, :func:`find_degenerate_faces`,
:func:`find_misoriented_edges`, :func:`find_nonmanifold_edges`, :func:`find_unreferenced_vertices` and
:func:`weld_vertices`.
"""

from torchgarment.structures.garment_mesh import GarmentMesh, MeshLayout, seam_weld_index, welded_faces
from torchgarment.structures.mesh_checks import (
    check_mesh,
    edge_table,
    face_areas,
    find_boundary_edges,
    find_degenerate_faces,
    find_misoriented_edges,
    find_nonmanifold_edges,
    find_unreferenced_vertices,
    weld_vertices,
)

__all__ = [
    "GarmentMesh",
    "MeshLayout",
    "check_mesh",
    "edge_table",
    "face_areas",
    "find_boundary_edges",
    "find_degenerate_faces",
    "find_misoriented_edges",
    "find_nonmanifold_edges",
    "find_unreferenced_vertices",
    "seam_weld_index",
    "weld_vertices",
    "welded_faces",
]
