"""Boundary parametrization (Wang 2018 Eq. 7-8): exact base, linearity, affine reproduction, seams,
gradients."""

from __future__ import annotations

import math

import pytest
import torch

from torchgarment.adjust.parametrization import BoundaryParametrization, pattern_laplacian
from torchgarment.body.size_chart import chart_row
from torchgarment.errors import InputError, MeshError
from torchgarment.pattern.library import draft
from torchgarment.pattern.meshing import mesh_pattern
from torchgarment.structures.garment_mesh import GarmentMesh

_MESH: dict = {}


def skirt(h: float = 0.04) -> GarmentMesh:
    if h not in _MESH:
        _MESH[h] = mesh_pattern(draft("straight_skirt", chart_row("12")), h)
    return _MESH[h]


def panel_affine(P: BoundaryParametrization, mesh: GarmentMesh, seed: int = 0):
    """q and the expected p when every panel moves by its own random affine map."""
    g = torch.Generator().manual_seed(seed)
    pid = mesh.vertex_panel_ids
    p_expected = mesh.p.clone()
    for k in range(len(mesh.panel_names)):
        A = torch.eye(2, dtype=torch.float64) + 0.2 * torch.randn(2, 2, generator=g, dtype=torch.float64)
        b = 0.1 * torch.randn(2, generator=g, dtype=torch.float64)
        sel = pid == k
        p_expected[sel] = mesh.p[sel] @ A.T + b
    return p_expected[P.boundary_index], p_expected


@pytest.mark.parametrize("solve", ["factorized", "explicit"])
@pytest.mark.parametrize("weights", ["cotangent", "mean_value", "uniform"])
def test_initial_reproduces_base_pattern(weights, solve):
    mesh = skirt()
    P = BoundaryParametrization(mesh, weights=weights, solve=solve)
    q = P.initial()
    assert q.shape == (P.num_boundary, 2)
    assert float((P(q) - mesh.p).abs().max()) <= 1e-12
    assert P.boundary_index.numel() + P.interior_index.numel() == mesh.num_vertices


@pytest.mark.parametrize("solve", ["factorized", "explicit"])
def test_map_is_affine_in_q(solve):
    mesh = skirt()
    P = BoundaryParametrization(mesh, solve=solve)
    q0 = P.initial()
    g = torch.Generator().manual_seed(1)
    d1 = 0.01 * torch.randn(q0.shape, generator=g, dtype=torch.float64)
    d2 = 0.01 * torch.randn(q0.shape, generator=g, dtype=torch.float64)
    lin = lambda d: P(q0 + d) - mesh.p  # noqa: E731
    assert torch.allclose(lin(2.0 * d1 - 3.0 * d2), 2.0 * lin(d1) - 3.0 * lin(d2), atol=1e-13, rtol=0)
    assert torch.equal(P(q0 + d1)[P.boundary_index], q0 + d1)  # boundary vertices are the parameters


@pytest.mark.parametrize("weights", ["cotangent", "mean_value"])
def test_interior_follows_boundary_affine_map(weights):
    # cotangent and mean value weights reproduce affine functions on a flat mesh, so Eq. 8 maps an affine
    # motion of a panel's boundary to the same affine motion of its interior
    mesh = skirt()
    P = BoundaryParametrization(mesh, weights=weights)
    q, p_expected = panel_affine(P, mesh)
    assert float((P(q) - p_expected).abs().max()) <= 1e-11


def test_uniform_weights_do_not_reproduce_affine_maps():
    mesh = skirt()
    P = BoundaryParametrization(mesh, weights="uniform")
    q, p_expected = panel_affine(P, mesh)
    assert float((P(q) - p_expected).abs().max()) > 1e-5  # only translations are reproduced
    t = torch.tensor([0.3, -0.2], dtype=torch.float64)
    assert float((P(P.initial() + t) - (mesh.p + t)).abs().max()) <= 1e-12


def test_laplacian_rows_sum_to_zero_and_cotangent_is_symmetric():
    mesh = skirt()
    p, f = mesh.p.numpy(), mesh.faces.numpy()
    for kind in ("cotangent", "mean_value", "uniform"):
        L = pattern_laplacian(p, f, kind)
        assert abs(L.sum(axis=1)).max() < 1e-9
    L = pattern_laplacian(p, f, "cotangent")
    assert abs(L - L.T).max() < 1e-12
    # linear functions are harmonic at interior vertices (flat mesh)
    P = BoundaryParametrization(mesh)
    inner = P.interior_index.numpy()
    assert abs(L @ p)[inner].max() < 1e-12


