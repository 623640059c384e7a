"""Benchmark of online data-driven fitting (Gillies et al. 2004): garment from known weights, and batches.

A synthetic body model of the anny size (13,348 vertices) and a synthetic clothing basis of a 30K-vertex
garment (random, the right sizes: the timing does not depend on the values) are stacked in an
:class:`~torchgarment.datadriven.online.OnlineFitter`. Reported (medians over repeats, CPU):

* ``fit_ms``: one customer's garment once the weights are known (target <= 2 ms);
* ``weights_ms``: the projection of one body to weights (done once per customer);
* ``bodies_per_s``: batch throughput of ``fit`` over B customers at once;
* each in both frames: ``absolute`` (Gillies: blend positions) and ``body`` (blend body-relative
  coordinates, then decode on the customer's body);
* ``push-out``: the collision push-out of one customer's garment on a real body (the size-12 and size-14 chart
  bodies in turn, 13,348 vertices, so each customer's body differs from the last one's): exact distances at
  the garment's vertices (:func:`~torchgarment.datadriven.online.push_out`, the distance tree included: built
  for each customer, so that the result does not depend on the customers before; a refit would be faster),
  on a 30K-vertex
  garment-like point set (body surface points offset along their normals by N(4 mm, 6 mm), so that about a
  quarter start inside); ``online_ms`` = weights + fit + push-out (target <= 100 ms);
* ``anchor_ms``: the waist-plane measurement that hangs a garment with a support (a skirt's waistband) from
  the customer's waist (:meth:`~torchgarment.datadriven.online.OnlineFitter.anchors`), once per customer like
  the weights, on the same body; ``online_anchored_ms`` adds it (the move itself is part of ``fit``).

Example::

    python scripts/bench_pca_fit.py --vertices 30000 --k 5 10 20 --batch 256 --json /tmp/bench_pca.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def median_seconds(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def bench_push_out(n: int, repeats: int) -> dict:
    """Median push-out time of an ``n``-vertex garment-like point set (see the module docstring), float64
    (the push-out computes in float64), on customers that alternate between the size-12 and size-14 chart
    bodies, so that every push-out is on another body than the last. ``tree_ms``: the tree the push-out
    builds; ``tree_refit_ms``: a refit of the last body's tree (what a pooled tree would cost)."""
    import numpy as np
    import trimesh

    from torchgarment.body import Body
    from torchgarment.datadriven.online import push_out
    from torchgarment.sdf import MeshProximity

    customers = []
    for i, size in enumerate(("12", "14")):
        body = Body.from_size(size)
        v, f = body.vertices.numpy(), body.faces.numpy()
        surface, tri = trimesh.sample.sample_surface(trimesh.Trimesh(v, f, process=False), n, seed=i)
        normals = np.cross(v[f[tri, 1]] - v[f[tri, 0]], v[f[tri, 2]] - v[f[tri, 0]])
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        offset = np.random.default_rng(i).normal(0.004, 0.006, size=(n, 1))
        customers.append((body, torch.as_tensor(surface + offset * normals)))
    body, x = customers[0]
    v, f = body.vertices.numpy(), body.faces.numpy()
    res = push_out(x, body.vertices, body.faces)
    live = []  # instances kept alive so that each one builds its own tree
    build_s = median_seconds(lambda: live.append(MeshProximity(v, f)), repeats)
    live.clear()
    turn = itertools.cycle(customers)

    def refit() -> None:
        b, _ = next(turn)
        MeshProximity(b.vertices.numpy(), b.faces.numpy())

    def one() -> None:
        b, y = next(turn)
        push_out(y, b.vertices, b.faces)

    refit_s = median_seconds(refit, repeats)
    push_s = median_seconds(one, repeats)
    return {"push_out_ms": 1e3 * push_s, "tree_ms": 1e3 * build_s, "tree_refit_ms": 1e3 * refit_s,
            "repeats": repeats, "inside_before": res.inside_before, "moved": res.moved,
            "inside_after": res.inside_after, "min_distance_after_mm": 1e3 * res.min_phi}


