"""MeshProximity: exact closest points and pseudo-normal signed distances, the tree built once."""

from __future__ import annotations

import gc

import igl
import numpy as np
import pytest
import trimesh

from torchgarment.errors import InputError, MeshError
from torchgarment.sdf import MeshProximity, SignType, exact_signed_distance, winding_number


@pytest.fixture(scope="module")
def blob():
    """A closed, non-convex mesh: a sphere with a dent and a bump (so vertices, edges and faces of both
    curvatures are closest features)."""
    m = trimesh.creation.icosphere(subdivisions=3)
    v = m.vertices * (1.0 + 0.3 * np.sin(3 * m.vertices[:, [0]]) * np.cos(2 * m.vertices[:, [1]]))
    return np.asarray(v), np.asarray(m.faces, dtype=np.int64)


def test_matches_libigl_and_the_winding_number(blob):
    v, f = blob
    rng = np.random.default_rng(0)
    p = np.concatenate([rng.uniform(-1.5, 1.5, (3000, 3)), v[:50] + 1e-3 * rng.normal(size=(50, 3)),
                        0.5 * (v[f[:50, 0]] + v[f[:50, 1]]) * 1.001])
    tree = MeshProximity(v, f)
    d, c, out = tree.query(p)
    ref = igl.signed_distance(p, v, f, sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)
    # the closest triangle is found in float32: where two triangles sharing no edge or vertex are within
    # float32 rounding of the same distance (a point on the medial axis), either may be picked; the distance
    # is then within 1e-7 of libigl's (coordinates of magnitude 1) and its closest point is the other one
    same = np.abs(d - ref[0]) <= 1e-12
    assert np.all(np.abs(d - ref[0]) <= 1e-7) and same.mean() > 0.99 and np.array_equal(d < 0, ref[0] < 0)
    assert np.allclose(c[same], ref[2][same], atol=1e-12)
    assert np.allclose(np.linalg.norm(p - c, axis=1), np.abs(d), rtol=0, atol=1e-12)
    assert np.allclose(igl.signed_distance(c, v, f)[0], 0.0, atol=1e-12)  # every closest point is on the mesh
    # stable: the closest triangle in float64 among those the float32 search could return, so libigl's
    # distance to rounding everywhere, and the triangle that closest_triangles names
    ds, cs, _ = tree.query(p, stable=True)
    assert np.all(np.abs(ds - ref[0]) <= 1e-12) and np.all(np.abs(ds) <= np.abs(d))
    assert np.allclose(ds[same], d[same], rtol=0, atol=1e-12) and np.array_equal(ds < 0, d < 0)
    tri = tree.closest_triangles(p)  # the triangle each stable closest point lies on
    on_tri = trimesh.triangles.closest_point(v[f[tri]], p)
    assert np.allclose(on_tri, cs, atol=1e-12)
    inside = np.abs(winding_number(p, v, f, SignType.WINDING_NUMBER)) > 0.5
    assert np.array_equal(d < 0, inside)  # exact for a closed manifold
    assert np.allclose(np.linalg.norm(out, axis=1), 1.0)
    assert np.allclose(c + d[:, None] * out, p, atol=1e-9)  # outward: towards the point outside, away inside
    assert np.allclose(exact_signed_distance(p, v, f, SignType.PSEUDONORMAL), d)


def test_points_on_the_surface_and_refusals(blob):
    v, f = blob
    d, c, out = MeshProximity(v, f).query(v[:20])
    assert np.allclose(d, 0.0, atol=1e-12) and np.allclose(c, v[:20])
    assert np.all((out * (v[:20] / np.linalg.norm(v[:20], axis=1, keepdims=True))).sum(1) > 0.3)  # outward
    assert MeshProximity(v, f).query(np.zeros((0, 3)))[0].shape == (0,)
    with pytest.raises(MeshError):
        MeshProximity(v, np.zeros((0, 3), dtype=np.int64))


def test_near_is_the_exact_distance_within_the_radius(blob):
    v, f = blob
    p = np.random.default_rng(1).uniform(-1.4, 1.4, (4000, 3))
    ref = np.sqrt(igl.point_mesh_squared_distance(p, v, f)[0])
    r = 0.08
    near = MeshProximity(v, f).near(p, r)
    within = ref <= r
    assert within.sum() > 200 and (~within).sum() > 200
    assert np.allclose(near[within], ref[within], rtol=0, atol=1e-12)  # the exact minimum, no float32 tie
    assert np.all(near[~within] > r) and np.all(near >= ref - 1e-12)  # beyond r: an upper bound above r
    assert MeshProximity(v, f).near(np.zeros((0, 3)), r).shape == (0,)
    with pytest.raises(InputError):
        MeshProximity(v, f).near(p, -1.0)


def test_a_released_tree_is_refitted_for_the_next_mesh_and_never_shared(blob):
    v, f = blob
    f = np.ascontiguousarray(f[:, [1, 2, 0]])  # the same mesh, a topology no other test has pooled
    p = np.random.default_rng(2).uniform(-1.5, 1.5, (2000, 3))
    meshes = [v, 1.3 * v + 0.1, 0.7 * v[:, [1, 0, 2]]]

    def reference(w: np.ndarray) -> np.ndarray:
        return igl.signed_distance(p, w, f, sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)[0]

    a, b = MeshProximity(meshes[0], f), MeshProximity(meshes[1], f)
    assert a._tree._tree is not b._tree._tree  # two live instances, two trees
    first = a._tree._tree
    del a
    gc.collect()
    c = MeshProximity(meshes[2], f)
    assert c._tree._tree is first  # the released tree, refitted
    for tree, w in ((b, meshes[1]), (c, meshes[2])):
        assert np.all(np.abs(tree.query(p)[0] - reference(w)) <= 1e-7 * (1 + np.abs(w).max()))
    # stable queries do not depend on the hierarchy: the refitted tree answers as a fresh one, to the bit
    fresh = MeshProximity(meshes[2], f)  # b and c hold the pooled trees: a new one, built on this mesh
    assert fresh._tree._tree is not c._tree._tree
    for x, y in zip(c.query(p, stable=True), fresh.query(p, stable=True)):
        assert np.array_equal(x, y)


def test_pooled_trees_under_threads(blob):
    """Threads that build, query and release meshes of one topology at once each get their own tree."""
    from concurrent.futures import ThreadPoolExecutor

    v, f = blob
    f = np.ascontiguousarray(f[:, [2, 0, 1]])  # a topology of this test only
    p = np.random.default_rng(3).uniform(-1.5, 1.5, (500, 3))
    scales = [0.8 + 0.1 * i for i in range(4)]
    expected = [igl.signed_distance(p, s * v, f, sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)[0]
                for s in scales]

    def worst(i: int) -> float:
        err = 0.0
        for _ in range(10):
            err = max(err, float(np.abs(MeshProximity(scales[i] * v, f).query(p)[0] - expected[i]).max()))
        return err

    with ThreadPoolExecutor(4) as ex:
        assert max(ex.map(worst, range(4))) <= 1e-6
