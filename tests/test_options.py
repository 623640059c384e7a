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
