"""Read and write sewing patterns in GarmentCode's JSON specification.

GarmentCode (Korosteleva et al.) stores a pattern as::

    {"pattern": {"panels": {name: {"vertices": [[x, y], ...], "edges": [{"endpoints": [i, j],
                                   "curvature": {...}, "label": s}, ...],
                                   "translation": [x, y, z], "rotation": [rx, ry, rz], "label": s}},
                 "stitches": [[{"panel": name, "edge": i}, {"panel": name, "edge": j}], ...],
                 "panel_order": [name, ...]},
     "parameters": {...}, "parameter_order": [...],
     "properties": {"units_in_meter": 100, "curvature_coords": "relative", ...}}

Conversions on reading (and the reverse on writing):

* Lengths (vertices, translations, arc radii) are divided by ``properties.units_in_meter`` (100 for
  centimetres), giving metres. Files are always written in centimetres (``units_in_meter = 100``) so that
  GarmentCode's own tools read them.
* ``rotation`` is in degrees (extrinsic XYZ Euler angles, scipy's ``"xyz"``) and becomes radians.
* ``curvature`` is ``{"type": "quadratic", "params": [[u, v]]}``, ``{"type": "cubic", "params": [[u1, v1],
  [u2, v2]]}`` (edge-relative controls, see :mod:`torchgarment.pattern.spec`; ``curvature_coords =
  "absolute"`` files are converted to relative), ``{"type": "circle", "params": [radius, large_arc,
  right]}`` where ``right`` is the SVG sweep flag, or the legacy bare ``[u, v]`` (one quadratic control).

Stitch orientation (which ends of two stitched edges meet): a side of a stitch carrying our extra key
``"orientation": "opposite" | "same"`` is used as is. Otherwise :class:`OrientationRule` decides:

* ``GARMENTCODE`` (default): GarmentCode's own rule, as in its box mesher
  (``pygarment/meshgen/boxmeshgen.py``, ``read_stitches``): a stitch whose list has a third entry
  ``"right_wrong"`` is SAME, every other stitch is OPPOSITE. This matches our counter-clockwise-from-outside
  convention: all four GarmentCode specs in the shared data have their panels' outward normals pointing away
  from the body.
* ``PLACEMENT``: inferred from the 3D placement (:func:`infer_stitch_orientation`): both edges' end points
  are placed in 3D and the pairing with the smaller summed endpoint distance wins (ties go to OPPOSITE).
  This needs no convention but is fragile when two panels are far apart compared with the edge length (a
  front and a back panel 45 cm apart joined by a 1 cm edge): on ``dress_pencil`` it picks SAME for one tiny
  waist edge where GarmentCode means OPPOSITE.

Writers always store the key in both sides, and add the ``"right_wrong"`` entry for SAME stitches, so that
both GarmentCode and we read the intended orientation. GarmentCode readers ignore the unknown key.

Extra keys we read and write (all ignored by GarmentCode): per panel ``"notches": [{"edge": i, "t": f,
"name": s}]`` and ``"grainline": [x, y]``; top level ``"name"``, ``"metadata"`` (the pattern's JSON
metadata) and ``"support"`` (``[[panel, edge], ...]``, :attr:`SewingPattern.support`). GarmentCode's own
``parameters``, ``parameter_order`` and extra ``properties`` are kept in
``metadata["garmentcode"]`` and written back to their places.

Every problem with the input raises :class:`~torchgarment.errors.PatternError` with a one-line message
that names the panel and edge concerned.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from torchgarment.errors import PatternError
from torchgarment.io.atomic import atomic_open
from torchgarment.options import OptionEnum
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

UNITS_IN_METER = 100.0
"""Length unit of the files we write: centimetres, as GarmentCode does."""

MAX_STITCH_LENGTH_RATIO = 1.5
"""Default limit on the length ratio of two stitched edges when validating loaded patterns. GarmentCode
gathers fabric into seams: ``dress_pencil`` joins a 28.7 cm bodice waist to a 22.0 cm skirt edge (1.30)."""

_GC_KEY = "garmentcode"
_OWN_PROPERTIES = ("units_in_meter", "curvature_coords", "normalize_panel_translation",
                   "normalized_edge_loops")
_RIGHT_WRONG = "right_wrong"


class OrientationRule(OptionEnum):
    """How to decide a stitch's orientation when the file does not store it (see the module docstring)."""

    GARMENTCODE = "garmentcode"  # "right_wrong" third entry -> SAME, else OPPOSITE
    PLACEMENT = "placement"  # closest endpoint pairing in 3D


