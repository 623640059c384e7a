"""Regularizers on the boundary parameters (Wang 2018 Eq. 9-10, seam lengths): values, invariances, gradients,
approximate Hessians."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchgarment.adjust.parametrization import BoundaryParametrization
from torchgarment.adjust.regularizers import (
    BoundaryCurvatureRegularizer,
    FixingRegularizer,
    LineEaseRegularizer,
    SeamLengthRegularizer,
    SupportShapeRegularizer,
)
from torchgarment.body.size_chart import chart_row
from torchgarment.errors import InputError
from torchgarment.pattern.library import draft
from torchgarment.pattern.meshing import mesh_pattern
from torchgarment.testing import check_gradient

_CACHE: dict = {}


def setup():
    if "P" not in _CACHE:
        mesh = mesh_pattern(draft("straight_skirt", chart_row("12")), 0.06)
        _CACHE["mesh"] = mesh
        _CACHE["P"] = BoundaryParametrization(mesh)
    return _CACHE["mesh"], _CACHE["P"]


def noisy(q: torch.Tensor, scale: float = 0.005, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return q + scale * torch.randn(q.shape, generator=g, dtype=q.dtype)


def per_panel_similarity(mesh, P, seed: int = 3) -> torch.Tensor:
    """q after a random rotation + uniform scale + translation of every panel."""
    g = torch.Generator().manual_seed(seed)
    q = P.initial().clone()
    pid = mesh.vertex_panel_ids[P.boundary_index]
    for k in range(len(mesh.panel_names)):
        th = float(torch.rand(1, generator=g)) * 6.0
        s = 0.8 + 0.4 * float(torch.rand(1, generator=g))
        R = torch.tensor([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]], dtype=torch.float64)
        sel = pid == k
        q[sel] = s * q[sel] @ R.T + torch.randn(2, generator=g, dtype=torch.float64)
    return q


def dense_hessian(fn, q: torch.Tensor) -> torch.Tensor:
    n = q.numel()
    H = torch.autograd.functional.hessian(lambda v: fn(v.view_as(q)), q.reshape(-1).clone())
    return H.reshape(n, n)


def assert_gauss_newton_hessian(R, q0: torch.Tensor, symmetry: float, atol: float) -> None:
    """``R.hessian()`` is symmetric (within ``symmetry``), positive semidefinite, and at the base pattern
    (zero residuals) equal to the exact Hessian of ``R`` (within ``atol``)."""
    H = R.hessian()
    assert abs(H - H.T).max() < symmetry
    assert np.linalg.eigvalsh(H.toarray()).min() > -1e-6
    assert np.allclose(H.toarray(), dense_hessian(R, q0).numpy(), rtol=1e-8, atol=atol)


def test_fixing_value_gradient_hessian():
    _, P = setup()
    q0 = P.initial()
    R = FixingRegularizer(q0, weight=100.0)
    q = noisy(q0)
    assert float(R(q0)) == 0.0
    assert float(R(q)) == pytest.approx(50.0 * float((q - q0).pow(2).sum()), rel=1e-12)
    check_gradient(R, q, rtol=1e-7)
    H = R.hessian().toarray()
    assert np.allclose(H, dense_hessian(R, q).numpy(), atol=1e-9)
    with pytest.raises(InputError):
        R(q[:-1])


def test_curvature_zero_at_base_and_under_similarities():
    mesh, P = setup()
    R = BoundaryCurvatureRegularizer(P, weight=1e6)
    assert float(R(P.initial())) < 1e-20
    q = per_panel_similarity(mesh, P)
    assert float(R(q)) < 1e-14  # invariant to rotation + uniform scale + translation of each outline
    # a non-uniform scale is penalized
    q2 = P.initial() * torch.tensor([1.1, 0.9], dtype=torch.float64)
    assert float(R(q2)) > 1e-3


def test_curvature_similarity_recovers_rotation_and_scale():
    mesh, P = setup()
    R = BoundaryCurvatureRegularizer(P, weight=1.0)
    th, s = 0.7, 1.3
    Rm = torch.tensor([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]], dtype=torch.float64)
    T = R.similarities(s * P.initial() @ Rm.T)
    assert torch.allclose(T, torch.tensor([s * np.cos(th), s * np.sin(th)], dtype=torch.float64).expand_as(T),
                          atol=1e-12)


def test_curvature_gradient_and_corner_weight():
    mesh, P = setup()
    R = BoundaryCurvatureRegularizer(P, weight=1e6, corner_weight=0.1)
    check_gradient(R, noisy(P.initial()), rtol=1e-6)
    # the same bump costs 10x less at a corner than at a regular outline vertex
    c = int(torch.nonzero(P.corner_mask)[0])
    r = int(torch.nonzero(~P.corner_mask & ~P.corner_mask[P.boundary_prev] & ~P.corner_mask[P.boundary_next]
                          & ~P.corner_mask[P.boundary_prev[P.boundary_prev]]
                          & ~P.corner_mask[P.boundary_next[P.boundary_next]])[0])
    R1 = BoundaryCurvatureRegularizer(P, weight=1e6, corner_weight=1.0)
    R0 = BoundaryCurvatureRegularizer(P, weight=1e6, corner_weight=0.0)
    bump = torch.zeros(P.num_boundary, 2, dtype=torch.float64)
    bump[c] = 1e-3
    # at the corner, only the corner's own residual weight changes
    v1, v0 = float(R1(P.initial() + bump)), float(R0(P.initial() + bump))
    assert float(R(P.initial() + bump)) == pytest.approx(v0 + 0.1 * (v1 - v0), rel=1e-9)
    assert v1 > v0 > 0
    bump2 = torch.zeros_like(bump)
    bump2[r] = 1e-3
    assert float(R(P.initial() + bump2)) == pytest.approx(float(R1(P.initial() + bump2)), rel=1e-12)


def test_curvature_hessian_is_exact_with_T_held_constant():
    mesh, P = setup()
    R = BoundaryCurvatureRegularizer(P, weight=1e6, corner_weight=0.1)
    q0 = P.initial()
    w = R.vertex_weight

    def fixed_T(q):  # Eq. 10 with T_i = identity
        lap = q[R.prev] + q[R.next] - 2 * q
        lap0 = q0[R.prev] + q0[R.next] - 2 * q0
        return 0.5 * R.weight * (w * (lap - lap0).pow(2).sum(-1)).sum()

    H = R.hessian()
    assert np.allclose(H.toarray(), dense_hessian(fixed_T, q0).numpy(), rtol=1e-10, atol=1e-4)
    assert abs(H - H.T).max() < 1e-6


def test_seam_regularizer():
    mesh, P = setup()
    R = SeamLengthRegularizer(P, weight=1e6)
    q0 = P.initial()
    assert float(R(q0)) < 1e-20
    assert float(R(1.07 * q0)) < 1e-20  # scaling all panels keeps the ratios
    assert float(R(per_panel_similarity(mesh, P))) > 1.0  # different scales per panel break the seams
    check_gradient(R, noisy(q0), rtol=1e-6)
    assert_gauss_newton_hessian(R, q0, symmetry=1e-6, atol=1e-3)


def test_residuals_give_the_value():
    mesh, P = setup()
    q = noisy(P.initial())
    for R in (FixingRegularizer(P.initial(), 3.0), BoundaryCurvatureRegularizer(P, 5.0, 0.2),
              SeamLengthRegularizer(P, 7.0), line_ease((0.01, 0.03), 11.0)[0]):
        assert float(R(q)) == pytest.approx(0.5 * R.weight * float(R.residuals(q).pow(2).sum()), rel=1e-12)


def line_ease(targets_change: tuple[float, ...] | None = None, weight: float = 1e4):
    """The ease regularizer of the 12 straight skirt's construction lines, targets = base girths + change."""
    from torchgarment.adjust.acceptance import line_vertices, pattern_line_widths
    from torchgarment.adjust.fit import construction_lines

    mesh, P = setup()
    pattern = draft("straight_skirt", chart_row("12"))
    lines = construction_lines(pattern)
    pos = torch.full((mesh.num_vertices,), -1, dtype=torch.long)
    pos[P.boundary_index] = torch.arange(P.num_boundary)
    corners, line_of = [], []
    for k, (a, b) in enumerate(lines.values()):
        c = pos[torch.as_tensor(line_vertices(pattern, mesh, a, b)).reshape(-1, 2)]
        corners.append(c)
        line_of.append(torch.full((c.shape[0],), k, dtype=torch.long))
    base = torch.tensor(list(pattern_line_widths(pattern, lines).values()), dtype=torch.float64)
    change = torch.zeros_like(base) if targets_change is None else torch.tensor(targets_change,
                                                                                 dtype=torch.float64)
    reg = LineEaseRegularizer(torch.cat(corners), torch.cat(line_of), base + change, P.initial(), weight)
    return reg, base


