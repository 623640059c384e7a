"""Draping: sew placed pattern panels together around a body and solve for the quasistatic equilibrium.

:func:`drape` runs a two-stage schedule on a :class:`~torchgarment.sim.scene.Scene`:

1. **sew**: stretch, sewing springs, bending and the body barrier, *no gravity*, starting from the placed
   panels projected out of the body (``project_feasible``: placed panels may start slightly inside). The
   seams pull the flat panels around the body; the stage stops once the largest seam gap is below
   :attr:`DrapeSettings.sew_gap` (or at its iteration budget / tolerance).
2. **settle**: the full scene (gravity on) with sewing springs stiffened to
   :attr:`DrapeSettings.final_sew_stiffness` so that seams close to well under a millimetre against the cloth
   tension, solved to equilibrium. With a support (a pattern whose :attr:`SewingPattern.support` is not empty,
   e.g. a skirt's waistband, and :attr:`DrapeSettings.support` on) this stage also holds the support where
   the garment is worn: soft sticking springs (``Effect.PINS``) from its vertices to the body's waist line
   (:func:`~torchgarment.sim.support.waist_band_targets`: the band's loop in the waist plane, around the
   convex hull of the body's section, keeping its own length, rotated to match the sewn band), with the
   stiffness :func:`~torchgarment.sim.support.support_stiffness` (the band holds the garment's weight with a
   mean give of :attr:`DrapeSettings.support_sag`).

With :attr:`DrapeSettings.self_contact` the sewing stage has IPC contact within each panel and the settle
stage on the whole welded garment (see there).

Every stage keeps its :class:`~torchgarment.sim.solvers.SolveInfo` (residual and energy histories). The
result reports the body clearance ``min phi`` (SDF), the largest distance between paired seam vertices and
whether the final stage converged; :attr:`DrapeResult.ok` is all three checks together. Nothing is faked: a
drape that does not meet a check says so in its metrics.

Example::

    body = Body.from_size("6")
    pattern = draft("straight_skirt", chart_row("6"))
    result = drape(pattern, body, settings=DrapeSettings(edge_length=0.02))
    result.metrics["max_seam_gap_mm"], result.metrics["min_sdf_mm"], result.converged
"""

from __future__ import annotations

import math
import time
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Callable

import torch

from torchgarment.errors import InputError, MeshError, NonConvergenceError
from torchgarment.linalg import SparseBackend
from torchgarment.sdf.grid import SDFSampling
from torchgarment.sim.scene import Effect, Material, Scene, SimModel
from torchgarment.sim.solvers import (
    LinearSolver,
    SolveInfo,
    SolverKind,
    SolveSettings,
    exact_curvature_iterations,
    solve,
)
from torchgarment.sim.support import (
    DEFAULT_SUPPORT_SAG,
    SupportLoop,
    support_metrics,
    support_stiffness,
    waist_band_targets,
)
from torchgarment.structures.garment_mesh import GarmentMesh

if TYPE_CHECKING:
    from torchgarment.body import Body
    from torchgarment.pattern.spec import SewingPattern
    from torchgarment.sdf import BodySDF

#: ``progress(stage_name, iteration, residual)`` called after every solver iteration (e.g. a tqdm update).
ProgressFn = Callable[[str, int, float], None]


