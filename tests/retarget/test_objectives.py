"""Retargeting objectives: float64 finite-difference gradients, Hessians, invariances."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from retarget_synth import pocketed_tube, scene  # noqa: E402

from torchgarment.errors import InputError  # noqa: E402
from torchgarment.retarget.objectives import (  # noqa: E402
    Attachment,
    Contact,
    CurveShape,
    Fit,
    Positional,
    SurfaceShape,
    adjacent_triangle_pairs,
    boundary_loops,
    element_hessians,
    layer_anchors,
    loop_winds_around_a_bone,
    make_state,
    project_psd,
)
from torchgarment.sdf.build import SDFSettings  # noqa: E402
from torchgarment.sdf.grid import BodySDF  # noqa: E402
from torchgarment.testing import check_gradient, fd_hessian_columns  # noqa: E402

if TYPE_CHECKING:
    from torchgarment.sim.energies.base import EnergyTerm

torch.manual_seed(0)


@pytest.fixture(scope="module")
def sc() -> dict[str, torch.Tensor]:
    return scene(rings=6, segments=12)


def _hess(term: EnergyTerm, x: torch.Tensor, t: float | torch.Tensor = 1.0) -> np.ndarray:
    """The term's (unweighted) Hessian over [x.flatten(), t] as a dense (3N + 1, 3N + 1) array."""
    n = x.shape[0]
    b = term.unweighted_blocks(x, torch.as_tensor(t, dtype=x.dtype), True)
    from torchgarment.sim.energies.base import HessianBlocks

    h = HessianBlocks(b.rows, b.cols, b.values).to_sparse(n + 1).to_dense().numpy()
    return h[: 3 * n + 1, : 3 * n + 1]


def _wavy(x: torch.Tensor, amp: float = 0.01) -> torch.Tensor:
    """A smooth non-affine deformation."""
    return x + amp * torch.stack(
        [torch.sin(7 * x[:, 1]), torch.cos(5 * x[:, 0]), torch.sin(6 * x[:, 1] + x[:, 0])], 1
    )


