"""Benchmark of the batch runner (``torchgarment batch``, Ray embedded on this machine): throughput of N drape
jobs with 1 and 2 workers, and an estimate of a catalogue's wall time on a cluster.

Measured:

* a warm-up batch (not timed) fits the bodies and builds their SDFs into the disk cache, so that the timed
  batches measure the jobs, not the one-off preparation;
* for each ``--workers`` W: a fresh batch of the same ``--jobs`` drape jobs (library garments x chart sizes
  at ``--edge-length``, one torch thread per job), its wall time from the call to the summary (Ray's start
  included), jobs per minute, and the median of the jobs' own times (the command inside the worker);
  the speed-up against W = 1 in the same run;
* the one-off costs per new customer: fitting a body to measurements (no cache) and building its SDF;
* one job at the library's default drape settings (the realistic per-job cost of a catalogue), in-process;
* with ``--pca-customers N``: N ``pca_fit`` jobs (random anny customers, push-out on) on one model built
  first (untimed), with 2 workers, one task per fit (``--chunk 1``) against the fits of a model grouped into
  one batched call per 32 bodies (the default), in customers per minute.

Estimate (a table, not a promise): ``--customers`` x ``--garments`` drape jobs at the default settings plus
one body fit and SDF per customer, on K nodes of C cores each with one job per core, at the parallel
efficiency measured here with 2 workers: ``wall = (jobs x t_job + customers x t_body) / (K x C x
efficiency)``. Network transfer, Ray's scheduling across nodes and stragglers are not modelled.

Example::

    python scripts/bench_batch.py --jobs 12 --workers 1 2 --json /tmp/bench_batch.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

GARMENTS = ("straight_skirt", "aline_skirt", "trousers")
SIZES = ("6", "8", "10", "12", "14", "16", "18", "20")


def drape_manifest(n: int, edge_length: float) -> dict:
    """``n`` drape jobs: garments x sizes, in that order."""
    pairs = [(g, s) for s in SIZES for g in GARMENTS][:n]
    if len(pairs) < n:
        raise SystemExit(f"--jobs at most {len(GARMENTS) * len(SIZES)}")
    return {"jobs": [{"method": "drape", "garment": g, "size": s, "settings": {"edge_length": edge_length}}
                     for g, s in pairs]}


def run(manifest: dict, workers: int, folder: Path, chunk: int = 32) -> dict:
    from torchgarment.batch import BatchSettings, parse_manifest, run_batch

    jobs = parse_manifest(manifest, base_dir=folder)
    t0 = time.perf_counter()
    report = run_batch(jobs, BatchSettings(out=folder / f"out_w{workers}_{time.time_ns()}", workers=workers,
                                           chunk=chunk, progress=False, sheet=False))
    wall = time.perf_counter() - t0
    if report.failed:
        raise SystemExit(f"{report.failed} job(s) failed: {[r['error'] for r in report.rows if r['error']]}")
    job_seconds = [float(r["seconds"]) for r in report.rows]
    return {"workers": workers, "chunk": chunk, "jobs": len(jobs), "wall_s": wall,
            "jobs_per_min": 60.0 * len(jobs) / wall, "job_median_s": statistics.median(job_seconds),
            "job_sum_s": sum(job_seconds)}


def pca_runs(customers: int, folder: Path) -> list[dict]:
    """``customers`` pca_fit jobs on one model (built by an untimed first batch), chunk 1 against 32."""
    from torchgarment.body.anny_phenotype import body_from_phenotype, sample_phenotypes
    from torchgarment.io.mesh import save_obj

    names = []
    for i, phenotype in enumerate(sample_phenotypes(customers, seed=123)):
        body = body_from_phenotype(phenotype)
        save_obj(folder / f"customer{i}.obj", body.vertices, body.faces)
        names.append(f"customer{i}.obj")
    build = {"method": "pca_fit", "garment": "straight_skirt", "build": {"bodies": 8, "k": 2},
             "bodies": names[:1], "settings": {"push_out": True}}
    from torchgarment.batch import BatchSettings, parse_manifest, run_batch

    out = folder / "pca_build"
    run_batch(parse_manifest({"cross": [build]}, base_dir=folder),
              BatchSettings(out=out, progress=False, sheet=False))
    (model,) = (out / "shared" / "pca").iterdir()
    manifest = {"cross": [{"method": "pca_fit", "model": str(model), "bodies": names,
                           "settings": {"push_out": True}}]}
    return [run(manifest, 2, folder, chunk=c) for c in (1, 32)]


def per_customer_costs() -> dict:
    """Seconds to fit one body to measurements (no cache) and to build its SDF (default grid, no cache)."""
    import torch

    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.sdf import BodySDF, SDFSettings

    torch.set_num_threads(1)
    row = dict(chart_row("14"))
    row["waist"] += 0.013  # not a chart body: a customer
    t0 = time.perf_counter()
    body = Body.from_measurements(cache=False, **row)
    t_fit = time.perf_counter() - t0
    t0 = time.perf_counter()
    BodySDF.from_mesh(body.vertices, body.faces, SDFSettings())
    return {"body_fit_s": t_fit, "sdf_build_s": time.perf_counter() - t0}


def default_job_seconds(folder: Path) -> float:
    """One drape at the library's default settings (straight skirt on size 12, caches warm), in-process."""
    from torchgarment.batch.worker import run_command

    argv = ["drape", "--pattern", "straight_skirt", "--size", "12", "--body", "12", "--no-progress"]
    run_command(argv, 1, [])  # warm (body and SDF at the default grid)
    result = run_command(argv, 1, [])
    if result["code"] != 0:
        raise SystemExit(f"default drape failed: {result['stderr'][-500:]}")
    return float(result["seconds"])


