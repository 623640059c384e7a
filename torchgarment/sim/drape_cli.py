"""The ``torchgarment drape`` subcommand: drape a pattern on a body and write ``garment.obj``, ``drape.png``
and ``metrics.json``.

:func:`add_drape_parser` adds the subcommand to the ``torchgarment`` parser (:mod:`torchgarment.cli`) with
:func:`cmd_drape` as its handler.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from torchgarment.errors import InputError
from torchgarment.options import resolve_device

if TYPE_CHECKING:
    from torchgarment.linalg import SparseBackend
    from torchgarment.pattern.spec import SewingPattern


def add_newton_system_arguments(p: argparse.ArgumentParser, sparse_backend: SparseBackend,
                                whose: str) -> None:
    """Add ``--sparse-backend`` (default ``sparse_backend``) and ``--exact-curvature-cg`` (default None: the
    settings' own rule) for the Newton solves ``whose`` (e.g. "the settle's") names; ``drape``, ``adjust`` and
    ``grade`` share them."""
    from torchgarment.linalg import SparseBackend
    from torchgarment.sim.solvers import DEFAULT_EXACT_CURVATURE_CG

    p.add_argument("--sparse-backend", default=sparse_backend.value, choices=[k.value for k in SparseBackend],
                   help=f"sparse direct solver of {whose} factorizations: superlu (always installed) or an "
                        "optional one; cholmod (pip install -e \".[cholmod]\") factorizes 3-4x faster "
                        f"(default {sparse_backend.value})")
    p.add_argument("--exact-curvature-cg", type=int, default=None, metavar="N",
                   help=f"{whose} Newton direction by up to N CG iterations on the exact Hessian, "
                        "preconditioned by a factorization of the projected one; 0 = projected Newton "
                        f"(default {DEFAULT_EXACT_CURVATURE_CG} with --linear-solver direct, 0 with "
                        "jacobi-pcg)")


def add_drape_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``drape`` subcommand to ``subparsers`` (the object ``add_subparsers`` returned)."""
    from torchgarment.sim.drape import DrapeSettings
    from torchgarment.sim.solvers import LinearSolver, SolverKind

    d = DrapeSettings()
    p = subparsers.add_parser(
        "drape", help="drape a sewing pattern on a body",
        description="Place a pattern's panels around a body, sew them and solve for the quasistatic "
                    "equilibrium (Wang et al. 2018). Writes garment.obj, drape.png (garment coloured by the "
                    "stretch ratio) and metrics.json.")
    p.add_argument("--pattern", required=True, metavar="P",
                   help="a pattern file (.json GarmentCode specification or .dxf) or a library garment name "
                        "(with --size)")
    p.add_argument("--size", help="chart size to draft a library garment for (default: the body's size when "
                                  "--body is a chart size)")
    p.add_argument("--body", required=True, metavar="B",
                   help="a body mesh file (OBJ, PLY, ...) or a chart size")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--edge-length", type=float, default=d.edge_length, metavar="M",
                   help=f"triangle edge length in metres (default {d.edge_length})")
    p.add_argument("--voxel", type=float, default=d.voxel_size, metavar="M",
                   help=f"body SDF voxel size in metres (default {d.voxel_size})")
    p.add_argument("--solver", default=d.solver.value, choices=[k.value for k in SolverKind],
                   help=f"solver of the final (settle) stage (default {d.solver.value})")
    p.add_argument("--linear-solver", default=d.linear_solver.value, choices=[k.value for k in LinearSolver],
                   help="how the newton settle solves its systems: a sparse factorization on the CPU "
                        "(direct) or block-Jacobi CG on --device (jacobi-pcg, the GPU path) "
                        f"(default {d.linear_solver.value})")
    add_newton_system_arguments(p, d.sparse_backend, "the settle's")
    p.add_argument("--max-iterations", type=int, default=d.max_iterations, metavar="N",
                   help=f"iteration budget of the settle stage (default {d.max_iterations})")
    p.add_argument("--support", metavar="PANEL:EDGE[,...]",
                   help="the support (waistband) held at the body's waist: unstitched edges forming one "
                        "closed loop, each PANEL:EDGE with an edge label or index (default: the library "
                        "garment's; for a pattern file without one, the topmost closed loop of a bottom "
                        "garment, named on stderr)")
    p.add_argument("--no-support", action="store_true", help="no support (the garment hangs by its tension)")
    p.add_argument("--self-contact", action="store_true",
                   help="IPC cloth-cloth contact (within each panel while sewing, on the welded garment in "
                        "the settle): the garment cannot pass through itself (slower; needed for "
                        "retargeting, which takes intersection-free garments only)")
    p.add_argument("--device", default="cpu", metavar="D",
                   help="compute device: cpu, cuda or cuda:N (default cpu; the SDF build and the newton "
                        "solver's factorizations stay on the CPU; --linear-solver jacobi-pcg runs on it)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.add_argument("--allow-unconverged", action="store_true",
                   help="write the result even when it is unusable (far from equilibrium, far from the body) "
                        "and exit 0, for studies; without it such a drape exits 3 and writes nothing")
    p.set_defaults(func=cmd_drape)
    return p


