"""torchgarment.studies (the helpers of scripts/accuracy_vs_time.py): Pareto front, CSV and summaries on
synthetic rows."""

from __future__ import annotations

import csv
import math
from types import ModuleType

import pytest


@pytest.fixture(scope="module")
def avt() -> ModuleType:
    from torchgarment import studies

    return studies


def test_pareto_front(avt):
    times = [1.0, 2.0, 0.5, 3.0, 2.0, math.nan, 0.1]
    errors = [5.0, 3.0, 9.0, 3.5, 2.0, 0.0, math.inf]
    # 0.5/9 (fastest finite), 1/5, 2/2 (dominates 2/3 and 3/3.5); nan/inf never on the front
    assert avt.pareto_front(times, errors) == [2, 0, 4]
    assert avt.pareto_front([], []) == []
    # ties: equal time, the lower error wins; a dominated duplicate is dropped
    assert avt.pareto_front([1.0, 1.0, 1.0], [2.0, 1.0, 1.0]) == [1]
    with pytest.raises(ValueError):
        avt.pareto_front([1.0], [])


def _rows():
    return [
        {"method": "pca", "setting": "pca k=0", "body": 0, "seconds": 1e-4, "offline_seconds": 300.0,
         "mean_mm": 10.0, "max_mm": 40.0, "inside": 3, "waist_ease_err_mm": 5.0, "hip_ease_err_mm": math.nan},
        {"method": "pca", "setting": "pca k=0", "body": 1, "seconds": 3e-4, "offline_seconds": 300.0,
         "mean_mm": 20.0, "max_mm": 50.0, "inside": 1, "waist_ease_err_mm": 7.0, "hip_ease_err_mm": 2.0},
        {"method": "sim", "setting": "sim e=5cm tol=0.001", "body": 0, "seconds": 60.0,
         "offline_seconds": 0.0, "mean_mm": 2.0, "max_mm": 8.0, "inside": 0, "waist_ease_err_mm": 1.0,
         "hip_ease_err_mm": 1.0, "note": "ok", "extra": "x"},
    ]


def test_write_csv(avt, tmp_path):
    path = tmp_path / "sub" / "rows.csv"
    path.parent.mkdir()
    header = avt.write_csv(_rows(), path)
    assert header[:4] == ["method", "setting", "body", "seconds"]
    assert header[-1] == "extra"  # unknown keys after the known columns
    with open(path, newline="") as f:
        got = list(csv.DictReader(f))
    assert len(got) == 3
    assert float(got[1]["mean_mm"]) == 20.0 and got[2]["note"] == "ok" and got[0]["note"] == ""
    assert float(got[0]["seconds"]) == pytest.approx(1e-4)
    assert got[0]["hip_ease_err_mm"] == "nan"


def test_summarize_and_table(avt, tmp_path):
    summary = avt.summarize(_rows())
    assert [s["setting"] for s in summary] == ["pca k=0", "sim e=5cm tol=0.001"]
    pca = summary[0]
    assert pca["bodies"] == 2 and pca["median_seconds"] == pytest.approx(2e-4)
    assert pca["mean_mm"] == pytest.approx(15.0) and pca["max_mm"] == 50.0 and pca["inside"] == 2.0
    assert pca["hip_ease_err_mm"] == pytest.approx(2.0)  # NaN ignored
    table = avt.format_table(summary, {"pca k=0"})
    assert table.count("\n") == 2 and table.splitlines()[1].endswith("*")
    avt.plot_pareto(summary, tmp_path / "p.png", "synthetic")
    assert (tmp_path / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
