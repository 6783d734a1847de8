"""The procedural textures of node programs against Cycles' formulas written here in numpy
(kernel/svm/voronoi.h, wave.h, magic.h, brick.h, white_noise.h and util/hash.h): a plane's
Object coordinates feed the texture, its output becomes the base colour under a sun straight
down (tests/test_materials.py render_program_under_sun), so each pixel is the texture x E / pi."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.layout import (NODE_OP_CODES as OP, NODE_OUT_CODES, NODE_REF_REGISTER as R,
                                 NODE_VORONOI_FEATURE_CODES, NODE_VORONOI_METRIC_CODES,
                                 NODE_VORONOI_OUTPUT_CODES, NODE_WAVE_BANDS_CODES,
                                 NODE_WAVE_PROFILE_CODES, NODE_WAVE_RINGS_CODES,
                                 NODE_WAVE_TYPE_CODES)
from kdtrace.core.scene.model import Geometry
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.tracer import Tracer
from tests.meshes import grid_plane
from tests.test_materials import lookup3, noise_texture, render_program_under_sun

SIZE = 24
Z = 0.37
WHOLE = (lambda r: r * R + 4)


@pytest.fixture(scope="module")
def tracer():
    vertices, triangles = grid_plane(2.0, 1, Z)
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16),
                        uvs=np.zeros((3 * len(triangles), 2), np.float32))
    tracer = Tracer()
    tracer.load(Scene.from_parts(geometry, build_kdtree(vertices, triangles)))
    return tracer


def points():
    """The plane's points at the pixel centres (x right, y up, z = Z), (SIZE, SIZE, 3)."""
    centres = (np.arange(SIZE) + 0.5) / SIZE * 2 - 1
    x, y = np.meshgrid(centres, centres[::-1])
    return np.stack([x, y, np.full_like(x, Z)], -1)


def render(tracer, texture, b=(0, 0, 0), c=(0, 0, 0), params=(0, 0, 0), lane=None):
    """The plane rendered with `texture` (op name) of its Object coordinates (operand a), b and
    c as constants; its whole result (or one lane) as the base colour: the texture's value."""
    out = WHOLE(3) if lane is None else 3 * R + lane
    code = [(OP["TRANSFORM"], 0, 0, 0), (0, 14, 0, 0),          # identity rows after END
            (OP["CONST"], 1, 0, 0), (*b, 1.0),
            (OP["CONST"], 2, 0, 0), (*c, 1.0),
            (OP[texture], 3, WHOLE(0), WHOLE(1)), (WHOLE(2), *params),
            (OP["OUT"], 0, out, 0), (0, NODE_OUT_CODES["BASE_COLOR"], 0, 0),
            (OP["END"], 0, 0, 0), (0, 0, 0, 0),
            (0, 0, 0, 0), (0, 0, 0, 0),
            (1, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0, 0, 0, 0)]
    image = render_program_under_sun(tracer, np.array(code, np.float32), SIZE)
    return image * np.pi / 2.0


def check(image, expected, tolerance=2e-3, outliers=0.0, varies=True):
    """Every pixel within tolerance, but for a share `outliers` of them (where a texture jumps:
    a Voronoi cell's border, a brick's edge, which float rounding may put either side)."""
    expected = np.broadcast_to(np.maximum(expected, 0), image.shape)
    bad = np.abs(image - expected) > tolerance * (1 + np.abs(expected))
    assert bad.any(axis=-1).mean() <= outliers, (bad.any(axis=-1).mean(), image[bad][:4], expected[bad][:4])
    assert expected.std() > 0.02 or not varies


# ---------------------------------------------------------------------------------------------
# Cycles' hashes

def float_bits(v):
    return np.asarray(v, np.float32).view(np.uint32)


def hash_floats(*k):
    """hash_float_to_float ... hash_float4_to_float: lookup3 of the floats' bits in [0, 1]."""
    return lookup3(*[float_bits(v) for v in k]).astype(np.float64) / 4294967296.0


def hash_floats_to_float3(*k):
    n = len(k)
    one, two = [np.ones_like(np.asarray(k[0], np.float32)) * v for v in (1.0, 2.0)]
    if n == 1:
        return np.stack([hash_floats(*k), hash_floats(k[0], one), hash_floats(k[0], two)], -1)
    if n == 2:
        return np.stack([hash_floats(*k), hash_floats(*k, one), hash_floats(*k, two)], -1)
    if n == 3:
        return np.stack([hash_floats(*k), hash_floats(*k, one), hash_floats(*k, two)], -1)
    x, y, z, w = k
    return np.stack([hash_floats(x, y, z, w), hash_floats(z, x, w, y), hash_floats(w, z, y, x)], -1)


