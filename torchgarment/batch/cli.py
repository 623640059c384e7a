"""The ``torchgarment batch`` subcommand: run a manifest of jobs on Ray (:mod:`torchgarment.batch`).

:func:`add_batch_parser` adds the subcommand to the ``torchgarment`` parser (:mod:`torchgarment.cli`) with
:func:`cmd_batch` as its handler. Exit codes: 0 every job ok, 1 some job failed (the others' results are
written), 2 a bad manifest or option (nothing runs), 130 interrupted (the summary of the jobs done is
written; ``--resume`` goes on).
"""

from __future__ import annotations

import argparse
import sys

from torchgarment.errors import InputError

EXIT_JOBS_FAILED = 1


def add_batch_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``batch`` subcommand to ``subparsers`` (the object ``add_subparsers`` returned)."""
    p = subparsers.add_parser(
        "batch", help="run many drape/adjust/grade/retarget/pca_fit jobs on Ray (locally or on a cluster)",
        description="Run the jobs of a manifest (YAML or JSON: 'jobs' and/or 'cross' products; see the "
                    "README's 'Batch and cluster') as Ray tasks. Each job writes the single command's files "
                    "into DIR/jobs/<job>/; DIR gets summary.csv, contact_sheet.png and batch.json. Needs "
                    "Ray: "
                    "pip install -e \".[batch]\".")
    p.add_argument("manifest", metavar="MANIFEST", help="the manifest file (.yaml, .yml or .json)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--address", metavar="ADDRESS",
                   help="join this Ray cluster (HOST:6379, or 'auto' on a cluster node) instead of starting "
                        "Ray on this machine")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="jobs at once (default: the CPUs of this machine or of the cluster, divided by "
                        "--threads)")
    p.add_argument("--threads", type=int, default=1, metavar="T",
                   help="torch threads (and Ray CPUs) per job (default 1: one job per core)")
    p.add_argument("--retries", type=int, default=2, metavar="K",
                   help="further attempts of a failed job before it is recorded as failed (default 2)")
    p.add_argument("--resume", action="store_true",
                   help="skip the jobs an earlier run into DIR finished")
    p.add_argument("--chunk", type=int, default=32, metavar="B",
                   help="pca_fit jobs on one model are fitted B bodies a task (model loaded once, one "
                        "batched call; default 32, 1 = one task per fit)")
    p.add_argument("--no-sheet", action="store_true", help="no contact sheet")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.set_defaults(func=cmd_batch)
    return p


def cmd_batch(args: argparse.Namespace) -> int:
    """Run ``torchgarment batch``; returns the exit code."""
    from pathlib import Path

    from torchgarment.batch.manifest import load_manifest
    from torchgarment.batch.runner import BatchSettings, ray_environment, run_batch

    settings = BatchSettings(out=Path(args.out), address=args.address, workers=args.workers,
                             threads=args.threads, retries=args.retries, resume=args.resume,
                             chunk=args.chunk,
                             progress=not args.no_progress, sheet=not args.no_sheet)
    settings.validate()
    jobs = load_manifest(args.manifest)
    ray_environment(settings)  # before Ray is imported
    try:
        import ray  # noqa: F401 - checked before any work
    except ImportError:
        raise InputError("torchgarment batch needs Ray: pip install -e \".[batch]\" (or pip install ray)") \
            from None
    report = run_batch(jobs, settings)
    retried = f", {report.retried} retried attempt(s)" if report.retried else ""
    skipped = f", {report.skipped} finished earlier (skipped)" if report.skipped else ""
    print(f"batch: {report.jobs} jobs: {report.ok} ok, {report.failed} failed{retried}{skipped}; "
          f"{report.ran} run in {report.seconds:.1f} s with {report.workers} worker(s) -> {args.out} "
          f"(summary.csv{', ' + report.sheets[0].name if report.sheets else ''})")
    for row in report.rows:
        if row["status"] == "failed":
            print(f"  failed: {row['job']}: {row['error']}", file=sys.stderr)
    return 0 if report.failed == 0 else EXIT_JOBS_FAILED
