"""Reading a pattern file whatever its format (chosen by the file's suffix)."""

from __future__ import annotations

import os
from pathlib import Path

from torchgarment.errors import InputError
from torchgarment.pattern.spec import SewingPattern

PATTERN_SUFFIXES = (".json", ".dxf")
"""Suffixes :func:`load_pattern_file` reads: GarmentCode JSON specifications and AAMA / ASTM D6673 DXF."""


def load_pattern_file(path: str | os.PathLike) -> SewingPattern:
    """Read a GarmentCode ``.json`` specification or an AAMA ``.dxf`` file.

    Raises:
        InputError: the file is missing or has another suffix; PatternError (an InputError) when malformed.
    """
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{path}: is a folder, not a pattern file ({' or '.join(PATTERN_SUFFIXES)})")
    if not p.is_file():
        raise InputError(f"{path}: no such file")
    suffix = p.suffix.lower()
    if suffix == ".json":
        from torchgarment.pattern.garmentcode import load_pattern

        return load_pattern(p)
    if suffix == ".dxf":
        from torchgarment.pattern.dxf import load_dxf

        return load_dxf(p)
    raise InputError(f"{path}: unknown pattern format '{suffix}' (expected {' or '.join(PATTERN_SUFFIXES)})")
