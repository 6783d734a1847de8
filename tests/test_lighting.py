"""The world and emissive meshes as lights (docs/shading.md), against references computed
here independently of the kernel: the irradiance integral of an environment map, an area
light of the same size and power as an emissive panel, exact alias-table probabilities; and
the kernel features a scene compiles."""
from __future__ import annotations

import math

import numpy as np
import pytest

from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.scene.features import ALL_FEATURES, scene_features
from kdtrace.core.layout import VISIBILITY_CODES, VISIBLE_TO_ALL
from kdtrace.core.scene.model import (MATERIAL_PARAMS, Camera, Geometry, Light, RenderSettings,
                                      Shading, View, WorldTexture, default_material_params)
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.buffers import alias_table, emitter_powers, world_importance
from kdtrace.slave.tracer import Tracer, kernel_options
from tests.meshes import grid_plane, merge

ALBEDO = 0.5


@pytest.fixture(scope="module")
def tracer():
    return Tracer()


def load(tracer, vertices, triangles, ids=None, **arrays):
    ids = np.zeros(len(triangles), np.uint16) if ids is None else ids
    geometry = Geometry(vertices, triangles, ids, **arrays)
    tracer.load(Scene.from_parts(geometry, build_kdtree(geometry.vertices, geometry.triangles)))
    return geometry


def camera_down(height=1.0, half=1.0):
    """Orthographic, looking straight down at the plane z = 0 (image x = world x)."""
    m = np.eye(4)
    m[2, 3] = height
    return Camera("ORTHO", m, (half, half), (0.0, 0.0), 0.01, 100.0)


def settings(n=8, **extra):
    return RenderSettings(samples_per_axis=n, adaptive=False, **extra)


def render(tracer, view):
    return tracer.render_tile(view, 0, 0, view.width, view.height)["combined"][..., :3]


def test_world_colour_lights_a_plane(tracer):
    """Sky fill: a diffuse plane under a constant world of radiance W is albedo x W."""
    load(tracer, *grid_plane(40.0, 1, 0.0))
    world = (0.2, 0.4, 0.6)
    view = View(camera_down(), 16, 16, Shading(np.array([[ALBEDO] * 3 + [1]], np.float32), [],
                                               world), settings=settings(8))
    image = render(tracer, view)
    assert "WORLD" in tracer.last_render["features"]
    np.testing.assert_allclose(image.reshape(-1, 3).mean(0), ALBEDO * np.array(world), rtol=0.01)


def sky_texels(width, height, projection):
    """A small sky: a blue gradient and a bright 'sun' patch (float RGBA rows bottom first),
    as a function of the texture-space direction, sampled at texel centres."""
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    if projection == "EQUIRECTANGULAR":
        phi = 2 * np.pi * (0.5 - u)[None, :]
        elevation = np.pi * (v - 0.5)[:, None]
        d = np.stack(np.broadcast_arrays(np.cos(elevation) * np.cos(phi),
                                         np.cos(elevation) * np.sin(phi), np.sin(elevation)), -1)
        inside = np.ones((height, width), bool)
    else:
        x, z = np.meshgrid(2 * u - 1, 2 * v - 1)
        r2 = x * x + z * z
        s = 2 * np.sqrt(np.maximum(1 - r2, 0))
        d = np.stack([s * x, 2 * r2 - 1, s * z], -1)
        inside = r2 <= 1
    sun = np.array([0.5, -0.3, 0.8]) / np.linalg.norm([0.5, -0.3, 0.8])
    rgb = 0.3 + 0.5 * np.clip(d[..., 2:3], 0, 1) * np.array([0.3, 0.6, 1.0])
    rgb = np.where((d @ sun > 0.985)[..., None], np.array([60.0, 50.0, 40.0]), rgb)
    rgb = np.where(inside[..., None], rgb, 0.0)
    return np.concatenate([rgb, np.ones((height, width, 1))], -1).reshape(-1, 4)


