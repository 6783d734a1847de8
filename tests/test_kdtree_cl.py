"""The OpenCL kd-tree builder (core/accel/kdtree_cl.py, kernels/build/): it builds the numpy
builder's tree bit for bit; its trees pass every invariant the numpy builder's trees are tested
for (tests/test_kdtree.py, brute-force rays and the compaction's invariants of
tests/test_kdtree_compact.py, identical images through the tracer); and they are the same bits
whatever the subtree threshold, chunk size, work-group size, PoCL thread count or double
arithmetic (native fp64 or the software double used where a device has none).
"""
from __future__ import annotations

import functools
import hashlib
import os
import subprocess
import sys

import numpy as np
import pytest

from core.accel.compact import (MODES, _standard_reencoded, compact_params, compact_tree,
                                 level_ranges)
from core.accel.kdtree import KDTree, KDTreeParams, build_kdtree
from core.accel import compact_cl
from core.accel.kdtree_cl import KDTreeBuilderCL
from core.layout import LEAF_TAG, PLAIN_FIELD, PLAIN_TAG
from core.opencl import kernel_source
from core.scene.model import Camera, Geometry, Light, RenderSettings, Shading, View
from core.scene.scene import Scene
from tests.meshes import grid_plane, load_bunny, load_dragon, look_at, merge, uv_sphere
from tests.scenes_architecture import architecture_scene
from tests.test_kdtree import SCENES, _reference_halves, check_tree, cube_of_quads
from tests.test_kdtree_compact import brute_force, check_invariants, random_rays, trace_compact

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SPLIT_FILES = ("build/fp64.cl", "build/split.cl")


@pytest.fixture(scope="module")
def builder():
    return KDTreeBuilderCL("cpu")


@pytest.fixture(scope="module")
def soft_builder():
    return KDTreeBuilderCL("cpu", soft_fp64=True)


def digest(tree) -> str:
    return hashlib.sha256(tree.nodes.tobytes() + tree.leaf_indices.tobytes()
                          + tree.bounds.tobytes()).hexdigest()


def same_tree(a, b):
    assert np.array_equal(a.nodes, b.nodes)
    assert np.array_equal(a.leaf_indices, b.leaf_indices)
    assert np.array_equal(a.bounds, b.bounds)


def architecture_small():
    return architecture_scene(rooms=(3, 2), floors=2, seed=3)


# ---------------------------------------------------------------------------------------------
# The numpy builder's invariants

@pytest.mark.parametrize("name", [name for name in SCENES if name != "bunny"])
def test_leaves_hold_exactly_the_overlapping_triangles(builder, name):
    # (The bunny's tree is the numpy builder's, whose own tests check it the same way.)
    vertices, triangles = SCENES[name]()
    tree = builder.build(vertices, triangles)
    check_tree(vertices, triangles, tree)
    assert tree.stats["leaves"] > 1


def test_stats_are_the_numpy_builders_plus_builder_and_device(builder):
    vertices, triangles = SCENES["sphere"]()
    tree = builder.build(vertices, triangles)
    reference = build_kdtree(vertices, triangles)
    assert set(tree.stats) == set(reference.stats) | {"builder", "device"}
    assert tree.stats["builder"] == "opencl" and "pthread" in tree.stats["device"].lower()
    assert tree.stats["depth_cap"] == reference.stats["depth_cap"]


def test_coarse_bins_still_correct(builder):
    vertices, triangles = merge(uv_sphere(16, 8), cube_of_quads(2))
    params = KDTreeParams(max_bins=4, min_bins=2)
    check_tree(vertices, triangles, builder.build(vertices, triangles, params), params)


