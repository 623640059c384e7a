"""Projected Newton with a collision-free step bound for the retargeting objectives (Huang et al. 2025, 3.7).

The unknowns are the retargeting state ``y`` (N + 1, 3) of
:func:`~torchgarment.retarget.objectives.make_state`: garment positions and the inflation parameter ``t``.
Step 2 frees ``t`` (augmented Lagrangian :class:`InflationPenalty` pushes it to 1); Step 3 fixes it at 1. The
objective is a :class:`~torchgarment.sim.scene.SimModel` of
:class:`~torchgarment.retarget.objectives.RetargetEnergy` terms and the solver the simulator's projected
Newton (:func:`~torchgarment.sim.solvers.newton.solve_newton`) with:

* the free unknowns: the garment, plus ``t`` in Step 2;
* the step bound :class:`CollisionFreeBound`: the largest vertex displacement (garment or avatar) capped at
  ``max_displacement``, ``t`` kept in [0, t_max], then a collision-free step size
  (:class:`~torchgarment.sim.contact.StepBound`: Additive CCD by default, Tight-Inclusion CCD, or the
  conservative distance bound; see :func:`~torchgarment.sim.contact.collision_free_step`);
* the Hessian shifted from the start (``1e-8`` of its mean diagonal, times 100 per failed factorization, the
  scaled gradient as the last resort), value-only backtracking from the bound (halving, Armijo constant
  ``armijo_c``), no Levenberg retries;
* IPC's barrier stiffness update after each step (:meth:`~torchgarment.sim.contact.MovingObstacleContact.
  update_stiffness`), and stops on the gradient (``max(atol, rtol |g_0|)`` over the free unknowns), a stalled
  energy or a vanishing step.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from torchgarment.errors import InputError
from torchgarment.linalg import SparseBackend
from torchgarment.retarget.objectives import (
    Contact,
    RetargetEnergy,
    _empty_blocks,
    _t_tensor,
    make_state,
    split_state,
)
from torchgarment.sim.contact import StepBound
from torchgarment.sim.energies.base import HessianBlocks
from torchgarment.sim.scene import SimModel
from torchgarment.sim.solvers.common import NonFiniteError, SolveSettings
from torchgarment.sim.solvers.newton import NewtonOptions, NewtonStep, solve_newton


class InflationPenalty(RetargetEnergy):
    """Augmented Lagrangian of the equality t = 1: ``lambda1 / 2 (1 - t)^2 + lambda2 (1 - t)``.

    Attributes:
        lambda1: penalty stiffness (> 0). lambda2: multiplier estimate.
    """

    name = "al"
    uses_t = True

    def __init__(self, lambda1: float, lambda2: float = 0.0) -> None:
        super().__init__(1.0)
        if not lambda1 > 0:
            raise InputError(f"lambda1 must be positive, got {lambda1}")
        self.lambda1 = float(lambda1)
        self.lambda2 = float(lambda2)

    def energy(self, x: torch.Tensor, t: torch.Tensor | float) -> torch.Tensor:  # noqa: D102
        c = 1.0 - _t_tensor(t, x)
        return 0.5 * self.lambda1 * c * c + self.lambda2 * c

    def unweighted_blocks(
        self, x: torch.Tensor, t: torch.Tensor | float, project_psd: bool = True
    ) -> HessianBlocks:
        """The t-t entry ``lambda1`` (vertex N's block, entry (0, 0))."""
        n = torch.tensor([x.shape[0]], device=x.device)
        v = torch.zeros(1, 3, 3, dtype=x.dtype, device=x.device)
        v[0, 0, 0] = self.lambda1
        return HessianBlocks(n, n.clone(), v)

    def update(self, t: float) -> None:
        """Multiplier update ``lambda2 += lambda1 (1 - t)``."""
        self.lambda2 += self.lambda1 * (1.0 - float(t))


class RetargetModel(SimModel):
    """A :class:`SimModel` over the retargeting state (N + 1, 3) (:func:`retarget_model`) that also hands the
    solver its Hessian blocks in two groups, the terms with a fixed sparsity and the contact, whose pairs
    change every iteration (:func:`~torchgarment.sim.solvers.newton.solve_newton` assembles each group with
    its own cached pattern)."""

    def hessian_block_parts(self, y: torch.Tensor, project_psd: bool = True) -> list[HessianBlocks]:
        """``[blocks of the non-volatile terms, blocks of the volatile ones]``; their sum is
        :meth:`hessian_blocks`."""
        y = y.detach()
        return [HessianBlocks.cat([_empty_blocks(y)] + [t.hessian_blocks(y, project_psd) for t in self.terms
                                                        if t.volatile_hessian == volatile])
                for volatile in (False, True)]


def retarget_model(terms: list[RetargetEnergy], x: torch.Tensor) -> RetargetModel:
    """The objective: a :class:`RetargetModel` over the state (N + 1, 3) summing the terms of non-zero weight.

    Args:
        terms: the retargeting terms (distinct names). x: (N, 3) garment (its size, dtype and device).
    """
    kept = [t for t in terms if t.weight != 0.0]
    return RetargetModel(kept, x.shape[0] + 1, device=x.device, dtype=x.dtype)


def term_values(terms: list[RetargetEnergy], x: torch.Tensor, t: torch.Tensor | float) -> dict[str, float]:
    """Unweighted value of each term at garment ``x`` (N, 3) and inflation ``t``."""
    y = make_state(x, t)
    return {term.name: term.value(y) for term in terms}


@dataclass
class NewtonSettings:
    """Settings of :func:`projected_newton`.

    Attributes:
        max_iterations: Newton iterations at most.
        rtol: stop when |g| <= max(atol, rtol * |g_0|) (2-norm over free unknowns).
        atol: absolute gradient floor.
        step_tol: stop when the accepted step moves no vertex by more than this (units of x).
        max_displacement: cap of the largest vertex displacement (garment or avatar) of one Newton step
            (units of x), None: no cap.
        step_bound: collision-free step method (:class:`~torchgarment.sim.contact.StepBound` or its name).
        armijo_c: sufficient-decrease constant.
        max_backtracks: line-search trials (halving the step) before giving up (27: down to 1e-8 of the
            bound).
        update_stiffness: IPC's barrier stiffness update after each iteration (ipctk.update_barrier_stiffness:
            doubles kappa, up to its maximum, while the minimum distance decreases below
            ``stiffness_distance * dhat``).
        stiffness_distance: see ``update_stiffness`` (IPC's default is 1e-9 of the scene's diagonal).
        energy_tol: also stop (converged, reason "energy") when the energy fell by less than
            ``energy_tol * |E|`` over the last ``energy_window`` iterations; 0 disables it.
        energy_window: see ``energy_tol``.
        reuse_factorization: solve each Newton system by conjugate gradients preconditioned with the last
            sparse LU factorization (an inexact Newton step, to relative residual ``pcg_rtol``), and factorize
            afresh only when that takes more than ``pcg_max_iterations`` iterations or does not give a descent
            direction. The Hessian changes little from one iteration to the next, so most iterations cost a
            few triangular solves instead of a factorization (0.36 s at 6K garment vertices). None (the
            default): reuse with SuperLU and pardiso, not with a Cholesky backend (``"cholmod"``,
            ``"cholespy"``), whose fresh factorization in the garment mesh's ordering (see
            :func:`~torchgarment.sim.solvers.newton.solve_newton`) costs about as much as the 15-20 CG
            iterations (triangular solves of 5-6 ms at 5K garment vertices) that the reuse spent per Newton
            iteration: the messy bench's mean pair 4-7 % shorter without the reuse, in two rounds of pairs
            run alternately, the clean bench's mean unchanged (README, "Retargeting", "Each Newton system
            factorized afresh in the garment's ordering").
        pcg_rtol: relative residual of the preconditioned CG solve.
        pcg_max_iterations: CG iterations before a fresh factorization.
        pcg_accept_rtol: a CG solve that used up ``pcg_max_iterations`` short of ``pcg_rtol`` is still
            Newton's direction when its relative residual is at most this (an inexact Newton step; 0.1, a
            textbook forcing term); only a worse one is factorized afresh at once. On the messy bench most
            budget-stopped solves ended at relative residuals of 0.01-0.1, each then followed by a fresh
            factorization (README, "Retargeting"). A solve taken this way also drops the factorization, so
            the next iteration factorizes afresh instead of spending another whole budget on a drifted
            preconditioner. None: factorize after every budget-stopped solve.
        sparse_backend: the sparse direct solver of the Newton systems
            (:class:`~torchgarment.linalg.SparseBackend`).
    """

    max_iterations: int = 100
    rtol: float = 1e-3
    atol: float = 1e-7
    step_tol: float = 1e-7
    max_displacement: float | None = None
    step_bound: StepBound | str = StepBound.ADDITIVE
    armijo_c: float = 1e-4
    max_backtracks: int = 27
    update_stiffness: bool = True
    stiffness_distance: float = 0.1
    energy_tol: float = 0.0
    energy_window: int = 3
    reuse_factorization: bool | None = None
    pcg_rtol: float = 1e-2
    pcg_max_iterations: int = 25
    pcg_accept_rtol: float | None = 0.1
    sparse_backend: SparseBackend | str = SparseBackend.SUPERLU

    def __post_init__(self) -> None:
        self.step_bound = StepBound.resolve(self.step_bound)
        self.sparse_backend = SparseBackend.resolve(self.sparse_backend)
        if self.reuse_factorization is None:
            self.reuse_factorization = not self.sparse_backend.positive_definite_only
        if self.max_iterations < 0 or not self.rtol >= 0 or not self.atol >= 0 or not self.step_tol >= 0:
            raise InputError("NewtonSettings: max_iterations, rtol, atol and step_tol must be non-negative")
        if not (0 < self.pcg_rtol < 1) or self.pcg_max_iterations < 1:
            raise InputError("NewtonSettings: pcg_rtol must lie in (0, 1) and pcg_max_iterations be >= 1")
        if self.pcg_accept_rtol is not None and not self.pcg_rtol <= self.pcg_accept_rtol < 1:
            raise InputError("NewtonSettings: pcg_accept_rtol must be None or lie in [pcg_rtol, 1)")
        if self.max_displacement is not None and not self.max_displacement > 0:
            raise InputError(f"NewtonSettings.max_displacement must be positive, got {self.max_displacement}")
        if not 0 < self.armijo_c < 1 or self.max_backtracks < 1:
            raise InputError("NewtonSettings: armijo_c must lie in (0, 1) and max_backtracks be >= 1")
        if not (self.energy_tol >= 0 and self.energy_window >= 1 and self.stiffness_distance > 0):
            raise InputError("NewtonSettings: energy_tol >= 0, energy_window >= 1 and stiffness_distance > 0")

    def solve_settings(self) -> SolveSettings:
        """The shared solver's settings (the regularization: 1e-8 of the mean diagonal, 12 retries)."""
        s = SolveSettings(
            rtol=self.rtol,
            atol=self.atol,
            max_iterations=self.max_iterations,
            armijo_c=self.armijo_c,
            backtrack=0.5,
            max_backtracks=self.max_backtracks,
            regularization=1e-8,
            max_regularizations=12,
            reuse_factorization=self.reuse_factorization,
            pcg_rtol=self.pcg_rtol,
            pcg_max_iterations=self.pcg_max_iterations,
            pcg_accept_rtol=self.pcg_accept_rtol,
            sparse_backend=self.sparse_backend,
        )
        s.validate()
        return s


@dataclass
class NewtonResult:
    """Outcome of :func:`projected_newton`.

    Attributes:
        x: (N, 3) final garment. t: final inflation. iterations: Newton iterations done. grad_norm: final |g|.
        energy: final weighted total. converged: gradient criterion met. reason: why it stopped ("gradient",
        "energy", "step", "line_search", "callback" or "max_iterations").
        step_bound_seconds: time spent in collision-free step queries. history: per-iteration stats.
    """

    x: torch.Tensor
    t: float
    iterations: int
    grad_norm: float
    energy: float
    converged: bool
    reason: str
    step_bound_seconds: float = 0.0
    history: list[dict] = field(default_factory=list)


class CollisionFreeBound:
    """The retargeting step bound (a :class:`~torchgarment.sim.solvers.newton.StepLimiter`) on states (N + 1,
    3).

    ``max_step`` caps the largest vertex displacement (garment, or avatar: ``|dt| * delta_max``) at
    ``max_displacement``, keeps ``t`` in [0, t_max] and multiplies by the contact's collision-free step size.

    Args:
        contact: the contact machinery or None (no collision bound). max_displacement: cap or None.
        method: :class:`StepBound`. t_max: upper bound of t.
    """

    def __init__(
        self, contact: Contact | None, max_displacement: float | None, method: StepBound, t_max: float = 1.0
    ) -> None:
        self.ipc = None if contact is None else contact.ipc
        self.max_displacement = max_displacement
        self.method = StepBound.resolve(method)
        self.t_max = float(t_max)
        #: seconds spent in collision-free step queries
        self.seconds = 0.0

    def displacement(self, dy: torch.Tensor) -> float:
        """Largest garment or avatar vertex displacement of the step ``dy`` (N + 1, 3)."""
        dx, dt = split_state(dy)
        move = float(torch.linalg.vector_norm(dx, dim=-1).max()) if dx.shape[0] else 0.0
        dt = float(dt)
        if self.ipc is not None and self.ipc.uses_t and dt != 0.0:
            move = max(move, abs(dt) * self.ipc.delta_max)
        return move

    def max_step(self, y: torch.Tensor, dy: torch.Tensor) -> float:
        """Largest admissible step of ``y + alpha dy`` (states (N + 1, 3))."""
        xn = y[:-1].detach().to("cpu", torch.float64).numpy()
        dx = dy[:-1].detach().to("cpu", torch.float64).numpy()
        dt = float(dy[-1, 0])
        amax = 1.0
        move = float(np.sqrt((dx * dx).sum(1)).max(initial=0.0))
        if self.ipc is not None and self.ipc.uses_t and dt != 0.0:
            move = max(move, abs(dt) * self.ipc.delta_max)
        if self.max_displacement is not None and move > self.max_displacement:
            amax = self.max_displacement / move
        tv = float(y[-1, 0])
        if dt > 0:
            amax = min(amax, (self.t_max - tv) / dt)
        elif dt < 0:
            amax = min(amax, tv / -dt)
        amax = max(amax, 0.0)
        if self.ipc is not None and amax > 0:
            tb = time.perf_counter()
            amax *= self.ipc.max_step(xn, tv, amax * dx, amax * dt, self.method)
            self.seconds += time.perf_counter() - tb
        return amax


class _Monitor:
    """Per-iteration statistics, IPC's stiffness update and the user callback of :func:`projected_newton`."""

    def __init__(
        self,
        terms: list[RetargetEnergy],
        contact: Contact | None,
        settings: NewtonSettings,
        callback: Callable[[dict], bool | None] | None,
    ) -> None:
        self.terms = terms
        self.contact = contact
        self.settings = settings
        self.callback = callback
        self.history: list[dict] = []
        self.stop = False
        self.prev_dmin = math.inf

    def start(self, x0: torch.Tensor, t0: float) -> None:
        """The initial state's minimum distance (within dhat): the stiffness update's first reference."""
        if self.contact is not None:
            ipc = self.contact.ipc
            self.prev_dmin = ipc.min_distance(x0, float(t0), ipc.dhat)

    def after_step(self, y: torch.Tensor, step: NewtonStep) -> bool:
        """Record the step's stats, update the barrier stiffness; True when the stiffness changed."""
        vals = {term.name: term.value(y) for term in self.terms}
        stats = {
            "iteration": step.iteration,
            "energy": step.energy,
            "grad_norm": step.grad_norm,
            "alpha": step.alpha,
            "alpha_max": step.alpha_max,
            "max_displacement": step.displacement,
            "t": float(y[-1, 0]),
            **{f"term/{k}": v for k, v in vals.items()},
        }
        changed = False
        if self.contact is not None:
            ipc = self.contact.ipc
            dmin = ipc.last_stats.min_distance
            stats["min_distance"] = dmin
            stats["stiffness"] = ipc.stiffness
            if self.settings.update_stiffness:
                changed = ipc.update_stiffness(self.prev_dmin, dmin, self.settings.stiffness_distance)
            self.prev_dmin = dmin
        self.history.append(stats)
        if self.callback is not None and self.callback(stats):
            self.stop = True
        return changed

    def __call__(self, k: int, y: torch.Tensor, gn: float, e: float) -> bool:
        return self.stop


_REASONS = {
    "converged": "gradient",
    "energy stalled": "energy",
    "small step": "step",
    "stopped by callback": "callback",
    "max iterations reached": "max_iterations",
}


def projected_newton(
    model: SimModel,
    x0: torch.Tensor,
    t0: float,
    *,
    free_t: bool,
    settings: NewtonSettings | None = None,
    callback: Callable[[dict], bool | None] | None = None,
    t_max: float = 1.0,
) -> NewtonResult:
    """Minimise ``model`` (:func:`retarget_model`) from ``(x0, t0)`` by the shared projected Newton
    (:func:`~torchgarment.sim.solvers.newton.solve_newton`) with a collision-free step bound.

    Args:
        model: the objective; its term named "contact" (if any) gives the step bound and the stiffness update.
        x0: (N, 3) intersection-free garment. t0: initial inflation.
        free_t: optimise t too (Step 2) or keep it fixed (Step 3).
        settings: :class:`NewtonSettings`.
        callback: called with each iteration's stats dict; returning True stops early (reason "callback").
        t_max: upper bound of t.

    Returns:
        :class:`NewtonResult`.

    Raises:
        InputError: the initial state has a non-finite energy.
    """
    s = settings or NewtonSettings()
    terms = list(model.terms)
    contact = next((t for t in terms if isinstance(t, Contact)), None)
    y0 = make_state(x0.detach(), float(t0))
    free = torch.ones_like(y0, dtype=torch.bool)
    free[-1, 1:] = False
    free[-1, 0] = bool(free_t)
    bound = CollisionFreeBound(contact, s.max_displacement, s.step_bound, t_max)
    monitor = _Monitor(terms, contact, s, callback)
    monitor.start(x0, float(t0))
    options = NewtonOptions(
        free=free,
        step_bound=bound,
        regularize_first=True,
        regularization_growth=100.0,
        gradient_fallback=True,
        levenberg=False,
        value_only_line_search=True,
        armijo_slack=0.0,
        step_tol=s.step_tol,
        energy_tol=s.energy_tol,
        energy_window=s.energy_window,
        after_step=monitor.after_step,
    )
    try:
        y, info = solve_newton(model, y0, s.solve_settings(), s.max_iterations, monitor, options)
    except NonFiniteError as err:
        if "iteration 0" not in str(err):
            raise
        vals = {t.name: t.value(y0) for t in terms}
        bad = ", ".join(k for k, v in vals.items() if not math.isfinite(v))
        raise InputError(
            f"the initial state has a non-finite energy in: {bad} (touching contact or a degenerate element)"
        ) from None
    reason = (
        "line_search" if info.message.startswith("line search") else _REASONS.get(info.message, info.message)
    )
    x, t = split_state(y)
    return NewtonResult(
        x.detach().clone(),
        float(t),
        info.iterations,
        info.residual,
        info.energy_history[-1],
        info.converged,
        reason,
        bound.seconds,
        monitor.history,
    )


def initial_stiffness(
    model: SimModel, x: torch.Tensor, t: torch.Tensor | float, average_mass: float
) -> float:
    """IPC's adaptive initial barrier stiffness (ipctk.initial_barrier_stiffness) of the model's contact term.

    Balances the barrier gradient against the gradient of all other terms of ``model``; sets the contact's
    ``stiffness`` and ``max_stiffness`` and returns the stiffness.

    Args:
        model: a :func:`retarget_model` with a :class:`~torchgarment.retarget.objectives.Contact` term.
        x: (N, 3); t: inflation. average_mass: IPC's mass scale (here the mean lumped vertex area).
    """
    contact = next((term for term in model.terms if isinstance(term, Contact)), None)
    if contact is None:
        raise InputError("initial_stiffness: the model has no contact term")
    y = make_state(x.detach(), t)
    ge = torch.zeros_like(y)
    for term in model.terms:
        if term is not contact:
            ge += term.value_and_grad(y)[1]
    other = np.r_[ge[:-1].detach().to("cpu", torch.float64).numpy().reshape(-1), float(ge[-1, 0])]
    return contact.ipc.initial_stiffness(x, float(t), other, average_mass)
