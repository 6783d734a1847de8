"""The slave's TCP server: listens for masters, gives each admitted connection a slot, and
renders every connection's tiles on the one shared device. A connection (its handshake, its
threads, the messages it handles) is slave/connection.py's MasterConnection; the bounded queues
between its threads and the upload budget, slave/queues.py's.

Everything a master can make the slave hold is bounded: the work queue (a master may have at
most protocol.MAX_TILES_IN_FLIGHT tiles requested and not yet sent; a tile requested twice is
refused), the outbox (the render loop and the reader wait when it is full: backpressure), each
message (core/net/channel.py: limits, and a deadline for the whole message either way), the
messages larger than a channel's buffer being received by all connections together (an
UploadBudget), and a frame's work (protocol.MAX_TILE_RAYS a tile, MAX_SAMPLE_RAYS a camera
sample). A tile renders in short launches and stops between two of them once its frame is
cancelled or its master gone, so a cancel never waits for a whole tile.
Connections in their handshake are a pool of their own with a deadline for the whole handshake,
so unauthenticated peers never hold the slots of authenticated masters; a master that finds
every slot taken by masters at work is told "slave busy" with the reason. Heartbeats keep a
connection open but are no work: a master that sent nothing else for EVICTABLE_AFTER_S gives
its slot to a new one.

A misbehaving master (garbage, truncated or oversized frames) gets an ERROR message if possible
and its connection is closed with a logged reason; the server keeps serving the others.
"""
from __future__ import annotations

import logging
import socket
import threading
import time
import uuid

from ..core.net import protocol, trust
from ..core.net.identity import Identity

from .activity import Activity
from .connection import MasterConnection
from .queues import Frame, UploadBudget
from .scene_cache import SceneCache
from .tracer import RenderStopped

log = logging.getLogger("kdtrace.slave")

MAX_CONNECTIONS = 16        # masters served at once
MAX_HANDSHAKES = 32         # connections still in their handshake (the oldest gives way)
DEVICE_POLL_S = 0.05        # how often a tile waiting for the device looks at its stop


