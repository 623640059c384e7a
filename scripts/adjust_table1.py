"""Pattern adjustment over every library garment, reported like Wang et al. 2018's Table 1.

For each library garment (or ``--garment`` ones) drafted for chart size ``--base-size``, adjust it to each
``--target-size`` with :func:`torchgarment.adjust.pipeline.adjust` (pgd, Algorithm 1) and report, per row:
vertices, triangles and panels of the mesh, the target body, the strength coefficients
(``δ_fix, δ_cur, δ_dis, δ_smo, δ_str, δ_pos``), the objective of the base pattern, after the section-7
initialization and at the end, the objective reduction (final against initialized, as :func:`adjust` reports
it), the maximum boundary displacement, the time per iteration (optimizer and simulation together; the paper
also splits off the optimizer's share, which is not measured separately here), the number of iterations, the
optimization total and the precomputation (base drape, transfer, set-up, initialization; the paper's totals
exclude it). A garment that fails is reported with its error and the script goes on.

Usage::

    python scripts/adjust_table1.py [--edge-length 0.05] [--voxel 0.01] [--iterations 32] \\
        [--target-size 6 20] [--garment NAME ...] [--weights JSON] [--json FILE] [--threads 1]

Prints a Markdown table; ``--json`` writes every row. Runs are independent, so a long sweep can be split by
``--garment``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import traceback
from pathlib import Path
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from torchgarment.adjust.pipeline import AdjustSettings


def _row(garment: str, base_size: str, target_size: str, settings: AdjustSettings) -> dict:
    from torchgarment.adjust.objective import CostWeights
    from torchgarment.adjust.pipeline import adjust
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    pattern = draft(garment, chart_row(base_size))
    t0 = time.perf_counter()
    res = adjust(pattern, Body.from_size(base_size), Body.from_size(target_size), settings, progress=False)
    total = time.perf_counter() - t0
    m = res.metrics
    w = settings.weights or CostWeights()
    mesh = res.mesh_target
    opt = float(m["seconds"])
    pre = sum(float(m.get(k, 0.0)) for k in ("drape_seconds", "transfer_seconds", "setup_seconds",
                                              "initialization_seconds"))
    n_it = max(1, int(m["iterations"]))
    return {
        "garment": garment, "base_size": base_size, "target_size": target_size,
        "vertices": int(mesh.num_vertices), "triangles": int(mesh.faces.shape[0]),
        "panels": len(mesh.panel_names),
        "coefficients": [w.fixing, w.curvature, w.distance, w.smoothness, w.stretching, w.positional],
        "objective_base": float(m["objective_base"]), "objective_initial": float(m["objective_initial"]),
        "objective_final": float(m["objective_final"]), "reduction_percent": float(m["reduction_percent"]),
        "max_displacement_mm": float(m["max_boundary_displacement_mm"]),
        "seconds_per_iteration": opt / n_it, "iterations": n_it, "optimization_seconds": opt,
        "precomputation_seconds": pre, "total_seconds": total, "closure_calls": int(m["closure_calls"]),
        "stopped": m.get("stopped"), "ok": True,
    }


def _markdown(rows: list[dict]) -> str:
    head = ("| garment (V, T, panels) | target | coefficients | objective base -> init -> final | reduction "
            "| max disp. mm | s / iteration | iterations | optimization s | precomputation s |")
    lines = [head, "|" + "---|" * 10]
    for r in rows:
        if not r["ok"]:
            lines.append(f"| {r['garment']} | {r['target_size']} | | FAILED: {r['error']} | | | | | | |")
            continue
        c = ", ".join(f"{v:g}" for v in r["coefficients"])
        lines.append(
            f"| {r['garment']} ({r['vertices']}, {r['triangles']}, {r['panels']}) | size {r['target_size']} "
            f"| {c} | {r['objective_base']:.3g} -> {r['objective_initial']:.3g} -> "
            f"{r['objective_final']:.3g} | {r['reduction_percent']:.0f} % | {r['max_displacement_mm']:.1f} | "
            f"{r['seconds_per_iteration']:.3f} | {r['iterations']} | {r['optimization_seconds']:.1f} | "
            f"{r['precomputation_seconds']:.1f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from tqdm import tqdm

    from torchgarment.adjust.objective import CostWeights
    from torchgarment.adjust.pipeline import AdjustSettings
    from torchgarment.pattern.library import list_garments

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--garment", nargs="+", default=None, help="library garments (default: all)")
    ap.add_argument("--base-size", default="12")
    ap.add_argument("--target-size", nargs="+", default=["6", "20"])
    ap.add_argument("--edge-length", type=float, default=0.05, help="triangle edge length in metres")
    ap.add_argument("--voxel", type=float, default=0.01, help="body SDF voxel size in metres")
    ap.add_argument("--iterations", type=int, default=32, help="outer iterations of Algorithm 1")
    ap.add_argument("--exact-interval", type=int, default=8, help="M: exact solve every this many iterations")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    ap.add_argument("--no-support", action="store_true",
                    help="no sticking supports (the figures before supports existed)")
    ap.add_argument("--weights", type=json.loads, default=None,
                    help="cost weights overriding the defaults, as JSON; '{\"reference_edge_length\": null}' "
                         "gives the paper's coefficients as given at any resolution (the figures before "
                         "issue 18 made the resolution-consistent rescaling the default)")
    ap.add_argument("--json", type=Path, default=None, help="write the rows to this JSON file")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    garments = args.garment or list_garments()
    weights = CostWeights.from_dict(args.weights) if args.weights else CostWeights()
    settings = AdjustSettings(edge_length=args.edge_length, voxel_size=args.voxel, iterations=args.iterations,
                              exact_interval=args.exact_interval, support=not args.no_support,
                              weights=weights)
    rows = []
    jobs = [(g, t) for g in garments for t in args.target_size]
    for g, t in tqdm(jobs, desc="adjust", unit="run", file=sys.stderr):
        try:
            rows.append(_row(g, args.base_size, t, settings))
        except Exception as exc:  # noqa: BLE001 - reported per row, the sweep goes on
            traceback.print_exc()
            rows.append({"garment": g, "base_size": args.base_size, "target_size": t, "ok": False,
                         "error": f"{type(exc).__name__}: {exc}".splitlines()[0]})
    ref = weights.reference_edge_length
    print(f"\nresolution: {args.edge_length * 100:g} cm edges, {args.voxel * 1e3:g} mm voxels, pgd, "
          f"{args.iterations} iterations, exact every {args.exact_interval}; base size {args.base_size}; "
          f"regularizers {'as given' if ref is None else f'rescaled to {ref * 1e3:g} mm edges'}\n")
    print(_markdown(rows))
    if args.json is not None:
        from torchgarment.io.atomic import atomic_open

        with atomic_open(args.json) as f:
            json.dump({"settings": vars(args) | {"json": str(args.json)}, "rows": rows}, f, indent=2,
                      default=str)
            f.write("\n")
    return 0 if all(r["ok"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