def hash_pcg(cells):
    """hash_int2_to_float2 .. hash_int4_to_float4 of int cells (..., dims) in [0, 1]."""
    with np.errstate(over="ignore"):
        v = np.asarray(cells, np.int64).astype(np.int32) * np.int32(1664525) + np.int32(1013904223)
        v = [v[..., k].copy() for k in range(v.shape[-1])]
        dims = len(v)
        for step in range(2):
            if step:
                v = [x ^ (x >> np.int32(16)) for x in v]
            if dims == 2:
                v[0] += v[1] * np.int32(1664525)
                v[1] += v[0] * np.int32(1664525)
            elif dims == 3:
                v[0] += v[1] * v[2]
                v[1] += v[2] * v[0]
                v[2] += v[0] * v[1]
            else:
                v[0] += v[1] * v[3]
                v[1] += v[2] * v[0]
                v[2] += v[0] * v[1]
                v[3] += v[1] * v[2]
    return np.stack([(x & np.int32(0x7FFFFFFF)).astype(np.float64) / 2147483648.0 for x in v], -1)


# ---------------------------------------------------------------------------------------------
# Voronoi

def cell_point(dims, cell):
    if dims == 1:
        return hash_floats(cell[..., 0].astype(np.float32))[..., None]
    return hash_pcg(cell)


def cell_colour(dims, cell):
    if dims == 1:
        return hash_floats_to_float3(cell[..., 0].astype(np.float32))
    if dims == 2:
        cell = np.concatenate([cell, np.zeros_like(cell[..., :1])], -1)
    return hash_pcg(cell)[..., :3]


def metric_distance(a, b, metric, exponent, dims, bound=False):
    d = np.abs(a - b)
    if dims == 1:
        return d[..., 0]
    if metric == "MANHATTAN":
        return d.sum(-1)
    if metric == "CHEBYCHEV":
        return d.max(-1)
    if metric == "MINKOWSKI":
        s = (d ** exponent).sum(-1)
        return s if bound else s ** (1 / exponent)
    s = (d * d).sum(-1)
    return s if bound else np.sqrt(s)


def voronoi_octave(coord, feature, metric, exponent, randomness, smoothness):
    dims = coord.shape[-1]
    cellf = np.floor(coord)
    inside = coord - cellf
    cell = cellf.astype(np.int64)
    smooth = feature == "SMOOTH_F1" and smoothness != 0
    r = 2 if smooth else 1
    offsets = [np.array(o[::-1]) for o in itertools.product(range(-r, r + 1), repeat=dims)]
    shape = coord.shape[:-1]
    d1, d2 = np.full(shape, np.inf), np.full(shape, np.inf)
    o1, o2 = np.zeros(coord.shape, np.int64), np.zeros(coord.shape, np.int64)
    p1, p2 = np.zeros(coord.shape), np.zeros(coord.shape)
    sd, sc, sp, h = np.zeros(shape), np.zeros(shape + (3,)), np.zeros(coord.shape), None
    for o in offsets:
        point = o + cell_point(dims, cell + o) * randomness
        if smooth:
            d = metric_distance(point, inside, metric, exponent, dims)
            if h is None:
                h = np.ones(shape)
            else:
                x = 0.5 + 0.5 * (sd - d) / smoothness
                h = np.where(x < 0, 0.0, np.where(x >= 1, 1.0, (3 - 2 * x) * x * x))
            corr = smoothness * h * (1 - h)
            sd = sd + h * (d - sd) - corr
            corr = corr / (1 + 3 * smoothness)
            sc = sc + h[..., None] * (cell_colour(dims, cell + o) - sc) - corr[..., None]
            sp = sp + h[..., None] * (point - sp) - corr[..., None]
            continue
        f2 = feature == "F2"
        d = metric_distance(point, inside, metric, exponent, dims, bound=not f2)
        first = d < d1
        second = ~first & (d < d2)
        d2, o2, p2 = (np.where(first, d1, np.where(second, d, d2)),
                      np.where(first[..., None], o1, np.where(second[..., None], o, o2)),
                      np.where(first[..., None], p1, np.where(second[..., None], point, p2)))
        d1, o1, p1 = (np.where(first, d, d1), np.where(first[..., None], o, o1),
                      np.where(first[..., None], point, p1))
    if smooth:
        return sd, sc, cellf + sp
    if feature == "F2":
        return d2, cell_colour(dims, cell + o2), p2 + cellf
    return (metric_distance(p1, inside, metric, exponent, dims), cell_colour(dims, cell + o1),
            p1 + cellf)


