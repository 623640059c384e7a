"""Tests of linear blend skinning, nearest-bone weights, arm finding and A/T re-posing."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from torchgarment.body.body import Body
from torchgarment.body.kinematics import KinematicSkeleton
from torchgarment.body.skeleton import Skeleton
from torchgarment.body.skinning import (
    Pose,
    find_arms,
    linear_blend_skinning,
    nearest_bone_weights,
    repose,
)
from torchgarment.errors import InputError

BONES = [(0, 1), (1, 2), (1, 3), (3, 4), (4, 5), (1, 6), (6, 7), (7, 8), (0, 9), (9, 10), (10, 11), (0, 12), (12, 13), (13, 14)]


def stick_joints(arm_drop_deg: float = 45.0) -> torch.Tensor:
    """Joints of a 1.7 m stick figure (+Y up, X sideways) with upper arms ``arm_drop_deg`` below horizontal."""
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
    t[0, :3, :3] = torch.tensor([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0], [0, 0, 1]])
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
    assert torch.allclose(t_body.landmarks["left_wrist"], t_body.skeleton.joints[5] + torch.tensor([0, 0, 0.01], dtype=torch.float64), atol=1e-12)
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
    assert torch.allclose((posed[in_subtree] - hip).norm(dim=1), (body.vertices[in_subtree] - hip).norm(dim=1), atol=1e-12)
