"""torchgarment.adjust.fit: construction lines, the fit of a drape at them, fit preservation rows."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchgarment.errors import InputError


# ---------------------------------------------------------------------------------------------- lines
@pytest.mark.parametrize("garment,expected", [
    ("straight_skirt", ("waist", "hips")), ("aline_skirt", ("waist", "hips")),
    ("trousers", ("waist", "hips")),
    ("tshirt", ("bust", "waist", "hem")), ("sheath_dress", ("bust", "waist", "hips", "hem")),
    ("bodysuit", ("bust", "waist", "hips")),
])
def test_construction_lines_of_every_library_garment(garment, expected):
    from torchgarment.adjust.acceptance import line_vertices, pattern_line_widths
    from torchgarment.adjust.fit import construction_lines
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft, draft_options, list_garments
    from torchgarment.pattern.meshing import mesh_pattern

    assert set(list_garments()) <= {"straight_skirt", "aline_skirt", "trousers", "tshirt", "sheath_dress",
                                     "bodysuit"}
    row = chart_row("12")
    pattern = draft(garment, row)
    lines = construction_lines(pattern)
    assert tuple(lines) == expected
    widths = pattern_line_widths(pattern, lines)
    mesh = mesh_pattern(pattern, 0.05)
    y = mesh.x[:, 1].numpy()
    options = draft_options(garment)
    for line in lines:
        idx = line_vertices(pattern, mesh, *lines[line])
        # every panel contributes its two corners, and the corners of a line are at one height of the placed
        # pattern (horizontal construction lines), at the draft's height for the line
        assert idx.size >= 4 and np.ptp(y[idx]) < 1e-9
        if line in ("waist", "hips"):
            heights = pattern.metadata["measurements"]
            assert y[idx[0]] == pytest.approx(heights[f"{'hip' if line == 'hips' else line}_height"],
                                              abs=1e-6)
        if line in ("waist", "hips", "bust"):
            # the girth is the chart's plus the draft's ease for that line (a constant-ease draft)
            ease = options.get(f"{'hip' if line == 'hips' else line}_ease", 0.0)
            if garment == "tshirt" and line == "waist":  # a straight side seam from underarm to waist
                assert widths["waist"] == pytest.approx(widths["bust"], abs=1e-9)
            else:
                assert widths[line] == pytest.approx(row[line] + ease, abs=1e-9), line
    if "hem" in lines:
        assert widths["hem"] >= widths.get("hips", widths["waist"]) - 1e-9


def test_construction_lines_of_unknown_patterns():
    from torchgarment.adjust.fit import construction_lines
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    pattern = draft("straight_skirt", chart_row("12"))
    pattern.name, pattern.metadata = "my skirt", {}
    # found by its edge labels
    assert construction_lines(pattern) == {"waist": ("waist_r", "waist_l"),
                                           "hips": ("side_hip_r", "side_hip_l")}
    for garment in ("tshirt", "sheath_dress", "bodysuit", "trousers"):
        other = draft(garment, chart_row("12"))
        other.name, other.metadata = "mine", {}
        assert construction_lines(other) == construction_lines(draft(garment, chart_row("12"))), garment
    for p in pattern.panels.values():
        for e in p.edges:
            e.label = "x" + e.label
    assert construction_lines(pattern) == {}


def test_mirrored_panels_measure_the_same_line():
    # trousers: the right legs list their edges in the reverse order; the hip line still joins the side
    # corner to the centre corner
    from torchgarment.adjust.acceptance import line_corners, line_width
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    pattern = draft("trousers", chart_row("12"))
    for panel in pattern.panels.values():
        (i, a), (j, b) = line_corners(panel, "side_hip", "centre")
        p0, p1 = panel.edge_endpoints(i)[a], panel.edge_endpoints(j)[b]
        assert p0[1] == pytest.approx(p1[1], abs=1e-9)  # both at the hip line
        assert line_width(panel, "side_hip", "centre") == line_width(panel, "centre", "side_hip")
        assert line_width(panel, "side_hip", "centre") > 0.15


# ---------------------------------------------------------------------------------------------- synthetic
def _cylinder_body(r: float, sections: int = 64):
    import trimesh

    from torchgarment.body import Body

    m = trimesh.creation.cylinder(radius=r, height=1.0, sections=sections)
    v = torch.as_tensor(m.vertices[:, [0, 2, 1]] + [0.0, 0.5, 0.0])
    f = torch.as_tensor(m.faces[:, [0, 2, 1]].copy(), dtype=torch.long)
    return Body(vertices=v, faces=f, skeleton=None, skin_weights=None, landmarks={}, params={})


def _tube(r: float, h: float, y0: float):
    """A tube of two w x h panels (w = pi r), meshed, and its drape: each panel wrapped on a half cylinder
    of radius ``r``, bottom at ``y0``."""
    from torchgarment.pattern.meshing import mesh_pattern
    from torchgarment.pattern.spec import Edge, EdgeKind, Panel, SewingPattern

    w = math.pi * r
    v = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
    labels = ["hem", "side_r", "waist", "side_l"]
    edges = [Edge(i, (i + 1) % 4, EdgeKind.LINE, label=labels[i]) for i in range(4)]
    pattern = SewingPattern("tube", {"front": Panel("front", v, edges),
                                     "back": Panel("back", v, edges, translation=[0.0, 0.0, -1.0])}, [], {})
    mesh = mesh_pattern(pattern, 0.05)
    p = mesh.p.numpy()
    k = np.zeros(len(p))
    for i, name in enumerate(mesh.panel_names):
        k[np.unique(mesh.faces[mesh.panel_ids == i].numpy())] = i
    theta = math.pi * (k + p[:, 0] / w)
    x = np.stack([r * np.cos(theta), y0 + p[:, 1], r * np.sin(theta)], axis=1)
    return pattern, mesh, torch.as_tensor(x)


def test_measure_fit_tube_on_cylinder():
    from torchgarment.adjust.fit import measure_fit

    rb, rg, n = 0.15, 0.16, 64
    body = _cylinder_body(rb, n)
    pattern, mesh, x = _tube(rg, 0.3, 0.45)
    lines = {"waist": ("waist", "waist"), "hem": ("hem", "hem")}
    fit = measure_fit(pattern, mesh, x, body, lines=lines, landmarks={"waist": 0.72, "hips": 0.5})
    body_girth = n * 2 * rb * math.sin(math.pi / n)  # the inscribed 64-gon
    assert body_girth == pytest.approx(2 * math.pi * rb, rel=2e-3)
    w = fit["waist"]
    assert w.height_m == pytest.approx(0.75, abs=1e-12)
    assert w.pattern_girth_m == pytest.approx(2 * math.pi * rg, abs=1e-12)
    assert w.body_girth_m == pytest.approx(body_girth, rel=1e-9)
    assert w.ease_m == pytest.approx(2 * math.pi * (rg - rb), abs=2 * math.pi * rb * 2e-3)
    assert w.ease_m == pytest.approx(2 * math.pi * rg - body_girth, abs=1e-12)
    assert (w.landmark, w.placement_m) == ("waist", pytest.approx(0.03, abs=1e-12))
    h = fit["hem"]
    assert h.height_m == pytest.approx(0.45, abs=1e-12) and h.landmark == "hips"
    assert h.placement_m == pytest.approx(-0.05, abs=1e-12)
    assert h.landmark_heights == {"waist": 0.72, "hips": 0.5}
    with pytest.raises(InputError, match="x must be"):
        measure_fit(pattern, mesh, x[:-1], body, lines=lines, landmarks={"waist": 0.7})
    with pytest.raises(InputError, match="landmark"):
        measure_fit(pattern, mesh, x, body, lines=lines, landmarks={})


def test_body_girth_below_the_crotch_goes_around_both_legs():
    # two cylinders side by side (legs, centres at x = +-d): no loop encloses the axis, the tape's hull is
    # 2 pi r + 4 d (polygon: the two half 64-gons plus the two straight spans)
    import trimesh

    from torchgarment.adjust.acceptance import body_girth_at
    from torchgarment.body import Body

    r, d, n = 0.06, 0.1, 64
    parts = []
    for sx in (-d, d):
        m = trimesh.creation.cylinder(radius=r, height=1.0, sections=n)
        m.apply_translation([sx, 0.0, 0.5])
        parts.append(m)
    m = trimesh.util.concatenate(parts)
    body = Body(vertices=torch.as_tensor(m.vertices[:, [0, 2, 1]]),
                faces=torch.as_tensor(m.faces[:, [0, 2, 1]].copy(), dtype=torch.long), skeleton=None,
                skin_weights=None, landmarks={}, params={})
    half_polygon = n * 2 * r * math.sin(math.pi / n)
    assert body_girth_at(body, 0.4) == pytest.approx(half_polygon + 4 * d, rel=2e-3)


# ---------------------------------------------------------------------------------------------- rows
def _lf(line, y, pg, bg, landmark, place, heights):
    from torchgarment.adjust.fit import LineFit

    return LineFit(line, y, pg, bg, pg - bg, landmark, place, heights)


def test_fit_rows_arithmetic_and_pass():
    from torchgarment.adjust.fit import ROW_KEYS, fit_rows

    hb = {"waist": 1.05, "hips": 0.85, "bust": 1.2}
    ht = {"waist": 1.07, "hips": 0.86, "bust": 1.24}
    base = {"waist": _lf("waist", 1.06, 0.70, 0.68, "waist", 0.01, hb),
            "hips": _lf("hips", 0.88, 0.96, 0.92, "hips", 0.03, hb)}
    target = {"waist": _lf("waist", 1.085, 0.75, 0.725, "waist", 0.015, ht),   # ease +5 mm: pass
              "hips": _lf("hips", 0.96, 1.02, 0.96, "waist", -0.11, ht)}      # ease +2 cm, other landmark
    rows = fit_rows(base, target, {"waist": 0.05})
    assert [r["line"] for r in rows] == ["waist", "hips"] and all(tuple(r) == ROW_KEYS for r in rows)
    w, h = rows
    assert w["ease_change_m"] == pytest.approx(0.005, abs=1e-12)
    assert w["pattern_change_m"] == pytest.approx(0.05, abs=1e-12)
    assert w["body_change_m"] == pytest.approx(0.045, abs=1e-12)
    assert w["placement_change_m"] == pytest.approx(0.005, abs=1e-12)
    assert w["chart_change_m"] == 0.05 and w["pass"] is True
    assert (w["pattern_girth_m"], w["body_girth_m"]) == (0.75, 0.725)
    # the ease change is the pattern change minus the body change, identically
    assert h["ease_change_m"] == pytest.approx(h["pattern_change_m"] - h["body_change_m"], abs=1e-15)
    assert h["ease_change_m"] == pytest.approx(0.02, abs=1e-12) and h["pass"] is False
    # the target's placement is taken against the base's landmark (hips: 0.96 - 0.86 = 0.10)
    assert h["placement_change_m"] == pytest.approx(0.10 - 0.03, abs=1e-12)
    assert math.isnan(h["chart_change_m"])
    # the tolerance decides: 2.5 cm lets the ease pass but not the 7 cm placement
    assert fit_rows(base, target, None, tolerance_m=0.025)[1]["pass"] is False
    assert fit_rows(base, target, None, tolerance_m=0.08)[1]["pass"] is True
    # placement alone fails a row
    t2 = dict(target, waist=_lf("waist", 1.1, 0.75, 0.725, "waist", 0.03, ht))
    r2 = fit_rows(base, t2, None)[0]
    assert r2["ease_change_m"] == pytest.approx(0.005) and r2["placement_change_m"] == pytest.approx(0.02)
    assert r2["pass"] is False
    # identical fits pass with zero changes
    same = fit_rows(base, base, None)
    assert all(r["pass"] and r["ease_change_m"] == 0 and r["placement_change_m"] == 0 for r in same)
    # NaN fails
    t3 = dict(target, waist=_lf("waist", 1.085, math.nan, 0.725, "waist", 0.015, ht))
    assert fit_rows(base, t3, None)[0]["pass"] is False
    with pytest.raises(InputError, match="no line"):
        fit_rows(base, {"waist": target["waist"]}, None)
    with pytest.raises(InputError, match="tolerance"):
        fit_rows(base, target, None, tolerance_m=0.0)


def test_chart_changes():
    from torchgarment.adjust.fit import chart_changes
    from torchgarment.body.size_chart import chart_row

    b, t = chart_row("12"), chart_row("16")
    c = chart_changes(b, t, {"waist": ("a", "b"), "hem": ("c", "d"), "bust": ("e", "f")})
    assert set(c) == {"waist", "bust"} and c["bust"] == pytest.approx(t["bust"] - b["bust"], abs=1e-12)
    assert 0.05 < c["waist"] < 0.12


# ---------------------------------------------------------------------------------------------- real drape
@pytest.fixture(scope="module")
def skirt_drape():
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft
    from torchgarment.sim.drape import DrapeSettings, drape

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        body = Body.from_size("12")
        pattern = draft("straight_skirt", chart_row("12"))
        r = drape(pattern, body, settings=DrapeSettings(edge_length=0.05, voxel_size=0.01))
    finally:
        torch.set_num_threads(n)
    return body, pattern, r


def test_measure_fit_on_a_real_skirt_drape(skirt_drape):
    from torchgarment.adjust.fit import fit_rows, landmark_heights, measure_fit
    from torchgarment.body.size_chart import chart_row

    body, pattern, r = skirt_drape
    assert r.converged
    fit = measure_fit(pattern, r.mesh, r.x, body)
    lm = landmark_heights(body)
    assert lm["hips"] < lm["waist"] < lm["bust"]
    w, h = fit["waist"], fit["hips"]
    assert w.landmark == "waist" and abs(w.placement_m) < 0.05
    assert h.landmark == "hips" and h.height_m < w.height_m
    assert w.ease_m > 0 and h.ease_m > 0
    # the garment girths are the draft's, the body's are near the chart's at the landmark planes
    assert w.pattern_girth_m == pytest.approx(chart_row("12")["waist"] + 0.01, abs=1e-9)
    assert h.ease_m < 0.15 and w.ease_m < 0.1
    assert all(row["pass"] for row in fit_rows(fit, fit, None))


def test_adjustment_fit_of_an_unchanged_result(skirt_drape):
    from types import SimpleNamespace

    from torchgarment.adjust.fit import adjustment_fit

    body, pattern, r = skirt_drape
    res = SimpleNamespace(pattern=pattern, base_pattern=pattern, mesh_base=r.mesh, mesh_target=r.mesh)
    base, target, rows = adjustment_fit(res, body, body, {"waist": 0.0})
    assert list(base) == ["waist", "hips"] and base["hips"].ease_m == target["hips"].ease_m
    assert all(row["pass"] and row["pattern_change_m"] == 0 and row["body_change_m"] == 0 for row in rows)
    assert rows[0]["chart_change_m"] == 0.0
    with pytest.raises(InputError, match="no pattern"):
        adjustment_fit(SimpleNamespace(pattern=None, base_pattern=None), body, body)


def test_line_targets_keep_the_base_ease_and_placement():
    """Same body: the targets are the base girths and heights; a body scaled by s about its feet, with the
    garment scaled alike: each line's target height is where the scaled landmark plane puts it, and its
    target girth grows by the body's girth change there (about (s - 1) times its girth)."""
    from torchgarment.adjust.acceptance import body_girth_at, pattern_line_widths, scaled_body
    from torchgarment.adjust.fit import construction_lines, landmark_heights, line_targets
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft
    from torchgarment.pattern.meshing import mesh_pattern

    pattern = draft("straight_skirt", chart_row("12"))
    mesh = mesh_pattern(pattern, 0.05)
    body = Body.from_size("12")
    widths = pattern_line_widths(pattern, construction_lines(pattern))
    same = line_targets(pattern, mesh, mesh.x, mesh.x, body, body, guides={})
    assert same.lines == ["waist", "hips"] and not same.skipped
    assert same.landmark == ["waist", "hips"]
    assert same.body_change_m == [0.0, 0.0]
    assert same.target_height_m == pytest.approx(same.base_height_m, abs=1e-12)
    assert same.target_girth_m == pytest.approx([widths["waist"], widths["hips"]], abs=1e-9)
    s = 1.05
    big = scaled_body(body, s)
    c = torch.stack([body.vertices[:, 0].mean(), body.vertices[:, 1].min(), body.vertices[:, 2].mean()])
    xs = c + s * (mesh.x - c)
    lm_b, lm_t = landmark_heights(body), landmark_heights(big)
    for at_landmarks in (True, False):
        out = line_targets(pattern, mesh, mesh.x, xs, body, big, at_landmarks=at_landmarks, guides={})
        for i, line in enumerate(out.lines):
            yb, lm = out.base_height_m[i], out.landmark[i]
            assert out.transfer_height_m[i] == pytest.approx(float(c[1]) + s * (yb - float(c[1])))
            expected = lm_t[lm] + yb - lm_b[lm] if at_landmarks else out.transfer_height_m[i]
            assert out.target_height_m[i] == pytest.approx(expected, abs=1e-12)
            change = body_girth_at(big, out.target_height_m[i]) - body_girth_at(body, yb)
            assert out.body_change_m[i] == pytest.approx(change, abs=1e-12)
            assert out.body_change_m[i] == pytest.approx((s - 1) * body_girth_at(body, yb), abs=5e-3), line
            assert out.target_girth_m[i] == pytest.approx(widths[line] + out.body_change_m[i], abs=1e-9)
    d = out.to_dict()
    assert set(d["lines"]) == {"waist", "hips"} and d["skipped"] == {}


