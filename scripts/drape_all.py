"""Drape every library garment on the smallest and largest chart bodies, and the GarmentCode specs on their
bodies.

Prints a table (garment, body, vertices, iterations, seconds, residual, min_sdf_mm, max_seam_gap_mm,
converged, intersects_self) and optionally writes every case's metrics as JSON.

Example::

    python scripts/drape_all.py --edge-length 0.03 --voxel 0.005 --json out/drape_all.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from torchgarment.body import Body
    from torchgarment.pattern.spec import SewingPattern

LIBRARY = ["straight_skirt", "aline_skirt", "sheath_dress", "tshirt", "trousers", "bodysuit"]
SIZES = ["6", "20"]
GARMENTCODE = [("shirt_mean", "mean_all"), ("dress_pencil", "mean_female")]
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "garmentcode"


def _cases(data: Path, only: list[str] | None) -> Iterator[
        tuple[str, str, Callable[[], Body], Callable[[], SewingPattern]]]:
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    for size in SIZES:
        for g in LIBRARY:
            if only and g not in only:
                continue
            yield (g, f"size {size}", (lambda s=size: Body.from_size(s)),
                   (lambda g=g, s=size: draft(g, chart_row(s))))
    for spec, body in GARMENTCODE:
        if only and spec not in only:
            continue
        from torchgarment.body.load import load_body
        from torchgarment.pattern.garmentcode import load_pattern

        yield (spec, body, (lambda b=body: load_body(data / "bodies" / f"{b}.obj")),
               (lambda s=spec: load_pattern(data / "patterns" / f"{s}_specification.json")))


def main(argv: list[str] | None = None) -> int:
    from torchgarment.sim.drape import DrapeSettings, drape

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--edge-length", type=float, default=0.03, help="triangle edge length in metres")
    ap.add_argument("--voxel", type=float, default=0.005, help="SDF voxel size in metres")
    ap.add_argument("--sew-solver", default="gd-chebyshev")
    ap.add_argument("--solver", default="newton")
    ap.add_argument("--sew-iterations", type=int, default=800)
    ap.add_argument("--max-iterations", type=int, default=1500)
    ap.add_argument("--only", nargs="+", help="garment names to run (default all)")
    ap.add_argument("--data", type=Path, default=DATA, help="GarmentCode data folder")
    ap.add_argument("--json", type=Path, help="write all metrics to this JSON file")
    ap.add_argument("--self-contact", action="store_true",
                    help="IPC cloth-cloth contact: within panels while sewing, welded in the settle "
                         "(DrapeSettings.self_contact)")
    args = ap.parse_args(argv)

    settings = DrapeSettings(edge_length=args.edge_length, voxel_size=args.voxel, sew_solver=args.sew_solver,
                             solver=args.solver, sew_max_iterations=args.sew_iterations,
                             max_iterations=args.max_iterations, self_contact=args.self_contact)
    cols = ["garment", "body", "vertices", "iterations", "seconds", "residual", "min_sdf_mm",
            "max_seam_gap_mm", "converged", "intersects_self"]
    print(" | ".join(cols), flush=True)
    rows = []
    for garment, body_name, make_body, make_pattern in _cases(args.data, args.only):
        t0 = time.perf_counter()
        try:
            result = drape(make_pattern(), make_body(), settings=settings)
            m = dict(result.metrics)
            m["seconds"] = time.perf_counter() - t0
            row = {"garment": garment, "body": body_name, **m}
            print(f"{garment} | {body_name} | {m['vertices']} | {m['iterations']} | {m['seconds']:.1f} | "
                  f"{m['residual']:.3g} | {m['min_sdf_mm']:.2f} | {m['max_seam_gap_mm']:.3f} | "
                  f"{m['converged']} | {m['intersects_self']}",
                  flush=True)
        except Exception as exc:  # report the failure and go on with the next case
            traceback.print_exc(file=sys.stderr)
            row = {"garment": garment, "body": body_name, "error": f"{type(exc).__name__}: {exc}"}
            print(f"{garment} | {body_name} | FAILED: {row['error']}", flush=True)
        rows.append(row)
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(rows, indent=2, default=float) + "\n")
    return 0 if all("error" not in r and r.get("ok") for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
