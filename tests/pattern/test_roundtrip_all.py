"""Acceptance: every shipped pattern meshes with 1:1 seams and survives JSON, SVG and DXF round trips.

Patterns: the four GarmentCode specifications of the shared data and every library garment drafted for the
smallest and the largest row of the built-in size chart. For each:

* meshing at 5 mm and 10 mm pairs every stitch one to one: the mesh boundary vertices on the two stitched
  edges (found geometrically, independently of the mesher's bookkeeping) are equally many, sit at the same
  arc-length fractions (mirrored for OPPOSITE stitches), and ``seam_pairs`` is exactly the set of those
  pairs; before de-duplication that is the sum over stitches of the edge's vertex count;
* JSON (GarmentCode) and DXF (AAMA) files read back with the same panels, edges, placements and stitches,
  every outline within 0.1 mm (symmetric Hausdorff distance of outlines sampled every 1 mm);
* the SVG sheet parses with :mod:`xml.etree`, and its outline paths, rebuilt into panels, match within 0.1 mm.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from scipy.spatial import cKDTree

from torchgarment.body.size_chart import chart_row, list_sizes
from torchgarment.pattern.dxf import load_dxf, save_dxf
from torchgarment.pattern.garmentcode import MAX_STITCH_LENGTH_RATIO, load_pattern, save_pattern
from torchgarment.pattern.library import draft, list_garments
from torchgarment.pattern.meshing import mesh_pattern
from torchgarment.pattern.spec import Edge, EdgeKind, Panel, SewingPattern, StitchOrientation
from torchgarment.pattern.svg import save_svg, svg_panel_layout

GARMENTCODE_SPECS = ["dress_pencil", "hoody_mean", "js_mean_all", "shirt_mean"]
SIZES = [list_sizes()[0], list_sizes()[-1]]
CASES = [f"gc:{n}" for n in GARMENTCODE_SPECS] + [f"{g}:{s}" for g in list_garments() for s in SIZES]
OUTLINE_TOLERANCE = 1e-4  # metres: the 0.1 mm
_SVG_NS = "{http://www.w3.org/2000/svg}"
_cache: dict[str, SewingPattern] = {}


@pytest.fixture
def pattern(request) -> SewingPattern:
    """The pattern of a case id (``gc:<spec>`` or ``<garment>:<size>``), built once per session."""
    case = request.param
    if case not in _cache:
        kind, _, name = case.partition(":")
        if kind == "gc":
            gc_dir = request.getfixturevalue("garmentcode_dir")
            _cache[case] = load_pattern(gc_dir / "patterns" / f"{name}_specification.json")
        else:
            _cache[case] = draft(kind, chart_row(name))
    return _cache[case]


# ---------------------------------------------------------------------------------------------- geometry
def _dist_to_polyline(points: np.ndarray, poly: np.ndarray, tree: cKDTree,
                      closed: bool) -> tuple[np.ndarray, np.ndarray]:
    """Distance (n,) of points (n, 2) to a dense polyline (m, 2) and the arc length (n,) of the foot point.

    Only the segments next to the 4 nearest polyline vertices are tried: the distance is never below the
    true one (the Hausdorff estimate is conservative), and exact for polylines much denser than the points'
    distance to them.
    """
    m = poly.shape[0]
    seg_end = np.roll(poly, -1, axis=0) if closed else np.concatenate([poly[1:], poly[-1:]])
    seg_len = np.linalg.norm(seg_end - poly, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    _, near = tree.query(points, k=min(4, m))
    near = near.reshape(points.shape[0], -1)
    cand = np.concatenate([near, (near - 1) % m], axis=1)  # the segment starting and the one ending there
    a, b = poly[cand], seg_end[cand]
    ab = b - a
    t = np.clip(((points[:, None] - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-300), 0.0, 1.0)
    d = np.linalg.norm(points[:, None] - (a + t[..., None] * ab), axis=-1)
    k = np.argmin(d, axis=1)
    rows = np.arange(points.shape[0])
    return d[rows, k], cum[cand[rows, k]] + t[rows, k] * seg_len[cand[rows, k]]


def _outline(panel: Panel, spacing: float = 1e-3) -> np.ndarray:
    """Closed outline sampled every ``spacing`` metres of arc length or closer, (M, 2), no repeated point."""
    parts = []
    for i, e in enumerate(panel.edges):
        a, b = panel.edge_endpoints(i)
        n = max(1, math.ceil(e.length(a, b) / spacing))
        parts.append(e.sample_by_length(a, b, n)[:-1])
    return np.concatenate(parts)


def hausdorff(p: Panel, q: Panel) -> float:
    """Symmetric Hausdorff distance (metres) of two panel outlines, points every 1 mm against the other's
    outline sampled every 0.1 mm."""
    out = 0.0
    for x, y in ((p, q), (q, p)):
        dense = _outline(y, 1e-4)
        d, _ = _dist_to_polyline(_outline(x), dense, cKDTree(dense), closed=True)
        out = max(out, float(d.max()))
    return out


def assert_same_pattern(got: SewingPattern, want: SewingPattern, what: str) -> None:
    """Same panels (order, edges, placement) within 0.1 mm, and the same stitches with orientations."""
    assert list(got.panels) == list(want.panels), what
    for name, p in want.panels.items():
        q = got.panels[name]
        assert len(q.edges) == len(p.edges), f"{what} {name}"
        assert [e.kind for e in q.edges] == [e.kind for e in p.edges], f"{what} {name}"
        assert [e.label for e in q.edges] == [e.label for e in p.edges], f"{what} {name}"
        np.testing.assert_allclose(q.vertices[[e.start for e in q.edges]],
                                   p.vertices[[e.start for e in p.edges]],
                                   atol=1e-9, err_msg=f"{what} {name}")
        np.testing.assert_allclose(q.translation, p.translation, atol=1e-9, err_msg=f"{what} {name}")
        np.testing.assert_allclose(q.rotation, p.rotation, atol=1e-9, err_msg=f"{what} {name}")
        assert q.label == p.label, f"{what} {name}"
        h = hausdorff(p, q)
        assert h < OUTLINE_TOLERANCE, f"{what} {name}: outline moved {h * 1000:.4f} mm"
    assert [(s.a, s.b, s.orientation) for s in got.stitches] == \
        [(s.a, s.b, s.orientation) for s in want.stitches], what


# ---------------------------------------------------------------------------------------------- meshing
def _edge_vertices(panel: Panel, edge: int, boundary: np.ndarray,
                   p2d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mesh boundary vertices lying on a panel edge, ordered along it: indices (k,) and arc-length
    fractions."""
    e = panel.edges[edge]
    a, b = panel.edge_endpoints(edge)
    dense = e.polyline(a, b, 1 if e.kind is EdgeKind.LINE else 4096)
    d, s = _dist_to_polyline(p2d[boundary], dense, cKDTree(dense), closed=False)
    on = d < 1e-5  # the mesher interpolates on a polyline of the curve: its seam vertices sit microns off it
    total = float(np.linalg.norm(np.diff(dense, axis=0), axis=1).sum())
    order = np.argsort(s[on])
    return boundary[on][order], s[on][order] / total