def test_edge_cases(builder):
    one = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    tree = builder.build(one, np.array([[0, 1, 2]], np.uint32))
    check_tree(one, np.array([[0, 1, 2]]), tree)

    tilted = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.5]], np.float32)
    identical = np.tile(np.array([[0, 1, 2]], np.uint32), (50, 1))
    check_tree(tilted, identical, builder.build(tilted, identical))

    vertices, triangles = uv_sphere(16, 8)
    collinear = np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2]], np.float32)
    vertices, triangles = merge((vertices, triangles), (collinear, np.array([[0, 1, 2]], np.uint32)))
    triangles = np.vstack([triangles, np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2], [0, 0, 1]])])
    tree = builder.build(vertices, triangles)
    check_tree(vertices, triangles, tree)
    assert tree.stats["dropped_degenerate"] == 5
    assert not np.isin(np.arange(len(triangles) - 5, len(triangles)), tree.leaf_indices).any()

    points = np.array([[0, 0, 0], [1, 1, 1]], np.float32)
    for triangles in (np.array([[0, 0, 1]], np.uint32), np.zeros((0, 3), np.uint32)):
        tree = builder.build(points, triangles)
        assert tree.stats["nodes"] == 1 and tree.stats["references"] == 0
        assert (tree.bounds[0] < tree.bounds[1]).all()

    vertices, triangles = grid_plane(4.0, 6, z=2.5)
    tree = builder.build(vertices, triangles)
    check_tree(vertices, triangles, tree)
    assert tree.bounds[0, 2] < 2.5 < tree.bounds[1, 2], "root box padded in the flat axis"

    with pytest.raises(ValueError):
        builder.build(np.zeros((3, 3), np.float32), np.array([[0, 1, 3]]))
    with pytest.raises(ValueError):
        builder.build(np.full((3, 3), np.nan, np.float32), np.array([[0, 1, 2]]))


def test_breadth_first_layout_like_the_numpy_builder(builder):
    # Children of the k-th inner node at 1 + 2k, leaf lists in node order and ascending: the
    # compaction's fast path for mode standard applies, as for the numpy builder's trees.
    vertices, triangles = load_bunny()
    tree = builder.build(vertices, triangles)
    inner = np.flatnonzero(PLAIN_TAG.get(tree.nodes[:, 0]) != LEAF_TAG)
    assert np.array_equal(PLAIN_FIELD.get(tree.nodes[inner, 0]), 1 + 2 * np.arange(len(inner)))
    assert _standard_reencoded(tree, len(triangles), compact_params("standard")) is not None


# ---------------------------------------------------------------------------------------------
# The numpy builder's tree

ORACLE_SCENES = dict(SCENES, architecture=architecture_small,
                     sphere_in_cube=lambda: merge(uv_sphere(16, 8), cube_of_quads(2)))


@pytest.mark.parametrize("name, coarse", [(name, False) for name in ORACLE_SCENES]
                         + [(name, True) for name in ("sphere_in_cube", "slivers", "architecture")])
def test_same_tree_as_the_numpy_builder(builder, name, coarse):
    # Every decision uses the numpy builder's arithmetic (split.cl), so the tree is the same
    # bits, whatever path each node took through the kernels; the SAH cost is then the same
    # too (summed in another order: equal to rounding).
    vertices, triangles = ORACLE_SCENES[name]()
    params = KDTreeParams(max_bins=4, min_bins=2) if coarse else KDTreeParams()
    ours = builder.build(vertices, triangles, params)
    reference = build_kdtree(vertices, triangles, params)
    same_tree(ours, reference)
    for key in ("nodes", "leaves", "empty_leaves", "depth", "depth_cap", "references",
                "dropped_degenerate", "bytes"):
        assert ours.stats[key] == reference.stats[key], key
    assert ours.stats["sah_cost"] == pytest.approx(reference.stats["sah_cost"], rel=1e-6)


@pytest.mark.parametrize("name", ["bunny", "dragon", "architecture"])
def test_sah_cost_within_two_percent_of_the_numpy_builder(builder, name):
    # The quality bar on its three scenes (the full dragon and the full-size building):
    # the SAH cost of each tree computed from its own nodes (an independent sum, not the
    # builder's stat) within 2 % of the numpy builder's; the trees are in fact the same bits.
    load = {"bunny": load_bunny, "dragon": load_dragon, "architecture": architecture_scene}[name]
    vertices, triangles = load()
    ours, reference = builder.build(vertices, triangles), build_kdtree(vertices, triangles)
    cost, reference_cost = sah_cost(ours), sah_cost(reference)
    assert abs(cost - reference_cost) <= 0.02 * reference_cost
    assert cost == pytest.approx(ours.stats["sah_cost"], rel=1e-6)
    assert reference_cost == pytest.approx(reference.stats["sah_cost"], rel=1e-6)
    same_tree(ours, reference)


