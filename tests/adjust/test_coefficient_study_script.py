"""scripts/adjust_coefficient_study.py end to end on one coarse held-out case (5 cm edges, 2 iterations): two
candidate coefficient sets, the printed table and the JSON summary."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import torch

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "adjust_coefficient_study.py"


def test_study_grades_a_held_out_case_under_each_candidate(tmp_path, capsys):
    spec = importlib.util.spec_from_file_location("adjust_coefficient_study", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    # the default cases are held out: none is an acceptance case (base 12 to 6/8/10/14/16/20)
    assert all(not (c.split(":")[1] == "12" and c.split(":")[2] in {"6", "8", "10", "14", "16", "20"})
               for c in mod.CASES)
    n = torch.get_num_threads()
    out = tmp_path / "study.json"
    try:
        rc = mod.main(["--cases", "straight_skirt:14:18", "--candidates", '{"paper": {}}',
                       '{"fix10": {"fixing": 10}}', "--edge-length", "0.05", "--iterations", "2", "--json",
                       str(out)])
    finally:
        torch.set_num_threads(n)
    assert rc == 0
    data = json.loads(out.read_text())
    assert set(data["summary"]) == {"paper", "fix10"}
    assert data["summary"]["fix10"]["weights"]["fixing"] == 10.0
    for label in ("paper", "fix10"):
        rows = data["results"][label][0]["rows"]
        assert [r["line"] for r in rows] == ["waist", "hips"]
        # size 18 is larger: the pattern grows at both lines
        assert all(r["pattern_change_m"] > 0.01 for r in rows)
        s = data["summary"][label]
        assert s["lines"] == 2 and 0 <= s["lines_passing"] <= 2 and s["max_girth_error_m"] >= 0
    assert "lines pass" in capsys.readouterr().out
