"""``torchgarment grade`` (torchgarment.adjust.grade, grade_cli): outputs, graded DXF, resume, a failing size,
reproducibility, bad input. Coarse: 5 cm edges, 1 cm voxels, 2 iterations, sizes 10 and 14 from 12."""

from __future__ import annotations

import csv
import importlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from torchgarment.adjust.grade import CSV_COLUMNS, SIZE_FILES, acceptance_summary, format_table
from torchgarment.cli import main
from torchgarment.pattern.dxf import graded_dxf_sizes, load_dxf
from torchgarment.pattern.garmentcode import load_pattern

# the module (``torchgarment.adjust.grade`` as an attribute is the re-exported function)
grade_mod = importlib.import_module("torchgarment.adjust.grade")
SIZES = ("10", "14")
PANELS = {"skirt_front", "skirt_back"}


def _argv(out: Path, *extra: str) -> list[str]:
    return ["grade", "--garment", "straight_skirt", "--base-size", "12", "--sizes", *SIZES, "--out", str(out),
            "--iterations", "2", "--exact-interval", "2", "--init-iterations", "5", "--edge-length", "0.05",
            "--voxel", "0.01", "--no-progress", *extra]


def _run(argv: list[str]) -> int:
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return main(argv)
    finally:
        torch.set_num_threads(n)


def _max_pattern_difference(a: Path, b: Path) -> float:
    pa, pb = load_pattern(a), load_pattern(b)
    assert set(pa.panels) == set(pb.panels)
    worst = 0.0
    for name in pa.panels:
        x, y = pa.panels[name], pb.panels[name]
        worst = max(worst, float(np.abs(np.asarray(x.vertices) - np.asarray(y.vertices)).max()))
        for ex, ey in zip(x.edges, y.edges, strict=True):
            assert ex.kind == ey.kind
            if ex.controls is not None:
                worst = max(worst, float(np.abs(np.asarray(ex.controls) - np.asarray(ey.controls)).max()))
    return worst


