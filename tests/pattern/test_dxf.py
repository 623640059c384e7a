"""ASTM D6673 / AAMA DXF: structure, chord error, round trip of outlines (Hausdorff), stitches, bad files."""

from __future__ import annotations

import math

import ezdxf
import numpy as np
import pytest
from ezdxf.addons import gerber_D6673
from ezdxf.document import Drawing

from torchgarment.errors import PatternError
from torchgarment.pattern.dxf import load_dxf, save_dxf
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


def _pattern() -> SewingPattern:
    quad = Panel("front", [[0, 0], [0.4, 0], [0.4, 0.6], [0, 0.6]], [
        Edge(0, 1), Edge(1, 2, EdgeKind.QUADRATIC, controls=[[0.5, 0.15]]), Edge(2, 3),
        Edge(3, 0, label="cf")],
        notches=[Notch(0, 0.5, "mid"), Notch(1, 0.3)], translation=[0.0, 1.1, 0.2], label="torso")
    curvy = Panel("back", [[0.4, 0], [0.4, 0.6], [0, 0.6], [0, 0]], [
        Edge(3, 0, EdgeKind.CUBIC, controls=[[0.3, -0.1], [0.7, 0.1]]), Edge(0, 1),
        Edge(1, 2, EdgeKind.ARC, arc=(0.25, False, True)), Edge(2, 3)], rotation=[0, math.pi, 0],
                  grainline=[1, 1])
    cap = Panel("cäp é", [[0, 0], [0.2, 0], [0.2, 0.1]], [
        Edge(0, 1, EdgeKind.ARC, arc=(0.15, True, False)),
        Edge(1, 2, EdgeKind.CUBIC, controls=[[0.2, 0.3], [0.6, -0.4]]), Edge(2, 0)])
    return SewingPattern("test", {"front": quad, "back": curvy, "cäp é": cap}, [
        Stitch(EdgeRef("front", 3), EdgeRef("back", 1)),
        Stitch(EdgeRef("front", 0), EdgeRef("back", 0), StitchOrientation.SAME)])


