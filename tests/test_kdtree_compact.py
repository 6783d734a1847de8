"""Compressed kd-tree layouts (core/accel/compact.py): a reference traversal checked against
brute force, and the invariants of the lifting (every triangle still reachable from every leaf
cell it overlaps, per-node and per-path limits).

`trace_compact` is the per-layout reference that the OpenCL kernel must agree with: numpy,
vectorised over rays, float64 ray/triangle tests (the same function as the brute force, so the
two agree exactly whenever the traversal tests the right triangles).
"""
from __future__ import annotations

import functools

import numpy as np
import pytest

from kdtrace.core.accel.arrays import distinct_count
from kdtrace.core.accel.compact import MODES, compact_params, compact_tree, geometry_nbytes
from kdtrace.core.accel.compact_lifts import lift_candidates, neighbour_lcas
from kdtrace.core.accel.compact_topology import Topology
from kdtrace.core.accel.kdtree import KDTree, build_kdtree
from kdtrace.core.layout import LEAF_TAG, NO_TRIANGLE
from tests.meshes import load_bunny, uv_sphere
from tests.scenes_architecture import architecture_scene

STACK = 128


# ---------------------------------------------------------------------------------------------
# Ray/triangle test (float64 Moller-Trumbore, explicit sums so that every layout computes the
# same bits) and brute force

def _dot(a, b):
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _cross(a, b):
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], -1)


def intersect(o, d, corners, tmax):
    """t of each (ray, triangle) pair (broadcast), inf on a miss or beyond tmax; t >= 0."""
    v0, v1, v2 = corners[..., 0, :], corners[..., 1, :], corners[..., 2, :]
    e1, e2 = v1 - v0, v2 - v0
    p = _cross(d, e2)
    det = _dot(e1, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = o - v0
        u = _dot(s, p) * inv
        q = _cross(s, e1)
        v = _dot(d, q) * inv
        t = _dot(e2, q) * inv
    hit = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= tmax)
    return np.where(hit, t, np.inf)


