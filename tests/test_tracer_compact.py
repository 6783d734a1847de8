"""The OpenCL traversal of the compact kd-tree layout (issue 3): all three modes (standard, choi,
ours) against brute force through the same kernel, and pixel-identical tiles across the modes.

Brute force here is the tracer itself over a one-leaf tree holding every triangle: the same
watertight test on the same float32 rays, so nearest triangle and distance must agree exactly
(bit for bit), ties included (to the lower triangle index). The float64 reference traversal of
the layout is tests/test_kdtree_compact.py `trace_compact`.
"""
from __future__ import annotations

import functools

import numpy as np
import pytest

from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.accel.compact import MODES, CompactTree, compact_tree
from kdtrace.core.scene.model import (Camera, Geometry, Light, RenderSettings, SceneError, Shading,
                                      View)
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.tracer import RayHits, Tracer, TracerError
from tests.meshes import grid_plane, load_bunny, merge, uv_sphere
from tests.scenes_architecture import architecture_scene
from tests.test_kdtree_compact import random_rays

SCENES = {
    "sphere": lambda: uv_sphere(48, 24),
    "bunny": load_bunny,
    "architecture": lambda: architecture_scene(rooms=(3, 2), floors=2, seed=3),
}
RAYS = 12_000


@pytest.fixture(scope="module")
def tracer():
    return Tracer()


def one_leaf(triangle_count, vertices):
    """Every triangle in one 32-bit leaf of the compact layout: the kernel's brute force."""
    return CompactTree(np.array([[3 | (triangle_count << 3), 0]], np.uint32),
                       np.arange(triangle_count, dtype=np.uint32), np.zeros(0, np.uint16),
                       np.array([vertices.min(0), vertices.max(0)], np.float32), 0)


@functools.lru_cache(maxsize=None)
def scene(name):
    vertices, triangles = SCENES[name]()
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16))
    tree = build_kdtree(vertices, triangles)
    corners = vertices.astype(np.float64)[triangles.astype(np.int64)]
    origins, directions = random_rays(corners, RAYS, seed=7 + len(name))
    return geometry, tree, origins.astype(np.float32), directions.astype(np.float32)


@functools.lru_cache(maxsize=None)
def brute(name):
    geometry, _, origins, directions = scene(name)
    t = Tracer()
    t.load(Scene.from_parts(geometry, one_leaf(geometry.triangle_count, geometry.vertices)))
    return t.intersect(origins, directions)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("name", list(SCENES))
def test_modes_match_brute_force(tracer, name, mode):
    geometry, tree, origins, directions = scene(name)
    ct = compact_tree(tree, geometry.triangle_count, mode)
    tracer.load(Scene.from_parts(geometry, ct))
    hits = tracer.intersect(origins, directions)
    ref = brute(name)
    assert np.isfinite(ref.t).mean() > 0.3, "the rays should hit often"
    wrong = np.flatnonzero(hits.triangle != ref.triangle)
    assert not len(wrong), (f"{len(wrong)} rays found another triangle, e.g. ray {wrong[0]}: "
                            f"{hits.triangle[wrong[0]]} at {hits.t[wrong[0]]!r} instead of "
                            f"{ref.triangle[wrong[0]]} at {ref.t[wrong[0]]!r}")
    assert np.array_equal(hits.t, ref.t)
    assert np.array_equal(hits.u, ref.u) and np.array_equal(hits.v, ref.v)


def camera_fan(geometry, count, seed):
    """Coherent rays as a camera makes them (one origin, neighbouring directions in rows),
    the kind the packets are for; origin outside the scene, looking at its centre."""
    rng = np.random.default_rng(seed)
    lo, hi = geometry.vertices.min(0), geometry.vertices.max(0)
    centre, size = (lo + hi) / 2, float(np.abs(hi - lo).max())
    away = rng.normal(size=3)
    eye = centre + 1.5 * size * away / np.linalg.norm(away)
    forward = (centre - eye) / np.linalg.norm(centre - eye)
    right = np.cross(forward, rng.normal(size=3))
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    side = int(np.ceil(np.sqrt(count)))
    s = ((np.arange(side) + 0.5) / side - 0.5) * 0.7
    x, y = np.meshgrid(s, s)
    directions = forward + x.reshape(-1, 1) * right + y.reshape(-1, 1) * up
    origins = np.broadcast_to(eye, directions.shape)
    return origins[:count].astype(np.float32), directions[:count].astype(np.float32)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("name", list(SCENES))
