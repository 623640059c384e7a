"""Garment-obstacle candidate pairs (Warp BVHs over the obstacle) against ipctk's broad phase on the whole
mesh."""

from __future__ import annotations

import ipctk
import numpy as np
import pytest
import trimesh

from torchgarment.sim.obstacle_pairs import GarmentObstaclePairs

DHAT = 0.01


def _scene() -> dict[str, np.ndarray]:
    """A two-layer garment cap close over a messy obstacle: two interpenetrating spheres (the obstacle's own
    boxes overlap everywhere along their intersection) and a thin sliver triangle near the cap."""
    a = trimesh.creation.icosphere(subdivisions=3, radius=0.2)
    b = trimesh.creation.icosphere(subdivisions=3, radius=0.15)
    sliver = np.array([[0.0, 0.0, 0.212], [0.3, 0.0, 0.2125], [0.0, 0.0005, 0.2122]])
    ov = np.concatenate([a.vertices, b.vertices + [0.18, 0.0, 0.0], sliver])
    na, nb = a.vertices.shape[0], b.vertices.shape[0]
    of = np.concatenate([a.faces, b.faces + na, [[na + nb, na + nb + 1, na + nb + 2]]])
    # the cap: the upper part of a sphere of radius 0.2 + 0.4 dhat, wavy by +-0.3 dhat, and a second layer
    # 0.45 dhat outside it
    cap = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    keep = cap.vertices[:, 2] > 0.55
    fkeep = keep[cap.faces].all(1)
    used = np.unique(cap.faces[fkeep])
    remap = -np.ones(cap.vertices.shape[0], dtype=np.int64)
    remap[used] = np.arange(used.shape[0])
    u = cap.vertices[used]
    gf1 = remap[cap.faces[fkeep]]
    wave = 0.3 * DHAT * np.sin(23 * u[:, 0]) * np.cos(19 * u[:, 1])
    inner = u * (0.2 + 0.4 * DHAT + wave)[:, None]
    outer = u * (0.2 + 0.85 * DHAT + wave)[:, None]
    gv = np.concatenate([inner, outer])
    gf = np.concatenate([gf1, gf1 + used.shape[0]])
    return {"gv": gv, "gf": gf.astype(np.int32), "ov": ov, "of": of.astype(np.int32)}


@pytest.fixture(scope="module")
def sc() -> dict[str, object]:
    s = _scene()
    n = s["gv"].shape[0]
    pairs = GarmentObstaclePairs(s["gv"], s["gf"], s["of"], s["ov"].shape[0], ipctk.LBVH)
    x = np.asfortranarray(np.concatenate([s["gv"], s["ov"]]))
    mesh = ipctk.CollisionMesh(x, pairs.mesh_edges(), pairs.mesh_faces())
    mesh.can_collide = ipctk.make_static_obstacle_filter(n)
    return {**s, "n": n, "pairs": pairs, "mesh": mesh, "x": x}


def _reference_collisions(mesh: ipctk.CollisionMesh, x: np.ndarray, dhat: float) -> ipctk.NormalCollisions:
    col = ipctk.NormalCollisions()
    col.build(mesh, x, dhat, 0.0, ipctk.LBVH())
    return col


def _moved(sc: dict, s: float) -> np.ndarray:
    """The garment pushed towards the obstacle's centre by s dhat and the obstacle grown by 2 s %."""
    n, x = sc["n"], sc["x"].copy()
    x[:n] -= s * DHAT * x[:n] / np.linalg.norm(x[:n], axis=1, keepdims=True)
    x[n:] *= 1.0 + 0.02 * s
    return np.asfortranarray(x)


def test_the_scene_is_messy(sc: dict) -> None:
    """The obstacle's two spheres cross each other (its own pairs, which the queries skip, include crossing
    triangles)."""
    m = ipctk.CollisionMesh(np.asfortranarray(sc["ov"]), ipctk.edges(sc["of"]), sc["of"])
    assert ipctk.has_intersections(m, np.asfortranarray(sc["ov"]))


@pytest.mark.parametrize("s", [0.0, 0.05])
def test_collision_sets_match_ipctk(sc: dict, s: float) -> None:
    """Same pairs within dhat, so the same barrier energy, gradient and Hessian, as ipctk's broad phase on the
    whole mesh with the static-obstacle filter (garment-garment, garment-obstacle, the sliver included)."""
    mesh, x = sc["mesh"], _moved(sc, s)
    ref = _reference_collisions(mesh, x, DHAT)
    col = ipctk.NormalCollisions()
    col.build(sc["pairs"].candidates(x, DHAT / 2), mesh, x, DHAT, 0.0)
    assert len(ref) > 100 and len(col) == len(ref)
    assert len(ref.ee_collisions) > 0 and len(ref.fv_collisions) > 0
    b = ipctk.BarrierPotential(DHAT, 1.0, False)
    assert b(col, mesh, x) == pytest.approx(b(ref, mesh, x), rel=1e-12)
    g_ref = np.asarray(b.gradient(ref, mesh, x))
    g = np.asarray(b.gradient(col, mesh, x))
    np.testing.assert_allclose(g, g_ref, rtol=0, atol=1e-12 * np.abs(g_ref).max())
    h_ref = b.hessian(ref, mesh, x, ipctk.PSDProjectionMethod.NONE)
    diff = abs(b.hessian(col, mesh, x, ipctk.PSDProjectionMethod.NONE) - h_ref).max()
    assert diff <= 1e-12 * abs(h_ref).max()


