"""The adjustment objective (Wang 2018 Eq. 17): composition, zero at the base state, gradients through the
parametrization, preconditioner Hessian, initialization objective."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from torchgarment.adjust.objective import TERM_NAMES, AdjustObjective, CostWeights
from torchgarment.adjust.parametrization import BoundaryParametrization
from torchgarment.adjust.transfer import transfer_deformation
from torchgarment.body.body import Body
from torchgarment.body.size_chart import chart_row
from torchgarment.errors import InputError
from torchgarment.pattern.library import draft
from torchgarment.pattern.meshing import mesh_pattern
from torchgarment.testing import check_gradient

_CACHE: dict = {}


class ShiftedSphereSDF(torch.nn.Module):
    """A smooth stand-in SDF (the body SDF's trilinear gradient jumps across voxels, bad for FD checks)."""

    def __init__(self, radius: float) -> None:
        super().__init__()
        self.radius = radius

    def forward(self, x):
        return (x - torch.tensor([0.0, 0.9, 0.0], dtype=x.dtype)).norm(dim=-1) - self.radius


def setup():
    if "mesh" not in _CACHE:
        body = Body.from_size("12")
        mesh = mesh_pattern(draft("straight_skirt", chart_row("12")), 0.05)
        # a bent stand-in for the draped base garment: the placed panels pushed onto a cylinder
        x = mesh.x.clone()
        ang = torch.atan2(x[:, 2], x[:, 0])
        x = torch.stack([0.2 * torch.cos(ang), x[:, 1], 0.2 * torch.sin(ang)], 1) + 0.03 * (x - x.mean(0))
        _CACHE.update(body=body, mesh=mesh.with_positions(x), P=BoundaryParametrization(mesh))
    return _CACHE["body"], _CACHE["mesh"], _CACHE["P"]


def scaled(body: Body, s: float) -> Body:
    c = torch.tensor([0.0, 0.9, 0.0], dtype=torch.float64)
    return replace(body, vertices=(body.vertices - c) * s + c)


def objective(target_scale: float = 1.0, weights: CostWeights | None = None) -> AdjustObjective:
    body, mesh, P = setup()
    target = body if target_scale == 1.0 else scaled(body, target_scale)
    return AdjustObjective(mesh, body, target, P, weights, base_sdf=ShiftedSphereSDF(0.15),
                           target_sdf=ShiftedSphereSDF(0.15 * target_scale))


def test_zero_at_base_state():
    _, mesh, P = setup()
    obj = objective()
    vals = obj.term_values(mesh.x, P(P.initial()))
    assert set(vals) == set(TERM_NAMES)
    assert all(abs(v) < 1e-20 for v in vals.values()), vals
    assert float(obj(mesh.x, mesh.p)) < 1e-20


def test_total_is_sum_of_terms_and_gradients():
    _, mesh, P = setup()
    obj = objective(1.04)
    g = torch.Generator().manual_seed(0)
    x = mesh.x + 0.005 * torch.randn(mesh.x.shape, generator=g, dtype=torch.float64)
    q = P.initial() + 0.003 * torch.randn(P.initial().shape, generator=g, dtype=torch.float64)
    p = P(q)
    vals = obj.term_values(x, p)
    # no construction-line targets and no support given: no line terms, no support-shape term
    assert all(vals.pop(k) == 0.0 for k in ("ease", "placement", "guide_ease", "guide_placement",
                                            "support_shape"))
    assert all(v > 0 for v in vals.values()), vals
    assert float(obj(x, p)) == pytest.approx(sum(vals.values()), rel=1e-12)
    check_gradient(lambda v: obj(v, p), x, rtol=1e-6, num_samples=20)
    check_gradient(lambda v: obj(x, v), p, rtol=1e-6, num_samples=20)
    # through the parametrization: df/dq = (dp/dq)^T df/dp
    check_gradient(lambda v: obj(x, P(v)), q, rtol=1e-6, num_samples=20)


def test_weights_turn_terms_off_and_scale_them():
    _, mesh, P = setup()
    x = mesh.x + 0.004
    q = P.initial() * 1.01
    w = CostWeights(distance=0.0, smoothness=0.0)
    obj = objective(1.04, w)
    assert set(obj.costs) == {"stretching", "positional"}
    vals = obj.term_values(x, P(q))
    assert vals["distance"] == 0.0 and vals["smoothness"] == 0.0
    obj2 = objective(1.04, replace(w, positional=2 * w.positional))
    assert obj2.term_values(x, P(q))["positional"] == pytest.approx(2 * vals["positional"], rel=1e-12)
    with pytest.raises(InputError):
        CostWeights(fixing=-1.0).validate()
    with pytest.raises(InputError):
        CostWeights.from_dict({"fixng": 1.0})
    assert CostWeights.from_dict(CostWeights().to_dict()) == CostWeights()


def test_paper_default_weights():
    w = CostWeights.paper()
    assert (w.fixing, w.curvature, w.distance, w.smoothness, w.stretching, w.positional) == (100, 1e6, 1,
                                                                                             0.05, 1, 100)
    assert w.reference_edge_length is None and w.ease == 0.0 and w.placement == 0.0  # the paper's terms
    w = CostWeights()
    # the defaults: the paper's coefficients, rescaled to the mesh resolution
    assert (w.fixing, w.curvature, w.distance, w.smoothness, w.stretching, w.positional) == (100, 1e6, 1,
                                                                                             0.05, 1, 100)
    # resolution-consistent by default (issue 18): the coefficients refer to the paper's 8 mm mesh
    assert w.reference_edge_length == 0.008


def test_resolution_factors_rescale_the_regularizers():
    """On a mesh of edge length h the regularizers are rescaled by (h_ref/h)^(1, 3, 4); at h = h_ref, or with
    the normalization off, they are the coefficients as given."""
    from torchgarment.adjust.objective import resolution_factors

    assert resolution_factors(0.05, None) == {"fixing": 1.0, "seam": 1.0, "curvature": 1.0, "lines": 1.0}
    f = resolution_factors(0.04, 0.008)
    assert abs(f["fixing"] - 0.2) < 1e-12 and abs(f["seam"] - 0.008) < 1e-12 and abs(f["curvature"]
                                                                                     - 0.0016) < 1e-12
    assert abs(f["lines"] - 0.04) < 1e-12
    assert resolution_factors(0.008, 0.008) == {"fixing": 1.0, "seam": 1.0, "curvature": 1.0, "lines": 1.0}
    with pytest.raises(InputError):
        resolution_factors(0.0, 0.008)
    with pytest.raises(InputError):
        CostWeights(reference_edge_length=-1.0).validate()
    _, mesh, P = setup()
    raw = objective(weights=CostWeights(reference_edge_length=None))
    norm = objective()
    r = 0.008 / norm.edge_length
    assert abs(norm.regularizers["fixing"].weight - r * raw.regularizers["fixing"].weight) < 1e-9
    assert abs(norm.regularizers["curvature"].weight - r ** 4 * raw.regularizers["curvature"].weight) < 1e-6


def test_regularizer_hessian_is_spd_and_matches_regularizers():
    _, mesh, P = setup()
    obj = objective()
    H = obj.regularizer_hessian()
    n = 2 * P.num_boundary
    assert H.shape == (n, n)
    assert abs(H - H.T).max() < 1e-6
    ev = np.linalg.eigvalsh(H.toarray())
    fix = 100.0 * obj.resolution_factors["fixing"]  # the effective delta_fix on this mesh
    assert ev.min() >= fix * (1 - 1e-9)  # fixing adds delta_fix * I to PSD parts
    # it is the Hessian of the regularizers at the base pattern along T-fixed directions: for a translation of
    # a panel (curvature, seam-free direction) it is delta_fix exactly
    d = torch.zeros(P.num_boundary, 2, dtype=torch.float64)
    d[:, 0] = 1.0
    v = d.reshape(-1).numpy()
    assert float(v @ (H @ v)) == pytest.approx(fix * P.num_boundary, rel=1e-9)
    # without the fixing term a tiny identity keeps it positive definite
    obj0 = objective(weights=CostWeights(fixing=0.0))
    assert np.linalg.eigvalsh(obj0.regularizer_hessian().toarray()).min() > 0


def test_initialization_objective():
    body, mesh, P = setup()
    s = 1.05
    obj = objective(s, CostWeights(distance=0.0))
    # the transferred garment of a scaled body is the scaled garment
    assert torch.allclose(obj.x_transfer,
                          (mesh.x - torch.tensor([0.0, 0.9, 0.0])) * s + torch.tensor([0.0, 0.9, 0.0]),
                          atol=1e-9)
    q0 = P.initial()
    f0 = float(obj.initialization_objective(P(q0)))
    check_gradient(lambda v: obj.initialization_objective(P(v)), q0 + 0.001, rtol=1e-5, num_samples=30)
    area = lambda p: float(torch.det(torch.cov(p.T)))  # noqa: E731

    def minimize(o, iterations=50):
        q = q0.clone().requires_grad_(True)
        opt = torch.optim.LBFGS([q], max_iter=iterations, line_search_fn="strong_wolfe", history_size=50,
                                tolerance_grad=1e-14, tolerance_change=1e-16)

        def closure():
            opt.zero_grad()
            f = o.initialization_objective(P(q))
            f.backward()
            return f

        opt.step(closure)
        return q.detach()

    q = minimize(obj)
    f1 = float(obj.initialization_objective(P(q)))
    assert f1 < 0.7 * f0  # with the paper's weights the fixing term holds the coarse test pattern back
    grow = (area(P(q)) / area(mesh.p)) ** 0.25
    assert 1.01 < grow < s
    # with a weak fixing term the pattern becomes s times the base (stretch ratios of the scaled garment)
    # (curvature lowered to 1e3: at 1e6 the problem is too ill-conditioned for a quick plain L-BFGS run)
    weak = objective(s, CostWeights(distance=0.0, fixing=1e-3, curvature=1e3, seam=1e3))
    q = minimize(weak, 120)
    assert float(weak.initialization_objective(P(q))) < 1e-2 * f0
    assert (area(P(q)) / area(mesh.p)) ** 0.25 == pytest.approx(s, abs=2e-3)


def test_transfer_is_computed_when_not_given():
    body, mesh, P = setup()
    obj = AdjustObjective(mesh, body, body, P, CostWeights(distance=0.0))
    assert torch.allclose(obj.x_transfer, mesh.x, atol=1e-12)
    x_t = transfer_deformation(mesh.x, body, scaled(body, 1.02))
    obj2 = AdjustObjective(mesh, body, body, P, CostWeights(distance=0.0), x_transfer=x_t)
    assert torch.equal(obj2.x_transfer, x_t)
    with pytest.raises(InputError):
        AdjustObjective(mesh, body, body, P, CostWeights(distance=0.0), x_transfer=x_t[:-1])


def test_default_body_sdfs():
    body, mesh, P = setup()
    obj = AdjustObjective(mesh, body, body, P)  # default weights, cached BodySDFs of the bodies
    assert "distance" in obj.costs
    assert obj.term_values(mesh.x, mesh.p)["distance"] == 0.0
    x = (mesh.x + 0.01).requires_grad_(True)
    f = obj(x, mesh.p)
    (g,) = torch.autograd.grad(f, x)
    assert torch.isfinite(g).all() and float(obj.term_values(x.detach(), mesh.p)["distance"]) > 0


def test_line_terms_are_built_from_line_targets_and_differentiate():
    """With construction-line targets the objective has the ease regularizer and the placement cost, weighted
    by ``weight * r^2``, and for the guide line (the hem) the same terms weighted ``guide`` times as much;
    each is zero when its targets are the base's, and the total's gradients are right."""
    from torchgarment.adjust.fit import line_targets

    body, mesh, P = setup()
    pattern = draft("straight_skirt", chart_row("12"))
    placed = mesh_pattern(pattern, 0.05)
    targets = line_targets(pattern, placed, placed.x, placed.x, body, body)
    assert targets.lines == ["waist", "hips", "hem"]
    dg, dy = (0.03, -0.02, 0.01), (0.01, -0.005, 0.02)
    targets.target_girth_m = [g + d for g, d in zip(targets.target_girth_m, dg, strict=True)]
    targets.target_height_m = [float(mesh.x[targets.corners[targets.line_of == i].reshape(-1), 1].mean()) + d
                               for i, d in enumerate(dy)]
    held = targets.held_vertices
    targets.held_height_m = mesh.x[held, 1].numpy() + 0.02
    assert len(targets.girth_slope) == 3 and targets.girth_slope[2] == 0.0  # the guide line has none
    targets.girth_slope = [0.0, 0.5, 0.0]  # the hip line sits where the girth grows by 5 mm per cm
    w = CostWeights(placement=1e4, guide=0.5)
    obj = AdjustObjective(mesh, body, body, P, w, base_sdf=ShiftedSphereSDF(0.15),
                          target_sdf=ShiftedSphereSDF(0.15), lines=targets)
    r = 0.008 / obj.edge_length
    assert obj.regularizers["ease"].weight == pytest.approx(w.ease * r ** 2, rel=1e-12)
    assert obj.costs["placement"].weight == pytest.approx(w.placement * r ** 2, rel=1e-12)
    assert obj.regularizers["guide_ease"].weight == pytest.approx(0.5 * w.ease * r ** 2, rel=1e-12)
    # the hem's height term holds each of its M vertices, weighted to count as its 4 corners
    assert obj.costs["guide_placement"].weight == pytest.approx(0.5 * w.placement * r ** 2 * 4 / len(held),
                                                                rel=1e-12)
    q0 = P.initial()
    vals = obj.term_values(mesh.x, P(q0))
    assert vals["ease"] == pytest.approx(0.5 * obj.regularizers["ease"].weight * (0.03 ** 2 + 0.02 ** 2),
                                         rel=1e-9)
    assert vals["placement"] == pytest.approx(
        0.5 * obj.costs["placement"].weight * (0.01 ** 2 + (1 + w.ease / w.placement * 0.25) * 0.005 ** 2),
        rel=1e-9)
    assert vals["guide_ease"] == pytest.approx(0.5 * obj.regularizers["guide_ease"].weight * 0.01 ** 2,
                                               rel=1e-9)
    assert vals["guide_placement"] == pytest.approx(
        0.5 * obj.costs["guide_placement"].weight * len(held) * 0.02 ** 2, rel=1e-9)
    no_guide = AdjustObjective(mesh, body, body, P, CostWeights(placement=1e4, guide=0.0),
                               base_sdf=ShiftedSphereSDF(0.15), target_sdf=ShiftedSphereSDF(0.15),
                               lines=targets)
    assert "guide_ease" not in no_guide.regularizers and "guide_placement" not in no_guide.costs
    g = torch.Generator().manual_seed(5)
    q = q0 + 0.003 * torch.randn(q0.shape, generator=g, dtype=q0.dtype)
    x = mesh.x + 0.005 * torch.randn(mesh.x.shape, generator=g, dtype=torch.float64)
    check_gradient(lambda v: obj.regularization(P(v)), q, rtol=1e-6)
    check_gradient(lambda v: obj(v, P(q)), x, rtol=1e-6, num_samples=20)
    # the paper's weights: neither term
    off = AdjustObjective(mesh, body, body, P, CostWeights.paper(), base_sdf=ShiftedSphereSDF(0.15),
                          target_sdf=ShiftedSphereSDF(0.15), lines=targets)
    assert "ease" not in off.regularizers and "placement" not in off.costs
    assert off.term_values(mesh.x, P(q0))["ease"] == 0.0


def test_support_shape_term_is_built_from_the_support():
    """Given the support's vertices the objective holds their outline with ``support_shape * placement * r^2``
    spread so that each panel's support counts as two corners; off with ``support_shape=0``, with the
    placement term off, or without a support; zero at the base pattern; its gradient through the
    parametrization is right."""
    from torchgarment.pattern.support import support_vertices

    body, mesh, P = setup()
    idx, _, _ = support_vertices(draft("straight_skirt", chart_row("12")), mesh)
    kw = dict(base_sdf=ShiftedSphereSDF(0.15), target_sdf=ShiftedSphereSDF(0.15), support=idx)
    w = CostWeights(support_shape=0.5)
    obj = AdjustObjective(mesh, body, body, P, w, **kw)
    reg = obj.regularizers["support_shape"]
    r = 0.008 / obj.edge_length
    n_panels = int(torch.unique(mesh.vertex_panel_ids[idx]).numel())
    assert reg.rows.numel() == idx.numel()
    assert reg.weight == pytest.approx(0.5 * w.placement * r ** 2 * 2 * n_panels / idx.numel(), rel=1e-12)
    q0 = P.initial()
    assert obj.term_values(mesh.x, P(q0))["support_shape"] < 1e-24
    q = q0.clone()
    q[reg.rows, 1] += 0.002
    assert obj.term_values(mesh.x, P(q))["support_shape"] == pytest.approx(
        0.5 * reg.weight * idx.numel() * 0.002 ** 2, rel=1e-9)
    g = torch.Generator().manual_seed(2)
    check_gradient(lambda v: obj.regularization(P(v)), q0 + 0.003 * torch.randn(q0.shape, generator=g,
                                                                                dtype=q0.dtype), rtol=1e-6)
    for off in (CostWeights(support_shape=0.0), CostWeights(placement=0.0)):
        assert "support_shape" not in AdjustObjective(mesh, body, body, P, off, **kw).regularizers
    assert "support_shape" not in objective().regularizers
    with pytest.raises(InputError, match="support vertex"):
        interior = torch.tensor([int(torch.nonzero(~torch.isin(torch.arange(mesh.num_vertices),
                                                               P.boundary_index))[0])])
        AdjustObjective(mesh, body, body, P, w, **{**kw, "support": torch.cat([idx, interior])})


def test_scaled_panels_scales_each_panel_about_its_mean():
    """``scaled_panels``: each panel's rows scaled by s about their own mean (the means stay, every distance
    within a panel grows by s, rows of different panels are not mixed); s = 1 returns ``q`` itself; a bad s or
    a ``panel_of`` of another length is refused."""
    from torchgarment.adjust.objective import scaled_panels

    g = torch.Generator().manual_seed(0)
    q = torch.randn(12, 2, generator=g, dtype=torch.float64)
    panel_of = torch.tensor([0, 0, 0, 0, 1, 1, 1, 2, 2, 2, 2, 2])
    s = 1.07
    out = scaled_panels(q, panel_of, s)
    for k in range(3):
        a, b = q[panel_of == k], out[panel_of == k]
        assert torch.allclose(b.mean(0), a.mean(0), atol=1e-14)
        assert torch.allclose(torch.cdist(b, b), s * torch.cdist(a, a), atol=1e-13)
    assert scaled_panels(q, panel_of, 1.0) is q
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(InputError, match="positive"):
            scaled_panels(q, panel_of, bad)
    with pytest.raises(InputError, match="panel_of"):
        scaled_panels(q, panel_of[:-1], s)
