"""Pattern sheets as SVG: panels side by side at real scale, true curves, seams, notches and grainlines.

The sheet prints 1:1: its ``width``/``height`` are in millimetres and its ``viewBox`` uses millimetres, so one
user unit is one millimetre. Panels keep their own coordinates up to a translation chosen by a shelf packing
of their bounding boxes (:func:`svg_panel_layout`, shared with :mod:`torchgarment.pattern.plot` and
:mod:`torchgarment.pattern.dxf`). The pattern is Y-up (metres); SVG is Y-down, so a point ``(x, y)`` of the
layout goes to ``(1000 x, 1000 (H - y))`` and an arc's sweep flag is inverted.

Drawn per panel (one ``<g class="panel" data-panel=NAME>``):

* ``path.outline``: the closed outline with ``L`` (line), ``Q`` (quadratic), ``C`` (cubic) and ``A`` (arc)
  commands, one command per edge, starting at the start vertex of edge 0.
* ``path.seam`` (``data-stitch=k``, ``data-edge=i``): each stitched edge again, thicker, in the stitch colour,
  with a ``text.stitch-label`` "S<k>" at the edge's middle, inside the panel, and a ``path.stitch-arrow``
  chevron there. The arrows of the two sides of a stitch point from the ends that meet to the ends that meet
  (for ``OPPOSITE`` the arrow on edge ``b`` runs against ``b``'s direction), so matching arrows sew together.
* ``line.notch``: a short tick from the edge into the panel.
* ``path.grainline``: a line with arrowheads at both ends.
* ``text.panel-name``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from xml.sax.saxutils import escape, quoteattr

import numpy as np

from torchgarment.errors import PatternError
from torchgarment.io.atomic import atomic_open
from torchgarment.pattern.spec import Edge, EdgeKind, Notch, Panel, SewingPattern, StitchOrientation

#: Stitch colours (matplotlib's tab10), cycled by stitch index.
STITCH_COLORS = (
    "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd",
    "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf",
)  # fmt: skip

NOTCH_LENGTH = 0.006  # metres
_OUTLINE_FILL = "#f6f1e7"


def stitch_color(k: int) -> str:
    """Hex colour of stitch ``k``."""
    return STITCH_COLORS[k % len(STITCH_COLORS)]


# ---------------------------------------------------------------------------------------------- layout
def panel_bbox(panel: Panel) -> np.ndarray:
    """Bounding box ``[[xmin, ymin], [xmax, ymax]]`` (2, 2) of a panel's outline, metres."""
    o = panel.outline(resolution=64)
    if o.shape[0] == 0 or not np.all(np.isfinite(o)):
        raise PatternError(f"panel '{panel.name}' has no finite outline to lay out")
    return np.stack([o.min(axis=0), o.max(axis=0)])


