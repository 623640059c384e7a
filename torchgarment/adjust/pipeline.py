"""Sewing-pattern adjustment end to end (Wang et al. 2018): :func:`adjust`.

1. drape the base garment on the base body (:func:`torchgarment.sim.drape.drape`);
2. transfer it to the target body (Eq. 15, :func:`~torchgarment.adjust.transfer.transfer_deformation`);
3. initialize (section 7): with ``x`` held at the transferred garment, minimize stretching plus regularizers
   (``AdjustObjective.initialization_objective``) by L-BFGS; the full objective of the initialized pattern is
   reported against the base pattern's (the paper sees 1/6 to 1/10);
4. optimize with the chosen optimizer: ``pgd`` runs Algorithm 1 (inexact simulations, long-range backtracking,
   :class:`~torchgarment.adjust.inexact.InexactRunner`) unless ``inexact=False``; ``lbfgs``, ``gn`` and
   ``fixed-point`` evaluate exactly (their line searches / updates need true equilibria). The result is the
   best exactly evaluated pattern, never worse than the start of step 4.

Every iteration records the objective, each term, the step length, ``S`` and the wall time (TensorBoard
scalars under ``log_dir``); a tqdm bar shows progress; Ctrl-C (KeyboardInterrupt) writes a resumable
checkpoint (``checkpoint_dir/adjust.pt``, atomic) before re-raising, and ``resume=True`` continues from it.

Objective numbers: ``objective_base`` is the objective of the base pattern on the target body,
``objective_initial`` that of the initialized pattern (the start of the optimization, the reference of
``reduction_percent`` as in the paper's Table 1) and ``objective_final`` that of the result.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from torchgarment.adjust.fit import FitScale
from torchgarment.adjust.inexact import AdjustProblem, InexactRunner, InexactSettings, IterationRecord
from torchgarment.adjust.optimizers import OptimizerKind, make_optimizer
from torchgarment.errors import InputError, PatternError
from torchgarment.linalg import SparseBackend
from torchgarment.logging import RunLogger
from torchgarment.sim.diff import AdjointHessian, AdjointLinearSolver
from torchgarment.sim.drape import DrapeResult, DrapeSettings, drape
from torchgarment.sim.energies.pins import Pins
from torchgarment.sim.scene import Effect, Scene
from torchgarment.sim.solvers import LinearSolver, SolverKind, SolveSettings, exact_curvature_iterations
from torchgarment.sim.support import support_metrics
from torchgarment.structures.garment_mesh import GarmentMesh

if TYPE_CHECKING:
    from collections.abc import Callable

    from torchgarment.adjust.objective import AdjustObjective
    from torchgarment.adjust.parametrization import BoundaryParametrization
    from torchgarment.body import Body
    from torchgarment.pattern.spec import SewingPattern
    from torchgarment.sdf import BodySDF

CHECKPOINT_NAME = "adjust.pt"
"""File name of the resumable checkpoint inside ``checkpoint_dir``."""


@dataclass
class AdjustSettings:
    """Settings of :func:`adjust`.

    Attributes:
        optimizer: ``"pgd"`` (default, the paper's), ``"lbfgs"``, ``"gn"`` or ``"fixed-point"``.
        iterations: outer iterations of the optimizer (paper: 256-512).
        inexact: run Algorithm 1 (pgd only; the other optimizers always evaluate exactly).
        inner_iterations: initial ``S`` (solver iterations per inexact outer iteration).
        exact_interval: ``M``, outer iterations between exact checks (paper: 32).
        min_model_ratio: the ratio test of an exact check that drops
            (:attr:`~torchgarment.adjust.inexact.InexactSettings.min_model_ratio`): below it, S grows and the
            step shrinks although the check is kept. 0: the paper's rule alone.
        adapt_step: halve the step after an inexact objective above the last ``step_window`` ones, lengthen
            it after one below them (:attr:`~torchgarment.adjust.inexact.InexactSettings.adapt_step`). False
            (default): the paper's step, changed only at the exact checks.
        step_window: how many recent inexact objectives ``adapt_step`` compares with (1: the plain bold
            driver).
        inner_solver: solver of the S-iteration simulations (``"newton"``: S Newton steps).
        solver: solver of the exact simulations.
        step: step length ``s`` (``lr``) of the optimizer; None = pgd: unbounded (every step is capped by
            ``max_displacement``, so the first steps move the boundary by ``max_displacement``; long-range
            backtracking then
            shrinks it), the others 1 (the quasi-Newton / Gauss-Newton step, the fixed point's full update).
        max_displacement: largest move of a boundary vertex per step in metres (caps the steps of pgd, gn
            and L-BFGS).
        weights: cost coefficients (an ``AdjustObjective`` ``CostWeights``); None = its defaults.
        initialize: run the section-7 initialization.
        init_iterations: L-BFGS iterations of the initialization.
        init_trial_iterations: when the initialized pattern's equilibrium scores no better than the base
            pattern's, optimize this many iterations from each and start from the one that ends lower (the
            initialization works on the transferred garment and cannot see where the construction lines hang,
            so its first equilibrium can score worse although the optimization goes far better from it: the
            sheath dress 12 -> 14 at 1.5 cm edges scored 6,415 against the base's 1,042, and 48 iterations
            reached 43 from it, 923 from the base). 0: the base pattern, without a trial.
        edge_length: triangle edge length in metres when a pattern is given.
        voxel_size: body SDF voxel size in metres.
        drape: settings of the base drape; None = ``DrapeSettings(edge_length, voxel_size)``.
        atol_weight: exact-solve force tolerance as a fraction of the garment's weight (as the drape's).
        max_solver_iterations: iteration budget of an exact solve. An exact check after inexact
            iterations starts several times the garment's weight out of balance and takes 70-150 Newton
            iterations (README, "Not yet met"); a check that runs out of budget counts as a failed evaluation
            and makes Algorithm 1 backtrack. 200 (it was 100: the coarse demo's first check needed more after
            Newton's barrier blocks gained the body's curvature, and the demo then returned its initialized
            pattern).
        adjoint: :class:`~torchgarment.sim.diff.AdjointLinearSolver` of the gradients: ``"direct"`` (a SuperLU
            factorization per gradient, exact) or ``"iterative"`` (block-Jacobi CG warm-started from the last
            adjoint, at most ``adjoint_max_iterations``: the large-mesh path, inexact gradients).
        adjoint_rtol, adjoint_max_iterations: stopping rule of the iterative adjoint.
        inexact_adjoint: the Hessian of the adjoint at an inexact iteration's state, which is not an
            equilibrium (:class:`~torchgarment.sim.diff.AdjointHessian`): ``"exact"`` (default: the
            unprojected one, by SuperLU when ``sparse_backend`` is a Cholesky) or ``"projected"`` (the
            PSD-projected Hessian the Newton solver factorizes, by ``sparse_backend``, CHOLMOD's Cholesky
            included: about 5x cheaper at 30K vertices). Out of balance the exact Hessian is indefinite and
            can be nearly singular; measured against the gradient at the equilibrium of the same pattern
            (README, "The adjoint at inexact states") the projected one was the better estimate, but end to
            end it was not better in general (the 3K dress ended higher), so it is not the default. Exact
            checks and the exact method always use the exact Hessian.
        reuse_factorization: each Newton solve (exact or inexact) solves its systems by CG preconditioned with
            its last sparse LU factorization (``SolveSettings.reuse_factorization``); a fresh factorization
            only when CG stalls. Measured on the 2,960-vertex sheath dress (24 iterations, exact every 8, 1
            thread): 62.3 s without, 35.8 s with. Off by default: CG's stopping decisions amplify round-off,
            so two runs of one setup then differ (1e-3 of the objective on the 5 cm skirt, 15 % on the 3K
            dress; without it by ~1e-10) and a resumed run no longer repeats the uninterrupted one.
        pcg_accept_rtol: with ``reuse_factorization``, a CG step that used up its iterations short of its
            tolerance is still taken when its relative residual is at most this, and the next system is
            factorized afresh (``SolveSettings.pcg_accept_rtol``); None: never. On the 30K dress's last
            exact check (README, "Not yet met") 0.3 made 55 factorizations instead of 76 for 117 Newton
            iterations instead of 121.
        exact_curvature_cg: Newton's direction in the base drape's settle and the exact solves by up to this
            many CG iterations on the exact Hessian preconditioned by the projected one's factorization
            (``SolveSettings.exact_curvature_cg``; 0: projected Newton; None, the default:
            :data:`~torchgarment.sim.solvers.DEFAULT_EXACT_CURVATURE_CG` with ``linear_solver="direct"``, 0
            with ``"jacobi-pcg"``). With ``reuse_factorization`` the last factorization preconditions while CG
            converges.
        sparse_backend: the sparse direct solver of the simulation's Newton systems (the base drape's too),
            adjoints and tangents (:class:`~torchgarment.linalg.SparseBackend`: ``"superlu"``, or
            ``"cholmod"`` / ``"pardiso"`` when installed; see the README's linear algebra section).
        linear_solver: how the simulation's Newton (the base drape's settle, the exact and Newton inexact
            solves) solves its systems (:class:`~torchgarment.sim.solvers.LinearSolver`): ``"direct"``
            (``sparse_backend``, default) or ``"jacobi-pcg"`` (block-Jacobi CG on the device, no
            factorization; with ``adjoint="iterative"`` no simulation system is factorized, only the
            optimizer's small pattern-space preconditioner, once). Not with ``reuse_factorization``.
        band: blending band ``B`` of the deformation transfer in metres; None = its default.
        checkpoint_every: also write a checkpoint every this many iterations (0 = only on Ctrl-C).
        support: stick the pattern's support (:attr:`SewingPattern.support`, e.g. a skirt's waistband; the
            paper's sticking energy ``F(x)`` of Eq. 4): the base drape holds it at the base body's waist
            (``DrapeSettings.support``) and the target simulation holds its vertices at their base positions
            carried by the deformation transfer (the positional cost's ``x_transfer``) plus the base's pin
            extension (each pin's target minus where its vertex hung in the base drape, so that the support
            hangs where the transfer carries it rather than one sag lower), with the base drape's pin
            stiffness. The transfer is levelled first (:func:`~torchgarment.adjust.transfer.level_support`):
            the support hangs as high above the target's waist plane as it hung above the base's, and the
            garment down to the hip plane follows (the shift is ``support_level_shift_mm`` in the metrics).
            False: no support in either (the garment hangs by its own tension).
        fit_scale: how the lengths the fit rules keep (the lines' ease and heights, the support's level, the
            distance cost's looseness, the pattern the fixing and support-shape terms hold) scale with the
            body (:class:`~torchgarment.adjust.fit.FitScale`): ``"none"`` (default) keeps them absolute;
            ``"stature"`` multiplies them by the target's height over the base's, so a uniformly scaled body
            gets the uniformly scaled pattern (1 between bodies of one height, as a size chart's).
    """

    optimizer: OptimizerKind = OptimizerKind.PGD
    iterations: int = 256
    inexact: bool = True
    inner_iterations: int = 2
    exact_interval: int = 32
    min_model_ratio: float = 0.25
    adapt_step: bool = False
    step_window: int = 4
    inner_solver: SolverKind = SolverKind.NEWTON
    solver: SolverKind = SolverKind.NEWTON
    step: float | None = None
    max_displacement: float = 0.005
    weights: object | None = None
    initialize: bool = True
    init_iterations: int = 100
    init_trial_iterations: int = 16
    edge_length: float = 0.03
    voxel_size: float = 0.005
    drape: DrapeSettings | None = None
    atol_weight: float = 1e-3
    max_solver_iterations: int = 200
    adjoint: AdjointLinearSolver = AdjointLinearSolver.SPARSE
    adjoint_rtol: float = 1e-3
    adjoint_max_iterations: int = 50
    inexact_adjoint: AdjointHessian = AdjointHessian.EXACT
    reuse_factorization: bool = False
    pcg_accept_rtol: float | None = 0.3
    sparse_backend: SparseBackend = SparseBackend.SUPERLU
    exact_curvature_cg: int | None = None
    linear_solver: LinearSolver = LinearSolver.DIRECT
    band: float | None = None
    checkpoint_every: int = 0
    support: bool = True
    fit_scale: FitScale = FitScale.NONE

    def __post_init__(self) -> None:
        """Validate at construction (and on ``dataclasses.replace``)."""
        self.validate()

    def validate(self) -> None:
        """Normalize option names and raise :class:`InputError` for out-of-range values."""
        self.optimizer = OptimizerKind.resolve(self.optimizer)
        self.inner_solver = SolverKind.resolve(self.inner_solver)
        self.solver = SolverKind.resolve(self.solver)
        self.adjoint = AdjointLinearSolver.resolve(self.adjoint)
        self.inexact_adjoint = AdjointHessian.resolve(self.inexact_adjoint)
        self.sparse_backend = SparseBackend.resolve(self.sparse_backend)
        self.linear_solver = LinearSolver.resolve(self.linear_solver)
        self.fit_scale = FitScale.resolve(self.fit_scale)
        checks = [
            (not (self.reuse_factorization and self.linear_solver == LinearSolver.JACOBI_PCG),
             "reuse_factorization reuses a factorization, which linear_solver='jacobi-pcg' never makes: set "
             "one of them"),
            (self.iterations >= 0, "iterations must be >= 0"),
            (self.inner_iterations >= 1 and self.exact_interval >= 1,
             "inner_iterations/exact_interval must be >= 1"),
            (0.0 <= self.min_model_ratio < 1.0, "min_model_ratio must be in [0, 1)"),
            (self.step_window >= 1, "step_window must be >= 1"),
            ((self.step is None or self.step > 0) and self.max_displacement > 0,
             "step and max_displacement must be > 0"),
            (self.init_iterations >= 0, "init_iterations must be >= 0"),
            (self.init_trial_iterations >= 0, "init_trial_iterations must be >= 0"),
            (self.edge_length > 0 and self.voxel_size > 0, "edge_length and voxel_size must be > 0"),
            (self.atol_weight > 0 and self.max_solver_iterations >= 1,
             "atol_weight and max_solver_iterations"),
            (self.checkpoint_every >= 0, "checkpoint_every must be >= 0"),
            (0.0 < self.adjoint_rtol < 1.0 and self.adjoint_max_iterations >= 1,
             "adjoint_rtol must be in (0, 1) and adjoint_max_iterations >= 1"),
            (self.pcg_accept_rtol is None or SolveSettings.pcg_rtol <= self.pcg_accept_rtol < 1.0,
             f"pcg_accept_rtol must be None or lie in [{SolveSettings.pcg_rtol}, 1)"),
            (self.exact_curvature_cg is None or (
                isinstance(self.exact_curvature_cg, int) and self.exact_curvature_cg >= 0
                and (self.exact_curvature_cg == 0 or self.linear_solver == LinearSolver.DIRECT)),
             "exact_curvature_cg must be >= 0, and 0 with linear_solver='jacobi-pcg' (it preconditions by a "
             "factorization)"),
        ]
        for ok, msg in checks:
            if not ok:
                raise InputError(f"invalid AdjustSettings: {msg}")


@dataclass
class AdjustResult:
    """Outcome of :func:`adjust`.

    Attributes:
        pattern: the adjusted :class:`SewingPattern` (None when a mesh was given).
        base_pattern: the input pattern (None when a mesh was given).
        mesh_base: the base garment draped on the base body (``p`` the base pattern).
        mesh_target: the adjusted garment on the target body (``p`` the adjusted pattern, ``x`` its
            equilibrium).
        x_transfer: (V, 3) the transferred garment (the target of the positional cost).
        x_base_on_target: (V, 3) the equilibrium of the base pattern on the target body (the "before").
        q_base, q: (B, 2) base and adjusted boundary vertices in metres.
        boundary_index: (B,) the pattern vertex of each boundary row.
        metrics: JSON-serializable numbers (see :func:`adjust`).
        records: one :class:`IterationRecord` per outer iteration.
        term_history: per iteration, each term's value (at the iteration's evaluation).
    """

    pattern: object | None
    base_pattern: object | None
    mesh_base: GarmentMesh
    mesh_target: GarmentMesh
    x_transfer: torch.Tensor
    x_base_on_target: torch.Tensor
    q_base: torch.Tensor
    q: torch.Tensor
    boundary_index: torch.Tensor
    metrics: dict
    records: list[IterationRecord] = field(default_factory=list)
    term_history: list[dict[str, float]] = field(default_factory=list)


# --------------------------------------------------------------------------------------------- pattern output
def _cubic_fit(pts: np.ndarray) -> np.ndarray:
    """Inner control points (2, 2) of the cubic Bezier through the end points closest to ``pts`` (m, 2)."""
    a, b = pts[0], pts[-1]
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    t = np.concatenate([[0.0], np.cumsum(seg)]) / max(seg.sum(), 1e-300)
    b1, b2 = 3 * (1 - t) ** 2 * t, 3 * (1 - t) * t**2
    rhs = pts - np.outer((1 - t) ** 3, a) - np.outer(t**3, b)
    A = np.stack([b1, b2], axis=1)
    ctrl, *_ = np.linalg.lstsq(A, rhs, rcond=None)
    return ctrl


def pattern_from_mesh(pattern: SewingPattern, mesh: GarmentMesh, p: torch.Tensor,
                      edge_length: float | None = None, line_tolerance: float = 2e-4
                      ) -> tuple[SewingPattern, float]:
    """The sewing pattern whose outline passes through the boundary vertices of ``p``.

    The vertices of each edge are read from ``mesh.layout`` (the
    :class:`~torchgarment.structures.MeshLayout` that :func:`~torchgarment.pattern.meshing.mesh_pattern`
    records). Each edge keeps its index, end vertices and stitches; its shape becomes a line when the
    adjusted samples lie within ``line_tolerance`` metres of the chord and the base edge was a line, else a
    cubic Bezier fitted by least squares (chord-length parameters). Panel placement is kept.

    Args:
        pattern: the base :class:`SewingPattern`.
        mesh: its mesh, made by ``mesh_pattern(pattern, ...)`` (or a copy keeping its layout).
        p: (V, 2) adjusted rest positions in metres.
        edge_length: the meshing edge length in metres; if given, the layout's edge runs are checked against
            :func:`~torchgarment.pattern.meshing.edge_segment_counts` at that length.
        line_tolerance: in metres.

    Returns:
        ``(pattern, max_fit_error_m)``.

    Raises:
        PatternError: the mesh has no layout or is not a mesh of ``pattern``.
    """
    from torchgarment.pattern.meshing import edge_segment_counts
    from torchgarment.pattern.spec import Edge, EdgeKind, Panel, SewingPattern

    layout = mesh.layout
    if layout is None:
        raise PatternError("pattern_from_mesh needs a mesh made by mesh_pattern (it has no layout)")
    counts = None if edge_length is None else edge_segment_counts(pattern, edge_length)
    P = p.detach().cpu().double().numpy()
    panels, worst = {}, 0.0
    for name, panel in pattern.panels.items():
        if name not in layout.panel_names:
            raise PatternError(f"panel {name!r} is not in the mesh")
        runs = [r.cpu().numpy() for r in layout.runs(name)]
        if len(runs) != len(panel.edges) or (counts is not None and
                                             [len(r) - 1 for r in runs] != [int(c) for c in counts[name]]):
            raise PatternError(f"panel {name!r}: the mesh's edge layout does not match the pattern")
        verts = P[[int(r[0]) for r in runs]]
        edges = []
        for i, e in enumerate(panel.edges):
            pts = P[runs[i]]
            a, b = pts[0], pts[-1]
            d = b - a
            chord = float(np.linalg.norm(d))
            off_chord = np.abs((pts - a) @ np.array([-d[1], d[0]])) / max(chord, 1e-300)
            if e.kind is EdgeKind.LINE and float(off_chord.max()) <= line_tolerance:
                edges.append(Edge(i, (i + 1) % len(panel.edges), EdgeKind.LINE, label=e.label))
                worst = max(worst, float(off_chord.max()))
                continue
            ctrl = _cubic_fit(pts)
            perp = np.array([-d[1], d[0]])
            M = np.stack([d, perp], axis=1)
            rel = np.linalg.solve(M, (ctrl - a).T).T
            new = Edge(i, (i + 1) % len(panel.edges), EdgeKind.CUBIC, controls=rel, label=e.label)
            curve = new.evaluate(a, b, np.linspace(0, 1, 200))
            err = float(np.min(np.linalg.norm(pts[:, None, :] - curve[None], axis=2), axis=1).max())
            worst = max(worst, err)
            edges.append(new)
        panels[name] = Panel(name, verts, edges, translation=panel.translation.copy(),
                             rotation=panel.rotation.copy(), label=panel.label, notches=list(panel.notches),
                             grainline=panel.grainline.copy())
    out = SewingPattern(pattern.name, panels, list(pattern.stitches), dict(pattern.metadata),
                        support=pattern.support)
    return out, worst


# ---------------------------------------------------------------------------------------------- helpers
def _target_sdf(body: Body, voxel: float, dtype: torch.dtype, device: torch.device | str | None) -> BodySDF:
    from torchgarment.sdf import BodySDF, SDFSampling, SDFSettings

    if isinstance(body, BodySDF):
        return body
    sdf = BodySDF.cached(body.vertices, body.faces, SDFSettings(voxel_size=voxel), device=device, dtype=dtype)
    return sdf.with_sampling(SDFSampling.QUADRATIC)


def _initialize(objective: AdjustObjective, param: BoundaryParametrization, q_base: torch.Tensor,
                iterations: int) -> torch.Tensor:
    """Section 7: minimize ``objective.initialization_objective(param(q))`` over q by L-BFGS (no
    simulation)."""
    q = q_base.detach().clone().requires_grad_(True)
    if iterations == 0:
        return q.detach()
    opt = torch.optim.LBFGS([q], lr=1.0, max_iter=iterations, history_size=20, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-12, tolerance_change=1e-15)

    def closure() -> torch.Tensor:
        opt.zero_grad()
        f = objective.initialization_objective(param(q))
        f.backward()
        return f

    opt.step(closure)
    return q.detach()


def _plane_height(body: Body, name: str) -> float:
    """Height (m) of one of the body's landmark planes (:meth:`Body.measurements`, cached on the body)."""
    return float(body.measurements().planes[name].point[1])


def _pins(model: torch.nn.Module) -> Pins | None:
    """The model's sticking term (the support), or None."""
    return next((t for t in getattr(model, "terms", ()) if isinstance(t, Pins)), None)


def _support_metrics(model: torch.nn.Module, x: torch.Tensor) -> dict:
    """``support_force_n``, ``support_max_displacement_mm``, ... of the target model's support pins at ``x``
    (see :func:`~torchgarment.sim.support.support_metrics`); empty without a support."""
    pins = _pins(model)
    return {} if pins is None else support_metrics(x, pins.indices, pins.targets, pins.stiffness)


def _terms(objective: AdjustObjective, x: torch.Tensor, p: torch.Tensor) -> dict[str, float]:
    with torch.no_grad():
        return {k: float(v) for k, v in objective.term_values(x, p).items()}


def _save_checkpoint(directory: Path, state: dict) -> Path:
    from torchgarment.io.atomic import atomic_path

    directory.mkdir(parents=True, exist_ok=True)
    path = directory / CHECKPOINT_NAME
    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    return path


def _fingerprint(setup: AdjustSetup, settings: AdjustSettings) -> dict:
    """What a checkpoint must share with the run that resumes it: the objective's coefficients, the optimizer,
    the garment's size, the base boundary ``q_base`` and the transferred garment ``x_transfer`` (the bodies,
    pattern and resolution show in those two)."""
    w = getattr(setup.objective, "weights", None)
    return {"weights": None if w is None else w.to_dict(), "optimizer": settings.optimizer.value,
            "inexact": bool(settings.inexact), "vertices": int(setup.x_transfer.shape[0]),
            "q_base": setup.q_base.detach().cpu().double().clone(),
            "x_transfer": setup.x_transfer.detach().cpu().double().clone()}


def _check_fingerprint(saved: dict | None, now: dict, path: Path) -> None:
    """Raise :class:`InputError` unless a checkpoint's fingerprint matches this run's (1 µm on positions)."""
    if saved is None:
        raise InputError(f"the checkpoint {path} does not say which run wrote it (an older version): run "
                         "without --resume")
    for key in ("weights", "optimizer", "inexact", "vertices"):
        if saved.get(key) != now[key]:
            raise InputError(f"the checkpoint {path} is of another run ({key} differs: {saved.get(key)!r} "
                             f"there, {now[key]!r} here): resume with the same inputs and settings, or run "
                             "without --resume")
    for key, what in (("q_base", "base pattern"), ("x_transfer", "bodies or base drape")):
        a, b = saved.get(key), now[key]
        if a is None or tuple(a.shape) != tuple(b.shape) or float((a - b).abs().max()) > 1e-6:
            raise InputError(f"the checkpoint {path} is of another run (its {what} differ): resume with the "
                             "same inputs and settings, or run without --resume")


def exact_checks(records: list[IterationRecord], final: dict | None = None) -> list[dict]:
    """One entry per outer iteration evaluated exactly (Algorithm 1's checks and restarts; every iteration of
    the exact optimizers): its iteration, objective, whether it was accepted, its simulator iterations and
    seconds, and how far the garment moved in its solves (``displacement_max_mm``, ``displacement_mean_mm``:
    at a check, the distance of the inexact iterations' state from the equilibrium); and last, with
    ``"final": True``, the exact evaluation of the last iterate when the run ended on an inexact one
    (:attr:`~torchgarment.adjust.inexact.RunResult.final_check`)."""
    out, before = [], 0.0
    for r in records:
        if r.exact:
            out.append({"iteration": r.iteration, "objective": r.objective, "accepted": r.accepted,
                        "sim_iterations": r.sim_iterations, "seconds": r.seconds - before,
                        "displacement_max_mm": r.displacement_max_mm,
                        "displacement_mean_mm": r.displacement_mean_mm})
        before = r.seconds
    if final is not None:
        out.append({**final, "accepted": True, "final": True})
    return out


def _log_iteration(logger: RunLogger, rec: IterationRecord, terms: dict[str, float]) -> None:
    """TensorBoard scalars of one outer iteration and the progress bar's step."""
    k = rec.iteration
    logger.scalars({"objective": rec.objective,
                    "objective_exact" if rec.exact else "objective_inexact": rec.objective}, k)
    logger.scalars(terms, k, prefix="terms/")
    logger.scalars({"step_length": rec.step, "step_norm_m": rec.step_norm, "S": rec.inner_iterations,
                    "wall_time_s": rec.seconds, "closure_calls": rec.closure_calls,
                    "sim_iterations": rec.sim_iterations, "displacement_max_mm": rec.displacement_max_mm,
                    "displacement_mean_mm": rec.displacement_mean_mm}, k)
    if rec.model_ratio is not None:
        logger.scalars({"model_ratio": rec.model_ratio}, k)
    logger.advance({"f": f"{rec.objective:.4g}", "S": rec.inner_iterations})


# ---------------------------------------------------------------------------------------------- adjust
@dataclass
class AdjustSetup:
    """Everything before the optimization (steps 1-3 of the module docstring), reusable by several optimizers.

    Attributes:
        settings: the settings used.
        pattern: the input :class:`SewingPattern` (None for a mesh).
        mesh_base: the base garment draped on the base body.
        base_drape_metrics: the drape's metrics.
        x_transfer: (V, 3) transferred garment.
        param: the :class:`BoundaryParametrization`.
        objective: the :class:`AdjustObjective`.
        model: the simulation model on the target body.
        exact_settings: settings of exact solves.
        q_base: (B, 2) base boundary. x_base_on_target: (V, 3) base pattern's equilibrium on the target body.
        objective_base, terms_base: objective and terms of the base pattern on the target body.
        q_init: (B, 2) initialized boundary; objective_initial, terms_initial its objective and terms;
        x_init: (V, 3) its equilibrium. initialization_used: whether it beat the base pattern.
        timings: seconds of each stage.
        support_level_shift_m: how far (m, up positive) :func:`~torchgarment.adjust.transfer.level_support`
            moved the transferred support to the target's waist plane; None without a support.
        lines: the construction lines' targets of the objective's ease and placement terms
            (:func:`~torchgarment.adjust.fit.line_targets`); None without them.
        fit_scale: the factor on the lengths the fit rules keep (:func:`~torchgarment.adjust.fit.fit_scale`).
    """

    settings: AdjustSettings
    pattern: object | None
    mesh_base: GarmentMesh
    base_drape_metrics: dict
    x_transfer: torch.Tensor
    param: torch.nn.Module
    objective: torch.nn.Module
    model: torch.nn.Module
    exact_settings: SolveSettings
    q_base: torch.Tensor
    x_base_on_target: torch.Tensor
    objective_base: float
    terms_base: dict
    q_init: torch.Tensor
    x_init: torch.Tensor
    objective_initial: float
    terms_initial: dict
    initialization_used: bool
    timings: dict = field(default_factory=dict)
    support_level_shift_m: float | None = None
    lines: object | None = None
    fit_scale: float = 1.0

    def new_problem(self, x_start: torch.Tensor | None = None, settings: AdjustSettings | None = None
                    ) -> AdjustProblem:
        """A fresh :class:`AdjustProblem` warm-started at ``x_start`` (default: the initialized equilibrium),
        with the solvers, adjoint and factorization reuse of ``settings`` (default: ``self.settings``)."""
        s = self.settings if settings is None else settings
        self.model.reset_caches()  # a second optimize() of one setup repeats the first bit for bit
        return AdjustProblem(self.model, self.param, self.objective,
                             self.x_init if x_start is None else x_start,
                             exact_settings=replace(self.exact_settings,
                                                    reuse_factorization=s.reuse_factorization,
                                                    pcg_accept_rtol=s.pcg_accept_rtol,
                                                    sparse_backend=s.sparse_backend,
                                                    linear_solver=s.linear_solver,
                                                    exact_curvature_cg=exact_curvature_iterations(
                                                        s.exact_curvature_cg, s.linear_solver)),
                             solver=s.solver, inexact_solver=s.inner_solver, adjoint=s.adjoint,
                             adjoint_rtol=s.adjoint_rtol, adjoint_max_iterations=s.adjoint_max_iterations,
                             inexact_adjoint=s.inexact_adjoint,
                             retain_graph=s.optimizer == OptimizerKind.GN)


def base_drape_settings(settings: AdjustSettings) -> DrapeSettings:
    """The settings of the base drape :func:`prepare` computes (and that a ``base=`` drape must use):
    ``settings.drape`` or ``DrapeSettings(edge_length, voxel_size)``, with the support held only when
    ``settings.support``."""
    dset = (settings.drape if settings.drape is not None
            else DrapeSettings(edge_length=settings.edge_length, voxel_size=settings.voxel_size,
                               linear_solver=settings.linear_solver, sparse_backend=settings.sparse_backend,
                               exact_curvature_cg=settings.exact_curvature_cg))
    return replace(dset, support=dset.support and settings.support)


def prepare(
    pattern_or_mesh: SewingPattern | GarmentMesh,
    base_body: Body,
    target_body: Body,
    settings: AdjustSettings | None = None,
    *,
    base: DrapeResult | None = None,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> AdjustSetup:
    """Steps 1-3: base drape, transfer, parametrization/objective/simulation, base objective, initialization.

    Args:
        base: an already computed base drape of the same pattern on ``base_body`` with this ``settings``'
            drape settings (``drape(pattern, base_body, settings=...)``; a grade drapes once for all sizes);
            None = drape here. Its support pins (if any) are reused: with ``settings.support`` the target
            simulation sticks ``base.support_indices`` to their transferred positions.
        others: see :func:`adjust`.

    Raises:
        InputError: see :func:`adjust`; ``base`` of another mesh.
    """
    from torchgarment.adjust.fit import construction_lines, fit_scale, line_targets
    from torchgarment.adjust.objective import AdjustObjective, CostWeights
    from torchgarment.adjust.parametrization import BoundaryParametrization
    from torchgarment.adjust.transfer import level_support, transfer_deformation
    from torchgarment.pattern.spec import SewingPattern

    settings = replace(settings) if settings is not None else AdjustSettings()
    settings.validate()
    if not isinstance(pattern_or_mesh, (SewingPattern, GarmentMesh)):
        raise InputError("adjust takes a SewingPattern or a GarmentMesh, got "
                         f"{type(pattern_or_mesh).__name__}")
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    dset = base_drape_settings(settings)
    settings.drape = dset
    if base is None:
        base = drape(pattern_or_mesh, base_body, settings=dset, dtype=dtype, device=device)
    elif not isinstance(base, DrapeResult):
        raise InputError(f"prepare(base=...) takes a DrapeResult, got {type(base).__name__}")
    elif isinstance(pattern_or_mesh, SewingPattern) and (
            base.mesh.layout is None or tuple(base.mesh.layout.panel_names) != tuple(pattern_or_mesh.panels)):
        raise InputError("prepare(base=...) is a drape of another pattern: its mesh's panels are not the "
                         "pattern's")
    mesh_base = base.mesh
    timings["drape_seconds"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    kw = {} if settings.band is None else {"band": settings.band}
    x_transfer = transfer_deformation(base.x, base_body, target_body,
                                      **kw).to(dtype=dtype, device=mesh_base.device)
    support_shift = None
    # the kept lengths' factor: the stature ratio (1 between a size chart's bodies) or 1
    scale = fit_scale(base_body, target_body, settings.fit_scale)
    if settings.support and base.support_indices is not None:
        # the support hangs as high above the target's waist plane as it hung above the base's (in
        # proportion): its equilibrium heights, not its pins' targets (the pins hold it a sag above those)
        above = scale * (float(base.x[base.support_indices, 1].mean()) - _plane_height(base_body, "waist"))
        x_transfer, support_shift = level_support(x_transfer, base.x.to(x_transfer), base.support_indices,
                                                  _plane_height(target_body, "waist") + above,
                                                  _plane_height(base_body, "hips"))
    timings["transfer_seconds"] = time.perf_counter() - t1

    t1 = time.perf_counter()
    param = BoundaryParametrization(mesh_base, dtype=dtype, device=mesh_base.device)
    from torchgarment.sdf import SDFSampling

    # one grid per body at the settings' voxel size for both the objective (trilinear) and the simulation
    # (quadratic sampling): the objective's own default grid (2.5 mm) cost 5-10 s per new body to build
    sdf = _target_sdf(target_body, dset.voxel_size, dtype, mesh_base.device)
    base_grid = _target_sdf(base_body, dset.voxel_size, dtype, mesh_base.device)
    weights = settings.weights if settings.weights is not None else CostWeights()
    lines = None
    if ((weights.ease > 0 or weights.placement > 0) and isinstance(pattern_or_mesh, SewingPattern)
            and construction_lines(pattern_or_mesh)):
        # the line terms' targets: the base ease and placement at each construction line (placed by the
        # landmark planes when the placement term is on, else where the transfer carries the line)
        lines = line_targets(pattern_or_mesh, mesh_base, base.x, x_transfer, base_body, target_body,
                             at_landmarks=weights.placement > 0, scale=scale)
    objective = AdjustObjective(mesh_base, base_body, target_body, param, weights,
                                x_transfer=x_transfer,
                                base_sdf=base_grid.with_sampling(SDFSampling.TRILINEAR),
                                target_sdf=sdf.with_sampling(SDFSampling.TRILINEAR), lines=lines,
                                support=base.support_indices if settings.support else None,
                                fit_scale=scale)
    mat = replace(dset.material)
    if mesh_base.seam_pairs.shape[0] and dset.final_sew_stiffness is not None:
        mat.sew_stiffness = float(dset.final_sew_stiffness)
    if dset.barrier_mu is not None:
        mat.barrier_mu = float(dset.barrier_mu)
    effects = {Effect.STRETCH, Effect.BEND, Effect.GRAVITY, Effect.BODY_BARRIER}
    if mesh_base.seam_pairs.shape[0]:
        effects.add(Effect.SEW)
    pin_idx = pin_tgt = None
    if settings.support and base.support_indices is not None:
        # sticking targets: the base drape's support positions carried by the deformation transfer (Eq. 15),
        # levelled with the target's waist plane (level_support), plus the base's pin extension (each
        # target minus where its vertex hung): the support then hangs where the transfer carries it, not a
        # second sag below
        pin_idx = base.support_indices.to(mesh_base.device)
        extension = (base.support_targets.to(x_transfer) - base.x[base.support_indices].to(x_transfer))
        pin_tgt = (x_transfer[pin_idx] + extension).detach().clone()
        mat.pin_stiffness = float(base.support_stiffness)
        effects.add(Effect.PINS)
    model = Scene(mesh_base.with_positions(x_transfer), body_sdf=sdf, effects=effects, material=mat,
                  pin_indices=pin_idx, pin_targets=pin_tgt).build()
    weight = float(mesh_base.rest_face_areas.abs().sum()) * mat.density * mat.gravity
    exact = SolveSettings(rtol=0.0, atol=settings.atol_weight * weight,
                          max_iterations=settings.max_solver_iterations,
                          reuse_factorization=settings.reuse_factorization,
                          pcg_accept_rtol=settings.pcg_accept_rtol,
                          sparse_backend=settings.sparse_backend, linear_solver=settings.linear_solver,
                          exact_curvature_cg=exact_curvature_iterations(settings.exact_curvature_cg,
                                                                        settings.linear_solver))
    problem = AdjustProblem(model, param, objective, x_transfer, exact_settings=exact, solver=settings.solver,
                            inexact_solver=settings.inner_solver)
    q_base = param.initial().detach()
    timings["setup_seconds"] = time.perf_counter() - t1

    t1 = time.perf_counter()
    # the first solves start from the transferred garment, far from equilibrium: the drape's settle budget
    settle = max(exact.max_iterations, dset.max_iterations)
    ev = problem.evaluate(q_base, exact=True, need_grad=False, max_iterations=settle)
    f_base, terms_base = ev.objective, problem.term_values()
    x_before = problem.x.clone()
    q_init, x_init, f_init, terms_init, init_used = q_base, x_before, f_base, terms_base, False
    trial = None
    if settings.initialize:
        q_try = _initialize(objective, param, q_base, settings.init_iterations)
        problem.reset_state(x_transfer)
        ev = problem.evaluate(q_try, exact=True, need_grad=False, max_iterations=settle)
        if ev.objective < f_base:
            q_init, x_init, f_init, terms_init, init_used = q_try, problem.x.clone(), ev.objective, \
                problem.term_values(), True
        elif settings.init_trial_iterations > 0:
            trial = (q_try, problem.x.clone(), ev.objective, problem.term_values())
    timings["initialization_seconds"] = time.perf_counter() - t1
    pattern = pattern_or_mesh if isinstance(pattern_or_mesh, SewingPattern) else None
    setup = AdjustSetup(settings, pattern, mesh_base, dict(base.metrics), x_transfer, param, objective, model,
                        exact, q_base, x_before, f_base, terms_base, q_init, x_init, f_init, terms_init,
                        init_used, timings, support_level_shift_m=support_shift, lines=lines,
                        fit_scale=scale)
    if trial is not None:
        t1 = time.perf_counter()
        setup = _initialization_trial(setup, *trial)
        timings["initialization_trial_seconds"] = time.perf_counter() - t1
    return setup


def _initialization_trial(setup: AdjustSetup, q_try: torch.Tensor, x_try: torch.Tensor, f_try: float,
                          terms_try: dict) -> AdjustSetup:
    """The setup to optimize from: ``setup`` (the base pattern) or, when ``init_trial_iterations`` of the
    optimizer from the rejected initialization end lower than as many from the base pattern, the setup
    starting at the initialization (see :class:`AdjustSettings`)."""
    trial = replace(setup.settings, iterations=setup.settings.init_trial_iterations, checkpoint_every=0)
    candidate = replace(setup, q_init=q_try, x_init=x_try, objective_initial=f_try, terms_initial=terms_try,
                        initialization_used=True)
    from_base = optimize(setup, trial, progress=False).metrics["objective_final"]
    from_init = optimize(candidate, trial, progress=False).metrics["objective_final"]
    setup.timings["initialization_trial"] = {"iterations": trial.iterations, "objective_from_base": from_base,
                                             "objective_from_initialization": from_init}
    return candidate if from_init < from_base else setup


def optimize(
    setup: AdjustSetup,
    settings: AdjustSettings | None = None,
    *,
    log_dir: str | Path | None = None,
    checkpoint_dir: str | Path | None = None,
    progress: bool = True,
    resume: bool = False,
    callback: Callable[[IterationRecord, dict], None] | None = None,
) -> AdjustResult:
    """Step 4 on a prepared setup, with a fresh simulation state (see :func:`adjust`).

    Args:
        setup: from :func:`prepare`.
        settings: optimizer settings (optimizer, iterations, inexact, S, M, step, max_displacement,
            checkpoint_every); default ``setup.settings``.
        log_dir, checkpoint_dir, progress, resume: see :func:`adjust`.
        callback: ``callback(record, terms)`` after every outer iteration.
    """
    settings = replace(settings) if settings is not None else replace(setup.settings)
    settings.validate()
    ckpt_path = None if checkpoint_dir is None else Path(checkpoint_dir) / CHECKPOINT_NAME
    if resume and (ckpt_path is None or not ckpt_path.is_file()):
        raise InputError(f"resume=True but there is no checkpoint {ckpt_path}")
    problem = setup.new_problem(settings=settings)
    q = setup.q_init.detach().clone().requires_grad_(True)
    kind = settings.optimizer
    use_inexact = settings.inexact and kind == OptimizerKind.PGD
    opt = make_optimizer(kind, [q], preconditioner=setup.objective.regularizer_hessian(), problem=problem,
                         lr=settings.step if settings.step is not None else (
                             math.inf if kind == OptimizerKind.PGD else 1.0),
                         line_search=not use_inexact, max_displacement=settings.max_displacement,
                         edges=setup.mesh_base.edges,
                         boundary_index=setup.param.boundary_index, x_target=setup.x_transfer)
    runner = InexactRunner(problem, opt, q, InexactSettings(
        inner_iterations=settings.inner_iterations, exact_interval=settings.exact_interval,
        min_model_ratio=settings.min_model_ratio,
        adapt_step=settings.adapt_step, step_window=settings.step_window, exact=not use_inexact))
    term_history: list[dict[str, float]] = []
    fingerprint = _fingerprint(setup, settings)
    if resume:
        state = torch.load(ckpt_path, weights_only=False)
        _check_fingerprint(state.get("fingerprint"), fingerprint, ckpt_path)
        runner.load_state_dict(state["runner"])
        term_history = list(state["term_history"])

    def checkpoint_state() -> dict:
        return {"runner": runner.state_dict(), "term_history": term_history, "optimizer": kind.value,
                "objective_initial": setup.objective_initial, "fingerprint": fingerprint}

    logger = RunLogger(log_dir, progress, "adjust", total=settings.iterations, initial=runner.iteration)

    def on_iteration(rec: IterationRecord) -> None:
        terms = problem.term_values()
        term_history.append(terms)
        _log_iteration(logger, rec, terms)
        if callback is not None:
            callback(rec, terms)
        if (ckpt_path is not None and settings.checkpoint_every
                and rec.iteration % settings.checkpoint_every == 0):
            _save_checkpoint(ckpt_path.parent, checkpoint_state())

    try:
        run = runner.run(settings.iterations, on_iteration)
    except KeyboardInterrupt:
        if ckpt_path is not None:
            _save_checkpoint(ckpt_path.parent, checkpoint_state())
        raise
    finally:
        logger.close()
    opt_seconds = runner.state_dict()["seconds"]

    param, objective, mesh_base = setup.param, setup.objective, setup.mesh_base
    with torch.no_grad():
        p_new = param(run.q).detach()
    terms_final = _terms(objective, run.x, p_new)
    mesh_target = GarmentMesh(run.x, mesh_base.faces, p=p_new, panel_ids=mesh_base.panel_ids,
                              panel_names=mesh_base.panel_names, seam_pairs=mesh_base.seam_pairs,
                              layout=mesh_base.layout)
    pattern_out, fit_error = None, None
    if setup.pattern is not None:
        pattern_out, fit_error = pattern_from_mesh(setup.pattern, mesh_base, p_new)
    disp = torch.linalg.vector_norm(run.q - setup.q_base, dim=1)
    n_it = max(run.iterations, 1)
    f_base, f_init = setup.objective_base, setup.objective_initial
    bd = setup.base_drape_metrics
    metrics = {
        "optimizer": kind.value,
        "inexact": use_inexact,
        "vertices": mesh_base.num_vertices,
        "boundary_vertices": int(setup.q_base.shape[0]),
        "objective_base": f_base,
        "objective_initial": f_init,
        "objective_final": run.objective,
        "initialization_used": setup.initialization_used,
        "initialization_ratio": f_init / f_base if f_base > 0 else math.nan,
        "reduction_percent": 100.0 * (1.0 - run.objective / f_init) if f_init > 0 else 0.0,
        "reduction_vs_base_percent": 100.0 * (1.0 - run.objective / f_base) if f_base > 0 else 0.0,
        "terms": {"base": setup.terms_base, "initial": setup.terms_initial, "final": terms_final},
        "max_boundary_displacement_mm": 1e3 * float(disp.max()) if disp.numel() else 0.0,
        "mean_boundary_displacement_mm": 1e3 * float(disp.mean()) if disp.numel() else 0.0,
        "iterations": run.iterations,
        "seconds": opt_seconds,
        "seconds_per_iteration": opt_seconds / n_it,
        "closure_calls": int(getattr(opt, "closure_calls", 0)),
        "failed_closure_calls": int(getattr(opt, "failed_calls", 0)),
        "sim_iterations": problem.sim_iterations,
        "factorizations": problem.factorizations,
        "adjoint": problem.adjoint.value,
        "inexact_adjoint": settings.inexact_adjoint.value,
        "adjoint_iterations": problem.adjoint_iterations,
        "adjoint_fallbacks": problem.adjoint_fallbacks,
        "exact_evaluations": problem.exact_evaluations,
        "stage_seconds": dict(problem.stage_seconds),
        "stage_linalg": {k: v.as_dict() for k, v in problem.stage_linalg.items()},
        "backtracks": run.backtracks,
        "poor_model_checks": sum(1 for r in run.records if r.model_ratio is not None
                                 and r.model_ratio < runner.settings.min_model_ratio),
        "exact_checks": exact_checks(run.records, run.final_check),
        "stopped": run.stopped,
        "base_drape_ok": bool(bd.get("ok", False)),
        "base_drape": {k: bd.get(k) for k in ("residual", "min_sdf_mm", "max_seam_gap_mm", "converged",
                                              "support_force_n", "support_max_displacement_mm",
                                              "support_target")},
        "support": bd.get("support") if _pins(setup.model) is not None else None,
        **_support_metrics(setup.model, run.x),
        "support_level_shift_mm": (None if setup.support_level_shift_m is None
                                   else 1e3 * setup.support_level_shift_m),
        "fit_scale": setup.fit_scale,
        "line_targets": None if setup.lines is None else setup.lines.to_dict(),
        "pattern_fit_error_mm": None if fit_error is None else 1e3 * fit_error,
        **setup.timings,
    }
    return AdjustResult(pattern=pattern_out, base_pattern=setup.pattern, mesh_base=mesh_base,
                        mesh_target=mesh_target, x_transfer=setup.x_transfer,
                        x_base_on_target=setup.x_base_on_target, q_base=setup.q_base, q=run.q,
                        boundary_index=param.boundary_index, metrics=metrics, records=run.records,
                        term_history=term_history)


def adjust(
    pattern_or_mesh: SewingPattern | GarmentMesh,
    base_body: Body,
    target_body: Body,
    settings: AdjustSettings | None = None,
    *,
    log_dir: str | Path | None = None,
    checkpoint_dir: str | Path | None = None,
    progress: bool = True,
    resume: bool = False,
    base: DrapeResult | None = None,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> AdjustResult:
    """Adjust a sewing pattern made for ``base_body`` to ``target_body`` (see the module docstring).

    Args:
        pattern_or_mesh: a :class:`SewingPattern` (meshed at ``settings.edge_length``) or a meshed
            :class:`GarmentMesh` with ``p``, panels and seams (then no pattern is returned).
        base_body: the body the pattern fits (a :class:`~torchgarment.body.Body`).
        target_body: the body to fit, same topology as ``base_body`` (the transfer maps triangle to triangle).
        settings: :class:`AdjustSettings`.
        log_dir: TensorBoard folder (scalars per iteration); None = no logs.
        checkpoint_dir: where Ctrl-C (and ``checkpoint_every``) writes ``adjust.pt``; None = no checkpoints.
        progress: tqdm bar on stderr.
        resume: continue the optimization from ``checkpoint_dir/adjust.pt`` (same input and settings expected;
            steps 1-3 are recomputed, they are deterministic).
        base: a base drape to reuse (see :func:`prepare`).
        dtype, device: of the computation.

    Returns:
        The :class:`AdjustResult`; ``metrics`` holds ``objective_base``, ``objective_initial``,
        ``objective_final``, ``reduction_percent``, ``reduction_vs_base_percent``, ``terms`` (base, initial,
        final), ``max_boundary_displacement_mm``, ``iterations``, ``seconds`` (optimization),
        ``seconds_per_iteration``, ``closure_calls``, ``sim_iterations``, ``backtracks``,
        ``exact_evaluations``, the timings of each stage (``total_seconds`` included) and, with a support,
        ``support`` (``PANEL:EDGE,...``), ``support_force_n`` (``|sum k (t - x)|``, the net force of the
        target's pins, N), ``support_force_sum_n`` (sum of the pins' force magnitudes, N) and
        ``support_max_displacement_mm`` (largest ``|x - t|``) at the result (the base drape's under
        ``base_drape``).

    Raises:
        InputError: bad settings or input; ``resume`` without a checkpoint.
    """
    t0 = time.perf_counter()
    if resume and (checkpoint_dir is None or not (Path(checkpoint_dir) / CHECKPOINT_NAME).is_file()):
        raise InputError(f"resume=True but there is no checkpoint in {checkpoint_dir}")
    setup = prepare(pattern_or_mesh, base_body, target_body, settings, base=base, dtype=dtype, device=device)
    result = optimize(setup, log_dir=log_dir, checkpoint_dir=checkpoint_dir, progress=progress, resume=resume)
    result.metrics["total_seconds"] = time.perf_counter() - t0
    return result
