"""Measurements of the pattern-adjustment acceptance study (``scripts/adjust_acceptance.py``).

* Pattern widths at construction lines: the width of a panel at a line is the distance between the start
  vertex of one labelled edge and the end vertex of another (:func:`line_width`); summed over panels it is the
  pattern's girth at that line (:func:`pattern_line_widths`). :data:`SKIRT_LINES` and :data:`TSHIRT_LINES`
  name the lines of the library's straight skirt and T-shirt.
* Mesh vertices of labelled edges and line corners, read from the mesh's
  :class:`~torchgarment.structures.MeshLayout` (:func:`boundary_vertex_labels`, :func:`line_vertices`).
* Rigid-motion-free deviation of 2D outlines (:func:`procrustes_deviation`).
* Bodies: the horizontal girth at a height (:func:`body_girth_at`) and derived target bodies, uniformly scaled
  (:func:`scaled_body`), with enlarged hips or bust (:func:`hips_body`, :func:`bust_body`,
  :func:`hip_weight`, :func:`amount_for_girth_change`).

Lengths are in metres.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import torch

from torchgarment.body.body import Body
from torchgarment.body.measure import SectionPlane, plane_basis, section_girths, section_loops
from torchgarment.body.skeleton import Skeleton
from torchgarment.errors import InputError, MeshError, PatternError

if TYPE_CHECKING:
    from torchgarment.adjust.pipeline import AdjustResult
    from torchgarment.pattern.library import DraftMeasurements
    from torchgarment.pattern.spec import Panel, SewingPattern
    from torchgarment.structures.garment_mesh import GarmentMesh, MeshLayout

__all__ = [
    "ARM_KEYS",
    "SKIRT_LINES",
    "TSHIRT_LINES",
    "amount_for_girth_change",
    "body_girth_at",
    "boundary_vertex_labels",
    "bust_body",
    "draft_measurements",
    "drafted_deviation",
    "edge_moves",
    "edges_length",
    "girth",
    "hip_weight",
    "hips_body",
    "line_corners",
    "line_vertices",
    "line_width",
    "pattern_line_widths",
    "procrustes_deviation",
    "scaled_outline_deviation",
    "scaled_body",
]

SKIRT_LINES = {"waist": ("waist_r", "waist_l"), "hips": ("side_hip_r", "side_hip_l")}
"""Construction lines of the straight skirt: line -> (label of the edge whose start vertex is the line's first
corner, label of the edge whose end vertex is its second)."""
TSHIRT_LINES = {"bust": ("armhole_r", "armhole_l"), "waist": ("side_up_r", "side_up_l")}
"""Construction lines of the T-shirt, as :data:`SKIRT_LINES`."""
ARM_KEYS = ("arm", "wrist", "finger", "metacarpal", "shoulder", "clavicle")
"""Substrings of the skeleton bone names whose skinned vertices :func:`hips_body` leaves in place."""


# ---------------------------------------------------------------------------------------------- outlines
def procrustes_deviation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances of ``a`` to ``b`` after the best rigid motion (rotation + translation, no scale) of ``a``.

    Args:
        a, b: (N, 2) corresponding points.

    Returns:
        (N,) distances ``|R a_i + t - b_i|`` for the least-squares ``R`` (proper rotation), ``t``.

    Raises:
        InputError: ``a`` and ``b`` are not two (N, 2) arrays of one shape.
    """
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 2:
        raise InputError(f"procrustes_deviation needs two (N, 2) arrays, got {a.shape} and {b.shape}")
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    A, B = a - ca, b - cb
    u, _, vt = np.linalg.svd(A.T @ B)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    R = (u @ np.diag([1.0, d]) @ vt).T  # maps A onto B: B ~ A R^T
    return np.linalg.norm(A @ R.T - B, axis=1)


