"""Pattern exchange as DXF in ASTM D6673 / AAMA form (millimetres), and reading it back.

Writing uses ezdxf's ``ezdxf.addons.gerber_D6673`` add-on. That add-on does not build pattern content: it
only serialises a DXF R12 document the caller has filled with ASTM D6673 content, leaving out the layout
blocks (``$MODEL_SPACE``...) and tables that Gerber's strict parser rejects. The AAMA content is built here:

* one ``BLOCK`` per panel (block name: the panel name with characters DXF forbids replaced by ``_``),
  inserted into model space at the sheet position of :func:`torchgarment.pattern.svg.svg_panel_layout`;
  block coordinates are the panel's own coordinates in millimetres;
* layer ``1``: the cut line as one closed ``POLYLINE`` starting at the start vertex of edge 0, counter-
  clockwise as in the pattern; curves are dense polylines with chord error below ``0.01`` mm; plus
  ``TEXT`` "Piece Name: <name>" and "Quantity: 1";
* layer ``2``: ``POINT`` at every turn point (panel vertex); layer ``3``: ``POINT`` at every curve point;
* layer ``4``: notches as ``LINE`` from the cut line 6 mm into the piece;
* layer ``7``: the grainline as a ``LINE``;
* model space ``TEXT`` "Style Name: <pattern>" and "Units: METRIC".

What AAMA cannot hold goes on the extra layer ``TORCHGARMENT`` as ``TEXT`` entities that AAMA readers skip
(they only read the numbered layers): per block ``translation x y z`` (metres), ``rotation x y z``
(radians), ``label <text>``, ``edge_label <i> <text>``, ``notch_name <j> <text>``, and for every edge its
exact definition relative to its two turn points: ``edge <i> line``, ``edge <i> quadratic <u> <v>``,
``edge <i> cubic <u1> <v1> <u2> <v2>`` (relative controls, see :mod:`torchgarment.pattern.spec`) or
``edge <i> circle <radius metres> <large 0|1> <sweep 0|1>``; in model space one
``stitch <block a> <edge a> <block b> <edge b> <opposite|same>`` per stitch. Text outside printable ASCII
is written as DXF ``\\U+XXXX`` escapes. The pattern's free-form ``metadata`` is not stored.

Reading (:func:`load_dxf`) turns turn points into vertices and the curve points between two turn points
into one edge. When the piece carries an ``edge`` entry for every turn-point segment and an entry agrees
with its boundary points (each point within 1 um of the stored curve, and the curve within the writing
chord tolerance plus 1 um of the points), that exact edge is used, so our own files round-trip exactly
(kinds, controls, arcs). Otherwise (files from other CAD tools, or edited geometry) the edge is refitted:
a ``LINE`` when the points are collinear (within 1 um), an ``ARC`` when they lie on a circle (within
1 um), else a cubic Bezier fitted by Gauss-Newton on orthogonal distances (see :func:`_fit_cubic`). A
cubic that stays further than ``max_fit_error`` from its points, or loops back at an end, is split at the
point farthest from the chord (a new vertex) until every piece fits. Files from other CAD tools without
turn points get one at every polyline corner sharper than 20 degrees; clockwise pieces without
torchgarment data are reversed.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from typing import TYPE_CHECKING

import ezdxf
import numpy as np
from ezdxf.addons import gerber_D6673
from ezdxf.document import Drawing
from scipy.spatial import cKDTree

from torchgarment.errors import PatternError
from torchgarment.io.atomic import atomic_open
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
from torchgarment.pattern.svg import NOTCH_LENGTH, grainline_segment, notch_segment, svg_panel_layout

if TYPE_CHECKING:
    from ezdxf.layouts import BlockLayout

CHORD_TOLERANCE = 1e-5  # metres: max distance between a curve and its written polyline
LINE_TOLERANCE = 1e-6  # metres: curve points this close to the chord make a LINE edge
ARC_TOLERANCE = 1e-6  # metres: curve points this close to a circle make an ARC edge
DATA_LAYER = "TORCHGARMENT"
_MM = 1000.0
_FORBIDDEN = re.compile(r'[<>/\\":;?*|=`,\s]')
_ESCAPE = re.compile(r"\\U\+([0-9A-Fa-f]{4})")


# ---------------------------------------------------------------------------------------------- text
def _escape_text(s: str) -> str:
    """Printable ASCII as is; everything else (and the backslash) as DXF ``\\U+XXXX`` (UTF-16 units)."""
    out = []
    for ch in s:
        if 32 <= ord(ch) < 127 and ch != "\\":
            out.append(ch)
        else:
            units = ch.encode("utf-16-be", "surrogatepass")
            out.extend(f"\\U+{int.from_bytes(units[i:i + 2], 'big'):04X}" for i in range(0, len(units), 2))
    return "".join(out)


def _unescape_text(s: str) -> str:
    raw = _ESCAPE.sub(lambda m: chr(int(m.group(1), 16)), s)
    return raw.encode("utf-16", "surrogatepass").decode("utf-16")


def _block_names(names: list[str]) -> dict[str, str]:
    """Unique DXF-legal block names for panel names."""
    out: dict[str, str] = {}
    used: set[str] = set()
    for n in names:
        base = _FORBIDDEN.sub("_", n.encode("ascii", "replace").decode("ascii").replace("?", "_")) or "piece"
        if base.startswith("*"):
            base = "_" + base[1:]
        cand, k = base, 1
        while cand.upper() in used:
            k += 1
            cand = f"{base}_{k}"
        used.add(cand.upper())
        out[n] = cand
    return out


# ---------------------------------------------------------------------------------------------- writing
def _edge_params(edge: Edge, a: np.ndarray, b: np.ndarray, tol: float) -> np.ndarray:
    """Curve parameters in [0, 1) of an edge's polyline points (the end point excluded)."""
    if edge.kind is EdgeKind.LINE:
        return np.zeros(1)
    if edge.kind is EdgeKind.ARC:
        _, r, _, dt = edge.arc_center(a, b)
        step = 2.0 * math.acos(max(1.0 - tol / r, -1.0)) if tol < r else math.pi / 2
        n = max(2, math.ceil(abs(dt) / step))
    else:
        ctrl = np.concatenate([a[None], edge.absolute_controls(a, b), b[None]])
        deg = ctrl.shape[0] - 1
        second = ctrl[2:] - 2 * ctrl[1:-1] + ctrl[:-2]
        bound = deg * (deg - 1) * float(np.linalg.norm(second, axis=1).max())  # max |B''|
        n = max(2, math.ceil(math.sqrt(bound / (8.0 * tol)))) if bound > 0 else 2
    return np.arange(n) / n


