"""Device memory of the kd-tree builder and compactor, reused within a build or compaction.

A new buffer's memory is new pages, which the operating system zeroes at their first touch,
and a compaction creates many times its peak in buffers over its run (per level and step;
docs/kdtree_native.md, "Device memory"). So the builder's large buffers are sub-buffers of a
few big ones (chunks): a region that is free again is lent again, its pages already touched. The chunks go when the build or
compaction ends (release), so nothing is held between renders.

Reuse is safe on the builder's in-order queue: everything that reads or writes a pooled
buffer is a queued command (kernels, fills, copies), so the commands of a region's next user
run after those of its last one. Small buffers are not pooled (malloc recycles their memory);
nor are results that outlive the work (the tree's arrays, mapped): `standalone`.
"""
from __future__ import annotations

import sys

MIN_POOLED_BYTES = 1 << 20
MIN_CHUNK_BYTES = 256 << 20
ALIGN = 4096


def _round_up(n: int, to: int) -> int:
    return -(-int(n) // to) * to


class _Chunk:
    def __init__(self, buffer, size):
        self.buffer, self.size = buffer, size
        self.free = [(0, size)]         # (offset, size), by offset, coalesced
        self.lent = []                  # (offset, size, sub-buffer)

    def place(self, nbytes):
        for i, (offset, size) in enumerate(self.free):
            if size >= nbytes:
                if size == nbytes:
                    del self.free[i]
                else:
                    self.free[i] = (offset + nbytes, size - nbytes)
                return offset
        return None

    def collect(self):
        lent = []
        for offset, size, buffer in self.lent:
            # References: the tuple, this loop's name, getrefcount's argument.
            if sys.getrefcount(buffer) > 3:
                lent.append((offset, size, buffer))
            else:
                self.free.append((offset, size))
        self.lent = lent
        merged = []
        for offset, size in sorted(self.free):
            if merged and merged[-1][0] + merged[-1][1] == offset:
                merged[-1] = (merged[-1][0], merged[-1][1] + size)
            else:
                merged.append((offset, size))
        self.free = merged


class BufferPool:
    def __init__(self, cl, context, device):
        self._cl, self._context = cl, context
        self._align = max(ALIGN, int(device.mem_base_addr_align) // 8)
        self._chunks: list[_Chunk] = []

    def standalone(self, nbytes: int):
        cl = self._cl
        return cl.Buffer(self._context, cl.mem_flags.READ_WRITE, max(int(nbytes), 4))

    def take(self, nbytes: int):
        """A READ_WRITE buffer of at least nbytes (contents undefined)."""
        if nbytes < MIN_POOLED_BYTES:
            return self.standalone(nbytes)
        nbytes = _round_up(nbytes, self._align)
        for chunk in self._chunks:
            chunk.collect()
        for chunk in self._chunks:
            offset = chunk.place(nbytes)
            if offset is not None:
                break
        else:
            # A new chunk; wholly free ones go first, so that the pool does not add to the peak.
            self._chunks = [c for c in self._chunks if c.lent]
            held = sum(c.size for c in self._chunks)
            size = _round_up(max(nbytes, MIN_CHUNK_BYTES, held // 4), self._align)
            chunk = _Chunk(self.standalone(size), size)
            self._chunks.append(chunk)
            offset = chunk.place(nbytes)
        buffer = chunk.buffer.get_sub_region(offset, nbytes)
        chunk.lent.append((offset, nbytes, buffer))
        return buffer

    def release(self) -> None:
        """Drop the chunks (a sub-buffer still held keeps its chunk's memory until it goes)."""
        self._chunks = []

    @property
    def held_bytes(self) -> int:
        return sum(c.size for c in self._chunks)
