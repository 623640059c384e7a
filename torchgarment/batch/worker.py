"""What a batch worker runs: the shared preparation of a body, and one job (the single command, in-process).

Both are plain functions; :mod:`torchgarment.batch.runner` wraps them as Ray tasks. A job runs the very
command a user would type (:func:`torchgarment.cli.main`) into a private temporary folder and returns the
files it wrote, as bytes, with its exit code and output: the driver publishes them into the job's folder in
one step (:func:`~torchgarment.io.staging.staged_output`), so a worker killed mid-job leaves no partial job
folder, and the output folder need not be visible to the workers of a cluster.

Shared work travels the same way: :func:`prepare_body` fits a body and builds its SDF once, and returns the
two disk-cache entries (:mod:`torchgarment.body.cache`, :mod:`torchgarment.sdf.cache`); every job on that body
installs them into its machine's cache (:func:`install_cache_files`, atomic, safe under concurrent writers)
before it runs, so it finds the body and the SDF there.
"""

from __future__ import annotations

import contextlib
import io
import os
import shutil
import socket
import tempfile
import time
from pathlib import Path

__all__ = ["LOGS", "MODEL", "folder_files", "install_cache_files", "prepare_body", "run_command",
           "run_pca_fits"]

MODEL = "<model>"
"""Placeholder of a ``pca_fit`` job's ``--model`` folder in its argv: the shared model, unpacked where the job
runs."""

LOGS = "<logs>"
"""Placeholder of ``--log-dir`` in a job's argv: the job's own ``logs/`` (TensorBoard) folder."""

_WORK_NAME = "torchgarment-batch"
"""A job's private folder is a hidden ``.torchgarment-batch.staging-*`` in the temporary folder: the staging
naming of :mod:`torchgarment.io.staging`, so that :func:`~torchgarment.io.staging.remove_orphan_stages`
removes the ones that workers killed mid-job (``kill -9``) left behind."""


def prepare_body(spec: str, voxel: float | None) -> dict:
    """Fit (or load) the body ``spec`` names and build its SDF at ``voxel`` through the disk caches.

    Args:
        spec: a chart size or a body mesh file (as ``--body`` takes it). voxel: SDF voxel size (m), or None
            for no SDF.

    Returns:
        ``{"files": {path relative to the cache root: bytes}}``. A body the command would refuse gives no
        files: the job then fails with the command's own message.
    """
    from torchgarment.body.cache import cache_root, entry_path
    from torchgarment.body.load import load_body_spec
    from torchgarment.errors import TorchGarmentError

    try:
        body, _ = load_body_spec(spec, "body")
        paths = []
        if body.params.get("cache_key"):
            paths.append(entry_path(body.params["cache_key"]))
        if voxel is not None:
            from torchgarment.sdf import SDFSettings, cached_sdf, sdf_cache_path

            settings = SDFSettings(voxel_size=voxel)
            cached_sdf(body.vertices, body.faces, settings)
            paths.append(sdf_cache_path(body.vertices, body.faces, settings))
    except (TorchGarmentError, OSError):
        return {"files": {}}
    root = cache_root()
    return {"files": {str(p.relative_to(root)): p.read_bytes() for p in paths if p.is_file()}}


def install_cache_files(files: dict[str, bytes]) -> int:
    """Write the cache entries ``files`` (path relative to the cache root -> bytes) that this machine's cache
    lacks; each is written atomically, so concurrent workers never see half a file.

    Returns:
        How many were written.
    """
    from torchgarment.body.cache import cache_root
    from torchgarment.io.atomic import atomic_path

    root, written = cache_root(), 0
    for rel, data in files.items():
        path = root / rel
        if path.is_file():
            continue
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            tmp.write_bytes(data)
        written += 1
    return written


def _unpack(files: dict[str, bytes], folder: Path) -> None:
    for rel, data in files.items():
        path = folder / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)


