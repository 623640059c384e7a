"""Camera views and the orthographic camera that fits a scene into an image."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np

from torchgarment.errors import InputError


class View(Enum):
    """Where the viewer stands (world is +Y up, the body faces +Z).

    FRONT: viewer at +Z looking along -Z. SIDE: viewer at +X looking along -X. BACK: viewer at -Z looking
    along +Z.
    """

    FRONT = "front"
    SIDE = "side"
    BACK = "back"

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) world-to-camera rotation; camera axes are x right, y up, z toward the viewer."""
        return _ROTATIONS[self].copy()


_ROTATIONS = {
    View.FRONT: np.eye(3),
    View.SIDE: np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]),
    View.BACK: np.array([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]),
}


@dataclass(frozen=True)
class OrthoCamera:
    """An orthographic camera.

    Attributes:
        view: viewing direction.
        center: (2,) camera-space point (metres) drawn at the image centre.
        scale: pixels per metre.
        width: image width in pixels.
        height: image height in pixels.
    """

    view: View
    center: tuple[float, float]
    scale: float
    width: int
    height: int

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points to the screen.

        Args:
            points: (N, 3) world positions in metres.

        Returns:
            xy: (N, 2) pixel positions (x right, y down; pixel (r, c) has its centre at (c + 0.5, r + 0.5)).
            depth: (N,) distance along the viewing direction in metres, smaller is nearer.
        """
        cam = np.asarray(points, dtype=np.float64) @ self.view.rotation.T
        x = (cam[:, 0] - self.center[0]) * self.scale + 0.5 * self.width
        y = 0.5 * self.height - (cam[:, 1] - self.center[1]) * self.scale
        return np.stack([x, y], axis=1), -cam[:, 2]

    def with_size(self, width: int, height: int) -> "OrthoCamera":
        """The same framing at another resolution (used for supersampling)."""
        factor = min(width / self.width, height / self.height)
        return OrthoCamera(self.view, self.center, self.scale * factor, width, height)


def fit_camera(
    points: np.ndarray,
    view: View,
    size: tuple[int, int],
    margin: float = 0.05,
    views_for_scale: tuple[View, ...] | None = None,
) -> OrthoCamera:
    """An orthographic camera that shows all ``points`` centred with a margin.

    Args:
        points: (N, 3) world positions in metres, N >= 1, finite.
        view: viewing direction.
        size: (width, height) in pixels.
        margin: empty border on each side, as a fraction of the image size, in [0, 0.45].
        views_for_scale: when given, the scale is the largest that fits the points in every one of these
            views, so that several views of one scene share the same pixels per metre.

    Returns:
        The camera.
    """
    width, height = int(size[0]), int(size[1])
    if width < 1 or height < 1:
        raise InputError(f"image size must be positive, got {size}")
    if not 0.0 <= margin <= 0.45:
        raise InputError(f"margin must be in [0, 0.45], got {margin}")
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if pts.shape[0] == 0:
        raise InputError("cannot fit a camera to an empty scene")

    def extent(v: View) -> tuple[np.ndarray, np.ndarray]:
        cam = pts @ v.rotation.T
        return cam[:, :2].min(axis=0), cam[:, :2].max(axis=0)

    usable = np.array([width, height]) * (1.0 - 2.0 * margin)
    scales = []
    for v in views_for_scale or (view,):
        lo, hi = extent(v)
        span = np.maximum(hi - lo, 1e-9)
        scales.append(float(np.min(usable / span)))
    lo, hi = extent(view)
    center = 0.5 * (lo + hi)
    return OrthoCamera(view, (float(center[0]), float(center[1])), min(scales), width, height)
