"""Compressed kd-tree layouts: triangle references in inner nodes and the 2-byte leaf mode.

A post-pass over the standard SAH tree of core/accel/kdtree.py (it only reads `KDTree.nodes`,
`leaf_indices` and `bounds`), in vectorised numpy with loops per tree level only:

1. **Lifting** (modes `choi` and `compressed`): a triangle that is duplicated into many leaves of a
   subtree is referenced once at the subtree's root (an inner node) and removed from every leaf
   below it. Which triangles and where is decided by the occupancy and frequency thresholds
   (docs/kdtree_compression.md), under a limit of references per inner node (1 for `choi`, 2 for
   `compressed`) and per root-to-leaf path (unlimited for `choi`, 8 for `compressed`).
2. **Collapsing**: a subtree whose leaves lost (most of) their references is replaced by a single
   leaf when that is not more expensive by the SAH (with the subtree's exact, bottom-up cost).
3. **Layout**: one node format for all three modes (`standard` uses none of the extras), 8 bytes
   per node; an inner node's children (and its triangle-reference slot) are stored side by side;
   empty leaves are not stored; leaf triangle lists are 16-bit where they fit, 32-bit otherwise.

Node format: core/layout.py COMPACT_NODE (uint32 pairs, `nodes[i, 0]` is word 0), the table that
also writes the kernels' header. An inner node's group holds its T-reference slot (if R), then
the children that are stored; a leaf's list is 16-bit (base B, triangle = (B << leaf_shift) +
entry) or 32-bit. `leaf_shift` is per tree: max(0, bits(triangle_count - 1) - 16), so B spans
every index.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from ..layout import (INNER_EMPTY_ABOVE, INNER_EMPTY_BELOW, INNER_GROUP, INNER_REF, LEAF16_BASE,
                      LEAF16_COUNT, LEAF16_INDEX_BITS, LEAF32_COUNT, LEAF_TAG, LEAF_WIDE,
                      NO_TRIANGLE, PLAIN_FIELD, PLAIN_TAG, TAG)
from .arrays import concat_ranges, distinct_count, exclusive_cumsum, run_lengths, run_starts
from .compact_cl import compact_on_device

MODES = ("standard", "choi", "compressed")
MAX_GROUP_INDEX = INNER_GROUP.max
MAX_LEAF16_COUNT = LEAF16_COUNT.max
MAX_LEAF32_COUNT = LEAF32_COUNT.max


@dataclass(frozen=True)
class CompactParams:
    """What the post-pass does; `compact_params(mode)` gives each mode's defaults."""

    mode: str = "compressed"
    tau_occu: float = 0.5          # lift t to n only if occupancy(t, n) >= tau_occu
    tau_freq: float = 0.4          # ... and frequency(t, n) >= tau_freq
    refs_per_node: int = 2         # triangle references per inner node (1 or 2)
    refs_per_path: int | None = 8  # total on any root-to-leaf path; None: unlimited
    min_refs: int = 2              # a lift must remove at least this many leaf references
    collapse: bool = True          # replace subtrees by leaves where the SAH says so
    elide_empty: bool = True       # empty leaves are flags in the parent, not nodes
    leaf16: bool = True            # the 2-byte leaf mode
    # K_T, K_I of the collapse decision. K_T is twice the builder's 15: collapsing subtrees at
    # that price makes trees 10-17 points smaller at the same render time within the noise
    # (the collapse sweep in docs/kdtree_compression.md).
    traversal_cost: float = 30.0
    intersection_cost: float = 20.0


