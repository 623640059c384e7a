"""Small helpers to draft panels: outline chains with absolute Bezier controls, mirroring, placement, seams.

A :class:`Chain` is an open sequence of points joined by labelled segments whose Bezier controls are given in
absolute panel coordinates (metres); :func:`make_panel` closes a chain into a :class:`Panel`, converting the
controls to the pattern format's relative coordinates. Symmetric panels are drafted as their right half
(``x >= 0``) from the bottom centre to the top centre and closed with :func:`mirror_half`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from torchgarment.errors import PatternError
from torchgarment.pattern.spec import Edge, EdgeKind, EdgeRef, Panel, Stitch, StitchOrientation


@dataclass
class Segment:
    """One outline segment: kind, absolute controls (k, 2) and a label used to find it again."""

    kind: EdgeKind
    controls: np.ndarray
    label: str


@dataclass
class Chain:
    """Open outline: ``points[i]`` to ``points[i + 1]`` is ``segments[i]``."""

    points: list[np.ndarray] = field(default_factory=list)
    segments: list[Segment] = field(default_factory=list)

    @classmethod
    def start(cls, p: ArrayLike) -> "Chain":
        return cls(points=[np.asarray(p, dtype=np.float64)])

    def line(self, p: ArrayLike, label: str) -> "Chain":
        """Append a straight segment to ``p``."""
        return self._add(p, EdgeKind.LINE, np.zeros((0, 2)), label)

    def quad(self, c: ArrayLike, p: ArrayLike, label: str) -> "Chain":
        """Append a quadratic Bezier with absolute control ``c``."""
        return self._add(p, EdgeKind.QUADRATIC, np.asarray([c], dtype=np.float64), label)

    def cubic(self, c1: ArrayLike, c2: ArrayLike, p: ArrayLike, label: str) -> "Chain":
        """Append a cubic Bezier with absolute controls ``c1``, ``c2``."""
        return self._add(p, EdgeKind.CUBIC, np.asarray([c1, c2], dtype=np.float64), label)

    def _add(self, p: ArrayLike, kind: EdgeKind, controls: np.ndarray, label: str) -> "Chain":
        self.points.append(np.asarray(p, dtype=np.float64))
        self.segments.append(Segment(kind, controls, label))
        return self

    def mirrored(self, suffix_from: str = "_r", suffix_to: str = "_l") -> "Chain":
        """Mirror ``x -> -x`` and reverse the direction (keeps counter-clockwise order); relabel suffixes."""
        flip = np.array([-1.0, 1.0])
        pts = [p * flip for p in reversed(self.points)]
        segs = []
        for s in reversed(self.segments):
            label = s.label
            if suffix_from and label.endswith(suffix_from):
                label = label[: -len(suffix_from)] + suffix_to
            segs.append(Segment(s.kind, s.controls[::-1] * flip, label))
        return Chain(pts, segs)


def mirror_half(right: Chain) -> Chain:
    """Close a right half (from ``(0, y_bottom)`` to ``(0, y_top)``) with its mirror image into a full loop.

    Labels ending in ``_r`` (local +x side) get ``_l`` on the mirrored side. The result is a closed chain:
    its last point equals its first.
    """
    if abs(right.points[0][0]) > 1e-12 or abs(right.points[-1][0]) > 1e-12:
        raise PatternError("a half outline must start and end on the centre line x = 0")
    left = right.mirrored()
    return Chain(right.points + left.points[1:], right.segments + left.segments)


def make_panel(name: str, chain: Chain, *, closed: bool = False,
               label: str = "") -> tuple[Panel, dict[str, int]]:
    """Turn a chain into a panel and a map from segment label to edge index.

    Args:
        name: panel name.
        chain: the outline, counter-clockwise seen from outside. If ``closed`` its last point repeats the
            first; otherwise a final segment must not be implied (the last segment ends at the first point).
        closed: whether ``chain.points[-1]`` duplicates ``chain.points[0]``.
        label: panel label.
    """
    pts = chain.points[:-1] if closed else chain.points
    n = len(pts)
    if len(chain.segments) != n:
        raise PatternError(f"panel '{name}': {n} corners but {len(chain.segments)} segments")
    verts = np.stack(pts)
    edges: list[Edge] = []
    index: dict[str, int] = {}
    for i, seg in enumerate(chain.segments):
        a, b = verts[i], verts[(i + 1) % n]
        controls = None
        if seg.kind is not EdgeKind.LINE:
            d = b - a
            dd = float(d @ d)
            rel = seg.controls - a
            perp = np.array([-d[1], d[0]])
            controls = np.stack([rel @ d / dd, rel @ perp / dd], axis=-1)
        edges.append(Edge(i, (i + 1) % n, seg.kind, controls, label=seg.label))
        if seg.label in index:
            raise PatternError(f"panel '{name}': duplicate edge label '{seg.label}'")
        index[seg.label] = i
    panel = Panel(name=name, vertices=verts, edges=edges, label=label)
    if panel.area() <= 0:
        raise PatternError(f"panel '{name}' outline is not counter-clockwise")
    return panel, index


def place(panel: Panel, origin: ArrayLike, x_axis: ArrayLike, y_axis: ArrayLike) -> Panel:
    """Set the placement so that local (0, 0) goes to ``origin`` and local x, y to the given world axes.

    Args:
        origin: (3,) world position of the panel's local origin, metres.
        x_axis, y_axis: (3,) orthonormal world directions of the panel's local x and y axes; the panel's
            outside normal is ``x_axis x y_axis``.
    """
    ex = np.asarray(x_axis, dtype=np.float64)
    ey = np.asarray(y_axis, dtype=np.float64)
    ex = ex / np.linalg.norm(ex)
    ey = ey - (ey @ ex) * ex
    ey = ey / np.linalg.norm(ey)
    m = np.stack([ex, ey, np.cross(ex, ey)], axis=1)
    panel.rotation = Rotation.from_matrix(m).as_euler("xyz")
    panel.translation = np.asarray(origin, dtype=np.float64).reshape(3)
    return panel


def place_front(panel: Panel, z: float, x: float = 0.0) -> Panel:
    """Front placement: local axes = world axes, panel plane at ``z`` (> 0), local origin at world ``x``."""
    return place(panel, (x, 0.0, z), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))


def place_back(panel: Panel, z: float, x: float = 0.0) -> Panel:
    """Back placement: rotated 180 deg about Y (local +x is the body's right), plane at ``-z``."""
    return place(panel, (x, 0.0, -z), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0))


