"""Scene description for rendering: :class:`MeshLayer` and its validation into numpy arrays."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np
import torch

from torchgarment.errors import InputError, MeshError
from torchgarment.render.colormap import ScalarColors, make_scalar_colors

#: Colour of a layer that has neither ``color`` nor ``scalars`` (light grey, as used for bodies).
DEFAULT_COLOR = (0.82, 0.82, 0.82)


class ScalarLocation(Enum):
    """Where the scalars of a :class:`MeshLayer` live."""

    VERTEX = "vertex"
    FACE = "face"


@dataclass
class MeshLayer:
    """One triangle mesh of a scene, drawn with a flat colour or a scalar field.

    Attributes:
        vertices: (V, 3) positions in metres, +Y up (numpy array or torch tensor).
        faces: (F, 3) integer vertex indices (numpy array or torch tensor), F >= 1.
        color: flat RGB colour in [0, 1]; None with no ``scalars`` means :data:`DEFAULT_COLOR`.
        scalars: (V,) or (F,) finite values mapped through ``cmap`` (see ``scalar_on``); excludes ``color``.
        scalar_on: whether ``scalars`` are per vertex (interpolated per pixel) or per face (constant).
            A string ``"vertex"`` / ``"face"`` is accepted and converted.
        cmap: matplotlib colormap name.
        vmin: value at the bottom of the colormap; None for the data minimum.
        vmax: value at the top of the colormap; None for the data maximum.
        log: logarithmic colour scale (values <= 0 are drawn with the bottom colour).
        label: colourbar label.
        smooth: shade with interpolated vertex normals (True) or flat face normals (False).
    """

    vertices: np.ndarray | torch.Tensor
    faces: np.ndarray | torch.Tensor
    color: tuple[float, float, float] | None = None
    scalars: np.ndarray | torch.Tensor | None = None
    scalar_on: ScalarLocation = ScalarLocation.VERTEX
    cmap: str = "viridis"
    vmin: float | None = None
    vmax: float | None = None
    log: bool = False
    label: str | None = None
    smooth: bool = True


@dataclass
class PreparedLayer:
    """A validated :class:`MeshLayer` as float64 / int64 numpy arrays.

    Attributes:
        vertices: (V, 3) metres.
        faces: (F, 3) int64.
        color: (3,) flat colour, used when ``colors`` is None.
        colors: scalar colour mapping, or None.
        vertex_scalars: (V,) scalars or None.
        face_colors: (F, 3) RGB per face (per-face scalars already mapped) or None.
        smooth: shade with vertex normals.
    """

    vertices: np.ndarray
    faces: np.ndarray
    color: np.ndarray
    colors: ScalarColors | None
    vertex_scalars: np.ndarray | None
    face_colors: np.ndarray | None
    smooth: bool


def _to_numpy(x: np.ndarray | torch.Tensor) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def prepare_layer(layer: MeshLayer, index: int = 0) -> PreparedLayer:
    """Validate a layer and convert it to numpy.

    Args:
        layer: the layer.
        index: its position in the scene (for error messages).

    Returns:
        The prepared layer.

    Raises:
        MeshError: bad vertices or faces (wrong shape, non-finite, out-of-range indices, no faces).
        InputError: bad colour, scalars or colour limits.
    """
    name = f"layer {index}" + (f" ({layer.label})" if layer.label else "")
    v = _to_numpy(layer.vertices)
    f = _to_numpy(layer.faces)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise MeshError(f"{name}: vertices must have shape (V, 3) with V >= 1, got {tuple(v.shape)}")
    if not np.issubdtype(v.dtype, np.number):
        raise MeshError(f"{name}: vertices must be numeric, got dtype {v.dtype}")
    v = v.astype(np.float64)
    if not np.isfinite(v).all():
        raise MeshError(f"{name}: {int((~np.isfinite(v).all(axis=1)).sum())} vertices are NaN or infinite")
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise MeshError(f"{name}: faces must have shape (F, 3) with F >= 1, got {tuple(f.shape)}")
    if not np.issubdtype(f.dtype, np.integer):
        raise MeshError(f"{name}: faces must be integers, got dtype {f.dtype}")
    f = f.astype(np.int64)
    if f.min() < 0 or f.max() >= v.shape[0]:
        raise MeshError(f"{name}: face indices must be in [0, {v.shape[0]}), got [{f.min()}, {f.max()}]")

    try:
        location = ScalarLocation(layer.scalar_on)
    except ValueError as exc:
        raise InputError(f"{name}: scalar_on must be 'vertex' or 'face', got {layer.scalar_on!r}") from exc

    color = np.array(DEFAULT_COLOR)
    colors = None
    vertex_scalars = None
    face_colors = None
    if layer.scalars is not None:
        if layer.color is not None:
            raise InputError(f"{name}: give either color or scalars, not both")
        s = _to_numpy(layer.scalars)
        expected = v.shape[0] if location is ScalarLocation.VERTEX else f.shape[0]
        if s.shape != (expected,):
            raise InputError(
                f"{name}: per-{location.value} scalars must have shape ({expected},), got {s.shape}"
            )
        s = s.astype(np.float64)
        if not np.isfinite(s).all():
            raise InputError(f"{name}: {int((~np.isfinite(s)).sum())} scalars are NaN or infinite")
        colors = make_scalar_colors(s, layer.cmap, layer.vmin, layer.vmax, layer.log, layer.label)
        if location is ScalarLocation.VERTEX:
            vertex_scalars = s
        else:
            face_colors = colors(s)
    elif layer.color is not None:
        color = np.asarray(layer.color, dtype=np.float64)
        if color.shape != (3,) or not np.isfinite(color).all() or color.min() < 0 or color.max() > 1:
            raise InputError(f"{name}: color must be 3 floats in [0, 1], got {layer.color}")
    return PreparedLayer(v, f, color, colors, vertex_scalars, face_colors, bool(layer.smooth))


def prepare_layers(layers: list[MeshLayer]) -> list[PreparedLayer]:
    """Validate a scene (see :func:`prepare_layer`); an empty scene raises :class:`InputError`."""
    if len(layers) == 0:
        raise InputError("nothing to render: the layer list is empty")
    for i, layer in enumerate(layers):
        if not isinstance(layer, MeshLayer):
            raise InputError(f"layer {i} is a {type(layer).__name__}, expected MeshLayer")
    return [prepare_layer(layer, i) for i, layer in enumerate(layers)]
