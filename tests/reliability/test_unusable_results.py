"""Issue 17: a drape whose result nobody can use (far from equilibrium: ``--max-iterations 0`` left 954 N of
residual force on a 0.85 N skirt) exits 3 with one line and writes nothing; ``--allow-unconverged`` keeps it
for studies and says so on stderr; the reasons are computed by ``sim.drape.unusable_reason``."""

from __future__ import annotations

from dataclasses import replace

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
