"""The ``torchgarment retarget`` subcommand: intersection-free garment retargeting (Huang et al. 2025).

Writes ``garment.obj`` (the retargeted garment in the target avatar's frame, welded), ``retarget.png`` (the
garment on the avatar, coloured by the per-triangle surface distortion L_surf on a log scale, like the paper's
Fig. 7) and ``metrics.json`` (seconds, newton_iterations, grad_norm, min_distance_mm, intersections,
distortion_mean / distortion_max, each term's value, ...). TensorBoard scalars go to ``--log-dir``
(default ``logs/retarget/<garment>-on-<avatar>-<time>``).

:func:`add_retarget_parser` adds the subcommand to the ``torchgarment`` parser (:mod:`torchgarment.cli`) with
:func:`cmd_retarget` as its handler; :func:`render_result` draws ``retarget.png``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from torchgarment.errors import InputError

if TYPE_CHECKING:
    import torch

    from torchgarment.retarget.pipeline import RetargetResult


def add_retarget_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``retarget`` subcommand to ``subparsers`` (the object ``add_subparsers`` returned)."""
    from torchgarment.linalg import SparseBackend
    from torchgarment.retarget.pipeline import FitTarget, RetargetSettings
    from torchgarment.sim.contact import StepBound

    d = RetargetSettings()
    p = subparsers.add_parser(
        "retarget",
        help="move a garment onto another avatar without intersections",
        description="Retarget a garment designed on a source avatar onto a target avatar "
        "(Huang et al. 2025): "
        "shrink the avatar onto its skeleton, inflate it inside the garment under IPC contact, "
        "then fit. The output never intersects the avatar or itself. Writes garment.obj, "
        "retarget.png (surface distortion, log scale) and metrics.json.",
    )
    p.add_argument(
        "--garment", required=True, metavar="G.obj", help="source garment (manifold triangle mesh)"
    )
    p.add_argument(
        "--source-skeleton",
        required=True,
        metavar="S.obj",
        help="source skeleton as an OBJ edge graph (v joints, l bones)",
    )
    p.add_argument(
        "--target-avatar",
        required=True,
        metavar="A.obj",
        help="target avatar (triangle mesh; may be non-manifold, disconnected, self-intersecting)",
    )
    p.add_argument(
        "--target-skeleton",
        required=True,
        metavar="T.obj",
        help="target skeleton (same bones and joint order as the source skeleton)",
    )
    p.add_argument(
        "--source-avatar",
        metavar="SA.obj",
        help="source avatar: the fit region is chosen by garment-to-avatar distance",
    )
    p.add_argument("--skin-weights", metavar="W.txt", help="target skin weights (joints x avatar vertices)")
    p.add_argument("--no-fit", metavar="F.txt", help="garment vertex indices (0-based) the fit term ignores")
    p.add_argument(
        "--curves", metavar="C.txt", help="curve loops to preserve, one line of vertex indices each"
    )
    p.add_argument(
        "--fit-weight",
        type=float,
        default=d.w_fit,
        metavar="W",
        help=f"fit weight: tightness (default {d.w_fit}; 0 keeps the garment's shape)",
    )
    p.add_argument(
        "--fit-target",
        default=FitTarget.resolve(d.fit_target).value,
        choices=[k.value for k in FitTarget],
        help="the gap the fit pulls the garment to: source-gap (each vertex's gap on the source avatar: "
             "the source's tightness; needs --source-avatar), surface (dhat: onto the avatar) or auto "
             "(source-gap with --source-avatar, else surface; the default)",
    )
    p.add_argument(
        "--pos-weight",
        type=float,
        default=d.w_pos,
        metavar="W",
        help=f"positional (boundary along bones) weight (default {d.w_pos})",
    )
    p.add_argument(
        "--attach-weight",
        type=float,
        default=d.w_attach,
        metavar="W",
        help=f"weight that keeps the garment's separate pieces (a patch pocket, a collar) where they lie on "
             f"the cloth under them (default {d.w_attach}; 0 lets them slide)",
    )
    p.add_argument(
        "--step-bound",
        default=StepBound.resolve(d.step_bound).value,
        choices=[k.value for k in StepBound],
        help="collision-free step size method",
    )
    p.add_argument("--fit-iterations", type=int, default=d.fit_iterations, metavar="N",
                   help=f"Newton iterations of the final fit at most (default {d.fit_iterations}); a result "
                        "stopped by this budget is kept when it is intersection-free, with a line on stderr")
    p.add_argument("--sparse-backend", default="auto",
                   choices=["auto", *(k.value for k in SparseBackend)],
                   help="sparse direct solver of the Newton systems: auto (default: cholmod when cvxopt is "
                        "installed, pip install -e \".[cholmod]\", 3-5x faster factorizations; else superlu, "
                        f"always installed; here: {d.sparse_backend.value}) or one by name")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--log-dir", metavar="DIR", help="TensorBoard folder (default logs/retarget/<run>)")
    p.add_argument("--no-log", action="store_true", help="no TensorBoard scalars")
    p.add_argument("--no-render", action="store_true", help="skip retarget.png")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.add_argument("--device", default="cpu", metavar="D",
                   help="compute device: only cpu (the commands' common option; retargeting's barrier, CCD, "
                        "Hessian projection and intersection checks come from ipctk, which has no GPU path)")
    p.set_defaults(func=cmd_retarget)
    return p


