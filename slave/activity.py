"""What the slave is doing, for its log and its status query: the server reports connections,
frames, tiles and bytes here; one log line is written per frame when the frame ends (the
master starts another, cancels it or leaves), and status() gives the current state."""
from __future__ import annotations

import collections
import logging
import threading
import time
from dataclasses import dataclass

log = logging.getLogger("kdtrace.slave")

RECENT_FRAMES = 5   # frame lines kept for the status query


SHOWN_HASH = 8   # hex digits of a scene's hash in the log and the status

@dataclass
class FrameActivity:
    frame_id: int
    master: str
    scene_hash: str
    tiles_in_frame: int
    started: float              # time.monotonic()
    tiles: int = 0
    render_ms: float = 0.0
    build_seconds: float = 0.0  # kernel programs built for this frame's tiles
    bytes_sent: int = 0

    def line(self) -> str:
        per_tile = self.render_ms / self.tiles if self.tiles else 0.0
        return (f"frame {self.frame_id:x} for {self.master}: scene {self.scene_hash[:SHOWN_HASH]}, "
                f"{self.tiles} of {self.tiles_in_frame} tiles, {per_tile:.1f} ms/tile, "
                f"kernel build {self.build_seconds:.2f} s, {self.bytes_sent / 2 ** 20:.2f} MiB "
                f"sent, {time.monotonic() - self.started:.1f} s")


class Activity:
    """Thread-safe: the server's connection threads call it, the status server reads it."""

    def __init__(self):
        self.started = time.time()
        self._lock = threading.Lock()
        self._masters: dict = {}      # master label -> time.time() of its connection
        self._frames: dict = {}       # master label -> FrameActivity of its current frame
        self._recent = collections.deque(maxlen=RECENT_FRAMES)
        self.totals = {"frames": 0, "tiles": 0, "bytes_sent": 0, "build_seconds": 0.0}

    def master_connected(self, master: str) -> None:
        with self._lock:
            self._masters[master] = time.time()

    def master_left(self, master: str) -> None:
        self.frame_over(master)
        with self._lock:
            self._masters.pop(master, None)

    def frame_started(self, master: str, frame_id: int, scene_hash: str, tiles: int) -> None:
        self.frame_over(master)   # a new frame supersedes the master's previous one
        with self._lock:
            self._frames[master] = FrameActivity(frame_id, master, scene_hash, tiles,
                                                 time.monotonic())

    def tile_rendered(self, master: str, frame_id: int, ms: float, build_seconds: float) -> None:
        with self._lock:
            frame = self._current(master, frame_id)
            if frame is not None:
                frame.tiles += 1
                frame.render_ms += ms
                frame.build_seconds += build_seconds
            self.totals["tiles"] += 1
            self.totals["build_seconds"] += build_seconds
        log.debug("frame %x for %s: tile rendered in %.1f ms", frame_id, master, ms)

    def sent(self, master: str, frame_id: int, nbytes: int) -> None:
        with self._lock:
            frame = self._current(master, frame_id)
            if frame is not None:
                frame.bytes_sent += nbytes
            self.totals["bytes_sent"] += nbytes

    def frame_over(self, master: str) -> None:
        """The master's current frame ended: log its line (frames without tiles say nothing)."""
        with self._lock:
            frame = self._frames.pop(master, None)
            if frame is None or not frame.tiles:
                return
            line = frame.line()
            self._recent.append(f"{time.strftime('%Y-%m-%d %H:%M:%S')} {line}")
            self.totals["frames"] += 1
        log.info("%s", line)

    def _current(self, master: str, frame_id: int) -> FrameActivity | None:
        frame = self._frames.get(master)
        return frame if frame is not None and frame.frame_id == frame_id else None

    def status(self) -> dict:
        now = time.time()
        with self._lock:
            return {
                "uptime_seconds": round(now - self.started, 1),
                "masters": [{"master": m, "connected_seconds": round(now - t, 1)}
                            for m, t in sorted(self._masters.items())],
                "frames": [{"frame_id": f"{f.frame_id:x}", "master": f.master,
                            # a prefix: a scene's hash is not shown whole
                            "scene": f.scene_hash[:SHOWN_HASH], "tiles": f.tiles,
                            "tiles_in_frame": f.tiles_in_frame,
                            "ms_per_tile": round(f.render_ms / f.tiles, 1) if f.tiles else None,
                            "bytes_sent": f.bytes_sent}
                           for f in self._frames.values()],
                "totals": dict(self.totals, build_seconds=round(self.totals["build_seconds"], 3)),
                "recent_frames": list(self._recent)}
