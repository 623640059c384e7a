"""torchgarment.adjust.acceptance (the helpers of scripts/adjust_acceptance.py): Procrustes deviation, pattern
widths, boundary labels, derived bodies."""

from __future__ import annotations

import math
from types import ModuleType

import numpy as np
import pytest
import torch

from torchgarment.errors import InputError, PatternError


@pytest.fixture(scope="module")
def acc() -> ModuleType:
    from torchgarment.adjust import acceptance

    return acceptance


def _rot(a: float) -> np.ndarray:
    return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])


def test_procrustes_removes_rigid_motion_exactly(acc):
    rng = np.random.default_rng(0)
    b = rng.normal(size=(40, 2))
    a = b @ _rot(0.7).T + np.array([3.0, -2.0])
    assert acc.procrustes_deviation(a, b).max() < 1e-12


def test_procrustes_on_rotated_and_scaled_outline(acc):
    # a rectangle outline rotated, translated and scaled by 1.05, compared with the unscaled one: no scale is
    # removed, so the deviation is exactly the (centred) scaling's displacement 0.05 * |p - centroid|
    t = np.linspace(0.0, 1.0, 11)[:-1]
    w, h = 0.5, 0.6
    b = np.concatenate([np.stack([w * t, 0 * t], 1), np.stack([w + 0 * t, h * t], 1),
                        np.stack([w * (1 - t), h + 0 * t], 1), np.stack([0 * t, h * (1 - t)], 1)])
    a = 1.05 * (b @ _rot(-1.2).T) + np.array([0.3, 0.1])
    d = acc.procrustes_deviation(a, b)
    expected = 0.05 * np.linalg.norm(b - b.mean(axis=0), axis=1)
    np.testing.assert_allclose(d, expected, atol=1e-12)
    # and a scaled target is matched exactly
    assert acc.procrustes_deviation(a, 1.05 * b).max() < 1e-12
    with pytest.raises(ValueError, match="N, 2"):
        acc.procrustes_deviation(a, b[:-1])


def test_procrustes_never_reflects(acc):
    b = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 1.0]])
    a = b * np.array([-1.0, 1.0])  # mirror image: a rotation cannot match it
    assert acc.procrustes_deviation(a, b).max() > 0.1


def _rect_pattern(w: float, h: float, angle: float = 0.0):
    from torchgarment.pattern.spec import Edge, EdgeKind, Panel, SewingPattern

    v = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]]) @ _rot(angle).T
    labels = ["hem", "side_r", "waist", "side_l"]
    edges = [Edge(i, (i + 1) % 4, EdgeKind.LINE, label=labels[i]) for i in range(4)]
    return SewingPattern("rect", {"p": Panel("p", v, edges), "q": Panel("q", 2 * v, edges)}, [], {})


def test_pattern_width_on_rectangle_panels(acc):
    pat = _rect_pattern(0.4, 0.6, angle=0.3)
    assert acc.line_width(pat.panels["p"], "waist", "waist") == pytest.approx(0.4, abs=1e-12)
    assert acc.line_width(pat.panels["p"], "side_r", "side_r") == pytest.approx(0.6, abs=1e-12)
    # hem start (0, 0) to waist end (0, h): the left side
    assert acc.line_width(pat.panels["p"], "hem", "waist") == pytest.approx(0.6, abs=1e-12)
    w = acc.pattern_line_widths(pat, {"waist": ("waist", "waist"), "hem": ("hem", "hem")})
    assert w["waist"] == pytest.approx(0.4 + 0.8, abs=1e-12) and w["hem"] == pytest.approx(1.2, abs=1e-12)
    with pytest.raises(PatternError):
        acc.pattern_line_widths(pat, {"x": ("armhole_r", "armhole_l")})
    with pytest.raises(PatternError):
        acc.line_width(pat.panels["p"], "waist", "armhole_l")


def test_skirt_widths_match_the_draft(acc):
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    w = acc.pattern_line_widths(draft("straight_skirt", chart_row("12")), acc.SKIRT_LINES)
    w2 = acc.pattern_line_widths(draft("straight_skirt", chart_row("20")), acc.SKIRT_LINES)
    # the draft adds a constant ease: the pattern girths grow exactly as the chart's
    assert w2["hips"] - w["hips"] == pytest.approx(chart_row("20")["hips"] - chart_row("12")["hips"],
                                                   abs=1e-9)
    assert w2["waist"] - w["waist"] == pytest.approx(chart_row("20")["waist"] - chart_row("12")["waist"],
                                                     abs=1e-9)
    assert chart_row("12")["hips"] < w["hips"] < chart_row("12")["hips"] + 0.1


