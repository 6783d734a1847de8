"""The OpenCL tracer against brute force in numpy float64, and render_tile on analytic scenes."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest

from kdtrace.core.accel.kdtree import KDTree, build_kdtree
from kdtrace.core.scene.model import Camera, Geometry, Light, RenderSettings, Shading, View
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.tracer import Tracer, TracerError, kernel_options, tile_pixel_order
from tests.meshes import grid_plane, load_bunny, merge, uv_sphere


# -- trees ----------------------------------------------------------------------------------
def single_leaf_tree(vertices, triangles):
    """One leaf holding every triangle: traversal reduces to brute force."""
    count = len(triangles)
    return KDTree(np.array([[(count << 2) | 3, 0]], np.uint32), np.arange(count, dtype=np.uint32),
                  np.array([vertices.min(0), vertices.max(0)], np.float32))


def two_level_tree(vertices, triangles, axis=0, split=None):
    """Root split at `split` on `axis` (default: the box centre), two leaves; a triangle goes
    to each side its extent touches."""
    lo, hi = vertices.min(0), vertices.max(0)
    split = np.float32((lo[axis] + hi[axis]) / 2 if split is None else split)
    coords = vertices[triangles][:, :, axis]
    below = np.flatnonzero(coords.min(1) <= split).astype(np.uint32)
    above = np.flatnonzero(coords.max(1) >= split).astype(np.uint32)
    nodes = np.array([[(1 << 2) | axis, split.view(np.uint32)],
                      [(len(below) << 2) | 3, 0],
                      [(len(above) << 2) | 3, len(below)]], np.uint32)
    return KDTree(nodes, np.concatenate([below, above]), np.array([lo, hi], np.float32))


def make_tree(vertices, triangles):
    return build_kdtree(vertices, triangles)


# -- brute force reference --------------------------------------------------------------------
def brute_force(vertices, triangles, origins, directions, chunk=256):
    """Nearest hit per ray in float64 (Moller-Trumbore, no epsilon), ties to the lower index.
    Returns t (inf on miss), triangle (-1), and the smallest barycentric of that hit."""
    tri = vertices.astype(np.float64)[triangles]
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    best_t = np.full(len(origins), np.inf)
    best_i = np.full(len(origins), -1)
    best_edge = np.full(len(origins), np.inf)
    for s in range(0, len(origins), chunk):
        o = origins[s:s + chunk, None, :].astype(np.float64)
        d = directions[s:s + chunk, None, :].astype(np.float64)
        p = np.cross(d, e2)
        det = np.einsum("rtk,tk->rt", p, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            tv = o - v0
            u = np.einsum("rtk,rtk->rt", tv, p) * inv
            q = np.cross(tv, e1)
            v = np.einsum("rtk,rtk->rt", d, q) * inv
            t = np.einsum("tk,rtk->rt", e2, q) * inv
            ok = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0)
        t = np.where(ok, t, np.inf)
        i = np.argmin(t, axis=1)            # first minimum: the lower index wins ties
        rows = np.arange(len(i))
        found = np.isfinite(t[rows, i])
        best_t[s:s + chunk] = t[rows, i]
        best_i[s:s + chunk] = np.where(found, i, -1)
        edge = np.minimum(np.minimum(u[rows, i], v[rows, i]), 1 - u[rows, i] - v[rows, i])
        best_edge[s:s + chunk] = np.where(found, edge, np.inf)
    return best_t, best_i, best_edge


def ray_t_on_triangle(vertices, triangles, index, origins, directions):
    """float64 t at which each ray meets the plane of triangle `index` (nan for -1)."""
    tri = vertices.astype(np.float64)[triangles[np.maximum(index, 0)]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.einsum("rk,rk->r", tri[:, 0] - origins, n) / np.einsum("rk,rk->r", directions, n)
    return np.where(index >= 0, t, np.nan)


def random_rays(vertices, count, rng):
    """Origins in a box 1.5x the mesh's, aimed at random points inside the mesh's box."""
    lo, hi = vertices.min(0).astype(np.float64), vertices.max(0).astype(np.float64)
    centre, half = (lo + hi) / 2, (hi - lo) / 2 + 1e-3
    origins = centre + rng.uniform(-1.5, 1.5, (count, 3)) * half
    targets = centre + rng.uniform(-1, 1, (count, 3)) * half
    return origins.astype(np.float32), (targets - origins).astype(np.float32)


def triangle_soup(count, rng):
    centres = rng.uniform(-1, 1, (count, 1, 3))
    vertices = (centres + rng.normal(scale=0.15, size=(count, 3, 3))).reshape(-1, 3)
    return vertices.astype(np.float32), np.arange(3 * count, dtype=np.uint32).reshape(-1, 3)


@pytest.fixture(scope="module")
def tracer():
    return Tracer()


def load(tracer, vertices, triangles, tree=None, material_ids=None):
    if material_ids is None:
        material_ids = np.zeros(len(triangles), np.uint16)
    tracer.load(Scene.from_parts(Geometry(vertices, triangles, material_ids),
                tree if tree is not None else make_tree(vertices, triangles)))


MESHES = {
    "uv_sphere": lambda rng: uv_sphere(32, 16),
    "bunny": lambda rng: load_bunny(),
    "sphere_on_plane": lambda rng: merge(uv_sphere(24, 12, 1.0, (0, 0, 1.0)), grid_plane(6.0, 8, 0.0)),
    "soup": lambda rng: triangle_soup(400, rng),
}
RAYS = {"uv_sphere": 15_000, "bunny": 12_000, "sphere_on_plane": 12_000, "soup": 10_000}


@pytest.mark.parametrize("name", list(MESHES))
def test_intersect_matches_brute_force(tracer, name):
    rng = np.random.default_rng(1234)
    vertices, triangles = MESHES[name](rng)
    load(tracer, vertices, triangles)
    origins, directions = random_rays(vertices, RAYS[name], rng)
    hits = tracer.intersect(origins, directions)
    ref_t, ref_i, ref_edge = brute_force(vertices, triangles, origins, directions)

    assert hits.t.dtype == np.float32 and hits.triangle.dtype == np.int32
    assert np.isfinite(ref_t).mean() > 0.2, "the rays should mostly hit something"
    assert ((hits.triangle >= 0) == np.isfinite(hits.t)).all()
    assert not np.isnan(hits.t).any() and not np.isnan(hits.u).any()

    same = (hits.triangle == ref_i) & (
        (ref_i < 0) | np.isclose(hits.t, ref_t, rtol=1e-5, atol=0))
    differ = np.flatnonzero(~same)
    # A difference is explained only by a near-edge reference hit or a near tie: our triangle's
    # exact (float64) t equals the reference t within tolerance.
    our_exact_t = ray_t_on_triangle(vertices, triangles, hits.triangle[differ],
                                    origins[differ].astype(np.float64),
                                    directions[differ].astype(np.float64))
    near_edge = ref_edge[differ] < 1e-5
    tie = np.isclose(our_exact_t, ref_t[differ], rtol=1e-5, atol=0)
    unexplained = differ[~(near_edge | tie)]
    assert len(unexplained) == 0, (
        f"{len(unexplained)} unexplained of {len(differ)} differences, first: ray "
        f"{unexplained[0]} ours {hits.triangle[unexplained[0]]} t={hits.t[unexplained[0]]} "
        f"ref {ref_i[unexplained[0]]} t={ref_t[unexplained[0]]}")
    assert len(differ) <= 1e-4 * len(origins) + 2

    # The reported barycentrics reproduce the hit point.
    hit = hits.triangle >= 0
    tri = vertices[triangles[hits.triangle[hit]]].astype(np.float64)
    u, v = hits.u[hit, None].astype(np.float64), hits.v[hit, None].astype(np.float64)
    point_bary = (1 - u - v) * tri[:, 0] + u * tri[:, 1] + v * tri[:, 2]
    point_ray = origins[hit] + hits.t[hit, None].astype(np.float64) * directions[hit]
    scale = np.abs(vertices).max()
    assert np.abs(point_bary - point_ray).max() < 1e-4 * scale


def test_zero_copy_queries_match_copied_ones_and_leave_the_rays_alone():
    """On CPU devices the ray queries read the caller's arrays and write their results in place
    (USE_HOST_PTR): the same answers as with copies, inputs untouched, read-only inputs fine,
    and no result aliases another query's."""
    tracer = Tracer("cpu")
    assert tracer.zero_copy
    rng = np.random.default_rng(7)
    vertices, triangles = MESHES["sphere_on_plane"](rng)
    load(tracer, vertices, triangles)
    origins, directions = random_rays(vertices, 5_000, rng)
    origins, directions = origins.astype(np.float32), directions.astype(np.float32)
    kept = origins.copy(), directions.copy()
    answers = {}
    for zero_copy in (True, False):
        tracer.zero_copy = zero_copy
        answers[zero_copy] = (tracer.intersect(origins, directions),
                              tracer.occluded(origins, directions, tmax=0.5))
    (hits, blocked), (ref_hits, ref_blocked) = answers[True], answers[False]
    for field in ("t", "triangle", "u", "v"):
        assert np.array_equal(getattr(hits, field), getattr(ref_hits, field))
    assert np.array_equal(blocked, ref_blocked) and 0 < blocked.mean() < 1
    assert np.array_equal(origins, kept[0]) and np.array_equal(directions, kept[1])
    tracer.zero_copy = True
    frozen_o, frozen_d = origins.copy(), directions.copy()
    frozen_o.flags.writeable = frozen_d.flags.writeable = False
    again = tracer.intersect(frozen_o, frozen_d)
    assert np.array_equal(again.t, ref_hits.t) and np.array_equal(again.triangle, ref_hits.triangle)
    assert not np.shares_memory(again.t, hits.t)


