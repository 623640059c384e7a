"""Does the objective of pattern adjustment prefer the chart-drafted pattern? (the grading diagnosis of issue
4)

The library drafts every garment from a size-chart row, so a pattern drafted for the target size is the
grading a pattern maker would give. This script evaluates the adjustment objective (Eq. 17, on the target
body, at the exact equilibrium) for:

- ``base``: the base pattern unchanged;
- ``initialized``: the section-7 initialization;
- ``drafted``: the pattern drafted for the target size, resampled with the base mesh's boundary counts (same
  mesh topology) and moved onto the base panels by the best rigid motion per panel (the fixing term is not
  rigid-invariant);
- ``adjusted``: the result of the optimization;

and prints each one's terms and the pattern's line-width changes (waist, hips or bust, waist) against the
drafted pattern's. When ``drafted`` scores far above ``adjusted``, the objective's minimum is not the chart's
grading: a better optimizer cannot close the gap.

Usage:
    python scripts/adjust_drafted_vs_adjusted.py [--garment straight_skirt] [--base-size 12]
        [--target-size 20] [--edge-length 0.03] [--voxel 0.01] [--iterations 64]
        [--reference-edge-length 0.008] [--stretch-stiffness 25] [--threads 1] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:
    from torchgarment.adjust.pipeline import AdjustSetup
    from torchgarment.pattern.spec import SewingPattern


def drafted_boundary(setup: AdjustSetup, drafted: SewingPattern, edge_length: float) -> torch.Tensor:
    """(B, 2) boundary of ``drafted`` with the base mesh's per-edge sample counts, in the row order of
    ``setup.param``, each panel moved onto the base panel by its best rigid motion."""
    from torchgarment.errors import PatternError
    from torchgarment.pattern.meshing import edge_segment_counts

    mesh = setup.mesh_base
    counts, counts_d = edge_segment_counts(setup.pattern, edge_length), edge_segment_counts(drafted,
                                                                                            edge_length)
    p = mesh.p.detach().cpu().double().numpy().copy()
    vp = mesh.vertex_panel_ids.cpu().numpy()
    names = list(mesh.panel_names)
    for name, panel in drafted.panels.items():
        if name not in names or len(counts[name]) != len(counts_d[name]):
            raise PatternError(f"panel {name!r} of the drafted pattern does not match the base pattern's "
                               "edges")
        off = int(np.nonzero(vp == names.index(name))[0].min())
        n = counts[name]
        b = np.concatenate([e.sample_by_length(*panel.edge_endpoints(i), int(n[i]))[:-1]
                            for i, e in enumerate(panel.edges)])
        p[off:off + b.shape[0]] = b
    bi = setup.param.boundary_index.cpu().numpy()
    q, q_base = p[bi], setup.q_base.cpu().double().numpy()
    panel_of = vp[bi]
    for k in np.unique(panel_of):
        m = panel_of == k
        a, b = q[m], q_base[m]
        ca, cb = a.mean(0), b.mean(0)
        u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
        d = np.sign(np.linalg.det(u @ vt))
        r = (u @ np.diag([1.0, d]) @ vt).T
        q[m] = (a - ca) @ r.T + cb
    return torch.as_tensor(q, dtype=setup.q_base.dtype, device=setup.q_base.device)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--garment", default="straight_skirt", choices=["straight_skirt", "tshirt"])
    ap.add_argument("--base-size", default="12")
    ap.add_argument("--target-size", default="20")
    ap.add_argument("--edge-length", type=float, default=0.03)
    ap.add_argument("--voxel", type=float, default=0.01)
    ap.add_argument("--iterations", type=int, default=64)
    ap.add_argument("--reference-edge-length", type=float, default=None,
                    help="CostWeights.reference_edge_length (default: the paper's coefficients as given)")
    ap.add_argument("--stretch-stiffness", type=float, default=None, help="Material.stretch_stiffness in N")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", default=None, help="write the results to this JSON file")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    sys.path.insert(0, str(Path(__file__).parent))
    from adjust_acceptance import SKIRT_LINES, TSHIRT_LINES, pattern_line_widths

    from torchgarment.adjust.objective import CostWeights
    from torchgarment.adjust.pipeline import AdjustSettings, optimize, prepare
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.io.atomic import atomic_open
    from torchgarment.pattern.library import draft
    from torchgarment.sim.drape import DrapeSettings
    from torchgarment.sim.scene import Material

    base_pattern = draft(args.garment, chart_row(args.base_size))
    drafted = draft(args.garment, chart_row(args.target_size))
    weights = (CostWeights(reference_edge_length=args.reference_edge_length)
               if args.reference_edge_length else None)
    material = (Material() if args.stretch_stiffness is None
                else Material(stretch_stiffness=args.stretch_stiffness))
    settings = AdjustSettings(edge_length=args.edge_length, voxel_size=args.voxel, iterations=args.iterations,
                              weights=weights, drape=DrapeSettings(edge_length=args.edge_length,
                                                                   voxel_size=args.voxel, material=material))
    setup = prepare(base_pattern, Body.from_size(args.base_size), Body.from_size(args.target_size), settings)
    result = optimize(setup, progress=True)
    problem = setup.new_problem(setup.x_transfer)
    settle = setup.settings.drape.max_iterations
    rows = {}
    for name, q in (("base", setup.q_base), ("initialized", setup.q_init),
                    ("drafted", drafted_boundary(setup, drafted, args.edge_length)), ("adjusted", result.q)):
        problem.reset_state(setup.x_transfer)
        ev = problem.evaluate(q, exact=True, need_grad=False, max_iterations=settle)
        rows[name] = {"objective": ev.objective, "terms": problem.term_values()}
    lines = SKIRT_LINES if "skirt" in args.garment else TSHIRT_LINES
    w0 = pattern_line_widths(base_pattern, lines)
    widths = {"adjusted": pattern_line_widths(result.pattern, lines),
              "drafted": pattern_line_widths(drafted, lines)}
    changes = {k: {line: 100.0 * (w[line] - w0[line]) for line in lines} for k, w in widths.items()}

    names = list(rows["base"]["terms"])
    print(f"\n{args.garment} {args.base_size} -> {args.target_size}, {1e3 * args.edge_length:.0f} mm edges, "
          f"{args.iterations} iterations")
    print(f"{'pattern':>12} {'objective':>10} " + " ".join(f"{n:>11}" for n in names))
    for k, r in rows.items():
        print(f"{k:>12} {r['objective']:10.3f} " + " ".join(f"{r['terms'][n]:11.3f}" for n in names))
    for k, c in changes.items():
        print(f"{k:>12} width change cm: " + ", ".join(f"{line} {v:+.2f}" for line, v in c.items()))
    out = {"args": vars(args), "objectives": rows, "width_change_cm": changes, "metrics": result.metrics}
    if args.json:
        with atomic_open(args.json, "w") as f:
            json.dump(out, f, indent=2, default=float)
            f.write("\n")


if __name__ == "__main__":
    main()
