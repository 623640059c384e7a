"""The ``torchgarment grade`` subcommand: a whole size run (:func:`torchgarment.adjust.grade.grade`).

``torchgarment grade --garment G --base-size 12 --sizes 6 8 10 14 16 20 --out DIR`` drafts the library garment
for the base size, drapes it once on the base body and adjusts it to every size's body;
``--pattern P --base-body B --target-body T1 T2 ...`` does the same for a pattern file and measured bodies
(chart sizes or body files, as ``torchgarment adjust`` takes them; a body file's size name is its file
stem). Writes ``DIR/<size>/`` (what ``torchgarment adjust`` writes, plus ``fit.json``), ``grade.dxf``,
``grade_nest.png``, ``grade.csv`` and ``metrics.json``, and prints the table of ``grade.csv``. A failing size
is reported on one line and the others go on; the exit code is then 1. Bad input: one line, exit code 2
(:func:`torchgarment.cli.main`).

:func:`add_grade_parser` adds the subcommand to the ``torchgarment`` parser with :func:`cmd_grade` as its
handler.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from torchgarment.errors import InputError

if TYPE_CHECKING:
    from torchgarment.body import Body

EXIT_SIZE_FAILED = 1


def add_grade_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``grade`` subcommand to ``subparsers`` (the object ``add_subparsers`` returned)."""
    from torchgarment.adjust.cli import add_pattern_arguments, add_settings_arguments

    p = subparsers.add_parser(
        "grade", help="grade a sewing pattern over a size run (pattern adjustment to every size's body)",
        description="Drape the pattern on the base body once and adjust it to every target body (Wang et al. "
                    "2018). Writes DIR/<size>/ (pattern.json/.svg/.dxf, garments, renders, metrics.json, "
                    "fit.json), grade.dxf (every size of every piece, AAMA/ASTM D6673), grade_nest.png, "
                    "grade.csv and metrics.json; prints the table of grade.csv.")
    add_pattern_arguments(p)
    tgt = p.add_mutually_exclusive_group(required=True)
    tgt.add_argument("--sizes", nargs="+", metavar="S", help="target chart sizes")
    tgt.add_argument("--target-body", nargs="+", metavar="T",
                     help="target bodies: body files or chart sizes")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    add_settings_arguments(p)
    p.add_argument("--resume", action="store_true", help="skip the sizes whose DIR/<size>/ is complete")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.set_defaults(func=cmd_grade)
    return p


def _targets(specs: list[str], flag: str) -> dict[str, Body]:
    from torchgarment.body.load import load_body_spec

    out: dict[str, Body] = {}
    for spec in specs:
        body, name = load_body_spec(spec, flag)
        name = name.removeprefix("size ").replace("/", "_").replace(" ", "_")
        if name in out:
            raise InputError(f"--{flag}: two targets are named {name!r}")
        out[name] = body
    return out


def cmd_grade(args: argparse.Namespace) -> int:
    """Run ``torchgarment grade``; returns the exit code (1 when a size failed)."""
    from torchgarment.adjust.cli import pattern_from_args, settings_from_args, write_outputs
    from torchgarment.adjust.grade import format_table, grade
    from torchgarment.body.load import load_body_spec
    from torchgarment.body.size_chart import chart_row, list_sizes

    settings = settings_from_args(args)
    base_spec = args.base_body if args.base_body is not None else args.base_size
    base_flag = "base-body" if args.base_body is not None else "base-size"
    if args.sizes is not None:
        bad = [s for s in args.sizes if s not in list_sizes()]
        if bad:
            raise InputError(f"--sizes {' '.join(bad)}: not chart sizes ({', '.join(list_sizes())})")
    base_size = base_spec if base_spec in list_sizes() else None
    pattern = pattern_from_args(args, base_size)
    base_body, base_name = load_body_spec(base_spec, base_flag)
    base_name = base_name.removeprefix("size ").replace("/", "_").replace(" ", "_")
    targets = _targets(args.sizes if args.sizes is not None else args.target_body,
                       "sizes" if args.sizes is not None else "target-body")
    chart = None
    if base_size is not None:
        b = chart_row(base_size)
        chart = {k: {m: chart_row(k)[m] - b[m] for m in b if m != "height"}
                 for k in targets if k in list_sizes()}
    out = Path(args.out)
    result = grade(pattern, base_body, targets, settings, out, resume=args.resume,
                   progress=not args.no_progress, base_size=base_name, chart_changes=chart,
                   writer=write_outputs)
    print(format_table(result.rows))
    acc = result.metrics["acceptance"]
    done = [k for k, s in result.sizes.items() if s.status != "failed"]
    print(f"grade {pattern.name}: base {base_name}, {len(done)}/{len(targets)} sizes "
          f"({sum(s.status == 'resumed' for s in result.sizes.values())} resumed), "
          f"{acc['lines_passed']}/{acc['lines']} lines within {acc['tolerance_m'] * 100:g} cm, "
          f"{result.metrics['total_seconds']:.1f} s -> {out}")
    if result.failed:
        print(f"grade: {len(result.failed)} size(s) failed: {', '.join(result.failed)}", file=sys.stderr)
        return EXIT_SIZE_FAILED
    return 0
