"""scripts/adjust_accuracy_guard.py end to end on one coarse straight skirt (about 300 vertices, 2
iterations): the configuration against the exact method, the cached precomputation, the summary and bad
input."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import torch

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "adjust_accuracy_guard.py"


def _load():
    spec = importlib.util.spec_from_file_location("adjust_accuracy_guard", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_guard_compares_with_the_exact_method_from_one_cached_setup(tmp_path, capsys):
    mod = _load()
    n = torch.get_num_threads()
    args = ["--garment", "straight_skirt", "--vertices", "300", "--targets", "14", "--iterations", "2",
            "--exact-interval", "2", "--setup-dir", str(tmp_path / "setups")]
    try:
        assert mod.main(args + ["--json", str(tmp_path / "a.json")]) == 0
        assert mod.main(args + ["--json", str(tmp_path / "b.json")]) == 0
    finally:
        torch.set_num_threads(n)
    a, b = (json.loads((tmp_path / f).read_text()) for f in ("a.json", "b.json"))
    (row,) = a["rows"]
    assert row["ok"] and row["target_size"] == "14"
    # both runs descend from the initialized pattern; the ratio is what the summary reports
    assert row["objective_final"] < row["objective_initial"]
    assert row["exact_objective_final"] < row["objective_initial"]
    assert math.isclose(row["ratio"], row["objective_final"] / row["exact_objective_final"])
    assert a["summary"]["targets"] == 1
    assert a["summary"]["within_2_percent"] == int(row["ratio"] <= 1.02)
    assert math.isclose(a["summary"]["geometric_mean_ratio"], row["ratio"])
    # the second run loaded the first one's precomputation (no precomputation time) and, one thread on the
    # same setup, repeats its results
    assert "precomputation_seconds" in row and "precomputation_seconds" not in b["rows"][0]
    assert b["rows"][0]["objective_final"] == row["objective_final"]
    assert b["rows"][0]["exact_objective_final"] == row["exact_objective_final"]
    assert "geometric mean of final / exact method" in capsys.readouterr().out


def test_guard_refuses_an_unknown_size_in_one_line(capsys):
    mod = _load()
    n = torch.get_num_threads()
    try:
        assert mod.main(["--targets", "8x"]) == 2
    finally:
        torch.set_num_threads(n)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "8x" in err[0]


def test_summary_of_no_rows_and_of_failed_rows():
    mod = _load()
    assert mod.summarize([]) == {"targets": 0}
    s = mod.summarize([{"ok": True, "ratio": 1.01}, {"ok": True, "ratio": 1.21}, {"ok": False}])
    assert s["targets"] == 2 and s["within_2_percent"] == 1
    assert math.isclose(s["geometric_mean_ratio"], math.sqrt(1.01 * 1.21))
    assert s["best_ratio"] == 1.01 and s["worst_ratio"] == 1.21