def sah_cost(tree, params=KDTreeParams()) -> float:
    """The tree's SAH cost from its nodes: K_T per inner node and K_I per leaf reference, each
    weighted by its cell's surface area over the root's (cells walked down from the bounds)."""
    inner = PLAIN_TAG.get(tree.nodes[:, 0]) != LEAF_TAG
    lo, hi = np.zeros((len(inner), 3)), np.zeros((len(inner), 3))
    lo[0], hi[0] = tree.bounds[0], tree.bounds[1]
    axis = PLAIN_TAG.get(tree.nodes[:, 0])
    plane = tree.nodes[:, 1].view(np.float32).astype(np.float64)
    child = np.where(inner, PLAIN_FIELD.get(tree.nodes[:, 0]).astype(np.int64), 0)
    level = np.array([0])
    while len(level):               # cells handed down one level at a time
        level = level[inner[level]]
        below, above, a = child[level], child[level] + 1, axis[level]
        for side in (below, above):
            lo[side], hi[side] = lo[level], hi[level]
        hi[below, a] = lo[above, a] = plane[level]
        level = np.concatenate([below, above])
    extent = hi - lo
    area = extent[:, 0] * extent[:, 1] + extent[:, 1] * extent[:, 2] + extent[:, 2] * extent[:, 0]
    counts = np.where(inner, 0, PLAIN_FIELD.get(tree.nodes[:, 0]).astype(np.int64))
    cost = np.where(inner, params.traversal_cost, params.intersection_cost * counts)
    return float((cost * area).sum() / area[0])


# ---------------------------------------------------------------------------------------------
# Determinism

@pytest.mark.parametrize("name", ["bunny", "cube_of_quads", "slivers"])
def test_tree_does_not_depend_on_subtrees_chunks_or_work_groups(builder, name):
    vertices, triangles = SCENES[name]()
    reference = builder.build(vertices, triangles)
    assert builder.subtree_queue        # on the CPU the subtrees are taken in turn; and without:
    for subtree_refs, chunk_refs, local_size, queue in ((16, 7, 1, True), (100, 4096, 4, False),
                                                        (1 << 20, 64, 1, True), (64, 256, 1, False)):
        other = KDTreeBuilderCL("cpu", subtree_refs=subtree_refs, chunk_refs=chunk_refs,
                                local_size=local_size, subtree_queue=queue)
        same_tree(reference, other.build(vertices, triangles))
        assert other.build(vertices, triangles).stats["sah_cost"] == reference.stats["sah_cost"]


def test_tree_does_not_depend_on_the_stores_chunks(builder, monkeypatch):
    # Finished subtrees go into chunks of the device store; tiny chunks (a new one for every
    # launch, some launches larger than a chunk) must give the same tree.
    import core.accel.kdtree_cl as kcl
    vertices, triangles = load_bunny()
    small = KDTreeBuilderCL("cpu", subtree_refs=64)
    reference = small.build(vertices, triangles)
    chunks = []

    class CountedChunk(kcl._Chunk):
        def __init__(self, *args):
            super().__init__(*args)
            chunks.append(self.rec_capacity)
    monkeypatch.setattr(kcl, "_Chunk", CountedChunk)
    monkeypatch.setattr(kcl._Store, "CHUNK_RECORDS", 512)
    monkeypatch.setattr(kcl._Store, "CHUNK_REFS", 256)
    small.batch_seconds = 1e-6         # launches of about subtree_refs references
    same_tree(reference, small.build(vertices, triangles))
    assert len(chunks) > 10 and max(chunks) > 512


