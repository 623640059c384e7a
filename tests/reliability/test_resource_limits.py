"""Issue 17: a mesh that would not fit in memory (``--edge-length 1e-5``: billions of vertices, memory growing
by 110 MB/s) is refused before meshing, in one line, with exit code 2 and nothing left behind; the limit is
documented and set by ``TORCHGARMENT_MAX_VERTICES``."""

from __future__ import annotations

import pytest

from torchgarment.body.size_chart import chart_row
from torchgarment.errors import InputError
from torchgarment.pattern.library import draft, list_garments
from torchgarment.pattern.meshing import DEFAULT_MAX_VERTICES, estimate_vertices, max_vertices, mesh_pattern


def test_tiny_edge_length_is_refused_before_meshing(tmp_path, cli, one_line):
    for cmd in (["pattern", "--garment", "straight_skirt", "--size", "12"],
                ["drape", "--pattern", "straight_skirt", "--size", "12", "--body", "12", "--no-progress"]):
        proc = cli(*cmd, "--edge-length", "1e-5", "--out", "o", cwd=tmp_path)
        one_line(proc, "would make about 6.68e+09 vertices (limit 500000)")
        assert list(tmp_path.iterdir()) == []  # no output, no hidden staging folder


def test_vertex_estimate_and_limit(monkeypatch):
    for g in list_garments():
        p = draft(g, chart_row("12"))
        assert estimate_vertices(p, 0.03) == pytest.approx(mesh_pattern(p, 0.03).num_vertices, rel=0.15)
    monkeypatch.delenv("TORCHGARMENT_MAX_VERTICES", raising=False)
    assert max_vertices() == DEFAULT_MAX_VERTICES
    skirt = draft("straight_skirt", chart_row("12"))
    monkeypatch.setenv("TORCHGARMENT_MAX_VERTICES", "100")
    with pytest.raises(InputError, match=r"limit 100\)"):
        mesh_pattern(skirt, 0.03)
    monkeypatch.setenv("TORCHGARMENT_MAX_VERTICES", "lots")
    with pytest.raises(InputError, match="TORCHGARMENT_MAX_VERTICES must be a number >= 1"):
        max_vertices()


def test_pca_build_refuses_absurd_body_counts(tmp_path, cli, one_line):
    from torchgarment.datadriven.cli import DEFAULT_MAX_BODIES

    for n in ("1000000000", "100000"):
        proc = cli("pca", "build", "--garment", "straight_skirt", "--bodies", n, "--out", "m", cwd=tmp_path)
        one_line(proc, f"(limit {DEFAULT_MAX_BODIES} bodies)")
        assert list(tmp_path.iterdir()) == []


def test_sdf_build_refuses_absurd_voxels(tmp_path, monkeypatch, cli, one_line):
    """``drape --voxel 1e-5`` made numpy ask for 11.6 TiB; the SDF's memory is estimated first."""
    import numpy as np

    from torchgarment.sdf.build import SDFSettings, build_sdf_grid, estimate_sdf_bytes, max_sdf_bytes

    proc = cli("drape", "--pattern", "straight_skirt", "--size", "12", "--body", "12", "--voxel", "1e-5",
               "--no-progress", "--out", "o", cwd=tmp_path)
    one_line(proc, "GiB (limit 16 GiB)")
    assert list(tmp_path.iterdir()) == []
    # a unit cube: a finer voxel costs more, and the limit is read from the environment
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]],
                 dtype=float)
    f = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4], [2, 6, 3], [3, 6, 7],
                  [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])
    a, b = (estimate_sdf_bytes(v, f, SDFSettings(voxel_size=h)) for h in (0.02, 0.01))
    assert b > 3 * a  # fine nodes grow as voxel^-3 in a shell that narrows with the voxel
    monkeypatch.setenv("TORCHGARMENT_MAX_SDF_GB", "0.001")
    assert max_sdf_bytes() == pytest.approx(0.001 * 2**30)
    with pytest.raises(InputError, match="TORCHGARMENT_MAX_SDF_GB"):
        build_sdf_grid(v, f, SDFSettings(voxel_size=0.01))
    monkeypatch.setenv("TORCHGARMENT_MAX_SDF_GB", "-1")
    with pytest.raises(InputError, match="TORCHGARMENT_MAX_SDF_GB must be a number"):
        max_sdf_bytes()


def test_a_panel_with_absurdly_many_points_is_refused(tmp_path, cli, one_line):
    """A 200,000-vertex panel made ``pattern`` allocate a 37 GiB n x n array in the self-crossing test."""
    import numpy as np

    from torchgarment.errors import PatternError
    from torchgarment.pattern.garmentcode import save_pattern
    from torchgarment.pattern.spec import Edge, Panel, SewingPattern, _first_self_crossing

    def ring(n: int) -> Panel:
        t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
        v = 0.3 * np.stack([np.cos(t), np.sin(t)], axis=1)
        return Panel(name="ring", vertices=v, edges=[Edge(i, (i + 1) % n) for i in range(n)])

    with pytest.raises(PatternError, match="200000 edges, more than 5000"):
        SewingPattern(name="big", panels={"ring": ring(200_000)}).validate()
    SewingPattern(name="ok", panels={"ring": ring(2_000)}).validate()
    # the blocked crossing test finds what the all-pairs one found
    star = np.array([[0, 0], [2, 0], [0, 1], [2, 1]], dtype=float)  # a bow tie: segments 0 and 2 cross
    assert np.allclose(_first_self_crossing(star, block_pairs=1), [1.0, 0.5])
    path = tmp_path / "big.json"
    save_pattern(path, SewingPattern(name="big", panels={"ring": ring(20_000)}))
    one_line(cli("pattern", str(path), "--out", "o", cwd=tmp_path), "more than 5000")
    assert not (tmp_path / "o").exists()


def test_a_pattern_in_the_wrong_units_is_refused_before_meshing(tmp_path, cli, one_line):
    """Every panel x1000 (millimetres read as centimetres) had no size check; ``--edge-length 10`` (10 mm
    meant) wrote a 16-vertex garment."""
    import json

    from torchgarment.pattern.garmentcode import save_pattern

    save_pattern(tmp_path / "p.json", draft("straight_skirt", chart_row("12")))
    data = json.loads((tmp_path / "p.json").read_text())
    for panel in data["pattern"]["panels"].values():
        panel["vertices"] = [[1000.0 * c for c in v] for v in panel["vertices"]]
    (tmp_path / "big.json").write_text(json.dumps(data))
    one_line(cli("pattern", "big.json", "--edge-length", "0.03", "--out", "o", cwd=tmp_path),
             "vertices (limit 500000)")
    line = one_line(cli("pattern", "p.json", "--edge-length", "10", "--out", "o", cwd=tmp_path),
                    "longer than the largest panel")
    assert "edge lengths are in metres" in line
    assert not (tmp_path / "o").exists()
