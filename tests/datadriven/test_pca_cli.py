"""Tests of the ``torchgarment pca build`` / ``pca fit`` subcommands (torchgarment.datadriven.cli)."""

from __future__ import annotations

import argparse
import json
from types import SimpleNamespace

import pytest
import torch

import torchgarment.datadriven.basis as basis_mod
from torchgarment.datadriven.cli import add_pca_parser, load_model
from torchgarment.errors import InputError
from torchgarment.io.mesh import load_mesh, save_obj


def run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="torchgarment")
    add_pca_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


def fake_drape(mesh, vertices, faces, reference, settings, frame=None, start=None, support=None):
    """Affine stand-in for the simulator (fast): the garment moves with the body's first vertices."""
    body = vertices[: mesh.num_vertices].double()
    x = basis_mod.place_for_body(mesh.x, reference, reference) + 0.1 * (body - body.mean(0))
    return SimpleNamespace(x=x,
                           metrics={"vertices": mesh.num_vertices, "iterations": 1, "converged": True,
                                    "ok": True,
                                         "min_sdf_mm": 1.0, "inside_vertices": 0, "max_seam_gap_mm": 0.0,
                                         "residual": 0.0})


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("pca") / "model"
    cache = tmp_path_factory.mktemp("cache")
    mp = pytest.MonkeyPatch()
    mp.setattr(basis_mod, "drape_on_body", fake_drape)
    try:
        rc = run(["pca", "build", "--garment", "straight_skirt", "--bodies", "5", "--k", "2", "--edge-length",
                  "0.08",
                  "--voxel", "0.01", "--cache", str(cache), "--out", str(out), "--no-progress"])
    finally:
        mp.undo()
    assert rc == 0
    return out


def test_build_writes_model(model_dir):
    assert {p.name for p in model_dir.iterdir()} == {"pca.pt", "basis.pt", "model.json"}
    info = json.loads((model_dir / "model.json").read_text())
    assert info["k"] == 2 and info["bodies"] == 5 and info["garment"] == "straight_skirt"
    assert set(info["drapes"]) == {"mean", "plus_0", "minus_0", "plus_1", "minus_1"}
    assert info["all_drapes_ok"] is True and 0 < info["explained_variance"] <= 1
    pca, basis, _ = load_model(model_dir)
    assert basis.k == 2 and basis.pca_fingerprint == pca.fingerprint()
    # the skirt's waistband is kept in the basis (its drapes and refines hold it at each body's waist)
    assert basis.support is not None and basis.support.name.startswith("skirt_front:waist")


def test_fit_writes_garment_and_metrics(model_dir, tmp_path):
    from torchgarment.body.anny_phenotype import body_from_phenotype, sample_phenotypes

    body = body_from_phenotype(sample_phenotypes(1, seed=77)[0])
    save_obj(tmp_path / "b.obj", body.vertices, body.faces)
    out = tmp_path / "fit"
    rc = run(["pca", "fit", "--model", str(model_dir), "--body", str(tmp_path / "b.obj"), "--out", str(out),
              "--push-out"])
    assert rc == 0
    assert (out / "garment.obj").is_file()
    m = json.loads((out / "metrics.json").read_text())
    assert m["k"] == 2 and len(m["weights"]) == 2
    for key in ("weights", "fit", "push_out", "total"):
        assert m["seconds"][key] >= 0
    assert m["penetrations"]["inside_after_push_out"] == 0
    # the weights are the projection of the body
    pca, _, _ = load_model(model_dir)
    from torchgarment.body.load import load_body

    w = pca.project(load_body(tmp_path / "b.obj").vertices, 2)
    assert torch.allclose(torch.tensor(m["weights"], dtype=torch.float64), w, atol=1e-9)
    # the skirt has a waistband: by default it hangs from the body's waist plane (--no-anchor: as blended)
    assert m["anchored"] is True and m["seconds"]["anchor"] > 0
    for name, extra in (("anchored", []), ("plain", ["--no-anchor"])):
        assert run(["pca", "fit", "--model", str(model_dir), "--body", str(tmp_path / "b.obj"), "--out",
                    str(tmp_path / name), *extra]) == 0
    m2 = json.loads((tmp_path / "plain" / "metrics.json").read_text())
    assert m2["anchored"] is False and m2["seconds"]["anchor"] < 0.01
    (a, _), (b, _) = (load_mesh(tmp_path / n / "garment.obj") for n in ("anchored", "plain"))
    d = a - b  # a rigid vertical move
    assert float(d[:, [0, 2]].abs().max()) < 1e-6
    assert float(d[:, 1].max() - d[:, 1].min()) < 1e-6 and float(d[:, 1].abs().max()) > 1e-5


