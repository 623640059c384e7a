"""Reporting and metrics of the accuracy-vs-time study of the fitting methods
(``scripts/accuracy_vs_time.py``).

* Reporting: the Pareto front of (time, error) points (:func:`pareto_front`), rows written to CSV
  (:func:`write_csv`, columns :data:`CSV_COLUMNS`), per-setting summaries (:func:`summarize`), their printed
  table (:func:`format_table`) and the Pareto plot (:func:`plot_pareto`).
* Metrics of a fitted garment against a reference drape on one body (:class:`BodyCase`, :func:`evaluate`):
  point-to-surface distances, ease at the body's waist and hip planes (:func:`garment_ease`), vertices inside
  the body; :func:`welded_surface` welds a sewn garment's seams, :func:`top_boundary_height` and
  :func:`lower_waist_plane` move the waist plane down to a waistband that sits below the natural waist.

Lengths are in metres unless a name ends in ``_mm``; times in seconds.
"""

from __future__ import annotations

import csv
import io
import math
import statistics
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from torchgarment.body.measure import section_girths
from torchgarment.errors import InputError, TorchGarmentError
from torchgarment.io.atomic import atomic_path

if TYPE_CHECKING:
    from torchgarment.body.measure import SectionPlane
    from torchgarment.datadriven.basis import BodyFrame
    from torchgarment.structures.garment_mesh import GarmentMesh

__all__ = [
    "CSV_COLUMNS",
    "BodyCase",
    "evaluate",
    "format_table",
    "garment_ease",
    "lower_waist_plane",
    "pareto_front",
    "plot_pareto",
    "summarize",
    "top_boundary_height",
    "welded_surface",
    "write_csv",
]

CSV_COLUMNS = (
    "method",
    "setting",
    "body",
    "seconds",
    "offline_seconds",
    "mean_mm",
    "max_mm",
    "inside",
    "waist_ease_mm",
    "hip_ease_mm",
    "waist_ease_err_mm",
    "hip_ease_err_mm",
    "vertices",
    "note",
)
"""Columns of the CSV, in order (rows may carry more keys: they are appended after these)."""


# ----------------------------------------------------------------------------------------------------------
# reporting
# ----------------------------------------------------------------------------------------------------------


def pareto_front(times: list[float], errors: list[float]) -> list[int]:
    """Indices of the non-dominated points (less time and less error are better), sorted by time.

    A point is dominated when another is at most as slow and at most as wrong, and strictly better in one.
    Points with a non-finite time or error are never on the front.

    Args:
        times: seconds per point. errors: error per point (same length).

    Returns:
        the indices on the Pareto front, fastest first (errors then strictly decrease).
    """
    if len(times) != len(errors):
        raise InputError(f"times and errors differ in length ({len(times)} vs {len(errors)})")
    ok = [i for i in range(len(times)) if math.isfinite(times[i]) and math.isfinite(errors[i])]
    ok.sort(key=lambda i: (times[i], errors[i]))
    front: list[int] = []
    best = math.inf
    for i in ok:
        if errors[i] < best:
            front.append(i)
            best = errors[i]
    return front


def write_csv(rows: list[dict], path: str | Path) -> list[str]:
    """Write rows (dicts) to a CSV atomically: :data:`CSV_COLUMNS` first, then any other keys in order met.

    Floats are written with 6 significant digits; missing values are empty.

    Returns:
        the header written.
    """
    header = [c for c in CSV_COLUMNS if any(c in r for r in rows)]
    for r in rows:
        header += [k for k in r if k not in header]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=header, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    with atomic_path(path) as tmp:
        Path(tmp).write_text(buf.getvalue())
    return header


