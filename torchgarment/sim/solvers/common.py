"""Settings, results and helpers shared by the quasistatic solvers.

A quasistatic solve finds garment positions ``x: (V, 3)`` (metres) where the total force ``-dE/dx`` of a
:class:`~torchgarment.sim.scene.SimModel` vanishes. Every solver reports the force norm ``|g|`` (newtons, the
Euclidean norm over all ``3V`` entries) per iteration and stops when ``|g| <= max(rtol * |g0|, atol)``.

The solvers only use the model through this interface (duck-typed, see :class:`SolverModel`):
``value_and_grad``, ``hessian_diagonal``, ``hessian_blocks``, ``max_step`` and ``project_feasible``.
"""

from __future__ import annotations

import inspect
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Callable, Protocol

import torch

from torchgarment.errors import InputError, TorchGarmentError
from torchgarment.linalg import SparseBackend
from torchgarment.options import OptionEnum
from torchgarment.sim.energies.base import HessianBlocks

__all__ = [
    "Callback", "LinearSolver", "NonFiniteError", "Preconditioner", "Safeguard", "SolveInfo",
    "SolveSettings", "SolverKind", "SolverModel", "Timer", "check_x0", "checked_max_step", "evaluate",
    "evaluate_with_diagonal", "supports_elastic_reuse", "tolerance",
]

#: ``callback(iteration, x, residual, energy) -> stop``; return True to stop the solve early.
Callback = Callable[[int, torch.Tensor, float, float], "bool | None"]


class NonFiniteError(TorchGarmentError, FloatingPointError):
    """The model returned a NaN or infinite energy, gradient or Hessian during a solve."""


class SolverKind(OptionEnum):
    """Available quasistatic solvers."""

    GD_CHEBYSHEV = "gd-chebyshev"
    NEWTON = "newton"


class Preconditioner(OptionEnum):
    """Jacobi preconditioner of the gradient-descent solver."""

    #: 3x3 Hessian diagonal blocks, inverted per vertex (non positive-definite blocks fall back to SCALAR)
    BLOCK = "block"
    #: the scalar Hessian diagonal (clamped to a small positive floor)
    SCALAR = "scalar"


class LinearSolver(OptionEnum):
    """How Newton solves its linear systems ``(H + lambda I) dx = -g``."""

    #: a sparse direct factorization (:attr:`SolveSettings.sparse_backend`, on the CPU), optionally reused as
    # CG preconditioner (:attr:`SolveSettings.reuse_factorization`)
    DIRECT = "direct"
    #: conjugate gradients preconditioned by the inverse of the Hessian's 3x3 diagonal blocks, on the
    # positions' device: no factorization (on a GPU, 25x faster than SuperLU at 30K vertices, see the README)
    JACOBI_PCG = "jacobi-pcg"


class Safeguard(OptionEnum):
    """How the gradient-descent solver keeps barriers finite after each step."""

    #: scale the step by ``0.9 * model.max_step(x, dx)`` when that is below 1 (works for any barrier, incl.
    # CCD)
    MAX_STEP = "max-step"
    #: take the step, then ``model.project_feasible`` per vertex (Wang 2018; only for barriers it can project)
    PROJECT = "project"


