"""Render a scene of :class:`MeshLayer` into an RGB image (software rasterizer, Lambert + ambient shading)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torchgarment.errors import InputError
from torchgarment.render.layers import MeshLayer, PreparedLayer, prepare_layers
from torchgarment.render.raster import Fragments, rasterize
from torchgarment.render.views import OrthoCamera, View, fit_camera


@dataclass(frozen=True)
class RenderStyle:
    """Lighting and drawing options.

    Attributes:
        ambient: light that reaches every surface, in [0, 1].
        key: strength of the key light (upper left, in front of the viewer).
        fill: strength of the fill light (right, in front of the viewer).
        key_dir: (3,) camera-space direction towards the key light (x right, y up, z to the viewer).
        fill_dir: (3,) camera-space direction towards the fill light.
        back_face: factor applied to the colour of back faces (the inside of open garments).
        background: RGB background in [0, 1].
        margin: empty border on each side, as a fraction of the image size.
        supersample: render at this many times the resolution and box-filter down (anti-aliasing), >= 1.
        wireframe: draw triangle edges.
        wire_color: RGB of the edges.
        wire_width: edge width in output pixels.
        outline: darken silhouettes and depth discontinuities.
        outline_depth: depth jump (metres) between neighbouring pixels that counts as a discontinuity.
        layer_depth_bias: metres by which each layer is drawn nearer than the layer before it, so that cloth
            resting a few millimetres on a body (drawn first) is not speckled by the body showing through.
    """

    ambient: float = 0.38
    key: float = 0.55
    fill: float = 0.2
    key_dir: tuple[float, float, float] = (-0.45, 0.55, 1.0)
    fill_dir: tuple[float, float, float] = (0.7, -0.1, 0.6)
    back_face: float = 0.72
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    margin: float = 0.05
    supersample: int = 2
    wireframe: bool = False
    wire_color: tuple[float, float, float] = (0.15, 0.15, 0.15)
    wire_width: float = 0.6
    outline: bool = False
    outline_depth: float = 0.03
    layer_depth_bias: float = 0.006


def render_image(
    layers: list[MeshLayer],
    view: View,
    size: tuple[int, int] = (800, 800),
    *,
    style: RenderStyle = RenderStyle(),
    camera: OrthoCamera | None = None,
) -> np.ndarray:
    """Render the scene from one view.

    Args:
        layers: meshes to draw (at least one).
        view: viewing direction.
        size: (width, height) of the image in pixels.
        style: lighting and drawing options.
        camera: camera to use; None fits the scene's bounding box with ``style.margin``. Its size must
            equal ``size``.

    Returns:
        (H, W, 3) uint8 RGB image.

    Raises:
        InputError: empty scene, malformed meshes (NaN vertices, bad faces), bad colours or sizes.
    """
    prepared = prepare_layers(layers)
    width, height = check_size(size)
    if camera is None:
        camera = fit_camera(scene_points(prepared), View(view), (width, height), style.margin)
    elif camera.view is not View(view):
        raise InputError(f"camera looks {camera.view.value}, but view {View(view).value} was asked for")
    elif (camera.width, camera.height) != (width, height):
        raise InputError(
            f"camera size {(camera.width, camera.height)} differs from image size {(width, height)}"
        )
    return render_prepared(prepared, camera, style)


def render_prepared(prepared: list[PreparedLayer], camera: OrthoCamera, style: RenderStyle) -> np.ndarray:
    """Render validated layers with a given camera (see :func:`render_image`); returns (H, W, 3) uint8."""
    ss = int(style.supersample)
    if ss < 1:
        raise InputError(f"supersample must be >= 1, got {style.supersample}")
    cam = camera.with_size(camera.width * ss, camera.height * ss)

    # Concatenate the layers into one mesh, remembering where each face came from.
    offsets = np.cumsum([0] + [p.vertices.shape[0] for p in prepared])
    verts = np.concatenate([p.vertices for p in prepared])
    faces = np.concatenate([p.faces + o for p, o in zip(prepared, offsets[:-1])])
    face_layer = np.repeat(np.arange(len(prepared)), [p.faces.shape[0] for p in prepared])
    face_start = np.cumsum([0] + [p.faces.shape[0] for p in prepared])

    xy, depth = cam.project(verts)
    if style.layer_depth_bias and len(prepared) > 1:
        vertex_layer = np.repeat(np.arange(len(prepared)), [p.vertices.shape[0] for p in prepared])
        depth = depth - style.layer_depth_bias * vertex_layer
    frags = rasterize(xy, depth, faces, cam.width, cam.height)

    npix = cam.width * cam.height
    rgb = np.empty((npix, 3), dtype=np.float32)
    rgb[:] = np.asarray(style.background, dtype=np.float32)
    covered = np.flatnonzero(frags.face.reshape(-1) >= 0)
    if covered.size:
        fid = frags.face.reshape(-1)[covered]
        bary = frags.bary.reshape(-1, 3)[covered]
        base = _base_colors(prepared, faces, face_layer, face_start, fid, bary)
        cam_verts = verts @ cam.view.rotation.T
        fn = _face_normals(cam_verts, faces)
        back = fn[fid, 2] < 0.0
        normal = _pixel_normals(prepared, cam_verts, faces, fn, face_layer, fid, bary)
        normal[back] *= -1.0
        light = _lighting(normal, style)
        base[back] *= style.back_face
        color = base * light[:, None]
        if style.wireframe:
            t = _wire_weight(xy, faces, fid, bary, style.wire_width * ss)
            color = color * (1 - t[:, None]) + np.asarray(style.wire_color) * t[:, None]
        rgb[covered] = color
    rgb = rgb.reshape(cam.height, cam.width, 3)
    if style.outline:
        rgb[_discontinuities(frags, style.outline_depth)] *= 0.35
    if ss > 1:
        # Box filter: average the ss x ss samples of each output pixel.
        acc = np.zeros((camera.height, camera.width, 3), dtype=np.float32)
        for i in range(ss):
            for j in range(ss):
                acc += rgb[i::ss, j::ss]
        rgb = acc * (1.0 / (ss * ss))
    return np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)


def check_size(size: tuple[int, int]) -> tuple[int, int]:
    """Validate an image size ``(width, height)`` in pixels and return it as ints."""
    if len(size) != 2 or int(size[0]) < 1 or int(size[1]) < 1:
        raise InputError(f"size must be (width, height) with positive entries, got {size}")
    return int(size[0]), int(size[1])


def scene_points(prepared: list[PreparedLayer]) -> np.ndarray:
    """(N, 3) all vertices of the scene, metres."""
    return np.concatenate([p.vertices for p in prepared])


def _face_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) area-weighted (unnormalised) face normals."""
    v0, v1, v2 = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    return np.cross(v1 - v0, v2 - v0)


