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
* **bust**: the nipple level is the highest local maximum (over +-0.01 ``h``; the window is truncated at the
  top of the band, so a high breast just under the armpits still counts) of the front profile (the most
  frontal point of the torso loop as a function of height) between ``armpit - 0.15 h`` and ``armpit - 0.005
  h``, refined to sub-sample precision with a parabola; the bust is the maximum torso girth within +-0.0075
  ``h`` of it (the tape slid to the fullest part, also refined with a parabola). Without such a maximum (flat
  chest) the nipple level is the level of maximum torso girth in that band.
* **underbust**: below the nipple the front profile drops steeply with the breast down to the breast fold,
  where the rib cage takes over and the profile flattens (or turns forward again over a belly). The fold is
  the *soft* minimum (temperature ``0.001 h`` of depth) of the tilted profile ``front(y) - 0.3 y`` within
  ``0.08 h`` below the nipple, i.e. about where the profile's slope drops below 0.3; the tape sits just under
  it, at ``fold - 0.005 h``. With a breast depth (nipple front minus fold front) below ``0.01 h`` the level is
  blended linearly towards ``nipple - 0.035 h`` (the fold distance of the GarmentCode mean bodies), the rule
  for a flat chest. Every step is continuous in the shape (no thresholds, no discrete picks among sections),
  so the underbust plane moves little when the body changes little, even for large, low-hanging breasts
  whose fold is a crease.
* **waist**: horizontal plane of minimum torso girth between ``crotch + 0.1 h`` and ``underbust - 0.03 h``
  (the natural waist of the GarmentCode mean bodies and of every chart body lies 0.031-0.065 ``h`` below the
  underbust; a torso that keeps narrowing up to the breast fold, i.e. a waist larger than the underbust, is
  measured 0.03 ``h`` under the fold, about where a tape goes round a belly, not just under the fold).
* **hips**: the buttocks level is the most posterior point of the torso between crotch and waist; the hips are
  the maximum torso girth within +-0.01 ``h`` of it.
* **thigh**: horizontal plane ``0.01 h`` below the crotch, the body's right leg (as GarmentCode's
  ``leg_circ``).
* **arm** (the body's right arm, as GarmentCode's ``wrist``): a centreline is traced by cutting with planes
  normal to the lateral axis from the side of the chest outwards (the arm loop is the highest loop in each
  cut); it runs from the shoulder to the fingertips, parametrised by arc-length fraction. Girths are taken
  perpendicular to the local centreline direction (a chord over +-3 samples, about +-2.5 cm), at the loop
  around the centreline point; loops reaching within half a chest width of the mid-sagittal plane have merged
  with the torso and are skipped.
* **wrist**: the hand is the maximum girth at fractions 0.65-0.9; the wrist is the minimum girth between
  fraction 0.5 and the hand (refined in steps of 0.004).
* **upper_arm**: with ``first`` the first isolated arm section and the elbow at ``first + 0.55 (wrist -
  first)``, the maximum girth between ``first + 0.25 (elbow - first)`` and the elbow (the top quarter is left
  out: there the perpendicular plane slices obliquely through the deltoid and armpit fold).
* **neck**: the *minimum* neck girth: the minimum horizontal torso girth between ``armpit + 0.03 h`` and 90 %
  of the height gives its level; the plane is then tilted perpendicular to the neck axis (the line through the
  torso-loop centroids 0.015 ``h`` above and below) and the minimum over nine offsets of +-0.008 ``h`` along
  the axis is taken.

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
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial import ConvexHull, QhullError

from torchgarment.errors import InputError, MeshError
from torchgarment.structures.mesh_checks import edge_table

GIRTH_NAMES = ("bust", "underbust", "waist", "hips", "thigh", "upper_arm", "neck", "wrist")

_UP = np.array([0.0, 1.0, 0.0])

_WAIST_BELOW_UNDERBUST = 0.03
"""The waist search band ends this far below the underbust plane, in units of the body height."""
_FOLD_SLOPE = 0.3
"""Slope (metres of front depth per metre of height) of the front profile below which the breast has ended."""

_FOLD_SEARCH = 0.08
"""How far below the nipple the breast fold is searched, as a fraction of the height."""

_FOLD_SOFTNESS = 0.001
"""Temperature (fraction of the height, in front depth) of the soft minimum that places the breast fold:
levels whose tilted front depth is within a few times this of the minimum share the weight, so the fold moves
continuously with the shape instead of jumping between mesh rows."""