@dataclass
class DrapeSettings:
    """Settings of :func:`drape`.

    Attributes:
        edge_length: target triangle edge length in metres when a pattern is given (ignored for a mesh).
        voxel_size: SDF voxel size in metres when the body is given as a mesh/:class:`Body` (ignored when
            an ``sdf`` is passed to :func:`drape`).
        sdf_sampling: interpolation of the body SDF in the simulation (and in the clearance check):
            ``"quadratic"`` (default, C1: the barrier force is continuous, so Newton's settle stage has a
            smooth equilibrium to converge to) or ``"trilinear"`` (cheaper, C0: the barrier force jumps across
            voxel faces, and the settle stage may stall at voxel scale). Applied to a :class:`BodySDF` body or
            ``sdf`` argument as a view (:meth:`BodySDF.with_sampling`); other SDF modules are used as given.
        material: cloth parameters (stretch, sewing, bending, density, barrier).
        sew_solver: solver of the sewing stage (``"gd-chebyshev"`` or ``"newton"``; Newton closes a skirt's
            seams in ~20 iterations but can snag a tshirt on the body, GD-Chebyshev is slower and robust).
        solver: solver of the settle stage.
        sew_gap: the sewing stage stops once the largest seam gap is below this (metres).
        sew_rtol: relative force tolerance of the sewing stage.
        sew_max_iterations: iteration budget of the sewing stage.
        final_sew_stiffness: sewing spring constant (N/m) of the settle stage; None keeps ``material``'s.
        barrier_mu: body-barrier weight (J) of the settle stage; None (default) keeps ``material``'s (the
            paper's 0.01 J, range-limited to ``material.barrier_dhat`` = 3 mm). With the unbounded ``-mu log
            phi`` (``material.barrier_dhat = None``) the paper's weight pushes with ``mu / phi`` at every
            distance (0.25 N at 4 cm, hundreds of times a 3 cm cloth vertex's weight): loose cloth floats on
            the far field and the settle stage stalls; use about 1e-3 J with that form.
        rtol: relative force tolerance of the settle stage (relative to its initial force norm); default 0:
            the initial force of the settle stage is dominated by the stiffened seam springs (hundreds of
            newtons for a 2 mm gap), so a relative test would accept whatever that leftover happens to be.
        atol_weight: absolute force tolerance of the settle stage as a fraction of the garment's total weight
            ``W = m g`` (newtons): converged when ``|g|_2 <= max(rtol |g0|, atol_weight * W)``. The default
            1e-3 makes the whole residual force vector (2-norm over all vertices) at most 0.1 % of the weight,
            about one vertex's weight at 3 cm edges (~1,000 vertices), so every vertex is in equilibrium to
            within its own weight and the total unbalanced force is negligible against gravity.
        max_iterations: iteration budget of the settle stage (a converged drape stops early; the tight
            GarmentCode pencil dress needs about 1,150 Newton iterations as its skirt slides into place).
        reuse_factorization: the settle stage's Newton reuses its last factorization as a CG preconditioner
            (``SolveSettings.reuse_factorization``). Measured on the straight skirt, size 12: 7,349 vertices
            settle in 62.6 s instead of 96.8 s (138 and 136 iterations), 1,877 vertices in 5.5 s instead of
            7.2 s. No effect with ``linear_solver="jacobi-pcg"``, which makes no factorization. With
            ``exact_curvature_cg`` the factorization preconditions CG on the exact Hessian while CG converges.
        exact_curvature_cg: the settle's Newton direction by up to this many CG iterations on the exact
            Hessian preconditioned by a factorization of the projected one
            (``SolveSettings.exact_curvature_cg``; 0: projected Newton; None, the default:
            :data:`~torchgarment.sim.solvers.DEFAULT_EXACT_CURVATURE_CG` with ``linear_solver="direct"``, 0
            with ``"jacobi-pcg"``). Measured at 1.5-2 cm edges, SuperLU,
            factorizations reused, 1 thread: the sheath dress drafted for 12 on the size-20 body settles in 36
            Newton iterations (4.0 s) instead of 193 (10.3 s); over eight library drapes 59.8 s of settling
            instead of 88.5 s (see the README).
        sparse_backend: the sparse direct solver of those factorizations
            (:class:`~torchgarment.linalg.SparseBackend`): ``"superlu"`` (default) or an optional one,
            e.g. ``"cholmod"`` (``pip install -e ".[cholmod]"``; 3-4x faster factorizations).
        linear_solver: how the settle stage's Newton solves its systems
            (:class:`~torchgarment.sim.solvers.LinearSolver`): ``"direct"`` (a sparse factorization on the
            CPU, default) or ``"jacobi-pcg"`` (block-Jacobi CG on the garment's device, the GPU path).
        max_displacement: GD trust region per iteration in metres.
        check_interval: iterations between seam-gap checks in the sewing stage.
        max_seam_gap: largest acceptable seam gap in metres for :attr:`DrapeResult.ok`.
        support: hold the pattern's support (:attr:`SewingPattern.support`) at the body's waist in the settle
            stage (needs a body mesh: a :class:`Body`, not only an SDF); no effect for a pattern without a
            support or a :class:`GarmentMesh`.
        support_sag: the support's stiffness: its pins hold the garment's whole weight with this mean
            displacement in metres (``k = W / (P sag)`` per pin, see :mod:`torchgarment.sim.support`).
        self_contact: the settle stage adds IPC cloth-cloth contact on the welded garment
            (``Effect.SELF_CONTACT``), so the garment cannot pass through itself as it settles (without it a
            tshirt's sleeve settled through its side on one machine and not on another:
            ``metrics["intersects_self"]``). The sewing stage, which draws panels together across each other
            by design, gets contact within each panel (``Effect.PANEL_CONTACT``, for a garment with panel
            ids), so that no panel folds through itself (a GarmentCode shirt's sleeves did at their cuffs).
            Needs panels placed without crossing themselves (else :class:`~torchgarment.errors.MeshError`) and
            an intersection-free sewn garment (else :class:`~torchgarment.errors.NonConvergenceError`: panels
            may still cross each other after sewing). Costs ipctk's broad phase and continuous collision
            checks every iteration: the library's 11 drapes that converge at 3 cm took 141 s, 121 s with
            contact in the settle only (README, "Contact within each panel while sewing").
        contact_threads: ipctk's threads in the self-contact stages
            (:func:`~torchgarment.sim.contact.ipc_threads`; None: ipctk's default, every core). 1, the
            default, makes the drape the same bit for bit on every run: with 2 threads two drapes of the
            GarmentCode pencil dress took 1,064 and 888 settle iterations, with 1 both 903, in 65 and 59 s
            against 72 and 67 s (2 cores).
    """

    edge_length: float = 0.02
    voxel_size: float = 0.005
    sdf_sampling: SDFSampling = SDFSampling.QUADRATIC
    material: Material = field(default_factory=Material)
    sew_solver: SolverKind = SolverKind.GD_CHEBYSHEV
    solver: SolverKind = SolverKind.NEWTON
    sew_gap: float = 2.0e-3
    sew_rtol: float = 1.0e-4
    sew_max_iterations: int = 1500
    final_sew_stiffness: float | None = 1.0e5
    barrier_mu: float | None = None
    rtol: float = 0.0
    atol_weight: float = 1.0e-3
    max_iterations: int = 1500
    reuse_factorization: bool = True
    sparse_backend: SparseBackend = SparseBackend.SUPERLU
    exact_curvature_cg: int | None = None
    linear_solver: LinearSolver = LinearSolver.DIRECT
    max_displacement: float | None = 0.01
    check_interval: int = 5
    max_seam_gap: float = 1.0e-3
    support: bool = True
    support_sag: float = DEFAULT_SUPPORT_SAG
    self_contact: bool = False
    contact_threads: int | None = 1

    def __post_init__(self) -> None:
        self.sew_solver = SolverKind.resolve(self.sew_solver)
        self.solver = SolverKind.resolve(self.solver)
        self.sparse_backend = SparseBackend.resolve(self.sparse_backend)
        self.sdf_sampling = SDFSampling.resolve(self.sdf_sampling)
        self.linear_solver = LinearSolver.resolve(self.linear_solver)
        self.validate()

    def validate(self) -> None:
        """Raise :class:`InputError` for out-of-range settings (called on construction; changes nothing)."""
        for name, kind in (("sew_solver", SolverKind), ("solver", SolverKind), ("sdf_sampling", SDFSampling),
                           ("linear_solver", LinearSolver)):
            if not isinstance(getattr(self, name), kind):
                raise InputError(f"DrapeSettings.{name} must be one of {[k.value for k in kind]}, "
                                 f"got {getattr(self, name)!r}")
        positive = {"edge_length": self.edge_length, "voxel_size": self.voxel_size, "sew_gap": self.sew_gap,
                    "max_seam_gap": self.max_seam_gap, "support_sag": self.support_sag}
        for name, v in positive.items():
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InputError(f"DrapeSettings.{name} must be a positive number, got {v!r}")
        if self.final_sew_stiffness is not None and not self.final_sew_stiffness > 0:
            raise InputError(f"DrapeSettings.final_sew_stiffness must be > 0 or None, "
                             f"got {self.final_sew_stiffness}")
        if self.barrier_mu is not None and not self.barrier_mu > 0:
            raise InputError(f"DrapeSettings.barrier_mu must be > 0 or None, got {self.barrier_mu}")
        if self.contact_threads is not None and not (isinstance(self.contact_threads, int)
                                                     and self.contact_threads >= 1):
            raise InputError(f"DrapeSettings.contact_threads must be a positive integer or None, "
                             f"got {self.contact_threads!r}")
        if self.sew_max_iterations < 0 or self.max_iterations < 0 or self.check_interval < 1:
            raise InputError("DrapeSettings: iteration budgets must be >= 0 and check_interval >= 1")
        if not (self.rtol >= 0 and self.sew_rtol >= 0 and self.atol_weight >= 0):
            raise InputError("DrapeSettings: tolerances must be >= 0")
        ecg = self.exact_curvature_cg
        if ecg is not None and (not isinstance(ecg, int) or ecg < 0
                                or (ecg and self.linear_solver != LinearSolver.DIRECT)):
            raise InputError("DrapeSettings.exact_curvature_cg must be >= 0, and 0 with linear_solver="
                             "'jacobi-pcg' (it preconditions by a factorization)")


