"""One frame in progress (RenderJob): its tiles, the image they are written into, the slaves
that render them (one SlaveWorker each, core/net/slave_worker.py, run on the master's frame
loop), and the caller's side: results, cancel, errors. The master (core/net/master.py) starts
it and passes what the job needs of it as callbacks and objects (report_state, rejoin,
spares, on_complete): the job never reaches into the master."""
from __future__ import annotations

import math
import queue
import threading
import time
import uuid
from dataclasses import dataclass

import numpy as np

from . import protocol
from .connection import SlaveConnection
from .frame_loop import FrameLoop
from .protocol import MsgType
from .slave_worker import SlaveWorker
from ..scene.model import View
from .tiles import TileGrid, TilePool

DEPTH_MISS = 1e10        # the tracer's depth where a pixel sees nothing (kernels/shade/render.cl)
MAX_SPARE_FRAMES = 2     # frames handed back by RenderJob.release() kept for reuse
RESULTS_EVERY_S = 0.02   # RenderJob.next_results returns at most 50 times a second while tiles
                         # come: smooth to watch, and a wake-up takes the tiles that came meanwhile


def _channels(name: str) -> tuple:
    """The last axis of a pass's frame: none for a pass of one channel (depth, mist)."""
    channels = protocol.TILE_PASSES[name]
    return (channels,) if channels > 1 else ()


def _empty_frame(shape: tuple, passes: tuple, reuse: dict | None = None) -> dict:
    """pass -> the empty float32 frame (zero colour and normal, depth DEPTH_MISS: no surface),
    written into `reuse` (an earlier frame of this shape and passes) when given."""
    if reuse is None:
        return {name: (np.full(shape, DEPTH_MISS, np.float32) if name == "depth" else
                       np.zeros(shape + _channels(name), np.float32))
                for name in passes}
    for name, array in reuse.items():
        array.fill(DEPTH_MISS if name == "depth" else 0.0)
    return reuse


class SpareFrames:
    """Frames handed back by their callers (RenderJob.release), kept for the next frames of
    the same size and passes; nothing is kept once closed."""

    def __init__(self):
        self._frames: list = []
        self._closed = False
        self._lock = threading.Lock()

    def take(self, shape: tuple, passes: tuple) -> dict | None:
        """A frame of this shape and passes, or None."""
        with self._lock:
            for i, image in enumerate(self._frames):
                if tuple(image) == passes and image["combined"].shape[:2] == shape:
                    return self._frames.pop(i)
        return None

    def keep(self, image: dict) -> None:
        with self._lock:
            if not self._closed:
                self._frames = [image] + self._frames[:MAX_SPARE_FRAMES - 1]

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._frames = []


@dataclass(frozen=True)
class TileBudget:
    """How long one step of a slave (loading a scene, compiling, waiting for its device,
    rendering one tile) may take before the slave is dropped although it says it is busy:
    base_s for any step, plus s_per_ray for each ray a tile may trace at most (View.tile_rays:
    the count the slaves' work budget uses). Generous: it catches a slave stuck for good,
    never a slow one (the default allows a device 500 times slower than one core here)."""

    base_s: float = 600.0
    s_per_ray: float = 1e-4

    def seconds(self, view: View, w: int, h: int) -> float:
        return self.base_s + view.tile_rays(w, h) * self.s_per_ray


@dataclass
class TileResult:
    index: int
    x: int
    y: int
    w: int
    h: int
    passes: dict            # the frame's passes ("combined" (h,w,4), "depth" (h,w), "normal" (h,w,3)):
                            # float32 windows of job.image, top row first
    slave_name: str
    slave_id: str
    render_ms: float


