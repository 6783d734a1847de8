"""Tiles of a frame and the pool that hands them out to slaves dynamically.

Dynamic pull (rather than a fixed region per slave) keeps fast slaves busy and lets a lost
slave's tiles go back to the others.
"""
from __future__ import annotations

import threading


def tile_grid(region, tile_size: int) -> list:
    """(x, y, w, h) tiles covering region (x0, y0, x1, y1; top-left origin, x1/y1 exclusive),
    row by row from the top; the last tile of a row or column may be smaller."""
    x0, y0, x1, y1 = (int(v) for v in region)
    if isinstance(tile_size, bool) or not isinstance(tile_size, int) or tile_size < 1:
        raise ValueError(f"tile size must be a positive integer, got {tile_size!r}")
    if x1 <= x0 or y1 <= y0:
        raise ValueError(f"empty region {region!r}")
    return [(x, y, min(tile_size, x1 - x), min(tile_size, y1 - y))
            for y in range(y0, y1, tile_size) for x in range(x0, x1, tile_size)]


class TilePool:
    """Thread-safe set of tile indices: pending -> taken -> done (or back to pending)."""

    def __init__(self, count: int):
        self.count = count
        self._pending = list(range(count - 1, -1, -1))  # pop() hands out index 0 first
        self._done = set()
        self._closed = False
        self._changed = threading.Condition()

    def take(self, timeout: float | None = None) -> int | None:
        """The next pending tile; waits up to `timeout` while none is pending but some are still
        out (they may come back). None if nothing to hand out."""
        with self._changed:
            self._changed.wait_for(lambda: self._pending or self._closed or self.all_done, timeout)
            if self._closed or not self._pending:
                return None
            return self._pending.pop()

    def put_back(self, index: int) -> None:
        """A tile whose slave failed goes back to the front of the queue."""
        with self._changed:
            if index not in self._done and index not in self._pending:
                self._pending.append(index)
                self._changed.notify_all()

    def mark_done(self, index: int) -> bool:
        """Record a finished tile; False if it was already done (a duplicate)."""
        with self._changed:
            if index in self._done:
                return False
            self._done.add(index)
            if index in self._pending:
                self._pending.remove(index)
            self._changed.notify_all()
            return True

    def close(self) -> None:
        """Stop handing out tiles (cancel); wakes every waiting taker."""
        with self._changed:
            self._closed = True
            self._changed.notify_all()

    @property
    def done_count(self) -> int:
        return len(self._done)

    @property
    def all_done(self) -> bool:
        return len(self._done) == self.count
