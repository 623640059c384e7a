"""Tests of torchgarment.sim.drape: one small drape end to end, plus the full matrix (slow)."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
import torch

from torchgarment.errors import InputError
from torchgarment.sim.drape import DrapeSettings, drape, max_seam_gap, seam_gaps, vertex_stretch_ratio
from torchgarment.sim.solvers import LinearSolver
from torchgarment.structures.garment_mesh import GarmentMesh

# small case at the default (strict) force tolerance |g|_2 <= 1e-3 * weight, with the default C1 (quadratic)
# SDF sampling and settle-stage barrier weight 1e-3 J.
SMALL = DrapeSettings(edge_length=0.035, voxel_size=0.008, sew_solver="gd-chebyshev", solver="newton",
                      sew_max_iterations=600, max_iterations=120)


@pytest.fixture(scope="module")
def small_drape():
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    body = Body.from_size("6")
    pattern = draft("straight_skirt", chart_row("6"))
    return body, pattern, drape(pattern, body, settings=SMALL)


def test_small_drape_end_to_end(small_drape):
    body, pattern, r = small_drape
    m = r.metrics
    sdf = r.model.term("body_barrier").sdf
    phi = sdf(r.x)
    assert float(phi.min()) >= 0.0 and m["min_sdf_mm"] >= 0.0 and m["inside_vertices"] == 0
    assert abs(m["min_sdf_mm"] - 1e3 * float(phi.min())) < 1e-9
    assert m["max_seam_gap_mm"] <= 1.0
    assert r.converged and m["converged"] and r.ok
    # the strict weight-based criterion
    assert m["residual"] <= m["tolerance"] <= 1e-3 * m["weight_n"] + 1e-15
    assert m["energy"] < m["energy_start"]
    # every stage keeps its residual history; the sewing stage closed the seams from ~30 cm
    assert [s.name for s in r.stages] == ["sew", "settle"]
    assert all(len(s.info.residual_history) == s.info.iterations + 1 for s in r.stages)
    placed = pattern_mesh(pattern)
    assert r.stages[0].max_seam_gap < 0.02 < max_seam_gap(placed, placed.x)
    assert m["iterations"] == sum(s.info.iterations for s in r.stages)
    # the skirt's waistband is its support: held by sticking springs in the settle stage
    assert set(m["energy_terms"]) == {"stretch", "sew", "bend", "gravity", "body_barrier", "pins"}
    assert m["self_contact"] is False and m["intersects_self"] is False  # the welded skirt, checked by ipctk
    assert r.x.shape == (m["vertices"], 3) and torch.isfinite(r.x).all()
    json.dumps(m)  # serializable
    # draped cloth is near its rest lengths (the skirt neither collapses nor blows up)
    ratio = vertex_stretch_ratio(r.mesh, r.x)
    assert 0.9 < float(ratio.median()) < 1.1


@pytest.mark.parametrize("option, value, bad", [
    ("linear_solver", "jacobi-pcg", "lu"),
    ("sparse_backend", "cholmod", "umfpack"),
])
def test_settle_without_superlu_matches_the_default(small_drape, splu_calls: dict, option, value, bad):
    """The settle's Newton without a single SuperLU factorization reaches a usable drape next to the default's
    (mean vertex within 0.5 mm; a hem may settle on another of its equilibria), converged, outside the body:
    ``linear_solver="jacobi-pcg"`` solves by block-Jacobi CG (the GPU path, no factorization at all),
    ``sparse_backend="cholmod"`` factorizes by CHOLMOD's Cholesky (the extra ``.[cholmod]``)."""
    from dataclasses import replace

    if value == "cholmod":
        pytest.importorskip("cvxopt")
    body, pattern, ref = small_drape
    r = drape(pattern, body, settings=replace(SMALL, **{option: value}))
    assert splu_calls["n"] == 0
    assert r.ok and r.converged and r.metrics["inside_vertices"] == 0
    assert float((r.x - ref.x).norm(dim=1).mean()) <= 5e-4
    with pytest.raises(InputError):
        DrapeSettings(**{option: bad})


