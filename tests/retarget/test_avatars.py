"""Generated test avatars for retargeting."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pytest
import torch

from torchgarment.errors import InputError
from torchgarment.retarget.avatars import list_avatars, make_avatar
from torchgarment.structures.mesh_checks import find_misoriented_edges, find_nonmanifold_edges

if TYPE_CHECKING:
    from torchgarment.body.skeleton import Skeleton
    from torchgarment.retarget.avatars import TestAvatar


@pytest.fixture(scope="module")
def avatars() -> dict[str, TestAvatar]:
    return {name: make_avatar(name) for name in list_avatars()}


def _bone_lengths(sk: Skeleton, prefixes: tuple[str, ...]) -> torch.Tensor:
    idx = [k for k, (i, _) in enumerate(sk.bones.tolist()) if sk.names[i].startswith(prefixes)]
    b = sk.bones[idx]
    return (sk.joints[b[:, 1]] - sk.joints[b[:, 0]]).norm(dim=1)


def test_shapes_and_consistent_skeletons(avatars: dict) -> None:
    ref = avatars["anny-12"].skeleton
    for name, a in avatars.items():
        v, f, sk, w = a.vertices, a.faces, a.skeleton, a.skin_weights
        assert v.ndim == 2 and v.shape[1] == 3 and v.dtype == torch.float64, name
        assert f.dtype == torch.long and int(f.min()) >= 0 and int(f.max()) < v.shape[0], name
        assert torch.equal(sk.bones, ref.bones) and sk.names == ref.names, name
        assert w.shape == (sk.num_joints, v.shape[0]), name
        assert torch.allclose(w.sum(dim=0), torch.ones(v.shape[0], dtype=w.dtype)), name
        assert torch.isfinite(v).all(), name
        assert find_nonmanifold_edges(f).numel() == 0 and find_misoriented_edges(f).numel() == 0, name


def test_edited_proportions(avatars: dict) -> None:
    base, long_arms, short_legs = avatars["anny-12"], avatars["long-arms"], avatars["short-legs"]
    ratio = _bone_lengths(long_arms.skeleton, ("upperarm", "lowerarm")) / _bone_lengths(
        base.skeleton, ("upperarm", "lowerarm")
    )
    assert torch.allclose(ratio, torch.full_like(ratio, 1.6))
    ratio = _bone_lengths(short_legs.skeleton, ("upperleg", "lowerleg")) / _bone_lengths(
        base.skeleton, ("upperleg", "lowerleg")
    )
    assert torch.allclose(ratio, torch.full_like(ratio, 0.6))
    # Hands keep their size; the arm span grows; the body gets shorter with short legs.
    hand = ("finger", "metacarpal")
    assert torch.allclose(_bone_lengths(long_arms.skeleton, hand), _bone_lengths(base.skeleton, hand))
    span = lambda a: float(a.vertices[:, 0].max() - a.vertices[:, 0].min())  # noqa: E731
    assert span(long_arms) > 1.25 * span(base)
    height = lambda a: float(a.vertices[:, 1].max() - a.vertices[:, 1].min())  # noqa: E731
    leg = float(
        base.skeleton.joints[base.skeleton.names.index("upperleg01.L"), 1]
        - base.skeleton.joints[base.skeleton.names.index("foot.L"), 1]
    )
    assert height(short_legs) == pytest.approx(height(base) - 0.4 * leg, abs=0.03)


def test_big_head(avatars: dict) -> None:
    base, big = avatars["anny-12"], avatars["big-head"]
    j = base.skeleton.names.index("head")
    y0 = float(base.skeleton.joints[j, 1])
    assert float(big.skeleton.joints[j, 1]) == pytest.approx(y0)
    above = lambda a: float(a.vertices[:, 1].max()) - y0  # noqa: E731
    assert above(big) == pytest.approx(1.8 * above(base), rel=0.02)


def test_floating_parts_and_hole_topology(avatars: dict) -> None:
    import trimesh

    base = avatars["anny-12"]
    fp = avatars["floating-parts"]
    m = trimesh.Trimesh(fp.vertices.numpy(), fp.faces.numpy(), process=False)
    assert m.body_count == 3 and m.is_watertight
    extra = fp.vertices[base.vertices.shape[0] :]
    shoulder = [fp.skeleton.names.index(n) for n in ("shoulder01.L", "shoulder01.R")]
    assert set(fp.skin_weights[:, base.vertices.shape[0] :].argmax(dim=0).tolist()) == set(shoulder)
    # Detached: clear of the body.
    import igl

    d, _, _ = igl.point_mesh_squared_distance(extra.numpy(), base.vertices.numpy(), base.faces.numpy())
    assert float(np.sqrt(d).min()) > 0.01
    hole = avatars["torso-hole"]
    m = trimesh.Trimesh(hole.vertices.numpy(), hole.faces.numpy(), process=False)
    assert m.is_watertight and m.euler_number == 0  # genus 1
    # The hole axis (along Z, through the belly) stays clear of the surface: the hole is open.
    from torchgarment.retarget.avatars import HOLE_OFFSET, HOLE_RADIUS, _anny

    y = float(_anny("12").landmarks["waist"][1])
    axis = torch.stack(
        [torch.full((21,), HOLE_OFFSET), torch.full((21,), y), torch.linspace(-0.3, 0.3, 21)], 1
    )
    d, _, _ = igl.point_mesh_squared_distance(axis.numpy(), hole.vertices.numpy(), hole.faces.numpy())
    assert float(np.sqrt(d).min()) > 0.8 * HOLE_RADIUS
    d, _, _ = igl.point_mesh_squared_distance(axis.numpy(), base.vertices.numpy(), base.faces.numpy())
    assert float(np.sqrt(d).min()) < 0.02  # the intact body has its belly there (axis sampled every 3 cm)


def test_scaled_copies(avatars: dict) -> None:
    mini, giant = avatars["miniature"], avatars["giant"]
    h = lambda a: float(a.vertices[:, 1].max() - a.vertices[:, 1].min())  # noqa: E731
    assert h(mini) == pytest.approx(0.06) and h(giant) == pytest.approx(4.0)
    assert float(mini.vertices[:, 0].mean()) == pytest.approx(100.0, abs=0.05)
    assert float(mini.vertices[:, 1].min()) == pytest.approx(-50.0)


def test_unknown_avatar() -> None:
    with pytest.raises(InputError, match="unknown test avatar"):
        make_avatar("dragon")


def test_creatures_are_messy(avatars: dict) -> None:
    """Issue 14's non-human avatars: 10K / 50K triangles, self-intersecting, not closed, at 6 cm and 10 m."""
    import ipctk
    import trimesh

    for name, triangles, height in (("creature-10k", 10_000, 0.06), ("creature-50k", 50_000, 10.0)):
        a = avatars[name]
        assert abs(a.faces.shape[0] - triangles) <= 0.1 * triangles, (name, a.faces.shape[0])
        m = trimesh.Trimesh(a.vertices.numpy(), a.faces.numpy(), process=False)
        assert not m.is_watertight and m.body_count > 10, name
        h = float(a.vertices[:, 1].max() - a.vertices[:, 1].min())
        assert h == pytest.approx(height), name
        v = np.asfortranarray(a.vertices.numpy())
        f = np.asfortranarray(a.faces.numpy().astype(np.int32))
        assert ipctk.has_intersections(ipctk.CollisionMesh(v, ipctk.edges(f), f), v), name
        # rigid skinning: every vertex belongs to one joint
        assert torch.equal(a.skin_weights.max(dim=0).values, torch.ones(v.shape[0], dtype=torch.float64))


def test_rig_from_fitted_anny_recovers_a_chart_bodys_own_rig() -> None:
    """An anny chart body stripped of its rig gets back a skeleton within 2 cm of its own and skin weights
    that mostly name the same dominant joint (the refit from its measured girths is a slightly different
    body)."""
    from torchgarment.body import Body
    from torchgarment.retarget.avatars import rig_from_fitted_anny

    own = Body.from_size("12")
    rigged = rig_from_fitted_anny(Body(own.vertices, own.faces))
    assert torch.equal(rigged.vertices, own.vertices) and rigged.skeleton.names == own.skeleton.names
    assert float((rigged.skeleton.joints - own.skeleton.joints).norm(dim=1).max()) < 0.02
    assert torch.allclose(rigged.skin_weights.sum(dim=0), torch.ones(own.num_vertices, dtype=torch.float64))
    same = (rigged.skin_weights.argmax(dim=0) == own.skin_weights.argmax(dim=0)).double().mean()
    assert float(same) > 0.9
