"""SAH kd-tree over triangles, built breadth-first with vectorised numpy: the oracle the kernel
builder (core/accel/binned.py) is tested against, and the builder of a master without OpenCL.

The tree follows Wald & Havran 2006 (SAH cost, automatic termination, perfect splits) and is stored
in Wald's 8-byte node layout described in docs/architecture.md. docs/kdtree.md describes the
algorithm.

The build keeps one flat list of *references* (triangle id, node, clipped float32 box) sorted by
node, each one row of 7 float32 words (box, then the triangle id's int32 bits), and processes a
whole level of the tree at a time: every step below is a numpy operation over all references or
all nodes of the level, never a Python loop per node or per triangle. The level's steps live
here; the split search in core/accel/sah_splits.py, the clipping of straddling references in
core/accel/clipping.py, the reference rows in core/accel/ref_rows.py.

Zero-area triangles (exactly zero cross product in float64) are dropped: a watertight ray test
never reports a hit on them, and their clipped pieces would all look like zero-area contacts.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..layout import LEAF_TAG, PLAIN_FIELD     # the node format: core/layout.py PLAIN_NODE
from .arrays import exclusive_cumsum
from .clipping import clip_straddlers, round_down_f32, round_up_f32
from .ref_rows import BOX_ROW, REF_WORDS, gather_refs, ref_triangles
from .sah_splits import best_splits, no_decisions, sah_split_cost, surface_area

MAX_NODE_FIELD = PLAIN_FIELD.max    # word 0 bits 2-31: child index or leaf reference count


@dataclass(frozen=True)
class KDTreeParams:
    """Tunables of the build. The cost model and its constants are Wald & Havran 2006's (K_T
    15, K_I 20, lambda 0.8; pbrt's kd-tree prices differently: traversal 1, intersection 80,
    empty bonus 0.5); the depth cap and the allowance of bad refines follow pbrt
    (docs/kdtree.md)."""

    traversal_cost: float = 15.0      # K_T: cost of visiting an inner node
    intersection_cost: float = 20.0   # K_I: cost of one ray/triangle test
    empty_bonus: float = 0.8          # lambda: cost factor when a split leaves one side empty
    max_bins: int = 32                # SAH bins per axis for big nodes
    min_bins: int = 4                 # bins per axis for the smallest nodes
    bins_per_reference: float = 2.0   # small nodes get this many bins per reference (clamped)
    max_bad_refines: int = 3          # as pbrt: a leaf once a path has refined badly this often
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
# The build

def root_bounds(boxes_lo, boxes_hi, vertices):
    """The root cell (2, 3) float32: the boxes' bounds (the vertices' when there are none),
    flat axes padded, rounded outward to float32; both builders take it from here."""
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
    return np.stack([round_down_f32(lo), round_up_f32(hi)]).astype(np.float32)


@dataclass
class _Frontier:
    """The nodes of one level, not yet decided, with their references (rows sorted by node)
    and their paths' bad-refine counts."""

    cell_lo: np.ndarray        # (n, 3) float32
    cell_hi: np.ndarray
    counts: np.ndarray         # (n,) int64 references per node
    bad_refines: np.ndarray    # (n,) int64
    refs: np.ndarray           # (R, REF_WORDS) float32

    def __len__(self) -> int:
        return len(self.counts)



@dataclass
class _Level:
    """One level's nodes as decided: their words with the fields that depend on the nodes
    before them left at zero (an inner node's child index, a leaf's offset into
    leaf_indices), which nodes are leaves, the leaves' triangle ids and the level's share
    of the SAH cost."""

    words: np.ndarray          # (n, 2) uint32
    make_leaf: np.ndarray      # (n,) bool
    leaf_triangles: np.ndarray  # uint32
    sah_cost: float



@dataclass(frozen=True)
class _BuildContext:
    params: KDTreeParams
    depth_cap: int
    corners: np.ndarray        # (T, 3, 3) float32 triangle corners, for clipping
    root_area: float


