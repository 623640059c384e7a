"""The ``torchgarment adjust`` subcommand: adjust a sewing pattern from a base body to a target body
(Wang 2018).

Writes to ``--out DIR`` (staged: nothing is published unless the run succeeds): ``pattern.json``
(GarmentCode), ``pattern.svg``, ``pattern.dxf``, ``garment_base.obj`` (base garment on the base body),
``garment_target.obj`` (adjusted garment on the target body), ``target_before.png`` / ``target_after.png``
(the base and the adjusted pattern simulated on the target body, coloured by the difference of their stretch
ratio to the base drape's, like the paper's Fig. 8), ``overlay.png`` (old and new pattern) and
``metrics.json``. TensorBoard scalars go to ``logs/adjust/<run>`` (``--log-dir``) during the run; Ctrl-C
leaves ``DIR/checkpoint/adjust.pt`` and ``--resume`` continues from it.

:func:`add_adjust_parser` adds the subcommand to the ``torchgarment`` parser (:mod:`torchgarment.cli`) with
:func:`cmd_adjust` as its handler; :func:`write_outputs` writes the files above from an ``AdjustResult``.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from torchgarment.errors import InputError
from torchgarment.options import resolve_device

if TYPE_CHECKING:
    from torchgarment.adjust.pipeline import AdjustResult, AdjustSettings
    from torchgarment.body import Body
    from torchgarment.pattern.spec import SewingPattern


def _length_or_none(text: str) -> float | None:
    """argparse type: a length in metres, or ``none`` (None). Range checks are CostWeights'."""
    if text.strip().lower() == "none":
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a length in metres or 'none', got {text!r}") from None


