"""SAH kd-tree over triangles, built breadth-first with vectorised numpy: the oracle the kernel
builder (core/accel/binned.py) is tested against, and the builder of a master without OpenCL.

The tree follows Wald & Havran 2006 (SAH cost, automatic termination, perfect splits) and is stored
in Wald's 8-byte node layout described in docs/architecture.md. docs/kdtree.md describes the
algorithm.

The build keeps one flat list of *references* (triangle id, node, clipped float32 box) sorted by
node, each one row of 7 float32 words (box, then the triangle id's int32 bits), and processes a
whole level of the tree at a time: every step below is a numpy operation over all references or
all nodes of the level, never a Python loop per node or per triangle.

Zero-area triangles (exactly zero cross product in float64) are dropped: a watertight ray test
never reports a hit on them, and their clipped pieces would all look like zero-area contacts.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..layout import LEAF_TAG, PLAIN_FIELD     # the node format: core/layout.py PLAIN_NODE
from .arrays import exclusive_cumsum

MAX_NODE_FIELD = PLAIN_FIELD.max    # word 0 bits 2-31: child index or leaf reference count


@dataclass(frozen=True)
class KDTreeParams:
    """Tunables of the build. The cost model and its constants are Wald & Havran 2006's (K_T
    15, K_I 20, lambda 0.8; pbrt's kd-tree prices differently: traversal 1, intersection 80,
    empty bonus 0.5); the depth cap and the allowance of bad refines follow pbrt
    (docs/kdtree.md)."""

    traversal_cost: float = 15.0      # K_T: cost of visiting an inner node
    intersection_cost: float = 20.0   # K_I: cost of one ray/triangle test
    empty_bonus: float = 0.8          # lambda: cost factor when a split leaves one side empty
    max_bins: int = 32                # SAH bins per axis for big nodes
    min_bins: int = 4                 # bins per axis for the smallest nodes
    bins_per_reference: float = 2.0   # small nodes get this many bins per reference (clamped)
    max_bad_refines: int = 3          # as pbrt: a leaf once a path has refined badly this often
    small_node: int = 16              # nodes with fewer references never refine badly
    max_depth: int | None = None      # None: 8 + 1.3 log2(triangle count), rounded

    def depth_cap(self, triangle_count: int) -> int:
        if self.max_depth is not None:
            return int(self.max_depth)
        return int(round(8 + 1.3 * math.log2(max(triangle_count, 1))))


@dataclass
class KDTree:
    nodes: np.ndarray          # uint32 (N, 2), see docs/architecture.md
    leaf_indices: np.ndarray   # uint32, each leaf's triangle list contiguous
    bounds: np.ndarray         # float32 (2, 3): box of the root cell
    stats: dict = field(default_factory=dict)

    @property
    def nbytes(self) -> int:
        return int(self.nodes.nbytes + self.leaf_indices.nbytes)


# ---------------------------------------------------------------------------------------------
# Small numeric helpers

def _round_down_f32(x: np.ndarray) -> np.ndarray:
    """The largest float32 <= x (x float64)."""
    f = x.astype(np.float32)
    return np.where(f.astype(np.float64) > x, np.nextafter(f, np.float32(-np.inf)), f)


def _round_up_f32(x: np.ndarray) -> np.ndarray:
    """The smallest float32 >= x (x float64)."""
    f = x.astype(np.float32)
    return np.where(f.astype(np.float64) < x, np.nextafter(f, np.float32(np.inf)), f)


# A reference is one row of 7 float32 words: box lo (3), box hi (3), triangle id (int32 bits),
# so that moving references is one gather of 28-byte rows instead of three gathers.
REF_WORDS = 7
_REF_ROW = np.dtype((np.void, 4 * REF_WORDS))
_BOX_ROW = np.dtype((np.void, 4 * 6))


def _gather_refs(refs: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Rows `index` of the (N, 7) float32 reference array, as one gather of whole rows."""
    rows = np.take(refs.view(_REF_ROW).reshape(-1), index.reshape(-1))
    return rows.view(np.float32).reshape(index.shape + (REF_WORDS,))


def _ref_triangles(refs: np.ndarray) -> np.ndarray:
    return refs[:, 6].view(np.int32)


def _surface_area(dims: np.ndarray) -> np.ndarray:
    return 2.0 * (dims[..., 0] * dims[..., 1] + dims[..., 1] * dims[..., 2]
                  + dims[..., 2] * dims[..., 0])


def _split_cost(params: KDTreeParams, dims, area, axis, below_width, count_below, count_above):
    """SAH cost of splitting cells (dims, area) on `axis` at `below_width` from their low side."""
    if np.ndim(axis) == 0:
        side_a, side_b = dims[:, (axis + 1) % 3], dims[:, (axis + 2) % 3]
        width = dims[:, axis]
    else:                                           # one axis per cell
        rows = np.arange(len(dims))
        side_a, side_b = dims[rows, (axis + 1) % 3], dims[rows, (axis + 2) % 3]
        width = dims[rows, axis]
    above_width = width - below_width
    area_below = 2.0 * (below_width * (side_a + side_b) + side_a * side_b)
    area_above = 2.0 * (above_width * (side_a + side_b) + side_a * side_b)
    cost = params.traversal_cost + params.intersection_cost * (
        area_below * count_below + area_above * count_above) / area
    return np.where((count_below == 0) | (count_above == 0), cost * params.empty_bonus, cost)


