"""Triangle meshes from and to files.

OBJ files are read by a small order-preserving parser (vertex ``i`` of the file is vertex ``i - 1`` of the
result, unreferenced vertices included), so that per-vertex data stored next to the mesh (skin weights,
correspondences) stays aligned; trimesh re-orders and drops vertices along UV seams. PLY, STL, OFF, GLB and
GLTF are read through trimesh (scenes are concatenated with their node transforms applied, polygons are
triangulated). Every failure is reported as one :class:`~torchgarment.errors.InputError` line.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import torch

from torchgarment.errors import InputError, MeshError
from torchgarment.io.atomic import atomic_open

__all__ = ["MESH_SUFFIXES", "load_mesh", "read_obj", "save_obj"]

#: File suffixes :func:`load_mesh` accepts.
MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")

# OBJ statements that carry no triangle data; they are skipped.
_OBJ_IGNORED = frozenset(
    "vt vn vp l p o g s usemtl mtllib maplib usemap lod shadow_obj trace_obj bevel c_interp d_interp "
    "cstype deg bmat step curv curv2 surf parm trim hole scrv sp end con mg ctech stech call csh".split()
)


_FIRST_TOKEN = re.compile(r"^[ \t]*([^\s#]+)", re.M)
_V_LINE = re.compile(r"^[ \t]*v[ \t]+([^\n#]*)", re.M)
_F_LINE = re.compile(r"^[ \t]*f[ \t]+([^\n#]*)", re.M)
_VF_TOKEN = re.compile(r"^[ \t]*(v|f)[ \t]", re.M)
_SLASH_SUFFIX = re.compile(r"/[^\s#]*")


def _one_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0]}" if text else type(e).__name__


def _check_file(path: Path, suffixes: tuple[str, ...], what: str) -> str:
    if not path.exists():
        raise InputError(f"{what} file not found: {path}")
    if not path.is_file():
        raise InputError(f"{path}: is a folder or a special file, not a {what} file")
    suffix = path.suffix.lower()
    if suffix not in suffixes:
        raise InputError(
            f"unsupported {what} format {suffix or '(no suffix)'!r} for {path}; use one of "
            f"{', '.join(suffixes)}"
        )
    return suffix


def read_obj(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Parse the vertices and polygon faces of an OBJ file, keeping the file's vertex order.

    Polygons are fan-triangulated; negative (relative) indices are resolved; texture and normal indices
    (``f 1/2/3``) are ignored.

    Args:
        path: OBJ file.

    Returns:
        vertices: (V, 3) float64 array, in file order.
        faces: (F, 3) int64 array of 0-based vertex indices.

    Raises:
        InputError: the file is missing, not text, or has malformed ``v`` or ``f`` lines or unknown
            statements.
    """
    path = Path(path)
    _check_file(path, (".obj",), "mesh")
    try:
        text = path.read_text(encoding="utf-8")
    except (UnicodeDecodeError, OSError) as e:
        raise InputError(f"cannot read OBJ {path}: {_one_line(e)}") from None
    lines = text.splitlines()
    keys = [m.group(1) for m in _FIRST_TOKEN.finditer(text)]
    unknown = set(keys) - _OBJ_IGNORED - {"v", "f"}
    if unknown:
        bad = next(i for i, ln in enumerate(lines) if ln.split("#", 1)[0].split()[:1]
                   and ln.split()[0] in unknown)
        raise InputError(f"malformed OBJ {path}: line {bad + 1}: unknown statement "
                         f"{lines[bad].split()[0][:40]!r}")
    v_body = [b.split() for b in _V_LINE.findall(text)]
    f_body = [ln.split() for ln in _F_LINE.findall(_SLASH_SUFFIX.sub("", text))]
    try:
        if any(len(tok) < 3 for tok in v_body):
            raise ValueError("a vertex needs three coordinates")
        vertices = np.array([tok[:3] for tok in v_body], dtype=np.float64).reshape(-1, 3)
    except ValueError as e:
        raise InputError(f"malformed OBJ {path}: {_one_line(e)}") from None
    sizes = np.array([len(tok) for tok in f_body], dtype=np.int64)
    if sizes.size and sizes.min() < 3:
        raise InputError(f"malformed OBJ {path}: face {int(np.argmin(sizes)) + 1} has fewer than three "
                         "vertices")
    defined_before = None
    triangles = []
    for k in np.unique(sizes):
        group = np.nonzero(sizes == k)[0]
        try:
            idx = np.array([f_body[g] for g in group], dtype=np.int64).reshape(-1, int(k))
        except ValueError as e:
            raise InputError(f"malformed OBJ {path}: bad face index ({_one_line(e)})") from None
        if (idx == 0).any():
            raise InputError(f"malformed OBJ {path}: face index 0 (OBJ indices start at 1)")
        if (idx < 0).any():
            if defined_before is None:
                # Number of vertices defined before each face line, for relative (negative) indices.
                kinds = [m.group(1) for m in _VF_TOKEN.finditer(text)]
                is_v = np.array([kd == "v" for kd in kinds], dtype=np.int64)
                defined_before = np.cumsum(is_v)[np.array([kd == "f" for kd in kinds], dtype=bool)]
            idx = np.where(idx > 0, idx - 1, defined_before[group][:, None] + idx)
        else:
            idx = idx - 1
        fan = np.stack([np.zeros(k - 2, dtype=np.int64), np.arange(1, k - 1), np.arange(2, k)], axis=1)
        triangles.append((group, idx[:, fan].reshape(-1, 3), k - 2))
    # Restore the file's face order.
    if triangles:
        order = np.concatenate([np.repeat(g, n) for g, _, n in triangles])
        sub = np.concatenate([np.tile(np.arange(n), len(g)) for g, _, n in triangles])
        tris = np.concatenate([t for _, t, _ in triangles], axis=0)
        faces = tris[np.lexsort((sub, order))]
    else:
        faces = np.zeros((0, 3), dtype=np.int64)
    return vertices, faces