def test_boundary_vertex_labels(acc):
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft
    from torchgarment.pattern.meshing import mesh_pattern

    pattern = draft("straight_skirt", chart_row("12"))
    mesh = mesh_pattern(pattern, 0.05)
    verts, labels = acc.boundary_vertex_labels(pattern, mesh)
    p = mesh.p.numpy()
    waist = verts[np.isin(labels, ["waist_r", "waist_l"])]
    # every waistband sample lies on the waist line (y = top of the panel), both corners included
    top = p[:, 1].max()
    assert np.allclose(p[waist, 1], top, atol=1e-9) and len(np.unique(waist)) >= 6
    hem = verts[np.isin(labels, ["hem_r", "hem_l"])]
    assert np.allclose(p[hem, 1], p[:, 1].min(), atol=1e-9)


def test_hip_weight_bump(acc):
    y = torch.tensor([0.5, 0.75, 0.8, 0.84, 0.95, 1.055, 1.2], dtype=torch.float64)
    w = acc.hip_weight(y, 0.84, 1.055, 0.75)
    w = w.tolist()
    assert w[3] == pytest.approx(1.0) and w[0] == pytest.approx(0.0, abs=1e-15)
    assert w[1] == pytest.approx(0.0, abs=1e-15) and w[5] == pytest.approx(0.0, abs=1e-15)
    assert w[6] == pytest.approx(0.0, abs=1e-15) and 0.1 < w[2] < 0.9 and 0.1 < w[4] < 0.9


def test_demo_rejects_bad_input(tmp_path):
    from torchgarment.adjust.demo import run_adjust_demo
    from torchgarment.errors import InputError

    with pytest.raises(InputError, match="chart size"):
        run_adjust_demo(tmp_path, target_size="99")
    with pytest.raises(InputError, match="library garment"):
        run_adjust_demo(tmp_path, garment="kilt")
    with pytest.raises(InputError, match="positive"):
        run_adjust_demo(tmp_path, edge_length=0.0)
    with pytest.raises(InputError, match="iterations"):
        run_adjust_demo(tmp_path, iterations=-1)
    assert not any(tmp_path.iterdir())


@pytest.mark.slow
def test_demo_end_to_end(tmp_path):
    from torchgarment.adjust.demo import run_adjust_demo

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        m = run_adjust_demo(tmp_path / "demo", iterations=4, progress=False)
    finally:
        torch.set_num_threads(n)
    for name in ("pattern.json", "pattern.svg", "pattern.dxf", "garment_base.obj", "garment_target.obj",
                 "target_before.png", "target_after.png", "overlay.png", "metrics.json"):
        assert (tmp_path / "demo" / name).is_file(), name
    assert m["iterations"] == 4 and m["objective_final"] <= m["objective_initial"]
    assert m["garment"] == "straight_skirt" and m["target_size"] == "20"


def test_edges_length_on_rectangle(acc):
    pat = _rect_pattern(0.4, 0.6, angle=0.5)
    assert acc.edges_length(pat, ("waist",)) == pytest.approx(0.4 + 0.8, abs=1e-9)
    assert acc.edges_length(pat, ("waist", "hem")) == pytest.approx(2.4, abs=1e-9)
    with pytest.raises(PatternError):
        acc.edges_length(pat, ("armhole_r",))