def _check_chain(panel: Panel) -> None:
    edges = panel.edges
    if len(edges) < 2:
        raise PatternError(f"panel '{panel.name}' has {len(edges)} edge(s); it cannot close")
    for i, e in enumerate(edges):
        nxt = edges[(i + 1) % len(edges)]
        if e.end != nxt.start:
            raise PatternError(f"panel '{panel.name}' does not close: edge {i} ends at vertex {e.end} but "
                               f"edge {(i + 1) % len(edges)} starts at vertex {nxt.start}")


def pattern_dxf_document(pattern: SewingPattern) -> Drawing:
    """The DXF R12 document :func:`save_dxf` writes (ASTM D6673 blocks plus the ``TORCHGARMENT`` layer)."""
    if not pattern.panels:
        raise PatternError(f"pattern '{pattern.name}' has no panels to write")
    for p in pattern.panels.values():
        _check_chain(p)
    offsets, _ = svg_panel_layout(pattern)
    blocks = _block_names(list(pattern.panels))
    doc = Drawing.new("R12")  # not ezdxf.new: it sets $INSUNITS, which R12 cannot hold, and logs a warning
    msp = doc.modelspace()
    for name, panel in pattern.panels.items():
        blk = doc.blocks.new(name=blocks[name])
        parts = _edge_points(panel)
        turn = [pts[0] for pts in parts]
        curve = [q for pts in parts for q in pts[1:]]
        outline = np.concatenate(parts) * _MM
        blk.add_polyline2d([tuple(p) for p in outline], close=True, dxfattribs={"layer": "1"})
        for p in turn:
            blk.add_point(tuple(p * _MM), dxfattribs={"layer": "2"})
        for p in curve:
            blk.add_point(tuple(p * _MM), dxfattribs={"layer": "3"})
        for notch in panel.notches:
            s = notch_segment(panel, notch, NOTCH_LENGTH) * _MM
            blk.add_line(tuple(s[0]), tuple(s[1]), dxfattribs={"layer": "4"})
        g = grainline_segment(panel) * _MM
        blk.add_line(tuple(g[0]), tuple(g[1]), dxfattribs={"layer": "7"})
        centre = panel.outline(resolution=16).mean(axis=0) * _MM
        h = 8.0
        for k, text in enumerate([f"Piece Name: {name}", "Quantity: 1"]):
            blk.add_text(_escape_text(text), dxfattribs={"layer": "1", "height": h,
                                                           "insert": (centre[0],
                                                                      centre[1] - 1.5 * h * (k + 1))})
        data = [
            "translation " + " ".join(repr(float(x)) for x in panel.translation),
            "rotation " + " ".join(repr(float(x)) for x in panel.rotation),
        ]
        if panel.label:
            data.append(f"label {panel.label}")
        data += [_edge_entry(i, e) for i, e in enumerate(panel.edges)]
        data += [f"edge_label {i} {e.label}" for i, e in enumerate(panel.edges) if e.label]
        data += [f"notch_name {j} {n.name}" for j, n in enumerate(panel.notches) if n.name]
        for k, text in enumerate(data):
            blk.add_text(_escape_text(text), dxfattribs={"layer": DATA_LAYER, "height": 2.0,
                                                           "insert": (centre[0], centre[1] + 3.0 * (k + 1))})
        msp.add_blockref(blocks[name], tuple(offsets[name] * _MM))
    msp.add_text(_escape_text(f"Style Name: {pattern.name}"), dxfattribs={"layer": "1", "height": 8.0})
    msp.add_text("Units: METRIC", dxfattribs={"layer": "1", "height": 8.0, "insert": (0.0, -12.0)})
    for k, s in enumerate(pattern.stitches):
        for ref in (s.a, s.b):
            if ref.panel not in pattern.panels or not 0 <= ref.edge < len(pattern.panels[ref.panel].edges):
                raise PatternError(f"stitch {k} refers to a missing edge {ref.edge} of panel '{ref.panel}'")
        text = f"stitch {blocks[s.a.panel]} {s.a.edge} {blocks[s.b.panel]} {s.b.edge} {s.orientation.value}"
        msp.add_text(text, dxfattribs={"layer": DATA_LAYER, "height": 2.0, "insert": (0.0, -20.0 - 3.0 * k)})
    return doc


def _edge_entry(i: int, edge: Edge) -> str:
    """The ``edge`` entry of the data layer: the exact definition of edge ``i`` relative to its turn
    points."""
    if edge.kind is EdgeKind.ARC:
        r, large, sweep = edge.arc
        numbers = [repr(float(r)), str(int(large)), str(int(sweep))]
    elif edge.kind is EdgeKind.LINE:
        numbers = []
    else:
        numbers = [repr(float(x)) for x in np.asarray(edge.controls, dtype=np.float64).reshape(-1)]
    return " ".join([f"edge {i} {edge.kind.value}"] + numbers)


