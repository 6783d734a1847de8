"""SAH kd-tree build in OpenCL kernels (kernels/build/, docs/kdtree_native.md).

The same tree definition as core/accel/kdtree.py (KDTreeParams cost model, automatic
termination with bad refines, depth cap, perfect splits in double precision, planar triangles on
the cheaper side, zero-area triangles dropped), built in two stages:

- **Big nodes** (more than `subtree_refs` references), one level at a time, data-parallel over
  the level's references in chunks: binned SAH with exact counts at the bin planes, exact counts
  at the chosen plane, leaf or split, clipping of straddlers, every reference moved to its child
  by prefix sums computed here.
- **Subtrees**: a child small enough (or a big node that became a leaf) is a subtree root; one
  work-item builds each subtree depth first, exact SAH for nodes of up to 16 references.

Every decision is made by the same kernel functions from order-independent counts, so the tree
does not depend on `subtree_refs`, the chunk size, work-group sizes, thread counts or devices
(fp64 natively where the device has it, a bit-exact software double elsewhere). The nodes are
then placed breadth-first, exactly the layout of the numpy builder: a subtree's nodes of one
level are contiguous there, ordered among the others by the path from the root.

pyopencl is imported only when a builder is made.
"""
from __future__ import annotations

import math
import time

import numpy as np

from ..layout import (BIG_CHOICE, BIG_CHUNK, BIG_DECISION, BIG_DEST, BUILD_REF, CELL,
                      CHILD_COUNTS, CORNERS, DECISION_FLAGS, HISTOGRAM_BOUND_WORDS,
                      HISTOGRAM_WORDS_PER_BIN, LEAF_TAG, LEVEL_BASE, LEVEL_COUNT, NODE_CHUNKS,
                      PLAIN_FIELD, PLAIN_TAG, PLANE_COUNTS, STORE_MOVE, SUBTREE_PLACE,
                      SUBTREE_LEVELS, SUBTREE_RESULT, SUBTREE_ROOT, SUBTREE_STATUS)
from ..opencl import kernel_source
from .arrays import concat_ranges, exclusive_cumsum
from .device import DeviceContext
from .kdtree import KDTree, KDTreeParams, build_kdtree, checked_mesh, root_bounds

KERNEL_FILES = ("build/fp64.cl", "build/common.cl", "build/split.cl", "build/big.cl",
                "build/subtree.cl", "build/layout.cl")
EXACT_MAX = 16          # nodes with up to this many references get exact SAH (as kdtree.py)
FLT_MIN = np.float32(np.finfo(np.float32).tiny)
# Launches over more than this many references (big-node passes) or items (one work-item
# each) go in pieces, with the progress callback between them: Esc is seen within a piece.
PIECE_REFS = 1 << 20
PIECE_ITEMS = 1 << 22


def _float_literal(x: float) -> str:
    """A float32 constant for a -D option, exact (hex notation)."""
    return float(np.float32(x)).hex() + "f"


def _double_bits(x: float) -> str:
    """The IEEE double bit pattern of x, as a ulong literal for a -D option."""
    return f"0x{np.float64(x).view(np.uint64):016X}UL"


def _power_of_two_scale(bounds: np.ndarray) -> np.float32:
    """2^-e with 2^e around the scene's largest extent: cell sizes scaled by it stay near 1."""
    extent = float(np.max(bounds[1].astype(np.float64) - bounds[0]))
    exponent = math.frexp(extent)[1] if extent > 0 else 0
    return np.float32(math.ldexp(1.0, -exponent))


def _half_area_f32(lo: np.ndarray, hi: np.ndarray, pow2: np.float32) -> np.float32:
    """split.cl's cell_dims().half_area, in the same float32 operations."""
    d = [np.float32(hi[a]) * pow2 - np.float32(lo[a]) * pow2 for a in range(3)]
    return np.float32(d[0] * d[1] + d[1] * d[2] + d[2] * d[0])


def _rows(table, dtype=np.uint32, **columns) -> np.ndarray:
    """Rows of a core/layout.py table from its columns by name (the others 0). A name whose
    table has NAME_x, NAME_y, NAME_z takes (n, 3) values; float32 ones go to a uint32 table
    as their bits."""
    rows = np.zeros((len(next(iter(columns.values()))), len(table.columns)), dtype)
    for name, values in columns.items():
        if name in table.columns:
            rows[:, table.index(name)] = values
            continue
        values = np.asarray(values)
        if values.dtype.kind == "f" and rows.dtype.kind != "f":
            values = values.view(rows.dtype)
        first = table.index(f"{name}_x")
        rows[:, first:first + 3] = values
    return rows


def _corner(rows, table, name) -> np.ndarray:
    """The (n, 3) columns NAME_x, NAME_y, NAME_z of a table's rows."""
    first = table.index(f"{name}_x")
    return rows[:, first:first + 3]