@dataclass
class SolveSettings:
    """Settings of a quasistatic solve.

    Attributes:
        rtol: stop when the force norm ``|g| <= rtol * |g(x0)|``.
        atol: or when ``|g| <= atol`` (newtons); 0 disables the absolute test.
        max_iterations: iteration budget (one iteration = one gradient evaluation for GD, one linear solve
            for Newton).
        chebyshev_rho: spectral-radius estimate of the Jacobi iteration (Wang & Yang 2016), in [0, 1);
            0 disables the acceleration (plain preconditioned gradient descent).
        chebyshev_delay: iterations of plain descent before the Chebyshev weights start (and after a restart).
        step: initial under-relaxation ``alpha`` of the Jacobi step ``-alpha * D^-1 g``, in (0, 1].
        step_decrease: factor applied to ``step`` when the energy increases between two checkpoints.
        min_step: smallest allowed ``step``; the solve stops (not converged) below it.
        check_interval: iterations between energy checkpoints (energy increase -> roll back, shrink the step,
            restart Chebyshev).
        diagonal_interval: rebuild the Jacobi preconditioner every this many iterations (1 = every iteration).
        elastic_diagonal_interval: when the preconditioner is rebuilt, the diagonal of the volatile terms
            (barriers and contact, whose stiffness changes fast) is always evaluated at the current positions;
            that of the elastic terms (springs) only every this many iterations, and reused in between
            (``SimModel.value_grad_hessian_diagonal(reuse_elastic=True)``). 1 = always fresh.
        preconditioner: BLOCK (3x3 block Jacobi) or SCALAR (diagonal Jacobi).
        seam_blocks: with BLOCK, precondition each seam pair (two vertices joined by a sewing spring, each in
            no other pair) with its exact 6x6 block instead of two 3x3 blocks, so that stiff seams do not
            freeze the pair's common motion (see
            :func:`~torchgarment.sim.solvers.chebyshev.seam_block_inverse`); Newton's ``"jacobi-pcg"``
            uses the same blocks in its CG preconditioner.
        diagonal_floor: relative floor of the preconditioner, times the mean Hessian diagonal, so that
            vertices without stiffness do not get infinite steps.
        safeguard: how GD keeps barriers finite (MAX_STEP or PROJECT).
        max_displacement: GD trust region in metres: each vertex's move per iteration is clamped to this
            length (flat cloth has no out-of-plane stiffness, so ``D^-1 g`` can be huge there); None disables.
        project_psd: project per-element Hessian blocks to PSD in Newton (projected Newton).
        armijo_c: Armijo sufficient-decrease constant of Newton's backtracking line search.
        backtrack: step shrink factor of the line search.
        max_backtracks: line-search trials before the solve stops as stalled.
        step_fraction: fraction of ``model.max_step`` Newton steps are capped to when the full step is
            infeasible.
        regularization: initial ``lambda`` (relative to the mean Hessian diagonal) added as ``lambda * I``
            when the factorization fails or the direction is not a descent direction; grows by 10 per retry.
        max_regularizations: retries of the regularized factorization before giving up.
        reuse_factorization: Newton solves each system by CG preconditioned with the last sparse LU
            factorization (an inexact Newton step to relative residual ``pcg_rtol``) and factorizes afresh
            only when CG needs more than ``pcg_max_iterations`` iterations or gives no descent direction
            (:class:`~torchgarment.linalg.FactorCache`).
            Large meshes (the drape's settle stage) spend most of a Newton iteration in the factorization.
        pcg_rtol: relative residual of those CG solves, in (0, 1).
        pcg_max_iterations: CG iterations before a fresh factorization (>= 1).
        pcg_accept_rtol: a CG solve stopped by ``pcg_max_iterations`` short of ``pcg_rtol`` is still taken as
            Newton's direction when its relative residual is at most this (in [``pcg_rtol``, 1); an inexact
            Newton step with this forcing term), instead of factorizing afresh, and the next system is then
            factorized afresh; None: ``pcg_rtol`` (never). The same holds for the exact-curvature CG below
            when it is preconditioned by the last factorization and uses up its ``exact_curvature_cg``
            iterations short of ``exact_curvature_rtol``.
        exact_curvature_cg: 0 (default): Newton's direction is the projected Newton step ``-H_psd^-1 g``.
            N > 0: up to N conjugate-gradient iterations on the exact (unprojected) Hessian, preconditioned by
            the factorization of the projected one, from zero, to relative residual ``exact_curvature_rtol``
            or the first direction of non-positive curvature (Steihaug); the first iterate is the projected
            step scaled by the exact curvature along it. Projecting every compressed spring's block makes the
            model 6-12x stiffer than the energy along the Newton direction of a settling garment (measured on
            the 3K sheath dress), which costs projected Newton hundreds of full but short steps. With
            ``reuse_factorization`` the preconditioner is the last factorization while CG reaches
            ``exact_curvature_rtol`` (or non-positive curvature) within N iterations, or within
            ``pcg_accept_rtol`` after N, else a fresh one, which is then kept. Not with ``"jacobi-pcg"``.
        exact_curvature_rtol: relative residual of those CG iterations, in (0, 1).
        sparse_backend: the sparse direct solver of Newton's systems
            (:class:`~torchgarment.linalg.SparseBackend`; ``"superlu"``, always installed and deterministic,
            by default; ``"cholmod"``, a Cholesky, factorizes the projected Newton systems 3-4x faster, and
            a differentiable solve then factorizes its possibly indefinite exact Hessians by SuperLU).
        linear_solver: :class:`LinearSolver`: Newton's systems by ``sparse_backend`` (``"direct"``, default)
            or by block-Jacobi preconditioned CG on the positions' device (``"jacobi-pcg"``, an inexact Newton
            step to relative residual ``jacobi_pcg_rtol``; not with ``reuse_factorization``).
        jacobi_pcg_rtol: relative residual of the ``"jacobi-pcg"`` solves, in (0, 1).
        jacobi_pcg_max_iterations: CG iterations of one ``"jacobi-pcg"`` solve (>= 1); the iterate reached
            is used when the tolerance is not (any CG iterate from zero is a descent direction).
    """

    rtol: float = 1e-4
    atol: float = 0.0
    max_iterations: int = 1000
    chebyshev_rho: float = 0.99
    chebyshev_delay: int = 10
    step: float = 0.7
    step_decrease: float = 0.7
    min_step: float = 1e-6
    check_interval: int = 8
    diagonal_interval: int = 1
    elastic_diagonal_interval: int = 4
    preconditioner: Preconditioner = Preconditioner.BLOCK
    seam_blocks: bool = True
    diagonal_floor: float = 1e-8
    safeguard: Safeguard = Safeguard.MAX_STEP
    max_displacement: float | None = 0.01
    project_psd: bool = True
    armijo_c: float = 1e-4
    backtrack: float = 0.5
    max_backtracks: int = 40
    step_fraction: float = 0.9
    regularization: float = 1e-8
    max_regularizations: int = 12
    reuse_factorization: bool = False
    pcg_rtol: float = 1e-2
    pcg_max_iterations: int = 25
    pcg_accept_rtol: float | None = None
    exact_curvature_cg: int = 0
    exact_curvature_rtol: float = 0.05
    sparse_backend: SparseBackend = SparseBackend.SUPERLU
    linear_solver: LinearSolver = LinearSolver.DIRECT
    jacobi_pcg_rtol: float = 1e-4
    jacobi_pcg_max_iterations: int = 5000

    def __post_init__(self) -> None:
        self.preconditioner = Preconditioner.resolve(self.preconditioner)
        self.safeguard = Safeguard.resolve(self.safeguard)
        self.sparse_backend = SparseBackend.resolve(self.sparse_backend)
        self.linear_solver = LinearSolver.resolve(self.linear_solver)
        self.validate()

    def validate(self) -> None:
        """Raise :class:`InputError` for out-of-range settings (called on construction; changes nothing)."""
        checks = [
            (isinstance(self.preconditioner, Preconditioner) and isinstance(self.safeguard, Safeguard)
             and isinstance(self.sparse_backend, SparseBackend),
             f"preconditioner, safeguard and sparse_backend must be one of "
             f"{[p.value for p in Preconditioner]}, {[g.value for g in Safeguard]} and "
             f"{[b.value for b in SparseBackend]}"),
            (self.rtol >= 0 and self.atol >= 0, "rtol and atol must be >= 0"),
            (self.max_iterations >= 0, "max_iterations must be >= 0"),
            (0.0 <= self.chebyshev_rho < 1.0, "chebyshev_rho must lie in [0, 1)"),
            (self.chebyshev_delay >= 0, "chebyshev_delay must be >= 0"),
            (0.0 < self.step <= 1.0, "step must lie in (0, 1]"),
            (0.0 < self.step_decrease < 1.0, "step_decrease must lie in (0, 1)"),
            (self.min_step > 0, "min_step must be > 0"),
            (self.check_interval >= 1 and self.diagonal_interval >= 1 and self.elastic_diagonal_interval >= 1,
             "check/diagonal intervals must be >= 1"),
            (self.diagonal_floor > 0, "diagonal_floor must be > 0"),
            (self.max_displacement is None or self.max_displacement > 0,
             "max_displacement must be > 0 or None"),
            (0.0 < self.armijo_c < 1.0 and 0.0 < self.backtrack < 1.0,
             "armijo_c and backtrack must lie in (0, 1)"),
            (self.max_backtracks >= 1 and self.max_regularizations >= 0, "max_backtracks must be >= 1"),
            (0.0 < self.step_fraction < 1.0, "step_fraction must lie in (0, 1)"),
            (self.regularization > 0, "regularization must be > 0"),
            (0.0 < self.pcg_rtol < 1.0 and self.pcg_max_iterations >= 1,
             "pcg_rtol must lie in (0, 1) and pcg_max_iterations be >= 1"),
            (self.pcg_accept_rtol is None or self.pcg_rtol <= self.pcg_accept_rtol < 1.0,
             "pcg_accept_rtol must be None or lie in [pcg_rtol, 1)"),
            (isinstance(self.linear_solver, LinearSolver),
             f"linear_solver must be one of {[v.value for v in LinearSolver]}"),
            (0.0 < self.jacobi_pcg_rtol < 1.0 and self.jacobi_pcg_max_iterations >= 1,
             "jacobi_pcg_rtol must lie in (0, 1) and jacobi_pcg_max_iterations be >= 1"),
            (not (self.reuse_factorization and self.linear_solver == LinearSolver.JACOBI_PCG),
             "reuse_factorization reuses a factorization, which linear_solver='jacobi-pcg' never makes: "
             "set one of them"),
            (self.exact_curvature_cg >= 0 and 0.0 < self.exact_curvature_rtol < 1.0,
             "exact_curvature_cg must be >= 0 and exact_curvature_rtol lie in (0, 1)"),
            (self.exact_curvature_cg == 0 or self.linear_solver == LinearSolver.DIRECT,
             "exact_curvature_cg preconditions by a factorization of the projected Hessian, which "
             "linear_solver='jacobi-pcg' never makes: set one of them"),
        ]
        for ok, msg in checks:
            if not ok:
                raise InputError(f"invalid SolveSettings: {msg}")


