"""Tiles of a frame and the pool that hands them out to slaves dynamically.

Dynamic pull (rather than a fixed region per slave) keeps fast slaves busy and lets a lost
slave's tiles go back to the others. Near the end of a frame, when nothing is pending, an idle
slave may take a *copy* of a tile still outstanding elsewhere (the first result wins): a slow or
hung slave then no longer holds up the frame.
"""
from __future__ import annotations

import math
import threading
import time


def tile_dims(tile_size) -> tuple:
    """(width, height) of a tile size given as an int (square) or a (width, height) pair."""
    if isinstance(tile_size, (tuple, list)) and len(tile_size) == 2:
        dims = tuple(tile_size)
    else:
        dims = (tile_size, tile_size)
    if not all(isinstance(d, int) and not isinstance(d, bool) and d >= 1 for d in dims):
        raise ValueError(f"tile size must be a positive integer or a pair of them, got {tile_size!r}")
    return dims


def partition_tile_size(region, n: int) -> tuple:
    """The (width, height) of the tiles of an n x n partition of region (Table 5b's 4x4 etc.)."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"partition must be a positive integer, got {n!r}")
    x0, y0, x1, y1 = (int(v) for v in region)
    return (max(1, math.ceil((x1 - x0) / n)), max(1, math.ceil((y1 - y0) / n)))


def tile_grid(region, tile_size) -> list:
    """(x, y, w, h) tiles covering region (x0, y0, x1, y1; top-left origin, x1/y1 exclusive),
    row by row from the top; the last tile of a row or column may be smaller. `tile_size` is an
    int (square tiles) or a (width, height) pair."""
    x0, y0, x1, y1 = (int(v) for v in region)
    tw, th = tile_dims(tile_size)
    if x1 <= x0 or y1 <= y0:
        raise ValueError(f"empty region {region!r}")
    return [(x, y, min(tw, x1 - x), min(th, y1 - y))
            for y in range(y0, y1, th) for x in range(x0, x1, tw)]


class TilePool:
    """Thread-safe tile indices: pending -> held by one or more slaves -> done (or back to
    pending when the last holder is lost)."""

    def __init__(self, count: int, max_copies: int = 2):
        self.count = count
        self.max_copies = max_copies      # holders of one tile at once (1 = no duplicates)
        self._pending = list(range(count - 1, -1, -1))  # pop() hands out index 0 first
        self._holders: dict = {}          # index -> set of holder keys
        self._taken_at: dict = {}         # index -> monotonic time first handed out
        self._done = set()
        self._closed = False
        self._changed = threading.Condition()
        self.duplicates_handed_out = 0

    def _copyable(self, holder):
        best = None
        for index, holders in self._holders.items():
            if holder in holders or len(holders) >= self.max_copies:
                continue
            key = (len(holders), self._taken_at[index])  # fewest copies, then the oldest
            if best is None or key < best[0]:
                best = (key, index)
        return None if best is None else best[1]

    def take(self, timeout: float | None = None, holder=None, duplicates: bool = False) -> int | None:
        """The next pending tile; with `duplicates`, when nothing is pending, a copy of a tile
        that other holders still have. Waits up to `timeout` for one; None if none."""
        def ready():
            return (self._pending or self._closed or self.all_done
                    or (duplicates and self._copyable(holder) is not None))
        with self._changed:
            self._changed.wait_for(ready, timeout)
            if self._closed or self.all_done:
                return None
            if self._pending:
                index = self._pending.pop()
                self._taken_at[index] = time.monotonic()
            elif duplicates:
                index = self._copyable(holder)
                if index is None:
                    return None
                self.duplicates_handed_out += 1
            else:
                return None
            self._holders.setdefault(index, set()).add(holder)
            return index

    def put_back(self, index: int, holder=None) -> None:
        """`holder` gives the tile up (its slave failed); it is pending again unless another
        holder still has it."""
        with self._changed:
            holders = self._holders.get(index)
            if holders is not None:
                holders.discard(holder)
                if holders:
                    return
                del self._holders[index]
            if index not in self._done and index not in self._pending:
                self._pending.append(index)
            self._changed.notify_all()

    def mark_done(self, index: int) -> bool:
        """Record a finished tile; False if it was already done (a duplicate)."""
        with self._changed:
            if index in self._done:
                return False
            self._done.add(index)
            self._holders.pop(index, None)
            if index in self._pending:
                self._pending.remove(index)
            self._changed.notify_all()
            return True

    def is_done(self, index: int) -> bool:
        with self._changed:
            return index in self._done

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