def _step(fr: _Frontier, level: int, ctx: _BuildContext):
    """Decide every node of one level: (_Level, the next level's frontier or None)."""
    params = ctx.params
    cell_lo, cell_hi, counts, refs = fr.cell_lo, fr.cell_hi, fr.counts, fr.refs
    node_count = len(counts)
    ref_start = exclusive_cumsum(counts)
    dims = cell_hi.astype(np.float64) - cell_lo
    area = surface_area(dims)

    # 1. Best split of every non-empty node that may still split.
    cost, axis, plane = no_decisions(node_count)
    if level < ctx.depth_cap:
        cand = np.flatnonzero(counts > 0)
        if len(cand):
            cost[cand], axis[cand], plane[cand] = best_splits(
                params, cell_lo[cand], cell_hi[cand], counts[cand], ref_start[cand], refs)
    has_plane = np.isfinite(cost)

    # 2. Exact counts at the chosen planes (references of nodes with a plane only); planar
    #    references go to the cheaper side.
    n_below = np.zeros(node_count, np.int64)
    n_above = np.zeros(node_count, np.int64)
    n_planar = np.zeros(node_count, np.int64)
    ref_has_plane = np.repeat(has_plane, counts)
    cand = np.flatnonzero(has_plane)          # all non-empty
    sel = np.flatnonzero(ref_has_plane)
    sel_counts = counts[cand]
    sel_starts = exclusive_cumsum(sel_counts)[:-1]
    flat_index = REF_WORDS * sel + np.repeat(axis[cand], sel_counts)
    ref_plane = np.repeat(plane[cand], sel_counts)
    lo_on_axis = refs.reshape(-1)[flat_index]
    flat_index += 3
    hi_on_axis = refs.reshape(-1)[flat_index]
    del flat_index
    below = lo_on_axis < ref_plane
    above = hi_on_axis > ref_plane
    planar = (lo_on_axis == ref_plane) & (hi_on_axis == ref_plane)
    del lo_on_axis, hi_on_axis, ref_plane
    if len(cand):
        n_below[cand] = np.add.reduceat(below, sel_starts, dtype=np.int64)
        n_above[cand] = np.add.reduceat(above, sel_starts, dtype=np.int64)
        n_planar[cand] = np.add.reduceat(planar, sel_starts, dtype=np.int64)
    # Split costs only where there is a plane (empty nodes and the last level have none).
    planar_below = np.ones(node_count, bool)
    split_cost = np.full(node_count, np.inf)
    if len(cand):
        c_axis = axis[cand]
        width_below = plane[cand].astype(np.float64) - cell_lo[cand, c_axis]
        c_area = area[cand]
        safe_area = np.where(c_area > 0, c_area, 1.0)
        c_dims, c_below, c_above = dims[cand], n_below[cand], n_above[cand]
        c_planar = n_planar[cand]
        cost_planar_below = sah_split_cost(params, c_dims, safe_area, c_axis, width_below,
                                           c_below + c_planar, c_above)
        cost_planar_above = sah_split_cost(params, c_dims, safe_area, c_axis, width_below,
                                           c_below, c_above + c_planar)
        planar_below[cand] = cost_planar_below <= cost_planar_above
        split_cost[cand] = np.minimum(cost_planar_below, cost_planar_above)

    # 3. Leaf or split: automatic termination with pbrt's allowance of bad refines.
    leaf_cost = params.intersection_cost * counts
    bad = split_cost >= leaf_cost
    bad_refines = fr.bad_refines + bad
    # Unlike pbrt, a small node never refines badly: that only deepened the tree (docs/kdtree.md).
    make_leaf = ~has_plane | (bad & ((bad_refines >= params.max_bad_refines)
                                     | (counts < params.small_node)))
    split = ~make_leaf
    split_count = int(split.sum())

    # 4. This level's nodes (child indices and leaf offsets are added by `_write_nodes`).
    if int(counts.max(initial=0)) > MAX_NODE_FIELD:
        raise ValueError("kd-tree leaf too large for the 30-bit reference count")
    words = np.zeros((node_count, 2), np.uint32)
    words[:, 0] = np.where(make_leaf, LEAF_TAG | PLAIN_FIELD.put(counts), axis)
    words[:, 1] = np.where(make_leaf, 0, plane.view(np.uint32))
    leaf_triangles = ref_triangles(refs)[np.repeat(make_leaf, counts)].astype(np.uint32)
    leaf_area = area[make_leaf] / ctx.root_area
    sah_cost = (params.traversal_cost * area[split].sum() / ctx.root_area
                + params.intersection_cost * (leaf_area * counts[make_leaf]).sum())
    decided = _Level(words, make_leaf, leaf_triangles, float(sah_cost))
    if not split_count:
        return decided, None

    # 5. Send the references of split nodes (a subset of `sel`) to the children; clip those
    #    that straddle the plane.
    split_nodes = np.flatnonzero(split)
    in_split = split[cand]                                  # per node of `cand`
    sel_split = np.repeat(in_split, sel_counts)
    src = sel[sel_split]                                    # reference ids, by node
    below, above, planar = below[sel_split], above[sel_split], planar[sel_split]
    split_counts = counts[split_nodes]
    planar_side_below = np.repeat(planar_below[split_nodes], split_counts)
    goes_below = (below & ~planar) | (planar & planar_side_below)
    goes_above = (above & ~planar) | (planar & ~planar_side_below)
    del below, above, planar, planar_side_below
    straddles = np.flatnonzero(goes_below & goes_above)     # positions in src
    if len(straddles):
        s_node = np.repeat(split_nodes, split_counts)[straddles]
        (b_lo, b_hi, b_ok), (a_lo, a_hi, a_ok) = clip_straddlers(
            ctx.corners[ref_triangles(refs)[src[straddles]]].astype(np.float64),
            cell_lo[s_node], cell_hi[s_node], axis[s_node], plane[s_node])
        goes_below[straddles] = b_ok
        goes_above[straddles] = a_ok

    # Children in parent order, each parent's below child first: node j's children are
    # 2 rank(j) and 2 rank(j) + 1. References keep their order within a child.
    seg = exclusive_cumsum(split_counts)[:-1]
    n_child_below = np.add.reduceat(goes_below, seg, dtype=np.int64)
    n_child_above = np.add.reduceat(goes_above, seg, dtype=np.int64)
    child_counts = np.stack([n_child_below, n_child_above], 1).reshape(-1)
    child_start = exclusive_cumsum(child_counts)
    total = int(child_start[-1])
    new_src = np.empty(total, np.int64)
    at_straddler = []
    for side, goes, n_child in ((0, goes_below, n_child_below), (1, goes_above, n_child_above)):
        pos_in_src = np.flatnonzero(goes)
        shift = child_start[0::2][:-1] if side == 0 else child_start[1::2]
        shift = shift - exclusive_cumsum(n_child)[:-1]
        where = np.arange(len(pos_in_src)) + np.repeat(shift, n_child)
        new_src[where] = src[pos_in_src]
        if len(straddles):
            ok = (b_ok, a_ok)[side]
            at_straddler.append(where[(np.cumsum(goes) - 1)[straddles[ok]]])
    new_refs = gather_refs(refs, new_src)
    if len(straddles):
        # Straddlers get their clipped box on each side they go to (the 6 box words of
        # a row written as one 24-byte item).
        box_items = new_refs[:, 0:6].view(BOX_ROW)[:, 0]
        for at, lo_s, hi_s, ok in ((at_straddler[0], b_lo, b_hi, b_ok),
                                   (at_straddler[1], a_lo, a_hi, a_ok)):
            box = np.concatenate([lo_s, hi_s], 1)
            box_items[at] = box.view(BOX_ROW)[:, 0][ok]
    del new_src

    # 6. Children's cells and bad-refine counts.
    child_lo = np.repeat(cell_lo[split_nodes], 2, 0)
    child_hi = np.repeat(cell_hi[split_nodes], 2, 0)
    child_axis = np.repeat(axis[split_nodes], 2)
    child_plane = np.repeat(plane[split_nodes], 2)
    rows = np.arange(2 * split_count)
    child_hi[rows[0::2], child_axis[0::2]] = child_plane[0::2]
    child_lo[rows[1::2], child_axis[1::2]] = child_plane[1::2]
    return decided, _Frontier(child_lo, child_hi, child_counts,
                              np.repeat(bad_refines[split_nodes], 2), new_refs)


