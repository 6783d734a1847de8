"""The BSDF (kernels/shade/bsdf.cl): GGX reflection and transmission at any roughness,
checked on the device against its own definitions (sampled densities equal evaluated ones,
energy preserved as Cycles' Multiscatter GGX preserves it), in a white furnace, for
continuity across roughness, and for convergence of rough glossy and glass."""
from __future__ import annotations

import importlib.util
import pathlib
import re

import numpy as np
import pytest

from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.opencl import KERNEL_DIR, kernel_source
from kdtrace.core.scene.model import (Camera, Geometry, Light, RenderSettings, Shading, View,
                                      default_material_params)
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.tracer import Tracer, kernel_files_through
from tests.meshes import grid_plane, look_at, merge, uv_sphere

# metallic, roughness, transmission, ior, specular (Principled inputs)
MATERIALS = {
    "diffuse": (0.0, 0.5, 0.0, 1.5, 0.0),
    "plastic": (0.0, 0.4, 0.0, 1.5, 0.5),
    "smooth plastic": (0.0, 0.0, 0.0, 1.5, 0.5),
    "metal 0.2": (1.0, 0.2, 0.0, 1.5, 0.5),
    "metal 1": (1.0, 1.0, 0.0, 1.5, 0.5),
    "glass": (0.0, 0.0, 1.0, 1.5, 0.5),
    "glass 0.3": (0.0, 0.3, 1.0, 1.5, 0.5),
    "glass 0.8": (0.0, 0.8, 1.0, 1.5, 0.5),
    "mixed": (0.3, 0.35, 0.4, 1.45, 0.7),
}

PROBE = r'''
// A material of the Principled inputs under test on a grey base colour.
Material grey_material(float grey, float metallic, float roughness, float transmission,
                       float ior, float specular)
{
    Material m;
    m.base = (float3)(grey, grey, grey);
    m.alpha = 1.0f;
    m.metallic = metallic;
    m.roughness = roughness;
    m.transmission = transmission;
    m.ior = ior;
    m.emission = (float3)(0.0f, 0.0f, 0.0f);
    m.specular = specular;
#ifdef HAS_TRANSLUCENT
    m.translucent = 0.0f;
#endif
#ifdef HAS_COAT
    m.coat_weight = 0.0f;
    m.coat_roughness = 0.03f;
    m.coat_ior = 1.5f;
    m.coat_tint = (float3)(1.0f, 1.0f, 1.0f);
#endif
    return m;
}

// Samples the BSDF of one material from wo (cos theta = cos_o) n times per work-item; sums
// the reflected and transmitted weights (transmission as energy: times eta^2) and the largest
// relative difference between a sample's density and bsdf_eval_local's.
__kernel void probe(float metallic, float roughness, float transmission, float ior,
                    float specular, float cos_o, int front, int n, float4 extra,
                    __global float4 *out)
{
    int i = get_global_id(0);
    Material m = grey_material(1.0f, metallic, roughness, transmission, ior, specular);
#ifdef HAS_TRANSLUCENT
    m.translucent = extra.x;                // extra: translucent, coat weight, roughness, IOR
#endif
#ifdef HAS_COAT
    m.coat_weight = extra.y;
    m.coat_roughness = extra.z;
    m.coat_ior = extra.w;
#endif
    float3 wo = (float3)(sqrt(1.0f - cos_o * cos_o), 0.0f, cos_o);
    Lobes l = lobes_at(&m, cos_o, front != 0, 0.0f);
    Rng r = rng_seed((uint)i, 3u, 11u);
    float reflected = 0.0f, transmitted = 0.0f, pdf_error = 0.0f;
    for (int k = 0; k < n; ++k) {
        float3 wi, w;
        float pdf;
        int kind;
        float a = rng_next(&r), b = rng_next(&r), c = rng_next(&r), d = rng_next(&r);
        if (!bsdf_sample_local(&m, &l, wo, a, b, c, d, &wi, &w, &pdf, &kind))
            continue;
        if (wi.z > 0.0f)
            reflected += w.x;
        else if (kind == LOBE_TRANSLUCENT)
            transmitted += w.x;
        else
            transmitted += w.x * l.eta_glass * l.eta_glass;
        if (pdf > 0.0f) {
            float again;
            bsdf_eval_local(&m, &l, wo, wi, &again);
            pdf_error = fmax(pdf_error, fabs(again - pdf) / pdf);
        }
    }
    out[i] = (float4)(reflected / (float)n, transmitted / (float)n, pdf_error, 0.0f);
}

// Integral of bsdf_eval_local's density over the sphere by uniform sampling.
__kernel void pdf_integral(float metallic, float roughness, float transmission, float ior,
                           float specular, float cos_o, int n, __global float *out)
{
    int i = get_global_id(0);
    Material m = grey_material(0.7f, metallic, roughness, transmission, ior, specular);
    float3 wo = (float3)(sqrt(1.0f - cos_o * cos_o), 0.0f, cos_o);
    Lobes l = lobes_at(&m, cos_o, true, 0.0f);
    Rng r = rng_seed((uint)i, 5u, 13u);
    float sum = 0.0f;
    for (int k = 0; k < n; ++k) {
        float3 wi = uniform_cone((float3)(0.0f, 0.0f, 1.0f), -1.0f, rng_next(&r), rng_next(&r));
        float pdf;
        bsdf_eval_local(&m, &l, wo, wi, &pdf);
        sum += pdf * 4.0f * M_PI_F;
    }
    out[i] = sum / (float)n;
}
'''


