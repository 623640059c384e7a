"""Small stand-in problems for the optimizer / Algorithm 1 tests (no dependency on the objective module).

A square sheet pinned along two opposite sides hangs under gravity; the pattern is parametrized by its
boundary vertices with the interior following a graph-Laplacian solve (like Eq. 8); the objective is the
positional cost to the equilibrium of a pattern scaled by 5 % plus a fixing regularizer (Eq. 9)."""

from __future__ import annotations

import numpy as np
import scipy.sparse
import torch

from torchgarment.sim import Scene
from torchgarment.sim.solvers import SolveSettings, solve
from torchgarment.structures.garment_mesh import GarmentMesh


def sheet(n: int = 6, h: float = 0.03):
    pts = [(i * h, j * h) for i in range(n + 1) for j in range(n + 1)]
    vid = lambda i, j: i * (n + 1) + j  # noqa: E731
    faces = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = vid(i, j), vid(i + 1, j), vid(i + 1, j + 1), vid(i, j + 1)
            faces += [(a, b, c), (a, c, d)] if (i + j) % 2 == 0 else [(a, b, d), (b, c, d)]
    p = torch.tensor(pts, dtype=torch.float64)
    x = torch.stack([p[:, 0], torch.zeros_like(p[:, 0]), p[:, 1]], dim=1)
    mesh = GarmentMesh(x, torch.tensor(faces), p=p)
    boundary = torch.tensor([vid(i, j) for i in range(n + 1) for j in range(n + 1) if i in (0, n)
                             or j in (0, n)])
    pins = torch.tensor([vid(i, j) for i in range(n + 1) for j in range(n + 1) if j in (0, n)])
    return mesh, boundary, pins


class LinearParam(torch.nn.Module):
    """p = p_bar + A (q - q_bar): boundary rows copy q, interior rows solve a graph Laplacian (affine)."""

    def __init__(self, mesh: GarmentMesh, boundary: torch.Tensor) -> None:
        super().__init__()
        V = mesh.num_vertices
        e = mesh.edges.numpy()
        W = scipy.sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(V, V))
        W = (W + W.T).tocsr()
        L = (scipy.sparse.diags(np.asarray(W.sum(1)).ravel()) - W).toarray()
        b = boundary.numpy()
        inner = np.setdiff1d(np.arange(V), b)
        A = np.zeros((V, len(b)))
        A[b, np.arange(len(b))] = 1.0
        A[inner] = -np.linalg.solve(L[np.ix_(inner, inner)], L[np.ix_(inner, b)])
        self.register_buffer("A", torch.tensor(A))
        self.register_buffer("p_bar", mesh.p.clone())
        self.boundary_index = boundary.clone()
        self.corner_mask = torch.zeros(len(b), dtype=torch.bool)

    def initial(self) -> torch.Tensor:
        return self.p_bar[self.boundary_index].clone()

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        return self.p_bar + self.A @ (q - self.initial())


class PositionalObjective(torch.nn.Module):
    """f = w/2 |x - x_t|^2 + fix/2 |p_B - p_bar_B|^2 ; regularizer Hessian = fix I (2B)."""

    def __init__(self, x_target: torch.Tensor, param: LinearParam, weight: float = 1e4,
                 fixing: float = 1.0) -> None:
        super().__init__()
        self.register_buffer("x_target", x_target.clone())
        self.param, self.weight, self.fixing = param, weight, fixing

    def forward(self, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        return self.weight / 2 * ((x - self.x_target) ** 2).sum() + self.fixing / 2 * (
            (p[self.param.boundary_index] - self.param.initial()) ** 2).sum()

    def term_values(self, x: torch.Tensor, p: torch.Tensor) -> dict[str, float]:
        return {"positional": float(self.weight / 2 * ((x - self.x_target) ** 2).sum()),
                "fixing": float(self.fixing / 2
                                * ((p[self.param.boundary_index] - self.param.initial()) ** 2).sum())}

    def regularizer_hessian(self) -> scipy.sparse.csr_matrix:
        return scipy.sparse.identity(2 * len(self.param.boundary_index), format="csr") * self.fixing


EXACT = SolveSettings(rtol=0.0, atol=1e-6, max_iterations=300)


def problem_parts(n: int = 6, scale: float = 1.05):
    """(model, param, objective, x_start, q0, mesh): the target is the equilibrium of the pattern scaled by
    s."""
    mesh, boundary, pins = sheet(n)
    model = Scene(mesh, pin_indices=pins).build()
    x_start, _ = solve(model, mesh.x, EXACT, solver="newton")
    c = mesh.p.mean(0)
    model.term("stretch").p.copy_(c + scale * (mesh.p - c))
    x_target, info = solve(model, x_start, EXACT, solver="newton")
    assert info.converged
    model.term("stretch").p.copy_(mesh.p)
    param = LinearParam(mesh, boundary)
    obj = PositionalObjective(x_target, param)
    return model, param, obj, x_start, param.initial(), mesh