def closest_lookup(texels, width, height, projection, d):
    """Reference of the kernel's world lookup (closest texel), in float64."""
    if projection == "EQUIRECTANGULAR":
        u = 0.5 - np.arctan2(d[..., 1], d[..., 0]) / (2 * np.pi)
        v = 0.5 + np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1])) / np.pi
    else:
        div = np.sqrt(2 * np.maximum(1 - d[..., 1], 0))
        u = 0.5 * (np.where(div > 0, d[..., 0] / np.where(div > 0, div, 1), d[..., 0]) + 1)
        v = 0.5 * (np.where(div > 0, d[..., 2] / np.where(div > 0, div, 1), d[..., 2]) + 1)
    u, v = u - np.floor(u), v - np.floor(v)
    i = np.minimum((u * width).astype(int), width - 1)
    j = np.minimum((v * height).astype(int), height - 1)
    return texels[j * width + i, :3]


def rotation_z(angle):
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


@pytest.mark.parametrize("projection, mapping", [
    ("EQUIRECTANGULAR", rotation_z(0.7)),
    ("EQUIRECTANGULAR", np.diag([1.0, -1.0, 1.0]) @ rotation_z(-0.4)),      # mirrored
    ("MIRROR_BALL", rotation_z(0.3) @ np.diag([1.0, 1.0, 1.3])),           # stretched
])
def test_environment_map_lights_a_plane_as_its_integral(tracer, projection, mapping):
    """A diffuse plane under an environment texture (importance-sampled, weighted against the
    BSDF) has radiance albedo / pi x the cosine-weighted integral of the texture over the upper
    hemisphere, computed here on a fine grid of world directions: this holds only if the
    sampled directions' densities (projection and mapping Jacobians) are right."""
    width, height = (64, 32) if projection == "EQUIRECTANGULAR" else (48, 48)
    texels = sky_texels(width, height, projection)
    load(tracer, *grid_plane(40.0, 1, 0.0), texels=texels.astype(np.float16),
         texture_sizes=np.array([[0, width, height]], np.uint32))
    texels = texels.astype(np.float16).astype(np.float64)
    world = WorldTexture(0, projection, mapping, "CLOSEST")
    view = View(camera_down(), 8, 8, Shading(np.array([[ALBEDO] * 3 + [1]], np.float32), [],
                                             (1.5, 1.5, 1.5), world_texture=world),
                settings=settings(16))
    image = render(tracer, view)
    assert {"WORLD", "WORLD_TEXTURE"} <= set(tracer.last_render["features"])
    # Reference: midpoint rule over the upper hemisphere in (cos theta, phi).
    n = 1024
    mu = (np.arange(n) + 0.5) / n
    phi = (np.arange(2 * n) + 0.5) / (2 * n) * 2 * np.pi
    mu, phi = np.meshgrid(mu, phi, indexing="ij")
    s = np.sqrt(1 - mu * mu)
    d = np.stack([s * np.cos(phi), s * np.sin(phi), mu], -1)
    a = d @ mapping.T
    radiance = closest_lookup(texels, width, height, projection, a / np.linalg.norm(a, axis=-1, keepdims=True))
    irradiance = 1.5 * (radiance * mu[..., None]).mean(axis=(0, 1)) * 2 * np.pi
    expected = ALBEDO / np.pi * irradiance
    np.testing.assert_allclose(image.reshape(-1, 3).mean(0), expected, rtol=0.02)


def test_environment_importance_map_is_a_cdf():
    width, height = 64, 32
    texels = sky_texels(width, height, "EQUIRECTANGULAR")
    geometry = Geometry(*grid_plane(2.0, 1, 0.0), np.zeros(2, np.uint16),
                        texels=texels.astype(np.float16),
                        texture_sizes=np.array([[0, width, height]], np.uint32))
    cdf, w, h = world_importance(geometry, WorldTexture(0))
    assert (w, h) == (width, height) and cdf.dtype == np.float32
    marginal, rows = cdf[:h + 1], cdf[h + 1:].reshape(h, w + 1)
    for c in (marginal, *rows):
        assert c[0] == 0 and c[-1] == 1 and (np.diff(c) >= 0).all()
    # The brightest cell (the sun) is the likeliest; weights follow colour x cos(elevation),
    # each texel's colour the brightest of its 3 x 3 (the texture wraps both ways).
    p = np.diff(marginal)[:, None] * np.diff(rows, axis=1)
    own = texels[:, :3].astype(np.float16).astype(np.float64).mean(1).reshape(h, w)
    mean = np.max([np.roll(own, (dy, dx), axis=(0, 1)) for dy in (-1, 0, 1) for dx in (-1, 0, 1)],
                  axis=0)
    assert (mean > own).any()
    weight = mean * np.cos(np.pi * ((np.arange(h) + 0.5) / h - 0.5))[:, None]
    np.testing.assert_allclose(p, weight / weight.sum(), rtol=1e-4, atol=1e-8)
    again, _, _ = world_importance(geometry, WorldTexture(0))
    assert again.tobytes() == cdf.tobytes()


