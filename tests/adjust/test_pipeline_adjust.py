"""End to end pattern adjustment (torchgarment.adjust.pipeline): a straight skirt drafted for chart size 12,
adjusted to size 20 at a coarse edge length (5 cm) and SDF voxel (10 mm) with Algorithm 1 (pgd)."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
import pytest
import torch

from torchgarment.adjust.inexact import AdjustProblem
from torchgarment.adjust.pipeline import AdjustSettings, adjust, optimize, prepare
from torchgarment.errors import InputError
from torchgarment.sim.diff import AdjointLinearSolver
from torchgarment.testing import directional_derivatives

if TYPE_CHECKING:
    from torchgarment.adjust.inexact import IterationRecord
    from torchgarment.pattern.spec import SewingPattern

SETTINGS = AdjustSettings(edge_length=0.05, voxel_size=0.01, iterations=16, exact_interval=8)


@pytest.fixture(scope="module")
def skirt_case():
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        b12, b20 = Body.from_size("12"), Body.from_size("20")
        pattern = draft("straight_skirt", chart_row("12"))
        setup = prepare(pattern, b12, b20, SETTINGS)
        result = optimize(setup, progress=False)
    finally:
        torch.set_num_threads(n)
    return pattern, setup, result


def _panel_areas(pattern: SewingPattern) -> float:
    return sum(abs(p.area()) for p in pattern.panels.values())


def test_initialization_then_optimization_reduce_the_objective(skirt_case):
    _, setup, result = skirt_case
    m = result.metrics
    # measured with the default coefficients (resolution-consistent, with the construction and guide lines'
    # terms, ease 1e6): base 1637 -> initialized 12.6 -> 9.53 after 16 pgd iterations (24 % below the
    # initialized), 16 closure calls. (Ease 1e5 without the guide lines: 156.0 -> 2.21 -> 1.95.)
    # (Without the line terms: 118.9 -> 2.39 -> 1.87; with the coefficients as given and no line terms,
    # CostWeights.paper(): 118.9 -> 64.9 -> 17.9; the initialization does most of the work now.)
    assert m["objective_initial"] < 0.1 * m["objective_base"]
    assert m["objective_final"] < 0.95 * m["objective_initial"]
    assert m["reduction_percent"] > 5.0
    assert m["iterations"] == 16 and m["closure_calls"] >= 16
    assert set(m["terms"]) == {"base", "initial", "final"}
    assert set(m["terms"]["final"]) >= {"distance", "smoothness", "stretching", "positional", "fixing",
                                        "curvature", "ease"}
    assert m["terms"]["final"]["ease"] > 0.0 and m["terms"]["final"]["placement"] > 0.0
    assert set(m["line_targets"]["lines"]) == {"waist", "hips", "hem"}
    assert m["line_targets"]["lines"]["hem"]["kind"] == "guide" and m["terms"]["final"]["guide_placement"] > 0
    assert math.isclose(sum(m["terms"]["final"].values()), m["objective_final"], rel_tol=1e-6)
    assert 1.0 < m["max_boundary_displacement_mm"] < 200.0
    assert len(result.records) == 16 and len(result.term_history) == 16


def test_result_is_an_exact_equilibrium_never_worse_than_the_start(skirt_case):
    _, setup, result = skirt_case
    problem = setup.new_problem(result.mesh_target.x)
    ev = problem.evaluate(result.q, exact=True, need_grad=False)
    assert ev.sim_iterations <= 2  # the returned garment is already in equilibrium
    assert ev.objective == pytest.approx(result.metrics["objective_final"], rel=1e-4)
    assert result.metrics["objective_final"] <= result.metrics["objective_initial"]


def test_adjusted_pattern_is_larger_and_consistent(skirt_case):
    pattern, setup, result = skirt_case
    new = result.pattern
    assert new is not None and list(new.panels) == list(pattern.panels)
    new.validate()
    # size 20 is larger than size 12 everywhere: the adjusted panels grow (measured about +10 %)
    assert _panel_areas(new) > 1.03 * _panel_areas(pattern)
    assert result.metrics["pattern_fit_error_mm"] < 3.0
    # the rebuilt outline passes within 3 mm of every optimized boundary vertex
    vp = setup.mesh_base.vertex_panel_ids
    bidx = setup.param.boundary_index
    for k, name in enumerate(setup.mesh_base.panel_names):
        pts = result.mesh_target.p[bidx[vp[bidx] == k]].numpy()
        panel = new.panels[name]
        t = np.linspace(0.0, 1.0, 400)
        outline = np.concatenate([e.evaluate(*panel.edge_endpoints(i), t) for i, e in enumerate(panel.edges)])
        d = np.linalg.norm(pts[:, None, :] - outline[None], axis=2).min(axis=1)
        assert d.max() < 3e-3, name
    q_new = result.mesh_target.p[setup.param.boundary_index]
    assert torch.allclose(q_new, result.q.to(q_new.dtype), atol=1e-12)
    assert np.isfinite(result.mesh_target.x.numpy()).all()


def test_bad_input():
    with pytest.raises(InputError, match="SewingPattern or a GarmentMesh"):
        prepare("skirt", None, None, SETTINGS)
    with pytest.raises(InputError, match="iterations"):
        AdjustSettings(iterations=-1).validate()
    with pytest.raises(InputError, match="unknown optimizer kind"):
        AdjustSettings(optimizer="adam").validate()
    for bad in ({"exact_curvature_cg": -1}, {"exact_curvature_cg": 10, "linear_solver": "jacobi-pcg"}):
        with pytest.raises(InputError, match="exact_curvature_cg"):
            AdjustSettings(**bad).validate()
    with pytest.raises(InputError, match="unknown sparse backend"):
        AdjustSettings(sparse_backend="umfpack").validate()
    with pytest.raises(InputError, match="projected"):
        AdjustSettings(inexact_adjoint="psd").validate()


def test_ctrl_c_leaves_a_resumable_checkpoint(skirt_case, tmp_path):
    _, setup, result = skirt_case
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        settings = AdjustSettings(**{**SETTINGS.__dict__, "iterations": 4})

        def interrupt(rec: IterationRecord, terms: dict[str, float]) -> None:
            # stands for the user's Ctrl-C after iteration 3
            if rec.iteration == 2:
                raise KeyboardInterrupt

        with pytest.raises(KeyboardInterrupt):
            optimize(setup, settings, checkpoint_dir=tmp_path, progress=False, callback=interrupt)
        assert (tmp_path / "adjust.pt").is_file()
        resumed = optimize(setup, settings, checkpoint_dir=tmp_path, progress=False, resume=True,
                           log_dir=tmp_path / "logs")
        straight = optimize(setup, settings, progress=False)
    finally:
        torch.set_num_threads(n)
    assert resumed.metrics["iterations"] == 4 and len(resumed.records) == 4
    assert resumed.metrics["objective_final"] == pytest.approx(straight.metrics["objective_final"], rel=1e-6)
    # issue 18: the resumed pattern is the uninterrupted one within 0.1 mm (measured: equal to round-off)
    assert float((resumed.q - straight.q).abs().max()) <= 1e-4
    assert any(p.name.startswith("events.out.tfevents") for p in (tmp_path / "logs").iterdir())
    with pytest.raises(InputError, match="no checkpoint"):
        optimize(setup, settings, checkpoint_dir=tmp_path / "none", resume=True, progress=False)
    # issue 17: a checkpoint of another run is refused (another optimizer; another target's transfer)
    with pytest.raises(InputError, match="optimizer differs"):
        optimize(setup, replace(settings, optimizer="lbfgs"), checkpoint_dir=tmp_path, resume=True,
                 progress=False)
    other = replace(setup, x_transfer=setup.x_transfer + 1e-3)
    with pytest.raises(InputError, match="bodies or base drape differ"):
        optimize(other, settings, checkpoint_dir=tmp_path, resume=True, progress=False)
    state = torch.load(tmp_path / "adjust.pt", weights_only=False)
    del state["fingerprint"]
    torch.save(state, tmp_path / "adjust.pt")
    with pytest.raises(InputError, match="does not say which run wrote it"):
        optimize(setup, settings, checkpoint_dir=tmp_path, resume=True, progress=False)



def test_iterative_adjoint_matches_the_direct_one_on_the_real_skirt(skirt_case):
    """Seams (6x6 seam blocks in the preconditioner), the body barrier and its curvature: CG to a tight
    tolerance gives the direct (SuperLU) gradient; capped at a few iterations it is warm-started from the last
    adjoint."""
    _, setup, result = skirt_case
    q = result.q
    direct = setup.new_problem(result.mesh_target.x)
    g_direct = direct.evaluate(q, exact=True).grad
    it = setup.new_problem(result.mesh_target.x, settings=replace(
        setup.settings, adjoint=AdjointLinearSolver.CG, adjoint_rtol=1e-10, adjoint_max_iterations=5000))
    g_it = it.evaluate(q, exact=True).grad
    # measured: 4e-10 relative after ~300 CG iterations
    assert (float(torch.linalg.vector_norm(g_it - g_direct))
            <= 1e-6 * float(torch.linalg.vector_norm(g_direct)))
    first = it.adjoint_iterations
    assert first > 10
    it.evaluate(q, exact=True)  # same system: the warm start is already the solution
    assert it.adjoint_iterations - first <= 1
    capped = setup.new_problem(result.mesh_target.x, settings=replace(
        setup.settings, adjoint=AdjointLinearSolver.CG, adjoint_max_iterations=3))
    capped.evaluate(q, exact=True)
    assert capped.adjoint_iterations == 3 and capped.last_adjoint_residual > 1e-3


def test_setup_pickles_and_optimizes_after_loading(skirt_case, tmp_path):
    """torch.save/torch.load of a prepared setup (the Laplacian's SuperLU factorization is rebuilt on
    load)."""
    _, setup, _ = skirt_case
    path = tmp_path / "setup.pt"
    torch.save(setup, path)
    loaded = torch.load(path, weights_only=False)
    assert torch.equal(loaded.param(setup.q_init), setup.param(setup.q_init))
    res = optimize(loaded, replace(loaded.settings, iterations=2), progress=False)
    assert res.metrics["objective_final"] <= setup.objective_initial


def test_optimizing_one_setup_twice_gives_the_same_result(skirt_case, one_torch_thread):
    """optimize() starts each run from a clean model (SimModel.reset_caches): the barrier's lazy sampling
    references left by an earlier run changed the step bounds' last bits, and the optimization amplified them
    (the 3K dress: 53.8 and 115.5 from one setup)."""
    _, setup, result = skirt_case
    again = optimize(setup, progress=False)
    assert again.metrics["objective_final"] == result.metrics["objective_final"]
    assert torch.equal(again.q, result.q)


def test_adjust_with_the_large_mesh_path_reduces_the_objective(skirt_case):
    """gd-chebyshev S-iteration simulations and the iterative adjoint (bench_adjust.py's large-mesh
    options), from the base pattern (no section-7 initialization: the initialized pattern is already within
    25 % of what 16 exact-path iterations reach, too close to test a reduction)."""
    from torchgarment.body import Body

    pattern, _, _ = skirt_case
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        raw = prepare(pattern, Body.from_size("12"), Body.from_size("20"),
                      replace(SETTINGS, initialize=False))
    finally:
        torch.set_num_threads(n)
    st = replace(raw.settings, iterations=8, inner_solver="gd-chebyshev", inner_iterations=8,
                 adjoint="iterative", adjoint_max_iterations=50)
    res = optimize(raw, st, progress=False)
    m = res.metrics
    # no factorization: 7 of the 9 CG adjoints meet negative curvature at the inexact states and are solved
    # by MINRES (their CG iterates had been used as gradients, and the run ended at 1579 instead of 1529; the
    # direct adjoint ends at 1531). On 2026-12-02 this run gave 1618 -> 1535 in 445 CG and MINRES iterations,
    # and with inexact_adjoint="projected" (CG on the positive definite projected Hessian) 1541 in 400
    assert m["adjoint"] == "cg" and m["adjoint_iterations"] > 0
    assert m["factorizations"] == 0 and m["adjoint_fallbacks"] == 0
    # measured: 1641 -> 1529 with today's defaults (the 5 mm step bound limits 8 iterations, and the base
    # pattern is 19 cm of girth from the line targets, which the ease weight of 1e6 makes most of the
    # objective; 31.2 -> 29.2 before the line terms)
    assert m["objective_final"] < 0.97 * m["objective_initial"]


def test_pipeline_gradient_is_loss_backward_through_the_solve_function(skirt_case):
    """The adjust pipeline's gradient is ``f.backward()`` through :class:`QuasistaticSolve` (the Function is
    on the graph of the evaluation), and it equals central finite differences of the whole objective (exact
    solves to 1e-10 of the weight, float64) within 1e-4 relative on the real skirt."""
    from torchgarment.sim.diff import QuasistaticSolve
    from torchgarment.sim.solvers import SolveSettings

    _, setup, result = skirt_case
    weight = setup.exact_settings.atol / setup.settings.atol_weight
    tight = SolveSettings(rtol=0.0, atol=1e-10 * weight, max_iterations=400)
    prob = AdjustProblem(setup.model, setup.param, setup.objective, result.mesh_target.x,
                         exact_settings=tight)
    q0 = result.q.detach()
    ev = prob.evaluate(q0, exact=True)
    qr, p, x = prob.last_graph
    assert x.grad_fn is not None and x.grad_fn.name() == f"{QuasistaticSolve.__name__}Backward"
    assert torch.equal(qr.grad, ev.grad)
    x_eq = prob.x.clone()

    def objective(q: torch.Tensor) -> float:
        prob.reset_state(x_eq)
        return prob.evaluate(q, exact=True, need_grad=False).objective

    # errors relative to the larger of the two directional derivatives. The central differences' noise grows
    # as the step shrinks (the solves' tolerance over h), and a step too large can straddle a kink of the
    # equilibrium map, so the adjoint must match at one of two steps. Measured (pin extension kept, issue 18)
    # 3.1e-5 / 9.1e-5 absolute at h = 1e-5, 1.9e-4 / 5.5e-4 at 3e-6, 4.3e-3 / 9.4e-3 at 3e-7. Since Newton's
    # barrier blocks hold the SDF's curvature the fixture's adjustment ends elsewhere; there the directional
    # derivatives are 6.1667 and 28.5377, and the first one's differences are 6.1541 / 6.1665 / 6.1591 /
    # 6.16667 at h = 1e-4 / 3e-5 / 1e-5 / 3e-6 (a kink within 1e-5; both agree to 1e-6 at 3e-6)
    # On 2026-12-02 (anny 0.6.1, scipy 1.17.1, numpy 2.4.6) the first direction straddled a kink at every
    # step: adjoint 13.66951, differences 14.7148 / 13.7038 / 13.6732 at h = 1e-5 / 3e-6 / 1e-6 (the second
    # direction matched at 3e-6). So a direction also passes when, at the smallest step, its mismatch is
    # within 1e-3 and at least 3x below the previous step's: the differences converging onto the adjoint as
    # the step leaves the kink behind (a wrong adjoint would leave them converging elsewhere).
    errors = []
    for h in (1e-5, 3e-6, 1e-6):
        pairs = directional_derivatives(objective, q0, ev.grad, directions=2, h=h, seed=3)
        scale = max(abs(fd) for _, fd in pairs)
        errors.append([abs(ad - fd) / scale for ad, fd in pairs])
        if all(e <= 1e-4 for e in errors[-1]):
            break
    for d in range(2):
        matched = any(step[d] <= 1e-4 for step in errors)
        converging = len(errors) == 3 and errors[-1][d] <= 1e-3 and errors[-1][d] * 3 <= errors[-2][d]
        assert matched or converging, (d, errors)


def test_rejected_initialization_is_judged_by_a_short_optimization_from_each_start(skirt_case, monkeypatch):
    """``init_trial_iterations``: a section-7 initialization whose first equilibrium scores worse than the
    base pattern is still chosen when the optimizer ends lower from it after the trial's iterations, and not
    otherwise. The optimizer is replaced by a record of its starts and budgets here; the real case (the
    sheath dress 12 -> 14 at 1.5 cm) is in the README's acceptance table."""
    import torchgarment.adjust.pipeline as pipeline

    _, prepared, _ = skirt_case
    setup = replace(prepared, q_init=prepared.q_base, initialization_used=False)  # as when rejected
    q_try = setup.q_base + 1e-3
    calls = []

    def fake_optimize(s, settings, progress=True):
        from_init = bool(torch.equal(s.q_init, q_try))
        calls.append((from_init, settings.iterations))
        final = outcome["init" if from_init else "base"]
        return type("R", (), {"metrics": {"objective_final": final}})()

    monkeypatch.setattr(pipeline, "optimize", fake_optimize)
    for outcome, chosen_init in (({"init": 5.0, "base": 9.0}, True), ({"init": 9.0, "base": 5.0}, False)):
        calls.clear()
        chosen = pipeline._initialization_trial(replace(setup, timings={}), q_try, setup.x_init, 1e9, {})
        n = SETTINGS.init_trial_iterations
        assert sorted(calls) == [(False, n), (True, n)]
        assert chosen.initialization_used is chosen_init
        assert torch.equal(chosen.q_init, q_try if chosen_init else setup.q_init)
        trial = chosen.timings["initialization_trial"]
        assert trial["objective_from_initialization"] == outcome["init"]
    with pytest.raises(InputError, match="init_trial_iterations"):
        replace(SETTINGS, init_trial_iterations=-1).validate()