def test_fit_scale_asks_a_scaled_body_for_the_scaled_fit():
    """``fit_scale``: 1 between the chart bodies (one height) and for ``none``, the height ratio onto a body
    scaled by s. With it, the line targets on the body scaled by s about its feet are the base garment scaled
    alike: every line (and every held hem vertex) at s times its base height above the feet, every girth s
    times the base pattern's; ``scale=1`` is the absolute rule bit for bit."""
    from torchgarment.adjust.acceptance import pattern_line_widths, scaled_body
    from torchgarment.adjust.fit import FitScale, construction_lines, fit_scale, guide_lines, line_targets
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft
    from torchgarment.pattern.meshing import mesh_pattern

    body = Body.from_size("12")
    assert fit_scale(body, Body.from_size("20")) == 1.0 and fit_scale(body, Body.from_size("6")) == 1.0
    s = 1.05
    big = scaled_body(body, s)
    assert fit_scale(body, big) == pytest.approx(s, abs=1e-6)
    assert fit_scale(body, big, "none") == 1.0 and fit_scale(body, big, FitScale.NONE) == 1.0
    with pytest.raises(InputError, match="unknown fit scale 'girth'"):
        fit_scale(body, big, "girth")
    pattern = draft("straight_skirt", chart_row("12"))
    mesh = mesh_pattern(pattern, 0.05)
    c = torch.stack([body.vertices[:, 0].mean(), body.vertices[:, 1].min(), body.vertices[:, 2].mean()])
    xs = c + s * (mesh.x - c)
    lines = {**construction_lines(pattern),
             **{k: (g.first, g.second) for k, g in guide_lines(pattern).items()}}
    widths = pattern_line_widths(pattern, lines)
    out = line_targets(pattern, mesh, mesh.x, xs, body, big, scale=fit_scale(body, big))
    assert out.lines == ["waist", "hips", "hem"]
    for i, line in enumerate(out.lines):
        assert out.target_height_m[i] == pytest.approx(out.transfer_height_m[i], abs=2e-3), line
        assert out.target_girth_m[i] == pytest.approx(s * widths[line], abs=2e-3), line
    held = out.held_vertices
    assert np.allclose(out.held_height_m, xs[held, 1].numpy(), atol=2e-3)
    absolute = line_targets(pattern, mesh, mesh.x, xs, body, big)
    one = line_targets(pattern, mesh, mesh.x, xs, body, big, scale=1.0)
    assert one.target_girth_m == absolute.target_girth_m and one.target_height_m == absolute.target_height_m
    assert np.array_equal(one.held_height_m, absolute.held_height_m)
    # absolute lengths fall short by (s - 1) times the base ease at each line
    hips = out.lines.index("hips")
    assert out.target_girth_m[hips] - absolute.target_girth_m[hips] > 0.5e-3
    with pytest.raises(InputError, match="scale"):
        line_targets(pattern, mesh, mesh.x, xs, body, big, scale=0.0)