def voronoi(coord, scale, feature="F1", metric="EUCLIDEAN", exponent=1.0, detail=0.0,
            roughness=0.5, lacunarity=2.0, smoothness=1.0, randomness=1.0, normalize=False):
    """Cycles' Voronoi Texture (F1, F2, Smooth F1 with fractal detail) at coord (..., dims)
    times scale: (distance, colour, position)."""
    dims = coord.shape[-1]
    coord = coord * scale
    smoothness = min(max(smoothness / 2, 0), 0.5)
    reach = 0.5 + 0.5 * randomness
    max_distance = metric_distance(np.zeros(dims), np.full(dims, reach), metric, exponent,
                                   dims) * (2 if feature == "F2" else 1)
    amplitude, octave_scale, max_amplitude = 1.0, 1.0, 0.0
    distance, colour, position = 0.0, 0.0, 0.0
    zero_input = detail == 0 or roughness == 0
    for i in range(int(np.ceil(detail)) + 1):
        d, c, p = voronoi_octave(coord * octave_scale, feature, metric, exponent, randomness,
                                 smoothness)
        if zero_input:
            max_amplitude, distance, colour, position = 1.0, d, c, p
            break
        if i <= detail:
            max_amplitude += amplitude
            distance = distance + d * amplitude
            colour = colour + c * amplitude
            position = position + amplitude * (p / octave_scale - position)
            octave_scale *= lacunarity
            amplitude *= roughness
        elif detail % 1:
            rest = detail % 1
            max_amplitude += rest * amplitude
            distance = distance + rest * d * amplitude
            colour = colour + rest * c * amplitude
            position = position + rest * amplitude * (p / octave_scale - position)
    if normalize:
        distance = distance / (max_amplitude * max_distance)
        colour = colour / max_amplitude
    return distance, colour, position / scale


def voronoi_edge_radius(coord, scale, feature, randomness=1.0):
    """Cycles' Distance to Edge (one octave) and N-Sphere Radius at coord times scale."""
    dims = coord.shape[-1]
    coord = coord * scale
    cellf = np.floor(coord)
    inside = coord - cellf
    cell = cellf.astype(np.int64)
    offsets = [np.array(o[::-1]) for o in itertools.product(range(-1, 2), repeat=dims)]
    shape = coord.shape[:-1]
    points = [o + cell_point(dims, cell + o) * randomness for o in offsets]
    if feature == "DISTANCE_TO_EDGE":
        vectors = [p - inside for p in points]
        best, closest = np.full(shape, np.inf), np.zeros(coord.shape)
        for v in vectors:
            d = (v * v).sum(-1)
            closest = np.where((d < best)[..., None], v, closest)
            best = np.minimum(best, d)
        best = np.full(shape, np.inf)
        for v in vectors:
            perpendicular = v - closest
            lsq = (perpendicular * perpendicular).sum(-1)
            edge = (((closest + v) / 2) * perpendicular / np.sqrt(np.maximum(lsq, 1e-30))[..., None]).sum(-1)
            best = np.where(lsq > 0.0001, np.minimum(best, edge), best)
        return best
    best, closest, closest_offset = np.full(shape, np.inf), np.zeros(coord.shape), np.zeros(coord.shape, np.int64)
    for o, p in zip(offsets, points):
        d = ((p - inside) ** 2).sum(-1)
        closest = np.where((d < best)[..., None], p, closest)
        closest_offset = np.where((d < best)[..., None], o, closest_offset)
        best = np.minimum(best, d)
    best, second = np.full(shape, np.inf), np.zeros(coord.shape)
    for o in offsets:
        if not o.any():
            continue
        oo = o + closest_offset
        p = oo + cell_point(dims, cell + oo) * randomness
        d = ((closest - p) ** 2).sum(-1)
        second = np.where((d < best)[..., None], p, second)
        best = np.minimum(best, d)
    return np.sqrt(((second - closest) ** 2).sum(-1)) / 2