def test_metrics_break_the_time_down_by_stage(skirt_case):
    """Issue 14's breakdown: forward solves (exact and inexact) and objective + adjoints, within the run's
    time."""
    _, _, result = skirt_case
    st = result.metrics["stage_seconds"]
    assert set(st) == {"exact_solves", "inexact_solves", "objective_and_adjoints"}
    assert st["exact_solves"] > 0 and st["inexact_solves"] > 0 and st["objective_and_adjoints"] > 0
    assert sum(st.values()) <= result.metrics["seconds"] + 1e-6
    # the sparse direct work inside each stage: Newton's factorizations in the solves, the adjoints' (one per
    # gradient, the count the differentiable solver keeps) in the last, each within its stage's time
    la = result.metrics["stage_linalg"]
    assert set(la) == set(st)
    assert la["exact_solves"]["factorizations"] > 0 and la["inexact_solves"]["factorizations"] > 0
    assert la["objective_and_adjoints"]["factorizations"] == result.metrics["factorizations"] > 0
    for stage, work in la.items():
        assert work["solves"] >= work["factorizations"] > 0
        assert 0 < work["factorization_seconds"] + work["solve_seconds"] <= st[stage] + 1e-6


def test_metrics_list_each_exact_check_with_how_far_the_garment_moved(skirt_case):
    """metrics["exact_checks"]: one entry per exactly evaluated iteration (and the final evaluation after an
    inexact last iterate), with its simulator iterations and the garment's displacement in it, which agree
    with the iteration records; a check after inexact iterations moves the garment (its state was not the
    equilibrium), by a mean below the maximum."""
    _, _, result = skirt_case
    checks = result.metrics["exact_checks"]
    exact_records = [r for r in result.records if r.exact]
    assert [c["iteration"] for c in checks if not c.get("final")] == [r.iteration for r in exact_records]
    for c, r in zip(checks, exact_records):
        assert (c["sim_iterations"], c["displacement_max_mm"]) == (r.sim_iterations, r.displacement_max_mm)
    after_inexact = [c for c in checks if c["iteration"] > 1]
    assert after_inexact, checks
    for c in after_inexact:
        assert c["sim_iterations"] > 2 and c["seconds"] > 0
        assert 0 < c["displacement_mean_mm"] < c["displacement_max_mm"]
    inexact = [r for r in result.records if not r.exact]
    assert inexact and all(r.sim_iterations >= 1 and r.displacement_max_mm > 0 for r in inexact)
    assert result.metrics["sim_iterations"] >= sum(r.sim_iterations for r in result.records)
    if not result.records[-1].exact:
        assert checks[-1]["final"] and checks[-1]["iteration"] == result.records[-1].iteration


