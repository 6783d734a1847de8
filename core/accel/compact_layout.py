"""The compaction's last steps (core/accel/compact.py): the collapse of subtrees into leaves by
the SAH, which nodes survive and where their contents go, and the layout: the surviving nodes
numbered level by level and written in core/layout.py COMPACT_NODE words, leaf lists 16-bit
where they fit (the numpy twin of kernels/build/compact_layout.cl; docs/kdtree_compression.md)."""
from __future__ import annotations

import numpy as np

from ..layout import (INNER_EMPTY_ABOVE, INNER_EMPTY_BELOW, INNER_GROUP, INNER_REF, LEAF16_BASE,
                      LEAF16_COUNT, LEAF16_INDEX_BITS, LEAF32_COUNT, LEAF_TAG, LEAF_WIDE,
                      NO_TRIANGLE, TAG)
from .arrays import exclusive_cumsum, run_starts
from .compact_topology import pass_down

MAX_GROUP_INDEX = INNER_GROUP.max
MAX_LEAF16_COUNT = LEAF16_COUNT.max
MAX_LEAF32_COUNT = LEAF32_COUNT.max


def collapse(topo, leaf_count, refs_at, distinct, params):
    """Bottom-up SAH: replace a subtree by one leaf when that is no more expensive."""
    K_T, K_I = params.traversal_cost, params.intersection_cost
    cost = K_I * leaf_count.astype(np.float64)
    collapsed = np.zeros(topo.n, bool)
    for k in reversed(range(len(topo.levels))):
        inner = topo.inner_at(k)
        if not len(inner):
            continue
        child = topo.field[inner]
        area = topo.area[inner]
        sub = K_T + K_I * refs_at[inner] + (topo.area[child] * cost[child]
                                            + topo.area[child + 1] * cost[child + 1]) / area
        as_leaf = K_I * distinct[inner]
        c = as_leaf <= sub
        collapsed[inner] = c
        cost[inner] = np.where(c, as_leaf, sub)
    return collapsed


def owners(topo, collapsed):
    """Which nodes are gone (below a collapsed node), and the leaf that takes each node's
    contents: top-down level by level."""
    dead = np.zeros(topo.n, bool)
    owner = np.arange(topo.n)
    if topo.ranges is not None:
        for (a, b), (c, d) in topo.level_pairs():
            inner = ~topo.is_leaf[a:b]
            gone = np.repeat((dead[a:b] | collapsed[a:b])[inner], 2)
            dead[c:d] = gone
            owner[c:d] = np.where(gone, np.repeat(owner[a:b][inner], 2), np.arange(c, d))
        return dead, owner
    for k in range(len(topo.levels)):
        inner = topo.inner_at(k)
        child = topo.field[inner]
        gone = dead[inner] | collapsed[inner]
        for c in (child, child + 1):
            dead[c] = gone
            owner[c] = np.where(gone, owner[inner], c)
    return dead, owner


def max_refs_on_path(topo, dead, refs_at) -> int:
    """The most triangle references met on a path from the root to a surviving node."""
    on_path = np.zeros(topo.n, np.int64)
    max_path = 0
    for k in range(len(topo.levels)):
        if topo.ranges is not None:
            a, b = topo.ranges[k]
            live = ~dead[a:b]
            if live.any():
                max_path = max(max_path, int((on_path[a:b][live] + refs_at[a:b][live]).max()))
        else:
            level = topo.levels[k]
            live = level[~dead[level]]
            if len(live):
                max_path = max(max_path, int((on_path[live] + refs_at[live]).max()))
        pass_down(topo, k, on_path, on_path, refs_at)
    return max_path


def leaf_shift(triangles_count: int) -> int:
    """Shift of a 16-bit leaf's base B, so that B << shift reaches every triangle index."""
    return max(0, (max(triangles_count, 1) - 1).bit_length() - LEAF16_INDEX_BITS)


