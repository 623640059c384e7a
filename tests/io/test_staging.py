"""Staged output folders publish only on success."""

from pathlib import Path

import pytest

from torchgarment.io.atomic import atomic_open, atomic_path
from torchgarment.io.staging import staged_output


def test_staged_output_publishes_files_on_success(tmp_path: Path):
    out = tmp_path / "out"
    with staged_output(out) as stage:
        (stage / "a.txt").write_text("a")
        (stage / "sub").mkdir()
        (stage / "sub" / "b.txt").write_text("b")
    assert (out / "a.txt").read_text() == "a"
    assert (out / "sub" / "b.txt").read_text() == "b"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_staged_output_leaves_nothing_on_failure(tmp_path: Path):
    out = tmp_path / "out"
    with pytest.raises(RuntimeError):
        with staged_output(out) as stage:
            (stage / "a.txt").write_text("a")
            raise RuntimeError("boom")
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


def test_atomic_write_keeps_old_file_on_failure(tmp_path: Path):
    target = tmp_path / "f.json"
    target.write_text("old")
    with pytest.raises(ValueError):
        with atomic_open(target) as f:
            f.write("new, half")
            raise ValueError("stop")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["f.json"]


def test_atomic_path_keeps_suffix(tmp_path: Path):
    with atomic_path(tmp_path / "x.png") as tmp:
        assert tmp.suffix == ".png"
        tmp.write_bytes(b"1")
    assert (tmp_path / "x.png").read_bytes() == b"1"


def test_atomic_files_get_ordinary_permissions(tmp_path: Path):
    import os

    umask = os.umask(0o022)
    try:
        with atomic_open(tmp_path / "p.txt") as f:
            f.write("x")
    finally:
        os.umask(umask)
    assert (tmp_path / "p.txt").stat().st_mode & 0o777 == 0o644