def test_hand_built_trees_agree(tracer):
    """The single leaf, a hand-built split, and the real tree give identical answers."""
    rng = np.random.default_rng(5)
    vertices, triangles = merge(uv_sphere(16, 8), grid_plane(4.0, 4, -1.0))
    origins, directions = random_rays(vertices, 5000, rng)
    results = []
    for tree in (single_leaf_tree(vertices, triangles), two_level_tree(vertices, triangles, 2),
                 make_tree(vertices, triangles)):
        load(tracer, vertices, triangles, tree)
        results.append(tracer.intersect(origins, directions))
    for other in results[1:]:
        np.testing.assert_array_equal(other.triangle, results[0].triangle)
        np.testing.assert_array_equal(other.t, results[0].t)


def test_tmin_tmax_and_ties(tracer):
    # Two identical triangles: the lower index wins; a third, further along, is found beyond.
    tri = np.array([[-1, -1, 0], [1, -1, 0], [0, 1, 0]], np.float32)
    vertices = np.vstack([tri, tri, tri + [0, 0, -2]])
    triangles = np.arange(9, dtype=np.uint32).reshape(3, 3)
    load(tracer, vertices, triangles)
    o = np.array([[0, 0, 1]] * 3, np.float32)
    d = np.array([[0, 0, -1]] * 3, np.float32)
    hits = tracer.intersect(o, d)
    assert hits.triangle.tolist() == [0, 0, 0] and hits.t.tolist() == [1, 1, 1]
    hits = tracer.intersect(o, d, tmin=1.5)
    assert hits.triangle.tolist() == [2, 2, 2] and hits.t.tolist() == [3, 3, 3]
    hits = tracer.intersect(o, d, tmax=0.5)
    assert hits.triangle.tolist() == [-1] * 3 and np.isinf(hits.t).all()


