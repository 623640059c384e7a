"""Benchmark of BodySDF: build time, memory, sampling error against exact libigl distances, gradient norms.

Usage:
    python scripts/bench_sdf.py [--mesh PATH] [--voxels 5 2.5 1.25] [--runs 3] [--points 50000] [--json PATH]
    python scripts/bench_sdf.py --query [--mesh PATH] [--voxels 2.5] [--sdf PATH] [--threads 2] [--calls 50]
        [--json PATH]

``--query`` times sampling only: the median (and min) over ``--calls`` calls of ``value_and_gradient`` and of
``forward`` (value only, no autograd) at 5K, 30K and 100K points near the body surface (body vertices plus a
normal offset of 1.5 cm per axis), in random order and in mesh order (spatially coherent, like a garment's
vertices), in float32 and float64, with ``torch.set_num_threads(--threads)``.
The SDF comes from ``--sdf`` (a file written by ``BodySDF.save``) or from the disk cache (built on a miss).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
import trimesh

from torchgarment.io.atomic import atomic_open
from torchgarment.sdf import BodySDF, SDFSettings, SignType, exact_signed_distance

QUERY_SIZES = (5_000, 30_000, 100_000)

DEFAULT_MESH = (Path(__file__).resolve().parents[1].parent / "shared" / "data" / "garmentcode" / "bodies"
                / "mean_female.obj")


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


def _times_ms(fn: Callable[[], object], calls: int) -> tuple[float, float]:
    """(median, min) wall time of ``fn()`` in ms over ``calls`` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(calls):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3, min(times) * 1e3


def query_points(v: np.ndarray, n: int, order: str, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) points near the body: random vertices plus N(0, 1.5 cm) per axis, in random or mesh order."""
    idx = rng.integers(0, len(v), n)
    if order == "mesh":
        idx.sort()  # spatially coherent like a garment's vertex array
    return v[idx] + rng.normal(scale=0.015, size=(n, 3))


def bench_query(sdf: torch.nn.Module, v: np.ndarray, calls: int, seed: int = 0) -> list[dict]:
    """Median and min wall time (ms) of ``value_and_gradient`` and ``forward`` per dtype, order and size."""
    rng = np.random.default_rng(seed)
    rows = []
    for dtype in (torch.float32, torch.float64):
        s = sdf.to(dtype=dtype)
        for order in ("random", "mesh"):
            for n in QUERY_SIZES:
                x = torch.as_tensor(query_points(v, n, order, rng), dtype=dtype)
                with torch.no_grad():
                    vg_med, vg_min = _times_ms(lambda: s.value_and_gradient(x), calls)
                    f_med, f_min = _times_ms(lambda: s(x), calls)
                rows.append({"dtype": str(dtype).removeprefix("torch."), "order": order, "points": n,
                             "value_and_gradient_ms": vg_med, "value_and_gradient_min_ms": vg_min,
                             "forward_ms": f_med, "forward_min_ms": f_min})
    return rows


def print_query_table(rows: list[dict]) -> None:
    print(f"{'dtype':>8} {'order':>6} {'points':>7} {'v+g med ms':>10} {'v+g min':>8} {'fwd med ms':>10} "
          f"{'fwd min':>8} {'ns/pt':>6}")
    for r in rows:
        print(f"{r['dtype']:>8} {r['order']:>6} {r['points']:>7d} {r['value_and_gradient_ms']:>10.3f} "
              f"{r['value_and_gradient_min_ms']:>8.3f} {r['forward_ms']:>10.3f} {r['forward_min_ms']:>8.3f} "
              f"{r['value_and_gradient_ms'] / r['points'] * 1e6:>6.0f}")


def main_query(args: argparse.Namespace, v: np.ndarray, f: np.ndarray) -> None:
    torch.set_num_threads(args.threads)
    if args.sdf is not None:
        sdf = BodySDF.load(args.sdf)
        src = str(args.sdf)
    else:
        settings = SDFSettings(voxel_size=args.voxels[0] * 1e-3)
        t0 = time.perf_counter()
        sdf = BodySDF.cached(v, f, settings)
        src = f"cache ({time.perf_counter() - t0:.2f} s to get)"
    print(f"SDF {src}: {sdf}; torch threads {torch.get_num_threads()}, {args.calls} calls per case")
    rows = bench_query(sdf, v, args.calls)
    print_query_table(rows)
    if args.json is not None:
        with atomic_open(args.json) as fh:
            json.dump({"mesh": str(args.mesh), "sdf": src, "threads": args.threads, "calls": args.calls,
                       "rows": rows},
                      fh, indent=2)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", type=Path, default=DEFAULT_MESH)
    ap.add_argument("--voxels", type=float, nargs="+", default=None,
                    help="voxel sizes in mm (default 5 2.5 1.25; --query: the first one, default 2.5)")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--points", type=int, default=50_000)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--query", action="store_true", help="time sampling only (see the module docstring)")
    ap.add_argument("--sdf", type=Path, default=None, help="--query: load this saved SDF instead of building")
    ap.add_argument("--threads", type=int, default=2, help="--query: torch threads")
    ap.add_argument("--calls", type=int, default=50, help="--query: timed calls per case")
    args = ap.parse_args(argv)

    m = trimesh.load(args.mesh, process=False, force="mesh")
    v, f = np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)
    if args.query:
        args.voxels = args.voxels or [2.5]
        main_query(args, v, f)
        return
    args.voxels = args.voxels or [5.0, 2.5, 1.25]
    print(f"mesh {args.mesh.name}: {len(v)} vertices, {len(f)} faces, "
          f"torch threads {torch.get_num_threads()}")
    rows = []
    head = (f"{'voxel':>6} {'band':>5} {'build s':>8} {'MB f64':>7} {'MB f32':>7} {'dense MB':>8} "
            f"{'bricks':>7} {'exact':>9} {'err mean':>8} {'p99':>6} {'max':>6} {'|g| p1':>6} {'med':>6} "
            f"{'p99':>6} {'us/pt':>6}")
    print(head)
    for vox in args.voxels:
        r = bench_one(v, f, vox, args.runs, args.points)
        rows.append(r)
        print(
            f"{r['voxel_mm']:>6.2f} {r['band_mm']:>5.1f} {r['build_s_median']:>8.2f} "
            f"{r['bytes_float64'] / 1e6:>7.1f} {r['bytes_float32'] / 1e6:>7.1f} "
            f"{r['dense_fine_float32_bytes'] / 1e6:>8.1f} {r['bricks']:>7d} {r['exact_nodes']:>9d} "
            f"{r['err_mm_mean']:>8.4f} {r['err_mm_p99']:>6.3f} {r['err_mm_max']:>6.3f} "
            f"{r['grad_norm_p1']:>6.3f} {r['grad_norm_median']:>6.4f} {r['grad_norm_p99']:>6.3f} "
            f"{r['query_us_per_point']:>6.2f}",
            flush=True,
        )
    print("err: |sampled - exact (igl, exact winding-number sign)| in mm at random points with |phi| <= band")
    if args.json is not None:
        with atomic_open(args.json) as fh:
            json.dump({"mesh": str(args.mesh), "rows": rows}, fh, indent=2)


if __name__ == "__main__":
    main()
