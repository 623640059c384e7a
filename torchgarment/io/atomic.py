"""Atomic file writes: write to a temporary file in the same folder, then rename.

Nothing half-written is ever left behind under the final name.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import time
from pathlib import Path
from typing import IO, Iterator


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` if the block succeeds.

    The temporary name keeps the final suffix so that libraries choosing a format by extension
    (trimesh, matplotlib, ezdxf) write the right format.

    Args:
        path: final destination.

    Yields:
        A temporary path in the same directory. It is removed if the block raises.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_path, 0o666 & ~umask)  # mkstemp creates 0600; give the file ordinary permissions
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


ORPHAN_AGE_S = 3600.0
"""Age in seconds after which :func:`remove_orphan_temporaries` takes a temporary file for an orphan (a writer
killed before its rename); younger ones may belong to a writer still at work."""


def remove_orphan_temporaries(folder: str | os.PathLike, max_age_s: float = ORPHAN_AGE_S) -> int:
    """Delete the temporaries :func:`atomic_path` left in ``folder`` (``.<stem>.*.tmp<suffix>``) that are
    older than ``max_age_s`` seconds: a process killed while writing (``kill -9``) never renames or removes
    its temporary. Caches call it when they store an entry.

    Returns:
        How many files were removed (files another process removes first are skipped).
    """
    folder = Path(folder)
    if not folder.is_dir():
        return 0
    now, removed = time.time(), 0
    for p in folder.glob(".*.tmp*"):
        with contextlib.suppress(OSError):
            if p.is_file() and now - p.stat().st_mtime > max_age_s:
                p.unlink()
                removed += 1
    return removed


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w", encoding: str | None = "utf-8") -> Iterator[IO]:
    """Open a file for writing atomically (see :func:`atomic_path`)."""
    if "b" in mode:
        encoding = None
    with atomic_path(path) as tmp:
        with open(tmp, mode, encoding=encoding) as f:
            yield f