DEFAULT_EXACT_CURVATURE_CG = 10
"""Newton's exact-curvature CG budget in drapes and adjustments when none is given (with a direct linear
solver; see :attr:`SolveSettings.exact_curvature_cg`). Over eight library drapes at 1.5-2 cm edges (SuperLU, 1
thread) their settles took 59.8 s instead of 88.5 s with projected Newton (see the README)."""


def exact_curvature_iterations(requested: int | None, linear_solver: LinearSolver) -> int:
    """The ``SolveSettings.exact_curvature_cg`` of a drape's settle or an adjustment's Newton solves:
    ``requested``, or when None :data:`DEFAULT_EXACT_CURVATURE_CG` with ``linear_solver="direct"`` and 0 with
    ``"jacobi-pcg"`` (which makes no factorization to precondition by)."""
    if requested is not None:
        return int(requested)
    return DEFAULT_EXACT_CURVATURE_CG if linear_solver == LinearSolver.DIRECT else 0


@dataclass
class SolveInfo:
    """What happened during a solve.

    Attributes:
        solver: the solver's name (a :class:`SolverKind` value).
        iterations: iterations performed.
        converged: whether the force-norm tolerance was met.
        residual_history: force norm ``|g|`` (N) at the start and after every iteration (``iterations + 1``
            entries for GD unless stopped early; entry 0 is ``|g(x0)|``).
        energy_history: total energy (J) at the same points.
        seconds: wall time of the solve.
        message: why the solve stopped.
        restarts: GD: Chebyshev restarts after energy increases; Newton: regularized factorizations.
        final_step: GD: the step ``alpha`` at the end; Newton: the last line-search step.
    """

    solver: str
    iterations: int = 0
    converged: bool = False
    residual_history: list[float] = field(default_factory=list)
    energy_history: list[float] = field(default_factory=list)
    seconds: float = 0.0
    message: str = ""
    restarts: int = 0
    final_step: float = 1.0

    @property
    def residual(self) -> float:
        """The final force norm (N)."""
        return self.residual_history[-1] if self.residual_history else math.nan

    def to_dict(self) -> dict:
        """A JSON-serializable dictionary (for metrics.json)."""
        return asdict(self)


