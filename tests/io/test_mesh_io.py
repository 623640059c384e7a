"""Tests of mesh file reading and writing."""

from __future__ import annotations

import pytest
import torch
import trimesh

from torchgarment.errors import InputError
from torchgarment.io.mesh import load_mesh, read_obj, save_obj


def _sphere():
    return trimesh.creation.icosphere(subdivisions=1)


def test_obj_keeps_file_order_quads_relative_indices(tmp_path):
    p = tmp_path / "m.obj"
    p.write_text(
        "# comment\nmtllib x.mtl\no thing\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1 0.5 0.5 0.5\nv 9 9 9\n"
        "vt 0 0\nvn 0 0 1\ns off\nusemtl a\nf 1/1/1 2/1/1 3/1/1 4/1/1\nf -6//1 -5//1 -2//1  # tail comment\n"
    )
    v, f = read_obj(p)
    assert v.shape == (6, 3) and v[5].tolist() == [9, 9, 9]  # unreferenced vertex kept, in order
    assert f.tolist() == [[0, 1, 2], [0, 2, 3], [0, 1, 4]]
    tv, tf = load_mesh(p, weld=False)
    assert tv.dtype == torch.float64 and tf.dtype == torch.long and tv.shape == (6, 3)


def test_save_load_round_trip_and_formats(tmp_path):
    mesh = _sphere()
    v = torch.tensor(mesh.vertices, dtype=torch.float64)
    f = torch.tensor(mesh.faces, dtype=torch.long)
    save_obj(tmp_path / "a.obj", v, f)
    v2, f2 = load_mesh(tmp_path / "a.obj")
    assert torch.equal(v2, v) and torch.equal(f2, f)  # 17 digits: exact
    assert not list(tmp_path.glob(".*tmp*"))  # no temporary left behind
    for suffix in (".ply", ".stl", ".glb", ".off"):
        mesh.export(tmp_path / f"a{suffix}")
        v3, f3 = load_mesh(tmp_path / f"a{suffix}", dtype=torch.float32)
        assert v3.dtype == torch.float32 and f3.shape == f.shape
        assert abs(trimesh.Trimesh(v3.numpy(), f3.numpy()).area - mesh.area) < 1e-5


def test_glb_scene_is_concatenated(tmp_path):
    a = trimesh.creation.box()
    b = trimesh.creation.box()
    scene = trimesh.Scene()
    scene.add_geometry(a, node_name="a")
    scene.add_geometry(b, node_name="b", transform=trimesh.transformations.translation_matrix([3, 0, 0]))
    scene.export(tmp_path / "s.glb")
    v, f = load_mesh(tmp_path / "s.glb")
    assert f.shape[0] == 24 and v.shape[0] == 16
    assert v[:, 0].max().item() == pytest.approx(3.5)


def test_weld_merges_seam_copies(tmp_path):
    p = tmp_path / "seam.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 4 5 6\n")
    v, f = load_mesh(p)
    assert v.shape == (4, 3) and f.tolist() == [[0, 1, 2], [0, 2, 3]]
    assert load_mesh(p, weld=False)[0].shape == (6, 3)


@pytest.mark.parametrize(
    "name, content, match",
    [
        ("garbage.obj", "hello world\nthis is not a mesh\n", "unknown statement 'hello'"),
        ("empty.obj", "", "empty"),
        ("lines.obj", "v 0 0 0\nv 1 0 0\nl 1 2\n", "empty"),
        ("short.obj", "v 0 0\nf 1 1 1\n", "three coordinates"),
        ("nan.obj", "v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "non-finite"),
        ("word.obj", "v 0 0 x\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "malformed"),
        ("range.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "out of range"),
        ("zero.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "index 0"),
        ("edge.obj", "v 0 0 0\nv 1 0 0\nf 1 2\n", "three vertices"),
        ("bad.ply", "\x00\x01junk", "cannot read mesh"),
        ("bad.glb", "junk", "cannot read mesh"),
        ("bad.stl", "solid x\n garbage\n", "empty"),
        ("mesh.xyz", "1 2 3\n", "unsupported mesh format"),
    ],
)
def test_bad_files(tmp_path, name, content, match):
    p = tmp_path / name
    p.write_text(content)
    with pytest.raises(InputError, match=match) as info:
        load_mesh(p)
    assert "\n" not in str(info.value)
    assert info.value.__cause__ is None


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_mesh(tmp_path / "nope.obj")
    (tmp_path / "d.obj").mkdir()
    with pytest.raises(InputError, match="is a folder or a special file, not a mesh file"):
        load_mesh(tmp_path / "d.obj")
    (tmp_path / "bin.obj").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(InputError, match="cannot read OBJ"):
        load_mesh(tmp_path / "bin.obj")


def test_save_obj_validates(tmp_path):
    with pytest.raises(InputError, match="vertices"):
        save_obj(tmp_path / "x.obj", torch.zeros(3, 2), torch.tensor([[0, 1, 2]]))
    with pytest.raises(InputError, match="out of range"):
        save_obj(tmp_path / "x.obj", torch.zeros(3, 3), torch.tensor([[0, 1, 3]]))
    assert not (tmp_path / "x.obj").exists()


def test_garmentcode_body(garmentcode_dir):
    v, f = load_mesh(garmentcode_dir / "bodies" / "mean_all.obj", weld=False)
    assert v.shape == (23752, 3) and f.shape == (47500, 3)
    height = (v[:, 1].max() - v[:, 1].min()).item()
    assert 1.4 < height < 2.1  # metres, +Y up
