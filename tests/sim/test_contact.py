"""Tests of the ipctk IPC contact terms (torchgarment.sim.contact)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import textwrap
from typing import TYPE_CHECKING

import numpy as np
import pytest
import torch
import trimesh

from torchgarment.errors import InputError
from torchgarment.sim.contact import (
    BodyMeshContact,
    SeamWeld,
    SelfContact,
    StepBound,
    ipc_threads,
    self_crossings,
)

if TYPE_CHECKING:
    from torchgarment.sim.energies.base import EnergyTerm, HessianBlocks

DHAT = 2e-3
FACES2 = torch.tensor([[0, 1, 2], [3, 4, 5]])


def two_triangles(gap: float) -> torch.Tensor:
    """A triangle at z=0 and a shifted parallel one at z=gap (their projections overlap)."""
    return torch.tensor(
        [[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0.02, 0.02, gap], [0.12, 0.02, gap], [0.02, 0.12, gap]],
        dtype=torch.float64,
    )


def tilted_pair() -> torch.Tensor:
    """Two non-parallel triangles 0.4-1.5 mm apart: face-vertex, edge-edge and edge-vertex pairs are
    active."""
    x = two_triangles(1e-3)
    x[4, 2] = 1.4e-3
    x[5, 2] = 0.7e-3
    x[3, 0] += 0.003
    return x


def grid(nu: int, nv: int) -> torch.Tensor:
    """(F, 3) triangles of an nu x nv vertex grid (row-major vertex ids)."""
    i, j = np.meshgrid(np.arange(nu - 1), np.arange(nv - 1), indexing="ij")
    a = (i * nv + j).reshape(-1)
    b, c, d = a + nv, a + 1, a + nv + 1
    return torch.as_tensor(np.concatenate([np.stack([a, b, c], 1), np.stack([c, b, d], 1)]))


def folded_sheet(
    length: float = 0.05, width: float = 0.03, gap: float = 5e-3, h: float = 2.5e-3
) -> tuple[torch.Tensor, torch.Tensor]:
    """A rectangle folded over itself: two layers ``gap`` apart joined by a half-cylinder fold."""
    r = gap / 2
    total = 2 * length + math.pi * r
    u = np.linspace(0, total, int(round(total / h)) + 1)
    xs = np.where(
        u < length,
        u,
        np.where(
            u > length + math.pi * r, 2 * length + math.pi * r - u, length + r * np.sin((u - length) / r)
        ),
    )
    zs = np.where(u < length, 0.0, np.where(u > length + math.pi * r, gap, r - r * np.cos((u - length) / r)))
    ys = np.linspace(0, width, int(round(width / h)) + 1)
    X = np.stack(np.broadcast_arrays(xs[:, None], ys[None, :], zs[:, None]), -1).reshape(-1, 3)
    return torch.as_tensor(X), grid(len(xs), len(ys))


def fd_grad(term: EnergyTerm, x: torch.Tensor, h: float) -> torch.Tensor:
    g = torch.zeros_like(x)
    for k in range(x.numel()):
        xp, xm = x.clone(), x.clone()
        xp.view(-1)[k] += h
        xm.view(-1)[k] -= h
        g.view(-1)[k] = (term(xp) - term(xm)) / (2 * h)
    return g


def dense(blocks: HessianBlocks, n: int) -> torch.Tensor:
    return blocks.to_sparse(n).to_dense()


# ---------------------------------------------------------------------------------------------- self contact


def test_energy_vs_gap() -> None:
    t = SelfContact(FACES2, two_triangles(0.01), dhat=DHAT, stiffness=1e3)
    assert t(two_triangles(2.5e-3)).item() == 0.0
    assert t(two_triangles(DHAT * 1.001)).item() == 0.0
    gaps = [1.9e-3, 1.5e-3, 1e-3, 5e-4, 1e-4, 1e-5]
    energies = [t(two_triangles(g)).item() for g in gaps]
    assert energies[0] > 0
    assert all(b > a for a, b in zip(energies, energies[1:]))
    assert t(two_triangles(0.0)).item() == math.inf  # touching / coplanar overlap
    crossing = two_triangles(1e-3)
    crossing[3, 2] = -1e-3  # edges 3-4 and 3-5 pierce the lower triangle; every pair stays >= ~0.5 mm apart
    assert t.has_intersections(crossing)
    assert t(crossing).item() == math.inf
    t.check_intersections = False
    assert math.isfinite(t(crossing).item())  # the barrier alone cannot see a crossing


def test_stiffness_scales_energy_and_default() -> None:
    x = two_triangles(1e-3)
    t1 = SelfContact(FACES2, x, dhat=DHAT, stiffness=1.0)
    t2 = SelfContact(FACES2, x, dhat=DHAT, stiffness=250.0)
    assert t2(x).item() == pytest.approx(250.0 * t1(x).item(), rel=1e-12)
    t0 = SelfContact(FACES2, x, dhat=DHAT)
    assert t0.stiffness == pytest.approx(t0.min_stiffness) and t0.max_stiffness > t0.min_stiffness > 0
    # gradient balance: a gravity-like pull that pushes the top triangle down
    ge = torch.zeros_like(x)
    ge[3:, 2] = 1e6
    k = t0.calibrate_stiffness(x, ge)
    assert t0.min_stiffness <= k <= t0.max_stiffness
    assert t0.stiffness == k


def test_gradient_matches_finite_differences_and_autograd() -> None:
    x = tilted_pair()
    t = SelfContact(FACES2, two_triangles(0.01), dhat=DHAT, stiffness=1e3)
    e, g = t.value_and_grad(x)
    assert e.item() > 0 and g.shape == (6, 3)
    g_fd = fd_grad(t, x, 1e-9)
    assert torch.linalg.norm(g - g_fd) / torch.linalg.norm(g) < 1e-5
    xr = x.clone().requires_grad_(True)
    (ga,) = torch.autograd.grad(t(xr), xr)
    assert torch.allclose(ga, g, rtol=0, atol=1e-12 * g.abs().max())
    # Newton's third law: barrier forces sum to zero
    assert g.sum(0).abs().max() < 1e-9 * g.abs().max()


def test_hessian_blocks_fd_and_psd() -> None:
    x = tilted_pair()
    t = SelfContact(FACES2, two_triangles(0.01), dhat=DHAT, stiffness=1e3)
    h = dense(t.hessian_blocks(x, project_psd=False), 6)
    assert torch.allclose(h, h.T, atol=1e-9 * h.abs().max())
    eps = 1e-9
    cols = []
    for k in range(18):
        xp, xm = x.clone(), x.clone()
        xp.view(-1)[k] += eps
        xm.view(-1)[k] -= eps
        cols.append(((t.value_and_grad(xp)[1] - t.value_and_grad(xm)[1]) / (2 * eps)).reshape(-1))
    h_fd = torch.stack(cols, 1)
    assert torch.linalg.norm(h - h_fd) / torch.linalg.norm(h) < 1e-5
    hp = dense(t.hessian_blocks(x, project_psd=True), 6)
    ev = torch.linalg.eigvalsh(hp)
    assert ev.min() > -1e-9 * ev.abs().max()
    assert torch.linalg.eigvalsh(h).min() < -1e-6 * ev.abs().max()  # projection did something here
    diag = t.hessian_diagonal(x)
    for i in range(6):
        assert torch.allclose(diag[i], hp[3 * i : 3 * i + 3, 3 * i : 3 * i + 3])


@pytest.mark.parametrize("method", [StepBound.TIGHT_INCLUSION, StepBound.CONSERVATIVE])
def test_max_step_stops_before_intersection(method: StepBound) -> None:
    x = two_triangles(1e-3)
    t = SelfContact(FACES2, x, dhat=DHAT, stiffness=1e3)
    dx = torch.zeros_like(x)
    dx[3:, 2] = -3e-3  # would pass through the lower triangle at alpha = 1/3
    a = t.max_step(x, dx, method)
    assert 0 < a < 1 / 3
    x1 = x + a * dx
    assert not t.has_intersections(x1)
    assert math.isfinite(t(x1).item()) and t.min_distance(x1) > 0
    assert t.max_step(x, torch.zeros_like(x), method) == 1.0
    away = -dx
    assert t.max_step(x, away, StepBound.TIGHT_INCLUSION) == 1.0


@pytest.mark.parametrize("radius", [None, 10 * DHAT])
def test_conservative_step_below_ccd(radius: float | None) -> None:
    x = tilted_pair()
    t = SelfContact(FACES2, two_triangles(0.01), dhat=DHAT, stiffness=1e3, conservative_radius=radius)
    gen = torch.Generator().manual_seed(0)
    for _ in range(5):
        dx = 4e-3 * torch.randn(x.shape, generator=gen, dtype=torch.float64)
        cons = t.max_step(x, dx, StepBound.CONSERVATIVE)
        ccd = t.max_step(x, dx, StepBound.TIGHT_INCLUSION)
        assert 0 < cons <= ccd + 1e-12
        assert not t.has_intersections(x + cons * dx)


def test_folded_sheet_self_contact() -> None:
    x, f = folded_sheet()
    t = SelfContact(f, x, dhat=8e-3, stiffness=1e3)
    assert not t.has_intersections(x)
    e, g = t.value_and_grad(x)
    assert e.item() > 0 and math.isfinite(e.item())
    assert 1e-3 < t.min_distance(x) <= 5e-3 + 1e-9  # layers 5 mm apart; closer chords around the fold
    assert t.min_distance(x, max_distance=1e-3) == math.inf
    # the layers are pushed apart: bottom layer gets force -z (gradient +z), top layer the opposite
    bottom, top = x[:, 2] < 1e-9, x[:, 2] > 5e-3 - 1e-9
    assert g[bottom, 2].sum() > 0 and g[top, 2].sum() < 0
    h = t.hessian_blocks(x)
    assert h.rows.max() < x.shape[0] and h.values.shape[1:] == (3, 3)


def test_seam_pairs_allow_closed_seams() -> None:
    # two panels sharing a seam edge: vertices 0,1 of panel A coincide with 3,4 of panel B (a sewn seam);
    # triangle 6-8 is a third, unsewn piece that lies 1 mm above panel A
    x = torch.tensor(
        [
            [0, 0, 0],
            [0.1, 0, 0],
            [0.05, 0.05, 0.0],
            [0, 0, 0],
            [0.1, 0, 0],
            [0.05, -0.05, 0.01],
            [0.01, 0.01, 1e-3],
            [0.09, 0.005, 1e-3],
            [0.05, 0.04, 1e-3],
        ],
        dtype=torch.float64,
    )
    f = torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    seams = torch.tensor([[0, 3], [1, 4]])
    plain = SelfContact(f, x, dhat=DHAT, stiffness=1.0, check_intersections=False)
    assert plain(x).item() == math.inf
    sewn = SelfContact(f, x, dhat=DHAT, stiffness=1.0, seam_pairs=seams)
    assert not sewn.has_intersections(x)
    e = sewn(x).item()
    assert 0 < e < math.inf  # the third piece still collides with both panels
    weld = SeamWeld.of(seams.numpy(), 9)
    assert weld.index.tolist() == [0, 1, 2, 0, 1, 3, 4, 5, 6] and weld.num_welded == 7
    assert weld.faces(f.numpy()).tolist() == [[0, 1, 2], [0, 1, 3], [4, 5, 6]]
    # the gradient lives on the garment's vertices, and the force of the third piece is shared by the panels
    _, g = sewn.value_and_grad(x)
    assert g.shape == (9, 3) and g.sum(0).abs().max() < 1e-9 * g.abs().max()


def sewn_fold(tip_z: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Panels A (0-1-2) and B (3-4-5) sewn along 0-3 and 1-4; B goes on past its seam with triangle 5-6-7.
    Vertex 5 (next to the seam) at height ``tip_z`` under or over A, 6 and 7 1 cm above A."""
    x = torch.tensor([[0, 0, 0], [0.1, 0, 0], [0.05, 0.1, 0], [0, 0, 0], [0.1, 0, 0], [0.05, 0.04, tip_z],
                      [0.04, 0.05, 0.01], [0.06, 0.05, 0.01]], dtype=torch.float64)
    return x, torch.tensor([[0, 1, 2], [3, 4, 5], [5, 6, 7]]), torch.tensor([[0, 3], [1, 4]])


