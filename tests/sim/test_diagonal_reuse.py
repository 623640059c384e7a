"""The GD-Chebyshev preconditioner's reuse machinery: cached constant Hessian diagonals, the reused elastic
diagonal with fresh volatile (barrier) rows, sparse barrier accumulation, partial re-inversion and the
adjugate 3x3 inverse. Each is checked against the plain computation it replaces."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from torchgarment.sim.scene import Material
from torchgarment.sim.solvers import Preconditioner, SolveSettings, solve
from torchgarment.sim.solvers.chebyshev import (
    JacobiState,
    apply_inverse,
    jacobi_inverse,
    seam_pairs,
    spd_inverse_3x3,
)

sys.path.insert(0, str(Path(__file__).parent))
from test_hard_cases import tube_scene  # noqa: E402


def _settled_tube(iterations: int = 60):
    """A tube sewn around a thin cylinder, after some GD iterations (some vertices within the barrier's
    range)."""
    scene, sdf = tube_scene(0.03, 0.02, torch.float64, material=Material())
    model = scene.build()
    x, _ = solve(model, scene.garment.x, SolveSettings(rtol=0.0, atol=0.0, max_iterations=iterations))
    return model, x


def _sum_of_terms(model, x):
    E = sum(float(t.value_and_grad(x)[0]) for t in model.terms)
    g = sum(t.value_and_grad(x)[1] for t in model.terms)
    h = sum(t.hessian_diagonal(x) for t in model.terms)
    return E, g, h


def test_model_diagonal_equals_the_sum_of_the_terms():
    model, x = _settled_tube()
    E0, g0, h0 = _sum_of_terms(model, x)
    E, g, h = model.value_grad_hessian_diagonal(x)
    assert abs(float(E) - E0) <= 1e-12 * max(1.0, abs(E0))
    torch.testing.assert_close(g, g0, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(h, h0, rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(model.hessian_diagonal(x), h0, rtol=1e-12, atol=1e-9)
    barrier = model.term("body_barrier")
    rows = model.last_volatile_rows
    # the barrier acts on a few vertices only
    assert rows is not None and 0 < rows.numel() < model.num_vertices
    phi = barrier.sdf(x)
    assert set(rows.tolist()) == set(torch.nonzero(phi < barrier.dhat).flatten().tolist())


def test_constant_diagonal_cache_follows_stiffness_changes():
    model, x = _settled_tube(5)
    c1 = model.constant_hessian_diagonal(x.dtype, x.device).clone()
    assert model.constant_hessian_diagonal(x.dtype, x.device) is model.constant_hessian_diagonal(x.dtype,
                                                                                                 x.device)
    sew = model.term("sew")
    sew.stiffness *= 2.0
    c2 = model.constant_hessian_diagonal(x.dtype, x.device)
    expected = sum(t.hessian_diagonal(x) for t in model.terms if t.constant_hessian)
    torch.testing.assert_close(c2, expected)
    assert not torch.allclose(c1, c2)


def test_reuse_elastic_keeps_the_elastic_part_and_refreshes_the_barrier():
    model, x = _settled_tube()
    x2, _ = solve(model, x, SolveSettings(rtol=0.0, atol=0.0, max_iterations=10))
    _, _, h_full = model.value_grad_hessian_diagonal(x)  # the last full evaluation: at x
    # at x2 the barrier part must follow, the elastic part stays that of x
    E, g, h = model.value_grad_hessian_diagonal(x2, reuse_elastic=True)
    E_ref, g_ref, _ = _sum_of_terms(model, x2)
    assert abs(float(E) - E_ref) <= 1e-12 * max(1.0, abs(E_ref))
    torch.testing.assert_close(g, g_ref, rtol=1e-12, atol=1e-12)
    elastic_at_x = sum(t.hessian_diagonal(x) for t in model.terms if not t.volatile_hessian)
    volatile_at_x2 = sum(t.hessian_diagonal(x2) for t in model.terms if t.volatile_hessian)
    torch.testing.assert_close(h, elastic_at_x + volatile_at_x2, rtol=1e-12, atol=1e-9)
    assert not torch.allclose(h, h_full)


def test_barrier_accumulation_matches_autograd_and_the_dense_diagonal():
    """The sparse accumulation (rows within dhat only) against independent computations: the energy and
    gradient of the autograd ``forward`` (full SDF query) and the dense ``hessian_diagonal`` blocks."""
    model, x = _settled_tube()
    barrier = model.term("body_barrier")
    g = torch.zeros_like(x)
    h = torch.zeros(x.shape[0], 3, 3, dtype=x.dtype)
    E = barrier.accumulate_value_grad_hessian_diagonal(x, g, h)
    xr = x.clone().requires_grad_(True)
    E_ad = barrier(xr)
    (g_ad,) = torch.autograd.grad(E_ad, xr)
    e_ad = float(E_ad.detach())
    assert abs(float(E) - e_ad) <= 1e-10 * max(1.0, abs(e_ad))
    torch.testing.assert_close(g, g_ad, rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(h, barrier.hessian_diagonal(x), rtol=1e-12, atol=0.0)
    rows = barrier.last_hessian_rows
    assert 0 < rows.numel() < x.shape[0]
    off = torch.ones(x.shape[0], dtype=torch.bool)
    off[rows] = False
    assert float(g[off].abs().max()) == 0.0 and float(h[off].abs().max()) == 0.0


def test_partial_update_equals_a_rebuild_with_the_same_scale():
    model, x = _settled_tube()
    settings = SolveSettings()
    x2, _ = solve(model, x, SolveSettings(rtol=0.0, atol=0.0, max_iterations=10))
    _, _, h = model.value_grad_hessian_diagonal(x)
    state = JacobiState(settings, seam_pairs(model))
    state.rebuild(h, model.last_volatile_rows)
    _, g2, h2 = model.value_grad_hessian_diagonal(x2, reuse_elastic=True)
    state.update(h2, model.last_volatile_rows)
    full = JacobiState(settings, seam_pairs(model))
    full.rebuild(h2)
    full_scale_state = JacobiState(settings, seam_pairs(model))
    full_scale_state._scale = state._scale  # the partial update keeps the scale of its last full rebuild
    full_scale_state._base = jacobi_inverse(h2, settings.preconditioner, settings.diagonal_floor,
                                            state._scale)
    full_scale_state._finish(h2)
    torch.testing.assert_close(apply_inverse(state.inverse, g2), apply_inverse(full_scale_state.inverse, g2),
                               rtol=1e-10, atol=0.0)
    # and the floor's scale barely matters: the same as a plain rebuild to round-off of the floor
    torch.testing.assert_close(apply_inverse(state.inverse, g2), apply_inverse(full.inverse, g2), rtol=1e-6,
                               atol=0.0)


def test_partial_update_with_seam_blocks_equals_a_rebuild():
    """A partial update whose rows include seam vertices (one pair stops being positive definite and falls
    back to its 3x3 inverses) equals a full rebuild with the same floor scale; a positive definite pair's
    block is the exact 6x6 inverse."""
    torch.manual_seed(0)
    V, k = 40, 50.0
    eye = torch.eye(3, dtype=torch.float64)
    m = torch.randn(V, 3, 3, dtype=torch.float64)
    h = m @ m.transpose(1, 2) + 3.0 * eye
    pairs = torch.tensor([[0, 1], [2, 3], [4, 5], [6, 7]])
    h[pairs.flatten()] += k * eye
    settings = SolveSettings(preconditioner=Preconditioner.BLOCK)
    state = JacobiState(settings, (pairs, k))
    state.rebuild(h, torch.tensor([0, 10]))
    assert state.inverse.i.numel() == 4
    h2 = h.clone()
    h2[2] += 5.0 * eye
    h2[11] += 2.0 * eye
    h2[7] = -h2[7]  # the pair (6, 7) is no longer positive definite
    state.update(h2, torch.tensor([2, 11, 7]))
    assert state.inverse.i.tolist() == [0, 2, 4]  # (6, 7) keeps its 3x3 inverses
    ref = JacobiState(settings, (pairs, k))
    ref._scale = state._scale
    ref._base = jacobi_inverse(h2, settings.preconditioner, settings.diagonal_floor, state._scale)
    ref._finish(h2)
    g = torch.randn(V, 3, dtype=torch.float64)
    out = apply_inverse(state.inverse, g)
    torch.testing.assert_close(out, apply_inverse(ref.inverse, g), rtol=1e-12, atol=0.0)
    f = settings.diagonal_floor * state._scale
    for i, j in ((2, 3), (0, 1)):
        block = torch.cat([torch.cat([h2[i] + f * eye, -k * eye], 1),
                           torch.cat([-k * eye, h2[j] + f * eye], 1)])
        uv = torch.linalg.solve(block, torch.cat([g[i], g[j]]))
        torch.testing.assert_close(torch.cat([out[i], out[j]]), uv, rtol=1e-9, atol=0.0)
    base = jacobi_inverse(h2, settings.preconditioner, settings.diagonal_floor, state._scale)
    for v in (6, 7, 11):
        torch.testing.assert_close(out[v], base[v] @ g[v], rtol=1e-12, atol=0.0)


def test_spd_inverse_3x3_against_linalg():
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(200, 3, 3, dtype=torch.float64, generator=gen)
    spd = a @ a.transpose(1, 2) + 0.1 * torch.eye(3, dtype=torch.float64)
    inv, pd = spd_inverse_3x3(spd)
    assert bool(pd.all())
    torch.testing.assert_close(inv, torch.linalg.inv(spd), rtol=1e-9, atol=1e-9)
    inv_s, _ = spd_inverse_3x3(spd, shift=0.5)
    torch.testing.assert_close(inv_s, torch.linalg.inv(spd + 0.5 * torch.eye(3, dtype=torch.float64)),
                               rtol=1e-9, atol=1e-9)
    indefinite = torch.diag_embed(torch.tensor([[1.0, -1.0, 1.0], [0.0, 1.0, 1.0]], dtype=torch.float64))
    assert spd_inverse_3x3(indefinite)[1].tolist() == [False, False]
    # jacobi_inverse falls back to the scalar diagonal exactly there
    out = jacobi_inverse(indefinite, Preconditioner.BLOCK, 1e-8)
    assert bool(torch.isfinite(out).all())


def _adjugate_inverse_elementwise(blocks, shift=0.0):
    """The adjugate inverse written entry by entry on strided columns (the implementation before
    2026-12-01): spd_inverse_3x3's selection products must give the same bits."""
    n = blocks.shape[0]
    hv = blocks.reshape(n, 9)
    a00, a11, a22 = hv[:, 0] + shift, hv[:, 4] + shift, hv[:, 8] + shift
    a01 = (hv[:, 1] + hv[:, 3]).mul_(0.5)
    a02 = (hv[:, 2] + hv[:, 6]).mul_(0.5)
    a12 = (hv[:, 5] + hv[:, 7]).mul_(0.5)
    c00 = torch.mul(a11, a22).addcmul_(a12, a12, value=-1.0)
    c01 = torch.mul(a02, a12).addcmul_(a01, a22, value=-1.0)
    c02 = torch.mul(a01, a12).addcmul_(a02, a11, value=-1.0)
    c11 = torch.mul(a00, a22).addcmul_(a02, a02, value=-1.0)
    c12 = torch.mul(a01, a02).addcmul_(a00, a12, value=-1.0)
    c22 = torch.mul(a00, a11).addcmul_(a01, a01, value=-1.0)
    det = (a00 * c00).addcmul_(a01, c01).addcmul_(a02, c02)
    tiny = 1e3 * torch.finfo(blocks.dtype).eps
    m2 = a00 * a11
    pd = (a00 > 0) & (c22 > tiny * m2) & (det > m2.mul_(a22).mul_(tiny))
    inv_det = torch.where(pd, det, torch.ones_like(det)).reciprocal_()
    inv = torch.stack([c00, c01, c02, c01, c11, c12, c02, c12, c22], dim=1).mul_(inv_det.unsqueeze(1))
    return inv.view(n, 3, 3), pd


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_spd_inverse_3x3_equals_the_elementwise_adjugate_bit_for_bit(dtype):
    gen = torch.Generator().manual_seed(1)
    a = torch.randn(3000, 3, 3, dtype=torch.float64, generator=gen)
    blocks = (a @ a.transpose(1, 2) + 0.1 * torch.eye(3, dtype=torch.float64)).to(dtype)
    blocks[::7, 0, 1] += 1e-3  # not quite symmetric: the symmetric part is inverted
    blocks[::5, 2, 1] -= 0.25
    blocks[::11] *= -1.0  # not positive definite
    blocks[::13] *= 1e6  # large and small scales
    blocks[::17] *= 1e-6
    for shift in (0.0, 0.5):
        inv, pd = spd_inverse_3x3(blocks, shift=shift)
        ref, pd_ref = _adjugate_inverse_elementwise(blocks, shift=shift)
        assert torch.equal(pd, pd_ref) and 0 < int(pd.sum()) < blocks.shape[0]
        assert torch.equal(inv[pd], ref[pd])
        assert inv.is_contiguous() and inv.dtype == dtype


