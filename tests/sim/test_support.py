"""The support in the base drape (torchgarment.sim.support, DrapeSettings.support): stiffness from the weight,
targets at the body's waist, and a straight skirt held there."""

from __future__ import annotations

import math

import pytest
import torch

from torchgarment.errors import InputError
from torchgarment.sim.drape import DrapeSettings, drape
from torchgarment.sim.support import support_metrics, support_stiffness

COARSE = DrapeSettings(edge_length=0.05, voxel_size=0.01)


@pytest.fixture(scope="module")
def body12():
    from torchgarment.body import Body

    return Body.from_size("12")


@pytest.fixture(scope="module")
def skirt_drapes(body12):
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        pattern = draft("straight_skirt", chart_row("12"))
        on = drape(pattern, body12, settings=COARSE)
        off = drape(pattern, body12, settings=DrapeSettings(edge_length=0.05, voxel_size=0.01, support=False))
    finally:
        torch.set_num_threads(n)
    return pattern, on, off


def test_stiffness_from_the_weight():
    # k = W / (P sag): 18 pins holding 0.85 N with a mean give of 0.5 mm
    assert support_stiffness(0.85, 18, 5e-4) == pytest.approx(0.85 / (18 * 5e-4))
    for bad in ((0.0, 18, 5e-4), (1.0, 0, 5e-4), (1.0, 18, 0.0)):
        with pytest.raises(InputError, match="support stiffness"):
            support_stiffness(*bad)
    with pytest.raises(InputError, match="support_sag"):
        DrapeSettings(support_sag=0.0)


def test_support_metrics_numbers():
    x = torch.zeros(4, 3, dtype=torch.float64)
    x[1] = torch.tensor([0.0, 0.003, 0.0])
    x[2] = torch.tensor([0.004, 0.0, 0.0])
    idx = torch.tensor([1, 2])
    t = torch.zeros(2, 3, dtype=torch.float64)
    m = support_metrics(x, idx, t, 100.0)
    assert m["support_force_n"] == pytest.approx(100.0 * 0.005)  # |(0.004, 0.003, 0)| k
    assert m["support_force_sum_n"] == pytest.approx(100.0 * 0.007)
    assert m["support_max_displacement_mm"] == pytest.approx(4.0)
    assert m["support_vertices"] == 2 and m["support_stiffness_n_per_m"] == 100.0


def test_base_drape_holds_the_band_at_the_waist_plane(skirt_drapes, body12):
    """Measured (size 12, 5 cm edges, 10 mm voxels): the band's mean height is 0.8 mm above the waist plane
    (without the support it rides 22 mm above it), its pins give at most 7.2 mm (the straight-waisted draft
    pulls its side seams down and its centres up) and carry a net 2.8 N."""
    from torchgarment.body.measure import find_section_planes

    pattern, on, off = skirt_drapes
    y_waist = float(find_section_planes(body12.vertices, body12.faces, names=("waist",))["waist"].point[1])
    m = on.metrics
    assert on.ok and m["support"] == ("skirt_front:waist_r,skirt_front:waist_l,skirt_back:waist_r,"
                                      "skirt_back:waist_l")
    assert "pins" in on.stages[-1].effects and "pins" not in off.stages[-1].effects
    idx, tgt = on.support_indices, on.support_targets
    # targets: in the waist plane, a loop of the band's own length around the body's section
    assert torch.allclose(tgt[:, 1], torch.full_like(tgt[:, 1], y_waist), atol=1e-12)
    closed = torch.cat([tgt, tgt[:1]])
    loop = float(torch.linalg.vector_norm(closed[1:] - closed[:-1], dim=1).sum())
    band = m["support_target"]["band_length_m"]
    # (the chords between 18 targets 4 cm apart are 1 % shorter than the curve they lie on: measured 1.0 %)
    assert loop == pytest.approx(band, rel=0.02) and loop < band
    assert m["support_target"]["stretch"] == pytest.approx(1.0)
    assert 0.0 < m["support_target"]["offset_mm"] < 5.0  # 1 cm of ease: 1.6 mm off the convex hull
    # the drape: the band sits at the waist plane (mean within 3 mm), every pin within 10 mm of its target
    y_band = float(on.x[idx, 1].mean())
    assert abs(y_band - y_waist) < 3e-3
    assert m["support_max_displacement_mm"] < 10.0
    assert m["support_force_n"] <= m["support_force_sum_n"] and m["support_force_n"] > 0
    assert on.support_stiffness == pytest.approx(m["weight_n"] / (idx.numel() * COARSE.support_sag))
    # without the support the band rides well away from the waist plane
    assert abs(float(off.x[idx, 1].mean()) - y_waist) > 1e-2
    assert off.support_indices is None and off.metrics["support"] is None


def test_garments_without_a_support_are_unchanged(body12):
    """The T-shirt hangs from its shoulders: no pins, and the support flag changes nothing."""
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    tee = draft("tshirt", chart_row("12"))
    settings = DrapeSettings(edge_length=0.08, voxel_size=0.01, max_iterations=5, sew_max_iterations=5)
    a = drape(tee, body12, settings=settings)
    assert a.support_indices is None and a.metrics["support"] is None
    assert "pins" not in a.stages[-1].effects


