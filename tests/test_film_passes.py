"""The passes beside the image (kernels/shade/film.cl, slave/film.py; docs/shading.md "Passes"):
the denoising guides follow Cycles' rules (kernel/film/denoising_passes.h) on analytic scenes
whose answer numpy knows: a diffuse plane seen directly, in a mirror and through a glass slab
gives its albedo, tinted by what the path passed; the world gives its colour and a zero
normal; a Mix Shader's albedo is the mix. The passes change no pixel of the image and are
compiled only when asked for."""
from __future__ import annotations

import numpy as np
import pytest

from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.layout import CLOSURE_CODES
from kdtrace.core.scene.model import (MATERIAL_PARAMS, Camera, Geometry, RenderSettings, Shading,
                                      View, default_material_params)
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.film import CYCLES_CAMERA_AXES, camera_space, fill_untraced
from kdtrace.slave.tracer import Tracer
from tests.meshes import grid_plane, look_at, merge

COLUMN = {name: i for i, name in enumerate(MATERIAL_PARAMS)}
GUIDES = ("combined", "albedo", "denoising_normal")
WALL = np.array([0.7, 0.3, 0.2])


@pytest.fixture(scope="module")
def tracer():
    return Tracer("cpu")


def load(tracer, *meshes_and_ids):
    vertices, triangles = merge(*[m for m, _ in meshes_and_ids])
    ids = np.concatenate([np.full(len(m[1]), i, np.uint16) for m, i in meshes_and_ids])
    geometry = Geometry(vertices, triangles, ids)
    tracer.load(Scene.from_parts(geometry, build_kdtree(geometry.vertices, geometry.triangles)))


def material(base, metallic=0.0, roughness=0.5, transmission=0.0, ior=1.5):
    row = default_material_params(1)[0]
    row[[COLUMN["metallic"], COLUMN["roughness"], COLUMN["transmission"], COLUMN["ior"]]] = \
        metallic, roughness, transmission, ior
    return (*base, 1.0), row


def shading(materials, world=(0.0, 0.0, 0.0)):
    colours, params = zip(*materials)
    return Shading(np.array(colours, np.float32), [], world, np.array(params, np.float32))


def view_of(eye, target, shade, size=8, n=4, fov=0.05, film_transparent=False, up=(0, 0, 1)):
    camera = Camera("PERSP", look_at(eye, target, up), (fov, fov), (0, 0), 0.01, 100)
    return View(camera, size, size, shade, film_transparent=film_transparent, settings=RenderSettings(
        samples_per_axis=n, adaptive=False, max_bounces=12, glossy_bounces=12,
        transmission_bounces=12, clamp_indirect=0.0, filter_glossy=0.0))


