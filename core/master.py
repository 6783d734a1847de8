"""The master: connects to slaves, uploads the scene where needed, and renders frames.

Usable without Blender (plain threads, no bpy). The paper's Fig. 3b on this side: per slave one
sender thread that hands out the next tile index as soon as the slave has a free slot (several
tiles in flight hide the network latency) and one receiver thread that validates finished tiles
and puts them on the job's results queue. The caller's thread (Blender's render thread) only
polls that queue with a timeout, so it can check for cancel in between:

    master = Master([("127.0.0.1", 47600)]); master.connect()
    master.load_scene(geometry, tree)
    job = master.render(view, tile_size=64)
    while not job.finished:
        result = job.next_result(0.1)      # TileResult or None
        ...                                # job.cancel() on user break
    job.error                              # None, or why the frame could not be finished

A slave that fails loses its tiles back to the pool and the others finish the frame.
"""
from __future__ import annotations

import queue
import select
import socket
import threading
import time
import uuid
from dataclasses import dataclass

from . import protocol
from .protocol import MsgType, ProtocolError
from .scene import SCENE_FORMAT_VERSION, Geometry, View
from .tiles import TilePool, tile_grid

POLL_S = 0.2             # how often worker threads look at the job's state
CANCEL_TIMEOUT_S = 30.0  # a slave that does not confirm a cancel by then is dropped


class MasterError(Exception):
    """Something the user should read: an unreachable slave, a refused handshake, no slaves."""


@dataclass
class TileResult:
    index: int
    x: int
    y: int
    w: int
    h: int
    passes: dict            # "combined" (h,w,4), "depth" (h,w), "normal" (h,w,3); float32, top row first
    slave_name: str
    slave_id: str
    render_ms: float


class SlaveConnection:
    """A connected, handshaken slave. Sends are serialised by a lock; one thread receives."""

    def __init__(self, host: str, port: int, sock: socket.socket, welcome: dict):
        self.host, self.port, self.sock = host, port, sock
        self.name = protocol.get_str(welcome, "name", 64)
        self.id = protocol.get_str(welcome, "id", 64)
        self.device = protocol.get_str(welcome, "device", 256)
        self.compute_units = protocol.get_int(welcome, "compute_units")
        self.memory = protocol.get_int(welcome, "memory")
        self.closed = False
        self._send_lock = threading.Lock()

    @property
    def label(self) -> str:
        return f"{self.name} ({self.host}:{self.port})"

    def send(self, msg_type: MsgType, header: dict | None = None, arrays: dict | None = None) -> None:
        with self._send_lock:
            protocol.send_message(self.sock, msg_type, header, arrays)

    def recv(self, limits: protocol.Limits = protocol.DEFAULT_LIMITS) -> protocol.Message:
        return protocol.recv_message(self.sock, limits, protocol.SLAVE_TO_MASTER)

    def close(self, say_bye: bool = False) -> None:
        if self.closed:
            return
        self.closed = True
        if say_bye:
            try:
                self.send(MsgType.BYE)
            except OSError:
                pass
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()


def _reason(exc: OSError) -> str:
    if isinstance(exc, ConnectionRefusedError):
        return "connection refused"
    if isinstance(exc, socket.timeout):
        return "timed out"
    return exc.strerror or str(exc) or type(exc).__name__


def connect_slave(host: str, port: int, timeout: float = 3.0, master_name: str = "master") -> SlaveConnection:
    """Connect and handshake; MasterError with a readable message on any failure."""
    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except OSError as exc:
        raise MasterError(f"cannot reach slave {host}:{port} ({_reason(exc)})") from None
    try:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # tile requests are tiny
        protocol.send_message(sock, MsgType.HELLO, {
            "protocol_version": protocol.PROTOCOL_VERSION,
            "scene_format_version": SCENE_FORMAT_VERSION, "name": master_name})
        reply = protocol.recv_message(sock, protocol.DEFAULT_LIMITS, {MsgType.WELCOME, MsgType.ERROR})
        if reply.type == MsgType.ERROR:
            raise MasterError(f"slave {host}:{port} refused the connection: "
                              f"{reply.header.get('message')}")
        theirs = reply.header.get("scene_format_version")
        if theirs != SCENE_FORMAT_VERSION:
            raise MasterError(f"slave {host}:{port}: scene format version mismatch: slave uses "
                              f"version {theirs}, master uses version {SCENE_FORMAT_VERSION}")
        connection = SlaveConnection(host, port, sock, reply.header)
        sock.settimeout(None)
        return connection
    except protocol.VersionMismatch as exc:
        sock.close()
        raise MasterError(f"slave {host}:{port}: protocol version mismatch: slave speaks version "
                          f"{exc.peer_version}, master speaks version {protocol.PROTOCOL_VERSION}") from None
    except (ProtocolError, OSError) as exc:
        sock.close()
        reason = _reason(exc) if isinstance(exc, OSError) else str(exc)
        raise MasterError(f"slave {host}:{port} failed the handshake: {reason}") from None
    except BaseException:
        sock.close()
        raise


