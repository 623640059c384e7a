"""Reading the tagged ``torch.save`` dictionaries that models and data sets are stored as."""

from __future__ import annotations

import os
from pathlib import Path

import torch

from torchgarment.errors import InputError


def load_payload(path: str | os.PathLike, fmt: str, what: str) -> dict:
    """The dictionary saved at ``path`` with ``payload["format"] == fmt`` (tensors on the CPU).

    Args:
        path: file written with ``torch.save`` (plain tensors and Python containers only).
        fmt: the expected format tag, e.g. ``"torchgarment.body_pca/1"``.
        what: what the file holds, for the messages (e.g. ``"PCA body model"``).

    Raises:
        InputError: missing file, unreadable file, or a file of another format (one line each).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} {path} does not exist")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is bad input
        # torch's own message is several lines and suggests weights_only=False, which would run code from
        # the file: never pass it on
        raise InputError(f"{path} is not a readable {what}: corrupt, truncated or not written by "
                         f"torchgarment ({type(exc).__name__}); write it again") from None
    if not isinstance(payload, dict) or payload.get("format") != fmt:
        raise InputError(f"{path} is not a torchgarment {what} (format {fmt})")
    return payload
