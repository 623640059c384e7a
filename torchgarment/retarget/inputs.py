"""Inputs of intersection-free garment retargeting (Huang et al. 2025): files, validation, the work frame.

A :class:`RetargetProblem` holds everything the retargeting steps need, in one *work frame*: the frame of the
source garment and source skeleton (the garment is never moved before the optimisation). The target avatar
and target skeleton are mapped into it by a similarity ``to_work`` (:class:`Similarity`) that follows the
skeletons, so avatars in any unit and place (a 6 cm figurine far from the origin, a 4 m giant, centimetres
instead of metres) land on the source model:

* scale: the length-weighted median, over the bones longer than ``1e-6`` of the skeleton's size in both
  skeletons, of the ratio source length / target length (weights: source bone lengths, so that the many
  short finger and toe bones do not dominate). The median ignores the bones an unusual avatar changes as
  long as they make less than half of the skeleton's length (long arms: about 30 %, short legs: about 45 %
  of anny's), so such avatars keep their proportions relative to the garment, while a change of unit or an
  overall size change is removed. Results map back with ``to_work.inverse``.
* translation: the root joint of the target skeleton (the root of the bone tree holding the most joints)
  lands on the source root joint.

``length_scale`` is the largest extent of the axis-aligned bounding box of the source skeleton joints and the
garment vertices (about 1.6 m for an adult in A-pose); tolerances (welding, degenerate areas, the default
fit distance, the solver's dhat) are relative to it.

File conventions (those of the reference implementation): the garment is a manifold triangle OBJ (vertices
split along UV seams are welded first, see :func:`weld_garment`); skeletons are OBJ edge graphs (``v`` joints,
``l`` bones, read by :func:`torchgarment.body.skeleton_io.read_skeleton_obj`) with the same connectivity and
joint order in the source and the target; the target avatar is a triangle mesh that may be non-manifold,
disconnected and self-intersecting (degenerate triangles are dropped, the rest kept); skin weights are a
joints x avatar-vertices text matrix; the no-fit file lists whitespace-separated **0-based** garment vertex
indices (indices of the file, before welding) that the fit term ignores; the curves file has one curve loop
per line, as 0-based garment vertex indices.

Fit region: with a source avatar, garment vertices within ``fit_distance`` of it (unsigned distance, default
:data:`DEFAULT_FIT_DISTANCE` scaled by ``length_scale / 1.7``) are fitted (:func:`automatic_fit_mask`); the
no-fit list, when given, is removed from that region (or from the whole garment without a source avatar).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchgarment.body.body import Body
from torchgarment.body.kinematics import check_bone_forest
from torchgarment.body.skeleton import Skeleton
from torchgarment.body.skeleton_io import (
    read_skeleton_obj,
    read_skin_weights,
    read_text_file,
    validate_skin_weights,
)
from torchgarment.errors import InputError, MeshError
from torchgarment.io.mesh import load_mesh
from torchgarment.structures.mesh_checks import check_mesh, find_unreferenced_vertices, weld_vertices

__all__ = [
    "DEFAULT_FIT_DISTANCE",
    "REFERENCE_HEIGHT",
    "RetargetProblem",
    "Similarity",
    "automatic_fit_mask",
    "load_problem",
    "problem_from_arrays",
    "problem_from_bodies",
    "read_curves",
    "read_index_list",
    "skeleton_root",
    "source_gaps",
    "weld_garment",
    "work_similarity",
]

#: Size (metres) of the model for which the absolute defaults below are stated; other sizes scale them.
REFERENCE_HEIGHT = 1.7
#: Default fit distance (metres at ``REFERENCE_HEIGHT``): garment vertices closer than this to the source
#: avatar form the automatic fit region (tight parts: shoulders, waistband, cuffs; not a flaring skirt).
DEFAULT_FIT_DISTANCE = 0.03
#: Welding tolerance of the garment, relative to ``length_scale`` (UV-seam copies are exact duplicates).
WELD_TOLERANCE = 1e-7
#: Triangles with area below ``(DEGENERATE_RELATIVE * size)**2`` count as degenerate.
DEGENERATE_RELATIVE = 1e-7


@dataclass
class Similarity:
    """A uniform scale followed by a translation: ``x_work = scale * x + translation``.

    Attributes:
        scale: positive scale factor (work units per input unit).
        translation: (3,) translation in work-frame metres.
    """

    scale: float
    translation: torch.Tensor

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        """Map (..., 3) points into the work frame."""
        return x * self.scale + self.translation.to(dtype=x.dtype, device=x.device)

    def inverse(self, x: torch.Tensor) -> torch.Tensor:
        """Map (..., 3) work-frame points back to the input frame."""
        return (x - self.translation.to(dtype=x.dtype, device=x.device)) / self.scale

    @classmethod
    def identity(
        cls, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
    ) -> "Similarity":
        """The identity map."""
        return cls(1.0, torch.zeros(3, dtype=dtype, device=device))


@dataclass
class RetargetProblem:
    """A retargeting problem, everything in the work frame (= the source garment's frame), metres.

    Attributes:
        garment_vertices: (N, 3) welded, manifold, intersection-free garment.
        garment_faces: (F, 3) long.
        source_skeleton: joints (J, 3) and bones (B, 2) of the source model.
        target_skeleton: target joints mapped by ``to_work``; the same bones (order included) as the source.
        avatar_vertices: (A, 3) target avatar in the work frame.
        avatar_faces: (G, 3) long; degenerate faces dropped; may be non-manifold, disconnected,
            self-intersecting.
        skin_weights: (J, A) target skin weights (columns sum to 1) or None.
        fit_mask: (N,) bool, garment vertices the fit term uses.
        curves: extra curve loops (long index tensors into the welded garment) to preserve.
        to_work: target frame -> work frame.
        length_scale: characteristic size of the source model (metres), see the module docstring.
        source_avatar_vertices: (A_s, 3) source avatar or None.
        source_avatar_faces: (G_s, 3) long or None.
        garment_index_map: (N_in,) long, welded index of every input garment vertex (-1: dropped, unused by
            any face), or None when the garment was given welded.
    """

    garment_vertices: torch.Tensor
    garment_faces: torch.Tensor
    source_skeleton: Skeleton
    target_skeleton: Skeleton
    avatar_vertices: torch.Tensor
    avatar_faces: torch.Tensor
    skin_weights: torch.Tensor | None
    fit_mask: torch.Tensor
    curves: list[torch.Tensor]
    to_work: Similarity
    length_scale: float
    source_avatar_vertices: torch.Tensor | None = None
    source_avatar_faces: torch.Tensor | None = None
    garment_index_map: torch.Tensor | None = None


# ----------------------------------------------------------------------------------------------------------
# Garment
# ----------------------------------------------------------------------------------------------------------


def weld_garment(
    vertices: torch.Tensor, faces: torch.Tensor, tol: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Weld a garment split along UV seams into one surface and check that it is a usable manifold.

    Vertices closer than ``tol`` are merged (:func:`~torchgarment.structures.mesh_checks.weld_vertices`),
    faces that collapse are removed, and vertices that no face uses are dropped (they would be free
    unknowns without any energy).

    Args:
        vertices: (N, 3) positions in metres.
        faces: (F, 3) long vertex indices.
        tol: merge distance in metres (>= 0).

    Returns:
        vertices: (N', 3) welded positions.
        faces: (F', 3) long faces of the welded mesh.
        old_to_new: (N,) long, the new index of every input vertex, -1 for dropped (unreferenced) ones.

    Raises:
        MeshError: bad shapes, out-of-range indices, degenerate faces, non-manifold edges or inconsistently
            oriented neighbours after welding.
    """
    if not isinstance(vertices, torch.Tensor) or vertices.ndim != 2 or vertices.shape[1] != 3:
        raise MeshError(
            f"garment vertices must be a (N, 3) tensor, got {getattr(vertices, 'shape', vertices)}"
        )
    if not isinstance(faces, torch.Tensor) or faces.ndim != 2 or faces.shape[1] != 3 or faces.numel() == 0:
        raise MeshError(
            f"garment faces must be a non-empty (F, 3) tensor, got {getattr(faces, 'shape', faces)}"
        )
    faces = faces.long()
    if faces.min() < 0 or faces.max() >= vertices.shape[0]:
        raise MeshError(f"garment faces index vertices outside [0, {vertices.shape[0]})")
    if not torch.isfinite(vertices).all():
        raise MeshError("garment vertices have non-finite coordinates")
    welded, wfaces, index_map = weld_vertices(vertices, faces, tol)
    if wfaces.shape[0] == 0:
        raise MeshError("garment has no faces left after welding")
    unused = find_unreferenced_vertices(welded.shape[0], wfaces)
    if unused.numel():
        keep = torch.ones(welded.shape[0], dtype=torch.bool, device=welded.device)
        keep[unused] = False
        compact = torch.full((welded.shape[0],), -1, dtype=torch.long, device=welded.device)
        compact[keep] = torch.arange(int(keep.sum()), device=welded.device)
        welded, wfaces, index_map = welded[keep], compact[wfaces], compact[index_map]
    extent = float((welded.max(dim=0).values - welded.min(dim=0).values).max()) if welded.shape[0] else 0.0
    check_mesh(
        welded,
        wfaces,
        require_manifold=True,
        name="garment (after welding UV-seam splits)",
        area_tol=(DEGENERATE_RELATIVE * max(extent, 1e-300)) ** 2,
    )
    return welded, wfaces, index_map


def source_gaps(
    garment_vertices: torch.Tensor,
    avatar_vertices: torch.Tensor,
    avatar_faces: torch.Tensor,
) -> torch.Tensor:
    """Each garment vertex's unsigned distance to an avatar surface: how loose the garment sits on it.

    Args:
        garment_vertices: (N, 3) garment positions in metres.
        avatar_vertices: (A, 3) avatar positions (the source avatar, in the garment's frame).
        avatar_faces: (G, 3) long avatar faces (any mesh: non-manifold, open, self-intersecting).

    Returns:
        (N,) distances in metres, in the garment's dtype and on its device.

    Raises:
        InputError: an avatar without faces.
    """
    import igl

    if avatar_faces.numel() == 0:
        raise InputError("source avatar has no faces; cannot measure the garment's gaps to it")
    p = np.ascontiguousarray(garment_vertices.detach().cpu().numpy(), dtype=np.float64)
    v = np.ascontiguousarray(avatar_vertices.detach().cpu().numpy(), dtype=np.float64)
    f = np.ascontiguousarray(avatar_faces.detach().cpu().numpy(), dtype=np.int64)
    sq, _, _ = igl.point_mesh_squared_distance(p, v, f)
    gaps = np.sqrt(np.asarray(sq))
    return torch.as_tensor(gaps, dtype=garment_vertices.dtype, device=garment_vertices.device)


def automatic_fit_mask(
    garment_vertices: torch.Tensor,
    avatar_vertices: torch.Tensor,
    avatar_faces: torch.Tensor,
    threshold: float,
) -> torch.Tensor:
    """Garment vertices close to an avatar: the region whose tightness the fit term preserves.

    Args:
        garment_vertices: (N, 3) garment positions in metres.
        avatar_vertices: (A, 3) avatar positions (the source avatar, in the garment's frame).
        avatar_faces: (G, 3) long avatar faces (any mesh: non-manifold, open, self-intersecting).
        threshold: distance in metres; vertices with unsigned distance to the avatar surface <= threshold
            are selected.

    Returns:
        (N,) bool on the garment's device.

    Raises:
        InputError: a non-positive or non-finite threshold, or an avatar without faces.
    """
    if not (math.isfinite(threshold) and threshold > 0):
        raise InputError(f"fit distance must be a positive length in metres, got {threshold}")
    if avatar_faces.numel() == 0:
        raise InputError("source avatar has no faces; cannot choose the fit region")
    return source_gaps(garment_vertices.double(), avatar_vertices, avatar_faces) <= threshold


# ----------------------------------------------------------------------------------------------------------
# Index files
# ----------------------------------------------------------------------------------------------------------


def _parse_indices(tokens: list[str], count: int, where: str) -> np.ndarray:
    try:
        idx = np.array([int(t) for t in tokens], dtype=np.int64)
    except ValueError:
        bad = next(t for t in tokens if not t.lstrip("+-").isdigit())
        raise InputError(f"{where}: {bad[:40]!r} is not an integer vertex index") from None
    out = idx[(idx < 0) | (idx >= count)]
    if out.size:
        raise InputError(
            f"{where}: vertex index {int(out[0])} is out of range for a garment of {count} vertices "
            "(indices are 0-based)"
        )
    return idx


def read_index_list(path: str | os.PathLike, count: int, *, what: str = "no-fit") -> torch.Tensor:
    """Read whitespace-separated 0-based vertex indices (``#`` starts a comment).

    Args:
        path: text file.
        count: number of garment vertices in the file's indexing (indices must lie in [0, count)).
        what: name of the file in error messages.

    Returns:
        (K,) long indices, in file order.

    Raises:
        InputError: missing or empty file, a non-integer token or an index out of range.
    """
    path = Path(path)
    text = read_text_file(path, what)
    tokens = [t for line in text.splitlines() for t in line.split("#", 1)[0].split()]
    if not tokens:
        raise InputError(f"{what} file {path} is empty (expected whitespace-separated vertex indices)")
    return torch.as_tensor(_parse_indices(tokens, count, f"{what} file {path}"))


def read_curves(path: str | os.PathLike, count: int) -> list[torch.Tensor]:
    """Read curve loops: one loop per non-empty line, as 0-based vertex indices.

    Args:
        path: text file.
        count: number of garment vertices in the file's indexing.

    Returns:
        One (K_i,) long tensor per loop (K_i >= 3).

    Raises:
        InputError: missing or empty file, bad tokens, indices out of range or a loop of fewer than three
            vertices.
    """
    path = Path(path)
    text = read_text_file(path, "curves")
    loops = []
    for number, line in enumerate(text.splitlines(), start=1):
        tokens = line.split("#", 1)[0].split()
        if not tokens:
            continue
        idx = _parse_indices(tokens, count, f"curves file {path}: line {number}")
        if idx.size < 3:
            raise InputError(f"curves file {path}: line {number}: a curve loop needs at least three vertices")
        loops.append(torch.as_tensor(idx))
    if not loops:
        raise InputError(f"curves file {path} is empty (expected one line of vertex indices per curve loop)")
    return loops


# ----------------------------------------------------------------------------------------------------------
# Skeletons and the work frame
# ----------------------------------------------------------------------------------------------------------


def skeleton_root(skeleton: Skeleton) -> int:
    """The root joint of the bone tree with the most joints (a joint that is no bone's child).

    When the bones are not written parent -> child (a joint with several parents), the joint of that tree
    nearest to its mean joint position is used.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    j = skeleton.num_joints
    bones = skeleton.bones.detach().cpu().long().numpy()
    graph = coo_matrix((np.ones(len(bones)), (bones[:, 0], bones[:, 1])), shape=(j, j))
    _, labels = connected_components(graph, directed=False)
    biggest = np.argmax(np.bincount(labels))
    members = np.nonzero(labels == biggest)[0]
    child_count = np.bincount(bones[:, 1], minlength=j)
    roots = [int(m) for m in members if child_count[m] == 0]
    if len(roots) == 1:
        return roots[0]
    joints = skeleton.joints.detach().cpu().double().numpy()[members]
    return int(members[np.argmin(np.linalg.norm(joints - joints.mean(axis=0), axis=1))])


def _check_compatible(source: Skeleton, target: Skeleton) -> torch.Tensor:
    """The target bones re-ordered like the source's; InputError when the connectivity differs."""
    for name, s in (("source", source), ("target", target)):
        if s.joints.ndim != 2 or s.joints.shape[1] != 3 or s.num_joints == 0:
            raise InputError(f"{name} skeleton joints must have shape (J, 3), got {tuple(s.joints.shape)}")
        if not torch.isfinite(s.joints).all():
            raise InputError(f"{name} skeleton has non-finite joint positions")
        check_bone_forest(s.num_joints, s.bones)
    if source.num_joints != target.num_joints:
        raise InputError(
            "source and target skeletons must have the same joints: "
            f"{source.num_joints} vs {target.num_joints}"
        )
    sb = torch.sort(source.bones.detach().cpu().long(), dim=1).values
    tb = torch.sort(target.bones.detach().cpu().long(), dim=1).values
    skeys = set(map(tuple, sb.tolist()))
    tkeys = set(map(tuple, tb.tolist()))
    if skeys != tkeys:
        missing = sorted(skeys - tkeys)[:3]
        extra = sorted(tkeys - skeys)[:3]
        raise InputError(
            "source and target skeletons must have the same bones (same connectivity and joint order): "
            f"{len(skeys - tkeys)} source bones missing in the target (first {missing}), "
            f"{len(tkeys - skeys)} extra (first {extra})"
        )
    return source.bones.clone()


def work_similarity(source: Skeleton, target: Skeleton) -> Similarity:
    """The similarity taking the target skeleton onto the source skeleton (see the module docstring).

    Args:
        source: source skeleton (work frame).
        target: target skeleton (its own frame), same bones as the source.

    Returns:
        ``to_work``: median bone-length ratio as scale, root joint onto root joint.

    Raises:
        InputError: no bone has a positive length in both skeletons.
    """
    bones = source.bones.long()
    sj = source.joints.detach().double().cpu()
    tj = target.joints.detach().double().cpu()
    ls = (sj[bones[:, 1]] - sj[bones[:, 0]]).norm(dim=1)
    lt = (tj[bones[:, 1]] - tj[bones[:, 0]]).norm(dim=1)
    size_s = float((sj.max(dim=0).values - sj.min(dim=0).values).max())
    size_t = float((tj.max(dim=0).values - tj.min(dim=0).values).max())
    ok = (ls > 1e-6 * size_s) & (lt > 1e-6 * size_t)
    if not bool(ok.any()):
        raise InputError("the skeletons have no bone of positive length in both; cannot relate their sizes")
    ratio, weight = (ls[ok] / lt[ok]), ls[ok]
    order = torch.argsort(ratio)
    cumulative = torch.cumsum(weight[order], dim=0)
    scale = float(ratio[order][int(torch.searchsorted(cumulative, 0.5 * cumulative[-1]))])
    root = skeleton_root(source)
    translation = sj[root] - scale * tj[root]
    return Similarity(scale, translation.to(dtype=source.joints.dtype, device=source.joints.device))


# ----------------------------------------------------------------------------------------------------------
# Problem assembly
# ----------------------------------------------------------------------------------------------------------


def _as_float(
    x: torch.Tensor | np.ndarray, dtype: torch.dtype, device: torch.device | str | None, name: str
) -> torch.Tensor:
    t = torch.as_tensor(np.asarray(x) if not isinstance(x, torch.Tensor) else x)
    if t.ndim != 2 or t.shape[1] != 3 or t.shape[0] == 0:
        raise InputError(f"{name} must be a non-empty (n, 3) array, got shape {tuple(t.shape)}")
    t = t.detach().to(dtype=dtype, device=device)
    if not torch.isfinite(t).all():
        raise InputError(f"{name} has non-finite coordinates")
    return t


def _as_faces(
    f: torch.Tensor | np.ndarray, num_vertices: int, device: torch.device | str | None, name: str
) -> torch.Tensor:
    t = torch.as_tensor(np.asarray(f) if not isinstance(f, torch.Tensor) else f)
    if t.ndim != 2 or t.shape[1] != 3 or t.shape[0] == 0:
        raise InputError(
            f"{name} must be a non-empty (m, 3) array of vertex indices, got shape {tuple(t.shape)}"
        )
    if t.is_floating_point():
        raise InputError(f"{name} must be integer vertex indices, got {t.dtype}")
    t = t.detach().long().to(device=device)
    if t.min() < 0 or t.max() >= num_vertices:
        raise InputError(f"{name} index vertices outside [0, {num_vertices})")
    return t


def _drop_degenerate(vertices: torch.Tensor, faces: torch.Tensor, name: str) -> torch.Tensor:
    """Faces of a messy avatar without repeated indices and (near) zero-area triangles."""
    extent = float((vertices.max(dim=0).values - vertices.min(dim=0).values).max())
    tri = vertices[faces]
    area2 = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1).norm(dim=-1)
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    keep = ~repeated & (0.5 * area2 > (DEGENERATE_RELATIVE * max(extent, 1e-300)) ** 2)
    if not bool(keep.any()):
        raise InputError(f"{name} has only degenerate triangles")
    return faces[keep]


