"""Tests of the sparse narrow-band body SDF (torchgarment.sdf)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from torchgarment.body.body import Body
from torchgarment.errors import InputError, MeshError
from torchgarment.sdf import BodySDF, SDFSettings, SignType, exact_signed_distance
from torchgarment.sdf.build import is_closed

R = 0.1  # sphere radius, metres
SMALL = SDFSettings(voxel_size=0.005, brick=4)  # band = max(2 cm, 2.17 cm)


@pytest.fixture(scope="module")
def sphere():
    m = trimesh.creation.icosphere(subdivisions=4, radius=R)
    return np.asarray(m.vertices), np.asarray(m.faces)


@pytest.fixture(scope="module")
def sphere_sdf(sphere):
    return BodySDF.from_mesh(*sphere, SMALL)


def _band_points(v, n, width, seed=0):
    rng = np.random.default_rng(seed)
    return v[rng.integers(0, len(v), n)] + rng.uniform(-width, width, size=(n, 3))


def _errors(sdf, v, f, pts):
    ex = exact_signed_distance(pts, v, f, SignType.WINDING_NUMBER)
    phi = sdf(torch.as_tensor(pts, dtype=sdf.dtype)).double().numpy()
    return ex, phi


def test_settings_validation():
    assert SDFSettings().band == 0.02
    assert SDFSettings(voxel_size=0.005).band == pytest.approx(0.5 * np.sqrt(3) * 9 * 0.005)
    with pytest.raises(InputError):
        SDFSettings(band=0.005)
    with pytest.raises(InputError):
        SDFSettings(voxel_size=-1.0)
    with pytest.raises(InputError):
        SDFSettings(brick=1)


def test_sphere_accuracy_and_gradient_norm(sphere, sphere_sdf):
    v, f = sphere
    pts = _band_points(v, 4000, 0.02)
    ex, phi = _errors(sphere_sdf, v, f, pts)
    band = np.abs(ex) <= sphere_sdf.band
    assert band.sum() > 3000
    err = np.abs(phi - ex)[band]
    assert err.max() < 2e-4  # 0.2 mm at 5 mm voxels on a smooth surface
    _, grad = sphere_sdf.value_and_gradient(torch.as_tensor(pts))
    gn = grad.norm(dim=-1).numpy()[band]
    assert np.abs(gn - 1).max() < 0.05
    # Gradient points away from the centre.
    cos = (grad.numpy() * pts).sum(1) / (grad.norm(dim=-1).numpy() * np.linalg.norm(pts, axis=1))
    assert cos[band].min() > 0.98


def test_far_field_sign_and_outside_box(sphere, sphere_sdf):
    v, f = sphere
    rng = np.random.default_rng(1)
    lo, hi = sphere_sdf.bounds.numpy()
    pts = rng.uniform(lo, hi, size=(3000, 3))
    ex, phi = _errors(sphere_sdf, v, f, pts)
    assert (np.sign(phi) == np.sign(ex))[np.abs(ex) > 1e-3].all()
    far = np.abs(ex) > sphere_sdf.band
    bound = 0.5 * np.sqrt(3) * (SMALL.brick + 1) * SMALL.voxel_size
    assert np.abs(phi - ex)[far].max() <= bound
    # Outside the grid box: continuous upper estimate phi(p) + |x - p|.
    x = torch.tensor([[1.0, 0.0, 0.0], [0.0, -2.0, 0.5], [3.0, 3.0, 3.0]], dtype=torch.float64)
    ex_out = exact_signed_distance(x.numpy(), v, f)
    phi_out = sphere_sdf(x).numpy()
    assert (phi_out >= ex_out - 1e-3).all() and (phi_out <= ex_out * 1.1).all()


def _off_face_points(sdf, n, seed):
    """Points in the band whose local cell coordinates stay 0.1 voxel away from cell faces."""
    rng = np.random.default_rng(seed)
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    x = dirs * (R + rng.uniform(-0.015, 0.015, size=(n, 1)))
    h = sdf.voxel_size
    o = sdf.origin.numpy()
    u = (x - o) / h
    u = np.floor(u) + 0.1 + 0.8 * (u - np.floor(u))
    return torch.tensor(o + u * h, dtype=torch.float64)


def test_gradcheck_fine_coarse_and_outside(sphere_sdf):
    x = _off_face_points(sphere_sdf, 20, 2).requires_grad_(True)
    assert torch.autograd.gradcheck(sphere_sdf, (x,), eps=1e-6, atol=1e-6)
    # Far field (coarse cells near the centre) and outside the box.
    y = torch.tensor([[0.011, -0.013, 0.017], [0.9, 0.2, -0.1], [0.03, 1.5, 2.2]], dtype=torch.float64,
                     requires_grad=True)
    assert torch.autograd.gradcheck(sphere_sdf, (y,), eps=1e-6, atol=1e-6)


def test_value_and_gradient_matches_autograd(sphere_sdf):
    rng = np.random.default_rng(3)
    x = torch.tensor(rng.uniform(-0.4, 0.4, size=(500, 3)), dtype=torch.float64, requires_grad=True)
    phi = sphere_sdf(x)
    (g_auto,) = torch.autograd.grad(phi.sum(), x)
    phi2, g = sphere_sdf.value_and_gradient(x.reshape(25, 20, 3))
    assert phi2.shape == (25, 20) and g.shape == (25, 20, 3) and not g.requires_grad
    torch.testing.assert_close(phi2.reshape(-1), phi.detach(), rtol=0, atol=1e-14)
    torch.testing.assert_close(g.reshape(-1, 3), g_auto, rtol=1e-10, atol=1e-10)


def test_float32_and_dtype_move(sphere_sdf):
    sdf32 = BodySDF(sphere_sdf.to_data(), dtype=torch.float32)
    x = _off_face_points(sphere_sdf, 100, 4)
    phi64 = sphere_sdf(x)
    phi32 = sdf32(x.float())
    assert phi32.dtype == torch.float32
    assert (phi32.double() - phi64).abs().max() < 1e-6
    moved = BodySDF(sphere_sdf.to_data()).to(dtype=torch.float32)
    assert moved.dtype == torch.float32 and moved.brick_index.dtype == torch.int64
    assert (moved(x.float()).double() - phi64).abs().max() < 1e-6


def test_open_mesh_sign():
    m = trimesh.creation.icosphere(subdivisions=4, radius=R)
    keep = m.vertices[m.faces].mean(axis=1)[:, 2] < 0.7 * R  # cut a hole in the top
    v, f = np.asarray(m.vertices), np.asarray(m.faces[keep])
    assert not is_closed(f)
    sdf = BodySDF.from_mesh(v, f, SMALL)
    rng = np.random.default_rng(5)
    dirs = rng.normal(size=(2000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dirs = dirs[dirs[:, 2] < 0.3]  # away from the hole
    r = rng.uniform(0.3 * R, 1.6 * R, size=(len(dirs), 1))
    pts = dirs * r
    phi = sdf(torch.as_tensor(pts)).numpy()
    clear = np.abs(r[:, 0] - R) > 2e-3
    assert (np.sign(phi) == np.where(r[:, 0] < R, -1, 1))[clear].all()
    ex = exact_signed_distance(pts, v, f, SignType.WINDING_NUMBER)
    near = np.abs(ex) <= sdf.band
    assert np.abs(phi - ex)[near].max() < 2e-4


def test_self_intersecting_spheres_sign():
    a = trimesh.creation.icosphere(subdivisions=4, radius=R)
    v = np.concatenate([a.vertices - [0.06, 0, 0], a.vertices + [0.06, 0, 0]])
    f = np.concatenate([a.faces, a.faces + len(a.vertices)])
    assert is_closed(f)
    sdf = BodySDF.from_mesh(v, f, SMALL)
    rng = np.random.default_rng(6)
    pts = rng.uniform(-0.2, 0.2, size=(6000, 3))
    d = np.minimum(np.linalg.norm(pts + [0.06, 0, 0], axis=1), np.linalg.norm(pts - [0.06, 0, 0], axis=1)) - R
    phi = sdf(torch.as_tensor(pts)).numpy()
    clear = np.abs(d) > 2e-3
    assert (np.sign(phi) == np.sign(d))[clear].all()
    # The overlap region (winding number 2) is inside.
    assert (sdf(torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.05, 0.0]], dtype=torch.float64)) < 0).all()
    ex = exact_signed_distance(pts, v, f, SignType.WINDING_NUMBER)
    err = np.abs(phi - ex)[np.abs(ex) <= sdf.band]
    # Larger error only at the crease where the spheres cross (the distance field has a kink there).
    h = SMALL.voxel_size
    assert err.mean() < 0.02 * h and np.percentile(err, 99) < 0.25 * h and err.max() < 0.5 * h


def test_bad_meshes():
    v = np.random.default_rng(0).normal(size=(10, 3))
    with pytest.raises(MeshError):
        BodySDF.from_mesh(v, np.zeros((0, 3), dtype=np.int64), SMALL)
    v_nan = v.copy()
    v_nan[3, 1] = np.nan
    with pytest.raises(MeshError):
        BodySDF.from_mesh(v_nan, np.array([[0, 1, 2], [2, 3, 4]]), SMALL)
    with pytest.raises(MeshError):
        BodySDF.from_mesh(v, np.array([[0, 1, 12]]), SMALL)
    with pytest.raises(MeshError):
        BodySDF.from_mesh(np.zeros((0, 3)), np.array([[0, 1, 2]]), SMALL)


def test_bad_queries(sphere_sdf):
    with pytest.raises(InputError):
        sphere_sdf(torch.zeros(4, 2, dtype=torch.float64))


def test_save_load_roundtrip(sphere_sdf, tmp_path):
    p = tmp_path / "sub" / "sphere.npz"
    sphere_sdf.save(p)
    assert [q.name for q in p.parent.iterdir()] == ["sphere.npz"]  # no temporary left behind
    back = BodySDF.load(p)
    x = _off_face_points(sphere_sdf, 200, 7)
    torch.testing.assert_close(back(x), sphere_sdf(x), rtol=0, atol=0)
    assert back.band == sphere_sdf.band and back.voxel_size == sphere_sdf.voxel_size
    bad = tmp_path / "bad.npz"
    np.savez(bad, foo=np.zeros(3))
    with pytest.raises(InputError):
        BodySDF.load(bad)


def test_from_body(sphere):
    v, f = sphere
    body = Body(vertices=torch.as_tensor(v, dtype=torch.float32), faces=torch.as_tensor(f, dtype=torch.int64))
    sdf = BodySDF.from_body(body, SMALL)
    assert sdf.dtype == torch.float32 and sdf.device == body.device
    phi = sdf(torch.tensor([[0.0, R - 0.005, 0.0], [0.0, 0.0, R + 0.01]]))
    assert phi.tolist() == pytest.approx([-0.005, 0.01], abs=2e-4)
    assert sdf(torch.zeros(1, 3)).item() < -0.05  # far field: sign right, magnitude approximate


def _real_body_check(garmentcode_dir, voxel, brick, n=20000):
    m = trimesh.load(garmentcode_dir / "bodies" / "mean_female.obj", process=False)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    sdf = BodySDF.from_mesh(v, f, SDFSettings(voxel_size=voxel, brick=brick))
    assert sdf.num_bricks < np.prod(sdf.shape)  # sparse
    pts = _band_points(v, n, sdf.band, seed=11)
    ex = exact_signed_distance(pts, v, f, SignType.WINDING_NUMBER)
    phi, grad = sdf.value_and_gradient(torch.as_tensor(pts))
    phi = phi.numpy()
    band = np.abs(ex) <= sdf.band
    err = np.abs(phi - ex)[band]
    gn = grad.norm(dim=-1).numpy()[band]
    return sdf, err, gn


def test_real_body_coarse(garmentcode_dir):
    h = 0.01
    sdf, err, gn = _real_body_check(garmentcode_dir, h, 4, n=10000)
    # Scaled tolerances: at 1 cm voxels fingers and creases are a few voxels wide (see the slow 2.5 mm test).
    assert err.mean() < 0.05 * h and np.percentile(err, 99) < 0.3 * h and err.max() < 0.6 * h
    assert np.median(np.abs(gn - 1)) < 0.02 and np.percentile(gn, 5) > 0.7


@pytest.mark.slow
def test_real_body_2p5mm(garmentcode_dir):
    sdf, err, gn = _real_body_check(garmentcode_dir, 0.0025, 8)
    assert err.mean() < 1e-4 and np.percentile(err, 99) < 5e-4 and err.max() < 1.25e-3
    assert np.median(np.abs(gn - 1)) < 0.01 and np.percentile(gn, 5) > 0.8


@pytest.mark.slow
def test_real_body_1p75mm_within_1mm(garmentcode_dir):
    # The acceptance bound (1 mm everywhere in the band) needs voxels below 2 mm: the worst points sit
    # in concave creases (armpit, between the legs), where the distance field has a kink that trilinear
    # interpolation rounds off by about 0.45 voxel (2.5 mm: 1.18 mm, see test_real_body_2p5mm; 2 mm: 1.01 mm).
    sdf, err, gn = _real_body_check(garmentcode_dir, 0.00175, 8, n=50000)
    assert err.max() < 1e-3 and np.percentile(err, 99) < 4e-4
    assert np.median(np.abs(gn - 1)) < 0.01


# ---------------------------------------------------------------------------------------------- fast sampling
def _reference_sample(sdf, x):
    """The straightforward sampler (separate fine / coarse lookups, one gather per corner) as ground truth."""
    h, B = sdf.voxel_size, sdf.brick
    nb = sdf.brick_index.shape
    n_fine = torch.tensor([n * B for n in nb], dtype=x.dtype)
    u = (x - sdf.origin) / h
    uc = torch.minimum(torch.clamp(u, min=0.0), n_fine)
    off = (u - uc) * h
    sq = (off * off).sum(-1)
    outside = sq > 0
    dist = torch.where(outside, torch.sqrt(torch.where(outside, sq, torch.ones_like(sq))),
                       torch.zeros_like(sq))
    cell = torch.minimum(torch.floor(uc), n_fine - 1).long()
    bc = torch.div(cell, B, rounding_mode="floor")
    loc = cell - bc * B
    bid = sdf.brick_index[bc[:, 0], bc[:, 1], bc[:, 2]]
    fine = bid >= 0
    bricks = sdf.bricks[bid.clamp(min=0)]  # (N, B+1, B+1, B+1)
    r = torch.arange(len(x))

    def interp(corner, t):
        c = {(i, j, k): corner(i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1)}
        tx, ty, tz = t.unbind(-1)
        c00 = c[0, 0, 0] + (c[0, 0, 1] - c[0, 0, 0]) * tz
        c01 = c[0, 1, 0] + (c[0, 1, 1] - c[0, 1, 0]) * tz
        c10 = c[1, 0, 0] + (c[1, 0, 1] - c[1, 0, 0]) * tz
        c11 = c[1, 1, 0] + (c[1, 1, 1] - c[1, 1, 0]) * tz
        c0, c1 = c00 + (c01 - c00) * ty, c10 + (c11 - c10) * ty
        d0 = (c[0, 0, 1] - c[0, 0, 0]) + ((c[0, 1, 1] - c[0, 1, 0]) - (c[0, 0, 1] - c[0, 0, 0])) * ty
        d1 = (c[1, 0, 1] - c[1, 0, 0]) + ((c[1, 1, 1] - c[1, 1, 0]) - (c[1, 0, 1] - c[1, 0, 0])) * ty
        dy = (c01 - c00) + ((c11 - c10) - (c01 - c00)) * tx
        return c0 + (c1 - c0) * tx, torch.stack([c1 - c0, dy, d0 + (d1 - d0) * tx], -1)

    pf, gf = interp(lambda i, j, k: bricks[r, loc[:, 0] + i, loc[:, 1] + j, loc[:, 2] + k], uc - cell)
    pc, gc = interp(lambda i, j, k: sdf.coarse[bc[:, 0] + i, bc[:, 1] + j, bc[:, 2] + k], uc / B - bc)
    phi = torch.where(fine, pf, pc) + dist
    grad = torch.where(fine[:, None], gf / h, gc / (B * h))
    grad = torch.where((u >= 0) & (u <= n_fine), grad, torch.zeros_like(grad))
    grad = grad + torch.where(outside[:, None], off / dist.clamp(min=torch.finfo(x.dtype).tiny)[:, None], 0.0)
    return phi, grad


@pytest.mark.parametrize("brick", [4, 3])
def test_fast_sampler_matches_reference(sphere, sphere_sdf, brick, mixed_points):
    sdf = sphere_sdf if brick == 4 else BodySDF.from_mesh(*sphere, SDFSettings(voxel_size=0.005, brick=3))
    assert sdf.num_bricks < np.prod(sdf.shape)  # both fine and coarse cells are sampled
    pts = mixed_points(sdf, 3000, 8)
    for dtype, tol in ((torch.float64, 1e-15), (torch.float32, 1e-6)):
        s = BodySDF(sdf.to_data(), dtype=dtype)
        x = torch.as_tensor(pts, dtype=dtype)
        phi, grad = s.value_and_gradient(x)
        phi_ref, grad_ref = _reference_sample(s, x)
        assert phi.dtype == dtype and grad.dtype == dtype
        torch.testing.assert_close(phi, phi_ref, rtol=0, atol=tol)
        torch.testing.assert_close(grad, grad_ref, rtol=0, atol=tol * 100)
        torch.testing.assert_close(s(x), phi_ref, rtol=0, atol=tol)
        # All inside the box (the far-field term is skipped then) gives the same values.
        inner = x[:3000]
        lo, hi = s.bounds
        assert ((inner > lo) & (inner < hi)).all()
        torch.testing.assert_close(s.value_and_gradient(inner)[1], grad_ref[:3000], rtol=0, atol=tol * 100)


def test_blocked_queries(sphere_sdf, monkeypatch, mixed_points):
    from torchgarment.sdf import grid

    x = torch.as_tensor(mixed_points(sphere_sdf, 1000, 11))
    phi, grad = sphere_sdf.value_and_gradient(x)
    monkeypatch.setattr(grid, "_BLOCK", 700)  # 3250 points -> 5 blocks, the last one partial
    phi_b, grad_b = sphere_sdf.value_and_gradient(x)
    assert torch.equal(phi, phi_b) and torch.equal(grad, grad_b) and grad_b.is_contiguous()
    assert torch.equal(sphere_sdf(x), phi)
    xr = x.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(sphere_sdf(xr).sum(), xr)
    assert torch.equal(g, grad)


def test_forward_autograd_first_order_only(sphere_sdf):
    x = _off_face_points(sphere_sdf, 50, 9).requires_grad_(True)
    phi = sphere_sdf(x)
    (g,) = torch.autograd.grad(phi.square().sum(), x, create_graph=False)
    _, g_ref = sphere_sdf.value_and_gradient(x)
    torch.testing.assert_close(g, 2 * phi.detach()[:, None] * g_ref, rtol=1e-12, atol=1e-14)
    # A float32 query on a float64 SDF: the gradient flows back through the cast.
    x32 = x.detach().float().requires_grad_(True)
    (g32,) = torch.autograd.grad(sphere_sdf(x32).sum(), x32)
    assert g32.dtype == torch.float32 and (g32.double() - g_ref).abs().max() < 1e-3
    # Second derivatives are not provided: asking for them fails loudly instead of returning zeros.
    (g2,) = torch.autograd.grad(sphere_sdf(x).sum(), x, create_graph=True)
    with pytest.raises(RuntimeError):
        torch.autograd.grad(g2.sum(), x)


def test_non_finite_queries(sphere_sdf):
    for bad in (float("nan"), float("inf")):
        x = torch.zeros(10, 3, dtype=torch.float64)
        x[4, 1] = bad
        with pytest.raises(InputError):
            sphere_sdf(x)
        with pytest.raises(InputError):
            sphere_sdf.value_and_gradient(x)


def test_buffers_move_and_state(sphere_sdf):
    s = BodySDF(sphere_sdf.to_data()).to(dtype=torch.float32)
    assert s.nodes.dtype == torch.float32 and s.cell_base.dtype == torch.int32
    assert s.bricks.dtype == torch.float32
    assert s.bricks.data_ptr() == s.nodes.data_ptr()  # a view, no second copy
    assert set(s.state_dict()) == {"origin", "coarse", "brick_index", "nodes"}
    np.testing.assert_array_equal(s.to_data().bricks, sphere_sdf.to_data().bricks.astype(np.float32))


# ---------------------------------------------------------------------------------------------- disk cache
def test_sdf_cache(sphere, tmp_path, monkeypatch, mixed_points):
    from torchgarment.sdf import cache as sdf_cache

    v, f = sphere
    calls = []
    real_build = sdf_cache.build_sdf_grid
    monkeypatch.setattr(sdf_cache, "build_sdf_grid", lambda *a: calls.append(1) or real_build(*a))
    a = BodySDF.cached(v, f, SMALL, cache_dir=tmp_path)
    b = BodySDF.cached(torch.as_tensor(v), torch.as_tensor(f), SMALL, cache_dir=tmp_path)
    assert len(calls) == 1 and len(list(tmp_path.glob("*.npz"))) == 1
    # the entry's path, as the batch runner ships it to other machines
    entry = sdf_cache.sdf_cache_path(v, torch.as_tensor(f), SMALL, cache_dir=tmp_path)
    assert [entry] == list(tmp_path.glob("*.npz"))
    x = mixed_points(a, 500, 10)
    x = torch.as_tensor(x)
    assert torch.equal(a(x), b(x)) and torch.equal(a.value_and_gradient(x)[1], b.value_and_gradient(x)[1])
    fresh = BodySDF.from_mesh(v, f, SMALL)
    assert torch.equal(fresh(x), b(x))
    c32 = BodySDF.cached(v, f, SMALL, cache_dir=tmp_path, dtype=torch.float32)
    assert len(calls) == 1 and c32.dtype == torch.float32
    # Keys depend on the settings that change the grid and on the mesh, not on the thread count.
    key = sdf_cache.sdf_cache_key(v, f, SMALL)
    assert key != sdf_cache.sdf_cache_key(v, f, SDFSettings(voxel_size=0.005, brick=4, band=0.025))
    assert key != sdf_cache.sdf_cache_key(v, f, SDFSettings(voxel_size=0.004, brick=4))
    assert key != sdf_cache.sdf_cache_key(v, f,
                                          SDFSettings(voxel_size=0.005, brick=4, sign_type="pseudonormal"))
    assert key != sdf_cache.sdf_cache_key(v * (1 + 1e-12), f, SMALL)
    assert key == sdf_cache.sdf_cache_key(v.astype(np.float64), f.astype(np.int32),
                                          SDFSettings(voxel_size=0.005, brick=4, workers=1))
    # A corrupt entry is rebuilt.
    entry = tmp_path / f"{key}.npz"
    entry.write_bytes(entry.read_bytes()[:1000])
    d = BodySDF.cached(v, f, SMALL, cache_dir=tmp_path)
    assert len(calls) == 2 and torch.equal(d(x), a(x))
    # Default folder: $TORCHGARMENT_CACHE/sdf.
    monkeypatch.setenv("TORCHGARMENT_CACHE", str(tmp_path / "root"))
    BodySDF.cached(v, f, SMALL)
    assert (tmp_path / "root" / "sdf" / f"{key}.npz").is_file()