def test_guide_line_keeps_the_hem_on_the_leg_and_follows_the_hip_grade():
    """The skirt's hem (a guide line): its target height keeps its height above the knee (the same height on
    a body of the same height, whatever the transfer does), its target girth takes the hip line's change;
    ``of_kind`` splits the lines with their corners; ``guides={}`` leaves it out."""
    from torchgarment.adjust.acceptance import pattern_line_widths
    from torchgarment.adjust.fit import KNEE_HEIGHT_RATIO, guide_lines, knee_height, line_targets
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft
    from torchgarment.pattern.meshing import mesh_pattern

    pattern = draft("straight_skirt", chart_row("12"))
    assert set(guide_lines(pattern)) == {"hem"} and guide_lines(draft("tshirt", chart_row("12"))) == {}
    mesh = mesh_pattern(pattern, 0.05)
    base, target = Body.from_size("12"), Body.from_size("16")
    assert knee_height(base) == pytest.approx(KNEE_HEIGHT_RATIO * base.measurements().height, abs=1e-6)
    assert knee_height(target) == pytest.approx(knee_height(base), abs=1e-3)  # one chart height
    xt = mesh.x + torch.tensor([0.0, -0.04, 0.0])  # a transfer that lowers everything by 4 cm
    out = line_targets(pattern, mesh, mesh.x, xt, base, target)
    assert out.lines == ["waist", "hips", "hem"] and out.kind == ["construction", "construction", "guide"]
    h = out.lines.index("hem")
    assert out.landmark[h] == "knee" and out.girth_slope[h] == 0.0
    from torchgarment.adjust.acceptance import body_girth_at
    from torchgarment.adjust.fit import GIRTH_SLOPE_STEP_M as d

    for i in range(2):  # the construction lines: the target body's girth slope at the target height
        y = out.target_height_m[i]
        assert out.girth_slope[i] == pytest.approx(
            (body_girth_at(target, y + d) - body_girth_at(target, y - d)) / (2 * d), abs=1e-12)
    assert out.target_height_m[h] == pytest.approx(
        knee_height(target) + out.base_height_m[h] - knee_height(base), abs=1e-12)
    assert out.transfer_height_m[h] == pytest.approx(out.base_height_m[h] - 0.04, abs=1e-9)
    assert out.body_change_m[h] == out.body_change_m[out.lines.index("hips")] > 0.05
    hem_width = pattern_line_widths(pattern, {"hem": ("side_low_r", "side_low_l")})["hem"]
    assert out.target_girth_m[h] == pytest.approx(hem_width + out.body_change_m[h], abs=1e-9)
    guide, construction = out.of_kind("guide"), out.of_kind("construction")
    assert guide.lines == ["hem"] and construction.lines == ["waist", "hips"]
    assert guide.line_of.tolist() == [0] * len(guide.line_of) and len(guide.corners) == 2  # two panels
    assert np.array_equal(guide.corners, out.corners[out.line_of == h])
    assert construction.target_girth_m == out.target_girth_m[:2]
    assert out.to_dict()["lines"]["hem"]["kind"] == "guide"
    # every hem vertex is held at its base height moved like the line (the hem stays level)
    hem_vertices = guide.held_vertices
    assert set(guide.corners.reshape(-1).tolist()) <= set(hem_vertices.tolist())
    assert len(hem_vertices) > len(guide.corners.reshape(-1)) and len(construction.held_vertices) == 0
    shift = out.target_height_m[h] - out.base_height_m[h]
    assert np.allclose(guide.held_height_m, mesh.x[hem_vertices, 1].numpy() + shift, atol=1e-12)
    # targets built by hand, without kinds or slopes: every line a construction line of slope 0
    from dataclasses import replace

    bare = replace(out, kind=[], girth_slope=[])
    assert bare.per_line("kind") == ["construction"] * 3 and bare.per_line("girth_slope") == [0.0] * 3
    assert bare.of_kind("construction").lines == ["waist", "hips", "hem"]
    assert bare.of_kind("guide").lines == []
    assert guide_lines(draft("aline_skirt", chart_row("12"))) == guide_lines(pattern)
    free = line_targets(pattern, mesh, mesh.x, xt, base, target, at_landmarks=False)
    assert free.target_height_m[h] == pytest.approx(free.transfer_height_m[h], abs=1e-12)