def test_line_vertices_are_the_measured_corners(acc):
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft
    from torchgarment.pattern.meshing import mesh_pattern

    pattern = draft("straight_skirt", chart_row("12"))
    mesh = mesh_pattern(pattern, 0.05)
    p = mesh.p.numpy()
    widths = acc.pattern_line_widths(pattern, acc.SKIRT_LINES)
    for line, (first, second) in acc.SKIRT_LINES.items():
        idx = acc.line_vertices(pattern, mesh, first, second)
        assert idx.shape == (2 * len(pattern.panels),)
        pairs = p[idx].reshape(-1, 2, 2)
        assert (np.linalg.norm(pairs[:, 1] - pairs[:, 0], axis=1).sum()
                == pytest.approx(widths[line], abs=1e-9))
    with pytest.raises(PatternError):
        acc.line_vertices(pattern, mesh, "armhole_r", "armhole_l")
    # a mesh without a layout (not made by mesh_pattern) is refused
    plain = type(mesh)(mesh.x, mesh.faces, p=mesh.p, panel_ids=mesh.panel_ids, panel_names=mesh.panel_names)
    with pytest.raises(InputError, match="layout"):
        acc.line_vertices(pattern, plain, "waist_r", "waist_l")


def test_body_girth_at_on_a_cylinder(acc):
    import trimesh

    from torchgarment.body import Body

    r = 0.15
    m = trimesh.creation.cylinder(radius=r, height=1.0, sections=64)
    v = torch.as_tensor(m.vertices[:, [0, 2, 1]] + [0.0, 0.5, 0.0])  # Y up, from y = 0 to 1
    # keep the winding outward after the swap
    f = torch.as_tensor(m.faces[:, [0, 2, 1]].copy(), dtype=torch.long)
    body = Body(vertices=v, faces=f, skeleton=None, skin_weights=None, landmarks={}, params={})
    perimeter = 64 * 2 * r * math.sin(math.pi / 64)  # the inscribed 64-gon
    for y in (0.2, 0.5, 0.83):
        assert acc.body_girth_at(body, y) == pytest.approx(perimeter, rel=1e-9)


def test_bust_body_changes_only_the_bust(acc):
    from torchgarment.body import Body

    base = Body.from_size("12")
    amount = acc.amount_for_girth_change(acc.bust_body, base, "bust", 0.06)
    target = acc.bust_body(base, amount)
    assert 0.03 < amount < 0.1
    assert acc.girth(target, "bust") - acc.girth(base, "bust") == pytest.approx(0.06, abs=1e-3)
    assert abs(acc.girth(target, "waist") - acc.girth(base, "waist")) < 1e-3
    assert acc.girth(target, "hips") == pytest.approx(acc.girth(base, "hips"), abs=1e-9)
    # below the waist landmark nothing moved
    y_waist = float(base.landmarks["waist"][1])
    below = base.vertices[:, 1] <= y_waist
    assert torch.allclose(target.vertices[below], base.vertices[below], rtol=0.0, atol=1e-15)
    # the same solve for the hips
    a_h = acc.amount_for_girth_change(acc.hips_body, base, "hips", 0.06)
    hips = acc.girth(acc.hips_body(base, a_h), "hips")
    assert hips - acc.girth(base, "hips") == pytest.approx(0.06, abs=1e-3)
    with pytest.raises(InputError, match="finite"):
        acc.amount_for_girth_change(acc.bust_body, base, "bust", math.nan)


def _fake_result(pattern, mesh, p_target):
    from types import SimpleNamespace

    return SimpleNamespace(mesh_base=mesh, mesh_target=SimpleNamespace(p=p_target),
                           boundary_index=torch.as_tensor(np.unique(acc_labels(pattern, mesh))))


def acc_labels(pattern, mesh):
    from torchgarment.adjust.acceptance import boundary_vertex_labels

    return boundary_vertex_labels(pattern, mesh)[0]


