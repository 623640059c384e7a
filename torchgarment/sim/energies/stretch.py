"""Planar springs on the pattern edges (Wang et al. 2018, Eq. 5, the in-panel case).

Every mesh edge ``(i, j)`` inside a panel is a spring whose rest length comes from the 2D pattern::

    E = sum_s  Y / (2 L_s) * (|x_i - x_j| - r_s L_s)^2,      L_s = |p_i - p_j|

with ``Y`` the "Young's modulus" of the paper (newtons: the force of a spring stretched by 100 %), ``p``
the (V, 2) rest positions in panel coordinates and ``r_s`` a per-edge shirring factor (1 = no shirring).
``p`` and ``r_s`` are ``nn.Parameter`` s (frozen by default): call ``term.p.requires_grad_(True)`` and
``forward`` is differentiable in them, which is what pattern optimisation needs.

Stiffness units: the spring constant is ``Y / L``, so the membrane stiffness of a uniform triangle lattice
is about ``2 Y / (sqrt(3) L)`` newtons per metre (it depends on the edge length ``L``, as in the paper). The
default ``Y = 25 N`` gives about 2,900 N/m at 1 cm edges, the order of woven cotton's stretch stiffness
(10^3 - 10^4 N/m).

Hessian of one spring (``d = x_i - x_j``, ``l = |d|``, ``u = d / l``, ``k = Y / L``)::

    K = k u u^T + k (1 - r L / l) (I - u u^T),      H_s = [[K, -K], [-K, K]]

``H_s`` is PSD iff ``K`` is; the PSD projection is the standard one for springs: a compressed spring
(``l < r L``) drops its negative transverse part, ``(1 - r L / l)`` is clamped at 0.

The helper at the bottom (:class:`PairOperator`, sparse incidence matrices for gathers and scatters) is shared
with the sewing springs.
"""

from __future__ import annotations

import warnings

import torch

from torchgarment.errors import InputError, MeshError
from torchgarment.linalg import compact_csr
from torchgarment.sim.energies.base import EnergyTerm, HessianBlocks
from torchgarment.structures.garment_mesh import GarmentMesh

DEFAULT_STRETCH_STIFFNESS = 25.0
"""Default ``Y`` of the planar springs in newtons (about 2,900 N/m membrane stiffness at 1 cm edges)."""


