"""core/accel/compact.py's compaction in OpenCL kernels (kernels/build/compact*.cl), for trees in
the builders' order: breadth-first with the k-th inner node's children at 1 + 2k, leaf lists in
node order (what core/accel/kdtree.py and binned.py both build). Each level of such a tree is
a contiguous range of nodes whose inner nodes' children are, pair by pair, the next level, so
every per-level step is one kernel over a range, and the final numbering is a prefix sum in
node order. The result is compact_tree's, bit for bit: the kernels use its float64 arithmetic
and numpy's summation order, and the greedy choice of lifts takes the same lifts in the same
order (choose_lifts). Every array of the size of the tree stays on the device (buffers freed
as soon as their step is done), so that a 10 M-triangle scene fits in a few GB.
docs/kdtree_native.md.
"""
from __future__ import annotations

import numpy as np

from ..layout import (CELL, CLIMB, INNER_GROUP, LAYOUT_COUNTS, LEAF16_INDEX_BITS, LEAF32_COUNT,
                      LIFT_CANDIDATE, LIFT_GROUPED, LIFT_SCRATCH_WORDS, WALK)
from ..opencl import kernel_source
from .arrays import exclusive_cumsum, run_starts
from .device import DeviceContext, device_for

KERNEL_FILES = ("build/common.cl", "build/compact.cl", "build/compact_lifts.cl",
                "build/compact_layout.cl")
U4 = np.uint32
PRIVATE_GAPS = 64         # a triangle with more references keeps its lift stacks in the scratch
TOPO_STACK = 64           # topo_subtrees' stack: more than the levels below its start
TOPO_ROOTS = 4096         # topo_subtrees starts at the first level this wide
# Launches in pieces, so that Esc is seen soon; smaller pieces cost time (the sizes' figures:
# docs/kdtree_native.md, "Progress and Esc").
PIECE_CLIMBS = 1 << 19     # lift_candidates and neighbour_lcas, which walk up the tree for each
                           # triangle or reference: launches of this many
PIECE_NODES = 1 << 22      # the other steps' launches: of this many nodes or references
PIECE_SUBTREE_NODES = 1 << 20  # topo_subtrees' launches: roots of about this many nodes


def program_options() -> list:
    """The -D options of compact*.cl (besides the device's double arithmetic)."""
    return [f"-DPRIVATE_GAPS={PRIVATE_GAPS}u", f"-DTOPO_STACK={TOPO_STACK}"]


