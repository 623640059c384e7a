"""Objective vs time and vs closure calls (cloth solves) for every pattern-adjustment optimizer (Wang 2018,
Fig. 12).

Usage:
    python scripts/compare_optimizers.py --out DIR [--garment straight_skirt] [--base-size 12]
        [--target-size 20] [--edge-length 0.04] [--voxel 0.01] [--iterations 32]
        [--optimizers pgd pgd-exact lbfgs gn fixed-point] [--threads 1]

The base drape, transfer and initialization are done once (:func:`torchgarment.adjust.pipeline.prepare`); each
optimizer then starts from the same initialized pattern with a fresh simulation state. ``pgd`` is Algorithm 1
(inexact simulations, the paper's method); ``pgd-exact`` the same preconditioned descent with exact solves and
an Armijo line search. Writes ``DIR/compare_optimizers.png`` (two panels: objective vs wall time and vs
closure calls, log scale), ``DIR/compare_optimizers.json`` (the curves and final numbers) and TensorBoard runs
under ``DIR/tb/<optimizer>``.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from torchgarment.adjust.pipeline import IterationRecord
    from torchgarment.body import Body
    from torchgarment.pattern.spec import SewingPattern


def load_case(args: argparse.Namespace) -> tuple[SewingPattern, Body, Body]:
    """(pattern drafted for the base size, base body, target body)."""
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    return draft(args.garment, chart_row(args.base_size)), Body.from_size(args.base_size), \
        Body.from_size(args.target_size)


def add_case_arguments(ap: argparse.ArgumentParser, iterations: int) -> None:
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--garment", default="straight_skirt", help="library garment")
    ap.add_argument("--base-size", default="12", help="chart size the pattern is drafted for")
    ap.add_argument("--target-size", default="20", help="chart size to adjust to")
    ap.add_argument("--edge-length", type=float, default=0.04, help="triangle edge length in metres")
    ap.add_argument("--voxel", type=float, default=0.01, help="SDF voxel size in metres")
    ap.add_argument("--iterations", type=int, default=iterations, help="outer iterations per run")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")


def save_figure(fig: Figure, path: Path) -> None:
    from torchgarment.io.atomic import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_case_arguments(ap, 32)
    ap.add_argument("--optimizers", nargs="+", default=["pgd", "pgd-exact", "lbfgs", "gn", "fixed-point"])
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchgarment.adjust.pipeline import AdjustSettings, optimize, prepare
    from torchgarment.io.atomic import atomic_open

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    pattern, base, target = load_case(args)
    settings = AdjustSettings(edge_length=args.edge_length, voxel_size=args.voxel, iterations=args.iterations)
    setup = prepare(pattern, base, target, settings)
    print(f"prepared: {setup.mesh_base.num_vertices} vertices, objective base {setup.objective_base:.4g}, "
          f"initialized {setup.objective_initial:.4g}")
    curves = {}
    for name in args.optimizers:
        kind, exact = (name[:-6], True) if name.endswith("-exact") else (name, False)
        s = replace(settings, optimizer=kind, inexact=not exact)
        calls = [0]
        rows = [(0.0, 0, setup.objective_initial, True)]

        def cb(rec: IterationRecord, terms: dict[str, float], rows: list[tuple] = rows,
               calls: list[int] = calls) -> None:
            calls[0] += rec.closure_calls
            rows.append((rec.seconds, calls[0], rec.objective, rec.exact))

        res = optimize(setup, s, log_dir=out / "tb" / name, progress=True, callback=cb)
        m = res.metrics
        curves[name] = {"seconds": [r[0] for r in rows], "closure_calls": [r[1] for r in rows],
                        "objective": [r[2] for r in rows], "exact": [r[3] for r in rows],
                        "objective_final": m["objective_final"], "reduction_percent": m["reduction_percent"],
                        "total_closure_calls": m["closure_calls"], "seconds_total": m["seconds"],
                        "max_boundary_displacement_mm": m["max_boundary_displacement_mm"]}
        print(f"{name:12s} final {m['objective_final']:.4g} ({m['reduction_percent']:.1f} %), "
              f"{m['closure_calls']} closure calls, {m['seconds']:.1f} s")
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for name, c in curves.items():
        axes[0].semilogy(c["seconds"], c["objective"], label=name)
        axes[1].semilogy(c["closure_calls"], c["objective"], label=name)
    axes[0].set_xlabel("wall time (s)")
    axes[1].set_xlabel("closure calls (cloth solves)")
    for ax in axes:
        ax.set_ylabel("objective")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.suptitle(f"{args.garment} {args.base_size} -> {args.target_size}, {setup.mesh_base.num_vertices} "
                 "vertices")
    fig.tight_layout()
    save_figure(fig, out / "compare_optimizers.png")
    with atomic_open(out / "compare_optimizers.json") as f:
        json.dump({"vertices": setup.mesh_base.num_vertices, "objective_base": setup.objective_base,
                   "objective_initial": setup.objective_initial, "curves": curves}, f, indent=2)
    print(f"-> {out / 'compare_optimizers.png'}")


if __name__ == "__main__":
    main()
