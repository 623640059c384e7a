"""Projected Newton with a sparse direct solver and a barrier-aware backtracking line search.

Each iteration assembles the Hessian from ``model.hessian_blocks(x, project_psd=True)`` (per-element blocks
projected to positive semi-definite) into a scipy CSR matrix on the CPU, solves ``H dx = -g`` with SuperLU,
caps the step at ``step_fraction * model.max_step(x, dx)`` when the full step would make a barrier infinite, and
backtracks until the Armijo condition ``E(x + a dx) <= E(x) + c a g.dx`` holds. When the factorization fails or
the solution is not a descent direction, ``lambda * I`` is added (``lambda`` growing tenfold per retry).

When the line search fails (the projected Hessian is a poor model: dropped negative-curvature parts of
compressed springs or of the barrier, a non-smooth SDF), the step is not abandoned: the direction is recomputed
with a Levenberg damping ``(H + lambda diag(H)) dx = -g`` (``lambda`` from ``levenberg_start``, tenfold per retry,
up to :data:`LEVENBERG_RETRIES` retries), which bends the step towards scaled gradient descent and shortens it. A
damping that worked is kept (divided by ten per successful iteration) so that the next iterations start from it.
The solve stops as stalled only when every damped direction also fails.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from torchgarment.errors import SingularMatrixError
from torchgarment.linalg import SparseBackend, factorize
from torchgarment.sim.solvers.common import (
    Callback,
    CSRAssembler,
    FactorCache,
    NonFiniteError,
    SolveInfo,
    SolverKind,
    SolverModel,
    SolveSettings,
    Timer,
    checked_max_step,
    evaluate,
    tolerance,
)


LEVENBERG_START = 1e-4
"""First Levenberg damping ``lambda`` (relative to the Hessian diagonal) after a failed line search."""

LEVENBERG_RETRIES = 8
"""Damped directions tried (``lambda`` tenfold each) before a failed line search stops the solve."""


def sparse_solve(h: scipy.sparse.csr_matrix, rhs: np.ndarray, cache: FactorCache | None = None,
                 shift: float = 0.0, backend: SparseBackend = SparseBackend.SUPERLU) -> np.ndarray | None:
    """Solve ``h y = rhs`` by :func:`~torchgarment.linalg.factorize` (symmetric mode of ``backend``); None if
    the factorization fails or is not finite. With a ``cache``, a successful factorization is stored in it (as
    one of ``h`` made with diagonal ``shift``)."""
    try:
        fact = factorize(h, backend=backend, what="Newton system")
        y = fact.solve(rhs)
    except SingularMatrixError:
        return None
    if cache is not None:
        cache.store(fact, shift)
    return y


def newton_direction(
    h: scipy.sparse.csr_matrix, g: np.ndarray, settings: SolveSettings, iteration: int,
    cache: FactorCache | None = None,
) -> tuple[np.ndarray, int]:
    """A descent direction ``dx`` solving ``(H + lambda I) dx = -g``, regularizing when needed.

    Args:
        h: (3V, 3V) Hessian (CSR, float64).
        g: (3V,) gradient (float64).
        settings: solve settings (regularization, max_regularizations).
        iteration: for error messages.
        cache: with one, first try CG preconditioned by the cached factorization
            (``settings.reuse_factorization``), and keep every fresh factorization in it.

    Returns:
        ``(dx, retries)``: the direction (3V,) and how many regularized factorizations were needed.

    Raises:
        NonFiniteError: no descent direction was found after ``max_regularizations`` retries.
    """
    if cache is not None:
        dx = cache.solve(h, -g, settings.pcg_rtol, settings.pcg_max_iterations)
        if dx is not None and float(g @ dx) < 0.0:
            return dx, 0
    dx = sparse_solve(h, -g, cache)
    if dx is not None and float(g @ dx) < 0.0:
        return dx, 0
    scale = float(np.abs(h.diagonal()).mean()) or 1.0
    eye = scipy.sparse.identity(h.shape[0], format="csr", dtype=np.float64)
    lam = settings.regularization * scale
    for retry in range(1, settings.max_regularizations + 1):
        dx = sparse_solve((h + lam * eye).tocsr(), -g, cache, lam)
        if dx is not None and float(g @ dx) < 0.0:
            return dx, retry
        lam *= 10.0
    raise NonFiniteError(
        f"Newton: no descent direction at solver iteration {iteration} even with lambda={lam / 10.0:.3g} * I"
    )


def solve_newton(
    model: SolverModel,
    x0: torch.Tensor,
    settings: SolveSettings,
    max_iterations: int,
    callback: Callback | None = None,
) -> tuple[torch.Tensor, SolveInfo]:
    """Minimize the model's energy from ``x0`` with projected Newton.

    Args:
        model: the simulation model (see :class:`~torchgarment.sim.solvers.common.SolverModel`).
        x0: (V, 3) initial positions (metres); must be feasible (all barriers finite).
        settings: solver settings (validated by the caller).
        max_iterations: iteration budget (Newton steps).
        callback: called after every iteration as ``callback(k, x, |g|, E)``; returning True stops.

    Returns:
        ``(x, info)``: the final positions (V, 3) and a :class:`SolveInfo`.
    """
    timer = Timer()
    info = SolveInfo(solver=SolverKind.NEWTON.value)
    slack = 16.0 * torch.finfo(x0.dtype).eps
    assembler = CSRAssembler(model.num_vertices)

    with torch.no_grad():
        x = x0.detach().clone()
        e, g, gn = evaluate(model, x, 0, "initial state")
        info.residual_history.append(gn)
        info.energy_history.append(e)
        tol = tolerance(settings, gn)
        info.message = "max iterations reached"
        if gn <= tol:
            info.converged, info.message = True, "converged"

        k = 0
        damping = 0.0  # Levenberg damping carried between iterations (0: plain projected Newton)
        cache = FactorCache() if settings.reuse_factorization else None
        while not info.converged and k < max_iterations:
            k += 1
            h = assembler.assemble(model.hessian_blocks(x, project_psd=settings.project_psd))
            if not np.all(np.isfinite(h.data)):
                raise NonFiniteError(f"model returned a non-finite Hessian at solver iteration {k}")
            g64 = g.detach().to(device="cpu", dtype=torch.float64).numpy().reshape(-1)
            diag = np.maximum(np.abs(h.diagonal()), 1e-12 * float(np.abs(h.diagonal()).max() or 1.0))
            accepted = False
            trial = 0
            while not accepted and trial <= LEVENBERG_RETRIES:
                hk = h if damping == 0.0 else (h + scipy.sparse.diags(damping * diag, format="csr")).tocsr()
                dx64, retries = newton_direction(hk, g64, settings, k, cache if damping == 0.0 else None)
                info.restarts += retries
                slope = float(g64 @ dx64)  # < 0
                dx = torch.from_numpy(dx64).to(device=x.device, dtype=x.dtype).reshape(x.shape)
                a = checked_max_step(model, x, dx, k)
                a = 1.0 if a >= 1.0 else settings.step_fraction * a
                for _ in range(settings.max_backtracks):
                    xt = x + a * dx
                    et, gt, gnt = evaluate(model, xt, k, f"line search, step {a:.3g}")
                    if et <= e + settings.armijo_c * a * slope + slack * abs(e):
                        accepted = True
                        break
                    a *= settings.backtrack
                if not accepted:
                    trial += 1
                    damping = LEVENBERG_START if damping == 0.0 else 10.0 * damping
                    info.restarts += 1
            if not accepted:
                info.message = f"line search failed at iteration {k} (no sufficient decrease, damping {damping:.3g})"
                k -= 1
                break
            damping = 0.0 if damping <= LEVENBERG_START else 0.1 * damping
            x, e, g, gn = xt, et, gt, gnt
            info.final_step = a
            info.residual_history.append(gn)
            info.energy_history.append(e)
            if gn <= tol:
                info.converged, info.message = True, "converged"
            if callback is not None and callback(k, x, gn, e) and not info.converged:
                info.message = "stopped by callback"
                break

    info.iterations = k
    info.seconds = timer.elapsed()
    return x, info
