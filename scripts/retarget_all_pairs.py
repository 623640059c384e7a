"""Retarget every garment onto every test avatar (Huang et al. 2025): runtime and intersections per pair.

Garments are OBJ files dressed on an anny chart body (``--source-size``, default 12). Without ``--garment``
the library garments of ``--drape`` are draped on that body by the simulator first (several minutes each) and
cached under ``OUT/garments``. Avatars: every name of :func:`torchgarment.retarget.avatars.list_avatars`
(anny sizes, long arms, big head, short legs, floating parts, torso hole, miniature, giant) unless
``--avatar`` is given.

Writes ``OUT/pairs.json`` (one record per pair: seconds, Newton iterations, intersections, min distance,
distortion), ``OUT/<garment>-<avatar>.obj`` and a contact sheet ``OUT/contact_sheet.png`` (one render per
pair). Exits 1 when any pair intersects or fails.

Example::

    python scripts/retarget_all_pairs.py --garment skirt.obj --garment tshirt.obj --out out/retarget_pairs
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import traceback
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from torchgarment.body import Body
    from torchgarment.retarget.pipeline import RetargetSettings


def _drape_garment(name: str, size: str, cache: Path) -> Path:
    """Drape a library garment on the chart body (cached OBJ), with self-contact in the settle stage:
    retargeting takes intersection-free garments only."""
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.io.mesh import save_obj
    from torchgarment.pattern.library import draft
    from torchgarment.sim.drape import DrapeSettings, drape

    path = cache / f"{name}-size{size}-scp.obj"  # scp: + panel contact in sewing
    if path.is_file():
        return path
    body = Body.from_size(size)
    result = drape(draft(name, chart_row(size)), body, settings=DrapeSettings(self_contact=True),
                   dtype=body.dtype, device=body.device)
    welded, _ = result.mesh.welded()
    save_obj(path, welded.x, welded.faces)
    return path


def run_pair(
    garment: Path, avatar_name: str, source: Body, settings: RetargetSettings, out: Path | None = None
) -> tuple[dict, object]:
    """Retarget one garment OBJ (dressed on ``source``) onto a test avatar; returns (record, result)."""
    import torch

    from torchgarment.io.mesh import load_mesh, save_obj
    from torchgarment.retarget.avatars import make_avatar
    from torchgarment.retarget.inputs import problem_from_arrays
    from torchgarment.retarget.pipeline import retarget

    gv, gf = load_mesh(garment, weld=True, dtype=torch.float64)
    avatar = make_avatar(avatar_name)
    t0 = time.perf_counter()
    problem = problem_from_arrays(
        gv,
        gf,
        source.skeleton,
        avatar.vertices,
        avatar.faces,
        avatar.skeleton,
        skin_weights=avatar.skin_weights,
        source_avatar=(source.vertices, source.faces),
    )
    result = retarget(problem, settings, progress=False)
    seconds = time.perf_counter() - t0
    m = result.metrics
    rec = {
        "garment": garment.stem,
        "avatar": avatar_name,
        "seconds": seconds,
        "retarget_seconds": m["seconds"],
        "garment_vertices": m["garment_vertices"],
        "avatar_vertices": m["avatar_vertices"],
        "newton_iterations": m["newton_iterations"],
        "intersections": m["intersections"],
        "min_distance_mm": m["min_distance_mm"],
        "distortion_mean": m["distortion_mean"],
        "distortion_max": m["distortion_max"],
        "converged": m["converged"],
        "ok": True,
    }
    if out is not None:
        save_obj(out / f"{garment.stem}-{avatar_name}.obj", result.garment_vertices, result.garment_faces)
    return rec, (avatar, result)


def contact_sheet(path: Path, tiles: list[tuple[str, object, object]], columns: int) -> None:
    """One front render per pair (avatar grey, garment coloured by distortion), tiled into a PNG."""
    import tempfile

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.image as mpimg
    import matplotlib.pyplot as plt

    from torchgarment.io.atomic import atomic_path
    from torchgarment.render import MeshLayer, render_views
    from torchgarment.render.views import View

    rows = max(1, math.ceil(len(tiles) / columns))
    fig, axes = plt.subplots(rows, columns, figsize=(3 * columns, 4 * rows), squeeze=False)
    with tempfile.TemporaryDirectory() as tmp:
        for k, ax in enumerate(axes.reshape(-1)):
            ax.axis("off")
            if k >= len(tiles):
                continue
            title, avatar, result = tiles[k]
            png = Path(tmp) / f"{k}.png"
            dist = result.distortion.detach().cpu().numpy()
            render_views(
                [
                    MeshLayer(vertices=avatar.vertices, faces=avatar.faces, color=(0.78, 0.78, 0.8)),
                    MeshLayer(
                        vertices=result.garment_vertices,
                        faces=result.garment_faces,
                        scalars=dist.clip(1e-5, None),
                        scalar_on="face",
                        cmap="magma",
                        log=True,
                        vmin=1e-4,
                        vmax=1.0,
                        label="L_surf",
                    ),
                ],
                png,
                views=(View.FRONT,),
                size=(300, 450),
            )
            ax.imshow(mpimg.imread(png))
            ax.set_title(title, fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as p:
        fig.savefig(p, dpi=100, format="png")
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    from torchgarment.body import Body
    from torchgarment.linalg import SparseBackend
    from torchgarment.retarget.avatars import list_avatars
    from torchgarment.retarget.pipeline import RetargetSettings

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--garment", action="append", type=Path, help="garment OBJ dressed on the source body (repeat)"
    )
    ap.add_argument(
        "--drape",
        action="append",
        default=None,
        help="library garments to drape when no --garment is given (default straight_skirt, tshirt)",
    )
    ap.add_argument("--source-size", default="12", help="anny chart size of the source body (default 12)")
    ap.add_argument("--avatar", action="append", help="avatar names (default: all of list_avatars())")
    ap.add_argument("--fit-weight", type=float, default=RetargetSettings().w_fit)
    ap.add_argument("--sparse-backend", default="auto",
                    choices=["auto", *(k.value for k in SparseBackend)],
                    help="sparse direct solver of the Newton systems (default auto: cholmod when cvxopt is "
                         "installed, else superlu; pardiso/cholespy/cholmod: when installed)")
    ap.add_argument("--out", type=Path, default=Path("out/retarget_pairs"))
    ap.add_argument("--columns", type=int, default=5)
    args = ap.parse_args(argv)

    args.out.mkdir(parents=True, exist_ok=True)
    if args.garment:
        garments = args.garment
    else:
        (args.out / "garments").mkdir(parents=True, exist_ok=True)
        garments = [
            _drape_garment(g, args.source_size, args.out / "garments")
            for g in (args.drape or ["straight_skirt", "tshirt"])
        ]
    avatars = args.avatar or list_avatars()
    source = Body.from_size(args.source_size)
    settings = RetargetSettings(w_fit=args.fit_weight, sparse_backend=args.sparse_backend)
    records, tiles, bad = [], [], 0
    print(
        f"{'garment':<22}{'avatar':<16}{'verts':>7}{'avatar':>8}{'iters':>7}{'seconds':>9}{'inter':>7}"
        f"{'dmin mm':>10}{'dist mean':>11}"
    )
    for g in garments:
        for a in avatars:
            try:
                rec, (avatar, result) = run_pair(Path(g), a, source, settings, args.out)
                tiles.append((f"{Path(g).stem} / {a}", avatar, result))
            except Exception as e:  # noqa: BLE001 - a failing pair is reported, the study goes on
                traceback.print_exc(file=sys.stderr)
                rec = {"garment": Path(g).stem, "avatar": a, "ok": False, "error": f"{type(e).__name__}: {e}"}
            records.append(rec)
            if not rec["ok"] or rec["intersections"]:
                bad += 1
                print(f"{rec['garment']:<22}{a:<16} FAILED: {rec.get('error', 'intersections')}")
                continue
            print(
                f"{rec['garment']:<22}{a:<16}{rec['garment_vertices']:>7}{rec['avatar_vertices']:>8}"
                f"{rec['newton_iterations']:>7}{rec['seconds']:>9.1f}{rec['intersections']:>7}"
                f"{rec['min_distance_mm']:>10.3f}{rec['distortion_mean']:>11.3g}",
                flush=True,
            )
    ok = [r for r in records if r["ok"]]
    summary = {
        "pairs": len(records),
        "failed_or_intersecting": bad,
        "mean_seconds": sum(r["seconds"] for r in ok) / max(len(ok), 1),
        "max_seconds": max((r["seconds"] for r in ok), default=0.0),
    }
    from torchgarment.io.atomic import atomic_open

    with atomic_open(args.out / "pairs.json") as f:
        json.dump({"summary": summary, "pairs": records}, f, indent=2)
        f.write("\n")
    if tiles:
        contact_sheet(args.out / "contact_sheet.png", tiles, args.columns)
    print(
        f"{summary['pairs']} pairs, {bad} failed or intersecting, mean {summary['mean_seconds']:.1f} s, "
        f"max {summary['max_seconds']:.1f} s -> {args.out}"
    )
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
