"""Benchmark of ``torchgarment grade`` (issue 18): the straight skirt from size 12 over a size run at the
default settings of ``torchgarment adjust``; prints the total wall time and the time per size, writes JSON.

Target: 6 sizes within 10 minutes on 2 cores.

    OMP_NUM_THREADS=2 python scripts/bench_grade.py --threads 2 --out bench_grade_out --json bench_grade.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--garment", default="straight_skirt")
    ap.add_argument("--base-size", default="12")
    ap.add_argument("--sizes", nargs="+", default=["6", "8", "10", "14", "16", "20"])
    ap.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    ap.add_argument("--iterations", type=int, default=None, help="outer iterations (default: adjust's)")
    ap.add_argument("--out", default="bench_grade_out", help="output folder of the grade run")
    ap.add_argument("--json", default=None, help="write the figures here")
    args = ap.parse_args()

    import torch

    from torchgarment.adjust.cli import write_outputs
    from torchgarment.adjust.grade import format_table, grade
    from torchgarment.adjust.pipeline import AdjustSettings
    from torchgarment.benchmarking import machine_record
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    torch.set_num_threads(args.threads)
    settings = AdjustSettings() if args.iterations is None else AdjustSettings(iterations=args.iterations)
    t0 = time.perf_counter()
    base_body = Body.from_size(args.base_size)
    targets = {s: Body.from_size(s) for s in args.sizes}
    pattern = draft(args.garment, chart_row(args.base_size))
    load_seconds = time.perf_counter() - t0
    b = chart_row(args.base_size)
    chart = {s: {m: chart_row(s)[m] - b[m] for m in b if m != "height"} for s in args.sizes}
    result = grade(pattern, base_body, targets, settings, Path(args.out), resume=False, progress=True,
                   base_size=args.base_size, chart_changes=chart, writer=write_outputs)
    m = result.metrics
    print(format_table(result.rows))
    print()
    print(f"{'size':>6}  {'status':>8}  {'seconds':>8}  {'iterations':>10}  {'reduction %':>11}")
    for k, s in result.sizes.items():
        print(f"{k:>6}  {s.status:>8}  {s.seconds:8.1f}  {s.metrics.get('iterations', 0):>10}  "
              f"{s.metrics.get('reduction_percent', float('nan')):11.1f}")
    n = max(len(result.sizes), 1)
    print(f"total {m['total_seconds']:.1f} s ({m['total_seconds'] / 60:.2f} min) for {len(result.sizes)} "
          f"sizes, "
          f"{m['total_seconds'] / n:.1f} s per size; base drape once: {m['base_drape_once']} "
          f"({m['base_drape_seconds']:.1f} s); bodies and pattern {load_seconds:.1f} s; "
          f"{args.threads} threads; failed: {result.failed or 'none'}")
    if args.json:
        out = {"garment": args.garment, "base_size": args.base_size, "sizes": args.sizes,
               "threads": args.threads, "settings": {"edge_length": settings.edge_length,
                                                     "voxel_size": settings.voxel_size,
                                                     "iterations": settings.iterations},
               "total_seconds": m["total_seconds"], "seconds_per_size": m["seconds_per_size"],
               "mean_seconds_per_size": m["total_seconds"] / n, "base_drape_once": m["base_drape_once"],
               "base_drape_seconds": m["base_drape_seconds"], "load_seconds": load_seconds,
               "failed": result.failed, "acceptance": m["acceptance"],
               "machine": machine_record()}
        Path(args.json).write_text(json.dumps(out, indent=2, default=str) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
