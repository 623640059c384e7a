"""Continuous deformation transfer of a garment from one body to another (Wang et al. 2018, Eq. 15).

Each garment vertex ``x̄_i`` is attached to its closest base-body triangle ``t0`` and to the closest triangle
``t1`` of a *different* local minimum of the point-triangle distance (over the triangle adjacency graph of the
body), and its transferred position is the blend::

    x̃_i = w x̃_i0 + (1 - w) x̃_i1,    w = 0.5 + min(d_i1 - d_i0, 2B) / (4B),

with ``d`` the point-triangle distances and ``B`` the transition bandwidth. (The paper prints
``min(d_i0 - d_i1, 2B)``, which with ``d_i0 <= d_i1`` would weight the FARTHER triangle more; the sign is
flipped here so that ``w = 1`` when the second minimum is at least ``2B`` farther and ``w = 1/2`` at a tie,
which is what makes the transfer continuous.)

Per triangle, a vertex is stored in the triangle's affine frame: ``x̄ = v0 + a e1 + b e2 + h n`` (``e1``,
``e2`` edges, ``n`` unit normal, ``a``, ``b`` unclamped barycentric coordinates, ``h`` the height over the
plane) and transferred as ``x̃ = v0' + a e1' + b e2' + h s n'``, where ``s`` is 1 (:class:`OffsetScaling`
``distance``: the paper's "vertex-triangle distance" is kept) or ``sqrt(area'/area)`` (``scaled``, default:
the offset grows with the triangle, so that a body scaled by ``s`` carries the garment scaled by ``s``
exactly, and the ease of a graded garment scales with the body).

``t0`` is exact (libigl's AABB tree). The second minimum is searched among the ``candidates`` nearest
triangles by centroid (default 48): a candidate is a local minimum when no vertex-adjacent candidate is
strictly closer, and local minima whose closest point coincides with ``t0``'s (triangles around a shared
closest vertex or edge) belong to ``t0``'s basin and are skipped. Only ``d_i1 < d_i0 + 2B`` matters. (An exact
candidate set, every triangle with centroid within ``d_i0 + 2B + r_max``, measured 200 s for 30K points on the
anny body whose largest triangles reach 3 cm, so the candidate search is approximate; a missed second minimum
farther than the candidates only removes a blend.)
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
from scipy.spatial import cKDTree

from torchgarment.body.body import Body
from torchgarment.errors import InputError
from torchgarment.options import OptionEnum
from torchgarment.sdf import closest_points_on_triangles

if TYPE_CHECKING:
    import scipy.sparse

DEFAULT_BAND = 0.01
"""Transition bandwidth ``B`` of Eq. 15 in metres (the paper gives no value)."""

_CHUNK_PAIRS = 400_000  # point-triangle pairs evaluated per block

DEFAULT_CANDIDATES = 48
"""Nearest body triangles (by centroid) searched for the second local minimum."""


class OffsetScaling(OptionEnum):
    """How the height of a vertex over its body triangle is transferred (see the module docstring)."""

    SCALED = "scaled"
    DISTANCE = "distance"


def _frames(v: np.ndarray,
            f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-triangle frame: v0, e1, e2, unit normal n, area."""
    v0 = v[f[:, 0]]
    e1 = v[f[:, 1]] - v0
    e2 = v[f[:, 2]] - v0
    cr = np.cross(e1, e2)
    dbl = np.linalg.norm(cr, axis=1)
    n = cr / np.maximum(dbl, 1e-300)[:, None]
    return v0, e1, e2, n, 0.5 * dbl


def _local_coordinates(x: np.ndarray, v0: np.ndarray, e1: np.ndarray, e2: np.ndarray,
                       n: np.ndarray) -> np.ndarray:
    """(N, 3) ``(a, b, h)`` with ``x = v0 + a e1 + b e2 + h n`` (rows matched)."""
    r = x - v0
    h = (r * n).sum(1)
    r = r - h[:, None] * n
    g11, g12, g22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    r1, r2 = (r * e1).sum(1), (r * e2).sum(1)
    det = g11 * g22 - g12 * g12
    a = (g22 * r1 - g12 * r2) / det
    b = (g11 * r2 - g12 * r1) / det
    return np.stack([a, b, h], 1)


def _vertex_adjacency(f: np.ndarray, num_vertices: int) -> scipy.sparse.csr_matrix:
    """(F, F) sparse boolean: triangles sharing a vertex (diagonal included)."""
    import scipy.sparse

    F = f.shape[0]
    inc = scipy.sparse.coo_matrix((np.ones(3 * F), (np.repeat(np.arange(F), 3), f.reshape(-1))),
                                  shape=(F, num_vertices)).tocsr()
    return (inc @ inc.T).tocsr()


