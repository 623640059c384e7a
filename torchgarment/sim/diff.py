"""The differentiable quasistatic solve (Wang et al. 2018, section 7, Eq. 18-19).

The equilibrium ``x*(theta)`` of a :class:`~torchgarment.sim.scene.SimModel` solves ``grad_x E(x*, theta) =
0`` (the force ``f = -grad_x E`` vanishes), with ``theta`` the model's differentiable parameters: the planar
springs' 2D rest positions ``stretch.p`` (V, 2) in metres and per-edge shirring factors ``stretch.shirring``
(E,), the pin targets ``pins.targets`` (P, 3) in metres, and any other ``nn.Parameter`` a term owns directly.
By the implicit function theorem, for a loss ``L(x*)``::

    K lambda = dL/dx*,     K = d^2E/dx^2 (x*) = -df/dx (the UNPROJECTED Hessian, (3V, 3V), symmetric)
    dL/dtheta = -lambda^T d(grad_x E)/dtheta (x*, theta)

The second line is computed matrix-free (the paper's product): ``torch.autograd.grad`` of
``(grad_x E(x*, theta) . lambda)`` with respect to ``theta``, with ``grad_x E`` built by autograd
(``create_graph=True``) from the terms' differentiable ``forward``. ``K`` is never formed densely: the adjoint
system is solved by

* :attr:`AdjointLinearSolver.SPARSE`: ``K`` assembled from ``model.hessian_blocks(x*, project_psd=False)``
  into a CSR matrix and factorized with SuperLU (scipy, on the CPU; GPU tensors are copied), or
* :attr:`AdjointLinearSolver.CG`: preconditioned conjugate gradients with a 3x3 block-Jacobi preconditioner
  over Hessian-vector products. The products come from the assembled blocks as a torch sparse CSR matrix
  (:attr:`HessianProduct.ASSEMBLED`, the default; scipy CSR on the CPU, torch CSR elsewhere) or from autograd
  double-backward of ``model.energy`` (:attr:`HessianProduct.AUTOGRAD`; needs twice-differentiable terms,
  which a :class:`~torchgarment.sdf.BodySDF` is not).

Exactness of ``K``: every term's unprojected blocks are exact; the body barrier's include ``b'(phi)
Hess(phi)`` with ``Hess(phi)`` from central differences of the SDF's analytic gradient (exact for a trilinear
interpolant away from cell faces, up to rounding; :meth:`~torchgarment.sim.energies.barrier.BodyBarrier.
curvature_blocks`), so the adjoint gradient is that of the energy the forward solve actually minimizes.

Backward modes (:class:`BackwardMode`, chosen by name as in theseus): ``"adjoint"`` (alias ``"implicit"``)
as above; ``"unroll"`` differentiates through a damped Newton iteration from the cold start (autograd through
every step, the dense autograd Hessian included: small problems and twice-differentiable terms only, so not
with a :class:`~torchgarment.sdf.BodySDF` barrier; for tests); ``"truncated"`` solves without a graph and
unrolls only the last ``truncated_steps`` Newton steps from the (detached) solution, with the exact assembled
Hessian held constant (one step reproduces the adjoint gradient; more steps need twice-differentiable terms).

Measured adjoint solve times (2 CPU cores, float64, a stretched square sheet with 1 cm edges, boundary pinned,
with stretch, bend, gravity and pins, at its equilibrium, random right-hand side; assembly included):

==========  =====================  ==========================  ==========================
vertices    SPARSE (SuperLU)       CG, assembled (scipy CSR)   CG, autograd HVPs
==========  =====================  ==========================  ==========================
5,041       0.64 s (res 8e-15)     1.3 s / 240 it (rtol 1e-6)  14-35 s / 240-376 it
                                   1.4 s / 376 it (rtol 1e-10)
19,881      1.7 s (res 8e-15)      9.9 s / 451 it (rtol 1e-6)  (not run)
==========  =====================  ==========================  ==========================

Hence the defaults: SPARSE, and ASSEMBLED products for CG (torch's CSR product was 25x slower than scipy's
on the CPU: 12 ms vs 0.5 ms at 5K vertices).

Failure mode: the gradient formula only holds at an equilibrium. The forward solve must reach its force
tolerance; otherwise :class:`NonConvergenceError` is raised (or, with ``strict=False``, a
:class:`NonConvergenceWarning` is issued and the gradient is that of the unconverged state, i.e. inexact).
A non-converged CG, or negative curvature met by CG (``K`` not positive definite, e.g. a saddle), also raises.

Inexact states (Wang 2018, Algorithm 1: ``S`` solver iterations, not an equilibrium): the formula is then an
estimate of the gradient at the equilibrium the pattern would settle to, and the exact ``K`` at a state out of
balance can be indefinite and nearly singular (compressed springs, the barrier's curvature), which makes that
estimate erratic. ``DifferentiableSolver(inexact_hessian="projected")`` solves the adjoint of such states with
the Newton solver's PSD-projected Hessian instead (:class:`AdjointHessian`), by the Newton systems' sparse
backend (CHOLMOD's Cholesky where chosen); exact solves keep the exact ``K``.

Example::

    model = Scene(mesh, pin_indices=top).build()
    layer = DifferentiableSolver(model, mesh.x)
    p = model.term("stretch").p.detach().clone().requires_grad_(True)
    x = layer(p=p)                       # (V, 3) equilibrium, warm-started from the previous call
    loss = ((x - target) ** 2).sum()
    loss.backward()                      # p.grad via the adjoint solve
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch.autograd.function import FunctionCtx
from torch.func import functional_call
from torch.func import grad as func_grad
from torch.func import jvp as func_jvp

from torchgarment.errors import InputError, NonConvergenceError, SingularMatrixError
from torchgarment.linalg import CSRAssembler, FactorizationCache, armijo_backtracking, csr_matvec, minres, pcg
from torchgarment.options import OptionEnum
from torchgarment.sim.energies.barrier import BodyBarrier
from torchgarment.sim.energies.base import HessianBlocks
from torchgarment.sim.solvers import SolveInfo, SolverKind, SolveSettings, solve
from torchgarment.sim.solvers.chebyshev import JacobiState, apply_inverse, seam_pairs
from torchgarment.sim.solvers.common import Preconditioner


class NonConvergenceWarning(UserWarning):
    """Issued instead of :class:`NonConvergenceError` when ``strict=False``: the gradient is inexact."""


class BackwardMode(OptionEnum):
    """How the gradient of the equilibrium is computed."""

    ADJOINT = "adjoint"
    """Implicit differentiation: one adjoint linear solve at the equilibrium (alias ``"implicit"``)."""
    UNROLL = "unroll"
    """Autograd through every iteration of a differentiable Newton solve from the cold start (small cases)."""
    TRUNCATED = "truncated"
    """Solve without a graph, then unroll only the last ``truncated_steps`` Newton steps from the solution."""

    @classmethod
    def aliases(cls) -> dict[str, str]:
        """``"implicit"`` means ADJOINT; ``"full"`` and ``"unrolled"`` mean UNROLL."""
        return {"implicit": "adjoint", "full": "unroll", "unrolled": "unroll"}


class AdjointLinearSolver(OptionEnum):
    """Linear solver of the adjoint system ``K lambda = dL/dx``."""

    CG = "cg"
    """Block-Jacobi preconditioned conjugate gradients over Hessian-vector products (needs ``K`` SPD)."""
    SPARSE = "sparse"
    """Assembled sparse ``K``, sparse direct factorization (any non-singular ``K``)."""

    @classmethod
    def aliases(cls) -> dict[str, str]:
        """``"direct"`` means SPARSE; ``"iterative"`` means CG."""
        return {"direct": "sparse", "iterative": "cg"}


class AdjointHessian(OptionEnum):
    """The matrix ``K`` of the adjoint system at a state that is not an equilibrium (an inexact solve's)."""

    EXACT = "exact"
    """The unprojected Hessian ``d^2E/dx^2``: the implicit function theorem's matrix, exact at an equilibrium;
    at a state out of balance it may be indefinite and nearly singular (a factorization by SuperLU)."""
    PROJECTED = "projected"
    """The per-element PSD-projected Hessian that Newton factorizes (positive definite where the garment is
    held: a Cholesky backend serves it). Away from equilibrium it estimated the equilibrium's gradient better
    than EXACT on the 3K and 10K dresses, but the adjustments of the 3K and 30K dresses ended higher with it
    (README, "The adjoint at inexact states"), so EXACT is the default."""


class HessianProduct(OptionEnum):
    """Where CG's Hessian-vector products come from."""

    ASSEMBLED = "assembled"
    """:func:`exact_hessian_blocks` assembled once into a torch sparse CSR matrix; one SpMV per product."""
    AUTOGRAD = "autograd"
    """Double backward through ``model.energy`` (exact for twice-differentiable terms; not for a BodySDF)."""


@dataclass
class AdjointInfo:
    """What the last adjoint solve did.

    Attributes:
        solver: ``"cg"`` or ``"sparse"``.
        iterations: CG iterations (0 for SPARSE).
        relative_residual: ``|K lambda - b| / |b|`` of the returned ``lambda``.
        seconds: wall time of the linear solve, assembly included.
        negative_curvature: CG stopped at a direction of non-positive curvature (``K`` is not positive
            definite there; only with ``require_convergence=False``, which returns the iterate reached).
        hessian: the :class:`AdjointHessian` ``K`` was (``"exact"`` or ``"projected"``).
    """

    solver: str
    iterations: int
    relative_residual: float
    seconds: float
    negative_curvature: bool = False
    hessian: str = AdjointHessian.EXACT.value


# ---------------------------------------------------------------------------------------------- Hessian
def exact_hessian_blocks(model: torch.nn.Module, x: torch.Tensor) -> HessianBlocks:
    """The unprojected Hessian ``d^2E/dx^2`` of ``model`` at ``x`` as block-COO, including the barrier
    curvature: ``model.hessian_blocks(x, project_psd=False)``.

    Args:
        model: a SimModel. x: (V, 3) positions in metres.
    """
    return model.hessian_blocks(x.detach(), project_psd=False)


def check_twice_differentiable(model: torch.nn.Module, x: torch.Tensor, rtol: float = 1e-5) -> None:
    """Raise :class:`InputError` unless autograd's second derivatives of the model's barrier terms are exact.

    A :class:`~torchgarment.sdf.BodySDF` is differentiable once (its backward is the analytic gradient): a
    double backward through it silently drops ``Hess(phi)`` instead of failing. This compares, for each
    :class:`BodyBarrier`, an autograd Hessian-vector product with its exact blocks (``hessian_blocks(x,
    project_psd=False)``, curvature included) on a random vector.

    Args:
        model: a SimModel. x: (V, 3) feasible positions. rtol: accepted relative mismatch.
    """
    gen = torch.Generator(device="cpu").manual_seed(0)
    for t in model.terms:
        if not isinstance(t, BodyBarrier):
            continue
        v = torch.randn(x.shape, generator=gen, dtype=torch.float64).to(device=x.device, dtype=x.dtype)
        with torch.enable_grad():
            xr = x.detach().clone().requires_grad_(True)
            try:
                (g,) = torch.autograd.grad(t(xr), xr, create_graph=True)
                (hv,) = torch.autograd.grad(g, xr, v, allow_unused=True)
            except RuntimeError as exc:
                raise InputError(f"the body SDF is not twice differentiable by autograd ({exc})") from exc
        exact = t.hessian_blocks(x.detach(), project_psd=False)
        ref = (exact.to_sparse(t.num_vertices) @ v.reshape(-1, 1)).view_as(v)
        hv = torch.zeros_like(v) if hv is None else hv
        err = float(torch.linalg.vector_norm(hv - ref)) / max(float(torch.linalg.vector_norm(ref)), 1e-300)
        if not err <= rtol:
            raise InputError(f"the body SDF ({type(t.sdf).__name__}) is not twice differentiable by autograd "
                             f"(autograd Hessian-vector products are off by {err:.2g}, relative): autograd "
                             f"Hessians would be wrong")


def _diagonal_blocks(blocks: HessianBlocks, num_vertices: int) -> torch.Tensor:
    """(V, 3, 3) sum of the blocks with row == col."""
    on = blocks.rows == blocks.cols
    out = torch.zeros(num_vertices, 3, 3, dtype=blocks.values.dtype, device=blocks.values.device)
    return out.index_add_(0, blocks.rows[on], blocks.values[on])


def _torch_csr(blocks: HessianBlocks, num_vertices: int) -> torch.Tensor:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "sparse CSR support is in beta"
        return blocks.to_sparse(num_vertices).to_sparse_csr()


# ---------------------------------------------------------------------------------------------- linear solves
def solve_adjoint(
    model: torch.nn.Module,
    x: torch.Tensor,
    rhs: torch.Tensor,
    linear_solver: "str | AdjointLinearSolver" = AdjointLinearSolver.SPARSE,
    *,
    hessian_product: "str | HessianProduct" = HessianProduct.ASSEMBLED,
    rtol: float = 1e-10,
    max_iterations: int | None = None,
    x0: torch.Tensor | None = None,
    require_convergence: bool = True,
    assembler: CSRAssembler | None = None,
    cache: FactorizationCache | None = None,
    hessian: "str | AdjointHessian" = AdjointHessian.EXACT,
) -> tuple[torch.Tensor, AdjointInfo]:
    """Solve ``K lambda = rhs`` with ``K`` the exact unprojected Hessian of ``model`` at ``x`` (or, with
    ``hessian="projected"``, its PSD-projected one).

    Args:
        model: a SimModel.
        x: (V, 3) equilibrium positions in metres.
        rhs: (V, 3) right-hand side (``dL/dx``, in loss units per metre).
        linear_solver: ``"cg"`` or ``"sparse"``.
        hessian_product: CG's products: ``"assembled"`` or ``"autograd"``.
        rtol: CG tolerance ``|r| <= rtol |rhs|``; also the accepted residual of SPARSE (times 1e3).
        max_iterations: CG budget; None = ``max(200, 3V)``.
        x0: (V, 3) CG warm start, e.g. the previous adjoint of a sequence of nearby solves (default zero).
        require_convergence: False accepts CG's iterate when the budget runs out (an inexact adjoint;
            ``info.relative_residual`` says how inexact); at a direction of non-positive curvature (``K``
            indefinite) the system is solved by preconditioned MINRES instead, to the same tolerance and
            budget (``info.solver == "minres"``).
        assembler: a :class:`CSRAssembler` reused across calls (it caches the COO -> CSR permutation).
        cache: a :class:`FactorizationCache` keyed on ``x``: SPARSE solves at the same ``x`` (an adjoint and
            the tangent solves of Gauss-Newton products) share one factorization. It must hold factorizations
            of the Hessian ``hessian`` names (a Cholesky backend only for PROJECTED).
        hessian: :class:`AdjointHessian`: ``"exact"`` (default; the implicit function theorem's ``K``) or
            ``"projected"`` (``model.hessian_blocks(x, project_psd=True)``, symmetric positive semi-definite:
            an approximate adjoint for states that are not equilibria).

    CG is preconditioned with the simulator's block Jacobi, each seam pair of a ``sew`` term as one 6x6 block
    (:class:`~torchgarment.sim.solvers.chebyshev.JacobiState`): stiff seams otherwise slow CG down.

    Returns:
        ``(lambda, info)``: (V, 3) adjoint in the dtype and device of ``x`` (loss units per newton), and an
        :class:`AdjointInfo`.

    Raises:
        NonConvergenceError: CG did not reach ``rtol`` or met negative curvature (with
            ``require_convergence``), or ``K`` is singular.
        InputError: AUTOGRAD products on a model that is not twice differentiable.
    """
    kind = AdjointLinearSolver.resolve(linear_solver)
    product = HessianProduct.resolve(hessian_product)
    which = AdjointHessian.resolve(hessian)
    projected = which == AdjointHessian.PROJECTED
    if projected and kind == AdjointLinearSolver.CG and product == HessianProduct.AUTOGRAD:
        raise InputError("the projected adjoint Hessian has no autograd products: use hessian_product="
                         "'assembled'")
    t0 = time.perf_counter()
    V = model.num_vertices
    x = x.detach()
    rhs = rhs.detach().to(x.dtype)
    bn = float(torch.linalg.vector_norm(rhs))
    assembler = CSRAssembler(V) if assembler is None else assembler
    if kind == AdjointLinearSolver.SPARSE:
        cache = FactorizationCache(what="simulation Hessian") if cache is None else cache
        fact = cache.factorize(x, lambda: assembler.assemble(model.hessian_blocks(x,
                                                                                  project_psd=projected)))
        b64 = rhs.to(device="cpu", dtype=torch.float64).numpy().reshape(-1)
        y = fact.solve(b64)
        res = float(np.linalg.norm(fact.matrix @ y - b64)) / bn if bn > 0 else 0.0
        lam = torch.from_numpy(y).to(device=x.device, dtype=x.dtype).view(V, 3)
        if res > max(1e3 * rtol, 1e-6):
            raise NonConvergenceError(f"adjoint sparse solve is inaccurate: relative residual {res:.3g} "
                                      f"(ill-conditioned Hessian at the solution)")
        return lam, AdjointInfo(kind.value, 0, res, time.perf_counter() - t0, hessian=which.value)

    if product == HessianProduct.ASSEMBLED:
        blocks = model.hessian_blocks(x, project_psd=projected)
        diag = _diagonal_blocks(blocks, V)
        if x.device.type == "cpu":  # scipy's CSR product is ~25x faster than torch's on the CPU (measured)
            kc = csr_matvec(assembler.assemble(blocks), x.device)

            def matvec(v: torch.Tensor) -> torch.Tensor:
                return kc(v.detach().to(torch.float64).reshape(-1)).to(v.dtype).view(V, 3)
        else:
            K = _torch_csr(blocks, V)

            def matvec(v: torch.Tensor) -> torch.Tensor:
                return (K @ v.reshape(-1, 1)).view(V, 3)
    else:
        check_twice_differentiable(model, x)
        diag = _diagonal_blocks(exact_hessian_blocks(model, x), V)
        matvec = _autograd_hvp(model, x)
    pre = JacobiState(SolveSettings(preconditioner=Preconditioner.BLOCK, diagonal_floor=1e-10),
                      seam_pairs(model))
    pre.rebuild(diag)
    n_max = max(200, 3 * V) if max_iterations is None else int(max_iterations)
    lam, k, res = pcg(matvec, rhs, lambda r: apply_inverse(pre.inverse, r), rtol, n_max, x0=x0,
                      stop_at_negative_curvature=not require_convergence)
    if not bool(torch.isfinite(lam).all()):
        raise NonConvergenceError("adjoint CG returned non-finite values")
    if require_convergence and not res <= rtol:
        raise NonConvergenceError(f"adjoint CG did not converge: relative residual {res:.3g} > {rtol:g} "
                                  f"after {k} iterations; raise cg_max_iterations or use the 'sparse' solver")
    # pcg's other exits are the tolerance and the budget: stopping earlier means non-positive curvature, where
    # CG's iterate approximates nothing; MINRES (the same SPD preconditioner) handles the indefinite system
    if not res <= rtol and k < n_max:
        lam, k2, res = minres(matvec, rhs, lambda r: apply_inverse(pre.inverse, r), rtol, n_max, x0=x0)
        if not bool(torch.isfinite(lam).all()):
            raise NonConvergenceError("adjoint MINRES returned non-finite values")
        return lam, AdjointInfo("minres", k + k2, res, time.perf_counter() - t0, negative_curvature=True,
                                hessian=which.value)
    return lam, AdjointInfo(kind.value, k, res, time.perf_counter() - t0, hessian=which.value)


def _autograd_hvp(model: torch.nn.Module, x: torch.Tensor) -> Callable[[torch.Tensor], torch.Tensor]:
    """``v -> K v`` by double backward through ``model.energy`` (graph of the gradient built once)."""
    with torch.enable_grad():
        xr = x.detach().clone().requires_grad_(True)
        (g,) = torch.autograd.grad(model.energy(xr), xr, create_graph=True)

    def matvec(v: torch.Tensor) -> torch.Tensor:
        with torch.enable_grad():
            try:
                (hv,) = torch.autograd.grad(g, xr, v, retain_graph=True)
            except RuntimeError as exc:
                raise InputError(f"autograd Hessian-vector products need twice-differentiable energy terms "
                                 f"({exc}); use hessian_product='assembled'") from exc
        return hv

    return matvec


# ---------------------------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class _ParamSlot:
    name: str  # "stretch.p"
    path: str  # "terms.0.p" (for functional_call on the model)
    term: int
    attr: str


def _parameter_slots(model: torch.nn.Module) -> list[_ParamSlot]:
    slots = []
    for i, t in enumerate(model.terms):
        for attr, _ in t.named_parameters(recurse=False):
            slots.append(_ParamSlot(f"{t.name}.{attr}", f"terms.{i}.{attr}", i, attr))
    return slots


def parameter_vjp(
    model: torch.nn.Module, x: torch.Tensor, lam: torch.Tensor, values: Mapping[str, torch.Tensor]
) -> dict[str, torch.Tensor]:
    """``-lambda^T d(grad_x E)/dtheta`` at ``x`` for the parameters in ``values``, matrix-free through
    autograd.

    Args:
        model: a SimModel.
        x: (V, 3) positions in metres.
        lam: (V, 3) adjoint vector.
        values: term parameter values by qualified name (``"stretch.p"``), each shaped like the parameter.

    Returns:
        The gradient for each name in ``values``, shaped like it (zeros where the energy does not depend on
        it).
    """
    slots = {s.name: s for s in _parameter_slots(model)}
    leafs = {n: v.detach().clone().requires_grad_(True) for n, v in values.items()}
    by_term: dict[int, dict[str, torch.Tensor]] = {}
    for n, leaf in leafs.items():
        s = slots[n]
        by_term.setdefault(s.term, {})[s.attr] = leaf
    with torch.enable_grad():
        xr = x.detach().clone().requires_grad_(True)
        energy = sum(functional_call(model.terms[i], params, (xr,)) for i, params in by_term.items())
        (g,) = torch.autograd.grad(energy, xr, create_graph=True)
        inputs = list(leafs.values())
        grads = torch.autograd.grad((g * lam.detach().to(g.dtype)).sum(), inputs, allow_unused=True)
    return {n: torch.zeros_like(leafs[n]) if gr is None else -gr for n, gr in zip(leafs, grads)}


# ----------------------------------------------------------------------------------- autograd.Function
class QuasistaticSolve(torch.autograd.Function):
    """``x* = argmin_x E(x; theta)`` with the adjoint backward (see the module docstring).

    ``forward(ctx, layer, names, request, *values)``: ``layer`` is the :class:`DifferentiableSolver` (it holds
    the model, settings, warm start and factorization cache), ``names`` the qualified parameter names,
    ``request`` the :class:`SolveRequest` of this call (exact, or ``S`` solver iterations) and ``values`` the
    parameter tensors. Returns the equilibrium (V, 3). ``backward`` solves ``K lambda = dL/dx*`` with the
    layer's adjoint solver (:meth:`DifferentiableSolver.adjoint`) and returns ``-lambda^T d(grad E)/dtheta``
    for the values that need a gradient. First-order only (no double backward).
    """

    @staticmethod
    def forward(ctx: FunctionCtx, layer: DifferentiableSolver, names: tuple[str, ...],  # type: ignore[override]
                request: SolveRequest, *values: torch.Tensor) -> torch.Tensor:
        x = layer._solve_no_grad(dict(zip(names, values)), request)
        ctx.layer, ctx.names = layer, names
        # an inexact solve's state is not an equilibrium: its adjoint uses the layer's inexact_hessian
        ctx.hessian = AdjointHessian.EXACT if request.iterations is None else layer.inexact_hessian
        ctx.save_for_backward(x, *values)
        return x.clone()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: FunctionCtx, grad_x: torch.Tensor) -> tuple[torch.Tensor | None, ...]:  # type: ignore[override]
        x, *values = ctx.saved_tensors
        layer: DifferentiableSolver = ctx.layer
        want = {n: v for n, v, need in zip(ctx.names, values, ctx.needs_input_grad[3:]) if need}
        if not want:
            return (None, None, None) + (None,) * len(values)
        lam = layer.adjoint(x, grad_x, hessian=ctx.hessian)
        grads = parameter_vjp(layer.model, x, lam, want)
        return (None, None, None) + tuple(grads.get(n) for n in ctx.names)


