"""OptionEnum: option names resolve to members, unknown names give one clear InputError."""

import pytest

from torchgarment.errors import InputError
from torchgarment.options import OptionEnum


class ColourMode(OptionEnum):
    FLAT = "flat"
    SMOOTH = "smooth"

    @classmethod
    def aliases(cls) -> dict[str, str]:
        return {"gouraud": "smooth"}


def test_resolve_members_names_and_aliases():
    assert ColourMode.resolve(ColourMode.FLAT) is ColourMode.FLAT
    assert ColourMode.resolve(" Smooth ") is ColourMode.SMOOTH
    assert ColourMode.resolve("GOURAUD") is ColourMode.SMOOTH


def test_unknown_name_lists_the_valid_ones():
    with pytest.raises(InputError) as e:
        ColourMode.resolve("phong")
    assert str(e.value) == "unknown colour mode 'phong'; expected one of: flat, smooth, gouraud (= smooth)"


def test_resolve_device() -> None:
    import torch

    from torchgarment.options import resolve_device

    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(" CPU ") == torch.device("cpu")
    for bad in ("gpu", "mps", "cuda:x"):
        with pytest.raises(InputError, match="expected one of cpu, cuda"):
            resolve_device(bad)
    if not torch.cuda.is_available():
        with pytest.raises(InputError, match="CUDA is not available on this machine"):
            resolve_device("cuda")
    else:
        with pytest.raises(InputError, match="CUDA device"):
            resolve_device(f"cuda:{torch.cuda.device_count()}")