class SlaveServer:
    """Listens for masters; one MasterConnection (thread) per master; one shared Tracer."""

    def __init__(self, tracer, name: str, bind: str = "0.0.0.0", port: int = 0,
                 limits: protocol.Limits = protocol.DEFAULT_LIMITS, cache_size: int = 2,
                 secret: bytes | None = None, cache_dir=None,
                 cache_disk_bytes: int = 2 * 1024 ** 3, *, identity: Identity | None = None,
                 allowed: trust.AllowList | None = None,
                 pairing: trust.PairingCode | None = None, upload_bytes: int | None = None):
        """Serves masters whose ID is `allowed`, that pair with `pairing` (the code is used up
        by the first) or that prove the farm `secret` (generated: trust.new_farm_secret); no
        other. `identity`: this slave's (None: a new one for this server only). `cache_dir`:
        also keep scenes on disk there (a folder private to this user), up to
        `cache_disk_bytes`. `upload_bytes`: what all connections' large messages being
        received may hold at once (default: the largest scene, limits.max_scene_bytes)."""
        self.tracer, self.name = tracer, name
        self.device_info = dict(tracer.device_info)
        self.identity = identity or Identity.ephemeral("slave")
        self.slave_id = self.identity.id
        self.instance = uuid.uuid4().hex[:12]    # this process (zeroconf names it apart)
        self.limits = limits
        self.uploads = UploadBudget(limits.max_scene_bytes if upload_bytes is None
                                    else upload_bytes)
        self.secret = None if secret is None else trust.check_farm_secret(
            secret.strip(), "the slave's secret")
        self.allowed = allowed if allowed is not None else trust.AllowList()
        self.pairing = pairing
        self.scenes = SceneCache(cache_size, cache_dir, cache_disk_bytes)
        self.activity = Activity()   # what it is doing: per-frame log lines, the status query
        self._device_lock = threading.Lock()
        self._loaded_hash = None
        self._connections = set()    # admitted masters
        self._handshakes = {}        # connections in their handshake, oldest first
        self._connections_lock = threading.Lock()
        self.bind = bind
        self._listener = socket.create_server((bind, port), reuse_port=False)
        self.address = self._listener.getsockname()[:2]
        self._accept_thread = None

    @property
    def serves_nobody(self) -> bool:
        """No master can be admitted: no allowed ID, no farm secret, no pairing code."""
        return (self.secret is None and not len(self.allowed)
                and (self.pairing is None or not self.pairing.active))

    def start(self) -> None:
        self._accept_thread = threading.Thread(target=self._accept_loop, name="accept", daemon=True)
        self._accept_thread.start()

    def _accept_loop(self) -> None:
        while True:
            try:
                sock, address = self._listener.accept()
            except OSError:
                return  # listener closed
            peer = f"{address[0]}:{address[1]}"
            try:  # tile requests and results must not wait for Nagle's algorithm
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except OSError:
                pass
            connection = MasterConnection(self, sock, peer)
            with self._connections_lock:
                if len(self._handshakes) >= MAX_HANDSHAKES:
                    oldest = next(iter(self._handshakes))
                    del self._handshakes[oldest]
                    log.warning("dropping master %s: %d connections in their handshake",
                                oldest.peer, MAX_HANDSHAKES)
                    oldest.abort()
                self._handshakes[connection] = None
            threading.Thread(target=connection.run, name=f"master {peer}", daemon=True).start()

    def _handshake_over(self, connection: MasterConnection) -> None:
        with self._connections_lock:
            self._handshakes.pop(connection, None)

    def _admit(self, connection: MasterConnection) -> tuple:
        """(True, "") if `connection` gets a slot, taking it from the longest idle master when
        all are taken; else (False, why)."""
        with self._connections_lock:
            if len(self._connections) >= MAX_CONNECTIONS:
                now = time.monotonic()
                idle = [(c.evictable(now), c) for c in self._connections]
                idle = [(seconds, c) for seconds, c in idle if seconds is not None]
                if not idle:
                    return False, f"{MAX_CONNECTIONS} masters connected and at work"
                seconds, victim = max(idle, key=lambda pair: pair[0])
                self._connections.discard(victim)
                log.info("master %s: closing: idle for %.0f s and %s needs the slot",
                         victim.peer, seconds, connection.peer)
                victim._end(f"closing: idle for {seconds:.0f} s and another master needs the slot")
            self._connections.add(connection)
            return True, ""

    def _connection_closed(self, connection: MasterConnection) -> None:
        with self._connections_lock:
            self._connections.discard(connection)

    def render_tile(self, frame: Frame, x: int, y: int, w: int, h: int, step,
                    stop=None) -> tuple:
        """(passes, render ms) of one tile; step(state) says what is happening (the master hears
        it in heartbeats). One device for all masters: loading and rendering are serialised.
        RenderStopped once stop() says so, while the tile waits for the device or between two
        of its launches (the tracer's render_tile)."""
        step("waiting")
        while not self._device_lock.acquire(timeout=DEVICE_POLL_S):
            if stop is not None and stop():
                raise RenderStopped("stopped while waiting for the device")
        try:
            if self._loaded_hash != frame.scene.hash:
                step("loading")
                self._loaded_hash = None
                self.tracer.load(frame.scene)
                self._loaded_hash = frame.scene.hash
            step("compiling")
            self.tracer.prepare(frame.view, frame.passes)
            step("rendering")
            start = time.perf_counter()
            passes = self.tracer.render_tile(frame.view, x, y, w, h, frame.passes, stop=stop)
            return passes, (time.perf_counter() - start) * 1000.0
        finally:
            self._device_lock.release()

    def close(self) -> None:
        self._listener.close()
        with self._connections_lock:
            connections = list(self._connections) + list(self._handshakes)
        for connection in connections:
            connection._end()
            connection.abort()
