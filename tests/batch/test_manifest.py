"""Batch manifests: expansion of cross products, option mapping onto the single commands, and one clear line
per bad entry (no Ray needed)."""

from __future__ import annotations

import json

import pytest

from torchgarment.batch import ManifestError, load_manifest, parse_manifest
from torchgarment.cli import main


def test_the_issue_example_expands_to_the_single_commands(tmp_path):
    (tmp_path / "pattern.json").write_text("{}")
    (tmp_path / "body.obj").write_text("")
    jobs = parse_manifest({
        "jobs": [{"method": "drape", "garment": "straight_skirt", "size": "6",
                  "settings": {"edge_length": 0.05}},
                 {"method": "drape", "pattern": "pattern.json", "body": "body.obj"}],
        "cross": [{"method": "drape", "garments": ["straight_skirt", "tshirt"], "sizes": ["6", "12"],
                   "settings": {"edge_length": 0.05}}],
    }, base_dir=tmp_path)
    # the first listed job is also in the cross product: kept once
    assert len(jobs) == 5
    first = jobs[0]
    assert first.argv == ("drape", "--pattern", "straight_skirt", "--size", "6", "--body", "6",
                          "--edge-length", "0.05", "--no-progress")
    assert (first.method, first.garment, first.body) == ("drape", "straight_skirt", "6")
    assert [b for b, _ in first.bodies] == ["6"]
    # relative paths are relative to the manifest's folder
    assert jobs[1].argv[2] == str((tmp_path / "pattern.json").resolve())
    assert jobs[1].argv[4] == str((tmp_path / "body.obj").resolve())
    assert (jobs[1].garment, jobs[1].body) == ("pattern", "body")
    assert len({j.id for j in jobs}) == 5
    # a changed setting is another job
    other = parse_manifest({"jobs": [{"method": "drape", "garment": "straight_skirt", "size": "6",
                                      "settings": {"edge_length": 0.04}}]}, base_dir=tmp_path)
    assert other[0].id != first.id and other[0].id.startswith("drape-straight_skirt-6-")


def test_flags_lists_and_mappings_in_cross_products(tmp_path):
    jobs = parse_manifest({"jobs": [{
        "method": "grade", "garment": "straight_skirt", "size": "12",
        "settings": {"sizes": ["10", "14"], "exact": True, "no_init": False, "iterations": 3}}]},
        base_dir=tmp_path)
    argv = jobs[0].argv
    assert argv[:5] == ("grade", "--garment", "straight_skirt", "--base-size", "12")
    assert "--exact" in argv and "--no-init" not in argv
    i = argv.index("--sizes")
    assert argv[i + 1:i + 3] == ("10", "14")
    assert jobs[0].body == "12->10+14"
    assert [b for b, _ in jobs[0].bodies] == ["12", "10", "14"]
    jobs = parse_manifest({"cross": [{"method": "adjust", "garment": "straight_skirt",
                                      "settings": {"base_size": "12"},
                                      "bodies": [{"size": "10"},
                                                 {"size": "14", "settings": {"iterations": 2}}]}]},
                          base_dir=tmp_path)
    assert [j.body for j in jobs] == ["12->10", "12->14"]
    assert "--iterations" in jobs[1].argv and "--iterations" not in jobs[0].argv
    assert "--log-dir" in jobs[0].argv  # TensorBoard scalars into the job's own folder


def test_pca_fit_jobs_share_one_build(tmp_path):
    jobs = parse_manifest({"cross": [{"method": "pca_fit", "garment": "straight_skirt",
                                      "build": {"bodies": 8},
                                      "bodies": ["a.obj", "b.obj"], "settings": {"push_out": True}}]},
                          base_dir=tmp_path)
    assert len(jobs) == 2 and jobs[0].build == jobs[1].build and jobs[0].build_id == jobs[1].build_id
    assert jobs[0].build[:4] == ("pca", "build", "--garment", "straight_skirt")
    assert "--push-out" in jobs[0].argv


@pytest.mark.parametrize("entry, message", [
    ({"method": "dance"}, "method 'dance' is not one of"),
    ({"method": "drape", "garment": "straight_skirt", "size": "6", "settings": {"edge_lenght": 0.05}},
     "'edge_lenght' is not an option of this command"),
    ({"method": "drape", "garment": "straight_skirt", "size": "6", "settings": {"edge_length": "thin"}},
     "invalid float value: 'thin'"),
    ({"method": "drape", "garment": "straight_skirt", "size": "6", "settings": {"solver": "magic"}},
     "invalid choice: 'magic'"),
    ({"method": "drape", "garment": "straight_skirt", "size": "6", "settings": {"no_support": "yes"}},
     "'no_support' is a flag: give true or false"),
    ({"method": "drape", "garment": "straight_skirt", "size": "6", "settings": {"out": "x"}},
     "'out' is set by the batch runner"),
    ({"method": "drape", "pattern": "p.json"}, "the following arguments are required: --body"),
    ({"method": "drape", "garment": "straight_skirt", "size": "6", "colour": "red"},
     "unknown key(s) ['colour']"),
    ({"method": "retarget", "size": "6"}, "method retarget takes no 'size'"),
    ({"method": "pca_fit", "body": "b.obj"}, "a pca_fit job takes 'model'"),
])
def test_bad_entries_get_one_line_each(tmp_path, entry, message):
    with pytest.raises(ManifestError) as info:
        parse_manifest({"jobs": [entry]}, base_dir=tmp_path, name="m.yaml")
    text = str(info.value)
    assert message in text and text.count("\n") == 0 and text.startswith("m.yaml jobs[0]: ")


def test_every_bad_entry_is_reported_and_nothing_runs(tmp_path, capsys):
    manifest = tmp_path / "m.json"
    manifest.write_text(json.dumps({"jobs": [
        {"method": "drape", "garment": "straight_skirt", "size": "6"},
        {"method": "dance"},
        {"method": "drape", "garment": "straight_skirt", "size": "6", "settings": {"voxel": -1, "bogus": 1}},
    ], "cross": [{"method": "drape", "garments": "straight_skirt"}]}))
    out = tmp_path / "out"
    assert main(["batch", str(manifest), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "jobs[1]: method 'dance'" in err and "jobs[2]: setting 'bogus'" in err
    assert "cross[0]: 'garments' must be a non-empty list" in err
    assert not out.exists()


@pytest.mark.parametrize("text, message", [
    ("jobs: [\n", "not valid YAML"),
    ("- a\n- b\n", "expected a mapping with 'jobs'"),
    ("jobs: {method: drape}\n", "'jobs' must be a list"),
])
def test_unreadable_manifests(tmp_path, text, message):
    path = tmp_path / "m.yaml"
    path.write_text(text)
    with pytest.raises(Exception) as info:
        load_manifest(path)
    assert message in str(info.value) and "Traceback" not in str(info.value)
