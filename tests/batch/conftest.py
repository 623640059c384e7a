"""Fixtures of the batch tests."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True)
def _ray_workers_at_normal_priority(monkeypatch: pytest.MonkeyPatch) -> None:
    """Ray starts its workers at niceness 15 (``RAY_worker_niceness``), so that they yield to everything
    else on the machine. The test suite runs in two pytest-xdist workers on two cores: beside the other
    worker's tests a niced Ray worker gets almost no CPU, and one six-drape batch took 894 s instead of about
    60 s. The raylet (started by ``ray.init`` in the test process or in a ``torchgarment batch`` subprocess)
    reads this variable."""
    monkeypatch.setenv("RAY_worker_niceness", "0")
