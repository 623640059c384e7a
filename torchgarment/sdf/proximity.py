"""Closest points and pseudo-normal signed distances on a triangle mesh: NVIDIA Warp's BVH for the closest
triangle, float64 geometry for the rest, in one CPU kernel.

Warp (a dependency of torchgarment, and of anny) builds a bounding volume hierarchy of the
mesh in float32 and finds each point's closest triangle; the kernel then computes, in float64 on that
triangle, the closest point (Ericson, *Real-Time Collision Detection*, 5.1.5), the feature it lies on (face,
edge or vertex, by its barycentric coordinates), that feature's angle-weighted pseudo-normal (Baerentzen and
Aanaes 2005) and the sign. The distance is exact to the closest triangle's float64 distance; where two
triangles that share no edge or vertex are within float32 rounding of the same distance (about 1e-7 of the
coordinates' magnitude: a point on the medial axis of a crease) the float32 search may pick either, so the
distance is then within about 1e-7 m of libigl's and the closest point may be the other one.

Measured on the 26,692-triangle anny chart body and 30,000 points within 2 cm of it (1 thread, the slower
2-core box of issue 15): the tree and the pseudo-normals take 16 ms against 44-49 ms with libigl's tree, and
the query about 50-60 ms against libigl's 85 ms plus 28 ms of numpy for the signs
(``scripts/bench_pca_fit.py``). A body of a topology met before refits a released tree (0.4-0.6 ms against
10-12 ms for a build), so the bodies of one model after the first cost 4-7 ms with the pseudo-normals.

Shapes: ``vertices`` (V, 3) float64 metres, ``faces`` (F, 3) int, ``points`` (P, 3) float64 metres.
"""

from __future__ import annotations

import hashlib
import threading

import numpy as np
import torch

from torchgarment.structures.mesh_checks import edge_table
from torchgarment.warp_runtime import import_warp

_KERNELS: dict[str, object] = {}


