"""The ``torchgarment pca`` subcommands: build a data-driven garment model, fit it to a customer's body.

* ``torchgarment pca build --garment NAME|--pattern P --bodies N --out MODEL_DIR``: sample N anny adults
  (or read ``--dataset`` meshes), fit the PCA body model, drape the garment on the mean and the
  ``+-c sigma`` example bodies (Gillies et al. 2004) and write ``pca.pt``, ``basis.pt`` and ``model.json``.
* ``torchgarment pca fit --model MODEL_DIR --body B.obj --out DIR``: project the body (same topology as the
  model) to weights, evaluate the garment, optionally push it out of the body, and write ``garment.obj`` and
  ``metrics.json`` (seconds per step, weights, penetrations).

:func:`add_pca_parser` adds the ``pca`` subcommand to the ``torchgarment`` parser (:mod:`torchgarment.cli`)
with :func:`cmd_pca_build` and :func:`cmd_pca_fit` as the handlers of its two subcommands; :func:`load_model`
reads a model folder written by ``pca build``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import TYPE_CHECKING

from torchgarment.errors import InputError, TorchGarmentError
from torchgarment.io.jsonfile import write_json
from torchgarment.options import env_limit, resolve_device

if TYPE_CHECKING:
    from torchgarment.datadriven.basis import ClothingBasis
    from torchgarment.datadriven.dataset import BodyDataset
    from torchgarment.datadriven.pca import BodyPCA
    from torchgarment.pattern.spec import SewingPattern

MODEL_FORMAT = "torchgarment.pca_garment_model/1"


def add_pca_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``pca`` subcommand (with ``build`` and ``fit``) to ``subparsers``."""
    from torchgarment.datadriven.basis import BasisFit, Interpolation
    from torchgarment.datadriven.relative import BasisFrame
    from torchgarment.sim.drape import DrapeSettings

    d = DrapeSettings()
    p = subparsers.add_parser(
        "pca", help="data-driven garment fitting (Gillies et al. 2004): build a model, fit a body",
        description="PCA body model + parallel clothing basis draped offline; online fitting by a weighted "
                    "sum.")
    sub = p.add_subparsers(dest="pca_command", required=True)

    b = sub.add_parser(
        "build", help="sample bodies, fit the PCA body model and drape the clothing basis",
        description="Sample N anny adults (or read --dataset), fit the PCA body model, drape the garment on "
                    "the mean body and on mean +- c sigma_i along each kept component, and write pca.pt, "
                    "basis.pt and model.json into MODEL_DIR. Drapes are cached and resumable (--cache).")
    g = b.add_mutually_exclusive_group(required=True)
    g.add_argument("--garment", metavar="NAME",
                   help="a library garment, drafted for the mean body's measurements")
    g.add_argument("--pattern", metavar="P",
                   help="a pattern file (.json GarmentCode or .dxf), placed as in the file")
    src = b.add_mutually_exclusive_group(required=True)
    src.add_argument("--bodies", type=int, metavar="N", help="number of random anny adults to sample")
    src.add_argument("--dataset", metavar="PATH",
                     help="a saved body dataset (.pt) or a folder of meshes (OBJ/PLY) "
                                                       "of one topology")
    b.add_argument("--population", default="female",
                   help="anny adults to sample: female or male (default female)")
    b.add_argument("--seed", type=int, default=0, help="sampling seed (default 0)")
    b.add_argument("--k", type=int, default=None, help="components to drape (default: reach --variance)")
    b.add_argument("--variance", type=float, default=0.95,
                   help="variance target when --k is not given (default 0.95)")
    b.add_argument("--c", type=float, default=1.0,
                   help="example bodies at +-c standard deviations (default 1)")
    b.add_argument("--edge-length", type=float, default=d.edge_length, metavar="M",
                   help=f"garment triangle edge length in metres (default {d.edge_length})")
    b.add_argument("--voxel", type=float, default=d.voxel_size, metavar="M",
                   help=f"body SDF voxel size in metres (default {d.voxel_size})")
    b.add_argument("--cache", metavar="DIR", help="clothing-basis cache folder (default $TORCHGARMENT_CACHE/"
                                                  "clothing_basis)")
    b.add_argument("--out", required=True, metavar="MODEL_DIR", help="output model folder")
    b.add_argument("--no-progress", action="store_true", help="no progress bars on stderr")
    b.add_argument("--no-continuation", action="store_true",
                   help="drape every example body from the placed panels (Gillies et al.) instead of from "
                        "the mean body's drape carried onto it")
    b.add_argument("--fit", default=BasisFit.EXAMPLES.value, choices=[m.value for m in BasisFit],
                   help="examples (default, Gillies et al.: drapes of the mean and the +-c sigma example "
                        "bodies) or regression (cold drapes of every sampled body and a least-squares linear "
                        "model: the drapes' mean for a body's weights; one drape per body)")
    b.set_defaults(func=cmd_pca_build)

    f = sub.add_parser(
        "fit", help="fit a built model's garment to a body",
        description="Project a body (same topology as the model's bodies) to PCA weights, evaluate the "
                    "garment as mean + sum_i w_i G_i, optionally push vertices out of the body, and write "
                    "garment.obj and metrics.json (seconds per step, weights, penetrations).")
    f.add_argument("--model", required=True, metavar="MODEL_DIR", help="folder written by `pca build`")
    f.add_argument("--body", required=True, metavar="B",
                   help="body mesh file (OBJ, PLY, ...) of the model's topology")
    f.add_argument("--out", required=True, metavar="DIR", help="output folder")
    f.add_argument("--k", type=int, default=None, help="components to use (default: all of the basis)")
    f.add_argument("--interpolation", default=Interpolation.PIECEWISE.value,
                   choices=[m.value for m in Interpolation], help="basis interpolation (default piecewise)")
    f.add_argument("--frame", default=BasisFrame.BODY.value, choices=[m.value for m in BasisFrame],
                   help="blend the basis in body-relative coordinates (default body: the garment follows the "
                        "customer's surface) or in absolute positions (Gillies et al.)")
    f.add_argument("--no-anchor", action="store_true",
                   help="leave a garment with a support (a skirt's waistband) at its blended height instead "
                        "of hanging it from the body's measured waist plane, as a drape does (the default "
                        "measures that plane: about 0.25 s per body)")
    f.add_argument("--push-out", action="store_true",
                   help="move vertices inside the body (or closer than --margin) out to --margin from its "
                        "surface (exact distances at the garment's vertices)")
    f.add_argument("--margin", type=float, default=1e-3, metavar="M",
                   help="push-out clearance (default 0.001 m)")
    f.add_argument("--refine", type=int, default=None, metavar="N",
                   help="settle the prediction on the body with the simulator for at most N iterations (the "
                        "model's drape settings; builds the body's SDF), before any push-out")
    f.add_argument("--device", default="cpu", metavar="D",
                   help="compute device of the fit and the refine: cpu, cuda or cuda:N (default cpu; the "
                        "push-out's exact distances and the SDF build stay on the CPU)")
    f.set_defaults(func=cmd_pca_fit)
    return p


