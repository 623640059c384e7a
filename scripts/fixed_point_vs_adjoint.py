"""The fixed-point method of Bartle et al. 2016 against the adjoint method, on the positional cost only
(Wang 2018, section 8.1 and Fig. 13).

Usage:
    python scripts/fixed_point_vs_adjoint.py --out DIR [--garment straight_skirt] [--base-size 12]
        [--target-size 20] [--edge-length 0.04] [--voxel 0.01] [--iterations 32] [--threads 1]

The objective keeps only the positional cost (Eq. 16) and a tiny fixing regularizer (its Hessian is the
preconditioner and must be positive definite); no initialization, so both methods start from the base pattern.
Writes ``DIR/fixed_point_vs_adjoint.png`` (objective vs iteration and vs wall time), ``.json`` and TensorBoard
runs under ``DIR/tb/``.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from compare_optimizers import add_case_arguments, load_case, save_figure  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_case_arguments(ap, 32)
    ap.add_argument("--fixing", type=float, default=1e-2, help="fixing coefficient (1/m^2)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchgarment.adjust.objective import CostWeights
    from torchgarment.adjust.pipeline import AdjustSettings, optimize, prepare
    from torchgarment.io.atomic import atomic_open

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    pattern, base, target = load_case(args)
    weights = CostWeights(distance=0.0, smoothness=0.0, stretching=0.0, positional=100.0, fixing=args.fixing,
                          curvature=0.0, seam=0.0)
    settings = AdjustSettings(edge_length=args.edge_length, voxel_size=args.voxel, iterations=args.iterations,
                              weights=weights, initialize=False)
    setup = prepare(pattern, base, target, settings)
    runs = {}
    for label, tb, s in [("fixed-point", "fixed_point", replace(settings, optimizer="fixed-point")),
                         ("adjoint (pgd, Algorithm 1)", "adjoint_pgd", replace(settings, optimizer="pgd")),
                         ("adjoint (gn)", "adjoint_gn", replace(settings, optimizer="gn"))]:
        rows = [(0, 0.0, setup.objective_initial)]
        res = optimize(setup, s, log_dir=out / "tb" / tb, progress=True,
                       callback=lambda rec, terms, rows=rows: rows.append((rec.iteration, rec.seconds,
                                                                           terms.get("positional",
                                                                                     rec.objective))))
        runs[label] = {"rows": rows, "final": res.metrics["objective_final"],
                       "positional_final": res.metrics["terms"]["final"].get("positional"),
                       "seconds": res.metrics["seconds"], "closure_calls": res.metrics["closure_calls"]}
        print(f"{label:28s} final {res.metrics['objective_final']:.5g} "
              f"(from {setup.objective_initial:.5g}), {res.metrics['closure_calls']} closure calls, "
              f"{res.metrics['seconds']:.1f} s")
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for label, r in runs.items():
        axes[0].semilogy([x[0] for x in r["rows"]], [x[2] for x in r["rows"]], label=label)
        axes[1].semilogy([x[1] for x in r["rows"]], [x[2] for x in r["rows"]], label=label)
    axes[0].set_xlabel("iteration")
    axes[1].set_xlabel("wall time (s)")
    for ax in axes:
        ax.set_ylabel("positional cost")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.suptitle(f"fixed point vs adjoint, {setup.mesh_base.num_vertices} vertices")
    fig.tight_layout()
    save_figure(fig, out / "fixed_point_vs_adjoint.png")
    with atomic_open(out / "fixed_point_vs_adjoint.json") as fh:
        json.dump({"objective_start": setup.objective_initial, "runs": runs}, fh, indent=2)
    print(f"-> {out / 'fixed_point_vs_adjoint.png'}")


if __name__ == "__main__":
    main()
