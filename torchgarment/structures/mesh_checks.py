"""Generic triangle-mesh checks: degenerate faces, non-manifold edges, unreferenced vertices, welding.

All functions are vectorized (no Python loops over vertices or faces) and accept vertices of shape (V, 3)
or (V, 2) (flat panels) and faces of shape (F, 3) with long vertex indices.
"""

from __future__ import annotations

import numpy as np
import torch

from torchgarment.errors import MeshError

__all__ = [
    "check_mesh",
    "face_areas",
    "find_boundary_edges",
    "find_degenerate_faces",
    "find_misoriented_edges",
    "find_nonmanifold_edges",
    "find_unreferenced_vertices",
    "weld_vertices",
]

#: Default area below which a triangle counts as degenerate, in square metres (1 square micrometre).
DEFAULT_AREA_TOL = 1e-12


def face_areas(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Triangle areas.

    Args:
        vertices: (V, 3) or (V, 2) positions in metres.
        faces: (F, 3) long vertex indices.

    Returns:
        (F,) areas in square metres (differentiable w.r.t. ``vertices``).
    """
    tri = vertices[faces.long()]
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    if vertices.shape[-1] == 2:
        return 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).abs()
    return 0.5 * torch.linalg.vector_norm(torch.linalg.cross(e1, e2, dim=-1), dim=-1)


def find_degenerate_faces(
    vertices: torch.Tensor, faces: torch.Tensor, area_tol: float = DEFAULT_AREA_TOL
) -> torch.Tensor:
    """Faces with a repeated vertex index or an area at most ``area_tol``.

    Args:
        vertices: (V, 3) or (V, 2) positions in metres.
        faces: (F, 3) long vertex indices (assumed in range).
        area_tol: area threshold in square metres.

    Returns:
        (K,) long indices of the degenerate faces, ascending.
    """
    faces = faces.long()
    if faces.numel() == 0:
        return torch.zeros(0, dtype=torch.long, device=faces.device)
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    small = face_areas(vertices.detach(), faces) <= area_tol
    return torch.nonzero(repeated | small, as_tuple=False).flatten()


def edge_table(faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The unique undirected edges of a triangle mesh, the one edge table of the package (garment meshes,
    body sections, the distance queries' pseudo-normals).

    Args:
        faces: (F, 3) integer vertex indices.

    Returns:
        ``(edges, face_edges, counts)``: (E, 2) long vertex pairs, smaller index first, sorted
        lexicographically; (F, 3) long, ``face_edges[f, k]`` indexes ``edges`` for the side ``faces[f, k]``
        -> ``faces[f, (k + 1) % 3]``; (E,) long number of faces using each edge.
    """
    f = faces.long()
    directed = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], dim=0)  # (3F, 2); row k * F + i
    edges, inverse, counts = _unique_pairs(torch.sort(directed, dim=1).values)
    return edges, inverse.view(3, f.shape[0]).T.contiguous(), counts


