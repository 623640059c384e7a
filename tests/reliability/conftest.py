"""Helpers of the reliability tests: run the command line as a user would, and check a refusal."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

MEMORY_LIMIT_BYTES = 6 * 2**30
"""Address-space limit of every command these tests run (``RLIMIT_AS``): a regression that allocates
terabytes or swaps (a body in centimetres took 22 GB) fails with a MemoryError instead of taking the machine
down. A drape or an anny body fit runs within 4 GiB."""


def _limit_memory() -> None:
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT_BYTES, MEMORY_LIMIT_BYTES))


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "torchgarment", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=300, preexec_fn=_limit_memory if os.name == "posix" else None)


def _one_line(proc: subprocess.CompletedProcess, needle: str, code: int = 2) -> str:
    assert proc.returncode == code, proc.stderr
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert needle in lines[0], lines[0]
    return lines[0]


@pytest.fixture
def cli() -> Callable[..., subprocess.CompletedProcess]:
    """``cli(*args, cwd=folder)``: ``python -m torchgarment *args`` in ``folder``, output captured, within
    :data:`MEMORY_LIMIT_BYTES` of address space and 300 s."""
    return _run


@pytest.fixture
def one_line() -> Callable[..., str]:
    """``one_line(proc, needle, code=2)``: assert exit ``code`` and exactly one stderr line, without a
    traceback, containing ``needle``; returns the line."""
    return _one_line
