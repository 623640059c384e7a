"""Linear blend skinning and re-posing a body's arms (A-pose, T-pose, any angle, back to rest).

Skin weights follow the SMPL convention of :mod:`torchgarment.body.kinematics`: row ``j`` of the (J, V)
weight matrix is the influence of joint ``j``'s frame, which carries the bones leaving ``j``. A body
without skin weights gets :func:`nearest_bone_weights`: every vertex follows the parent joint of its
nearest bone, with weight 1 (rigid segments; simple, but with creases at joints).

Arm rule of :func:`find_arms` (the skeleton is in metres, +Y up, the body's left-right axis is X, its left
is +X; ``H`` is the skeleton's height, the y extent of its joints):

1. The arm tips are the leaf joints farthest from the midline (the median joint x) on the +X and the -X
   side; each must lie at least ``MIN_ARM_REACH`` = 15 % of ``H`` from the midline.
2. The chest is their deepest common ancestor. The arm path runs from the chest to a tip.
3. Shoulder (the ball joint the upper arm turns about): the first path joint after the chest that lies at
   least ``SHOULDER_LATERAL`` = 8.5 % of ``H`` sideways from the chest. Clavicle joints lie closer to the
   midline (anny ``clavicle``/``shoulder01`` 2-6 %, Mixamo ``LeftShoulder``, SMPL ``left_collar`` about
   4-5 %), the glenohumeral joint at the edge of the torso (anny ``upperarm01``, Mixamo ``LeftArm``, SMPL
   ``left_shoulder``: 10-12 %). Secondary aid: when joint names are given and a path joint named like an
   upper arm (``upperarm``, ``upper_arm``, ``humerus``, ``LeftArm``/``RightArm``, ``arm_l``) lies 6-16 % of
   ``H`` sideways, the first such joint is taken instead.
4. Wrist: the first path joint after the shoulder with more than one child (the hand branches into
   fingers); the tip when the arm does not branch.
5. Elbow: the path joint strictly between shoulder and wrist whose distance along the path from the
   shoulder is closest to ``ELBOW_FRACTION`` = 53 % of the shoulder-to-wrist path length (the upper arm is
   51-55 % of it in anny, SMPL and Mixamo); twist joints (anny ``upperarm02``, ``lowerarm02``) are skipped.

Posing (:func:`repose`). Every body has a *rest pose*: the pose it was built or loaded in, in which its
skin weights are defined. The rotations applied so far are stored, relative to the rest pose, in
``params["joint_rotations"]`` (joint index -> local axis-angle, SMPL convention). Each call recovers the
rest-pose vertices exactly (per-vertex inverse of the blended transform,
:func:`inverse_linear_blend_skinning`) and poses them with the new rotations, so the result depends only on
the target, never on the path (A -> T -> A equals A, A -> T -> rest returns the input to round-off). The
target rotations are computed on the rest skeleton:

* shoulder: the smallest rotation taking the rest shoulder->elbow direction to the target direction, which
  lies in the coronal plane (spanned by +Y and +-X) at the target angle below horizontal; this removes any
  forward/backward swing of the upper arm.
* elbow (``straighten_elbows=True``, the default): the smallest rotation taking the forearm (elbow->wrist)
  into line with the upper arm, so that the whole arm is straight in the coronal plane. With ``False`` the
  elbow keeps its rest flexion.

Nothing else moves: vertices without weight on the arm joints' subtrees stay where they are.
"""

from __future__ import annotations

import enum
import math
import re
from dataclasses import dataclass

import torch

from torchgarment.body.body import Body
from torchgarment.body.kinematics import KinematicSkeleton, axis_angle_to_matrix, joint_parents
from torchgarment.body.skeleton import Skeleton
from torchgarment.errors import InputError

__all__ = [
    "ArmChain",
    "ROTATIONS_KEY",
    "Pose",
    "arm_angles",
    "find_arms",
    "inverse_linear_blend_skinning",
    "joint_rotations",
    "linear_blend_skinning",
    "nearest_bone_weights",
    "repose",
]

