"""Jacobi-preconditioned gradient descent with Chebyshev acceleration (Wang & Yang 2016).

The method Wang et al. 2018 (section 4.2) use for their quasistatic garment simulator. With ``D`` the
Hessian's diagonal (3x3 blocks per vertex, or its scalar diagonal) and ``alpha`` an under-relaxation step,
each iteration is

    x_bar    = x_k - alpha * D^-1 g(x_k)
    x_{k+1}  = omega_{k+1} (x_bar - x_{k-1}) + x_{k-1}

with the Chebyshev weights ``omega_1..S = 1`` (``S`` = ``chebyshev_delay`` plain steps), ``omega_{S+1} =
2 / (2 - rho^2)`` and ``omega_{k+1} = 4 / (4 - rho^2 omega_k)`` afterwards, ``rho`` an estimate of the
spectral radius of the Jacobi iteration. Every ``check_interval`` iterations the energy is compared with the
last checkpoint; if it increased, the solver rolls back to the checkpoint, multiplies ``alpha`` by
``step_decrease`` and restarts the Chebyshev sequence (Wang & Yang's step-length adjustment).

To keep barriers finite each step is either capped by ``0.9 * model.max_step`` (``Safeguard.MAX_STEP``) or
followed by ``model.project_feasible`` (``Safeguard.PROJECT``, Wang 2018's per-vertex projection onto the
body).

One iteration costs one ``model.value_and_grad`` plus, every ``diagonal_interval`` iterations (default 1), the
Hessian diagonal and a batched 3x3 inverse, plus the safeguard (``max_step`` or ``project_feasible``). The
diagonal of the volatile terms (barriers, contact) is evaluated at the current positions; that of the elastic
terms, which changes slowly, every ``elastic_diagonal_interval`` iterations (default 4) and reused in between.
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
    energy_float64,
    evaluate,
    evaluate_with_diagonal,
    supports_elastic_reuse,
    tolerance,
)


def diagonal_scale(diag_blocks: torch.Tensor) -> float:
    """The mean absolute diagonal entry of ``diag_blocks`` (V, 3, 3): the scale of the relative floor."""
    return float(diag_blocks.reshape(-1, 9)[:, 0::4].abs().mean()) if diag_blocks.shape[0] else 0.0


def jacobi_inverse(diag_blocks: torch.Tensor, kind: Preconditioner, floor: float,
                   scale: float | None = None) -> torch.Tensor:
    """Inverse of the Jacobi preconditioner.

    Args:
        diag_blocks: (V, 3, 3) Hessian diagonal blocks (or a subset of the rows).
        kind: BLOCK inverts each (symmetrized) 3x3 block; blocks that are not positive definite after adding
            ``floor * I`` use the inverse of their clamped scalar diagonal ``max(|H_ii|, floor)`` instead.
            SCALAR always uses the clamped scalar diagonal.
        floor: relative floor, multiplied by ``scale``.
        scale: the floor's scale; None = :func:`diagonal_scale` of ``diag_blocks`` (pass the full matrix's
            scale when inverting a subset of the rows).

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
    if scale is None:
        scale = float(dsafe.mean()) if V else 0.0
    if not math.isfinite(scale):
        raise NonFiniteError("model.hessian_diagonal returned non-finite values")
    if scale <= 0.0:
        raise InputError("the Hessian diagonal is zero everywhere; the Jacobi preconditioner is undefined")
    f = floor * scale
    dsafe.clamp_min_(f)
    if kind == Preconditioner.SCALAR:
        return dsafe.reciprocal_()
    inv, pd = spd_inverse_3x3(h, shift=f)
    if not bool(pd.all()):  # non positive-definite blocks: the clamped scalar diagonal
        bad = torch.nonzero(~pd, as_tuple=False).flatten()
        fallback = torch.zeros(bad.numel(), 9, dtype=h.dtype, device=h.device)
        fallback[:, 0::4] = dsafe[bad].reciprocal()
        inv.view(V, 9)[bad] = fallback
    return inv


