"""Materials of several closures (Mix Shader, Add Shader; docs/shading.md, Closures): the kernel's
closure sum and its choice of one scattering closure (kernels/shade/material.cl closures_eval)
against numpy, the Fresnel and Layer Weight nodes against Cycles' formulas (svm_node_fresnel,
svm_node_layer_weight) in numpy, a rendered mix against its expectation, and closure counts
from the network checked against the table."""
from __future__ import annotations

import numpy as np
import pytest

from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.layout import (CLOSURE_CODES, MATERIAL, NODE_LAYER_WEIGHT_CODES, NODE_MATH_CODES,
                                 NODE_OP_CODES as OP, NODE_OUT_CODES, NODE_REF_REGISTER as R)
from kdtrace.core.opencl import kernel_source
from kdtrace.core.scene.model import (MATERIAL_PARAMS, Camera, Geometry, Light, RenderSettings,
                                      SceneError, Shading, View, default_material_params)
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.buffers import material_emission, pack_materials
from kdtrace.slave.tracer import Tracer, kernel_files_through
from tests.meshes import grid_plane
from tests.opencl_programs import programs_on

COLUMN = {name: i for i, name in enumerate(MATERIAL_PARAMS)}

CLOSURES = r'''
// closures_eval on material `id` for n choices u = (i + 0.5) / n: the sums (once) and which
// closure each choice took (its base colour's red, distinct per closure).
__kernel void closures(__global float *out, __global const float4 *materials,
                       __global const ushort *ids, int n)
{
    Scene sc;
    sc.materials = materials;
    sc.material_ids = ids;
    for (int i = 0; i < n; ++i) {
        ClosureSum cs;
        Material m = closures_eval(&sc, 0u, 0.25f, 0.25f, 0, 0, ((float)i + 0.5f) / (float)n, &cs);
        out[8 + i] = m.base.x;
        if (i == 0) {
            vstore3(cs.emission, 0, out);
            vstore3(cs.transparency, 1, out);
            out[6] = cs.holdout;
            out[7] = cs.scatter;
        }
    }
}

// node_fresnel for kind k (-1 Fresnel, else a Layer Weight output) at each (cos, value, back).
__kernel void fresnel(__global float *out, __global const float4 *cases, int count)
{
    for (int i = 0; i < count; ++i) {
        float4 c = cases[i];
        ShadeInfo info;
        info.incoming = (float3)(sqrt(fmax(1.0f - c.x * c.x, 0.0f)), 0.0f, c.x);
        info.normal = (float3)(0.0f, 0.0f, 1.0f);
        info.backfacing = c.z > 0.0f;
        out[i] = node_fresnel((int)c.w, c.y, info.normal, &info);
    }
}
'''


def closure_set(rows):
    """Shading of one material of closures: rows of (kind, weight, base RGB, alpha, emission)."""
    params = default_material_params(len(rows))
    colours = np.ones((len(rows), 4), np.float32)
    for k, (kind, weight, base, alpha, emission) in enumerate(rows):
        params[k, COLUMN["kind"]] = CLOSURE_CODES[kind]
        params[k, COLUMN["weight"]] = weight
        params[k, [COLUMN["emission_r"], COLUMN["emission_g"], COLUMN["emission_b"]]] = emission
        colours[k] = (*base, alpha)
    params[0, COLUMN["closures"]] = len(rows)
    return Shading(colours, [], (0, 0, 0), params)


@pytest.fixture(scope="module")
def kernels():
    cl, context, queue, programs = programs_on(None)
    built = programs.kernels(kernel_source(kernel_files_through("shade/material.cl")) + CLOSURES,
                             ["-DKD_STACK_SIZE=32", "-DHAS_CLOSURES", "-DHAS_NODES"])

    def run(name, out_count, *inputs):
        out = np.zeros(out_count, np.float32)
        out_buf = cl.Buffer(context, cl.mem_flags.WRITE_ONLY, out.nbytes)
        built[name](queue, (1,), None, out_buf, *[
            a if isinstance(a, np.integer) else cl.Buffer(
                context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                hostbuf=np.ascontiguousarray(a)) for a in inputs])
        cl.enqueue_copy(queue, out, out_buf)
        return out
    return run