def test_alias_table_probabilities_are_exact():
    weights = np.random.default_rng(5).exponential(size=1000) ** 3
    threshold, alias = alias_table(weights)
    n = len(weights)
    probability = threshold.copy()
    np.add.at(probability, alias, 1.0 - threshold)
    np.testing.assert_allclose(probability / n, weights / weights.sum(), rtol=1e-9, atol=1e-15)
    assert ((threshold >= 0) & (threshold <= 1 + 1e-12)).all()


def panel_scene(emissive=True):
    """A floor under two square panels facing down (0.6 m at height 2, 0.3 m at height 1.5)
    of radiance 4 and 9: emissive triangles, or area lights of the same size and power."""
    floor = grid_plane(40.0, 1, 0.0)
    big, small = grid_plane(0.6, 1, 2.0), grid_plane(0.3, 1, 1.5)
    big = (big[0] + np.float32([0.4, 0.2, 0]), big[1][:, ::-1].copy())
    small = (small[0] + np.float32([-0.6, -0.3, 0]), small[1][:, ::-1].copy())
    radiance = {"big": (4.0, (0.4, 0.2, 2.0), 0.6), "small": (9.0, (-0.6, -0.3, 1.5), 0.3)}
    if emissive:
        vertices, triangles = merge(floor, big, small)
        ids = np.r_[np.zeros(2), np.ones(2), 2 * np.ones(2)].astype(np.uint16)
        params = default_material_params(3)
        params[1, 4:7], params[2, 4:7] = radiance["big"][0], radiance["small"][0]
        colours = np.array([[ALBEDO] * 3 + [1], [0, 0, 0, 1], [0, 0, 0, 1]], np.float32)
        return (vertices, triangles, ids), Shading(colours, [], (0, 0, 0), params)
    lights = [Light("AREA", (1, 1, 1), L * math.pi * size * size, position, (0, 0, -1),
                    size_u=size, size_v=size) for L, position, size in radiance.values()]
    return (*floor, None), Shading(np.array([[ALBEDO] * 3 + [1]], np.float32), lights, (0, 0, 0))


def test_emissive_panels_light_as_area_lights_do(tracer):
    """Emissive triangles, sampled by power with the alias table and weighted against the
    BSDF, light a floor as area lights of the same size and power do (Blender's area light of
    power P has radiance P / (pi area)); diffuse bounces on, so BSDF rays meet the panels."""
    images = {}
    for emissive in (True, False):
        mesh, shading = panel_scene(emissive)
        load(tracer, *mesh)
        view = View(camera_down(1.0, 1.5), 24, 24, shading, settings=settings(12))
        images[emissive] = render(tracer, view)
        assert ("EMISSION" in tracer.last_render["features"]) == emissive
    ours, reference = images[True], images[False]
    assert reference.mean() > 0.05
    np.testing.assert_allclose(ours.mean(), reference.mean(), rtol=0.01)
    mse = np.mean((ours - reference) ** 2)
    assert math.sqrt(mse) < 0.05 * reference.mean()       # noise, no pattern


def test_emitter_powers_follow_emission_and_area():
    (vertices, triangles, ids), shading = panel_scene(True)
    geometry = Geometry(vertices, triangles, ids)
    emissive, power = emitter_powers(geometry, shading)
    np.testing.assert_array_equal(emissive, [2, 3, 4, 5])
    np.testing.assert_allclose(power, [4 * 0.18] * 2 + [9 * 0.045] * 2, rtol=1e-6)


