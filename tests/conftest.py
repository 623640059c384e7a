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


#: The test files with the most test time, heaviest first: run before all others. pytest-xdist hands whole
#: files (``--dist loadfile``) to the worker that is free, in collection order, so a long file collected late
#: (``test_cli.py`` is collected last) keeps one worker busy while the other has nothing left. Measured with
#: ``python -m pytest -q -n 2 --dist loadfile --durations=0`` (2026-11-27): 249.6 / 87.3 / 75.9 / 66.2 s of
#: the suite's 1,134 s of test time. Replaying the scheduling with the per-file times gives 598 s in
#: collection order (that run took 608 s) and 569 s with these four first; the floor is 567 s.
LONGEST_FILES_FIRST = (
    "tests/batch/test_runner.py",
    "tests/reliability/test_body_reach.py",
    "tests/adjust/test_grade.py",
    "tests/test_cli.py",
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Move the tests of :data:`LONGEST_FILES_FIRST` to the front, in that order; every file's tests stay
    together and in their order, and the other files keep the collection order (a stable sort)."""
    rank = {path: i for i, path in enumerate(LONGEST_FILES_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::", 1)[0], len(rank)))