def scaled_outline_deviation(result: AdjustResult, s: float) -> dict[str, dict[str, float]]:
    """Per panel, the adjusted boundary's distance from ``s`` times the base boundary, rigid motion removed.

    The manufactured solution: adjusted onto the base body scaled by ``s``, the exact answer is the base
    pattern scaled by ``s``. Per panel, :func:`procrustes_deviation` of the adjusted boundary vertices from
    ``s`` times the base ones.

    Returns:
        Per panel name: ``size_m`` (the base panel's bounding-box diagonal), ``max_m``, ``mean_m`` (the
        deviation), ``unadjusted_max_m``, ``unadjusted_mean_m`` (the base pattern's own deviation: what the
        adjustment has to recover).
    """
    bidx = result.boundary_index.cpu().numpy()
    vp = result.mesh_base.vertex_panel_ids.cpu().numpy()[bidx]
    pb = result.mesh_base.p.detach().cpu().double().numpy()[bidx]
    pn = result.mesh_target.p.detach().cpu().double().numpy()[bidx]
    out = {}
    for k, name in enumerate(result.mesh_base.panel_names):
        m = vp == k
        dev = procrustes_deviation(pn[m], s * pb[m])
        ref = procrustes_deviation(pb[m], s * pb[m])
        out[name] = {"size_m": float(np.linalg.norm(pb[m].max(axis=0) - pb[m].min(axis=0))),
                     "max_m": float(dev.max()), "mean_m": float(dev.mean()),
                     "unadjusted_max_m": float(ref.max()), "unadjusted_mean_m": float(ref.mean())}
    return out


def draft_measurements(body: Body) -> DraftMeasurements:
    """The drafting measurements of a body as a drafter would take them from it: the measured height and
    girths (:meth:`Body.measurements`) and the heights above the floor of its waist, hip and bust planes and
    of its crotch (0.01 of the height above the thigh plane); the rest from the proportion rules of
    :class:`~torchgarment.pattern.library.DraftMeasurements`."""
    from torchgarment.pattern.library import DraftMeasurements

    m = body.measurements()
    floor = float(body.vertices[:, 1].min())
    y = {name: float(m.planes[name].point[1]) - floor for name in ("waist", "hips", "bust", "thigh")}
    return DraftMeasurements(height=m.height, bust=m.bust, underbust=m.underbust, waist=m.waist, hips=m.hips,
                             waist_height=y["waist"], hip_height=y["hips"], bust_height=y["bust"],
                             crotch_height=y["thigh"] + 0.01 * m.height)


def drafted_deviation(pattern: SewingPattern, drafted: SewingPattern,
                      grade: tuple[SewingPattern, SewingPattern, SewingPattern] | None = None
                      ) -> dict[str, dict]:
    """Per panel, how far a graded pattern's corners are from a pattern drafted for the target, rigid motion
    removed (how a graded pattern is checked against a reference grade: the paper's 1.5 cm against manual
    grading).

    Args:
        pattern: the graded (adjusted) pattern. drafted: the same design drafted for the target body (e.g.
            :func:`torchgarment.pattern.library.draft` for the target's chart row); panels of the same names
            and corner counts.
        grade: ``(base, drafted_base, drafted_target)``: compare instead with the drafting system's *grade*,
            ``base + (drafted_target - drafted_base)`` corner by corner (the change a drafter's measurements
            of the two bodies make, applied to the base pattern; ``drafted`` is then unused). With drafts
            from the bodies' own landmark heights (:func:`draft_measurements`) this is the reference a
            drafting system that measures the body, as GarmentCode does, gives.

    Returns:
        Per panel name: ``max_m``, ``mean_m`` (:func:`procrustes_deviation` of the corners, metres) and
        ``worst_corner`` (the label of the edge that starts at the farthest corner).

    Raises:
        PatternError: a panel of ``drafted`` is missing from ``pattern`` or has another number of corners.
    """
    out = {}
    for name, ref in (drafted if grade is None else grade[2]).panels.items():
        others = [pattern] if grade is None else [pattern, grade[0], grade[1]]
        if any(p.panels.get(name) is None or p.panels[name].vertices.shape != ref.vertices.shape
               for p in others):
            raise PatternError(f"panel {name!r} of the drafted pattern has no counterpart with as many "
                               "corners in the graded pattern")
        target = ref.vertices if grade is None else (
            grade[0].panels[name].vertices + ref.vertices - grade[1].panels[name].vertices)
        dev = procrustes_deviation(pattern.panels[name].vertices, target)
        worst = int(dev.argmax())
        label = next((e.label for e in ref.edges if e.start == worst), str(worst))
        out[name] = {"max_m": float(dev.max()), "mean_m": float(dev.mean()), "worst_corner": label}
    return out


