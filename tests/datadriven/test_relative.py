"""Body-relative clothing coordinates (issue 15): exact round trips, rigid invariance, and a body-frame fit
that follows the customer's surface where absolute blending cannot."""

from __future__ import annotations

import math

import pytest
import torch

from torchgarment.body.frames import attach, decode, encode
from torchgarment.datadriven import BodyDataset, BodyPCA, ClothingBasis, OnlineFitter
from torchgarment.datadriven.relative import BasisFrame
from torchgarment.errors import InputError
from torchgarment.structures.garment_mesh import GarmentMesh


@pytest.fixture(scope="module")
def pca() -> BodyPCA:
    return BodyPCA.fit(BodyDataset.from_anny(5, seed=4))


def _rotation(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float64)


def test_round_trip_and_rigid_invariance(pca):
    body, faces = pca.mean, pca.faces.long()
    g = torch.Generator().manual_seed(0)
    x = body[::40] + 0.03 * torch.randn(body[::40].shape, generator=g, dtype=torch.float64)
    tri = attach(x, body, faces)
    local = encode(x, body, faces, tri)
    assert torch.allclose(decode(local, body, faces, tri), x, atol=1e-12)
    r, t = _rotation(0.7), torch.tensor([0.3, -0.1, 2.0], dtype=torch.float64)
    moved = encode(x @ r.T + t, body @ r.T + t, faces, tri)  # the frame moves with the body
    assert torch.allclose(moved, local, atol=1e-10)
    both = encode(torch.stack([x, x @ r.T + t]), torch.stack([body, body @ r.T + t]), faces, tri)  # batched
    assert torch.allclose(both[1], local, atol=1e-10)


def test_body_frame_fit_follows_the_customer(pca):
    """A garment that keeps its body-relative coordinates on every example body is fitted exactly on any
    body in the body frame, also a body moved rigidly (outside the PCA span); absolute blending is off."""
    faces = pca.faces.long()
    g = torch.Generator().manual_seed(1)
    x_mean = pca.mean[::30] + 0.02 * torch.randn(pca.mean[::30].shape, generator=g, dtype=torch.float64)
    tri = attach(x_mean, pca.mean, faces)
    local = encode(x_mean, pca.mean, faces, tri)
    k, c = 2, 1.0
    plus = torch.stack([decode(local, pca.sample_body(i, c), faces, tri) for i in range(k)])
    minus = torch.stack([decode(local, pca.sample_body(i, -c), faces, tri) for i in range(k)])
    garment = GarmentMesh(x_mean, torch.tensor([[0, 1, 2]]))
    basis = ClothingBasis(x_mean, plus, minus, c * pca.sigmas[:k].clone(), garment, pca.fingerprint(),
                          "", "g")
    shift = torch.tensor([0.1, 0.0, 0.05], dtype=torch.float64)
    customer = pca.sample_body(0, 0.6) @ _rotation(0.2).T + shift
    truth = decode(local, customer, faces, tri)
    body_fit = OnlineFitter(pca, [basis], frame=BasisFrame.BODY)
    x = body_fit.fit(body_fit.weights(customer), bodies=customer)["g"]
    assert torch.allclose(x, truth, atol=1e-9)
    batch = body_fit.fit(body_fit.weights(torch.stack([customer, pca.mean])),
                         bodies=torch.stack([customer, pca.mean]))["g"]
    assert torch.allclose(batch[0], truth, atol=1e-9) and torch.allclose(batch[1], x_mean, atol=1e-9)
    absolute = OnlineFitter(pca, [basis])
    xa = absolute.fit(absolute.weights(customer))["g"]
    assert float((xa - truth).norm(dim=1).max()) > 0.02  # blending positions cannot follow a moved body
    with pytest.raises(InputError, match="bodies"):
        body_fit.fit(body_fit.weights(customer))


