"""The builder's buffer pool (core/accel/buffer_pool.py): a region nobody holds is lent again,
a held one never is, and every lent buffer reads back what its user wrote."""
from __future__ import annotations

import numpy as np

from kdtrace.core.accel.buffer_pool import MIN_POOLED_BYTES
from kdtrace.core.accel.device import DeviceContext


def _fill(builder, buffer, value, nbytes):
    import pyopencl as cl
    cl.enqueue_copy(builder.queue, buffer, np.full(nbytes // 4, value, np.uint32))


def _read(builder, buffer, nbytes):
    return builder.read(buffer, np.uint32, nbytes // 4)


def test_freed_regions_are_lent_again_and_held_ones_never():
    b = DeviceContext("cpu")
    pool, n = b.buffers, 3 * MIN_POOLED_BYTES
    kept = [pool.take(n) for _ in range(3)]
    for i, buffer in enumerate(kept):
        _fill(b, buffer, i + 1, n)
    held = pool.held_bytes
    gone = kept.pop(1)
    offset = gone.offset
    del gone
    again = pool.take(n)                      # the freed region, no new chunk
    assert again.offset == offset and pool.held_bytes == held
    _fill(b, again, 7, n)
    for value, buffer in zip((1, 3, 7), kept + [again]):
        assert (_read(b, buffer, n) == value).all()
    # Sub-buffers still held keep their contents after the pool lets the chunks go.
    pool.release()
    assert pool.held_bytes == 0
    assert (_read(b, kept[0], n) == 1).all() and (_read(b, again, n) == 7).all()
    small = pool.take(1000)
    assert pool.held_bytes == 0 and small.size >= 1000
