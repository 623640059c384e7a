"""Tests of online data-driven fitting (torchgarment.datadriven.online)."""

from __future__ import annotations

import pytest
import torch

from torchgarment.datadriven.basis import ClothingBasis
from torchgarment.datadriven.dataset import BodyDataset
from torchgarment.datadriven.online import OnlineFitter, PushOutResult, push_out
from torchgarment.datadriven.pca import BodyPCA
from torchgarment.errors import InputError, MeshError
from torchgarment.structures.garment_mesh import GarmentMesh


def grid_mesh(n: int) -> GarmentMesh:
    u = torch.linspace(0.0, 0.3, n, dtype=torch.float64)
    gx, gy = torch.meshgrid(u, u, indexing="xy")
    p = torch.stack([gx.reshape(-1), gy.reshape(-1)], dim=1)
    x = torch.stack([p[:, 0], p[:, 1] + 0.9, torch.full_like(p[:, 0], 0.2)], dim=1)
    faces = [[j * n + i, j * n + i + 1, (j + 1) * n + i + 1] for j in range(n - 1) for i in range(n - 1)]
    return GarmentMesh(x, torch.tensor(faces, dtype=torch.long), p=p)


def random_basis(pca: BodyPCA, n: int, k: int, seed: int, name: str) -> ClothingBasis:
    g = torch.Generator().manual_seed(seed)
    mesh = grid_mesh(n)
    nv = n * n
    mean = mesh.x + 0.01 * torch.randn(nv, 3, generator=g, dtype=torch.float64)
    plus = mean + 0.02 * torch.randn(k, nv, 3, generator=g, dtype=torch.float64)
    minus = mean - 0.02 * torch.randn(k, nv, 3, generator=g, dtype=torch.float64)
    return ClothingBasis(mean, plus, minus, pca.sigmas[:k].clone(), mesh.with_positions(mean),
                         pca.fingerprint(),
                         f"key{seed}", name)


@pytest.fixture(scope="module")
def pca():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(10, 30, 3, generator=g, dtype=torch.float64)
    return BodyPCA.fit(BodyDataset(x, torch.tensor([[0, 1, 2]], dtype=torch.long)))


def test_online_fit_matches_basis_garments_exactly_at_basis_bodies(pca):
    bases = {"a": random_basis(pca, 4, 3, 1, "a"), "b": random_basis(pca, 5, 3, 2, "b")}
    fitter = OnlineFitter(pca, bases, interpolation="piecewise")
    bodies = [pca.mean] + [pca.sample_body(i, s) for i in range(3) for s in (1.0, -1.0)]
    w = fitter.weights(torch.stack(bodies))  # weights once per customer, (7, 3)
    out = fitter.fit(w)
    for name, b in bases.items():
        expected = torch.stack([b.mean] + [g for i in range(3) for g in (b.plus[i], b.minus[i])])
        assert torch.allclose(out[name], expected, atol=1e-12)
    lin = OnlineFitter(pca, bases, interpolation="linear")
    assert torch.allclose(lin.fit(lin.weights(pca.mean))["b"], bases["b"].mean, atol=1e-12)


