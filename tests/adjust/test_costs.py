"""Cost functions of pattern adjustment (Wang 2018 Eq. 11-16): zero at the base state, values, gradients."""

from __future__ import annotations

import math

import pytest
import torch

from torchgarment.adjust.costs import (
    DistanceCost,
    LinePlacementCost,
    PositionalCost,
    SmoothnessCost,
    StretchingCost,
    hinge_kernel,
)
from torchgarment.body.size_chart import chart_row
from torchgarment.errors import InputError
from torchgarment.pattern.library import draft
from torchgarment.pattern.meshing import mesh_pattern
from torchgarment.structures.garment_mesh import GarmentMesh
from torchgarment.testing import check_gradient

_CACHE: dict = {}


def base_mesh() -> GarmentMesh:
    """A skirt whose 3D positions are the placed panels, wrapped onto a cylinder (bent, so hinges are
    non-flat)."""
    if "mesh" not in _CACHE:
        m = mesh_pattern(draft("straight_skirt", chart_row("12")), 0.05)
        x = m.x.clone()
        r = 0.2
        ang = torch.atan2(x[:, 2], x[:, 0])
        x = torch.stack([r * torch.cos(ang), x[:, 1], r * torch.sin(ang)], 1) + 0.3 * (x - x.mean(0)) * 0.1
        _CACHE["mesh"] = m.with_positions(x)
    return _CACHE["mesh"]


def perturbed(mesh: GarmentMesh, seed: int = 0, sx: float = 0.003, sp: float = 0.002):
    g = torch.Generator().manual_seed(seed)
    x = mesh.x + sx * torch.randn(mesh.x.shape, generator=g, dtype=torch.float64)
    p = mesh.p + sp * torch.randn(mesh.p.shape, generator=g, dtype=torch.float64)
    return x, p


class SphereSDF(torch.nn.Module):
    def __init__(self, radius: float, center=(0.0, 1.0, 0.0)) -> None:
        super().__init__()
        self.radius = radius
        self.register_buffer("center", torch.tensor(center, dtype=torch.float64))

    def forward(self, x):
        return (x - self.center).norm(dim=-1) - self.radius


def grad_checks(cost, x, p, rtol=1e-6, uses_p=False):
    check_gradient(lambda v: cost(v, p), x, rtol=rtol, num_samples=30)
    if uses_p:
        check_gradient(lambda v: cost(x, v), p, rtol=rtol, num_samples=30)
    else:  # d/dp = 0: the value does not change with p
        assert float(cost(x, p)) == float(cost(x, 1.3 * p))


def test_distance_cost():
    m = base_mesh()
    base, target = SphereSDF(0.15), SphereSDF(0.17)
    same = DistanceCost.from_garment(m.x, base, base, weight=2.0)
    x, p = perturbed(m)
    assert float(same(m.x, m.p)) == 0.0
    c = DistanceCost.from_garment(m.x, base, target, weight=2.0)
    # moving every vertex 2 cm radially outward keeps the looseness on the larger sphere
    d = m.x - base.center
    x_out = base.center + d * (1 + 0.02 / d.norm(dim=1, keepdim=True))
    assert float(c(x_out, m.p)) < 1e-24
    assert float(c(m.x, m.p)) == pytest.approx(0.5 * 2.0 * m.num_vertices * 0.02**2, rel=1e-9)
    grad_checks(c, x, p)
    with pytest.raises(InputError):
        c(x[:-1], p)
    # a fit scale s: the looseness kept in proportion; the garment scaled by s about the centre of a sphere
    # scaled by s keeps it
    s = 1.05
    big = SphereSDF(0.15 * s)
    scaled = DistanceCost.from_garment(m.x, base, big, weight=2.0, scale=s)
    x_s = base.center + s * (m.x - base.center)
    assert float(scaled(x_s, m.p)) < 1e-24 < float(DistanceCost.from_garment(m.x, base, big)(x_s, m.p))
    assert torch.equal(DistanceCost.from_garment(m.x, base, big, scale=1.0).base_distance,
                       DistanceCost.from_garment(m.x, base, big).base_distance)
    with pytest.raises(InputError, match="scale"):
        DistanceCost.from_garment(m.x, base, big, scale=-1.0)


def test_hinge_kernel_vanishes_on_flat_embeddings():
    m = base_mesh()
    K = hinge_kernel(m.p, m.hinges)
    th = 0.4
    R = torch.tensor([[math.cos(th), 0.0], [0.0, 1.0], [math.sin(th), 0.0]], dtype=torch.float64)  # isometry
    x = m.p @ R.T + torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    lx = (K[:, :, None] * x[m.hinges]).sum(1)
    assert float(lx.abs().max()) < 1e-13


def test_hinge_kernel_equals_the_bending_energy_weights():
    """The cost's Bergou kernel is the bending energy's four-vertex kernel (one formula per angle here, see
    hinge_kernel's docstring), to round-off."""
    from torchgarment.sim.energies.bend import hinge_weights

    m = base_mesh()
    K = hinge_kernel(m.p, m.hinges)
    rest = torch.cat([m.p, torch.zeros_like(m.p[:, :1])], dim=1)
    w, _, _ = hinge_weights(rest, m.hinges[:, [0, 1, 2, 0, 1, 3]])
    ref = torch.stack([w[:, 0] + w[:, 3], w[:, 1] + w[:, 4], w[:, 2], w[:, 5]], dim=1)
    assert float((K - ref).abs().max()) <= 1e-12 * float(ref.abs().max())