@dataclass
class DrapeStage:
    """One stage of the schedule: its name, the effects it used and what its solve did."""

    name: str
    effects: tuple[str, ...]
    info: SolveInfo
    max_seam_gap: float

    def to_dict(self) -> dict:
        return {"name": self.name, "effects": list(self.effects), "max_seam_gap_mm": 1e3 * self.max_seam_gap,
                "seconds_per_iteration": self.info.seconds / max(self.info.iterations, 1),
                **self.info.to_dict()}


@dataclass
class DrapeResult:
    """Outcome of :func:`drape`.

    Attributes:
        x: (V, 3) draped positions in metres.
        mesh: the garment mesh at ``x`` (same topology, ``p`` and seams as the input).
        info: the settle stage's :class:`SolveInfo` (final residual, histories).
        stages: every stage of the schedule, in order, with its histories.
        metrics: JSON-serializable numbers: ``vertices``, ``faces``, ``iterations``, ``seconds``,
            ``residual``, ``tolerance``, ``min_sdf_mm``, ``inside_vertices``, ``max_seam_gap_mm``,
            ``mean_seam_gap_mm``, ``energy_start``, ``energy``, ``energy_terms`` (J per term), ``converged``,
            ``ok``, ``support`` (the held support as ``PANEL:EDGE,...``, or None) and, with a support, the
            numbers of :func:`~torchgarment.sim.support.support_metrics` (``support_force_n``,
            ``support_force_sum_n``, ``support_max_displacement_mm``, ...) and ``support_target`` (waist plane
            height, hull girth, band length, offset).
        model: the settle stage's :class:`SimModel` (to evaluate energies or continue solving).
        support_indices: (P,) long pinned support vertices, or None without a support.
        support_targets: (P, 3) their targets in metres, or None.
        support_stiffness: the pins' spring constant in N/m, or None.
    """

    x: torch.Tensor
    mesh: GarmentMesh
    info: SolveInfo
    stages: list[DrapeStage]
    metrics: dict
    model: SimModel
    support_indices: torch.Tensor | None = None
    support_targets: torch.Tensor | None = None
    support_stiffness: float | None = None

    @property
    def converged(self) -> bool:
        """Whether the settle stage met its force tolerance."""
        return bool(self.info.converged)

    @property
    def ok(self) -> bool:
        """Converged, no vertex inside the body and every seam closed to ``max_seam_gap``."""
        return bool(self.metrics["ok"])


