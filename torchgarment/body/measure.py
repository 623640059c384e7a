"""Tape-measure body measurements of any closed triangle mesh: height and eight girths.

A girth is measured the way a tape measure is: a plane is placed on the body, the mesh is cut by the plane,
the closed section loop around the limb or torso of interest is picked, and the length of its convex hull
(a tape bridges concavities) is the girth. The cut is differentiable with respect to the vertices (section
points are linear interpolations of edge endpoints), so an optimiser can fit a body to target girths with
:func:`section_girths` and :func:`body_height`; only the choice of planes (:func:`find_section_planes`) is
discrete and is recomputed on detached data.

Conventions: +Y up, metres. The body may stand anywhere and face any horizontal direction; the lateral
(left-right) axis is the horizontal direction of largest vertex spread (the arm span in A- and T-pose) and the
front is the side the toes point to.

Landmark heuristics (all found from horizontal section loops, never from vertex labels; ``h`` is the height):

* **crotch**: the lowest height (scanning up from 25 % of ``h``) from which on a section loop *straddles* the
  body's mid-sagittal plane (its lateral extent contains the body's lateral centre). Below it the legs are two
  separate loops. Refined by bisection to 0.5 mm.
* **armpit**: scanning up from the hips, the first height where the straddling (torso) loop abruptly widens by
  more than 0.02 ``h`` between two neighbouring sections: the arms join the torso. Refined by bisection.
* **bust**: horizontal plane of maximum torso girth between ``armpit - 0.12 h`` and ``armpit - 0.02 h``.
* **underbust**: below the bust, the front profile (the most frontal point of the torso loop as a function of
  height) drops with the breast and then flattens out on the rib cage: the underbust is the height, between the
  bust and ``bust - 0.07 h``, where the front profile has its largest convex bend (the breast fold; maximum
  second difference). On a flat-chested body this is the top of the rib-cage line just below the bust.
* **waist**: horizontal plane of minimum torso girth between the hips and the underbust.
* **hips**: horizontal plane of maximum torso girth around the buttocks, between
  ``crotch + 0.25 (waist_guess - crotch)`` and the waist guess (``waist_guess`` = the minimum torso girth between
  ``crotch + 0.1 h`` and the underbust). The lower bound excludes the sections through the tops of both thighs.
* **thigh**: horizontal plane ``0.01 h`` below the crotch, the body's left leg (GarmentCode's ``leg_circ``).
* **upper_arm**: the left arm's vertices (laterally outside the chest) give the arm axis by PCA; the upper arm
  is the part within 45 % of the arm length from the shoulder end. Planes perpendicular to the upper-arm axis
  are swept from the elbow towards the shoulder until the section loop merges with the torso; the maximum girth
  is the upper-arm girth.
* **neck**: the *minimum* neck girth: horizontal sections between the shoulders and the head give the level of
  minimum girth; the plane there is tilted perpendicular to the neck axis (the line through the centroids of
  neck sections 2 cm above and below), and the minimum over a few heights of that tilted plane is taken.
* **wrist**: planes perpendicular to the forearm axis (PCA of the left-arm vertices between 45 % and 85 % of
  the arm length) swept over the distal part of the forearm; the minimum girth is the wrist.

Comparison with GarmentCode's body YAML (``bodies/*.yaml``, cm; measured with the GarmentMeasurements tool of
Botsch et al. on a fixed mesh topology):

* ``bust``, ``waist``, ``hips``: horizontal plane, convex hull, local max / min / max around a fixed vertex
  ring: the same definition as here.
* ``underbust``: horizontal plane through a fixed vertex ring, convex hull (no search).
* ``leg_circ``: one thigh, horizontal plane slid down from the crotch until the section is a single leg ring;
  measured as the loop length, *not* the convex hull. It is our ``thigh``.
* ``wrist``: convex hull of a fixed vertex ring around the wrist.
* ``neck_w`` is a neck *width* (not a girth) and the YAML has no upper-arm girth, so ``neck`` and
  ``upper_arm`` have no reference value.
* ``bust_line``, ``waist_line``, ``hips_line`` are vertical distances used by GarmentCode's pattern drafting
  (neck-base to bust / waist, waist to hips); they are not used here.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, QhullError

from torchgarment.errors import InputError, MeshError

GIRTH_NAMES = ("bust", "underbust", "waist", "hips", "thigh", "upper_arm", "neck", "wrist")

_UP = np.array([0.0, 1.0, 0.0])


@dataclass
class SectionPlane:
    """One tape-measure placement.

    Attributes:
        name: the girth measured here (one of :data:`GIRTH_NAMES`).
        point: (3,) a point on the plane, metres.
        normal: (3,) unit normal of the plane.
        seed: (3,) a point inside the limb or torso to measure: the section loop enclosing it (or, when none
            encloses it, the loop nearest to it) is the one measured; other loops are ignored.
    """

    name: str
    point: torch.Tensor
    normal: torch.Tensor
    seed: torch.Tensor


@dataclass
class BodyMeasurements:
    """Height and girths of a body, metres.

    Attributes:
        height: vertical extent (max y - min y).
        bust, underbust, waist, hips, thigh, upper_arm, neck, wrist: convex-hull girths, see the module doc.
        planes: where each girth was taken, by girth name.
    """

    height: float
    bust: float
    underbust: float
    waist: float
    hips: float
    thigh: float
    upper_arm: float
    neck: float
    wrist: float
    planes: dict[str, SectionPlane] = field(default_factory=dict, repr=False)

    def to_dict(self) -> dict[str, float]:
        """The ten numbers (height and the girths), metres, as plain floats (JSON-ready)."""
        out = {"height": float(self.height)}
        for name in GIRTH_NAMES:
            out[name] = float(getattr(self, name))
        return out


# ----------------------------------------------------------------------------------------------------------
# Mesh topology and plane cuts
# ----------------------------------------------------------------------------------------------------------


@dataclass
class _Topology:
    """Unique edges of a triangle mesh and the three edge ids of every face.

    Attributes:
        edges: (E, 2) int64 vertex ids, sorted within each row.
        face_edges: (F, 3) int64 edge ids of the edges (v0,v1), (v1,v2), (v2,v0) of each face.
        num_vertices: highest vertex id + 1.
    """

    edges: np.ndarray
    face_edges: np.ndarray
    num_vertices: int


_TOPOLOGY_CACHE: dict[tuple, _Topology] = {}


def _topology(faces: torch.Tensor | np.ndarray) -> _Topology:
    """Edges of ``faces`` (F, 3), cached by content (fitting loops cut the same topology many times)."""
    f = faces.detach().cpu().numpy() if isinstance(faces, torch.Tensor) else np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise MeshError(f"faces must be a non-empty (F, 3) index array, got shape {tuple(f.shape)}")
    f = np.ascontiguousarray(f, dtype=np.int64)
    key = (f.shape, hashlib.blake2b(f.tobytes(), digest_size=16).hexdigest())
    topo = _TOPOLOGY_CACHE.get(key)
    if topo is None:
        if f.min() < 0:
            raise MeshError("faces contain negative vertex indices")
        he = np.stack([f, np.roll(f, -1, axis=1)], axis=2).reshape(-1, 2)
        he.sort(axis=1)
        edges, inverse = np.unique(he, axis=0, return_inverse=True)
        topo = _Topology(edges=edges, face_edges=inverse.reshape(-1, 3), num_vertices=int(f.max()) + 1)
        if len(_TOPOLOGY_CACHE) > 8:
            _TOPOLOGY_CACHE.clear()
        _TOPOLOGY_CACHE[key] = topo
    return topo


def _plane_basis(normal: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal in-plane axes (u, w) with u x w = normal."""
    n = normal / np.linalg.norm(normal)
    a = np.eye(3)[int(np.argmin(np.abs(n)))]
    u = a - a.dot(n) * n
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(n, u)])