@dataclass(frozen=True)
class SolveRequest:
    """What one call of a :class:`DifferentiableSolver` solves.

    Attributes:
        iterations: None for an exact solve (to the force tolerance; a miss raises with ``strict``), else
            ``S``: run at most ``S`` iterations of the layer's ``inexact_solver`` from the warm start (Wang
            2018, Algorithm 1); the result need not be an equilibrium and its gradient is the paper's inexact
            one (the adjoint at the state reached).
        max_iterations: iteration budget of an exact solve (None: ``settings.max_iterations``).
    """

    iterations: int | None = None
    max_iterations: int | None = None


# ---------------------------------------------------------------------------------------------- the layer
class DifferentiableSolver(torch.nn.Module):
    """A solve layer: ``x = layer(p=..., shirring=..., targets=...)`` returns the equilibrium, differentiable.

    Parameters are named by their qualified name ``"<term>.<attribute>"`` (``"stretch.p"``,
    ``"stretch.shirring"``, ``"pins.targets"``) or by the bare attribute when that is unique (``"p"``). Each
    call writes the given values into the model (in place, without grad; parameters not given keep their
    current values), solves from the previous solution (the warm start; the cold start ``x0`` the first time
    and after :meth:`reset`), and returns the equilibrium (V, 3) in metres. Gradients flow to every given
    value that requires grad, through :class:`QuasistaticSolve` (ADJOINT) or autograd (UNROLL, TRUNCATED).

    Convergence: the force tolerance is ``max(settings.atol, settings.rtol * |g(x0)|)`` with ``g(x0)`` the
    force at the cold start for the current parameters, so a warm start stops at the same accuracy as a cold
    one. A solve that misses it raises :class:`NonConvergenceError` (``strict=True``) or warns.

    Args:
        model: the SimModel (frozen; its parameters are overwritten by calls).
        x0: (V, 3) cold-start positions in metres (made feasible with ``model.project_feasible``).
        settings: forward solve settings; default ``SolveSettings(rtol=1e-8, max_iterations=200)``.
        solver: forward solver, ``"newton"`` (default, converges tightly) or ``"gd-chebyshev"``.
        backward: ``"adjoint"``/``"implicit"``, ``"unroll"`` or ``"truncated"`` (:class:`BackwardMode`).
        linear_solver: adjoint solver, ``"sparse"`` (default, faster on the CPU, see :func:`solve_adjoint`) or
            ``"cg"`` (:class:`AdjointLinearSolver`).
        hessian_product: CG products, ``"assembled"`` or ``"autograd"`` (:class:`HessianProduct`).
        inexact_solver: solver of the ``S``-iteration calls (:class:`SolveRequest`; default ``solver``).
        cg_rtol: adjoint CG relative tolerance.
        cg_max_iterations: CG budget (None = ``max(200, 3V)``).
        cg_warm_start: start each adjoint CG from the previous adjoint (a sequence of nearby solves).
        cg_require_convergence: False accepts CG's iterate at the budget (an inexact adjoint, Wang 2018
            section 7; ``last_adjoint_info.relative_residual`` says how inexact). Where CG meets
            non-positive curvature (the Hessian is indefinite at ``x``: CG's iterate approximates nothing,
            measured 5.3x off the exact gradient with a relative residual of 15.9 on the real skirt) MINRES
            solves instead (:func:`solve_adjoint`); a MINRES answer no better than zero (relative residual
            >= 1) is replaced by the sparse direct adjoint at that state, counted in ``adjoint_fallbacks``.
        inexact_hessian: the :class:`AdjointHessian` of the adjoint at an inexact solve's state (``S``
            iterations, not an equilibrium): ``"exact"`` (default) or ``"projected"`` (factorized by
            ``settings.sparse_backend``, a Cholesky one included; a singular projected Hessian falls back to
            the exact one, counted in ``adjoint_fallbacks``). An exact solve's adjoint always uses the exact
            Hessian, so the gradients at equilibria are the implicit function theorem's.
        truncated_steps: Newton steps unrolled in TRUNCATED mode (>= 1).
        unroll_iterations: Newton iteration budget of UNROLL mode.
        warm_start: start each solve from the last solution.
        strict: raise on a non-converged forward solve (else warn).
    """

    #: UNROLL/TRUNCATED form dense (3V, 3V) autograd Hessians; larger models are refused.
    max_unroll_vertices = 1500

    def __init__(
        self,
        model: torch.nn.Module,
        x0: torch.Tensor,
        settings: SolveSettings | None = None,
        *,
        solver: "str | SolverKind" = SolverKind.NEWTON,
        backward: "str | BackwardMode" = BackwardMode.ADJOINT,
        linear_solver: "str | AdjointLinearSolver" = AdjointLinearSolver.SPARSE,
        hessian_product: "str | HessianProduct" = HessianProduct.ASSEMBLED,
        inexact_solver: "str | SolverKind | None" = None,
        cg_rtol: float = 1e-10,
        cg_max_iterations: int | None = None,
        cg_warm_start: bool = False,
        cg_require_convergence: bool = True,
        inexact_hessian: "str | AdjointHessian" = AdjointHessian.EXACT,
        truncated_steps: int = 1,
        unroll_iterations: int = 100,
        warm_start: bool = True,
        strict: bool = True,
    ) -> None:
        super().__init__()
        self.model = model
        if (not isinstance(x0, torch.Tensor) or x0.shape != (model.num_vertices, 3)
                or not x0.is_floating_point()):
            raise InputError(f"x0 must be a floating ({model.num_vertices}, 3) tensor, got "
                             f"{getattr(x0, 'shape', type(x0))}")
        self.settings = SolveSettings(rtol=1e-8, max_iterations=200) if settings is None else settings
        self.settings.validate()
        self.solver = SolverKind.resolve(solver)
        self.inexact_solver = self.solver if inexact_solver is None else SolverKind.resolve(inexact_solver)
        self.backward_mode = BackwardMode.resolve(backward)
        self.linear_solver = AdjointLinearSolver.resolve(linear_solver)
        self.hessian_product = HessianProduct.resolve(hessian_product)
        self.inexact_hessian = AdjointHessian.resolve(inexact_hessian)
        if (self.inexact_hessian == AdjointHessian.PROJECTED and self.linear_solver == AdjointLinearSolver.CG
                and self.hessian_product == HessianProduct.AUTOGRAD):
            raise InputError("inexact_hessian='projected' needs hessian_product='assembled' (autograd "
                             "products are of the exact Hessian)")
        if not (cg_rtol > 0 and truncated_steps >= 1 and unroll_iterations >= 1):
            raise InputError("cg_rtol must be > 0, truncated_steps and unroll_iterations >= 1")
        self.cg_rtol = float(cg_rtol)
        self.cg_max_iterations = cg_max_iterations
        self.cg_warm_start = bool(cg_warm_start)
        self.cg_require_convergence = bool(cg_require_convergence)
        self.truncated_steps = int(truncated_steps)
        self.unroll_iterations = int(unroll_iterations)
        self.warm_start = bool(warm_start)
        self.strict = bool(strict)
        self._slots = _parameter_slots(model)
        with torch.no_grad():
            self.x_init = model.project_feasible(x0.detach().to(model.dtype).clone())
        self._x_last: torch.Tensor | None = None
        self._adjoint_last: torch.Tensor | None = None
        self._assembler = CSRAssembler(model.num_vertices)
        # the exact Hessian may be indefinite: a Cholesky backend serves the Newton systems only
        self._factorizations = FactorizationCache(self.settings.sparse_backend.for_indefinite(),
                                                  what="simulation Hessian")
        # the projected Hessian is positive semi-definite: the Newton systems' backend, Cholesky included
        self._projected_factorizations = FactorizationCache(self.settings.sparse_backend,
                                                            what="projected simulation Hessian")
        self.last_info: SolveInfo | None = None
        self.last_adjoint_info: AdjointInfo | None = None
        self.sim_iterations = 0
        self.adjoint_iterations = 0
        self.adjoint_fallbacks = 0

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Qualified names of the parameters a call may set (``"stretch.p"``, ...)."""
        return tuple(s.name for s in self._slots)

    def reset(self) -> None:
        """Forget the warm start: the next solve starts from ``x0``."""
        self._x_last = None

    @property
    def state(self) -> torch.Tensor:
        """(V, 3) the warm start of the next solve in metres (the last solution, or ``x0``)."""
        return self.x_init if self._x_last is None else self._x_last

    def set_state(self, x: torch.Tensor) -> None:
        """Set the warm start (V, 3) of the next solve (e.g. going back to an earlier iterate). A state where
        the model's energy is infinite (vertices inside the body: a transferred garment may start there, the
        trousers 18 -> 14 put two vertices 0.6 mm deep) is made feasible with ``model.project_feasible`` like
        ``x0``; a feasible state is kept as given."""
        x = x.detach().to(self.model.dtype).clone()
        with torch.no_grad():
            feasible = bool(torch.isfinite(self.model(x)))
        self._x_last = x if feasible else self.model.project_feasible(x)

    @property
    def factorizations(self) -> int:
        """Sparse factorizations of ``K`` done so far (one per new state a SPARSE adjoint or tangent
        needs; projected ones included)."""
        return self._factorizations.factorizations + self._projected_factorizations.factorizations

    # ------------------------------------------------------------------ call
    def forward(self, params: Mapping[str, torch.Tensor] | None = None, *, iterations: int | None = None,
                max_iterations: int | None = None, **kwargs: torch.Tensor) -> torch.Tensor:
        """Solve for the equilibrium with the given parameter values.

        Args:
            params: values by name (qualified or bare attribute name).
            iterations: None (an exact solve) or ``S``, the iterations of an inexact one
                (:class:`SolveRequest`; ADJOINT mode only).
            max_iterations: the budget of an exact solve (default ``settings.max_iterations``).
            **kwargs: more values by name (``p=...``); a name may not appear in both.

        Returns:
            (V, 3) equilibrium positions in metres, differentiable in the given values.

        Raises:
            InputError: unknown or ambiguous names, wrong shapes/dtypes/devices, non-finite values.
            NonConvergenceError: the forward solve missed its tolerance (``strict``).
        """
        values = self._resolve(params, kwargs)
        if iterations is not None and int(iterations) < 1:
            raise InputError(f"an inexact solve needs iterations >= 1, got {iterations}")
        if max_iterations is not None and int(max_iterations) < 0:
            raise InputError(f"max_iterations must be >= 0, got {max_iterations}")
        request = SolveRequest(None if iterations is None else int(iterations),
                               None if max_iterations is None else int(max_iterations))
        mode = self.backward_mode
        if mode == BackwardMode.ADJOINT:
            names = tuple(values)
            return QuasistaticSolve.apply(self, names, request, *values.values())
        if request.iterations is not None:
            raise InputError(f"inexact solves (iterations=) need backward mode 'adjoint', not {mode.value!r}")
        if self.model.num_vertices > self.max_unroll_vertices:
            raise InputError(f"backward mode {mode.value!r} forms dense Hessians and is limited to "
                             f"{self.max_unroll_vertices} vertices; use 'adjoint'")
        if mode == BackwardMode.TRUNCATED:
            x = self._solve_no_grad(values, request)
            if self.truncated_steps > 1:
                check_twice_differentiable(self.model, x)
            return self._newton_unrolled(values, x, self.truncated_steps, tol=None,
                                         differentiate_hessian=False)
        with torch.no_grad():
            self._write(values)
            tol = self._tolerance()
        try:
            check_twice_differentiable(self.model, self.x_init)
        except InputError as exc:
            raise InputError(f"backward mode 'unroll' needs twice-differentiable energy terms: {exc}; "
                             f"use 'adjoint'") from exc
        x = self._newton_unrolled(values, self.x_init, self.unroll_iterations, tol=tol,
                                  differentiate_hessian=True)
        self._x_last = x.detach().clone()
        return x

    def _resolve(self, params: Mapping[str, torch.Tensor] | None, kwargs: Mapping[str, torch.Tensor]
                 ) -> dict[str, torch.Tensor]:
        given: dict[str, torch.Tensor] = {}
        for src in (params or {}, kwargs):
            if not isinstance(src, Mapping):
                raise InputError("parameters must be given as a mapping of name -> tensor, got "
                                 f"{type(src).__name__}")
            for key, v in src.items():
                slot = self._slot(key)
                if slot.name in given:
                    raise InputError(f"parameter {slot.name!r} given twice")
                ref = self.model.get_parameter(slot.path)
                if not isinstance(v, torch.Tensor) or v.shape != ref.shape or v.dtype != ref.dtype \
                        or v.device != ref.device:
                    raise InputError(f"parameter {slot.name!r} must be a {ref.dtype} tensor of shape "
                                     f"{tuple(ref.shape)} on {ref.device}, got "
                                     f"{getattr(v, 'dtype', type(v))} {tuple(getattr(v, 'shape', ()))}")
                if not bool(torch.isfinite(v.detach()).all()):
                    raise InputError(f"parameter {slot.name!r} contains NaN or infinite values")
                given[slot.name] = v
        return given

    def _slot(self, key: str) -> _ParamSlot:
        for s in self._slots:
            if key == s.name:
                return s
        matches = [s for s in self._slots if s.attr == key]
        if len(matches) == 1:
            return matches[0]
        if len(matches) > 1:
            raise InputError(f"parameter name {key!r} is ambiguous; use one of {[s.name for s in matches]}")
        raise InputError(f"unknown parameter {key!r}; this model has {list(self.parameter_names)}")

    # ------------------------------------------------------------------ forward solve
    def _write(self, values: Mapping[str, torch.Tensor]) -> None:
        slots = {s.name: s for s in self._slots}
        for n, v in values.items():
            self.model.get_parameter(slots[n].path).copy_(v.detach())

    def _tolerance(self) -> float:
        if self.settings.rtol == 0.0:
            return self.settings.atol
        _, g = self.model.value_and_grad(self.x_init)
        return max(self.settings.atol, self.settings.rtol * float(torch.linalg.vector_norm(g)))

    @torch.no_grad()
    def _solve_no_grad(self, values: Mapping[str, torch.Tensor], request: SolveRequest = SolveRequest()
                       ) -> torch.Tensor:
        """Write ``values`` into the model and solve (warm-started) as ``request`` asks; an exact solve raises
        (``strict``) or warns when it misses the tolerance. The warm start only moves on success."""
        self._write(values)
        tol = self._tolerance()
        start = self._x_last if (self.warm_start and self._x_last is not None) else self.x_init
        settings = replace(self.settings, rtol=0.0, atol=tol)
        if request.iterations is not None:  # inexact: S iterations, stopping early at the tolerance
            x, info = solve(self.model, start, settings, solver=self.inexact_solver,
                            max_iterations=request.iterations)
        else:
            x, info = solve(self.model, start, settings, solver=self.solver,
                            max_iterations=request.max_iterations)
        self.last_info = info
        self.sim_iterations += info.iterations
        if request.iterations is None and not (info.residual <= tol):
            self._fail(f"forward solve did not converge: force norm {info.residual:.3g} N > tolerance "
                       f"{tol:.3g} N after {info.iterations} iterations ({info.message}); its gradient would "
                       "be wrong")
        self._x_last = x.detach().clone()
        return x.detach()

    # ------------------------------------------------------------------ linear solves at a state
    def adjoint(self, x: torch.Tensor, rhs: torch.Tensor, *,
                hessian: "str | AdjointHessian" = AdjointHessian.EXACT) -> torch.Tensor:
        """``lambda = K^-1 rhs`` (V, 3) at ``x`` with the layer's adjoint solver: the backward of
        :class:`QuasistaticSolve`. SPARSE factorizations are cached on ``x`` (the exact Hessian's shared with
        :meth:`tangent`); CG starts from the previous adjoint with ``cg_warm_start`` and accepts an
        unconverged iterate unless ``cg_require_convergence`` (MINRES where ``K`` is indefinite); a MINRES
        answer no better than zero is replaced by the SPARSE solve (``adjoint_fallbacks`` counts them).

        Args:
            x: (V, 3) state in metres (an equilibrium for an exact gradient).
            rhs: (V, 3) ``dL/dx`` in loss units per metre.
            hessian: the :class:`AdjointHessian` ``K`` (``"exact"``, or ``"projected"``: falls back to the
                exact one, counted in ``adjoint_fallbacks``, where the projected one is singular).
        """
        which = AdjointHessian.resolve(hessian)
        warm = self._adjoint_last if (self.cg_warm_start and self._adjoint_last is not None
                                      and self._adjoint_last.shape == x.shape) else None
        solve_kw = dict(hessian_product=self.hessian_product, rtol=self.cg_rtol,
                        max_iterations=self.cg_max_iterations, x0=warm,
                        require_convergence=self.cg_require_convergence, assembler=self._assembler)
        info = None
        if which == AdjointHessian.PROJECTED:
            try:
                lam, info = solve_adjoint(self.model, x, rhs, self.linear_solver, **solve_kw,
                                          cache=self._projected_factorizations, hessian=which)
            except SingularMatrixError:  # a part that nothing holds: the exact Hessian, as by default
                self.adjoint_fallbacks += 1
        if info is None:
            lam, info = solve_adjoint(self.model, x, rhs, self.linear_solver, **solve_kw,
                                      cache=self._factorizations)
        self.adjoint_iterations += info.iterations  # a replaced MINRES answer's iterations count too
        if info.negative_curvature and not info.relative_residual < 1.0:
            lam, info = solve_adjoint(self.model, x, rhs, AdjointLinearSolver.SPARSE,
                                      assembler=self._assembler, cache=self._factorizations)
            self.adjoint_fallbacks += 1
        self.last_adjoint_info = info
        if self.cg_warm_start:
            self._adjoint_last = lam.detach().clone()
        return lam

    def tangent(self, values: Mapping[str, torch.Tensor],
                dvalues: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """``dx = (dx*/dtheta) dtheta`` (V, 3) at the last solution: one tangent solve ``K dx = -(d grad_x E /
        dtheta) dtheta``, with the SPARSE factorization cached on the state (the one an adjoint at the same
        state uses), whatever the adjoint solver. ``(d grad_x E / dtheta) dtheta`` is forward-over-reverse
        autograd of the terms that own the parameters.

        Args:
            values: the parameter values of the last solve, by name (as for :meth:`forward`).
            dvalues: the directions ``dtheta``, by the same names, shaped like the values.

        Returns:
            (V, 3) in metres per unit of ``dtheta``.
        """
        if self._x_last is None:
            raise InputError("solve before asking for a tangent")
        x = self._x_last
        vals = self._resolve(values, {})
        dirs = {self._slot(k).name: v.detach() for k, v in dvalues.items()}
        if set(dirs) != set(vals):
            raise InputError(f"tangent directions {sorted(dirs)} do not match the values {sorted(vals)}")
        slots = {s.name: s for s in self._slots}
        names = tuple(vals)

        def grad_x(*prim: torch.Tensor) -> torch.Tensor:
            by_term: dict[int, dict[str, torch.Tensor]] = {}
            for n, v in zip(names, prim):
                by_term.setdefault(slots[n].term, {})[slots[n].attr] = v
            total = None
            for i, params in by_term.items():
                term = self.model.terms[i]
                g = func_grad(lambda xx, term=term, params=params: functional_call(term, params, (xx,)))(x)
                total = g if total is None else total + g
            return total

        prim = tuple(vals[n].detach() for n in names)
        tang = tuple(dirs[n].to(vals[n].dtype) for n in names)
        _, dg = func_jvp(grad_x, prim, tang)
        lam, _ = solve_adjoint(self.model, x, dg.detach(), AdjointLinearSolver.SPARSE,
                               assembler=self._assembler,
                               cache=self._factorizations)
        return -lam

    def _fail(self, msg: str) -> None:
        if self.strict:
            raise NonConvergenceError(msg)
        warnings.warn(msg, NonConvergenceWarning, stacklevel=3)

    # ------------------------------------------------------------------ differentiable Newton
    def _energy_fn(self, values: Mapping[str, torch.Tensor]) -> Callable[[torch.Tensor], torch.Tensor]:
        slots = {s.name: s for s in self._slots}
        params = {slots[n].path: v for n, v in values.items()}
        return lambda x: functional_call(self.model, params, (x,))

    def _newton_unrolled(self, values: Mapping[str, torch.Tensor], x_start: torch.Tensor, steps: int,
                         tol: float | None, differentiate_hessian: bool) -> torch.Tensor:
        """Newton iterations as an autograd graph in ``x`` and the parameter values.

        Each step ``x <- x - a (H + l I)^-1 g`` uses the autograd gradient ``g`` (differentiable in ``x`` and
        the parameters) and the exact dense Hessian ``H``: differentiable (autograd, batched double backward)
        when ``differentiate_hessian``, else the detached assembled :func:`exact_hessian_blocks` (TRUNCATED:
        from a converged start the dropped derivative multiplies ``g ~ 0``). The step length ``a``
        (barrier-capped Armijo backtracking) and the regularization ``l`` (0 unless ``H`` is not positive
        definite) are decisions taken on detached values. With ``tol`` None, exactly ``steps`` steps; else
        until ``|g| <= tol`` (at most ``steps``).
        """
        energy = self._energy_fn(values)
        s = self.settings
        x = x_start.detach().clone()
        n = x.numel()
        eye = torch.eye(n, dtype=x.dtype, device=x.device)
        converged = False
        gn = math.inf
        with torch.enable_grad():
            for k in range(steps + (0 if tol is None else 1)):
                xr = x if x.requires_grad else x.detach().requires_grad_(True)
                e = energy(xr)
                (g,) = torch.autograd.grad(e, xr, create_graph=True)
                gn = float(torch.linalg.vector_norm(g.detach()))
                if tol is not None and gn <= tol:
                    converged = True
                    break
                if k == steps:
                    break
                if differentiate_hessian:
                    try:
                        rows = torch.autograd.grad(g.reshape(-1), xr, eye, create_graph=True,
                                                   is_grads_batched=True)[0]
                    except RuntimeError as exc:
                        raise InputError(f"backward mode 'unroll' needs twice-differentiable energy terms "
                                         f"({exc}); use 'adjoint'") from exc
                    H = rows.reshape(n, n)
                    H = 0.5 * (H + H.T)
                else:
                    H = exact_hessian_blocks(self.model, x.detach()).to_sparse(
                        self.model.num_vertices).to_dense()
                lam = 0.0
                scale = float(H.detach().diagonal().abs().mean()) or 1.0
                for _ in range(s.max_regularizations + 1):
                    chol, info = torch.linalg.cholesky_ex(H.detach() + lam * eye)
                    if int(info) == 0:
                        break
                    lam = s.regularization * scale if lam == 0.0 else 10.0 * lam
                else:
                    raise NonConvergenceError("unrolled Newton: no positive definite regularization found")
                A = H + lam * eye if lam > 0 else H
                dx = -torch.linalg.solve(A, g.reshape(-1)).view_as(x)
                a = self._step_length(x.detach(), g.detach(), dx.detach(), float(e.detach()))
                x = xr + a * dx
        if tol is not None and not converged:
            self._fail(f"unrolled Newton did not converge: force norm {gn:.3g} N > tolerance {tol:.3g} N "
                       f"after {steps} iterations")
        return x

    @torch.no_grad()
    def _step_length(self, x: torch.Tensor, g: torch.Tensor, dx: torch.Tensor, e: float) -> float:
        s = self.settings
        slope = float(torch.sum(g * dx))
        a = float(self.model.max_step(x, dx))
        a = 1.0 if a >= 1.0 else s.step_fraction * a
        if slope >= 0.0:  # not a descent direction (cannot happen with a PD matrix); take the capped step
            return a
        slack = 16.0 * torch.finfo(x.dtype).eps * abs(e)

        def energy(t: float) -> float:
            return float(self.model.value_and_grad(x + t * dx)[0])

        a, _, ok = armijo_backtracking(energy, e, slope, a, armijo_c=s.armijo_c, backtrack=s.backtrack,
                                       max_backtracks=s.max_backtracks, slack=slack)
        return a if ok else a * s.backtrack  # out of backtracks: the step shrunk once more


SolveLayer = DifferentiableSolver
"""Alias of :class:`DifferentiableSolver`."""

__all__ = [
    "AdjointInfo",
    "AdjointLinearSolver",
    "FactorizationCache",
    "BackwardMode",
    "DifferentiableSolver",
    "HessianProduct",
    "NonConvergenceError",
    "NonConvergenceWarning",
    "QuasistaticSolve",
    "SolveLayer",
    "SolveRequest",
    "check_twice_differentiable",
    "exact_hessian_blocks",
    "parameter_vjp",
    "solve_adjoint",
]