def test_spring_diagonal_is_the_sum_of_the_spring_blocks():
    """PlanarSprings' fused diagonal (seven sums per vertex, assembled by one product) against the diagonal
    blocks of its block-COO Hessian, projected and not."""
    from torchgarment.benchmarking import reference_grid
    from torchgarment.sim import PlanarSprings

    edges, p, x = reference_grid(400)
    springs = PlanarSprings(edges, p)
    x[::3, :2] *= 0.97  # some springs compressed: the projection clamps them
    for project in (True, False):
        _, _, h = springs.value_grad_hessian_diagonal(x, project_psd=project)
        blocks = springs.hessian_blocks(x, project_psd=project)
        ref = torch.zeros_like(h).index_add_(0, blocks.rows[blocks.rows == blocks.cols],
                                             blocks.values[blocks.rows == blocks.cols])
        torch.testing.assert_close(h, ref, rtol=1e-12, atol=1e-9)
        assert torch.equal(h, h.transpose(1, 2))


def test_elastic_reuse_does_not_change_the_converged_drape():
    """Reusing the elastic diagonal changes the path, not the equilibrium: both settings converge to the same
    positions within the tolerance's displacement scale."""
    scene, _ = tube_scene(0.03, 0.02, torch.float64, material=Material())
    model = scene.build()
    st = dict(rtol=1e-7, atol=0.0, max_iterations=6000)
    xa, ia = solve(model, scene.garment.x, SolveSettings(elastic_diagonal_interval=1, **st),
                   solver="gd-chebyshev")
    xb, ib = solve(model, scene.garment.x, SolveSettings(elastic_diagonal_interval=4, **st),
                   solver="gd-chebyshev")
    assert ia.converged and ib.converged
    assert float((xa - xb).norm(dim=1).max()) < 1e-3


