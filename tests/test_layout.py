"""The host/kernel layouts (core/layout.py): the generated header against the Python tables on
the OpenCL device, and no kernel file with layout numbers of its own."""
from __future__ import annotations

import math
import re

import numpy as np
import pytest

from kdtrace.core import layout
from kdtrace.core.opencl import KERNEL_DIR, kernel_source
from kdtrace.core.scene.model import (DEFAULT_MATERIAL_PARAMS, MATERIAL_PARAMS, Camera, Geometry,
                                      Light, Shading, View)
from kdtrace.slave.buffers import (light_intensity, pack_bounds, pack_camera, pack_lights,
                                   pack_materials, pack_triangles)
from kdtrace.slave.tracer import KERNEL_FILES
from tests.opencl_programs import programs_on

FIELDS = [f for node in layout.NODE_FORMATS for f in node.fields]


def header_numbers() -> dict:
    """Every number the header should define, by C name, as the tables give it."""
    numbers = {}
    for node in layout.NODE_FORMATS:
        numbers.update({c.name: c.value for c in node.constants})
        for f in node.fields:
            numbers.update({f"{f.name}_SHIFT": f.shift, f"{f.name}_BITS": f.bits,
                            f"{f.name}_MAX": f.max})
            if f.bits == 1:
                numbers[f"{f.name}_BIT"] = f.bit
    for codes in layout.CODES:
        numbers.update({f"{codes.prefix}_{name}": value for name, value in codes.codes.items()})
    for record in layout.RECORDS:
        numbers[f"{record.prefix}_SIZE"] = record.size
        numbers.update({f"{record.prefix}_{s.name.upper()}_SLOT": s.index for s in record.slots})
    for table in layout.COLUMNS:
        numbers[f"{table.prefix}_COLUMNS"] = len(table.columns)
        numbers.update({f"{table.prefix}_{name.upper()}": table.index(name)
                        for name in table.columns})
    numbers.update({f"{element.prefix}_BYTES": element.nbytes for element in layout.ELEMENTS})
    return numbers


@pytest.fixture(scope="module")
def device():
    return programs_on(None)


def run_kernel(device, source, name, out_count, *inputs, dtype=np.uint32):
    """Build header + source, run `name(out, inputs...)` on one work-item, return out."""
    cl, context, queue, programs = device
    kernel = programs.kernels(layout.c_header() + source, [])[name]
    mf = cl.mem_flags
    out = np.zeros(out_count, dtype)
    out_buf = cl.Buffer(context, mf.WRITE_ONLY, out.nbytes)
    buffers = [cl.Buffer(context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(a))
               for a in inputs]
    kernel(queue, (1,), None, out_buf, *buffers)
    cl.enqueue_copy(queue, out, out_buf)
    queue.finish()
    return out


def test_header_numbers_match_the_tables(device):
    numbers = header_numbers()
    body = "\n".join(f"    out[{i}] = (uint)({name});" for i, name in enumerate(numbers))
    source = f"__kernel void numbers(__global uint *out)\n{{\n{body}\n}}\n"
    got = run_kernel(device, source, "numbers", len(numbers))
    assert dict(zip(numbers, got.tolist())) == numbers
    # Every number in the header is one of these (nothing defined that the tables lack); the
    # rest are the kernels' parameter lists (tests/test_kernel_sources.py).
    defined = set(re.findall(r"^#define (\w+)(?: |$)", layout.c_header(), re.M))
    assert defined == set(numbers) | {"KDTRACE_LAYOUT"} | {k.macro for k in layout.KERNEL_PARAMS}


def test_node_field_macros_decode_and_encode_as_the_tables(device):
    rng = np.random.default_rng(5)
    words = np.concatenate([rng.integers(0, 1 << 32, 200, dtype=np.uint64),
                            [0, 0xFFFFFFFF, 1, 1 << 31]]).astype(np.uint32)
    n = len(words)
    lines = []
    for k, f in enumerate(FIELDS):
        lines.append(f"        out[(2 * {k}) * {n} + i] = {f.name}(w);")
        lines.append(f"        out[(2 * {k} + 1) * {n} + i] = {f.name}_PUT({f.name}(w));")
    body = "\n".join(lines)
    source = (f"__kernel void fields(__global uint *out, __global const uint *words)\n{{\n"
              f"    for (uint i = 0; i < {n}u; ++i) {{\n        uint w = words[i];\n{body}\n"
              f"    }}\n}}\n")
    got = run_kernel(device, source, "fields", 2 * len(FIELDS) * n, words).reshape(-1, n)
    for k, f in enumerate(FIELDS):
        value = f.get(words.astype(np.int64))
        np.testing.assert_array_equal(got[2 * k], value, err_msg=f.name)
        np.testing.assert_array_equal(got[2 * k + 1], f.put(value) & 0xFFFFFFFF, err_msg=f.name)
        assert f.put(f.max) >> f.shift == f.max and f.shift + f.bits <= 32


