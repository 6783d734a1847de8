"""Object motion blur through the top level (docs/instances.md): instances that carry a second
transform (shutter close) are traced, at a ray's time, where the linear blend of the two
transforms puts them. Checked against numpy brute force over the triangles placed by the
blend in float64, at shutter open, close and in between; and the scene's checks (the flag,
the wire, transforms that turn through zero)."""
from __future__ import annotations

import numpy as np
import pytest

from kdtrace.core.accel.compact import compact_tree
from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.scene.model import Camera, Geometry, SceneError, Shading, View
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.tracer import Tracer
from tests.meshes import uv_sphere


def _mesh(vertices, triangles):
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16))
    return geometry, compact_tree(build_kdtree(geometry.vertices, geometry.triangles),
                                  geometry.triangle_count, mode="compressed")


def _turn(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _placements():
    """Transforms at shutter open and close of four instances: one still, one translating,
    one turning and growing, one mirrored and sheared moving diagonally."""
    start, end = np.tile(np.eye(4), (4, 1, 1)), np.tile(np.eye(4), (4, 1, 1))
    start[0, :3, 3] = end[0, :3, 3] = (0.0, 0.0, -6.0)
    start[1, :3, 3], end[1, :3, 3] = (-6.0, 0.0, 0.0), (-2.0, 1.0, 0.0)
    start[2, :3, :3], end[2, :3, :3] = _turn(0.2), _turn(1.3) * 1.6
    start[2, :3, 3] = end[2, :3, 3] = (5.0, 0.0, 0.0)
    shear = np.array([[1.0, 0.4, 0.0], [0.0, -1.0, 0.3], [0.2, 0.0, 1.2]])
    start[3, :3, :3] = end[3, :3, :3] = shear
    start[3, :3, 3], end[3, :3, 3] = (0.0, 5.0, 2.0), (2.0, 3.0, 0.0)
    return start, end


def _brute_force(corners, origins, directions):
    """Nearest (t, triangle) of each ray over world-space triangles (T, 3, 3), float64
    Moeller-Trumbore; (inf, -1) on a miss."""
    o, d = origins[:, None].astype(np.float64), directions[:, None].astype(np.float64)
    v0, e1, e2 = corners[:, 0], corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    p = np.cross(d, e2)
    det = np.einsum("rtk,tk->rt", p, e1)
    inv = 1.0 / np.where(det == 0, np.inf, det)
    s = o - v0
    u = np.einsum("rtk,rtk->rt", s, p) * inv
    q = np.cross(s, e1)
    v = np.einsum("rtk,rtk->rt", d, q) * inv
    t = np.einsum("tk,rtk->rt", e2, q) * inv
    ok = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    t = np.where(ok, t, np.inf)
    nearest = np.argmin(t, axis=1)
    best = t[np.arange(len(t)), nearest]
    return best, np.where(np.isfinite(best), nearest, -1)


@pytest.fixture(scope="module")
def moving():
    sphere_v, sphere_t = uv_sphere(16, 8, radius=1.5)
    cube_v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float32)
    cube_t = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                       [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.uint32)
    meshes = [_mesh(sphere_v, sphere_t), _mesh(cube_v, cube_t)]
    which = [0, 1, 0, 1]
    start, end = _placements()
    return meshes, which, start, end, Scene.from_instances(meshes, which, start, to_world_end=end)


@pytest.mark.parametrize("time", [0.0, 0.35, 1.0])
def test_moving_instances_hit_where_the_blend_places_them(moving, time):
    meshes, which, start, end, scene = moving
    blend = (1 - time) * start + time * end
    corners = np.concatenate([
        meshes[w][0].vertices.astype(np.float64)[meshes[w][0].triangles] @ m[:3, :3].T + m[:3, 3]
        for w, m in zip(which, blend)])
    rng = np.random.default_rng(11)
    n = 3000
    origins = rng.uniform(-12, 12, (n, 3)).astype(np.float32)
    aims = corners[rng.integers(0, len(corners), n)].mean(axis=1)
    directions = (aims + rng.normal(0, 0.6, (n, 3)) - origins).astype(np.float32)
    expected_t, expected_key = _brute_force(corners, origins, directions)

    tracer = Tracer()
    tracer.load(scene)
    hits = tracer.intersect(origins, directions, time=time)
    occluded = tracer.occluded(origins, directions, 0.0, 0.9, time=time)
    inst = scene.instances
    i = np.maximum(hits.instance, 0)
    key = np.where(hits.instance < 0, -1, inst.key_base[i].astype(np.int64) + hits.triangle
                   - inst.mesh_table[inst.mesh[i], 0].astype(np.int64))

    found = expected_key >= 0
    assert 0.3 < found.mean() < 0.95                      # the rays see the moving objects
    assert ((key >= 0) == found).mean() > 0.998           # misses and hits agree but at edges
    both = found & (key >= 0)
    assert (key[both] == expected_key[both]).mean() > 0.995
    assert np.allclose(hits.t[both], expected_t[both], rtol=1e-4, atol=1e-5)
    assert ((expected_t < 0.9) == occluded).mean() > 0.998


def test_motion_scene_flag_wire_and_checks(moving):
    meshes, which, start, end, scene = moving
    view = View(Camera("PERSP", np.eye(4)), 4, 4, Shading())
    assert "OBJECT_MOTION" in scene.features(view)
    still = Scene.from_instances(meshes, which, start, to_world_end=start)
    assert "OBJECT_MOTION" not in still.features(view) and still.instances.to_world_end is None
    assert still.hash == Scene.from_instances(meshes, which, start).hash != scene.hash
    # The shutter-close transforms travel with the scene and with a placement.
    again = Scene.from_wire(scene.wire_arrays())
    assert again.hash == scene.hash and np.array_equal(again.instances.to_world_end,
                                                       scene.instances.to_world_end)
    assert still.placed_from_wire(scene.instance_arrays()).hash == scene.hash
    # The top level bounds both ends: each world box holds the open and the close box.
    close = Scene.from_instances(meshes, which, end).instances.world_bounds
    opened = still.instances.world_bounds
    boxes = scene.instances.world_bounds
    assert (boxes[:, 0] <= np.minimum(opened[:, 0], close[:, 0])).all()
    assert (boxes[:, 1] >= np.maximum(opened[:, 1], close[:, 1])).all()
    # A blend through a half turn passes a singular matrix; NaN is refused.
    half_turn = end.copy()
    half_turn[2, :3, :3] = _turn(np.pi) @ start[2, :3, :3]
    with pytest.raises(SceneError, match="instance 2's transform may become singular"):
        Scene.from_instances(meshes, which, start, to_world_end=half_turn)
    arrays = scene.instance_arrays()
    arrays["instance_to_world_end"] = arrays["instance_to_world_end"].copy()
    arrays["instance_to_world_end"][1, 0, 3] = np.nan
    with pytest.raises(SceneError, match="instance 1's shutter-close transform has NaN"):
        still.placed_from_wire(arrays)