def test_fit_rejects_other_topology_and_missing_model(model_dir, tmp_path):
    tet = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
    save_obj(tmp_path / "tet.obj", tet, torch.tensor([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]]))
    with pytest.raises(InputError, match="topology"):
        run(["pca", "fit", "--model", str(model_dir), "--body", str(tmp_path / "tet.obj"),
             "--out", str(tmp_path / "o")])
    assert not (tmp_path / "o").exists()
    with pytest.raises(InputError, match="no such folder"):
        run(["pca", "fit", "--model", str(tmp_path / "none"), "--body", str(tmp_path / "tet.obj"),
             "--out", str(tmp_path / "o")])
    with pytest.raises(InputError, match="no such file"):
        run(["pca", "fit", "--model", str(model_dir), "--body", str(tmp_path / "none.obj"),
             "--out", str(tmp_path / "o")])


def test_build_regression_drapes_every_body_and_fits_anchored(tmp_path, monkeypatch):
    """``pca build --fit regression``: one drape per sampled body, a symmetric (linear) basis that keeps the
    skirt's support; ``pca fit`` hangs it from the body's waist plane."""
    monkeypatch.setattr(basis_mod, "drape_on_body", fake_drape)
    out = tmp_path / "model"
    assert run(["pca", "build", "--garment", "straight_skirt", "--bodies", "5", "--k", "1", "--edge-length",
                "0.08", "--voxel", "0.01", "--cache", str(tmp_path / "cache"), "--out", str(out),
                "--no-progress", "--fit", "regression"]) == 0
    info = json.loads((out / "model.json").read_text())
    assert info["fit"] == "regression" and len(info["drapes"]) == 5 and info["k"] == 1
    pca, basis, _ = load_model(out)
    assert torch.allclose(basis.plus - basis.mean, basis.mean - basis.minus, atol=1e-12)
    assert basis.support is not None
    body = pca.reconstruct(0.5 * pca.sigmas[:1])
    save_obj(tmp_path / "b.obj", body, pca.faces)
    assert run(["pca", "fit", "--model", str(out), "--body", str(tmp_path / "b.obj"), "--out",
                str(tmp_path / "fit")]) == 0
    assert json.loads((tmp_path / "fit" / "metrics.json").read_text())["anchored"] is True
    with pytest.raises(InputError, match="needs the anchor"):
        run(["pca", "fit", "--model", str(out), "--body", str(tmp_path / "b.obj"), "--out",
             str(tmp_path / "fit2"), "--no-anchor"])


def test_build_rejects_bad_options(tmp_path):
    with pytest.raises(InputError, match="at least 3"):
        run(["pca", "build", "--garment", "straight_skirt", "--bodies", "2", "--out", str(tmp_path / "m")])
    with pytest.raises(InputError, match="c must"):
        run(["pca", "build", "--garment", "straight_skirt", "--bodies", "4", "--c", "0", "--out",
             str(tmp_path / "m")])
    with pytest.raises(SystemExit):
        run(["pca", "build", "--bodies", "4", "--out", str(tmp_path / "m")])  # no garment
    assert not (tmp_path / "m").exists()


def test_build_from_a_folder_of_meshes(tmp_path, monkeypatch):
    from torchgarment.datadriven.dataset import BodyDataset

    ds = BodyDataset.from_anny(4, seed=9)
    folder = tmp_path / "bodies"
    for i in range(4):
        save_obj(folder / f"b{i}.obj", ds.vertices[i], ds.faces)
    monkeypatch.setattr(basis_mod, "drape_on_body", fake_drape)
    out = tmp_path / "model"
    rc = run(["pca", "build", "--garment", "aline_skirt", "--dataset", str(folder), "--k", "1",
              "--edge-length",
              "0.1", "--cache", str(tmp_path / "cache"), "--out", str(out), "--no-progress"])
    assert rc == 0
    info = json.loads((out / "model.json").read_text())
    assert info["bodies"] == 4 and info["source"] == "meshes" and info["seed"] is None
    pca, _, _ = load_model(out)
    assert torch.allclose(pca.mean, ds.vertices.mean(dim=0), atol=1e-9)


