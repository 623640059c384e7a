"""Tests of skeleton OBJ edge graphs and skin-weight text files."""

from __future__ import annotations

import pytest
import torch

from torchgarment.body.skeleton import Skeleton
from torchgarment.body.skeleton_io import (
    read_skeleton_obj,
    read_skin_weights,
    validate_skin_weights,
    write_skeleton_obj,
    write_skin_weights,
)
from torchgarment.errors import InputError


def test_read_polyline_and_comments(tmp_path):
    p = tmp_path / "s.obj"
    p.write_text("# skeleton\nv 0 1 0\nv 0 1.5 0\nv 0.3 1.4 0\nv 0.6 1.2 0\nl 1 2\nl 2 3 4\n")
    s = read_skeleton_obj(p)
    assert s.joints.shape == (4, 3) and s.joints.dtype == torch.float64
    assert s.bones.tolist() == [[0, 1], [1, 2], [2, 3]]
    assert s.names == []


def test_round_trip_with_names(tmp_path):
    s = Skeleton(torch.rand(4, 3, dtype=torch.float64), torch.tensor([[0, 1], [1, 2], [1, 3]]),
                 ["root", "chest", "left arm", "head"])
    write_skeleton_obj(tmp_path / "s.obj", s)
    r = read_skeleton_obj(tmp_path / "s.obj", dtype=torch.float32)
    assert torch.equal(r.joints, s.joints.float()) and torch.equal(r.bones, s.bones) and r.names == s.names
    r64 = read_skeleton_obj(tmp_path / "s.obj")
    assert torch.equal(r64.joints, s.joints)


@pytest.mark.parametrize(
    "content, match",
    [
        ("", "needs joints"),
        ("v 0 0 0\nv 1 0 0\n", "needs joints"),
        ("v 0 0 0\nv 1 0 0\nl 1 3\n", "outside"),
        ("v 0 0 0\nv 1 0 0\nl 1\n", "two 1-based"),
        ("v 0 0 0\nv 1 0 0\nl 0 1\n", "two 1-based"),
        ("v 0 0 0\nv 1 0 0\nl 1 a\n", "bad joint index"),
        ("v 0 0\nv 1 0 0\nl 1 2\n", "three coordinates"),
        ("v 0 0 q\nv 1 0 0\nl 1 2\n", "non-numeric"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "has faces"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2 3 1\n", "cycle"),
        ("bones everywhere\n", "unknown statement"),
        ("# joint 0 a\nv 0 0 0\nv 1 0 0\nl 1 2\n", "name every joint"),
    ],
)
def test_bad_skeleton_files(tmp_path, content, match):
    p = tmp_path / "bad.obj"
    p.write_text(content)
    with pytest.raises(InputError, match=match):
        read_skeleton_obj(p)


def test_missing_skeleton_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_skeleton_obj(tmp_path / "none.obj")


def test_write_rejects_cycles(tmp_path):
    s = Skeleton(torch.rand(3, 3), torch.tensor([[0, 1], [1, 2], [2, 0]]))
    with pytest.raises(InputError, match="cycle"):
        write_skeleton_obj(tmp_path / "s.obj", s)
    assert not (tmp_path / "s.obj").exists()


def test_skin_weights_read_normalize_round_trip(tmp_path):
    w = torch.rand(3, 7, dtype=torch.float64)
    w[0, 2] = 0.0
    write_skin_weights(tmp_path / "w.txt", w)
    r = read_skin_weights(tmp_path / "w.txt", 3, 7)
    assert r.shape == (3, 7)
    assert torch.allclose(r.sum(0), torch.ones(7, dtype=torch.float64), atol=1e-15)
    assert torch.allclose(r, w / w.sum(0), atol=1e-15)


@pytest.mark.parametrize(
    "content, shape, match",
    [
        ("1 0 0\n0 1 1\n", (3, 2), "looks transposed"),
        ("1 0 0\n0 1 1\n", (2, 4), r"expected \(joints, vertices\) = \(2, 4\)"),
        ("1 0 -1\n0 1 2\n", (2, 3), "negative for 1 vertices"),
        ("1 0 0\n0 1 0\n", (2, 3), r"all zero for 1 vertices, first \[2\]"),
        ("1 0\n0 1 1\n", (2, 3), "ragged"),
        ("1 x 0\n0 1 1\n", (2, 3), "non-numeric"),
        ("1 nan 0\n0 1 1\n", (2, 3), "non-finite"),
        ("# nothing\n", (2, 3), "empty"),
    ],
)
def test_bad_skin_weights(tmp_path, content, shape, match):
    p = tmp_path / "w.txt"
    p.write_text(content)
    with pytest.raises(InputError, match=match):
        read_skin_weights(p, *shape)


def test_validate_skin_weights_tensor():
    with pytest.raises(InputError, match="floating"):
        validate_skin_weights(torch.ones(2, 3, dtype=torch.long), 2, 3)
    out = validate_skin_weights(torch.tensor([[1.0, 3.0], [1.0, 1.0]]), 2, 2)
    assert torch.allclose(out, torch.tensor([[0.5, 0.75], [0.5, 0.25]]))