def test_a_crossing_next_to_a_seam_is_seen() -> None:
    """Edges 5-6 and 5-7 pierce panel A right next to the seam. Contact on the welded garment sees it (the
    old seam filter, which excluded every vertex pair in a seam's closed one-ring, had no barrier against it:
    the GarmentCode pencil dress settled with self-contact through itself at its seams)."""
    x, f, seams = sewn_fold(-0.005)
    t = SelfContact(f, x, dhat=DHAT, stiffness=1.0, seam_pairs=seams)
    assert t.has_intersections(x) and t(x).item() == math.inf
    above, _, _ = sewn_fold(0.005)
    assert not t.has_intersections(above) and t(above).item() == 0.0
    welded = SeamWeld.of(seams.numpy(), 8)
    wf = welded.faces(f.numpy())  # [[0, 1, 2], [0, 1, 3], [3, 4, 5]]: vertex 5 is welded vertex 3
    rows = self_crossings(torch.as_tensor(welded.mean @ x.numpy()), wf)
    assert sorted(map(tuple, rows.tolist())) == [(3, 4, 0), (3, 5, 0)]  # edges 5-6 and 5-7 through A
    assert self_crossings(torch.as_tensor(welded.mean @ above.numpy()), wf).shape == (0, 3)
    near, _, _ = sewn_fold(0.001)  # 5 is 1 mm over A: in contact, though both are next to the seam
    assert 0 < t(near).item() < math.inf
    down = torch.zeros_like(near)
    down[5, 2] = -0.01  # 5 moved 1 cm down through A
    assert t.max_step(near, down, StepBound.TIGHT_INCLUSION) < 0.1  # stops at A (the old filter: 1.0)