def test_node_fields_tile_their_words():
    """Within each kind of node word the fields do not overlap; the tag is bits 0-1 of all."""
    kinds = {"plain": [layout.PLAIN_TAG, layout.PLAIN_FIELD],
             "inner": [layout.TAG, layout.INNER_REF, layout.INNER_EMPTY_BELOW,
                       layout.INNER_EMPTY_ABOVE, layout.INNER_GROUP],
             "leaf32": [layout.TAG, layout.LEAF_WIDE, layout.LEAF32_COUNT],
             "leaf16": [layout.TAG, layout.LEAF_WIDE, layout.LEAF16_COUNT, layout.LEAF16_BASE]}
    for kind, fields in kinds.items():
        masks = [f.put(f.max) for f in fields]
        assert sum(masks) == 0xFFFFFFFF and np.bitwise_or.reduce(masks) == 0xFFFFFFFF, kind


# Names under the layout's prefixes that kernels define for their own purposes (not layouts).
LAYOUT_PREFIXES = ("KD_", "LIGHT_", "MATERIAL_", "CAMERA_", "BOUNDS_", "TRIANGLE_", "ACCUM_",
                   "STATS_", "TEXTURE_SIZE_", "CELL_", "BIN_", "CLIMB_", "LIFT_", "LAYOUT_COUNTS_",
                   "BUILD_REF_", "BUILD_SPLIT_", "WALK_")


def kernel_files():
    files = sorted(KERNEL_DIR.rglob("*.cl"))
    assert files
    return files


def test_no_kernel_defines_layout_numbers():
    """Kernels take layout numbers from the header only: none defines a header name again, nor
    an integer constant under a layout prefix (a private node bit, slot count or code)."""
    header = set(re.findall(r"^#define (\w+)", layout.c_header(), re.M))
    own_number = re.compile(r"^\s*#\s*define\s+((?:%s)\w*)\s+\(?(0x[0-9a-fA-F]+|\d+)u?\)?"
                            r"\s*(//.*)?$" % "|".join(LAYOUT_PREFIXES), re.M)
    for path in kernel_files():
        text = path.read_text()
        defined = set(re.findall(r"^\s*#\s*define\s+(\w+)", text, re.M))
        assert not defined & header, f"{path.name} defines {sorted(defined & header)} again"
        assert not own_number.findall(text), f"{path.name} defines {own_number.findall(text)}"


def slot_reads(record, pointer: str, out: str) -> list:
    """C lines writing every slot of the record at `pointer`, read through the header's names,
    to out[o++] (the slots in table order, lanes in order)."""
    lines = []
    for s in record.slots:
        name = f"{record.prefix}_{s.name.upper()}"
        if s.rows > 1:
            lines += [f"    for (int j = 0; j < {s.rows}; ++j) {{",
                      f"        float4 row = {name}({pointer})[j];",
                      f"        {out}[o++] = row.x; {out}[o++] = row.y; {out}[o++] = row.z;"
                      f" {out}[o++] = row.w;", "    }"]
        elif len(s.lanes) == 1:
            lines.append(f"    {out}[o++] = {name}({pointer});")
        else:
            vector = f"float{len(s.lanes)}"
            lanes = " ".join(f"{out}[o++] = v.s{k};" for k in range(len(s.lanes)))
            lines.append(f"    {{ {vector} v = {name}({pointer}); {lanes} }}")
    return lines


def slot_values(record, packed) -> np.ndarray:
    """What slot_reads writes for each record of `packed` (records, size, width)."""
    return np.concatenate([np.ravel(record.get(packed, s.name)) for s in record.slots])


