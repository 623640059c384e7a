"""Continuous deformation transfer (Wang 2018 Eq. 15): identity, similarity, two-minimum blending, errors."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from torchgarment.adjust.transfer import (
    level_support,
    transfer_deformation,
    two_minimum_triangles,
)
from torchgarment.body.body import Body
from torchgarment.errors import InputError

_CACHE: dict = {}


def body12() -> Body:
    if "b" not in _CACHE:
        _CACHE["b"] = Body.from_size("12")
    return _CACHE["b"]


def garment_points(body: Body, n: int = 400, seed: int = 0) -> torch.Tensor:
    """Points 0-4 cm off the body surface along (area-weighted) vertex normals."""
    import trimesh

    tm = trimesh.Trimesh(body.vertices.numpy(), body.faces.numpy(), process=False)
    g = np.random.default_rng(seed)
    idx = g.choice(len(tm.vertices), n, replace=False)
    x = tm.vertices[idx] + tm.vertex_normals[idx] * g.uniform(0.0, 0.04, (n, 1))
    return torch.as_tensor(x, dtype=torch.float64)


def two_planes(gap: float = 0.1, lift: float = 0.0, n: int = 3) -> Body:
    """Two parallel n x n squares (z = 0 and z = gap + lift), 2 n^2 triangles each."""
    g = np.linspace(-1.0, 1.0, n + 1)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    grid = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], 1)
    vid = lambda i, j: i * (n + 1) + j  # noqa: E731
    f = []
    for i in range(n):
        for j in range(n):
            f += [(vid(i, j), vid(i + 1, j), vid(i + 1, j + 1)),
                  (vid(i, j), vid(i + 1, j + 1), vid(i, j + 1))]
    f = np.array(f)
    top = grid + np.array([0.0, 0.0, gap + lift])
    v = np.concatenate([grid, top])
    faces = np.concatenate([f, f[:, ::-1] + len(grid)])
    return Body(torch.as_tensor(v, dtype=torch.float64), torch.as_tensor(faces, dtype=torch.long))


def test_closest_points_on_triangles_match_dense_sampling():
    from torchgarment.sdf import closest_points_on_triangles

    g = np.random.default_rng(1)
    a, b, c = (g.normal(size=(200, 3)) for _ in range(3))
    x = 2.0 * g.normal(size=(200, 3))
    cp = closest_points_on_triangles(x, a, b, c)
    u, v = np.meshgrid(np.linspace(0, 1, 201), np.linspace(0, 1, 201))
    keep = (u + v) <= 1.0
    u, v = u[keep], v[keep]
    samples = a[:, None] + u[None, :, None] * (b - a)[:, None] + v[None, :, None] * (c - a)[:, None]
    d_dense = np.linalg.norm(samples - x[:, None], axis=2).min(1)
    d = np.linalg.norm(cp - x, axis=1)
    assert np.all(d <= d_dense + 1e-12)
    assert np.all(d >= d_dense - 0.01)  # dense sampling at 1/200 of the triangle


def test_identity_when_target_is_base():
    b = body12()
    x = garment_points(b)
    y = transfer_deformation(x, b, b)
    assert y.dtype == x.dtype and y.shape == x.shape
    assert float((y - x).abs().max()) < 1e-12


@pytest.mark.parametrize("s", [1.05, 0.95])
def test_uniformly_scaled_body_scales_the_garment(s):
    b = body12()
    x = garment_points(b)
    c = torch.tensor([0.05, 0.9, -0.02], dtype=torch.float64)
    bs = replace(b, vertices=(b.vertices - c) * s + c)
    y = transfer_deformation(x, b, bs)  # default "scaled" offsets: exact
    assert float((y - ((x - c) * s + c)).abs().max()) < 1e-9
    # the paper's literal rule keeps the distance to the body: off by at most |s - 1| * (max offset)
    y = transfer_deformation(x, b, bs, offset="distance")
    err = float((y - ((x - c) * s + c)).norm(dim=1).max())
    assert 1e-5 < err <= abs(s - 1) * 0.04 + 1e-9


def test_rigidly_moved_body_moves_the_garment():
    b = body12()
    x = garment_points(b, 200)
    th = 0.3
    R = torch.tensor([[np.cos(th), 0.0, np.sin(th)], [0.0, 1.0, 0.0], [-np.sin(th), 0.0, np.cos(th)]],
                     dtype=torch.float64)
    t = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    y = transfer_deformation(x, b, replace(b, vertices=b.vertices @ R.T + t), offset="distance")
    assert float((y - (x @ R.T + t)).abs().max()) < 1e-9


def test_second_minimum_and_blend_between_two_planes():
    base = two_planes()
    target = two_planes(lift=0.04)  # the top plane moves up by 4 cm
    band = 0.01
    z = torch.tensor([0.02, 0.04, 0.045, 0.05 - 1e-9, 0.05 + 1e-9, 0.055, 0.06, 0.08], dtype=torch.float64)
    x = torch.stack([torch.full_like(z, 0.13), torch.full_like(z, -0.21), z], 1)
    t0, d0, t1, d1 = two_minimum_triangles(x.numpy(), base.vertices.numpy(), base.faces.numpy(), band)
    bottom = t0 < 18
    assert np.array_equal(bottom, (z < 0.05).numpy())
    assert np.allclose(d0, np.minimum(z.numpy(), 0.1 - z.numpy()))
    # the second minimum (the other plane) is found when it is within 2B
    near = np.abs(0.1 - 2 * z.numpy()) < 2 * band
    assert np.array_equal(t1 >= 0, near)
    assert np.all((t1[near] < 18) != bottom[near])
    assert np.allclose(d1[near], np.maximum(z.numpy(), 0.1 - z.numpy())[near])
    y = transfer_deformation(x, base, target, band=band)
    lift = (y - x)[:, 2].numpy()
    # w0 = 0.5 + min(d1 - d0, 2B) / 4B: the lift grows linearly from 0 to 4 cm across the band,
    # 2 cm at the tie
    w_top = np.clip(0.5 + (z.numpy() - 0.05) * 2 / (4 * band), 0.0, 1.0)
    assert np.allclose(lift, 0.04 * w_top, atol=1e-12)
    assert abs(lift[3] - lift[4]) < 1e-6  # continuous across the switch of the closest triangle
    assert float((y - x)[:, :2].abs().max()) < 1e-12


def test_bad_input():
    b = body12()
    x = garment_points(b, 10)
    with pytest.raises(InputError):
        transfer_deformation(x, b, two_planes())
    with pytest.raises(InputError):
        transfer_deformation(x, b, b, band=0.0)
    with pytest.raises(InputError):
        transfer_deformation(x[:, :2], b, b)
    with pytest.raises(InputError):
        transfer_deformation(x, b, b, offset="sideways")


def test_level_support_moves_the_band_to_its_height_and_fades_to_the_hips():
    """The support's mean height becomes ``height``; vertices follow with a weight linear in their base
    height, 1 at the band, 0 at the base hip plane and below; only y changes."""
    yb = torch.tensor([1.05, 1.05, 1.00, 0.95, 0.90, 0.80], dtype=torch.float64)
    x_base = torch.stack([torch.arange(6.0, dtype=torch.float64), yb, torch.zeros(6, dtype=torch.float64)], 1)
    x_t = x_base + torch.tensor([0.01, 0.02, 0.0], dtype=torch.float64)  # the transfer moved it up 2 cm
    out, delta = level_support(x_t, x_base, torch.tensor([0, 1]), 1.06, base_hips=0.90)
    assert delta == pytest.approx(1.06 - 1.07, abs=1e-12)
    assert float(out[:2, 1].mean()) == pytest.approx(1.06, abs=1e-12)
    w = torch.tensor([1.0, 1.0, 2 / 3, 1 / 3, 0.0, 0.0], dtype=torch.float64)
    assert torch.allclose(out[:, 1] - x_t[:, 1], delta * w, atol=1e-12)
    assert torch.equal(out[:, [0, 2]], x_t[:, [0, 2]])
    with pytest.raises(InputError, match="below the support"):
        level_support(x_t, x_base, torch.tensor([0, 1]), 1.06, base_hips=1.10)
    with pytest.raises(InputError, match="support must be"):
        level_support(x_t, x_base, torch.tensor([], dtype=torch.long), 1.06, base_hips=0.9)
    with pytest.raises(InputError, match="finite"):
        level_support(x_t, x_base, torch.tensor([0, 1]), float("nan"), base_hips=0.9)
