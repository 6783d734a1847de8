"""Exact bounds where a peer's numbers meet memory (issue 39, finding 1). Every size, offset and
index that a scene upload, a view or a message carries is checked in Python integers against
a cap (numpy's int64 and uint32 arithmetic wraps silently) before anything is done with it,
and the kernels clamp texel coordinates besides. Each product of a peer's numbers is tried
at 2^31, 2^32 - 1 and 2^32 where they apply, and each cap that keeps a kernel's 32-bit index
exact is checked against that index's width."""
from __future__ import annotations

import logging
import socket
import time

import numpy as np
import pytest

from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.layout import (ACCUM, LEAF16_BASE, LEAF16_INDEX_BITS, MATERIAL, MAX_LEAF_SHIFT,
                                 MESH, NODE_EXTENSION_CODES, NODE_MATH_CODES, NODE_OP_CODES,
                                 NODE_OUT_CODES, TRIANGLE)
from kdtrace.core.net import protocol
from kdtrace.core.net.protocol import MsgType, ProtocolError
from kdtrace.core.scene import scene as scene_module
from kdtrace.core.scene.instances import (MAX_MESHES, MAX_REFERENCED_TRIANGLES, InstanceSet)
from kdtrace.core.scene.model import (MATERIAL_PARAMS, MAX_IMAGE_SIDE, MAX_MATERIALS, MAX_NODE_ROWS,
                                      MAX_TEXTURE_SIDE, MAX_TRIANGLES, Camera, Geometry, Light,
                                      RenderSettings, SceneError, Shading, View, check_node_program,
                                      default_material_params)
from kdtrace.core.scene.scene import Scene
from tests.meshes import grid_plane
from tests.test_protocol import raw, send_raw, small_scene
from tests.conftest import FARM_SECRET
from tests.tls_peers import handshaken


def textured(sizes, texel_count=4) -> Geometry:
    """The two triangles of small_scene with `texel_count` texels and texture_sizes `sizes`."""
    geometry, _ = small_scene()
    return Geometry(geometry.vertices, geometry.triangles, geometry.material_ids,
                    uvs=np.zeros((6, 2), np.float32), texels=np.ones((texel_count, 4), np.float16),
                    texture_sizes=np.array(sizes, np.uint32).reshape(-1, 3))


def textured_upload(sizes, texel_count=4) -> dict:
    """SCENE_UPLOAD arrays of small_scene with those textures."""
    geometry, tree = small_scene()
    arrays = Scene.from_parts(geometry, tree).wire_arrays()
    arrays.update(uvs=np.zeros((6, 2), np.float32), texels=np.ones((texel_count, 4), np.float16),
                  texture_sizes=np.array(sizes, np.uint32).reshape(-1, 3))
    return arrays


# -- textures: offset + w x h <= texels ------------------------------------------------------
HUGE_TEXTURES = [(2 ** 31, 2 ** 31), (2 ** 32 - 1, 2 ** 32 - 1), (2 ** 32 - 1, 1),
                 (1, 2 ** 32 - 1), (MAX_TEXTURE_SIDE + 1, 1), (1, MAX_TEXTURE_SIDE + 1),
                 (0, 4), (4, 0)]


@pytest.mark.parametrize("width, height", HUGE_TEXTURES)
def test_textures_past_the_side_cap_are_refused_at_upload(width, height):
    """The finding: (2^32 - 1) x (2^32 - 1) over 4 texels passed the int64 check (the product
    passes 2^63 and wraps); refused now, from the wire and from the exporter, naming it."""
    with pytest.raises(SceneError, match=rf"texture 0 is {width} x {height} texels; each "
                                         rf"side must be 1 to {MAX_TEXTURE_SIDE}"):
        Scene.from_wire(textured_upload([0, width, height]))
    with pytest.raises(SceneError, match=rf"texture 0 is {width} x {height}"):
        textured([0, width, height]).validate()


def test_the_old_int64_check_wrapped_for_the_findings_texture():
    """Why the check is in Python integers: numpy's int64 product of the finding's sizes wraps
    below the texel count, so the old check let them through."""
    sizes = np.array([[0, 2 ** 32 - 1, 2 ** 32 - 1]], np.uint32).astype(np.int64)
    assert (sizes[:, 0] + sizes[:, 1] * sizes[:, 2] <= 4).all()       # wrapped
    assert 0 + (2 ** 32 - 1) * (2 ** 32 - 1) > 4                       # exact