class SeamBlockInverse:
    """Block-Jacobi inverse in which each seam pair ``(i, j)`` is one 6x6 block.

    A sewing spring of stiffness ``k`` couples its two vertices by ``-k I``; with 3x3 blocks each vertex sees
    ``A = A0 + k I`` alone, so the pair's common motion (governed by the soft cloth ``A0 + B0``) gets steps
    ``k`` times too small and GD stalls once seams are stiff. The 6x6 block ``[[A, -k I], [-k I, B]]`` is
    inverted exactly through its Schur complement: ``u = S^-1 (g_i + k B^-1 g_j)``, ``v = B^-1 (g_j + k u)``
    with ``S = A - k^2 B^-1``.

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


def seam_pairs(model: SolverModel) -> tuple[torch.Tensor, float] | None:
    """The seam pairs ``(P, 2)`` that belong to no other pair, and the sewing stiffness, of a model's ``sew``
    term; None without one."""
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


_SELECTIONS: dict[tuple[torch.dtype, torch.device], tuple[torch.Tensor, torch.Tensor]] = {}


def _selections(dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """The (6, 9) matrices of :func:`spd_inverse_3x3`, cached per dtype and device: ``into`` maps a row-major
    3x3 block to ``(a00, a11, a22, a01, a02, a12)`` of its symmetric part, ``out`` the six cofactors ``(c00,
    c01, c02, c11, c12, c22)`` back to a row-major symmetric block. Their entries are 0, 0.5 and 1, so the
    products through them are exact: each result is one entry, or the halved sum of two, as elementwise code
    would compute it."""
    key = (dtype, device)
    hit = _SELECTIONS.get(key)
    if hit is None:
        into = torch.zeros(6, 9, dtype=dtype)
        out = torch.zeros(6, 9, dtype=dtype)
        for row, (i, j) in enumerate(((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))):
            into[row, 3 * i + j] += 0.5
            into[row, 3 * j + i] += 0.5
        for row, (i, j) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))):
            out[row, 3 * i + j] = 1.0
            out[row, 3 * j + i] = 1.0
        hit = _SELECTIONS[key] = (into.to(device), out.to(device))
    return hit


def spd_inverse_3x3(blocks: torch.Tensor, shift: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverses of the symmetric parts of ``blocks`` (N, 3, 3) plus ``shift * I`` through the adjugate (a few
    vectorized operations; batched LAPACK calls on 3x3 matrices cost far more), and which of them are positive
    definite (by the leading minors, relative to round-off).

    The six distinct entries are taken out, and the six cofactors put back, by one exact matrix product each
    (:func:`_selections`), so the arithmetic in between runs on contiguous (N,) rows: strided column reads and
    writes of an (N, 9) view cost about 0.1 ms each at N = 30K, the whole inverse half as much as before
    (``README.md``, "The parts of an iteration"). The results are the same to the bit.

    Returns:
        ``(inv, pd)``: (N, 3, 3) inverses (meaningless where not ``pd``) and an (N,) bool mask.
    """
    n = blocks.shape[0]
    into, out = _selections(blocks.dtype, blocks.device)
    a = into @ blocks.reshape(n, 9).T  # (6, N): a00, a11, a22, a01, a02, a12
    if shift != 0.0:
        a[0:3] += shift
    a00, a11, a22, a01, a02, a12 = a.unbind(0)
    c = torch.empty(6, n, dtype=blocks.dtype, device=blocks.device)
    c00, c01, c02, c11, c12, c22 = c.unbind(0)
    torch.mul(a11, a22, out=c00).addcmul_(a12, a12, value=-1.0)
    torch.mul(a02, a12, out=c01).addcmul_(a01, a22, value=-1.0)
    torch.mul(a01, a12, out=c02).addcmul_(a02, a11, value=-1.0)
    torch.mul(a00, a22, out=c11).addcmul_(a02, a02, value=-1.0)
    torch.mul(a01, a02, out=c12).addcmul_(a00, a12, value=-1.0)
    torch.mul(a00, a11, out=c22).addcmul_(a01, a01, value=-1.0)
    det = (a00 * c00).addcmul_(a01, c01).addcmul_(a02, c02)
    tiny = 1e3 * torch.finfo(blocks.dtype).eps
    m2 = a00 * a11
    pd = (a00 > 0) & (c22 > tiny * m2) & (det > m2.mul_(a22).mul_(tiny))
    inv_det = torch.where(pd, det, torch.ones_like(det)).reciprocal_()
    c.mul_(inv_det)
    return (c.T @ out).view(n, 3, 3), pd