def test_batched_equals_per_body_and_reference(pca):
    bases = [random_basis(pca, 4, 3, 3, "a"), random_basis(pca, 6, 3, 4, "b")]
    fitter = OnlineFitter(pca, bases, k=2)
    g = torch.Generator().manual_seed(5)
    bodies = pca.mean + 0.3 * torch.randn(6, 30, 3, generator=g, dtype=torch.float64)
    w = fitter.weights(bodies)
    assert w.shape == (6, 2) and torch.allclose(w, pca.project(bodies, 2))
    flat = fitter.fit_all(w)
    assert flat.shape == (6, 16 + 36, 3)
    per = fitter.fit(w)
    for i in range(6):
        single = fitter.fit(w[i])
        for b in bases:
            assert torch.allclose(single[b.name], per[b.name][i], atol=1e-14)
            assert torch.allclose(per[b.name][i], b.evaluate(w[i]), atol=1e-14)
    assert torch.equal(flat[:, :16], per["a"])
    only_b = fitter.fit(w, ["b"])
    assert list(only_b) == ["b"]
    assert torch.allclose(fitter.fit_all(w, chunk=1), flat, atol=1e-14)
    assert torch.allclose(fitter.fit_all(w, chunk=0), flat, atol=1e-14)
    wg = w.clone().requires_grad_(True)  # differentiable path gives the same garments and a gradient
    xg = fitter.fit_all(wg)
    assert torch.allclose(xg.detach(), flat, atol=1e-14)
    xg.sum().backward()
    assert wg.grad is not None and torch.isfinite(wg.grad).all()
    # float64 finite-difference check of d garment / d weights (away from the piecewise kink at w = 0)
    assert torch.autograd.gradcheck(lambda ww: fitter.fit_all(ww)[:, :5],
                                    (w[:2].clone().requires_grad_(True),))
    zero = OnlineFitter(pca, bases, k=0)  # k = 0: everybody gets the mean garment
    assert torch.equal(zero.fit(zero.weights(bodies))["a"], bases[0].mean.expand(6, -1, -1))
    f32 = OnlineFitter(pca, bases, k=2, dtype=torch.float32)
    assert torch.allclose(f32.fit(f32.weights(bodies))["b"].double(), per["b"], atol=1e-4)


def test_errors(pca):
    b = random_basis(pca, 4, 2, 1, "a")
    with pytest.raises(InputError, match="k must"):
        OnlineFitter(pca, [b], k=3)
    other = random_basis(pca, 4, 2, 1, "x")
    other.pca_fingerprint = "0" * 64
    with pytest.raises(InputError, match="another body model"):
        OnlineFitter(pca, [b, other])
    fitter = OnlineFitter(pca, [b])
    with pytest.raises(MeshError, match="topology"):
        fitter.weights(torch.zeros(29, 3, dtype=torch.float64))
    with pytest.raises(InputError, match="unknown garment"):
        fitter.fit(torch.zeros(2, dtype=torch.float64), ["zzz"])
    with pytest.raises(InputError, match="fitter.s k"):
        fitter.fit_all(torch.zeros(5, dtype=torch.float64))


def test_push_out_leaves_no_vertex_inside():
    """Exact distances at the garment's vertices (no SDF grid); checked with the exact winding number."""
    import numpy as np

    from torchgarment.body.anny_phenotype import body_from_phenotype
    from torchgarment.sdf import MeshProximity, SignType, winding_number

    body = body_from_phenotype({"gender": 1.0, "weight": 0.6})
    bv, bf = body.vertices.numpy(), body.faces.numpy()
    # a garment-like point set: torso vertices moved 1 cm inwards (inside) and 3 cm outwards, and points
    # 1 cm deep in the crotch and armpits' concave places
    import trimesh

    v = body.vertices
    sel = (v[:, 1] > 0.9) & (v[:, 1] < 1.3)
    torso = v[sel][::5]
    n = torch.as_tensor(np.asarray(trimesh.Trimesh(bv, bf, process=False).vertex_normals))[sel][::5]
    inward, outside = torso - 0.01 * n, torso + 0.03 * n
    x = torch.cat([inward, outside])

    def inside(points: torch.Tensor) -> np.ndarray:
        return np.abs(winding_number(points.numpy(), bv, bf, SignType.WINDING_NUMBER)) > 0.5

    assert inside(x).sum() > 0.8 * inward.shape[0]
    res = push_out(x, body.vertices, body.faces, margin=1e-3)
    # in concave places (armpits) a move can end near another part: 4 passes leave >= 0.96 of the margin
    assert inside(res.x).sum() == 0 and res.inside_after == 0 and res.min_phi >= 0.9e-3
    assert res.inside_before == int(inside(x).sum())
    d0 = MeshProximity(bv, bf).query(x.numpy())[0]
    far = torch.as_tensor(d0 > 1e-3)
    assert torch.equal(res.x[far], x[far])  # vertices beyond the margin do not move
    after = MeshProximity(bv, bf).query(res.x.numpy())[0]  # the result's distances are the exact ones
    assert abs(res.min_phi - after.min()) <= 1e-7 and res.inside_after == int((after < 0).sum())
    assert res.moved == int((~far).sum())
    # a vertex left at the margin up to rounding stays; only a real shortfall (a concave place) moves again
    again = push_out(res.x, body.vertices, body.faces, margin=1e-3)
    short = MeshProximity(bv, bf).query(res.x.numpy())[0] < 1e-3 - 1e-12
    assert again.moved == int(short.sum()) < 0.05 * res.moved
    measured = push_out(x, body.vertices, body.faces, margin=1e-3, iterations=0)  # measures only
    assert torch.equal(measured.x, x) and measured.moved == 0 and measured.inside_before == res.inside_before
    with pytest.raises(InputError):
        push_out(x, body.vertices, body.faces, margin=-1.0)


