"""Fit an anny body to every size of the built-in chart and report the accuracy and timing.

For each size: a cold fit (cache bypassed, then stored in a temporary cache), a warm load (cache hit), and the
body's own measurements (``measure_body``) against the request.

Usage::

    python scripts/bench_bodies.py [--sizes 6 12 20] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import torch


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="*", default=None, help="sizes to fit (default: all chart sizes)")
    parser.add_argument("--json", default=None, help="write the results to this JSON file")
    args = parser.parse_args(argv)

    from torchgarment.body.anny_body import body_from_measurements, load_anny_model
    from torchgarment.body.measure import measure_body
    from torchgarment.body.size_chart import SIZES, chart_row
    from torchgarment.errors import InputError
    from torchgarment.io.atomic import atomic_open

    t = time.perf_counter()
    load_anny_model()
    print(f"anny model load: {time.perf_counter() - t:.2f} s", flush=True)
    sizes = args.sizes or list(SIZES)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["TORCHGARMENT_CACHE"] = tmp
        header = (f"{'size':>4} | {'height mm':>18} | {'bust mm':>18} | {'waist mm':>18} | {'hips mm':>18} "
                  "| fit s | hit s")
        print(header)
        print("-" * len(header))
        for size in sizes:
            request = chart_row(size)
            t = time.perf_counter()
            try:
                body = body_from_measurements(request, cache=True)
            except InputError as e:
                print(f"{size:>4} | FAILED: {e}", flush=True)
                rows.append({"size": size, "error": str(e)})
                continue
            fit_s = time.perf_counter() - t
            t = time.perf_counter()
            again = body_from_measurements(request, cache=True)
            hit_s = time.perf_counter() - t
            assert again.params["cache_hit"] and torch.equal(again.vertices, body.vertices)
            measured = measure_body(body.vertices, body.faces).to_dict()
            row = {"size": size, "fit_seconds": fit_s, "cache_hit_seconds": hit_s}
            cells = []
            for k in ("height", "bust", "waist", "hips"):
                err = 1000 * (measured[k] - request[k])
                row[k] = {"requested": request[k], "measured": measured[k], "error_mm": err}
                cells.append(f"{1000 * request[k]:7.1f} {1000 * measured[k]:7.1f} {err:+4.1f}")
            row["underbust_error_mm"] = 1000 * (measured["underbust"] - request["underbust"])
            rows.append(row)
            print(f"{size:>4} | " + " | ".join(cells) + f" | {fit_s:5.1f} | {hit_s:5.2f}", flush=True)
    if args.json:
        with atomic_open(args.json) as f:
            json.dump(rows, f, indent=2)
    return 0 if all("error" not in r for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
