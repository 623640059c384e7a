"""Tests of body data sets of one topology (torchgarment.datadriven.dataset)."""

from __future__ import annotations

import pytest
import torch

from torchgarment.datadriven.dataset import BodyDataset
from torchgarment.errors import InputError, MeshError
from torchgarment.io.mesh import save_obj

TET_FACES = torch.tensor([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]], dtype=torch.long)


def tet(scale: float) -> torch.Tensor:
    return scale * torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)


@pytest.fixture(scope="module")
def anny():
    return BodyDataset.from_anny(3, seed=2)


def test_from_anny(anny):
    assert len(anny) == 3 and anny.vertices.shape == (3, 13348, 3)
    assert anny.topology == "anny-noeyes-notongue" and anny.source == "anny"
    assert anny.faces.dtype == torch.long and int(anny.faces.max()) == 13347
    assert "stature" in anny.params[0]
    assert not torch.equal(anny.vertices[0], anny.vertices[1])
    again = BodyDataset.from_anny(3, seed=2)
    assert torch.equal(again.vertices, anny.vertices)


def test_save_load_roundtrip(anny, tmp_path):
    anny.save(tmp_path / "bodies.pt")
    back = BodyDataset.load(tmp_path / "bodies.pt")
    assert torch.equal(back.vertices, anny.vertices) and torch.equal(back.faces, anny.faces)
    assert back.params == anny.params and back.topology == anny.topology
    assert BodyDataset.load(tmp_path / "bodies.pt", dtype=torch.float32).vertices.dtype == torch.float32
    with pytest.raises(InputError, match="does not exist"):
        BodyDataset.load(tmp_path / "nope.pt")
    torch.save({"format": "other"}, tmp_path / "other.pt")
    with pytest.raises(InputError, match="not a torchgarment body dataset"):
        BodyDataset.load(tmp_path / "other.pt")


def test_from_meshes_files_and_pairs(tmp_path):
    paths = []
    for i, s in enumerate((1.0, 1.2, 0.9)):
        p = tmp_path / f"b{i}.obj"
        save_obj(p, tet(s), TET_FACES)
        paths.append(p)
    ds = BodyDataset.from_meshes(paths)
    assert ds.vertices.shape == (3, 4, 3)
    assert torch.allclose(ds.vertices[1], tet(1.2))
    assert ds.params[2]["path"] == str(paths[2])
    ds2 = BodyDataset.from_meshes([(tet(1.0), TET_FACES), (tet(2.0), TET_FACES)])
    assert torch.allclose(ds2.vertices[1], tet(2.0))


def test_topology_mismatch_is_a_clear_error(tmp_path):
    other_faces = TET_FACES[[1, 0, 2, 3]]
    with pytest.raises(MeshError, match="different faces"):
        BodyDataset.from_meshes([(tet(1.0), TET_FACES), (tet(1.0), other_faces)])
    five = torch.cat([tet(1.0), torch.ones(1, 3, dtype=torch.float64)])
    with pytest.raises(MeshError, match="5 vertices but the first mesh has 4"):
        BodyDataset.from_meshes([(tet(1.0), TET_FACES), (five, TET_FACES)])
    with pytest.raises(MeshError, match="no meshes"):
        BodyDataset.from_meshes([])
    with pytest.raises(InputError, match="does not exist"):
        BodyDataset.from_meshes([tmp_path / "missing.obj"])
    ds = BodyDataset.from_meshes([(tet(1.0), TET_FACES), (tet(2.0), TET_FACES)])
    with pytest.raises(MeshError, match="topology"):
        ds.check_topology(five)
    with pytest.raises(MeshError, match="different faces"):
        ds.check_topology(tet(1.0), other_faces)
    ds.check_topology(tet(3.0), TET_FACES)


def test_validation_and_subset():
    with pytest.raises(MeshError):
        BodyDataset(torch.zeros(4, 3, dtype=torch.float64), TET_FACES)
    with pytest.raises(MeshError, match="NaN"):
        BodyDataset(torch.full((1, 4, 3), float("nan"), dtype=torch.float64), TET_FACES)
    with pytest.raises(MeshError, match="outside"):
        BodyDataset(torch.zeros(1, 3, 3, dtype=torch.float64), TET_FACES)
    ds = BodyDataset(torch.stack([tet(1.0), tet(2.0), tet(3.0)]), TET_FACES, [{"i": 0}, {"i": 1}, {"i": 2}])
    sub = ds.subset([2, 0])
    assert [p["i"] for p in sub.params] == [2, 0] and torch.equal(sub.vertices[0], tet(3.0))
    assert len(ds.subset(slice(1, None))) == 2
    assert ds.body(1).vertices.shape == (4, 3)