@pytest.mark.parametrize("offset", [4, 2 ** 31, 2 ** 32 - 1])
def test_a_texture_past_the_end_of_the_texels_is_refused(offset):
    with pytest.raises(SceneError, match=rf"texture 0 \(1 x 1 texels from texel {offset}\) "
                                         rf"reaches past the end of the 4 texels"):
        Scene.from_wire(textured_upload([offset, 1, 1]))


def test_textures_at_the_caps_are_accepted_and_the_bad_one_is_named():
    textured([[3, 1, 1], [0, 2, 2]]).validate()                 # the last texel; all of them
    textured([0, MAX_TEXTURE_SIDE, 1], MAX_TEXTURE_SIDE).validate()
    textured([0, 1, MAX_TEXTURE_SIDE], MAX_TEXTURE_SIDE).validate()
    with pytest.raises(SceneError, match="texture 1 "):
        textured([[0, 2, 2], [1, 2, 2]]).validate()


# -- the kernel's texel reads stay inside the texture ------------------------------------------
TEXEL_PROBE = r"""
__kernel void probe(__global const half *texels, __global const uint *sizes,
                    __global const float2 *uv, __global const int *mode,
                    __global const int2 *xy, __global float4 *looked_up, __global float4 *read)
{
    uint i = get_global_id(0);
    Scene sc;
    sc.texels = texels;
    sc.tex_sizes = sizes;
    looked_up[i] = texture_lookup_ext(&sc, 1, uv[i], mode[i] & 1, mode[i] >> 1);
    read[i] = texel(&sc, sizes[TEXTURE_SIZE_COLUMNS + TEXTURE_SIZE_OFFSET],
                    (int)sizes[TEXTURE_SIZE_COLUMNS + TEXTURE_SIZE_WIDTH],
                    (int)sizes[TEXTURE_SIZE_COLUMNS + TEXTURE_SIZE_HEIGHT], xy[i].x, xy[i].y);
}
"""


def test_texel_reads_never_leave_the_texture():
    """A node program can hand the Image Texture any coordinate (inf * 0, inf - inf: NaN),
    which converts to any int; closest/repeat then read at y * w + x of INT_MIN (a crash
    before the clamp). Every lookup, and texel() at any int, reads the texture's own texels,
    never its neighbours' (sentinels 7 and 9 around a 3 x 2 texture)."""
    from kdtrace.core.opencl import kernel_source
    from kdtrace.slave.tracer import kernel_files_through
    from tests.opencl_programs import programs_on
    cl, context, queue, programs = programs_on("cpu")
    source = kernel_source(kernel_files_through("shade/textures.cl")) + TEXEL_PROBE
    kernel = programs.kernels(source, ["-DKD_STACK_SIZE=32", "-DHAS_TEXTURES"])["probe"]
    w, h = 3, 2
    texels = np.full((4 + w * h + 4, 4), 7.0, np.float16)
    texels[4 + w * h:] = 9.0
    own = np.arange(w * h * 4, dtype=np.float16).reshape(-1, 4) / 32
    texels[4:4 + w * h] = own
    sizes = np.array([[0, 2, 2], [4, w, h]], np.uint32)
    odd = [np.nan, np.inf, -np.inf, 3e38, -3e38, 0.5]
    uvs = np.array([(u, v) for u in odd for v in odd], np.float32)
    modes = [closest | (extension << 1) for closest in (0, 1)
             for extension in NODE_EXTENSION_CODES.values()]
    int_min, int_max = -2 ** 31, 2 ** 31 - 1
    coords = [(x, y) for x in (int_min, -1, 0, w - 1, w, int_max)
              for y in (int_min, -1, 0, h - 1, h, int_max)]
    n = len(uvs) * len(modes)
    uv = np.tile(uvs, (len(modes), 1))
    mode = np.repeat(np.array(modes, np.int32), len(uvs))
    xy = np.array([coords[i % len(coords)] for i in range(n)], np.int32)
    flags = cl.mem_flags
    inputs = [cl.Buffer(context, flags.READ_ONLY | flags.COPY_HOST_PTR, hostbuf=a)
              for a in (texels, sizes, uv, mode, xy)]
    looked_up, read = np.empty((n, 4), np.float32), np.empty((n, 4), np.float32)
    outputs = [cl.Buffer(context, flags.WRITE_ONLY, a.nbytes) for a in (looked_up, read)]
    kernel(queue, (n,), None, *inputs, *outputs)
    for host, buffer in zip((looked_up, read), outputs):
        cl.enqueue_copy(queue, host, buffer)
    queue.finish()
    assert not np.isin(looked_up, (7.0, 9.0)).any() and not np.isin(read, (7.0, 9.0)).any()
    own = own.astype(np.float32)
    closest = (mode & 1) == 1
    clip = (mode >> 1) == NODE_EXTENSION_CODES["CLIP"]
    for value in looked_up[closest & ~clip]:        # (Clip may give transparent black)
        assert (value == own).all(axis=1).any(), value
    clamped = np.clip(xy, 0, (w - 1, h - 1))
    np.testing.assert_array_equal(read, own[clamped[:, 1] * w + clamped[:, 0]])


