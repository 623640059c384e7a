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

__all__ = ["HUMAN_HEIGHT_RANGE", "BodyMeshWarning", "check_human_body", "load_body"]

HUMAN_HEIGHT_RANGE = (0.4, 2.8)
"""Heights (metres, along +Y) accepted for a human body by the commands that need one (``drape``, ``adjust``,
``grade``, ``measure``, ``pca fit``): a toddler to well above the tallest person. Retargeting takes avatars of
any size and does not apply it."""

UPSIDE_DOWN_RATIO = 1.2
"""A body whose top 8 % (the head) is this many times wider than its bottom 8 % (the feet) is upside down."""

_UNITS = (("millimetres", 1000.0), ("centimetres", 100.0), ("inches", 1.0 / 0.0254), ("feet", 1.0 / 0.3048))


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
        InputError: neither a chart size nor an existing file (one line naming the sizes); a mesh that
            cannot be a standing human body in metres (:func:`check_human_body`).
    """
    from pathlib import Path

    from torchgarment.body.size_chart import list_sizes

    if spec in list_sizes():
        return Body.from_size(spec), f"size {spec}"
    path = Path(spec)
    if path.is_dir():
        raise InputError(f"--{flag} {spec}: is a folder, not a chart size ({', '.join(list_sizes())}) or a "
                         "mesh file")
    if not path.is_file():
        raise InputError(f"--{flag} {spec}: neither a chart size ({', '.join(list_sizes())}) nor an existing "
                         "mesh file")
    body = load_body(path)
    check_human_body(body.vertices, body.faces, f"--{flag} {spec}")
    return body, path.stem


def check_human_body(vertices: torch.Tensor, faces: torch.Tensor, name: str = "the body") -> None:
    """Refuse, in one line, a mesh that cannot be a standing human body in metres with +Y up (issue 17).

    A body in millimetres or centimetres made the SDF build allocate terabytes or swap the machine, and one
    upside down "converged". Checked: the height (extent along Y) within :data:`HUMAN_HEIGHT_RANGE`, naming
    the unit and factor that would bring it there; the longest side along Y (not lying or Z-up); the top 8 %
    of the height (the head) not wider than :data:`UPSIDE_DOWN_RATIO` times the bottom 8 % (the feet); no
    vertex that no face uses (stray points, which corrupted the height and were reported as "not a standing
    human body").

    Args:
        vertices: (V, 3) positions. faces: (F, 3) vertex indices (only the vertices faces use count).
        name: the body's name in the message (a file path or option).

    Raises:
        InputError: one of the checks fails.
    """
    v = vertices.detach().to(device="cpu", dtype=torch.float64)
    used = torch.unique(faces.detach().cpu().long().reshape(-1))
    used = used[(used >= 0) & (used < v.shape[0])]
    if 0 < used.numel() < v.shape[0]:
        stray = torch.ones(v.shape[0], dtype=torch.bool)
        stray[used] = False
        first = [round(float(c), 3) for c in v[int(torch.nonzero(stray)[0])]]
        raise InputError(f"{name}: {int(stray.sum())} vertices are used by no face (stray points, the first "
                         f"at {first}): remove the unreferenced vertices")
    v = v[used]
    if v.shape[0] < 3 or not bool(torch.isfinite(v).all()):
        raise InputError(f"{name}: not a body (fewer than 3 used vertices or non-finite coordinates)")
    extent = v.max(dim=0).values - v.min(dim=0).values  # (3,) metres
    height = float(extent[1])
    lo, hi = HUMAN_HEIGHT_RANGE
    longest = int(torch.argmax(extent))
    if longest != 1 and float(extent[longest]) > 1.2 * height:
        raise InputError(f"{name}: its longest side is along {'XYZ'[longest]} ({float(extent[longest]):.4g} "
                         f"against {height:.4g} along Y): a body must stand with +Y up (rotate it)")
    if not lo <= height <= hi:
        fits = [f"{unit}: scale it by {1.0 / f:g}" for unit, f in _UNITS if lo <= height / f <= hi]
        hint = ("; if it is in " + ", or in ".join(fits)) if fits else ""
        raise InputError(f"{name}: {height:.4g} tall along Y, outside {lo:g}-{hi:g} m for a human body in "
                         f"metres{hint}")
    y = v[:, 1]
    ymin, ymax = float(y.min()), float(y.max())
    bottom = v[y <= ymin + 0.08 * height][:, [0, 2]]
    top = v[y >= ymax - 0.08 * height][:, [0, 2]]
    width_bottom = float((bottom.max(dim=0).values - bottom.min(dim=0).values).norm())
    width_top = float((top.max(dim=0).values - top.min(dim=0).values).norm())
    if width_top > UPSIDE_DOWN_RATIO * width_bottom:
        raise InputError(f"{name}: looks upside down (its top is {width_top / max(width_bottom, 1e-12):.2g} "
                         "times as wide as its bottom, where the feet should be): +Y must point from the "
                         "feet to the head")
