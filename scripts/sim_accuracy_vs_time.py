"""What simulation accuracy costs in time: solver residual vs wall time, and SDF resolution vs collision
accuracy.

Usage:
    python scripts/sim_accuracy_vs_time.py [--garment straight_skirt] [--size 12] [--edge-length 0.02]
        [--voxels-mm 1 1.75 2.5 5 10] [--gd-iterations 2000] [--newton-iterations 150] [--threads 2]
        [--json FILE] [--png FILE] [--log-dir logs/sim_accuracy_vs_time]

Part 1 (solvers): the library garment is drafted for chart size ``--size``, placed and sewn on that body
(:func:`torchgarment.sim.drape.drape` with a settle budget of 0 iterations), and the settle problem (stretch,
sew, bend, gravity, body barrier on the 2.5 mm SDF) is then solved from that same sewn state by GD-Chebyshev
and by projected Newton, each with a zero tolerance and a fixed iteration budget. Every iteration's residual
(the force 2-norm in newtons, relative to the garment's weight) is recorded against the wall time since the
solve began.

Part 2 (SDF resolution): for each voxel size the body SDF is built afresh (no disk cache; build seconds
timed), the same settle problem is solved with Newton to the drape tolerance (0.1 % of the weight; solve
seconds timed), and the result is checked against the exact signed distance to the body mesh (libigl, fast
winding number sign): the smallest exact clearance in mm, the count of vertices truly inside the body, and the
largest |SDF - exact distance| over the garment's vertices in mm, overall (far vertices sample the coarse far
field) and over the vertices within 1 cm of the body (where collisions are decided).

Outputs: a table on stdout, ``--json`` (everything), ``--png`` (two panels: residual vs time; SDF error and
clearance vs voxel size with build/solve seconds) and TensorBoard scalars under ``--log-dir/<time>``
(``residual/<solver>`` by iteration with the wall time as TensorBoard's walltime, ``residual_vs_ms/<solver>``
by elapsed milliseconds, ``sdf/*`` by voxel size in tenths of a millimetre).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:
    from torchgarment.body import Body
    from torchgarment.sdf import BodySDF
    from torchgarment.sim.scene import Material, SimModel
    from torchgarment.sim.solvers import SolveInfo
    from torchgarment.structures.garment_mesh import GarmentMesh


def _settle_problem(garment: str, size: str, edge_length: float
                    ) -> tuple[Body, GarmentMesh, torch.Tensor, Material, float, float]:
    """(body, mesh, sewn x, settle Material, settle tolerance in N, weight in N)."""
    from dataclasses import replace

    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft
    from torchgarment.sim.drape import DrapeSettings, drape

    body = Body.from_size(size)
    pattern = draft(garment, chart_row(size))
    settings = DrapeSettings(edge_length=edge_length, voxel_size=0.0025, max_iterations=0)
    res = drape(pattern, body, settings=settings)
    mat = replace(settings.material)
    if settings.final_sew_stiffness is not None:
        mat.sew_stiffness = settings.final_sew_stiffness
    if settings.barrier_mu is not None:
        mat.barrier_mu = settings.barrier_mu
    weight = float(res.metrics["weight_n"])
    return body, res.mesh, res.x.detach(), mat, settings.atol_weight * weight, weight


def _model(mesh: GarmentMesh, sdf: BodySDF, material: Material) -> SimModel:
    from torchgarment.sim.scene import Effect, Scene

    effects = {Effect.STRETCH, Effect.SEW, Effect.BEND, Effect.GRAVITY, Effect.BODY_BARRIER}
    return Scene(mesh, body_sdf=sdf, effects=effects, material=material).build()


def _timed_solve(model: SimModel, x0: torch.Tensor, solver: str, iterations: int, atol: float
                 ) -> tuple[torch.Tensor, SolveInfo, list[tuple[float, float]]]:
    """Solve and record (seconds since start, residual) after every iteration."""
    from torchgarment.sim.solvers import SolveSettings, solve

    x0 = model.project_feasible(x0)
    g0 = float(torch.linalg.vector_norm(model.value_and_grad(x0)[1]))
    trace = [(0.0, g0)]
    t0 = time.perf_counter()

    def cb(k: int, x: torch.Tensor, gn: float, e: float) -> bool:  # noqa: ARG001
        trace.append((time.perf_counter() - t0, gn))
        return False

    x, info = solve(model, x0,
                    SolveSettings(rtol=0.0, atol=atol, max_iterations=iterations, max_displacement=0.01),
                    solver=solver, callback=cb)
    return x, info, trace


def _exact_distance(points: np.ndarray, body_v: np.ndarray, body_f: np.ndarray) -> np.ndarray:
    import igl

    d, _, _ = igl.signed_distance(points, body_v, body_f, igl.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER)[:3]
    return np.asarray(d)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--garment", default="straight_skirt")
    ap.add_argument("--size", default="12")
    ap.add_argument("--edge-length", type=float, default=0.02, help="triangle edge length in metres")
    ap.add_argument("--voxels-mm", type=float, nargs="+", default=[1.0, 1.75, 2.5, 5.0, 10.0])
    ap.add_argument("--gd-iterations", type=int, default=2000)
    ap.add_argument("--newton-iterations", type=int, default=150)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--png", type=Path, default=Path("sim_accuracy_vs_time.png"))
    ap.add_argument("--log-dir", type=Path, default=Path("logs") / "sim_accuracy_vs_time")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    from torch.utils.tensorboard import SummaryWriter

    from torchgarment.io.atomic import atomic_path
    from torchgarment.sdf import BodySDF, SDFSampling, SDFSettings
    from torchgarment.sim.drape import max_seam_gap

    run_dir = args.log_dir / time.strftime("%Y%m%d-%H%M%S")
    writer = SummaryWriter(str(run_dir))
    print(f"sewing {args.garment} on size {args.size} at {args.edge_length} m edges ...", flush=True)
    body, mesh, x_sewn, mat, tol, weight = _settle_problem(args.garment, args.size, args.edge_length)
    bv, bf = body.vertices.detach().cpu().numpy(), body.faces.cpu().numpy()
    out: dict = {"garment": args.garment, "size": args.size, "vertices": mesh.num_vertices,
                 "weight_n": weight,
                 "tolerance_n": tol, "threads": args.threads, "solvers": {}, "sdf": []}

    # ------------------------------------------------------------------ part 1: residual vs time
    sdf25 = BodySDF.cached(body.vertices, body.faces, SDFSettings(voxel_size=0.0025)).with_sampling(
        SDFSampling.QUADRATIC)
    model = _model(mesh, sdf25, mat)
    print(f"{'solver':<14}{'iterations':>11}{'seconds':>9}{'residual/W':>12}{'time to 1e-3 W':>16}")
    for solver, iters in (("gd-chebyshev", args.gd_iterations), ("newton", args.newton_iterations)):
        _, info, trace = _timed_solve(model, x_sewn, solver, iters, atol=1e-3 * tol)
        t_tol = next((t for t, r in trace if r <= tol), math.nan)
        wall0 = time.time()
        for k, (t, r) in enumerate(trace):
            writer.add_scalar(f"residual/{solver}", r / weight, k, walltime=wall0 + t)
            writer.add_scalar(f"residual_vs_ms/{solver}", r / weight, int(round(1e3 * t)))
        out["solvers"][solver] = {"iterations": info.iterations, "seconds": trace[-1][0],
                                  "final_residual_n": trace[-1][1], "seconds_to_tolerance": t_tol,
                                  "trace": trace}
        print(f"{solver:<14}{info.iterations:>11d}{trace[-1][0]:>9.2f}{trace[-1][1] / weight:>12.2e}"
              f"{t_tol:>16.2f}", flush=True)

    # ------------------------------------------------------------------ part 2: SDF resolution
    print(f"\n{'voxel mm':>9}{'build s':>9}{'solve s':>9}{'iters':>6}{'conv':>6}{'min exact mm':>14}"
          f"{'inside':>7}{'max |err| mm':>14}{'near <1cm':>11}{'seam gap mm':>13}")
    for vmm in args.voxels_mm:
        t = time.perf_counter()
        sdf = BodySDF.from_mesh(body.vertices, body.faces, SDFSettings(voxel_size=vmm * 1e-3))
        build_s = time.perf_counter() - t
        sdf = sdf.with_sampling(SDFSampling.QUADRATIC)
        model = _model(mesh, sdf, mat)
        t = time.perf_counter()
        x, info, _ = _timed_solve(model, x_sewn, "newton", 150, atol=tol)
        solve_s = time.perf_counter() - t
        xn = x.detach().cpu().numpy()
        exact = _exact_distance(xn, bv, bf)
        with torch.no_grad():
            phi = sdf(x).detach().cpu().numpy()
        row = {"voxel_mm": vmm, "build_seconds": build_s, "solve_seconds": solve_s,
               "iterations": info.iterations,
               "converged": bool(info.converged), "min_exact_clearance_mm": 1e3 * float(exact.min()),
               "inside_vertices": int((exact < 0).sum()),
               "max_sdf_error_mm": 1e3 * float(np.abs(phi - exact).max()),
               "mean_sdf_error_mm": 1e3 * float(np.abs(phi - exact).mean()),
               # where collisions are decided: the vertices within 1 cm of the body (the rest sample the
               # coarse far field, whose error does not matter to a barrier that acts within dhat = 3 mm)
               "near_vertices": int((exact < 0.01).sum()),
               "max_sdf_error_near_mm": 1e3 * float(np.abs(phi - exact)[exact < 0.01].max(initial=0.0)),
               "max_seam_gap_mm": 1e3 * max_seam_gap(mesh, x), "sdf_mib": sdf.nbytes() / 2 ** 20}
        out["sdf"].append(row)
        step = int(round(vmm * 10))
        for key in ("build_seconds", "solve_seconds", "min_exact_clearance_mm", "max_sdf_error_mm",
                    "inside_vertices"):
            writer.add_scalar(f"sdf/{key}", row[key], step)
        print(f"{vmm:>9.2f}{build_s:>9.1f}{solve_s:>9.1f}{info.iterations:>6d}{str(row['converged']):>6}"
              f"{row['min_exact_clearance_mm']:>14.2f}{row['inside_vertices']:>7d}{row['max_sdf_error_mm']:>14.2f}"
              f"{row['max_sdf_error_near_mm']:>11.2f}"
              f"{row['max_seam_gap_mm']:>13.2f}", flush=True)
    writer.close()

    # ------------------------------------------------------------------ plot
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.5))
    for solver, d in out["solvers"].items():
        tr = np.asarray(d["trace"])
        a1.semilogy(tr[:, 0], tr[:, 1] / weight, label=f"{solver} ({d['iterations']} it)")
    a1.axhline(tol / weight, color="k", ls="--", lw=0.8, label="drape tolerance (1e-3 W)")
    a1.set_xlabel("wall time (s)")
    a1.set_ylabel("residual |f| / garment weight")
    a1.set_title(f"{args.garment}, size {args.size}, {mesh.num_vertices} vertices")
    a1.legend()
    rows = out["sdf"]
    vx = [r["voxel_mm"] for r in rows]
    a2.plot(vx, [r["max_sdf_error_mm"] for r in rows], "o-", label="max |SDF - exact| at garment (mm)")
    a2.plot(vx, [r["max_sdf_error_near_mm"] for r in rows], "o:", label="same, vertices within 1 cm (mm)")
    a2.plot(vx, [r["min_exact_clearance_mm"] for r in rows], "s-", label="min exact clearance (mm)")
    a2.axhline(0.0, color="k", lw=0.6)
    a2.set_xlabel("SDF voxel size (mm)")
    a2.set_ylabel("mm")
    a3 = a2.twinx()
    a3.plot(vx, [r["build_seconds"] for r in rows], "^--", color="tab:red", label="build (s)")
    a3.plot(vx, [r["solve_seconds"] for r in rows], "v--", color="tab:purple", label="solve (s)")
    a3.set_ylabel("seconds")
    h1, l1 = a2.get_legend_handles_labels()
    h2, l2 = a3.get_legend_handles_labels()
    a2.legend(h1 + h2, l1 + l2, fontsize=8)
    a2.set_title("SDF resolution: collision accuracy vs time")
    fig.tight_layout()
    args.png.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(args.png) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    print(f"\nwrote {args.png}; TensorBoard run {run_dir}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(args.json) as tmp:
            Path(tmp).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