def test_a_node_program_with_infinite_coordinates_renders_the_clamped_texel():
    """Render level: Math 1e9 ^ 1e9 = inf into a closest, repeating Image Texture (uv = inf
    - floor(inf) = NaN) shades as texel (0, 0), as a program that asks for that texel (the
    unclamped kernel crashed here)."""
    from kdtrace.slave.tracer import Tracer
    from tests.test_materials import render_program_under_sun
    texels = np.array([[1, 0, 0, 1], [0, 1, 0, 1], [0, 1, 0, 1], [0, 1, 0, 1]], np.float16)
    vertices, triangles = grid_plane(2.0, 1, 0.0)
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16),
                        uvs=np.zeros((3 * len(triangles), 2), np.float32), texels=texels,
                        texture_sizes=np.array([[0, 2, 2]], np.uint32))
    tracer = Tracer()
    tracer.load(Scene.from_parts(geometry, build_kdtree(geometry.vertices, geometry.triangles)))

    def program(coordinates):
        image = [[NODE_OP_CODES["IMAGE"], 2, 8 * coordinates + 4, 0],
                 [0, 0, 1, NODE_EXTENSION_CODES["REPEAT"]]]
        return np.array([[NODE_OP_CODES["CONST"], 0, 0, 0], [1e9, 1e9, 1e9, 1e9],
                         [NODE_OP_CODES["MATH"], 1, 0, 0], [0, NODE_MATH_CODES["POWER"], 0, 0],
                         [NODE_OP_CODES["CONST"], 3, 0, 0], [0.1, 0.1, 0, 0], *image,
                         [NODE_OP_CODES["OUT"], 0, 2 * 8 + 4, 0], [0, NODE_OUT_CODES["BASE_COLOR"], 0, 0],
                         [NODE_OP_CODES["END"], 0, 0, 0], [0, 0, 0, 0]], np.float32)
    infinite = render_program_under_sun(tracer, program(1), 4)
    assert np.isfinite(infinite).all() and infinite[..., 0].min() > 0.5
    np.testing.assert_array_equal(infinite, render_program_under_sun(tracer, program(3), 4))


# -- triangles ----------------------------------------------------------------------------------
def test_more_triangles_than_the_kernels_index_are_refused_before_any_work():
    """The kernels address corner rows as 3 * tri in 32 bits: at most MAX_TRIANGLES, checked
    first (a zero-stride array of 2^30 + 1 triangles: any pass over it would take seconds)."""
    assert 3 * MAX_TRIANGLES <= 2 ** 32 and TRIANGLE.size * MAX_TRIANGLES <= 2 ** 32
    geometry, _ = small_scene()
    geometry.triangles = np.broadcast_to(np.zeros(3, np.uint32), (MAX_TRIANGLES + 1, 3))
    with pytest.raises(SceneError, match=f"{MAX_TRIANGLES + 1} triangles, at most {MAX_TRIANGLES}"):
        geometry.validate()


# -- the compact kd-tree's leaves (their offsets at 32 bits: tests/test_protocol.py) ---------
def test_a_16_bit_leafs_triangle_fits_32_bits():
    """The kernel adds (base << leaf_shift) + entry in uint: at most 2^32 - 1 (validate_compact
    refuses it when it is no triangle: tests/test_protocol.py)."""
    top = (((1 << LEAF16_BASE.bits) - 1) << MAX_LEAF_SHIFT) + (1 << LEAF16_INDEX_BITS) - 1
    assert top <= 2 ** 32 - 1