def test_closures_sum_and_choose_by_weight(kernels):
    """A Principled closure with alpha and emission, a second Principled, a tinted Transparent
    and a Holdout: emission x weight x alpha, transparency (colour x weight and Principled's
    1 - alpha), holdout and scattering weight as numpy sums them; the scattering closures are
    chosen in proportion to weight x alpha (stratified choices: exact to 1 / n)."""
    rows = [("PRINCIPLED", 0.2, (0.1, 0, 0), 0.5, (1.0, 0.5, 0.0)),
            ("PRINCIPLED", 0.5, (0.2, 0, 0), 1.0, (0.0, 0.0, 0.0)),
            ("TRANSPARENT", 0.3, (0.5, 0.6, 0.7), 1.0, (0.0, 0.0, 0.0)),
            ("HOLDOUT", 0.25, (0.3, 0, 0), 1.0, (0.0, 0.0, 0.0))]
    n = 600
    out = kernels("closures", 8 + n, pack_materials(closure_set(rows)), np.zeros(1, np.uint16),
                  np.int32(n))
    np.testing.assert_allclose(out[:3], [0.1, 0.05, 0.0], rtol=1e-6)
    np.testing.assert_allclose(out[3:6], 0.3 * np.array([0.5, 0.6, 0.7]) + 0.2 * 0.5, rtol=1e-6)
    assert out[6] == pytest.approx(0.25) and out[7] == pytest.approx(0.6)
    chosen = out[8:]
    assert set(chosen.tolist()) == {np.float32(0.1), np.float32(0.2)}
    assert abs((chosen < 0.15).mean() - 0.1 / 0.6) <= 1.0 / n


def test_an_emission_closure_only_emits(kernels):
    """A Principled closure and an Emission closure (Add Shader): the emission adds, only the
    Principled one scatters; the emitters' power per area is each closure's mean emission x
    weight (slave/buffers.py material_emission, as lights.cl emitter_pdf)."""
    rows = [("PRINCIPLED", 1.0, (0.4, 0, 0), 1.0, (0.0, 0.0, 0.0)),
            ("EMISSION", 0.4, (0.0, 0, 0), 1.0, (0.0, 2.0, 1.0))]
    shading = closure_set(rows)
    out = kernels("closures", 8 + 10, pack_materials(shading), np.zeros(1, np.uint16), np.int32(10))
    np.testing.assert_allclose(out[:3], [0.0, 0.8, 0.4], rtol=1e-6)
    assert out[7] == pytest.approx(1.0) and (out[8:] == np.float32(0.4)).all()
    assert material_emission(shading)[0] == pytest.approx(0.4 * 1.0)


def fresnel_dielectric_cos(cosi, eta):
    """Cycles' fresnel_dielectric_cos (kernel/closure/bsdf_util.h) in numpy."""
    c = np.abs(cosi)
    g = eta * eta - 1 + c * c
    root = np.sqrt(np.maximum(g, 0))
    a = (root - c) / (root + c)
    b = (c * (root + c) - 1) / (c * (root - c) + 1)
    return np.where(g > 0, 0.5 * a * a * (1 + b * b), 1.0)


def test_fresnel_and_layer_weight_are_cycles(kernels):
    """The Fresnel node (IOR, front and back) and Layer Weight's Fresnel and Facing outputs
    (Blend, including 0.5, where Facing is 1 - |cos|) against Cycles' formulas."""
    cases, want = [], []
    for cos in (1.0, 0.9, 0.6, 0.3, 0.05):
        for back in (0, 1):
            for ior in (1.0, 1.45, 2.5, 0.7):
                cases.append((cos, ior, back, -1))
                eta = max(ior, 1e-5)
                want.append(fresnel_dielectric_cos(cos, 1 / eta if back else eta))
            for blend in (0.0, 0.3, 0.5, 0.8, 1.0):
                cases.append((cos, blend, back, NODE_LAYER_WEIGHT_CODES["FRESNEL"]))
                eta = max(1 - blend, 1e-5)
                want.append(fresnel_dielectric_cos(cos, eta if back else 1 / eta))
                cases.append((cos, blend, back, NODE_LAYER_WEIGHT_CODES["FACING"]))
                b = min(max(blend, 0), 1 - 1e-5)
                exponent = 2 * b if b < 0.5 else 0.5 / (1 - b)
                want.append(1 - (abs(cos) ** exponent if blend != 0.5 else abs(cos)))
    out = kernels("fresnel", len(cases), np.array(cases, np.float32), np.int32(len(cases)))
    np.testing.assert_allclose(out, want, rtol=1e-4, atol=2e-6)   # float32: eta down to 1e-5


