"""A whole size run (issue 18, section 4): drape the base once, adjust the pattern to every target body.

:func:`grade` takes a pattern made for ``base_body`` and a dict of target bodies (size name -> body) and, per
size, prepares and optimizes the adjustment (:func:`torchgarment.adjust.pipeline.prepare` with the base drape
computed once, then :func:`~torchgarment.adjust.pipeline.optimize`) and measures the fit at every
construction line (:mod:`torchgarment.adjust.fit`: ease, pattern change, body change, placement).

With an output folder it writes, per size, ``DIR/<size>/`` with what the ``writer`` writes (the command
passes ``torchgarment adjust``'s ``write_outputs``; default :func:`write_pattern_files`) plus ``fit.json``
(the size's construction-line rows), each size staged (:func:`torchgarment.io.staging.staged_output`: a size
folder is published whole or not at all); then, for the whole run, ``grade.dxf`` (every size of every piece,
:func:`~torchgarment.pattern.dxf.save_graded_dxf`), ``grade_nest.png``
(:func:`~torchgarment.pattern.plot.plot_grade_nest`), ``grade.csv`` (:data:`CSV_COLUMNS`, one row per size
and line, the base size first) and ``metrics.json`` (per size and the acceptance figures). ``resume=True``
skips sizes whose folder is complete (:func:`size_complete`). A size that fails is reported (one line on
stderr) and the others go on; :attr:`GradeResult.failed` lists them.

Lengths are in metres.
"""

from __future__ import annotations

import csv
import io
import json
import math
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from torchgarment.adjust.fit import fit_rows, measure_fit
from torchgarment.adjust.pipeline import AdjustSettings, base_drape_settings, optimize, prepare
from torchgarment.errors import InputError
from torchgarment.io.jsonfile import write_json

if TYPE_CHECKING:
    from collections.abc import Callable

    from torchgarment.adjust.pipeline import AdjustResult
    from torchgarment.body import Body
    from torchgarment.pattern.spec import SewingPattern
    from torchgarment.sim.drape import DrapeResult

__all__ = [
    "CSV_COLUMNS",
    "PATTERN_SIZE_FILES",
    "SIZE_FILES",
    "GradeResult",
    "SizeOutcome",
    "acceptance_summary",
    "adjust_to_target",
    "format_table",
    "grade",
    "size_complete",
    "write_pattern_files",
]

CSV_COLUMNS = ("size", "line", "pattern_girth_m", "body_girth_m", "ease_m", "ease_change_m",
               "pattern_change_m", "body_change_m", "chart_change_m", "placement_change_m")
"""Columns of ``grade.csv`` and of the printed table (changes against the base size, metres)."""
SIZE_FILES = ("pattern.json", "pattern.svg", "pattern.dxf", "garment_base.obj", "garment_target.obj",
              "target_before.png", "target_after.png", "overlay.png", "metrics.json", "fit.json")
"""The files of a finished size folder of ``torchgarment grade`` (what ``torchgarment adjust`` writes, its
``write_outputs`` passed as ``writer``, plus ``fit.json``)."""
PATTERN_SIZE_FILES = ("pattern.json", "pattern.svg", "pattern.dxf", "metrics.json", "fit.json")
"""The files of a finished size folder without a ``writer`` (:func:`write_pattern_files`, ``fit.json``)."""
TOLERANCE_M = 0.01
"""Pass tolerance of the fit-preservation acceptance (issue 18, section 2)."""


# ---------------------------------------------------------------------------------------------- fit lines


# ---------------------------------------------------------------------------------------------- results
@dataclass
class SizeOutcome:
    """What happened to one size of a :func:`grade` run.

    Attributes:
        size: the size name. status: ``"done"``, ``"resumed"`` (a finished folder was found) or ``"failed"``.
        pattern: the adjusted pattern (None when failed). rows: its construction-line rows (see
            :func:`fit_rows`), ``size`` included. metrics: the adjustment's metrics (``metrics.json`` of the
            size; read back when resumed). seconds: wall time of the size. error: one line, when failed.
    """

    size: str
    status: str
    pattern: SewingPattern | None = None
    rows: list[dict] = field(default_factory=list)
    metrics: dict = field(default_factory=dict)
    seconds: float = 0.0
    error: str | None = None