# ---------------------------------------------------------------------------------------------
# Clipping triangles to boxes (Sutherland-Hodgman on padded polygon arrays)
#
# Polygons are stored coordinate-major, (3, W, K) float64 for K polygons of at most W vertices,
# `count` vertices each, so that every step is an elementwise operation over K contiguous values
# (reductions run over the short W axis). Unused slots repeat vertex 0: "the next vertex" is
# simply the next slot (cyclically), the closing edge runs into the first padding copy of
# vertex 0, and padding-to-padding edges have zero length and never cross a plane.

def _next_slot(values: np.ndarray, slot_axis: int) -> np.ndarray:
    return np.roll(values, -1, slot_axis)


def _crossing_edges(poly, dist, valid):
    """Edges (slot i to i+1, cyclically) of the polygons that cross the plane strictly.

    Returns the (W, K) mask and, for the m crossing edges in row-major order, their row, slot
    and crossing point (3, m) (not yet snapped onto the plane). Only crossing edges are
    interpolated: a convex polygon has at most two of them.
    """
    W = dist.shape[0]
    d_next = _next_slot(dist, 0)
    crossing = ((dist > 0) & (d_next < 0)) | ((dist < 0) & (d_next > 0))
    crossing &= valid
    row, slot = np.nonzero(crossing.T)
    d0, d1 = dist[slot, row], d_next[slot, row]
    t = d0 / (d0 - d1)
    nxt = slot + 1
    nxt[nxt == W] = 0
    start = poly[:, slot, row]
    point = start + t * (poly[:, nxt, row] - start)
    return crossing, row, slot, point


def _clip_face(poly, count, axis: int, value, keep_below: bool):
    """Clip convex polygons to x[axis] <= value (keep_below) or >= value.

    A vertex on the plane counts as inside; crossing points are snapped onto the plane.
    Returns the clipped polygons (3, width, n) and their vertex counts, for only the n rows
    that had a vertex outside (`changed`, their indices); the others are unchanged. The width
    is the largest new count: the caller pads wider rows with vertex 0.
    """
    _, W, K = poly.shape
    dist = value - poly[axis] if keep_below else poly[axis] - value
    valid = np.arange(W)[:, None] < count
    changed = np.flatnonzero((valid & (dist < 0)).any(0))
    if not len(changed):
        return None, None, changed
    if len(changed) < K:
        poly, dist, valid = poly[:, :, changed], dist[:, changed], valid[:, changed]
    crossing, row, slot, point = _crossing_edges(poly, dist, valid)
    point[axis] = value[changed][row]
    inside = valid & (dist >= 0)
    n = len(changed)
    # Vertex i in slot 2 i, the crossing point of edge i in slot 2 i + 1 (only read where kept).
    candidates = np.empty((3, W, 2, n))
    candidates[:, :, 0] = poly
    candidates[:, slot, 1, row] = point
    candidates = candidates.reshape(3, 2 * W, n)
    keep = np.stack([inside, crossing], 1).reshape(2 * W, n)
    slot = np.cumsum(keep, 0) - 1
    new_count = slot[-1] + 1
    new_width = max(1, int(new_count.max()))
    first = candidates[:, np.argmax(keep, 0), np.arange(n)]
    out = np.repeat(first[:, None, :], new_width, 1)
    target = (slot * n + np.arange(n))[keep]
    out.reshape(3, -1)[:, target] = candidates.reshape(3, -1)[:, keep.reshape(-1)]
    return out, new_count, changed


def _split_piece_boxes(poly, count, axis, plane):
    """float64 boxes and vertex counts of both halves of polygons cut by their own plane.

    Each half is what Sutherland-Hodgman would keep: the vertices on its side (a vertex on the
    plane belongs to both) plus the crossing points snapped onto the plane.
    """
    _, W, K = poly.shape
    rows = np.arange(K)
    d = poly[axis, :, rows].T - plane                         # (W, K)
    valid = np.arange(W)[:, None] < count
    crossing, row, slot, point = _crossing_edges(poly, d, valid)
    point[axis[row], np.arange(len(row))] = plane[row]
    lo = np.empty((2, 3, K))
    hi = np.empty((2, 3, K))
    n_cross = np.bincount(row, minlength=K)
    # The crossing points belong to both halves: their extremes are taken once (per row: the
    # crossing edges come row by row).
    cross_lo = np.full((3, K), np.inf)
    cross_hi = np.full((3, K), -np.inf)
    if len(row):
        cut = np.flatnonzero(n_cross)
        first = exclusive_cumsum(n_cross[cut])[:-1]
        cross_lo[:, cut] = np.minimum.reduceat(point, first, axis=1)
        cross_hi[:, cut] = np.maximum.reduceat(point, first, axis=1)
    del point
    counts = []
    for side, keep in ((0, valid & (d <= 0)), (1, valid & (d >= 0))):
        np.minimum(np.where(keep, poly, np.inf).min(1), cross_lo, out=lo[side])
        np.maximum(np.where(keep, poly, -np.inf).max(1), cross_hi, out=hi[side])
        counts.append(keep.sum(0) + n_cross)
    return lo, hi, counts


