"""Pattern sheets as PNG (matplotlib, Agg, no display): the SVG sheet's layout, seams, notches, grainlines.

Panels sit where :func:`torchgarment.pattern.svg.svg_panel_layout` puts them, so a PNG and an SVG of the same
pattern match. Seams are coloured per stitch (:func:`torchgarment.pattern.svg.stitch_color`) and labelled
"S<k>" with an arrow showing which way the two sides run together (see :mod:`torchgarment.pattern.svg`).
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Protocol

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.figure import Figure

from torchgarment.errors import InputError, PatternError
from torchgarment.io.atomic import atomic_path
from torchgarment.pattern.spec import Panel, SewingPattern
from torchgarment.pattern.svg import (
    grainline_segment,
    notch_segment,
    panel_bbox,
    shelf_layout,
    stitch_color,
    stitch_marks,
    svg_panel_layout,
)

if TYPE_CHECKING:
    from matplotlib.axes import Axes

_DPI = 100
_LONG_SIDE_IN = 14.0  # inches of the longer figure side
_FILL = "#f6f1e7"


class PanelMesh(Protocol):
    """What :func:`plot_pattern` needs of a garment mesh (e.g. ``GarmentMesh``).

    Attributes:
        p: (V, 2) rest positions in metres, in the coordinates of the panel of each face using the vertex.
        faces: (F, 3) vertex indices.
        panel_ids: (F,) index of each face's panel: into ``panel_names`` when the mesh has a non-empty
            ``panel_names`` attribute (as ``GarmentMesh`` does), else into the pattern's panel order.
    """

    p: object
    faces: object
    panel_ids: object


def _numpy(x: object, name: str) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    try:
        return np.asarray(x)
    except (TypeError, ValueError) as exc:
        raise InputError(f"mesh.{name} is not array-like") from exc


def _mesh_triangles(mesh: PanelMesh, offsets_by_name: dict[str, np.ndarray]) -> np.ndarray:
    """(F, 3, 2) triangles of a panel mesh moved to the sheet layout."""
    for attr in ("p", "faces", "panel_ids"):
        if getattr(mesh, attr, None) is None:
            raise InputError(f"mesh has no '{attr}' (need p (V, 2), faces (F, 3), panel_ids (F,))")
    names = tuple(getattr(mesh, "panel_names", None) or ())
    if names:
        missing = [n for n in names if n not in offsets_by_name]
        if missing:
            raise InputError(f"mesh panel '{missing[0]}' is not a panel of the pattern")
        offsets = [offsets_by_name[n] for n in names]
    else:
        offsets = list(offsets_by_name.values())
    p = _numpy(mesh.p, "p").astype(np.float64)
    faces = _numpy(mesh.faces, "faces")
    ids = _numpy(mesh.panel_ids, "panel_ids")
    if p.ndim != 2 or p.shape[1] != 2:
        raise InputError(f"mesh.p must be (V, 2) 2D rest positions, got shape {p.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise InputError(f"mesh.faces must be (F, 3) integers, got shape {faces.shape} {faces.dtype}")
    if ids.shape != (faces.shape[0],) or not np.issubdtype(ids.dtype, np.integer):
        raise InputError(f"mesh.panel_ids must be (F,) integers, got shape {ids.shape} for {faces.shape[0]} "
                         "faces")
    if faces.size and (faces.min() < 0 or faces.max() >= p.shape[0]):
        raise InputError(f"mesh.faces refer to vertices outside 0..{p.shape[0] - 1}")
    if ids.size and (ids.min() < 0 or ids.max() >= len(offsets)):
        raise InputError(f"mesh.panel_ids must lie in 0..{len(offsets) - 1} (one per panel)")
    return p[faces] + np.stack(offsets)[ids][:, None, :]


def _outline(panel: Panel, offset: np.ndarray) -> np.ndarray:
    return panel.outline(resolution=48) + offset


def _new_figure(sheet: np.ndarray, title: str | None) -> tuple[Figure, object]:
    w, h = float(sheet[0]), float(sheet[1])
    k = _LONG_SIDE_IN / max(w, h)
    header = 0.5 if title else 0.0
    fig = Figure(figsize=(max(w * k, 3.0), max(h * k, 3.0) + header), dpi=_DPI)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.01, 0.01, 0.98, 0.98 - header / (max(h * k, 3.0) + header)))
    ax.set_xlim(0, w)
    ax.set_ylim(0, h)
    ax.set_aspect("equal")
    ax.set_axis_off()
    if title:
        fig.suptitle(title, fontsize=14, y=0.995, va="top")
    bar = 0.1 if w > 0.3 else 0.01  # scale bar, metres
    y0 = 0.004
    ax.plot([0.01, 0.01 + bar], [y0, y0], color="k", lw=2)
    ax.text(0.01 + bar / 2, y0 + 0.002, f"{bar * 100:g} cm", ha="center", va="bottom", fontsize=8)
    return fig, ax


def _save(fig: Figure, path: str | os.PathLike) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=_DPI)


def _draw_panel(ax: Axes, panel: Panel, offset: np.ndarray, *, color: str = "k", fill: str | None = _FILL,
                lw: float = 1.0, ls: str = "-", alpha: float = 1.0, name: bool = True) -> None:
    o = _outline(panel, offset)
    if fill:
        ax.fill(o[:, 0], o[:, 1], color=fill, zorder=0)
    closed = np.concatenate([o, o[:1]])
    ax.plot(closed[:, 0], closed[:, 1], color=color, lw=lw, ls=ls, alpha=alpha, zorder=2)
    if panel.notches:
        segs = [notch_segment(panel, n) + offset for n in panel.notches]
        ax.add_collection(LineCollection(segs, colors=color, linewidths=lw, alpha=alpha, zorder=3))
    g = grainline_segment(panel) + offset
    ax.annotate("", xy=g[1], xytext=g[0], zorder=3,
                arrowprops={"arrowstyle": "<|-|>", "color": color, "lw": 0.8 * lw, "alpha": alpha})
    if name:
        c = panel.outline(resolution=16).mean(axis=0) + offset
        ax.text(c[0] + 0.01, c[1], panel.name, fontsize=9, color=color, alpha=alpha, va="center", zorder=4)


def plot_pattern(
    pattern: SewingPattern,
    path: str | os.PathLike,
    *,
    mesh: PanelMesh | None = None,
    title: str | None = None,
) -> None:
    """Write a PNG pattern sheet; atomic.

    Args:
        pattern: the pattern (metres).
        path: destination ``.png``.
        mesh: optional triangulation drawn over the panels (see :class:`PanelMesh`, e.g. a ``GarmentMesh``):
            ``p`` (V, 2) panel-local rest positions in metres, ``faces`` (F, 3), ``panel_ids`` (F,); numpy
            arrays or tensors.
        title: optional title above the sheet.

    Raises:
        PatternError: no panels or a stitch to a missing panel/edge. InputError: a malformed mesh.
    """
    offsets, sheet = svg_panel_layout(pattern)
    names = list(pattern.panels)
    tris = _mesh_triangles(mesh, offsets) if mesh is not None else None
    marks = stitch_marks(pattern)
    fig, ax = _new_figure(sheet, title)
    for n in names:
        _draw_panel(ax, pattern.panels[n], offsets[n])
    if tris is not None:
        ax.add_collection(PolyCollection(tris, facecolors="none", edgecolors="#6c7a89", linewidths=0.25,
                                         zorder=1))
    for m in marks:
        panel, off = pattern.panels[m.panel], offsets[m.panel]
        col = stitch_color(m.stitch)
        a, b = panel.edge_endpoints(m.edge)
        pts = panel.edges[m.edge].polyline(a, b, 48) + off
        ax.plot(pts[:, 0], pts[:, 1], color=col, lw=2.5, zorder=5, solid_capstyle="round")
        base = m.point + off + 0.006 * m.inward - 0.008 * m.direction
        ax.annotate("", xy=base + 0.016 * m.direction, xytext=base, zorder=6,
                    arrowprops={"arrowstyle": "-|>", "color": col, "lw": 1.2})
        lab = m.point + off + 0.018 * m.inward
        ax.text(lab[0], lab[1], f"S{m.stitch}", color=col, fontsize=8, ha="center", va="center",
                fontweight="bold", zorder=6)
    _save(fig, path)


def plot_pattern_overlay(
    old: SewingPattern,
    new: SewingPattern,
    path: str | os.PathLike,
    *,
    title: str | None = None,
) -> None:
    """Write a PNG with two versions of a pattern on top of each other; atomic.

    Panels are matched by name and placed with one offset per name (a shelf layout of the union of both
    versions' bounding boxes), so differences show as displaced outlines: ``old`` dashed grey, ``new`` solid
    blue. Panels present in only one version are drawn alone.

    Args:
        old: the earlier version. new: the later version. path: destination ``.png``.
        title: optional title above the sheet.
    """
    names = list(old.panels) + [n for n in new.panels if n not in old.panels]
    if not names:
        raise PatternError("nothing to plot: both patterns have no panels")
    boxes = {}
    for n in names:
        bb = [panel_bbox(p.panels[n]) for p in (old, new) if n in p.panels]
        boxes[n] = np.stack([np.min([b[0] for b in bb], axis=0), np.max([b[1] for b in bb], axis=0)])
    offsets, sheet = shelf_layout(boxes)
    fig, ax = _new_figure(sheet, title)
    for n in names:
        if n in old.panels:
            _draw_panel(ax, old.panels[n], offsets[n], color="#7f7f7f", fill=_FILL, lw=1.2, ls="--",
                        name=n not in new.panels)
        if n in new.panels:
            _draw_panel(ax, new.panels[n], offsets[n], color="#1f4e9c", fill=None, lw=1.2)
    ax.plot([], [], color="#7f7f7f", ls="--", label=old.name or "old")
    ax.plot([], [], color="#1f4e9c", label=new.name or "new")
    fig.legend(loc="upper left", fontsize=9, frameon=False, ncols=2)
    _save(fig, path)


def grade_reference_vertices(pattern: SewingPattern) -> dict[str, int]:
    """Per panel, the turn point a grade nest is aligned at: the vertex nearest the top centre of the panel's
    bounding box (the centre-front / centre-back waist point of a skirt's or bodice's full panels).

    Returns:
        panel name -> vertex index into ``panel.vertices``.
    """
    out = {}
    for name, panel in pattern.panels.items():
        bb = panel_bbox(panel)
        top = np.array([0.5 * (bb[0, 0] + bb[1, 0]), bb[1, 1]])
        out[name] = int(np.argmin(np.linalg.norm(np.asarray(panel.vertices) - top, axis=1)))
    return out


def plot_grade_nest(
    patterns: dict[str, SewingPattern],
    path: str | os.PathLike,
    *,
    base: str | None = None,
    reference: dict[str, int] | None = None,
    title: str | None = None,
    cmap: str = "viridis",
) -> dict[str, int]:
    """Write a grade-nest PNG: every size of each panel overlaid, aligned at a reference point; atomic.

    As a pattern maker checks a grade: the outlines of one panel in every size are translated so that their
    reference turn points coincide (marked with a dot), coloured by size in the given order (``cmap``),
    the base size drawn thicker and dashed. The steps between neighbouring sizes should be even and the
    outlines should not cross. Panels are matched by name; each panel gets one place on a shelf layout.

    Args:
        patterns: size name -> pattern (metres), smallest size first; the sizes share panel names and
            vertex numbering (as adjusted patterns of one base do).
        path: destination ``.png``.
        base: the base size's name (a key of ``patterns``), drawn dashed.
        reference: panel name -> reference vertex index; default :func:`grade_reference_vertices` of the
            base (or the first) pattern.
        title: optional title above the sheet.
        cmap: matplotlib colormap name of the size colours.

    Returns:
        The reference vertex of each panel.

    Raises:
        PatternError: no sizes or panels, or a reference vertex a panel does not have. InputError: unknown
            ``base``.
    """
    from matplotlib import colormaps

    if not patterns:
        raise PatternError("grade nest: no sizes to plot")
    if base is not None and base not in patterns:
        raise InputError(f"grade nest: base size {base!r} is not one of {', '.join(patterns)}")
    ref_pattern = patterns[base] if base is not None else next(iter(patterns.values()))
    if reference is None:
        reference = grade_reference_vertices(ref_pattern)
    names: list[str] = []
    for pat in patterns.values():
        names += [n for n in pat.panels if n not in names]
    if not names:
        raise PatternError("grade nest: the patterns have no panels")
    anchors: dict[tuple[str, str], np.ndarray] = {}
    boxes = {}
    for n in names:
        k = reference.get(n, 0)
        bb = []
        for size, pat in patterns.items():
            if n not in pat.panels:
                continue
            verts = np.asarray(pat.panels[n].vertices)
            if not 0 <= k < verts.shape[0]:
                raise PatternError(f"grade nest: panel {n!r} of size {size} has no vertex {k}")
            anchors[size, n] = verts[k]
            bb.append(panel_bbox(pat.panels[n]) - verts[k])
        boxes[n] = np.stack([np.min([b[0] for b in bb], axis=0), np.max([b[1] for b in bb], axis=0)])
    offsets, sheet = shelf_layout(boxes)
    fig, ax = _new_figure(sheet, title)
    colours = colormaps[cmap](np.linspace(0.0, 0.9, max(len(patterns), 2)))
    for i, (size, pat) in enumerate(patterns.items()):
        col = colours[i]
        is_base = size == base
        for n in names:
            if n not in pat.panels:
                continue
            off = offsets[n] - anchors[size, n]
            o = _outline(pat.panels[n], off)
            closed = np.concatenate([o, o[:1]])
            ax.plot(closed[:, 0], closed[:, 1], color=col, lw=1.8 if is_base else 1.0,
                    ls="--" if is_base else "-", zorder=3 if is_base else 2)
        ax.plot([], [], color=col, lw=1.8 if is_base else 1.0, ls="--" if is_base else "-",
                label=f"{size} (base)" if is_base else str(size))
    for n in names:
        ax.plot(*offsets[n], "o", color="k", ms=3, zorder=4)
        ax.text(offsets[n][0] + 0.01, offsets[n][1] - 0.02, n, fontsize=9, va="top", zorder=4)
    fig.legend(loc="upper left", fontsize=9, frameon=False, ncols=min(len(patterns), 8), title="size")
    _save(fig, path)
    return dict(reference)
