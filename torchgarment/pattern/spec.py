"""Sewing-pattern data model: panels of straight, Bezier and arc edges, stitches with explicit orientation.

Conventions (shared with GarmentCode's JSON specification, see :mod:`torchgarment.pattern.garmentcode`):

* Panel outlines are 2D, in metres, and run counter-clockwise seen from the panel's outside (the side that
  faces away from the body once placed); edge ``i`` runs from ``vertices[edges[i].start]`` to
  ``vertices[edges[i].end]`` and each edge ends where the next one starts.
* Bezier control points use GarmentCode's *relative* coordinates: a control ``(u, v)`` on the edge from
  ``a`` to ``b`` sits at ``a + u (b - a) + v perp(b - a)`` with ``perp(x, y) = (-y, x)``.
* Arcs use the SVG convention GarmentCode uses: ``(radius, large_arc, sweep)``; ``sweep = True`` means the
  arc runs counter-clockwise (increasing angle, Y up).
* 3D placement: a point ``q`` of the panel plane goes to ``R (q_x, q_y, 0) + translation`` with ``R`` the
  extrinsic XYZ Euler rotation ``rotation`` (radians).
* A stitch joins edge ``a`` to edge ``b``. :class:`StitchOrientation` says which ends meet: ``OPPOSITE``
  (the usual case for two panels both counter-clockwise seen from outside) pairs ``a.start`` with ``b.end``;
  ``SAME`` pairs ``a.start`` with ``b.start``. GarmentCode's own files leave this implicit; readers infer it
  from the 3D placement and writers store it explicitly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from torchgarment.errors import PatternError
from torchgarment.options import OptionEnum


class EdgeKind(OptionEnum):
    """Shape of a panel edge."""

    LINE = "line"
    QUADRATIC = "quadratic"
    CUBIC = "cubic"
    ARC = "circle"


class StitchOrientation(OptionEnum):
    """Which ends of two stitched edges meet."""

    OPPOSITE = "opposite"  # a.start <-> b.end
    SAME = "same"  # a.start <-> b.start


def _perp(d: np.ndarray) -> np.ndarray:
    return np.stack([-d[..., 1], d[..., 0]], axis=-1)


@dataclass
class Edge:
    """One edge of a panel outline.

    Attributes:
        start: index of the start vertex in the panel's ``vertices``.
        end: index of the end vertex.
        kind: line, quadratic or cubic Bezier, or circular arc.
        controls: (1, 2) or (2, 2) Bezier controls in relative coordinates (see module docstring).
        arc: (radius in metres, large_arc, sweep) for arcs.
        label: optional free text (GarmentCode uses it for interfaces such as "lower_interface").
    """

    start: int
    end: int
    kind: EdgeKind = EdgeKind.LINE
    controls: np.ndarray | None = None
    arc: tuple[float, bool, bool] | None = None
    label: str = ""

    def __post_init__(self) -> None:
        self.kind = EdgeKind(self.kind)
        if self.kind in (EdgeKind.QUADRATIC, EdgeKind.CUBIC):
            need = 1 if self.kind is EdgeKind.QUADRATIC else 2
            if self.controls is None:
                raise PatternError(f"{self.kind.value} edge {self.start}->{self.end} has no control points")
            self.controls = np.asarray(self.controls, dtype=np.float64).reshape(-1, 2)
            if self.controls.shape[0] != need:
                raise PatternError(
                    f"{self.kind.value} edge {self.start}->{self.end} needs {need} control point(s), "
                    f"got {self.controls.shape[0]}"
                )
        if self.kind is EdgeKind.ARC:
            if self.arc is None:
                raise PatternError(f"arc edge {self.start}->{self.end} has no (radius, large_arc, sweep)")
            r, large, sweep = self.arc
            self.arc = (float(r), bool(large), bool(sweep))

    # ------------------------------------------------------------------ geometry
    def absolute_controls(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Bezier control points in panel coordinates: (k, 2)."""
        if self.controls is None:
            return np.zeros((0, 2))
        d = b - a
        return a + self.controls[:, :1] * d + self.controls[:, 1:2] * _perp(d)

    def arc_center(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float, float, float]:
        """Centre, radius, start angle and signed sweep angle (radians) of an arc edge."""
        r, large, sweep = self.arc
        chord = float(np.linalg.norm(b - a))
        if chord == 0.0:
            raise PatternError(f"arc edge {self.start}->{self.end} has coincident endpoints")
        r = max(r, chord / 2.0)  # SVG rule: radii too small are scaled up to just fit
        mid = 0.5 * (a + b)
        h = math.sqrt(max(r * r - (chord / 2.0) ** 2, 0.0))
        left = _perp((b - a) / chord)
        # centre on the left of travel for a counter-clockwise small arc
        sign = 1.0 if (sweep != large) else -1.0
        c = mid + sign * h * left
        t0 = math.atan2(a[1] - c[1], a[0] - c[0])
        t1 = math.atan2(b[1] - c[1], b[0] - c[0])
        dt = t1 - t0
        if sweep:
            while dt <= 0:
                dt += 2 * math.pi
        else:
            while dt >= 0:
                dt -= 2 * math.pi
        return c, r, t0, dt

    def evaluate(self, a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Points at curve parameters ``t`` in [0, 1].

        Args:
            a: (2,) start point. b: (2,) end point. t: (n,) parameters.

        Returns:
            (n, 2) points in panel coordinates (metres).
        """
        a = np.asarray(a, dtype=np.float64)
        b = np.asarray(b, dtype=np.float64)
        t = np.asarray(t, dtype=np.float64)[:, None]
        if self.kind is EdgeKind.LINE:
            return a + t * (b - a)
        if self.kind is EdgeKind.QUADRATIC:
            (c,) = self.absolute_controls(a, b)
            return (1 - t) ** 2 * a + 2 * (1 - t) * t * c + t**2 * b
        if self.kind is EdgeKind.CUBIC:
            c1, c2 = self.absolute_controls(a, b)
            return (1 - t) ** 3 * a + 3 * (1 - t) ** 2 * t * c1 + 3 * (1 - t) * t**2 * c2 + t**3 * b
        c, r, t0, dt = self.arc_center(a, b)
        ang = t0 + t[:, 0] * dt
        return np.stack([c[0] + r * np.cos(ang), c[1] + r * np.sin(ang)], axis=-1)

    def polyline(self, a: np.ndarray, b: np.ndarray, resolution: int = 64) -> np.ndarray:
        """A dense polyline of the edge, (resolution + 1, 2); exactly ``a`` and ``b`` at the ends."""
        if self.kind is EdgeKind.LINE:
            resolution = 1
        pts = self.evaluate(a, b, np.linspace(0.0, 1.0, resolution + 1))
        pts[0], pts[-1] = a, b
        return pts

    def length(self, a: np.ndarray, b: np.ndarray, resolution: int = 256) -> float:
        """Arc length in metres (exact for lines and arcs, polyline estimate for Beziers)."""
        if self.kind is EdgeKind.LINE:
            return float(np.linalg.norm(np.asarray(b) - np.asarray(a)))
        if self.kind is EdgeKind.ARC:
            _, r, _, dt = self.arc_center(np.asarray(a, float), np.asarray(b, float))
            return float(r * abs(dt))
        p = self.polyline(a, b, resolution)
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())

    def sample_by_length(self, a: np.ndarray, b: np.ndarray, n_segments: int) -> np.ndarray:
        """``n_segments + 1`` points equally spaced in arc length, ends exactly ``a`` and ``b``: (n+1, 2)."""
        if n_segments < 1:
            raise PatternError("an edge needs at least one segment")
        if self.kind in (EdgeKind.LINE, EdgeKind.ARC):
            pts = self.evaluate(a, b, np.linspace(0.0, 1.0, n_segments + 1))
        else:
            dense = self.polyline(a, b, max(256, 8 * n_segments))
            s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
            target = np.linspace(0.0, s[-1], n_segments + 1)
            pts = np.stack([np.interp(target, s, dense[:, 0]), np.interp(target, s, dense[:, 1])], axis=-1)
        pts[0], pts[-1] = a, b
        return pts


@dataclass
class Notch:
    """A notch (balance mark) on a panel edge.

    Attributes:
        edge: index of the edge in the panel's edge list.
        t: position along the edge as a fraction of its arc length, in [0, 1].
        name: optional label.
    """

    edge: int
    t: float
    name: str = ""


@dataclass
class Panel:
    """A closed 2D panel outline with its 3D placement.

    Attributes:
        name: unique name within the pattern.
        vertices: (N, 2) corner positions in metres.
        edges: the outline, in order; edge ``i`` ends where edge ``i + 1`` starts.
        translation: (3,) placement translation in metres.
        rotation: (3,) extrinsic XYZ Euler angles in radians.
        label: optional free text (GarmentCode body-part labels such as "leg").
        notches: balance marks.
        grainline: (2,) unit vector of the fabric's warp direction in panel coordinates.
    """

    name: str
    vertices: np.ndarray
    edges: list[Edge]
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rotation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    label: str = ""
    notches: list[Notch] = field(default_factory=list)
    grainline: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0]))

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 2)
        self.translation = np.asarray(self.translation, dtype=np.float64).reshape(3)
        self.rotation = np.asarray(self.rotation, dtype=np.float64).reshape(3)
        g = np.asarray(self.grainline, dtype=np.float64).reshape(2)
        n = float(np.linalg.norm(g))
        if not np.isfinite(n) or n == 0.0:
            raise PatternError(f"panel '{self.name}': grainline must be a non-zero vector")
        self.grainline = g / n

    def edge_endpoints(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Start and end points (2,) of edge ``i``."""
        e = self.edges[i]
        return self.vertices[e.start], self.vertices[e.end]

    def edge_length(self, i: int) -> float:
        """Arc length of edge ``i`` in metres."""
        return self.edges[i].length(*self.edge_endpoints(i))

    def outline(self, resolution: int = 32) -> np.ndarray:
        """Closed outline as a polyline without the repeated last point: (M, 2)."""
        parts = [e.polyline(*self.edge_endpoints(i), resolution)[:-1] for i, e in enumerate(self.edges)]
        return np.concatenate(parts, axis=0)

    def rotation_matrix(self) -> np.ndarray:
        """(3, 3) placement rotation."""
        return Rotation.from_euler("xyz", self.rotation).as_matrix()

    def to_3d(self, points: np.ndarray) -> np.ndarray:
        """Place panel points (n, 2) in 3D by the panel's rotation and translation: (n, 3)."""
        p = np.asarray(points, dtype=np.float64)
        p3 = np.concatenate([p, np.zeros((p.shape[0], 1))], axis=1)
        return p3 @ self.rotation_matrix().T + self.translation

    def area(self) -> float:
        """Signed area of the outline (positive when counter-clockwise), square metres."""
        o = self.outline()
        x, y = o[:, 0], o[:, 1]
        return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


@dataclass(frozen=True)
class EdgeRef:
    """A reference to one edge of one panel."""

    panel: str
    edge: int


@dataclass
class Stitch:
    """Two panel edges sewn together, with explicit orientation."""

    a: EdgeRef
    b: EdgeRef
    orientation: StitchOrientation = StitchOrientation.OPPOSITE

    def __post_init__(self) -> None:
        self.orientation = StitchOrientation(self.orientation)


@dataclass
class SewingPattern:
    """Panels and stitches of a garment.

    Attributes:
        name: pattern name.
        panels: panels by name, in a stable order.
        stitches: seams between panel edges.
        metadata: free-form information carried through files (drafting measurements, source file).
        support: the supporting line, the paper's sticking line (Wang 2018, Eq. 4's ``F(x)``): (panel name,
            edge) pairs, the edge given by its label or, for an unlabelled edge, its index as a string; the
            edges form one closed loop of unstitched edges (a waistband). Empty: the garment hangs from the
            shoulders. See :mod:`torchgarment.pattern.support`.
    """

    name: str
    panels: dict[str, Panel]
    stitches: list[Stitch] = field(default_factory=list)
    metadata: dict = field(default_factory=dict)
    support: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        self.support = tuple((str(a), str(b)) for a, b in self.support)

    def edge_index(self, panel: str, edge: str) -> int:
        """The index of the edge of ``panel`` named ``edge``: its label (unique in the panel), else an index.

        Raises:
            PatternError: no panel ``panel``, or no edge labelled ``edge`` and ``edge`` is not an index in
                range (or the label is ambiguous).
        """
        if panel not in self.panels:
            raise PatternError(f"pattern '{self.name}' has no panel '{panel}' (panels: "
                               f"{', '.join(self.panels)})")
        edges = self.panels[panel].edges
        hits = [i for i, e in enumerate(edges) if e.label and e.label == edge]
        if len(hits) == 1:
            return hits[0]
        if len(hits) > 1:
            raise PatternError(f"panel '{panel}' has {len(hits)} edges labelled '{edge}'; name the edge by "
                               f"its index (0..{len(edges) - 1})")
        if edge.isdigit() and int(edge) < len(edges):
            return int(edge)
        labels = [e.label or str(i) for i, e in enumerate(edges)]
        raise PatternError(f"panel '{panel}' has no edge '{edge}' (edges: {', '.join(labels)})")

    def support_refs(self) -> list[EdgeRef]:
        """The support's edges as :class:`EdgeRef` s, in declaration order (see :meth:`edge_index`)."""
        return [EdgeRef(p, self.edge_index(p, e)) for p, e in self.support]

    def edge_length(self, ref: EdgeRef) -> float:
        """Arc length (metres) of a referenced edge."""
        return self.panels[ref.panel].edge_length(ref.edge)

    def validate(self, *, max_stitch_length_ratio: float = 1.5) -> None:
        """Raise :class:`PatternError` with a one-line reason if the pattern is unusable.

        Checks: at least one panel; every panel has >= 3 vertices, finite coordinates, edges with valid
        indices that chain into one closed loop visiting every vertex once, a non-self-crossing outline and a
        non-zero area; every stitch refers to existing panels and edges, no edge is stitched twice, and the
        two sides' lengths differ by at most ``max_stitch_length_ratio`` (ease is allowed, gross mismatch is
        not); the support (if any) is one closed loop of unstitched edges.
        """
        if not self.panels:
            raise PatternError(f"pattern '{self.name}' has no panels")
        for name, panel in self.panels.items():
            _validate_panel(name, panel)
        used: dict[EdgeRef, int] = {}
        for k, s in enumerate(self.stitches):
            for ref in (s.a, s.b):
                if ref.panel not in self.panels:
                    raise PatternError(f"stitch {k} refers to unknown panel '{ref.panel}'")
                if not 0 <= ref.edge < len(self.panels[ref.panel].edges):
                    raise PatternError(f"stitch {k} refers to edge {ref.edge} of panel '{ref.panel}', which "
                                       f"has {len(self.panels[ref.panel].edges)} edges")
                if ref in used:
                    raise PatternError(f"edge {ref.edge} of panel '{ref.panel}' is stitched twice "
                                       f"(stitches {used[ref]} and {k})")
                used[ref] = k
            la, lb = self.edge_length(s.a), self.edge_length(s.b)
            if min(la, lb) <= 0 or max(la, lb) / min(la, lb) > max_stitch_length_ratio:
                raise PatternError(
                    f"stitch {k} joins edges of mismatched length: {s.a.panel}[{s.a.edge}] {la * 1000:.1f} "
                    f"mm vs {s.b.panel}[{s.b.edge}] {lb * 1000:.1f} mm (ratio limit "
                    f"{max_stitch_length_ratio})"
                )
        if self.support:
            from torchgarment.pattern.support import ordered_loop

            ordered_loop(self)


def _validate_panel(name: str, panel: Panel) -> None:
    v = panel.vertices
    if v.shape[0] < 3:
        raise PatternError(f"panel '{name}' has {v.shape[0]} vertices; a closed outline needs at least 3")
    if not np.all(np.isfinite(v)):
        raise PatternError(f"panel '{name}' has non-finite vertex coordinates")
    if len(panel.edges) < 2:
        raise PatternError(f"panel '{name}' has {len(panel.edges)} edge(s); it cannot close")
    n = v.shape[0]
    for i, e in enumerate(panel.edges):
        if not (0 <= e.start < n and 0 <= e.end < n):
            raise PatternError(f"panel '{name}' edge {i} refers to a vertex outside 0..{n - 1}")
        nxt = panel.edges[(i + 1) % len(panel.edges)]
        if e.end != nxt.start:
            raise PatternError(f"panel '{name}' does not close: edge {i} ends at vertex {e.end} but edge "
                               f"{(i + 1) % len(panel.edges)} starts at vertex {nxt.start}")
        if np.linalg.norm(v[e.end] - v[e.start]) == 0.0:
            raise PatternError(f"panel '{name}' edge {i} has zero length")
    starts = [e.start for e in panel.edges]
    if len(set(starts)) != len(starts):
        raise PatternError(f"panel '{name}' outline visits a vertex twice")
    if len(panel.edges) > MAX_PANEL_EDGES:
        raise PatternError(f"panel '{name}' has {len(panel.edges)} edges, more than {MAX_PANEL_EDGES}: "
                           "simplify its outline (a pattern piece has tens to a few thousand points)")
    outline = panel.outline(resolution=16)
    if outline.shape[0] > MAX_OUTLINE_POINTS:
        raise PatternError(f"panel '{name}' outline has {outline.shape[0]} points when its curves are "
                           f"sampled, more than {MAX_OUTLINE_POINTS}: simplify it (fewer curved edges)")
    if abs(panel.area()) < 1e-8:
        raise PatternError(f"panel '{name}' has zero area")
    crossing = _first_self_crossing(outline)
    if crossing is not None:
        raise PatternError(f"panel '{name}' outline crosses itself near ({crossing[0]:.4f}, "
                           f"{crossing[1]:.4f}) m")


MAX_PANEL_EDGES = 5_000
"""Most edges a panel may have (:meth:`SewingPattern.validate`): a 200,000-vertex panel made the self-crossing
test allocate 37 GiB (issue 17); real pattern pieces have tens to a few thousand points."""
MAX_OUTLINE_POINTS = 10_000
"""Most points of a panel's sampled outline (16 per curved edge) in the self-crossing test, whose time grows
as the square of it (about 5 s at 10,000 points on this machine)."""


def _first_self_crossing(poly: np.ndarray, block_pairs: int = 2_000_000) -> np.ndarray | None:
    """First proper intersection point of two non-adjacent segments of a closed polyline (M, 2), or None.

    Segment pairs are tested in blocks of rows (about ``block_pairs`` pairs each), so memory stays bounded
    (about 150 bytes per pair of a block) whatever ``M``."""
    m = poly.shape[0]
    b = np.roll(poly, -1, axis=0)  # each segment's end
    rows = max(1, block_pairs // max(m, 1))
    for start in range(0, m, rows):
        hit = _crossing_in_rows(poly, b, start, min(m, start + rows))
        if hit is not None:
            return hit
    return None


def _crossing_in_rows(a: np.ndarray, b: np.ndarray, lo: int, hi: int) -> np.ndarray | None:
    """:func:`_first_self_crossing` of the segments ``a -> b`` (M, 2) over the pairs ``(i, j)``, ``lo <= i <
    hi``, ``j >= i + 2``."""
    m = a.shape[0]
    ii = np.arange(lo, hi)
    counts = np.maximum(m - (ii + 2), 0)
    i = np.repeat(ii, counts)
    if i.size == 0:
        return None
    j = np.arange(i.size) - np.repeat(np.cumsum(counts) - counts, counts) + i + 2
    keep = ~((i == 0) & (j == m - 1))  # first and last segments are adjacent
    i, j = i[keep], j[keep]
    p, r = a[i], b[i] - a[i]
    q, s = a[j], b[j] - a[j]
    denom = r[:, 0] * s[:, 1] - r[:, 1] * s[:, 0]
    qp = q - p
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (qp[:, 0] * s[:, 1] - qp[:, 1] * s[:, 0]) / denom
        u = (qp[:, 0] * r[:, 1] - qp[:, 1] * r[:, 0]) / denom
    eps = 1e-9
    hit = (np.abs(denom) > 1e-18) & (t > eps) & (t < 1 - eps) & (u > eps) & (u < 1 - eps)
    if not hit.any():
        return None
    k = int(np.argmax(hit))
    return p[k] + t[k] * r[k]
