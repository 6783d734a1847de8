"""What a master's connection holds between its threads, and what all connections hold
together, each bounded: the Frame a master started, its WorkQueue (tile requests and cancels,
at most protocol.MAX_TILES_IN_FLIGHT tiles), its Outbox (finished tiles and replies for the
sender) and the UploadBudget (the large messages all connections are receiving at once). The
connection's threads are slave/connection.py's; the server that owns the budget,
slave/server.py's."""
from __future__ import annotations

import collections
import threading
from dataclasses import dataclass

from ..core.net import protocol
from ..core.net.protocol import ProtocolError
from ..core.net.tiles import TileGrid
from ..core.scene.model import View
from ..core.scene.scene import Scene

UPLOAD_WAIT_S = 5.0         # a large message waits this long for the upload budget, then is
                            # refused (the sender's deadline allows SILENCE_S)
OUTBOX_TILES = 2            # finished tiles waiting for the sender
OUTBOX_MESSAGES = 64        # other replies waiting for the sender


@dataclass
class Frame:
    frame_id: int
    scene: Scene
    view: View
    tiles: TileGrid
    model: str = protocol.DEFAULT_MODEL   # "3a": the render thread sends each tile itself
    payload: str = "f32"
    compress: bool = False
    passes: tuple = protocol.ALL_PASSES   # only these travel back
    cancelled: bool = False


class UploadBudget:
    """Bytes of the large messages (over channel.RECV_KEEP_BYTES: scenes, big frames) that all
    connections are receiving at once, at most `capacity`: each such message takes its length
    when its header arrives and gives it back when its receiver asks for the next message (its
    handling, a scene's validation included, is over) or closes (Channel's `budget`).
    A message that does not fit waits up to `wait_s` for others to finish, then is refused; one
    larger than the whole budget is taken alone (so at most max(capacity, the largest message
    the limits allow) bytes are held)."""

    def __init__(self, capacity: int, wait_s: float = UPLOAD_WAIT_S):
        self.capacity, self.wait_s = int(capacity), wait_s
        self.used = 0
        self._changed = threading.Condition()

    def take(self, nbytes: int) -> None:
        with self._changed:
            if not self._changed.wait_for(
                    lambda: self.used == 0 or self.used + nbytes <= self.capacity, self.wait_s):
                raise ProtocolError(
                    f"slave busy: uploads in progress hold {self.used / 2 ** 20:.0f} of the "
                    f"{self.capacity / 2 ** 20:.0f} MiB it receives at once, and this message "
                    f"needs {nbytes / 2 ** 20:.0f} MiB; try again later")
            self.used += nbytes

    def give(self, nbytes: int) -> None:
        with self._changed:
            self.used -= nbytes
            self._changed.notify_all()


class WorkQueue:
    """Tile requests in arrival order, bounded: at most `capacity` tiles requested and not yet
    handed to the sender, no tile twice; a cancel removes the frame's queued tiles at once."""

    def __init__(self, capacity: int = protocol.MAX_TILES_IN_FLIGHT):
        self.capacity = capacity
        self._items = collections.deque()
        self._in_flight = set()     # (frame id, tile) requested and not yet sent back
        self._acks = 0              # cancel confirmations queued
        self._closed = False
        self._ready = threading.Condition()

    def request(self, frame: Frame, index: int) -> None:
        key = (frame.frame_id, index)
        with self._ready:
            if key in self._in_flight:
                raise ProtocolError(f"tile {index} requested again while it is in flight")
            if len(self._in_flight) >= self.capacity:
                raise ProtocolError(f"more than {self.capacity} tiles requested at once")
            self._in_flight.add(key)
            self._items.append(("tile", frame, index))
            self._ready.notify()

    def cancel(self, frame: Frame | None, frame_id: int, ack: bool = True) -> None:
        with self._ready:
            if frame is not None:
                frame.cancelled = True
                kept = collections.deque()
                for item in self._items:
                    if item[0] == "tile" and item[1] is frame:
                        self._in_flight.discard((frame.frame_id, item[2]))
                    else:
                        kept.append(item)
                self._items = kept
            if ack:
                # The ack goes through the render loop, so it leaves after the tile being rendered.
                if self._acks >= self.capacity:
                    raise ProtocolError(f"more than {self.capacity} cancels unanswered")
                self._acks += 1
                self._items.append(("cancel_ack", frame_id))
            self._ready.notify()

    def done(self, frame: Frame, index: int) -> None:
        """The tile left the queue's care (handed to the sender, skipped or failed)."""
        with self._ready:
            self._in_flight.discard((frame.frame_id, index))

    def get(self):
        """The next item, or None once closed."""
        with self._ready:
            self._ready.wait_for(lambda: self._items or self._closed)
            if self._closed:
                return None
            item = self._items.popleft()
            if item[0] == "cancel_ack":
                self._acks -= 1
            return item

    @property
    def pending(self) -> bool:
        return bool(self._items or self._in_flight)

    def close(self) -> None:
        with self._ready:
            self._closed = True
            self._items.clear()
            self._in_flight.clear()
            self._ready.notify_all()


class Outbox:
    """What the sender transmits, in order, bounded: at most OUTBOX_TILES finished tiles (the
    render loop waits) and OUTBOX_MESSAGES other messages (the reader waits). After close()
    nothing more is taken; what is queued still goes out."""

    def __init__(self):
        self._items = collections.deque()
        self._counts = {True: 0, False: 0}
        self._closed = False
        self._changed = threading.Condition()

    def put(self, item, is_tile: bool = False, block: bool = True) -> bool:
        limit = OUTBOX_TILES if is_tile else OUTBOX_MESSAGES
        with self._changed:
            if block:
                self._changed.wait_for(lambda: self._closed or self._counts[is_tile] < limit)
            if self._closed or self._counts[is_tile] >= limit:
                return False
            self._items.append((is_tile, item))
            self._counts[is_tile] += 1
            self._changed.notify_all()
            return True

    def get(self):
        """The next item; None when closed and empty."""
        with self._changed:
            self._changed.wait_for(lambda: self._items or self._closed)
            if not self._items:
                return None
            is_tile, item = self._items.popleft()
            self._counts[is_tile] -= 1
            self._changed.notify_all()
            return item

    @property
    def pending(self) -> bool:
        return bool(self._items)

    def close(self, discard: bool = False) -> None:
        with self._changed:
            self._closed = True
            if discard:
                self._items.clear()
                self._counts = {True: 0, False: 0}
            self._changed.notify_all()
