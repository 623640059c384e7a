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


def test_staged_output_refuses_empty_and_file_names(tmp_path: Path, monkeypatch):
    from torchgarment.errors import InputError

    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match="empty"):
        with staged_output("") as stage:
            (stage / "a.txt").write_text("a")
    (tmp_path / "f").write_text("not a folder")
    with pytest.raises(InputError, match="not a folder"):
        with staged_output(tmp_path / "f"):
            pass
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]


def test_staged_output_moves_nothing_when_an_output_name_is_a_folder(tmp_path: Path):
    """A folder named like an output file: nothing is moved, the old set stays whole (issue 17)."""
    from torchgarment.errors import InputError

    out = tmp_path / "out"
    out.mkdir()
    (out / "a.txt").write_text("old a")
    (out / "b.txt").mkdir()
    with pytest.raises(InputError, match="is a folder where an output file goes"):
        with staged_output(out) as stage:
            (stage / "a.txt").write_text("new a")
            (stage / "b.txt").write_text("new b")
    assert (out / "a.txt").read_text() == "old a" and (out / "b.txt").is_dir()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_cli_refuses_an_empty_out_before_any_work(tmp_path: Path, monkeypatch, capsys):
    from torchgarment.cli import main

    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:
        main(["adjust", "--garment", "straight_skirt", "--base-size", "12", "--target-size", "14",
              "--out", ""])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "--out is empty" in err[0]
    assert list(tmp_path.iterdir()) == []


def test_orphan_stages_of_killed_runs_are_removed_by_the_next_run(tmp_path):
    """Issue 17: a ``pattern`` killed while writing left its hidden staging folder for ever."""
    import os
    import time

    from torchgarment.io.staging import remove_orphan_stages

    out = tmp_path / "o"
    old = tmp_path / ".o.staging-dead"
    old.mkdir()
    (old / "pattern.json").write_text("{}")
    young = tmp_path / ".o.staging-busy"  # a writer may still be at work
    young.mkdir()
    other = tmp_path / ".p.staging-dead"  # another output's stage: not ours to judge
    other.mkdir()
    hour_ago = time.time() - 7200
    for d in (old, other):
        os.utime(d, (hour_ago, hour_ago))
    with staged_output(out) as stage:
        (stage / "a.txt").write_text("a")
    assert not old.exists() and young.is_dir() and other.is_dir()
    assert (out / "a.txt").read_text() == "a"
    assert remove_orphan_stages(tmp_path / "p") == 1 and not other.exists()


def test_orphan_temporaries_of_killed_writers_are_removed(tmp_path):
    """Issue 17: a ``kill -9`` while the SDF cache was written left a 40 MB ``.tmp.npz`` for ever; caches
    remove such temporaries older than an hour when they store an entry."""
    import os
    import time

    from torchgarment.io.atomic import remove_orphan_temporaries

    old, young = tmp_path / ".sdf_ab.1234.tmp.npz", tmp_path / ".sdf_cd.5678.tmp.npz"
    entry = tmp_path / "sdf_ab.npz"
    for f in (old, young, entry):
        f.write_bytes(b"x")
    os.utime(old, (time.time() - 7200, time.time() - 7200))
    os.utime(entry, (time.time() - 7200, time.time() - 7200))
    assert remove_orphan_temporaries(tmp_path) == 1
    assert not old.exists() and young.exists() and entry.exists()


def test_a_failing_write_names_the_output_not_the_temporaries(tmp_path):
    """Issue 17: temporary names (the hidden stage, ``.name.xxxx.tmp.png``) leaked into error messages."""
    import errno

    from torchgarment.io.atomic import atomic_path

    out = tmp_path / "o"
    with pytest.raises(OSError) as info:
        with staged_output(out) as stage:
            with atomic_path(stage / "pattern.png") as tmp:
                raise OSError(errno.ENOSPC, "No space left on device", str(tmp))
    message = str(info.value)
    assert str(out / "pattern.png") in message and ".staging-" not in message and ".tmp" not in message
    assert not out.exists() and list(tmp_path.iterdir()) == []