# ---------------------------------------------------------------------------------------------- reading
def load_pattern(
    path: str | os.PathLike,
    *,
    validate: bool = True,
    orientation_rule: OrientationRule = OrientationRule.GARMENTCODE,
    max_stitch_length_ratio: float = MAX_STITCH_LENGTH_RATIO,
) -> SewingPattern:
    """Read a GarmentCode JSON specification.

    Args:
        path: a ``*_specification.json`` file (or one written by :func:`save_pattern`).
        validate: run :meth:`SewingPattern.validate` on the result.
        orientation_rule: how to orient stitches that do not store their orientation.
        max_stitch_length_ratio: passed to :meth:`SewingPattern.validate`.

    Returns:
        The pattern in metres and radians. Its name is the file's ``"name"`` key, else the file stem without
        a trailing ``_specification``.

    Raises:
        PatternError: unreadable file, malformed JSON, missing keys, bad types or an invalid pattern.
    """
    from torchgarment.io.jsonfile import read_json

    path = Path(path)
    d = read_json(path, "pattern file", PatternError)
    stem = path.stem
    if stem.endswith("_specification"):
        stem = stem[: -len("_specification")]
    name = d.get("name") if isinstance(d, dict) and isinstance(d.get("name"), str) else stem
    try:
        return pattern_from_dict(d, name, validate=validate, orientation_rule=orientation_rule,
                                 max_stitch_length_ratio=max_stitch_length_ratio)
    except PatternError as exc:
        raise PatternError(f"{path}: {exc}") from exc


def pattern_from_dict(
    d: Any,
    name: str | None = None,
    *,
    validate: bool = True,
    orientation_rule: OrientationRule = OrientationRule.GARMENTCODE,
    max_stitch_length_ratio: float = MAX_STITCH_LENGTH_RATIO,
) -> SewingPattern:
    """Build a pattern from a parsed GarmentCode specification.

    Args:
        d: the parsed JSON object (see the module docstring).
        name: pattern name; defaults to ``d["name"]`` or ``"pattern"``.
        validate: run :meth:`SewingPattern.validate` on the result.
        orientation_rule: how to orient stitches that do not store their orientation.
        max_stitch_length_ratio: passed to :meth:`SewingPattern.validate`.

    Raises:
        PatternError: missing keys, bad types, indices out of range or an invalid pattern.
    """
    if not isinstance(d, dict):
        raise PatternError(f"a GarmentCode specification is a JSON object, got {type(d).__name__}")
    if name is None:
        name = d["name"] if isinstance(d.get("name"), str) else "pattern"
    props = d.get("properties", {})
    if not isinstance(props, dict):
        raise PatternError("'properties' must be an object")
    units = props.get("units_in_meter", UNITS_IN_METER)
    if not _is_number(units) or not units > 0:
        raise PatternError(f"properties.units_in_meter must be a positive number, got {units!r}")
    scale = 1.0 / float(units)
    coords = props.get("curvature_coords", "relative")
    if coords not in ("relative", "absolute"):
        raise PatternError(f"properties.curvature_coords must be 'relative' or 'absolute', got {coords!r}")

    spec = _get(d, "pattern", dict, "specification")
    panels_d = _get(spec, "panels", dict, "pattern")
    if not panels_d:
        raise PatternError("pattern.panels is empty")
    order = list(panels_d)
    if "panel_order" in spec:
        po = spec["panel_order"]
        if not isinstance(po, list) or sorted(map(str, po)) != sorted(order):
            raise PatternError("pattern.panel_order must list every panel exactly once")
        order = [str(n) for n in po]
    panels = {n: _panel_from_dict(n, panels_d[n], scale, coords == "absolute") for n in order}

    stitches_d = spec.get("stitches", [])
    if not isinstance(stitches_d, list):
        raise PatternError("pattern.stitches must be a list")
    rule = OrientationRule(orientation_rule)
    stitches = [_stitch_from_list(k, s, panels, rule) for k, s in enumerate(stitches_d)]

    metadata = d.get("metadata", {})
    if not isinstance(metadata, dict):
        raise PatternError("'metadata' must be an object")
    metadata = dict(metadata)
    gc = {}
    for key in ("parameters", "parameter_order"):
        if d.get(key):
            gc[key] = d[key]
    extra_props = {k: v for k, v in props.items() if k not in _OWN_PROPERTIES}
    if extra_props:
        gc["properties"] = extra_props
    if gc and _GC_KEY not in metadata:
        metadata[_GC_KEY] = gc

    support = d.get("support", [])
    if not (isinstance(support, list) and all(isinstance(s, list) and len(s) == 2 for s in support)):
        raise PatternError("'support' must be a list of [panel, edge] pairs")
    pattern = SewingPattern(name=name, panels=panels, stitches=stitches, metadata=metadata,
                            support=tuple((str(a), str(b)) for a, b in support))
    if validate:
        pattern.validate(max_stitch_length_ratio=max_stitch_length_ratio)
    return pattern


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _get(d: dict, key: str, typ: type, where: str) -> Any:
    if key not in d:
        raise PatternError(f"{where}: missing key '{key}'")
    v = d[key]
    if not isinstance(v, typ):
        raise PatternError(f"{where}: '{key}' must be {'an object' if typ is dict else 'a list'}, "
                           f"got {type(v).__name__}")
    return v


