"""SAH kd-tree over triangles, built breadth-first with vectorised numpy.

The tree follows Wald & Havran 2006 (SAH cost, automatic termination, perfect splits) and is stored
in Wald's 8-byte node layout described in docs/architecture.md. docs/kdtree.md describes the
algorithm and its measured numbers.

The build keeps one flat list of *references* (triangle id, node, clipped float32 box) sorted by
node, and processes a whole level of the tree at a time: every step below is a numpy operation
over all references or all nodes of the level, never a Python loop per node or per triangle.

Zero-area triangles (exactly zero cross product in float64) are dropped: a watertight ray test
never reports a hit on them, and their clipped pieces would all look like zero-area contacts.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

LEAF_TAG = 3                 # word 0, bits 0-1, of a leaf
MAX_NODE_FIELD = (1 << 30) - 1  # bits 2-31 of word 0: child index or leaf reference count


@dataclass(frozen=True)
class KDTreeParams:
    """Tunables of the build; defaults follow Wald & Havran 2006 and pbrt."""

    traversal_cost: float = 15.0      # K_T: cost of visiting an inner node
    intersection_cost: float = 20.0   # K_I: cost of one ray/triangle test
    empty_bonus: float = 0.8          # lambda: cost factor when a split leaves one side empty
    max_bins: int = 32                # SAH bins per axis for big nodes
    min_bins: int = 4                 # bins per axis for the smallest nodes
    bins_per_reference: float = 2.0   # small nodes get this many bins per reference (clamped)
    max_bad_refines: int = 3          # pbrt: give up after this many splits costlier than a leaf
    small_node: int = 16              # nodes with fewer references never refine badly
    max_depth: int | None = None      # None: 8 + 1.3 log2(triangle count), rounded

    def depth_cap(self, triangle_count: int) -> int:
        if self.max_depth is not None:
            return int(self.max_depth)
        return int(round(8 + 1.3 * math.log2(max(triangle_count, 1))))


@dataclass
class KDTree:
    nodes: np.ndarray          # uint32 (N, 2), see docs/architecture.md
    leaf_indices: np.ndarray   # uint32, each leaf's triangle list contiguous
    bounds: np.ndarray         # float32 (2, 3): box of the root cell
    stats: dict = field(default_factory=dict)

    @property
    def nbytes(self) -> int:
        return int(self.nodes.nbytes + self.leaf_indices.nbytes)


# ---------------------------------------------------------------------------------------------
# Small numeric helpers

def _round_down_f32(x: np.ndarray) -> np.ndarray:
    """The largest float32 <= x (x float64)."""
    f = x.astype(np.float32)
    return np.where(f.astype(np.float64) > x, np.nextafter(f, np.float32(-np.inf)), f)


def _round_up_f32(x: np.ndarray) -> np.ndarray:
    """The smallest float32 >= x (x float64)."""
    f = x.astype(np.float32)
    return np.where(f.astype(np.float64) < x, np.nextafter(f, np.float32(np.inf)), f)


def _exclusive_cumsum(counts: np.ndarray) -> np.ndarray:
    out = np.zeros(len(counts) + 1, np.int64)
    np.cumsum(counts, out=out[1:])
    return out


def _surface_area(dims: np.ndarray) -> np.ndarray:
    return 2.0 * (dims[..., 0] * dims[..., 1] + dims[..., 1] * dims[..., 2]
                  + dims[..., 2] * dims[..., 0])


def _split_cost(params: KDTreeParams, dims, area, axis, below_width, count_below, count_above):
    """SAH cost of splitting cells (dims, area) on `axis` at `below_width` from their low side."""
    if np.ndim(axis) == 0:
        side_a, side_b = dims[:, (axis + 1) % 3], dims[:, (axis + 2) % 3]
        width = dims[:, axis]
    else:                                           # one axis per cell
        rows = np.arange(len(dims))
        side_a, side_b = dims[rows, (axis + 1) % 3], dims[rows, (axis + 2) % 3]
        width = dims[rows, axis]
    above_width = width - below_width
    area_below = 2.0 * (below_width * (side_a + side_b) + side_a * side_b)
    area_above = 2.0 * (above_width * (side_a + side_b) + side_a * side_b)
    cost = params.traversal_cost + params.intersection_cost * (
        area_below * count_below + area_above * count_above) / area
    return np.where((count_below == 0) | (count_above == 0), cost * params.empty_bonus, cost)


def _segment_argmin(values: np.ndarray, starts: np.ndarray):
    """Minimum and index of its first occurrence within each segment [starts[i], starts[i+1])."""
    seg_min = np.minimum.reduceat(values, starts)
    segment_of = np.repeat(np.arange(len(starts)), np.diff(np.append(starts, len(values))))
    index = np.where(values == seg_min[segment_of], np.arange(len(values)), len(values))
    return seg_min, np.minimum.reduceat(index, starts)


# ---------------------------------------------------------------------------------------------
# Clipping triangles to boxes (Sutherland-Hodgman on padded polygon arrays)

def _clip_polygons(poly, count, axis, value, keep_below):
    """Clip convex polygons to the half-space x[axis] <= value (keep_below) or >= value.

    poly (K, W, 3) float64 holds `count` vertices per row. Returns new (poly, count); the new
    width is just enough for the result (a plane adds at most one vertex to a convex polygon).
    Rows with no vertex outside come back unchanged; a vertex on the plane counts as inside.
    """
    K, W, _ = poly.shape
    rows = np.arange(K)[:, None]
    slots = np.arange(W)[None, :]
    coord = poly[rows, slots, axis[:, None]]
    dist = value[:, None] - coord if keep_below else coord - value[:, None]
    valid = slots < count[:, None]
    needs_clip = (valid & (dist < 0)).any(1)
    if not needs_clip.any():
        return poly, count
    sub = np.flatnonzero(needs_clip)
    p, d, v, c = poly[sub], dist[sub], valid[sub], count[sub]
    nxt = np.where(slots + 1 < c[:, None], slots + 1, 0)
    d_next = np.take_along_axis(d, nxt, 1)
    inside = v & (d >= 0)
    crossing = v & (((d > 0) & (d_next < 0)) | ((d < 0) & (d_next > 0)))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(crossing, d / (d - d_next), 0.0)
    p_next = np.take_along_axis(p, nxt[..., None], 1)
    crossing_point = p + t[..., None] * (p_next - p)
    # Snap onto the plane so that pieces meet the child's face exactly.
    crossing_point[np.arange(len(sub))[:, None], slots, axis[sub][:, None]] = value[sub][:, None]
    candidates = np.stack([p, crossing_point], 2).reshape(len(sub), 2 * W, 3)
    keep = np.stack([inside, crossing], 2).reshape(len(sub), 2 * W)
    new_count = keep.sum(1)
    new_width = max(W, int(new_count.max()))
    out = np.zeros((len(sub), new_width, 3))
    r, col = np.nonzero(keep)
    out[r, (np.cumsum(keep, 1) - 1)[r, col]] = candidates[r, col]
    if new_width > W:
        poly = np.concatenate([poly, np.zeros((K, new_width - W, 3))], 1)
    else:
        poly = poly.copy()
    count = count.copy()
    poly[sub] = out
    count[sub] = new_count
    return poly, count


def _piece_boxes(poly, count, triangle_flat):
    """float64 box of each clipped piece and whether the piece has positive area.

    A piece of a non-degenerate triangle has zero area exactly when it only touches the box: it
    is then empty, a point or a segment, or it lies flat in a box face plane that the triangle
    itself does not lie in (flat in an axis where the triangle is not).
    """
    valid = (np.arange(poly.shape[1])[None, :] < count[:, None])[..., None]
    lo = np.where(valid, poly, np.inf).min(1)
    hi = np.where(valid, poly, -np.inf).max(1)
    flat = (hi - lo) == 0
    positive = (count >= 3) & ~(flat & ~triangle_flat).any(1)
    return lo, hi, positive


def _clip_straddlers(corners, cell_lo, cell_hi, axis, plane):
    """Perfect split of references that straddle their node's split plane.

    Each triangle is clipped in float64 to its node's cell, then cut by the plane; each half's
    box is rounded outward to float32 and clamped to the child's cell. Returns both halves'
    boxes and whether each half has positive area (a zero-area half is dropped by the caller).
    """
    K = len(corners)
    poly, count = corners.copy(), np.full(K, 3)
    lo64, hi64 = cell_lo.astype(np.float64), cell_hi.astype(np.float64)
    for a in range(3):
        axis_a = np.full(K, a)
        poly, count = _clip_polygons(poly, count, axis_a, lo64[:, a], keep_below=False)
        poly, count = _clip_polygons(poly, count, axis_a, hi64[:, a], keep_below=True)
    triangle_flat = corners.max(1) == corners.min(1)
    plane64 = plane.astype(np.float64)
    halves = []
    for keep_below in (True, False):
        piece, piece_count = _clip_polygons(poly, count, axis, plane64, keep_below)
        lo, hi, positive = _piece_boxes(piece, piece_count, triangle_flat)
        child_lo, child_hi = cell_lo.copy(), cell_hi.copy()
        (child_hi if keep_below else child_lo)[np.arange(K), axis] = plane
        lo32 = np.maximum(_round_down_f32(np.where(positive[:, None], lo, 0.0)), child_lo)
        hi32 = np.minimum(_round_up_f32(np.where(positive[:, None], hi, 0.0)), child_hi)
        halves.append((lo32, hi32, positive))
    return halves


# ---------------------------------------------------------------------------------------------
# Choosing splits

def _binned_best_splits(params, cell_lo, cell_hi, counts, ref_node, ref_lo, ref_hi):
    """Best SAH split of each node from binned counts, plus the exact empty-space cuts.

    All arrays cover only nodes with at least one reference; ref_* are sorted by node. Each node
    gets its own bin count (bins_per_reference * N clamped to [min_bins, max_bins]) laid out in
    one flat array, so that every node's sweep is a segment of one cumsum.
    Returns (cost, axis, plane float32); cost is inf where no plane lies strictly inside.
    """
    node_count = len(counts)
    dims = (cell_hi.astype(np.float64) - cell_lo)
    area = _surface_area(dims)
    bins = np.clip(np.round(params.bins_per_reference * counts), params.min_bins,
                   params.max_bins).astype(np.int64)
    bin_start = _exclusive_cumsum(bins)
    total_bins = int(bin_start[-1])
    bin_start = bin_start[:-1]
    bin_node = np.repeat(np.arange(node_count), bins)
    bin_local = np.arange(total_bins) - bin_start[bin_node]
    ref_start = _exclusive_cumsum(counts)[:-1]

    best_cost = np.full(node_count, np.inf)
    best_axis = np.zeros(node_count, np.int64)
    best_plane = np.zeros(node_count, np.float32)

    def consider(cost, axis, plane):
        better = cost < best_cost
        best_cost[better] = cost[better]
        best_axis[better] = axis
        best_plane[better] = plane[better]

    for axis in range(3):
        low = cell_lo[:, axis].astype(np.float64)
        width = dims[:, axis]
        scale = (bins / width)[ref_node]
        last_bin = (bins - 1)[ref_node]
        # A reference counts below plane k if its low end is below it, above if its high end is
        # above it: bin the low ends by floor and the high ends by ceil - 1.
        start_bin = np.clip(np.floor((ref_lo[:, axis] - low[ref_node]) * scale), 0, last_bin)
        end_bin = np.clip(np.ceil((ref_hi[:, axis] - low[ref_node]) * scale) - 1, 0, last_bin)
        starts = np.cumsum(np.bincount(bin_start[ref_node] + start_bin.astype(np.int64),
                                       minlength=total_bins))
        ends = np.cumsum(np.bincount(bin_start[ref_node] + end_bin.astype(np.int64),
                                     minlength=total_bins))
        starts_before = np.concatenate([[0], starts])[bin_start][bin_node]
        ends_before = np.concatenate([[0], ends])[bin_start][bin_node]
        count_below = starts - starts_before
        count_above = counts[bin_node] - (ends - ends_before)
        # Plane after bin k; the last bin of each node ends at the cell's high side.
        plane = (low[bin_node] + (bin_local + 1) * (width / bins)[bin_node]).astype(np.float32)
        inside = ((bin_local < bins[bin_node] - 1) & (plane > cell_lo[bin_node, axis])
                  & (plane < cell_hi[bin_node, axis]))
        cost = _split_cost(params, dims[bin_node], area[bin_node], axis,
                           plane.astype(np.float64) - low[bin_node], count_below, count_above)
        cost = np.where(inside, cost, np.inf)
        node_cost, index = _segment_argmin(cost, bin_start)
        consider(node_cost, axis, plane[index])

        # Exact cuts at the references' tight bounds: bins alone would leave empty slivers.
        for plane, below, above in (
                (np.minimum.reduceat(ref_lo[:, axis], ref_start), 0, counts),
                (np.maximum.reduceat(ref_hi[:, axis], ref_start), counts, 0)):
            inside = (plane > cell_lo[:, axis]) & (plane < cell_hi[:, axis])
            cost = _split_cost(params, dims, area, axis, plane.astype(np.float64) - low,
                               below, above)
            consider(np.where(inside, cost, np.inf), axis, plane)
    return best_cost, best_axis, best_plane


# ---------------------------------------------------------------------------------------------
# The build

def _root_bounds(boxes_lo, boxes_hi, vertices):
    if len(boxes_lo):
        lo, hi = boxes_lo.min(0).astype(np.float64), boxes_hi.max(0).astype(np.float64)
    elif len(vertices):
        lo, hi = vertices.min(0).astype(np.float64), vertices.max(0).astype(np.float64)
    else:
        lo, hi = np.zeros(3), np.zeros(3)
    # A scene flat in an axis would give cells of zero width there; pad such axes a little.
    extent = hi - lo
    pad = np.maximum(1e-4 * extent.max(), 1e-6 * np.maximum(np.abs(lo), np.abs(hi)))
    pad = np.maximum(pad, 1e-6)
    flat = extent <= 1e-6 * np.maximum(extent.max(), 0)
    lo = np.where(flat, lo - pad, lo)
    hi = np.where(flat, hi + pad, hi)
    return np.stack([_round_down_f32(lo), _round_up_f32(hi)]).astype(np.float32)


def build_kdtree(vertices, triangles, params: KDTreeParams | None = None, progress=None) -> KDTree:
    """Build an SAH kd-tree with perfect splits over triangles (see module docstring).

    `progress(fraction, message)`, if given, is called once per level.
    """
    params = params or KDTreeParams()
    started = time.perf_counter()
    vertices = np.ascontiguousarray(vertices, np.float32).reshape(-1, 3)
    triangles = np.asarray(triangles).reshape(-1, 3)
    if len(triangles) and (triangles.min() < 0 or triangles.max() >= len(vertices)):
        raise ValueError("a triangle refers to a vertex that does not exist")
    if not np.isfinite(vertices).all():
        raise ValueError("vertex coordinates contain NaN or infinity")
    triangles = triangles.astype(np.int64)
    triangle_count = len(triangles)

    corners = vertices[triangles].astype(np.float64)                  # (T, 3, 3)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    kept = np.flatnonzero((normal != 0).any(1))                        # drop zero-area triangles
    del normal

    ref_tri = kept.astype(np.int64)
    ref_lo = corners[kept].min(1).astype(np.float32)                 # exact: corners are float32
    ref_hi = corners[kept].max(1).astype(np.float32)
    bounds = _root_bounds(ref_lo, ref_hi, vertices)
    ref_node = np.zeros(len(kept), np.int64)

    depth_cap = params.depth_cap(triangle_count)
    root_area = float(_surface_area(bounds[1].astype(np.float64) - bounds[0]))
    cell_lo, cell_hi = bounds[:1].copy(), bounds[1:].copy()
    bad_refines = np.zeros(1, np.int64)

    level_words, leaf_lists = [], []
    leaf_total = 0
    level_base = 0
    level = 0
    sah_cost = 0.0
    leaf_count = empty_leaves = 0
    max_leaf_depth = 0
    while len(cell_lo):
        node_count = len(cell_lo)
        if progress is not None:
            progress(min(level / (depth_cap + 1), 1.0),
                     f"kd-tree level {level}: {node_count} nodes, {len(ref_tri)} references")
        counts = np.bincount(ref_node, minlength=node_count)
        ref_start = _exclusive_cumsum(counts)
        dims = cell_hi.astype(np.float64) - cell_lo
        area = _surface_area(dims)

        # 1. Best binned split of every node that may still split.
        cost = np.full(node_count, np.inf)
        axis = np.zeros(node_count, np.int64)
        plane = np.zeros(node_count, np.float32)
        if level < depth_cap:
            candidates = np.flatnonzero(counts > 0)
            if len(candidates):
                in_candidate = np.zeros(node_count, bool)
                in_candidate[candidates] = True
                ref_sel = in_candidate[ref_node]
                compact = np.cumsum(in_candidate) - 1
                c_cost, c_axis, c_plane = _binned_best_splits(
                    params, cell_lo[candidates], cell_hi[candidates], counts[candidates],
                    compact[ref_node[ref_sel]], ref_lo[ref_sel], ref_hi[ref_sel])
                cost[candidates], axis[candidates], plane[candidates] = c_cost, c_axis, c_plane
        has_plane = np.isfinite(cost)

        # 2. Exact counts at the chosen planes; planar references go to the cheaper side.
        ref_axis = axis[ref_node]
        ref_plane = plane[ref_node]
        lo_on_axis = np.take_along_axis(ref_lo, ref_axis[:, None], 1)[:, 0]
        hi_on_axis = np.take_along_axis(ref_hi, ref_axis[:, None], 1)[:, 0]
        planar = (lo_on_axis == ref_plane) & (hi_on_axis == ref_plane)
        below = lo_on_axis < ref_plane
        above = hi_on_axis > ref_plane
        n_below = np.bincount(ref_node, below, node_count)
        n_above = np.bincount(ref_node, above, node_count)
        n_planar = np.bincount(ref_node, planar, node_count)
        width_below = plane.astype(np.float64) - np.take_along_axis(cell_lo, axis[:, None], 1)[:, 0]
        safe_area = np.where(area > 0, area, 1.0)
        cost_planar_below = _split_cost(params, dims, safe_area, axis, width_below,
                                        n_below + n_planar, n_above)
        cost_planar_above = _split_cost(params, dims, safe_area, axis, width_below,
                                        n_below, n_above + n_planar)
        planar_below = cost_planar_below <= cost_planar_above
        split_cost = np.where(has_plane, np.minimum(cost_planar_below, cost_planar_above), np.inf)

        # 3. Leaf or split: automatic termination with pbrt's allowance of bad refines.
        leaf_cost = params.intersection_cost * counts
        bad = split_cost >= leaf_cost
        bad_refines = bad_refines + bad
        # Unlike pbrt, a small node never refines badly: that only deepened the tree (docs/kdtree.md).
        make_leaf = ~has_plane | (bad & ((bad_refines >= params.max_bad_refines)
                                         | (counts < params.small_node)))
        split = ~make_leaf
        split_rank = np.cumsum(split) - 1
        split_count = int(split.sum())

        # 4. Write this level's nodes: leaves point into leaf_indices, inner nodes at children.
        words = np.zeros((node_count, 2), np.uint32)
        leaf_offset = leaf_total + _exclusive_cumsum(np.where(make_leaf, counts, 0))[:-1]
        first_child = level_base + node_count + 2 * split_rank
        if split_count and first_child.max() > MAX_NODE_FIELD:
            raise ValueError("kd-tree too large for the 30-bit child index")
        words[:, 0] = np.where(make_leaf, LEAF_TAG | (counts << 2), axis | (first_child << 2))
        words[:, 1] = np.where(make_leaf, leaf_offset, plane.view(np.uint32))
        level_words.append(words)
        ref_in_leaf = make_leaf[ref_node]
        leaf_lists.append(ref_tri[ref_in_leaf])
        leaf_total += int(counts[make_leaf].sum())
        leaf_area = area[make_leaf] / root_area
        sah_cost += (params.traversal_cost * area[split].sum() / root_area
                     + params.intersection_cost * (leaf_area * counts[make_leaf]).sum())
        leaf_count += int(make_leaf.sum())
        empty_leaves += int((make_leaf & (counts == 0)).sum())
        if make_leaf.any():
            max_leaf_depth = level
        if not split_count:
            break

        # 5. Send references to the children; clip those that straddle the plane.
        ref_split = split[ref_node]
        planar_side_below = planar_below[ref_node]
        goes_below = ref_split & ((below & ~planar) | (planar & planar_side_below))
        goes_above = ref_split & ((above & ~planar) | (planar & ~planar_side_below))
        straddles = np.flatnonzero(goes_below & goes_above)
        below_lo, below_hi = ref_lo.copy(), ref_hi.copy()
        above_lo, above_hi = ref_lo, ref_hi
        if len(straddles):
            s_node = ref_node[straddles]
            (b_lo, b_hi, b_ok), (a_lo, a_hi, a_ok) = _clip_straddlers(
                corners[ref_tri[straddles]], cell_lo[s_node], cell_hi[s_node],
                axis[s_node], plane[s_node])
            goes_below[straddles] = b_ok
            goes_above[straddles] = a_ok
            below_lo[straddles], below_hi[straddles] = b_lo, b_hi
            above_lo, above_hi = ref_lo.copy(), ref_hi.copy()
            above_lo[straddles], above_hi[straddles] = a_lo, a_hi

        # Counting sort into child order: node j's children are 2 * rank(j) and 2 * rank(j) + 1.
        n_child_below = np.bincount(ref_node, goes_below, node_count).astype(np.int64)[split]
        n_child_above = np.bincount(ref_node, goes_above, node_count).astype(np.int64)[split]
        child_counts = np.stack([n_child_below, n_child_above], 1).reshape(-1)
        child_start = _exclusive_cumsum(child_counts)
        total = int(child_start[-1])
        new_tri = np.empty(total, np.int64)
        new_node = np.empty(total, np.int64)
        new_lo = np.empty((total, 3), np.float32)
        new_hi = np.empty((total, 3), np.float32)
        for side, goes, lo, hi in ((0, goes_below, below_lo, below_hi),
                                   (1, goes_above, above_lo, above_hi)):
            running = np.cumsum(goes) - goes                       # exclusive, over all refs
            rank_in_node = running - running[np.minimum(ref_start[:-1], len(running) - 1)][ref_node]
            sel = np.flatnonzero(goes)
            child = 2 * split_rank[ref_node[sel]] + side
            where = child_start[child] + rank_in_node[sel]
            new_tri[where] = ref_tri[sel]
            new_node[where] = child
            new_lo[where] = lo[sel]
            new_hi[where] = hi[sel]

        # 6. Children's cells and bad-refine counts.
        split_nodes = np.flatnonzero(split)
        child_lo = np.repeat(cell_lo[split_nodes], 2, 0)
        child_hi = np.repeat(cell_hi[split_nodes], 2, 0)
        child_axis = np.repeat(axis[split_nodes], 2)
        child_plane = np.repeat(plane[split_nodes], 2)
        rows = np.arange(2 * split_count)
        child_hi[rows[0::2], child_axis[0::2]] = child_plane[0::2]
        child_lo[rows[1::2], child_axis[1::2]] = child_plane[1::2]

        level_base += node_count
        cell_lo, cell_hi = child_lo, child_hi
        bad_refines = np.repeat(bad_refines[split_nodes], 2)
        ref_tri, ref_node, ref_lo, ref_hi = new_tri, new_node, new_lo, new_hi
        level += 1

    nodes = np.concatenate(level_words)
    leaf_indices = np.concatenate(leaf_lists).astype(np.uint32)
    tree = KDTree(nodes, leaf_indices, bounds)
    tree.stats = {
        "nodes": len(nodes),
        "leaves": leaf_count,
        "empty_leaves": empty_leaves,
        "depth": max_leaf_depth,
        "depth_cap": depth_cap,
        "references": len(leaf_indices),
        "refs_per_triangle": len(leaf_indices) / max(len(kept), 1),
        "dropped_degenerate": triangle_count - len(kept),
        "bytes": tree.nbytes,
        "sah_cost": float(sah_cost),
        "build_seconds": time.perf_counter() - started,
    }
    if progress is not None:
        progress(1.0, f"kd-tree done: {len(nodes)} nodes, {len(leaf_indices)} references")
    return tree