def test_packets_match_the_one_ray_kernel(name, mode):
    """intersect_rays with 8 rays per work-item (CPU devices: a packet where the rays share
    the direction octant, else trace_ray one after another) gives the same bits as one ray
    per work-item: rays of one octant from scattered origins (the packet's lanes disagree on
    the child order), incoherent rays, camera rays, rays starting inside the scene, rays
    straight down through vertices (edge functions exactly 0, ties between the triangles
    sharing the vertex), ray counts that leave a packet part-full, tmin/tmax. The rays are
    traced in the order given (no reordering of scattered rays)."""
    geometry, tree, origins, directions = scene(name)
    tracer = Tracer("cpu")
    assert tracer.packet == 8
    tracer.reorder_rays = False
    tracer.load(Scene.from_parts(geometry, compact_tree(tree, geometry.triangle_count, mode)))
    cam_o, cam_d = camera_fan(geometry, 4099, seed=len(name))
    size = float(np.abs(geometry.vertices.max(0) - geometry.vertices.min(0)).max())
    inside_o = np.repeat(((geometry.vertices.min(0) + geometry.vertices.max(0)) / 2)[None], 500, 0)
    down_o = geometry.vertices[:2000] + np.float32([0, 0, size])
    down_d = np.repeat(np.float32([[0, 0, -1]]), len(down_o), 0)
    one_octant = np.abs(directions)
    cases = [(origins, one_octant, 0.0, np.inf), (origins, directions, 0.0, np.inf),
             (cam_o, cam_d, 0.0, np.inf),
             (down_o, down_d, 0.0, np.inf),
             (inside_o, directions[:500], 0.0, np.inf), (origins[:9], directions[:9], 0.0, np.inf),
             (origins[:1], directions[:1], 0.0, np.inf), (cam_o, cam_d, 1.2 * size, 1.5 * size)]
    for o, d, tmin, tmax in cases:
        tracer.packet = 8
        packets = tracer.intersect(o, d, tmin, tmax)
        tracer.packet = 0
        single = tracer.intersect(o, d, tmin, tmax)
        assert len(o) < 10 or (single.triangle >= 0).mean() > 0.02
        for field in RayHits._fields:
            ours, ref = getattr(packets, field), getattr(single, field)
            differ = np.flatnonzero(ours.view(np.uint32) != ref.view(np.uint32))
            assert not len(differ), (f"{len(differ)} of {len(o)} rays differ in {field}, e.g. "
                                     f"ray {differ[0]}: {ours[differ[0]]!r} vs {ref[differ[0]]!r}")


