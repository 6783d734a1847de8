"""An application-level network link emulator: a TCP proxy that adds latency and limits
bandwidth per connection and direction (this machine's kernel has no netem/tbf qdiscs).

    link = LinkEmulator(("10.0.0.2", 47600), latency_s=0.003, bandwidth_bps=300e6)
    link.start(); Master([link.endpoint]) ...; link.close()

Each direction of each connection is a link of its own: a chunk read at time t leaves the
link's serialiser at free = max(t, free) + bytes * 8 / bandwidth and is delivered latency_s
later (store and forward, in chunks of at most `chunk` bytes so a large tile streams).
bandwidth_bps=None and latency_s=0 forward unchanged ("loopback, unlimited").

A shared medium (real Wi-Fi: one channel for every station, both directions) is one
serialiser for all the traffic of every link given it:

    air = SharedMedium(300e6)
    links = [LinkEmulator(ep, latency_s=0.003, medium=air) for ep in endpoints]

A chunk then leaves at free = max(t, air.free) + bytes * 8 / air.bandwidth, whichever link and
direction it belongs to.
Used by the benchmarks and tests only; nothing here parses the bytes it forwards.
"""
from __future__ import annotations

import collections
import socket
import threading
import time


class SharedMedium:
    """One serialiser shared by several links (see the module's docstring)."""

    def __init__(self, bandwidth_bps: float):
        self.bandwidth_bps = float(bandwidth_bps)
        self.free = 0.0
        self.bytes = 0
        self._lock = threading.Lock()

    def reserve(self, now: float, nbytes: int) -> float:
        """When `nbytes` read at `now` have crossed the medium."""
        with self._lock:
            self.free = max(now, self.free) + nbytes * 8.0 / self.bandwidth_bps
            self.bytes += nbytes
            return self.free


class _Direction:
    def __init__(self, source: socket.socket, sink: socket.socket, latency_s: float,
                 bandwidth_bps: float | None, chunk: int, medium: SharedMedium | None = None):
        self.source, self.sink = source, sink
        self.latency_s, self.bandwidth_bps, self.chunk = latency_s, bandwidth_bps, chunk
        self.medium = medium
        self.queue = collections.deque()
        self.ready = threading.Condition()
        self.eof = False
        self.bytes = 0

    def read_loop(self) -> None:
        free = 0.0
        try:
            while True:
                data = self.source.recv(self.chunk)
                if not data:
                    break
                now = time.monotonic()
                if self.medium is not None:
                    free = self.medium.reserve(now, len(data))
                elif self.bandwidth_bps:
                    free = max(now, free) + len(data) * 8.0 / self.bandwidth_bps
                else:
                    free = now
                with self.ready:
                    self.queue.append((free + self.latency_s, data))
                    self.ready.notify()
        except OSError:
            pass
        with self.ready:
            self.eof = True
            self.ready.notify()

    def write_loop(self) -> None:
        try:
            while True:
                with self.ready:
                    self.ready.wait_for(lambda: self.queue or self.eof)
                    if not self.queue:
                        break
                    due, data = self.queue.popleft()
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                self.bytes += len(data)     # before sending: what the peer has read is counted
                self.sink.sendall(data)
            self.sink.shutdown(socket.SHUT_WR)
        except OSError:
            pass
        for sock in (self.source, self.sink):  # one side failed: end the connection
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass


class LinkEmulator:
    def __init__(self, target, latency_s: float = 0.0, bandwidth_bps: float | None = None,
                 listen_host: str = "127.0.0.1", chunk: int = 16384,
                 medium: SharedMedium | None = None):
        """`medium`: share that serialiser with other links instead of a bandwidth of its own."""
        self.target = (str(target[0]), int(target[1]))
        self.latency_s, self.bandwidth_bps, self.chunk = float(latency_s), bandwidth_bps, chunk
        self.medium = medium
        self._listener = socket.create_server((listen_host, 0))
        self.endpoint = self._listener.getsockname()[:2]
        self._sockets: list = []
        self._lock = threading.Lock()
        self.directions: list = []

    def start(self) -> "LinkEmulator":
        threading.Thread(target=self._accept_loop, daemon=True, name="linkemu accept").start()
        return self

    def _accept_loop(self) -> None:
        while True:
            try:
                client, _ = self._listener.accept()
            except OSError:
                return
            try:
                server = socket.create_connection(self.target, timeout=10)
                server.settimeout(None)
            except OSError:
                client.close()
                continue
            for sock in (client, server):
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._sockets += [client, server]
            for source, sink in ((client, server), (server, client)):
                direction = _Direction(source, sink, self.latency_s, self.bandwidth_bps,
                                       self.chunk, self.medium)
                self.directions.append(direction)
                threading.Thread(target=direction.read_loop, daemon=True).start()
                threading.Thread(target=direction.write_loop, daemon=True).start()

    def close(self) -> None:
        try:
            self._listener.shutdown(socket.SHUT_RDWR)  # wakes the accept() of our thread
        except OSError:
            pass
        self._listener.close()
        with self._lock:
            for sock in self._sockets:
                try:
                    sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                sock.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()
