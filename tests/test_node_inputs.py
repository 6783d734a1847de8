"""The nodes that read the hit, its object and the ray (issue 38): Color Attribute / Attribute
(a corner array in the texture table), Object Info (its table), Geometry and Light Path, each
as a node program's base colour on a plane under a sun straight down, seen from straight above
(tests/test_materials.py render_program_under_sun), against what numpy says they are."""
from __future__ import annotations

import numpy as np

from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.layout import (NODE_ATTRIBUTE_CODES, NODE_GEOMETRY_CODES, NODE_LIGHT_PATH_CODES,
                                 NODE_OBJECT_INFO_CODES, NODE_OP_CODES as OP, NODE_OUT_CODES,
                                 NODE_REF_REGISTER as R)
from kdtrace.core.scene.model import Geometry
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.tracer import Tracer
from tests.meshes import grid_plane
from tests.test_materials import render_program_under_sun

SIZE = 16
Z = 0.25
WHOLE = (lambda r: r * R + 4)


def program(op, params, lane=None, table=()):
    """One instruction `op` with `params` into register 0, its result (or one lane) as the base
    colour; `table` rows after the END (the instruction's p0 names them)."""
    out = WHOLE(0) if lane is None else lane
    code = [(OP[op], 0, 0, 0), (0, *params),
            (OP["OUT"], 0, out, 0), (0, NODE_OUT_CODES["BASE_COLOR"], 0, 0),
            (OP["END"], 0, 0, 0), (0, 0, 0, 0)]
    return np.array(code + [tuple(r) for r in table], np.float32)


def centres():
    c = (np.arange(SIZE) + 0.5) / SIZE * 2 - 1
    x, y = np.meshgrid(c, c[::-1])
    return x, y


def test_geometry_light_path_and_object_info_as_numpy_says():
    """Geometry's Position, Normal, True Normal, Incoming and Backfacing; Light Path's kind,
    length and depth of a camera ray; Object Info's location, Random, colour and indices."""
    vertices, triangles = grid_plane(2.0, 1, Z)
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16),
                        uvs=np.zeros((3 * len(triangles), 2), np.float32))
    tracer = Tracer()
    tracer.load(Scene.from_parts(geometry, build_kdtree(vertices, triangles)))
    x, y = centres()

    def render(rows):
        return render_program_under_sun(tracer, rows, SIZE) * np.pi / 2.0
    position = render(program("GEOMETRY", (NODE_GEOMETRY_CODES["POSITION"], 0, 0)))
    np.testing.assert_allclose(position[..., 0], np.maximum(x, 0), atol=1e-5)
    np.testing.assert_allclose(position[..., 1], np.maximum(y, 0), atol=1e-5)
    np.testing.assert_allclose(position[..., 2], Z, atol=1e-5)
    for output, want in (("NORMAL", (0, 0, 1)), ("TRUE_NORMAL", (0, 0, 1)),
                         ("INCOMING", (0, 0, 1)), ("BACKFACING", (0, 0, 0))):
        got = render(program("GEOMETRY", (NODE_GEOMETRY_CODES[output], 0, 0)))
        np.testing.assert_allclose(got, np.broadcast_to(want, got.shape), atol=1e-5, err_msg=output)
    assert "LIGHT_PATH" not in tracer.last_render["features"]
    for output, want in (("IS_CAMERA_RAY", 1), ("IS_SHADOW_RAY", 0), ("IS_DIFFUSE_RAY", 0),
                         ("RAY_LENGTH", 1 - Z), ("RAY_DEPTH", 0), ("TRANSPARENT_DEPTH", 0)):
        got = render(program("LIGHT_PATH", (NODE_LIGHT_PATH_CODES[output], 0, 0)))
        np.testing.assert_allclose(got, want, atol=1e-5, err_msg=output)
        assert "LIGHT_PATH" in tracer.last_render["features"]
    table = [(0.5, -0.25, 0.75, 0.375), (0.9, 0.6, 0.3, 0.7), (3, 0, 0, 0), (0, 0, 0, 0)]
    for output, want in (("LOCATION", (0.5, 0, 0.75)), ("RANDOM", 0.375), ("COLOR", (0.9, 0.6, 0.3)),
                         ("ALPHA", 0.7), ("OBJECT_INDEX", 3)):
        got = render(program("OBJECT_INFO", (6, NODE_OBJECT_INFO_CODES[output], 0), table=table))
        np.testing.assert_allclose(got, np.broadcast_to(want, got.shape), atol=1e-5, err_msg=output)


def test_an_attribute_blends_its_corners_values():
    """A Color Attribute: the exporter's value at each triangle corner (texels 3 t + k of its
    texture, laid out in rows of 4) blended by the hit's barycentrics; Alpha and Fac (the mean)
    as well."""
    vertices, triangles = grid_plane(2.0, 1, Z)
    rng = np.random.default_rng(5)
    # a value per vertex at its corners, so that both triangles agree along their edge
    corners = rng.uniform(0.1, 0.9, (len(vertices), 4)).astype(np.float16)[triangles.reshape(-1)]
    width = 4
    texels = np.zeros((-(-len(corners) // width) * width, 4), np.float16)
    texels[:len(corners)] = corners
    sizes = np.array([[0, width, len(texels) // width]], np.uint32)
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16),
                        uvs=np.zeros((3 * len(triangles), 2), np.float32), texels=texels,
                        texture_sizes=sizes)
    tracer = Tracer()
    tracer.load(Scene.from_parts(geometry, build_kdtree(vertices, triangles)))
    x, y = centres()
    points = np.stack([x, y], -1)
    expected = np.zeros((SIZE, SIZE, 4))
    values = corners.astype(np.float64).reshape(-1, 3, 4)
    for t, tri in enumerate(triangles):
        a, b, c = vertices[tri][:, :2].astype(np.float64)
        m = np.stack([b - a, c - a], 1)
        u, v = np.moveaxis(np.linalg.solve(m, (points - a)[..., None])[..., 0], -1, 0)
        inside = (u >= -1e-6) & (v >= -1e-6) & (u + v <= 1 + 1e-6)
        expected[inside] = ((1 - u - v)[..., None] * values[t, 0] + u[..., None] * values[t, 1]
                            + v[..., None] * values[t, 2])[inside]
    for output, want in (("COLOR", expected[..., :3]), ("ALPHA", expected[..., 3:]),
                         ("FAC", expected[..., :3].mean(-1, keepdims=True))):
        got = render_program_under_sun(tracer, program("ATTRIBUTE", (
            0, NODE_ATTRIBUTE_CODES[output], 0)), SIZE) * np.pi / 2.0
        np.testing.assert_allclose(got, np.broadcast_to(want, got.shape), atol=2e-5, err_msg=output)
    assert "TEXTURES" in tracer.last_render["features"]
