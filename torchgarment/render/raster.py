"""A vectorized software z-buffer rasterizer for triangles in screen space (numpy, no OpenGL).

Triangles are processed in chunks. For each chunk the pixels of every triangle's bounding box are generated
with ``np.repeat``/``np.arange``, tested against the triangle with barycentric coordinates, and the nearest
fragment per pixel is found with a scatter-min (``np.minimum.at``) into the z-buffer.
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
    chunk_pixels: int = 1_000_000,
) -> Fragments:
    """Rasterize triangles with a z-buffer; both windings are drawn.

    Pixel ``(row, col)`` has its centre at screen position ``(col + 0.5, row + 0.5)``.

    Args:
        xy: (V, 2) screen positions in pixels: x to the right, y downward.
        depth: (V,) depth per vertex, smaller is nearer the viewer (any unit).
        faces: (F, 3) integer vertex indices.
        width: image width in pixels.
        height: image height in pixels.
        chunk_pixels: approximate number of candidate pixels handled at once (bounds memory use, about
            100 bytes per candidate).

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
    slot = np.zeros(npix, dtype=np.int64)

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

    # Barycentrics and depth are affine in the pixel centre: value = c + a * col + d * row, where (col, row)
    # counts pixels from the corner (cmin) of the triangle's bounding box.
    inv_area = 1.0 / np.where(ok, area, 1.0)
    ox = cmin[:, 0] + 0.5
    oy = cmin[:, 1] + 0.5

    def edge(pa: np.ndarray, pb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # Signed area of (pa, pb, p) divided by the triangle's: the barycentric of the third corner.
        ax = (pa[:, 1] - pb[:, 1]) * inv_area
        ay = (pb[:, 0] - pa[:, 0]) * inv_area
        c = ((pa[:, 0] - ox) * (pb[:, 1] - oy) - (pa[:, 1] - oy) * (pb[:, 0] - ox)) * inv_area
        return c, ax, ay

    c0, a0, d0 = edge(p1, p2)
    c1, a1, d1 = edge(p2, p0)
    z0, z1, z2 = depth[faces[:, 0]], depth[faces[:, 1]], depth[faces[:, 2]]
    c2, a2, d2 = 1.0 - c0 - c1, -a0 - a1, -d0 - d1
    cz = c0 * z0 + c1 * z1 + c2 * z2
    az = a0 * z0 + a1 * z1 + a2 * z2
    dz = d0 * z0 + d1 * z1 + d2 * z2

    # Tiles: each bounding box, cut into bands of rows when it alone exceeds chunk_pixels candidates.
    rows_per_band = np.maximum(1, chunk_pixels // nx[tri_ids])
    num_bands = -(-ny[tri_ids] // rows_per_band)
    tile_tri = np.repeat(tri_ids, num_bands)
    band = np.arange(tile_tri.size) - np.repeat(np.cumsum(num_bands) - num_bands, num_bands)
    row0 = band * np.repeat(rows_per_band, num_bands)  # first row of the tile inside its bounding box
    tile_w = nx[tile_tri]
    tile_h = np.minimum(np.repeat(rows_per_band, num_bands), ny[tile_tri] - row0)
    tile_x0 = cmin[tile_tri, 0]
    tile_y0 = cmin[tile_tri, 1] + row0
    # One contiguous array per coefficient and tile, with the constant term moved to the tile's corner.
    c0, c1, cz = (c[tile_tri] + d[tile_tri] * row0 for c, d in ((c0, d0), (c1, d1), (cz, dz)))
    a0, d0, a1, d1, az, dz = (np.ascontiguousarray(c[tile_tri]) for c in (a0, d0, a1, d1, az, dz))
    counts = tile_w * tile_h

    # Group the tiles into chunks of about chunk_pixels candidates each.
    cum = np.cumsum(counts)
    bounds = np.searchsorted(cum, np.arange(chunk_pixels, cum[-1], chunk_pixels), side="left") + 1
    bounds = np.unique(np.concatenate([[0], np.minimum(bounds, tile_tri.size), [tile_tri.size]]))

    for a, b in zip(bounds[:-1], bounds[1:]):
        cnt = counts[a:b]
        total = int(cnt.sum())
        t = np.repeat(np.arange(a, b), cnt)
        local = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        ly = local // tile_w[t]
        lx = local - ly * tile_w[t]
        fx = lx.astype(np.float64)
        fy = ly.astype(np.float64)
        b0 = c0[t] + a0[t] * fx + d0[t] * fy
        b1 = c1[t] + a1[t] * fx + d1[t] * fy
        inside = np.nonzero((b0 >= -_BARY_EPS) & (b1 >= -_BARY_EPS) & (b0 + b1 <= 1.0 + _BARY_EPS))[0]
        t, b0, b1, fx, fy = t[inside], b0[inside], b1[inside], fx[inside], fy[inside]
        z = cz[t] + az[t] * fx + dz[t] * fy
        pix = (tile_y0[t] + ly[inside]) * width + tile_x0[t] + lx[inside]
        # Nearest fragment per pixel: scatter-min the depths, keep the fragments that reached the minimum.
        np.minimum.at(zbuf, pix, z)
        win = np.nonzero(z == zbuf[pix])[0]
        if win.size == 0:
            continue
        tgt = pix[win]
        # Exact depth ties leave several winners per pixel; take whichever the scatter kept, for all buffers.
        slot[tgt] = win
        sel = slot[tgt]
        fbuf[tgt] = tile_tri[t[sel]]
        bbuf[tgt, 0] = b0[sel]
        bbuf[tgt, 1] = b1[sel]
        bbuf[tgt, 2] = 1.0 - b0[sel] - b1[sel]
    return _fragments(fbuf, bbuf, zbuf, width, height)


def _fragments(fbuf: np.ndarray, bbuf: np.ndarray, zbuf: np.ndarray, width: int, height: int) -> Fragments:
    return Fragments(
        face=fbuf.reshape(height, width),
        bary=bbuf.reshape(height, width, 3),
        depth=zbuf.reshape(height, width),
    )