def estimate(jobs: int, customers: int, t_job: float, t_body: float, efficiency: float,
             nodes: list[int], cores: list[int]) -> list[dict]:
    rows = []
    for c in cores:
        for k in nodes:
            wall = (jobs * t_job + customers * t_body) / (k * c * efficiency)
            rows.append({"nodes": k, "cores_per_node": c, "wall_h": wall / 3600.0})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=12)
    ap.add_argument("--edge-length", type=float, default=0.05)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--customers", type=int, default=1000)
    ap.add_argument("--garments", type=int, default=20)
    ap.add_argument("--nodes", type=int, nargs="+", default=[1, 4, 16, 64])
    ap.add_argument("--cores", type=int, nargs="+", default=[2, 16])
    ap.add_argument("--pca-customers", type=int, default=0)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()

    load_before = os.getloadavg()
    manifest = drape_manifest(args.jobs, args.edge_length)
    with tempfile.TemporaryDirectory(prefix="bench_batch_") as tmp:
        folder = Path(tmp)
        run(manifest, max(args.workers), folder)  # warm-up: bodies and SDFs into the cache, Ray's files
        runs = [run(manifest, w, folder) for w in args.workers]
        t_default = default_job_seconds(folder)
        pca = pca_runs(args.pca_customers, folder) if args.pca_customers else []
    costs = per_customer_costs()
    load_after = os.getloadavg()
    base = next((r for r in runs if r["workers"] == 1), runs[0])
    for r in runs:
        r["speedup"] = base["wall_s"] / r["wall_s"]
    best = max(runs, key=lambda r: r["workers"])
    efficiency = min(1.0, best["speedup"] / best["workers"])
    n_jobs = args.customers * args.garments
    t_body = costs["body_fit_s"] + costs["sdf_build_s"]
    table = estimate(n_jobs, args.customers, t_default, t_body, efficiency, args.nodes, args.cores)

    print(f"load average {load_before[0]:.2f} -> {load_after[0]:.2f}; {args.jobs} drape jobs at edge length "
          f"{args.edge_length} m, 1 torch thread per job")
    print(f"{'workers':>7} {'wall s':>8} {'jobs/min':>9} {'job median s':>13} {'speed-up':>9}")
    for r in runs:
        print(f"{r['workers']:>7} {r['wall_s']:>8.1f} {r['jobs_per_min']:>9.1f} {r['job_median_s']:>13.2f} "
              f"{r['speedup']:>9.2f}")
    print(f"per customer: body fit {costs['body_fit_s']:.1f} s, SDF build {costs['sdf_build_s']:.1f} s; one "
          f"drape at default settings {t_default:.1f} s; parallel efficiency at {best['workers']} workers "
          f"{efficiency:.2f}")
    for r in pca:
        print(f"pca_fit, {r['jobs']} customers, 2 workers, chunk {r['chunk']:>2}: {r['wall_s']:.1f} s, "
              f"{r['jobs_per_min']:.0f} customers/min, {r['job_median_s'] * 1e3:.0f} ms per customer in the "
              "worker")
    print(f"estimate: {args.customers} customers x {args.garments} garments = {n_jobs} drapes")
    print(f"{'nodes':>5} {'cores/node':>10} {'wall h':>8}")
    for row in table:
        print(f"{row['nodes']:>5} {row['cores_per_node']:>10} {row['wall_h']:>8.2f}")
    if args.json:
        args.json.write_text(json.dumps({
            "load_average": [load_before[0], load_after[0]], "edge_length": args.edge_length, "runs": runs,
            "per_customer": costs, "default_job_s": t_default, "efficiency": efficiency, "pca_fit": pca,
            "estimate": {"customers": args.customers, "garments": args.garments, "rows": table}}, indent=2))


if __name__ == "__main__":
    main()
