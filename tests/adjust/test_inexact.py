"""Algorithm 1 (torchgarment.adjust.inexact.InexactRunner): the returned pattern comes from an exact solve and
is never worse than the start; long-range backtracking raises S, shrinks the step and goes back to the last
exact iterate; the run is resumable from its state_dict."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from adjust_standin import EXACT, problem_parts  # noqa: E402

from torchgarment.adjust.inexact import AdjustProblem, InexactRunner, InexactSettings  # noqa: E402
from torchgarment.adjust.optimizers import PreconditionedGD  # noqa: E402
from torchgarment.errors import InputError  # noqa: E402


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _runner(step: float = 1.0, max_move: float | None = 0.01, S: int = 1, M: int = 4, solver: str = "newton"):
    model, param, obj, x0, q0, _ = problem_parts()
    prob = AdjustProblem(model, param, obj, x0, exact_settings=EXACT, inexact_solver=solver)
    q = q0.clone().requires_grad_(True)
    opt = PreconditionedGD([q], obj.regularizer_hessian(), lr=step, line_search=False,
                           max_displacement=max_move)
    return prob, q, InexactRunner(prob, opt, q, InexactSettings(inner_iterations=S, exact_interval=M))


def test_result_is_exact_and_better_than_start():
    prob, q, runner = _runner()
    res = runner.run(24)
    # measured: 35.1 -> ~12 in 24 iterations (S = 1 Newton step)
    assert res.objective < 0.9 * res.objective_start
    # the reported garment is an equilibrium of the returned pattern (an exact solve from it does not move it)
    # and the reported objective is its objective
    prob.reset_state(res.x)
    x = prob.simulate(prob.param(res.q), exact=True)
    assert prob.last_info.iterations <= 1
    assert float((x - res.x).abs().max()) < 1e-6
    f = prob.objective(x, prob.param(res.q)).item()
    assert f == pytest.approx(res.objective, rel=1e-5, abs=1e-9)
    assert any(not r.exact for r in res.records) and any(r.exact for r in res.records)
    assert max(r.inner_iterations for r in res.records) >= 1


def test_never_worse_than_start_with_a_diverging_step():
    """Absurd steps (no trust cap) make every inexact phase worse: backtracking must raise S, shrink the step
    and the result must still be the start (or better), from an exact solve."""
    prob, q, runner = _runner(step=50.0, max_move=None, M=2)
    res = runner.run(16)
    assert res.backtracks >= 1
    backs = [r for r in res.records if r.backtracked]
    assert backs and all(not r.accepted for r in backs)
    assert runner.S > 1 and runner.step_length < 50.0
    assert res.objective <= res.objective_start
    assert prob.best_q is not None and torch.equal(prob.best_q, res.q)


def test_resume_from_state_dict_continues_identically():
    prob_a, q_a, run_a = _runner()
    run_a.run(6)
    state = run_a.state_dict()
    res_a = run_a.run(12)
    prob_b, q_b, run_b = _runner()
    run_b.load_state_dict(state)
    res_b = run_b.run(12)
    assert res_b.iterations == res_a.iterations == 12
    assert res_b.objective == pytest.approx(res_a.objective, rel=1e-9)
    assert torch.allclose(res_b.q, res_a.q, atol=1e-12)


def test_bad_settings_raise():
    with pytest.raises(InputError, match="exact_interval"):
        InexactSettings(exact_interval=0).validate()
    prob, q, _ = _runner()
    with pytest.raises(InputError, match="iterations >= 1"):
        prob.simulate(prob.param(q.detach()), exact=False, iterations=0)


class _ScriptedProblem:
    """The interface :class:`InexactRunner` uses, with objectives read from a script (exact or not as asked):
    the runner's decisions alone are under test."""

    def __init__(self, values: list[float]) -> None:
        self.values = list(values)
        self.exact_settings = SimpleNamespace(max_iterations=10)
        self.x = torch.zeros(4, 3, dtype=torch.float64)
        self.last, self.last_q = None, None
        self.best_q, self.best_x, self.best_objective = None, None, float("inf")
        self.sim_iterations = 0  # one per evaluation

    def reset_state(self, x: torch.Tensor) -> None:
        self.x = x.clone()

    def evaluate(self, q, exact=True, need_grad=False, max_iterations=None):
        f = self.values.pop(0)
        self.sim_iterations += 1
        self.last, self.last_q = SimpleNamespace(objective=f, exact=exact), q.detach().clone()
        if exact and f < self.best_objective:
            self.best_q, self.best_x, self.best_objective = q.detach().clone(), self.x.clone(), f
        return self.last

    def closure(self, q, exact, iterations, need_grad):
        def inner():
            return torch.tensor(self.evaluate(q, exact=exact).objective)
        inner.cacheable = False
        return inner


