"""core/scene/spatial_order.py: the add-on puts exported triangles in spatial order. Only indices
change: every triangle keeps its material, normals and UVs, and the tracer finds the same hits
(same t, u, v, the same triangle under its new index) on a tree built over the new order."""
from __future__ import annotations

import numpy as np

from kdtrace.core.accel.compact import compact_tree
from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.scene.model import Geometry
from kdtrace.core.scene.scene import Scene
from kdtrace.core.scene.spatial_order import spatial_order
from kdtrace.slave.tracer import Tracer
from tests.meshes import load_bunny
from tests.test_kdtree_compact import random_rays


def shuffled_bunny():
    """The bunny in random triangle order, each triangle with a material and its own corner
    normals and UVs (random values: anything lost or swapped shows)."""
    vertices, triangles = load_bunny()
    rng = np.random.default_rng(3)
    triangles = triangles[rng.permutation(len(triangles))]
    count = len(triangles)
    return Geometry(vertices, triangles, rng.integers(0, 7, count).astype(np.uint16),
                    rng.normal(size=(3 * count, 3)).astype(np.float32),
                    rng.random((3 * count, 2)).astype(np.float32))


def records(geometry):
    """Each triangle with everything that belongs to it, one row each, rows sorted."""
    count = geometry.triangle_count
    rows = np.hstack([geometry.triangles.astype(np.float64),
                      geometry.material_ids[:, None].astype(np.float64),
                      geometry.normals.reshape(count, 9), geometry.uvs.reshape(count, 6)])
    return rows[np.lexsort(rows.T[::-1])]


def first_corner_steps(geometry):
    """Mean distance between consecutive triangles' first corners."""
    first = geometry.vertices[geometry.triangles[:, 0]].astype(np.float64)
    return float(np.linalg.norm(np.diff(first, axis=0), axis=1).mean())


def test_triangles_keep_their_materials_normals_and_uvs():
    geometry = shuffled_bunny()
    ordered, order = spatial_order(geometry)
    assert np.shares_memory(ordered.vertices, geometry.vertices)      # vertices stay as they are
    assert ordered.triangle_count == geometry.triangle_count
    assert not np.array_equal(ordered.triangles, geometry.triangles)
    assert np.array_equal(records(ordered), records(geometry))


def test_neighbours_in_space_are_neighbours_in_memory_and_the_order_is_stable():
    geometry = shuffled_bunny()
    ordered, order = spatial_order(geometry)
    assert first_corner_steps(ordered) < 0.1 * first_corner_steps(geometry)
    again, same_order = spatial_order(geometry)
    assert np.array_equal(order, same_order)
    assert all(np.array_equal(a, b) for a, b in zip(ordered.arrays().values(),
                                                     again.arrays().values()))
    same, none = spatial_order(ordered)                  # in order already: nothing to do
    assert same is ordered and none is None
    single = Geometry(geometry.vertices, geometry.triangles[:1], geometry.material_ids[:1])
    same, none = spatial_order(single)
    assert same is single and none is None
    # A given order (the add-on's last one for the mesh) is applied as it is.
    reversed_order = order[::-1].copy()
    moved, used = spatial_order(ordered, reversed_order)
    assert used is reversed_order
    assert np.array_equal(moved.triangles, ordered.triangles[reversed_order])
    assert np.array_equal(moved.normals.reshape(-1, 9), ordered.normals.reshape(-1, 9)[reversed_order])


def test_the_tracer_finds_the_same_hits_in_the_new_order():
    geometry = shuffled_bunny()
    ordered, order = spatial_order(geometry)
    index_of = {tuple(t): i for i, t in enumerate(geometry.triangles.tolist())}
    old_index = np.array([index_of[tuple(t)] for t in ordered.triangles.tolist()])
    corners = geometry.vertices.astype(np.float64)[geometry.triangles.astype(np.int64)]
    origins, directions = random_rays(corners, 6000, seed=11)
    origins, directions = origins.astype(np.float32), directions.astype(np.float32)
    tracer = Tracer()
    hits = []
    for g in (geometry, ordered):
        tree = compact_tree(build_kdtree(g.vertices, g.triangles), g.triangle_count, "compressed")
        tracer.load(Scene.from_parts(Geometry(g.vertices, g.triangles, g.material_ids), tree))
        hits.append(tracer.intersect(origins, directions))
    before, after = hits
    hit = before.triangle >= 0
    assert 0.3 < hit.mean() < 1.0
    assert np.array_equal(after.triangle >= 0, hit)
    assert np.array_equal(old_index[after.triangle[hit]], before.triangle[hit])
    for field in ("t", "u", "v"):
        assert np.array_equal(getattr(after, field), getattr(before, field))