def _load_pattern(spec: str, size: str | None, body_spec: str) -> SewingPattern:
    from torchgarment.body.size_chart import chart_row, list_sizes
    from torchgarment.pattern.library import draft, list_garments

    if spec in list_garments():
        size = size if size is not None else (body_spec if body_spec in list_sizes() else None)
        if size is None:
            raise InputError(f"--pattern {spec} is a library garment: give --size S (one of "
                             f"{', '.join(list_sizes())})")
        return draft(spec, chart_row(size))
    if not Path(spec).is_file():
        raise InputError(f"--pattern {spec}: neither a library garment ({', '.join(list_garments())}) nor a "
                         "file")
    from torchgarment.pattern.files import load_pattern_file

    return load_pattern_file(spec)


class _Progress:
    """A tqdm bar per drape stage, on stderr."""

    def __init__(self, totals: dict[str, int], enabled: bool) -> None:
        self.totals, self.enabled = totals, enabled
        self.bar = None
        self.stage = None

    def __call__(self, stage: str, k: int, residual: float) -> None:
        if not self.enabled:
            return
        from tqdm import tqdm

        if stage != self.stage:
            self.close()
            self.stage = stage
            self.bar = tqdm(total=self.totals.get(stage), desc=f"drape: {stage}", file=sys.stderr,
                            leave=False,
                            unit="it")
        self.bar.update(1)
        if k % 10 == 0:
            self.bar.set_postfix(residual=f"{residual:.3g} N", refresh=False)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def cmd_drape(args: argparse.Namespace) -> int:
    """Run ``torchgarment drape``; returns the exit code: 0 also when the drape stopped at its iteration
    budget with a usable result (one line on stderr says so); an unusable one (:func:`unusable_reason`)
    raises :class:`~torchgarment.errors.UnusableResultError` (exit 3) unless ``--allow-unconverged``."""
    from torchgarment.errors import UnusableResultError
    from torchgarment.io.mesh import save_obj
    from torchgarment.io.staging import staged_output
    from torchgarment.render import MeshLayer, render_views
    from torchgarment.sim.drape import DrapeSettings, drape, unusable_reason, vertex_stretch_ratio

    if args.max_iterations < 0:
        raise InputError(f"--max-iterations must be >= 0, got {args.max_iterations}")
    if args.support is not None and args.no_support:
        raise InputError("--support and --no-support exclude each other")
    settings = DrapeSettings(edge_length=args.edge_length, voxel_size=args.voxel, solver=args.solver,
                             max_iterations=args.max_iterations, support=not args.no_support,
                             linear_solver=args.linear_solver, sparse_backend=args.sparse_backend,
                             exact_curvature_cg=args.exact_curvature_cg, self_contact=args.self_contact)
    settings.validate()
    device = resolve_device(args.device)
    t0 = time.perf_counter()
    from torchgarment.body.load import load_body_spec

    body, body_name = load_body_spec(args.body, "body")
    body = body.to(device)
    pattern = _load_pattern(args.pattern, args.size, args.body)
    from torchgarment.pattern.support import choose_support

    pattern, note = choose_support(pattern, args.support, not args.no_support)
    if note:
        print(note, file=sys.stderr)
    progress = _Progress({"sew": settings.sew_max_iterations, "settle": settings.max_iterations},
                         enabled=not args.no_progress)
    try:
        result = drape(pattern, body, settings=settings, progress=progress, dtype=body.dtype,
                       device=body.device)
    finally:
        progress.close()
    reason = unusable_reason(result, body.vertices)
    if reason is not None and not args.allow_unconverged:
        raise UnusableResultError(f"drape of {pattern.name} on {body_name} is unusable: {reason}; nothing "
                                  "written (--allow-unconverged writes it anyway)")
    metrics = {"pattern": args.pattern, "body": args.body, **result.metrics, "unusable": reason}
    metrics["seconds"] = time.perf_counter() - t0
    with staged_output(args.out) as stage:
        welded, _ = result.mesh.welded()
        save_obj(stage / "garment.obj", welded.x, welded.faces)
        ratio = vertex_stretch_ratio(result.mesh, result.x)
        layers = [MeshLayer(vertices=body.vertices, faces=body.faces, color=(0.78, 0.78, 0.80), label="body"),
                  MeshLayer(vertices=result.x, faces=result.mesh.faces, scalars=ratio, cmap="coolwarm",
                            vmin=0.9, vmax=1.1, label="stretch ratio")]
        render_views(layers, stage / "drape.png", title=f"{pattern.name} on {body_name}")
        from torchgarment.io.jsonfile import write_json

        write_json(stage / "metrics.json", metrics)
    m = result.metrics
    print(f"drape {pattern.name} on {body_name}: {m['vertices']} vertices, {m['iterations']} iterations, "
          f"{metrics['seconds']:.1f} s, residual {m['residual']:.3g} N, min sdf {m['min_sdf_mm']:.2f} mm, "
          f"max seam gap {m['max_seam_gap_mm']:.3f} mm, {'converged' if m['converged'] else 'NOT converged'} "
          f"-> {args.out}")
    if not m["converged"] and reason is None:
        print(f"drape: stopped at its iteration budget with a usable result: residual {m['residual']:.3g} N "
              f"against a tolerance of {m['tolerance']:.3g} N (the garment weighs {m['weight_n']:.3g} N)",
              file=sys.stderr)
    elif reason is not None:
        print(f"drape: written although unusable (--allow-unconverged): {reason}", file=sys.stderr)
    if m["intersects_self"]:
        print("drape: the garment passes through itself somewhere (metrics.json: intersects_self); "
              "--self-contact keeps it intersection free", file=sys.stderr)
    return 0