@dataclass
class GradeResult:
    """Outcome of :func:`grade`.

    Attributes:
        base_size: the base size's name. base_pattern: the input pattern.
        sizes: size name -> :class:`SizeOutcome`, in the order given.
        base_rows: the base's own rows (changes 0), the first rows of ``grade.csv``.
        metrics: what ``metrics.json`` holds (per size, ``acceptance`` of :func:`acceptance_summary`,
            ``failed``, timings).
    """

    base_size: str
    base_pattern: SewingPattern
    sizes: dict[str, SizeOutcome]
    base_rows: list[dict]
    metrics: dict

    @property
    def failed(self) -> list[str]:
        """The sizes that failed, in order."""
        return [k for k, s in self.sizes.items() if s.status == "failed"]

    @property
    def rows(self) -> list[dict]:
        """Every row of ``grade.csv``: the base's, then each finished size's."""
        return list(self.base_rows) + [r for s in self.sizes.values() for r in s.rows]


# ---------------------------------------------------------------------------------------------- helpers
def size_complete(folder: Path, files: tuple[str, ...] = SIZE_FILES) -> bool:
    """Whether a size folder holds every one of ``files`` (a finished size)."""
    return all((folder / name).is_file() for name in files)


def write_pattern_files(result: AdjustResult, stage: Path, base_body: Body, target_body: Body,
                        title: str) -> None:
    """The default per-size writer of :func:`grade`: ``pattern.json/.svg/.dxf`` and ``metrics.json`` (the
    command passes ``torchgarment adjust``'s ``write_outputs``, which adds garments and renders)."""
    from torchgarment.pattern.dxf import save_dxf
    from torchgarment.pattern.garmentcode import save_pattern
    from torchgarment.pattern.svg import save_svg

    save_pattern(stage / "pattern.json", result.pattern)
    save_svg(stage / "pattern.svg", result.pattern)
    save_dxf(stage / "pattern.dxf", result.pattern)
    write_json(stage / "metrics.json", _json_safe(result.metrics))


def _json_safe(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, (bool, int, float, str)) or v is None:
        return v
    return str(v)


def _num(v: Any) -> float:
    return math.nan if v is None else float(v)