def brute_force(corners, origins, directions, chunk=64):
    """Nearest triangle and t of every ray over all triangles; ties to the lower index.

    Every triangle is tested against every ray whose line meets the (padded) box of the chunk
    of triangles it belongs to; the box test only skips pairs that cannot hit.
    """
    n = len(origins)
    best_t = np.full(n, np.inf)
    best_tri = np.full(n, -1, np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / directions
    for start in range(0, len(corners), chunk):
        part = corners[start:start + chunk]
        lo, hi = part.reshape(-1, 3).min(0), part.reshape(-1, 3).max(0)
        pad = 1e-9 * (np.abs(lo).max() + np.abs(hi).max()) + 1e-12
        with np.errstate(invalid="ignore"):
            t_lo, t_hi = (lo - pad - origins) * inv, (hi + pad - origins) * inv
            near = np.fmax.reduce(np.fmin(t_lo, t_hi), 1)
            far = np.fmin.reduce(np.fmax(t_lo, t_hi), 1)
        rays = np.flatnonzero((near <= far) & (far >= 0) & (near <= best_t))
        if not len(rays):
            continue
        t = intersect(origins[rays, None, :], directions[rays, None, :], part[None], np.inf)
        k = np.argmin(t, 1)          # first minimum: the lower index among equal t
        tk = t[np.arange(len(rays)), k]
        better = tk < best_t[rays]   # earlier chunks hold lower indices: keep them on ties
        best_t[rays[better]] = tk[better]
        best_tri[rays[better]] = start + k[better]
    return best_t, best_tri


# ---------------------------------------------------------------------------------------------
# Reference traversal of the compact layout

def _update(best_t, best_tri, ray, t, tri):
    """Nearest of (ray, t, tri) candidates into best_*; ties to the lower triangle index."""
    hit = np.isfinite(t)
    ray, t, tri = ray[hit], t[hit], tri[hit]
    if not len(ray):
        return
    order = np.lexsort((tri, t, ray))
    ray, t, tri = ray[order], t[order], tri[order]
    first = np.flatnonzero(np.r_[True, ray[1:] != ray[:-1]])
    ray, t, tri = ray[first], t[first], tri[first]
    better = (t < best_t[ray]) | ((t == best_t[ray]) & (tri < best_tri[ray]))
    best_t[ray[better]] = t[better]
    best_tri[ray[better]] = tri[better]


def leaf_triangles(ct, word0, word1):
    """Triangle lists of leaves given their words: (leaf position repeated per item, triangle)."""
    word0 = word0.astype(np.int64)
    word1 = word1.astype(np.int64)
    wide16 = ((word0 >> 2) & 1) == 1
    count = np.where(wide16, (word0 >> 3) & 0x1FFF, word0 >> 3)
    base = np.where(wide16, (word0 >> 16) << ct.leaf_shift, 0)
    owner = np.repeat(np.arange(len(word0)), count)
    j = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    index = np.repeat(word1, count) + j
    is16 = np.repeat(wide16, count)
    tri = np.empty(len(index), np.int64)
    tri[is16] = ct.leaf_index16[index[is16]].astype(np.int64) + np.repeat(base, count)[is16]
    tri[~is16] = ct.leaf_index32[index[~is16]]
    return owner, tri


def trace_compact(ct, corners, origins, directions, tmax=np.inf, any_hit=False,
                  tie_tolerance=1e-9):
    """Nearest hit (t, triangle) of every ray through a CompactTree (any mode).

    Front-to-back stack traversal. Triangles referenced by an inner node are tested when the
    node is visited; such a hit is only a candidate: traversal stops when the next node popped
    starts beyond the best hit by more than a tolerance, or the stack is empty. The tolerance
    (relative to t plus the scene's coordinate scale along the ray) makes exact ties (coplanar
    overlapping faces, common in architecture) resolve to the lower triangle index even when
    the other triangle sits in a cell whose computed entry rounds just past the hit. any_hit:
    stop at the first hit (shadow rays).
    """
    n = len(origins)
    o, d = origins.astype(np.float64), directions.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        lo, hi = ct.bounds.astype(np.float64)
        t_lo, t_hi = (lo - o) * inv, (hi - o) * inv
        t_near = np.fmax.reduce(np.fmin(t_lo, t_hi), 1)
        t_far = np.fmin.reduce(np.fmax(t_lo, t_hi), 1)
    tmax = np.broadcast_to(np.asarray(tmax, np.float64), (n,))
    tn = np.maximum(t_near, 0.0)
    tf = np.minimum(t_far, tmax)
    scale = np.abs(ct.bounds).max() / np.linalg.norm(d, axis=1)
    best_t = np.full(n, np.inf)
    best_tri = np.full(n, -1, np.int64)
    node = np.zeros(n, np.int64)
    stack_node = np.zeros((n, STACK), np.int64)
    stack_tn = np.zeros((n, STACK))
    stack_tf = np.zeros((n, STACK))
    sp = np.zeros(n, np.int64)
    active = np.flatnonzero(tn <= tf)
    nodes = ct.nodes
    visits = 0
    while len(active):
        visits += len(active)
        w0 = nodes[node[active], 0].astype(np.int64)
        w1 = nodes[node[active], 1]
        leaf = (w0 & 3) == LEAF_TAG
        pop = np.zeros(len(active), bool)

        # Inner nodes: referenced triangles first (candidates), then the children.
        ii = np.flatnonzero(~leaf)
        if len(ii):
            rays, w = active[ii], w0[ii]
            axis, has_ref = w & 3, (w >> 2) & 1
            empty_b, empty_a, group = (w >> 3) & 1, (w >> 4) & 1, w >> 5
            with_ref = np.flatnonzero(has_ref)
            if len(with_ref):
                r = rays[with_ref]
                slots = nodes[group[with_ref]].astype(np.int64)
                for s in (0, 1):
                    ok = slots[:, s] != NO_TRIANGLE
                    tri = slots[ok, s]
                    t = intersect(o[r[ok]], d[r[ok]], corners[tri], tmax[r[ok]])
                    _update(best_t, best_tri, r[ok], t, tri)
            below = group + has_ref
            above = below + 1 - empty_b
            split = w1[ii].view(np.float32).astype(np.float64)
            oa, da = o[rays, axis], d[rays, axis]
            with np.errstate(divide="ignore", invalid="ignore"):
                tp = (split - oa) * inv[rays, axis]
            below_first = (oa < split) | ((oa == split) & (da <= 0))
            near = np.where(below_first, below, above)
            far = np.where(below_first, above, below)
            near_ok = np.where(below_first, empty_b, empty_a) == 0
            far_ok = np.where(below_first, empty_a, empty_b) == 0
            a_tn, a_tf = tn[rays], tf[rays]
            only_near = (tp > a_tf) | (tp <= 0)
            only_far = ~only_near & (tp < a_tn)
            both = ~only_near & ~only_far
            push = both & far_ok & near_ok
            pr = rays[push]
            stack_node[pr, sp[pr]] = far[push]
            stack_tn[pr, sp[pr]] = tp[push]
            stack_tf[pr, sp[pr]] = a_tf[push]
            sp[pr] += 1
            assert (sp < STACK).all()
            go_near = (only_near | both) & near_ok
            go_far = (only_far & far_ok) | (both & ~near_ok & far_ok)
            node[rays[go_near]] = near[go_near]
            tf[rays[go_near & both]] = tp[go_near & both]
            node[rays[go_far]] = far[go_far]
            tn[rays[go_far & both]] = tp[go_far & both]
            pop[ii[~go_near & ~go_far]] = True

        # Leaves: test the list, then pop.
        li = np.flatnonzero(leaf)
        if len(li):
            owner, tri = leaf_triangles(ct, w0[li], w1[li])
            r = active[li][owner]
            t = intersect(o[r], d[r], corners[tri], tmax[r])
            _update(best_t, best_tri, r, t, tri)
            pop[li] = True

        # Pop; stop when the stack is empty or the next node starts beyond the best hit.
        rays = active[pop]
        alive = sp[rays] > 0
        rays = rays[alive]
        sp[rays] -= 1
        node[rays] = stack_node[rays, sp[rays]]
        tn[rays] = stack_tn[rays, sp[rays]]
        tf[rays] = stack_tf[rays, sp[rays]]
        finished = np.zeros(n, bool)
        finished[active[pop]] = True
        margin = tie_tolerance * (best_t[rays] + scale[rays])
        finished[rays[tn[rays] <= best_t[rays] + margin]] = False
        if any_hit:
            finished[active] |= np.isfinite(best_t[active])
        active = active[~finished[active]]
    return best_t, best_tri, visits


# ---------------------------------------------------------------------------------------------
# Decoding the layout for the invariants

def locate(ct, points):
    """Descend the compact tree with points strictly inside leaf cells.

    Returns (point of each visited reference slot, triangle), (point, node) of every inner node
    on the way, and per point its final node (-1 where the cell is an elided empty leaf).
    """
    nodes = ct.nodes
    n = len(points)
    node = np.zeros(n, np.int64)
    final = np.full(n, -1, np.int64)
    ref_pt, ref_tri, path_pt, path_node = [], [], [], []
    live = np.arange(n)
    while len(live):
        w0 = nodes[node[live], 0].astype(np.int64)
        leaf = (w0 & 3) == LEAF_TAG
        final[live[leaf]] = node[live[leaf]]
        live, w0 = live[~leaf], w0[~leaf]
        if not len(live):
            break
        path_pt.append(live)
        path_node.append(node[live])
        axis, has_ref = w0 & 3, (w0 >> 2) & 1
        empty_b, empty_a, group = (w0 >> 3) & 1, (w0 >> 4) & 1, w0 >> 5
        assert not (empty_b & empty_a).any(), "both children elided"
        r = np.flatnonzero(has_ref)
        slots = nodes[group[r]].astype(np.int64)
        assert (slots[:, 0] != NO_TRIANGLE).all(), "a reference slot without a first triangle"
        for s in (0, 1):
            ok = slots[:, s] != NO_TRIANGLE
            ref_pt.append(live[r[ok]])
            ref_tri.append(slots[ok, s])
        split = nodes[node[live], 1].view(np.float32).astype(np.float64)
        below = points[live, axis] < split
        empty = np.where(below, empty_b, empty_a) == 1
        child = group + has_ref + np.where(below, 0, 1 - empty_b)
        node[live] = child
        live = live[~empty]
    cat = lambda parts: np.concatenate(parts) if parts else np.zeros(0, np.int64)
    return cat(ref_pt), cat(ref_tri), cat(path_pt), cat(path_node), final


def check_layout(ct, triangle_count):
    """Every node reached exactly once from the root, slots where the format puts them."""
    nodes = ct.nodes
    seen = np.zeros(len(nodes), np.int64)
    level = np.zeros(1, np.int64)
    seen[0] += 1
    refs_per_node = []
    while len(level):
        w0 = nodes[level, 0].astype(np.int64)
        inner = level[(w0 & 3) != LEAF_TAG]
        leaf = level[(w0 & 3) == LEAF_TAG]
        lw = nodes[leaf, 0].astype(np.int64)
        is16 = ((lw >> 2) & 1) == 1
        if is16.any():
            count16 = (lw[is16] >> 3) & 0x1FFF
            assert (count16 > 0).all()
            assert (nodes[leaf[is16], 1] + count16 <= len(ct.leaf_index16)).all()
        assert (nodes[leaf[~is16], 1] + (lw[~is16] >> 3) <= len(ct.leaf_index32)).all()
        w = nodes[inner, 0].astype(np.int64)
        has_ref, eb, ea, group = (w >> 2) & 1, (w >> 3) & 1, (w >> 4) & 1, w >> 5
        slot_nodes = group[has_ref == 1]
        seen[slot_nodes] += 1
        slots = nodes[slot_nodes].astype(np.int64)
        refs_per_node.append((slots != NO_TRIANGLE).sum(1))
        assert (slots[slots != NO_TRIANGLE] < triangle_count).all()
        below = group + has_ref
        above = below + 1 - eb
        children = np.concatenate([below[eb == 0], above[ea == 0]])
        assert (children < len(nodes)).all()
        seen[children] += 1
        level = children
    assert (seen == 1).all(), "every node (and reference slot) reached exactly once"
    return np.concatenate(refs_per_node) if refs_per_node else np.zeros(0, np.int64)


def check_invariants(tree, ct, triangle_count):
    """Lifting lost nothing: every (standard leaf, triangle) reference is found in the compact
    leaf holding that cell or on its path; the compact tree holds nothing new; limits hold."""
    params = ct.params
    refs_per_node = check_layout(ct, triangle_count)
    assert (refs_per_node <= max(params.refs_per_node, 0)).all()
    if params.mode == "choi":
        assert (refs_per_node <= 1).all()

    # Standard leaves and their cells (walk the plain tree).
    nodes = tree.nodes
    level, cell_lo, cell_hi = np.zeros(1, np.int64), tree.bounds[:1].astype(np.float64), \
        tree.bounds[1:].astype(np.float64)
    leaves, leaf_lo, leaf_hi = [], [], []
    while len(level):
        w0 = nodes[level, 0].astype(np.int64)
        is_leaf = (w0 & 3) == LEAF_TAG
        leaves.append(level[is_leaf])
        leaf_lo.append(cell_lo[is_leaf])
        leaf_hi.append(cell_hi[is_leaf])
        inner, w0 = level[~is_leaf], w0[~is_leaf]
        axis, child = w0 & 3, w0 >> 2
        split = nodes[inner, 1].view(np.float32).astype(np.float64)
        rows = np.arange(len(inner))
        b_hi, a_lo = cell_hi[~is_leaf].copy(), cell_lo[~is_leaf].copy()
        b_hi[rows, axis] = split
        a_lo[rows, axis] = split
        level = np.concatenate([child, child + 1])
        cell_lo = np.concatenate([cell_lo[~is_leaf], a_lo])
        cell_hi = np.concatenate([b_hi, cell_hi[~is_leaf]])
    leaves = np.concatenate(leaves)
    centre = (np.concatenate(leaf_lo) + np.concatenate(leaf_hi)) / 2
    count = (nodes[leaves, 0] >> 2).astype(np.int64)
    offset = nodes[leaves, 1].astype(np.int64)
    ref_point = np.repeat(np.arange(len(leaves)), count)
    ref_tri = tree.leaf_indices[np.repeat(offset, count) + np.arange(count.sum())
                                - np.repeat(np.cumsum(count) - count, count)].astype(np.int64)

    # Where each standard leaf cell lands in the compact tree.
    slot_pt, slot_tri, path_pt, path_node, final = locate(ct, centre)
    holder = final >= 0
    fw0, fw1 = ct.nodes[final[holder], 0], ct.nodes[final[holder], 1]
    owner, tri = leaf_triangles(ct, fw0, fw1)
    leaf_pt = np.flatnonzero(holder)[owner]
    T = np.int64(triangle_count)
    available = np.concatenate([leaf_pt * T + tri, slot_pt * T + slot_tri])
    needed = ref_point * T + ref_tri
    missing = ~np.isin(needed, available)
    assert not missing.any(), f"{missing.sum()} references lost (not in leaf nor on the path)"

    # Nothing new: a compact leaf or reference slot holds only triangles of standard leaves in
    # its cell.
    final_of_ref = final[ref_point]
    leaf_items = np.unique(final[leaf_pt] * T + tri)
    assert np.isin(leaf_items, final_of_ref * T + ref_tri).all(), "a compact leaf gained a triangle"
    # Reference slots: (inner node on the path, triangle) pairs that some standard reference
    # below that node has.
    owners = _slot_owner(ct, slot_pt, path_pt, path_node, slot_tri)
    slot_keys = np.unique(owners * T + slot_tri)
    # Only pairs of nodes that hold slots can match: the others are not made (the dragon's
    # pairs of every node on every path were 54 M keys to sort).
    holds = np.zeros(len(ct.nodes), bool)
    holds[owners] = True
    keep = holds[path_node]
    allowed = np.unique(path_node_pairs(path_pt[keep], path_node[keep], ref_point, ref_tri, T))
    assert np.isin(slot_keys, allowed, assume_unique=True).all(), \
        "a reference slot holds a triangle not below it"

    # Per-path limit: references met on the way to every cell.
    path_refs = np.bincount(slot_pt, minlength=len(leaves))
    if params.refs_per_path is not None:
        assert path_refs.max(initial=0) <= params.refs_per_path
    assert path_refs.max(initial=0) <= ct.stats["max_refs_on_path"]
    return path_refs


def _slot_owner(ct, slot_pt, path_pt, path_node, slot_tri):
    """The inner node whose slot each (point, triangle) reference came from."""
    nodes = ct.nodes
    w = nodes[path_node, 0].astype(np.int64)
    has_ref = (w >> 2) & 1
    pairs_pt, pairs_node = path_pt[has_ref == 1], path_node[has_ref == 1]
    slots = nodes[(w >> 5)[has_ref == 1]].astype(np.int64)
    out_pt, out_node, out_tri = [], [], []
    for s in (0, 1):
        ok = slots[:, s] != NO_TRIANGLE
        out_pt.append(pairs_pt[ok])
        out_node.append(pairs_node[ok])
        out_tri.append(slots[ok, s])
    # Same order as locate() emits slot references: level by level, slot 0 then 1. Rebuild the
    # owner by matching (point, triangle): a triangle appears once per path at most.
    key = np.concatenate(out_pt) * (1 << 32) + np.concatenate(out_tri)
    node = np.concatenate(out_node)
    order = np.argsort(key)
    want = slot_pt * (1 << 32) + slot_tri
    at = np.searchsorted(key[order], want)
    assert (key[order][at] == want).all()
    return node[order][at]


def path_node_pairs(path_pt, path_node, ref_point, ref_tri, T):
    """(compact inner node, triangle) for every standard reference and every inner node on the
    path to its cell."""
    order = np.argsort(ref_point, kind="stable")
    ref_point, ref_tri = ref_point[order], ref_tri[order]
    start = np.searchsorted(ref_point, np.arange(ref_point.max(initial=-1) + 2))
    per = start[1:] - start[:-1]
    pt = np.minimum(path_pt, len(per) - 1) if len(per) else path_pt
    n = per[pt] if len(per) else np.zeros(0, np.int64)
    pair_node = np.repeat(path_node, n)
    idx = np.repeat(start[pt], n) + np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
    return pair_node * T + ref_tri[idx]


# ---------------------------------------------------------------------------------------------
# Scenes, rays, fixtures

SCENES = {
    "sphere": lambda: uv_sphere(48, 24),
    "bunny": load_bunny,
    "architecture": lambda: architecture_scene(rooms=(3, 2), floors=2, seed=3),
}


def random_rays(corners, count, seed=0):
    """Half aimed at random points on random triangles, half in random directions; origins
    uniform in the scene box enlarged by 20 %."""
    rng = np.random.default_rng(seed)
    lo, hi = corners.reshape(-1, 3).min(0), corners.reshape(-1, 3).max(0)
    pad = 0.2 * (hi - lo)
    origins = rng.uniform(lo - pad, hi + pad, (count, 3))
    directions = rng.normal(size=(count, 3))
    aimed = np.arange(count) < count // 2
    tri = rng.integers(0, len(corners), aimed.sum())
    w = rng.dirichlet(np.ones(3), aimed.sum())
    target = np.einsum("tk,tkd->td", w, corners[tri])
    directions[aimed] = target - origins[aimed]
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return origins, directions


@functools.lru_cache(maxsize=None)
def scene(name):
    vertices, triangles = SCENES[name]()
    tree = build_kdtree(vertices, triangles)
    corners = vertices.astype(np.float64)[triangles.astype(np.int64)]
    return vertices, triangles, corners, tree


@functools.lru_cache(maxsize=None)
def reference_hits(name, count=20_000):
    _, _, corners, _ = scene(name)
    origins, directions = random_rays(corners, count, seed=len(name))
    return origins, directions, brute_force(corners, origins, directions)


# ---------------------------------------------------------------------------------------------
# Tests

@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("name", list(SCENES))
def test_nearest_hit_matches_brute_force(name, mode):
    vertices, triangles, corners, tree = scene(name)
    ct = compact_tree(tree, len(triangles), mode)
    origins, directions, (bt, btri) = reference_hits(name)
    t, tri, _ = trace_compact(ct, corners, origins, directions)
    assert np.isfinite(bt).sum() > len(bt) // 3, "the rays should hit often"
    assert np.array_equal(tri, btri), f"{(tri != btri).sum()} rays found another triangle"
    assert np.array_equal(t, bt)


def test_invariants_find_a_slot_that_holds_a_triangle_not_below_it():
    """The oracle can fail: a reference slot given a triangle from elsewhere (its empty second
    slot filled, nothing lost) is found."""
    vertices, triangles, corners, tree = scene("bunny")
    ct = compact_tree(tree, len(triangles), "compressed")
    w = ct.nodes[:, 0].astype(np.int64)
    inner = np.flatnonzero(((w & 3) != LEAF_TAG) & ((w >> 2) & 1 == 1))
    slots = ct.nodes[(w >> 5)[inner]]
    one = inner[(slots[:, 1] == NO_TRIANGLE)][-1]           # a deep node with one slot used
    nodes = ct.nodes.copy()
    below = set(nodes[w[one] >> 5].tolist())
    nodes[w[one] >> 5, 1] = next(t for t in range(len(triangles)) if t not in below)
    ct.nodes = nodes
    with pytest.raises(AssertionError, match="not below it"):
        check_invariants(tree, ct, len(triangles))


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("name", list(SCENES))
def test_invariants(name, mode):
    vertices, triangles, corners, tree = scene(name)
    ct = compact_tree(tree, len(triangles), mode)
    check_invariants(tree, ct, len(triangles))
    stats = ct.stats
    if mode == "standard":
        assert ct.nbytes == tree.nbytes and len(ct.nodes) == len(tree.nodes)
        assert stats["inner_references"] == 0 and stats["leaves_16bit"] == 0
    else:
        assert stats["inner_references"] > 0 and stats["references_removed"] > 0
        assert ct.nbytes < tree.nbytes
    parts = ct.nbytes_by_part()
    assert parts["nodes"] + parts["leaf_indices"] == parts["total"] == ct.nbytes
    assert parts["inner_nodes"] + parts["tref_slots"] + parts["leaf_nodes"] == parts["nodes"]


def test_shadow_rays_stop_at_any_hit():
    vertices, triangles, corners, tree = scene("architecture")
    ct = compact_tree(tree, len(triangles), "compressed")
    origins, directions, (bt, _) = reference_hits("architecture")
    tmax = np.where(np.isfinite(bt), bt * 1.5, 10.0)
    t, tri, _ = trace_compact(ct, corners, origins, directions, tmax=tmax, any_hit=True)
    assert np.array_equal(np.isfinite(t), np.isfinite(bt) & (bt <= tmax))


@pytest.mark.parametrize("refs_per_path", [0, 1, 3])
def test_path_limit_respected(refs_per_path):
    vertices, triangles, corners, tree = scene("architecture")
    ct = compact_tree(tree, len(triangles), "compressed", refs_per_path=refs_per_path,
                      tau_occu=0.05, tau_freq=0.05)
    path_refs = check_invariants(tree, ct, len(triangles))
    assert path_refs.max(initial=0) <= refs_per_path


def test_tight_thresholds_lift_more():
    vertices, triangles, corners, tree = scene("architecture")
    loose = compact_tree(tree, len(triangles), "compressed", tau_occu=0.2, tau_freq=0.2)
    strict = compact_tree(tree, len(triangles), "compressed", tau_occu=2.0, tau_freq=0.9)
    assert loose.stats["inner_references"] > strict.stats["inner_references"]


def test_16bit_leaves_round_trip():
    # More than 65,536 triangles: the base of a 16-bit list matters (leaf_shift > 0).
    vertices, triangles = architecture_scene(rooms=(6, 4), floors=3, seed=1)
    tree = build_kdtree(vertices, triangles)
    ct = compact_tree(tree, len(triangles), "compressed")
    assert len(triangles) > 65536 and ct.leaf_shift > 0
    assert ct.stats["leaves_16bit"] > 0
    check_invariants(tree, ct, len(triangles))


def test_geometry_bytes():
    assert geometry_nbytes(10, 4)["triangles"] == 4 * 3 * 2
    assert geometry_nbytes(70000, 4, material_count=3) == {
        "vertices": 840000, "triangles": 48, "material_ids": 8, "total": 840056}


def test_params_validation():
    with pytest.raises(ValueError):
        compact_params("fancy")
    with pytest.raises(ValueError):
        compact_params("compressed", refs_per_node=3)
    assert compact_params("choi").refs_per_path is None
    assert compact_params("compressed").refs_per_path == 8


def naive_candidates(tree, params):
    """(depth, node, triangle, references, first, end) of every lift candidate, node by node from
    the definitions (docs/kdtree_compression.md): the references of t in the node's subtree, no
    candidate above the inner node where all of t's references have met."""
    topo = Topology(tree)
    ref_leaf, ref_tri = topo.leaf_references(tree)
    order = np.lexsort((topo.pre[ref_leaf], ref_tri))
    leaf, tri, pre = ref_leaf[order], ref_tri[order], topo.pre[ref_leaf[order]]
    r_total = np.bincount(tri)
    nonempty = (topo.is_leaf & (topo.field > 0)).astype(np.int64)
    found = set()
    for n in np.flatnonzero(~topo.is_leaf):
        inside = np.flatnonzero((pre >= topo.pre[n]) & (pre < topo.pre_end[n]))
        ne = nonempty[(topo.pre >= topo.pre[n]) & (topo.pre < topo.pre_end[n])].sum()
        for t in np.unique(tri[inside]):
            run = inside[tri[inside] == t]
            r = len(run)
            below = [c for c in (topo.field[n], topo.field[n] + 1) if not topo.is_leaf[c]
                     and ((pre[run] >= topo.pre[c]) & (pre[run] < topo.pre_end[c])).all()]
            if r == r_total[t] and below:
                continue                      # all met in an inner node below n: dropped
            occupancy = np.add.reduceat(topo.area[leaf[run]], [0])[0] / topo.area[n]
            if (r >= params.min_refs and occupancy >= params.tau_occu
                    and r / max(ne, 1) >= params.tau_freq):
                found.add((int(topo.depth[n]), int(n), int(t), r, int(run[0]), int(run[-1]) + 1))
    return found


def fast_candidates(tree, params):
    topo = Topology(tree)
    ref_leaf, ref_tri = topo.leaf_references(tree)
    order = np.lexsort((topo.pre[ref_leaf], ref_tri))
    s_leaf, s_tri = ref_leaf[order], ref_tri[order]
    gap_node, gap_depth = neighbour_lcas(topo, s_leaf, s_tri)
    per_depth = lift_candidates(topo, s_leaf, s_tri, gap_node, gap_depth, params)
    return {(d, *map(int, row)) for d, cand in enumerate(per_depth) if cand is not None
            for row in zip(*cand)}


@pytest.mark.parametrize("stretched", [False, True])
@pytest.mark.parametrize("thresholds", [(0.5, 0.4, 2), (0.1, 0.1, 1), (0.0, 0.0, 2)])
def test_lift_candidates_match_definition(thresholds, stretched):
    """The run-based candidate search (one LCA per neighbour pair, walks stopped at the first
    failure where cells grow going up) finds exactly the pairs of the definition, also where
    a split lies outside its cell (`stretched`: a child then has a larger area than its
    parent, so a walk may not stop at a failure)."""
    vertices, triangles = uv_sphere(12, 16)
    tree = build_kdtree(vertices, triangles)
    if stretched:
        nodes = tree.nodes.copy()
        inner = np.flatnonzero((nodes[:, 0] & 3) != LEAF_TAG)[1::7]
        split = nodes[inner, 1].view(np.float32)
        nodes[inner, 1] = (split + np.float32(3) * np.sign(split)).view(np.uint32)
        tree = KDTree(nodes, tree.leaf_indices, tree.bounds)
    tau_occu, tau_freq, min_refs = thresholds
    params = compact_params("compressed", tau_occu=tau_occu, tau_freq=tau_freq, min_refs=min_refs)
    expected = naive_candidates(tree, params)
    assert expected
    assert fast_candidates(tree, params) == expected


def _general_standard(tree, triangle_count, monkeypatch):
    import kdtrace.core.accel.compact as kc
    with monkeypatch.context() as m:
        m.setattr(kc, "_standard_reencoded", lambda *args: None)
        return compact_tree(tree, triangle_count, "standard")


def _same_compact(a, b):
    for name in ("nodes", "leaf_index32", "leaf_index16", "bounds"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and np.array_equal(x, y), name
    assert a.leaf_shift == b.leaf_shift
    strip = lambda stats: {k: v for k, v in stats.items() if k != "compact_seconds"}
    assert strip(a.stats) == strip(b.stats)


@pytest.mark.parametrize("name", list(SCENES))
def test_standard_reencoding_equals_the_general_layout(name, monkeypatch):
    # Mode standard re-encodes a builder-ordered tree's words directly (_standard_reencoded);
    # it must give exactly what the general decode-and-lay-out path gives.
    import kdtrace.core.accel.compact as kc
    _, triangles, _, tree = scene(name)
    assert kc._standard_reencoded(tree, len(triangles), compact_params("standard")) is not None
    _same_compact(compact_tree(tree, len(triangles), "standard"),
                  _general_standard(tree, len(triangles), monkeypatch))


def test_standard_reencoding_falls_back_for_other_orders(monkeypatch):
    import kdtrace.core.accel.compact as kc
    # Root with two leaves: an empty one first, then one whose list is not ascending.
    tree = KDTree(np.array([[0 | (1 << 2), np.float32(0.5).view(np.uint32)],
                            [LEAF_TAG, 7], [LEAF_TAG | (2 << 2), 0]], np.uint32),
                  np.array([3, 1], np.uint32), np.array([[0, 0, 0], [1, 1, 1]], np.float32))
    params = compact_params("standard")
    assert kc._standard_reencoded(tree, 4, params) is None
    _same_compact(compact_tree(tree, 4, "standard"), _general_standard(tree, 4, monkeypatch))
    ascending = KDTree(tree.nodes, np.array([1, 3], np.uint32), tree.bounds)
    assert kc._standard_reencoded(ascending, 4, params) is not None
    _same_compact(compact_tree(ascending, 4, "standard"),
                  _general_standard(ascending, 4, monkeypatch))
    # Children not at 1 + 2k (a tree laid out in another order) also fall back.
    _, triangles, _, built = scene("sphere")
    inner = np.flatnonzero((built.nodes[:, 0] & 3) != LEAF_TAG)
    assert len(inner) > 2
    assert kc._standard_reencoded(KDTree(built.nodes[::-1].copy(), built.leaf_indices,
                                         built.bounds), len(triangles), params) is None


def test_distinct_count_is_the_number_of_unique_values():
    # The compact tree's "lifted_triangles" stat.
    rng = np.random.default_rng(7)
    for values in (rng.integers(0, 1000, 5000), rng.integers(0, 10, 3), np.zeros(0, np.int64),
                   np.array([0]), np.array([5, 5, 5], np.uint32)):
        assert distinct_count(values) == len(np.unique(values))
