"""Acceptance of sewing-pattern adjustment by fit preservation, measured where the garment sits (issue 18).

Every case drafts a library garment for chart size 12, adjusts it with
:func:`torchgarment.adjust.pipeline.adjust` to a target body and measures, per construction line
(:func:`torchgarment.adjust.fit.construction_lines`: waist and hips for skirts and trousers; bust, waist,
(hips,) hem for the T-shirt and the sheath dress), the fit of the base drape (base pattern on the base body)
and of the target (adjusted pattern at its equilibrium on the target body), :func:`torchgarment.adjust.fit.
measure_fit`: the line's height, the pattern's girth there, the body's girth at that height, the ease
(their difference) and the placement (height above the body's nearest waist / hip / bust plane). A line
passes (:func:`torchgarment.adjust.fit.fit_rows`) when |ease change|, |pattern change - body change| (the
same number) and |placement change| are all <= 1 cm; the chart's girth change is printed for reference.

Resolution: ``torchgarment adjust``'s defaults (:class:`~torchgarment.adjust.pipeline.AdjustSettings`);
``--edge-length``, ``--voxel`` and ``--iterations`` override them (coarse runs: 0.05, 0.01, 16).

1. Grading: straight skirt, A-line skirt, trousers, T-shirt, sheath dress (``--garments``) from size 12 to
   6, 8, 10, 14, 16, 20 (``--sizes``). ``--half-resolution`` also runs each case at half the edge length and
   reports the difference of the pattern changes per line (pass: <= 5 mm). Each graded pattern is also
   compared with drafts (reported, no pass test): per panel the largest corner distance after a rigid
   alignment (:func:`~torchgarment.adjust.acceptance.drafted_deviation`) from the library's draft for the
   target chart size, and from the grade of the library's drafts from the two bodies' own measurements
   (:func:`~torchgarment.adjust.acceptance.draft_measurements`), beside the ungraded base pattern's.
2. Made to measure (``mtm``): the straight skirt onto the size-12 body with only the hips +6 cm
   (:func:`~torchgarment.adjust.acceptance.hips_body`, its amount solved for a measured +6 cm): the
   waistband (waist edges) moves <= 2 mm in the pattern and the hip line takes the change within 1 cm
   (its fit row passes: |pattern change - body change| and |placement change| <= 1 cm); the T-shirt onto
   the body with only the bust +6 cm (:func:`~torchgarment.adjust.acceptance.bust_body`): the hem's girth
   changes <= 5 mm.
3. Manufactured solution: the straight skirt onto the base body scaled by s = 1.05 and 0.95; the adjusted
   panels must be s times the base panels within 1.5 mm after a rigid motion
   (:func:`~torchgarment.adjust.acceptance.scaled_outline_deviation`).

Run: ``python scripts/adjust_acceptance.py [--only grading mtm manufactured] [--garments ...] [--sizes ...]
[--edge-length M] [--voxel M] [--iterations N] [--half-resolution] [--weights JSON] [--json FILE]``.
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

import torch

# SKIRT_LINES, TSHIRT_LINES and pattern_line_widths are re-exported for scripts/adjust_drafted_vs_adjusted.py
from torchgarment.adjust.acceptance import (  # noqa: F401
    SKIRT_LINES,
    TSHIRT_LINES,
    amount_for_girth_change,
    bust_body,
    draft_measurements,
    drafted_deviation,
    edge_moves,
    hips_body,
    pattern_line_widths,
    scaled_body,
    scaled_outline_deviation,
)
from torchgarment.adjust.fit import adjustment_fit, chart_changes

if TYPE_CHECKING:
    from torchgarment.adjust.pipeline import AdjustResult, AdjustSettings
    from torchgarment.body import Body

GARMENTS = ("straight_skirt", "aline_skirt", "trousers", "tshirt", "sheath_dress")
SIZES = ("6", "8", "10", "14", "16", "20")
BASE_SIZE = "12"
FIT_TOLERANCE_M = 0.01
HALF_RESOLUTION_M = 0.005
WAISTBAND_MOVE_M = 0.002
HEM_CHANGE_M = 0.005
MANUFACTURED_M = 0.0015
MTM_CHANGE_M = 0.06


# ---------------------------------------------------------------------------------------------- cases
def _adjust(garment: str, base: Body, target: Body, settings: AdjustSettings) -> AdjustResult:
    from torchgarment.adjust.pipeline import adjust
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    return adjust(draft(garment, chart_row(BASE_SIZE)), base, target, settings, progress=False)


def _summary(res: AdjustResult) -> dict:
    m = res.metrics
    keys = ("objective_base", "objective_initial", "objective_final", "reduction_percent", "stopped",
            "max_boundary_displacement_mm", "total_seconds")
    return {k: m.get(k) for k in keys}


def _fit(res: AdjustResult, base: Body, target: Body, chart: dict[str, float] | None) -> dict:
    fb, ft, rows = adjustment_fit(res, base, target, chart, FIT_TOLERANCE_M)
    return {"base": {k: v.to_dict() for k, v in fb.items()},
            "target": {k: v.to_dict() for k, v in ft.items()}, "rows": rows}


def _drafted(garment: str, size: str, res: AdjustResult, base: Body, target: Body) -> dict:
    """The graded pattern against drafts (reported, not a pass test): per panel the largest corner distance
    after a rigid alignment, and the base pattern's own (the change a grade has to make). ``chart``: the
    library's draft for the target's chart row (fixed height proportions); ``measured``: the base pattern
    plus the change between the library's drafts from the two bodies' own measurements and landmark heights
    (:func:`torchgarment.adjust.acceptance.draft_measurements`)."""
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    drafted = draft(garment, chart_row(size))
    grade = (res.base_pattern, draft(garment, draft_measurements(base)),
             draft(garment, draft_measurements(target)))
    out = {}
    for key, kw in (("chart", {}), ("measured", {"grade": grade})):
        graded = drafted_deviation(res.pattern, drafted, **kw)
        ungraded = drafted_deviation(res.base_pattern, drafted, **kw)
        out[key] = {"panels": graded, "max_m": max(p["max_m"] for p in graded.values()),
                    "base_max_m": max(p["max_m"] for p in ungraded.values())}
    return out


def grading(garment: str, size: str, base: Body, settings: AdjustSettings, half: bool) -> dict:
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row

    target = Body.from_size(size)
    chart = chart_changes(chart_row(BASE_SIZE), chart_row(size), ("waist", "hips", "bust"))
    res = _adjust(garment, base, target, settings)
    out = {"garment": garment, "from": BASE_SIZE, "to": size, **_fit(res, base, target, chart),
           "adjust": _summary(res)}
    out["pass"] = all(r["pass"] for r in out["rows"])
    out["drafted"] = _drafted(garment, size, res, base, target)
    if half:
        res2 = _adjust(garment, base, target, replace(settings, edge_length=settings.edge_length / 2))
        fit2 = _fit(res2, base, target, chart)
        diff = {a["line"]: b["pattern_change_m"] - a["pattern_change_m"]
                for a, b in zip(out["rows"], fit2["rows"], strict=True)}
        out["half_resolution"] = {"edge_length": settings.edge_length / 2, "rows": fit2["rows"],
                                  "pattern_change_difference_m": diff, "adjust": _summary(res2),
                                  "pass": all(abs(v) <= HALF_RESOLUTION_M for v in diff.values())}
    return out


def mtm_hips(base: Body, settings: AdjustSettings) -> dict:
    from torchgarment.adjust.acceptance import girth

    amount = amount_for_girth_change(hips_body, base, "hips", MTM_CHANGE_M)
    target = hips_body(base, amount)
    res = _adjust("straight_skirt", base, target, settings)
    fit = _fit(res, base, target, None)
    hips = next(r for r in fit["rows"] if r["line"] == "hips")
    band = edge_moves(res.base_pattern, res, ("waist_r", "waist_l"))
    hip_error = hips["pattern_change_m"] - hips["body_change_m"]
    return {"case": "hips +6 cm", "garment": "straight_skirt", "amount": amount,
            "body_hips_change_m": girth(target, "hips") - girth(base, "hips"),
            "body_waist_change_m": girth(target, "waist") - girth(base, "waist"),
            "waistband_move_m": band["max_m"], "waistband_shape_change_m": band["shape_max_m"],
            "hip_line_error_m": hip_error, "hip_line_pattern_change_m": hips["pattern_change_m"], **fit,
            "adjust": _summary(res), "pass": band["max_m"] <= WAISTBAND_MOVE_M and hips["pass"]}


def mtm_bust(base: Body, settings: AdjustSettings) -> dict:
    from torchgarment.adjust.acceptance import girth

    amount = amount_for_girth_change(bust_body, base, "bust", MTM_CHANGE_M)
    target = bust_body(base, amount)
    res = _adjust("tshirt", base, target, settings)
    fit = _fit(res, base, target, None)
    hem = next(r for r in fit["rows"] if r["line"] == "hem")
    return {"case": "bust +6 cm", "garment": "tshirt", "amount": amount,
            "body_bust_change_m": girth(target, "bust") - girth(base, "bust"),
            "body_waist_change_m": girth(target, "waist") - girth(base, "waist"),
            "hem_change_m": hem["pattern_change_m"], **fit, "adjust": _summary(res),
            "pass": abs(hem["pattern_change_m"]) <= HEM_CHANGE_M}


def manufactured(base: Body, s: float, settings: AdjustSettings) -> dict:
    res = _adjust("straight_skirt", base, scaled_body(base, s), settings)
    panels = scaled_outline_deviation(res, s)
    worst = max(p["max_m"] for p in panels.values())
    return {"scale": s, "panels": panels, "max_m": worst, "pass": worst <= MANUFACTURED_M,
            "adjust": _summary(res)}


# ---------------------------------------------------------------------------------------------- output
def _cm(v: float) -> str:
    return "     -" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{100 * v:6.2f}"


def print_table(results: dict) -> None:
    """Print the acceptance table of a ``results`` dict (as written by ``--json``)."""
    st = results["settings"]
    print(f"resolution: {100 * st['edge_length']:.1f} cm edges, {1e3 * st['voxel_size']:.1f} mm voxels, "
          f"{st['iterations']} iterations; tolerance {100 * FIT_TOLERANCE_M:.0f} cm; changes in cm")
    print(f"{'case':>22} {'line':>5} {'height':>6} {'pat':>6} {'body':>6} {'chart':>6} {'ease_b':>6} "
          f"{'ease_t':>6} {'d_ease':>6} {'d_place':>7} {'half':>6}  pass")
    cases = [(f"{r['garment']} {r['from']}->{r['to']}", r) for r in results["grading"]]
    cases += [(f"{r['garment']} {r['case']}", r) for r in results["mtm"]]
    for name, r in cases:
        half = r.get("half_resolution", {}).get("pattern_change_difference_m", {})
        for row in r["rows"]:
            b, t = r["base"][row["line"]], r["target"][row["line"]]
            print(f"{name:>22} {row['line']:>5} {t['height_m']:6.3f} {_cm(row['pattern_change_m'])} "
                  f"{_cm(row['body_change_m'])} {_cm(row['chart_change_m'])} {_cm(b['ease_m'])} "
                  f"{_cm(t['ease_m'])} {_cm(row['ease_change_m'])} {_cm(row['placement_change_m']):>7} "
                  f"{_cm(half.get(row['line']))}  {'yes' if row['pass'] else 'NO'}")
    for r in results["mtm"]:
        if "waistband_move_m" in r:
            print(f"  {r['case']}: body hips {_cm(r['body_hips_change_m'])}, waist "
                  f"{_cm(r['body_waist_change_m'])}; waistband moves {1e3 * r['waistband_move_m']:.1f} mm "
                  f"(<= {1e3 * WAISTBAND_MOVE_M:.0f}; shape {1e3 * r['waistband_shape_change_m']:.1f}); hip "
                  f"line: pattern {_cm(r['hip_line_pattern_change_m'])}, error {_cm(r['hip_line_error_m'])} "
                  f"-> {'pass' if r['pass'] else 'FAIL'}")
        else:
            print(f"  {r['case']}: body bust {_cm(r['body_bust_change_m'])}, waist "
                  f"{_cm(r['body_waist_change_m'])}; hem girth change {1e3 * r['hem_change_m']:.1f} mm "
                  f"(<= {1e3 * HEM_CHANGE_M:.0f}) -> {'pass' if r['pass'] else 'FAIL'}")
    for r in results["manufactured"]:
        per = ", ".join(f"{k} {1e3 * p['max_m']:.1f} (unadjusted {1e3 * p['unadjusted_max_m']:.1f})"
                        for k, p in r["panels"].items())
        print(f"  manufactured s = {r['scale']:.2f} (fit scale {st.get('fit_scale', '?')}): max deviation mm "
              f"{per} (<= {1e3 * MANUFACTURED_M:.1f}) -> {'pass' if r['pass'] else 'FAIL'}")
    for r in results["grading"]:
        for key, what in (("chart", "the chart draft"), ("measured", "the measured bodies' draft grade")):
            d = r.get("drafted", {}).get(key)
            if d is None:
                continue
            worst = max(d["panels"].items(), key=lambda kv: kv[1]["max_m"])
            print(f"  {r['garment']} {r['from']}->{r['to']} against {what}: corners within "
                  f"{_cm(d['max_m']).strip()} cm ({worst[0]} at {worst[1]['worst_corner']}; the base "
                  f"pattern: {_cm(d['base_max_m']).strip()} cm)")
    for r in results["grading"]:
        if "half_resolution" in r:
            d = max(abs(v) for v in r["half_resolution"]["pattern_change_difference_m"].values())
            print(f"  {r['garment']} {r['from']}->{r['to']} at half the edge length: pattern changes differ "
                  f"by at most {1e3 * d:.1f} mm (<= {1e3 * HALF_RESOLUTION_M:.0f}) "
                  f"-> {'pass' if r['half_resolution']['pass'] else 'FAIL'}")
    n = sum(r["pass"] for sec in ("grading", "mtm", "manufactured") for r in results[sec])
    total = sum(len(results[sec]) for sec in ("grading", "mtm", "manufactured"))
    print(f"{n}/{total} cases pass; {results['seconds']:.0f} s")


def main(argv: list[str] | None = None) -> int:
    from tqdm import tqdm

    from torchgarment.adjust.objective import CostWeights
    from torchgarment.adjust.pipeline import AdjustSettings
    from torchgarment.body import Body
    from torchgarment.linalg import SparseBackend
    from torchgarment.sim.solvers import exact_curvature_iterations

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", choices=("grading", "mtm", "manufactured"), nargs="+", default=None,
                    help="run only these checks (default all)")
    ap.add_argument("--garments", nargs="+", choices=GARMENTS, default=None,
                    help=f"garments of the grading check (default {' '.join(GARMENTS)})")
    ap.add_argument("--sizes", nargs="+", default=None,
                    help=f"target chart sizes of the grading check (default {' '.join(SIZES)})")
    ap.add_argument("--edge-length", type=float, default=None,
                    help="triangle edge length in metres (default: torchgarment adjust's)")
    ap.add_argument("--voxel", type=float, default=None,
                    help="body SDF voxel size in metres (default: torchgarment adjust's)")
    ap.add_argument("--iterations", type=int, default=None,
                    help="outer iterations (default: torchgarment adjust's)")
    ap.add_argument("--half-resolution", action="store_true",
                    help="also run every grading case at half the edge length and compare the pattern "
                         "changes (pass: within 5 mm)")
    ap.add_argument("--weights", type=json.loads, default=None,
                    help="cost weights overriding the defaults, as JSON, e.g. '{\"fixing\": 4}'")
    ap.add_argument("--fit-scale", choices=("stature", "none"), default=None,
                    help="how the fit rules' lengths scale with the body's height (default: torchgarment "
                         "adjust's; the manufactured solution is exact with 'stature')")
    ap.add_argument("--sparse-backend", default=None, choices=[k.value for k in SparseBackend],
                    help="sparse direct solver of the simulation (default: torchgarment adjust's, superlu)")
    ap.add_argument("--exact-curvature-cg", type=int, default=None, metavar="N",
                    help="Newton's direction by N CG iterations on the exact Hessian (AdjustSettings."
                         "exact_curvature_cg; default: torchgarment adjust's, 10; 0: projected Newton)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    ap.add_argument("--json", type=Path, default=None, help="write the results to this JSON file")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    overrides = {k: v for k, v in (("edge_length", args.edge_length), ("voxel_size", args.voxel),
                                   ("iterations", args.iterations), ("fit_scale", args.fit_scale),
                                   ("sparse_backend", args.sparse_backend),
                                   ("exact_curvature_cg", args.exact_curvature_cg))
                 if v is not None}
    if args.weights:
        overrides["weights"] = CostWeights.from_dict(args.weights)
    settings = AdjustSettings(**overrides)
    base = Body.from_size(BASE_SIZE)
    only = set(args.only or ("grading", "mtm", "manufactured"))
    jobs = []
    if "grading" in only:
        jobs += [("grading", (g, s)) for g in (args.garments or GARMENTS) for s in (args.sizes or SIZES)]
    if "mtm" in only:
        jobs += [("mtm", "hips"), ("mtm", "bust")]
    if "manufactured" in only:
        jobs += [("manufactured", s) for s in (1.05, 0.95)]
    results = {"settings": {"edge_length": settings.edge_length, "voxel_size": settings.voxel_size,
                            "iterations": settings.iterations, "optimizer": str(settings.optimizer),
                            "fit_scale": settings.fit_scale.value,
                            "sparse_backend": settings.sparse_backend.value,
                            "exact_curvature_cg": exact_curvature_iterations(settings.exact_curvature_cg,
                                                                             settings.linear_solver),
                            "weights": (settings.weights or CostWeights()).to_dict(),
                            "fit_tolerance_m": FIT_TOLERANCE_M},
               "grading": [], "mtm": [], "manufactured": []}
    t0 = time.perf_counter()
    for kind, arg in tqdm(jobs, desc="acceptance", unit="case", file=sys.stderr):
        if kind == "grading":
            results["grading"].append(grading(arg[0], arg[1], base, replace(settings), args.half_resolution))
        elif kind == "mtm":
            results["mtm"].append((mtm_hips if arg == "hips" else mtm_bust)(base, replace(settings)))
        else:
            results["manufactured"].append(manufactured(base, arg, replace(settings)))
    results["seconds"] = time.perf_counter() - t0

    print_table(results)
    if args.json is not None:
        from torchgarment.io.atomic import atomic_open

        with atomic_open(args.json) as f:
            json.dump(results, f, indent=2, default=float)
            f.write("\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