@pytest.mark.parametrize("name", ["bunny", "slivers", "soup", "cube_of_quads"])
def test_software_double_gives_the_same_tree(builder, soft_builder, name):
    vertices, triangles = SCENES[name]()
    same_tree(builder.build(vertices, triangles), soft_builder.build(vertices, triangles))


THREADS_SCRIPT = """
import hashlib, sys
sys.path.insert(0, {root!r})
from core.accel import compact_cl
from core.accel.kdtree_cl import KDTreeBuilderCL
from tests.test_kdtree_cl import architecture_small, digest
from tests.meshes import load_bunny
b = KDTreeBuilderCL("cpu", subtree_refs=256, chunk_refs=512)
print(digest(b.build(*load_bunny())), digest(b.build(*architecture_small())), b.device.max_compute_units)
"""


def test_same_tree_with_one_and_two_pocl_threads(builder):
    # PoCL reads its thread count once at start: one process per count.
    script = THREADS_SCRIPT.format(root=ROOT)
    lines = {}
    for threads in ("1", "2"):
        env = dict(os.environ, POCL_MAX_PTHREAD_COUNT=threads)
        out = subprocess.run([sys.executable, "-c", script], env=env, check=True,
                             capture_output=True, text=True, timeout=300).stdout.split()
        assert out[2] == threads
        lines[threads] = out[:2]
    here = [digest(builder.build(*load_bunny())), digest(builder.build(*architecture_small()))]
    assert lines["1"] == lines["2"] == here


# ---------------------------------------------------------------------------------------------
# The perfect split and the double arithmetic, kernel by kernel

CLIP_TEST = """
__kernel void clip_cases(__global const float* corners, __global const float* cells,
                         __global const int* axes,
                         __global const float* planes, __global float* out, uint count)
{
    uint i = get_global_id(0);
    if (i >= count)
        return;
    Cell c;
    for (int a = 0; a < 3; a++) {
        c.lo[a] = cells[8 * i + a];
        c.hi[a] = cells[8 * i + 4 + a];
    }
    Ref below, above;
    int kept = clip_straddler(corners, i, &c, axes[i], planes[i], &below, &above);
    float box[12] = {below.lo.x, below.lo.y, below.lo.z, below.hi.x, below.hi.y, below.hi.z,
                     above.lo.x, above.lo.y, above.lo.z, above.hi.x, above.hi.y, above.hi.z};
    for (int k = 0; k < 12; k++)
        out[13 * i + k] = box[k];
    out[13 * i + 12] = (float)kept;
}
"""


def run_kernel(b, source, name, count, *arrays, out_shape, out_dtype):
    buffers = [b.buffer(np.ascontiguousarray(a)) for a in arrays]
    out = b.buffer(nbytes=np.dtype(out_dtype).itemsize * int(np.prod(out_shape)))
    kernel = b.program(kernel_source(SPLIT_FILES) + source)[name]
    kernel(b.queue, (count,), None, *buffers, out, np.uint32(count))
    return b.read(out, out_dtype, out_shape)


@pytest.mark.parametrize("soft", [False, True])
def test_clipping_matches_one_polygon_at_a_time(builder, soft_builder, soft):
    # The same random cases as tests/test_kdtree.py's check of the numpy clipping.
    rng = np.random.default_rng(5)
    count = 600
    tri = rng.uniform(-1, 1, (count, 3, 3)).astype(np.float32)
    tri[:50, :, 2] = np.float32(0.25)                       # flat triangles
    tri[50:100, 0] = [0.0, 0.0, 0.0]                        # a vertex on the plane below
    cell_lo = rng.uniform(-0.8, -0.1, (count, 3)).astype(np.float32)
    cell_hi = rng.uniform(0.1, 0.8, (count, 3)).astype(np.float32)
    cell_lo[:20], cell_hi[:20] = -2, 2                       # triangles inside their cell
    axis = rng.integers(0, 3, count).astype(np.int32)
    plane = np.zeros(count, np.float32)
    plane[100:] = rng.uniform(-0.05, 0.05, count - 100).astype(np.float32)
    cells = np.zeros((count, 8), np.float32)
    cells[:, 0:3], cells[:, 4:7] = cell_lo, cell_hi
    out = run_kernel(soft_builder if soft else builder, CLIP_TEST, "clip_cases", count,
                     tri.reshape(-1, 9), cells, axis, plane, out_shape=(count, 13),
                     out_dtype=np.float32)
    for k in range(count):
        expected = _reference_halves(tri[k].astype(np.float64), cell_lo[k], cell_hi[k], axis[k],
                                     plane[k])
        kept = int(out[k, 12])
        for side in (0, 1):
            assert bool(kept >> side & 1) == (expected[side] is not None), (k, side)
            if expected[side] is not None:
                assert np.array_equal(out[k, 6 * side:6 * side + 3], expected[side][0]), (k, side)
                assert np.array_equal(out[k, 6 * side + 3:6 * side + 6], expected[side][1]), (k, side)


