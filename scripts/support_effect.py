"""What the support (Wang 2018's sticking energy on the waistband) changes in a skirt's adjustment.

For the straight skirt drafted for chart size 12, adjusted to each target size (default 10 and 20) with the
support on and off (``AdjustSettings.support``), at coarse settings (5 cm edges, 10 mm voxels, 16 pgd
iterations, exact check every 8): the base is draped once per support setting and reused for every target
(``prepare(..., base=...)``). Reported per run:

* the waistband's height: mean y of its vertices (``SewingPattern.support``) in the base drape (base pattern
  on the base body) and in the adjusted target drape (adjusted pattern on the target body), and its drop
  (base - target, mm); ``drop_vs_waist_mm`` is the drop of the band relative to each body's waist plane
  (:meth:`Body.measurements`), i.e. how much lower the band sits on the target body than on the base body;
* the pattern's waist and hip girth changes (:func:`torchgarment.adjust.acceptance.pattern_line_widths`)
  beside the chart's girth differences (:func:`~torchgarment.body.size_chart.chart_row`), in cm;
* the objective, and the support's force and largest displacement in the target (``metrics.json``'s
  ``support_force_n``, ``support_max_displacement_mm``).

Run: ``python scripts/support_effect.py [--sizes 10 20] [--iterations 16] [--json FILE]``.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import torch

from torchgarment.adjust.acceptance import SKIRT_LINES, pattern_line_widths
from torchgarment.adjust.pipeline import AdjustSettings, optimize, prepare
from torchgarment.body import Body
from torchgarment.body.size_chart import chart_row
from torchgarment.pattern.library import draft
from torchgarment.pattern.support import support_vertices
from torchgarment.sim.drape import DrapeSettings, drape

COLUMNS = ("target", "support", "band_base_y_m", "band_target_y_m", "drop_mm", "drop_vs_waist_mm",
           "waist_change_cm", "chart_waist_cm", "hip_change_cm", "chart_hips_cm", "objective_initial",
           "objective_final", "support_force_n", "support_max_displacement_mm", "seconds")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", default="12")
    ap.add_argument("--sizes", nargs="+", default=["10", "20"])
    ap.add_argument("--iterations", type=int, default=16)
    ap.add_argument("--exact-interval", type=int, default=8)
    ap.add_argument("--edge-length", type=float, default=0.05)
    ap.add_argument("--voxel", type=float, default=0.01)
    ap.add_argument("--json", metavar="FILE")
    args = ap.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))

    base_body = Body.from_size(args.base)
    pattern = draft("straight_skirt", chart_row(args.base))
    base_lines = pattern_line_widths(pattern, SKIRT_LINES)
    waist_y = {args.base: float(base_body.measurements().planes["waist"].point[1])}
    rows = []
    for support in (True, False):
        settings = AdjustSettings(edge_length=args.edge_length, voxel_size=args.voxel,
                                  iterations=args.iterations, exact_interval=args.exact_interval,
                                  support=support)
        t0 = time.perf_counter()
        dset = DrapeSettings(edge_length=args.edge_length, voxel_size=args.voxel, support=support)
        base = drape(pattern, base_body, settings=dset)
        drape_s = time.perf_counter() - t0
        idx, _, _ = support_vertices(pattern, base.mesh)
        y_base = float(base.x[idx, 1].mean())
        for size in args.sizes:
            t1 = time.perf_counter()
            target_body = Body.from_size(size)
            waist_y.setdefault(size, float(target_body.measurements().planes["waist"].point[1]))
            setup = prepare(pattern, base_body, target_body, settings, base=base)
            result = optimize(setup, progress=False)
            y_t = float(result.mesh_target.x[idx, 1].mean())
            lines = pattern_line_widths(result.pattern, SKIRT_LINES)
            m = result.metrics
            rows.append({
                "target": size, "support": support, "band_base_y_m": y_base, "band_target_y_m": y_t,
                "drop_mm": 1e3 * (y_base - y_t),
                "drop_vs_waist_mm": 1e3 * ((y_base - waist_y[args.base]) - (y_t - waist_y[size])),
                "waist_change_cm": 100 * (lines["waist"] - base_lines["waist"]),
                "chart_waist_cm": 100 * (chart_row(size)["waist"] - chart_row(args.base)["waist"]),
                "hip_change_cm": 100 * (lines["hips"] - base_lines["hips"]),
                "chart_hips_cm": 100 * (chart_row(size)["hips"] - chart_row(args.base)["hips"]),
                "objective_initial": m["objective_initial"], "objective_final": m["objective_final"],
                "support_force_n": m.get("support_force_n"),
                "support_max_displacement_mm": m.get("support_max_displacement_mm"),
                "seconds": time.perf_counter() - t1 + drape_s / len(args.sizes),
                "base_drape_support_max_displacement_mm": base.metrics.get("support_max_displacement_mm"),
                "base_band_minus_waist_mm": 1e3 * (y_base - waist_y[args.base]),
                "target_band_minus_waist_mm": 1e3 * (y_t - waist_y[size]),
            })
            _print_row(rows[-1])
    print()
    print(" ".join(f"{c:>12.12}" for c in COLUMNS))
    for r in rows:
        _print_row(r)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"settings": vars(args), "rows": rows}, f, indent=2)


def _print_row(r: dict) -> None:
    cells = []
    for c in COLUMNS:
        v = r[c]
        cells.append(f"{'-':>12}" if v is None else f"{v:>12.4g}" if isinstance(v, float) else f"{v!s:>12}")
    print(" ".join(cells), flush=True)


if __name__ == "__main__":
    main()