def read_records(device, record, packed):
    """Every record of `packed` read by a kernel through the header's names, as slot_reads."""
    count = len(packed)
    per_record = len(slot_values(record, packed[0]))
    vector = f"float{record.width}"
    lines = "\n".join(slot_reads(record, "r", "out"))
    source = (f"__kernel void read(__global float *out, __global const {vector} *records)\n{{\n"
              f"    int o = 0;\n    for (int i = 0; i < {count}; ++i) {{\n"
              f"    __global const {vector} *r = records + {record.prefix}_SIZE * i;\n{lines}\n"
              f"    }}\n}}\n")
    got = run_kernel(device, source, "read", count * per_record, packed.astype(np.float32),
                     dtype=np.float32)
    return got.reshape(count, per_record)


LIGHTS = [Light("POINT", (1.0, 0.5, 0.25), 100.0, (1, 2, 3), radius=0.25),
          Light("SUN", (0.9, 1.0, 0.8), 3.0, direction=(0.2, 0.3, -2), radius=0.1),
          Light("SPOT", (1.0, 1.0, 1.0), 500.0, (-1, 0, 4), (0, 0.6, -0.8), spot_size=1.0,
                spot_blend=0.25, radius=0.5),
          Light("AREA", (0.5, 0.5, 1.0), 300.0, (0, 0, 5), (0, 0, -1), (2, 0, 0), (0, 0.5, 0),
                shape="RECTANGLE", size_u=1.5, size_v=0.75),
          Light("AREA", (1.0, 1.0, 1.0), 200.0, (2, 2, 2), (0, -1, 0), shape="DISK",
                size_u=0.5, size_v=0.5)]


def expected_light(light) -> dict:
    """Each LIGHT slot of a light, from its definition (docs/shading.md, docs/tracer.md)."""
    e = {"position": light.position, "direction": np.divide(light.direction,
                                                            np.linalg.norm(light.direction)),
         "intensity": light_intensity(light), "spot_cos_half": 0.0, "spot_smooth": 0.0,
         "radius": 0.0, "area_u": (0, 0, 0), "area_v": (0, 0, 0), "area_shape": 0.0,
         "sun_cos_half_angle": 1.0}
    if light.kind == "SPOT":
        e["spot_cos_half"] = math.cos(light.spot_size / 2)
        e["spot_smooth"] = 1.0 / ((1.0 - e["spot_cos_half"]) * light.spot_blend)
    if light.kind in ("POINT", "SPOT"):
        e["radius"] = light.radius
    if light.kind == "SUN":
        e["sun_cos_half_angle"] = math.cos(light.radius / 2)
    if light.kind == "AREA":
        e["area_u"] = np.multiply(light.axis_u, light.size_u / np.linalg.norm(light.axis_u))
        e["area_v"] = np.multiply(light.axis_v, light.size_v / np.linalg.norm(light.axis_v))
        e["area_shape"] = 1.0 if light.shape in ("DISK", "ELLIPSE") else 0.0
    return e


def test_lights_as_the_kernels_read_them(device):
    packed = pack_lights(LIGHTS).reshape(len(LIGHTS), layout.LIGHT.size, 4)
    got = read_records(device, layout.LIGHT, packed)
    np.testing.assert_array_equal(got, [slot_values(layout.LIGHT, p) for p in packed])
    for light, record in zip(LIGHTS, packed):
        for name, value in expected_light(light).items():
            np.testing.assert_allclose(layout.LIGHT.get(record, name), value, rtol=1e-6,
                                       atol=1e-7, err_msg=f"{light.kind} {name}")
    # The codes as the kernel compares them.
    tests = [f"LIGHT_KIND(r) == LIGHT_{kind}" for kind in layout.LIGHT_CODES]
    tests += [f"LIGHT_AREA_SHAPE(r) == LIGHT_SHAPE_{shape}" for shape in layout.AREA_SHAPE_CODES]
    body = "\n".join(f"        out[{len(tests)} * i + {k}] = {test};"
                     for k, test in enumerate(tests))
    source = (f"__kernel void codes(__global uint *out, __global const float4 *lights)\n{{\n"
              f"    for (int i = 0; i < {len(LIGHTS)}; ++i) {{\n"
              f"        __global const float4 *r = lights + LIGHT_SIZE * i;\n{body}\n    }}\n}}\n")
    codes = run_kernel(device, source, "codes", len(tests) * len(LIGHTS), packed.astype(np.float32))
    codes = codes.reshape(len(LIGHTS), len(tests))
    for light, row in zip(LIGHTS, codes):
        shape = "ELLIPSE" if light.kind == "AREA" and light.shape == "DISK" else "RECTANGLE"
        want = [kind == light.kind for kind in layout.LIGHT_CODES]
        want += [s == shape for s in layout.AREA_SHAPE_CODES]
        assert row.tolist() == want, light