_FOLD_DEPTH = 0.01
"""Breast depth (nipple minus fold front depth, fraction of the height) from which the fold fully sets the
underbust; shallower breasts blend towards the flat-chest rule."""


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
        edge_face_ptr: (E + 1,) int64, edge_face_ids: (3F,) int64: the faces of edge i are
            ``edge_face_ids[edge_face_ptr[i]:edge_face_ptr[i + 1]]`` (CSR).
    """

    edges: np.ndarray
    face_edges: np.ndarray
    num_vertices: int
    edge_face_ptr: np.ndarray
    edge_face_ids: np.ndarray

    def faces_of(self, edge_ids: np.ndarray) -> np.ndarray:
        """Sorted unique ids of the faces that contain any of the edges ``edge_ids`` (K,)."""
        start, stop = self.edge_face_ptr[edge_ids], self.edge_face_ptr[edge_ids + 1]
        return np.unique(self.edge_face_ids[_ranges(start, stop - start)])


def _ranges(start: np.ndarray, count: np.ndarray) -> np.ndarray:
    """The concatenated index ranges ``[start[i], start[i] + count[i])`` (sum(count),)."""
    return np.repeat(start, count) + np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)


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
        edges, face_edges, counts = (t.numpy() for t in edge_table(torch.tensor(f)))
        order = np.argsort(face_edges.reshape(-1), kind="stable")  # (3F,) face-major sides grouped by edge
        ptr = np.concatenate([[0], np.cumsum(counts)])
        topo = _Topology(edges=edges, face_edges=face_edges, num_vertices=int(f.max()) + 1,
                         edge_face_ptr=ptr, edge_face_ids=order // 3)
        if len(_TOPOLOGY_CACHE) > 8:
            _TOPOLOGY_CACHE.clear()
        _TOPOLOGY_CACHE[key] = topo
    return topo


def plane_basis(normal: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal in-plane axes (u, w) with u x w = normal."""
    n = normal / np.linalg.norm(normal)
    a = np.eye(3)[int(np.argmin(np.abs(n)))]
    u = a - a.dot(n) * n
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(n, u)])


@dataclass
class SectionLoop:
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


def _components(seg: np.ndarray, n: int) -> tuple[int, np.ndarray]:
    """Connected components of the graph of ``n`` nodes and the (S, 2) edges ``seg``: (count, (n,) labels),
    labelled in the order of their smallest node (as ``scipy.sparse.csgraph.connected_components`` does,
    without its per-call overhead: a cut takes 255 of these to find a waist).

    Union by smaller label and pointer jumping: each round hooks every edge's larger root under the smaller,
    then flattens the trees; a section's loops take 2-4 rounds.
    """
    lab = np.arange(n)
    a, b = seg[:, 0], seg[:, 1]
    while True:
        la, lb = lab[a], lab[b]
        differ = la != lb
        if not differ.any():
            break
        np.minimum.at(lab, np.maximum(la, lb)[differ], np.minimum(la, lb)[differ])
        while True:
            up = lab[lab]
            if np.array_equal(up, lab):
                break
            lab = up
    roots, labels = np.unique(lab, return_inverse=True)
    return len(roots), labels.reshape(-1)


def _graph_loops(fe: np.ndarray, edge_ids: np.ndarray, v0: np.ndarray, v1: np.ndarray, d0: np.ndarray,
                 d1: np.ndarray) -> list[tuple[int, SectionLoop]]:
    """The loops of a section graph: a node per crossed edge, a segment per cut face.

    Args:
        fe: (C, 3) node of each cut face's crossing sides, -1 on the side it does not cross.
        edge_ids: (n,) the mesh edge of each node. v0, v1: (n, 3) its end points; d0, d1: (n,) their signed
            distances to the cutting plane (of opposite signs).

    Returns:
        ``(first node, loop)`` per connected component, in the order of their smallest node.
    """
    # the two crossing edges of each cut face, in column order
    order = np.argsort(fe < 0, axis=1, kind="stable")[:, :2]
    seg = np.take_along_axis(fe, order, axis=1)
    n = len(edge_ids)
    ncomp, labels = _components(seg, n)
    degree = np.bincount(seg.ravel(), minlength=n)
    t = d0 / (d0 - d1)
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
        loops.append((int(nodes[0]), SectionLoop(edge_ids=edge_ids[nodes], points=pts[nodes],
                                                 closed=bool(np.all(degree[nodes] == 2)), segments=segs)))
    return loops


def _cut(vertices: np.ndarray, topo: _Topology, point: np.ndarray, normal: np.ndarray,
         edge_ids: np.ndarray | None = None) -> list[SectionLoop]:
    """Cut a mesh by a plane; return its connected section loops (detached numpy).

    A vertex is on the positive side when its signed distance is > 0, so every face is crossed by 0 or 2 of
    its edges and each crossed face contributes one segment between its two crossing points.

    Args:
        vertices: (V, 3) positions.
        topo: the mesh topology.
        point: (3,) a point on the plane.
        normal: (3,) plane normal.
        edge_ids: (K,) ascending ids of exactly the edges the plane crosses, when the caller knows them
            (:meth:`_Slicer.horizontal`); None: found here.

    Returns:
        The loops, each with its edge ids, points and segments; empty when the plane misses the mesh.
    """
    offset = float(point @ normal)
    e = topo.edges
    if edge_ids is None:
        pos = vertices @ normal - offset > 0
        edge_ids = np.flatnonzero(pos[e[:, 0]] != pos[e[:, 1]])
    if edge_ids.size == 0:
        return []
    cut_faces = topo.faces_of(edge_ids)  # 0 or 2 crossing edges per face
    fe = topo.face_edges[cut_faces]
    fe = np.searchsorted(edge_ids, fe).clip(max=len(edge_ids) - 1)
    fe[edge_ids[fe] != topo.face_edges[cut_faces]] = -1  # (C, 3) node of each crossing edge, -1 elsewhere
    v0, v1 = vertices[e[edge_ids, 0]], vertices[e[edge_ids, 1]]
    loops = [lp for _, lp in _graph_loops(fe, edge_ids, v0, v1, v0 @ normal - offset, v1 @ normal - offset)]
    return loops


def _pick_loop(loops: list[SectionLoop], seed: np.ndarray, basis: np.ndarray) -> SectionLoop | None:
    """The innermost loop whose polygon encloses ``seed`` (ray casting in the plane), else the nearest
    loop."""
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