@pytest.mark.parametrize("edge_length", [0.005, 0.01], ids=["5mm", "10mm"])
@pytest.mark.parametrize("pattern", CASES, indirect=True)
def test_mesh_pairs_every_stitch_one_to_one(pattern, edge_length):
    mesh = mesh_pattern(pattern, edge_length, max_stitch_length_ratio=MAX_STITCH_LENGTH_RATIO)
    p2d = mesh.p.numpy()
    faces = mesh.faces.numpy()
    vpanel = np.full(p2d.shape[0], -1)
    vpanel[faces.ravel()] = np.repeat(mesh.panel_ids.numpy(), 3)
    assert (vpanel >= 0).all()  # no unused vertex
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    uniq, cnt = np.unique(e, axis=0, return_counts=True)
    on_boundary = np.unique(uniq[cnt == 1])
    names = list(mesh.panel_names)
    assert names == list(pattern.panels)

    expected, raw = [], 0
    for k, st in enumerate(pattern.stitches):
        sides = []
        for ref in (st.a, st.b):
            boundary = on_boundary[vpanel[on_boundary] == names.index(ref.panel)]
            idx, frac = _edge_vertices(pattern.panels[ref.panel], ref.edge, boundary, p2d)
            length = pattern.edge_length(ref)
            n = idx.shape[0] - 1
            # both ends present, segments no longer than the target, equal arc-length spacing
            assert n >= 1 and frac[0] < 1e-6 and frac[-1] > 1 - 1e-6, f"stitch {k} {ref}"
            assert length / n <= edge_length * (1 + 1e-6), f"stitch {k} {ref}"
            np.testing.assert_allclose(frac, np.linspace(0.0, 1.0, n + 1), atol=1e-3,
                                       err_msg=f"stitch {k} {ref}")
            sides.append((idx, frac))
        (ia, fa), (ib, fb) = sides
        assert ia.shape == ib.shape, f"stitch {k}: {ia.shape[0]} vs {ib.shape[0]} seam vertices"
        if st.orientation is StitchOrientation.OPPOSITE:
            ib, fb = ib[::-1], 1.0 - fb[::-1]
        np.testing.assert_allclose(fa, fb, atol=2e-3, err_msg=f"stitch {k}: vertices at different fractions")
        raw += ia.shape[0]
        expected.append(np.stack([ia, ib], axis=1))
    pairs = np.sort(np.concatenate(expected), axis=1) if expected else np.zeros((0, 2), dtype=np.int64)
    self_pairs = int((pairs[:, 0] == pairs[:, 1]).sum())
    pairs = np.unique(pairs[pairs[:, 0] != pairs[:, 1]], axis=0)
    got = mesh.seam_pairs.numpy()
    # seam_pairs lists each distinct pair once: the raw count (sum over stitches of the edge's vertex count)
    # less dart tips paired with themselves and corner pairs that two stitches share
    duplicates = raw - self_pairs - pairs.shape[0]
    assert 0 <= duplicates <= 2 * len(pattern.stitches)  # at most both ends of a stitch repeat
    assert got.shape[0] == np.unique(np.sort(got, axis=1), axis=0).shape[0] == raw - self_pairs - duplicates
    np.testing.assert_array_equal(np.unique(np.sort(got, axis=1), axis=0), pairs)


