"""Sheath dress: bodice and skirt in one front and one back panel, shaped side seams, sleeveless."""

from __future__ import annotations

from torchgarment.errors import InputError
from torchgarment.pattern.library.blocks import neck_frame, positive
from torchgarment.pattern.library.builder import Chain, side_curve
from torchgarment.pattern.library.measurements import DraftMeasurements
from torchgarment.pattern.library.torso import draft_torso
from torchgarment.pattern.spec import SewingPattern


def sheath_dress(m: DraftMeasurements, *, bust_ease: float = 0.05, waist_ease: float = 0.03,
                 hip_ease: float = 0.04, front_bias: float = 0.005, length_below_knee: float = 0.05,
                 neck_widening: float = 0.01, front_neck_drop: float = 0.02) -> SewingPattern:
    """Draft a sheath dress (Aldrich close-fitting dress block ease: bust +5, waist +3, hips +4 cm).

    Each panel runs from the hem up the side seam (straight to the hip line, cubic in to the waist, cubic out
    to the underarm point on the bust line), around the armhole to the shoulder point, along the shoulder
    to the neck point and round the neckline; there are no darts, so the bust shaping of a woven dress is
    missing (suits stretch fabrics).

    Args:
        m: body measurements (metres).
        bust_ease, waist_ease, hip_ease: ease on the girths (metres).
        front_bias: side seam moved backwards, per quarter (metres).
        length_below_knee: hem below the knee (metres).
        neck_widening: added to the half neck width (metres).
        front_neck_drop: added to the front neck depth (metres).

    Returns:
        pattern with panels ``dress_front`` and ``dress_back``: side seams (three segments each side) and
        shoulder seams.
    """
    for k, v in (("bust_ease", bust_ease), ("waist_ease", waist_ease), ("hip_ease", hip_ease),
                 ("front_bias", front_bias), ("neck_widening", neck_widening),
                 ("front_neck_drop", front_neck_drop)):
        positive(k, v, allow_zero=True)
    hem = m.knee_height - length_below_knee
    if hem <= 0.02:
        raise InputError(f"length_below_knee {length_below_knee} m puts the hem at or below the floor")
    bq, wq, hq = (m.bust + bust_ease) / 4, (m.waist + waist_ease) / 4, (m.hips + hip_ease) / 4
    neck = neck_frame(m, neck_widening=neck_widening, front_neck_drop=front_neck_drop)

    def lower(sign: float) -> Chain:
        d = sign * front_bias
        c = Chain.start((0.0, hem)).line((hq + d, hem), "hem_r").line((hq + d, m.hip_height), "side_low_r")
        side_curve((hq + d, m.hip_height), (wq + d, m.waist_height), c, "side_hip_r")
        side_curve((wq + d, m.waist_height), (bq + d, m.bust_height), c, "side_bust_r")
        return c

    t = draft_torso("dress", m, lower, neck, ["side_low", "side_hip", "side_bust"])
    # no support: it hangs from the shoulders
    return SewingPattern(name="sheath_dress", support=(), panels=t.panels, stitches=t.stitches, metadata={
        "garment": "sheath_dress", "measurements": m.to_dict(),
        "options": {"bust_ease": bust_ease, "waist_ease": waist_ease, "hip_ease": hip_ease,
                    "front_bias": front_bias, "length_below_knee": length_below_knee,
                    "neck_widening": neck_widening, "front_neck_drop": front_neck_drop}})


__all__ = ["sheath_dress"]
