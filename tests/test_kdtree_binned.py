"""The kd-tree builder (core/accel/binned.py, kernels/build/binned.cl) against the oracle's
definitions: every triangle referenced by exactly the leaves its clipped piece overlaps
(tests/test_kdtree.py check_tree), the node format and stats, the SAH cost against the numpy
build, the compaction's invariants and brute-force rays in all three modes, identical images
from the three modes, and the same bits whatever the thread count, work-group size, launch
pieces or big-node chunks.
"""
from __future__ import annotations

import functools
import hashlib
import os
import subprocess
import sys

import numpy as np
import pytest

from kdtrace.core.accel import binned
from kdtrace.core.accel.binned import BinnedBuilder
from kdtrace.core.accel.compact import MODES, compact_tree
from kdtrace.core.accel.kdtree import KDTreeParams, build_kdtree
from kdtrace.core.layout import LEAF_TAG, PLAIN_FIELD, PLAIN_TAG
from tests.meshes import load_bunny, load_dragon, merge, uv_sphere
from tests.scenes_architecture import architecture_scene
from tests.test_kdtree import SCENES, check_tree
from tests.test_kdtree_compact import brute_force, check_invariants, random_rays, trace_compact

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def builder():
    return BinnedBuilder("cpu")


def digest(tree) -> str:
    return hashlib.sha256(tree.nodes.tobytes() + tree.leaf_indices.tobytes()
                          + tree.bounds.tobytes()).hexdigest()


def same_tree(a, b):
    assert np.array_equal(a.nodes, b.nodes)
    assert np.array_equal(a.leaf_indices, b.leaf_indices)
    assert np.array_equal(a.bounds, b.bounds)


def architecture_small():
    return architecture_scene(rooms=(3, 2), floors=2, seed=3)


def instanced_mesh():
    """What an instanced scene's builds see: one small mesh, its triangles far from the origin
    (object space of a moved copy) and with copies of itself side by side."""
    v, t = uv_sphere(16, 8, 0.5, (100.0, -50.0, 3.0))
    return merge((v, t), (v + np.float32(1.5), t), (v, t))


ALL_SCENES = dict(SCENES, architecture=architecture_small, instanced=instanced_mesh)


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
# The definitions

@pytest.mark.parametrize("name", [pytest.param(name, marks=pytest.mark.slow)  # 30 s
                                  if name == "architecture" else name for name in ALL_SCENES])
def test_leaves_hold_exactly_the_overlapping_triangles(builder, name):
    vertices, triangles = ALL_SCENES[name]()
    tree = builder.build(vertices, triangles)
    check_tree(vertices, triangles, tree)
    assert tree.stats["leaves"] > 1


def test_coarse_bins_and_small_exact_nodes_still_correct(builder, monkeypatch):
    # Every node binned (no exact candidates), 4 bins: a poor tree, still a correct one.
    monkeypatch.setattr(binned, "EXACT_MAX", 1)
    vertices, triangles = load_bunny()
    params = KDTreeParams(max_bins=4)
    tree = BinnedBuilder("cpu", big_refs=64, chunk_refs=16).build(vertices, triangles, params)
    check_tree(vertices, triangles, tree, params)


def test_format_breadth_first_and_stats(builder):
    vertices, triangles = load_bunny()
    tree = builder.build(vertices, triangles)
    reference = build_kdtree(vertices, triangles)
    assert set(tree.stats) == set(reference.stats) | {"builder", "device"}
    assert tree.stats["builder"] == "opencl" and "pthread" in tree.stats["device"].lower()
    assert tree.stats["depth_cap"] == reference.stats["depth_cap"]
    assert tree.stats["sah_cost"] == pytest.approx(sah_cost(tree), rel=1e-5)
    # The k-th inner node's children at 1 + 2k (what compact_cl.py compacts), leaf lists in
    # node order.
    inner = PLAIN_TAG.get(tree.nodes[:, 0]) != LEAF_TAG
    child = PLAIN_FIELD.get(tree.nodes[inner, 0]).astype(np.int64)
    assert np.array_equal(child, 1 + 2 * np.arange(inner.sum()))
    count = PLAIN_FIELD.get(tree.nodes[~inner, 0]).astype(np.int64)
    offset = tree.nodes[~inner, 1].astype(np.int64)
    assert np.array_equal(offset, np.cumsum(count) - count)