def tracer_source(extra: str) -> str:
    return kernel_source(KERNEL_FILES) + "\n" + extra


def test_materials_as_material_at_reads_them(device):
    """shading.cl's material_at (with textures) on packed materials: each parameter where the
    exporter put it, the texture index and the texture-alpha flag (slot 3) as it reads them."""
    params = np.tile(np.array(DEFAULT_MATERIAL_PARAMS, np.float32), (3, 1))
    column = {name: i for i, name in enumerate(MATERIAL_PARAMS)}
    params[0, [column[n] for n in ("metallic", "roughness", "transmission", "ior")]] = (
        0.25, 0.125, 0.5, 1.25)
    params[0, [column["emission_r"], column["emission_g"], column["emission_b"]]] = (2, 3, 4)
    params[0, column["specular"]] = 0.75
    params[1, column["texture"]] = 0
    params[2, column["texture"]] = 1
    colours = np.array([[0.5, 0.25, 0.125, 1.0], [0.8, 0.6, 0.4, 0.5], [1.0, 1.0, 1.0, 1.0]],
                       np.float32)
    shading = Shading(colours, [], (0, 0, 0), params)
    texels = np.array([[0.5, 0.5, 0.5, 0.25], [0.25, 1.0, 0.5, 0.5]], np.float16)
    sizes = np.array([[0, 1, 1], [1, 1, 1]], np.uint32)   # two 1x1 textures
    packed = pack_materials(shading)
    fields = ("base.x", "base.y", "base.z", "alpha", "metallic", "roughness", "transmission",
              "ior", "emission.x", "emission.y", "emission.z", "specular")
    body = "\n".join(f"        out[{len(fields)} * i + {k}] = m.{f};" for k, f in enumerate(fields))
    source = tracer_source(
        "__kernel void materials(__global float *out, __global const float4 *materials,\n"
        "                        __global const ushort *ids, __global const float *uvs,\n"
        "                        __global const half *texels, __global const uint *sizes)\n{\n"
        "    Scene sc;\n    sc.materials = materials;\n    sc.material_ids = ids;\n"
        "    sc.uvs = uvs;\n    sc.texels = texels;\n    sc.tex_sizes = sizes;\n"
        "    for (uint i = 0; i < 3u; ++i) {\n"
        "        Material m = material_at(&sc, i, 0.25f, 0.25f);\n"
        f"{body}\n    }}\n}}\n")
    cl, context, queue, programs = device
    kernel = programs.kernels(source, ["-DKD_STACK_SIZE=32", "-DHAS_TEXTURES"])["materials"]
    inputs = [packed, np.arange(3, dtype=np.uint16), np.zeros((9, 2), np.float32), texels, sizes]
    mf = cl.mem_flags
    out = np.zeros((3, len(fields)), np.float32)
    out_buf = cl.Buffer(context, mf.WRITE_ONLY, out.nbytes)
    kernel(queue, (1,), None, out_buf,
           *[cl.Buffer(context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a) for a in inputs])
    cl.enqueue_copy(queue, out, out_buf)
    texel = texels.astype(np.float32)
    base = colours[:, :3] * np.stack([np.ones(3), texel[0, :3], texel[1, :3]])
    alpha = colours[:, 3] * np.array([1.0, texel[0, 3], texel[1, 3]])   # texture alpha drives alpha
    want = np.column_stack([base, alpha] + [params[:, column[n]] for n in (
        "metallic", "roughness", "transmission", "ior", "emission_r", "emission_g", "emission_b",
        "specular")])
    np.testing.assert_array_equal(out, want.astype(np.float32))


CAMERAS = [Camera("PERSP", [[0, 0, 1, 4], [1, 0, 0, -2], [0, 1, 0, 1], [0, 0, 0, 1]],
                  (0.6, 0.45), (0.05, -0.1), 0.25, 80.0),
           Camera("ORTHO", [[2, 0, 0, 1], [0, 0, -2, 3], [0, 2, 0, 0.5], [0, 0, 0, 1]],
                  (3.0, 2.0), (0.5, 0.0), 0.0, 1e30)]