# ---------------------------------------------------------------------------------------------- widths
def line_corners(panel: Panel, first: str, second: str) -> tuple[tuple[int, int], tuple[int, int]]:
    """The two corners of a construction line on a panel, as ``(edge index, 0 = start / 1 = end)`` pairs.

    The line joins the two ends of the run of edges from the edge labelled ``first`` to the one labelled
    ``second`` in the panel's edge order: the start of ``first`` and the end of ``second`` when ``first``
    comes first (or is ``second``: the edge's own ends), else the start of ``second`` and the end of
    ``first`` (a mirrored panel lists its edges in the reverse order).

    Raises:
        PatternError: the panel has no edge labelled ``first`` or ``second``.
    """
    labels = [e.label for e in panel.edges]
    if first not in labels or second not in labels:
        raise PatternError(f"panel {panel.name!r} has no edges {first!r}/{second!r}")
    i, j = labels.index(first), labels.index(second)
    if i > j:
        i, j = j, i
    return (i, 0), (j, 1)


def line_width(panel: Panel, first: str, second: str) -> float:
    """Distance (m) between the two corners of a construction line on a panel (:func:`line_corners`).

    Raises:
        PatternError: the panel has no edge labelled ``first`` or ``second``.
    """
    (i, a_end), (j, b_end) = line_corners(panel, first, second)
    a = panel.edge_endpoints(i)[a_end]
    b = panel.edge_endpoints(j)[b_end]
    return float(np.linalg.norm(np.asarray(b) - np.asarray(a)))


def pattern_line_widths(pattern: SewingPattern, lines: dict[str, tuple[str, str]]) -> dict[str, float]:
    """Per construction line, the sum over the panels that have both edges of :func:`line_width` (m).

    Args:
        pattern: the pattern. lines: line name -> (first edge label, second edge label).

    Raises:
        PatternError: no panel has both edges of a line.
    """
    out = {}
    for name, (first, second) in lines.items():
        total, found = 0.0, False
        for panel in pattern.panels.values():
            labels = {e.label for e in panel.edges}
            if first in labels and second in labels:
                total += line_width(panel, first, second)
                found = True
        if not found:
            raise PatternError(f"pattern {pattern.name!r}: no panel has edges {first!r} and {second!r}")
        out[name] = total
    return out


def edges_length(pattern: SewingPattern, labels: tuple[str, ...]) -> float:
    """Total length (m) of the edges with these labels over all panels (e.g. the waistband's girth).

    Raises:
        PatternError: no edge has one of these labels.
    """
    total = sum(p.edge_length(i) for p in pattern.panels.values() for i, e in enumerate(p.edges)
                if e.label in labels)
    if total == 0.0:
        raise PatternError(f"pattern {pattern.name!r} has no edges labelled {labels}")
    return float(total)


# ---------------------------------------------------------------------------------------------- mesh vertices
def _layout(mesh: GarmentMesh) -> MeshLayout:
    if mesh.layout is None:
        raise InputError("the mesh has no layout: make it with torchgarment.pattern.meshing.mesh_pattern")
    return mesh.layout


def boundary_vertex_labels(pattern: SewingPattern, mesh: GarmentMesh) -> tuple[np.ndarray, np.ndarray]:
    """Mesh vertex indices of every panel edge's boundary samples (end points included) and their edge labels.

    Args:
        pattern: the pattern ``mesh`` was made from. mesh: made by ``mesh_pattern`` (it has a ``layout``).

    Returns:
        ``(vertex, label)``: (M,) int array and (M,) object array (a corner appears once per adjacent edge).

    Raises:
        InputError: the mesh has no layout. MeshError: a panel of the pattern is not in the mesh.
    """
    layout = _layout(mesh)
    verts, labels = [], []
    for name, panel in pattern.panels.items():
        for e, run in zip(panel.edges, layout.runs(name), strict=True):
            idx = run.cpu().numpy()
            verts.append(idx)
            labels.append(np.full(idx.shape, e.label, dtype=object))
    return np.concatenate(verts), np.concatenate(labels)


def edge_moves(pattern: SewingPattern, result: AdjustResult, labels: tuple[str, ...]) -> dict[str, float]:
    """How the pattern moved along the edges with these labels in an adjustment (m).

    Returns:
        ``max_m``: the largest move of their boundary vertices in panel coordinates (base to adjusted);
        ``shape_max_m``: the largest after each panel's own best rigid motion of those vertices
        (:func:`procrustes_deviation`: a piece moved on the cutting table is the same piece).

    Raises:
        PatternError: no edge has one of the labels.
    """
    verts, lab = boundary_vertex_labels(pattern, result.mesh_base)
    sel = np.unique(verts[np.isin(lab, list(labels))])
    if sel.size == 0:
        raise PatternError(f"pattern {pattern.name!r} has no edges labelled {labels}")
    pb = result.mesh_base.p.detach().cpu().double().numpy()
    pn = result.mesh_target.p.detach().cpu().double().numpy()
    panel = result.mesh_base.vertex_panel_ids.cpu().numpy()
    shape = 0.0
    for k in np.unique(panel[sel]):
        v = sel[panel[sel] == k]
        if v.size >= 2:
            shape = max(shape, float(procrustes_deviation(pn[v], pb[v]).max()))
    return {"max_m": float(np.linalg.norm(pn[sel] - pb[sel], axis=1).max()), "shape_max_m": shape}


