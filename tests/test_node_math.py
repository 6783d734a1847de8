"""Every operation of Blender's Math and Vector Math nodes in the kernel's node programs, against
Cycles' formulas (svm_math, svm_vector_math) written here in numpy: a plane's UVs feed the
operation's inputs, its result becomes the base colour under a sun straight down."""
from __future__ import annotations

import numpy as np
import pytest

from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.layout import (NODE_MATH_CODES, NODE_OP_CODES as OP, NODE_OUT_CODES,
                                 NODE_REF_REGISTER as R, NODE_VECTOR_MATH_CODES)
from kdtrace.core.scene.model import Geometry
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.tracer import Tracer
from tests.meshes import grid_plane
from tests.test_materials import render_program_under_sun

SIZE = 16
B, C = 0.7, 0.3           # the second and third inputs (and their vectors' first lanes)
B3, C3 = (0.7, -0.4, 1.3), (0.3, 0.9, -0.2)


def safe_divide(a, b):
    with np.errstate(all="ignore"):
        return np.where(b != 0, a / np.where(b != 0, b, 1), 0.0)


def wrap(value, high, low):
    span = high - low
    with np.errstate(all="ignore"):
        return np.where(span != 0, value - span * np.floor((value - low) / np.where(span != 0, span, 1)), low)


def pingpong(a, b):
    if b == 0:
        return np.zeros_like(a)
    x = (a - b) / (b * 2)
    return np.abs((x - np.floor(x)) * b * 2 - b)


def smooth_min(a, b, k):
    h = np.maximum(k - np.abs(a - b), 0) / k
    return np.minimum(a, b) - h ** 3 * k / 6


def power(a, b):
    with np.errstate(all="ignore"):
        out = np.where(a < 0, np.where(b % 2 == 1, -1.0, 1.0) * np.abs(a) ** b, a ** b)
    return np.where((a < 0) & (b != np.floor(b)), 0.0, out)


MATH = {
    "ADD": lambda a, b, c: a + b, "SUBTRACT": lambda a, b, c: a - b,
    "MULTIPLY": lambda a, b, c: a * b, "DIVIDE": lambda a, b, c: safe_divide(a, b),
    "MULTIPLY_ADD": lambda a, b, c: a * b + c, "POWER": lambda a, b, c: power(a, b),
    "MINIMUM": lambda a, b, c: np.minimum(a, b), "MAXIMUM": lambda a, b, c: np.maximum(a, b),
    "LESS_THAN": lambda a, b, c: (a < b) * 1.0, "GREATER_THAN": lambda a, b, c: (a > b) * 1.0,
    "ABSOLUTE": lambda a, b, c: np.abs(a), "SQRT": lambda a, b, c: np.sqrt(np.maximum(a, 0)),
    "INVERSE_SQRT": lambda a, b, c: safe_divide(1.0, np.sqrt(np.maximum(a, 0))),
    "LOGARITHM": lambda a, b, c: np.where(a > 0, np.log(np.maximum(a, 1e-30)) / np.log(b), 0.0),
    "EXPONENT": lambda a, b, c: np.exp(a), "RADIANS": lambda a, b, c: np.radians(a),
    "DEGREES": lambda a, b, c: np.degrees(a), "SIGN": lambda a, b, c: np.sign(a),
    "COMPARE": lambda a, b, c: (np.abs(a - b) <= c) * 1.0,
    "SMOOTH_MIN": lambda a, b, c: smooth_min(a, b, c),
    "SMOOTH_MAX": lambda a, b, c: -smooth_min(-a, -b, c),
    "ROUND": lambda a, b, c: np.floor(a + 0.5), "FLOOR": lambda a, b, c: np.floor(a),
    "CEIL": lambda a, b, c: np.ceil(a), "TRUNC": lambda a, b, c: np.trunc(a),
    "FRACT": lambda a, b, c: a - np.floor(a), "MODULO": lambda a, b, c: np.fmod(a, b),
    "FLOORED_MODULO": lambda a, b, c: a - np.floor(a / b) * b,
    "WRAP": lambda a, b, c: wrap(a, b, c), "SNAP": lambda a, b, c: np.floor(a / b) * b,
    "PINGPONG": lambda a, b, c: pingpong(a, b), "SINE": lambda a, b, c: np.sin(a),
    "COSINE": lambda a, b, c: np.cos(a), "TANGENT": lambda a, b, c: np.tan(a),
    "SINH": lambda a, b, c: np.sinh(a), "COSH": lambda a, b, c: np.cosh(a),
    "TANH": lambda a, b, c: np.tanh(a), "ARCSINE": lambda a, b, c: np.arcsin(np.clip(a, -1, 1)),
    "ARCCOSINE": lambda a, b, c: np.arccos(np.clip(a, -1, 1)),
    "ARCTANGENT": lambda a, b, c: np.arctan(a), "ARCTAN2": lambda a, b, c: np.arctan2(a, b),
}