@pytest.fixture(scope="module")
def probe():
    import pyopencl as cl
    tracer = Tracer()
    source = kernel_source(kernel_files_through("shade/bsdf.cl")) + PROBE
    program = cl.Program(tracer.context, source).build(
        options=["-DKD_STACK_SIZE=32", "-DHAS_SPECULAR", "-DHAS_TRANSMISSION"])
    items = 256
    out4 = np.zeros((items, 4), np.float32)
    out1 = np.zeros(items, np.float32)
    buf4 = cl.Buffer(tracer.context, cl.mem_flags.WRITE_ONLY, out4.nbytes)
    buf1 = cl.Buffer(tracer.context, cl.mem_flags.WRITE_ONLY, out1.nbytes)
    kernels = {name: cl.Kernel(program, name) for name in ("probe", "pdf_integral")}

    def sample(material, cos_o, front=True, n=1000):
        kernels["probe"](tracer.queue, (items,), None, *map(np.float32, material),
                         np.float32(cos_o), np.int32(front), np.int32(n),
                         np.array([0, 0, 0.03, 1.5], np.float32), buf4)
        cl.enqueue_copy(tracer.queue, out4, buf4)
        return out4[:, 0].mean(), out4[:, 1].mean(), out4[:, 2].max()

    def pdf_integral(material, cos_o, n=2000):
        kernels["pdf_integral"](tracer.queue, (items,), None, *map(np.float32, material),
                                np.float32(cos_o), np.int32(n), buf1)
        cl.enqueue_copy(tracer.queue, out1, buf1)
        return out1.mean()
    return sample, pdf_integral


@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_bsdf_samples_have_the_density_it_evaluates_and_keep_energy(probe, name):
    sample, pdf_integral = probe
    material = MATERIALS[name]
    for cos_o in (0.95, 0.6, 0.25):
        for front in ((True, False) if material[2] > 0 else (True,)):
            reflected, transmitted, pdf_error = sample(material, cos_o, front)
            assert pdf_error < 1e-3, f"{name} cos {cos_o}: sampled density off by {pdf_error:.2e}"
            # A white material loses (almost) nothing and makes no energy (Multiscatter GGX
            # compensates what single scattering loses; a little remains at grazing angles).
            energy = reflected + transmitted
            assert 0.96 < energy < 1.02, f"{name} cos {cos_o} front {front}: albedo {energy:.4f}"
        if material[1] >= 0.3:
            # A density integrates to at most 1 (what is missing: reflections below the
            # horizon); uniform sampling estimates it well for wide lobes only.
            assert 0.3 < pdf_integral(material, cos_o) < 1.02


def plane_under_sun(tracer, colour, params, sun, size=8):
    """The loaded plane (z = 0) of one material (`colour`, `params`) under a sun of irradiance 2
    shining along `sun`, seen from straight above, one sample at each pixel centre: RGB."""
    shading = Shading(np.array([[*colour, 1]], np.float32),
                      [Light("SUN", (1, 1, 1), 2.0, direction=tuple(sun))], (0, 0, 0), params)
    m = np.eye(4)
    m[2, 3] = 1.0
    view = View(Camera("ORTHO", m, (1.0, 1.0), (0, 0), 0.01, 10.0), size, size, shading,
                settings=RenderSettings(samples_per_axis=1, adaptive=False, max_bounces=0))
    return tracer.render_tile(view, 0, 0, size, size)["combined"][..., :3]


def test_translucent_transmits_lambertian_light():
    """The Translucent share of a white material (lobes_at, bsdf_sample_local,
    bsdf_eval_local): its samples transmit t of the light and reflect 1 - t, their densities
    are those evaluated; and a translucent plane lit from behind by a sun straight up shows
    colour x t x E / pi from above (one sample per pixel centre, as numpy says)."""
    import pyopencl as cl
    tracer = Tracer()
    program = cl.Program(tracer.context, kernel_source(kernel_files_through("shade/bsdf.cl"))
                         + PROBE).build(options=["-DKD_STACK_SIZE=32", "-DHAS_TRANSLUCENT"])
    kernel = cl.Kernel(program, "probe")
    out = np.zeros((64, 4), np.float32)
    buf = cl.Buffer(tracer.context, cl.mem_flags.WRITE_ONLY, out.nbytes)
    for t in (1.0, 0.4):
        for cos_o in (0.9, 0.3):
            # a white diffuse material (specular 0) with its translucent share t
            kernel(tracer.queue, (64,), None, *map(np.float32, (0, 0.5, 0, 1.5, 0, cos_o)),
                   np.int32(1), np.int32(1000), np.array([t, 0, 0.03, 1.5], np.float32), buf)
            cl.enqueue_copy(tracer.queue, out, buf)
            assert out[:, 2].max() < 1e-3
            assert abs(out[:, 1].mean() - t) < 0.01 and abs(out[:, 0].mean() - (1 - t)) < 0.01
    from kdtrace.core.scene.model import MATERIAL_PARAMS
    vertices, triangles = grid_plane(2.0, 1, 0.0)
    tracer.load(Scene.from_parts(Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16)),
                                 build_kdtree(vertices, triangles)))
    params = default_material_params(1)
    params[0, MATERIAL_PARAMS.index("specular")] = 0.0
    params[0, MATERIAL_PARAMS.index("translucent")] = 0.75
    colour = np.array([0.9, 0.6, 0.3])
    image = plane_under_sun(tracer, colour, params, (0, 0, 1))
    assert "TRANSLUCENT" in tracer.last_render["features"]
    np.testing.assert_allclose(image, np.broadcast_to(colour * 0.75 * 2.0 / np.pi, image.shape),
                               rtol=1e-5)


def ggx(alpha2, cos_h):
    return alpha2 / (np.pi * (cos_h * cos_h * (alpha2 - 1) + 1) ** 2)


def smith_lambda(alpha2, cos_t):
    return 0.5 * (-1 + np.sqrt(1 + alpha2 * (1 - cos_t ** 2) / cos_t ** 2))


def fresnel(cos_i, eta):
    sin2 = (1 - cos_i ** 2) / eta ** 2
    cos_t = np.sqrt(np.maximum(1 - sin2, 0))
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    return np.where(sin2 >= 1, 1.0, 0.5 * (rs * rs + rp * rp))


