"""Morton (Z-order) curves over a box: points that are near each other in space get near
positions in the order. The tracer traces scattered rays in their origins' order
(slave.tracer.ray_order) and the exporter stores triangles in their corners' order
(core.scene.spatial_order); neither changes what is computed, only what stays in cache."""
from __future__ import annotations

import functools

import numpy as np

MORTON_BITS = 10        # per axis: a 30-bit key


@functools.lru_cache(maxsize=1)
def _spread() -> np.ndarray:
    """The MORTON_BITS bits of i spread to every third bit (a Morton code's lookup table)."""
    i = np.arange(1 << MORTON_BITS, dtype=np.uint32)
    out = np.zeros_like(i)
    for bit in range(MORTON_BITS):
        out |= ((i >> np.uint32(bit)) & np.uint32(1)) << np.uint32(3 * bit)
    return out


def morton_order(points: np.ndarray, lo, hi) -> np.ndarray:
    """The indices of `points` (n, 3) in the Morton order of their cells in the box [lo, hi]
    (points outside go to its nearest cell; equal cells keep their given order). The cells are
    computed in float32 operations, which round the same on every machine, so the same points
    give the same order everywhere."""
    lo, hi = np.asarray(lo, np.float32), np.asarray(hi, np.float32)
    cells = np.float32((1 << MORTON_BITS) - 1)
    scale = cells / np.maximum(hi - lo, np.float32(1e-30))
    spread = _spread()
    key = np.zeros(len(points), np.uint32)
    for axis in range(3):
        x = np.subtract(points[:, axis], lo[axis], dtype=np.float32)
        x *= scale[axis]
        np.clip(x, 0, cells, out=x)
        key |= spread[x.astype(np.int32)] << np.uint32(axis)
    # The 30-bit keys sorted in two stable 15-bit passes (numpy sorts 16-bit keys by radix:
    # half the time of an argsort of wider keys).
    low = np.argsort((key & 0x7FFF).astype(np.uint16), kind="stable")
    return low[np.argsort((key[low] >> 15).astype(np.uint16), kind="stable")]