def seam_gaps(mesh: GarmentMesh, x: torch.Tensor) -> torch.Tensor:
    """(S,) distances in metres between the two vertices of every seam pair at positions ``x`` (V, 3)."""
    s = mesh.seam_pairs
    return torch.linalg.vector_norm(x[s[:, 0]] - x[s[:, 1]], dim=1)


def max_seam_gap(mesh: GarmentMesh, x: torch.Tensor) -> float:
    """Largest seam-pair distance in metres (0 without seams)."""
    return float(seam_gaps(mesh, x).max()) if mesh.seam_pairs.shape[0] else 0.0


def vertex_stretch_ratio(mesh: GarmentMesh, x: torch.Tensor) -> torch.Tensor:
    """(V,) mean ratio current / rest length of the mesh edges at each vertex (1 = unstretched).

    Rest lengths come from the pattern ``p``; a mesh without ``p`` uses ``mesh.x`` as its rest state.
    """
    e = mesh.edges
    rest_pos = mesh.p if mesh.p is not None else mesh.x
    rest = torch.linalg.vector_norm(rest_pos[e[:, 0]] - rest_pos[e[:, 1]], dim=1)
    cur = torch.linalg.vector_norm(x[e[:, 0]] - x[e[:, 1]], dim=1)
    ratio = cur / rest.clamp_min(torch.finfo(x.dtype).tiny)
    V = mesh.num_vertices
    sums = torch.zeros(V, dtype=x.dtype, device=x.device)
    cnt = torch.zeros(V, dtype=x.dtype, device=x.device)
    for col in (0, 1):
        sums.index_add_(0, e[:, col], ratio)
        cnt.index_add_(0, e[:, col], torch.ones_like(ratio))
    return sums / cnt.clamp_min(1.0)


