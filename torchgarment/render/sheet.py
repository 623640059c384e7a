"""Contact sheets: many results' pictures as labelled thumbnails on one PNG (the batch runner's overview)."""

from __future__ import annotations

import math
import os
from pathlib import Path

__all__ = ["contact_sheet"]


def contact_sheet(tiles: list[tuple[str | os.PathLike | None, str]], path: str | os.PathLike, *,
                  columns: int = 4, tile_size: tuple[int, int] = (480, 200),
                  title: str | None = None) -> Path:
    """Write a grid of thumbnails with a label under each.

    Args:
        tiles: ``(picture, label)`` per cell, in order; a missing picture (None, or no such file) gives a grey
            cell with the label (a failed job).
        path: the PNG to write (atomically).
        columns: cells per row. tile_size: (width, height) of a thumbnail in pixels. title: a line above the
            grid.

    Returns:
        ``path`` as a Path.
    """
    from PIL import Image, ImageDraw, ImageFont

    from torchgarment.io.atomic import atomic_path

    if not tiles:
        raise ValueError("contact_sheet needs at least one tile")
    columns = max(1, min(columns, len(tiles)))
    rows = math.ceil(len(tiles) / columns)
    tw, th = tile_size
    label_h, pad, head = 30, 6, (28 if title else 0)
    sheet = Image.new("RGB", (columns * (tw + pad) + pad, head + rows * (th + label_h + pad) + pad), "white")
    draw = ImageDraw.Draw(sheet)
    font = ImageFont.load_default()
    if title:
        draw.text((pad, 8), title, fill="black", font=font)
    for i, (picture, label) in enumerate(tiles):
        x = pad + (i % columns) * (tw + pad)
        y = head + pad + (i // columns) * (th + label_h + pad)
        if picture is not None and Path(picture).is_file():
            with Image.open(picture) as img:
                img = img.convert("RGB")
                img.thumbnail((tw, th))
                sheet.paste(img, (x + (tw - img.width) // 2, y + (th - img.height) // 2))
        else:
            draw.rectangle([x, y, x + tw - 1, y + th - 1], fill=(215, 215, 215))
            draw.text((x + 8, y + th // 2 - 6), "no picture", fill=(90, 90, 90), font=font)
        for n, line in enumerate(_wrap(label, tw)[:2]):
            draw.text((x, y + th + 3 + 13 * n), line, fill="black", font=font)
    path = Path(path)
    with atomic_path(path) as tmp:
        sheet.save(tmp, format="PNG")
    return path


def _wrap(text: str, width_px: int) -> list[str]:
    chars = max(8, width_px // 6)
    return [text[i:i + chars] for i in range(0, len(text), chars)] or [""]