class _CountingStep(torch.optim.Optimizer):
    """Takes no step; reports the step length ``lr`` as taken."""

    def __init__(self, params, lr: float) -> None:
        super().__init__(params, {"lr": lr})

    def step(self, closure):
        loss = closure()
        self.last_step_length = self.param_groups[0]["lr"]
        return loss


@pytest.mark.parametrize(("check", "poor"), [(90.0, True), (60.0, False), (110.0, None)])
def test_ratio_test_of_an_exact_check(check, poor):
    """Start 100 (exact), three inexact iterations at 50, then the exact check. 90 dropped by 10 where 50 was
    predicted (rho = 0.2 < 0.25): kept, but S doubles and the step halves. 60 (rho = 0.8): the paper's success
    rule (S stays at its floor, the step grows). 110: no drop, the paper's backtrack."""
    q = torch.zeros(2, 2, dtype=torch.float64, requires_grad=True)
    prob = _ScriptedProblem([100.0, 100.0, 50.0, 50.0, 50.0, check, 100.0])
    opt = _CountingStep([q], lr=1.0)
    settings = InexactSettings(inner_iterations=2, exact_interval=4, max_step=4.0, adapt_step=False)
    runner = InexactRunner(prob, opt, q, settings)
    runner.run(5)
    rec = runner.records[-1]
    assert rec.exact
    if poor is None:
        assert rec.backtracked and not rec.accepted and rec.model_ratio is None
        assert runner.S == 4 and runner.step_length == pytest.approx(0.5)
        return
    assert rec.accepted and not rec.backtracked
    assert rec.model_ratio == pytest.approx((100.0 - check) / 50.0)
    assert runner.checkpoint["objective"] == check
    if poor:
        assert runner.S == 4 and runner.step_length == pytest.approx(0.5)
    else:
        assert runner.S == 2 and runner.step_length == pytest.approx(1.25)
    # the paper's rule alone (min_model_ratio = 0) treats both drops as successes
    prob = _ScriptedProblem([100.0, 100.0, 50.0, 50.0, 50.0, check, 100.0])
    q2 = torch.zeros(2, 2, dtype=torch.float64, requires_grad=True)
    paper = InexactSettings(inner_iterations=2, exact_interval=4, max_step=4.0, min_model_ratio=0.0,
                            adapt_step=False)
    runner = InexactRunner(prob, _CountingStep([q2], lr=1.0), q2, paper)
    runner.run(5)
    assert runner.S == 2 and runner.step_length == pytest.approx(1.25)


def test_ratio_test_survives_resume():
    """The prediction (the last inexact objective) is part of the resumable state."""
    q = torch.zeros(2, 2, dtype=torch.float64, requires_grad=True)
    prob = _ScriptedProblem([100.0, 100.0, 50.0, 50.0, 50.0, 90.0, 100.0])
    settings = InexactSettings(inner_iterations=2, exact_interval=4, adapt_step=False)
    runner = InexactRunner(prob, _CountingStep([q], lr=1.0), q, settings)
    runner.run(4)  # its finish() evaluates the last iterate exactly (the script's 90)
    state = runner.state_dict()
    assert state["last_inexact"] == 50.0
    q2 = torch.zeros(2, 2, dtype=torch.float64, requires_grad=True)
    prob = _ScriptedProblem([90.0, 100.0])
    resumed = InexactRunner(prob, _CountingStep([q2], lr=1.0), q2, settings)
    resumed.load_state_dict(state)
    resumed.run(5)
    assert resumed.records[-1].model_ratio == pytest.approx(0.2) and resumed.S == 4