DEFAULT_MAX_BODIES = 20_000
"""Most bodies ``pca build --bodies`` samples by default (about 6 GiB of float64 vertices plus the PCA's
copies); the environment variable ``TORCHGARMENT_MAX_BODIES`` raises or lowers it."""
ANNY_BODY_BYTES = 13_348 * 3 * 8
"""Bytes of one sampled anny body's vertices (13,348 x 3 float64)."""


def _max_bodies() -> int:
    return int(env_limit("TORCHGARMENT_MAX_BODIES", DEFAULT_MAX_BODIES, 3))


def _dataset(args: argparse.Namespace) -> BodyDataset:
    from torchgarment.datadriven.dataset import BodyDataset

    if args.bodies is not None:
        if args.bodies < 3:
            raise InputError(f"--bodies must be at least 3, got {args.bodies}")
        limit = _max_bodies()
        if args.bodies > limit:
            gib = args.bodies * ANNY_BODY_BYTES / 2**30
            raise InputError(f"--bodies {args.bodies}: about {gib:.3g} GiB of bodies to sample and hold "
                             f"(limit {limit} bodies): sample fewer, or raise the limit with "
                             "TORCHGARMENT_MAX_BODIES")
        from torchgarment.body.anny_phenotype import PhenotypeRanges

        ranges = PhenotypeRanges.for_population(args.population)
        return BodyDataset.from_anny(args.bodies, seed=args.seed, ranges=ranges)
    path = Path(args.dataset)
    if path.is_dir():
        files = sorted(q for q in path.iterdir()
                       if q.suffix.lower() in (".obj", ".ply", ".stl", ".off", ".glb"))
        if len(files) < 3:
            raise InputError(f"--dataset {path}: needs at least 3 mesh files, found {len(files)}")
        return BodyDataset.from_meshes(files)
    return BodyDataset.load(path)


