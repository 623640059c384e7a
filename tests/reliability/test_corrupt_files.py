"""Issue 17: a corrupt model file (``pca.pt``, a data set) is refused in one line that never suggests
``weights_only=False`` (torch's own multi-line message does: loading that way would run code from the
file)."""

from __future__ import annotations

import collections

import pytest
import torch

from torchgarment.errors import InputError
from torchgarment.io.payload import load_payload


def test_corrupt_or_foreign_payloads_are_refused_in_one_line(tmp_path):
    garbage = tmp_path / "pca.pt"
    garbage.write_bytes(b"\x00garbage" * 10)
    foreign = tmp_path / "foreign.pt"
    torch.save({"format": "torchgarment.body_pca/1", "x": collections.OrderedDict(a=slice(1, 2))}, foreign)
    truncated = tmp_path / "truncated.pt"
    torch.save({"format": "torchgarment.body_pca/1", "mean": torch.zeros(1000)}, truncated)
    truncated.write_bytes(truncated.read_bytes()[:200])
    for path in (garbage, foreign, truncated):
        with pytest.raises(InputError) as info:
            load_payload(path, "torchgarment.body_pca/1", "PCA body model")
        msg = str(info.value)
        assert "\n" not in msg and "weights_only" not in msg and "corrupt" in msg and str(path) in msg
    ok = tmp_path / "ok.pt"
    torch.save({"format": "torchgarment.body_pca/1", "mean": torch.zeros(3)}, ok)
    assert load_payload(ok, "torchgarment.body_pca/1", "PCA body model")["mean"].shape == (3,)


def test_a_publish_that_fails_half_way_leaves_the_whole_old_set(tmp_path, monkeypatch):
    """Issue 17: when a move fails half-way, DIR used to end with the new pattern.json / pattern.dxf and the
    old pattern.png / pattern.svg; now it keeps the whole old set (and the files the new set does not name),
    and no hidden staging or backup folder is left."""
    import os

    from torchgarment.io import staging

    out = tmp_path / "out"
    out.mkdir()
    names = ("pattern.dxf", "pattern.json", "pattern.png", "pattern.svg")
    for n in names:
        (out / n).write_text("old " + n)
    (out / "notes.txt").write_text("mine")
    real = os.replace
    calls = {"n": 0}

    def flaky(src, dst):
        calls["n"] += 1
        if calls["n"] == 5:  # the third file's move aside, after two files were replaced
            raise OSError("simulated failure")
        return real(src, dst)

    monkeypatch.setattr(staging.os, "replace", flaky)
    with pytest.raises(OSError, match="simulated"):
        with staging.staged_output(out) as stage:
            for n in names:
                (stage / n).write_text("new " + n)
    monkeypatch.setattr(staging.os, "replace", real)
    assert {p.name: p.read_text() for p in out.iterdir()} == {**{n: "old " + n for n in names},
                                                               "notes.txt": "mine"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    with staging.staged_output(out) as stage:  # and a publish that succeeds replaces the whole set
        for n in names:
            (stage / n).write_text("new " + n)
    assert {p.name: p.read_text() for p in out.iterdir()} == {**{n: "new " + n for n in names},
                                                               "notes.txt": "mine"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


@pytest.mark.parametrize("where", ["translation", "boundary"])
def test_nan_in_a_dxf_is_named_as_such(tmp_path, where, cli, one_line):
    """Issue 17: a NaN in a DXF was reported as a "bad TORCHGARMENT entry" (or, in a boundary vertex, as a
    stitch to an unknown piece); it is now named as a non-finite number, in one line, exit 2."""
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.dxf import save_dxf
    from torchgarment.pattern.library import draft

    save_dxf(tmp_path / "p.dxf", draft("straight_skirt", chart_row("12")))
    lines = (tmp_path / "p.dxf").read_text().split("\n")
    if where == "translation":
        i = next(i for i, ln in enumerate(lines) if ln.startswith("translation "))
        lines[i] = "translation nan 0.0 0.1"
    else:  # the first boundary vertex's x
        v = lines.index("VERTEX")
        x = next(j for j in range(v, v + 20) if lines[j].strip() == "10")
        lines[x + 1] = "nan"
    (tmp_path / "bad.dxf").write_text("\n".join(lines))
    line = one_line(cli("pattern", "bad.dxf", "--out", "o", cwd=tmp_path), "non-finite")
    assert "skirt_front" in line and "bad TORCHGARMENT entry" not in line
    assert not (tmp_path / "o").exists()
