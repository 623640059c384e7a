"""Intersection-free garment retargeting end to end (Huang et al. 2025, section 3).

``retarget(problem)``: Step 1 shrinks the target avatar onto the source skeleton
(:func:`~torchgarment.retarget.shrink.shrink_avatar`); Step 2 inflates it back (``t`` from 0 to 1 under an
augmented Lagrangian) while projected Newton moves the garment, minimising
``L_AL + w_surf L_surf + w_pos L_pos + L_contact + w_curve L_curve + w_attach L_attach`` (the last holds a
garment's separate pieces, a pocket or a collar, where they lie on the cloth under them); as soon as
continuous collision detection says the move from the current ``t`` to ``t = 1`` (garment fixed) is
intersection-free, ``t`` snaps to 1; Step 3 fits the garment to the fixed avatar with ``w_fit L_fit`` in
place of ``L_AL``. Step 3's contact uses the input avatar mesh: Step 1's subdivision only splits triangles
into fans that tile them (at ``t = 1`` the same surface), and its T-junction vertices and slivers would add
pairs (on a GarmentCode body, 35,915 vertices and 62,432 faces instead of 23,752 and 47,500).

The optimisation runs in a canonical frame: the work frame scaled by ``1.7 / problem.length_scale`` (a model
of human size in metres), so that the paper's constants (dhat = 2 mm, the fit length, the step caps) are
stated once and scale with the model (dhat = 2e-3 * length_scale / 1.7 in the work frame).

Guarantee: every accepted step is capped by a conservative collision-free step size and the snap by CCD, so
the output never intersects; it is checked at the end with ``ipctk.has_intersections`` (garment + avatar and
garment alone) and the minimum distance, reported in :attr:`RetargetResult.metrics`, and a failure raises
:class:`RetargetError` instead of returning an intersecting garment.

Multi-layer: :func:`layer_problem` adds a retargeted garment to the avatar of a new problem (it then counts
as part of the avatar) and :func:`retarget_layers` dresses several garments from the inside out.
"""

from __future__ import annotations

import math
import time
from contextlib import closing
from dataclasses import asdict, dataclass, field
from enum import Enum
from pathlib import Path

import ipctk
import numpy as np
import torch

from torchgarment.errors import InputError, TorchGarmentError
from torchgarment.linalg import SparseBackend
from torchgarment.logging import RunLogger
from torchgarment.options import OptionEnum
from torchgarment.retarget.inputs import REFERENCE_HEIGHT, RetargetProblem, source_gaps
from torchgarment.retarget.objectives import (
    Attachment,
    Contact,
    CurveShape,
    Fit,
    Positional,
    SurfaceShape,
    boundary_loops,
    loop_winds_around_a_bone,
    usable_bones,
    vertex_areas,
)
from torchgarment.retarget.solver import (
    InflationPenalty,
    NewtonSettings,
    initial_stiffness,
    projected_newton,
    retarget_model,
    term_values,
)
from torchgarment.sim.contact import BroadPhase, MovingObstacleContact, StepBound, ipc_threads


class RetargetError(TorchGarmentError):
    """Retargeting could not produce a guaranteed intersection-free garment (e.g. inflation never
    finished)."""


class FitTarget(OptionEnum):
    """The gap Step 3's fit term pulls each fit vertex to (:class:`~.objectives.Fit`).

    SOURCE_GAP: the vertex's own distance to the source avatar, at least dhat: the garment keeps the
        tightness it had on the source (loose parts stay loose; a layer keeps its height above the cloth
        under it). Needs a source avatar.
    SURFACE: dhat everywhere (the paper's D^2, moved just outside the barrier): the fit region is pulled onto
        the avatar, and layers onto each other.
    AUTO: SOURCE_GAP when the problem has a source avatar, else SURFACE (``metrics["fit_target"]`` says
        which ran).
    """

    AUTO = "auto"
    SOURCE_GAP = "source-gap"
    SURFACE = "surface"

    @classmethod
    def aliases(cls) -> dict[str, str]:  # noqa: D102
        return {"source_gap": "source-gap", "gap": "source-gap", "dhat": "surface"}

    def for_problem(self, problem: RetargetProblem) -> FitTarget:
        """The target that runs on ``problem`` (AUTO resolved).

        Raises:
            InputError: SOURCE_GAP on a problem without a source avatar.
        """
        has_source = problem.source_avatar_vertices is not None and problem.source_avatar_faces is not None
        if self is FitTarget.AUTO:
            return FitTarget.SOURCE_GAP if has_source else FitTarget.SURFACE
        if self is FitTarget.SOURCE_GAP and not has_source:
            raise InputError("fit_target 'source-gap' needs the source avatar (--source-avatar); "
                             "use 'surface' without one")
        return self