def add_settings_arguments(p: argparse.ArgumentParser) -> None:
    """Add the options of :class:`~torchgarment.adjust.pipeline.AdjustSettings` that ``adjust`` and ``grade``
    share (read back by :func:`settings_from_args`)."""
    from torchgarment.adjust.fit import FitScale
    from torchgarment.adjust.objective import (
        DEFAULT_EASE_WEIGHT,
        DEFAULT_PLACEMENT_WEIGHT,
        DEFAULT_REFERENCE_EDGE_LENGTH,
    )
    from torchgarment.adjust.optimizers import OptimizerKind
    from torchgarment.adjust.pipeline import AdjustSettings
    from torchgarment.sim.diff import AdjointHessian
    from torchgarment.sim.drape_cli import add_newton_system_arguments
    from torchgarment.sim.solvers import LinearSolver, SolverKind

    d = AdjustSettings()
    p.add_argument("--optimizer", default=d.optimizer.value, choices=[k.value for k in OptimizerKind],
                   help=f"optimizer (default {d.optimizer.value}: preconditioned gradient descent, Algorithm "
                        "1)")
    p.add_argument("--iterations", type=int, default=d.iterations, metavar="N",
                   help=f"outer iterations (default {d.iterations})")
    p.add_argument("--edge-length", type=float, default=d.edge_length, metavar="M",
                   help=f"triangle edge length in metres (default {d.edge_length})")
    p.add_argument("--voxel", type=float, default=d.voxel_size, metavar="M",
                   help=f"body SDF voxel size in metres (default {d.voxel_size})")
    p.add_argument("--inner-iterations", type=int, default=d.inner_iterations, metavar="S",
                   help=f"simulation iterations per inexact outer iteration (default {d.inner_iterations})")
    p.add_argument("--exact-interval", type=int, default=d.exact_interval, metavar="M",
                   help=f"outer iterations between exact solves (default {d.exact_interval})")
    p.add_argument("--min-model-ratio", type=float, default=d.min_model_ratio, metavar="R",
                   help="an exact check that drops by less than R of what the inexact iterations predicted "
                        f"raises S and shortens the step (default {d.min_model_ratio}; 0: the paper's rule)")
    p.add_argument("--adapt-step", action=argparse.BooleanOptionalAction, default=d.adapt_step,
                   help="between exact checks, halve the step after an inexact objective above the last "
                        "--step-window ones and lengthen it after one below them (AdjustSettings.adapt_step; "
                        f"default {'on' if d.adapt_step else 'off'})")
    p.add_argument("--step-window", type=int, default=d.step_window, metavar="K",
                   help=f"inexact objectives --adapt-step compares with (default {d.step_window}; 1: the "
                        "plain bold driver)")
    p.add_argument("--inner-solver", default=d.inner_solver.value, choices=[k.value for k in SolverKind],
                   help=f"solver of the S-iteration simulations (default {d.inner_solver.value}; "
                        f"gd-chebyshev for large meshes)")
    p.add_argument("--linear-solver", default=d.linear_solver.value, choices=[k.value for k in LinearSolver],
                   help="how the simulation's newton solves its systems: a sparse factorization on the CPU "
                        "(direct) or block-Jacobi CG on --device (jacobi-pcg; with --adjoint iterative no "
                        f"simulation system is factorized, the GPU path) (default {d.linear_solver.value})")
    add_newton_system_arguments(p, d.sparse_backend, "the simulation's (base drape, Newton solves)")
    p.add_argument("--adjoint", default="direct", choices=["direct", "iterative", "sparse", "cg"],
                   help="adjoint solve of the gradients: direct (= sparse, the default) or iterative "
                        "(= cg, for large meshes)")
    p.add_argument("--inexact-adjoint", default=d.inexact_adjoint.value,
                   choices=[k.value for k in AdjointHessian],
                   help="the Hessian of the adjoint at an inexact iteration's state (not an equilibrium): "
                        "projected (PSD, by --sparse-backend) or exact (default "
                        f"{d.inexact_adjoint.value})")
    p.add_argument("--reference-edge-length", type=_length_or_none, default=DEFAULT_REFERENCE_EDGE_LENGTH,
                   metavar="M",
                   help="rescale the regularizers to the balance of a mesh of this edge length in metres "
                        "(see CostWeights.reference_edge_length); 'none' uses the paper's coefficients as "
                        f"given at any resolution (default {DEFAULT_REFERENCE_EDGE_LENGTH}: the paper's "
                        "Table 1 dress)")
    p.add_argument("--ease-weight", type=float, default=DEFAULT_EASE_WEIGHT, metavar="W",
                   help="coefficient (1/m^2) of the construction lines' ease term (the base ease kept at the "
                        "waist, hips, bust and hem of a library garment; not in the paper); 0 turns it off "
                        f"(default {DEFAULT_EASE_WEIGHT:g})")
    p.add_argument("--placement-weight", type=float, default=DEFAULT_PLACEMENT_WEIGHT, metavar="W",
                   help="coefficient (1/m^2) of the construction lines' placement term (each line as high "
                        "above the target's waist, hip or bust plane as it sat above the base's; not in the "
                        f"paper); 0 turns it off (default {DEFAULT_PLACEMENT_WEIGHT:g})")
    p.add_argument("--guide-weight", type=float, default=1.0, metavar="R",
                   help="weight of the guide lines (a skirt's hem: kept level at its height above the knee, "
                        "its girth following the hip line's grade) relative to the construction lines; 0 "
                        "turns them off (default 1)")
    p.add_argument("--support-shape-weight", type=float, default=1.0, metavar="R",
                   help="weight of the support's outline (a waistband graded by its length only: its "
                        "position and curve held in the pattern) relative to the placement term; 0 turns it "
                        "off (default 1)")
    p.add_argument("--no-support", action="store_true", help="no support (the garment hangs by its tension)")
    p.add_argument("--fit-scale", default=d.fit_scale.value, choices=[k.value for k in FitScale],
                   help="how the kept ease, line heights and waistband level scale with the body: 'stature' "
                        "multiplies them by the target's height over the base's (1 within a size chart), "
                        f"'none' keeps them absolute (default {d.fit_scale.value})")
    p.add_argument("--exact", action="store_true",
                   help="exact simulation at every iteration (no Algorithm 1)")
    p.add_argument("--init-iterations", type=int, default=d.init_iterations, metavar="N",
                   help=f"L-BFGS iterations of the section-7 initialization (default {d.init_iterations})")
    p.add_argument("--no-init", action="store_true", help="skip the section-7 initialization")
    p.add_argument("--init-trial-iterations", type=int, default=d.init_trial_iterations, metavar="N",
                   help="when the initialized pattern scores no better than the base pattern, optimize N "
                        "iterations from each and keep the start that ends lower; 0 keeps the base pattern "
                        f"(default {d.init_trial_iterations})")