def _norm(x: np.ndarray) -> np.ndarray:
    """Euclidean norm over the last axis (of size 3)."""
    return np.sqrt(x[..., 0] ** 2 + x[..., 1] ** 2 + x[..., 2] ** 2)


def _normalize(x: np.ndarray) -> np.ndarray:
    n = _norm(x)[..., None]
    return x / np.where(n > 0, n, 1.0)


def _pixel_normals(
    prepared: list[PreparedLayer],
    cam_verts: np.ndarray,
    faces: np.ndarray,
    face_normals: np.ndarray,
    face_layer: np.ndarray,
    fid: np.ndarray,
    bary: np.ndarray,
) -> np.ndarray:
    """(M, 3) unit camera-space normals per covered pixel: interpolated vertex normals or face normals."""
    vn = np.zeros_like(cam_verts)
    for k in range(3):
        np.add.at(vn, faces[:, k], face_normals)
    vn = _normalize(vn)
    fn_unit = _normalize(face_normals)
    smooth_layer = np.array([p.smooth for p in prepared])
    smooth = smooth_layer[face_layer[fid]]
    out = fn_unit[fid]
    if smooth.any():
        f = faces[fid[smooth]]
        b = bary[smooth]
        interp = b[:, 0:1] * vn[f[:, 0]] + b[:, 1:2] * vn[f[:, 1]] + b[:, 2:3] * vn[f[:, 2]]
        length = _norm(interp)
        # Where neighbouring faces have opposite windings the vertex normals cancel; keep the face normal.
        strong = length >= 0.3
        idx = np.flatnonzero(smooth)[strong]
        out[idx] = interp[strong] / length[strong, None]
    return out


def _lighting(normal: np.ndarray, style: RenderStyle) -> np.ndarray:
    """(M,) Lambert + ambient intensity for (M, 3) unit normals."""
    key = _normalize(np.asarray(style.key_dir, dtype=np.float64))
    fill = _normalize(np.asarray(style.fill_dir, dtype=np.float64))
    return (
        style.ambient
        + style.key * np.clip(normal @ key, 0.0, None)
        + style.fill * np.clip(normal @ fill, 0.0, None)
    )


def _base_colors(
    prepared: list[PreparedLayer],
    faces: np.ndarray,
    face_layer: np.ndarray,
    face_start: np.ndarray,
    fid: np.ndarray,
    bary: np.ndarray,
) -> np.ndarray:
    """(M, 3) unlit colour per covered pixel."""
    out = np.empty((fid.size, 3))
    layer = face_layer[fid]
    for i, p in enumerate(prepared):
        sel = layer == i
        if not sel.any():
            continue
        local = fid[sel] - face_start[i]
        if p.face_colors is not None:
            out[sel] = p.face_colors[local]
        elif p.vertex_scalars is not None:
            f = p.faces[local]
            s = (bary[sel] * p.vertex_scalars[f]).sum(axis=1)
            out[sel] = p.colors(s)
        else:
            out[sel] = p.color
    return out


def _wire_weight(
    xy: np.ndarray, faces: np.ndarray, fid: np.ndarray, bary: np.ndarray, width: float
) -> np.ndarray:
    """(M,) in [0, 1]: how much of the edge colour to use (1 on an edge, fading over one pixel)."""
    p = xy[faces[fid]]  # (M, 3, 2)
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    area2 = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    # Length of the edge opposite each corner.
    opp = np.stack(
        [
            np.linalg.norm(p[:, 2] - p[:, 1], axis=1),
            np.linalg.norm(p[:, 0] - p[:, 2], axis=1),
            np.linalg.norm(p[:, 1] - p[:, 0], axis=1),
        ],
        axis=1,
    )
    dist = (bary * area2[:, None] / np.maximum(opp, 1e-12)).min(axis=1)
    return np.clip(1.0 - (dist - width) / 1.0, 0.0, 1.0) * (dist < width + 1.0)


def _discontinuities(frags: Fragments, jump: float) -> np.ndarray:
    """(H, W) bool: covered pixels next to an empty pixel or a depth jump larger than ``jump``."""
    d = np.where(frags.mask, frags.depth, np.inf)
    pad = np.pad(d, 1, mode="constant", constant_values=np.inf)
    h, w = d.shape
    edge = np.zeros_like(frags.mask)
    with np.errstate(invalid="ignore"):
        for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
            nb = pad[dy : dy + h, dx : dx + w]
            # The farther pixel of a jump is left alone, so outlines sit on the near surface.
            edge |= frags.mask & ((nb - d) > jump)
    return edge
