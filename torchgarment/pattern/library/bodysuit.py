"""Bodysuit (leotard): front and back torso panels with leg openings and a crotch seam, sleeveless."""

from __future__ import annotations

from torchgarment.errors import InputError
from torchgarment.pattern.library.blocks import neck_frame, positive
from torchgarment.pattern.library.builder import Chain, seam, side_curve
from torchgarment.pattern.library.measurements import DraftMeasurements
from torchgarment.pattern.library.torso import draft_torso
from torchgarment.pattern.spec import SewingPattern


def bodysuit(m: DraftMeasurements, *, bust_ease: float = 0.0, waist_ease: float = 0.0, hip_ease: float = 0.0,
             crotch_drop: float = 0.04, gusset_width: float = 0.07, leg_cut: float = 0.0,
             neck_widening: float = 0.01, front_neck_drop: float = 0.02) -> SewingPattern:
    """Draft a bodysuit for stretch fabric (zero ease by default; negative ease is not supported).

    Each panel runs from the crotch edge (a gusset ``gusset_width`` wide, ``crotch_drop`` below the crotch
    so that front and back meet under the body) along a cubic leg opening to the side at the hip line
    (raised by ``leg_cut``), up the shaped side seam to the underarm point on the bust line, round the
    armhole, shoulder and neckline.

    Args:
        m: body measurements (metres).
        bust_ease, waist_ease, hip_ease: ease on the girths (metres).
        crotch_drop: how far each panel's crotch edge lies below the crotch height (metres).
        gusset_width: width of the crotch seam (metres).
        leg_cut: how far above the hip line the leg opening meets the side seam (metres, high-cut legs).
        neck_widening: added to the half neck width (metres).
        front_neck_drop: added to the front neck depth (metres).

    Returns:
        pattern with panels ``bodysuit_front`` and ``bodysuit_back``: crotch seam (two halves), side seams
        (two segments per side) and shoulder seams.
    """
    for k, v in (("bust_ease", bust_ease), ("waist_ease", waist_ease), ("hip_ease", hip_ease),
                 ("crotch_drop", crotch_drop), ("leg_cut", leg_cut), ("neck_widening", neck_widening),
                 ("front_neck_drop", front_neck_drop)):
        positive(k, v, allow_zero=True)
    positive("gusset_width", gusset_width)
    bq, wq, hq = (m.bust + bust_ease) / 4, (m.waist + waist_ease) / 4, (m.hips + hip_ease) / 4
    y_leg = m.hip_height + leg_cut
    y_cr = m.crotch_height - crotch_drop
    if not y_leg < m.waist_height - 0.03:
        raise InputError(f"leg_cut {leg_cut} m raises the leg opening to the waist")
    if gusset_width / 2 >= hq - 0.03:
        raise InputError(f"gusset_width {gusset_width} m is wider than the hips allow")
    neck = neck_frame(m, neck_widening=neck_widening, front_neck_drop=front_neck_drop)

    def lower(sign: float) -> Chain:
        g = 0.5 * gusset_width
        c = Chain.start((0.0, y_cr)).line((g, y_cr), "crotch_r")
        dy = y_leg - y_cr
        c.cubic((g, y_cr + 0.45 * dy), (hq - 0.45 * (hq - g), y_leg), (hq, y_leg), "leg_r")
        side_curve((hq, y_leg), (wq, m.waist_height), c, "side_hip_r")
        side_curve((wq, m.waist_height), (bq, m.bust_height), c, "side_bust_r")
        return c

    t = draft_torso("bodysuit", m, lower, neck, ["side_hip", "side_bust"])
    f, b = "bodysuit_front", "bodysuit_back"
    t.stitches.append(seam(f, t.index["front"], "crotch_r", b, t.index["back"], "crotch_l"))
    t.stitches.append(seam(f, t.index["front"], "crotch_l", b, t.index["back"], "crotch_r"))
    # no support: it hangs from the shoulders
    return SewingPattern(name="bodysuit", support=(), panels=t.panels, stitches=t.stitches, metadata={
        "garment": "bodysuit", "measurements": m.to_dict(),
        "options": {"bust_ease": bust_ease, "waist_ease": waist_ease, "hip_ease": hip_ease,
                    "crotch_drop": crotch_drop, "gusset_width": gusset_width, "leg_cut": leg_cut,
                    "neck_widening": neck_widening, "front_neck_drop": front_neck_drop}})
