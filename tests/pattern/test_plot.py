"""PNG pattern sheets: files written atomically, sheet aspect, seams in stitch colours, mesh overlay, overlay
plot."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from matplotlib.colors import to_rgb
from matplotlib.image import imread

from torchgarment.errors import InputError
from torchgarment.pattern.plot import plot_pattern, plot_pattern_overlay
from torchgarment.pattern.spec import Edge, EdgeKind, EdgeRef, Notch, Panel, SewingPattern, Stitch
from torchgarment.pattern.svg import stitch_color, svg_panel_layout


def _pattern() -> SewingPattern:
    a = Panel("front", [[0, 0], [0.4, 0], [0.4, 0.6], [0, 0.6]], [
        Edge(0, 1), Edge(1, 2, EdgeKind.QUADRATIC, controls=[[0.5, 0.15]]), Edge(2, 3), Edge(3, 0)],
        notches=[Notch(0, 0.5)])
    b = Panel("back", [[0, 0], [0.4, 0], [0.4, 0.6], [0, 0.6]], [
        Edge(0, 1, EdgeKind.CUBIC, controls=[[0.3, -0.1], [0.7, 0.1]]), Edge(1, 2),
        Edge(2, 3, EdgeKind.ARC, arc=(0.25, False, True)), Edge(3, 0)])
    return SewingPattern("test", {"front": a, "back": b}, [Stitch(EdgeRef("front", 3), EdgeRef("back", 1))])


class _FakeMesh:
    """Duck-typed panel mesh: two triangles per panel covering each panel's unit square corners."""

    def __init__(self, ids):
        self.p = torch.tensor([[0, 0], [0.4, 0], [0.4, 0.6], [0, 0.6]], dtype=torch.float64)
        self.faces = torch.tensor([[0, 1, 2], [0, 2, 3]] * len(ids))
        self.panel_ids = torch.tensor([i for i in ids for _ in range(2)])


def _has_color(img: np.ndarray, color: str, tol: float = 0.06, min_pixels: int = 30) -> bool:
    rgb = np.asarray(to_rgb(color))
    return int((np.abs(img[..., :3] - rgb).max(axis=-1) < tol).sum()) >= min_pixels


def test_plot_pattern(tmp_path):
    pat = _pattern()
    plot_pattern(pat, tmp_path / "p.png", title="test")
    assert [f.name for f in tmp_path.iterdir()] == ["p.png"]
    img = imread(tmp_path / "p.png")
    _, sheet = svg_panel_layout(pat)
    h, w = img.shape[:2]
    assert abs(w / h - sheet[0] / (sheet[1] + 0.5 * sheet.max() / 14)) < 0.05  # sheet aspect plus title band
    assert _has_color(img, stitch_color(0), min_pixels=200)  # the seam, both sides
    assert not _has_color(img, stitch_color(1))  # there is no second stitch
    assert not _has_color(img, "#6c7a89")  # no mesh drawn


def test_plot_with_mesh(tmp_path):
    pat = _pattern()
    plot_pattern(pat, tmp_path / "m.png", mesh=_FakeMesh([0, 1]))
    img = imread(tmp_path / "m.png")
    assert _has_color(img, "#6c7a89", tol=0.12, min_pixels=100)
    mesh = _FakeMesh([0, 1])
    mesh.panel_names = ("back", "front")  # names decide, not the pattern order
    plot_pattern(pat, tmp_path / "n.png", mesh=mesh)
    bad = _FakeMesh([0, 5])
    with pytest.raises(InputError, match="panel_ids"):
        plot_pattern(pat, tmp_path / "bad.png", mesh=bad)
    bad = _FakeMesh([0])
    bad.p = bad.p[:, :1]
    with pytest.raises(InputError, match=r"\(V, 2\)"):
        plot_pattern(pat, tmp_path / "bad.png", mesh=bad)
    bad = _FakeMesh([0])
    bad.panel_names = ("sleeve",)
    with pytest.raises(InputError, match="sleeve"):
        plot_pattern(pat, tmp_path / "bad.png", mesh=bad)
    assert not (tmp_path / "bad.png").exists()


def test_overlay(tmp_path):
    old = _pattern()
    new = copy.deepcopy(old)
    new.panels["front"].vertices[2] += [0.05, 0.03]
    new.panels["yoke"] = Panel("yoke", [[0, 0], [0.2, 0], [0.1, 0.1]], [Edge(0, 1), Edge(1, 2), Edge(2, 0)])
    plot_pattern_overlay(old, new, tmp_path / "o.png", title="adjusted")
    img = imread(tmp_path / "o.png")
    assert _has_color(img, "#1f4e9c", min_pixels=300)
    assert _has_color(img, "#7f7f7f", tol=0.1, min_pixels=100)
