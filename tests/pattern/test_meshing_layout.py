"""The vertex layout mesh_pattern records (GarmentMesh.layout): edge runs on the outline, seams, copies."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchgarment.body.size_chart import chart_row
from torchgarment.errors import MeshError
from torchgarment.pattern import StitchOrientation, draft
from torchgarment.pattern.meshing import edge_segment_counts, mesh_pattern
from torchgarment.structures import GarmentMesh, MeshLayout


@pytest.mark.parametrize("garment", ["straight_skirt", "tshirt"])
def test_layout_runs_lie_on_their_edges(garment: str) -> None:
    pattern = draft(garment, chart_row("12"))
    h = 0.05
    mesh = mesh_pattern(pattern, h)
    layout = mesh.layout
    assert isinstance(layout, MeshLayout)
    assert layout.panel_names == mesh.panel_names == tuple(pattern.panels)
    assert layout.num_vertices == mesh.num_vertices
    vp = mesh.vertex_panel_ids
    counts = edge_segment_counts(pattern, h)
    p = mesh.p.numpy()
    for k, (name, panel) in enumerate(pattern.panels.items()):
        start, stop = int(layout.panel_starts[k]), int(layout.panel_starts[k + 1])
        assert bool((vp[start:stop] == k).all()) and int((vp == k).sum()) == stop - start
        runs = layout.runs(name)
        assert [len(r) - 1 for r in runs] == counts[name].tolist()
        boundary = layout.boundary(name)
        assert len(boundary) == int(counts[name].sum()) == int(layout.boundary_counts[k])
        # runs chain around the outline: each starts where the previous ended, the last closes the loop
        assert torch.equal(torch.cat([r[:-1] for r in runs]), boundary)
        for i, r in enumerate(runs):
            assert int(r[-1]) == int(runs[(i + 1) % len(runs)][0])
            a, b = panel.edge_endpoints(i)
            np.testing.assert_allclose(p[int(r[0])], a, atol=1e-9)
            np.testing.assert_allclose(p[int(r[-1])], b, atol=1e-9)
            assert torch.equal(layout.run(name, i), r)
        # the outline is the panel's boundary loop in the mesh
        loop_vertices = {int(v) for loop in mesh.boundary_loops for v in loop if int(vp[v]) == k}
        assert loop_vertices == set(boundary.tolist())


def test_layout_gives_the_seam_pairs() -> None:
    pattern = draft("tshirt", chart_row("12"))
    mesh = mesh_pattern(pattern, 0.05)
    pairs = set()
    for s in pattern.stitches:
        a, b = mesh.layout.run(s.a.panel, s.a.edge), mesh.layout.run(s.b.panel, s.b.edge)
        if s.orientation is StitchOrientation.OPPOSITE:
            b = b.flip(0)
        pairs |= {tuple(sorted(ab)) for ab in zip(a.tolist(), b.tolist(), strict=True) if ab[0] != ab[1]}
    assert pairs == {tuple(x) for x in mesh.seam_pairs.tolist()}


def test_layout_travels_with_copies_and_is_checked() -> None:
    mesh = mesh_pattern(draft("straight_skirt", chart_row("12")), 0.05, dtype=torch.float32)
    layout = mesh.layout
    assert mesh.with_positions(mesh.x + 1).layout is layout
    assert mesh.to(dtype=torch.float64).layout is layout
    assert mesh.clone().layout is layout
    assert GarmentMesh.from_arrays(mesh.x, mesh.faces, p=mesh.p, panel_ids=mesh.panel_ids,
                                   panel_names=mesh.panel_names, layout=layout).layout is layout
    welded, _ = mesh.welded()
    assert welded.layout is None
    with pytest.raises(MeshError, match="layout"):
        GarmentMesh(mesh.x[:-1], mesh.faces[:3], layout=layout)
    with pytest.raises(MeshError, match="no panel"):
        layout.runs("sleeve")
    with pytest.raises(MeshError, match="no edge"):
        layout.run(layout.panel_names[0], 99)
    with pytest.raises(MeshError, match="MeshLayout needs"):
        MeshLayout(("a",), layout.panel_starts, layout.boundary_counts, layout.edge_runs)