def _dist_to_closed(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Distance (n,) of points (n, 2) to a closed polyline (m, 2)."""
    a, b = poly, np.roll(poly, -1, axis=0)
    ab = b - a
    out = []
    for q in np.array_split(p, max(1, len(p) // 256)):
        t = np.clip(((q[:, None] - a[None]) * ab[None]).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-300)[None],
                    0, 1)
        out.append(np.linalg.norm(q[:, None] - (a[None] + t[..., None] * ab[None]), axis=-1).min(axis=1))
    return np.concatenate(out)


def hausdorff(p: Panel, q: Panel, resolution: int = 600) -> float:
    """Symmetric Hausdorff distance (metres) between two panels' outlines, points against dense polylines."""
    op, oq = p.outline(resolution), q.outline(resolution)
    return float(max(_dist_to_closed(op, oq).max(), _dist_to_closed(oq, op).max()))


def test_aama_structure(tmp_path):
    pat = _pattern()
    path = tmp_path / "p.dxf"
    save_dxf(path, pat)
    assert [f.name for f in tmp_path.iterdir()] == ["p.dxf"]
    text = path.read_text(encoding="ascii")
    assert "$MODEL_SPACE" not in text.upper() and "TABLES" not in text  # Gerber-friendly R12 layout
    doc = ezdxf.readfile(path)
    assert doc.dxfversion == "AC1009"
    blocks = [b for b in doc.blocks if not b.block_record.is_any_layout]
    assert len(blocks) == 3
    msp_text = [e.dxf.text for e in doc.modelspace() if e.dxftype() == "TEXT"]
    assert "Units: METRIC" in msp_text and "Style Name: test" in msp_text
    assert len([e for e in doc.modelspace() if e.dxftype() == "INSERT"]) == 3
    for blk, panel in zip(blocks, pat.panels.values()):
        layers = {}
        for e in blk:
            layers.setdefault((e.dxftype(), e.dxf.layer), []).append(e)
        (poly,) = layers[("POLYLINE", "1")]
        assert poly.is_closed
        pts = np.array([(v.x, v.y) for v in poly.points()]) / 1000
        # turn points: exactly the panel vertices in edge order; the polyline starts at edge 0's start
        turn = np.array([[e.dxf.location.x, e.dxf.location.y] for e in layers[("POINT", "2")]]) / 1000
        np.testing.assert_allclose(turn, panel.vertices[[e.start for e in panel.edges]], atol=1e-12)
        np.testing.assert_allclose(pts[0], turn[0], atol=1e-12)
        n_curve = len(layers.get(("POINT", "3"), []))
        assert n_curve + len(turn) == len(pts)
        # chord error of the written polyline against the true curve: well under 0.05 mm
        assert _dist_to_closed(panel.outline(2000), pts).max() < 1.5e-5
        assert len(layers.get(("LINE", "4"), [])) == len(panel.notches)
        assert len(layers[("LINE", "7")]) == 1
        names = [e.dxf.text for e in layers[("TEXT", "1")]]
        assert any(t.startswith("Piece Name: ") for t in names) and "Quantity: 1" in names
    stitches = [e.dxf.text for e in doc.modelspace() if e.dxf.layer == "TORCHGARMENT"]
    assert stitches == ["stitch front 3 back 1 opposite", "stitch front 0 back 0 same"]


def test_round_trip(tmp_path):
    pat = _pattern()
    pat.validate()
    save_dxf(tmp_path / "p.dxf", pat)
    got = load_dxf(tmp_path / "p.dxf")
    got.validate()
    assert got.name == "test" and list(got.panels) == list(pat.panels)
    assert got.metadata["dxf_max_fit_error"] < 1e-9  # the stored exact edges match their points
    for name, p in pat.panels.items():
        q = got.panels[name]
        assert hausdorff(p, q) < 1e-9  # acceptance is 0.1 mm; the stored exact edges reach float precision
        assert len(q.edges) == len(p.edges)
        for i, (ep, eq) in enumerate(zip(p.edges, q.edges)):
            assert np.allclose(q.edge_endpoints(i), p.edge_endpoints(i), atol=1e-9)
            assert eq.kind is ep.kind  # exact: a quadratic stays quadratic
            if ep.controls is not None:
                np.testing.assert_allclose(eq.controls, ep.controls, atol=1e-12)
            assert eq.arc == ep.arc
            assert eq.label == ep.label
            assert abs(q.edge_length(i) - p.edge_length(i)) < 1e-9
        np.testing.assert_allclose(q.translation, p.translation, atol=1e-15)
        np.testing.assert_allclose(q.rotation, p.rotation, atol=1e-15)
        np.testing.assert_allclose(q.grainline, p.grainline, atol=1e-9)
        assert q.label == p.label
        assert [n.edge for n in q.notches] == [n.edge for n in p.notches]
        assert [n.name for n in q.notches] == [n.name for n in p.notches]
        assert np.allclose([n.t for n in q.notches], [n.t for n in p.notches], atol=5e-3)
    assert [(s.a, s.b, s.orientation) for s in got.stitches] == [(s.a, s.b, s.orientation)
                                                                 for s in pat.stitches]


def _without_exact_edges(src, dst, replace=None):
    """Copy a DXF of ours with the ``edge`` data entries disabled (or one entry replaced): a 'foreign'
    file."""
    lines = src.read_text(encoding="ascii").splitlines()
    if replace is None:
        lines = ["x" + ln if ln.startswith("edge ") else ln for ln in lines]
    else:
        assert replace[0] in lines
        lines = [replace[1] if ln == replace[0] else ln for ln in lines]
    dst.write_text("\n".join(lines) + "\n", encoding="ascii")


def test_refit_without_exact_edges(tmp_path):
    # the fallback path other CAD tools' files take: lines, arcs and cubics are refitted from the points
    pat = _pattern()
    save_dxf(tmp_path / "p.dxf", pat)
    _without_exact_edges(tmp_path / "p.dxf", tmp_path / "f.dxf")
    got = load_dxf(tmp_path / "f.dxf")
    assert got.metadata["dxf_max_fit_error"] < 1e-6
    for name, p in pat.panels.items():
        q = got.panels[name]
        assert hausdorff(p, q) < 1e-6
        assert len(q.edges) == len(p.edges)
        for ep, eq in zip(p.edges, q.edges):
            want = {EdgeKind.LINE: EdgeKind.LINE, EdgeKind.ARC: EdgeKind.ARC}.get(ep.kind, EdgeKind.CUBIC)
            assert eq.kind is want
    np.testing.assert_allclose(got.panels["back"].edges[0].controls, [[0.3, -0.1], [0.7, 0.1]], atol=1e-6)
    quad = got.panels["front"].edges[1]  # degree-elevated quadratic
    np.testing.assert_allclose(quad.controls, [[1 / 3, 0.1], [2 / 3, 0.1]], atol=1e-6)
    assert got.panels["cäp é"].edges[0].arc == pytest.approx((0.15, True, False))
    assert [(s.a, s.b, s.orientation) for s in got.stitches] == [(s.a, s.b, s.orientation)
                                                                 for s in pat.stitches]


def test_inconsistent_exact_edge_is_refitted(tmp_path):
    # a stored definition that disagrees with the boundary points (geometry edited elsewhere) is not trusted
    pat = _pattern()
    save_dxf(tmp_path / "p.dxf", pat)
    _without_exact_edges(tmp_path / "p.dxf", tmp_path / "t.dxf",
                         replace=("edge 0 cubic 0.3 -0.1 0.7 0.1", "edge 0 cubic 0.3 -0.1 0.7 0.102"))
    got = load_dxf(tmp_path / "t.dxf")
    edge = got.panels["back"].edges[0]
    np.testing.assert_allclose(edge.controls, [[0.3, -0.1], [0.7, 0.1]], atol=1e-6)  # fitted to the points
    assert got.panels["front"].edges[1].kind is EdgeKind.QUADRATIC  # other edges still exact
    assert got.metadata["dxf_max_fit_error"] < 1e-6
    _without_exact_edges(tmp_path / "p.dxf", tmp_path / "m.dxf", replace=("edge 0 line", "edge 0 cubic 0.5"))
    with pytest.raises(PatternError, match="bad TORCHGARMENT entry 'edge 0 cubic 0.5'"):
        load_dxf(tmp_path / "m.dxf")


def test_library_tshirt_round_trip_keeps_stitched_edges(tmp_path):
    # regression: the largest tshirt's armhole cubic used to be refitted into a loop and split, losing
    # a stitch
    lib = pytest.importorskip("torchgarment.pattern.library")
    chart = pytest.importorskip("torchgarment.body.size_chart")
    pat = lib.draft("tshirt", chart.chart_row(chart.list_sizes()[-1]))
    save_dxf(tmp_path / "t.dxf", pat)
    _without_exact_edges(tmp_path / "t.dxf", tmp_path / "f.dxf")
    for path, tol in ((tmp_path / "t.dxf", 1e-9), (tmp_path / "f.dxf", 1e-6)):
        got = load_dxf(path)
        got.validate()
        assert [len(p.edges) for p in got.panels.values()] == [len(p.edges) for p in pat.panels.values()]
        assert max(hausdorff(p, got.panels[n], 200) for n, p in pat.panels.items()) < tol
        assert [(s.a, s.b, s.orientation) for s in got.stitches] == [(s.a, s.b, s.orientation)
                                                                     for s in pat.stitches]


def _foreign(path, points_mm, bulges=None, turn_points=None, layer_units=None):
    """An R12 DXF as another CAD tool might write it: one block, a layer-1 boundary, optional turn points."""
    doc = Drawing.new("R12")
    blk = doc.blocks.new("PIECE1")
    poly = blk.add_polyline2d(points_mm, close=True, dxfattribs={"layer": "1"})
    if bulges is not None:
        for v, bulge in zip(poly.vertices, bulges):
            v.dxf.bulge = bulge
    for p in turn_points or []:
        blk.add_point(p, dxfattribs={"layer": "2"})
    blk.add_text("Piece Name: sleeve", dxfattribs={"layer": "1"})
    doc.modelspace().add_blockref("PIECE1", (0, 0))
    if layer_units:
        doc.modelspace().add_text(f"Units: {layer_units}", dxfattribs={"layer": "1"})
    gerber_D6673.export_file(doc, path)


def test_foreign_clockwise_piece_with_bulge_and_no_turn_points(tmp_path):
    # clockwise 200 x 100 inch rectangle whose top side bulges out as a 90 degree arc (bulge tan(pi / 8))
    pts = [(0, 0), (0, 100), (200, 100), (200, 0)]
    bulge = math.tan(math.pi / 8)
    _foreign(tmp_path / "f.dxf", pts, bulges=[0, -bulge, 0, 0], layer_units="ENGLISH")
    got = load_dxf(tmp_path / "f.dxf")
    (panel,) = got.panels.values()
    assert panel.name == "sleeve" and got.stitches == []
    assert panel.area() > 0  # reversed to counter-clockwise
    kinds = sorted(e.kind.value for e in panel.edges)
    assert kinds == ["circle", "line", "line", "line"]
    arc = next(e for e in panel.edges if e.kind is EdgeKind.ARC)
    r = 100 * math.sqrt(2)  # chord 200 over 90 degrees
    assert arc.arc[0] == pytest.approx(r * 25.4e-3, rel=1e-9)  # inches -> metres
    assert not arc.arc[1]
    segment = r**2 / 2 * (math.pi / 2 - 1)  # circular segment of 90 degrees
    o = panel.outline(4000)
    area = 0.5 * float(np.dot(o[:, 0], np.roll(o[:, 1], -1)) - np.dot(o[:, 1], np.roll(o[:, 0], -1)))
    assert area == pytest.approx((200 * 100 + segment) * 25.4e-3**2, rel=1e-6)


def test_non_cubic_curve_is_split_to_fit(tmp_path):
    x = np.linspace(0, 300, 301)
    top = np.stack([x[::-1], 100 + 20 * np.sin(x[::-1] / 300 * 4 * np.pi)], axis=1)  # two sine periods
    pts = [(0.0, 0.0), (300.0, 0.0)] + [tuple(p) for p in top]
    turns = [(0, 0), (300, 0), (300, 100), (0, 100)]
    _foreign(tmp_path / "s.dxf", pts, turn_points=turns)
    got = load_dxf(tmp_path / "s.dxf", max_fit_error=2e-5)
    (panel,) = got.panels.values()
    assert len(panel.edges) > 4  # the sine side became several cubics
    assert got.metadata["dxf_max_fit_error"] <= 2e-5
    ref = Panel("ref", np.array(pts) / 1000, [Edge(i, (i + 1) % len(pts)) for i in range(len(pts))])
    assert hausdorff(ref, panel) < 5e-5


def test_bad_files(tmp_path):
    garbage = tmp_path / "g.dxf"
    garbage.write_text("this is not\na dxf file\n")
    with pytest.raises(PatternError, match="not a readable DXF"):
        load_dxf(garbage)
    with pytest.raises(PatternError, match="does not exist"):
        load_dxf(tmp_path / "missing.dxf")
    empty = Drawing.new("R12")
    empty.modelspace().add_line((0, 0), (1, 1))
    gerber_D6673.export_file(empty, tmp_path / "e.dxf")
    with pytest.raises(PatternError, match="no pattern pieces"):
        load_dxf(tmp_path / "e.dxf")
    pat = _pattern()
    save_dxf(tmp_path / "ok.dxf", pat)
    text = (tmp_path / "ok.dxf").read_text(encoding="ascii").replace("stitch front 3 back 1",
                                                                     "stitch front 3 nope 1")
    (tmp_path / "bad.dxf").write_text(text, encoding="ascii")
    with pytest.raises(PatternError, match="unknown piece 'nope'"):
        load_dxf(tmp_path / "bad.dxf")
    with pytest.raises(PatternError, match="no panels"):
        save_dxf(tmp_path / "x.dxf", SewingPattern("empty", {}))
    assert not (tmp_path / "x.dxf").exists()


def test_garmentcode_round_trip(garmentcode_dir, tmp_path):
    gc = pytest.importorskip("torchgarment.pattern.garmentcode", reason="GarmentCode reader not written yet")
    pat = gc.load_pattern(garmentcode_dir / "patterns" / "shirt_mean_specification.json")
    save_dxf(tmp_path / "shirt.dxf", pat)
    got = load_dxf(tmp_path / "shirt.dxf")
    assert list(got.panels) == list(pat.panels)
    worst = max(hausdorff(p, got.panels[n], 200) for n, p in pat.panels.items())
    assert worst < 1e-4
    for n, p in pat.panels.items():
        assert len(got.panels[n].edges) == len(p.edges)
    assert [(s.a, s.b, s.orientation) for s in got.stitches] == [(s.a, s.b, s.orientation)
                                                                 for s in pat.stitches]
    got.validate(max_stitch_length_ratio=gc.MAX_STITCH_LENGTH_RATIO)
