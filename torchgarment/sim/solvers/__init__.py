"""Quasistatic solvers: find garment positions where the total force of a simulation model vanishes.

* ``"gd-chebyshev"``: Jacobi-preconditioned gradient descent with Chebyshev acceleration (Wang & Yang 2016),
  the simulator of Wang et al. 2018; cheap iterations (one gradient + Hessian diagonal), many of them.
* ``"newton"``: projected Newton with a sparse direct solve (SuperLU) and a barrier-aware Armijo line search;
  few, expensive iterations.

Example:
    >>> x, info = solve(model, x0, SolveSettings(rtol=1e-5), solver="newton")
    >>> info.converged, info.iterations, info.residual
"""

from __future__ import annotations

import torch

from torchgarment.errors import InputError
from torchgarment.sim.solvers.chebyshev import solve_gd_chebyshev
from torchgarment.sim.solvers.common import (
    DEFAULT_EXACT_CURVATURE_CG,
    Callback,
    LinearSolver,
    NonFiniteError,
    Preconditioner,
    Safeguard,
    SolveInfo,
    SolverKind,
    SolverModel,
    SolveSettings,
    check_x0,
    exact_curvature_iterations,
)
from torchgarment.sim.solvers.newton import jacobi_pcg_solve, solve_newton

__all__ = [
    "DEFAULT_EXACT_CURVATURE_CG",
    "LinearSolver",
    "NonFiniteError",
    "Preconditioner",
    "Safeguard",
    "SolveInfo",
    "SolveSettings",
    "SolverKind",
    "exact_curvature_iterations",
    "jacobi_pcg_solve",
    "solve",
]


def solve(
    model: SolverModel,
    x0: torch.Tensor,
    settings: SolveSettings | None = None,
    solver: "str | SolverKind" = SolverKind.GD_CHEBYSHEV,
    max_iterations: int | None = None,
    callback: Callback | None = None,
) -> tuple[torch.Tensor, SolveInfo]:
    """Solve for the quasistatic equilibrium of ``model`` starting from ``x0``.

    Args:
        model: a :class:`~torchgarment.sim.scene.SimModel` (or anything with its solver interface).
        x0: (V, 3) feasible initial positions (metres), on the model's device and dtype.
        settings: tolerances and solver parameters; defaults to ``SolveSettings()``.
        solver: ``"gd-chebyshev"`` or ``"newton"`` (a :class:`SolverKind` or its value).
        max_iterations: overrides ``settings.max_iterations`` (e.g. Wang 2018's inexact inner solves).
        callback: ``callback(k, x, |g|, E)`` after every iteration; returning True stops the solve.

    Returns:
        ``(x, info)``: equilibrium positions (V, 3), detached, same dtype/device as ``x0``, and a
        :class:`SolveInfo` with the force-norm and energy histories.

    Raises:
        InputError: unknown solver, bad settings or malformed ``x0``.
        NonFiniteError: the model returned NaN/Inf (the message names the iteration).
    """
    kind = SolverKind.resolve(solver)
    settings = SolveSettings() if settings is None else settings
    settings.validate()
    n_iter = settings.max_iterations if max_iterations is None else int(max_iterations)
    if n_iter < 0:
        raise InputError(f"max_iterations must be >= 0, got {n_iter}")
    check_x0(model, x0)
    if kind == SolverKind.NEWTON:
        return solve_newton(model, x0, settings, n_iter, callback)
    return solve_gd_chebyshev(model, x0, settings, n_iter, callback)
