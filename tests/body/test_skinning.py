"""Tests of linear blend skinning, nearest-bone weights, arm finding and A/T re-posing."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from torchgarment.body import skinning
from torchgarment.body.body import Body
from torchgarment.body.kinematics import KinematicSkeleton
from torchgarment.body.skeleton import Skeleton
from torchgarment.body.skinning import (
    Pose,
    arm_angles,
    find_arms,
    inverse_linear_blend_skinning,
    linear_blend_skinning,
    nearest_bone_weights,
    repose,
)
from torchgarment.errors import InputError

BONES = [(0, 1), (1, 2), (1, 3), (3, 4), (4, 5), (1, 6), (6, 7), (7, 8), (0, 9), (9, 10), (10, 11), (0, 12),
         (12, 13), (13, 14)]


def stick_joints(arm_drop_deg: float = 45.0) -> torch.Tensor:
    """Joints of a 1.7 m stick figure (+Y up, X sideways) with upper arms ``arm_drop_deg`` below
    horizontal."""
    c, s = math.cos(math.radians(arm_drop_deg)), math.sin(math.radians(arm_drop_deg))
    j = [[0, 1.0, 0], [0, 1.4, 0], [0, 1.7, 0]]
    for side in (1, -1):
        sh = np.array([0.18 * side, 1.45, 0.0])
        el = sh + 0.30 * np.array([side * c, -s, 0.0])
        wr = el + 0.25 * np.array([side * c, -s, 0.0])
        j += [sh.tolist(), el.tolist(), wr.tolist()]
    for side in (1, -1):
        j += [[0.1 * side, 0.95, 0], [0.1 * side, 0.5, 0], [0.1 * side, 0.08, 0]]
    return torch.tensor(j, dtype=torch.float64)


def stick_body(arm_drop_deg: float = 45.0) -> Body:
    """Capsules (radius 4 cm) along the bones of :func:`stick_joints`; no skin weights."""
    joints = stick_joints(arm_drop_deg)
    parts = []
    for a, b in BONES:
        pa, pb = joints[a].numpy(), joints[b].numpy()
        d = pb - pa
        length = float(np.linalg.norm(d))
        cap = trimesh.creation.capsule(height=length, radius=0.04, count=[8, 8])
        cap.apply_translation(-cap.bounds.mean(axis=0))
        transform = trimesh.geometry.align_vectors([0, 0, 1], d / length)
        transform[:3, 3] = (pa + pb) / 2
        cap.apply_transform(transform)
        parts.append(cap)
    mesh = trimesh.util.concatenate(parts)
    return Body(
        vertices=torch.tensor(mesh.vertices, dtype=torch.float64),
        faces=torch.tensor(mesh.faces, dtype=torch.long),
        skeleton=Skeleton(joints, torch.tensor(BONES), []),
    )


def test_lbs_identity_is_exact():
    body = stick_body()
    weights = torch.rand(15, body.num_vertices, dtype=torch.float64)
    weights = weights / weights.sum(0)
    transforms = torch.eye(4, dtype=torch.float64).expand(15, 4, 4)
    out = linear_blend_skinning(body.vertices, weights, transforms)
    assert torch.allclose(out, body.vertices, atol=1e-15, rtol=0)


def test_lbs_rigid_and_batched():
    v = torch.randn(50, 3, dtype=torch.float64)
    w = torch.zeros(2, 50, dtype=torch.float64)
    w[0] = 1.0
    angle = 0.7
    t = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    t[0, :3, :3] = torch.tensor([[math.cos(angle), -math.sin(angle), 0],
                                 [math.sin(angle), math.cos(angle), 0], [0, 0, 1]])
    t[0, :3, 3] = torch.tensor([1.0, 2.0, 3.0])
    out = linear_blend_skinning(v, w, t)
    expected = v @ t[0, :3, :3].T + t[0, :3, 3]
    assert torch.allclose(out, expected, atol=1e-14)
    batched = linear_blend_skinning(v, w, torch.stack([t, torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)]))
    assert batched.shape == (2, 50, 3)
    assert torch.allclose(batched[0], expected, atol=1e-14) and torch.allclose(batched[1], v, atol=1e-15)


def test_lbs_gradcheck():
    v = torch.randn(6, 3, dtype=torch.float64, requires_grad=True)
    w = torch.rand(3, 6, dtype=torch.float64, requires_grad=True)
    t = torch.randn(3, 4, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(linear_blend_skinning, (v, w, t))


def test_lbs_bad_shapes():
    v = torch.zeros(5, 3, dtype=torch.float64)
    with pytest.raises(InputError, match="weights"):
        linear_blend_skinning(v, torch.zeros(2, 4, dtype=torch.float64), torch.eye(4).repeat(2, 1, 1))
    with pytest.raises(InputError, match="transforms"):
        linear_blend_skinning(v, torch.zeros(2, 5, dtype=torch.float64), torch.eye(4).repeat(3, 1, 1))
    with pytest.raises(InputError, match="vertices"):
        linear_blend_skinning(torch.zeros(5, 2), torch.zeros(2, 5), torch.eye(4).repeat(2, 1, 1))


def test_nearest_bone_weights_one_hot_and_owner():
    body = stick_body()
    w = nearest_bone_weights(body.vertices, body.skeleton)
    assert w.shape == (15, body.num_vertices)
    assert torch.equal(w.sum(0), torch.ones(body.num_vertices, dtype=torch.float64))
    # A point right next to the middle of the left forearm (bone 4->5) follows the elbow joint 4.
    j = body.skeleton.joints
    probe = ((j[4] + j[5]) / 2 + torch.tensor([0.0, 0.0, 0.03], dtype=torch.float64))[None]
    assert int(torch.argmax(nearest_bone_weights(probe, body.skeleton)[:, 0])) == 4
    # Leaves (wrists, head, ankles) own no vertex.
    assert w[[2, 5, 8, 11, 14]].sum() == 0


def test_find_arms_rule():
    skel = stick_body().skeleton
    plus, minus = find_arms(skel)
    assert (plus.side, plus.chest, plus.shoulder, plus.elbow, plus.tip) == (1, 1, 3, 4, 5)
    assert (minus.side, minus.chest, minus.shoulder, minus.elbow, minus.tip) == (-1, 1, 6, 7, 8)
    # With a clavicle joint in each arm, the shoulder is still found (the clavicle is skipped).
    joints = stick_joints()
    clav = torch.tensor([[0.04, 1.43, 0.0], [-0.04, 1.43, 0.0]], dtype=torch.float64)
    joints = torch.cat([joints, clav])
    bones = [b for b in BONES if b not in ((1, 3), (1, 6))] + [(1, 15), (15, 3), (1, 16), (16, 6)]
    plus, minus = find_arms(Skeleton(joints, torch.tensor(bones)))
    assert (plus.shoulder, plus.elbow, minus.shoulder, minus.elbow) == (3, 4, 6, 7)


def test_find_arms_errors():
    joints = stick_joints()
    with pytest.raises(InputError, match="arm"):  # arms folded down to the body: no lateral reach
        find_arms(Skeleton(joints * torch.tensor([0.1, 1.0, 1.0], dtype=torch.float64), torch.tensor(BONES)))
    arm_bones = ((1, 3), (3, 4), (4, 5), (1, 6), (6, 7), (7, 8))
    bones = [b for b in BONES if b not in arm_bones] + [(1, 5), (1, 8)]  # hands hang off the chest
    with pytest.raises(InputError, match="shoulder joint"):
        find_arms(Skeleton(joints, torch.tensor(bones)))


def _arm_angle_deg(skel: Skeleton, shoulder: int, elbow: int) -> float:
    d = skel.joints[elbow] - skel.joints[shoulder]
    return math.degrees(math.atan2(-float(d[1]), abs(float(d[0]))))


def test_repose_a_to_t_to_a_round_trip():
    body = stick_body(45.0)
    t_body = repose(body, Pose.T)
    assert t_body.params["pose"] == "T"
    for sh, el in ((3, 4), (6, 7)):
        assert abs(_arm_angle_deg(t_body.skeleton, sh, el)) < 1e-10
        # the whole arm is straight and horizontal, wrist included
        assert abs(float(t_body.skeleton.joints[el + 1, 1] - t_body.skeleton.joints[sh, 1])) < 1e-12
    # body parts that are not arms did not move
    for j in (0, 1, 2, 3, 6, 9, 10, 11, 12, 13, 14):
        assert torch.allclose(t_body.skeleton.joints[j], body.skeleton.joints[j], atol=1e-15, rtol=0)
    # hand vertices moved up by about the arm's drop
    moved = (t_body.vertices - body.vertices).norm(dim=1)
    assert moved.max() > 0.3
    back = repose(t_body, Pose.A)
    err_v = (back.vertices - body.vertices).abs().max().item()
    err_j = (back.skeleton.joints - body.skeleton.joints).abs().max().item()
    assert err_v < 1e-12 and err_j < 1e-12, (err_v, err_j)


def test_repose_a_to_a_is_identity_and_angle():
    body = stick_body(45.0)
    same = repose(body, Pose.A)
    assert (same.vertices - body.vertices).abs().max() < 1e-12
    steep = repose(body, Pose.A, a_pose_angle=math.radians(60))
    assert abs(_arm_angle_deg(steep.skeleton, 3, 4) - 60.0) < 1e-9
    assert abs(_arm_angle_deg(steep.skeleton, 6, 7) - 60.0) < 1e-9


def test_repose_uses_given_skin_weights_and_moves_landmarks():
    body = stick_body(30.0)
    body.skin_weights = nearest_bone_weights(body.vertices, body.skeleton)
    wrist = body.skeleton.joints[5] + torch.tensor([0.0, 0.0, 0.01], dtype=torch.float64)
    body.landmarks = {"left_wrist": wrist, "navel": torch.tensor([0.0, 1.1, 0.1], dtype=torch.float64)}
    t_body = repose(body, Pose.T)
    assert torch.allclose(t_body.landmarks["left_wrist"],
                          t_body.skeleton.joints[5] + torch.tensor([0, 0, 0.01], dtype=torch.float64),
                          atol=1e-12)
    assert torch.allclose(t_body.landmarks["navel"], body.landmarks["navel"], atol=1e-15, rtol=0)
    assert t_body.skin_weights is body.skin_weights
    assert repose(stick_body(), Pose.T).skin_weights.shape == (15, body.num_vertices)  # derived weights kept


def test_repose_errors():
    body = stick_body()
    with pytest.raises(InputError, match="skeleton"):
        repose(Body(body.vertices, body.faces), Pose.T)
    with pytest.raises(ValueError):
        repose(body, "X")
    with pytest.raises(InputError, match="a_pose_angle"):
        repose(body, Pose.A, a_pose_angle=2.0)


def test_single_bone_rotation_moves_only_its_subtree():
    body = stick_body()
    kin = KinematicSkeleton(body.skeleton)
    weights = nearest_bone_weights(body.vertices, body.skeleton)
    rot = torch.zeros(15, 3, dtype=torch.float64)
    rot[9] = torch.tensor([0.5, 0.0, 0.2], dtype=torch.float64)  # left hip: moves joints 10, 11
    transforms = kin.skinning_transforms(rot)
    posed = linear_blend_skinning(body.vertices, weights, transforms)
    joints = kin.posed_joints(rot)
    subtree = [10, 11]
    others = [j for j in range(15) if j not in subtree]
    assert torch.allclose(joints[others], body.skeleton.joints[others], atol=1e-15, rtol=0)
    assert (joints[subtree] - body.skeleton.joints[subtree]).norm(dim=1).min() > 0.1
    follows_hip = weights[9] > 0  # thigh vertices (owned by joint 9); the shin follows joint 10, child of 9
    in_subtree = weights[[9, 10, 11]].sum(0) > 0
    assert (posed[~in_subtree] - body.vertices[~in_subtree]).abs().max() < 1e-14
    assert (posed[follows_hip] - body.vertices[follows_hip]).norm(dim=1).max() > 0.05
    # distances to the hip joint are preserved (rigid rotation about the hip)
    hip = body.skeleton.joints[9]
    assert torch.allclose((posed[in_subtree] - hip).norm(dim=1),
                          (body.vertices[in_subtree] - hip).norm(dim=1), atol=1e-12)


# ----------------------------------------------------------------------------------------------------------
# Real rig: an anny body (104 joints, smooth LBS weights); size "6" is fitted once and then disk-cached.
# ----------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def anny():
    return Body.from_size("6")


@pytest.fixture(scope="module")
def anny_t(anny):
    return repose(anny, Pose.T)


def _arm_subtree(skel: Skeleton, arms) -> list[int]:
    parents = KinematicSkeleton(skel).parents.tolist()
    out = []
    for j in range(len(parents)):
        k = j
        while k >= 0 and k not in (arms[0].shoulder, arms[1].shoulder):
            k = parents[k]
        if k >= 0:
            out.append(j)
    return out


def test_find_arms_on_anny_picks_ball_joints(anny):
    names = anny.skeleton.names
    for arm, s in zip(find_arms(anny.skeleton), "LR"):
        assert names[arm.chest] == "spine01"
        assert [names[arm.shoulder], names[arm.elbow], names[arm.wrist]] == [f"upperarm01.{s}",
                                                                             f"lowerarm01.{s}", f"wrist.{s}"]
    # The geometric rule alone (no names) finds the same joints.
    unnamed = Skeleton(anny.skeleton.joints, anny.skeleton.bones, [])
    assert find_arms(unnamed) == find_arms(anny.skeleton)


def test_find_arms_name_hint_and_pattern():
    # A wide clavicle (9 % of the height sideways) passes the lateral rule; the upper-arm name wins over it.
    joints = torch.cat([stick_joints(),
                        torch.tensor([[0.15, 1.43, 0.0], [-0.15, 1.43, 0.0]], dtype=torch.float64)])
    bones = [b for b in BONES if b not in ((1, 3), (1, 6))] + [(1, 15), (15, 3), (1, 16), (16, 6)]
    geometric = find_arms(Skeleton(joints, torch.tensor(bones)))
    assert (geometric[0].shoulder, geometric[1].shoulder) == (15, 16)
    names = [f"j{i}" for i in range(17)]
    names[3], names[6] = "mixamorig:LeftArm", "mixamorig:RightArm"
    names[15], names[16] = "LeftShoulder", "RightShoulder"
    named = find_arms(Skeleton(joints, torch.tensor(bones), names))
    assert (named[0].shoulder, named[0].elbow, named[1].shoulder, named[1].elbow) == (3, 4, 6, 7)
    pattern = skinning._UPPER_ARM_NAME
    for good in ("upperarm01.L", "mixamorig:LeftArm", "RightArm", "l_upperarm", "Humerus_R", "arm_l"):
        assert pattern.search(good), good
    for bad in ("LeftForeArm", "lowerarm01.L", "LeftShoulder", "shoulder01.L", "left_shoulder", "forearm_r",
                "armature"):
        assert not pattern.search(bad), bad


def test_anny_t_pose_arms_straight_in_coronal_plane(anny, anny_t):
    joints = anny_t.skeleton.joints
    for arm in find_arms(anny_t.skeleton):
        for j in (arm.elbow, arm.wrist):
            assert abs(float(joints[j, 1] - joints[arm.shoulder, 1])) < 0.015
            assert abs(float(joints[j, 2] - joints[arm.shoulder, 2])) < 0.015
        assert arm.side * float(joints[arm.wrist, 0] - joints[arm.shoulder, 0]) > 0.4  # reaches out sideways
    assert all(abs(a) < 1e-9 for a in arm_angles(anny_t))
    assert anny_t.params["pose"] == "T" and anny_t.skin_weights is anny.skin_weights
    # The rest pose is an A-pose a few degrees steeper than 45 (so a 45-degree A-pose also moves the arms).
    assert all(math.radians(40) < a < math.radians(55) for a in arm_angles(anny))


def test_anny_a_pose_angle_and_path_independence(anny, anny_t):
    a_from_t = repose(anny_t, Pose.A)
    for angle in arm_angles(a_from_t):
        assert abs(math.degrees(angle) - 45.0) < 1.0
    a_direct = repose(anny, Pose.A)
    assert (a_from_t.vertices - a_direct.vertices).abs().max() < 1e-9
    custom = repose(anny_t, (math.radians(30), math.radians(60)))
    left, right = arm_angles(custom)
    assert abs(math.degrees(left) - 30) < 1e-6 and abs(math.degrees(right) - 60) < 1e-6
    assert custom.params["pose"] == "custom"


def test_anny_round_trip_to_rest_and_torso_fixed(anny, anny_t):
    back = repose(anny_t, Pose.REST)
    err = (back.vertices - anny.vertices).norm(dim=1).max().item()
    assert err < 2e-3 and err < 1e-9, err  # exact up to round-off
    assert (back.skeleton.joints - anny.skeleton.joints).abs().max() < 1e-9
    assert skinning.ROTATIONS_KEY not in back.params and back.params["pose"] == "rest"
    moved = (anny_t.vertices - anny.vertices).norm(dim=1)
    arm_weight = anny.skin_weights[_arm_subtree(anny.skeleton, find_arms(anny.skeleton))].sum(0)
    torso = arm_weight == 0
    assert torso.sum() > anny.num_vertices // 2
    assert moved[torso].max() < 1e-12
    assert moved[arm_weight > 0.99].min() > 0.005 and moved.max() > 0.3


def test_anny_keep_elbows_and_naive_inverse_is_worse(anny, anny_t):
    bent = repose(anny_t, arm_angles(anny), straighten_elbows=False)
    # Same upper-arm angles as the rest pose, rest elbow flexion: only the removed upper-arm swing differs.
    assert max(abs(a - b) for a, b in zip(arm_angles(bent), arm_angles(anny))) < 1e-9
    assert (bent.vertices - anny.vertices).norm(dim=1).max() < 0.03
    # Skinning the T-pose with the inverse rotations does not undo the T-pose where weights blend joints.
    kin = KinematicSkeleton(anny.skeleton)
    rotations = skinning.joint_rotations(anny_t)
    transforms = kin.skinning_transforms(rotations)
    weights = anny.skin_weights
    posed = linear_blend_skinning(anny.vertices, weights, transforms)
    assert (posed - anny_t.vertices).abs().max() < 1e-12
    exact = inverse_linear_blend_skinning(posed, weights, transforms)
    naive = linear_blend_skinning(posed, weights,
                                  KinematicSkeleton(anny_t.skeleton).skinning_transforms(-rotations))
    assert (exact - anny.vertices).norm(dim=1).max() < 1e-10
    assert (naive - anny.vertices).norm(dim=1).max() > 5e-3


def test_inverse_lbs_gradcheck_and_errors():
    torch.manual_seed(0)
    v = torch.randn(5, 3, dtype=torch.float64, requires_grad=True)
    w = torch.rand(3, 5, dtype=torch.float64)
    w = (w / w.sum(0)).requires_grad_(True)
    t = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1) + 0.1 * torch.randn(3, 4, 4, dtype=torch.float64)
    t.requires_grad_(True)
    assert torch.autograd.gradcheck(inverse_linear_blend_skinning, (v, w, t))
    posed = linear_blend_skinning(v, w, t)
    assert torch.allclose(inverse_linear_blend_skinning(posed, w, t), v, atol=1e-12)
    with pytest.raises(InputError, match="singular"):
        inverse_linear_blend_skinning(v, torch.zeros(3, 5, dtype=torch.float64), t)
    with pytest.raises(InputError, match="transforms"):
        inverse_linear_blend_skinning(v, w, t[:2])


def test_repose_targets_and_params_errors():
    body = stick_body(45.0)
    for bad in (math.pi / 2, (0.1, 2.0), "X", (0.1,)):
        with pytest.raises((InputError, ValueError)):
            repose(body, bad)
    broken = Body(body.vertices, body.faces, body.skeleton,
                  params={skinning.ROTATIONS_KEY: {"99": [0, 0, 1]}})
    with pytest.raises(InputError, match="malformed"):
        repose(broken, Pose.T)
    t_body = repose(body, Pose.T)
    assert set(t_body.params[skinning.ROTATIONS_KEY]) == {"3", "6"}  # shoulders only: the arms are straight
    t_body.skin_weights = None
    with pytest.raises(InputError, match="skin_weights"):
        repose(t_body, Pose.A)