def test_edge_cases(builder):
    one = (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32), np.array([[0, 1, 2]]))
    tree = builder.build(*one)
    check_tree(*one, tree)
    assert tree.stats["references"] == 1
    # Identical triangles, stacked.
    v, t = uv_sphere(8, 4)
    same = (v, np.vstack([t, t, t]))
    check_tree(*same, builder.build(*same))
    # Zero-area triangles are dropped (a repeated corner, three collinear corners).
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]], np.float32)
    t = np.array([[0, 1, 2], [0, 0, 1], [0, 1, 3]])
    tree = builder.build(v, t)
    assert tree.stats["dropped_degenerate"] == 2 and list(tree.leaf_indices) == [0]
    for empty in ((v, t[1:]), (v, np.zeros((0, 3), np.int64))):
        tree = builder.build(*empty)
        assert len(tree.nodes) == 1 and tree.stats["references"] == 0
        assert PLAIN_TAG.get(int(tree.nodes[0, 0])) == LEAF_TAG
    # A flat scene: its root box is padded in the flat axis.
    v, t = SCENES["sphere_over_plane"]()
    flat = (v[t[-200:].reshape(-1)] * np.float32([1, 1, 0]), np.arange(600).reshape(-1, 3))
    tree = builder.build(*flat)
    check_tree(*flat, tree)
    assert tree.bounds[0, 2] < 0 < tree.bounds[1, 2]
    with pytest.raises(ValueError):
        builder.build(v, np.array([[0, 1, len(v)]]))
    with pytest.raises(ValueError):
        builder.build(np.full((3, 3), np.nan, np.float32), np.array([[0, 1, 2]]))


@pytest.mark.parametrize("name", ["bunny", "sphere_over_plane", "cube_of_quads", "soup",
                                  "architecture"])
def test_sah_cost_within_three_percent_of_the_numpy_build(builder, name):
    # The numpy build: exact SAH up to 16 references, 32 bins above.
    vertices, triangles = ALL_SCENES[name]()
    ours, reference = builder.build(vertices, triangles), build_kdtree(vertices, triangles)
    assert sah_cost(ours) <= 1.03 * sah_cost(reference)


# ---------------------------------------------------------------------------------------------
# Determinism

@pytest.mark.parametrize("name", ["bunny", "cube_of_quads", "slivers", "architecture"])
def test_tree_does_not_depend_on_big_nodes_chunks_or_work_groups(builder, name):
    vertices, triangles = ALL_SCENES[name]()
    reference = builder.build(vertices, triangles)
    exact = binned.EXACT_MAX
    for big_refs, chunk_refs, local_size in ((exact, 7, 1), (exact + 44, 4096, 4),
                                             (1 << 20, 64, 64), (2 * exact, 33, 3)):
        other = BinnedBuilder("cpu", big_refs=big_refs, chunk_refs=chunk_refs,
                              local_size=local_size)
        tree = other.build(vertices, triangles)
        same_tree(reference, tree)
        assert tree.stats == {**reference.stats, "build_seconds": tree.stats["build_seconds"]}


