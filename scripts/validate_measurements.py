"""Compare torchgarment's tape-measure body measurements with GarmentCode's YAML measurements.

Usage:
    python scripts/validate_measurements.py [--data DIR] [--json PATH]

``DIR`` defaults to ``../shared/data/garmentcode`` next to the repository. Prints, for the three mean bodies,
ours vs the YAML value vs the difference in cm for height and every girth (``-`` where the YAML has no
equivalent: ``upper_arm``, ``neck``). ``--json`` also writes the numbers (cm) to ``PATH``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
import trimesh
import yaml

from torchgarment.body.measure import GIRTH_NAMES, measure_body
from torchgarment.errors import InputError
from torchgarment.io.atomic import atomic_open

BODIES = ("mean_female", "mean_male", "mean_all")
YAML_KEY = {"height": "height", "bust": "bust", "underbust": "underbust", "waist": "waist", "hips": "hips",
            "thigh": "leg_circ", "wrist": "wrist"}


def validate(data_dir: Path) -> dict[str, dict[str, dict[str, float | None]]]:
    """Measure each mean body; return {body: {measurement: {ours, yaml, diff}}} in cm."""
    out = {}
    for name in BODIES:
        obj, yml = data_dir / "bodies" / f"{name}.obj", data_dir / "bodies" / f"{name}.yaml"
        if not obj.is_file() or not yml.is_file():
            raise InputError(f"missing {obj} or {yml}")
        mesh = trimesh.load(obj, process=False)
        ref = yaml.safe_load(yml.read_text())["body"]
        meas = measure_body(torch.tensor(mesh.vertices, dtype=torch.float64), torch.tensor(mesh.faces))
        rows = {}
        for key, value in meas.to_dict().items():
            ours = 100.0 * value
            theirs = ref.get(YAML_KEY[key]) if key in YAML_KEY else None
            rows[key] = {"ours": ours, "yaml": theirs, "diff": None if theirs is None else ours - theirs}
        out[name] = rows
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "garmentcode"
    parser.add_argument("--data", type=Path, default=default, help="GarmentCode data folder (with bodies/)")
    parser.add_argument("--json", type=Path, default=None, help="also write the table as JSON here")
    args = parser.parse_args(argv)
    try:
        table = validate(args.data)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    keys = ("height", *GIRTH_NAMES)
    print(f"{'cm':<11}" + "".join(f"{b:>27}" for b in BODIES))
    print(f"{'':<11}" + "".join(f"{'ours':>9}{'yaml':>9}{'diff':>9}" for _ in BODIES))
    for key in keys:
        line = f"{key:<11}"
        for b in BODIES:
            r = table[b][key]
            y = "-" if r["yaml"] is None else f"{r['yaml']:.2f}"
            d = "-" if r["diff"] is None else f"{r['diff']:+.2f}"
            line += f"{r['ours']:>9.2f}{y:>9}{d:>9}"
        print(line)
    if args.json is not None:
        with atomic_open(args.json) as fh:
            json.dump(table, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