def _edge_points(panel: Panel) -> list[np.ndarray]:
    """Per edge, its turn point then its curve points, (k_i, 2) metres, the edge's end excluded."""
    parts = []
    for i, e in enumerate(panel.edges):
        a, b = panel.edge_endpoints(i)
        pts = e.evaluate(a, b, _edge_params(e, a, b, CHORD_TOLERANCE))
        pts[0] = a
        parts.append(pts)
    return parts


def save_dxf(path: str | os.PathLike, pattern: SewingPattern) -> None:
    """Write a pattern as ASTM D6673 / AAMA DXF (R12, millimetres); atomic.

    Args:
        path: destination ``.dxf`` file.
        pattern: the pattern (metres).

    Raises:
        PatternError: no panels, a panel whose edges do not chain into a loop, or a stitch to a missing edge.
    """
    doc = pattern_dxf_document(pattern)
    with atomic_open(path, "w", encoding="ascii") as f:
        gerber_D6673.export_stream(doc, f)


# ---------------------------------------------------------------------------------------------- reading
@dataclass
class _Fit:
    """One reconstructed edge: its kind, parameters and the curve points it stands for."""

    kind: EdgeKind
    points: np.ndarray  # (m, 2) metres, first and last are the edge's ends
    controls: np.ndarray | None = None  # (2, 2) relative
    arc: tuple[float, bool, bool] | None = None
    error: float = 0.0


def _relative(c: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = b - a
    perp = np.array([-d[1], d[0]])
    dd = float(d @ d)
    return np.stack([(c - a) @ d / dd, (c - a) @ perp / dd], axis=-1)


def _fit_circle(q: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Least-squares circle through points (m, 2): centre (2,), radius, max radial residual."""
    m = q.mean(axis=0)
    x = q - m
    a = np.concatenate([x, np.ones((x.shape[0], 1))], axis=1)
    sol, *_ = np.linalg.lstsq(a, -(x**2).sum(axis=1), rcond=None)
    c = -0.5 * sol[:2]
    r2 = float(c @ c - sol[2])
    if not np.isfinite(r2) or r2 <= 0:
        return m, math.inf, math.inf
    r = math.sqrt(r2)
    for _ in range(5):  # Gauss-Newton on the geometric residual |x - c| - r
        diff = x - c
        dist = np.linalg.norm(diff, axis=1)
        if np.any(dist == 0):
            break
        jac = np.concatenate([-diff / dist[:, None], -np.ones((x.shape[0], 1))], axis=1)
        step, *_ = np.linalg.lstsq(jac, -(dist - r), rcond=None)
        c, r = c + step[:2], r + float(step[2])
    res = float(np.abs(np.linalg.norm(x - c, axis=1) - r).max())
    return c + m, abs(r), res


def _bezier(ctrl: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cubic Bezier (4, 2) at t (m,): points, first and second derivatives, each (m, 2)."""
    t = t[:, None]
    s = 1 - t
    p = s**3 * ctrl[0] + 3 * s**2 * t * ctrl[1] + 3 * s * t**2 * ctrl[2] + t**3 * ctrl[3]
    d1 = 3 * (s**2 * (ctrl[1] - ctrl[0]) + 2 * s * t * (ctrl[2] - ctrl[1]) + t**2 * (ctrl[3] - ctrl[2]))
    d2 = 6 * (s * (ctrl[2] - 2 * ctrl[1] + ctrl[0]) + t * (ctrl[3] - 2 * ctrl[2] + ctrl[1]))
    return p, d1, d2


def _project(ctrl: np.ndarray, q: np.ndarray, t: np.ndarray, steps: int) -> np.ndarray:
    """Foot-point parameters (m,) of points q (m, 2) on the cubic ctrl, refined from t; ends stay at 0 and 1.

    Each point starts from the better of ``t`` and the nearest of 129 curve samples (so that a point cannot
    stay trapped at a far local minimum after the curve changed), then takes safeguarded Newton steps: the
    Gauss-Newton denominator ``|B'|^2`` is used where the full one is not clearly positive, and a step is
    at most 1/64 of the parameter range.
    """
    t = np.array(t, dtype=np.float64)
    grid = np.linspace(0.0, 1.0, 129)
    g, _, _ = _bezier(ctrl, grid)
    for chunk in range(0, q.shape[0], 2048):
        qc = q[chunk: chunk + 2048]
        d2 = ((qc[:, None, :] - g[None]) ** 2).sum(axis=-1)
        k = np.argmin(d2, axis=1)
        p, _, _ = _bezier(ctrl, t[chunk: chunk + 2048])
        worse = ((p - qc) ** 2).sum(axis=1) > d2[np.arange(qc.shape[0]), k]
        t[chunk: chunk + 2048] = np.where(worse, grid[k], t[chunk: chunk + 2048])
    for _ in range(steps):
        p, d1, d2 = _bezier(ctrl, t)
        diff = p - q
        num = (diff * d1).sum(axis=1)
        gn = (d1 * d1).sum(axis=1)
        den = gn + (diff * d2).sum(axis=1)
        den = np.where(den > 0.25 * gn, den, gn)
        ok = den > 1e-300
        step = np.clip(np.where(ok, num / np.where(ok, den, 1.0), 0.0), -1.0 / 64, 1.0 / 64)
        t = np.clip(t - step, 0.0, 1.0)
        t[0], t[-1] = 0.0, 1.0
    return t


def _fit_cubic(q: np.ndarray, iterations: int = 30) -> tuple[np.ndarray, float, bool]:
    """Cubic Bezier with ends ``q[0]``, ``q[-1]`` fitted to points (m, 2).

    Returns:
        Absolute inner controls (2, 2), the largest distance (metres) of a point from the curve, and whether
        the fit loops back at an end (an inner control behind its end's tangent).

    Two starts, the better result kept: parameters uniform in the point index (exact for curves sampled at
    uniform curve parameters, as :func:`save_dxf` and many CAD tools do) and normalised arc length. From
    each: the linear least-squares inner controls for those parameters, then Gauss-Newton on the orthogonal
    distances (project every point onto the curve, linearise the normal component of the residual in the
    four inner control coordinates, solve; a step that raises the squared error is shortened). A fit that
    loops back at an end (a tiny loop can hide inside the error bound and makes the outline cross itself)
    loses against one that does not.
    """
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(q, axis=0), axis=1))])
    best: tuple[np.ndarray, float, bool] | None = None
    for t in (np.linspace(0.0, 1.0, q.shape[0]), s / s[-1]):
        ctrl, err, loops = _fit_cubic_from(q, t, iterations)
        if best is None or (loops, err) < (best[2], best[1]):
            best = (ctrl, err, loops)
        if not best[2] and best[1] <= 1e-12 * s[-1]:
            break
    return best