def test_scaled_outline_deviation_and_edge_moves(acc):
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft
    from torchgarment.pattern.meshing import mesh_pattern

    pattern = draft("straight_skirt", chart_row("12"))
    mesh = mesh_pattern(pattern, 0.05)
    p = mesh.p.double()
    rot = torch.as_tensor(_rot(0.3))
    # the exact manufactured answer, rotated and moved: no deviation; the base pattern itself deviates by
    # 5 % of its distance from the centroid
    dev = acc.scaled_outline_deviation(_fake_result(pattern, mesh, 1.05 * p @ rot.T + 0.2), 1.05)
    assert set(dev) == set(pattern.panels)
    for d in dev.values():
        assert d["max_m"] < 1e-12 and 0.01 < d["unadjusted_max_m"] < 0.05 and 0.5 < d["size_m"] < 1.0
    # a pattern moved by (3 mm, 4 mm): the waistband moves 5 mm, its shape not at all
    moved = acc.edge_moves(pattern, _fake_result(pattern, mesh, p + torch.tensor([0.003, 0.004],
                                                                                 dtype=p.dtype)),
                           ("waist_r", "waist_l"))
    assert moved["max_m"] == pytest.approx(0.005, abs=1e-12) and moved["shape_max_m"] < 1e-12
    # widening the panels by 1 % about their centre line changes the waistband's shape: its ends move by
    # 1 % of the half waist width, and no rigid motion of the symmetric band undoes that
    q = p.clone()
    q[:, 0] *= 1.01
    widened = acc.edge_moves(pattern, _fake_result(pattern, mesh, q), ("waist_r", "waist_l"))
    half_waist = max(acc.line_width(pn, "waist_r", "waist_l") for pn in pattern.panels.values()) / 2
    assert widened["max_m"] == pytest.approx(0.01 * half_waist, abs=1e-12)
    assert widened["shape_max_m"] == pytest.approx(widened["max_m"], rel=1e-6)
    with pytest.raises(PatternError):
        acc.edge_moves(pattern, _fake_result(pattern, mesh, q), ("armhole_r",))


def test_drafted_deviation_of_a_pattern_and_of_a_grade(acc):
    """Against itself or a rigidly moved copy: 0; one corner moved by 1 cm: the largest deviation is at that
    corner and at most 1 cm; against a grade ``base + (drafted_target - drafted_base)``: 0 for the pattern
    that makes exactly that change, and the drafts' own corner changes for the base."""
    import copy

    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    base, big = draft("straight_skirt", chart_row("12")), draft("straight_skirt", chart_row("16"))
    assert all(d["max_m"] < 1e-12 for d in acc.drafted_deviation(base, base).values())
    moved = copy.deepcopy(base)
    for p in moved.panels.values():
        p.vertices = p.vertices @ _rot(0.3).T + np.array([0.5, -0.2])
    assert all(d["max_m"] < 1e-12 for d in acc.drafted_deviation(moved, base).values())
    bent = copy.deepcopy(base)
    labels = [e.label for e in bent.panels["skirt_front"].edges]
    corner = bent.panels["skirt_front"].edges[labels.index("side_low_r")].start  # the hem's right corner
    bent.panels["skirt_front"].vertices[corner] += np.array([0.0, 0.01])
    dev = acc.drafted_deviation(bent, base)
    assert 0.005 < dev["skirt_front"]["max_m"] <= 0.01 and dev["skirt_front"]["worst_corner"] == "side_low_r"
    assert dev["skirt_back"]["max_m"] < 1e-12
    graded = copy.deepcopy(base)
    for name, p in graded.panels.items():
        p.vertices = base.panels[name].vertices + big.panels[name].vertices - base.panels[name].vertices
    grade = (base, base, big)
    assert all(d["max_m"] < 1e-12 for d in acc.drafted_deviation(graded, None, grade=grade).values())
    via_grade, direct = acc.drafted_deviation(base, None, grade=grade), acc.drafted_deviation(base, big)
    for name in direct:
        assert via_grade[name]["max_m"] == pytest.approx(direct[name]["max_m"], abs=1e-12)
        assert via_grade[name]["worst_corner"] == direct[name]["worst_corner"]
    with pytest.raises(PatternError, match="counterpart"):
        acc.drafted_deviation(draft("aline_skirt", chart_row("12")), draft("tshirt", chart_row("12")))


def test_draft_measurements_take_the_body_landmark_heights(acc):
    from torchgarment.body import Body
    from torchgarment.pattern.library import draft

    body = Body.from_size("12")
    m, dm = body.measurements(), acc.draft_measurements(body)
    floor = float(body.vertices[:, 1].min())
    assert dm.height == pytest.approx(m.height) and dm.hips == pytest.approx(m.hips)
    assert dm.waist_height == pytest.approx(float(m.planes["waist"].point[1]) - floor)
    assert dm.hip_height == pytest.approx(float(m.planes["hips"].point[1]) - floor)
    assert dm.knee_height == pytest.approx(0.285 * m.height)
    skirt = draft("straight_skirt", dm)
    assert set(skirt.panels) == {"skirt_front", "skirt_back"}