#: Minimal lateral distance of an arm tip from the midline, as a fraction of the skeleton height.
MIN_ARM_REACH = 0.15
#: Minimal lateral distance of the shoulder (ball) joint from the chest, as a fraction of the skeleton height.
SHOULDER_LATERAL = 0.085
#: Lateral band (fraction of the skeleton height) in which a joint named like an upper arm is accepted.
NAMED_SHOULDER_BAND = (0.06, 0.16)
#: Elbow position along the shoulder-to-wrist path, as a fraction of its length.
ELBOW_FRACTION = 0.53
#: ``Body.params`` key of the rotations applied since the rest pose: {"joint index": [x, y, z]} axis-angle.
ROTATIONS_KEY = "joint_rotations"

_UPPER_ARM_NAME = re.compile(r"upper_?arm|humerus|(^|[:_.\s])((left|right|l|r)_?)?arm([._]?(l|r))?$",
                             re.IGNORECASE)


class Pose(enum.Enum):
    """Canonical arm poses."""

    A = "A"  # straight arms in the coronal plane, a_pose_angle (default 45 degrees) below horizontal
    T = "T"  # straight arms in the coronal plane, horizontal
    REST = "rest"  # the pose the body was built or loaded in (all recorded rotations undone)


@dataclass(frozen=True)
class ArmChain:
    """One arm found by :func:`find_arms`.

    Attributes:
        side: +1 for the arm on the +X side (the body's left), -1 for the -X side.
        chest: index of the joint where the two arms meet.
        shoulder: index of the shoulder ball joint (the upper arm turns about it).
        elbow: index of the elbow joint (end of the upper arm, start of the forearm).
        wrist: index of the wrist joint (end of the forearm).
        tip: index of the arm's tip joint (a finger end).
    """

    side: int
    chest: int
    shoulder: int
    elbow: int
    wrist: int
    tip: int


def linear_blend_skinning(vertices: torch.Tensor, weights: torch.Tensor,
                          transforms: torch.Tensor) -> torch.Tensor:
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
            f"transforms must have shape (J={weights.shape[0]}, 4, 4) or (B, J, 4, 4), got "
            f"{tuple(transforms.shape)}"
        )
    blended = torch.einsum("jv,...jab->...vab", weights, transforms[..., :3, :])  # (..., V, 3, 4)
    return (blended[..., :3] @ vertices[..., None])[..., 0] + blended[..., 3]


def inverse_linear_blend_skinning(
    posed: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor, *, min_det: float = 1e-6
) -> torch.Tensor:
    """Exact inverse of :func:`linear_blend_skinning`: rest positions from posed ones.

    Each vertex's blended transform ``M_v = sum_j w[j, v] A_j`` is affine, so ``v = M_v[:3, :3]^-1
    (v' - M_v[:3, 3])``. (Skinning with the inverse rotations is *not* the inverse of skinning where weights
    blend joints that turn differently; this is.)

    Args:
        posed: (V, 3) posed positions in metres.
        weights: (J, V) skin weights.
        transforms: (J, 4, 4) skinning transforms that produced ``posed``.
        min_det: smallest accepted ``|det M_v[:3, :3]|``.

    Returns:
        (V, 3) rest positions; differentiable w.r.t. all inputs.

    Raises:
        InputError: inconsistent shapes, or a (nearly) singular blended transform (weights that do not sum
            to 1, or joints blended across turns near 180 degrees).
    """
    if posed.ndim != 2 or posed.shape[1] != 3:
        raise InputError(f"posed vertices must have shape (V, 3), got {tuple(posed.shape)}")
    if weights.ndim != 2 or weights.shape[1] != posed.shape[0]:
        raise InputError(f"weights must have shape (J, V={posed.shape[0]}), got {tuple(weights.shape)}")
    if tuple(transforms.shape) != (weights.shape[0], 4, 4):
        raise InputError(f"transforms must have shape (J={weights.shape[0]}, 4, 4), got "
                         f"{tuple(transforms.shape)}")
    blended = torch.einsum("jv,jab->vab", weights, transforms[:, :3, :])  # (V, 3, 4)
    linear = blended[..., :3]
    det = torch.linalg.det(linear.detach())
    if posed.shape[0] and not bool((det.abs() >= min_det).all()):
        bad = int(torch.argmin(det.abs()))
        raise InputError(
            f"cannot unpose vertex {bad}: its blended skinning transform is singular (|det| = "
            f"{float(det[bad].abs()):.2e}); check that its skin weights sum to 1"
        )
    return torch.linalg.solve(linear, (posed - blended[..., 3])[..., None])[..., 0]


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
            heads[torch.argmin(_point_segment_distance2(points[i : i + chunk], joints[heads],
                                                        joints[children]), 1)]
            for i in range(0, points.shape[0], chunk)
        ]
    )
    weights = torch.zeros(skeleton.num_joints, vertices.shape[0], dtype=vertices.dtype,
                          device=vertices.device)
    weights[owner, torch.arange(vertices.shape[0], device=vertices.device)] = 1.0
    return weights


