"""Tests of the built-in pattern library: drafting, seams, widths, placement around the body."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from torchgarment.errors import InputError
from torchgarment.pattern.library import GARMENTS, DraftMeasurements, draft, draft_options, list_garments
from torchgarment.pattern.spec import StitchOrientation

SMALL = {"height": 1.60, "bust": 0.80, "underbust": 0.70, "waist": 0.62, "hips": 0.86}
LARGE = {"height": 1.75, "bust": 1.20, "underbust": 1.05, "waist": 1.05, "hips": 1.25}
BODIES = {"small": SMALL, "large": LARGE}
NAMES = ["straight_skirt", "aline_skirt", "sheath_dress", "tshirt", "trousers", "bodysuit"]


def width_at(panel, y: float) -> float:
    """Width of a panel along the horizontal line at height ``y`` (panel coordinates, metres)."""
    o = panel.outline(resolution=400)
    a, b = o, np.roll(o, -1, axis=0)
    cross = (a[:, 1] - y) * (b[:, 1] - y) < 0
    t = (y - a[cross, 1]) / (b[cross, 1] - a[cross, 1])
    x = a[cross, 0] + t * (b[cross, 0] - a[cross, 0])
    assert x.size >= 2, f"line y={y} misses panel {panel.name}"
    return float(x.max() - x.min())


def outline_3d(panel, resolution: int = 32) -> np.ndarray:
    return panel.to_3d(panel.outline(resolution))


@pytest.fixture(scope="module", params=[(n, b) for n in NAMES for b in BODIES])
def drafted(request):
    name, body = request.param
    return name, body, draft(name, BODIES[body])


def test_registry_names_and_order():
    assert list_garments() == NAMES
    assert list(GARMENTS) == NAMES


def test_drafts_validate_and_record_measurements(drafted):
    name, body, p = drafted
    p.validate(max_stitch_length_ratio=1.02)
    assert p.name == name and p.metadata["garment"] == name
    assert p.metadata["measurements"]["bust"] == BODIES[body]["bust"]
    assert set(p.metadata["options"]) == set(draft_options(name))
    for panel in p.panels.values():
        assert panel.area() > 0.0  # counter-clockwise in panel coordinates


def test_stitched_lengths_match_within_2_percent(drafted):
    _, _, p = drafted
    assert p.stitches
    for s in p.stitches:
        la, lb = p.edge_length(s.a), p.edge_length(s.b)
        assert max(la, lb) / min(la, lb) < 1.02, (s, la, lb)


def test_stitch_orientation_pairs_the_nearer_ends(drafted):
    """OPPOSITE stitches join a.start to b.end: in 3D that pairing must be the closer of the two."""
    _, _, p = drafted
    for s in p.stitches:
        assert s.orientation is StitchOrientation.OPPOSITE
        pa, pb = p.panels[s.a.panel], p.panels[s.b.panel]
        a0, a1 = pa.to_3d(np.stack(pa.edge_endpoints(s.a.edge)))
        b0, b1 = pb.to_3d(np.stack(pb.edge_endpoints(s.b.edge)))
        paired = np.linalg.norm(a0 - b1) + np.linalg.norm(a1 - b0)
        crossed = np.linalg.norm(a0 - b0) + np.linalg.norm(a1 - b1)
        assert paired < crossed, s


def test_normals_point_away_from_body_axis(drafted):
    _, _, p = drafted
    for panel in p.panels.values():
        n = panel.rotation_matrix() @ np.array([0.0, 0.0, 1.0])
        c = outline_3d(panel).mean(axis=0)
        radial = c * np.array([1.0, 0.0, 1.0])
        assert float(n @ radial) > 0.5 * np.linalg.norm(radial), panel.name
        # front panels face +z, back panels -z, with a clearance in front of / behind the body
        if "front" in panel.name or "back" in panel.name:
            sign = 1.0 if "front" in panel.name else -1.0
            assert n[2] * sign > 0.99
            m = DraftMeasurements.from_dict(BODIES[drafted[1]])
            assert sign * c[2] > max(m.bust, m.waist, m.hips) / (2 * math.pi) + 0.02


def test_panels_keep_clear_of_each_other(drafted):
    """Axis-aligned boxes of every two placed panels are separated by >= 1 cm along some axis."""
    _, _, p = drafted
    boxes = {k: (outline_3d(v).min(axis=0), outline_3d(v).max(axis=0)) for k, v in p.panels.items()}
    for (ka, (lo_a, hi_a)), (kb, (lo_b, hi_b)) in itertools.combinations(boxes.items(), 2):
        gap = np.maximum(lo_a - hi_b, lo_b - hi_a)
        assert gap.max() >= 0.01, (ka, kb, gap)


def test_panels_sit_at_body_heights(drafted):
    name, body, p = drafted
    m = DraftMeasurements.from_dict(BODIES[body])
    top = max(outline_3d(v)[:, 1].max() for v in p.panels.values())
    if name in ("straight_skirt", "aline_skirt", "trousers"):
        assert top == pytest.approx(m.waist_height, abs=1e-9)
    else:
        assert m.shoulder_height < top < m.shoulder_height + 0.08  # neck point above the shoulder point
    sleeves = [v for k, v in p.panels.items() if k.startswith("sleeve_")]
    for s in sleeves:  # sleeves run along the arm direction
        x_axis = s.rotation_matrix()[:, 0]
        assert abs(abs(x_axis[1]) - math.sin(m.arm_angle)) < 1e-9


@pytest.mark.parametrize("name", ["straight_skirt", "aline_skirt"])
@pytest.mark.parametrize("body", ["small", "large"])
def test_skirt_waist_and_hip_widths(name, body):
    m = DraftMeasurements.from_dict(BODIES[body])
    opts = draft_options(name)
    p = draft(name, m)
    waist = sum(v.edge_length(i) for v in p.panels.values() for i, e in enumerate(v.edges)
                if e.label.startswith("waist"))
    assert waist == pytest.approx(m.waist + opts["waist_ease"], abs=0.002)
    hips = sum(width_at(v, m.hip_height - 1e-6) for v in p.panels.values())
    assert hips == pytest.approx(m.hips + opts["hip_ease"], abs=0.002)
    # custom ease goes where it should
    q = draft(name, m, hip_ease=0.08, waist_ease=0.0)
    assert sum(width_at(v, m.hip_height - 1e-6) for v in q.panels.values()) == pytest.approx(m.hips + 0.08,
                                                                                             abs=0.002)


def test_aline_flares_and_straight_does_not():
    m = DraftMeasurements.from_dict(SMALL)
    hem_y = m.knee_height - 0.05 + 0.001
    straight = draft("straight_skirt", m)
    aline = draft("aline_skirt", m, flare=0.2)
    hip = sum(width_at(v, m.hip_height - 1e-6) for v in straight.panels.values())
    assert sum(width_at(v, hem_y) for v in straight.panels.values()) == pytest.approx(hip, abs=1e-6)
    y = hem_y + 0.05  # above the curved hem's corners
    expected = hip + 4 * (m.hip_height - y) * math.tan(0.2)
    assert sum(width_at(v, y) for v in aline.panels.values()) == pytest.approx(expected, abs=1e-4)


@pytest.mark.parametrize("body", ["small", "large"])
def test_tshirt_bust_width_and_sleeve_cap(body):
    m = DraftMeasurements.from_dict(BODIES[body])
    opts = draft_options("tshirt")
    p = draft("tshirt", m)
    y = m.bust_height - opts["armhole_drop"] - 1e-6  # the bust width is squared across the armscye line
    bust = width_at(p.panels["tshirt_front"], y) + width_at(p.panels["tshirt_back"], y)
    assert bust == pytest.approx(m.bust + opts["bust_ease"], abs=0.002)
    sleeve = p.panels["sleeve_front_left"]
    bicep = 2 * (sleeve.vertices[:, 1].max() - sleeve.vertices[:, 1].min())
    assert bicep == pytest.approx(m.upper_arm_girth + opts["sleeve_ease"], abs=1e-6)
    eased = draft("tshirt", m, cap_ease=0.06)
    for s in eased.stitches:
        if eased.panels[s.b.panel].edges[s.b.edge].label == "cap":
            ratio = eased.edge_length(s.b) / eased.edge_length(s.a)
            assert ratio == pytest.approx(1.06, abs=1e-3)


@pytest.mark.parametrize("body", ["small", "large"])
def test_trousers_and_bodysuit_girths(body):
    m = DraftMeasurements.from_dict(BODIES[body])
    t = draft("trousers", m)
    hips = sum(width_at(v, m.hip_height - 1e-6) for v in t.panels.values())
    assert hips == pytest.approx(m.hips + draft_options("trousers")["hip_ease"], abs=0.002)
    waist = sum(v.edge_length(i) for v in t.panels.values() for i, e in enumerate(v.edges)
                if e.label == "waist")
    assert waist == pytest.approx(m.waist + draft_options("trousers")["waist_ease"], abs=0.002)
    # one leg's girth just below the crotch is at least thigh + ease
    leg = width_at(t.panels["front_left"], m.crotch_height - 0.01) + width_at(t.panels["back_left"],
                                                                             m.crotch_height - 0.01)
    assert leg >= m.thigh_girth + draft_options("trousers")["thigh_ease"] - 0.03
    b = draft("bodysuit", m)
    for y, g in ((m.waist_height - 1e-6, m.waist), (m.hip_height + 1e-6, m.hips),
                 (m.bust_height - 1e-6, m.bust)):
        assert sum(width_at(v, y) for v in b.panels.values()) == pytest.approx(g, abs=0.002)


@pytest.mark.parametrize("name", NAMES)
def test_every_garment_scales_with_measurements(name):
    small, large = draft(name, SMALL), draft(name, LARGE)

    def extent(p):
        pts = np.concatenate([outline_3d(v) for v in p.panels.values()])
        return pts.max(axis=0) - pts.min(axis=0)

    def area(p):
        return sum(v.area() for v in p.panels.values())

    assert area(large) > 1.15 * area(small)
    es, el = extent(small), extent(large)
    assert el[0] > es[0] and el[1] > es[1] * 1.03 and el[2] > es[2]
    taller = draft(name, {**SMALL, "height": 1.80})
    assert extent(taller)[1] > 1.08 * es[1]


def test_measurement_defaults_and_overrides():
    m = DraftMeasurements.from_dict(SMALL)
    assert m.waist_height == pytest.approx(0.634 * 1.60)
    assert m.crotch_height == pytest.approx((0.634 - 0.171) * 1.60)
    assert m.knee_height < m.crotch_height < m.hip_height < m.waist_height < m.bust_height < m.shoulder_height
    m2 = DraftMeasurements.from_dict({**SMALL, "waist_height": 1.05, "arm_angle": 0.5})
    assert m2.waist_height == 1.05 and m2.arm_angle == 0.5
    p = draft("tshirt", m2)
    assert abs(p.panels["sleeve_front_left"].rotation_matrix()[1, 0]) == pytest.approx(math.sin(0.5))
    skirt = draft("straight_skirt", {**SMALL, "waist_height": 1.05})
    assert max(v.vertices[:, 1].max() for v in skirt.panels.values()) == pytest.approx(1.05)


def test_bad_input_raises_input_error():
    with pytest.raises(InputError, match="straight_skirt"):
        draft("ballgown", SMALL)
    with pytest.raises(InputError, match="unknown measurement"):
        draft("tshirt", {**SMALL, "shoe_size": 0.3})
    with pytest.raises(InputError, match="missing"):
        DraftMeasurements.from_dict({"height": 1.6, "bust": 0.8})
    with pytest.raises(InputError, match="unknown option"):
        draft("tshirt", SMALL, hip_ease=0.04, flare=0.1)
    with pytest.raises(InputError):
        draft("straight_skirt", SMALL, hip_ease=-0.01)
    with pytest.raises(InputError):
        draft("straight_skirt", {**SMALL, "height": 160.0})  # centimetres, not metres
    with pytest.raises(InputError):
        draft("straight_skirt", {**SMALL, "waist_height": 0.3})  # below the hips
    with pytest.raises(InputError):
        draft("tshirt", SMALL, bust_ease=float("nan"))


def test_drafts_clear_a_real_body(garmentcode_dir):
    """Every panel point of every garment lies outside GarmentCode's mean female body (winding number)."""
    import igl
    import trimesh
    import yaml

    body = trimesh.load(garmentcode_dir / "bodies" / "mean_female.obj", process=False)
    meas = yaml.safe_load((garmentcode_dir / "bodies" / "mean_female.yaml").read_text())["body"]
    m = DraftMeasurements.from_dict({
        "height": meas["height"] / 100, "bust": meas["bust"] / 100, "underbust": meas["underbust"] / 100,
        "waist": meas["waist"] / 100, "hips": meas["hips"] / 100,
        "arm_angle": math.radians(meas["arm_pose_angle"]),
    })
    v, f = np.asarray(body.vertices, dtype=np.float64), np.asarray(body.faces, dtype=np.int64)
    for name in NAMES:
        p = draft(name, m)
        pts = np.concatenate([_panel_samples(panel) for panel in p.panels.values()])
        w = igl.winding_number(v, f, pts)
        assert np.all(w < 0.5), (name, int((w >= 0.5).sum()))


def _panel_samples(panel, step: float = 0.02) -> np.ndarray:
    """Outline points and a grid of interior points of a panel, placed in 3D: (n, 3)."""
    from matplotlib.path import Path

    o = panel.outline(16)
    lo, hi = o.min(axis=0), o.max(axis=0)
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0], step), np.arange(lo[1], hi[1], step))
    grid = np.stack([gx.ravel(), gy.ravel()], axis=-1)
    inside = grid[Path(o).contains_points(grid)]
    return panel.to_3d(np.concatenate([o, inside]))
