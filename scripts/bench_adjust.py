"""Benchmark of pattern adjustment: a ~30K-vertex garment, 256 outer iterations of Algorithm 1, total seconds
(target: at most 230 s on 2 CPU cores, issue 14's: twice the paper's 115 s for its 34K-vertex dress on a GTX
Titan X).

Usage:
    python scripts/bench_adjust.py --json FILE [--vertices 30000] [--iterations 256] [--garment sheath_dress]
        [--base-size 12] [--target-size 20] [--voxel 0.005] [--threads 2] [--inner-iterations 2]
        [--inner-solver newton|gd-chebyshev] [--adjoint direct|iterative] [--adjoint-max-iterations 50]
        [--inexact-adjoint projected|exact]
        [--reuse-factorization [--pcg-accept-rtol R]] [--linear-solver direct|jacobi-pcg] [--setup FILE]
        [--device cpu|cuda]
        [--sparse-backend superlu|cholmod|...] [--exact-curvature-cg N] [--min-model-ratio R]
        [--adapt-step | --no-adapt-step] [--step-window K] [--compare-exact]

``--setup FILE`` saves the precomputation (base drape, transfer, initialization: minutes at 30K vertices) on
the first run and loads it on the next ones, so that optimizer options can be compared on one setup.
``--compare-exact`` then also runs the exact method (an exact solve at every iteration, with its line search)
from the same precomputation and reports the timed configuration's final objective against it (the accuracy
that its speed must not buy: within 2 %).

The garment is meshed at the edge length that gives about ``--vertices`` vertices (measured on a coarse mesh
and scaled by the square root of the vertex ratio). As in the paper's Table 1, the timed total excludes the
precomputation (base drape, transfer, factorizations, initialization), which is reported separately. Reports
total seconds, seconds per iteration, closure calls (cloth solves), simulator iterations, objective reduction,
and a per-stage breakdown (``stages``: inexact solves, exact checks, the objective and its adjoints; for each
its seconds, sparse factorizations and substitutions with their seconds, counted by
:func:`torchgarment.linalg.count_linalg`, and the rest), and each exact evaluation (``exact_checks``: its
simulator iterations, seconds, and how far the garment moved in it, from the inexact iterations' state to the
equilibrium). ``meets_target`` is true only for a run at the target's scale (``--vertices 30000`` or more,
256 iterations or more) within ``target_seconds``.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from torchgarment.adjust.pipeline import AdjustSettings, AdjustSetup
    from torchgarment.body import Body
    from torchgarment.pattern.spec import SewingPattern


def edge_length_for(pattern: SewingPattern, vertices: int) -> tuple[float, int]:
    from torchgarment.pattern.meshing import mesh_pattern

    e = 0.05
    for _ in range(3):
        n = mesh_pattern(pattern, e).num_vertices
        e = e * math.sqrt(n / vertices)
    return e, mesh_pattern(pattern, e).num_vertices


def load_or_prepare(path: str | Path | None, pattern: SewingPattern, base: Body, target: Body,
                    settings: AdjustSettings, vertices: int,
                    device: torch.device | None = None) -> AdjustSetup:
    """The precomputation of ``pattern`` on ``base`` -> ``target``: loaded from ``path`` when it exists and is
    readable, else computed by :func:`~torchgarment.adjust.pipeline.prepare` and saved there atomically (a
    cache: an unreadable file is made again; None: no file).

    Raises:
        InputError: ``path`` holds a setup of another mesh (not ``vertices`` vertices at
            ``settings.edge_length``).
    """
    from torchgarment.adjust.pipeline import prepare
    from torchgarment.errors import InputError
    from torchgarment.io.atomic import atomic_path

    setup = None
    if path is not None and Path(path).is_file():
        try:
            setup = torch.load(path, weights_only=False, map_location=device)
        except Exception as exc:  # noqa: BLE001 - a cache: any unreadable file is made again
            print(f"{path} is unreadable ({type(exc).__name__}); making the precomputation again")
    if setup is not None:
        if (setup.mesh_base.num_vertices != vertices
                or not math.isclose(setup.settings.edge_length, settings.edge_length)):
            raise InputError(f"{path} holds a {setup.mesh_base.num_vertices}-vertex setup, not this "
                             f"{vertices}-vertex garment; pass another setup file")
        print(f"precomputation loaded from {path}")
        return setup
    setup = prepare(pattern, base, target, settings, device=device)
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            torch.save(setup, tmp)
    return setup


def main() -> None:
    from torchgarment.linalg import SparseBackend

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", default=None, help="write the results to this JSON file")
    ap.add_argument("--vertices", type=int, default=30000)
    ap.add_argument("--iterations", type=int, default=256)
    ap.add_argument("--garment", default="sheath_dress")
    ap.add_argument("--base-size", default="12")
    ap.add_argument("--target-size", default="20")
    ap.add_argument("--voxel", type=float, default=0.005)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--inner-iterations", type=int, default=2)
    ap.add_argument("--exact-interval", type=int, default=32)
    ap.add_argument("--min-model-ratio", type=float, default=None,
                    help="Algorithm 1's ratio test (AdjustSettings.min_model_ratio; default: the library's; "
                         "0: the paper's rule alone)")
    ap.add_argument("--adapt-step", action=argparse.BooleanOptionalAction, default=None,
                    help="between exact checks, halve the step after an inexact objective above the last "
                         "--step-window ones and lengthen it after one below them "
                         "(AdjustSettings.adapt_step; default: the library's)")
    ap.add_argument("--step-window", type=int, default=None,
                    help="inexact objectives --adapt-step compares with (AdjustSettings.step_window; "
                         "default: the library's)")
    ap.add_argument("--compare-exact", action="store_true",
                    help="also run the exact method from the same precomputation and report the final "
                         "objective against it")
    ap.add_argument("--inner-solver", default="newton", choices=["newton", "gd-chebyshev"],
                    help="solver of the S-iteration simulations")
    ap.add_argument("--adjoint", default="direct", choices=["direct", "iterative"], help="adjoint solve")
    ap.add_argument("--adjoint-max-iterations", type=int, default=50)
    ap.add_argument("--inexact-adjoint", default=None, choices=["projected", "exact"],
                    help="the Hessian of the adjoint at inexact states (AdjustSettings.inexact_adjoint; "
                         "default: the library's)")
    ap.add_argument("--reuse-factorization", action="store_true",
                    help="Newton solves reuse their LU factorization through PCG "
                         "(AdjustSettings.reuse_factorization)")
    ap.add_argument("--pcg-accept-rtol", type=float, default=None, metavar="R",
                    help="with --reuse-factorization, a CG step stopped by its budget is still taken within "
                         "this relative residual (AdjustSettings.pcg_accept_rtol; 0: never; default: the "
                         "library's)")
    ap.add_argument("--sparse-backend", default="superlu",
                    choices=[k.value for k in SparseBackend],
                    help="sparse direct solver of Newton systems, adjoints and tangents "
                         "(pardiso/cholespy/cholmod: when installed)")
    ap.add_argument("--exact-curvature-cg", type=int, default=None, metavar="N",
                    help="Newton's direction by N CG iterations on the exact Hessian preconditioned by a "
                         "factorization of the projected one (AdjustSettings.exact_curvature_cg; 0: "
                         "projected Newton; default: the library's, 10 with --linear-solver direct, else 0)")
    ap.add_argument("--linear-solver", default="direct", choices=["direct", "jacobi-pcg"],
                    help="Newton's linear solves (AdjustSettings.linear_solver): a factorization on the CPU "
                         "or block-Jacobi CG on --device")
    ap.add_argument("--setup", default=None, metavar="FILE",
                    help="load the precomputation from FILE when it exists, else compute it and save it "
                         "there (torch.save of the AdjustSetup; the timed optimization is unaffected)")
    ap.add_argument("--device", default="cpu",
                    help="cpu, cuda or cuda:N: where the simulation and the objective run (the sparse "
                         "factorizations stay on the CPU); a --setup file is read onto this device")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from torchgarment.adjust.pipeline import AdjustSettings, optimize
    from torchgarment.benchmarking import MachineWatch
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.io.atomic import atomic_open
    from torchgarment.options import resolve_device
    from torchgarment.pattern.library import draft
    from torchgarment.sim.solvers import LinearSolver, exact_curvature_iterations

    watch = MachineWatch()

    device = resolve_device(args.device)

    pattern = draft(args.garment, chart_row(args.base_size))
    edge, n = edge_length_for(pattern, args.vertices)
    print(f"{args.garment}: edge length {1e3 * edge:.1f} mm -> {n} vertices")
    base = Body.from_size(args.base_size, device=device)
    target = Body.from_size(args.target_size, device=device)
    ratio = AdjustSettings.min_model_ratio if args.min_model_ratio is None else args.min_model_ratio
    if args.pcg_accept_rtol is None:
        args.pcg_accept_rtol = AdjustSettings.pcg_accept_rtol
    elif args.pcg_accept_rtol == 0:
        args.pcg_accept_rtol = None
    adapt = AdjustSettings.adapt_step if args.adapt_step is None else args.adapt_step
    window = AdjustSettings.step_window if args.step_window is None else args.step_window
    inexact_adjoint = (AdjustSettings.inexact_adjoint if args.inexact_adjoint is None
                       else args.inexact_adjoint)
    settings = AdjustSettings(edge_length=edge, voxel_size=args.voxel, iterations=args.iterations,
                              inner_iterations=args.inner_iterations, exact_interval=args.exact_interval,
                              min_model_ratio=ratio, adapt_step=adapt, step_window=window,
                              inner_solver=args.inner_solver, adjoint=args.adjoint,
                              adjoint_max_iterations=args.adjoint_max_iterations,
                              inexact_adjoint=inexact_adjoint,
                              reuse_factorization=args.reuse_factorization,
                              pcg_accept_rtol=args.pcg_accept_rtol,
                              sparse_backend=args.sparse_backend, linear_solver=args.linear_solver,
                              exact_curvature_cg=args.exact_curvature_cg)
    t0 = time.perf_counter()
    setup = load_or_prepare(args.setup, pattern, base, target, settings, n, device)
    t_prep = time.perf_counter() - t0
    print(f"precomputation {t_prep:.1f} s ({setup.timings})")
    run_settings = replace(setup.settings, iterations=args.iterations, inner_iterations=args.inner_iterations,
                           exact_interval=args.exact_interval, min_model_ratio=ratio,
                           adapt_step=adapt, step_window=window,
                           inner_solver=args.inner_solver, adjoint=args.adjoint,
                           adjoint_max_iterations=args.adjoint_max_iterations,
                           inexact_adjoint=inexact_adjoint,
                           reuse_factorization=args.reuse_factorization,
                           pcg_accept_rtol=args.pcg_accept_rtol, sparse_backend=args.sparse_backend,
                           linear_solver=args.linear_solver, exact_curvature_cg=args.exact_curvature_cg)
    res = optimize(setup, run_settings, progress=True)
    m = res.metrics
    out = {
        "garment": args.garment, "vertices": m["vertices"], "boundary_vertices": m["boundary_vertices"],
        "edge_length_mm": 1e3 * edge, "iterations": m["iterations"], "threads": args.threads,
        "inner_iterations": args.inner_iterations, "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor(),
        "exact_interval": args.exact_interval, "min_model_ratio": ratio,
        "adapt_step": adapt, "step_window": window,
        "poor_model_checks": m["poor_model_checks"],
        "inner_solver": args.inner_solver, "adjoint": args.adjoint, "sparse_backend": args.sparse_backend,
        "inexact_adjoint": m["inexact_adjoint"],
        "reuse_factorization": args.reuse_factorization, "pcg_accept_rtol": args.pcg_accept_rtol,
        "linear_solver": args.linear_solver,
        "exact_curvature_cg": exact_curvature_iterations(args.exact_curvature_cg,
                                                         LinearSolver.resolve(args.linear_solver)),
        "adjoint_iterations": m["adjoint_iterations"],
        "adjoint_max_iterations": args.adjoint_max_iterations,
        "adjoint_factorizations": m["factorizations"],
        "total_seconds": m["seconds"], "seconds_per_iteration": m["seconds_per_iteration"],
        "target_seconds": TARGET_SECONDS,
        # the target is for the paper's scale: a smaller run says nothing about it
        "meets_target": bool(args.vertices >= 30_000 and m["iterations"] >= 256
                             and m["seconds"] <= TARGET_SECONDS),
        "closure_calls": m["closure_calls"], "sim_iterations": m["sim_iterations"],
        "exact_evaluations": m["exact_evaluations"], "backtracks": m["backtracks"],
        "stage_seconds": m["stage_seconds"],
        "stages": stage_breakdown(m),
        "exact_checks": m["exact_checks"],
        "objective_initial": m["objective_initial"], "objective_final": m["objective_final"],
        "reduction_percent": m["reduction_percent"], "precomputation_seconds": t_prep,
        "timings": setup.timings,
        "machine": watch.finish(), "torch": torch.__version__,
    }
    if args.compare_exact:
        ref = optimize(setup, replace(run_settings, inexact=False), progress=True).metrics
        out["exact_reference"] = {k: ref[k] for k in ("objective_final", "seconds", "sim_iterations",
                                                       "closure_calls", "stage_seconds")}
        out["exact_reference"]["stages"] = stage_breakdown(ref)
        out["objective_vs_exact_percent"] = 100.0 * (m["objective_final"] / ref["objective_final"] - 1.0)
        out["within_2_percent_of_exact"] = bool(m["objective_final"] <= 1.02 * ref["objective_final"])
    print(json.dumps(out, indent=2))
    rows = [(f"timed (S = {args.inner_iterations}, M = {args.exact_interval})", m["objective_final"],
             m["seconds"])]
    if args.compare_exact:
        rows.append(("exact every iteration", out["exact_reference"]["objective_final"],
                     out["exact_reference"]["seconds"]))
    print(f"\n{'run':<32} {'objective':>22} {'seconds':>9}")
    for name, f, sec in rows:
        print(f"{name:<32} {m['objective_initial']:>10.4g} -> {f:<8.4g} {sec:>9.1f}")
    print_stages(out["stages"], m["seconds"])
    print_checks(m["exact_checks"])
    if args.compare_exact:
        print(f"timed against exact: {out['objective_vs_exact_percent']:+.2f} % (target <= +2 %)")
    print(MachineWatch.describe(out["machine"]))
    if args.json:
        with atomic_open(args.json, "w") as f:
            json.dump(out, f, indent=2)
            f.write("\n")


TARGET_SECONDS = 230.0
"""Issue 14's target for 30K vertices x 256 iterations on 2 CPU cores (twice the paper's GPU time)."""

STAGE_NAMES = {"inexact_solves": "inexact solves", "exact_solves": "exact checks",
               "objective_and_adjoints": "objective and adjoints"}


def stage_breakdown(metrics: dict) -> dict[str, dict[str, float]]:
    """Per stage of the loop (``metrics["stage_seconds"]`` and ``["stage_linalg"]`` of
    :func:`~torchgarment.adjust.optimize`): seconds, factorizations and substitutions (counts and seconds),
    and the seconds outside them."""
    out = {}
    for stage, seconds in metrics["stage_seconds"].items():
        la = metrics["stage_linalg"][stage]
        out[stage] = {"seconds": seconds, **la,
                      "other_seconds": seconds - la["factorization_seconds"] - la["solve_seconds"]}
    return out


def print_stages(stages: dict[str, dict[str, float]], total: float) -> None:
    """The breakdown as a table (the loop's remainder, the optimizer's own work, as the last row)."""
    print(f"\n{'stage':<24} {'seconds':>9} {'factorizations':>15} {'(s)':>8} {'solves':>7} {'(s)':>8} "
          f"{'other (s)':>10}")
    for stage, r in stages.items():
        print(f"{STAGE_NAMES.get(stage, stage):<24} {r['seconds']:9.1f} {r['factorizations']:15d} "
              f"{r['factorization_seconds']:8.1f} {r['solves']:7d} {r['solve_seconds']:8.1f} "
              f"{r['other_seconds']:10.1f}")
    rest = total - sum(r["seconds"] for r in stages.values())
    print(f"{'optimizer (the rest)':<24} {rest:9.1f}")


def print_checks(checks: list[dict]) -> None:
    """The exact evaluations as a table: how long each took and how far the garment moved in it (from the
    inexact iterations' state to the equilibrium)."""
    if not checks:
        return
    print(f"\n{'exact check':<12} {'objective':>10} {'sim its':>8} {'seconds':>9} {'moved max (mm)':>15} "
          f"{'mean (mm)':>10}")
    for c in checks:
        name = f"{c['iteration']}{' (final)' if c.get('final') else ''}"
        print(f"{name:<12} {c['objective']:10.4g} {c['sim_iterations']:8d} {c['seconds']:9.1f} "
              f"{c['displacement_max_mm']:15.2f} {c['displacement_mean_mm']:10.2f}")


if __name__ == "__main__":
    from torchgarment.cli import exit_code
    from torchgarment.errors import TorchGarmentError

    try:
        main()
    except TorchGarmentError as exc:  # e.g. a 30K precomputation's settle that does not converge: one line
        print(f"bench_adjust: error: {type(exc).__name__}: {exc}", file=sys.stderr)
        sys.exit(exit_code(exc))
