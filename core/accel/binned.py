"""The kd-tree builder: binned SAH, breadth first, in OpenCL kernels (kernels/build/binned.cl,
binned_level.cl; docs/kdtree_native.md).

One level of the tree per round of launches, over every node of the level at once: nodes
choose their splits (one work-item per node; nodes of more than `big_refs` references are
binned by chunks of their references, so that the top levels keep every core busy too), the
level's counts are summed by blocks of nodes into places, the level's node words and the next
level's nodes are written, and every reference moves to its children (straddlers clipped in
double) or into its leaf's list. The nodes come out breadth first, the k-th inner node's
children at 1 + 2k of the next level, leaf lists in node order: the order compact_cl.py
compacts.

The tree depends only on the geometry and KDTreeParams (the kernels' docstring says why), not
on the device, thread count, work-group size, launch pieces, `big_refs` or `chunk_refs`. The
device needs cl_khr_fp64 (the clipping's doubles).

pyopencl is imported only when a builder is made.
"""
from __future__ import annotations

import math
import time

import numpy as np

from ..layout import (BIN_BIG, BIN_BOUNDS, BIN_CHUNK, BIN_NODE, BIN_PLACES, BIN_SUMS,
                      BUILD_REF, BUILD_SPLIT, PLAIN_FIELD)
from ..opencl import OpenCLError, kernel_source
from .arrays import exclusive_cumsum
from .device import DeviceContext
from .kdtree import KDTree, KDTreeParams, checked_mesh, root_bounds

KERNEL_FILES = ("build/binned.cl", "build/binned_level.cl")
EXACT_MAX = 256          # nodes of up to this many references: every reference bound a candidate
SUM_BLOCK = 128          # nodes per work-item of level_sums and emit
SPLIT_BYTES = BUILD_SPLIT.nbytes
REF_BYTES = BUILD_REF.nbytes
# Launches over more than this many nodes (or chunks' references) go in pieces, with the
# progress callback between them, so that Esc is seen within a piece.
PIECE_NODES = 1 << 18
PIECE_REFS = 1 << 20
PIECE_PAIRS = 1 << 24    # choose_nodes: about this many (reference, candidate) pairs a piece
FLT_MIN = np.float32(np.finfo(np.float32).tiny)


def _float_literal(x: float) -> str:
    """A float32 constant for a -D option, exact (hex notation)."""
    return float(np.float32(x)).hex() + "f"


def power_of_two_scale(bounds: np.ndarray) -> np.float32:
    """2^-e with 2^e around the scene's largest extent: cell sizes scaled by it stay near 1."""
    extent = float(np.max(bounds[1].astype(np.float64) - bounds[0]))
    exponent = math.frexp(extent)[1] if extent > 0 else 0
    return np.float32(math.ldexp(1.0, -exponent))


def _rows(table, n_rows, dtype=np.uint32, **columns) -> np.ndarray:
    rows = np.zeros((n_rows, len(table.columns)), dtype)
    for name, values in columns.items():
        rows[:, table.index(name)] = values
    return rows