def section_loops(vertices: torch.Tensor, faces: torch.Tensor, point: torch.Tensor,
                  normal: torch.Tensor) -> list[SectionLoop]:
    """The loops (closed and open, detached, numpy) where the plane through ``point`` (3,) with ``normal``
    (3,) cuts the mesh ``vertices`` (V, 3) / ``faces`` (F, 3); the same cut as :func:`section_girths`."""
    _check_mesh(vertices, faces)
    vd = vertices.detach().cpu().numpy().astype(np.float64, copy=False)
    p = np.asarray(point.detach().cpu() if isinstance(point, torch.Tensor) else point, dtype=np.float64)
    n = np.asarray(normal.detach().cpu() if isinstance(normal, torch.Tensor) else normal, dtype=np.float64)
    return _cut(vd, _topology(faces), p, n / np.linalg.norm(n))


def section_loop(vertices: torch.Tensor, faces: torch.Tensor, plane: SectionPlane) -> SectionLoop | None:
    """The loop :func:`section_girths` measures for ``plane``: the innermost one enclosing the plane's seed,
    else the nearest; None when the plane misses the mesh."""
    n = plane.normal.detach().cpu().numpy().astype(np.float64)
    loops = section_loops(vertices, faces, plane.point, plane.normal)
    return _pick_loop(loops, plane.seed.detach().cpu().numpy().astype(np.float64), plane_basis(n))


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
        raise MeshError(f"faces index vertex {int(faces.max())} but there are only {vertices.shape[0]} "
                        "vertices")


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

    Each plane cuts the mesh edges; the cut points are linear interpolations of the edge endpoints, so
    gradients flow to the vertices. The loop enclosing (or nearest to) the plane's seed is measured by the
    perimeter of its convex hull; the hull's corner order comes from scipy on detached coordinates (it is
    locally constant).

    Args:
        vertices: (V, 3) positions, metres, any float dtype and device.
        faces: (F, 3) long vertex indices of a closed (watertight) mesh.
        planes: placements, e.g. from :func:`find_section_planes`.

    Returns:
        For each plane name, a 0-dim tensor (the girth in metres) of ``vertices``' dtype and device.

    Raises:
        MeshError: the plane misses the mesh, or the picked section loop is not closed (open mesh) or
            degenerate.
    """
    _check_mesh(vertices, faces)
    topo = _topology(faces)
    if topo.num_vertices > vertices.shape[0]:
        raise MeshError("faces index more vertices than given")
    vd = vertices.detach().cpu().numpy().astype(np.float64, copy=False)
    names = list(planes)
    hull_edges, owner, nxt, pts, nrms = [], [], [], [], []
    count = 0
    for k, name in enumerate(names):
        plane = planes[name]
        p = plane.point.detach().cpu().numpy().astype(np.float64)
        n = plane.normal.detach().cpu().numpy().astype(np.float64)
        n = n / np.linalg.norm(n)
        seed = plane.seed.detach().cpu().numpy().astype(np.float64)
        basis = plane_basis(n)
        loop = _pick_loop(_cut(vd, topo, p, n), seed, basis)
        if loop is None:
            raise MeshError(f"the {name!r} plane does not cut the mesh")
        if not loop.closed:
            raise MeshError(f"the {name!r} section is not a closed loop: the mesh is open or non-manifold "
                            "there")
        hull = loop.hull_indices(basis)
        m = len(hull)
        hull_edges.append(loop.edge_ids[hull])
        owner.append(np.full(m, k))
        nxt.append(count + (np.arange(m) + 1) % m)
        pts.append(np.broadcast_to(p, (m, 3)))
        nrms.append(np.broadcast_to(n, (m, 3)))
        count += m
    if not names:
        return {}
    # one batched, differentiable evaluation of all hull corners: q = a + da / (da - db) (b - a)
    dev, dt = vertices.device, vertices.dtype
    e = torch.as_tensor(topo.edges[np.concatenate(hull_edges)], device=dev)
    pt = torch.as_tensor(np.concatenate(pts), dtype=dt, device=dev)
    nt = torch.as_tensor(np.concatenate(nrms), dtype=dt, device=dev)
    a, b = vertices[e[:, 0]], vertices[e[:, 1]]
    da, db = ((a - pt) * nt).sum(dim=1), ((b - pt) * nt).sum(dim=1)
    q = a + (da / (da - db)).unsqueeze(1) * (b - a)
    seg = torch.linalg.vector_norm(q[torch.as_tensor(np.concatenate(nxt), device=dev)] - q, dim=1)
    total = torch.zeros(len(names), dtype=dt, device=dev).index_add(
        0, torch.as_tensor(np.concatenate(owner), device=dev), seg
    )
    return {name: total[k] for k, name in enumerate(names)}


# ----------------------------------------------------------------------------------------------------------
# Landmarks
# ----------------------------------------------------------------------------------------------------------


@dataclass
class _Frame:
    """Body frame (detached): heights, horizontal axes and the lateral centre.

    Attributes:
        y0: lowest y, metres.
        height: vertical extent, metres.
        left: (3,) horizontal unit vector towards the body's left.
        front: (3,) horizontal unit vector towards the body's front.
    """

    y0: float
    height: float
    left: np.ndarray
    front: np.ndarray


class _Slicer:
    """Horizontal and oblique cuts of one (detached) mesh, with the body frame."""

    def __init__(self, vertices: np.ndarray, topo: _Topology) -> None:
        self.v = vertices
        self.topo = topo
        self._lo: np.ndarray | None = None  # the horizontal cuts' edge index (built on the first cut)
        y = vertices[:, 1]
        y0, h = float(y.min()), float(np.ptp(y))
        if h <= 0:
            raise MeshError("the mesh is flat (zero height)")
        # lateral axis: horizontal direction of largest spread (arm span)
        xz = vertices[:, [0, 2]] - vertices[:, [0, 2]].mean(axis=0)
        _, vecs = np.linalg.eigh(xz.T @ xz)
        lat = np.array([vecs[0, 1], 0.0, vecs[1, 1]])
        depth = np.cross(lat, _UP)
        # front: the toes point forward, so the feet reach further front than the ankles do
        feet = vertices[y < y0 + 0.03 * h]
        shins = vertices[(y > y0 + 0.08 * h) & (y < y0 + 0.12 * h)]
        if len(feet) == 0 or len(shins) == 0:
            raise MeshError("cannot find the feet of the body (is +Y up?)")
        df = feet @ depth
        ds = shins @ depth
        toe_front = df.max() - ds.max()
        toe_back = ds.min() - df.min()
        front = depth if toe_front >= toe_back else -depth
        left = np.cross(_UP, front)
        self.frame = _Frame(y0=y0, height=h, left=left, front=front)
        self.basis = np.stack([left, front])  # 2D coordinates of horizontal sections: (lateral, depth)

    def _edge_index(self) -> None:
        """The edges sorted by their lower end's height (built on the first horizontal cut)."""
        if self._lo is None:
            ye = self.v[self.topo.edges, 1]  # (E, 2)
            lo, hi = ye.min(axis=1), ye.max(axis=1)
            self._order = np.argsort(lo, kind="stable")
            self._lo, self._hi = lo[self._order], hi[self._order]
            self._span = float((hi - lo).max())

    def horizontal(self, y: float) -> list[SectionLoop]:
        """The loops of the horizontal cut at height ``y``: the same as ``_cut`` with the plane, but the edges
        it crosses (one end at or below ``y``, the other above) are looked up among the few whose lower end
        lies within the longest edge's height below ``y``, not tested one by one."""
        self._edge_index()
        a = int(np.searchsorted(self._lo, y - self._span, side="left"))
        b = int(np.searchsorted(self._lo, y, side="right"))
        near = np.flatnonzero(self._hi[a:b] > y) + a
        return _cut(self.v, self.topo, np.array([0.0, y, 0.0]), _UP, np.sort(self._order[near]))

    def scan_up(self, start: float, step: float,
                chunk: int = 16) -> Iterator[tuple[float, list[SectionLoop]]]:
        """``(y, self.horizontal(y))`` for ``y = start + step``, ``+ step``, ... (summed one step at a time,
        as a loop doing ``y += step`` would), cut :meth:`horizontal_many` ``chunk`` levels at a time, so a
        search that stops early cuts few levels beyond its stop. Endless: the caller stops."""
        y = start
        while True:
            ys = np.cumsum(np.concatenate([[y], np.full(chunk, step)]))[1:]
            yield from zip(ys.tolist(), self.horizontal_many(ys))
            y = float(ys[-1])

    def horizontal_many(self, ys: np.ndarray) -> list[list[SectionLoop]]:
        """``[self.horizontal(y) for y in ys]`` (L,), identical loops, with every step of :func:`_cut` done
        once for all the levels: the section graph of all levels is one graph (a node per crossed (level,
        edge), level-major), whose components, labelled in the order of their smallest node, are the loops
        of each level in :func:`_cut`'s order. A torso profile's 120 cuts cost a few single cuts."""
        self._edge_index()
        ys = np.asarray(ys, dtype=np.float64).reshape(-1)
        out: list[list[SectionLoop]] = [[] for _ in range(ys.size)]
        topo, v = self.topo, self.v
        a = np.searchsorted(self._lo, ys - self._span, side="left")
        count = np.searchsorted(self._lo, ys, side="right") - a
        pos = _ranges(a, count)  # candidates: lower end within the longest edge's height below the level
        lev = np.repeat(np.arange(ys.size), count)
        keep = self._hi[pos] > ys[lev]
        eid, lev = self._order[pos[keep]], lev[keep]
        if eid.size == 0:
            return out
        num_edges, num_faces = len(topo.edges), len(topo.face_edges)
        node_key = np.sort(lev * num_edges + eid)  # (n,) distinct; level-major, edges ascending per level
        lev, eid = node_key // num_edges, node_key % num_edges
        n = node_key.size
        # the cut faces of each level, ascending (as np.unique in _Topology.faces_of)
        start = topo.edge_face_ptr[eid]
        nf = topo.edge_face_ptr[eid + 1] - start
        face_key = np.sort(np.repeat(lev, nf) * num_faces + topo.edge_face_ids[_ranges(start, nf)])
        face_key = face_key[np.concatenate([[True], face_key[1:] != face_key[:-1]])]  # each cut face once
        cut_lev, cut_face = face_key // num_faces, face_key % num_faces
        sides = cut_lev[:, None] * num_edges + topo.face_edges[cut_face]  # (C, 3) node keys of the sides
        fe = np.searchsorted(node_key, sides).clip(max=n - 1)
        fe[node_key[fe] != sides] = -1  # (C, 3) node of each crossing side, -1 elsewhere
        e = topo.edges
        v0, v1 = v[e[eid, 0]], v[e[eid, 1]]
        for first, loop in _graph_loops(fe, eid, v0, v1, v0 @ _UP - ys[lev], v1 @ _UP - ys[lev]):
            out[int(lev[first])].append(loop)
        return out

    def lateral_range(self, loop: SectionLoop) -> tuple[float, float]:
        s = loop.points @ self.frame.left
        return float(s.min()), float(s.max())


