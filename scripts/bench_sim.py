"""Benchmark of one simulator iteration (GD-Chebyshev) against a bare spring evaluation, per garment size.

Usage:
    python scripts/bench_sim.py [--json FILE] [--sizes 5000 15000 30000 60000] [--garment tshirt]
                                [--body-size 12] [--voxel-mm 2.5] [--sdf-dtype float32] [--threads 2]
                                [--warmup 200] [--iterations 60] [--calls 60] [--rounds 6]
                                [--diagonal-interval 4] [--device cpu|cuda] [--sweep] [--parts]
                                [--profile N]

For every target size the library garment ``--garment`` (drafted for chart size ``--body-size``) is meshed at
the edge length that gives about that many vertices, and a scene with stretch, sew, bend, gravity and the body
barrier (SDF of ``Body.from_size(--body-size)`` at ``--voxel-mm``, from the disk cache, stored in
``--sdf-dtype``; positions stay float64) is built. Its state is the placed panels projected out of the body
and then ``--warmup`` GD-Chebyshev iterations (some vertices close to the body, as in a real drape). Measured
in the same process, with ``torch.set_num_threads(--threads)``:

* ``ms_per_iteration``: wall time between consecutive solver callbacks with the default :class:`SolveSettings`
  (the preconditioner is rebuilt every iteration with the barrier's rows fresh; the springs' diagonal is
  refreshed every ``elastic_diagonal_interval`` = 4 iterations): gradient, Hessian diagonal, preconditioner,
  Chebyshev update and step bound; ``ms_per_iteration_diagonal_interval``: the same with the whole
  preconditioner rebuilt only every ``--diagonal-interval`` iterations; ``ms_per_iteration_after_restart``:
  the same with the springs' diagonal fresh every iteration, the regime after the solver's first restart
  (an energy increase at a checkpoint), which lasts the rest of the solve;
* ``ms_bare_spring``: the baseline, one stretch ``value_and_grad`` (energy and gradient of the springs alone)
  on the same mesh and state;
* per effect: ``ms_value_grad`` and ``ms_value_grad_diag`` of its term alone on fresh positions (no cache
  hit), for the barrier also ``ms_max_step`` (its own SDF query) and ``ms_value_grad_then_max_step`` (as the
  solver calls it: the step bound reuses the gradient's SDF query), with the solver's first step; and
  ``ms_saved_when_left_out``: ``ms_per_iteration`` minus the per-iteration time of the same solve without
  that effect.

``--parts`` also times, at about 30K vertices on one settled state, each part of an iteration as the solver
calls it (see :func:`parts`): the model's value and gradient, its value, gradient and diagonal with the
elastic diagonal fresh or reused, the preconditioner's full rebuild and its update of the volatile rows, its
application, the row clamp and the step bound, each against the bare spring pass (the solver's own vector
updates and energy checks are not among them).

All measurements are interleaved over ``--rounds`` rounds so that a varying machine load affects them alike.
Times are medians, ``*_min`` minima (the best estimate on a shared machine); ratios are against the baseline
measured in the same run. A table is printed; ``--json`` writes everything.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import time
from collections.abc import Callable, Iterable
from dataclasses import replace
from typing import TYPE_CHECKING

import torch

from torchgarment.benchmarking import MachineWatch
from torchgarment.body import Body
from torchgarment.body.size_chart import chart_row
from torchgarment.io.atomic import atomic_open
from torchgarment.options import resolve_device
from torchgarment.pattern.library import draft
from torchgarment.pattern.meshing import mesh_pattern
from torchgarment.sdf import BodySDF, SDFSettings
from torchgarment.sim.scene import Effect, Scene, SimModel
from torchgarment.sim.solvers import Preconditioner, SolveSettings, solve
from torchgarment.sim.solvers.chebyshev import (
    JacobiState,
    apply_inverse,
    clamp_displacement_,
    jacobi_inverse,
    seam_pairs,
)

if TYPE_CHECKING:
    from torchgarment.pattern.spec import SewingPattern
    from torchgarment.structures.garment_mesh import GarmentMesh

DEFAULT_SIZES = (5_000, 15_000, 30_000, 60_000)
EFFECTS = (Effect.STRETCH, Effect.SEW, Effect.BEND, Effect.GRAVITY, Effect.BODY_BARRIER)
TARGET_MS_30K = 20.0
TARGET_RATIO = 4.0


def call_times(fn: Callable[[torch.Tensor], object], x: torch.Tensor, calls: int,
               before: Callable[[torch.Tensor], object] | None = None) -> list[float]:
    """Seconds of ``calls`` calls of ``fn(x)``.

    Every call gets its own copy of ``x`` (made before the clock starts), so that no term can reuse results
    cached for the previous call's positions (the barrier caches its last SDF query). ``before(copy)``, when
    given, runs before the clock starts (``model.value_and_grad`` before the step bound, which reuses the
    evaluation's SDF query as in the solver).
    """
    ts = []
    for _ in range(calls):
        xc = x.clone()
        if before is not None:
            before(xc)
        sync(x.device)
        t0 = time.perf_counter()
        fn(xc)
        sync(x.device)
        ts.append(time.perf_counter() - t0)
    return ts


def sync(device: torch.device) -> None:
    """Wait for the device's queued work (CUDA launches are asynchronous; a no-op on the CPU)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def run_interleaved(tasks: dict, rounds: int) -> dict[str, tuple[float, float]]:
    """Run every task (``name -> () -> list of seconds``) once per round, in turn, so that a varying machine
    load hits all of them alike; returns ``name -> (median ms, min ms)`` over all samples (after one warm-up
    round that is discarded)."""
    samples: dict[str, list[float]] = {k: [] for k in tasks}
    for r in range(rounds + 1):
        for k, fn in tasks.items():
            ts = fn()
            if r > 0:
                samples[k].extend(ts)
    return {k: (1e3 * statistics.median(v), 1e3 * min(v)) for k, v in samples.items()}


def mesh_with_vertices(pattern: SewingPattern, target: int, dtype: torch.dtype) -> tuple[GarmentMesh, float]:
    """Mesh ``pattern`` at the edge length giving about ``target`` vertices (V ~ 1 / h^2, two corrections)."""
    h = 0.005
    mesh = mesh_pattern(pattern, h, dtype=dtype)
    for _ in range(2):
        h *= math.sqrt(mesh.num_vertices / target)
        mesh = mesh_pattern(pattern, h, dtype=dtype)
    return mesh, h


def iteration_times(model: SimModel, x: torch.Tensor, settings: SolveSettings,
                    iterations: int) -> list[float]:
    """Seconds between consecutive solver callbacks (one per iteration) of a GD-Chebyshev solve from ``x``."""
    stamps: list[float] = []

    def cb(k: int, xk: torch.Tensor, gn: float, e: float) -> bool:
        sync(xk.device)
        stamps.append(time.perf_counter())
        return False

    solve(model, x, settings, solver="gd-chebyshev", max_iterations=iterations + 1, callback=cb)
    return [b - a for a, b in zip(stamps[:-1], stamps[1:])]


def bench_size(target: int, args: argparse.Namespace, pattern: SewingPattern, sdf: BodySDF) -> dict:
    """One table row (a dict) for the size ``target``."""
    dtype = torch.float64
    mesh, h = mesh_with_vertices(pattern, target, dtype)
    mesh = mesh.to(sdf.device)
    settings = SolveSettings(rtol=0.0, atol=0.0)

    def build(effects: Iterable[Effect]) -> SimModel:
        return Scene(mesh, body_sdf=sdf, effects=set(effects)).build()

    model = build(EFFECTS)
    x = model.project_feasible(mesh.x.detach())
    if args.warmup > 0:
        x, _ = solve(model, x, settings, solver="gd-chebyshev", max_iterations=args.warmup)
    phi = sdf(x.to(sdf.dtype))
    near = int((phi < 0.01).sum())

    stretch = model.term(Effect.STRETCH.value)
    # the solver's first step from x (for timing max_step on a realistic step)
    _, g, hd = model.value_grad_hessian_diagonal(x)
    inverse = jacobi_inverse(hd, settings.preconditioner, settings.diagonal_floor)
    step = apply_inverse(inverse, g).mul_(-settings.step)
    n = torch.linalg.vector_norm(step, dim=1, keepdim=True)
    step.mul_(settings.max_displacement / n.clamp_min(settings.max_displacement))

    per_round = max(1, args.iterations // args.rounds)
    calls = max(1, args.calls // args.rounds)
    settings_k = replace(settings, diagonal_interval=args.diagonal_interval)
    # after a restart (energy up at a checkpoint) GD-Chebyshev refreshes the elastic diagonal every iteration
    # for the rest of the solve: the regime of most of a long solve (library drapes' sewing stages restart
    # once after 88-288 iterations)
    settings_fresh = replace(settings, elastic_diagonal_interval=1)
    tasks = {
        "spring": lambda: call_times(stretch.value_and_grad, x, calls),
        "iteration": lambda: iteration_times(model, x, settings, per_round),
        "iteration_k": lambda: iteration_times(model, x, settings_k, per_round),
        "iteration_fresh": lambda: iteration_times(model, x, settings_fresh, per_round),
    }
    for eff in EFFECTS:
        term = model.term(eff.value)
        without = build([e for e in EFFECTS if e is not eff])
        tasks[f"{eff.value}/v+g"] = lambda term=term: call_times(term.value_and_grad, x, calls)
        fused = getattr(term, "value_grad_hessian_diagonal", None)
        if fused is not None:
            tasks[f"{eff.value}/v+g+diag"] = lambda fused=fused: call_times(fused, x, calls)
        if hasattr(term, "max_step"):
            tasks[f"{eff.value}/max_step"] = lambda term=term: call_times(lambda xc: term.max_step(xc, step),
                                                                          x, calls)
            # as the solver does it: the gradient at x, then the step bound from the same x
            tasks[f"{eff.value}/v+g,max_step"] = lambda term=term: call_times(
                lambda xc: (term.value_and_grad(xc), term.max_step(xc, step)), x, calls)
        tasks[f"{eff.value}/without"] = lambda without=without: iteration_times(without, x, settings,
                                                                                per_round)
    res = run_interleaved(tasks, args.rounds)
    (bare, bare_min), (ms_it, ms_it_min) = res["spring"], res["iteration"]
    effects = {}
    for eff in EFFECTS:
        term = model.term(eff.value)
        row: dict = {}
        row["ms_value_grad"], row["ms_value_grad_min"] = res[f"{eff.value}/v+g"]
        if f"{eff.value}/v+g+diag" in res:
            row["ms_value_grad_diag"], row["ms_value_grad_diag_min"] = res[f"{eff.value}/v+g+diag"]
        if f"{eff.value}/max_step" in res:
            row["ms_max_step"], row["ms_max_step_min"] = res[f"{eff.value}/max_step"]
            (row["ms_value_grad_then_max_step"],
             row["ms_value_grad_then_max_step_min"]) = res[f"{eff.value}/v+g,max_step"]
            row["max_step"] = float(term.max_step(x, step))
        row["ms_per_iteration_without"], row["ms_per_iteration_without_min"] = res[f"{eff.value}/without"]
        row["ms_saved_when_left_out"] = ms_it - row["ms_per_iteration_without"]
        row["ms_saved_when_left_out_min"] = ms_it_min - row["ms_per_iteration_without_min"]
        effects[eff.value] = row
    its_k, its_k_min = res["iteration_k"]
    its_f, its_f_min = res["iteration_fresh"]

    return {
        "vertices": mesh.num_vertices,
        "target_vertices": target,
        "edge_length_m": h,
        "springs": int(stretch.edges.shape[0]),
        "seam_pairs": int(mesh.seam_pairs.shape[0]),
        "vertices_within_1cm_of_body": near,
        "ms_per_iteration": ms_it,
        "ms_per_iteration_min": ms_it_min,
        "ms_bare_spring": bare,
        "ms_bare_spring_min": bare_min,
        "ratio_iteration_to_spring": ms_it / bare,
        "ratio_iteration_to_spring_min": ms_it_min / bare_min,
        "ms_per_iteration_after_restart": its_f,
        "ms_per_iteration_after_restart_min": its_f_min,
        "ratio_after_restart_to_spring": its_f / bare,
        "diagonal_interval": args.diagonal_interval,
        "ms_per_iteration_diagonal_interval": its_k,
        "ms_per_iteration_diagonal_interval_min": its_k_min,
        "effects": effects,
    }


def print_table(rows: list[dict]) -> None:
    """Print the per-size table and the per-effect table."""
    k = rows[0]["diagonal_interval"] if rows else 1
    print(f"\n{'vertices':>9} {'ms/iter':>8} {'(min)':>7} {'ms spring':>9} {'(min)':>7} {'ratio':>6} "
          f"{'(min)':>6} {f'ms/iter diag/{k}':>14} {'(min)':>7} {'ratio':>6} {'after restart':>13} "
          f"{'ratio':>6}")
    for r in rows:
        print(f"{r['vertices']:>9d} {r['ms_per_iteration']:8.2f} {r['ms_per_iteration_min']:7.2f} "
              f"{r['ms_bare_spring']:9.3f} {r['ms_bare_spring_min']:7.3f} "
              f"{r['ratio_iteration_to_spring']:6.2f} {r['ratio_iteration_to_spring_min']:6.2f} "
              f"{r['ms_per_iteration_diagonal_interval']:14.2f} "
              f"{r['ms_per_iteration_diagonal_interval_min']:7.2f} "
              f"{r['ms_per_iteration_diagonal_interval'] / r['ms_bare_spring']:6.2f} "
              f"{r['ms_per_iteration_after_restart']:13.2f} {r['ratio_after_restart_to_spring']:6.2f}")
    print(f"\n{'vertices':>9} {'effect':>13} {'ms v+g':>8} {'ms v+g+diag':>11} {'ms max_step':>11} "
          f"{'ms/iter without':>15} {'saved':>7} {'(min)':>7}")
    for r in rows:
        for name, e in r["effects"].items():
            diag = e.get("ms_value_grad_diag", math.nan)
            ms = e.get("ms_value_grad_then_max_step", math.nan) - e["ms_value_grad"]
            print(f"{r['vertices']:>9d} {name:>13} {e['ms_value_grad']:8.3f} {diag:11.3f} {ms:11.3f} "
                  f"{e['ms_per_iteration_without']:15.2f} {e['ms_saved_when_left_out']:7.2f} "
                  f"{e['ms_saved_when_left_out_min']:7.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", default=None, help="write the results to this JSON file")
    ap.add_argument("--sizes", type=int, nargs="+", default=list(DEFAULT_SIZES), help="target vertex counts")
    ap.add_argument("--garment", default="tshirt", help="library garment to mesh")
    ap.add_argument("--body-size", default="12", help="size-chart body (garment drafted for it)")
    ap.add_argument("--voxel-mm", type=float, default=2.5, help="SDF voxel size in mm")
    ap.add_argument("--sdf-dtype", choices=("float32", "float64"), default="float32",
                    help="storage dtype of the SDF (positions stay float64)")
    ap.add_argument("--threads", type=int, default=2, help="torch.set_num_threads")
    ap.add_argument("--warmup", type=int, default=200, help="GD iterations before timing (realistic state)")
    ap.add_argument("--iterations", type=int, default=60,
                    help="timed solver iterations per model (all rounds)")
    ap.add_argument("--calls", type=int, default=60,
                    help="timed calls per single-term measurement (all rounds)")
    ap.add_argument("--rounds", type=int, default=6, help="rounds the measurements are interleaved in")
    ap.add_argument("--diagonal-interval", type=int, default=4,
                    help="also time iterations with the Hessian diagonal recomputed only every this many "
                         "iterations")
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (the mesh, the SDF and the solve)")
    ap.add_argument("--sweep", action="store_true",
                    help="also time the iteration at about 30K vertices with each SWEEP configuration (and "
                         "on a GPU the elastic terms replayed from a CUDA graph)")
    ap.add_argument("--parts", action="store_true",
                    help="also time each part of an iteration at about 30K vertices (see parts())")
    ap.add_argument("--profile", type=int, default=0, metavar="N",
                    help="also print torch.profiler's table of N solver iterations at about 30K vertices")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    watch = MachineWatch()

    body = Body.from_size(args.body_size)
    pattern = draft(args.garment, chart_row(args.body_size))
    sdf_dtype = getattr(torch, args.sdf_dtype)
    sdf = BodySDF.cached(body.vertices, body.faces, SDFSettings(voxel_size=args.voxel_mm * 1e-3),
                         dtype=sdf_dtype, device=device)
    rows = []
    for target in args.sizes:
        t0 = time.perf_counter()
        rows.append(bench_size(target, args, pattern, sdf))
        print(f"size {target}: {rows[-1]['vertices']} vertices, {rows[-1]['ms_per_iteration']:.2f} "
              f"ms/iteration ({time.perf_counter() - t0:.1f} s)", flush=True)
    print_table(rows)
    r30 = min(rows, key=lambda r: abs(r["vertices"] - 30_000))
    print(f"\nat {r30['vertices']} vertices: {r30['ms_per_iteration']:.2f} ms/iteration "
          f"(target <= {TARGET_MS_30K} ms), {r30['ratio_iteration_to_spring']:.2f}x the bare spring "
          f"evaluation (target <= {TARGET_RATIO}x); after a restart "
          f"{r30['ms_per_iteration_after_restart']:.2f} ms/iteration, "
          f"{r30['ratio_after_restart_to_spring']:.2f}x")
    machine = watch.finish()
    print(MachineWatch.describe(machine))
    out = {
        "threads": args.threads,
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor(),
        "garment": args.garment,
        "body_size": args.body_size,
        "voxel_mm": args.voxel_mm,
        "sdf_dtype": args.sdf_dtype,
        "warmup_iterations": args.warmup,
        "timed_iterations": args.iterations,
        "calls": args.calls,
        "torch": torch.__version__,
        "machine": machine,
        "targets": {"vertices": 30_000, "ms_per_iteration": TARGET_MS_30K,
                    "ratio_to_bare_spring": TARGET_RATIO},
        "sizes": rows,
    }
    if args.sweep:
        out["sweep"] = sweep(args, pattern, sdf, r30["target_vertices"])
    if args.parts:
        out["parts"] = parts(args, pattern, sdf, r30["target_vertices"])
    if args.json:
        with atomic_open(args.json, "w") as f:
            json.dump(out, f, indent=2)
    if args.profile > 0:
        profile_iterations(args, pattern, sdf, r30["target_vertices"])


def settled_state(args: argparse.Namespace, pattern: SewingPattern, sdf: BodySDF,
                  target: int) -> tuple[GarmentMesh, SimModel, torch.Tensor]:
    """``(mesh, model, x)``: the garment meshed at about ``target`` vertices, its full scene
    (:data:`EFFECTS`) and its state after ``--warmup`` GD-Chebyshev iterations from the placed panels (as
    :func:`bench_size`)."""
    mesh, _ = mesh_with_vertices(pattern, target, torch.float64)
    mesh = mesh.to(sdf.device)
    model = Scene(mesh, body_sdf=sdf, effects=set(EFFECTS)).build()
    x = model.project_feasible(mesh.x.detach())
    x, _ = solve(model, x, SolveSettings(rtol=0.0, atol=0.0), solver="gd-chebyshev",
                 max_iterations=max(args.warmup, 1))
    return mesh, model, x


def profile_iterations(args: argparse.Namespace, pattern: SewingPattern, sdf: BodySDF, target: int) -> None:
    """Print torch.profiler's table (top operators by self time, CPU and CUDA) of ``--profile`` solver
    iterations at about ``target`` vertices, after the warm-up; where the iteration's time goes."""
    from torch.profiler import ProfilerActivity, profile

    mesh, model, x = settled_state(args, pattern, sdf, target)
    settings = SolveSettings(rtol=0.0, atol=0.0)
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if sdf.device.type == "cuda" else [])
    with profile(activities=activities) as prof:
        solve(model, x, settings, solver="gd-chebyshev", max_iterations=args.profile)
        sync(sdf.device)
    key = "self_cuda_time_total" if sdf.device.type == "cuda" else "self_cpu_time_total"
    table = prof.key_averages()
    print(f"\nprofile of {args.profile} iterations at {mesh.num_vertices} vertices on {sdf.device}, "
          f"by {key}:")
    print(table.table(sort_by=key, row_limit=25, max_name_column_width=60))
    if sdf.device.type == "cuda":
        print(table.table(sort_by="self_cpu_time_total", row_limit=25, max_name_column_width=60))


SWEEP = {
    # name: (settings changed from SolveSettings(rtol=0, atol=0), whether the barrier samples only the
    # vertices that may be within its range (its default) or every vertex)
    "default": ({}, True),
    "barrier_every_vertex": ({}, False),
    "preconditioner_every_4": ({"diagonal_interval": 4}, True),
    "no_seam_blocks": ({"seam_blocks": False}, True),
    "scalar_jacobi": ({"preconditioner": Preconditioner.SCALAR}, True),
    "every_vertex+every_4+no_seam_blocks": ({"diagonal_interval": 4, "seam_blocks": False}, False),
}
"""The ``--sweep`` configurations: each switches settings that exist, on the same state."""


def sweep(args: argparse.Namespace, pattern: SewingPattern, sdf: BodySDF, target: int) -> dict:
    """What each part of an iteration costs on this device: the median and minimum ms per iteration of each
    :data:`SWEEP` configuration from the same state (interleaved rounds), and on a GPU the elastic terms'
    ``value_and_grad`` (stretch, sew, bend, gravity) eager against a replay of it captured in a CUDA graph
    (what graph capture of the static-shape terms would save)."""
    mesh, model, x = settled_state(args, pattern, sdf, target)
    every_vertex = Scene(mesh, body_sdf=sdf, effects=set(EFFECTS)).build()  # the same scene, its barrier
    every_vertex.term(Effect.BODY_BARRIER.value).lazy = False  # sampling every vertex (BodyBarrier(lazy=))
    models = {True: model, False: every_vertex}
    base = SolveSettings(rtol=0.0, atol=0.0)
    per_round = max(1, args.iterations // args.rounds)

    def task(changes: dict, lazy: bool) -> Callable[[], list[float]]:
        return lambda: iteration_times(models[lazy], x, replace(base, **changes), per_round)

    res = run_interleaved({name: task(*cfg) for name, cfg in SWEEP.items()}, args.rounds)
    out: dict = {"vertices": mesh.num_vertices,
                 "ms_per_iteration": {k: v[0] for k, v in res.items()},
                 "ms_per_iteration_min": {k: v[1] for k, v in res.items()}}
    if x.device.type == "cuda":
        elastic = Scene(mesh, effects={Effect.STRETCH, Effect.SEW, Effect.BEND, Effect.GRAVITY}).build()
        xs = x.clone()
        out["elastic_value_grad_eager_ms"] = 1e3 * statistics.median(
            call_times(lambda xc: elastic.value_and_grad(xs), xs, args.calls))
        side = torch.cuda.Stream(x.device)
        side.wait_stream(torch.cuda.current_stream(x.device))
        with torch.cuda.stream(side):
            for _ in range(3):  # warm-up on a side stream, as graph capture asks
                elastic.value_and_grad(xs)
        torch.cuda.current_stream(x.device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            _, g_graph = elastic.value_and_grad(xs)
        out["elastic_value_grad_graph_ms"] = 1e3 * statistics.median(
            call_times(lambda xc: graph.replay(), xs, args.calls))
        xs.add_(1e-6)
        graph.replay()
        out["graph_matches_eager"] = bool(torch.allclose(g_graph, elastic.value_and_grad(xs)[1], rtol=1e-9,
                                                         atol=1e-12))
    print(f"\nsweep at {mesh.num_vertices} vertices on {x.device} (ms per iteration, median / min):")
    for k in SWEEP:
        print(f"  {k:>38} {out['ms_per_iteration'][k]:7.2f} {out['ms_per_iteration_min'][k]:7.2f}")
    if "elastic_value_grad_graph_ms" in out:
        print(f"  elastic terms' value_and_grad: eager {out['elastic_value_grad_eager_ms']:.3f} ms, CUDA "
              f"graph replay {out['elastic_value_grad_graph_ms']:.3f} ms (same gradient: "
              f"{out['graph_matches_eager']})")
    return out


def parts(args: argparse.Namespace, pattern: SewingPattern, sdf: BodySDF, target: int) -> dict:
    """The median and minimum ms of each part of a GD-Chebyshev iteration at about ``target`` vertices, each
    alone, called as the solver calls it on one settled state (interleaved rounds; a fresh copy of the
    positions per call, so that no cache hits): ``value_and_grad`` of the whole model;
    ``value_grad_hessian_diagonal`` with the elastic diagonal fresh (a full evaluation: the first iterations
    every ``elastic_diagonal_interval``, every iteration after a restart) and reused (volatile rows only); the
    preconditioner's full ``rebuild`` and its ``update`` of the volatile rows; ``apply_inverse``; the row
    clamp; the step bound (``max_step`` after an untimed evaluation at the same positions, whose SDF query it
    reuses, as in the solver); and the bare spring pass. The solver's own vector updates and energy checks
    are not among the parts."""
    mesh, model, x = settled_state(args, pattern, sdf, target)
    settings = SolveSettings(rtol=0.0, atol=0.0)
    stretch = model.term(Effect.STRETCH.value)
    _, g, h = model.value_grad_hessian_diagonal(x)
    rows = model.last_volatile_rows
    pre = JacobiState(settings, seam_pairs(model) if settings.seam_blocks else None)
    pre.rebuild(h, rows)
    step = apply_inverse(pre.inverse, g).mul_(-settings.step)
    calls = max(1, args.calls // args.rounds)
    tasks = {
        "bare_spring": lambda: call_times(stretch.value_and_grad, x, calls),
        "value_grad": lambda: call_times(model.value_and_grad, x, calls),
        "value_grad_diag_fresh": lambda: call_times(model.value_grad_hessian_diagonal, x, calls),
        "value_grad_diag_reused": lambda: call_times(
            lambda xc: model.value_grad_hessian_diagonal(xc, reuse_elastic=True), x, calls),
        "preconditioner_rebuild": lambda: call_times(lambda xc: pre.rebuild(h, rows), x, calls),
        "preconditioner_update": lambda: call_times(lambda xc: pre.update(h, rows), x, calls),
        "apply_inverse": lambda: call_times(lambda xc: apply_inverse(pre.inverse, g), x, calls),
        "clamp_rows": lambda: call_times(
            lambda xc: clamp_displacement_(step.clone(), settings.max_displacement), x, calls),
        "max_step": lambda: call_times(lambda xc: model.max_step(xc, step), x, calls,
                                       before=model.value_and_grad),
    }
    res = run_interleaved(tasks, args.rounds)
    out: dict = {"vertices": mesh.num_vertices, "ms": {k: v[0] for k, v in res.items()},
                 "ms_min": {k: v[1] for k, v in res.items()}}
    ms = out["ms"]
    bare = ms["bare_spring"]
    print(f"\nparts of an iteration at {mesh.num_vertices} vertices on {x.device}, {torch.get_num_threads()} "
          f"threads (median / min ms, median / bare spring pass):")
    for k in tasks:
        print(f"  {k:>24} {ms[k]:8.2f} {out['ms_min'][k]:8.2f} {ms[k] / bare:7.2f}x")
    return out


if __name__ == "__main__":
    main()