def test_adapt_step_between_checks():
    """The bold driver: an inexact objective above the previous inexact one halves the step taken, one below
    (or equal) lengthens the step by step_increase up to max_step; an exact evaluation is never compared with
    an inexact one. Without adapt_step the step stays until the check."""
    values = [100.0, 100.0, 80.0, 90.0, 70.0, 60.0]
    q = torch.zeros(2, 2, dtype=torch.float64, requires_grad=True)
    runner = InexactRunner(_ScriptedProblem(values + [60.0]), _CountingStep([q], lr=1.0), q,
                           InexactSettings(inner_iterations=2, exact_interval=8, max_step=1.6,
                                           adapt_step=True))
    steps = []
    runner.run(5, callback=lambda rec: steps.append(runner.step_length))
    # iteration 1 exact (restart), 2 inexact (no previous), 3 rose -> 0.5, 4 fell -> 0.625, 5 fell -> 0.78125
    assert steps == pytest.approx([1.0, 1.0, 0.5, 0.625, 0.78125])
    q2 = torch.zeros(2, 2, dtype=torch.float64, requires_grad=True)
    fixed = InexactRunner(_ScriptedProblem(values + [60.0]), _CountingStep([q2], lr=1.0), q2,
                          InexactSettings(inner_iterations=2, exact_interval=8, adapt_step=False))
    fixed.run(5)
    assert fixed.step_length == 1.0


@pytest.mark.parametrize(("window", "expected"), [
    # iteration 3: 90 above 80 -> 0.5; 4: 85 between 80 and 90 -> kept; 5: 95 above all -> 0.25;
    # 6: 70 below all -> 0.3125
    (4, [1.0, 1.0, 0.5, 0.5, 0.25, 0.3125]),
    # the plain bold driver compares with the last value only: 85 < 90 grows, 95 > 85 shrinks, 70 < 95 grows
    (1, [1.0, 1.0, 0.5, 0.625, 0.3125, 0.390625]),
])
def test_adapt_step_window(window, expected):
    """``step_window``: a rise above the largest of the last ``step_window`` inexact objectives shortens the
    step, a drop below the smallest lengthens it, a value between them keeps it."""
    values = [100.0, 100.0, 80.0, 90.0, 85.0, 95.0, 70.0, 70.0]
    q = torch.zeros(2, 2, dtype=torch.float64, requires_grad=True)
    runner = InexactRunner(_ScriptedProblem(values), _CountingStep([q], lr=1.0), q,
                           InexactSettings(inner_iterations=2, exact_interval=8, max_step=1.6,
                                           adapt_step=True, step_window=window))
    steps = []
    runner.run(6, callback=lambda rec: steps.append(runner.step_length))
    assert steps == pytest.approx(expected)


def test_adapt_step_window_survives_resume():
    """The window of recent inexact objectives is part of the resumable state: a resumed run takes the
    uninterrupted run's steps."""
    values = [100.0, 100.0, 80.0, 90.0, 85.0, 95.0, 70.0]
    settings = InexactSettings(inner_iterations=2, exact_interval=8, max_step=1.6, adapt_step=True)
    q = torch.zeros(2, 2, dtype=torch.float64, requires_grad=True)
    whole = InexactRunner(_ScriptedProblem(values + [70.0]), _CountingStep([q], lr=1.0), q, settings)
    whole.run(6)
    q1 = torch.zeros(2, 2, dtype=torch.float64, requires_grad=True)
    first = InexactRunner(_ScriptedProblem(values[:5] + [85.0]), _CountingStep([q1], lr=1.0), q1, settings)
    first.run(4)  # its finish() evaluates the last iterate exactly (the script's 85)
    state = first.state_dict()
    assert state["recent_inexact"] == [80.0, 90.0, 85.0]
    q2 = torch.zeros(2, 2, dtype=torch.float64, requires_grad=True)
    resumed = InexactRunner(_ScriptedProblem(values[5:] + [70.0]), _CountingStep([q2], lr=1.0), q2, settings)
    resumed.load_state_dict(state)
    resumed.run(6)
    assert resumed.step_length == pytest.approx(whole.step_length) == pytest.approx(0.3125)


def test_step_window_must_be_positive():
    with pytest.raises(InputError, match="step_window"):
        InexactSettings(step_window=0)
