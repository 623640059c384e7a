"""Step 1 of Huang et al. 2025 (section 3.3): shrink the target avatar onto the source skeleton.

Every target avatar vertex is given a bone of the target skeleton: the closest bone, or, with skin weights,
the closest of the bones leaving its most weighted joint (the bone entering it when the joint is a leaf;
skin weights follow the SMPL convention: joint ``j`` carries the bones leaving ``j``). The vertex is
projected onto that bone (bone parameter ``s`` in [0, 1]; a parameter of exactly 0 or 1, e.g. after
clamping, puts it *at* a joint, which lies on every bone of that joint).

A triangle whose vertices lie on different bones does not lie on the skeleton. The number of joints strictly
between two skeleton points is computed from the joint-graph hop distances of the skeleton (Floyd-Warshall,
``scipy.sparse.csgraph.floyd_warshall``, with predecessors for the paths). Counting on joints is the paper's
"bones as nodes, joints as edges" graph. For every triangle spanning several bones, the edge with the most
joints between its ends is split (greedy, as in the paper's Fig. 3): ``k`` joints between its ends give
``k`` new vertices placed uniformly along the edge on the *full* avatar and *at* those joints on the
skeleton, and the triangle becomes a fan of ``k + 1`` triangles around its third vertex (orientation kept).
Neighbouring triangles are not split (non-conforming), except that two triangles splitting the same edge
share the new vertices. This repeats until every triangle has its three vertices on one bone, so the whole
shrunk mesh lies on the skeleton (degenerate triangles on bone segments). On the full avatar the fans tile
the original triangles exactly, so ``at(1)`` is the input avatar surface.

Finally each skeleton point is mapped onto the *source* skeleton by its bone parameter (joints onto joints):
``vertices_shrunk`` lies on the source skeleton, inside the garment.

Offset: exactly on the skeleton, many shrunk vertices coincide (every vertex clamped to a joint lands on
it), which makes zero-length avatar edges. ipctk mis-classifies edge-edge distances with a zero-length edge
(measured with ipctk 1.6.1: a point 0.29 m from a garment edge gets the 0.06 m distance to the edge's
*line*, type ``EA_EB0``), so barriers and minimum distances would be wrong. Each shrunk vertex is therefore
placed ``SHRINK_OFFSET * length_scale`` (0.17 mm for a 1.7 m model) from its skeleton point, in the
direction from its target-skeleton point to the vertex on the full avatar (any direction perpendicular to
the bone when that is zero). The shrunk triangles then lie within that offset of the skeleton (a capsule
around a bone is convex), zero-area triangles become thin slivers, and coincident vertices only remain where
two vertices have the same skeleton point and the same direction. Degenerate and sliver triangles are fine
for ipctk's point-triangle distances (checked in the tests: finite barrier, gradient and Hessian).

Check (``check=True``): the shrunk avatar is a subset of the bone segments its triangles cover. Those segments
(per bone the parameter interval covered by its triangles) and the garment form an ``ipctk.CollisionMesh``
in which only garment-skeleton pairs may collide; ``ipctk.has_intersections`` must be false and the minimum
distance (``NormalCollisions`` within ``CHECK_RADIUS * length_scale``) must exceed twice the offset; the
reported ``min_distance`` is that distance minus the offset, a lower bound of the garment-to-shrunk-avatar
distance. Checking the covered
segments instead of the thousands of coincident degenerate triangles is cheaper and, being a superset, at
least as strict.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from torchgarment.errors import InputError
from torchgarment.retarget.inputs import RetargetProblem

__all__ = ["CHECK_RADIUS", "ShrunkAvatar", "bone_hop_distances", "project_to_bones", "shrink_avatar"]

#: Radius (relative to ``length_scale``) within which the check measures the garment-to-skeleton distance;
#: a garment farther than that from every covered bone reports this radius as ``min_distance`` (a lower
# bound).
CHECK_RADIUS = 0.1
#: Distance of the shrunk vertices from the skeleton, relative to ``length_scale`` (see the module docstring).
SHRINK_OFFSET = 1e-4
#: Bones shorter than this (relative to ``length_scale``) in both skeletons are merged into their joints.
ZERO_BONE = 1e-9
#: Points are processed in chunks of this many rows when measuring point-to-bone distances.
_CHUNK = 8192


@dataclass
class ShrunkAvatar:
    """The target avatar after subdivision, with its shrunk copy on the source skeleton (work frame).

    Attributes:
        vertices_full: (A', 3) target avatar after non-conforming subdivision; the first ``num_original``
            (= A) rows are the original avatar vertices, the others lie on original triangle edges.
        vertices_shrunk: (A', 3) every vertex at distance ``offset`` from its bone point on the source
            skeleton (t = 0).
        faces: (G', 3) long faces; every triangle has its three shrunk vertices on one bone.
        bone_of_vertex: (A',) long bone index (for a vertex at a joint: one bone incident to it).
        joint_of_vertex: (A',) long joint a vertex sits at, -1 for a vertex inside a bone.
        bone_parameter: (A',) parameter along ``bone_of_vertex`` in [0, 1] (0 at the bone's first joint).
        num_original: A.
        iterations: subdivision rounds used.
        min_distance: lower bound (metres) of the garment-to-shrunk-avatar distance: the distance to the
            covered bone segments (capped at ``CHECK_RADIUS * length_scale``) minus ``offset``; NaN without
            check.
        offset: distance (metres) of the shrunk vertices from the skeleton.
        skeleton_points: (A', 3) the points on the source skeleton (``vertices_shrunk`` minus the offset).
    """

    vertices_full: torch.Tensor
    vertices_shrunk: torch.Tensor
    faces: torch.Tensor
    bone_of_vertex: torch.Tensor
    joint_of_vertex: torch.Tensor | None = None
    bone_parameter: torch.Tensor | None = None
    num_original: int = 0
    iterations: int = 0
    min_distance: float = math.nan
    offset: float = 0.0
    skeleton_points: torch.Tensor | None = None

    def at(self, t: float | torch.Tensor) -> torch.Tensor:
        """Avatar at inflation parameter ``t``: ``(1 - t) * vertices_shrunk + t * vertices_full``, (A', 3).

        ``t`` may be a float or a 0-dim tensor (differentiable).
        """
        return (1 - t) * self.vertices_shrunk + t * self.vertices_full


def project_to_bones(
    points: torch.Tensor, joints: torch.Tensor, bones: torch.Tensor, allowed: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Closest bone of each point and the projection parameter on it.

    Args:
        points: (P, 3) positions.
        joints: (J, 3) joint positions.
        bones: (B, 2) long joint index pairs.
        allowed: optional (P, B) bool; only allowed bones are considered (every row needs one).

    Returns:
        bone: (P,) long index of the closest (allowed) bone.
        param: (P,) parameter in [0, 1] of the closest point on it (0 for zero-length bones).
        distance: (P,) distance to it, metres.
    """
    a = joints[bones[:, 0]]
    d = joints[bones[:, 1]] - a
    dd = (d * d).sum(dim=1)
    inv = torch.where(dd > 0, 1.0 / torch.where(dd > 0, dd, torch.ones_like(dd)), torch.zeros_like(dd))
    out_bone, out_param, out_dist = [], [], []
    for start in range(0, points.shape[0], _CHUNK):
        p = points[start : start + _CHUNK]
        rel = p[:, None, :] - a[None]  # (P, B, 3)
        s = ((rel * d[None]).sum(dim=-1) * inv[None]).clamp(0.0, 1.0)
        dist2 = (rel - s[..., None] * d[None]).square().sum(dim=-1)
        if allowed is not None:
            dist2 = dist2.masked_fill(~allowed[start : start + _CHUNK], math.inf)
        best = dist2.argmin(dim=1)
        out_bone.append(best)
        out_param.append(s.gather(1, best[:, None])[:, 0])
        out_dist.append(dist2.gather(1, best[:, None])[:, 0].sqrt())
    return torch.cat(out_bone), torch.cat(out_param), torch.cat(out_dist)


def bone_hop_distances(num_joints: int, bones: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hop distances and shortest-path predecessors of the joint graph (Floyd-Warshall).

    Args:
        num_joints: J.
        bones: (B, 2) int joint pairs.

    Returns:
        hops: (J, J) float array of hop counts (inf between disconnected joints).
        predecessors: (J, J) int array, ``predecessors[i, j]`` is the joint before ``j`` on the path from
            ``i`` (-9999 when none).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import floyd_warshall

    graph = coo_matrix((np.ones(len(bones)), (bones[:, 0], bones[:, 1])), shape=(num_joints, num_joints))
    hops, pred = floyd_warshall(graph.tocsr(), directed=False, unweighted=True, return_predecessors=True)
    return hops, pred


class _Skeleton:
    """Graph data of the bone tree used by the subdivision (numpy, CPU).

    Joints joined by a bone of zero length in both skeletons (anny's root, pelvis and lowest spine joints
    coincide) are merged into one graph *node*, so that a path through them inserts one vertex, not one per
    coincident joint. ``node_of_joint`` maps joints to nodes, ``rep`` nodes back to one of their joints.
    """

    def __init__(self, num_joints: int, bones: np.ndarray, zero: np.ndarray) -> None:
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        self.bones = bones
        glue = coo_matrix(
            (np.ones(int(zero.sum())), (bones[zero, 0], bones[zero, 1])), shape=(num_joints, num_joints)
        )
        num_nodes, node = connected_components(glue, directed=False)
        self.node_of_joint = node.astype(np.int64)
        self.rep = np.full(num_nodes, num_joints, dtype=np.int64)
        np.minimum.at(self.rep, self.node_of_joint, np.arange(num_joints))
        self.node_bones = self.node_of_joint[bones]  # (B, 2) bones as node pairs
        real = ~zero
        self.hops, self.pred = bone_hop_distances(num_nodes, self.node_bones[real])
        # One incident (non-merged) bone per node (prefer a bone leaving it) and the bone between two nodes.
        order = np.nonzero(real)[0][::-1]
        self.node_bone = np.full(num_nodes, -1, dtype=np.int64)
        self.node_bone[self.node_bones[order, 1]] = order
        self.node_bone[self.node_bones[order, 0]] = order
        missing = self.node_bone < 0  # a node with merged bones only: any bone of it
        if missing.any():
            order_all = np.arange(len(bones))[::-1]
            fallback = np.full(num_nodes, -1, dtype=np.int64)
            fallback[self.node_bones[order_all, 0]] = order_all
            fallback[self.node_bones[order_all, 1]] = order_all
            self.node_bone[missing] = fallback[missing]
        self.between = np.full((num_nodes, num_nodes), -1, dtype=np.int64)
        self.between[self.node_bones[real, 0], self.node_bones[real, 1]] = np.nonzero(real)[0]
        self.between[self.node_bones[real, 1], self.node_bones[real, 0]] = np.nonzero(real)[0]

    def anchors(self, bone: np.ndarray, joint: np.ndarray) -> np.ndarray:
        """(P, 2) nodes a skeleton point reaches first: its bone's ends, or its node twice (``joint``: node
        index or -1)."""
        ends = self.node_bones[bone]
        at = joint >= 0
        ends[at] = joint[at, None]
        return ends

    def counts(
        self, bone_p: np.ndarray, joint_p: np.ndarray, bone_q: np.ndarray, joint_q: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Joints strictly between skeleton points p and q, and the anchors (x, y) of the shortest path."""
        ap = self.anchors(bone_p, joint_p)
        aq = self.anchors(bone_q, joint_q)
        cand = self.hops[ap[:, :, None], aq[:, None, :]].reshape(
            -1, 4
        )  # (P, 4): (x0,y0),(x0,y1),(x1,y0),(x1,y1)
        best = cand.argmin(axis=1)
        m = cand[np.arange(len(best)), best]
        x = ap[np.arange(len(best)), best // 2]
        y = aq[np.arange(len(best)), best % 2]
        count = m + 1 - (joint_p >= 0) - (joint_q >= 0)
        same = (joint_p < 0) & (joint_q < 0) & (bone_p == bone_q)
        count = np.where(same, 0, np.maximum(count, 0))
        return count, x, y

    def path_joints(self, x: np.ndarray, y: np.ndarray, skip_first: np.ndarray, k: int) -> np.ndarray:
        """(M, k) joints on the paths x -> y, dropping x when ``skip_first`` (paths have k + skip + end)."""
        hops = self.hops[x, y].astype(np.int64)
        longest = int(hops.max()) if len(hops) else 0
        rev = np.empty((len(x), longest + 1), dtype=np.int64)
        rev[:, 0] = y
        for step in range(1, longest + 1):
            prev = self.pred[x, rev[:, step - 1]]
            rev[:, step] = np.where(step <= hops, prev, rev[:, step - 1])
        cols = hops[:, None] - skip_first.astype(np.int64)[:, None] - np.arange(k)[None, :]
        return np.take_along_axis(rev, cols, axis=1)


def _assign_bones(problem: RetargetProblem) -> tuple[torch.Tensor, torch.Tensor]:
    """Bone (A,) and parameter (A,) of every target avatar vertex on the target skeleton."""
    joints = problem.target_skeleton.joints
    bones = problem.target_skeleton.bones.long()
    points = problem.avatar_vertices
    allowed = None
    if problem.skin_weights is not None:
        num_j = joints.shape[0]
        strongest = problem.skin_weights.argmax(dim=0)  # (A,)
        leaving = bones[:, 0][None, :] == torch.arange(num_j, device=bones.device)[:, None]  # (J, B)
        entering = bones[:, 1][None, :] == torch.arange(num_j, device=bones.device)[:, None]
        cand = torch.where(leaving.any(dim=1, keepdim=True), leaving, entering)
        cand = torch.where(cand.any(dim=1, keepdim=True), cand, torch.ones_like(cand))  # isolated joint: any
        allowed = cand[strongest]
    bone, param, _ = project_to_bones(points, joints, bones, allowed)
    return bone, param


def _subdivide(
    full: np.ndarray,
    faces: np.ndarray,
    bone: np.ndarray,
    param: np.ndarray,
    joint: np.ndarray,
    skel: _Skeleton,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Non-conforming subdivision until every triangle lies on one bone (see the module docstring)."""
    num_joints = skel.hops.shape[0]
    max_rounds = len(skel.bones) + 2
    done_faces = []
    rounds = 0
    while faces.shape[0]:
        pairs = [(0, 1), (1, 2), (2, 0)]
        counts, xs, ys = [], [], []
        for i, j in pairs:
            c, x, y = skel.counts(
                bone[faces[:, i]], joint[faces[:, i]], bone[faces[:, j]], joint[faces[:, j]]
            )
            counts.append(c)
            xs.append(x)
            ys.append(y)
        counts = np.stack(counts, axis=1)
        if not np.isfinite(counts).all():
            bad = int(np.nonzero(~np.isfinite(counts).all(axis=1))[0][0])
            raise InputError(
                f"avatar triangle {faces[bad].tolist()} joins vertices on disconnected parts of the "
                "skeleton; "
                "connect the skeleton or give skin weights that keep each avatar part on one skeleton part"
            )
        counts = counts.astype(np.int64)
        worst = counts.max(axis=1)
        ok = worst == 0
        done_faces.append(faces[ok])
        if ok.all():
            break
        rounds += 1
        if rounds > max_rounds:
            raise InputError(
                f"skeleton subdivision did not finish in {max_rounds} rounds (malformed skeleton?)"
            )
        sel = np.nonzero(~ok)[0]
        edge = counts[sel].argmax(axis=1)
        ar = np.arange(len(sel))
        xs = np.stack(xs, axis=1)[sel, edge]
        ys = np.stack(ys, axis=1)[sel, edge]
        tri = faces[sel]
        r0 = tri[ar, edge]
        r1 = tri[ar, (edge + 1) % 3]
        r2 = tri[ar, (edge + 2) % 3]
        k_all = counts[sel, edge]
        new_keys, new_pos, new_joint, new_tris = [], [], [], []
        slot_base = 0
        num_v = full.shape[0]
        for k in np.unique(k_all):
            g = np.nonzero(k_all == k)[0]
            path = skel.path_joints(xs[g], ys[g], joint[r0[g]] >= 0, int(k))  # (M, k)
            alpha = np.arange(1, k + 1, dtype=np.float64) / (k + 1)
            pos = full[r0[g]][:, None, :] + alpha[None, :, None] * (full[r1[g]] - full[r0[g]])[:, None, :]
            lo = np.minimum(r0[g], r1[g])
            hi = np.maximum(r0[g], r1[g])
            keys = (lo[:, None] * num_v + hi[:, None]) * num_joints + path
            slots = slot_base + np.arange(len(g) * k).reshape(len(g), k)
            slot_base += len(g) * k
            new_keys.append(keys.reshape(-1))
            new_pos.append(pos.reshape(-1, 3))
            new_joint.append(path.reshape(-1))
            # Chain r0, new..., r1 (new vertices as -(slot + 1)) and the fan around r2.
            chain = np.concatenate([r0[g][:, None], -(slots + 1), r1[g][:, None]], axis=1)
            fan = np.stack(
                [chain[:, :-1], chain[:, 1:], np.broadcast_to(r2[g][:, None], (len(g), int(k) + 1))], axis=2
            )
            new_tris.append(fan.reshape(-1, 3))
        keys = np.concatenate(new_keys)
        ukeys, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
        pos = np.concatenate(new_pos)[first]
        jnt = np.concatenate(new_joint)[first]
        tris = np.concatenate(new_tris)
        neg = tris < 0
        tris[neg] = num_v + inverse[-tris[neg] - 1]
        full = np.concatenate([full, pos])
        jb = skel.node_bone[jnt]
        bone = np.concatenate([bone, jb])
        param = np.concatenate([param, np.where(skel.node_bones[jb, 0] == jnt, 0.0, 1.0)])
        joint = np.concatenate([joint, jnt])
        faces = tris
    faces = np.concatenate(done_faces) if done_faces else np.zeros((0, 3), dtype=np.int64)
    return full, faces, bone, param, joint, rounds


def _covered_segments(
    faces: np.ndarray, bone: np.ndarray, param: np.ndarray, joint: np.ndarray, skel: _Skeleton
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per bone the covered parameter interval (lo, hi; NaN when unused) and the joints used as points."""
    num_bones = len(skel.bones)
    fb = bone[faces]
    fj = joint[faces]
    interior = fj < 0
    has_interior = interior.any(axis=1)
    tri_bone = np.where(has_interior, fb[np.arange(len(faces)), interior.argmax(axis=1)], -1)
    # Triangles with all three vertices at joints: the bone between the two distinct joints, if any.
    jmin = fj.min(axis=1)
    jmax = fj.max(axis=1)
    two = ~has_interior & (jmin != jmax)
    tri_bone[two] = skel.between[jmin[two], jmax[two]]
    on_bone = tri_bone >= 0
    fb_ = np.broadcast_to(tri_bone[:, None], faces.shape)
    params = np.where(
        interior, param[faces], np.where(skel.node_bones[np.maximum(fb_, 0), 0] == fj, 0.0, 1.0)
    )
    lo = np.full(num_bones, np.inf)
    hi = np.full(num_bones, -np.inf)
    np.minimum.at(lo, tri_bone[on_bone], params[on_bone].min(axis=1))
    np.maximum.at(hi, tri_bone[on_bone], params[on_bone].max(axis=1))
    points = skel.rep[np.unique(fj[~has_interior & ~two, 0])]
    return lo, hi, points


def _check(
    problem: RetargetProblem,
    shrunk_joints: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    points: np.ndarray,
    bones: np.ndarray,
) -> float:
    """Intersection and distance check of the garment against the covered source-skeleton segments."""
    import ipctk

    used = np.isfinite(lo)
    a = shrunk_joints[bones[:, 0]]
    d = shrunk_joints[bones[:, 1]] - a
    seg0 = a + np.where(used, lo, 0.0)[:, None] * d
    seg1 = a + np.where(used, hi, 0.0)[:, None] * d
    length = np.linalg.norm(seg1 - seg0, axis=1)
    tiny = 1e-12 * problem.length_scale
    segs = np.nonzero(used & (length > tiny))[0]
    dots = np.concatenate([seg0[used & (length <= tiny)], shrunk_joints[points]])
    gv = problem.garment_vertices.detach().cpu().numpy().astype(np.float64)
    gf = problem.garment_faces.detach().cpu().numpy().astype(np.int64)
    n = gv.shape[0]

    def mesh_for(seg_ids: np.ndarray, extra: np.ndarray) -> tuple[ipctk.CollisionMesh, np.ndarray]:
        ends = np.concatenate([seg0[seg_ids], seg1[seg_ids]])
        verts = np.asfortranarray(np.concatenate([gv, ends, extra]))
        m = len(seg_ids)
        sedges = n + np.stack([np.arange(m), m + np.arange(m)], axis=1)
        edges = np.asfortranarray(np.concatenate([ipctk.edges(gf), sedges]), dtype=np.int32)
        mesh = ipctk.CollisionMesh(verts, edges, np.asfortranarray(gf, dtype=np.int32))
        patches = np.r_[np.zeros(n, np.int32), np.ones(verts.shape[0] - n, np.int32)]
        mesh.can_collide = ipctk.make_vertex_patches_filter(patches)
        return mesh, verts

    mesh, verts = mesh_for(segs, dots)
    if ipctk.has_intersections(mesh, verts):
        names = problem.source_skeleton.names
        crossing = []
        for b in segs:
            one, vv = mesh_for(np.array([b]), np.zeros((0, 3)))
            if ipctk.has_intersections(one, vv):
                i, j = bones[b]
                crossing.append(f"{names[i]}-{names[j]}" if names else f"{i}-{j}")
        listed = ", ".join(crossing[:6]) + (", ..." if len(crossing) > 6 else "")
        raise InputError(
            "the source skeleton is not inside the garment: the shrunk target avatar would intersect it "
            f"(bones crossing the garment surface: {listed or 'unknown'})"
        )
    radius = CHECK_RADIUS * problem.length_scale
    col = ipctk.NormalCollisions()
    col.build(mesh, verts, radius)
    if len(col) == 0:
        return radius
    distance = math.sqrt(max(float(col.compute_minimum_distance(mesh, verts)), 0.0))
    if not distance > 0:
        raise InputError(
            "the shrunk target avatar touches the garment (zero distance to the source skeleton)"
        )
    return min(distance, radius)


def shrink_avatar(
    problem: RetargetProblem, *, check: bool = True, offset: float = SHRINK_OFFSET
) -> ShrunkAvatar:
    """Shrink the target avatar onto the source skeleton (paper section 3.3).

    Args:
        problem: the retargeting problem (work frame).
        check: assert with ipctk that the shrunk avatar does not intersect the garment and keeps a positive
            distance from it.
        offset: distance of the shrunk vertices from the skeleton, relative to ``length_scale`` (> 0).

    Returns:
        The subdivided avatar with full and shrunk positions (problem dtype and device).

    Raises:
        InputError: the avatar cannot be shrunk (a triangle across disconnected skeleton parts), or, with
            ``check``, the shrunk avatar intersects or touches the garment (the source skeleton is not inside
            the garment).
    """
    dtype, device = problem.avatar_vertices.dtype, problem.avatar_vertices.device
    bones_t = problem.source_skeleton.bones.long()
    bones = bones_t.cpu().numpy()
    num_joints = problem.source_skeleton.num_joints
    src = problem.source_skeleton.joints.detach().cpu().double().numpy()
    tgt = problem.target_skeleton.joints.detach().cpu().double().numpy()
    tiny = ZERO_BONE * problem.length_scale
    zero = (np.linalg.norm(src[bones[:, 1]] - src[bones[:, 0]], axis=1) <= tiny) & (
        np.linalg.norm(tgt[bones[:, 1]] - tgt[bones[:, 0]], axis=1) <= tiny
    )
    skel = _Skeleton(num_joints, bones, zero)
    bone_t, param_t = _assign_bones(problem)
    bone = bone_t.cpu().numpy()
    param = param_t.detach().cpu().double().numpy()
    ends = skel.node_bones[bone]
    node = np.where(param <= 0.0, ends[:, 0], np.where(param >= 1.0, ends[:, 1], -1))
    full = problem.avatar_vertices.detach().cpu().double().numpy()
    faces = problem.avatar_faces.cpu().numpy().astype(np.int64)
    full, faces, bone, param, node, rounds = _subdivide(full, faces, bone, param, node, skel)
    joint = np.where(node >= 0, skel.rep[np.maximum(node, 0)], -1)
    a = src[bones[bone, 0]]
    b = src[bones[bone, 1]]
    on_source = np.where((joint >= 0)[:, None], src[np.maximum(joint, 0)], a + param[:, None] * (b - a))
    ta = tgt[bones[bone, 0]]
    tb = tgt[bones[bone, 1]]
    on_target = np.where((joint >= 0)[:, None], tgt[np.maximum(joint, 0)], ta + param[:, None] * (tb - ta))
    direction = full - on_target
    norm = np.linalg.norm(direction, axis=1)
    flat = norm <= 1e-12 * problem.length_scale
    if flat.any():  # a vertex on its bone: any direction perpendicular to the (source) bone
        axis = b[flat] - a[flat]
        helper = np.eye(3)[np.argmin(np.abs(axis), axis=1)]
        perp = np.cross(axis, helper)
        perp[np.linalg.norm(perp, axis=1) == 0] = np.array([1.0, 0.0, 0.0])
        direction[flat] = perp
        norm[flat] = np.linalg.norm(perp, axis=1)
    if not (math.isfinite(offset) and offset > 0):
        raise InputError(f"shrink offset must be positive, got {offset}")
    eps = offset * problem.length_scale
    shrunk = on_source + eps * direction / norm[:, None]
    min_distance = math.nan
    if check:
        lo, hi, points = _covered_segments(faces, bone, param, node, skel)
        distance = _check(problem, src, lo, hi, points, bones)
        if not distance > 2 * eps:
            raise InputError(
                f"the garment comes within {distance:.3g} m of the source skeleton; the shrunk avatar needs "
                f"more than {2 * eps:.3g} m"
            )
        min_distance = distance - eps
    num_original = int(problem.avatar_vertices.shape[0])
    full_t = torch.as_tensor(full, dtype=dtype, device=device)
    full_t[:num_original] = problem.avatar_vertices.detach()
    return ShrunkAvatar(
        vertices_full=full_t,
        vertices_shrunk=torch.as_tensor(shrunk, dtype=dtype, device=device),
        faces=torch.as_tensor(faces, dtype=torch.long, device=device),
        bone_of_vertex=torch.as_tensor(bone, dtype=torch.long, device=device),
        joint_of_vertex=torch.as_tensor(joint, dtype=torch.long, device=device),
        bone_parameter=torch.as_tensor(param, dtype=dtype, device=device),
        num_original=num_original,
        iterations=rounds,
        min_distance=min_distance,
        offset=eps,
        skeleton_points=torch.as_tensor(on_source, dtype=dtype, device=device),
    )