@pytest.mark.parametrize("camera", CAMERAS, ids=lambda c: c.kind)
def test_camera_as_camera_ray_reads_it(device, camera):
    """render.cl's camera_ray and the camera slots it reads, on a packed camera, against the
    camera model (core/scene/model.py Camera) evaluated here."""
    view = View(camera, 64, 48, Shading(world_color=(0.25, 0.5, 0.75)))
    packed = pack_camera(view)
    got = read_records(device, layout.CAMERA, packed[None])[0]
    np.testing.assert_array_equal(got, slot_values(layout.CAMERA, packed))
    m = camera.to_world
    forward = m[:3, :3] @ (0, 0, -1)
    for name, value in {"to_world": m[:3], "ndc_scale": camera.ndc_scale,
                        "ndc_offset": camera.ndc_offset,
                        "view_axis": forward / np.linalg.norm(forward),
                        "clip_start": camera.clip_start, "clip_end": min(camera.clip_end, 3e38),
                        "width": 64, "height": 48, "world_color": (0.25, 0.5, 0.75)}.items():
        np.testing.assert_allclose(layout.CAMERA.get(packed, name), value, rtol=1e-6,
                                   err_msg=name)
    pixels = np.array([[0.5, 0.5], [63.5, 47.5], [10.25, 30.75], [32, 24]], np.float32)
    source = tracer_source(
        "__kernel void rays(__global float *out, __global const float4 *cam,\n"
        "                   __global const float *pixels)\n{\n"
        f"    for (int i = 0; i < {len(pixels)}; ++i) {{\n        float3 o, d;\n"
        "        camera_ray(cam, pixels[2 * i], pixels[2 * i + 1], (float2)(0.0f, 0.0f), 0.5f, &o, &d);\n"
        "        vstore3(o, 2 * i, out);\n        vstore3(d, 2 * i + 1, out);\n    }\n}\n")
    cl, context, queue, programs = device
    kernel = programs.kernels(source, ["-DKD_STACK_SIZE=32"])["rays"]
    mf = cl.mem_flags
    out = np.zeros((len(pixels), 2, 3), np.float32)
    out_buf = cl.Buffer(context, mf.WRITE_ONLY, out.nbytes)
    kernel(queue, (1,), None, out_buf,
           *[cl.Buffer(context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)
             for a in (packed, pixels)])
    cl.enqueue_copy(queue, out, out_buf)
    ndc = np.column_stack([pixels[:, 0] / 64 * 2 - 1, 1 - pixels[:, 1] / 48 * 2])
    p = ndc * camera.ndc_scale + camera.ndc_offset
    if camera.kind == "PERSP":
        origins = np.repeat(m[None, :3, 3], len(p), 0)
        directions = np.column_stack([p, -np.ones(len(p))]) @ m[:3, :3].T
    else:
        origins = np.column_stack([p, np.zeros(len(p)), np.ones(len(p))]) @ m[:3].T
        directions = np.repeat((m[:3, :3] @ (0, 0, -1))[None], len(p), 0)
    np.testing.assert_allclose(out[:, 0], origins, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(out[:, 1], directions, rtol=1e-5, atol=1e-5)


def test_bounds_and_triangles_as_the_traversal_reads_them(device):
    """make_kdtree's box and extent, and the corners triangle_corners gives the triangle test."""
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, -3]], np.float32)
    triangles = np.array([[0, 1, 2], [3, 2, 1]], np.uint32)
    geometry = Geometry(vertices, triangles, np.zeros(2, np.uint16))
    bounds = np.array([[-1.5, 0, -3], [1, 2, 0.5]], np.float32)
    source = tracer_source(
        "__kernel void tree(__global float *out, __global const float4 *bounds,\n"
        "                   __global const float4 *tri_verts)\n{\n"
        "    KdTree kd = make_kdtree(0, 0, 0, 0u, bounds);\n"
        "    vstore3(kd.bmin, 0, out);\n    vstore3(kd.bmax, 1, out);\n    out[6] = kd.extent;\n"
        "    for (uint t = 0; t < 2u; ++t) {\n"
        "        Corners c = triangle_corners(tri_verts, t);\n"
        "        for (int k = 0; k < 3; ++k) {\n"
        "            out[7 + 9 * t + k] = c.v0[k];\n            out[10 + 9 * t + k] = c.v1[k];\n"
        "            out[13 + 9 * t + k] = c.v2[k];\n        }\n    }\n}\n")
    cl, context, queue, programs = device
    kernel = programs.kernels(source, ["-DKD_STACK_SIZE=32"])["tree"]
    mf = cl.mem_flags
    out = np.zeros(7 + 18, np.float32)
    out_buf = cl.Buffer(context, mf.WRITE_ONLY, out.nbytes)
    kernel(queue, (1,), None, out_buf,
           *[cl.Buffer(context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)
             for a in (pack_bounds(bounds), pack_triangles(geometry))])
    cl.enqueue_copy(queue, out, out_buf)
    np.testing.assert_array_equal(out[:3], bounds[0])
    np.testing.assert_array_equal(out[3:6], bounds[1])
    assert out[6] == 3.0
    np.testing.assert_array_equal(out[7:].reshape(2, 3, 3), vertices[triangles])


