"""Trousers: front and back panel per leg, crotch curves, side seams shaped from hip to waist."""

from __future__ import annotations

from torchgarment.errors import InputError
from torchgarment.pattern.library.blocks import panel_depth, positive, trouser_leg
from torchgarment.pattern.library.builder import Chain, make_panel, place_back, place_front, seam
from torchgarment.pattern.library.measurements import DraftMeasurements
from torchgarment.pattern.spec import SewingPattern

LEG_GAP = 0.01  # distance of each leg's crotch point from the body's mid-plane x = 0 when placed (metres)


def trousers(m: DraftMeasurements, *, waist_ease: float = 0.01, hip_ease: float = 0.05,
             thigh_ease: float = 0.06,
             hem_ratio: float = 0.45, hem_above_ankle: float = 0.0,
             front_bias: float = 0.01) -> SewingPattern:
    """Draft straight-leg trousers after Aldrich's trouser block, without darts or waistband.

    Per leg: front and back panels; hip widths ``(hips + hip_ease) / 4 -/+ front_bias``; crotch extensions
    (forks) front ``H / 16`` and back ``H / 8`` with ``H = hips + hip_ease``, enlarged in the 1 : 2 ratio if
    the leg at crotch level would be narrower than ``thigh + thigh_ease``; the back centre seam slopes in by
    a fifth of the waist suppression, the rest is taken in the side seams; inseam and side seam run straight
    to a hem of girth ``hem_ratio H`` at ankle height (Drillis & Contini 0.039 height) + ``hem_above_ankle``.

    Args:
        m: body measurements (metres).
        waist_ease, hip_ease, thigh_ease: ease on the girths (metres).
        hem_ratio: leg-opening girth as a fraction of the eased hips.
        hem_above_ankle: hem raised above the ankle (metres).
        front_bias: side seam moved forwards at the hip line, per panel (metres).

    Returns:
        pattern with panels ``{front,back}_{left,right}``; seams: inseam, side seam (two segments), centre
        front/back and crotch curves; supported by the waist line (the ``waist`` edge of every panel).
    """
    for k, v in (("waist_ease", waist_ease), ("hip_ease", hip_ease), ("thigh_ease", thigh_ease),
                 ("hem_above_ankle", hem_above_ankle), ("front_bias", front_bias)):
        positive(k, v, allow_zero=True)
    positive("hem_ratio", hem_ratio)
    h_e, w_e = m.hips + hip_ease, m.waist + waist_ease
    fork_f, fork_b = h_e / 16, h_e / 8
    need = m.thigh_girth + thigh_ease - h_e / 2
    if fork_f + fork_b < need:
        fork_f, fork_b = need / 3, 2 * need / 3
    hip_f, hip_b = h_e / 4 - front_bias, h_e / 4 + front_bias
    supp = (h_e - w_e) / 2  # per leg
    cb = max(0.2 * supp, 0.0)
    side = (supp - cb) / 2  # identical side-seam suppression front and back
    hem_girth = hem_ratio * h_e
    crotch_width = hip_f + fork_f + hip_b + fork_b
    run = (crotch_width - hem_girth) / 2  # per panel, shared by front and back so their seams match
    if run < 0:
        raise InputError(f"hem_ratio {hem_ratio} makes the hem wider than the leg at the crotch")
    hem = 0.039 * m.height + hem_above_ankle
    legs = {
        "front": trouser_leg(m, hip_width=hip_f, waist_width=hip_f - side, centre_shift=0.0, fork=fork_f,
                             inseam_run=0.6 * run, side_run=0.4 * run, hem_height=hem),
        "back": trouser_leg(m, hip_width=hip_b, waist_width=hip_b - side - cb, centre_shift=cb, fork=fork_b,
                            inseam_run=0.6 * run, side_run=0.4 * run, hem_height=hem),
    }
    z = panel_depth(m)
    forks = {"front": fork_f, "back": fork_b}
    panels, idx = {}, {}
    for part in ("front", "back"):
        for side_name in ("left", "right"):
            # the left front and right back are the canonical layout; the others are mirrored.
            mirrored = (part == "front") == (side_name == "right")
            chain = legs[part].mirrored("", "") if mirrored else legs[part]
            chain = Chain(chain.points[:], chain.segments[:])
            name = f"{part}_{side_name}"
            panel, idx[name] = make_panel(name, chain, closed=True, label="leg")
            # crotch point at world x = +-(LEG_GAP): local x of the crotch point is -fork (canonical) or +fork
            x = LEG_GAP + forks[part] if side_name == "left" else -(LEG_GAP + forks[part])
            panels[name] = (place_front if part == "front" else place_back)(panel, z, x)
    stitches = []
    for s in ("left", "right"):
        for e in ("inseam", "side_low", "side_hip"):
            stitches.append(seam(f"front_{s}", idx[f"front_{s}"], e, f"back_{s}", idx[f"back_{s}"], e))
    for part in ("front", "back"):
        for e in ("centre", "crotch"):
            stitches.append(seam(f"{part}_left", idx[f"{part}_left"], e, f"{part}_right",
                                 idx[f"{part}_right"], e))
    support = tuple((f"{part}_{s}", "waist") for part in ("front", "back") for s in ("left", "right"))
    return SewingPattern(name="trousers", panels=panels, stitches=stitches, support=support, metadata={
        "garment": "trousers", "measurements": m.to_dict(),
        "options": {"waist_ease": waist_ease, "hip_ease": hip_ease, "thigh_ease": thigh_ease,
                    "hem_ratio": hem_ratio, "hem_above_ankle": hem_above_ankle, "front_bias": front_bias}})


__all__ = ["trousers"]
