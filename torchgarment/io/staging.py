"""Staged output folders: a command writes into a hidden temporary folder and publishes on success.

A command that fails half-way leaves nothing in its output folder; one that succeeds moves its files into
place as one transaction of renames (:func:`_publish`): if a move fails half-way, the folder keeps its whole
old set of files (issue 17: it used to end with two new files and two old ones).
"""

from __future__ import annotations

import contextlib
import glob
import os
import re
import shutil
import tempfile
import time
from pathlib import Path
from typing import Iterator

from torchgarment.errors import InputError
from torchgarment.io.atomic import ORPHAN_AGE_S

__all__ = ["check_output_folder", "staged_output"]


def check_output_folder(out_dir: str | os.PathLike) -> Path:
    """The output folder ``out_dir`` as a Path, checked before any work is done.

    Raises:
        InputError: the name is empty (``--out ""`` would write into the current folder), or a file (not a
            folder) of that name exists.
    """
    if str(out_dir).strip() == "":
        raise InputError("the output folder name is empty: give --out DIR")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"the output folder {out} exists and is not a folder")
    return out


def remove_orphan_stages(out_dir: str | os.PathLike, max_age_s: float = ORPHAN_AGE_S) -> int:
    """Delete the staging folders of ``out_dir`` (``.<name>.staging-*`` beside it) older than ``max_age_s``
    seconds: a command killed while writing (``kill -9``) never removes its stage, and a stage lives only
    while the outputs are written (seconds), so an hour-old one has no writer. :func:`staged_output` calls
    it.

    Returns:
        How many folders were removed.
    """
    out = Path(out_dir)
    if not out.parent.is_dir():
        return 0
    now, removed = time.time(), 0
    for stage in out.parent.glob(f".{glob.escape(out.name)}.staging-*"):
        with contextlib.suppress(OSError):
            if stage.is_dir() and now - stage.stat().st_mtime > max_age_s:
                shutil.rmtree(stage)
                removed += 1
    return removed


@contextlib.contextmanager
def staged_output(out_dir: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary folder beside ``out_dir``; on success move its files into ``out_dir``.

    Args:
        out_dir: the final output folder (created if missing; existing files of the same name are replaced).

    Yields:
        The staging folder. It is removed whether the block succeeds or fails.

    Raises:
        InputError: see :func:`check_output_folder`; or, after the block, an output name that is a folder in
            ``out_dir`` (checked for every file before any is moved, so ``out_dir`` is not left half old, half
            new by it).
    """
    out = check_output_folder(out_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    remove_orphan_stages(out)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-", dir=out.parent))
    try:
        try:
            yield stage
        except OSError as exc:  # a write into the stage failed: name the output, not the hidden stage
            raise OSError(_public(str(exc), stage, out)) from exc
        out = check_output_folder(out_dir)
        files = [src for src in sorted(stage.rglob("*")) if src.is_file()]
        clash = [out / f.relative_to(stage) for f in files if (out / f.relative_to(stage)).is_dir()]
        if clash:
            raise InputError(f"{clash[0]} is a folder where an output file goes: move it away and run again")
        out.mkdir(parents=True, exist_ok=True)
        _publish(stage, files, out)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


_TEMPORARY_NAME = re.compile(r"\.([^/\\\s'\"]+?)\.[A-Za-z0-9_]+\.tmp(\.[A-Za-z0-9]+)?")
"""An :func:`~torchgarment.io.atomic.atomic_path` temporary name: ``.<stem>.<random>.tmp<suffix>``."""


def _public(message: str, stage: Path, out: Path) -> str:
    """``message`` with the staging folder's path, and atomic writers' temporary names (``.<stem>.<random>
    .tmp<suffix>``), replaced by the output paths a user knows."""
    message = message.replace(str(stage), str(out))
    return _TEMPORARY_NAME.sub(lambda m: m.group(1) + (m.group(2) or ""), message)


def _publish(stage: Path, files: list[Path], out: Path) -> None:
    """Move the staged ``files`` into ``out`` as one transaction: every file the new set replaces is first
    moved aside (into a hidden folder beside ``out``), then the new file moved in; if any move fails, the new
    files already moved are removed and the old ones put back, so ``out`` holds the whole old set or the whole
    new set (files of ``out`` that the new set does not name are left alone). Renames only, on one file
    system."""
    backup = Path(tempfile.mkdtemp(prefix=f".{out.name}.previous-", dir=out.parent))
    moved: list[Path] = []
    saved: list[tuple[Path, Path]] = []
    try:
        for src in files:
            rel = src.relative_to(stage)
            dst = out / rel
            if dst.exists():
                aside = backup / rel
                aside.parent.mkdir(parents=True, exist_ok=True)
                os.replace(dst, aside)
                saved.append((aside, dst))
            dst.parent.mkdir(parents=True, exist_ok=True)
            os.replace(src, dst)
            moved.append(dst)
    except BaseException:
        for dst in moved:
            with contextlib.suppress(OSError):
                dst.unlink()
        for aside, dst in reversed(saved):
            with contextlib.suppress(OSError):
                os.replace(aside, dst)
        raise
    finally:
        shutil.rmtree(backup, ignore_errors=True)
