"""Disk cache of built body SDFs.

Entries live in ``$TORCHGARMENT_CACHE/sdf`` (default ``~/.cache/torchgarment/sdf``), one ``<key>.npz`` file
each, written atomically by :meth:`BodySDF.save <torchgarment.sdf.grid.BodySDF.save>` in float64, so a hit
returns exactly the values of a fresh build. The key is a SHA-256 hash of the mesh arrays (float64 vertices,
int64 faces, with their shapes), of the settings that change the grid (voxel size, band, brick, sign type; not
the thread count) and of :data:`SDF_CACHE_VERSION`.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
import torch

from torchgarment.body.cache import cache_root
from torchgarment.errors import InputError
from torchgarment.io.atomic import remove_orphan_temporaries
from torchgarment.sdf.build import SDFSettings, build_sdf_grid, check_mesh
from torchgarment.sdf.grid import BodySDF

SDF_CACHE_VERSION = 1
"""Bump when :func:`~torchgarment.sdf.build.build_sdf_grid` changes its output, to invalidate old entries."""


def sdf_cache_dir() -> Path:
    """Folder of cached SDFs: ``$TORCHGARMENT_CACHE/sdf`` or ``~/.cache/torchgarment/sdf``."""
    return cache_root() / "sdf"


def _as_numpy(a: torch.Tensor | np.ndarray) -> np.ndarray:
    return a.detach().cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)


def sdf_cache_key(vertices: torch.Tensor | np.ndarray, faces: torch.Tensor | np.ndarray,
                  settings: SDFSettings | None = None) -> str:
    """Hash a mesh and SDF settings into a cache key.

    Args:
        vertices: (V, 3) positions in metres (hashed as float64).
        faces: (F, 3) vertex indices (hashed as int64).
        settings: grid settings; default :class:`SDFSettings()`.

    Returns:
        A 32-character hex key.

    Raises:
        MeshError: invalid mesh (see :func:`~torchgarment.sdf.build.check_mesh`).
    """
    settings = settings or SDFSettings()
    v, f = check_mesh(_as_numpy(vertices), _as_numpy(faces))
    hsh = hashlib.sha256()
    desc = (
        f"torchgarment-sdf v{SDF_CACHE_VERSION} V={v.shape[0]} F={f.shape[0]} voxel={settings.voxel_size!r} "
        f"band={settings.band!r} brick={settings.brick} sign={settings.sign_type.value}"
    )
    hsh.update(desc.encode())
    hsh.update(v.tobytes())
    hsh.update(f.tobytes())
    return hsh.hexdigest()[:32]


def sdf_cache_path(vertices: torch.Tensor | np.ndarray, faces: torch.Tensor | np.ndarray,
                   settings: SDFSettings | None = None, *,
                   cache_dir: str | os.PathLike | None = None) -> Path:
    """Path of the cache entry of a mesh's SDF (:func:`cached_sdf` reads and writes it; the batch runner
    ships it to other machines).

    Args:
        vertices: (V, 3) positions in metres. faces: (F, 3) vertex indices. settings: grid settings; default
            :class:`SDFSettings()`. cache_dir: folder of the entries; default :func:`sdf_cache_dir`.
    """
    folder = Path(cache_dir).expanduser() if cache_dir is not None else sdf_cache_dir()
    return folder / f"{sdf_cache_key(_as_numpy(vertices), _as_numpy(faces), settings or SDFSettings())}.npz"


def cached_sdf(
    vertices: torch.Tensor | np.ndarray,
    faces: torch.Tensor | np.ndarray,
    settings: SDFSettings | None = None,
    *,
    cache_dir: str | os.PathLike | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float64,
) -> BodySDF:
    """The SDF of a mesh from the disk cache, built and stored on a miss.

    Args:
        vertices: (V, 3) positions in metres.
        faces: (F, 3) vertex indices.
        settings: grid settings; default :class:`SDFSettings()`.
        cache_dir: folder of the entries; default :func:`sdf_cache_dir`.
        device: device of the returned SDF.
        dtype: floating dtype of the returned SDF (entries are stored in float64).

    Returns:
        The :class:`BodySDF`, equal to ``BodySDF.from_mesh(vertices, faces, settings, device=device,
        dtype=dtype)``.

    Raises:
        MeshError: invalid mesh.
    """
    settings = settings or SDFSettings()
    v, f = check_mesh(_as_numpy(vertices), _as_numpy(faces))
    path = sdf_cache_path(v, f, settings, cache_dir=cache_dir)
    folder = path.parent
    if path.is_file():
        try:
            return BodySDF.load(path, device=device, dtype=dtype)
        except InputError:  # truncated or foreign file: drop it and rebuild
            path.unlink(missing_ok=True)
    sdf = BodySDF(build_sdf_grid(v, f, settings))  # float64 on the CPU: the stored values are exact
    remove_orphan_temporaries(folder)  # a writer killed mid-save leaves its temporary (40 MB) behind
    sdf.save(path)
    return sdf.to(device=device, dtype=dtype)
