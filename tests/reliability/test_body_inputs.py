"""Issue 17: bodies that cannot be a standing human in metres (millimetres, centimetres, upside down, lying, a
single triangle) are refused in one line with exit code 2 before any heavy work (the SDF of a body in
centimetres took 22 GB; one upside down "converged"), naming the factor that would fix the units; nothing is
written."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torchgarment.body.load import check_human_body
from torchgarment.errors import InputError
from torchgarment.io.mesh import save_obj


@pytest.fixture(scope="module")
def body_files(tmp_path_factory) -> dict[str, Path]:
    from torchgarment.body import Body

    body = Body.from_size("12")
    d = tmp_path_factory.mktemp("bodies")
    v, f = body.vertices, body.faces
    flipped = v.clone()
    flipped[:, 1] = -flipped[:, 1]
    lying = v[:, [0, 2, 1]].clone()
    stray = torch.cat([v, torch.tensor([[0.0, 5.0, 0.0]], dtype=v.dtype)])
    files = {"metres": (v, f), "mm": (1000.0 * v, f), "cm": (100.0 * v, f), "upside_down": (flipped, f),
             "lying": (lying, f), "stray": (stray, f),
             "triangle": (torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]]),
                          torch.tensor([[0, 1, 2]]))}
    out = {}
    for name, (vv, ff) in files.items():
        out[name] = d / f"{name}.obj"
        save_obj(out[name], vv, ff)
    return out




def test_check_human_body(body_files):
    from torchgarment.io.mesh import load_mesh

    check_human_body(*load_mesh(body_files["metres"]))
    for name, needle in (("mm", "if it is in millimetres: scale it by 0.001"),
                         ("cm", "if it is in centimetres: scale it by 0.01"), ("upside_down", "upside down"),
                         ("lying", "+Y up"), ("triangle", "outside 0.4-2.8 m"),
                         ("stray", "1 vertices are used by no face")):
        with pytest.raises(InputError, match=needle.replace("+", r"\+")):
            check_human_body(*load_mesh(body_files[name]), name=name)
    v, f = load_mesh(body_files["metres"])
    with pytest.raises(InputError, match="non-finite"):
        check_human_body(torch.where(torch.arange(v.shape[0])[:, None] == 0, float("nan"), v), f)


def test_measure_refuses_a_body_in_millimetres(body_files, tmp_path, cli, one_line):
    proc = cli("measure", str(body_files["mm"]), "--out", "m.json", cwd=tmp_path)
    one_line(proc, "scale it by 0.001")
    assert not (tmp_path / "m.json").exists()
    one_line(cli("measure", str(body_files["cm"]), "--out", "m.json", cwd=tmp_path), "scale it by 0.01")
    assert not (tmp_path / "m.json").exists()
    # stray points were reported as "not a standing human body"
    proc = cli("measure", str(body_files["stray"]), "--out", "m.json", cwd=tmp_path)
    one_line(proc, "used by no face (stray points, the first at [0.0, 5.0, 0.0])")
    assert not (tmp_path / "m.json").exists()


def test_pca_fit_refuses_a_body_in_millimetres_first(body_files, tmp_path, cli, one_line):
    """The body is checked before the model is loaded (a body in millimetres asked for 79 TiB in the SDF)."""
    proc = cli("pca", "fit", "--model", "no_model", "--body", str(body_files["mm"]), "--out", "o",
               cwd=tmp_path)
    one_line(proc, "scale it by 0.001")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("name, needle", [("cm", "scale it by 0.01"), ("upside_down", "upside down"),
                                          ("triangle", "human body")])
def test_drape_refuses_before_any_heavy_work(body_files, tmp_path, name, needle, cli, one_line):
    proc = cli("drape", "--pattern", "straight_skirt", "--size", "12", "--body", str(body_files[name]),
                "--out", "o", "--no-progress", cwd=tmp_path)
    one_line(proc, needle)
    assert not (tmp_path / "o").exists()


def test_anny_commands_print_no_warp_cuda_warning(tmp_path):
    """Every anny-loading command printed "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver"
    on a machine without a GPU; warp is now initialized while stderr is muted."""
    code = ("from torchgarment.body.anny_phenotype import body_from_phenotype, sample_phenotypes\n"
            "body_from_phenotype(sample_phenotypes(1, seed=1)[0])\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "Warp" not in proc.stderr and "CUDA" not in proc.stderr, proc.stderr
