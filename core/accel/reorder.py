"""A cache-friendly node order for a compact kd-tree: node groups in treelets.

The compactor (compact.py) stores the tree breadth-first, as the builders make it: a node's
children sit far from it in memory below the first levels, so a ray that goes down the tree
fetches a new cache line at almost every level once the upper levels have left the cache, which
incoherent rays (bounces, shadow rays, rays in random order) do all the time. Here the same
tree is laid out in treelets: the groups (a node's T-reference slot and stored children, which
the format keeps side by side) of every subtree of `height` levels are stored together, level by
level, so that one or two cache lines hold a ray's next `height` steps, and the treelets follow
each other depth first, so that a subtree's treelets are near each other too. Leaf lists are
laid out in the new order of their leaves.

The result is the same tree in the same CompactTree format (core/layout.py COMPACT_NODE): the
same nodes, splits, slots and lists, only their indices change, so a traversal visits the same
nodes in the same order and returns the same hits; `validate_compact` accepts it.
"""
from __future__ import annotations

import numpy as np

from ..layout import (INNER_EMPTY_ABOVE, INNER_EMPTY_BELOW, INNER_GROUP, INNER_REF, LEAF16_COUNT,
                      LEAF32_COUNT, LEAF_TAG, LEAF_WIDE, TAG)
from .arrays import concat_ranges, exclusive_cumsum
from .compact import CompactTree

# Levels per treelet. Measured on the dragon (docs/tracer.md): a treelet of 3 levels holds
# about 8-12 nodes (one or two 64-byte lines); 2 and 4 levels are slower.
TREELET_HEIGHT = 3