@dataclass
class _Loop:
    """One connected section loop (detached, numpy).

    Attributes:
        edge_ids: (K,) ids of the mesh edges the loop crosses.
        points: (K, 3) section points, metres.
        closed: every section point has exactly two neighbours (the loop is a closed curve).
        segments: (S, 2) indices into ``points``: the section segments (one per cut face).
    """

    edge_ids: np.ndarray
    points: np.ndarray
    closed: bool
    segments: np.ndarray

    _hull: np.ndarray | None = None

    def hull_indices(self, basis: np.ndarray) -> np.ndarray:
        """Indices into ``points`` of the convex-hull corners, in order (counter-clockwise in ``basis``)."""
        if self._hull is None:
            p2 = self.points @ basis.T
            try:
                self._hull = ConvexHull(p2).vertices
            except (QhullError, ValueError) as exc:
                raise MeshError(f"degenerate section loop of {len(p2)} points: {exc}") from None
        return self._hull

    def hull_perimeter(self, basis: np.ndarray) -> float:
        h = self.points[self.hull_indices(basis)]
        return float(np.linalg.norm(h - np.roll(h, 1, axis=0), axis=1).sum())


def _cut(vertices: np.ndarray, topo: _Topology, point: np.ndarray, normal: np.ndarray) -> list[_Loop]:
    """Cut a mesh by a plane; return its connected section loops (detached numpy).

    A vertex is on the positive side when its signed distance is > 0, so every face is crossed by 0 or 2 of its
    edges and each crossed face contributes one segment between its two crossing points.

    Args:
        vertices: (V, 3) positions.
        topo: the mesh topology.
        point: (3,) a point on the plane.
        normal: (3,) plane normal.

    Returns:
        The loops, each with its edge ids, points and segments; empty when the plane misses the mesh.
    """
    d = (vertices - point) @ normal
    pos = d > 0
    e = topo.edges
    crossing = pos[e[:, 0]] != pos[e[:, 1]]
    fc = crossing[topo.face_edges]
    cut_faces = np.flatnonzero(fc.sum(axis=1) == 2)
    if cut_faces.size == 0:
        return []
    edge_ids = np.flatnonzero(crossing)
    node_of_edge = np.full(len(e), -1, dtype=np.int64)
    node_of_edge[edge_ids] = np.arange(len(edge_ids))
    fe = topo.face_edges[cut_faces]
    m = fc[cut_faces]
    # the two crossing edges of each cut face, in column order
    order = np.argsort(~m, axis=1, kind="stable")[:, :2]
    seg = node_of_edge[np.take_along_axis(fe, order, axis=1)]
    n = len(edge_ids)
    graph = coo_matrix((np.ones(len(seg)), (seg[:, 0], seg[:, 1])), shape=(n, n))
    ncomp, labels = connected_components(graph, directed=False)
    degree = np.bincount(seg.ravel(), minlength=n)
    d0, d1 = d[e[edge_ids, 0]], d[e[edge_ids, 1]]
    t = d0 / (d0 - d1)
    v0, v1 = vertices[e[edge_ids, 0]], vertices[e[edge_ids, 1]]
    pts = v0 + t[:, None] * (v1 - v0)
    order_nodes = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order_nodes], np.arange(ncomp + 1))
    local = np.empty(n, dtype=np.int64)
    seg_label = labels[seg[:, 0]]
    seg_order = np.argsort(seg_label, kind="stable")
    seg_bounds = np.searchsorted(seg_label[seg_order], np.arange(ncomp + 1))
    loops = []
    for c in range(ncomp):
        nodes = order_nodes[bounds[c] : bounds[c + 1]]
        local[nodes] = np.arange(len(nodes))
        segs = local[seg[seg_order[seg_bounds[c] : seg_bounds[c + 1]]]]
        loops.append(
            _Loop(
                edge_ids=edge_ids[nodes],
                points=pts[nodes],
                closed=bool(np.all(degree[nodes] == 2)),
                segments=segs,
            )
        )
    return loops


