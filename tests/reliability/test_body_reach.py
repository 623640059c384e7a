"""Issue 17: bodies from every plausible measurement set. GarmentCode's mean bodies with the bust, waist and
hips graded by 2 inches and the underbust kept ended 1-2 cm off (a waist larger than the underbust was
measured just under the breast fold, and the fit stalled where the tape planes jump); a request that really
is out of reach is refused in one line naming ``--closest``, which writes the closest body with its errors.
The full table is ``scripts/body_fit_acceptance.py``."""

from __future__ import annotations

import json

import pytest

from torchgarment.body.anny_body import FitSettings, body_from_measurements
from torchgarment.errors import InputError

# GarmentCode's mean_female / mean_male YAML (cm -> m) with bust, waist and hips moved by +-5.08 cm, underbust
# kept
FEMALE_BWH_PLUS = {"height": 1.66194, "bust": 1.024876, "underbust": 0.807483, "waist": 0.854242,
                   "hips": 1.09171}
MALE_BWH_MINUS = {"height": 1.78873, "bust": 0.97707, "underbust": 0.930277, "waist": 0.83923, "hips": 0.9777}
OUT_OF_REACH = {"height": 1.6, "bust": 0.8, "underbust": 0.75, "waist": 1.2, "hips": 0.9}


@pytest.mark.parametrize("request_m", [FEMALE_BWH_PLUS, MALE_BWH_MINUS], ids=["female_bwh+5", "male_bwh-5"])
def test_graded_measurement_sets_are_reached_within_3mm(request_m):
    """The female case needs the waist measured where a tape goes round a belly (a waist 4.7 cm larger
    than the underbust); the male case needs the continuation (the direct fit stalls 12.6 mm off)."""
    body = body_from_measurements(request_m, cache=False)
    assert body.params["reached"]
    errors = body.params["reach_errors"]
    assert set(errors) == set(request_m)
    assert max(abs(e) for e in errors.values()) <= 3.0, errors
    measured = body.measurements().to_dict()
    for k, v in request_m.items():
        assert abs(measured[k] - v) <= 3e-3, (k, measured[k], v)


def test_fit_settings_refuse_bad_counts():
    for bad in (0, 1.5, True):
        with pytest.raises(InputError, match="continuation"):
            FitSettings(continuation=bad)
        with pytest.raises(InputError, match="stall_rounds"):
            FitSettings(stall_rounds=bad)


def test_out_of_reach_is_refused_and_closest_writes_the_closest_body(tmp_path, monkeypatch, cli, one_line):
    monkeypatch.setenv("TORCHGARMENT_CACHE", str(tmp_path / "cache"))
    request = tmp_path / "m.json"
    request.write_text(json.dumps(OUT_OF_REACH))
    out = tmp_path / "out"
    line = one_line(cli("body", "--measurements", str(request), "--out", str(out), cwd=tmp_path),
                    "cannot reach")
    assert "--closest" in line and "waist" in line
    assert not out.exists()
    # the closest body was cached by the refused run: the --closest run loads it
    proc = cli("body", "--measurements", str(request), "--out", str(out), "--closest", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    warnings = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(warnings) == 1 and warnings[0].startswith("warning:") and "errors in mm" in warnings[0]
    report = json.loads((out / "measurements.json").read_text())
    assert set(report["fit_errors_mm"]) == set(OUT_OF_REACH)
    assert abs(report["fit_errors_mm"]["waist"]) > 3.0
    assert abs(report["measured"]["waist"] - OUT_OF_REACH["waist"]) > 3e-3
    assert (out / "body.obj").is_file()
