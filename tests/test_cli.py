"""The torchgarment command line: outputs, listings, and one clean line for bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from torchgarment.cli import main


def run_cli(*args: str) -> subprocess.CompletedProcess:
    """Run the CLI in a subprocess, as a user would."""
    return subprocess.run([sys.executable, "-m", "torchgarment", *args], capture_output=True, text=True,
                          timeout=600)


def assert_one_line_error(proc: subprocess.CompletedProcess, needle: str) -> None:
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    assert needle in lines[0], lines[0]


def test_every_subcommand_has_help(capsys):
    """``python -m torchgarment --help`` lists the subcommands (one process, as a user would start it); each
    subcommand's ``--help`` prints its usage and exits 0 (in this process: the same parser, without a Python
    start and a torch import per subcommand)."""
    proc = run_cli("--help")
    assert proc.returncode == 0, proc.stderr
    commands = ("body", "pattern", "measure", "drape", "adjust", "grade", "retarget", "pca", "batch", "demo")
    assert "{" + ",".join(commands) + "}" in proc.stdout
    for cmd in commands:
        with pytest.raises(SystemExit) as stop:
            main([cmd, "--help"])
        assert stop.value.code == 0
        assert "usage: torchgarment " + cmd in capsys.readouterr().out


def test_list_sizes_and_garments(capsys):
    from torchgarment.body.size_chart import list_sizes
    from torchgarment.pattern.library import list_garments

    assert main(["body", "--list-sizes"]) == 0
    assert capsys.readouterr().out.split() == list(list_sizes())
    assert main(["pattern", "--list"]) == 0
    names = capsys.readouterr().out.split()
    assert names == list(list_garments())
    for required in ("straight_skirt", "aline_skirt", "sheath_dress", "tshirt", "trousers", "bodysuit"):
        assert required in names


def test_pattern_from_library_writes_all_files(tmp_path: Path):
    from torchgarment.body.size_chart import list_sizes

    out = tmp_path / "skirt"
    assert main(["pattern", "--garment", "straight_skirt", "--size", list_sizes()[0], "--out", str(out),
                 "--edge-length", "0.02"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["pattern.dxf", "pattern.json", "pattern.png",
                                                     "pattern.svg"]
    assert json.loads((out / "pattern.json").read_text())["pattern"]["panels"]
    assert [p.name for p in tmp_path.iterdir()] == ["skirt"]  # no staging folder left behind


def test_pattern_roundtrip_through_cli(tmp_path: Path):
    from torchgarment.body.size_chart import list_sizes
    from torchgarment.pattern.garmentcode import load_pattern

    first, second = tmp_path / "a", tmp_path / "b"
    assert main(["pattern", "--garment", "tshirt", "--size", list_sizes()[-1], "--out", str(first)]) == 0
    assert main(["pattern", str(first / "pattern.dxf"), "--out", str(second)]) == 0
    a = load_pattern(first / "pattern.json")
    b = load_pattern(second / "pattern.json")
    assert sorted(a.panels) == sorted(b.panels)


@pytest.mark.parametrize(
    "args, needle",
    [
        (["measure", "no/such/file.obj", "--out", "m.json"], "no/such/file.obj"),
        (["pattern", "no_such_pattern.json", "--out", "o"], "no_such_pattern.json"),
        (["pattern", "--garment", "ballgown", "--size", "12", "--out", "o"], "ballgown"),
        (["body", "--size", "not-a-size", "--out", "o"], "not-a-size"),
    ],
)
def test_bad_input_one_line(tmp_path: Path, args, needle):
    proc = subprocess.run([sys.executable, "-m", "torchgarment", *args], capture_output=True, text=True,
                          cwd=tmp_path, timeout=300)
    assert_one_line_error(proc, needle)
    assert not (tmp_path / "o").exists() and not (tmp_path / "m.json").exists()


def test_malformed_files_one_line(tmp_path: Path):
    bad_json = tmp_path / "bad.json"
    bad_json.write_text("{ not json")
    proc = run_cli("pattern", str(bad_json), "--out", str(tmp_path / "o1"))
    assert_one_line_error(proc, "bad.json")
    bad_dxf = tmp_path / "bad.dxf"
    bad_dxf.write_text("this is not a dxf file\n")
    proc = run_cli("pattern", str(bad_dxf), "--out", str(tmp_path / "o2"))
    assert_one_line_error(proc, "bad.dxf")
    bad_obj = tmp_path / "bad.obj"
    bad_obj.write_text("v 0 0 0\nf 1 2 3\n")
    proc = run_cli("measure", str(bad_obj), "--out", str(tmp_path / "m.json"))
    assert_one_line_error(proc, "bad.obj")
    meas = tmp_path / "meas.json"
    meas.write_text(json.dumps({"height": 1.7, "shoe_size": 0.3}))
    proc = run_cli("body", "--measurements", str(meas), "--out", str(tmp_path / "o3"))
    assert_one_line_error(proc, "shoe_size")
    for name in ("o1", "o2", "o3", "m.json"):
        assert not (tmp_path / name).exists()


def test_measure_garmentcode_body(garmentcode_dir: Path, tmp_path: Path):
    import yaml

    out = tmp_path / "m.json"
    assert main(["measure", str(garmentcode_dir / "bodies" / "mean_female.obj"), "--out", str(out)]) == 0
    measured = json.loads(out.read_text())["measured"]
    truth = yaml.safe_load((garmentcode_dir / "bodies" / "mean_female.yaml").read_text())["body"]
    for key in ("bust", "waist", "hips"):
        assert abs(measured[key] * 100 - truth[key]) < 1.5, key