def folder_files(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder``: relative path -> bytes (empty for a missing folder)."""
    if not folder.is_dir():
        return {}
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _work_folder() -> Path:
    """A new private folder for one job (see :data:`_WORK_NAME`), after removing the orphaned ones."""
    from torchgarment.io.staging import remove_orphan_stages

    name = Path(tempfile.gettempdir()) / _WORK_NAME
    remove_orphan_stages(name)
    return Path(tempfile.mkdtemp(prefix=f".{_WORK_NAME}.staging-", dir=name.parent))


def run_command(argv: list[str], threads: int, cache_files: list[dict[str, bytes]],
                model_files: dict[str, bytes] | None = None) -> dict:
    """Run one job: the single command ``torchgarment ARGV --out TMP`` in this process.

    Args:
        argv: the command's arguments without ``--out`` (:attr:`~torchgarment.batch.manifest.Job.argv`), with
            :data:`MODEL` and :data:`LOGS` placeholders. threads: torch threads for this job (the batch gives
            each job as many CPUs in Ray, so that workers do not oversubscribe the cores). cache_files: the
            shared preparations' cache entries (:func:`prepare_body`'s ``files``), installed first.
            model_files: the shared ``pca build`` model's files, for a :data:`MODEL` placeholder.

    Returns:
        ``{"code", "files", "stdout", "stderr", "seconds", "host", "pid"}``: the exit code (0 success, 2 bad
        input, 3 unusable result, ...), the files written under ``--out`` (relative path -> bytes; empty
        unless the command succeeded), its output, its wall time.
    """
    import torch

    from torchgarment.cli import main

    torch.set_num_threads(max(1, int(threads)))
    for files in cache_files:
        install_cache_files(files)
    tmp = _work_folder()
    out, stdout, stderr = tmp / "out", io.StringIO(), io.StringIO()
    argv = [str(out / "logs") if a == LOGS else a for a in argv]
    if MODEL in argv:
        _unpack(model_files or {}, tmp / "model")
        argv = [str(tmp / "model") if a == MODEL else a for a in argv]
    t0 = time.perf_counter()
    try:
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            try:
                code = main([*argv, "--out", str(out)])
            except SystemExit as exc:  # argparse's usage errors
                code = exc.code if isinstance(exc.code, int) else 2
        seconds = time.perf_counter() - t0
        files = folder_files(out) if code == 0 else {}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {"code": int(code or 0), "files": files, "stdout": stdout.getvalue(), "stderr": stderr.getvalue(),
            "seconds": seconds, "host": socket.gethostname(), "pid": os.getpid()}


def run_pca_fits(argvs: list[list[str]], threads: int,
                 model_files: dict[str, bytes] | None = None) -> list[dict]:
    """Run several ``pca_fit`` jobs on one model in one call: the model is loaded once and the bodies are
    fitted in one batched call (:func:`torchgarment.datadriven.cli.fit_bodies`); each job gets the files of
    its single command.

    Args:
        argvs: the jobs' ``pca fit`` arguments without ``--out``; they differ only in ``--body``.
        threads, model_files: as for :func:`run_command`.

    Returns:
        One :func:`run_command`-like result per job, in order; ``seconds`` is the call's wall time divided
        among the jobs.
    """
    import torch

    from torchgarment.cli import build_parser, exit_code
    from torchgarment.datadriven.cli import fit_bodies
    from torchgarment.errors import TorchGarmentError

    torch.set_num_threads(max(1, int(threads)))
    tmp = _work_folder()
    try:
        _unpack(model_files or {}, tmp / "model")
        parser = build_parser()
        outs = [tmp / f"out{i}" for i in range(len(argvs))]
        args = [parser.parse_args([str(tmp / "model") if a == MODEL else a for a in argv]
                                  + ["--out", str(out)]) for argv, out in zip(argvs, outs)]
        t0 = time.perf_counter()
        try:
            outcomes = fit_bodies(args[0], [(a.body, a.out) for a in args])
        except (TorchGarmentError, OSError) as exc:  # the model or an option: every job fails alike
            outcomes = [exc] * len(args)
        share = (time.perf_counter() - t0) / len(args)
        results = []
        for outcome, out in zip(outcomes, outs):
            failed = isinstance(outcome, BaseException)
            results.append({"code": exit_code(outcome) if failed else 0,
                            "files": {} if failed else folder_files(out),
                            "stdout": "" if failed else outcome + "\n",
                            "stderr": f"torchgarment: error: {outcome}\n" if failed else "",
                            "seconds": share, "host": socket.gethostname(), "pid": os.getpid()})
        return results
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