def _pick_loop(loops: list[_Loop], seed: np.ndarray, basis: np.ndarray) -> _Loop | None:
    """The innermost loop whose polygon encloses ``seed`` (ray casting in the plane), else the nearest loop."""
    if not loops:
        return None
    s = seed @ basis.T
    best, best_key = None, None
    for loop in loops:
        p2 = loop.points @ basis.T
        a, b = p2[loop.segments[:, 0]], p2[loop.segments[:, 1]]
        straddle = (a[:, 1] > s[1]) != (b[:, 1] > s[1])
        with np.errstate(divide="ignore", invalid="ignore"):
            x_cross = a[:, 0] + (s[1] - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
        inside = int(np.count_nonzero(straddle & (x_cross > s[0]))) % 2 == 1
        dist = float(np.min(np.linalg.norm(p2 - s, axis=1)))
        key = (0 if inside else 1, dist)
        if best_key is None or key < best_key:
            best, best_key = loop, key
    return best


# ----------------------------------------------------------------------------------------------------------
# Differentiable measuring
# ----------------------------------------------------------------------------------------------------------


def _check_mesh(vertices: torch.Tensor, faces: torch.Tensor) -> None:
    if not isinstance(vertices, torch.Tensor) or vertices.ndim != 2 or vertices.shape[1] != 3:
        raise MeshError(f"vertices must be a (V, 3) tensor, got {getattr(vertices, 'shape', type(vertices))}")
    if vertices.shape[0] == 0:
        raise MeshError("the mesh has no vertices")
    if not torch.is_floating_point(vertices):
        raise MeshError(f"vertices must be floating point, got {vertices.dtype}")
    if not bool(torch.isfinite(vertices.detach()).all()):
        raise MeshError("vertices contain NaN or infinite values")
    if int(faces.max()) >= vertices.shape[0]:
        raise MeshError(f"faces index vertex {int(faces.max())} but there are only {vertices.shape[0]} vertices")


def body_height(vertices: torch.Tensor) -> torch.Tensor:
    """Vertical extent of a body (differentiable).

    Args:
        vertices: (V, 3) positions, metres, +Y up.

    Returns:
        0-dim tensor: max y - min y, metres.
    """
    if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.shape[0] == 0:
        raise MeshError(f"vertices must be a non-empty (V, 3) tensor, got shape {tuple(vertices.shape)}")
    y = vertices[:, 1]
    return y.max() - y.min()


def section_girths(
    vertices: torch.Tensor, faces: torch.Tensor, planes: dict[str, SectionPlane]
) -> dict[str, torch.Tensor]:
    """Convex-hull girths of the section loops picked by ``planes`` (differentiable w.r.t. ``vertices``).

    Each plane cuts the mesh edges; the cut points are linear interpolations of the edge endpoints, so gradients
    flow to the vertices. The loop enclosing (or nearest to) the plane's seed is measured by the perimeter of its
    convex hull; the hull's corner order comes from scipy on detached coordinates (it is locally constant).

    Args:
        vertices: (V, 3) positions, metres, any float dtype and device.
        faces: (F, 3) long vertex indices of a closed (watertight) mesh.
        planes: placements, e.g. from :func:`find_section_planes`.

    Returns:
        For each plane name, a 0-dim tensor (the girth in metres) of ``vertices``' dtype and device.

    Raises:
        MeshError: the plane misses the mesh, or the picked section loop is not closed (open mesh) or degenerate.
    """
    _check_mesh(vertices, faces)
    topo = _topology(faces)
    if topo.num_vertices > vertices.shape[0]:
        raise MeshError("faces index more vertices than given")
    vd = vertices.detach().cpu().numpy().astype(np.float64, copy=False)
    edges_t = torch.as_tensor(topo.edges, device=vertices.device)
    out: dict[str, torch.Tensor] = {}
    for name, plane in planes.items():
        p = plane.point.detach().cpu().numpy().astype(np.float64)
        n = plane.normal.detach().cpu().numpy().astype(np.float64)
        n = n / np.linalg.norm(n)
        seed = plane.seed.detach().cpu().numpy().astype(np.float64)
        basis = _plane_basis(n)
        loop = _pick_loop(_cut(vd, topo, p, n), seed, basis)
        if loop is None:
            raise MeshError(f"the {name!r} plane does not cut the mesh")
        if not loop.closed:
            raise MeshError(f"the {name!r} section is not a closed loop: the mesh is open or non-manifold there")
        hull = loop.hull_indices(basis)
        e = edges_t[torch.as_tensor(loop.edge_ids[hull], device=vertices.device)]
        pt = torch.as_tensor(p, dtype=vertices.dtype, device=vertices.device)
        nt = torch.as_tensor(n, dtype=vertices.dtype, device=vertices.device)
        a, b = vertices[e[:, 0]], vertices[e[:, 1]]
        da, db = (a - pt) @ nt, (b - pt) @ nt
        q = a + (da / (da - db)).unsqueeze(1) * (b - a)
        out[name] = torch.linalg.vector_norm(q - torch.roll(q, 1, dims=0), dim=1).sum()
    return out