def _numbers(x: Any, shape: tuple[int, ...], where: str) -> np.ndarray:
    """A nested list of finite numbers with the given shape (-1 = any length >= 1) as float64."""
    def ok(v: Any, dims: tuple[int, ...]) -> bool:
        if not dims:
            return _is_number(v)
        if not isinstance(v, list) or (dims[0] >= 0 and len(v) != dims[0]) or (dims[0] < 0 and not v):
            return False
        return all(ok(e, dims[1:]) for e in v)

    if not ok(x, shape):
        want = " x ".join("n" if s < 0 else str(s) for s in shape)
        raise PatternError(f"{where} must be a {want} list of finite numbers, got {repr(x)[:60]}")
    return np.asarray(x, dtype=np.float64)


def _index(x: Any, n: int, where: str) -> int:
    if not isinstance(x, int) or isinstance(x, bool):
        raise PatternError(f"{where} must be an integer, got {x!r}")
    if not 0 <= x < n:
        raise PatternError(f"{where} = {x} is out of range 0..{n - 1}")
    return x


def _panel_from_dict(name: str, p: Any, scale: float, absolute_controls: bool) -> Panel:
    where = f"panel '{name}'"
    if not isinstance(p, dict):
        raise PatternError(f"{where} must be an object, got {type(p).__name__}")
    vertices = _numbers(_get(p, "vertices", list, where), (-1, 2), f"{where} vertices") * scale
    edges_d = _get(p, "edges", list, where)
    if not edges_d:
        raise PatternError(f"{where} has no edges")
    edges = [_edge_from_dict(f"{where} edge {i}", e, vertices, scale, absolute_controls)
             for i, e in enumerate(edges_d)]
    translation = _numbers(p.get("translation", [0.0, 0.0, 0.0]), (3,), f"{where} translation") * scale
    rotation = np.deg2rad(_numbers(p.get("rotation", [0.0, 0.0, 0.0]), (3,), f"{where} rotation"))
    label = p.get("label", "")
    if not isinstance(label, str):
        raise PatternError(f"{where} label must be a string")
    notches = []
    notches_d = p.get("notches", [])
    if not isinstance(notches_d, list):
        raise PatternError(f"{where} notches must be a list")
    for k, nd in enumerate(notches_d):
        w = f"{where} notch {k}"
        if not isinstance(nd, dict):
            raise PatternError(f"{w} must be an object")
        e = _index(nd.get("edge"), len(edges), f"{w} edge")
        t = nd.get("t")
        if not _is_number(t) or not 0.0 <= t <= 1.0:
            raise PatternError(f"{w} t must be a number in [0, 1], got {t!r}")
        nname = nd.get("name", "")
        if not isinstance(nname, str):
            raise PatternError(f"{w} name must be a string")
        notches.append(Notch(edge=e, t=float(t), name=nname))
    grain = _numbers(p.get("grainline", [0.0, 1.0]), (2,), f"{where} grainline")
    return Panel(name=name, vertices=vertices, edges=edges, translation=translation, rotation=rotation,
                 label=label, notches=notches, grainline=grain)