def summarize(rows: list[dict]) -> list[dict]:
    """One summary per method setting (in order of first appearance): median seconds, mean of ``mean_mm``, max
    of ``max_mm``, mean ``inside``, mean absolute ease errors, offline seconds, number of bodies."""
    out: dict[str, dict] = {}
    for r in rows:
        out.setdefault(r["setting"], {"method": r["method"], "setting": r["setting"], "_rows": []})[
            "_rows"
        ].append(r)

    def nanmean(vals: list[float]) -> float:
        v = [x for x in vals if isinstance(x, (int, float)) and math.isfinite(x)]
        return statistics.mean(v) if v else math.nan

    res = []
    for s in out.values():
        rs = s.pop("_rows")
        s.update(
            {
                "bodies": len(rs),
                "median_seconds": statistics.median(r["seconds"] for r in rs),
                "offline_seconds": max(r.get("offline_seconds", 0.0) for r in rs),
                "mean_mm": nanmean([r["mean_mm"] for r in rs]),
                "max_mm": max(r["max_mm"] for r in rs),
                "inside": nanmean([r["inside"] for r in rs]),
                "waist_ease_err_mm": nanmean([r.get("waist_ease_err_mm", math.nan) for r in rs]),
                "hip_ease_err_mm": nanmean([r.get("hip_ease_err_mm", math.nan) for r in rs]),
            }
        )
        res.append(s)
    return res


def format_table(summary: list[dict], front: set[str]) -> str:
    """The printed table (one line per setting; ``*`` marks the Pareto front)."""
    lines = [
        f"{'setting':<34} {'n':>2} {'med s':>9} {'offl s':>7} {'mean mm':>8} {'max mm':>8} {'inside':>7} "
        f"{'waist':>7} {'hip':>7}  (ease errors in mm; * = Pareto front)"
    ]
    for s in summary:
        lines.append(
            f"{s['setting']:<34} {s['bodies']:>2} {s['median_seconds']:>9.4g} {s['offline_seconds']:>7.0f} "
            f"{s['mean_mm']:>8.2f} {s['max_mm']:>8.2f} {s['inside']:>7.1f} {s['waist_ease_err_mm']:>7.1f} "
            f"{s['hip_ease_err_mm']:>7.1f}{'  *' if s['setting'] in front else ''}"
        )
    return "\n".join(lines)


