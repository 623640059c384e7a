"""GarmentMesh: the one structure for a garment's triangle mesh, sewn from a pattern or a plain 3D mesh.

A mesh made from a sewing pattern (:func:`torchgarment.pattern.meshing.mesh_pattern`) keeps its panels
separate: a vertex on a seam exists once per panel, and ``seam_pairs`` lists which vertices the stitches
join (the simulator sews them with zero-rest-length springs). Each vertex then belongs to exactly one panel
and has a 2D rest position ``p`` in that panel's coordinates. :meth:`GarmentMesh.welded` merges the seam
pairs for rendering and measuring. A plain 3D garment mesh (for retargeting) has only ``x`` and ``faces``.

A mesh made by ``mesh_pattern`` also records its vertex layout (:class:`MeshLayout`, ``GarmentMesh.layout``):
each panel's vertices are contiguous, its outline comes first, edge by edge, and the layout maps every
(panel, edge) to the run of vertices sampled along that edge. Code that needs the vertices of a pattern edge
reads them there instead of re-deriving the meshing convention.

Derived data (edges, boundary loops, hinge stencils, areas, normals) is computed on first use and cached,
pytorch3d style. The topology cache is shared (by reference) with meshes made by
:meth:`GarmentMesh.with_positions`; geometry caches are per mesh.
Treat the tensors of a mesh as immutable: make a new mesh (``with_positions``, ``clone``) instead of
editing them in place, or the caches go stale.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from torchgarment.errors import MeshError
from torchgarment.structures.mesh_checks import (
    DEFAULT_AREA_TOL,
    check_mesh,
    edge_table,
    find_degenerate_faces,
)


def _as_tensor(a: Any, dtype: torch.dtype, device: torch.device | str | None, what: str) -> torch.Tensor:
    try:
        return torch.as_tensor(np.asarray(a) if not isinstance(a, torch.Tensor) else a, dtype=dtype,
                               device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise MeshError(f"{what} cannot be converted to a {dtype} tensor: {exc}") from exc


@dataclass(frozen=True)
class MeshLayout:
    """Where a pattern's panels and edges lie in a mesh made by ``mesh_pattern``: a (panel, edge) -> vertices
    table.

    The vertices of panel ``k`` are ``panel_starts[k]`` to ``panel_starts[k + 1] - 1``; the first
    ``boundary_counts[k]`` of them are the panel's outline in the order of its edges (each edge's samples from
    its start vertex, its end vertex being the next edge's first sample), then come the interior vertices.

    Attributes:
        panel_names: (P,) panel names, in mesh order (the ``panel_names`` of the mesh).
        panel_starts: (P + 1,) long vertex index of each panel's first vertex; ``panel_starts[-1]`` is V.
        boundary_counts: (P,) long number of outline vertices of each panel.
        edge_runs: per panel (P entries), per edge in the panel's edge order, a (n + 1,) long tensor: the mesh
            vertices of the edge's ``n`` boundary segments from its start vertex to its end vertex, both
            included (the last edge ends at the panel's first vertex; consecutive runs share their corner
            vertex).
    """

    panel_names: tuple[str, ...]
    panel_starts: torch.Tensor
    boundary_counts: torch.Tensor
    edge_runs: tuple[tuple[torch.Tensor, ...], ...]

    def __post_init__(self) -> None:
        P = len(self.panel_names)
        if len(self.edge_runs) != P or tuple(self.panel_starts.shape) != (P + 1,) \
                or tuple(self.boundary_counts.shape) != (P,):
            raise MeshError(f"MeshLayout needs {P} panels of edge runs, ({P + 1},) panel_starts and ({P},) "
                            f"boundary_counts, got {len(self.edge_runs)}, {_describe(self.panel_starts)} and "
                            f"{_describe(self.boundary_counts)}")

    @property
    def num_vertices(self) -> int:
        """V, the number of mesh vertices the layout describes."""
        return int(self.panel_starts[-1])

    @property
    def device(self) -> torch.device:
        """Device of the index tensors."""
        return self.panel_starts.device

    def panel_index(self, panel: str) -> int:
        """Index of the panel named ``panel`` (mesh order).

        Raises:
            MeshError: no panel of that name.
        """
        if panel not in self.panel_names:
            raise MeshError(f"the mesh has no panel {panel!r} (panels: {', '.join(self.panel_names)})")
        return self.panel_names.index(panel)

    def runs(self, panel: str) -> tuple[torch.Tensor, ...]:
        """The vertex runs of every edge of ``panel``, in its edge order: (n_e + 1,) long tensors."""
        return self.edge_runs[self.panel_index(panel)]

    def run(self, panel: str, edge: int) -> torch.Tensor:
        """(n + 1,) long mesh vertices along edge ``edge`` of ``panel``, start to end vertex included.

        Raises:
            MeshError: unknown panel or edge index out of range.
        """
        runs = self.runs(panel)
        if not 0 <= edge < len(runs):
            raise MeshError(f"panel {panel!r} has {len(runs)} edges, no edge {edge}")
        return runs[edge]

    def boundary(self, panel: str) -> torch.Tensor:
        """(B,) long outline vertices of ``panel`` in edge order (each corner once, the first edge's start
        first)."""
        k = self.panel_index(panel)
        start = int(self.panel_starts[k])
        return torch.arange(start, start + int(self.boundary_counts[k]), dtype=torch.long, device=self.device)

    def to(self, device: torch.device | str | None) -> MeshLayout:
        """The layout with its index tensors on ``device`` (itself when they are there already)."""
        if device is None or torch.device(device) == self.device:
            return self
        return MeshLayout(self.panel_names, self.panel_starts.to(device=device),
                          self.boundary_counts.to(device=device),
                          tuple(tuple(r.to(device=device) for r in runs) for runs in self.edge_runs))


class GarmentMesh:
    """A triangle mesh of a garment, optionally with its sewing-pattern structure.

    Attributes:
        x: (V, 3) 3D positions in metres.
        faces: (F, 3) long vertex indices; panels are counter-clockwise seen from outside.
        p: (V, 2) rest positions in panel coordinates (metres), or None for a plain 3D mesh.
        panel_ids: (F,) long panel index of every face, or None. Per-vertex ids: :attr:`vertex_panel_ids`.
        panel_names: names of the panels, indexed by ``panel_ids``.
        seam_pairs: (S, 2) long pairs of vertices joined by stitches (empty (0, 2) without a pattern).
        layout: the :class:`MeshLayout` of a mesh made by ``mesh_pattern`` (the vertices of each panel edge),
            kept by copies that keep the vertices (``to``, ``clone``, ``with_positions``), None otherwise.
    """

    def __init__(
        self,
        x: torch.Tensor,
        faces: torch.Tensor,
        *,
        p: torch.Tensor | None = None,
        panel_ids: torch.Tensor | None = None,
        panel_names: Sequence[str] = (),
        seam_pairs: torch.Tensor | None = None,
        layout: MeshLayout | None = None,
    ) -> None:
        """Wrap tensors (no copy). Shapes and dtypes are checked; use :meth:`validate` for mesh quality.

        Raises:
            MeshError: wrong shapes or dtypes, tensors on different devices, or a ``layout`` of another mesh
                (other vertex count or panel names).
        """
        if not isinstance(x, torch.Tensor) or x.ndim != 2 or x.shape[1] != 3 or not x.is_floating_point():
            raise MeshError(f"x must be a floating (V, 3) tensor, got {_describe(x)}")
        if (not isinstance(faces, torch.Tensor) or faces.ndim != 2 or faces.shape[1] != 3
                or faces.dtype != torch.long):
            raise MeshError(f"faces must be a long (F, 3) tensor, got {_describe(faces)}")
        V, F = x.shape[0], faces.shape[0]
        if p is not None and (not isinstance(p, torch.Tensor) or p.shape != (V, 2) or p.dtype != x.dtype):
            raise MeshError(f"p must be a ({V}, 2) {x.dtype} tensor, got {_describe(p)}")
        if panel_ids is not None and (not isinstance(panel_ids, torch.Tensor) or panel_ids.shape != (F,)
                                      or panel_ids.dtype != torch.long):
            raise MeshError(f"panel_ids must be a long ({F},) tensor (one id per face), got "
                            f"{_describe(panel_ids)}")
        if seam_pairs is None:
            seam_pairs = torch.zeros(0, 2, dtype=torch.long, device=x.device)
        if not isinstance(seam_pairs, torch.Tensor) or seam_pairs.ndim != 2 or seam_pairs.shape[1] != 2 \
                or seam_pairs.dtype != torch.long:
            raise MeshError(f"seam_pairs must be a long (S, 2) tensor, got {_describe(seam_pairs)}")
        for name, t in (("faces", faces), ("p", p), ("panel_ids", panel_ids), ("seam_pairs", seam_pairs)):
            if t is not None and t.device != x.device:
                raise MeshError(f"{name} is on {t.device} but x is on {x.device}")
        if layout is not None:
            if not isinstance(layout, MeshLayout):
                raise MeshError(f"layout must be a MeshLayout, got {type(layout).__name__}")
            if layout.num_vertices != V or layout.panel_names != tuple(str(n) for n in panel_names):
                raise MeshError(f"layout describes {layout.num_vertices} vertices and panels "
                                f"{layout.panel_names}, the mesh has {V} vertices and panels "
                                f"{tuple(panel_names)}")
            if layout.device != x.device:
                raise MeshError(f"layout is on {layout.device} but x is on {x.device}")
        self.x = x
        self.faces = faces
        self.p = p
        self.panel_ids = panel_ids
        self.panel_names = tuple(str(n) for n in panel_names)
        self.seam_pairs = seam_pairs
        self.layout = layout
        self._cache: dict[str, Any] = {}  # geometry (depends on x / p)
        self._topo: dict[str, Any] = {}  # topology (faces only); shared by meshes made with with_positions

    # ------------------------------------------------------------------------------------ construction
    @classmethod
    def from_arrays(
        cls,
        x: Any,
        faces: Any,
        *,
        p: Any = None,
        panel_ids: Any = None,
        panel_names: Sequence[str] = (),
        seam_pairs: Any = None,
        layout: MeshLayout | None = None,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> GarmentMesh:
        """Build from numpy arrays, lists or tensors (copied/converted to ``dtype`` and ``device``).

        Args:
            x: (V, 3) positions in metres. faces: (F, 3) vertex indices.
            p: optional (V, 2) rest positions. panel_ids: optional (F,) per-face panel index.
            panel_names: names indexed by ``panel_ids``. seam_pairs: optional (S, 2) vertex pairs.
            layout: optional :class:`MeshLayout` (moved to ``device``).
            dtype: floating dtype of ``x`` and ``p``. device: target device.
        """
        return cls(
            _as_tensor(x, dtype, device, "x"),
            _as_tensor(faces, torch.long, device, "faces"),
            p=None if p is None else _as_tensor(p, dtype, device, "p"),
            panel_ids=None if panel_ids is None else _as_tensor(panel_ids, torch.long, device, "panel_ids"),
            panel_names=panel_names,
            seam_pairs=(None if seam_pairs is None
                        else _as_tensor(seam_pairs, torch.long, device, "seam_pairs")),
            layout=None if layout is None else layout.to(device),
        )

    @classmethod
    def from_trimesh(
        cls, mesh: Any, *, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
    ) -> GarmentMesh:
        """A plain 3D mesh (no pattern) from a ``trimesh.Trimesh``."""
        if not hasattr(mesh, "vertices") or not hasattr(mesh, "faces"):
            raise MeshError(f"expected a trimesh.Trimesh, got {type(mesh).__name__}")
        return cls.from_arrays(np.asarray(mesh.vertices), np.asarray(mesh.faces), dtype=dtype, device=device)

    # ------------------------------------------------------------------------------------ basic info
    @property
    def num_vertices(self) -> int:
        """V."""
        return int(self.x.shape[0])

    @property
    def num_faces(self) -> int:
        """F."""
        return int(self.faces.shape[0])

    @property
    def device(self) -> torch.device:
        """Device of all tensors."""
        return self.x.device

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of ``x`` (and ``p``)."""
        return self.x.dtype

    def __repr__(self) -> str:
        extra = (f", {len(self.panel_names)} panels, {self.seam_pairs.shape[0]} seam pairs"
                 if self.p is not None else "")
        return (f"GarmentMesh({self.num_vertices} vertices, {self.num_faces} faces{extra}, {self.dtype}, "
                f"{self.device})")

    # ------------------------------------------------------------------------------------ copies
    def _new(self, x: torch.Tensor, faces: torch.Tensor, p: torch.Tensor | None,
             panel_ids: torch.Tensor | None, seam_pairs: torch.Tensor) -> GarmentMesh:
        layout = None if self.layout is None else self.layout.to(x.device)
        return GarmentMesh(x, faces, p=p, panel_ids=panel_ids, panel_names=self.panel_names,
                           seam_pairs=seam_pairs, layout=layout)

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> GarmentMesh:
        """A mesh on ``device`` with floating tensors of ``dtype`` (index tensors stay long).

        Topology caches travel along; geometry caches are recomputed on demand.
        """
        fdt = dtype or self.dtype
        if not fdt.is_floating_point:
            raise MeshError(f"dtype must be floating point, got {fdt}")
        out = self._new(
            self.x.to(device=device, dtype=fdt),
            self.faces.to(device=device),
            None if self.p is None else self.p.to(device=device, dtype=fdt),
            None if self.panel_ids is None else self.panel_ids.to(device=device),
            self.seam_pairs.to(device=device),
        )
        out._topo = {k: _move(v, device) for k, v in self._topo.items()}
        return out

    def clone(self) -> GarmentMesh:
        """A deep copy (tensors cloned, caches dropped; the immutable ``layout`` is shared)."""
        return self._new(
            self.x.clone(), self.faces.clone(), None if self.p is None else self.p.clone(),
            None if self.panel_ids is None else self.panel_ids.clone(), self.seam_pairs.clone(),
        )

    def with_positions(self, x: torch.Tensor) -> GarmentMesh:
        """The same mesh with new 3D positions ``x`` (V, 3); topology caches are shared, not recomputed."""
        if not isinstance(x, torch.Tensor) or x.shape != self.x.shape:
            raise MeshError(f"with_positions needs a {tuple(self.x.shape)} tensor, got {_describe(x)}")
        p = self.p
        if p is not None and (p.dtype != x.dtype or p.device != x.device):
            p = p.to(device=x.device, dtype=x.dtype)
        out = GarmentMesh(x, self.faces.to(x.device), p=p,
                          panel_ids=None if self.panel_ids is None else self.panel_ids.to(x.device),
                          panel_names=self.panel_names, seam_pairs=self.seam_pairs.to(x.device),
                          layout=None if self.layout is None else self.layout.to(x.device))
        out._topo = (self._topo if x.device == self.device
                     else {k: _move(v, x.device) for k, v in self._topo.items()})
        return out

    # ------------------------------------------------------------------------------------ topology
    def _edge_table(self) -> None:
        """Fill edges, face_edges, edge_counts and the sorted occurrence table."""
        f = self.faces
        edges, face_edges, counts = edge_table(f)
        self._topo["edges"] = edges
        self._topo["face_edges"] = face_edges
        self._topo["edge_counts"] = counts
        directed = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], dim=0)  # (3F, 2); row k*F + i
        inverse = face_edges.T.reshape(-1)  # (3F,) edge of each row of `directed`
        # occurrences (rows of `directed`) grouped by edge; start offset of each edge's group
        order = torch.argsort(inverse, stable=True)
        start = torch.cumsum(counts, 0) - counts
        self._topo["occurrence"] = (order, start, directed)

    @property
    def edges(self) -> torch.Tensor:
        """(E, 2) long unique undirected edges, smaller index first, sorted lexicographically."""
        if "edges" not in self._topo:
            self._edge_table()
        return self._topo["edges"]

    @property
    def face_edges(self) -> torch.Tensor:
        """(F, 3) long: ``face_edges[f, k]`` indexes :attr:`edges` for the side ``faces[f, k]`` ->
        ``faces[f, k+1]``."""
        if "face_edges" not in self._topo:
            self._edge_table()
        return self._topo["face_edges"]

    @property
    def edge_face_counts(self) -> torch.Tensor:
        """(E,) long number of faces using each edge (1 on the boundary, 2 inside, more if non-manifold)."""
        if "edge_counts" not in self._topo:
            self._edge_table()
        return self._topo["edge_counts"]

    @property
    def boundary_edges(self) -> torch.Tensor:
        """(B, 2) long boundary edges (used by one face), directed as in their face."""
        if "boundary_edges" not in self._topo:
            self.edges  # noqa: B018 - fills the table
            order, start, directed = self._topo["occurrence"]
            b = torch.nonzero(self._topo["edge_counts"] == 1, as_tuple=False).flatten()
            self._topo["boundary_edges"] = directed[order[start[b]]]
        return self._topo["boundary_edges"]

    @property
    def boundary_loops(self) -> list[torch.Tensor]:
        """Closed boundary loops, each a (L,) long tensor of vertices in face orientation, longest first.

        Raises:
            MeshError: a vertex has two outgoing boundary edges (non-manifold vertex), so loops are ambiguous.
        """
        if "boundary_loops" not in self._topo:
            self._topo["boundary_loops"] = _walk_loops(self.boundary_edges, self.num_vertices)
        return self._topo["boundary_loops"]

    def _hinge_table(self) -> None:
        self.edges  # noqa: B018 - fills the table
        order, start, directed = self._topo["occurrence"]
        F = self.num_faces
        interior = torch.nonzero(self._topo["edge_counts"] == 2, as_tuple=False).flatten()
        occ0 = order[start[interior]]
        occ1 = order[start[interior] + 1]
        f0, k0 = occ0 % F, occ0 // F
        f1, k1 = occ1 % F, occ1 // F
        v0 = directed[occ0, 0]
        v1 = directed[occ0, 1]
        v2 = self.faces[f0, (k0 + 2) % 3]
        v3 = self.faces[f1, (k1 + 2) % 3]
        self._topo["hinges"] = torch.stack([v0, v1, v2, v3], dim=1)
        self._topo["hinge_faces"] = torch.stack([f0, f1], dim=1)

    @property
    def hinges(self) -> torch.Tensor:
        """(H, 4) long bending stencils ``[v0, v1, v2, v3]``, one per interior edge (used by two faces).

        ``v0``-``v1`` is the shared edge, directed as in the first face ``(v0, v1, v2)``; ``v3`` is the
        opposite vertex of the second face (which, for consistently oriented faces, runs ``v1`` -> ``v0``).
        """
        if "hinges" not in self._topo:
            self._hinge_table()
        return self._topo["hinges"]

    @property
    def hinge_faces(self) -> torch.Tensor:
        """(H, 2) long: the two faces of each hinge, in the order of :attr:`hinges`."""
        if "hinge_faces" not in self._topo:
            self._hinge_table()
        return self._topo["hinge_faces"]

    @property
    def vertex_panel_ids(self) -> torch.Tensor:
        """(V,) long panel index of every vertex (from its faces), -1 for unreferenced vertices.

        Raises:
            MeshError: no ``panel_ids``, or a vertex is used by faces of two panels (panels must stay
                separate).
        """
        if "vertex_panel_ids" not in self._topo:
            if self.panel_ids is None:
                raise MeshError("this mesh has no panel_ids")
            V = self.num_vertices
            ids = self.panel_ids[:, None].expand(-1, 3).reshape(-1)
            idx = self.faces.reshape(-1)
            lo = torch.full((V,), torch.iinfo(torch.long).max, dtype=torch.long, device=self.device)
            hi = torch.full((V,), -1, dtype=torch.long, device=self.device)
            lo = lo.scatter_reduce(0, idx, ids, reduce="amin")
            hi = hi.scatter_reduce(0, idx, ids, reduce="amax")
            used = hi >= 0
            if bool((lo[used] != hi[used]).any()):
                v = int(torch.nonzero(used & (lo != hi))[0])
                raise MeshError(f"vertex {v} is used by faces of panels {int(lo[v])} and {int(hi[v])}")
            self._topo["vertex_panel_ids"] = torch.where(used, hi, torch.full_like(hi, -1))
        return self._topo["vertex_panel_ids"]

    # ------------------------------------------------------------------------------------ geometry
    def _cached_geometry(self, key: str, fn: Callable[[], torch.Tensor]) -> torch.Tensor:
        if key not in self._cache:
            self._cache[key] = fn()
        return self._cache[key]

    @property
    def face_normals(self) -> torch.Tensor:
        """(F, 3) unit face normals (right-hand rule on the face order); differentiable in ``x``."""
        def fn() -> torch.Tensor:
            c = _face_cross(self.x, self.faces)
            return c / torch.linalg.vector_norm(c, dim=1, keepdim=True).clamp_min(torch.finfo(c.dtype).tiny)
        return self._cached_geometry("face_normals", fn)

    @property
    def face_areas(self) -> torch.Tensor:
        """(F,) 3D triangle areas in square metres; differentiable in ``x``."""
        return self._cached_geometry(
            "face_areas", lambda: 0.5 * torch.linalg.vector_norm(_face_cross(self.x, self.faces), dim=1))

    @property
    def rest_face_areas(self) -> torch.Tensor:
        """(F,) signed 2D rest areas from ``p`` (positive for counter-clockwise faces), square metres.

        Raises:
            MeshError: the mesh has no rest positions.
        """
        if self.p is None:
            raise MeshError("this mesh has no 2D rest positions p")

        def fn() -> torch.Tensor:
            t = self.p[self.faces]
            e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
            return 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
        return self._cached_geometry("rest_face_areas", fn)

    @property
    def vertex_normals(self) -> torch.Tensor:
        """(V, 3) unit vertex normals, area-weighted average of face normals (zero for unused vertices)."""
        def fn() -> torch.Tensor:
            c = _face_cross(self.x, self.faces)  # length = 2 * area: area weighting for free
            n = torch.zeros_like(self.x).index_add(0, self.faces.reshape(-1), c.repeat_interleave(3, dim=0))
            norm = torch.linalg.vector_norm(n, dim=1, keepdim=True)
            return n / norm.clamp_min(torch.finfo(n.dtype).tiny)
        return self._cached_geometry("vertex_normals", fn)

    @property
    def edge_lengths(self) -> torch.Tensor:
        """(E,) 3D lengths of :attr:`edges` in metres; differentiable in ``x``."""
        def fn() -> torch.Tensor:
            e = self.edges
            return torch.linalg.vector_norm(self.x[e[:, 1]] - self.x[e[:, 0]], dim=1)
        return self._cached_geometry("edge_lengths", fn)

    # ------------------------------------------------------------------------------------ checks
    def validate(self, *, area_tol: float = DEFAULT_AREA_TOL, name: str = "garment mesh") -> None:
        """Raise :class:`MeshError` (one line) if the mesh is unusable.

        Checks: finite positions, face indices in range, no degenerate 3D triangles (area <= ``area_tol``)
        nor, with ``p``, degenerate 2D rest triangles or a panel whose rest triangles mix orientations; no
        unreferenced vertices; no edge shared by more than two faces; consistently oriented neighbours;
        ``panel_ids`` within ``panel_names`` and (with ``p``) panels not sharing vertices; seam pairs in
        range, distinct, and joining boundary vertices.
        """
        # edge-based checks use the cached 1D-keyed edge table (much faster than unique over rows)
        check_mesh(self.x, self.faces, require_manifold=False, name=name, area_tol=area_tol,
                   allow_unreferenced=False)
        V = self.num_vertices
        over = torch.nonzero(self.edge_face_counts > 2, as_tuple=False).flatten()
        if over.numel():
            raise MeshError(f"{name}: {over.numel()} non-manifold edges (shared by more than two faces), "
                            f"first {self.edges[over[0]].tolist()}")
        f = self.faces
        directed = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], dim=0)
        key = torch.sort(directed[:, 0] * V + directed[:, 1]).values
        dup = torch.nonzero(key[1:] == key[:-1], as_tuple=False).flatten()
        if dup.numel():
            k = int(key[dup[0]])
            raise MeshError(f"{name}: {dup.numel()} edges where neighbouring faces have opposite "
                            f"orientation, first {(k // V, k % V)}")
        if self.p is not None:
            if not bool(torch.isfinite(self.p).all()):
                raise MeshError(f"{name}: rest positions p are not finite")
            bad = find_degenerate_faces(self.p, self.faces, area_tol)
            if bad.numel():
                raise MeshError(f"{name}: {bad.numel()} degenerate rest (2D) triangles, first "
                                f"{bad[:5].tolist()}")
            # one orientation per panel (a panel drawn clockwise in 2D has all its rest triangles clockwise)
            group = self.panel_ids if self.panel_ids is not None else torch.zeros_like(self.faces[:, 0])
            sign = torch.sign(self.rest_face_areas).long()
            n_groups = int(group.max()) + 1
            smin = torch.full((n_groups,), 2, dtype=torch.long, device=self.device).scatter_reduce(
                0, group, sign, reduce="amin")
            smax = torch.full((n_groups,), -2, dtype=torch.long, device=self.device).scatter_reduce(
                0, group, sign, reduce="amax")
            mixed = torch.nonzero((smin != smax) & (smax > -2), as_tuple=False).flatten()
            if mixed.numel():
                raise MeshError(f"{name}: rest triangles of panel {int(mixed[0])} have mixed 2D orientations "
                                f"(some flipped)")
        if self.panel_ids is not None:
            if self.panel_ids.numel() and (int(self.panel_ids.min()) < 0
                                           or int(self.panel_ids.max()) >= max(len(self.panel_names), 1)):
                raise MeshError(f"{name}: panel_ids must lie in [0, {len(self.panel_names)}) "
                                "(one per panel name)")
            if self.p is not None:  # rest positions are per panel: panels must not share vertices
                self.vertex_panel_ids  # noqa: B018 - raises if they do
        s = self.seam_pairs
        if s.numel():
            if int(s.min()) < 0 or int(s.max()) >= V:
                raise MeshError(f"{name}: seam_pairs index vertices outside [0, {V})")
            if bool((s[:, 0] == s[:, 1]).any()):
                raise MeshError(f"{name}: a seam pair joins a vertex to itself")
            on_boundary = torch.zeros(V, dtype=torch.bool, device=self.device)
            on_boundary[self.boundary_edges.reshape(-1)] = True
            inside = torch.nonzero(~on_boundary[s].all(dim=1), as_tuple=False).flatten()
            if inside.numel():
                raise MeshError(f"{name}: {inside.numel()} seam pairs use interior vertices, first pair "
                                f"{s[inside[0]].tolist()}")

    # ------------------------------------------------------------------------------------ welding
    def welded(self) -> tuple[GarmentMesh, torch.Tensor]:
        """The mesh with every seam pair merged into one vertex (for rendering and measuring).

        Vertices joined through chains of seam pairs (corners where several seams meet) become one vertex
        at the mean of their 3D positions (differentiable in ``x``). Faces that collapse (two corners
        merged, e.g. at a dart tip) are dropped. The result has no ``p`` (rest positions of different
        panels do not agree), no seam pairs and no ``layout``; ``panel_ids`` are kept for the surviving faces.

        Returns:
            mesh: the welded mesh, (V', 3) positions.
            index_map: (V,) long, the new index of every vertex.
        """
        V = self.num_vertices
        index, n_new = seam_weld_index(self.seam_pairs.detach().cpu().numpy(), V)
        index_map = torch.as_tensor(index, dtype=torch.long, device=self.device)
        sums = torch.zeros(n_new, 3, dtype=self.dtype, device=self.device).index_add(0, index_map, self.x)
        counts = torch.zeros(n_new, dtype=self.dtype, device=self.device).index_add(
            0, index_map, torch.ones(V, dtype=self.dtype, device=self.device))
        x = sums / counts[:, None]
        faces, kept = welded_faces(index, self.faces.detach().cpu().numpy())
        keep = torch.as_tensor(kept, device=self.device)
        mesh = GarmentMesh(x, torch.as_tensor(faces, dtype=torch.long, device=self.device),
                           panel_ids=None if self.panel_ids is None else self.panel_ids[keep],
                           panel_names=self.panel_names)
        return mesh, index_map