DOUBLE_TEST = """
__kernel void double_ops(__global const float* a, __global const float* b,
                         __global const float* c, __global ulong* out, uint count)
{
    uint i = get_global_id(0);
    if (i >= count)
        return;
    dbl x = D_FROM_F(a[i]), y = D_FROM_F(b[i]), z = D_FROM_F(c[i]);
    dbl d0 = D_SUB(x, y), d1 = D_SUB(z, y);
    dbl t = D_DIV(d0, D_SUB(d0, d1));
    dbl p = D_ADD(x, D_MUL(t, D_SUB(z, x)));
    dbl results[6] = {d0, D_ADD(x, z), D_MUL(d0, d1), t, p, D_MUL(x, z)};
    for (int k = 0; k < 6; k++) {
#ifdef KDTRACE_SOFT_FP64
        out[8 * i + k] = results[k];
#else
        out[8 * i + k] = as_ulong(results[k]);
#endif
    }
    out[8 * i + 6] = as_uint(d_to_float_outward(p, 0));
    out[8 * i + 7] = as_uint(d_to_float_outward(p, 1));
}
"""


def outward_f32(x: np.ndarray, up: bool) -> np.ndarray:
    """The documented rounding: outward to float32, magnitudes below FLT_MIN to 0 / +-FLT_MIN."""
    f = x.astype(np.float32)
    if up:
        f = np.where(f.astype(np.float64) < x, np.nextafter(f, np.float32(np.inf)), f)
    else:
        f = np.where(f.astype(np.float64) > x, np.nextafter(f, np.float32(-np.inf)), f)
    tiny = np.float32(np.finfo(np.float32).tiny)
    small = (np.abs(x) < tiny) & (x != 0)
    policy = np.where(x > 0, tiny if up else 0, 0 if up else -tiny).astype(np.float32)
    return np.where(small, policy, f) + np.float32(0)


@pytest.mark.parametrize("soft", [False, True])
def test_double_arithmetic_is_ieee(builder, soft_builder, soft):
    # Chained like the clipping: differences, a quotient in [0, 1], an interpolation; inputs
    # over many magnitudes, with cancellations, equal values, zeros and float32 denormals.
    rng = np.random.default_rng(11)
    n = 20000
    def values():
        v = rng.normal(size=n) * np.exp2(rng.integers(-60, 60, n))
        return v.astype(np.float32)
    a, b, c = values(), values(), values()
    b[:2000] = a[:2000]                                   # exact cancellation
    c[2000:4000] = np.nextafter(a[2000:4000], np.float32(np.inf))
    a[4000:4500] = 0
    b[4500:5000] = np.float32(3e-39) * rng.integers(1, 100, 500)   # float32 denormals
    x, y, z = (v.astype(np.float64) for v in (a, b, c))
    d0, d1 = x - y, z - y
    with np.errstate(all="ignore"):
        t = d0 / (d0 - d1)
    p = x + t * (z - x)
    expected = np.stack([d0, x + z, d0 * d1, t, p, x * z], 1)
    out = run_kernel(soft_builder if soft else builder, DOUBLE_TEST, "double_ops", n, a, b, c,
                     out_shape=(n, 8), out_dtype=np.uint64)
    valid = np.isfinite(t)
    got = out[:, :6].view(np.float64)
    assert np.array_equal(got[valid].view(np.uint64), expected[valid].view(np.uint64))
    for k, up in ((6, False), (7, True)):
        rounded = out[valid, k].astype(np.uint32).view(np.float32)
        assert np.array_equal(rounded, outward_f32(p[valid], up))


