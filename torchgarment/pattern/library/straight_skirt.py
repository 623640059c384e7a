"""Straight skirt: waist-to-hip shaped side seams, straight side seams from hip to a knee-length hem."""

from __future__ import annotations

from torchgarment.pattern.library.measurements import DraftMeasurements
from torchgarment.pattern.library.skirts import draft_skirt
from torchgarment.pattern.spec import SewingPattern


def straight_skirt(m: DraftMeasurements, *, waist_ease: float = 0.01, hip_ease: float = 0.04,
                   front_bias: float = 0.005, length_below_knee: float = 0.05) -> SewingPattern:
    """Draft a straight skirt (Aldrich skirt block ease: waist +1 cm, hips +4 cm).

    Args:
        m: body measurements (metres).
        waist_ease, hip_ease: ease added to the waist and hip girths (metres).
        front_bias: how far the side seam sits behind the body's side, per quarter (metres).
        length_below_knee: hem distance below the knee (metres).

    Returns:
        pattern with panels ``skirt_front`` and ``skirt_back`` and four side-seam stitches, supported by the
        waist line (edges ``waist_r`` and ``waist_l`` of both panels).
    """
    pattern = draft_skirt("straight_skirt", m, waist_ease=waist_ease, hip_ease=hip_ease,
                          front_bias=front_bias,
                          length_below_knee=length_below_knee, flare=0.0)
    del pattern.metadata["options"]["flare"]  # not an option of the straight skirt
    return pattern
