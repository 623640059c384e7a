"""Supports (torchgarment.pattern.support): library declarations, the proposal rule, ``--support`` parsing,
the GarmentCode round trip and the support's mesh vertices."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from torchgarment.body.size_chart import chart_row
from torchgarment.errors import InputError, PatternError
from torchgarment.pattern.library import draft, list_garments
from torchgarment.pattern.support import (
    choose_support,
    format_support,
    free_loops,
    ordered_loop,
    parse_support,
    propose_support,
    support_loop_length,
    support_vertices,
)

EXPECTED = {
    "straight_skirt": {("skirt_front", "waist_r"), ("skirt_front", "waist_l"), ("skirt_back", "waist_r"),
                       ("skirt_back", "waist_l")},
    "aline_skirt": {("skirt_front", "waist_r"), ("skirt_front", "waist_l"), ("skirt_back", "waist_r"),
                    ("skirt_back", "waist_l")},
    "trousers": {("front_left", "waist"), ("front_right", "waist"), ("back_left", "waist"),
                 ("back_right", "waist")},
    "tshirt": set(),
    "sheath_dress": set(),
    "bodysuit": set(),
}


@pytest.mark.parametrize("garment", list_garments())
def test_every_library_garment_declares_its_support(garment):
    pattern = draft(garment, chart_row("12"))
    assert set(pattern.support) == EXPECTED[garment] and len(pattern.support) == len(EXPECTED[garment])
    # the proposal rule, applied to the library garment without its declaration, finds the same loop
    assert set(propose_support(replace(pattern, support=()))) == EXPECTED[garment]
    if pattern.support:
        loop = ordered_loop(pattern)
        assert len(loop) == len(pattern.support)
        # the waistband keeps the drafted waist: its rest length is the chart waist plus the waist ease (1 cm)
        ease = pattern.metadata["options"]["waist_ease"]
        assert support_loop_length(pattern) == pytest.approx(chart_row("12")["waist"] + ease, abs=1e-9)


def test_free_loops_are_the_openings():
    counts = {g: len(free_loops(draft(g, chart_row("12")))) for g in list_garments()}
    # skirt: waist + hem; trousers: waist + 2 hems; T-shirt: neck + hem + 2 cuffs
    assert counts["straight_skirt"] == 2 and counts["trousers"] == 3 and counts["tshirt"] == 4


def test_parse_support_and_its_errors():
    pattern = draft("straight_skirt", chart_row("12"))
    spec = format_support(pattern.support)
    assert parse_support(spec, pattern) == pattern.support
    # by index as well as by label
    idx = pattern.edge_index("skirt_front", "waist_r")
    mixed = spec.replace("skirt_front:waist_r", f"skirt_front:{idx}")
    assert [pattern.edge_index(p, e) for p, e in parse_support(mixed, pattern)] == \
        [pattern.edge_index(p, e) for p, e in pattern.support]
    cases = [
        ("skirt_front", "expected PANEL:EDGE"),
        ("cape:waist_r", "no panel 'cape'"),
        ("skirt_front:belt", "no edge 'belt'"),
        ("skirt_front:99", "no edge '99'"),
        ("skirt_front:waist_r,skirt_front:waist_l", "do not form one closed loop"),
        ("skirt_front:side_low_r", "is stitched"),
        (f"{spec},skirt_front:waist_r", "names an edge twice"),
        ("", "give PANEL:EDGE"),
    ]
    for bad, msg in cases:
        with pytest.raises(InputError, match=msg) as info:
            parse_support(bad, pattern)
        assert "\n" not in str(info.value)


def test_validate_checks_the_support():
    pattern = draft("straight_skirt", chart_row("12"))
    with pytest.raises(PatternError, match="closed loop"):
        replace(pattern, support=pattern.support[:2]).validate()
    with pytest.raises(PatternError, match="no panel"):
        replace(pattern, support=(("cape", "waist_r"),)).validate()


def test_choose_support_rule():
    skirt = draft("straight_skirt", chart_row("12"))
    bare = replace(skirt, support=())
    chosen, note = choose_support(bare, None)
    assert chosen.support and set(chosen.support) == EXPECTED["straight_skirt"]
    assert note is not None and "proposed" in note and "skirt_front:waist_r" in note and "\n" not in note
    assert choose_support(skirt, None) == (skirt, None)  # declared: kept, no note
    assert choose_support(bare, None, enabled=False) == (bare, None)
    tee = draft("tshirt", chart_row("12"))
    assert choose_support(tee, None) == (tee, None)  # hangs from the shoulders: nothing proposed
    with pytest.raises(InputError, match="no panel"):
        choose_support(skirt, "front:waist")


def test_garmentcode_round_trip_keeps_the_support(tmp_path):
    from torchgarment.pattern.garmentcode import load_pattern, save_pattern

    pattern = draft("trousers", chart_row("12"))
    save_pattern(tmp_path / "t.json", pattern)
    assert load_pattern(tmp_path / "t.json").support == pattern.support
    tee = draft("tshirt", chart_row("12"))
    save_pattern(tmp_path / "s.json", tee)
    assert load_pattern(tmp_path / "s.json").support == ()


def test_support_vertices_follow_the_loop():
    from torchgarment.pattern.meshing import mesh_pattern

    pattern = draft("straight_skirt", chart_row("12"))
    mesh = mesh_pattern(pattern, 0.03)
    idx, s, length = support_vertices(pattern, mesh)
    assert idx.dtype == torch.long and len(set(idx.tolist())) == idx.numel()
    expected = set()
    for p, e in pattern.support:
        expected |= set(mesh.layout.run(p, pattern.edge_index(p, e)).tolist())
    assert set(idx.tolist()) == expected
    # the waist edges are straight: the meshed loop has the pattern's length, arc lengths increase
    assert length == pytest.approx(support_loop_length(pattern), abs=1e-9)
    assert bool((s[1:] >= s[:-1] - 1e-12).all()) and float(s[0]) == 0.0
    # the loop closes at a stitched corner: its other vertex comes last, at arc length L (the same point as 0)
    assert float(s[-1]) == pytest.approx(length, abs=1e-12)
    # consecutive vertices of the loop are neighbours: rest distance equals the arc-length step (a stitched
    # corner's two vertices share one arc length)
    ds = s[1:] - s[:-1]
    assert float(ds.max()) <= 0.03 + 1e-9


def _garmentcode_skirt(data):
    from torchgarment.pattern.garmentcode import load_pattern
    from torchgarment.pattern.spec import SewingPattern

    dress = load_pattern(data / "dress_pencil_specification.json")
    keep = {"skirt_front", "skirt_back"}
    stitches = [s for s in dress.stitches if s.a.panel in keep and s.b.panel in keep]
    skirt = SewingPattern("pencil_skirt", {n: dress.panels[n] for n in keep}, stitches)
    skirt.validate()
    return dress, skirt


def test_proposed_loop_on_a_garmentcode_skirt(garmentcode_dir):
    """GarmentCode's pencil dress without its bodice is a skirt with back darts: its topmost loop is the waist
    seam the bodice was sewn to (every edge labelled ``lower_interface``, darts excluded)."""
    data = garmentcode_dir / "patterns"
    dress, skirt = _garmentcode_skirt(data)
    proposed = propose_support(skirt)
    want = {(n, i) for n in ("skirt_front", "skirt_back") for i, e in enumerate(skirt.panels[n].edges)
            if e.label == "lower_interface"}
    assert {(p, skirt.edge_index(p, e)) for p, e in proposed} == want and len(want) == 9
    assert parse_support(format_support(proposed), skirt) == proposed
    # the whole dress hangs from its shoulders, as do the other GarmentCode tops
    assert propose_support(dress) == ()
    from torchgarment.pattern.garmentcode import load_pattern

    for name in ("shirt_mean", "hoody_mean", "js_mean_all"):
        assert propose_support(load_pattern(data / f"{name}_specification.json")) == (), name
