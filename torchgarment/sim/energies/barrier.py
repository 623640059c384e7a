"""Log barrier keeping the garment outside the body (Wang et al. 2018, Eq. 4).

::

    E = sum_i b(phi(x_i))                  phi: the body's signed distance (metres, negative inside)
    b(phi) = -mu log(phi)                                   unbounded (dhat = None): the paper's Eq. 4
    b(phi) = -mu (phi/dhat - 1)^2 log(phi/dhat), phi < dhat range-limited (IPC form, Li et al. 2020), 0 beyond

``mu`` is in joules (the paper uses 0.01). Near the body both forms push with ``mu grad phi / phi``, which
grows without bound as a vertex approaches the body. The unbounded form also pushes at every distance
(``mu / phi`` = 0.25 N at 4 cm for ``mu = 0.01`` J, hundreds of times a cloth vertex's weight in SI units), so
loose cloth floats on the far field; the range-limited form (the default in :class:`~torchgarment.sim.scene.
Material`, ``dhat`` = 3 mm) is C2 at ``dhat`` and acts only within ``dhat`` of the body: resting cloth sits
just inside ``dhat`` (for a vertex weight ``w`` the equilibrium is ``phi = dhat (1 - u)`` with
``3 mu u^2 / dhat = w``, ``u`` ~ 1 % at 2 cm edges), and with it the paper's ``mu = 0.01`` J drapes well.
Where ``phi <= 0`` the energy is ``+inf`` (never NaN); the gradient and Hessian there are evaluated as if
``phi = offset`` (finite, pushing outward), but solvers must not accept such states: use
:meth:`BodyBarrier.max_step` to stay feasible and :meth:`BodyBarrier.project_feasible` to repair an infeasible
start (the paper projects penetrating vertices onto the body surface).

Hessian: per vertex ``b''(phi) g g^T + b'(phi) Hess(phi)`` (``b'' = mu / phi^2``, ``b' = -mu / phi`` for the
unbounded form). ``Hess(phi)`` is the central difference of the SDF's analytic gradient
(:meth:`BodyBarrier.curvature_blocks`, only at the vertices within ``dhat``).
:meth:`BodyBarrier.hessian_blocks` gives the exact sum without projection, and ``b'' g g^T + P(b' Hess(phi))``
with it (``P``: the nearest PSD matrix). Since ``b' < 0``, the curvature part is negative semi-definite where
the body is convex (projected to zero) and positive where it is concave (under the bust, between the legs, at
the armpits): there, without it, Newton's model of a tight garment is too soft and its steps overshoot into
the barrier. Measured on the adjustment's first exact solve of a sheath dress from size 12 on the size-20 body
(1,530 vertices): 590 Newton iterations, the line search cutting the step to 1/8 in 546 of them, without the
part; 113 with it. (Projecting the whole block instead, ``P(b'' g g^T + b' Hess(phi))``, took 228: the
interpolated SDF's ``Hess(phi)`` has a normal component, and its negative part then softens the normal
stiffness.) :meth:`BodyBarrier.hessian_diagonal`, the Jacobi preconditioner of the GD solver, keeps
``b'' g g^T`` alone: the curvature costs six more SDF queries per vertex in range, and GD iterations are meant
to be cheap.

The SDF is any module with ``forward(x) -> phi`` (differentiable) and ``value_and_gradient(x) -> (phi,
grad)``, typically a :class:`~torchgarment.sdf.BodySDF`.
"""

from __future__ import annotations

import math

import torch

from torchgarment.errors import InputError
from torchgarment.sim.energies.base import EnergyTerm, HessianBlocks
from torchgarment.sim.energies.stretch import check_positions

DEFAULT_BARRIER_MU = 0.01
"""Default barrier weight ``mu`` in joules (Wang et al. 2018)."""

DEFAULT_BARRIER_DHAT = 3.0e-3
"""Default range in metres of the range-limited body barrier used by scenes (:class:`~torchgarment.sim.scene.
Material`); resting cloth sits just inside it."""

DEFAULT_OFFSET = 1.0e-3
"""Default minimum clearance in metres that :meth:`BodyBarrier.project_feasible` restores (raised to a quarter
voxel for coarse SDFs)."""