def _overlaps(a: tuple[float, float], b: tuple[float, float]) -> bool:
    return a[0] <= b[1] and b[0] <= a[1]


def _find_crotch(sl: _Slicer) -> tuple[float, float, list[tuple[float, float]]]:
    """Crotch height: where the two leg loops (tracked up from 25 % of the height) merge into one.

    Returns:
        (crotch y, lateral centre of the body, lateral ranges of the two legs just below the crotch)
    """
    f = sl.frame
    y = f.y0 + 0.25 * f.height
    loops = sl.horizontal(y)
    if len(loops) != 2:
        raise InputError(
            f"expected two legs at 25% of the body height, found {len(loops)} section loops: "
            "the mesh is not a standing human body"
        )
    legs = [sl.lateral_range(lp) for lp in loops]

    def step(legs_now: list[tuple[float, float]], yq: float, loops: list[SectionLoop] | None = None
             ) -> tuple[bool | None, list[tuple[float, float]]]:
        """(merged?, new leg ranges) at height ``yq`` (``loops``: its cut, when already made)"""
        ranges = [sl.lateral_range(lp) for lp in (sl.horizontal(yq) if loops is None else loops)]
        new = []
        for r in ranges:
            if _overlaps(r, legs_now[0]) and _overlaps(r, legs_now[1]):
                return True, legs_now
        for leg in legs_now:
            cands = [r for r in ranges if _overlaps(r, leg)]
            if not cands:
                return None, legs_now
            new.append(max(cands, key=lambda r: r[1] - r[0]))
        return False, new

    dy = 0.005 * f.height
    lo = y
    for hi, loops in sl.scan_up(y, dy):
        if hi > f.y0 + 0.7 * f.height:
            raise InputError("the legs never join: cannot find the crotch")
        merged, new = step(legs, hi, loops)
        if merged is None:
            raise InputError(f"lost track of a leg at height {hi - f.y0:.3f} m above the feet")
        if merged:
            break
        legs, lo = new, hi
    for _ in range(8):  # bisection to dy / 256
        mid = 0.5 * (lo + hi)
        merged, new = step(legs, mid)
        if merged:
            hi = mid
        elif merged is False:
            legs, lo = new, mid
        else:
            hi = mid
    centre = 0.5 * (max(legs[0][0], legs[1][0]) + min(legs[0][1], legs[1][1]))
    return 0.5 * (lo + hi), centre, legs