def seam_weld_index(seam_pairs: np.ndarray, num_vertices: int) -> tuple[np.ndarray, int]:
    """The welded vertex of every vertex when the seams are closed: vertices joined through chains of seam
    pairs (corners where several seams meet) share one, numbered by their lowest vertex so that an unsewn
    mesh keeps its numbering (:meth:`GarmentMesh.welded`, the contact terms' welded collision mesh).

    Args:
        seam_pairs: (S, 2) int vertex pairs. num_vertices: V.

    Returns:
        ``(index, V')``: (V,) int64 welded indices in ``[0, V')`` and the number of welded vertices.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    V = int(num_vertices)
    s = np.asarray(seam_pairs, dtype=np.int64).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(s)), (s[:, 0], s[:, 1])), shape=(V, V))
    _, labels = connected_components(graph, directed=False)
    first = np.full(labels.max() + 1 if V else 0, V, dtype=np.int64)
    np.minimum.at(first, labels, np.arange(V))
    rank = np.empty_like(first)
    rank[np.argsort(first, kind="stable")] = np.arange(first.shape[0])
    return rank[labels], int(first.shape[0])


def welded_faces(index: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The faces of a welded mesh (:func:`seam_weld_index`): faces that collapse (two corners sewn together,
    e.g. at a dart tip) are dropped (:meth:`GarmentMesh.welded`, the contact terms' welded collision mesh).

    Args:
        index: (V,) int welded vertex of every vertex. faces: (F, 3) int triangles over the V vertices.

    Returns:
        ``(faces, kept)``: (F', 3) int64 triangles over the welded vertices and the (F,) bool mask of the
        faces kept.
    """
    w = np.asarray(index, dtype=np.int64)[np.asarray(faces, dtype=np.int64)]
    kept = (w[:, 0] != w[:, 1]) & (w[:, 1] != w[:, 2]) & (w[:, 0] != w[:, 2])
    return w[kept], kept


