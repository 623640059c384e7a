"""SVG pattern sheets: well-formed XML, real scale, true curves where the panel's edges are, layout, marks."""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from torchgarment.errors import PatternError
from torchgarment.pattern.spec import (
    Edge,
    EdgeKind,
    EdgeRef,
    Notch,
    Panel,
    SewingPattern,
    Stitch,
    StitchOrientation,
)
from torchgarment.pattern.svg import save_svg, stitch_marks, svg_panel_layout

NS = {"s": "http://www.w3.org/2000/svg"}


def _pattern() -> SewingPattern:
    quad = Panel("front", [[0, 0], [0.4, 0], [0.4, 0.6], [0, 0.6]], [
        Edge(0, 1), Edge(1, 2, EdgeKind.QUADRATIC, controls=[[0.5, 0.15]]), Edge(2, 3), Edge(3, 0)],
        notches=[Notch(0, 0.5), Notch(2, 0.25)])
    curvy = Panel("back", [[0, 0], [0.4, 0], [0.4, 0.6], [0, 0.6]], [
        Edge(0, 1, EdgeKind.CUBIC, controls=[[0.3, -0.1], [0.7, 0.1]]), Edge(1, 2),
        Edge(2, 3, EdgeKind.ARC, arc=(0.25, False, True)), Edge(3, 0)], grainline=[1, 1])
    big_arc = Panel("cap", [[0, 0], [0.2, 0], [0.2, 0.1]], [
        Edge(0, 1, EdgeKind.ARC, arc=(0.15, True, False)), Edge(1, 2), Edge(2, 0)])
    return SewingPattern("test", {"front": quad, "back": curvy, "cap": big_arc}, [
        Stitch(EdgeRef("front", 3), EdgeRef("back", 1)),
        Stitch(EdgeRef("front", 0), EdgeRef("back", 0), StitchOrientation.SAME)])


def _svg_arc(p0, rx, large, sweep, p1, n):
    """Points of an SVG elliptical arc with rx = ry and no rotation (SVG spec F.6.5)."""
    x1p = (p0 - p1) / 2
    r = max(rx, float(np.linalg.norm(x1p)))
    sq = max(r * r - x1p @ x1p, 0.0) / (x1p @ x1p)
    coef = (-1 if large == sweep else 1) * math.sqrt(sq)
    cp = coef * np.array([x1p[1], -x1p[0]])
    c = cp + (p0 + p1) / 2
    t0 = math.atan2(p0[1] - c[1], p0[0] - c[0])
    t1 = math.atan2(p1[1] - c[1], p1[0] - c[0])
    dt = t1 - t0
    if sweep and dt < 0:
        dt += 2 * math.pi
    if not sweep and dt > 0:
        dt -= 2 * math.pi
    ang = t0 + np.linspace(0, 1, n) * dt
    return c + r * np.stack([np.cos(ang), np.sin(ang)], axis=1)


def _sample_path(d: str, n: int = 200) -> tuple[np.ndarray, list[np.ndarray]]:
    """Dense points of an SVG path with M/L/Q/C/A/Z commands and the end point of every command."""
    tokens = re.findall(r"[MLQCAZ]|-?\d+(?:\.\d+)?", d)
    pts, ends, cur, i = [], [], None, 0
    t = np.linspace(0, 1, n)[:, None]
    while i < len(tokens):
        cmd = tokens[i]
        i += 1
        nums = []
        while i < len(tokens) and tokens[i] not in "MLQCAZ":
            nums.append(float(tokens[i]))
            i += 1
        if cmd == "M":
            cur = np.array(nums[:2])
            ends.append(cur)
            continue
        if cmd == "Z":
            continue
        if cmd == "L":
            end = np.array(nums)
            seg = cur + t * (end - cur)
        elif cmd == "Q":
            c, end = np.array(nums[:2]), np.array(nums[2:])
            seg = (1 - t) ** 2 * cur + 2 * (1 - t) * t * c + t**2 * end
        elif cmd == "C":
            c1, c2, end = np.array(nums[:2]), np.array(nums[2:4]), np.array(nums[4:])
            seg = (1 - t) ** 3 * cur + 3 * (1 - t) ** 2 * t * c1 + 3 * (1 - t) * t**2 * c2 + t**3 * end
        else:
            rx, _, _, large, sweep = nums[:5]
            end = np.array(nums[5:7])
            seg = _svg_arc(cur, rx, bool(large), bool(sweep), end, n)
        pts.append(seg)
        ends.append(end)
        cur = end
    return np.concatenate(pts), ends