def test_line_ease_girths_value_gradient_hessian():
    _, P = setup()
    q0 = P.initial()
    R, base = line_ease()
    # the pattern's girth at each line is the fit measure's (pattern_line_widths), zero at the base targets
    assert torch.allclose(R.girths(q0), base, atol=1e-12)
    assert float(R(q0)) < 1e-24
    # a uniform scale s of every panel scales the girths by s
    assert torch.allclose(R.girths(1.05 * q0), 1.05 * base, atol=1e-12)
    R2, _ = line_ease((0.04, -0.02))
    assert float(R2(q0)) == pytest.approx(0.5 * 1e4 * (0.04 ** 2 + 0.02 ** 2), rel=1e-10)
    check_gradient(R2, noisy(q0), rtol=1e-6)
    assert_gauss_newton_hessian(R, q0, symmetry=1e-9, atol=1e-6)
    with pytest.raises(InputError):
        R(q0[:-1])


def test_line_ease_rejects_bad_corners():
    _, P = setup()
    q0 = P.initial()
    t = torch.zeros(2, dtype=torch.float64)
    with pytest.raises(InputError, match="needs corners"):
        LineEaseRegularizer(torch.tensor([[0, 1]]), torch.tensor([0]), t, q0)
    with pytest.raises(InputError, match="corner positions"):
        LineEaseRegularizer(torch.tensor([[0, q0.shape[0]]]), torch.tensor([0]), t[:1], q0)
    with pytest.raises(InputError, match=r"\(K, 2\)"):
        LineEaseRegularizer(torch.tensor([0, 1]), torch.tensor([0]), t[:1], q0)


