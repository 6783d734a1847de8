"""The top level of an instanced scene: a small SAH BVH over the instances' world boxes, built
on the host with numpy (docs/instances.md). Deterministic: the same boxes give the same nodes
on every machine (float64 arithmetic, stable sorts, no threads).

Each node is a TOPLEVEL_NODE record (core/layout.py): its box, and either two children side by
side or a run of at most TOPLEVEL_LEAF_MAX instances in `order`. A split bins the node's
instances by box centre along each axis and takes the cut of least surface-area cost; below
a depth of TOPLEVEL_MAX_DEPTH - 24 the cut is the median, so the tree stays within
TOPLEVEL_MAX_DEPTH levels for any input within the instance limit (2^20: 20 median levels).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..layout import TOPLEVEL_LEAF_MAX, TOPLEVEL_MAX_DEPTH, TOPLEVEL_NODE

MEDIAN_DEPTH = TOPLEVEL_MAX_DEPTH - 24
# SAH constants (relative): a traversal step costs this much against one instance's test.
TRAVERSAL_COST = 0.5
BINS = 8                # per axis: 16 gave trees of slightly lower SAH cost at a longer build
                        # (docs/instances.md)


class TopLevel(NamedTuple):
    nodes: np.ndarray       # (N, TOPLEVEL_NODE.size, 4) float32 records
    order: np.ndarray       # (I,) int64: the instance of each leaf slot
    depth: int              # levels (root = 1)


def _half_area(lo, hi):
    e = np.maximum(hi - lo, 0.0)
    return e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]


def build_toplevel(lo: np.ndarray, hi: np.ndarray) -> TopLevel:
    """The BVH over world boxes lo/hi ((I, 3) each, I >= 1, lo <= hi), built a level at a
    time: every node of a level is split at once (binned SAH over box centres, BINS bins
    per axis; the median where the bins cannot part the centres, or below MEDIAN_DEPTH)."""
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    count = len(lo)
    centre = 0.5 * (lo + hi)
    order = np.arange(count)
    # Per node: box, first child or first instance, count (0 = inner); nodes of a level are
    # made together, a node's two children side by side (at most 2 I - 1 nodes).
    box_lo, box_hi = np.zeros((2 * count - 1, 3)), np.zeros((2 * count - 1, 3))
    first, leaf_count = np.zeros(2 * count - 1, np.int64), np.zeros(2 * count - 1, np.int64)
    starts = np.array([0])
    ends = np.array([count])
    ids = np.array([0])             # node index of each node of the level
    made = 1
    depth = 0
    while len(starts):
        depth += 1
        sizes = ends - starts
        # The level's instances, contiguous per node in `order`.
        item_node = np.repeat(np.arange(len(starts)), sizes)
        heads = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        places = np.repeat(starts - heads, sizes) + np.arange(len(item_node))
        items = order[places]
        nlo = np.minimum.reduceat(lo[items], heads)
        nhi = np.maximum.reduceat(hi[items], heads)
        clo = np.minimum.reduceat(centre[items], heads)
        chi = np.maximum.reduceat(centre[items], heads)
        # The best binned cut of each node over the three axes.
        best_cost = np.full(len(starts), np.inf)
        best_axis = np.zeros(len(starts), np.int64)
        best_cut = np.zeros(len(starts), np.int64)
        for axis in range(3):
            width = chi[:, axis] - clo[:, axis]
            scale = np.where(width > 0, BINS / np.where(width > 0, width, 1.0), 0.0)
            bins = np.minimum(((centre[items, axis] - clo[item_node, axis]) * scale[item_node])
                              .astype(np.int64), BINS - 1)
            # Each bin's box, bins first (so the running unions below are over whole rows):
            # the instances sorted by bin, reduced over each bin's run.
            nodes = len(starts)
            cell = bins * nodes + item_node
            by_cell = np.argsort(cell, kind="stable")
            sorted_cells = cell[by_cell]
            runs = np.flatnonzero(np.diff(sorted_cells, prepend=-1))
            blo = np.full((BINS * nodes, 3), np.inf)
            bhi = np.full((BINS * nodes, 3), -np.inf)
            blo[sorted_cells[runs]] = np.minimum.reduceat(lo[items[by_cell]], runs)
            bhi[sorted_cells[runs]] = np.maximum.reduceat(hi[items[by_cell]], runs)
            n = np.bincount(cell, minlength=BINS * nodes).reshape(BINS, nodes)
            blo, bhi = blo.reshape(BINS, nodes, 3), bhi.reshape(BINS, nodes, 3)
            with np.errstate(invalid="ignore"):
                left = _half_area(np.minimum.accumulate(blo), np.maximum.accumulate(bhi))[:-1]
                right = _half_area(np.minimum.accumulate(blo[::-1])[::-1],
                                   np.maximum.accumulate(bhi[::-1])[::-1])[1:]
            n_left = np.cumsum(n, axis=0)[:-1]
            n_right = sizes[None, :] - n_left
            with np.errstate(invalid="ignore"):
                cost = np.where((n_left > 0) & (n_right > 0),
                                left * n_left + right * n_right, np.inf).T
            cut = np.argmin(cost, axis=1)
            cost = cost[np.arange(len(starts)), cut]
            better = cost < best_cost
            best_cost = np.where(better, cost, best_cost)
            best_axis = np.where(better, axis, best_axis)
            best_cut = np.where(better, cut + 1, best_cut)       # bins below go left
        area = _half_area(nlo, nhi)
        leaf = (sizes == 1) | ((sizes <= TOPLEVEL_LEAF_MAX)
                               & (sizes * area <= TRAVERSAL_COST * area + best_cost))
        median = ~leaf & (~np.isfinite(best_cost) | (depth >= MEDIAN_DEPTH))
        # Which side each instance of a split node goes to: its bin along the best axis, or
        # its rank by centre along the node's widest centre axis (median).
        axis = best_axis[item_node]
        width = (chi - clo)[np.arange(len(starts)), best_axis]
        scale = np.where(width > 0, BINS / np.where(width > 0, width, 1.0), 0.0)
        bins = np.minimum(((centre[items, axis] - clo[item_node, axis]) * scale[item_node])
                          .astype(np.int64), BINS - 1)
        right_side = bins >= best_cut[item_node]
        wide = np.argmax(chi - clo, axis=1)
        rank_key = centre[items, wide[item_node]]
        ranked = np.lexsort((rank_key, item_node))            # by node, then centre
        rank = np.empty(len(items), np.int64)
        rank[ranked] = np.arange(len(items)) - heads[item_node[ranked]]
        right_side = np.where(median[item_node], rank >= sizes[item_node] // 2, right_side)
        # Stable partition of each node's instances: left side first.
        regroup = np.lexsort((right_side, item_node))
        order[places] = items[regroup]
        n_left = np.bincount(item_node, ~right_side, len(starts)).astype(np.int64)
        # Record the level's nodes, then the next level: the children of split nodes.
        split = ~leaf
        children = made + 2 * np.cumsum(split) - 2
        box_lo[ids], box_hi[ids] = nlo, nhi
        first[ids] = np.where(leaf, starts, children)
        leaf_count[ids] = np.where(leaf, sizes, 0)
        made += 2 * int(split.sum())
        mid = starts[split] + n_left[split]
        starts, ends = (np.stack([starts[split], mid], axis=1).reshape(-1),
                        np.stack([mid, ends[split]], axis=1).reshape(-1))
        ids = np.stack([children[split], children[split] + 1], axis=1).reshape(-1)
    nodes = np.zeros((made, TOPLEVEL_NODE.size, 4), np.float32)
    TOPLEVEL_NODE.put(nodes, "min", box_lo[:made].astype(np.float32))
    TOPLEVEL_NODE.put(nodes, "max", box_hi[:made].astype(np.float32))
    TOPLEVEL_NODE.put(nodes, "first", first[:made].astype(np.uint32).view(np.float32))
    TOPLEVEL_NODE.put(nodes, "count", leaf_count[:made].astype(np.uint32).view(np.float32))
    return TopLevel(nodes, order, depth)
