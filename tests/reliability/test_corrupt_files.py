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