def _clip_straddlers(corners, cell_lo, cell_hi, axis, plane):
    """Perfect split of references that straddle their node's split plane.

    Each triangle is clipped in float64 to its node's cell (only against the faces its box
    crosses), then cut by the plane; each half's box is rounded outward to float32 and clamped
    to the child's cell. Returns both halves' boxes and whether each half has positive area (a
    zero-area half is dropped by the caller).

    A piece of a non-degenerate triangle has zero area exactly when it only touches the box: it
    is then empty, a point or a segment, or it lies flat in a box face plane that the triangle
    itself does not lie in (flat in an axis where the triangle is not).
    """
    K = len(corners)
    # Elementwise over the 3 corners / axes: numpy reduces a length-3 axis slowly.
    tri_lo = np.minimum(np.minimum(corners[:, 0], corners[:, 1]), corners[:, 2])
    tri_hi = np.maximum(np.maximum(corners[:, 0], corners[:, 1]), corners[:, 2])
    lo64, hi64 = cell_lo.astype(np.float64), cell_hi.astype(np.float64)
    beyond_lo, beyond_hi = tri_lo < lo64, tri_hi > hi64
    outside = beyond_lo | beyond_hi
    clipped = np.flatnonzero(outside[:, 0] | outside[:, 1] | outside[:, 2])
    del outside
    piece_lo = np.empty((2, 3, K))
    piece_hi = np.empty((2, 3, K))
    piece_count = np.empty((2, K), np.int64)
    plane64 = plane.astype(np.float64)
    # Triangles inside their cell are cut as they are; the others are clipped to it first.
    whole = np.ones(K, bool)
    whole[clipped] = False
    for rows, is_whole in ((np.flatnonzero(whole), True), (clipped, False)):
        if not len(rows):
            continue
        poly = np.ascontiguousarray(corners[rows].transpose(2, 1, 0))    # (3, 3, k)
        count = np.full(len(rows), 3)
        if not is_whole:
            for a in range(3):
                for keep_below, face, beyond in ((False, lo64[rows, a], beyond_lo[rows, a]),
                                                 (True, hi64[rows, a], beyond_hi[rows, a])):
                    sub = np.flatnonzero(beyond)
                    if not len(sub):
                        continue
                    # Only the slots in use (slots past a polygon's count repeat vertex 0).
                    width = int(count[sub].max())
                    out, new_count, changed = _clip_face(poly[:, :width, sub], count[sub], a,
                                                         face[sub], keep_below)
                    if not len(changed):
                        continue
                    changed = sub[changed]
                    extra = out.shape[1] - poly.shape[1]
                    if extra > 0:
                        poly = np.concatenate([poly, np.repeat(poly[:, :1], extra, 1)], 1)
                    poly[:, :out.shape[1], changed] = out
                    if out.shape[1] < poly.shape[1]:
                        poly[:, out.shape[1]:, changed] = out[:, :1]
                    count[changed] = new_count
        # Cut polygons of equal vertex count together, each group only as wide as its count.
        sizes = np.bincount(count)
        for size in np.flatnonzero(sizes):
            group = np.flatnonzero(count == size) if sizes[size] < len(rows) else slice(None)
            width = max(int(size), 1)
            part = poly[:, :width] if isinstance(group, slice) else poly[:, :width, group]
            at = rows[group]
            lo, hi, counts = _split_piece_boxes(part, count[group], axis[at], plane64[at])
            piece_lo[:, :, at], piece_hi[:, :, at] = lo, hi
            piece_count[0, at], piece_count[1, at] = counts
    triangle_flat = tri_hi == tri_lo
    halves = []
    for side in (0, 1):
        lo, hi = piece_lo[side].T, piece_hi[side].T
        flat = (hi - lo) == 0
        flat &= ~triangle_flat
        positive = (piece_count[side] >= 3) & ~(flat[:, 0] | flat[:, 1] | flat[:, 2])
        child_lo, child_hi = cell_lo.copy(), cell_hi.copy()
        (child_hi if side == 0 else child_lo)[np.arange(K), axis] = plane
        lo32 = np.maximum(_round_down_f32(np.where(positive[:, None], lo, 0.0)), child_lo)
        hi32 = np.minimum(_round_up_f32(np.where(positive[:, None], hi, 0.0)), child_hi)
        halves.append((lo32, hi32, positive))
    return halves


# ---------------------------------------------------------------------------------------------
# Choosing splits

