"""Issue 17: a drape whose result nobody can use (far from equilibrium: ``--max-iterations 0`` left 954 N of
residual force on a 0.85 N skirt) exits 3 with one line and writes nothing; ``--allow-unconverged`` keeps it
for studies and says so on stderr; the reasons are computed by ``sim.drape.unusable_reason``. A single
unstitched panel (which drape wrote at 2e12 m) is not given its own outline as a support, falls, and the
settle stops once it has fallen; ``adjust`` refuses an unusable base drape before optimizing."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from torchgarment.sim.drape import unusable_reason

COARSE = ("--edge-length", "0.08", "--voxel", "0.01", "--no-progress")


def test_unconverged_drape_exits_3_and_writes_nothing(tmp_path, cli, one_line):
    args = ("drape", "--pattern", "straight_skirt", "--size", "12", "--body", "12", *COARSE,
            "--max-iterations", "0")
    line = one_line(cli(*args, "--out", "o", cwd=tmp_path), "unusable: far from equilibrium", code=3)
    assert "--allow-unconverged" in line
    assert not (tmp_path / "o").exists()
    kept = cli(*args, "--out", "k", "--allow-unconverged", cwd=tmp_path)
    assert kept.returncode == 0, kept.stderr
    assert "written although unusable" in kept.stderr
    assert (tmp_path / "k" / "metrics.json").is_file()


def test_unusable_reason():
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft
    from torchgarment.sim.drape import DrapeSettings, drape

    body = Body.from_size("12")
    r = drape(draft("straight_skirt", chart_row("12")), body,
              settings=DrapeSettings(edge_length=0.08, voxel_size=0.01))
    assert r.metrics["converged"] and unusable_reason(r, body.vertices) is None
    fell = replace(r, x=r.x - torch.tensor([0.0, 9.3, 0.0], dtype=r.x.dtype))
    assert "outside the body's bounding box" in unusable_reason(fell, body.vertices)
    nan = replace(r, x=torch.full_like(r.x, float("nan")))
    assert "non-finite" in unusable_reason(nan, body.vertices)
    heavy = replace(r, metrics={**r.metrics, "converged": False, "residual": 10 * r.metrics["weight_n"]})
    assert "far from equilibrium" in unusable_reason(heavy, body.vertices)
    budget = replace(r, metrics={**r.metrics, "converged": False, "residual": 0.5 * r.metrics["weight_n"]})
    assert unusable_reason(budget, body.vertices) is None


@pytest.fixture(scope="module")
def single_panel(tmp_path_factory):
    """The straight skirt's front panel alone, no stitches, no support: (GarmentCode file, pattern)."""
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.garmentcode import save_pattern
    from torchgarment.pattern.library import draft

    skirt = draft("straight_skirt", chart_row("12"))
    single = replace(skirt, panels={"skirt_front": skirt.panels["skirt_front"]}, stitches=[], support=())
    path = tmp_path_factory.mktemp("single") / "single.json"
    save_pattern(path, single)
    return path, single


def test_a_single_unstitched_panel_is_not_held_by_its_outline_and_its_fall_is_stopped(single_panel):
    from torchgarment.body import Body
    from torchgarment.pattern.support import propose_support
    from torchgarment.sim.drape import DrapeSettings, drape

    _, single = single_panel
    assert propose_support(single) == ()  # its outline is a closed free loop, but not round the body
    body = Body.from_size("12")
    r = drape(single, body, settings=DrapeSettings(edge_length=0.08, voxel_size=0.01))
    assert r.metrics["message"] == "stopped by callback" and not r.metrics["converged"]
    assert "fell or exploded" in unusable_reason(r, body.vertices)
    assert r.metrics["iterations"] < 1000  # measured: 390 (the budget is 1500)


def test_adjust_refuses_an_unusable_base_drape(single_panel, tmp_path, cli, one_line):
    path, _ = single_panel
    args = ("adjust", "--pattern", str(path), "--base-size", "12", "--target-size", "14", *COARSE)
    line = one_line(cli(*args, "--out", "o", cwd=tmp_path), "the base drape on size 12 is unusable", code=3)
    assert "fell or exploded" in line and "--allow-unconverged" in line
    assert not (tmp_path / "o").exists()