THREADS_SCRIPT = """
import sys
sys.path.insert(0, {root!r})
from kdtrace.core.accel.binned import BinnedBuilder
from tests.test_kdtree_binned import architecture_small, digest
from tests.meshes import load_bunny
b = BinnedBuilder("cpu", big_refs=256, chunk_refs=512)
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


def test_pieces_give_the_same_tree_and_progress_stops_the_build(builder, monkeypatch):
    vertices, triangles = load_bunny()
    small = BinnedBuilder("cpu", big_refs=256, chunk_refs=32)
    reference = small.build(vertices, triangles)
    fractions, messages = [], []
    monkeypatch.setattr(binned, "PIECE_NODES", 64)
    monkeypatch.setattr(binned, "PIECE_REFS", 64)

    def progress(fraction, message):
        fractions.append(fraction)
        messages.append(message)
    same_tree(reference, small.build(vertices, triangles, progress=progress))
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    assert len(messages) > 2 * sum(m.startswith("kd-tree level") for m in set(messages))

    class Stop(Exception):
        pass

    def stop_in_a_piece(fraction, message, seen=[]):
        seen.append(message)
        if seen.count(message) > 2:
            raise Stop
    with pytest.raises(Stop):
        small.build(vertices, triangles, progress=stop_in_a_piece)
    same_tree(reference, small.build(vertices, triangles))


# ---------------------------------------------------------------------------------------------
# The compaction, rays and images

@functools.lru_cache(maxsize=None)
def scene(name):
    vertices, triangles = ALL_SCENES[name]()
    tree = BinnedBuilder("cpu").build(vertices, triangles)
    corners = vertices.astype(np.float64)[triangles.astype(np.int64)]
    return vertices, triangles, corners, tree


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("name", ["bunny", "architecture", "instanced"])
def test_compaction_invariants_and_rays_match_brute_force(builder, name, mode):
    vertices, triangles, corners, tree = scene(name)
    ct = compact_tree(tree, len(triangles), mode, device=builder)
    reference = compact_tree(tree, len(triangles), mode)        # numpy's, the same bits
    for part in ("nodes", "leaf_index32", "leaf_index16"):
        assert np.array_equal(getattr(ct, part), getattr(reference, part)), part
    check_invariants(tree, ct, len(triangles))
    origins, directions = random_rays(corners, 4000, seed=3 + len(name))
    bt, btri = brute_force(corners, origins, directions)
    t, tri, _ = trace_compact(ct, corners, origins, directions)
    assert np.isfinite(bt).mean() > 0.3
    assert np.array_equal(tri, btri) and np.array_equal(t, bt)


@pytest.mark.slow          # the full dragon: about 40 s
def test_dragon_invariants_in_every_mode(builder):
    # The full dragon: the compaction's invariants in every mode (the leaves' own check is
    # brute force over every triangle and cell, for the smaller scenes above), and the kernels'
    # trees the same whatever the big-node threshold.
    vertices, triangles = load_dragon()
    tree = builder.build(vertices, triangles)
    assert tree.stats["sah_cost"] == pytest.approx(sah_cost(tree), rel=1e-4)
    for mode in MODES:
        check_invariants(tree, compact_tree(tree, len(triangles), mode, device=builder),
                         len(triangles))
    same_tree(tree, BinnedBuilder("cpu", big_refs=2048, chunk_refs=1000).build(vertices, triangles))


def test_images_identical_in_every_mode():
    from kdtrace.core.scene.model import Camera, Geometry, Light, RenderSettings, Shading, View
    from kdtrace.core.scene.scene import Scene
    from kdtrace.slave.tracer import Tracer
    from tests.meshes import look_at
    vertices, triangles, _, tree = scene("architecture")
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16))
    lo = vertices.min(0)
    eye = lo + np.array([2.5, 2.0, 1.6])
    camera = Camera("PERSP", look_at(eye, eye + np.array([3.0, 2.0, -0.3]), (0.0, 0.0, 1.0)),
                    (0.6, 0.6), (0.0, 0.0), 1e-3, 1e5)
    light = Light("POINT", (1.0, 1.0, 1.0), 200.0, tuple(eye + np.array([0.3, 0.2, 0.5])))
    shading = Shading(np.array([[0.7, 0.7, 0.7, 1.0]], np.float32), [light], (0.1, 0.1, 0.1))
    view = View(camera, 64, 64, shading, settings=RenderSettings(samples_per_axis=1,
                                                                 max_bounces=1))
    tracer = Tracer("cpu")
    images = {}
    for mode in MODES:
        tracer.load(Scene.from_parts(geometry, compact_tree(tree, len(triangles), mode)))
        images[mode] = tracer.render_tile(view, 0, 0, 64, 64)
    first = images["standard"]
    assert (first["depth"] < 1e9).mean() > 0.5
    for mode, image in images.items():
        for name in first:
            assert np.array_equal(image[name], first[name]), (mode, name)


# ---------------------------------------------------------------------------------------------
# What the add-on calls (core/frame/tree_cache.py TreeCache.get)

def test_tree_cache_builds_here_and_sends_treelets(builder):
    from kdtrace.core.accel.binned import build_standard, opencl_builder
    from kdtrace.core.accel.compact import user_settings
    from kdtrace.core.accel.reorder import treelet_order
    from kdtrace.core.frame.tree_cache import TreeCache
    from kdtrace.core.scene.model import Geometry
    vertices, triangles = load_bunny()
    geometry = Geometry(vertices, triangles.astype(np.uint32), np.zeros(len(triangles), np.uint16))
    settings = user_settings("compressed", 0.5, 0.4, 8)
    messages = []
    ct, where = TreeCache().get(geometry, "compressed", settings, device="cpu",
                                progress=lambda f, m: messages.append(m))
    assert where == "built" and ct.stats["builder"] == "opencl"
    assert ct.stats["node_order"].startswith("treelets")
    assert "laying the kd-tree out in treelets" in messages
    expected = treelet_order(compact_tree(builder.build(vertices, triangles), len(triangles),
                                          "compressed", **settings))
    for part in ("nodes", "leaf_index32", "leaf_index16"):
        assert np.array_equal(getattr(ct, part), getattr(expected, part)), part
    # Without an OpenCL device: the numpy builder, and the stats say so.
    tree, used = build_standard(vertices, triangles, "7:7")
    assert used is None and tree.stats["builder"] == "numpy" and "7:7" in tree.stats["device"]
    check_tree(vertices, triangles, tree)
    assert opencl_builder("cpu")[0] is opencl_builder("cpu")[0], "one builder per device"

    class Stop(Exception):
        pass

    def stop_in_treelets(fraction, message):
        if "treelets" in message:
            raise Stop
    with pytest.raises(Stop):
        TreeCache().get(geometry, "compressed", settings, device="cpu", progress=stop_in_treelets)