def _binned_best_splits(params, cell_lo, cell_hi, counts, ref_lo, ref_hi):
    """Best SAH split of each node from binned counts, plus the exact empty-space cuts.

    For nodes with at least one reference; ref_* hold exactly their references, sorted by node.
    Each node gets its own bin count (bins_per_reference * N clamped to [min_bins, max_bins]);
    the counts live in one (nodes, most bins) array, so that every node's sweep is a row cumsum.
    Binning only proposes planes (float32 is enough): the caller recounts exactly.
    Returns (cost, axis, plane float32); cost is inf where no plane lies strictly inside.
    """
    node_count = len(counts)
    dims = (cell_hi.astype(np.float64) - cell_lo)
    area = _surface_area(dims)
    bins = np.clip(np.round(params.bins_per_reference * counts), params.min_bins,
                   params.max_bins).astype(np.int64)
    B = int(bins.max())
    ref_start = exclusive_cumsum(counts)[:-1]
    ref_row = np.repeat(np.arange(node_count) * B, counts)
    ref_last_bin = np.repeat(bins - 1, counts).astype(np.float32)
    k = np.arange(B)[None, :]
    rows = np.arange(node_count)

    best_cost = np.full(node_count, np.inf)
    best_axis = np.zeros(node_count, np.int64)
    best_plane = np.zeros(node_count, np.float32)

    def consider(cost, axis, plane):
        better = cost < best_cost
        best_cost[better] = cost[better]
        best_axis[better] = axis
        best_plane[better] = plane[better]

    # Every node has the same number of bins (the usual case: all binned nodes have more than
    # max_bins / bins_per_reference references): clamp to a scalar, cheaper than to an array.
    last_bin = np.float32(B - 1) if int(bins.min()) == B else ref_last_bin
    for axis in range(3):
        low = cell_lo[:, axis].astype(np.float64)
        width = dims[:, axis]
        ref_low = np.repeat(cell_lo[:, axis], counts)
        scale = np.repeat((bins / width).astype(np.float32), counts)
        # A reference counts below plane k if its low end is below it, above if its high end is
        # above it: bin the low ends by floor and the high ends by ceil - 1.
        per_ref = []
        for ends, rounding, shift in ((ref_lo, np.floor, 0), (ref_hi, np.ceil, 1)):
            b = np.subtract(ends[:, axis], ref_low)
            b *= scale
            rounding(b, out=b)
            if shift:
                b -= 1
            np.maximum(b, 0, out=b)
            np.minimum(b, last_bin, out=b)
            key = b.astype(np.int64)
            key += ref_row
            per_ref.append(np.bincount(key, minlength=node_count * B).reshape(node_count, B))
            del b, key
        del ref_low, scale
        count_below = per_ref[0].cumsum(1)
        count_above = counts[:, None] - per_ref[1].cumsum(1)
        del per_ref
        # Plane after bin k; the last bin of each node ends at the cell's high side.
        plane = (low[:, None] + (k + 1) * (width / bins)[:, None]).astype(np.float32)
        inside = ((k < bins[:, None] - 1) & (plane > cell_lo[:, axis, None])
                  & (plane < cell_hi[:, axis, None]))
        side_a, side_b = dims[:, (axis + 1) % 3, None], dims[:, (axis + 2) % 3, None]
        perimeter, cap = side_a + side_b, side_a * side_b
        # K_T + K_I (A_b N_b + A_a N_a) / A with A_b = 2 (w_b (a + b) + a b), in place (the
        # same float64 operations in the same order as written out).
        area_below = plane - low[:, None]                       # width below, then its area
        area_above = width[:, None] - area_below
        for part in (area_below, area_above):
            part *= perimeter
            part += cap
            part *= 2.0
        area_below *= count_below
        area_above *= count_above
        cost = area_below
        cost += area_above
        del area_above
        cost *= params.intersection_cost
        cost /= area[:, None]
        cost += params.traversal_cost
        empty = count_below == 0
        empty |= count_above == 0
        np.multiply(cost, params.empty_bonus, out=cost, where=empty)
        np.logical_not(inside, out=inside)
        np.copyto(cost, np.inf, where=inside)
        del empty, inside
        index = np.argmin(cost, 1)
        consider(cost[rows, index], axis, plane[rows, index])

        # Exact cuts at the references' tight bounds: bins alone would leave empty slivers.
        for plane, below, above in (
                (np.minimum.reduceat(ref_lo[:, axis], ref_start), 0, counts),
                (np.maximum.reduceat(ref_hi[:, axis], ref_start), counts, 0)):
            inside = (plane > cell_lo[:, axis]) & (plane < cell_hi[:, axis])
            cost = _split_cost(params, dims, area, axis, plane.astype(np.float64) - low,
                               below, above)
            consider(np.where(inside, cost, np.inf), axis, plane)
    return best_cost, best_axis, best_plane


def _exact_best_splits(params, cell_lo, cell_hi, counts, first_ref, refs, width):
    """Exact SAH over all candidate planes of small nodes (at most `width` references each).

    Every reference bound is a candidate. The nodes' references are packed into (n, width)
    arrays (padding counts on no side), and each candidate is compared against all of its
    node's boxes: below = low end < plane, above = high end > plane, planar = flat at the plane
    (planar references go to the cheaper side). Returns (cost, axis, plane float32).
    """
    slots = np.arange(width)
    used = slots[None, :] < counts[:, None]
    index = np.minimum(first_ref[:, None] + slots, len(refs) - 1)
    group = _gather_refs(refs, index)                                   # (n, width, 7)
    del index
    per_axis = []
    for axis in range(3):
        lo = np.where(used, group[:, :, axis], np.float32(np.inf))
        hi = np.where(used, group[:, :, 3 + axis], np.float32(-np.inf))
        planar = used & (lo == hi)
        cand = np.concatenate([lo, hi], 1)                      # (n, 2 width)
        # Counts as int8 (width <= 16), viewing each comparison's bools as 0/1 bytes.
        below = np.zeros(cand.shape, np.int8)
        above = np.zeros(cand.shape, np.int8)
        planar_rows = planar.any(1)
        test = np.empty(cand.shape, bool)
        test8 = test.view(np.int8)
        for j in range(width):
            np.less(lo[:, j:j + 1], cand, out=test)
            below += test8
            np.greater(hi[:, j:j + 1], cand, out=test)
            above += test8
        on_plane = None
        if planar_rows.any():
            # Planar references are rare: count them only in the rows that have some.
            pr = np.flatnonzero(planar_rows)
            p_lo, p_cand, p_planar = lo[pr], cand[pr], planar[pr]
            p_on = np.zeros(p_cand.shape, np.int8)
            test = np.empty(p_cand.shape, bool)
            test8 = test.view(np.int8)
            for j in range(width):
                np.equal(p_lo[:, j:j + 1], p_cand, out=test)
                test &= p_planar[:, j:j + 1]
                p_on += test8
            on_plane = np.zeros(cand.shape, np.int8)
            on_plane[pr] = p_on
        per_axis.append(_ranking_terms(params, cand, below, above, on_plane, planar_rows))
    del group
    return _rank_exact(params, per_axis, cell_lo, cell_hi)