def test_projected_newton_settle_matches_the_default(small_drape):
    """The default settle takes Newton's directions by CG on the exact Hessian (``exact_curvature_cg`` None:
    10 with the direct solver, 0 with ``jacobi-pcg``); projected Newton (``exact_curvature_cg=0``) reaches
    the same drape (mean vertex within 0.5 mm), converged, outside the body; out-of-range values are
    refused."""
    from dataclasses import replace

    from torchgarment.sim.solvers import DEFAULT_EXACT_CURVATURE_CG, exact_curvature_iterations

    assert SMALL.exact_curvature_cg is None
    assert exact_curvature_iterations(None, SMALL.linear_solver) == DEFAULT_EXACT_CURVATURE_CG > 0
    assert exact_curvature_iterations(None, LinearSolver.JACOBI_PCG) == 0
    assert exact_curvature_iterations(3, SMALL.linear_solver) == 3
    body, pattern, ref = small_drape
    r = drape(pattern, body, settings=replace(SMALL, exact_curvature_cg=0))
    assert r.ok and r.converged and r.metrics["inside_vertices"] == 0
    assert not torch.equal(r.x, ref.x)  # another path: the default did not run projected Newton
    assert float((r.x - ref.x).norm(dim=1).mean()) <= 5e-4
    for bad in ({"exact_curvature_cg": -1}, {"exact_curvature_cg": 5, "linear_solver": "jacobi-pcg"}):
        with pytest.raises(InputError, match="exact_curvature_cg"):
            DrapeSettings(**bad).validate()


def pattern_mesh(pattern):
    from torchgarment.pattern.meshing import mesh_pattern

    return mesh_pattern(pattern, SMALL.edge_length)


def test_self_contact_settle_keeps_the_garment_intersection_free(small_drape):
    """``self_contact``: the settle stage has IPC cloth-cloth contact on the welded garment, so the seams
    stay closed and the garment cannot pass through itself, and the sewing stage contact within each panel;
    the result stays close to the plain drape's where the skirt does not touch itself. ipctk runs on
    ``contact_threads`` (1) in both stages."""
    import ipctk

    body, pattern, plain = small_drape
    before = ipctk.get_num_threads()
    seen = []
    r = drape(pattern, body, settings=replace(SMALL, self_contact=True),
              progress=lambda stage, k, res: seen.append((stage, ipctk.get_num_threads())))
    assert {t for stage, t in seen} == {1} and {stage for stage, _ in seen} == {"sew", "settle"}
    assert ipctk.get_num_threads() == before
    for bad in (0, 1.5):
        with pytest.raises(InputError, match="contact_threads"):
            DrapeSettings(contact_threads=bad)
    m = r.metrics
    assert [s.name for s in r.stages] == ["sew", "settle"]
    assert "self_contact" not in r.stages[0].effects and "self_contact" in r.stages[1].effects
    assert "panel_contact" in r.stages[0].effects and "panel_contact" not in r.stages[1].effects
    assert m["self_contact"] is True and m["intersects_self"] is False
    assert r.converged and m["max_seam_gap_mm"] <= 1.0 and m["min_sdf_mm"] >= 0.0
    contact = r.model.term("self_contact")
    assert contact.min_distance(r.x) > 0.0 and not contact.has_intersections(r.x)
    assert float((r.x - plain.x).norm(dim=1).median()) < 5e-3