def test_welded_contact_gradient_and_hessian_match_finite_differences() -> None:
    x, f, seams = sewn_fold(0.001)
    x[3:5, 1] -= 2e-4  # the seam a little open, as the sewing springs leave it
    t = SelfContact(f, x, dhat=DHAT, stiffness=1e3, seam_pairs=seams)
    e, g = t.value_and_grad(x)
    assert e.item() > 0 and g.shape == (8, 3)
    g_fd = fd_grad(t, x, 1e-9)
    assert torch.linalg.norm(g - g_fd) / torch.linalg.norm(g) < 1e-5
    h = dense(t.hessian_blocks(x, project_psd=False), 8)
    cols = []
    for k in range(24):
        xp, xm = x.clone(), x.clone()
        xp.view(-1)[k] += 1e-9
        xm.view(-1)[k] -= 1e-9
        cols.append(((t.value_and_grad(xp)[1] - t.value_and_grad(xm)[1]) / 2e-9).reshape(-1))
    h_fd = torch.stack(cols, 1)
    assert torch.linalg.norm(h - h_fd) / torch.linalg.norm(h) < 1e-5
    diag = t.hessian_diagonal(x, project_psd=False)
    for i in range(8):
        assert torch.allclose(diag[i], h[3 * i : 3 * i + 3, 3 * i : 3 * i + 3])


