"""The ``torchgarment`` command line.

Subcommands: ``body``, ``pattern``, ``measure``, ``drape``, ``adjust``, ``grade``, ``retarget``,
``pca``, ``batch``, ``demo``. Every subcommand has ``--help``. Bad input ends with one readable line on
stderr and exit code 2, a result nobody can use (:class:`~torchgarment.errors.UnusableResultError`: a drape
far from equilibrium or from the body) with one line and exit code 3; outputs are staged and published only
on success.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence

from torchgarment.errors import TorchGarmentError, UnusableResultError
from torchgarment.io.jsonfile import write_json

if TYPE_CHECKING:
    from torchgarment.body import Body
    from torchgarment.pattern.spec import SewingPattern
    from torchgarment.render import MeshLayer

EXIT_BAD_INPUT = 2
EXIT_UNUSABLE_RESULT = 3
EXIT_INTERRUPTED = 130


# --------------------------------------------------------------------------------------------- helpers
def _read_json_object(path: str) -> dict:
    from torchgarment.errors import InputError
    from torchgarment.io.jsonfile import read_json

    data = read_json(path, "measurements file")
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a JSON object of name -> value")
    return data


def _body_layer(body: Body) -> MeshLayer:
    from torchgarment.render import MeshLayer

    return MeshLayer(vertices=body.vertices, faces=body.faces, color=(0.78, 0.78, 0.80), label="body")


def _write_body_outputs(body: Body, stage: Path, title: str) -> dict:
    """Write body.obj, skeleton.obj, measurements.json and body.png into ``stage``; return the
    measurements."""
    from torchgarment.body.skeleton_io import write_skeleton_obj
    from torchgarment.io.mesh import save_obj
    from torchgarment.render import render_views

    save_obj(stage / "body.obj", body.vertices, body.faces)
    if body.skeleton is not None:
        write_skeleton_obj(stage / "skeleton.obj", body.skeleton)
    measured = body.measurements().to_dict()
    report = {"units": "metres", "measured": measured, "requested": body.params.get("requested", {})}
    if "reach_errors" in body.params:
        report["fit_errors_mm"] = body.params["reach_errors"]
    write_json(stage / "measurements.json", report)
    render_views([_body_layer(body)], stage / "body.png", title=title)
    return measured


def _draft_measurements_for_size(size: str) -> dict[str, float]:
    from torchgarment.body.size_chart import chart_row

    return chart_row(size)


def _write_pattern_outputs(pattern: SewingPattern, stage: Path, edge_length: float | None) -> dict:
    from torchgarment.pattern.dxf import save_dxf
    from torchgarment.pattern.garmentcode import save_pattern
    from torchgarment.pattern.plot import plot_pattern
    from torchgarment.pattern.svg import save_svg

    pattern.validate()
    mesh = None
    if edge_length is not None:
        from torchgarment.pattern.meshing import mesh_pattern

        mesh = mesh_pattern(pattern, edge_length)
    save_pattern(stage / "pattern.json", pattern)
    save_svg(stage / "pattern.svg", pattern)
    save_dxf(stage / "pattern.dxf", pattern)
    plot_pattern(pattern, stage / "pattern.png", mesh=mesh, title=pattern.name)
    info = {"name": pattern.name, "panels": len(pattern.panels), "stitches": len(pattern.stitches)}
    if mesh is not None:
        info.update(vertices=int(mesh.x.shape[0]), faces=int(mesh.faces.shape[0]))
    return info


# --------------------------------------------------------------------------------------------- commands
def cmd_body(args: argparse.Namespace) -> int:
    from torchgarment.body import Body
    from torchgarment.io.staging import staged_output

    if args.list_sizes:
        from torchgarment.body.size_chart import list_sizes

        print("\n".join(list_sizes()))
        return 0
    if args.out is None or (args.size is None) == (args.measurements is None):
        raise _UsageError("body: give --list-sizes, or --out DIR with exactly one of --size S or "
                          "--measurements FILE")
    t0 = time.perf_counter()
    if args.size is not None:
        body = Body.from_size(args.size, cache=not args.no_cache)
        title = f"size {args.size}"
    else:
        body = Body.from_measurements(cache=not args.no_cache, closest=args.closest,
                                      **_read_json_object(args.measurements))
        title = Path(args.measurements).stem
        if not body.params["reached"]:
            print("warning: anny cannot reach these measurements; writing the closest body (errors in mm: "
                  f"{body.params['reach_errors']})", file=sys.stderr)
    with staged_output(args.out) as stage:
        measured = _write_body_outputs(body, stage, title)
    print(f"body ({title}): {body.num_vertices} vertices, "
          + ", ".join(f"{k} {v * 100:.1f} cm" for k, v in measured.items()
                      if k in ("height", "bust", "waist", "hips"))
          + f"; {time.perf_counter() - t0:.1f} s -> {args.out}")
    return 0


def cmd_pattern(args: argparse.Namespace) -> int:
    from torchgarment.io.staging import staged_output

    if args.list:
        from torchgarment.pattern.library import list_garments

        print("\n".join(list_garments()))
        return 0
    if args.out is None or (args.garment is None) == (args.file is None):
        raise _UsageError("pattern: give --list, or --out DIR with exactly one of --garment NAME or FILE")
    if args.garment is not None:
        from torchgarment.pattern.library import draft

        if args.size is None:
            raise _UsageError("pattern: --garment needs --size S (see `torchgarment body --list-sizes`)")
        pattern = draft(args.garment, _draft_measurements_for_size(args.size))
    else:
        from torchgarment.pattern.files import load_pattern_file

        pattern = load_pattern_file(args.file)
    with staged_output(args.out) as stage:
        info = _write_pattern_outputs(pattern, stage, args.edge_length)
    print(f"pattern {info['name']}: {info['panels']} panels, {info['stitches']} stitches -> {args.out}")
    return 0


def cmd_measure(args: argparse.Namespace) -> int:
    from torchgarment.body.load import check_human_body
    from torchgarment.body.measure import measure_body
    from torchgarment.io.mesh import load_mesh

    vertices, faces = load_mesh(args.mesh)
    check_human_body(vertices, faces, str(args.mesh))
    measured = measure_body(vertices, faces).to_dict()
    write_json(Path(args.out), {"units": "metres", "mesh": str(args.mesh), "measured": measured})
    print(", ".join(f"{k} {v * 100:.1f} cm" for k, v in measured.items()))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """Two bodies of the chart, a skirt drafted for each, placed around its body, rendered; then the first
    size's pattern adjusted to the last size's body (Wang 2018) unless ``--no-adjust``."""
    from torchgarment.body import Body
    from torchgarment.body.size_chart import list_sizes
    from torchgarment.io.mesh import save_obj
    from torchgarment.io.staging import staged_output
    from torchgarment.pattern.library import draft
    from torchgarment.pattern.meshing import mesh_pattern
    from torchgarment.render import MeshLayer, render_views

    sizes = list_sizes()
    chosen = args.sizes or [sizes[len(sizes) // 4], sizes[(3 * len(sizes)) // 4]]
    summary = {"sizes": {}, "garment": args.garment}
    with staged_output(args.out) as stage:
        for size in chosen:
            t0 = time.perf_counter()
            body = Body.from_size(size)
            sub = stage / f"size_{size}"
            measured = _write_body_outputs(body, sub, f"size {size}")
            pattern = draft(args.garment, _draft_measurements_for_size(size))
            info = _write_pattern_outputs(pattern, sub, 0.01)
            mesh = mesh_pattern(pattern, 0.01)
            save_obj(sub / "garment_placed.obj", mesh.x, mesh.faces)
            layers = [_body_layer(body),
                      MeshLayer(vertices=mesh.x, faces=mesh.faces, color=(0.20, 0.45, 0.80),
                                                   label=args.garment)]
            render_views(layers, sub / "placed.png",
                         title=f"{args.garment}, size {size}: panels placed for draping")
            summary["sizes"][size] = {"measured": measured, "pattern": info,
                                      "seconds": round(time.perf_counter() - t0, 3)}
            print(f"size {size}: height {measured['height'] * 100:.1f} cm, bust {measured['bust'] * 100:.1f} "
                  f"cm, waist {measured['waist'] * 100:.1f} cm, hips {measured['hips'] * 100:.1f} cm; "
                  f"{args.garment}: {info['panels']} panels, {info.get('vertices', 0)} vertices "
                  f"({summary['sizes'][size]['seconds']:.1f} s)")
        if not args.no_adjust and len(chosen) >= 2:
            from torchgarment.adjust.demo import run_adjust_demo

            print(f"adjusting the {args.garment} pattern from size {chosen[0]} to size {chosen[-1]} "
                  f"(Wang 2018) ...", flush=True)
            metrics = run_adjust_demo(stage / "adjust", base_size=chosen[0], target_size=chosen[-1],
                                      garment=args.garment, progress=True)
            summary["adjust"] = {k: metrics[k] for k in ("objective_initial", "objective_final",
                                                         "reduction_percent", "seconds") if k in metrics}
            print(f"adjust: objective {metrics['objective_initial']:.4g} -> {metrics['objective_final']:.4g} "
                  f"({metrics['reduction_percent']:.1f} % reduction) in {metrics['seconds']:.1f} s")
        write_json(stage / "summary.json", summary)
    print(f"demo outputs in {args.out}")
    return 0


# --------------------------------------------------------------------------------------------- parser
class _UsageError(TorchGarmentError):
    """Wrong combination of command-line options."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="torchgarment", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("body", help="make a human body from the size chart or from measurements",
                       description="Fit an anny body to a chart size or to measurements (JSON object of "
                                   "metres: height, bust, underbust, waist, hips, optional thigh, upper_arm, "
                                   "neck, wrist) and write body.obj, skeleton.obj, measurements.json and "
                                   "body.png.")
    p.add_argument("--size", help="a size label of the built-in chart (see --list-sizes)")
    p.add_argument("--measurements", metavar="FILE.json", help="JSON object of measurements in metres")
    p.add_argument("--out", metavar="DIR", help="output folder")
    p.add_argument("--list-sizes", action="store_true", help="print the chart's size labels, smallest first")
    p.add_argument("--no-cache", action="store_true", help="fit again even if the body is in the disk cache")
    p.add_argument("--closest", action="store_true",
                   help="with --measurements: when anny cannot reach them within 3 mm, write the closest "
                        "body with a warning and the per-measurement errors (measurements.json), not fail")
    p.set_defaults(func=cmd_body)

    p = sub.add_parser("pattern", help="draft a library pattern or convert a pattern file",
                       description="Draft a library garment for a chart size, or read a pattern file "
                                   "(GarmentCode JSON or AAMA DXF), and write pattern.json, pattern.svg, "
                                   "pattern.dxf, pattern.png.")
    p.add_argument("file", nargs="?", help="a pattern file (.json GarmentCode specification, or .dxf)")
    p.add_argument("--garment", metavar="NAME", help="a library garment (see --list)")
    p.add_argument("--size", help="chart size to draft the library garment for")
    p.add_argument("--out", metavar="DIR", help="output folder")
    p.add_argument("--edge-length", type=float, default=None, metavar="M",
                   help="also triangulate at this target edge length (metres) and draw the mesh in "
                        "pattern.png")
    p.add_argument("--list", action="store_true", help="print the library garments' names, one per line")
    p.set_defaults(func=cmd_pattern)

    p = sub.add_parser("measure", help="measure a closed body mesh (height and girths)",
                       description="Measure height and the girths bust, underbust, waist, hips, thigh, "
                                   "upper_arm, neck, wrist of a closed body mesh (+Y up, metres) and write "
                                   "them as JSON.")
    p.add_argument("mesh", help="body mesh file (OBJ, PLY, STL, GLB)")
    p.add_argument("--out", required=True, metavar="FILE.json", help="output JSON file")
    p.set_defaults(func=cmd_measure)

    from torchgarment.sim.drape_cli import add_drape_parser

    add_drape_parser(sub)

    from torchgarment.adjust.cli import add_adjust_parser
    from torchgarment.adjust.grade_cli import add_grade_parser
    from torchgarment.datadriven.cli import add_pca_parser
    from torchgarment.retarget.cli import add_retarget_parser

    add_adjust_parser(sub)
    add_grade_parser(sub)
    add_retarget_parser(sub)
    add_pca_parser(sub)

    from torchgarment.batch.cli import add_batch_parser

    add_batch_parser(sub)

    p = sub.add_parser("demo", help="run the main job on built-in defaults",
                       description="Make bodies of two chart sizes, draft a garment for each, mesh it, place "
                                   "it around the body, and write renders, patterns and measurements; then "
                                   "adjust the first size's pattern to the last size's body (Wang 2018) and "
                                   "write its outputs under adjust/.")
    p.add_argument("--out", default="demo_out", metavar="DIR", help="output folder (default: demo_out)")
    p.add_argument("--sizes", nargs="+", metavar="S", help="chart sizes (default: two from the chart)")
    p.add_argument("--garment", default="straight_skirt", help="library garment (default: straight_skirt)")
    p.add_argument("--no-adjust", action="store_true",
                   help="skip adjusting the pattern from the first size to the last (a few minutes)")
    p.set_defaults(func=cmd_demo)
    return parser


def exit_code(exc: BaseException) -> int:
    """The exit code of a command that failed with ``exc``: 3 for an unusable result, 2 for bad input
    (:class:`~torchgarment.errors.TorchGarmentError`, a file that cannot be read or written)."""
    return EXIT_UNUSABLE_RESULT if isinstance(exc, UnusableResultError) else EXIT_BAD_INPUT


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``torchgarment`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        if isinstance(getattr(args, "out", None), str) and not args.out.strip():
            # before any work: an empty --out would write into the current folder (after minutes of work)
            raise _UsageError("--out is empty: give the output folder (or file) a name")
        return func(args)
    except _UsageError as e:
        parser.exit(EXIT_BAD_INPUT, f"torchgarment: error: {e}\n")
    except (TorchGarmentError, OSError, json.JSONDecodeError) as e:
        print(f"torchgarment: error: {e}", file=sys.stderr)
        return exit_code(e)
    except KeyboardInterrupt:
        print("torchgarment: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