def test_push_out_settles_vertices_in_a_gap_narrower_than_twice_the_margin():
    """Between two bodies 0.4 mm apart, a 1 mm margin cannot hold: each move lands inside the other side's
    margin, or inside it; the settled vertex ends outside both, at a quarter of the gap or more."""
    import numpy as np
    import trimesh

    from torchgarment.sdf import SignType, winding_number

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    gap = 4e-4
    v = np.concatenate([sphere.vertices - [0.1 + gap / 2, 0, 0], sphere.vertices + [0.1 + gap / 2, 0, 0]])
    f = np.concatenate([sphere.faces, sphere.faces + len(sphere.vertices)])
    rng = np.random.default_rng(0)
    yz = rng.uniform(-2e-3, 2e-3, (200, 2))
    x = np.concatenate([np.column_stack([rng.uniform(-gap, gap, 200), yz]),  # in the gap, or just inside
                        np.column_stack([rng.uniform(-3e-3, -gap / 2, 200), yz])])  # inside the left one
    bv, bf = torch.as_tensor(v), torch.as_tensor(f)
    res = push_out(torch.as_tensor(x), bv, bf, margin=1e-3)
    inside = np.abs(winding_number(res.x.numpy(), v, f, SignType.WINDING_NUMBER)) > 0.5
    assert res.inside_before > 200 and res.inside_after == 0 and inside.sum() == 0
    assert res.min_phi >= gap / 4


def test_push_out_does_not_depend_on_the_bodies_before():
    """The push-out of one garment on one body gives the same result to the bit whether or not a tree of
    another body of the model was released before (a pooled tree refitted to this body would pick the other
    triangle at float32 near-ties: points between the thighs moved to the other side, 3.7 mm between a
    batched fit and the single command)."""
    import gc

    import numpy as np

    from torchgarment.body.anny_phenotype import body_from_phenotype
    from torchgarment.sdf import MeshProximity, proximity

    body = body_from_phenotype({"gender": 1.0, "weight": 0.6})
    other = body_from_phenotype({"gender": 0.0, "weight": 0.3, "height": 0.8})
    # points on and near the plane of symmetry, between the legs and inside the torso: on medial axes, where
    # the left and right sides tie
    g = np.stack(np.meshgrid(np.linspace(-0.002, 0.002, 5), np.linspace(0.3, 1.3, 101),
                             np.linspace(-0.1, 0.1, 21)), -1).reshape(-1, 3)
    x = torch.as_tensor(g)

    def run(released: bool) -> PushOutResult:
        proximity._TOPOLOGIES.clear()  # no pooled tree
        if released:
            t = MeshProximity(other.vertices.numpy(), other.faces.numpy())
            del t
            gc.collect()
        return push_out(x, body.vertices, body.faces)

    fresh, after = run(False), run(True)
    assert torch.equal(fresh.x, after.x) and fresh.moved == after.moved > 0