def seam_block_inverse(diag_blocks: torch.Tensor, base: torch.Tensor, pairs: torch.Tensor, k: float,
                       floor: float, scale: float | None = None) -> SeamBlockInverse:
    """The :class:`SeamBlockInverse` of the Hessian diagonal blocks ``(V, 3, 3)`` (which include each seam
    spring's ``k I``) for disjoint seam ``pairs`` ``(P, 2)``; pairs whose 6x6 block is not positive definite
    keep their 3x3 inverses from ``base``. ``floor * scale`` is added to the diagonal (``scale`` None: the
    mean absolute diagonal entry of ``diag_blocks``)."""
    i, j = pairs[:, 0], pairs[:, 1]
    f = floor * (diagonal_scale(diag_blocks) if scale is None else scale)
    a, b = diag_blocks.index_select(0, i), diag_blocks.index_select(0, j)  # only the pairs' rows
    b_inv, ok_b = spd_inverse_3x3(b, shift=f)
    s_inv, ok_s = spd_inverse_3x3(a - (k * k) * b_inv, shift=f)
    ok = ok_b & ok_s
    if not bool(ok.all()):
        i, j, s_inv, b_inv = i[ok], j[ok], s_inv[ok], b_inv[ok]
    return SeamBlockInverse(base, i, j, s_inv, b_inv, k)