def _random_affine(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    a = torch.eye(3, dtype=torch.float64) + 0.4 * torch.randn(3, 3, generator=g, dtype=torch.float64)
    return a, torch.randn(3, generator=g, dtype=torch.float64)


def _rotation(seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
    return q * torch.sign(torch.linalg.det(q))


def test_mesh_helpers(sc: dict) -> None:
    f = sc["garment_faces"].numpy()
    loops = boundary_loops(f)
    assert sorted(len(lp) for lp in loops) == [12, 12]
    pairs = adjacent_triangle_pairs(f)
    # interior edges of a 6 x 12 tube: 12 * 5 vertical-ish + 12 * 4 ring edges + 12 * 5 diagonals
    assert pairs.shape == (12 * 5 + 12 * 4 + 12 * 5, 6)
    # shared edge (v1, v2) belongs to both faces, v3 / v4 are the opposite vertices
    for v1, v2, v3, v4, f1, f2 in pairs[:20]:
        assert {v1, v2, v3} == set(f[f1]) and {v1, v2, v4} == set(f[f2])


def test_surface_gradient_and_hessian(sc: dict) -> None:
    x0, f = sc["garment_vertices"], sc["garment_faces"]
    term = SurfaceShape(x0, f)
    x = _wavy(x0, 0.02)
    check_gradient(lambda y: term.energy(y), x, rtol=1e-5, atol=1e-9, num_samples=40)
    # closed-form Jacobian gives the exact gradient 2 w J^T r
    r, J = term.residual_jacobian(x)
    g = torch.zeros(x.numel() + 1, dtype=x.dtype)
    gl = 2 * term.weights[:, None] * (J.transpose(1, 2) @ r[..., None])[..., 0]
    from torchgarment.retarget.objectives import vertex_dofs

    g.index_add_(0, vertex_dofs(term.quads).reshape(-1), gl.reshape(-1))
    xr = x.clone().requires_grad_(True)
    (ga,) = torch.autograd.grad(term.energy(xr), xr)
    assert torch.allclose(g[:-1].reshape(-1, 3), ga, rtol=1e-9, atol=1e-12)
    h = _hess(term, x)
    assert np.allclose(h, h.T) and np.linalg.eigvalsh(h).min() > -1e-10


def test_surface_invariances(sc: dict) -> None:
    x0, f = sc["garment_vertices"], sc["garment_faces"]
    term = SurfaceShape(x0, f)
    assert float(term.energy(x0)) < 1e-25
    r = _rotation()
    assert (
        float(term.energy(2.7 * x0 @ r.T + torch.tensor([1.0, -2.0, 0.5], dtype=x0.dtype))) < 1e-20
    )  # similarity
    # any affine map: zero on a flat sheet (all pairs coplanar)
    plane = torch.stack(
        [torch.arange(12.0).repeat(6), torch.arange(6.0).repeat_interleave(12), torch.zeros(72)], 1
    )
    plane = plane.to(torch.float64) * 0.05
    sheet_f = torch.as_tensor(_grid_faces(6, 12))
    sheet = SurfaceShape(plane, sheet_f)
    a, b = _random_affine()
    assert float(sheet.energy(plane @ a.T + b)) < 1e-20
    # curved surface under an anisotropic affine map: ~1000x smaller than under a non-affine deformation of
    # the same largest displacement, and vanishing as the mesh is refined (O(h^2): the out-of-plane part of
    # the map has no triangle-local representative)
    values = []
    for rings, segments in ((6, 12), (12, 24)):
        s = scene(rings=rings, segments=segments)
        xs, fs = s["garment_vertices"], s["garment_faces"]
        ts = SurfaceShape(xs, fs)
        stretched = xs * torch.tensor([1.3, 0.8, 1.1], dtype=xs.dtype)
        amp = float((stretched - xs).norm(dim=1).max()) / 1.7
        wavy = xs + amp * torch.stack(
            [torch.sin(20 * xs[:, 1]), torch.cos(15 * xs[:, 0]), torch.sin(12 * xs[:, 2])], 1
        )
        assert float(ts.energy(stretched)) < 0.01 * float(ts.energy(wavy))
        values.append(float(ts.energy(stretched)))
    assert values[1] < 0.5 * values[0]


def _grid_faces(rows: int, cols: int) -> np.ndarray:
    i, j = np.meshgrid(np.arange(rows - 1), np.arange(cols - 1), indexing="ij")
    a = i * cols + j
    return np.concatenate(
        [
            np.stack([a, a + 1, a + cols], -1).reshape(-1, 3),
            np.stack([a + 1, a + cols + 1, a + cols], -1).reshape(-1, 3),
        ]
    )


def test_positional(sc: dict) -> None:
    x0, f = sc["garment_vertices"], sc["garment_faces"]
    js = sc["joints"]
    jt = js * torch.tensor([1.0, 1.2, 1.0], dtype=js.dtype)
    term = Positional(x0, f, js, jt, sc["bones"])
    assert len(term.vertices) == 24  # both boundary rings
    t0 = torch.tensor(0.0, dtype=torch.float64)
    assert float(term.energy(x0, t0)) < 1e-28
    x = _wavy(x0, 0.02)
    t = torch.tensor(0.4, dtype=torch.float64)
    check_gradient(lambda y: term.energy(y, t), x, rtol=1e-5, atol=1e-10)
    check_gradient(lambda tt: term.energy(x, tt), t, rtol=1e-5, atol=1e-10)
    # moving the boundary with the stretched skeleton keeps the barycentric coordinates: zero at t = 1
    moved = x0.clone()
    moved[:, 1] = x0[:, 1] * 1.2
    assert float(term.energy(moved, torch.tensor(1.0, dtype=torch.float64))) < 1e-25
    h = _hess(term, x, t)
    assert np.linalg.eigvalsh(h).min() > -1e-10
    # the t column couples with the vertices (skeleton moves with t)
    assert np.abs(h[-1, :-1]).max() > 0


def test_curve_gradient_and_invariances(sc: dict) -> None:
    x0, f = sc["garment_vertices"], sc["garment_faces"]
    # make the loops non-planar so that the torsion is exercised
    x0 = x0 + 0.02 * torch.stack(
        [torch.zeros(72), torch.sin(3 * torch.atan2(x0[:, 2], x0[:, 0])), torch.zeros(72)], 1
    ).to(x0)
    loops = [torch.as_tensor(lp) for lp in boundary_loops(f.numpy())]
    term = CurveShape(x0, loops)
    assert len(term.triples) == 24 and len(term.quads) == 24
    assert float(term.energy(x0)) < 1e-25
    r = _rotation(3)
    sim = 0.4 * x0 @ r.T + torch.tensor([0.3, 0.1, -2.0], dtype=x0.dtype)
    assert float(term.energy(sim)) < 1e-20
    aniso = x0 * torch.tensor([1.5, 1.0, 0.7], dtype=x0.dtype)
    assert float(term.energy(aniso)) > 1e-4
    x = _wavy(x0, 0.01)
    check_gradient(lambda y: term.energy(y), x, rtol=1e-5, atol=1e-10)
    h = _hess(term, x)
    assert np.linalg.eigvalsh(h).min() > -1e-10


@pytest.mark.parametrize("with_gap", [False, True])
def test_fit_gradient(sc: dict, with_gap: bool) -> None:
    """FD gradient and PSD Hessian, with the offset as every target or with per-vertex source gaps (each fit
    vertex's gap where it exceeds the offset)."""
    av, af = sc["avatar_full"], sc["avatar_faces"]
    sdf = BodySDF.from_mesh(av, af, SDFSettings(voxel_size=0.01))
    x0, f = sc["garment_vertices"], sc["garment_faces"]
    mask = torch.zeros(x0.shape[0], dtype=torch.bool)
    mask[::2] = True
    gap = torch.linspace(0.0, 0.03, x0.shape[0], dtype=x0.dtype) if with_gap else None
    term = Fit(sdf, x0, f, mask, fit_length=0.01, offset=0.002, source_gap=gap)
    offsets = torch.full((int(mask.sum()),), 0.002, dtype=x0.dtype)
    targets = gap[mask].clamp_min(0.002) if gap is not None else offsets
    assert torch.equal(term.targets, targets)
    x = x0 * torch.tensor([1.25, 1.0, 1.25], dtype=x0.dtype)  # outside the 0.17 capsule
    # distances match the capsule: ~0.1875 - 0.17 (up to the SDF's interpolation and the polygonal capsule)
    d = sdf(x[mask])
    assert float((d - (0.1875 - 0.17)).abs().max()) < 4e-3
    # the energy is the sum of area-weighted squared misses of the targets
    expected = float((term.weights * (d - targets) ** 2).sum())
    assert math.isclose(float(term.energy(x)), expected, rel_tol=1e-12)
    check_gradient(lambda y: term.energy(y), x, rtol=1e-4, atol=1e-8, num_samples=40, eps=1e-7)
    h = _hess(term, x)
    assert np.linalg.eigvalsh(h).min() > -1e-10
    if gap is not None:
        with pytest.raises(InputError, match="source_gap"):
            Fit(sdf, x0, f, mask, fit_length=0.01, source_gap=gap[:-1])
        with pytest.raises(InputError, match="source_gap"):
            Fit(sdf, x0, f, mask, fit_length=0.01, source_gap=torch.full_like(gap, math.nan))


def test_contact_gradient_t_and_hessian(sc: dict) -> None:
    x0, f = sc["garment_vertices"], sc["garment_faces"]
    c = Contact(x0, f, sc["avatar_full"], sc["avatar_faces"], sc["avatar_shrunk"], dhat=0.03, stiffness=10.0)
    t = torch.tensor(0.82, dtype=torch.float64)  # avatar radius ~0.139 vs garment 0.15: within dhat
    assert math.isfinite(float(c.energy(x0, t))) and float(c.energy(x0, t)) > 0
    assert not c.ipc.has_intersections(x0, float(t))
    xr, tr = x0.clone().requires_grad_(True), t.clone().requires_grad_(True)
    gx, gt = torch.autograd.grad(c.energy(xr, tr), (xr, tr))
    check_gradient(lambda y: c.energy(y, t), x0, grad=gx, rtol=1e-5, atol=1e-8, num_samples=30)
    check_gradient(lambda tt: c.energy(x0, tt), t, grad=gt, rtol=1e-5, atol=1e-8)
    assert float(gt) > 0  # inflating pushes the avatar into the garment
    h = _hess(c, x0, t)
    assert h.shape == (3 * x0.shape[0] + 1,) * 2
    hd = h
    assert (
        np.allclose(hd, hd.T, atol=1e-8 * np.abs(hd).max())
        and np.linalg.eigvalsh(hd).min() > -1e-6 * np.abs(hd).max()
    )
    # the t-t entry matches a finite difference of dE/dt
    eps = 1e-6

    def dedt(tv: float) -> float:
        trr = torch.tensor(tv, dtype=torch.float64, requires_grad=True)
        return float(torch.autograd.grad(c.energy(x0, trr), trr)[0])

    fd = (dedt(0.82 + eps) - dedt(0.82 - eps)) / (2 * eps)
    assert hd[-1, -1] >= 0 and abs(hd[-1, -1] - fd) <= 0.05 * abs(fd) + 1e-9


def test_element_hessians_and_projection() -> None:
    z = torch.randn(5, 4, dtype=torch.float64)
    fn = lambda z: z[:, 0] * z[:, 1] ** 2 + torch.sin(z[:, 2]) * z[:, 3]  # noqa: E731
    h = element_hessians(fn, z)
    ref = torch.stack([torch.autograd.functional.hessian(lambda v: fn(v[None])[0], zi) for zi in z])
    assert torch.allclose(h, ref, atol=1e-12)
    p = project_psd(h)
    assert float(torch.linalg.eigvalsh(p).min()) > -1e-12


def test_positional_skips_zero_length_bones(sc: dict) -> None:
    # a zero-length root bone at the hem's height (like anny's root) must not be chosen: finite values
    x0, f = sc["garment_vertices"], sc["garment_faces"]
    js = torch.cat([sc["joints"], torch.tensor([[0.0, 0.75, 0.0]], dtype=torch.float64)])
    bones = torch.cat([sc["bones"], torch.tensor([[3, 3]])])
    term = Positional(x0, f, js, js.clone(), bones)
    assert int((term.bone == 2).sum()) == 0
    t = torch.tensor(0.5, dtype=torch.float64)
    assert math.isfinite(float(term.energy(_wavy(x0), t)))


def test_terms_follow_the_energy_term_contract_on_the_state(sc: dict) -> None:
    """forward(y) = weight * energy(x, t) on the state (N + 1, 3); the gradient's t entry is y[N, 0]'s, the
    two padding entries get none; hessian_blocks are the weighted unweighted_blocks."""
    x0, f = sc["garment_vertices"], sc["garment_faces"]
    jt = sc["joints"] * torch.tensor([1.0, 1.2, 1.0], dtype=torch.float64)
    term = Positional(x0, f, sc["joints"], jt, sc["bones"], weight=2.5)
    x = _wavy(x0, 0.02)
    t = torch.tensor(0.4, dtype=torch.float64)
    y = make_state(x, t)
    e, g = term.value_and_grad(y)
    assert float(e) == pytest.approx(2.5 * float(term.energy(x, t)), rel=1e-14)
    tr = t.clone().requires_grad_(True)
    (gt,) = torch.autograd.grad(term.energy(x, tr), tr)
    assert float(g[-1, 0]) == pytest.approx(2.5 * float(gt), rel=1e-12)
    assert float(g[-1, 1:].abs().max()) == 0.0
    assert term.value(y) == pytest.approx(float(term.energy(x, t)), rel=1e-14)
    hb = (
        term.hessian_blocks(y)
        .to_sparse(y.shape[0])
        .to_dense()
        .numpy()[: 3 * x.shape[0] + 1, : 3 * x.shape[0] + 1]
    )
    np.testing.assert_allclose(hb, 2.5 * _hess(term, x, t), rtol=1e-14, atol=0)


def test_culled_contact_matches_the_whole_avatar_and_keeps_its_mesh_when_it_can(
    sc: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The culled collision mesh gives the whole avatar's energy, gradient and step bounds along a path, and a
    re-cull that keeps the same faces does not rebuild it."""
    from torchgarment.sim.contact import MovingObstacleContact, StepBound

    x0, f = sc["garment_vertices"], sc["garment_faces"]
    args = (x0, f, sc["avatar_full"], sc["avatar_faces"], sc["avatar_shrunk"])
    whole = MovingObstacleContact(*args, dhat=0.03, stiffness=10.0)
    culled = MovingObstacleContact(*args, dhat=0.03, stiffness=10.0, cull_radius=0.12)
    builds: list[int] = []
    original = MovingObstacleContact._set_subset

    def counting(self: MovingObstacleContact, verts: np.ndarray, faces: np.ndarray) -> None:
        builds.append(faces.shape[0])
        original(self, verts, faces)

    monkeypatch.setattr(MovingObstacleContact, "_set_subset", counting)
    x, t = x0.clone(), 0.82
    for k in range(16):  # the garment slides along the avatar by 15 mm a step, up and back down: re-culls
        dx = torch.tensor([0.0, 0.015 if k % 8 < 4 else -0.015, 0.0], dtype=torch.float64).expand_as(x)
        a_whole = whole.max_step(x, t, dx.numpy(), 0.0, StepBound.ADDITIVE)
        a_culled = culled.max_step(x, t, dx.numpy(), 0.0, StepBound.ADDITIVE)
        assert a_culled == pytest.approx(a_whole, rel=1e-9, abs=1e-12)
        x = x + a_whole * dx
        e0, g0, gt0 = whole.value_grad(x, t)
        e1, g1, gt1 = culled.value_grad(x, t)
        assert e0 > 0 and e1 == pytest.approx(e0, rel=1e-12)
        assert gt1 == pytest.approx(gt0, rel=1e-9, abs=1e-12)
        np.testing.assert_allclose(g1, g0, rtol=1e-9, atol=1e-12 * np.abs(g0).max())
    assert culled.num_culls >= 3 and len(builds) >= 2 and max(builds) < sc["avatar_faces"].shape[0]
    # a re-cull that keeps the same faces (here: at the same positions, then 0.1 mm away) does not rebuild
    # the mesh
    xn = x.numpy()
    culled._recull(xn, t)
    rebuilt, culls = len(builds), culled.num_culls
    culled._recull(xn, t)
    culled._recull(xn + 1e-4, t)
    assert culled.num_culls == culls + 2 and len(builds) == rebuilt
    assert culled.value_grad(x, t)[0] == pytest.approx(whole.value_grad(x, t)[0], rel=1e-12)


def test_stiffness_update_doubles_kappa_while_the_closest_pair_approaches_below_the_threshold(
    sc: dict,
) -> None:
    """IPC's adaptive stiffness: kappa doubles (up to its maximum) exactly when the minimum distance, in the
    units of x, is below ``stiffness_distance * dhat`` at both iterations and decreasing (ipctk compares
    squared distances, so the distances handed to it are squared). Before this was so, a pair at 1e-3 of
    dhat never raised kappa and the inflation squeezed pairs to 1e-8 m."""
    from torchgarment.sim.contact import MovingObstacleContact

    args = (sc["garment_vertices"], sc["garment_faces"], sc["avatar_full"], sc["avatar_faces"],
            sc["avatar_shrunk"])
    ipc = MovingObstacleContact(*args, dhat=0.03, stiffness=10.0)
    ipc.max_stiffness = 35.0
    below = 0.1 * 0.03  # the threshold at stiffness_distance = 0.1
    assert not ipc.update_stiffness(0.9 * below, 0.95 * below, 0.1)  # moving apart
    assert not ipc.update_stiffness(1.5 * below, 0.5 * below, 0.1)  # was above the threshold
    assert not ipc.update_stiffness(0.5 * below, 0.5 * below, 0.1)  # not decreasing
    assert ipc.stiffness == 10.0
    assert ipc.update_stiffness(0.5 * below, 0.4 * below, 0.1) and ipc.stiffness == 20.0
    assert ipc.update_stiffness(1e-3 * below, 1e-4 * below, 0.1) and ipc.stiffness == 35.0  # capped
    assert not ipc.update_stiffness(0.5 * below, 0.4 * below, 0.1) and ipc.stiffness == 35.0
    assert not ipc.update_stiffness(math.inf, 0.4 * below, 0.1)


def test_layer_anchors_attach_the_pieces_that_lie_on_a_larger_one() -> None:
    v, f, n, m = pocketed_tube()
    idx, tri, bary = layer_anchors(v, f, 0.01)
    # every pocket vertex, nothing of the tube (the largest piece) or of the ring 5 cm out
    assert sorted(idx.tolist()) == list(range(n, n + m))
    assert bool((tri < n).all())  # anchored on the tube
    assert torch.allclose(bary.sum(1), torch.ones(m, dtype=bary.dtype)) and float(bary.min()) > -1e-9
    anchor = (bary[:, :, None] * v[tri]).sum(1)
    assert float((v[idx] - anchor).norm(dim=1).max()) < 0.0045  # 4 mm out, the tube's chords a bit more
    # a wider reach also takes the ring; a garment in one piece has no anchors
    assert len(layer_anchors(v, f, 0.1)[0]) == m + 48
    assert len(layer_anchors(v[:n], f[: 2 * 24 * 9], 0.01)[0]) == 0


def test_attachment_holds_a_pocket_in_place_and_is_blind_to_rigid_motions() -> None:
    v, f, n, m = pocketed_tube()
    term = Attachment(v, f, 0.01, 0.01, weight=3.0)
    assert len(term.vertices) == m and float(term.energy(v)) < 1e-25
    r = _rotation(5)
    assert float(term.energy(v @ r.T + torch.tensor([0.3, -1.0, 2.0], dtype=v.dtype))) < 1e-25
    # the pocket turned 5 cm around the tube's axis: held; the ring (not attached) costs nothing
    slid = v.clone()
    c, s_ = math.cos(0.2), math.sin(0.2)
    turn = torch.tensor([[c, 0.0, -s_], [0.0, 1.0, 0.0], [s_, 0.0, c]], dtype=v.dtype)
    slid[n:n + m] = v[n:n + m] @ turn.T
    assert float(term.residuals(slid).norm(dim=1).median()) > 0.04
    moved_ring = v.clone()
    moved_ring[n + m:] += 0.05
    assert float(term.energy(moved_ring)) < 1e-25
    # the gradient by central differences, off the source shape
    g = torch.Generator().manual_seed(2)
    x = v + 0.003 * torch.randn(v.shape, generator=g, dtype=v.dtype)
    check_gradient(lambda y: term.energy(y), x, rtol=1e-5, atol=1e-10, num_samples=60)
    # Gauss-Newton Hessian: PSD; exact where the residuals vanish (the source shape)
    h = _hess(term, x)
    assert np.linalg.eigvalsh(h).min() > -1e-9
    ids = torch.cat([term.vertices[:3], term.anchors[:3].reshape(-1)]).unique()
    cols = (3 * ids[:, None] + torch.arange(3)).reshape(-1)

    def grad(y: torch.Tensor) -> torch.Tensor:
        yr = y.clone().requires_grad_(True)
        with torch.enable_grad():
            return torch.autograd.grad(term.energy(yr), yr)[0]

    fd = fd_hessian_columns(grad, v, cols, eps=1e-6).numpy()
    np.testing.assert_allclose(_hess(term, v)[: 3 * v.shape[0], cols.numpy()], fd, rtol=1e-5, atol=1e-4)
    with pytest.raises(InputError, match="max_distance"):
        Attachment(v, f, -1.0, 0.01)


def test_a_hem_winds_around_its_bone_and_a_pocket_rim_does_not() -> None:
    """The positional term stays on an attached piece's rims that wind around a bone (a waistband's) and
    leaves those that lie beside one (a pocket's) to the attachment."""
    joints = torch.tensor([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.3, 1.1, 0.0]],
                          dtype=torch.float64)
    bones = torch.tensor([[0, 1], [2, 3]])
    th = torch.linspace(0, 2 * math.pi, 25, dtype=torch.float64)[:-1]
    ring = torch.stack([0.15 * torch.cos(th), 0.4 + 0.02 * torch.sin(3 * th), 0.12 * torch.sin(th)], 1)
    patch = torch.stack([0.03 * torch.cos(th), 0.4 + 0.03 * torch.sin(th), 0.12 + 0.0 * th], 1)
    assert loop_winds_around_a_bone(ring, joints, bones)
    assert loop_winds_around_a_bone(ring.flip(0), joints, bones)  # either orientation
    assert not loop_winds_around_a_bone(patch, joints, bones)
