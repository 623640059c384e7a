"""A built-in women's size chart (US "Misses" sizes 6 to 20), in metres.

Source and choice
-----------------
The rows are the US *Misses* body-measurement chart: the body (not garment) measurements that US
sewing-pattern makers have drafted Misses sizes to since the 1967 revision by the Measurement Standard
Committee of the Pattern Fashion Industry, the system that the US National Bureau of Standards' Voluntary
Product Standard PS 42-70 ("Body Measurements for the Sizing of Women's Patterns and Apparel", 1971, a US
government work) standardised. The figures are published openly in every pattern catalogue; the copy used here
is the table reproduced at http://sewingscholar.blogspot.com/2011/02 ("Misses Sizing: designed for the female
American figure of average proportions, 5'5" to 5'6" tall without shoes"). Measurement figures are facts, free
to use.

Why this chart: it is a real, widely used, openly published *size chart* (labels "6" ... "20" that users
know), for one body type at one height, so sizes differ by girths only, which is what garment grading needs.
Raw anthropometric surveys (e.g. ANSUR II) are public domain too but are not size charts: turning them into
one requires choosing a sizing system, which would make the numbers ours rather than the source's.

Columns (the source gives inches; converted exactly with 1 in = 0.0254 m):

* ``bust``, ``waist``, ``hips``: straight from the source (its "Hip" is the full-hip girth).
* ``height``: the source gives the range 5'5" to 5'6" for every size; its midpoint 65.5 in = 1.6637 m is used.
* ``underbust``: not in the source. Derived with the rule ``underbust = bust * UNDERBUST_RATIO`` where
  :data:`UNDERBUST_RATIO` = 80.7483 / 97.4076 is the underbust-to-bust ratio of the GarmentCode mean female
  body (``garmentcode/bodies/mean_female.yaml``, cm), the reference body of the garment data this library
  targets.
"""

from __future__ import annotations

from torchgarment.errors import InputError

INCH = 0.0254
"""One inch in metres."""

UNDERBUST_RATIO = 80.7483 / 97.4076
"""Underbust / bust of the GarmentCode mean female body; the rule that derives the ``underbust`` column."""

SOURCE = "US Misses body-measurement chart (pattern industry 1967 / NBS PS 42-70), sizes 6-20"
"""Short citation of the chart, stored in the params of bodies made from it."""

_HEIGHT_IN = 65.5  # midpoint of 5'5" .. 5'6"

# size: (bust, waist, hip) in inches, as published.
_MISSES_IN: dict[str, tuple[float, float, float]] = {
    "6": (30.5, 23.0, 32.5),
    "8": (31.5, 24.0, 33.5),
    "10": (32.5, 25.0, 34.5),
    "12": (34.0, 26.5, 36.0),
    "14": (36.0, 28.0, 38.0),
    "16": (38.0, 30.0, 40.0),
    "18": (40.0, 32.0, 42.0),
    "20": (42.0, 34.0, 44.0),
}

SIZES: tuple[str, ...] = tuple(_MISSES_IN)
"""Size labels, smallest first."""


def list_sizes() -> list[str]:
    """The size labels of the chart, smallest first."""
    return list(SIZES)


def chart_row(size: str | int) -> dict[str, float]:
    """Body measurements of one size, metres.

    Args:
        size: a label of :data:`SIZES` (``"6"`` ... ``"20"``); an int is accepted (``12`` is ``"12"``).

    Returns:
        ``{"height", "bust", "underbust", "waist", "hips"}`` in metres.

    Raises:
        InputError: unknown size; the message lists the valid ones.
    """
    key = str(size).strip()
    if key not in _MISSES_IN:
        raise InputError(f"unknown size {size!r}; valid sizes: {', '.join(SIZES)}")
    bust, waist, hip = _MISSES_IN[key]
    return {
        "height": _HEIGHT_IN * INCH,
        "bust": bust * INCH,
        "underbust": bust * INCH * UNDERBUST_RATIO,
        "waist": waist * INCH,
        "hips": hip * INCH,
    }