def _ranking_terms(params, cand, below, above, on_plane, planar_rows):
    """What `_rank_exact` needs of one axis of `_exact_best_splits`' counts: counts as
    float32, the empty-bonus factor.

    Planar variants (planar references below / above) only for the rows that have planar
    references, `planar_at[row]` a planar row's index among them.
    """
    bonus = np.float32(params.empty_bonus)
    one = np.float32(1)

    def factor(n_below, n_above):
        return np.where((n_below == 0) | (n_above == 0), bonus, one)

    terms = dict(cand=cand, below=below, above=above, on_plane=on_plane,
                 nb=below.astype(np.float32), na=above.astype(np.float32),
                 fac=factor(below, above), planar_rows=planar_rows)
    if on_plane is not None:
        pr = np.flatnonzero(planar_rows)
        b, a, o = below[pr], above[pr], on_plane[pr]
        b_o, a_o = b + o, a + o
        terms.update(
            planar_at=np.cumsum(planar_rows) - 1,
            variants=((b_o.astype(np.float32), terms["na"][pr], factor(b_o, a)),
                      (terms["nb"][pr], a_o.astype(np.float32), factor(b, a_o))))
    return terms


def _rank_exact(params, per_axis, cell_lo, cell_hi):
    """Cheapest candidate of each node from the counts of `_exact_best_splits`, for cells
    (cell_lo, cell_hi): cost, axis and plane."""
    dims = (cell_hi.astype(np.float64) - cell_lo)
    inv_area = 1.0 / _surface_area(dims)
    dims = dims.astype(np.float32)
    n = len(dims)
    best_cost = np.full(n, np.inf)
    best_axis = np.zeros(n, np.int64)
    best_plane = np.zeros(n, np.float32)
    rows = np.arange(n)
    K_T = np.float32(params.traversal_cost)
    for axis, terms in enumerate(per_axis):
        cand, on_plane = terms["cand"], terms["on_plane"]
        nb, na, fac, planar_rows = terms["nb"], terms["na"], terms["fac"], terms["planar_rows"]
        # Costs in float32 (they only rank candidates; the caller recounts the chosen plane).
        # With w the width below the plane, area_below = w P + Q and area_above = R - w P
        # (all scaled by K_I / area).
        side_a, side_b = dims[:, (axis + 1) % 3], dims[:, (axis + 2) % 3]
        scale = (2 * params.intersection_cost * inv_area).astype(np.float32)
        P = ((side_a + side_b) * scale)[:, None]
        Q = (side_a * side_b * scale)[:, None]
        R = dims[:, axis, None] * P + Q
        cell_low = cell_lo[:, axis:axis + 1]
        inside = (cand > cell_low) & (cand < cell_hi[:, axis:axis + 1])
        wP = np.where(inside, cand - cell_low, np.float32(0)) * P
        no_plane = np.where(inside, np.float32(1), np.float32(np.inf))

        def variant(n_below, n_above, fac, wP=wP, Q=Q, R=R, no_plane=no_plane):
            # ((wP + Q) n_below + (R - wP) n_above + K_T) (lambda if a side is empty)
            return ((wP + Q) * n_below + (R - wP) * n_above + K_T) * fac * no_plane

        cost = variant(nb, na, fac)
        if on_plane is not None:
            # Planar references on the cheaper side, with its empty bonus; only rows that have
            # planar references (elsewhere both variants equal the plain one).
            pr = np.flatnonzero(planar_rows)
            sub = dict(wP=wP[pr], Q=Q[pr], R=R[pr], no_plane=no_plane[pr])
            variants = terms["variants"]
            cost[pr] = np.minimum(variant(*variants[0], **sub), variant(*variants[1], **sub))
        k = np.argmin(cost, 1)
        c = cost[rows, k].astype(np.float64)
        better = c < best_cost
        best_cost[better] = c[better]
        best_axis[better] = axis
        best_plane[better] = cand[rows[better], k[better]]
    return best_cost, best_axis, best_plane


# ---------------------------------------------------------------------------------------------
# The build

EXACT_WIDTHS = (1, 2, 4, 8, 16)   # nodes with up to 16 references: exact SAH in padded groups
EXACT_CHUNK = 16384               # nodes per exact-SAH step (temporaries stay in cache)
BINNED_CHUNK = 1024               # nodes per binned-SAH step (cost arrays stay in cache)


def root_bounds(boxes_lo, boxes_hi, vertices):
    """The root cell (2, 3) float32: the boxes' bounds (the vertices' when there are none),
    flat axes padded, rounded outward to float32; both builders take it from here."""
    if len(boxes_lo):
        lo, hi = boxes_lo.min(0).astype(np.float64), boxes_hi.max(0).astype(np.float64)
    elif len(vertices):
        lo, hi = vertices.min(0).astype(np.float64), vertices.max(0).astype(np.float64)
    else:
        lo, hi = np.zeros(3), np.zeros(3)
    # A scene flat in an axis would give cells of zero width there; pad such axes a little.
    extent = hi - lo
    pad = np.maximum(1e-4 * extent.max(), 1e-6 * np.maximum(np.abs(lo), np.abs(hi)))
    pad = np.maximum(pad, 1e-6)
    flat = extent <= 1e-6 * np.maximum(extent.max(), 0)
    lo = np.where(flat, lo - pad, lo)
    hi = np.where(flat, hi + pad, hi)
    return np.stack([_round_down_f32(lo), _round_up_f32(hi)]).astype(np.float32)


