"""The standard kd-tree as the compaction (core/accel/compact.py) reads it: `Topology` decodes
the plain nodes into levels, parents, depths, cells' surface areas and preorder numbers, with
the per-level passes the lifting and the layout share (docs/kdtree_compression.md)."""
from __future__ import annotations

import numpy as np

from ..layout import LEAF_TAG, PLAIN_FIELD, PLAIN_TAG
from .arrays import concat_ranges, exclusive_cumsum


def level_ranges(is_leaf: np.ndarray, field: np.ndarray):
    """The level ranges of a tree in the builders' order (breadth-first, the k-th inner
    node's children at 1 + 2k: then level k + 1 starts where level k ends, and ends at 1 + 2
    (inner nodes before it)); None for a tree in any other order."""
    inner = np.flatnonzero(~is_leaf)
    if len(is_leaf) != 1 + 2 * len(inner) or not np.array_equal(
            field[inner], 1 + 2 * np.arange(len(inner))):
        return None
    inner_before = exclusive_cumsum(~is_leaf)
    ranges = [(0, 1)]
    while True:
        a, b = ranges[-1]
        end = 1 + 2 * int(inner_before[b])
        if end == b:
            return ranges
        ranges.append((b, end))


class Topology:
    """The standard tree decoded: levels, parents, cells' surface areas, preorder numbers.

    For a tree in the builders' order (breadth-first, the k-th inner node's children at
    1 + 2k, see `builder_order`), every level is a contiguous range (`ranges`) and the
    children of its inner nodes are, pair by pair, the next level: the per-level passes here
    and below then work on slices (same values as the general passes, which follow child
    indices). `ranges` is None for any other order."""

    def __init__(self, tree):
        nodes = tree.nodes
        n = len(nodes)
        word0 = nodes[:, 0]
        self.n = n
        self.is_leaf = PLAIN_TAG.get(word0) == LEAF_TAG
        self.axis = PLAIN_TAG.get(word0).astype(np.int8)
        self.field = PLAIN_FIELD.get(word0).astype(np.int64)
        self.split_bits = nodes[:, 1]
        self.ranges = level_ranges(self.is_leaf, self.field)
        if self.ranges is not None:
            self._decode_levels(tree)
        else:
            self._decode(tree)
        self.max_depth = len(self.levels) - 1

    def _decode(self, tree):
        """Levels, parents, depths, areas, then subtree sizes and preorder numbers, following
        child indices from the root (any order of nodes)."""
        n = self.n
        self.parent = np.full(n, -1, np.int64)
        self.depth = np.zeros(n, np.int16)
        self.area = np.zeros(n, np.float64)
        self.levels = []
        lo = tree.bounds[0].astype(np.float64)[None]
        hi = tree.bounds[1].astype(np.float64)[None]
        level = np.zeros(1, np.int64)
        d = 0
        while len(level):
            self.levels.append(level)
            self.depth[level] = d
            dims = hi - lo
            self.area[level] = 2 * (dims[:, 0] * dims[:, 1] + dims[:, 1] * dims[:, 2]
                                    + dims[:, 2] * dims[:, 0])
            inner = ~self.is_leaf[level]
            parents = level[inner]
            if not len(parents):
                break
            child = self.field[parents]
            if (child <= parents).any() or (child + 1 >= n).any():
                raise ValueError("kd-tree children must follow their parent and exist")
            self.parent[child] = parents
            self.parent[child + 1] = parents
            ax = self.axis[parents].astype(np.int64)
            split = self.split_bits[parents].view(np.float32).astype(np.float64)
            rows = np.arange(len(parents))
            b_lo, b_hi = lo[inner], hi[inner].copy()
            a_lo, a_hi = lo[inner].copy(), hi[inner]
            b_hi[rows, ax] = split
            a_lo[rows, ax] = split
            level = np.stack([child, child + 1], 1).reshape(-1)
            lo = np.stack([b_lo, a_lo], 1).reshape(-1, 3)
            hi = np.stack([b_hi, a_hi], 1).reshape(-1, 3)
            d += 1
        reached = sum(len(l) for l in self.levels)
        if reached != n:
            raise ValueError(f"{n - reached} kd-tree nodes are not reachable from the root")
        # Subtree sizes (bottom-up), then preorder numbers (top-down): a subtree is the preorder
        # range [pre[n], pre[n] + size[n]).
        size = np.ones(n, np.int64)
        for level in reversed(self.levels):
            inner = level[~self.is_leaf[level]]
            child = self.field[inner]
            size[inner] += size[child] + size[child + 1]
        self.pre = np.zeros(n, np.int64)
        for level in self.levels:
            inner = level[~self.is_leaf[level]]
            child = self.field[inner]
            self.pre[child] = self.pre[inner] + 1
            self.pre[child + 1] = self.pre[inner] + 1 + size[child]
        self.pre_end = self.pre + size

    def _decode_levels(self, tree):
        """The same arrays for a tree in the builders' order, level range by level range."""
        n, is_leaf = self.n, self.is_leaf
        ranges = self.ranges
        self.levels = [np.arange(a, b) for a, b in ranges]
        self.parent = np.full(n, -1, np.int64)
        self.parent[1:] = np.flatnonzero(~is_leaf)[(np.arange(1, n) - 1) >> 1]
        self.depth = np.repeat(np.arange(len(ranges), dtype=np.int16),
                               [b - a for a, b in ranges])
        self.area = np.empty(n, np.float64)
        split = self.split_bits.view(np.float32)
        lo = tree.bounds[0].astype(np.float64)[None]
        hi = tree.bounds[1].astype(np.float64)[None]
        for a, b in ranges:
            dims = hi - lo
            self.area[a:b] = 2 * (dims[:, 0] * dims[:, 1] + dims[:, 1] * dims[:, 2]
                                  + dims[:, 2] * dims[:, 0])
            inner = ~is_leaf[a:b]
            if not inner.any():
                break
            parents = a + np.flatnonzero(inner)
            ax = self.axis[parents].astype(np.int64)
            sp = split[parents].astype(np.float64)
            lo = np.repeat(lo[inner], 2, 0)
            hi = np.repeat(hi[inner], 2, 0)
            rows = 2 * np.arange(len(parents))
            hi[rows, ax] = sp
            lo[rows + 1, ax] = sp
        size = np.ones(n, np.int64)
        for (a, b), (c, d) in reversed(self.level_pairs()):
            size[a:b][~is_leaf[a:b]] += size[c:d].reshape(-1, 2).sum(1)
        self.pre = np.zeros(n, np.int64)
        for (a, b), (c, d) in self.level_pairs():
            below = np.repeat(self.pre[a:b][~is_leaf[a:b]] + 1, 2)
            below[1::2] += size[c:d][0::2]
            self.pre[c:d] = below
        self.pre_end = self.pre + size

    def level_pairs(self) -> list:
        """(level range, its children's range) for every level with children (builders'
        order only)."""
        return list(zip(self.ranges[:-1], self.ranges[1:]))

    def inner_at(self, k) -> np.ndarray:
        """Inner nodes of level k, in index order."""
        if self.ranges is not None:
            a, b = self.ranges[k]
            return a + np.flatnonzero(~self.is_leaf[a:b])
        level = self.levels[k]
        return level[~self.is_leaf[level]]

    def subtree_sum(self, values) -> np.ndarray:
        """Sum of `values` (one per node) over each node's subtree, bottom-up level by level
        (siblings are neighbours in memory, unlike a preorder prefix sum's scattered reads)."""
        total = np.array(values, copy=True)
        if self.ranges is not None:
            for (a, b), (c, d) in reversed(self.level_pairs()):
                total[a:b][~self.is_leaf[a:b]] += total[c:d].reshape(-1, 2).sum(1)
            return total
        for level in reversed(self.levels):
            inner = level[~self.is_leaf[level]]
            child = self.field[inner]
            total[inner] += total[child] + total[child + 1]
        return total

    def lca(self, a, b) -> np.ndarray:
        """Lowest common ancestor of each node pair (a, b) with pre[a] <= pre[b].

        Binary lifting: climb from a by the largest jumps (2^k ancestors) that stay outside the
        subtree holding b; the parent of where it stops is the LCA (a itself when a is b or an
        ancestor of b). A constant number of passes instead of one per level; int32 tables and
        each subtree's preorder range in one row halve the scattered reads.
        """
        jumps = [np.maximum(self.parent, 0).astype(np.int32)]   # the root is its own parent
        for _ in range(max(self.max_depth, 1).bit_length() - 1):
            jumps.append(jumps[-1][jumps[-1]])
        span = np.stack([self.pre, self.pre_end], 1).astype(np.int32)
        pre_b = self.pre[b].astype(np.int32)
        x = np.asarray(a).astype(np.int32)
        for up in reversed(jumps):
            y = up[x]
            y_span = span[y]
            x = np.where((y_span[:, 0] <= pre_b) & (pre_b < y_span[:, 1]), x, y)
        a_holds_b = span[a, 1] > pre_b
        return np.where(a_holds_b, a, jumps[0][x]).astype(np.int64)

    def leaf_references(self, tree):
        """(leaf node, triangle) of every reference of the standard tree."""
        leaves = np.flatnonzero(self.is_leaf)
        count = self.field[leaves]
        offset = tree.nodes[leaves, 1].astype(np.int64)
        ref_leaf = np.repeat(leaves, count)
        ref_tri = tree.leaf_indices[concat_ranges(offset, count)].astype(np.int64)
        return ref_leaf, ref_tri


def pass_down(topo, k, target, source, extra):
    """target[children] = source[parent] + extra[parent] for the inner nodes of level k."""
    if topo.ranges is not None:
        if k + 1 < len(topo.ranges):
            (a, b), (c, d) = topo.ranges[k], topo.ranges[k + 1]
            inner = ~topo.is_leaf[a:b]
            target[c:d] = np.repeat(source[a:b][inner] + extra[a:b][inner], 2)
        return
    inner = topo.inner_at(k)
    child = topo.field[inner]
    target[child] = source[inner] + extra[inner]
    target[child + 1] = target[child]

