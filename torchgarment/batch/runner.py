"""The batch runner: jobs of a manifest run as Ray tasks, locally (Ray embedded) or on a Ray cluster.

Output folder ``DIR``:

* ``jobs/<id>/``: each job's files, the same the single command writes, plus ``job.log`` (its output);
  published in one step when the job succeeds, so a job folder is whole or absent;
* ``records/<id>.json``: each job's record (status, seconds, attempts, error line, key metrics, host);
* ``shared/pca/<model>/``: ``pca build`` models shared by ``pca_fit`` jobs;
* ``summary.csv`` (one row per job of the manifest), ``contact_sheet.png`` (``contact_sheet_<n>.png`` past
  :data:`SHEET_TILES` jobs) and ``batch.json`` (counts, settings, timing).

Scheduling: every job is one Ray task with ``num_cpus = threads`` and runs with that many torch threads, and
the local Ray instance gets ``workers x threads`` CPUs, so at most ``workers`` jobs run at once and together
they use the cores they were given (no oversubscription). Shared work is done once: a body is fitted and its
SDF built by one preparation task (:func:`~torchgarment.batch.worker.prepare_body`) whose cache entries every
job on that body receives through Ray's object store; a ``pca build`` model is built by one task and shared by
every fit that needs it. A failed job (exit code not 0, an exception, or its worker killed) is retried up to
``retries`` times, then recorded as failed with its error line; the other jobs go on. ``resume`` skips the
jobs whose record says ``ok`` and whose folder is there.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import shutil
import sys
import time
from collections import deque
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterator

from torchgarment.batch.manifest import METHODS, Job
from torchgarment.batch.worker import folder_files, prepare_body, run_command, run_pca_fits
from torchgarment.errors import InputError
from torchgarment.io.jsonfile import write_json

__all__ = ["SHEET_TILES", "SUMMARY_COLUMNS", "BatchReport", "BatchSettings", "ray_environment", "run_batch"]

SUMMARY_COLUMNS = ("job", "method", "garment", "body", "status", "seconds", "error", "attempts", "folder")
"""The first columns of ``summary.csv``; the jobs' scalar metrics (``metrics.json``) follow."""

SHEET_TILES = 48
"""Jobs per contact sheet page."""


@dataclass
class BatchSettings:
    """How a batch runs.

    Attributes:
        out: the output folder ``DIR``.
        address: a Ray cluster's address (``HOST:6379`` or ``auto``); None starts Ray embedded on this
            machine.
        workers: jobs at once; default: the CPUs (this machine's, or the cluster's) divided by ``threads``.
        threads: torch threads (and Ray CPUs) per job.
        retries: further attempts of a failed job.
        resume: skip the jobs finished (``ok``) by an earlier run into ``out``.
        chunk: ``pca_fit`` jobs on one model fitted together, at most this many bodies a task (the model
            loaded once, one batched weights and fit call; 1: every fit a task of its own).
        progress: a tqdm bar on stderr.
        sheet: write the contact sheet.
    """

    out: Path
    address: str | None = None
    workers: int | None = None
    threads: int = 1
    retries: int = 2
    resume: bool = False
    chunk: int = 32
    progress: bool = True
    sheet: bool = True

    def validate(self) -> None:
        """Raise :class:`~torchgarment.errors.InputError` on a bad value."""
        if self.workers is not None and self.workers < 1:
            raise InputError(f"--workers must be >= 1, got {self.workers}")
        if self.threads < 1:
            raise InputError(f"--threads must be >= 1, got {self.threads}")
        if self.retries < 0:
            raise InputError(f"--retries must be >= 0, got {self.retries}")
        if self.chunk < 1:
            raise InputError(f"--chunk must be >= 1, got {self.chunk}")


@dataclass
class BatchReport:
    """What a batch did.

    Attributes:
        jobs: jobs in the manifest. ran: jobs run now. skipped: jobs finished earlier (resume). ok, failed:
        jobs with that status after this run. retried: attempts beyond the first. seconds: wall time.
        workers: jobs at once. rows: the summary's rows. summary: ``summary.csv``. sheets: the contact sheet
        PNGs.
    """

    jobs: int
    ran: int
    skipped: int
    ok: int
    failed: int
    retried: int
    seconds: float
    workers: int
    rows: list[dict] = field(default_factory=list)
    summary: Path | None = None
    sheets: list[Path] = field(default_factory=list)


