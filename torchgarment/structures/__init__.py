"""Mesh data structures: the garment mesh and generic triangle-mesh checks."""

from torchgarment.structures.garment_mesh import GarmentMesh
from torchgarment.structures.mesh_checks import (
    check_mesh,
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
    "check_mesh",
    "face_areas",
    "find_boundary_edges",
    "find_degenerate_faces",
    "find_misoriented_edges",
    "find_nonmanifold_edges",
    "find_unreferenced_vertices",
    "weld_vertices",
]