def _fit_cubic_from(q: np.ndarray, t: np.ndarray, iterations: int) -> tuple[np.ndarray, float, bool]:
    """One start of :func:`_fit_cubic`: initial parameters t (m,) in [0, 1]."""
    a, b = q[0], q[-1]
    u = 1 - t
    basis = np.stack([3 * u**2 * t, 3 * u * t**2], axis=1)
    rhs = q - (u**3)[:, None] * a - (t**3)[:, None] * b
    inner, *_ = np.linalg.lstsq(basis, rhs, rcond=None)
    ctrl = np.stack([a, inner[0], inner[1], b])
    scale = float(np.linalg.norm(b - a))
    t = _project(ctrl, q, t, 8)
    p, d1, _ = _bezier(ctrl, t)
    cost = float(((p - q) ** 2).sum())
    for _ in range(iterations):
        tn = np.linalg.norm(d1, axis=1)
        normal = np.stack([-d1[:, 1], d1[:, 0]], axis=1) / np.where(tn > 0, tn, 1.0)[:, None]
        res = ((p - q) * normal).sum(axis=1)
        u = 1 - t
        b1, b2 = 3 * u**2 * t, 3 * u * t**2
        jac = np.stack([normal[:, 0] * b1, normal[:, 1] * b1, normal[:, 0] * b2, normal[:, 1] * b2], axis=1)
        step, *_ = np.linalg.lstsq(jac, -res, rcond=None)
        for _ in range(4):
            trial = ctrl.copy()
            trial[1] += step[:2]
            trial[2] += step[2:]
            t_trial = _project(trial, q, t, 8)
            p_trial, d1_trial, _ = _bezier(trial, t_trial)
            c_trial = float(((p_trial - q) ** 2).sum())
            if c_trial <= cost:
                break
            step = 0.25 * step
        else:
            break
        ctrl, t, p, d1, cost = trial, t_trial, p_trial, d1_trial, c_trial
        if float(np.abs(step).max()) < 1e-13 * max(scale, 1e-300):
            break
    err = float(np.linalg.norm(p - q, axis=1).max())
    loops = float((ctrl[1] - a) @ (q[1] - q[0])) <= 0.0 or float((b - ctrl[2]) @ (q[-1] - q[-2])) <= 0.0
    return ctrl[1:3], err, loops


def _fit_edge(q: np.ndarray, max_fit_error: float) -> list[_Fit]:
    """Edges standing for the points q (m, 2) from one turn point to the next (split when a cubic misfits)."""
    a, b = q[0], q[-1]
    d = b - a
    chord = float(np.linalg.norm(d))
    if chord == 0.0:
        raise PatternError("two consecutive turn points coincide")
    if q.shape[0] == 2:
        return [_Fit(EdgeKind.LINE, q)]
    rel = q - a
    along = rel @ d / chord
    off = np.abs(rel[:, 0] * d[1] - rel[:, 1] * d[0]) / chord
    if off.max() <= LINE_TOLERANCE and np.all(np.diff(along) >= -LINE_TOLERANCE):
        return [_Fit(EdgeKind.LINE, q, error=float(off.max()))]
    c, r, res = _fit_circle(q)
    if res <= ARC_TOLERANCE and r < 1e3 * chord:
        ang = np.unwrap(np.arctan2(q[:, 1] - c[1], q[:, 0] - c[0]))
        steps = np.diff(ang)
        dt = float(ang[-1] - ang[0])
        if np.all(steps * np.sign(dt) > 0):
            arc = (r, abs(dt) > math.pi, dt > 0)
            edge = Edge(0, 1, EdgeKind.ARC, arc=arc)
            cc, rr, t0, sweep = edge.arc_center(a, b)
            err = float(np.abs(np.linalg.norm(q - cc, axis=1) - rr).max())
            if err <= ARC_TOLERANCE and abs(abs(sweep) - abs(dt)) < 1e-6:
                return [_Fit(EdgeKind.ARC, q, arc=arc, error=err)]
    ctrl, err, loops = _fit_cubic(q)
    if (err <= max_fit_error and not loops) or q.shape[0] <= 4:
        return [_Fit(EdgeKind.CUBIC, q, controls=_relative(ctrl, a, b), error=err)]
    # split at the point farthest from the chord (a stable choice that is never an end)
    k = int(np.argmax(off[1:-1])) + 1
    return _fit_edge(q[: k + 1], max_fit_error) + _fit_edge(q[k:], max_fit_error)