def _garment(args: argparse.Namespace, pca: BodyPCA) -> tuple[SewingPattern, str, dict]:
    """(pattern, garment name, provenance for model.json) of ``--garment`` or ``--pattern``."""
    if args.garment is not None:
        from torchgarment.body.measure import measure_body
        from torchgarment.pattern.library import draft, list_garments

        if args.garment not in list_garments():
            raise InputError(f"--garment {args.garment}: not a library garment "
                             f"({', '.join(list_garments())})")
        m = measure_body(pca.mean.detach().cpu().double(), pca.faces.cpu()).to_dict()
        request = {k: m[k] for k in ("height", "bust", "underbust", "waist", "hips")}
        return draft(args.garment, request), args.garment, {"drafted_for_mean_body": request}
    from torchgarment.pattern.files import load_pattern_file

    pattern = load_pattern_file(args.pattern)
    return pattern, pattern.name or Path(args.pattern).stem, {"pattern_file": str(args.pattern)}


def cmd_pca_build(args: argparse.Namespace) -> int:
    """Run ``torchgarment pca build``; returns the exit code."""
    from torchgarment.datadriven.basis import BasisFit, BasisSettings, build_basis
    from torchgarment.datadriven.pca import BodyPCA
    from torchgarment.io.staging import staged_output
    from torchgarment.sim.drape import DrapeSettings

    settings = BasisSettings(k=args.k, variance=args.variance, c=args.c,
                             drape=DrapeSettings(edge_length=args.edge_length, voxel_size=args.voxel),
                             continuation=not args.no_continuation, fit=args.fit)
    settings.validate()
    t0 = time.perf_counter()
    dataset = _dataset(args)
    t_data = time.perf_counter()
    pca = BodyPCA.fit(dataset)
    if args.k is not None and args.k > pca.num_components:
        raise InputError(f"--k {args.k}: the body model of {len(dataset)} bodies has only "
                         f"{pca.num_components} components")
    pattern, name, info = _garment(args, pca)
    t_pca = time.perf_counter()
    basis = build_basis(pca, pattern, settings, name=name, cache_dir=args.cache,
                        progress=not args.no_progress,
                        bodies=dataset.vertices if settings.fit is BasisFit.REGRESSION else None)
    t_basis = time.perf_counter()
    ratio = pca.explained_variance_ratio
    model = {
        "format": MODEL_FORMAT, "garment": name, **info, "bodies": len(dataset), "source": dataset.source,
        "topology": dataset.topology, "seed": args.seed if args.bodies is not None else None,
        "population": args.population if args.bodies is not None else None,
        "k": basis.k, "c": settings.c, "fit": settings.fit.value,
        "variance_target": settings.variance if args.k is None else None,
        "explained_variance": float(ratio[: basis.k].sum()) if basis.k else 0.0,
        "k_for_95": pca.k_for_variance(0.95), "k_for_99": pca.k_for_variance(0.99),
        "garment_vertices": basis.num_vertices, "basis_key": basis.key,
        "pca_fingerprint": basis.pca_fingerprint,
        "drapes": basis.metrics, "all_drapes_ok": all(m.get("ok", False) for m in basis.metrics.values()),
        "seconds": {"dataset": t_data - t0, "pca": t_pca - t_data, "basis": t_basis - t_pca,
                    "total": time.perf_counter() - t0},
        "edge_length": args.edge_length, "voxel_size": args.voxel,
    }
    with staged_output(args.out) as stage:
        pca.save(stage / "pca.pt")
        basis.save(stage / "basis.pt")
        write_json(stage / "model.json", model)
    bad = [n for n, m in basis.metrics.items() if not m.get("ok", False)]
    print(f"pca build {name}: {len(dataset)} bodies, k={basis.k} ({100 * model['explained_variance']:.1f} % "
          f"of the variance), {basis.num_vertices} garment vertices, {len(basis.metrics)} drapes"
          + (f" ({len(bad)} not ok: {', '.join(bad)})" if bad else " (all ok)")
          + f", {model['seconds']['total']:.1f} s -> {args.out}")
    return 0