def test_branch_deviation_is_zero_on_the_carried_branch_and_sees_a_moved_hem(pca):
    from torchgarment.datadriven.relative import branch_deviation

    faces = pca.faces.long()
    x_mean = pca.mean[::30].clone()
    tri = attach(x_mean, pca.mean, faces)
    local = encode(x_mean, pca.mean, faces, tri)
    plus = torch.stack([decode(local, pca.sample_body(0, 1.0), faces, tri)])
    minus = torch.stack([decode(local, pca.sample_body(0, -1.0), faces, tri)])
    hem = x_mean[:, 1] <= torch.quantile(x_mean[:, 1], 0.1)
    minus[0, hem, 2] += 0.05  # the hem swung 5 cm forward
    garment = GarmentMesh(x_mean, torch.tensor([[0, 1, 2]]))
    basis = ClothingBasis(x_mean, plus, minus, pca.sigmas[:1].clone(), garment, pca.fingerprint(), "", "g")
    dev = branch_deviation(basis, pca)
    assert dev["plus_0"]["mean_mm"] < 1e-6 and dev["plus_0"]["hem_mean_mm"] < 1e-6
    assert abs(dev["minus_0"]["hem_mean_mm"] - 50.0) < 1e-6 and dev["minus_0"]["mean_mm"] < 10.0


def test_anchor_hangs_a_supported_garment_from_the_customers_waist_plane(pca):
    """Issue 15: the waist plane (the minimum torso girth's level, where a drape puts a support's band) is a
    flat minimum that a linear blend cannot follow. With ``anchors=`` the fit moves each supported garment
    vertically, rigidly, so that its band sits over the customer's measured waist plane as the mean drape's
    band sits over the mean body's; a garment without a support is left as blended."""
    from torchgarment.sim.support import SupportLoop, waist_height

    faces = pca.faces.long()
    y_mean = waist_height(pca.mean, faces)
    g = torch.Generator().manual_seed(3)
    x_mean = pca.mean[::30] + 0.02 * torch.randn(pca.mean[::30].shape, generator=g, dtype=torch.float64)
    k, c = 2, 1.0
    plus = torch.stack([x_mean + 0.01 * torch.randn(x_mean.shape, generator=g, dtype=torch.float64)
                        for _ in range(k)])
    minus = torch.stack([x_mean - 0.01 * torch.randn(x_mean.shape, generator=g, dtype=torch.float64)
                         for _ in range(k)])
    band = torch.arange(0, x_mean.shape[0], 7)
    loop = SupportLoop(band, torch.arange(band.numel(), dtype=torch.float64), float(band.numel()), "waist")
    garment = GarmentMesh(x_mean, torch.tensor([[0, 1, 2]]))
    supported = ClothingBasis(x_mean, plus, minus, c * pca.sigmas[:k].clone(), garment, pca.fingerprint(),
                              "", "skirt", support=loop)
    free = ClothingBasis(x_mean, plus, minus, c * pca.sigmas[:k].clone(), garment, pca.fingerprint(), "",
                         "shirt")
    customers = torch.stack([pca.sample_body(0, 1.5), pca.sample_body(1, -0.8)])
    for frame in BasisFrame:
        fitter = OnlineFitter(pca, [supported, free], frame=frame)
        assert fitter.anchored_garments == ["skirt"]
        a = fitter.anchors(customers)
        assert a.shape == (2,)
        assert float(a[0]) == pytest.approx(waist_height(customers[0], faces), abs=1e-12)
        w = fitter.weights(customers)
        plain = fitter.fit(w, bodies=customers)
        anchored = fitter.fit(w, bodies=customers, anchors=a)
        assert torch.equal(anchored["shirt"], plain["shirt"])
        for i in range(2):
            d = anchored["skirt"][i] - plain["skirt"][i]
            assert float(d[:, [0, 2]].abs().max()) == 0.0  # only vertical
            assert float(d[:, 1].max() - d[:, 1].min()) < 1e-12  # rigidly
            band_y = float(anchored["skirt"][i][band, 1].mean())
            assert band_y - float(a[i]) == pytest.approx(float(x_mean[band, 1].mean()) - y_mean, abs=1e-9)
        one = fitter.fit(w[0], bodies=customers[0], anchors=a[0])["skirt"]
        assert torch.allclose(one, anchored["skirt"][0], atol=1e-12)
        with pytest.raises(InputError, match="anchors"):
            fitter.fit(w, bodies=customers, anchors=a[:1])
    # a regression basis of a supported garment is relative to the waist plane: no fit without anchors
    from dataclasses import replace

    regression = OnlineFitter(pca, [replace(supported, fit="regression"), free])
    with pytest.raises(InputError, match="anchors=fitter.anchors"):
        regression.fit(regression.weights(customers))
    assert not replace(free, fit="regression").needs_anchor
