"""Projected Newton with collision-free line search (retarget solver)."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from retarget_synth import scene  # noqa: E402

from torchgarment.errors import InputError  # noqa: E402
from torchgarment.retarget.objectives import (  # noqa: E402
    Contact,
    Positional,
    RetargetEnergy,
    SurfaceShape,
    element_blocks,
    make_state,
    vertex_areas,
)
from torchgarment.retarget.solver import (  # noqa: E402
    InflationPenalty,
    NewtonSettings,
    initial_stiffness,
    projected_newton,
    retarget_model,
)
from torchgarment.sim.contact import StepBound  # noqa: E402
from torchgarment.testing import check_gradient  # noqa: E402

if TYPE_CHECKING:
    import scipy.sparse

    from torchgarment.sim.energies.base import HessianBlocks


def _square(z: float, n: int = 4, size: float = 0.2) -> tuple[torch.Tensor, torch.Tensor]:
    """A flat n x n grid at height z (garment) and its faces."""
    u = torch.linspace(-size, size, n, dtype=torch.float64)
    gx, gy = torch.meshgrid(u, u, indexing="ij")
    v = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.full((n * n,), z, dtype=torch.float64)], 1)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = i * n + j
    f = np.concatenate(
        [
            np.stack([a, a + n, a + 1], -1).reshape(-1, 3),
            np.stack([a + 1, a + n, a + n + 1], -1).reshape(-1, 3),
        ]
    )
    return v, torch.as_tensor(f)


def test_step_options_resolve() -> None:
    assert StepBound.resolve("CCD") is StepBound.ADDITIVE
    assert StepBound.resolve("distance") is StepBound.CONSERVATIVE
    with pytest.raises(InputError):
        StepBound.resolve("bogus")
    with pytest.raises(InputError):
        NewtonSettings(max_displacement=-1.0)
    with pytest.raises(InputError, match="pcg_accept_rtol"):
        NewtonSettings(pcg_accept_rtol=0.001)  # below pcg_rtol
    assert NewtonSettings().solve_settings().pcg_accept_rtol == 0.1
    assert NewtonSettings(pcg_accept_rtol=None).solve_settings().pcg_accept_rtol is None


@pytest.mark.parametrize("method", list(StepBound))
def test_collision_free_step_is_safe(method: StepBound) -> None:
    # garment sheet 1 cm above an obstacle sheet, moving straight down by 3 cm: impact at alpha = 1/3
    g, gf = _square(0.01)
    a, af = _square(0.0, n=3, size=0.3)
    c = Contact(g, gf, a, af, None, dhat=1e-3).ipc
    dx = np.zeros((g.shape[0], 3))
    dx[:, 2] = -0.03
    alpha = c.max_step(g.numpy(), 1.0, dx, 0.0, method)
    assert 0.0 < alpha < 1.0 / 3.0
    # not uselessly small: CCD gets close to the impact, the distance bound is 0.8 * 0.01 / (2 * 0.03) = 0.133
    assert alpha > (0.2 if method is not StepBound.CONSERVATIVE else 0.1)
    # moving away: CCD sees no impact; the distance bound is direction-blind (same 0.133)
    away = c.max_step(g.numpy(), 1.0, -dx, 0.0, method)
    assert away == 1.0 if method is not StepBound.CONSERVATIVE else away == pytest.approx(0.8 * 0.01 / 0.06)


@pytest.mark.parametrize("method", list(StepBound))
def test_collision_free_step_with_moving_avatar(method: StepBound) -> None:
    # avatar inflating with t towards the garment: the avatar moves, the garment does not
    g, gf = _square(0.05)
    a_full, af = _square(0.09, n=3, size=0.3)
    a_shr = a_full.clone()
    a_shr[:, 2] = 0.0
    c = Contact(g, gf, a_full, af, a_shr, dhat=1e-3).ipc
    # at t = 0 the avatar is at z = 0; t = 5/9 puts it on the garment (z = 0.05)
    alpha = c.max_step(g.numpy(), 0.0, np.zeros((g.shape[0], 3)), 1.0, method)
    assert 0.0 < alpha < 5.0 / 9.0


def test_inflation_penalty_gradient() -> None:
    al = InflationPenalty(3.0, 0.5)
    x = torch.zeros(2, 3, dtype=torch.float64)
    check_gradient(lambda t: al(make_state(x, t)), torch.tensor(0.3, dtype=torch.float64), rtol=1e-7)
    al.update(0.3)
    assert al.lambda2 == pytest.approx(0.5 + 3.0 * 0.7)
    assert al.hessian_blocks(make_state(x, 0.3)).to_sparse(3).to_dense()[6, 6] == pytest.approx(3.0)


def test_newton_pushes_garment_against_obstacle_without_crossing() -> None:
    # the positional term drags a sheet down through a fixed obstacle 1 cm below; contact must stop it
    g, gf = _square(0.01, n=5)
    a, af = _square(0.0, n=3, size=0.4)
    torch.tensor([[0.0, 0.0, 0.01], [0.0, 1.0, 0.01]], dtype=torch.float64)
    torch.tensor([[0, 1]])
    surf = SurfaceShape(g, gf)
    c = Contact(g, gf, a, af, None, dhat=2e-3)

    # a "pulling" quadratic: every vertex wants z = -0.02 (below the obstacle)
    class Pull(RetargetEnergy):
        name = "pull"

        def energy(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            return 10.0 * ((x[:, 2] + 0.02) ** 2).sum()

        def unweighted_blocks(
            self, x: torch.Tensor, t: torch.Tensor, project_psd: bool = True
        ) -> HessianBlocks:
            h = torch.zeros(x.shape[0], 3, 3, dtype=x.dtype)
            h[:, 2, 2] = 20.0
            return element_blocks(h, torch.arange(x.shape[0])[:, None])

    obj = retarget_model([surf, Pull(), c], g)
    initial_stiffness(obj, g, 1.0, float(vertex_areas(g, gf).mean()) * 100)
    r = projected_newton(obj, g, 1.0, free_t=False, settings=NewtonSettings(max_iterations=60, rtol=1e-4))
    assert r.converged, r.reason
    assert not c.ipc.has_intersections(r.x, 1.0)
    z = r.x[:, 2]
    assert float(z.min()) > 0.0 and float(z.max()) < 2e-3  # pressed into the barrier zone, never through
    assert len(r.history) == r.iterations


def test_inflation_reaches_t1_and_keeps_garment_outside() -> None:
    s = scene(rings=6, segments=16)
    x0, f = s["garment_vertices"], s["garment_faces"]
    surf = SurfaceShape(x0, f)
    pos = Positional(x0, f, s["joints"], s["joints"], s["bones"], weight=10.0)
    c = Contact(x0, f, s["avatar_full"], s["avatar_faces"], s["avatar_shrunk"], dhat=2e-3)
    al = InflationPenalty(5.0)
    obj = retarget_model([surf, pos, c, al], x0)
    initial_stiffness(obj, x0, 0.0, float(vertex_areas(x0, f).mean()) * 100)
    x, t = x0, 0.0
    for _ in range(10):
        settings = NewtonSettings(max_iterations=10, max_displacement=0.03, rtol=0)
        r = projected_newton(obj, x, t, free_t=True, settings=settings)
        x, t = r.x, r.t
        if t > 0.999:
            break
        al.update(t)
    assert t > 0.9
    # the garment (radius 0.15) was pushed outside the inflating capsule (radius 0.17 * t, polygonal)
    radius = x[:, [0, 2]].norm(dim=1)
    assert float(radius.min()) > 0.17 * t * math.cos(math.pi / 16) - 1e-3
    assert not c.ipc.has_intersections(x, t)


def test_newton_solve_reuses_its_factorization_through_pcg() -> None:
    """With a FactorCache the first system is factorized; a nearby one is solved by CG preconditioned with
    that factorization (no new factorization), to the requested relative residual, as a descent direction."""
    import scipy.sparse as sp

    from torchgarment.linalg import FactorCache
    from torchgarment.retarget.solver import NewtonSettings as RetargetNewtonSettings
    from torchgarment.sim.solvers.newton import NewtonOptions, newton_direction

    options = NewtonOptions(regularize_first=True, regularization_growth=100.0, gradient_fallback=True)

    def _solve(
        h: scipy.sparse.csr_matrix,
        g: np.ndarray,
        shift: float,
        cache: FactorCache,
        rtol: float = 1e-2,
        maxiter: int = 25,
        accept: float | None = None,
    ) -> tuple[np.ndarray, int]:
        st = RetargetNewtonSettings(pcg_rtol=rtol, pcg_max_iterations=maxiter,
                                    pcg_accept_rtol=accept).solve_settings()
        assert st.regularization == shift
        return newton_direction(h, g, st, 1, cache, options)

    rng = np.random.default_rng(0)
    n = 300
    a = sp.random(n, n, density=0.02, random_state=1)
    h1 = (a @ a.T + sp.identity(n)).tocsr()
    g = rng.standard_normal(n)
    cache = FactorCache()
    p1, _ = _solve(h1, g, 1e-8, cache)
    assert cache.factorizations == 1 and cache.pcg_solves == 0
    np.testing.assert_allclose(h1 @ p1, -g, rtol=1e-6, atol=1e-6)  # up to the 1e-8 diagonal shift
    h2 = (h1 + 0.05 * sp.diags(rng.uniform(0.0, 1.0, n))).tocsr()  # the next Newton system, a little stiffer
    p2, _ = _solve(h2, g, 1e-8, cache, rtol=1e-6, maxiter=50)
    assert cache.factorizations == 1 and cache.pcg_solves == 1
    assert float(p2 @ g) < 0
    assert np.linalg.norm(h2 @ p2 + g) <= 1e-6 * np.linalg.norm(g) * 1.0001
    # a system far from the cached one: CG gives up within maxiter and a fresh factorization is made
    h3 = (h1 + 1e3 * sp.diags(rng.uniform(0.0, 1.0, n))).tocsr()
    p3, _ = _solve(h3, g, 1e-8, cache, rtol=1e-10, maxiter=2)
    assert cache.factorizations == 2
    np.testing.assert_allclose(h3 @ p3, -g, rtol=1e-5, atol=1e-5)
    # the retargeting default: a solve stopped by its budget (2 updates, short of 1e-10) on a system near
    # the cached one is Newton's direction when within pcg_accept_rtol = 0.1, without a factorization
    h4 = (h3 + 30.0 * sp.diags(rng.uniform(0.0, 1.0, n))).tocsr()
    p4, _ = _solve(h4, g, 1e-8, cache, rtol=1e-10, maxiter=3, accept=0.1)
    assert cache.factorizations == 2 and cache.pcg_solves == 2
    assert 1e-10 < np.linalg.norm(h4 @ p4 + g) / np.linalg.norm(g) <= 0.1 and float(p4 @ g) < 0
    # that step dropped the factorization: the next system is factorized afresh and solved exactly
    p5, _ = _solve(h4, g, 1e-8, cache, rtol=1e-10, maxiter=3, accept=0.1)
    assert cache.factorizations == 3 and cache.pcg_solves == 2
    np.testing.assert_allclose(h4 @ p5, -g, rtol=1e-5, atol=1e-5)


def test_newton_factorizes_in_the_fixed_terms_ordering(monkeypatch: pytest.MonkeyPatch) -> None:
    """With the Hessian in block groups (the retargeting model: the terms of fixed sparsity, then the
    contact), every factorization of a solve uses the fill-reducing ordering of the first group's pattern,
    computed once, while the contacts change the whole pattern; and a Cholesky backend solves each Newton
    system afresh by default, where SuperLU reuses its factorization."""
    import torchgarment.sim.solvers.newton as newton_mod
    from torchgarment.linalg import CSRAssembler, fill_reducing_permutation

    g, gf = _square(0.01, n=5)
    a, af = _square(0.0, n=3, size=0.4)
    c = Contact(g, gf, a, af, None, dhat=2e-3)

    class Pull(RetargetEnergy):  # every vertex wants z = -0.02, below the obstacle
        name = "pull"

        def energy(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            return 10.0 * ((x[:, 2] + 0.02) ** 2).sum()

        def unweighted_blocks(self, x: torch.Tensor, t: torch.Tensor, project_psd: bool = True
                              ) -> HessianBlocks:
            h = torch.zeros(x.shape[0], 3, 3, dtype=x.dtype)
            h[:, 2, 2] = 20.0
            return element_blocks(h, torch.arange(x.shape[0])[:, None])

    obj = retarget_model([SurfaceShape(g, gf), Pull(), c], g)
    initial_stiffness(obj, g, 1.0, float(vertex_areas(g, gf).mean()) * 100)
    seen: list[np.ndarray | None] = []
    original = newton_mod.factorize

    def spy(matrix: scipy.sparse.spmatrix, **kwargs: object) -> object:
        seen.append(kwargs.get("ordering"))
        return original(matrix, **kwargs)

    monkeypatch.setattr(newton_mod, "factorize", spy)
    settings = NewtonSettings(max_iterations=8, rtol=0.0, sparse_backend="superlu", reuse_factorization=False)
    r = projected_newton(obj, g, 1.0, free_t=False, settings=settings)
    assert r.iterations >= 3 and len(seen) >= r.iterations  # a factorization per iteration
    fixed = CSRAssembler(obj.num_vertices).assemble(obj.hessian_block_parts(make_state(g, 1.0))[0])
    n = 3 * g.shape[0]  # free_t=False: the inflation's row of the state is not an unknown
    expected = fill_reducing_permutation(fixed[:n, :n])
    assert all(p is seen[0] for p in seen) and np.array_equal(seen[0], expected)
    assert not c.ipc.has_intersections(r.x, 1.0)
    # the reuse's default follows the backend; an explicit choice stays
    assert NewtonSettings(sparse_backend="cholmod").reuse_factorization is False
    assert NewtonSettings(sparse_backend="superlu").reuse_factorization is True
    assert NewtonSettings(sparse_backend="cholmod", reuse_factorization=True).reuse_factorization is True