def _ancestors(parents: list[int], j: int) -> list[int]:
    out = [j]
    while parents[out[-1]] >= 0:
        out.append(parents[out[-1]])
    return out


def _side_name(side: int) -> str:
    return "+X" if side > 0 else "-X"


def find_arms(skeleton: Skeleton, parents: torch.Tensor | None = None) -> tuple[ArmChain, ArmChain]:
    """Find the two arms of a humanoid skeleton with the rule in the module docstring.

    Args:
        skeleton: joints (J, 3) in metres, +Y up, X left-right; ``names`` optional (used as a hint).
        parents: (J,) parent indices (computed when None).

    Returns:
        The arms on the +X side and on the -X side.

    Raises:
        InputError: no joint reaches far enough sideways on one side, the two tips are in different trees,
            or an arm has no shoulder or elbow joint of its own.
    """
    if parents is None:
        parents = joint_parents(skeleton)
    joints = skeleton.joints.detach().cpu().double()
    names = list(skeleton.names) if len(skeleton.names) == skeleton.num_joints else []
    plist = parents.tolist()
    num_children = torch.bincount(parents[parents >= 0], minlength=len(plist))
    is_leaf = num_children == 0
    height = float(joints[:, 1].max() - joints[:, 1].min())
    lateral = joints[:, 0] - joints[:, 0].median()
    tips = []
    for side in (1, -1):
        reach = torch.where(is_leaf, side * lateral, torch.full_like(lateral, -math.inf))
        tip = int(torch.argmax(reach))
        if not float(reach[tip]) >= MIN_ARM_REACH * height:
            raise InputError(
                f"cannot find the {_side_name(side)} arm: no end joint lies {MIN_ARM_REACH:.0%} of the "
                f"skeleton height ({height:.3f} m) sideways from the midline"
            )
        tips.append(tip)
    up = [_ancestors(plist, t) for t in tips]
    common = [j for j in up[0] if j in set(up[1])]
    if not common:
        raise InputError("cannot find the arms: the two arm tips are in different skeleton trees")
    chest = common[0]
    arms = []
    for side, tip, path_up in zip((1, -1), tips, up):
        path = path_up[: path_up.index(chest) + 1][::-1]  # chest ... tip
        if len(path) < 3:
            raise InputError(
                f"the {_side_name(side)} arm leaves the chest joint {chest} directly; the skeleton needs a "
                "shoulder joint per arm to pose the arms"
            )
        out = (side * (joints[path, 0] - joints[chest, 0]) / height).tolist()  # lateral offsets / H
        inner = range(1, len(path) - 1)  # neither the chest nor the tip
        named = [k for k in inner if names and _UPPER_ARM_NAME.search(names[path[k]])
                 and NAMED_SHOULDER_BAND[0] <= out[k] <= NAMED_SHOULDER_BAND[1]]
        lateral_ok = [k for k in inner if out[k] >= SHOULDER_LATERAL]
        if not (named or lateral_ok):
            raise InputError(
                f"the {_side_name(side)} arm has no shoulder joint: no joint between chest and tip lies "
                f"{SHOULDER_LATERAL:.1%} of the skeleton height sideways from the chest"
            )
        s = named[0] if named else lateral_ok[0]
        w = next((k for k in range(s + 1, len(path)) if int(num_children[path[k]]) > 1), len(path) - 1)
        if w - s < 2:
            raise InputError(
                f"the {_side_name(side)} arm has no elbow joint between its shoulder joint {path[s]} and its "
                f"wrist joint {path[w]}"
            )
        seg = torch.linalg.vector_norm(joints[path[s + 1 : w + 1]] - joints[path[s:w]], dim=1)
        along = torch.cumsum(seg, 0)  # distance from the shoulder of path[s + 1 .. w]
        e = s + 1 + int(torch.argmin((along[:-1] - ELBOW_FRACTION * along[-1]).abs()))
        arms.append(ArmChain(side=side, chest=chest, shoulder=path[s], elbow=path[e], wrist=path[w], tip=tip))
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