def line_vertices(pattern: SewingPattern, mesh: GarmentMesh, first: str, second: str) -> np.ndarray:
    """Mesh vertex indices of a construction line's corners.

    Per panel with both edges, the two corners of :func:`line_corners` (the two points :func:`line_width`
    measures).

    Args:
        pattern: the pattern ``mesh`` was made from. mesh: made by ``mesh_pattern`` (it has a ``layout``).
        first, second: edge labels.

    Returns:
        (2 K,) int64 array, K the number of panels with both edges, the two corners of each panel in turn.

    Raises:
        InputError: the mesh has no layout. PatternError: no panel has both edges.
    """
    layout = _layout(mesh)
    out = []
    for name, panel in pattern.panels.items():
        labels = {e.label for e in panel.edges}
        if first in labels and second in labels:
            runs = layout.runs(name)
            (i, a_end), (j, b_end) = line_corners(panel, first, second)
            out += [int(runs[i][0 if a_end == 0 else -1]), int(runs[j][0 if b_end == 0 else -1])]
    if not out:
        raise PatternError(f"pattern {pattern.name!r}: no panel has edges {first!r} and {second!r}")
    return np.asarray(out, dtype=np.int64)


# ---------------------------------------------------------------------------------------------- bodies
def body_girth_at(body: Body, y: float) -> float:
    """The body's horizontal tape girth (m) at height ``y`` (m).

    Above the crotch, the perimeter of the convex hull of the section loop around the body's vertical axis
    (x = z = 0, where bodies are centred), as :func:`torchgarment.body.measure.section_girths` (arms, separate
    loops, are left out). Below it, where no loop encloses the axis, the tape goes around both legs: the
    convex hull of the two loops nearest the axis.

    Raises:
        MeshError: the plane misses the body.
    """
    from scipy.spatial import ConvexHull

    v = body.vertices
    pt = torch.tensor([0.0, float(y), 0.0], dtype=v.dtype, device=v.device)
    up = torch.tensor([0.0, 1.0, 0.0], dtype=v.dtype, device=v.device)
    loops = [lp for lp in section_loops(v, body.faces, pt, up) if lp.closed]
    if not loops:
        raise MeshError(f"the horizontal plane at y = {y:.3f} m misses the body")
    basis = plane_basis(up.cpu().numpy())
    if any(_encloses_origin(lp.points @ basis.T, lp.segments) for lp in loops):
        return float(section_girths(v, body.faces, {"line": SectionPlane("line", pt, up, pt)})["line"])
    near = sorted(loops, key=lambda lp: float(np.min(np.linalg.norm(lp.points[:, [0, 2]], axis=1))))[:2]
    p2 = np.concatenate([lp.points for lp in near]) @ basis.T
    h = p2[ConvexHull(p2).vertices]
    return float(np.linalg.norm(h - np.roll(h, 1, axis=0), axis=1).sum())


