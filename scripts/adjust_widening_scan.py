"""Where does the pattern-adjustment objective want a graded pattern? A scan along uniform panel widening.

Drafts a library garment for chart size ``--base-size`` and prepares its adjustment to ``--target-size`` (base
drape, transfer, objective; :func:`torchgarment.adjust.pipeline.prepare`). Then it solves the target
equilibrium exactly for the base pattern widened per panel by factors ``--scales`` along the panel's x axis
(about the panel's boundary centroid; the skirt's and T-shirt's girth direction) and prints the objective and
each term. Where the costs (positional, stretching, distance) are smallest near the chart's girth ratio but
the total is not, the regularizers are what keeps the adjusted pattern from following the chart. ``--weights``
overrides coefficients (e.g. ``'{"reference_edge_length": 0.008}'``).

Usage::

    python scripts/adjust_widening_scan.py [--garment straight_skirt] [--base-size 12] [--target-size 20]
        [--scales 1.0 1.1 1.2 1.22 1.25] [--edge-length 0.05] [--voxel 0.01] [--weights JSON] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import torch


def main(argv: list[str] | None = None) -> int:
    from torchgarment.adjust.inexact import AdjustProblem
    from torchgarment.adjust.objective import CostWeights
    from torchgarment.adjust.pipeline import AdjustSettings, prepare
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--garment", default="straight_skirt")
    ap.add_argument("--base-size", default="12")
    ap.add_argument("--target-size", default="20")
    ap.add_argument("--scales", type=float, nargs="+", default=[1.0, 1.1, 1.15, 1.2, 1.22, 1.25])
    ap.add_argument("--edge-length", type=float, default=0.05, help="triangle edge length in metres")
    ap.add_argument("--voxel", type=float, default=0.01, help="body SDF voxel size in metres")
    ap.add_argument("--weights", type=json.loads, default=None, help="cost coefficients as JSON")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    weights = CostWeights.from_dict(args.weights) if args.weights else None
    settings = AdjustSettings(edge_length=args.edge_length, voxel_size=args.voxel, weights=weights)
    setup = prepare(draft(args.garment, chart_row(args.base_size)), Body.from_size(args.base_size),
                    Body.from_size(args.target_size), settings)
    budget = replace(setup.exact_settings, max_iterations=4 * setup.exact_settings.max_iterations)
    problem = AdjustProblem(setup.model, setup.param, setup.objective, setup.x_transfer,
                            exact_settings=budget,
                            solver=settings.solver)
    panel = setup.mesh_base.vertex_panel_ids[setup.param.boundary_index]
    rows = []
    print(f"{args.garment} {args.base_size} -> {args.target_size}: {setup.mesh_base.num_vertices} vertices; "
          f"chart ratios "
          + ", ".join(f"{k} {chart_row(args.target_size)[k] / chart_row(args.base_size)[k]:.3f}"
                                       for k in ("bust", "waist", "hips")))
    print(f"{'scale':>6} {'objective':>10}  terms")
    for sx in args.scales:
        q = setup.q_base.clone()
        for k in panel.unique():
            m = panel == k
            c = q[m, 0].mean()
            q[m, 0] = c + sx * (q[m, 0] - c)
        problem.reset_state(setup.x_transfer)
        ev = problem.evaluate(q, exact=True, need_grad=False)
        terms = problem.term_values()
        rows.append({"scale": sx, "objective": ev.objective, "terms": terms})
        print(f"{sx:6.3f} {ev.objective:10.3f}  " + ", ".join(f"{k} {v:.3g}" for k, v in terms.items()))
    if args.json is not None:
        from torchgarment.io.atomic import atomic_open

        with atomic_open(args.json) as f:
            json.dump({"args": {k: str(v) for k, v in vars(args).items()}, "rows": rows}, f, indent=2)
            f.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
