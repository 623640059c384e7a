"""Benchmark of intersection-free retargeting: seconds per pair over garment and avatar sizes.

Garments of 600 to 6,000 vertices on avatars of 2K to 10K vertices (the issue's target: mean <= 20 s,
max <= 60 s per pair on 2 CPU cores). Garments: a draped garment OBJ (``--garment``, dressed on the anny
body of ``--source-size``) remeshed to each requested vertex count by Loop subdivision / quadric decimation
(``--garment-vertices``); without ``--garment`` an open tube around the torso (a synthetic skirt) of each
size. Avatars: anny bodies (``--avatar``, default anny-6 and anny-20) decimated to each ``--avatar-vertices``
count (skin weights carried to the kept vertices by nearest original vertex). Every pair also reports the
collision-free step method's time (``--step-bound`` to compare ``additive``, ``tight_inclusion``,
``distance``).

Example::

    python scripts/bench_retarget.py --garment skirt.obj --json out/bench_retarget.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:
    from torchgarment.retarget.avatars import TestAvatar


def _decimate(vertices: np.ndarray, faces: np.ndarray, target_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadric decimation (libigl) to about ``target_vertices`` vertices (no-op when already smaller)."""
    import igl

    if vertices.shape[0] <= target_vertices:
        return vertices, faces
    v, f, *_ = igl.decimate(
        np.asfortranarray(vertices, dtype=np.float64),
        np.asfortranarray(faces, dtype=np.int32),
        int(2 * target_vertices),
    )
    return np.asarray(v), np.asarray(f)


def _resize_garment(v: np.ndarray, f: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Subdivide (Loop, upsample) or decimate a garment mesh to about n vertices."""
    import igl

    while v.shape[0] * 3 < n:
        v, f = igl.upsample(v, f)
    if v.shape[0] > 1.05 * n:  # within 5 % of the requested size (subdivision overshoots by up to 4x)
        v, f = _decimate(v, f, n)
    return v, f


def _tube(n: int) -> tuple[np.ndarray, np.ndarray]:
    """An open tube (skirt) around an anny torso, about n vertices, metres."""
    from torchgarment.retarget.avatars import tube_mesh

    rings = max(4, int(round((n / 2.5) ** 0.5)))
    segments = max(8, n // rings)
    v, f = tube_mesh(0.22, 0.18, 0.55, 1.05, segments, rings)
    return v.numpy(), f.numpy()


def _avatar(name: str, n: int) -> tuple[TestAvatar, torch.Tensor, torch.Tensor, torch.Tensor | None]:
    from scipy.spatial import cKDTree

    from torchgarment.retarget.avatars import make_avatar

    a = make_avatar(name)
    v0, f0 = a.vertices.numpy(), a.faces.numpy()
    v, f = _decimate(v0, f0, n)
    w = None
    if a.skin_weights is not None:
        idx = cKDTree(v0).query(v, k=1)[1]
        w = a.skin_weights[:, torch.as_tensor(idx)]
    return a, torch.as_tensor(v), torch.as_tensor(f).long(), w


def main(argv: list[str] | None = None) -> int:
    from torchgarment.body import Body
    from torchgarment.io.atomic import atomic_open
    from torchgarment.io.mesh import load_mesh
    from torchgarment.retarget.inputs import problem_from_arrays
    from torchgarment.retarget.pipeline import RetargetSettings, retarget

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--garment", type=Path, help="draped garment OBJ on the source body (default: a tube)")
    ap.add_argument("--source-size", default="12")
    ap.add_argument("--garment-vertices", type=int, nargs="+", default=[600, 2000, 6000])
    ap.add_argument("--avatar", nargs="+", default=["anny-6", "anny-20"])
    ap.add_argument("--avatar-vertices", type=int, nargs="+", default=[2000, 10000])
    ap.add_argument("--step-bound", default=RetargetSettings().step_bound.value)
    ap.add_argument("--json", type=Path, help="write the records and the summary here")
    args = ap.parse_args(argv)

    source = Body.from_size(args.source_size)
    settings = RetargetSettings(step_bound=args.step_bound)
    if args.garment is not None:
        gv0, gf0 = load_mesh(args.garment, weld=True, dtype=torch.float64)
        gv0, gf0 = gv0.numpy(), gf0.numpy()
    records = []
    print(
        f"{'garment':>8}{'avatar':>16}{'a.verts':>9}{'iters':>7}{'seconds':>9}{'bound s':>9}{'inter':>7}"
        f"{'dmin mm':>9}"
    )
    for gn in args.garment_vertices:
        gv, gf = _resize_garment(gv0, gf0, gn) if args.garment is not None else _tube(gn)
        for name in args.avatar:
            for an in args.avatar_vertices:
                a, av, af, w = _avatar(name, an)
                t0 = time.perf_counter()
                rec = {
                    "garment_vertices": int(gv.shape[0]),
                    "avatar": name,
                    "avatar_vertices": int(av.shape[0]),
                }
                try:
                    p = problem_from_arrays(
                        torch.as_tensor(gv),
                        torch.as_tensor(gf).long(),
                        source.skeleton,
                        av,
                        af,
                        a.skeleton,
                        skin_weights=w,
                        source_avatar=(source.vertices, source.faces),
                    )
                    r = retarget(p, settings, progress=False)
                    m = r.metrics
                    rec.update(
                        seconds=time.perf_counter() - t0,
                        newton_iterations=m["newton_iterations"],
                        intersections=m["intersections"],
                        min_distance_mm=m["min_distance_mm"],
                        step_bound_seconds=sum(s.get("step_bound_seconds", 0.0) for s in r.steps),
                        steps={s["step"]: s["seconds"] for s in r.steps},
                        ok=True,
                    )
                except Exception as e:  # noqa: BLE001 - reported per pair
                    rec.update(seconds=time.perf_counter() - t0, ok=False, error=f"{type(e).__name__}: {e}")
                records.append(rec)
                if rec["ok"]:
                    print(
                        f"{rec['garment_vertices']:>8}{name:>16}{rec['avatar_vertices']:>9}"
                        f"{rec['newton_iterations']:>7}{rec['seconds']:>9.1f}{rec['step_bound_seconds']:>9.1f}"
                        f"{rec['intersections']:>7}{rec['min_distance_mm']:>9.3f}",
                        flush=True,
                    )
                else:
                    print(
                        f"{rec['garment_vertices']:>8}{name:>16}{rec['avatar_vertices']:>9} "
                        f"FAILED {rec['error']}"
                    )
    secs = [r["seconds"] for r in records if r["ok"]]
    summary = {
        "pairs": len(records),
        "failed": sum(not r["ok"] for r in records),
        "intersecting": sum(r.get("intersections", 0) > 0 for r in records),
        "mean_seconds": float(np.mean(secs)) if secs else None,
        "max_seconds": float(np.max(secs)) if secs else None,
        "step_bound": args.step_bound,
        "torch_threads": settings.threads,
    }
    print(json.dumps(summary))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        with atomic_open(args.json) as f:
            json.dump({"summary": summary, "records": records}, f, indent=2)
            f.write("\n")
    return 0 if summary["failed"] == 0 and summary["intersecting"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