# --------------------------------------------------------------------------------------------- folder
@contextlib.contextmanager
def _lock(out: Path) -> Iterator[None]:
    """One batch at a time writes into ``out`` (an advisory lock on ``out/.batch.lock``)."""
    import fcntl

    out.mkdir(parents=True, exist_ok=True)
    with open(out / ".batch.lock", "w") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise InputError(f"another torchgarment batch is writing into {out}: wait for it or choose "
                             "another --out") from None
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _remove_stale_stages(out: Path) -> None:
    """Staging and backup folders of publishes cut short (the driver killed): nothing else writes here while
    the lock is held, so all of them are stale."""
    for sub in ("jobs", "shared/pca"):
        for stale in (out / sub).glob(".*.staging-*"):
            shutil.rmtree(stale, ignore_errors=True)
        for stale in (out / sub).glob(".*.previous-*"):
            shutil.rmtree(stale, ignore_errors=True)


def _read_record(path: Path) -> dict | None:
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return None  # missing or corrupt: the job runs again
    return record if isinstance(record, dict) else None


def _publish(folder: Path, files: dict[str, bytes]) -> None:
    from torchgarment.io.staging import staged_output

    with staged_output(folder) as stage:
        for rel, data in files.items():
            path = stage / rel
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)


def _scalar_metrics(files: dict[str, bytes]) -> dict[str, Any]:
    raw = files.get("metrics.json")
    if raw is None:
        return {}
    try:
        data = json.loads(raw)
    except ValueError:
        return {}
    if not isinstance(data, dict):
        return {}
    # a metric named like a summary column (the command's own "seconds") is kept as "metric_<name>"
    return {(f"metric_{k}" if k in SUMMARY_COLUMNS else k): v for k, v in data.items()
            if isinstance(v, (int, float, bool))}


def _error_line(result: dict) -> str:
    lines = [ln.strip() for ln in result.get("stderr", "").splitlines() if ln.strip()]
    for line in reversed(lines):
        if line.startswith("torchgarment: error:") or ": error: " in line:
            return line.split("error: ", 1)[1]
    return lines[-1] if lines else f"exit code {result.get('code')}"


def _ray_error_line(exc: BaseException) -> str:
    import ray.exceptions as rex

    if isinstance(exc, rex.WorkerCrashedError):
        return "the worker died while running the job (killed, or out of memory)"
    if isinstance(exc, rex.OutOfMemoryError):
        return "the worker was killed for lack of memory"
    if isinstance(exc, rex.RayTaskError):
        cause = exc.cause if getattr(exc, "cause", None) is not None else exc
        text = str(cause).strip().splitlines()
        return f"{type(cause).__name__}: {text[-1] if text else ''}"
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}"


# --------------------------------------------------------------------------------------------- Ray
def _ray_tasks() -> tuple[Any, Any, Any]:
    import ray

    def batch_prepare(spec: str, voxel: float | None, threads: int) -> dict:
        import torch

        torch.set_num_threads(threads)
        return prepare_body(spec, voxel)

    def build_failed(model: dict) -> dict:
        return {"code": model["code"], "files": {}, "stdout": "", "seconds": 0.0, "host": "", "pid": 0,
                "stderr": f"torchgarment: error: the shared pca build failed: {_error_line(model)}"}

    def batch_job(argv: list[str], threads: int, model: dict | None, *preps: dict) -> dict:
        if model is not None and model["code"] != 0:
            return build_failed(model)
        return run_command(argv, threads, [p["files"] for p in preps],
                           None if model is None else model["files"])

    def batch_pca_fits(argvs: list[list[str]], threads: int, model: dict | None) -> list[dict]:
        if model is not None and model["code"] != 0:
            return [build_failed(model)] * len(argvs)
        return run_pca_fits(argvs, threads, None if model is None else model["files"])

    # Ray names a worker's process "ray::batch_job" while it runs a job (what `ps` shows)
    return (ray.remote(max_retries=3)(batch_prepare), ray.remote(max_retries=0)(batch_job),
            ray.remote(max_retries=0)(batch_pca_fits))