def _kernels() -> dict[str, object]:
    """The Warp kernels (defined on first use: importing Warp takes about 1 s; the first launch on a machine
    compiles them once into Warp's kernel cache)."""
    if _KERNELS:
        return _KERNELS
    wp = import_warp()
    zero = wp.float64(0.0)

    @wp.func
    def closest_on_triangle(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> wp.vec3d:
        ab = b - a
        ac = c - a
        ap = p - a
        d1 = wp.dot(ab, ap)
        d2 = wp.dot(ac, ap)
        if d1 <= zero and d2 <= zero:
            return a
        bp = p - b
        d3 = wp.dot(ab, bp)
        d4 = wp.dot(ac, bp)
        if d3 >= zero and d4 <= d3:
            return b
        vc = d1 * d4 - d3 * d2
        if vc <= zero and d1 >= zero and d3 <= zero:
            return a + ab * (d1 / (d1 - d3))
        cp = p - c
        d5 = wp.dot(ab, cp)
        d6 = wp.dot(ac, cp)
        if d6 >= zero and d5 <= d6:
            return c
        vb = d5 * d2 - d1 * d6
        if vb <= zero and d2 >= zero and d6 <= zero:
            return a + ac * (d2 / (d2 - d6))
        va = d3 * d6 - d5 * d4
        if va <= zero and (d4 - d3) >= zero and (d5 - d6) >= zero:
            return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))
        s = va + vb + vc
        if s <= zero:  # a degenerate (zero-area) triangle that no region test caught
            return a
        return a + ab * (vb / s) + ac * (vc / s)

    @wp.kernel(enable_backward=False)
    def query(mesh: wp.uint64, v: wp.array(dtype=wp.vec3d), f: wp.array(dtype=wp.int32, ndim=2),
              face_normals: wp.array(dtype=wp.vec3d), edge_normals: wp.array(dtype=wp.vec3d),
              vertex_normals: wp.array(dtype=wp.vec3d), face_edge: wp.array(dtype=wp.int32, ndim=2),
              points: wp.array(dtype=wp.vec3d), feature_tol: wp.float64, stable: wp.int32, pad: wp.float32,
              sdist: wp.array(dtype=wp.float64), tri: wp.array(dtype=wp.int32),
              closest: wp.array(dtype=wp.vec3d), direction: wp.array(dtype=wp.vec3d)) -> None:
        i = wp.tid()
        p = points[i]
        q = wp.mesh_query_point_no_sign(mesh, wp.vec3(p), 1.0e30)
        t = q.face
        if stable != 0:
            # the float32 search may pick either of two triangles at nearly the same distance, and which one
            # depends on the tree's hierarchy (a fresh tree or a refitted one); the closest in float64 among
            # every triangle whose box meets the point's box of that distance (the lower index on a tie)
            # does not
            e = p - closest_on_triangle(p, v[f[t, 0]], v[f[t, 1]], v[f[t, 2]])
            best = wp.dot(e, e)
            r = wp.float32(wp.sqrt(best)) + pad
            box = wp.vec3(r, r, r)
            qa = wp.mesh_query_aabb(mesh, wp.vec3(p) - box, wp.vec3(p) + box)
            s = int(0)
            while wp.mesh_query_aabb_next(qa, s):
                e = p - closest_on_triangle(p, v[f[s, 0]], v[f[s, 1]], v[f[s, 2]])
                d2 = wp.dot(e, e)
                if d2 < best or (d2 == best and s < t):
                    best = d2
                    t = s
        a = v[f[t, 0]]
        b = v[f[t, 1]]
        c = v[f[t, 2]]
        cp = closest_on_triangle(p, a, b, c)
        # barycentric coordinates of the closest point: the feature it lies on picks the pseudo-normal
        v0 = b - a
        v1 = c - a
        v2 = cp - a
        d00 = wp.dot(v0, v0)
        d01 = wp.dot(v0, v1)
        d11 = wp.dot(v1, v1)
        d20 = wp.dot(v2, v0)
        d21 = wp.dot(v2, v1)
        den = wp.max(d00 * d11 - d01 * d01, wp.float64(1e-300))
        w1 = (d11 * d20 - d01 * d21) / den
        w2 = (d00 * d21 - d01 * d20) / den
        w0 = wp.float64(1.0) - w1 - w2
        n = face_normals[t]
        low = 0
        first = -1
        if w0 < feature_tol:
            low += 1
            first = 0
        if w1 < feature_tol:
            low += 1
            if first < 0:
                first = 1
        if w2 < feature_tol:
            low += 1
            if first < 0:
                first = 2
        if low == 1:  # on the edge opposite that corner
            n = edge_normals[face_edge[t, first]]
        if low >= 2:  # at the corner of the largest coordinate
            corner = 0
            if w1 > w0 and w1 >= w2:
                corner = 1
            elif w2 > w0 and w2 > w1:
                corner = 2
            n = vertex_normals[f[t, corner]]
        d = p - cp
        dist = wp.sqrt(wp.dot(d, d))
        sign = wp.float64(1.0)
        if wp.dot(d, n) < zero:
            sign = wp.float64(-1.0)
        if dist > wp.float64(1e-12):
            direction[i] = d * (sign / dist)
        else:
            direction[i] = n / wp.max(wp.length(n), wp.float64(1e-300))
        sdist[i] = sign * dist
        tri[i] = t
        closest[i] = cp

    @wp.kernel(enable_backward=False)
    def normals(v: wp.array(dtype=wp.vec3d), f: wp.array(dtype=wp.int32, ndim=2),
                face_edge: wp.array(dtype=wp.int32, ndim=2), face_normals: wp.array(dtype=wp.vec3d),
                vertex_normals: wp.array(dtype=wp.vec3d), edge_normals: wp.array(dtype=wp.vec3d)) -> None:
        t = wp.tid()
        p0 = v[f[t, 0]]
        p1 = v[f[t, 1]]
        p2 = v[f[t, 2]]
        e0 = p1 - p0  # edge k leaves corner k
        e1 = p2 - p1
        e2 = p0 - p2
        c = wp.cross(e0, -e2)
        n = c / wp.max(wp.length(c), wp.float64(1e-300))
        face_normals[t] = n
        tiny = wp.float64(1e-300)
        l0 = wp.max(wp.length(e0), tiny)
        l1 = wp.max(wp.length(e1), tiny)
        l2 = wp.max(wp.length(e2), tiny)
        one = wp.float64(1.0)
        # the angle at corner k, between the edge leaving it and the reversed edge arriving at it, weights
        # the face's normal in the vertex pseudo-normal
        a0 = wp.acos(wp.clamp(-wp.dot(e0, e2) / (l0 * l2), -one, one))
        a1 = wp.acos(wp.clamp(-wp.dot(e1, e0) / (l1 * l0), -one, one))
        a2 = wp.acos(wp.clamp(-wp.dot(e2, e1) / (l2 * l1), -one, one))
        wp.atomic_add(vertex_normals, f[t, 0], a0 * n)
        wp.atomic_add(vertex_normals, f[t, 1], a1 * n)
        wp.atomic_add(vertex_normals, f[t, 2], a2 * n)
        # the edge pseudo-normal is the sum of its faces' normals
        wp.atomic_add(edge_normals, face_edge[t, 0], n)
        wp.atomic_add(edge_normals, face_edge[t, 1], n)
        wp.atomic_add(edge_normals, face_edge[t, 2], n)

    @wp.kernel(enable_backward=False)
    def pairs(x: wp.array(dtype=wp.vec3d), a: wp.array(dtype=wp.vec3d), b: wp.array(dtype=wp.vec3d),
              c: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.vec3d)) -> None:
        i = wp.tid()
        out[i] = closest_on_triangle(x[i], a[i], b[i], c[i])

    @wp.kernel(enable_backward=False)
    def near(mesh: wp.uint64, v: wp.array(dtype=wp.vec3d), f: wp.array(dtype=wp.int32, ndim=2),
             points: wp.array(dtype=wp.vec3d), radius: wp.float64, pad: wp.float32,
             distance: wp.array(dtype=wp.float64)) -> None:
        i = wp.tid()
        p = points[i]
        r = wp.float32(radius) + pad
        box = wp.vec3(r, r, r)
        q = wp.mesh_query_aabb(mesh, wp.vec3(p) - box, wp.vec3(p) + box)
        best = wp.float64(1e300)
        t = int(0)
        while wp.mesh_query_aabb_next(q, t):
            d = p - closest_on_triangle(p, v[f[t, 0]], v[f[t, 1]], v[f[t, 2]])
            best = wp.min(best, wp.dot(d, d))
        distance[i] = wp.sqrt(best)

    _KERNELS["closest_on_triangle"] = closest_on_triangle  # a wp.func, shared with sim.obstacle_pairs
    _KERNELS["query"] = query
    _KERNELS["near"] = near
    _KERNELS["normals"] = normals
    _KERNELS["pairs"] = pairs
    return _KERNELS


