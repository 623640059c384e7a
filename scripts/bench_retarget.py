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

``--messy`` runs the harder bench of issue 14 instead (target: mean <= 20 s, max <= 60 s per pair, 0
intersections): garments draped on the size-12 anny body at 1.6 cm edges with layered parts
(:func:`~torchgarment.retarget.avatars.layered_garment`): a T-shirt with a collar, two chest pockets and a
hood (about 3.5K vertices) and trousers with a waistband and two back pockets (about 5.5K); avatars at full
resolution: the anny size-12 body (13,348 vertices), the GarmentCode mean bodies from ``../shared/data``
(23,752 vertices; rigged with the skeleton and skin weights of the anny body fitted to their measurements,
nearest vertex; skipped when the data is absent) and the procedural creatures ``creature-10k`` (6 cm) and
``creature-50k`` (10 m), which intersect themselves and are not closed. Drapes are cached under ``--cache``.
Each pair also reports each step's seconds and Newton iterations (``steps``, ``step_iterations``), its mean
distortion, the fit's gaps (``RetargetResult.metrics["fit_gap_mm"]``) and
each layered part's median height above the garment under it on the source and in the result
(``layer_heights_mm``; ``--fit-target surface`` pulls the layers onto the cloth, the default keeps them), and
how far each part's vertices are from their place on the cloth under them (``layer_slide_mm``, median; the
attachment term holds them there, ``--w-attach 0`` lets them slide).
Each pair also reports its sparse direct work (``linalg``: factorizations and substitutions, counts and
seconds, by :func:`torchgarment.linalg.count_linalg`, without cProfile's overhead), and the seconds of the
fit's avatar SDF (``sdf_seconds``; the summary's total): part of the pair's time, built on the first run on a
machine (4-7 s for ``creature-50k``) and read from the disk cache (``~/.cache/torchgarment/sdf``) on the next.
``--profile`` adds, per pair, the self seconds by stage (cProfile, so with its overhead; :data:`STAGES`): CCD
(the collision-free step), broad phase and the avatar's culling (with the garment-avatar BVH queries and
every Warp launch), sparse factorization, linear solves (the
preconditioned CG's triangular solves), Hessian assembly, barrier values and gradients, line search, the rest;
and the top functions by self time.

Both modes print and write (``summary["machine"]``) the machine's load average and a speed reference
measured at the start and end of the run (:class:`torchgarment.benchmarking.MachineWatch`): the machines'
speed varies by 2x from hour to hour, and a pair's seconds are comparable across runs only beside it.
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
    from torchgarment.body import Body
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


MESSY_GARMENTS = {  # name -> (library garment, layered parts)
    "tshirt+collar+pockets+hood": ("tshirt", {"pockets": ((0.09, 1.22, 0.2), (-0.09, 1.22, 0.2)),
                                               "collar": True, "hood": True}),
    "trousers+waistband+pockets": ("trousers", {"pockets": ((0.09, 0.88, -0.2), (-0.09, 0.88, -0.2)),
                                                 "collar": True}),
}
MESSY_AVATARS = ("anny-12", "mean_female", "mean_male", "creature-10k", "creature-50k")

#: cProfile function-name fragments -> stage (first match wins)
STAGES = (
    ("ccd", ("collision_free", "stepsize")),
    ("broad_phase_and_culling", ("ipctk.build", "_recull", "_set_subset", "BroadPhase", "Candidates",
                                 "obstacle_pairs", "ipctk.detect", "warp/_src")),
    ("factorization", ("gstrf", "splu", "factorize", "cvxopt.cholmod.numeric", "cvxopt.cholmod.symbolic")),
    ("linear_solves", ("SuperLU", "pcg", "minres", "csr_matvec", "spsolve", "cvxopt.cholmod.solve")),
    ("hessian_assembly", ("ipctk.hessian", "hessian", "unweighted_blocks", "to_sparse", "CSRAssembler")),
    ("barrier_value_gradient", ("ipctk.potential", "ipctk.gradient", "ipctk.compute", "barrier")),
    ("line_search", ("armijo", "line_search")),
)


def _stage_seconds(prof: object, top: int = 12) -> tuple[dict[str, float], list[tuple[str, float]]]:
    """Self time (s) of the profiled functions summed by stage (:data:`STAGES`), and the ``top`` functions by
    self time."""
    import pstats

    stats = pstats.Stats(prof)
    out = {name: 0.0 for name, _ in STAGES} | {"other": 0.0}
    functions = []
    for (file, line, func), (_cc, _nc, tottime, _ct, _callers) in stats.stats.items():
        label = f"{file}:{func}"
        stage = next((name for name, keys in STAGES if any(k in label for k in keys)), "other")
        out[stage] += tottime
        functions.append((f"{Path(file).name}:{line}:{func}", tottime))
    return out, sorted(functions, key=lambda kv: -kv[1])[:top]


def _messy_garment(name: str, source: Body, cache: Path) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """The draped library garment (cached OBJ) with its layered parts. Draped with self-contact in the settle
    stage: retargeting takes intersection-free garments only, and without it the tshirt's sleeve settled
    through its side on one machine (2026-12-02) and not on others."""
    from torchgarment.body.size_chart import chart_row
    from torchgarment.io.mesh import load_mesh, save_obj
    from torchgarment.pattern.library import draft
    from torchgarment.retarget.avatars import layered_garment
    from torchgarment.sim.drape import DrapeSettings, drape

    garment, layers = MESSY_GARMENTS[name]
    path = cache / f"{garment}-size12-e16-scp.obj"  # scp: + panel contact in sewing
    if not path.is_file():
        r = drape(draft(garment, chart_row("12")), source,
                  settings=DrapeSettings(edge_length=0.016, self_contact=True))
        welded, _ = r.mesh.welded()
        save_obj(path, welded.x, welded.faces)
    gv, gf = load_mesh(path, weld=True, dtype=torch.float64)
    return layered_garment(gv, gf, source, **layers)


def _garmentcode_avatar(name: str) -> TestAvatar | None:
    """A GarmentCode mean body rigged from the anny body fitted to its measurements
    (:func:`~torchgarment.retarget.avatars.rig_from_fitted_anny`); None without ``../shared/data``."""
    from torchgarment.body.load import load_body
    from torchgarment.retarget.avatars import TestAvatar, rig_from_fitted_anny

    root = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "garmentcode" / "bodies"
    if not (root / f"{name}.obj").is_file():
        return None
    b = rig_from_fitted_anny(load_body(root / f"{name}.obj"))
    return TestAvatar(name=name, vertices=b.vertices, faces=b.faces, skeleton=b.skeleton,
                      skin_weights=b.skin_weights,
                      description=f"GarmentCode {name}, rigged from the fitted anny body")


def _report(summary: dict, records: list[dict], path: Path | None) -> int:
    """Print the summary and write it with the records to ``path`` (JSON) when given; the exit code: 1 when a
    pair failed or intersects."""
    from torchgarment.io.jsonfile import write_json

    print(json.dumps(summary))
    if path is not None:
        write_json(path, {"summary": summary, "records": records})
    return 0 if summary["failed"] == 0 and summary["intersecting"] == 0 else 1


def _layer_heights(vertices: np.ndarray, faces: np.ndarray, parts: dict[str, int]) -> dict[str, float]:
    """Median height (mm at human scale) of each layered part's vertices above the base garment (the first
    ``parts["garment"]`` faces; then each part's faces in order): a pocket or collar that keeps its height
    stays a layer."""
    import igl

    nb = parts["garment"]
    base = np.ascontiguousarray(faces[:nb], dtype=np.int64)
    x = np.ascontiguousarray(vertices, dtype=np.float64)
    out, start = {}, nb
    for name, n in list(parts.items())[1:]:
        ids = np.unique(faces[start:start + n])
        start += n
        sq, _, _ = igl.point_mesh_squared_distance(x[ids], x, base)
        out[name] = 1000.0 * float(np.median(np.sqrt(sq)))
    return out


def _layer_slides(source: np.ndarray, result: np.ndarray, faces: np.ndarray, parts: dict[str, int],
                  max_distance: float) -> dict[str, float]:
    """Median distance (mm at human scale) of each layered part's vertices from their place on the cloth
    under them (:class:`~torchgarment.retarget.objectives.Attachment`'s residual, whatever weight the run
    gave it): a pocket that stays where it was sewn reads about 0, one that slid around the body reads the
    slide."""
    from torchgarment.retarget.objectives import Attachment

    f = torch.as_tensor(faces, dtype=torch.long)
    term = Attachment(torch.as_tensor(source), f, max_distance, 1.0)
    miss = 1000.0 * term.residuals(torch.as_tensor(result)).norm(dim=-1).numpy()
    held = term.vertices.numpy()
    out, start = {}, parts["garment"]
    for name, n in list(parts.items())[1:]:
        mine = np.isin(held, np.unique(faces[start:start + n]))
        start += n
        if mine.any():
            out[name] = float(np.median(miss[mine]))
    return out


def messy(args: argparse.Namespace) -> int:
    """The ``--messy`` bench (see the module docstring)."""
    import cProfile

    import ipctk

    from torchgarment.benchmarking import MachineWatch
    from torchgarment.body import Body
    from torchgarment.linalg import count_linalg
    from torchgarment.retarget.avatars import make_avatar
    from torchgarment.retarget.inputs import REFERENCE_HEIGHT, problem_from_arrays
    from torchgarment.retarget.pipeline import RetargetSettings, retarget

    torch.set_num_threads(args.threads)
    watch = MachineWatch()
    source = Body.from_size("12")
    settings = RetargetSettings(step_bound=args.step_bound, sparse_backend=args.sparse_backend,
                                fit_target=args.fit_target, w_attach=args.w_attach)
    args.cache.mkdir(parents=True, exist_ok=True)
    records = []
    print(f"{'garment':>28}{'avatar':>14}{'g.verts':>8}{'a.tris':>8}{'iters':>7}{'seconds':>9}{'inter':>7}"
          f"{'dmin mm':>9}{'inflation dmin mm':>19}{'distort':>8}  layer heights mm (source->result); "
          f"slide mm")
    for gname in args.messy_garments:
        gv, gf, parts = _messy_garment(gname, source, args.cache)
        v = np.asfortranarray(gv.numpy())
        f = np.asfortranarray(gf.numpy().astype(np.int32))
        self_hit = bool(ipctk.has_intersections(ipctk.CollisionMesh(v, ipctk.edges(f), f), v))
        print(f"{gname}: {gv.shape[0]} vertices, parts {parts}, intersects itself: {self_hit}", flush=True)
        for aname in args.messy_avatars:
            a = _garmentcode_avatar(aname) if aname.startswith("mean_") else make_avatar(aname)
            if a is None:
                print(f"{aname}: skipped (../shared/data absent)")
                continue
            rec = {"garment": gname, "garment_vertices": int(gv.shape[0]), "parts": parts, "avatar": aname,
                   "avatar_vertices": int(a.vertices.shape[0]), "avatar_triangles": int(a.faces.shape[0])}
            prof = cProfile.Profile() if args.profile else None
            t0 = time.perf_counter()
            try:
                p = problem_from_arrays(gv, gf, source.skeleton, a.vertices, a.faces, a.skeleton,
                                        skin_weights=a.skin_weights,
                                        source_avatar=(source.vertices, source.faces))
                if prof is not None:
                    prof.enable()
                with count_linalg() as work:
                    r = retarget(p, settings, progress=False)
                if prof is not None:
                    prof.disable()
                m = r.metrics
                fit = next(s for s in r.steps if s["step"] == "fit")
                faces = p.garment_faces.numpy()
                k = REFERENCE_HEIGHT / p.length_scale  # human-scale millimetres
                rec.update(seconds=time.perf_counter() - t0, newton_iterations=m["newton_iterations"],
                           intersections=m["intersections"], min_distance_mm=m["min_distance_mm"],
                           distortion_mean=m["distortion_mean"], fit_target=m["fit_target"],
                           fit_gap_mm=m["fit_gap_mm"],
                           layer_heights_mm={
                               "source": _layer_heights(k * p.garment_vertices.numpy(), faces, parts),
                               "result": _layer_heights(k * r.work_vertices.numpy(), faces, parts)},
                           layer_slide_mm=_layer_slides(k * p.garment_vertices.numpy(),
                                                        k * r.work_vertices.numpy(), faces, parts,
                                                        settings.attach_distance),
                           inflation_min_distance_mm=next(s["min_distance_mm"] for s in r.steps
                                                          if s["step"] == "inflate"),
                           steps={s["step"]: s["seconds"] for s in r.steps},
                           step_iterations={s["step"]: s["newton_iterations"] for s in r.steps
                                            if "newton_iterations" in s}, linalg=work.as_dict(),
                           fit_stop={k: fit[k] for k in ("newton_iterations", "reason", "final_motion_mm")},
                           sdf_seconds=float(fit.get("sdf_seconds", 0.0)), ok=True)
                if prof is not None:
                    rec["stages_seconds"], rec["top_functions"] = _stage_seconds(prof)
            except Exception as e:  # noqa: BLE001 - reported per pair
                rec.update(seconds=time.perf_counter() - t0, ok=False, error=f"{type(e).__name__}: {e}")
            records.append(rec)
            if rec["ok"]:
                print(f"{gname:>28}{aname:>14}{rec['garment_vertices']:>8}{rec['avatar_triangles']:>8}"
                      f"{rec['newton_iterations']:>7}{rec['seconds']:>9.1f}{rec['intersections']:>7}"
                      f"{rec['min_distance_mm']:>9.3f}{rec['inflation_min_distance_mm']:>19.2e}"
                      f"{rec['distortion_mean']:>8.4f}  " + ", ".join(
                          f"{kk} {rec['layer_heights_mm']['source'][kk]:.1f}->{vv:.1f}"
                          for kk, vv in rec["layer_heights_mm"]["result"].items()) + "; " + ", ".join(
                          f"{kk} {vv:.1f}" for kk, vv in rec["layer_slide_mm"].items()), flush=True)
                print(f"      fit: {rec['fit_stop']['newton_iterations']} iterations, stopped on "
                      f"{rec['fit_stop']['reason']}, its last 3 steps moved a vertex up to "
                      f"{rec['fit_stop']['final_motion_mm']:.2f} mm; the avatar's SDF "
                      f"{rec['sdf_seconds']:.1f} s (built, or read from the disk cache)", flush=True)
                la = rec["linalg"]
                print(f"      sparse direct: {la['factorizations']} factorizations "
                      f"{la['factorization_seconds']:.1f} s, {la['solves']} solves "
                      f"{la['solve_seconds']:.1f} s", flush=True)
                if "stages_seconds" in rec:
                    print("      stages (s): " + ", ".join(f"{k} {v:.1f}" for k, v in
                                                           rec["stages_seconds"].items()), flush=True)
                    for name, sec in rec["top_functions"]:
                        print(f"      {sec:8.2f} s  {name}", flush=True)
            else:
                print(f"{gname:>28}{aname:>14} FAILED {rec['error']}", flush=True)
    secs = [r["seconds"] for r in records if r["ok"]]
    summary = {"pairs": len(records), "failed": sum(not r["ok"] for r in records),
               "intersecting": sum(r.get("intersections", 0) > 0 for r in records),
               "mean_seconds": float(np.mean(secs)) if secs else None,
               "max_seconds": float(np.max(secs)) if secs else None,
               # the fit's avatar SDF, part of every pair's seconds: built on a cold disk cache (seconds on a
               # dense avatar), read on a warm one, so a first run is slower than the next
               "sdf_seconds": float(sum(r["sdf_seconds"] for r in records if r["ok"])),
               "targets": {"mean_seconds": 20.0, "max_seconds": 60.0}, "threads": args.threads,
               "profiled": bool(args.profile), "sparse_backend": settings.sparse_backend.value,
               "fit_target": settings.fit_target.value, "w_attach": settings.w_attach,
               "machine": watch.finish()}
    print(MachineWatch.describe(summary["machine"]))
    done = [r for r in records if r["ok"]]
    if done:  # the share of the pairs' time spent in sparse factorizations and substitutions
        summary["linalg_share"] = {
            key: float(sum(r["linalg"][key] for r in done) / sum(r["seconds"] for r in done))
            for key in ("factorization_seconds", "solve_seconds")}
    return _report(summary, records, args.json)


def main(argv: list[str] | None = None) -> int:
    from torchgarment.benchmarking import MachineWatch
    from torchgarment.body import Body
    from torchgarment.io.mesh import load_mesh
    from torchgarment.linalg import SparseBackend
    from torchgarment.retarget.inputs import problem_from_arrays
    from torchgarment.retarget.pipeline import FitTarget, RetargetSettings, retarget

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--garment", type=Path, help="draped garment OBJ on the source body (default: a tube)")
    ap.add_argument("--source-size", default="12")
    ap.add_argument("--garment-vertices", type=int, nargs="+", default=[600, 2000, 6000])
    ap.add_argument("--avatar", nargs="+", default=["anny-6", "anny-20"])
    ap.add_argument("--avatar-vertices", type=int, nargs="+", default=[2000, 10000])
    ap.add_argument("--step-bound", default=RetargetSettings().step_bound.value)
    ap.add_argument("--sparse-backend", default="auto",
                    choices=["auto", *(k.value for k in SparseBackend)],
                    help="sparse direct solver of the Newton systems (default auto: cholmod when cvxopt is "
                         "installed, else superlu; pardiso/cholespy/cholmod: when installed)")
    ap.add_argument("--json", type=Path, help="write the records and the summary here")
    ap.add_argument("--messy", action="store_true", help="the messy bench (layered garments, dense avatars)")
    ap.add_argument("--messy-garments", nargs="+", default=list(MESSY_GARMENTS), choices=list(MESSY_GARMENTS))
    ap.add_argument("--messy-avatars", nargs="+", default=list(MESSY_AVATARS))
    ap.add_argument("--cache", type=Path, default=Path("logs/bench_retarget_messy"),
                    help="folder of the cached drapes (--messy)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (--messy)")
    ap.add_argument("--profile", action="store_true", help="seconds by stage per pair (--messy; cProfile)")
    ap.add_argument("--fit-target", default=RetargetSettings().fit_target.value,
                    choices=[k.value for k in FitTarget],
                    help="RetargetSettings.fit_target (--messy): auto (default), source-gap or surface")
    ap.add_argument("--w-attach", type=float, default=RetargetSettings().w_attach,
                    help="RetargetSettings.w_attach (--messy): what holds the layered parts on the garment; "
                         "0 lets them slide (the objective before 2026-11-28's seventh session)")
    args = ap.parse_args(argv)
    if args.messy:
        return messy(args)

    source = Body.from_size(args.source_size)
    settings = RetargetSettings(step_bound=args.step_bound, sparse_backend=args.sparse_backend)
    if settings.threads is not None:  # retarget()'s threads, for the speed reference too
        torch.set_num_threads(settings.threads)
    watch = MachineWatch()
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
        "sparse_backend": settings.sparse_backend.value,
        "torch_threads": settings.threads,
        "machine": watch.finish(),
    }
    print(MachineWatch.describe(summary["machine"]))
    return _report(summary, records, args.json)


if __name__ == "__main__":
    sys.exit(main())