def ray_environment(settings: BatchSettings) -> None:
    """Set what Ray reads when it is imported, before the first ``import ray`` (the command line calls it;
    a library user joining a cluster sets it in the environment).

    Ray clusters authenticate with a token (``ray start`` writes ``~/.ray/auth_token``); a driver joining by
    an explicit ``--address`` sends it only in token mode, and Ray reads the mode when it is imported
    (measured with ray 2.60: without ``RAY_AUTH_MODE=token`` the head answers "InvalidAuthToken"; with it,
    set before the import, the join succeeds). So with an address and a token at hand, ``RAY_AUTH_MODE``
    defaults to ``token``.
    """
    if not settings.address or "RAY_AUTH_MODE" in os.environ:
        return
    if os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH") \
            or Path("~/.ray/auth_token").expanduser().is_file():
        os.environ["RAY_AUTH_MODE"] = "token"


def _check_reachable(address: str) -> None:
    """Refuse a ``HOST:PORT`` nobody listens on at once (Ray itself retries for minutes)."""
    import socket

    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit() or "://" in address:
        return  # "auto" or a ray:// client address: Ray resolves it
    try:
        socket.create_connection((host, int(port)), timeout=10).close()
    except OSError as exc:
        raise InputError(f"--address {address}: cannot join the Ray cluster: nothing answers there ({exc}); "
                         "start it with `ray start --head --port=PORT` or check the address") from None


