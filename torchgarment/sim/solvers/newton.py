"""Projected Newton with a sparse direct solver, a pluggable step bound and a backtracking line search.

The one Newton loop of the package: the quasistatic drape (:func:`~torchgarment.sim.solvers.solve`) and the
garment retargeting (:func:`~torchgarment.retarget.solver.projected_newton`) both run :func:`solve_newton`;
what differs between them is passed in :class:`NewtonOptions` (which unknowns are free, how the step is
bounded, the regularization policy, extra stopping rules, a hook after every accepted step).

Each iteration assembles the Hessian from ``model.hessian_blocks(x, project_psd=True)`` (per-element blocks
projected to positive semi-definite) into a scipy CSR matrix on the CPU, solves ``H dx = -g`` with SuperLU
(or, with ``SolveSettings.linear_solver = "jacobi-pcg"``, by block-Jacobi CG on the positions' device,
:func:`jacobi_pcg_solve`), caps the step at ``step_fraction * model.max_step(x, dx)`` when the full step
would make a barrier infinite (or at ``NewtonOptions.step_bound.max_step(x, dx)``, e.g. retargeting's CCD
bound), and backtracks (:func:`armijo_backtracking`) until the Armijo condition
``E(x + a dx) <= E(x) + c a g.dx`` holds. When the factorization fails or the solution is not a descent
direction, ``lambda * I`` is added (``lambda`` growing tenfold per retry).

When the line search fails (the projected Hessian is a poor model: dropped negative-curvature parts of
compressed springs or of the barrier, a non-smooth SDF), the step is not abandoned: the direction is
recomputed with a Levenberg damping ``(H + lambda diag(H)) dx = -g`` (``lambda`` from ``levenberg_start``,
tenfold per retry, up to :data:`LEVENBERG_RETRIES` retries), which bends the step towards scaled gradient
descent and shortens it. A damping that worked is kept (divided by ten per successful iteration) so that the
next iterations start from it. The solve stops as stalled only when every damped direction also fails.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Protocol

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from torchgarment.errors import InputError, NonConvergenceError, SingularMatrixError
from torchgarment.linalg import (
    CSRAssembler,
    FactorCache,
    SparseBackend,
    armijo_backtracking,
    csr_matvec,
    factorize,
    fill_reducing_permutation,
    pcg,
)
from torchgarment.sim.solvers.chebyshev import JacobiState, apply_inverse, seam_pairs
from torchgarment.sim.solvers.common import (
    Callback,
    LinearSolver,
    NonFiniteError,
    Preconditioner,
    SolveInfo,
    SolverKind,
    SolverModel,
    SolveSettings,
    Timer,
    checked_evaluation,
    checked_max_step,
    energy_float64,
    evaluate,
    tolerance,
)

LEVENBERG_START = 1e-4
"""First Levenberg damping ``lambda`` (relative to the Hessian diagonal) after a failed line search."""

LEVENBERG_RETRIES = 8
"""Damped directions tried (``lambda`` tenfold each) before a failed line search stops the solve."""


def sparse_solve(h: scipy.sparse.csr_matrix, rhs: np.ndarray, cache: FactorCache | None = None,
                 shift: float = 0.0, backend: SparseBackend = SparseBackend.SUPERLU,
                 ordering: np.ndarray | None = None) -> np.ndarray | None:
    """Solve ``h y = rhs`` by :func:`~torchgarment.linalg.factorize` (symmetric mode of ``backend``, in
    ``ordering`` when given); None if the factorization fails or is not finite. With a ``cache``, a successful
    factorization is stored in it (as one of ``h`` made with diagonal ``shift``)."""
    try:
        fact = factorize(h, backend=backend, what="Newton system", ordering=ordering)
        y = fact.solve(rhs)
    except SingularMatrixError:
        return None
    if cache is not None:
        cache.store(fact, shift)
    return y


def jacobi_pcg_solve(h: scipy.sparse.csr_matrix, rhs: np.ndarray, device: torch.device, rtol: float,
                     max_iterations: int, *, blocks: bool = True,
                     seams: tuple[torch.Tensor, float] | None = None) -> tuple[np.ndarray | None, int]:
    """Solve ``h y = rhs`` (``h`` symmetric positive definite) by conjugate gradients on ``device``,
    preconditioned by the inverse of ``h``'s 3x3 diagonal blocks (``blocks``; unknowns ordered ``x, y, z`` per
    vertex) or of its scalar diagonal.

    With ``seams`` (disjoint seam pairs ``(P, 2)`` and the sewing stiffness ``k``, as
    :func:`~torchgarment.sim.solvers.chebyshev.seam_pairs` gives them) each pair's 6x6 block, coupled by
    ``-k I``, is inverted exactly (:func:`~torchgarment.sim.solvers.chebyshev.seam_block_inverse`, the GD
    solver's seam blocks): stiff seams otherwise make CG creep.

    No factorization: one CSR product (scipy's on the CPU, torch's elsewhere) and one batched 3x3 product per
    iteration, on ``device`` (torch tensors, :func:`~torchgarment.linalg.pcg`). Stops at relative residual
    ``rtol``, after ``max_iterations``, or at a direction of non-positive curvature (Steihaug), returning the
    iterate reached; from a zero start every CG iterate is a descent direction of the quadratic model.

    Args:
        h: (n, n) CSR float64 (n a multiple of 3 when ``blocks``).
        rhs: (n,) float64.
        device: where the iteration runs.
        rtol, max_iterations: CG's stopping rule.
        blocks: 3x3 block Jacobi (True) or scalar Jacobi.

    Returns:
        ``(y, iterations)``: y (n,) float64, or None when it is not finite.
    """
    n = h.shape[0]
    if blocks and n % 3:
        raise InputError(f"block-Jacobi PCG needs 3 unknowns per vertex, got a system of size {n}")
    coo = h.tocoo()
    if blocks:
        same = coo.row // 3 == coo.col // 3  # the entries of the 3x3 diagonal blocks
        diag = torch.zeros(n // 3, 9, dtype=torch.float64)
        diag.index_put_((torch.from_numpy(coo.row[same] // 3),
                         torch.from_numpy(coo.row[same] % 3 * 3 + coo.col[same] % 3)),
                        torch.from_numpy(coo.data[same]), accumulate=True)
        diag = diag.view(-1, 3, 3).to(device)
        # the GD solver's preconditioner, as the iterative adjoint builds it (one mechanism)
        pre = JacobiState(SolveSettings(preconditioner=Preconditioner.BLOCK, diagonal_floor=1e-8),
                          None if seams is None else (seams[0].to(device), seams[1]))
        pre.rebuild(diag)
        inv = pre.inverse

        def precondition(r: torch.Tensor) -> torch.Tensor:
            return apply_inverse(inv, r.view(-1, 3)).view(-1)
    else:
        d = torch.from_numpy(np.abs(h.diagonal()))
        dinv = d.clamp_min(1e-8 * float(d.mean()) if n else 1.0).reciprocal_().to(device)

        def precondition(r: torch.Tensor) -> torch.Tensor:
            return dinv * r

    matvec = csr_matvec(h, device)
    b = torch.from_numpy(np.ascontiguousarray(rhs, dtype=np.float64)).to(device)
    try:
        y, iterations, _ = pcg(matvec, b, precondition, rtol, max_iterations, stop_at_negative_curvature=True)
    except NonConvergenceError:
        return None, 0
    out = y.cpu().numpy()
    return (out if np.all(np.isfinite(out)) else None), iterations


@dataclass
class NewtonStep:
    """One accepted Newton step, as passed to :attr:`NewtonOptions.after_step`.

    Attributes:
        iteration: 1-based iteration. energy: energy after the step. grad_norm: gradient norm over the free
        unknowns before the step. alpha: accepted step. alpha_max: the step bound it started from.
        displacement: the step bound's displacement measure of the accepted step (units of x).
    """

    iteration: int
    energy: float
    grad_norm: float
    alpha: float
    alpha_max: float
    displacement: float


class StepLimiter(Protocol):
    """A pluggable step bound (see :attr:`NewtonOptions.step_bound`)."""

    def max_step(self, x: torch.Tensor, dx: torch.Tensor) -> float:
        """Largest admissible ``alpha >= 0`` of the step ``x + alpha dx`` (any safety fraction applied)."""
        ...

    def displacement(self, dx: torch.Tensor) -> float:
        """The largest displacement of the step ``dx`` (for ``step_tol`` and the statistics)."""
        ...


@dataclass
class NewtonOptions:
    """What a caller of :func:`solve_newton` can change beyond :class:`SolveSettings` (defaults: the drape's
    projected Newton).

    Attributes:
        free: (V, 3) bool mask of the unknowns that move (others keep their value in ``x0``); None: all.
        step_bound: a :class:`StepLimiter`; None: ``step_fraction * model.max_step(x, dx)`` when below 1
            (the barrier's bound, draping).
        regularize_first: factorize ``H + lambda I`` from the start (``lambda = settings.regularization``
            times the mean Hessian diagonal) instead of trying ``H`` alone first.
        regularization_growth: factor applied to ``lambda`` per retry (> 1).
        gradient_fallback: when no regularized factorization gives a descent direction, take the scaled
            gradient ``-g / mean(diag H)`` instead of raising :class:`NonFiniteError`.
        levenberg: after a failed line search retry with Levenberg-damped directions (module docstring);
            False: stop at once.
        value_only_line_search: the line search evaluates energies only (``model.energy``) and the gradient
            once after the step is accepted; False: ``model.value_and_grad`` per trial (+inf, a barrier's
            infeasible side, rejects the trial; NaN or a non-finite gradient raises).
        armijo_slack: the Armijo test tolerates ``armijo_slack * eps * |E|`` (rounding of large energies;
            ``eps`` of float64: a float32 solve's line search compares float64 energies).
        step_tol: stop (not converged) when the accepted step's displacement is <= this (> 0); 0 disables.
        energy_tol: stop (converged) when the energy fell by less than ``energy_tol * |E|`` over the last
            ``energy_window`` steps; 0 disables. The window holds the energies of one objective: when
            ``after_step`` changes the model, it starts again from the new objective's energy.
        after_step: ``after_step(x, step) -> changed``, called after every accepted step (before the
            convergence test); returning True says the model changed (e.g. a barrier stiffness update), and
            the energy and
            gradient are evaluated again.
    """

    free: torch.Tensor | None = None
    step_bound: StepLimiter | None = None
    regularize_first: bool = False
    regularization_growth: float = 10.0
    gradient_fallback: bool = False
    levenberg: bool = True
    value_only_line_search: bool = False
    armijo_slack: float = 16.0
    step_tol: float = 0.0
    energy_tol: float = 0.0
    energy_window: int = 3
    after_step: Callable[[torch.Tensor, NewtonStep], bool] | None = None

    def __post_init__(self) -> None:
        if not self.regularization_growth > 1.0:
            raise InputError(
                f"NewtonOptions.regularization_growth must be > 1, got {self.regularization_growth}"
            )
        if not (self.armijo_slack >= 0 and self.step_tol >= 0 and self.energy_tol >= 0):
            raise InputError("NewtonOptions: armijo_slack, step_tol and energy_tol must be >= 0")
        if self.energy_window < 1:
            raise InputError(f"NewtonOptions.energy_window must be >= 1, got {self.energy_window}")


def newton_direction(
    h: scipy.sparse.csr_matrix, g: np.ndarray, settings: SolveSettings, iteration: int,
    cache: FactorCache | None = None, options: NewtonOptions | None = None, *,
    device: torch.device | None = None, blocks: bool = True, seams: tuple[torch.Tensor, float] | None = None,
    exact: Callable[[], scipy.sparse.csr_matrix] | None = None, ordering: np.ndarray | None = None,
) -> tuple[np.ndarray, int]:
    """A descent direction ``dx`` solving ``(H + lambda I) dx = -g``, regularizing when needed.

    Args:
        h: (n, n) Hessian (CSR, float64).
        g: (n,) gradient (float64).
        settings: solve settings (regularization, max_regularizations).
        iteration: for error messages.
        cache: with one, first try CG preconditioned by the cached factorization
            (``settings.reuse_factorization``; on the exact Hessian with ``exact``), and keep every fresh
            factorization in it.
        options: the regularization policy (``regularize_first``, ``regularization_growth``,
            ``gradient_fallback``); None: the defaults.
        device: where ``settings.linear_solver = "jacobi-pcg"`` iterates (None: the CPU).
        blocks: that solver's preconditioner is 3x3 block Jacobi (False: scalar, for systems on a subset of
            the unknowns).
        seams: that solver's seam blocks (see :func:`jacobi_pcg_solve`); None: none.
        exact: with ``settings.exact_curvature_cg > 0``, builds the exact (unprojected) Hessian: the direction
            is then CG on it preconditioned by the factorization of ``h`` (see
            :class:`~torchgarment.sim.solvers.SolveSettings`); the projected step when ``h`` does not
            factorize to a descent direction's first try.
        ordering: (n,) fill-reducing permutation of every sparse factorization here (see
            :func:`~torchgarment.linalg.factorize`); None: METIS' ordering of ``h``'s pattern.

    Returns:
        ``(dx, retries)``: the direction (n,) and how many regularized solves were needed.

    Raises:
        NonFiniteError: no descent direction was found after ``max_regularizations`` retries (unless
            ``gradient_fallback``).
    """
    o = options or NewtonOptions()
    curvature = exact is not None and settings.exact_curvature_cg > 0 and not o.regularize_first
    if curvature:
        assert exact is not None
        k_exact = exact()
        budget, rtol = settings.exact_curvature_cg, settings.exact_curvature_rtol

        def exact_cg(precondition: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, int, float]:
            return pcg(lambda v: k_exact @ v, -g, precondition, rtol, budget, stop_at_negative_curvature=True)

        stale = cache.factorization if cache is not None else None
        if stale is not None and tuple(stale.shape) == h.shape:
            # the last factorization (of an earlier, nearby projected Hessian) as the preconditioner: kept
            # when CG gets to its tolerance, or stops at non-positive curvature after at least one iteration
            try:
                y, its, res = exact_cg(stale.solve)
            except SingularMatrixError:
                its = 0
            good = its > 0 and np.all(np.isfinite(y)) and float(g @ y) < 0.0
            if good and (res <= rtol or its < budget):
                cache.pcg_solves += 1
                return y, 0
            if good and settings.pcg_accept_rtol is not None and res <= settings.pcg_accept_rtol:
                # the budget spent short of rtol, but within the accepted forcing term: take the step and
                # factorize the next system afresh (the preconditioner has gone stale), as FactorCache.solve
                cache.pcg_solves += 1
                cache.factorization = None
                return y, 0
        try:
            fact = factorize(h, backend=settings.sparse_backend, what="Newton system", ordering=ordering)
            dx = fact.solve(-g)
        except SingularMatrixError:
            dx = None
        if dx is not None and float(g @ dx) < 0.0:
            if cache is not None:
                cache.store(fact)
            y, its, _ = exact_cg(fact.solve)
            # from zero every CG iterate before a non-positive curvature is a descent direction
            return (y if its > 0 and float(g @ y) < 0.0 else dx), 0
    elif cache is not None:
        dx = cache.solve(h, -g, settings.pcg_rtol, settings.pcg_max_iterations, settings.pcg_accept_rtol)
        if dx is not None and float(g @ dx) < 0.0:
            return dx, 0

    def linear_solve(a: scipy.sparse.csr_matrix, shift: float) -> np.ndarray | None:
        if settings.linear_solver == LinearSolver.JACOBI_PCG:
            return jacobi_pcg_solve(a, -g, torch.device("cpu") if device is None else device,
                                    settings.jacobi_pcg_rtol, settings.jacobi_pcg_max_iterations,
                                    blocks=blocks, seams=seams)[0]
        return sparse_solve(a, -g, cache, shift, backend=settings.sparse_backend, ordering=ordering)

    if not o.regularize_first:
        dx = linear_solve(h, 0.0)
        if dx is not None and float(g @ dx) < 0.0:
            return dx, 0
    scale = float(np.abs(h.diagonal()).mean()) or 1.0
    eye = scipy.sparse.identity(h.shape[0], format="csr", dtype=np.float64)
    lam = settings.regularization * scale
    for retry in range(1, settings.max_regularizations + 1):
        dx = linear_solve((h + lam * eye).tocsr(), lam)
        if dx is not None and float(g @ dx) < 0.0:
            return dx, retry
        lam *= o.regularization_growth
    if o.gradient_fallback:
        return -g / scale, settings.max_regularizations  # still a descent direction
    raise NonFiniteError(
        f"Newton: no descent direction at solver iteration {iteration} even with "
        f"lambda={lam / o.regularization_growth:.3g} * I"
    )


def solve_newton(
    model: SolverModel,
    x0: torch.Tensor,
    settings: SolveSettings,
    max_iterations: int,
    callback: Callback | None = None,
    options: NewtonOptions | None = None,
) -> tuple[torch.Tensor, SolveInfo]:
    """Minimize the model's energy from ``x0`` with projected Newton.

    Args:
        model: the simulation model (see :class:`~torchgarment.sim.solvers.common.SolverModel`; with
            ``options.value_only_line_search`` it also needs ``energy(x)``). A model may also provide
            ``hessian_block_parts(x, project_psd) -> list[HessianBlocks]`` (the Hessian's blocks in groups
            whose sum is ``hessian_blocks``), assembled group by group; the first group's sparsity must not
            change during the solve (the terms of a fixed mesh), and every sparse factorization of the solve
            then uses its fill-reducing ordering, computed once, where the whole Hessian's pattern (its
            contacts) changes from one iteration to the next.
        x0: (V, 3) initial positions (metres); must be feasible (all barriers finite).
        settings: solver settings (validated by the caller).
        max_iterations: iteration budget (Newton steps).
        callback: called after every iteration as ``callback(k, x, |g|, E)``; returning True stops.
        options: :class:`NewtonOptions` (free unknowns, step bound, regularization policy, extra stops).

    Returns:
        ``(x, info)``: the final positions (V, 3) and a :class:`SolveInfo` (``message`` is "converged",
        "max iterations reached", "stopped by callback", "small step", "energy stalled" or starts with
        "line search failed").
    """
    o = options or NewtonOptions()
    timer = Timer()
    info = SolveInfo(solver=SolverKind.NEWTON.value)
    # a float32 solve's line search compares energies in float64, as GD-Chebyshev's checkpoints do: near
    # convergence a full Newton step lowers the energy by about as much as float32 round-off moves it, and
    # whether Armijo accepted the step depended on the CPU's rounding (a float32 sliver sheet stalled at 22x
    # the tolerance on one machine and converged on others)
    low_precision = x0.dtype != torch.float64
    eps = torch.finfo(torch.float64).eps
    # one list of cached assemblers (one per block group) for the projected and one for the exact Hessian
    # (exact_curvature_cg), so that alternating between the two never rebuilds a sparsity pattern
    assemblers: dict[bool, list[CSRAssembler]] = {True: [], False: []}
    block_parts = getattr(model, "hessian_block_parts", None)
    # with block groups: the first group's ordering (METIS, 30 ms of a 5K-vertex garment's 125 ms CHOLMOD
    # factorization when computed for every new contact pattern)
    fixed_ordering: np.ndarray | None = None

    def assemble_hessian(x: torch.Tensor, project: bool = True) -> scipy.sparse.csr_matrix:
        """The Hessian as CSR (projected per ``settings.project_psd`` unless ``project`` is False); a model
        with ``hessian_block_parts`` (blocks grouped by how often their sparsity changes) gets one cached
        assembler per group, so a changing contact pattern does not re-sort the rest."""
        psd = settings.project_psd and project
        parts = ([model.hessian_blocks(x, project_psd=psd)] if block_parts is None
                 else block_parts(x, project_psd=psd))
        cached = assemblers[project]
        while len(cached) < len(parts):
            cached.append(CSRAssembler(model.num_vertices))
        nonlocal fixed_ordering
        mats = [asm.assemble(b) for asm, b in zip(cached, parts)]
        if len(mats) > 1 and project and fixed_ordering is None:
            fixed_ordering = fill_reducing_permutation(mats[0] if free is None else mats[0][free][:, free])
        h = mats[0]
        for m in mats[1:]:
            h = h + m
        return h.tocsr()

    free = None if o.free is None else o.free.detach().to("cpu", torch.bool).numpy().reshape(-1)

    def free_norm(g: torch.Tensor, gn: float) -> float:
        if free is None:
            return gn
        g64 = g.detach().to(device="cpu", dtype=torch.float64).numpy().reshape(-1)
        return float(np.linalg.norm(g64[free]))

    with torch.no_grad():
        x = x0.detach().clone()
        e, g, gn = evaluate(model, x, 0, "initial state")
        gn = free_norm(g, gn)
        info.residual_history.append(gn)
        info.energy_history.append(e)
        step_energies = [e]
        tol = tolerance(settings, gn)
        info.message = "max iterations reached"
        if gn <= tol:
            info.converged, info.message = True, "converged"

        k = 0
        damping = 0.0  # Levenberg damping carried between iterations (0: plain projected Newton)
        cache = FactorCache() if settings.reuse_factorization else None
        seams = (seam_pairs(model) if settings.linear_solver == LinearSolver.JACOBI_PCG and free is None
                 and settings.seam_blocks else None)
        while not info.converged and k < max_iterations:
            k += 1
            h = assemble_hessian(x)
            if not np.all(np.isfinite(h.data)):
                raise NonFiniteError(f"model returned a non-finite Hessian at solver iteration {k}")
            g64 = g.detach().to(device="cpu", dtype=torch.float64).numpy().reshape(-1)
            if free is not None:
                h = h[free][:, free]
                g64 = g64[free]
            diag = np.maximum(np.abs(h.diagonal()), 1e-12 * float(np.abs(h.diagonal()).max() or 1.0))

            def exact_hessian(x: torch.Tensor = x) -> scipy.sparse.csr_matrix:
                he = assemble_hessian(x, project=False)
                return he if free is None else he[free][:, free]

            accepted = False
            trial = 0
            e_ref = energy_float64(model, x) if low_precision else e  # the line search's reference energy
            while not accepted and trial <= (LEVENBERG_RETRIES if o.levenberg else 0):
                hk = h if damping == 0.0 else (h + scipy.sparse.diags(damping * diag, format="csr")).tocsr()
                dxf, retries = newton_direction(hk, g64, settings, k, cache if damping == 0.0 else None, o,
                                                device=x.device, blocks=free is None, seams=seams,
                                                exact=exact_hessian if damping == 0.0 else None,
                                                ordering=fixed_ordering)
                info.restarts += retries
                slope = float(g64 @ dxf)  # < 0
                if free is None:
                    dx64 = dxf
                else:
                    dx64 = np.zeros(free.shape[0])
                    dx64[free] = dxf
                dx = torch.from_numpy(dx64).to(device=x.device, dtype=x.dtype).reshape(x.shape)
                if o.step_bound is None:
                    a_max = checked_max_step(model, x, dx, k)
                    a_max = 1.0 if a_max >= 1.0 else settings.step_fraction * a_max
                else:
                    a_max = float(o.step_bound.max_step(x, dx))
                trial_state: dict = {}

                def energy_at(a: float, dx: torch.Tensor = dx, state: dict = trial_state) -> float:
                    xt = x + a * dx
                    state["x"] = xt
                    if o.value_only_line_search:
                        return energy_float64(model, xt) if low_precision else float(model.energy(xt))
                    e_t, g_t = model.value_and_grad(xt)
                    checked = checked_evaluation(e_t, g_t, k, f"line search, step {a:.3g}",
                                                 infeasible_ok=True)
                    if checked[0] == math.inf:  # a barrier's infeasible side, which the step bound should
                        state.pop("e_g_gn", None)  # have kept out (a closing contact's round-off)
                        return math.inf
                    state["e_g_gn"] = checked
                    return energy_float64(model, xt) if low_precision else checked[0]

                if a_max > 0.0:
                    a, et, accepted = armijo_backtracking(
                        energy_at, e_ref, slope, a_max, armijo_c=settings.armijo_c,
                        backtrack=settings.backtrack, max_backtracks=settings.max_backtracks,
                        slack=o.armijo_slack * eps * abs(e_ref))
                if not accepted:
                    trial += 1
                    if o.levenberg:
                        damping = LEVENBERG_START if damping == 0.0 else 10.0 * damping
                        info.restarts += 1
            if not accepted:
                info.message = (
                    f"line search failed at iteration {k} (no sufficient decrease, damping {damping:.3g})"
                )
                k -= 1
                break
            damping = 0.0 if damping <= LEVENBERG_START else 0.1 * damping
            x = trial_state["x"]
            if o.value_only_line_search:
                e, g, gnt = evaluate(model, x, k, "accepted step")
            else:
                e, g, gnt = trial_state["e_g_gn"]
            step = NewtonStep(k, e, gn, a, a_max, a * _displacement(o, dx))
            if o.after_step is not None and o.after_step(x, step):
                e, g, gnt = evaluate(model, x, k, "after the step hook")
                step_energies = []  # a new objective: the energy test compares its energies only
            gn = free_norm(g, gnt)
            step_energies.append(e)
            info.final_step = a
            info.residual_history.append(gn)
            info.energy_history.append(e)
            if gn <= tol:
                info.converged, info.message = True, "converged"
            if callback is not None and callback(k, x, gn, e) and not info.converged:
                info.message = "stopped by callback"
                break
            if info.converged:
                break
            w = o.energy_window
            if o.energy_tol > 0 and len(step_energies) > w + 1 and \
                    step_energies[-1 - w] - step_energies[-1] <= o.energy_tol * abs(step_energies[-1]):
                info.converged, info.message = True, "energy stalled"
                break
            if o.step_tol > 0 and step.displacement <= o.step_tol:
                info.message = "small step"
                break

    info.iterations = k
    info.seconds = timer.elapsed()
    return x, info


def _displacement(options: NewtonOptions, dx: torch.Tensor) -> float:
    """The step bound's displacement measure of ``dx`` (default: the largest vertex displacement)."""
    if options.step_bound is not None:
        return float(options.step_bound.displacement(dx))
    return float(torch.linalg.vector_norm(dx, dim=-1).max()) if dx.numel() else 0.0