def _torso_loop(sl: _Slicer, loops: list[SectionLoop], centre: float) -> SectionLoop | None:
    """The loop whose lateral range contains the body's lateral centre (the largest if several)."""
    cands = [lp for lp in loops if (lambda r: r[0] < centre < r[1])(sl.lateral_range(lp))]
    if not cands:
        return None
    return max(cands, key=lambda lp: len(lp.points))


def _torso_profile(sl: _Slicer, centre: float, ys: np.ndarray) -> dict[str, np.ndarray]:
    """Torso loop girth, lateral width, front-most and back-most depth at heights ``ys``."""
    out = {k: np.full(len(ys), np.nan) for k in ("girth", "width", "front", "back", "lo", "hi")}
    for i, loops in enumerate(sl.horizontal_many(ys)):
        lp = _torso_loop(sl, loops, centre)
        if lp is None or not lp.closed:
            continue
        lat = lp.points @ sl.frame.left
        dep = lp.points @ sl.frame.front
        out["girth"][i] = lp.hull_perimeter(sl.basis)
        out["lo"][i], out["hi"][i] = lat.min(), lat.max()
        out["width"][i] = np.ptp(lat)
        out["front"][i], out["back"][i] = dep.max(), dep.min()
    return out


def _find_armpit(sl: _Slicer, crotch: float, centre: float) -> float:
    """Armpit height: the first height above the hips where the torso loop abruptly widens (arms join)."""
    f = sl.frame
    dy = 0.005 * f.height
    jump = 0.02 * f.height

    def width(yq: float, loops: list[SectionLoop] | None = None) -> float:
        lp = _torso_loop(sl, sl.horizontal(yq) if loops is None else loops, centre)
        if lp is None:
            raise InputError(f"no torso section at height {yq - f.y0:.3f} m above the feet")
        r = sl.lateral_range(lp)
        return r[1] - r[0]

    lo = crotch + 0.1 * f.height
    w_lo = width(lo)
    for hi, loops in sl.scan_up(lo, dy):
        if hi > f.y0 + 0.95 * f.height:
            raise InputError("the arms never join the torso: cannot find the armpits")
        w_hi = width(hi, loops)
        if w_hi - w_lo > jump:
            break
        lo, w_lo = hi, w_hi
    for _ in range(8):
        mid = 0.5 * (lo + hi)
        w_mid = width(mid)
        if w_mid - w_lo > jump:
            hi = mid
        else:
            lo, w_lo = mid, w_mid
    return lo


