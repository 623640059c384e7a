"""JSON files: reading inputs with limits (:func:`read_json`: a size cap and a clear refusal of absurd
nesting, issue 17) and writing outputs atomically (:func:`write_json`).

Python's JSON parser recurses once per nesting level, so a file of 100,000 ``[`` raised a ``RecursionError``
traceback; and a multi-gigabyte file was read whole. :func:`read_json` refuses both with one line.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from torchgarment.errors import InputError

MAX_JSON_BYTES = 64 * 2**20
"""Largest JSON input file in bytes (64 MiB; a GarmentCode pattern or a measurements file is a few kB)."""


def read_json(path: str | Path, what: str = "JSON file", error: type[InputError] = InputError) -> Any:
    """Read and decode a JSON file, refusing what cannot be an input with one line.

    Args:
        path: the file.
        what: what the file should be, for the messages (``"measurements file"``, ``"pattern"``).
        error: the :class:`~torchgarment.errors.InputError` subclass to raise (e.g. ``PatternError``).

    Returns:
        The decoded value (any JSON type).

    Raises:
        InputError (``error``): a folder, no such file, unreadable, larger than :data:`MAX_JSON_BYTES`, not
            UTF-8, malformed, or nested deeper than the parser's recursion limit.
    """
    p = Path(path)
    if p.is_dir():
        raise error(f"{path}: is a folder, not a {what}")
    if not p.is_file():
        raise error(f"{path}: no such file")
    try:
        size = p.stat().st_size
        if size > MAX_JSON_BYTES:
            raise error(f"{path}: {size / 2**20:.1f} MiB is too large for a {what} (limit "
                        f"{MAX_JSON_BYTES // 2**20} MiB)")
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise error(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise error(f"{path}: not a UTF-8 text file, so not a {what}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise error(f"{path}: malformed JSON at line {exc.lineno} column {exc.colno}: {exc.msg}") from None
    except RecursionError:
        raise error(f"{path}: JSON nested too deeply to be a {what}") from None


def write_json(path: str | Path, data: Any) -> None:
    """Write ``data`` as indented JSON with a final newline, atomically (a reader never sees half a file).

    Args:
        path: the file (its folder is created). data: JSON-serialisable plain data; numpy and 0-d tensor
            scalars are written as floats.
    """
    from torchgarment.io.atomic import atomic_open

    with atomic_open(path) as f:
        json.dump(data, f, indent=2, default=float)
        f.write("\n")


__all__ = ["MAX_JSON_BYTES", "read_json", "write_json"]
