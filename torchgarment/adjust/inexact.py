"""The simulate-then-differentiate problem of pattern adjustment and the inexact strategy (Wang 2018, Algorithm 1).

:class:`AdjustProblem` evaluates the objective of Eq. 17 for pattern parameters ``q`` (B, 2), the boundary
vertices of the pattern (section 5)::

    p = param(q)                     (V, 2) rest positions, Eq. 8
    x = Sim(p)                       (V, 3) quasistatic garment on the target body (exact or S iterations)
    f = objective(x, p)              scalar, Eq. 17

and its gradient by the adjoint method (Eq. 18-19): ``K lambda = df/dx`` with ``K`` the exact unprojected
Hessian of the simulation energy at ``x`` (SuperLU factorization, or with ``adjoint="iterative"`` block-Jacobi
conjugate gradients warm-started from the previous adjoint, :class:`AdjointSolve`), ``df/dp += -lambda^T d(grad_x E)/dp``
(matrix-free, :func:`~torchgarment.sim.diff.parameter_vjp`), ``df/dq = (dp/dq)^T df/dp`` (autograd through the
parametrization). Simulations are warm-started from the previous state. An *exact* evaluation solves to the
force tolerance; an *inexact* one runs ``S`` solver iterations only, and its gradient uses the adjoint at the
unconverged state (the paper's inexact gradient). The problem also provides Gauss-Newton products (a tangent
solve ``K dx = -(d grad_x E / dp) dp`` and an adjoint solve per product, with the same factorization) and
records the best exact evaluation it has seen.

:class:`InexactRunner` is Algorithm 1 generalized to any :class:`~torchgarment.adjust.optimizers` optimizer:
``S`` simulation iterations per outer iteration, an exact evaluation every ``M`` outer iterations (default
32) compared with the last exact one; when the objective fails to drop, the run goes back to the last exact
iterate (parameters, optimizer state and simulation state), doubles ``S`` and halves the step; when it drops,
``S`` shrinks and the step grows. The result is the best *exactly evaluated* iterate, which includes the start:
it is never worse than the start. With ``exact=True`` every evaluation is exact (the optimizers' own line
searches then see true values) and the same best-exact rule applies.

Example::

    problem = AdjustProblem(model, param, objective, x0, exact_settings=SolveSettings(rtol=0, atol=1e-3))
    opt = PreconditionedGD([q], objective.regularizer_hessian(), line_search=False)
    runner = InexactRunner(problem, opt, q, InexactSettings(inner_iterations=8))
    result = runner.run(256)
    result.q, result.objective        # best exact iterate and its objective
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse.linalg
import torch
from torch.func import functional_call, grad as func_grad, jvp as func_jvp

from torchgarment.errors import InputError
from torchgarment.options import OptionEnum
from torchgarment.sim.diff import (
    AdjointLinearSolver,
    NonConvergenceError,
    exact_hessian_blocks,
    parameter_vjp,
    solve_adjoint,
)
from torchgarment.sim.solvers import NonFiniteError, SolveInfo, SolverKind, SolveSettings, solve
from torchgarment.sim.solvers.common import CSRAssembler


class AdjointSolve(OptionEnum):
    """How :class:`AdjustProblem` solves the adjoint system ``K lambda = df/dx`` of a gradient."""

    #: a fresh SuperLU factorization of ``K`` per evaluation: exact, cost grows fast with the mesh (1-10 s at 30K)
    DIRECT = "direct"
    #: conjugate gradients on ``K`` with the simulator's block-Jacobi preconditioner (3x3 blocks, seam pairs as
    #: 6x6 blocks), warm-started from the previous adjoint and capped at ``adjoint_max_iterations``: the paper's
    #: iterative solver (section 7); an inexact gradient, like the S-iteration simulation it pairs with
    ITERATIVE = "iterative"


@dataclass
class Evaluation:
    """One evaluation of the problem.

    Attributes:
        objective: ``f(x, p)`` (objective units).
        grad: (B, 2) ``df/dq`` or None when not asked for.
        exact: whether ``x`` is an equilibrium (solved to the force tolerance).
        sim_iterations: solver iterations spent on ``x``.
        residual: force norm of ``x`` in newtons.
        seconds: wall time of the evaluation.
    """

    objective: float
    grad: torch.Tensor | None
    exact: bool
    sim_iterations: int
    residual: float
    seconds: float


class AdjustProblem:
    """``q -> f(Sim(param(q)), param(q))`` with adjoint gradients and Gauss-Newton products (module docstring).

    Args:
        model: the :class:`~torchgarment.sim.scene.SimModel` of the garment on the target body; its
            ``stretch.p`` is overwritten by every evaluation.
        parametrization: module ``q (B, 2) -> p (V, 2)`` (Eq. 8; :class:`BoundaryParametrization`).
        objective: module ``(x (V, 3), p (V, 2)) -> ()`` (the :class:`AdjustObjective`); ``term_values(x, p)``
            is used for reporting when it exists.
        x0: (V, 3) initial garment positions in metres (the warm start of the first solve).
        exact_settings: settings of exact solves (their tolerance ``atol`` in newtons is also the early stop of
            inexact ones).
        solver: quasistatic solver of the simulations (``"newton"`` or ``"gd-chebyshev"``).
        inexact_solver: solver of the S-iteration simulations (default: ``solver``).
        parameter: qualified name of the model parameter ``p`` is written to.
        strict: raise :class:`NonConvergenceError` when an exact solve misses its tolerance.
        adjoint: :class:`AdjointSolve` of the gradients (``"direct"`` or ``"iterative"``); Gauss-Newton's
            tangent solves are always direct.
        adjoint_rtol: relative residual at which the iterative adjoint stops.
        adjoint_max_iterations: CG iterations of an iterative adjoint (it stops there, converged or not: the
            gradient is then inexact; Algorithm 1's exact checks and backtracking keep the run safe).
    """

    def __init__(self, model: torch.nn.Module, parametrization: torch.nn.Module, objective: torch.nn.Module,
                 x0: torch.Tensor, *, exact_settings: SolveSettings | None = None,
                 solver: "str | SolverKind" = SolverKind.NEWTON, inexact_solver: "str | SolverKind | None" = None,
                 parameter: str = "stretch.p", strict: bool = True,
                 adjoint: "str | AdjointSolve" = AdjointSolve.DIRECT, adjoint_rtol: float = 1e-3,
                 adjoint_max_iterations: int = 50) -> None:
        self.model = model
        self.param = parametrization
        self.objective = objective
        self.solver = SolverKind.resolve(solver)
        self.inexact_solver = self.solver if inexact_solver is None else SolverKind.resolve(inexact_solver)
        self.exact_settings = exact_settings if exact_settings is not None else SolveSettings(rtol=1e-6,
                                                                                              max_iterations=200)
        self.exact_settings.validate()
        self.adjoint = AdjointSolve.resolve(adjoint)
        if not (0.0 < adjoint_rtol < 1.0 and int(adjoint_max_iterations) >= 1):
            raise InputError(f"adjoint_rtol must be in (0, 1) and adjoint_max_iterations >= 1, got {adjoint_rtol}, "
                             f"{adjoint_max_iterations}")
        self.adjoint_rtol, self.adjoint_max_iterations = float(adjoint_rtol), int(adjoint_max_iterations)
        self._adjoint_warm: torch.Tensor | None = None
        self.adjoint_iterations = 0
        self.last_adjoint_residual = math.nan
        self.strict = bool(strict)
        term_name, _, attr = parameter.partition(".")
        try:
            self._term = model.term(term_name)
        except Exception as exc:  # noqa: BLE001 - SimModel.term raises InputError/KeyError
            raise InputError(f"the simulation model has no term {term_name!r} for parameter {parameter!r}") from exc
        if not hasattr(self._term, attr):
            raise InputError(f"term {term_name!r} has no parameter {attr!r}")
        self.parameter, self._attr = parameter, attr
        self._assembler = CSRAssembler(model.num_vertices)
        with torch.no_grad():
            self.x = model.project_feasible(x0.detach().to(model.dtype).clone())
        self.closure_evaluations = 0
        self.sim_iterations = 0
        self.exact_evaluations = 0
        self.last: Evaluation | None = None
        self.last_q: torch.Tensor | None = None
        self.last_p: torch.Tensor | None = None
        self.last_x: torch.Tensor | None = None
        self.last_info: SolveInfo | None = None
        self.best_q: torch.Tensor | None = None
        self.best_x: torch.Tensor | None = None
        self.best_objective = math.inf
        self._lu = None
        self._lu_key: torch.Tensor | None = None
        self.factorizations = 0
        self._hess_graph = None

    # ------------------------------------------------------------------ simulation
    @torch.no_grad()
    def simulate(self, p: torch.Tensor, *, exact: bool, iterations: int | None = None) -> torch.Tensor:
        """Write ``p`` into the model and solve from the current state (warm start); returns (V, 3).

        Args:
            p: (V, 2) rest positions in metres.
            exact: solve to ``exact_settings``' tolerance (raising if missed and ``strict``), else run
                ``iterations`` solver iterations (stopping early if that tolerance is met).
            iterations: the ``S`` of an inexact solve (>= 1).
        """
        getattr(self._term, self._attr).copy_(p.detach().to(self.model.dtype))
        if exact:
            x, info = solve(self.model, self.x, self.exact_settings, solver=self.solver)
            if not info.converged:
                msg = (f"exact simulation did not converge: force norm {info.residual:.3g} N after {info.iterations} "
                       f"iterations ({info.message})")
                if self.strict:
                    raise NonConvergenceError(msg)
        else:
            if iterations is None or int(iterations) < 1:
                raise InputError(f"an inexact simulation needs iterations >= 1, got {iterations}")
            x, info = solve(self.model, self.x, self.exact_settings, solver=self.inexact_solver,
                            max_iterations=int(iterations))
        self.x = x.detach()
        self.last_info = info
        self.sim_iterations += info.iterations
        return self.x

    def reset_state(self, x: torch.Tensor) -> None:
        """Set the warm start (V, 3) of the next simulation (used when a run goes back to an earlier iterate)."""
        self.x = x.detach().clone()

    # ------------------------------------------------------------------ evaluation
    def _factorize(self, x: torch.Tensor):  # noqa: ANN202 - SuperLU object
        if self._lu is not None and self._lu_key is not None and torch.equal(self._lu_key, x):
            return self._lu
        K = self._assembler.assemble(exact_hessian_blocks(self.model, x)).tocsc()
        self.factorizations += 1
        try:
            lu = scipy.sparse.linalg.splu(K, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                          options={"SymmetricMode": True})
        except RuntimeError as exc:
            raise NonConvergenceError(f"the simulation Hessian is singular at the current state ({exc})") from exc
        self._lu, self._lu_key = lu, x.detach().clone()
        return lu

    def _solve_k(self, x: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
        b = rhs.detach().to("cpu", torch.float64).numpy().reshape(-1)
        y = self._factorize(x).solve(b)
        if not np.all(np.isfinite(y)):
            raise NonConvergenceError("the adjoint/tangent solve returned non-finite values")
        return torch.from_numpy(y).to(device=x.device, dtype=x.dtype).view_as(x)

    def _solve_k_iterative(self, x: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
        """``K^-1 rhs`` (V, 3) by block-Jacobi CG (:func:`~torchgarment.sim.diff.solve_adjoint`), warm-started
        from the last adjoint; it stops at ``adjoint_rtol``, after ``adjoint_max_iterations`` iterations or at a
        direction of non-positive curvature (``K`` is the unprojected Hessian), returning the iterate reached."""
        warm = self._adjoint_warm if self._adjoint_warm is not None and self._adjoint_warm.shape == x.shape else None
        lam, info = solve_adjoint(self.model, x, rhs, AdjointLinearSolver.CG, rtol=self.adjoint_rtol,
                                  max_iterations=self.adjoint_max_iterations, x0=warm, require_convergence=False,
                                  assembler=self._assembler)
        self.adjoint_iterations += info.iterations
        self.last_adjoint_residual = info.relative_residual
        self._adjoint_warm = lam.detach().clone()
        return lam

    def _solve_adjoint(self, x: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
        if self.adjoint is AdjointSolve.ITERATIVE:
            return self._solve_k_iterative(x, rhs)
        return self._solve_k(x, rhs)

    def _pullback(self, q: torch.Tensor, x: torch.Tensor, p: torch.Tensor, gx: torch.Tensor, gp: torch.Tensor,
                  *, adjoint: bool = True) -> torch.Tensor:
        """``(dq)^T`` of a covector ``(gx (V,3), gp (V,2))`` on ``(x, p)``: adjoint solve + parametrization vjp
        (``adjoint=False``: the direct solve, as Gauss-Newton's products need exact adjoints)."""
        lam = self._solve_adjoint(x, gx) if adjoint else self._solve_k(x, gx)
        gp = gp + parameter_vjp(self.model, x, lam, {self.parameter: p})[self.parameter].to(gp.dtype)
        with torch.enable_grad():
            qr = q.detach().clone().requires_grad_(True)
            (gq,) = torch.autograd.grad(self.param(qr), qr, gp)
        return gq

    def evaluate(self, q: torch.Tensor, *, exact: bool, iterations: int | None = None, need_grad: bool = True
                 ) -> Evaluation:
        """Simulate and evaluate the objective (and its gradient) at ``q`` (B, 2).

        Args:
            q: (B, 2) boundary positions in metres.
            exact: exact solve (else ``iterations`` solver iterations).
            iterations: S of an inexact evaluation.
            need_grad: compute ``df/dq`` (one adjoint solve).
        """
        t0 = time.perf_counter()
        before = self.sim_iterations
        q = q.detach()
        x_before = self.x
        with torch.no_grad():
            p = self.param(q).detach()
        try:
            x = self.simulate(p, exact=exact, iterations=iterations)
        except (NonConvergenceError, NonFiniteError):
            self.x = x_before  # the next evaluation starts from the last good state
            raise
        self._hess_graph = None
        with torch.enable_grad():
            xr = x.clone().requires_grad_(True)
            pr = p.clone().requires_grad_(True)
            f = self.objective(xr, pr)
            if need_grad:
                gx, gp = torch.autograd.grad(f, (xr, pr), allow_unused=True)
                gx = torch.zeros_like(x) if gx is None else gx
                gp = torch.zeros_like(p) if gp is None else gp
        fval = float(f.detach())
        if not math.isfinite(fval):
            raise NonConvergenceError(f"the objective is not finite ({fval}) at the current pattern")
        gq = self._pullback(q, x, p, gx.detach(), gp.detach()) if need_grad else None
        info = self.last_info
        ev = Evaluation(fval, gq, bool(exact), self.sim_iterations - before,
                        info.residual if info is not None else math.nan, time.perf_counter() - t0)
        self.closure_evaluations += 1
        self.last, self.last_q, self.last_p, self.last_x = ev, q.clone(), p, x
        if exact:
            self.exact_evaluations += 1
            if fval < self.best_objective:
                self.best_objective, self.best_q, self.best_x = fval, q.clone(), x.clone()
        return ev

    def closure(self, q: torch.Tensor, *, exact: bool, iterations: int | None = None, need_grad: bool = True
                ) -> Callable[[], torch.Tensor]:
        """A ``torch.optim`` closure over the leaf ``q`` (B, 2): evaluates at ``q`` and writes ``q.grad``.

        The closure has attribute ``cacheable`` (True for exact closures: re-evaluating the same ``q`` gives the
        same value, so optimizers may reuse it).
        """

        def fn() -> torch.Tensor:
            ev = self.evaluate(q, exact=exact, iterations=iterations, need_grad=need_grad)
            if ev.grad is not None:
                q.grad = ev.grad.to(q.dtype).clone()
            return torch.tensor(ev.objective, dtype=q.dtype)

        fn.cacheable = bool(exact)  # type: ignore[attr-defined]
        return fn

    def term_values(self) -> dict[str, float]:
        """Each objective term's value at the last evaluation (empty if the objective does not report terms)."""
        if self.last_x is None or not hasattr(self.objective, "term_values"):
            return {}
        with torch.no_grad():
            return {k: float(v) for k, v in self.objective.term_values(self.last_x, self.last_p).items()}

    # ------------------------------------------------------------------ Gauss-Newton
    def _objective_gradient_graph(self):  # noqa: ANN202
        if self._hess_graph is None:
            with torch.enable_grad():
                xr = self.last_x.clone().requires_grad_(True)
                pr = self.last_p.clone().requires_grad_(True)
                f = self.objective(xr, pr)
                gx, gp = torch.autograd.grad(f, (xr, pr), create_graph=True, allow_unused=True)
            self._hess_graph = (xr, pr, gx, gp)
        return self._hess_graph

    def tangent(self, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(dx, dp) = (dx/dq v, dp/dq v)`` at the last evaluation: one tangent solve ``K dx = -(dg/dp) dp``.

        ``dp`` is the parametrization's difference quotient (Eq. 8 is affine in ``q``, so it is exact up to
        rounding); ``(d grad_x E / dp) dp`` is forward-over-reverse autograd of the stretch term.
        """
        if self.last_x is None:
            raise InputError("evaluate the problem before asking for Jacobian products")
        q, x, p = self.last_q, self.last_x, self.last_p
        scale = float(v.abs().max())
        if scale == 0.0:
            return torch.zeros_like(x), torch.zeros_like(p)
        t = 1e-2 / scale
        with torch.no_grad():
            dp = (self.param(q + t * v) - p) / t
        term, attr = self._term, self._attr

        def gx_of(pp: torch.Tensor) -> torch.Tensor:
            return func_grad(lambda xx: functional_call(term, {attr: pp}, (xx,)))(x)

        _, dg = func_jvp(gx_of, (p,), (dp.to(p.dtype),))
        dx = -self._solve_k(x, dg.detach())
        return dx, dp

    def gauss_newton_product(self, v: torch.Tensor) -> torch.Tensor:
        """``J^T H J v`` (B, 2) at the last evaluation: J = d(x, p)/dq (tangent solve), H = Hessian of the
        objective in ``(x, p)`` (autograd double backward; the SDF's curvature is dropped, which for a squared
        distance residual is exactly the Gauss-Newton term), then an adjoint solve back to ``q``.
        The simulator's second derivative (the first term of Eq. 20) is left out, as in Gauss-Newton."""
        dx, dp = self.tangent(v)
        xr, pr, gx, gp = self._objective_gradient_graph()
        with torch.enable_grad():
            s = (0.0 if gx is None else (gx * dx).sum()) + (0.0 if gp is None else (gp * dp).sum())
            hx, hp = torch.autograd.grad(s, (xr, pr), retain_graph=True, allow_unused=True)
        hx = torch.zeros_like(dx) if hx is None else hx.detach()
        hp = torch.zeros_like(dp) if hp is None else hp.detach()
        return self._pullback(self.last_q, self.last_x, self.last_p, hx, hp, adjoint=False)


# ---------------------------------------------------------------------------------------------- Algorithm 1
@dataclass
class InexactSettings:
    """Settings of :class:`InexactRunner` (Algorithm 1).

    Attributes:
        inner_iterations: initial ``S``, solver iterations per inexact outer iteration.
        exact_interval: ``M``, outer iterations between exact evaluations (paper: 32).
        inner_increase: factor on ``S`` when the objective fails to drop (long-range backtracking).
        inner_decrease: factor on ``S`` after a successful exact check (``S`` never goes below its initial value).
        step_decrease: factor on the step length (the optimizer's ``lr``) on failure.
        step_increase: factor on the step length on success (capped at ``max_step``).
        max_step: largest step length; None = the optimizer's initial ``lr``.
        max_inner_iterations: largest ``S``; when a failure happens at this ``S`` and the step is below
            ``min_step`` the run stops (converged as far as the strategy can tell).
        min_step: smallest step length.
        exact: evaluate exactly at every outer iteration (no S, no backtracking: the exact method).
    """

    inner_iterations: int = 4
    exact_interval: int = 32
    inner_increase: float = 2.0
    inner_decrease: float = 0.75
    step_decrease: float = 0.5
    step_increase: float = 1.25
    max_step: float | None = None
    max_inner_iterations: int = 256
    min_step: float = 1e-8
    exact: bool = False

    def validate(self) -> None:
        """Raise :class:`InputError` for out-of-range settings."""
        checks = [
            (self.inner_iterations >= 1, "inner_iterations must be >= 1"),
            (self.exact_interval >= 1, "exact_interval must be >= 1"),
            (self.inner_increase > 1.0 and 0.0 < self.inner_decrease <= 1.0, "inner factors out of range"),
            (0.0 < self.step_decrease < 1.0 and self.step_increase >= 1.0, "step factors out of range"),
            (self.max_inner_iterations >= self.inner_iterations, "max_inner_iterations < inner_iterations"),
            (self.min_step > 0 and (self.max_step is None or self.max_step > 0), "step bounds must be > 0"),
        ]
        for ok, msg in checks:
            if not ok:
                raise InputError(f"invalid InexactSettings: {msg}")


@dataclass
class IterationRecord:
    """What one outer iteration did (for logs, TensorBoard and metrics)."""

    iteration: int
    objective: float
    exact: bool
    inner_iterations: int
    step: float
    step_norm: float
    seconds: float
    closure_calls: int
    accepted: bool = True
    backtracked: bool = False


@dataclass
class RunResult:
    """Outcome of :meth:`InexactRunner.run`: the best exact iterate."""

    q: torch.Tensor
    x: torch.Tensor
    objective: float
    objective_start: float
    iterations: int
    backtracks: int
    records: list[IterationRecord] = field(default_factory=list)
    stopped: str = ""


class InexactRunner:
    """Algorithm 1 (see the module docstring) over an optimizer whose parameter is the leaf ``q`` (B, 2).

    The runner is resumable: :meth:`state_dict` / :meth:`load_state_dict` hold everything (the iterate, the
    optimizer state, the last exact checkpoint, ``S``, the step, counters).

    Args:
        problem: the :class:`AdjustProblem`.
        optimizer: an optimizer over ``[q]`` (its param group's ``lr`` is the step length ``s``).
        q: the leaf tensor (B, 2) the optimizer updates in place.
        settings: :class:`InexactSettings`.
    """

    def __init__(self, problem: AdjustProblem, optimizer: torch.optim.Optimizer, q: torch.Tensor,
                 settings: InexactSettings | None = None) -> None:
        self.problem, self.optimizer, self.q = problem, optimizer, q
        self.settings = settings if settings is not None else InexactSettings()
        self.settings.validate()
        self.S = int(self.settings.inner_iterations)
        self.max_step = float(self.settings.max_step if self.settings.max_step is not None
                              else optimizer.param_groups[0]["lr"])
        self.iteration = 0
        self.backtracks = 0
        self.since_check = 0
        self.restart = True
        self.start_objective: float | None = None
        self.checkpoint: dict | None = None
        self.records: list[IterationRecord] = []
        self.t_start = time.perf_counter()
        self.seconds_before = 0.0

    # ------------------------------------------------------------------ state
    @property
    def step_length(self) -> float:
        return float(self.optimizer.param_groups[0]["lr"])

    def _set_step(self, s: float) -> None:
        for g in self.optimizer.param_groups:
            g["lr"] = float(s)

    def _snapshot(self, q: torch.Tensor, f: float, x: torch.Tensor, opt_state: dict) -> dict:
        return {"q": q.detach().clone(), "objective": f, "x": x.detach().clone(), "optimizer": opt_state}

    def state_dict(self) -> dict:
        """Everything needed to resume (tensors and plain values; ``torch.save``-able)."""
        p = self.problem
        return {"q": self.q.detach().clone(), "x": p.x.clone(), "optimizer": copy.deepcopy(self.optimizer.state_dict()),
                "S": self.S, "step": self.step_length, "iteration": self.iteration, "backtracks": self.backtracks,
                "since_check": self.since_check, "restart": self.restart, "start_objective": self.start_objective,
                "checkpoint": copy.deepcopy(self.checkpoint), "records": [r.__dict__.copy() for r in self.records],
                "best_q": None if p.best_q is None else p.best_q.clone(),
                "best_x": None if p.best_x is None else p.best_x.clone(), "best_objective": p.best_objective,
                "closure_calls": getattr(self.optimizer, "closure_calls", 0),
                "seconds": self.seconds_before + time.perf_counter() - self.t_start}

    def load_state_dict(self, state: dict) -> None:
        """Resume from :meth:`state_dict`."""
        p = self.problem
        with torch.no_grad():
            self.q.copy_(state["q"])
        p.reset_state(state["x"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.S, self.iteration, self.backtracks = int(state["S"]), int(state["iteration"]), int(state["backtracks"])
        self._set_step(state["step"])
        self.since_check, self.restart = int(state["since_check"]), bool(state["restart"])
        self.start_objective, self.checkpoint = state["start_objective"], state["checkpoint"]
        self.records = [IterationRecord(**r) for r in state["records"]]
        p.best_q, p.best_x, p.best_objective = state["best_q"], state["best_x"], float(state["best_objective"])
        if hasattr(self.optimizer, "closure_calls"):
            self.optimizer.closure_calls = int(state["closure_calls"])
        self.seconds_before = float(state["seconds"])
        self.t_start = time.perf_counter()

    # ------------------------------------------------------------------ run
    def _needs_grad(self) -> bool:
        return bool(getattr(self.optimizer, "needs_gradient", True))

    def run(self, iterations: int, callback: Callable[[IterationRecord], None] | None = None) -> RunResult:
        """Run until ``iterations`` outer iterations have been done in total (discarded ones included).

        Args:
            iterations: total outer-iteration budget (counting those of earlier, resumed runs).
            callback: called with each :class:`IterationRecord`.

        Returns:
            The :class:`RunResult` with the best exactly evaluated iterate (never worse than the start).
        """
        st, p, q = self.settings, self.problem, self.q
        stopped = "iteration budget"
        if self.start_objective is None:
            budget = p.exact_settings
            # the first solve may start from a state that is not this pattern's equilibrium: a larger budget
            p.exact_settings = replace(budget, max_iterations=4 * budget.max_iterations)
            try:
                ev = p.evaluate(q, exact=True, need_grad=False)
            finally:
                p.exact_settings = budget
            self.start_objective = ev.objective
            self.checkpoint = self._snapshot(q, ev.objective, p.x, copy.deepcopy(self.optimizer.state_dict()))
        while self.iteration < iterations:
            exact_eval = st.exact or self.restart or self.since_check >= st.exact_interval
            compare = (not st.exact) and (not self.restart) and self.since_check >= st.exact_interval
            opt_before = copy.deepcopy(self.optimizer.state_dict()) if compare else None
            q_before = q.detach().clone()
            inner = p.closure(q, exact=exact_eval, iterations=None if exact_eval else self.S,
                              need_grad=self._needs_grad())
            first: dict[str, torch.Tensor] = {}

            def closure(inner=inner, first=first) -> torch.Tensor:  # noqa: ANN001 - keeps x of the first call
                out = inner()
                first.setdefault("x", p.x.clone())
                return out

            closure.cacheable = inner.cacheable  # type: ignore[attr-defined]
            calls_before = getattr(self.optimizer, "closure_calls", 0)
            loss = float(self.optimizer.step(closure))
            self.iteration += 1
            accepted, backtracked = True, False
            if compare:
                if loss < self.checkpoint["objective"]:
                    self.checkpoint = self._snapshot(q_before, loss, first["x"], opt_before)
                    self.S = max(st.inner_iterations, int(round(self.S * st.inner_decrease)))
                    self._set_step(min(self.max_step, self.step_length * st.step_increase))
                    self.since_check = 1
                else:  # long-range backtracking: back to the last exact iterate, more accuracy, shorter steps
                    accepted, backtracked = False, True
                    self.backtracks += 1
                    at_limit = self.S >= st.max_inner_iterations and self.step_length <= st.min_step
                    with torch.no_grad():
                        q.copy_(self.checkpoint["q"])
                    p.reset_state(self.checkpoint["x"])
                    # shrink the step actually taken (a step capped by a trust length is shorter than lr)
                    s_now = min(self.step_length, float(getattr(self.optimizer, "last_step_length", math.inf))
                                or self.step_length)
                    self.optimizer.load_state_dict(copy.deepcopy(self.checkpoint["optimizer"]))
                    self.S = min(st.max_inner_iterations, int(math.ceil(self.S * st.inner_increase)))
                    self._set_step(max(st.min_step, s_now * st.step_decrease))
                    self.restart = True
                    self.since_check = 0
                    if at_limit:
                        stopped = "no decrease at the finest accuracy and smallest step"
            elif self.restart and not st.exact:
                self.restart = False
                self.since_check = 1
            else:
                self.since_check += 1
            step_norm = float(torch.linalg.vector_norm(q.detach() - q_before))
            s_taken = float(getattr(self.optimizer, "last_step_length", self.step_length))
            rec = IterationRecord(self.iteration, loss, exact_eval, 0 if exact_eval else self.S, s_taken,
                                  step_norm, self.seconds_before + time.perf_counter() - self.t_start,
                                  getattr(self.optimizer, "closure_calls", 0) - calls_before, accepted, backtracked)
            self.records.append(rec)
            if callback is not None:
                callback(rec)
            if stopped != "iteration budget":
                break
        return self.finish(stopped)

    def finish(self, stopped: str = "") -> RunResult:
        """Evaluate the current iterate exactly and return the best exact iterate."""
        p, q = self.problem, self.q
        if p.last_q is None or not torch.equal(p.last_q, q.detach()) or not (p.last is not None and p.last.exact):
            budget = p.exact_settings
            # after inexact iterations the state can be far from equilibrium: a larger budget for this solve
            p.exact_settings = replace(budget, max_iterations=4 * budget.max_iterations)
            try:
                p.evaluate(q, exact=True, need_grad=False)
            except (NonConvergenceError, NonFiniteError):
                stopped = f"{stopped}; the last iterate could not be solved exactly".lstrip("; ")
            finally:
                p.exact_settings = budget
        assert p.best_q is not None and p.best_x is not None
        return RunResult(q=p.best_q.clone(), x=p.best_x.clone(), objective=p.best_objective,
                         objective_start=float(self.start_objective), iterations=self.iteration,
                         backtracks=self.backtracks, records=list(self.records), stopped=stopped)
