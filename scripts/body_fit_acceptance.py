"""Reach of ``torchgarment body --measurements``: the GarmentCode mean bodies' tape measurements, graded.

For each of the three GarmentCode mean bodies (``mean_female``, ``mean_male``, ``mean_all``), the request is
the YAML's height, bust, underbust, waist and hips (cm -> m), then the same with bust, underbust, waist and
hips all moved by +-5.08 and +-10.16 cm (2 and 4 inches), and with bust, waist and hips moved by +-5.08 cm and
the underbust kept: 21 fits. Each is a cold fit (cache bypassed). Prints one row per fit with every
measurement's error (mm), the largest, the rounds and the seconds; ``--json`` writes the same.

Usage::

    python scripts/body_fit_acceptance.py [--data DIR] [--bodies mean_female ...] [--json out.json]

``DIR`` defaults to ``../shared/data/garmentcode`` next to the repository. Pass: every fit within 3 mm.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import yaml

BODIES = ("mean_female", "mean_male", "mean_all")
KEYS = ("height", "bust", "underbust", "waist", "hips")
ALL = ("bust", "underbust", "waist", "hips")
KEPT_UNDERBUST = ("bust", "waist", "hips")
MOVES = [("as measured", (), 0.0)] + [
    (f"{', '.join(ALL)} {d:+.2f} cm", ALL, d) for d in (5.08, -5.08, 10.16, -10.16)
] + [(f"{', '.join(KEPT_UNDERBUST)} {d:+.2f} cm", KEPT_UNDERBUST, d) for d in (5.08, -5.08)]


def requests(data: Path, bodies: tuple[str, ...]) -> list[tuple[str, str, dict[str, float]]]:
    """(body, move label, request in metres) for every case."""
    from torchgarment.errors import InputError

    out = []
    for name in bodies:
        path = data / "bodies" / f"{name}.yaml"
        if not path.is_file():
            raise InputError(f"missing {path}: pass --data with GarmentCode's folder")
        measured = yaml.safe_load(path.read_text())["body"]
        base = {k: measured[k] / 100.0 for k in KEYS}
        for label, moved, d in MOVES:
            out.append((name, label, {k: v + (d / 100.0 if k in moved else 0.0) for k, v in base.items()}))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "garmentcode"
    parser.add_argument("--data", type=Path, default=default, help="GarmentCode data folder (with bodies/)")
    parser.add_argument("--bodies", nargs="*", default=list(BODIES), choices=BODIES)
    parser.add_argument("--json", type=Path, default=None, help="also write the rows as JSON here")
    args = parser.parse_args(argv)

    from tqdm import tqdm

    from torchgarment.body.anny_body import FitSettings, body_from_measurements, load_anny_model
    from torchgarment.errors import InputError
    from torchgarment.io.atomic import atomic_open

    try:
        cases = requests(args.data, tuple(args.bodies))
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    load_anny_model()
    accept_mm = 1000.0 * FitSettings().accept
    rows = []
    for name, label, request in tqdm(cases, desc="fits", unit="fit", file=sys.stderr):
        t = time.perf_counter()
        body = body_from_measurements(request, cache=False, closest=True)
        seconds = time.perf_counter() - t
        errors = body.params["reach_errors"]
        rows.append({"body": name, "move": label, "request_m": request, "errors_mm": errors,
                     "max_error_mm": max(abs(e) for e in errors.values()),
                     "rounds": body.params["fit_rounds"], "seconds": seconds,
                     "pass": bool(body.params["reached"])})
    header = (f"{'body':<12} {'move':<40}" + "".join(f"{k:>10}" for k in KEYS)
              + f"{'max mm':>8}{'rounds':>7}{'s':>6}")
    print(header)
    print("-" * len(header))
    for r in rows:
        print(f"{r['body']:<12} {r['move']:<40}" + "".join(f"{r['errors_mm'][k]:>+10.1f}" for k in KEYS)
              + f"{r['max_error_mm']:>8.1f}{r['rounds']:>7}{r['seconds']:>6.1f}"
              + ("" if r["pass"] else "  FAIL"))
    passed = sum(r["pass"] for r in rows)
    seconds = [r["seconds"] for r in rows]
    print(f"{passed}/{len(rows)} within {accept_mm:.0f} mm; largest error "
          f"{max(r['max_error_mm'] for r in rows):.1f} mm; seconds per fit: median "
          f"{statistics.median(seconds):.1f}, max {max(seconds):.1f}")
    if args.json is not None:
        with atomic_open(args.json) as fh:
            json.dump({"accept_mm": accept_mm, "rows": rows}, fh, indent=2)
    return 0 if passed == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