def seam(pa: str, ia: dict[str, int], la: str, pb: str, ib: dict[str, int], lb: str,
         orientation: StitchOrientation = StitchOrientation.OPPOSITE) -> Stitch:
    """A stitch between edge ``la`` of panel ``pa`` and edge ``lb`` of panel ``pb`` (labels via index
    maps)."""
    return Stitch(EdgeRef(pa, ia[la]), EdgeRef(pb, ib[lb]), orientation)


def cubic_length(p0: ArrayLike, c1: ArrayLike, c2: ArrayLike, p1: ArrayLike, n: int = 256) -> float:
    """Arc length of an absolute cubic Bezier (polyline estimate, metres)."""
    t = np.linspace(0.0, 1.0, n + 1)[:, None]
    pts = ((1 - t) ** 3 * np.asarray(p0) + 3 * (1 - t) ** 2 * t * np.asarray(c1)
           + 3 * (1 - t) * t**2 * np.asarray(c2) + t**3 * np.asarray(p1))
    return float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())


def side_curve(p_low: ArrayLike, p_high: ArrayLike, chain: Chain, label: str, bulge: float = 0.5) -> Chain:
    """Append a cubic from the chain's last point ``p_low`` to ``p_high`` with vertical end tangents.

    Used for the waist-to-hip and waist-to-bust side shaping: the curve leaves and arrives vertically, so
    consecutive shaped segments join smoothly. ``bulge`` is the fraction of the height used by each tangent.
    """
    p_low = np.asarray(p_low, dtype=np.float64)
    p_high = np.asarray(p_high, dtype=np.float64)
    dy = p_high[1] - p_low[1]
    c1 = p_low + np.array([0.0, bulge * dy])
    c2 = p_high - np.array([0.0, bulge * dy])
    return chain.cubic(c1, c2, p_high, label)