@dataclass
class RetargetSettings:
    """Settings of :func:`retarget`. Lengths are at human scale (metres for a 1.7 m model) and scale with it.

    Attributes:
        w_fit: fit weight (tightness, paper Fig. 8); 0 skips Step 3's fit term (Step 3 still relaxes).
        w_pos: positional weight (paper: 10). w_surf: surface-shape weight. w_curve: curve-shape weight.
        w_attach: weight of the garment's separate pieces keeping their place on the pieces under them
            (:class:`~torchgarment.retarget.objectives.Attachment`: a patch pocket, a collar); as high as the
            positional term's, since both hold what the shape terms cannot see. The positional term then
            leaves the attached pieces' rims that do not wind around a bone (a pocket's) to it. 0 lets such
            pieces slide (the objective before this term).
        attach_distance: a separate piece's vertex within this distance of a larger piece is attached to it
            (layers lie a few millimetres apart).
        dhat: barrier activation distance (paper: 2 mm).
        fit_length: length ``ell`` that normalises the fit term (one ``ell`` of gap costs like a unit
            distortion of the same area).
        fit_target: the gap the fit pulls each fit vertex to (:class:`FitTarget`): by default its gap on the
            source avatar when the problem has one, else dhat.
        sdf_voxel: voxel size of the target avatar SDF used by the fit term.
        step_bound: collision-free step method (:class:`~torchgarment.sim.contact.StepBound`).
        max_displacement: largest vertex displacement (garment or avatar) of one Newton step.
        inflation_rounds: augmented-Lagrangian outer rounds of Step 2 at most.
        inflation_iterations: Newton iterations per outer round.
        fit_iterations: Newton iterations of Step 3 at most.
        rtol: Step 3 stops when |g| <= rtol * |g_0|.
        energy_tol: ... or when its energy fell by less than this fraction over the last 3 iterations. Where
            the garment slides slowly these two rules stop short of convergence: on the messy bench the
            T-shirt on a GarmentCode body stopped within 1.3 mm of the shape 120 iterations reach, the
            trousers and the T-shirt on the creatures 7-23 mm (mean) and 34-117 mm (largest) from it (README,
            "Retargeting").
        snap_min_distance: the snap CCD keeps every pair at least this far apart (fraction of dhat).
        al_lambda: initial augmented-Lagrangian stiffness per unit garment area.
        check_shrink: check that the shrunk avatar does not touch the garment (Step 1).
        curves_from_boundaries: preserve the garment boundary loops' curvature and torsion.
        broad_phase: ipctk broad phase (:class:`~torchgarment.sim.contact.BroadPhase` or an ipctk class
            name) of the garment's own pairs and the intersection checks; the garment-avatar pairs come from
            BVHs over the avatar queried by the garment
            (:class:`~torchgarment.sim.obstacle_pairs.GarmentObstaclePairs`).
        stiffness_scale: IPC's adaptive barrier stiffness (ipctk.initial_barrier_stiffness) gets the mean
            garment vertex area times this as its "average mass": the lower bound of kappa grows with it.
            The energies here are areas (m^2, dimensionless densities), so kappa ~ area / dhat^2 balances
            them; 100 keeps pairs well apart (about 0.1 dhat at least under the fit's pull).
        cull_radius: when given, the contact's collision mesh keeps the avatar faces within this distance of
            the garment (exact: re-culled after half of it of motion, see :class:`~torchgarment.sim.contact.
            MovingObstacleContact`); None (default) keeps the whole avatar. Culling paid off when ipctk's
            broad phase traversed the avatar's own overlaps; the garment-avatar BVH queries never do, and
            re-culling then costs more than it saves (``README.md``, retargeting).
        threads: torch's intra-op threads, ipctk's threads and the BLAS libraries' threads during the run (all
            restored afterwards; :func:`~torchgarment.sim.contact.ipc_threads`); None keeps the current
            numbers. The per-element work is many small tensor ops, for which one thread is fastest
            (measured: 2 threads were 2-3x slower on a loaded 2-core machine). With one ipctk thread a run is
            reproducible bit for bit; ipctk's parallel queries (2 threads) made two runs of the same pair
            differ by 0.4 mm, and a hard pair (a layered T-shirt on the 10 m creature) pass in one run and
            fail in the next two.
        sparse_backend: the sparse direct solver of the Newton systems (SPD: projected Hessians plus the
            barrier's PSD blocks). ``"auto"`` (default): CHOLMOD when ``cvxopt`` is installed (``pip install
            -e ".[cholmod]"``), else SuperLU (:meth:`~torchgarment.linalg.SparseBackend.fastest_spd`; the
            settings then hold the resolved backend, and results record it). Measured on the messy bench
            (2026-12-02): mean 18.7 s with CHOLMOD against 25.6 s with SuperLU, the same 0 intersections.
            ``"superlu"``, ``"cholmod"``, ``"pardiso"`` or ``"cholespy"`` choose one.
    """

    w_fit: float = 2.0
    w_pos: float = 10.0
    w_surf: float = 1.0
    w_curve: float = 1.0
    w_attach: float = 10.0
    attach_distance: float = 0.01
    dhat: float = 2e-3
    fit_length: float = 0.01
    fit_target: FitTarget | str = FitTarget.AUTO
    sdf_voxel: float = 0.008
    step_bound: StepBound | str = StepBound.ADDITIVE
    max_displacement: float = 0.03
    inflation_rounds: int = 40
    inflation_iterations: int = 8
    fit_iterations: int = 60
    rtol: float = 1e-3
    energy_tol: float = 2e-3
    snap_min_distance: float = 0.05
    al_lambda: float = 10.0
    check_shrink: bool = True
    curves_from_boundaries: bool = True
    broad_phase: BroadPhase | str = BroadPhase.LBVH
    stiffness_scale: float = 100.0
    cull_radius: float | None = None
    threads: int | None = 1
    sparse_backend: SparseBackend | str = "auto"

    def __post_init__(self) -> None:
        self.step_bound = StepBound.resolve(self.step_bound)
        if isinstance(self.sparse_backend, str) and self.sparse_backend.lower() == "auto":
            self.sparse_backend = SparseBackend.fastest_spd()
        self.sparse_backend = SparseBackend.resolve(self.sparse_backend)
        self.broad_phase = BroadPhase.resolve(self.broad_phase)
        self.fit_target = FitTarget.resolve(self.fit_target)
        for name in ("w_fit", "w_pos", "w_surf", "w_curve", "w_attach"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"RetargetSettings.{name} must be a non-negative number, got {v}")
        if self.cull_radius is not None and not self.cull_radius >= 4 * self.dhat:
            raise InputError(
                f"RetargetSettings.cull_radius must be None or >= 4 dhat, got {self.cull_radius}"
            )
        for name in ("dhat", "fit_length", "sdf_voxel", "max_displacement", "al_lambda", "stiffness_scale",
                     "attach_distance"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"RetargetSettings.{name} must be positive, got {v}")
        if not 0 < self.snap_min_distance < 1:
            raise InputError(
                f"RetargetSettings.snap_min_distance must be in (0, 1), got {self.snap_min_distance}"
            )
        for name in ("inflation_rounds", "inflation_iterations", "fit_iterations"):
            if int(getattr(self, name)) < 0:
                raise InputError(f"RetargetSettings.{name} must be >= 0")
        if not (
            math.isfinite(self.rtol)
            and self.rtol >= 0
            and math.isfinite(self.energy_tol)
            and self.energy_tol >= 0
        ):
            raise InputError("RetargetSettings.rtol and energy_tol must be non-negative numbers")
        if self.threads is not None and int(self.threads) < 1:
            raise InputError(f"RetargetSettings.threads must be >= 1 or None, got {self.threads}")


