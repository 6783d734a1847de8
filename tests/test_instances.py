"""Instanced scenes (docs/instances.md) against their realised versions: the same meshes
transformed into world space on the host in float64 and traced as one flat scene with its own
kd-tree. Hits, occlusion and rendered images must agree; bad instance data from the wire must
be refused with a SceneError that names the problem."""
from __future__ import annotations

import numpy as np
import pytest

from kdtrace.core.accel.compact import compact_tree
from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.accel.toplevel import build_toplevel
from kdtrace.core.layout import INSTANCE, TOPLEVEL_LEAF_MAX, TOPLEVEL_MAX_DEPTH
from kdtrace.core.scene.instances import MAX_INSTANCES
from kdtrace.core.scene.model import (MATERIAL_PARAMS, Camera, Geometry, Light, RenderSettings,
                                      SceneError, Shading, View)
from kdtrace.core.scene.scene import Scene, memory_report
from kdtrace.slave.tracer import Tracer
from tests.meshes import grid_plane, load_bunny, look_at, uv_sphere


def _rotation(angle, axis):
    c, s = np.cos(angle), np.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    m = np.eye(3)
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    return m


def _transforms(count, seed, spread=12.0):
    """Rotated and scaled transforms; every 3rd mirrored (negative scale), every 3rd + 1
    sheared."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        m = np.eye(4)
        linear = _rotation(rng.uniform(0, 6.3), i % 3) * rng.uniform(0.6, 1.8)
        if i % 3 == 0:
            linear = linear @ np.diag([1.0, -1.0, 1.0])
        if i % 3 == 1:
            linear = linear @ np.array([[1.0, 0.4, 0.0], [0.0, 1.0, 0.3], [0.2, 0.0, 1.0]])
        m[:3, :3] = linear
        m[:3, 3] = rng.uniform(-spread, spread, 3)
        out.append(m)
    return out


def _sphere_normals(vertices, triangles):
    n = vertices[triangles].reshape(-1, 3).astype(np.float64)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _mesh(vertices, triangles, material=0, normals=None):
    geometry = Geometry(vertices, triangles, np.full(len(triangles), material, np.uint16), normals)
    return geometry, compact_tree(build_kdtree(geometry.vertices, geometry.triangles),
                                  geometry.triangle_count, mode="compressed")


def _realised(meshes, which, matrices):
    """The flat scene of the same instances: world-space triangles in instance order (so a
    triangle's index is the instanced hit's key), normals by the inverse transpose."""
    vertices, triangles, materials, normals, base = [], [], [], [], 0
    smooth = any(g.normals is not None for g, _ in meshes)
    for m, w in zip(matrices, which):
        g = meshes[w][0]
        vertices.append((g.vertices.astype(np.float64) @ m[:3, :3].T + m[:3, 3]).astype(np.float32))
        triangles.append(g.triangles + np.uint32(base))
        materials.append(g.material_ids)
        base += len(g.vertices)
        if smooth:
            from kdtrace.core.scene.features import full_geometry
            n = full_geometry(g).normals.astype(np.float64) @ np.linalg.inv(m[:3, :3])
            normals.append(n / np.linalg.norm(n, axis=1, keepdims=True))
    geometry = Geometry(np.concatenate(vertices), np.concatenate(triangles),
                        np.concatenate(materials), np.concatenate(normals) if smooth else None)
    return Scene.from_parts(geometry, build_kdtree(geometry.vertices, geometry.triangles))


@pytest.fixture(scope="module")
def tracer():
    return Tracer()


@pytest.fixture(scope="module")
def bunny_and_sphere():
    bunny_v, bunny_t = load_bunny()
    sphere_v, sphere_t = uv_sphere(24, 12, radius=2.0)
    return [_mesh(bunny_v * 0.4, bunny_t), _mesh(sphere_v, sphere_t)]


def _key(scene, hits):
    """The realised triangle index of instanced hits (-1: miss)."""
    inst = scene.instances
    i = np.maximum(hits.instance, 0)
    mesh_base = inst.mesh_table[inst.mesh[i], 0].astype(np.int64)
    return np.where(hits.instance < 0, -1, inst.key_base[i] + hits.triangle - mesh_base)


def test_instanced_hits_match_the_realised_scene(tracer, bunny_and_sphere):
    meshes = bunny_and_sphere
    matrices = _transforms(8, seed=3)
    which = [i % 2 for i in range(8)]
    scene = Scene.from_instances(meshes, which, matrices)
    assert scene.instances is not None and "INSTANCES" in scene.features(
        View(Camera("PERSP", np.eye(4)), 4, 4, Shading()))
    realised = _realised(meshes, which, matrices)
    rng = np.random.default_rng(7)
    n = 12000
    origins = rng.uniform(-20, 20, (n, 3)).astype(np.float32)
    targets = realised.geometry.vertices[rng.integers(0, len(realised.geometry.vertices), n)]
    directions = (targets + rng.normal(0, 0.2, (n, 3)) - origins).astype(np.float32)

    tracer.load(realised)
    expected = tracer.intersect(origins, directions)
    expected_occluded = tracer.occluded(origins, directions, 0.0, 0.95)
    tracer.load(scene)
    got = tracer.intersect(origins, directions)
    got_occluded = tracer.occluded(origins, directions, 0.0, 0.95)

    key = _key(scene, got)
    hit = expected.triangle >= 0
    assert hit.sum() > 0.8 * n and (hit == (key >= 0)).all()
    # t within 1e-5 relative: to the hit's distance, or, for origins next to a surface, to
    # the origin's magnitude (the float32 rounding of the ray transformed into object space).
    length = np.linalg.norm(directions[hit], axis=1)
    scale = np.maximum(expected.t[hit] * length, np.abs(origins[hit]).max(axis=1))
    rel = np.abs(got.t[hit] - expected.t[hit]) * length / scale
    same = key[hit] == expected.triangle[hit]
    # Another triangle only where two meet within rounding (a ray through their edge).
    assert same.mean() > 0.9995 and rel[~same].max(initial=0) < 1e-5
    assert rel.max() < 1e-5 and np.percentile(rel, 99) < 1e-6
    assert (got_occluded == expected_occluded).mean() > 0.9995
    assert expected_occluded.sum() > 0.3 * n


def test_instanced_render_matches_the_realised_render(tracer):
    sphere_v, sphere_t = uv_sphere(20, 10, radius=1.0)
    plane_v, plane_t = grid_plane(16.0, 2)
    meshes = [_mesh(plane_v, plane_t, material=0),
              _mesh(sphere_v, sphere_t, material=1, normals=_sphere_normals(sphere_v, sphere_t))]
    matrices = [np.eye(4)] + [m @ np.diag([1.0, 1.0, 0.7, 1.0]) for m in _transforms(5, seed=5, spread=3.0)]
    for m in matrices[1:]:
        m[2, 3] = 1.5
    which = [0] + [1] * 5
    scene = Scene.from_instances(meshes, which, matrices)
    realised = _realised(meshes, which, matrices)
    shading = Shading(np.array([[0.8, 0.8, 0.8, 1.0], [0.9, 0.3, 0.2, 1.0]], np.float32),
                      [Light("SUN", (1.0, 1.0, 1.0), 3.0, direction=(-0.3, -0.2, -1.0))],
                      (0.1, 0.1, 0.12))
    camera = Camera("PERSP", look_at((9.0, -7.0, 8.0), (0.0, 0.0, 1.0)), ndc_scale=(0.6, 0.45))
    view = View(camera, 48, 36, shading, settings=RenderSettings(
        samples_per_axis=2, adaptive=False, max_bounces=1, diffuse_bounces=1))
    tracer.load(realised)
    expected = tracer.render_tile(view, 0, 0, 48, 36)
    tracer.load(scene)
    got = tracer.render_tile(view, 0, 0, 48, 36)
    a, b = expected["combined"][..., :3], got["combined"][..., :3]
    assert a.mean() > 0.05
    diff = np.abs(a - b).max(axis=2)
    psnr = 10 * np.log10(a.max() ** 2 / np.mean((a - b) ** 2)) if (a != b).any() else np.inf
    assert psnr > 60 and (diff < 1e-3).mean() > 0.995, (psnr, (diff < 1e-3).mean())
    assert np.allclose(got["depth"], expected["depth"], rtol=1e-4)
    both = (expected["depth"] < 1e9)
    assert (np.einsum("ijk,ijk->ij", got["normal"], expected["normal"])[both] > 0.999).mean() > 0.99


def test_one_identity_instance_is_the_flat_scene(bunny_and_sphere):
    geometry, tree = bunny_and_sphere[0]
    scene = Scene.from_instances([(geometry, tree)], [0], [np.eye(4)])
    assert scene.instances is None
    assert scene.hash == Scene.from_parts(geometry, tree).hash


def test_instanced_scene_survives_the_wire(bunny_and_sphere):
    scene = Scene.from_instances(bunny_and_sphere, [0, 1, 1], _transforms(3, seed=1))
    again = Scene.from_wire({k: v.copy() for k, v in scene.wire_arrays().items()})
    assert again.hash == scene.hash and again.instances.count == 3
    assert np.array_equal(again.instances.toplevel.nodes, scene.instances.toplevel.nodes)
    assert again.instances.referenced_triangles == \
        bunny_and_sphere[0][0].triangle_count + 2 * bunny_and_sphere[1][0].triangle_count
    report = memory_report(scene)
    assert report["triangles_stored"] == scene.geometry.triangle_count
    assert report["triangles_referenced"] == again.instances.referenced_triangles
    assert report["bytes_top_level"] == scene.instances.toplevel.nodes.nbytes + 3 * INSTANCE.size * 16


def test_moved_instances_are_the_scene_with_those_transforms(bunny_and_sphere):
    scene = Scene.from_instances(bunny_and_sphere, [0, 1, 1], _transforms(3, seed=1))
    moved_to = _transforms(3, seed=9)
    moved = scene.moved(moved_to)
    fresh = Scene.from_instances(bunny_and_sphere, [0, 1, 1], moved_to)
    assert moved.hash == fresh.hash != scene.hash and moved.meshes_hash == scene.meshes_hash
    assert np.array_equal(moved.instances.toplevel.nodes, fresh.instances.toplevel.nodes)
    assert moved.geometry is scene.geometry and moved.tree.nodes is scene.tree.nodes
    with pytest.raises(SceneError, match="2 transforms for 3 instances"):
        scene.moved(moved_to[:2])


@pytest.mark.parametrize("change, message", [
    (lambda a: a["instance_mesh"].__setitem__(1, 7), "uses mesh 7"),
    (lambda a: a["instance_to_world"].__setitem__((2, 0, 3), np.nan), "instance 2's transform has NaN"),
    (lambda a: a["instance_to_world"].__setitem__((0, slice(None), 0), 0.0), "instance 0's transform is singular"),
    (lambda a: a["instance_visibility"].__setitem__(0, 255), "visibility has bits"),
    (lambda a: a["mesh_counts"].__setitem__((0, 1), a["mesh_counts"][0, 1] + 1), "add up to"),
    (lambda a: a.__setitem__("instance_visibility", a["instance_visibility"][:2]), "one each per instance"),
    (lambda a: a.__setitem__("instance_to_world", a["instance_to_world"].astype("<f8")), "instance_to_world"),
])
def test_bad_instance_data_from_the_wire_is_refused(bunny_and_sphere, change, message):
    arrays = {k: v.copy() for k, v in
              Scene.from_instances(bunny_and_sphere, [0, 1, 1], _transforms(3, seed=2)).wire_arrays().items()}
    change(arrays)
    with pytest.raises(SceneError, match=message):
        Scene.from_wire(arrays)


def test_too_many_instances_are_refused(bunny_and_sphere):
    geometry, tree = bunny_and_sphere[1]
    with pytest.raises(SceneError, match=f"1 to {MAX_INSTANCES} instances"):
        Scene.from_instances([(geometry, tree)], np.zeros(MAX_INSTANCES + 1, int),
                             np.broadcast_to(np.eye(4), (MAX_INSTANCES + 1, 4, 4)))


@pytest.mark.parametrize("column", ["emission_r", "program"])
def test_world_space_materials_on_instanced_meshes_are_refused(bunny_and_sphere, column):
    scene = Scene.from_instances(bunny_and_sphere, [0, 1], _transforms(2, seed=4))
    shading = Shading(node_program=[[0, 0, 0, 0], [0, 0, 0, 0]])    # END
    shading.material_params[0, MATERIAL_PARAMS.index(column)] = 1.0 if column != "program" else 0.0
    with pytest.raises(SceneError, match="emissive or node-program materials"):
        scene.check_view(View(Camera("PERSP", np.eye(4)), 4, 4, shading))


@pytest.mark.parametrize("count, same", [(1, False), (5, False), (1000, False), (300, True)])
def test_toplevel_covers_every_instance_once(count, same):
    rng = np.random.default_rng(count)
    centre = np.zeros((count, 3)) if same else rng.uniform(-50, 50, (count, 3))
    lo = (centre - rng.uniform(0.1, 3, (count, 3))).astype(np.float32)
    hi = (centre + rng.uniform(0.1, 3, (count, 3))).astype(np.float32)
    top = build_toplevel(lo, hi)
    assert np.array_equal(build_toplevel(lo, hi).nodes, top.nodes)     # deterministic
    nodes = top.nodes
    first = nodes[:, 0, 3].view(np.uint32).astype(np.int64)
    size = nodes[:, 1, 3].view(np.uint32).astype(np.int64)
    seen, stack, depth = [], [(0, 1)], 0
    while stack:
        node, level = stack.pop()
        depth = max(depth, level)
        box_lo, box_hi = nodes[node, 0, :3], nodes[node, 1, :3]
        if size[node]:
            assert size[node] <= TOPLEVEL_LEAF_MAX
            members = top.order[first[node]:first[node] + size[node]]
            assert (lo[members] >= box_lo).all() and (hi[members] <= box_hi).all()
            seen += list(members)
        else:
            for child in (first[node], first[node] + 1):
                assert (nodes[child, 0, :3] >= box_lo).all() and (nodes[child, 1, :3] <= box_hi).all()
                stack.append((child, level + 1))
    assert sorted(seen) == list(range(count)) and depth == top.depth <= TOPLEVEL_MAX_DEPTH