def test_smoothness_cost():
    m = base_mesh()
    c = SmoothnessCost(m, weight=0.05)
    assert float(c(m.x, m.p)) < 1e-30
    x, p = perturbed(m)
    assert float(c(x, p)) > 0
    # p does not enter (the kernel is a constant of the base pattern)
    assert float(c(x, p)) == float(c(x, m.p))
    check_gradient(lambda v: c(v, p), x, rtol=1e-6, num_samples=30)
    # mirroring keeps |L_e x| but turns convex into concave w.r.t. the (index-oriented) normals: s_e = -1, so
    # every residual is |L_e x| + |L_e x̄| = 2 |L_e x̄| instead of 0
    mirror = m.x * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)
    lx = c.edge_vectors(m.x).norm(dim=1)
    assert float(lx.min()) > 1e-6  # the test mesh is bent everywhere
    assert torch.allclose(c.residuals(mirror), 2.0 * lx, atol=1e-12)
    # a rigid motion keeps everything
    th = 0.3
    R = torch.tensor([[math.cos(th), -math.sin(th), 0.0], [math.sin(th), math.cos(th), 0.0], [0.0, 0.0, 1.0]],
                     dtype=torch.float64)
    assert float(c(m.x @ R.T + 1.0, m.p)) < 1e-24
    # flattening every hinge: residual = +-|Lx̄| (L_e x = 0, so the convexity sign is arbitrary)
    flat = torch.cat([m.p, torch.zeros(m.num_vertices, 1, dtype=torch.float64)], 1)
    assert torch.allclose(c.residuals(flat).abs(), lx, atol=1e-10)


def test_stretching_cost():
    m = base_mesh()
    c = StretchingCost(m, weight=1.0)
    assert float(c(m.x, m.p)) < 1e-28
    # scaling garment and pattern together keeps every ratio
    assert float(c(1.1 * m.x, 1.1 * m.p)) < 1e-26
    # scaling only the garment by s multiplies the ratios by s
    s = 1.05
    expected = 0.5 * float(((s - 1) * c.base_ratio).pow(2).sum())
    assert float(c(s * m.x, m.p)) == pytest.approx(expected, rel=1e-9)
    x, p = perturbed(m)
    grad_checks(c, x, p, uses_p=True)


def test_positional_cost():
    m = base_mesh()
    target = m.x + 0.01
    c = PositionalCost.for_mesh(m, target, weight=100.0, boundary_weight=4.0)
    assert float(c(target, m.p)) == 0.0
    nb = torch.unique(m.boundary_edges).numel()
    # every vertex 1 cm off in x, y and z: 3e-4 m^2 each
    expected = 0.5 * 100.0 * 3e-4 * (m.num_vertices - nb + 4.0 * nb)
    assert float(c(m.x, m.p)) == pytest.approx(expected, rel=1e-9)
    x, p = perturbed(m)
    grad_checks(c, x, p)
    with pytest.raises(InputError):
        PositionalCost(target, torch.full((m.num_vertices,), -1.0, dtype=torch.float64))


def test_line_placement_cost():
    m = base_mesh()
    V = m.num_vertices
    verts = torch.tensor([0, 1, 2, 3, 4, 5])
    line_of = torch.tensor([0, 0, 1, 1, 1, 1])
    h = torch.stack([m.x[:2, 1].mean(), m.x[2:6, 1].mean()])
    c = LinePlacementCost(verts, line_of, h, V, weight=1e4)
    assert torch.allclose(c.heights(m.x), h, atol=1e-15) and float(c(m.x, m.p)) == 0.0
    # lifting the garment by 1 cm lifts every line by 1 cm
    up = m.x + torch.tensor([0.0, 0.01, 0.0], dtype=m.x.dtype)
    assert float(c(up, m.p)) == pytest.approx(0.5 * 1e4 * 2 * 1e-4, rel=1e-9)
    x, p = perturbed(m)
    grad_checks(c, x, p)
    # per-line weights multiply each line's squared residual
    cw = LinePlacementCost(verts, line_of, h, V, weight=1e4,
                           line_weight=torch.tensor([1.0, 3.0], dtype=h.dtype))
    assert float(cw(up, m.p)) == pytest.approx(0.5 * 1e4 * (1 + 3) * 1e-4, rel=1e-9)
    grad_checks(cw, x, p)
    for bad in (torch.tensor([1.0]), torch.tensor([1.0, -1.0]), torch.tensor([1.0, float("nan")])):
        with pytest.raises(InputError, match="line_weight"):
            LinePlacementCost(verts, line_of, h, V, line_weight=bad.to(h.dtype))
    with pytest.raises(InputError, match="needs vertices"):
        LinePlacementCost(verts, torch.zeros(6, dtype=torch.long), h, V)
    with pytest.raises(InputError, match="vertex indices"):
        LinePlacementCost(torch.tensor([0, V]), torch.tensor([0, 1]), h, V)
    with pytest.raises(InputError, match=r"\(M,\)"):
        LinePlacementCost(verts, line_of[:3], h, V)
    with pytest.raises(InputError):
        c(m.x[:-1], m.p[:-1])


def test_residuals_give_the_value():
    m = base_mesh()
    x, p = perturbed(m)
    for c in (StretchingCost(m, 3.0), SmoothnessCost(m, 0.5), PositionalCost.for_mesh(m, m.x, 7.0),
              DistanceCost.from_garment(m.x, SphereSDF(0.1), SphereSDF(0.12), 2.0),
              LinePlacementCost(torch.arange(4), torch.tensor([0, 0, 1, 1]),
                                torch.tensor([0.9, 1.0], dtype=torch.float64), m.num_vertices, 5.0)):
        assert float(c(x, p)) == pytest.approx(0.5 * c.weight * float(c.residuals(x, p).pow(2).sum()),
                                               rel=1e-12)
