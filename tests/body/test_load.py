"""Tests of loading a body with its skeleton and skin weights."""

from __future__ import annotations

import warnings

import pytest
import torch
import trimesh

from torchgarment.body.body import Body
from torchgarment.body.load import BodyMeshWarning, load_body
from torchgarment.body.skeleton import Skeleton
from torchgarment.body.skeleton_io import write_skeleton_obj, write_skin_weights
from torchgarment.errors import InputError
from torchgarment.io.mesh import save_obj


@pytest.fixture
def files(tmp_path):
    box = trimesh.creation.box(extents=[0.4, 1.6, 0.2])
    box.apply_translation([0, 0.8, 0])
    v = torch.tensor(box.vertices, dtype=torch.float64)
    f = torch.tensor(box.faces, dtype=torch.long)
    save_obj(tmp_path / "body.obj", v, f)
    skel = Skeleton(torch.tensor([[0, 0.2, 0], [0, 0.8, 0], [0, 1.4, 0]], dtype=torch.float64),
                    torch.tensor([[0, 1], [1, 2]]))
    write_skeleton_obj(tmp_path / "skel.obj", skel)
    w = torch.rand(3, v.shape[0], dtype=torch.float64)
    write_skin_weights(tmp_path / "w.txt", w)
    return tmp_path, v, f, skel, w


def test_load_body_with_paths(files):
    d, v, f, skel, w = files
    body = load_body(d / "body.obj", d / "skel.obj", d / "w.txt", dtype=torch.float32)
    assert isinstance(body, Body) and body.dtype == torch.float32
    assert torch.equal(body.vertices, v.float()) and torch.equal(body.faces, f)
    assert torch.equal(body.skeleton.bones, skel.bones)
    assert torch.allclose(body.skin_weights, (w / w.sum(0)).float())
    assert body.params["source"].endswith("body.obj")
    same = Body.from_file(d / "body.obj", skel, w)
    assert same.skin_weights.dtype == torch.float64 and torch.allclose(same.skin_weights, w / w.sum(0))


def test_load_body_open_nonmanifold_and_degenerate(tmp_path):
    # an open fan with a non-manifold edge and a zero-area face: loads, with a warning for the degenerate face
    (tmp_path / "avatar.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 -1 0\nv 0 0 1\nv 2 0 0\nf 1 2 3\nf 2 1 4\nf 1 2 5\nf 1 2 6\n"
    )
    with pytest.warns(BodyMeshWarning, match="1 degenerate faces"):
        body = load_body(tmp_path / "avatar.obj")
    assert body.faces.shape == (4, 3) and body.skeleton is None
    (tmp_path / "clean.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_body(tmp_path / "clean.obj")


def test_weld_averages_skin_weights(tmp_path):
    (tmp_path / "seam.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 4 5 "
                                       "6\n")
    skel = Skeleton(torch.tensor([[0, 0, 0], [0, 1, 0]], dtype=torch.float64), torch.tensor([[0, 1]]))
    w = torch.tensor([[1.0, 1, 1, 0, 0, 0], [0, 0, 0, 1, 1, 1]], dtype=torch.float64)
    body = load_body(tmp_path / "seam.obj", skel, w, weld=True)
    assert body.num_vertices == 4
    assert torch.allclose(body.skin_weights,
                          torch.tensor([[0.5, 1, 0.5, 0], [0.5, 0, 0.5, 1]], dtype=torch.float64))


def test_load_body_errors(files):
    d, v, f, skel, w = files
    with pytest.raises(InputError, match="not found"):
        load_body(d / "missing.obj")
    with pytest.raises(InputError, match="need a skeleton"):
        load_body(d / "body.obj", skin_weights=w)
    with pytest.raises(InputError, match="looks transposed"):
        load_body(d / "body.obj", skel, w.T.contiguous())
    with pytest.raises(InputError, match="expected"):
        load_body(d / "body.obj", skel, w[:, :-1])
    cyclic = Skeleton(skel.joints, torch.tensor([[0, 1], [1, 2], [2, 0]]))
    with pytest.raises(InputError, match="cycle"):
        load_body(d / "body.obj", cyclic)
    with pytest.raises(InputError, match="Skeleton or a path"):
        load_body(d / "body.obj", 42)
    (d / "garbage.obj").write_text("not an obj\n")
    with pytest.raises(InputError, match="unknown statement"):
        load_body(d / "garbage.obj")


def test_garmentcode_body(garmentcode_dir):
    body = load_body(garmentcode_dir / "bodies" / "mean_female.obj")
    assert body.num_vertices == 23752 and body.faces.shape == (47500, 3)
    assert body.vertices[:, 1].min() > -0.1 and 1.4 < body.vertices[:, 1].max() < 2.1
