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

import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..layout import INNER_GROUP, LEAF32_COUNT, LEAF_TAG, PLAIN_FIELD, PLAIN_TAG, TAG
from .arrays import distinct_count, exclusive_cumsum, run_lengths
from .compact_cl import compact_on_device
from .compact_layout import (MAX_GROUP_INDEX, MAX_LEAF32_COUNT, collapse, layout, leaf_shift,
                             max_refs_on_path, owners)
from .compact_lifts import distinct_below, lift_candidates, neighbour_lcas, select_lifts
from .compact_topology import Topology

MODES = ("standard", "choi", "compressed")


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
                                  leaf_shift(triangles_count), report)
        if parts is not None:
            return _finish(tree, params, *parts, started, report)

    topo = Topology(tree)
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
        gap_node, gap_depth = neighbour_lcas(topo, s_leaf, s_tri)
    if lifting:
        per_depth = lift_candidates(topo, s_leaf, s_tri, gap_node, gap_depth, params)
        removed, lift_node, lift_tri, refs_at, lift_first = select_lifts(
            topo, per_depth, len(s_tri), params)
        del per_depth
    else:
        removed = np.zeros(len(s_tri), bool)
        lift_node = lift_tri = lift_first = np.zeros(0, np.int64)
        refs_at = np.zeros(topo.n, np.int64)
    report(0.5, f"compact: {len(lift_tri)} triangle references lifted")

    # 2. Collapse subtrees (the triangles lifted inside a subtree come back into its leaf).
    if params.collapse:
        distinct = distinct_below(topo, removed, s_leaf, gap_node, gap_depth, lift_node,
                                  lift_first)
        del gap_node, gap_depth
    keep_ref = ~removed
    k_leaf, k_tri = s_leaf[keep_ref], s_tri[keep_ref]
    del s_leaf, s_tri, removed, keep_ref
    leaf_count = np.bincount(k_leaf, minlength=topo.n)
    if params.collapse:
        collapsed = collapse(topo, leaf_count, refs_at, distinct, params)
    else:
        collapsed = np.zeros(topo.n, bool)
    report(0.7, f"compact: {int(collapsed.sum())} subtrees collapsed")

    # Which nodes survive, and the leaf each removed node's contents go to.
    dead, owner = owners(topo, collapsed)
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
    laid_out = layout(topo, params, is_final_leaf, dead, final_count, item_tri, lift_node,
                      lift_tri, refs_at, triangles_count)
    return _finish(tree, params, topo.n, reference_count, int((collapsed & ~dead).sum()),
                   laid_out, max_refs_on_path(topo, dead, refs_at), len(item_tri), lift_node,
                   lift_tri, started, report)


def _finish(tree, params, standard_nodes, reference_count, collapsed_subtrees, laid_out,
            max_path, item_count, lift_node, lift_tri, started, report) -> CompactTree:
    """The CompactTree and its stats (both the numpy and the kernel path): `laid_out` is
    layout's result, item_count the final leaves' references, lift_node / lift_tri the lifts
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
    shift = leaf_shift(triangles_count)
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

