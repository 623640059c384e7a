"""Scene: effect detection, building only the requested terms, and the SimModel interface."""

from __future__ import annotations

import sys

import pytest
import torch

from torchgarment.errors import InputError
from torchgarment.pattern.library import draft
from torchgarment.pattern.meshing import mesh_pattern
from torchgarment.sim import Effect, Material, Scene, SimModel
from torchgarment.structures.garment_mesh import GarmentMesh
from torchgarment.testing import check_gradient, check_hessian_blocks

MEASUREMENTS = {"height": 1.65, "bust": 0.9, "underbust": 0.78, "waist": 0.72, "hips": 0.98}


class PlaneSDF(torch.nn.Module):
    """phi = y - c (floor below the garment)."""

    def __init__(self, c: float = 0.0) -> None:
        super().__init__()
        self.c = c

    def forward(self, x):
        return x[:, 1] - self.c

    def value_and_gradient(self, x):
        g = torch.zeros_like(x)
        g[:, 1] = 1.0
        return x[:, 1].detach() - self.c, g


@pytest.fixture(scope="module")
def skirt() -> GarmentMesh:
    return mesh_pattern(draft("straight_skirt", MEASUREMENTS), 0.05)


@pytest.fixture(scope="module")
def x_noisy(skirt) -> torch.Tensor:
    gen = torch.Generator().manual_seed(1)
    return skirt.x + 0.01 * torch.randn(skirt.x.shape, dtype=torch.float64, generator=gen)


def test_detection(skirt):
    assert Scene(skirt).build().term_names == ("stretch", "sew", "bend", "gravity")
    model = Scene(skirt, body_sdf=PlaneSDF(), pin_indices=torch.tensor([0, 1])).build()
    assert model.term_names == ("stretch", "sew", "bend", "gravity", "pins", "body_barrier")
    assert model.effects == (Effect.STRETCH, Effect.SEW, Effect.BEND, Effect.GRAVITY, Effect.PINS,
                             Effect.BODY_BARRIER)
    # a plain 3D mesh: no stretch, no seams
    plain = GarmentMesh(skirt.x, skirt.faces)
    assert Scene(plain).build().term_names == ("bend", "gravity")


def test_builds_only_requested(skirt):
    assert Scene(skirt, effects={Effect.STRETCH}).build().term_names == ("stretch",)
    m = Scene(skirt, body_sdf=PlaneSDF(), effects={"gravity", Effect.SEW}).build()
    assert m.term_names == ("sew", "gravity")  # SDF given but no barrier asked for
    assert Scene(skirt, effects=set()).build().term_names == ()
    with pytest.raises(InputError, match="unknown effect"):
        Scene(skirt, effects={"wind"}).build()


@pytest.mark.parametrize("effect, match", [
    (Effect.BODY_BARRIER, "body_sdf"),
    (Effect.PINS, "pin_indices"),
    (Effect.BODY_CONTACT, "body_vertices"),
])
def test_asked_but_impossible(skirt, effect, match):
    with pytest.raises(InputError, match=match):
        Scene(skirt, effects={effect}).build()


def test_asked_but_impossible_plain_mesh(skirt):
    plain = GarmentMesh(skirt.x, skirt.faces)
    with pytest.raises(InputError, match="rest positions"):
        Scene(plain, effects={Effect.STRETCH}).build()
    with pytest.raises(InputError, match="seam pairs"):
        Scene(plain, effects={Effect.SEW}).build()


def test_material_reaches_terms(skirt):
    mat = Material(stretch_stiffness=7.0, sew_stiffness=3.0, bend_stiffness=1e-4, density=0.3,
                   pin_stiffness=5.0,
                   barrier_mu=0.02)
    m = Scene(skirt, body_sdf=PlaneSDF(), pin_indices=[3], material=mat).build()
    assert m.term("stretch").stiffness == 7.0 and m.term("sew").stiffness == 3.0
    assert m.term("bend").stiffness == 1e-4 and m.term("pins").stiffness == 5.0
    assert m.term("body_barrier").mu == 0.02
    assert float(m.term("gravity").masses.sum()) == pytest.approx(0.3
                                                                  * float(skirt.rest_face_areas.abs().sum()))
    # default pin targets are the current positions: zero energy there
    assert m.term_values(skirt.x)["pins"] == 0.0
    with pytest.raises(InputError, match="no term"):
        m.term("wind")


