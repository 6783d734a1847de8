"""One slave's part in one frame (SlaveWorker), run on the master's frame loop: the requests
it has outstanding, what it says it is doing, the deadlines it owes, and its life in the frame
as one explicit state (WorkerState) with the transitions allowed between them."""
from __future__ import annotations

import enum
import math
import time
from typing import TYPE_CHECKING

from . import protocol
from .connection import SlaveConnection, describe
from .protocol import MsgType, ProtocolError
from .tile_payloads import decode_tile

if TYPE_CHECKING:
    from .render_job import RenderJob

DEFAULT_TILES_IN_FLIGHT = 2
# tiles_in_flight="auto": per slave, 1 + as many tiles as it renders in one round trip (the
# least time from a request to its result, less the render time, seen in this frame), at
# least AUTO_IN_FLIGHT and at most AUTO_MAX_IN_FLIGHT: a slave whose tiles take less than a
# round trip gets more requests ahead, one with long tiles does not hoard them.
AUTO_IN_FLIGHT = 2
AUTO_MAX_IN_FLIGHT = 8


class WorkerState(enum.Enum):
    """A slave's life in one frame."""
    WAITING = 1      # in the frame; FRAME_START not sent yet (begin() runs on the frame loop)
    RUNNING = 2      # FRAME_START sent: it takes tiles and owes those it was asked for
    CANCELLING = 3   # the frame is over and it still held tiles (copies), or the frame was
                     # cancelled: CANCEL sent, its confirmation owed like a tile
    CANCELLED = 4    # it confirmed the cancel and owes nothing more
    RELEASED = 5     # its socket is no longer read for this frame; the connection stays
    LOST = 6         # dropped: the connection closed, its tiles back in the pool


NEXT_STATES = {
    WorkerState.WAITING: {WorkerState.RUNNING, WorkerState.RELEASED},   # released: frame over
    WorkerState.RUNNING: {WorkerState.CANCELLING, WorkerState.RELEASED, WorkerState.LOST},
    WorkerState.CANCELLING: {WorkerState.CANCELLED, WorkerState.LOST},
    WorkerState.CANCELLED: {WorkerState.RELEASED, WorkerState.LOST},
    # A step already under way (a sweep over a list taken before the release) may still find
    # the connection broken: it is closed and the slave named as lost.
    WorkerState.RELEASED: {WorkerState.LOST},
    WorkerState.LOST: set(),
}


class _SlaveLost(Exception):
    def __init__(self, reason: str, retry: bool):
        super().__init__(reason)
        self.reason, self.retry = reason, retry