def test_self_contact_needs_an_intersection_free_start():
    """Two sheets crossing each other in front of a body: with ``self_contact`` the settle cannot start, one
    clear error; the plain drape reports the crossing in ``metrics["intersects_self"]``."""
    from torchgarment.body import Body
    from torchgarment.errors import MeshError
    from torchgarment.sim.contact import intersects_itself

    u = torch.linspace(-0.1, 0.1, 5, dtype=torch.float64)
    gu, gv = torch.meshgrid(u, u, indexing="ij")
    flat = torch.stack([gu.reshape(-1), gv.reshape(-1), torch.zeros(25, dtype=torch.float64)], 1)
    i, j = torch.meshgrid(torch.arange(4), torch.arange(4), indexing="ij")
    a = (5 * i + j).reshape(-1)
    quads = torch.cat([torch.stack([a, a + 5, a + 6], 1), torch.stack([a, a + 6, a + 1], 1)])
    second = flat[:, [2, 1, 0]]  # the same sheet turned 90 degrees about y: the two cross along a line
    x = torch.cat([flat, second]) + torch.tensor([0.0, 1.2, 0.45], dtype=torch.float64)
    faces = torch.cat([quads, quads + 25])
    assert intersects_itself(x, faces) and not intersects_itself(flat, quads)
    rest = torch.cat([flat[:, :2], flat[:, :2] + torch.tensor([0.3, 0.0], dtype=torch.float64)])
    mesh = GarmentMesh(x, faces, p=rest)
    body = Body.from_size("6")
    settings = DrapeSettings(voxel_size=0.02, max_iterations=2, support=False)
    where = (r"intersects itself at the start \(\d+ edge-triangle crossings, the first at "
             r"\(-?0\.\d\d, 1\.\d\d, 0\.\d\d\) m\)")
    with pytest.raises(MeshError, match=where):
        drape(mesh, body, settings=replace(settings, self_contact=True))
    assert drape(mesh, body, settings=settings).metrics["intersects_self"] is True
    # the same sheets as one panel with a seam: the sewing stage's contact within panels cannot start
    panel = GarmentMesh(x, faces, p=rest, seam_pairs=torch.tensor([[24, 45]]),
                        panel_ids=torch.zeros(faces.shape[0], dtype=torch.long), panel_names=["sheet"])
    placed = r"a panel intersects itself as placed \(\d+ edge-triangle crossings, in panel sheet, the first"
    with pytest.raises(MeshError, match=placed):
        drape(panel, body, settings=replace(settings, self_contact=True))