def test_model_sums_terms(skirt, x_noisy):
    model = Scene(skirt, body_sdf=PlaneSDF(), pin_indices=torch.tensor([0, 7])).build()
    assert isinstance(model, SimModel) and model.num_vertices == skirt.num_vertices
    E, g = model.value_and_grad(x_noisy)
    vals = model.term_values(x_noisy)
    assert float(E) == pytest.approx(sum(vals.values()), rel=1e-12)
    assert float(model.energy(x_noisy)) == pytest.approx(float(E), rel=1e-12)
    g_sum = sum(t.value_and_grad(x_noisy)[1] for t in model.terms)
    assert torch.allclose(g, g_sum, rtol=1e-12, atol=1e-12)
    check_gradient(model.energy, x_noisy, g, num_samples=150)
    D = model.hessian_diagonal(x_noisy)
    assert torch.allclose(D, sum(t.hessian_diagonal(x_noisy) for t in model.terms))
    E3, g3, D3 = model.value_grad_hessian_diagonal(x_noisy)
    assert float(E3) == pytest.approx(float(E), rel=1e-12) and torch.allclose(g3, g) and torch.allclose(D3, D)
    # the plane SDF has zero Hessian: the model's unprojected Hessian is exact
    check_hessian_blocks(_Unprojected(model), x_noisy, num_columns=30, atol=1e-9)


class _Unprojected:
    """Adapter: SimModel.hessian_diagonal has no project_psd; sum the terms' unprojected diagonals."""

    def __init__(self, model):
        self.model = model

    def value_and_grad(self, x):
        return self.model.value_and_grad(x)

    def hessian_blocks(self, x, project_psd=True):
        return self.model.hessian_blocks(x, project_psd=project_psd)

    def hessian_diagonal(self, x, project_psd=True):
        return sum(t.hessian_diagonal(x, project_psd=project_psd) for t in self.model.terms)


def test_barrier_interface(skirt):
    x = skirt.x
    free = Scene(skirt).build()
    dx = torch.full_like(x, -10.0)
    assert free.max_step(x, dx) == 1.0
    assert free.project_feasible(x) is x
    floor = float(x[:, 1].min()) - 0.05
    model = Scene(skirt, body_sdf=PlaneSDF(floor)).build()
    down = torch.zeros_like(x)
    down[:, 1] = -0.1  # the lowest vertex reaches the floor at alpha = 0.5
    a = model.max_step(x, down)
    assert 0.45 <= a <= 0.5
    y = model.project_feasible(x + down)
    assert float(y[:, 1].min()) >= floor and torch.isfinite(model.value_and_grad(y)[0])


def test_contact_effects_are_lazy(skirt, monkeypatch):
    monkeypatch.setitem(sys.modules, "torchgarment.sim.contact", None)  # import fails
    with pytest.raises(InputError, match="torchgarment.sim.contact"):
        Scene(skirt, effects={Effect.SELF_CONTACT}).build()
    # other effects do not need the module
    assert Scene(skirt, effects={Effect.BEND}).build().term_names == ("bend",)


def test_self_contact_builds_when_available(skirt):
    pytest.importorskip("ipctk")
    pytest.importorskip("torchgarment.sim.contact")
    m = Scene(skirt, effects={Effect.SELF_CONTACT, Effect.STRETCH}).build()
    assert m.term_names == ("stretch", "self_contact")
    E, g = m.value_and_grad(skirt.x)
    assert torch.isfinite(E) and g.shape == skirt.x.shape


def test_panel_contact_builds_within_panels(skirt):
    pytest.importorskip("ipctk")
    pytest.importorskip("torchgarment.sim.contact")
    m = Scene(skirt, effects={Effect.PANEL_CONTACT}).build()
    assert m.term_names == ("panel_contact",) and torch.isfinite(m.value_and_grad(skirt.x)[0])
    bare = GarmentMesh(skirt.x, skirt.faces, p=skirt.p, seam_pairs=skirt.seam_pairs)
    with pytest.raises(InputError, match="panel_contact.*no panel_ids"):
        Scene(bare, effects={Effect.PANEL_CONTACT}).build()
