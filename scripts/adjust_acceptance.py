"""Acceptance checks of sewing-pattern adjustment (issue 4, Wang et al. 2018) at a coarse resolution.

Every case drafts a library garment for chart size 12, adjusts it with
:func:`torchgarment.adjust.pipeline.adjust` (pgd, Algorithm 1) and measures the adjusted pattern. Resolution
(documented, coarse to fit 2 CPU cores): 5 cm triangle edges (``--edge-length``), 10 mm SDF voxels
(``--voxel``), ``--iterations`` outer iterations (default 32, ``--quick`` 16), exact check every 8 iterations.
``--quick``: straight skirt only, sizes 20 and 6 (cached bodies).

1. Manufactured solution: target body = base body scaled uniformly by s (1.05, 0.95) about its feet centre
   (vertices, skeleton joints and landmarks scaled). Per panel the adjusted boundary vertices are compared
   with s times the base boundary vertices after removing a rigid motion (2D Procrustes without scale);
   reported in mm and in % of the panel size (the base panel's bounding-box diagonal). The unadjusted
   pattern's deviation is reported as the reference (what the adjustment has to recover).
2. Grading: straight skirt (and T-shirt unless ``--quick``) from size 12 to chart sizes up and down. The width
   of a panel at a construction line is the distance between the line's two corner vertices of the pattern
   (skirt: waist = the ends of the waist edges, hip = the side-seam corners between ``side_low`` and
   ``side_hip``; T-shirt: bust = the underarm corners, waist = the corners between ``side_low`` and
   ``side_up``), summed over panels, i.e. the pattern's girth at that line. Its change from the base pattern
   is compared with the chart's girth difference (:func:`torchgarment.body.size_chart.chart_row`); the
   discrepancy is in cm. Also reported for the skirt, as a diagnostic: ``body@band``, the bodies' own girth
   change at the height where the waistband sits (its corners in the base drape on the base body, and in the
   transferred garment on the target body). A tight band's fit-preserving girth follows it; the fitted bodies
   match the chart only at their landmark planes.
3. Hips-only change: the base body with x, z of the torso vertices scaled about the hip axis by
   ``1 + a w(y)``, ``w`` a cos^2 bump equal to 1 at the hip landmark height and 0 at the waist landmark and at
   the thigh landmark (arms and hands, by skin weight, excluded). Reported: hip-width change, largest move of
   the side-seam boundary vertices and the largest move of the waistband boundary vertices (waist edges), in
   mm (the pass test); also the waistband's shape change after its own best rigid motion per panel, and its
   length change. A row with the target equal to the base body (amount 0) is the control: what the adjustment
   moves when nothing should change.

Run: ``python scripts/adjust_acceptance.py [--quick] [--only manufactured grading hips] [--garments ...]
[--sizes ...] [--weights JSON] [--json FILE]``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from torchgarment.adjust.acceptance import (
    SKIRT_LINES,
    TSHIRT_LINES,
    body_girth_at,
    boundary_vertex_labels,
    edges_length,
    girth,
    hips_body,
    line_vertices,
    pattern_line_widths,
    procrustes_deviation,
    scaled_body,
)

if TYPE_CHECKING:
    from torchgarment.adjust.pipeline import AdjustResult, AdjustSettings
    from torchgarment.body import Body
    from torchgarment.pattern.spec import SewingPattern

ACCEPT_MS_PERCENT = 1.0
ACCEPT_GRADING_CM = 1.0
ACCEPT_WAISTBAND_MM = 2.0

# ---------------------------------------------------------------------------------------------- cases
def _run(pattern: SewingPattern, base: Body, target: Body, settings: AdjustSettings) -> AdjustResult:
    from torchgarment.adjust.pipeline import adjust

    return adjust(pattern, base, target, settings, progress=False)


def _summary(res: AdjustResult) -> dict:
    m = res.metrics
    return {k: m.get(k)
            for k in ("objective_base", "objective_initial", "objective_final", "reduction_percent",
                      "initialization_used", "stopped", "backtracks", "max_boundary_displacement_mm",
                      "total_seconds")}


def manufactured(pattern: SewingPattern, base: Body, s: float, settings: AdjustSettings) -> dict:
    res = _run(pattern, base, scaled_body(base, s), settings)
    bidx = res.boundary_index.cpu().numpy()
    vp = res.mesh_base.vertex_panel_ids.cpu().numpy()[bidx]
    pb = res.mesh_base.p.detach().cpu().double().numpy()[bidx]
    pn = res.mesh_target.p.detach().cpu().double().numpy()[bidx]
    panels = {}
    for k, name in enumerate(res.mesh_base.panel_names):
        m = vp == k
        size = float(np.linalg.norm(pb[m].max(axis=0) - pb[m].min(axis=0)))
        dev = procrustes_deviation(pn[m], s * pb[m])
        ref = procrustes_deviation(pb[m], s * pb[m])
        panels[name] = {"size_mm": 1e3 * size, "max_mm": 1e3 * dev.max(), "mean_mm": 1e3 * dev.mean(),
                        "max_percent": 100 * dev.max() / size, "mean_percent": 100 * dev.mean() / size,
                        "unadjusted_max_mm": 1e3 * ref.max(), "unadjusted_mean_mm": 1e3 * ref.mean()}
    worst = max(p["max_percent"] for p in panels.values())
    return {"scale": s, "panels": panels, "max_percent": worst, "pass": worst <= ACCEPT_MS_PERCENT,
            "adjust": _summary(res)}


def grading(garment: str, base_size: str, target_size: str, base: Body, settings: AdjustSettings) -> dict:
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    lines = SKIRT_LINES if "skirt" in garment else TSHIRT_LINES
    row_b, row_t = chart_row(base_size), chart_row(target_size)
    pattern = draft(garment, row_b)
    target = Body.from_size(target_size)
    res = _run(pattern, base, target, settings)
    w0, w1 = pattern_line_widths(pattern, lines), pattern_line_widths(res.pattern, lines)
    wd = pattern_line_widths(draft(garment, row_t), lines)
    out = {"garment": garment, "from": base_size, "to": target_size, "lines": {},
           "adjust": _summary(res)}
    for line in lines:
        chart = 100 * (row_t[line] - row_b[line])
        change = 100 * (w1[line] - w0[line])
        out["lines"][line] = {"chart_cm": chart, "pattern_change_cm": change, "drafted_change_cm":
                              100 * (wd[line] - w0[line]), "discrepancy_cm": change - chart}
    if "skirt" in garment:
        # a diagnostic: the skirt's waistband is a tight band whose girth is the pattern's waist width, so a
        # fit-preserving pattern follows the bodies' girth change where the band sits (the base drape's waist
        # corners on the base body, the transferred ones on the target body), not at the chart's waist plane.
        # (Lines that cross loose cloth, the hips and the bust, are set by the fullest girth below them
        # instead.)
        idx = line_vertices(pattern, res.mesh_base, *lines["waist"])
        yb, yt = float(res.mesh_base.x[idx, 1].mean()), float(res.x_transfer[idx, 1].mean())
        at_band = 100 * (body_girth_at(target, yt) - body_girth_at(base, yb))
        out["lines"]["waist"].update({
            "body_at_band_cm": at_band,
            "discrepancy_body_at_band_cm": out["lines"]["waist"]["pattern_change_cm"] - at_band,
            "band_height_base_m": yb, "band_height_target_m": yt})
    if "skirt" in garment:  # the waistband's length along the (possibly curved) waist edges, reported only
        wb = [edges_length(p, ("waist_r", "waist_l")) for p in (pattern, res.pattern)]
        out["waistband_length_change_cm"] = 100 * (wb[1] - wb[0])
    out["max_discrepancy_cm"] = max(abs(v["discrepancy_cm"]) for v in out["lines"].values())
    out["pass"] = out["max_discrepancy_cm"] <= ACCEPT_GRADING_CM
    return out


def hips_only(pattern: SewingPattern, base: Body, amount: float, settings: AdjustSettings) -> dict:
    target = hips_body(base, amount)
    res = _run(pattern, base, target, settings)
    verts, labels = boundary_vertex_labels(pattern, res.mesh_base)
    pb = res.mesh_base.p.detach().cpu().double().numpy()
    pn = res.mesh_target.p.detach().cpu().double().numpy()
    disp = np.linalg.norm(pn - pb, axis=1)
    waist = np.isin(labels, ["waist_r", "waist_l"])
    side = np.array([str(x).startswith(("side_hip", "side_low")) for x in labels])
    w0, w1 = pattern_line_widths(pattern, SKIRT_LINES), pattern_line_widths(res.pattern, SKIRT_LINES)
    hb, ht = girth(base, "hips"), girth(target, "hips")
    waist_mm = 1e3 * float(disp[verts[waist]].max())
    inner = np.setdiff1d(verts[waist], verts[side])  # waistband without its corners on the side seams
    # the waistband's own shape change: each panel's waistband vertices after their best rigid motion (a panel
    # moved on the cutting table is the same pattern), and the waistband's length change
    panel = res.mesh_base.vertex_panel_ids.cpu().numpy()
    shape_mm = 0.0
    for k in np.unique(panel[verts[waist]]):
        wv = verts[waist][panel[verts[waist]] == k]
        shape_mm = max(shape_mm, 1e3 * float(procrustes_deviation(pn[wv], pb[wv]).max()))
    band = [edges_length(pt, ("waist_r", "waist_l")) for pt in (pattern, res.pattern)]
    return {"amount": amount, "body_hips_change_mm": 1e3 * (ht - hb),
            "hip_width_change_mm": 1e3 * (w1["hips"] - w0["hips"]),
            "waist_width_change_mm": 1e3 * (w1["waist"] - w0["waist"]),
            "side_seam_max_move_mm": 1e3 * float(disp[verts[side]].max()),
            "waistband_max_move_mm": waist_mm, "pass": waist_mm <= ACCEPT_WAISTBAND_MM,
            "waistband_interior_max_move_mm": 1e3 * float(disp[inner].max()) if inner.size else math.nan,
            "waistband_shape_change_mm": shape_mm, "waistband_length_change_mm": 1e3 * (band[1] - band[0]),
            "body_waist_change_mm": 1e3 * (girth(target, "waist") - girth(base, "waist")),
            "adjust": _summary(res)}


# ---------------------------------------------------------------------------------------------- main
def print_tables(results: dict) -> None:
    """Print the acceptance tables of a ``results`` dict (as written by ``--json``)."""
    st = results["settings"]
    print(f"resolution: {st['edge_length'] * 100:.0f} cm edges, {st['voxel_size'] * 1e3:.0f} mm voxels, "
          f"{st['optimizer']}, {st['iterations']} iterations")
    print("\n1. manufactured solution (straight skirt, deviation from s * base outline after a rigid motion)")
    print(f"{'s':>5} {'panel':>12} {'size mm':>8} {'max mm':>7} {'mean mm':>8} {'max %':>6} {'mean %':>7} "
          f"{'unadj. max mm':>13}  pass")
    for r in results["manufactured"]:
        for name, p in r["panels"].items():
            print(f"{r['scale']:5.2f} {name:>12} {p['size_mm']:8.0f} {p['max_mm']:7.1f} {p['mean_mm']:8.1f} "
                  f"{p['max_percent']:6.2f} {p['mean_percent']:7.2f} {p['unadjusted_max_mm']:13.1f}  "
                  f"{'yes' if r['pass'] else 'NO'}")
    print("\n2. grading from size 12 (pattern girth change vs chart girth change, cm)")
    print("   body@band (skirt waist only): the bodies' girth change at the height where the waistband sits, "
          "not at the chart's waist plane; err@band: pattern - body@band (a diagnostic, not the pass test)")
    print(f"{'garment':>15} {'to':>3} {'line':>6} {'chart':>7} {'pattern':>8} {'drafted':>8} {'error':>7} "
          f"{'body@band':>9} {'err@band':>8}  pass")
    for r in results["grading"]:
        for line, v in r["lines"].items():
            print(f"{r['garment']:>15} {r['to']:>3} {line:>6} {v['chart_cm']:7.2f} "
                  f"{v['pattern_change_cm']:8.2f} {v['drafted_change_cm']:8.2f} {v['discrepancy_cm']:7.2f} "
                  f"{v.get('body_at_band_cm', math.nan):9.2f} "
                  f"{v.get('discrepancy_body_at_band_cm', math.nan):8.2f}  {'yes' if r['pass'] else 'NO'}")
        if "waistband_length_change_cm" in r:
            print(f"{'':>15} {r['to']:>3} waistband length (along the waist edges) change "
                  f"{r['waistband_length_change_cm']:.2f} cm")
    print("\n3. hips-only change (straight skirt, mm)")
    for r in results["hips_only"]:
        print(f"amount {r['amount']:.3f}: body hips {r['body_hips_change_mm']:+.1f}, pattern hip width "
              f"{r['hip_width_change_mm']:+.1f}, waist width {r['waist_width_change_mm']:+.1f}, side seam "
              f"max move {r['side_seam_max_move_mm']:.1f}, waistband max move "
              f"{r['waistband_max_move_mm']:.1f} (<= {ACCEPT_WAISTBAND_MM} mm: "
              f"{'yes' if r['pass'] else 'NO'}), without its corners "
              f"{r.get('waistband_interior_max_move_mm', math.nan):.1f}, after its own rigid motion "
              f"{r.get('waistband_shape_change_mm', math.nan):.1f}, waistband length "
              f"{r.get('waistband_length_change_mm', math.nan):+.1f}, body waist "
              f"{r.get('body_waist_change_mm', math.nan):+.1f}")
    print("\nadjust runs: objective base -> initialized -> final, init used, stop reason, seconds")
    for sec in ("manufactured", "grading", "hips_only"):
        for r in results[sec]:
            a = r["adjust"]
            tag = r.get("scale", r.get("amount"))
            tag = f"{r['garment']} {r['to']}" if tag is None else tag
            print(f"{sec:>12} {tag!s:>18}: {a['objective_base']:.4g} -> {a['objective_initial']:.4g} -> "
                  f"{a['objective_final']:.4g}, {a['initialization_used']}, {a['stopped']}, "
                  f"{a['total_seconds']:.0f} s")
    print(f"\ntotal {results['seconds']:.0f} s")


def main(argv: list[str] | None = None) -> int:
    from tqdm import tqdm

    from torchgarment.adjust.pipeline import AdjustSettings
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true",
                    help="skirt only, sizes 20 and 6 (cached bodies), 16 iterations")
    ap.add_argument("--iterations", type=int, default=None, help="outer iterations (default 32, --quick 16)")
    ap.add_argument("--edge-length", type=float, default=0.05,
                    help="triangle edge length in metres (default 0.05)")
    ap.add_argument("--voxel", type=float, default=0.01, help="body SDF voxel size in metres (default 0.01)")
    ap.add_argument("--hips", type=float, default=0.10,
                    help="hips-only enlargement factor (default 0.10, about +9 cm hip girth: more than the "
                         "skirt's 4 cm hip ease); a 0.0 row (target = base body) is run as the noise-floor "
                         "control")
    ap.add_argument("--json", type=Path, default=None, help="write the results to this JSON file")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    ap.add_argument("--weights", type=json.loads, default=None,
                    help="cost weights overriding the paper's, as JSON, "
                         'e.g. \'{"fixing": 4, "curvature": 1600}\'')
    ap.add_argument("--only", choices=("manufactured", "grading", "hips"), nargs="+", default=None,
                    help="run only these checks (default all)")
    ap.add_argument("--garments", nargs="+", choices=("straight_skirt", "tshirt"), default=None,
                    help="garments of the grading check (default both; --quick: the skirt)")
    ap.add_argument("--sizes", nargs="+", default=None,
                    help="target chart sizes of the grading check (default 16 20 8 6; --quick: 20 6)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    it = args.iterations if args.iterations is not None else (16 if args.quick else 32)
    from torchgarment.adjust.objective import CostWeights

    weights = CostWeights.from_dict(args.weights) if args.weights else None
    settings = AdjustSettings(edge_length=args.edge_length, voxel_size=args.voxel, iterations=it,
                              exact_interval=8,
                              weights=weights)
    base = Body.from_size("12")
    skirt = draft("straight_skirt", chart_row("12"))
    sizes = args.sizes or (["20", "6"] if args.quick else ["16", "20", "8", "6"])
    garments = args.garments or (["straight_skirt"] if args.quick else ["straight_skirt", "tshirt"])
    jobs = [("ms", s) for s in (1.05, 0.95)] + [("grade", (g, t)) for g in garments for t in sizes] + \
        [("hips", 0.0), ("hips", args.hips)]
    only = set(args.only or ("manufactured", "grading", "hips"))
    jobs = [j for j in jobs if {"ms": "manufactured", "grade": "grading", "hips": "hips"}[j[0]] in only]
    results = {"settings": {"edge_length": settings.edge_length, "voxel_size": settings.voxel_size,
                            "iterations": it, "optimizer": "pgd", "exact_interval": settings.exact_interval,
                            "weights": (weights or CostWeights()).to_dict()},
               "manufactured": [], "grading": [], "hips_only": []}
    t0 = time.perf_counter()
    for kind, arg in tqdm(jobs, desc="acceptance", unit="case", file=sys.stderr):
        if kind == "ms":
            results["manufactured"].append(manufactured(skirt, base, arg, replace(settings)))
        elif kind == "grade":
            results["grading"].append(grading(arg[0], "12", arg[1], base, replace(settings)))
        else:
            results["hips_only"].append(hips_only(skirt, base, arg, replace(settings)))
    results["seconds"] = time.perf_counter() - t0

    print_tables(results)
    if args.json is not None:
        from torchgarment.io.atomic import atomic_open

        with atomic_open(args.json) as f:
            json.dump(results, f, indent=2, default=float)
            f.write("\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