def centre(image):
    h, w = image.shape[:2]
    return image[h // 2 - 2:h // 2 + 2, w // 2 - 2:w // 2 + 2].reshape(-1, image.shape[-1]).mean(0)


def wall_facing(y, size=8.0, z=3.0):
    """A vertical plane at y facing -y (towards the origin)."""
    v, t = grid_plane(size, 2)
    v = np.stack([v[:, 0], np.full(len(v), y), v[:, 1] + z], 1).astype(np.float32)
    return v, t[:, ::-1].copy()


def test_a_diffuse_plane_gives_its_albedo_and_its_normal_in_cycles_camera_space(tracer):
    load(tracer, (grid_plane(4.0, 2), 0))
    eye = (0.0, -3.0, 3.0)
    view = view_of(eye, (0, 0, 0), shading([material((0.8, 0.2, 0.1))]))
    passes = tracer.render_tile(view, 0, 0, 8, 8, GUIDES)
    np.testing.assert_allclose(passes["albedo"], np.broadcast_to([0.8, 0.2, 0.1], (8, 8, 3)),
                               rtol=1e-5)
    # Cycles' camera space: x right, y up, z away from the camera (a facing normal: z < 0).
    expected = camera_space(np.array([0.0, 0.0, 1.0]), view.camera.to_world)
    np.testing.assert_allclose(expected, [0, np.sqrt(0.5), -np.sqrt(0.5)], atol=1e-6)
    np.testing.assert_allclose(passes["denoising_normal"],
                               np.broadcast_to(expected, (8, 8, 3)), atol=1e-5)


def test_adaptive_sampling_divides_by_each_pixels_samples_and_fills_skipped_pixels(tracer):
    """Adaptive sampling: each pixel's own sample count divides its sums, and the pixels that
    undersampling filled from their neighbours (no samples) take their guides alike."""
    load(tracer, (grid_plane(4.0, 2), 0))
    view = view_of((0, -3, 3), (0, 0, 0), shading([material((0.8, 0.2, 0.1))], (0.5, 0.5, 0.5)),
                   size=16)
    view.settings = RenderSettings(samples_per_axis=8, adaptive=True, adaptive_threshold=0.5,
                                   adaptive_min_samples=4, undersample=True)
    passes = tracer.render_tile(view, 0, 0, 16, 16, GUIDES)
    assert tracer.last_render["samples"] < 16 * 16 * 64      # it stopped early somewhere
    counts = tracer.last_render["pixel_samples"]              # 1 where undersampling filled
    assert counts.shape == (16, 16) and (counts == 1).any() and counts.max() <= 64
    assert counts[counts > 1].sum() == tracer.last_render["samples"]
    np.testing.assert_allclose(passes["albedo"], np.broadcast_to([0.8, 0.2, 0.1], (16, 16, 3)),
                               rtol=1e-5)
    assert np.allclose(np.linalg.norm(passes["denoising_normal"], axis=-1), 1.0, atol=1e-5)


def test_the_world_gives_its_colour_and_a_zero_normal(tracer):
    load(tracer, (grid_plane(4.0, 2), 0))
    world = (0.3, 0.4, 0.5)
    view = view_of((0, -3, 3), (0, 3, 6), shading([material((0.8, 0.2, 0.1))], world))
    passes = tracer.render_tile(view, 0, 0, 8, 8, GUIDES)
    assert np.array_equal(passes["denoising_normal"], np.zeros((8, 8, 3), np.float32))
    np.testing.assert_allclose(passes["albedo"], np.broadcast_to(world, (8, 8, 3)), rtol=1e-5)
    # Film > Transparent: the camera sees no world, and neither do the guides.
    view.film_transparent = True
    passes = tracer.render_tile(view, 0, 0, 8, 8, GUIDES)
    assert not passes["albedo"].any() and not passes["denoising_normal"].any()


def test_a_plane_seen_in_a_mirror_gives_its_albedo_tinted_by_the_mirror(tracer):
    """A perfect metal mirror (z = 0) at 45 degrees reflects a diffuse wall: the guides pass
    the mirror (a sharp lobe) and write the wall's albedo times the mirror's Fresnel colour,
    and the wall's normal."""
    tint = np.array([0.9, 0.8, 0.5])
    load(tracer, (grid_plane(4.0, 2), 0), (wall_facing(3.0), 1))
    view = view_of((0, -3, 3), (0, 0, 0), shading([material(tint, metallic=1.0, roughness=0.0),
                                                   material(WALL)]))
    passes = tracer.render_tile(view, 0, 0, 8, 8, GUIDES)
    cos_o = np.sqrt(0.5)
    fresnel = tint + (1 - tint) * (1 - cos_o) ** 5      # bsdf.cl metal_fresnel
    np.testing.assert_allclose(centre(passes["albedo"]), fresnel * WALL, rtol=2e-3)
    wall_normal = camera_space(np.array([0.0, -1.0, 0.0]), view.camera.to_world)
    np.testing.assert_allclose(centre(passes["denoising_normal"]), wall_normal, atol=2e-3)


def test_a_plane_seen_through_glass_gives_its_albedo_tinted_by_the_glass(tracer):
    """A glass slab (two sharp interfaces) above a diffuse floor, the world black: the guides
    pass both interfaces, each tinting by its albedo F + (1 - F) sqrt(base) (Cycles' bsdf_albedo
    of a glass closure), and the floor's albedo is written where the path refracted through
    both, (1 - F)^2 of the paths; the floor's normal faces the camera."""
    tint = np.array([0.5, 0.8, 1.0])
    top, bottom = grid_plane(4.0, 2, z=1.0), grid_plane(4.0, 2, z=0.5)
    bottom = (bottom[0], bottom[1][:, ::-1].copy())     # facing down: the slab's outside
    load(tracer, (grid_plane(6.0, 2), 1), (top, 0), (bottom, 0))
    view = view_of((0, 0, 5), (0, 0, 0), shading([material(tint, roughness=0.0, transmission=1.0),
                                                  material(WALL)]), n=16, up=(0, 1, 0))
    passes = tracer.render_tile(view, 0, 0, 8, 8, GUIDES)
    F = ((1.5 - 1) / (1.5 + 1)) ** 2
    interface = F + (1 - F) * np.sqrt(tint)
    expected = (1 - F) ** 2 * interface ** 2 * WALL
    np.testing.assert_allclose(passes["albedo"].reshape(-1, 3).mean(0), expected, rtol=0.02)
    floor_normal = camera_space(np.array([0.0, 0.0, 1.0]), view.camera.to_world)
    np.testing.assert_allclose(floor_normal, [0, 0, -1], atol=1e-6)
    np.testing.assert_allclose(passes["denoising_normal"].reshape(-1, 3).mean(0),
                               (1 - F) ** 2 * floor_normal, atol=0.02)


def test_a_mix_shader_gives_the_mix_of_its_closures_albedo(tracer):
    """Mix Shader at 0.3 of red and blue diffuse: one closure is chosen per sample and the
    guides take its albedo times the scattering weight, so their mean is the mix."""
    load(tracer, (grid_plane(4.0, 2), 0))
    params = default_material_params(2)
    params[:, COLUMN["kind"]] = CLOSURE_CODES["PRINCIPLED"]
    params[:, COLUMN["weight"]] = (0.7, 0.3)
    params[0, COLUMN["closures"]] = 2
    shade = Shading(np.array([[0.9, 0.1, 0.1, 1], [0.1, 0.1, 0.9, 1]], np.float32), [],
                    (0, 0, 0), params)
    view = view_of((0, -3, 3), (0, 0, 0), shade, n=16)
    passes = tracer.render_tile(view, 0, 0, 8, 8, GUIDES)
    assert "CLOSURES" in tracer.last_render["features"]
    expected = 0.7 * np.array([0.9, 0.1, 0.1]) + 0.3 * np.array([0.1, 0.1, 0.9])
    np.testing.assert_allclose(passes["albedo"].reshape(-1, 3).mean(0), expected, rtol=0.03)


def test_the_passes_change_no_pixel_and_are_compiled_only_when_asked(tracer):
    load(tracer, (grid_plane(4.0, 2), 0), (wall_facing(3.0), 1))
    view = view_of((0, -3, 3), (0, 0, 0), shading([material((0.9, 0.8, 0.5), metallic=1.0,
                                                             roughness=0.2),
                                                   material(WALL)], (0.2, 0.2, 0.2)))
    plain = tracer.render_tile(view, 0, 0, 8, 8)
    assert "FILM" not in tracer.last_render["features"] and "albedo" not in plain
    guided = tracer.render_tile(view, 0, 0, 8, 8, GUIDES)
    assert {"FILM", "GUIDES"} <= set(tracer.last_render["features"])
    assert np.array_equal(plain["combined"], guided["combined"])


def test_untraced_pixels_take_their_traced_neighbours_mean():
    value = np.arange(12, dtype=np.float64).reshape(3, 4)
    traced = np.ones((3, 4), bool)
    traced[1, 1] = False
    filled = fill_untraced(value, traced)
    neighbours = [value[r, c] for r in (0, 1, 2) for c in (0, 1, 2) if (r, c) != (1, 1)]
    assert filled[1, 1] == pytest.approx(np.mean(neighbours))
    assert np.array_equal(np.delete(filled.ravel(), 5), np.delete(value.ravel(), 5))
    assert CYCLES_CAMERA_AXES[2] == -1


def test_mist_is_cycles_distance_ramp_and_the_world_is_mist(tracer):
    """Mist (start 2, depth 10, each falloff) of a floor 5 below a camera looking straight
    down: ((distance - start) / depth)^falloff, 1 where the camera sees the world."""
    load(tracer, (grid_plane(2.0, 2), 0))
    view = view_of((0, 0, 5), (0, 0, 0), shading([material((0.5, 0.5, 0.5))]), size=16,
                   fov=0.3, up=(0, 1, 0))
    camera = view.camera
    for falloff in (2.0, 1.0, 0.5):
        view.mist = (2.0, 10.0, falloff)
        passes = tracer.render_tile(view, 0, 0, 16, 16, ("combined", "mist"))
        mist = passes["mist"]
        assert mist[0, 0] == 1.0 and mist.dtype == np.float32    # a corner sees the world
        # the centre pixel's ray, through the pixel's centre (the filter keeps the plane flat)
        ndc = np.array([0.5 / 8, -0.5 / 8]) * camera.ndc_scale
        ray = np.array([ndc[0], ndc[1], -1.0])
        distance = 5.0 * np.linalg.norm(ray)
        expected = ((distance - 2.0) / 10.0) ** falloff
        assert mist[8, 8] == pytest.approx(expected, rel=2e-3)


def test_emission_diffuse_and_glossy_colour_of_the_camera_hit(tracer):
    """Emission: what the camera sees emitted (the world is not emission); Diffuse Color and
    Glossy Color: the camera hit's diffuse and glossy albedos (a diffuse plane: its base and
    none; a perfect metal: none and its Fresnel colour)."""
    names = ("combined", "emission", "diffuse_color", "glossy_color")
    load(tracer, (grid_plane(4.0, 2), 0))
    glow = material((0.2, 0.4, 0.6))
    glow[1][[COLUMN["emission_r"], COLUMN["emission_g"], COLUMN["emission_b"]]] = (2.0, 1.0, 0.5)
    view = view_of((0, -3, 3), (0, 0, 0), shading([glow], (0.3, 0.3, 0.3)))
    passes = tracer.render_tile(view, 0, 0, 8, 8, names)
    np.testing.assert_allclose(passes["emission"], np.broadcast_to([2.0, 1.0, 0.5], (8, 8, 3)),
                               rtol=1e-5)
    np.testing.assert_allclose(passes["diffuse_color"], np.broadcast_to([0.2, 0.4, 0.6], (8, 8, 3)),
                               rtol=1e-5)
    assert not passes["glossy_color"].any()
    tint = np.array([0.9, 0.8, 0.5])
    view = view_of((0, -3, 3), (0, 0, 0), shading([material(tint, metallic=1.0, roughness=0.0)],
                                                  (0.3, 0.3, 0.3)))
    passes = tracer.render_tile(view, 0, 0, 8, 8, names)
    assert not passes["emission"].any() and not passes["diffuse_color"].any()
    fresnel = tint + (1 - tint) * (1 - np.sqrt(0.5)) ** 5
    np.testing.assert_allclose(centre(passes["glossy_color"]), fresnel, rtol=2e-3)


def test_the_views_mist_travels_and_is_checked():
    from kdtrace.core.scene.model import MIST, SceneError
    view = view_of((0, -3, 3), (0, 0, 0), shading([material((0.5, 0.5, 0.5))]))
    assert View.from_dict(view.to_dict()).mist == MIST
    view.mist = (1.0, 4.0, 0.5)
    assert View.from_dict(view.to_dict()).mist == (1.0, 4.0, 0.5)
    for bad in ([1.0, -1.0, 2.0], [1.0, 4.0, 3.0], [1.0, float("nan"), 2.0], [1.0, 2.0]):
        d = view.to_dict()
        d["mist"] = bad
        with pytest.raises(SceneError, match="mist"):
            View.from_dict(d)