class JacobiState:
    """The GD-Chebyshev preconditioner ``D^-1`` (3x3 blocks or scalars, with seam blocks when asked for),
    rebuilt in full or, between elastic refreshes, only on the rows whose diagonal changed.

    Between two full rebuilds only the volatile terms' diagonal changes (barriers, contact; see
    ``SimModel.value_grad_hessian_diagonal(reuse_elastic=True)``), and a range-limited barrier touches only
    the vertices within its range, a few percent of a garment. :meth:`update` re-inverts just the rows it
    touches now or touched at the last update (a vertex that left the barrier's range must lose its barrier
    stiffness), keeping the floor's scale of the last full rebuild; the result equals a full rebuild up to
    that scale.

    Attributes:
        inverse: the current inverse, for :func:`apply_inverse`.
    """

    def __init__(self, settings: SolveSettings, seams: "tuple[torch.Tensor, float] | None") -> None:
        self.settings = settings
        self.seams = seams if settings.preconditioner == Preconditioner.BLOCK else None
        self.inverse: "torch.Tensor | SeamBlockInverse | None" = None
        self._base: torch.Tensor | None = None
        self._scale = 0.0
        self._rows: torch.Tensor | None = None  # volatile rows of the last build or update (None: unknown)

    def rebuild(self, h: torch.Tensor, rows: torch.Tensor | None = None) -> None:
        """Invert the full diagonal ``h`` (V, 3, 3); ``rows`` (long) are the rows the volatile terms touched
        in ``h`` (None: unknown, which makes the next :meth:`update` a full rebuild)."""
        st = self.settings
        self._scale = diagonal_scale(h)
        self._base = jacobi_inverse(h, st.preconditioner, st.diagonal_floor, self._scale)
        self._finish(h)
        self._rows = rows

    def update(self, h: torch.Tensor, rows: torch.Tensor | None) -> None:
        """Re-invert the rows of ``h`` (V, 3, 3) touched by the volatile terms now (``rows``) or at the last
        build; a full :meth:`rebuild` when either is unknown."""
        if rows is None or self._rows is None or self._base is None:
            self.rebuild(h, rows)
            return
        st = self.settings
        mask = torch.zeros(h.shape[0], dtype=torch.bool, device=h.device)
        mask[rows] = True
        mask[self._rows] = True
        idx = torch.nonzero(mask, as_tuple=False).flatten()
        if idx.numel():
            rows_h = h.index_select(0, idx)
            if not bool(torch.isfinite(rows_h).all()):
                raise NonFiniteError("model.hessian_diagonal returned non-finite values")
            part = jacobi_inverse(rows_h, st.preconditioner, st.diagonal_floor, self._scale)
            self._base.index_copy_(0, idx, part)
            if self.seams is not None:
                self._finish(h)
        self._rows = rows

    def _finish(self, h: torch.Tensor) -> None:
        if self.seams is None:
            self.inverse = self._base
        else:
            self.inverse = seam_block_inverse(h, self._base, self.seams[0], self.seams[1],
                                              self.settings.diagonal_floor, self._scale)


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
    if step.shape[0] == 0 or float(n.max()) <= max_length:
        return step
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
    # Energies are compared in float64 even for a float32 solve: float32 energies carry round-off (~eps times
    # the energy's terms) far above the decrease per iteration near convergence, which made the test below
    # roll back good steps until the step fell below min_step. One extra float64 energy evaluation per
    # checkpoint.
    low_precision = x0.dtype != torch.float64
    slack = 16.0 * torch.finfo(torch.float64).eps

    def check_energy(xc: torch.Tensor, ec: float) -> float:
        return energy_float64(model, xc) if low_precision else ec

    with torch.no_grad():
        x = x0.detach().clone()
        e, g, gn, h = evaluate_with_diagonal(model, x, 0, "initial state")
        pre = JacobiState(settings, seam_pairs(model) if settings.seam_blocks else None)
        pre.rebuild(h, getattr(model, "last_volatile_rows", None))
        info.residual_history.append(gn)
        info.energy_history.append(e)
        tol = tolerance(settings, gn)
        ckpt = (x, e, g, gn)
        e_ck = check_energy(x, e)
        x_prev: torch.Tensor | None = None
        omega = 1.0
        since_restart = 0
        info.message = "max iterations reached"
        if gn <= tol:
            info.converged, info.message = True, "converged"

        elastic_interval = settings.elastic_diagonal_interval if supports_elastic_reuse(model) else 1
        k = 0
        while not info.converged and k < max_iterations:
            step = apply_inverse(pre.inverse, g).mul_(-alpha)
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
                reuse = k % elastic_interval != 0
                e, g, gn, h = evaluate_with_diagonal(model, x, k, reuse_elastic=reuse, infeasible_ok=True)
                if e != math.inf:
                    rows = getattr(model, "last_volatile_rows", None)
                    if reuse:
                        pre.update(h, rows)
                    else:
                        pre.rebuild(h, rows)
            else:
                e, g, gn = evaluate(model, x, k, infeasible_ok=True)
            if gn <= tol:
                info.converged, info.message = True, "converged"
            elif e == math.inf or k % settings.check_interval == 0:
                # +inf: a barrier's infeasible side, which the step bound should have kept out (a closing
                # contact's round-off); rejected at once like an energy increase
                e_now = e if e == math.inf else check_energy(x, e)
                if e_now == math.inf or e_now > e_ck + slack * max(abs(e_ck), abs(e_now)):
                    # energy went up since the checkpoint: roll back, shrink the step, restart Chebyshev
                    x, e, g, gn = ckpt
                    x_prev, omega, since_restart = None, 1.0, 0
                    pre.rebuild(model.hessian_diagonal(x))
                    if elastic_interval > 1:
                        # the first remedy is the approximation, not the step: with a reused (stale) elastic
                        # diagonal, go on from the checkpoint with a fresh one every iteration, step unchanged
                        elastic_interval = 1
                    else:
                        alpha *= settings.step_decrease
                    info.restarts += 1
                    if alpha < settings.min_step:
                        info.message = (f"step fell below min_step={settings.min_step:g} "
                                        f"(energy keeps increasing)")
                        info.residual_history.append(gn)
                        info.energy_history.append(e)
                        break
                else:
                    ckpt, e_ck = (x, e, g, gn), e_now
            info.residual_history.append(gn)
            info.energy_history.append(e)
            if callback is not None and callback(k, x, gn, e) and not info.converged:
                info.message = "stopped by callback"
                break

    info.iterations = k
    info.final_step = alpha
    info.seconds = timer.elapsed()
    return x, info
