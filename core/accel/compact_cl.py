"""core/accel/compact.py's compaction in OpenCL kernels (kernels/build/compact.cl), for trees in
the builders' order: breadth-first with the k-th inner node's children at 1 + 2k, leaf lists in
node order (what core/accel/kdtree.py and kdtree_cl.py both build). Each level of such a tree is
a contiguous range of nodes whose inner nodes' children are, pair by pair, the next level, so
every per-level step is one kernel over a range. The result is compact_tree's, bit for bit:
the kernels use its float64 arithmetic and numpy's summation order; steps that need the whole
tree in order (the greedy choice of lifts, numbering the nodes) stay on the host, over level
ranges. docs/kdtree_native.md.
"""
from __future__ import annotations

import numpy as np

from ..layout import LEAF_TAG, PLAIN_FIELD, PLAIN_TAG
from . import compact as host

KERNEL_FILES = ("build/fp64.cl", "build/compact.cl")


def _exclusive(counts) -> np.ndarray:
    out = np.zeros(len(counts) + 1, np.int64)
    np.cumsum(counts, out=out[1:])
    return out


class DeviceTopology:
    """compact.py _Topology's arrays on the device, for a tree in the builders' order (`shape`:
    its host part, compact._Topology.shape_only)."""

    def __init__(self, c, tree, shape):
        b, k = c.b, c.k
        u4 = np.uint32
        nodes = np.ascontiguousarray(tree.nodes, np.uint32)
        n = len(nodes)
        self.n = n
        self.is_leaf = shape.is_leaf
        ranges = shape.ranges
        self.nodes = b._buffer(nodes)
        self.area = b._buffer(nbytes=8 * n)
        self.depth = b._buffer(nbytes=n)
        self.parent = b._buffer(nbytes=4 * n)
        self.stops = b._buffer(nbytes=n)
        self.size = b._buffer(nbytes=4 * n)
        self.nonempty = b._buffer(nbytes=4 * n)
        self.pre = b._buffer(np.zeros(1, u4)) if n == 1 else b._buffer(nbytes=4 * n)
        widest = max(e - a for a, e in ranges)
        cells = [b._buffer(nbytes=24 * widest), b._buffer(nbytes=24 * widest)]
        bounds = b._buffer(np.ascontiguousarray(tree.bounds, np.float32).reshape(-1))
        k["topo_root"](b.queue, (1,), None, bounds, cells[0], self.area, self.depth,
                       self.parent, self.stops)
        for level, (first, end) in enumerate(ranges):
            c._run(b, k["topo_down"], end - first, self.nodes, cells[level % 2],
                   cells[(level + 1) % 2], self.area, self.depth, self.parent, self.stops,
                   u4(first), u4(end), u4(level))
            b.heartbeat()
        del cells
        for first, end in reversed(ranges):
            c._run(b, k["topo_up"], end - first, self.nodes, self.size, self.nonempty, u4(first),
                   u4(end))
            b.heartbeat()
        b._cl.enqueue_fill_buffer(b.queue, self.pre, np.uint32(0), 0, 4)
        for first, end in ranges:
            c._run(b, k["topo_pre"], end - first, self.nodes, self.size, self.pre, u4(first), u4(end))
            b.heartbeat()
        self.max_depth = len(ranges) - 1
        self.node_at_pre = b._buffer(nbytes=4 * n)
        self.climb = b._buffer(nbytes=16 * n)
        self.walk = b._buffer(nbytes=16 * n)
        c._run(b, k["preorder_records"], n, self.pre, self.size, self.parent, self.depth,
               self.area, self.nonempty, self.stops, self.node_at_pre, self.climb, self.walk,
               u4(n))


