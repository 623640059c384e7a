"""A vectorized software z-buffer rasterizer for triangles in screen space (numpy, no OpenGL).

Triangles are processed in chunks. For each chunk the pixels of every triangle's bounding box are generated
with ``np.repeat``/``np.arange``, tested against the triangle with barycentric coordinates, and the nearest
fragment per pixel is found with a lexsort on (pixel, depth) and merged into the z-buffer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Tolerance on barycentric coordinates so that pixel centres exactly on a shared edge are never dropped.
_BARY_EPS = 1e-7


@dataclass
class Fragments:
    """Per-pixel result of :func:`rasterize` (row 0 is the top of the image).

    Attributes:
        face: (H, W) int64 index of the nearest triangle, -1 where no triangle covers the pixel centre.
        bary: (H, W, 3) float64 barycentric coordinates of the pixel centre in that triangle (0 where empty).
        depth: (H, W) float64 depth of the nearest fragment (smaller is nearer), +inf where empty.
    """

    face: np.ndarray
    bary: np.ndarray
    depth: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool: pixels covered by some triangle."""
        return self.face >= 0


def rasterize(
    xy: np.ndarray,
    depth: np.ndarray,
    faces: np.ndarray,
    width: int,
    height: int,
    chunk_pixels: int = 2_000_000,
) -> Fragments:
    """Rasterize triangles with a z-buffer; both windings are drawn.

    Pixel ``(row, col)`` has its centre at screen position ``(col + 0.5, row + 0.5)``.

    Args:
        xy: (V, 2) screen positions in pixels: x to the right, y downward.
        depth: (V,) depth per vertex, smaller is nearer the viewer (any unit).
        faces: (F, 3) integer vertex indices.
        width: image width in pixels.
        height: image height in pixels.
        chunk_pixels: approximate number of candidate pixels handled at once (bounds memory use).

    Returns:
        The nearest fragment per pixel.
    """
    xy = np.asarray(xy, dtype=np.float64)
    depth = np.asarray(depth, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    npix = width * height
    zbuf = np.full(npix, np.inf)
    fbuf = np.full(npix, -1, dtype=np.int64)
    bbuf = np.zeros((npix, 3))

    p0, p1, p2 = xy[faces[:, 0]], xy[faces[:, 1]], xy[faces[:, 2]]
    area = (p1[:, 0] - p0[:, 0]) * (p2[:, 1] - p0[:, 1]) - (p1[:, 1] - p0[:, 1]) * (p2[:, 0] - p0[:, 0])
    lo = np.minimum(np.minimum(p0, p1), p2)
    hi = np.maximum(np.maximum(p0, p1), p2)
    # Pixels whose centre c + 0.5 lies in [lo, hi].
    cmin = np.maximum(np.ceil(lo - 0.5), 0).astype(np.int64)
    cmax = np.minimum(np.floor(hi - 0.5), [width - 1, height - 1]).astype(np.int64)
    nx = cmax[:, 0] - cmin[:, 0] + 1
    ny = cmax[:, 1] - cmin[:, 1] + 1
    ok = (nx > 0) & (ny > 0) & (np.abs(area) > 1e-12) & np.isfinite(area)
    tri_ids = np.nonzero(ok)[0]
    if tri_ids.size == 0:
        return _fragments(fbuf, bbuf, zbuf, width, height)
    counts = nx[tri_ids] * ny[tri_ids]

    # Split the triangles into chunks of about chunk_pixels candidates each.
    cum = np.cumsum(counts)
    bounds = np.searchsorted(cum, np.arange(chunk_pixels, cum[-1], chunk_pixels), side="left")
    bounds = np.unique(np.concatenate([[0], bounds + 1, [tri_ids.size]]))
    bounds = bounds[bounds <= tri_ids.size]

    inv_area = 1.0 / area
    z0, z1, z2 = depth[faces[:, 0]], depth[faces[:, 1]], depth[faces[:, 2]]
    for a, b in zip(bounds[:-1], bounds[1:]):
        ids = tri_ids[a:b]
        cnt = counts[a:b]
        total = int(cnt.sum())
        if total == 0:
            continue
        tri = np.repeat(ids, cnt)
        starts = np.repeat(np.cumsum(cnt) - cnt, cnt)
        local = np.arange(total, dtype=np.int64) - starts
        w = nx[tri]
        px = cmin[tri, 0] + local % w
        py = cmin[tri, 1] + local // w
        cx = px + 0.5
        cy = py + 0.5
        # Barycentric coordinates from edge functions.
        q1, q2 = p1[tri], p2[tri]
        inv = inv_area[tri]
        b0 = ((q1[:, 0] - cx) * (q2[:, 1] - cy) - (q1[:, 1] - cy) * (q2[:, 0] - cx)) * inv
        q0 = p0[tri]
        b1 = ((q2[:, 0] - cx) * (q0[:, 1] - cy) - (q2[:, 1] - cy) * (q0[:, 0] - cx)) * inv
        b2 = 1.0 - b0 - b1
        inside = (b0 >= -_BARY_EPS) & (b1 >= -_BARY_EPS) & (b2 >= -_BARY_EPS)
        tri, b0, b1, b2 = tri[inside], b0[inside], b1[inside], b2[inside]
        pix = py[inside] * width + px[inside]
        z = b0 * z0[tri] + b1 * z1[tri] + b2 * z2[tri]
        closer = z < zbuf[pix]
        if not closer.any():
            continue
        tri, b0, b1, b2, pix, z = tri[closer], b0[closer], b1[closer], b2[closer], pix[closer], z[closer]
        order = np.lexsort((z, pix))
        ps = pix[order]
        first = np.ones(ps.size, dtype=bool)
        first[1:] = ps[1:] != ps[:-1]
        sel = order[first]
        tgt = pix[sel]
        zbuf[tgt] = z[sel]
        fbuf[tgt] = tri[sel]
        bbuf[tgt, 0] = b0[sel]
        bbuf[tgt, 1] = b1[sel]
        bbuf[tgt, 2] = b2[sel]
    return _fragments(fbuf, bbuf, zbuf, width, height)


def _fragments(fbuf: np.ndarray, bbuf: np.ndarray, zbuf: np.ndarray, width: int, height: int) -> Fragments:
    return Fragments(
        face=fbuf.reshape(height, width),
        bary=bbuf.reshape(height, width, 3),
        depth=zbuf.reshape(height, width),
    )