def _edge_from_dict(where: str, e: Any, vertices: np.ndarray, scale: float, absolute_controls: bool) -> Edge:
    if not isinstance(e, dict):
        raise PatternError(f"{where} must be an object, got {type(e).__name__}")
    ends = _get(e, "endpoints", list, where)
    if len(ends) != 2:
        raise PatternError(f"{where} endpoints must be two vertex indices, got {ends!r}")
    n = vertices.shape[0]
    s = _index(ends[0], n, f"{where} start vertex")
    t = _index(ends[1], n, f"{where} end vertex")
    label = e.get("label", "")
    if not isinstance(label, str):
        raise PatternError(f"{where} label must be a string")
    curv = e.get("curvature")
    if curv is None:
        return Edge(start=s, end=t, label=label)
    if isinstance(curv, list):  # legacy GarmentCode: one relative quadratic control
        curv = {"type": "quadratic", "params": [curv]}
    if not isinstance(curv, dict):
        raise PatternError(f"{where} curvature must be an object")
    kind = curv.get("type")
    params = curv.get("params")
    try:
        if kind in ("quadratic", "cubic"):
            need = 1 if kind == "quadratic" else 2
            ctrl = _numbers(params, (need, 2), f"{where} {kind} params")
            if absolute_controls:
                ctrl = _absolute_to_relative(ctrl * scale, vertices[s], vertices[t], where)
            return Edge(start=s, end=t, kind=EdgeKind(kind), controls=ctrl, label=label)
        if kind == "circle":
            if (not isinstance(params, list) or len(params) != 3 or not _is_number(params[0])
                    or not all(isinstance(f, (int, bool)) or _is_number(f) for f in params[1:])):
                raise PatternError(f"{where} circle params must be [radius, large_arc, right], "
                                   f"got {params!r}")
            radius = float(params[0]) * scale
            if radius <= 0:
                raise PatternError(f"{where} circle radius must be positive, got {params[0]!r}")
            return Edge(start=s, end=t, kind=EdgeKind.ARC, arc=(radius, bool(params[1]), bool(params[2])),
                        label=label)
    except PatternError as exc:
        if str(exc).startswith(where):
            raise
        raise PatternError(f"{where}: {exc}") from exc
    raise PatternError(f"{where} has unknown curvature type {kind!r} (expected quadratic, cubic or circle)")


def _absolute_to_relative(ctrl: np.ndarray, a: np.ndarray, b: np.ndarray, where: str) -> np.ndarray:
    d = b - a
    dd = float(d @ d)
    if dd == 0.0:
        raise PatternError(f"{where} has coincident endpoints")
    rel = ctrl - a
    perp = np.array([-d[1], d[0]])
    return np.stack([rel @ d / dd, rel @ perp / dd], axis=-1)


def _stitch_from_list(k: int, s: Any, panels: dict[str, Panel], rule: OrientationRule) -> Stitch:
    where = f"stitch {k}"
    if not isinstance(s, list) or len(s) not in (2, 3):
        raise PatternError(f"{where} must be a list of two {{panel, edge}} objects (and optionally "
                           "'right_wrong')")
    right_wrong = False
    if len(s) == 3:
        if s[2] != _RIGHT_WRONG:
            raise PatternError(f"{where}: third entry must be '{_RIGHT_WRONG}', got {s[2]!r}")
        right_wrong = True
    refs = []
    orients = []
    for side_i, side in enumerate(s[:2]):
        w = f"{where} side {side_i}"
        if not isinstance(side, dict):
            raise PatternError(f"{w} must be an object")
        pname = side.get("panel")
        if not isinstance(pname, str):
            raise PatternError(f"{w}: missing or non-string 'panel'")
        if pname not in panels:
            raise PatternError(f"{w} refers to unknown panel '{pname}'")
        e = _index(side.get("edge"), len(panels[pname].edges), f"{w} edge of panel '{pname}'")
        refs.append(EdgeRef(pname, e))
        if "orientation" in side:
            try:
                orients.append(StitchOrientation(side["orientation"]))
            except ValueError:
                raise PatternError(f"{w} orientation must be 'opposite' or 'same', got "
                                   f"{side['orientation']!r}") \
                    from None
    if len(set(orients)) > 1:
        raise PatternError(f"{where}: its two sides disagree on the orientation")
    if orients:
        orient = orients[0]
    elif rule is OrientationRule.PLACEMENT:
        orient = infer_stitch_orientation(panels, refs[0], refs[1])
    else:
        orient = StitchOrientation.SAME if right_wrong else StitchOrientation.OPPOSITE
    return Stitch(a=refs[0], b=refs[1], orientation=orient)


