"""Boundary parametrization of a sewing pattern (Wang et al. 2018, section 5, Eq. 7-8).

Each panel is controlled by its boundary vertices ``q`` (B, 2); the interior vertices follow from the
pre-factorized Laplacian system of Eq. 8::

    p_I = p̄_I - L_II^{-1} L_IB (q - q̄),        p_B = q,

where ``L`` is a Laplacian of the base pattern ``p̄`` (all panels at once: panels share no vertices, so the
system is block diagonal, i.e. solved per panel). The map ``q -> p`` is affine with a constant matrix, so its
backward pass is the transposed solve.

Laplacian weights (:class:`LaplacianWeights`):

* ``cotangent`` (default): the cotangent weights ``(cot a + cot b) / 2`` of the flat pattern, the weights of
  the hinge-edge kernel of Bergou et al. 2006 that the paper names; ``L_II`` is symmetric positive definite as
  the paper states. On a planar mesh the cotangent Laplacian of a linear function vanishes at interior
  vertices, so the map reproduces affine maps of the boundary exactly.
* ``mean_value``: Floater's mean value weights (the paper notes the scheme is equivalent to positive mean
  value coordinates); also reproduces affine maps, weights always positive (no fold-over for convex
  one-rings), ``L_II`` non-symmetric.
* ``uniform``: graph Laplacian; does NOT reproduce affine maps (only translations).

Seams: the two sides of a seam are separate boundary vertices (both are variables). Their consistency (equal
stitched lengths up to the base pattern's gathering ratio) is the job of
:class:`torchgarment.adjust.regularizers.SeamLengthRegularizer`; this module exposes the stitched boundary
edge pairs (:attr:`BoundaryParametrization.seam_edge_pairs`) it needs. A hard tie is impossible in a linear
parametrization of two panels with different shapes, so the constraint is soft (like every term of the paper).

Solve modes (:class:`ParametrizationSolve`): ``factorized`` keeps a sparse factorization of ``L_II`` (CPU,
two triangular solves per call); ``explicit`` precomputes the block-diagonal dense operator
``-L_II^{-1} L_IB`` per panel and applies it as a sparse matrix product (stays on the device, memory
``sum_k I_k B_k``); ``auto`` picks ``factorized`` on the CPU and ``explicit`` on other devices when it has at
most :data:`EXPLICIT_MAX_ENTRIES` entries. Measured on a 16K-vertex dress (736 boundary vertices, 2 panels,
2 loaded CPU cores): factorized 1.8 s to build and 16 ms per forward + backward, explicit 39 s to build and
83 ms per forward + backward, hence the CPU default.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import scipy.sparse
import torch

from torchgarment.adjust.linear_map import StoredTransposeMatmul
from torchgarment.errors import MeshError
from torchgarment.linalg import factorize
from torchgarment.options import OptionEnum
from torchgarment.structures.garment_mesh import GarmentMesh

EXPLICIT_MAX_ENTRIES = 40_000_000
"""``auto`` uses the explicit operator up to this many stored entries (320 MB in float64)."""

DEFAULT_CORNER_ANGLE = math.radians(30.0)
"""A boundary vertex whose outline turns by more than this is a corner (radians)."""


class LaplacianWeights(OptionEnum):
    """Weights of the pattern Laplacian of Eq. 7 (see the module docstring)."""

    COTANGENT = "cotangent"
    MEAN_VALUE = "mean_value"
    UNIFORM = "uniform"

    @classmethod
    def aliases(cls) -> dict[str, str]:
        return {"cot": "cotangent", "mvc": "mean_value", "mean-value": "mean_value", "graph": "uniform"}


class ParametrizationSolve(OptionEnum):
    """How the interior solve of Eq. 8 is applied (see the module docstring)."""

    AUTO = "auto"
    FACTORIZED = "factorized"
    EXPLICIT = "explicit"


def pattern_laplacian(p: np.ndarray, faces: np.ndarray, weights: LaplacianWeights | str = "cotangent"
                      ) -> scipy.sparse.csr_matrix:
    """Laplacian ``L = D - W`` of a flat triangle mesh (rows sum to zero, positive diagonal).

    Args:
        p: (V, 2) vertex positions (metres).
        faces: (F, 3) vertex indices.
        weights: :class:`LaplacianWeights` or its name.

    Returns:
        (V, V) csr matrix; ``(L u)_i = sum_j w_ij (u_i - u_j)``.
    """
    kind = LaplacianWeights.resolve(weights)
    V = p.shape[0]
    f = np.asarray(faces, dtype=np.int64)
    rows, cols, vals = [], [], []
    for k in range(3):
        i, j, m = f[:, k], f[:, (k + 1) % 3], f[:, (k + 2) % 3]
        if kind is LaplacianWeights.UNIFORM:
            # every edge appears in one or two faces; 0.5 per face side then clipped to 1 below
            rows += [i, j]
            cols += [j, i]
            vals += [np.full(len(i), 1.0), np.full(len(i), 1.0)]
        elif kind is LaplacianWeights.COTANGENT:
            # angle at m is opposite edge (i, j)
            u, v = p[i] - p[m], p[j] - p[m]
            cross = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
            cot = (u * v).sum(1) / np.abs(cross)
            rows += [i, j]
            cols += [j, i]
            vals += [0.5 * cot, 0.5 * cot]
        else:  # mean value: row i gets tan(theta_i / 2) / |p_i - p_j| for both face edges at i
            a, b = p[j] - p[i], p[m] - p[i]
            la, lb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
            cos = np.clip((a * b).sum(1) / (la * lb), -1.0, 1.0)
            t = np.tan(0.5 * np.arccos(cos))
            rows += [i, i]
            cols += [j, m]
            vals += [t / la, t / lb]
    W = scipy.sparse.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                                shape=(V, V)).tocsr()
    if kind is LaplacianWeights.UNIFORM:
        W.data[:] = 1.0  # duplicates summed: an interior edge counted twice
    W.sum_duplicates()
    L = scipy.sparse.diags(np.asarray(W.sum(axis=1)).ravel()) - W
    return L.tocsr()


class _FactorizedMap(torch.autograd.Function):
    """``d_I = M d_B`` (``transpose``: ``M^T g_I``) with ``M = -L_II^{-1} L_IB`` through a factorization.

    The backward of each direction is the other direction, so double backward works (the map is linear).
    """

    @staticmethod
    def forward(ctx: torch.autograd.function.FunctionCtx, v: torch.Tensor, param: "BoundaryParametrization",  # type: ignore[override]
                transpose: bool) -> torch.Tensor:
        ctx.param, ctx.transpose = param, transpose
        vn = v.detach().cpu().numpy()
        if transpose:
            y = param._lu.solve(np.ascontiguousarray(vn), transpose=True) if vn.shape[0] else vn
            out = -(param._L_IB.T @ y)
        else:
            rhs = -(param._L_IB @ vn)
            out = param._lu.solve(np.ascontiguousarray(rhs)) if rhs.shape[0] else rhs
        return torch.as_tensor(out, dtype=v.dtype, device=v.device)

    @staticmethod
    def backward(ctx: torch.autograd.function.FunctionCtx,  # type: ignore[override]
                 g: torch.Tensor) -> tuple[torch.Tensor, None, None]:
        return _FactorizedMap.apply(g.contiguous(), ctx.param, not ctx.transpose), None, None


class BoundaryParametrization(torch.nn.Module):
    """Pattern positions ``p`` (V, 2) from boundary positions ``q`` (B, 2) by Eq. 8 (affine, differentiable).

    Attributes:
        boundary_index: (B,) long, the boundary vertices (the variables), loop by loop (each panel outline and
            hole in face orientation), so that ``q[k]``'s outline neighbours are
            :attr:`boundary_prev`/``next``.
        interior_index: (I,) long, the other vertices.
        boundary_prev, boundary_next: (B,) long, positions in ``q`` of the previous/next vertex of the loop.
        corner_mask: (B,) bool, panel corners (outline turning by more than ``corner_angle`` or a change of
            the seam the outline is stitched to).
        seam_edge_pairs: (K, 4) long positions in ``q`` ``[a0, a1, b0, b1]``: boundary edge ``a0-a1`` is
            stitched to boundary edge ``b0-b1`` (``a0`` paired with ``b0``), each pair of edges once.
        p_base: buffer (V, 2), the base pattern ``mesh.p``.
        weights: the :class:`LaplacianWeights` used. solve: the :class:`ParametrizationSolve` used.
    """

    boundary_index: torch.Tensor
    interior_index: torch.Tensor
    boundary_prev: torch.Tensor
    boundary_next: torch.Tensor
    corner_mask: torch.Tensor
    seam_edge_pairs: torch.Tensor
    p_base: torch.Tensor

    def __init__(self, mesh: GarmentMesh, *, dtype: torch.dtype | None = None,
                 device: torch.device | str | None = None, weights: LaplacianWeights | str = "cotangent",
                 solve: ParametrizationSolve | str = "auto", corner_angle: float = DEFAULT_CORNER_ANGLE,
                 corners: torch.Tensor | None = None) -> None:
        """Build the Laplacian of the base pattern and factorize (or invert per panel) its interior block.

        Args:
            mesh: a pattern mesh (with ``p``; every vertex used by a face).
            dtype, device: of ``q``/``p`` (default: those of ``mesh.p``).
            weights: Laplacian weights (default cotangent; see the module docstring).
            solve: ``auto``, ``factorized`` or ``explicit`` (see the module docstring).
            corner_angle: turning angle (radians) above which a boundary vertex is a corner.
            corners: optional (V,) bool mask of corner vertices overriding the automatic detection.

        Raises:
            MeshError: no pattern positions, unreferenced vertices, or a non-manifold boundary.
        """
        super().__init__()
        if mesh.p is None:
            raise MeshError("BoundaryParametrization needs a pattern mesh (mesh.p is None)")
        dtype = dtype or mesh.p.dtype
        device = torch.device(device) if device is not None else mesh.p.device
        self.weights = LaplacianWeights.resolve(weights)
        V = mesh.num_vertices
        faces = mesh.faces.detach().cpu().numpy()
        p = mesh.p.detach().cpu().double().numpy()
        used = np.zeros(V, dtype=bool)
        used[faces.reshape(-1)] = True
        if not used.all():
            raise MeshError(f"{int((~used).sum())} vertices are not used by any face "
                            f"(first {int(np.argmin(used))})")
        loops = [lp.cpu().numpy() for lp in mesh.boundary_loops]
        if not loops:
            raise MeshError("the pattern mesh has no boundary")
        bidx = np.concatenate(loops)
        starts = np.cumsum([0] + [len(lp) for lp in loops])
        pos = np.arange(len(bidx))
        prev = np.concatenate([np.roll(np.arange(s, e), 1) for s, e in zip(starts[:-1], starts[1:])])
        nxt = np.concatenate([np.roll(np.arange(s, e), -1) for s, e in zip(starts[:-1], starts[1:])])
        is_b = np.zeros(V, dtype=bool)
        is_b[bidx] = True
        iidx = np.nonzero(~is_b)[0]
        slot = np.full(V, -1, dtype=np.int64)
        slot[bidx] = pos

        # ---- Laplacian blocks
        L = pattern_laplacian(p, faces, self.weights)
        L_II = L[iidx][:, iidx].tocsc()
        self._L_IB = L[iidx][:, bidx].tocsr()
        mode = ParametrizationSolve.resolve(solve)
        panel = (mesh.vertex_panel_ids.cpu().numpy() if mesh.panel_ids is not None
                 else np.zeros(V, dtype=np.int64))
        if mode is ParametrizationSolve.AUTO:
            entries = sum(int((panel[iidx] == k).sum()) * int((panel[bidx] == k).sum())
                          for k in np.unique(panel))
            mode = ParametrizationSolve.EXPLICIT if device.type != "cpu" and entries <= EXPLICIT_MAX_ENTRIES \
                else ParametrizationSolve.FACTORIZED
        self.solve = mode
        self._L_II = L_II
        self._lu = factorize(L_II, symmetric=False, what="interior Laplacian") if len(iidx) else None
        if mode is ParametrizationSolve.EXPLICIT:
            M = self._explicit_operator(L_II.tocsr(), panel, iidx, bidx)
            self.register_buffer("_M", _torch_csr(M, dtype, device), persistent=False)
            self.register_buffer("_MT", _torch_csr(M.T.tocsr(), dtype, device), persistent=False)

        # ---- corners and seams
        seam_pairs = mesh.seam_pairs.cpu().numpy()
        pairs_q = self._seam_edge_pairs(bidx, slot, nxt, seam_pairs)
        if corners is not None:
            cm = corners.detach().cpu().numpy().astype(bool)[bidx]
        else:
            cm = (_corner_mask(p[bidx], prev, nxt, corner_angle)
                  | _seam_change_mask(pairs_q, panel[bidx], prev, len(bidx)))

        kw = dict(dtype=torch.long, device=device)
        self.register_buffer("boundary_index", torch.as_tensor(bidx, **kw))
        self.register_buffer("interior_index", torch.as_tensor(iidx, **kw))
        self.register_buffer("boundary_prev", torch.as_tensor(prev, **kw))
        self.register_buffer("boundary_next", torch.as_tensor(nxt, **kw))
        self.register_buffer("corner_mask", torch.as_tensor(cm, dtype=torch.bool, device=device))
        self.register_buffer("seam_edge_pairs", torch.as_tensor(pairs_q.reshape(-1, 4), **kw))
        self.register_buffer("p_base", torch.as_tensor(p, dtype=dtype, device=device))
        self.num_vertices = V

    # ------------------------------------------------------------------ pickling
    def __getstate__(self) -> dict:
        """Pickle without the factorization (not picklable); :meth:`__setstate__` factorizes ``L_II``
        again."""
        state = self.__dict__.copy()
        state["_lu"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        super().__setstate__(state)
        if self._L_II.shape[0]:
            self._lu = factorize(self._L_II, symmetric=False, what="interior Laplacian")

    # ------------------------------------------------------------------ construction helpers
    def _explicit_operator(self, L_II: scipy.sparse.csr_matrix, panel: np.ndarray, iidx: np.ndarray,
                           bidx: np.ndarray) -> scipy.sparse.csr_matrix:
        """Block-diagonal ``-L_II^{-1} L_IB`` (I, B) with one dense block per panel."""
        pi, pb = panel[iidx], panel[bidx]
        rows, cols, vals = [], [], []
        for k in np.unique(pi):
            ri = np.nonzero(pi == k)[0]
            cb = np.nonzero(pb == k)[0]
            if not len(cb):
                raise MeshError(f"panel {k} has interior vertices but no boundary")
            rhs = -self._L_IB[ri][:, cb].toarray()
            # panels share no vertices, so the panel's rows/columns of L_II are its own system
            blk = factorize(L_II[ri][:, ri].tocsc(), symmetric=False, what="panel Laplacian").solve(
                np.ascontiguousarray(rhs))
            rr, cc = np.meshgrid(ri, cb, indexing="ij")
            rows.append(rr.ravel())
            cols.append(cc.ravel())
            vals.append(blk.ravel())
        if not rows:
            return scipy.sparse.csr_matrix((len(iidx), len(bidx)))
        return scipy.sparse.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                                       shape=(len(iidx), len(bidx))).tocsr()

    @staticmethod
    def _seam_edge_pairs(bidx: np.ndarray, slot: np.ndarray, nxt: np.ndarray,
                         seam_pairs: np.ndarray) -> np.ndarray:
        """(K, 4) positions in q of stitched boundary edge pairs ``[a0, a1, b0, b1]``."""
        if seam_pairs.shape[0] == 0:
            return np.zeros((0, 4), dtype=np.int64)
        partners: dict[int, set[int]] = {}
        for u, v in seam_pairs.tolist():
            partners.setdefault(u, set()).add(v)
            partners.setdefault(v, set()).add(u)
        # directed boundary edges a0 -> a1 in q positions, keyed by their vertex pair
        a0 = np.arange(len(bidx))
        a1 = nxt
        edge_of = {}
        for s, t in zip(a0.tolist(), a1.tolist()):
            edge_of[(int(bidx[s]), int(bidx[t]))] = (s, t)
        out = []
        seen = set()
        for s, t in zip(a0.tolist(), a1.tolist()):
            u, v = int(bidx[s]), int(bidx[t])
            for u2 in partners.get(u, ()):
                for v2 in partners.get(v, ()):
                    e = edge_of.get((u2, v2)) or edge_of.get((v2, u2))
                    if e is None:
                        continue
                    b0, b1 = (slot[u2], slot[v2])
                    key = frozenset((tuple(sorted((s, t))), tuple(sorted((int(b0), int(b1))))))
                    if key in seen:
                        continue
                    seen.add(key)
                    out.append((s, t, int(b0), int(b1)))
        return np.asarray(out, dtype=np.int64).reshape(-1, 4)

    # ------------------------------------------------------------------ API
    @property
    def num_boundary(self) -> int:
        """B, the number of boundary vertices."""
        return int(self.boundary_index.shape[0])

    def initial(self) -> torch.Tensor:
        """(B, 2) boundary positions of the base pattern (``mesh.p[boundary_index]``)."""
        return self.p_base[self.boundary_index].clone()

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        """Pattern positions from boundary positions.

        Args:
            q: (B, 2) boundary positions in metres (same order as :attr:`boundary_index`).

        Returns:
            (V, 2) pattern positions: ``p[boundary_index] = q``, interior vertices by Eq. 8.
        """
        if q.shape != (self.num_boundary, 2):
            raise MeshError(f"q must be ({self.num_boundary}, 2), got {tuple(q.shape)}")
        return self.p_base.to(q.dtype) + self.linear(q - self.p_base[self.boundary_index].to(q.dtype))

    def linear(self, dq: torch.Tensor) -> torch.Tensor:
        """(V, 2) ``dp = (dp/dq) dq`` for a boundary displacement ``dq`` (B, 2) (the map is affine).

        Differentiable to any order; ``torch.autograd.grad(P.linear(dq), dq, g)`` gives the transposed
        product.
        """
        if dq.shape != (self.num_boundary, 2):
            raise MeshError(f"dq must be ({self.num_boundary}, 2), got {tuple(dq.shape)}")
        if self.solve is ParametrizationSolve.EXPLICIT:
            di = StoredTransposeMatmul.apply(dq, self._M.to(dtype=dq.dtype), self._MT.to(dtype=dq.dtype))
        else:
            di = _FactorizedMap.apply(dq, self, False)
        d = torch.zeros(self.num_vertices, 2, dtype=dq.dtype, device=dq.device)
        return d.index_copy(0, self.boundary_index, dq).index_copy(0, self.interior_index, di)

    def extra_repr(self) -> str:
        return (f"{self.num_vertices} vertices, {self.num_boundary} boundary, "
                f"{int(self.corner_mask.sum())} corners, "
                f"{self.seam_edge_pairs.shape[0]} seam edge pairs, {self.weights.value}, {self.solve.value}")


def _torch_csr(M: scipy.sparse.csr_matrix, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    M = M.tocsr()
    with warnings.catch_warnings():  # "sparse CSR support is in beta"
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(torch.as_tensor(M.indptr, dtype=torch.long),
                                       torch.as_tensor(M.indices, dtype=torch.long),
                                       torch.as_tensor(M.data, dtype=dtype), size=M.shape, device=device,
                                       check_invariants=False)


def _corner_mask(qb: np.ndarray, prev: np.ndarray, nxt: np.ndarray, angle: float) -> np.ndarray:
    """(B,) bool: the outline turns by more than ``angle`` at the vertex."""
    a = qb - qb[prev]
    b = qb[nxt] - qb
    cross = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    turn = np.abs(np.arctan2(cross, (a * b).sum(1)))
    return turn > angle


def _seam_change_mask(pairs_q: np.ndarray, panel_b: np.ndarray, prev: np.ndarray, B: int) -> np.ndarray:
    """(B,) bool: the outgoing and incoming boundary edges are stitched to different panels (or one is
    free)."""
    out_partner = np.full(B, -1, dtype=np.int64)  # partner panel of the edge k -> next(k)
    # edges are directed a0 -> a1 by construction (a1 = next(a0)); b0/b1 may be in either direction
    if pairs_q.size:
        out_partner[pairs_q[:, 0]] = panel_b[pairs_q[:, 2]]
        b_start = np.where(prev[pairs_q[:, 3]] == pairs_q[:, 2], pairs_q[:, 2], pairs_q[:, 3])
        out_partner[b_start] = panel_b[pairs_q[:, 0]]
    return out_partner != out_partner[prev]