def _as_mesh(pattern_or_mesh: SewingPattern | GarmentMesh, settings: DrapeSettings, dtype: torch.dtype,
             device: torch.device | str | None) -> GarmentMesh:
    if isinstance(pattern_or_mesh, GarmentMesh):
        if pattern_or_mesh.seam_pairs.shape[0] == 0 and pattern_or_mesh.p is None:
            raise InputError("drape needs a sewn garment: the mesh has neither rest positions p nor seam "
                             "pairs")
        return pattern_or_mesh.to(device=device, dtype=dtype)
    from torchgarment.pattern.spec import SewingPattern

    if isinstance(pattern_or_mesh, SewingPattern):
        from torchgarment.pattern.meshing import mesh_pattern

        return mesh_pattern(pattern_or_mesh, settings.edge_length, dtype=dtype, device=device)
    raise InputError(f"drape takes a SewingPattern or a GarmentMesh, got {type(pattern_or_mesh).__name__}")


def _body_sdf(body: Body | BodySDF | torch.nn.Module | None, settings: DrapeSettings, dtype: torch.dtype,
              device: torch.device | str | None) -> torch.nn.Module:
    from torchgarment.sdf import BodySDF, SDFSettings

    if isinstance(body, BodySDF):
        return body.to(device=device, dtype=dtype).with_sampling(settings.sdf_sampling)
    if body is not None and hasattr(body, "value_and_gradient") and not hasattr(body, "faces"):
        return body  # another SDF module: used as given
    verts, faces = getattr(body, "vertices", None), getattr(body, "faces", None)
    if verts is None or faces is None:
        raise InputError(f"drape needs a body with vertices and faces (a Body) or a BodySDF, "
                         f"got {type(body).__name__}")
    sdf = BodySDF.cached(verts, faces, SDFSettings(voxel_size=settings.voxel_size), device=device,
                         dtype=dtype)
    return sdf.with_sampling(settings.sdf_sampling)


FALL_CHECK_INTERVAL = 10
"""Settle iterations between two checks that the garment has not fallen off the body (:func:`drape`)."""


def _callback(name: str, mesh: GarmentMesh, gap_stop: float | None, every: int,
              progress: ProgressFn | None, body_vertices: torch.Tensor | None = None
              ) -> Callable[[int, torch.Tensor, float, float], bool]:
    """The solver callback of a stage: progress, the sew stage's seam-gap stop, and (with ``body_vertices``)
    a stop once the garment has fallen off the body or exploded (:func:`unusable_positions`): gravity then
    has nothing to balance it and the solve would run to its iteration budget (a single unstitched panel
    fell for 69 s)."""
    def cb(k: int, x: torch.Tensor, residual: float, energy: float) -> bool:
        if progress is not None:
            progress(name, k, residual)
        if gap_stop is not None and k % every == 0:
            return max_seam_gap(mesh, x) <= gap_stop
        if body_vertices is not None and k % FALL_CHECK_INTERVAL == 0:
            return unusable_positions(x, body_vertices) is not None
        return False

    return cb


def _run_stage(name: str, scene: Scene, x: torch.Tensor, solver: SolverKind, solve_settings: SolveSettings,
               mesh: GarmentMesh, gap_stop: float | None, every: int, progress: ProgressFn | None,
               ) -> tuple[torch.Tensor, SimModel, DrapeStage]:
    model = scene.build()
    x = model.project_feasible(x)
    if Effect.PANEL_CONTACT in model.effects and not math.isfinite(float(model.value_and_grad(x)[0])):
        where = _crossing_summary(mesh.with_positions(x), within_panels=True)
        raise MeshError(f"a panel intersects itself as placed ({where}), so the sewing stage cannot keep it "
                        "intersection free; drape without self_contact")
    x, info = solve(model, x, solve_settings, solver=solver,
                    callback=_callback(name, mesh, gap_stop, every, progress))
    stage = DrapeStage(name, tuple(e.value for e in model.effects), info, max_seam_gap(mesh, x))
    return x, model, stage