def compact_params(mode: str = "compressed", **overrides) -> CompactParams:
    """Defaults of a mode (`standard`: the plain tree in the common layout), then overrides."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if mode == "standard":
        base = CompactParams(mode, refs_per_node=0, refs_per_path=0, collapse=False,
                             elide_empty=False, leaf16=False)
    elif mode == "choi":
        base = CompactParams(mode, refs_per_node=1, refs_per_path=None)
    else:
        base = CompactParams(mode, refs_per_node=2, refs_per_path=8)
    overrides = {k: v for k, v in overrides.items() if v is not None}
    params = replace(base, **overrides)
    if not 0 <= params.refs_per_node <= 2:
        raise ValueError("refs_per_node must be 0, 1 or 2 (one 8-byte slot)")
    if params.refs_per_path is not None and params.refs_per_path < 0:
        raise ValueError("refs_per_path must be >= 0 or None")
    if params.min_refs < 1:
        raise ValueError("min_refs must be >= 1")
    return params


# What a user may set of a compact tree (the add-on's kd-Tree panel), with its range; the
# defaults are those of compact_params(mode).
USER_SETTING_LIMITS = {"tau_occu": (0.0, 16.0), "tau_freq": (0.0, 1.0), "refs_per_path": (0, 64)}


def user_settings(mode: str, tau_occu: float, tau_freq: float, refs_per_path: int) -> dict:
    """The compact_tree keyword arguments of a user's settings, only those that `mode` uses
    (standard: none; choi: the thresholds, its path is unlimited; compressed: all three), so that
    settings which cannot change the tree do not make another tree (or another scene hash)."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    chosen = {"tau_occu": float(tau_occu), "tau_freq": float(tau_freq),
              "refs_per_path": int(refs_per_path)}
    used = {"standard": (), "choi": ("tau_occu", "tau_freq"), "compressed": tuple(chosen)}[mode]
    return {name: chosen[name] for name in used}


@dataclass
class CompactTree:
    nodes: np.ndarray          # uint32 (N, 2), format in the module docstring
    leaf_index32: np.ndarray   # uint32
    leaf_index16: np.ndarray   # uint16
    bounds: np.ndarray         # float32 (2, 3)
    leaf_shift: int
    params: CompactParams | None = None      # None for a tree received from elsewhere
    stats: dict = field(default_factory=dict)
    # (triangle count, depth) once core/scene/scene.py has validated the tree for that many
    # triangles: a tree the master keeps in its cache is checked once, not at every render.
    # A CompactTree's arrays are not changed after it is made.
    checked: tuple | None = field(default=None, compare=False, repr=False)
    digest: str | None = field(default=None, compare=False, repr=False)   # scene.py's, once

    @property
    def mode(self) -> str | None:
        return None if self.params is None else self.params.mode

    def nbytes_by_part(self) -> dict:
        """Bytes of each array a tracer needs for the tree (nodes split by kind)."""
        kinds = self.stats["node_kinds"]
        return {"inner_nodes": 8 * kinds["inner"], "tref_slots": 8 * kinds["tref"],
                "leaf_nodes": 8 * kinds["leaf"], "nodes": int(self.nodes.nbytes),
                "leaf_index32": int(self.leaf_index32.nbytes),
                "leaf_index16": int(self.leaf_index16.nbytes),
                "leaf_indices": int(self.leaf_index32.nbytes + self.leaf_index16.nbytes),
                "total": self.nbytes}

    @property
    def nbytes(self) -> int:
        return int(self.nodes.nbytes + self.leaf_index32.nbytes + self.leaf_index16.nbytes)


def geometry_nbytes(vertex_count: int, triangle_count: int, material_count: int = 1) -> dict:
    """Bytes of the geometry a tracer needs: float32 vertices, 16-bit vertex indices when every
    index fits, else 32-bit, and 16-bit material ids only when there is more than one material."""
    index_bytes = 2 if vertex_count <= 0x10000 else 4
    parts = {"vertices": 12 * vertex_count, "triangles": 3 * index_bytes * triangle_count,
             "material_ids": 2 * triangle_count if material_count > 1 else 0}
    parts["total"] = sum(parts.values())
    return parts


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


class _Topology:
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


# ---------------------------------------------------------------------------------------------
# 1. Lifting

def _nearest_lower(values, index, step, strict):
    """For each i in `index`, the nearest k in direction `step` (+1 or -1) with values[k] below
    values[i] (`strict`) or at most values[i]. `values` must end in sentinels lower than any
    queried value on both sides. Pointer jumping: every pointer k -> p[k] skips only values
    that do not stop k, hence none that would stop i either."""
    pointer = np.arange(len(values)) + step
    target = values[index]
    active = np.arange(len(index))
    while len(active):
        at = pointer[index[active]]
        seen = values[at]
        move = (seen >= target[active]) if strict else (seen > target[active])
        active = active[move]
        pointer[index[active]] = pointer[at[move]]
    return pointer[index]