def support_shape(weight: float = 1e3):
    """The support-shape regularizer of the 12 straight skirt's waistband (its support)."""
    from torchgarment.pattern.support import support_vertices

    mesh, P = setup()
    pattern = draft("straight_skirt", chart_row("12"))
    idx, _, _ = support_vertices(pattern, mesh)
    pos = torch.full((mesh.num_vertices,), -1, dtype=torch.long)
    pos[P.boundary_index] = torch.arange(P.num_boundary)
    return SupportShapeRegularizer(pos[idx], mesh.vertex_panel_ids[idx], P.initial(), weight), pos[idx]


def test_support_shape_holds_position_and_depth_but_not_length():
    """Zero at the base and when each panel's waist is stretched along its chord about the chord's midpoint
    (a waist graded by its length); a rise of the side-waist corners, a rigid move of the panel or a deeper
    waist curve cost; gradient and Gauss-Newton Hessian are right."""
    mesh, P = setup()
    R, rows = support_shape()
    q0 = P.initial()
    assert R.rows.numel() == rows.numel() and float(R(q0)) < 1e-28
    q = q0.clone()
    for k in torch.unique(R.ends[:, 0]).tolist():  # stretch every panel's support along its chord by 6 %
        sel = R.ends[:, 0] == k
        c0, c1 = q0[R.ends[sel][0, 0]], q0[R.ends[sel][0, 1]]
        u = (c1 - c0) / (c1 - c0).norm()
        rel = q0[R.rows[sel]] - 0.5 * (c0 + c1)
        q[R.rows[sel]] = q0[R.rows[sel]] + 0.06 * (rel @ u)[:, None] * u
    assert float(R(q)) < 1e-20
    corners = R.ends.unique()
    up = q0.clone()
    up[corners, 1] += 0.004  # the side-waist corners 4 mm higher
    assert float(R(up)) > 0.5 * R.weight * 0.004 ** 2
    moved = q0 + torch.tensor([0.0, 0.01], dtype=torch.float64)  # a rigid move of every panel
    assert float(R(moved)) == pytest.approx(0.5 * R.weight * rows.numel() * 0.01 ** 2, rel=1e-9)
    check_gradient(R, noisy(q0), rtol=1e-6)
    assert_gauss_newton_hessian(R, q0, symmetry=1e-9, atol=1e-6)


def test_support_shape_rejects_bad_vertices():
    _, P = setup()
    q0 = P.initial()
    with pytest.raises(InputError, match="at least two"):
        SupportShapeRegularizer(torch.tensor([0, 1, 2]), torch.tensor([0, 0, 1]), q0)
    with pytest.raises(InputError, match="positions"):
        SupportShapeRegularizer(torch.tensor([0, q0.shape[0]]), torch.tensor([0, 0]), q0)
    with pytest.raises(InputError, match=r"\(P,\)"):
        SupportShapeRegularizer(torch.tensor([[0, 1]]), torch.tensor([0, 0]), q0)
    same = torch.cat([q0[:1], q0[:1], q0[2:]])
    with pytest.raises(InputError, match="one point"):
        SupportShapeRegularizer(torch.tensor([0, 1]), torch.tensor([0, 0]), same)