def _in_parallel(function, items) -> list:
    """function(item) for each item on its own thread; returns [(item, result or exception)]."""
    outcomes = [None] * len(items)

    def call(i, item):
        try:
            outcomes[i] = (item, function(item))
        except Exception as exc:
            outcomes[i] = (item, exc)

    threads = [threading.Thread(target=call, args=(i, item), daemon=True) for i, item in enumerate(items)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return outcomes


class Master:
    """A set of slave connections that render frames of one scene."""

    def __init__(self, endpoints, connect_timeout: float = 3.0, name: str = "master"):
        self.endpoints = [(str(host), int(port)) for host, port in endpoints]
        self.connect_timeout = connect_timeout
        self.name = name
        self.connections: list = []
        self.errors: list = []           # connection and upload problems, readable
        self.scene_hash: str | None = None
        self.uploaded_to: list = []      # labels of the slaves the last load_scene uploaded to
        self._job: RenderJob | None = None

    @property
    def slaves(self) -> list:
        return [c for c in self.connections if not c.closed]

    def connect(self) -> list:
        """Connect to every endpoint; MasterError if none answers. Returns the connections."""
        outcomes = _in_parallel(
            lambda ep: connect_slave(ep[0], ep[1], self.connect_timeout, self.name), self.endpoints)
        for _, outcome in outcomes:
            if isinstance(outcome, SlaveConnection):
                self.connections.append(outcome)
            else:
                self.errors.append(str(outcome))
        if not self.slaves:
            raise MasterError("no slave reachable: " + "; ".join(self.errors or ["no endpoints given"]))
        return self.slaves

    def load_scene(self, geometry: Geometry, tree) -> str:
        """Make the scene present on every slave, uploading only where its hash is unknown.
        Slaves that fail are dropped (see .errors). Returns the scene hash."""
        scene_hash = protocol.scene_hash(geometry, tree)
        arrays = protocol.scene_arrays(geometry, tree)
        upload_bytes = sum(a.nbytes for a in arrays.values())
        # Generous: the slave validates and hashes the scene before it answers.
        timeout = 60.0 + upload_bytes / (10 * 2 ** 20)

        def ensure(connection: SlaveConnection) -> bool:
            connection.sock.settimeout(timeout)
            try:
                connection.send(MsgType.SCENE_QUERY, {"scene_hash": scene_hash})
                if self._scene_ready(connection, scene_hash):
                    return False
                connection.send(MsgType.SCENE_UPLOAD, {"scene_hash": scene_hash}, arrays)
                if not self._scene_ready(connection, scene_hash):
                    raise MasterError("slave did not accept the scene")
                return True
            finally:
                connection.sock.settimeout(None)

        self.uploaded_to = []
        for connection, outcome in _in_parallel(ensure, self.slaves):
            if outcome is True:
                self.uploaded_to.append(connection.label)
            elif isinstance(outcome, Exception):
                reason = _reason(outcome) if isinstance(outcome, OSError) else str(outcome)
                self.errors.append(f"slave {connection.label} dropped while loading the scene: {reason}")
                connection.close()
        if not self.slaves:
            raise MasterError("no slave could load the scene: " + "; ".join(self.errors))
        self.scene_hash = scene_hash
        return scene_hash

    @staticmethod
    def _scene_ready(connection: SlaveConnection, scene_hash: str) -> bool:
        reply = connection.recv()
        if reply.type == MsgType.ERROR:
            raise MasterError(f"slave error: {reply.header.get('message')}")
        if reply.type != MsgType.SCENE_READY or reply.header.get("scene_hash") != scene_hash:
            raise ProtocolError(f"expected SCENE_READY for {scene_hash}, got {reply.type.name}")
        return reply.header.get("present") is True

    def render(self, view: View, tile_size: int = 64, tiles_in_flight: int = 2) -> "RenderJob":
        """Start rendering `view` on every connected slave; returns at once with the job."""
        if self.scene_hash is None:
            raise MasterError("no scene loaded: call load_scene first")
        if not 1 <= tile_size <= protocol.MAX_TILE_SIZE:
            raise MasterError(f"tile size must be 1 to {protocol.MAX_TILE_SIZE}, got {tile_size}")
        if self._job is not None:
            self._job.wait()  # one receiver per socket: the previous job's threads must be gone
        if not self.slaves:
            raise MasterError("no slaves connected")
        self._job = RenderJob(self.slaves, view, tile_size, max(1, tiles_in_flight), self.scene_hash)
        self._job.start()
        return self._job

    def close(self) -> None:
        if self._job is not None:
            self._job.cancel()
            self._job.wait(5)
        for connection in self.connections:
            connection.close(say_bye=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class _SlaveWorker:
    """One slave's part in one job: its sender and receiver threads and its tiles in flight."""

    def __init__(self, job: "RenderJob", connection: SlaveConnection):
        self.job, self.connection = job, connection
        self.in_flight: set = set()
        self.alive = True
        self.cancel_deadline = None     # set while waiting for the slave to confirm a cancel
        self.tiles_done = 0
        self.state = threading.Condition()
        self.threads = [
            threading.Thread(target=self._send_loop, name=f"send {connection.label}", daemon=True),
            threading.Thread(target=self._receive_loop, name=f"recv {connection.label}", daemon=True)]

    def _send_loop(self) -> None:
        job = self.job
        try:
            self.connection.send(MsgType.FRAME_START, {
                "frame_id": job.frame_id, "scene_hash": job.scene_hash,
                "view": job.view.to_dict(), "tile_size": job.tile_size})
            while self.alive and not job.over:
                with self.state:
                    if not self.state.wait_for(
                            lambda: len(self.in_flight) < job.tiles_in_flight or not self.alive,
                            POLL_S):
                        continue
                index = job.pool.take(POLL_S)
                if index is None:
                    continue
                with self.state:
                    if not self.alive:
                        job.pool.put_back(index)
                        return
                    self.in_flight.add(index)
                self.connection.send(MsgType.TILE_REQUEST, {"frame_id": job.frame_id, "tile": index})
        except OSError as exc:
            self.lose(f"send failed ({_reason(exc)})")

    def _receive_loop(self) -> None:
        job, sock = self.job, self.connection.sock
        try:
            while True:
                with self.state:
                    waiting = self.in_flight or self.cancel_deadline is not None
                    if not self.alive or (job.over and not waiting):
                        return
                if self.cancel_deadline is not None and time.monotonic() > self.cancel_deadline:
                    self.lose("did not confirm the cancel")
                    return
                # Wait for data with a timeout, then read a whole message: a timeout inside a
                # message would desynchronise the stream.
                if not select.select([sock], [], [], POLL_S)[0]:
                    continue
                self._handle(self.connection.recv(job.limits))
        except (ProtocolError, OSError, ValueError) as exc:
            if isinstance(exc, protocol.ConnectionClosed):
                reason = "disconnected"
            elif isinstance(exc, OSError):
                reason = f"connection lost ({_reason(exc)})"
            else:
                reason = str(exc)
            self.lose(reason)

    def _handle(self, msg: protocol.Message) -> None:
        job, h = self.job, msg.header
        if msg.type == MsgType.CANCEL:
            if h.get("frame_id") == job.frame_id:
                with self.state:
                    self.cancel_deadline = None
                    self.in_flight.clear()  # the slave dropped what it had not rendered
                    self.state.notify_all()
            return
        if msg.type == MsgType.ERROR:
            raise ProtocolError(f"slave error: {h.get('message')}")
        if msg.type != MsgType.TILE_RESULT:
            raise ProtocolError(f"unexpected {msg.type.name} during a frame")
        if protocol.get_int(h, "frame_id") != job.frame_id:
            return  # a late tile of an earlier, cancelled frame
        index = protocol.get_int(h, "tile", 0, len(job.tiles) - 1)
        with self.state:
            if index not in self.in_flight:
                if self.cancel_deadline is not None or job.cancelled:
                    return
                raise ProtocolError(f"sent tile {index}, which was not asked of it")
        x, y, w, h_ = job.tiles[index]
        if [h.get(k) for k in ("x", "y", "w", "h")] != [x, y, w, h_]:
            raise ProtocolError(f"tile {index} has the wrong rectangle")
        problem = protocol.tile_passes_ok(msg.arrays, w, h_)
        if problem:
            raise ProtocolError(f"tile {index}: {problem}")
        render_ms = protocol.get_float(h, "render_ms")
        with self.state:
            self.in_flight.discard(index)
            self.state.notify_all()
        if job.cancelled:
            return
        if job.pool.mark_done(index):
            self.tiles_done += 1
            job._deliver(TileResult(index, x, y, w, h_, dict(msg.arrays), self.connection.name,
                                    self.connection.id, render_ms))

    def cancel(self) -> None:
        with self.state:
            if not self.alive:
                return
            self.cancel_deadline = time.monotonic() + CANCEL_TIMEOUT_S
        try:
            self.connection.send(MsgType.CANCEL, {"frame_id": self.job.frame_id})
        except OSError as exc:
            self.lose(f"send failed ({_reason(exc)})")

    def lose(self, reason: str) -> None:
        """Drop this slave: its tiles go back to the pool for the others."""
        with self.state:
            if not self.alive:
                return
            self.alive = False
            lost = sorted(self.in_flight)
            self.in_flight.clear()
            self.cancel_deadline = None
            self.state.notify_all()
        self.connection.close()
        for index in lost:
            self.job.pool.put_back(index)
        self.job._slave_lost(self, reason)


class RenderJob:
    """One frame in progress. Thread-safe; the caller polls next_result()."""

    def __init__(self, connections: list, view: View, tile_size: int, tiles_in_flight: int,
                 scene_hash: str):
        self.view, self.tile_size, self.tiles_in_flight = view, tile_size, tiles_in_flight
        self.scene_hash = scene_hash
        self.frame_id = uuid.uuid4().int >> 65   # unique across masters and renders; fits JSON ints
        self.tiles = tile_grid(view.region, tile_size)
        self.pool = TilePool(len(self.tiles))
        self.limits = protocol.Limits(max_tile_pixels=tile_size * tile_size)
        self.errors: list = []       # every problem, including slaves lost and recovered from
        self.error: str | None = None  # set when the frame cannot be finished
        self.cancelled = False
        self._results: queue.Queue = queue.Queue()
        self._delivered = self._taken = 0
        self._over = threading.Event()
        self._lock = threading.Lock()
        self._workers = [_SlaveWorker(self, c) for c in connections]

    def start(self) -> None:
        for worker in self._workers:
            for thread in worker.threads:
                thread.start()

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
        return {w.connection.label: w.tiles_done for w in self._workers}

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

    def cancel(self) -> None:
        """Stop the frame; every slave is told and confirms (see wait())."""
        with self._lock:
            if self._over.is_set():
                return
            self.cancelled = True
        self._end()
        for worker in self._workers:
            worker.cancel()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the job's threads to end (after the frame or a cancel); True if they did."""
        deadline = None if timeout is None else time.monotonic() + timeout
        for worker in self._workers:
            for thread in worker.threads:
                thread.join(None if deadline is None else max(0.0, deadline - time.monotonic()))
        return not any(t.is_alive() for w in self._workers for t in w.threads)

    # -- the workers' side

    def _deliver(self, result: TileResult) -> None:
        with self._lock:
            self._delivered += 1
        self._results.put(result)
        if self.pool.all_done:
            self._end()

    def _slave_lost(self, worker: _SlaveWorker, reason: str) -> None:
        with self._lock:
            self.errors.append(f"slave {worker.connection.label} lost: {reason}")
            if self._over.is_set() or any(w.alive for w in self._workers):
                return
            self.error = ("all slaves lost before the frame was finished: " + "; ".join(self.errors))
        self._end()

    def _end(self) -> None:
        if not self._over.is_set():
            self._over.set()
            self.pool.close()
            self._results.put(None)