@dataclass
class RetargetResult:
    """Outcome of :func:`retarget`.

    Attributes:
        garment_vertices: (N, 3) retargeted garment in the TARGET avatar's frame.
        garment_faces: (F, 3) long (the problem's welded garment).
        work_vertices: (N, 3) the garment in the work frame.
        distortion: (F,) per-triangle L_surf distortion (mean unweighted pair value, dimensionless).
        steps: per-step stats (name, newton iterations, seconds, final t, grad norm, reason; the fit's
            ``final_motion_mm``, the largest vertex motion of its last 3 steps at human scale).
        history: per-iteration stats of both steps.
        metrics: summary (see :func:`retarget`).
    """

    garment_vertices: torch.Tensor
    garment_faces: torch.Tensor
    work_vertices: torch.Tensor
    distortion: torch.Tensor
    steps: list[dict] = field(default_factory=list)
    history: list[dict] = field(default_factory=list)
    metrics: dict = field(default_factory=dict)


class _Progress:
    """The retargeting's per-iteration log: history records, TensorBoard scalars and the progress bar."""

    def __init__(self, log_dir: str | Path | None, progress: bool) -> None:
        self.logger = RunLogger(log_dir, progress, "retarget")
        self.step = 0
        self.history: list[dict] = []

    def __call__(self, stage: str, stats: dict) -> None:
        self.step += 1
        self.history.append({"stage": stage, **stats})
        self.logger.scalars(
            {
                k: v
                for k, v in stats.items()
                if isinstance(v, (int, float)) and math.isfinite(v) and k != "iteration"
            },
            self.step,
            prefix=f"{stage}/",
        )
        self.logger.advance(
            {"stage": stage, "t": f"{stats.get('t', 1.0):.3f}", "g": f"{stats.get('grad_norm', 0):.2e}"}
        )

    def close(self) -> None:
        self.logger.close()