def _unique_pairs(pairs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Like ``torch.unique(pairs, dim=0, return_inverse=True, return_counts=True)`` for (N, 2) non-negative
    integer pairs, via one 1D unique on the key ``a * (max + 1) + b`` (much faster than ``dim=0``)."""
    base = int(pairs.max()) + 1 if pairs.numel() else 1
    keys = pairs[:, 0] * base + pairs[:, 1]
    ukeys, inverse, counts = torch.unique(keys, return_inverse=True, return_counts=True)
    return torch.stack([ukeys // base, ukeys % base], dim=1), inverse, counts


def find_nonmanifold_edges(faces: torch.Tensor) -> torch.Tensor:
    """Edges shared by more than two faces.

    Args:
        faces: (F, 3) long vertex indices.

    Returns:
        (E, 2) long vertex index pairs (smaller index first), sorted lexicographically.
    """
    if faces.numel() == 0:
        return torch.zeros(0, 2, dtype=torch.long, device=faces.device)
    edges, _, counts = edge_table(faces)
    return edges[counts > 2]


def find_boundary_edges(faces: torch.Tensor) -> torch.Tensor:
    """Edges used by exactly one face (the border of an open surface).

    Args:
        faces: (F, 3) long vertex indices.

    Returns:
        (E, 2) long vertex index pairs (smaller index first), sorted lexicographically.
    """
    if faces.numel() == 0:
        return torch.zeros(0, 2, dtype=torch.long, device=faces.device)
    edges, _, counts = edge_table(faces)
    return edges[counts == 1]


def find_misoriented_edges(faces: torch.Tensor) -> torch.Tensor:
    """Edges traversed twice in the same direction (neighbouring faces with opposite orientations).

    Args:
        faces: (F, 3) long vertex indices.

    Returns:
        (E, 2) long directed vertex index pairs that occur more than once, sorted lexicographically.
    """
    if faces.numel() == 0:
        return torch.zeros(0, 2, dtype=torch.long, device=faces.device)
    f = faces.long()
    directed = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], dim=0)
    edges, _, counts = _unique_pairs(directed)
    return edges[counts > 1]


def find_unreferenced_vertices(num_vertices: int, faces: torch.Tensor) -> torch.Tensor:
    """Vertices that no face uses.

    Args:
        num_vertices: V.
        faces: (F, 3) long vertex indices in [0, V).

    Returns:
        (K,) long vertex indices, ascending.
    """
    used = torch.zeros(int(num_vertices), dtype=torch.bool, device=faces.device)
    if faces.numel():
        used[faces.long().flatten()] = True
    return torch.nonzero(~used, as_tuple=False).flatten()


def _first(indices: torch.Tensor, k: int = 5) -> str:
    """The first ``k`` entries of an index tensor as a short string."""
    items = indices[:k].tolist()
    text = ", ".join(str(tuple(i)) if isinstance(i, list) else str(i) for i in items)
    return f"[{text}{', ...' if indices.shape[0] > k else ''}]"


def check_mesh(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    *,
    require_manifold: bool = True,
    require_closed: bool = False,
    name: str = "mesh",
    area_tol: float = DEFAULT_AREA_TOL,
    allow_unreferenced: bool = True,
) -> None:
    """Validate a triangle mesh; raise :class:`MeshError` with a one-line message on the first problem.

    Checks, in order: tensor shapes and dtypes, finite coordinates, non-empty, face indices in range,
    degenerate faces (repeated index or area <= ``area_tol``), unreferenced vertices (unless
    ``allow_unreferenced``), non-manifold edges (more than two faces) and inconsistently oriented
    neighbours (when ``require_manifold``), boundary edges (when ``require_closed``).

    Args:
        vertices: (V, 3) or (V, 2) floating positions in metres.
        faces: (F, 3) integer vertex indices.
        require_manifold: reject edges shared by more than two faces and flipped neighbours.
        require_closed: reject boundary edges (the surface must be watertight).
        name: what to call the mesh in error messages.
        area_tol: degenerate-face area threshold in square metres.
        allow_unreferenced: accept vertices that no face uses.

    Raises:
        MeshError: the mesh fails a check.
    """
    if not isinstance(vertices, torch.Tensor) or not isinstance(faces, torch.Tensor):
        raise MeshError(f"{name}: vertices and faces must be torch tensors")
    if vertices.ndim != 2 or vertices.shape[1] not in (2, 3):
        raise MeshError(f"{name}: vertices must have shape (V, 3) or (V, 2), got {tuple(vertices.shape)}")
    if not vertices.is_floating_point():
        raise MeshError(f"{name}: vertices must be floating point, got {vertices.dtype}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise MeshError(f"{name}: faces must have shape (F, 3), got {tuple(faces.shape)}")
    if faces.is_floating_point() or faces.dtype == torch.bool or faces.is_complex():
        raise MeshError(f"{name}: faces must be integer indices, got {faces.dtype}")
    if vertices.shape[0] == 0 or faces.shape[0] == 0:
        raise MeshError(f"{name}: empty mesh ({vertices.shape[0]} vertices, {faces.shape[0]} faces)")
    bad_rows = torch.nonzero(~torch.isfinite(vertices).all(dim=1), as_tuple=False).flatten()
    if bad_rows.numel():
        raise MeshError(
            f"{name}: {bad_rows.numel()} vertices have non-finite coordinates, first {_first(bad_rows)}"
        )
    faces = faces.long()
    out = torch.nonzero(((faces < 0) | (faces >= vertices.shape[0])).any(dim=1), as_tuple=False).flatten()
    if out.numel():
        raise MeshError(
            f"{name}: {out.numel()} faces index vertices outside [0, {vertices.shape[0]}), first faces "
            f"{_first(out)}"
        )
    degenerate = find_degenerate_faces(vertices, faces, area_tol)
    if degenerate.numel():
        raise MeshError(
            f"{name}: {degenerate.numel()} degenerate faces (area <= {area_tol:g} m^2), first "
            f"{_first(degenerate)}"
        )
    if not allow_unreferenced:
        unref = find_unreferenced_vertices(vertices.shape[0], faces)
        if unref.numel():
            raise MeshError(f"{name}: {unref.numel()} vertices are used by no face, first {_first(unref)}")
    if require_manifold:
        nonmanifold = find_nonmanifold_edges(faces)
        if nonmanifold.numel():
            raise MeshError(
                f"{name}: {nonmanifold.shape[0]} non-manifold edges (shared by more than two faces), "
                f"first {_first(nonmanifold)}"
            )
        misoriented = find_misoriented_edges(faces)
        if misoriented.numel():
            raise MeshError(
                f"{name}: {misoriented.shape[0]} edges where neighbouring faces have opposite orientation, "
                f"first {_first(misoriented)}"
            )
    if require_closed:
        boundary = find_boundary_edges(faces)
        if boundary.numel():
            raise MeshError(
                f"{name}: not closed, {boundary.shape[0]} boundary edges (used by one face), "
                f"first {_first(boundary)}"
            )


def weld_vertices(
    vertices: torch.Tensor, faces: torch.Tensor, tol: float = 0.0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Merge vertices closer than ``tol`` (OBJ exporters split vertices along UV and normal seams).

    Vertices are grouped into the connected components of the graph "distance <= tol" (found with a
    k-d tree, so the grouping is exact, unlike grid quantization). Each group keeps the position of its
    lowest-index vertex; groups are numbered in order of their lowest index, so a mesh without duplicates
    comes back unchanged. Faces that collapse (two corners in one group) are removed.

    Args:
        vertices: (V, 3) or (V, 2) positions in metres.
        faces: (F, 3) long vertex indices.
        tol: merge distance in metres (0 merges exact duplicates only).

    Returns:
        vertices: (V', D) welded positions (indexing the input, so gradients flow back).
        faces: (F', 3) remapped faces without collapsed ones.
        index_map: (V,) long, new index of every input vertex.

    Raises:
        MeshError: ``tol`` is negative or not finite.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    if not np.isfinite(tol) or tol < 0:
        raise MeshError(f"weld tolerance must be finite and >= 0, got {tol}")
    n = int(vertices.shape[0])
    device = vertices.device
    if n == 0:
        return vertices, faces.long(), torch.zeros(0, dtype=torch.long, device=device)
    pts = vertices.detach().cpu().numpy().astype(np.float64)
    if tol == 0.0:
        _, labels = np.unique(pts, axis=0, return_inverse=True)
        labels = labels.reshape(-1)
    else:
        pairs = cKDTree(pts).query_pairs(r=float(tol), output_type="ndarray")
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        _, labels = connected_components(graph, directed=False)
    # Renumber groups by their lowest member index.
    first = np.full(labels.max() + 1, n, dtype=np.int64)
    np.minimum.at(first, labels, np.arange(n))
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.shape[0])
    index_map_np = rank[labels]
    representatives = first[order]
    index_map = torch.as_tensor(index_map_np, dtype=torch.long, device=device)
    new_vertices = vertices[torch.as_tensor(representatives, dtype=torch.long, device=device)]
    new_faces = index_map[faces.long()]
    keep = (new_faces[:, 0] != new_faces[:, 1]) & (new_faces[:, 1] != new_faces[:, 2]) & (
        new_faces[:, 0] != new_faces[:, 2]
    )
    return new_vertices, new_faces[keep], index_map
