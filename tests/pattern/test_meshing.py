"""Meshing the GarmentCode specs: one-to-one seams, manifold panels, triangle quality, target edge length."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from torchgarment.errors import InputError, PatternError
from torchgarment.pattern import StitchOrientation
from torchgarment.pattern.garmentcode import load_pattern, pattern_from_dict
from torchgarment.pattern.meshing import edge_segment_counts, mesh_pattern

SPECS = ["shirt_mean", "hoody_mean", "dress_pencil", "js_mean_all"]
_CACHE: dict = {}


def meshed(garmentcode_dir, name, h):
    key = (name, h)
    if key not in _CACHE:
        p = load_pattern(garmentcode_dir / "patterns" / f"{name}_specification.json")
        t0 = time.perf_counter()
        m = mesh_pattern(p, h)
        _CACHE[key] = (p, m, time.perf_counter() - t0)
    return _CACHE[key]


def arc_fraction(panel, edge_index, points, resolution=4096):
    """Arc-length fraction along an edge of points lying on it (nearest point of a fine polyline) and
    distance."""
    a, b = panel.edge_endpoints(edge_index)
    poly = panel.edges[edge_index].evaluate(a, b, np.linspace(0.0, 1.0, resolution + 1))
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    d, k = cKDTree(poly).query(points)
    return s[k] / s[-1], d


def triangle_min_angles(t):
    """(F,) smallest angle (degrees) of triangles t (F, 3, 2)."""
    e = [t[:, 1] - t[:, 0], t[:, 2] - t[:, 1], t[:, 0] - t[:, 2]]
    ang = []
    for i in range(3):
        u, v = -e[i - 1], e[i]
        c = (u * v).sum(-1) / (np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1))
        ang.append(np.degrees(np.arccos(np.clip(c, -1, 1))))
    return np.min(ang, axis=0)


@pytest.mark.parametrize("h", [0.01, 0.005])
@pytest.mark.parametrize("name", SPECS)
def test_mesh_spec(garmentcode_dir, name, h):
    pattern, mesh, seconds = meshed(garmentcode_dir, name, h)
    print(f"{name} at {h * 1000:.0f} mm: {mesh.num_vertices} vertices, {mesh.num_faces} faces, "
          f"{mesh.seam_pairs.shape[0]} seam pairs, {seconds:.2f} s")
    mesh.validate()  # manifold, no degenerate triangles (3D and rest), seams on the boundary
    assert mesh.panel_names == tuple(pattern.panels)
    p = mesh.p.numpy()
    x = mesh.x.numpy()
    vpid = mesh.vertex_panel_ids.numpy()
    # 3D positions are the placed rest positions
    for k, panel in enumerate(pattern.panels.values()):
        sel = vpid == k
        np.testing.assert_allclose(x[sel], panel.to_3d(p[sel]), atol=1e-12)
    # every face normal points outward like its panel (counter-clockwise seen from outside)
    for k, panel in enumerate(pattern.panels.values()):
        outward = panel.rotation_matrix()[:, 2] * np.sign(panel.area())
        n = mesh.face_normals[mesh.panel_ids == k].numpy()
        assert (n @ outward > 0.999).all()

    # every stitch pairs its two edges' vertices one to one at matching arc-length parameters
    on_boundary = np.zeros(mesh.num_vertices, dtype=bool)
    on_boundary[mesh.boundary_edges.reshape(-1).numpy()] = True
    partners: dict[int, set] = {}
    for i, j in mesh.seam_pairs.tolist():
        partners.setdefault(i, set()).add(j)
        partners.setdefault(j, set()).add(i)
    names = list(pattern.panels)
    counts = edge_segment_counts(pattern, h)
    for s in pattern.stitches:
        sides = []
        for ref in (s.a, s.b):
            panel = pattern.panels[ref.panel]
            cand = np.nonzero(on_boundary & (vpid == names.index(ref.panel)))[0]
            t, d = arc_fraction(panel, ref.edge, p[cand])
            on_edge = d < 2e-4  # fine-polyline vertices are < 0.1 mm apart; interior vertices are mm away
            sides.append(dict(zip(cand[on_edge].tolist(), t[on_edge].tolist())))
        va, vb = sides
        n = counts[s.a.panel][s.a.edge]
        assert len(va) == len(vb) == n + 1 or (s.a.panel == s.b.panel and len(set(va) | set(vb)) < 2 * n + 2)
        for u, tu in va.items():
            match = [v for v in partners.get(u, ()) if v in vb]
            if not match:  # a dart tip is its own partner
                assert u in vb
                continue
            (v,) = match
            tv = vb[v]
            expected = 1.0 - tu if s.orientation is StitchOrientation.OPPOSITE else tu
            assert tv == pytest.approx(expected, abs=2e-3)
        # equal spacing in arc length on each side
        ta = np.sort(list(va.values()))
        np.testing.assert_allclose(np.diff(ta), 1.0 / n, atol=2e-3)

    # quality: Triangle's bound everywhere except at the outline's own very short edges
    ang = triangle_min_angles(p[mesh.faces.numpy()])
    bad = ang < 20.0
    assert bad.mean() < 1e-3
    if bad.any():  # each poor triangle touches a boundary edge much shorter than the target
        f = mesh.faces.numpy()[bad]
        el = np.linalg.norm(p[f] - p[np.roll(f, -1, axis=1)], axis=2)
        assert (el.min(axis=1) < 0.3 * h).all()
    mean_edge = float(mesh.edge_lengths.mean())
    assert abs(mean_edge / h - 1.0) < 0.25
    # total rest area equals the pattern's area
    total = sum(abs(panel.area()) for panel in pattern.panels.values())
    assert float(mesh.rest_face_areas.abs().sum()) == pytest.approx(total, rel=2e-3)


def test_welded_spec_is_one_surface(garmentcode_dir):
    pattern, mesh, _ = meshed(garmentcode_dir, "shirt_mean", 0.01)
    w, index_map = mesh.welded()
    w.validate()
    s = mesh.seam_pairs
    assert torch.equal(index_map[s[:, 0]], index_map[s[:, 1]])
    assert w.num_vertices == int(index_map.max()) + 1 < mesh.num_vertices - s.shape[0] // 2
    # a shirt has four openings: neck, waist and two cuffs
    assert len(w.boundary_loops) == 4


def square_pair(same: bool) -> dict:
    """Two 10 cm squares 4 cm apart sewn along one side, explicitly SAME or OPPOSITE."""
    sq = [[0, 0], [10, 0], [10, 10], [0, 10]]
    edges = [{"endpoints": [i, (i + 1) % 4]} for i in range(4)]
    back_v = sq if same else [[0, 0], [0, 10], [10, 10], [10, 0]]
    back_edge = 1 if same else 2
    o = "same" if same else "opposite"
    return {"pattern": {"panels": {
        "front": {"translation": [0, 0, 2], "rotation": [0, 0, 0], "vertices": sq, "edges": edges},
        "back": {"translation": [0, 0, -2], "rotation": [0, 0, 0], "vertices": back_v, "edges": edges}},
        "stitches": [[{"panel": "front", "edge": 1, "orientation": o},
                      {"panel": "back", "edge": back_edge, "orientation": o}]]},
        "properties": {"units_in_meter": 100}}


@pytest.mark.parametrize("same", [False, True])
def test_orientation_respected(same):
    p = pattern_from_dict(square_pair(same), "pair")
    m = mesh_pattern(p, 0.013, min_angle=30.0)
    m.validate()
    s = m.seam_pairs
    assert s.shape[0] == math.ceil(0.1 / 0.013) + 1
    # paired vertices sit at the same height and x = 0.1, 4 cm apart in z
    np.testing.assert_allclose(m.x[s[:, 0], :2].numpy(), m.x[s[:, 1], :2].numpy(), atol=1e-12)
    np.testing.assert_allclose(m.x[s[:, 0], 0].numpy(), 0.1, atol=1e-12)
    assert torch.allclose((m.x[s[:, 0], 2] - m.x[s[:, 1], 2]).abs(), torch.tensor(0.04, dtype=torch.float64))


def test_dtype_device_and_bad_arguments():
    p = pattern_from_dict(square_pair(False), "pair")
    m = mesh_pattern(p, 0.02, dtype=torch.float32)
    assert m.x.dtype == m.p.dtype == torch.float32 and m.faces.dtype == torch.long
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(InputError, match="edge_length"):
            mesh_pattern(p, bad)
    with pytest.raises(InputError, match="min_angle"):
        mesh_pattern(p, 0.01, min_angle=40.0)
    d = square_pair(False)
    # the last edge crosses edge 1
    d["pattern"]["panels"]["front"]["vertices"] = [[0, 0], [10, 0], [10, 10], [12, 5]]
    with pytest.raises(PatternError, match="crosses itself"):
        mesh_pattern(pattern_from_dict(d, "bad", validate=False), 0.01)