def render_result(
    path: Path, avatar_vertices: torch.Tensor, avatar_faces: torch.Tensor, result: RetargetResult, title: str
) -> None:
    """Render the avatar and the garment coloured by per-triangle distortion (log scale) to ``path``."""
    import numpy as np

    from torchgarment.render import MeshLayer, render_views

    dist = result.distortion.detach().cpu().numpy()
    pos = dist[dist > 0]
    vmin = float(max(pos.min(), pos.max() * 1e-4)) if pos.size else 1e-6
    vmax = float(max(dist.max(), vmin * 10))
    layers = [
        MeshLayer(vertices=avatar_vertices, faces=avatar_faces, color=(0.78, 0.78, 0.80), label="avatar"),
        MeshLayer(
            vertices=result.garment_vertices,
            faces=result.garment_faces,
            scalars=np.maximum(dist, vmin),
            scalar_on="face",
            cmap="magma",
            vmin=vmin,
            vmax=vmax,
            log=True,
            label="L_surf distortion",
        ),
    ]
    render_views(layers, path, title=title)


def cmd_retarget(args: argparse.Namespace) -> int:
    """Run ``torchgarment retarget``; returns the exit code (bad input raises InputError: exit 2 in the
    CLI)."""
    from torchgarment.io.jsonfile import write_json
    from torchgarment.io.mesh import save_obj
    from torchgarment.io.staging import staged_output
    from torchgarment.retarget.inputs import load_problem
    from torchgarment.retarget.pipeline import RetargetSettings, retarget

    for name in ("fit_weight", "pos_weight", "attach_weight"):
        v = getattr(args, name)
        if not (math.isfinite(v) and v >= 0):
            raise InputError(f"--{name.replace('_', '-')} must be a non-negative number, got {v}")
    for name in (
        "garment",
        "source_skeleton",
        "target_avatar",
        "target_skeleton",
        "source_avatar",
        "skin_weights",
        "no_fit",
        "curves",
    ):
        v = getattr(args, name)
        if v is not None and not Path(v).is_file():
            raise InputError(f"--{name.replace('_', '-')} {v}: no such file")
    if str(args.device).strip().lower() != "cpu":
        raise InputError(f"--device {args.device}: retarget runs on the CPU only (its barrier, CCD, Hessian "
                         "projection and intersection checks come from ipctk, which has no GPU path); use "
                         "--device cpu")
    t0 = time.perf_counter()
    problem = load_problem(
        args.garment,
        args.source_skeleton,
        args.target_avatar,
        args.target_skeleton,
        source_avatar=args.source_avatar,
        skin_weights=args.skin_weights,
        no_fit=args.no_fit,
        curves=args.curves,
    )
    settings = RetargetSettings(w_fit=args.fit_weight, w_pos=args.pos_weight, w_attach=args.attach_weight,
                                step_bound=args.step_bound,
                                fit_iterations=args.fit_iterations, sparse_backend=args.sparse_backend,
                                fit_target=args.fit_target)
    log_dir = None
    if not args.no_log:
        run = f"{Path(args.garment).stem}-on-{Path(args.target_avatar).stem}-{time.strftime('%Y%m%d-%H%M%S')}"
        log_dir = Path(args.log_dir) if args.log_dir else Path("logs") / "retarget" / run
    result = retarget(problem, settings, progress=not args.no_progress, log_dir=log_dir)
    metrics = {"garment": str(args.garment), "target_avatar": str(args.target_avatar), **result.metrics}
    metrics["seconds_total"] = time.perf_counter() - t0
    metrics["log_dir"] = None if log_dir is None else str(log_dir)
    with staged_output(args.out) as stage:
        save_obj(stage / "garment.obj", result.garment_vertices, result.garment_faces)
        if not args.no_render:
            av = problem.to_work.inverse(problem.avatar_vertices)
            render_result(
                stage / "retarget.png",
                av,
                problem.avatar_faces,
                result,
                f"{Path(args.garment).stem} on {Path(args.target_avatar).stem}",
            )
        write_json(stage / "metrics.json", metrics)
    m = result.metrics
    print(
        f"retarget {Path(args.garment).name} -> {Path(args.target_avatar).name}: {m['garment_vertices']} "
        f"vertices, {m['newton_iterations']} Newton iterations, {metrics['seconds_total']:.1f} s, "
        f"intersections {m['intersections']}, min distance {m['min_distance_mm']:.3f} mm, distortion mean "
        f"{m['distortion_mean']:.3g} max {m['distortion_max']:.3g} -> {args.out}"
    )
    if not m["converged"]:  # usable (intersection-free, checked) but stopped by the iteration budget
        print(f"retarget: stopped at the iteration budget before the gradient tolerance (gradient norm "
              f"{m['grad_norm']:.3g}); the result is intersection-free", file=sys.stderr)
    return 0