def _neighbour_lcas(topo, s_leaf, s_tri):
    """Gap j lies before sorted reference j: the LCA of the leaves of references j-1 and j when
    they hold the same triangle, and its depth; depth -1 between triangles and at both ends."""
    count = len(s_tri)
    gap_depth = np.full(count + 1, -1, np.int64)
    gap_node = np.zeros(count + 1, np.int64)
    same = np.flatnonzero(s_tri[1:] == s_tri[:-1]) + 1
    gap_node[same] = topo.lca(s_leaf[same - 1], s_leaf[same])
    gap_depth[same] = topo.depth[gap_node[same]]
    return gap_node, gap_depth


def _lift_candidates(topo, s_leaf, s_tri, gap_node, gap_depth, params):
    """Every (inner node, triangle) pair that passes both thresholds, per depth.

    s_leaf/s_tri: references sorted by (triangle, preorder of the leaf), so that the references of
    a triangle inside any subtree are one contiguous run. The run of t below a node at depth d is
    a maximal stretch of t's references whose gaps (`_neighbour_lcas`) lie at depth >= d: it
    appears at the depth of its LCA and lasts, unchanged but for its node, up to the depth where
    it merges with a neighbour (a triangle whose references have all met is dropped there:
    higher up its occupancy only falls). Each run is walked up from its LCA only while it
    qualifies: occupancy and frequency only fall going up where cells grow (checked per path),
    so no pair above a failure can qualify. A triangle with fewer than min_refs references has
    no run long enough. Returns per depth a tuple of arrays (node, triangle, references removed,
    first and end position of the run in the sorted list).
    """
    same = np.flatnonzero(gap_depth >= 0)
    # Runs of two or more references: one per gap that is the first of its depth in its run.
    left = _nearest_lower(gap_depth, same, -1, strict=False)
    right = _nearest_lower(gap_depth, same, +1, strict=True)
    first = gap_depth[left] < gap_depth[same]
    run_lo, run_hi = left[first], right[first]   # references run_lo .. run_hi - 1
    run_node, run_depth = gap_node[same[first]], gap_depth[same[first]]
    # Copies of a triangle within one leaf (never made by core/accel/kdtree.py): the leaf is no
    # candidate, the run starts at its parent.
    in_leaf = np.flatnonzero(topo.is_leaf[run_node])
    run_node[in_leaf], run_depth[in_leaf] = topo.parent[run_node[in_leaf]], run_depth[in_leaf] - 1
    if params.min_refs <= 1:                     # single references are runs of their own
        single = np.flatnonzero(topo.depth[s_leaf] > 0)
        run_lo = np.concatenate([run_lo, single])
        run_hi = np.concatenate([run_hi, single + 1])
        run_node = np.concatenate([run_node, topo.parent[s_leaf[single]]])
        run_depth = np.concatenate([run_depth, topo.depth[s_leaf[single]] - 1])
    # The run merges with a neighbour one level above the deeper of its two bounding gaps; a
    # run bounded by the triangle's ends on both sides holds all its references: last depth.
    bound_lo, bound_hi = gap_depth[run_lo], gap_depth[run_hi]
    top_depth = np.where((bound_lo < 0) & (bound_hi < 0), run_depth,
                         np.maximum(bound_lo, bound_hi) + 1)
    r = run_hi - run_lo
    keep = (r >= params.min_refs) & (run_depth >= top_depth) & (run_depth >= 0)
    run_lo, run_hi, run_node, run_depth, r, top_depth = (
        run_lo[keep], run_hi[keep], run_node[keep], run_depth[keep], r[keep], top_depth[keep])
    # Summed per run over the same contiguous values as a run-by-run reduceat (same bits).
    edges = np.stack([run_lo, run_hi], 1).reshape(-1)
    area_sum = np.add.reduceat(np.append(topo.area[s_leaf], 0.0), edges)[0::2] \
        if len(edges) else np.zeros(0)
    run_tri, first, end = s_tri[run_lo], run_lo, run_hi
    nonempty_below = topo.subtree_sum((topo.is_leaf & (topo.field > 0)).astype(np.int64))
    stops = _falls_going_up(topo)

    found = []                                   # (depth, node, triangle, r, first, end)
    node, depth = run_node, run_depth
    active = np.arange(len(node))
    while len(active):
        occupancy = area_sum[active] / topo.area[node]
        frequency = r[active] / np.maximum(nonempty_below[node], 1)
        ok = (occupancy >= params.tau_occu) & (frequency >= params.tau_freq)
        hit = active[ok]
        found.append((depth[ok], node[ok], run_tri[hit], r[hit], first[hit], end[hit]))
        go_on = (depth > top_depth[active]) & (ok | ~stops[node])
        active, node, depth = active[go_on], topo.parent[node[go_on]], depth[go_on] - 1
    found = [np.concatenate(column) for column in zip(*found)] if found else [np.zeros(0)] * 6
    order = np.argsort(found[0], kind="stable")
    found = [column[order] for column in found]
    bounds = np.searchsorted(found[0], np.arange(topo.max_depth + 2))
    per_depth = [None] * (topo.max_depth + 1)
    for d in range(topo.max_depth + 1):
        if bounds[d] < bounds[d + 1]:
            per_depth[d] = tuple(column[bounds[d]:bounds[d + 1]] for column in found[1:])
    return per_depth


