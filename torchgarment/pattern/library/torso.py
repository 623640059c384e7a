"""Shared assembly of torso garments: front and back panels cut on the fold, side and shoulder seams."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from torchgarment.pattern.library.blocks import Neck, add_armhole_shoulder_neck, panel_depth
from torchgarment.pattern.library.builder import Chain, make_panel, mirror_half, place_back, place_front, seam
from torchgarment.pattern.library.measurements import DraftMeasurements
from torchgarment.pattern.spec import Panel, Stitch


@dataclass
class Torso:
    """Placed front and back panels, their edge-label maps, seams and the panels' distance from the axis."""

    panels: dict[str, Panel]
    index: dict[str, dict[str, int]]
    stitches: list[Stitch]
    depth: float


def draft_torso(prefix: str, m: DraftMeasurements, lower: Callable[[float], Chain], neck: Neck,
                seams: list[str]) -> Torso:
    """Build ``{prefix}_front`` and ``{prefix}_back``.

    Args:
        prefix: panel name prefix.
        m: measurements.
        lower: ``lower(sign)`` returns the right half from its bottom centre up to the underarm point, for the
            front (``sign = +1``) or the back (``sign = -1``).
        neck: shoulder/neck frame.
        seams: labels (without side suffix) of the right-half segments sewn front to back; the shoulder is
            always sewn.

    Returns:
        the two placed panels and the side/shoulder stitches (front ``_r`` to back ``_l`` is the body's left).
    """
    z = panel_depth(m)
    panels, index = {}, {}
    for part, sign, placer in (("front", 1.0, place_front), ("back", -1.0, place_back)):
        half = add_armhole_shoulder_neck(lower(sign), neck, front=sign > 0)
        panel, idx = make_panel(f"{prefix}_{part}", mirror_half(half), closed=True, label=f"{prefix}_{part}")
        panels[panel.name] = placer(panel, z)
        index[part] = idx
    f, b = f"{prefix}_front", f"{prefix}_back"
    stitches = []
    for label in [*seams, "shoulder"]:
        stitches.append(seam(f, index["front"], f"{label}_r", b, index["back"], f"{label}_l"))
        stitches.append(seam(f, index["front"], f"{label}_l", b, index["back"], f"{label}_r"))
    return Torso(panels, index, stitches, z)
