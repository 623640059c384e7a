"""GarmentCode JSON: import of the four shared specs, units and placement, round trip, orientation, bad
input."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from torchgarment.errors import PatternError
from torchgarment.pattern import EdgeKind, EdgeRef, Notch, StitchOrientation
from torchgarment.pattern.garmentcode import (
    OrientationRule,
    infer_stitch_orientation,
    load_pattern,
    pattern_from_dict,
    pattern_to_dict,
    save_pattern,
)

SPECS = ["shirt_mean", "hoody_mean", "dress_pencil", "js_mean_all"]


def spec_path(garmentcode_dir, name):
    return garmentcode_dir / "patterns" / f"{name}_specification.json"


@pytest.mark.parametrize("name", SPECS)
def test_import_specs(garmentcode_dir, name):
    raw = json.loads(spec_path(garmentcode_dir, name).read_text())
    p = load_pattern(spec_path(garmentcode_dir, name))
    assert p.name == name
    assert len(p.panels) == len(raw["pattern"]["panels"])
    assert len(p.stitches) == len(raw["pattern"]["stitches"])
    for pname, panel in p.panels.items():
        rp = raw["pattern"]["panels"][pname]
        np.testing.assert_allclose(panel.vertices, np.asarray(rp["vertices"]) / 100.0, rtol=0, atol=1e-12)
        np.testing.assert_allclose(panel.translation, np.asarray(rp["translation"]) / 100.0, atol=1e-12)
        np.testing.assert_allclose(np.rad2deg(panel.rotation), rp["rotation"], atol=1e-9)
        for e, re_ in zip(panel.edges, rp["edges"]):
            assert [e.start, e.end] == re_["endpoints"]
            if "curvature" in re_ and re_["curvature"]["type"] == "circle":
                assert e.kind is EdgeKind.ARC and e.arc[0] == pytest.approx(re_["curvature"]["params"][0]
                                                                            / 100)
    # GarmentCode's own rule: no "right_wrong" entries in these files, so every stitch is OPPOSITE
    assert all(s.orientation is StitchOrientation.OPPOSITE for s in p.stitches)


@pytest.mark.parametrize("name", SPECS)
def test_placement_around_mean_body(garmentcode_dir, name):
    """Placed panels surround the GarmentCode mean body, outward normals point away from it."""
    import igl
    import trimesh

    body = trimesh.load(garmentcode_dir / "bodies" / "mean_all.obj", process=False)
    v, f = np.asarray(body.vertices), np.asarray(body.faces)
    p = load_pattern(spec_path(garmentcode_dir, name))
    for pname, panel in p.panels.items():
        c = panel.to_3d(panel.outline(16)).mean(axis=0)
        s, _, closest = igl.signed_distance(c[None], v, f)[:3]
        assert 0.0 < s[0] < 0.3, pname  # outside the body, within 30 cm of it
        outward = panel.rotation_matrix()[:, 2] * np.sign(panel.area())  # counter-clockwise seen from outside
        d = c - closest[0]
        assert outward @ d / np.linalg.norm(d) > 0.8, pname
        if "ftorso" in pname or "_f" in pname or "front" in pname:
            assert c[2] > 0.05 and outward[2] > 0.99, pname  # front panels at +z facing +z


def test_circle_sweep_and_curvature_direction(garmentcode_dir):
    """Necklines and armholes curve into the panel (checks the 'right' flag and relative controls)."""
    from matplotlib.path import Path

    p = load_pattern(spec_path(garmentcode_dir, "hoody_mean"))
    torso = [(n, i) for n in ("left_btorso", "left_ftorso", "right_btorso", "right_ftorso")
             for i, e in enumerate(p.panels[n].edges) if e.kind is not EdgeKind.LINE]
    assert len(torso) == 8 and {p.panels[n].edges[i].kind for n, i in torso} == {EdgeKind.ARC, EdgeKind.CUBIC}
    for pname, ei in torso:
        panel = p.panels[pname]
        a, b = panel.edge_endpoints(ei)
        mid = panel.edges[ei].evaluate(a, b, np.array([0.5]))[0]
        chord_mid = 0.5 * (a + b)
        assert np.linalg.norm(mid - chord_mid) > 0.005, (pname, ei)
        # bulging into the panel: the curve's middle lies inside the straight-edged corner polygon and the
        # chord's middle is cut away (outside the true outline)
        assert Path(panel.vertices).contains_point(mid), (pname, ei)
        assert not Path(panel.outline(64)).contains_point(chord_mid), (pname, ei)


@pytest.mark.parametrize("name", SPECS)
def test_round_trip(garmentcode_dir, name, tmp_path):
    p = load_pattern(spec_path(garmentcode_dir, name))
    first = next(iter(p.panels.values()))
    first.notches.append(Notch(edge=1, t=0.25, name="front"))
    first.grainline = np.array([0.6, 0.8])
    p.metadata["source"] = "test"
    p.stitches[0].orientation = StitchOrientation.SAME  # explicit key must win over the rule
    out = tmp_path / "rt.json"
    save_pattern(out, p)
    raw = json.loads(out.read_text())
    assert raw["properties"]["units_in_meter"] == 100
    assert raw["pattern"]["stitches"][0][0]["orientation"] == "same"
    assert raw["pattern"]["stitches"][0][2] == "right_wrong"  # GarmentCode's own SAME marker
    q = load_pattern(out)
    assert list(q.panels) == list(p.panels) and q.name == p.name
    for n in p.panels:
        a, b = p.panels[n], q.panels[n]
        np.testing.assert_allclose(a.outline(32), b.outline(32), rtol=0, atol=1e-9)
        np.testing.assert_allclose(a.translation, b.translation, atol=1e-12)
        np.testing.assert_allclose(a.rotation, b.rotation, atol=1e-12)
        assert [e.kind for e in a.edges] == [e.kind for e in b.edges]
        assert [e.label for e in a.edges] == [e.label for e in b.edges] and a.label == b.label
        assert a.notches == b.notches
        np.testing.assert_allclose(a.grainline, b.grainline)
    assert [(s.a, s.b, s.orientation) for s in p.stitches] == [(s.a, s.b, s.orientation) for s in q.stitches]
    assert q.metadata == p.metadata
    # a second save is byte-identical
    out2 = tmp_path / "rt2.json"
    save_pattern(out2, q)
    assert out2.read_text() == out.read_text()


def two_panels(flip_back: bool) -> dict:
    """A front and a back rectangle 20 cm apart, stitched along their right sides (GarmentCode form, cm).

    Both run counter-clockwise seen from outside. With ``flip_back`` the back panel's outline is reversed
    (drawn the wrong way round), so its stitched edge runs the same way as the front's.
    """
    front = {"translation": [0, 100, 10], "rotation": [0, 0, 0],
             "vertices": [[0, 0], [20, 0], [20, 30], [0, 30]],
             "edges": [{"endpoints": [0, 1]}, {"endpoints": [1, 2]}, {"endpoints": [2, 3]},
                       {"endpoints": [3, 0]}]}
    back_v = [[0, 0], [0, 30], [20, 30], [20, 0]]  # clockwise in 2D = counter-clockwise seen from -z
    back = {"translation": [0, 100, -10], "rotation": [0, 0, 0], "vertices": back_v,
            "edges": [{"endpoints": [0, 1]}, {"endpoints": [1, 2]}, {"endpoints": [2, 3]},
                      {"endpoints": [3, 0]}]}
    stitch_edge = 2  # back's right side (20, 30) -> (20, 0)
    if flip_back:
        back["vertices"] = [[0, 0], [20, 0], [20, 30], [0, 30]]
        stitch_edge = 1  # (20, 0) -> (20, 30): same direction as the front's edge 1
    return {"pattern": {"panels": {"front": front, "back": back},
                        "stitches": [[{"panel": "front", "edge": 1},
                                      {"panel": "back", "edge": stitch_edge}]]},
            "properties": {"units_in_meter": 100}}


@pytest.mark.parametrize("flip_back, expected",
                         [(False, StitchOrientation.OPPOSITE), (True, StitchOrientation.SAME)])
def test_orientation_inferred_from_placement(flip_back, expected):
    d = two_panels(flip_back)
    p = pattern_from_dict(d, "two", orientation_rule=OrientationRule.PLACEMENT)
    assert p.stitches[0].orientation is expected
    assert infer_stitch_orientation(p.panels, EdgeRef("front", 1), p.stitches[0].b) is expected
    # GarmentCode's rule ignores geometry: OPPOSITE unless marked right_wrong
    assert pattern_from_dict(d, "two").stitches[0].orientation is StitchOrientation.OPPOSITE
    d2 = copy.deepcopy(d)
    d2["pattern"]["stitches"][0].append("right_wrong")
    assert pattern_from_dict(d2, "two").stitches[0].orientation is StitchOrientation.SAME
    # an explicit key wins over both rules
    d3 = copy.deepcopy(d)
    for side in d3["pattern"]["stitches"][0]:
        side["orientation"] = "same"
    for rule in OrientationRule:
        stitch = pattern_from_dict(d3, "two", orientation_rule=rule).stitches[0]
        assert stitch.orientation is StitchOrientation.SAME
    d3["pattern"]["stitches"][0][1]["orientation"] = "opposite"
    with pytest.raises(PatternError, match="disagree"):
        pattern_from_dict(d3, "two")


def test_units_absolute_controls_and_legacy_curvature():
    d = two_panels(False)
    d["properties"] = {"units_in_meter": 1000, "curvature_coords": "absolute"}  # millimetres
    d["pattern"]["panels"]["front"]["edges"][0]["curvature"] = {"type": "quadratic", "params": [[10, -5]]}
    d["pattern"]["panels"]["back"]["edges"][0]["curvature"] = [0.5, 0.1]  # legacy form, relative
    d["properties"]["curvature_coords"] = "absolute"
    p = pattern_from_dict(d, "mm", validate=False)
    front = p.panels["front"]
    np.testing.assert_allclose(front.vertices[2], [0.02, 0.03])
    np.testing.assert_allclose(front.translation, [0, 0.1, 0.01])
    # absolute control (10, -5) mm on edge (0,0)->(20,0) mm is relative (0.5, -0.25)
    np.testing.assert_allclose(front.edges[0].controls, [[0.5, -0.25]])
    assert p.panels["back"].edges[0].kind is EdgeKind.QUADRATIC


def test_bad_input(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text('{"pattern": {"panels": ')
    with pytest.raises(PatternError, match="malformed JSON at line 1"):
        load_pattern(bad)
    with pytest.raises(PatternError, match="no such file"):
        load_pattern(tmp_path / "missing.json")
    with pytest.raises(PatternError, match="missing key 'pattern'"):
        pattern_from_dict({"properties": {}})
    with pytest.raises(PatternError, match="JSON object"):
        pattern_from_dict([1, 2])

    def broken(edit):
        d = two_panels(False)
        edit(d)
        return d

    cases = [
        (lambda d: d["pattern"]["stitches"][0][1].update(panel="sleeve"), "unknown panel 'sleeve'"),
        (lambda d: d["pattern"]["stitches"][0][1].update(edge=7),
         r"stitch 0 side 1 edge of panel 'back' = 7 is out of range"),
        (lambda d: d["pattern"]["panels"]["front"]["edges"][2].update(endpoints=[2, 9]),
         r"panel 'front' edge 2 end vertex = 9 is out of range"),
        (lambda d: d["pattern"]["panels"]["front"]["edges"][3].update(endpoints=[2, 0]),
         "panel 'front' does not close"),
        (lambda d: d["pattern"]["panels"]["front"].update(vertices=[[0, 0], [1]]),
         "panel 'front' vertices must be"),
        (lambda d: d["pattern"]["panels"]["back"]["edges"][1].update(curvature={"type": "spline",
                                                                                "params": []}),
         "panel 'back' edge 1 has unknown curvature type 'spline'"),
        (lambda d: d["pattern"]["panels"]["back"]["edges"][1].update(curvature={"type": "cubic",
                                                                                "params": [[0.5, 1]]}),
         "panel 'back' edge 1 cubic params must be"),
        (lambda d: d["pattern"]["panels"]["front"].update(rotation=[0, "x", 0]), "panel 'front' rotation"),
        (lambda d: d["pattern"]["panels"]["front"].pop("edges"), "panel 'front': missing key 'edges'"),
        (lambda d: d["pattern"]["panels"]["front"].update(notches=[{"edge": 0, "t": 2.0}]),
         "notch 0 t must be"),
        (lambda d: d["properties"].update(units_in_meter=0), "units_in_meter"),
        (lambda d: d["pattern"]["stitches"][0].append("inside_out"), "third entry must be 'right_wrong'"),
    ]
    for edit, msg in cases:
        with pytest.raises(PatternError, match=msg) as info:
            pattern_from_dict(broken(edit), "bad")
        assert "\n" not in str(info.value)
    # the file name is part of the message
    f = tmp_path / "open_specification.json"
    f.write_text(json.dumps(broken(cases[3][0])))
    with pytest.raises(PatternError, match="open_specification.json: panel 'front' does not close"):
        load_pattern(f)


def test_save_rejects_unserializable_metadata(tmp_path):
    p = pattern_from_dict(two_panels(False), "two")
    p.metadata["obj"] = object()
    with pytest.raises(PatternError, match="cannot be written as JSON"):
        save_pattern(tmp_path / "x.json", p)
    assert not (tmp_path / "x.json").exists()
    assert pattern_to_dict(pattern_from_dict(two_panels(False), "two"))["name"] == "two"