def _falls_going_up(topo):
    """Nodes from which the cell area never shrinks up to the root (and is positive, finite):
    there occupancy, like frequency, can only fall going up, so a failed test ends a walk."""
    ok = np.isfinite(topo.area) & (topo.area > 0)
    if topo.ranges is not None:
        for (a, b), (c, d) in topo.level_pairs():
            inner = ~topo.is_leaf[a:b]
            parent_ok = np.repeat(ok[a:b][inner], 2)
            parent_area = np.repeat(topo.area[a:b][inner], 2)
            ok[c:d] &= parent_ok & (parent_area >= topo.area[c:d])
        return ok
    for level in topo.levels[1:]:
        ok[level] &= ok[topo.parent[level]] & (topo.area[topo.parent[level]] >= topo.area[level])
    return ok


def _pass_down(topo, k, target, source, extra):
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


def _choose_lifts(cand, removed, on_path_of, params):
    """One depth of the greedy choice: the candidates (node, triangle, r, first, end) whose
    triangle was not lifted to an ancestor (its run not yet removed), by node the ones that
    remove the most references (ties: lower triangle), as many as the node and the path allow
    (`on_path_of(nodes)`: references on their proper ancestors). Marks the taken runs removed;
    returns the taken (node, triangle, first), sorted by node."""
    node, tri, r, first, end = cand
    live = ~removed[first]
    node, tri, r, first, end = node[live], tri[live], r[live], first[live], end[live]
    order = np.lexsort((tri, -r, node))
    node, tri, first, end = node[order], tri[order], first[order], end[order]
    group = run_starts(node)
    rank = np.arange(len(node)) - np.repeat(group, np.diff(np.append(group, len(node))))
    path_cap = params.refs_per_path if params.refs_per_path is not None else 1 << 30
    cap = np.minimum(params.refs_per_node, path_cap - on_path_of(node))
    take = rank < cap
    removed[concat_ranges(first[take], end[take] - first[take])] = True
    return node[take], tri[take], first[take]


def _select_lifts(topo, per_depth, ref_count, params):
    """Top-down greedy choice under the per-node and per-path limits (_choose_lifts, depth by
    depth). Returns (removed mask over sorted references, lift node, lift triangle, references
    per node, first position of each lift's run)."""
    removed = np.zeros(ref_count, bool)
    refs_at = np.zeros(topo.n, np.int64)
    on_path = np.zeros(topo.n, np.int64)          # references on the proper ancestors
    limited = params.refs_per_path is not None    # else on_path never matters
    lift_node, lift_tri, lift_first = [], [], []
    for d in range(len(topo.levels)):
        cand = per_depth[d] if d < len(per_depth) else None
        if cand is not None and len(cand[0]) and params.refs_per_node:
            taken, tri, first = _choose_lifts(cand, removed, lambda nodes: on_path[nodes], params)
            runs = run_starts(taken)                      # one run per node
            refs_at[taken[runs]] += np.diff(np.append(runs, len(taken)))
            lift_node.append(taken)
            lift_tri.append(tri)
            lift_first.append(first)
        if limited:
            _pass_down(topo, d, on_path, on_path, refs_at)
    lift_node, lift_tri, lift_first = (np.concatenate(part) if part else np.zeros(0, np.int64)
                                       for part in (lift_node, lift_tri, lift_first))
    return removed, lift_node, lift_tri, refs_at, lift_first


