"""The SAH split search of the numpy kd-tree builder (core/accel/kdtree.py): for every node of a
level, the cheapest plane by exact SAH over its references' bounds (small nodes, in padded
groups) or by binned SAH plus the exact empty-space cuts (big nodes); the cost model is
Wald & Havran 2006's with `KDTreeParams`' constants (docs/kdtree.md)."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .arrays import exclusive_cumsum
from .ref_rows import gather_refs

if TYPE_CHECKING:
    from .kdtree import KDTreeParams

EXACT_WIDTHS = (1, 2, 4, 8, 16)   # nodes with up to 16 references: exact SAH in padded groups
EXACT_CHUNK = 16384               # nodes per exact-SAH step (temporaries stay in cache)
BINNED_CHUNK = 1024               # nodes per binned-SAH step (cost arrays stay in cache)


def surface_area(dims: np.ndarray) -> np.ndarray:
    return 2.0 * (dims[..., 0] * dims[..., 1] + dims[..., 1] * dims[..., 2]
                  + dims[..., 2] * dims[..., 0])


def sah_split_cost(params: KDTreeParams, dims, area, axis, below_width, count_below,
                   count_above):
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
    area = surface_area(dims)
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
            cost = sah_split_cost(params, dims, area, axis, plane.astype(np.float64) - low,
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
    group = gather_refs(refs, index)                                   # (n, width, 7)
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
    inv_area = 1.0 / surface_area(dims)
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


def no_decisions(n: int) -> tuple:
    """Split decisions of n nodes, none made yet: cost, axis, plane."""
    return np.full(n, np.inf), np.zeros(n, np.int64), np.zeros(n, np.float32)


def best_splits(params, cell_lo, cell_hi, counts, ref_start, refs):
    """Best split of every node given (all with at least one reference): cost, axis, plane.

    Small nodes get exact SAH over all their references' bounds, in chunks of EXACT_CHUNK
    nodes (smaller temporaries); bigger ones binned SAH.
    """
    n = len(counts)
    cost, axis, plane = no_decisions(n)
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
            refs = gather_refs(refs, ref_sel)
        # In chunks of BINNED_CHUNK nodes: the (nodes, bins) cost arrays stay in cache.
        ref_lo, ref_hi = refs[:, 0:3], refs[:, 3:6]
        big_first = exclusive_cumsum(counts[big])
        for at in range(0, len(big), BINNED_CHUNK):
            part = big[at:at + BINNED_CHUNK]
            refs = slice(big_first[at], big_first[at + len(part)])
            cost[part], axis[part], plane[part] = _binned_best_splits(
                params, cell_lo[part], cell_hi[part], counts[part], ref_lo[refs], ref_hi[refs])
    return cost, axis, plane

