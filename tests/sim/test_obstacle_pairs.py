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


def test_additive_bound_is_a_lower_bound(sc: dict) -> None:
    """Every garment-obstacle pair's rescaled first advancement is at most the time ipctk's additive CCD
    reports for it (pairs whose bound exceeds the running minimum can be skipped), and the bound is not slack
    by orders of magnitude (it prunes)."""
    from torchgarment.sim.obstacle_pairs import _EDGE_EDGE, _FACE_VERTEX, _VERTEX_FACE

    pairs, n = sc["pairs"], sc["n"]
    ccd = ipctk.AdditiveCCD(conservative_rescaling=0.9)
    x0, x1 = _moved(sc, 0.0), _moved(sc, 1.5)
    c = pairs._cross(x0, x1, 0.0)
    g0, g1, a0, a1 = x0[:n], x1[:n], x0[n:], x1[n:]
    hits, ratios = 0, []
    for kind, (ii, jj, adv) in c.items():
        assert ii.shape[0] > 0
        for i, j, b in zip(ii, jj, 0.9 * adv):
            if kind == _VERTEX_FACE:
                f = pairs.obstacle_faces[j]
                hit, toi = ccd.point_triangle_ccd(g0[i], *a0[f], g1[i], *a1[f])
            elif kind == _FACE_VERTEX:
                f = pairs.garment_faces[i]
                hit, toi = ccd.point_triangle_ccd(a0[j], *g0[f], a1[j], *g1[f])
            else:
                e, o = pairs.garment_edges[i], pairs.obstacle_edges[j]
                hit, toi = ccd.edge_edge_ccd(*g0[e], *a0[o], *g1[e], *a1[o])
            assert kind in (_VERTEX_FACE, _FACE_VERTEX, _EDGE_EDGE)
            if hit:
                hits += 1
                assert toi >= b * (1.0 - 1e-12)
                ratios.append(toi / b)
            else:
                assert b > 0.0
    assert hits > 50 and np.median(ratios) < 3.0


