"""Issue 14's accuracy guard over several problems: a configuration of Algorithm 1 against the exact method
(an exact solve at every iteration), one precomputation per target size.

Usage::

    python scripts/adjust_accuracy_guard.py [--garment sheath_dress] [--vertices 3000] [--base-size 12]
        [--targets 6 8 16 20] [--iterations 24] [--exact-interval 8] [--inner-iterations 2]
        [--inexact-adjoint exact|projected] [--sparse-backend superlu|cholmod|...] [--voxel 0.005]
        [--threads 1] [--setup-dir D] [--json F]

Issue 14 asks that speed not be bought with accuracy: the fast configuration's final objective within 2 % of
the exact method's on the 3K-vertex dress. On one target that comparison is mostly the path: Algorithm 1's
inexact iterations and its exact checks every ``M`` iterations take one of several nearby descents, and a
difference of round-off at one check sends two runs to objectives tens of percent apart (on 2026-12-02 the
library's defaults ended 1 % to 25 % above the exact method on four targets of the 3K dress, 24 iterations,
``M`` = 8). This script runs the configuration and the exact method from the same precomputation on each
target and reports every ratio, their geometric mean and how many are within 2 %, so that configurations are
compared over several problems instead of one path.

The garment is meshed as in ``scripts/bench_adjust.py`` (``--vertices``). With ``--setup-dir`` each target's
precomputation (base drape, transfer, initialization) is saved there on the first run and loaded on the next
ones (``setup_<garment>_<base>_<target>_<vertices>.pt``), as ``bench_adjust.py --setup`` does; the exact
method runs every time (its result depends on the code, not only on the setup). Writes a JSON with one row
per target and the summary; exit 1 if a target failed (the others go on), 2 on bad input.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import traceback
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from bench_adjust import edge_length_for, load_or_prepare  # noqa: E402

WITHIN = 0.02
"""The issue's guard: the configuration's final objective at most 2 % above the exact method's."""


def summarize(rows: list[dict]) -> dict:
    """Geometric mean, best and worst of the ratios final / exact-method final over the rows that ran."""
    ratios = [r["ratio"] for r in rows if r.get("ok")]
    if not ratios:
        return {"targets": 0}
    return {"targets": len(ratios),
            "geometric_mean_ratio": math.exp(sum(math.log(x) for x in ratios) / len(ratios)),
            "best_ratio": min(ratios), "worst_ratio": max(ratios),
            "within_2_percent": sum(x <= 1.0 + WITHIN for x in ratios)}