def normalized(v):
    length = np.linalg.norm(v, axis=-1, keepdims=True)
    return safe_divide(v, length)


def refract(x, n, eta):
    n = normalized(n)
    cosine = np.sum(n * x, -1, keepdims=True)
    k = 1 - eta * eta * (1 - cosine * cosine)
    return np.where(k < 0, 0.0, eta * x - (eta * cosine + np.sqrt(np.maximum(k, 0))) * n)


VECTOR_MATH = {     # (vector result, value result) of a (n, 3), b, c (3,), scale
    "ADD": lambda a, b, c, s: a + b, "SUBTRACT": lambda a, b, c, s: a - b,
    "MULTIPLY": lambda a, b, c, s: a * b, "DIVIDE": lambda a, b, c, s: safe_divide(a, b),
    "SCALE": lambda a, b, c, s: a * s,
    "DOT_PRODUCT": lambda a, b, c, s: np.sum(a * b, -1),
    "CROSS_PRODUCT": lambda a, b, c, s: np.cross(a, b),
    "LENGTH": lambda a, b, c, s: np.linalg.norm(a, axis=-1),
    "NORMALIZE": lambda a, b, c, s: normalized(a), "ABSOLUTE": lambda a, b, c, s: np.abs(a),
    "MINIMUM": lambda a, b, c, s: np.minimum(a, b), "MAXIMUM": lambda a, b, c, s: np.maximum(a, b),
    "MULTIPLY_ADD": lambda a, b, c, s: a * b + c,
    "DISTANCE": lambda a, b, c, s: np.linalg.norm(a - b, axis=-1),
    "PROJECT": lambda a, b, c, s: np.sum(a * b, -1, keepdims=True) / np.dot(b, b) * b,
    "REFLECT": lambda a, b, c, s: a - 2 * np.sum(normalized(b) * a, -1, keepdims=True) * normalized(b),
    "REFRACT": lambda a, b, c, s: refract(a, np.broadcast_to(b, a.shape), s),
    "FACEFORWARD": lambda a, b, c, s: a if np.dot(c, b) < 0 else -a,
    "SNAP": lambda a, b, c, s: np.floor(a / b) * b, "FLOOR": lambda a, b, c, s: np.floor(a),
    "CEIL": lambda a, b, c, s: np.ceil(a), "MODULO": lambda a, b, c, s: np.fmod(a, b),
    "FRACTION": lambda a, b, c, s: a - np.floor(a), "WRAP": lambda a, b, c, s: wrap(a, b, c),
    "SINE": lambda a, b, c, s: np.sin(a), "COSINE": lambda a, b, c, s: np.cos(a),
    "TANGENT": lambda a, b, c, s: np.tan(a), "POWER": lambda a, b, c, s: power(a, b),
    "SIGN": lambda a, b, c, s: np.sign(a),
}


@pytest.fixture(scope="module")
def tracer():
    tracer = Tracer()
    vertices, triangles = grid_plane(2.0, 1, 0.0)
    uvs = (vertices[triangles.reshape(-1)][:, :2] + 1.0) / 2.0
    tracer.load(Scene.from_parts(Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16),
                                          uvs=uvs.astype(np.float32)),
                                 build_kdtree(vertices, triangles)))
    return tracer


def whole(r):
    return r * R + 4


