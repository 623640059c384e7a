"""Sewing patterns: panels, stitches, GarmentCode JSON, library drafts, SVG/DXF export, meshing."""

from torchgarment.pattern.spec import (
    Edge,
    EdgeKind,
    EdgeRef,
    Notch,
    Panel,
    SewingPattern,
    Stitch,
    StitchOrientation,
)

__all__ = ["Edge", "EdgeKind", "EdgeRef", "Notch", "Panel", "SewingPattern", "Stitch", "StitchOrientation"]