def test_coat_layers_as_cycles_does():
    """Principled's Coat (lobes_at, bsdf_eval_local, bsdf_sample_local): samples have the density
    evaluated and a white coated diffuse keeps at most the energy it gets; and a coated diffuse
    plane under a slanted sun, seen from straight above, is Cycles' layering: base / pi x E cos
    x (1 - weight F(cos_o)) x the tint over its path, plus the coat's GGX reflection of the sun
    (alpha = coat roughness^2, exact Fresnel of the coat's IOR), as numpy says."""
    import pyopencl as cl
    tracer = Tracer()
    program = cl.Program(tracer.context, kernel_source(kernel_files_through("shade/bsdf.cl"))
                         + PROBE).build(options=["-DKD_STACK_SIZE=32", "-DHAS_COAT",
                                                 "-DHAS_SPECULAR"])
    kernel = cl.Kernel(program, "probe")
    out = np.zeros((64, 4), np.float32)
    buf = cl.Buffer(tracer.context, cl.mem_flags.WRITE_ONLY, out.nbytes)
    for weight, coat_roughness in ((1.0, 0.3), (0.6, 0.1)):
        for cos_o in (0.9, 0.4):
            kernel(tracer.queue, (64,), None, *map(np.float32, (0, 0.5, 0, 1.5, 0.5, cos_o)),
                   np.int32(1), np.int32(1000), np.array([0, weight, coat_roughness, 1.5],
                                                         np.float32), buf)
            cl.enqueue_copy(tracer.queue, out, buf)
            assert out[:, 2].max() < 1e-3
            assert 0.85 < out[:, 0].mean() < 1.01
    from kdtrace.core.scene.model import MATERIAL_PARAMS
    vertices, triangles = grid_plane(2.0, 1, 0.0)
    tracer.load(Scene.from_parts(Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16)),
                                 build_kdtree(vertices, triangles)))
    params = default_material_params(1)
    column = {name: k for k, name in enumerate(MATERIAL_PARAMS)}
    weight, coat_roughness, coat_ior, tint = 0.8, 0.4, 1.6, np.array([0.9, 0.6, 0.3])
    params[0, column["specular"]] = 0.0
    params[0, column["coat_weight"]] = weight
    params[0, column["coat_roughness"]] = coat_roughness
    params[0, column["coat_ior"]] = coat_ior
    params[0, [column["coat_tint_r"], column["coat_tint_g"], column["coat_tint_b"]]] = tint
    colour = np.array([0.2, 0.7, 0.4])
    sun = np.array([0.5, 0.0, -1.0])
    image = plane_under_sun(tracer, colour, params, sun)
    assert "COAT" in tracer.last_render["features"]
    wi = -sun / np.linalg.norm(sun)
    cos_i, cos_o = wi[2], 1.0
    depth = 1 / np.sqrt(1 - (1 - cos_o ** 2) / coat_ior ** 2)
    below = (1 - weight * fresnel(cos_o, coat_ior)) * (1 + weight * (tint ** depth - 1))
    h = (wi + np.array([0, 0, 1.0]))
    h /= np.linalg.norm(h)
    alpha2 = coat_roughness ** 4
    g2 = 1 / (1 + smith_lambda(alpha2, cos_o) + smith_lambda(alpha2, cos_i))
    coat = weight * fresnel(h @ wi, coat_ior) * ggx(alpha2, h[2]) * g2 / (4 * cos_o * cos_i)
    expected = (colour / np.pi * below + coat) * 2.0 * cos_i
    np.testing.assert_allclose(image, np.broadcast_to(expected, image.shape), rtol=2e-4)


def render_sphere(tracer, params, world=(1.0, 1.0, 1.0), base=(1, 1, 1), size=16, n=12):
    vertices, triangles = uv_sphere(64, 32, 1.0, (0, 0, 0))
    corners = vertices[triangles]
    normals = (corners / np.linalg.norm(corners, axis=-1, keepdims=True)).reshape(-1, 3)
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16), normals=normals)
    tracer.load(Scene.from_parts(geometry, build_kdtree(geometry.vertices, geometry.triangles)))
    camera = Camera("PERSP", look_at((0, -4, 0), (0, 0, 0)), (0.27, 0.27), (0, 0), 0.1, 100)
    shading = Shading(np.array([[*base, 1]], np.float32), [], world, np.array([params], np.float32))
    view = View(camera, size, size, shading, settings=RenderSettings(
        samples_per_axis=n, adaptive=False, max_bounces=64, diffuse_bounces=64, glossy_bounces=64,
        transmission_bounces=64, clamp_indirect=0.0, filter_glossy=0.0))
    passes = tracer.render_tile(view, 0, 0, size, size)
    return passes["combined"][..., :3], passes["depth"] < 1e9


def principled(metallic, roughness, transmission, ior, specular):
    row = default_material_params(1)[0]
    row[:4], row[7] = (metallic, roughness, transmission, ior), specular
    return row


@pytest.fixture(scope="module")
def tracer():
    return Tracer()


def test_white_furnace(tracer):
    """A white sphere of any of the materials inside a uniform white world is invisible
    (energy neither lost nor made), up to noise and what compensation leaves at grazing."""
    for name, material in MATERIALS.items():
        image, hit = render_sphere(tracer, principled(*material))
        assert hit.mean() > 0.5
        assert abs(image[hit].mean() - 1.0) < 0.015, f"{name}: {image[hit].mean():.4f}"