class BinnedBuilder(DeviceContext):
    """Builds kd-trees on one OpenCL device (a DeviceContext, which compact_tree(device=...)
    shares for the compaction). big_refs: nodes with more references are binned by chunks of
    chunk_refs references (None: sizes that suit the device kind); local_size: work-group
    size. None of them changes the tree, only the speed."""

    def __init__(self, device=None, big_refs: int | None = None, chunk_refs: int | None = None,
                 local_size: int | None = None, profile_kernels: bool = False):
        super().__init__(device, profile_kernels)
        self.big_refs = int(big_refs or (16384 if self.is_cpu else 1024))
        self.chunk_refs = int(chunk_refs or (4096 if self.is_cpu else 256))
        if self.big_refs < EXACT_MAX:
            raise ValueError(f"big_refs must be at least {EXACT_MAX}")
        self.local_size = int(local_size or (16 if self.is_cpu else 64))
        self.last_profile: dict = {}

    def build_options(self, params: KDTreeParams) -> list:
        return [f"-DKD_KT={_float_literal(params.traversal_cost)}",
                f"-DKD_KI={_float_literal(params.intersection_cost)}",
                f"-DKD_LAMBDA={_float_literal(params.empty_bonus)}",
                f"-DKD_MIN_BINS={int(params.min_bins)}u", f"-DKD_MAX_BINS={int(params.max_bins)}u",
                f"-DKD_MAX_BAD={int(params.max_bad_refines)}u",
                f"-DKD_SMALL_NODE={int(params.small_node)}u", f"-DKD_EXACT_MAX={EXACT_MAX}u",
                f"-DKD_BIG_REFS={self.big_refs}u", f"-DKD_SUM_BLOCK={SUM_BLOCK}u"]

    def program(self, params: KDTreeParams | None = None) -> dict:
        return self.kernels(kernel_source(KERNEL_FILES), self.build_options(params or KDTreeParams()))

    def launch(self, name, count, *args, piece=None):
        self.run(self.k[name], count, *args, local_size=self.local_size, piece=piece)

    # -- the build -------------------------------------------------------------------------
    def build(self, vertices, triangles, params: KDTreeParams | None = None,
              progress=None) -> KDTree:
        """The kd-tree of the triangles. progress(fraction, message) is called between
        levels and launch pieces, on this thread; an exception it raises stops the build."""
        try:
            return self._build(vertices, triangles, params or KDTreeParams(), progress)
        finally:
            self.k = None
            self.release()

    def _build(self, vertices, triangles, params, progress) -> KDTree:
        started = time.perf_counter()
        report = self.reporting(progress)
        vertices, triangles = checked_mesh(vertices, triangles)
        T = len(triangles)
        if T > PLAIN_FIELD.max:
            raise ValueError("too many triangles for the 30-bit leaf reference count")
        # Coordinates below FLT_MIN are 0: devices that flush float32 denormals see the same.
        tiny = (np.abs(vertices) < FLT_MIN) & (vertices != 0)
        if tiny.any():
            vertices = np.where(tiny, np.float32(0), vertices)
        depth_cap = params.depth_cap(T)
        self.k = self.program(params)
        # binned.cl's HIST_WORDS: per bin and axis the low ends, high ends, flat references;
        # the tight bounds and the count.
        self._hist_words = 9 * int(params.max_bins) + 7
        u4 = np.uint32

        # The level's buffers, each reused while it is big enough (fresh pages cost about 1 s
        # per GB on the VMs measured: a new buffer per level was most of 12 dragons' build),
        # and the tree's arrays, written level by level where they end (grown when needed).
        held = _Held(self)
        tree_nodes = _Growing(self, 8, 6 * T + 64)
        tree_lists = _Growing(self, 4, 3 * T + 64)

        # First references, the corners for the clipping, the root cell.
        corners = self.buffer(nbytes=36 * max(T, 1))
        refs = held.get("refs0", REF_BYTES * max(T, 1))
        self.launch("first_refs", T, self.buffer(vertices), self.buffer(triangles.astype(u4)),
                    corners, refs, u4(T), piece=PIECE_REFS)
        per = SUM_BLOCK * 64
        blocks = -(-T // per)
        kept, lo, hi = 0, np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
        if blocks:
            out = self.buffer(nbytes=BIN_BOUNDS.nbytes * blocks)
            self.launch("ref_bounds", blocks, refs, out, u4(T))
            rows = self.read(out, np.float32, (blocks, len(BIN_BOUNDS.columns)))
            counts = rows[:, BIN_BOUNDS.index("kept")].view(u4).astype(np.int64)
            kept = int(counts.sum())
            lo, hi = rows[counts > 0, 0:3], rows[counts > 0, 3:6]
        bounds = root_bounds(lo, hi, vertices) + np.float32(0)
        pow2 = power_of_two_scale(bounds)
        d = (bounds[1] * pow2 - bounds[0] * pow2).astype(np.float32)
        inv_root = np.float32(1) / np.float32(d[0] * d[1] + d[1] * d[2] + d[2] * d[0])

        # The levels.
        node_rows = _rows(BIN_NODE, 1, count=T)
        node_rows[0, 0:6] = bounds.reshape(-1).view(u4)
        nodes = held.get("nodes0", node_rows.nbytes)
        self._cl.enqueue_copy(self.queue, nodes, node_rows)
        host_nodes = node_rows             # the level's rows while it may have big nodes
        n, level, level_base, leaf_total, sah, leaves, empty = 1, 0, 0, 0, 0, 0, 0
        slots = T                          # the level's references, holes included
        while n:
            report(min(0.95, 0.95 * level / (depth_cap + 1)),
                   f"kd-tree level {level}: {n:,} nodes")
            splits = held.get("splits", SPLIT_BYTES * n)
            args = (u4(n), u4(level), u4(depth_cap), pow2)
            # A node's exact candidates cost (its references)^2: pieces of about PIECE_PAIRS.
            mean = max(1.0, slots / n)
            piece = int(min(PIECE_NODES, max(64, PIECE_PAIRS / (mean * mean))))
            self.launch("choose_nodes", n, nodes, refs, splits, *args, piece=piece)
            chunks = None
            if host_nodes is not None:
                chunks, n_chunks = self._big_nodes(host_nodes, nodes, refs, splits, *args)
            # Places: inner nodes, children's references and leaf entries before each block.
            blocks = -(-n // SUM_BLOCK)
            d_sums = self.buffer(nbytes=BIN_SUMS.nbytes * blocks)
            self.launch("level_sums", blocks, nodes, splits, d_sums, u4(n), pow2, inv_root)
            sums = self.read(d_sums, u4, (blocks, len(BIN_SUMS.columns))).astype(np.int64)
            col = {name: sums[:, BIN_SUMS.index(name)] for name in BIN_SUMS.columns}
            sah += int(((col["sah_high"] << 32) | col["sah_low"]).astype(np.uint64)
                       .view(np.int64).sum())
            leaves += int(col["leaves"].sum())
            empty += int(col["empty_leaves"].sum())
            firsts = {name: exclusive_cumsum(col[name]) for name in BIN_PLACES.columns}
            inner, places, leaf_refs = (int(firsts[name][-1]) for name in BIN_PLACES.columns)
            if level_base + n + 2 * inner - 1 > PLAIN_FIELD.max:
                raise ValueError("kd-tree too large for the 30-bit child index")
            d_places = self.buffer(_rows(BIN_PLACES, blocks, **{
                name: firsts[name][:-1] for name in BIN_PLACES.columns}))
            words = tree_nodes.reserve(level_base + n)
            next_nodes = held.get(f"nodes{(level + 1) % 2}", BIN_NODE.nbytes * max(2 * inner, 1))
            self.launch("emit", blocks, nodes, splits, d_places, words, next_nodes, u4(n),
                        u4(level_base), u4(level_base + n), u4(leaf_total))
            next_refs = held.get(f"refs{(level + 1) % 2}", REF_BYTES * max(places, 1))
            leaf_tris = tree_lists.reserve(leaf_total + leaf_refs)
            self.launch("scatter_nodes", n, nodes, refs, splits, corners, next_refs, leaf_tris,
                        u4(n), piece=PIECE_NODES)
            if chunks is not None:
                self.launch("scatter_chunks", n_chunks, refs, chunks, splits, corners, next_refs,
                            leaf_tris, u4(n_chunks), piece=max(1, PIECE_REFS // self.chunk_refs))
            level_base += n
            leaf_total += leaf_refs
            n, nodes, refs, slots = 2 * inner, next_nodes, next_refs, places
            host_nodes = None
            if n and int(col["widest"].max()) > self.big_refs:
                host_nodes = self.read(nodes, u4, (n, len(BIN_NODE.columns)))
            level += 1
            self.heartbeat()
        del nodes, refs, splits, held
        report(0.96, f"kd-tree: {level_base:,} nodes")
        nodes_array = self.take(tree_nodes.buffer, u4, (level_base, 2))
        leaf_indices = (self.take(tree_lists.buffer, u4, leaf_total) if leaf_total
                        else np.zeros(0, u4))
        tree = KDTree(nodes_array, leaf_indices, bounds)
        tree.stats = {
            "nodes": level_base,
            "leaves": leaves,
            "empty_leaves": empty,
            "depth": level - 1,
            "depth_cap": depth_cap,
            "references": leaf_total,
            "refs_per_triangle": leaf_total / max(kept, 1),
            "dropped_degenerate": T - kept,
            "bytes": tree.nbytes,
            "sah_cost": sah / 2.0**32,
            "build_seconds": time.perf_counter() - started,
            "threads": self.compute_units,
            "builder": "opencl",
            "device": self.device_name,
        }
        report(1.0, f"kd-tree done: {level_base:,} nodes, {leaf_total:,} references")
        return tree

    def _big_nodes(self, host_nodes, nodes, refs, splits, n, level, depth_cap, pow2):
        """Bin the level's big nodes by chunks and choose their splits; returns the chunk rows'
        buffer and how many (None, 0 without big nodes)."""
        u4 = np.uint32
        count = host_nodes[:, BIN_NODE.index("count")].astype(np.int64)
        big = np.flatnonzero(count > self.big_refs)
        if not len(big):
            return None, 0
        first = host_nodes[big, BIN_NODE.index("first")].astype(np.int64)
        per = -(-count[big] // self.chunk_refs)
        chunk_first = exclusive_cumsum(per)
        C = int(chunk_first[-1])
        node_of = np.repeat(np.arange(len(big)), per)
        within = np.arange(C) - chunk_first[:-1][node_of]
        start = first[node_of] + within * self.chunk_refs
        size = np.minimum(self.chunk_refs, count[big][node_of] - within * self.chunk_refs)
        chunks = self.buffer(_rows(BIN_CHUNK, C, node=big[node_of], first=start, count=size))
        hist = self.buffer(nbytes=4 * C * self._hist_words)
        self.launch("bin_chunks", C, nodes, refs, chunks, hist, u4(C),
                    piece=max(1, PIECE_REFS // self.chunk_refs))
        rows = self.buffer(_rows(BIN_BIG, len(big), node=big, first_chunk=chunk_first[:-1],
                                 chunks=per))
        self.launch("choose_big", len(big), nodes, rows, chunks, hist, splits, u4(len(big)),
                    level, depth_cap, pow2)
        return chunks, C


class _Held:
    """A buffer per role, outside the pool, reused while big enough and grown by a quarter
    beyond what is asked (a level's references, nodes and splits: the next level needs a
    little more than this one)."""

    def __init__(self, device: DeviceContext):
        self.device, self.buffers = device, {}

    def get(self, role: str, nbytes: int):
        buffer, capacity = self.buffers.get(role, (None, 0))
        if capacity < nbytes:
            capacity = max(int(1.25 * nbytes), 4096)
            self.buffers[role] = (None, 0)          # let the old one go first
            buffer = self.device.standalone(capacity)
            self.buffers[role] = (buffer, capacity)
        return buffer


class _Growing:
    """One of the tree's arrays, written level by level in place: a buffer of `capacity`
    items of `itemsize` bytes (pages are touched only where written), replaced by one half
    as big again, with the items so far copied over, when a level needs more."""

    def __init__(self, device: DeviceContext, itemsize: int, capacity: int):
        self.device, self.itemsize, self.capacity = device, itemsize, int(capacity)
        self.buffer, self.used = device.standalone(itemsize * self.capacity), 0

    def reserve(self, items: int):
        """The buffer, holding at least `items` items; the items written so far kept."""
        if items > self.capacity:
            capacity = max(int(items), int(1.5 * self.capacity))
            grown = self.device.standalone(self.itemsize * capacity)
            if self.used:
                self.device.copy(grown, self.buffer, self.itemsize * self.used)
            self.buffer, self.capacity = grown, capacity
        self.used = max(self.used, int(items))
        return self.buffer


_BUILDERS: dict = {}


def builder_for(device) -> BinnedBuilder:
    """A builder for `device` (a BinnedBuilder itself, or a core.opencl.select_device spec:
    None or "auto" means a GPU if any, else the CPU), kept per spec: contexts and programs are
    made once."""
    if isinstance(device, BinnedBuilder):
        return device
    key = str(device)
    builder = _BUILDERS.get(key)
    if builder is None:
        builder = _BUILDERS[key] = BinnedBuilder(device)
    return builder


def opencl_builder(device="auto"):
    """(builder_for(device), None), or (None, why not): pyopencl missing, no such OpenCL
    device, or one without double precision."""
    try:
        return builder_for(device), None
    except ImportError as error:
        return None, f"pyopencl is not installed ({error})"
    except OpenCLError as error:
        return None, str(error).splitlines()[0]


def build_standard(vertices, triangles, device="auto", params: KDTreeParams | None = None,
                   progress=None):
    """The standard kd-tree, on the OpenCL device `device` (see builder_for) when there is one,
    else with the numpy builder (core.accel.kdtree.build_kdtree: slower, another tree of the
    same definition). Returns (tree, the builder or None); tree.stats["builder"] and
    ["device"] say which ran where."""
    builder, reason = opencl_builder(device)
    if builder is not None:
        return builder.build(vertices, triangles, params, progress), builder
    from .kdtree import build_kdtree
    tree = build_kdtree(vertices, triangles, params, progress)
    tree.stats.update(builder="numpy", device=f"host CPU ({reason})")
    return tree, None