def feature_view(shading, **extra):
    return View(camera_down(), 8, 8, shading, settings=RenderSettings(**extra))


FEATURE_CASES = {
    # name: (shading, settings, the features exactly)
    "point light, direct only": (
        Shading(np.array([[0.5, 0.5, 0.5, 1]], np.float32), [Light("POINT", (1, 1, 1), 10.0, (0, 0, 2))],
                (0, 0, 0)), dict(max_bounces=0), {"POINT"}),
    "sky fill": (
        Shading(np.array([[0.5, 0.5, 0.5, 1]], np.float32), [], (0.1, 0.1, 0.1)), {},
        {"WORLD", "BOUNCES"}),
    "soft sun and bounces": (
        Shading(np.array([[0.5, 0.5, 0.5, 1]], np.float32),
                [Light("SUN", (1, 1, 1), 2.0, radius=0.05)], (0, 0, 0)), {},
        {"SUN", "SOFT_LIGHTS", "BOUNCES"}),
}


@pytest.mark.parametrize("name", sorted(FEATURE_CASES))
def test_unused_features_are_off_in_the_kernel_build(tracer, name):
    """The kernel of a scene is built with exactly the features it uses: every other
    HAS_<FEATURE> is off (tests/test_cycles_scenes.py checks the same for its scenes)."""
    shading, extra, expected = FEATURE_CASES[name]
    geometry = load(tracer, *grid_plane(4.0, 1, 0.0))
    view = feature_view(shading, samples_per_axis=1, adaptive=False, **extra)
    assert scene_features(geometry, view) == expected
    tracer.render_tile(view, 0, 0, 8, 8)
    assert set(tracer.last_render["features"]) == expected
    options = [o for o in kernel_options({"flags": expected}) if o.startswith("-DHAS_")]
    assert sorted(options) == sorted(f"-DHAS_{f}" for f in expected)
    assert not {f"-DHAS_{f}" for f in ALL_FEATURES - expected} & set(options)


def test_unused_emissive_and_world_textures_compile_nothing():
    """An emissive material no triangle uses, a world texture behind a black world colour,
    and no bounces: no EMISSION, WORLD or WORLD_TEXTURE."""
    params = default_material_params(2)
    params[1, 4:7] = 5.0
    texels = np.ones((4, 4), np.float16)
    geometry = Geometry(*grid_plane(4.0, 1, 0.0), np.zeros(2, np.uint16), texels=texels,
                        texture_sizes=np.array([[0, 2, 2]], np.uint32))
    shading = Shading(np.array([[0.5, 0.5, 0.5, 1], [0, 0, 0, 1]], np.float32),
                      [Light("POINT", (1, 1, 1), 10.0, (0, 0, 2))], (0, 0, 0), params,
                      WorldTexture(0))
    assert scene_features(geometry, feature_view(shading, max_bounces=0)) == {"POINT"}


# -- Film > Transparent, holdout, ray visibility, depth of field, camera motion -------------------

def sphere_on_floor():
    """A unit sphere (material 1) on a floor (material 0), seen from above at an angle."""
    from tests.meshes import look_at, uv_sphere
    sphere = uv_sphere(24, 12, 1.0, (0, 0, 1))
    vertices, triangles = merge(sphere, grid_plane(8.0, 2, 0.0))
    ids = np.zeros(len(triangles), np.uint16)
    ids[:len(sphere[1])] = 1
    camera = Camera("PERSP", look_at((0.0, -7.0, 5.0), (0.0, 0.0, 0.5)), (0.45, 0.34), (0, 0),
                    0.1, 100.0)
    return vertices, triangles, ids, camera


def two_materials(visibility=VISIBLE_TO_ALL):
    params = default_material_params(2)
    params[1, MATERIAL_PARAMS.index("visibility")] = visibility
    return Shading(np.array([[ALBEDO] * 3 + [1], [0.8, 0.3, 0.2, 1]], np.float32),
                   [Light("SUN", (1, 1, 1), 3.0, direction=(0.4, 0.3, -1.0))], (0.2, 0.25, 0.3),
                   params)


