"""Tests of the pytorch-kinematics forward kinematics of skeletons against a direct torch implementation."""

from __future__ import annotations

import math

import pytest
import torch

from torchgarment.body.kinematics import (
    KinematicSkeleton,
    RotationFormat,
    axis_angle_to_matrix,
    euler_xyz_to_matrix,
    joint_parents,
    matrix_to_euler_xyz,
    skeleton_to_urdf,
)
from torchgarment.body.skeleton import Skeleton
from torchgarment.errors import InputError

JOINTS = torch.tensor(
    [[0, 1, 0], [0, 1.3, 0.02], [0.2, 1.4, 0], [0.5, 1.3, 0.01], [-0.2, 1.4, 0], [0.1, 0.9, 0],
     [0.1, 0.5, 0.03],
     [1.0, 1.0, 1.0], [1.0, 1.2, 1.0]],
    dtype=torch.float64,
)
BONES = torch.tensor([[0, 1], [1, 2], [2, 3], [1, 4], [0, 5], [5, 6], [7, 8]])  # two trees: a forest


def direct_fk(joints: torch.Tensor, parents: torch.Tensor, rotations: torch.Tensor) -> torch.Tensor:
    """Reference FK: G_j = G_parent @ [[R_j, t_j - t_parent], [0, 1]] (loop in topological order)."""
    r = axis_angle_to_matrix(rotations)
    out: list[torch.Tensor | None] = [None] * joints.shape[0]
    order = sorted(range(joints.shape[0]), key=lambda j: _depth(parents, j))
    for j in order:
        p = int(parents[j])
        local = torch.eye(4, dtype=rotations.dtype)
        local[:3, :3] = r[j]
        local[:3, 3] = joints[j] - (joints[p] if p >= 0 else 0)
        out[j] = local if p < 0 else out[p] @ local
    return torch.stack(out)


def _depth(parents, j):
    d = 0
    while parents[j] >= 0:
        j, d = int(parents[j]), d + 1
    return d


@pytest.fixture(scope="module")
def kin() -> KinematicSkeleton:
    return KinematicSkeleton(Skeleton(JOINTS, BONES))


def test_parents_and_urdf(kin):
    assert kin.parents.tolist() == [-1, 0, 1, 2, 1, 0, 5, -1, 7]
    assert kin.urdf.count("<joint ") == 3 * 9 and 'type="continuous"' in kin.urdf
    assert kin.chain(torch.float64, torch.device("cpu")).n_joints == 27


def test_identity_pose_is_exact(kin):
    g = kin.forward_kinematics(torch.zeros(9, 3, dtype=torch.float64))
    assert torch.equal(g[:, :3, :3], torch.eye(3, dtype=torch.float64).expand(9, 3, 3))
    assert (g[:, :3, 3] - JOINTS).abs().max() < 1e-15
    a = kin.skinning_transforms(torch.zeros(9, 3, dtype=torch.float64))
    assert (a - torch.eye(4, dtype=torch.float64)).abs().max() < 1e-15


def test_matches_direct_fk_batched(kin):
    torch.manual_seed(0)
    rot = torch.randn(5, 9, 3, dtype=torch.float64)
    g = kin.forward_kinematics(rot)
    assert g.shape == (5, 9, 4, 4)
    for b in range(5):
        assert (g[b] - direct_fk(JOINTS, kin.parents, rot[b])).abs().max() < 1e-13
    mats = kin.forward_kinematics(axis_angle_to_matrix(rot), rotation_format=RotationFormat.MATRIX)
    assert (mats - g).abs().max() < 1e-13


def test_gimbal_lock_rotation(kin):
    rot = torch.zeros(9, 3, dtype=torch.float64)
    rot[1] = torch.tensor([0.0, math.pi / 2, 0.0])  # Euler middle angle exactly 90 degrees
    rot[2] = torch.tensor([0.3, -math.pi / 2, 0.0])
    assert (kin.forward_kinematics(rot) - direct_fk(JOINTS, kin.parents, rot)).abs().max() < 1e-7


def test_float32(kin):
    rot = torch.randn(9, 3, dtype=torch.float64)
    g32 = kin.forward_kinematics(rot.float())
    assert g32.dtype == torch.float32
    assert (g32.double() - direct_fk(JOINTS, kin.parents, rot)).abs().max() < 1e-5