def test_rays_on_and_parallel_to_split_planes(tracer):
    """Rays lying in a split plane or starting on it (0 * inf = NaN in the traversal)."""
    vertices, triangles = grid_plane(4.0, 4, 0.0)       # the plane x = 0 is a grid line
    # A vertical wall in the split plane x = 0 and the floor grid.
    wall = np.array([[0, -1, -1], [0, 1, -1], [0, 0, 1]], np.float32)
    vertices, triangles = merge((vertices, triangles), (wall, np.array([[0, 1, 2]], np.uint32)))
    wall_index = len(triangles) - 1
    for tree in (two_level_tree(vertices, triangles, 0, 0.0), make_tree(vertices, triangles)):
        load(tracer, vertices, triangles, tree)
        o = np.array([[0, 0, 2],          # on the plane x = 0, straight down: floor
                      [0, 1.5, 1],        # on the plane, down: floor at x = 0
                      [0, -1.5, 0.5],     # parallel to the plane, inside it: edge-on wall
                      [-1, 0.2, 0.2],     # along +x through the plane: hits the wall
                      [1, 0.2, 0.2]], np.float32)
        d = np.array([[0, 0, -1], [0, 0, -1], [0, 1, 0], [1, 0, 0], [-1, 0, 0]], np.float32)
        hits = tracer.intersect(o, d)
        assert np.isfinite(hits.t[[0, 1, 3, 4]]).all()
        assert hits.t[0] == pytest.approx(2) and hits.t[1] == pytest.approx(1)
        assert hits.triangle[3] == wall_index and hits.t[3] == pytest.approx(1)
        assert hits.triangle[4] == wall_index and hits.t[4] == pytest.approx(1)
        assert not np.isnan(hits.t).any()