def _leaf_counts(words) -> tuple[int, int]:
    """Leaves and empty leaves among plain nodes' first words, a slice at a time: whole-tree
    temporaries are fresh pages, slices stay in cache."""
    tag_mask = np.uint32(PLAIN_TAG.put(PLAIN_TAG.max))
    leaf_tag = np.uint32(PLAIN_TAG.put(LEAF_TAG))        # also an empty leaf's whole word
    leaves = empties = 0
    for start in range(0, len(words), 1 << 20):
        part = words[start:start + (1 << 20)]
        leaves += int(np.count_nonzero((part & tag_mask) == leaf_tag))
        empties += int(np.count_nonzero(part == leaf_tag))
    return leaves, empties


class KDTreeBuilderCL(DeviceContext):
    """Builds kd-trees on one OpenCL device; programs are built once per KDTreeParams. The
    builder is the device's DeviceContext (device.py), which compact_tree(device=builder)
    shares for the compaction.

    subtree_refs: nodes with at most this many references are built by one work-item each
    (None: a size that suits the device kind); chunk_refs: references per work-item in the
    big-node passes; subtree_queue: the subtrees taken in turn by a few work-items (None: on CPU
    devices). None of them changes the tree, only the speed.
    """

    def __init__(self, device=None, subtree_refs: int | None = None,
                 chunk_refs: int | None = None, soft_fp64: bool | None = None,
                 local_size: int | None = None, profile_kernels: bool = False,
                 subtree_queue: bool | None = None):
        super().__init__(device, soft_fp64, profile_kernels)
        self.subtree_refs = subtree_refs or (2048 if self.is_cpu else 64)
        self.chunk_refs = chunk_refs or (4096 if self.is_cpu else 256)
        self.local_size = local_size if local_size is not None else (1 if self.is_cpu else 32)
        # CPU devices: a few work-items take a launch's subtrees one at a time (subtree.cl);
        # elsewhere one work-item per subtree.
        self.subtree_queue = self.is_cpu if subtree_queue is None else bool(subtree_queue)
        self.batch_seconds = 0.15      # target time of one subtree launch (Esc stays prompt)
        self.last_profile: dict = {}

    def build_options(self, params: KDTreeParams) -> list:
        """The -D options of the build kernels: KDTreeParams and the subtree queue."""
        options = [f"-DKD_KT_BITS={_double_bits(params.traversal_cost)}",
                   f"-DKD_KI_BITS={_double_bits(params.intersection_cost)}",
                   f"-DKD_2KI_BITS={_double_bits(2 * params.intersection_cost)}",
                   f"-DKD_LAMBDA_BITS={_double_bits(params.empty_bonus)}",
                   f"-DKD_BPR_BITS={_double_bits(params.bins_per_reference)}",
                   f"-DKD_KT={_float_literal(params.traversal_cost)}",
                   f"-DKD_KI={_float_literal(params.intersection_cost)}",
                   f"-DKD_LAMBDA={_float_literal(params.empty_bonus)}",
                   f"-DKD_MIN_BINS={int(params.min_bins)}", f"-DKD_MAX_BINS={int(params.max_bins)}",
                   f"-DKD_MAX_BAD={int(params.max_bad_refines)}u",
                   f"-DKD_SMALL_NODE={int(params.small_node)}u", f"-DKD_EXACT_MAX={EXACT_MAX}u"]
        if self.subtree_queue:
            options.append("-DKD_SUBTREE_QUEUE")
        return options

    def program(self, source: str, params: KDTreeParams | None = None) -> dict:
        """Kernels of `source` (which includes kernels/build/ files) built with this builder's
        options: the build's own, or test kernels."""
        return self.kernels(source, self.build_options(params or KDTreeParams()))

    def launch(self, kernel, count, *args, piece=None):
        """run() with the builder's work-group size."""
        self.run(kernel, count, *args, local_size=self.local_size, piece=piece)

    # -- the build -------------------------------------------------------------------------
    def build(self, vertices, triangles, params: KDTreeParams | None = None,
              progress=None) -> KDTree:
        """Build the kd-tree (see module docstring). `progress(fraction, message)` is called
        between kernel launches, on this thread; an exception it raises stops the build."""
        try:
            return self._build(vertices, triangles, params, progress)
        finally:
            self.release()

    def _build(self, vertices, triangles, params, progress) -> KDTree:
        params = params or KDTreeParams()
        report = self.reporting(progress)
        started = time.perf_counter()
        profile = {}
        clock = [time.perf_counter(), time.process_time()]

        def lap(name):
            now = time.perf_counter(), time.process_time()
            wall, cpu = profile.get(name, (0.0, 0.0))
            profile[name] = (wall + now[0] - clock[0], cpu + now[1] - clock[1])
            clock[:] = now

        vertices, triangles = checked_mesh(vertices, triangles)
        if len(triangles) > PLAIN_FIELD.max:
            raise ValueError("too many triangles for the 30-bit leaf reference count")
        # Coordinates below FLT_MIN are treated as 0: devices that flush float32 denormals
        # then see the same numbers.
        tiny = (np.abs(vertices) < FLT_MIN) & (vertices != 0)
        if tiny.any():
            vertices = np.where(tiny, np.float32(0), vertices)
        triangles = np.ascontiguousarray(triangles, np.uint32)
        triangle_count = len(triangles)
        depth_cap = params.depth_cap(triangle_count)
        if not 0 <= depth_cap < SUBTREE_LEVELS - 1:
            raise ValueError(f"depth cap {depth_cap} outside 0..{SUBTREE_LEVELS - 2}")

        kernels = self.program(kernel_source(KERNEL_FILES), params)
        lap("programs")
        state = _BuildState(self, kernels, params, vertices, triangles, depth_cap, report)
        kept_count, bounds = state.first_refs()
        pow2 = _power_of_two_scale(bounds)
        inv_root = np.float32(1) / _half_area_f32(bounds[0], bounds[1], pow2)
        state.pow2, state.inv_root = pow2, inv_root
        lap("setup")

        state.big_stage(bounds)
        lap("big nodes")
        state.subtree_stage()
        lap("subtrees")
        nodes, leaf_indices = state.layout()
        lap("layout")
        report(0.97, f"kd-tree laid out: {len(nodes):,} nodes")

        leaf_count, empty_count = _leaf_counts(nodes[:, 0])
        tree = KDTree(nodes, leaf_indices, bounds)
        tree.stats = {
            "nodes": len(nodes),
            "leaves": leaf_count,
            "empty_leaves": empty_count,
            "depth": state.depth,
            "depth_cap": depth_cap,
            "references": len(leaf_indices),
            "refs_per_triangle": len(leaf_indices) / max(kept_count, 1),
            "dropped_degenerate": triangle_count - kept_count,
            "bytes": tree.nbytes,
            "sah_cost": state.sah_fixed / 2.0**32,
            "build_seconds": time.perf_counter() - started,
            "threads": self.compute_units,
            "builder": "opencl",
            "device": self.device_name,
        }
        profile["subtree_launches"] = state.launches
        profile["subtree_count"] = state.subtree_count
        self.last_profile = profile
        report(1.0, f"kd-tree done: {len(nodes)} nodes, {len(leaf_indices)} references")
        return tree