def _below_horizontal(direction: torch.Tensor) -> float:
    """Angle (radians) of a direction (3,) below the horizontal XZ plane."""
    return math.atan2(-float(direction[1]), math.hypot(float(direction[0]), float(direction[2])))


def arm_angles(body: Body) -> tuple[float, float]:
    """Angles of the upper arms (shoulder -> elbow, :func:`find_arms`) below horizontal.

    Args:
        body: body with a skeleton, +Y up, X left-right.

    Returns:
        (left, right): radians below the horizontal plane of the +X (left) and the -X (right) upper arm;
        0 in a T-pose, positive with the arms down, negative with the arms raised.

    Raises:
        InputError: no skeleton, or arms not found.
    """
    if body.skeleton is None:
        raise InputError("arm_angles needs a body with a skeleton")
    joints = body.skeleton.joints.detach().cpu().double()
    plus, minus = find_arms(body.skeleton)
    return tuple(_below_horizontal(joints[a.elbow] - joints[a.shoulder]) for a in (plus, minus))


def joint_rotations(body: Body) -> torch.Tensor:
    """Local rotations applied to a body since its rest pose, read from ``params[ROTATIONS_KEY]``.

    Args:
        body: a body with a skeleton.

    Returns:
        (J, 3) float64 CPU axis-angle rotations (radians), zero for joints never turned.

    Raises:
        InputError: no skeleton, or a malformed ``params[ROTATIONS_KEY]`` entry.
    """
    if body.skeleton is None:
        raise InputError("joint_rotations needs a body with a skeleton")
    rotations = torch.zeros(body.skeleton.num_joints, 3, dtype=torch.float64)
    stored = body.params.get(ROTATIONS_KEY, {})
    if not isinstance(stored, dict):
        raise InputError(
            f"params[{ROTATIONS_KEY!r}] must be a dict of joint index -> [x, y, z], got "
            f"{type(stored).__name__}"
        )
    for key, value in stored.items():
        try:
            j, vec = int(key), [float(x) for x in value]
        except (TypeError, ValueError):
            raise InputError(f"params[{ROTATIONS_KEY!r}] has a malformed entry {key!r}: {value!r}") from None
        if not (0 <= j < rotations.shape[0] and len(vec) == 3 and all(math.isfinite(x) for x in vec)):
            raise InputError(f"params[{ROTATIONS_KEY!r}] has a malformed entry {key!r}: {value!r}")
        rotations[j] = torch.tensor(vec, dtype=torch.float64)
    return rotations