def shelf_layout(bboxes: dict[str, np.ndarray],
                 margin: float = 0.02) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Shelf-pack bounding boxes into rows without overlap.

    Boxes are sorted by height (tallest first, stable) and placed left to right in rows of a width about
    1.5 times the square root of the total box area; rows stack downward from the top of the sheet.

    Args:
        bboxes: name -> (2, 2) ``[[xmin, ymin], [xmax, ymax]]`` in metres.
        margin: gap between boxes and around the sheet, metres.

    Returns:
        ``offsets`` (name -> (2,) translation added to the item's coordinates, metres) and the sheet size
        (2,) ``(width, height)`` in metres; every translated box lies inside ``[0, width] x [0, height]``.
    """
    if not bboxes:
        raise PatternError("nothing to lay out: the pattern has no panels")
    if margin < 0 or not math.isfinite(margin):
        raise PatternError(f"layout margin must be a finite non-negative length, got {margin}")
    names = list(bboxes)
    size = {n: np.asarray(bboxes[n][1]) - np.asarray(bboxes[n][0]) for n in names}
    total = sum(float((s[0] + margin) * (s[1] + margin)) for s in size.values())
    row_width = max(max(float(s[0]) for s in size.values()), 1.5 * math.sqrt(total))
    order = sorted(names, key=lambda n: -float(size[n][1]))
    # place with y measured downward from the top edge of the sheet
    placed: dict[str, tuple[float, float]] = {}
    x, y_top, row_h = margin, margin, 0.0
    for n in order:
        w, h = float(size[n][0]), float(size[n][1])
        if x > margin and x + w > margin + row_width:
            x, y_top, row_h = margin, y_top + row_h + margin, 0.0
        placed[n] = (x, y_top + h)  # (left, bottom measured downward)
        x += w + margin
        row_h = max(row_h, h)
    sheet_w = max(placed[n][0] + float(size[n][0]) for n in names) + margin
    sheet_h = y_top + row_h + margin
    offsets = {}
    for n in names:
        left, bottom_down = placed[n]
        offsets[n] = np.array([left, sheet_h - bottom_down]) - np.asarray(bboxes[n][0], dtype=np.float64)
    return offsets, np.array([sheet_w, sheet_h])


def svg_panel_layout(pattern: SewingPattern, *,
                     margin: float = 0.02) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Per-panel offsets of the sheet layout used by :func:`save_svg` (and the PNG and DXF writers).

    Args:
        pattern: the pattern.
        margin: gap between panels and around the sheet, metres.

    Returns:
        ``offsets`` (panel name -> (2,) translation in metres added to the panel's coordinates) and the sheet
        size (2,) in metres.
    """
    return shelf_layout({name: panel_bbox(p) for name, p in pattern.panels.items()}, margin)


# ---------------------------------------------------------------------------------------------- marks
def _inward_sign(panel: Panel) -> float:
    """+1 when the panel runs counter-clockwise (interior on the left of travel), else -1."""
    return 1.0 if panel.area() >= 0 else -1.0


def edge_point_and_tangent(panel: Panel, edge: int, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Point (2,) at arc-length fraction ``t`` of an edge and the unit tangent (2,) along the edge there."""
    if not 0 <= edge < len(panel.edges):
        raise PatternError(f"panel '{panel.name}' has no edge {edge}")
    a, b = panel.edge_endpoints(edge)
    n = 256
    pts = panel.edges[edge].sample_by_length(a, b, n)
    s = min(max(float(t), 0.0), 1.0) * n
    i = min(int(s), n - 1)
    p = pts[i] + (s - i) * (pts[i + 1] - pts[i])
    d = pts[i + 1] - pts[i]
    norm = float(np.linalg.norm(d))
    if norm == 0.0:
        raise PatternError(f"panel '{panel.name}' edge {edge} is degenerate")
    return p, d / norm


def inward_normal(panel: Panel, tangent: np.ndarray) -> np.ndarray:
    """Unit normal (2,) pointing into the panel for an outline tangent (2,)."""
    return _inward_sign(panel) * np.array([-tangent[1], tangent[0]])


def notch_segment(panel: Panel, notch: Notch, length: float = NOTCH_LENGTH) -> np.ndarray:
    """(2, 2) segment of a notch: the point on the edge, then the point ``length`` metres inside."""
    p, tan = edge_point_and_tangent(panel, notch.edge, notch.t)
    return np.stack([p, p + length * inward_normal(panel, tan)])


def grainline_segment(panel: Panel) -> np.ndarray:
    """(2, 2) grainline through the outline's centroid along ``panel.grainline``, 60 % of the panel's
    extent."""
    o = panel.outline(resolution=32)
    c = o.mean(axis=0)
    g = panel.grainline
    proj = (o - c) @ g
    half = 0.3 * float(proj.max() - proj.min())
    return np.stack([c - half * g, c + half * g])


@dataclass(frozen=True)
class StitchMark:
    """Label position of one side of a stitch.

    Attributes:
        stitch: stitch index.
        panel: panel name.
        edge: edge index.
        point: (2,) middle of the edge (arc length), panel coordinates, metres.
        direction: (2,) unit vector along the edge pointing from the end that meets the other side's
            "first" end (``a.start``) toward the other end.
        inward: (2,) unit normal into the panel.
    """

    stitch: int
    panel: str
    edge: int
    point: np.ndarray
    direction: np.ndarray
    inward: np.ndarray


def stitch_marks(pattern: SewingPattern) -> list[StitchMark]:
    """Both sides of every stitch, in stitch order (a then b); stitches to unknown panels raise."""
    marks = []
    for k, s in enumerate(pattern.stitches):
        for side, ref in (("a", s.a), ("b", s.b)):
            if ref.panel not in pattern.panels:
                raise PatternError(f"stitch {k} refers to unknown panel '{ref.panel}'")
            panel = pattern.panels[ref.panel]
            p, tan = edge_point_and_tangent(panel, ref.edge, 0.5)
            flip = side == "b" and s.orientation is StitchOrientation.OPPOSITE
            marks.append(StitchMark(k, ref.panel, ref.edge, p, -tan if flip else tan,
                                    inward_normal(panel, tan)))
    return marks


# ---------------------------------------------------------------------------------------------- SVG
class _Frame:
    """Layout coordinates (metres, Y up) -> SVG user units (millimetres, Y down)."""

    def __init__(self, offset: np.ndarray, sheet_h: float) -> None:
        self.offset = offset
        self.sheet_h = sheet_h

    def __call__(self, p: np.ndarray) -> np.ndarray:
        q = np.asarray(p, dtype=np.float64) + self.offset
        return np.stack([1000.0 * q[..., 0], 1000.0 * (self.sheet_h - q[..., 1])], axis=-1)


def _f(x: float) -> str:
    s = f"{x:.4f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _pt(p: np.ndarray) -> str:
    return f"{_f(p[0])} {_f(p[1])}"


def edge_svg_command(edge: Edge, a: np.ndarray, b: np.ndarray, frame: _Frame) -> str:
    """SVG path command drawing one edge from the current point ``a`` to ``b`` (both panel coordinates)."""
    end = frame(b)
    if edge.kind is EdgeKind.LINE:
        return f"L {_pt(end)}"
    if edge.kind is EdgeKind.QUADRATIC:
        (c,) = frame(edge.absolute_controls(a, b))
        return f"Q {_pt(c)} {_pt(end)}"
    if edge.kind is EdgeKind.CUBIC:
        c1, c2 = frame(edge.absolute_controls(a, b))
        return f"C {_pt(c1)} {_pt(c2)} {_pt(end)}"
    _, r, _, _ = edge.arc_center(a, b)
    _, large, sweep = edge.arc
    # Y flips, so counter-clockwise (sweep) in the pattern is the negative-angle direction in SVG
    return f"A {_f(1000 * r)} {_f(1000 * r)} 0 {int(large)} {int(not sweep)} {_pt(end)}"


def _arrow_d(tip: np.ndarray, direction: np.ndarray, size: float) -> str:
    """Open chevron at ``tip`` pointing along ``direction`` (SVG units)."""
    d = direction / max(float(np.linalg.norm(direction)), 1e-12)
    n = np.array([-d[1], d[0]])
    p1 = tip - size * d + 0.5 * size * n
    p2 = tip - size * d - 0.5 * size * n
    return f"M {_pt(p1)} L {_pt(tip)} L {_pt(p2)}"


def pattern_svg(pattern: SewingPattern, *, margin: float = 0.02) -> str:
    """The SVG document text of :func:`save_svg`."""
    offsets, sheet = svg_panel_layout(pattern, margin=margin)
    w_mm, h_mm = 1000 * sheet
    marks = stitch_marks(pattern)
    out = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" version="1.1" width="{_f(w_mm)}mm" height="{_f(h_mm)}mm" '
        f'viewBox="0 0 {_f(w_mm)} {_f(h_mm)}">',
        f"<title>{escape(pattern.name)}</title>",
        '<style>text { font-family: sans-serif; } .outline { stroke: #000; stroke-width: 0.5; } '
        ".seam { fill: none; stroke-width: 1.6; stroke-linecap: round; } "
        ".notch, .grainline { fill: none; stroke: #000; stroke-width: 0.4; } "
        ".stitch-arrow { fill: none; stroke-width: 0.6; }</style>",
    ]
    for name, panel in pattern.panels.items():
        frame = _Frame(offsets[name], float(sheet[1]))
        v = panel.vertices
        out.append(f'<g class="panel" data-panel={quoteattr(name)}>')
        cmds = [f"M {_pt(frame(v[panel.edges[0].start]))}"] if panel.edges else []
        for i, e in enumerate(panel.edges):
            cmds.append(edge_svg_command(e, *panel.edge_endpoints(i), frame))
        out.append(f'<path class="outline" fill="{_OUTLINE_FILL}" d="{" ".join(cmds)} Z"/>')
        for m in (m for m in marks if m.panel == name):
            a, b = panel.edge_endpoints(m.edge)
            col = stitch_color(m.stitch)
            seg = edge_svg_command(panel.edges[m.edge], a, b, frame)
            out.append(f'<path class="seam" stroke="{col}" data-stitch="{m.stitch}" data-edge="{m.edge}" '
                       f'd="M {_pt(frame(a))} {seg}"/>')
            tip_m = m.point + 0.004 * m.inward + 0.006 * m.direction
            tip, base = frame(tip_m), frame(m.point + 0.004 * m.inward)
            out.append(f'<path class="stitch-arrow" stroke="{col}" d="{_arrow_d(tip, tip - base, 3.0)}"/>')
            lab = frame(m.point + 0.012 * m.inward)
            out.append(f'<text class="stitch-label" fill="{col}" x="{_f(lab[0])}" y="{_f(lab[1])}" '
                       f'font-size="6" text-anchor="middle" dominant-baseline="middle">S{m.stitch}</text>')
        for notch in panel.notches:
            p, q = frame(notch_segment(panel, notch))
            out.append(f'<line class="notch" x1="{_f(p[0])}" y1="{_f(p[1])}" x2="{_f(q[0])}" '
                       f'y2="{_f(q[1])}"/>')
        g0, g1 = frame(grainline_segment(panel))
        out.append(f'<path class="grainline" d="M {_pt(g0)} L {_pt(g1)} {_arrow_d(g1, g1 - g0, 5.0)} '
                   f'{_arrow_d(g0, g0 - g1, 5.0)}"/>')
        c = frame(panel.outline(resolution=32).mean(axis=0))
        size = float(np.clip(0.08 * 1000 * np.ptp(panel.outline(resolution=8), axis=0).min(), 4.0, 14.0))
        out.append(f'<text class="panel-name" x="{_f(c[0] + 0.6 * size)}" y="{_f(c[1])}" '
                   f'font-size="{_f(size)}" dominant-baseline="middle">{escape(name)}</text>')
        out.append("</g>")
    out.append("</svg>")
    return "\n".join(out) + "\n"


def save_svg(path: str | os.PathLike, pattern: SewingPattern, *, margin: float = 0.02) -> None:
    """Write a pattern sheet as SVG at real scale (1 user unit = 1 mm); atomic.

    Args:
        path: destination ``.svg`` file.
        pattern: the pattern (metres).
        margin: gap between panels and around the sheet, metres.

    Raises:
        PatternError: the pattern has no panels, or a stitch refers to a missing panel or edge.
    """
    text = pattern_svg(pattern, margin=margin)
    with atomic_open(path, "w") as f:
        f.write(text)
