"""Lifting, the compaction's first step (core/accel/compact.py, modes `choi` and `compressed`):
which triangles are referenced once at an inner node instead of in many leaves below it, chosen
greedily under the per-node and per-path limits, and the distinct triangles below each node that
the collapse then prices (the numpy twin of kernels/build/compact_lifts.cl;
docs/kdtree_compression.md)."""
from __future__ import annotations

import numpy as np

from .arrays import concat_ranges, run_starts
from .compact_topology import pass_down


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


def neighbour_lcas(topo, s_leaf, s_tri):
    """Gap j lies before sorted reference j: the LCA of the leaves of references j-1 and j when
    they hold the same triangle, and its depth; depth -1 between triangles and at both ends."""
    count = len(s_tri)
    gap_depth = np.full(count + 1, -1, np.int64)
    gap_node = np.zeros(count + 1, np.int64)
    same = np.flatnonzero(s_tri[1:] == s_tri[:-1]) + 1
    gap_node[same] = topo.lca(s_leaf[same - 1], s_leaf[same])
    gap_depth[same] = topo.depth[gap_node[same]]
    return gap_node, gap_depth


def lift_candidates(topo, s_leaf, s_tri, gap_node, gap_depth, params):
    """Every (inner node, triangle) pair that passes both thresholds, per depth.

    s_leaf/s_tri: references sorted by (triangle, preorder of the leaf), so that the references of
    a triangle inside any subtree are one contiguous run. The run of t below a node at depth d is
    a maximal stretch of t's references whose gaps (`neighbour_lcas`) lie at depth >= d: it
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


def select_lifts(topo, per_depth, ref_count, params):
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
            pass_down(topo, d, on_path, on_path, refs_at)
    lift_node, lift_tri, lift_first = (np.concatenate(part) if part else np.zeros(0, np.int64)
                                       for part in (lift_node, lift_tri, lift_first))
    return removed, lift_node, lift_tri, refs_at, lift_first


def distinct_below(topo, removed, s_leaf, gap_node, gap_depth, lift_node, lift_first):
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