def _world_rotations(rotations: torch.Tensor, parents: list[int], order: list[int]) -> torch.Tensor:
    """(J, 3, 3) world rotation of every joint frame: ``W_j = W_parent(j) @ R_j`` (float64)."""
    local = axis_angle_to_matrix(rotations)
    world = local.clone()
    for j in order:
        if parents[j] >= 0:
            world[j] = world[parents[j]] @ local[j]
    return world


def _topological_order(parents: list[int]) -> list[int]:
    depth = [len(_ancestors(parents, j)) for j in range(len(parents))]
    return sorted(range(len(parents)), key=depth.__getitem__)


def _rest_joints(posed: torch.Tensor, rotations: torch.Tensor, parents: list[int],
                 order: list[int]) -> torch.Tensor:
    """Rest joint positions (J, 3) from posed ones: ``t_j - t_p = W_p^T (g_j - g_p)`` (float64)."""
    world = _world_rotations(rotations, parents, order)
    rest = posed.clone()
    for j in order:
        p = parents[j]
        if p >= 0:
            rest[j] = rest[p] + world[p].T @ (posed[j] - posed[p])
    return rest


def _target_angles(target: Pose | float | tuple[float, float],
                   a_pose_angle: float) -> tuple[float, float] | None:
    if isinstance(target, (Pose, str)):
        pose = Pose(target)
        if pose is Pose.REST:
            return None
        if not (0.0 <= a_pose_angle < math.pi / 2):
            raise InputError(f"a_pose_angle must be in [0, pi/2) radians, got {a_pose_angle}")
        angle = 0.0 if pose is Pose.T else a_pose_angle
        return angle, angle
    if isinstance(target, (int, float)) and not isinstance(target, bool):
        angles = (float(target), float(target))
    elif isinstance(target, (tuple, list)) and len(target) == 2:
        angles = (float(target[0]), float(target[1]))
    else:
        raise InputError(f"target must be a Pose, an angle or a (left, right) pair of angles, got {target!r}")
    if not all(-math.pi / 2 < a < math.pi / 2 for a in angles):
        raise InputError(f"arm angles must be in (-pi/2, pi/2) radians below horizontal, got {angles}")
    return angles


def _pose_name(target: Pose | float | tuple[float, float]) -> str:
    return Pose(target).value if isinstance(target, (Pose, str)) else "custom"