def bench_anchor(repeats: int) -> float:
    """Median seconds of the waist-plane measurement of the size-12 chart body (an anny body)."""
    from torchgarment.body import Body
    from torchgarment.sim.support import waist_height

    body = Body.from_size("12")
    v, f = body.vertices.double(), body.faces.long()
    return median_seconds(lambda: waist_height(v, f), repeats)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vertices", type=int, default=30000, help="garment vertices (default 30000)")
    ap.add_argument("--body-vertices", type=int, default=13348, help="body vertices (default 13348, anny)")
    ap.add_argument("--k", type=int, nargs="+", default=[5, 10, 20],
                    help="component counts (default 5 10 20)")
    ap.add_argument("--batch", type=int, default=256,
                    help="customers per batch for the throughput (default 256)")
    ap.add_argument("--repeats", type=int, default=50, help="timed repeats (default 50)")
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"], help="default float32")
    ap.add_argument("--interpolation", default="piecewise", choices=["linear", "piecewise"])
    ap.add_argument("--threads", type=int, default=1,
                    help="torch intra-op threads (default 1: one customer per core; 0 keeps torch's default)")
    ap.add_argument("--json", default=None, metavar="FILE", help="write the results as JSON")
    args = ap.parse_args(argv)

    from torchgarment.datadriven.basis import ClothingBasis
    from torchgarment.datadriven.online import OnlineFitter
    from torchgarment.datadriven.pca import BodyPCA
    from torchgarment.structures.garment_mesh import GarmentMesh

    if args.threads > 0:
        torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    g = torch.Generator().manual_seed(0)
    kmax = max(args.k)
    nb, ng = args.body_vertices, args.vertices
    q, _ = torch.linalg.qr(torch.randn(3 * nb, kmax, generator=g, dtype=torch.float64))
    pca = BodyPCA(mean=torch.randn(nb, 3, generator=g, dtype=torch.float64),
                  components=q.T.reshape(kmax, nb, 3),
                  variances=torch.linspace(1.0, 0.01, kmax, dtype=torch.float64), total_variance=6.0,
                  faces=torch.tensor([[0, 1, 2]], dtype=torch.long), num_bodies=kmax + 1)
    mean = torch.randn(ng, 3, generator=g, dtype=torch.float64)
    garment = GarmentMesh(mean, torch.tensor([[0, 1, 2]], dtype=torch.long))
    basis = ClothingBasis(mean, mean + 0.01 * torch.randn(kmax, ng, 3, generator=g, dtype=torch.float64),
                          mean - 0.01 * torch.randn(kmax, ng, 3, generator=g, dtype=torch.float64),
                          pca.sigmas.clone(), garment, pca.fingerprint(), "bench", "synthetic")
    rows = []
    for frame in ("absolute", "body"):
        for k in args.k:
            fitter = OnlineFitter(pca, [basis], k=k, interpolation=args.interpolation, frame=frame,
                                  dtype=dtype)
            body = (pca.mean + 0.01 * torch.randn(nb, 3, generator=g, dtype=torch.float64)).to(dtype)
            w = fitter.weights(body)
            bodies = body + 0.01 * torch.randn(args.batch, nb, 3, generator=g, dtype=torch.float64).to(dtype)
            wb = fitter.weights(bodies)
            with torch.no_grad():
                fit_s = median_seconds(lambda: fitter.fit_all(w, bodies=body), args.repeats)
                weights_s = median_seconds(lambda: fitter.weights(body), args.repeats)
                batch_s = median_seconds(lambda: fitter.fit_all(wb, bodies=bodies),
                                         max(5, args.repeats // 10))
            rows.append({"frame": frame, "k": k, "fit_ms": 1e3 * fit_s, "weights_ms": 1e3 * weights_s,
                         "batch": args.batch, "batch_ms": 1e3 * batch_s,
                         "bodies_per_s": args.batch / batch_s})
    push = bench_push_out(ng, max(11, args.repeats // 5))
    online_ms = {f"{r['frame']} k={r['k']}": r["weights_ms"] + r["fit_ms"] + push["push_out_ms"]
                 for r in rows}
    anchor_ms = 1e3 * bench_anchor(max(5, args.repeats // 10))
    result = {"garment_vertices": ng, "body_vertices": nb, "dtype": args.dtype,
              "interpolation": args.interpolation,
              "threads": torch.get_num_threads(), "torch": torch.__version__, "rows": rows,
              "push_out": push, "online_ms": online_ms, "anchor_ms": anchor_ms,
              "online_anchored_ms": {k: v + anchor_ms for k, v in online_ms.items()}}
    print(f"online fit of a {ng}-vertex garment ({args.dtype}, {args.interpolation}, {result['threads']} "
          f"threads), medians of {args.repeats}:")
    print(f"{'frame':>8} {'k':>3} {'fit ms':>8} {'weights ms':>11} {'batch':>6} {'batch ms':>9} "
          f"{'bodies/s':>10}")
    for r in rows:
        print(f"{r['frame']:>8} {r['k']:>3} {r['fit_ms']:>8.3f} {r['weights_ms']:>11.3f} {r['batch']:>6} "
              f"{r['batch_ms']:>9.2f} {r['bodies_per_s']:>10.0f}")
    print(f"push-out on the size-12 and size-14 bodies in turn, {ng} vertices "
          f"({push['inside_before']} inside, {push['moved']} moved, {push['inside_after']} inside after, "
          "size 12): median "
          f"{push['push_out_ms']:.1f} ms of {push['repeats']}, of which the tree "
          f"{push['tree_ms']:.1f} ms (built "
          f"for each customer; a refit of the last one's would take {push['tree_refit_ms']:.1f} ms); "
          "online cost per customer "
          "(weights + fit + push-out): "
          + ", ".join(f"{k} {v:.1f} ms" for k, v in online_ms.items()))
    print(f"anchor (waist-plane measurement of the size-12 body, once per customer, for a garment with a "
          f"support): median {anchor_ms:.1f} ms")
    if args.json:
        from torchgarment.io.atomic import atomic_path

        with atomic_path(args.json) as tmp:
            Path(tmp).write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
