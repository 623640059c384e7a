"""Jacobi-preconditioned gradient descent with Chebyshev acceleration (Wang & Yang 2016).

The method Wang et al. 2018 (section 4.2) use for their quasistatic garment simulator. With ``D`` the Hessian's
diagonal (3x3 blocks per vertex, or its scalar diagonal) and ``alpha`` an under-relaxation step, each iteration is

    x_bar    = x_k - alpha * D^-1 g(x_k)
    x_{k+1}  = omega_{k+1} (x_bar - x_{k-1}) + x_{k-1}

with the Chebyshev weights ``omega_1..S = 1`` (``S`` = ``chebyshev_delay`` plain steps), ``omega_{S+1} =
2 / (2 - rho^2)`` and ``omega_{k+1} = 4 / (4 - rho^2 omega_k)`` afterwards, ``rho`` an estimate of the spectral
radius of the Jacobi iteration. Every ``check_interval`` iterations the energy is compared with the last
checkpoint; if it increased, the solver rolls back to the checkpoint, multiplies ``alpha`` by ``step_decrease``
and restarts the Chebyshev sequence (Wang & Yang's step-length adjustment).

To keep barriers finite each step is either capped by ``0.9 * model.max_step`` (``Safeguard.MAX_STEP``) or
followed by ``model.project_feasible`` (``Safeguard.PROJECT``, Wang 2018's per-vertex projection onto the body).

One iteration costs one ``model.value_and_grad`` plus, every ``diagonal_interval`` iterations, one
``model.hessian_diagonal`` and a batched 3x3 inverse, plus the safeguard (``max_step`` or ``project_feasible``).
"""

from __future__ import annotations

import math

import torch

from torchgarment.errors import InputError
from torchgarment.sim.solvers.common import (
    Callback,
    NonFiniteError,
    Preconditioner,
    Safeguard,
    SolveInfo,
    SolverKind,
    SolverModel,
    SolveSettings,
    Timer,
    checked_max_step,
    evaluate,
    evaluate_with_diagonal,
    tolerance,
)


def jacobi_inverse(diag_blocks: torch.Tensor, kind: Preconditioner, floor: float) -> torch.Tensor:
    """Inverse of the Jacobi preconditioner.

    Args:
        diag_blocks: (V, 3, 3) Hessian diagonal blocks.
        kind: BLOCK inverts each (symmetrized) 3x3 block; blocks that are not positive definite after adding
            ``floor * I`` use the inverse of their clamped scalar diagonal ``max(|H_ii|, floor)`` instead.
            SCALAR always uses the clamped scalar diagonal.
        floor: relative floor, multiplied by the mean of the (absolute) diagonal entries.

    Returns:
        (V, 3, 3) inverse blocks for BLOCK, (V, 3) inverse diagonal for SCALAR.

    Raises:
        NonFiniteError: the blocks contain NaN/Inf.
        InputError: the Hessian diagonal is zero everywhere (the preconditioner is undefined).
    """
    h = diag_blocks
    V = h.shape[0]
    hv = h.reshape(V, 9)
    dsafe = hv[:, 0::4].abs()  # (V, 3) diagonal entries
    scale = float(dsafe.mean()) if V else 0.0
    if not math.isfinite(scale):
        raise NonFiniteError("model.hessian_diagonal returned non-finite values")
    if scale <= 0.0:
        raise InputError("the Hessian diagonal is zero everywhere; the Jacobi preconditioner is undefined")
    f = floor * scale
    dsafe.clamp_min_(f)
    if kind == Preconditioner.SCALAR:
        return dsafe.reciprocal_()
    # symmetrized block plus floor * I, inverted through the adjugate; PD tested by the leading minors.
    # Every entry is read once into a contiguous (V,) vector (no (V, 3, 3) temporaries, no transposed copies).
    a00, a11, a22 = hv[:, 0] + f, hv[:, 4] + f, hv[:, 8] + f
    a01 = (hv[:, 1] + hv[:, 3]).mul_(0.5)
    a02 = (hv[:, 2] + hv[:, 6]).mul_(0.5)
    a12 = (hv[:, 5] + hv[:, 7]).mul_(0.5)
    c00 = torch.mul(a11, a22).addcmul_(a12, a12, value=-1.0)
    c01 = torch.mul(a02, a12).addcmul_(a01, a22, value=-1.0)
    c02 = torch.mul(a01, a12).addcmul_(a02, a11, value=-1.0)
    c11 = torch.mul(a00, a22).addcmul_(a02, a02, value=-1.0)
    c12 = torch.mul(a01, a02).addcmul_(a00, a12, value=-1.0)
    c22 = torch.mul(a00, a11).addcmul_(a01, a01, value=-1.0)
    det = (a00 * c00).addcmul_(a01, c01).addcmul_(a02, c02)
    # relative tests so that nearly singular blocks (det ~ roundoff) also fall back
    tiny = 1e3 * torch.finfo(h.dtype).eps
    m2 = a00 * a11
    pd = (a00 > 0) & (c22 > tiny * m2) & (det > m2.mul_(a22).mul_(tiny))
    all_pd = bool(pd.all())
    scale_inv = det.reciprocal_() if all_pd else torch.where(pd, det, torch.ones_like(det)).reciprocal_()
    inv = torch.stack([c00, c01, c02, c01, c11, c12, c02, c12, c22], dim=1).mul_(scale_inv.unsqueeze(1))
    if not all_pd:
        bad = torch.nonzero(~pd, as_tuple=False).flatten()
        fallback = torch.zeros(bad.numel(), 9, dtype=h.dtype, device=h.device)
        fallback[:, 0::4] = dsafe[bad].reciprocal()
        inv[bad] = fallback
    return inv.view(V, 3, 3)