def test_pruned_additive_step_matches_ipctk(sc: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    """With small batches (several rounds of the lowest bounds) the additive step size is still ipctk's, and
    fewer garment-obstacle pairs than found are handed to the narrow phase."""
    import torchgarment.sim.obstacle_pairs as op

    monkeypatch.setattr(op, "CCD_BATCH", 2)
    mesh, pairs = sc["mesh"], sc["pairs"]
    queried = []
    real = pairs._cross_candidates

    def spy(c: dict, rows: np.ndarray | None = None) -> tuple[list, list]:
        ee, fv = real(c, rows)
        queried.append(len(ee) + len(fv))
        return ee, fv

    monkeypatch.setattr(pairs, "_cross_candidates", spy)
    ccd = ipctk.AdditiveCCD(conservative_rescaling=0.9)
    rounds = []
    for s1 in (0.2, 1.5, 3.0):
        x0, x1 = _moved(sc, 0.0), _moved(sc, s1)
        ref = ipctk.Candidates()
        ref.build(mesh, x0, x1, 0.0, ipctk.LBVH())
        queried.clear()
        a = pairs.collision_free_stepsize(mesh, x0, x1, ccd)
        a_ref = ref.compute_collision_free_stepsize(mesh, x0, x1, 0.0, ccd)
        assert a == pytest.approx(a_ref, rel=1e-12, abs=0)
        found = sum(v[0].shape[0] for v in pairs._cross(x0, x1, 0.0).values())
        assert sum(queried) < found
        rounds.append(len(queried))
    assert max(rounds) >= 2


@pytest.mark.parametrize("batch, reverse", [(4096, False), (8, False), (8, True)])
def test_step_free_matches_ipctk(
    sc: dict, batch: int, reverse: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``is_step_collision_free`` with a minimum distance, for steps that keep it and steps that break it
    (garment-obstacle pairs in one batch or in many; ``reverse``: the likeliest pairs last)."""
    import torchgarment.sim.obstacle_pairs as op

    monkeypatch.setattr(op, "CCD_BATCH", batch)
    mesh, pairs = sc["mesh"], sc["pairs"]
    if reverse:
        cross = pairs._cross

        def reversed_cross(*args: object) -> dict:
            return {k: (i, j, -adv) for k, (i, j, adv) in cross(*args).items()}

        monkeypatch.setattr(pairs, "_cross", reversed_cross)
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


def _pair_set(cand: ipctk.Candidates) -> set[tuple[str, int, int]]:
    return ({("ee", c.edge0_id, c.edge1_id) for c in cand.ee_candidates}
            | {("fv", c.face_id, c.vertex_id) for c in cand.fv_candidates})


def test_line_search_trials_reuse_the_step_pairs(sc: dict) -> None:
    """After an additive step bound that keeps the pairs within dhat of the step, the candidates at points of
    the step (computed the way a line search does, with its round-off) come from those pairs without a BVH
    query and are the same pairs as a fresh query's; points off the step are queried afresh. The step size
    does not change."""
    s = _scene()
    kept = GarmentObstaclePairs(s["gv"], s["gf"], s["of"], s["ov"].shape[0], ipctk.LBVH)
    mesh, fresh = sc["mesh"], sc["pairs"]
    ccd = ipctk.AdditiveCCD(conservative_rescaling=0.9)
    x0, x1 = _moved(sc, 0.0), _moved(sc, 1.5)
    a = kept.collision_free_stepsize(mesh, x0, x1, ccd, keep_within=DHAT)
    assert a == fresh.collision_free_stepsize(mesh, x0, x1, ccd) and 0.0 < a < 1.0
    p = x1 - x0
    sizes = []
    for alpha in (0.0, 0.37 * a, a, 1.0):
        xt = np.asfortranarray(x0 + alpha * p)
        before = kept.sweep_reuses
        got = _pair_set(kept.candidates(xt, DHAT / 2))
        assert kept.sweep_reuses == before + 1
        want = _pair_set(fresh.candidates(xt, DHAT / 2))
        col = ipctk.NormalCollisions()
        col.build(kept.candidates(xt, DHAT / 2), mesh, xt, DHAT, 0.0)
        assert len(col) == len(_reference_collisions(mesh, xt, DHAT))
        assert got == want
        sizes.append(len(got))
    assert min(sizes) > 1000
    off = x0 + 0.5 * a * p
    off[0] += 1e-3 * DHAT
    off = np.asfortranarray(off)
    before = kept.sweep_reuses
    assert _pair_set(kept.candidates(off, DHAT / 2)) == _pair_set(fresh.candidates(off, DHAT / 2))
    assert _pair_set(kept.candidates(x0, DHAT)) == _pair_set(fresh.candidates(x0, DHAT))  # a wider reach
    assert kept.sweep_reuses == before


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


#: a garment edge and an avatar edge 4.2e-11 apart that pass through each other at t = 0.34 of a linear step
#: (captured from the inflation of a layered T-shirt on creature-50k, canonical frame); ipctk's additive CCD
#: with its default 1e7 steps drifts past the crossing and reports no collision
_CROSSING_EDGES = np.array([
    [[-0.09600990444098724, 1.4917722921659375, 0.0246562109769964],
     [-0.09637109531072587, 1.513994115570442, -0.02425210608567061],
     [-0.09082336058485568, 1.492230078734339, -0.0009545100829563107],
     [-0.10217800234769726, 1.5112290733177496, 0.009552900095384363]],
    [[-0.09608391148330563, 1.4917987221987183, 0.02471867349677727],
     [-0.09644549621208785, 1.5140617057403085, -0.024280243033869435],
     [-0.09085818124231193, 1.49220634644835, -0.0009625716601609803],
     [-0.10221625333426775, 1.5112114586104397, 0.009546547349769077]],
])


def test_slow_crossing_pair_is_caught() -> None:
    """The crossing edge pair above, each edge in its own triangle (the garment's and the avatar's, their
    third vertices moving along): the step bound (additive CCD capped at ADDITIVE_MAX_ITERATIONS steps) stops
    before the crossing, where ipctk's additive CCD with its default 1e7 steps does not."""
    from torchgarment.sim.contact import ADDITIVE_MAX_ITERATIONS

    (a0, a1, b0, b1), (a0e, a1e, b0e, b1e) = _CROSSING_EDGES
    ts = np.linspace(0.0, 1.0, 2001)
    gap = [_segment_distance(*(e + t * (f - e) for e, f in ((a0, a0e), (a1, a1e), (b0, b0e), (b1, b1e))))
           for t in ts]
    t_cross = float(ts[int(np.argmin(gap))])
    assert 0.3 < t_cross < 0.4 and min(gap) < 1e-12 < 1e-11 < min(gap[0], gap[-1])
    up = np.array([0.0, 0.0, 0.05])
    side = np.array([0.05, 0.0, 0.0])
    x0 = np.asfortranarray([a0, a1, (a0 + a1) / 2 + up, b0, b1, (b0 + b1) / 2 - side])
    x1 = np.asfortranarray([a0e, a1e, (a0e + a1e) / 2 + up, b0e, b1e, (b0e + b1e) / 2 - side])
    tri = np.array([[0, 1, 2]], np.int32)
    pairs = GarmentObstaclePairs(x0[:3], tri, tri, 3, ipctk.LBVH)
    mesh = ipctk.CollisionMesh(x0, pairs.mesh_edges(), pairs.mesh_faces())
    mesh.can_collide = ipctk.make_static_obstacle_filter(3)
    ref = ipctk.Candidates()
    ref.build(mesh, x0, x1, 0.0, ipctk.LBVH())
    default_additive = ipctk.AdditiveCCD(conservative_rescaling=0.9)  # 1e7 steps
    assert ref.compute_collision_free_stepsize(mesh, x0, x1, 0.0, default_additive) > 0.99
    additive = ipctk.AdditiveCCD(max_iterations=ADDITIVE_MAX_ITERATIONS, conservative_rescaling=0.9)
    assert 0.0 < pairs.collision_free_stepsize(mesh, x0, x1, additive) < t_cross


def _segment_distance(p: np.ndarray, q: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Distance of segments pq and ab (closest points by the 2x2 normal equations, clamped; the segments here
    are far from parallel)."""
    d1, d2, r = q - p, b - a, p - a
    m = np.array([[d1 @ d1, -(d1 @ d2)], [-(d1 @ d2), d2 @ d2]])
    u, v = np.clip(np.linalg.solve(m, [-(d1 @ r), d2 @ r]), 0.0, 1.0)
    return float(np.linalg.norm(p + u * d1 - (a + v * d2)))


def test_snap_check_skips_the_garments_own_pairs_when_it_does_not_move() -> None:
    """A snap moves the obstacle alone: the garment's own pairs keep their distances, so two layers closer
    than the minimum distance do not make the obstacle's move unsafe. The garment-obstacle pairs are still
    checked, and a moving garment's own pairs too."""
    def square(z: float, half: float, offset: int) -> tuple[np.ndarray, np.ndarray]:
        v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
        return v, np.array([[0, 1, 2], [0, 2, 3]]) + offset

    lo, flo = square(0.0, 0.05, 0)
    hi, fhi = square(0.1 * DHAT, 0.05, 4)  # a layer 0.1 dhat above the first
    ov, of = square(-3.0 * DHAT, 0.2, 0)
    gv, gf = np.concatenate([lo, hi]), np.concatenate([flo, fhi]).astype(np.int32)
    n = gv.shape[0]
    pairs = GarmentObstaclePairs(gv, gf, of.astype(np.int32), ov.shape[0], ipctk.LBVH)
    x0 = np.asfortranarray(np.concatenate([gv, ov]))
    mesh = ipctk.CollisionMesh(x0, pairs.mesh_edges(), pairs.mesh_faces())
    mesh.can_collide = ipctk.make_static_obstacle_filter(n)
    ccd = ipctk.TightInclusionCCD(tolerance=1e-6, conservative_rescaling=0.8)
    dmin = 0.5 * DHAT

    def obstacle_to(z: float) -> np.ndarray:
        x1 = x0.copy()
        x1[n:, 2] = z
        return np.asfortranarray(x1)

    # the obstacle moves away: free, although the layers are 0.1 dhat < dmin apart (ipctk counts them)
    assert pairs.is_step_collision_free(mesh, x0, obstacle_to(-4.0 * DHAT), dmin, ccd)
    assert not ipctk.is_step_collision_free(mesh, x0, obstacle_to(-4.0 * DHAT), dmin, ipctk.LBVH(), ccd)
    # the obstacle comes within dmin of the garment, or passes through it: not free
    assert not pairs.is_step_collision_free(mesh, x0, obstacle_to(-0.2 * DHAT), dmin, ccd)
    assert not pairs.is_step_collision_free(mesh, x0, obstacle_to(DHAT), dmin, ccd)
    assert pairs.is_step_collision_free(mesh, x0, obstacle_to(-0.2 * DHAT), 0.1 * dmin, ccd)
    # the garment moves: its own pairs are checked (the layers start closer than dmin)
    x1 = x0.copy()
    x1[:n, 0] += 1e-4
    assert not pairs.is_step_collision_free(mesh, x0, np.asfortranarray(x1), dmin, ccd)
    assert pairs.is_step_collision_free(mesh, x0, np.asfortranarray(x1), 0.1 * dmin, ccd)
