"""Disk cache of generated bodies.

Entries live in ``$TORCHGARMENT_CACHE/bodies`` (default ``~/.cache/torchgarment/bodies``), one ``<key>.pt``
file each, written atomically (:mod:`torchgarment.io.atomic`), so a crash never leaves a half-written entry.
The key is a SHA-256 hash of a JSON description of everything the body depends on (the requested measurements,
the generator's version, the fitting code's version); callers build that description. Every entry also stores
its own key (``"_key"``), checked on load: a file copied or moved over another entry (another body's) is
dropped and regenerated instead of served (issue 17). Entries written before the key was stored are read as
they are.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import torch

from torchgarment.io.atomic import atomic_path, remove_orphan_temporaries

ENV_VAR = "TORCHGARMENT_CACHE"
"""Environment variable naming the cache root (default ``~/.cache/torchgarment``)."""


def cache_root() -> Path:
    """The torchgarment cache root: ``$TORCHGARMENT_CACHE`` or ``~/.cache/torchgarment``."""
    env = os.environ.get(ENV_VAR)
    return Path(env).expanduser() if env else Path.home() / ".cache" / "torchgarment"


def bodies_dir() -> Path:
    """Folder of cached bodies: ``cache_root() / "bodies"``."""
    return cache_root() / "bodies"


def cache_key(description: dict) -> str:
    """Hash a JSON-serialisable description of a body into a cache key.

    Floats are rounded to 1e-9 (a nanometre for lengths) so that values equal up to round-off share a key.

    Args:
        description: plain data (dicts, lists, str, int, float, bool).

    Returns:
        A 32-character hex key.
    """

    def norm(x: Any) -> Any:
        if isinstance(x, float):
            return round(x, 9)
        if isinstance(x, dict):
            return {str(k): norm(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [norm(v) for v in x]
        return x

    text = json.dumps(norm(description), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def entry_path(key: str) -> Path:
    """Path of the cache entry of ``key``."""
    return bodies_dir() / f"{key}.pt"


def load_entry(key: str) -> dict | None:
    """Load a cached entry, or None when absent, unreadable or another key's (such an entry is removed).

    Args:
        key: from :func:`cache_key`.

    Returns:
        The stored dict (tensors, lists, strings, numbers), or None.
    """
    path = entry_path(key)
    if not path.is_file():
        return None
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # a truncated or foreign file: drop it, the caller regenerates
        path.unlink(missing_ok=True)
        return None
    if not isinstance(data, dict) or data.get("_key", key) != key:  # another entry's file: not this body
        path.unlink(missing_ok=True)
        return None
    data.pop("_key", None)
    return data


def store_entry(key: str, data: dict) -> Path:
    """Write an entry atomically.

    Args:
        key: from :func:`cache_key`.
        data: tensors, lists, strings and numbers only (loadable with ``weights_only=True``).

    Returns:
        The entry's path.
    """
    path = entry_path(key)
    remove_orphan_temporaries(path.parent)
    with atomic_path(path) as tmp:
        torch.save({**data, "_key": key}, tmp)
    return path