# ---------------------------------------------------------------------------------------------
# 2. Collapsing

def _distinct_below(topo, removed, s_leaf, gap_node, gap_depth, lift_node, lift_first):
    """Number of distinct triangles among the kept references and the lifts in each subtree.

    The kept references and the lifts' runs partition the sorted references into segments,
    in (triangle, preorder) order: a triangle's segments inside any subtree are consecutive, and
    each neighbouring pair of them has its LCA inside the subtree while a pair reaching outside
    has it above. The LCA of two neighbouring segments is the gap before the second (inside a
    lift's run every gap lies below the lift). So items below a node minus those gaps below it
    counts every triangle once.
    """
    starts = np.concatenate([np.flatnonzero(~removed), lift_first])
    starts = starts[gap_depth[starts] >= 0]
    per_node = (np.bincount(s_leaf[~removed], minlength=topo.n)
                + np.bincount(lift_node, minlength=topo.n)
                - np.bincount(gap_node[starts], minlength=topo.n))
    return topo.subtree_sum(per_node)


def _collapse(topo, leaf_count, refs_at, distinct, params):
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


# ---------------------------------------------------------------------------------------------
# The post-pass

def compact_tree(tree, triangles_count: int, mode: str = "compressed", tau_occu: float | None = None,
                 tau_freq: float | None = None, refs_per_node: int | None = None,
                 refs_per_path: int | None = -1, progress=None, device=None,
                 **options) -> CompactTree:
    """Rewrite a standard kd-tree (core.accel.kdtree.KDTree) in the compact layout of `mode`.

    `refs_per_path=-1` keeps the mode's default (8 for `compressed`, unlimited for `choi`); None means
    unlimited. Other CompactParams fields (min_refs, collapse, elide_empty, leaf16) may be
    overridden by keyword. `progress(fraction, message)` is called after each step.
    `device`: an OpenCL device (a core.accel.device.DeviceContext, such as the
    core.accel.binned.BinnedBuilder that built the tree, or a core.opencl.select_device
    spec) that runs the heavy steps as kernels (core/accel/compact_cl.py) for trees in the
    builders' order; the result is the same, bit for bit. None: numpy only.
    """
    started = time.perf_counter()
    overrides = dict(tau_occu=tau_occu, tau_freq=tau_freq, refs_per_node=refs_per_node, **options)
    params = compact_params(mode, **overrides)
    if refs_per_path != -1:
        params = replace(params, refs_per_path=refs_per_path)
    report = progress or (lambda fraction, message: None)
    triangles_count = int(triangles_count)
    if len(tree.leaf_indices) and int(tree.leaf_indices.max()) >= triangles_count:
        raise ValueError("the tree refers to triangles beyond triangles_count")

    if params == compact_params("standard"):
        out = _standard_reencoded(tree, triangles_count, params)
        if out is not None:
            out.stats["compact_seconds"] = time.perf_counter() - started
            report(1.0, f"compact (standard): {len(out.nodes)} nodes, {out.nbytes} bytes")
            return out

    if device is not None:
        parts = compact_on_device(device, tree, triangles_count, params,
                                  _leaf_shift(triangles_count), report)
        if parts is not None:
            return _finish(tree, params, *parts, started, report)

    topo = _Topology(tree)
    ref_leaf, ref_tri = topo.leaf_references(tree)
    reference_count = len(ref_tri)
    # Sorted by (triangle, preorder of the leaf): sorting the keys themselves and decoding
    # them is cheaper than an argsort and two gathers (equal keys are equal references).
    key = np.sort(ref_tri * topo.n + topo.pre[ref_leaf])
    del ref_leaf, ref_tri
    node_at_pre = np.empty(topo.n, np.int64)
    node_at_pre[topo.pre] = np.arange(topo.n)
    s_tri, s_leaf = np.divmod(key, topo.n)
    s_leaf = node_at_pre[s_leaf]
    del key, node_at_pre
    report(0.2, "compact: tree decoded")

    lifting = params.refs_per_node > 0 and (params.refs_per_path is None
                                            or params.refs_per_path > 0)
    if lifting or params.collapse:
        gap_node, gap_depth = _neighbour_lcas(topo, s_leaf, s_tri)
    if lifting:
        per_depth = _lift_candidates(topo, s_leaf, s_tri, gap_node, gap_depth, params)
        removed, lift_node, lift_tri, refs_at, lift_first = _select_lifts(
            topo, per_depth, len(s_tri), params)
        del per_depth
    else:
        removed = np.zeros(len(s_tri), bool)
        lift_node = lift_tri = lift_first = np.zeros(0, np.int64)
        refs_at = np.zeros(topo.n, np.int64)
    report(0.5, f"compact: {len(lift_tri)} triangle references lifted")

    # 2. Collapse subtrees (the triangles lifted inside a subtree come back into its leaf).
    if params.collapse:
        distinct = _distinct_below(topo, removed, s_leaf, gap_node, gap_depth, lift_node,
                                   lift_first)
        del gap_node, gap_depth
    keep_ref = ~removed
    k_leaf, k_tri = s_leaf[keep_ref], s_tri[keep_ref]
    del s_leaf, s_tri, removed, keep_ref
    leaf_count = np.bincount(k_leaf, minlength=topo.n)
    if params.collapse:
        collapsed = _collapse(topo, leaf_count, refs_at, distinct, params)
    else:
        collapsed = np.zeros(topo.n, bool)
    report(0.7, f"compact: {int(collapsed.sum())} subtrees collapsed")

    # Which nodes survive, and the leaf each removed node's contents go to.
    dead, owner = _owners(topo, collapsed)
    is_final_leaf = ~dead & (topo.is_leaf | collapsed)
    lift_gone = dead[lift_node] | collapsed[lift_node]
    item_leaf = np.concatenate([owner[k_leaf], owner[lift_node[lift_gone]]])
    item_tri = np.concatenate([k_tri, lift_tri[lift_gone]])
    lift_node, lift_tri = lift_node[~lift_gone], lift_tri[~lift_gone]
    del k_leaf, k_tri
    key = np.unique(item_leaf * np.int64(triangles_count) + item_tri)
    item_leaf, item_tri = key // triangles_count, key % triangles_count
    del key
    final_count = np.bincount(item_leaf, minlength=topo.n)
    refs_at = np.bincount(lift_node, minlength=topo.n)
    laid_out = _layout(topo, params, is_final_leaf, dead, final_count, item_tri, lift_node,
                       lift_tri, refs_at, triangles_count)
    return _finish(tree, params, topo.n, reference_count, int((collapsed & ~dead).sum()),
                   laid_out, _max_refs_on_path(topo, dead, refs_at), len(item_tri), lift_node,
                   lift_tri, started, report)


