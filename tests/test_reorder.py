"""core/accel/reorder.py: the treelet node order is the same tree in the same format.

Checked with the float64 reference traversal of tests/test_kdtree_compact.py (independent of the
kernels): the reordered tree passes validate_compact, keeps its depth, nodes and list entries,
and gives the same hits (any hit too) as the breadth-first tree; its groups sit nearer their
nodes. The kernels run on it in every tracer test (Tracer.load reorders every tree)."""
from __future__ import annotations

import numpy as np
import pytest

from kdtrace.core.accel.compact import MODES, compact_tree
from kdtrace.core.accel.reorder import treelet_order
from kdtrace.core.accel.validate import validate_compact
from kdtrace.core.layout import (INNER_EMPTY_ABOVE, INNER_EMPTY_BELOW, INNER_GROUP, INNER_REF,
                                 LEAF_TAG, TAG)
from tests.test_kdtree_compact import random_rays, scene, trace_compact


def group_distance(ct):
    """Mean distance in nodes from an inner node to its group (T-reference slots excluded:
    their first word is a triangle index)."""
    w = ct.nodes[:, 0].astype(np.int64)
    level, dist = np.zeros(1, np.int64), []
    while len(level):
        inner = level[TAG.get(w[level]) != LEAF_TAG]
        g = INNER_GROUP.get(w[inner])
        dist.append(g - inner)
        below = g + INNER_REF.get(w[inner])
        above = below + 1 - INNER_EMPTY_BELOW.get(w[inner])
        level = np.concatenate([below[INNER_EMPTY_BELOW.get(w[inner]) == 0],
                                above[INNER_EMPTY_ABOVE.get(w[inner]) == 0]])
    return float(np.concatenate(dist).mean())


@pytest.mark.parametrize("height", [1, 3, 5])
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("name", ["bunny", "architecture"])
def test_treelet_order_is_the_same_tree(name, mode, height):
    corners, tree = scene(name)[2:]
    ct = compact_tree(tree, len(corners), mode)
    rt = treelet_order(ct, height)
    depth = validate_compact(rt.nodes, rt.leaf_index32, rt.leaf_index16, rt.bounds,
                             rt.leaf_shift, len(corners))
    assert depth == validate_compact(ct.nodes, ct.leaf_index32, ct.leaf_index16, ct.bounds,
                                     ct.leaf_shift, len(corners))
    assert rt.nodes.shape == ct.nodes.shape and rt.leaf_shift == ct.leaf_shift
    assert np.array_equal(np.sort(rt.leaf_index32), np.sort(ct.leaf_index32))
    assert np.array_equal(np.sort(rt.leaf_index16), np.sort(ct.leaf_index16))
    assert not np.array_equal(rt.nodes, ct.nodes)
    origins, directions = random_rays(corners, 3000, seed=height)
    for any_hit in (False, True):
        ref = trace_compact(ct, corners, origins, directions, any_hit=any_hit)
        got = trace_compact(rt, corners, origins, directions, any_hit=any_hit)
        assert np.isfinite(ref[0]).mean() > 0.3
        for a, b in zip(ref, got):
            assert np.array_equal(a, b)


def test_treelets_keep_groups_near_their_nodes():
    corners, tree = scene("bunny")[2:]
    ct = compact_tree(tree, len(corners), "compressed")
    assert group_distance(treelet_order(ct)) < 0.05 * group_distance(ct)
    with pytest.raises(ValueError):
        treelet_order(ct, 0)


def test_keys_sorted_in_pieces_give_the_order_of_one_sort(monkeypatch):
    """treelet_order sorts its keys a piece at a time (so that Esc is heard between pieces):
    the same tree as one sort, and the heartbeat called at every piece."""
    from kdtrace.core.accel import reorder
    corners, tree = scene("architecture")[2:]
    ct = compact_tree(tree, len(corners), "compressed")
    whole = treelet_order(ct)
    monkeypatch.setattr(reorder, "SORT_PIECE", 64)
    beats = []
    pieces = treelet_order(ct, heartbeat=lambda: beats.append(1))
    assert np.array_equal(whole.nodes, pieces.nodes)
    assert np.array_equal(whole.leaf_index32, pieces.leaf_index32)
    assert np.array_equal(whole.leaf_index16, pieces.leaf_index16)
    inner = int((TAG.get(ct.nodes[:, 0].astype(np.int64)) != LEAF_TAG).sum())
    assert len(beats) > min(inner // 64, 1 << 15)
