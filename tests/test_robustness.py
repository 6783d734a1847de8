"""Stiff and extreme cases: far from the origin, tiny scales, degenerate and coplanar
triangles, split planes, rays from inside closed meshes, glass with extreme IORs, very bright
emitters. No NaN or infinity may reach a pixel."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.scene.model import (Camera, Geometry, Light, RenderSettings, SceneError, Shading,
                                      View, default_material_params)
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.tracer import Tracer
from tests.meshes import grid_plane, look_at, merge, uv_sphere
from tests.test_tracer import single_leaf_tree, two_level_tree


@pytest.fixture(scope="module")
def tracer():
    return Tracer()


def sphere_on_plane():
    sphere = uv_sphere(32, 16, 1.0, (0, 0, 1.0))
    vertices, triangles = merge(sphere, grid_plane(8.0, 4, 0.0))
    ids = np.r_[np.zeros(len(sphere[1])), np.ones(len(triangles) - len(sphere[1]))]
    return vertices, triangles, ids.astype(np.uint16)


def shading(lights, params=None, colours=((0.8, 0.3, 0.2, 1), (0.7, 0.7, 0.7, 1)), world=(0.1, 0.1, 0.1)):
    return Shading(np.array(colours, np.float32), lights, world, params)


def render(tracer, vertices, triangles, ids, camera, shade, size=(64, 48), tree=None, **settings):
    geometry = Geometry(vertices, triangles, ids)
    tracer.load(Scene.from_parts(geometry, tree if tree is not None else build_kdtree(geometry.vertices, geometry.triangles)))
    # 2 x 2 samples unless a test asks for more: these tests compare pictures of the same
    # samples, which Cycles' final-render defaults (up to 64 x 64, adaptive) only make slower.
    settings = {"samples_per_axis": 2, "adaptive": False, **settings}
    view = View(camera, *size, shade, settings=RenderSettings(**settings))
    passes = tracer.render_tile(view, 0, 0, *size)
    for name, image in passes.items():
        assert np.isfinite(image).all(), f"{name} has NaN/inf"
    return passes["combined"][..., :3]


def reference_scene(offset=0.0, scale=1.0):
    vertices, triangles, ids = sphere_on_plane()
    vertices = vertices.astype(np.float64) * scale + offset
    camera = Camera("PERSP", look_at(np.array([0, -6, 3]) * scale + offset,
                                     np.array([0, 0, 0.8]) * scale + offset),
                    (0.6, 0.45), (0, 0), 0.05 * scale, 100.0 * scale)
    # Point light power scales with area (W -> same irradiance at the scaled distance).
    lights = [Light("POINT", (1, 1, 1), 400.0 * scale * scale, tuple(np.array([2, -2, 4.0]) * scale + offset)),
              Light("SUN", (1, 1, 1), 1.5, direction=(-0.3, 0.4, -1.0))]
    return vertices, triangles, ids, camera, shading(lights)


def test_far_from_origin_and_tiny_scale(tracer):
    """1e5 from the origin and scaled to 1e-4: the same picture, no self-shadowing acne."""
    base = render(tracer, *reference_scene())
    for offset, scale in ((1e5, 1.0), (0.0, 1e-4)):
        image = render(tracer, *reference_scene(offset, scale))
        lit = base.mean(-1) > 0.05
        darker = image.mean(-1)[lit] < 0.5 * base.mean(-1)[lit]
        assert darker.mean() < 0.01, f"offset {offset} scale {scale}: {darker.mean():.2%} acne"
        # float32 vertices at 1e5 are quantised to 1/128: silhouettes move by a pixel or so.
        assert np.median(np.abs(image - base)) < 0.01
        assert np.mean(np.abs(image - base) > 0.1) < 0.06


def test_slivers_zero_area_and_duplicates(tracer):
    """Zero-area and sliver triangles never produce NaN; duplicate coplanar triangles render
    as one (ties to the lower index, no shadow acne between them)."""
    vertices, triangles = grid_plane(4.0, 2, 0.0)
    camera = Camera("PERSP", look_at((0.3, -3, 3), (0, 0, 0)), (0.6, 0.45), (0, 0), 0.05, 100)
    lights = [Light("POINT", (1, 1, 1), 300.0, (0.5, -1, 2)), Light("SUN", (1, 1, 1), 1.0, direction=(0.2, 0.3, -1))]
    shade = shading(lights, colours=((0.7, 0.7, 0.7, 1), (0.2, 0.2, 0.9, 1)))
    ids = np.zeros(len(triangles), np.uint16)
    base = render(tracer, vertices, triangles, ids, camera, shade)
    extra = np.array([[0, 0, 0.5], [0, 0, 0.5], [1, 1, 0.5],          # repeated vertex
                      [-1, -1, 0.3], [0, 0, 0.3], [1, 1, 0.3],        # collinear
                      [-1, 0, 0.4], [1, 0, 0.4], [0, 1e-7, 0.4]],     # sliver
                     np.float32)
    v2 = np.vstack([vertices, extra])
    t2 = np.vstack([triangles, np.arange(len(vertices), len(v2), dtype=np.uint32).reshape(3, 3)])
    image = render(tracer, v2, t2, np.zeros(len(t2), np.uint16), camera, shade)
    assert np.mean(np.abs(image - base) > 0.05) < 0.02
    # Every triangle twice, the copies with another material: the lower index wins everywhere.
    dup = render(tracer, np.vstack([vertices, vertices]),
                 np.vstack([triangles, triangles + len(vertices)]),
                 np.r_[ids, np.ones(len(triangles), np.uint16)], camera, shade)
    np.testing.assert_allclose(dup, base, atol=1e-6)


def test_split_planes_camera_on_plane_and_axis_aligned_rays(tracer):
    """Triangles lying in split planes, a camera on a split plane, rays along the axes: the same
    pixels with a single leaf, a hand-made split through the camera and the real kd-tree."""
    floor = grid_plane(4.0, 4, 0.0)
    wall = (np.array([[0, -2, 0], [0, 2, 0], [0, 0, 2]], np.float32), np.array([[0, 1, 2]], np.uint32))
    vertices, triangles = merge(floor, wall)
    ids = np.zeros(len(triangles), np.uint16)
    lights = [Light("SUN", (1, 1, 1), 2.0, direction=(0.4, 0.3, -1))]
    cameras = [Camera("ORTHO", look_at((0, -5, 1), (0, 0, 1)), (3, 3), (0, 0), 0.01, 100),   # on x = 0
               Camera("ORTHO", look_at((0.5, 0.5, 5), (0.5, 0.5, 0), up=(0, 1, 0)), (3, 3), (0, 0), 0.01, 100),
               Camera("PERSP", look_at((0, -5, 1), (0, 0, 1)), (0.8, 0.8), (0, 0), 0.01, 100)]
    for camera in cameras:
        images = [render(tracer, vertices, triangles, ids, camera, shading(lights, colours=((0.8, 0.8, 0.8, 1),)),
                         tree=tree)
                  for tree in (single_leaf_tree(vertices, triangles),
                               two_level_tree(vertices, triangles, 0, 0.0),
                               two_level_tree(vertices, triangles, 2, 0.0),
                               build_kdtree(vertices, triangles))]
        for other in images[1:]:
            np.testing.assert_array_equal(other, images[0])


def closed_meshes():
    # A cube and a UV sphere with welded poles: every edge is shared by two triangles.
    cube_v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float32)
    cube_t = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                       [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.uint32)
    return {"cube": (cube_v, cube_t), "sphere": uv_sphere(24, 12, 1.3, (0.1, -0.2, 0.05))}


@pytest.mark.parametrize("name", ["cube", "sphere"])
def test_closed_mesh_from_inside_no_ray_escapes(tracer, name):
    vertices, triangles = closed_meshes()[name]
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16))
    centre = vertices.mean(0)
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    targets = np.concatenate([vertices, vertices[edges].mean(1),
                              np.einsum("eij,i->ej", vertices[edges], np.float32([0.3, 0.7]))])
    for tree in (build_kdtree(geometry.vertices, geometry.triangles), single_leaf_tree(vertices, triangles)):
        tracer.load(Scene.from_parts(geometry, tree))
        for origin in (centre, centre + np.float32([0.01, 0.02, -0.03]), np.float32([0, 0, 0])):
            directions = targets - origin
            hits = tracer.intersect(np.tile(origin, (len(targets), 1)), directions)
            assert (hits.triangle >= 0).all(), f"{(hits.triangle < 0).sum()} rays escaped"
            np.testing.assert_allclose(hits.t, 1.0, rtol=1e-4)


def glass_scene(ior, with_glass=True, emission=0.0):
    floor = grid_plane(8.0, 2, 0.0)
    cube_v, cube_t = closed_meshes()["cube"]
    meshes = [floor, (cube_v * 0.7 + np.float32([0, 0, 1.0]), cube_t)] if with_glass else [floor]
    vertices, triangles = merge(*meshes)
    ids = np.r_[np.zeros(len(floor[1])), np.ones(len(triangles) - len(floor[1]))].astype(np.uint16)
    params = default_material_params(2)
    params[1, :9] = [0.0, 0.0, 1.0, ior, emission, emission, emission, 0.5, -1]
    if emission:
        params[1, 2] = 0.0
    camera = Camera("PERSP", look_at((0.5, -5, 4), (0, 0, 0.5)), (0.5, 0.4), (0, 0), 0.05, 100)
    lights = [Light("SUN", (1, 1, 1), 2.0, direction=(-0.3, 0.4, -1)), Light("POINT", (1, 1, 1), 300.0, (2, -2, 4))]
    colours = ((0.6, 0.7, 0.5, 1), (1, 1, 1, 1))
    return vertices, triangles, ids, camera, shading(lights, params, colours)


def test_glass_ior_one_is_invisible(tracer):
    """Glass of IOR 1 neither bends nor dims what is seen through it (here an emissive floor
    without lights; glass blocks shadow rays, as in Cycles, so lit scenes differ)."""
    def emissive_floor(with_glass):
        vertices, triangles, ids, camera, shade = glass_scene(1.0, with_glass=with_glass)
        shade.lights = []
        shade.world_color = (0.0, 0.0, 0.0)
        shade.material_params[0, 4:7] = (0.6, 0.7, 0.5)
        return vertices, triangles, ids, camera, shade
    plain = render(tracer, *emissive_floor(False), max_bounces=8, samples_per_axis=1, adaptive=False)
    glass = render(tracer, *emissive_floor(True), max_bounces=8, samples_per_axis=1, adaptive=False)
    assert plain.max() > 0.4
    assert np.abs(glass - plain).max() < 2e-3


def test_glass_ior_three_and_bright_emitter(tracer):
    image = render(tracer, *glass_scene(3.0), samples_per_axis=2, max_bounces=16)
    assert image.max() > 0
    bright = render(tracer, *glass_scene(1.5, emission=1e6), samples_per_axis=4, adaptive=True,
                    max_bounces=4, diffuse_bounces=1)
    assert bright.max() >= 1e5


def test_flat_scene_and_flat_cells(tracer):
    """Everything in one plane: a flat root box and flat cells; grazing and perpendicular rays."""
    vertices, triangles = grid_plane(4.0, 8, 0.0)
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16))
    tree = build_kdtree(geometry.vertices, geometry.triangles)
    tracer.load(Scene.from_parts(geometry, tree))
    rng = np.random.default_rng(3)
    origins = np.c_[rng.uniform(-1.9, 1.9, (500, 2)), np.full(500, 1.0)].astype(np.float32)
    hits = tracer.intersect(origins, np.tile(np.float32([0, 0, -1]), (500, 1)))
    assert (hits.triangle >= 0).all() and np.allclose(hits.t, 1.0)
    grazing = tracer.intersect(np.float32([[-3, 0.1, 0], [0.3, 0.3, 0]]), np.float32([[1, 0, 0], [0, 1, 0]]))
    assert not np.isnan(grazing.t).any()
    image = render(tracer, vertices, triangles, np.zeros(len(triangles), np.uint16),
                   Camera("PERSP", look_at((0, -4, 2), (0, 0, 0)), (0.6, 0.45), (0, 0), 0.05, 100),
                   shading([Light("SUN", (1, 1, 1), 1.0, direction=(0, 0, -1))], colours=((0.5, 0.5, 0.5, 1),)),
                   tree=tree)
    assert image.max() > 0.1


def test_bad_geometry_is_rejected_with_a_message():
    vertices, triangles = grid_plane(2.0, 1, 0.0)
    vertices[0, 1] = np.nan
    with pytest.raises(SceneError, match="NaN"):
        Scene.from_parts(Geometry(vertices, triangles, np.zeros(2, np.uint16)),
                         single_leaf_tree(np.nan_to_num(vertices), triangles))