class CompactorCL:
    """One compaction's kernel steps on a DeviceContext (device.py): its kernels, launched
    over the tree's levels and ranges; every buffer comes from and goes back to the device's
    pool."""

    def __init__(self, device: DeviceContext, local_size=None):
        self.device = device
        # Many small work-items: work-groups of them (PoCL pays per work-group).
        self.local_size = local_size or (256 if device.is_cpu else 64)
        self.k = device.kernels(kernel_source(KERNEL_FILES), program_options())

    # -- helpers ---------------------------------------------------------------------------
    def run(self, name, count, *args, piece=None):
        """Kernel `name` over count work-items, in pieces of PIECE_NODES unless told."""
        self.device.run(self.k[name], count, *args, local_size=self.local_size,
                        piece=piece or PIECE_NODES)

    def gather(self, buffer, at, kernel="gather_values") -> np.ndarray:
        """buffer[at] on the host (uint32 values; kernel gather_bytes for uchar buffers)."""
        d = self.device
        if not len(at):
            return np.zeros(0, np.int64)
        out = d.buffer(nbytes=4 * len(at))
        self.run(kernel, len(at), buffer, d.buffer(np.asarray(at, U4)), out, U4(len(at)))
        return d.read(out, U4, len(at)).astype(np.int64)

    def set_counts(self, buffer, nodes):
        """buffer[node] += how often node appears in `nodes`."""
        used, counts = np.unique(nodes, return_counts=True)
        self.add_at(buffer, used, counts)

    def add_at(self, buffer, places, values):
        """buffer[places] += values (distinct places)."""
        d = self.device
        if len(places):
            self.run("add_values", len(places), d.buffer(places.astype(U4)),
                     d.buffer(values.astype(U4)), buffer, U4(len(places)))

    def scan(self, values, n, out=None):
        """Exclusive prefix sum of n uints (into `out`, or in place); returns the total."""
        d = self.device
        block = 4096
        blocks = max(1, -(-n // block))
        sums = d.buffer(nbytes=8 * blocks)
        piece = max(1, PIECE_NODES // block)
        d.run(self.k["block_sums"], blocks, values, sums, U4(n), U4(block), local_size=1,
              piece=piece)
        offsets = exclusive_cumsum(d.read(sums, np.uint64, blocks).astype(np.int64))
        d.run(self.k["block_scan"], blocks, values, d.buffer(offsets[:-1].astype(np.uint64)),
              values if out is None else out, U4(n), U4(block), local_size=1, piece=piece)
        return int(offsets[-1])

    # -- steps -----------------------------------------------------------------------------
    def level_ranges(self, nodes, n):
        """The level ranges of a tree in the builders' order (compact_topology.level_ranges),
        or None."""
        d = self.device
        flags = d.buffer(nbytes=4 * n)
        self.run("inner_flags", n, nodes, flags, U4(n))
        inner = self.scan(flags, n)                     # now: inner nodes before each node
        if n != 1 + 2 * inner:
            return None
        bad = d.zeros(4)
        self.run("order_check", n, nodes, flags, bad, U4(n))
        if d.value_at(bad, 0):
            return None
        ranges = [(0, 1)]
        while True:
            a, b = ranges[-1]
            end = 1 + 2 * (inner if b == n else d.value_at(flags, b))
            if end == b:
                return ranges
            ranges.append((b, end))

    def topology(self, nodes, n, ranges, bounds):
        """Per node its preorder number (by node), and by preorder number the climb and walk
        records (compact.cl)."""
        d = self.device
        size, nonempty = d.buffer(nbytes=4 * n), d.buffer(nbytes=4 * n)
        for first, end in reversed(ranges):
            self.run("topo_up", end - first, nodes, size, nonempty, U4(first), U4(end))
            d.heartbeat()
        pre = d.buffer(nbytes=4 * n)
        climb, walk = d.buffer(nbytes=CLIMB.nbytes * n), d.buffer(nbytes=WALK.nbytes * n)
        # Level by level down to the first wide level, then each of its subtrees depth first
        # (topo_subtrees: the records in preorder, one after another).
        wide = next((k for k, (a, e) in enumerate(ranges) if e - a >= TOPO_ROOTS), len(ranges))
        wide = max(wide, len(ranges) - TOPO_STACK)
        widest = max(e - a for a, e in ranges[:wide + 1])
        cells = [d.buffer(nbytes=CELL.nbytes * widest) for _ in range(2)]
        root_cell = d.buffer(np.ascontiguousarray(bounds, np.float32).reshape(-1))
        d.run(self.k["topo_root"], 1, root_cell, cells[0], size, nonempty, pre, climb, walk,
              local_size=1)
        for level, (first, end) in enumerate(ranges[:wide]):
            self.run("topo_down", end - first, nodes, cells[level % 2], cells[(level + 1) % 2],
                     size, nonempty, pre, climb, walk, U4(first), U4(end), U4(level))
            d.heartbeat()
        if wide < len(ranges):
            first, end = ranges[wide]
            roots = end - first
            # Small work-groups, as the subtrees differ in size.
            d.run(self.k["topo_subtrees"], roots, nodes, cells[wide % 2], size, nonempty, pre,
                  climb, walk, U4(first), U4(end), U4(wide),
                  local_size=8 if d.is_cpu else self.local_size,
                  piece=max(1, PIECE_SUBTREE_NODES * roots // (n - first)))
            d.heartbeat()
        return pre, climb, walk

    def sorted_references(self, nodes, n, leaf_indices, pre, triangle_count):
        """References sorted by (triangle, preorder of the leaf): leaf, its preorder number,
        triangle, and each triangle's first place."""
        d = self.device
        R = len(leaf_indices)
        d_leaf_indices = d.view(leaf_indices)
        # Counted on the device (numpy's bincount over all references was a long stretch
        # with Esc unseen); the (T + 1)-th count is 0, so its prefix is R.
        tri_first = d.zeros(4 * (triangle_count + 1))
        s_leaf, s_pre, s_tri = (d.buffer(nbytes=4 * max(R, 1)) for _ in range(3))
        rank = s_tri                  # each reference's place in its range, until refs_sort
        self.run("refs_count", R, d_leaf_indices, tri_first, rank, U4(R))
        self.scan(tri_first, triangle_count + 1)
        self.run("refs_scatter", n, nodes, d_leaf_indices, tri_first, rank, pre,
                 s_leaf, s_pre, U4(n))
        self.run("refs_sort", triangle_count, tri_first, s_leaf, s_pre, s_tri, U4(triangle_count))
        return s_leaf, s_pre, s_tri, tri_first

    def neighbour_lcas(self, s_pre, s_tri, climb, R):
        gap_node, gap_pre, gap_depth = (self.device.buffer(nbytes=4 * (R + 1)) for _ in range(3))
        self.run("neighbour_lcas", R + 1, s_pre, s_tri, climb, gap_node, gap_pre, gap_depth,
                 U4(R), piece=PIECE_CLIMBS)
        return gap_node, gap_pre, gap_depth

    def lift_candidates(self, tri_first, triangle_count, s_pre, gap_pre, gap_depth, climb, walk,
                        R, params):
        """compact_lifts.py lift_candidates: (a buffer of candidate rows, their number)."""
        d = self.device
        # Triangles with more than PRIVATE_GAPS references keep their stacks in the scratch.
        big_first = d.zeros(4 * (triangle_count + 1))
        self.run("scratch_spans", triangle_count, tri_first, big_first, U4(triangle_count))
        scratch = d.buffer(nbytes=4 * LIFT_SCRATCH_WORDS
                           * max(self.scan(big_first, triangle_count + 1), 1))
        taus = (np.float64(params.tau_occu).view(np.uint64),
                np.float64(params.tau_freq).view(np.uint64))
        capacity = max(R // 2, 1024)
        while True:
            out = d.buffer(nbytes=LIFT_CANDIDATE.nbytes * capacity)
            used = d.zeros(4)
            self.run("lift_candidates", triangle_count, tri_first, s_pre, gap_pre, gap_depth,
                     climb, walk, big_first, scratch, out,
                     used, U4(capacity), U4(triangle_count), U4(params.min_refs), *taus,
                     piece=PIECE_CLIMBS)
            total = d.value_at(used, 0)
            if total <= capacity:
                return out, total
            capacity = total          # more candidates than room: again with room for all

    def group_candidates(self, candidates, total, n):
        """The candidate rows grouped by node: (each node's end in `grouped`, grouped
        (triangle, references, first, end), each one's node)."""
        d = self.device
        node_next = d.zeros(4 * n)
        self.run("cand_count", total, candidates, node_next, U4(total))
        self.scan(node_next, n)                         # each node's first place
        grouped = d.buffer(nbytes=LIFT_GROUPED.nbytes * total)
        grouped_node = d.buffer(nbytes=4 * total)
        self.run("cand_group", total, candidates, node_next, grouped, grouped_node, U4(total))
        return node_next, grouped, grouped_node         # node_next: now each node's end

    def select_lifts(self, nodes, ranges, grouped_candidates, total, R, n, params):
        """compact_lifts.py select_lifts on the device (choose_lifts, level by level): (removed
        references: a uchar buffer; lift node, triangle, first: host arrays, by node; refs per
        node: a buffer)."""
        d = self.device
        node_end, grouped, grouped_node = grouped_candidates
        removed, taken, refs_at = d.zeros(R), d.zeros(4 * (total + 1)), d.zeros(4 * n)
        limited = params.refs_per_path is not None
        on_path = d.zeros(4 * n if limited else 4)
        for first, end in ranges:
            self.run("choose_lifts", end - first, node_end, grouped, removed, taken, refs_at,
                     on_path, U4(first), U4(end), U4(params.refs_per_node),
                     U4(params.refs_per_path or 0), U4(limited))
            if limited:
                self.run("pass_down", end - first, nodes, refs_at, on_path, U4(first), U4(end))
            d.heartbeat()
        del on_path
        count = self.scan(taken, total + 1)
        d.heartbeat()
        lifts = [d.buffer(nbytes=4 * max(count, 1)) for _ in range(3)]
        self.run("lifts_out", total, taken, grouped, grouped_node, *lifts, U4(total))
        node, tri, first = (d.read(x, U4, count).astype(np.int64) for x in lifts)
        return removed, node, tri, first, refs_at

    def collapse(self, nodes, n, ranges, R, d_removed, s_leaf, gap_node, gap_depth, lift_node,
                 lift_first, refs_at, pre, walk, params):
        """compact_lifts.py distinct_below, compact_layout.py collapse: the collapsed nodes (a
        buffer)."""
        d = self.device
        per_node = d.zeros(4 * n)
        leaf_count = d.zeros(4 * n)
        self.run("distinct_refs", R, d_removed, s_leaf, gap_node, gap_depth, per_node, leaf_count,
                 U4(R))
        self.run("distinct_lifts", len(lift_node), d.buffer(lift_node.astype(U4)),
                 d.buffer(lift_first.astype(U4)), gap_node, gap_depth, per_node,
                 U4(len(lift_node)))
        for first, end in reversed(ranges):
            self.run("subtree_sums", end - first, nodes, per_node, U4(first), U4(end))
            d.heartbeat()
        cost = d.buffer(nbytes=8 * n)
        collapsed = d.buffer(nbytes=n)
        kt = np.float64(params.traversal_cost).view(np.uint64)
        ki = np.float64(params.intersection_cost).view(np.uint64)
        for first, end in reversed(ranges):
            self.run("collapse", end - first, nodes, pre, walk, leaf_count, refs_at, per_node,
                     cost, collapsed, U4(first), U4(end), kt, ki)
            d.heartbeat()
        return collapsed

    def owners(self, nodes, n, ranges, collapsed):
        """compact_layout.py owners: (dead, owner) buffers."""
        d = self.device
        dead, owner = d.zeros(n), d.zeros(4 * n)
        for first, end in ranges:
            self.run("owners", end - first, nodes, collapsed, dead, owner, U4(first), U4(end))
            d.heartbeat()
        return dead, owner

    def items(self, n, R, d_removed, s_leaf, s_tri, owner, extra_owner, extra_tri):
        """Every final leaf's triangles (kept references and the lifts of removed nodes),
        sorted, without repeats, one list after another in node order: buffers (count per
        node, first place per node, the lists) and the number of items."""
        d = self.device
        per_owner = d.zeros(4 * (n + 1))
        self.run("items_count", R, d_removed, s_leaf, owner, per_owner, U4(R))
        # The lifts of removed nodes go first in their owner's bucket, then the references.
        order = np.argsort(extra_owner, kind="stable")
        by_owner = extra_owner[order]
        starts = run_starts(by_owner)
        runs = np.diff(np.append(starts, len(by_owner)))
        cursor = d.zeros(4 * n)
        self.add_at(cursor, by_owner[starts], runs)
        self.add_at(per_owner, by_owner[starts], runs)
        d.heartbeat()
        owner_first = d.buffer(nbytes=4 * (n + 1))
        total = self.scan(per_owner, n + 1, owner_first)
        del per_owner
        d.heartbeat()
        items = d.buffer(nbytes=4 * max(total, 1))
        if len(extra_owner):
            rank = np.arange(len(by_owner)) - np.repeat(starts, runs)
            first = self.gather(owner_first, by_owner)
            self.run("put_values", len(by_owner), d.buffer((first + rank).astype(U4)),
                     d.buffer(extra_tri[order].astype(U4)), items, U4(len(by_owner)))
            d.heartbeat()
        self.run("items_scatter", R, d_removed, s_leaf, s_tri, owner, owner_first, cursor, items,
                 U4(R))
        del cursor
        kept = d.buffer(nbytes=4 * (n + 1))
        self.run("items_unique", n, owner_first, items, kept, U4(n))
        d.heartbeat()
        item_first = d.buffer(nbytes=4 * (n + 1))
        item_count = self.scan(kept, n, item_first)
        final_items = d.buffer(nbytes=4 * max(item_count, 1))
        self.run("close_buckets", n, owner_first, kept, item_first, items, final_items, U4(n))
        return kept, item_first, final_items, item_count

    def layout(self, nodes, n, params, dead, collapsed, final_count, item_first, items,
               lift_node, lift_tri, shift):
        """compact_layout.py layout: (nodes, leaf_index32, leaf_index16, leaf_shift, node kinds,
        leaf stats), the refs per node of the kept lifts (a buffer), the collapsed nodes
        that stay."""
        d = self.device
        classes = d.buffer(nbytes=n)
        self.run("layout_classes", n, nodes, dead, collapsed, final_count, classes, U4(n))
        refs_at = d.zeros(4 * n)
        self.set_counts(refs_at, lift_node)
        elided = d.zeros(n)
        groups = d.buffer(nbytes=4 * n)
        self.run("layout_groups", n, nodes, classes, refs_at, elided, groups, U4(n),
                 U4(bool(params.elide_empty)))
        total = 1 + self.scan(groups, n)                 # now each live inner node's group - 1
        if total - 1 > INNER_GROUP.max:
            raise ValueError(f"compact kd-tree too large: {total} nodes "
                             f"(at most {INNER_GROUP.max})")
        d.heartbeat()
        off32, count16, base_of = (d.buffer(nbytes=4 * n) for _ in range(3))
        self.run("layout_leaves", n, classes, elided, final_count, item_first, items, off32,
                 count16, base_of, U4(n), U4(shift), U4(bool(params.leaf16)),
                 U4(LEAF16_INDEX_BITS))
        off16 = d.buffer(nbytes=4 * n)
        total32 = self.scan(off32, n)
        total16 = self.scan(count16, n, off16)
        out = d.standalone(8 * total)           # take(): the compact tree's arrays
        index32 = d.standalone(4 * max(total32, 1))
        index16 = d.standalone(2 * max(total16, 2))
        new_index = d.buffer(nbytes=4 * n)
        self.run("layout_places", n, nodes, classes, elided, refs_at, groups, new_index, out,
                 U4(n))
        d.heartbeat()
        self.run("layout_words", n, nodes, classes, elided, refs_at, groups, final_count,
                 item_first, items, count16, off32, off16, base_of, new_index, out, index32,
                 index16, U4(n), U4(shift))
        lifted_nodes = 0
        if len(lift_node):
            # By (node, triangle): the lifts come by node, so this stable sort of a combined
            # key is nearly linear, unlike a lexsort.
            order = np.argsort((lift_node << 32) | lift_tri, kind="stable")
            node_sorted = lift_node[order]
            first = run_starts(node_sorted)
            lifted_nodes = len(first)
            slot = np.arange(len(order)) - np.repeat(first, np.diff(np.append(first, len(order))))
            self.run("layout_slots", len(order), d.buffer(node_sorted.astype(U4)),
                     d.buffer(lift_tri[order].astype(U4)), d.buffer(slot.astype(U4)), groups,
                     out, U4(len(order)))
            d.heartbeat()
        block = 4096
        blocks = max(1, -(-n // block))
        counters = d.buffer(nbytes=LAYOUT_COUNTS.nbytes * blocks)
        d.run(self.k["layout_stats"], blocks, classes, elided, final_count, count16, collapsed,
              dead, counters, U4(n), U4(block), local_size=1)
        per_block = d.read(counters, U4, (blocks, len(LAYOUT_COUNTS.columns))).astype(np.int64)
        d.heartbeat()
        if int(per_block[:, LAYOUT_COUNTS.index("largest_leaf")].max()) > LEAF32_COUNT.max:
            raise ValueError("a leaf holds too many triangles for the 32-bit list's count")
        counts = dict(zip(LAYOUT_COUNTS.columns, (int(x) for x in per_block.sum(0))))
        stored, leaves16, leaves32 = (counts[name] for name in ("leaves", "leaves_16bit",
                                                                 "leaves_32bit"))
        laid_out = (d.take(out, U4, (total, 2)), d.take(index32, U4, total32),
                    d.take(index16, np.uint16, total16), shift,
                    {"inner": counts["inner"], "tref": lifted_nodes, "leaf": stored},
                    {"leaves": stored, "empty_leaves_stored": counts["empty_leaves_stored"],
                     "empty_leaves_elided": counts["empty_leaves_elided"],
                     "leaves_16bit": leaves16, "leaves_32bit": leaves32,
                     "leaf16_share": float(leaves16 / max(leaves16 + leaves32, 1)),
                     "leaf_shift": shift})
        assert sum(laid_out[4].values()) == total
        return laid_out, refs_at, counts["collapsed_kept"]

    def max_refs_on_path(self, nodes, n, ranges, dead, refs_at) -> int:
        d = self.device
        on_path, most = d.zeros(4 * n), d.zeros(4)
        for first, end in ranges:
            self.run("path_refs", end - first, nodes, dead, refs_at, on_path, most, U4(first),
                     U4(end))
            d.heartbeat()
        return d.value_at(most, 0)


def compact_on_device(device, tree, triangles_count, params, leaf_shift, report):
    """compact.py's post-pass with its steps in kernels (the choice of lifts and the stats on
    the host) on `device`, a DeviceContext (a BinnedBuilder is one) or a select_device spec.
    Returns what compact._finish makes the CompactTree of: (standard nodes, references,
    collapsed subtrees kept, the laid-out arrays, the most references on a path, leaf
    references, lift nodes, lift triangles); None when the tree is not in the builders'
    order."""
    if not isinstance(device, DeviceContext):
        device = device_for(device)
    try:
        return _compact(CompactorCL(device), tree, triangles_count, params, leaf_shift,
                        device.reporting(report))
    finally:
        device.release()


def _compact(c, tree, triangles_count, params, leaf_shift, report):
    d = c.device
    plain = np.ascontiguousarray(tree.nodes, U4)
    n, R = len(plain), len(tree.leaf_indices)
    nodes = d.view(plain)
    report(0.0, f"compact ({params.mode}): {n:,} nodes")
    ranges = c.level_ranges(nodes, n)
    if ranges is None:
        return None
    pre, climb, walk = c.topology(nodes, n, ranges, tree.bounds)
    report(0.1, "compact: topology")
    s_leaf, s_pre, s_tri, tri_first = c.sorted_references(nodes, n, tree.leaf_indices, pre,
                                                          triangles_count)
    report(0.2, "compact: tree decoded")

    lifting = params.refs_per_node > 0 and (params.refs_per_path is None
                                            or params.refs_per_path > 0)
    if lifting or params.collapse:
        gap_node, gap_pre, gap_depth = c.neighbour_lcas(s_pre, s_tri, climb, R)
        report(0.3, "compact: neighbouring references' common ancestors")
    if lifting:
        candidates, total = c.lift_candidates(tri_first, triangles_count, s_pre, gap_pre,
                                              gap_depth, climb, walk, R, params)
        del climb, gap_pre, s_pre, tri_first
        grouped = c.group_candidates(candidates, total, n)
        del candidates
        removed, lift_node, lift_tri, lift_first, refs_at = c.select_lifts(
            nodes, ranges, grouped, total, R, n, params)
        del grouped
    else:
        del climb, s_pre, tri_first
        removed = d.zeros(R)
        lift_node = lift_tri = lift_first = np.zeros(0, np.int64)
        refs_at = d.zeros(4 * n)
    report(0.5, f"compact: {len(lift_tri)} triangle references lifted")

    if params.collapse:
        collapsed = c.collapse(nodes, n, ranges, R, removed, s_leaf, gap_node, gap_depth, lift_node,
                               lift_first, refs_at, pre, walk, params)
        del gap_node, gap_depth
    else:
        collapsed = d.zeros(n)
    del refs_at, pre, walk
    report(0.7, "compact: subtrees collapsed")

    dead, owner = c.owners(nodes, n, ranges, collapsed)
    report(0.75, "compact: owners of the collapsed subtrees' contents")
    gone = ((c.gather(dead, lift_node, "gather_bytes") > 0)
            | (c.gather(collapsed, lift_node, "gather_bytes") > 0))
    final_count, item_first, items, item_count = c.items(
        n, R, removed, s_leaf, s_tri, owner, c.gather(owner, lift_node[gone]), lift_tri[gone])
    del owner, s_leaf, s_tri, removed
    lift_node, lift_tri = lift_node[~gone], lift_tri[~gone]
    report(0.85, f"compact: {item_count:,} leaf references")
    laid_out, refs_at, kept_collapsed = c.layout(nodes, n, params, dead, collapsed, final_count,
                                                 item_first, items, lift_node, lift_tri,
                                                 leaf_shift)
    del final_count, item_first, items, collapsed
    max_path = c.max_refs_on_path(nodes, n, ranges, dead, refs_at)
    return n, R, kept_collapsed, laid_out, max_path, item_count, lift_node, lift_tri