def lane(r, k):
    return r * R + k


def pixel_uvs():
    centres = (np.arange(SIZE) + 0.5) / SIZE
    return np.meshgrid(centres, centres[::-1])


def shown(code, tracer):
    """The base colour the program sets, read back from the render (E / pi per unit albedo)."""
    rows = np.array(code + [(OP["END"], 0, 0, 0), (0, 0, 0, 0)], np.float32)
    return render_program_under_sun(tracer, rows, SIZE) * np.pi / 2.0


# Registers: 0 UV; 1 a = 4u - 2 (all lanes: 4 (u, v, 0.5) - 2); 2 b; 3 c; 4 the operation; 5
# (out) 0.5 + 0.1 result, so that negative results show.
def inputs(b, c):
    return [(OP["UV"], 0, 0, 0), (0, 0, 0, 0),
            (OP["CONST"], 6, 0, 0), (4.0, 4.0, 4.0, 0.0),
            (OP["CONST"], 7, 0, 0), (-2.0, -2.0, 0.0, 0.0),
            (OP["CONST"], 2, 0, 0), (*b, 0.0),
            (OP["CONST"], 3, 0, 0), (*c, 0.0),
            (OP["VECTOR_MATH"], 1, whole(0), whole(6)),
            (whole(7), NODE_VECTOR_MATH_CODES["MULTIPLY_ADD"], 0, 0)]


def shifted(source):
    return [(OP["CONST"], 8, 0, 0), (0.1, 0.1, 0.1, 0.0), (OP["CONST"], 9, 0, 0), (0.5, 0.5, 0.5, 0.0),
            (OP["VECTOR_MATH"], 5, source, whole(8)),
            (whole(9), NODE_VECTOR_MATH_CODES["MULTIPLY_ADD"], 0, 0),
            (OP["OUT"], 0, whole(5), 0), (0, NODE_OUT_CODES["BASE_COLOR"], 0, 0)]


@pytest.mark.parametrize("operation", list(MATH))
def test_math_operation_is_cycles(tracer, operation):
    assert set(MATH) == set(NODE_MATH_CODES)
    code = inputs((B,) * 3, (C,) * 3) + [
        (OP["MATH"], 4, lane(1, 0), lane(2, 0)), (lane(3, 0), NODE_MATH_CODES[operation], 0, 0),
        (OP["COMBINE"], 10, lane(4, 0), lane(4, 0)), (lane(4, 0), 0, 0, 0)] + shifted(whole(10))
    image = shown(code, tracer)
    u, _ = pixel_uvs()
    with np.errstate(all="ignore"):
        expected = 0.5 + 0.1 * MATH[operation](4 * u - 2, np.float64(B), np.float64(C))
    np.testing.assert_allclose(image[..., 0], np.maximum(expected, 0), rtol=2e-3, atol=2e-4)


@pytest.mark.parametrize("operation", list(VECTOR_MATH))
def test_vector_math_operation_is_cycles(tracer, operation):
    assert set(VECTOR_MATH) == set(NODE_VECTOR_MATH_CODES)
    code = inputs(B3, C3) + [
        (OP["VECTOR_MATH"], 4, whole(1), whole(2)),
        (lane(3, 0) if operation in ("SCALE", "REFRACT") else whole(3),
         NODE_VECTOR_MATH_CODES[operation], 0, 0)]
    value = operation in ("DOT_PRODUCT", "LENGTH", "DISTANCE")
    code += [(OP["COMBINE"], 10, lane(4, 3), lane(4, 3)), (lane(4, 3), 0, 0, 0)] if value else []
    code += shifted(whole(10) if value else whole(4))
    image = shown(code, tracer)
    u, v = pixel_uvs()
    a = np.stack([4 * u - 2, 4 * v - 2, np.zeros_like(u)], -1)
    with np.errstate(all="ignore"):
        result = VECTOR_MATH[operation](a, np.array(B3), np.array(C3), C)
    result = np.broadcast_to(result[..., None], a.shape) if value else result
    np.testing.assert_allclose(image, np.maximum(0.5 + 0.1 * result, 0), rtol=2e-3, atol=2e-4)