# ---------------------------------------------------------------------------------------------
# Rays and images

@functools.lru_cache(maxsize=None)
def scene(name):
    vertices, triangles = load_bunny() if name == "bunny" else architecture_small()
    tree = KDTreeBuilderCL("cpu").build(vertices, triangles)
    corners = vertices.astype(np.float64)[triangles.astype(np.int64)]
    return vertices, triangles, corners, tree


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("name", ["bunny", "architecture"])
def test_rays_match_brute_force_in_every_mode(name, mode):
    vertices, triangles, corners, tree = scene(name)
    ct = compact_tree(tree, len(triangles), mode)
    check_invariants(tree, ct, len(triangles))
    origins, directions = random_rays(corners, 4000, seed=3 + len(name))
    bt, btri = brute_force(corners, origins, directions)
    t, tri, _ = trace_compact(ct, corners, origins, directions)
    assert np.isfinite(bt).mean() > 0.3
    assert np.array_equal(tri, btri) and np.array_equal(t, bt)


def test_images_identical_to_the_numpy_trees_in_every_mode():
    from slave.tracer import Tracer
    vertices, triangles, _, tree = scene("architecture")
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16))
    lo, hi = vertices.min(0), vertices.max(0)
    eye = lo + np.array([2.5, 2.0, 1.6])
    camera = Camera("PERSP", look_at(eye, eye + np.array([3.0, 2.0, -0.3]), (0.0, 0.0, 1.0)),
                    (0.6, 0.6), (0.0, 0.0), 1e-3, 1e5)
    light = Light("POINT", (1.0, 1.0, 1.0), 200.0, tuple(eye + np.array([0.3, 0.2, 0.5])))
    shading = Shading(np.array([[0.7, 0.7, 0.7, 1.0]], np.float32), [light], (0.1, 0.1, 0.1))
    view = View(camera, 64, 64, shading, settings=RenderSettings(samples_per_axis=1,
                                                                 max_bounces=1))
    reference = build_kdtree(vertices, triangles)
    tracer = Tracer("cpu")
    images = {}
    for label, plain in (("numpy", reference), ("opencl", tree)):
        for mode in MODES:
            tracer.load(Scene.from_parts(geometry, compact_tree(plain, len(triangles), mode)))
            images[label, mode] = tracer.render_tile(view, 0, 0, 64, 64)
    first = images["numpy", "standard"]
    assert (first["depth"] < 1e9).mean() > 0.5
    for key, image in images.items():
        for name in first:
            assert np.array_equal(image[name], first[name]), (key, name)


# ---------------------------------------------------------------------------------------------
# Progress

def test_progress_is_reported_and_an_exception_stops_the_build(builder):
    vertices, triangles = load_bunny()
    small = KDTreeBuilderCL("cpu", subtree_refs=64)
    fractions = []
    small.build(vertices, triangles, progress=lambda f, m: fractions.append(f))
    assert len(fractions) > 3 and fractions == sorted(fractions) and fractions[-1] == 1.0

    class Stop(Exception):
        pass

    def stop_in_subtrees(fraction, message):
        if "subtrees" in message:
            raise Stop
    with pytest.raises(Stop):
        small.build(vertices, triangles, progress=stop_in_subtrees)
    same_tree(small.build(vertices, triangles), builder.build(vertices, triangles))


# ---------------------------------------------------------------------------------------------
# The compaction in kernels (core/accel/compact_cl.py): compact_tree's result, bit for bit