def drape_base(pattern: SewingPattern, base_body: Body, settings: AdjustSettings, *,
               dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> DrapeResult:
    """The base drape :func:`prepare` would compute (same drape settings), computed once for every size."""
    from torchgarment.sim.drape import drape

    return drape(pattern, base_body, settings=base_drape_settings(settings), dtype=dtype, device=device)


def adjust_to_target(pattern: SewingPattern, base_body: Body, target_body: Body, settings: AdjustSettings,
                     base: DrapeResult | None, *, dtype: torch.dtype = torch.float64,
                     device: torch.device | str | None = None) -> AdjustResult:
    """Adjust ``pattern`` to one target body from an already computed base drape (steps 2-4 of
    :func:`torchgarment.adjust.pipeline.adjust`); ``base=None`` drapes again."""
    t0 = time.perf_counter()
    setup = prepare(pattern, base_body, target_body, settings, dtype=dtype, device=device, base=base)
    result = optimize(setup, progress=False)
    result.metrics["total_seconds"] = time.perf_counter() - t0
    return result


def acceptance_summary(rows: list[dict], tolerance_m: float = TOLERANCE_M) -> dict:
    """The acceptance figures of section 2 over rows of :func:`fit_rows` (the base's rows excluded by the
    caller): the largest |ease change|, |pattern change - body change| and |placement change| (m), the
    lines passed, and whether all pass."""
    def worst(f: Any) -> float:
        vals = [abs(f(r)) for r in rows if math.isfinite(f(r))]
        return max(vals) if vals else math.nan

    passed = sum(bool(r.get("pass")) for r in rows)
    return {"tolerance_m": tolerance_m, "lines": len(rows), "lines_passed": passed,
            "pass": bool(rows) and passed == len(rows),
            "max_abs_ease_change_m": worst(lambda r: _num(r["ease_change_m"])),
            "max_abs_pattern_minus_body_change_m": worst(
                lambda r: _num(r["pattern_change_m"]) - _num(r["body_change_m"])),
            "max_abs_placement_change_m": worst(lambda r: _num(r["placement_change_m"]))}


def format_table(rows: list[dict]) -> str:
    """The rows as a fixed-width text table of :data:`CSV_COLUMNS` (metres, 4 decimals) plus ``pass``."""
    cols = [*CSV_COLUMNS, "pass"]
    cells = [[c for c in cols]]
    for r in rows:
        line = []
        for c in cols:
            v = r.get(c, "")
            if c == "pass":
                line.append("" if v in ("", None) else ("yes" if v else "NO"))
            elif isinstance(v, float) or v is None:
                line.append("-" if v is None or not math.isfinite(v) else f"{v:+.4f}" if "change" in c
                            else f"{v:.4f}")
            else:
                line.append(str(v))
        cells.append(line)
    widths = [max(len(row[i]) for row in cells) for i in range(len(cols))]
    return "\n".join("  ".join(s.rjust(w) for s, w in zip(row, widths, strict=True)) for row in cells)


def _write_csv(path: Path, rows: list[dict]) -> None:
    from torchgarment.io.atomic import atomic_open

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for r in rows:
        w.writerow(["" if r.get(c) is None or (isinstance(r.get(c), float) and not math.isfinite(r[c]))
                    else (repr(float(r[c])) if isinstance(r[c], float) else r[c]) for c in CSV_COLUMNS])
    with atomic_open(path) as f:
        f.write(buf.getvalue())


def _fits_dict(fits: dict) -> dict[str, dict]:
    return {k: asdict(v) for k, v in fits.items()}


def _base_rows(base_fit: dict[str, dict], base_size: str) -> list[dict]:
    rows = []
    for line, f in base_fit.items():
        rows.append({"size": base_size, "line": line, "pattern_girth_m": f["pattern_girth_m"],
                     "body_girth_m": f["body_girth_m"], "ease_m": f["ease_m"], "ease_change_m": 0.0,
                     "pattern_change_m": 0.0, "body_change_m": 0.0, "chart_change_m": 0.0,
                     "placement_change_m": 0.0})
    return rows


# ---------------------------------------------------------------------------------------------- grade
def grade(
    pattern: SewingPattern,
    base_body: Body,
    targets: dict[str, Body],
    settings: AdjustSettings,
    out: Path | None,
    resume: bool = False,
    progress: bool = True,
    *,
    base_size: str = "base",
    chart_changes: dict[str, dict[str, float]] | None = None,
    writer: Callable[[AdjustResult, Path, Body, Body, str], None] | None = None,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> GradeResult:
    """Adjust ``pattern`` (made for ``base_body``) to every target body (see the module docstring).

    Args:
        pattern: the base :class:`SewingPattern`.
        base_body: the body the pattern fits.
        targets: size name -> target body (same topology as ``base_body``), in the order to run and write.
        settings: :class:`AdjustSettings` of every adjustment.
        out: output folder (``DIR/<size>/...`` and the run's files); None = write nothing.
        resume: skip sizes whose folder under ``out`` is complete (:func:`size_complete`).
        progress: tqdm bar over the sizes on stderr.
        base_size: the base's name in the tables, the graded DXF (``Sample Size``) and the nest.
        chart_changes: size name -> (line -> the chart's girth difference to the base, m), printed beside
            the measured changes; None = none.
        writer: ``writer(result, stage, base_body, target_body, title)`` writes a size's files into its
            staging folder; None = :func:`write_pattern_files` (then a size is finished when its folder
            holds :data:`PATTERN_SIZE_FILES`, else :data:`SIZE_FILES`). ``torchgarment grade`` passes
            :func:`torchgarment.adjust.cli.write_outputs`.
        dtype, device: of the computation.

    Returns:
        The :class:`GradeResult`.

    Raises:
        InputError: no targets, a size named like the base, a size name unusable as a folder name, or
            ``resume`` without ``out``.
    """
    if not targets:
        raise InputError("grade: give at least one target size or body")
    if resume and out is None:
        raise InputError("grade: resume needs an output folder")
    for name in targets:
        if name == base_size:
            raise InputError(f"grade: target {name!r} has the base's name; the base is not graded to itself")
        if not name or name in (".", "..") or any(c in name for c in "/\\"):
            raise InputError(f"grade: size name {name!r} cannot name a folder")
    settings.validate()
    t_start = time.perf_counter()
    out = None if out is None else Path(out)
    chart_changes = chart_changes or {}
    outcomes: dict[str, SizeOutcome] = {}
    base: DrapeResult | None = None
    base_fit: dict[str, dict] | None = None
    base_seconds = 0.0

    files = SIZE_FILES if writer is not None else PATTERN_SIZE_FILES
    writer = writer if writer is not None else write_pattern_files
    todo = [k for k in targets if not (resume and out is not None and size_complete(out / k, files))]
    for k in targets:
        if k not in todo:
            folder = out / k
            from torchgarment.pattern.garmentcode import load_pattern

            fit = json.loads((folder / "fit.json").read_text(encoding="utf-8"))
            outcomes[k] = SizeOutcome(k, "resumed", load_pattern(folder / "pattern.json"), fit["rows"],
                                      json.loads((folder / "metrics.json").read_text(encoding="utf-8")),
                                      float(fit.get("seconds", 0.0)))
            base_fit = base_fit or fit["base"]
    if todo:
        t0 = time.perf_counter()
        base = drape_base(pattern, base_body, settings, dtype=dtype, device=device)
        base_seconds = time.perf_counter() - t0

    from tqdm.auto import tqdm

    bar = tqdm(total=len(targets), initial=len(targets) - len(todo), desc="grade", unit="size",
               disable=not progress, file=sys.stderr)
    try:
        for k in todo:
            bar.set_postfix_str(f"size {k}")
            t0 = time.perf_counter()
            try:
                result = adjust_to_target(pattern, base_body, targets[k], settings, base, dtype=dtype,
                                          device=device)
                mesh_base = result.mesh_base
                fit_base = measure_fit(pattern, mesh_base, mesh_base.x, base_body)
                fit_target = measure_fit(result.pattern, result.mesh_target, result.mesh_target.x, targets[k])
                rows = [{"size": k, **r} for r in fit_rows(fit_base, fit_target, chart_changes.get(k),
                                                           tolerance_m=TOLERANCE_M)]
                seconds = time.perf_counter() - t0
                if out is not None:
                    from torchgarment.io.staging import staged_output

                    with staged_output(out / k) as stage:
                        writer(result, stage, base_body, targets[k], f"{pattern.name}: {base_size} -> {k}")
                        write_json(stage / "fit.json", _json_safe({
                            "size": k, "base_size": base_size, "base": _fits_dict(fit_base),
                            "target": _fits_dict(fit_target), "rows": rows, "seconds": seconds}))
                base_fit = base_fit or _fits_dict(fit_base)
                outcomes[k] = SizeOutcome(k, "done", result.pattern, rows, dict(result.metrics), seconds)
            except Exception as e:  # noqa: BLE001 - a failing size is reported and the others go on
                msg = (str(e).splitlines() or [""])[0]
                outcomes[k] = SizeOutcome(k, "failed", seconds=time.perf_counter() - t0,
                                          error=f"{type(e).__name__}: {msg}")
                bar.write(f"grade: size {k} failed: {outcomes[k].error}", file=sys.stderr)
            bar.update(1)
    finally:
        bar.close()
    outcomes = {k: outcomes[k] for k in targets}
    base_rows = _base_rows(base_fit, base_size) if base_fit else []
    size_rows = [r for s in outcomes.values() for r in s.rows]
    metrics = {
        "garment": pattern.name,
        "base_size": base_size,
        "sizes": list(targets),
        "failed": {k: s.error for k, s in outcomes.items() if s.status == "failed"},
        "acceptance": acceptance_summary(size_rows),
        "per_size": {k: {"status": s.status, "seconds": s.seconds, "error": s.error,
                         "acceptance": acceptance_summary(s.rows) if s.status != "failed" else None,
                         "rows": s.rows,
                         **{m: s.metrics.get(m) for m in (
                             "objective_base", "objective_initial", "objective_final", "reduction_percent",
                             "iterations", "max_boundary_displacement_mm", "support_force_n",
                             "support_max_displacement_mm", "total_seconds") if m in s.metrics}}
                     for k, s in outcomes.items()},
        "base_drape_once": base is not None,
        "base_drape_seconds": base_seconds,
        "seconds_per_size": {k: s.seconds for k, s in outcomes.items()},
        "total_seconds": time.perf_counter() - t_start,
    }
    result = GradeResult(base_size, pattern, outcomes, base_rows, metrics)
    if out is not None:
        _write_run_outputs(result, out)
    return result


def _write_run_outputs(result: GradeResult, out: Path) -> None:
    """``grade.dxf``, ``grade_nest.png``, ``grade.csv`` and ``metrics.json`` of a run (staged)."""
    from torchgarment.io.staging import staged_output
    from torchgarment.pattern.dxf import save_graded_dxf
    from torchgarment.pattern.plot import plot_grade_nest

    patterns = {result.base_size: result.base_pattern}
    patterns.update({k: s.pattern for k, s in result.sizes.items() if s.pattern is not None})
    order = _size_order(list(patterns), result.base_size)
    patterns = {k: patterns[k] for k in order}
    with staged_output(out) as stage:
        save_graded_dxf(stage / "grade.dxf", patterns, sample_size=result.base_size,
                        style=result.base_pattern.name)
        plot_grade_nest(patterns, stage / "grade_nest.png", base=result.base_size,
                        title=f"{result.base_pattern.name}: grade nest (base {result.base_size})")
        _write_csv(stage / "grade.csv", result.rows)
        write_json(stage / "metrics.json", _json_safe(result.metrics))


def _size_order(names: list[str], base: str) -> list[str]:
    """Chart sizes in chart order (the base among them); otherwise the given order with the base first."""
    from torchgarment.body.size_chart import list_sizes

    chart = list_sizes()
    if all(n in chart for n in names):
        return sorted(names, key=chart.index)
    return [base] + [n for n in names if n != base]