def load_model(model_dir: str | Path) -> tuple[BodyPCA, ClothingBasis, dict]:
    """Read a folder written by ``pca build``: (PCA, basis, model.json contents).

    Raises:
        InputError: a missing folder or file, or a basis that does not belong to the PCA model.
    """
    from torchgarment.datadriven.basis import ClothingBasis
    from torchgarment.datadriven.pca import BodyPCA

    folder = Path(model_dir)
    if not folder.is_dir():
        raise InputError(f"--model {folder}: no such folder (write one with `torchgarment pca build`)")
    for n in ("pca.pt", "basis.pt", "model.json"):
        if not (folder / n).is_file():
            raise InputError(f"--model {folder}: missing {n} (not a `torchgarment pca build` folder)")
    try:
        info = json.loads((folder / "model.json").read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{folder / 'model.json'}: not valid JSON ({exc})") from None
    pca = BodyPCA.load(folder / "pca.pt")
    basis = ClothingBasis.load(folder / "basis.pt")
    if basis.pca_fingerprint != pca.fingerprint():
        raise InputError(f"--model {folder}: basis.pt was built for another body model than pca.pt")
    return pca, basis, info


def cmd_pca_fit(args: argparse.Namespace) -> int:
    """Run ``torchgarment pca fit``; returns the exit code."""
    (outcome,) = fit_bodies(args, [(args.body, args.out)])
    if isinstance(outcome, BaseException):
        raise outcome
    print(outcome)
    return 0


def fit_bodies(args: argparse.Namespace, jobs: list[tuple[str, str | Path]]) -> list[str | BaseException]:
    """``pca fit`` for many bodies on one model: the model is loaded once, the bodies' weights and garments
    are computed in one batched call (:meth:`OnlineFitter.weights`, :meth:`OnlineFitter.fit` on (B, V, 3)),
    then each body is refined and pushed out and its folder written as the single command writes it. The
    batch runner groups a catalogue's fits this way; ``pca fit`` is the case of one body.

    Args:
        args: the ``pca fit`` options (``model``, ``k``, ``interpolation``, ``frame``, ``push_out``,
            ``margin``, ``refine``; ``body`` and ``out`` are ignored).
        jobs: ``(body mesh file, output folder)`` per body.

    Returns:
        Per body, the command's summary line, or the exception that body failed with (a bad body fails alone;
        a bad model or option fails them all).
    """
    import torch

    from torchgarment.body.load import check_human_body, load_body
    from torchgarment.datadriven.online import OnlineFitter

    if not args.margin >= 0:
        raise InputError(f"--margin must be >= 0, got {args.margin}")
    if args.refine is not None and args.refine < 0:
        raise InputError(f"--refine must be >= 0 iterations, got {args.refine}")
    device = resolve_device(getattr(args, "device", "cpu"))
    t0 = time.perf_counter()
    outcomes: list[str | BaseException] = []
    bodies = []
    for body_path, _ in jobs:
        try:
            if not Path(body_path).is_file():
                raise InputError(f"--body {body_path}: no such file")
            body = load_body(body_path, device=device)
            check_human_body(body.vertices, body.faces, f"--body {body_path}")  # before the model: cheap
            bodies.append(body)
            outcomes.append("")
        except (TorchGarmentError, OSError) as exc:
            bodies.append(None)
            outcomes.append(exc)
    if all(b is None for b in bodies):
        return outcomes
    pca, basis, info = load_model(args.model)
    if device.type != "cpu":
        pca, basis = pca.to(device=device), basis.to(device=device)
    for n, (body, (body_path, _)) in enumerate(zip(bodies, jobs)):
        if body is not None and (body.num_vertices != pca.num_vertices
                                 or body.faces.shape != pca.faces.shape
                                 or not torch.equal(body.faces.long(), pca.faces.long())):
            outcomes[n] = InputError(
                f"--body {body_path}: {body.num_vertices} vertices / {body.faces.shape[0]} faces, but the "
                f"model's bodies have {pca.num_vertices} / {pca.faces.shape[0]} of topology "
                f"{pca.topology or '(unnamed)'}: the body must have the model's topology (same vertices and "
                "faces in the same order)")
            bodies[n] = None
    ok = [n for n, b in enumerate(bodies) if b is not None]
    if not ok:
        return outcomes
    name = basis.name or "garment"
    fitter = OnlineFitter(pca, {name: basis}, k=args.k, interpolation=args.interpolation, frame=args.frame)
    stack = torch.stack([bodies[n].vertices for n in ok])
    t_load = time.perf_counter()
    w = fitter.weights(stack)
    t_w = time.perf_counter()
    if args.no_anchor and basis.needs_anchor:
        raise InputError(f"--no-anchor: the model's basis ({args.model}) is a regression relative to the "
                         "waist plane, which needs the anchor")
    anchors = None if args.no_anchor or not fitter.anchored_garments else fitter.anchors(stack)
    t_a = time.perf_counter()
    x = fitter.fit(w, bodies=stack, anchors=anchors)[name]
    t_fit = time.perf_counter()
    share = 1.0 / len(ok)  # the shared steps' time (model and bodies read, batched weights and fit), per body
    seconds = {"load": (t_load - t0) * share, "weights": (t_w - t_load) * share,
               "anchor": (t_a - t_w) * share, "fit": (t_fit - t_a) * share}
    mean_frame = None
    if args.refine is not None:  # the refines' support reference: the mean-body drape placed for each body
        from torchgarment.datadriven.basis import BodyFrame

        mean_frame = BodyFrame.of(pca.mean.cpu(), pca.faces.cpu())
    for row, n in enumerate(ok):
        try:
            outcomes[n] = _finish_fit(args, jobs[n], bodies[n], pca, basis, info, fitter, w[row], x[row],
                                      dict(seconds), len(ok), mean_frame)
        except (TorchGarmentError, OSError) as exc:  # one body's failure (e.g. its refine) leaves the others
            outcomes[n] = exc
    return outcomes


def _finish_fit(args: argparse.Namespace, job: tuple[str, str | Path], body: object, pca: BodyPCA,
                basis: ClothingBasis, info: dict, fitter: object, w: object, x: object, seconds: dict,
                batch: int, mean_frame: object | None) -> str:
    """Refine, push out, measure and write one body's fit; returns the command's summary line.
    ``mean_frame``: the PCA mean body's :class:`~torchgarment.datadriven.basis.BodyFrame` (needed with
    ``--refine``)."""
    t0 = time.perf_counter()
    from torchgarment.datadriven.online import push_out
    from torchgarment.io.mesh import save_obj
    from torchgarment.io.staging import staged_output

    body_path, out = job
    name = basis.name or "garment"
    refined = None
    if args.refine is not None:
        from torchgarment.datadriven.online import refine
        from torchgarment.sdf import BodySDF, SDFSettings
        from torchgarment.sim.drape import DrapeSettings

        if not all(isinstance(info.get(k), (int, float)) for k in ("edge_length", "voxel_size")):
            raise InputError(f"--model {args.model}: model.json has no edge_length / voxel_size to refine "
                             "with")
        dset = DrapeSettings(edge_length=float(info["edge_length"]), voxel_size=float(info["voxel_size"]))
        t = time.perf_counter()
        sdf = BodySDF.cached(body.vertices, body.faces, SDFSettings(voxel_size=dset.voxel_size))
        seconds["refine_sdf"] = time.perf_counter() - t
        # the support's targets take their rotation about the body from the mean-body drape placed for this
        # body (as a cold drape's from its placed panels), not from the prediction
        from torchgarment.datadriven.basis import BodyFrame, place_for_body

        placed = place_for_body(basis.garment.x.detach().cpu(), mean_frame,
                                BodyFrame.of(body.vertices.cpu(), body.faces.cpu()))
        r = refine(basis.garment, x, body, dset, iterations=args.refine, sdf=sdf, support=basis.support,
                   support_reference=placed)
        x = r.x.detach().to(x)
        seconds["refine"] = r.metrics["seconds"]
        refined = {"iterations": r.metrics["iterations"], "converged": r.metrics["converged"],
                   "residual_n": r.metrics["residual"], "weight_n": r.metrics["weight_n"]}
    # exact signed distances at the garment's vertices (a zero-pass push-out only measures)
    res = push_out(x, body.vertices, body.faces, margin=args.margin, iterations=4 if args.push_out else 0)
    pen = {"inside_vertices": res.inside_before, "min_distance_mm": None}
    if args.push_out:
        x = res.x
        seconds["push_out"] = res.seconds
        pen.update(pushed_vertices=res.moved, inside_after_push_out=res.inside_after,
                   min_distance_after_push_out_mm=1e3 * res.min_phi)
    else:
        seconds["distances"] = res.seconds
        pen["min_distance_mm"] = 1e3 * res.min_phi
    seconds["total"] = (seconds["load"] + seconds["weights"] + seconds["anchor"] + seconds["fit"]
                        + time.perf_counter() - t0)
    res_rec = pca.reconstruction_error(body.vertices, fitter.k)
    metrics = {"model": str(args.model), "body": str(body_path), "garment": name, "k": fitter.k,
               "interpolation": fitter.interpolation.value, "frame": fitter.frame.value,
               "anchored": bool(name in fitter.anchored_garments and not args.no_anchor), "seconds": seconds,
               "bodies_in_call": batch,
               "weights": [float(v) for v in w],
               "weights_in_sigmas": [float(v) for v in w / pca.sigmas[: fitter.k]],
               "penetrations": pen, "refine": refined, "garment_vertices": int(x.shape[0]),
               "body_reconstruction_error_mm": {"mean": 1e3 * float(res_rec["mean"][0]),
                                                "max": 1e3 * float(res_rec["max"][0])}}
    with staged_output(out) as stage:
        welded, _ = basis.garment.with_positions(x.detach()).welded()
        save_obj(stage / "garment.obj", welded.x, welded.faces)
        write_json(stage / "metrics.json", metrics)
    return (f"pca fit {name}: k={fitter.k}, weights {seconds['weights'] * 1e3:.2f} ms, "
            f"fit {seconds['fit'] * 1e3:.2f} ms, {pen['inside_vertices']} vertices inside the body"
            + (f" ({pen['inside_after_push_out']} after push-out)" if args.push_out else "") + f" -> {out}")