def _min_distance(contact: MovingObstacleContact, x: torch.Tensor, t: float, start: float) -> float:
    """Minimum garment-self / garment-avatar distance, searching radii start, 4 start, ... (+inf if none)."""
    r = start
    for _ in range(6):
        d = contact.min_distance(x, t, r)
        if math.isfinite(d):
            return d
        r *= 4.0
    return math.inf


def check_result(
    x: torch.Tensor,
    faces: torch.Tensor,
    avatar_vertices: torch.Tensor,
    avatar_faces: torch.Tensor,
    search: float,
) -> dict:
    """Intersection checks of a garment on an avatar (any consistent length unit).

    Returns:
        dict with ``intersects_avatar`` (garment+avatar mesh, avatar-avatar pairs ignored),
        ``intersects_self`` (garment alone), ``intersections`` (the number of those two checks that fail,
        0 when intersection-free) and ``min_distance`` (garment-self / garment-avatar, searched from
        ``search`` outwards).
    """
    c = MovingObstacleContact(x, faces, avatar_vertices, avatar_faces, None, search)
    inter_av = c.has_intersections(x, 1.0)
    gf = faces.cpu().numpy().astype(np.int32)
    xn = np.asfortranarray(x.detach().to("cpu", torch.float64).numpy())
    gm = ipctk.CollisionMesh(xn, ipctk.edges(gf), gf)
    inter_self = bool(ipctk.has_intersections(gm, xn, ipctk.LBVH()))
    dmin = _min_distance(c, x, 1.0, search)
    return {
        "intersects_avatar": bool(inter_av),
        "intersects_self": inter_self,
        "intersections": int(inter_av) + int(inter_self),
        "min_distance": dmin,
    }