def shadow_rays(geometry, count, seed):
    """Rays from random points just off random triangles to random points of others, with
    tmax = 1 - 1e-4 (direction = target - origin): about half are blocked."""
    rng = np.random.default_rng(seed)
    corners = geometry.vertices.astype(np.float64)[geometry.triangles.astype(np.int64)]

    def points():
        tri = rng.integers(0, len(corners), count)
        return np.einsum("tk,tkd->td", rng.dirichlet(np.ones(3), count), corners[tri]), tri
    start, tri = points()
    normal = np.cross(corners[tri, 1] - corners[tri, 0], corners[tri, 2] - corners[tri, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    size = float(np.abs(geometry.vertices.max(0) - geometry.vertices.min(0)).max())
    end, _ = points()
    side = np.sign(np.sum((end - start) * normal, 1, keepdims=True))
    origins = start + side * normal * (1e-4 * size)
    return origins.astype(np.float32), (end - origins).astype(np.float32)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("name", list(SCENES))
def test_occluded_is_whether_intersect_hits(name, mode):
    """Tracer.occluded (any hit: the traversal stops at the first hit it finds) says exactly
    whether brute force finds a hit in [tmin, tmax]: shadow rays between surface points,
    random rays, a tmin/tmax window, camera rays; 8-ray packets and one ray per work-item,
    in the given and in the origins' order."""
    geometry, tree, origins, directions = scene(name)
    tracer = Tracer("cpu")
    tracer.load(Scene.from_parts(geometry, compact_tree(tree, geometry.triangle_count, mode)))
    reference = Tracer("cpu")
    reference.load(Scene.from_parts(geometry, one_leaf(geometry.triangle_count, geometry.vertices)))
    shadow_o, shadow_d = shadow_rays(geometry, 6000, seed=len(name))
    cam_o, cam_d = camera_fan(geometry, 4099, seed=len(name))
    size = float(np.abs(geometry.vertices.max(0) - geometry.vertices.min(0)).max())
    cases = [(shadow_o, shadow_d, 0.0, 1 - 1e-4), (origins, directions, 0.0, np.inf),
             (origins, directions, 0.3 * size, 0.6 * size), (cam_o, cam_d, 0.0, np.inf),
             (shadow_o[:13], shadow_d[:13], 0.0, 1 - 1e-4)]
    blocked = []
    for o, d, tmin, tmax in cases:
        expected = reference.intersect(o, d, tmin, tmax).triangle >= 0
        blocked.append(expected)
        for packet, reorder in ((8, True), (8, False), (0, False)):
            tracer.packet, tracer.reorder_rays = packet, reorder
            hit = tracer.occluded(o, d, tmin, tmax)
            assert hit.dtype == np.bool_ and hit.shape == (len(o),)
            wrong = np.flatnonzero(hit != expected)
            assert not len(wrong), (f"packet {packet}, reorder {reorder}: {len(wrong)} of "
                                    f"{len(o)} rays, e.g. ray {wrong[0]}: {hit[wrong[0]]}")
    assert 0.1 < np.concatenate(blocked).mean() < 0.9


def test_scattered_rays_are_traced_in_origin_order(tracer):
    """intersect() traces rays in scattered order (consecutive origins far apart) in their
    origins' Morton order and gives every ray its own result back; coherent rays (one origin)
    and small queries keep their order."""
    from kdtrace.slave.tracer import MIN_REORDERED_RAYS, ray_order
    geometry, tree, origins, directions = scene("bunny")
    bounds = np.array([geometry.vertices.min(0), geometry.vertices.max(0)])
    order = ray_order(origins, bounds)
    assert order is not None and np.array_equal(np.sort(order), np.arange(len(origins)))
    key_steps = np.abs(np.diff(origins[order], axis=0)).max(1).mean()
    assert key_steps < 0.2 * np.abs(np.diff(origins, axis=0)).max(1).mean()
    cam_o, cam_d = camera_fan(geometry, 5000, seed=1)
    assert ray_order(cam_o, bounds) is None
    assert ray_order(origins[:MIN_REORDERED_RAYS - 1], bounds) is None
    tracer.load(Scene.from_parts(geometry, compact_tree(tree, geometry.triangle_count, "compressed")))
    results = []
    for reorder in (True, False):
        tracer.reorder_rays = reorder
        results.append(tracer.intersect(origins, directions))
    tracer.reorder_rays = True
    for field in RayHits._fields:
        assert np.array_equal(getattr(results[0], field).view(np.uint32),
                              getattr(results[1], field).view(np.uint32)), field


def test_plain_tree_is_loaded_as_standard(tracer):
    """A scene of a plain KDTree is laid out in mode standard (README's ray-query API)."""
    geometry, tree, origins, directions = scene("sphere")
    tracer.load(Scene.from_parts(geometry, tree))
    plain = tracer.intersect(origins, directions)
    tracer.load(Scene.from_parts(geometry, compact_tree(tree, geometry.triangle_count, "standard")))
    standard = tracer.intersect(origins, directions)
    assert np.array_equal(plain.triangle, standard.triangle)
    assert np.array_equal(plain.t, standard.t)


def test_16bit_leaves_with_a_shift(tracer):
    """> 65,536 triangles: 16-bit leaves with a nonzero leaf_shift in the kernel."""
    rng = np.random.default_rng(5)
    count = 70_000
    centres = rng.uniform(-1, 1, (count, 1, 3))
    vertices = (centres + rng.normal(scale=0.01, size=(count, 3, 3))).reshape(-1, 3)
    vertices = vertices.astype(np.float32)
    triangles = np.arange(3 * count, dtype=np.uint32).reshape(-1, 3)
    geometry = Geometry(vertices, triangles, np.zeros(count, np.uint16))
    tree = build_kdtree(vertices, triangles)
    ct = compact_tree(tree, count, "compressed")
    assert ct.leaf_shift == 1 and ct.stats["leaves_16bit"] > 0
    origins = rng.uniform(-1.5, 1.5, (1000, 3)).astype(np.float32)
    directions = (rng.uniform(-1, 1, (1000, 3)) - origins).astype(np.float32)
    tracer.load(Scene.from_parts(geometry, ct))
    hits = tracer.intersect(origins, directions)
    t = Tracer()
    t.load(Scene.from_parts(geometry, one_leaf(count, vertices)))
    ref = t.intersect(origins, directions)
    assert np.isfinite(ref.t).mean() > 0.3
    assert np.array_equal(hits.triangle, ref.triangle) and np.array_equal(hits.t, ref.t)


def small_scene():
    """A sphere on a plane with a box beside it: shadows, a mirror bounce, two materials."""
    sphere_v, sphere_t = uv_sphere(40, 20, 1.0, (0, 0, 1.0))
    plane_v, plane_t = grid_plane(8.0, 16, 0.0)
    v, t = merge((sphere_v, sphere_t), (plane_v, plane_t))
    mats = np.zeros(len(t), np.uint16)
    mats[len(sphere_t):] = 1
    return Geometry(v, t, mats)


def test_render_tile_identical_across_modes(tracer):
    geometry = small_scene()
    tree = build_kdtree(geometry.vertices, geometry.triangles)
    m = np.eye(4)
    m[:3, 3] = (0.5, -6.0, 3.0)
    angle = np.radians(70)
    m[:3, :3] = np.array([[1, 0, 0], [0, np.cos(angle), -np.sin(angle)],
                          [0, np.sin(angle), np.cos(angle)]])
    lights = [Light("POINT", (1, 1, 1), 600.0, (2, -2, 4), radius=0.2),
              Light("SUN", (1, 0.9, 0.8), 2.0, direction=(-0.3, 0.2, -1))]
    materials = np.array([[0.8, 0.3, 0.2, 1], [0.7, 0.7, 0.7, 1]], np.float32)
    settings = RenderSettings(samples_per_axis=2, max_bounces=2)
    view = View(Camera("PERSP", m, (0.6, 0.6), (0, 0), 0.1, 100), 64, 64,
                Shading(materials, lights, (0.1, 0.2, 0.3)), settings=settings)
    images = {}
    for mode in MODES:
        tracer.load(Scene.from_parts(geometry, compact_tree(tree, geometry.triangle_count, mode)))
        images[mode] = tracer.render_tile(view, 0, 0, 64, 64)
    assert (images["standard"]["depth"] < 1e10).mean() > 0.5
    for mode in ("choi", "compressed"):
        for name in ("combined", "depth", "normal"):
            assert np.array_equal(images[mode][name], images["standard"][name]), (mode, name)


def test_bad_compact_trees_are_rejected(tracer):
    geometry, tree, _, _ = scene("sphere")
    ct = compact_tree(tree, geometry.triangle_count, "compressed")
    T = geometry.triangle_count

    def broken(**changes):
        base = dict(nodes=ct.nodes.copy(), leaf_index32=ct.leaf_index32.copy(),
                    leaf_index16=ct.leaf_index16.copy(), bounds=ct.bounds, leaf_shift=ct.leaf_shift)
        base.update(changes)
        return CompactTree(**base)

    slot_owner = next(i for i in range(len(ct.nodes))
                      if (ct.nodes[i, 0] & 3) != 3 and ct.nodes[i, 0] & 4)
    bad_slot = ct.nodes.copy()
    bad_slot[ct.nodes[slot_owner, 0] >> 5, 0] = T
    cycle = ct.nodes.copy()
    cycle[0, 0] = (cycle[0, 0] & 31)          # group 0: points back at the root
    leaf16 = ct.leaf_index16.copy()
    leaf16[:] = 0xFFFF
    cases = [(broken(nodes=bad_slot), "triangle that does not exist"),
             (broken(nodes=cycle), "backwards"),
             (broken(leaf_index16=ct.leaf_index16[:10]), "past the end"),
             (broken(leaf_index16=leaf16), "triangle that does not exist"),
             (broken(leaf_shift=17), "leaf_shift")]
    for bad, message in cases:
        with pytest.raises(SceneError, match=message):
            Scene.from_parts(geometry, bad)


def test_validation_catches_shared_nodes_and_overlapping_leaves_in_any_order():
    # The shortcuts of validate_compact: nodes counted instead of sorted per level, leaves
    # sorted only when out of order, one slice for lists that follow each other.
    from kdtrace.core.accel.validate import validate_compact
    from kdtrace.core.layout import INNER_GROUP, LEAF32_COUNT, LEAF_TAG, LEAF_WIDE, TAG
    geometry, tree, _, _ = scene("bunny")
    T = geometry.triangle_count
    ct = compact_tree(tree, T, "standard")      # 32-bit lists, every node stored
    good = (ct.nodes, ct.leaf_index32, ct.leaf_index16, ct.bounds, ct.leaf_shift, T)
    depth = validate_compact(*good)
    inner = TAG.get(ct.nodes[:, 0]) != LEAF_TAG
    leaf = np.flatnonzero(~inner & (LEAF_WIDE.get(ct.nodes[:, 0]) == 0)
                          & (LEAF32_COUNT.get(ct.nodes[:, 0]) > 0))     # lists not empty
    # Two inner nodes of one level whose children are the same nodes.
    a, b = next((i, i + 1) for i in range(1, len(ct.nodes) - 1) if inner[i] and inner[i + 1])
    shared = ct.nodes.copy()
    shared[b, 0] = (shared[b, 0] & ~np.uint32(INNER_GROUP.put(INNER_GROUP.max))) | (
        shared[a, 0] & np.uint32(INNER_GROUP.put(INNER_GROUP.max)))
    with pytest.raises(ValueError, match="reached more than once"):
        validate_compact(shared, *good[1:])
    # Two leaves sharing their list.
    overlapping = ct.nodes.copy()
    overlapping[leaf[-1], 1] = overlapping[leaf[-2], 1]
    with pytest.raises(ValueError, match="overlap"):
        validate_compact(overlapping, *good[1:])
    # The first leaf's list moved past the others (lists out of order, with a gap): valid.
    first = leaf[0]
    count = int(LEAF32_COUNT.get(ct.nodes[first, 0]))
    start = int(ct.nodes[first, 1])
    moved_nodes = ct.nodes.copy()
    moved_nodes[first, 1] = len(ct.leaf_index32) + 3
    moved = np.concatenate([ct.leaf_index32, np.zeros(3, np.uint32),
                            ct.leaf_index32[start:start + count]])
    assert validate_compact(moved_nodes, moved, *good[2:]) == depth
    moved[-1] = T
    with pytest.raises(ValueError, match="triangle that does not exist"):
        validate_compact(moved_nodes, moved, *good[2:])
