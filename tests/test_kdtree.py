"""kd-tree tests: node format, and leaf contents checked against brute-force triangle/box tests."""
import numpy as np
import pytest

from kdtrace.core.accel.kdtree import KDTree, KDTreeParams, LEAF_TAG, build_kdtree
from tests.meshes import grid_plane, load_bunny, merge, uv_sphere


# ---------------------------------------------------------------------------------------------
# An independent reading of the tree

def walk(tree: KDTree):
    """Decode every node from the root; check the format on the way.

    Returns the leaves in node-index order as arrays: node index, cell lo, cell hi, depth, first
    reference, count.
    """
    nodes = tree.nodes
    assert nodes.dtype == np.uint32 and nodes.ndim == 2 and nodes.shape[1] == 2
    assert tree.leaf_indices.dtype == np.uint32
    visited = np.zeros(len(nodes), bool)
    leaves = []
    stack = [(0, tree.bounds[0].astype(np.float32), tree.bounds[1].astype(np.float32), 0)]
    while stack:
        index, lo, hi, depth = stack.pop()
        assert 0 <= index < len(nodes) and not visited[index], "each node reached once"
        visited[index] = True
        word0, word1 = int(nodes[index, 0]), int(nodes[index, 1])
        tag, field = word0 & 3, word0 >> 2
        if tag == LEAF_TAG:
            assert word1 + field <= len(tree.leaf_indices), "leaf range inside leaf_indices"
            leaves.append((index, lo, hi, depth, word1, field))
            continue
        split = np.uint32(word1).view(np.float32)
        assert lo[tag] < split < hi[tag], "split strictly inside the parent cell"
        assert field + 1 < len(nodes), "children in range"
        below_hi, above_lo = hi.copy(), lo.copy()
        below_hi[tag] = split
        above_lo[tag] = split
        stack.append((field, lo, below_hi, depth + 1))
        stack.append((field + 1, above_lo, hi, depth + 1))
    assert visited.all(), "no unreachable nodes"
    leaves.sort(key=lambda leaf: leaf[0])   # node-index order, as leaf_number() counts them
    index, lo, hi, depth, first, count = zip(*leaves)
    return (np.array(index), np.array(lo, np.float64), np.array(hi, np.float64), np.array(depth),
            np.array(first, np.int64), np.array(count, np.int64))


def separation(corners, lo, hi):
    """Signed distance by which a triangle and a box are apart along the best separating axis.

    Separating axis theorem over the 13 axes (3 box normals, the triangle normal, 9 edge
    crosses), in float64, each normalised. > 0: disjoint by that gap; < 0: the triangle reaches
    that deep into the box's interior; 0: they touch only on the boundary.
    """
    center, half = (lo + hi) / 2, (hi - lo) / 2
    v = corners - center[:, None, :]
    edges = np.stack([v[:, 1] - v[:, 0], v[:, 2] - v[:, 1], v[:, 0] - v[:, 2]], 1)
    unit = np.eye(3)
    axes = [np.broadcast_to(unit[i], (len(v), 3)) for i in range(3)]
    axes.append(np.cross(edges[:, 0], edges[:, 1]))
    axes += [np.cross(unit[i], edges[:, j]) for i in range(3) for j in range(3)]
    worst = np.full(len(v), -np.inf)
    for axis in axes:
        length = np.linalg.norm(axis, axis=1)
        usable = length > 0
        n = axis / np.where(usable, length, 1.0)[:, None]
        proj = np.einsum("pk,pjk->pj", n, v)
        radius = (np.abs(n) * half).sum(1)
        gap = np.maximum(proj.min(1) - radius, -radius - proj.max(1))
        worst = np.where(usable, np.maximum(worst, gap), worst)
    return worst


