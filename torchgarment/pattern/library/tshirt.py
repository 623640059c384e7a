"""T-shirt: front and back cut on the fold, two-piece set-in short sleeves, round neckline."""

from __future__ import annotations

import math

import numpy as np

from torchgarment.errors import InputError
from torchgarment.pattern.library.blocks import CLEARANCE, armhole_length, neck_frame, positive, sleeve_half
from torchgarment.pattern.library.builder import Chain, make_panel, place, seam
from torchgarment.pattern.library.measurements import DraftMeasurements
from torchgarment.pattern.library.torso import draft_torso
from torchgarment.pattern.spec import SewingPattern


def tshirt(m: DraftMeasurements, *, bust_ease: float = 0.08, hip_ease: float = 0.06,
           sleeve_ease: float = 0.04,
           cap_ease: float = 0.0, sleeve_length: float = 0.22, armhole_drop: float = 0.03,
           length_below_hip: float = 0.03,
           shoulder_extension: float = 0.015, neck_widening: float = 0.015,
           front_neck_drop: float = 0.01) -> SewingPattern:
    """Draft a jersey T-shirt (ease after Aldrich's jersey/easy-fitting blocks).

    The bust width ``(bust + bust_ease) / 4`` per quarter is squared across the armscye line, which lies
    ``armhole_drop`` below the bust line (Aldrich's easy-fitting blocks lower the armhole); the body panels
    are straight from the underarm point to the waist line, then flare or taper straight to the hem at
    ``(max(bust + bust_ease, hips + hip_ease)) / 4``. Front and back armholes are identical, so each sleeve is
    two identical halves (front and back, joined by overarm and underarm seams) whose cap height is solved so
    that the cap is ``1 + cap_ease`` times the armhole (jersey: no cap ease).

    Args:
        m: body measurements (metres).
        bust_ease, hip_ease: ease on bust and hip girths (metres).
        sleeve_ease: ease on the upper-arm girth (metres).
        cap_ease: sleeve-cap length excess over the armhole, as a fraction (woven sleeves use 0.03..0.08).
        sleeve_length: shoulder point to sleeve hem along the arm (metres).
        armhole_drop: armscye line below the bust line (metres).
        length_below_hip: hem below the hip line (metres).
        shoulder_extension: shoulder point moved beyond the body's (metres).
        neck_widening: added to the half neck width (metres).
        front_neck_drop: added to the front neck depth (metres).

    Returns:
        pattern with panels ``tshirt_front``, ``tshirt_back`` and ``sleeve_{front,back}_{left,right}``.
    """
    for k, v in (("bust_ease", bust_ease), ("hip_ease", hip_ease), ("sleeve_ease", sleeve_ease),
                 ("cap_ease", cap_ease), ("armhole_drop", armhole_drop),
                 ("shoulder_extension", shoulder_extension),
                 ("neck_widening", neck_widening), ("front_neck_drop", front_neck_drop)):
        positive(k, v, allow_zero=True)
    positive("sleeve_length", sleeve_length)
    if cap_ease > 0.15:
        raise InputError(f"cap_ease {cap_ease} is more than the 15% a sleeve cap can be eased in")
    hem = m.hip_height - length_below_hip
    if hem <= m.crotch_height - 0.1:
        raise InputError(f"length_below_hip {length_below_hip} m is too long for a T-shirt")
    bq = (m.bust + bust_ease) / 4
    hq = max(m.bust + bust_ease, m.hips + hip_ease) / 4
    neck = neck_frame(m, shoulder_extension=shoulder_extension, neck_widening=neck_widening,
                      front_neck_drop=front_neck_drop, same_armholes=True)
    underarm = np.array([bq, m.bust_height - armhole_drop])
    if underarm[1] < m.waist_height + 0.05:
        raise InputError(f"armhole_drop {armhole_drop} m lowers the armhole to the waist")

    def lower(sign: float) -> Chain:
        c = Chain.start((0.0, hem)).line((hq, hem), "hem_r").line((bq, m.waist_height), "side_low_r")
        return c.line(underarm, "side_up_r")

    t = draft_torso("tshirt", m, lower, neck, ["side_low", "side_up"])
    panels, stitches = dict(t.panels), list(t.stitches)

    cap_length = armhole_length(neck, underarm, front=True) * (1.0 + cap_ease)
    if abs(armhole_length(neck, underarm, front=False) * (1 + cap_ease) - cap_length) > 1e-9:
        raise AssertionError("front and back armholes differ")  # pragma: no cover - construction invariant
    bicep = m.upper_arm_girth + sleeve_ease
    reach = min(sleeve_length / m.arm_length, 1.0)
    cuff = bicep - (m.upper_arm_girth - m.wrist_girth) * reach
    half = sleeve_half(cap_length=cap_length, bicep_half=bicep / 2, cuff_half=cuff / 2, length=sleeve_length)
    z = t.depth + CLEARANCE
    a = m.arm_angle
    xs, ys = neck.shoulder_point
    ca, sa = math.cos(a), math.sin(a)
    # (name, mirrored layout?, origin, local x axis, local y axis); the normal x_axis x y_axis points
    # outwards.
    layout = [
        ("sleeve_front_left", False, (xs, ys, z), (ca, -sa, 0.0), (sa, ca, 0.0)),
        ("sleeve_back_left", True, (xs, ys, -z), (-ca, sa, 0.0), (sa, ca, 0.0)),
        ("sleeve_front_right", True, (-xs, ys, z), (ca, sa, 0.0), (-sa, ca, 0.0)),
        ("sleeve_back_right", False, (-xs, ys, -z), (-ca, -sa, 0.0), (-sa, ca, 0.0)),
    ]
    idx = {}
    for name, mirrored, origin, ex, ey in layout:
        chain = half.mirrored() if mirrored else half
        panel, idx[name] = make_panel(name, Chain(chain.points[:], chain.segments[:]), closed=True,
                                      label="sleeve")
        panel.grainline = np.array([1.0, 0.0])  # warp along the arm
        panels[name] = place(panel, origin, ex, ey)
    f, b = "tshirt_front", "tshirt_back"
    fi, bi = t.index["front"], t.index["back"]
    for side, body_front, body_back in (("left", "armhole_r", "armhole_l"),
                                        ("right", "armhole_l", "armhole_r")):
        sf, sb = f"sleeve_front_{side}", f"sleeve_back_{side}"
        stitches.append(seam(f, fi, body_front, sf, idx[sf], "cap"))
        stitches.append(seam(b, bi, body_back, sb, idx[sb], "cap"))
        stitches.append(seam(sf, idx[sf], "overarm", sb, idx[sb], "overarm"))
        stitches.append(seam(sf, idx[sf], "underarm", sb, idx[sb], "underarm"))
    # no support: it hangs from the shoulders
    return SewingPattern(name="tshirt", support=(), panels=panels, stitches=stitches, metadata={
        "garment": "tshirt", "measurements": m.to_dict(),
        "options": {"bust_ease": bust_ease, "hip_ease": hip_ease, "sleeve_ease": sleeve_ease,
                    "cap_ease": cap_ease, "sleeve_length": sleeve_length,
                    "armhole_drop": armhole_drop, "length_below_hip": length_below_hip,
                    "shoulder_extension": shoulder_extension, "neck_widening": neck_widening,
                    "front_neck_drop": front_neck_drop}})