def test_transparent_film_and_holdout_give_alpha_where_camera_rays_do():
    """Alpha 0 exactly where the pixel's camera ray misses (Film > Transparent) or hits a
    holdout (then black too), checked against intersect() of the same rays; elsewhere alpha 1
    and the colours of an opaque film."""
    tracer = Tracer()
    vertices, triangles, ids, camera = sphere_on_floor()
    load(tracer, vertices, triangles, ids)
    w, h = 40, 30
    opaque = View(camera, w, h, two_materials(), settings=settings(1, max_bounces=0))
    film = View(camera, w, h, two_materials(), settings=settings(1, max_bounces=0),
                film_transparent=True)
    held = View(camera, w, h, two_materials(VISIBLE_TO_ALL | VISIBILITY_CODES["HOLDOUT"]),
                settings=settings(1, max_bounces=0), film_transparent=True)
    base = tracer.render_tile(opaque, 0, 0, w, h)["combined"]
    transparent = tracer.render_tile(film, 0, 0, w, h)["combined"]
    assert "TRANSPARENT_FILM" in tracer.last_render["features"]
    holdout = tracer.render_tile(held, 0, 0, w, h)["combined"]
    assert {"HOLDOUT", "TRANSPARENT_FILM"} <= set(tracer.last_render["features"])
    # The pixel-centre rays, made here.
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    ndc = np.stack([(xs / w * 2 - 1) * 0.45, (1 - ys / h * 2) * 0.34, -np.ones_like(xs)], -1)
    directions = ndc.reshape(-1, 3) @ camera.to_world[:3, :3].T
    origins = np.broadcast_to(camera.to_world[:3, 3], directions.shape)
    hits = tracer.intersect(origins, directions)
    missed = (hits.triangle < 0).reshape(h, w)
    on_sphere = (hits.triangle >= 0).reshape(h, w) & (ids[np.maximum(hits.triangle, 0)] == 1).reshape(h, w)
    assert missed.any() and on_sphere.any() and not (missed & on_sphere).any()
    assert (base[..., 3] == 1).all()
    np.testing.assert_array_equal(transparent[..., 3], np.where(missed, 0.0, 1.0))
    np.testing.assert_array_equal(transparent[missed, :3], 0.0)
    np.testing.assert_array_equal(transparent[~missed], base[~missed])
    np.testing.assert_array_equal(holdout[..., 3], np.where(missed | on_sphere, 0.0, 1.0))
    np.testing.assert_array_equal(holdout[on_sphere, :3], 0.0)


def grow(mask):
    """The mask and its 8 neighbours."""
    out = mask.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            out |= np.roll(mask, (dy, dx), axis=(0, 1))
    return out


def test_an_object_no_ray_sees_is_not_rendered():
    """A sphere with every ray visibility off renders as the floor without it; with Camera
    off the floor shows where it was, its shadows stay; with Shadow off it is seen and casts
    none (no bounces, so every difference is the sphere's or its shadow's)."""
    tracer = Tracer()
    vertices, triangles, ids, camera = sphere_on_floor()
    floor_only = slice(int((ids == 1).sum()), None)
    w, h = 40, 30

    def image(visibility, n=4, bounces=0):
        view = View(camera, w, h, two_materials(visibility), settings=settings(n, max_bounces=bounces))
        return tracer.render_tile(view, 0, 0, w, h)
    load(tracer, vertices, triangles[floor_only], ids[floor_only])
    alone, alone_bounced = image(VISIBLE_TO_ALL), image(VISIBLE_TO_ALL, bounces=4)
    load(tracer, vertices, triangles, ids)
    ghost = image(0, bounces=4)["combined"]
    assert "VISIBILITY" in tracer.last_render["features"]
    np.testing.assert_allclose(ghost, alone_bounced["combined"], atol=2e-3)
    full = image(VISIBLE_TO_ALL)
    no_camera = image(VISIBLE_TO_ALL & ~VISIBILITY_CODES["CAMERA"])
    no_shadow = image(VISIBLE_TO_ALL & ~VISIBILITY_CODES["SHADOW"])
    sphere = np.abs(full["depth"] - alone["depth"]) > 1e-3 * np.minimum(full["depth"], 100.0)
    inside, near = sphere & ~grow(~sphere), grow(sphere)
    shadowed = ~near & (np.abs(full["combined"] - alone["combined"]).max(-1) > 0.05)
    assert inside.sum() > 10 and shadowed.sum() > 10
    np.testing.assert_allclose(no_camera["depth"], alone["depth"], rtol=1e-5)
    np.testing.assert_allclose(no_camera["combined"][~near], full["combined"][~near], atol=2e-3)
    assert np.abs(no_camera["combined"][inside] - full["combined"][inside]).max() > 0.1
    np.testing.assert_allclose(no_shadow["combined"][inside], full["combined"][inside], atol=2e-3)
    # (BSDF rays from the floor still meet the sphere: only the shadows of light samples go.)
    lit = np.abs(no_shadow["combined"] - alone["combined"])[shadowed].mean()
    assert lit < 0.25 * np.abs(full["combined"] - alone["combined"])[shadowed].mean()