def _finish(tree, params, standard_nodes, reference_count, collapsed_subtrees, laid_out,
            max_path, item_count, lift_node, lift_tri, started, report) -> CompactTree:
    """The CompactTree and its stats (both the numpy and the kernel path): `laid_out` is
    _layout's result, item_count the final leaves' references, lift_node / lift_tri the lifts
    that stay."""
    nodes, leaf32, leaf16, shift, kinds, leaf_stats = laid_out
    per_node = run_lengths(lift_node)
    out = CompactTree(nodes, leaf32, leaf16, tree.bounds.astype(np.float32), shift, params)
    out.stats = {
        "mode": params.mode,
        "nodes": len(nodes),
        "node_kinds": kinds,
        "standard_nodes": standard_nodes,
        "references_standard": reference_count,
        "leaf_references": int(item_count),
        "references_removed": reference_count - int(item_count),
        "inner_references": int(len(lift_tri)),
        "lifted_triangles": distinct_count(lift_tri),
        "tref_nodes": int(len(per_node)),
        "nodes_with_two_refs": int((per_node > 1).sum()),
        "max_refs_on_path": max_path,
        "collapsed_subtrees": collapsed_subtrees,
        **leaf_stats,
        "bytes": out.nbytes,
        "compact_seconds": time.perf_counter() - started,
    }
    report(1.0, f"compact ({params.mode}): {len(nodes)} nodes, {out.nbytes} bytes")
    return out


