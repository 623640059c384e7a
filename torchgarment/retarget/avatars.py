"""Test avatars for retargeting, generated in code from anny bodies (metres, +Y up, front +Z).

Human avatars are anny bodies of the built-in size chart (sizes 6, 12 and 20 are disk-cached; other sizes
take 30-60 s to fit). Non-human avatars are edits of the size-12 body by per-bone linear blend skinning with
its own skeleton and skin weights: joint ``j`` gets an affine map ``x -> new_j + M_j (x - old_j)`` where
``M_j`` is the linear change of the bones leaving ``j`` (a stretch along the bone, or a uniform scale), new
joint positions follow from the parents' maps (``new_c = new_p + M_p (old_c - old_p)``), and every vertex
moves by the skin-weighted blend of the maps of its joints. At a joint both neighbouring maps agree, so the
surface stays continuous; the skeleton is edited with the same maps (same bones, same joint order).

Avatars (:func:`list_avatars`):

* ``anny-6``, ``anny-12``, ``anny-20``: anny bodies of those sizes.
* ``long-arms``: upper and lower arm bones x1.6 (stretched along the bone; hands keep their size).
* ``big-head``: head region x1.8 about the head joint (the top of the neck).
* ``short-legs``: thigh and shin bones x0.6 (along the bone; feet keep their size).
* ``floating-parts``: two detached closed spheres (radius 5 cm) centred 15 cm above and 10 cm outside the
  shoulder joints, skinned to the shoulder joints; the avatar is disconnected.
* ``torso-hole``: a hole of radius 3.5 cm through the belly at the waist, along Z, 5.5 cm beside the spine
  (genus 1): the torso faces
  inside the cylinder are removed, the openings' rims snapped onto the cylinder and bridged by a tube.
* ``miniature``: the size-6 body scaled to 6 cm tall and moved to (100, -50, 30) m (tests ``to_work``).
* ``giant``: the size-20 body scaled to 4 m tall and moved to (-20, 3, 7) m.
* ``creature-10k``, ``creature-50k``: non-human avatars of about 10K and 50K triangles built on the size-12
  skeleton with longer arms (x1.3) and shorter legs (x0.7) (:func:`creature`): a barrel torso, a big head with
  two horns, capsule limbs, ball hands and feet and a tail, each a separate closed or open part that overlaps
  its neighbours (the mesh intersects itself), with the tail's end and the horns' bases open (not closed).
  Each part is skinned rigidly to one joint. ``creature-10k`` is scaled to 6 cm tall at (3, 1, -2) m,
  ``creature-50k`` to 10 m at (-40, 0, 25) m.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from torchgarment.body.body import Body
from torchgarment.body.skeleton import Skeleton
from torchgarment.errors import InputError

__all__ = [
    "AVATARS",
    "TestAvatar",
    "ToyCase",
    "creature",
    "layered_garment",
    "rig_from_fitted_anny",
    "edit_by_bones",
    "list_avatars",
    "make_avatar",
    "toy_case",
    "tube_mesh",
]


#: Radius (m) of the torso hole and the distance (m) of its axis from the body's midline (off the spine).
HOLE_RADIUS = 0.035
HOLE_OFFSET = 0.055


@dataclass
class TestAvatar:
    """A generated avatar.

    Attributes:
        name: its name in :func:`list_avatars`.
        vertices: (V, 3) positions, metres.
        faces: (F, 3) long.
        skeleton: joints (J, 3) and bones, the anny bone graph.
        skin_weights: (J, V) weights (columns sum to 1) or None.
        description: one line.
    """

    __test__ = False  # not a pytest test class

    name: str
    vertices: torch.Tensor
    faces: torch.Tensor
    skeleton: Skeleton
    skin_weights: torch.Tensor | None
    description: str

    def as_body(self) -> Body:
        """The avatar as a :class:`Body` (skeleton and skin weights attached)."""
        return Body(self.vertices, self.faces, self.skeleton, self.skin_weights, params={"avatar": self.name})


@functools.lru_cache(maxsize=4)
def _anny(size: str) -> Body:
    return Body.from_size(size)


def _base(size: str) -> Body:
    b = _anny(size)
    return Body(
        b.vertices.clone(),
        b.faces.clone(),
        Skeleton(b.skeleton.joints.clone(), b.skeleton.bones.clone(), list(b.skeleton.names)),
        b.skin_weights.clone(),
    )


def _joints_named(skeleton: Skeleton, prefixes: tuple[str, ...]) -> list[int]:
    found = [i for i, n in enumerate(skeleton.names) if n.startswith(prefixes)]
    if not found:
        raise InputError(f"skeleton has no joint named like {prefixes}")
    return found


def edit_by_bones(body: Body, linear: dict[int, torch.Tensor]) -> Body:
    """Edit a rigged body by per-joint linear maps blended with its skin weights.

    Args:
        body: body with skeleton (J joints, bones parent -> child) and (J, V) skin weights.
        linear: joint index -> (3, 3) linear map of the bones leaving that joint (identity for the others).

    Returns:
        A new body: vertices ``sum_j w_j (new_j + M_j (x - old_j))`` and the edited skeleton (same bones).
    """
    sk = body.skeleton
    old = sk.joints
    eye = torch.eye(3, dtype=old.dtype, device=old.device)
    maps = eye.expand(sk.num_joints, 3, 3).clone()
    for j, m in linear.items():
        maps[j] = m.to(old)
    parent = torch.full((sk.num_joints,), -1, dtype=torch.long)
    parent[sk.bones[:, 1].cpu()] = sk.bones[:, 0].cpu()
    new = old.clone()
    order = _topological(parent)
    for j in order:  # joints (about a hundred), parents before children
        p = int(parent[j])
        if p >= 0:
            new[j] = new[p] + maps[p] @ (old[j] - old[p])
    w = body.skin_weights  # (J, V)
    x = body.vertices
    local = torch.einsum("jab,vb->jva", maps, x) - torch.einsum("jab,jb->ja", maps, old)[:, None]  # (J, V, 3)
    moved = (w[..., None] * (local + new[:, None])).sum(dim=0)
    return Body(moved, body.faces, Skeleton(new, sk.bones.clone(), list(sk.names)), w)


def _topological(parent: torch.Tensor) -> list[int]:
    depth = torch.zeros_like(parent)
    cur = parent.clone()
    while bool((cur >= 0).any()):
        depth += (cur >= 0).long()
        cur = torch.where(cur >= 0, parent[cur.clamp(min=0)], cur)
    return torch.argsort(depth, stable=True).tolist()


def _stretch(direction: torch.Tensor, factor: float) -> torch.Tensor:
    d = direction / direction.norm()
    return torch.eye(3, dtype=d.dtype) + (factor - 1.0) * torch.outer(d, d)


def _stretch_bones(body: Body, prefixes: tuple[str, ...], factor: float) -> Body:
    sk = body.skeleton
    linear = {}
    for j in _joints_named(sk, prefixes):
        children = sk.bones[sk.bones[:, 0] == j, 1]
        if children.numel() != 1:
            raise InputError(f"joint {sk.names[j]} has {children.numel()} child bones; expected one")
        linear[j] = _stretch(sk.joints[int(children[0])] - sk.joints[j], factor)
    return edit_by_bones(body, linear)


def _icosphere(
    center: torch.Tensor, radius: float, subdivisions: int = 2
) -> tuple[torch.Tensor, torch.Tensor]:
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    v = torch.as_tensor(np.asarray(s.vertices), dtype=center.dtype) + center
    return v, torch.as_tensor(np.asarray(s.faces), dtype=torch.long)


def _floating_parts(body: Body) -> Body:
    sk = body.skeleton
    v, f, w = body.vertices, body.faces, body.skin_weights
    for name in ("shoulder01.L", "shoulder01.R"):
        j = sk.names.index(name)
        side = 1.0 if float(sk.joints[j, 0]) > 0 else -1.0
        center = sk.joints[j] + torch.tensor([0.1 * side, 0.15, 0.0], dtype=v.dtype)
        sv, sf = _icosphere(center, 0.05)
        sw = torch.zeros(sk.num_joints, sv.shape[0], dtype=w.dtype)
        sw[j] = 1.0
        f = torch.cat([f, sf + v.shape[0]])
        v = torch.cat([v, sv])
        w = torch.cat([w, sw], dim=1)
    return Body(v, f, sk, w)


def _torso_hole(body: Body, radius: float = HOLE_RADIUS) -> Body:
    """Cut a cylinder along Z through the belly and bridge the two openings with a tube (genus 1)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    sk = body.skeleton
    v = body.vertices.clone()
    f = body.faces
    waist = body.landmarks.get("waist")
    spine = sk.joints[sk.names.index("spine03")]
    y_c = float(waist[1]) if waist is not None else float(spine[1])
    axis = torch.tensor([HOLE_OFFSET, y_c], dtype=v.dtype)
    rel = v[:, :2] - axis
    dist = rel.norm(dim=1)
    centroid_d = (v[f][:, :, :2].mean(dim=1) - axis).norm(dim=1)
    remove = centroid_d < radius
    faces = f[~remove]
    # Boundary loops of the cut.
    directed = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = directed[:, 0] * v.shape[0] + directed[:, 1]
    rkey = directed[:, 1] * v.shape[0] + directed[:, 0]
    boundary = directed[~torch.isin(key, rkey)].numpy()  # directed edges without a twin
    n = v.shape[0]
    graph = coo_matrix((np.ones(len(boundary)), (boundary[:, 0], boundary[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    loop_labels = np.unique(labels[boundary[:, 0]])
    if len(loop_labels) != 2:
        raise InputError(f"torso-hole cut produced {len(loop_labels)} openings, expected 2")
    # Snap rim vertices radially onto the cylinder.
    rim = np.unique(boundary)
    rim_t = torch.as_tensor(rim)
    v[rim_t, :2] = axis + radius * rel[rim_t] / dist[rim_t, None]
    loops = []
    succ = dict(zip(boundary[:, 0].tolist(), boundary[:, 1].tolist()))
    for lab in loop_labels:
        start = int(boundary[labels[boundary[:, 0]] == lab][0, 0])
        loop = [start]
        while succ[loop[-1]] != start:  # rim of a few dozen vertices
            loop.append(succ[loop[-1]])
        loops.append(np.array(loop))
    front, back = sorted(loops, key=lambda lp: -float(v[torch.as_tensor(lp), 2].mean()))
    tube = _bridge(v, front, back, axis)
    faces = torch.cat([faces, tube])
    used = torch.zeros(n, dtype=torch.bool)
    used[faces.flatten()] = True
    new_index = torch.cumsum(used.long(), 0) - 1
    return Body(v[used], new_index[faces], sk, body.skin_weights[:, used])


def _bridge(v: torch.Tensor, front: np.ndarray, back: np.ndarray, axis: torch.Tensor) -> torch.Tensor:
    """Triangles joining two rim loops on a cylinder along Z, merged by angle (a zipper).

    The rims are directed boundary loops (each boundary edge a -> b is used by a face as a -> b), so a tube
    triangle containing that edge must use it as b -> a; the tube is oriented to match.
    """

    def angles(loop: np.ndarray) -> torch.Tensor:
        rel = v[torch.as_tensor(loop), :2] - axis
        return torch.atan2(rel[:, 1], rel[:, 0]).numpy()

    # Walk both loops in increasing angle, starting from their smallest angle.
    def ordered(loop: np.ndarray) -> np.ndarray:
        a = angles(loop)
        if np.sum(np.diff(np.unwrap(np.r_[a, a[0]]))) < 0:
            loop, a = loop[::-1], a[::-1]
        s = int(np.argmin(a))
        loop, a = np.roll(loop, -s), np.roll(a, -s)
        return loop, np.unwrap(a)

    lf, af = ordered(front)
    lb, ab = ordered(back)
    af = np.r_[af, af[0] + 2 * math.pi]
    ab = np.r_[ab, ab[0] + 2 * math.pi]
    lf = np.r_[lf, lf[0]]
    lb = np.r_[lb, lb[0]]
    i = j = 0
    tris = []
    while i < len(lf) - 1 or j < len(lb) - 1:  # rim vertices, a few dozen
        if j >= len(lb) - 1 or (i < len(lf) - 1 and af[i + 1] <= ab[j + 1]):
            tris.append((lf[i], lf[i + 1], lb[j]))
            i += 1
        else:
            tris.append((lf[i], lb[j + 1], lb[j]))
            j += 1
    tris = torch.as_tensor(np.array(tris), dtype=torch.long)
    # Orientation: the first tube triangle's front edge lf[0] -> lf[1]; the rim uses it as a boundary edge.
    if _uses_edge_forward(front, lf[0], lf[1]):
        tris = tris[:, [1, 0, 2]]
    return tris


def _uses_edge_forward(loop: np.ndarray, a: int, b: int) -> bool:
    """Whether the directed boundary loop contains the edge a -> b (it is used so by an existing face)."""
    pos = {int(x): k for k, x in enumerate(loop)}
    return pos[int(b)] == (pos[int(a)] + 1) % len(loop)


def _rescale(body: Body, height: float, offset: tuple[float, float, float]) -> Body:
    v = body.vertices
    s = height / float(v[:, 1].max() - v[:, 1].min())
    t = torch.tensor(offset, dtype=v.dtype)
    sk = body.skeleton
    return Body(
        v * s + t, body.faces, Skeleton(sk.joints * s + t, sk.bones, list(sk.names)), body.skin_weights
    )


def _part_mesh(kind: str, a: torch.Tensor, b: torch.Tensor, radius: float, detail: int,
               radius_end: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One creature part between points ``a`` and ``b`` (metres): a closed ``capsule`` of ``radius``, an
    ``ellipsoid`` with ``a``-``b`` as its long axis and ``radius`` across, or a ``horn`` / ``tail``: an open
    tube tapering from ``radius`` at ``a`` to ``radius_end`` at ``b`` (no cap at either end). ``detail``:
    segments around."""
    import trimesh

    a64, b64 = a.double().numpy(), b.double().numpy()
    axis = b64 - a64
    length = float(np.linalg.norm(axis))
    if kind == "capsule":
        m = trimesh.creation.capsule(height=length, radius=radius, count=[detail, max(4, detail // 2)])
    elif kind == "ellipsoid":
        m = trimesh.creation.icosphere(subdivisions=1 + int(detail >= 24) + int(detail >= 48), radius=1.0)
        m.apply_scale([radius, radius, 0.5 * length + radius])
    else:
        rings = max(2, int(round(detail * length / (2 * math.pi * radius))))
        r_end = radius if radius_end is None else radius_end
        th = np.arange(detail) * (2 * math.pi / detail)
        z = np.linspace(-0.5 * length, 0.5 * length, rings + 1)
        r = np.linspace(radius, r_end, rings + 1)
        v = np.stack([np.outer(r, np.cos(th)), np.outer(r, np.sin(th)), np.repeat(z[:, None], detail, 1)],
                     -1)
        i = np.arange(rings)[:, None] * detail
        j = np.arange(detail)[None, :]
        a0, a1 = i + j, i + (j + 1) % detail
        b0, b1 = a0 + detail, a1 + detail
        f = np.concatenate([np.stack([a0, a1, b1], -1).reshape(-1, 3),
                            np.stack([a0, b1, b0], -1).reshape(-1, 3)])
        m = trimesh.Trimesh(v.reshape(-1, 3), f, process=False)
    z = np.array([0.0, 0.0, 1.0])
    d = axis / length
    rot = trimesh.geometry.align_vectors(z, d)
    m.apply_transform(rot)
    m.apply_translation(0.5 * (a64 + b64))
    return np.asarray(m.vertices), np.asarray(m.faces)


def creature(body: Body, triangles: int) -> Body:
    """A non-human avatar on ``body``'s skeleton (an anny skeleton): overlapping parts, some open (see the
    module docstring), about ``triangles`` triangles.

    Args:
        body: a rigged anny body (its skeleton is used, its mesh is not).
        triangles: the approximate triangle count (the parts' resolution is scaled to reach it).

    Returns:
        A :class:`Body` with the same skeleton and (J, V) rigid skin weights (one joint per part).
    """
    sk = body.skeleton
    J = sk.joints
    n = sk.names.index

    def mid(*names: str) -> torch.Tensor:
        return torch.stack([J[n(k)] for k in names]).mean(dim=0)

    up = torch.tensor([0.0, 1.0, 0.0], dtype=J.dtype)
    back = torch.tensor([0.0, 0.0, -1.0], dtype=J.dtype)
    parts: list[tuple[str, torch.Tensor, torch.Tensor, float, str, float | None, float]] = [
        # kind, a, b, radius, skinning joint, end radius, relative area weight
        ("ellipsoid", J[n("spine05")] - 0.05 * up, J[n("neck01")], 0.16, "spine03", None, 3.0),
        ("ellipsoid", J[n("head")], J[n("head")] + 0.2 * up, 0.13, "head", None, 1.5),
        ("tail", J[n("spine05")] + 0.08 * back, J[n("spine05")] + 0.55 * back - 0.25 * up, 0.06, "spine05",
         0.015, 0.8),
    ]
    for side in ("L", "R"):
        sgn = 1.0 if float(J[n(f"clavicle.{side}"), 0]) > 0 else -1.0
        horn_a = J[n("head")] + 0.14 * up + 0.06 * sgn * torch.tensor([1.0, 0.0, 0.0], dtype=J.dtype)
        parts += [
            ("horn", horn_a, horn_a + 0.16 * up + 0.1 * sgn * torch.tensor([1.0, 0.0, 0.0], dtype=J.dtype),
             0.035, "head", 0.005, 0.3),
            ("capsule", J[n(f"clavicle.{side}")], J[n(f"upperarm02.{side}")], 0.06, f"clavicle.{side}",
             None, 0.8),
            ("capsule", J[n(f"upperarm02.{side}")], J[n(f"lowerarm01.{side}")], 0.05, f"upperarm02.{side}",
             None, 0.8),
            ("capsule", J[n(f"lowerarm01.{side}")], J[n(f"wrist.{side}")], 0.042, f"lowerarm01.{side}",
             None, 0.8),
            ("ellipsoid", J[n(f"wrist.{side}")], mid(f"finger3-1.{side}", f"wrist.{side}"), 0.05,
             f"wrist.{side}", None, 0.4),
            ("capsule", J[n(f"upperleg01.{side}")], J[n(f"lowerleg01.{side}")], 0.085,
             f"upperleg01.{side}", None, 1.0),
            ("capsule", J[n(f"lowerleg01.{side}")], J[n(f"foot.{side}")], 0.065, f"lowerleg01.{side}",
             None, 1.0),
            ("ellipsoid", J[n(f"foot.{side}")], mid(f"toe3-1.{side}", f"foot.{side}"), 0.06,
             f"foot.{side}", None, 0.5),
        ]
    total = sum(p[6] for p in parts)
    scale = 1.0
    for _ in range(2):  # the second pass corrects the triangle count of the first
        verts, faces, joints = [], [], []
        offset = 0
        for kind, a, b, r, joint, r_end, share in parts:
            # segments around from the part's share of the triangles (about detail^2 per part)
            detail = max(8, int(round(scale * math.sqrt(triangles * share / total))))
            v, f = _part_mesh(kind, a, b, r, detail, r_end)
            verts.append(v)
            faces.append(f + offset)
            joints.append(np.full(len(v), n(joint)))
            offset += len(v)
        scale *= math.sqrt(triangles / sum(len(f) for f in faces))
    v = torch.as_tensor(np.concatenate(verts), dtype=J.dtype)
    f = torch.as_tensor(np.concatenate(faces), dtype=torch.long)
    w = torch.zeros(sk.num_joints, v.shape[0], dtype=J.dtype)
    w[torch.as_tensor(np.concatenate(joints)), torch.arange(v.shape[0])] = 1.0
    return Body(v, f, Skeleton(J.clone(), sk.bones.clone(), list(sk.names)), w)


def _creature(triangles: int, height: float, offset: tuple[float, float, float]) -> Body:
    edited = _stretch_bones(_stretch_bones(_base("12"), ("upperarm", "lowerarm"), 1.3),
                            ("upperleg", "lowerleg"), 0.7)
    return _rescale(creature(edited, triangles), height, offset)


def rig_from_fitted_anny(body: Body) -> Body:
    """A skeleton and skin weights for an unrigged human mesh (e.g. a GarmentCode body): those of the anny
    body fitted to the mesh's own measurements (height, bust, waist, hips; the closest anny body when they are
    out of reach), placed on the same floor and centre in x and z, the weights taken from the nearest anny
    vertex.

    Args:
        body: the mesh (metres, +Y up, A- or T-pose, closed), on the CPU.

    Returns:
        ``body``'s mesh with the fitted anny body's skeleton and (J, V) skin weights (columns sum to one).
    """
    from scipy.spatial import cKDTree

    from torchgarment.body.measure import measure_body

    v = body.vertices.detach().double().cpu()
    m = measure_body(v, body.faces)
    fitted = Body.from_measurements(height=m.height, bust=m.bust, waist=m.waist, hips=m.hips, closest=True)
    fv = fitted.vertices.double()
    shift = torch.stack([v[:, 0].mean() - fv[:, 0].mean(), v[:, 1].min() - fv[:, 1].min(),
                         v[:, 2].mean() - fv[:, 2].mean()])
    idx = torch.as_tensor(cKDTree((fv + shift).numpy()).query(v.numpy(), k=1)[1])
    sk = fitted.skeleton
    return Body(v.to(body.vertices.dtype), body.faces.long(),
                Skeleton((sk.joints + shift).to(body.vertices.dtype), sk.bones.clone(), list(sk.names)),
                fitted.skin_weights[:, idx].to(body.vertices.dtype), params={"rigged_from": "anny"})


def _outward_offset(patch_v: np.ndarray, patch_f: np.ndarray, body: Body, offset: float) -> np.ndarray:
    """``patch_v`` moved ``offset`` metres along the patch's vertex normals, oriented away from ``body``."""
    import igl
    import trimesh

    n = trimesh.Trimesh(patch_v, patch_f, process=False).vertex_normals
    bv, bf = body.vertices.double().numpy(), body.faces.numpy().astype(np.int64)
    moved = patch_v + offset * n
    d0 = igl.signed_distance(patch_v, bv, bf)[0]
    d1 = igl.signed_distance(moved, bv, bf)[0]
    return moved if float(np.mean(d1 - d0)) >= 0 else patch_v - offset * n


def _patch(v: np.ndarray, f: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The faces of ``f`` whose three vertices are all in ``keep`` (a (V,) bool mask), reindexed."""
    faces = f[keep[f].all(axis=1)]
    used, inverse = np.unique(faces, return_inverse=True)
    return v[used], inverse.reshape(-1, 3)


def layered_garment(vertices: torch.Tensor, faces: torch.Tensor, body: Body, *,
                    pockets: tuple[tuple[float, float, float], ...] = (), pocket_radius: float = 0.05,
                    collar: bool = False, hood: bool = False, offset: float = 0.004,
                    ) -> tuple[torch.Tensor, torch.Tensor, dict[str, int]]:
    """A garment dressed on ``body`` with layered parts added as separate pieces (issue 14's messy bench).

    Args:
        vertices, faces: (N, 3) the garment (metres) and (F, 3) its faces.
        body: the body it is dressed on (rigged anny body).
        pockets: points (m) near which a round patch of the garment (``pocket_radius``) is copied
            ``offset`` outwards: patch pockets.
        collar: copy the faces within 3 cm of the garment's topmost boundary loop ``offset`` outwards (a
            collar or a waistband).
        hood: a shell ``5 * offset`` behind the back of the head and neck (the body's surface there, moved
            along its normals).
        offset: the layers' distance from what they lie on (m).

    Returns:
        ``(vertices, faces, parts)``: the garment with its layers, and the number of faces of each part.
    """
    from torchgarment.retarget.objectives import boundary_loops

    v = vertices.detach().double().cpu().numpy()
    f = faces.cpu().numpy().astype(np.int64)
    parts: dict[str, int] = {"garment": len(f)}
    out_v, out_f = [v], [f]
    count = len(v)

    def add(name: str, pv: np.ndarray, pf: np.ndarray) -> None:
        nonlocal count
        out_v.append(pv)
        out_f.append(pf + count)
        count += len(pv)
        parts[name] = len(pf)

    for k, point in enumerate(pockets):
        centre = v[int(np.argmin(np.linalg.norm(v - np.asarray(point), axis=1)))]
        pv, pf = _patch(v, f, np.linalg.norm(v - centre, axis=1) <= pocket_radius)
        add(f"pocket{k}", _outward_offset(pv, pf, body, offset), pf)
    if collar:
        loops = boundary_loops(f)
        top = max(loops, key=lambda lp: float(v[lp, 1].mean()))
        from scipy.spatial import cKDTree

        near = cKDTree(v[top]).query(v, k=1)[0] <= 0.03
        pv, pf = _patch(v, f, near)
        add("collar", _outward_offset(pv, pf, body, offset), pf)
    if hood:
        sk = body.skeleton
        neck = sk.joints[sk.names.index("neck01")].double().numpy()
        head = sk.joints[sk.names.index("head")].double().numpy()
        bv, bf = body.vertices.double().numpy(), body.faces.numpy().astype(np.int64)
        keep = (bv[:, 1] > neck[1] + 0.02) & (bv[:, 2] < head[2] - 0.02)
        pv, pf = _patch(bv, bf, keep)
        add("hood", _outward_offset(pv, pf, body, 5 * offset), pf)
    return (torch.as_tensor(np.concatenate(out_v), dtype=vertices.dtype),
            torch.as_tensor(np.concatenate(out_f), dtype=torch.long), parts)


def _anny_size(size: str) -> Callable[[], TestAvatar]:
    return lambda: _base(size)


AVATARS: dict[str, tuple[str, callable]] = {
    "anny-6": ("anny body, US size 6", _anny_size("6")),
    "anny-12": ("anny body, US size 12", _anny_size("12")),
    "anny-20": ("anny body, US size 20", _anny_size("20")),
    "long-arms": (
        "size 12 with upper and lower arm bones x1.6",
        lambda: _stretch_bones(_base("12"), ("upperarm", "lowerarm"), 1.6),
    ),
    "big-head": (
        "size 12 with the head x1.8 about the head joint",
        lambda: edit_by_bones(
            _base("12"),
            {
                j: 1.8 * torch.eye(3, dtype=torch.float64)
                for j in _joints_named(_base("12").skeleton, ("head", "eye"))
            },
        ),
    ),
    "short-legs": (
        "size 12 with thigh and shin bones x0.6",
        lambda: _stretch_bones(_base("12"), ("upperleg", "lowerleg"), 0.6),
    ),
    "floating-parts": (
        "size 12 with two detached spheres above the shoulders",
        lambda: _floating_parts(_base("12")),
    ),
    "torso-hole": (
        "size 12 with a 3.5 cm hole through the belly (genus 1)",
        lambda: _torso_hole(_with_landmarks("12")),
    ),
    "miniature": (
        "size 6 scaled to 6 cm, far from the origin",
        lambda: _rescale(_base("6"), 0.06, (100.0, -50.0, 30.0)),
    ),
    "giant": (
        "size 20 scaled to 4 m, away from the origin",
        lambda: _rescale(_base("20"), 4.0, (-20.0, 3.0, 7.0)),
    ),
    "creature-10k": (
        "a non-human creature of about 10K triangles (horns, tail; self-intersecting, open), 6 cm tall",
        lambda: _creature(10_000, 0.06, (3.0, 1.0, -2.0)),
    ),
    "creature-50k": (
        "a non-human creature of about 50K triangles (horns, tail; self-intersecting, open), 10 m tall",
        lambda: _creature(50_000, 10.0, (-40.0, 0.0, 25.0)),
    ),
}
"""Name -> (description, builder)."""


def _with_landmarks(size: str) -> Body:
    b = _base(size)
    b.landmarks = dict(_anny(size).landmarks)
    return b


def list_avatars() -> list[str]:
    """Names of the generated test avatars."""
    return list(AVATARS)


def make_avatar(
    name: str, *, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> TestAvatar:
    """Build a test avatar by name (see the module docstring).

    Args:
        name: one of :func:`list_avatars`.
        dtype: floating dtype of the result.
        device: device of the result.

    Returns:
        The avatar (anny sizes 6, 12 and 20 load from the disk cache in about a second).

    Raises:
        InputError: unknown name.
    """
    if name not in AVATARS:
        raise InputError(f"unknown test avatar {name!r}; expected one of: {', '.join(AVATARS)}")
    description, build = AVATARS[name]
    body = build()
    sk = body.skeleton.to(device=device, dtype=dtype)
    return TestAvatar(
        name=name,
        vertices=body.vertices.to(device=device, dtype=dtype),
        faces=body.faces.to(device=device).long(),
        skeleton=sk,
        skin_weights=None if body.skin_weights is None else body.skin_weights.to(device=device, dtype=dtype),
        description=description,
    )


# ----------------------------------------------------------------------------------------------------------
# A small synthetic case (fast tests)
# ----------------------------------------------------------------------------------------------------------


@dataclass
class ToyCase:
    """A tiny retargeting case: a Y-shaped 5-joint skeleton, ellipsoid avatars, a tube garment (metres).

    Attributes:
        garment_vertices: (N, 3) open tube of radius 0.3 around the source trunk (y in [-0.2, 1.25]).
        garment_faces: (F, 3) long.
        source_skeleton: joints (0,0,0), (0,0.6,0), (0,1.2,0), (+-0.35,1.45,0); bones 0-1, 1-2, 2-3, 2-4.
        source_vertices: (A_s, 3) ellipsoid around the source skeleton (inside the garment).
        source_faces: (G_s, 3) long.
        target_vertices: (A, 3) coarse ellipsoid around the target skeleton.
        target_faces: (G, 3) long.
        target_skeleton: the source skeleton with arms x1.3, then scaled by ``target_scale`` and moved by
            ``target_offset``.
    """

    __test__ = False

    garment_vertices: torch.Tensor
    garment_faces: torch.Tensor
    source_skeleton: Skeleton
    source_vertices: torch.Tensor
    source_faces: torch.Tensor
    target_vertices: torch.Tensor
    target_faces: torch.Tensor
    target_skeleton: Skeleton


def tube_mesh(
    radius_x: float,
    radius_z: float,
    y0: float,
    y1: float,
    segments: int,
    rings: int,
    dtype: torch.dtype = torch.float64,
) -> tuple[torch.Tensor, torch.Tensor]:
    """An open elliptic tube along Y: (segments * rings, 3) vertices, outward-facing (F, 3) faces."""
    th = torch.arange(segments, dtype=dtype) * (2 * math.pi / segments)
    ys = torch.linspace(y0, y1, rings, dtype=dtype)
    t, y = torch.meshgrid(th, ys, indexing="ij")
    v = torch.stack([radius_x * torch.cos(t), y, radius_z * torch.sin(t)], dim=-1).reshape(-1, 3)
    i = torch.arange(segments)[:, None]
    j = torch.arange(rings - 1)[None, :]
    a = i * rings + j
    b = ((i + 1) % segments) * rings + j
    f = torch.cat(
        [torch.stack([a, a + 1, b + 1], -1).reshape(-1, 3), torch.stack([a, b + 1, b], -1).reshape(-1, 3)]
    )
    return v, f


def _ellipsoid(
    center: torch.Tensor, radii: torch.Tensor, subdivisions: int, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor]:
    v, f = _icosphere(torch.zeros(3, dtype=dtype), 1.0, subdivisions)
    return v * torch.tensor(radii, dtype=dtype) + torch.tensor(center, dtype=dtype), f


def toy_case(
    *,
    target_scale: float = 1.0,
    target_offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
    avatar_subdivisions: int = 1,
    segments: int = 24,
    rings: int = 10,
    dtype: torch.dtype = torch.float64,
) -> ToyCase:
    """Build the :class:`ToyCase` (coarse avatar triangles span several bones: subdivision is exercised)."""
    joints = torch.tensor(
        [[0, 0, 0], [0, 0.6, 0], [0, 1.2, 0], [0.35, 1.45, 0], [-0.35, 1.45, 0]], dtype=dtype
    )
    bones = torch.tensor([[0, 1], [1, 2], [2, 3], [2, 4]])
    source = Skeleton(joints, bones, ["hip", "spine", "chest", "arm.L", "arm.R"])
    tj = joints.clone()
    tj[3:] = joints[2] + 1.3 * (joints[3:] - joints[2])
    offset = torch.tensor(target_offset, dtype=dtype)
    target = Skeleton(tj * target_scale + offset, bones.clone(), list(source.names))
    gv, gf = tube_mesh(0.3, 0.3, -0.2, 1.25, segments, rings, dtype)
    sv, sf = _ellipsoid((0.0, 0.6, 0.0), (0.28, 0.8, 0.22), 3, dtype)
    av, af = _ellipsoid((0.0, 0.7, 0.0), (0.6, 0.95, 0.2), avatar_subdivisions, dtype)
    return ToyCase(gv, gf, source, sv, sf, av * target_scale + offset, af, target)
