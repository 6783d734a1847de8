"""Point lights with Soft Falloff off (issue 38): Cycles' sphere of light (kernels/shade/lights.cl
sample_sphere_light). A sphere light dipping into a white diffuse plane, seen from above: each
pixel is the irradiance of the sphere's cap above the plane's horizon / pi (inside the sphere:
its radiance), which numpy integrates here; with Soft Falloff on (a disk facing the surface)
the plane under the light gets a third less."""
from __future__ import annotations

import numpy as np

from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.scene.model import (MATERIAL_PARAMS, Camera, Geometry, Light, RenderSettings,
                                      Shading, View, default_material_params)
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.tracer import Tracer
from tests.meshes import grid_plane

SIZE = 12
HEIGHT, RADIUS, POWER = 0.2, 0.3, 40.0      # the sphere dips into the plane


def sphere_irradiance(points, centre, radius, radiance, n=400):
    """Irradiance at plane points (z = 0, normal +z) from a sphere of uniform radiance: the
    integral of radiance x cos over the directions to the sphere above the horizon (midpoint
    rule over the cap's solid angle)."""
    out = np.zeros(len(points))
    for k, p in enumerate(points):
        to = centre - p
        d = np.linalg.norm(to)
        if d <= radius:             # inside: the sphere's radiance from every direction
            out[k] = radiance * np.pi
            continue
        axis = to / d
        cos_max = np.sqrt(1 - (radius / d) ** 2)
        cos_t = 1 - (np.arange(n) + 0.5) / n * (1 - cos_max)
        phi = (np.arange(n) + 0.5) / n * 2 * np.pi
        c, f = np.meshgrid(cos_t, phi)
        s = np.sqrt(1 - c * c)
        u = np.cross(axis, [1.0, 0, 0] if abs(axis[0]) < 0.9 else [0, 1.0, 0])
        u /= np.linalg.norm(u)
        v = np.cross(axis, u)
        w = (s * np.cos(f))[..., None] * u + (s * np.sin(f))[..., None] * v + c[..., None] * axis
        cos_surface = np.maximum(w[..., 2], 0)
        out[k] = radiance * cos_surface.mean() * 2 * np.pi * (1 - cos_max)
    return out


def test_a_sphere_light_lights_a_plane_as_its_cap_above_the_horizon():
    vertices, triangles = grid_plane(4.0, 1, 0.0)
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16))
    tracer = Tracer()
    tracer.load(Scene.from_parts(geometry, build_kdtree(vertices, triangles)))
    params = default_material_params(1)
    params[0, MATERIAL_PARAMS.index("specular")] = 0.0
    m = np.eye(4)
    m[2, 3] = 3.0
    centres = (np.arange(SIZE) + 0.5) / SIZE * 2 - 1
    x, y = np.meshgrid(centres, centres[::-1])
    points = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], -1)
    centre = np.array([0.0, 0.0, HEIGHT])
    images = {}
    for soft in (False, True):
        light = Light("POINT", (1, 1, 1), POWER, tuple(centre), radius=RADIUS, soft_falloff=soft)
        shading = Shading(np.array([[1, 1, 1, 1]], np.float32), [light], (0, 0, 0), params)
        view = View(Camera("ORTHO", m, (1.0, 1.0), (0, 0), 0.01, 10.0), SIZE, SIZE, shading,
                    settings=RenderSettings(samples_per_axis=1, adaptive=False, max_bounces=0,
                                            light_samples_per_axis=16, pixel_filter="BOX",
                                            filter_width=1.0))   # each pixel's centre
        images[soft] = tracer.render_tile(view, 0, 0, SIZE, SIZE)["combined"][..., 0].ravel()
        assert ("SPHERE_LIGHTS" in tracer.last_render["features"]) == (not soft)
    radiance = POWER / (4 * np.pi ** 2 * RADIUS ** 2)
    expected = sphere_irradiance(points, centre, RADIUS, radiance) / np.pi
    np.testing.assert_allclose(images[False], expected, rtol=0.02)
    assert abs(images[False].mean() / expected.mean() - 1) < 0.01
    # Soft Falloff on (a disk facing each point): under the light, a third less than the
    # sphere that surrounds those points gives.
    near = np.linalg.norm(points[:, :2], axis=1) < 0.15
    assert images[True][near].mean() < 0.75 * images[False][near].mean()