class CompactorCL:
    """Kernel compaction on a kd-tree builder's device (core.accel.kdtree_cl.KDTreeBuilderCL)."""

    def __init__(self, builder, local_size=None):
        from ..opencl import kernel_source
        self.b = builder
        # Many small work-items: work-groups of them (PoCL pays per work-group).
        self.local_size = local_size or (256 if builder.is_cpu else 64)
        self.k = builder._programs.kernels(kernel_source(KERNEL_FILES),
                                           ["-DKDTRACE_SOFT_FP64"] if builder.soft_fp64 else [])

    def _run(self, b, kernel, count, *args):
        from .kdtree_cl import PIECE_ITEMS
        b._run(kernel, count, *args, local_size=self.local_size, piece=PIECE_ITEMS)

    def sorted_references(self, topo, tree, triangle_count):
        """References sorted by (triangle, preorder of the leaf): (s_leaf, s_tri, tri_first)
        buffers and the reference count."""
        b, k = self.b, self.k
        u4 = np.uint32
        leaves = np.flatnonzero(topo.is_leaf).astype(u4)
        R = len(tree.leaf_indices)
        d_leaves = b._buffer(leaves)
        d_lists = b._buffer(np.ascontiguousarray(tree.leaf_indices, u4))
        counts = np.bincount(tree.leaf_indices, minlength=triangle_count)
        tri_first = _exclusive(counts).astype(u4)
        d_first = b._buffer(tri_first)
        per_triangle = self.zeros(4 * max(triangle_count, 1))
        s_leaf, s_pre, s_tri = (b._buffer(nbytes=4 * max(R, 1)) for _ in range(3))
        self._run(b, k["refs_scatter"], len(leaves), topo.nodes, d_leaves, d_lists, d_first,
               per_triangle, topo.pre, s_leaf, s_pre, u4(len(leaves)))
        self._run(b, k["refs_sort"], triangle_count, d_first, s_leaf, s_pre, s_tri, u4(triangle_count))
        return s_leaf, s_pre, s_tri, d_first, tri_first, R

    def neighbour_lcas(self, topo, s_pre, s_tri, R):
        b, k = self.b, self.k
        gap_node, gap_pre, gap_depth = (b._buffer(nbytes=4 * (R + 1)) for _ in range(3))
        self._run(b, k["neighbour_lcas"], R + 1, s_pre, s_tri, topo.climb, gap_node, gap_pre,
                  gap_depth, np.uint32(R))
        return gap_node, gap_pre, gap_depth

    def lift_candidates(self, topo, d_first, triangle_count, s_pre, gap_pre, gap_depth, R,
                        params):
        """compact.py _lift_candidates: per depth (node, triangle, r, first, end) arrays."""
        b, k = self.b, self.k
        u4 = np.uint32
        scratch = [b._buffer(nbytes=4 * (R + 1)) for _ in range(3)]
        taus = (np.float64(params.tau_occu).view(np.uint64), np.float64(params.tau_freq).view(np.uint64))
        capacity = max(R, 1024)
        while True:
            out = b._buffer(nbytes=24 * capacity)
            used = b._buffer(np.zeros(1, u4))
            self._run(b, k["lift_candidates"], triangle_count, d_first, s_pre, gap_pre, gap_depth,
                      topo.nodes, topo.climb, topo.walk, *scratch, out, used, topo.node_at_pre,
                      u4(capacity), u4(triangle_count), u4(params.min_refs), *taus)
            total = int(b._read(used, u4, 1)[0])
            if total <= capacity:
                break
            capacity = total          # more candidates than room: again with room for all
        found = b._read(out, u4, (total, 6))
        # By depth (numpy's stable sort of a uint8 key is a radix sort), in columns per depth.
        found = found[np.argsort(found[:, 0].astype(np.uint8), kind="stable")]
        bounds = np.searchsorted(found[:, 0], np.arange(topo.max_depth + 2))
        per_depth = [None] * (topo.max_depth + 1)
        for d in range(topo.max_depth + 1):
            if bounds[d] < bounds[d + 1]:
                part = found[bounds[d]:bounds[d + 1]].astype(np.int64)
                per_depth[d] = tuple(part[:, j] for j in range(1, 6))
        return per_depth

    def collapse(self, topo, shape, removed, host_s_leaf, host_gap_node, host_gap_depth,
                 lift_node, lift_first, refs_at, params):
        """compact.py _distinct_below and _collapse: the collapsed nodes (host bool array)."""
        b, k = self.b, self.k
        u4 = np.uint32
        n = topo.n
        b.heartbeat()
        kept = ~removed
        kept_leaf = host_s_leaf[kept]
        counts = np.bincount(kept_leaf, minlength=n)
        starts = np.concatenate([np.flatnonzero(kept), lift_first])
        starts = starts[host_gap_depth[starts] >= 0]
        values = (counts + np.bincount(lift_node, minlength=n)
                  - np.bincount(host_gap_node[starts], minlength=n))
        per_node = b._buffer(values.astype(np.int32))
        leaf_count = b._buffer(counts.astype(u4))
        b.heartbeat()
        for first, end in reversed(shape.ranges):
            self._run(b, k["subtree_sums"], end - first, topo.nodes, per_node, u4(first), u4(end))
            b.heartbeat()
        d_refs_at = b._buffer(refs_at.astype(u4))
        cost = b._buffer(nbytes=8 * n)
        collapsed = b._buffer(nbytes=n)
        kt = np.float64(params.traversal_cost).view(np.uint64)
        ki = np.float64(params.intersection_cost).view(np.uint64)
        for first, end in reversed(shape.ranges):
            self._run(b, k["collapse"], end - first, topo.nodes, topo.area, leaf_count, d_refs_at,
                      per_node, cost, collapsed, u4(first), u4(end), kt, ki)
            b.heartbeat()
        return collapsed

    def zeros(self, nbytes):
        buffer = self.b._buffer(nbytes=max(int(nbytes), 4))
        self.b._cl.enqueue_fill_buffer(self.b.queue, buffer, np.uint8(0), 0, max(int(nbytes), 4))
        return buffer

    def gather(self, buffer, at, dtype=np.uint8):
        """buffer[at] on the host (a few values of a device array)."""
        b, k = self.b, self.k
        if not len(at):
            return np.zeros(0, dtype)
        if dtype == np.uint8:
            values = b._read(buffer, np.uint8, int(np.max(at)) + 1)   # small arrays only
            return values[at]
        out = b._buffer(nbytes=4 * len(at))
        self._run(b, k["gather_values"], len(at), buffer, b._buffer(np.asarray(at, np.uint32)),
                  out, np.uint32(len(at)))
        return b._read(out, np.uint32, len(at)).astype(np.int64)

    def owners(self, topo, shape, collapsed):
        """compact.py _owners: (dead, owner) device buffers."""
        b, k = self.b, self.k
        u4 = np.uint32
        n = topo.n
        dead = self.zeros(n)
        owner = self.zeros(4 * n)
        for first, end in shape.ranges:
            self._run(b, k["owners"], end - first, topo.nodes, collapsed, dead, owner,
                      u4(first), u4(end))
            b.heartbeat()
        return dead, owner

    def scan(self, values, n, out=None):
        """Exclusive prefix sum of n uints (into `out`, or in place); returns the total."""
        b, k = self.b, self.k
        u4 = np.uint32
        block = 4096
        blocks = max(1, -(-n // block))
        sums = b._buffer(nbytes=8 * blocks)
        b._run(k["block_sums"], blocks, values, sums, u4(n), u4(block), local_size=1)
        offsets = _exclusive(b._read(sums, np.uint64, blocks).astype(np.int64))
        b._run(k["block_scan"], blocks, values, b._buffer(offsets[:-1].astype(np.uint64)),
               values if out is None else out, u4(n), u4(block), local_size=1)
        return int(offsets[-1])

    def count_collapsed(self, topo, collapsed, dead) -> int:
        n = topo.n
        c = self.b._read(collapsed, np.uint8, n).astype(bool)
        d = self.b._read(dead, np.uint8, n).astype(bool)
        return int((c & ~d).sum())

    def items(self, topo, d_removed, s_leaf, s_tri, owner, R, extra_owner, extra_tri):
        """Every final leaf's triangles (kept references and the lifts of removed nodes),
        sorted, without repeats, in buckets by node: device buffers (count per node, bucket
        start per node, the buckets) and the number of items."""
        b, k = self.b, self.k
        u4 = np.uint32
        n = topo.n
        per_owner = self.zeros(4 * (n + 1))
        self._run(b, k["items_count"], R, d_removed, s_leaf, owner, per_owner, u4(R))
        # The lifts of removed nodes go first in their owner's bucket, then the references.
        extra_count = np.bincount(extra_owner, minlength=1)
        owners_used = np.flatnonzero(extra_count)
        cursor = self.zeros(4 * n)
        if len(owners_used):
            self._run(b, k["put_values"], len(owners_used), b._buffer(owners_used.astype(u4)),
                      b._buffer(extra_count[owners_used].astype(u4)), cursor, u4(len(owners_used)))
            self._run(b, k["add_values"], len(owners_used), b._buffer(owners_used.astype(u4)),
                      b._buffer(extra_count[owners_used].astype(u4)), per_owner, u4(len(owners_used)))
        owner_first = b._buffer(nbytes=4 * (n + 1))
        total = self.scan(per_owner, n + 1, owner_first)
        items = b._buffer(nbytes=4 * max(total, 1))
        if len(owners_used):
            by_owner = np.sort(extra_owner)
            rank = np.arange(len(by_owner)) - np.searchsorted(by_owner, by_owner)
            first = self.gather(owner_first, by_owner, np.uint32)
            self._run(b, k["put_values"], len(by_owner), b._buffer((first + rank).astype(u4)),
                      b._buffer(extra_tri[np.argsort(extra_owner, kind="stable")].astype(u4)),
                      items, u4(len(by_owner)))
        self._run(b, k["items_scatter"], R, d_removed, s_leaf, s_tri, owner, owner_first, cursor,
                  items, u4(R))
        b.heartbeat()
        kept = b._buffer(nbytes=4 * (n + 1))
        self._run(b, k["items_unique"], n, owner_first, items, kept, u4(n))
        # The buckets closed up: final lists one after another in node order.
        item_first = b._buffer(nbytes=4 * (n + 1))
        item_count = self.scan(kept, n, item_first)
        final_items = b._buffer(nbytes=4 * max(item_count, 1))
        self._run(b, k["close_buckets"], n, owner_first, kept, item_first, items, final_items,
                  u4(n))
        return kept, item_first, final_items, item_count

    def layout(self, topo, shape, params, dead, collapsed, final_count, item_first, items,
               lift_node, lift_tri, triangles_count):
        """compact.py _layout on the device: (nodes, leaf_index32, leaf_index16, leaf_shift,
        node kinds, leaf stats)."""
        from .compact import (MAX_GROUP_INDEX, MAX_LEAF32_COUNT, _leaf_shift, _run_starts)
        from ..layout import LEAF16_INDEX_BITS
        b, k = self.b, self.k
        u4 = np.uint32
        n = topo.n
        classes = b._buffer(nbytes=n)
        self._run(b, k["layout_classes"], n, topo.nodes, dead, collapsed, final_count, classes,
                  u4(n))
        refs_at = self.zeros(4 * n)
        nodes_used, per_node = np.unique(lift_node, return_counts=True)
        if len(nodes_used):
            self._run(b, k["put_values"], len(nodes_used), b._buffer(nodes_used.astype(u4)),
                      b._buffer(per_node.astype(u4)), refs_at, u4(len(nodes_used)))
        elided = self.zeros(n)
        group_size = b._buffer(nbytes=4 * n)
        self._run(b, k["layout_groups"], n, topo.nodes, classes, refs_at, elided, group_size,
                  u4(n), u4(bool(params.elide_empty)))
        total = 1 + self.scan(group_size, n)              # now each live inner node's group - 1
        b.heartbeat()
        if total - 1 > MAX_GROUP_INDEX:
            raise ValueError(f"compact kd-tree too large: {total} nodes (at most {MAX_GROUP_INDEX})")
        shift = _leaf_shift(triangles_count)
        count32, count16, base_of = (b._buffer(nbytes=4 * n) for _ in range(3))
        self._run(b, k["layout_leaves"], n, classes, elided, final_count, item_first, items,
                  count32, count16, base_of, u4(n), u4(shift), u4(bool(params.leaf16)),
                  u4(LEAF16_INDEX_BITS))
        off32, off16 = b._buffer(nbytes=4 * n), b._buffer(nbytes=4 * n)
        total32 = self.scan(count32, n, off32)
        total16 = self.scan(count16, n, off16)
        out = b._buffer(nbytes=8 * total)
        index32 = b._buffer(nbytes=4 * max(total32, 1))
        index16 = b._buffer(nbytes=2 * max(total16, 2))
        new_index = b._buffer(nbytes=4 * n)
        self._run(b, k["layout_places"], n, topo.nodes, classes, elided, refs_at, group_size,
                  new_index, out, u4(n))
        b.heartbeat()
        self._run(b, k["layout_words"], n, topo.nodes, classes, elided, refs_at, group_size,
                  final_count, item_first, items, count16, off32, off16, base_of, new_index, out,
                  index32, index16, u4(n), u4(shift))
        if len(lift_node):
            order = np.lexsort((lift_tri, lift_node))
            node_sorted = lift_node[order]
            first = _run_starts(node_sorted)
            slot = np.arange(len(order)) - np.repeat(first, np.diff(np.append(first, len(order))))
            self._run(b, k["layout_slots"], len(order), b._buffer(node_sorted.astype(u4)),
                      b._buffer(lift_tri[order].astype(u4)), b._buffer(slot.astype(u4)),
                      group_size, out, u4(len(order)))
        block = 4096
        blocks = max(1, -(-n // block))
        counters = b._buffer(nbytes=32 * blocks)
        b._run(k["layout_stats"], blocks, classes, elided, final_count, count16, counters, u4(n),
               u4(block), local_size=1)
        per_block = b._read(counters, u4, (blocks, 8)).astype(np.int64)
        stored, empty, elided_count, leaves16, leaves32, inner_count = (
            int(x) for x in per_block[:, :6].sum(0))
        most = int(per_block[:, 6].max())
        if most > MAX_LEAF32_COUNT:
            raise ValueError("a leaf holds too many triangles for the 32-bit list's count")
        nodes = b._read(out, u4, (total, 2))
        leaf32 = b._read(index32, u4, total32)
        leaf16 = b._read(index16, np.uint16, total16)
        kinds = {"inner": inner_count, "tref": int(len(nodes_used)), "leaf": stored}
        assert sum(kinds.values()) == total
        leaf_stats = {
            "leaves": stored,
            "empty_leaves_stored": empty,
            "empty_leaves_elided": elided_count,
            "leaves_16bit": leaves16,
            "leaves_32bit": leaves32,
            "leaf16_share": float(leaves16 / max(leaves16 + leaves32, 1)),
            "leaf_shift": shift,
        }
        return nodes, leaf32, leaf16, shift, kinds, leaf_stats

    def max_refs_on_path(self, topo, shape, dead, lift_node) -> int:
        b, k = self.b, self.k
        u4 = np.uint32
        n = topo.n
        refs_at = self.zeros(4 * n)
        nodes_used, per_node = np.unique(lift_node, return_counts=True)
        if len(nodes_used):
            self._run(b, k["put_values"], len(nodes_used), b._buffer(nodes_used.astype(u4)),
                      b._buffer(per_node.astype(u4)), refs_at, u4(len(nodes_used)))
        on_path = self.zeros(4 * n)
        most = self.zeros(4)
        for first, end in shape.ranges:
            self._run(b, k["path_refs"], end - first, topo.nodes, dead, refs_at, on_path, most,
                      u4(first), u4(end))
            b.heartbeat()
        return int(b._read(most, u4, 1)[0])


def compactor_for(builder) -> CompactorCL:
    """The builder's compactor (made once per builder)."""
    c = getattr(builder, "_compactor", None)
    if c is None:
        c = builder._compactor = CompactorCL(builder)
    return c


def compact_on_device(device, tree, triangles_count, params, report, started):
    """compact_tree's lifting, collapse and leaf items in kernels, the numbering and stats on
    the host (compact._finish). None when the tree is not in the builders' order."""
    from .kdtree_cl import builder_for
    shape = host._Topology.shape_only(tree)
    if shape is None:
        return None
    builder = builder_for(device)
    c = compactor_for(builder)
    b, k = c.b, c.k
    report = b.reporting(report)
    u4 = np.uint32
    n = shape.n
    report(0.0, f"compact ({params.mode}): {n:,} nodes")
    topo = DeviceTopology(c, tree, shape)
    report(0.1, "compact: topology")
    s_leaf, s_pre, s_tri, d_first, tri_first, R = c.sorted_references(topo, tree, triangles_count)
    report(0.2, "compact: tree decoded")

    lifting = params.refs_per_node > 0 and (params.refs_per_path is None
                                            or params.refs_per_path > 0)
    if lifting or params.collapse:
        gap_node, gap_pre, gap_depth = c.neighbour_lcas(topo, s_pre, s_tri, R)
        report(0.3, "compact: neighbouring references' common ancestors")
    if lifting:
        per_depth = c.lift_candidates(topo, d_first, triangles_count, s_pre, gap_pre, gap_depth,
                                      R, params)
        removed, lift_node, lift_tri, refs_at, lift_first = host._select_lifts(
            shape, per_depth, R, params, b.heartbeat)
        del per_depth
    else:
        removed = np.zeros(R, bool)
        lift_node = lift_tri = lift_first = np.zeros(0, np.int64)
        refs_at = np.zeros(n, np.int64)
    report(0.5, f"compact: {len(lift_tri)} triangle references lifted")

    d_removed = b._buffer(removed.astype(np.uint8))
    if params.collapse:
        collapsed = c.collapse(topo, shape, removed, b._read(s_leaf, u4, R),
                               b._read(gap_node, u4, R + 1), b._read(gap_depth, np.int32, R + 1),
                               lift_node, lift_first, refs_at, params)
    else:
        collapsed = c.zeros(n)
    report(0.7, "compact: subtrees collapsed")

    dead, owner = c.owners(topo, shape, collapsed)
    report(0.75, "compact: owners of the collapsed subtrees' contents")
    gone = c.gather(dead, lift_node).astype(bool) | c.gather(collapsed, lift_node).astype(bool)
    final_count, item_first, items, item_count = c.items(
        topo, d_removed, s_leaf, s_tri, owner, R, c.gather(owner, lift_node[gone], np.uint32),
        lift_tri[gone])
    lift_node, lift_tri = lift_node[~gone], lift_tri[~gone]
    report(0.85, f"compact: {item_count:,} leaf references")
    laid_out = c.layout(topo, shape, params, dead, collapsed, final_count, item_first, items,
                        lift_node, lift_tri, triangles_count)
    max_path = c.max_refs_on_path(topo, shape, dead, lift_node)
    collapsed_subtrees = c.count_collapsed(topo, collapsed, dead)
    return host._finish(tree, params, n, R, collapsed_subtrees, laid_out, max_path, item_count,
                        lift_node, lift_tri, started, report)
