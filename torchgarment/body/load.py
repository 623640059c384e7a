"""Load any mesh file as a :class:`~torchgarment.body.body.Body`, with an optional skeleton and skin weights.

Bodies (avatars) may be open, non-manifold, disconnected and self-intersecting (Huang et al. 2025 allow
all of it), so only the basics are enforced: a non-empty mesh with valid indices. Degenerate faces are
allowed but reported with a :class:`BodyMeshWarning`.
"""

from __future__ import annotations

import os
import warnings

import torch

from torchgarment.body.body import Body
from torchgarment.body.kinematics import check_bone_forest
from torchgarment.body.skeleton import Skeleton
from torchgarment.body.skeleton_io import read_skeleton_obj, read_skin_weights, validate_skin_weights
from torchgarment.errors import InputError
from torchgarment.io.mesh import load_mesh
from torchgarment.structures.mesh_checks import find_degenerate_faces

__all__ = ["BodyMeshWarning", "load_body"]


class BodyMeshWarning(UserWarning):
    """A body mesh has defects that torchgarment tolerates (degenerate faces)."""


def load_body(
    path: str | os.PathLike,
    skeleton: Skeleton | str | os.PathLike | None = None,
    skin_weights: torch.Tensor | str | os.PathLike | None = None,
    *,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
    weld: bool = False,
) -> Body:
    """Load a body mesh (OBJ, PLY, STL, OFF, GLB, GLTF) with an optional skeleton and skin weights.

    Args:
        path: mesh file in metres, +Y up.
        skeleton: a :class:`Skeleton` or a skeleton OBJ edge graph (see :mod:`torchgarment.body.skeleton_io`).
        skin_weights: a (J, V) tensor or a weights text file (joints x vertices); needs ``skeleton``.
            Columns are normalized to sum to one.
        dtype: floating dtype of all tensors.
        device: device of all tensors.
        weld: merge exactly coincident vertices. Off by default so that vertex ``i`` stays the file's
            vertex ``i`` (skin weights refer to file order); when on, the weights of merged vertices are
            averaged.

    Returns:
        The body; ``params["source"]`` holds the mesh path.

    Raises:
        InputError: unreadable or empty mesh, bad skeleton or skin weights.

    Warns:
        BodyMeshWarning: the mesh has degenerate faces.
    """
    vertices, faces = load_mesh(path, weld=False, dtype=dtype, device=device)
    num_file_vertices = vertices.shape[0]
    index_map = None
    if weld:
        from torchgarment.structures.mesh_checks import weld_vertices

        vertices, faces, index_map = weld_vertices(vertices, faces, 0.0)
        if faces.shape[0] == 0:
            raise InputError(f"body mesh {path} has no faces left after welding")

    skel = None
    if skeleton is not None:
        if isinstance(skeleton, Skeleton):
            check_bone_forest(skeleton.num_joints, skeleton.bones)
            skel = skeleton.to(device=device, dtype=dtype)
        elif isinstance(skeleton, (str, os.PathLike)):
            skel = read_skeleton_obj(skeleton, dtype=dtype, device=device)
        else:
            raise InputError(f"skeleton must be a Skeleton or a path, got {type(skeleton).__name__}")

    weights = None
    if skin_weights is not None:
        if skel is None:
            raise InputError("skin weights need a skeleton")
        if isinstance(skin_weights, torch.Tensor):
            weights = validate_skin_weights(
                skin_weights.to(dtype=dtype, device=device), skel.num_joints, num_file_vertices
            )
        elif isinstance(skin_weights, (str, os.PathLike)):
            weights = read_skin_weights(skin_weights, skel.num_joints, num_file_vertices, dtype=dtype,
                                        device=device)
        else:
            raise InputError(f"skin_weights must be a tensor or a path, got {type(skin_weights).__name__}")
        if index_map is not None:
            summed = torch.zeros(weights.shape[0], vertices.shape[0], dtype=dtype, device=weights.device)
            summed.index_add_(1, index_map, weights)
            weights = summed / summed.sum(dim=0, keepdim=True)

    degenerate = find_degenerate_faces(vertices, faces)
    if degenerate.numel():
        warnings.warn(
            f"body mesh {path}: {degenerate.numel()} degenerate faces (first {degenerate[:5].tolist()})",
            BodyMeshWarning,
            stacklevel=2,
        )
    return Body(vertices=vertices, faces=faces, skeleton=skel, skin_weights=weights,
                params={"source": str(path)})


def load_body_spec(spec: str, flag: str) -> tuple[Body, str]:
    """The body a command-line option names: a chart size (:meth:`Body.from_size`) or a mesh file
    (:func:`load_body`).

    Args:
        spec: the option's value. flag: the option's name without dashes, for the error message.

    Returns:
        ``(body, name)``: the body and a short name for outputs (``"size 12"`` or the file's stem).

    Raises:
        InputError: neither a chart size nor an existing file (one line naming the sizes).
    """
    from pathlib import Path

    from torchgarment.body.size_chart import list_sizes

    if spec in list_sizes():
        return Body.from_size(spec), f"size {spec}"
    path = Path(spec)
    if not path.is_file():
        raise InputError(f"--{flag} {spec}: neither a chart size ({', '.join(list_sizes())}) nor an existing "
                         "mesh file")
    return load_body(path), path.stem