class RenderJob:
    """One frame in progress, run by the master's frame loop; the caller polls next_result().

    What it needs of its master comes in as arguments: `report_state(endpoint, state,
    reason="", connection=None)` tells the panel what a slave is doing, `rejoin(endpoint, job)`
    starts reconnecting to a lost slave (the job then waits for join_over() before it may fail
    for want of slaves), `spares` (SpareFrames) lends and takes back frames' memory, and
    `on_complete(job)` is called once every tile has been delivered."""

    def __init__(self, connections: list, view: View, tiles: TileGrid, tiles_in_flight,
                 scene_hash: str, loop: FrameLoop, *, report_state, rejoin,
                 spares: SpareFrames, on_complete, model: str = protocol.DEFAULT_MODEL,
                 payload: str = "f32", compress: bool = False, passes=protocol.ALL_PASSES,
                 duplicates: bool = True, silence_timeout: float = protocol.SILENCE_S,
                 tile_budget: TileBudget = TileBudget(), hold_when_stranded: bool = False,
                 order=None):
        self.loop, self.report_state, self._spares = loop, report_state, spares
        self._rejoin, self._on_complete = rejoin, on_complete
        self.view, self.view_dict, self.tiles_in_flight = view, view.to_dict(), tiles_in_flight
        self.tiles = tiles
        self.tile_w, self.tile_h = tiles.tile_w, tiles.tile_h
        self.model, self.payload, self.compress = model, payload, compress
        self.passes = protocol.check_passes(passes)
        # The frame, composed by the frame loop as tiles arrive (what is not rendered stays
        # empty: zero colour, no surface).
        x0, y0, x1, y1 = view.region
        self.origin, shape = (x0, y0), (y1 - y0, x1 - x0)
        self.image = _empty_frame(shape, self.passes, spares.take(shape, self.passes))
        self._released = False
        self.duplicates, self.silence_timeout = duplicates, silence_timeout
        self.tile_budget, self.hold_when_stranded = tile_budget, hold_when_stranded
        self.scene_hash = scene_hash
        self.frame_id = uuid.uuid4().int >> 65   # unique across masters and renders; fits JSON ints
        self.frame_start = protocol.encode_message(MsgType.FRAME_START, {   # the same for all
            "frame_id": self.frame_id, "scene_hash": scene_hash, "view": self.view_dict,
            "tile_size": self.tile_w, "tile_height": self.tile_h, "model": model,
            "payload": payload, "compress": compress, "passes": list(self.passes)})
        self.pool = TilePool(len(self.tiles), max_copies=2 if duplicates else 1, order=order)
        self.tile_ms = [None] * len(self.tiles)   # render ms of each delivered tile
        self.limits = protocol.Limits(
            max_tile_pixels=self.tile_w * self.tile_h,
            tile_bytes_per_pixel=protocol.tile_bytes_per_pixel(payload, self.passes))
        self.errors: list = []       # every problem, including slaves lost and recovered from
        self.error: str | None = None  # set when the frame cannot be finished
        self.cancelled = False
        self.stranded = False        # no slave left, none reconnecting (hold_when_stranded)
        self.started = time.monotonic()
        self.first_tile_s: float | None = None   # seconds from start to the first result
        self.elapsed_s: float | None = None      # seconds from start to the last tile
        self._results: queue.Queue = queue.Queue()
        self._results_returned = -math.inf     # when next_results last returned
        self._delivered = self._taken = 0
        self._joins = 0              # reconnections under way that may still bring a slave
        self._rejoined: set = set()  # endpoints reconnected after a loss, no tile since
        self._over = threading.Event()
        self._quiet = threading.Event()   # over, and no slave's socket read for it any more
        self._lock = threading.Lock()
        self._workers = [SlaveWorker(self, c) for c in connections]

    def start(self) -> None:
        for worker in list(self._workers):
            self._start_worker(worker)

    def windows(self, x: int, y: int, w: int, h: int) -> dict:
        """name -> the tile's window of job.image."""
        left, top = x - self.origin[0], y - self.origin[1]
        return {name: image[top:top + h, left:left + w] for name, image in self.image.items()}

    def _start_worker(self, worker: SlaveWorker) -> None:
        self.report_state(worker.connection.endpoint, "waiting", connection=worker.connection)
        self.loop.call(worker.begin)

    def add_connection(self, connection: SlaveConnection) -> bool:
        """Let a slave that connected after the start (reconnected, or found later) take tiles
        of this frame; False if the frame is over or the slave lacks its scene."""
        if connection.scene_hash != self.scene_hash or connection.closed:
            return False
        with self._lock:
            if self._over.is_set():
                return False
            worker = SlaveWorker(self, connection)
            self._workers.append(worker)
            self.stranded = False
        self._start_worker(worker)
        return True

    # -- the caller's side

    @property
    def over(self) -> bool:
        """No more tiles will be produced (all done, cancelled or failed)."""
        return self._over.is_set()

    @property
    def finished(self) -> bool:
        """Over, and every produced result has been taken with next_result()."""
        with self._lock:
            return self._over.is_set() and self._taken == self._delivered

    @property
    def progress(self) -> tuple:
        return self.pool.done_count, len(self.tiles)

    @property
    def tiles_by_slave(self) -> dict:
        counts: dict = {}
        for worker in list(self._workers):
            label = worker.connection.label
            counts[label] = counts.get(label, 0) + worker.tiles_done
        return counts

    @property
    def duplicates_handed_out(self) -> int:
        return self.pool.duplicates_handed_out

    def next_result(self, timeout: float | None = None) -> TileResult | None:
        """The next finished tile, or None after `timeout` seconds or once the job is over."""
        try:
            result = self._results.get(timeout=timeout)
        except queue.Empty:
            return None
        if result is None:
            self._results.put(None)  # keep the end marker for later callers
            return None
        with self._lock:
            self._taken += 1
        return result

    def next_results(self, timeout: float | None = None) -> list:
        """The finished tiles waiting, within `timeout` seconds ([] if none came, or once the
        job is over), no sooner than RESULTS_EVERY_S after the last call returned while the
        frame goes on: a caller that shows tiles (the add-on's render thread) wakes once for
        the tiles that came meanwhile, not once a tile (64 slaves deliver 256 tiles in 0.2 s;
        every wake-up also costs the frame loop a hand-over of the interpreter)."""
        started = time.monotonic()
        pause = self._results_returned + RESULTS_EVERY_S - started
        if pause > 0 and not self._over.is_set():
            time.sleep(pause if timeout is None else min(pause, timeout))
        left = None if timeout is None else max(0.0, started + timeout - time.monotonic())
        results = []
        result = self.next_result(left)
        while result is not None:
            results.append(result)
            result = self.next_result(0)
        self._results_returned = time.monotonic()
        return results

    def cancel(self) -> None:
        """Stop the frame; every slave is told and confirms (see wait())."""
        with self._lock:
            if self._over.is_set():
                return
            self.cancelled = True
        self._end()

    def give_up(self) -> None:
        """End a stranded frame (hold_when_stranded) with its error."""
        with self._lock:
            if self._over.is_set():
                return
            self.error = self._lost_message()
        self._end()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the frame is over and no slave owes it anything more (copies and
        cancels confirmed); True if so."""
        return self._quiet.wait(timeout)

    def release(self) -> None:
        """The caller is done with job.image and its TileResults' passes: the master writes a
        later frame of the same size and passes into that memory (a new frame's 16 MiB would
        otherwise fault in page by page as tiles arrive). The memory is handed over, and
        job.image set to None, once the frame is quiet (no late tile can be written into it)."""
        with self._lock:
            if self._released:
                return
            self._released = True
        self._hand_back()

    # -- the slaves' side (their workers, on the frame loop)

    def deliver(self, index: int, windows: dict, connection: SlaveConnection,
                render_ms: float) -> None:
        """Tile `index`, written into `windows` (its part of job.image) from `connection`, is
        the first of its copies to arrive: a result for the caller."""
        x, y, w, h = self.tiles[index]
        result = TileResult(index, x, y, w, h, windows, connection.name, connection.instance, render_ms)
        with self._lock:
            self._rejoined.discard(connection.endpoint)
            self._delivered += 1
            now = time.monotonic() - self.started
            if self.first_tile_s is None:
                self.first_tile_s = now
        self._results.put(result)
        if self.pool.all_done:
            self.elapsed_s = now
            self._on_complete(self)
            self._end()

    def offer(self) -> None:
        """Tiles went back to the pool: slaves with a free slot take them."""
        for worker in list(self._workers):
            worker.refill()

    def worker_released(self) -> None:
        """A slave's socket is no longer read for this frame."""
        with self._lock:
            if self._over.is_set() and all(w.released for w in self._workers):
                self._quiet.set()
        self._hand_back()

    def _hand_back(self) -> None:
        """Once released by the caller and quiet: the frame's memory goes back to the spares."""
        with self._lock:
            if not (self._released and self._quiet.is_set()) or self.image is None:
                return
            image, self.image = self.image, None
        self._spares.keep(image)

    def slave_lost(self, worker: SlaveWorker, reason: str, retry: bool) -> None:
        """A slave that drops is reconnected to, once per loss; one that drops again before
        it delivers a tile is not tried again in this frame (it would only fail again)."""
        connection = worker.connection
        with self._lock:
            self.errors.append(f"slave {connection.label} lost: {reason}")
            retry = retry and not self._over.is_set() and (
                worker.tiles_done > 0 or connection.endpoint not in self._rejoined)
            if retry:
                self._rejoined.add(connection.endpoint)
        self.report_state(connection.endpoint, "lost", reason, connection)
        if retry:
            self._rejoin(connection.endpoint, self)
        self._check_stranded()

    # -- the master's side (its threads that connect to slaves)

    def join_started(self) -> None:
        """A reconnection that may bring a slave into this frame is under way."""
        with self._lock:
            self._joins += 1

    def join_over(self, endpoint, reason: str | None) -> None:
        """That reconnection ended: `reason` says why it failed, None if the slave joined."""
        with self._lock:
            self._joins -= 1
            if reason is not None and not self._over.is_set():
                self.errors.append(f"reconnecting to {endpoint[0]}:{endpoint[1]} failed: {reason}")
        self._check_stranded()

    def _lost_message(self) -> str:
        return "all slaves lost before the frame was finished: " + "; ".join(self.errors)

    def _check_stranded(self) -> None:
        """Fail the frame (or, with hold_when_stranded, wait for help) once no slave is left
        and no reconnection is under way."""
        with self._lock:
            if self._over.is_set() or self._joins or any(w.alive for w in self._workers):
                return
            if self.hold_when_stranded:
                self.stranded = True
                return
            self.error = self._lost_message()
        self._end()

    def _end(self) -> None:
        with self._lock:
            if self._over.is_set():
                return
            self._over.set()
        self.pool.close()
        self._results.put(None)
        self.loop.call(self._wind_down)

    def _wind_down(self) -> None:
        """On the frame loop, once the frame is over: each slave cancels what it still has
        (copies, or everything on a cancel) and is let go once it owes nothing."""
        for worker in list(self._workers):
            worker.wind_down()
        self.worker_released()
