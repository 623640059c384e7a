"""Skeleton graphs and skin weights as files.

Skeletons use the OBJ edge-graph convention of the reference code of Huang et al. 2025: ``v x y z`` lines
are joints (metres), ``l a b [c ...]`` lines are bones (1-based, a polyline ``l a b c`` is the bones
(a, b) and (b, c)); the first index of a bone is its parent. Joint names, when present, are comment lines
``# joint <index> <name>`` (0-based index), which other OBJ readers ignore.

Skin weights are a whitespace-separated text matrix with one row per joint and one column per vertex.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import torch

from torchgarment.body.kinematics import check_bone_forest
from torchgarment.body.skeleton import Skeleton
from torchgarment.errors import InputError
from torchgarment.io.atomic import atomic_open

__all__ = [
    "read_skeleton_obj",
    "read_skin_weights",
    "validate_skin_weights",
    "write_skeleton_obj",
    "write_skin_weights",
]

_NAME = re.compile(r"^#\s*joint\s+(\d+)\s+(\S.*?)\s*$")
_IGNORED = frozenset("vt vn vp p o g s usemtl mtllib".split())


def read_text_file(path: Path, what: str) -> str:
    """The UTF-8 text of ``path``; :class:`InputError` (one line naming ``what``) if missing or unreadable."""
    if not path.exists():
        raise InputError(f"{what} file not found: {path}")
    if not path.is_file():
        raise InputError(f"{path}: is a folder or a special file, not a {what} file")
    try:
        return path.read_text(encoding="utf-8")
    except (UnicodeDecodeError, OSError) as e:
        raise InputError(f"cannot read {what} {path}: {type(e).__name__}") from None


def read_skeleton_obj(
    path: str | os.PathLike, *, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> Skeleton:
    """Read a skeleton from an OBJ edge graph.

    Args:
        path: ``.obj`` file with ``v`` (joint) and ``l`` (bone) lines.
        dtype: floating dtype of the joint positions.
        device: device of the returned tensors.

    Returns:
        The skeleton, joints in file order, bones in file order.

    Raises:
        InputError: missing file, malformed lines, faces, no joints or bones, indices out of range, or a
            bone graph that is not a forest.
    """
    path = Path(path)
    text = read_text_file(path, "skeleton")
    joints: list[list[str]] = []
    bones: list[tuple[int, int]] = []
    names: dict[int, str] = {}
    for number, raw in enumerate(text.splitlines(), start=1):
        match = _NAME.match(raw.strip())
        if match:
            names[int(match.group(1))] = match.group(2)
            continue
        tokens = raw.split("#", 1)[0].split()
        if not tokens or tokens[0] in _IGNORED:
            continue
        key = tokens[0]
        if key == "v":
            if len(tokens) < 4:
                raise InputError(f"malformed skeleton OBJ {path}: line {number}: a joint needs three "
                                 "coordinates")
            joints.append(tokens[1:4])
        elif key == "l":
            try:
                idx = [int(t.split("/", 1)[0]) for t in tokens[1:]]
            except ValueError:
                raise InputError(f"malformed skeleton OBJ {path}: line {number}: bad joint index") from None
            if len(idx) < 2 or 0 in idx:
                raise InputError(
                    f"malformed skeleton OBJ {path}: line {number}: a bone needs two 1-based joint indices"
                )
            idx = [i - 1 if i > 0 else len(joints) + i for i in idx]
            bones.extend(zip(idx[:-1], idx[1:]))
        elif key == "f":
            raise InputError(f"skeleton OBJ {path}: line {number}: has faces; a skeleton has only v and l "
                             "lines")
        else:
            raise InputError(f"malformed skeleton OBJ {path}: line {number}: unknown statement {key[:40]!r}")
    if not joints or not bones:
        raise InputError(
            f"skeleton OBJ {path} needs joints (v lines) and bones (l lines); got {len(joints)} and "
            f"{len(bones)}"
        )
    try:
        joint_array = np.array(joints, dtype=np.float64)
    except ValueError:
        raise InputError(f"malformed skeleton OBJ {path}: non-numeric joint coordinate") from None
    if not np.isfinite(joint_array).all():
        raise InputError(f"skeleton OBJ {path} has non-finite joint coordinates")
    bone_tensor = torch.tensor(bones, dtype=torch.long)
    try:
        check_bone_forest(len(joints), bone_tensor)
    except InputError as e:
        raise InputError(f"skeleton OBJ {path}: {e}") from None
    name_list: list[str] = []
    if names:
        if sorted(names) != list(range(len(joints))):
            raise InputError(f"skeleton OBJ {path}: '# joint <index> <name>' comments must name every joint "
                             "once")
        name_list = [names[i] for i in range(len(joints))]
    return Skeleton(
        joints=torch.as_tensor(joint_array, dtype=dtype, device=device),
        bones=bone_tensor.to(device=device),
        names=name_list,
    )


def write_skeleton_obj(path: str | os.PathLike, skeleton: Skeleton) -> None:
    """Write a skeleton as an OBJ edge graph (see the module docstring), atomically.

    Args:
        path: destination ``.obj`` file.
        skeleton: joints (J, 3) in metres, bones (B, 2), optional names.

    Raises:
        InputError: the skeleton's shapes or indices are invalid.
    """
    joints = skeleton.joints.detach().cpu().double().numpy()
    if joints.ndim != 2 or joints.shape[1] != 3:
        raise InputError(f"skeleton joints must have shape (J, 3), got {joints.shape}")
    check_bone_forest(joints.shape[0], skeleton.bones)
    if skeleton.names and len(skeleton.names) != joints.shape[0]:
        raise InputError(f"skeleton has {len(skeleton.names)} names for {joints.shape[0]} joints")
    if any("\n" in n or not n.strip() for n in skeleton.names):
        raise InputError("skeleton joint names must be non-empty single lines")
    bones = skeleton.bones.detach().cpu().long().numpy()
    with atomic_open(path, "w") as fh:
        fh.write(f"# torchgarment skeleton: {joints.shape[0]} joints, {bones.shape[0]} bones\n")
        for i, name in enumerate(skeleton.names):
            fh.write(f"# joint {i} {name.strip()}\n")
        np.savetxt(fh, joints, fmt="v %.17g %.17g %.17g")
        np.savetxt(fh, bones + 1, fmt="l %d %d")


def validate_skin_weights(
    weights: torch.Tensor, num_joints: int, num_vertices: int, *, source: str = "skin weights"
) -> torch.Tensor:
    """Check a (J, V) skin-weight matrix and normalize its columns to sum to one.

    Args:
        weights: (J, V) non-negative weights.
        num_joints: expected J.
        num_vertices: expected V.
        source: what to call the weights in error messages.

    Returns:
        (J, V) weights whose columns sum to 1 (same dtype and device).

    Raises:
        InputError: wrong shape (with a hint when it is transposed), non-finite or negative entries, or a
            vertex whose weights are all zero.
    """
    if not isinstance(weights, torch.Tensor) or not weights.is_floating_point():
        raise InputError(f"{source} must be a floating-point tensor")
    expected = (int(num_joints), int(num_vertices))
    if tuple(weights.shape) != expected:
        hint = " (it looks transposed: rows must be joints)" if tuple(weights.shape) == expected[::-1] else ""
        raise InputError(
            f"{source} have shape {tuple(weights.shape)}, expected (joints, vertices) = {expected}{hint}"
        )
    if not torch.isfinite(weights).all():
        raise InputError(f"{source} contain non-finite values")
    negative = torch.nonzero((weights < 0).any(dim=0), as_tuple=False).flatten()
    if negative.numel():
        raise InputError(f"{source} are negative for {negative.numel()} vertices, first "
                         f"{negative[:5].tolist()}")
    total = weights.sum(dim=0)
    empty = torch.nonzero(total <= 0, as_tuple=False).flatten()
    if empty.numel():
        raise InputError(f"{source} are all zero for {empty.numel()} vertices, first {empty[:5].tolist()}")
    return weights / total


def read_skin_weights(
    path: str | os.PathLike,
    num_joints: int,
    num_vertices: int,
    *,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Read a (joints x vertices) whitespace text matrix of skin weights.

    Args:
        path: text file, one row per joint, one column per vertex.
        num_joints: J of the skeleton.
        num_vertices: V of the mesh.
        dtype: floating dtype of the result.
        device: device of the result.

    Returns:
        (J, V) weights, columns normalized to sum to 1.

    Raises:
        InputError: missing file, non-numeric or ragged content, wrong shape, negative entries or a vertex
            with all-zero weights.
    """
    path = Path(path)
    text = read_text_file(path, "skin weights")
    rows = [r for r in (line.split("#", 1)[0].split() for line in text.splitlines()) if r]
    if not rows:
        raise InputError(f"skin weights file {path} is empty")
    lengths = {len(r) for r in rows}
    if len(lengths) != 1:
        raise InputError(f"skin weights file {path} is ragged: rows have {sorted(lengths)[:4]} entries")
    try:
        array = np.array(rows, dtype=np.float64)
    except ValueError:
        raise InputError(f"skin weights file {path} has non-numeric entries") from None
    weights = torch.as_tensor(array, dtype=dtype, device=device)
    return validate_skin_weights(weights, num_joints, num_vertices, source=f"skin weights {path}")


def write_skin_weights(path: str | os.PathLike, weights: torch.Tensor) -> None:
    """Write (J, V) skin weights as a whitespace text matrix (rows are joints), atomically."""
    if weights.ndim != 2:
        raise InputError(f"skin weights must have shape (J, V), got {tuple(weights.shape)}")
    with atomic_open(path, "w") as fh:
        np.savetxt(fh, weights.detach().cpu().double().numpy(), fmt="%.17g")