@pytest.fixture(scope="module")
def graded(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("grade") / "out"
    assert _run(_argv(out)) == 0
    return out


def test_outputs_exist_and_parse(graded, capsys):
    for size in SIZES:
        for name in SIZE_FILES:
            f = graded / size / name
            assert f.is_file() and f.stat().st_size > 0, (size, name)
        pat = load_pattern(graded / size / "pattern.json")
        assert set(pat.panels) == PANELS
        assert set(load_dxf(graded / size / "pattern.dxf").panels) == PANELS
        fit = json.loads((graded / size / "fit.json").read_text())
        assert {r["line"] for r in fit["rows"]} == {"waist", "hips"}
    for name in ("grade.dxf", "grade_nest.png", "grade.csv", "metrics.json"):
        assert (graded / name).is_file() and (graded / name).stat().st_size > 0, name
    with open(graded / "grade.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert tuple(rows[0]) == CSV_COLUMNS
    expected = [(s, ln) for s in ("12", *SIZES) for ln in ("waist", "hips")]
    assert [(r["size"], r["line"]) for r in rows] == expected
    for r in rows:
        if r["size"] == "12":
            assert float(r["ease_change_m"]) == 0.0 and float(r["pattern_change_m"]) == 0.0
            continue
        # ease = pattern girth - body girth; the changes are against the base rows
        assert math.isclose(float(r["ease_m"]), float(r["pattern_girth_m"]) - float(r["body_girth_m"]),
                            abs_tol=1e-12)
        base = next(b for b in rows if b["size"] == "12" and b["line"] == r["line"])
        assert math.isclose(float(r["ease_change_m"]), float(r["ease_m"]) - float(base["ease_m"]),
                            abs_tol=1e-12)
        assert math.isclose(float(r["pattern_change_m"]),
                            float(r["pattern_girth_m"]) - float(base["pattern_girth_m"]), abs_tol=1e-12)
        # the chart's differences: 10 is smaller than 12, 14 larger
        assert (float(r["chart_change_m"]) < 0) == (r["size"] == "10")
    # the adjusted patterns follow the body: size 10's girths below 14's at both lines
    g = {(r["size"], r["line"]): float(r["pattern_girth_m"]) for r in rows}
    assert g["10", "hips"] < g["14", "hips"] and g["10", "waist"] < g["14", "waist"]
    m = json.loads((graded / "metrics.json").read_text())
    assert m["sizes"] == list(SIZES) and m["failed"] == {}
    assert m["acceptance"]["lines"] == 4 and 0 <= m["acceptance"]["lines_passed"] <= 4
    assert all(m["per_size"][s]["status"] == "done" and m["per_size"][s]["seconds"] > 0 for s in SIZES)
    assert m["base_drape_once"] is True


def test_graded_dxf_holds_every_size_of_every_piece(graded):
    sizes = graded_dxf_sizes(graded / "grade.dxf")
    assert set(sizes) == {"12", *SIZES}
    assert all(set(pieces) == PANELS for pieces in sizes.values())
    # our own reader reads the file as one pattern with every size's pieces; each equals its size's pattern
    read = load_dxf(graded / "grade.dxf")
    own = {s: load_pattern(graded / s / "pattern.json") for s in SIZES}
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    own["12"] = draft("straight_skirt", chart_row("12"))
    assert len(read.panels) == 3 * len(PANELS)
    assert len(read.stitches) == sum(len(p.stitches) for p in own.values()) == 3 * len(own["12"].stitches)
    for s, pat in own.items():
        for name, panel in pat.panels.items():
            v = np.asarray(panel.vertices)
            dist = [float(np.abs(np.asarray(p.vertices) - v).max()) for p in read.panels.values()
                    if np.asarray(p.vertices).shape == v.shape]
            assert min(dist) < 1e-6, (s, name, min(dist))


def test_resume_skips_finished_sizes_and_reproduces(graded, tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"
    import shutil

    shutil.copytree(graded, out)
    calls: list = []
    real = grade_mod.adjust_to_target

    def counting(pattern, base_body, target_body, settings, base, **kw):
        calls.append(target_body)
        return real(pattern, base_body, target_body, settings, base, **kw)

    monkeypatch.setattr(grade_mod, "adjust_to_target", counting)
    assert _run(_argv(out, "--resume")) == 0
    assert calls == []  # both sizes finished: nothing adjusted, the run's files rewritten
    assert json.loads((out / "metrics.json").read_text())["per_size"]["10"]["status"] == "resumed"
    (out / "14" / "target_after.png").unlink()  # an incomplete size folder is done again
    assert _run(_argv(out, "--resume")) == 0
    assert len(calls) == 1
    m = json.loads((out / "metrics.json").read_text())
    assert m["per_size"]["10"]["status"] == "resumed" and m["per_size"]["14"]["status"] == "done"
    assert _max_pattern_difference(out / "14" / "pattern.json", graded / "14" / "pattern.json") <= 1e-9
    assert (out / "grade.csv").read_text() == (graded / "grade.csv").read_text()


def test_a_failing_size_is_reported_and_the_others_finish(graded, tmp_path, monkeypatch, capsys):
    """The same command again with one size failing: the other size is written, and it is the full run's
    pattern (this is also the check that the same command gives the same pattern twice)."""
    from torchgarment.body import Body

    real = grade_mod.adjust_to_target
    size10 = Body.from_size("10").vertices

    def failing(pattern, base_body, target_body, settings, base, **kw):
        if torch.equal(target_body.vertices, size10):
            raise RuntimeError("solver exploded\nsecond line")
        return real(pattern, base_body, target_body, settings, base, **kw)

    monkeypatch.setattr(grade_mod, "adjust_to_target", failing)
    out = tmp_path / "out"
    assert _run(_argv(out)) == 1
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if "size 10 failed" in ln]
    assert lines == ["grade: size 10 failed: RuntimeError: solver exploded"]
    assert not (out / "10").exists()
    assert all((out / "14" / name).is_file() for name in SIZE_FILES)
    m = json.loads((out / "metrics.json").read_text())
    assert list(m["failed"]) == ["10"] and m["per_size"]["14"]["status"] == "done"
    assert set(graded_dxf_sizes(out / "grade.dxf")) == {"12", "14"}
    # the surviving size is the same pattern as in the full run
    assert _max_pattern_difference(out / "14" / "pattern.json", graded / "14" / "pattern.json") <= 1e-9


def test_bad_input_one_line_exit_2(tmp_path, capsys):
    for argv, msg in (
        (["grade", "--garment", "cape", "--base-size", "12", "--sizes", "10", "--out", str(tmp_path / "a")],
         "not a library garment"),
        (["grade", "--garment", "straight_skirt", "--base-size", "12", "--sizes", "11", "--out",
          str(tmp_path / "a")], "not chart sizes"),
        (["grade", "--garment", "straight_skirt", "--base-size", "12", "--target-body", "nope.obj", "--out",
          str(tmp_path / "a")], "neither a chart size"),
        (["grade", "--garment", "straight_skirt", "--base-size", "12", "--sizes", "12", "--out",
          str(tmp_path / "a")], "base's name"),
        (["grade", "--garment", "straight_skirt", "--base-size", "12", "--sizes", "10", "--out",
          str(tmp_path / "a"), "--iterations", "-1"], "iterations"),
        (["grade", "--garment", "straight_skirt", "--base-size", "12", "--sizes", "10", "--out",
          str(tmp_path / "a"), "--support", "skirt_front:waist_r", "--no-support"], "exclude each other"),
        (["grade", "--garment", "straight_skirt", "--base-size", "12", "--sizes", "10", "--out",
          str(tmp_path / "a"), "--support", "nopanel:waist"], "nopanel"),
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and msg in err[0], err
    assert not (tmp_path / "a").exists()


def test_acceptance_summary_and_table():
    rows = [{"size": "10", "line": "waist", "pattern_girth_m": 0.65, "body_girth_m": 0.64, "ease_m": 0.01,
             "ease_change_m": 0.004, "pattern_change_m": -0.03, "body_change_m": -0.034,
             "chart_change_m": -0.038, "placement_change_m": 0.002, "pass": True},
            {"size": "10", "line": "hips", "pattern_girth_m": 0.91, "body_girth_m": 0.84, "ease_m": 0.07,
             "ease_change_m": -0.014, "pattern_change_m": -0.038, "body_change_m": -0.024,
             "chart_change_m": math.nan, "placement_change_m": -0.005, "pass": False}]
    s = acceptance_summary(rows)
    assert s["lines"] == 2 and s["lines_passed"] == 1 and s["pass"] is False
    assert math.isclose(s["max_abs_ease_change_m"], 0.014)
    assert math.isclose(s["max_abs_pattern_minus_body_change_m"], 0.014)
    assert math.isclose(s["max_abs_placement_change_m"], 0.005)
    table = format_table(rows).splitlines()
    assert len(table) == 3 and table[0].split() == [*CSV_COLUMNS, "pass"]
    assert table[2].split()[-1] == "NO" and "-" in table[2].split()[8]