def apply_inverse(dinv: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """``D^-1 g`` for block (V, 3, 3) or scalar (V, 3) inverses; ``g: (V, 3)``."""
    if dinv.dim() == 2:
        return dinv * g
    return torch.bmm(dinv, g.unsqueeze(-1)).squeeze(-1)


def clamp_displacement_(step: torch.Tensor, max_length: float) -> torch.Tensor:
    """Scale rows of ``step`` (V, 3) in place so that no vertex moves more than ``max_length`` metres."""
    n = torch.linalg.vector_norm(step, dim=1, keepdim=True)
    return step.mul_((max_length / n.clamp_min(max_length)))


def chebyshev_weight(iteration: int, omega: float, rho: float, delay: int) -> float:
    """Chebyshev weight ``omega_{k+1}`` for the ``iteration``-th step since the last restart (0-based)."""
    if rho <= 0.0 or iteration < delay:
        return 1.0
    if iteration == delay:
        return 2.0 / (2.0 - rho * rho)
    return 4.0 / (4.0 - rho * rho * omega)


def solve_gd_chebyshev(
    model: SolverModel,
    x0: torch.Tensor,
    settings: SolveSettings,
    max_iterations: int,
    callback: Callback | None = None,
) -> tuple[torch.Tensor, SolveInfo]:
    """Minimize the model's energy from ``x0`` with Jacobi-preconditioned, Chebyshev-accelerated descent.

    Args:
        model: the simulation model (see :class:`~torchgarment.sim.solvers.common.SolverModel`).
        x0: (V, 3) initial positions (metres); must be feasible (all barriers finite).
        settings: solver settings (validated by the caller).
        max_iterations: iteration budget.
        callback: called after every iteration as ``callback(k, x, |g|, E)``; returning True stops.

    Returns:
        ``(x, info)``: the final positions (V, 3) and a :class:`SolveInfo`.
    """
    timer = Timer()
    info = SolveInfo(solver=SolverKind.GD_CHEBYSHEV.value)
    rho = settings.chebyshev_rho
    alpha = settings.step
    slack = 16.0 * torch.finfo(x0.dtype).eps

    with torch.no_grad():
        x = x0.detach().clone()
        e, g, gn, h = evaluate_with_diagonal(model, x, 0, "initial state")
        dinv = jacobi_inverse(h, settings.preconditioner, settings.diagonal_floor)
        info.residual_history.append(gn)
        info.energy_history.append(e)
        tol = tolerance(settings, gn)
        ckpt = (x, e, g, gn)
        x_prev: torch.Tensor | None = None
        omega = 1.0
        since_restart = 0
        info.message = "max iterations reached"
        if gn <= tol:
            info.converged, info.message = True, "converged"

        k = 0
        while not info.converged and k < max_iterations:
            step = apply_inverse(dinv, g).mul_(-alpha)
            omega = chebyshev_weight(since_restart, omega, rho, settings.chebyshev_delay)
            if omega != 1.0 and x_prev is not None:
                # x_new - x = omega (x + step - x_prev) + x_prev - x = omega step + (omega - 1) (x - x_prev)
                step.mul_(omega).add_(x - x_prev, alpha=omega - 1.0)
            if settings.max_displacement is not None:
                clamp_displacement_(step, settings.max_displacement)
            if settings.safeguard == Safeguard.MAX_STEP:
                t = checked_max_step(model, x, step, k + 1)
                if t < 1.0:
                    step.mul_(settings.step_fraction * t)
                x_new = x + step
            else:
                x_new = model.project_feasible(x + step)
            x_prev, x = x, x_new
            since_restart += 1
            k += 1
            if k % settings.diagonal_interval == 0:
                e, g, gn, h = evaluate_with_diagonal(model, x, k)
                dinv = jacobi_inverse(h, settings.preconditioner, settings.diagonal_floor)
            else:
                e, g, gn = evaluate(model, x, k)
            if gn <= tol:
                info.converged, info.message = True, "converged"
            elif k % settings.check_interval == 0:
                e_ck = ckpt[1]
                if e > e_ck + slack * max(abs(e_ck), abs(e)):
                    # energy went up since the checkpoint: roll back, shrink the step, restart Chebyshev
                    x, e, g, gn = ckpt
                    x_prev, omega, since_restart = None, 1.0, 0
                    dinv = jacobi_inverse(model.hessian_diagonal(x), settings.preconditioner, settings.diagonal_floor)
                    alpha *= settings.step_decrease
                    info.restarts += 1
                    if alpha < settings.min_step:
                        info.message = f"step fell below min_step={settings.min_step:g} (energy keeps increasing)"
                        info.residual_history.append(gn)
                        info.energy_history.append(e)
                        break
                else:
                    ckpt = (x, e, g, gn)
            info.residual_history.append(gn)
            info.energy_history.append(e)
            if callback is not None and callback(k, x, gn, e) and not info.converged:
                info.message = "stopped by callback"
                break

    info.iterations = k
    info.final_step = alpha
    info.seconds = timer.elapsed()
    return x, info