def settings_from_args(args: argparse.Namespace) -> AdjustSettings:
    """The :class:`~torchgarment.adjust.pipeline.AdjustSettings` of the options of
    :func:`add_settings_arguments` (validated: bad values raise InputError)."""
    from torchgarment.adjust.objective import CostWeights
    from torchgarment.adjust.pipeline import AdjustSettings

    if args.iterations < 0:
        raise InputError(f"--iterations must be >= 0, got {args.iterations}")
    weights = CostWeights(reference_edge_length=args.reference_edge_length, ease=args.ease_weight,
                          placement=args.placement_weight, guide=args.guide_weight,
                          support_shape=args.support_shape_weight)
    return AdjustSettings(optimizer=args.optimizer, iterations=args.iterations, edge_length=args.edge_length,
                          voxel_size=args.voxel, inner_iterations=args.inner_iterations,
                          exact_interval=args.exact_interval, inexact=not args.exact,
                          min_model_ratio=args.min_model_ratio, adapt_step=args.adapt_step,
                          step_window=args.step_window,
                          inner_solver=args.inner_solver, adjoint=args.adjoint,
                          inexact_adjoint=args.inexact_adjoint,
                          init_iterations=args.init_iterations, initialize=not args.no_init, weights=weights,
                          support=not args.no_support, init_trial_iterations=args.init_trial_iterations,
                          fit_scale=args.fit_scale, linear_solver=args.linear_solver,
                          sparse_backend=args.sparse_backend, exact_curvature_cg=args.exact_curvature_cg)


