"""Sewing patterns: panels, stitches, GarmentCode JSON, library drafts, SVG/DXF export, meshing.

File formats (``torchgarment.pattern.svg``, ``torchgarment.pattern.dxf``) and plots
(``torchgarment.pattern.plot``) are imported from their modules so that importing this package stays light.
"""

from torchgarment.pattern.garmentcode import load_pattern, save_pattern
from torchgarment.pattern.library import DraftMeasurements, draft, list_garments
from torchgarment.pattern.meshing import mesh_pattern
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

__all__ = [
    "DraftMeasurements",
    "Edge",
    "EdgeKind",
    "EdgeRef",
    "Notch",
    "Panel",
    "SewingPattern",
    "Stitch",
    "StitchOrientation",
    "draft",
    "list_garments",
    "load_pattern",
    "mesh_pattern",
    "save_pattern",
]
