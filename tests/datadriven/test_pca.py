"""Tests of the PCA body model (torchgarment.datadriven.pca)."""

from __future__ import annotations

import pytest
import torch

from torchgarment.datadriven.dataset import BodyDataset
from torchgarment.datadriven.pca import BodyPCA
from torchgarment.errors import InputError, MeshError


def synthetic(n: int = 12, nv: int = 50, scales=(0.3, 0.1, 0.03, 0.01), seed: int = 0, dtype=torch.float64):
    """Bodies = base + sum_j s_j z_j d_j with orthonormal directions d_j and standardized z (zero mean, unit
    sample variance), so the PCA variances are exactly s_j**2."""
    g = torch.Generator().manual_seed(seed)
    base = torch.randn(nv, 3, generator=g, dtype=torch.float64)
    q, _ = torch.linalg.qr(torch.randn(3 * nv, len(scales), generator=g, dtype=torch.float64))
    z = torch.randn(n, len(scales), generator=g, dtype=torch.float64)
    z = z - z.mean(dim=0)
    # make the score columns orthogonal with unit sample variance (exact principal axes)
    u, _, _ = torch.linalg.svd(z, full_matrices=False)
    z = u * (n - 1) ** 0.5
    s = torch.tensor(scales, dtype=torch.float64)
    x = base.reshape(-1) + (z * s) @ q.T
    faces = torch.tensor([[0, 1, 2], [1, 2, 3]], dtype=torch.long)
    return BodyDataset(x.reshape(n, nv, 3).to(dtype), faces), s**2, q


def test_full_rank_reconstruction_is_exact_on_training_set():
    ds, _, _ = synthetic(n=9, scales=(0.3, 0.2, 0.1, 0.05, 0.02, 0.01, 0.005, 0.002))
    pca = BodyPCA.fit(ds)
    assert pca.num_components == 8  # N - 1
    rec = pca.reconstruct(pca.project(ds.vertices))
    assert float((rec - ds.vertices).abs().max()) < 1e-12
    err = pca.reconstruction_error(ds.vertices)
    assert float(err["max"].max()) < 1e-12


def test_projecting_a_training_body_gives_its_own_weights():
    ds, var, _ = synthetic()
    pca = BodyPCA.fit(ds)
    w = pca.project(ds.vertices)  # (N, K)
    # the weights of the training set are its principal scores: independent SVD of the centred data
    x = ds.vertices.reshape(len(ds), -1)
    xc = x - x.mean(dim=0)
    u, s, _ = torch.linalg.svd(xc, full_matrices=False)
    scores = u[:, : pca.num_components] * s[: pca.num_components]
    signs = torch.sign((scores * w).sum(dim=0))
    assert torch.allclose(w, scores * signs, atol=1e-12)
    # a body built from given weights projects back to exactly those weights
    w0 = torch.tensor([0.2, -0.1, 0.05, 0.0], dtype=torch.float64)
    assert torch.allclose(pca.project(pca.reconstruct(w0)), w0, atol=1e-12)
    assert pca.project(ds.vertices[3]).shape == (pca.num_components,)
    assert torch.allclose(pca.project(ds.vertices[3]), w[3])


def test_components_orthonormal_and_variances():
    ds, var, q = synthetic()
    pca = BodyPCA.fit(ds)
    c = pca.components.reshape(pca.num_components, -1)
    assert torch.allclose(c @ c.T, torch.eye(pca.num_components, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(pca.variances, var, rtol=1e-10)
    assert pca.total_variance == pytest.approx(float(var.sum()), rel=1e-10)
    # each component is +- one of the generating directions
    assert torch.allclose((c @ q).abs(), torch.eye(4, dtype=torch.float64), atol=1e-9)
    assert torch.allclose(pca.sigmas, var.sqrt())


def test_k_for_variance_targets():
    ds, var, _ = synthetic(scales=(0.3, 0.1, 0.03, 0.01))
    pca = BodyPCA.fit(ds)
    ratio = var / var.sum()  # cumulative 0.891, 0.990, 0.999, 1
    cum = torch.cumsum(ratio, 0)
    assert pca.k_for_variance(0.5) == 1
    assert pca.k_for_variance(float(cum[0]) + 1e-6) == 2
    assert pca.k_for_variance(0.95) == 2
    assert pca.k_for_variance(0.99) == 2
    assert pca.k_for_variance(0.995) == 3
    assert pca.k_for_variance(0.9995) == 4
    assert pca.k_for_variance(1.0) == 4
    with pytest.raises(InputError):
        pca.k_for_variance(0.0)
    with pytest.raises(InputError):
        pca.k_for_variance(1.5)


def test_truncated_reconstruction_error_decreases_with_k():
    ds, _, _ = synthetic()
    pca = BodyPCA.fit(ds)
    errs = [float(pca.reconstruction_error(ds.vertices, k)["mean"].mean()) for k in range(5)]
    assert all(a > b for a, b in zip(errs[:-1], errs[1:]))
    assert errs[-1] < 1e-12


def test_save_load_fingerprint_and_dtype(tmp_path):
    ds, _, _ = synthetic()
    pca = BodyPCA.fit(ds, max_components=3)
    assert pca.num_components == 3
    pca.save(tmp_path / "pca.pt")
    back = BodyPCA.load(tmp_path / "pca.pt")
    assert back.fingerprint() == pca.fingerprint()
    assert torch.equal(back.components, pca.components)
    f32 = BodyPCA.load(tmp_path / "pca.pt", dtype=torch.float32)
    assert f32.mean.dtype == torch.float32
    w = f32.project(ds.vertices[0])
    assert w.dtype == torch.float32 and torch.allclose(w.double(), pca.project(ds.vertices[0]), atol=1e-5)
    pca32 = BodyPCA.fit(ds.to(dtype=torch.float32))
    assert pca32.components.dtype == torch.float32
    assert torch.allclose(pca32.variances[:3].double(), pca.variances, rtol=1e-3)
    with pytest.raises(InputError, match="not a torchgarment PCA"):
        torch.save({"x": 1}, tmp_path / "bad.pt")
        BodyPCA.load(tmp_path / "bad.pt")
    with pytest.raises(InputError, match="does not exist"):
        BodyPCA.load(tmp_path / "missing.pt")


def test_other_topology_is_a_clear_error():
    ds, _, _ = synthetic()
    pca = BodyPCA.fit(ds)
    with pytest.raises(MeshError, match="topology"):
        pca.project(torch.zeros(49, 3, dtype=torch.float64))
    with pytest.raises(InputError):
        BodyPCA.fit(ds.subset([0]))


def test_anny_bodies_pca():
    ds = BodyDataset.from_anny(10, seed=5)
    pca = BodyPCA.fit(ds)
    assert pca.num_components == 9 and pca.topology == "anny-noeyes-notongue"
    k95 = pca.k_for_variance(0.95)
    assert 1 <= k95 <= pca.k_for_variance(0.99) <= 9
    rec = pca.reconstruct(pca.project(ds.vertices))
    assert float((rec - ds.vertices).abs().max()) < 1e-9