def test_pcg_accept_rtol_reaches_the_exact_solves_and_is_validated(skirt_case):
    """AdjustSettings.pcg_accept_rtol, the forcing term of the reused factorization's budget-stopped CG
    steps (SolveSettings.pcg_accept_rtol, tested in tests/sim/test_solvers.py), reaches every simulation."""
    _, setup, _ = skirt_case
    assert AdjustSettings().pcg_accept_rtol == 0.3
    for accept in (0.3, None):
        st = replace(setup.settings, reuse_factorization=True, pcg_accept_rtol=accept)
        problem = setup.new_problem(settings=st)
        assert problem.exact_settings.reuse_factorization and problem.exact_settings.pcg_accept_rtol == accept
    for bad in (0.0, 1.0, 0.005):
        with pytest.raises(InputError, match="pcg_accept_rtol"):
            replace(SETTINGS, pcg_accept_rtol=bad)


def test_manufactured_solution_a_scaled_body_gets_the_scaled_pattern():
    """Issue 18's manufactured solution, end to end at 5 cm edges: adjusted onto the size-12 body scaled by
    1.05, the straight skirt's panels come out within 1.5 mm of the base panels scaled by 1.05 (rigid motion
    removed; measured 0.50 / 0.52 mm after 16 iterations, the unadjusted panels 19.5 / 19.2 mm off). With the
    fit rules' lengths kept absolute (``fit_scale="none"``) they miss it (measured 3.5 / 2.7 mm)."""
    from torchgarment.adjust.acceptance import scaled_body, scaled_outline_deviation
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row
    from torchgarment.pattern.library import draft

    base, s = Body.from_size("12"), 1.05
    target = scaled_body(base, s)
    worst = {}
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for kind in ("stature", "none"):
            res = adjust(draft("straight_skirt", chart_row("12")), base, target,
                         replace(SETTINGS, fit_scale=kind), progress=False)
            dev = scaled_outline_deviation(res, s)
            assert all(p["unadjusted_max_m"] > 0.015 for p in dev.values())
            worst[kind] = max(p["max_m"] for p in dev.values())
            assert res.metrics["fit_scale"] == pytest.approx(s if kind == "stature" else 1.0, abs=1e-6)
    finally:
        torch.set_num_threads(n)
    assert worst["stature"] <= 1.5e-3 < worst["none"], worst
