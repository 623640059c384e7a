"""Energy terms: analytic gradients and Hessians against finite differences, parameter gradients, physics."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh
from torch.func import functional_call

from torchgarment.errors import InputError, MeshError
from torchgarment.pattern.library import draft
from torchgarment.pattern.meshing import mesh_pattern
from torchgarment.sdf import BodySDF, SDFSettings
from torchgarment.sim.energies import (
    BodyBarrier,
    Gravity,
    Pins,
    PlanarSprings,
    QuadraticBending,
    SewingSprings,
)
from torchgarment.structures.garment_mesh import GarmentMesh
from torchgarment.testing import check_gradient, check_hessian_blocks, min_eigenvalue

MEASUREMENTS = {"height": 1.65, "bust": 0.9, "underbust": 0.78, "waist": 0.72, "hips": 0.98}


@pytest.fixture(scope="module")
def skirt() -> GarmentMesh:
    return mesh_pattern(draft("straight_skirt", MEASUREMENTS), 0.05)


@pytest.fixture(scope="module")
def x_noisy(skirt) -> torch.Tensor:
    """Placed positions with 1 cm noise: some springs stretched, some compressed."""
    gen = torch.Generator().manual_seed(0)
    return skirt.x + 0.01 * torch.randn(skirt.x.shape, dtype=torch.float64, generator=gen)


def two_panel_grid(n: int = 4, m: int = 3, h: float = 0.02) -> GarmentMesh:
    """A flat (2n x m) grid cut down the middle into two panels, the cut sewn with seam pairs.

    Panel coordinates p are the global grid coordinates, so x = (p, 0) is the flat sewn sheet.
    """
    def panel(x0: int, offset: int):
        pts = [(x0 + i, j) for i in range(n + 1) for j in range(m + 1)]
        vid = lambda i, j: offset + i * (m + 1) + j  # noqa: E731
        faces = []
        for i in range(n):
            for j in range(m):
                a, b, c, d = vid(i, j), vid(i + 1, j), vid(i + 1, j + 1), vid(i, j + 1)
                faces += [(a, b, c), (a, c, d)]
        return pts, faces, vid

    pa, fa, va = panel(0, 0)
    pb, fb, vb = panel(n, (n + 1) * (m + 1))
    p = torch.tensor(pa + pb, dtype=torch.float64) * h
    faces = torch.tensor(fa + fb)
    seams = torch.tensor([(va(n, j), vb(0, j)) for j in range(m + 1)])
    x = torch.cat([p, torch.zeros(p.shape[0], 1, dtype=torch.float64)], dim=1)
    ids = torch.cat([torch.zeros(len(fa), dtype=torch.long), torch.ones(len(fb), dtype=torch.long)])
    mesh = GarmentMesh(x, faces, p=p, panel_ids=ids, panel_names=["a", "b"], seam_pairs=seams)
    mesh.validate()
    return mesh


class PlaneSDF(torch.nn.Module):
    """phi(x) = n . x - c: exact gradient, zero Hessian (so the barrier Hessian is exact)."""

    voxel_size = 0.0

    def __init__(self, normal=(0.3, 1.0, -0.2), c: float = 0.5) -> None:
        super().__init__()
        n = torch.tensor(normal, dtype=torch.float64)
        self.n = n / n.norm()
        self.c = c

    def forward(self, x):
        return x @ self.n.to(x.dtype) - self.c

    def value_and_gradient(self, x):
        return self.forward(x.detach()), self.n.to(x.dtype).expand(x.shape[0], 3).clone()


@pytest.fixture(scope="module")
def sphere_sdf() -> BodySDF:
    m = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    return BodySDF.from_mesh(m.vertices, m.faces, SDFSettings(voxel_size=0.01))


def _shell_points(n: int, r0: float, r1: float, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, dtype=torch.float64, generator=gen)
    r = r0 + (r1 - r0) * torch.rand(n, 1, dtype=torch.float64, generator=gen)
    return d / d.norm(dim=1, keepdim=True) * r


def _check_term(term, x, *, num_samples=240, num_columns=48, rtol=1e-6):
    """Shared checks: value = forward, analytic grad vs FD and autograd, Hessian vs FD, projected PSD."""
    E, g = term.value_and_grad(x)
    assert torch.isfinite(g).all()
    assert float(E) == pytest.approx(float(term(x)), rel=1e-12, abs=1e-14)
    check_gradient(term, x, g, num_samples=num_samples, rtol=rtol)
    with torch.enable_grad():
        xr = x.clone().requires_grad_(True)
        (ga,) = torch.autograd.grad(term(xr), xr)
    assert torch.allclose(ga, g, rtol=1e-10, atol=1e-12 * float(g.abs().max()) + 1e-15)
    check_hessian_blocks(term, x, num_columns=num_columns, rtol=rtol, atol=1e-9)
    V = x.shape[0]
    proj = term.hessian_blocks(x, project_psd=True)
    H = proj.to_sparse(V).to_dense()
    scale = float(H.abs().max()) if H.numel() else 0.0
    if scale > 0:
        assert min_eigenvalue(proj, V) >= -1e-10 * scale
    # projected diagonal = diagonal blocks of the projected matrix
    D = term.hessian_diagonal(x)
    idx = torch.arange(V)
    Hb = H.view(V, 3, V, 3)[idx, :, idx, :]
    assert torch.allclose(D, Hb, rtol=1e-12, atol=1e-12 * max(scale, 1.0))
    if hasattr(term, "value_grad_hessian_diagonal"):
        E2, g2, D2 = term.value_grad_hessian_diagonal(x)
        assert float(E2) == pytest.approx(float(E), rel=1e-12, abs=1e-14)
        assert torch.allclose(g2, g) and torch.allclose(D2, D)


# ------------------------------------------------------------------------------------------------ stretch
def test_stretch_derivatives(skirt, x_noisy):
    term = PlanarSprings.from_mesh(skirt)
    _check_term(term, x_noisy)
    # compressed springs make the unprojected Hessian indefinite: the projection matters here
    assert min_eigenvalue(term.hessian_blocks(x_noisy, project_psd=False), skirt.num_vertices) < 0


def test_stretch_zero_at_rest_and_shirring(skirt):
    flat = torch.cat([skirt.p, torch.zeros(skirt.num_vertices, 1, dtype=torch.float64)], dim=1)
    term = PlanarSprings.from_mesh(skirt)
    E, g = term.value_and_grad(flat)
    assert float(E) < 1e-20 and float(g.abs().max()) < 1e-9
    # shirring 0.9: every spring is 10 % too long; E = sum Y L / 2 * 0.01
    L = (skirt.p[term.edges[:, 0]] - skirt.p[term.edges[:, 1]]).norm(dim=1)
    shirred = PlanarSprings.from_mesh(skirt, shirring=0.9)
    assert float(shirred(flat)) == pytest.approx(float((term.stiffness * L / 2 * 0.01).sum()), rel=1e-10)
    assert torch.allclose(shirred.rest_lengths(), 0.9 * L)


def test_stretch_parameter_gradients(skirt, x_noisy):
    term = PlanarSprings.from_mesh(skirt, shirring=torch.linspace(0.9, 1.1, skirt.edges.shape[0],
                                                                    dtype=torch.float64))
    p0 = term.p.detach().clone()
    check_gradient(lambda p: functional_call(term, {"p": p}, (x_noisy,)), p0, num_samples=120)
    r0 = term.shirring.detach().clone()
    check_gradient(lambda r: functional_call(term, {"shirring": r}, (x_noisy,)), r0, num_samples=120)
    # d/dp through the module's own parameter, and the analytic cache follows in-place edits of p
    term.p.requires_grad_(True)
    term(x_noisy).backward()
    assert term.p.grad is not None and float(term.p.grad.abs().max()) > 0
    with torch.no_grad():
        term.p.mul_(1.01)
    assert float(term.value_and_grad(x_noisy)[0]) == pytest.approx(float(term(x_noisy).detach()), rel=1e-12)


def test_stretch_errors(skirt):
    plain = GarmentMesh(skirt.x, skirt.faces)
    with pytest.raises(MeshError, match="rest positions"):
        PlanarSprings.from_mesh(plain)
    with pytest.raises(InputError, match="positive"):
        PlanarSprings.from_mesh(skirt, stiffness=0.0)
    with pytest.raises(InputError, match="shirring"):
        PlanarSprings.from_mesh(skirt, shirring=torch.ones(3, dtype=torch.float64))
    with pytest.raises(InputError, match="positions"):
        PlanarSprings.from_mesh(skirt).value_and_grad(skirt.x[:10])
    # coincident vertices: finite gradient, no NaN
    x = skirt.x.clone()
    e = skirt.edges[0]
    x[e[1]] = x[e[0]]
    E, g = PlanarSprings.from_mesh(skirt).value_and_grad(x)
    assert torch.isfinite(E) and torch.isfinite(g).all()
    assert torch.isfinite(PlanarSprings.from_mesh(skirt).hessian_blocks(x).values).all()


# ------------------------------------------------------------------------------------------------ sew
def test_sew_derivatives(skirt, x_noisy):
    term = SewingSprings.from_mesh(skirt)
    _check_term(term, x_noisy)
    s = skirt.seam_pairs
    d = x_noisy[s[:, 0]] - x_noisy[s[:, 1]]
    assert float(term(x_noisy)) == pytest.approx(0.5 * term.stiffness * float((d * d).sum()), rel=1e-12)
    with pytest.raises(InputError, match="itself"):
        SewingSprings(torch.tensor([[1, 1]]), 5)


# ------------------------------------------------------------------------------------------------ bend
def test_bend_derivatives(skirt, x_noisy):
    _check_term(QuadraticBending.from_mesh(skirt), x_noisy)


def test_bend_flat_is_zero_and_seams_bend():
    grid = two_panel_grid()
    flat = grid.x
    within = QuadraticBending.from_mesh(grid, across_seams=False)
    across = QuadraticBending.from_mesh(grid)
    # the welded sheet's interior edges: within-panel hinges + one hinge per seam edge
    assert across.stencils.shape[0] == within.stencils.shape[0] + 3
    for t in (within, across):
        E, g = t.value_and_grad(flat)
        assert float(E) < 1e-15 and float(g.abs().max()) < 1e-12  # a 0.3 rad fold costs ~1e-6 J
    # folding panel b about the seam line bends only across the seam
    x = flat.clone()
    b = grid.vertex_panel_ids == 1
    seam_x = 4 * 0.02
    ang = 0.3
    u = x[b, 0] - seam_x
    x[b, 0] = seam_x + u * math.cos(ang)
    x[b, 2] = u * math.sin(ang)
    assert float(within(x)) < 1e-15
    assert float(across(x)) > 1e-7
    # translating panel b away (an open seam) changes nothing: each half-stencil is translation invariant
    x2 = x.clone()
    x2[b] += torch.tensor([0.05, -0.02, 0.1], dtype=torch.float64)
    assert float(across(x2)) == pytest.approx(float(across(x)), rel=1e-10)


def test_bend_cylinder_matches_continuum():
    """Rolling a flat panel into a cylinder of radius R: E ~ k/2 * area / R^2 (minus the open boundary)."""
    g = mesh_pattern(draft("straight_skirt", MEASUREMENTS), 0.02)
    term = QuadraticBending.from_mesh(g, across_seams=False)
    R = 0.2
    s, y = g.p[:, 0], g.p[:, 1]
    x = torch.stack([R * torch.sin(s / R), y, R * (1 - torch.cos(s / R))], dim=1)
    area = float(g.rest_face_areas.abs().sum())
    ratio = float(term(x)) / (0.5 * term.stiffness * area / R**2)
    assert 0.93 <= ratio <= 1.02
    # the energy is quadratic in the curvature: half the radius, four times the energy (up to the chords)
    x2 = torch.stack([R / 2 * torch.sin(2 * s / R), y, R / 2 * (1 - torch.cos(2 * s / R))], dim=1)
    assert float(term(x2)) / float(term(x)) == pytest.approx(4.0, rel=0.03)


# ------------------------------------------------------------------------------------------------ gravity
def test_gravity(skirt, x_noisy):
    term = Gravity.from_mesh(skirt, density=0.2)
    _check_term(term, x_noisy)
    total_area = float(skirt.rest_face_areas.abs().sum())
    assert float(term.masses.sum()) == pytest.approx(0.2 * total_area, rel=1e-12)
    _, g = term.value_and_grad(x_noisy)
    assert torch.allclose(g[:, 1], 9.81 * term.masses) and float(g[:, [0, 2]].abs().max()) == 0.0
    # lifting everything by 1 m costs m g joules
    up = x_noisy + torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    assert float(term(up) - term(x_noisy)) == pytest.approx(9.81 * float(term.masses.sum()), rel=1e-10)


# ------------------------------------------------------------------------------------------------ pins
def test_pins(skirt, x_noisy):
    idx = torch.tensor([0, 5, 5, 17])
    targets = skirt.x[idx] + 0.01
    term = Pins(idx, targets, skirt.num_vertices)
    _check_term(term, x_noisy)
    t0 = term.targets.detach().clone()
    check_gradient(lambda t: functional_call(term, {"targets": t}, (x_noisy,)), t0)
    with pytest.raises(InputError, match="outside"):
        Pins(torch.tensor([10_000]), torch.zeros(1, 3, dtype=torch.float64), skirt.num_vertices)


# ------------------------------------------------------------------------------------------------ barrier
def test_barrier_plane_exact_derivatives():
    x = _shell_points(60, 0.0, 0.3, seed=3) + torch.tensor([0.0, 0.9, 0.0], dtype=torch.float64)
    sdf = PlaneSDF()
    assert bool((sdf(x) > 0).all())
    _check_term(BodyBarrier(sdf, x.shape[0]), x, num_samples=None, num_columns=None)


@pytest.mark.parametrize("dhat", [0.3, 0.7])
def test_range_limited_barrier_plane_exact_derivatives(dhat):
    # points at 0 .. 0.3 m from the plane y = 0.9 - ...: some inside dhat, some beyond
    x = _shell_points(60, 0.0, 0.3, seed=3) + torch.tensor([0.0, 0.9, 0.0], dtype=torch.float64)
    sdf = PlaneSDF()
    phi = sdf(x)
    assert bool((phi > 0).all()) and bool((phi < dhat).any())
    term = BodyBarrier(sdf, x.shape[0], dhat=dhat)
    _check_term(term, x, num_samples=None, num_columns=None)
    # the closed form, zero beyond dhat
    s = (phi / dhat).clamp(max=1.0)
    assert float(term(x)) == pytest.approx(float((-0.01 * (s - 1) ** 2 * torch.log(s)).sum()), rel=1e-12)
    E, g = term.value_and_grad(x)
    assert torch.all(g[phi >= dhat] == 0)


def test_range_limited_barrier_scalar_derivatives():
    """b, b', b'' of the range-limited form against autograd, C2 at dhat, the log singularity near 0."""
    sdf = PlaneSDF()
    term = BodyBarrier(sdf, 1, dhat=3e-3)
    phi = torch.linspace(1e-6, 4e-3, 400, dtype=torch.float64, requires_grad=True)
    b = term.barrier(phi)
    (d1,) = torch.autograd.grad(b.sum(), phi, create_graph=True)
    (d2,) = torch.autograd.grad(d1.sum(), phi)
    a1, a2 = term.derivatives(phi.detach())
    torch.testing.assert_close(a1, d1.detach(), rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(a2, d2, rtol=1e-10, atol=1e-9)
    assert bool((a2 >= 0).all()) and bool((a1 <= 0).all())  # convex and repulsive
    # continuity at dhat: value, slope and curvature -> 0
    at = torch.tensor([3e-3 * (1 - 1e-6)], dtype=torch.float64)
    b1, b2 = term.derivatives(at)
    assert abs(float(term.barrier(at))) < 1e-18 and abs(float(b1)) < 1e-10 and abs(float(b2)) < 1e-2
    # near the body it is the paper's force mu / phi
    near = torch.tensor([1e-9], dtype=torch.float64)
    assert float(term.derivatives(near)[0]) == pytest.approx(-0.01 / 1e-9, rel=1e-4)
    with pytest.raises(InputError, match="dhat"):
        BodyBarrier(sdf, 1, dhat=-1.0)
    with pytest.raises(InputError, match="below dhat"):
        BodyBarrier(sdf, 1, dhat=1e-3, offset=2e-3)


def test_lazy_barrier_matches_full_queries(sphere_sdf):
    """The lazy range-limited barrier (SDF sampled only where a vertex may be within dhat) gives the same
    energy, gradient and Hessian diagonal as sampling every vertex, along a random walk towards the body, and
    samples fewer vertices once most are far."""
    x = _shell_points(400, 0.303, 0.5, seed=7)
    lazy = BodyBarrier(sphere_sdf, x.shape[0], dhat=0.02, lazy=True)
    full = BodyBarrier(sphere_sdf, x.shape[0], dhat=0.02, lazy=False)
    gen = torch.Generator().manual_seed(8)
    counts = []
    for _ in range(25):
        step = 0.004 * torch.randn(x.shape, dtype=torch.float64, generator=gen) - 0.002 * x / x.norm(dim=1,
                                                                                                     keepdim=True)
        x = x + step
        x = full.project_feasible(x)
        El, gl, hl = lazy.value_grad_hessian_diagonal(x)
        Ef, gf, hf = full.value_grad_hessian_diagonal(x)
        counts.append(lazy.last_query_count)
        assert float(El) == pytest.approx(float(Ef), rel=1e-12, abs=1e-15)
        torch.testing.assert_close(gl, gf, rtol=1e-12, atol=1e-15)
        torch.testing.assert_close(hl, hf, rtol=1e-12, atol=1e-12)
        # the lazy phi is a lower bound of the true one, so the step bound stays safe
        dx = 0.01 * torch.randn(x.shape, dtype=torch.float64, generator=gen)
        a = lazy.max_step(x, dx)
        assert bool((sphere_sdf(x + a * dx) > 0).all())
    assert full.last_query_count == x.shape[0]
    assert max(counts[1:]) < 0.5 * x.shape[0]  # most vertices start 3-20 cm away


def test_barrier_body_sdf_gradient(sphere_sdf):
    x = _shell_points(200, 0.31, 0.36, seed=4)
    term = BodyBarrier(sphere_sdf, x.shape[0])
    E, g = term.value_and_grad(x)
    phi = sphere_sdf(x)
    assert float(E) == pytest.approx(float(-0.01 * torch.log(phi).sum()), rel=1e-12)
    check_gradient(term, x, g, num_samples=200, eps=1e-7, rtol=1e-5)
    blocks = term.hessian_blocks(x)
    assert min_eigenvalue(blocks, x.shape[0]) >= -1e-12 * float(blocks.values.abs().max())


class BallSDF(torch.nn.Module):
    """phi = sign (|x| - R): a ball (sign +1, a convex body) or a spherical cavity (sign -1, a concave one),
    with its analytic gradient; ``Hess(phi) = sign (I - u u^T) / |x|``."""

    def __init__(self, radius: float, sign: float) -> None:
        super().__init__()
        self.radius, self.sign = radius, sign

    def forward(self, x):
        return self.sign * (torch.linalg.vector_norm(x, dim=1) - self.radius)

    def value_and_gradient(self, x):
        r = torch.linalg.vector_norm(x, dim=1)
        return self.sign * (r - self.radius), self.sign * x / r.unsqueeze(1)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_barrier_hessian_blocks_include_the_curvature(sign):
    """The unprojected blocks are the exact Hessian on a curved SDF (``b' Hess(phi)`` included); projected,
    the curvature part is dropped where the body is convex and kept where it is concave."""
    radius, dhat = 0.3, 0.02
    r = radius + sign * torch.linspace(0.002, 0.03, 40, dtype=torch.float64)  # some beyond dhat
    x = _shell_points(40, 1.0, 1.0, seed=7) * r.unsqueeze(1)
    term = BodyBarrier(BallSDF(radius, sign), x.shape[0], dhat=dhat)
    check_hessian_blocks(term, x, num_columns=None, rtol=1e-6, atol=1e-9)
    gn = term.hessian_diagonal(x)
    exact = term.hessian_blocks(x, project_psd=False).values
    proj = term.hessian_blocks(x, project_psd=True).values
    curv = term.curvature_blocks(x)
    assert torch.allclose(exact, gn + curv)
    near = term.sdf(x) < dhat
    assert bool(near.any()) and bool((~near).any()) and bool((curv[~near] == 0).all())
    assert float(curv[near].abs().amax()) > 1e-3 * float(gn[near].abs().amax())
    assert float(torch.linalg.eigvalsh(proj).min()) >= -1e-9 * float(proj.abs().max())
    scale = float(proj.abs().max())
    if sign > 0:  # convex: b' Hess(phi) is negative semi-definite, projected away
        assert torch.allclose(proj, gn, atol=1e-9 * scale)
    else:  # concave: positive semi-definite, kept whole
        assert torch.allclose(proj, exact, atol=1e-9 * scale)


class CountingBallSDF(BallSDF):
    """A :class:`BallSDF` that counts the points its gradient is asked for."""

    def __init__(self, radius: float, sign: float) -> None:
        super().__init__(radius, sign)
        self.points = 0

    def value_and_gradient(self, x):
        self.points += x.shape[0]
        return super().value_and_gradient(x)


def test_barrier_curvature_is_differenced_once_per_position():
    """Projected Newton assembles the projected and the exact Hessian at one ``x``: the SDF's Hessian rows
    are differenced once and reused, and any change of ``x`` (in place too), of ``mu`` or of ``dhat``
    gives the same blocks as a fresh barrier."""
    radius = 0.3
    r = radius - torch.linspace(0.002, 0.03, 40, dtype=torch.float64)  # inside a cavity, some beyond dhat
    x = _shell_points(40, 1.0, 1.0, seed=7) * r.unsqueeze(1)
    sdf = CountingBallSDF(radius, -1.0)
    term = BodyBarrier(sdf, x.shape[0], dhat=0.02)

    def fresh(xx, **kw):
        t = BodyBarrier(BallSDF(radius, -1.0), x.shape[0], dhat=kw.get("dhat", 0.02), mu=kw.get("mu", 0.01))
        return t.hessian_blocks(xx, project_psd=False).values, t.hessian_blocks(xx, project_psd=True).values

    proj = term.hessian_blocks(x, project_psd=True).values
    n_first = sdf.points
    exact = term.hessian_blocks(x, project_psd=False).values
    assert sdf.points == n_first  # the second assembly at the same x queries nothing
    ref_exact, ref_proj = fresh(x)
    assert float(sdf(x).min()) > 0 and float(ref_exact.abs().amax()) > 0
    assert torch.equal(exact, ref_exact) and torch.equal(proj, ref_proj)
    x.mul_(1.01)  # in place: the cache must see it
    n = sdf.points
    exact = term.hessian_blocks(x, project_psd=False).values
    assert sdf.points > n
    assert torch.equal(exact, fresh(x)[0])
    term.mu = 0.05  # the curvature scales with b', recomputed from the cached Hess(phi)
    assert torch.equal(term.hessian_blocks(x, project_psd=False).values, fresh(x, mu=0.05)[0])
    term.dhat = 0.01  # fewer active rows: differenced again
    assert torch.equal(term.hessian_blocks(x, project_psd=False).values, fresh(x, mu=0.05, dhat=0.01)[0])


def test_barrier_infeasible_is_inf_not_nan():
    sdf = PlaneSDF(normal=(0.0, 1.0, 0.0), c=0.0)
    x = torch.tensor([[0.0, 0.1, 0.0], [0.2, 0.0, 0.0], [0.0, -0.1, 0.3]], dtype=torch.float64)
    term = BodyBarrier(sdf, 3)
    E, g = term.value_and_grad(x)
    assert math.isinf(float(E)) and float(E) > 0 and torch.isfinite(g).all()
    assert math.isinf(float(term(x))) and not math.isnan(float(term(x)))
    assert torch.isfinite(term.hessian_diagonal(x)).all()
    # phi -> 0+: finite
    near = torch.tensor([[0.0, 1e-9, 0.0]], dtype=torch.float64)
    t1 = BodyBarrier(sdf, 1)
    E1, g1 = t1.value_and_grad(near)
    assert math.isfinite(float(E1)) and math.isfinite(float(t1(near))) and torch.isfinite(g1).all()
    assert float(g1[0, 1]) == pytest.approx(-0.01 / 1e-9, rel=1e-9)


def test_barrier_max_step_plane():
    sdf = PlaneSDF(normal=(0.0, 1.0, 0.0), c=0.0)
    x = torch.tensor([[0.0, 0.1, 0.0], [1.0, 0.5, 0.0]], dtype=torch.float64)
    term = BodyBarrier(sdf, 2)
    dx = torch.tensor([[0.0, -0.3, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    a = term.max_step(x, dx)
    assert 0.9 / 3 <= a <= 1 / 3  # phi hits 0 at alpha = 1/3
    assert float(sdf(x + a * dx).min()) > 0
    assert term.max_step(x, -dx) == 1.0  # moving away
    assert term.max_step(x, 0.1 * dx) == 1.0  # stays outside
    with pytest.raises(InputError, match="project_feasible"):
        term.max_step(x - torch.tensor([0.0, 0.2, 0.0], dtype=torch.float64), dx)


def test_barrier_max_step_catches_tunnelling(sphere_sdf):
    """A path through the sphere whose end point is outside again must still be cut."""
    x = torch.tensor([[-0.35, 0.0, 0.0]], dtype=torch.float64)
    dx = torch.tensor([[0.7, 0.0, 0.0]], dtype=torch.float64)  # ends at +0.35: outside
    term = BodyBarrier(sphere_sdf, 1)
    assert float(sphere_sdf(x + dx)) > 0
    a = term.max_step(x, dx)
    assert a <= 0.05 / 0.7 + 1e-3  # enters the sphere at alpha ~ 0.0714
    assert a >= 0.5 * 0.05 / 0.7


def test_barrier_project_feasible(sphere_sdf):
    inside = _shell_points(50, 0.2, 0.29, seed=5)
    outside = _shell_points(50, 0.33, 0.4, seed=6)
    x = torch.cat([inside, outside])
    term = BodyBarrier(sphere_sdf, 100)
    y = term.project_feasible(x)
    phi = sphere_sdf(y)
    assert float(phi.min()) > 0.5 * term.offset
    assert float(phi[:50].max()) < 3 * term.offset  # moved just outside, not far
    assert torch.equal(y[50:], x[50:]) and not torch.equal(y[:50], x[:50])
    assert term.offset == pytest.approx(max(1e-3, 0.25 * sphere_sdf.voxel_size))
    assert math.isfinite(float(term.value_and_grad(y)[0]))


def test_pair_operator_index_path_equals_csr_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """The GPU's gather/scatter path (index_select, index_add_) computes what the CPU's CSR products do; run
    here on the CPU by forcing it."""
    from torchgarment.sim.energies import PairOperator

    gen = torch.Generator().manual_seed(3)
    V, E = 50, 200
    i = torch.randint(0, V, (E,), generator=gen)
    j = (i + torch.randint(1, V, (E,), generator=gen)) % V  # pairs of two vertices (repeats allowed)
    x = torch.randn(V, 3, dtype=torch.float64, generator=gen)
    f = torch.randn(E, 9, dtype=torch.float64, generator=gen)
    csr = PairOperator(i, j, V)
    expected = (csr.diff(x), csr.scatter(f), csr.scatter_both(f))
    monkeypatch.setattr(PairOperator, "uses_index_ops", staticmethod(lambda device: True))
    op = PairOperator(i, j, V)
    for got, want in zip((op.diff(x), op.scatter(f), op.scatter_both(f)), expected):
        assert got.shape == want.shape
        assert torch.allclose(got, want, rtol=0, atol=1e-12)