def check_tree(vertices, triangles, tree, params=None):
    """Structural checks and completeness/soundness of every leaf against brute force."""
    params = params or KDTreeParams()
    vertices = np.asarray(vertices, np.float32)
    triangles = np.asarray(triangles, np.int64)
    corners = vertices[triangles].astype(np.float64)
    leaf_node, leaf_lo, leaf_hi, depth, first, count = walk(tree)

    # Stats agree with the arrays.
    stats = tree.stats
    assert stats["nodes"] == len(tree.nodes)
    assert stats["leaves"] == len(leaf_node)
    assert stats["empty_leaves"] == int((count == 0).sum())
    assert stats["depth"] == depth.max()
    assert stats["references"] == len(tree.leaf_indices) == count.sum()
    assert stats["bytes"] == tree.nbytes == tree.nodes.nbytes + tree.leaf_indices.nbytes
    assert depth.max() <= params.depth_cap(len(triangles))
    assert tree.bounds.dtype == np.float32 and tree.bounds.shape == (2, 3)
    assert (tree.bounds[0] < tree.bounds[1]).all()

    # Every reference: (leaf, triangle) pairs, no triangle twice in one leaf.
    ref_leaf = np.repeat(np.arange(len(leaf_node)), count)
    ref_tri = np.concatenate([tree.leaf_indices[f:f + c] for f, c in zip(first, count)]
                             + [np.zeros(0, np.uint32)]).astype(np.int64)
    assert (ref_tri < len(triangles)).all()
    referenced = ref_leaf * len(triangles) + ref_tri
    assert len(np.unique(referenced)) == len(referenced), "a triangle twice in one leaf"

    scale = max(float(np.abs(tree.bounds).max()), 1e-30)
    tolerance = 1e-9 * scale

    # Soundness: a referenced triangle touches its leaf's cell (within a tiny tolerance).
    gap = separation(corners[ref_tri], leaf_lo[ref_leaf], leaf_hi[ref_leaf])
    assert (gap <= tolerance).all(), f"{(gap > tolerance).sum()} references to far triangles"

    # Completeness: every non-degenerate triangle reaching into a cell's interior is referenced.
    area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    solid = np.flatnonzero(area > 0)
    tri_lo, tri_hi = corners[solid].min(1), corners[solid].max(1)
    chunk = max(1, 2_000_000 // max(len(solid), 1))
    for start in range(0, len(leaf_node), chunk):
        lo, hi = leaf_lo[start:start + chunk], leaf_hi[start:start + chunk]
        near = ((tri_lo[None] < hi[:, None]) & (tri_hi[None] > lo[:, None])).all(2)
        pair_leaf, pair_solid = np.nonzero(near)
        pair_tri = solid[pair_solid]
        pair_leaf += start
        depth_inside = separation(corners[pair_tri], leaf_lo[pair_leaf], leaf_hi[pair_leaf])
        required = depth_inside < -1e-12 * scale
        missing = ~np.isin(pair_leaf * len(triangles) + pair_tri, referenced) & required
        assert not missing.any(), f"{missing.sum()} triangles missing from leaves they cross"

    # Triangles lying in a cell face reach no interior: check instead that sample points on every
    # triangle find it in at least one leaf whose closed cell holds the point.
    check_points_covered(tree, corners, solid, referenced, len(triangles))


def check_points_covered(tree, corners, solid, referenced, triangle_count):
    weights = np.array([[1, 1, 1], [4, 1, 1], [1, 4, 1], [1, 1, 4]], np.float64)
    weights /= weights.sum(1, keepdims=True)
    points = np.einsum("sk,tkd->tsd", weights, corners[solid]).reshape(-1, 3)
    point_tri = np.repeat(solid, len(weights))
    # Descend all points at once; a point on a split plane goes to both children (within the
    # points' own rounding: a triangle lying in a split plane may be in either child, and its
    # sample points, formed in float64, may round to just off the plane).
    tolerance = 1e-12 * max(float(np.abs(tree.bounds).max()), 1e-30)
    point, node = np.arange(len(points)), np.zeros(len(points), np.int64)
    found = np.zeros(len(points), bool)
    while len(point):
        word0 = tree.nodes[node, 0].astype(np.int64)
        is_leaf = (word0 & 3) == LEAF_TAG
        leaf_point = point[is_leaf]
        key = leaf_number(tree, node[is_leaf]) * triangle_count + point_tri[leaf_point]
        found[leaf_point[np.isin(key, referenced)]] = True
        point, node, word0 = point[~is_leaf], node[~is_leaf], word0[~is_leaf]
        axis, child = word0 & 3, word0 >> 2
        split = tree.nodes[node, 1].view(np.float32).astype(np.float64)
        coord = points[point, axis]
        below, above = coord <= split + tolerance, coord >= split - tolerance
        point = np.concatenate([point[below], point[above]])
        node = np.concatenate([child[below], child[above] + 1])
    assert found.all(), f"{(~found).sum()} sample points not covered by their triangle's leaves"


def leaf_number(tree, node_index):
    """The position walk() gives a leaf node: leaves counted in order of node index."""
    is_leaf = (tree.nodes[:, 0] & 3) == LEAF_TAG
    return (np.cumsum(is_leaf) - 1)[node_index]


def build_and_check(vertices, triangles, params=None):
    tree = build_kdtree(vertices, triangles, params)
    check_tree(vertices, triangles, tree, params)
    return tree


# ---------------------------------------------------------------------------------------------
# Scenes

def cube_of_quads(cells=4, size=2.0):
    """An axis-aligned cube surface of cells x cells quads per face, with coplanar duplicates."""
    meshes = []
    for axis in range(3):
        for side in (-size / 2, size / 2):
            v, t = grid_plane(size, cells, 0.0)
            v = v.astype(np.float64)
            v = np.roll(np.column_stack([v[:, 0], v[:, 1], np.full(len(v), side)]), axis + 1, 1)
            meshes.append((v.astype(np.float32), t))
    # Internal axis-aligned walls exactly on likely split planes (the centre), twice over.
    v, t = grid_plane(size, cells, 0.0)
    meshes += [(v, t), (v, t), (np.roll(v, 1, 1), t)]
    return merge(*meshes)


def sliver_scene(count=200, seed=1):
    """Long thin triangles, each nearly a line segment, crossing each other."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(-1, 1, (count, 3))
    b = rng.uniform(-1, 1, (count, 3))
    c = a + rng.uniform(-1, 1, (count, 3)) * 1e-4
    vertices = np.stack([a, b, c], 1).reshape(-1, 3).astype(np.float32)
    return vertices, np.arange(3 * count, dtype=np.uint32).reshape(-1, 3)


def triangle_soup(count=400, seed=2):
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-5, 5, (count, 1, 3))
    vertices = (centres + rng.normal(0, 0.7, (count, 3, 3))).reshape(-1, 3).astype(np.float32)
    return vertices, np.arange(3 * count, dtype=np.uint32).reshape(-1, 3)


SCENES = {
    "sphere": lambda: uv_sphere(32, 16),
    "bunny": load_bunny,
    "sphere_over_plane": lambda: merge(uv_sphere(24, 12, 1.0, (0, 0, 1.2)), grid_plane(10, 8, 0.0)),
    "cube_of_quads": cube_of_quads,
    "slivers": sliver_scene,
    "soup": triangle_soup,
}


@pytest.mark.parametrize("name", list(SCENES))
def test_leaves_hold_exactly_the_overlapping_triangles(name):
    vertices, triangles = SCENES[name]()
    tree = build_and_check(vertices, triangles)
    assert tree.stats["leaves"] > 1


def test_coarse_bins_still_correct():
    # Few bins: more planes fall on awkward positions; correctness must not depend on binning.
    vertices, triangles = merge(uv_sphere(16, 8), cube_of_quads(2))
    build_and_check(vertices, triangles, KDTreeParams(max_bins=4, min_bins=2))


def test_node_format_and_stats():
    vertices, triangles = uv_sphere(32, 16)
    levels = []
    tree = build_kdtree(vertices, triangles, progress=lambda f, m: levels.append(f))
    assert tree.nodes.shape[1] == 2 and tree.stats["nodes"] == len(tree.nodes)
    assert levels == sorted(levels) and levels[-1] == 1.0 and len(levels) >= tree.stats["depth"]
    word0 = tree.nodes[:, 0]
    inner = (word0 & 3) != LEAF_TAG
    assert ((word0[inner] >> 2) > np.flatnonzero(inner)).all(), "children after their parent"
    assert tree.stats["refs_per_triangle"] == pytest.approx(
        len(tree.leaf_indices) / len(triangles))
    assert tree.stats["build_seconds"] >= 0


def test_one_triangle():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    tree = build_and_check(vertices, np.array([[0, 1, 2]], np.uint32))
    assert tree.stats["references"] >= 1


def test_identical_triangles():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.5]], np.float32)
    triangles = np.tile(np.array([[0, 1, 2]], np.uint32), (50, 1))
    tree = build_and_check(vertices, triangles)
    assert tree.stats["references"] >= 50


def test_zero_area_triangles_are_dropped():
    vertices, triangles = uv_sphere(16, 8)
    degenerate = np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2], [0, 0, 1]], np.uint32)
    collinear = np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2]], np.float32)
    vertices, triangles = merge((vertices, triangles), (collinear, np.array([[0, 1, 2]], np.uint32)))
    triangles = np.vstack([triangles, degenerate])
    tree = build_and_check(vertices, triangles)
    assert tree.stats["dropped_degenerate"] == 5
    assert not np.isin(np.arange(len(triangles) - 5, len(triangles)), tree.leaf_indices).any()


def test_only_degenerate_or_no_triangles():
    vertices = np.array([[0, 0, 0], [1, 1, 1]], np.float32)
    for triangles in (np.array([[0, 0, 1]], np.uint32), np.zeros((0, 3), np.uint32)):
        tree = build_kdtree(vertices, triangles)
        assert tree.stats["nodes"] == 1 and tree.stats["references"] == 0
        assert (tree.bounds[0] < tree.bounds[1]).all()


def test_flat_scene():
    vertices, triangles = grid_plane(4.0, 6, z=2.5)
    tree = build_and_check(vertices, triangles)
    assert tree.bounds[0, 2] < 2.5 < tree.bounds[1, 2], "root box padded in the flat axis"


def test_bad_input_is_rejected():
    vertices = np.zeros((3, 3), np.float32)
    with pytest.raises(ValueError):
        build_kdtree(vertices, np.array([[0, 1, 3]]))
    with pytest.raises(ValueError):
        build_kdtree(np.full((3, 3), np.nan, np.float32), np.array([[0, 1, 2]]))


@pytest.mark.parametrize("name", ["bunny", "cube_of_quads"])
def test_binned_sah_in_chunks_gives_the_same_tree(name, monkeypatch):
    # Binned SAH runs in chunks of BINNED_CHUNK nodes; the chunking must not change the tree.
    import kdtrace.core.accel.sah_splits as sah
    vertices, triangles = SCENES[name]()
    reference = build_kdtree(vertices, triangles)
    monkeypatch.setattr(sah, "BINNED_CHUNK", 3)
    chunked = build_kdtree(vertices, triangles)
    assert np.array_equal(reference.nodes, chunked.nodes)
    assert np.array_equal(reference.leaf_indices, chunked.leaf_indices)


def _round_f32(x, down):
    f = np.float32(x)
    if (float(f) > x) if down else (float(f) < x):
        f = np.nextafter(f, np.float32(-np.inf if down else np.inf))
    return f


def _reference_halves(tri, cell_lo, cell_hi, axis, plane):
    """Perfect split of one triangle, one polygon at a time (plain Sutherland-Hodgman): the
    triangle clipped to the faces of the cell that its box crosses, then cut at the plane."""
    def clip(poly, a, value, keep_below):
        dist = [value - p[a] if keep_below else p[a] - value for p in poly]
        out = []
        for i, p in enumerate(poly):
            j = (i + 1) % len(poly)
            if dist[i] >= 0:
                out.append(p)
            if (dist[i] > 0 and dist[j] < 0) or (dist[i] < 0 and dist[j] > 0):
                t = dist[i] / (dist[i] - dist[j])
                q = p + t * (poly[j] - p)
                q[a] = value
                out.append(q)
        return out

    lo64, hi64 = cell_lo.astype(np.float64), cell_hi.astype(np.float64)
    poly = [tri[i].copy() for i in range(3)]
    for a in range(3):
        if tri[:, a].min() < lo64[a]:
            poly = clip(poly, a, lo64[a], False)
        if tri[:, a].max() > hi64[a]:
            poly = clip(poly, a, hi64[a], True)
    halves = []
    for side in (0, 1):
        piece = clip(poly, axis, float(plane), side == 0) if poly else []
        tri_flat = tri.min(0) == tri.max(0)
        if len(piece) < 3:
            halves.append(None)
            continue
        lo, hi = np.min(piece, 0), np.max(piece, 0)
        if ((hi - lo == 0) & ~tri_flat).any():
            halves.append(None)
            continue
        child_lo, child_hi = cell_lo.copy(), cell_hi.copy()
        (child_hi if side == 0 else child_lo)[axis] = plane
        halves.append((np.maximum([_round_f32(x, True) for x in lo], child_lo),
                       np.minimum([_round_f32(x, False) for x in hi], child_hi)))
    return halves


def test_batched_straddler_clipping_matches_one_polygon_at_a_time():
    # clip_straddlers clips only crossing faces, groups polygons by vertex count and
    # interpolates only crossing edges; the boxes must equal a plain per-polygon clip exactly.
    from kdtrace.core.accel.clipping import clip_straddlers
    rng = np.random.default_rng(5)
    count = 600
    tri = rng.uniform(-1, 1, (count, 3, 3)).astype(np.float32).astype(np.float64)
    tri[:50, :, 2] = np.float32(0.25)                       # flat triangles
    tri[50:100, 0] = [0.0, 0.0, 0.0]                        # a vertex on the plane below
    cell_lo = rng.uniform(-0.8, -0.1, (count, 3)).astype(np.float32)
    cell_hi = rng.uniform(0.1, 0.8, (count, 3)).astype(np.float32)
    cell_lo[:20], cell_hi[:20] = -2, 2                       # triangles inside their cell
    axis = rng.integers(0, 3, count)
    plane = np.zeros(count, np.float32)
    plane[100:] = rng.uniform(-0.05, 0.05, count - 100).astype(np.float32)
    halves = clip_straddlers(tri, cell_lo, cell_hi, axis, plane)
    for k in range(count):
        expected = _reference_halves(tri[k], cell_lo[k], cell_hi[k], axis[k], plane[k])
        for side in (0, 1):
            lo, hi, ok = halves[side]
            assert ok[k] == (expected[side] is not None), (k, side)
            if ok[k]:
                assert np.array_equal(lo[k], expected[side][0]), (k, side)
                assert np.array_equal(hi[k], expected[side][1]), (k, side)


def test_reference_rows_keep_boxes_and_triangle_ids_bit_exact():
    # References live in one (N, 7) float32 array (box lo, box hi, triangle id as int32 bits)
    # moved by whole-row gathers; ids whose bits read as float32 NaN or denormals (very large
    # or small ids) and the boxes must come through unchanged.
    import kdtrace.core.accel.ref_rows as ref_rows
    rng = np.random.default_rng(3)
    ids = np.array([0, 1, 5, 2**23 + 1, 0x7F800001, 0x7FC00000, 2**31 - 1], np.int32)
    refs = np.empty((len(ids), ref_rows.REF_WORDS), np.float32)
    refs[:, 0:3] = rng.uniform(-1, 1, (len(ids), 3))
    refs[:, 3:6] = refs[:, 0:3] + 1
    refs[:, 6].view(np.int32)[:] = ids
    index = np.array([[6, 0, 4], [5, 5, 3]])
    moved = ref_rows.gather_refs(refs, index)
    assert moved.shape == (2, 3, ref_rows.REF_WORDS)
    assert np.array_equal(moved.view(np.int32), refs.view(np.int32)[index])
    triangles = ref_rows.ref_triangles(moved.reshape(-1, ref_rows.REF_WORDS))
    assert np.array_equal(triangles, ids[index.reshape(-1)])


@pytest.mark.parametrize("name", ["bunny", "cube_of_quads"])
def test_exact_sah_in_chunks_gives_the_same_tree(name, monkeypatch):
    # Exact SAH runs in chunks of EXACT_CHUNK nodes; the chunking must not change the tree.
    import kdtrace.core.accel.sah_splits as sah
    vertices, triangles = SCENES[name]()
    reference = build_kdtree(vertices, triangles)
    monkeypatch.setattr(sah, "EXACT_CHUNK", 7)
    chunked = build_kdtree(vertices, triangles)
    assert np.array_equal(reference.nodes, chunked.nodes)
    assert np.array_equal(reference.leaf_indices, chunked.leaf_indices)


def test_progress_is_reported_and_can_stop_the_build():
    vertices, triangles = SCENES["bunny"]()
    fractions = []
    build_kdtree(vertices, triangles, progress=lambda fraction, message: fractions.append(fraction))
    assert fractions == sorted(fractions) and fractions[-1] == 1.0

    class Stop(Exception):
        pass

    def stop_at_level_5(fraction, message):
        if message.startswith("kd-tree level 5"):
            raise Stop
    with pytest.raises(Stop):
        build_kdtree(vertices, triangles, progress=stop_at_level_5)
