"""Optimizers of torchgarment.adjust.optimizers: each reduces the objective of a small simulated inverse
problem (a hanging sheet whose target is the equilibrium of a 5 % larger pattern), closure calls are counted
and cached, name resolution, Gauss-Newton products against finite differences, the adjoint gradient against
finite differences."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from adjust_standin import EXACT, problem_parts  # noqa: E402

from torchgarment.adjust.inexact import AdjustProblem, InexactRunner, InexactSettings  # noqa: E402
from torchgarment.adjust.optimizers import (  # noqa: E402
    LBFGS,
    FixedPoint,
    GaussNewton,
    OptimizerKind,
    PreconditionedGD,
    make_optimizer,
)
from torchgarment.errors import InputError  # noqa: E402
from torchgarment.sim.solvers import SolveSettings  # noqa: E402


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _setup(kind: str):
    model, param, obj, x0, q0, mesh = problem_parts()
    prob = AdjustProblem(model, param, obj, x0, exact_settings=EXACT)
    q = q0.clone().requires_grad_(True)
    opt = make_optimizer(kind, [q], preconditioner=obj.regularizer_hessian(), problem=prob, edges=mesh.edges,
                         boundary_index=param.boundary_index, x_target=obj.x_target)
    return prob, q, opt


# measured (float64, 7x7 sheet, 10 exact outer iterations): start 35.12;
# pgd 10.6 (34 calls), lbfgs 4.4 (16), gn 0.39 (14), fixed-point 0.92 (10)
@pytest.mark.parametrize("kind,ratio", [("pgd", 0.5), ("lbfgs", 0.5), ("gn", 0.05), ("fixed-point", 0.1)])
def test_each_optimizer_reduces_the_objective(kind, ratio):
    prob, q, opt = _setup(kind)
    run = InexactRunner(prob, opt, q, InexactSettings(exact=True)).run(10)
    assert run.objective < ratio * run.objective_start
    assert opt.closure_calls >= 10  # one call per iteration at least
    # every counted call is one simulation; the runner adds the exact evaluations at the start and the end
    assert opt.closure_calls <= prob.closure_evaluations <= opt.closure_calls + 2
    if kind == "fixed-point":
        assert opt.closure_calls == 10  # one simulation per step, no line search
        assert prob.last.grad is None  # the baseline needs no gradient


def test_names_resolve_and_types():
    assert OptimizerKind.resolve("Gauss-Newton") is OptimizerKind.GN
    assert OptimizerKind.resolve("bartle") is OptimizerKind.FIXED_POINT
    with pytest.raises(InputError, match="expected one of"):
        OptimizerKind.resolve("adam")
    kinds = [("pgd", PreconditionedGD), ("lbfgs", LBFGS), ("gn", GaussNewton), ("fixed-point", FixedPoint)]
    for kind, cls in kinds:
        _, _, opt = _setup(kind)
        assert isinstance(opt, cls) and isinstance(opt, torch.optim.Optimizer)
    q = torch.zeros(3, 2, requires_grad=True)
    with pytest.raises(InputError, match="needs the problem"):
        make_optimizer("gn", [q])
    with pytest.raises(InputError, match=r"\(6, 6\)"):
        PreconditionedGD([q], torch.eye(4).numpy())


def test_closure_calls_counted_and_cached_for_exact_closures():
    """PGD without line search: one call per step; exact closures at an unchanged point are reused."""
    calls = []

    def quad_closure(q):
        def fn():
            calls.append(1)
            f = ((q - 1.0) ** 2).sum()
            q.grad = torch.autograd.grad(f, q)[0]
            return f.detach()
        fn.cacheable = True
        return fn

    q = torch.zeros(4, 2, dtype=torch.float64, requires_grad=True)
    opt = PreconditionedGD([q], None, lr=0.25, line_search=False, max_displacement=None)
    for _ in range(5):
        opt.step(quad_closure(q))
    assert opt.closure_calls == 5 and len(calls) == 5
    assert torch.allclose(q.detach(), torch.full((4, 2), 1 - 0.5**5, dtype=torch.float64))
    # L-BFGS on the same quadratic: the accepted line-search point is not evaluated twice
    q2 = torch.zeros(4, 2, dtype=torch.float64, requires_grad=True)
    lb = LBFGS([q2], max_displacement=None)
    calls.clear()
    for _ in range(3):
        lb.step(quad_closure(q2))
    assert lb.closure_calls == len(calls)
    assert float(((q2.detach() - 1) ** 2).sum()) < 1e-12


def test_adjoint_gradient_matches_finite_differences():
    prob, q, _ = _setup("pgd")
    q0 = q.detach()
    ev = prob.evaluate(q0, exact=True)
    gen = torch.Generator().manual_seed(0)
    v = torch.randn(q0.shape, generator=gen, dtype=q0.dtype)
    h = 1e-5
    fp = prob.evaluate(q0 + h * v, exact=True, need_grad=False).objective
    fm = prob.evaluate(q0 - h * v, exact=True, need_grad=False).objective
    fd = (fp - fm) / (2 * h)
    assert abs(float((ev.grad * v).sum()) - fd) <= 1e-3 * abs(fd) + 1e-6


def test_tangent_matches_finite_differences_and_gn_product_is_symmetric():
    model, param, obj, x0, q0, _ = problem_parts()
    prob = AdjustProblem(model, param, obj, x0,
                         exact_settings=SolveSettings(rtol=0, atol=3e-9, max_iterations=300))
    prob.evaluate(q0, exact=True)
    x0 = prob.last_x.clone()
    gen = torch.Generator().manual_seed(1)
    v = torch.randn(q0.shape, generator=gen, dtype=q0.dtype) * 1e-3
    dx, _ = prob.tangent(v)
    h = 1e-3
    xp = prob.simulate(prob.param(q0 + h * v), exact=True).clone()
    prob.reset_state(x0)
    xm = prob.simulate(prob.param(q0 - h * v), exact=True).clone()
    fd = (xp - xm) / (2 * h)
    # measured: 8e-5 relative at h = 1e-3 (1e-2 at h = 1e-2: the FD error, O(h^2))
    assert float(torch.linalg.vector_norm(dx - fd)) <= 1e-3 * float(torch.linalg.vector_norm(fd))
    prob.reset_state(x0)
    prob.evaluate(q0, exact=True)
    w = torch.randn(q0.shape, generator=gen, dtype=q0.dtype) * 1e-3
    a = float((w * prob.gauss_newton_product(v)).sum())
    b = float((v * prob.gauss_newton_product(w)).sum())
    assert abs(a - b) <= 1e-6 * max(abs(a), abs(b))
    assert float((v * prob.gauss_newton_product(v)).sum()) > 0.0


def test_hyperparameters_in_param_groups_and_counters_in_state_round_trip() -> None:
    def quad_closure(q: torch.Tensor) -> Callable[[], torch.Tensor]:
        def fn() -> torch.Tensor:
            f = ((q - 1.0) ** 2).sum()
            q.grad = torch.autograd.grad(f, q)[0]
            return f.detach()
        return fn

    q = torch.zeros(4, 2, dtype=torch.float64, requires_grad=True)
    opt = make_optimizer("lbfgs", [q], max_displacement=0.2)
    group = opt.param_groups[0]
    assert group["max_displacement"] == 0.2 and group["armijo_c"] == 1e-4 and group["backtrack"] == 0.5
    for _ in range(3):
        opt.step(quad_closure(q))
    state = opt.state_dict()
    q2 = q.detach().clone().requires_grad_(True)
    other = LBFGS([q2], max_displacement=None)
    other.load_state_dict(state)
    assert other.param_groups[0]["max_displacement"] == 0.2
    assert other.closure_calls == opt.closure_calls > 0 and other.last_step_length == opt.last_step_length
    assert other.failed_calls == 0
    with pytest.raises(InputError, match="max_displacement"):
        PreconditionedGD([q], None, max_displacement=-1.0)