def test_a_mixed_material_renders_its_expectation():
    """A plane under a sun straight down, one sample per pixel centre and 64 choices: a Mix
    Shader of two diffuse colours by a factor its program computes from the UVs (u), with a
    tinted Transparent closure added over a black world: each pixel is ((1 - u) c1 + u c2)
    E / pi in expectation (the choice's noise: within 4 standard errors)."""
    vertices, triangles = grid_plane(2.0, 1, 0.0)
    uvs = (vertices[triangles.reshape(-1)][:, :2] + 1.0) / 2.0
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16),
                        uvs=uvs.astype(np.float32))
    tracer = Tracer()
    tracer.load(Scene.from_parts(geometry, build_kdtree(vertices, triangles)))
    c1, c2, tint = np.array([0.9, 0.2, 0.1]), np.array([0.1, 0.4, 0.9]), np.array([0.5, 0.5, 0.5])
    shading = closure_set([("PRINCIPLED", 1.0, c1, 1.0, (0, 0, 0)),
                           ("PRINCIPLED", 1.0, c2, 1.0, (0, 0, 0)),
                           ("TRANSPARENT", 1.0, tint, 1.0, (0, 0, 0))])
    lane, one = (lambda r, k: r * R + k), 1 * R
    weight = lambda inverted: [      # u (or 1 - u) as the closure's WEIGHT
        (OP["UV"], 0, 0, 0), (0, 0, 0, 0),
        (OP["CONST"], 1, 0, 0), (1.0, 1.0, 1.0, 1.0),
        (OP["MATH"], 2, one if inverted else lane(0, 0), lane(0, 0) if inverted else one),
        (0, NODE_MATH_CODES["SUBTRACT" if inverted else "MULTIPLY"], 0, 0),
        (OP["OUT"], 0, lane(2, 0), 0), (0, NODE_OUT_CODES["WEIGHT"], 0, 0),
        (OP["END"], 0, 0, 0), (0, 0, 0, 0)]
    program = np.array(weight(True) + weight(False), np.float32)
    shading.material_params[:, COLUMN["specular"]] = 0.0
    shading.material_params[0, COLUMN["program"]] = 0
    shading.material_params[1, COLUMN["program"]] = 10
    shading.node_program = program
    shading.lights = [Light("SUN", (1, 1, 1), 2.0, direction=(0, 0, -1))]
    m = np.eye(4)
    m[2, 3] = 1.0
    size, n = 16, 8
    view = View(Camera("ORTHO", m, (1.0, 1.0), (0, 0), 0.01, 10.0), size, size, shading,
                settings=RenderSettings(samples_per_axis=n, adaptive=False, max_bounces=0))
    image = tracer.render_tile(view, 0, 0, size, size)["combined"][..., :3]
    assert {"CLOSURES", "ALPHA", "NODES"} <= set(tracer.last_render["features"])
    centres = (np.arange(size) + 0.5) / size
    u = np.meshgrid(centres, centres)[0][..., None]
    # The sum of weights is 2: the path is weighted by 2 x the chosen closure over its
    # probability (transparency 1/2 of the time, to the black world).
    expected = ((1 - u) * c1 + u * c2) * 2.0 / np.pi
    spread = np.abs(c1 - c2) * 2.0 / np.pi + expected
    assert np.all(np.abs(image - expected) <= 4 * spread / n + 1e-3)
    assert abs(image.mean() / expected.mean() - 1) < 0.03


@pytest.mark.parametrize("closures, match", [
    (3, "past the"), (5, r"closures must be in"), (1.5, "whole number")])
def test_closure_counts_from_the_network_stay_inside_the_table(closures, match):
    """A material's closure count is checked against the rows after it (Python integers):
    none reaches past the table, none is more than MAX_CLOSURES or a fraction."""
    shading = closure_set([("PRINCIPLED", 1.0, (1, 1, 1), 1.0, (0, 0, 0))] * 2)
    d = shading.to_dict()
    d["material_params"][0][COLUMN["closures"]] = closures
    with pytest.raises(SceneError, match=match):
        Shading.from_dict(d)
    d["material_params"][0][COLUMN["closures"]] = 2
    assert Shading.from_dict(d).param("closures")[0] == 2
    assert MATERIAL.slot("closures").index == 4
