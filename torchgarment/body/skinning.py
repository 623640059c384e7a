"""Linear blend skinning and re-posing a body between A-pose and T-pose.

Skin weights follow the SMPL convention of :mod:`torchgarment.body.kinematics`: row ``j`` of the (J, V)
weight matrix is the influence of joint ``j``'s frame, which carries the bones leaving ``j``. A body
without skin weights gets :func:`nearest_bone_weights`: every vertex follows the parent joint of its
nearest bone, with weight 1 (rigid segments; simple and exactly invertible, but with creases at joints).

Arm rule of :func:`find_arms` (the skeleton is in metres, +Y up, the body's left-right axis is X):

1. The hand tips are the leaf joints farthest from the midline (the median joint x) on the +X and the -X
   side; each must lie at least 15 % of the skeleton height from the midline.
2. The chest is their deepest common ancestor. The arm path runs from the chest to a hand tip.
3. The shoulder is the path joint after the chest whose distance from the chest along the path is closest
   to 20 % of the path's length (clavicle about 0.2, upper arm about 0.3 of chest-to-fingertip in human
   proportions; this skips clavicle joints and keeps twist joints out). The elbow is the next path joint.
   The upper-arm bone is shoulder -> elbow.

:func:`repose` rotates each upper arm about its shoulder, with the smallest rotation, so that it points
straight sideways (T-pose) or sideways and ``a_pose_angle`` below horizontal in the frontal XY plane
(A-pose); the rest of the arm follows rigidly, the rest of the body does not move.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import torch

from torchgarment.body.body import Body
from torchgarment.body.kinematics import KinematicSkeleton, joint_parents
from torchgarment.body.skeleton import Skeleton
from torchgarment.errors import InputError

__all__ = ["ArmChain", "Pose", "find_arms", "linear_blend_skinning", "nearest_bone_weights", "repose"]

#: Shoulder position along the chest-to-hand path, as a fraction of its length.
SHOULDER_FRACTION = 0.2
#: Minimal lateral distance of a hand tip from the midline, as a fraction of the skeleton height.
MIN_ARM_REACH = 0.15


class Pose(enum.Enum):
    """Canonical arm poses."""

    A = "A"  # upper arms a_pose_angle (default 45 degrees) below horizontal
    T = "T"  # upper arms horizontal


@dataclass(frozen=True)
class ArmChain:
    """One arm found by :func:`find_arms`.

    Attributes:
        side: +1 for the arm on the +X side, -1 for the -X side.
        chest: index of the joint where the two arms meet.
        shoulder: index of the shoulder joint (the upper arm leaves it).
        elbow: index of the joint at the end of the upper-arm bone.
        tip: index of the hand tip joint.
    """

    side: int
    chest: int
    shoulder: int
    elbow: int
    tip: int


def linear_blend_skinning(vertices: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """Pose vertices: ``v' = sum_j w[j, v] (A_j[:3, :3] v + A_j[:3, 3])``.

    Args:
        vertices: (V, 3) rest positions in metres.
        weights: (J, V) skin weights (columns normally sum to 1).
        transforms: (J, 4, 4) or (B, J, 4, 4) skinning transforms, e.g.
            :meth:`KinematicSkeleton.skinning_transforms`.

    Returns:
        (V, 3) or (B, V, 3) posed positions; differentiable w.r.t. all inputs.

    Raises:
        InputError: inconsistent shapes.
    """
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise InputError(f"vertices must have shape (V, 3), got {tuple(vertices.shape)}")
    if weights.ndim != 2 or weights.shape[1] != vertices.shape[0]:
        raise InputError(f"weights must have shape (J, V={vertices.shape[0]}), got {tuple(weights.shape)}")
    if transforms.ndim not in (3, 4) or tuple(transforms.shape[-3:]) != (weights.shape[0], 4, 4):
        raise InputError(
            f"transforms must have shape (J={weights.shape[0]}, 4, 4) or (B, J, 4, 4), got {tuple(transforms.shape)}"
        )
    blended = torch.einsum("jv,...jab->...vab", weights, transforms[..., :3, :])  # (..., V, 3, 4)
    return (blended[..., :3] @ vertices[..., None])[..., 0] + blended[..., 3]


def _point_segment_distance2(points: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Squared distances (P, S) from points (P, 3) to segments a->b (S, 3)."""
    ab = b - a
    ap = points[:, None, :] - a[None]
    t = ((ap * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(torch.finfo(ab.dtype).tiny)).clamp(0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    return ((points[:, None, :] - closest) ** 2).sum(-1)


def nearest_bone_weights(
    vertices: torch.Tensor, skeleton: Skeleton, parents: torch.Tensor | None = None, *, chunk: int = 65536
) -> torch.Tensor:
    """One-hot skin weights: each vertex follows the parent joint of its nearest bone segment.

    Args:
        vertices: (V, 3) positions in metres.
        skeleton: joints (J, 3) and at least one bone.
        parents: (J,) parent indices from :func:`joint_parents` (computed when None).
        chunk: vertices processed at once (bounds memory to about chunk x bones x 3 floats).

    Returns:
        (J, V) weights of the vertices' dtype and device; columns are one-hot.

    Raises:
        InputError: the skeleton has no bones.
    """
    if parents is None:
        parents = joint_parents(skeleton)
    children = torch.nonzero(parents >= 0, as_tuple=False).flatten()
    if children.numel() == 0:
        raise InputError("cannot derive skin weights: the skeleton has no bones")
    joints = skeleton.joints.detach().to(dtype=vertices.dtype, device=vertices.device)
    children = children.to(vertices.device)
    heads = parents.to(vertices.device)[children]
    points = vertices.detach()
    owner = torch.cat(
        [
            heads[torch.argmin(_point_segment_distance2(points[i : i + chunk], joints[heads], joints[children]), 1)]
            for i in range(0, points.shape[0], chunk)
        ]
    )
    weights = torch.zeros(skeleton.num_joints, vertices.shape[0], dtype=vertices.dtype, device=vertices.device)
    weights[owner, torch.arange(vertices.shape[0], device=vertices.device)] = 1.0
    return weights


def _ancestors(parents: list[int], j: int) -> list[int]:
    out = [j]
    while parents[out[-1]] >= 0:
        out.append(parents[out[-1]])
    return out


def find_arms(skeleton: Skeleton, parents: torch.Tensor | None = None) -> tuple[ArmChain, ArmChain]:
    """Find the two arms of a humanoid skeleton with the rule in the module docstring.

    Args:
        skeleton: joints (J, 3) in metres, +Y up, X left-right.
        parents: (J,) parent indices (computed when None).

    Returns:
        The arms on the +X side and on the -X side.

    Raises:
        InputError: no joint reaches far enough sideways on one side, the two hands are in different trees,
            or an arm has no shoulder joint of its own.
    """
    if parents is None:
        parents = joint_parents(skeleton)
    joints = skeleton.joints.detach().cpu().double()
    plist = parents.tolist()
    is_leaf = torch.ones(len(plist), dtype=torch.bool)
    is_leaf[parents[parents >= 0]] = False
    height = float(joints[:, 1].max() - joints[:, 1].min())
    lateral = joints[:, 0] - joints[:, 0].median()
    tips = []
    for side in (1, -1):
        reach = torch.where(is_leaf, side * lateral, torch.full_like(lateral, -math.inf))
        tip = int(torch.argmax(reach))
        if not float(reach[tip]) >= MIN_ARM_REACH * height:
            raise InputError(
                f"cannot find the {'+X' if side > 0 else '-X'} arm: no end joint lies {MIN_ARM_REACH:.0%} of the "
                f"skeleton height ({height:.3f} m) sideways from the midline"
            )
        tips.append(tip)
    up = [_ancestors(plist, t) for t in tips]
    common = [j for j in up[0] if j in set(up[1])]
    if not common:
        raise InputError("cannot find the arms: the two hand tips are in different skeleton trees")
    chest = common[0]
    arms = []
    for side, tip, path_up in zip((1, -1), tips, up):
        path = path_up[: path_up.index(chest) + 1][::-1]  # chest ... tip
        seg = torch.linalg.vector_norm(joints[path[1:]] - joints[path[:-1]], dim=1)
        along = torch.cat([torch.zeros(1, dtype=seg.dtype), torch.cumsum(seg, 0)])
        if len(path) < 3:
            raise InputError(
                f"the {'+X' if side > 0 else '-X'} arm leaves the chest joint {chest} directly; the skeleton needs a "
                "shoulder joint per arm to pose the arms"
            )
        k = 1 + int(torch.argmin((along[1:-1] - SHOULDER_FRACTION * along[-1]).abs()))
        arms.append(ArmChain(side=side, chest=chest, shoulder=path[k], elbow=path[k + 1], tip=tip))
    return arms[0], arms[1]


def _rotation_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Axis-angle (3,) of the smallest rotation taking direction ``a`` to direction ``b`` (float64)."""
    a = a / torch.linalg.vector_norm(a)
    b = b / torch.linalg.vector_norm(b)
    axis = torch.linalg.cross(a, b)
    sin, cos = torch.linalg.vector_norm(axis), torch.dot(a, b)
    angle = torch.atan2(sin, cos)
    if sin < 1e-12:
        if cos > 0:
            return torch.zeros(3, dtype=a.dtype)
        axis = torch.tensor([0.0, 0.0, 1.0], dtype=a.dtype)  # opposite: turn in the frontal plane
        axis = axis - torch.dot(axis, a) * a
        return axis / torch.linalg.vector_norm(axis) * math.pi
    return axis / sin * angle


def repose(body: Body, target: Pose, *, a_pose_angle: float = math.radians(45.0)) -> Body:
    """Move the arms of a rigged body into the A-pose or the T-pose.

    The upper arms are found with :func:`find_arms`; the rotation at each shoulder is the smallest one
    taking the current upper-arm direction to the target direction (see the module docstring). Vertices
    are posed by linear blend skinning (the body's skin weights, or :func:`nearest_bone_weights`),
    joints and landmarks by the same transforms (landmarks follow their nearest bone).

    Args:
        body: body with a skeleton, in metres, +Y up, X left-right.
        target: :attr:`Pose.A` or :attr:`Pose.T`.
        a_pose_angle: angle of the upper arms below horizontal in the A-pose, radians.

    Returns:
        A new :class:`Body`: vertices, skeleton joints and landmarks moved; faces, bones and params kept,
        ``params["pose"]`` set to the target's value; ``skin_weights`` are the weights used (derived ones
        included, so that posing back uses the same weights and A -> T -> A returns to the start).

    Raises:
        InputError: no skeleton, arms not found, or a bad target.
    """
    target = Pose(target)
    if body.skeleton is None:
        raise InputError("repose needs a body with a skeleton")
    if not (0.0 <= a_pose_angle < math.pi / 2):
        raise InputError(f"a_pose_angle must be in [0, pi/2) radians, got {a_pose_angle}")
    skeleton = body.skeleton
    kin = KinematicSkeleton(skeleton)
    arms = find_arms(skeleton, kin.parents)
    joints = skeleton.joints.detach().cpu().double()
    rotations = torch.zeros(skeleton.num_joints, 3, dtype=torch.float64)
    drop = 0.0 if target is Pose.T else a_pose_angle
    for arm in arms:
        direction = joints[arm.elbow] - joints[arm.shoulder]
        goal = torch.tensor([arm.side * math.cos(drop), -math.sin(drop), 0.0], dtype=torch.float64)
        rotations[arm.shoulder] = _rotation_between(direction, goal)
    dtype, device = body.dtype, body.device
    rotations = rotations.to(dtype=dtype, device=device)
    transforms = kin.skinning_transforms(rotations)
    weights = body.skin_weights
    if weights is None:
        weights = nearest_bone_weights(body.vertices, skeleton, kin.parents)
    vertices = linear_blend_skinning(body.vertices, weights.to(dtype=dtype, device=device), transforms)
    posed = kin.posed_joints(rotations)
    landmarks = {}
    if body.landmarks:
        names = list(body.landmarks)
        points = torch.stack([body.landmarks[n].to(dtype=dtype, device=device) for n in names])
        moved = linear_blend_skinning(points, nearest_bone_weights(points, skeleton, kin.parents), transforms)
        landmarks = dict(zip(names, moved.unbind(0)))
    return Body(
        vertices=vertices,
        faces=body.faces,
        skeleton=Skeleton(
            joints=posed.to(dtype=skeleton.joints.dtype), bones=skeleton.bones, names=list(skeleton.names)
        ),
        skin_weights=weights,
        landmarks=landmarks,
        params={**body.params, "pose": target.value},
    )
