"""Tests of the generic mesh checks and vertex welding."""

from __future__ import annotations

import pytest
import torch
import trimesh

from torchgarment.errors import MeshError
from torchgarment.structures.mesh_checks import (
    check_mesh,
    face_areas,
    find_boundary_edges,
    find_degenerate_faces,
    find_misoriented_edges,
    find_nonmanifold_edges,
    find_unreferenced_vertices,
    weld_vertices,
)


def icosphere():
    m = trimesh.creation.icosphere(subdivisions=2)
    return torch.tensor(m.vertices, dtype=torch.float64), torch.tensor(m.faces, dtype=torch.long)


def test_closed_sphere_passes_and_areas():
    v, f = icosphere()
    check_mesh(v, f, require_closed=True)
    assert abs(face_areas(v, f).sum().item() - trimesh.creation.icosphere(subdivisions=2).area) < 1e-12
    assert find_boundary_edges(f).shape == (0, 2)


def test_face_areas_2d_and_gradcheck():
    v2 = torch.tensor([[0.0, 0.0], [2.0, 0.0], [0.0, 3.0]], dtype=torch.float64, requires_grad=True)
    f = torch.tensor([[0, 1, 2]])
    assert face_areas(v2, f).item() == pytest.approx(3.0)
    assert torch.autograd.gradcheck(lambda x: face_areas(x, f), (v2,))
    v3 = torch.randn(4, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: face_areas(x, torch.tensor([[0, 1, 2], [0, 2, 3]])), (v3,))


def test_degenerate_faces():
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]], dtype=torch.float64)
    f = torch.tensor([[0, 1, 2], [0, 1, 3], [0, 0, 2], [2, 1, 0]])  # collinear, repeated index
    assert find_degenerate_faces(v, f).tolist() == [1, 2]
    with pytest.raises(MeshError, match=r"garment: 2 degenerate faces.*\[1, 2\]"):
        check_mesh(v, f, require_manifold=False, name="garment")


def test_nonmanifold_and_misoriented_edges():
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], dtype=torch.float64)
    fan = torch.tensor([[0, 1, 2], [1, 0, 3], [0, 1, 4]])  # edge (0,1) in three faces
    assert find_nonmanifold_edges(fan).tolist() == [[0, 1]]
    with pytest.raises(MeshError, match="1 non-manifold edges"):
        check_mesh(v, fan)
    check_mesh(v, fan, require_manifold=False)
    flipped = torch.tensor([[0, 1, 2], [0, 1, 3]])  # neighbours with opposite orientation
    assert find_misoriented_edges(flipped).tolist() == [[0, 1]]
    with pytest.raises(MeshError, match="opposite orientation"):
        check_mesh(v, flipped)


def test_open_mesh_and_unreferenced():
    v, f = icosphere()
    with pytest.raises(MeshError, match="not closed"):
        check_mesh(v, f[1:], require_closed=True)
    assert find_boundary_edges(f[1:]).shape == (3, 2)
    extra = torch.cat([v, torch.zeros(2, 3, dtype=torch.float64)])
    assert find_unreferenced_vertices(extra.shape[0], f).tolist() == [v.shape[0], v.shape[0] + 1]
    check_mesh(extra, f)
    with pytest.raises(MeshError, match="2 vertices are used by no face"):
        check_mesh(extra, f, allow_unreferenced=False)


@pytest.mark.parametrize(
    "vertices, faces, match",
    [
        (torch.zeros(3, 4), torch.tensor([[0, 1, 2]]), "shape"),
        (torch.zeros(3, 3, dtype=torch.long), torch.tensor([[0, 1, 2]]), "floating"),
        (torch.zeros(3, 3), torch.tensor([[0, 1, 2.0]]), "integer"),
        (torch.zeros(3, 3), torch.zeros(0, 3, dtype=torch.long), "empty"),
        (torch.tensor([[0, 0, 0], [1, 0, 0], [float("nan"), 1, 0]]), torch.tensor([[0, 1, 2]]), "non-finite"),
        (torch.eye(3), torch.tensor([[0, 1, 3]]), "outside"),
        (torch.eye(3), torch.tensor([[0, 1, -1]]), "outside"),
    ],
)
def test_check_mesh_bad_input(vertices, faces, match):
    with pytest.raises(MeshError, match=match):
        check_mesh(vertices, faces)


def test_weld_merges_seam_duplicates():
    v, f = icosphere()
    n = v.shape[0]
    # split every vertex of the first 20 faces into a copy (like an OBJ UV seam) with a tiny jitter
    dup_idx = f[:20].flatten()
    copies = v[dup_idx] + 1e-9
    split_v = torch.cat([v, copies])
    split_f = f.clone()
    split_f[:20] = (n + torch.arange(60)).reshape(20, 3)
    assert find_boundary_edges(split_f).shape[0] > 0
    wv, wf, index_map = weld_vertices(split_v, split_f, tol=1e-6)
    assert wv.shape[0] == n and torch.equal(wv, v)
    assert torch.equal(wf, f)
    assert torch.equal(index_map[n:], dup_idx)
    check_mesh(wv, wf, require_closed=True)
    # tol=0 only merges exact copies: the jittered copies stay apart from the originals
    assert weld_vertices(split_v, split_f, 0.0)[0].shape[0] == n + torch.unique(dup_idx).numel()
    exact = torch.cat([v, v[:3]])
    assert weld_vertices(exact, f, 0.0)[0].shape[0] == n


def test_weld_drops_collapsed_faces_and_rejects_bad_tol():
    v = torch.tensor([[0, 0, 0], [1e-8, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=torch.float64)
    f = torch.tensor([[0, 1, 2], [1, 3, 2]])
    wv, wf, index_map = weld_vertices(v, f, 1e-6)
    assert wv.shape[0] == 3 and wf.tolist() == [[0, 2, 1]] and index_map.tolist() == [0, 0, 1, 2]
    with pytest.raises(MeshError, match="tolerance"):
        weld_vertices(v, f, -1.0)


def test_weld_gradient_flows():
    v = torch.randn(5, 3, dtype=torch.float64, requires_grad=True)
    wv, _, _ = weld_vertices(v, torch.tensor([[0, 1, 2], [2, 3, 4]]), 0.0)
    wv.sum().backward()
    assert torch.equal(v.grad, torch.ones_like(v))