# -- instanced scenes -------------------------------------------------------------------------
@pytest.fixture(scope="module")
def two_meshes():
    meshes = []
    for cells in (1, 2):
        vertices, triangles = grid_plane(2.0, cells, 0.0)
        geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16))
        meshes.append((geometry, build_kdtree(geometry.vertices, geometry.triangles)))
    offset = np.eye(4)
    offset[0, 3] = 3.0
    return meshes, Scene.from_instances(meshes, [0, 1], [np.eye(4), offset])


def test_too_many_meshes_are_refused_before_any_mesh_is_validated(two_meshes, monkeypatch):
    """mesh_counts of MAX_MESHES + 1 rows that add up to the arrays: refused before the
    per-mesh tree checks (each a validate_compact call) run MAX_MESHES + 1 times."""
    _, scene = two_meshes
    arrays = scene.wire_arrays()
    counts = np.zeros((MAX_MESHES + 1, 5), np.uint32)
    counts[0, :4] = arrays["mesh_counts"][:, :4].sum(axis=0)
    arrays.update(mesh_counts=counts,
                  mesh_bounds=np.repeat(arrays["mesh_bounds"][:1], MAX_MESHES + 1, axis=0))

    def validated(*args, **kwargs):
        raise AssertionError("a mesh was validated before the meshes were counted")
    monkeypatch.setattr(scene_module, "validate_compact", validated)
    with pytest.raises(SceneError, match=f"1 to {MAX_MESHES} meshes, got {MAX_MESHES + 1}"):
        Scene.from_wire(arrays)


def test_mesh_counts_are_summed_without_wrapping(two_meshes):
    """Triangle counts 2^32 - 1 and 3 add up to 2 in 32 bits (the scene's count), 2^32 + 2 in
    fact: refused."""
    _, scene = two_meshes
    arrays = scene.wire_arrays()
    total = int(arrays["mesh_counts"][:, 0].sum())
    arrays["mesh_counts"][:, 0] = [2 ** 32 - 1, total + 1]
    with pytest.raises(SceneError, match=rf"add up to \({2 ** 32 + total}, "):
        Scene.from_wire(arrays)


def test_bases_past_the_mesh_tables_32_bits_are_refused(two_meshes, monkeypatch):
    """The MESH table holds each mesh's bases in uint32 (the kernels' pointers): totals past
    MAX_MESH_BASE would wrap there (arrays that large are not made here: the cap lowered)."""
    _, scene = two_meshes
    monkeypatch.setattr(scene_module, "MAX_MESH_BASE", 3)
    with pytest.raises(SceneError, match="do not fit the 32-bit bases of the mesh table"):
        Scene.from_wire(scene.wire_arrays())


@pytest.mark.parametrize("mesh", [2 ** 32, 2 ** 32 + 1, 2, -1])
def test_instances_placed_on_meshes_outside_the_table_are_refused(two_meshes, mesh):
    """Scene.placed cast the indices to uint32 unchecked above: 2^32 became mesh 0."""
    _, scene = two_meshes
    with pytest.raises(SceneError, match=r"a mesh outside 0\.\.1"):
        scene.placed([0, mesh], [np.eye(4), np.eye(4)])


@pytest.mark.parametrize("visibility", [256, 256 + 31, -1, 2 ** 32])
def test_visibility_that_does_not_fit_a_byte_is_refused(two_meshes, visibility):
    """from_instances cast visibility to uint8 unchecked: 256 became 0 (an invisible
    instance), 287 every ray."""
    meshes, scene = two_meshes
    with pytest.raises(SceneError, match="instance visibility must be integers"):
        Scene.from_instances(meshes, [0, 1], [np.eye(4), np.eye(4)], visibility=[31, visibility])
    with pytest.raises(SceneError, match="instance visibility must be integers"):
        scene.placed([0, 1], [np.eye(4), np.eye(4)], [visibility, 31])


