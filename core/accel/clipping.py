"""Perfect splits for the numpy kd-tree builder (core/accel/kdtree.py): the references that
straddle their node's split plane are clipped to the node's cell and cut at the plane in float64
(Sutherland-Hodgman on padded polygon arrays, every step vectorised over all such references),
and each half's box rounded outward to float32 (docs/kdtree.md)."""
from __future__ import annotations

import numpy as np

from .arrays import exclusive_cumsum


def round_down_f32(x: np.ndarray) -> np.ndarray:
    """The largest float32 <= x (x float64)."""
    f = x.astype(np.float32)
    return np.where(f.astype(np.float64) > x, np.nextafter(f, np.float32(-np.inf)), f)


def round_up_f32(x: np.ndarray) -> np.ndarray:
    """The smallest float32 >= x (x float64)."""
    f = x.astype(np.float32)
    return np.where(f.astype(np.float64) < x, np.nextafter(f, np.float32(np.inf)), f)


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


def clip_straddlers(corners, cell_lo, cell_hi, axis, plane):
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
        lo32 = np.maximum(round_down_f32(np.where(positive[:, None], lo, 0.0)), child_lo)
        hi32 = np.minimum(round_up_f32(np.where(positive[:, None], hi, 0.0)), child_hi)
        halves.append((lo32, hi32, positive))
    return halves