def test_no_switch_at_a_roughness_threshold(tracer):
    """Metal and glass change continuously with roughness (there is no mirror/rough switch):
    a sphere under a world with a bright cap, at roughness steps of 0.02 around 0.1."""
    previous = None
    for roughness in (0.04, 0.06, 0.08, 0.1, 0.12, 0.14):
        images = [render_sphere(tracer, principled(m, roughness, t, 1.5, 0.5), world=(0.8, 0.9, 1.0),
                                base=(0.9, 0.6, 0.3), n=6)[0] for m, t in ((1, 0), (0, 1))]
        current = np.concatenate([i.ravel() for i in images])
        if previous is not None:
            change = np.abs(current - previous).mean() / previous.mean()
            assert change < 0.02, f"roughness {roughness}: the image changed by {change:.3f}"
        previous = current


def glossy_scene(tracer):
    """Rough metal, rough plastic and rough glass on a floor under an area light and a dim
    world: what used to stay noisy."""
    parts = [grid_plane(10.0, 1, 0.0), uv_sphere(32, 16, 0.5, (-1.1, 0, 0.5)),
             uv_sphere(32, 16, 0.5, (0, 0.3, 0.5)), uv_sphere(32, 16, 0.5, (1.1, 0, 0.5))]
    vertices, triangles = merge(*parts)
    ids = np.concatenate([np.full(len(p[1]), i) for i, p in enumerate(parts)]).astype(np.uint16)
    tracer.load(Scene.from_parts(Geometry(vertices, triangles, ids),
                                 build_kdtree(vertices, triangles)))
    params = np.stack([principled(0, 0.5, 0, 1.5, 0.0), principled(1, 0.3, 0, 1.5, 0.5),
                       principled(0, 0.25, 0, 1.5, 0.5), principled(0, 0.2, 1, 1.5, 0.5)])
    colours = np.array([[0.6, 0.6, 0.6, 1], [0.9, 0.7, 0.4, 1], [0.8, 0.2, 0.1, 1], [1, 1, 1, 1]],
                       np.float32)
    lights = [Light("AREA", (1, 1, 1), 200.0, (0.5, -2.0, 3.0), (-0.15, 0.6, -0.8), size_u=1.0,
                    size_v=1.0)]
    camera = Camera("PERSP", look_at((0, -4, 1.6), (0, 0, 0.4)), (0.45, 0.34), (0, 0), 0.1, 100)
    return View(camera, 24, 18, Shading(colours, lights, (0.1, 0.1, 0.12), params))


def test_rough_glossy_and_glass_converge(tracer):
    """The error against a 48 x 48 sample reference falls as 1 / sqrt(samples) from 16 to 256
    samples (a factor of 4; at least 3 here), so rough glossy and glass converge. Each error is
    over 8 images of other seeds: the rough glass's rare bright paths make one image's error a
    lottery."""
    view = glossy_scene(tracer)

    def image(n, seed):
        view.settings = RenderSettings(samples_per_axis=n, adaptive=False, seed=seed)
        return tracer.render_tile(view, 0, 0, view.width, view.height)["combined"][..., :3]
    reference = image(48, 0)
    errors = [np.sqrt(np.mean([np.mean((image(n, seed) - reference) ** 2) for seed in range(1, 9)]))
              for n in (4, 16)]
    assert errors[0] / errors[1] > 3.0, f"RMSE {errors[0]:.4f} at 16, {errors[1]:.4f} at 256"
    assert errors[1] < 0.03


def test_albedo_tables_match_a_fresh_integration():
    """kernels/shade/ggx_albedo.cl against its generator (.ci/ggx_albedo.py), re-integrated at
    a few entries."""
    spec = importlib.util.spec_from_file_location("ggx_albedo", KERNEL_DIR.parent / ".ci" / "ggx_albedo.py")
    generator = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(generator)
    text = (KERNEL_DIR / "shade" / "ggx_albedo.cl").read_text()

    def table(name):
        body = text.split(f"__constant float {name}[")[1].split("{", 1)[1].split("};")[0]
        return np.array([float(v) for v in re.findall(r"(-?[0-9.]+(?:e-?\d+)?)f", body)])
    e = table("GGX_E").reshape(generator.SIZE, generator.SIZE)
    n = generator.DIELECTRIC_SIZE
    glass = table("GLASS_E_ENTER").reshape(n, n, n)
    leave = table("GLASS_E_LEAVE").reshape(n, n, n)
    specular = table("SPECULAR_E").reshape(n, n, n)
    for r, m in ((31, 31), (10, 5), (20, 30)):
        mu, rough = m / (generator.SIZE - 1), r / (generator.SIZE - 1)
        assert abs(e[r, m] - generator.albedo(mu, rough, 64)) < 3e-3
    low, high = generator.IOR_RANGE
    for i, r, m in ((5, 8, 12), (15, 15, 3), (2, 12, 9)):
        ior, rough, mu = low + i / (n - 1) * (high - low), r / (n - 1), m / (n - 1)
        reflection, total = generator.dielectric_albedo(mu, rough, ior, 64)
        assert abs(specular[i, r, m] - reflection) < 3e-3
        assert abs(glass[i, r, m] - total) < 3e-3
        assert abs(leave[i, r, m] - generator.dielectric_albedo(mu, rough, 1 / ior, 64)[1]) < 3e-3


def render_program_under_sun(tracer, rows, size, sun=(0, 0, -1)):
    """The loaded scene (seen from z = 1 by an orthographic camera over [-1, 1]^2, one sample
    at each pixel centre) with one white diffuse material whose node program is `rows`
    (checked as the network's are), under a sun of irradiance 2: Combined RGB."""
    from kdtrace.core.scene.model import MATERIAL_PARAMS, check_node_program
    params = default_material_params(1)
    params[0, MATERIAL_PARAMS.index("specular")] = 0.0
    params[0, MATERIAL_PARAMS.index("program")] = 0
    check_node_program(rows.tolist(), params[:, MATERIAL_PARAMS.index("program")])
    shading = Shading(np.array([[1, 1, 1, 1]], np.float32),
                      [Light("SUN", (1, 1, 1), 2.0, direction=sun)], (0, 0, 0), params,
                      node_program=rows)
    m = np.eye(4)
    m[2, 3] = 1.0
    view = View(Camera("ORTHO", m, (1.0, 1.0), (0, 0), 0.01, 10.0), size, size, shading,
                settings=RenderSettings(samples_per_axis=1, adaptive=False, max_bounces=0))
    return tracer.render_tile(view, 0, 0, size, size)["combined"][..., :3]