def _local_maxima(values: np.ndarray, half_window: int) -> np.ndarray:
    """Indices i whose value is the strict maximum of values[i-hw : i+hw+1].

    Windows are truncated at the ends of the array (a peak close to an end is still found) but must keep at
    least one neighbour on each side, which must be lower.
    """
    idx = []
    n = len(values)
    for i in range(1, n - 1):
        win = values[max(0, i - half_window) : min(n, i + half_window + 1)]
        if np.all(np.isfinite(win)) and values[i] == win.max() and win[0] < values[i] and win[-1] < values[i]:
            idx.append(i)
    return np.asarray(idx, dtype=np.int64)


def _parabolic_offset(values: np.ndarray, i: int) -> float:
    """Sub-sample position (in samples, within [-0.5, 0.5]) of the extremum at ``values[i]``.

    The parabola through the samples i-1, i, i+1; 0 at the ends of the array or where it is not curved.
    """
    if i <= 0 or i >= len(values) - 1:
        return 0.0
    a, b, c = values[i - 1], values[i], values[i + 1]
    den = a - 2.0 * b + c
    if not np.isfinite(den) or abs(den) < 1e-15:
        return 0.0
    return float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))


def _arm_centreline(sl: _Slicer, chest_lo: float, crotch: float) -> np.ndarray:
    """(K, 3) centroids of the right arm's sections by planes normal to the lateral axis, shoulder to
    fingertip.

    The planes run from the right side of the chest outwards; at each, the arm is the section loop with the
    highest centroid (in A- and T-pose the arm is above the hip).
    """
    f = sl.frame
    lat = sl.v @ f.left
    step = 0.004 * f.height
    positions = np.arange(chest_lo - step, lat.min() + 0.5 * step, -step)
    cents = []
    for s in positions:
        loops = _cut(sl.v, sl.topo, s * f.left, f.left)
        if not loops:
            break
        c = [lp.points.mean(axis=0) for lp in loops]
        best = int(np.argmax([p[1] for p in c]))
        if c[best][1] <= crotch:
            break
        cents.append(c[best])
    if len(cents) < 10:
        raise InputError("cannot find the right arm: too few arm sections outside the chest")
    return np.asarray(cents)


def _arc_fraction(line: np.ndarray) -> np.ndarray:
    seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    return s / s[-1]


def _perp_girths(sl: _Slicer, line: np.ndarray, normal: np.ndarray, fractions: np.ndarray, arc: np.ndarray,
                 centre: float, half_chest: float) -> tuple[np.ndarray, np.ndarray]:
    """Hull girths of the loops around centreline points (at arc ``fractions``) cut perpendicular to
    ``normal``.

    A loop reaching within ``half_chest / 2`` of the body's lateral centre has merged with the torso: NaN.

    Returns:
        (girths (N,), centreline points (N, 3))
    """
    pts = np.stack([np.interp(fractions, arc, line[:, k]) for k in range(3)], axis=1)
    basis = plane_basis(normal)
    g = np.full(len(fractions), np.nan)
    for i, p in enumerate(pts):
        lp = _pick_loop(_cut(sl.v, sl.topo, p, normal), p, basis)
        if lp is None or not lp.closed:
            continue
        if np.min(np.abs(lp.points @ sl.frame.left - centre)) < 0.5 * half_chest:
            continue
        g[i] = lp.hull_perimeter(basis)
    return g, pts


def _local_direction(line: np.ndarray, arc: np.ndarray, fraction: float, half: int = 3) -> np.ndarray:
    j = min(int(np.searchsorted(arc, fraction)), len(line) - 1)
    d = line[min(j + half, len(line) - 1)] - line[max(j - half, 0)]
    return d / np.linalg.norm(d)