def test_explicit_and_factorized_agree_in_value_and_gradient():
    mesh = skirt()
    Pe = BoundaryParametrization(mesh, solve="explicit")
    Pf = BoundaryParametrization(mesh, solve="factorized")
    g = torch.Generator().manual_seed(2)
    q = Pe.initial() + 0.01 * torch.randn(Pe.initial().shape, generator=g, dtype=torch.float64)
    w = torch.randn(mesh.num_vertices, 2, generator=g, dtype=torch.float64)
    grads = []
    for P in (Pe, Pf):
        qq = q.clone().requires_grad_(True)
        (P(qq) * w).sum().backward()
        grads.append(qq.grad)
    assert torch.allclose(Pe(q), Pf(q), atol=1e-13, rtol=0)
    assert torch.allclose(grads[0], grads[1], atol=1e-11, rtol=0)


def test_gradcheck():
    # (the explicit mode agrees with this one in value and gradient, see above)
    mesh = skirt(0.08)
    P = BoundaryParametrization(mesh, solve="factorized")
    q = P.initial().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(P, (q,), eps=1e-6, atol=1e-8)


def test_seams_and_corners():
    mesh = skirt()
    P = BoundaryParametrization(mesh)
    b = set(P.boundary_index.tolist())
    assert all(int(v) in b for v in mesh.seam_pairs.reshape(-1))  # both sides of every seam are parameters
    # straight skirt: two side seams; every stitched vertex chain of n vertices gives n - 1 edge pairs
    assert P.seam_edge_pairs.shape[0] == mesh.seam_pairs.shape[0] - 2
    q = P.initial()
    sp = P.seam_edge_pairs
    la = (q[sp[:, 1]] - q[sp[:, 0]]).norm(dim=1)
    lb = (q[sp[:, 3]] - q[sp[:, 2]]).norm(dim=1)
    assert torch.allclose(la, lb, rtol=0.02)  # plain seams: matching lengths in the drafted pattern
    # the edge pairs join paired vertices
    pairs = {tuple(sorted(t)) for t in mesh.seam_pairs.tolist()}
    bi = P.boundary_index
    for a0, a1, b0, b1 in sp.tolist():
        assert tuple(sorted((int(bi[a0]), int(bi[b0])))) in pairs
        assert tuple(sorted((int(bi[a1]), int(bi[b1])))) in pairs
    # outline neighbours and corners: 4 corners per rectangular-ish skirt panel
    assert torch.equal(P.boundary_next[P.boundary_prev], torch.arange(P.num_boundary))
    assert int(P.corner_mask.sum()) == 4 * len(mesh.panel_names)
    forced = torch.zeros(mesh.num_vertices, dtype=torch.bool)
    forced[P.boundary_index[:3]] = True
    assert P.corner_mask.sum() != 3
    assert int(BoundaryParametrization(mesh, corners=forced).corner_mask.sum()) == 3


def test_bad_input():
    mesh = skirt()
    P = BoundaryParametrization(mesh)
    with pytest.raises(MeshError):
        P(torch.zeros(3, 2, dtype=torch.float64))
    with pytest.raises(MeshError):
        BoundaryParametrization(GarmentMesh(mesh.x, mesh.faces))
    with pytest.raises(InputError):
        BoundaryParametrization(mesh, weights="harmonic-ish")
    with pytest.raises(InputError):
        BoundaryParametrization(mesh, solve="magic")


def test_dtype_and_device_follow_arguments():
    mesh = skirt()
    P = BoundaryParametrization(mesh, dtype=torch.float32)
    q = P.initial()
    assert q.dtype == torch.float32 and P(q).dtype == torch.float32
    assert float((P(q).double() - mesh.p).abs().max()) < 1e-6
    assert math.isfinite(float(P(q).sum()))


def test_linear_part_and_double_backward():
    mesh = skirt(0.08)
    P = BoundaryParametrization(mesh, solve="factorized")
    g = torch.Generator().manual_seed(4)
    dq = 0.01 * torch.randn(P.num_boundary, 2, generator=g, dtype=torch.float64)
    assert torch.allclose(P.linear(dq), P(P.initial() + dq) - mesh.p, atol=1e-14)
    # the backward is the transposed map, itself differentiable: second derivatives of a quadratic in p
    q = P.initial().clone().requires_grad_(True)
    assert torch.autograd.gradgradcheck(lambda v: P(v).pow(2).sum(), (q,), eps=1e-6, atol=1e-6)