def test_node_program_evaluates_per_hit_as_numpy_does(tracer):
    """A shader node program (checker on the UVs, math, colour ramp, multiply mix) sets the base
    colour per hit: under a sun straight down (one sample at each pixel centre, no specular)
    each pixel is that colour x E / pi, against the same nodes evaluated here in numpy."""
    from kdtrace.core.layout import (NODE_MATH_CODES, NODE_MIX_CODES, NODE_OP_CODES as OP,
                                     NODE_OUT_CODES)
    from kdtrace.core.layout import NODE_RAMP_SIZE, NODE_REF_REGISTER as R
    vertices, triangles = grid_plane(2.0, 1, 0.0)
    uvs = (vertices[triangles.reshape(-1)][:, :2] + 1.0) / 2.0          # u, v = (x, y + 1) / 2
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16),
                        uvs=uvs.astype(np.float32))
    tracer.load(Scene.from_parts(geometry, build_kdtree(vertices, triangles)))
    ramp = np.stack([np.linspace(0, 1, NODE_RAMP_SIZE), np.linspace(1, 0.2, NODE_RAMP_SIZE),
                     np.full(NODE_RAMP_SIZE, 0.5), np.ones(NODE_RAMP_SIZE)], 1)
    whole, lane = (lambda r: r * R + 4), (lambda r, k: r * R + k)
    code = [
        (OP["UV"], 0, 0, 0), (0, 0, 0, 0),
        (OP["CONST"], 2, 0, 0), (0.9, 0.2, 0.1, 1.0),
        (OP["CONST"], 3, 0, 0), (0.2, 0.3, 0.9, 1.0),
        (OP["CHECKER"], 1, whole(0), whole(2)), (whole(3), 3.0, 0, 0),
        (OP["CONST"], 5, 0, 0), (0.5, 0.5, 0.5, 0.5),
        (OP["MATH"], 4, lane(0, 0), lane(5, 0)), (lane(1, 3), NODE_MATH_CODES["MULTIPLY_ADD"], 1, 0),
        (OP["RAMP"], 6, lane(4, 0), 0), (0, 0, 1, 0),      # table offset set below
        (OP["MIX"], 7, lane(5, 0), whole(1)), (whole(6), NODE_MIX_CODES["MULTIPLY"], 0, 0),
        (OP["OUT"], 0, whole(7), 0), (0, NODE_OUT_CODES["BASE_COLOR"], 0, 0),
        (OP["END"], 0, 0, 0), (0, 0, 0, 0)]
    code[13] = (0, len(code) - 12, 1, 0)                      # the table follows END
    size = 24
    image = render_program_under_sun(tracer, np.array(code + [tuple(r) for r in ramp], np.float32),
                                     size)
    assert {"NODES"} <= set(tracer.last_render["features"])
    # numpy: the same nodes at the pixel centres (x right, y up)
    centres = (np.arange(size) + 0.5) / size
    u, v = np.meshgrid(centres, centres[::-1])
    p = (np.stack([u * 3, v * 3, np.zeros_like(u)], -1) + 1e-6) * 0.999999
    cell = np.abs(np.floor(p)).astype(int) % 2
    fac = ((cell[..., 0] == cell[..., 1]) == cell[..., 2]).astype(float)
    checker = np.where(fac[..., None] == 1, [0.9, 0.2, 0.1], [0.2, 0.3, 0.9])
    f = np.clip(np.clip(u * 0.5 + fac, 0, 1), 0, 1) * (NODE_RAMP_SIZE - 1)
    i = np.minimum(f.astype(int), NODE_RAMP_SIZE - 1)
    t = (f - i)[..., None]
    ramped = np.where(t > 0, (1 - t) * ramp[i, :3] + t * ramp[np.minimum(i + 1, NODE_RAMP_SIZE - 1), :3],
                      ramp[i, :3])
    base = 0.5 * checker + 0.5 * checker * ramped
    np.testing.assert_allclose(image, base * 2.0 / np.pi, rtol=2e-3, atol=1e-4)
    assert fac.min() == 0 and fac.max() == 1


def lookup3(*words):
    """Bob Jenkins' lookup3 of one to four uint32 words (arrays), as Cycles' hash_uint to
    hash_uint4."""
    def rot(x, k):
        return (x << np.uint32(k)) | (x >> np.uint32(32 - k))
    seed = np.uint32(0xdeadbeef + (len(words) << 2) + 13)
    with np.errstate(over="ignore"):
        a, b, c = (seed + (np.asarray(words[j], np.uint32) if j < len(words) else np.uint32(0))
                   for j in range(3))
        a, b, c = (np.array(v, np.uint32) for v in np.broadcast_arrays(a, b, c))
        if len(words) == 4:             # lookup3's mix, then the fourth word
            for x, y, z, k in ((a, c, b, 4), (b, a, c, 6), (c, b, a, 8), (a, c, b, 16),
                               (b, a, c, 19), (c, b, a, 4)):
                x -= y
                x ^= rot(y, k)
                y += z
            a += np.asarray(words[3], np.uint32)
        for x, y, k in ((c, b, 14), (a, c, 11), (b, a, 25), (c, b, 16), (a, c, 4), (b, a, 14),
                        (c, b, 24)):
            x ^= y
            x -= rot(y, k)
    return c