def drape(
    pattern_or_mesh: SewingPattern | GarmentMesh,
    body: Body | BodySDF | None,
    *,
    settings: DrapeSettings | None = None,
    sdf: BodySDF | None = None,
    progress: ProgressFn | None = None,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
    support: SupportLoop | None = None,
    support_reference: torch.Tensor | None = None,
) -> DrapeResult:
    """Sew a garment's placed panels around a body and solve for equilibrium (see the module docstring).

    Args:
        pattern_or_mesh: a :class:`~torchgarment.pattern.spec.SewingPattern` (meshed at
            ``settings.edge_length``, panels at their 3D placement) or a sewn :class:`GarmentMesh` whose ``x``
            holds the placed panels.
        body: a :class:`~torchgarment.body.Body` (anything with ``vertices`` (B, 3) and ``faces`` (G, 3)),
            whose SDF is built at ``settings.voxel_size`` through the disk cache, or a ready :class:`BodySDF`.
        settings: schedule and tolerances; default :class:`DrapeSettings()`.
        sdf: a prebuilt SDF of ``body`` (skips building); it is also what the clearance is checked with.
        progress: ``progress(stage, iteration, residual)`` after every solver iteration.
        dtype: floating dtype of the simulation. device: its device.
        support: the support of a :class:`GarmentMesh` (:meth:`SupportLoop.of` its pattern), held like a
            pattern's own support (:attr:`DrapeSettings.support`); a pattern's own support is used for a
            pattern, and a mesh without one hangs by its tension.
        support_reference: (V, 3) positions whose support vertices choose the rotation (phase) of the
            support's targets around the waist (:func:`waist_band_targets`); None: the positions after the
            sewing stage. A warm start (:func:`~torchgarment.datadriven.basis.refine`) passes the garment's
            placed panels: its targets then are a cold drape's, instead of following a rotated start (a start
            rotated by 2 degrees about the body kept 3.5 mm of it after a converged settle).

    Returns:
        The :class:`DrapeResult`.

    Raises:
        InputError: bad settings, an unusable pattern/mesh or body.
        NonFiniteError: a solver met NaN/Inf.
    """
    settings = replace(settings) if settings is not None else DrapeSettings()
    settings.validate()
    t0 = time.perf_counter()
    mesh = _as_mesh(pattern_or_mesh, settings, dtype, device)
    sdf = _body_sdf(body if sdf is None else sdf, settings, dtype, mesh.device)
    mat = settings.material
    has_seams = mesh.seam_pairs.shape[0] > 0
    stages: list[DrapeStage] = []
    x = mesh.x.detach()

    base = {Effect.BEND, Effect.BODY_BARRIER}
    if mesh.p is not None:
        base.add(Effect.STRETCH)
    if has_seams:
        base.add(Effect.SEW)
        sew_settings = SolveSettings(rtol=settings.sew_rtol, max_iterations=settings.sew_max_iterations,
                                     max_displacement=settings.max_displacement,
                                     sparse_backend=settings.sparse_backend)
        sew_effects = set(base)
        if settings.self_contact and mesh.panel_ids is not None:  # each panel cannot pass through itself
            sew_effects.add(Effect.PANEL_CONTACT)
        scene = Scene(mesh, body_sdf=sdf, effects=sew_effects, material=mat)
        with _contact_threads(settings):
            x, _, stage = _run_stage("sew", scene, x, settings.sew_solver, sew_settings, mesh,
                                     settings.sew_gap, settings.check_interval, progress)
        stages.append(stage)

    final_mat = replace(mat)
    if has_seams and settings.final_sew_stiffness is not None:
        final_mat.sew_stiffness = float(settings.final_sew_stiffness)
    if settings.barrier_mu is not None:
        final_mat.barrier_mu = float(settings.barrier_mu)
    weight = (float(mesh.rest_face_areas.abs().sum()) * mat.density * mat.gravity if mesh.p is not None
              else 0.0)
    if isinstance(pattern_or_mesh, GarmentMesh):
        loop = support
    else:
        loop = SupportLoop.of(pattern_or_mesh, mesh) if settings.support else None
    if support_reference is not None and tuple(support_reference.shape) != (mesh.num_vertices, 3):
        raise InputError(f"support_reference must be ({mesh.num_vertices}, 3), got "
                         f"{tuple(support_reference.shape)}")
    phase_x = x if support_reference is None else support_reference.to(x)
    pins = _support_pins(loop, mesh, body, phase_x, weight, settings)
    effects = base | {Effect.GRAVITY}
    if settings.self_contact:
        effects.add(Effect.SELF_CONTACT)
    if pins is not None:
        final_mat.pin_stiffness = pins[2]
        effects.add(Effect.PINS)
    scene = Scene(mesh, body_sdf=sdf, effects=effects, material=final_mat,
                  pin_indices=None if pins is None else pins[0],
                  pin_targets=None if pins is None else pins[1])
    settle_settings = SolveSettings(rtol=settings.rtol, atol=settings.atol_weight * weight,
                                    max_iterations=settings.max_iterations,
                                    max_displacement=settings.max_displacement,
                                    linear_solver=settings.linear_solver,
                                    sparse_backend=settings.sparse_backend,
                                    exact_curvature_cg=exact_curvature_iterations(settings.exact_curvature_cg,
                                                                                  settings.linear_solver),
                                    reuse_factorization=(settings.reuse_factorization
                                                         and settings.linear_solver == LinearSolver.DIRECT))
    model = scene.build()
    with _contact_threads(settings):
        x_start = model.project_feasible(x)
        energy_start = float(model.value_and_grad(x_start)[0])
        if settings.self_contact and not math.isfinite(energy_start):
            error = NonConvergenceError if has_seams else MeshError
            when = "after sewing" if has_seams else "at the start"
            where = _crossing_summary(mesh.with_positions(x_start))
            raise error(f"the garment intersects itself {when} ({where}), so the settle stage cannot keep it "
                        "intersection free; drape without self_contact")
        stop = _callback("settle", mesh, None, 1, progress, getattr(body, "vertices", None))
        x, info = solve(model, x_start, settle_settings, solver=settings.solver, callback=stop)
        energy_terms = model.term_values(x)  # on the same ipctk threads: metrics.json the same every run
    stages.append(DrapeStage("settle", tuple(e.value for e in model.effects), info, max_seam_gap(mesh, x)))

    with torch.no_grad():
        phi = sdf(x)
    gaps = seam_gaps(mesh, x) if has_seams else torch.zeros(1, dtype=x.dtype, device=x.device)
    min_phi = float(phi.min())
    gap = float(gaps.max())
    iterations = sum(s.info.iterations for s in stages)
    seconds = time.perf_counter() - t0
    metrics = {
        "vertices": mesh.num_vertices,
        "faces": int(mesh.faces.shape[0]),
        "seam_pairs": int(mesh.seam_pairs.shape[0]),
        "iterations": iterations,
        "seconds": seconds,
        "solve_seconds": sum(s.info.seconds for s in stages),
        "residual": info.residual,
        "tolerance": max(settle_settings.rtol * info.residual_history[0], settle_settings.atol)
        if info.residual_history else math.nan,
        "weight_n": weight,
        "min_sdf_mm": 1e3 * min_phi,
        "inside_vertices": int((phi < 0).sum()),
        "max_seam_gap_mm": 1e3 * gap,
        "mean_seam_gap_mm": 1e3 * float(gaps.mean()),
        "energy_start": energy_start,
        "energy": info.energy_history[-1] if info.energy_history else math.nan,
        "energy_terms": energy_terms,
        "converged": bool(info.converged),
        "message": info.message,
        "voxel_size": float(getattr(sdf, "voxel_size", math.nan)),
        "stages": [s.to_dict() for s in stages],
        "self_contact": bool(settings.self_contact),
        "intersects_self": _intersects_itself(mesh.with_positions(x)),
    }
    metrics["ok"] = bool(info.converged and min_phi >= 0 and gap <= settings.max_seam_gap)
    metrics["support"] = None
    if pins is not None:
        metrics["support"] = loop.name
        metrics.update(support_metrics(x, pins[0], pins[1], pins[2]))
        metrics["support_target"] = pins[3]
    return DrapeResult(x=x, mesh=mesh.with_positions(x), info=info, stages=stages, metrics=metrics,
                       model=model, support_indices=None if pins is None else pins[0],
                       support_targets=None if pins is None else pins[1],
                       support_stiffness=None if pins is None else pins[2])