def test_support_needs_the_body_mesh(body12):
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft
    from torchgarment.sdf import BodySDF, SDFSettings

    sdf = BodySDF.cached(body12.vertices, body12.faces, SDFSettings(voxel_size=0.01))
    skirt = draft("straight_skirt", chart_row("12"))
    settings = DrapeSettings(edge_length=0.08, voxel_size=0.01, max_iterations=2, sew_max_iterations=2)
    with pytest.raises(InputError, match="needs the body mesh"):
        drape(skirt, sdf, settings=settings)
    r = drape(skirt, sdf, settings=DrapeSettings(edge_length=0.08, voxel_size=0.01, max_iterations=2,
                                                 sew_max_iterations=2, support=False))
    assert math.isfinite(r.metrics["residual"])


def _drape_parser():
    import argparse

    from torchgarment.sim.drape_cli import add_drape_parser

    parser = argparse.ArgumentParser()
    add_drape_parser(parser.add_subparsers(dest="command"))
    return parser


def test_drape_cli_support_errors(tmp_path):
    parser = _drape_parser()
    out = str(tmp_path / "o")
    for support, msg in (("skirt_front:belt", "no edge 'belt'"), ("cape:waist_r", "no panel 'cape'"),
                         ("skirt_front", "expected PANEL:EDGE"),
                         ("skirt_front:waist_r", "do not form one closed loop")):
        args = parser.parse_args(["drape", "--pattern", "straight_skirt", "--body", "12", "--out", out,
                                  "--support", support])
        with pytest.raises(InputError, match=msg) as info:
            args.func(args)
        assert "\n" not in str(info.value) and str(info.value).startswith("--support")
    args = parser.parse_args(["drape", "--pattern", "straight_skirt", "--body", "12", "--out", out,
                              "--support", "skirt_front:waist_r", "--no-support"])
    with pytest.raises(InputError, match="exclude each other"):
        args.func(args)
    assert not (tmp_path / "o").exists()


def test_drape_cli_proposes_a_support_for_a_file_without_one(tmp_path, capsys):
    """A skirt pattern file with no declared support: the topmost closed loop (its waist) is proposed, named
    on stderr and in metrics.json, and held."""
    import json
    from dataclasses import replace

    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.garmentcode import save_pattern
    from torchgarment.pattern.library import draft

    skirt = replace(draft("straight_skirt", chart_row("12")), support=())
    save_pattern(tmp_path / "skirt.json", skirt)
    args = _drape_parser().parse_args(["drape", "--pattern", str(tmp_path / "skirt.json"), "--body", "12",
                                       "--out", str(tmp_path / "o"), "--edge-length", "0.08", "--voxel",
                                       "0.01", "--max-iterations", "3", "--no-progress",
                                       "--allow-unconverged"])
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert args.func(args) == 0
    finally:
        torch.set_num_threads(n)
    err = capsys.readouterr().err
    assert "support: proposed skirt_front:waist_r,skirt_front:waist_l,skirt_back:waist_r,skirt_back:waist_l" \
        in err
    m = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert m["support"] == "skirt_front:waist_r,skirt_front:waist_l,skirt_back:waist_r,skirt_back:waist_l"
    assert m["support_vertices"] > 0 and "support_force_n" in m and "support_max_displacement_mm" in m


def test_a_mesh_drapes_with_its_patterns_support_loop(skirt_drapes, body12):
    """A mesh without its pattern (a clothing basis keeps only the mesh) is held by its SupportLoop exactly as
    the pattern's drape holds it; without the loop it hangs by its tension like the unsupported drape."""
    from torchgarment.pattern.meshing import mesh_pattern
    from torchgarment.sim.support import SupportLoop

    pattern, on, off = skirt_drapes
    mesh = mesh_pattern(pattern, COARSE.edge_length)
    loop = SupportLoop.of(pattern, mesh)
    assert loop is not None and loop.name == on.metrics["support"]
    saved = {k: v.clone() if torch.is_tensor(v) else v for k, v in loop.to_dict().items()}
    back = SupportLoop.from_dict(saved)
    assert torch.equal(back.indices, loop.indices) and torch.equal(back.arc, loop.arc)
    assert (back.length, back.name) == (loop.length, loop.name) and SupportLoop.from_dict(None) is None
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        held = drape(mesh, body12, settings=COARSE, support=loop)
        off_settings = DrapeSettings(edge_length=0.05, voxel_size=0.01, support=False)
        hanging = drape(mesh, body12, settings=off_settings, support=loop)
    finally:
        torch.set_num_threads(n)
    assert torch.equal(held.support_indices, on.support_indices)
    assert float((held.x - on.x).abs().max()) <= 1e-9
    assert held.metrics["support"] == on.metrics["support"]
    assert hanging.support_indices is None and float((hanging.x - off.x).abs().max()) <= 1e-9
    with pytest.raises(InputError, match="does not belong to this mesh"):
        drape(mesh_pattern(pattern, 0.1), body12, settings=COARSE, support=loop)