def _check_garment_intersections(vertices: torch.Tensor, faces: torch.Tensor) -> None:
    from torchgarment.sim.contact import intersects_itself

    if intersects_itself(vertices, faces):
        raise MeshError("the garment intersects itself; retargeting needs an intersection-free garment "
                        "(torchgarment drape --self-contact makes one)")


def _remap(indices: torch.Tensor, index_map: torch.Tensor | None, what: str) -> torch.Tensor:
    if index_map is None:
        return indices
    new = index_map[indices.to(index_map.device)]
    if bool((new < 0).any()):
        bad = int(indices[new < 0][0])
        raise InputError(f"{what}: vertex {bad} belongs to no garment face")
    return new


GARMENT_SCALE_RANGE = (1.0 / 200.0, 20.0)
"""Accepted ratio of the garment's size (its bounding box's largest side) to the source skeleton's: from an
earring on a person (about 1/100) to a cape or a train several times a body's size. Outside it the garment and
the skeleton are in different units (a garment in millimetres on a skeleton in metres is 1000 times too big,
and its solve ran for minutes at seconds per iteration)."""


def check_garment_scale(garment_vertices: torch.Tensor, skeleton_joints: torch.Tensor) -> None:
    """Raise :class:`InputError` when the garment (V, 3) and the source skeleton's joints (J, 3) look like
    different units (:data:`GARMENT_SCALE_RANGE`), naming the power of ten that would reconcile them. A
    skeleton of zero extent (one joint) is not checked."""
    g = float((garment_vertices.amax(dim=0) - garment_vertices.amin(dim=0)).max())
    s = float((skeleton_joints.amax(dim=0) - skeleton_joints.amin(dim=0)).max())
    if not s > 0:
        return
    ratio = g / s
    lo, hi = GARMENT_SCALE_RANGE
    if not lo <= ratio <= hi:
        factor = 10.0 ** -round(math.log10(ratio)) if ratio > 0 else math.nan
        raise InputError(f"the garment ({g:.4g} across) is {ratio:.3g} times the size of the source skeleton "
                         f"({s:.4g} across), outside {lo:g}-{hi:g}: they look like different units (scale "
                         f"the garment by {factor:g})")