def repose(
    body: Body,
    target: Pose | float | tuple[float, float],
    *,
    a_pose_angle: float = math.radians(45.0),
    straighten_elbows: bool = True,
) -> Body:
    """Move the arms of a rigged body into the A-pose, the T-pose, given angles, or back to its rest pose.

    See the module docstring for the rule. Vertices are posed by linear blend skinning from the exactly
    recovered rest pose with the body's skin weights (or :func:`nearest_bone_weights` of the rest pose),
    joints by forward kinematics, landmarks rigidly with their nearest bone.

    Args:
        body: body with a skeleton, in metres, +Y up, X left-right (left = +X).
        target: :attr:`Pose.A`, :attr:`Pose.T`, :attr:`Pose.REST`, one angle for both upper arms or a
            (left, right) pair, in radians below horizontal in (-pi/2, pi/2) (e.g. :func:`arm_angles`).
        a_pose_angle: angle of the upper arms below horizontal for :attr:`Pose.A`, radians in [0, pi/2).
        straighten_elbows: put the forearms in line with the upper arms (ignored for :attr:`Pose.REST`).

    Returns:
        A new :class:`Body`: vertices, skeleton joints and landmarks moved; faces, bones and other params
        kept; ``params["pose"]`` = ``"A"``, ``"T"``, ``"rest"`` or ``"custom"``; ``params[ROTATIONS_KEY]``
        the rotations relative to the rest pose (absent for the rest pose); ``skin_weights`` the weights
        used (derived ones included).

    Raises:
        InputError: no skeleton, arms not found, a bad target or angle, malformed ``params[ROTATIONS_KEY]``.
    """
    if body.skeleton is None:
        raise InputError("repose needs a body with a skeleton")
    angles = _target_angles(target, a_pose_angle)
    skeleton = body.skeleton
    dtype, device = body.dtype, body.device
    parents = joint_parents(skeleton)
    plist = parents.tolist()
    order = _topological_order(plist)
    current = joint_rotations(body)
    posed_joints = skeleton.joints.detach().cpu().double()
    rest_joints = _rest_joints(posed_joints, current, plist, order) if current.any() else posed_joints
    rest_skeleton = Skeleton(joints=rest_joints, bones=skeleton.bones, names=list(skeleton.names))
    kin = KinematicSkeleton(rest_skeleton)
    # Rest-pose vertices (exact inverse of the skinning that produced the current pose).
    weights = body.skin_weights
    current_transforms = kin.skinning_transforms(current.to(dtype=dtype, device=device))
    if weights is None:
        if current.any():
            raise InputError(f"a body with params[{ROTATIONS_KEY!r}] needs the skin_weights that posed it")
        weights = nearest_bone_weights(body.vertices, rest_skeleton, parents)
    weights = weights.to(dtype=dtype, device=device)
    if current.any():
        rest_vertices = inverse_linear_blend_skinning(body.vertices, weights, current_transforms)
    else:
        rest_vertices = body.vertices
    # Target rotations, computed on the rest skeleton.
    rotations = torch.zeros_like(current)
    if angles is not None:
        arms = find_arms(rest_skeleton, parents)
        rotations = current.clone()
        for arm in arms:
            rotations[arm.shoulder] = 0.0
            rotations[arm.elbow] = 0.0
        for arm, angle in zip(arms, angles):
            g = kin.forward_kinematics(rotations)
            goal = torch.tensor([arm.side * math.cos(angle), -math.sin(angle), 0.0], dtype=torch.float64)
            turn = _rotation_between(g[arm.elbow, :3, 3] - g[arm.shoulder, :3, 3], goal)
            parent = plist[arm.shoulder]
            parent_world = g[parent, :3, :3] if parent >= 0 else torch.eye(3, dtype=torch.float64)
            rotations[arm.shoulder] = parent_world.T @ turn
            if straighten_elbows:
                g = kin.forward_kinematics(rotations)
                turn = _rotation_between(g[arm.wrist, :3, 3] - g[arm.elbow, :3, 3], goal)
                rotations[arm.elbow] = g[plist[arm.elbow], :3, :3].T @ turn
    transforms = kin.skinning_transforms(rotations.to(dtype=dtype, device=device))
    vertices = linear_blend_skinning(rest_vertices, weights, transforms)
    joints = kin.posed_joints(rotations)
    landmarks = {}
    if body.landmarks:
        names = list(body.landmarks)
        points = torch.stack([body.landmarks[n].to(dtype=dtype, device=device) for n in names])
        owner = nearest_bone_weights(points, Skeleton(posed_joints, skeleton.bones), parents).argmax(0)
        step = transforms[owner] @ torch.linalg.inv(current_transforms[owner])  # rigid per landmark
        moved = (step[:, :3, :3] @ points[..., None])[..., 0] + step[:, :3, 3]
        landmarks = dict(zip(names, moved.unbind(0)))
    params = {k: v for k, v in body.params.items() if k != ROTATIONS_KEY}
    params["pose"] = _pose_name(target)
    nonzero = torch.nonzero(rotations.abs().amax(1) > 0).flatten().tolist()
    if nonzero:
        params[ROTATIONS_KEY] = {str(j): rotations[j].tolist() for j in nonzero}
    return Body(
        vertices=vertices,
        faces=body.faces,
        skeleton=Skeleton(
            joints=joints.to(dtype=skeleton.joints.dtype, device=skeleton.joints.device),
            bones=skeleton.bones,
            names=list(skeleton.names),
        ),
        skin_weights=weights,
        landmarks=landmarks,
        params=params,
    )
