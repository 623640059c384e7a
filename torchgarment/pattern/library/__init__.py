"""Built-in sewing patterns drafted from body measurements, placed around the body, with explicit stitches.

Body frame of the placements: +Y up, feet at y = 0, body centred on the Y axis, front facing +Z, the body's
left at +X. Front panels lie in a plane in front of the body (``z > 0``, outside normal +Z), back panels
behind it (rotated 180 deg about Y), sleeves beside the arms along ``arm_angle``; every panel outline is
counter-clockwise seen from outside and clears the body by a few centimetres.

Example::

    from torchgarment.pattern.library import draft
    pattern = draft("tshirt", {"height": 1.65, "bust": 0.9, "underbust": 0.78, "waist": 0.72, "hips": 0.98},
                    bust_ease=0.1)
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable

from torchgarment.errors import InputError
from torchgarment.pattern.library.aline_skirt import aline_skirt
from torchgarment.pattern.library.bodysuit import bodysuit
from torchgarment.pattern.library.measurements import DraftMeasurements
from torchgarment.pattern.library.sheath_dress import sheath_dress
from torchgarment.pattern.library.straight_skirt import straight_skirt
from torchgarment.pattern.library.trousers import trousers
from torchgarment.pattern.library.tshirt import tshirt
from torchgarment.pattern.spec import SewingPattern

GARMENTS: dict[str, Callable[..., SewingPattern]] = {
    "straight_skirt": straight_skirt,
    "aline_skirt": aline_skirt,
    "sheath_dress": sheath_dress,
    "tshirt": tshirt,
    "trousers": trousers,
    "bodysuit": bodysuit,
}


def list_garments() -> list[str]:
    """Names of the built-in garments, in registry order."""
    return list(GARMENTS)


def draft_options(name: str) -> dict[str, float]:
    """The drafting options (ease, lengths; metres or radians) of a garment with their defaults."""
    fn = _lookup(name)
    return {p.name: p.default for p in inspect.signature(fn).parameters.values() if p.kind is p.KEYWORD_ONLY}


def draft(name: str, measurements: DraftMeasurements | dict[str, float], **ease: float) -> SewingPattern:
    """Draft a built-in garment for a body.

    Args:
        name: one of :func:`list_garments`.
        measurements: :class:`DraftMeasurements` or a dict of measurement names to metres.
        **ease: the garment's drafting options (see :func:`draft_options`); unknown names raise InputError.

    Returns:
        a validated :class:`SewingPattern`.
    """
    fn = _lookup(name)
    options = draft_options(name)
    unknown = sorted(set(ease) - set(options))
    if unknown:
        raise InputError(f"unknown option(s) {unknown} for '{name}'; valid options: {sorted(options)}")
    values = {}
    for k, v in ease.items():
        try:
            values[k] = float(v)
        except (TypeError, ValueError):
            raise InputError(f"option '{k}' must be a number, got {v!r}") from None
        if not math.isfinite(values[k]):
            raise InputError(f"option '{k}' must be finite, got {v!r}")
    m = (measurements if isinstance(measurements, DraftMeasurements)
         else DraftMeasurements.from_dict(measurements))
    pattern = fn(m, **values)
    pattern.validate()
    return pattern


def _lookup(name: str) -> Callable[..., SewingPattern]:
    if name not in GARMENTS:
        raise InputError(f"unknown garment '{name}'; valid names: {', '.join(GARMENTS)}")
    return GARMENTS[name]


__all__ = ["GARMENTS", "DraftMeasurements", "draft", "draft_options", "list_garments"]