def _face_cross(x: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    t = x[faces]
    return torch.linalg.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0], dim=1)


def _move(v: Any, device: torch.device | str | None) -> Any:
    if isinstance(v, torch.Tensor):
        return v.to(device=device)
    if isinstance(v, (list, tuple)):
        return type(v)(_move(e, device) for e in v)
    return v


def _describe(t: Any) -> str:
    if isinstance(t, torch.Tensor):
        return f"{t.dtype} tensor of shape {tuple(t.shape)}"
    return type(t).__name__


def _walk_loops(boundary: torch.Tensor, num_vertices: int) -> list[torch.Tensor]:
    """Order directed boundary edges (B, 2) into closed loops with a successor-array walk."""
    if boundary.shape[0] == 0:
        return []
    b = boundary.detach().cpu().numpy()
    out_deg = np.bincount(b[:, 0], minlength=num_vertices)
    if (out_deg > 1).any():
        v = int(np.argmax(out_deg > 1))
        raise MeshError(f"boundary passes through vertex {v} more than once (non-manifold vertex)")
    succ = np.full(num_vertices, -1, dtype=np.int64)
    succ[b[:, 0]] = b[:, 1]
    visited = np.zeros(num_vertices, dtype=bool)
    loops = []
    for start in b[:, 0]:
        if visited[start]:
            continue
        loop = []
        v = int(start)
        while not visited[v]:
            visited[v] = True
            loop.append(v)
            v = int(succ[v])
            if v < 0:
                raise MeshError(f"boundary is not closed: it stops at vertex {loop[-1]}")
        if v != start:
            raise MeshError(f"boundary walk from vertex {int(start)} runs into another loop at vertex {v}")
        loops.append(torch.as_tensor(loop, dtype=torch.long, device=boundary.device))
    loops.sort(key=lambda t: -t.shape[0])
    return loops
