"""Held-out accuracy of data-driven garment fitting (Gillies et al. 2004) against full drapes, as a function
of k.

N training anny adults give the PCA body model; a garment drafted for the mean body is draped on the mean and
the +-c sigma_i example bodies (the clothing basis, cached and resumable). For each of H held-out bodies
(sampled with another seed) the same garment mesh, placed by the same rule, is fully draped (the reference,
also cached), and the PCA garment for k = 0..kmax components is compared with it: mean and max vertex
distance (mm), vertices inside the body (exact signed distance) before and after the push-out, and the body's
own rank-k reconstruction error. A garment with a support (the skirt's waistband) is shown both as blended and
anchored (``anchor`` column): moved vertically to hang from each body's measured waist plane, as its drape
does (:meth:`~torchgarment.datadriven.online.OnlineFitter.anchors`); the refine starts from the anchored
prediction unless ``--no-anchor``.

``--fit regression`` replaces the 2 kmax + 1 example drapes with cold drapes of the N training bodies and a
least-squares linear model of them (``BasisSettings.fit``; N more drapes, cached the same way).

The references' own reproducibility (``--reference-noise``): each held-out body moved by 0.1 mm along x
(the SDF's grid samples shift; nothing a customer would notice) is draped cold again and compared with its
reference (the translation taken back out). A drape with several equilibria lands on another one for some
bodies, so no method can be judged closer to the reference than this floor.

Example (about 30 drapes; tens of minutes on 2 CPU cores)::

    python scripts/pca_heldout.py --train 60 --heldout 20 --kmax 3 --json /tmp/pca_heldout.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import statistics
import sys
import time
from pathlib import Path

import torch

REFERENCE_SHIFT_M = 1e-4
"""How far ``--reference-noise`` moves each held-out body (metres) before draping it again."""

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def main(argv: list[str] | None = None) -> int:
    from torchgarment.datadriven.basis import BasisFit

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train", type=int, default=60, help="training bodies (default 60)")
    ap.add_argument("--heldout", type=int, default=20, help="held-out bodies (default 20)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the training bodies (held-out: seed + 1000)")
    ap.add_argument("--garment", default="straight_skirt", help="library garment (default straight_skirt)")
    ap.add_argument("--hip-ease", type=float, default=0.06,
                    help="hip ease of the skirt drafts (default 0.06 m)")
    ap.add_argument("--kmax", type=int, default=3, help="largest k (components draped: 2 kmax + 1 drapes)")
    ap.add_argument("--c", type=float, default=1.0, help="example bodies at +-c sigma (default 1)")
    ap.add_argument("--edge-length", type=float, default=0.05, help="garment edge length, m (default 0.05)")
    ap.add_argument("--voxel", type=float, default=0.01, help="SDF voxel size, m (default 0.01)")
    ap.add_argument("--cache", default=None, help="cache folder (default $TORCHGARMENT_CACHE/clothing_basis)")
    ap.add_argument("--refine", type=int, nargs="*", default=[25, 100, 400], metavar="N",
                    help="settle budgets of the warm-started refine from the k = kmax piecewise prediction "
                         "(default 25 100 400; none: skip)")
    ap.add_argument("--time-cold", type=int, default=5, metavar="H",
                    help="cold drapes re-timed in this run, on the first H held-out bodies (default 5)")
    ap.add_argument("--fit", default=BasisFit.EXAMPLES.value, choices=[m.value for m in BasisFit],
                    help="clothing basis: Gillies' example drapes (default) or a least-squares model of the "
                         "training bodies' cold drapes (BasisSettings.fit)")
    ap.add_argument("--no-continuation", action="store_true",
                    help="basis drapes from the placed panels instead of continued from the mean drape")
    ap.add_argument("--no-support", action="store_true",
                    help="drapes (basis, references, refines) without the skirt's support: it hangs by its "
                         "waist tension, as before the basis kept the support")
    ap.add_argument("--reference-noise", type=int, default=None, metavar="H",
                    help="re-drape the first H held-out bodies moved by 0.1 mm and compare with their "
                         "references (the floor of every error here; default: all held-out bodies; 0: skip)")
    ap.add_argument("--no-anchor", action="store_true",
                    help="refine from the unanchored prediction (the table shows both; OnlineFitter.anchors)")
    ap.add_argument("--json", default=None, metavar="FILE", help="write the results as JSON")
    args = ap.parse_args(argv)
    if args.no_anchor and args.fit == BasisFit.REGRESSION.value:
        ap.error("--no-anchor: a regression basis is fitted relative to the waist plane and needs the anchor")

    from tqdm import tqdm

    from torchgarment.body.measure import measure_body
    from torchgarment.datadriven.basis import (
        BasisSettings,
        BodyFrame,
        Interpolation,
        basis_cache_dir,
        build_basis,
        drape_on_body,
        mesh_hash,
        place_for_body,
    )
    from torchgarment.datadriven.dataset import BodyDataset
    from torchgarment.datadriven.online import OnlineFitter, PushOutResult, push_out
    from torchgarment.datadriven.pca import BodyPCA
    from torchgarment.datadriven.relative import BasisFrame, branch_deviation
    from torchgarment.io.atomic import atomic_path
    from torchgarment.pattern.library import draft
    from torchgarment.pattern.meshing import mesh_pattern
    from torchgarment.sim.drape import DrapeSettings

    t0 = time.perf_counter()
    train = BodyDataset.from_anny(args.train, seed=args.seed)
    held = BodyDataset.from_anny(args.heldout, seed=args.seed + 1000)
    t_data = time.perf_counter() - t0
    pca = BodyPCA.fit(train)
    m = measure_body(pca.mean, pca.faces).to_dict()
    req = {k: m[k] for k in ("height", "bust", "underbust", "waist", "hips")}
    ease = {"hip_ease": args.hip_ease} if "skirt" in args.garment else {}
    pattern = draft(args.garment, req, **ease)
    dsettings = DrapeSettings(edge_length=args.edge_length, voxel_size=args.voxel,
                              support=not args.no_support)
    mesh = mesh_pattern(pattern, args.edge_length)
    settings = BasisSettings(k=args.kmax, c=args.c, drape=dsettings, continuation=not args.no_continuation,
                             fit=args.fit)
    regression = args.fit == BasisFit.REGRESSION.value
    t1 = time.perf_counter()
    basis = build_basis(pca, pattern, settings, name=args.garment, cache_dir=args.cache,
                        bodies=train.vertices if regression else None)
    support = basis.support  # the references and the refines hold the same support as the basis drapes
    t_basis = time.perf_counter() - t1
    reference = BodyFrame.of(pca.mean, pca.faces)

    # full drapes of the held-out bodies (the references), cached per body
    cache = Path(args.cache) if args.cache else basis_cache_dir()
    tag = hashlib.sha256(basis.key.encode() + held.vertices.double().numpy().tobytes()
                         + mesh_hash(mesh).encode() + (b"" if support is None else b"support"))
    ref_dir = cache / f"heldout-{tag.hexdigest()[:20]}"
    refs, ref_metrics, drape_seconds = [], [], []
    for i in tqdm(range(len(held)), desc="held-out full drapes"):
        path = ref_dir / f"body_{i:03d}.pt"
        if path.is_file():
            e = torch.load(path, map_location="cpu", weights_only=True)
        else:
            t = time.perf_counter()
            r = drape_on_body(mesh, held.vertices[i], held.faces, reference, dsettings, support=support)
            e = {"x": r.x.detach().double(), "metrics_json": json.dumps(
                {"ok": r.ok, "converged": r.converged, "min_sdf_mm": r.metrics["min_sdf_mm"],
                 "seconds": time.perf_counter() - t})}
            with atomic_path(path) as tmp:
                torch.save(e, tmp)
        refs.append(e["x"])
        ref_metrics.append(json.loads(e["metrics_json"]))
        drape_seconds.append(ref_metrics[-1]["seconds"])

    def measured(i: int, x: torch.Tensor) -> PushOutResult:
        """Exact distances of x on held-out body i (a push-out of zero passes only measures)."""
        return push_out(x, held.vertices[i], held.faces, iterations=0)

    rows = []
    variants = [(f, i, a) for f in (BasisFrame.ABSOLUTE, BasisFrame.BODY)
                for i in (Interpolation.LINEAR, Interpolation.PIECEWISE) for a in (False, True)]
    anchors = None
    for frame, interp, anchored in variants:
        if (anchored and support is None) or (not anchored and basis.needs_anchor):
            continue
        for k in range(args.kmax + 1):
            fitter = OnlineFitter(pca, {args.garment: basis}, k=k, interpolation=interp, frame=frame)
            tw = time.perf_counter()
            w = fitter.weights(held.vertices)
            tf = time.perf_counter()
            if anchored and anchors is None:  # measured once, timed apart from the fit
                anchors = fitter.anchors(held.vertices)
                anchor_ms = 1e3 * (time.perf_counter() - tf) / len(held)
                tf = time.perf_counter()
            xs = fitter.fit(w, bodies=held.vertices, anchors=anchors if anchored else None)[args.garment]
            tend = time.perf_counter()
            body_err = pca.reconstruction_error(held.vertices, k)
            means, maxes, inside, inside_after = [], [], [], []
            for i in range(len(held)):
                d = torch.linalg.vector_norm(xs[i] - refs[i], dim=1)
                means.append(1e3 * float(d.mean()))
                maxes.append(1e3 * float(d.max()))
                inside.append(measured(i, xs[i]).inside_before)
                inside_after.append(push_out(xs[i], held.vertices[i], held.faces).inside_after)
            rows.append({
                "frame": frame.value, "interpolation": interp.value, "k": k, "anchored": anchored,
                "explained_variance": float(pca.explained_variance_ratio[:k].sum()),
                "mean_error_mm": statistics.mean(means), "max_error_mm": max(maxes),
                "median_of_max_error_mm": statistics.median(maxes),
                "inside_vertices_mean": statistics.mean(inside), "inside_vertices_max": max(inside),
                "inside_after_push_out_max": max(inside_after),
                "body_reconstruction_mean_mm": 1e3 * float(body_err["mean"].mean()),
                "weights_ms_per_body": 1e3 * (tf - tw) / len(held),
                "fit_ms_per_body": 1e3 * (tend - tf) / len(held),
                "anchor_ms_per_body": anchor_ms if anchored else 0.0,
            })
    ref_inside = [measured(i, refs[i]).inside_before for i in range(len(held))]
    # each example drape against the mean drape carried onto its body (a regression has no example drapes)
    branch = {} if regression else branch_deviation(basis, pca)

    # warm-started refine (issue 15): the k = kmax piecewise prediction settled for N iterations, against the
    # cold drape; both timed here with the body's SDF built beforehand (its build is the same for both)
    from torchgarment.body.body import Body
    from torchgarment.datadriven.online import refine
    from torchgarment.sdf import BodySDF, SDFSettings

    # the references' reproducibility: the same cold drape of the body moved by 0.1 mm
    shift = torch.tensor([REFERENCE_SHIFT_M, 0.0, 0.0], dtype=held.vertices.dtype)
    noise_means, noise_maxes = [], []
    n_noise = len(held) if args.reference_noise is None else min(args.reference_noise, len(held))
    for i in tqdm(range(n_noise), desc="reference reproducibility"):
        r = drape_on_body(mesh, held.vertices[i] + shift, held.faces, reference, dsettings, support=support)
        d = torch.linalg.vector_norm(r.x.detach().double() - shift.double() - refs[i], dim=1)
        noise_means.append(1e3 * float(d.mean()))
        noise_maxes.append(1e3 * float(d.max()))
    noise = ({"bodies": n_noise, "shift_mm": 1e3 * REFERENCE_SHIFT_M,
              "mean_error_mm": statistics.mean(noise_means), "max_error_mm": max(noise_maxes),
              "median_of_max_error_mm": statistics.median(noise_maxes), "per_body_mean_mm": noise_means}
             if n_noise else None)

    refine_rows, cold_seconds = [], []
    if args.refine:
        fitter = OnlineFitter(pca, {args.garment: basis}, k=args.kmax, interpolation=Interpolation.PIECEWISE)
        a = None if args.no_anchor or support is None else anchors
        xs = fitter.fit(fitter.weights(held.vertices), anchors=a)[args.garment]
        bodies = [Body(vertices=held.vertices[i].double(), faces=held.faces.long()) for i in range(len(held))]
        sdfs = [BodySDF.cached(b.vertices, b.faces, SDFSettings(voxel_size=args.voxel)) for b in bodies]
        for i in tqdm(range(min(args.time_cold, len(held))), desc="cold drapes (timed)"):
            t = time.perf_counter()
            drape_on_body(mesh, held.vertices[i], held.faces, reference, dsettings, support=support)
            cold_seconds.append(time.perf_counter() - t)
        # the support's targets take their rotation from the garment placed for each body, as the cold drapes'
        placed = [place_for_body(mesh.x, reference, BodyFrame.of(held.vertices[i], held.faces))
                  for i in range(len(held))]
        for n in args.refine:
            means, maxes, secs, conv = [], [], [], 0
            for i in tqdm(range(len(held)), desc=f"refine {n}"):
                t = time.perf_counter()
                r = refine(mesh, xs[i], bodies[i], dsettings, iterations=n, sdf=sdfs[i], support=support,
                           support_reference=placed[i])
                secs.append(time.perf_counter() - t)
                d = torch.linalg.vector_norm(r.x.detach().double() - refs[i], dim=1)
                means.append(1e3 * float(d.mean()))
                maxes.append(1e3 * float(d.max()))
                conv += bool(r.metrics["converged"])
            med = statistics.median(secs)
            row = {"iterations": n, "mean_error_mm": statistics.mean(means), "max_error_mm": max(maxes)}
            row["median_of_max_error_mm"] = statistics.median(maxes)
            row.update(seconds_median=med, converged=conv,
                       time_ratio_to_cold=med / statistics.median(cold_seconds) if cold_seconds else None)
            refine_rows.append(row)
    result = {
        "train": args.train, "heldout": args.heldout, "garment": args.garment, "kmax": args.kmax, "c": args.c,
        "fit": args.fit,
        "edge_length": args.edge_length, "voxel": args.voxel, "garment_vertices": basis.num_vertices,
        "k_for_95": pca.k_for_variance(0.95), "k_for_99": pca.k_for_variance(0.99),
        "basis_drapes_ok": {n: mm.get("ok") for n, mm in basis.metrics.items()},
        "heldout_drapes_ok": sum(1 for mm in ref_metrics if mm["ok"]),
        "heldout_reference_inside_vertices_max": max(ref_inside),
        "seconds": {"dataset": t_data, "basis": t_basis,
                    "full_drape_median": statistics.median(drape_seconds)},
        "rows": rows,
        "basis_branch_deviation": branch,
        "refine": refine_rows,
        "reference_reproducibility": noise,
        "cold_drape_seconds_this_run": cold_seconds,
    }
    print(f"{args.garment}: {basis.num_vertices} vertices, {args.train} training / {args.heldout} held-out "
          f"bodies, k95={result['k_for_95']} k99={result['k_for_99']}, full drape median "
          f"{result['seconds']['full_drape_median']:.1f} s, {result['heldout_drapes_ok']}/{args.heldout} "
          "references ok")
    hdr = f"{'frame':>8} {'interp':>9} {'anchor':>6} {'k':>2} {'var%':>6} {'mean mm':>8} {'max mm':>8} " \
          f"{'med max':>8} {'inside':>7} {'in max':>6} {'push':>5} {'body mm':>8} {'fit ms':>7}"
    print(hdr)
    for r in rows:
        print(f"{r['frame']:>8} {r['interpolation']:>9} {'yes' if r['anchored'] else 'no':>6} {r['k']:>2} "
              f"{100 * r['explained_variance']:>6.2f} "
              f"{r['mean_error_mm']:>8.2f} {r['max_error_mm']:>8.2f} {r['median_of_max_error_mm']:>8.2f} "
              f"{r['inside_vertices_mean']:>7.1f} {r['inside_vertices_max']:>6d} "
              f"{r['inside_after_push_out_max']:>5d} {r['body_reconstruction_mean_mm']:>8.2f} "
              f"{r['fit_ms_per_body']:>7.3f}")
    if regression:
        print(f"clothing basis: least-squares linear model of {len(basis.metrics)} training drapes (cold)")
    else:
        kind = "continued from the mean drape" if settings.continuation else "cold"
        print(f"basis drapes ({kind}) against the mean drape carried onto their bodies, mean / hem mean mm: "
              + ", ".join(f"{n} {d['mean_mm']:.1f} / {d['hem_mean_mm']:.1f}" for n, d in branch.items()))
    if refine_rows:
        cold = statistics.median(cold_seconds) if cold_seconds else float("nan")
        kind = "" if args.no_anchor or support is None else " anchored"
        print(f"warm-started refine from k={args.kmax} piecewise{kind} (cold drape median {cold:.2f} s over "
              f"{len(cold_seconds)} bodies, this run, SDF prebuilt):")
        print(f"{'iters':>6} {'mean mm':>8} {'max mm':>8} {'med max':>8} {'s med':>7} {'/cold':>6} "
              f"{'conv':>5}")
        for r in refine_rows:
            ratio = r["time_ratio_to_cold"] if r["time_ratio_to_cold"] is not None else float("nan")
            print(f"{r['iterations']:>6} {r['mean_error_mm']:>8.2f} {r['max_error_mm']:>8.2f} "
                  f"{r['median_of_max_error_mm']:>8.2f} {r['seconds_median']:>7.2f} {ratio:>6.2f} "
                  f"{r['converged']:>3d}/{len(held)}")
    if noise is not None:
        print(f"the references' own reproducibility ({noise['bodies']} bodies moved by "
              f"{noise['shift_mm']:.1f} mm, draped cold again): mean {noise['mean_error_mm']:.2f} mm, max "
              f"{noise['max_error_mm']:.1f} mm, median of max {noise['median_of_max_error_mm']:.1f} mm")
    if args.json:
        with atomic_path(args.json) as tmp:
            Path(tmp).write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