def closest_points_on_triangles(x: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(N, 3) closest point of each point ``x[i]`` on the triangle ``(a[i], b[i], c[i])`` (Ericson's region
    tests in float64, the kernel :class:`WarpProximity` uses); all arguments (N, 3), metres."""
    wp = import_warp()
    n = x.shape[0]
    if n == 0:
        return np.zeros((0, 3))
    dev = "cpu"
    arrays = [wp.array(np.ascontiguousarray(t, dtype=np.float64), dtype=wp.vec3d, device=dev)
              for t in (x, a, b, c)]
    out = wp.empty(n, dtype=wp.vec3d, device=dev)
    wp.launch(_kernels()["pairs"], dim=n, device=dev, inputs=[*arrays, out])
    return out.numpy()


class _Topology:
    """What the bodies of one model share (their faces): the faces and each corner's opposite edge as Warp
    arrays, the edge count, and the pool of BVHs (:class:`_Tree`) not owned by a live
    :class:`WarpProximity`."""

    def __init__(self, faces: np.ndarray) -> None:
        wp = import_warp()
        edges, sides, _ = edge_table(torch.tensor(faces))
        fe = sides.numpy()[:, [1, 2, 0]].astype(np.int32)  # the side opposite corner k starts at corner k + 1
        f32 = faces.astype(np.int32)
        self.num_edges = int(edges.shape[0])
        self.faces = wp.array(f32, dtype=wp.int32, device="cpu")  # (F, 3)
        self.face_edges = wp.array(fe, dtype=wp.int32, device="cpu")  # (F, 3), edge opposite corner k
        self.indices = f32.reshape(-1)  # (3F,) the tree's flat triangle list
        self.free: list[_Tree] = []


def _box_pad(points: np.ndarray) -> float:
    """Metres added to a point's query box (P, 3 points): the float32 rounding of the tree's boxes and of the
    points, with room."""
    return 1e-5 * (1.0 + float(np.abs(points).max()))


class _Tree:
    """Warp's BVH of one mesh and the float32 points it was built or refitted on (Warp keeps a pointer to
    them: a refit reads them in place)."""

    def __init__(self, wp: object, vertices: np.ndarray, indices: np.ndarray) -> None:
        self.points = wp.array(vertices.astype(np.float32), dtype=wp.vec3, device="cpu")  # (V,)
        self.indices = wp.array(indices, dtype=wp.int32, device="cpu")  # (3F,)
        self.mesh = wp.Mesh(points=self.points, indices=self.indices)

    def refit(self, vertices: np.ndarray) -> None:
        """Move the tree onto ``vertices`` (V, 3) of the same topology: new bounds, the same hierarchy
        (0.4-0.6 ms against 10-12 ms for a build on the anny body; a hierarchy built on one anny body and
        refitted on the smallest or largest chart size queries 4-6 % slower than a fresh one)."""
        self.points.assign(vertices.astype(np.float32))
        self.mesh.refit()


_TOPOLOGIES: dict[tuple, _Topology] = {}
_POOL_LOCK = threading.RLock()  # re-entrant: a collection inside a locked block may release an instance
_POOL_SIZE = 4
"""Free trees kept per topology (one per thread that queries bodies of that model at the same time)."""


def _topology(faces: np.ndarray, num_vertices: int) -> _Topology:
    """The shared data of ``faces`` (F, 3) int64 on ``num_vertices`` vertices, cached by content (the
    bodies of one model share their topology; the last 8 topologies are kept)."""
    key = (num_vertices, faces.shape, hashlib.blake2b(faces.tobytes(), digest_size=16).hexdigest())
    with _POOL_LOCK:
        topo = _TOPOLOGIES.get(key)
    if topo is None:
        topo = _Topology(faces)
        with _POOL_LOCK:
            if len(_TOPOLOGIES) >= 8:
                _TOPOLOGIES.pop(next(iter(_TOPOLOGIES)))
            topo = _TOPOLOGIES.setdefault(key, topo)
    return topo


class WarpProximity:
    """The tree, the pseudo-normals (face, edge and angle-weighted vertex normals, computed by a kernel) and
    the query's inputs of one mesh (see the module docstring); built by
    :class:`~torchgarment.sdf.MeshProximity`.

    A mesh whose topology (its faces and vertex count) an earlier, now released, instance had reuses that
    instance's tree, refitted to the new vertices: each body of a model (every customer of a retailer) costs
    a refit, not a build. A tree belongs to one live instance at a time, so instances never share one.

    Args:
        vertices: (V, 3) float64 positions, metres. faces: (F, 3) int64 vertex indices, outward winding.
        reuse: take a released tree of this topology when there is one (False: build one; the instance's
            tree still goes to the pool when it is released).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, reuse: bool = True) -> None:
        wp = import_warp()
        self._wp = wp
        dev = "cpu"
        topo = _topology(faces, vertices.shape[0])
        with _POOL_LOCK:
            tree = topo.free.pop() if topo.free and reuse else None
        if tree is None:
            tree = _Tree(wp, vertices, topo.indices)
        else:
            tree.refit(vertices)
        self._topo, self._tree = topo, tree
        v = wp.array(vertices, dtype=wp.vec3d, device=dev)
        face_normals = wp.empty(topo.faces.shape[0], dtype=wp.vec3d, device=dev)
        vertex_normals = wp.zeros(len(vertices), dtype=wp.vec3d, device=dev)
        edge_normals = wp.zeros(topo.num_edges, dtype=wp.vec3d, device=dev)
        wp.launch(_kernels()["normals"], dim=topo.faces.shape[0], device=dev,
                  inputs=[v, topo.faces, topo.face_edges, face_normals, vertex_normals, edge_normals])
        self._inputs = [v, topo.faces, face_normals, edge_normals, vertex_normals, topo.face_edges]

    def __del__(self) -> None:
        tree = getattr(self, "_tree", None)
        if tree is None or _POOL_LOCK is None:  # a failed __init__, or interpreter shutdown
            return
        with _POOL_LOCK:
            if len(self._topo.free) < _POOL_SIZE:
                self._topo.free.append(tree)
        self._tree = None

    def query(self, points: np.ndarray, feature_tol: float, stable: bool = False
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(signed distances (P,), closest triangles (P,) int64, closest points (P, 3), outward directions
        (P, 3)) at ``points`` (P, 3) float64, P >= 1. ``stable``: the closest triangle in float64 among all
        that the float32 search could have returned (the lower index on a tie), the same whatever the tree's
        hierarchy (fresh or refitted); it visits every triangle within the point's distance box, so it costs
        more the farther the points are."""
        wp = self._wp
        dev = "cpu"
        n = points.shape[0]
        out = [wp.empty(n, dtype=wp.float64, device=dev), wp.empty(n, dtype=wp.int32, device=dev),
               wp.empty(n, dtype=wp.vec3d, device=dev), wp.empty(n, dtype=wp.vec3d, device=dev)]
        pad = _box_pad(points)
        wp.launch(_kernels()["query"], dim=n, device=dev,
                  inputs=[self._tree.mesh.id, *self._inputs, wp.array(points, dtype=wp.vec3d, device=dev),
                          float(feature_tol), int(bool(stable)), pad, *out])
        d, tri, c, direction = (a.numpy() for a in out)
        return d, tri.astype(np.int64), c, direction

    def near(self, points: np.ndarray, radius: float) -> np.ndarray:
        """(P,) float64 unsigned distance from each of ``points`` (P, 3) to the closest triangle that overlaps
        its ``radius`` box (metres), exact in float64 (so exact where the mesh is within ``radius``; above
        ``radius`` otherwise), ``1e150`` where none does. Visits only the
        triangles whose boxes overlap the point's ``radius`` box (padded by float32 rounding): much cheaper
        than :meth:`query` for a small radius."""
        wp = self._wp
        dev = "cpu"
        n = points.shape[0]
        pad = _box_pad(points)
        out = wp.empty(n, dtype=wp.float64, device=dev)
        wp.launch(_kernels()["near"], dim=n, device=dev,
                  inputs=[self._tree.mesh.id, self._inputs[0], self._inputs[1],
                          wp.array(points, dtype=wp.vec3d, device=dev), float(radius), pad, out])
        return out.numpy()