def _no_decisions(n: int) -> tuple:
    """Split decisions of n nodes, none made yet: cost, axis, plane."""
    return np.full(n, np.inf), np.zeros(n, np.int64), np.zeros(n, np.float32)


def _best_splits(params, cell_lo, cell_hi, counts, ref_start, refs):
    """Best split of every node given (all with at least one reference): cost, axis, plane.

    Small nodes get exact SAH over all their references' bounds, in chunks of EXACT_CHUNK
    nodes (smaller temporaries); bigger ones binned SAH.
    """
    n = len(counts)
    cost, axis, plane = _no_decisions(n)
    smaller = 0
    for width in EXACT_WIDTHS:
        group = np.flatnonzero((counts > smaller) & (counts <= width))
        smaller = width
        for at in range(0, len(group), EXACT_CHUNK):
            part = group[at:at + EXACT_CHUNK]
            cost[part], axis[part], plane[part] = _exact_best_splits(
                params, cell_lo[part], cell_hi[part], counts[part], ref_start[part],
                refs, width)
    big = np.flatnonzero(counts > smaller)
    if len(big):
        if int(counts[big].sum()) < len(refs):       # the big nodes' references only
            big_counts = counts[big]
            ref_sel = np.arange(int(big_counts.sum())) + np.repeat(
                ref_start[big] - exclusive_cumsum(big_counts)[:-1], big_counts)
            refs = _gather_refs(refs, ref_sel)
        # In chunks of BINNED_CHUNK nodes: the (nodes, bins) cost arrays stay in cache.
        ref_lo, ref_hi = refs[:, 0:3], refs[:, 3:6]
        big_first = exclusive_cumsum(counts[big])
        for at in range(0, len(big), BINNED_CHUNK):
            part = big[at:at + BINNED_CHUNK]
            refs = slice(big_first[at], big_first[at + len(part)])
            cost[part], axis[part], plane[part] = _binned_best_splits(
                params, cell_lo[part], cell_hi[part], counts[part], ref_lo[refs], ref_hi[refs])
    return cost, axis, plane


@dataclass
class _Frontier:
    """The nodes of one level, not yet decided, with their references (rows sorted by node)
    and their paths' bad-refine counts."""

    cell_lo: np.ndarray        # (n, 3) float32
    cell_hi: np.ndarray
    counts: np.ndarray         # (n,) int64 references per node
    bad_refines: np.ndarray    # (n,) int64
    refs: np.ndarray           # (R, REF_WORDS) float32

    def __len__(self) -> int:
        return len(self.counts)



@dataclass
class _Level:
    """One level's nodes as decided: their words with the fields that depend on the nodes
    before them left at zero (an inner node's child index, a leaf's offset into
    leaf_indices), which nodes are leaves, the leaves' triangle ids and the level's share
    of the SAH cost."""

    words: np.ndarray          # (n, 2) uint32
    make_leaf: np.ndarray      # (n,) bool
    leaf_triangles: np.ndarray  # uint32
    sah_cost: float



@dataclass(frozen=True)
class _BuildContext:
    params: KDTreeParams
    depth_cap: int
    corners: np.ndarray        # (T, 3, 3) float32 triangle corners, for clipping
    root_area: float