class SlaveWorker:
    """One slave's part in one job, run on the master's frame loop: its tiles in flight, what
    it says it is doing and the deadlines it owes. Model 3b keeps `window` requests
    outstanding and sends the next request as a tile arrives, before it is composed; model 3a
    asks for one tile and the next only once that one has been composed."""

    def __init__(self, job: RenderJob, connection: SlaveConnection):
        self.job, self.connection = job, connection
        self.state = WorkerState.WAITING
        self.in_flight: set = set()
        self.last_heard = time.monotonic()
        self._new_step(None, self.last_heard)   # (state, tile) the slave last said it was at
        self.tiles_done = 0
        self.render_s, self.tiles_rendered = 0.0, 0     # this frame: seconds of render, tiles
        self.requested_at: dict = {}    # tile -> when its request went out
        self.round_trip_s = None        # least (result - request - render) this frame
        if job.model == "3a":
            self.window = 1
        else:
            self.window = DEFAULT_TILES_IN_FLIGHT if job.tiles_in_flight == "auto" else job.tiles_in_flight

    @property
    def alive(self) -> bool:
        """Not dropped: it still counts as a slave of the frame."""
        return self.state is not WorkerState.LOST

    @property
    def released(self) -> bool:
        """Its socket is no longer read for this frame."""
        return self.state in (WorkerState.RELEASED, WorkerState.LOST)

    def _enter(self, state: WorkerState) -> None:
        if state not in NEXT_STATES[self.state]:
            raise RuntimeError(f"slave {self.connection.label}: no transition from "
                               f"{self.state.name} to {state.name}")
        self.state = state

    # -- what the frame loop and the job call

    def begin(self) -> None:
        if self.job.over:
            self._release()
            return
        self._guarded(self._start)

    def readable(self) -> None:
        self._guarded(self._receive)

    def sweep(self, now: float) -> None:
        self._guarded(self._check, now)

    def refill(self) -> None:
        """Tiles went back to the pool: take them if there is a free slot."""
        if self.state in (WorkerState.RUNNING, WorkerState.CANCELLING, WorkerState.CANCELLED):
            self._guarded(self._fill)

    def wind_down(self) -> None:
        """The frame is over: cancel what is still out, and let go once nothing is owed."""
        self._settle()
        self.job.loop.wake_by(self.due())

    def due(self) -> float | None:
        """When this slave needs looking at next, unless a message comes first."""
        if self.released:
            return None
        job, arriving = self.job, self.connection.channel.incoming_due()
        times = [arriving]
        if self.in_flight or self.state is WorkerState.CANCELLING:
            times.append(self.step_since + self.step_budget)
            if arriving is None:
                times.append(self.last_heard + job.silence_timeout)
        if not job.over:
            if not self.in_flight:
                times.append(self.connection.channel.last_sent + protocol.KEEPALIVE_S)
            if len(self.in_flight) < self.window and job.duplicates and not job.pool.has_pending:
                times.append(job.pool.copy_due(self))
        times = [t for t in times if t is not None]
        return min(times) if times else None

    # -- steps

    def _start(self) -> None:
        job = self.job
        self._enter(WorkerState.RUNNING)
        job.loop.register(self)
        channel = self.connection.channel
        with channel.batch():       # FRAME_START and the first requests in one write
            channel.send_encoded(job.frame_start)
            self._fill()

    def _receive(self) -> None:
        channel = self.connection.channel
        while True:
            for msg in channel.recv_available(self.job.limits, protocol.SLAVE_TO_MASTER):
                self._handle(msg)
                if not self.alive:
                    return
            # Decrypted bytes TLS holds back wake no selector: read them now.
            if self.released or not channel.has_pending():
                return

    def _check(self, now: float) -> None:
        self._check_deadlines(now)
        self.connection.channel.check_incoming()
        if not self.job.over:
            if len(self.in_flight) < self.window:
                self._fill()
            self._keep_alive()

    def _guarded(self, step, *args) -> None:
        """Any exception in a step for this slave drops this slave, with the reason: a frame
        never waits on a slave whose handling failed."""
        try:
            step(*args)
        except _SlaveLost as exc:
            self._lose(exc.reason, exc.retry)
        except Exception as exc:
            self._lose(describe(exc), protocol.is_transient(exc))
        self._settle()
        self.job.loop.wake_by(self.due())

    def _settle(self) -> None:
        """Once the frame is over: cancel copies still out (and everything on a cancel), and
        stop reading once nothing is owed."""
        job = self.job
        if not job.over or self.state in (WorkerState.WAITING, WorkerState.RELEASED,
                                          WorkerState.LOST):
            return   # waiting: begin() lets it go
        if self.state is WorkerState.RUNNING and (self.in_flight or job.cancelled):
            self._cancel()
        if self.state in (WorkerState.RUNNING, WorkerState.CANCELLED) and not self.in_flight:
            self._release()

    def _release(self) -> None:
        self._enter(WorkerState.RELEASED)
        self.job.loop.unregister(self)
        self.job.report_state(self.connection.endpoint, "idle", connection=self.connection)
        self.job.worker_released()

    def _cancel(self) -> None:
        self._enter(WorkerState.CANCELLING)
        if not self.in_flight:      # owed from now on
            self.last_heard = time.monotonic()
            self._new_step(None, self.last_heard)
        try:
            self.connection.send(MsgType.CANCEL, {"frame_id": self.job.frame_id})
        except (OSError, ProtocolError) as exc:
            self._lose(f"send failed ({describe(exc)})", retry=True)

    def _lose(self, reason: str, retry: bool = False) -> None:
        """Drop this slave: its tiles go back to the pool for the others; with `retry` the
        master tries to reconnect and bring it back into the frame."""
        if self.state is WorkerState.LOST:
            return
        was_released = self.released
        self._enter(WorkerState.LOST)
        lost = sorted(self.in_flight)
        self.in_flight.clear()
        self.job.loop.unregister(self)
        self.connection.close()
        for index in lost:
            self.job.pool.put_back(index, self)
        self.job.slave_lost(self, reason, retry)
        if not was_released:
            self.job.worker_released()   # after the loss is recorded: wait() may return now
        if lost:
            self.job.offer()

    # -- tiles

    def _fill(self) -> None:
        """Requests up to the window: the most expensive pending tiles, a cheap one for a slot
        beside another at the start of the frame (to hide the request's latency, see
        TilePool's order), copies of overdue tiles once nothing is pending."""
        job = self.job
        while self.alive and not job.over and len(self.in_flight) < self.window:
            index = self._take(copies=True, cheap=bool(self.in_flight))
            if index is None:
                return
            self._request(index)

    def _take(self, copies: bool, cheap: bool) -> int | None:
        job = self.job
        index = job.pool.take(0, holder=self, duplicates=copies and job.duplicates, cheap=cheap)
        if index is not None:
            if not self.in_flight:      # the deadlines run from the first request
                self.last_heard = time.monotonic()
                self._new_step(None, self.last_heard)
            self.in_flight.add(index)
        return index

    def _request(self, index: int) -> None:
        self.requested_at[index] = time.monotonic()
        self.connection.send(MsgType.TILE_REQUEST, {"frame_id": self.job.frame_id, "tile": index})

    def _keep_alive(self) -> None:
        """A slave with nothing to render while the frame goes on elsewhere (the last tiles
        take long) stays in the frame: tell it before its idle deadline closes the connection."""
        if not self.in_flight and time.monotonic() - self.connection.channel.last_sent >= protocol.KEEPALIVE_S:
            self.connection.send(MsgType.HEARTBEAT, {})

    def _auto_window(self) -> None:
        """tiles_in_flight="auto" (see AUTO_IN_FLIGHT)."""
        tile_s = self.render_s / max(1, self.tiles_rendered)
        trip = max(0.0, self.round_trip_s or 0.0)
        window = 1 + math.ceil(trip / tile_s) if tile_s > 0 else AUTO_MAX_IN_FLIGHT
        self.window = min(AUTO_MAX_IN_FLIGHT, max(AUTO_IN_FLIGHT, window))

    # -- deadlines

    def _check_deadlines(self, now: float) -> None:
        # A cancel is confirmed after the tile being rendered: owed like a tile, so the same
        # liveness rules apply (a slave finishing a long tile says so in its heartbeats).
        if not (self.in_flight or self.state is WorkerState.CANCELLING):
            return
        # A message under way is not silence: its own transfer deadline applies to it.
        silence = self.job.silence_timeout
        if now - self.last_heard > silence and self.connection.channel.incoming_due() is None:
            raise _SlaveLost(f"did not answer within {silence:g} s", retry=True)
        if now - self.step_since > self.step_budget:
            budget, what = self._budget()
            raise _SlaveLost(f"{what} took longer than its budget of {budget:.0f} s", retry=False)

    def _new_step(self, step, now: float) -> None:
        self.step, self.step_since = step, now
        self.step_budget = self._budget()[0]

    def _budget(self) -> tuple:
        """(seconds, what) the current step may take."""
        job = self.job
        state, tile = self.step or ("rendering", None)
        if state != "rendering":
            return job.tile_budget.base_s, state
        if tile is not None and 0 <= tile < len(job.tiles):
            _, _, w, h = job.tiles[tile]
            return job.tile_budget.seconds(job.view, w, h), f"tile {tile}"
        return job.tile_budget.seconds(job.view, job.tile_w, job.tile_h), "a tile"

    # -- messages

    def _handle(self, msg: protocol.Message) -> None:
        job, h = self.job, msg.header
        now = self.last_heard = time.monotonic()
        if msg.type == MsgType.HEARTBEAT:
            self._heartbeat(h, now)
            return
        if msg.type == MsgType.CANCEL:
            if h.get("frame_id") == job.frame_id:
                if self.state is WorkerState.CANCELLING:
                    self._enter(WorkerState.CANCELLED)
                for index in self.in_flight:  # the slave dropped what it had not rendered
                    job.pool.put_back(index, self)
                self.in_flight.clear()
            return
        if msg.type == MsgType.ERROR:
            raise ProtocolError(f"slave error: {h.get('message')}")
        if msg.type != MsgType.TILE_RESULT:
            raise ProtocolError(f"unexpected {msg.type.name} during a frame")
        if protocol.get_int(h, "frame_id") != job.frame_id:
            return  # a late tile of an earlier, cancelled frame
        index = protocol.get_int(h, "tile", 0, len(job.tiles) - 1)
        if index not in self.in_flight:
            if self.state is WorkerState.CANCELLING or job.cancelled:
                return
            raise ProtocolError(f"sent tile {index}, which was not asked of it")
        x, y, w, h_ = job.tiles[index]
        if [h.get(k) for k in ("x", "y", "w", "h")] != [x, y, w, h_]:
            raise ProtocolError(f"tile {index} has the wrong rectangle")
        render_ms = protocol.get_float(h, "render_ms")
        # Model 3b: the next request goes out before this tile is composed, so the slave's
        # queue refills at once (the most expensive pending tile: it starts after the ones
        # queued there).
        if job.model == "3b" and not job.over and len(self.in_flight) - 1 < self.window:
            following = self._take(copies=False, cheap=False)
            if following is not None:
                self._request(following)
        # Checked, then written straight into the frame; a copy of a tile another slave
        # delivered first is checked only (an honest copy has the same bits anyway).
        windows = job.windows(x, y, w, h_)
        decode_tile(h, msg.arrays, w, h_, job.payload, job.passes,
                    out=None if job.pool.is_done(index) else windows)
        self.render_s += max(render_ms, 0.0) / 1000.0
        self.tiles_rendered += 1
        self.in_flight.discard(index)
        self._new_step(None, now)
        sent = self.requested_at.pop(index, None)
        if sent is not None:
            trip = now - sent - max(render_ms, 0.0) / 1000.0
            self.round_trip_s = trip if self.round_trip_s is None else min(self.round_trip_s, trip)
        if job.tiles_in_flight == "auto" and job.model == "3b" and self.render_s > 0:
            self._auto_window()
        if job.cancelled:
            return
        job.tile_ms[index] = render_ms     # before the frame can be complete
        if job.pool.mark_done(index):
            self.tiles_done += 1
            job.deliver(index, windows, self.connection, render_ms)
        self._fill()
        if job.duplicates and not job.over and not job.pool.has_pending:
            job.loop.wake_by(job.pool.copy_due())   # the typical tile time changed

    def _heartbeat(self, h: dict, now: float) -> None:
        state = h.get("state")
        if state not in protocol.SLAVE_STATES:
            raise ProtocolError(f"heartbeat with an unknown state {str(state)[:32]!r}")
        frame_id = h.get("frame_id")
        if frame_id is not None and protocol.get_int(h, "frame_id") != self.job.frame_id:
            return   # still busy with an earlier frame: alive, but no step of ours
        tile = protocol.get_int(h, "tile", 0, len(self.job.tiles) - 1) if "tile" in h else None
        if (state, tile) != self.step:
            self._new_step((state, tile), now)
            self.job.report_state(self.connection.endpoint, state, connection=self.connection)