class _BuildState:
    """One build's buffers and bookkeeping (kdtree_cl.KDTreeBuilderCL.build)."""

    def __init__(self, builder, kernels, params, vertices, triangles, depth_cap, report):
        self.b, self.k, self.params = builder, kernels, params
        self.depth_cap = depth_cap
        self.report = report
        self.vertex_array = vertices
        self.triangle_count = len(triangles)
        self.vertices = builder.buffer(vertices)
        self.triangles = builder.buffer(triangles)
        self.corners = builder.buffer(nbytes=CORNERS.nbytes * len(triangles))
        self.max_bins = int(params.max_bins)
        self.queue_refs = None                 # device Ref array of subtree roots' references
        self.queue_used = 0
        self.queue_capacity = 0
        # Subtree roots, one list entry per level of the big stage.
        self.roots = []      # dicts of arrays: lo, hi, level, bad, key, start, count
        # Big inner nodes: level, key, axis, plane bits, and their below child's key.
        self.inner = []
        self.sah_fixed = 0
        self.launches = 0
        self.subtree_count = 0
        self.depth = 0

    def first_refs(self):
        """The kept triangles' references on the device (self.refs) and the root box; returns
        (kept count, bounds)."""
        b, k = self.b, self.k
        T = self.triangle_count
        u4 = np.uint32
        refs = b.buffer(nbytes=BUILD_REF.nbytes * T)
        keep = b.buffer(nbytes=T)
        b.launch(k["init_refs"], T, self.vertices, self.triangles, refs, keep, self.corners, u4(T),
                 piece=PIECE_ITEMS)
        self.vertices = self.triangles = None
        flags = b.read(keep, np.uint8, T)
        kept = int(flags.sum())
        if kept < T:
            place = (np.cumsum(flags, dtype=np.int64) - flags).astype(u4)
            out = b.buffer(nbytes=BUILD_REF.nbytes * kept)
            b.launch(k["compact_refs"], T, refs, keep, b.buffer(place), out, u4(T),
                     piece=PIECE_ITEMS)
            refs = out
        del keep
        chunk = 1 << 16
        n_chunks = -(-kept // chunk)
        if n_chunks:
            d_box = b.buffer(nbytes=CELL.nbytes * n_chunks)
            b.launch(k["chunk_bounds"], n_chunks, refs, d_box, u4(kept), u4(chunk))
            box = b.read(d_box, np.float32, (n_chunks, len(CELL.columns)))
            lo, hi = _corner(box, CELL, "lo").min(0), _corner(box, CELL, "hi").max(0)
        else:
            lo = hi = np.zeros(0, np.float32)
        self.refs, self.kept = refs, kept
        return kept, root_bounds(lo.reshape(-1, 3), hi.reshape(-1, 3), self.vertex_array) + np.float32(0)

    # -- queue of subtree references ------------------------------------------------------------
    def _reserve_queue(self, extra):
        need = self.queue_used + int(extra)
        if need <= self.queue_capacity:
            return
        capacity = max(need, int(1.25 * self.queue_capacity), 1024)
        grown = self.b.buffer(nbytes=BUILD_REF.nbytes * capacity)
        if self.queue_used:
            self.b.copy(grown, self.queue_refs, BUILD_REF.nbytes * self.queue_used)
        self.queue_refs, self.queue_capacity = grown, capacity

    def _add_roots(self, lo, hi, level, bad, key, count):
        """New subtree roots whose references are about to be written to the queue, in this
        order; returns their first places in the queue."""
        start = self.queue_used + exclusive_cumsum(count)[:-1]
        self._reserve_queue(int(count.sum()))
        self.queue_used += int(count.sum())
        self.roots.append(dict(lo=lo, hi=hi, level=np.broadcast_to(level, len(count)).astype(np.int64),
                               bad=bad.astype(np.int64), key=key.astype(np.uint64),
                               start=start, count=count.astype(np.int64)))
        return start

    # -- big nodes ------------------------------------------------------------------------------
    def big_stage(self, bounds):
        b, k = self.b, self.k
        u4 = np.uint32
        n0 = self.kept
        lo, hi = bounds[:1].copy(), bounds[1:].copy()
        count = np.array([n0], np.int64)
        bad = np.zeros(1, np.int64)
        key = np.zeros(1, np.uint64)
        level_refs, self.refs = self.refs, None
        if n0 <= b.subtree_refs:
            self._add_roots(lo, hi, 0, bad, key, count)
            if n0:
                b.copy(self.queue_refs, level_refs, BUILD_REF.nbytes * n0)
            return
        level = 0
        S, CH = b.subtree_refs, b.chunk_refs
        while len(count):
            self.report(0.15 * level / (self.depth_cap + 1),
                        f"kd-tree level {level}: {len(count)} big nodes, {int(count.sum())} references")
            m = len(count)
            per_node = -(-count // CH)
            chunk_first = exclusive_cumsum(per_node)
            C = int(chunk_first[-1])
            chunk_node = np.repeat(np.arange(m), per_node)
            ref_first = exclusive_cumsum(count)
            within = np.arange(C) - np.repeat(chunk_first[:-1], per_node)
            chunk_start = ref_first[:-1][chunk_node] + within * CH
            chunk_count = np.minimum(CH, count[chunk_node] - within * CH)
            chunks = _rows(BIG_CHUNK, node=chunk_node, ref_first=chunk_start,
                           ref_count=chunk_count)
            node_chunks = _rows(NODE_CHUNKS, first=chunk_first[:-1], count=per_node)
            cells = _rows(CELL, np.float32, lo=lo, hi=hi)
            d_chunks, d_node_chunks = b.buffer(chunks), b.buffer(node_chunks)
            d_cells, d_n, d_bad = b.buffer(cells), b.buffer(count.astype(u4)), b.buffer(bad.astype(u4))
            d_hist = b.buffer(nbytes=4 * C * (HISTOGRAM_WORDS_PER_BIN * self.max_bins
                                              + HISTOGRAM_BOUND_WORDS))
            d_choice = b.buffer(nbytes=BIG_CHOICE.nbytes * m)
            d_counts = b.buffer(nbytes=PLANE_COUNTS.nbytes * C)
            d_decision = b.buffer(nbytes=BIG_DECISION.nbytes * m)
            d_sah = b.buffer(nbytes=8 * m)
            d_out = b.buffer(nbytes=CHILD_COUNTS.nbytes * C)
            piece = max(1, PIECE_REFS // CH)
            b.launch(k["big_bin"], C, level_refs, d_chunks, d_cells, d_n, d_hist, u4(C),
                     piece=piece)
            b.launch(k["big_choose"], m, d_node_chunks, d_hist, d_cells, d_n, d_choice, u4(m))
            b.launch(k["big_recount"], C, level_refs, d_chunks, d_choice, d_counts, u4(C),
                     piece=piece)
            b.launch(k["big_decide"], m, d_node_chunks, d_counts, d_choice, d_cells, d_n, d_bad,
                     d_decision, d_sah, u4(m), u4(level), u4(self.depth_cap), self.pow2,
                     self.inv_root)
            b.launch(k["big_classify"], C, level_refs, d_chunks, d_decision, d_cells, self.corners,
                     d_out, u4(C), piece=piece)
            decision = b.read(d_decision, u4, (m, len(BIG_DECISION.columns)))
            out = b.read(d_out, u4, (C, len(CHILD_COUNTS.columns))).astype(np.int64)
            sah = b.read(d_sah, np.int64, m)
            del d_hist, d_choice, d_counts
            self.sah_fixed += int(sah.sum())

            flags, new_bad, axis, plane_bits = (decision[:, BIG_DECISION.index(name)]
                                                for name in BIG_DECISION.columns)
            is_leaf = (flags & DECISION_FLAGS["LEAF"]) != 0
            new_bad, axis = new_bad.astype(np.int64), axis.astype(np.int64)
            per_side = [out[:, CHILD_COUNTS.index(side)] for side in ("below", "above")]
            n_below = np.add.reduceat(per_side[0], chunk_first[:-1])
            n_above = np.add.reduceat(per_side[1], chunk_first[:-1])
            n_above[is_leaf] = 0
            split = ~is_leaf
            # Streams per node: "below" is the below child (or the leaf itself), "above" the
            # above child. Each child is big (next level) or a subtree root (queue).
            rows = np.arange(m)
            child_n = np.stack([n_below, n_above], 1)                     # (m, 2)
            big_child = (child_n > S) & split[:, None]
            small_child = ~big_child & split[:, None]
            # Next level: big children in node order, below before above.
            big_flat = big_child.reshape(-1)
            big_start = np.zeros(2 * m, np.int64)
            big_start[big_flat] = exclusive_cumsum(child_n.reshape(-1)[big_flat])[:-1]
            next_total = int(child_n.reshape(-1)[big_flat].sum())
            # Queue: per node the leaf itself, or its small children, in node order.
            to_queue = np.zeros((m, 2), bool)
            to_queue[:, 0] = is_leaf | small_child[:, 0]
            to_queue[:, 1] = small_child[:, 1]
            q_flat = to_queue.reshape(-1)
            q_counts = child_n.reshape(-1)[q_flat]
            q_node, q_side = np.divmod(np.flatnonzero(q_flat), 2)
            q_lo, q_hi = lo[q_node].copy(), hi[q_node].copy()
            q_split = split[q_node]
            sr = np.flatnonzero(q_split)
            qa, qp = axis[q_node[sr]], plane_bits[q_node[sr]].view(np.float32)
            above_side = q_side[sr] == 1
            q_hi[sr[~above_side], qa[~above_side]] = qp[~above_side]
            q_lo[sr[above_side], qa[above_side]] = qp[above_side]
            q_key = key[q_node].copy()
            bit = np.uint64(1) << np.uint64(63 - level) if level < 63 else np.uint64(0)
            q_key[sr[above_side]] |= bit
            q_level = np.where(q_split, level + 1, level)
            q_bad = np.where(q_split, new_bad[q_node], bad[q_node])
            q_start = np.zeros(2 * m, np.int64)
            q_start[q_flat] = self._add_roots(q_lo, q_hi, q_level, q_bad, q_key, q_counts)
            # Per chunk: destination kind and first place of both streams.
            dest = np.zeros((C, len(BIG_DEST.columns)), u4)
            for side, name in enumerate(("below", "above")):
                flat = 2 * chunk_node + side
                base = np.where(q_flat[flat], q_start[flat], big_start[flat])
                offset = exclusive_cumsum(per_side[side])
                node_offset = offset[chunk_first[:-1]]
                dest[:, BIG_DEST.index(f"{name}_to_queue")] = q_flat[flat]
                dest[:, BIG_DEST.index(f"{name}_first")] = (base + offset[:-1]
                                                            - node_offset[chunk_node])
            b.heartbeat()     # after the host's part of the level
            next_refs = b.buffer(nbytes=BUILD_REF.nbytes * max(next_total, 1))
            d_dest = b.buffer(dest)
            b.launch(k["big_scatter"], C, level_refs, d_chunks, d_decision, d_cells, self.corners,
                     d_dest, next_refs, self.queue_refs, u4(C), piece=piece)
            b.finish()

            # Inner nodes of this level (placed later), and the next level's big nodes.
            s_nodes = np.flatnonzero(split)
            below_key = key[s_nodes]
            self.inner.append(dict(level=level, key=key[s_nodes], axis=axis[s_nodes],
                                   plane=plane_bits[s_nodes], below_key=below_key))
            nxt = np.flatnonzero(big_flat)
            p_node, p_side = np.divmod(nxt, 2)
            n_lo, n_hi = lo[p_node].copy(), hi[p_node].copy()
            pa, pp = axis[p_node], plane_bits[p_node].view(np.float32)
            r = np.arange(len(nxt))
            up = p_side == 1
            n_hi[r[~up], pa[~up]] = pp[~up]
            n_lo[r[up], pa[up]] = pp[up]
            n_key = key[p_node].copy()
            n_key[up] |= bit
            lo, hi, count = n_lo, n_hi, child_n.reshape(-1)[nxt]
            bad, key = new_bad[p_node], n_key
            level_refs = next_refs
            level += 1
        self.depth = max(self.depth, level)

    # -- subtrees -------------------------------------------------------------------------------
    def subtree_stage(self):
        b, k = self.b, self.k
        u4 = np.uint32
        roots = {name: np.concatenate([r[name] for r in self.roots])
                 for name in ("level", "bad", "key", "start", "count")}
        roots["lo"] = np.concatenate([r["lo"] for r in self.roots]).reshape(-1, 3)
        roots["hi"] = np.concatenate([r["hi"] for r in self.roots]).reshape(-1, 3)
        self.roots = roots
        n_sub = len(roots["count"])
        self.subtree_count = n_sub
        span = self.depth_cap + 1 - roots["level"]
        # Results per subtree, filled batch by batch.
        self.rec_start = np.zeros(n_sub, np.int64)
        self.rec_count = np.zeros(n_sub, np.int64)
        self.leaf_start = np.zeros(n_sub, np.int64)
        self.chunk_of = np.zeros(n_sub, np.int64)
        self.levels = np.zeros(n_sub, np.int64)
        level_pieces = []                       # (subtrees, their per-level counts) per batch
        store = _Store(b, k["store_subtrees"])
        self.store = store
        total_refs = max(int(roots["count"].sum()), 1)
        done_refs = 0
        factor = np.ones(n_sub, np.int64)             # capacity multiplier, grows on overflow
        pending = np.argsort(-roots["count"], kind="stable")   # big subtrees first
        batch_refs = 4 * b.subtree_refs * max(1, b.compute_units)
        scratch = records = leafbuf = None
        sizes = (0, 0, 0)
        next_subtree = b.buffer(nbytes=4)
        while len(pending):
            take = max(1, int(np.searchsorted(np.cumsum(roots["count"][pending] * factor[pending]),
                                              batch_refs, side="right")))
            batch, pending = pending[:take], pending[take:]
            n = roots["count"][batch]
            f = factor[batch]
            rec_cap = f * (12 * n + 64)
            leaf_cap = f * (8 * n + 64)
            scr_cap = f * (4 * n + 64)
            rec_off, leaf_off, scr_off = (exclusive_cumsum(c) for c in (rec_cap, leaf_cap, scr_cap))
            lvl_off = exclusive_cumsum(span[batch])
            need = (int(rec_off[-1]), int(leaf_off[-1]), int(scr_off[-1]))
            if any(x > y for x, y in zip(need, sizes)):
                sizes = tuple(max(x, y) for x, y in zip(need, sizes))
                scratch = b.buffer(nbytes=BUILD_REF.nbytes * sizes[2])
                records = (b.buffer(nbytes=8 * sizes[0]), b.buffer(nbytes=4 * sizes[0]))
                leafbuf = b.buffer(nbytes=4 * sizes[1])
            words = _rows(SUBTREE_ROOT, lo=roots["lo"][batch], hi=roots["hi"][batch],
                          level=roots["level"][batch], bad_refines=roots["bad"][batch],
                          ref_first=roots["start"][batch], ref_count=n,
                          record_offset=rec_off[:-1], record_capacity=rec_cap,
                          leaf_offset=leaf_off[:-1], leaf_capacity=leaf_cap,
                          scratch_offset=scr_off[:-1], scratch_capacity=scr_cap,
                          level_offset=lvl_off[:-1], level_span=span[batch])
            d_roots = b.buffer(words)
            d_levels = b.buffer(nbytes=LEVEL_COUNT.nbytes * int(lvl_off[-1]))
            d_result = b.buffer(nbytes=SUBTREE_RESULT.nbytes * len(batch))
            d_sah = b.buffer(nbytes=8 * len(batch))
            t0 = time.perf_counter()
            workers = len(batch)
            if b.subtree_queue:     # a few work-items take the subtrees in turn
                b.clear(next_subtree, 4)
                workers = min(workers, b.compute_units)
            b.launch(k["build_subtrees"], workers, self.queue_refs, self.corners, d_roots,
                     scratch, records[0], records[1], leafbuf, d_levels, d_result, d_sah,
                     next_subtree, u4(len(batch)), self.pow2, self.inv_root, u4(self.depth_cap))
            result = b.read(d_result, u4, (len(batch), len(SUBTREE_RESULT.columns)))
            status, n_rec, n_leaf, n_levels = (
                result[:, SUBTREE_RESULT.index(name)].astype(np.int64)
                for name in ("status", "records", "leaf_refs", "levels"))
            seconds = time.perf_counter() - t0
            self.launches += 1
            if (status == SUBTREE_STATUS["RANKS"]).any():
                raise ValueError("a kd-tree subtree has more than 2^26 nodes on one level")
            ok = status == SUBTREE_STATUS["OK"]
            failed = batch[~ok]
            if len(failed):
                factor[failed] *= 4
                pending = np.concatenate([failed, pending])
            good = batch[ok]
            if len(good):
                sah = b.read(d_sah, np.int64, len(batch))
                self.sah_fixed += int(sah[ok].sum())
                levels_table = b.read(d_levels, u4, (int(lvl_off[-1]), len(LEVEL_COUNT.columns)))
                self.levels[good] = n_levels[ok]
                level_pieces.append((good, levels_table[concat_ranges(lvl_off[:-1][ok],
                                                                      n_levels[ok])]))
                chunk, rec_at, leaf_at = store.append(records, leafbuf, rec_off[:-1][ok],
                                                      n_rec[ok], leaf_off[:-1][ok], n_leaf[ok])
                self.chunk_of[good], self.rec_start[good], self.leaf_start[good] = \
                    chunk, rec_at, leaf_at
                self.rec_count[good] = n_rec[ok]
                done_refs += int(n[ok].sum())
            # Aim each launch at batch_seconds, so that Esc is seen promptly.
            if seconds > 0:
                scale = min(4.0, max(0.25, b.batch_seconds / seconds))
                batch_refs = max(b.subtree_refs, int(batch_refs * scale))
            self.report(0.15 + 0.8 * done_refs / total_refs,
                        f"kd-tree subtrees: {done_refs:,} of {total_refs:,} references")
        # Per-level counts in subtree order.
        self.level_counts = np.zeros((int(self.levels.sum()), len(LEVEL_COUNT.columns)), np.int64)
        first = exclusive_cumsum(self.levels)[:-1]
        for ids, rows in level_pieces:
            self.level_counts[concat_ranges(first[ids], self.levels[ids])] = rows

    # -- final layout -----------------------------------------------------------------------------
    def layout(self):
        b, k = self.b, self.k
        u4 = np.uint32
        roots = self.roots
        n_sub = self.subtree_count
        levels = self.levels
        # Entries: every (subtree, relative level) and every big inner node.
        sub_of = np.repeat(np.arange(n_sub), levels)
        rel = np.arange(int(levels.sum())) - np.repeat(exclusive_cumsum(levels)[:-1], levels)
        counts = self.level_counts
        inner_level = np.concatenate([np.full(len(x["key"]), x["level"]) for x in self.inner]) \
            if self.inner else np.zeros(0, np.int64)
        inner_key = np.concatenate([x["key"] for x in self.inner]) if self.inner else np.zeros(0, np.uint64)
        e_level = np.concatenate([roots["level"][sub_of] + rel, inner_level])
        e_key = np.concatenate([roots["key"][sub_of], inner_key])
        e_nodes = np.concatenate([counts[:, LEVEL_COUNT.index("nodes")],
                                  np.ones(len(inner_key), np.int64)])
        e_leaf = np.concatenate([counts[:, LEVEL_COUNT.index("leaf_refs")],
                                 np.zeros(len(inner_key), np.int64)])
        order = np.lexsort((e_key, e_level))
        node_base = np.empty(len(order), np.int64)
        leaf_base = np.empty(len(order), np.int64)
        node_base[order] = exclusive_cumsum(e_nodes[order])[:-1]
        leaf_base[order] = exclusive_cumsum(e_leaf[order])[:-1]
        total_nodes = int(e_nodes.sum())
        total_refs = int(e_leaf.sum())
        if total_nodes - 1 > PLAIN_FIELD.max:
            raise ValueError("kd-tree too large for the 30-bit child index")
        self.depth = int(e_level.max()) if len(e_level) else 0
        nsub_entries = len(sub_of)
        bases = _rows(LEVEL_BASE, node=node_base[:nsub_entries], leaf=leaf_base[:nsub_entries])
        places = _rows(SUBTREE_PLACE, record_first=self.rec_start, records=self.rec_count,
                       leaf_first=self.leaf_start, level_offset=exclusive_cumsum(levels)[:-1])
        d_nodes = b.standalone(8 * total_nodes)       # take(): they outlive the build
        d_leaves = b.standalone(4 * total_refs)
        d_bases = b.buffer(bases)
        per_subtree = max(1, int(self.rec_count.sum()) // max(n_sub, 1))
        for c, chunk in enumerate(self.store.chunks):
            ids = np.flatnonzero(self.chunk_of == c)
            b.launch(k["place_subtrees"], len(ids), chunk.words, chunk.meta, chunk.leaf_refs,
                     b.buffer(places[ids]), d_bases, d_nodes, d_leaves, u4(len(ids)),
                     piece=max(1, PIECE_ITEMS // per_subtree))
            b.heartbeat()
        nodes = b.take(d_nodes, u4, (total_nodes, 2))
        leaf_indices = b.take(d_leaves, u4, total_refs)
        self.store = None
        # Big inner nodes: their own place, and their children's (the entry at the next level
        # with the below child's key).
        if len(inner_key):
            inner_at = node_base[nsub_entries:]
            sorted_level, sorted_key = e_level[order], e_key[order]
            below_key = np.concatenate([x["below_key"] for x in self.inner])
            child = np.empty(len(inner_key), np.int64)
            for lvl in np.unique(inner_level):
                rows = np.flatnonzero(inner_level == lvl)
                lo_i, hi_i = np.searchsorted(sorted_level, [lvl + 1, lvl + 2])
                pos = lo_i + np.searchsorted(sorted_key[lo_i:hi_i], below_key[rows])
                child[rows] = node_base[order[pos]]
            axis = np.concatenate([x["axis"] for x in self.inner])
            plane = np.concatenate([x["plane"] for x in self.inner])
            nodes[inner_at, 0] = (PLAIN_TAG.put(axis) | PLAIN_FIELD.put(child)).astype(u4)
            nodes[inner_at, 1] = plane
        return nodes, leaf_indices


class _Chunk:
    """One piece of the store: record words, their meta, leaf references; how much is used."""

    def __init__(self, b, rec_capacity, ref_capacity):
        self.words, self.meta = b.buffer(nbytes=8 * rec_capacity), b.buffer(nbytes=4 * rec_capacity)
        self.leaf_refs = b.buffer(nbytes=4 * ref_capacity)
        self.rec_capacity, self.ref_capacity = rec_capacity, ref_capacity
        self.records = self.refs = 0


class _Store:
    """Subtree records and leaf references of the finished subtrees, on the device, in chunks
    that are never copied (growing one buffer meant copying all of it, a memcpy the next
    subtree launch waited for, with Esc unseen; docs/kdtree_native.md). A batch's
    subtrees go wholly into one chunk."""

    CHUNK_RECORDS = 1 << 22
    CHUNK_REFS = 1 << 22

    def __init__(self, builder, kernel):
        self.b, self.kernel = builder, kernel
        self.chunks: list[_Chunk] = []

    def append(self, records, leafbuf, rec_src, rec_n, leaf_src, leaf_n):
        """Copy finished subtrees' outputs in; returns their chunk's index, and their first
        record and reference in it."""
        b = self.b
        need_rec, need_refs = int(rec_n.sum()), int(leaf_n.sum())
        c = self.chunks[-1] if self.chunks else None
        if c is None or c.records + need_rec > c.rec_capacity or c.refs + need_refs > c.ref_capacity:
            c = _Chunk(b, max(need_rec, self.CHUNK_RECORDS), max(need_refs, self.CHUNK_REFS))
            self.chunks.append(c)
        rec_dst = c.records + exclusive_cumsum(rec_n)[:-1]
        leaf_dst = c.refs + exclusive_cumsum(leaf_n)[:-1]
        moves = _rows(STORE_MOVE, record_from=rec_src, record_to=rec_dst, records=rec_n,
                      leaf_from=leaf_src, leaf_to=leaf_dst, leaf_refs=leaf_n)
        b.launch(self.kernel, len(moves), records[0], records[1], leafbuf, b.buffer(moves),
                 c.words, c.meta, c.leaf_refs, np.uint32(len(moves)))
        c.records += need_rec
        c.refs += need_refs
        return len(self.chunks) - 1, rec_dst, leaf_dst


_BUILDERS: dict = {}


def builder_for(device) -> KDTreeBuilderCL:
    """A builder for `device` (a KDTreeBuilderCL itself, or a core.opencl.select_device spec:
    None means a GPU if any, else the CPU), kept per spec: contexts and programs are made
    once."""
    if isinstance(device, KDTreeBuilderCL):
        return device
    key = str(device)
    builder = _BUILDERS.get(key)
    if builder is None:
        builder = _BUILDERS[key] = KDTreeBuilderCL(device)
    return builder


def opencl_builder(device="auto"):
    """(builder_for(device), None), or (None, why not) when pyopencl is missing or there is no
    such OpenCL device."""
    from ..opencl import OpenCLError
    try:
        return builder_for(device), None
    except ImportError as error:
        return None, f"pyopencl is not installed ({error})"
    except OpenCLError as error:
        return None, str(error).splitlines()[0]


def build_standard(vertices, triangles, device="auto", params: KDTreeParams | None = None,
                   progress=None):
    """The standard kd-tree, on the OpenCL device `device` (see builder_for) when there is one,
    else with numpy (core.accel.kdtree.build_kdtree: the same tree). Returns (tree, the builder
    or None); tree.stats["builder"] / ["device"] say which ran where."""
    builder, reason = opencl_builder(device)
    if builder is not None:
        return builder.build(vertices, triangles, params, progress), builder
    tree = build_kdtree(vertices, triangles, params, progress)
    tree.stats.update(builder="numpy", device=f"host CPU ({reason})")
    return tree, None