def two_minimum_triangles(x: np.ndarray, v: np.ndarray, f: np.ndarray, band: float, *,
                          candidates: int = DEFAULT_CANDIDATES
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The closest triangle and the closest triangle of another local minimum within ``d0 + 2 band``.

    Args:
        x: (N, 3) points. v: (Vb, 3) body vertices. f: (F, 3) body faces. band: ``B`` (metres).
        candidates: number of nearest triangles (by centroid) searched for the second minimum.

    Returns:
        ``(t0, d0, t1, d1)``: (N,) closest triangle and distance (exact, AABB tree); (N,) second-minimum
        triangle (-1 if none within ``d0 + 2 band``) and its distance (``inf`` if none).
    """
    import igl

    N = x.shape[0]
    sq, t0, _ = igl.point_mesh_squared_distance(np.ascontiguousarray(x), np.ascontiguousarray(v),
                                                np.ascontiguousarray(f))
    t0 = np.asarray(t0, dtype=np.int64).reshape(N)
    d0 = np.sqrt(np.maximum(np.asarray(sq, dtype=np.float64).reshape(N), 0.0))
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    tree = cKDTree((a + b + c) / 3.0)
    k = int(min(candidates, f.shape[0]))
    adj = _vertex_adjacency(f, v.shape[0])
    t1 = np.full(N, -1, dtype=np.int64)
    d1 = np.full(N, np.inf)
    step = max(1, _CHUNK_PAIRS // k)
    for s in range(0, N, step):
        idx = np.arange(s, min(N, s + step))
        _, cand = tree.query(x[idx], k=k)
        cand = np.asarray(cand, dtype=np.int64).reshape(len(idx), k)
        _second(x, idx, cand, a, b, c, adj, t0, d0, band, t1, d1)
    return t0, d0, t1, d1


def _second(x: np.ndarray, idx: np.ndarray, cand: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray,
            adj: scipy.sparse.csr_matrix, t0: np.ndarray, d0: np.ndarray, band: float, t1: np.ndarray,
            d1: np.ndarray) -> None:
    """Fill t1/d1 for the points ``idx`` from their candidate triangles ``cand`` (n, k)."""
    n, k = cand.shape
    owner = np.repeat(idx, k)
    tri = cand.reshape(-1)
    cp = closest_points_on_triangles(x[owner], a[tri], b[tri], c[tri])
    d = np.linalg.norm(x[owner] - cp, axis=1)
    # local minimum among the candidates of the same point: no vertex-adjacent candidate strictly closer.
    # Neighbours outside the candidate set are ignored; a false minimum at the rim of the set is a triangle
    # near t0 whose frame nearly agrees with t0's, which keeps the blend continuous.
    F = adj.shape[0]
    m = len(owner)
    key = owner * (F + 1) + tri
    sorter = np.argsort(key)
    key_sorted = key[sorter]
    ptr, nb = adj.indptr, adj.indices
    deg = ptr[tri + 1] - ptr[tri]
    rep = np.repeat(np.arange(m), deg)
    offs = np.cumsum(deg) - deg
    nbr = nb[np.arange(int(deg.sum())) - np.repeat(offs, deg) + np.repeat(ptr[tri], deg)]
    nkey = owner[rep] * (F + 1) + nbr
    pos = np.minimum(np.searchsorted(key_sorted, nkey), m - 1)
    dn = np.where(key_sorted[pos] == nkey, d[sorter[pos]], np.inf)
    closer = np.zeros(m, dtype=bool)
    np.logical_or.at(closer, rep, dn < d[rep] - 1e-12)
    # not t0's basin: the closest point differs from t0's
    cp0 = closest_points_on_triangles(x[idx], a[t0[idx]], b[t0[idx]], c[t0[idx]])
    other = np.linalg.norm(cp - np.repeat(cp0, k, axis=0), axis=1) > 1e-9
    ok = ~closer & other & (tri != t0[owner]) & (d < d0[owner] + 2.0 * band)
    d = np.where(ok, d, np.inf).reshape(n, k)
    j = np.argmin(d, axis=1)
    best = d[np.arange(n), j]
    has = np.isfinite(best)
    t1[idx[has]] = cand[np.arange(n), j][has]
    d1[idx[has]] = best[has]


def transfer_deformation(x_base: torch.Tensor, base_body: Body, target_body: Body, *,
                         band: float = DEFAULT_BAND,
                         offset: OffsetScaling | str = OffsetScaling.SCALED) -> torch.Tensor:
    """Transfer a garment draped on ``base_body`` to ``target_body`` (Eq. 15).

    Args:
        x_base: (V, 3) garment positions on the base body (metres).
        base_body, target_body: bodies with the same topology (same vertex count and faces).
        band: transition bandwidth ``B`` (metres, > 0).
        offset: :class:`OffsetScaling` of the height over the triangle (default ``scaled``).

    Returns:
        (V, 3) transferred positions, dtype and device of ``x_base`` (not differentiable: a constant target).

    Raises:
        InputError: different body topologies, bad shapes, or a non-positive band.
    """
    mode = OffsetScaling.resolve(offset)
    if not isinstance(x_base, torch.Tensor) or x_base.ndim != 2 or x_base.shape[1] != 3:
        raise InputError(f"x_base must be a (V, 3) tensor, got {getattr(x_base, 'shape', type(x_base))}")
    if not band > 0:
        raise InputError(f"band must be > 0 metres, got {band}")
    vb = base_body.vertices.detach().cpu().double().numpy()
    vt = target_body.vertices.detach().cpu().double().numpy()
    fb = base_body.faces.detach().cpu().numpy().astype(np.int64)
    ft = target_body.faces.detach().cpu().numpy().astype(np.int64)
    if vb.shape != vt.shape or fb.shape != ft.shape or not np.array_equal(fb, ft):
        raise InputError(f"deformation transfer needs bodies of one topology: base has {vb.shape[0]} "
                         f"vertices and {fb.shape[0]} faces, target {vt.shape[0]} and {ft.shape[0]} (or "
                         "different faces)")
    x = x_base.detach().cpu().double().numpy()
    t0, d0, t1, d1 = two_minimum_triangles(x, vb, fb, band)
    F0 = _frames(vb, fb)
    F1 = _frames(vt, fb)
    scale = np.sqrt(F1[4] / np.maximum(F0[4], 1e-300)) if mode is OffsetScaling.SCALED else np.ones(len(fb))

    def place(t: np.ndarray) -> np.ndarray:
        abh = _local_coordinates(x, F0[0][t], F0[1][t], F0[2][t], F0[3][t])
        return (F1[0][t] + abh[:, :1] * F1[1][t] + abh[:, 1:2] * F1[2][t]
                + (abh[:, 2] * scale[t])[:, None] * F1[3][t])

    x0 = place(t0)
    has1 = t1 >= 0
    w = np.ones(len(x))
    w[has1] = 0.5 + np.minimum(d1[has1] - d0[has1], 2.0 * band) / (4.0 * band)
    out = x0.copy()
    if has1.any():
        x1 = place(np.where(has1, t1, t0))
        out[has1] = w[has1, None] * x0[has1] + (1.0 - w[has1, None]) * x1[has1]
    return torch.as_tensor(out, dtype=x_base.dtype, device=x_base.device)


def level_support(x_transfer: torch.Tensor, x_base: torch.Tensor, support: torch.Tensor, height: float,
                  base_hips: float) -> tuple[torch.Tensor, float]:
    """Level a transferred garment's support with the target body's waist plane.

    The transfer follows the body's surface, the landmark planes do not: between chart sizes the waist plane
    (the smallest torso girth) moves by up to 2 cm relative to the surface, so a waistband transferred from
    the base's waist lands above or below the target's. This moves the support's vertices vertically by
    ``δ = height - mean(x̃_y[support])`` and every other vertex between the support and the base body's hip
    plane by ``δ`` times a weight falling linearly with its base height from 1 at the support's mean height to
    0 at ``base_hips`` (vertices below are unchanged, vertices above move by ``δ``): the garment below the
    band follows it instead of hanging away from the positional cost's targets.

    Args:
        x_transfer: (V, 3) transferred garment (metres). x_base: (V, 3) the base drape it came from.
        support: (P,) long indices of the support's vertices.
        height: the support's target mean height (m): the target's waist plane plus the base support's height
            above the base's waist plane.
        base_hips: height (m) of the base body's hip plane.

    Returns:
        The levelled (V, 3) garment and ``δ`` (m, up positive).

    Raises:
        InputError: shapes differ, an empty support, a non-finite height, or a hip plane not below the
            support.
    """
    if x_transfer.shape != x_base.shape or x_base.ndim != 2 or x_base.shape[1] != 3:
        raise InputError(f"x_transfer and x_base must be the same (V, 3), got {tuple(x_transfer.shape)} and "
                         f"{tuple(x_base.shape)}")
    if support.ndim != 1 or support.numel() == 0:
        raise InputError(f"support must be (P,) indices with P >= 1, got {tuple(support.shape)}")
    if not (np.isfinite(height) and np.isfinite(base_hips)):
        raise InputError(f"the support's height and the hip plane must be finite, got {height}, {base_hips}")
    support = support.to(x_transfer.device)
    band = float(x_base[support, 1].mean())
    if not base_hips < band:
        raise InputError(f"the base hip plane ({base_hips:.3f} m) must be below the support ({band:.3f} m)")
    delta = float(height) - float(x_transfer[support, 1].mean())
    w = ((x_base[:, 1].to(x_transfer) - base_hips) / (band - base_hips)).clamp(0.0, 1.0)
    w[support] = 1.0  # the whole support moves by δ (its vertices sag a little below their mean height)
    out = x_transfer.clone()
    out[:, 1] += delta * w
    return out, delta