def test_thin_lens_keeps_the_plane_in_focus_sharp():
    """Every lens sample of a pixel meets the plane in focus at the same point: a diffuse
    plane there renders as with a pinhole; another plane is blurred."""
    tracer = Tracer()
    vertices, triangles = grid_plane(20.0, 10, 0.0)
    ids = (np.arange(len(triangles)) // 2 % 2 + np.arange(len(triangles)) // 20 % 2) % 2
    load(tracer, vertices, triangles, ids.astype(np.uint16))
    shading = two_materials()
    shading.world_color = (0.0, 0.0, 0.0)
    m = np.eye(4)
    m[2, 3] = 5.0
    w = h = 32
    def image(**lens):
        camera = Camera("PERSP", m, (0.6, 0.6), (0, 0), 0.1, 100.0, **lens)
        return render(tracer, View(camera, w, h, shading, settings=settings(4, max_bounces=0)))
    pinhole = image()
    focused = image(aperture=0.4, focus_distance=5.0, blades=6, blade_rotation=0.3)
    assert "DOF" in tracer.last_render["features"]
    np.testing.assert_allclose(focused, pinhole, atol=1e-4)
    # In focus 2.5 in front of the plane: a circle of confusion of 2 x 1.0 x 2.5 / 2.5 = 2
    # units on it, the checker's cells are 2: its contrast (grey against red) fades.
    blurred = image(aperture=1.0, focus_distance=2.5)
    assert blurred[..., 2].std() < 0.6 * pinhole[..., 2].std()
    np.testing.assert_allclose(blurred.mean(), pinhole.mean(), rtol=0.05)


def test_camera_motion_averages_the_shutter():
    """A camera moving over the shutter renders the mean of the cameras along its path."""
    tracer = Tracer()
    vertices, triangles, ids, camera = sphere_on_floor()
    load(tracer, vertices, triangles, ids)
    w, h = 32, 24
    end = camera.to_world.copy()
    end[0, 3] += 1.0
    moving = Camera(camera.kind, camera.to_world, camera.ndc_scale, camera.ndc_offset,
                    camera.clip_start, camera.clip_end, to_world_end=end)
    blurred = render(tracer, View(moving, w, h, two_materials(), settings=settings(16, max_bounces=0)))
    assert "CAMERA_MOTION" in tracer.last_render["features"]
    steps = []
    for t in (np.arange(16) + 0.5) / 16:
        m = camera.to_world.copy()
        m[0, 3] += t
        fixed = Camera(camera.kind, m, camera.ndc_scale, camera.ndc_offset, camera.clip_start,
                       camera.clip_end)
        steps.append(render(tracer, View(fixed, w, h, two_materials(), settings=settings(4, max_bounces=0))))
    reference = np.mean(steps, axis=0)
    mse = np.mean((np.clip(blurred, 0, 1) - np.clip(reference, 0, 1)) ** 2)
    assert 10 * np.log10(1 / mse) > 30
    still = render(tracer, View(camera, w, h, two_materials(), settings=settings(4, max_bounces=0)))
    assert np.mean((still - reference) ** 2) > 4 * mse