def test_bad_inputs(tracer):
    load(tracer, *uv_sphere(8, 4))
    with pytest.raises(ValueError):
        tracer.intersect(np.zeros((4, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError):
        tracer.intersect(np.zeros((4, 3)), np.zeros((4, 3)))     # zero directions
    with pytest.raises(ValueError):
        tracer.intersect(np.full((1, 3), np.nan), np.ones((1, 3)))
    with pytest.raises(TracerError):
        Tracer(device="7:7")
    assert "-DHAS_SPOT" in kernel_options({"stack_size": 32, "light_kinds": ["SPOT"]})
    assert not any("fast" in o or "finite" in o for o in kernel_options({"light_kinds": LIGHTS}))


LIGHTS = ["POINT", "SUN", "SPOT", "AREA"]


# -- render_tile --------------------------------------------------------------------------
def camera_looking_down(height=5.0, kind="PERSP", scale=1.0):
    """Camera at (0, 0, height) looking along -Z (identity rotation): the image x axis is
    world +X, image up is world +Y."""
    m = np.eye(4)
    m[2, 3] = height
    return Camera(kind, m, (scale, scale), (0.0, 0.0), 0.1, 100.0)


def plane_view(camera, lights=(), width=32, height=24, world=(0.1, 0.2, 0.3)):
    return View(camera, width, height, Shading(np.array([[0.5, 0.6, 0.7, 1]], np.float32),
                                               list(lights), world),
                settings=RenderSettings(samples_per_axis=1, adaptive=False))


def test_depth_and_normal_of_a_plane(tracer):
    vertices, triangles = grid_plane(4.0, 4, 0.0)
    load(tracer, vertices, triangles)
    for kind, scale in (("PERSP", 0.5), ("ORTHO", 3.0)):
        view = plane_view(camera_looking_down(5.0, kind, scale), width=40, height=30)
        passes = tracer.render_tile(view, 0, 0, 40, 30)
        assert passes["combined"].shape == (30, 40, 4) and passes["depth"].shape == (30, 40)
        assert passes["normal"].shape == (30, 40, 3)
        # Pixel centres -> world points on z = 0 (where inside the 4x4 plane).
        px, py = np.meshgrid(np.arange(40), np.arange(30))
        ndc_x, ndc_y = (px + 0.5) / 40 * 2 - 1, 1 - (py + 0.5) / 30 * 2
        world_x = ndc_x * scale * (5.0 if kind == "PERSP" else 1.0)
        world_y = ndc_y * scale * (5.0 if kind == "PERSP" else 1.0)
        inside = (np.abs(world_x) < 1.99) & (np.abs(world_y) < 1.99)
        outside = (np.abs(world_x) > 2.01) | (np.abs(world_y) > 2.01)
        assert inside.sum() > 100 and outside.sum() > 10
        # Depth along the view axis is the height for every pixel (Cycles' Depth), not the
        # ray length.
        np.testing.assert_allclose(passes["depth"][inside], 5.0, rtol=1e-6)
        assert (passes["depth"][outside] == 1e10).all()
        np.testing.assert_array_equal(passes["normal"][inside], [[0, 0, 1]] * inside.sum())
        assert (passes["normal"][outside] == 0).all()
        # Misses show the world colour; with no lights the plane is lit by the world alone
        # (albedo x world colour on average: the whole upper hemisphere is sky); alpha is 1.
        np.testing.assert_allclose(passes["combined"][outside], [[0.1, 0.2, 0.3, 1]] * outside.sum())
        np.testing.assert_allclose(passes["combined"][inside][:, :3].mean(0),
                                   [0.05, 0.12, 0.21], rtol=0.05)
        assert (passes["combined"][inside][:, 3] == 1).all()


def test_normal_faces_the_ray_and_clipping(tracer):
    vertices, triangles = grid_plane(4.0, 2, 0.0)
    load(tracer, vertices, triangles)
    m = np.diag([1.0, -1.0, -1.0, 1.0])     # camera below the plane, looking up (+Z)
    m[2, 3] = -3.0
    view = plane_view(Camera("PERSP", m, (0.1, 0.1), (0, 0), 0.1, 100.0), width=8, height=8)
    passes = tracer.render_tile(view, 0, 0, 8, 8)
    np.testing.assert_array_equal(passes["normal"].reshape(-1, 3), [[0, 0, -1]] * 64)
    np.testing.assert_allclose(passes["depth"], 3.0, rtol=1e-6)
    view.camera.clip_end = 2.9              # the plane lies beyond the far clip: all misses
    assert (tracer.render_tile(view, 0, 0, 8, 8)["depth"] == 1e10).all()
    view.camera.clip_end, view.camera.clip_start = 100.0, 3.1   # ... before the near clip
    assert (tracer.render_tile(view, 0, 0, 8, 8)["depth"] == 1e10).all()


def test_tile_equals_cut_from_full_image_and_is_deterministic(tracer):
    vertices, triangles = merge(uv_sphere(24, 12, 1.0, (0, 0, 1)), grid_plane(8.0, 8, 0.0))
    material_ids = np.r_[np.zeros(len(uv_sphere(24, 12)[1])), np.ones(128)].astype(np.uint16)
    load(tracer, vertices, triangles, material_ids=material_ids)
    m = np.eye(4)
    m[:3, 3] = (0, -6, 3)
    angle = math.radians(65)                # tilt the camera up from looking down
    m[:3, :3] = [[1, 0, 0], [0, math.cos(angle), -math.sin(angle)],
                 [0, math.sin(angle), math.cos(angle)]]
    lights = [Light("POINT", (1, 1, 1), 500.0, (2, -2, 4)),
              Light("SUN", (1, 0.9, 0.8), 2.0, direction=(-0.3, 0.2, -1)),
              Light("SPOT", (1, 1, 1), 800.0, (-2, 0, 5), (0.3, 0, -1), spot_size=0.8,
                    spot_blend=0.3),
              Light("AREA", (1, 1, 1), 300.0, (0, 2, 4), (0, -0.4, -1))]
    view = View(Camera("PERSP", m, (0.6, 0.45), (0.05, 0), 0.1, 100), 64, 48,
                Shading(np.array([[0.8, 0.2, 0.2, 1], [0.7, 0.7, 0.7, 1]], np.float32), lights,
                        (0.05, 0.05, 0.05)),
                settings=RenderSettings(samples_per_axis=1, adaptive=False))
    full = tracer.render_tile(view, 0, 0, 64, 48)
    tile = tracer.render_tile(view, 20, 10, 17, 13)
    for name in full:
        np.testing.assert_array_equal(tile[name], full[name][10:23, 20:37])
        assert np.isfinite(full[name]).all()
    again = tracer.render_tile(view, 0, 0, 64, 48)
    for name in full:
        np.testing.assert_array_equal(again[name], full[name])
    # Nor does the work-item that renders a pixel change it (a queue of pixels on CPU devices,
    # one work-item per pixel in the driver's groups elsewhere).
    queue = tracer.pixel_queue
    try:
        for tracer.pixel_queue in (not queue, queue):
            other = tracer.render_tile(view, 0, 0, 64, 48)
            for name in full:
                np.testing.assert_array_equal(other[name], full[name])
    finally:
        tracer.pixel_queue = queue
    # The sphere casts a shadow and both materials and the world appear.
    colours = full["combined"][..., :3].reshape(-1, 3)
    assert (colours[:, 0] > colours[:, 1] + 0.05).any()    # red sphere
    assert (full["depth"] == 1e10).any() and (full["depth"] < 1e10).any()
    with pytest.raises(ValueError):
        tracer.render_tile(view, 60, 0, 8, 8)


def test_launches_of_any_size_give_the_same_bits_and_stop_between_them(tracer, monkeypatch):
    """render_tile traces in launches of bounded work: with launches of one sample of a few
    pixels the tile is the one-launch tile bit for bit (uniform, stratified with depth and
    normal, adaptive); `stop` is asked before each launch and ends the tile with RenderStopped
    (the tracer renders on afterwards)."""
    import kdtrace.slave.tracer as tracer_module
    from kdtrace.slave.tracer import RenderStopped
    from tests.test_network import make_scene, make_view
    tracer.load(Scene.from_parts(*make_scene()))
    view = make_view(40, 30)
    view.shading.lights.append(Light("AREA", (1, 1, 1), 300.0, (0, 2, 4), (0, -0.4, -1)))
    for settings in (RenderSettings(samples_per_axis=1, adaptive=False),
                     RenderSettings(samples_per_axis=3, adaptive=False, light_samples_per_axis=2),
                     RenderSettings(samples_per_axis=6, adaptive=True, adaptive_min_samples=4,
                                    adaptive_threshold=0.05),
                     RenderSettings(samples_per_axis=6, adaptive=True, adaptive_min_samples=4,
                                    adaptive_threshold=0.05, undersample=True)):
        view.settings = settings
        monkeypatch.setattr(tracer_module, "FIRST_LAUNCH_RAYS", 1 << 62)
        monkeypatch.setattr(tracer_module, "MAX_LAUNCH_RAYS", 1 << 62)
        monkeypatch.setattr(tracer_module, "LAUNCH_SECONDS", 1e9)
        whole = tracer.render_tile(view, 3, 2, 33, 25)      # one launch a run
        assert tracer.last_render["launches"] <= 5
        per_sample = view.rays_per_sample()
        for budget in (per_sample, 37 * per_sample):      # one pixel-sample; 37 of them
            monkeypatch.setattr(tracer_module, "FIRST_LAUNCH_RAYS", budget)
            monkeypatch.setattr(tracer_module, "MIN_LAUNCH_RAYS", budget)
            monkeypatch.setattr(tracer_module, "MAX_LAUNCH_RAYS", budget)
            monkeypatch.setattr(tracer_module, "LAUNCH_PIXELS_PER_UNIT", 1)
            cut = tracer.render_tile(view, 3, 2, 33, 25)
            assert tracer.last_render["launches"] > 33 * 25 // 37
            for name in whole:
                assert cut[name].tobytes() == whole[name].tobytes(), (settings, budget, name)
        monkeypatch.undo()
    asked = []

    def stop():
        asked.append(time.perf_counter())
        return len(asked) > 3
    monkeypatch.setattr(tracer_module, "FIRST_LAUNCH_RAYS", view.rays_per_sample() * 50)
    monkeypatch.setattr(tracer_module, "MAX_LAUNCH_RAYS", view.rays_per_sample() * 50)
    with pytest.raises(RenderStopped):
        tracer.render_tile(view, 3, 2, 33, 25, stop=stop)
    assert len(asked) == 4          # asked before each of 3 launches, and the 4th was not made
    again = tracer.render_tile(view, 3, 2, 33, 25, stop=lambda: False)
    for name in whole:
        assert again[name].tobytes() == whole[name].tobytes()


def test_pixel_order_is_a_coherent_permutation():
    """render_tile hands pixels to the kernel in 16x16 Morton blocks (docs/tracer.md): every
    tile-local index exactly once, whatever the tile's size, and neighbours stay close."""
    for w, h in ((1, 1), (17, 5), (64, 48), (33, 70), (1024, 3)):
        order = tile_pixel_order(w, h)
        assert order.dtype == np.int32
        np.testing.assert_array_equal(np.sort(order), np.arange(w * h))
    # Each run of 256 work-items covers one 16x16 block (row order: 4 rows of 64).
    y, x = np.divmod(tile_pixel_order(64, 64).reshape(-1, 256), 64)
    np.testing.assert_array_equal(x.max(1) - x.min(1), 15)
    np.testing.assert_array_equal(y.max(1) - y.min(1), 15)