def reachable_nodes(nodes):
    """(inner, leaves): the node indices a traversal reaches, by the tables (breadth-first)."""
    inner, leaves, level = [], [], np.zeros(1, np.int64)
    while len(level):
        w = nodes[level, 0].astype(np.int64)
        leaf = layout.TAG.get(w) == layout.LEAF_TAG
        leaves.append(level[leaf])
        level, w = level[~leaf], w[~leaf]
        inner.append(level)
        below = layout.INNER_GROUP.get(w) + layout.INNER_REF.get(w)
        above = below + 1 - layout.INNER_EMPTY_BELOW.get(w)
        level = np.concatenate([below[layout.INNER_EMPTY_BELOW.get(w) == 0],
                                above[layout.INNER_EMPTY_ABOVE.get(w) == 0]])
    return np.concatenate(inner), np.concatenate(leaves)


@pytest.fixture(scope="module")
def bunny_trees():
    from kdtrace.core.accel.compact import compact_tree
    from kdtrace.core.accel.kdtree import build_kdtree
    from tests.meshes import load_bunny
    vertices, triangles = load_bunny()
    tree = build_kdtree(vertices, triangles)
    return [compact_tree(tree, len(triangles), "compressed"),
            compact_tree(tree, len(triangles), "compressed", leaf16=False)]