def test_gradcheck(kin):
    rot = (0.5 * torch.randn(2, 9, 3, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda r: kin.skinning_transforms(r), (rot,), fast_mode=True)
    # full Jacobian on a small output: posed positions of two joints
    one = (0.5 * torch.randn(9, 3, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda r: kin.posed_joints(r)[[3, 6]], (one,))


def test_rotation_conversions_round_trip_and_gradcheck():
    torch.manual_seed(1)
    angles = torch.rand(200, 3, dtype=torch.float64) * 2 * math.pi - math.pi
    angles[:20, 1] = math.pi / 2
    angles[20:40, 1] = -math.pi / 2
    r = euler_xyz_to_matrix(angles)
    assert (euler_xyz_to_matrix(matrix_to_euler_xyz(r)) - r).abs().max() < 1e-12
    aa = torch.randn(100, 3, dtype=torch.float64)
    aa[:5] *= 1e-5
    aa[5] = 0
    m = axis_angle_to_matrix(aa)
    assert (m @ m.transpose(1, 2) - torch.eye(3, dtype=torch.float64)).abs().max() < 1e-14
    assert torch.allclose(torch.linalg.det(m), torch.ones(100, dtype=torch.float64))
    x = torch.randn(4, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(axis_angle_to_matrix, (x,))
    assert torch.autograd.gradcheck(axis_angle_to_matrix,
                                    (torch.zeros(1, 3, dtype=torch.float64, requires_grad=True),))
    assert torch.autograd.gradcheck(lambda z: matrix_to_euler_xyz(axis_angle_to_matrix(z)), (x,))


def test_reroots_undirected_trees():
    # bones written child -> parent for the leg (joint 5 has two "parents"): re-rooted at the centre joint
    bones = torch.tensor([[0, 1], [1, 2], [2, 3], [1, 4], [0, 5], [6, 5]])
    parents = joint_parents(Skeleton(JOINTS[:7], bones))
    assert (parents < 0).sum() == 1
    root = int(torch.nonzero(parents < 0))
    centre = JOINTS[:7].mean(0)
    assert root == int(torch.argmin((JOINTS[:7] - centre).norm(dim=1)))
    assert parents[6] == 5 or parents[5] == 6  # the leg stays connected


@pytest.mark.parametrize(
    "bones, match",
    [
        (torch.tensor([[0, 1], [1, 2], [2, 0]]), "cycle"),
        (torch.tensor([[0, 1], [0, 1]]), "cycle"),
        (torch.tensor([[0, 0]]), "itself"),
        (torch.tensor([[0, 9]]), "outside"),
        (torch.tensor([0, 1]), r"\(B, 2\)"),
        (torch.tensor([[0.0, 1.0]]), "integer"),
    ],
)
def test_bad_bone_graphs(bones, match):
    with pytest.raises(InputError, match=match):
        KinematicSkeleton(Skeleton(JOINTS[:3], bones))


def test_bad_rotations(kin):
    with pytest.raises(InputError, match="axis-angle"):
        kin.forward_kinematics(torch.zeros(8, 3, dtype=torch.float64))
    with pytest.raises(InputError, match="matrices"):
        kin.forward_kinematics(torch.zeros(9, 3, dtype=torch.float64), rotation_format=RotationFormat.MATRIX)
    with pytest.raises(InputError, match="floating"):
        kin.forward_kinematics(torch.zeros(9, 3, dtype=torch.long))
    with pytest.raises(InputError, match="finite"):
        joint_parents(Skeleton(JOINTS * float("nan"), BONES))


def test_urdf_is_loadable_by_pytorch_kinematics():
    import pytorch_kinematics as pk

    chain = pk.build_chain_from_urdf(skeleton_to_urdf(Skeleton(JOINTS, BONES)))
    fk = chain.forward_kinematics(torch.zeros(1, 27))
    assert torch.allclose(fk["joint3"].get_matrix()[0, :3, 3].double(), JOINTS[3], atol=1e-6)


def test_chain_cache_per_topology_keeps_offsets_apart(kin):
    import time

    from torchgarment.body import kinematics

    torch.manual_seed(1)
    other_joints = JOINTS + 0.1 * torch.randn_like(JOINTS) + 1e-9  # not float32-representable
    start = time.perf_counter()
    other = KinematicSkeleton(Skeleton(other_joints, BONES))
    assert time.perf_counter() - start < 1.0
    assert tuple(other.parents.tolist()) in kinematics._CHAIN_TEMPLATES
    rot = torch.randn(9, 3, dtype=torch.float64)
    assert (other.forward_kinematics(rot) - direct_fk(other_joints, other.parents, rot)).abs().max() < 1e-13
    assert (kin.forward_kinematics(rot) - direct_fk(JOINTS, kin.parents, rot)).abs().max() < 1e-13
    assert (other.posed_joints(torch.zeros(9, 3, dtype=torch.float64)) - other_joints).abs().max() < 1e-15
    # A copied template does not share state: the cached chain still has the first skeleton's offsets.
    first = KinematicSkeleton(Skeleton(JOINTS, BONES))
    assert (first.posed_joints(torch.zeros(9, 3, dtype=torch.float64)) - JOINTS).abs().max() < 1e-15