def main(argv: list[str] | None = None) -> int:
    from torchgarment.adjust.pipeline import AdjustSettings, optimize
    from torchgarment.benchmarking import MachineWatch
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.errors import InputError
    from torchgarment.io.atomic import atomic_open
    from torchgarment.linalg import SparseBackend
    from torchgarment.pattern.library import draft
    from torchgarment.sim import AdjointHessian

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--garment", default="sheath_dress")
    ap.add_argument("--vertices", type=int, default=3000)
    ap.add_argument("--base-size", default="12")
    ap.add_argument("--targets", nargs="+", default=["6", "8", "16", "20"], help="target chart sizes")
    ap.add_argument("--iterations", type=int, default=24)
    ap.add_argument("--exact-interval", type=int, default=8, help="M")
    ap.add_argument("--inner-iterations", type=int, default=2, help="S")
    ap.add_argument("--inexact-adjoint", default=AdjustSettings.inexact_adjoint.value,
                    choices=[k.value for k in AdjointHessian])
    ap.add_argument("--sparse-backend", default="superlu", choices=[k.value for k in SparseBackend])
    ap.add_argument("--voxel", type=float, default=0.005)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--setup-dir", default=None, help="keep each target's precomputation here")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    watch = MachineWatch()
    try:
        targets = [(t, Body.from_size(t)) for t in args.targets]
        pattern = draft(args.garment, chart_row(args.base_size))
        base = Body.from_size(args.base_size)
        if args.vertices < 100:
            raise InputError(f"--vertices must be at least 100, got {args.vertices}")
        edge, n = edge_length_for(pattern, args.vertices)
        settings = AdjustSettings(edge_length=edge, voxel_size=args.voxel, iterations=args.iterations,
                                  inner_iterations=args.inner_iterations, exact_interval=args.exact_interval,
                                  inexact_adjoint=args.inexact_adjoint, sparse_backend=args.sparse_backend)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{args.garment}: {n} vertices ({1e3 * edge:.1f} mm edges); S = {args.inner_iterations}, "
          f"M = {args.exact_interval}, {args.iterations} iterations, inexact adjoint {args.inexact_adjoint}")
    rows: list[dict] = []
    for size, target in targets:
        row: dict = {"target_size": size}
        try:
            path = (None if args.setup_dir is None else
                    Path(args.setup_dir) / f"setup_{args.garment}_{args.base_size}_{size}_{args.vertices}.pt")
            made = path is None or not path.is_file()
            t0 = time.perf_counter()
            setup = load_or_prepare(path, pattern, base, target, settings, n)
            if made:
                row["precomputation_seconds"] = time.perf_counter() - t0
            run = replace(setup.settings, iterations=args.iterations, inner_iterations=args.inner_iterations,
                          exact_interval=args.exact_interval, inexact_adjoint=args.inexact_adjoint,
                          sparse_backend=args.sparse_backend)
            timed = optimize(setup, run, progress=False).metrics
            exact = optimize(setup, replace(run, inexact=False), progress=False).metrics
            row.update(ok=True, objective_initial=timed["objective_initial"],
                       objective_final=timed["objective_final"], seconds=timed["seconds"],
                       exact_evaluations=timed["exact_evaluations"], backtracks=timed["backtracks"],
                       exact_objective_final=exact["objective_final"], exact_seconds=exact["seconds"],
                       ratio=timed["objective_final"] / exact["objective_final"])
        except Exception as exc:  # noqa: BLE001 - one failed target must not stop the others
            if not isinstance(exc, InputError):  # bad input (a setup file of another mesh) is its one line
                traceback.print_exc()
            row.update(ok=False, error=f"{type(exc).__name__}: {exc}".splitlines()[0])
        rows.append(row)
        if row["ok"]:
            print(f"size {size}: {row['objective_initial']:.4g} -> {row['objective_final']:.4g} in "
                  f"{row['seconds']:.1f} s; exact method {row['exact_objective_final']:.4g} in "
                  f"{row['exact_seconds']:.1f} s ({100 * (row['ratio'] - 1):+.1f} %)", flush=True)
        else:
            print(f"size {size}: failed ({row['error']})", flush=True)
    summary = summarize(rows)
    print("\n| target | initial | final | exact method | vs exact | seconds (exact method) |\n"
          "|---|---|---|---|---|---|")
    for r in rows:
        if r["ok"]:
            print(f"| {r['target_size']} | {r['objective_initial']:.4g} | {r['objective_final']:.4g} | "
                  f"{r['exact_objective_final']:.4g} | {100 * (r['ratio'] - 1):+.1f} % | {r['seconds']:.1f} "
                  f"({r['exact_seconds']:.1f}) |")
        else:
            print(f"| {r['target_size']} | failed: {r['error']} | | | | |")
    if summary["targets"]:
        print(f"\ngeometric mean of final / exact method: {summary['geometric_mean_ratio']:.4f} (best "
              f"{summary['best_ratio']:.4f}, worst {summary['worst_ratio']:.4f}); within 2 %: "
              f"{summary['within_2_percent']} of {summary['targets']}")
    machine = watch.finish()
    print(MachineWatch.describe(machine))
    if args.json is not None:
        with atomic_open(args.json, "w") as f:
            json.dump({"settings": vars(args) | {"vertices_meshed": n, "edge_length_m": edge},
                       "rows": rows, "summary": summary, "machine": machine}, f, indent=2, default=str)
            f.write("\n")
    return 0 if all(r["ok"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