def _write_nodes(levels: list) -> tuple:
    """Nodes breadth-first, level after level, and the leaves' triangle lists: fills in the
    child index of every inner node and the leaf_indices offset of every leaf."""
    level_base = leaf_total = 0
    for decided in levels:
        words, make_leaf = decided.words, decided.make_leaf
        split_rank = np.cumsum(~make_leaf) - 1
        first_child = level_base + len(words) + 2 * split_rank
        if (~make_leaf).any() and first_child.max() > MAX_NODE_FIELD:
            raise ValueError("kd-tree too large for the 30-bit child index")
        leaf_counts = np.where(make_leaf, PLAIN_FIELD.get(words[:, 0]), 0).astype(np.int64)
        leaf_offset = leaf_total + exclusive_cumsum(leaf_counts)[:-1]
        words[:, 0] |= np.where(make_leaf, 0, PLAIN_FIELD.put(first_child)).astype(np.uint32)
        words[:, 1] |= np.where(make_leaf, leaf_offset, 0).astype(np.uint32)
        level_base += len(words)
        leaf_total += int(leaf_counts.sum())
    nodes = np.concatenate([d.words for d in levels])
    leaf_indices = np.concatenate([d.leaf_triangles for d in levels]).astype(np.uint32)
    return nodes, leaf_indices