class SolverModel(Protocol):
    """The part of :class:`~torchgarment.sim.scene.SimModel` the solvers use."""

    num_vertices: int

    def value_and_grad(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]: ...

    def hessian_diagonal(self, x: torch.Tensor) -> torch.Tensor: ...

    def hessian_blocks(self, x: torch.Tensor, project_psd: bool = True) -> HessianBlocks: ...

    def max_step(self, x: torch.Tensor, dx: torch.Tensor) -> float: ...

    def project_feasible(self, x: torch.Tensor) -> torch.Tensor: ...


def check_x0(model: SolverModel, x0: torch.Tensor) -> None:
    """Raise :class:`InputError` unless ``x0`` is a finite (num_vertices, 3) floating tensor."""
    if not isinstance(x0, torch.Tensor) or not x0.is_floating_point():
        raise InputError("x0 must be a floating-point torch tensor of shape (V, 3)")
    v = int(model.num_vertices)
    if x0.shape != (v, 3):
        raise InputError(f"x0 has shape {tuple(x0.shape)}, expected ({v}, 3)")
    if not bool(torch.isfinite(x0).all()):
        raise InputError("x0 contains NaN or infinite coordinates")


def evaluate(model: SolverModel, x: torch.Tensor, iteration: int, what: str = "", *,
             infeasible_ok: bool = False) -> tuple[float, torch.Tensor, float]:
    """Energy, gradient and gradient norm at ``x``; raises :class:`NonFiniteError` naming the iteration
    (``infeasible_ok``: see :func:`checked_evaluation`).

    Returns:
        ``(energy, g, |g|)`` with ``g: (V, 3)``.
    """
    e, g = model.value_and_grad(x)
    return checked_evaluation(e, g, iteration, what, infeasible_ok=infeasible_ok)