def _step(fr: _Frontier, level: int, ctx: _BuildContext):
    """Decide every node of one level: (_Level, the next level's frontier or None)."""
    params = ctx.params
    cell_lo, cell_hi, counts, refs = fr.cell_lo, fr.cell_hi, fr.counts, fr.refs
    node_count = len(counts)
    ref_start = exclusive_cumsum(counts)
    dims = cell_hi.astype(np.float64) - cell_lo
    area = _surface_area(dims)

    # 1. Best split of every non-empty node that may still split.
    cost, axis, plane = _no_decisions(node_count)
    if level < ctx.depth_cap:
        cand = np.flatnonzero(counts > 0)
        if len(cand):
            cost[cand], axis[cand], plane[cand] = _best_splits(
                params, cell_lo[cand], cell_hi[cand], counts[cand], ref_start[cand], refs)
    has_plane = np.isfinite(cost)

    # 2. Exact counts at the chosen planes (references of nodes with a plane only); planar
    #    references go to the cheaper side.
    n_below = np.zeros(node_count, np.int64)
    n_above = np.zeros(node_count, np.int64)
    n_planar = np.zeros(node_count, np.int64)
    ref_has_plane = np.repeat(has_plane, counts)
    cand = np.flatnonzero(has_plane)          # all non-empty
    sel = np.flatnonzero(ref_has_plane)
    sel_counts = counts[cand]
    sel_starts = exclusive_cumsum(sel_counts)[:-1]
    flat_index = REF_WORDS * sel + np.repeat(axis[cand], sel_counts)
    ref_plane = np.repeat(plane[cand], sel_counts)
    lo_on_axis = refs.reshape(-1)[flat_index]
    flat_index += 3
    hi_on_axis = refs.reshape(-1)[flat_index]
    del flat_index
    below = lo_on_axis < ref_plane
    above = hi_on_axis > ref_plane
    planar = (lo_on_axis == ref_plane) & (hi_on_axis == ref_plane)
    del lo_on_axis, hi_on_axis, ref_plane
    if len(cand):
        n_below[cand] = np.add.reduceat(below, sel_starts, dtype=np.int64)
        n_above[cand] = np.add.reduceat(above, sel_starts, dtype=np.int64)
        n_planar[cand] = np.add.reduceat(planar, sel_starts, dtype=np.int64)
    # Split costs only where there is a plane (empty nodes and the last level have none).
    planar_below = np.ones(node_count, bool)
    split_cost = np.full(node_count, np.inf)
    if len(cand):
        c_axis = axis[cand]
        width_below = plane[cand].astype(np.float64) - cell_lo[cand, c_axis]
        c_area = area[cand]
        safe_area = np.where(c_area > 0, c_area, 1.0)
        c_dims, c_below, c_above = dims[cand], n_below[cand], n_above[cand]
        c_planar = n_planar[cand]
        cost_planar_below = _split_cost(params, c_dims, safe_area, c_axis, width_below,
                                        c_below + c_planar, c_above)
        cost_planar_above = _split_cost(params, c_dims, safe_area, c_axis, width_below,
                                        c_below, c_above + c_planar)
        planar_below[cand] = cost_planar_below <= cost_planar_above
        split_cost[cand] = np.minimum(cost_planar_below, cost_planar_above)

    # 3. Leaf or split: automatic termination with pbrt's allowance of bad refines.
    leaf_cost = params.intersection_cost * counts
    bad = split_cost >= leaf_cost
    bad_refines = fr.bad_refines + bad
    # Unlike pbrt, a small node never refines badly: that only deepened the tree (docs/kdtree.md).
    make_leaf = ~has_plane | (bad & ((bad_refines >= params.max_bad_refines)
                                     | (counts < params.small_node)))
    split = ~make_leaf
    split_count = int(split.sum())

    # 4. This level's nodes (child indices and leaf offsets are added by `_write_nodes`).
    if int(counts.max(initial=0)) > MAX_NODE_FIELD:
        raise ValueError("kd-tree leaf too large for the 30-bit reference count")
    words = np.zeros((node_count, 2), np.uint32)
    words[:, 0] = np.where(make_leaf, LEAF_TAG | PLAIN_FIELD.put(counts), axis)
    words[:, 1] = np.where(make_leaf, 0, plane.view(np.uint32))
    leaf_triangles = _ref_triangles(refs)[np.repeat(make_leaf, counts)].astype(np.uint32)
    leaf_area = area[make_leaf] / ctx.root_area
    sah_cost = (params.traversal_cost * area[split].sum() / ctx.root_area
                + params.intersection_cost * (leaf_area * counts[make_leaf]).sum())
    decided = _Level(words, make_leaf, leaf_triangles, float(sah_cost))
    if not split_count:
        return decided, None

    # 5. Send the references of split nodes (a subset of `sel`) to the children; clip those
    #    that straddle the plane.
    split_nodes = np.flatnonzero(split)
    in_split = split[cand]                                  # per node of `cand`
    sel_split = np.repeat(in_split, sel_counts)
    src = sel[sel_split]                                    # reference ids, by node
    below, above, planar = below[sel_split], above[sel_split], planar[sel_split]
    split_counts = counts[split_nodes]
    planar_side_below = np.repeat(planar_below[split_nodes], split_counts)
    goes_below = (below & ~planar) | (planar & planar_side_below)
    goes_above = (above & ~planar) | (planar & ~planar_side_below)
    del below, above, planar, planar_side_below
    straddles = np.flatnonzero(goes_below & goes_above)     # positions in src
    if len(straddles):
        s_node = np.repeat(split_nodes, split_counts)[straddles]
        (b_lo, b_hi, b_ok), (a_lo, a_hi, a_ok) = _clip_straddlers(
            ctx.corners[_ref_triangles(refs)[src[straddles]]].astype(np.float64),
            cell_lo[s_node], cell_hi[s_node], axis[s_node], plane[s_node])
        goes_below[straddles] = b_ok
        goes_above[straddles] = a_ok

    # Children in parent order, each parent's below child first: node j's children are
    # 2 rank(j) and 2 rank(j) + 1. References keep their order within a child.
    seg = exclusive_cumsum(split_counts)[:-1]
    n_child_below = np.add.reduceat(goes_below, seg, dtype=np.int64)
    n_child_above = np.add.reduceat(goes_above, seg, dtype=np.int64)
    child_counts = np.stack([n_child_below, n_child_above], 1).reshape(-1)
    child_start = exclusive_cumsum(child_counts)
    total = int(child_start[-1])
    new_src = np.empty(total, np.int64)
    at_straddler = []
    for side, goes, n_child in ((0, goes_below, n_child_below), (1, goes_above, n_child_above)):
        pos_in_src = np.flatnonzero(goes)
        shift = child_start[0::2][:-1] if side == 0 else child_start[1::2]
        shift = shift - exclusive_cumsum(n_child)[:-1]
        where = np.arange(len(pos_in_src)) + np.repeat(shift, n_child)
        new_src[where] = src[pos_in_src]
        if len(straddles):
            ok = (b_ok, a_ok)[side]
            at_straddler.append(where[(np.cumsum(goes) - 1)[straddles[ok]]])
    new_refs = _gather_refs(refs, new_src)
    if len(straddles):
        # Straddlers get their clipped box on each side they go to (the 6 box words of
        # a row written as one 24-byte item).
        box_items = new_refs[:, 0:6].view(_BOX_ROW)[:, 0]
        for at, lo_s, hi_s, ok in ((at_straddler[0], b_lo, b_hi, b_ok),
                                   (at_straddler[1], a_lo, a_hi, a_ok)):
            box = np.concatenate([lo_s, hi_s], 1)
            box_items[at] = box.view(_BOX_ROW)[:, 0][ok]
    del new_src

    # 6. Children's cells and bad-refine counts.
    child_lo = np.repeat(cell_lo[split_nodes], 2, 0)
    child_hi = np.repeat(cell_hi[split_nodes], 2, 0)
    child_axis = np.repeat(axis[split_nodes], 2)
    child_plane = np.repeat(plane[split_nodes], 2)
    rows = np.arange(2 * split_count)
    child_hi[rows[0::2], child_axis[0::2]] = child_plane[0::2]
    child_lo[rows[1::2], child_axis[1::2]] = child_plane[1::2]
    return decided, _Frontier(child_lo, child_hi, child_counts,
                              np.repeat(bad_refines[split_nodes], 2), new_refs)