def test_first_restart_with_a_reused_elastic_diagonal_keeps_the_step():
    """An energy increase while the elastic diagonal is reused is answered with a fresh diagonal every
    iteration from the checkpoint, the step unchanged; only later increases shrink the step. (Shrinking it at
    that first restart too made GD-Chebyshev settles of five library garments take 1.24-1.48x longer.)"""
    scene, _ = tube_scene(0.03, 0.02, torch.float64, material=Material())
    model = scene.build()
    x0 = scene.garment.x
    for step in (0.7, 1.0):
        st = dict(rtol=0.0, atol=0.0, max_iterations=300, step=step)
        _, reused = solve(model, x0, SolveSettings(elastic_diagonal_interval=4, **st), solver="gd-chebyshev")
        _, fresh = solve(model, x0, SolveSettings(elastic_diagonal_interval=1, **st), solver="gd-chebyshev")
        assert reused.restarts >= 1  # the stale diagonal made the energy rise
        assert reused.final_step == pytest.approx(step * 0.7 ** (reused.restarts - 1), rel=1e-12)
        assert fresh.final_step == pytest.approx(step * 0.7 ** fresh.restarts, rel=1e-12)
    assert reused.restarts >= 2  # step 1.0: a second increase, with the fresh diagonal, shrinks the step