def test_fit_refine_settles_the_prediction(model_dir, tmp_path):
    """Issue 15: ``--refine N`` starts the quasistatic solve at the PCA prediction and runs at most N
    iterations; the result is no farther from equilibrium than the prediction."""
    from torchgarment.body.anny_phenotype import body_from_phenotype, sample_phenotypes

    body = body_from_phenotype(sample_phenotypes(1, seed=78)[0])
    save_obj(tmp_path / "b.obj", body.vertices, body.faces)
    out = {}
    for n in (0, 30):
        rc = run(["pca", "fit", "--model", str(model_dir), "--body", str(tmp_path / "b.obj"), "--out",
                  str(tmp_path / f"r{n}"), "--refine", str(n)])
        assert rc == 0
        out[n] = json.loads((tmp_path / f"r{n}" / "metrics.json").read_text())
    assert out[0]["refine"]["iterations"] == 0 and 0 < out[30]["refine"]["iterations"] <= 30
    assert out[30]["refine"]["residual_n"] < out[0]["refine"]["residual_n"]
    assert out[30]["seconds"]["refine"] > 0
    # the refine holds the waistband at the waist (1 mm outside the section's hull) with this test model's
    # 1 cm SDF grid: measured 2 of 154 vertices 0.12 mm inside by exact distance (the push-out's job)
    assert out[30]["penetrations"]["min_distance_mm"] > -1.0
    with pytest.raises(InputError, match="--refine must be >= 0"):
        run(["pca", "fit", "--model", str(model_dir), "--body", str(tmp_path / "b.obj"), "--out",
             str(tmp_path / "bad"), "--refine", "-1"])


def test_fit_bodies_batches_many_bodies_like_single_fits(model_dir, tmp_path):
    """The batched path (one model load, one weights and fit call for all bodies) writes each body's folder
    as ``pca fit`` does, with the same garment; a bad body fails alone."""
    from torchgarment.body.anny_phenotype import body_from_phenotype, sample_phenotypes
    from torchgarment.cli import build_parser
    from torchgarment.datadriven.cli import fit_bodies

    paths = []
    for i, phenotype in enumerate(sample_phenotypes(3, seed=5)):
        body = body_from_phenotype(phenotype)
        paths.append(tmp_path / f"b{i}.obj")
        save_obj(paths[-1], body.vertices, body.faces)
    jobs = [(str(paths[0]), tmp_path / "m0"), (str(tmp_path / "missing.obj"), tmp_path / "mx"),
            (str(paths[1]), tmp_path / "m1"), (str(paths[2]), tmp_path / "m2")]
    args = build_parser().parse_args(["pca", "fit", "--model", str(model_dir), "--body", "-", "--out", "-",
                                      "--push-out"])
    outcomes = fit_bodies(args, jobs)
    assert isinstance(outcomes[1], InputError) and "missing.obj" in str(outcomes[1])
    assert not (tmp_path / "mx").exists()
    for i, n in ((0, 0), (1, 2), (2, 3)):
        assert isinstance(outcomes[n], str) and outcomes[n].startswith("pca fit ")
        assert run(["pca", "fit", "--model", str(model_dir), "--body", str(paths[i]), "--out",
                    str(tmp_path / f"s{i}"), "--push-out"]) == 0
        batched = json.loads((tmp_path / f"m{i}" / "metrics.json").read_text())
        single = json.loads((tmp_path / f"s{i}" / "metrics.json").read_text())
        assert batched["bodies_in_call"] == 3 and single["bodies_in_call"] == 1
        assert batched["weights"] == pytest.approx(single["weights"], rel=1e-12, abs=1e-12)
        assert batched["penetrations"] == pytest.approx(single["penetrations"], rel=1e-12)
        a, _ = load_mesh(tmp_path / f"m{i}" / "garment.obj")
        b, _ = load_mesh(tmp_path / f"s{i}" / "garment.obj")
        assert float((a - b).abs().max()) <= 1e-9
