"""IPC contact energies (Li et al. 2020, Incremental Potential Contact) computed by ``ipctk``.

Two :class:`~torchgarment.sim.energies.base.EnergyTerm` subclasses:

* :class:`SelfContact`: cloth-cloth contact of a garment with itself (multi-layer garments), or only within
  each panel of an unsewn garment (the sewing stage's, ``vertex_panel_ids``).
* :class:`BodyMeshContact`: garment against a static body triangle mesh (optionally plus self-contact).

The energy is ipctk's area-weighted "physical" log barrier (the convergent IPC formulation)::

    E(x) = kappa * sum_k w_k * b(d_k),   b(d) = -(d^2 - dhat^2)^2 ln(d^2 / dhat^2) / units,  0 < d < dhat

over the point-triangle and edge-edge pairs closer than ``dhat`` (metres); ``w_k`` are barycentric areas
(m^2) and ``b`` is normalised to a length, so the stiffness ``kappa`` is a pressure (Pa) and E is in joules.
``E`` is 0 beyond ``dhat`` and tends to +inf as two primitives touch. Crossing (intersecting) primitives can
have a finite barrier, so the terms additionally report +inf when the mesh intersects
(``check_intersections``).

Collision candidates are rebuilt from ``x`` by ipctk's broad phase on every call (the last set is reused when
a call sees exactly the same positions, e.g. ``value_and_grad`` then ``hessian_blocks``). Everything at the
boundary is device/dtype agnostic: positions go to numpy float64 for ipctk, results come back in ``x``'s dtype
on ``x``'s device. Not differentiable twice (``forward`` has a first-order custom backward).

Seams: a pattern mesh keeps one vertex per panel on a seam, and sewing drives the pairs to distance 0, which
a barrier between the panels would forbid. Pass ``seam_pairs`` and contact works on the *welded* garment
(:class:`SeamWeld`): each group of stitched vertices is one collision vertex at their mean, so the primitives
that meet at a seam are adjacent, as in the finished garment, and every other pair is in contact; gradients
and Hessians go back to the garment's vertices through the averaging map. Before 2026-12-02 the seams were
an ipctk collision filter that excluded every vertex pair in the closed one-ring of a seam; it left folds
next to a seam free to pass through each other (the GarmentCode pencil dress settled with self-contact to 6
crossings of its welded mesh, all at seams) and then stalled the solver (ipctk's intersection test still saw
some of them).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass

import ipctk
import numpy as np
import scipy.sparse as sp
import torch
from threadpoolctl import threadpool_limits

from torchgarment.errors import InputError, MeshError
from torchgarment.options import OptionEnum
from torchgarment.sim.energies.base import EnergyTerm, HessianBlocks
from torchgarment.sim.obstacle_pairs import GarmentObstaclePairs
from torchgarment.structures import seam_weld_index, welded_faces

#: Additive CCD's steps per pair at most (ipctk's default is 1e7); a pair still closing after them gets the
#: time reached, a conservative bound (see :attr:`StepBound.ADDITIVE`)
ADDITIVE_MAX_ITERATIONS = 100_000


class StepBound(OptionEnum):
    """How a step ``x + alpha dx`` is bounded so that it stays intersection free
    (:func:`collision_free_step`).

    ADDITIVE: ipctk candidates of the swept boxes, then Additive CCD (conservative advancement, Li et al.
        2021) rescaled by 0.9: a safe lower bound of the time of impact at a fraction of Tight Inclusion's
        cost on dense contact (retargeting's default). Its loop advances the positions step by step, and
        round-off drifts them: a pair that needs millions of steps can pass through a crossing (measured: an
        edge pair 4.2e-11 apart at the start of a step, crossing at t = 0.34, ipctk's default 1e7 steps
        report no collision; 1e6 steps stop at 0.3399). The loop stops at :data:`ADDITIVE_MAX_ITERATIONS`
        steps and reports the time reached, a conservative bound (0.034 on that pair; Tight Inclusion took
        45 s on it).
    TIGHT_INCLUSION: ipctk's Tight-Inclusion CCD (tolerance ``ccd_tolerance``) rescaled by 0.8: the largest
        safe step, but expensive on dense steps.
    CONSERVATIVE: ``alpha = safety * min(d_min, r) / reach`` from the minimum distance ``d_min`` of pairs
        closer than ``r``, ``reach`` bounding how much any pair's distance can shrink over the step: one
        distance query,
        never larger than the true time of impact, usually smaller (the default of the simulation contacts).
    """

    ADDITIVE = "additive"
    TIGHT_INCLUSION = "tight_inclusion"
    CONSERVATIVE = "conservative"

    @classmethod
    def aliases(cls) -> dict[str, str]:  # noqa: D102
        return {"ccd": "additive", "acd": "additive", "tight": "tight_inclusion", "distance": "conservative"}


class BroadPhase(OptionEnum):
    """ipctk broad-phase method used to find candidate pairs (ipctk's class names are accepted too)."""

    HASH_GRID = "hash_grid"
    LBVH = "lbvh"
    SWEEP_AND_PRUNE = "sweep_and_prune"
    BRUTE_FORCE = "brute_force"

    @classmethod
    def aliases(cls) -> dict[str, str]:  # noqa: D102
        return {"hashgrid": "hash_grid", "sweepandprune": "sweep_and_prune", "bruteforce": "brute_force"}

    def make(self) -> "ipctk.BroadPhase":
        """A fresh ipctk broad-phase object."""
        return _BROAD_PHASES[self]()


_BROAD_PHASES = {
    BroadPhase.HASH_GRID: ipctk.HashGrid,
    BroadPhase.LBVH: ipctk.LBVH,
    BroadPhase.SWEEP_AND_PRUNE: ipctk.SweepAndPrune,
    BroadPhase.BRUTE_FORCE: ipctk.BruteForce,
}

#: default areal density (kg/m^2) of cloth used for IPC's minimum stiffness (light cotton ~0.1-0.3)
DEFAULT_AREAL_DENSITY = 0.2


def _np_faces(faces: torch.Tensor | np.ndarray, what: str) -> np.ndarray:
    f = faces.detach().cpu().numpy() if isinstance(faces, torch.Tensor) else np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise MeshError(f"{what} must be an integer (F, 3) array, got shape {f.shape} dtype {f.dtype}")
    if f.shape[0] == 0:
        raise MeshError(f"{what} is empty")
    return np.asfortranarray(f, dtype=np.int32)


def _np_points(p: torch.Tensor | np.ndarray, what: str) -> np.ndarray:
    a = (
        p.detach().to("cpu", torch.float64).numpy()
        if isinstance(p, torch.Tensor)
        else np.asarray(p, np.float64)
    )
    if a.ndim != 2 or a.shape[1] not in (2, 3):
        raise InputError(f"{what} must be a (V, 3) (or (V, 2) flat) array, got shape {a.shape}")
    if a.shape[1] == 2:
        a = np.concatenate([a, np.zeros((a.shape[0], 1))], axis=1)
    if not np.isfinite(a).all():
        raise InputError(f"{what} contains non-finite values")
    return np.asfortranarray(a)


def _np_seams(seam_pairs: torch.Tensor | np.ndarray, num_vertices: int) -> np.ndarray:
    a = np.asarray(seam_pairs.cpu() if isinstance(seam_pairs, torch.Tensor) else seam_pairs)
    if (
        a.ndim != 2
        or a.shape[1] != 2
        or not np.issubdtype(a.dtype, np.integer)
        or (a.size and (a.min() < 0 or a.max() >= num_vertices))
    ):
        raise InputError(
            f"seam_pairs must be an integer (S, 2) array of vertex indices in [0, {num_vertices})"
        )
    return a.astype(np.int64)


def _np_panel_ids(vertex_panel_ids: torch.Tensor | np.ndarray, num_vertices: int) -> np.ndarray:
    """(V, 1) int32 panel ids, as ipctk's vertex-patch filter takes them."""
    a = np.asarray(vertex_panel_ids.cpu() if isinstance(vertex_panel_ids, torch.Tensor) else vertex_panel_ids)
    if a.shape != (num_vertices,) or not np.issubdtype(a.dtype, np.integer):
        raise InputError(f"vertex_panel_ids must be an integer ({num_vertices},) array, got {a.dtype} "
                         f"{a.shape}")
    return a.astype(np.int32).reshape(-1, 1)


@dataclass(frozen=True)
class SeamWeld:
    """A sewn garment as contact sees it: every group of stitched vertices (chains of seam pairs) is one
    collision vertex at the group's mean position (:func:`~torchgarment.structures.seam_weld_index`, as
    :meth:`GarmentMesh.welded <torchgarment.structures.GarmentMesh.welded>`).

    Attributes:
        index: (V,) int64, the collision vertex of every garment vertex.
        mean: (V', V) CSR averaging map: collision positions ``= mean @ x`` (each row sums to 1).
        dof_mean: (3V', 3V) CSR, the same map on coordinates (``kron(mean, I3)``); gradients go back as
            ``dof_mean.T @ g``, Hessians as ``dof_mean.T @ H @ dof_mean``.
    """

    index: np.ndarray
    mean: sp.csr_matrix
    dof_mean: sp.csr_matrix

    @classmethod
    def of(cls, seam_pairs: np.ndarray, num_vertices: int) -> "SeamWeld":
        """The weld of ``num_vertices`` garment vertices along ``seam_pairs`` (S, 2)."""
        index, n_welded = seam_weld_index(seam_pairs, num_vertices)
        counts = np.bincount(index, minlength=n_welded).astype(np.float64)
        cols = np.arange(num_vertices)
        mean = sp.csr_matrix((1.0 / counts[index], (index, cols)), shape=(n_welded, num_vertices))
        return cls(index, mean, sp.kron(mean, sp.identity(3), format="csr"))

    @property
    def num_welded(self) -> int:
        """V', the number of collision vertices."""
        return int(self.mean.shape[0])

    def faces(self, faces: np.ndarray) -> np.ndarray:
        """(F', 3) int32 Fortran faces over the collision vertices; faces that collapse (two corners of one
        face sewn together, e.g. at a dart tip) are dropped."""
        return np.asfortranarray(welded_faces(self.index, faces)[0], dtype=np.int32)


@contextmanager
def ipc_threads(threads: int | None, *, whole_process: bool = False) -> Iterator[None]:
    """ipctk's thread count inside the block, restored at its end (None: left as it is).

    With ``whole_process`` also torch's intra-op threads and the thread pools of the BLAS libraries loaded in
    the process (numpy's OpenBLAS and any other that ``threadpoolctl`` finds), so that a run on ``threads``
    threads uses that many cores: without the BLAS limit numpy's OpenBLAS kept the second core of a 2-core
    machine busy through a retargeting run at ``threads=1`` (63.2 s of CPU for 43.1 s of wall time, the
    trousers on creature-10k; 40.9 s for 42.3 s with it, the pair 36.5 against 35.8 s). A BLAS library
    first loaded inside the block (cvxopt's, at the first CHOLMOD factorization) keeps its own count.

    ipctk sums energies, gradients and Hessians over its threads in no fixed order, so only one thread gives
    the same bits on every run (a folded sheet with 696,572 pairs: 8 different energies in 8 evaluations at 2
    threads). These libraries keep their counts for the whole process and take no per-call argument, hence a
    block.

    Raises:
        InputError: ``threads`` is neither None nor a positive integer.
    """
    if threads is None:
        yield
        return
    if not (isinstance(threads, int) and threads >= 1):
        raise InputError(f"ipctk threads must be a positive integer or None, got {threads!r}")
    saved = ipctk.get_num_threads(), torch.get_num_threads()
    with ExitStack() as stack:
        ipctk.set_num_threads(threads)
        stack.callback(ipctk.set_num_threads, saved[0])
        if whole_process:
            torch.set_num_threads(threads)
            stack.callback(torch.set_num_threads, saved[1])
            stack.enter_context(threadpool_limits(limits=threads, user_api="blas"))
        yield


def _on_segment(xn: np.ndarray, x0: np.ndarray, dx: np.ndarray, alpha: float) -> bool:
    """Whether ``xn`` is ``x0 + a dx`` for some ``0 <= a <= alpha``, up to the round-off of forming it (all
    (N, 3) arrays)."""
    dd = float(np.vdot(dx, dx))
    if not dd > 0:
        return False
    a = float(np.vdot(xn - x0, dx)) / dd
    if not -1e-12 <= a <= alpha * (1.0 + 1e-12):
        return False
    tol = 64 * np.finfo(np.float64).eps * (float(np.abs(x0).max()) + float(np.abs(dx).max()))
    return float(np.abs(xn - x0 - a * dx).max()) <= tol


def _energy_or_inf(e: float) -> float:
    # ipctk returns NaN (0 * inf in the area-weighted barrier) when two primitives touch exactly (d = 0),
    # where the barrier is +inf; no other input gives NaN (positions are checked finite).
    e = float(e)
    return math.inf if math.isnan(e) else e


def build_collisions(
    mesh: "ipctk.CollisionMesh", xn: np.ndarray, dhat: float, broad_phase: BroadPhase | GarmentObstaclePairs
) -> "ipctk.NormalCollisions":
    """ipctk's collision set of the pairs of ``mesh`` closer than ``dhat`` at positions ``xn`` (Fortran
    (V, 3)), with candidates from ipctk's ``broad_phase`` or from a :class:`GarmentObstaclePairs` (which
    numbers ``mesh``)."""
    col = ipctk.NormalCollisions()
    if isinstance(broad_phase, GarmentObstaclePairs):
        col.build(broad_phase.candidates(xn, 0.5 * float(dhat)), mesh, xn, float(dhat), 0.0)
    else:
        col.build(mesh, xn, float(dhat), 0.0, broad_phase.make())
    return col


def minimum_distance(
    mesh: "ipctk.CollisionMesh",
    xn: np.ndarray,
    max_distance: float,
    broad_phase: BroadPhase | GarmentObstaclePairs,
    collisions: "ipctk.NormalCollisions | None" = None,
) -> float:
    """Smallest distance between (non-filtered) primitives of ``mesh`` at positions ``xn`` (Fortran (V, 3)),
    searched within ``max_distance`` (units of ``xn``); +inf when no pair is that close. ``collisions``: a
    collision set already built within ``max_distance`` at ``xn`` (saves the query)."""
    col = collisions
    if col is None:
        col = build_collisions(mesh, xn, max_distance, broad_phase)
    if len(col) == 0:
        return math.inf
    return math.sqrt(max(float(col.compute_minimum_distance(mesh, xn)), 0.0))


def intersects_itself(vertices: torch.Tensor | np.ndarray, faces: torch.Tensor | np.ndarray) -> bool:
    """Whether a triangle mesh intersects itself: an edge crossing a triangle it does not share a vertex with
    (ipctk's exact test over its broad phase). Touching along a shared edge or vertex is not a crossing.

    Args:
        vertices: (V, 3) positions (any unit). faces: (F, 3) vertex indices.
    """
    v = _np_points(vertices, "vertices")
    f = _np_faces(faces, "faces")
    return bool(ipctk.has_intersections(ipctk.CollisionMesh(v, ipctk.edges(f), f), v))


def self_crossings(vertices: torch.Tensor | np.ndarray, faces: torch.Tensor | np.ndarray) -> np.ndarray:
    """Every crossing of :func:`intersects_itself`, for a diagnosis: the edges that pass through a triangle
    they share no vertex with (ipctk's edge-triangle candidates, each tested exactly).

    Args:
        vertices: (V, 3) positions (any unit). faces: (F, 3) vertex indices.

    Returns:
        (K, 3) int64 rows ``(edge start, edge end, crossed face)``.
    """
    v = _np_points(vertices, "vertices")
    f = _np_faces(faces, "faces")
    mesh = ipctk.CollisionMesh(v, ipctk.edges(f), f)
    broad = BroadPhase.LBVH.make()
    broad.build(v, mesh.edges, mesh.faces, 0.0)
    edges = np.asarray(mesh.edges)
    rows = []
    for cand in broad.detect_edge_face_candidates():
        a, b = edges[cand.edge_id]
        t = f[cand.face_id]
        if ipctk.is_edge_intersecting_triangle(v[a], v[b], v[t[0]], v[t[1]], v[t[2]]):
            rows.append((a, b, cand.face_id))
    return np.asarray(rows, dtype=np.int64).reshape(-1, 3)


def collision_free_step(
    mesh: "ipctk.CollisionMesh",
    x0: np.ndarray,
    x1: np.ndarray,
    method: StepBound,
    broad_phase: BroadPhase | GarmentObstaclePairs,
    *,
    reach: float,
    dhat: float,
    safety: float = 0.8,
    radius: float = math.inf,
    ccd_tolerance: float = 1e-6,
    dhat_collisions: "ipctk.NormalCollisions | None" = None,
) -> float:
    """Largest alpha in [0, 1] (conservative) such that the linear motion from ``x0`` to ``x0 + alpha (x1 -
    x0)`` of the collision mesh stays intersection free (see :class:`StepBound`).

    Args:
        mesh: the ipctk collision mesh. x0, x1: (V, 3) Fortran-ordered positions at alpha = 0 and 1.
        method: :class:`StepBound`. broad_phase: :class:`BroadPhase`, or the :class:`GarmentObstaclePairs`
            that numbers ``mesh``.
        reach: upper bound of how much the distance of any pair can shrink over the whole step (units of x):
            every point of a primitive moves by at most its vertices' largest displacement along a linear
            step, so ``2 max|dx|`` for self-contact (``M_g + max(M_g, M_a)`` with a moving obstacle); 0: no
            motion.
        dhat: the barrier's activation distance. safety: CONSERVATIVE's fraction of the distance bound.
        radius: CONSERVATIVE queries pairs within ``max(min(radius, reach), dhat)``; pairs farther apart are
            covered by the ``min(d_min, r)``.
        ccd_tolerance: TIGHT_INCLUSION's tolerance.
        dhat_collisions: the barrier's collision set at ``x0`` (within ``dhat``), reused by CONSERVATIVE when
            its query radius is ``dhat``.
    """
    if reach == 0.0:
        return 1.0
    method = StepBound.resolve(method)
    if method is StepBound.CONSERVATIVE:
        r = min(radius, reach)
        if r <= dhat:
            r = dhat  # the barrier's collision set at x0 already holds every pair closer than dhat
            d = minimum_distance(mesh, x0, r, broad_phase, dhat_collisions)
        else:
            d = minimum_distance(mesh, x0, r, broad_phase)
        return min(1.0, safety * min(d, r) / reach)
    narrow = (
        ipctk.AdditiveCCD(max_iterations=ADDITIVE_MAX_ITERATIONS, conservative_rescaling=0.9)
        if method is StepBound.ADDITIVE
        else ipctk.TightInclusionCCD(tolerance=ccd_tolerance, conservative_rescaling=0.8)
    )
    if isinstance(broad_phase, GarmentObstaclePairs):
        return broad_phase.collision_free_stepsize(mesh, x0, x1, narrow, keep_within=dhat)
    cand = ipctk.Candidates()
    cand.build(mesh, x0, x1, 0.0, broad_phase.make())
    if cand.empty():
        return 1.0
    return float(cand.compute_collision_free_stepsize(mesh, x0, x1, 0.0, narrow))


class _IPCEnergy(torch.autograd.Function):
    """E(x) with the ipctk analytic gradient as backward."""

    @staticmethod
    def forward(  # noqa: D102
        ctx: torch.autograd.function.FunctionCtx, x: torch.Tensor, term: "_IPCContact"
    ) -> torch.Tensor:
        if ctx.needs_input_grad[0]:
            e, g = term._value_grad_np(x)
            ctx.save_for_backward(torch.as_tensor(g.reshape(-1, 3), dtype=x.dtype, device=x.device))
        else:
            e = term._value_np(x)
        return torch.as_tensor(e, dtype=x.dtype, device=x.device)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(  # noqa: D102
        ctx: torch.autograd.function.FunctionCtx, grad_out: torch.Tensor
    ) -> tuple[torch.Tensor, None]:
        (g,) = ctx.saved_tensors
        return grad_out * g, None


class _IPCContact(EnergyTerm):
    """Shared machinery: a CollisionMesh whose first vertices are the garment ``x`` (``num_dynamic`` of
    them, or with a :class:`SeamWeld` its ``num_welded`` means), followed by static vertices (a body), which
    never move and get no gradient. ``faces`` and ``rest_positions`` number the collision vertices.
    """

    name = "ipc_contact"
    volatile_hessian = True

    def __init__(
        self,
        faces: np.ndarray,
        rest_positions: np.ndarray,
        num_dynamic: int,
        static_positions: np.ndarray | None,
        dhat: float,
        stiffness: float | None,
        areal_density: float,
        collision_filter: "ipctk.CollisionFilter | None",
        step_bound: StepBound,
        step_safety: float,
        conservative_radius: float | None,
        check_intersections: bool,
        broad_phase: BroadPhase,
        ccd_tolerance: float = 1e-6,
        weld: SeamWeld | None = None,
    ) -> None:
        super().__init__()
        if not (math.isfinite(dhat) and dhat > 0):
            raise InputError(f"dhat must be a positive distance in metres, got {dhat}")
        if not 0 < step_safety < 1:
            raise InputError(f"step_safety must be in (0, 1), got {step_safety}")
        if conservative_radius is not None and not conservative_radius > 0:
            raise InputError(f"conservative_radius must be positive, got {conservative_radius}")
        if not ccd_tolerance > 0:
            raise InputError(f"ccd_tolerance must be positive, got {ccd_tolerance}")
        if areal_density <= 0:
            raise InputError(f"areal_density must be positive, got {areal_density}")
        nv = rest_positions.shape[0]
        if faces.max() >= nv or faces.min() < 0:
            raise MeshError(f"faces index vertices outside [0, {nv})")
        self.dhat = float(dhat)
        self.num_vertices = int(num_dynamic)
        self._weld = weld
        self._num_collision = weld.num_welded if weld is not None else self.num_vertices
        self.step_bound = StepBound.resolve(step_bound)
        self.ccd_tolerance = float(ccd_tolerance)
        self.step_safety = float(step_safety)
        self.conservative_radius = (
            float(conservative_radius) if conservative_radius is not None else float(dhat)
        )
        self.check_intersections = bool(check_intersections)
        self.broad_phase = BroadPhase.resolve(broad_phase)
        self._static = static_positions
        self._mesh = ipctk.CollisionMesh(rest_positions, ipctk.edges(faces), faces)
        if collision_filter is not None:
            self._mesh.can_collide = collision_filter
        self._cache_x: np.ndarray | None = None
        self._cache_col: ipctk.NormalCollisions | None = None
        # intersection-free collision positions (tested, or reached along a step the step bound cleared) and
        # the step :meth:`max_step` last cleared from them: (x0, dx, alpha), see _intersecting
        self._free_x: np.ndarray | None = None
        self._cleared: tuple[np.ndarray, np.ndarray, float] | None = None
        # IPC's minimum stiffness for the mean garment vertex mass (area weighting: mass / mean weight)
        areas = np.asarray(self._mesh.vertex_areas)[: self._num_collision]
        mean_area = float(areas[areas > 0].mean()) if np.any(areas > 0) else 1.0
        self._average_mass = areal_density * mean_area
        self._mean_weight = mean_area
        self._bbox_diagonal = float(ipctk.world_bbox_diagonal_length(rest_positions))
        probe = ipctk.BarrierPotential(self.dhat, 1.0, True)
        zero = np.zeros(3)
        self.min_stiffness, self.max_stiffness = ipctk.initial_barrier_stiffness(
            self._bbox_diagonal, probe.barrier, self.dhat, self._average_mass / self._mean_weight, zero, zero
        )
        if stiffness is not None and not (math.isfinite(stiffness) and stiffness > 0):
            raise InputError(f"stiffness must be a positive pressure in Pa, got {stiffness}")
        self.stiffness = float(stiffness) if stiffness is not None else float(self.min_stiffness)

    # ------------------------------------------------------------------ conversions and caching

    @property
    def stiffness(self) -> float:
        """Barrier stiffness kappa (Pa)."""
        return self._stiffness

    @stiffness.setter
    def stiffness(self, value: float) -> None:
        self._stiffness = float(value)
        self._potential = ipctk.BarrierPotential(self.dhat, self._stiffness, True)

    def _positions(self, x: torch.Tensor) -> np.ndarray:
        if not isinstance(x, torch.Tensor) or x.shape != (self.num_vertices, 3):
            raise InputError(
                f"x must be a ({self.num_vertices}, 3) tensor, got {getattr(x, 'shape', type(x))}"
            )
        xn = x.detach().to("cpu", torch.float64).numpy()
        if not np.isfinite(xn).all():
            raise InputError("x contains non-finite positions")
        if self._weld is not None:
            xn = self._weld.mean @ xn
        if self._static is not None:
            xn = np.concatenate([xn, self._static], axis=0)
        return np.asfortranarray(xn)

    def _bp(self) -> "ipctk.BroadPhase":
        return self.broad_phase.make()

    def _collisions(self, xn: np.ndarray) -> "ipctk.NormalCollisions":
        if self._cache_x is not None and np.array_equal(self._cache_x, xn):
            return self._cache_col
        col = ipctk.NormalCollisions()
        col.use_area_weighting = True
        col.build(self._mesh, xn, self.dhat, 0.0, self._bp())
        self._cache_x, self._cache_col = xn.copy(), col
        return col

    def _intersecting(self, xn: np.ndarray) -> bool:
        """ipctk's intersection test at collision positions ``xn``, skipped where its answer is known: at the
        last positions found free, and along the step :meth:`max_step` last cleared from them (``x0 + a dx``,
        ``0 <= a <= alpha``, up to round-off): every step bound here (CCD or the conservative distance bound)
        proves that the linear motion from a free state crosses nothing. The solvers take every step that
        way, so a solve pays the test once, at its start and after a rollback."""
        if not self.check_intersections:
            return False
        if self._free_x is not None and np.array_equal(self._free_x, xn):
            return False
        if self._cleared is not None and _on_segment(xn, *self._cleared):
            self._free_x = xn.copy()
            return False
        if ipctk.has_intersections(self._mesh, xn, self._bp()):
            return True
        self._free_x = xn.copy()
        return False

    def _value_np(self, x: torch.Tensor) -> float:
        xn = self._positions(x)
        if self._intersecting(xn):
            return math.inf
        return _energy_or_inf(self._potential(self._collisions(xn), self._mesh, xn))

    def _value_grad_np(self, x: torch.Tensor) -> tuple[float, np.ndarray]:
        xn = self._positions(x)
        col = self._collisions(xn)
        g = self._to_garment(np.asarray(self._potential.gradient(col, self._mesh, xn)))
        e = math.inf if self._intersecting(xn) else _energy_or_inf(self._potential(col, self._mesh, xn))
        return e, g

    def _hessian_bsr(self, x: torch.Tensor, project_psd: bool) -> sp.bsr_matrix:
        xn = self._positions(x)
        method = ipctk.PSDProjectionMethod.CLAMP if project_psd else ipctk.PSDProjectionMethod.NONE
        h = self._potential.hessian(self._collisions(xn), self._mesh, xn, method)
        n = 3 * self._num_collision
        if self._static is not None:
            h = h[:n, :n]
        h = sp.csr_matrix(h)
        if self._weld is not None:
            h = self._weld.dof_mean.T @ h @ self._weld.dof_mean
        return h.tobsr(blocksize=(3, 3))

    def _to_garment(self, g: np.ndarray) -> np.ndarray:
        """The garment's (3V,) part of a collision-mesh gradient (3 x collision vertices,)."""
        g = g[: 3 * self._num_collision]
        return self._weld.dof_mean.T @ g if self._weld is not None else g

    # ------------------------------------------------------------------ EnergyTerm contract

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Barrier energy (J), a scalar tensor; +inf when the mesh intersects (with ``check_intersections``).

        Args:
            x: (V, 3) garment positions (m). Differentiable once (ipctk's analytic gradient).
        """
        return _IPCEnergy.apply(x, self)

    def value_and_grad(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Energy () in J and its analytic gradient (V, 3) in N.

        The energy is +inf when the mesh intersects (``check_intersections``); the gradient is then still
        the barrier gradient of the pairs within ``dhat``, which does not undo the crossing.
        """
        e, g = self._value_grad_np(x)
        return (
            torch.as_tensor(e, dtype=x.dtype, device=x.device),
            torch.as_tensor(g.reshape(-1, 3), dtype=x.dtype, device=x.device),
        )

    def hessian_blocks(self, x: torch.Tensor, project_psd: bool = True) -> HessianBlocks:
        """Block-COO Hessian (N/m) over garment vertices; per-collision PSD projection (clamp) when asked."""
        h = self._hessian_bsr(x, project_psd)
        rows = np.repeat(np.arange(h.shape[0] // 3), np.diff(h.indptr))
        dev, dt = x.device, x.dtype
        return HessianBlocks(
            torch.as_tensor(rows, dtype=torch.long, device=dev),
            torch.as_tensor(h.indices.astype(np.int64), device=dev),
            torch.as_tensor(h.data, dtype=dt, device=dev).reshape(-1, 3, 3),
        )

    def hessian_diagonal(self, x: torch.Tensor, project_psd: bool = True) -> torch.Tensor:
        """(V, 3, 3) diagonal blocks of the (by default PSD-projected) Hessian (N/m)."""
        h = self._hessian_bsr(x, project_psd)
        rows = np.repeat(np.arange(h.shape[0] // 3), np.diff(h.indptr))
        diag = rows == h.indices
        out = np.zeros((self.num_vertices, 3, 3))
        out[rows[diag]] = h.data[diag]
        return torch.as_tensor(out, dtype=x.dtype, device=x.device)

    # ------------------------------------------------------------------ step bounds and queries

    def max_step(self, x: torch.Tensor, dx: torch.Tensor, method: StepBound | None = None) -> float:
        """Largest alpha in [0, 1] such that ``x + alpha dx`` stays intersection free (barrier finite).

        ``StepBound.TIGHT_INCLUSION`` / ``ADDITIVE`` use ipctk's CCD (:func:`collision_free_step`).
        ``StepBound.CONSERVATIVE`` returns ``alpha = safety * min(d_min, r) / (2 M)``, ``M = max_i |dx_i|``:
        along a linear trajectory every point of a triangle or edge moves by a convex combination of its
        vertices' displacements, so by at most ``alpha M``; the distance between two primitives therefore
        shrinks by at most ``2 alpha M`` (``alpha M`` against the static body) and stays
        >= (1 - safety) * d_min > 0. Pairs farther apart than ``r = conservative_radius`` are not queried and
        are covered by the ``min(d_min, r)``; with the default ``r = dhat`` the query reuses the barrier's
        collision set at ``x`` (nearly free after ``value_and_grad(x)``) but caps one step's largest vertex
        move at ``safety * dhat / 2``; a larger ``r`` allows longer steps at the cost of a wider query. Since
        the true time of impact is >= d_min / (2M), this bound is below the CCD
        step whenever ``safety <= 0.8`` (CCD's rescaling). Assumes ``x`` is intersection free.

        Args:
            x: (V, 3) positions (m). dx: (V, 3) step (m). method: overrides ``self.step_bound``.
        """
        method = self.step_bound if method is None else StepBound.resolve(method)
        x0 = self._positions(x)
        if dx.shape != x.shape:
            raise InputError(f"dx must have the shape of x {tuple(x.shape)}, got {tuple(dx.shape)}")
        dxn = dx.detach().to("cpu", torch.float64).numpy()
        if not np.isfinite(dxn).all():
            raise InputError("dx contains non-finite values")
        if self._weld is not None:
            dxn = self._weld.mean @ dxn
        reach = 2.0 * float(np.sqrt((dxn * dxn).sum(1)).max(initial=0.0))
        x1 = x0.copy()
        x1[: self._num_collision] += dxn
        from_free = self._free_x is not None and np.array_equal(self._free_x, x0)
        col = (
            self._collisions(x0)
            if method is StepBound.CONSERVATIVE and min(self.conservative_radius, reach) <= self.dhat
            else None
        )
        alpha = collision_free_step(
            self._mesh,
            x0,
            np.asfortranarray(x1),
            method,
            self.broad_phase,
            reach=reach,
            dhat=self.dhat,
            safety=self.step_safety,
            radius=self.conservative_radius,
            ccd_tolerance=self.ccd_tolerance,
            dhat_collisions=col,
        )
        self._cleared = (x0, x1 - x0, alpha) if from_free else None
        return alpha

    def min_distance(self, x: torch.Tensor, max_distance: float | None = None) -> float:
        """Smallest distance (m) between non-adjacent (and non-filtered) primitives, searched within
        ``max_distance`` (default ``dhat``); +inf when no pair is that close."""
        r = self.dhat if max_distance is None else float(max_distance)
        if not r > 0:
            raise InputError(f"max_distance must be positive, got {max_distance}")
        return minimum_distance(self._mesh, self._positions(x), r, self.broad_phase)

    def has_intersections(self, x: torch.Tensor) -> bool:
        """Whether any two (non-filtered) triangles/edges of the collision mesh intersect at ``x``."""
        return bool(ipctk.has_intersections(self._mesh, self._positions(x), self._bp()))

    def calibrate_stiffness(self, x: torch.Tensor, elastic_grad: torch.Tensor) -> float:
        """IPC's adaptive initial stiffness: balance the barrier gradient against the other terms' gradient.

        ``kappa = -<g_b, g_e> / |g_b|^2`` clamped to [min_stiffness, max_stiffness] (ipctk
        initial_barrier_stiffness); sets and returns ``self.stiffness`` (Pa).

        Args:
            x: (V, 3) positions (m). elastic_grad: (V, 3) gradient (N) of the rest of the energy at ``x``.
        """
        if elastic_grad.shape != x.shape:
            raise InputError(f"elastic_grad must have the shape of x {tuple(x.shape)}")
        xn = self._positions(x)
        unit = ipctk.BarrierPotential(self.dhat, 1.0, True)
        gb = np.asarray(unit.gradient(self._collisions(xn), self._mesh, xn))
        if self._weld is not None:  # both gradients on the garment's vertices
            gb = np.concatenate([self._to_garment(gb), gb[3 * self._num_collision:]])
        ge = np.zeros_like(gb)
        ge[: 3 * self.num_vertices] = elastic_grad.detach().to("cpu", torch.float64).numpy().reshape(-1)
        kappa, kmax = ipctk.initial_barrier_stiffness(
            self._bbox_diagonal, unit.barrier, self.dhat, self._average_mass / self._mean_weight, ge, gb
        )
        self.max_stiffness = float(kmax)
        self.stiffness = float(kappa)
        return self.stiffness


class SelfContact(_IPCContact):
    """IPC self-contact of a garment (cloth-cloth, e.g. layered garments).

    Args:
        faces: (F, 3) int triangle vertex indices.
        rest_positions: (V, 3) reference positions (m) for adjacency and the area weights (a (V, 2) flat
            pattern is padded with z = 0).
        dhat: barrier activation distance (m).
        stiffness: kappa (Pa); None = IPC's minimum adaptive stiffness for the mean vertex mass
            (``areal_density`` x mean barycentric vertex area), refine it with :meth:`calibrate_stiffness`.
        num_vertices: V, checked against ``rest_positions`` (None: take it from ``rest_positions``).
        seam_pairs: (S, 2) stitched vertex pairs: contact then works on the welded garment (see the module
            docstring and :class:`SeamWeld`); None: on the mesh as given.
        vertex_panel_ids: (V,) int panel of every vertex (:attr:`GarmentMesh.vertex_panel_ids
            <torchgarment.structures.GarmentMesh.vertex_panel_ids>`): contact then works only *within* each
            panel of an unsewn garment (ipctk's vertex-patch filter, negated), the term then named
            ``"panel_contact"``. No panel can fold through itself while two panels may pass through each
            other: the sewing stage's contact, whose seams draw placed panels together across each other by
            design (without it a GarmentCode shirt's front sleeves at 3 cm folded through themselves at the
            cuffs while sewing, 10 crossings that the welded contact of the settle cannot undo). Not with
            ``seam_pairs``: the two sides of a seam within one panel (a dart) are in contact like any other
            pair. Use an ADDITIVE or TIGHT_INCLUSION ``step_bound`` there: sewing moves panels by up to a
            centimetre per iteration, which the conservative bound caps at ``0.4 dhat``. None: every pair.
        areal_density: kg/m^2, only for the default stiffness.
        step_bound: default :meth:`max_step` method.
        step_safety: fraction of the distance bound used by the conservative step (0 < s < 1).
        conservative_radius: distance (m) up to which the conservative step queries pairs; default dhat.
        check_intersections: report +inf energy when triangles cross (an extra ipctk query per evaluation).
        broad_phase: ipctk broad phase.
        ccd_tolerance: tolerance of the TIGHT_INCLUSION step bound.
    """

    name = "self_contact"

    def __init__(
        self,
        faces: torch.Tensor | np.ndarray,
        rest_positions: torch.Tensor | np.ndarray,
        dhat: float = 2e-3,
        stiffness: float | None = None,
        num_vertices: int | None = None,
        *,
        seam_pairs: torch.Tensor | np.ndarray | None = None,
        vertex_panel_ids: torch.Tensor | np.ndarray | None = None,
        areal_density: float = DEFAULT_AREAL_DENSITY,
        step_bound: StepBound = StepBound.CONSERVATIVE,
        step_safety: float = 0.8,
        conservative_radius: float | None = None,
        check_intersections: bool = True,
        broad_phase: BroadPhase = BroadPhase.LBVH,
        ccd_tolerance: float = 1e-6,
    ) -> None:
        f = _np_faces(faces, "faces")
        rest = _np_points(rest_positions, "rest_positions")
        if num_vertices is not None and num_vertices != rest.shape[0]:
            raise InputError(f"num_vertices={num_vertices} but rest_positions has {rest.shape[0]} rows")
        nv = rest.shape[0]
        weld = _weld(f, seam_pairs, nv)
        within = None
        if vertex_panel_ids is not None:
            if weld is not None:
                raise InputError("SelfContact takes seam_pairs (the sewn garment) or vertex_panel_ids "
                                 "(contact within the panels of the unsewn one), not both")
            within = ~ipctk.make_vertex_patches_filter(_np_panel_ids(vertex_panel_ids, nv))
        super().__init__(
            f if weld is None else weld.faces(f),
            rest if weld is None else np.asfortranarray(weld.mean @ rest),
            nv,
            None,
            dhat,
            stiffness,
            areal_density,
            within,
            step_bound,
            step_safety,
            conservative_radius,
            check_intersections,
            broad_phase,
            ccd_tolerance,
            weld,
        )
        if within is not None:
            self.name = "panel_contact"


def _weld(faces: np.ndarray, seam_pairs: torch.Tensor | np.ndarray | None,
          num_vertices: int) -> SeamWeld | None:
    """The :class:`SeamWeld` of ``seam_pairs`` (checked), None without seams."""
    if faces.size and faces.max() >= num_vertices:
        raise MeshError(f"faces index vertices outside [0, {num_vertices})")
    if seam_pairs is None:
        return None
    pairs = _np_seams(seam_pairs, num_vertices)
    return SeamWeld.of(pairs, num_vertices) if pairs.shape[0] else None


class BodyMeshContact(_IPCContact):
    """IPC contact of a garment against a static body mesh (one ipctk CollisionMesh over garment + body).

    The body vertices follow the garment vertices in the collision mesh and never move; body-body pairs are
    never tested. With ``self_contact=False`` only garment-body pairs are (ipctk vertex-patch filter). With
    ``self_contact`` and ``seam_pairs`` the garment's part is welded (:class:`SeamWeld`).

    Args:
        garment_faces: (F, 3) int garment triangles.
        body_vertices: (B, 3) body positions (m).
        body_faces: (G, 3) int body triangles (indices into ``body_vertices``).
        dhat: barrier activation distance (m).
        stiffness: kappa (Pa) or None (IPC minimum stiffness, see :class:`SelfContact`).
        garment_rest_positions: (V, 3) garment reference positions (area weights, adjacency); required.
        self_contact: also include garment-garment pairs.
        seam_pairs: (S, 2) garment seam pairs: with ``self_contact`` contact works on the welded garment (as
            :class:`SelfContact`); ignored without it (the seams never touch the body across each other).
        Others: as :class:`SelfContact`.
    """

    name = "body_contact"

    def __init__(
        self,
        garment_faces: torch.Tensor | np.ndarray,
        body_vertices: torch.Tensor | np.ndarray,
        body_faces: torch.Tensor | np.ndarray,
        dhat: float = 2e-3,
        stiffness: float | None = None,
        *,
        garment_rest_positions: torch.Tensor | np.ndarray,
        self_contact: bool = False,
        seam_pairs: torch.Tensor | np.ndarray | None = None,
        areal_density: float = DEFAULT_AREAL_DENSITY,
        step_bound: StepBound = StepBound.CONSERVATIVE,
        step_safety: float = 0.8,
        conservative_radius: float | None = None,
        check_intersections: bool = True,
        broad_phase: BroadPhase = BroadPhase.LBVH,
        ccd_tolerance: float = 1e-6,
    ) -> None:
        gf = _np_faces(garment_faces, "garment_faces")
        bf = _np_faces(body_faces, "body_faces")
        grest = _np_points(garment_rest_positions, "garment_rest_positions")
        bv = _np_points(body_vertices, "body_vertices")
        nv, nb = grest.shape[0], bv.shape[0]
        if gf.max() >= nv:
            raise MeshError(f"garment_faces index vertices outside [0, {nv})")
        if bf.max() >= nb or bf.min() < 0:
            raise MeshError(f"body_faces index vertices outside [0, {nb})")
        weld = _weld(gf, seam_pairs, nv) if self_contact else None
        if weld is not None:
            gf, grest = weld.faces(gf), weld.mean @ grest
        nc = grest.shape[0]  # the garment's collision vertices
        faces = np.asfortranarray(np.concatenate([gf, bf + nc]), dtype=np.int32)
        rest = np.asfortranarray(np.concatenate([grest, bv]))
        if self_contact:
            filt = ipctk.make_static_obstacle_filter(nc)
        else:
            filt = ipctk.make_vertex_patches_filter(np.r_[np.zeros(nc, np.int32), np.ones(nb, np.int32)])
        super().__init__(
            faces,
            rest,
            nv,
            np.ascontiguousarray(bv),
            dhat,
            stiffness,
            areal_density,
            filt,
            step_bound,
            step_safety,
            conservative_radius,
            check_intersections,
            broad_phase,
            ccd_tolerance,
            weld,
        )


@dataclass
class ContactStats:
    """Diagnostics of one contact evaluation: pairs within dhat and the minimum distance (units of x)."""

    num_pairs: int
    min_distance: float


class MovingObstacleContact:
    """IPC barrier (ipctk) over garment-self and garment-obstacle pairs, the obstacle moving with a parameter
    t.

    The obstacle (an avatar) is ``shrunk + t (full - shrunk)`` (retargeting's inflation), or fixed at ``full``
    when ``obstacle_shrunk`` is None. One ipctk CollisionMesh holds the garment (first N vertices) and the
    obstacle; obstacle-obstacle pairs are filtered out (it may be messy: self-intersecting, degenerate). The
    energy is ``kappa * sum_k b(d_k)`` with ipctk's barrier on squared distances,
    ``b = -(d^2 - dhat^2)^2 ln(d^2 / dhat^2)`` (no area weighting), and kappa (:attr:`stiffness`) chosen
    adaptively (:meth:`initial_stiffness`, :meth:`update_stiffness`). Lengths are in the units of ``x``.
    Candidate pairs come from a :class:`~torchgarment.sim.obstacle_pairs.GarmentObstaclePairs`
    (:attr:`pairs`): the garment's own by ipctk's ``broad_phase``, the garment-obstacle ones by BVHs over the
    obstacle queried by the garment, so the obstacle's own overlaps are never traversed (the barrier, the
    step bounds, the distance queries; the intersection check keeps ipctk's broad phase).

    This is the numpy-level machinery (positions in, floats and arrays out); the retargeting's
    :class:`~torchgarment.retarget.objectives.Contact` is the :class:`EnergyTerm` built on it.

    Args:
        garment_rest: (N, 3) garment rest positions (adjacency). garment_faces: (F, 3) int.
        obstacle_full: (A, 3) obstacle at t = 1. obstacle_faces: (G, 3) int.
        obstacle_shrunk: (A, 3) obstacle at t = 0, or None (fixed obstacle).
        dhat: activation distance. stiffness: initial kappa.
        broad_phase: :class:`BroadPhase` (or an ipctk class name such as "LBVH") of the garment-garment pairs
            and of the intersection check.
        cull_radius: when given (>= 4 dhat), the collision mesh keeps only the obstacle faces that may lie
            within
            this distance of the garment (see :meth:`_recull`), re-culled whenever the garment or the obstacle
            has moved by half of it; every query stays exact because dropped faces are farther than
            cull_radius / 2 > dhat. :meth:`prepare_step` makes a step's CCD valid.
        ccd_tolerance: tolerance of the TIGHT_INCLUSION step bound.
    """

    def __init__(
        self,
        garment_rest: torch.Tensor,
        garment_faces: torch.Tensor,
        obstacle_full: torch.Tensor,
        obstacle_faces: torch.Tensor,
        obstacle_shrunk: torch.Tensor | None,
        dhat: float,
        stiffness: float = 1.0,
        broad_phase: BroadPhase | str = BroadPhase.LBVH,
        cull_radius: float | None = None,
        ccd_tolerance: float = 1e-3,
    ) -> None:
        if not (math.isfinite(dhat) and dhat > 0):
            raise InputError(f"dhat must be positive, got {dhat}")
        if cull_radius is not None and not cull_radius >= 4 * dhat:
            raise InputError(f"cull_radius must be at least 4 dhat = {4 * dhat:.3g}, got {cull_radius}")
        self.uses_t = obstacle_shrunk is not None
        n = garment_rest.shape[0]
        self._gf = garment_faces.cpu().numpy().astype(np.int32)
        self._af_all = obstacle_faces.cpu().numpy().astype(np.int32)
        full = obstacle_full.detach().to("cpu", torch.float64).numpy()
        self.num_garment = int(n)
        self.dhat = float(dhat)
        self.cull_radius = None if cull_radius is None else float(cull_radius)
        self.ccd_tolerance = float(ccd_tolerance)
        self._garment_rest = garment_rest.detach().to("cpu", torch.float64).numpy()
        self._full_all = full
        self._delta_all = (
            (full - obstacle_shrunk.detach().to("cpu", torch.float64).numpy())
            if self.uses_t
            else np.zeros_like(full)
        )
        self._shrunk_all = full - self._delta_all
        #: largest obstacle vertex displacement per unit of t
        self.delta_max = float(np.sqrt((self._delta_all**2).sum(1)).max(initial=0.0))
        self.broad_phase = BroadPhase.resolve(broad_phase)
        self.stiffness = float(stiffness)
        self.max_stiffness = float(stiffness)
        self.bbox_diagonal = float(
            ipctk.world_bbox_diagonal_length(np.concatenate([self._garment_rest, full]))
        )
        self.last_stats = ContactStats(0, math.inf)
        self.num_culls = 0
        self._ref_x: np.ndarray | None = None
        self._ref_t = 0.0
        self._set_subset(np.arange(full.shape[0]), self._af_all)

    # ------------------------------------------------------------------ obstacle culling
    def _set_subset(self, verts: np.ndarray, faces: np.ndarray) -> None:
        """Use obstacle vertices ``verts`` and faces ``faces`` (indices into all obstacle vertices)."""
        n = self.num_garment
        remap = np.full(self._full_all.shape[0], -1, dtype=np.int64)
        remap[verts] = np.arange(verts.shape[0])
        af = remap[faces].astype(np.int32).reshape(-1, 3)
        self._full = self._full_all[verts]
        self.delta = self._delta_all[verts]
        self._shrunk = self._shrunk_all[verts]
        #: the candidate pairs' finder; it numbers :attr:`mesh`
        self.pairs = GarmentObstaclePairs(
            self._garment_rest, self._gf, af, verts.shape[0], self.broad_phase.make
        )
        rest = np.asfortranarray(np.concatenate([self._garment_rest, self._full]))
        self.mesh = ipctk.CollisionMesh(rest, self.pairs.mesh_edges(), self.pairs.mesh_faces())
        self.mesh.can_collide = ipctk.make_static_obstacle_filter(n)
        self._faces = faces
        self._cache_key: bytes | None = None
        self._cache_col = None

    def _motion(self, xn: np.ndarray, t: float) -> float:
        """Largest garment + obstacle displacement since the last cull (units of x)."""
        if self._ref_x is None:
            return math.inf
        return (
            float(np.sqrt(((xn - self._ref_x) ** 2).sum(1)).max(initial=0.0))
            + abs(t - self._ref_t) * self.delta_max
        )

    def _recull(self, xn: np.ndarray, t: float) -> None:
        """Keep the obstacle faces that may come within ``cull_radius`` of the garment at (xn, t).

        A point p of an obstacle face F and a point q of a garment triangle T satisfy
        ``|p - q| >= |v - w| - |p - v| - |q - w| >= dnear(v) - L_F - L_T`` for every vertex v of F and any
        vertex w of T (dnear the distance from v to the nearest garment vertex; the longest edge L of a
        triangle bounds
        the distance from a vertex to any point of it). F is dropped only when
        ``max_v dnear(v) - L_F - L_g > cull_radius`` (L_g the longest garment edge), so every dropped face is
        farther than cull_radius from the garment.
        """
        from scipy.spatial import cKDTree

        r = self.cull_radius
        a = self._shrunk_all + t * self._delta_all if self.uses_t else self._full_all
        dnear, _ = cKDTree(xn).query(a, k=1)
        fa = a[self._af_all]  # (G, 3, 3)
        le_f = np.sqrt(((fa - fa[:, [1, 2, 0]]) ** 2).sum(-1)).max(1)
        ga = xn[self._gf]
        le_g = float(np.sqrt(((ga - ga[:, [1, 2, 0]]) ** 2).sum(-1)).max(initial=0.0))
        keep = dnear[self._af_all].max(1) - le_f - le_g <= r
        faces = self._af_all[keep]
        # the same faces make the same collision mesh: keep it (often the case after small moves; a mesh
        # holding more faces would be valid too, but the broad phase's order, and so the run's round-off,
        # would change)
        if not np.array_equal(faces, self._faces):
            self._set_subset(np.unique(faces.reshape(-1)), faces)
        self._ref_x, self._ref_t = xn.copy(), float(t)
        self.num_culls += 1

    def _ensure(self, xn: np.ndarray, t: float) -> None:
        """Re-cull when the motion since the last cull could bring a dropped face within cull_radius / 2."""
        if self.cull_radius is not None and self._motion(xn, t) > 0.5 * self.cull_radius:
            self._recull(xn, t)

    def prepare_step(self, x: torch.Tensor | np.ndarray, t: float, dx: np.ndarray, dt: float) -> float:
        """Make the culled mesh valid along ``(x + a dx, t + a dt)`` and return the largest valid ``a <= 1``.

        Along the returned range every dropped face stays farther than cull_radius / 2 from the garment, so a
        CCD or distance query on the culled mesh is exact for the segment. Without culling returns 1.
        """
        if self.cull_radius is None:
            return 1.0
        xn = _garment_np(x)
        step = float(np.sqrt((dx * dx).sum(1)).max(initial=0.0)) + abs(dt) * self.delta_max
        budget = 0.5 * self.cull_radius
        if self._motion(xn, t) + step > budget:
            self._recull(xn, t)
        return 1.0 if step <= budget else budget / step

    # ------------------------------------------------------------------ state
    @property
    def stiffness(self) -> float:
        """kappa (energy units of the other terms per barrier unit)."""
        return self._kappa

    @stiffness.setter
    def stiffness(self, value: float) -> None:
        if not (math.isfinite(value) and value > 0):
            raise InputError(f"barrier stiffness must be positive, got {value}")
        self._kappa = float(value)
        self._potential = ipctk.BarrierPotential(self.dhat, self._kappa, False)

    def positions(self, x: torch.Tensor | np.ndarray, t: float, ensure: bool = True) -> np.ndarray:
        """(N + A', 3) collision-mesh positions (Fortran order) for garment ``x`` (N, 3) and parameter ``t``.

        With culling the obstacle part holds the kept vertices; ``ensure`` re-culls first when needed.
        """
        xn = _garment_np(x)
        if ensure:
            self._ensure(xn, float(t))
        return np.asfortranarray(np.concatenate([xn, self.obstacle_at(t)]))

    def obstacle_at(self, t: float) -> np.ndarray:
        """(A', 3) positions of the obstacle vertices in the collision mesh at ``t``."""
        return self._full if not self.uses_t or float(t) == 1.0 else self._shrunk + float(t) * self.delta

    def collisions(self, xa: np.ndarray) -> "ipctk.NormalCollisions":
        """Pairs closer than dhat at collision-mesh positions ``xa`` (cached on the last positions)."""
        key = xa.tobytes()
        if self._cache_key == key:
            return self._cache_col
        col = build_collisions(self.mesh, xa, self.dhat, self.pairs)
        self._cache_key, self._cache_col = key, col
        return col

    # ------------------------------------------------------------------ energy and derivatives
    def value(self, x: torch.Tensor | np.ndarray, t: float) -> float:
        """Energy only (+inf when two primitives touch)."""
        xa = self.positions(x, t)
        return _energy_or_inf(self._potential(self.collisions(xa), self.mesh, xa))

    def value_grad(self, x: torch.Tensor | np.ndarray, t: float) -> tuple[float, np.ndarray, float]:
        """Energy, gradient (N, 3) in x and derivative in t; records :attr:`last_stats`."""
        xa = self.positions(x, t)
        col = self.collisions(xa)
        e = _energy_or_inf(self._potential(col, self.mesh, xa))
        g = np.asarray(self._potential.gradient(col, self.mesh, xa)).reshape(-1, 3)
        n = self.num_garment
        gt = float((g[n:] * self.delta).sum()) if self.uses_t else 0.0
        self.last_stats = ContactStats(
            len(col), minimum_distance(self.mesh, xa, self.dhat, self.pairs, col)
        )
        return e, g[:n], gt

    def unit_barrier_gradient(self, x: torch.Tensor | np.ndarray, t: float) -> np.ndarray:
        """(3N + 1,) gradient of the barrier sum with kappa = 1 over ``[x.flatten(), t]``."""
        xa = self.positions(x, t)
        g = np.asarray(
            ipctk.BarrierPotential(self.dhat, 1.0, False).gradient(self.collisions(xa), self.mesh, xa)
        ).reshape(-1, 3)
        n = self.num_garment
        gt = float((g[n:] * self.delta).sum()) if self.uses_t else 0.0
        return np.r_[g[:n].reshape(-1), gt]

    def hessian(
        self, x: torch.Tensor | np.ndarray, t: float, project_psd: bool = True
    ) -> tuple[sp.csr_matrix, np.ndarray, float]:
        """Hessian over ``[x.flatten(), t]`` from ipctk's per-pair Hessians (PSD-clamped when
        ``project_psd``).

        Returns:
            ``(h_xx, h_xt, h_tt)``: the (3N, 3N) CSR block, the (3N,) coupling column (zero when the obstacle
            is fixed) and the t-t entry.
        """
        xa = self.positions(x, t)
        method = ipctk.PSDProjectionMethod.CLAMP if project_psd else ipctk.PSDProjectionMethod.NONE
        h = sp.csr_matrix(self._potential.hessian(self.collisions(xa), self.mesh, xa, method))
        n3 = 3 * self.num_garment
        hxx = h[:n3, :n3]
        if not self.uses_t:
            return hxx, np.zeros(n3), 0.0
        d = self.delta.reshape(-1)
        hxt = np.asarray(h[:n3, n3:] @ d).reshape(-1)
        htt = float(d @ (h[n3:, n3:] @ d))
        return hxx, hxt, htt

    # ------------------------------------------------------------------ stiffness
    def initial_stiffness(
        self, x: torch.Tensor | np.ndarray, t: float, other_grad: np.ndarray, average_mass: float
    ) -> float:
        """IPC's adaptive initial barrier stiffness (ipctk.initial_barrier_stiffness): balances the barrier
        gradient against ``other_grad`` (3N + 1,), the gradient of all other terms over ``[x, t]``; sets
        :attr:`stiffness` and :attr:`max_stiffness` and returns the stiffness."""
        gb = self.unit_barrier_gradient(x, t)
        bar = ipctk.BarrierPotential(self.dhat, 1.0, False)
        kappa, kmax = ipctk.initial_barrier_stiffness(
            self.bbox_diagonal,
            bar.barrier,
            self.dhat,
            float(average_mass),
            np.asarray(other_grad, np.float64),
            np.asarray(gb, np.float64),
        )
        self.max_stiffness = float(kmax)
        self.stiffness = float(kappa)
        return self.stiffness

    def update_stiffness(
        self, prev_min_distance: float, min_distance: float, stiffness_distance: float
    ) -> bool:
        """IPC's stiffness update (ipctk.update_barrier_stiffness): doubles kappa, up to its maximum, while
        the minimum distance decreases below ``stiffness_distance * dhat``; returns whether kappa changed.

        The distances are in the units of x; ipctk compares squared distances with its squared threshold, so
        they are squared here."""
        if not (math.isfinite(min_distance) and math.isfinite(prev_min_distance)):
            return False
        kappa = ipctk.update_barrier_stiffness(
            prev_min_distance * prev_min_distance,
            min_distance * min_distance,
            max(self.max_stiffness, self.stiffness),
            self.stiffness,
            self.bbox_diagonal,
            stiffness_distance * self.dhat / self.bbox_diagonal,
        )
        if kappa == self.stiffness:
            return False
        self.stiffness = kappa
        return True

    # ------------------------------------------------------------------ queries
    def max_step(
        self, x: torch.Tensor | np.ndarray, t: float, dx: np.ndarray, dt: float, method: StepBound | str
    ) -> float:
        """Largest alpha in [0, 1] (conservative) such that ``(x + a dx, t + a dt)`` stays intersection free.

        Args:
            x: (N, 3) garment; t: parameter; dx: (N, 3) step; dt: step of t. method: :class:`StepBound`
            (CONSERVATIVE queries pairs within ``max(dhat, reach)``, safety 0.8).
        """
        x0 = _garment_np(x)
        cap = self.prepare_step(x0, t, dx, dt)
        if cap < 1.0:
            return cap * self.max_step(x0, t, cap * dx, cap * dt, method)
        a0 = self.obstacle_at(t)
        da = self.delta * dt if self.uses_t else np.zeros_like(a0)
        mg = float(np.sqrt((dx * dx).sum(1)).max(initial=0.0))
        ma = float(np.sqrt((da * da).sum(1)).max(initial=0.0))
        X0 = np.asfortranarray(np.concatenate([x0, a0]))
        X1 = np.asfortranarray(np.concatenate([x0 + dx, a0 + da]))
        return collision_free_step(
            self.mesh,
            X0,
            X1,
            method,
            self.pairs,
            reach=mg + max(mg, ma),
            dhat=self.dhat,
            safety=0.8,
            ccd_tolerance=self.ccd_tolerance,
        )

    def is_step_free(self, x: torch.Tensor | np.ndarray, t0: float, t1: float, min_distance: float) -> bool:
        """Tight-Inclusion CCD (tolerance 1e-6): does moving the obstacle from ``t0`` to ``t1`` with the
        garment fixed keep every garment-obstacle pair at least ``min_distance`` apart? (The garment's own
        pairs do not move; they are not checked.)"""
        x0 = self.positions(x, t0)
        x1 = self.positions(x, t1)
        ccd = ipctk.TightInclusionCCD(tolerance=1e-6, conservative_rescaling=0.8)
        return self.pairs.is_step_collision_free(self.mesh, x0, x1, float(min_distance), ccd)

    def min_distance(self, x: torch.Tensor | np.ndarray, t: float, max_distance: float) -> float:
        """Smallest garment-self / garment-obstacle distance within ``max_distance`` (+inf if none)."""
        return minimum_distance(self.mesh, self.positions(x, t), float(max_distance), self.pairs)

    def has_intersections(self, x: torch.Tensor | np.ndarray, t: float) -> bool:
        """Whether garment triangles cross each other or the obstacle (obstacle-obstacle crossings
        ignored)."""
        xa = self.positions(x, t)  # may re-cull: take self.mesh afterwards
        return bool(ipctk.has_intersections(self.mesh, xa, self.broad_phase.make()))


def _garment_np(x: torch.Tensor | np.ndarray) -> np.ndarray:
    """(N, 3) float64 numpy copy-free view of garment positions."""
    return x.detach().to("cpu", torch.float64).numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