def _start_ray(settings: BatchSettings) -> int:
    """Start or join Ray; return how many jobs run at once."""
    import logging

    import ray

    common = dict(log_to_driver=False, logging_level=logging.ERROR, configure_logging=True)
    if settings.address:
        _check_reachable(settings.address)
        try:
            ray.init(address=settings.address, **common)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            raise InputError(f"--address {settings.address}: cannot join the Ray cluster: "
                             f"{str(exc).splitlines()[0]} (is it running, and does this machine have the "
                             "cluster's token, ~/.ray/auth_token from the head or RAY_AUTH_TOKEN?)") from None
        cpus = int(ray.cluster_resources().get("CPU", 1))
        return settings.workers or max(1, cpus // settings.threads)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    workers = settings.workers or max(1, cores // settings.threads)
    # address="local": a new embedded instance even when a cluster runs on this machine (a plain ray.init()
    # joins the cluster named in /tmp/ray/ray_current_cluster or RAY_ADDRESS, and then refuses num_cpus)
    ray.init(address="local", num_cpus=workers * settings.threads, include_dashboard=False, **common)
    return workers


def _units(jobs: list[Job], chunk: int) -> list[tuple[Job, ...]]:
    """Tasks to submit: ``pca_fit`` jobs that differ only in the body are grouped, ``chunk`` bodies a task,
    at the place of their first job; every other job is a task of its own."""
    units: list[list[Job]] = []
    open_units: dict[tuple, list[Job]] = {}
    for job in jobs:
        if job.method != "pca_fit" or chunk <= 1:
            units.append([job])
            continue
        i = job.argv.index("--body")
        key = (job.argv[:i] + job.argv[i + 2:], job.build_id)
        unit = open_units.get(key)
        if unit is None or len(unit) >= chunk:
            unit = open_units[key] = []
            units.append(unit)
        unit.append(job)
    return [tuple(u) for u in units]


# --------------------------------------------------------------------------------------------- run
def run_batch(jobs: list[Job], settings: BatchSettings) -> BatchReport:
    """Run ``jobs`` (from :func:`~torchgarment.batch.manifest.load_manifest`) as described in the module
    docstring, and write the summary and the contact sheet (also when interrupted: then of the jobs done).

    Raises:
        InputError: bad settings, another batch writing into the folder, a cluster that cannot be joined.
        KeyboardInterrupt: passed on after the summary is written and Ray is shut down.
    """
    import ray

    settings.validate()
    out = Path(settings.out)
    from torchgarment.io.staging import check_output_folder

    check_output_folder(out)
    created = not out.exists()
    t0 = time.perf_counter()
    with _lock(out):
        done = {}
        if settings.resume:
            for job in jobs:
                rec = _read_record(out / "records" / f"{job.id}.json")
                if rec and rec.get("status") == "ok" and (out / "jobs" / job.id).is_dir():
                    done[job.id] = rec
        todo = [j for j in jobs if j.id not in done]
        workers = 0
        if todo:
            try:
                workers = _start_ray(settings)
            except InputError:  # a cluster that cannot be joined: nothing written (the folder was new)
                if created:
                    shutil.rmtree(out, ignore_errors=True)
                raise
        _remove_stale_stages(out)
        (out / "records").mkdir(exist_ok=True)
        state = _Run(out, settings, jobs, done)
        try:
            if todo:
                state.run(todo, workers)
        finally:
            with contextlib.suppress(Exception):
                state.publish_models()
            if ray.is_initialized():
                ray.shutdown()
            report = state.finish(time.perf_counter() - t0, workers)
    return report


class _Run:
    """The driver's state of one batch run."""

    def __init__(self, out: Path, settings: BatchSettings, jobs: list[Job], done: dict[str, dict]) -> None:
        self.out, self.settings, self.jobs = out, settings, jobs
        self.records: dict[str, dict] = dict(done)
        self.skipped = len(done)
        self.ran = self.retried = 0
        self.models: dict[str, Any] = {}

    # ---- shared work
    def _model_ref(self, job: Job, job_task: Any) -> Any:
        if job.build_id is None:
            return None
        if job.build_id not in self.models:
            import ray

            folder = self.out / "shared" / "pca" / job.build_id
            if (folder / "model.json").is_file():  # built by an earlier run into this folder
                self.models[job.build_id] = ray.put({"code": 0, "files": folder_files(folder), "stderr": ""})
            else:
                build = job_task.options(num_cpus=self.settings.threads, max_retries=3)
                self.models[job.build_id] = build.remote(list(job.build), self.settings.threads, None)
        return self.models[job.build_id]

    def publish_models(self) -> None:
        import ray

        for build_id, ref in self.models.items():
            folder = self.out / "shared" / "pca" / build_id
            if (folder / "model.json").is_file():
                continue
            ready, _ = ray.wait([ref], timeout=0)
            if ready:
                result = ray.get(ref)
                if result["code"] == 0:
                    _publish(folder, result["files"])

    # ---- the loop
    def run(self, todo: list[Job], workers: int) -> None:
        import ray
        from tqdm import tqdm

        prepare_task, job_task, fits_task = _ray_tasks()
        preps: dict[tuple[str, float | None], Any] = {}
        threads = self.settings.threads

        def submit(unit: tuple[Job, ...]) -> Any:
            job = unit[0]
            model = self._model_ref(job, job_task)
            if len(unit) > 1:  # pca_fit jobs on one model: one batched call
                argvs = [list(j.argv) for j in unit]
                return fits_task.options(num_cpus=threads).remote(argvs, threads, model)
            refs = []
            for spec, voxel in job.bodies:
                if (spec, voxel) not in preps:
                    preps[(spec, voxel)] = prepare_task.options(num_cpus=threads).remote(spec, voxel, threads)
                refs.append(preps[(spec, voxel)])
            return job_task.options(num_cpus=threads).remote(list(job.argv), threads, model, *refs)

        pending = deque((unit, 1) for unit in _units(todo, self.settings.chunk))
        running: dict[Any, tuple[tuple[Job, ...], int, float]] = {}
        counts = {"ok": 0, "failed": 0}
        bar = tqdm(total=len(todo), unit="job", desc="batch", file=sys.stderr,
                   disable=not self.settings.progress, dynamic_ncols=True)
        start = time.perf_counter()
        try:
            while pending or running:
                while pending and len(running) < workers:
                    unit, attempt = pending.popleft()
                    running[submit(unit)] = (unit, attempt, time.perf_counter())
                ready, _ = ray.wait(list(running), num_returns=1, timeout=1.0)
                for ref in ready:
                    unit, attempt, t_start = running.pop(ref)
                    try:
                        results = ray.get(ref)
                        results = results if len(unit) > 1 else [results]
                    except Exception as exc:  # the worker died, or an exception escaped the command
                        failure = {"code": -1, "files": {}, "stdout": "",
                                   "seconds": (time.perf_counter() - t_start) / len(unit),
                                   "stderr": f"torchgarment: error: {_ray_error_line(exc)}"}
                        if attempt <= self.settings.retries:  # the whole unit again
                            self.retried += len(unit)
                            pending.appendleft((unit, attempt + 1))
                            continue
                        results = [failure] * len(unit)
                    for job, result in zip(unit, results):
                        if result["code"] != 0 and attempt <= self.settings.retries:
                            self.retried += 1
                            pending.appendleft(((job,), attempt + 1))  # a failed job of a unit runs alone
                            continue
                        status = self._record(job, attempt, result)
                        counts[status] += 1
                        self.ran += 1
                        bar.update(1)
                minutes = (time.perf_counter() - start) / 60.0
                bar.set_postfix(ok=counts["ok"], failed=counts["failed"], running=len(running),
                                per_min=f"{(counts['ok'] + counts['failed']) / max(minutes, 1e-9):.1f}",
                                refresh=True)
        finally:
            bar.close()

    def _record(self, job: Job, attempts: int, result: dict) -> str:
        status = "ok" if result["code"] == 0 else "failed"
        log = (result.get("stdout", "") + result.get("stderr", "")).encode()
        if status == "ok":
            _publish(self.out / "jobs" / job.id, {**result["files"], "job.log": log})
        record = {"job": job.id, "method": job.method, "garment": job.garment, "body": job.body,
                  "status": status, "seconds": round(float(result.get("seconds", 0.0)), 3),
                  "error": "" if status == "ok" else _error_line(result), "attempts": attempts,
                  "folder": f"jobs/{job.id}" if status == "ok" else "", "entry": job.entry,
                  "command": ["torchgarment", *job.argv], "host": result.get("host", ""),
                  "metrics": _scalar_metrics(result["files"]) if status == "ok" else {},
                  "log_tail": "" if status == "ok" else log.decode(errors="replace")[-4000:]}
        write_json(self.out / "records" / f"{job.id}.json", record)
        self.records[job.id] = record
        return status

    # ---- outputs
    def finish(self, seconds: float, workers: int) -> BatchReport:
        rows, metric_names = [], []
        for job in self.jobs:
            rec = self.records.get(job.id)
            if rec is None:
                rec = {"job": job.id, "method": job.method, "garment": job.garment, "body": job.body,
                       "status": "not run", "seconds": "", "error": "", "attempts": 0, "folder": "",
                       "metrics": {}}
            for name in rec.get("metrics", {}):
                if name not in metric_names:
                    metric_names.append(name)
            rows.append(rec)
        table = [{**{c: r.get(c, "") for c in SUMMARY_COLUMNS}, **r.get("metrics", {})} for r in rows]
        summary = self.out / "summary.csv"
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=[*SUMMARY_COLUMNS, *metric_names], restval="")
        writer.writeheader()
        writer.writerows(table)
        from torchgarment.io.atomic import atomic_open

        with atomic_open(summary) as f:
            f.write(buf.getvalue())
        sheets = self._sheets(rows) if self.settings.sheet else []
        ok = sum(r["status"] == "ok" for r in rows)
        failed = sum(r["status"] == "failed" for r in rows)
        report = BatchReport(jobs=len(self.jobs), ran=self.ran, skipped=self.skipped, ok=ok, failed=failed,
                             retried=self.retried, seconds=seconds, workers=workers, rows=table,
                             summary=summary, sheets=sheets)
        settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(self.settings).items()}
        write_json(self.out / "batch.json", {
            "jobs": report.jobs, "ran": report.ran, "skipped": report.skipped, "ok": ok, "failed": failed,
            "not_run": report.jobs - ok - failed, "retried": report.retried, "seconds": round(seconds, 3),
            "workers": workers, "settings": settings})
        return report

    def _sheets(self, rows: list[dict]) -> list[Path]:
        from torchgarment.render import contact_sheet

        method_of = {j.id: j.method for j in self.jobs}
        tiles = []
        for rec in rows:
            folder = self.out / "jobs" / rec["job"]
            picture = None
            if rec["status"] == "ok":
                preferred = METHODS[method_of[rec["job"]]].render
                names = [*preferred, *sorted(p.name for p in folder.glob("*.png"))]
                picture = next((folder / n for n in names if (folder / n).is_file()), None)
            label = f"{rec['method']} {rec['garment']} / {rec['body']}: {rec['status']}"
            tiles.append((picture, label))
        pages = [tiles[i:i + SHEET_TILES] for i in range(0, len(tiles), SHEET_TILES)]
        for old in self.out.glob("contact_sheet*.png"):
            old.unlink(missing_ok=True)
        paths = []
        for n, page in enumerate(pages):
            name = "contact_sheet.png" if len(pages) == 1 else f"contact_sheet_{n + 1:02d}.png"
            paths.append(contact_sheet(page, self.out / name,
                                       title=f"torchgarment batch: {len(rows)} jobs (page {n + 1} of "
                                             f"{len(pages)})"))
        return paths
