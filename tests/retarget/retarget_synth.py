"""Synthetic retargeting scenes for the retarget tests: a capsule avatar on a 3-joint skeleton inside a
tube."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch
import trimesh

if TYPE_CHECKING:
    from torchgarment.retarget.inputs import RetargetProblem


def tube(radius: float, y0: float, y1: float, rings: int, segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Open cylinder around the Y axis: (rings * segments, 3) vertices and (F, 3) outward faces."""
    ang = np.linspace(0.0, 2 * math.pi, segments, endpoint=False)
    ys = np.linspace(y0, y1, rings)
    v = np.stack(
        [
            np.broadcast_to(radius * np.cos(ang), (rings, segments)),
            np.broadcast_to(ys[:, None], (rings, segments)),
            np.broadcast_to(radius * np.sin(ang), (rings, segments)),
        ],
        -1,
    ).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(segments), indexing="ij")
    a = i * segments + j
    b = i * segments + (j + 1) % segments
    c = a + segments
    d = b + segments
    f = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return v, f


def capsule(
    radius: float, y0: float, y1: float, count: tuple[int, int] = (12, 16)
) -> tuple[np.ndarray, np.ndarray]:
    """Closed capsule along Y from y0 to y1 (cap centres)."""
    m = trimesh.creation.capsule(height=y1 - y0, radius=radius, count=list(count))
    v = np.asarray(m.vertices)[:, [0, 2, 1]] + np.array([0.0, 0.5 * (y0 + y1), 0.0])
    f = np.asarray(m.faces)[:, [0, 2, 1]]
    return v, f


def project_on_chain(points: np.ndarray, joints: np.ndarray, bones: np.ndarray) -> np.ndarray:
    """Closest point of each point on the bone segments (a stand-in for the shrunk avatar)."""
    a, b = joints[bones[:, 0]], joints[bones[:, 1]]
    ab = b - a
    u = np.clip(((points[:, None] - a) * ab).sum(-1) / (ab * ab).sum(-1), 0, 1)
    q = a + u[..., None] * ab
    d = np.linalg.norm(points[:, None] - q, axis=-1)
    k = d.argmin(1)
    return q[np.arange(points.shape[0]), k]


def scene(
    garment_radius: float = 0.15,
    avatar_radius: float = 0.17,
    rings: int = 12,
    segments: int = 24,
    dtype: torch.dtype = torch.float64,
) -> dict[str, torch.Tensor]:
    """A dict of tensors: garment (tube), skeleton (3 joints, 2 bones), avatar capsule full and shrunk."""
    gv, gf = tube(garment_radius, 0.75, 1.25, rings, segments)
    joints = np.array([[0.0, 0.6, 0.0], [0.0, 1.0, 0.0], [0.0, 1.4, 0.0]])
    bones = np.array([[0, 1], [1, 2]])
    av, af = capsule(avatar_radius, 0.6, 1.4)
    shr = project_on_chain(av, joints, bones)
    # keep the shrunk avatar strictly inside: a tiny radial offset avoids coincident degenerate geometry
    t = lambda a, dt=dtype: torch.as_tensor(a, dtype=dt)  # noqa: E731
    return dict(
        garment_vertices=t(gv),
        garment_faces=t(gf, torch.long),
        joints=t(joints),
        bones=t(bones, torch.long),
        avatar_full=t(av),
        avatar_faces=t(af, torch.long),
        avatar_shrunk=t(shr),
    )


def synthetic_problem(
    garment_radius: float = 0.15,
    avatar_radius: float = 0.17,
    rings: int = 12,
    segments: int = 24,
    target_stretch: float = 1.0,
    dtype: torch.dtype = torch.float64,
) -> RetargetProblem:
    """A RetargetProblem (identity frames) of the tube garment on the capsule avatar."""
    from torchgarment.body.skeleton import Skeleton
    from torchgarment.retarget.inputs import RetargetProblem, Similarity

    s = scene(garment_radius, avatar_radius, rings, segments, dtype)
    tj = s["joints"].clone()
    tj[:, 1] = 1.0 + (tj[:, 1] - 1.0) * target_stretch
    av = s["avatar_full"].clone()
    av[:, 1] = 1.0 + (av[:, 1] - 1.0) * target_stretch
    n = s["garment_vertices"].shape[0]
    return RetargetProblem(
        garment_vertices=s["garment_vertices"],
        garment_faces=s["garment_faces"],
        source_skeleton=Skeleton(s["joints"], s["bones"]),
        target_skeleton=Skeleton(tj, s["bones"]),
        avatar_vertices=av,
        avatar_faces=s["avatar_faces"],
        skin_weights=None,
        fit_mask=torch.ones(n, dtype=torch.bool),
        curves=[],
        to_work=Similarity.identity(dtype),
        length_scale=1.7,
    )


def pocketed_tube(ring: bool = True) -> tuple[torch.Tensor, torch.Tensor, int, int]:
    """A tube (the garment, 1-3 cm around the toy avatar's torso), a patch 4 mm outside its front (a patch
    pocket: a separate piece) and, with ``ring``, a ring 5 cm outside it (a separate piece lying on nothing).

    Returns:
        ``(vertices (N, 3), faces (F, 3), tube vertex count, patch vertex count)``; the tube's vertices come
        first, then the patch's, then the ring's.
    """
    from torchgarment.retarget.avatars import tube_mesh

    gv, gf = tube_mesh(0.29, 0.23, -0.2, 1.25, 24, 10)
    pv, pf = tube_mesh(0.294, 0.234, 0.45, 0.85, 24, 5)
    th = torch.atan2(pv[:, 2] / 0.234, pv[:, 0] / 0.294)
    front = (th - math.pi / 2).abs() < 0.6
    used, inv = torch.unique(pf[front[pf].all(1)], return_inverse=True)
    pv, pf = pv[used], inv.reshape(-1, 3)
    n, m = gv.shape[0], pv.shape[0]
    vs, fs = [gv, pv], [gf, pf + n]
    if ring:
        rv, rf = tube_mesh(0.34, 0.28, 0.0, 0.1, 24, 2)
        vs.append(rv)
        fs.append(rf + n + m)
    return torch.cat(vs), torch.cat(fs), n, m
