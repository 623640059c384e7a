"""Shared test fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def shared_data_dir() -> Path | None:
    """Location of ``../shared/data`` (or ``$TORCHGARMENT_SHARED_DATA``); None when absent."""
    env = os.environ.get("TORCHGARMENT_SHARED_DATA")
    candidates = [Path(env)] if env else []
    candidates.append(REPO_ROOT.parent / "shared" / "data")
    for c in candidates:
        if (c / "garmentcode").is_dir():
            return c
    return None


@pytest.fixture(scope="session")
def garmentcode_dir() -> Path:
    """GarmentCode bodies and patterns from ``../shared/data``; skips the test when absent."""
    d = shared_data_dir()
    if d is None:
        pytest.skip("../shared/data/garmentcode is absent")
    return d / "garmentcode"


@pytest.fixture
def splu_calls(monkeypatch: pytest.MonkeyPatch) -> dict:
    """``{"n": count}`` of SuperLU factorizations (``scipy.sparse.linalg.splu``) made during the test."""
    import scipy.sparse.linalg

    calls = {"n": 0}
    splu = scipy.sparse.linalg.splu

    def counting(*a, **kw):
        calls["n"] += 1
        return splu(*a, **kw)

    monkeypatch.setattr(scipy.sparse.linalg, "splu", counting)
    return calls


@pytest.fixture
def one_torch_thread():
    """Run the test with one torch thread (reproducible reductions), restoring the count afterwards."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def pytest_configure(config: pytest.Config) -> None:
    """Under pytest-xdist (the README's test command runs two workers, one per core) every worker runs torch
    on one thread, and so do the subprocesses its tests start: two workers of two threads each would
    oversubscribe the two cores, which slows torch several times."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        os.environ["OMP_NUM_THREADS"] = "1"
        import torch

        torch.set_num_threads(1)