@pytest.mark.parametrize("which", [0, 1], ids=["16-bit leaves", "32-bit leaves"])
def test_nodes_as_the_traversal_decodes_them(device, bunny_trees, which):
    """trace.cl's node routines (inner_node, tref_slot, leaf_node and the leaf lists), which
    trace_ray and trace_packet share, on every node a traversal reaches of a compact tree with
    T-reference slots (one and two triangles), elided children and 16- or 32-bit leaves (a
    leaf_shift of 5 for the 16-bit one, so the base's shift counts), against the tables."""
    ct = bunny_trees[which]
    shift = 5 if which == 0 else 0
    inner, leaves = reachable_nodes(ct.nodes)
    w = ct.nodes[inner, 0].astype(np.int64)
    has_ref = layout.INNER_REF.get(w)
    elided = layout.INNER_EMPTY_BELOW.get(w) | layout.INNER_EMPTY_ABOVE.get(w)
    assert has_ref.any() and elided.any()
    refs = ct.nodes[layout.INNER_GROUP.get(w)]
    assert ((refs[:, 1] != layout.NO_TRIANGLE) & (has_ref == 1)).any()
    lw = ct.nodes[leaves, 0].astype(np.int64)
    wide = layout.LEAF_WIDE.get(lw) == 1
    assert wide.all() if which == 0 else not wide.any()
    count = np.where(wide, layout.LEAF16_COUNT.get(lw), layout.LEAF32_COUNT.get(lw))
    offset = ct.nodes[leaves, 1].astype(np.int64)
    base = layout.LEAF16_BASE.get(lw) << shift
    want_tris = np.concatenate([
        (b + ct.leaf_index16[o:o + c].astype(np.int64)) if is16 else ct.leaf_index32[o:o + c]
        for b, o, c, is16 in zip(base, offset, count, wide)]).astype(np.uint32)
    below = layout.INNER_GROUP.get(w) + has_ref
    want_inner = np.column_stack([
        layout.TAG.get(w), ct.nodes[inner, 1], below, below + 1 - layout.INNER_EMPTY_BELOW.get(w),
        1 - layout.INNER_EMPTY_BELOW.get(w), 1 - layout.INNER_EMPTY_ABOVE.get(w), has_ref,
        np.where(has_ref == 1, refs[:, 0], 0),
        np.where(has_ref == 1, refs[:, 1] != layout.NO_TRIANGLE, 0),
        np.where((has_ref == 1) & (refs[:, 1] != layout.NO_TRIANGLE), refs[:, 1], 0),
    ]).astype(np.uint32)
    source = tracer_source("""
__kernel void decode(__global uint *out_inner, __global uint *out_leaf, __global uint *out_tris,
                     __global const uint *inner, uint inner_count, __global const uint *leaves,
                     uint leaf_count, __global const uint2 *nodes, __global const uint *leaf32,
                     __global const ushort *leaf16, uint leaf_shift, __global const float4 *bounds)
{
    KdTree kd = make_kdtree(nodes, leaf32, leaf16, leaf_shift, bounds);
    for (uint i = 0; i < inner_count; ++i) {
        uint2 n = load_node(&kd, inner[i]);
        InnerNode in = inner_node(n);
        uint2 refs = in.has_refs ? tref_slot(&kd, &in) : (uint2)(0u, 0u);
        bool second = in.has_refs && has_second_ref(refs);
        uint row[10] = {in.axis, as_uint(in.split), in.below, in.above, in.below_stored,
                        in.above_stored, in.has_refs, in.has_refs ? refs.x : 0u, second,
                        second ? refs.y : 0u};
        for (int k = 0; k < 10; ++k)
            out_inner[10 * i + k] = is_leaf(n) ? 0xDEADu : row[k];
    }
    uint t = 0;
    for (uint i = 0; i < leaf_count; ++i) {
        uint2 n = load_node(&kd, leaves[i]);
        LeafNode leaf = leaf_node(&kd, n);
        out_leaf[2 * i] = is_leaf(n);
        out_leaf[2 * i + 1] = leaf.count16 + leaf.count32;
        for (uint j = 0; j < leaf.count16; ++j)
            out_tris[t++] = leaf16_triangle(&leaf, j);
        for (uint j = 0; j < leaf.count32; ++j)
            out_tris[t++] = leaf32_triangle(&leaf, j);
    }
}
""")
    cl, context, queue, programs = device
    kernel = programs.kernels(source, ["-DKD_STACK_SIZE=32"])["decode"]
    mf = cl.mem_flags

    def buffer(a):
        a = np.ascontiguousarray(a)
        return cl.Buffer(context, mf.READ_ONLY | mf.COPY_HOST_PTR,
                         hostbuf=a if a.nbytes else np.zeros(1, a.dtype))

    outs = [np.zeros(want_inner.shape, np.uint32), np.zeros((len(leaves), 2), np.uint32),
            np.zeros(len(want_tris), np.uint32)]
    out_bufs = [cl.Buffer(context, mf.WRITE_ONLY, max(a.nbytes, 4)) for a in outs]
    kernel(queue, (1,), None, *out_bufs, buffer(inner.astype(np.uint32)), np.uint32(len(inner)),
           buffer(leaves.astype(np.uint32)), np.uint32(len(leaves)), buffer(ct.nodes),
           buffer(ct.leaf_index32), buffer(ct.leaf_index16), np.uint32(shift),
           buffer(pack_bounds(ct.bounds)))
    for host, buf in zip(outs, out_bufs):
        cl.enqueue_copy(queue, host, buf)
    queue.finish()
    np.testing.assert_array_equal(outs[0], want_inner)
    np.testing.assert_array_equal(outs[1], np.column_stack([np.ones(len(leaves)), count]))
    np.testing.assert_array_equal(outs[2], want_tris)


# What a kernel would write if it spelled a layout itself: a slot of a tracer record read by
# number (`cam[5].z`), a record buffer indexed with a literal stride (`materials[4 * id]`), and
# (in the traversal) a node word decoded with literal shifts and masks.
RECORD_BY_NUMBER = re.compile(
    r"\b(lights|materials|tri_verts|emitters|L|cam|bounds|accum|stats)\s*\[\s*\d+\s*\]\s*\."
    r"|\b(lights|materials|tri_verts|emitters)\s*[+\[]\s*\d+\s*\*")
FIELD_BY_NUMBER = re.compile(r"(>>|<<)\s*\d|&\s*(0x[0-9a-fA-F]+|\d+)u?\b")
SIGN_MASK = "& 0x7FFFFFFFu"      # |x| as a bit operation: not a layout


