"""GarmentMesh: derived topology checked by hand, geometry, copies, validation, welding, gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchgarment.errors import MeshError
from torchgarment.structures import GarmentMesh, seam_weld_index, welded_faces


def fan_square() -> GarmentMesh:
    """Unit square split into four triangles around its centre (vertex 4), counter-clockwise."""
    x = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0]]
    faces = [[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]]
    return GarmentMesh.from_arrays(x, faces)


def grid_with_hole() -> GarmentMesh:
    """4 x 4 vertex grid (3 x 3 unit squares) without the middle square: an annulus."""
    ii, jj = np.meshgrid(np.arange(4), np.arange(4), indexing="ij")
    x = np.stack([ii.ravel(), jj.ravel(), np.zeros(16)], axis=1).astype(float)
    faces = []
    for i in range(3):
        for j in range(3):
            if (i, j) == (1, 1):
                continue
            a, b, c, d = 4 * i + j, 4 * (i + 1) + j, 4 * (i + 1) + j + 1, 4 * i + j + 1
            faces += [[a, b, c], [a, c, d]]
    return GarmentMesh.from_arrays(x, faces)


def test_edges_and_face_edges_fan():
    m = fan_square()
    expected = [[0, 1], [0, 3], [0, 4], [1, 2], [1, 4], [2, 3], [2, 4], [3, 4]]
    assert m.edges.tolist() == expected
    # face_edges[f, k] is the edge faces[f, k] -> faces[f, k+1]
    fe = m.face_edges
    for f in range(m.num_faces):
        for k in range(3):
            a, b = m.faces[f, k].item(), m.faces[f, (k + 1) % 3].item()
            assert m.edges[fe[f, k]].tolist() == sorted([a, b])
    assert m.edge_face_counts.tolist() == [1, 1, 2, 1, 2, 1, 2, 2]


def test_hinges_fan_by_hand():
    m = fan_square()
    h = m.hinges
    assert h.shape == (4, 4)
    # interior edge {c, 4}: the two opposite vertices are c's neighbours on the square
    expected = {frozenset({0, 4}): {1, 3}, frozenset({1, 4}): {0, 2}, frozenset({2, 4}): {1, 3},
                frozenset({3, 4}): {0, 2}}
    faces = {tuple(np.roll(f, r)) for f in m.faces.tolist() for r in range(3)}
    got = {}
    for (v0, v1, v2, v3), (f0, f1) in zip(h.tolist(), m.hinge_faces.tolist()):
        got[frozenset({v0, v1})] = {v2, v3}
        assert (v0, v1, v2) in faces  # first face runs v0 -> v1
        assert (v1, v0, v3) in faces  # second face runs v1 -> v0 (consistent orientation)
        assert set(m.faces[f0].tolist()) == {v0, v1, v2} and set(m.faces[f1].tolist()) == {v0, v1, v3}
    assert got == expected


def test_boundary_loops_fan_and_annulus():
    m = fan_square()
    (loop,) = m.boundary_loops
    # counter-clockwise like the faces, any starting vertex
    seq = loop.tolist()
    k = seq.index(0)
    assert seq[k:] + seq[:k] == [0, 1, 2, 3]
    assert sorted(map(sorted, m.boundary_edges.tolist())) == [[0, 1], [0, 3], [1, 2], [2, 3]]

    a = grid_with_hole()
    loops = a.boundary_loops
    assert [len(lp) for lp in loops] == [12, 4]
    assert set(loops[1].tolist()) == {5, 6, 9, 10}

    def signed_area(idx):
        p = a.x[idx, :2]
        return 0.5 * float((p[:, 0] * p.roll(-1, 0)[:, 1] - p[:, 1] * p.roll(-1, 0)[:, 0]).sum())

    assert signed_area(loops[0]) == pytest.approx(9.0)  # outer loop counter-clockwise
    assert signed_area(loops[1]) == pytest.approx(-1.0)  # hole runs the other way
    assert a.hinges.shape[0] == a.edges.shape[0] - 16  # every non-boundary edge is a hinge


def test_geometry_areas_normals():
    m = fan_square()
    assert torch.allclose(m.face_areas, torch.full((4,), 0.25, dtype=torch.float64))
    assert torch.allclose(m.vertex_normals, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(5, 3))
    assert torch.allclose(m.face_normals[:, 2], torch.ones(4, dtype=torch.float64))
    # tilted copy: rotate 90 degrees about x, normals follow
    r = torch.tensor([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=torch.float64)
    t = m.with_positions(m.x @ r.T)
    assert torch.allclose(t.vertex_normals, torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64).expand(5, 3))
    assert t.edges is m.edges  # topology cache shared
    lengths = m.edge_lengths
    assert lengths.tolist() == pytest.approx([1, 1, 2**-0.5, 1, 2**-0.5, 1, 2**-0.5, 2**-0.5])


def test_rest_areas_and_panels():
    m = fan_square()
    p = m.x[:, :2].clone()
    g = GarmentMesh(m.x, m.faces, p=p, panel_ids=torch.tensor([0, 0, 1, 1]), panel_names=["a", "b"])
    assert torch.allclose(g.rest_face_areas, torch.full((4,), 0.25, dtype=torch.float64))
    with pytest.raises(MeshError, match="panels 0 and 1"):
        g.vertex_panel_ids  # noqa: B018 - panels share vertices 2, 4 and 0
    with pytest.raises(MeshError, match="rest positions"):
        fan_square().rest_face_areas  # noqa: B018


def test_to_clone_with_positions():
    m = fan_square()
    m.hinges  # noqa: B018 - fill caches
    m.face_areas  # noqa: B018
    f = m.to(dtype=torch.float32)
    assert f.x.dtype == torch.float32 and f.faces.dtype == torch.long
    assert torch.equal(f.hinges, m.hinges)
    assert "face_areas" not in f._cache and "hinges" in f._topo
    assert f.face_areas.dtype == torch.float32
    c = m.clone()
    c.x[0, 0] = 5.0
    assert m.x[0, 0] == 0.0
    moved = m.with_positions(m.x * 2)
    assert torch.allclose(moved.face_areas, 4 * m.face_areas)
    with pytest.raises(MeshError):
        m.with_positions(m.x[:3])


def test_validate_accepts_good_and_rejects_bad():
    fan_square().validate()
    grid_with_hole().validate()
    x = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [1, 1, 1]]
    with pytest.raises(MeshError, match="non-manifold"):  # edge 0-1 shared by three faces
        GarmentMesh.from_arrays(x, [[0, 1, 2], [1, 0, 3], [0, 1, 4]]).validate()
    with pytest.raises(MeshError, match="degenerate"):
        GarmentMesh.from_arrays([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]]).validate()
    with pytest.raises(MeshError, match="used by no face"):
        GarmentMesh.from_arrays(x, [[0, 1, 2]]).validate()
    with pytest.raises(MeshError, match="opposite orientation"):
        GarmentMesh.from_arrays(x[:4], [[0, 1, 2], [0, 1, 3]]).validate()
    with pytest.raises(MeshError, match=r"\(V, 3\)"):
        GarmentMesh(torch.zeros(3, 2, dtype=torch.float64), torch.zeros(1, 3, dtype=torch.long))
    with pytest.raises(MeshError, match="long"):
        GarmentMesh(torch.zeros(3, 3, dtype=torch.float64), torch.zeros(1, 3, dtype=torch.int32))
    m = fan_square()
    bad_seam = GarmentMesh(m.x, m.faces, seam_pairs=torch.tensor([[0, 4]]))
    with pytest.raises(MeshError, match="interior"):
        bad_seam.validate()


def two_triangles_sewn() -> GarmentMesh:
    """Two separate triangles whose shared side is duplicated and joined by two seam pairs."""
    x = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0.1], [0, 1, 0.1], [1, 1, 0]],
                     dtype=torch.float64)
    p = x[:, :2].clone()
    faces = torch.tensor([[0, 1, 2], [3, 5, 4]])
    return GarmentMesh(x, faces, p=p, panel_ids=torch.tensor([0, 1]), panel_names=["a", "b"],
                       seam_pairs=torch.tensor([[1, 3], [2, 4]]))


def test_welded():
    m = two_triangles_sewn()
    m.validate()
    assert m.vertex_panel_ids.tolist() == [0, 0, 0, 1, 1, 1]
    w, index_map = m.welded()
    assert index_map.tolist() == [0, 1, 2, 1, 2, 3]
    assert w.num_vertices == 4 and w.num_faces == 2 and w.p is None
    assert torch.allclose(w.x[1], torch.tensor([1.0, 0, 0.05], dtype=torch.float64))
    assert w.hinges.shape == (1, 4) and set(w.hinges[0, :2].tolist()) == {1, 2}
    w.validate()
    # an unsewn mesh comes back unchanged
    u, um = fan_square().welded()
    assert torch.equal(um, torch.arange(5)) and torch.equal(u.x, fan_square().x)


def test_from_trimesh():
    import trimesh

    tm = trimesh.creation.icosphere(subdivisions=1)
    m = GarmentMesh.from_trimesh(tm, dtype=torch.float32)
    assert m.x.dtype == torch.float32 and m.num_faces == len(tm.faces)
    m.validate()
    assert m.boundary_loops == [] and m.hinges.shape[0] == m.edges.shape[0] == 3 * m.num_faces // 2
    assert float(m.face_areas.sum()) == pytest.approx(tm.area, rel=1e-5)


def test_gradients():
    m = fan_square()
    x0 = (m.x + 0.05 * torch.randn(5, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)))
    x0 = x0.detach().requires_grad_(True)
    for attr in ("face_areas", "vertex_normals", "face_normals", "edge_lengths"):
        assert torch.autograd.gradcheck(lambda x, a=attr: getattr(m.with_positions(x), a), (x0,))
    s = two_triangles_sewn()
    xs = s.x.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: s.with_positions(x).welded()[0].x, (xs,))


def test_welded_faces_drop_the_faces_a_seam_collapses():
    """A dart: vertices 1 and 2 are sewn together, so faces 0 and 1 (each holding both) collapse; face 2
    survives, renumbered (as GarmentMesh.welded and the contact terms' welded collision mesh see it)."""
    faces = np.array([[0, 1, 2], [1, 3, 2], [3, 4, 2]])
    index, n = seam_weld_index(np.array([[1, 2]]), 5)
    assert index.tolist() == [0, 1, 1, 2, 3] and n == 4
    wf, kept = welded_faces(index, faces)
    assert kept.tolist() == [False, False, True] and wf.tolist() == [[2, 3, 1]]
