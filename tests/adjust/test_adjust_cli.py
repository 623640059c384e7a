"""The ``torchgarment adjust`` subcommand (torchgarment.adjust.cli): outputs and bad input."""

from __future__ import annotations

import argparse
import json

import pytest
import torch

from torchgarment.adjust.cli import add_adjust_parser, cmd_adjust
from torchgarment.errors import InputError


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="torchgarment")
    add_adjust_parser(parser.add_subparsers(dest="command"))
    return parser.parse_args(["adjust", *argv])


def test_adjust_writes_every_output(tmp_path, capsys):
    out = tmp_path / "out"
    args = _parse(["--garment", "straight_skirt", "--base-size", "12", "--target-size", "20", "--out",
                   str(out),
                   "--iterations", "4", "--exact-interval", "2", "--edge-length", "0.05", "--voxel", "0.01",
                   "--log-dir", str(tmp_path / "tb"), "--no-progress"])
    (out / "checkpoint").mkdir(parents=True)
    (out / "checkpoint" / "adjust.pt").write_bytes(b"a stale checkpoint of an interrupted earlier run")
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert args.func(args) == 0
    finally:
        torch.set_num_threads(n)
    for name in ("pattern.json", "pattern.svg", "pattern.dxf", "garment_base.obj", "garment_target.obj",
                 "target_before.png", "target_after.png", "overlay.png", "metrics.json"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    m = json.loads((out / "metrics.json").read_text())
    for key in ("objective_initial", "objective_final", "reduction_percent", "terms",
                "max_boundary_displacement_mm",
                "iterations", "seconds", "seconds_per_iteration", "closure_calls"):
        assert key in m, key
    assert m["iterations"] == 4 and m["objective_final"] <= m["objective_initial"]
    assert set(m["terms"]) == {"base", "initial", "final"}
    assert any(p.name.startswith("events.out.tfevents") for p in (tmp_path / "tb").iterdir())
    from torchgarment.pattern.garmentcode import load_pattern

    assert set(load_pattern(out / "pattern.json").panels) == {"front", "back"} or len(
        load_pattern(out / "pattern.json").panels) >= 2
    assert "reduction" in capsys.readouterr().out
    assert not (out / "checkpoint").exists()  # a finished run removes its checkpoint (issue 17)


def test_bad_input(tmp_path):
    with pytest.raises(InputError, match="not a library garment"):
        cmd_adjust(_parse(["--garment", "cape", "--base-size", "12", "--target-size", "20", "--out",
                           str(tmp_path)]))
    with pytest.raises(InputError, match="neither a chart size"):
        cmd_adjust(_parse(["--garment", "straight_skirt", "--base-body", "nope.obj", "--target-size", "20",
                           "--out", str(tmp_path)]))
    with pytest.raises(InputError, match="iterations"):
        cmd_adjust(_parse(["--garment", "straight_skirt", "--base-size", "12", "--target-size", "20",
                           "--out", str(tmp_path), "--iterations", "-1"]))
    with pytest.raises(InputError, match="reference_edge_length"):
        cmd_adjust(_parse(["--garment", "straight_skirt", "--base-size", "12", "--target-size", "20",
                           "--out", str(tmp_path), "--reference-edge-length", "-1"]))
    for flag in ("--ease-weight", "--placement-weight", "--guide-weight", "--support-shape-weight"):
        with pytest.raises(InputError, match="ease|placement|guide|support_shape"):
            cmd_adjust(_parse(["--garment", "straight_skirt", "--base-size", "12", "--target-size", "20",
                               "--out", str(tmp_path), flag, "nan"]))
    for ratio in ("1.5", "-0.1", "nan"):
        with pytest.raises(InputError, match="min_model_ratio"):
            cmd_adjust(_parse(["--garment", "straight_skirt", "--base-size", "12", "--target-size", "20",
                               "--out", str(tmp_path), "--min-model-ratio", ratio]))
    with pytest.raises(InputError, match="step_window"):
        cmd_adjust(_parse(["--garment", "straight_skirt", "--base-size", "12", "--target-size", "20",
                           "--out", str(tmp_path), "--step-window", "0"]))
    with pytest.raises(SystemExit):
        _parse(["--garment", "straight_skirt", "--base-size", "12", "--out", str(tmp_path)])  # no target
    with pytest.raises(SystemExit):
        _parse(["--garment", "straight_skirt", "--base-size", "12", "--target-size", "20", "--out",
                str(tmp_path), "--reference-edge-length", "fine"])
    assert not any(tmp_path.iterdir())


def test_reference_edge_length_option():
    """The regularizers are resolution-consistent by default; ``none`` gives the paper's coefficients as
    given."""
    from torchgarment.adjust.cli import settings_from_args

    base = ["--garment", "straight_skirt", "--base-size", "12", "--target-size", "20", "--out", "o"]
    assert settings_from_args(_parse(base)).weights.reference_edge_length == 0.008
    off = settings_from_args(_parse(base + ["--reference-edge-length", "none"]))
    assert off.weights.reference_edge_length is None
    fine = settings_from_args(_parse(base + ["--reference-edge-length", "0.01"]))
    assert fine.weights.reference_edge_length == 0.01


def test_min_model_ratio_option():
    """Algorithm 1's ratio test (the library's 0.25 by default, 0 gives the paper's rule alone) and the step
    control between checks (``--adapt-step`` / ``--no-adapt-step``, ``--step-window``)."""
    from torchgarment.adjust.cli import settings_from_args

    base = ["--garment", "straight_skirt", "--base-size", "12", "--target-size", "20", "--out", "o"]
    assert settings_from_args(_parse(base)).min_model_ratio == 0.25
    assert settings_from_args(_parse(base + ["--min-model-ratio", "0"])).min_model_ratio == 0.0
    from torchgarment.adjust.pipeline import AdjustSettings

    assert settings_from_args(_parse(base)).adapt_step is AdjustSettings().adapt_step
    assert settings_from_args(_parse(base + ["--adapt-step"])).adapt_step is True
    assert settings_from_args(_parse(base + ["--no-adapt-step"])).adapt_step is False
    assert settings_from_args(_parse(base)).step_window == 4
    assert settings_from_args(_parse(base + ["--step-window", "1"])).step_window == 1


def test_inexact_adjoint_option():
    """``--inexact-adjoint``: the library's default (``exact``) unless ``projected`` is asked for."""
    from torchgarment.adjust.cli import settings_from_args
    from torchgarment.sim.diff import AdjointHessian

    base = ["--garment", "straight_skirt", "--base-size", "12", "--target-size", "20", "--out", "o"]
    assert settings_from_args(_parse(base)).inexact_adjoint is AdjointHessian.EXACT
    projected = settings_from_args(_parse(base + ["--inexact-adjoint", "projected"]))
    assert projected.inexact_adjoint is AdjointHessian.PROJECTED
    with pytest.raises(SystemExit):
        _parse(base + ["--inexact-adjoint", "psd"])


def test_fit_scale_option(tmp_path):
    """``--fit-scale``: ``none`` by default, ``stature`` on request; another name is refused by argparse
    before anything is written."""
    from torchgarment.adjust.cli import settings_from_args
    from torchgarment.adjust.fit import FitScale

    base = ["--garment", "straight_skirt", "--base-size", "12", "--target-size", "20", "--out", str(tmp_path)]
    assert settings_from_args(_parse(base)).fit_scale is FitScale.NONE
    assert settings_from_args(_parse(base + ["--fit-scale", "stature"])).fit_scale is FitScale.STATURE
    with pytest.raises(SystemExit):
        _parse(base + ["--fit-scale", "girth"])
    assert not any(tmp_path.iterdir())


def test_line_term_options():
    """The construction lines' ease and placement terms: library defaults, settable, 0 turns them off."""
    from torchgarment.adjust.cli import settings_from_args
    from torchgarment.adjust.objective import CostWeights

    base = ["--garment", "straight_skirt", "--base-size", "12", "--target-size", "20", "--out", "o"]
    w = settings_from_args(_parse(base)).weights
    assert (w.ease, w.placement) == (CostWeights().ease, CostWeights().placement)
    w = settings_from_args(_parse(base + ["--ease-weight", "0", "--placement-weight", "250",
                                          "--guide-weight", "0", "--support-shape-weight", "0"])).weights
    assert (w.ease, w.placement, w.guide, w.support_shape) == (0.0, 250.0, 0.0, 0.0)
