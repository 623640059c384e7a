"""Shared skirt drafting: one front and one back panel (cut on the fold), shaped side seams."""

from __future__ import annotations

from torchgarment.errors import InputError
from torchgarment.pattern.library.blocks import panel_depth, positive, skirt_half
from torchgarment.pattern.library.builder import make_panel, mirror_half, place_back, place_front, seam
from torchgarment.pattern.library.measurements import DraftMeasurements
from torchgarment.pattern.spec import SewingPattern


def draft_skirt(name: str, m: DraftMeasurements, *, waist_ease: float, hip_ease: float, front_bias: float,
                length_below_knee: float, flare: float) -> SewingPattern:
    """Front and back skirt panels with side seams; see :mod:`torchgarment.pattern.library.blocks`.

    The front panel's waist/hip widths are ``(girth + ease) / 2 + 2 front_bias``, the back ones
    ``(girth + ease) / 2 - 2 front_bias``, so the sum over both panels is exactly ``girth + ease``.
    """
    positive("waist_ease", waist_ease, allow_zero=True)
    positive("hip_ease", hip_ease, allow_zero=True)
    positive("front_bias", front_bias, allow_zero=True)
    if not 0.0 <= flare < 0.8:
        raise InputError(f"drafting option 'flare' must be in [0, 0.8) rad, got {flare}")
    hem = m.knee_height - length_below_knee
    if hem <= 0.02:
        raise InputError(f"length_below_knee {length_below_knee} m puts the hem at or below the floor")
    wq = (m.waist + waist_ease) / 4.0
    hq = (m.hips + hip_ease) / 4.0
    if wq - front_bias <= 0.02 or hq - front_bias <= 0.02:
        raise InputError("front_bias leaves no back panel")
    z = panel_depth(m)
    panels, index = {}, {}
    for part, sign, placer in (("front", 1.0, place_front), ("back", -1.0, place_back)):
        half = skirt_half(m, waist_width=wq + sign * front_bias, hip_width=hq + sign * front_bias,
                          hem_height=hem, flare=flare)
        panel, idx = make_panel(f"skirt_{part}", mirror_half(half), closed=True, label=f"skirt_{part}")
        panels[panel.name] = placer(panel, z)
        index[part] = idx
    stitches = [
        seam("skirt_front", index["front"], f"{e}_r", "skirt_back", index["back"], f"{e}_l")
        for e in ("side_low", "side_hip")
    ] + [
        seam("skirt_front", index["front"], f"{e}_l", "skirt_back", index["back"], f"{e}_r")
        for e in ("side_low", "side_hip")
    ]
    # held up by the waist line (the waistband): the top edges of both panels
    support = tuple((f"skirt_{part}", f"waist_{side}") for part in ("front", "back") for side in ("r", "l"))
    return SewingPattern(name=name, panels=panels, stitches=stitches, support=support, metadata={
        "garment": name, "measurements": m.to_dict(),
        "options": {"waist_ease": waist_ease, "hip_ease": hip_ease, "front_bias": front_bias,
                    "length_below_knee": length_below_knee, "flare": flare}})