def retarget(
    problem: RetargetProblem,
    settings: RetargetSettings | None = None,
    *,
    progress: bool = True,
    log_dir: str | Path | None = None,
) -> RetargetResult:
    """Retarget ``problem.garment`` onto ``problem``'s target avatar without intersections.

    Args:
        problem: a :class:`~torchgarment.retarget.inputs.RetargetProblem` (work frame).
        settings: :class:`RetargetSettings` (defaults: the paper's weights, w_fit = 2).
        progress: show a tqdm bar on stderr.
        log_dir: write TensorBoard scalars (each term, t, step size, min distance, ...) there.

    Returns:
        :class:`RetargetResult`; ``metrics`` holds seconds (per step and total), newton_iterations, grad_norm,
        t_snap, min_distance_mm (at human scale), intersections (0), intersects_avatar / intersects_self,
        distortion_mean / distortion_max, fit_target (the :class:`FitTarget` that ran), fit_gap_mm (the fit
        vertices' median gap to the avatar, median target gap and median miss |gap - target|, in mm at human
        scale; None without a fit term), attached_vertices and attach_miss_mm (the separate pieces' vertices
        held by :class:`~torchgarment.retarget.objectives.Attachment`, and the median and max distance from
        their places on the cloth under them, mm at human scale; None when the garment is one piece), terms
        (each term's final unweighted value), weights, stiffness, vertex / face counts.

    Raises:
        InputError: from Step 1 (the shrunk avatar touches the garment), malformed settings, or
            ``fit_target="source-gap"`` without a source avatar.
        RetargetError: the inflation did not reach t = 1, or the final check found an intersection.
    """
    from torchgarment.retarget.shrink import shrink_avatar
    from torchgarment.sdf.build import SDFSettings
    from torchgarment.sdf.grid import BodySDF

    s = settings or RetargetSettings()
    fit_target = FitTarget.resolve(s.fit_target).for_problem(problem)
    t_start = time.perf_counter()
    dt, dev = problem.garment_vertices.dtype, problem.garment_vertices.device
    if problem.length_scale <= 0 or not math.isfinite(problem.length_scale):
        raise InputError(f"problem.length_scale must be positive, got {problem.length_scale}")
    k = REFERENCE_HEIGHT / problem.length_scale  # work -> canonical scale
    faces = problem.garment_faces.to(dev).long()
    x_src = problem.garment_vertices * k
    log = _Progress(log_dir, progress)
    steps: list[dict] = []
    with ipc_threads(None if s.threads is None else int(s.threads), whole_process=True), closing(log):
        # ---------------------------------------------------------------- Step 1
        t0 = time.perf_counter()
        shrunk = shrink_avatar(problem, check=s.check_shrink)
        full = shrunk.vertices_full.to(dt) * k
        shr = shrunk.vertices_shrunk.to(dt) * k
        steps.append(
            {
                "step": "shrink",
                "seconds": time.perf_counter() - t0,
                "avatar_vertices": int(full.shape[0]),
                "subdivision_iterations": int(shrunk.iterations),
            }
        )

        # ---------------------------------------------------------------- objectives
        js = problem.source_skeleton.joints.to(dt) * k
        jt = problem.target_skeleton.joints.to(dt) * k
        bones = problem.source_skeleton.bones.to(dev).long()
        loops = boundary_loops(faces.cpu().numpy())
        curves = ([torch.as_tensor(c) for c in loops] if s.curves_from_boundaries else []) + [
            c.cpu() for c in problem.curves]
        surf = SurfaceShape(x_src, faces, weight=s.w_surf)
        # a separate piece lying on a larger one (a pocket, a collar) is held there by L_attach. The
        # positional term is the paper's for cuffs and hems: it stays on the rims that wind around a bone (a
        # waistband's), not on those that lie beside one (a pocket's), which it crumpled (README,
        # "Retargeting")
        attach = Attachment(x_src, faces, s.attach_distance, s.fit_length, weight=s.w_attach)
        held = torch.zeros(x_src.shape[0], dtype=torch.bool, device=dev)
        if s.w_attach > 0:
            held[attach.vertices] = True
        rim = [torch.as_tensor(lp, device=dev) for lp in loops]
        if bool(held.any()):
            long = bones[usable_bones(js, jt, bones)]
            rim = [lp for lp in rim
                   if not bool(held[lp].all()) or loop_winds_around_a_bone(x_src[lp], js, long)]
        rim_v = torch.unique(torch.cat(rim)) if rim else torch.zeros(0, dtype=torch.long, device=dev)
        pos = Positional(x_src, faces, js, jt, bones, vertices=rim_v, weight=s.w_pos)
        curve = CurveShape(x_src, curves, weight=s.w_curve)
        shape = [surf, pos, curve] + ([attach] if bool(held.any()) else [])
        area = float(vertex_areas(x_src, faces).sum())
        mean_area = area / x_src.shape[0]
        weights = {
            "surf": s.w_surf,
            "pos": s.w_pos,
            "curve": s.w_curve,
            "attach": s.w_attach,
            "contact": 1.0,
            "al": 1.0,
            "fit": s.w_fit,
        }

        # ---------------------------------------------------------------- Step 2: inflation
        t0 = time.perf_counter()
        contact = Contact(
            x_src,
            faces,
            full,
            shrunk.faces,
            shr,
            s.dhat,
            broad_phase=s.broad_phase,
            cull_radius=s.cull_radius,
        )
        snap_contact = Contact(x_src, faces, full, shrunk.faces, shr, s.dhat, broad_phase=s.broad_phase)
        al = InflationPenalty(s.al_lambda * area)
        obj = retarget_model(shape + [contact, al], x_src)
        x = x_src.clone()
        t = 0.0
        initial_stiffness(obj, x, t, mean_area * s.stiffness_scale)
        ns = NewtonSettings(
            max_iterations=s.inflation_iterations,
            max_displacement=s.max_displacement,
            step_bound=s.step_bound,
            rtol=0.0,
            sparse_backend=s.sparse_backend,
        )
        iters2, snapped, bound_s, rounds = 0, False, 0.0, 0
        snap_min = s.snap_min_distance * s.dhat
        for rounds in range(1, s.inflation_rounds + 1):
            t_prev = t
            r = projected_newton(obj, x, t, free_t=True, settings=ns, callback=lambda st: log("inflate", st))
            x, t = r.x, r.t
            iters2 += r.iterations
            bound_s += r.step_bound_seconds
            if t >= 1.0 or snap_contact.ipc.is_step_free(x, t, 1.0, snap_min):
                snapped = True
                break
            al.update(t)
            if t - t_prev < 0.05:
                al.lambda1 *= 2.0
        if not snapped:
            raise RetargetError(
                f"the avatar inflation stopped at t = {t:.3f} after {rounds} rounds "
                f"({iters2} Newton iterations); raise inflation_rounds"
            )
        t_snap = t
        steps.append(
            {
                "step": "inflate",
                "seconds": time.perf_counter() - t0,
                "newton_iterations": iters2,
                "rounds": rounds,
                "t_snap": t_snap,
                "step_bound_seconds": bound_s,
                "culls": contact.ipc.num_culls,
                # the closest garment-avatar / garment-self pair met (human scale): far below dhat where the
                # inflation squeezes the garment (e.g. between overlapping parts of the avatar)
                "min_distance_mm": 1000.0 * min((h["min_distance"] for h in log.history
                                                 if h["stage"] == "inflate"), default=math.inf),
            }
        )

        # ---------------------------------------------------------------- Step 3: fit
        t0 = time.perf_counter()
        # the input avatar: at t = 1 the subdivided one is the same surface, with more pairs
        avatar = problem.avatar_vertices.to(dt) * k
        contact3 = Contact(
            x_src,
            faces,
            avatar,
            problem.avatar_faces,
            None,
            s.dhat,
            broad_phase=s.broad_phase,
            cull_radius=s.cull_radius,
        )
        if contact3.ipc.has_intersections(x, 1.0):  # cannot happen after a CCD-checked snap; never hide it
            raise RetargetError(
                f"the garment intersects the avatar after snapping t = {t_snap} to 1 (unculled: "
                f"{snap_contact.ipc.has_intersections(x, t_snap)} at t_snap, "
                f"{snap_contact.ipc.has_intersections(x, 1.0)} at 1)"
            )
        terms3 = shape + [contact3]
        sdf_s = 0.0
        fit: Fit | None = None
        # an attached layer's gap is its offset from the cloth under it (L_attach), not a gap to the avatar:
        # fitting both to the avatar squeezes the layer onto the cloth wherever the cloth cannot reach its own
        fit_mask = problem.fit_mask.to(dev).clone()
        fit_mask[held] = False
        if s.w_fit > 0 and bool(fit_mask.any()):
            ts = time.perf_counter()
            sdf = BodySDF.cached(
                avatar,
                problem.avatar_faces,
                SDFSettings(voxel_size=s.sdf_voxel),
                dtype=dt,
                device=dev,
            )
            sdf_s = time.perf_counter() - ts
            gap = None
            sav, saf = problem.source_avatar_vertices, problem.source_avatar_faces
            if fit_target is FitTarget.SOURCE_GAP and sav is not None and saf is not None:
                gap = source_gaps(x_src, sav.to(dt) * k, saf)
            fit = Fit(sdf, x_src, faces, fit_mask, s.fit_length, s.dhat, weight=s.w_fit, source_gap=gap)
            terms3.append(fit)
        obj3 = retarget_model(terms3, x)
        initial_stiffness(obj3, x, 1.0, mean_area * s.stiffness_scale)
        contact3.ipc.stiffness = max(contact3.stiffness, contact.stiffness)
        r3 = projected_newton(
            obj3,
            x,
            1.0,
            free_t=False,
            settings=NewtonSettings(
                max_iterations=s.fit_iterations,
                max_displacement=s.max_displacement,
                step_bound=s.step_bound,
                rtol=s.rtol,
                energy_tol=s.energy_tol,
                sparse_backend=s.sparse_backend,
            ),
            callback=lambda st: log("fit", st),
        )
        x = r3.x
        steps.append(
            {
                "step": "fit",
                "seconds": time.perf_counter() - t0,
                "newton_iterations": r3.iterations,
                "grad_norm": r3.grad_norm,
                "converged": r3.converged,
                "reason": r3.reason,
                "sdf_seconds": sdf_s,
                "step_bound_seconds": r3.step_bound_seconds,
                "culls": contact3.ipc.num_culls,
                # the largest vertex motion of the last 3 steps (human scale): a fit stopped while its garment
                # still slides moves millimetres a step (README, "On the creatures the fit stops short")
                "final_motion_mm": 1000.0 * max((h["max_displacement"] for h in r3.history[-3:]),
                                                default=0.0),
            }
        )

        # ---------------------------------------------------------------- checks and metrics
        chk = check_result(x, faces, full, shrunk.faces, s.dhat)
        if chk["intersections"]:
            raise RetargetError(
                f"final check failed: garment-avatar intersection {chk['intersects_avatar']}, "
                f"self-intersection {chk['intersects_self']}"
            )
        if not chk["min_distance"] > 0:
            raise RetargetError("final check failed: the garment touches the avatar or itself (distance 0)")
        vals = term_values(terms3, x, 1.0)
        distortion = surf.triangle_distortion(x)
        fit_gaps = None
        if fit is not None and fit.vertices.numel():
            with torch.no_grad():  # human-scale mm: the fit vertices' gaps, their targets, the misses
                gap_now = fit.sdf(x[fit.vertices].to(fit.sdf.dtype)).to(dt)
            fit_gaps = {
                "median": 1000.0 * float(gap_now.median()),
                "target_median": 1000.0 * float(fit.targets.median()),
                "miss_median": 1000.0 * float((gap_now - fit.targets).abs().median()),
            }
        attach_miss = None
        if bool(held.any()):  # human-scale mm: how far the attached vertices left their place
            with torch.no_grad():
                miss = 1000.0 * attach.residuals(x).norm(dim=-1)
            attach_miss = {"median": float(miss.median()), "max": float(miss.max())}
        metrics = {
            "seconds": time.perf_counter() - t_start,
            "newton_iterations": iters2 + r3.iterations,
            "grad_norm": r3.grad_norm,
            "converged": r3.converged,
            "t_snap": t_snap,
            "min_distance_mm": chk["min_distance"] * 1000.0,
            "min_distance": chk["min_distance"] / k,
            "intersections": chk["intersections"],
            "intersects_avatar": chk["intersects_avatar"],
            "intersects_self": chk["intersects_self"],
            "distortion_mean": float(distortion.mean()),
            "distortion_max": float(distortion.max()),
            "fit_target": fit_target.value,
            "fit_gap_mm": fit_gaps,
            "attached_vertices": int(held.sum()),
            "attach_miss_mm": attach_miss,
            "terms": vals,
            "weights": {kk: weights[kk] for kk in vals},
            "stiffness": contact3.stiffness,
            "garment_vertices": int(x.shape[0]),
            "garment_faces": int(faces.shape[0]),
            "avatar_vertices": int(problem.avatar_vertices.shape[0]),
            "steps": steps,
            "settings": {kk: (v.value if isinstance(v, Enum) else v) for kk, v in asdict(s).items()},
        }
    work = x / k
    return RetargetResult(
        garment_vertices=problem.to_work.inverse(work),
        garment_faces=faces,
        work_vertices=work,
        distortion=distortion,
        steps=steps,
        history=log.history,
        metrics=metrics,
    )