# In the builder's kernels: a column of a subtree root, cell, candidate or count row read by
# number (`root[6]`, `cell[3 + a]`), or such a buffer indexed with a literal stride.
BUILD_ROW_BY_NUMBER = re.compile(
    r"\b(root|cell|cells|out)\s*\[\s*\d+\s*[\]+]"
    r"|\b(roots|result|cand|cells|next_cells|stats|scratch|block)\s*[+\[]\s*\d+\s*\*")


def test_kernels_read_records_and_node_words_by_name():
    for path in kernel_files():
        for number, line in enumerate(path.read_text().splitlines(), 1):
            code = line.split("//")[0]
            assert not RECORD_BY_NUMBER.search(code), f"{path.name}:{number}: {line.strip()}"
            if path.parent.name == "build":
                assert not BUILD_ROW_BY_NUMBER.search(code), f"{path.name}:{number}: {line.strip()}"
            if path.parent.name == "trace":
                code = code.replace(SIGN_MASK, "")
                assert not FIELD_BY_NUMBER.search(code), f"{path.name}:{number}: {line.strip()}"


# ---------------------------------------------------------------------------------------------
# The kd-tree builder's and compactor's buffers (kernels/build/)

OPENCL_SCALAR_OR_VECTOR = re.compile(r"u?(char|short|int|long)\d*|float\d*|double\d*")


def test_build_elements_are_their_types_sizes():
    """The host sizes the buffers whose fields only kernels read by core/layout.py's ELEMENTS:
    each is sizeof(its C type) in the program that uses it, on the device, so that a struct
    changed on one side alone fails here."""
    from kdtrace.core.accel import binned, compact_cl
    from kdtrace.core.accel.kdtree import KDTreeParams
    builder = binned.BinnedBuilder("cpu")
    programs = [(binned.KERNEL_FILES, builder.build_options(KDTreeParams())),
                (compact_cl.KERNEL_FILES, compact_cl.program_options())]
    measured = {}
    for files, options in programs:
        source = kernel_source(files)
        known = [e for e in layout.ELEMENTS if OPENCL_SCALAR_OR_VECTOR.fullmatch(e.ctype)
                 or re.search(r"}\s*%s\s*;" % e.ctype, source)]
        body = "".join(f"    out[{i}] = sizeof({e.ctype});\n" for i, e in enumerate(known))
        probe = f"__kernel void element_sizes(__global uint* out)\n{{\n{body}}}\n"
        out = builder.buffer(nbytes=4 * len(known))
        builder.run(builder.kernels(source + probe, options)["element_sizes"], 1, out,
                    local_size=1)
        sizes = builder.read(out, np.uint32, len(known))
        measured.update({e.prefix: int(size) for e, size in zip(known, sizes)})
    assert measured == {e.prefix: e.nbytes for e in layout.ELEMENTS}


def test_vector_rows_name_every_lane(device):
    """A row that kernels load as one vector has a lane per column, and PREFIX_<NAME>_OF(v) is
    that column's lane, to write and to read."""
    tables = [table for table in layout.COLUMNS if table.vector]
    assert tables
    lines = []
    for k, table in enumerate(tables):
        assert int(re.search(r"\d+$", table.vector).group()) == len(table.columns), table.prefix
        lines.append(f"    {{ {table.vector} v = ({table.vector})(0u);")
        lines += [f"      {table.prefix}_{name.upper()}_OF(v) = {i}u;"
                  for i, name in enumerate(table.columns)]
        lines += [f"      out[{4 * k + i}] = v.s{i};" for i in range(len(table.columns))]
        lines.append("    }")
    source = "__kernel void lanes(__global uint *out)\n{\n" + "\n".join(lines) + "\n}\n"
    got = run_kernel(device, source, "lanes", 4 * len(tables)).reshape(-1, 4)
    for table, row in zip(tables, got):
        assert row[:len(table.columns)].tolist() == list(range(len(table.columns))), table.prefix


def test_corner_columns_follow_each_other():
    """Kernels read a row's corner as NAME_X + a for a = 0, 1, 2."""
    for table in layout.COLUMNS:
        for name in table.columns:
            if name.endswith("_x"):
                base = table.index(name)
                assert [table.index(name[:-1] + c) for c in "xyz"] == [base, base + 1, base + 2]
