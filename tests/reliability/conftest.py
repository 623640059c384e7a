"""Helpers of the reliability tests: run the command line as a user would, and check a refusal."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "torchgarment", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


def _one_line(proc: subprocess.CompletedProcess, needle: str, code: int = 2) -> str:
    assert proc.returncode == code, proc.stderr
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert needle in lines[0], lines[0]
    return lines[0]


@pytest.fixture
def cli() -> Callable[..., subprocess.CompletedProcess]:
    """``cli(*args, cwd=folder)``: ``python -m torchgarment *args`` in ``folder``, output captured."""
    return _run


@pytest.fixture
def one_line() -> Callable[..., str]:
    """``one_line(proc, needle, code=2)``: assert exit ``code`` and exactly one stderr line, without a
    traceback, containing ``needle``; returns the line."""
    return _one_line