VORONOI_CASES = [   # dims, feature, metric, detail, normalize, output
    (3, "F1", "EUCLIDEAN", 0.0, False, "COLOR"),
    (3, "F1", "EUCLIDEAN", 0.0, False, "DISTANCE"),
    (2, "F2", "MANHATTAN", 0.0, True, "DISTANCE"),
    (3, "F1", "CHEBYCHEV", 2.5, True, "POSITION"),
    (4, "F1", "MINKOWSKI", 0.0, False, "DISTANCE"),
    (3, "SMOOTH_F1", "EUCLIDEAN", 1.0, False, "COLOR"),
    (2, "SMOOTH_F1", "EUCLIDEAN", 0.0, False, "DISTANCE"),
    (1, "F1", "EUCLIDEAN", 1.5, True, "COLOR"),
    (3, "DISTANCE_TO_EDGE", "EUCLIDEAN", 0.0, False, "DISTANCE"),
    (2, "N_SPHERE_RADIUS", "EUCLIDEAN", 0.0, False, "DISTANCE"),
]


@pytest.mark.parametrize("case", VORONOI_CASES, ids=lambda c: "-".join(map(str, c)))
def test_voronoi_is_cycles(tracer, case):
    """The Voronoi Texture: every feature, each metric, 1D to 4D, fractal detail and
    normalisation, its Distance, Color, Position and Radius, against Cycles' formulas."""
    dims, feature, metric, detail, normalize, output = case
    scale, roughness, lacunarity, smoothness, exponent, randomness, w = 2.5, 0.6, 2.2, 0.8, 1.5, 0.9, 0.3
    flags = dims + 8 * NODE_VORONOI_FEATURE_CODES[feature] + 64 * NODE_VORONOI_METRIC_CODES[metric] \
        + 512 * int(normalize) + 1024 * NODE_VORONOI_OUTPUT_CODES[output]
    image = render(tracer, "VORONOI", (scale, detail, roughness), (lacunarity, smoothness, exponent),
                   (flags, randomness, w))
    p = points()
    coord = np.concatenate([p, np.full(p.shape[:-1] + (1,), w)], -1) if dims == 4 else \
        p[..., :dims] if dims > 1 else np.full(p.shape[:-1] + (1,), w)
    if feature in ("DISTANCE_TO_EDGE", "N_SPHERE_RADIUS"):
        expected = voronoi_edge_radius(coord, scale, feature, randomness)[..., None]
    else:
        distance, colour, position = voronoi(coord, scale, feature, metric, exponent, detail,
                                             roughness, lacunarity, smoothness, randomness,
                                             normalize)
        expected = {"DISTANCE": distance[..., None], "COLOR": colour,
                    "POSITION": position[..., :3]}[output]
    check(image, expected, outliers=0.03)


