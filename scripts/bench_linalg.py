"""Benchmark of the sparse direct solvers (:class:`~torchgarment.linalg.SparseBackend`) on the project's own
simulation Hessians: factorization and one solve, median of ``--repeats`` runs, per backend and mesh size.

Usage:
    python scripts/bench_linalg.py [--json FILE] [--vertices 5000 15000 30000] [--garment sheath_dress]
        [--size 12] [--threads 2] [--repeats 3] [--backends superlu pardiso cholespy]
        [--state rest|draped] [--pcg] [--device cpu|cuda]

The garment is meshed at the edge length that gives about each ``--vertices`` count; the matrix is the
unprojected Hessian ``model.hessian_blocks(x, project_psd=False)`` (stretch, sew, bend, gravity) at the mesh's
own positions, assembled by :class:`~torchgarment.linalg.CSRAssembler`, plus the Newton solver's first
regularization ``1e-8 * mean|diag H| * I`` (the free garment's rigid motions are its null space). Backends
that are not installed are skipped. Each backend is also checked for determinism: two factorizations and
solves of the same matrix must give bit-identical results (``"deterministic"``), and its solution is compared
with SuperLU's (``"max_rel_diff_vs_superlu"``).

``--state draped``: a Newton system as the drape meets it instead. The garment placed on the chart body
``--size`` (its SDF at 2.5 mm), 200 GD-Chebyshev iterations, then the projected Hessian of the whole scene
(stretch, sew, bend, gravity, body barrier) plus the same regularization, and the right-hand side ``-g`` (a
Newton step). ``--pcg`` adds conjugate gradients preconditioned by the 3x3 block Jacobi inverse
(:func:`~torchgarment.sim.solvers.jacobi_pcg_solve`, Newton's ``"jacobi-pcg"`` linear solver with the seam
pairs' 6x6 blocks, the CSR product on ``--device``) to relative residuals 1e-2, 1e-4 and 1e-6: iterations
and seconds (the second of two runs). The direct backends always factorize on the CPU.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", default=None, help="write the results to this JSON file")
    ap.add_argument("--vertices", type=int, nargs="+", default=[5000, 15000, 30000])
    ap.add_argument("--garment", default="sheath_dress")
    ap.add_argument("--size", default="12")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--backends", nargs="+", default=["superlu", "pardiso", "cholespy", "cholmod"])
    ap.add_argument("--state", choices=["rest", "draped"], default="rest",
                    help="the Hessian at the flat placed panels (rest) or a draped Newton system (see above)")
    ap.add_argument("--pcg", action="store_true", help="also block-Jacobi PCG on --device (torch tensors)")
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N: where --pcg runs")
    args = ap.parse_args()
    # MKL (pardiso) reads its thread count at load time
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(args.threads)

    import numpy as np
    import torch

    from torchgarment.benchmarking import machine_record
    from torchgarment.body.size_chart import chart_row
    from torchgarment.errors import InputError
    from torchgarment.linalg import CSRAssembler, SparseBackend, factorize
    from torchgarment.options import resolve_device
    from torchgarment.pattern.library import draft
    from torchgarment.pattern.meshing import mesh_pattern
    from torchgarment.sim.scene import Effect, Scene
    from torchgarment.sim.solvers.chebyshev import seam_pairs

    device = resolve_device(args.device)

    torch.set_num_threads(args.threads)
    pattern = draft(args.garment, chart_row(args.size))
    rows = []
    for target in args.vertices:
        edge = 0.05
        for _ in range(3):
            edge *= math.sqrt(mesh_pattern(pattern, edge).num_vertices / target)
        mesh = mesh_pattern(pattern, edge, dtype=torch.float64)
        if args.state == "rest":
            model = Scene(mesh, effects={Effect.STRETCH, Effect.SEW, Effect.BEND, Effect.GRAVITY}).build()
            h = CSRAssembler(model.num_vertices).assemble(model.hessian_blocks(mesh.x, project_psd=False))
            rhs = np.random.default_rng(0).standard_normal(h.shape[0])
        else:
            model, h, rhs = draped_system(mesh, args.size)
        shift = 1e-8 * float(np.abs(h.diagonal()).mean())
        print(f"{args.garment} size {args.size}: {mesh.num_vertices} vertices, {h.shape[0]} dofs, "
              f"{h.nnz} nonzeros")
        reference = None
        for name in args.backends:
            backend = SparseBackend.resolve(name)
            fact_s, solve_s, results = [], [], []
            try:
                for _ in range(args.repeats):
                    t0 = time.perf_counter()
                    fact = factorize(h, backend=backend, shift=shift, what="simulation Hessian")
                    t1 = time.perf_counter()
                    y = fact.solve(rhs)
                    t2 = time.perf_counter()
                    fact_s.append(t1 - t0)
                    solve_s.append(t2 - t1)
                    results.append(y)
            except InputError as exc:
                print(f"  {backend.value}: skipped ({exc})")
                continue
            if reference is None:
                reference = results[0]
            residual = np.linalg.norm(h @ results[0] + shift * results[0] - rhs) / np.linalg.norm(rhs)
            row = {"vertices": mesh.num_vertices, "dofs": h.shape[0], "nnz": int(h.nnz),
                   "backend": backend.value,
                   "factorize_s": statistics.median(fact_s), "solve_s": statistics.median(solve_s),
                   "factorize_all_s": fact_s, "solve_all_s": solve_s, "relative_residual": float(residual),
                   "deterministic": all(np.array_equal(results[0], r) for r in results[1:]),
                   "max_rel_diff_vs_superlu": float(np.abs(results[0] - reference).max()
                                                    / np.abs(reference).max())}
            rows.append(row)
            print(f"  {backend.value:9s} factorize {row['factorize_s']:7.3f} s  "
                  f"solve {row['solve_s']:6.3f} s  "
                  f"residual {residual:.1e}  deterministic {row['deterministic']}  "
                  f"vs superlu {row['max_rel_diff_vs_superlu']:.1e}")
        if args.pcg:
            row = pcg_row(h, shift, rhs, device, seam_pairs(model))
            row.update(vertices=mesh.num_vertices, dofs=h.shape[0], nnz=int(h.nnz))
            rows.append(row)
            print(f"  pcg ({row['device']}, 3x3 block Jacobi): " + ", ".join(
                f"rtol {t}: {r['iterations']} iterations {r['seconds']:.3f} s"
                for t, r in row["rtol"].items()))
    machine = machine_record()
    load = machine["load_average"]
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, {args.threads} threads")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"garment": args.garment, "size": args.size, "threads": args.threads,
                       "repeats": args.repeats, "machine": machine, "rows": rows}, f, indent=1)


def draped_system(mesh, size: str):  # noqa: ANN001, ANN201 (imports are local to main)
    """``(model, H, rhs)``: the whole scene of ``mesh`` on chart body ``size``, its projected Hessian (scipy
    CSR) after 200 GD-Chebyshev iterations from the placed panels, and ``-g`` there (flattened)."""
    import torch

    from torchgarment.body import Body
    from torchgarment.linalg import CSRAssembler
    from torchgarment.sdf import BodySDF, SDFSettings
    from torchgarment.sim.scene import Scene
    from torchgarment.sim.solvers import SolveSettings, solve

    body = Body.from_size(size)
    sdf = BodySDF.cached(body.vertices, body.faces, SDFSettings(voxel_size=2.5e-3), dtype=torch.float32)
    model = Scene(mesh, body_sdf=sdf).build()
    x = model.project_feasible(mesh.x.detach())
    x, _ = solve(model, x, SolveSettings(rtol=0.0, atol=0.0), solver="gd-chebyshev", max_iterations=200)
    _, g = model.value_and_grad(x)
    h = CSRAssembler(model.num_vertices).assemble(model.hessian_blocks(x, project_psd=True))
    return model, h, -g.detach().cpu().numpy().reshape(-1)


def pcg_row(h, shift: float, rhs, device, seams) -> dict:  # noqa: ANN001 (imports are local to main)
    """:func:`~torchgarment.sim.solvers.jacobi_pcg_solve` (Newton's ``"jacobi-pcg"`` linear solver, with the
    model's seam blocks ``seams``) of ``(h + shift I) y = rhs`` on ``device`` to three relative residuals;
    each timed on its second run (the first pays for kernel loading), the copy of the matrix to the device and
    the block inverses included."""
    import time

    import numpy as np
    import scipy.sparse
    import torch

    from torchgarment.sim.solvers import jacobi_pcg_solve

    a = (h + shift * scipy.sparse.identity(h.shape[0], format="csr")).tocsr()

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    out: dict = {"backend": "jacobi-pcg", "device": str(device), "seam_blocks": seams is not None, "rtol": {}}
    for tol in (1e-2, 1e-4, 1e-6):
        for _ in range(2):
            sync()
            t0 = time.perf_counter()
            y, its = jacobi_pcg_solve(a, rhs, device, tol, 20000, seams=seams)
            sync()
            seconds = time.perf_counter() - t0
        residual = float(np.linalg.norm(a @ y - rhs) / np.linalg.norm(rhs))
        out["rtol"][f"{tol:g}"] = {"iterations": its, "seconds": seconds, "relative_residual": residual}
    return out


if __name__ == "__main__":
    main()
