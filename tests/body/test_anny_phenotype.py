"""Tests of anny bodies sampled from phenotype parameters (torchgarment.body.anny_phenotype)."""

from __future__ import annotations

import math

import pytest
import torch

from torchgarment.body.anny_phenotype import (
    GIRTH_RANGES,
    PHENOTYPE_NAMES,
    PhenotypeRanges,
    age_from_years,
    body_from_phenotype,
    check_realistic,
    sample_phenotypes,
    vertices_from_phenotypes,
)
from torchgarment.errors import InputError


@pytest.fixture(scope="module")
def sampled():
    phenotypes = sample_phenotypes(8, seed=11)
    return phenotypes, vertices_from_phenotypes(phenotypes)


def test_sampling_is_seeded_and_in_range(sampled):
    phenotypes, _ = sampled
    again = sample_phenotypes(8, seed=11)
    assert again == phenotypes
    other = sample_phenotypes(8, seed=12)
    assert other != phenotypes
    r = PhenotypeRanges.female()
    for ph in phenotypes:
        assert set(PHENOTYPE_NAMES) <= set(ph)
        assert r.gender[0] <= ph["gender"] <= r.gender[1]
        assert r.weight[0] <= ph["weight"] <= r.weight[1]
        assert r.age_years[0] <= ph["age_years"] <= r.age_years[1]
        assert abs(ph["stature"] - r.stature_mean) <= r.stature_clip * r.stature_sd + 1e-12


def test_stature_is_reached_and_frame(sampled):
    phenotypes, v = sampled
    assert v.shape == (8, 13348, 3) and v.dtype == torch.float64
    heights = v[..., 1].amax(dim=1) - v[..., 1].amin(dim=1)
    target = torch.tensor([p["stature"] for p in phenotypes], dtype=torch.float64)
    assert float((heights - target).abs().max()) < 1e-3  # solved to 0.1 mm
    assert float(v[..., 1].amin(dim=1).abs().max()) < 1e-12  # feet at y = 0


def test_age_mapping_anchors():
    a = age_from_years(torch.tensor([11.0, 25.0, 90.0, 57.5], dtype=torch.float64))
    assert torch.allclose(a, torch.tensor([1 / 3, 2 / 3, 1.0, 2 / 3 + 1 / 6], dtype=torch.float64))


def test_body_from_phenotype_matches_batch_and_is_rigged(sampled):
    phenotypes, v = sampled
    body = body_from_phenotype(phenotypes[2])
    assert torch.allclose(body.vertices, v[2], atol=1e-12)
    assert body.skeleton is not None and body.skin_weights is not None
    assert body.skin_weights.shape == (body.skeleton.num_joints, 13348)
    assert torch.allclose(body.skin_weights.sum(dim=0), torch.ones(13348, dtype=torch.float64), atol=1e-9)
    root = body.skeleton.joints[body.skeleton.names.index("root")]
    assert abs(float(root[0])) < 1e-9 and abs(float(root[2])) < 1e-9  # root joint on the Y axis
    assert body.params["phenotype"]["gender"] == pytest.approx(phenotypes[2]["gender"])
    b32 = body_from_phenotype(phenotypes[2], dtype=torch.float32)
    assert b32.vertices.dtype == torch.float32


def test_sampled_bodies_are_realistic(sampled):
    from torchgarment.body.anny_body import load_anny_model
    from torchgarment.body.measure import measure_body

    _, v = sampled
    faces = load_anny_model().faces
    bad = []
    waists = []
    for i in range(4):
        m = measure_body(v[i], faces).to_dict()
        waists.append(m["waist"])
        bad += check_realistic(m, "female")
        assert m["bust"] > m["underbust"]
    assert len(bad) <= 1, bad
    assert 0.6 < sum(waists) / len(waists) < 1.1


def test_check_realistic_flags_out_of_range():
    lo = {k: v[0] for k, v in GIRTH_RANGES["female"].items()}
    assert check_realistic(lo) == []
    assert check_realistic(dict(lo, waist=2.0)) == ["waist"]


def test_male_population_differs():
    ph = sample_phenotypes(3, seed=0, ranges=PhenotypeRanges.for_population("men"))
    assert all(p["gender"] <= 0.1 for p in ph)
    assert sum(p["stature"] for p in ph) / 3 > 1.6


def test_bad_input():
    with pytest.raises(InputError, match="positive integer"):
        sample_phenotypes(0)
    with pytest.raises(InputError, match="weight"):
        sample_phenotypes(2, ranges=PhenotypeRanges(weight=(0.8, 0.2)))
    with pytest.raises(InputError, match="unknown anny parameter"):
        body_from_phenotype({"gender": 1.0, "bmi": 22})
    with pytest.raises(InputError, match="outside"):
        body_from_phenotype({"weight": 1.5})
    with pytest.raises(InputError, match="outside"):
        body_from_phenotype({"weight": math.nan})
    with pytest.raises(InputError, match="unknown"):
        PhenotypeRanges.for_population("robots")