def _support_pins(loop: SupportLoop | None, mesh: GarmentMesh, body: Body | BodySDF | None,
                  x: torch.Tensor, weight: float, settings: DrapeSettings
                  ) -> tuple[torch.Tensor, torch.Tensor, float, dict] | None:
    """(indices, targets, stiffness, target info) of the support's pins, or None without a support."""
    if not settings.support or loop is None:
        return None
    verts, faces = getattr(body, "vertices", None), getattr(body, "faces", None)
    if verts is None or faces is None:
        raise InputError("holding the support at the waist needs the body mesh: pass a Body (not only an "
                         "SDF) or DrapeSettings(support=False)")
    if weight <= 0:
        raise InputError("the support's stiffness needs the garment's weight: the mesh has no rest pattern p")
    idx = loop.indices.to(device=x.device)
    if idx.numel() == 0 or int(idx.max()) >= mesh.num_vertices:
        raise InputError(f"the support loop {loop.name} does not belong to this mesh of {mesh.num_vertices} "
                         "vertices")
    targets, info = waist_band_targets(verts, faces, x[idx], loop.arc, loop.length)
    return idx, targets, support_stiffness(weight, int(idx.numel()), settings.support_sag), info


def _contact_threads(settings: DrapeSettings) -> AbstractContextManager[None]:
    """:func:`~torchgarment.sim.contact.ipc_threads` of ``settings.contact_threads`` when the drape has
    self-contact (the sewing stage's within panels, the settle's on the welded garment; ipctk is imported
    only then)."""
    if not settings.self_contact:
        return nullcontext()
    from torchgarment.sim.contact import ipc_threads

    return ipc_threads(settings.contact_threads)