def problem_from_arrays(
    garment_vertices: torch.Tensor | np.ndarray,
    garment_faces: torch.Tensor | np.ndarray,
    source_skeleton: Skeleton,
    target_vertices: torch.Tensor | np.ndarray,
    target_faces: torch.Tensor | np.ndarray,
    target_skeleton: Skeleton,
    *,
    skin_weights: torch.Tensor | None = None,
    source_avatar: tuple | None = None,
    no_fit: torch.Tensor | None = None,
    curves: list[torch.Tensor] | None = None,
    fit_distance: float | None = None,
    check_garment: bool = True,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> RetargetProblem:
    """Assemble and validate a retargeting problem from arrays.

    Args:
        garment_vertices: (N, 3) source garment (may be split along UV seams; it is welded).
        garment_faces: (F, 3) garment faces.
        source_skeleton: skeleton of the source model, in the garment's frame.
        target_vertices: (A, 3) target avatar in its own frame and unit.
        target_faces: (G, 3) target avatar faces.
        target_skeleton: target skeleton in the avatar's frame; same joints and bones as the source.
        skin_weights: optional (J, A) target skin weights (columns are normalised).
        source_avatar: optional (vertices (A_s, 3), faces (G_s, 3)) in the garment's frame; selects the fit
            region automatically.
        no_fit: optional (K,) 0-based indices of *input* garment vertices the fit term ignores.
        curves: optional curve loops, each (K_i,) 0-based indices of input garment vertices.
        fit_distance: distance (work-frame metres) of the automatic fit region; default
            ``DEFAULT_FIT_DISTANCE * length_scale / REFERENCE_HEIGHT``.
        check_garment: reject a garment that intersects itself (ipctk).
        dtype: floating dtype of the problem.
        device: device of the problem's tensors.

    Returns:
        The problem in the work frame.

    Raises:
        MeshError: the garment is not a manifold (after welding) or intersects itself.
        InputError: incompatible skeletons, bad shapes, indices out of range, bad skin weights.
    """
    gv = _as_float(garment_vertices, dtype, device, "garment vertices")
    gf = _as_faces(garment_faces, gv.shape[0], device, "garment faces")
    source_skeleton = source_skeleton.to(device=device, dtype=dtype)
    target_skeleton = target_skeleton.to(device=device, dtype=dtype)
    bones = _check_compatible(source_skeleton, target_skeleton).to(device)
    sj = source_skeleton.joints
    extent = torch.cat([gv, sj]).amax(dim=0) - torch.cat([gv, sj]).amin(dim=0)
    length_scale = float(extent.max())
    if not length_scale > 0:
        raise InputError("the garment and source skeleton have zero size")
    check_garment_scale(gv, sj)

    welded, wfaces, index_map = weld_garment(gv, gf, WELD_TOLERANCE * length_scale)
    if check_garment:
        _check_garment_intersections(welded, wfaces)
    source = Skeleton(sj, bones, list(source_skeleton.names))
    target_in = Skeleton(target_skeleton.joints, bones, list(target_skeleton.names))
    to_work = work_similarity(source, target_in)
    target = Skeleton(to_work.apply(target_in.joints), bones, list(target_skeleton.names))

    av_raw = _as_float(target_vertices, dtype, device, "target avatar vertices")
    af_raw = _as_faces(target_faces, av_raw.shape[0], device, "target avatar faces")
    av = to_work.apply(av_raw)
    af = _drop_degenerate(av, af_raw, "target avatar")
    weights = None
    if skin_weights is not None:
        w = torch.as_tensor(skin_weights).to(dtype=dtype, device=device)
        weights = validate_skin_weights(w, source.num_joints, av.shape[0], source="target skin weights")

    sav = saf = None
    fit_mask = torch.ones(welded.shape[0], dtype=torch.bool, device=welded.device)
    if source_avatar is not None:
        if len(source_avatar) != 2:
            raise InputError("source_avatar must be a (vertices, faces) pair")
        sav = _as_float(source_avatar[0], dtype, device, "source avatar vertices")
        saf = _drop_degenerate(
            sav, _as_faces(source_avatar[1], sav.shape[0], device, "source avatar faces"), "source avatar"
        )
        distance = (
            DEFAULT_FIT_DISTANCE * length_scale / REFERENCE_HEIGHT
            if fit_distance is None
            else float(fit_distance)
        )
        fit_mask = automatic_fit_mask(welded, sav, saf, distance)
    elif fit_distance is not None:
        raise InputError("fit_distance needs a source avatar (the fit region is measured from it)")
    if no_fit is not None:
        nf = torch.as_tensor(no_fit).long().reshape(-1)
        if nf.numel() and (nf.min() < 0 or nf.max() >= gv.shape[0]):
            raise InputError(f"no-fit vertex index out of range for a garment of {gv.shape[0]} vertices")
        nf = index_map[nf.to(index_map.device)]
        fit_mask[nf[nf >= 0]] = False

    loops: list[torch.Tensor] = []
    for k, loop in enumerate(curves or []):
        loop = torch.as_tensor(loop).long().reshape(-1)
        if loop.numel() and (loop.min() < 0 or loop.max() >= gv.shape[0]):
            raise InputError(f"curve {k}: vertex index out of range for a garment of {gv.shape[0]} vertices")
        new = _remap(loop.to(device), index_map, f"curve {k}")
        # Welding can make neighbours of a loop coincide (a loop listing both copies of a seam vertex).
        keep = new != torch.roll(new, 1)
        new = new[keep] if bool(keep.any()) else new[:1]
        if new.numel() < 3:
            raise InputError(f"curve {k} has fewer than three distinct vertices after welding")
        loops.append(new)

    identity = bool(index_map.shape[0] == welded.shape[0]) and bool(
        torch.equal(index_map, torch.arange(index_map.shape[0], device=index_map.device))
    )
    return RetargetProblem(
        garment_vertices=welded,
        garment_faces=wfaces,
        source_skeleton=source,
        target_skeleton=target,
        avatar_vertices=av,
        avatar_faces=af,
        skin_weights=weights,
        fit_mask=fit_mask,
        curves=loops,
        to_work=to_work,
        length_scale=length_scale,
        source_avatar_vertices=sav,
        source_avatar_faces=saf,
        garment_index_map=None if identity else index_map,
    )


def problem_from_bodies(
    garment_vertices: torch.Tensor | np.ndarray,
    garment_faces: torch.Tensor | np.ndarray,
    source: Body,
    target: Body,
    *,
    use_skin_weights: bool = True,
    use_source_avatar: bool = True,
    no_fit: torch.Tensor | None = None,
    curves: list[torch.Tensor] | None = None,
    fit_distance: float | None = None,
    check_garment: bool = True,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> RetargetProblem:
    """A retargeting problem between two bodies that carry skeletons (e.g. anny bodies).

    Args:
        garment_vertices: (N, 3) garment dressed on ``source`` (the source body's frame).
        garment_faces: (F, 3) garment faces.
        source: body the garment was made for; needs a skeleton.
        target: body to dress; needs a skeleton with the same bones.
        use_skin_weights: shrink the target by its skin weights (when it has them) rather than closest bones.
        use_source_avatar: choose the fit region from the source body (:func:`automatic_fit_mask`).
        no_fit, curves, fit_distance, check_garment, dtype, device: as in :func:`problem_from_arrays`.

    Returns:
        The problem.

    Raises:
        InputError: a body without skeleton, or any error of :func:`problem_from_arrays`.
    """
    for name, body in (("source", source), ("target", target)):
        if body.skeleton is None:
            raise InputError(f"the {name} body has no skeleton; retargeting needs rigged avatars")
    return problem_from_arrays(
        garment_vertices,
        garment_faces,
        source.skeleton,
        target.vertices,
        target.faces,
        target.skeleton,
        skin_weights=target.skin_weights if use_skin_weights else None,
        source_avatar=(source.vertices, source.faces) if use_source_avatar else None,
        no_fit=no_fit,
        curves=curves,
        fit_distance=fit_distance,
        check_garment=check_garment,
        dtype=dtype,
        device=device,
    )


def load_problem(
    garment: str | os.PathLike,
    source_skeleton: str | os.PathLike,
    target_avatar: str | os.PathLike,
    target_skeleton: str | os.PathLike,
    *,
    source_avatar: str | os.PathLike | None = None,
    skin_weights: str | os.PathLike | None = None,
    no_fit: str | os.PathLike | None = None,
    curves: str | os.PathLike | None = None,
    fit_distance: float | None = None,
    check_garment: bool = True,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> RetargetProblem:
    """Load a retargeting problem from files (the reference implementation's conventions).

    Args:
        garment: garment mesh (OBJ, or any format of :func:`~torchgarment.io.mesh.load_mesh`); UV-seam
            splits are welded.
        source_skeleton: OBJ edge graph of the source skeleton (garment frame).
        target_avatar: target avatar mesh, read without welding so that skin-weight columns stay aligned.
        target_skeleton: OBJ edge graph of the target skeleton (avatar frame).
        source_avatar: optional source avatar mesh (garment frame) for the automatic fit region.
        skin_weights: optional joints x avatar-vertices text matrix.
        no_fit: optional file of 0-based garment vertex indices (file indexing) the fit term ignores.
        curves: optional file of curve loops, one per line.
        fit_distance, check_garment, dtype, device: as in :func:`problem_from_arrays`.

    Returns:
        The problem.

    Raises:
        InputError: missing or malformed files, incompatible skeletons, bad indices (with the file named).
        MeshError: a garment that is not a manifold after welding, or that intersects itself.
    """
    gv, gf = load_mesh(garment, weld=False, dtype=dtype, device=device)
    ssk = read_skeleton_obj(source_skeleton, dtype=dtype, device=device)
    av, af = load_mesh(target_avatar, weld=False, dtype=dtype, device=device)
    tsk = read_skeleton_obj(target_skeleton, dtype=dtype, device=device)
    weights = None
    if skin_weights is not None:
        weights = read_skin_weights(skin_weights, tsk.num_joints, av.shape[0], dtype=dtype, device=device)
    sa = None
    if source_avatar is not None:
        sa = load_mesh(source_avatar, weld=False, dtype=dtype, device=device)
    nf = read_index_list(no_fit, gv.shape[0], what="no-fit") if no_fit is not None else None
    loops = read_curves(curves, gv.shape[0]) if curves is not None else None
    try:
        return problem_from_arrays(
            gv,
            gf,
            ssk,
            av,
            af,
            tsk,
            skin_weights=weights,
            source_avatar=sa,
            no_fit=nf,
            curves=loops,
            fit_distance=fit_distance,
            check_garment=check_garment,
            dtype=dtype,
            device=device,
        )
    except MeshError as e:
        raise MeshError(f"{garment}: {e}") from None