def _dist_to_polyline(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Distance (n,) of points (n, 2) to an open polyline (m, 2)."""
    a, b = poly[:-1], poly[1:]
    ab = b - a
    out = []
    for q in np.array_split(p, max(1, len(p) // 256)):
        t = np.clip(((q[:, None] - a[None]) * ab[None]).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-300)[None],
                    0, 1)
        out.append(np.linalg.norm(q[:, None] - (a[None] + t[..., None] * ab[None]), axis=-1).min(axis=1))
    return np.concatenate(out)


@pytest.fixture()
def sheet(tmp_path):
    pat = _pattern()
    path = tmp_path / "p.svg"
    save_svg(path, pat)
    return pat, ET.parse(path).getroot(), path


def test_well_formed_real_scale(sheet):
    pat, root, path = sheet
    assert root.tag == "{http://www.w3.org/2000/svg}svg"
    w, h = root.get("width"), root.get("height")
    assert w.endswith("mm") and h.endswith("mm")
    vb = [float(x) for x in root.get("viewBox").split()]
    assert vb[:2] == [0, 0]
    assert vb[2] == pytest.approx(float(w[:-2])) and vb[3] == pytest.approx(float(h[:-2]))
    _, size = svg_panel_layout(pat)
    assert vb[2] == pytest.approx(1000 * size[0], abs=1e-3) and vb[3] == pytest.approx(1000 * size[1],
                                                                                       abs=1e-3)
    assert [p.name for p in path.parent.iterdir()] == ["p.svg"]  # atomic: no temporary left behind


def test_outline_paths_are_the_panels(sheet):
    pat, root, _ = sheet
    offsets, size = svg_panel_layout(pat)
    groups = {g.get("data-panel"): g for g in root.findall("s:g", NS)}
    assert set(groups) == set(pat.panels)
    for name, panel in pat.panels.items():
        d = groups[name].find("s:path[@class='outline']", NS).get("d")
        assert {"Q", "C", "A"} & set(d.split()) or name == "front"
        pts_mm, ends = _sample_path(d, 800)

        def to_panel(q):
            return np.stack([q[:, 0] / 1000, size[1] - q[:, 1] / 1000], axis=1) - offsets[name]

        ends = to_panel(np.array(ends))
        order = [e.start for e in panel.edges] + [panel.edges[0].start]
        np.testing.assert_allclose(ends, panel.vertices[order], atol=1e-6)
        svg_pts = to_panel(pts_mm)
        true = np.concatenate([panel.outline(resolution=1500), panel.vertices[:1]])
        assert _dist_to_polyline(svg_pts, true).max() < 2e-6  # every SVG point on the true outline
        assert _dist_to_polyline(true, np.concatenate([svg_pts, svg_pts[:1]])).max() < 2e-6  # and back


def test_layout_has_no_overlap():
    rng = np.random.default_rng(0)
    panels = {}
    for k in range(15):
        w, h = rng.uniform(0.05, 0.6, size=2)
        x0, y0 = rng.uniform(-1, 1, size=2)
        panels[f"p{k}"] = Panel(f"p{k}", [[x0, y0], [x0 + w, y0], [x0 + w, y0 + h], [x0, y0 + h]],
                                [Edge(0, 1), Edge(1, 2), Edge(2, 3), Edge(3, 0)])
    pat = SewingPattern("many", panels)
    offsets, size = svg_panel_layout(pat, margin=0.01)
    boxes = np.stack([np.stack([p.vertices.min(0), p.vertices.max(0)]) + offsets[n]
                      for n, p in panels.items()])
    assert boxes.min() >= 0.01 - 1e-12
    assert np.all(boxes[:, 1] <= size + 1e-12)
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            sep = np.maximum(boxes[j, 0] - boxes[i, 1], boxes[i, 0] - boxes[j, 1]).max()
            assert sep >= 0.01 - 1e-9
    assert size[0] < 3 * size[1] and size[1] < 3 * size[0]  # roughly square sheet, not one long strip


def test_stitch_labels_arrows_notches_grainlines(sheet):
    pat, root, _ = sheet
    labels = [t.text for t in root.iter("{http://www.w3.org/2000/svg}text")
              if t.get("class") == "stitch-label"]
    assert sorted(labels) == ["S0", "S0", "S1", "S1"]
    seams = root.findall(".//s:path[@class='seam']", NS)
    assert sorted((s.get("data-stitch"), s.get("data-edge")) for s in seams) == [
        ("0", "1"), ("0", "3"), ("1", "0"), ("1", "0")]
    assert len(root.findall(".//s:line[@class='notch']", NS)) == 2
    assert len(root.findall(".//s:path[@class='grainline']", NS)) == 3
    marks = stitch_marks(pat)
    for k, s in enumerate(pat.stitches):
        ma, mb = [m for m in marks if m.stitch == k]
        ta = np.diff(pat.panels[s.a.panel].edge_endpoints(s.a.edge), axis=0)[0]
        tb = np.diff(pat.panels[s.b.panel].edge_endpoints(s.b.edge), axis=0)[0]
        assert ma.direction @ ta > 0
        assert (mb.direction @ tb > 0) == (s.orientation is StitchOrientation.SAME)
        for m in (ma, mb):  # the label side points into the panel
            panel = pat.panels[m.panel]
            from matplotlib.path import Path as MplPath
            assert MplPath(panel.outline(64)).contains_point(m.point + 0.01 * m.inward)


def test_bad_input_writes_nothing(tmp_path):
    pat = _pattern()
    pat.stitches.append(Stitch(EdgeRef("front", 1), EdgeRef("nowhere", 0)))
    with pytest.raises(PatternError, match="unknown panel 'nowhere'"):
        save_svg(tmp_path / "bad.svg", pat)
    with pytest.raises(PatternError, match="no panels"):
        save_svg(tmp_path / "bad.svg", SewingPattern("empty", {}))
    assert list(tmp_path.iterdir()) == []