COMPACT_VARIANTS = [("standard", {}), ("compressed", {}), ("choi", {}),
                    ("compressed", dict(tau_occu=0.05, tau_freq=0.05)),
                    ("compressed", dict(refs_per_path=1, tau_occu=0.1, tau_freq=0.1)),
                    ("compressed", dict(min_refs=1, tau_occu=0.2, tau_freq=0.2)),
                    ("compressed", dict(collapse=False)), ("compressed", dict(elide_empty=False)),
                    ("compressed", dict(leaf16=False)), ("compressed", dict(refs_per_node=0)),
                    ("compressed", dict(refs_per_path=None)), ("choi", dict(tau_occu=0.0, tau_freq=0.0))]


def same_compact(a, b):
    for name in ("nodes", "leaf_index32", "leaf_index16", "bounds"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and np.array_equal(x, y), name
    assert a.leaf_shift == b.leaf_shift and a.params == b.params
    strip = lambda stats: {k: v for k, v in stats.items() if k != "compact_seconds"}
    assert strip(a.stats) == strip(b.stats)


@functools.lru_cache(maxsize=None)
def compact_scene(name):
    vertices, triangles = {"sphere": lambda: uv_sphere(12, 16), "bunny": load_bunny,
                           "architecture": architecture_small,
                           # more than 65,536 triangles: 16-bit leaves with a leaf_shift
                           "building": lambda: architecture_scene(rooms=(6, 4), floors=3,
                                                                  seed=1)}[name]()
    return build_kdtree(vertices, triangles), len(triangles)


@pytest.mark.parametrize("name", ["sphere", "bunny", "architecture", "building"])
def test_kernel_compaction_is_compact_tree(builder, name):
    tree, triangle_count = compact_scene(name)
    variants = COMPACT_VARIANTS if name != "building" else [("compressed", {}), ("choi", {})]
    for mode, options in variants:
        same_compact(compact_tree(tree, triangle_count, mode, device=builder, **options),
                     compact_tree(tree, triangle_count, mode, **options))


@pytest.mark.parametrize("roots, stack", [(1, 64), (1 << 30, 64), (1, 4)])
def test_kernel_compaction_topology_level_by_level_or_depth_first(builder, monkeypatch, roots,
                                                                  stack):
    # The topology goes level by level down to the first level of TOPO_ROOTS nodes, then
    # depth first below it (at most TOPO_STACK levels): from the root, never, or only for the
    # last 4 levels, the compact tree is the same.
    monkeypatch.setattr(compact_cl, "TOPO_ROOTS", roots)
    monkeypatch.setattr(compact_cl, "TOPO_STACK", stack)
    tree, triangle_count = compact_scene("bunny")
    same_compact(compact_tree(tree, triangle_count, "compressed", device=builder),
                 compact_tree(tree, triangle_count, "compressed"))


def with_copies_in_leaves(tree):
    """The same tree with every non-empty leaf listing its first triangle twice (a tree the
    builders never make, which compaction takes: the copies' common ancestor is the leaf)."""
    nodes, lists = tree.nodes.copy(), []
    for i in np.flatnonzero(PLAIN_TAG.get(nodes[:, 0]) == LEAF_TAG):
        count, offset = int(PLAIN_FIELD.get(int(nodes[i, 0]))), int(nodes[i, 1])
        items = list(tree.leaf_indices[offset:offset + count])
        items = items[:1] + items if items else items
        nodes[i] = (PLAIN_TAG.put(LEAF_TAG) | PLAIN_FIELD.put(len(items)),
                    sum(len(x) for x in lists))
        lists.append(items)
    return KDTree(nodes, np.array([t for x in lists for t in x], np.uint32), tree.bounds)


def test_kernel_compaction_with_copies_in_a_leaf(builder):
    tree, triangle_count = compact_scene("bunny")
    copies = with_copies_in_leaves(tree)
    assert len(copies.leaf_indices) > len(tree.leaf_indices)
    for mode in ("compressed", "choi"):
        same_compact(compact_tree(copies, triangle_count, mode, device=builder),
                     compact_tree(copies, triangle_count, mode))
        same_compact(compact_tree(copies, triangle_count, mode, device=builder, min_refs=1),
                     compact_tree(copies, triangle_count, mode, min_refs=1))


def test_kernel_compaction_with_software_double(soft_builder):
    tree, triangle_count = compact_scene("architecture")
    for mode in ("compressed", "choi"):
        same_compact(compact_tree(tree, triangle_count, mode, device=soft_builder),
                     compact_tree(tree, triangle_count, mode))


def depth_first(tree):
    """The same tree with its nodes in depth-first order: each inner node's children side by
    side, placed when it is reached (a valid layout, not the builders' order)."""
    nodes = tree.nodes
    place, stack = {0: 0}, [0]
    while stack:
        i = stack.pop()
        if PLAIN_TAG.get(int(nodes[i, 0])) != LEAF_TAG:
            c = PLAIN_FIELD.get(int(nodes[i, 0]))
            place[c], place[c + 1] = len(place), len(place) + 1
            stack += [c + 1, c]
    out = np.zeros_like(nodes)
    for old, new in place.items():
        out[new] = nodes[old]
        tag = PLAIN_TAG.get(int(nodes[old, 0]))
        if tag != LEAF_TAG:
            out[new, 0] = PLAIN_TAG.put(tag) | PLAIN_FIELD.put(place[PLAIN_FIELD.get(int(nodes[old, 0]))])
    return KDTree(out, tree.leaf_indices, tree.bounds)


def test_kernel_compaction_falls_back_for_other_orders(builder):
    tree, triangle_count = compact_scene("sphere")
    other = depth_first(tree)
    assert level_ranges(PLAIN_TAG.get(other.nodes[:, 0]) == LEAF_TAG,
                        PLAIN_FIELD.get(other.nodes[:, 0]).astype(np.int64)) is None
    for mode in ("compressed", "standard"):
        same_compact(compact_tree(other, triangle_count, mode, device=builder),
                     compact_tree(other, triangle_count, mode))


# ---------------------------------------------------------------------------------------------
# What the add-on calls (addon/session.py TreeCache.get)

def test_build_standard_uses_the_device_or_falls_back_to_numpy(builder):
    from core.accel.kdtree_cl import build_standard, opencl_builder
    vertices, triangles = SCENES["soup"]()
    tree, used = build_standard(vertices, triangles, "cpu")
    assert used is not None and tree.stats["builder"] == "opencl"
    assert opencl_builder("cpu")[0] is used, "one builder per device, made once"
    fallback, none = build_standard(vertices, triangles, "7:7")    # no such device
    assert none is None and fallback.stats["builder"] == "numpy"
    assert "7:7" in fallback.stats["device"]
    same_tree(tree, fallback)


def test_launches_in_pieces_give_the_same_tree_and_see_the_callback(monkeypatch):
    # Long launches go in pieces with the progress callback between them (Esc stays prompt):
    # the pieces change nothing, and an exception from the callback stops the work there.
    import core.accel.compact_cl as ccl
    import core.accel.kdtree_cl as kcl
    vertices, triangles = load_bunny()
    small = KDTreeBuilderCL("cpu", subtree_refs=64, chunk_refs=32)
    reference = small.build(vertices, triangles)
    calls = []
    monkeypatch.setattr(kcl, "PIECE_REFS", 64)
    monkeypatch.setattr(kcl, "PIECE_ITEMS", 256)
    monkeypatch.setattr(ccl, "PIECE_NODES", 256)
    monkeypatch.setattr(ccl, "PIECE_CLIMBS", 256)
    pieces = small.build(vertices, triangles, progress=lambda f, m: calls.append(m))
    same_tree(reference, pieces)
    assert sum(m.startswith("kd-tree level") for m in calls) > 20

    class Stop(Exception):
        pass

    def stop_at_the_second_call_of_a_level(fraction, message, seen=[]):
        seen.append(message)
        if seen.count(message) > 1:
            raise Stop
    with pytest.raises(Stop):
        small.build(vertices, triangles, progress=stop_at_the_second_call_of_a_level)
    ct = compact_tree(reference, len(triangles), "compressed", device=small,
                      progress=lambda f, m: calls.append(m))
    same_compact(ct, compact_tree(reference, len(triangles), "compressed"))