def layout(topo, params, is_final_leaf, dead, final_count, item_tri, lift_node, lift_tri,
           refs_at, triangles_count):
    """Number the surviving nodes level by level and write the words (module docstring)."""
    empty_leaf = is_final_leaf & (final_count == 0)
    elided = np.zeros(topo.n, bool)
    if params.elide_empty:
        inner_live = np.flatnonzero(~dead & ~is_final_leaf)
        child = topo.field[inner_live]
        below_empty, above_empty = empty_leaf[child], empty_leaf[child + 1]
        elided[child] = below_empty & ~above_empty
        elided[child + 1] = above_empty & ~below_empty
    # Slot of every lift: 0 or 1 within its node.
    order = np.lexsort((lift_tri, lift_node))
    lift_node, lift_tri = lift_node[order], lift_tri[order]
    first = run_starts(lift_node)
    slot = np.arange(len(lift_node)) - np.repeat(first, np.diff(np.append(first, len(lift_node))))

    new_index = np.full(topo.n, -1, np.int64)
    group_of = np.zeros(topo.n, np.int64)
    new_index[0] = 0
    next_free = 1
    for k in range(len(topo.levels)):
        if topo.ranges is not None:
            a, b = topo.ranges[k]
            inner = a + np.flatnonzero(~dead[a:b] & ~is_final_leaf[a:b])
        else:
            level = topo.levels[k]
            inner = level[~dead[level] & ~is_final_leaf[level]]
        if not len(inner):
            continue
        if (np.diff(new_index[inner]) < 0).any():     # already in order for breadth-first trees
            inner = inner[np.argsort(new_index[inner], kind="stable")]
        child = topo.field[inner]
        has_ref = (refs_at[inner] > 0).astype(np.int64)
        keep_b = (~elided[child]).astype(np.int64)
        keep_a = (~elided[child + 1]).astype(np.int64)
        sizes = has_ref + keep_b + keep_a
        start = next_free + exclusive_cumsum(sizes)[:-1]
        group_of[inner] = start
        new_index[child] = np.where(keep_b > 0, start + has_ref, -1)
        new_index[child + 1] = np.where(keep_a > 0, start + has_ref + keep_b, -1)
        next_free += int(sizes.sum())
    total = next_free
    if total - 1 > MAX_GROUP_INDEX:
        raise ValueError(f"compact kd-tree too large: {total} nodes (at most {MAX_GROUP_INDEX})")
    nodes = np.zeros((total, 2), np.uint32)

    # Inner nodes.
    inner = np.flatnonzero(~dead & ~is_final_leaf)
    child = topo.field[inner]
    word0 = (TAG.put(topo.axis[inner].astype(np.int64)) | INNER_REF.put(refs_at[inner] > 0)
             | INNER_EMPTY_BELOW.put(elided[child].astype(np.int64))
             | INNER_EMPTY_ABOVE.put(elided[child + 1].astype(np.int64))
             | INNER_GROUP.put(group_of[inner]))
    nodes[new_index[inner], 0] = word0
    nodes[new_index[inner], 1] = topo.split_bits[inner]
    # T-reference slots: at the start of their node's group.
    tref_nodes = np.flatnonzero(refs_at > 0)
    nodes[group_of[tref_nodes]] = NO_TRIANGLE
    nodes[group_of[lift_node], slot] = lift_tri

    # Leaves, in new index order (which is the old index order restricted to survivors).
    leaves = np.flatnonzero(is_final_leaf & ~elided)
    count = final_count[leaves]
    shift = leaf_shift(triangles_count)
    starts = exclusive_cumsum(final_count)[:-1][leaves]
    nonempty = count > 0
    low = np.zeros(len(leaves), np.int64)
    high = np.zeros(len(leaves), np.int64)
    low[nonempty] = item_tri[starts[nonempty]]
    high[nonempty] = item_tri[starts[nonempty] + count[nonempty] - 1]
    base = low >> shift
    fits16 = (params.leaf16 & nonempty & (count <= MAX_LEAF16_COUNT)
              & (high - (base << shift) < 1 << LEAF16_INDEX_BITS))
    if (count > MAX_LEAF32_COUNT).any():
        raise ValueError(f"a leaf holds too many triangles for the {LEAF32_COUNT.bits}-bit count")
    item_is16 = np.repeat(fits16, count)
    idx32 = item_tri[~item_is16].astype(np.uint32)
    idx16 = (item_tri[item_is16] - np.repeat((base << shift)[fits16], count[fits16])
             ).astype(np.uint16)
    off32 = exclusive_cumsum(np.where(fits16, 0, count))[:-1]
    off16 = exclusive_cumsum(np.where(fits16, count, 0))[:-1]
    word0 = np.where(fits16, TAG.put(LEAF_TAG) | LEAF_WIDE.bit | LEAF16_COUNT.put(count)
                     | LEAF16_BASE.put(base), TAG.put(LEAF_TAG) | LEAF32_COUNT.put(count))
    word1 = np.where(fits16, off16, np.where(nonempty, off32, 0))
    nodes[new_index[leaves], 0] = word0
    nodes[new_index[leaves], 1] = word1

    kinds = {"inner": int(len(inner)), "tref": int(len(tref_nodes)), "leaf": int(len(leaves))}
    assert sum(kinds.values()) == total
    leaf_stats = {
        "leaves": int(len(leaves)),
        "empty_leaves_stored": int((~nonempty).sum()),
        "empty_leaves_elided": int(elided.sum()),
        "leaves_16bit": int(fits16.sum()),
        "leaves_32bit": int((nonempty & ~fits16).sum()),
        "leaf16_share": float(fits16.sum() / max(int(nonempty.sum()), 1)),
        "leaf_shift": shift,
    }
    return nodes, idx32, idx16, shift, kinds, leaf_stats
