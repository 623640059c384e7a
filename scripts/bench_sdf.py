"""Benchmark of BodySDF: build time, memory, sampling error against exact libigl distances, gradient norms.

Usage:
    python scripts/bench_sdf.py [--mesh PATH] [--voxels 5 2.5 1.25] [--runs 3] [--points 50000] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from torchgarment.io.atomic import atomic_open
from torchgarment.sdf import BodySDF, SDFSettings, SignType, exact_signed_distance

DEFAULT_MESH = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "garmentcode" / "bodies" / "mean_female.obj"


def bench_one(v: np.ndarray, f: np.ndarray, voxel_mm: float, runs: int, points: int, seed: int = 0) -> dict:
    """Build the SDF ``runs`` times at ``voxel_mm`` and measure it; returns one table row."""
    settings = SDFSettings(voxel_size=voxel_mm * 1e-3)
    times = []
    sdf = None
    for _ in range(runs):
        t0 = time.perf_counter()
        sdf = BodySDF.from_mesh(v, f, settings)
        times.append(time.perf_counter() - t0)
    rng = np.random.default_rng(seed)
    pts = v[rng.integers(0, len(v), points)] + rng.uniform(-sdf.band, sdf.band, size=(points, 3))
    exact = exact_signed_distance(pts, v, f, SignType.WINDING_NUMBER)
    x = torch.as_tensor(pts)
    t0 = time.perf_counter()
    phi, grad = sdf.value_and_gradient(x)
    t_query = time.perf_counter() - t0
    band = np.abs(exact) <= sdf.band
    err_mm = np.abs(phi.numpy() - exact)[band] * 1e3
    gn = grad.norm(dim=-1).numpy()[band]
    dense_nodes = int(np.prod([n * sdf.brick + 1 for n in sdf.shape]))
    return {
        "voxel_mm": voxel_mm,
        "band_mm": sdf.band * 1e3,
        "build_s_median": statistics.median(times),
        "build_s_all": times,
        "bricks": sdf.num_bricks,
        "exact_nodes": sdf.num_exact,
        "bytes_float64": sdf.nbytes(),
        "bytes_float32": sdf.to(dtype=torch.float32).nbytes(),
        "dense_fine_float32_bytes": dense_nodes * 4,
        "points_in_band": int(band.sum()),
        "err_mm_mean": float(err_mm.mean()),
        "err_mm_p99": float(np.percentile(err_mm, 99)),
        "err_mm_max": float(err_mm.max()),
        "grad_norm_p1": float(np.percentile(gn, 1)),
        "grad_norm_median": float(np.median(gn)),
        "grad_norm_p99": float(np.percentile(gn, 99)),
        "grad_norm_within_5pct": float((np.abs(gn - 1) < 0.05).mean()),
        "query_us_per_point": t_query / points * 1e6,
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", type=Path, default=DEFAULT_MESH)
    ap.add_argument("--voxels", type=float, nargs="+", default=[5.0, 2.5, 1.25], help="voxel sizes in mm")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--points", type=int, default=50_000)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)

    m = trimesh.load(args.mesh, process=False, force="mesh")
    v, f = np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)
    print(f"mesh {args.mesh.name}: {len(v)} vertices, {len(f)} faces, torch threads {torch.get_num_threads()}")
    rows = []
    head = f"{'voxel':>6} {'band':>5} {'build s':>8} {'MB f64':>7} {'MB f32':>7} {'dense MB':>8} {'bricks':>7} {'exact':>9} " \
           f"{'err mean':>8} {'p99':>6} {'max':>6} {'|g| p1':>6} {'med':>6} {'p99':>6} {'us/pt':>6}"
    print(head)
    for vox in args.voxels:
        r = bench_one(v, f, vox, args.runs, args.points)
        rows.append(r)
        print(
            f"{r['voxel_mm']:>6.2f} {r['band_mm']:>5.1f} {r['build_s_median']:>8.2f} {r['bytes_float64'] / 1e6:>7.1f} "
            f"{r['bytes_float32'] / 1e6:>7.1f} {r['dense_fine_float32_bytes'] / 1e6:>8.1f} {r['bricks']:>7d} "
            f"{r['exact_nodes']:>9d} {r['err_mm_mean']:>8.4f} {r['err_mm_p99']:>6.3f} {r['err_mm_max']:>6.3f} "
            f"{r['grad_norm_p1']:>6.3f} {r['grad_norm_median']:>6.4f} {r['grad_norm_p99']:>6.3f} {r['query_us_per_point']:>6.2f}",
            flush=True,
        )
    print("err: |sampled - exact (igl, exact winding-number sign)| in mm at random points with |phi| <= band")
    if args.json is not None:
        with atomic_open(args.json) as fh:
            json.dump({"mesh": str(args.mesh), "rows": rows}, fh, indent=2)


if __name__ == "__main__":
    main()