@pytest.mark.parametrize("tri_count, instances, accepted", [
    (2 ** 31, 2, False), (2 ** 32 - 1, 1, False), (2 ** 32 - 2, 1, True),
    ((2 ** 32 - 2) // 2, 2, True), (2 ** 32 - 1, 2 ** 10, False)])
def test_referenced_triangles_fit_the_hit_keys(tri_count, instances, accepted):
    """Each instance's triangles are numbered after the ones before (uint32 hit keys,
    0xFFFFFFFF: no hit): at most MAX_REFERENCED_TRIANGLES in all."""
    table = np.zeros((1, len(MESH.columns)), np.uint32)
    table[0, MESH.index("tri_count")] = tri_count
    bounds = np.array([[[0, 0, 0], [1, 1, 1]]], np.float32)
    check = lambda: InstanceSet.checked(
        np.zeros(instances, np.uint32), np.tile(np.eye(3, 4, dtype=np.float32), (instances, 1, 1)),
        np.full(instances, 31, np.uint8), table, bounds)
    if accepted:
        assert int(check().key_base[-1]) == (instances - 1) * tri_count
    else:
        with pytest.raises(SceneError, match=rf"reference {instances * tri_count} triangles, "
                                             rf"at most {MAX_REFERENCED_TRIANGLES}"):
            check()


# -- views, settings and the JSON's numbers ------------------------------------------------------
def view_dict(**changes) -> dict:
    d = View(Camera("ORTHO", np.eye(4)), 8, 8, Shading(), settings=RenderSettings()).to_dict()
    d.update(changes)
    return d


@pytest.mark.parametrize("changes, match", [
    ({"width": 2 ** 32}, "image width"), ({"width": 2 ** 31}, "image width"),
    ({"height": MAX_IMAGE_SIDE + 1}, "image height"), ({"region": [0, 0, 2 ** 32, 8]}, "region x1"),
    ({"region": [2 ** 32 - 1, 0, 8, 8]}, "region x0"),
    ({"settings": {"samples_per_axis": 2 ** 32}}, "samples_per_axis"),
    ({"settings": {"seed": 2 ** 31}}, "seed"),
    ({"settings": {"light_samples_per_axis": 2 ** 32 - 1}}, "light_samples_per_axis"),
    ({"settings": {"undersample": 1}}, "undersample must be true or false"),
    ({"settings": {"adaptive": "yes"}}, "adaptive must be true or false"),
    ({"settings": {"undersampling": True}}, "unknown render settings"),
])
def test_view_numbers_past_their_caps_are_refused(changes, match):
    with pytest.raises(SceneError, match=match):
        View.from_dict(view_dict(**changes))


def test_switches_travel_with_the_view():
    d = view_dict(settings=dict(RenderSettings(undersample=True, adaptive=False).to_dict()))
    settings = View.from_dict(d).settings
    assert settings.undersample and not settings.adaptive


def test_the_caps_keep_the_kernels_32_bit_indices_exact():
    """render_pixel's global pixel index py * width + px is a uint; its tile index
    ACCUM_SIZE * here an int; a material's node program row (program + materials x
    MATERIAL_SIZE) travels as a float32; a texel's index inside its texture y * w + x."""
    assert (MAX_IMAGE_SIDE - 1) * MAX_IMAGE_SIDE + MAX_IMAGE_SIDE - 1 <= 2 ** 32 - 1
    assert ACCUM.size * protocol.MAX_TILE_SIZE ** 2 <= 2 ** 31 - 1
    assert MAX_NODE_ROWS + MAX_MATERIALS * MATERIAL.size <= 2 ** 24
    assert MAX_TEXTURE_SIDE * MAX_TEXTURE_SIDE <= 2 ** 32


def test_program_rows_pack_exactly_at_the_caps():
    from kdtrace.slave.buffers import pack_materials
    params = default_material_params(MAX_MATERIALS)
    params[:, MATERIAL_PARAMS.index("program")] = MAX_NODE_ROWS - 2
    shading = Shading(np.ones((MAX_MATERIALS, 4), np.float32), [], (0, 0, 0), params,
                      node_program=np.zeros((MAX_NODE_ROWS, 4), np.float32))
    packed = pack_materials(shading)[:MAX_MATERIALS * MATERIAL.size].reshape(-1, MATERIAL.size, 4)
    rows = MATERIAL.get(packed, "program").astype(np.int64)
    assert (rows == MAX_NODE_ROWS - 2 + MAX_MATERIALS * MATERIAL.size).all()


HUGE = 10 ** 400        # a JSON integer: float() of it raises OverflowError


@pytest.mark.parametrize("where", [
    lambda d: d["camera"]["to_world"].__setitem__(3, HUGE),
    lambda d: d["camera"].__setitem__("clip_end", HUGE),
    lambda d: d["settings"].__setitem__("clamp_direct", HUGE),
    lambda d: d["shading"]["materials"][0].__setitem__(0, HUGE),
    lambda d: d["shading"].__setitem__("world_color", [HUGE, 0, 0]),
    lambda d: d["shading"].__setitem__("lights", [dict(Light("POINT", (1, 1, 1), 1.0).to_dict(),
                                                       power=HUGE)]),
    lambda d: d["shading"].__setitem__("node_program", [[HUGE, 0, 0, 0], [0, 0, 0, 0]]),
])
def test_integers_past_floats_range_are_refused_with_a_message(where):
    d = view_dict()
    where(d)
    with pytest.raises(SceneError, match="must be"):
        View.from_dict(d)


def test_message_fields_past_floats_range_are_refused():
    for value in (HUGE, -HUGE, float("nan"), float("inf")):
        with pytest.raises(ProtocolError, match="'render_ms' must be a finite number"):
            protocol.get_float({"render_ms": value}, "render_ms")
    assert protocol.get_float({"x": 2 ** 64}, "x") == 2.0 ** 64


# -- node programs ------------------------------------------------------------------------------
def chain(steps: int) -> list:
    """`steps` UV instructions, then END."""
    return [[NODE_OP_CODES["UV"], 0, 0, 0], [0, 0, 0, 0]] * steps + [[0, 0, 0, 0]] * 2


@pytest.mark.parametrize("row", [[NODE_OP_CODES["CONST"], -1, 0, 0],
                                 [NODE_OP_CODES["CONST"], 16, 0, 0],
                                 [NODE_OP_CODES["CONST"], 2 ** 31, 0, 0],
                                 [NODE_OP_CODES["CONST"], 0, 2 ** 32, 0],
                                 [NODE_OP_CODES["CONST"], 0, 0, -9]])
def test_a_constants_register_and_operands_are_checked(row):
    """The kernel writes a CONST into regs[dst] and reads its operand slots as every
    instruction's: a register outside the 16 was a write outside the work-item's registers."""
    check_node_program([[NODE_OP_CODES["CONST"], 15, 127, 0], [-1e9, 2, 3, 4]] + chain(0), [0])
    with pytest.raises(SceneError, match="node program row 0: register out of range"):
        check_node_program([row, [1, 2, 3, 4]] + chain(0), [0])


def test_a_node_program_ends_within_the_kernels_1024_instructions():
    check_node_program(chain(1024), [0])
    check_node_program(chain(1025), [2])
    with pytest.raises(SceneError, match="at row 0 does not end"):
        check_node_program(chain(1025), [0])


def _walked_to_an_end(rows, tables, start) -> bool:
    """The check as it was: a walk from `start` over instructions (rows not in a table) that
    are not END, up to 1024 of them, then an END."""
    def op(pc):
        return None if pc >= len(rows) or pc in tables else rows[pc][0]
    pc = start
    while (op(pc) or 0) > 0 and pc < 2 * 1024 + start:
        pc += 2
    return op(pc) == NODE_OP_CODES["END"]


def test_node_program_ends_are_those_a_walk_from_each_start_finds():
    """Instructions to the END counted once, from the last back (a walk from each of 65535
    starts took 2.5 s): the same starts accepted, on chains of random length, some with a
    RAMP whose table follows their END, from rows at random, in tables and past the end."""
    from kdtrace.core.layout import NODE_RAMP_SIZE
    rng = np.random.default_rng(7)
    for _ in range(8):
        rows, tables = [], set()
        while len(rows) < 3000:
            steps = int(rng.integers(0, 1200))
            rows += chain(steps)
            if steps and rng.random() < 0.5:      # the last step a RAMP, its table after END
                at = len(rows) - 4
                rows[at:at + 2] = [[NODE_OP_CODES["RAMP"], 0, 0, 0], [0, len(rows) - at, 0, 0]]
                tables.update(range(len(rows), len(rows) + NODE_RAMP_SIZE))
                rows += [[0, 0, 0, 1]] * NODE_RAMP_SIZE
        starts = [int(v) for v in rng.integers(0, (len(rows) + 8) // 2, 40) * 2]
        walked = [_walked_to_an_end(rows, tables, start) for start in starts]
        assert any(walked) and not all(walked)
        check_node_program(rows, [s for s, ok in zip(starts, walked) if ok])
        for start in (s for s, ok in zip(starts, walked) if not ok):
            with pytest.raises(SceneError, match=f"at row {start} does not end"):
                check_node_program(rows, [start])


def _shared_tables(instructions: int) -> list:
    """The quadratic case of issue 39: `instructions` TRANSFORM instructions, each with its
    table (the same rows after the END: the table list grew with every instruction and was
    searched at every row)."""
    from kdtrace.core.layout import NODE_TRANSFORM_SIZE
    rows_total = 2 * instructions + 2 + NODE_TRANSFORM_SIZE
    table = rows_total - NODE_TRANSFORM_SIZE
    rows = []
    for i in range(instructions):
        rows += [[NODE_OP_CODES["TRANSFORM"], 0, 0, 0], [0, table - 2 * i, 0, 0]]
    return rows + [[0, 0, 0, 0]] * 2 + [[0, 0, 0, 1]] * NODE_TRANSFORM_SIZE


def _check_seconds(rows, starts) -> float:
    """CPU seconds of the checks a frame's node program gets (the check, then the
    instructions the scene's features and textures read), the best of 3."""
    from kdtrace.core.scene.features import program_instructions
    best = float("inf")
    for _ in range(3):
        began = time.process_time()
        program = check_node_program(rows, starts)
        program_instructions(program, starts)
        best = min(best, time.process_time() - began)
    return best


def test_the_node_program_checks_take_linear_time():
    """Issue 39: 16,000 instructions took 3 s, a 16 MiB frame most of an hour. Tables and
    starts 8 times as many cost at most 16 times as long (linear: 8; the quadratic check:
    64), and the largest program the limits allow (2^20 rows: 2^19 instructions with tables,
    65535 materials starting in it) is checked in seconds."""
    def case(instructions, starts):
        rows = _shared_tables(instructions)
        return rows, [2 * (instructions - 1 - k % 1000) for k in range(starts)]
    small = _check_seconds(*case(4096, 1024))
    large = _check_seconds(*case(8 * 4096, 8 * 1024))
    assert large < 16 * small + 0.05, (small, large)
    rows, starts = case(MAX_NODE_ROWS // 2 - 4, MAX_MATERIALS)
    assert len(rows) <= MAX_NODE_ROWS
    began = time.process_time()
    check_node_program(rows, starts)
    assert time.process_time() - began < 15


def _instructions_walked(program, starts) -> set:
    """The rows program_instructions gave before (a walk from each start to its END)."""
    rows = set()
    for start in {int(v) for v in starts if v >= 0}:
        pc = start
        while pc < len(program) - 1 and program[pc, 0] != NODE_OP_CODES["END"]:
            rows.add(pc)
            pc += 2
    return rows


def test_program_instructions_are_each_starts_up_to_its_end():
    """program_instructions (linear) gives every instruction that a walk from each start to
    its END passes, once: on chains sharing their ends, from starts at random."""
    from kdtrace.core.scene.features import program_instructions
    rng = np.random.default_rng(11)
    for _ in range(20):
        rows = []
        while len(rows) < 600:
            steps = int(rng.integers(0, 40))
            rows += [[float(rng.integers(1, 9)), 0, 0, 0], [0, 0, 0, 0]] * steps + [[0, 0, 0, 0]] * 2
        program = np.array(rows, np.float32)
        starts = list(rng.integers(0, len(rows) // 2, 30) * 2) + [-1]
        got = program_instructions(program, np.array(starts, np.float32))
        walked = _instructions_walked(program, starts)
        expected = np.concatenate([program[sorted(walked)], program[[r + 1 for r in sorted(walked)]]],
                                  axis=1) if walked else np.zeros((0, 8), np.float32)
        assert got.tobytes() == expected.tobytes()


# -- array shapes in a message --------------------------------------------------------------------
@pytest.mark.parametrize("shape, dtype, needs", [
    ([2 ** 32, 2 ** 32, 4], "u1", 2 ** 66), ([2 ** 31, 2 ** 31, 2, 2], "u1", 2 ** 64),
    ([2 ** 32 - 1, 2 ** 32 - 1], "f4", (2 ** 32 - 1) ** 2 * 4),
    ([2 ** 39, 2 ** 39, 2 ** 39, 2 ** 39], "u2", 2 ** 157)])
def test_array_sizes_are_multiplied_exactly(shape, dtype, needs):
    """Shapes whose size in int64 wraps (to 0 for 2^64 and 2^66 bytes) must not match an empty
    payload."""
    a, b = socket.socketpair()
    try:
        send_raw(a, raw(MsgType.TILE_RESULT, {"arrays": [{"name": "a", "dtype": dtype,
                                                           "shape": shape}]}))
        with pytest.raises(ProtocolError, match=f"needs {needs} bytes"):
            protocol.recv_message(b)
    finally:
        a.close()
        b.close()


# -- a slave over the wire ----------------------------------------------------------------------
class _NoDevice:
    device_info = {"name": "none", "compute_units": 1, "memory": 0, "platform": "test"}
    build_seconds = 0.0


def _reply(channel) -> protocol.Message:
    while True:
        msg = channel.recv(allowed=protocol.SLAVE_TO_MASTER, wait=10)
        assert msg is not None, "the slave said nothing"
        if msg.type != MsgType.HEARTBEAT:
            return msg


def test_a_slave_refuses_out_of_bounds_numbers_with_a_message(caplog):
    """Over a socket to a slave: a frame of 2^32 tiles, a frame whose camera holds an integer
    past float's range, a tile index of 2^32 and the finding's texture (4 texels, (2^32 - 1)^2)
    are each refused with an ERROR naming the problem, never an unexpected error."""
    from kdtrace.slave.server import SlaveServer
    server = SlaveServer(_NoDevice(), "kdt-bounds", bind="127.0.0.1", port=0, secret=FARM_SECRET)
    server.start()
    geometry, tree = small_scene()
    scene = Scene.from_parts(geometry, tree)
    try:
        with caplog.at_level(logging.INFO, logger="kdtrace.slave"):
            channel, refusal = handshaken(server.address, heartbeat_s=HUGE, name="bounds")
            assert refusal.type == MsgType.ERROR
            assert "'heartbeat_s' must be a finite number" in refusal.header["message"]
            channel.close()

            channel, welcome = handshaken(server.address, name="bounds")
            assert welcome.type == MsgType.WELCOME
            channel.send(MsgType.SCENE_UPLOAD, {"scene_hash": scene.hash}, scene.wire_arrays())
            assert _reply(channel).header.get("present") is True
            big = View(Camera("ORTHO", np.eye(4)), MAX_IMAGE_SIDE, MAX_IMAGE_SIDE, Shading())
            channel.send(MsgType.FRAME_START, {"frame_id": 1, "scene_hash": scene.hash,
                                               "view": big.to_dict(), "tile_size": 1})
            error = _reply(channel)
            assert error.type == MsgType.ERROR and error.header["frame_id"] == 1
            assert f"{2 ** 32} tiles in the frame, at most {protocol.MAX_FRAME_TILES}" \
                in error.header["message"]
            huge = view_dict()
            huge["camera"]["to_world"][0] = HUGE
            channel.send(MsgType.FRAME_START, {"frame_id": 2, "scene_hash": scene.hash,
                                               "view": huge, "tile_size": 4})
            error = _reply(channel)
            assert error.type == MsgType.ERROR and error.header["frame_id"] == 2
            assert "camera to_world must be 16 numbers" in error.header["message"]
            channel.send(MsgType.FRAME_START, {"frame_id": 3, "scene_hash": scene.hash,
                                               "view": view_dict(), "tile_size": 4})
            channel.send(MsgType.TILE_REQUEST, {"frame_id": 3, "tile": 2 ** 32})
            error = _reply(channel)
            assert error.type == MsgType.ERROR and "'tile' must be an integer in [0, 3]" \
                in error.header["message"]
            channel.close()

            channel, welcome = handshaken(server.address, name="bounds")
            assert welcome.type == MsgType.WELCOME
            channel.send(MsgType.SCENE_UPLOAD, {"scene_hash": "0" * 32},
                         textured_upload([0, 2 ** 32 - 1, 2 ** 32 - 1]))
            error = _reply(channel)
            assert error.type == MsgType.ERROR
            assert "invalid scene upload: texture 0 is 4294967295 x 4294967295 texels" \
                in error.header["message"]
            channel.close()
    finally:
        server.close()
    assert "unexpected error" not in caplog.text and "Traceback" not in caplog.text, caplog.text