_DIRECT_SAMPLES = 8192
"""Below this many path samples :meth:`BodyBarrier.max_step` skips its end-point pre-check (one query
less)."""

_MAX_TRIALS = 15
"""Trial step lengths certified at once by one multisection pass of :meth:`BodyBarrier.max_step`."""

_MAX_REFINE_SAMPLES = 65536
"""Most path samples of one multisection pass of :meth:`BodyBarrier.max_step`."""

SDF_LIPSCHITZ = math.sqrt(3.0)
"""Lipschitz bound of a trilinear interpolant of exact distances (each partial derivative is at most 1)."""


class BodyBarrier(EnergyTerm):
    """``sum_i b(phi(x_i))`` on a body signed distance field (the log barrier, optionally range-limited).

    Attributes:
        sdf: the signed distance module.
        mu: barrier weight in joules.
        dhat: activation distance in metres of the range-limited form, or None for the unbounded ``-mu log
            phi``.
        offset: clearance in metres restored by :meth:`project_feasible`; also the ``phi`` used for the
            gradient of infeasible vertices.
        lipschitz: assumed Lipschitz constant of ``phi`` (for the safe-step certificate of :meth:`max_step`).
        segment_samples: points sampled along a long vertex path in :meth:`max_step`.
        num_vertices: V.
    """

    name = "body_barrier"
    volatile_hessian = True

    def __init__(
        self,
        sdf: torch.nn.Module,
        num_vertices: int,
        *,
        mu: float = DEFAULT_BARRIER_MU,
        dhat: float | None = None,
        offset: float | None = None,
        lipschitz: float = SDF_LIPSCHITZ,
        segment_samples: int = 8,
        bisection_steps: int = 12,
        project_iterations: int = 8,
        lazy: bool = True,
    ) -> None:
        """Create the barrier.

        Args:
            sdf: module with ``forward`` and ``value_and_gradient`` (a BodySDF).
            num_vertices: V.
            mu: barrier weight in joules, > 0.
            dhat: activation distance in metres (> 0) of the range-limited barrier, or None (unbounded).
            offset: clearance in metres, > 0 (below ``dhat``); None means ``max(1 mm, voxel_size / 4)``, at
                most ``dhat / 2``.
            lipschitz: Lipschitz bound of ``phi`` (>= 1).
            segment_samples: samples per vertex path checked by :meth:`max_step` (>= 1).
            bisection_steps: bisection steps of :meth:`max_step`.
            project_iterations: Newton steps along ``grad phi`` in :meth:`project_feasible`.
            lazy: with a range-limited barrier, query the SDF only for vertices that may be within ``dhat``
                (see :meth:`_phi_grad_lazy`); the results are the same as querying every vertex.

        Raises:
            InputError: an SDF without the needed methods, or out-of-range settings.
        """
        super().__init__()
        if not callable(sdf) or not hasattr(sdf, "value_and_gradient"):
            raise InputError("the body barrier needs an SDF module with value_and_gradient, got "
                             f"{type(sdf).__name__}")
        if not mu > 0:
            raise InputError(f"barrier mu must be positive, got {mu}")
        if dhat is not None and not (math.isfinite(dhat) and dhat > 0):
            raise InputError(f"barrier dhat must be a positive distance in metres or None, got {dhat}")
        if offset is None:
            offset = max(DEFAULT_OFFSET, 0.25 * float(getattr(sdf, "voxel_size", 0.0)))
            if dhat is not None:
                offset = min(offset, 0.5 * dhat)
        if not offset > 0:
            raise InputError(f"barrier offset must be positive, got {offset}")
        if not lipschitz >= 1.0 or segment_samples < 1 or bisection_steps < 0 or project_iterations < 1:
            raise InputError("barrier settings out of range: lipschitz >= 1, segment_samples >= 1, "
                             "bisection_steps >= 0, project_iterations >= 1")
        self.sdf = sdf
        self.num_vertices = int(num_vertices)
        self.mu = float(mu)
        self.dhat = None if dhat is None else float(dhat)
        if self.dhat is not None and offset >= self.dhat:
            raise InputError(f"barrier offset ({offset} m) must be below dhat ({self.dhat} m): projected "
                             f"vertices must land where the barrier acts")
        self.offset = float(offset)
        self.lipschitz = float(lipschitz)
        self.segment_samples = int(segment_samples)
        self.bisection_steps = int(bisection_steps)
        self.project_iterations = int(project_iterations)
        self.lazy = bool(lazy)
        self._ref_x: torch.Tensor | None = None  # (V, 3) where each vertex's phi was last sampled
        self._ref_phi: torch.Tensor | None = None  # (V,) that phi
        #: vertices sampled by the last gradient evaluation (for benchmarks and tests)
        self.last_query_count = 0
        self._cache_x: torch.Tensor | None = None
        self._cache_key: tuple | None = None
        self._cache_val: tuple[torch.Tensor, torch.Tensor] | None = None
        # the last SDF Hessian rows (_sdf_hessian_rows): the x they are of (held), its key, (act, Hess phi)
        self._hess_x: torch.Tensor | None = None
        self._hess_key: tuple | None = None
        self._hess_val: tuple[torch.Tensor, torch.Tensor] | None = None

    def reset_cache(self) -> None:
        """Forget each vertex's last sample (:meth:`_phi_grad_lazy`) and the last query: the next evaluation
        samples every vertex. The lazy bounds are exact where the barrier acts, but the step bounds they give
        :meth:`max_step` depend on where the references were taken, so a solve's last bits depend on the
        solves before it without this."""
        self._ref_x = self._ref_phi = None
        self._cache_x = self._cache_key = self._cache_val = None
        self._hess_x = self._hess_key = self._hess_val = None

    # ------------------------------------------------------------------ sampling
    def _phi(self, x: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return self.sdf(x).to(x.dtype)

    def _phi_grad(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        phi, g = self.sdf.value_and_gradient(x)
        return phi.to(x.dtype), g.to(x.dtype)

    @staticmethod
    def _key(x: torch.Tensor) -> tuple:
        # the version counter is shared by a tensor and its detached aliases, so in-place changes are seen;
        # the cached tensor is held, so its storage (and data_ptr) cannot be reused by another tensor
        return (x.data_ptr(), x._version, tuple(x.shape), x.stride(), x.dtype, x.device)

    def _cached(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        """``(phi, grad phi)`` of the last :meth:`_phi_grad_cached` call if ``x`` is that same, unmodified
        tensor."""
        if self._cache_x is not None and self._cache_key == self._key(x):
            return self._cache_val
        return None

    def _phi_grad_cached(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(phi, grad phi)`` of all vertices ``x`` (V, 3), reusing the last evaluation when ``x`` is
        unchanged.

        The solvers evaluate the gradient at ``x`` and then call :meth:`max_step` from the same ``x``; the
        cache saves that second SDF query.
        """
        hit = self._cached(x)
        if hit is not None:
            return hit
        if self.lazy and self.dhat is not None:
            val = self._phi_grad_lazy(x)
        else:
            val = self._phi_grad(x)
            self.last_query_count = int(x.shape[0])
        self._cache_x, self._cache_key, self._cache_val = x, self._key(x), val
        return val

    def _phi_grad_lazy(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(phi, grad phi)`` where the range-limited barrier can act; a lower bound of ``phi`` (>= ``dhat``)
        and a zero gradient elsewhere.

        Each vertex keeps the position ``r_i`` and value ``phi(r_i)`` of its last sample. Since ``phi`` is
        ``L``-Lipschitz (:attr:`lipschitz`), ``phi(x_i) >= phi(r_i) - L |x_i - r_i|``; only vertices whose
        bound is below ``dhat`` are sampled again (and their references updated). The others are at least
        ``dhat`` from the body, where the barrier's energy, force and stiffness are exactly zero, so the
        energy and its derivatives equal those of a full query; the returned bound is a valid lower bound of
        ``phi`` for :meth:`max_step` and :meth:`project_feasible`. In a drape most of a loose garment is
        beyond ``dhat``, so most iterations sample a fraction of the vertices.
        """
        V = x.shape[0]
        if self._ref_x is None or self._ref_x.shape != x.shape or self._ref_x.dtype != x.dtype \
                or self._ref_x.device != x.device:
            phi, g = self._phi_grad(x)
            self._ref_x, self._ref_phi = x.clone(), phi.clone()
            self.last_query_count = V
            return phi, g
        bound = self._ref_phi - self.lipschitz * torch.linalg.vector_norm(x - self._ref_x, dim=1)
        idx = torch.nonzero(bound < self.dhat, as_tuple=False).flatten()
        self.last_query_count = int(idx.numel())
        phi = bound.clamp_min(self.dhat)
        g = torch.zeros_like(x)
        if idx.numel() == V:
            phi, g = self._phi_grad(x)
            self._ref_x.copy_(x)
            self._ref_phi.copy_(phi)
            return phi, g
        if idx.numel():
            xi = x.index_select(0, idx)
            pi, gi = self._phi_grad(xi)
            phi = phi.index_copy(0, idx, pi)
            g.index_copy_(0, idx, gi)
            self._ref_x.index_copy_(0, idx, xi)
            self._ref_phi.index_copy_(0, idx, pi)
        return phi, g

    # ------------------------------------------------------------------ energy
    def barrier(self, phi: torch.Tensor) -> torch.Tensor:
        """``b(phi)`` (any shape) for ``phi > 0``, differentiable (autograd); 0 beyond ``dhat``."""
        if self.dhat is None:
            return -self.mu * torch.log(phi)
        s = (phi / self.dhat).clamp(max=1.0)
        return -self.mu * (s - 1.0).square() * torch.log(s)

    def derivatives(self, phi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(b'(phi), b''(phi))`` (same shape as ``phi``) in J/m and J/m^2, for ``phi > 0``."""
        if self.dhat is None:
            inv = 1.0 / phi
            return -self.mu * inv, self.mu * inv * inv
        s = (phi / self.dhat).clamp(max=1.0)
        sm1 = s - 1.0
        ls = torch.log(s)
        d1 = (-self.mu / self.dhat) * (2.0 * sm1 * ls + sm1 * sm1 / s)
        d2 = (-self.mu / self.dhat ** 2) * (2.0 * ls + 4.0 * sm1 / s - (sm1 / s).square())
        return d1, d2

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Energy in joules of positions ``x`` (V, 3), ``+inf`` if a vertex has ``phi <= 0``;
        differentiable."""
        check_positions(x, self.num_vertices, self.name)
        phi = self.sdf(x).to(x.dtype)
        ok = phi > 0
        safe = torch.where(ok, phi, torch.ones_like(phi))
        e = torch.where(ok, self.barrier(safe), torch.full_like(phi, math.inf))
        return e.sum()

    def _evaluate(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Energy (), ``phi`` clamped to :attr:`offset` where infeasible (V,), and ``grad phi`` (V, 3)."""
        check_positions(x, self.num_vertices, self.name)
        phi, gphi = self._phi_grad_cached(x.detach())
        if phi.numel() == 0 or float(phi.min()) > 0:
            return self.barrier(phi).sum(), phi, gphi
        safe = torch.where(phi > 0, phi, torch.full_like(phi, self.offset))
        return torch.full((), math.inf, dtype=phi.dtype, device=phi.device), safe, gphi

    def value_and_grad(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Energy () in joules and analytic gradient ``b'(phi) grad phi`` (V, 3) in newtons."""
        g = torch.zeros_like(x)
        return self.accumulate_value_grad_hessian_diagonal(x, g, None), g

    def value_grad_hessian_diagonal(
        self, x: torch.Tensor, project_psd: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Energy, gradient and Hessian diagonal blocks ``b''(phi) g g^T`` sharing one SDF evaluation."""
        g = torch.zeros_like(x)
        h = torch.zeros(x.shape[0], 3, 3, dtype=x.dtype, device=x.device)
        return self.accumulate_value_grad_hessian_diagonal(x, g, h, project_psd), g, h

    def accumulate_value_grad_hessian_diagonal(
        self, x: torch.Tensor, g: torch.Tensor, h: torch.Tensor | None, project_psd: bool = True
    ) -> torch.Tensor:
        """Add the gradient (and the Hessian diagonal blocks unless ``h`` is None) in place, touching only the
        rows of vertices within ``dhat`` of the body (all rows for the unbounded barrier); return the
        energy."""
        if self.dhat is None:
            E, safe, gphi = self._evaluate(x)
            d1, d2 = self.derivatives(safe)
            g.add_(gphi * d1.unsqueeze(1))
            if h is not None:
                h.add_((gphi * d2.unsqueeze(1)).unsqueeze(2) * gphi.unsqueeze(1))
                self.last_hessian_rows = None
            return E
        check_positions(x, self.num_vertices, self.name)
        phi, gphi = self._phi_grad_cached(x.detach())
        idx = torch.nonzero(phi < self.dhat, as_tuple=False).flatten()  # the only rows the barrier acts on
        if h is not None:
            self.last_hessian_rows = idx
        if idx.numel() == 0:
            return torch.zeros((), dtype=phi.dtype, device=phi.device)
        pa = phi.index_select(0, idx)
        if float(pa.min()) > 0:
            E = self.barrier(pa).sum()
        else:  # infeasible: +inf energy, derivatives as if at the offset (pushing out)
            E = torch.full((), math.inf, dtype=phi.dtype, device=phi.device)
            pa = torch.where(pa > 0, pa, torch.full_like(pa, self.offset))
        gp = gphi.index_select(0, idx)
        d1, d2 = self.derivatives(pa)
        g.index_add_(0, idx, gp * d1.unsqueeze(1))
        if h is not None:
            h.index_add_(0, idx, (gp * d2.unsqueeze(1)).unsqueeze(2) * gp.unsqueeze(1))
        return E

    def _blocks(self, safe: torch.Tensor, gphi: torch.Tensor) -> torch.Tensor:
        _, d2 = self.derivatives(safe)
        s = d2.clamp_min(0.0).sqrt().unsqueeze(1) * gphi  # sqrt(b'') g
        return s.unsqueeze(2) * s.unsqueeze(1)

    def hessian_diagonal(self, x: torch.Tensor, project_psd: bool = True) -> torch.Tensor:
        """(V, 3, 3) diagonal blocks: with ``project_psd`` (the GD solver's Jacobi preconditioner) the
        Gauss-Newton part ``b''(phi) g g^T`` alone (PSD: ``b'' >= 0``; see the module docstring for why the
        curvature is left out there); without, the exact blocks of :meth:`hessian_blocks`."""
        if not project_psd:
            return self.hessian_blocks(x, project_psd=False).values
        _, safe, gphi = self._evaluate(x)
        return self._blocks(safe, gphi)

    def curvature_blocks(self, x: torch.Tensor) -> torch.Tensor:
        """(V, 3, 3) ``b'(phi(x_i)) Hess(phi)(x_i)`` in N/m, zero where ``b' = 0`` (beyond ``dhat``).

        ``Hess(phi)`` is the central difference of the SDF's analytic gradient ``value_and_gradient`` with
        step ``eps^(1/3) * 1 cm`` (``eps`` the dtype's machine epsilon; 6e-8 m in float64), symmetrized:
        exact (up to rounding) for a trilinear interpolant inside a cell and for smooth SDFs up to
        ``O(step^2)``.

        Args:
            x: (V, 3) feasible positions in metres.
        """
        check_positions(x, self.num_vertices, self.name)
        x = x.detach()
        act, curv = self._curvature_rows(x)
        out = torch.zeros(x.shape[0], 3, 3, dtype=x.dtype, device=x.device)
        return out.index_copy_(0, act, curv) if act.numel() else out

    def _curvature_rows(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(act, blocks)``: the vertices where ``b' != 0`` (A,) and their curvature blocks (A, 3, 3)."""
        phi, _ = self._phi_grad_cached(x)
        phi = torch.where(phi > 0, phi, torch.full_like(phi, self.offset))  # as the gradient (see _evaluate)
        d1 = self.derivatives(phi)[0]
        # a range-limited barrier acts on the vertices within dhat only (b' = 0 beyond): difference just those
        act = torch.nonzero(d1 != 0, as_tuple=False).flatten()
        if act.numel() == 0:
            return act, x.new_zeros(0, 3, 3)
        return act, self._sdf_hessian_rows(x, act) * d1.index_select(0, act)[:, None, None]

    def _sdf_hessian_rows(self, x: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        """(A, 3, 3) symmetrized ``Hess(phi)`` at the vertices ``act`` (A,) of ``x`` (see
        :meth:`curvature_blocks`), reusing the last result when ``x`` is the same, unmodified tensor and
        ``act`` the same rows: projected Newton assembles the projected and the exact Hessian at one ``x``,
        and each would otherwise difference the SDF six times."""
        key = (self._key(x), self.sdf)  # (the SDF itself, compared by identity, held with the key)
        if (self._hess_x is not None and self._hess_key == key and self._hess_val is not None
                and torch.equal(self._hess_val[0], act)):
            return self._hess_val[1]
        xa = x.index_select(0, act)
        step = torch.finfo(x.dtype).eps ** (1.0 / 3.0) * 1e-2
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        cols = []
        for a in range(3):
            gp = self._phi_grad(xa + step * eye[a])[1]
            gm = self._phi_grad(xa - step * eye[a])[1]
            cols.append((gp - gm) / (2.0 * step))
        hphi = torch.stack(cols, dim=2)  # (A, 3, 3): column a = d grad / d x_a
        hphi = 0.5 * (hphi + hphi.transpose(1, 2))
        self._hess_x, self._hess_key, self._hess_val = x, key, (act, hphi)
        return hphi

    def hessian_blocks(self, x: torch.Tensor, project_psd: bool = True) -> HessianBlocks:
        """The V diagonal blocks (the barrier couples no two vertices): ``b'' g g^T + b' Hess(phi)``, or with
        ``project_psd`` ``b'' g g^T + P(b' Hess(phi))`` (``P`` clamps negative eigenvalues to zero; see the
        module docstring)."""
        _, safe, gphi = self._evaluate(x)
        h = self._blocks(safe, gphi)
        act, c = self._curvature_rows(x.detach())
        if act.numel():
            if project_psd:
                w, v = torch.linalg.eigh(c)
                c = (v * w.clamp_min(0.0).unsqueeze(1)) @ v.transpose(1, 2)
            h.index_add_(0, act, c)
        ar = torch.arange(self.num_vertices, device=x.device)
        return HessianBlocks(ar, ar.clone(), h)

    # ------------------------------------------------------------------ feasibility
    @torch.no_grad()
    def max_step(self, x: torch.Tensor, dx: torch.Tensor) -> float:
        """Largest ``alpha`` in (0, 1] (up to bisection) such that every path ``x_i + t dx_i``, ``t <=
        alpha``, stays outside the body (``phi > 0``).

        Certificates use the Lipschitz bound ``L`` (:attr:`lipschitz`) of ``phi``: a piece of path from ``a``
        to ``b`` is safe when ``L |b - a| < phi(a) + phi(b)`` (and ``phi(b) > 0``), and so is the ball of
        radius ``phi(a) / L`` around a sample ``a``. In order of cost:

        1. a path shorter than ``phi(x_i) / L`` is safe (no SDF query: ``phi(x_i)`` is reused from the last
           energy evaluation at ``x`` when there was one); if all are, the result is 1.0;
        2. when many paths remain, they are first checked as one piece each, with one sample at the end point;
        3. the paths still open are sampled at :attr:`segment_samples` points; each gets a certified
           ``alpha_i`` (its pieces up to the first failing one, plus the safe ball of the last good sample)
           and, when a sample lies inside the body, an upper bound ``hi_i``;
        4. while the bracket ``[min alpha_i, min hi_i]`` is wider than 1 %: multisection, i.e. bisection
           with up to 15 trial ``alpha`` s per SDF query, each certified by :attr:`segment_samples` pieces on
           ``[0, alpha]`` of the paths not yet certified that far (at most the resolution of
           :attr:`bisection_steps` bisection steps).

        Each stage is one batched SDF query. The result ``min alpha_i`` is never below the conservative
        ``min_i phi(x_i) / (L |dx_i|)``.

        Args:
            x: (V, 3) feasible positions (every ``phi > 0``).
            dx: (V, 3) step.

        Raises:
            InputError: ``x`` is not feasible (use :meth:`project_feasible` first) or ``dx`` has the wrong
                shape.
        """
        check_positions(x, self.num_vertices, self.name)
        check_positions(dx, self.num_vertices, self.name + " step")
        x, dx = x.detach(), dx.detach().to(x.dtype)
        hit = self._cached(x)
        phi0 = hit[0] if hit is not None else self._phi(x)
        if phi0.numel() == 0:
            return 1.0
        if not float(phi0.min()) > 0:
            raise InputError(f"{int((phi0 <= 0).sum())} vertices are inside the body (phi <= 0); "
                             f"call project_feasible first")
        L, n = self.lipschitz, self.segment_samples
        length = torch.linalg.vector_norm(dx, dim=1)
        # stage 1: paths shorter than phi / L (a zero step never becomes a candidate)
        cand = torch.nonzero(L * length >= phi0, as_tuple=False).flatten()
        if cand.numel() == 0:
            return 1.0
        x_c, dx_c, phi_c, len_c = x[cand], dx[cand], phi0[cand], length[cand]
        if cand.numel() * n > _DIRECT_SAMPLES:
            # stage 2: the whole path as one piece
            phi_end = self._phi(x_c + dx_c)
            keep = ~((phi_end > 0) & (L * len_c < phi_c + phi_end))
            if not bool(keep.any()):
                return 1.0
            x_c, dx_c, phi_c, len_c = x_c[keep], dx_c[keep], phi_c[keep], len_c[keep]
        m = len_c.shape[0]
        lo_i = torch.zeros(m, dtype=x.dtype, device=x.device)
        hi_i = torch.ones(m, dtype=x.dtype, device=x.device)
        # stage 3 on all open paths (the start's phi is known), then stage 4 on the limiting ones
        lo_i, hi_i, _ = self._certify(x_c, dx_c, len_c, lo_i, hi_i, phi_c, n)
        lo, hi = min(float(lo_i.min()), 1.0), float(hi_i.min())
        steps = self.bisection_steps
        while steps > 0 and lo < 0.99 * hi:
            # multisection: certify J trial alphas in (lo, hi) at once, on the paths not certified up to them
            rows = torch.nonzero(lo_i < hi, as_tuple=False).flatten()
            J = max(1, min(_MAX_TRIALS, _MAX_REFINE_SAMPLES // (rows.numel() * n)))
            J = min(J, 2 ** steps - 1)  # no finer than the bisection steps left
            trials = lo + (hi - lo) * torch.arange(1, J + 1, dtype=x.dtype, device=x.device) / (J + 1)
            ok = self._certified(x_c[rows], dx_c[rows], phi_c[rows], len_c[rows], lo_i[rows], trials)
            j = int(ok.to(torch.int8).argmin()) if not bool(ok.all()) else J  # first failing trial
            if j > 0:
                lo = float(trials[j - 1])
            if j < J:
                hi = float(trials[j])
            steps -= max(1, int(math.log2(J + 1)))
        return max(min(lo, 1.0), 0.999 * float((phi_c / (L * len_c)).min()))

    def _certified(self, x: torch.Tensor, dx: torch.Tensor, phi: torch.Tensor, length: torch.Tensor,
                   lo_i: torch.Tensor, trials: torch.Tensor) -> torch.Tensor:
        """(J,) bool: whether every path ``x + t dx`` (m, 3) is certified on ``[0, a_j]`` for each trial
        ``a_j`` (``segment_samples`` pieces each); paths already certified up to ``lo_i >= a_j`` count as
        certified."""
        n, L = self.segment_samples, self.lipschitz
        t = torch.arange(1, n + 1, dtype=x.dtype, device=x.device) / n
        at = trials[:, None] * t[None, :]  # (J, n)
        pts = x[:, None, None, :] + at[None, :, :, None] * dx[:, None, None, :]  # (m, J, n, 3)
        ph = self._phi(pts.reshape(-1, 3)).view(x.shape[0], trials.shape[0], n)
        prev = torch.cat([phi[:, None, None].expand(-1, trials.shape[0], 1), ph[:, :, :-1]], dim=2)
        piece = (L / n) * trials[None, :, None] * length[:, None, None]
        good = ((ph > 0) & (piece < prev + ph)).all(dim=2) | (lo_i[:, None] >= trials[None, :])  # (m, J)
        return good.all(dim=0)

    def _certify(self, x: torch.Tensor, dx: torch.Tensor, length: torch.Tensor, s: torch.Tensor,
                 e: torch.Tensor,
                 phi_s: torch.Tensor | None, n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Sample the paths ``x + t dx`` (m, 3) on ``t in [s, e]`` (m,) in ``n`` pieces, where ``[0, s]`` is
        already certified.

        Args:
            phi_s: ``phi`` at ``t = s`` when known (then not sampled again), else None.

        Returns:
            The new certified ``alpha`` (m,), upper bounds (m,) (``e`` unless a sample is inside the body) and
            ``phi`` of the last good sample (m,) (a clearance estimate for the next pass).
        """
        L = self.lipschitz
        k = torch.arange(0 if phi_s is None else 1, n + 1, dtype=x.dtype, device=x.device) / n
        tt = s[:, None] + (e - s)[:, None] * k[None, :]  # (m, n + 1) or (m, n)
        pts = x[:, None, :] + tt[:, :, None] * dx[:, None, :]
        ph = self._phi(pts.reshape(-1, 3)).view(tt.shape)
        if phi_s is not None:
            ph = torch.cat([phi_s[:, None], ph], dim=1)
            tt = torch.cat([s[:, None], tt], dim=1)
        piece = (L / n) * (e - s) * length  # (m,) length of a piece times L
        good = (ph[:, 1:] > 0) & (piece[:, None] < ph[:, :-1] + ph[:, 1:]) & (ph[:, :1] > 0)  # (m, n)
        bad = ~good
        failing = bad.any(dim=1)
        f = bad.to(torch.int8).argmax(dim=1, keepdim=True)  # first failing piece (0 if none: masked below)
        t_a, t_b = tt.gather(1, f)[:, 0], tt.gather(1, f + 1)[:, 0]
        ball = ph.gather(1, f)[:, 0].clamp_min(0.0) / (L * length)
        lo = torch.where(failing, torch.minimum(t_a + ball, t_b), e)
        inside = failing & (ph.gather(1, f + 1)[:, 0] <= 0)
        hi = torch.where(inside, torch.minimum(t_b, e), e)
        return torch.maximum(lo, s), hi, ph.gather(1, f)[:, 0]

    @torch.no_grad()
    def project_feasible(self, x: torch.Tensor) -> torch.Tensor:
        """Positions with every vertex at least about :attr:`offset` outside the body.

        Vertices with ``phi < offset`` move along ``grad phi / |grad phi|`` by ``offset - phi``, repeated
        :attr:`project_iterations` times since the interpolated gradient is approximate. Others are unchanged
        (only the vertices below the offset are sampled again; none when every vertex is clear).

        Args:
            x: (V, 3) positions in metres.

        Returns:
            (V, 3) new positions (``x`` is not modified).

        Raises:
            InputError: some vertices are still inside the body afterwards (e.g. a zero SDF gradient).
        """
        check_positions(x, self.num_vertices, self.name)
        y = x.detach().clone()
        hit = self._cached(x.detach())
        phi = hit[0] if hit is not None else self._phi(y)
        idx = torch.nonzero(phi < self.offset, as_tuple=False).flatten()
        if idx.numel() == 0:
            return y
        moved = idx
        for _ in range(self.project_iterations):
            phib, gb = self._phi_grad(y[idx])
            low = phib < self.offset
            if not bool(low.any()):
                return y
            idx, phib, gb = idx[low], phib[low], gb[low]
            gn = torch.linalg.vector_norm(gb, dim=1, keepdim=True)
            y[idx] += (self.offset - phib).unsqueeze(1) * gb / gn.clamp_min(torch.finfo(y.dtype).tiny)
        inside = int((self._phi(y[moved]) <= 0).sum())
        if inside:
            raise InputError(f"project_feasible: {inside} vertices are still inside the body after "
                             f"{self.project_iterations} projection steps")
        return y

    def extra_repr(self) -> str:
        rng = "unbounded" if self.dhat is None else f"dhat={self.dhat} m"
        return f"mu={self.mu} J, {rng}, offset={self.offset} m"
