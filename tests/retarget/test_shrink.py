"""Step 1 of retargeting: shrinking the target avatar onto the source skeleton."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np
import pytest
import torch

from torchgarment.errors import InputError
from torchgarment.retarget.avatars import make_avatar, toy_case, tube_mesh
from torchgarment.retarget.inputs import problem_from_arrays
from torchgarment.retarget.shrink import project_to_bones, shrink_avatar

if TYPE_CHECKING:
    from torchgarment.retarget.inputs import RetargetProblem
    from torchgarment.retarget.shrink import ShrunkAvatar


def _toy_problem(**kw: object) -> RetargetProblem:
    case = toy_case(**kw)
    return problem_from_arrays(
        case.garment_vertices,
        case.garment_faces,
        case.source_skeleton,
        case.target_vertices,
        case.target_faces,
        case.target_skeleton,
    ), case


def _segment_distance(points: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    d = b - a
    dd = (d * d).sum(-1)
    s = torch.where(dd > 0, ((points - a) * d).sum(-1) / torch.where(dd > 0, dd, torch.ones_like(dd)), 0 * dd)
    return (points - a - s.clamp(0, 1)[..., None] * d).norm(dim=-1)


def _assert_on_skeleton(problem: RetargetProblem, shrunk: ShrunkAvatar, scale: float) -> None:
    sk = problem.source_skeleton
    a = sk.joints[sk.bones[:, 0]]
    b = sk.joints[sk.bones[:, 1]]
    # Skeleton points: every one on its own source bone; shrunk vertices exactly `offset` away from them.
    v = shrunk.skeleton_points
    own = _segment_distance(v, a[shrunk.bone_of_vertex], b[shrunk.bone_of_vertex])
    assert float(own.max()) <= 1e-9 * scale
    assert shrunk.offset == pytest.approx(1e-4 * problem.length_scale)
    gap = (shrunk.vertices_shrunk - v).norm(dim=1)
    assert torch.allclose(gap, torch.full_like(gap, shrunk.offset), rtol=1e-9, atol=0)
    # No zero-length edges (ipctk mis-measures those).
    f = shrunk.faces
    edges = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    vs = shrunk.vertices_shrunk
    assert float((vs[edges[:, 0]] - vs[edges[:, 1]]).norm(dim=1).min()) > 0
    # Every triangle's corners on one common bone, hence the whole (degenerate) triangle on the skeleton.
    tri = v[shrunk.faces]  # (G, 3, 3)
    cand = shrunk.bone_of_vertex[shrunk.faces]  # (G, 3) candidate common bones: the corners' own bones
    d = _segment_distance(tri[:, :, None, :], a[cand][:, None], b[cand][:, None])  # (G, 3 corners, 3 cands)
    common = d.max(dim=1).values.min(dim=1).values
    rest = common > 1e-9 * scale  # e.g. three joint corners: try every bone
    if bool(rest.any()):
        full = _segment_distance(tri[rest][:, :, None, :], a[None, None], b[None, None])
        common[rest] = full.max(dim=1).values.min(dim=1).values
    assert float(common.max()) <= 1e-9 * scale
    # Sampled points of the shrunk triangles lie within the offset of the bone union.
    w = torch.tensor([[1 / 3, 1 / 3, 1 / 3], [0.6, 0.2, 0.2], [0.1, 0.1, 0.8]], dtype=v.dtype)
    pts = torch.einsum("sk,gkd->gsd", w, shrunk.vertices_shrunk[shrunk.faces]).reshape(-1, 3)
    union = project_to_bones(pts, sk.joints, sk.bones)[2]
    assert float(union.max()) <= shrunk.offset * (1 + 1e-9)


def _areas(v: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    t = v[f]
    return 0.5 * torch.linalg.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0], dim=-1).norm(dim=-1)


def test_toy_shrink_on_skeleton_and_tiles_avatar() -> None:
    problem, case = _toy_problem()
    shrunk = shrink_avatar(problem)
    a = problem.avatar_vertices.shape[0]
    assert shrunk.num_original == a and shrunk.iterations >= 1
    assert shrunk.vertices_full.shape[0] > a  # triangles across bones were subdivided
    assert torch.equal(shrunk.vertices_full[:a], problem.avatar_vertices)
    _assert_on_skeleton(problem, shrunk, 1.0)
    # The non-conforming fans tile the original triangles: same total area, same area-weighted centroid.
    a0, a1 = _areas(problem.avatar_vertices, problem.avatar_faces), _areas(shrunk.vertices_full, shrunk.faces)
    assert float(a1.sum()) == pytest.approx(float(a0.sum()), rel=1e-12)
    c0 = (problem.avatar_vertices[problem.avatar_faces].mean(1) * a0[:, None]).sum(0)
    c1 = (shrunk.vertices_full[shrunk.faces].mean(1) * a1[:, None]).sum(0)
    assert torch.allclose(c0, c1, atol=1e-12)

    # Orientation kept: the signed volume of the closed ellipsoid is unchanged.
    def volume(v: torch.Tensor, f: torch.Tensor) -> float:
        t = v[f]
        return float((t[:, 0] * torch.linalg.cross(t[:, 1], t[:, 2], dim=-1)).sum() / 6)

    assert volume(shrunk.vertices_full, shrunk.faces) == pytest.approx(
        volume(problem.avatar_vertices, problem.avatar_faces), rel=1e-12
    )
    assert 0 < shrunk.min_distance <= 0.3
    # Interpolation.
    assert torch.equal(shrunk.at(1.0), shrunk.vertices_full)
    assert torch.equal(shrunk.at(0.0), shrunk.vertices_shrunk)
    t = torch.tensor(0.25, dtype=torch.float64, requires_grad=True)
    shrunk.at(t).sum().backward()
    assert float(t.grad) == pytest.approx(float((shrunk.vertices_full - shrunk.vertices_shrunk).sum()))


def test_toy_shrink_far_away_small_target_same_shrunk_avatar() -> None:
    p1, _ = _toy_problem()
    p2, _ = _toy_problem(target_scale=0.05, target_offset=(40.0, -3.0, 9.0))
    s1, s2 = shrink_avatar(p1), shrink_avatar(p2)
    assert torch.equal(s1.faces, s2.faces)
    assert torch.allclose(s1.vertices_shrunk, s2.vertices_shrunk, atol=1e-9)
    assert torch.allclose(
        p2.to_work.inverse(s2.vertices_full[: p2.avatar_vertices.shape[0]]),
        toy_case(target_scale=0.05, target_offset=(40.0, -3.0, 9.0)).target_vertices,
    )


def test_shrunk_avatar_has_no_intersection_with_garment_ipctk() -> None:
    import ipctk

    problem, _ = _toy_problem()
    shrunk = shrink_avatar(problem)
    gv = problem.garment_vertices.numpy()
    gf = problem.garment_faces.numpy()
    v = np.asfortranarray(np.concatenate([gv, shrunk.vertices_shrunk.numpy()]))
    f = np.asfortranarray(np.concatenate([gf, shrunk.faces.numpy() + gv.shape[0]]), dtype=np.int32)
    mesh = ipctk.CollisionMesh(v, ipctk.edges(f), f)
    mesh.can_collide = ipctk.make_vertex_patches_filter(
        np.r_[np.zeros(gv.shape[0], np.int32), np.ones(shrunk.vertices_shrunk.shape[0], np.int32)]
    )
    assert not ipctk.has_intersections(mesh, v)
    col = ipctk.NormalCollisions()
    col.build(mesh, v, 0.5)
    d = np.sqrt(col.compute_minimum_distance(mesh, v))
    # The check's bound: distance to the covered bone segments minus the offset.
    assert shrunk.min_distance <= d <= shrunk.min_distance + 2 * shrunk.offset + 1e-12
    true = float(
        torch.cdist(problem.garment_vertices, shrunk.vertices_shrunk).min()
    )  # vertex-vertex upper bound
    assert d <= true + 1e-12
    # ipctk handles the degenerate (segment) triangles: finite barrier, gradient and projected Hessian.
    barrier = ipctk.BarrierPotential(0.5, 1.0, True)
    assert np.isfinite(barrier(col, mesh, v))
    assert np.isfinite(barrier.gradient(col, mesh, v)).all()
    assert np.isfinite(barrier.hessian(col, mesh, v, ipctk.PSDProjectionMethod.CLAMP).data).all()
    # And at the fully inflated avatar the garment crosses it (the toy avatar is wider than the tube).
    v1 = np.asfortranarray(np.concatenate([gv, shrunk.at(1.0).numpy()]))
    assert ipctk.has_intersections(mesh, v1)


def test_skeleton_outside_garment_raises() -> None:
    case = toy_case()
    gv, gf = tube_mesh(0.2, 0.2, -0.2, 1.6, 24, 10)  # tall narrow tube: the arm bones cross its wall
    problem = problem_from_arrays(
        gv, gf, case.source_skeleton, case.target_vertices, case.target_faces, case.target_skeleton
    )
    with pytest.raises(InputError, match=r"source skeleton is not inside the garment.*arm\.L"):
        shrink_avatar(problem)
    assert shrink_avatar(problem, check=False).vertices_shrunk.shape[0] > 0


def test_skin_weights_choose_the_bones() -> None:
    problem, case = _toy_problem()
    a = problem.avatar_vertices.shape[0]
    # Everything weighted to the hip joint: every vertex on bone 0 (hip -> spine), no subdivision.
    w = torch.zeros(5, a, dtype=torch.float64)
    w[0] = 1.0
    problem.skin_weights = w
    shrunk = shrink_avatar(problem)
    assert shrunk.vertices_full.shape[0] == a and shrunk.iterations == 0
    assert set(shrunk.bone_of_vertex.tolist()) == {0}
    # Leaf joint arm.L (3): its incoming bone 2 (chest -> arm.L).
    w = torch.zeros(5, a, dtype=torch.float64)
    w[3] = 1.0
    problem.skin_weights = w
    assert set(shrink_avatar(problem, check=False).bone_of_vertex.tolist()) == {2}


def test_project_to_bones_matches_bruteforce() -> None:
    torch.manual_seed(0)
    joints = torch.randn(6, 3, dtype=torch.float64)
    bones = torch.tensor([[0, 1], [1, 2], [1, 3], [3, 4], [4, 5]])
    pts = torch.randn(200, 3, dtype=torch.float64)
    bone, param, dist = project_to_bones(pts, joints, bones)
    brute = torch.stack([_segment_distance(pts, joints[i], joints[j]) for i, j in bones.tolist()], dim=1)
    assert torch.allclose(dist, brute.min(dim=1).values, atol=1e-12)
    proj = joints[bones[bone, 0]] + param[:, None] * (joints[bones[bone, 1]] - joints[bones[bone, 0]])
    assert torch.allclose((pts - proj).norm(dim=1), dist, atol=1e-12)


def _torso_tube(body_vertices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """An elliptic tube around the torso of an anny body, clear of the body at every height."""
    y0, y1 = 0.72, 1.22
    band = (body_vertices[:, 1] > y0) & (body_vertices[:, 1] < y1) & (body_vertices[:, 0].abs() < 0.2)
    rx = float(body_vertices[band, 0].abs().max()) + 0.03
    rz = float(body_vertices[band, 2].abs().max()) + 0.03
    return tube_mesh(rx, rz, y0, y1, 48, 16)


def test_anny_size6_to_size20() -> None:
    from torchgarment.retarget.inputs import problem_from_bodies

    src = make_avatar("anny-6").as_body()
    tgt = make_avatar("anny-20").as_body()
    gv, gf = _torso_tube(src.vertices)
    problem = problem_from_bodies(gv, gf, src, tgt, use_source_avatar=False)
    start = time.perf_counter()
    shrunk = shrink_avatar(problem)
    seconds = time.perf_counter() - start
    print(
        f"shrink_avatar on {problem.avatar_vertices.shape[0]} vertices: {seconds:.2f} s, "
        f"{shrunk.vertices_full.shape[0]} vertices, {shrunk.iterations} rounds, "
        f"min distance {shrunk.min_distance * 1e3:.1f} mm"
    )
    assert shrunk.min_distance > 0.01
    _assert_on_skeleton(problem, shrunk, problem.length_scale)
    a0 = _areas(problem.avatar_vertices, problem.avatar_faces).sum()
    assert float(_areas(shrunk.vertices_full, shrunk.faces).sum()) == pytest.approx(float(a0), rel=1e-10)


@pytest.mark.slow
@pytest.mark.parametrize(
    "name", ["long-arms", "big-head", "short-legs", "floating-parts", "torso-hole", "miniature", "giant"]
)
def test_anny_to_generated_avatars(name: str) -> None:
    from torchgarment.retarget.inputs import problem_from_bodies

    src = make_avatar("anny-6").as_body()
    gv, gf = _torso_tube(src.vertices)
    for weights in (True, False):
        problem = problem_from_bodies(
            gv, gf, src, make_avatar(name).as_body(), use_source_avatar=False, use_skin_weights=weights
        )
        shrunk = shrink_avatar(problem)
        assert shrunk.min_distance > 0.01
        _assert_on_skeleton(problem, shrunk, problem.length_scale)