def _crossing_summary(mesh: GarmentMesh, within_panels: bool = False) -> str:
    """Where the welded garment (``within_panels``: each panel of the unsewn garment) passes through itself,
    in a few words: how many edges cross a triangle, the panels of the crossed triangles, and where the first
    crossing is (m)."""
    from torchgarment.sim.contact import self_crossings

    welded = mesh if within_panels else mesh.welded()[0]
    rows = self_crossings(welded.x, welded.faces)
    if within_panels:
        vertex_panel, face_panel = welded.vertex_panel_ids.cpu().numpy(), welded.panel_ids.cpu().numpy()
        rows = rows[vertex_panel[rows[:, 0]] == face_panel[rows[:, 2]]]
    if rows.shape[0] == 0:
        return "no edge crosses a triangle: primitives touch"
    x = welded.x.detach().cpu().double().numpy()
    first = 0.5 * (x[rows[0, 0]] + x[rows[0, 1]])
    where = ", ".join(f"{c:.2f}" for c in first)
    panels = ""
    if welded.panel_ids is not None and welded.panel_names:
        ids = sorted({int(i) for i in welded.panel_ids.detach().cpu()[torch.as_tensor(rows[:, 2])]})
        panels = f", in panel{'s' if len(ids) > 1 else ''} " + ", ".join(welded.panel_names[i] for i in ids)
    return f"{rows.shape[0]} edge-triangle crossings{panels}, the first at ({where}) m"


def _intersects_itself(mesh: GarmentMesh) -> bool:
    """Whether the welded garment (seams closed) intersects itself (ipctk)."""
    from torchgarment.sim.contact import intersects_itself

    welded, _ = mesh.welded()
    return intersects_itself(welded.x, welded.faces)


def unusable_positions(x: torch.Tensor, body_vertices: torch.Tensor) -> str | None:
    """Why garment positions cannot be a garment worn on a body, or None: non-finite coordinates, or a vertex
    farther outside the body's bounding box than half the body's largest extent (it fell or exploded).

    Args:
        x: (V, 3) garment vertices, metres. body_vertices: (B, 3) the body's vertices, metres.
    """
    x = x.detach()
    if not bool(torch.isfinite(x).all()):
        return "the garment has non-finite coordinates"
    b = body_vertices.detach().to(x)
    lo, hi = b.min(dim=0).values, b.max(dim=0).values
    margin = 0.5 * float((hi - lo).max())
    far = float(torch.maximum(lo - x, x - hi).clamp(min=0.0).norm(dim=1).max())
    if far > margin:
        return (f"a garment vertex ended {far:.3g} m outside the body's bounding box (limit {margin:.3g} m, "
                "half the body's size): it fell or exploded")
    return None


def unusable_reason(result: DrapeResult, body_vertices: torch.Tensor) -> str | None:
    """Why a drape's result cannot be used, or None when it can (issue 17; the command line then exits 3).

    Unusable: non-finite positions; a garment vertex farther outside the body's bounding box than half the
    body's largest extent (a garment that fell or exploded: a single unstitched panel ended at 2e12 m, a
    tiny pattern 9.3 m below the body); or a residual force larger than the garment's weight (far from
    equilibrium: 550 N against a 0.3 N garment). A drape that stopped at its iteration budget with neither is
    usable, converged or not.

    Args:
        result: the drape. body_vertices: (B, 3) the body's vertices in metres.

    Returns:
        One line naming the reason and the figures, or None.
    """
    reason = unusable_positions(result.x, body_vertices)
    if reason is not None:
        return reason
    m = result.metrics
    residual, weight = float(m.get("residual", math.nan)), float(m.get("weight_n", math.nan))
    if not m.get("converged", False) and not residual <= weight:
        return (f"far from equilibrium: a residual force of {residual:.3g} N, more than the garment's weight "
                f"({weight:.3g} N; tolerance {float(m.get('tolerance', math.nan)):.3g} N)")
    return None
