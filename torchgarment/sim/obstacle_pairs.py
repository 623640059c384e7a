"""Collision candidates of a garment against itself and against an obstacle, without the obstacle's own pairs.

ipctk's broad phases take one collision mesh and find every overlapping pair of its primitives' boxes; a
static-obstacle filter drops the obstacle-obstacle pairs only after the traversal has found them. An avatar
overlaps itself a great deal (every triangle's box overlaps its neighbours', and a shrunk or self-intersecting
avatar much more), so on dense avatars most of that traversal is wasted: on a T-shirt of 3,211 vertices
inflating inside a 23,752-vertex GarmentCode body, ipctk's LBVH took 117-240 ms per collision set, of which
the garment's own pairs took 6-9 ms (``README.md``, retargeting).

:class:`GarmentObstaclePairs` finds the pairs in two parts:

* garment-garment: ipctk's broad phase (and, for a step bound, ipctk's whole CCD) on the garment alone;
* garment-obstacle: Warp BVHs over the obstacle's vertex, edge and face boxes, queried by the garment's
  primitives only (garment vertex against obstacle faces, garment face against obstacle vertices, garment edge
  against obstacle edges), then a distance filter on the hits (point-triangle and segment-segment distances,
  float64): a pair is kept when its distance at the start is within the query's reach (twice the inflation)
  plus 1.25 times the largest displacement over the step of a vertex of one primitive relative to a vertex of
  the other (a garment carried along by the avatar moves little relative to it). Nothing a narrow phase could
  report is dropped: along a linear step the distance of a pair shrinks by at most that displacement (the
  points of a primitive are fixed convex combinations of its vertices), Tight
  Inclusion reports only pairs that meet within the step (then rescales their time by 0.8), and additive CCD
  (rescaling 0.9) stops a pair only once its gap has shrunk to a tenth of its start, which a pair farther than
  1 / 0.9 = 1.11 times that displacement cannot reach. The trees are built once and refit in place when the
  obstacle moves; they are rebuilt after it has moved by a tenth of its bounding box's diagonal since the last
  build (a tree refit after the avatar moved by 6.4 cm queried as fast as a rebuilt one; 25.6 cm away, 1.7x
  slower).

Additive CCD's step size asks only the garment-obstacle pairs that can lower it
(:meth:`GarmentObstaclePairs._cross_stepsize`). ipctk's additive CCD (Li et al. 2021) first advances a pair
by its distance over a bound on how fast that distance shrinks (the vertex displacements less their mean: the
largest on one primitive plus the largest on the other), so it never reports a time below that advancement
times its rescaling (0.9). The filter computes that bound for every pair; the pairs go to ipctk lowest bound
first, :data:`CCD_BATCH` at a time, until every bound left is above the smallest time found. A long step
of the inflation keeps 30,000-180,000 pairs within reach, and each ipctk candidate object costs about 0.7 us
from Python: on a T-shirt retargeted onto a GarmentCode body, making them took 2.7 s of the run instead of
6.6 s (cProfile).

A line search's trial points lie on the step whose size the additive CCD bounded. With ``keep_within`` (the
barrier's dhat) that query also keeps every garment-obstacle pair that may come within dhat anywhere on the
step, and the collision sets at the trial points (and so at the accepted point, whose gradient and Hessian
reuse its set) are filtered from those pairs instead of querying the BVHs again
(:meth:`GarmentObstaclePairs._on_sweep`): one BVH traversal per Newton iteration instead of one per
evaluation, and the same pairs.

Candidates refer to a collision mesh that holds the garment first and the obstacle after it, with edges
``[garment edges; obstacle edges]`` and faces ``[garment faces; obstacle faces]`` (:meth:`mesh_edges`,
:meth:`mesh_faces`); ipctk's ``NormalCollisions.build(candidates, ...)`` and CCDs do the narrow phases.
Boxes go to Warp in float32, widened by a relative 1e-6 so that they contain the float64 boxes. Positions are
numpy float64 arrays in the units of the caller.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable

import ipctk
import numpy as np

from torchgarment.errors import MeshError
from torchgarment.sdf.proximity import _kernels as _proximity_kernels
from torchgarment.warp_runtime import import_warp

_KERNELS: dict[str, object] = {}
_LOCK = threading.Lock()

#: garment-obstacle pairs per additive-CCD query, lowest bound first
#: (:meth:`GarmentObstaclePairs._cross_stepsize`)
CCD_BATCH = 4096


#: relative widening of a kept step's reach (:meth:`GarmentObstaclePairs.collision_free_stepsize`'s
#: ``keep_within``): covers the round-off by which a line search's trial point leaves the step
SWEEP_MARGIN = 1e-9

#: kinds of garment-obstacle pairs: (garment primitive, obstacle primitive)
_VERTEX_FACE, _FACE_VERTEX, _EDGE_EDGE = 0, 1, 2


def _kernels() -> dict[str, object]:
    """The Warp kernels (defined on first use; the first launch on a machine compiles them into Warp's
    cache)."""
    closest_on_triangle = _proximity_kernels()["closest_on_triangle"]
    with _LOCK:
        if _KERNELS:
            return _KERNELS
        wp = import_warp()

        @wp.func
        def widened(p: wp.vec3d, r: wp.float64, sign: wp.float64) -> wp.vec3:
            # float32 bound on the outer side of p + sign r (relative margin 1e-6 > float32's half ulp)
            q = p + wp.vec3d(sign * r, sign * r, sign * r)
            m = wp.float64(1.0e-6)
            return wp.vec3(
                wp.float32(q[0] + sign * m * wp.abs(q[0])),
                wp.float32(q[1] + sign * m * wp.abs(q[1])),
                wp.float32(q[2] + sign * m * wp.abs(q[2])),
            )

        @wp.func
        def box(x0: wp.array(dtype=wp.vec3d), x1: wp.array(dtype=wp.vec3d),
                idx: wp.array(dtype=wp.int32, ndim=2), i: int) -> wp.spatial_vectord:
            lo = x0[idx[i, 0]]
            hi = lo
            for k in range(idx.shape[1]):
                v = idx[i, k]
                lo = wp.min(lo, wp.min(x0[v], x1[v]))
                hi = wp.max(hi, wp.max(x0[v], x1[v]))
            return wp.spatial_vectord(lo[0], lo[1], lo[2], hi[0], hi[1], hi[2])

        @wp.func
        def relative_motion(g0: wp.array(dtype=wp.vec3d), g1: wp.array(dtype=wp.vec3d),
                            gi: wp.array(dtype=wp.int32, ndim=2), i: int, a0: wp.array(dtype=wp.vec3d),
                            a1: wp.array(dtype=wp.vec3d), ai: wp.array(dtype=wp.int32, ndim=2),
                            j: int) -> wp.float64:
            # largest displacement of a vertex of one primitive relative to a vertex of the other
            m = wp.float64(0.0)
            for k in range(gi.shape[1]):
                dg = g1[gi[i, k]] - g0[gi[i, k]]
                for q in range(ai.shape[1]):
                    m = wp.max(m, wp.length(dg - (a1[ai[j, q]] - a0[ai[j, q]])))
            return m

        @wp.func
        def segment_distance(p1: wp.vec3d, q1: wp.vec3d, p2: wp.vec3d, q2: wp.vec3d) -> wp.float64:
            # closest points of two segments (Ericson, Real-Time Collision Detection, 5.1.9)
            zero = wp.float64(0.0)
            one = wp.float64(1.0)
            d1 = q1 - p1
            d2 = q2 - p2
            r = p1 - p2
            a = wp.dot(d1, d1)
            e = wp.dot(d2, d2)
            f = wp.dot(d2, r)
            s = zero
            t = zero
            if a > zero and e > zero:
                c = wp.dot(d1, r)
                b = wp.dot(d1, d2)
                denom = a * e - b * b
                if denom > zero:
                    s = wp.clamp((b * f - c * e) / denom, zero, one)
                t = (b * s + f) / e
                if t < zero:
                    t = zero
                    s = wp.clamp(-c / a, zero, one)
                elif t > one:
                    t = one
                    s = wp.clamp((b - c) / a, zero, one)
            elif a > zero:
                s = wp.clamp(-wp.dot(d1, r) / a, zero, one)
            elif e > zero:
                t = wp.clamp(f / e, zero, one)
            return wp.length(p1 + d1 * s - (p2 + d2 * t))

        @wp.func
        def point_triangle(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> wp.vec2d:
            d = wp.length(p - closest_on_triangle(p, a, b, c))
            return wp.vec2d(d, wp.length(b - a) + wp.length(c - a))

        @wp.func
        def segment_segment(p: wp.vec3d, q: wp.vec3d, a: wp.vec3d, b: wp.vec3d) -> wp.vec2d:
            return wp.vec2d(segment_distance(p, q, a, b), wp.length(q - p) + wp.length(b - a))

        @wp.kernel(enable_backward=False)
        def boxes(x0: wp.array(dtype=wp.vec3d), x1: wp.array(dtype=wp.vec3d),
                  idx: wp.array(dtype=wp.int32, ndim=2), r: wp.float64, lowers: wp.array(dtype=wp.vec3),
                  uppers: wp.array(dtype=wp.vec3)) -> None:
            i = wp.tid()
            b = box(x0, x1, idx, i)
            lowers[i] = widened(wp.vec3d(b[0], b[1], b[2]), r, wp.float64(-1.0))
            uppers[i] = widened(wp.vec3d(b[3], b[4], b[5]), r, wp.float64(1.0))

        @wp.kernel(enable_backward=False)
        def overlaps(bvh: wp.uint64, x0: wp.array(dtype=wp.vec3d), x1: wp.array(dtype=wp.vec3d),
                     idx: wp.array(dtype=wp.int32, ndim=2), r: wp.float64, count: wp.array(dtype=wp.int32),
                     hit_i: wp.array(dtype=wp.int32), hit_j: wp.array(dtype=wp.int32)) -> None:
            # every tree box j that overlaps query box i: (i, j) into the next free slot while the slots last;
            # count[0] ends as the number of overlaps
            i = wp.tid()
            b = box(x0, x1, idx, i)
            q = wp.bvh_query_aabb(bvh, widened(wp.vec3d(b[0], b[1], b[2]), r, wp.float64(-1.0)),
                                  widened(wp.vec3d(b[3], b[4], b[5]), r, wp.float64(1.0)))
            j = int(0)
            while wp.bvh_query_next(q, j):
                k = wp.atomic_add(count, 0, 1)
                if k < hit_i.shape[0]:
                    hit_i[k] = i
                    hit_j[k] = j

        @wp.func
        def centered_reach(d0: wp.vec3d, d1: wp.vec3d, d2: wp.vec3d, d3: wp.vec3d, split: int) -> wp.float64:
            # ipctk's additive-CCD bound on how fast a pair's distance shrinks: the displacements less their
            # mean, the largest of the first ``split`` plus the largest of the rest
            m = (d0 + d1 + d2 + d3) * wp.float64(0.25)
            n0 = wp.length(d0 - m)
            n1 = wp.length(d1 - m)
            n2 = wp.length(d2 - m)
            n3 = wp.length(d3 - m)
            if split == 1:
                return n0 + wp.max(n1, wp.max(n2, n3))
            return wp.max(n0, n1) + wp.max(n2, n3)

        @wp.kernel(enable_backward=False)
        def near(g0: wp.array(dtype=wp.vec3d), g1: wp.array(dtype=wp.vec3d),
                 gi: wp.array(dtype=wp.int32, ndim=2), a0: wp.array(dtype=wp.vec3d),
                 a1: wp.array(dtype=wp.vec3d), ai: wp.array(dtype=wp.int32, ndim=2), kind: int,
                 pi: wp.array(dtype=wp.int32), pj: wp.array(dtype=wp.int32), reach: wp.float64,
                 keep: wp.array(dtype=wp.int8), advance: wp.array(dtype=wp.float64)) -> None:
            k = wp.tid()
            i = pi[k]
            j = pj[k]
            ds = wp.vec2d()  # (distance, size of the two primitives)
            speed = wp.float64(0.0)
            if kind == 0:
                ds = point_triangle(g0[gi[i, 0]], a0[ai[j, 0]], a0[ai[j, 1]], a0[ai[j, 2]])
                speed = centered_reach(g1[gi[i, 0]] - g0[gi[i, 0]], a1[ai[j, 0]] - a0[ai[j, 0]],
                                       a1[ai[j, 1]] - a0[ai[j, 1]], a1[ai[j, 2]] - a0[ai[j, 2]], 1)
            elif kind == 1:
                ds = point_triangle(a0[ai[j, 0]], g0[gi[i, 0]], g0[gi[i, 1]], g0[gi[i, 2]])
                speed = centered_reach(a1[ai[j, 0]] - a0[ai[j, 0]], g1[gi[i, 0]] - g0[gi[i, 0]],
                                       g1[gi[i, 1]] - g0[gi[i, 1]], g1[gi[i, 2]] - g0[gi[i, 2]], 1)
            else:
                ds = segment_segment(g0[gi[i, 0]], g0[gi[i, 1]], a0[ai[j, 0]], a0[ai[j, 1]])
                speed = centered_reach(g1[gi[i, 0]] - g0[gi[i, 0]], g1[gi[i, 1]] - g0[gi[i, 1]],
                                       a1[ai[j, 0]] - a0[ai[j, 0]], a1[ai[j, 1]] - a0[ai[j, 1]], 2)
            d = ds[0]
            size = ds[1]
            bound = reach + wp.float64(1.25) * relative_motion(g0, g1, gi, i, a0, a1, ai, j)
            # slack for the round-off of the distance (an upper bound of the true one would drop pairs)
            if d <= bound + wp.float64(1.0e-6) * (bound + size):
                keep[k] = wp.int8(1)
            else:
                keep[k] = wp.int8(0)
            # the first advancement of additive CCD before its rescaling, distance / speed: the pair cannot
            # meet earlier, and ipctk's additive CCD reports no time below the rescaled one
            lo = wp.max(d - wp.float64(1.0e-9) * size, wp.float64(0.0))
            if lo == wp.float64(0.0):
                advance[k] = wp.float64(0.0)
            elif speed > wp.float64(0.0):
                advance[k] = lo / speed
            else:
                advance[k] = wp.float64(1.0e300)

        _KERNELS.update(wp=wp, boxes=boxes, overlaps=overlaps, near=near)
        return _KERNELS


def _int32(a: np.ndarray, cols: int) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(a, dtype=np.int32).reshape(-1, cols))


class _ObstacleTree:
    """A Warp BVH over one kind of obstacle primitive (rows of ``idx``: vertices, edges or faces), refit in
    place."""

    def __init__(self, wp: object, idx: np.ndarray) -> None:
        self.wp = wp
        self.size = idx.shape[0]
        self.idx = wp.array(idx, dtype=wp.int32, device="cpu")
        self.lowers = wp.empty(self.size, dtype=wp.vec3, device="cpu")
        self.uppers = wp.empty(self.size, dtype=wp.vec3, device="cpu")
        self.bvh = None
        #: overlap slots of the next query (grows to 1.25 times the most overlaps seen)
        self.room = 4 * self.size

    def update(self, a0: object, a1: object, r: float, rebuild: bool) -> None:
        """Boxes of the primitives over positions ``a0``..``a1`` (Warp vec3d arrays) inflated by ``r``."""
        wp, k = self.wp, _kernels()
        wp.launch(k["boxes"], dim=self.size, inputs=[a0, a1, self.idx, r], outputs=[self.lowers, self.uppers],
                  device="cpu")
        if rebuild or self.bvh is None:
            self.bvh = wp.Bvh(self.lowers, self.uppers)
        else:
            self.bvh.refit()

    def query(self, g0: object, g1: object, gi: object, r: float) -> tuple[np.ndarray, np.ndarray]:
        """(i, j) int32: garment primitive i (row of ``gi`` over ``g0``..``g1``, inflated by ``r``) and tree
        primitive j have overlapping boxes. One traversal into room for 1.25 times the most overlaps seen so
        far; a second, into exactly enough room, when they did not fit."""
        wp, k = self.wp, _kernels()
        cpu = "cpu"
        room = self.room
        while True:
            count = wp.zeros(1, dtype=wp.int32, device=cpu)
            hit_i = wp.empty(room, dtype=wp.int32, device=cpu)
            hit_j = wp.empty(room, dtype=wp.int32, device=cpu)
            wp.launch(k["overlaps"], dim=gi.shape[0], inputs=[self.bvh.id, g0, g1, gi, r],
                      outputs=[count, hit_i, hit_j], device=cpu)
            total = int(count.numpy()[0])
            self.room = max(self.room, total + total // 4)
            if total <= room:
                return hit_i.numpy()[:total], hit_j.numpy()[:total]
            room = total


class GarmentObstaclePairs:
    """Collision candidates of a garment (against itself and an obstacle) for a garment-then-obstacle mesh.

    Raises :class:`~torchgarment.errors.MeshError` when a face indexes a vertex outside its mesh.

    Args:
        garment_rest: (N, 3) garment rest positions (the garment-only collision mesh's adjacency).
        garment_faces: (F, 3) int, garment vertex ids 0..N-1.
        obstacle_faces: (G, 3) int, obstacle vertex ids 0..A-1 (collision-mesh ids N..N+A-1).
        num_obstacle: A.
        broad_phase: a factory of the ipctk broad phase for the garment-garment pairs (e.g. ``ipctk.LBVH``).
    """

    def __init__(
        self,
        garment_rest: np.ndarray,
        garment_faces: np.ndarray,
        obstacle_faces: np.ndarray,
        num_obstacle: int,
        broad_phase: Callable[[], ipctk.BroadPhase],
    ) -> None:
        wp = _kernels()["wp"]
        self._wp = wp
        self.num_garment = int(garment_rest.shape[0])
        self.num_obstacle = int(num_obstacle)
        self.garment_faces = np.asfortranarray(_int32(garment_faces, 3))
        of = _int32(obstacle_faces, 3)
        # the Warp kernels index positions without bounds checks: refuse out-of-range faces here
        for name, f, nv in (("garment", self.garment_faces, self.num_garment),
                            ("obstacle", of, self.num_obstacle)):
            if f.size and (int(f.min()) < 0 or int(f.max()) >= nv):
                raise MeshError(f"{name} faces index vertices outside [0, {nv})")
        self.garment_edges = np.asfortranarray(_int32(ipctk.edges(self.garment_faces), 2))
        #: the garment alone (its own pairs' CCD)
        self.garment_mesh = ipctk.CollisionMesh(
            np.asfortranarray(garment_rest, dtype=np.float64), self.garment_edges, self.garment_faces
        )
        oe = _int32(ipctk.edges(np.asfortranarray(of)), 2) if of.shape[0] else np.zeros((0, 2), np.int32)
        self.obstacle_faces, self.obstacle_edges = of, oe
        self.broad_phase = broad_phase
        cpu = "cpu"
        self._garment = {  # garment primitives as Warp index arrays into the garment's positions
            _VERTEX_FACE: wp.array(np.arange(self.num_garment, dtype=np.int32).reshape(-1, 1), dtype=wp.int32,
                                   device=cpu),
            _FACE_VERTEX: wp.array(np.ascontiguousarray(self.garment_faces), dtype=wp.int32, device=cpu),
            _EDGE_EDGE: wp.array(np.ascontiguousarray(self.garment_edges), dtype=wp.int32, device=cpu),
        }
        self._trees = {  # the obstacle primitive each kind queries, over the obstacle's own positions
            _VERTEX_FACE: _ObstacleTree(wp, of),
            _FACE_VERTEX: _ObstacleTree(wp, np.arange(self.num_obstacle, dtype=np.int32).reshape(-1, 1)),
            _EDGE_EDGE: _ObstacleTree(wp, oe),
        }
        self._rebuild_distance = math.inf  # a tenth of the obstacle's box diagonal, set on the first build
        self._built_at: np.ndarray | None = None
        self._last_key: tuple[bytes, bytes, float] | None = None
        #: the last additive CCD's step (x0, x1 - x0, its garment-obstacle pairs, their reach), see
        #: :meth:`collision_free_stepsize`'s ``keep_within``
        self._sweep: tuple[np.ndarray, np.ndarray, dict[int, tuple[np.ndarray, ...]], float] | None = None
        #: :meth:`candidates` calls served from the last step's pairs (no BVH query)
        self.sweep_reuses = 0

    def mesh_edges(self) -> np.ndarray:
        """(Eg + Ea, 2) int32 Fortran edges of the collision mesh the candidates refer to."""
        return np.asfortranarray(np.concatenate([self.garment_edges, self.obstacle_edges + self.num_garment]))

    def mesh_faces(self) -> np.ndarray:
        """(Fg + Fa, 3) int32 Fortran faces of the collision mesh the candidates refer to."""
        return np.asfortranarray(np.concatenate([self.garment_faces, self.obstacle_faces + self.num_garment]))

    # ------------------------------------------------------------------ garment-obstacle pairs
    def _refit(self, a0: np.ndarray, a1: np.ndarray, w0: object, w1: object, r: float) -> None:
        key = (a0.tobytes(), a1.tobytes(), r)
        if key == self._last_key:
            return
        if self._built_at is None:
            self._rebuild_distance = 0.1 * float(np.linalg.norm(a0.max(0) - a0.min(0)))
            rebuild = True
        else:
            moved = max(float(np.sqrt(((a0 - self._built_at) ** 2).sum(1)).max(initial=0.0)),
                        float(np.sqrt(((a1 - self._built_at) ** 2).sum(1)).max(initial=0.0)))
            rebuild = moved > self._rebuild_distance
        for tree in self._trees.values():
            if tree.size:
                tree.update(w0, w1, r, rebuild)
        if rebuild:
            self._built_at = a0.copy()
        self._last_key = key

    def _cross(
        self,
        x0: np.ndarray,
        x1: np.ndarray,
        inflation: float,
        hits: dict[int, tuple[np.ndarray, ...]] | None = None,
    ) -> dict[int, tuple[np.ndarray, ...]]:
        """Garment-obstacle pairs by kind: (garment primitive ids, obstacle primitive ids, first advancement),
        each within reach (2 ``inflation``) plus 1.25 times its relative vertex
        displacement from ``x0`` to ``x1`` ((N + A, 3) each; see the module docstring). The first
        advancement (float64) is the pair's distance at ``x0`` over ipctk's additive-CCD speed bound (the
        displacements less their mean: the largest on one primitive plus the largest on the other); 0 for
        touching pairs, 1e300 for pairs that do not move relative to each other. ``hits``: pairs by kind (the
        first two entries of each) to filter instead of the BVH queries' (a superset of theirs)."""
        wp, k = self._wp, _kernels()
        n, cpu = self.num_garment, "cpu"
        static = x1 is x0
        g0 = wp.array(x0[:n], dtype=wp.vec3d, device=cpu)
        g1 = g0 if static else wp.array(x1[:n], dtype=wp.vec3d, device=cpu)
        a0 = wp.array(x0[n:], dtype=wp.vec3d, device=cpu)
        a1 = a0 if static else wp.array(x1[n:], dtype=wp.vec3d, device=cpu)
        r = float(inflation)
        if hits is None:
            self._refit(x0[n:], x1[n:], a0, a1, r)
        out = {}
        for kind, tree in self._trees.items():
            gi = self._garment[kind]
            if not tree.size or not gi.shape[0]:
                out[kind] = (np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0))
                continue
            i, j = tree.query(g0, g1, gi, r) if hits is None else hits[kind][:2]
            keep = wp.empty(i.shape[0], dtype=wp.int8, device=cpu)
            advance = wp.empty(i.shape[0], dtype=wp.float64, device=cpu)
            if i.shape[0]:
                wp.launch(k["near"], dim=i.shape[0],
                          inputs=[g0, g1, gi, a0, a1, tree.idx, kind, wp.array(i, dtype=wp.int32, device=cpu),
                                  wp.array(j, dtype=wp.int32, device=cpu), 2.0 * r],
                          outputs=[keep, advance], device=cpu)
            m = keep.numpy().astype(bool)
            out[kind] = (i[m], j[m], advance.numpy()[m])
        return out

    def _cross_candidates(
        self, c: dict[int, tuple[np.ndarray, ...]], rows: np.ndarray | None = None
    ) -> tuple[list, list]:
        """(edge-edge, face-vertex) ipctk candidates (the mesh's numbering) of the pairs ``c`` of
        :meth:`_cross`, or of the ``rows`` of their concatenation in kind order (:meth:`_advance`'s order)."""
        n, ne, nf = self.num_garment, self.garment_edges.shape[0], self.garment_faces.shape[0]
        start = 0
        ids = {}
        for kind, (i, j, _) in c.items():
            if rows is not None:
                sel = rows[(rows >= start) & (rows < start + i.shape[0])] - start
                start += i.shape[0]
                i, j = i[sel], j[sel]
            ids[kind] = (i.tolist(), j.astype(np.int64))
        i, j = ids[_VERTEX_FACE]
        fv = list(map(ipctk.FaceVertexCandidate, (j + nf).tolist(), i))
        i, j = ids[_FACE_VERTEX]
        fv += map(ipctk.FaceVertexCandidate, i, (j + n).tolist())
        i, j = ids[_EDGE_EDGE]
        ee = list(map(ipctk.EdgeEdgeCandidate, i, (j + ne).tolist()))
        return ee, fv

    def _cross_batch(
        self, c: dict[int, tuple[np.ndarray, ...]], rows: np.ndarray | None = None
    ) -> ipctk.Candidates:
        """ipctk candidates of the pairs ``c``, or of their ``rows`` (see :meth:`_cross_candidates`)."""
        cand = ipctk.Candidates()
        cand.ee_candidates, cand.fv_candidates = self._cross_candidates(c, rows)
        return cand

    @staticmethod
    def _advance(c: dict[int, tuple[np.ndarray, ...]]) -> np.ndarray:
        """The first advancements of the pairs ``c`` of :meth:`_cross`, concatenated in kind order."""
        return np.concatenate([adv for _, _, adv in c.values()])

    def _cross_stepsize(
        self,
        mesh: ipctk.CollisionMesh,
        x0: np.ndarray,
        x1: np.ndarray,
        narrow_phase: ipctk.AdditiveCCD,
        alpha: float,
        keep_within: float,
    ) -> float:
        """min(``alpha``, the additive CCD's step size over the garment-obstacle pairs), querying only the
        pairs whose lower bound (the rescaled first advancement) is below the running minimum, the lowest
        :data:`CCD_BATCH` first. The same minimum as all pairs: ipctk's additive CCD never reports a pair's
        time below its rescaled first advancement (computed here from the exact distance, less a relative
        1e-9 of the primitives' size; a skipped pair cannot come closer than a tenth of its distance before
        the minimum found, whatever ipctk's distance functions say). With ``keep_within`` > 0 the query also
        finds, and keeps for :meth:`candidates`, every pair that may come within ``keep_within`` on the step;
        those extra pairs stay farther apart than 1.11 times their relative displacement, so additive CCD
        cannot stop them and the step size is the same."""
        r = 0.5 * keep_within * (1.0 + SWEEP_MARGIN) if keep_within > 0 else 0.0
        c = self._cross(x0, x1, r)
        if keep_within > 0:
            self._sweep = (x0.copy(), x1 - x0, c, 2.0 * r)
        bound = narrow_phase.conservative_rescaling * self._advance(c)
        pending = np.flatnonzero(bound < alpha)
        while pending.size:
            if pending.size > CCD_BATCH:
                pending = pending[np.argpartition(bound[pending], CCD_BATCH)[:CCD_BATCH]]
            cand = self._cross_batch(c, pending)
            alpha = min(alpha, float(cand.compute_collision_free_stepsize(mesh, x0, x1, 0.0, narrow_phase)))
            bound[pending] = np.inf
            pending = np.flatnonzero(bound < alpha)
        return alpha

    # ------------------------------------------------------------------ queries
    def candidates(self, x: np.ndarray, inflation: float) -> ipctk.Candidates:
        """Every pair (garment-garment and garment-obstacle) that may be closer than ``2 inflation`` at
        positions ``x`` ((N + A, 3) float64), for ``NormalCollisions.build(candidates, ...)``."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        bp = self.broad_phase()
        g = np.asfortranarray(x[: self.num_garment])
        bp.build(g, self.garment_edges, self.garment_faces, float(inflation))
        ee = bp.detect_edge_edge_candidates()
        fv = bp.detect_face_vertex_candidates()
        if self.num_obstacle:
            c = self._on_sweep(x, inflation)
            cee, cfv = self._cross_candidates(self._cross(x, x, inflation) if c is None else c)
            ee += cee
            fv += cfv
        cand = ipctk.Candidates()
        cand.ee_candidates = ee
        cand.fv_candidates = fv
        return cand

    def _on_sweep(self, x: np.ndarray, inflation: float) -> dict[int, tuple[np.ndarray, ...]] | None:
        """The garment-obstacle pairs within ``2 inflation`` at ``x`` (as :meth:`_cross` of a static query),
        filtered from the last kept step's pairs when ``x`` lies on that step (a line search's trial), else
        None.

        A point of the step, ``x0 + a (x1 - x0)`` with a in [0, 1], moves no vertex of a pair by more than
        the pair's relative displacement over the whole step, so a pair within ``2 inflation`` there was
        within that plus its displacement at ``x0``, which the step's query kept. ``x`` may differ from the
        nearest point of the step by ``e`` per vertex (its round-off), which the step's wider reach covers
        when ``2 e`` is at most the difference of the reaches.
        """
        if self._sweep is None:
            return None
        x0, d, c, reach = self._sweep
        slack = reach - 2.0 * float(inflation)
        if slack < 0.0:
            return None
        off = x - x0
        dd = float(np.einsum("ij,ij->", d, d))
        a = 0.0 if dd == 0.0 else min(max(float(np.einsum("ij,ij->", off, d)) / dd, 0.0), 1.0)
        off -= a * d
        if 2.0 * math.sqrt(float(np.einsum("ij,ij->i", off, off).max(initial=0.0))) > slack:
            return None
        self.sweep_reuses += 1
        return self._cross(x, x, inflation, hits=c)

    def _own_motion(
        self, x0: np.ndarray, x1: np.ndarray, min_distance: float
    ) -> tuple[ipctk.Candidates, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The garment's own CCD candidates (on :attr:`garment_mesh`), the garment's positions and ``x0``,
        ``x1`` as contiguous float64."""
        n = self.num_garment
        x0 = np.ascontiguousarray(x0, dtype=np.float64)
        x1 = np.ascontiguousarray(x1, dtype=np.float64)
        g0, g1 = np.asfortranarray(x0[:n]), np.asfortranarray(x1[:n])
        own = ipctk.Candidates()
        own.build(self.garment_mesh, g0, g1, 0.5 * min_distance, self.broad_phase())
        return own, g0, g1, x0, x1

    def collision_free_stepsize(
        self,
        mesh: ipctk.CollisionMesh,
        x0: np.ndarray,
        x1: np.ndarray,
        narrow_phase: ipctk.NarrowPhaseCCD,
        keep_within: float = 0.0,
    ) -> float:
        """ipctk's CCD step size (min over the candidates) along ``x0`` -> ``x1`` ((N + A, 3) Fortran
        positions of ``mesh``), the garment's own pairs and the garment-obstacle pairs queried apart (with
        additive CCD only the garment-obstacle pairs that could lower the minimum, see
        :meth:`_cross_stepsize`).

        ``keep_within`` (additive CCD; units of x): keep the garment-obstacle pairs that may come within this
        distance anywhere on the step, so that :meth:`candidates` at points of the step (a line search's
        trials) with ``2 inflation <= keep_within`` filters them instead of querying the BVHs; 0 keeps
        nothing."""
        own, g0, g1, x0, x1 = self._own_motion(x0, x1, 0.0)
        alpha = 1.0
        if not own.empty():
            alpha = float(own.compute_collision_free_stepsize(self.garment_mesh, g0, g1, 0.0, narrow_phase))
        if not self.num_obstacle:
            return alpha
        if isinstance(narrow_phase, ipctk.AdditiveCCD):
            return self._cross_stepsize(mesh, x0, x1, narrow_phase, alpha, keep_within)
        cross = self._cross_batch(self._cross(x0, x1, 0.0))
        if not cross.empty():
            alpha = min(alpha, float(cross.compute_collision_free_stepsize(mesh, x0, x1, 0.0, narrow_phase)))
        return alpha

    def is_step_collision_free(
        self,
        mesh: ipctk.CollisionMesh,
        x0: np.ndarray,
        x1: np.ndarray,
        min_distance: float,
        narrow_phase: ipctk.NarrowPhaseCCD,
    ) -> bool:
        """ipctk's ``is_step_collision_free`` along ``x0`` -> ``x1``: every pair that moves stays
        ``min_distance`` apart. The garment's own pairs first, then the garment-obstacle pairs
        :data:`CCD_BATCH` at a time, the lowest first advancement (distance over speed bound) first, so that
        a step that is not free is usually told by the first batch.

        When the garment does not move (a snap of the obstacle), its own pairs keep their distances and are
        not checked: ipctk would report a step not free for two garment layers already closer than
        ``min_distance`` ("initial distance <= d_min, returning toi=0"), whatever the obstacle does."""
        n = self.num_garment
        if np.array_equal(np.asarray(x0)[:n], np.asarray(x1)[:n]):
            x0 = np.ascontiguousarray(x0, dtype=np.float64)
            x1 = np.ascontiguousarray(x1, dtype=np.float64)
        else:
            own, g0, g1, x0, x1 = self._own_motion(x0, x1, min_distance)
            if not own.is_step_collision_free(self.garment_mesh, g0, g1, min_distance, narrow_phase):
                return False
        if not self.num_obstacle:
            return True
        c = self._cross(x0, x1, 0.5 * min_distance)
        order = np.argsort(self._advance(c), kind="stable")
        for start in range(0, order.shape[0], CCD_BATCH):
            cand = self._cross_batch(c, order[start:start + CCD_BATCH])
            if not cand.is_step_collision_free(mesh, x0, x1, min_distance, narrow_phase):
                return False
        return True
