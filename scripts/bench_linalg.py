"""Benchmark of the sparse direct solvers (:class:`~torchgarment.linalg.SparseBackend`) on the project's own
simulation Hessians: factorization and one solve, median of ``--repeats`` runs, per backend and mesh size.

Usage:
    python scripts/bench_linalg.py [--json FILE] [--vertices 5000 15000 30000] [--garment sheath_dress]
        [--size 12] [--threads 2] [--repeats 3] [--backends superlu pardiso cholespy]

The garment is meshed at the edge length that gives about each ``--vertices`` count; the matrix is the
unprojected Hessian ``model.hessian_blocks(x, project_psd=False)`` (stretch, sew, bend, gravity) at the mesh's
own positions, assembled by :class:`~torchgarment.linalg.CSRAssembler`, plus the Newton solver's first
regularization ``1e-8 * mean|diag H| * I`` (the free garment's rigid motions are its null space). Backends
that are not installed are skipped. Each backend is also checked for determinism: two factorizations and
solves of the same matrix must give bit-identical results (``"deterministic"``), and its solution is compared
with SuperLU's (``"max_rel_diff_vs_superlu"``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
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
    ap.add_argument("--backends", nargs="+", default=["superlu", "pardiso", "cholespy"])
    args = ap.parse_args()
    # MKL (pardiso) reads its thread count at load time
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(args.threads)

    import numpy as np
    import torch

    from torchgarment.body.size_chart import chart_row
    from torchgarment.errors import InputError
    from torchgarment.linalg import CSRAssembler, SparseBackend, factorize
    from torchgarment.pattern.library import draft
    from torchgarment.pattern.meshing import mesh_pattern
    from torchgarment.sim.scene import Effect, Scene

    torch.set_num_threads(args.threads)
    pattern = draft(args.garment, chart_row(args.size))
    rows = []
    for target in args.vertices:
        edge = 0.05
        for _ in range(3):
            edge *= math.sqrt(mesh_pattern(pattern, edge).num_vertices / target)
        mesh = mesh_pattern(pattern, edge, dtype=torch.float64)
        model = Scene(mesh, effects={Effect.STRETCH, Effect.SEW, Effect.BEND, Effect.GRAVITY}).build()
        x = mesh.x
        h = CSRAssembler(model.num_vertices).assemble(model.hessian_blocks(x, project_psd=False))
        shift = 1e-8 * float(np.abs(h.diagonal()).mean())
        rhs = np.random.default_rng(0).standard_normal(h.shape[0])
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
    load = os.getloadavg()
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, {args.threads} threads")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"garment": args.garment, "size": args.size, "threads": args.threads,
                       "repeats": args.repeats, "load_average": load, "machine": platform.platform(),
                       "processor": platform.processor(), "cpus": os.cpu_count(), "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