def treelet_order(tree: CompactTree, height: int = TREELET_HEIGHT, heartbeat=None) -> CompactTree:
    """`tree` with its node groups in treelets of `height` levels (module docstring).
    heartbeat(), where given, is called after each level of each pass and between the steps,
    so that its exception (Esc) stops the work there."""
    beat = heartbeat or (lambda: None)
    if height < 1:
        raise ValueError("treelet height must be at least 1")
    nodes = np.ascontiguousarray(tree.nodes, np.uint32)     # (n, 2) words: viewed as uint64 below
    w0 = nodes[:, 0].astype(np.int64)
    if TAG.get(w0[0]) == LEAF_TAG:
        return tree
    # The inner nodes level by level (breadth first from the root): each one's parent and
    # group (start and size), and the leaves.
    inner_levels, parent_levels, leaves = [], [], []
    level, parents = np.zeros(1, np.int64), np.full(1, -1, np.int64)
    while len(level):
        is_leaf = TAG.get(w0[level]) == LEAF_TAG
        leaves.append(level[is_leaf])
        inner, parents = level[~is_leaf], parents[~is_leaf]
        if not len(inner):
            break
        inner_levels.append(inner)
        parent_levels.append(parents)
        w = w0[inner]
        below = INNER_GROUP.get(w) + INNER_REF.get(w)
        above = below + 1 - INNER_EMPTY_BELOW.get(w)
        has_below, has_above = INNER_EMPTY_BELOW.get(w) == 0, INNER_EMPTY_ABOVE.get(w) == 0
        # Each parent's children side by side, below first: the parents stay in order.
        stored = np.stack([has_below, has_above], 1)
        level = np.stack([below, above], 1)[stored]
        parents = np.stack([inner, inner], 1)[stored]      # a mask: faster than np.repeat
        beat()
    inner = np.concatenate(inner_levels)                    # breadth-first order
    level_start = exclusive_cumsum([len(x) for x in inner_levels])
    depth = np.repeat(np.arange(len(inner_levels)), np.diff(level_start))

    def at_depth(d):
        return np.arange(level_start[d], level_start[d + 1])
    slot_of = np.full(len(nodes), -1, np.int64)             # node -> its position in `inner`
    slot_of[inner] = np.arange(len(inner))
    parent = np.concatenate(parent_levels)
    parent = np.where(parent >= 0, slot_of[np.maximum(parent, 0)], -1)
    w = w0[inner]
    group = INNER_GROUP.get(w)
    group_size = INNER_REF.get(w) + 2 - INNER_EMPTY_BELOW.get(w) - INNER_EMPTY_ABOVE.get(w)

    # Preorder numbers of the inner nodes: subtree sizes bottom-up, then top-down, the below
    # child first (a parent's inner children appear in the next level in that order).
    size = np.ones(len(inner), np.int64)
    for d in range(len(inner_levels) - 1, 0, -1):
        at, above = at_depth(d), at_depth(d - 1)         # the parents are in the level above
        size[above] += np.bincount(parent[at] - above[0], size[at], len(above)).astype(np.int64)
        beat()
    preorder = np.zeros(len(inner), np.int64)
    for d in range(1, len(inner_levels)):
        at = at_depth(d)                     # per parent (in order): below, then above
        p = parent[at]
        # Within a parent, the second child starts after the first child's subtree.
        first = np.r_[True, p[1:] != p[:-1]]
        before = np.where(first, 0, np.r_[0, size[at][:-1]])
        preorder[at] = preorder[p] + 1 + before
        beat()

    # Each inner node's treelet root: its ancestor at the last depth that is a multiple of
    # `height` (top-down, so a parent's root is known first).
    root = np.arange(len(inner))
    for d in range(1, len(inner_levels)):
        if d % height:
            at = at_depth(d)
            root[at] = root[parent[at]]
    # Groups in treelet order: treelets depth first, within a treelet level by level.
    # One int64 key (preorder numbers are below 2^27 = INNER_GROUP's range, depths below 2^8).
    key = (preorder[root] << 35) | ((depth - depth[root]) << 27) | preorder
    beat()
    order = _argsort_in_pieces(key, preorder[root], len(inner), beat)
    new_group = 1 + exclusive_cumsum(group_size[order])[:-1]     # node 0 is the root
    # Each group's nodes keep their places in it (a group has at most 3: one pass per place).
    new_index = np.zeros(len(nodes), np.int64)
    old_group, sizes = group[order], group_size[order]
    for k in range(int(sizes.max())):
        has = sizes > k
        new_index[old_group[has] + k] = new_group[has] + k
    new_of_group = np.empty(len(inner), np.int64)
    new_of_group[order] = new_group
    beat()

    out = np.empty_like(nodes)
    out.view(np.uint64)[new_index, 0] = nodes.view(np.uint64)[:, 0]   # both words at once
    field = INNER_GROUP.put(INNER_GROUP.max)
    out[new_index[inner], 0] = ((w & ~field) | INNER_GROUP.put(new_of_group)).astype(np.uint32)

    beat()
    # Leaf lists in the leaves' new order.
    leaves = np.concatenate(leaves)
    leaves = leaves[_order_of_distinct(new_index[leaves], len(nodes))]
    beat()
    lw = w0[leaves]
    wide = LEAF_WIDE.get(lw) == 1
    lists = {}
    for is16, index in ((True, tree.leaf_index16), (False, tree.leaf_index32)):
        pick = leaves[wide == is16]
        count = (LEAF16_COUNT if is16 else LEAF32_COUNT).get(w0[pick])
        offset = nodes[pick, 1].astype(np.int64)
        lists[is16] = np.asarray(index)[concat_ranges(offset, count)]
        beat()
        new_offset = np.where(count > 0, exclusive_cumsum(count)[:-1], 0)
        out[new_index[pick], 1] = new_offset.astype(np.uint32)
    return CompactTree(out, np.ascontiguousarray(lists[False], np.uint32),
                       np.ascontiguousarray(lists[True], np.uint16), tree.bounds, tree.leaf_shift,
                       tree.params, dict(tree.stats, node_order=f"treelets of {height} levels"))


# Keys sorted a piece at a time: one argsort of 12 dragons' 6.8 M treelet keys held Esc for
# about a second.
SORT_PIECE = 1 << 20


def _argsort_in_pieces(key, primary, bound: int, beat):
    """np.argsort(key) of distinct keys whose order follows `primary` (values in [0, bound)),
    sorted in pieces of about SORT_PIECE keys with beat() between them: the keys go to buckets
    by ranges of `primary` (a radix sort of 16-bit bucket numbers), then each bucket is sorted
    alone. Distinct keys make the result that of one argsort."""
    pieces = min(-(-len(key) // SORT_PIECE), 1 << 15)
    if pieces <= 1:
        return np.argsort(key, kind="stable")
    bucket = (primary * pieces // bound).astype(np.uint16)
    by_bucket = np.argsort(bucket, kind="stable")
    starts = exclusive_cumsum(np.bincount(bucket, minlength=pieces))
    beat()
    order = np.empty(len(key), np.int64)
    for b in range(pieces):
        members = by_bucket[starts[b]:starts[b + 1]]
        order[starts[b]:starts[b + 1]] = members[np.argsort(key[members], kind="stable")]
        beat()
    return order


def _order_of_distinct(values, bound: int):
    """np.argsort(values) of distinct integers in [0, bound), in linear time (a scatter)."""
    place = np.full(bound, -1, np.int64)
    place[values] = np.arange(len(values))
    return place[place >= 0]