def _arm_planes(sl: _Slicer, chest: tuple[float, float], crotch: float,
                centre: float) -> dict[str, SectionPlane]:
    """Upper-arm and wrist planes on the right arm (see the module doc)."""
    line = _arm_centreline(sl, chest[0], crotch)
    arc = _arc_fraction(line)
    half_chest = 0.5 * (chest[1] - chest[0])

    def girths(fracs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        g = np.full(len(fracs), np.nan)
        normals = []
        pts = []
        for i, x in enumerate(fracs):
            n = _local_direction(line, arc, float(x))
            gi, p = _perp_girths(sl, line, n, np.array([x]), arc, centre, half_chest)
            g[i] = gi[0]
            normals.append(n)
            pts.append(p[0])
        return g, np.asarray(pts), np.asarray(normals)

    fr = np.linspace(0.0, 1.0, 41)
    g, _, _ = girths(fr)
    valid = np.flatnonzero(np.isfinite(g))
    if valid.size < 10:
        raise InputError("cannot measure the right arm: too few isolated arm sections")
    first = fr[valid[0]]
    hand_band = (fr >= 0.65) & (fr <= 0.9) & np.isfinite(g)
    if not hand_band.any():
        raise InputError("cannot find the right hand")
    hand = fr[hand_band][int(np.argmax(g[hand_band]))]
    fore_band = (fr >= 0.5) & (fr <= hand) & np.isfinite(g)
    if not fore_band.any():
        raise InputError("cannot find the right wrist")
    wrist0 = fr[fore_band][int(np.argmin(g[fore_band]))]
    fine = np.clip(np.arange(wrist0 - 0.02, wrist0 + 0.0201, 0.004), 0.0, 1.0)
    gw, pw, nw = girths(fine)
    if not np.isfinite(gw).any():
        raise InputError("cannot measure the right wrist")
    iw = int(np.nanargmin(gw))
    wrist_frac = fine[iw]
    elbow = first + 0.55 * (wrist_frac - first)
    up = np.arange(first + 0.25 * (elbow - first), elbow + 1e-9, 0.01)
    gu, pu, nu = girths(up)
    if not np.isfinite(gu).any():
        raise InputError("cannot measure the right upper arm")
    iu = int(np.nanargmax(gu))
    t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    return {
        "upper_arm": SectionPlane("upper_arm", t(pu[iu]), t(nu[iu]), t(pu[iu])),
        "wrist": SectionPlane("wrist", t(pw[iw]), t(nw[iw]), t(pw[iw])),
    }


def _refine_extreme(sl: _Slicer, centre: float, lo: float, hi: float, maximum: bool, n: int = 17) -> float:
    """Height of the max (or min) torso girth in [lo, hi]: ``n`` samples, then a parabola through the best
    three (so the height moves continuously with the shape)."""
    ys = np.linspace(lo, hi, n)
    g = _torso_profile(sl, centre, ys)["girth"]
    if not np.isfinite(g).any():
        raise InputError(f"no closed torso section between heights {lo:.3f} and {hi:.3f} m")
    i = int(np.nanargmax(g) if maximum else np.nanargmin(g))
    return float(ys[i] + _parabolic_offset(g, i) * (ys[1] - ys[0]))


def find_section_planes(
    vertices: torch.Tensor, faces: torch.Tensor, names: tuple[str, ...] | None = None
) -> dict[str, SectionPlane]:
    """Find where to put the tape measure for every girth of :data:`GIRTH_NAMES` (not differentiable).

    See the module docstring for the landmark heuristics.

    Args:
        vertices: (V, 3) positions of a closed human body mesh, metres, +Y up, A- or T-pose, any placement.
        faces: (F, 3) long vertex indices.
        names: only these girths (default: all of :data:`GIRTH_NAMES`); skipping the neck and the arms saves
            most of the time. The planes found do not depend on this choice.

    Returns:
        Planes by girth name (in the order of :data:`GIRTH_NAMES`); tensors are float64 on the CPU.

    Raises:
        MeshError: the mesh is empty, open or malformed.
        InputError: a landmark cannot be found (the mesh does not look like a standing human body).
    """
    wanted = GIRTH_NAMES if names is None else tuple(names)
    unknown = sorted(set(wanted) - set(GIRTH_NAMES))
    if unknown:
        raise InputError(f"unknown girth name(s) {unknown}; known: {', '.join(GIRTH_NAMES)}")
    _check_mesh(vertices, faces)
    topo = _topology(faces)
    _check_closed(topo)
    v = vertices.detach().cpu().numpy().astype(np.float64)
    sl = _Slicer(v, topo)
    f = sl.frame
    h = f.height
    crotch, centre, legs = _find_crotch(sl)
    armpit = _find_armpit(sl, crotch, centre)
    up = torch.as_tensor(_UP, dtype=torch.float64)

    def horizontal_plane(name: str, y: float, seed: np.ndarray) -> SectionPlane:
        return SectionPlane(name, up * y, up.clone(), torch.as_tensor(seed, dtype=torch.float64))

    def torso_seed(y: float) -> np.ndarray:
        lp = _torso_loop(sl, sl.horizontal(y), centre)
        if lp is None:
            raise InputError(f"no torso section at height {y - f.y0:.3f} m above the feet")
        c = lp.points.mean(axis=0)
        return np.array([c[0], y, c[2]])

    g = 0.0025 * h
    ys = np.arange(crotch + g, armpit - 0.005 * h, g)
    prof = _torso_profile(sl, centre, ys)
    chest = (float(prof["lo"][-1]), float(prof["hi"][-1]))

    # bust: the nipple level is the highest local maximum of the front profile in the chest band (windows
    # truncated at the top of the band, so a high breast close to the armpits is still found), refined to
    # sub-sample precision; the bust is the largest girth around it
    front = prof["front"]
    band = np.flatnonzero(ys >= armpit - 0.15 * h)
    hw = max(1, int(round(0.01 * h / g)))
    peaks = band[0] + _local_maxima(front[band], hw)
    if peaks.size:
        i_nip = int(peaks.max())
        nipple = float(ys[i_nip] + _parabolic_offset(front, i_nip) * g)
    else:  # flat chest: no breast point; use the level of largest torso girth in the band
        i_nip = int(band[int(np.nanargmax(prof["girth"][band]))])
        nipple = float(ys[i_nip])
    bust = _refine_extreme(sl, centre, nipple - 0.0075 * h, nipple + 0.0075 * h, maximum=True, n=9)

    # underbust: the breast fold is where the front profile, going down from the nipple, stops falling
    # steeply: the (soft) minimum of front(y) - FOLD_SLOPE * y within FOLD_SEARCH below the nipple (the level
    # where the profile's slope drops below FOLD_SLOPE). The tape sits 0.005 h under it. Shallow breasts blend
    # continuously towards nipple - 0.035 h (flat chest) with the breast depth.
    below = np.flatnonzero((ys >= nipple - _FOLD_SEARCH * h) & (ys <= ys[i_nip]) & np.isfinite(front))
    if below.size < 3:
        raise InputError("the torso is too short to find the underbust")
    tilted = front[below] - _FOLD_SLOPE * ys[below]
    weights = np.exp(-(tilted - tilted.min()) / (_FOLD_SOFTNESS * h))
    fold = float(np.sum(weights * ys[below]) / np.sum(weights))
    depth = float(front[i_nip] - np.interp(fold, ys[below], front[below]))
    w = float(np.clip(depth / (_FOLD_DEPTH * h), 0.0, 1.0))
    underbust = (1.0 - w) * (nipple - 0.035 * h) + w * (fold - 0.005 * h)

    # waist: minimum torso girth between crotch + 0.1 h and just below the underbust
    wb = np.flatnonzero((ys >= crotch + 0.1 * h) & (ys <= underbust - _WAIST_BELOW_UNDERBUST * h))
    if wb.size == 0:
        raise InputError("the torso is too short to find the waist")
    waist0 = float(ys[wb][int(np.nanargmin(prof["girth"][wb]))])
    waist = _refine_extreme(sl, centre, waist0 - g, waist0 + g, maximum=False, n=9)

    # hips: level of the buttocks (most posterior torso point below the waist), then the max girth nearby
    hb = np.flatnonzero((ys > crotch) & (ys < waist))
    buttocks = float(ys[hb][int(np.nanargmin(prof["back"][hb]))])
    hips = _refine_extreme(sl, centre, buttocks - 0.01 * h, buttocks + 0.01 * h, maximum=True, n=17)

    # thigh: right leg, 0.01 h below the crotch
    y_thigh = crotch - 0.01 * h
    right = [lp for lp in sl.horizontal(y_thigh) if float(lp.points.mean(axis=0) @ f.left) < centre]
    if not right:
        raise InputError("cannot find the right thigh below the crotch")
    thigh_loop = max(right, key=lambda lp: len(lp.points))
    thigh_seed = thigh_loop.points.mean(axis=0)

    planes = {
        "bust": horizontal_plane("bust", bust, torso_seed(bust)),
        "underbust": horizontal_plane("underbust", underbust, torso_seed(underbust)),
        "waist": horizontal_plane("waist", waist, torso_seed(waist)),
        "hips": horizontal_plane("hips", hips, torso_seed(hips)),
        "thigh": horizontal_plane("thigh", y_thigh, thigh_seed),
    }
    if "neck" in wanted:
        planes["neck"] = _neck_plane(sl, armpit, centre, torso_seed)
    if "upper_arm" in wanted or "wrist" in wanted:
        planes.update(_arm_planes(sl, chest, crotch, centre))
    return {name: planes[name] for name in GIRTH_NAMES if name in wanted}


def _neck_plane(sl: _Slicer, armpit: float, centre: float,
                torso_seed: Callable[[float], np.ndarray]) -> SectionPlane:
    """The neck plane (see the module doc); ``torso_seed(y)`` is the torso loop centroid at height y."""
    f = sl.frame
    h = f.height
    g = 0.0025 * h
    nys = np.arange(armpit + 0.03 * h, f.y0 + 0.9 * h, g)
    nprof = _torso_profile(sl, centre, nys)
    if not np.isfinite(nprof["girth"]).any():
        raise InputError("cannot find the neck")
    neck_y = float(nys[int(np.nanargmin(nprof["girth"]))])
    c_lo, c_hi = torso_seed(neck_y - 0.015 * h), torso_seed(neck_y + 0.015 * h)
    axis = (c_hi - c_lo) / np.linalg.norm(c_hi - c_lo)
    c_mid = 0.5 * (c_lo + c_hi)
    best = None
    basis = plane_basis(axis)
    for off in np.linspace(-0.008 * h, 0.008 * h, 9):
        p = c_mid + off * axis
        lp = _pick_loop(_cut(sl.v, sl.topo, p, axis), p, basis)
        if lp is None or not lp.closed:
            continue
        gn = lp.hull_perimeter(basis)
        if best is None or gn < best[0]:
            best = (gn, p)
    if best is None:
        raise InputError("cannot measure the neck")
    t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    return SectionPlane("neck", t(best[1]), t(axis), t(best[1]))


def _check_closed(topo: _Topology) -> None:
    """Raise MeshError unless every edge is shared by exactly two faces."""
    counts = np.bincount(topo.face_edges.ravel(), minlength=len(topo.edges))
    if np.any(counts == 1):
        raise MeshError(f"the mesh is open: {int(np.sum(counts == 1))} boundary edges; measuring needs a "
                        "closed body")
    if np.any(counts > 2):
        raise MeshError(f"the mesh is non-manifold: {int(np.sum(counts > 2))} edges shared by more than two "
                        "faces")


def measure_body(vertices: torch.Tensor, faces: torch.Tensor) -> BodyMeasurements:
    """Measure height and all girths of a closed human body mesh.

    Args:
        vertices: (V, 3) positions, metres, +Y up, A- or T-pose, any placement.
        faces: (F, 3) long vertex indices of a closed mesh.

    Returns:
        The measurements (metres) and the planes where the girths were taken.
    """
    planes = find_section_planes(vertices, faces)
    with torch.no_grad():
        girths = section_girths(vertices.detach(), faces, planes)
        height = float(body_height(vertices.detach()))
    return BodyMeasurements(height=height, **{k: float(g) for k, g in girths.items()}, planes=planes)
