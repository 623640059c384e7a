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


class SeamBlockInverse:
    """Block-Jacobi inverse in which each seam pair ``(i, j)`` is one 6x6 block.

    A sewing spring of stiffness ``k`` couples its two vertices by ``-k I``; with 3x3 blocks each vertex sees
    ``A = A0 + k I`` alone, so the pair's common motion (governed by the soft cloth ``A0 + B0``) gets steps
    ``k`` times too small and GD stalls once seams are stiff. The 6x6 block ``[[A, -k I], [-k I, B]]`` is
    inverted exactly through its Schur complement: ``u = S^-1 (g_i + k B^-1 g_j)``, ``v = B^-1 (g_j + k u)`` with
    ``S = A - k^2 B^-1``.

    Attributes:
        base: (V, 3, 3) 3x3 block inverses (used for every vertex not in a seam block).
        i, j: (P,) long vertices of the seam blocks.
        s_inv, b_inv: (P, 3, 3) ``S^-1`` and ``B^-1``.
        k: the spring constant in N/m.
    """

    def __init__(self, base: torch.Tensor, i: torch.Tensor, j: torch.Tensor, s_inv: torch.Tensor,
                 b_inv: torch.Tensor, k: float) -> None:
        self.base, self.i, self.j, self.s_inv, self.b_inv, self.k = base, i, j, s_inv, b_inv, float(k)

    def apply(self, g: torch.Tensor) -> torch.Tensor:
        """``P^-1 g`` for ``g: (V, 3)``."""
        out = torch.bmm(self.base, g.unsqueeze(-1)).squeeze(-1)
        if self.i.numel():
            gi, gj = g.index_select(0, self.i), g.index_select(0, self.j)
            bg = torch.bmm(self.b_inv, gj.unsqueeze(-1)).squeeze(-1)
            u = torch.bmm(self.s_inv, (gi + self.k * bg).unsqueeze(-1)).squeeze(-1)
            v = bg + self.k * torch.bmm(self.b_inv, u.unsqueeze(-1)).squeeze(-1)
            out.index_copy_(0, self.i, u)
            out.index_copy_(0, self.j, v)
        return out


def seam_pairs(model) -> tuple[torch.Tensor, float] | None:  # noqa: ANN001
    """The seam pairs ``(P, 2)`` that belong to no other pair, and the sewing stiffness, of a model's ``sew`` term;
    None without one."""
    term = None
    for t in getattr(model, "terms", ()):
        if getattr(t, "name", None) == "sew" and hasattr(t, "pairs") and hasattr(t, "stiffness"):
            term = t
    if term is None or term.pairs.numel() == 0:
        return None
    pairs = term.pairs
    counts = torch.bincount(pairs.flatten(), minlength=int(pairs.max()) + 1)
    keep = (counts[pairs[:, 0]] == 1) & (counts[pairs[:, 1]] == 1)
    return pairs[keep], float(term.stiffness)


def seam_block_inverse(diag_blocks: torch.Tensor, base: torch.Tensor, pairs: torch.Tensor, k: float,
                       floor: float) -> SeamBlockInverse:
    """The :class:`SeamBlockInverse` of the Hessian diagonal blocks ``(V, 3, 3)`` (which include each seam
    spring's ``k I``) for disjoint seam ``pairs`` ``(P, 2)``; pairs whose 6x6 block is not positive definite keep
    their 3x3 inverses from ``base``."""
    i, j = pairs[:, 0], pairs[:, 1]
    eye = torch.eye(3, dtype=diag_blocks.dtype, device=diag_blocks.device)
    f = floor * float(diag_blocks.diagonal(dim1=1, dim2=2).abs().mean())
    sym = 0.5 * (diag_blocks + diag_blocks.transpose(1, 2))
    a, b = sym.index_select(0, i) + f * eye, sym.index_select(0, j) + f * eye
    lb, info_b = torch.linalg.cholesky_ex(b)
    b_inv = torch.cholesky_inverse(lb)
    s = a - (k * k) * b_inv
    s = 0.5 * (s + s.transpose(1, 2))
    ls, info_s = torch.linalg.cholesky_ex(s)
    ok = (info_b == 0) & (info_s == 0)
    if not bool(ok.all()):
        i, j, ls, b_inv = i[ok], j[ok], ls[ok], b_inv[ok]
    return SeamBlockInverse(base, i, j, torch.cholesky_inverse(ls), b_inv, k)


def _preconditioner(model, h: torch.Tensor, settings: SolveSettings, seams):  # noqa: ANN001, ANN202
    """Jacobi inverse of the diagonal blocks ``h``, with seam blocks when asked for and available."""
    dinv = jacobi_inverse(h, settings.preconditioner, settings.diagonal_floor)
    if seams is None or settings.preconditioner != Preconditioner.BLOCK:
        return dinv
    return seam_block_inverse(h, dinv, seams[0], seams[1], settings.diagonal_floor)


def apply_inverse(dinv: "torch.Tensor | SeamBlockInverse", g: torch.Tensor) -> torch.Tensor:
    """``D^-1 g`` for block (V, 3, 3), scalar (V, 3) or seam-block inverses; ``g: (V, 3)``."""
    if isinstance(dinv, SeamBlockInverse):
        return dinv.apply(g)
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
        seams = seam_pairs(model) if settings.seam_blocks else None
        dinv = _preconditioner(model, h, settings, seams)
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
                dinv = _preconditioner(model, h, settings, seams)
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
                    dinv = _preconditioner(model, model.hessian_diagonal(x), settings, seams)
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