def plot_pareto(summary: list[dict], path: str | Path, title: str) -> None:
    """Mean error (mm) vs median seconds per setting (log x), one marker per setting, Pareto front as a
    line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    markers = {"pca": "o", "sim": "s", "retarget": "^", "adjust": "D"}
    fig, ax = plt.subplots(figsize=(8.5, 5.5))
    for method in dict.fromkeys(s["method"] for s in summary):
        ss = [s for s in summary if s["method"] == method]
        ax.scatter(
            [s["median_seconds"] for s in ss],
            [s["mean_mm"] for s in ss],
            marker=markers.get(method, "x"),
            s=48,
            label=method,
            zorder=3,
        )
        for s in ss:
            ax.annotate(
                s["setting"],
                (s["median_seconds"], s["mean_mm"]),
                fontsize=7,
                xytext=(4, 3),
                textcoords="offset points",
            )
    idx = pareto_front([s["median_seconds"] for s in summary], [s["mean_mm"] for s in summary])
    if idx:
        ax.step(
            [summary[i]["median_seconds"] for i in idx],
            [summary[i]["mean_mm"] for i in idx],
            where="post",
            color="k",
            lw=1.2,
            ls="--",
            label="Pareto front",
            zorder=2,
        )
    ax.set_xscale("log")
    ax.set_xlabel("median wall time per body (s, online part)")
    ax.set_ylabel("mean point-to-surface distance to reference (mm)")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)


# ----------------------------------------------------------------------------------------------------------
# metrics
# ----------------------------------------------------------------------------------------------------------


@dataclass
class BodyCase:
    """One held-out body with everything the metrics need.

    Attributes:
        index: the body's index in its data set.
        vertices: (V, 3) float64 body vertices, metres. faces: (F, 3) long.
        frame: the body's placement frame (:class:`~torchgarment.datadriven.basis.BodyFrame`).
        planes: ``"waist"`` and ``"hips"`` section planes. girths: the body's girths there, metres.
        phenotype: the anny phenotype parameters of the body.
        ref_vertices, ref_faces: (V', 3) float64 and (F', 3) int64 welded reference garment, or None.
        ref_ease: the reference garment's ease at the planes (:func:`garment_ease`), metres.
        waist_lowered_mm: how far :func:`lower_waist_plane` moved the waist plane down to the waistband.
    """

    index: int
    vertices: torch.Tensor
    faces: torch.Tensor
    frame: BodyFrame
    planes: dict[str, SectionPlane]
    girths: dict[str, float]
    phenotype: dict
    ref_vertices: np.ndarray | None = None
    ref_faces: np.ndarray | None = None
    ref_ease: dict[str, float] = field(default_factory=dict)
    waist_lowered_mm: float = 0.0


def garment_ease(case: BodyCase, vertices: torch.Tensor, faces: torch.Tensor) -> dict[str, float]:
    """Garment girth minus body girth at the body's waist and hip planes, metres (NaN where the plane
    misses)."""
    out = {}
    for name, plane in case.planes.items():
        try:
            g = float(section_girths(vertices.detach().double(), faces.long(), {name: plane})[name])
            out[name] = g - case.girths[name]
        except (TorchGarmentError, ValueError, IndexError):
            out[name] = math.nan
    return out


def top_boundary_height(vertices: torch.Tensor, faces: torch.Tensor) -> float:
    """Lowest height (m) of the garment's upper boundary (boundary vertices above the garment's mid-height): a
    horizontal plane below it cuts the garment in closed loops all around, even when the waistband is
    tilted."""
    f = faces.long()
    e = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]).sort(dim=1).values
    uniq, counts = torch.unique(e, dim=0, return_counts=True)
    b = torch.unique(uniq[counts == 1])
    y = vertices[b, 1]
    mid = 0.5 * float(vertices[:, 1].max() + vertices[:, 1].min())
    return float(y[y > mid].min()) if bool((y > mid).any()) else float(vertices[:, 1].max())


def lower_waist_plane(case: BodyCase, garment_top: float, below: float = 0.01) -> None:
    """Move the waist plane down to ``garment_top - below`` when the body's natural waist lies above the
    draped garment (a skirt's waistband sits lower), and re-measure the body there: the "waist" ease is then
    the ease at the waistband, on the same plane for the body, the reference and every method."""
    plane = case.planes["waist"]
    y = garment_top - below
    if float(plane.point[1]) <= y:
        return
    point, seed = plane.point.clone(), plane.seed.clone()
    point[1] = y
    seed[1] = y
    case.planes["waist"] = replace(plane, point=point, seed=seed)
    case.girths["waist"] = float(
        section_girths(case.vertices, case.faces, {"waist": case.planes["waist"]})["waist"]
    )
    case.waist_lowered_mm = 1e3 * (float(plane.point[1]) - y)


def welded_surface(vertices: torch.Tensor, mesh: GarmentMesh) -> tuple[torch.Tensor, torch.Tensor]:
    """(V', 3), (F', 3) of a sewn garment mesh at ``vertices`` with its seams welded."""
    w, _ = mesh.with_positions(vertices.detach().double()).welded()
    return w.x.detach(), w.faces


def evaluate(case: BodyCase, x: torch.Tensor, wv: torch.Tensor, wf: torch.Tensor) -> dict:
    """Metrics of one fitted garment: ``x`` (N, 3) all its vertices; ``wv, wf`` its welded surface (ease)."""
    import igl

    p = np.ascontiguousarray(x.detach().double().cpu().numpy())
    d2, _, _ = igl.point_mesh_squared_distance(p, case.ref_vertices, case.ref_faces)
    d = np.sqrt(np.maximum(d2, 0.0)) * 1e3
    bv = np.ascontiguousarray(case.vertices.numpy())
    bf = np.ascontiguousarray(case.faces.numpy().astype(np.int64))
    sd = igl.signed_distance(p, bv, bf)[0]
    ease = garment_ease(case, wv, wf)
    return {
        "mean_mm": float(d.mean()),
        "max_mm": float(d.max()),
        "inside": int((sd < 0).sum()),
        "waist_ease_mm": 1e3 * ease.get("waist", math.nan),
        "hip_ease_mm": 1e3 * ease.get("hips", math.nan),
        "waist_ease_err_mm": 1e3 * abs(ease.get("waist", math.nan) - case.ref_ease.get("waist", math.nan)),
        "hip_ease_err_mm": 1e3 * abs(ease.get("hips", math.nan) - case.ref_ease.get("hips", math.nan)),
        "vertices": int(p.shape[0]),
    }