def noise_texture(p, detail, roughness, lacunarity, distortion, colour, kind="FBM", offset=0.0,
                  gain=1.0):
    """Cycles' Noise Texture (fBm normalised, or the other types) at points p (..., dims), in
    numpy (float64)."""
    dims = p.shape[-1]

    def gradient(h, f):
        if dims == 1:
            h = h & np.uint32(15)
            g = 1.0 + (h & np.uint32(7))
            return np.where(h & 8, -g, g) * f[0]
        if dims == 2:
            h = h & np.uint32(7)
            u, v = np.where(h < 4, f[0], f[1]), 2 * np.where(h < 4, f[1], f[0])
            return np.where(h & 1, -u, u) + np.where(h & 2, -v, v)
        if dims == 3:
            h = h & np.uint32(15)
            u = np.where(h < 8, f[0], f[1])
            v = np.where(h < 4, f[1], np.where((h == 12) | (h == 14), f[0], f[2]))
            return np.where(h & 1, -u, u) + np.where(h & 2, -v, v)
        h = h & np.uint32(31)
        u, v, t = np.where(h < 24, f[0], f[1]), np.where(h < 16, f[1], f[2]), np.where(h < 8, f[2], f[3])
        return np.where(h & 1, -u, u) + np.where(h & 2, -v, v) + np.where(h & 4, -t, t)

    def signed(q):
        cell = np.floor(q)
        f, i = q - cell, cell.astype(np.int64)
        fade = f * f * f * (f * (f * 6 - 15) + 10)
        total = 0.0
        for k in range(1 << dims):
            d = [(k >> j) & 1 for j in range(dims)]
            h = lookup3(*[(i[..., j] + d[j]).astype(np.uint32) for j in range(dims)])
            weight = np.prod([fade[..., j] if d[j] else 1 - fade[..., j] for j in range(dims)], axis=0)
            total = total + weight * gradient(h, [f[..., j] - d[j] for j in range(dims)])
        return {1: 0.25, 2: 0.6616, 3: 0.982, 4: 0.8344}[dims] * total

    octaves, rest = int(detail), detail - np.floor(detail)

    def fbm(q):
        if kind != "FBM":
            return fractal(q)
        amp, scale, sums, total = 1.0, 1.0, [], 0.0
        for _ in range(octaves + 2):
            total = total + amp * signed(scale * q)
            sums.append((total, amp))
            amp, scale = amp * roughness, scale * lacunarity
        norm = [0.5 * t / sum(a for _, a in sums[:n + 1]) + 0.5 for n, (t, _) in enumerate(sums)]
        return norm[octaves] + rest * (norm[octaves + 1] - norm[octaves])

    def fractal(q):
        """The other types, as Cycles' fractal_noise.h sums them (weights with the hybrid's
        early stop per point)."""
        values = [signed(q * lacunarity ** i) for i in range(octaves + 2)]
        if kind == "MULTIFRACTAL":
            value = np.prod([roughness ** i * values[i] + 1 for i in range(octaves + 1)], axis=0)
            return value * (rest * roughness ** (octaves + 1) * values[octaves + 1] + 1)
        if kind == "HETERO_TERRAIN":
            value = offset + values[0]
            for i in range(1, octaves + 1):
                value = value + (values[i] + offset) * roughness ** i * value
            return value + rest * (values[octaves + 1] + offset) * roughness ** (octaves + 1) * value
        if kind == "HYBRID_MULTIFRACTAL":
            value, weight, alive = 0.0, np.ones_like(values[0]), np.ones(values[0].shape, bool)
            for i in range(octaves + 1):
                alive &= weight > 0.001
                weight = np.minimum(weight, 1.0)
                signal = (values[i] + offset) * roughness ** i
                value = value + np.where(alive, weight * signal, 0.0)
                weight = np.where(alive, weight * gain * signal, weight)
            alive &= weight > 0.001
            signal = (values[octaves + 1] + offset) * roughness ** (octaves + 1)
            return value + np.where(alive, rest * np.minimum(weight, 1.0) * signal, 0.0)
        signal = (offset - np.abs(values[0])) ** 2              # ridged multifractal
        value = signal
        for i in range(1, octaves + 1):
            weight = np.clip(signal * gain, 0, 1)
            signal = (offset - np.abs(values[i])) ** 2 * weight
            value = value + signal * roughness ** i
        return value

    def seed_offset(seed):
        bits = lambda v: np.float32(v).view(np.uint32)
        h = [lookup3(bits(seed))] if dims == 1 else [lookup3(bits(seed), bits(k)) for k in range(dims)]
        return 100.0 + np.array([float(v) for v in h]) * (100.0 / 4294967296.0)
    p = p + distortion * np.stack([signed(p + seed_offset(k)) for k in range(dims)], -1)
    value = fbm(p)
    return np.stack([value] + ([fbm(p + seed_offset(dims)), fbm(p + seed_offset(dims + 1))] if colour
                               else [value] * 2), -1)