# ---------------------------------------------------------------------------------------------- files
_TOKEN = re.compile(r"[MLQCAZ]|-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


def _relative(c: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = b - a
    perp = np.array([-d[1], d[0]])
    return np.stack([(c - a) @ d, (c - a) @ perp], axis=-1) / float(d @ d)


def _panel_from_svg_path(name: str, d: str, offset: np.ndarray, sheet_h: float) -> Panel:
    """Rebuild a panel (metres) from an outline path of ``save_svg`` (millimetres, Y down)."""
    tokens = _TOKEN.findall(d)
    assert tokens[0] == "M" and tokens[-1] == "Z", d[:40]

    def to_m(x: str, y: str) -> np.ndarray:
        return np.array([float(x) / 1000.0, sheet_h - float(y) / 1000.0]) - offset

    start = to_m(tokens[1], tokens[2])
    pos, verts, specs = 3, [start], []
    while tokens[pos] != "Z":
        cmd = tokens[pos]
        n = {"L": 2, "Q": 4, "C": 6, "A": 7}[cmd]
        args = tokens[pos + 1: pos + 1 + n]
        pos += 1 + n
        end = to_m(args[-2], args[-1])
        if cmd == "L":
            specs.append((EdgeKind.LINE, None, None))
        elif cmd == "A":
            r = float(args[0]) / 1000.0
            specs.append((EdgeKind.ARC, None, (r, args[3] == "1", args[4] == "0")))  # Y flip reverses sweep
        else:
            ctrl = np.array([to_m(args[i], args[i + 1]) for i in range(0, n - 2, 2)])
            specs.append((EdgeKind.QUADRATIC if cmd == "Q" else EdgeKind.CUBIC, ctrl, None))
        verts.append(end)
    assert np.linalg.norm(verts[-1] - verts[0]) < 1e-6, f"{name}: outline path does not close"
    verts = np.array(verts[:-1])
    m = verts.shape[0]
    edges = []
    for i, (kind, ctrl, arc) in enumerate(specs):
        a, b = verts[i], verts[(i + 1) % m]
        controls = None if ctrl is None else _relative(ctrl, a, b)
        edges.append(Edge(i, (i + 1) % m, kind, controls=controls, arc=arc))
    return Panel(name, verts, edges)


def _check_svg(path, pattern: SewingPattern) -> None:
    root = ET.parse(path).getroot()
    assert root.tag == f"{_SVG_NS}svg"
    offsets, sheet = svg_panel_layout(pattern)
    assert float(root.get("width").removesuffix("mm")) == pytest.approx(1000 * sheet[0], abs=1e-3)
    groups = [g for g in root.iter(f"{_SVG_NS}g") if g.get("class") == "panel"]
    assert [g.get("data-panel") for g in groups] == list(pattern.panels)
    seams = set()
    for g in groups:
        name = g.get("data-panel")
        paths = list(g.iter(f"{_SVG_NS}path"))
        (outline,) = [p for p in paths if p.get("class") == "outline"]
        got = _panel_from_svg_path(name, outline.get("d"), offsets[name], float(sheet[1]))
        want = pattern.panels[name]
        assert [e.kind for e in got.edges] == [e.kind for e in want.edges], name
        h = hausdorff(want, got)
        assert h < OUTLINE_TOLERANCE, f"SVG {name}: outline moved {h * 1000:.4f} mm"
        seams |= {(name, int(p.get("data-stitch")), int(p.get("data-edge"))) for p in paths
                  if p.get("class") == "seam"}
    assert seams == {(r.panel, k, r.edge) for k, s in enumerate(pattern.stitches) for r in (s.a, s.b)}


@pytest.mark.parametrize("pattern", CASES, indirect=True)
def test_json_svg_dxf_round_trip(pattern, tmp_path):
    save_pattern(tmp_path / "p.json", pattern)
    save_svg(tmp_path / "p.svg", pattern)
    save_dxf(tmp_path / "p.dxf", pattern)
    assert sorted(f.name for f in tmp_path.iterdir()) == ["p.dxf", "p.json", "p.svg"]  # no temporaries left

    from_json = load_pattern(tmp_path / "p.json")
    from_json.validate(max_stitch_length_ratio=MAX_STITCH_LENGTH_RATIO)
    assert_same_pattern(from_json, pattern, "JSON")
    for name, p in pattern.panels.items():  # JSON keeps the exact definitions
        for e, f in zip(p.edges, from_json.panels[name].edges):
            if e.controls is not None:
                np.testing.assert_allclose(f.controls, e.controls, atol=1e-12)
            assert (f.arc is None) == (e.arc is None) and (f.arc is None
                                                           or np.allclose(f.arc, e.arc, atol=1e-12))

    from_dxf = load_dxf(tmp_path / "p.dxf")
    from_dxf.validate(max_stitch_length_ratio=MAX_STITCH_LENGTH_RATIO)
    assert_same_pattern(from_dxf, pattern, "DXF")
    assert from_dxf.metadata["dxf_max_fit_error"] < 1e-9  # the stored exact edges were used

    _check_svg(tmp_path / "p.svg", pattern)