def _owners(topo, collapsed):
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


def _max_refs_on_path(topo, dead, refs_at) -> int:
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
        _pass_down(topo, k, on_path, on_path, refs_at)
    return max_path


def _leaf_shift(triangles_count: int) -> int:
    """Shift of a 16-bit leaf's base B, so that B << shift reaches every triangle index."""
    return max(0, (max(triangles_count, 1) - 1).bit_length() - LEAF16_INDEX_BITS)


def _standard_reencoded(tree, triangles_count, params):
    """Mode standard without decoding the topology, for a tree in the builder's own order:
    breadth-first with the k-th inner node's children at 1 + 2k, leaf lists in node order,
    each ascending. The general path lays such a tree out node for node the same way, so only
    the words are re-encoded (the same arrays and stats). None for any other tree."""
    nodes, lists = tree.nodes, tree.leaf_indices
    word0 = nodes[:, 0]
    is_leaf = PLAIN_TAG.get(word0) == LEAF_TAG
    field = PLAIN_FIELD.get(word0).astype(np.int64)
    inner = np.flatnonzero(~is_leaf)
    if len(nodes) != 1 + 2 * len(inner) or len(nodes) - 1 > MAX_GROUP_INDEX:
        return None
    if not np.array_equal(field[inner], 1 + 2 * np.arange(len(inner))):
        return None
    leaves = np.flatnonzero(is_leaf)
    count = field[leaves]
    nonempty = count > 0
    offset = exclusive_cumsum(count)
    if (int(offset[-1]) != len(lists) or (count > MAX_LEAF32_COUNT).any()
            or not np.array_equal(nodes[leaves[nonempty], 1], offset[:-1][nonempty])):
        return None
    if len(lists) > 1:
        ascending = np.diff(lists.astype(np.int64)) > 0
        starts = offset[1:-1]
        ascending[starts[(starts > 0) & (starts < len(lists))] - 1] = True   # across leaves
        if not ascending.all():
            return None
    out_nodes = np.empty_like(nodes)
    out_nodes[inner, 0] = (TAG.put(PLAIN_TAG.get(word0[inner]))
                           | INNER_GROUP.put(field[inner]).astype(np.uint32))
    out_nodes[inner, 1] = nodes[inner, 1]
    out_nodes[leaves, 0] = (TAG.put(LEAF_TAG) | LEAF32_COUNT.put(count)).astype(np.uint32)
    out_nodes[leaves, 1] = np.where(nonempty, offset[:-1], 0)
    shift = _leaf_shift(triangles_count)
    out = CompactTree(out_nodes, lists.astype(np.uint32), np.zeros(0, np.uint16),
                      tree.bounds.astype(np.float32), shift, params)
    leaf_refs = len(lists)
    out.stats = {
        "mode": params.mode, "nodes": len(nodes),
        "node_kinds": {"inner": len(inner), "tref": 0, "leaf": len(leaves)},
        "standard_nodes": len(nodes), "references_standard": leaf_refs,
        "leaf_references": leaf_refs, "references_removed": 0, "inner_references": 0,
        "lifted_triangles": 0, "tref_nodes": 0, "nodes_with_two_refs": 0,
        "max_refs_on_path": 0, "collapsed_subtrees": 0,
        "leaves": len(leaves), "empty_leaves_stored": int((~nonempty).sum()),
        "empty_leaves_elided": 0, "leaves_16bit": 0, "leaves_32bit": int(nonempty.sum()),
        "leaf16_share": 0.0, "leaf_shift": shift, "bytes": out.nbytes,
    }
    return out


def _layout(topo, params, is_final_leaf, dead, final_count, item_tri, lift_node, lift_tri,
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
    shift = _leaf_shift(triangles_count)
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