class PlanarSprings(EnergyTerm):
    """Mass-spring stretching energy over the pattern edges, rest lengths from the 2D pattern.

    Attributes:
        p: parameter (V, 2), rest positions in panel coordinates (metres); frozen unless asked.
        shirring: parameter (E,), per-edge rest-length factor ``r_s`` (unitless); frozen unless asked.
        edges: buffer (E, 2) long, the springs.
        stiffness: ``Y`` in newtons.
    """

    name = "stretch"

    def __init__(
        self,
        edges: torch.Tensor,
        p: torch.Tensor,
        *,
        stiffness: float = DEFAULT_STRETCH_STIFFNESS,
        shirring: torch.Tensor | float | None = None,
    ) -> None:
        """Create the springs.

        Args:
            edges: (E, 2) long vertex pairs (each edge once).
            p: (V, 2) floating rest positions in metres (copied into a frozen parameter).
            stiffness: ``Y`` in newtons, > 0.
            shirring: per-edge factor ``r_s``: None (all 1), a float, or an (E,) tensor; > 0.

        Raises:
            InputError: bad shapes, non-positive stiffness or shirring, zero-length rest edges.
        """
        super().__init__()
        if (not isinstance(edges, torch.Tensor) or edges.ndim != 2 or edges.shape[1] != 2
                or edges.dtype != torch.long):
            raise InputError(f"edges must be a long (E, 2) tensor, got {_shape(edges)}")
        if not isinstance(p, torch.Tensor) or p.ndim != 2 or p.shape[1] != 2 or not p.is_floating_point():
            raise InputError(f"rest positions p must be a floating (V, 2) tensor, got {_shape(p)}")
        if not stiffness > 0:
            raise InputError(f"stretch stiffness must be positive, got {stiffness}")
        if edges.numel() and (int(edges.min()) < 0 or int(edges.max()) >= p.shape[0]):
            raise InputError(f"edges index vertices outside [0, {p.shape[0]})")
        E = edges.shape[0]
        if shirring is None:
            r = torch.ones(E, dtype=p.dtype, device=p.device)
        elif isinstance(shirring, torch.Tensor):
            if shirring.shape != (E,):
                raise InputError(f"shirring must have shape ({E},) (one factor per edge), got "
                                 f"{tuple(shirring.shape)}")
            r = shirring.detach().to(dtype=p.dtype, device=p.device).clone()
        else:
            r = torch.full((E,), float(shirring), dtype=p.dtype, device=p.device)
        if r.numel() and not bool((r > 0).all()):
            raise InputError("shirring factors must be positive")
        self.stiffness = float(stiffness)
        self.p = torch.nn.Parameter(p.detach().clone(), requires_grad=False)
        self.shirring = torch.nn.Parameter(r, requires_grad=False)
        self.register_buffer("edges", edges.contiguous())
        self.register_buffer("_i", edges[:, 0].contiguous())
        self.register_buffer("_j", edges[:, 1].contiguous())
        rest = self._rest_lengths_raw().detach()
        if rest.numel() and not bool((rest > 0).all()):
            raise InputError("some pattern edges have zero rest length (duplicate rest positions)")
        self.num_vertices = int(p.shape[0])
        self._ops = PairOperator(self._i, self._j, self.num_vertices)
        self._cache_key: tuple | None = None
        self._cache: tuple[torch.Tensor, torch.Tensor] | None = None

    @classmethod
    def from_mesh(
        cls,
        mesh: GarmentMesh,
        *,
        stiffness: float = DEFAULT_STRETCH_STIFFNESS,
        shirring: torch.Tensor | float | None = None,
    ) -> "PlanarSprings":
        """Springs on every edge of a pattern mesh (panels are separate, so every edge lies in one panel).

        Raises:
            MeshError: the mesh has no rest positions ``p``.
        """
        if mesh.p is None:
            raise MeshError("planar springs need a mesh with 2D rest positions p (a meshed sewing pattern)")
        return cls(mesh.edges, mesh.p, stiffness=stiffness, shirring=shirring)

    # ------------------------------------------------------------------ rest state
    def _rest_lengths_raw(self) -> torch.Tensor:
        return torch.linalg.vector_norm(self.p[self._i] - self.p[self._j], dim=1)

    def rest_lengths(self) -> torch.Tensor:
        """(E,) rest lengths ``r_s |p_i - p_j|`` in metres, differentiable in ``p`` and ``shirring``."""
        return self.shirring * self._rest_lengths_raw()

    def _rest(self, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """Detached ``(k, rL)``: spring constants ``Y / L`` (N/m) and rest lengths ``r L`` (m), cached."""
        p, r = self.p, self.shirring
        key = (id(p), p._version, p.data_ptr(), id(r), r._version, r.data_ptr(), self.stiffness, dtype,
               p.device)
        if key != self._cache_key:
            with torch.no_grad():
                L = self._rest_lengths_raw().to(dtype)
                self._cache = ((self.stiffness / L).contiguous(), (r.to(dtype) * L).contiguous())
            self._cache_key = key
        assert self._cache is not None
        return self._cache

    # ------------------------------------------------------------------ energy
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Energy in joules of positions ``x`` (V, 3); differentiable in ``x``, ``p`` and ``shirring``."""
        check_positions(x, self.num_vertices, self.name)
        L = self._rest_lengths_raw()
        length = torch.linalg.vector_norm(x[self._i] - x[self._j], dim=1)
        s = length - self.shirring * L
        return (self.stiffness / (2.0 * L) * s * s).sum()

    def _kinematics(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        check_positions(x, self.num_vertices, self.name)
        k, rl = self._rest(x.dtype)
        d = self._ops.diff(x)
        length = torch.linalg.vector_norm(d, dim=1)
        # relative floor keeps 1/l finite for coincident vertices (the gradient there is 0, not NaN)
        lsafe = torch.maximum(length, rl * torch.finfo(x.dtype).eps)
        return k, rl, d, length, lsafe

    def value_and_grad(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Energy () in joules and analytic gradient (V, 3) in newtons."""
        E, g, _ = self.value_grad_hessian_diagonal(x, with_hessian=False)
        return E, g

    def value_grad_hessian_diagonal(
        self, x: torch.Tensor, project_psd: bool = True, *, with_hessian: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Energy, gradient and (optionally) Hessian diagonal blocks sharing one pass over the springs."""
        x = x.detach()
        k, rl, d, length, lsafe = self._kinematics(x)
        s = length - rl
        ks = k * s
        E = 0.5 * torch.dot(ks, s)
        w = ks / lsafe
        g = self._ops.scatter(d * w.unsqueeze(1))
        if not with_hessian:
            return E, g, None
        return E, g, self._diagonal(k, rl, d, lsafe, w, project_psd)

    def _diagonal(self, k: torch.Tensor, rl: torch.Tensor, d: torch.Tensor, lsafe: torch.Tensor,
                  w: torch.Tensor, project_psd: bool) -> torch.Tensor:
        """(V, 3, 3) sums of the spring blocks ``K = a I + (k - a) u u^T`` at both endpoints.

        Scatters 7 numbers per spring instead of 9 (``K`` is symmetric): ``c d d^T`` with ``c = (k - a) /
        l^2`` (3 diagonal and 3 off-diagonal entries) and ``a``. Here ``a = k (1 - rL / l) = w``, the force
        factor.
        """
        a = w.clamp_min(0.0) if project_psd else w
        c = (k - a).div_(lsafe * lsafe)
        cols = torch.empty(d.shape[0], 7, dtype=d.dtype, device=d.device)
        cd = d * c.unsqueeze(1)
        torch.mul(cd, d, out=cols[:, 0:3])
        torch.mul(cd[:, 0:2], d[:, 1:3], out=cols[:, 3:5])  # xy, yz
        torch.mul(cd[:, 0], d[:, 2], out=cols[:, 5])  # xz
        cols[:, 6] = a
        sums = self._ops.scatter_both(cols)  # (V, 7)
        # the (V, 9) blocks by one exact product (entries 0 and 1: each result is one sum, or the diagonal's
        # sum plus a): eight strided column copies cost 0.8-0.9 ms at 30K vertices, the product 0.06-0.14 ms
        return (sums @ _blocks_from_sums(d.dtype, d.device)).view(-1, 3, 3)

    def _blocks(self, k: torch.Tensor, rl: torch.Tensor, d: torch.Tensor, lsafe: torch.Tensor,
                project_psd: bool) -> torch.Tensor:
        """(E, 3, 3) blocks ``K = a I + (k - a) u u^T`` with ``a = k (1 - rL / l)`` (clamped at 0 if
        projecting)."""
        a = k * (1.0 - rl / lsafe)
        if project_psd:
            a = a.clamp_min(0.0)
        u = d / lsafe.unsqueeze(1)
        K = ((k - a)[:, None, None] * u.unsqueeze(2)) * u.unsqueeze(1)
        K.diagonal(dim1=1, dim2=2).add_(a.unsqueeze(1))
        return K

    def hessian_diagonal(self, x: torch.Tensor, project_psd: bool = True) -> torch.Tensor:
        """(V, 3, 3) diagonal blocks of the Hessian (N/m), of per-spring PSD-projected blocks by default."""
        x = x.detach()
        k, rl, d, length, lsafe = self._kinematics(x)
        return self._diagonal(k, rl, d, lsafe, k * (length - rl) / lsafe, project_psd)

    def hessian_blocks(self, x: torch.Tensor, project_psd: bool = True) -> HessianBlocks:
        """Block-COO Hessian: V diagonal blocks and 2E off-diagonal blocks ``-K``."""
        x = x.detach()
        k, rl, d, _, lsafe = self._kinematics(x)
        return self._ops.hessian_blocks(self._blocks(k, rl, d, lsafe, project_psd))

    def extra_repr(self) -> str:
        return f"springs={self.edges.shape[0]}, stiffness={self.stiffness} N"


_FROM_SUMS: dict[tuple[torch.dtype, torch.device], torch.Tensor] = {}


def _blocks_from_sums(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(7, 9) map of :meth:`PlanarSprings._diagonal`'s per-vertex sums ``(xx, yy, zz, xy, yz, xz, a)`` to the
    row-major 3x3 block ``c d d^T + a I`` (cached per dtype and device)."""
    key = (dtype, device)
    m = _FROM_SUMS.get(key)
    if m is None:
        m = torch.zeros(7, 9, dtype=dtype)
        for row, (i, j) in enumerate(((0, 0), (1, 1), (2, 2), (0, 1), (1, 2), (0, 2))):
            m[row, 3 * i + j] = 1.0
            m[row, 3 * j + i] = 1.0
        m[6, 0::4] = 1.0
        m = _FROM_SUMS[key] = m.to(device)
    return m


# ---------------------------------------------------------------------------------------- shared helpers
class PairOperator:
    """Gathers and scatters over vertex pairs ``(i_s, j_s)``, the fastest way on each device.

    On the CPU, ``torch.index_add_`` with many repeated indices is slow and CSR sparse-dense products are not:
    the CSR incidence matrices are built on first use for each (device, dtype) from the index tensors, and
    cached. On a GPU it is the other way round: cuSPARSE's CSR product with a (V, 3) operand took 0.17-1.2 ms
    at 30K vertices on an H200 (64 % of the simulator iteration's GPU time), so there the pairs are gathered
    with ``index_select`` and scattered with ``index_add_`` (atomic adds: the summation order, and so the
    last bits, may vary between runs).

    Args:
        i, j: (E,) long vertex indices. num_vertices: V.
    """

    def __init__(self, i: torch.Tensor, j: torch.Tensor, num_vertices: int) -> None:
        self.i, self.j, self.num_vertices = i, j, int(num_vertices)
        self._mats: dict[tuple, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}
        self._index: dict[torch.device, tuple[torch.Tensor, torch.Tensor]] = {}

    def _get(self, dtype: torch.dtype,
             device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        key = (dtype, device)
        if key not in self._mats:
            i, j = self.i.to(device), self.j.to(device)
            E, V = int(i.shape[0]), self.num_vertices
            ar = torch.arange(E, device=device)
            one = torch.ones(E, dtype=dtype, device=device)
            rows, cols = torch.cat([i, j]), torch.cat([ar, ar])
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # "sparse CSR support is in beta"
                signed = torch.sparse_coo_tensor(torch.stack([rows, cols]), torch.cat([one, -one]), (V, E),
                                                 check_invariants=False).coalesce()
                unsigned = torch.sparse_coo_tensor(signed.indices(), signed.values().abs(), (V, E),
                                                   check_invariants=False)
                # the transpose: row s holds +1 at i_s and -1 at j_s
                diff = torch.sparse_coo_tensor(torch.stack([cols, rows]), torch.cat([one, -one]), (E, V),
                                               check_invariants=False).coalesce()
                self._mats[key] = (compact_csr(signed.to_sparse_csr()), compact_csr(unsigned.to_sparse_csr()),
                                   compact_csr(diff.to_sparse_csr()))
        return self._mats[key]

    @staticmethod
    def uses_index_ops(device: torch.device) -> bool:
        """Whether gathers and scatters on ``device`` use index operations (a GPU), not CSR products."""
        return device.type != "cpu"

    def _indices(self, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        """``(i, j)`` on ``device`` (copied once per device)."""
        if device not in self._index:
            self._index[device] = (self.i.to(device), self.j.to(device))
        return self._index[device]

    def diff(self, x: torch.Tensor) -> torch.Tensor:
        """(E, C) ``x[i] - x[j]`` for x (V, C)."""
        if self.uses_index_ops(x.device):
            i, j = self._indices(x.device)
            return x.index_select(0, i) - x.index_select(0, j)
        return self._get(x.dtype, x.device)[2] @ x

    def scatter(self, f: torch.Tensor) -> torch.Tensor:
        """(V, C): ``+f_s`` added at ``i_s`` and ``-f_s`` at ``j_s`` for f (E, C)."""
        if self.uses_index_ops(f.device):
            i, j = self._indices(f.device)
            out = f.new_zeros(self.num_vertices, f.shape[1])
            return out.index_add_(0, i, f).index_add_(0, j, f, alpha=-1.0)
        return self._get(f.dtype, f.device)[0] @ f

    def scatter_both(self, f: torch.Tensor) -> torch.Tensor:
        """(V, C): ``f_s`` added at both ``i_s`` and ``j_s`` for f (E, C)."""
        if self.uses_index_ops(f.device):
            i, j = self._indices(f.device)
            return f.new_zeros(self.num_vertices, f.shape[1]).index_add_(0, i, f).index_add_(0, j, f)
        return self._get(f.dtype, f.device)[1] @ f

    def diagonal(self, K: torch.Tensor) -> torch.Tensor:
        """(V, 3, 3) sum of the blocks ``K_s`` (E, 3, 3) at both endpoints."""
        return self.scatter_both(K.reshape(-1, 9)).view(self.num_vertices, 3, 3)

    def hessian_blocks(self, K: torch.Tensor) -> HessianBlocks:
        """Blocks of ``sum_s [[K_s, -K_s], [-K_s, K_s]]``: V diagonal blocks and 2E off-diagonal ``-K_s``."""
        diag = self.diagonal(K)
        ar = torch.arange(self.num_vertices, device=K.device)
        i, j = self._indices(K.device)
        return HessianBlocks(torch.cat([ar, i, j]), torch.cat([ar, j, i]), torch.cat([diag, -K, -K]))


def check_positions(x: torch.Tensor, num_vertices: int, what: str) -> None:
    """Raise InputError unless ``x`` is a floating (num_vertices, 3) tensor."""
    if not isinstance(x, torch.Tensor) or x.shape != (num_vertices, 3) or not x.is_floating_point():
        raise InputError(f"{what}: positions must be a floating ({num_vertices}, 3) tensor, got {_shape(x)}")


def _shape(t: object) -> str:
    if isinstance(t, torch.Tensor):
        return f"{t.dtype} tensor of shape {tuple(t.shape)}"
    return type(t).__name__
