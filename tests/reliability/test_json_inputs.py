"""Issue 17: JSON inputs that crashed (a ``RecursionError`` traceback on absurd nesting) or could not be what
they claim (a folder, a huge file) end in one line and exit code 2, with nothing written."""

from __future__ import annotations

from pathlib import Path

import pytest

from torchgarment.errors import InputError, PatternError
from torchgarment.io import jsonfile
from torchgarment.io.jsonfile import read_json


@pytest.mark.parametrize("command", [["body", "--measurements"], ["pattern"]])
def test_deeply_nested_json_is_refused_in_one_line(tmp_path: Path, command: list[str], cli, one_line):
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000)
    proc = cli(*command, str(deep), "--out", "o", cwd=tmp_path)
    one_line(proc, "nested too deeply")
    assert not (tmp_path / "o").exists()


def test_read_json_refusals(tmp_path: Path, monkeypatch):
    good = tmp_path / "m.json"
    good.write_text('{"height": 1.7}')
    assert read_json(good) == {"height": 1.7}
    with pytest.raises(InputError, match="is a folder"):
        read_json(tmp_path, "measurements file")
    with pytest.raises(InputError, match="no such file"):
        read_json(tmp_path / "none.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"height": }')
    with pytest.raises(PatternError, match="malformed JSON at line 1 column 12"):
        read_json(bad, "pattern file", PatternError)
    latin = tmp_path / "latin.json"
    latin.write_bytes(b'{"name": "\xe9"}')
    with pytest.raises(InputError, match="not a UTF-8"):
        read_json(latin)
    deep = tmp_path / "deep.json"
    deep.write_text("{\"a\": " * 50_000)
    with pytest.raises(InputError, match="nested too deeply to be a pattern file"):
        read_json(deep, "pattern file")
    monkeypatch.setattr(jsonfile, "MAX_JSON_BYTES", 8)
    with pytest.raises(InputError, match="too large for a measurements file"):
        read_json(good, "measurements file")


@pytest.mark.parametrize("args, needle", [
    (["measure", "folder", "--out", "m.json"], "folder: is a folder or a special file, not a mesh file"),
    (["pattern", "folder", "--out", "o"], "folder: is a folder, not a pattern file"),
    (["body", "--measurements", "folder", "--out", "o"], "folder: is a folder, not a measurements file"),
    (["drape", "--pattern", "straight_skirt", "--size", "12", "--body", "folder", "--out", "o"],
     "--body folder: is a folder"),
])
def test_a_folder_given_as_a_file_is_named_as_such(tmp_path: Path, args, needle, cli, one_line):
    (tmp_path / "folder").mkdir()
    proc = cli(*args, cwd=tmp_path)
    one_line(proc, needle)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder"]


def test_oversized_dxf_is_refused_before_parsing(tmp_path: Path, monkeypatch):
    from torchgarment.pattern import dxf

    big = tmp_path / "big.dxf"
    big.write_text("0\nSECTION\n" * 100)
    monkeypatch.setattr(dxf, "MAX_DXF_BYTES", 100)
    with pytest.raises(PatternError, match="too large for a pattern DXF"):
        dxf.load_dxf(big)
    with pytest.raises(PatternError, match="is a folder"):
        dxf.load_dxf(tmp_path)
