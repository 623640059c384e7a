"""Triangulate a sewing pattern into a :class:`~torchgarment.structures.GarmentMesh` ready to sew.

Each panel is meshed on its own with Shewchuk's Triangle (package ``triangle``): a conforming constrained
Delaunay triangulation with a minimum-angle and a maximum-area bound (switches ``p q<angle> a<area> Y``).
The outline is first cut into segments of equal arc length (:meth:`Edge.sample_by_length`): an edge of
length ``L`` gets ``ceil(L / edge_length)`` segments, and the two sides of a stitch both get the larger of
their two counts, so the seam vertices pair one to one (respecting :class:`StitchOrientation`). Triangle
must not split these boundary segments (switch ``Y``), which keeps the pairing exact.

The panels stay separate in the result: seam vertices exist once per panel and ``seam_pairs`` lists the
pairs the stitches join. Faces are oriented so that their normals, after 3D placement, point out of the
garment (panels run counter-clockwise seen from outside, see :mod:`torchgarment.pattern.spec`).

The vertex layout is recorded on the mesh (``mesh.layout``, a :class:`~torchgarment.structures.MeshLayout`):
each panel's vertices are contiguous, in the pattern's panel order, its outline first, edge by edge, so every
(panel, edge) maps to a run of vertices.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from torchgarment.errors import InputError, MeshError, PatternError
from torchgarment.options import env_limit
from torchgarment.pattern.spec import SewingPattern, Stitch, StitchOrientation
from torchgarment.structures.garment_mesh import GarmentMesh, MeshLayout

MAX_STITCH_LENGTH_RATIO = 1.5
"""Stitched edges may differ in length by this ratio (gathering); see :meth:`SewingPattern.validate`."""

# Triangle's quality refinement is only guaranteed to terminate up to about 33.8 degrees
_MAX_MIN_ANGLE = 34.0

DEFAULT_MAX_VERTICES = 500_000
"""Largest garment mesh :func:`mesh_pattern` builds by default, in vertices (estimated before meshing from the
panels' areas and edge lengths): about 15 times the paper's 34K-vertex dress, and about 25 GB in a drape
(50 kB per vertex). The environment variable ``TORCHGARMENT_MAX_VERTICES`` raises or lowers it."""


def max_vertices() -> int:
    """The vertex limit in force: ``TORCHGARMENT_MAX_VERTICES`` when set, else :data:`DEFAULT_MAX_VERTICES`.

    Raises:
        InputError: the variable is not a number >= 1.
    """
    return int(env_limit("TORCHGARMENT_MAX_VERTICES", DEFAULT_MAX_VERTICES, 1))


def estimate_vertices(pattern: SewingPattern, edge_length: float) -> float:
    """Vertices :func:`mesh_pattern` would make at ``edge_length`` (metres), estimated before meshing: per
    panel its area over ``0.866 e^2`` (two triangles of mean area ``sqrt(3)/4 e^2`` per vertex) plus half its
    outline's segments."""
    total = 0.0
    for panel in pattern.panels.values():
        perimeter = sum(panel.edge_length(i) for i in range(len(panel.edges)))
        total += abs(panel.area()) / (0.866 * edge_length**2) + 0.5 * perimeter / edge_length
    return total


def edge_segment_counts(pattern: SewingPattern, edge_length: float) -> dict[str, np.ndarray]:
    """Number of boundary segments of every panel edge, equal on both sides of each stitch.

    Args:
        pattern: a valid pattern.
        edge_length: target edge length in metres.

    Returns:
        Panel name -> (n_edges,) int array: ``ceil(length / edge_length)`` (at least 1), raised to the
        larger count of the two sides for stitched edges.
    """
    counts = {
        name: np.array([max(1, math.ceil(panel.edge_length(i) / edge_length - 1e-9))
                        for i in range(len(panel.edges))],
                       dtype=np.int64)
        for name, panel in pattern.panels.items()
    }
    for s in pattern.stitches:
        n = max(counts[s.a.panel][s.a.edge], counts[s.b.panel][s.b.edge])
        counts[s.a.panel][s.a.edge] = n
        counts[s.b.panel][s.b.edge] = n
    return counts


def mesh_pattern(
    pattern: SewingPattern,
    edge_length: float = 0.01,
    *,
    min_angle: float = 25.0,
    max_stitch_length_ratio: float = MAX_STITCH_LENGTH_RATIO,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> GarmentMesh:
    """Triangulate every panel at a target edge length and collect the seam vertex pairs.

    Args:
        pattern: the sewing pattern; validated first (:meth:`SewingPattern.validate`).
        edge_length: target triangle edge length in metres (boundary spacing is at most this).
        min_angle: minimum triangle angle in degrees asked of Triangle, in (0, 34]. Angles of the outline
            itself (dart tips, sharp corners) can be smaller, since the boundary is never split.
        max_stitch_length_ratio: passed to :meth:`SewingPattern.validate`.
        dtype: floating dtype of the result. device: its device.

    Returns:
        A :class:`GarmentMesh` with ``x`` (V, 3) placed positions, ``p`` (V, 2) panel coordinates,
        ``faces`` (F, 3), per-face ``panel_ids`` indexing ``panel_names`` (the pattern's panel order) and
        ``seam_pairs`` (S, 2): unique vertex pairs joined by the stitches, smaller index first (a corner
        where several seams meet appears once per distinct pair; self-pairs such as a dart tip are left out),
        and its ``layout`` (:class:`~torchgarment.structures.MeshLayout`): per panel and edge, the vertices
        sampled along the edge.

    Raises:
        InputError: bad ``edge_length`` (also: longer than half the largest panel's outline, a unit
            mistake) or ``min_angle``; more vertices estimated than :func:`max_vertices`.
        PatternError: the pattern is invalid.
        MeshError: Triangle failed on a panel.
    """
    import triangle

    if not (isinstance(edge_length, (int, float)) and math.isfinite(edge_length) and edge_length > 0):
        raise InputError(f"edge_length must be a positive number of metres, got {edge_length!r}")
    if not (isinstance(min_angle, (int, float)) and 0.0 < min_angle <= _MAX_MIN_ANGLE):
        raise InputError(f"min_angle must be in (0, {_MAX_MIN_ANGLE}] degrees, got {min_angle!r}")
    pattern.validate(max_stitch_length_ratio=max_stitch_length_ratio)
    largest = max(0.5 * sum(panel.edge_length(i) for i in range(len(panel.edges)))
                  for panel in pattern.panels.values())
    if edge_length > largest:
        raise InputError(f"an edge length of {edge_length:g} m is longer than the largest panel of "
                         f"{pattern.name!r} ({largest:.3g} m, half its outline): edge lengths are in metres "
                         "(e.g. 0.01 for 1 cm)")
    estimate, limit = estimate_vertices(pattern, edge_length), max_vertices()
    if estimate > limit:
        raise InputError(f"meshing {pattern.name!r} at {edge_length:g} m edges would make about "
                         f"{estimate:.3g} vertices (limit {limit}): use a larger edge length, or raise the "
                         "limit with TORCHGARMENT_MAX_VERTICES")

    counts = edge_segment_counts(pattern, edge_length)
    # Triangle keeps areas well below the bound; 1.44 x the equilateral area gives a mean edge close to
    # edge_length on the four GarmentCode specs (measured 0.83 edge_length with the plain equilateral area)
    max_area = 1.44 * math.sqrt(3.0) / 4.0 * edge_length**2
    # Triangle parses its switches itself: no exponent notation
    opts = (f"pq{np.format_float_positional(min_angle, trim='-')}"
            f"a{np.format_float_positional(max_area, trim='-')}YQ")

    xs, ps, fs, ids = [], [], [], []
    # panel -> per edge, its (n + 1,) vertices from start to end vertex
    runs: dict[str, list[np.ndarray]] = {}
    starts, nbs = [0], []
    offset = 0
    for k, (name, panel) in enumerate(pattern.panels.items()):
        n = counts[name]
        boundary = np.concatenate(
            [e.sample_by_length(*panel.edge_endpoints(i), int(n[i]))[:-1] for i, e in enumerate(panel.edges)]
        )
        nb = boundary.shape[0]
        seg = np.stack([np.arange(nb), (np.arange(nb) + 1) % nb], axis=1)
        try:
            out = triangle.triangulate({"vertices": boundary, "segments": seg}, opts)
        except Exception as exc:  # triangle raises plain RuntimeError/ValueError on failure
            raise MeshError(f"panel '{name}': Triangle failed ({exc})") from exc
        verts = np.asarray(out.get("vertices", np.zeros((0, 2))), dtype=np.float64)
        tris = np.asarray(out.get("triangles", np.zeros((0, 3))), dtype=np.int64)
        if tris.shape[0] == 0 or verts.shape[0] < nb or not np.array_equal(verts[:nb], boundary):
            raise MeshError(f"panel '{name}': Triangle did not keep the {nb} boundary vertices")
        _check_boundary_kept(name, tris, nb)
        if panel.area() < 0:  # outline clockwise in 2D: flip so normals point outward once placed
            tris = tris[:, [0, 2, 1]]
        ps.append(verts)
        xs.append(panel.to_3d(verts))
        fs.append(tris + offset)
        ids.append(np.full(tris.shape[0], k, dtype=np.int64))
        first = np.concatenate([[0], np.cumsum(n)])  # (n_edges + 1,) each edge's first sample; first[-1] = nb
        runs[name] = [offset + np.arange(first[i], first[i] + n[i] + 1) % nb for i in range(len(panel.edges))]
        offset += verts.shape[0]
        starts.append(offset)
        nbs.append(nb)

    pairs = [_stitch_pairs(runs, s) for s in pattern.stitches]
    seam = np.concatenate(pairs) if pairs else np.zeros((0, 2), dtype=np.int64)
    seam = np.sort(seam, axis=1)
    seam = seam[seam[:, 0] != seam[:, 1]]
    seam = np.unique(seam, axis=0) if seam.shape[0] else seam.reshape(0, 2)

    dev = torch.device("cpu") if device is None else torch.device(device)
    layout = MeshLayout(
        tuple(pattern.panels),
        torch.as_tensor(starts, dtype=torch.long, device=dev),
        torch.as_tensor(nbs, dtype=torch.long, device=dev),
        tuple(tuple(torch.as_tensor(r, dtype=torch.long, device=dev) for r in runs[name])
              for name in pattern.panels),
    )
    return GarmentMesh.from_arrays(
        np.concatenate(xs), np.concatenate(fs), p=np.concatenate(ps), panel_ids=np.concatenate(ids),
        panel_names=list(pattern.panels), seam_pairs=seam, layout=layout, dtype=dtype, device=device,
    )


def _stitch_pairs(runs: dict[str, list[np.ndarray]], s: Stitch) -> np.ndarray:
    """(n + 1, 2) vertex pairs the stitch ``s`` joins, from the vertex runs of its two edges."""
    ia = runs[s.a.panel][s.a.edge]
    ib = runs[s.b.panel][s.b.edge]
    if ia.shape != ib.shape:  # cannot happen: edge_segment_counts equalizes both sides
        raise PatternError(f"stitch {s.a.panel}[{s.a.edge}] - {s.b.panel}[{s.b.edge}]: unequal vertex counts")
    if s.orientation is StitchOrientation.OPPOSITE:
        ib = ib[::-1]
    return np.stack([ia, ib], axis=1)


def _check_boundary_kept(name: str, tris: np.ndarray, nb: int) -> None:
    """The mesh boundary must be exactly the input outline (no Steiner points on it, nothing else open)."""
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    key = np.sort(e, axis=1)
    uniq, cnt = np.unique(key, axis=0, return_counts=True)
    boundary = uniq[cnt == 1]
    expected = np.sort(np.stack([np.arange(nb), (np.arange(nb) + 1) % nb], axis=1), axis=1)
    if boundary.shape[0] != nb or not np.array_equal(np.unique(expected, axis=0), boundary):
        raise MeshError(f"panel '{name}': triangulated boundary ({boundary.shape[0]} edges) differs from the "
                        f"outline ({nb} segments)")