def layer_problem(
    problem: RetargetProblem,
    inner_vertices: torch.Tensor,
    inner_faces: torch.Tensor,
    *,
    inner_source: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> RetargetProblem:
    """``problem`` with an already retargeted garment added to its target avatar (multi-layer retargeting).

    Args:
        problem: the problem of the outer garment (same target avatar and skeletons as the inner one).
        inner_vertices: (M, 3) inner garment in the TARGET frame (``RetargetResult.garment_vertices``).
        inner_faces: (K, 3) long inner garment faces.
        inner_source: optional ``(vertices (M', 3), faces (K', 3))``, the inner garment as it lies on the
            source avatar (its problem's ``garment_vertices`` / ``garment_faces``, the same frame as this
            problem's garment). When ``problem`` has a source avatar it is added to it, so that the outer
            garment's source gaps (``FitTarget.SOURCE_GAP``) are measured to the cloth under it, as its gaps
            on the target are.

    Returns:
        A new problem whose avatar is the avatar plus the inner garment (work frame). Skin weights are dropped
        (the inner garment has none; Step 1 then uses the closest bones).
    """
    if inner_vertices.ndim != 2 or inner_vertices.shape[1] != 3:
        raise InputError(f"inner_vertices must be (M, 3), got {tuple(inner_vertices.shape)}")
    sav, saf = problem.source_avatar_vertices, problem.source_avatar_faces
    if inner_source is not None and sav is not None and saf is not None:
        isv, isf = inner_source
        if isv.ndim != 2 or isv.shape[1] != 3:
            raise InputError(f"inner_source vertices must be (M, 3), got {tuple(isv.shape)}")
        saf = torch.cat([saf, isf.to(saf) + sav.shape[0]])
        sav = torch.cat([sav, isv.to(sav)])
    iv = problem.to_work.apply(inner_vertices.to(problem.avatar_vertices.dtype))
    av = torch.cat([problem.avatar_vertices, iv])
    af = torch.cat(
        [problem.avatar_faces, inner_faces.to(problem.avatar_faces) + problem.avatar_vertices.shape[0]]
    )
    return RetargetProblem(
        garment_vertices=problem.garment_vertices,
        garment_faces=problem.garment_faces,
        source_skeleton=problem.source_skeleton,
        target_skeleton=problem.target_skeleton,
        avatar_vertices=av,
        avatar_faces=af,
        skin_weights=None,
        fit_mask=problem.fit_mask,
        curves=problem.curves,
        to_work=problem.to_work,
        length_scale=problem.length_scale,
        source_avatar_vertices=sav,
        source_avatar_faces=saf,
        garment_index_map=problem.garment_index_map,
    )


def retarget_layers(
    problems: list[RetargetProblem],
    settings: RetargetSettings | None = None,
    *,
    progress: bool = True,
    log_dir: str | Path | None = None,
) -> list[RetargetResult]:
    """Retarget several garments onto one avatar from the inside out; each result joins the avatar of the
    next.

    Args:
        problems: one problem per garment, innermost first, all with the same target avatar and skeletons
            (and the same source avatar, in the same frame, for the source gaps of :class:`FitTarget`).
        settings, progress: as :func:`retarget`. log_dir: each layer logs under ``log_dir/layer<i>``.
    """
    results: list[RetargetResult] = []
    for i, p in enumerate(problems):
        for inner, r in zip(problems, results):
            p = layer_problem(p, r.garment_vertices, r.garment_faces,
                              inner_source=(inner.garment_vertices, inner.garment_faces))
        results.append(
            retarget(
                p,
                settings,
                progress=progress,
                log_dir=None if log_dir is None else Path(log_dir) / f"layer{i}",
            )
        )
    return results
