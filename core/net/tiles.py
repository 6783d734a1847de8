"""Tiles of a frame and the pool that hands them out to slaves dynamically.

Dynamic pull (rather than a fixed region per slave) keeps fast slaves busy and lets a lost
slave's tiles go back to the others. Near the end of a frame, when nothing is pending, an idle
slave may take a *copy* of a tile still outstanding elsewhere (the first result wins): a slow or
hung slave then no longer holds up the frame. Only a tile held longer than COPY_AFTER times the
frame's median tile time (hand-out to result) is copied, so slaves that are merely busy with
their last tiles are not doubled (with many slaves that was tens of wasted tiles a frame).
"""
from __future__ import annotations

import bisect
import heapq
import math
import threading
import time

COPY_AFTER = 2.0    # a tile is copied once held this many median tile times


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


class TileGrid:
    """The (x, y, w, h) tiles covering region (x0, y0, x1, y1; top-left origin, x1/y1
    exclusive), row by row from the top; the last tile of a row or column may be smaller.
    Computed per index, so a frame of a million tiles costs nothing until they are asked for."""

    def __init__(self, region, tile_size):
        self.x0, self.y0, self.x1, self.y1 = (int(v) for v in region)
        self.tile_w, self.tile_h = tile_dims(tile_size)
        if self.x1 <= self.x0 or self.y1 <= self.y0:
            raise ValueError(f"empty region {region!r}")
        self.columns = -(-(self.x1 - self.x0) // self.tile_w)
        self.rows = -(-(self.y1 - self.y0) // self.tile_h)

    def __len__(self) -> int:
        return self.columns * self.rows

    def __getitem__(self, index: int) -> tuple:
        if index < 0:
            index += len(self)
        if not 0 <= index < len(self):
            raise IndexError(f"tile {index} of {len(self)}")
        row, column = divmod(index, self.columns)
        x, y = self.x0 + column * self.tile_w, self.y0 + row * self.tile_h
        return (x, y, min(self.tile_w, self.x1 - x), min(self.tile_h, self.y1 - y))

    def __iter__(self):
        return (self[i] for i in range(len(self)))


def frame_work_problem(view, tile_size, max_tile_rays: int, max_sample_rays: int) -> str | None:
    """Why a frame of `view` (core.scene.model.View) in tiles of `tile_size` is over the work
    budget (its largest tile over `max_tile_rays`, a camera sample over `max_sample_rays`, as
    View.tile_rays counts them), or None. Python integers: no product wraps."""
    per_sample = view.rays_per_sample()
    if per_sample > max_sample_rays:
        return (f"one camera sample may trace {per_sample:,} rays (lights x light samples x "
                f"bounces), at most {max_sample_rays:,}: use fewer lights, light samples or "
                f"bounces")
    w, h = _largest_tile(view.region, tile_size)
    rays = view.tile_rays(w, h)
    if rays > max_tile_rays:
        return (f"a {w} x {h} tile may trace {rays:,} rays (pixels x samples x lights x "
                f"bounces), at most {max_tile_rays:,}: use smaller tiles or fewer samples")
    return None


def fit_tile_work(view, tile_size, max_tile_rays: int, max_sample_rays: int) -> tuple:
    """`tile_size` as (width, height), halved (the longer side first) until the frame's largest
    tile is within `max_tile_rays`; ValueError (frame_work_problem's words) where a camera
    sample or a single pixel is over budget."""
    w, h = _largest_tile(view.region, tile_size)
    while frame_work_problem(view, (w, h), max_tile_rays, max_sample_rays) and w * h > 1:
        if w >= h:
            w = -(-w // 2)
        else:
            h = -(-h // 2)
    problem = frame_work_problem(view, (w, h), max_tile_rays, max_sample_rays)
    if problem:
        raise ValueError(problem)
    return (w, h) if (w, h) != _largest_tile(view.region, tile_size) else tile_dims(tile_size)


def _largest_tile(region, tile_size) -> tuple:
    w, h = tile_dims(tile_size)
    x0, y0, x1, y1 = (int(v) for v in region)
    return min(w, x1 - x0), min(h, y1 - y0)


def tile_grid(region, tile_size) -> list:
    """The tiles of TileGrid(region, tile_size) as a list (`tile_size`: an int for square
    tiles or a (width, height) pair)."""
    return list(TileGrid(region, tile_size))


class TilePool:
    """Thread-safe tile indices: pending -> held by one or more slaves -> done (or back to
    pending when the last holder is lost)."""

    def __init__(self, count: int, max_copies: int = 2, order=None):
        """`order`: the tile indices from the most to the least expensive (e.g. as measured in
        the last frame): tiles go out most expensive first, so no long tile starts last, except
        that a `cheap` take (the slots a slave fills beside its first at the start of a frame,
        only to hide the request's latency) gets the cheapest pending tile, so that no slave
        starts with two long ones. Default: index order for all."""
        self.count = count
        self.max_copies = max_copies      # holders of one tile at once (1 = no duplicates)
        self._order = None if order is None else list(order)
        if self._order is not None and sorted(self._order) != list(range(count)):
            raise ValueError("order must be a permutation of the tile indices")
        self._next = 0                    # position in the order: from here on never handed out
        self._last = count                # ... up to here (the cheap end is taken from the back)
        self._returned = []               # heap of tiles handed out and given back
        self._holders: dict = {}          # index -> set of holder keys
        self._taken_at: dict = {}         # index -> monotonic time first handed out
        self._done = set()
        self._durations = []              # sorted seconds from hand-out to done, this frame
        self._closed = False
        self._changed = threading.Condition()
        self.duplicates_handed_out = 0

    # _holders is in hand-out order (a tile given back and handed out again is a new entry),
    # which is the order of _taken_at: the oldest held tiles come first, and a scan for a tile
    # to copy stops at the first that is not yet overdue.

    def _copyable(self, holder):
        best = None
        # Before any tile is done there is no typical time: anything may be copied.
        overdue = (time.monotonic() - COPY_AFTER * self._durations[len(self._durations) // 2]
                   if self._durations else math.inf)
        for index, holders in self._holders.items():
            if self._taken_at[index] > overdue:
                break
            if holder in holders or len(holders) >= self.max_copies:
                continue
            if best is None or len(holders) < len(self._holders[best]):   # fewest copies, then the oldest
                best = index
                if len(holders) == 1:
                    break
        return best

    def copy_due(self, holder=None):
        """When the first tile `holder` (None: anyone) could copy becomes overdue (monotonic
        time; None: none can, or nothing is done yet to tell)."""
        with self._changed:
            if not self._durations:
                return None
            for index, holders in self._holders.items():
                if holder not in holders and len(holders) < self.max_copies:
                    return self._taken_at[index] + COPY_AFTER * self._durations[len(self._durations) // 2]
            return None

    @property
    def has_pending(self) -> bool:
        """Tiles wait to be handed out (copies are handed out only when none does)."""
        return bool(self._returned) or self._next < self._last

    def _pop_pending(self, cheap: bool) -> int:
        if self._returned:
            return heapq.heappop(self._returned)
        if self._order is None:
            self._next += 1
            return self._next - 1
        if cheap:
            self._last -= 1
            return self._order[self._last]
        self._next += 1
        return self._order[self._next - 1]

    def take(self, timeout: float | None = None, holder=None, duplicates: bool = False,
             cheap: bool = False) -> int | None:
        """The next pending tile (`cheap`: for a slave that is still busy, see `order`); with
        `duplicates`, when nothing is pending, a copy of a tile that other holders still have.
        Waits up to `timeout` (0: not at all, the frame loop's take); None if none."""
        def ready():
            return (self.has_pending or self._closed or self.all_done
                    or (duplicates and self._copyable(holder) is not None))
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._changed:
            # Wait for a notification, the deadline, or the moment a held tile becomes
            # overdue (then it may be copied): no polling in between.
            while timeout != 0 and not ready():
                now = time.monotonic()
                wake = deadline
                if duplicates:
                    overdue = self.copy_due(holder)
                    if overdue is not None:
                        wake = overdue if wake is None else min(wake, overdue)
                if deadline is not None and now >= deadline:
                    break
                self._changed.wait(None if wake is None else max(0.001, wake - now))
            if self._closed or self.all_done:
                return None
            if self.has_pending:
                index = self._pop_pending(cheap)
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
            if index not in self._done and index not in self._returned and index in self._taken_at:
                heapq.heappush(self._returned, index)
                self._changed.notify()     # one taker can have it

    def mark_done(self, index: int) -> bool:
        """Record a finished tile; False if it was already done (a duplicate)."""
        with self._changed:
            if index in self._done:
                return False
            self._done.add(index)
            self._holders.pop(index, None)
            if index in self._taken_at:
                bisect.insort(self._durations, time.monotonic() - self._taken_at[index])
            if index in self._returned:
                self._returned.remove(index)
                heapq.heapify(self._returned)
            if self.all_done:   # wakes the takers to leave; nothing else became available
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