def checked_mesh(vertices, triangles):
    """float32 (V, 3) vertices and (T, 3) triangles, or ValueError for indices out of range
    or non-finite coordinates (both builders, core/accel/binned.py too)."""
    vertices = np.ascontiguousarray(vertices, np.float32).reshape(-1, 3)
    triangles = np.asarray(triangles).reshape(-1, 3)
    if len(triangles) and (triangles.min() < 0 or triangles.max() >= len(vertices)):
        raise ValueError("a triangle refers to a vertex that does not exist")
    if not np.isfinite(vertices).all():
        raise ValueError("vertex coordinates contain NaN or infinity")
    return vertices, triangles


def build_kdtree(vertices, triangles, params: KDTreeParams | None = None, progress=None) -> KDTree:
    """Build an SAH kd-tree with perfect splits over triangles (see module docstring).

    `progress(fraction, message)`, if given, is called once per level (once per level of
    each part in the parallel phase), always on the calling thread; an exception it raises
    stops the build.
    """
    params = params or KDTreeParams()
    started = time.perf_counter()
    vertices, triangles = checked_mesh(vertices, triangles)
    triangles = triangles.astype(np.int64)
    triangle_count = len(triangles)

    corners = vertices[triangles]                                     # (T, 3, 3) float32
    c64 = corners.astype(np.float64)
    normal = np.cross(c64[:, 1] - c64[:, 0], c64[:, 2] - c64[:, 0])
    kept = np.flatnonzero((normal != 0).any(1))                        # drop zero-area triangles
    del normal, c64

    refs = np.empty((len(kept), REF_WORDS), np.float32)
    refs[:, 0:3] = corners[kept].min(1)                               # exact: corners are float32
    refs[:, 3:6] = corners[kept].max(1)
    refs[:, 6].view(np.int32)[:] = kept
    bounds = root_bounds(refs[:, 0:3], refs[:, 3:6], vertices)

    ctx = _BuildContext(params, params.depth_cap(triangle_count), corners,
                        float(surface_area(bounds[1].astype(np.float64) - bounds[0])))
    root = _Frontier(bounds[:1].copy(), bounds[1:].copy(), np.array([len(kept)], np.int64),
                     np.zeros(1, np.int64), refs)
    del refs

    levels, frontier, level = [], root, 0
    while frontier is not None:
        if progress is not None:
            progress(min(level / (ctx.depth_cap + 1), 1.0),
                     f"kd-tree level {level}: {len(frontier)} nodes, "
                     f"{len(frontier.refs)} references")
        decided, frontier = _step(frontier, level, ctx)
        levels.append(decided)
        level += 1
    nodes, leaf_indices = _write_nodes(levels)
    leaf_levels = [k for k, d in enumerate(levels) if d.make_leaf.any()]
    tree = KDTree(nodes, leaf_indices, bounds)
    tree.stats = {
        "nodes": len(nodes),
        "leaves": sum(int(d.make_leaf.sum()) for d in levels),
        "empty_leaves": sum(int((d.make_leaf & (d.words[:, 0] == LEAF_TAG)).sum())
                            for d in levels),
        "depth": max(leaf_levels, default=0),
        "depth_cap": ctx.depth_cap,
        "references": len(leaf_indices),
        "refs_per_triangle": len(leaf_indices) / max(len(kept), 1),
        "dropped_degenerate": triangle_count - len(kept),
        "bytes": tree.nbytes,
        "sah_cost": float(sum(d.sah_cost for d in levels)),
        "build_seconds": time.perf_counter() - started,
        "threads": 1,
    }
    if progress is not None:
        progress(1.0, f"kd-tree done: {len(nodes)} nodes, {len(leaf_indices)} references")
    return tree