def test_noise_texture_is_cycles_perlin_fbm(tracer):
    """The Noise Texture instruction (fBm in 1D to 4D, and the other types in 3D, with a
    fractional detail, distortion and its Color) on a plane's Object coordinates (and W), as
    the base colour under a sun: each pixel is the numpy evaluation of Cycles' noise x E / pi."""
    from kdtrace.core.layout import NODE_NOISE_TYPE_CODES, NODE_OP_CODES as OP, NODE_OUT_CODES
    from kdtrace.core.layout import NODE_REF_REGISTER as R
    vertices, triangles = grid_plane(2.0, 1, 0.37)
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16),
                        uvs=np.zeros((3 * len(triangles), 2), np.float32))
    tracer.load(Scene.from_parts(geometry, build_kdtree(vertices, triangles)))
    whole = lambda r: r * R + 4
    detail, roughness, lacunarity, distortion, scale, w = 2.5, 0.6, 2.1, 0.4, 3.0, 0.3
    offset, gain = 0.9, 1.3
    size = 24
    centres = (np.arange(size) + 0.5) / size * 2 - 1
    x, y = np.meshgrid(centres, centres[::-1])
    point = np.stack([x, y, np.full_like(x, 0.37), np.full_like(x, w)], -1)
    for dims, kind in [(1, "FBM"), (2, "FBM"), (3, "FBM"), (4, "FBM")] + \
            [(3, kind) for kind in NODE_NOISE_TYPE_CODES if kind != "FBM"]:
        # normalize, Color, dimensions, type
        flags = 1 + 2 + 4 * dims + 32 * NODE_NOISE_TYPE_CODES[kind]
        code = [(OP["TRANSFORM"], 0, 0, 0), (0, 12, 0, 0),          # identity rows after END
                (OP["CONST"], 1, 0, 0), (detail, roughness, lacunarity, 1.0),
                (OP["CONST"], 2, 0, 0), (scale, offset, gain, 1.0),
                (OP["NOISE"], 3, whole(0), whole(1)), (whole(2), flags, distortion, w),
                (OP["OUT"], 0, whole(3), 0), (0, NODE_OUT_CODES["BASE_COLOR"], 0, 0),
                (OP["END"], 0, 0, 0), (0, 0, 0, 0),
                (1, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0, 0, 0, 0)]
        image = render_program_under_sun(tracer, np.array(code, np.float32), size)
        assert {"NODES", "NOISE"} <= set(tracer.last_render["features"])
        p = (point[..., 3:] if dims == 1 else point[..., :dims]) * scale
        expected = noise_texture(p, detail, roughness, lacunarity, distortion, True, kind, offset,
                                 gain)
        np.testing.assert_allclose(image, np.maximum(expected, 0) * 2.0 / np.pi, rtol=1e-3,
                                   atol=2e-4, err_msg=f"{dims}D {kind}")
        if dims > 1:
            assert expected.std() > 0.05 and np.abs(expected[..., 1] - expected[..., 0]).mean() > 0.03


def valid_reflection_normal(n, wi, ng=np.array([0, 0, 1.0])):
    """Cycles' ensure_valid_specular_reflection of normals n (..., 3) for the unit direction wi
    to the viewer over the geometric normal ng: tilted toward ng until the mirror reflection
    of wi is 0.01 (or 0.9 wi . ng) above the surface."""
    iz = wi @ ng
    threshold = min(0.9 * iz, 0.01)
    r = 2 * (n @ wi)[..., None] * n - wi
    x = n - (n @ ng)[..., None] * ng
    x /= np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-30)
    ix = x @ wi
    a, b = ix * ix + iz * iz, 2 * (ix * ix + iz * iz + iz * threshold)
    root = np.sqrt(np.maximum(b * b - 4 * a * (threshold + iz) ** 2, 0))
    nz2 = 0.25 * np.where(ix < 0, b + root, b - root) / a
    tilted = np.sqrt(np.maximum(1 - nz2, 0))[..., None] * x + np.sqrt(nz2)[..., None] * ng
    return np.where((r @ ng >= threshold)[..., None], n, tilted)


def test_normal_map_and_bump_set_the_shading_normal_as_numpy_does(tracer):
    """A tangent-space Normal Map of the colour (u, 0.5, 1) at Strength 0.7, then a Bump of the
    height u^2 on it (its Normal input; Distance 0, 0.5 and inverted) on a UV-mapped plane (u,
    v = (x, y + 1) / 2: the tangent is +x), under a slanted sun: each pixel is max(n . L, 0)
    E / pi for the normal numpy computes as Cycles' nodes do, times Cycles' bump shadowing (the
    GGX shadowing of alpha^2 = tan^2(tilt) / 8 at the light's angle to the unperturbed
    normal), the strongest tilts lifted as Cycles lifts normals that would mirror the view
    below the surface. One kernel for the three renders."""
    from kdtrace.core.layout import (NODE_MATH_CODES, NODE_NORMAL_SPACE_CODES, NODE_OP_CODES as OP,
                                     NODE_OUT_CODES, NODE_REF_REGISTER as R)
    vertices, triangles = grid_plane(2.0, 1, 0.0)
    uvs = (vertices[triangles.reshape(-1)][:, :2] + 1.0) / 2.0
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16),
                        uvs=uvs.astype(np.float32))
    tracer.load(Scene.from_parts(geometry, build_kdtree(vertices, triangles)))
    whole, lane = (lambda r: r * R + 4), (lambda r, k: r * R + k)
    normal_map = [(OP["UV"], 0, 0, 0), (0, 0, 0, 0),
                  (OP["CONST"], 1, 0, 0), (0.5, 0.5, 0.5, 0.5),
                  (OP["CONST"], 2, 0, 0), (1.0, 1.0, 1.0, 1.0),
                  (OP["COMBINE"], 3, lane(0, 0), lane(1, 0)), (lane(2, 0), 0, 0, 0),
                  (OP["CONST"], 4, 0, 0), (0.7, 0.7, 0.7, 0.7),
                  (OP["NORMAL_MAP"], 9, whole(3), lane(4, 0)),
                  (0, 0, NODE_NORMAL_SPACE_CODES["TANGENT"], 0)]
    heights = [(OP["CONST"], 5, 0, 0), (2.0, 2.0, 2.0, 2.0)]
    for step in range(3):           # u at the hit and at the two steps, squared
        heights += [(OP["UV"], 10 + 2 * step, 0, 0), (0, step, 0, 0),
                    (OP["MATH"], 11 + 2 * step, lane(10 + 2 * step, 0), lane(5, 0)),
                    (0, NODE_MATH_CODES["POWER"], 0, 0)]
    size, sun = 24, np.array([-0.5, 0.2, -1.0])
    centres = (np.arange(size) + 0.5) / size * 2 - 1
    x, _ = np.meshgrid(centres, centres[::-1])
    u = (x + 1) / 2
    light = -sun / np.linalg.norm(sun)
    mapped = np.stack([2 * u - 1, np.zeros_like(u), np.ones_like(u)], -1)
    mapped /= np.linalg.norm(mapped, axis=-1, keepdims=True)
    normal_in = np.array([0, 0, 1.0]) + (mapped - [0, 0, 1.0]) * 0.7
    normal_in /= np.linalg.norm(normal_in, axis=-1, keepdims=True)
    for distance, invert in ((0.0, 0), (0.5, 0), (0.5, 1)):
        program = normal_map + heights + [
            (OP["COMBINE"], 6, lane(11, 0), lane(13, 0)), (lane(15, 0), 0, 0, 0),
            (OP["CONST"], 7, 0, 0), (1.0, distance, 0.0, 1.0),
            (OP["BUMP"], 8, whole(6), whole(9)), (whole(7), invert, 1, 0),
            (OP["OUT"], 0, whole(8), 0), (0, NODE_OUT_CODES["NORMAL"], 0, 0),
            (OP["END"], 0, 0, 0), (0, 0, 0, 0)]
        image = render_program_under_sun(tracer, np.array(program, np.float32), size, sun)
        assert {"NODES", "NORMAL_MAP", "BUMP"} <= set(tracer.last_render["features"])
        # Cycles' bump with the steps along x and y: Rx = y x N, Ry = N x x, det = N.z, and
        # the height's gradient (u, 0): n = normalize(|N.z| N - distance sign(N.z) u Rx).
        n_x, n_z = normal_in[..., 0], normal_in[..., 2]
        rx = np.stack([n_z, np.zeros_like(u), -n_x], -1)
        n = np.abs(n_z)[..., None] * normal_in - \
            ((-1) ** invert * distance * np.sign(n_z) * u)[..., None] * rx
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        n = valid_reflection_normal(n, np.array([0, 0, 1.0]))      # seen straight from above
        alpha2 = np.clip(0.125 * (1 / n[..., 2] ** 2 - 1), 0, 1)
        shadowing = 2 / (1 + np.sqrt(1 + alpha2 * (1 / light[2] ** 2 - 1)))
        expected = (np.maximum(n @ light, 0) * shadowing * 2 / np.pi)[..., None].repeat(3, -1)
        np.testing.assert_allclose(image, expected, rtol=2e-3, atol=2e-4,
                                   err_msg=f"distance {distance} invert {invert}")
        assert expected.max() - expected.min() > 0.1


