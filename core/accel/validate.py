"""The check of a compact kd-tree that comes from elsewhere (the network, a disk cache) before
a kernel traverses it: no index outside its array, no cycle, bounded depth."""
from __future__ import annotations

import numpy as np

from ..layout import (INNER_EMPTY_ABOVE, INNER_EMPTY_BELOW, INNER_GROUP, INNER_REF, LEAF16_BASE,
                      LEAF16_COUNT, LEAF32_COUNT, LEAF_TAG, LEAF_WIDE, MAX_LEAF_SHIFT,
                      NO_TRIANGLE, TAG)
from .arrays import concat_ranges, exclusive_cumsum

MAX_DEPTH = 1024
PIECE = 1 << 21     # leaves decoded and checked between two heartbeats


def _pieces(n: int):
    return [(a, min(a + PIECE, n)) for a in range(0, n, PIECE)]


def validate_compact(nodes, leaf_index32, leaf_index16, bounds, leaf_shift,
                     triangle_count: int, heartbeat=None) -> int:
    """Check compact-layout arrays so that a traversal never reads outside them or loops.

    Raises ValueError naming the problem; returns the tree depth (root = 1). Checks: shapes and
    dtypes; children and reference slots after their parent and inside the node array, every
    node reached at most once (so no cycles, no sharing); leaf ranges inside their index list
    and not overlapping; every triangle index (slots, 32- and 16-bit lists) below
    triangle_count; depth at most MAX_DEPTH. heartbeat(), where given, is called after each
    level and each PIECE leaves, so that an exception from it (Esc) stops the check there
    (the stretches between calls: docs/kdtree_native.md, "Trees kept on disk").
    """
    beat = heartbeat or (lambda: None)
    nodes = np.asarray(nodes)
    leaf_index32 = np.asarray(leaf_index32).reshape(-1)
    leaf_index16 = np.asarray(leaf_index16).reshape(-1)
    bounds = np.asarray(bounds)
    if nodes.ndim == 2 and len(nodes) == 0:
        raise ValueError("kd-tree has no nodes")
    if nodes.ndim != 2 or nodes.shape[1] != 2 or nodes.dtype != np.uint32:
        raise ValueError(f"kd-tree nodes must be an (N, 2) uint32 array, "
                         f"got {nodes.dtype} {nodes.shape}")
    if leaf_index32.dtype != np.uint32 or leaf_index16.dtype != np.uint16:
        raise ValueError("leaf_index32 must be uint32 and leaf_index16 uint16")
    if bounds.shape != (2, 3) or not np.isfinite(bounds).all():
        raise ValueError(f"kd-tree bounds must be a finite (2, 3) array, got {bounds.shape}")
    leaf_shift = int(leaf_shift)
    if not 0 <= leaf_shift <= MAX_LEAF_SHIFT:
        raise ValueError(f"leaf_shift must be in 0..{MAX_LEAF_SHIFT}, got {leaf_shift}")
    n = len(nodes)
    T = int(triangle_count)
    reached = np.zeros(n, bool)
    reached[0] = True
    reached_count = 1
    word0 = nodes[:, 0]
    is_leaf_node = np.zeros(n, bool)
    level = np.zeros(1, np.int64)
    depth = 0
    while len(level):
        depth += 1
        if depth > MAX_DEPTH:
            raise ValueError(f"kd-tree deeper than {MAX_DEPTH} levels")
        w0 = word0[level].astype(np.int64)
        is_leaf = TAG.get(w0) == LEAF_TAG
        is_leaf_node[level[is_leaf]] = True
        inner, w = level[~is_leaf], w0[~is_leaf]
        if not len(inner):
            break
        has_ref, eb, ea = INNER_REF.get(w), INNER_EMPTY_BELOW.get(w), INNER_EMPTY_ABOVE.get(w)
        group = INNER_GROUP.get(w)
        if (eb & ea).any():
            raise ValueError("a kd-tree node has both children elided")
        below = group + has_ref
        above = below + 1 - eb
        slot = group[has_ref == 1]
        children = np.concatenate([below[eb == 0], above[ea == 0]])
        if (group <= inner).any() or (children >= n).any() or (slot >= n).any():
            raise ValueError("kd-tree nodes point outside the tree or backwards")
        if len(slot):
            refs = nodes[slot].astype(np.int64)
            if (refs[:, 0] >= T).any() or ((refs[:, 1] >= T) & (refs[:, 1] != NO_TRIANGLE)).any():
                raise ValueError("a kd-tree reference slot names a triangle that does not exist")
        touched = np.concatenate([slot, children])
        # Each node once: none reached before, and no two of this level the same (then fewer
        # new nodes are marked than were touched).
        if reached[touched].any():
            raise ValueError("a kd-tree node is reached more than once")
        reached[touched] = True
        reached_count += len(touched)
        if np.count_nonzero(reached) != reached_count:
            raise ValueError("a kd-tree node is reached more than once")
        level = children
        beat()
    # The leaves in node order (their lists' order in the compactor's trees and in treelets,
    # so that no sort is needed), decoded PIECE at a time.
    leaves = np.flatnonzero(is_leaf_node)
    kinds = {True: [], False: []}            # per list kind: (offset, count, base) pieces
    for a, b in _pieces(len(leaves)):
        w = word0[leaves[a:b]].astype(np.int64)
        offset = nodes[:, 1][leaves[a:b]].astype(np.int64)
        wide = LEAF_WIDE.get(w) == 1
        for is16 in (True, False):
            pick = wide == is16
            wk = w[pick]
            count = LEAF16_COUNT.get(wk) if is16 else LEAF32_COUNT.get(wk)
            base = (LEAF16_BASE.get(wk) << leaf_shift) if is16 else np.zeros(len(wk), np.int64)
            keep = count > 0
            kinds[is16].append((offset[pick][keep], count[keep], base[keep]))
        beat()
    for is16, index, name in ((True, leaf_index16, "leaf_index16"),
                              (False, leaf_index32, "leaf_index32")):
        parts = [part for part in kinds[is16] if len(part[0])]
        if any((off[1:] < off[:-1]).any() for off, _, _ in parts) or any(
                b[0][0] < a[0][-1] for a, b in zip(parts, parts[1:])):
            # Lists in another order than their leaves': sorted by offset, in one piece.
            off, count, base = (np.concatenate([part[k] for part in parts]) for k in range(3))
            order = np.argsort(off, kind="stable")
            parts = [(off[order], count[order], base[order])]
        beat()
        end = 0                 # where the ranges so far end
        for off, count, base in parts:
            if off[-1] + count[-1] > len(index):
                raise ValueError(f"a kd-tree leaf reaches past the end of {name}")
            ends = off + count
            if off[0] < end or (off[1:] < ends[:-1]).any():
                raise ValueError(f"kd-tree leaves overlap in {name}")
            # Ranges are disjoint, so expanding them reads each entry at most once; ranges one
            # after another (the compactor's) are a slice.
            if np.array_equal(off[1:], ends[:-1]):
                values = index[off[0]:ends[-1]]
                starts = off - off[0]
            else:
                values = index[concat_ranges(off, count)]
                starts = exclusive_cumsum(count)[:-1]
            top = np.maximum.reduceat(values, starts).astype(np.int64) + base
            if (top >= T).any():
                raise ValueError("a kd-tree leaf refers to a triangle that does not exist")
            end = int(ends[-1])
            beat()
    return depth
