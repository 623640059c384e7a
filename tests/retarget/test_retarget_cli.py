"""``torchgarment retarget`` end to end on small files; bad input exits 2 with one line."""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING

import numpy as np
import pytest
import torch

from torchgarment.body.skeleton_io import write_skeleton_obj
from torchgarment.errors import TorchGarmentError
from torchgarment.io.mesh import read_obj, save_obj
from torchgarment.retarget.avatars import toy_case
from torchgarment.retarget.cli import add_retarget_parser

if TYPE_CHECKING:
    from pathlib import Path

    from torchgarment.retarget.avatars import ToyCase


def _run(argv: list[str]) -> int:
    """Run through ``torchgarment.cli.main`` once the lead has wired the command, else an equivalent
    harness."""
    from torchgarment import cli

    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    if "retarget" in sub.choices:
        return cli.main(argv)
    parser = argparse.ArgumentParser(prog="torchgarment")
    add_retarget_parser(parser.add_subparsers())
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except TorchGarmentError as e:
        print(f"torchgarment: error: {e}", file=sys.stderr)
        return 2


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, ToyCase]:
    d = tmp_path_factory.mktemp("in")
    c = toy_case(target_scale=100.0, target_offset=(50.0, 0.0, -20.0))  # the avatar in centimetres, elsewhere
    save_obj(d / "garment.obj", c.garment_vertices, c.garment_faces)
    save_obj(d / "avatar.obj", c.target_vertices, c.target_faces)
    save_obj(d / "source_avatar.obj", c.source_vertices, c.source_faces)
    write_skeleton_obj(d / "source_skeleton.obj", c.source_skeleton)
    write_skeleton_obj(d / "target_skeleton.obj", c.target_skeleton)
    (d / "curves.txt").write_text(" ".join(str(i) for i in range(0, 240, 10)) + "\n")
    return d, c


def test_cli_end_to_end(files: tuple, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d, c = files
    out = tmp_path / "out"
    code = _run(
        [
            "retarget",
            "--garment",
            str(d / "garment.obj"),
            "--source-skeleton",
            str(d / "source_skeleton.obj"),
            "--target-avatar",
            str(d / "avatar.obj"),
            "--target-skeleton",
            str(d / "target_skeleton.obj"),
            "--source-avatar",
            str(d / "source_avatar.obj"),
            "--curves",
            str(d / "curves.txt"),
            "--out",
            str(out),
            "--log-dir",
            str(tmp_path / "tb"),
            "--no-progress",
        ]
    )
    assert code == 0
    assert {p.name for p in out.iterdir()} == {"garment.obj", "retarget.png", "metrics.json"}
    m = json.loads((out / "metrics.json").read_text())
    for key in (
        "seconds",
        "newton_iterations",
        "grad_norm",
        "min_distance_mm",
        "intersections",
        "distortion_mean",
        "distortion_max",
        "terms",
    ):
        assert key in m
    assert m["intersections"] == 0 and m["min_distance_mm"] > 0
    v, f = read_obj(out / "garment.obj")
    assert f.shape[0] == c.garment_faces.shape[0]
    # written in the target avatar's frame (centimetres, offset): around the avatar
    centre = c.target_vertices.numpy().mean(0)
    assert np.linalg.norm(v.mean(0)[[0, 2]] - centre[[0, 2]]) < 30.0 and np.ptp(v[:, 1]) > 50.0
    assert any((tmp_path / "tb").iterdir())
    assert "intersections 0" in capsys.readouterr().out


def test_cli_budget_stop_keeps_a_usable_result_and_says_so(
    files: tuple, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 17: a retarget stopped by its iteration budget with an intersection-free result exits 0 and says
    so in one line on stderr, with the gradient norm (it used to be only in metrics.json)."""
    d, _ = files
    out = tmp_path / "out"
    code = _run(["retarget", "--garment", str(d / "garment.obj"), "--source-skeleton",
                 str(d / "source_skeleton.obj"), "--target-avatar", str(d / "avatar.obj"),
                 "--target-skeleton", str(d / "target_skeleton.obj"), "--fit-iterations", "1",
                 "--out", str(out), "--no-log", "--no-progress", "--no-render"])
    assert code == 0
    m = json.loads((out / "metrics.json").read_text())
    assert not m["converged"] and m["intersections"] == 0
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "iteration budget" in err[0] and f"{m['grad_norm']:.3g}" in err[0], err


@pytest.mark.parametrize("case", ["missing", "bad_weight", "bad_attach_weight", "bad_skeleton",
                                  "garment_in_mm", "gpu", "source_gap_without_source_avatar"])
def test_cli_bad_input_one_line(
    files: tuple, tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str
) -> None:
    d, _ = files
    args = {
        "--garment": str(d / "garment.obj"),
        "--source-skeleton": str(d / "source_skeleton.obj"),
        "--target-avatar": str(d / "avatar.obj"),
        "--target-skeleton": str(d / "target_skeleton.obj"),
    }
    extra = []
    if case == "missing":
        args["--target-avatar"] = str(tmp_path / "nope.obj")
    elif case == "bad_weight":
        extra = ["--fit-weight", "-1"]
    elif case == "bad_attach_weight":
        extra = ["--attach-weight", "nan"]
    elif case == "gpu":  # ipctk has no GPU path: refused in one line, also on a machine with CUDA
        extra = ["--device", "cuda"]
    elif case == "source_gap_without_source_avatar":  # the gaps are measured to the source avatar
        extra = ["--fit-target", "source-gap"]
    elif case == "garment_in_mm":  # issue 17: its solve ran for minutes at seconds per iteration
        v, f = read_obj(d / "garment.obj")
        save_obj(tmp_path / "garment_mm.obj", torch.as_tensor(1000.0 * v), torch.as_tensor(f))
        args["--garment"] = str(tmp_path / "garment_mm.obj")
    else:
        bad = tmp_path / "bad_skeleton.obj"
        bad.write_text("v 0 0 0\nv 0 1 0\nl 1 2\n")  # one bone instead of four
        args["--target-skeleton"] = str(bad)
    argv = [
        "retarget",
        *sum(([k, v] for k, v in args.items()), []),
        "--out",
        str(tmp_path / "o"),
        "--no-log",
        "--no-progress",
        *extra,
    ]
    code = _run(argv)
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.startswith("torchgarment: error:") and len(err.splitlines()) == 1
    assert not (tmp_path / "o").exists()
    if case == "garment_in_mm":
        assert "different units" in err and "scale the garment by 0.001" in err, err
    if case == "gpu":
        assert "runs on the CPU only" in err and "ipctk" in err, err
    if case == "bad_attach_weight":
        assert "--attach-weight" in err, err
    if case == "source_gap_without_source_avatar":
        assert "source-gap" in err and "--source-avatar" in err, err