def checked_evaluation(e: torch.Tensor, g: torch.Tensor, iteration: int, what: str = "", *,
                       infeasible_ok: bool = False) -> tuple[float, torch.Tensor, float]:
    """``(energy, g, |g|)`` of an evaluation ``(e, g)`` at solver iteration ``iteration``; raises
    :class:`NonFiniteError` naming it when either is not finite.

    ``infeasible_ok``: an energy of +inf (a barrier's infeasible side, which a step bound should have kept out
    but round-off of a closing contact can reach) is returned as ``(inf, g, inf)`` for the caller to reject
    the step; NaN still raises."""
    ef = float(e)
    if infeasible_ok and ef == math.inf:
        return ef, g, math.inf
    gn = float(torch.linalg.vector_norm(g))
    if not (math.isfinite(ef) and math.isfinite(gn)):
        where = f" ({what})" if what else ""
        bad = "energy" if not math.isfinite(ef) else "gradient"
        raise NonFiniteError(f"model returned a non-finite {bad} at solver iteration {iteration}{where}: "
                             f"E={ef}, |g|={gn}")
    return ef, g, gn


def energy_float64(model: SolverModel, x: torch.Tensor) -> float:
    """The model's energy at ``x`` evaluated in float64 (``model.energy`` when it has one, else
    ``value_and_grad``); the terms cast their buffers to the positions' dtype. The solvers compare a
    float32 solve's energies with it: float32 energies carry round-off (about eps times the terms) at or above
    the decrease of a step near convergence."""
    x64 = x.detach().to(torch.float64)
    energy = getattr(model, "energy", None)
    return float(energy(x64) if energy is not None else model.value_and_grad(x64)[0])


def evaluate_with_diagonal(
    model: SolverModel, x: torch.Tensor, iteration: int, what: str = "", *, reuse_elastic: bool = False,
    infeasible_ok: bool = False,
) -> tuple[float, torch.Tensor, float, torch.Tensor]:
    """Like :func:`evaluate`, plus the Hessian diagonal blocks (V, 3, 3); uses the model's fused
    ``value_grad_hessian_diagonal`` when it has one (terms share their work), else two calls.
    ``reuse_elastic`` is passed on; only ask for it when :func:`supports_elastic_reuse` holds for the
    model. With ``infeasible_ok`` and a +inf energy the diagonal is not computed (the blocks returned are
    then meaningless: the caller rejects the step)."""
    fused = getattr(model, "value_grad_hessian_diagonal", None)
    if fused is None:
        e, g, gn = evaluate(model, x, iteration, what, infeasible_ok=infeasible_ok)
        return e, g, gn, (model.hessian_diagonal(x) if e != math.inf else g.new_empty(0, 3, 3))
    if reuse_elastic:  # callers check supports_elastic_reuse(model) once per solve
        e, g, h = fused(x, reuse_elastic=True)
    else:
        e, g, h = fused(x)
    return (*checked_evaluation(e, g, iteration, what, infeasible_ok=infeasible_ok), h)


def supports_elastic_reuse(model: SolverModel) -> bool:
    """Whether the model's fused ``value_grad_hessian_diagonal`` accepts ``reuse_elastic`` (a
    :class:`~torchgarment.sim.scene.SimModel` does; duck-typed models need not)."""
    fused = getattr(model, "value_grad_hessian_diagonal", None)
    if fused is None:
        return False
    try:
        return "reuse_elastic" in inspect.signature(fused).parameters
    except (TypeError, ValueError):
        return False


def checked_max_step(model: SolverModel, x: torch.Tensor, dx: torch.Tensor, iteration: int) -> float:
    """``model.max_step(x, dx)`` validated to lie in (0, 1]."""
    t = float(model.max_step(x, dx))
    if not (math.isfinite(t) and 0.0 < t <= 1.0 + 1e-12):
        raise NonFiniteError(f"model.max_step returned {t} at solver iteration {iteration}; expected a value "
                             f"in (0, 1]")
    return min(t, 1.0)


def tolerance(settings: SolveSettings, g0_norm: float) -> float:
    """The force-norm threshold ``max(rtol * |g0|, atol)``."""
    return max(settings.rtol * g0_norm, settings.atol)


class Timer:
    """Wall-clock stopwatch (``time.perf_counter``)."""

    def __init__(self) -> None:
        self.start = time.perf_counter()

    def elapsed(self) -> float:
        return time.perf_counter() - self.start