def add_adjust_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``adjust`` subcommand to ``subparsers`` (the object ``add_subparsers`` returned)."""
    p = subparsers.add_parser(
        "adjust", help="adjust a sewing pattern to another body (Wang et al. 2018)",
        description="Drape the pattern on the base body, transfer the garment to the target body and "
                    "optimize the pattern so that the garment fits the target body as the base garment fits "
                    "the base body. Writes pattern.json/.svg/.dxf, garment_base.obj, garment_target.obj, "
                    "renders, overlay.png and metrics.json; TensorBoard scalars under logs/adjust/<run> "
                    "(--log-dir).")
    add_pattern_arguments(p)
    tgt = p.add_mutually_exclusive_group(required=True)
    tgt.add_argument("--target-body", metavar="T", help="target body: a mesh file or a chart size")
    tgt.add_argument("--target-size", metavar="S", help="target body: a chart size")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    add_settings_arguments(p)
    p.add_argument("--device", default="cpu", metavar="D",
                   help="compute device: cpu, cuda or cuda:N (default cpu; sparse factorizations and the SDF "
                        "build stay on the CPU)")
    p.add_argument("--resume", action="store_true", help="continue from DIR/checkpoint/adjust.pt")
    p.add_argument("--log-dir", metavar="DIR",
                   help="TensorBoard folder (default logs/adjust/<garment>-<base>-to-<target>-<time>)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.add_argument("--allow-unconverged", action="store_true",
                   help="go on and write the result even when the base drape or the adjusted garment is "
                        "unusable (far from equilibrium, fallen or exploded; exit 3 otherwise)")
    p.set_defaults(func=cmd_adjust)
    return p


def add_pattern_arguments(p: argparse.ArgumentParser) -> None:
    """Add the pattern and base-body options that ``adjust`` and ``grade`` share (read back by
    :func:`pattern_from_args`): ``--pattern | --garment``, ``--base-body | --base-size`` and ``--support``."""
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--pattern", metavar="P",
                     help="a pattern file (.json GarmentCode or .dxf) or a library name")
    src.add_argument("--garment", metavar="NAME", help="a library garment, drafted for the base size")
    base = p.add_mutually_exclusive_group(required=True)
    base.add_argument("--base-body", metavar="B", help="base body: a body file or a chart size")
    base.add_argument("--base-size", metavar="S", help="base body: a chart size")
    p.add_argument("--support", metavar="PANEL:EDGE[,...]",
                   help="the support (waistband) held by sticking springs: unstitched edges forming one "
                        "closed loop, each PANEL:EDGE with an edge label or index (default: the library "
                        "garment's; for a pattern file without one, the topmost closed loop of a bottom "
                        "garment, named on stderr)")


def pattern_from_args(args: argparse.Namespace, base_size: str | None) -> SewingPattern:
    """The pattern of the options of :func:`add_pattern_arguments` (with ``--no-support`` of
    :func:`add_settings_arguments`), its support chosen (:func:`~torchgarment.pattern.support.choose_support`;
    a proposed support is named on stderr).

    Raises:
        InputError: ``--support`` with ``--no-support``, or a bad pattern or support.
    """
    from torchgarment.pattern.support import choose_support

    if args.support is not None and args.no_support:
        raise InputError("--support and --no-support exclude each other")
    spec, flag = (args.garment, "--garment") if args.garment is not None else (args.pattern, "--pattern")
    pattern = load_pattern_spec(spec, base_size, flag)
    pattern, note = choose_support(pattern, args.support, not args.no_support)
    if note:
        print(note, file=sys.stderr)
    return pattern


def load_pattern_spec(spec: str, base_size: str | None, flag: str) -> SewingPattern:
    from torchgarment.body.size_chart import chart_row, list_sizes
    from torchgarment.pattern.library import draft, list_garments

    if spec in list_garments():
        if base_size is None:
            raise InputError(f"{flag} {spec} is a library garment: give the base body as a chart size "
                             f"({', '.join(list_sizes())}) to draft it for")
        return draft(spec, chart_row(base_size))
    if flag == "--garment":
        raise InputError(f"--garment {spec}: not a library garment ({', '.join(list_garments())})")
    if not Path(spec).is_file():
        raise InputError(f"--pattern {spec}: neither a library garment ({', '.join(list_garments())}) nor a "
                         "file")
    from torchgarment.pattern.files import load_pattern_file

    return load_pattern_file(spec)


def _json_safe(v: Any) -> Any:
    if isinstance(v, dict):
        return {k: _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def write_outputs(result: AdjustResult, stage: Path, base_body: Body, target_body: Body, title: str) -> None:
    """Write every output file of ``torchgarment adjust`` for an :class:`AdjustResult` into ``stage``."""
    from torchgarment.io.jsonfile import write_json
    from torchgarment.io.mesh import save_obj
    from torchgarment.render import MeshLayer, render_views
    from torchgarment.sim.drape import vertex_stretch_ratio

    if result.pattern is not None:
        from torchgarment.pattern.dxf import save_dxf
        from torchgarment.pattern.garmentcode import save_pattern
        from torchgarment.pattern.plot import plot_pattern_overlay
        from torchgarment.pattern.svg import save_svg

        save_pattern(stage / "pattern.json", result.pattern)
        save_svg(stage / "pattern.svg", result.pattern)
        save_dxf(stage / "pattern.dxf", result.pattern)
        plot_pattern_overlay(result.base_pattern, result.pattern, stage / "overlay.png",
                             title=f"{title}: base (dashed) and adjusted (solid)")
    for name, mesh in (("garment_base.obj", result.mesh_base), ("garment_target.obj", result.mesh_target)):
        welded, _ = mesh.welded()
        save_obj(stage / name, welded.x, welded.faces)
    base_ratio = vertex_stretch_ratio(result.mesh_base, result.mesh_base.x)
    before = vertex_stretch_ratio(result.mesh_base, result.x_base_on_target) - base_ratio
    after = vertex_stretch_ratio(result.mesh_target, result.mesh_target.x) - base_ratio
    lim = max(0.02, float(before.abs().max()), float(after.abs().max()))
    body = MeshLayer(vertices=target_body.vertices, faces=target_body.faces, color=(0.78, 0.78, 0.80),
                     label="body")
    for fname, x, scal, what in (("target_before.png", result.x_base_on_target, before, "base pattern"),
                                 ("target_after.png", result.mesh_target.x, after, "adjusted pattern")):
        layer = MeshLayer(vertices=x, faces=result.mesh_base.faces, scalars=scal, cmap="coolwarm", vmin=-lim,
                          vmax=lim, label="stretch ratio - base")
        render_views([body, layer], stage / fname, title=f"{title}: {what} on the target body")
    write_json(stage / "metrics.json", _json_safe(result.metrics))


def _refuse_unusable(reason: str | None, what: str, allow: bool) -> None:
    """Raise :class:`UnusableResultError` (exit 3) naming ``what`` and ``reason``; with ``allow`` say it on
    stderr and go on."""
    from torchgarment.errors import UnusableResultError

    if reason is None:
        return
    if not allow:
        raise UnusableResultError(f"{what} is unusable: {reason}; nothing written (--allow-unconverged "
                                  "goes on)")
    print(f"adjust: going on although {what} is unusable (--allow-unconverged): {reason}", file=sys.stderr)


def cmd_adjust(args: argparse.Namespace) -> int:
    """Run ``torchgarment adjust``; returns the exit code."""
    from torchgarment.adjust.pipeline import CHECKPOINT_NAME, adjust
    from torchgarment.io.staging import staged_output

    device = resolve_device(args.device)
    settings = settings_from_args(args)
    base_spec = args.base_body if args.base_body is not None else args.base_size
    target_spec = args.target_body if args.target_body is not None else args.target_size
    from torchgarment.body.load import load_body_spec
    from torchgarment.body.size_chart import list_sizes

    base_flag = "base-body" if args.base_body is not None else "base-size"
    target_flag = "target-body" if args.target_body is not None else "target-size"
    base_body, base_name = load_body_spec(base_spec, base_flag)
    target_body, target_name = load_body_spec(target_spec, target_flag)
    base_size = base_spec if base_spec in list_sizes() else None
    pattern = pattern_from_args(args, base_size)
    if device.type != "cpu":
        base_body, target_body = base_body.to(device), target_body.to(device)
    out = Path(args.out)
    import time

    run = f"{pattern.name}-{base_name}-to-{target_name}-{time.strftime('%Y%m%d-%H%M%S')}"
    run = run.replace(" ", "_").replace("/", "_")
    log_dir = Path(args.log_dir) if args.log_dir else Path("logs") / "adjust" / run
    from torchgarment.adjust.pipeline import base_drape_settings
    from torchgarment.sim.drape import drape, unusable_positions, unusable_reason

    # an unusable base drape (issue 17) is refused before the optimization, an unusable result after it
    base = drape(pattern, base_body, settings=base_drape_settings(settings), device=device)
    _refuse_unusable(unusable_reason(base, base_body.vertices), f"the base drape on {base_name}",
                     args.allow_unconverged)
    result = adjust(pattern, base_body, target_body, settings, log_dir=log_dir,
                    checkpoint_dir=out / "checkpoint", progress=not args.no_progress, resume=args.resume,
                    base=base, device=device)
    _refuse_unusable(unusable_positions(result.mesh_target.x, target_body.vertices),
                     f"the adjusted garment on {target_name}", args.allow_unconverged)
    title = f"{pattern.name}: {base_name} -> {target_name}"
    with staged_output(out) as stage:
        write_outputs(result, stage, base_body, target_body, title)
    # a finished run's checkpoint is stale: a later --resume would start from it (issue 17)
    (out / "checkpoint" / CHECKPOINT_NAME).unlink(missing_ok=True)
    with contextlib.suppress(OSError):
        (out / "checkpoint").rmdir()
    m = result.metrics
    print(f"adjust {title}: objective {m['objective_base']:.4g} (base) -> {m['objective_initial']:.4g} "
          f"(initialized) -> {m['objective_final']:.4g} ({m['reduction_percent']:.1f} % reduction), "
          f"{m['iterations']} iterations, {m['closure_calls']} cloth solves, {m['seconds']:.1f} s, max "
          f"boundary displacement {m['max_boundary_displacement_mm']:.1f} mm -> {out}", file=sys.stdout)
    return 0