def infer_stitch_orientation(panels: dict[str, Panel], a: EdgeRef, b: EdgeRef) -> StitchOrientation:
    """Which ends of two edges meet, judged from the panels' 3D placement.

    Both edges' end points are placed in 3D; OPPOSITE (``a.start``-``b.end``, ``a.end``-``b.start``) is chosen
    unless SAME (``a.start``-``b.start``, ``a.end``-``b.end``) has a strictly smaller sum of endpoint
    distances.

    Args:
        panels: the pattern's panels by name.
        a: first edge. b: second edge.
    """
    def ends3d(ref: EdgeRef) -> np.ndarray:
        p = panels[ref.panel]
        return p.to_3d(np.stack(p.edge_endpoints(ref.edge)))

    pa, pb = ends3d(a), ends3d(b)
    same = np.linalg.norm(pa - pb, axis=1).sum()
    opposite = np.linalg.norm(pa - pb[::-1], axis=1).sum()
    return StitchOrientation.SAME if same < opposite else StitchOrientation.OPPOSITE


# ---------------------------------------------------------------------------------------------- writing
def pattern_to_dict(p: SewingPattern) -> dict:
    """The GarmentCode specification of a pattern (centimetres, degrees), with our extra keys.

    Raises:
        PatternError: the metadata is not JSON-serializable.
    """
    s = UNITS_IN_METER
    panels = {}
    for name, panel in p.panels.items():
        edges = []
        for e in panel.edges:
            ed: dict[str, Any] = {"endpoints": [int(e.start), int(e.end)]}
            if e.kind in (EdgeKind.QUADRATIC, EdgeKind.CUBIC):
                ed["curvature"] = {"type": e.kind.value, "params": np.asarray(e.controls, float).tolist()}
            elif e.kind is EdgeKind.ARC:
                r, large, sweep = e.arc
                ed["curvature"] = {"type": "circle", "params": [float(r) * s, int(large), int(sweep)]}
            if e.label:
                ed["label"] = e.label
            edges.append(ed)
        pd: dict[str, Any] = {
            "translation": (panel.translation * s).tolist(),
            "rotation": np.rad2deg(panel.rotation).tolist(),
            "vertices": (panel.vertices * s).tolist(),
            "edges": edges,
        }
        if panel.label:
            pd["label"] = panel.label
        pd["notches"] = [{"edge": int(n.edge), "t": float(n.t), "name": n.name} for n in panel.notches]
        pd["grainline"] = np.asarray(panel.grainline, float).tolist()
        panels[name] = pd
    stitches = []
    for st in p.stitches:
        sd: list[Any] = [{"panel": st.a.panel, "edge": int(st.a.edge), "orientation": st.orientation.value},
                         {"panel": st.b.panel, "edge": int(st.b.edge), "orientation": st.orientation.value}]
        if st.orientation is StitchOrientation.SAME:
            sd.append(_RIGHT_WRONG)
        stitches.append(sd)
    meta = dict(p.metadata)
    gc = meta.pop(_GC_KEY, {})
    if not isinstance(gc, dict):
        raise PatternError(f"pattern '{p.name}': metadata['{_GC_KEY}'] must be a dict")
    props = dict(gc.get("properties", {}))
    props.update(curvature_coords="relative", normalize_panel_translation=False, normalized_edge_loops=True,
                 units_in_meter=int(UNITS_IN_METER))
    out = {
        "name": p.name,
        "pattern": {"panels": panels, "stitches": stitches, "panel_order": list(p.panels)},
        "parameters": gc.get("parameters", {}),
        "parameter_order": gc.get("parameter_order", []),
        "properties": props,
        "metadata": meta,
    }
    if p.support:
        out["support"] = [[a, b] for a, b in p.support]
    try:
        json.dumps(out, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise PatternError(f"pattern '{p.name}' cannot be written as JSON: {exc}") from exc
    return out


def save_pattern(path: str | os.PathLike, p: SewingPattern) -> None:
    """Write a pattern as a GarmentCode JSON specification, atomically.

    Args:
        path: destination ``.json`` file.
        p: the pattern.
    """
    d = pattern_to_dict(p)
    with atomic_open(path, "w") as f:
        json.dump(d, f, indent=2, allow_nan=False)
        f.write("\n")
