"""The Warp kernels of BodySDF's CPU queries (torchgarment.sdf.grid_kernels) against the torch path."""

from __future__ import annotations

import copy
import pickle
import threading

import numpy as np
import pytest
import torch
import trimesh

from torchgarment.sdf import BodySDF, SDFSettings, grid_kernels

R = 0.1  # sphere radius, metres: the SPHERE_RADIUS that tests/sdf/conftest.py's points probe


@pytest.fixture(scope="module")
def sphere_data():
    m = trimesh.creation.icosphere(subdivisions=4, radius=R)
    return BodySDF.from_mesh(np.asarray(m.vertices), np.asarray(m.faces),
                             SDFSettings(voxel_size=0.005, brick=4)).to_data()


def _pair(data, dtype, sampling):
    sdf = BodySDF(data, dtype=dtype).with_sampling(sampling)
    ref = sdf.with_sampling(sampling)
    ref.use_kernels = False
    return sdf, ref


@pytest.mark.parametrize("sampling", ["trilinear", "quadratic"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_kernels_match_the_torch_path(sphere_data, dtype, sampling, mixed_points):
    """Values and gradients of the kernels equal the torch path's: bit for bit for trilinear float64 in the
    grid box, within a few units in the last place otherwise (torch groups its sums over the 8 quadratic
    samples and the far field's distance differently depending on the batch; see the module docstring)."""
    sdf, ref = _pair(sphere_data, dtype, sampling)
    assert grid_kernels.supported(sdf, sdf.origin) and sdf.num_bricks < np.prod(sdf.shape)
    x = torch.as_tensor(mixed_points(sdf, 2000, 3), dtype=dtype)
    phi, grad = sdf.value_and_gradient(x)
    phi_ref, grad_ref = ref.value_and_gradient(x)
    assert phi.dtype == dtype and grad.shape == (x.shape[0], 3) and grad.is_contiguous()
    if dtype == torch.float64 and sampling == "trilinear":  # in the box (outside, torch groups the distance)
        lo, hi = sdf.bounds
        box = ((x >= lo) & (x <= hi)).all(1)
        assert 0 < int(box.sum()) < x.shape[0]
        assert torch.equal(phi[box], phi_ref[box]) and torch.equal(grad[box], grad_ref[box])
    eps = torch.finfo(dtype).eps
    scale = float(phi_ref.abs().max())
    torch.testing.assert_close(phi, phi_ref, rtol=0, atol=8 * eps * scale)
    # the quadratic gradient divides sums of O(phi) terms by the voxel: its round-off is phi / h times eps
    gscale = scale / sdf.voxel_size if sampling == "quadratic" else 1.0
    torch.testing.assert_close(grad, grad_ref, rtol=0, atol=8 * eps * gscale)
    torch.testing.assert_close(sdf(x), phi_ref, rtol=0, atol=8 * eps * scale)
    # autograd through the same query
    xr = x[:200].clone().requires_grad_(True)
    (g,) = torch.autograd.grad(sdf(xr).sum(), xr)
    assert torch.equal(g, grad[:200])


@pytest.mark.parametrize("sampling", ["trilinear", "quadratic"])
def test_kernels_are_batch_invariant(sphere_data, sampling, mixed_points):
    """A point's value does not depend on the points queried with it (the lazy barrier queries changing
    subsets of a garment's vertices)."""
    sdf, _ = _pair(sphere_data, torch.float64, sampling)
    x = torch.as_tensor(mixed_points(sdf, 300, 5))
    phi, grad = sdf.value_and_gradient(x)
    for i in (0, 7, 301, 650, x.shape[0] - 1):
        p1, g1 = sdf.value_and_gradient(x[i:i + 1])
        assert torch.equal(p1, phi[i:i + 1]) and torch.equal(g1, grad[i:i + 1])
    p2, g2 = sdf.value_and_gradient(x[5:38])
    assert torch.equal(p2, phi[5:38]) and torch.equal(g2, grad[5:38])


def test_kernels_empty_pickled_moved_and_unsupported(sphere_data, mixed_points):
    """An empty query; a queried SDF pickles and deep-copies (without its Warp arrays) and queries the same
    afterwards; a dtype move rebuilds the kernels' constants; grids the kernels do not serve (a brick edge
    that is not a power of two) take the torch path."""
    sdf, _ = _pair(sphere_data, torch.float64, "quadratic")
    phi, grad = sdf.value_and_gradient(torch.zeros(0, 3, dtype=torch.float64))
    assert phi.shape == (0,) and grad.shape == (0, 3)
    x = torch.as_tensor(mixed_points(sdf, 100, 6))
    before = sdf.value_and_gradient(x)[0]
    for twin in (pickle.loads(pickle.dumps(sdf)), copy.deepcopy(sdf)):
        assert twin.sampling is sdf.sampling and torch.equal(twin.value_and_gradient(x)[0], before)
    old = copy.copy(sdf)  # an SDF pickled before the kernels existed has no use_kernels of its own
    old.__dict__ = {k: v for k, v in sdf.__dict__.items() if k not in ("use_kernels", "_warp_constants")}
    assert old.use_kernels and torch.equal(old.value_and_gradient(x)[0], before)
    sdf.to(dtype=torch.float32)
    after = sdf.value_and_gradient(x.float())[0]
    assert after.dtype == torch.float32
    torch.testing.assert_close(after.double(), before, rtol=0, atol=1e-5)
    m = trimesh.creation.icosphere(subdivisions=3, radius=R)
    odd = BodySDF.from_mesh(np.asarray(m.vertices), np.asarray(m.faces),
                            SDFSettings(voxel_size=0.005, brick=3))
    assert not grid_kernels.supported(odd, odd.origin)
    assert odd.value_and_gradient(odd.origin[None])[0].shape == (1,)


def test_kernels_under_threads(sphere_data, mixed_points):
    """Two views of one SDF (sharing its recorded launches) queried from 4 threads give the serial results."""
    tri, _ = _pair(sphere_data, torch.float64, "trilinear")
    quad = tri.with_sampling("quadratic")
    xs = [torch.as_tensor(mixed_points(tri, 200, 10 + k)) for k in range(4)]
    expect = [(tri.value_and_gradient(x), quad.value_and_gradient(x)) for x in xs]
    errors: list[str] = []

    def work(k: int) -> None:
        for _ in range(30):
            got = (tri.value_and_gradient(xs[k]), quad.value_and_gradient(xs[k]))
            for (p, g), (pe, ge) in zip(got, expect[k], strict=True):
                if not (torch.equal(p, pe) and torch.equal(g, ge)):
                    errors.append(f"thread {k}")

    threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