def test_seam_gaps_and_gradcheck():
    x = torch.tensor([[0.0, 0, 0], [0.0, 0, 0.003], [1.0, 0, 0], [1.0, 0.004, 0]], dtype=torch.float64)
    faces = torch.tensor([[0, 2, 3], [0, 3, 1]])
    mesh = GarmentMesh(x, faces, seam_pairs=torch.tensor([[0, 1], [2, 3]]))
    assert torch.allclose(seam_gaps(mesh, x), torch.tensor([0.003, 0.004], dtype=torch.float64))
    assert abs(max_seam_gap(mesh, x) - 0.004) < 1e-15
    xr = (x + 0.01 * torch.randn(4, 3, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda y: seam_gaps(mesh, y), (xr,))


def test_stretch_ratio_uniform_scaling():
    p = torch.tensor([[0.0, 0], [1, 0], [0, 1], [1, 1]], dtype=torch.float64)
    x = torch.cat([p, torch.zeros(4, 1, dtype=torch.float64)], dim=1)
    mesh = GarmentMesh(x, torch.tensor([[0, 1, 3], [0, 3, 2]]), p=p)
    assert torch.allclose(vertex_stretch_ratio(mesh, 1.05 * x), torch.full((4,), 1.05, dtype=torch.float64))


@pytest.fixture(scope="module")
def sphere_sdf():
    import trimesh

    from torchgarment.sdf import BodySDF, SDFSettings

    m = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    return BodySDF.from_mesh(m.vertices, m.faces, SDFSettings(voxel_size=0.005, brick=4))


def test_quadratic_sdf_sampling_is_c1_and_consistent(sphere_sdf):
    """The drape's default SDF sampling: box-filtered trilinear (C1), exact gradient, same Lipschitz bound."""
    from torchgarment.sdf import SDFSampling

    q = sphere_sdf.with_sampling("quadratic")
    assert q.sampling is SDFSampling.QUADRATIC and sphere_sdf.sampling is SDFSampling.TRILINEAR
    assert q.nodes.data_ptr() == sphere_sdf.nodes.data_ptr()  # a view: no copy of the grid
    gen = torch.Generator().manual_seed(0)
    d = torch.randn(40, 3, dtype=torch.float64, generator=gen)
    x = (0.1 + 0.02 * torch.rand(40, 1, dtype=torch.float64, generator=gen)) * d / d.norm(dim=1, keepdim=True)
    assert torch.autograd.gradcheck(q, (x.clone().requires_grad_(True),), eps=1e-6, atol=1e-7)
    phi, g = q.value_and_gradient(x)
    xr = x.clone().requires_grad_(True)
    (g_auto,) = torch.autograd.grad(q(xr).sum(), xr)
    torch.testing.assert_close(g, g_auto, rtol=0, atol=1e-14)
    exact = x.norm(dim=1) - 0.1
    assert float((phi - exact).abs().max()) < 1e-3  # within the trilinear error bound at 5 mm voxels
    assert float(g.norm(dim=1).max()) <= 3 ** 0.5 + 1e-12
    # along a segment crossing ~10 voxel faces: the trilinear gradient jumps, the quadratic one is continuous
    t = torch.linspace(0.0, 0.05, 50001, dtype=torch.float64)[:, None]
    seg = torch.tensor([0.0, 0.0, 0.105], dtype=torch.float64) + t * torch.tensor([0.6, 0.7, 0.387],
                                                                                  dtype=torch.float64)
    jump = {m.sampling: float(m.value_and_gradient(seg)[1].diff(dim=0).norm(dim=1).max())
            for m in (sphere_sdf, q)}
    assert jump[SDFSampling.TRILINEAR] > 0.02 and jump[SDFSampling.QUADRATIC] < 1e-3
    with pytest.raises(InputError):
        sphere_sdf.with_sampling("cubic")


def test_bad_input():
    with pytest.raises(InputError):
        drape("not a pattern", None, settings=DrapeSettings())
    with pytest.raises(InputError):
        DrapeSettings(edge_length=-1.0).validate()
    with pytest.raises(InputError):
        DrapeSettings(solver="nope").validate()


def test_cli_bad_input(tmp_path, capsys):
    import argparse

    from torchgarment.sim.drape_cli import add_drape_parser

    parser = argparse.ArgumentParser()
    add_drape_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["drape", "--pattern", "no_such_garment", "--body", "6", "--out",
                              str(tmp_path / "o")])
    with pytest.raises(InputError, match="neither a library garment"):
        args.func(args)
    args = parser.parse_args(["drape", "--pattern", "straight_skirt", "--body", str(tmp_path / "nobody.obj"),
                              "--out", str(tmp_path / "o")])
    with pytest.raises(InputError, match="neither a chart size"):
        args.func(args)
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
@pytest.mark.parametrize("garment", ["straight_skirt", "aline_skirt", "sheath_dress", "tshirt", "trousers",
                                     "bodysuit"])
@pytest.mark.parametrize("size", ["6", "20"])
def test_library_matrix(garment, size):
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    r = drape(draft(garment, chart_row(size)), Body.from_size(size),
              settings=DrapeSettings(edge_length=0.03, sew_solver="gd-chebyshev", max_iterations=300))
    assert r.metrics["min_sdf_mm"] >= 0 and r.metrics["max_seam_gap_mm"] <= 1.0
    assert r.converged, r.metrics["message"]


@pytest.mark.slow
@pytest.mark.parametrize("spec,body", [("shirt_mean", "mean_all"), ("dress_pencil", "mean_female")])
def test_garmentcode_matrix(garmentcode_dir, spec, body):
    from torchgarment.body.load import load_body
    from torchgarment.pattern.garmentcode import load_pattern

    # the pencil dress's skirt slides into place slowly: measured 1,145 settle iterations (94 s)
    r = drape(load_pattern(garmentcode_dir / "patterns" / f"{spec}_specification.json"),
              load_body(garmentcode_dir / "bodies" / f"{body}.obj"),
              settings=DrapeSettings(edge_length=0.03, sew_solver="gd-chebyshev", max_iterations=1500))
    assert r.metrics["min_sdf_mm"] >= 0 and r.metrics["max_seam_gap_mm"] <= 1.0
    assert r.converged, r.metrics["message"]