def _write_nodes(levels: list) -> tuple:
    """Nodes breadth-first, level after level, and the leaves' triangle lists: fills in the
    child index of every inner node and the leaf_indices offset of every leaf."""
    level_base = leaf_total = 0
    for decided in levels:
        words, make_leaf = decided.words, decided.make_leaf
        split_rank = np.cumsum(~make_leaf) - 1
        first_child = level_base + len(words) + 2 * split_rank
        if (~make_leaf).any() and first_child.max() > MAX_NODE_FIELD:
            raise ValueError("kd-tree too large for the 30-bit child index")
        leaf_counts = np.where(make_leaf, PLAIN_FIELD.get(words[:, 0]), 0).astype(np.int64)
        leaf_offset = leaf_total + exclusive_cumsum(leaf_counts)[:-1]
        words[:, 0] |= np.where(make_leaf, 0, PLAIN_FIELD.put(first_child)).astype(np.uint32)
        words[:, 1] |= np.where(make_leaf, leaf_offset, 0).astype(np.uint32)
        level_base += len(words)
        leaf_total += int(leaf_counts.sum())
    nodes = np.concatenate([d.words for d in levels])
    leaf_indices = np.concatenate([d.leaf_triangles for d in levels]).astype(np.uint32)
    return nodes, leaf_indices


def checked_mesh(vertices, triangles):
    """float32 (V, 3) vertices and (T, 3) triangles, or ValueError for indices out of range
    or non-finite coordinates (both builders, core/accel/binned.py too)."""
    vertices = np.ascontiguousarray(vertices, np.float32).reshape(-1, 3)
    triangles = np.asarray(triangles).reshape(-1, 3)
    if len(triangles) and (triangles.min() < 0 or triangles.max() >= len(vertices)):
        raise ValueError("a triangle refers to a vertex that does not exist")
    if not np.isfinite(vertices).all():
        raise ValueError("vertex coordinates contain NaN or infinity")
    return vertices, triangles


def build_kdtree(vertices, triangles, params: KDTreeParams | None = None, progress=None) -> KDTree:
    """Build an SAH kd-tree with perfect splits over triangles (see module docstring).

    `progress(fraction, message)`, if given, is called once per level (once per level of
    each part in the parallel phase), always on the calling thread; an exception it raises
    stops the build.
    """
    params = params or KDTreeParams()
    started = time.perf_counter()
    vertices, triangles = checked_mesh(vertices, triangles)
    triangles = triangles.astype(np.int64)
    triangle_count = len(triangles)

    corners = vertices[triangles]                                     # (T, 3, 3) float32
    c64 = corners.astype(np.float64)
    normal = np.cross(c64[:, 1] - c64[:, 0], c64[:, 2] - c64[:, 0])
    kept = np.flatnonzero((normal != 0).any(1))                        # drop zero-area triangles
    del normal, c64

    refs = np.empty((len(kept), REF_WORDS), np.float32)
    refs[:, 0:3] = corners[kept].min(1)                               # exact: corners are float32
    refs[:, 3:6] = corners[kept].max(1)
    refs[:, 6].view(np.int32)[:] = kept
    bounds = root_bounds(refs[:, 0:3], refs[:, 3:6], vertices)

    ctx = _BuildContext(params, params.depth_cap(triangle_count), corners,
                        float(_surface_area(bounds[1].astype(np.float64) - bounds[0])))
    root = _Frontier(bounds[:1].copy(), bounds[1:].copy(), np.array([len(kept)], np.int64),
                     np.zeros(1, np.int64), refs)
    del refs

    levels, frontier, level = [], root, 0
    while frontier is not None:
        if progress is not None:
            progress(min(level / (ctx.depth_cap + 1), 1.0),
                     f"kd-tree level {level}: {len(frontier)} nodes, "
                     f"{len(frontier.refs)} references")
        decided, frontier = _step(frontier, level, ctx)
        levels.append(decided)
        level += 1
    nodes, leaf_indices = _write_nodes(levels)
    leaf_levels = [k for k, d in enumerate(levels) if d.make_leaf.any()]
    tree = KDTree(nodes, leaf_indices, bounds)
    tree.stats = {
        "nodes": len(nodes),
        "leaves": sum(int(d.make_leaf.sum()) for d in levels),
        "empty_leaves": sum(int((d.make_leaf & (d.words[:, 0] == LEAF_TAG)).sum())
                            for d in levels),
        "depth": max(leaf_levels, default=0),
        "depth_cap": ctx.depth_cap,
        "references": len(leaf_indices),
        "refs_per_triangle": len(leaf_indices) / max(len(kept), 1),
        "dropped_degenerate": triangle_count - len(kept),
        "bytes": tree.nbytes,
        "sah_cost": float(sum(d.sah_cost for d in levels)),
        "build_seconds": time.perf_counter() - started,
        "threads": 1,
    }
    if progress is not None:
        progress(1.0, f"kd-tree done: {len(nodes)} nodes, {len(leaf_indices)} references")
    return tree