@pytest.mark.parametrize("bad", [
    lambda rows: rows.__setitem__(0, [99, 0, 0, 0]),                  # unknown operation
    lambda rows: rows.__setitem__(10, [6, 4, 8 * 40, 1]),             # register out of range
    lambda rows: rows.__setitem__(13, [0, 5000, 1, 0]),               # ramp table outside
    lambda rows: rows.__setitem__(16, [1, 0, 0, 0]),                  # no END
    lambda rows: rows.__setitem__(slice(0, 2), [[18, 0, 4, 4], [0, 0, 9, 0]]),  # normal map space
    lambda rows: rows.__setitem__(slice(0, 2), [[18, 0, 4, 4], [0, 900, 1, 0]]),  # its rows outside
])
def test_bad_node_programs_are_refused(bad):
    from kdtrace.core.scene.model import SceneError, check_node_program
    from kdtrace.core.layout import NODE_RAMP_SIZE
    # six UV instructions, a RAMP (its table 6 rows on: after the END), OUT, END, the table
    rows = [[2, 0, 0, 0], [0, 0, 0, 0]] * 6 + [[9, 6, 4 * 8, 0], [0, 6, 1, 0], [10, 0, 4, 0],
                                               [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]] \
        + [[0, 0, 0, 1]] * NODE_RAMP_SIZE
    check_node_program(rows, [0])
    bad(rows)
    with pytest.raises(SceneError):
        check_node_program(rows, [0])


def test_a_program_whose_tables_follow_in_another_order_is_accepted():
    """A TRANSFORM before a RAMP (the compiler writes the ramp's table first): the check skips
    both tables after the END whatever their order (a transform row of 0.9999 read as an
    operation refused the scene on every slave)."""
    from kdtrace.core.scene.model import check_node_program
    from kdtrace.core.layout import NODE_RAMP_SIZE, NODE_TRANSFORM_SIZE
    tables = 8                                              # the first table's row
    rows = [[16, 0, 0, 0], [0, tables + NODE_RAMP_SIZE, 0, 0],        # TRANSFORM
            [9, 1, 4, 0], [0, tables - 2, 1, 0],                      # RAMP
            [10, 0, 8 + 4, 0], [0, 0, 0, 0],                          # OUT
            [0, 0, 0, 0], [0, 0, 0, 0]]                               # END
    rows += [[0.5, 0.5, 0.5, 1.0]] * NODE_RAMP_SIZE + [[0.9999, 0, 0, 0.1]] * NODE_TRANSFORM_SIZE
    check_node_program(rows, [0])


def test_a_node_program_reading_a_missing_texture_is_refused():
    """Scene.check_view refuses a program whose Image Texture is not in the geometry."""
    from kdtrace.core.scene.model import MATERIAL_PARAMS, SceneError, default_material_params
    vertices, triangles = grid_plane(2.0, 1, 0.0)
    scene = Scene.from_parts(Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16)),
                             build_kdtree(vertices, triangles))
    params = default_material_params(1)
    params[0, MATERIAL_PARAMS.index("program")] = 0
    rows = np.array([[3, 0, 4, 0], [0, 2, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]], np.float32)
    view = View(Camera("ORTHO", np.eye(4)), 4, 4,
                Shading(np.ones((1, 4), np.float32), [], (0, 0, 0), params, node_program=rows))
    with pytest.raises(SceneError, match="reads texture 2"):
        scene.check_view(view)