def _encloses_origin(p2: np.ndarray, segments: np.ndarray) -> bool:
    """Whether the closed polygon of the (K, 2) points ``p2`` joined by ``segments`` (S, 2) encloses (0, 0)
    (ray casting along +u)."""
    a, b = p2[segments[:, 0]], p2[segments[:, 1]]
    straddle = (a[:, 1] > 0.0) != (b[:, 1] > 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = a[:, 0] - a[:, 1] * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return int(np.count_nonzero(straddle & (x_cross > 0.0))) % 2 == 1


def girth(body: Body, name: str) -> float:
    """A body's measured girth (m), :meth:`Body.measurements` (``"waist"``, ``"hips"``, ``"bust"``)."""
    m = body.measurements()
    return float(getattr(m, name))


def scaled_body(body: Body, s: float) -> Body:
    """``body`` scaled uniformly by ``s`` about its feet centre (mean x, min y, mean z of the vertices).

    Vertices, skeleton joints and landmarks are scaled; faces, bones and skin weights are copied.
    """
    v = body.vertices
    c = torch.stack([v[:, 0].mean(), v[:, 1].min(), v[:, 2].mean()])
    sk = None
    if body.skeleton is not None:
        sk = Skeleton(c + s * (body.skeleton.joints - c), body.skeleton.bones.clone(),
                      list(body.skeleton.names))
    return Body(vertices=c + s * (v - c), faces=body.faces.clone(), skeleton=sk,
                skin_weights=None if body.skin_weights is None else body.skin_weights.clone(),
                landmarks={k: c + s * (x - c) for k, x in body.landmarks.items()},
                params={"derived": "scaled", "scale": s})


def hip_weight(y: torch.Tensor, y_hip: float, y_waist: float, y_thigh: float) -> torch.Tensor:
    """cos^2 bump of the heights ``y`` (any shape, m): 1 at ``y_hip``, 0 at and beyond ``y_waist`` (above) and
    ``y_thigh`` (below)."""
    up = ((y - y_hip) / (y_waist - y_hip)).clamp(0.0, 1.0)
    down = ((y_hip - y) / (y_hip - y_thigh)).clamp(0.0, 1.0)
    t = torch.where(y >= y_hip, up, down)
    return torch.cos(0.5 * math.pi * t) ** 2


def _widened(body: Body, w: torch.Tensor, centre: torch.Tensor, amount: float, tag: str) -> Body:
    """``body`` with x, z scaled by ``1 + amount * w`` about the vertical axis through ``centre``, the
    vertices of the arms and hands (skin weight of the bones named by :data:`ARM_KEYS`) unchanged."""
    v = body.vertices
    if body.skin_weights is not None and body.skeleton is not None and body.skeleton.names:
        arm = torch.tensor([any(k in n for k in ARM_KEYS) for n in body.skeleton.names], device=v.device)
        w = w * (1.0 - body.skin_weights[arm].sum(dim=0).clamp(0.0, 1.0))
    f = 1.0 + amount * w
    nv = v.clone()
    nv[:, 0] = centre[0] + f * (v[:, 0] - centre[0])
    nv[:, 2] = centre[2] + f * (v[:, 2] - centre[2])
    return Body(vertices=nv, faces=body.faces.clone(), skeleton=body.skeleton,
                skin_weights=body.skin_weights, landmarks=dict(body.landmarks),
                params={"derived": tag, "amount": amount})


def hips_body(body: Body, amount: float) -> Body:
    """``body`` with the hips enlarged: x, z scaled by ``1 + amount * w(y)`` about the hip landmark's vertical
    axis (:func:`hip_weight` between the waist and thigh landmarks), arm/hand vertices (skin weight of the
    bones named by :data:`ARM_KEYS`) unchanged."""
    lm = body.landmarks
    w = hip_weight(body.vertices[:, 1], float(lm["hips"][1]), float(lm["waist"][1]), float(lm["thigh"][1]))
    return _widened(body, w, lm["hips"], amount, "hips")


def bust_body(body: Body, amount: float) -> Body:
    """``body`` with the bust enlarged: x, z scaled by ``1 + amount * w(y)`` about the bust landmark's
    vertical axis, ``w`` the cos^2 bump of :func:`hip_weight` equal to 1 at the bust landmark and 0 at and
    below the waist landmark and at and above the neck landmark; arm/hand vertices (:data:`ARM_KEYS`)
    unchanged. The waist and everything below it keep their shape."""
    lm = body.landmarks
    w = hip_weight(body.vertices[:, 1], float(lm["bust"][1]), float(lm["neck"][1]), float(lm["waist"][1]))
    return _widened(body, w, lm["bust"], amount, "bust")


def amount_for_girth_change(make: Callable[[Body, float], Body], body: Body, name: str, change: float,
                            steps: int = 2) -> float:
    """The ``amount`` of a derived-body maker (:func:`hips_body`, :func:`bust_body`) whose body's measured
    girth ``name`` (:meth:`Body.measurements`) is ``change`` (m) larger than ``body``'s.

    Starts from ``change / girth`` (exact for a uniform scaling of the whole section) and takes ``steps``
    secant steps on the measured girth.

    Raises:
        InputError: ``change`` is not finite.
    """
    if not math.isfinite(change):
        raise InputError(f"the girth change must be finite, got {change}")
    g0 = girth(body, name)
    a0, c0 = 0.0, 0.0
    a1 = change / g0
    for _ in range(steps):
        c1 = girth(make(body, a1), name) - g0
        if abs(c1 - change) < 1e-6 or c1 == c0:
            break
        a0, c0, a1 = a1, c1, a1 + (change - c1) * (a1 - a0) / (c1 - c0)
    return float(a1)