def _dist_to_polyline(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Distance (n,) of points (n, 2) to an open polyline (m, 2), m >= 2."""
    a, ab = poly[:-1], np.diff(poly, axis=0)
    ab2 = np.maximum((ab * ab).sum(axis=1), 1e-300)
    out = []
    for q in np.array_split(p, max(1, (p.shape[0] * a.shape[0]) // 200_000 + 1)):
        rel = q[:, None, :] - a[None]
        t = np.clip((rel * ab[None]).sum(axis=-1) / ab2[None], 0.0, 1.0)
        out.append(np.linalg.norm(rel - t[..., None] * ab[None], axis=-1).min(axis=1))
    return np.concatenate(out)


def _parse_edge_entry(rest: str) -> tuple[int, Edge]:
    """``<i> <kind> <numbers>`` of an ``edge`` data entry: the index and the edge (vertices 0 -> 1)."""
    parts = rest.split()
    i, kind = int(parts[0]), EdgeKind(parts[1])
    nums = [float(x) for x in parts[2:]]
    need = {EdgeKind.LINE: 0, EdgeKind.QUADRATIC: 2, EdgeKind.CUBIC: 4, EdgeKind.ARC: 3}[kind]
    if len(nums) != need or not all(math.isfinite(x) for x in nums):
        raise ValueError(f"{kind.value} edge needs {need} finite numbers")
    if kind is EdgeKind.ARC:
        if nums[0] <= 0 or nums[1] not in (0.0, 1.0) or nums[2] not in (0.0, 1.0):
            raise ValueError("arc needs radius > 0 and 0/1 flags")
        return i, Edge(0, 1, kind, arc=(nums[0], bool(nums[1]), bool(nums[2])))
    if kind is EdgeKind.LINE:
        return i, Edge(0, 1, kind)
    return i, Edge(0, 1, kind, controls=np.array(nums).reshape(-1, 2))


def _exact_fit(edge: Edge, q: np.ndarray) -> _Fit | None:
    """The stored exact edge if it agrees with the boundary points q (m, 2) between two turn points, else
    None.

    Agreement: the points are, within ``LINE_TOLERANCE``, the curve at the parameters :func:`save_dxf`
    samples; or (points resampled by another tool) every point lies within ``LINE_TOLERANCE`` of the curve
    (sampled with chord error ``LINE_TOLERANCE / 10``) and every such curve sample lies within
    ``CHORD_TOLERANCE + LINE_TOLERANCE`` of the boundary polyline.
    """
    a, b = q[0], q[-1]
    if float(np.linalg.norm(b - a)) == 0.0:
        return None
    written = _edge_params(edge, a, b, CHORD_TOLERANCE)
    if written.shape[0] == q.shape[0] - 1:  # the points save_dxf writes for this edge: compare one to one
        pts = np.concatenate([edge.evaluate(a, b, written), b[None]])
        err = float(np.linalg.norm(pts - q, axis=1).max())
        if err <= LINE_TOLERANCE:
            return _Fit(edge.kind, q, controls=edge.controls, arc=edge.arc, error=err)
    dense = np.concatenate([edge.evaluate(a, b, _edge_params(edge, a, b, 0.1 * LINE_TOLERANCE)), b[None]])
    dense[0] = a
    on_curve = float(_dist_to_polyline(q, dense).max())
    if (on_curve > LINE_TOLERANCE
            or float(_dist_to_polyline(dense, q).max()) > CHORD_TOLERANCE + LINE_TOLERANCE):
        return None
    return _Fit(edge.kind, q, controls=edge.controls, arc=edge.arc, error=on_curve)


@dataclass
class _Piece:
    block: str
    name: str
    points: np.ndarray  # (M, 2) closed boundary without the repeated point, metres
    turn: np.ndarray  # (T,) sorted indices into points
    notches: list[np.ndarray]  # (2, 2) segments, metres
    grainline: np.ndarray | None
    data: list[str]


MAX_DXF_BYTES = 256 * 2**20
"""Largest DXF file read (256 MiB; a graded set of a garment is a few hundred kB)."""


def _read_doc(path: str | os.PathLike) -> Drawing:
    if os.path.isdir(path):
        raise PatternError(f"'{path}' is a folder, not a DXF file")
    if not os.path.isfile(path):
        raise PatternError(f"DXF file '{path}' does not exist")
    size = os.path.getsize(path)
    if size > MAX_DXF_BYTES:
        raise PatternError(f"'{path}': {size / 2**20:.1f} MiB is too large for a pattern DXF (limit "
                           f"{MAX_DXF_BYTES // 2**20} MiB)")
    try:
        return ezdxf.readfile(path)
    except Exception as exc:  # ezdxf raises many types on garbage; all mean "not a readable DXF"
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise PatternError(f"'{path}' is not a readable DXF file: {reason}") from exc


def _bulge_points(p0: np.ndarray, p1: np.ndarray, bulge: float, tol: float) -> np.ndarray:
    """Points from p0 (included) toward p1 (excluded) along a DXF bulge arc (bulge = tan(angle / 4))."""
    if bulge == 0.0:
        return p0[None]
    theta = 4.0 * math.atan(bulge)  # signed, positive counter-clockwise
    chord = p1 - p0
    c_len = float(np.linalg.norm(chord))
    if c_len == 0.0:
        return p0[None]
    r = c_len / (2.0 * abs(math.sin(theta / 2.0)))
    mid = 0.5 * (p0 + p1)
    left = np.array([-chord[1], chord[0]]) / c_len
    centre = mid + left * (r * math.cos(theta / 2.0)) * math.copysign(1.0, theta)
    step = 2.0 * math.acos(max(1.0 - tol / r, -1.0)) if tol < r else math.pi / 2
    n = max(2, math.ceil(abs(theta) / step))
    ang = math.atan2(p0[1] - centre[1], p0[0] - centre[0]) + theta * np.arange(n) / n
    pts = centre + r * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    pts[0] = p0
    return pts


def _boundary(entities: list, tol: float, name: str) -> np.ndarray | None:
    """Largest closed boundary polyline on layer 1 (bulge arcs sampled), (M, 2) in file units, or None.

    Raises:
        PatternError: a boundary vertex with a non-finite coordinate or bulge (piece ``name``).
    """
    best, best_area = None, -1.0
    for e in entities:
        if (e.dxftype() == "POLYLINE" and e.dxf.layer == "1" and not e.is_3d_polyline
                and not e.is_poly_face_mesh and not e.is_polygon_mesh):
            verts = [(v.dxf.location.x, v.dxf.location.y, v.dxf.bulge) for v in e.vertices]
        elif e.dxftype() == "LWPOLYLINE" and e.dxf.layer == "1":
            verts = [(x, y, b) for x, y, b in e.get_points("xyb")]
        else:
            continue
        if len(verts) < 3:
            continue
        v = np.array(verts, dtype=np.float64)
        if not np.isfinite(v).all():
            raise PatternError(f"DXF piece '{name}': its boundary has a non-finite coordinate (nan or inf)")
        if np.allclose(v[0, :2], v[-1, :2], atol=1e-9):
            v = v[:-1]
        nxt = np.roll(v[:, :2], -1, axis=0)
        pts = np.concatenate([_bulge_points(v[i, :2], nxt[i], float(v[i, 2]), tol)
                              for i in range(v.shape[0])])
        keep = np.ones(pts.shape[0], dtype=bool)
        keep[1:] = np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9
        pts = pts[keep]
        if pts.shape[0] < 3:
            continue
        area = abs(_signed_area(pts))
        if area > best_area:
            best, best_area = pts, area
    return best


def _corner_indices(pts: np.ndarray, degrees: float = 20.0) -> np.ndarray:
    d_in = pts - np.roll(pts, 1, axis=0)
    d_out = np.roll(pts, -1, axis=0) - pts
    cos = (d_in * d_out).sum(axis=1) / (np.linalg.norm(d_in, axis=1) * np.linalg.norm(d_out, axis=1))
    return np.nonzero(cos < math.cos(math.radians(degrees)))[0]


def _read_piece(block: BlockLayout, scale: float) -> _Piece | None:
    entities = list(block)
    pts = _boundary(entities, 1e-3, block.name)  # file units: mm, or inches
    if pts is None:
        return None
    name, data, turn_pts, notches, grain = block.name, [], [], [], None
    for e in entities:
        kind, layer = e.dxftype(), e.dxf.layer
        if kind == "TEXT":
            text = _unescape_text(e.dxf.text)
            if layer == DATA_LAYER:
                data.append(text)
            elif text.lower().startswith("piece name:"):
                name = text.split(":", 1)[1].strip() or name
        elif kind == "POINT" and layer == "2":
            turn_pts.append((e.dxf.location.x, e.dxf.location.y))
        elif kind == "LINE" and layer in ("4", "7"):
            seg = np.array([(e.dxf.start.x, e.dxf.start.y), (e.dxf.end.x, e.dxf.end.y)]) * scale
            if layer == "4":
                notches.append(seg)
            elif grain is None:
                grain = seg
    marks = [np.asarray(turn_pts, dtype=np.float64).reshape(-1)] + [seg.reshape(-1) for seg in notches]
    if grain is not None:
        marks.append(grain.reshape(-1))
    if not np.isfinite(np.concatenate(marks)).all():
        raise PatternError(f"DXF piece '{name}': a turn point, notch or grain line has a non-finite "
                           "coordinate (nan or inf)")
    if turn_pts:
        dist, idx = cKDTree(pts).query(np.asarray(turn_pts), distance_upper_bound=1e-3)
        turn = np.unique(idx[np.isfinite(dist)])
    else:
        turn = _corner_indices(pts)
    if turn.shape[0] < 2:
        raise PatternError(f"DXF piece '{name}' has {turn.shape[0]} turn point(s) on its boundary; need at "
                           "least 2")
    pts = np.roll(pts, -int(turn[0]), axis=0) * scale
    turn = turn - turn[0]
    if not data and _signed_area(pts) < 0:  # foreign clockwise piece: make it counter-clockwise
        pts = np.concatenate([pts[:1], pts[:0:-1]])
        turn = np.sort((-turn) % pts.shape[0])
    return _Piece(block.name, name, pts, turn, notches, grain, data)


def _signed_area(p: np.ndarray) -> float:
    return 0.5 * float(np.dot(p[:, 0], np.roll(p[:, 1], -1)) - np.dot(p[:, 1], np.roll(p[:, 0], -1)))


def _notch_on(panel: Panel, seg: np.ndarray) -> Notch:
    """Edge and arc-length fraction of the outline point closest to a notch line's nearer end."""
    n = 512
    best = (math.inf, 0, 0.0)
    for i, e in enumerate(panel.edges):
        pts = e.sample_by_length(*panel.edge_endpoints(i), n)
        for end in seg:
            d = np.linalg.norm(pts - end, axis=1)
            k = int(np.argmin(d))
            if d[k] < best[0]:
                best = (float(d[k]), i, k / n)
    return Notch(best[1], best[2])


def _build_panel(piece: _Piece, max_fit_error: float) -> tuple[Panel, list[list[int]], float]:
    """Panel from a piece; also, per turn-point segment, the indices of the edges it became, and the worst
    fit."""
    m = piece.points.shape[0]
    bounds = list(piece.turn) + [m]
    closed = np.concatenate([piece.points, piece.points[:1]])
    exact: dict[int, Edge] = {}
    for line in piece.data:
        key, _, rest = line.partition(" ")
        if key == "edge":
            try:
                i, edge = _parse_edge_entry(rest)
            except (ValueError, IndexError, PatternError) as exc:
                raise PatternError(f"DXF piece '{piece.name}': bad {DATA_LAYER} entry '{line}'") from exc
            exact[i] = edge
    if set(exact) != set(range(len(piece.turn))):  # not the edges of these turn points: fit them all
        exact = {}
    fits: list[_Fit] = []
    seg_edges: list[list[int]] = []
    for k in range(len(piece.turn)):
        q = closed[bounds[k]: bounds[k + 1] + 1]
        known = _exact_fit(exact[k], q) if k in exact else None
        try:
            parts = [known] if known is not None else _fit_edge(q, max_fit_error)
        except PatternError as exc:
            raise PatternError(f"DXF piece '{piece.name}': {exc}") from None
        seg_edges.append(list(range(len(fits), len(fits) + len(parts))))
        fits.extend(parts)
    n = len(fits)
    vertices = np.stack([f.points[0] for f in fits])
    edges = [Edge(i, (i + 1) % n, f.kind, controls=f.controls, arc=f.arc) for i, f in enumerate(fits)]
    panel = Panel(piece.name, vertices, edges)
    if piece.grainline is not None and np.linalg.norm(piece.grainline[1] - piece.grainline[0]) > 0:
        panel.grainline = (piece.grainline[1] - piece.grainline[0]) / np.linalg.norm(
            piece.grainline[1] - piece.grainline[0])
    panel.notches = [_notch_on(panel, s) for s in piece.notches]
    for line in piece.data:
        key, _, rest = line.partition(" ")
        try:
            if key in ("translation", "rotation"):
                value = np.array([float(x) for x in rest.split()], dtype=np.float64).reshape(3)
                if not np.isfinite(value).all():
                    raise PatternError(f"DXF piece '{piece.name}': non-finite number (nan or inf) in its "
                                       f"{DATA_LAYER} entry '{line}'")
                setattr(panel, key, value)
            elif key == "label":
                panel.label = rest
            elif key == "edge_label":
                i, _, text = rest.partition(" ")
                panel.edges[seg_edges[int(i)][0]].label = text
            elif key == "notch_name":
                j, _, text = rest.partition(" ")
                panel.notches[int(j)].name = text
        except PatternError:
            raise
        except (ValueError, IndexError) as exc:
            raise PatternError(f"DXF piece '{piece.name}': bad {DATA_LAYER} entry '{line}'") from exc
    return panel, seg_edges, max(f.error for f in fits)


def load_dxf(path: str | os.PathLike, *, max_fit_error: float = 5e-5) -> SewingPattern:
    """Read an ASTM D6673 / AAMA DXF pattern (as written by :func:`save_dxf` or other CAD tools).

    Every block with a closed boundary polyline on layer 1 is a piece; turn points (layer 2) become panel
    vertices and the boundary points between them one edge each: the exact edge stored on the
    ``TORCHGARMENT`` layer when it agrees with the points, else a fitted line, arc or cubic (see the module
    docstring). Stitches, placements and labels come back from the ``TORCHGARMENT`` layer when present.

    Args:
        path: a ``.dxf`` file; "Units: ENGLISH" in model space means inches, otherwise millimetres.
        max_fit_error: largest distance (metres) a fitted cubic may stay from its points before the edge is
            split at a new vertex.

    Returns:
        The pattern in metres; ``metadata`` holds ``source`` (the path) and ``dxf_max_fit_error`` (metres).

    Raises:
        PatternError: unreadable or non-DXF file, no pieces, a piece without turn points, a stitch to an
            unknown piece or to an edge that had to be split.
    """
    doc = _read_doc(path)
    msp = doc.modelspace()
    style, scale, stitch_lines = None, 1e-3, []
    for e in msp:
        if e.dxftype() != "TEXT":
            continue
        text = _unescape_text(e.dxf.text)
        low = text.lower()
        if e.dxf.layer == DATA_LAYER and low.startswith("stitch "):
            stitch_lines.append(text)
        elif low.startswith("style name:"):
            style = text.split(":", 1)[1].strip()
        elif low.startswith("units:") and "english" in low:
            scale = 25.4e-3
    pieces = []
    for block in doc.blocks:
        if block.block_record.is_any_layout:
            continue
        piece = _read_piece(block, scale)
        if piece is not None:
            pieces.append(piece)
    if not pieces:
        raise PatternError(f"DXF file '{path}' has no pattern pieces (blocks with a closed layer-1 boundary)")
    panels: dict[str, Panel] = {}
    by_block: dict[str, tuple[str, list[list[int]]]] = {}
    worst = 0.0
    for piece in pieces:
        name = piece.name
        k = 1
        while name in panels:
            k += 1
            name = f"{piece.name}_{k}"
        piece.name = name
        panel, seg_edges, err = _build_panel(piece, max_fit_error)
        panels[name] = panel
        by_block[piece.block.upper()] = (name, seg_edges)
        worst = max(worst, err)
    stitches = [_parse_stitch(line, by_block) for line in stitch_lines]
    return SewingPattern(style or os.path.splitext(os.path.basename(path))[0], panels, stitches,
                         {"source": str(path), "dxf_max_fit_error": worst})


def _parse_stitch(line: str, by_block: dict[str, tuple[str, list[list[int]]]]) -> Stitch:
    parts = line.split()
    try:
        _, ba, ea, bb, eb, orient = parts
        refs = []
        for blk, edge in ((ba, int(ea)), (bb, int(eb))):
            if blk.upper() not in by_block:
                raise PatternError(f"DXF stitch '{line}' refers to unknown piece '{blk}'")
            name, seg_edges = by_block[blk.upper()]
            if not 0 <= edge < len(seg_edges):
                raise PatternError(f"DXF stitch '{line}' refers to edge {edge}, piece '{name}' has "
                                   f"{len(seg_edges)}")
            if len(seg_edges[edge]) != 1:
                raise PatternError(f"DXF stitch '{line}': edge {edge} of '{name}' did not fit one curve and "
                                   "was split")
            refs.append(EdgeRef(name, seg_edges[edge][0]))
        return Stitch(refs[0], refs[1], StitchOrientation(orient))
    except PatternError:
        raise
    except ValueError as exc:
        raise PatternError(f"malformed DXF stitch entry '{line}'") from exc


# ---------------------------------------------------------------------------------------------- graded sets
def graded_dxf_document(patterns: dict[str, SewingPattern], *, sample_size: str | None = None,
                        style: str | None = None) -> Drawing:
    """One ASTM D6673 / AAMA DXF holding every size of a graded pattern ("all sizes in the DXF file").

    A graded set goes to CAD systems either as the sample size plus grade rules (a ``.rul`` table) or, as
    here, with every size's piece written out: one ``BLOCK`` per piece per size, block name
    ``<piece>_<size>`` (DXF-legal, unique), holding exactly what :func:`save_dxf` writes for that piece
    (same layers, ``TORCHGARMENT`` data) plus the piece system text ``Size: <size>``; the piece name text
    (``Piece Name: <panel>``) is the same for every size, so importers group the sizes of a piece. All
    sizes of a piece are inserted at one sheet position (a graded nest, panel-local coordinates). Model
    space carries ``Style Name``, ``Sample Size`` (when given), ``Units: METRIC`` and one ``stitch`` data
    entry per stitch per size (block names of that size), so :func:`load_dxf` reads the file back as one
    pattern with every size's pieces.

    Args:
        patterns: size name -> the pattern of that size (metres), in size order; every size should have the
            same panels.
        sample_size: the base (sample) size, written as ``Sample Size: <name>``; must be a key of
            ``patterns``.
        style: style name; default the first pattern's name.

    Returns:
        The DXF R12 document.

    Raises:
        PatternError: no sizes, an unknown ``sample_size``, or what :func:`pattern_dxf_document` raises for a
            size's pattern.
    """
    if not patterns:
        raise PatternError("graded DXF: no sizes to write")
    if sample_size is not None and sample_size not in patterns:
        raise PatternError(f"graded DXF: sample size {sample_size!r} is not one of the sizes "
                           f"{', '.join(patterns)}")
    first = next(iter(patterns.values()))
    offsets, _ = svg_panel_layout(first)
    doc = Drawing.new("R12")
    msp = doc.modelspace()
    keys = [(size, name) for size, pat in patterns.items() for name in pat.panels]
    graded = _block_names([f"{name}_{size}" for size, name in keys])
    stitch_texts = []
    for size, pattern in patterns.items():
        src = pattern_dxf_document(pattern)  # validates the pattern; one block per panel
        own = _block_names(list(pattern.panels))
        for name, panel in pattern.panels.items():
            block = graded[f"{name}_{size}"]
            blk = doc.blocks.new(name=block)
            for e in src.blocks.get(own[name]):
                blk.add_foreign_entity(e)
            centre = panel.outline(resolution=16).mean(axis=0) * _MM
            blk.add_text(_escape_text(f"Size: {size}"), dxfattribs={"layer": "1", "height": 8.0,
                                                                   "insert": (centre[0], centre[1] - 36.0)})
            off = offsets.get(name)
            msp.add_blockref(block, tuple((off if off is not None else np.zeros(2)) * _MM))
        for s in pattern.stitches:
            stitch_texts.append(f"stitch {graded[f'{s.a.panel}_{size}']} {s.a.edge} "
                                f"{graded[f'{s.b.panel}_{size}']} {s.b.edge} {s.orientation.value}")
    header = [f"Style Name: {style if style is not None else first.name}"]
    if sample_size is not None:
        header.append(f"Sample Size: {sample_size}")
    header.append("Units: METRIC")
    for k, text in enumerate(header):
        msp.add_text(_escape_text(text), dxfattribs={"layer": "1", "height": 8.0, "insert": (0.0, -12.0 * k)})
    for k, text in enumerate(stitch_texts):
        msp.add_text(_escape_text(text), dxfattribs={"layer": DATA_LAYER, "height": 2.0,
                                                     "insert": (0.0, -12.0 * len(header) - 3.0 * k)})
    return doc


def save_graded_dxf(path: str | os.PathLike, patterns: dict[str, SewingPattern], *,
                    sample_size: str | None = None, style: str | None = None) -> None:
    """Write every size of a graded pattern into one ASTM D6673 / AAMA DXF (see :func:`graded_dxf_document`);
    atomic.

    Args:
        path: destination ``.dxf`` file.
        patterns: size name -> pattern (metres). sample_size: the base size's name. style: style name.
    """
    doc = graded_dxf_document(patterns, sample_size=sample_size, style=style)
    with atomic_open(path, "w", encoding="ascii") as f:
        gerber_D6673.export_stream(doc, f)


def graded_dxf_sizes(path: str | os.PathLike) -> dict[str, dict[str, str]]:
    """The sizes of a graded DXF (as :func:`save_graded_dxf` writes): size -> piece name -> block name.

    Blocks without a ``Size:`` text are listed under the size ``""``.

    Raises:
        PatternError: unreadable or non-DXF file.
    """
    doc = _read_doc(path)
    out: dict[str, dict[str, str]] = {}
    for block in doc.blocks:
        if block.block_record.is_any_layout:
            continue
        piece, size = block.name, ""
        for e in block:
            if e.dxftype() != "TEXT" or e.dxf.layer != "1":
                continue
            text = _unescape_text(e.dxf.text)
            low = text.lower()
            if low.startswith("piece name:"):
                piece = text.split(":", 1)[1].strip() or piece
            elif low.startswith("size:"):
                size = text.split(":", 1)[1].strip()
        out.setdefault(size, {})[piece] = block.name
    return out