def test_wave_magic_and_brick_are_cycles(tracer):
    """Wave (bands and rings, every profile, with distortion: Cycles' fBm), Magic (depth 0, 2
    and 5) and Brick (offset, squash, smooth mortar: its tint and mortar) against Cycles'
    formulas."""
    p = points()
    for wave, direction, profile, distortion in (("BANDS", "DIAGONAL", "SIN", 0.0),
                                                 ("BANDS", "X", "SAW", 3.0),
                                                 ("RINGS", "SPHERICAL", "TRI", 1.5),
                                                 ("RINGS", "Z", "SIN", 0.0)):
        flags = NODE_WAVE_TYPE_CODES[wave] + 2 * NODE_WAVE_BANDS_CODES.get(direction, 0) + \
            8 * NODE_WAVE_RINGS_CODES.get(direction, 0) + 32 * NODE_WAVE_PROFILE_CODES[profile]
        scale, detail, dscale, droughness, phase = 0.9, 2.0, 1.3, 0.55, 0.4
        image = render(tracer, "WAVE", (scale, distortion, detail), (dscale, droughness, phase),
                       (flags, 0, 0), lane=0)
        q = (p * scale + 0.000001) * 0.999999
        if wave == "BANDS":
            n = {"X": q[..., 0] * 20, "DIAGONAL": q.sum(-1) * 10}[direction]
        else:
            keep = {"SPHERICAL": (1, 1, 1), "Z": (1, 1, 0)}[direction]
            n = np.linalg.norm(q * keep, axis=-1) * 20
        n = n + phase
        if distortion:
            fbm = noise_texture(q * dscale, detail, droughness, 2.0, 0.0, False)[..., 0]
            n = n + distortion * (fbm * 2 - 1)
        expected = {"SIN": 0.5 + 0.5 * np.sin(n - np.pi / 2),
                    "SAW": (n / (2 * np.pi)) % 1,
                    "TRI": np.abs(n / (2 * np.pi) - np.floor(n / (2 * np.pi) + 0.5)) * 2}[profile]
        check(image, expected[..., None], outliers=0.01 if profile != "SIN" else 0.0)
    for depth in (0, 2, 5):
        scale, distortion = 1.7, 1.3
        image = render(tracer, "MAGIC", (scale, distortion, 0), params=(depth, 0, 0))
        px, py, pz = (np.fmod(p[..., k], 2 * np.pi) for k in range(3))
        x = np.sin((px + py + pz) * 5 * scale)
        y = np.cos((-px + py - pz) * 5 * scale)
        z = -np.cos((-px - py + pz) * 5 * scale)
        if depth > 0:
            x, y, z = x * distortion, y * distortion, z * distortion
            y = -np.cos(x - y + z) * distortion
            steps = [lambda x, y, z: (np.cos(x - y - z) * distortion, y, z),
                     lambda x, y, z: (x, y, np.sin(-x - y - z) * distortion),
                     lambda x, y, z: (-np.cos(-x + y - z) * distortion, y, z),
                     lambda x, y, z: (x, -np.sin(-x + y + z) * distortion, z)]
            for step in steps[:depth - 1]:
                x, y, z = step(x, y, z)
        x, y, z = (v / (2 * distortion) for v in (x, y, z))
        check(image, np.stack([0.5 - x, 0.5 - y, 0.5 - z], -1))
    scale, size, smooth, bias, width, height = 1.6, 0.05, 0.3, 0.1, 0.5, 0.25
    offset, frequency, squash, squash_frequency = 0.4, 2, 1.5, 3
    image = render(tracer, "BRICK", (scale, size, smooth), (bias, width, height),
                   (frequency + 256 * squash_frequency, offset, squash))
    q = p * scale
    row = np.floor(q[..., 1] / height).astype(np.int64)
    widths = np.where(row % squash_frequency != 0, width, width * squash)
    shift = np.where(row % frequency != 0, 0.0, widths * offset)
    brick = np.floor((q[..., 0] + shift) / widths).astype(np.int64)
    x = (q[..., 0] + shift) - widths * brick
    y = q[..., 1] - height * row
    n = ((((row << 16) + (brick & 0xFFFF)) + 1013) & 0x7FFFFFFF).astype(np.uint64)
    n = (n >> np.uint64(13)) ^ n
    nn = (n * (n * n * 60493 + 19990303) + 1376312589) & 0x7FFFFFFF
    tint = np.clip(0.5 * nn / 1073741824.0 + bias, 0, 1)
    edge = np.minimum(np.minimum(x, y), np.minimum(widths - x, height - y))
    f = np.clip((1 - edge / size) / smooth, 0, 1)
    mortar = np.where(edge >= size, 0.0, 3 * f * f - 2 * f ** 3)
    check(image[..., :2], np.stack([tint, mortar], -1), outliers=0.02)


WHITE_NOISE = r'''
__kernel void white_noise(__global float4 *out, __global const float4 *points, int count, int flags)
{
    for (int i = 0; i < count; ++i)
        out[i] = node_white_noise(flags & 7, points[i], (flags & 8) != 0);
}
'''


def test_white_noise_is_cycles_hash():
    """White Noise (1D to 4D, Value and Color) on given points: Cycles' lookup3 of the floats'
    bits, exactly (a hash has no tolerance: the points go in as bits)."""
    from kdtrace.core.opencl import kernel_source
    from kdtrace.slave.tracer import kernel_files_through
    from tests.opencl_programs import programs_on
    cl, context, queue, programs = programs_on(None)
    kernel = programs.kernels(kernel_source(kernel_files_through("shade/noise.cl")) + WHITE_NOISE,
                              ["-DKD_STACK_SIZE=32", "-DHAS_NOISE"])["white_noise"]
    rng = np.random.default_rng(3)
    pts = (rng.normal(size=(64, 4)) * 10).astype(np.float32)
    mf = cl.mem_flags
    source = cl.Buffer(context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=pts)
    out = np.zeros((64, 4), np.float32)
    out_buf = cl.Buffer(context, mf.WRITE_ONLY, out.nbytes)
    for dims in (1, 2, 3, 4):
        for colour in (False, True):
            kernel(queue, (1,), None, out_buf, source, np.int32(64), np.int32(dims + 8 * colour))
            cl.enqueue_copy(queue, out, out_buf)
            k = [pts[:, j] for j in range(dims)]
            expected = hash_floats_to_float3(*k) if colour else hash_floats(*k)[:, None]
            np.testing.assert_allclose(out[:, :3], np.broadcast_to(expected, (64, 3)), rtol=1e-6)