@pytest.mark.parametrize("narrow", ["additive", "tight_inclusion"])
def test_step_bounds_match_ipctk(sc: dict, narrow: str) -> None:
    """The CCD step size along garment and obstacle motions (both moving; the garment alone; short and long
    steps, some blocked by the obstacle, some by the garment's second layer) is ipctk's (to round-off: ipctk
    hands each pair the earliest time found so far, so the order of the pairs moves the last bit)."""
    mesh, pairs, n = sc["mesh"], sc["pairs"], sc["n"]
    ccd = (
        ipctk.AdditiveCCD(conservative_rescaling=0.9)
        if narrow == "additive"
        else ipctk.TightInclusionCCD(tolerance=1e-3, conservative_rescaling=0.8)
    )
    rng = np.random.default_rng(3)
    alphas = []
    cases = [(0.0, -0.01, False), (0.0, 0.2, False), (0.0, 1.5, False), (0.05, 3.0, False), (0.0, 0.8, True),
             (0.05, 0.07, True)]
    for s0, s1, layers in cases:
        x0, x1 = _moved(sc, s0), _moved(sc, s1)
        if layers:  # the outer layer moves inwards through the inner one, the obstacle stays
            x1 = x0.copy()
            m = n // 2
            x1[m:n] -= (s1 * 2 * DHAT) * x0[m:n] / np.linalg.norm(x0[m:n], axis=1, keepdims=True)
            x1[m:n] += 1e-3 * DHAT * rng.standard_normal((n - m, 3))
            x1 = np.asfortranarray(x1)
        ref = ipctk.Candidates()
        ref.build(mesh, x0, x1, 0.0, ipctk.LBVH())
        a_ref = ref.compute_collision_free_stepsize(mesh, x0, x1, 0.0, ccd)
        a = pairs.collision_free_stepsize(mesh, x0, x1, ccd)
        assert a == pytest.approx(a_ref, rel=1e-12, abs=0)
        alphas.append(a)
    assert min(alphas) < 0.05 and max(alphas) > 0.5  # the cases block hard and hardly


def test_step_free_matches_ipctk(sc: dict) -> None:
    """``is_step_collision_free`` with a minimum distance, for steps that keep it and steps that break it."""
    mesh, pairs = sc["mesh"], sc["pairs"]
    ccd = ipctk.TightInclusionCCD(tolerance=1e-6, conservative_rescaling=0.8)
    seen = set()
    cases = [(0.0, 0.03, 0.02 * DHAT), (0.0, 0.3, 0.1 * DHAT), (0.0, 0.01, 1e-4 * DHAT),
             (0.0, -0.01, 1e-4 * DHAT)]
    for s0, s1, dmin in cases:
        x0, x1 = _moved(sc, s0), _moved(sc, s1)
        ref = ipctk.is_step_collision_free(mesh, x0, x1, dmin, ipctk.LBVH(), ccd)
        assert pairs.is_step_collision_free(mesh, x0, x1, dmin, ccd) == ref
        seen.add(ref)
    assert seen == {True, False}


def test_far_garment_has_no_pairs(sc: dict) -> None:
    """A garment far from the obstacle (and its trees refit there) has only its own pairs."""
    n, x = sc["n"], sc["x"].copy()
    x[:n] += [5.0, 0.0, 0.0]
    x = np.asfortranarray(x)
    cand = sc["pairs"].candidates(x, DHAT / 2)
    assert all(c.vertex_id < n and c.face_id < sc["gf"].shape[0] for c in cand.fv_candidates)
    ne = sc["pairs"].garment_edges.shape[0]
    assert all(c.edge0_id < ne and c.edge1_id < ne for c in cand.ee_candidates)
    x1 = x.copy()
    x1[:n] += [0.01, 0.0, 0.0]
    ccd = ipctk.AdditiveCCD(conservative_rescaling=0.9)
    assert sc["pairs"].collision_free_stepsize(sc["mesh"], x, np.asfortranarray(x1), ccd) == 1.0


def test_out_of_range_faces_are_refused() -> None:
    """A face naming a vertex outside its mesh is one clear MeshError (the kernels do not check bounds)."""
    from torchgarment.errors import MeshError

    s = _scene()
    bad = s["of"].copy()
    bad[0, 0] = s["ov"].shape[0]
    with pytest.raises(MeshError, match="obstacle faces index vertices outside"):
        GarmentObstaclePairs(s["gv"], s["gf"], bad, s["ov"].shape[0], ipctk.LBVH)
    with pytest.raises(MeshError, match="garment faces index vertices outside"):
        GarmentObstaclePairs(s["gv"], s["gf"] - 1, s["of"], s["ov"].shape[0], ipctk.LBVH)