def fold_and_piercing_panel() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The folded sheet (panel 0, layers 5 mm apart) and a triangle (panel 1) standing through both layers,
    as a sleeve placed through the torso before sewing."""
    x, f = folded_sheet(length=0.02, width=0.01)
    n = x.shape[0]
    tri = torch.tensor([[0.008, 0.002, -0.01], [0.014, 0.002, -0.01], [0.011, 0.008, 0.015]],
                       dtype=torch.float64)
    ids = torch.cat([torch.zeros(n, dtype=torch.long), torch.ones(3, dtype=torch.long)])
    return torch.cat([x, tri]), torch.cat([f, torch.tensor([[n, n + 1, n + 2]])]), ids


def test_panel_contact_works_within_panels_only() -> None:
    """The sewing stage's contact: a panel's fold is in contact and may not pass through itself, while
    another panel passes through it freely."""
    x, f, ids = fold_and_piercing_panel()
    n = x.shape[0] - 3
    every = SelfContact(f, x, dhat=8e-3, stiffness=1e3, check_intersections=True)
    assert every.has_intersections(x) and every(x).item() == math.inf
    t = SelfContact(f, x, dhat=8e-3, stiffness=1e3, vertex_panel_ids=ids, step_bound="additive")
    assert t.name == "panel_contact" and not t.has_intersections(x)
    fold_only = SelfContact(f[:-1], x[:n], dhat=8e-3, stiffness=1e3)
    e, g = t.value_and_grad(x)
    e0, g0 = fold_only.value_and_grad(x[:n])
    assert e.item() == pytest.approx(e0.item(), rel=1e-12) and e.item() > 0
    assert torch.allclose(g[:n], g0, rtol=0, atol=1e-12 * g0.abs().max()) and g[n:].abs().max() == 0
    g_fd = fd_grad(t, x, 1e-8)
    assert torch.linalg.norm(g - g_fd) / torch.linalg.norm(g) < 1e-5
    # the fold's top layer pushed down through the bottom one is seen, and the step bound stops before it
    down = torch.zeros_like(x)
    down[:n, 2] = torch.where(x[:n, 2] > 4e-3, -0.01, 0.0)
    assert t(x + down).item() == math.inf
    assert 0 < t.max_step(x, down) < 0.5
    # the other panel moving through the fold is not
    across = torch.zeros_like(x)
    across[n:, 2] = 0.02
    assert t.max_step(x, across) == 1.0 and math.isfinite(t(x + across).item())
    with pytest.raises(InputError, match="vertex_panel_ids"):
        SelfContact(f, x, dhat=8e-3, vertex_panel_ids=ids[:-1])
    with pytest.raises(InputError, match="not both"):
        SelfContact(f, x, dhat=8e-3, vertex_panel_ids=ids, seam_pairs=torch.tensor([[0, 1]]))


def test_the_intersection_test_is_skipped_only_along_a_cleared_step(monkeypatch) -> None:
    """ipctk's intersection test runs once per solve: not again at free positions, nor along the step that
    max_step cleared from them (any point of it, up to the bound), but wherever else the energy is asked,
    where a crossing is +inf as before."""
    from torchgarment.sim import contact as C

    calls = []
    real = C.ipctk.has_intersections
    monkeypatch.setattr(C.ipctk, "has_intersections", lambda *a: calls.append(1) or real(*a))
    x = two_triangles(3e-3)
    for method in (StepBound.ADDITIVE, StepBound.CONSERVATIVE):
        t = SelfContact(FACES2, x, dhat=DHAT, stiffness=1e3, step_bound=method)
        down = torch.zeros_like(x)
        down[3, 2] = -4e-3  # a corner of the upper triangle moved 1 mm under the lower one
        assert t.max_step(x, down) < 1.0 and calls == []  # x never tested: nothing cleared
        calls.clear()
        assert t(x).item() == 0.0 and len(calls) == 1
        assert t(x).item() == 0.0 and len(calls) == 1  # the same positions: known free
        alpha = t.max_step(x, down)
        assert 0.0 < alpha < 0.75
        for a in (0.9 * alpha, 0.5 * alpha, alpha):
            assert math.isfinite(t(x + a * down).item())
        assert len(calls) == 1  # along the cleared step: not tested
        through = x + down
        assert t(through).item() == math.inf and len(calls) == 2  # beyond the bound: tested, crossing
        aside = x.clone()
        aside[3] = torch.tensor([0.021, 0.02, -1e-3])  # off the step (it moves in x too): tested, crosses
        assert t(aside).item() == math.inf and len(calls) == 3
        calls.clear()


def test_ipc_threads_sets_and_restores_ipctk_threads() -> None:
    import ipctk

    before = ipctk.get_num_threads()
    with ipc_threads(1):
        assert ipctk.get_num_threads() == 1
    assert ipctk.get_num_threads() == before
    with pytest.raises(RuntimeError), ipc_threads(1):
        raise RuntimeError("restored on the way out")
    assert ipctk.get_num_threads() == before
    with ipc_threads(None):
        assert ipctk.get_num_threads() == before
    torch_before = torch.get_num_threads()
    other = 2 if torch_before == 1 else 1
    with ipc_threads(other, whole_process=True):  # retargeting's block: ipctk, torch and the BLAS pools
        assert torch.get_num_threads() == other and ipctk.get_num_threads() == other
    assert torch.get_num_threads() == torch_before and ipctk.get_num_threads() == before
    with ipc_threads(other):
        assert torch.get_num_threads() == torch_before
    with pytest.raises(InputError, match="positive integer"), ipc_threads(0):
        pass


def test_ipc_threads_of_the_whole_process_limit_the_blas_pools() -> None:
    """numpy's OpenBLAS kept a second core busy through a retargeting run at ``threads=1`` until the block
    limited it (``README.md``, "One thread means one core"). Run in a fresh process without the thread
    variables that the test workers set, so that the BLAS pool starts at its default (one thread per core)."""
    probe = textwrap.dedent("""
        import json
        from threadpoolctl import threadpool_info
        from torchgarment.sim.contact import ipc_threads

        def pools():
            return sorted(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")

        out = {"before": pools()}
        with ipc_threads(1, whole_process=True):
            out["inside"] = pools()
        out["after"] = pools()
        with ipc_threads(1):
            out["ipctk_only"] = pools()
        print(json.dumps(out))
    """)
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
    run = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert out["before"], "numpy's BLAS is loaded, so threadpoolctl must find its pool"
    if max(out["before"]) == 1:
        pytest.skip("every BLAS pool runs on one thread by default here (a one-core machine)")
    assert out["inside"] == [1] * len(out["before"])
    assert out["after"] == out["before"] and out["ipctk_only"] == out["before"]


def test_dtype_device_boundary_and_errors() -> None:
    x = tilted_pair()
    t = SelfContact(FACES2, two_triangles(0.01), dhat=DHAT, stiffness=1e3)
    e32, g32 = t.value_and_grad(x.float())
    e64, g64 = t.value_and_grad(x)
    assert e32.dtype == torch.float32 and g32.dtype == torch.float32
    assert t.hessian_blocks(x.float()).values.dtype == torch.float32
    assert e32.item() == pytest.approx(e64.item(), rel=1e-2)
    with pytest.raises(InputError):
        t(x[:5])
    with pytest.raises(InputError):
        SelfContact(FACES2, x, dhat=-1.0)
    with pytest.raises(InputError):
        SelfContact(FACES2, x, num_vertices=7)


# ---------------------------------------------------------------------------------------------- body contact


@pytest.fixture(scope="module")
def sphere() -> tuple[torch.Tensor, torch.Tensor]:
    s = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    return torch.as_tensor(s.vertices), torch.as_tensor(s.faces)


def patch_above(height: float) -> tuple[torch.Tensor, torch.Tensor]:
    """A 4 cm square patch, centred over the sphere top, at y = 0.1 + height (sphere radius 0.1 m)."""
    u = np.linspace(-0.02, 0.02, 9)
    X = np.stack(np.broadcast_arrays(u[:, None], np.full((9, 9), 0.1 + height), u[None, :]), -1).reshape(
        -1, 3
    )
    return torch.as_tensor(X), grid(9, 9)


def test_body_contact_sphere(sphere: tuple[torch.Tensor, torch.Tensor]) -> None:
    bv, bf = sphere
    x, f = patch_above(5e-3)
    t = BodyMeshContact(f, bv, bf, dhat=DHAT, stiffness=1e3, garment_rest_positions=x)
    assert t(x).item() == 0.0
    near, _ = patch_above(1e-3)
    e, g = t.value_and_grad(near)
    assert e.item() > 0 and g.shape == near.shape
    assert g[:, 1].sum() < 0  # the energy decreases moving up, away from the sphere
    assert t(patch_above(5e-4)[0]).item() > e.item()
    # finite differences on a few coordinates of the lowest vertices
    lo = torch.argsort(near[:, 1])[:3]
    for i in lo.tolist():
        for c in range(3):
            xp, xm = near.clone(), near.clone()
            xp[i, c] += 1e-9
            xm[i, c] -= 1e-9
            fd = (t(xp) - t(xm)).item() / 2e-9
            assert fd == pytest.approx(g[i, c].item(), rel=1e-5, abs=1e-6 * g.abs().max().item())
    hp = dense(t.hessian_blocks(near), x.shape[0])
    assert hp.shape == (3 * x.shape[0],) * 2
    assert torch.linalg.eigvalsh(hp).min() > -1e-9 * hp.abs().max()
    # pushing through the sphere is an intersection; both step bounds stop before it
    through = near.clone()
    through[:, 1] -= 0.004  # patch centre inside the sphere, its corners outside
    assert t.has_intersections(through) and t(through).item() == math.inf
    dx = through - near
    ccd = t.max_step(near, dx, StepBound.TIGHT_INCLUSION)
    cons = t.max_step(near, dx, StepBound.CONSERVATIVE)
    assert 0 < cons <= ccd < 0.25  # the patch centre (1 mm above the top) hits at alpha = 0.25
    for a in (cons, ccd):
        assert not t.has_intersections(near + a * dx)


def test_body_contact_self_pairs_filter(sphere: tuple[torch.Tensor, torch.Tensor]) -> None:
    bv, bf = sphere
    x, f = folded_sheet()
    x = x + torch.tensor([0.2, 0.0, 0.0], dtype=torch.float64)  # far from the sphere
    body_only = BodyMeshContact(f, bv, bf, dhat=8e-3, stiffness=1e3, garment_rest_positions=x)
    with_self = BodyMeshContact(
        f, bv, bf, dhat=8e-3, stiffness=1e3, garment_rest_positions=x, self_contact=True
    )
    ref = SelfContact(f, x, dhat=8e-3, stiffness=1e3)
    assert body_only(x).item() == 0.0
    assert with_self(x).item() == pytest.approx(ref(x).item(), rel=1e-12)
    assert torch.allclose(with_self.value_and_grad(x)[1], ref.value_and_grad(x)[1])
    # a sewn garment: the body term's self pairs are those of the welded SelfContact
    y, fy, seams = sewn_fold(0.001)
    y = y + torch.tensor([0.2, 0.0, 0.0], dtype=torch.float64)
    sewn = BodyMeshContact(fy, bv, bf, dhat=DHAT, stiffness=1e3, garment_rest_positions=y, self_contact=True,
                           seam_pairs=seams)
    ref = SelfContact(fy, y, dhat=DHAT, stiffness=1e3, seam_pairs=seams)
    e, g = sewn.value_and_grad(y)
    assert e.item() > 0 and e.item() == pytest.approx(ref(y).item(), rel=1e-12)
    assert torch.allclose(g, ref.value_and_grad(y)[1])
    assert torch.allclose(sewn.hessian_diagonal(y), ref.hessian_diagonal(y))
