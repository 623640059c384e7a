"""A-line skirt: the straight skirt flared below the hip line, with a curved hem square to the side seams."""

from __future__ import annotations

from torchgarment.pattern.library.measurements import DraftMeasurements
from torchgarment.pattern.library.skirts import draft_skirt
from torchgarment.pattern.spec import SewingPattern


def aline_skirt(m: DraftMeasurements, *, waist_ease: float = 0.01, hip_ease: float = 0.04,
                front_bias: float = 0.005, length_below_knee: float = 0.05,
                flare: float = 0.15) -> SewingPattern:
    """Draft an A-line skirt.

    Args:
        m: body measurements (metres).
        waist_ease, hip_ease: ease added to the waist and hip girths (metres).
        front_bias: how far the side seam sits behind the body's side, per quarter (metres).
        length_below_knee: hem distance below the knee at the centre lines (metres).
        flare: side-seam angle from vertical below the hip line (radians, default 0.15 = 8.6 deg).

    Returns:
        pattern with panels ``skirt_front`` and ``skirt_back`` and four side-seam stitches, supported by the
        waist line (edges ``waist_r`` and ``waist_l`` of both panels).
    """
    return draft_skirt("aline_skirt", m, waist_ease=waist_ease, hip_ease=hip_ease, front_bias=front_bias,
                       length_below_knee=length_below_knee, flare=flare)
