"""Fixtures of the SDF tests."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

SPHERE_RADIUS = 0.1
"""Radius (metres) of the test spheres whose SDFs the point sets probe."""


def _mixed_points(sdf, n: int, seed: int) -> np.ndarray:
    """(4n + n/4 + 4, 3) float64 points around an SDF of a sphere of :data:`SPHERE_RADIUS` at the origin: n
    in its band, n anywhere in the grid box (coarse cells), n outside the box, n/4 exactly on grid nodes and
    4 on the box's faces."""
    rng = np.random.default_rng(seed)
    lo, hi = sdf.bounds.double().numpy()
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    band = dirs * (SPHERE_RADIUS + rng.uniform(-0.03, 0.03, size=(n, 1)))
    box = rng.uniform(lo, hi, size=(n, 3))
    out = rng.uniform(lo - 0.2, hi + 0.2, size=(n, 3))
    o, h = sdf.origin.double().numpy(), sdf.voxel_size
    nodes = o + np.round((band[: n // 4] - o) / h) * h
    faces = np.array([lo, hi, [lo[0], 0.0, hi[2]], [hi[0], 0.0, 0.0]])
    return np.concatenate([band, box, out, nodes, faces])


@pytest.fixture(scope="session")
def mixed_points() -> Callable[..., np.ndarray]:
    """``mixed_points(sdf, n, seed)``: band, box, outside, node and box-face points (``_mixed_points``)."""
    return _mixed_points
