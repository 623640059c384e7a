"""Optimizers of the pattern parameters, each a ``torch.optim.Optimizer`` with ``step(closure)`` (Wang 2018,
sec. 7).

Every closure call is a cloth solve (and usually an adjoint solve), so every optimizer counts them in
``closure_calls``. Hyperparameters (``lr``, ``armijo_c``, ``backtrack``, ``max_backtracks``,
``max_displacement``, ...) live in the param groups (torch's ``defaults``); counters (``closure_calls``,
``failed_calls``, ``last_step_length``) and memories in ``state``, so ``state_dict()`` / ``load_state_dict()``
round-trip a run (a rollback to an earlier ``state_dict`` also rolls the counters back). A closure with
attribute ``cacheable = True`` (an exact evaluation, see
:meth:`~torchgarment.adjust.inexact.AdjustProblem.closure`) is not called again at the last two points it was
called at: their values and gradients are reused (the accepted line-search point, and the start point after a
failed line search; re-solving there from another warm start could find another equilibrium).

* :class:`PreconditionedGD` (``"pgd"``, the paper's method): ``q <- q - s P^-1 grad`` with ``P`` the constant
  approximate Hessian of the regularizers (:meth:`AdjustObjective.regularizer_hessian`), factorized once
  (:func:`~torchgarment.linalg.factorize`). With ``line_search=True`` the step ``s`` is found by Armijo
  backtracking (and grown after an accepted step); with ``False`` it is the fixed ``lr`` (Algorithm 1 controls
  it).
* :class:`LBFGS` (``"lbfgs"``): L-BFGS two-loop recursion with a trust-capped Armijo line search.
* :class:`GaussNewton` (``"gn"``): ``(J^T H J + R) d = -grad`` by preconditioned CG (``P = R``, Steihaug stop
  at negative curvature), products from :meth:`AdjustProblem.gauss_newton_product` (a tangent and an adjoint
  solve each), then Armijo backtracking.
* :class:`FixedPoint` (``"fixed-point"``): the fixed-point method of Bartle et al. 2016 as Wang 2018 implement
  it on a mass-spring model (section 8.1): no gradient; every spring's rest vector is scaled by
  ``|target edge| / |simulated edge|`` and the pattern is refit to these edge vectors in the least-squares
  sense; the boundary of the refit pattern becomes the new ``q``.

Example::

    opt = make_optimizer("pgd", [q], preconditioner=objective.regularizer_hessian())
    for _ in range(50):
        opt.step(problem.closure(q, exact=True))
    opt.closure_calls
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Protocol

import numpy as np
import scipy.sparse
import torch

from torchgarment.errors import InputError, NonConvergenceError, SingularMatrixError
from torchgarment.linalg import armijo_backtracking, factorize, pcg
from torchgarment.options import OptionEnum
from torchgarment.sim.solvers import NonFiniteError

Closure = Callable[[], torch.Tensor]
#: the regularizer Hessian (n, n): a scipy sparse matrix or a dense array, or None (identity)
PreconditionerMatrix = scipy.sparse.spmatrix | np.ndarray | None


class GaussNewtonProblem(Protocol):
    """What :class:`GaussNewton` needs of the problem (an
    :class:`~torchgarment.adjust.inexact.AdjustProblem`): ``gauss_newton_product(v (B, 2)) -> (B, 2)``."""

    def gauss_newton_product(self, v: torch.Tensor) -> torch.Tensor: ...


class FixedPointProblem(Protocol):
    """What :class:`FixedPoint` needs of the problem: the pattern ``last_p`` (V, 2) and simulation ``last_x``
    (V, 3) of the last call."""

    last_p: torch.Tensor
    last_x: torch.Tensor


class OptimizerKind(OptionEnum):
    """Optimizers by name."""

    PGD = "pgd"
    LBFGS = "lbfgs"
    GN = "gn"
    FIXED_POINT = "fixed-point"

    @classmethod
    def aliases(cls) -> dict[str, str]:
        return {"preconditioned": "pgd", "l-bfgs": "lbfgs", "gauss-newton": "gn",
                "fixed_point": "fixed-point",
                "fixedpoint": "fixed-point", "bartle": "fixed-point"}


def _flat_params(params: list[torch.Tensor]) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in params])


def _flat_grads(params: list[torch.Tensor]) -> torch.Tensor:
    return torch.cat([(torch.zeros_like(p) if p.grad is None else p.grad.detach()).reshape(-1)
                      for p in params])


def _set_flat(params: list[torch.Tensor], flat: torch.Tensor) -> None:
    k = 0
    with torch.no_grad():
        for p in params:
            n = p.numel()
            p.copy_(flat[k:k + n].view_as(p))
            k += n


class _Counting:
    """Mixin: counts closure calls (in ``state``) and reuses the last cacheable evaluation at an unchanged
    point."""

    _cache: list | None
    param_groups: list[dict]
    state: dict

    def _init_counting(self) -> None:
        self._cache = None

    def _counters(self) -> dict:
        """The state entry of the first parameter, which holds the counters."""
        return self.state[self._all_params()[0]]

    @property
    def closure_calls(self) -> int:
        """Closure calls (simulations) so far."""
        return int(self._counters().get("closure_calls", 0))

    @closure_calls.setter
    def closure_calls(self, value: int) -> None:
        self._counters()["closure_calls"] = int(value)

    @property
    def failed_calls(self) -> int:
        """Closure calls at which the simulator failed (counted as an infinite objective)."""
        return int(self._counters().get("failed_calls", 0))

    @failed_calls.setter
    def failed_calls(self, value: int) -> None:
        self._counters()["failed_calls"] = int(value)

    @property
    def last_step_length(self) -> float:
        """The step length ``t`` of the last step along the search direction (0 when it did not move)."""
        return float(self._counters().get("last_step_length", 0.0))

    @last_step_length.setter
    def last_step_length(self, value: float) -> None:
        self._counters()["last_step_length"] = float(value)

    def _all_params(self) -> list[torch.Tensor]:
        return [p for g in self.param_groups for p in g["params"]]  # type: ignore[attr-defined]

    def _counted(self, closure: Closure) -> Closure:
        cacheable = bool(getattr(closure, "cacheable", False))
        params = self._all_params()

        def fn() -> torch.Tensor:
            flat = _flat_params(params)
            for entry in (self._cache or []) if cacheable else []:
                if torch.equal(entry[0], flat):
                    _, loss, grads = entry
                    for p, g in zip(params, grads):
                        p.grad = None if g is None else g.clone()
                    return loss.clone()
            try:
                with torch.enable_grad():
                    loss = closure()
            except (NonConvergenceError, NonFiniteError):
                # a trial pattern the simulator cannot solve (e.g. a step far too long): an infinite objective
                # that line searches reject; the problem has restored its simulation state
                self.closure_calls += 1
                self.failed_calls += 1
                for p in params:
                    p.grad = torch.zeros_like(p)
                return torch.tensor(math.inf, dtype=params[0].dtype)
            self.closure_calls += 1
            loss_t = torch.as_tensor(loss).detach()
            if cacheable:  # the last two points: a failed line search returns to the one before the trials
                grads = [None if p.grad is None else p.grad.detach().clone() for p in params]
                entry = (flat, loss_t.clone(), grads)
                self._cache = ([entry] + list(self._cache or []))[:2]
            else:
                self._cache = None
            return loss_t

        return fn

    def _check_finite(self, loss: torch.Tensor) -> float:
        v = float(loss)
        if math.isnan(v):
            raise InputError("the objective is NaN at the current parameters")
        return v

    def _start(self, closure: Closure | None) -> tuple[Closure, list[torch.Tensor], torch.Tensor, float]:
        """Common start of a step: ``(counted closure, params, loss, float loss)`` at the current point.

        When the loss is infinite (the simulator failed here, see :meth:`_counted`) the caller must not move;
        ``last_step_length`` is then set to 0.
        """
        if closure is None:
            raise InputError(f"{type(self).__name__}.step needs a closure")
        fn = self._counted(closure)
        params = self._all_params()
        loss = fn()
        f0 = self._check_finite(loss)
        if not math.isfinite(f0):
            self.last_step_length = 0.0
        return fn, params, loss, f0


class _PrecondSolve:
    """``v -> P^-1 v`` with a sparse SPD ``P`` (n, n) factorized once (float64, CPU)."""

    def __init__(self, P: scipy.sparse.spmatrix, n: int) -> None:
        if not scipy.sparse.issparse(P) and not isinstance(P, np.ndarray):
            raise InputError(f"the preconditioner must be a scipy sparse matrix or an array, "
                             f"got {type(P).__name__}")
        P = scipy.sparse.csc_matrix(P, dtype=np.float64)
        if P.shape != (n, n):
            raise InputError(f"the preconditioner must be ({n}, {n}) for {n} parameters, got {P.shape}")
        try:
            self.lu = factorize(P, symmetric=False, what="preconditioner")
        except SingularMatrixError as exc:
            raise InputError(f"the preconditioner is singular ({exc}); the fixing regularizer keeps it "
                             f"positive definite: give it a positive weight") from exc
        self.P = P

    def solve(self, v: torch.Tensor) -> torch.Tensor:
        y = self.lu.solve(v.detach().to("cpu", torch.float64).numpy())
        return torch.from_numpy(y).to(device=v.device, dtype=v.dtype)

    def matvec(self, v: torch.Tensor) -> torch.Tensor:
        y = self.P @ v.detach().to("cpu", torch.float64).numpy()
        return torch.from_numpy(y).to(device=v.device, dtype=v.dtype)


def _trust(t: float, d: torch.Tensor, max_displacement: float | None) -> float:
    """``t`` capped so that no parameter moves more than ``max_displacement`` (metres) along ``d``."""
    dmax = float(d.abs().max()) if d.numel() else 0.0
    if dmax == 0.0:
        return 0.0 if math.isinf(t) else t
    if max_displacement is None:
        return t
    return min(t, max_displacement / dmax)


def _line_search(fn: Closure, params: list[torch.Tensor], x0: torch.Tensor, f0: float, g0: torch.Tensor,
                 d: torch.Tensor, t: float, group: dict) -> tuple[float, bool]:
    """Armijo backtracking along ``d`` from ``x0`` with the group's ``armijo_c``, ``backtrack`` and
    ``max_backtracks``: ``(t, accepted)``, the parameters left at ``x0 + t d``; on failure ``t`` is the last
    tried step and the parameters are restored to ``x0``."""

    def f(alpha: float) -> float:
        _set_flat(params, x0 + alpha * d)
        return float(fn())

    t, _, ok = armijo_backtracking(f, f0, float(torch.dot(g0, d)), t, armijo_c=group["armijo_c"],
                                   backtrack=group["backtrack"], max_backtracks=group["max_backtracks"])
    if not ok:
        _set_flat(params, x0)
    return t, ok


def _check_line_search(armijo_c: float, backtrack: float, max_backtracks: int,
                       max_displacement: float | None) -> None:
    if not (0.0 < armijo_c < 1.0 and 0.0 < backtrack < 1.0 and max_backtracks >= 1):
        raise InputError(f"the line search needs armijo_c and backtrack in (0, 1) and max_backtracks >= 1, "
                         f"got {armijo_c}, {backtrack}, {max_backtracks}")
    if max_displacement is not None and not max_displacement > 0:
        raise InputError(f"max_displacement must be > 0 or None, got {max_displacement}")


class PreconditionedGD(_Counting, torch.optim.Optimizer):
    """Preconditioned gradient descent ``q <- q - s P^-1 grad`` (the paper's method; see the module
    docstring).

    Args:
        params: the parameters (usually ``[q]``, q (B, 2)); flattened in order, so ``P`` is (n, n) over them.
        preconditioner: sparse SPD (n, n), e.g. :meth:`AdjustObjective.regularizer_hessian`; None = identity
            (plain gradient descent).
        lr: the step length ``s`` (initial trial step with a line search).
        line_search: Armijo backtracking (True) or the fixed step ``lr`` (False, one closure call per step).
        armijo_c: sufficient-decrease constant. backtrack: backtracking factor. grow: ``lr`` factor after an
            accepted step (line search only). max_backtracks: trials per step.
        max_displacement: trust length in metres: no parameter moves more than this per step (None: no cap).
    """

    needs_gradient = True

    def __init__(self, params: Iterable[torch.Tensor], preconditioner: PreconditionerMatrix = None, *,
                 lr: float = 1.0, line_search: bool = True, armijo_c: float = 1e-4, backtrack: float = 0.5,
                 grow: float = 2.0, max_backtracks: int = 20, max_displacement: float | None = 0.01) -> None:
        if not lr > 0:
            raise InputError(f"lr must be > 0, got {lr}")
        if math.isinf(lr) and max_displacement is None:
            raise InputError("an unbounded step (lr = inf) needs a trust length max_displacement")
        _check_line_search(armijo_c, backtrack, max_backtracks, max_displacement)
        super().__init__(params, {
            "lr": float(lr), "line_search": bool(line_search), "armijo_c": float(armijo_c),
            "backtrack": float(backtrack), "grow": float(grow), "max_backtracks": int(max_backtracks),
            "max_displacement": None if max_displacement is None else float(max_displacement)})
        self._init_counting()
        n = sum(p.numel() for p in self._all_params())
        self.precond = None if preconditioner is None else _PrecondSolve(preconditioner, n)

    def direction(self, g: torch.Tensor) -> torch.Tensor:
        """``-P^-1 g``."""
        return -(g if self.precond is None else self.precond.solve(g))

    @torch.no_grad()
    def step(self, closure: Closure) -> torch.Tensor:  # type: ignore[override]
        """One iteration; returns the objective at the starting point."""
        fn, params, loss, f0 = self._start(closure)
        if not math.isfinite(f0):  # the simulator failed here (see _counted): no direction, no move
            return loss
        g = _flat_grads(params)
        d = self.direction(g)
        x0 = _flat_params(params)
        group = self.param_groups[0]
        t0 = _trust(group["lr"], d, group["max_displacement"])
        if not group["line_search"]:
            _set_flat(params, x0 + t0 * d)
            self.last_step_length = t0
            return loss
        if float(torch.dot(g, d)) >= 0.0:
            self.last_step_length = 0.0
            return loss
        t, ok = _line_search(fn, params, x0, f0, g, d, t0, group)
        self.last_step_length = t if ok else 0.0
        group["lr"] = t * group["grow"] if ok else t * group["backtrack"]
        return loss


class LBFGS(_Counting, torch.optim.Optimizer):
    """L-BFGS (torch.optim.LBFGS's two-loop recursion and curvature-pair memory) with a safeguarded line
    search.

    torch's strong-Wolfe search extrapolates trial steps up to 10x, far outside what a cloth solve starting
    from the previous equilibrium can follow; here every trial is capped so that no parameter moves more than
    ``max_displacement`` metres, and the step is accepted by Armijo backtracking. The initial inverse Hessian
    is ``(s^T y / y^T y) I`` (torch's scaling) or, with a preconditioner ``P`` (the regularizer Hessian, as
    the paper combines L-BFGS with its preconditioning), ``(s^T y / y^T P^-1 y) P^-1``; the first iteration is
    a (preconditioned) gradient step of length ``max_displacement``. A curvature pair is kept only when
    ``s^T y > 1e-10 |s| |y|``.

    Args:
        params: the parameters. preconditioner: sparse SPD (n, n) or None.
        lr: initial trial step (1 = the quasi-Newton step). history_size: memory.
        max_displacement: trust length in metres (None = no cap). armijo_c, backtrack, max_backtracks: line
            search.
    """

    needs_gradient = True

    def __init__(self, params: Iterable[torch.Tensor], preconditioner: PreconditionerMatrix = None, *,
                 lr: float = 1.0, history_size: int = 10, max_displacement: float | None = 0.01,
                 armijo_c: float = 1e-4, backtrack: float = 0.5, max_backtracks: int = 20) -> None:
        if not lr > 0 or history_size < 1:
            raise InputError("LBFGS needs lr > 0 and history_size >= 1")
        _check_line_search(armijo_c, backtrack, max_backtracks, max_displacement)
        super().__init__(params, {
            "lr": float(lr), "history_size": int(history_size), "armijo_c": float(armijo_c),
            "backtrack": float(backtrack), "max_backtracks": int(max_backtracks),
            "max_displacement": None if max_displacement is None else float(max_displacement)})
        self._init_counting()
        n = sum(p.numel() for p in self._all_params())
        self.precond = None if preconditioner is None else _PrecondSolve(preconditioner, n)

    def _memory(self) -> dict:
        return self.state[self._all_params()[0]]

    def _direction(self, g: torch.Tensor, mem: dict) -> torch.Tensor:
        S, Y = mem.get("s", []), mem.get("y", [])
        h0 = (lambda v: v) if self.precond is None else self.precond.solve  # noqa: E731
        if not S:
            pg = h0(g)
            gm = float(pg.abs().max())
            max_displacement = self.param_groups[0]["max_displacement"]
            scale = (max_displacement / gm) if (max_displacement is not None and gm > 0) else 1.0 / max(
                float(pg.abs().sum()), 1e-300)
            return -scale * pg
        qv = g.clone()
        alphas = []
        for s_, y_ in zip(reversed(S), reversed(Y)):
            rho = 1.0 / float(torch.dot(y_, s_))
            a = rho * float(torch.dot(s_, qv))
            alphas.append((a, rho))
            qv = qv - a * y_
        gamma = float(torch.dot(S[-1], Y[-1])) / float(torch.dot(Y[-1], h0(Y[-1])))
        r = gamma * h0(qv)
        for (s_, y_), (a, rho) in zip(zip(S, Y), reversed(alphas)):
            b = rho * float(torch.dot(y_, r))
            r = r + (a - b) * s_
        return -r

    @torch.no_grad()
    def step(self, closure: Closure) -> torch.Tensor:  # type: ignore[override]
        """One L-BFGS iteration with Armijo backtracking; returns the objective at the starting point."""
        fn, params, loss, f0 = self._start(closure)
        if not math.isfinite(f0):  # the simulator failed here (see _counted): no direction, no move
            return loss
        g = _flat_grads(params)
        x0 = _flat_params(params)
        mem = self._memory()
        group = self.param_groups[0]
        if "x_prev" in mem:
            s_, y_ = x0 - mem["x_prev"], g - mem["g_prev"]
            sy = float(torch.dot(s_, y_))
            if sy > 1e-10 * float(torch.linalg.vector_norm(s_)) * float(torch.linalg.vector_norm(y_)):
                mem.setdefault("s", []).append(s_)
                mem.setdefault("y", []).append(y_)
                if len(mem["s"]) > group["history_size"]:
                    mem["s"].pop(0)
                    mem["y"].pop(0)
        d = self._direction(g, mem)
        if float(torch.dot(g, d)) >= 0.0:  # lost curvature information: restart from the gradient
            mem["s"], mem["y"] = [], []
            d = self._direction(g, mem)
        mem["x_prev"], mem["g_prev"] = x0.clone(), g.clone()
        t0 = _trust(group["lr"], d, group["max_displacement"])
        t, ok = _line_search(fn, params, x0, f0, g, d, t0, group)
        self.last_step_length = t if ok else 0.0
        return loss


class GaussNewton(_Counting, torch.optim.Optimizer):
    """Gauss-Newton with CG on ``J^T H J + R`` (module docstring); needs the problem's Jacobian products.

    Args:
        params: ``[q]``.
        problem: an object with ``gauss_newton_product(v (B, 2)) -> (B, 2)`` valid at the point of the last
            closure call (:class:`~torchgarment.adjust.inexact.AdjustProblem`).
        preconditioner: the regularizer Hessian ``R`` (n, n) sparse SPD: added to the system (it is part of
            the objective but the products of the problem only hold the costs when ``include_regularizer``),
            and used as CG's preconditioner.
        include_regularizer: add ``R v`` to each product. The problem's products already hold the regularizers
            when they are part of the objective module; then keep False.
        lr: initial trial step. cg_iterations: CG budget per step (each a tangent + adjoint solve).
        cg_rtol: CG relative residual tolerance. armijo_c, backtrack, max_backtracks: line search.
        max_displacement: trust length in metres (None = no cap).
    """

    needs_gradient = True

    def __init__(self, params: Iterable[torch.Tensor], problem: GaussNewtonProblem,
                 preconditioner: PreconditionerMatrix = None, *, include_regularizer: bool = False,
                 lr: float = 1.0, cg_iterations: int = 10, cg_rtol: float = 1e-2, armijo_c: float = 1e-4,
                 backtrack: float = 0.5, max_backtracks: int = 20,
                 max_displacement: float | None = 0.01) -> None:
        _check_line_search(armijo_c, backtrack, max_backtracks, max_displacement)
        super().__init__(params, {
            "lr": float(lr), "cg_iterations": int(cg_iterations), "cg_rtol": float(cg_rtol),
            "armijo_c": float(armijo_c), "backtrack": float(backtrack), "max_backtracks": int(max_backtracks),
            "max_displacement": None if max_displacement is None else float(max_displacement)})
        self._init_counting()
        if not hasattr(problem, "gauss_newton_product"):
            raise InputError("GaussNewton needs a problem with gauss_newton_product(v)")
        self.problem = problem
        n = sum(p.numel() for p in self._all_params())
        self.precond = None if preconditioner is None else _PrecondSolve(preconditioner, n)
        if include_regularizer and self.precond is None:
            raise InputError("include_regularizer needs the regularizer Hessian as preconditioner")
        self.include_regularizer = bool(include_regularizer)

    @property
    def last_cg_iterations(self) -> int:
        """CG iterations of the last step."""
        return int(self._counters().get("last_cg_iterations", 0))

    def _product(self, v: torch.Tensor, shape: torch.Size) -> torch.Tensor:
        hv = self.problem.gauss_newton_product(v.view(shape)).reshape(-1).to(v.dtype)
        if self.include_regularizer:
            hv = hv + self.precond.matvec(v)
        return hv

    def _cg(self, g: torch.Tensor, shape: torch.Size) -> torch.Tensor:
        """Preconditioned CG for ``A d = -g``, stopped at negative curvature (Steihaug), ``cg_rtol`` or the
        budget;
        a zero direction when the first direction already has non-positive curvature (the caller then takes
        the preconditioned steepest descent)."""
        group = self.param_groups[0]
        pre = None if self.precond is None else self.precond.solve
        d, k, _ = pcg(lambda v: self._product(v, shape), -g, pre, group["cg_rtol"], group["cg_iterations"],
                      stop_at_negative_curvature=True)
        self._counters()["last_cg_iterations"] = k
        return d

    @torch.no_grad()
    def step(self, closure: Closure) -> torch.Tensor:  # type: ignore[override]
        """One Gauss-Newton step with Armijo backtracking; returns the objective at the starting point."""
        if closure is None:
            raise InputError("GaussNewton.step needs a closure")
        fn = self._counted(closure)
        params = self._all_params()
        if len(params) != 1:
            raise InputError("GaussNewton optimizes a single parameter tensor q")
        loss = fn()
        last_q = getattr(self.problem, "last_q", None)
        if last_q is not None and not torch.equal(last_q, params[0].detach()):
            # a cached value: the problem's linearization is at another point; evaluate here again
            self._cache = None
            loss = fn()
        f0 = self._check_finite(loss)
        if not math.isfinite(f0):  # the simulator failed here (see _counted): no direction, no move
            self.last_step_length = 0.0
            return loss
        g = _flat_grads(params)
        d = self._cg(g, params[0].shape)
        if float(torch.dot(g, d)) >= 0.0:
            d = -(g if self.precond is None else self.precond.solve(g))
        x0 = _flat_params(params)
        group = self.param_groups[0]
        t0 = _trust(group["lr"], d, group["max_displacement"])
        t, ok = _line_search(fn, params, x0, f0, g, d, t0, group)
        self.last_step_length = t if ok else 0.0
        return loss


class FixedPoint(_Counting, torch.optim.Optimizer):
    """The fixed-point pattern update of Bartle et al. 2016 (the baseline of Wang 2018, section 8.1).

    Each step simulates the current pattern (one closure call, no gradient needed), scales every pattern edge
    ``e = p_j - p_i`` by ``r_e = |x~_j - x~_i| / |x_j - x_i|`` (target over simulated 3D length: a spring
    stretched too much in the simulation gets a longer rest length), and refits the whole pattern to the
    scaled edge vectors: ``p' = argmin sum_e |p'_j - p'_i - r_e e|^2 + eps |p' - p|^2`` (a graph Laplacian
    system, factorized once). The update is relaxed by ``lr``: ``q <- q + lr (p'_B - q)``.

    Args:
        params: ``[q]`` (B, 2).
        problem: an object with ``last_x`` (V, 3) and ``last_p`` (V, 2) of the last closure call.
        edges: (E, 2) long pattern edges (the springs).
        boundary_index: (B,) long pattern vertex of each row of ``q``.
        x_target: (V, 3) target garment in metres (the transferred garment of the positional cost).
        lr: relaxation in (0, 1]. eps: anchoring weight (relative) that fixes the translation null space.
    """

    needs_gradient = False

    def __init__(self, params: Iterable[torch.Tensor], problem: FixedPointProblem, edges: torch.Tensor,
                 boundary_index: torch.Tensor, x_target: torch.Tensor, *, lr: float = 1.0,
                 eps: float = 1e-6) -> None:
        if not 0.0 < lr <= 1.0:
            raise InputError(f"FixedPoint lr (relaxation) must lie in (0, 1], got {lr}")
        super().__init__(params, {"lr": float(lr)})
        self._init_counting()
        self.problem = problem
        e = edges.detach().cpu().numpy().astype(np.int64)
        V = int(x_target.shape[0])
        if e.ndim != 2 or e.shape[1] != 2 or (e.size and (e.min() < 0 or e.max() >= V)):
            raise InputError(f"edges must be (E, 2) vertex indices below {V}")
        self.edges = edges.detach().to(torch.long)
        self.boundary_index = boundary_index.detach().to(torch.long)
        self.x_target = x_target.detach()
        E = e.shape[0]
        D = scipy.sparse.csr_matrix((np.r_[np.ones(E), -np.ones(E)],
                                     (np.r_[np.arange(E), np.arange(E)], np.r_[e[:, 1], e[:, 0]])),
                                    shape=(E, V))
        self.D = D
        self.eps = float(eps) * float(np.mean(np.asarray((D.T @ D).diagonal())))
        self.lu = factorize((D.T @ D + self.eps * scipy.sparse.eye(V)).tocsc(), symmetric=False,
                            what="fixed-point refit Laplacian")

    def refit(self, p: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """The refit pattern p' (V, 2) for the current pattern ``p`` (V, 2) and simulation ``x`` (V, 3)."""
        i, j = self.edges[:, 0], self.edges[:, 1]
        dev, dt = p.device, p.dtype
        xt = self.x_target.to(device=dev, dtype=dt)
        lt = torch.linalg.vector_norm(xt[j] - xt[i], dim=1)
        ls = torch.linalg.vector_norm(x[j] - x[i], dim=1).clamp_min(torch.finfo(dt).tiny)
        target = ((p[j] - p[i]) * (lt / ls)[:, None]).to("cpu", torch.float64).numpy()
        rhs = self.D.T @ target + self.eps * p.detach().to("cpu", torch.float64).numpy()
        return torch.from_numpy(self.lu.solve(rhs)).to(device=dev, dtype=dt)

    @torch.no_grad()
    def step(self, closure: Closure) -> torch.Tensor:  # type: ignore[override]
        """One fixed-point update; returns the objective at the starting point."""
        if closure is None:
            raise InputError("FixedPoint.step needs a closure")
        params = self._all_params()
        if len(params) != 1:
            raise InputError("FixedPoint optimizes a single parameter tensor q")
        q = params[0]
        group = self.param_groups[0]
        loss = self._counted(closure)()
        if not math.isfinite(float(loss)):
            # the last update gave a pattern the simulator cannot solve: go back to the previous pattern
            # (whose simulation is still the problem's last one) and halve the relaxation
            prev = self.state[q].get("q_prev")
            if prev is None or group["lr"] < 1e-3:
                raise InputError("the fixed-point iteration reached patterns the simulator cannot solve")
            q.copy_(prev)
            group["lr"] *= 0.5
            loss = self.state[q]["f_prev"].clone()
        self.state[q]["q_prev"], self.state[q]["f_prev"] = q.detach().clone(), loss.detach().clone()
        p_new = self.refit(self.problem.last_p, self.problem.last_x)
        q_new = p_new[self.boundary_index.to(p_new.device)]
        q.add_(group["lr"] * (q_new.to(q.dtype) - q))
        return loss


def make_optimizer(kind: "str | OptimizerKind", params: list[torch.Tensor], *,
                   preconditioner: PreconditionerMatrix = None,
                   problem: GaussNewtonProblem | FixedPointProblem | None = None, lr: float | None = None,
                   line_search: bool = True, max_displacement: float | None = 0.01,
                   edges: torch.Tensor | None = None, boundary_index: torch.Tensor | None = None,
                   x_target: torch.Tensor | None = None) -> torch.optim.Optimizer:
    """Build an optimizer by name (:class:`OptimizerKind`).

    Args:
        kind: ``"pgd"``, ``"lbfgs"``, ``"gn"`` or ``"fixed-point"``.
        params: ``[q]``.
        preconditioner: regularizer Hessian (pgd, gn).
        problem: the :class:`AdjustProblem` (gn, fixed-point).
        lr: step length / relaxation (default 1).
        line_search: pgd's Armijo line search (False inside Algorithm 1).
        max_displacement: trust length in metres of pgd, lbfgs and gn (None: no cap).
        edges, boundary_index, x_target: fixed-point's pattern edges, boundary map and target garment.
    """
    k = OptimizerKind.resolve(kind)
    lr = 1.0 if lr is None else float(lr)
    if math.isinf(lr) and k != OptimizerKind.PGD:
        lr = 1.0
    if k == OptimizerKind.PGD:
        return PreconditionedGD(params, preconditioner, lr=lr, line_search=line_search,
                                max_displacement=max_displacement)
    if k == OptimizerKind.LBFGS:
        return LBFGS(params, preconditioner, lr=lr, max_displacement=max_displacement)
    if k == OptimizerKind.GN:
        if problem is None:
            raise InputError("the gn optimizer needs the problem (for Jacobian products)")
        return GaussNewton(params, problem, preconditioner, lr=lr, max_displacement=max_displacement)
    if problem is None or edges is None or boundary_index is None or x_target is None:
        raise InputError("the fixed-point optimizer needs problem, edges, boundary_index and x_target")
    return FixedPoint(params, problem, edges, boundary_index, x_target, lr=min(lr, 1.0))


__all__ = ["FixedPoint", "GaussNewton", "LBFGS", "OptimizerKind", "PreconditionedGD", "make_optimizer"]