def _load_trimesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    try:
        loaded = trimesh.load(str(path), process=False, force="mesh")
    except Exception as e:  # trimesh raises many types for malformed files
        raise InputError(f"cannot read mesh {path}: {_one_line(e)}") from None
    faces = getattr(loaded, "faces", None)
    vertices = getattr(loaded, "vertices", None)
    if faces is None or vertices is None:
        raise InputError(f"mesh {path} contains no triangles ({type(loaded).__name__})")
    return (np.asarray(vertices, dtype=np.float64).reshape(-1, 3),
            np.asarray(faces, dtype=np.int64).reshape(-1, 3))


def load_mesh(
    path: str | os.PathLike,
    *,
    weld: bool = True,
    weld_tol: float = 0.0,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Load a triangle mesh from OBJ, PLY, STL, OFF, GLB or GLTF.

    Only the file's content is validated here (non-empty, finite, indices in range); topology checks
    (manifoldness, degenerate faces) are left to :func:`torchgarment.structures.mesh_checks.check_mesh`.

    Args:
        path: mesh file; the format is chosen by suffix.
        weld: merge vertices closer than ``weld_tol`` (see
            :func:`~torchgarment.structures.mesh_checks.weld_vertices`). Turn off to keep the file's vertex
            order, e.g. when per-vertex data comes with the mesh.
        weld_tol: merge distance in metres.
        dtype: floating dtype of the vertices.
        device: device of the returned tensors.

    Returns:
        vertices: (V, 3) positions, in the file's units (metres expected).
        faces: (F, 3) long vertex indices.

    Raises:
        InputError: missing file, unknown format, malformed content or an empty mesh.
    """
    path = Path(path)
    suffix = _check_file(path, MESH_SUFFIXES, "mesh")
    if suffix == ".obj":
        vertices, faces = read_obj(path)
    else:
        vertices, faces = _load_trimesh(path)
    if vertices.shape[0] == 0 or faces.shape[0] == 0:
        raise InputError(f"mesh {path} is empty ({vertices.shape[0]} vertices, {faces.shape[0]} faces)")
    if not np.isfinite(vertices).all():
        raise InputError(f"mesh {path} has non-finite vertex coordinates")
    if faces.min() < 0 or faces.max() >= vertices.shape[0]:
        raise InputError(f"mesh {path}: face index out of range for {vertices.shape[0]} vertices")
    v = torch.as_tensor(vertices, dtype=dtype, device=device)
    f = torch.as_tensor(faces, dtype=torch.long, device=device)
    if weld:
        from torchgarment.structures.mesh_checks import weld_vertices

        try:
            v, f, _ = weld_vertices(v, f, weld_tol)
        except MeshError as e:
            raise InputError(f"cannot weld mesh {path}: {e}") from None
        if f.shape[0] == 0:
            raise InputError(f"mesh {path} has no faces left after welding")
    return v, f


def save_obj(path: str | os.PathLike, vertices: torch.Tensor, faces: torch.Tensor) -> None:
    """Write a triangle mesh as OBJ, atomically.

    float64 vertices are written with 17 significant digits (exact round trip), others with 9.

    Args:
        path: destination ``.obj`` file.
        vertices: (V, 3) positions in metres.
        faces: (F, 3) long 0-based vertex indices.

    Raises:
        InputError: shapes are wrong or indices are out of range.
    """
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise InputError(f"save_obj: vertices must have shape (V, 3), got {tuple(vertices.shape)}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise InputError(f"save_obj: faces must have shape (F, 3), got {tuple(faces.shape)}")
    f = faces.detach().cpu().long().numpy()
    if f.size and (f.min() < 0 or f.max() >= vertices.shape[0]):
        raise InputError(f"save_obj: face index out of range for {vertices.shape[0]} vertices")
    v = vertices.detach().cpu().double().numpy()
    fmt = "%.17g" if vertices.dtype == torch.float64 else "%.9g"
    with atomic_open(path, "w") as fh:
        fh.write(f"# torchgarment mesh: {v.shape[0]} vertices, {f.shape[0]} faces\n")
        np.savetxt(fh, v, fmt=f"v {fmt} {fmt} {fmt}")
        np.savetxt(fh, f + 1, fmt="f %d %d %d")
