"""Inputs of garment retargeting: welding, validation, the work frame, the fit region."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pytest
import torch

from torchgarment.body.skeleton import Skeleton
from torchgarment.body.skeleton_io import write_skeleton_obj, write_skin_weights
from torchgarment.errors import InputError, MeshError
from torchgarment.io.mesh import read_obj, save_obj
from torchgarment.retarget.avatars import toy_case, tube_mesh
from torchgarment.retarget.inputs import (
    Similarity,
    automatic_fit_mask,
    load_problem,
    problem_from_arrays,
    weld_garment,
)

if TYPE_CHECKING:
    from pathlib import Path

    from torchgarment.retarget.avatars import ToyCase


def _write_split_tube(path: Path, segments: int = 12, rings: int = 4) -> tuple[int, int]:
    """An OBJ tube whose seam column (angle 0) is duplicated, as UV-seam exporters write it."""
    v, f = tube_mesh(0.3, 0.3, -0.2, 1.25, segments, rings)
    # Faces of the last column use copies of the first column's vertices (the seam).
    copies = v[:rings].clone()
    v = torch.cat([v, copies])
    seam_face = f >= 0
    last_col = (f // rings == segments - 1).any(dim=1)
    ff = f.clone()
    wrap = last_col[:, None] & (f < rings) & seam_face
    ff[wrap] = f[wrap] + segments * rings
    lines = ["# split tube", *(f"v {x:.9f} {y:.9f} {z:.9f}" for x, y, z in v.tolist())]
    lines += [f"vt {k / len(v):.4f} 0.5" for k in range(len(v))]
    lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in ff.tolist()]
    path.write_text("\n".join(lines) + "\n")
    return v.shape[0], segments * rings


def test_weld_uv_split_cube(tmp_path: Path) -> None:
    # A cube written with 4 separate vertices per face (24), as exporters do along UV seams.
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    lines = []
    for q in quads:
        lines += [f"v {' '.join(map(str, corners[i]))}" for i in q]
    lines += [f"f {4 * k + 1} {4 * k + 2} {4 * k + 3} {4 * k + 4}" for k in range(6)]
    p = tmp_path / "cube.obj"
    p.write_text("\n".join(lines) + "\n")
    v, f = read_obj(p)
    assert v.shape == (24, 3)
    wv, wf, old_to_new = weld_garment(torch.as_tensor(v), torch.as_tensor(f), 1e-9)
    assert wv.shape == (8, 3) and wf.shape == (12, 3)
    assert torch.allclose(wv[old_to_new], torch.as_tensor(v))


def test_load_problem_welds_and_maps_indices(tmp_path: Path) -> None:
    n_file, n_welded = _write_split_tube(tmp_path / "garment.obj")
    case = toy_case(target_scale=100.0, target_offset=(300.0, 20.0, -50.0))  # centimetres, elsewhere
    write_skeleton_obj(tmp_path / "src.obj", case.source_skeleton)
    write_skeleton_obj(tmp_path / "tgt.obj", case.target_skeleton)
    save_obj(tmp_path / "avatar.obj", case.target_vertices, case.target_faces)
    save_obj(tmp_path / "source_avatar.obj", case.source_vertices, case.source_faces)
    w = torch.rand(5, case.target_vertices.shape[0], dtype=torch.float64) + 0.01
    write_skin_weights(tmp_path / "w.txt", w)
    seam_copy = n_file - 1  # a duplicated seam vertex: welds onto vertex rings - 1
    (tmp_path / "nofit.txt").write_text(f"0 1\n{seam_copy}\n")
    (tmp_path / "curves.txt").write_text(" ".join(str(k * 4) for k in range(12)) + "\n")
    p = load_problem(
        tmp_path / "garment.obj",
        tmp_path / "src.obj",
        tmp_path / "avatar.obj",
        tmp_path / "tgt.obj",
        source_avatar=tmp_path / "source_avatar.obj",
        skin_weights=tmp_path / "w.txt",
        no_fit=tmp_path / "nofit.txt",
        curves=tmp_path / "curves.txt",
    )
    assert p.garment_vertices.shape == (n_welded, 3)
    assert p.garment_index_map is not None and int(p.garment_index_map[seam_copy]) == 3
    assert not p.fit_mask[[0, 1, 3]].any()
    assert p.fit_mask.any()
    assert len(p.curves) == 1 and p.curves[0].tolist() == [k * 4 for k in range(12)]
    assert p.skin_weights.shape == (5, case.target_vertices.shape[0])
    assert torch.allclose(
        p.skin_weights.sum(dim=0), torch.ones(case.target_vertices.shape[0], dtype=torch.float64)
    )
    # The target (centimetres, far away) lands on the source skeleton: scale 1/100, roots coincide.
    assert p.to_work.scale == pytest.approx(0.01, rel=1e-9)
    assert torch.allclose(p.target_skeleton.joints[0], p.source_skeleton.joints[0], atol=1e-9)
    assert p.length_scale == pytest.approx(1.65, rel=1e-6)


def test_to_work_round_trip_miniature() -> None:
    case = toy_case(target_scale=0.04, target_offset=(100.0, -50.0, 30.0))
    p = problem_from_arrays(
        case.garment_vertices,
        case.garment_faces,
        case.source_skeleton,
        case.target_vertices,
        case.target_faces,
        case.target_skeleton,
    )
    assert p.to_work.scale == pytest.approx(25.0, rel=1e-9)
    back = p.to_work.inverse(p.avatar_vertices)
    assert torch.allclose(back, case.target_vertices, atol=1e-12 * 100)
    assert torch.allclose(p.to_work.apply(case.target_skeleton.joints), p.target_skeleton.joints)
    # Trunk bones coincide with the source after mapping (the arms are 1.3x longer by construction).
    assert torch.allclose(p.target_skeleton.joints[:3], p.source_skeleton.joints[:3], atol=1e-9)
    s = Similarity(2.0, torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    x = torch.randn(10, 3, dtype=torch.float64)
    assert torch.allclose(s.inverse(s.apply(x)), x)


def test_degenerate_avatar_faces_dropped() -> None:
    case = toy_case()
    faces = torch.cat([case.target_faces, torch.tensor([[0, 0, 1], [2, 3, 3]])])
    p = problem_from_arrays(
        case.garment_vertices,
        case.garment_faces,
        case.source_skeleton,
        case.target_vertices,
        faces,
        case.target_skeleton,
    )
    assert p.avatar_faces.shape[0] == case.target_faces.shape[0]


def test_automatic_fit_mask_picks_near_vertices() -> None:
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    av = torch.as_tensor(np.asarray(s.vertices))
    af = torch.as_tensor(np.asarray(s.faces))
    dirs = torch.nn.functional.normalize(torch.randn(50, 3, dtype=torch.float64), dim=1)
    radii = torch.where(torch.arange(50) % 2 == 0, 1.01, 1.2).double()
    mask = automatic_fit_mask(dirs * radii[:, None], av, af, 0.03)
    assert mask.tolist() == (torch.arange(50) % 2 == 0).tolist()
    with pytest.raises(InputError, match="fit distance"):
        automatic_fit_mask(dirs, av, af, -1.0)


def test_toy_fit_region_from_source_avatar() -> None:
    case = toy_case()
    p = problem_from_arrays(
        case.garment_vertices,
        case.garment_faces,
        case.source_skeleton,
        case.target_vertices,
        case.target_faces,
        case.target_skeleton,
        source_avatar=(case.source_vertices, case.source_faces),
        fit_distance=0.05,
    )
    import igl

    d, _, _ = igl.point_mesh_squared_distance(
        p.garment_vertices.numpy(), case.source_vertices.numpy(), case.source_faces.numpy()
    )
    assert p.fit_mask.tolist() == (np.sqrt(d) <= 0.05).tolist()
    assert 0 < int(p.fit_mask.sum()) < p.fit_mask.numel()


def test_nonmanifold_garment_raises() -> None:
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], dtype=torch.float64)
    f = torch.tensor([[0, 1, 2], [1, 0, 3], [0, 1, 4]])  # edge 0-1 used by three faces
    with pytest.raises(MeshError, match="non-manifold"):
        weld_garment(v, f, 0.0)


def test_self_intersecting_garment_raises() -> None:
    case = toy_case()
    gv, gf = tube_mesh(0.3, 0.3, -0.2, 1.25, 24, 10)
    g2v, g2f = tube_mesh(0.45, 0.15, -0.1, 1.0, 24, 10)  # crosses the first tube
    v = torch.cat([gv, g2v])
    f = torch.cat([gf, g2f + gv.shape[0]])
    with pytest.raises(MeshError, match="intersects itself"):
        problem_from_arrays(
            v, f, case.source_skeleton, case.target_vertices, case.target_faces, case.target_skeleton
        )


def test_mismatched_skeletons_raise() -> None:
    case = toy_case()
    args = (
        case.garment_vertices,
        case.garment_faces,
        case.source_skeleton,
        case.target_vertices,
        case.target_faces,
    )
    fewer = Skeleton(case.target_skeleton.joints[:4], case.target_skeleton.bones[:3])
    with pytest.raises(InputError, match="same joints"):
        problem_from_arrays(*args, fewer)
    rewired = Skeleton(case.target_skeleton.joints, torch.tensor([[0, 1], [1, 2], [2, 3], [1, 4]]))
    with pytest.raises(InputError, match="same bones"):
        problem_from_arrays(*args, rewired)


def _files(tmp_path: Path) -> tuple[list[Path], ToyCase]:
    case = toy_case()
    save_obj(tmp_path / "g.obj", case.garment_vertices, case.garment_faces)
    write_skeleton_obj(tmp_path / "s.obj", case.source_skeleton)
    write_skeleton_obj(tmp_path / "t.obj", case.target_skeleton)
    save_obj(tmp_path / "a.obj", case.target_vertices, case.target_faces)
    return [tmp_path / n for n in ("g.obj", "s.obj", "a.obj", "t.obj")], case


def test_bad_index_files_raise(tmp_path: Path) -> None:
    paths, case = _files(tmp_path)
    n = case.garment_vertices.shape[0]
    (tmp_path / "bad.txt").write_text(f"0 5 {n}\n")
    with pytest.raises(InputError, match=f"vertex index {n} is out of range"):
        load_problem(*paths, no_fit=tmp_path / "bad.txt")
    (tmp_path / "word.txt").write_text("0 x 2\n")
    with pytest.raises(InputError, match="not an integer"):
        load_problem(*paths, no_fit=tmp_path / "word.txt")
    (tmp_path / "empty.txt").write_text("# nothing\n\n")
    with pytest.raises(InputError, match="empty"):
        load_problem(*paths, no_fit=tmp_path / "empty.txt")
    with pytest.raises(InputError, match="empty"):
        load_problem(*paths, curves=tmp_path / "empty.txt")
    (tmp_path / "short.txt").write_text("0 1\n")
    with pytest.raises(InputError, match="at least three"):
        load_problem(*paths, curves=tmp_path / "short.txt")
    with pytest.raises(InputError, match="not found"):
        load_problem(*paths, no_fit=tmp_path / "missing.txt")


def test_empty_garment_file_raises(tmp_path: Path) -> None:
    paths, _ = _files(tmp_path)
    (tmp_path / "empty.obj").write_text("# empty\n")
    with pytest.raises(InputError, match="empty"):
        load_problem(tmp_path / "empty.obj", *paths[1:])


def test_mismatched_skeleton_files_raise(tmp_path: Path) -> None:
    paths, case = _files(tmp_path)
    write_skeleton_obj(
        tmp_path / "t3.obj", Skeleton(case.target_skeleton.joints[:3], case.target_skeleton.bones[:2])
    )
    with pytest.raises(InputError, match="same joints"):
        load_problem(paths[0], paths[1], paths[2], tmp_path / "t3.obj")
