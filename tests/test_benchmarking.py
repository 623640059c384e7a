"""The benches' machine record (torchgarment.benchmarking): the reference grid, the speed reference and the
JSON block."""

from __future__ import annotations

import json
import math
import time

import pytest
import torch

from torchgarment.benchmarking import (
    MachineWatch,
    _incidence,
    _spring_pass,
    load_average,
    machine_record,
    reference_grid,
    speed_reference,
)
from torchgarment.errors import InputError
from torchgarment.sim import PlanarSprings


def test_reference_grid_is_a_triangulated_grid_in_tension() -> None:
    edges, p, x = reference_grid(100)  # 10 x 10
    n = 10
    assert x.shape == (n * n, 3) and p.shape == (n * n, 2)
    # horizontal + vertical + one diagonal per cell
    assert edges.shape[0] == 2 * n * (n - 1) + (n - 1) ** 2
    assert len({tuple(e) for e in edges.tolist()}) == edges.shape[0]
    i, j = edges[:, 0], edges[:, 1]
    rest = torch.linalg.vector_norm(p[i] - p[j], dim=1)
    assert bool((torch.linalg.vector_norm(x[i] - x[j], dim=1) > rest).all())  # every edge stretched
    assert torch.equal(reference_grid(100)[2], x)  # a fixed seed
    with pytest.raises(InputError):
        reference_grid(3)


def test_reference_spring_pass_is_the_library_springs_energy_and_gradient() -> None:
    """The reference pass (plain torch) computes what PlanarSprings does: the same workload."""
    edges, p, x = reference_grid(400)
    springs = PlanarSprings(edges, p, stiffness=25.0)
    D, S = _incidence(edges, x.shape[0])
    rest = torch.linalg.vector_norm(D @ p, dim=1)
    E, g = _spring_pass(x, D, S, rest, 25.0 / rest)
    E_ref, g_ref = springs.value_and_grad(x)
    torch.testing.assert_close(E, E_ref, rtol=1e-12, atol=0.0)
    torch.testing.assert_close(g, g_ref, rtol=1e-10, atol=1e-12)


def test_speed_reference_times_both_workloads() -> None:
    r = speed_reference(spring_vertices=400, factor_vertices=100, spring_repeats=3, factor_repeats=1)
    assert set(r) == {"spring_pass_ms", "spring_pass_min_ms", "spring_vertices", "factorization_ms",
                      "factorization_min_ms", "factor_vertices", "torch_threads"}
    assert r["spring_vertices"] == 400 and r["factor_vertices"] == 100
    for key in ("spring_pass_ms", "spring_pass_min_ms", "factorization_ms", "factorization_min_ms"):
        assert math.isfinite(r[key]) and r[key] > 0
    assert r["spring_pass_min_ms"] <= r["spring_pass_ms"]
    assert r["torch_threads"] == torch.get_num_threads()
    with pytest.raises(InputError):
        speed_reference(spring_repeats=0)


def test_machine_watch_block_is_json_and_described() -> None:
    a = load_average()
    assert len(a) == 3 and all(isinstance(v, float) for v in a)
    rec = machine_record()
    assert rec["cpus"] >= 1 and rec["torch"] == torch.__version__ and len(rec["load_average"]) == 3
    watch = MachineWatch(reference=False)
    t = time.perf_counter()
    while time.perf_counter() - t < 0.2:  # busy on this thread: CPU time accrues (less under load)
        pass
    block = watch.finish()
    assert block["speed_reference"] == {"start": None, "end": None}
    assert block["wall_seconds"] >= 0.2 and block["cpu_seconds"] > 0.0
    assert block["cores_used"] == pytest.approx(block["cpu_seconds"] / block["wall_seconds"])
    assert block["cores_used"] <= rec["cpus"] + 0.1
    assert len(block["load_average_end"]) == 3
    json.dumps(block)
    line = MachineWatch.describe(block)
    assert "load average" in line and "speed reference" not in line and "cores)" in line
    block = MachineWatch().finish()  # the default sizes: about half a second at each end
    json.dumps(block)
    for end in ("start", "end"):
        assert block["speed_reference"][end]["spring_vertices"] == 173 * 173
    assert "spring pass" in MachineWatch.describe(block)
