"""The master: connects to slaves, uploads the scene where needed, and renders frames.

Usable without Blender (plain threads, no bpy). The paper's Fig. 3b on this side: per slave one
sender thread that hands out the next tile index as soon as the slave has a free slot (several
tiles in flight hide the network latency) and one receiver thread that validates finished tiles
and puts them on the job's results queue. The caller's thread (Blender's render thread) only
polls that queue with a timeout, so it can check for cancel in between:

    master = Master([("127.0.0.1", 47600)]); master.connect()
    master.load_scene(scene)               # a core.scene.scene.Scene
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
from ..scene.model import SCENE_FORMAT_VERSION, View
from ..scene.scene import Scene
from .tiles import TilePool, partition_tile_size, tile_dims, tile_grid

POLL_S = 0.2             # how often worker threads look at the job's state
SLAVE_TIMEOUT_S = 30.0   # a slave that holds tiles and says nothing this long is dropped
DEFAULT_TILE_SIZE = 64
DEFAULT_TILES_IN_FLIGHT = 2
MAX_TILES_IN_FLIGHT = 16


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


FROM_ENVIRONMENT = object()   # Master(secret=...) default: read $KDTRACE_SECRET if it is set


def _handshake(sock: socket.socket, host: str, port: int, master_name: str,
               secret: bytes | None) -> dict:
    """HELLO, the HMAC challenge-response when the slave asks for it, WELCOME; returns the
    WELCOME header. MasterError names what went wrong."""
    nonce = protocol.new_nonce()
    protocol.send_message(sock, MsgType.HELLO, {
        "protocol_version": protocol.PROTOCOL_VERSION,
        "scene_format_version": SCENE_FORMAT_VERSION, "name": master_name, "nonce": nonce})
    expect = {MsgType.WELCOME, MsgType.ERROR, MsgType.CHALLENGE}
    reply = protocol.recv_message(sock, protocol.DEFAULT_LIMITS, expect)
    if reply.type == MsgType.CHALLENGE:
        if secret is None:
            raise MasterError(f"slave {host}:{port} requires a shared secret and this master has "
                              f"none (set {protocol.SECRET_ENV} or a secret file)")
        slave_nonce = protocol.check_hex(reply.header.get("nonce"), protocol.NONCE_HEX, "slave nonce")
        if not protocol.proof_ok(secret, "slave", nonce, slave_nonce, reply.header.get("proof")):
            raise MasterError(f"slave {host}:{port} failed authentication "
                              f"(its shared secret differs from the master's)")
        protocol.send_message(sock, MsgType.AUTH, {
            "proof": protocol.auth_proof(secret, "master", nonce, slave_nonce)})
        reply = protocol.recv_message(sock, protocol.DEFAULT_LIMITS, {MsgType.WELCOME, MsgType.ERROR})
    elif reply.type == MsgType.WELCOME and secret is not None:
        raise MasterError(f"slave {host}:{port} does not authenticate (no shared secret "
                          f"configured on the slave); refused")
    if reply.type == MsgType.ERROR:
        raise MasterError(f"slave {host}:{port} refused the connection: "
                          f"{reply.header.get('message')}")
    theirs = reply.header.get("scene_format_version")
    if theirs != SCENE_FORMAT_VERSION:
        raise MasterError(f"slave {host}:{port}: scene format version mismatch: slave uses "
                          f"version {theirs}, master uses version {SCENE_FORMAT_VERSION}")
    return reply.header


def connect_slave(host: str, port: int, timeout: float = 3.0, master_name: str = "master",
                  secret: bytes | None = None) -> SlaveConnection:
    """Connect and handshake; MasterError with a readable message on any failure."""
    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except OSError as exc:
        raise MasterError(f"cannot reach slave {host}:{port} ({_reason(exc)})") from None
    try:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # tile requests are tiny
        welcome = _handshake(sock, host, port, master_name, secret)
        connection = SlaveConnection(host, port, sock, welcome)
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

    def __init__(self, endpoints, connect_timeout: float = 3.0, name: str = "master",
                 secret=FROM_ENVIRONMENT, slave_timeout: float = SLAVE_TIMEOUT_S):
        """`secret`: bytes/str shared with the slaves, None for none, default: $KDTRACE_SECRET
        if set. `slave_timeout`: a slave holding tiles that sends nothing for this many seconds
        is dropped and its tiles go to the others."""
        self.endpoints = [(str(host), int(port)) for host, port in endpoints]
        self.connect_timeout = connect_timeout
        self.name = name
        if secret is FROM_ENVIRONMENT:
            try:
                secret = protocol.load_secret()
            except protocol.AuthError as exc:
                raise MasterError(str(exc)) from None
        self.secret = secret.encode("utf-8") if isinstance(secret, str) else secret
        self.slave_timeout = float(slave_timeout)
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
            lambda ep: connect_slave(ep[0], ep[1], self.connect_timeout, self.name, self.secret),
            self.endpoints)
        for _, outcome in outcomes:
            if isinstance(outcome, SlaveConnection):
                self.connections.append(outcome)
            else:
                self.errors.append(str(outcome))
        if not self.slaves:
            raise MasterError("no slave reachable: " + "; ".join(self.errors or ["no endpoints given"]))
        return self.slaves

    def load_scene(self, scene: Scene) -> str:
        """Make the scene present on every slave, uploading only where its hash is unknown.
        Slaves that fail are dropped (see .errors). Returns the scene hash."""
        if self._job is not None:
            self._job.wait()  # its threads may still read the sockets (copies being cancelled)
        scene_hash = scene.hash
        arrays = scene.wire_arrays()
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

    def render(self, view: View, tile_size=DEFAULT_TILE_SIZE,
               tiles_in_flight: int = DEFAULT_TILES_IN_FLIGHT, *, partition: int | None = None,
               model: str = protocol.DEFAULT_MODEL, payload: str = "f32",
               compress: bool = False, duplicates: bool = True) -> "RenderJob":
        """Start rendering `view` on every connected slave; returns at once with the job.

        tile_size: pixels (int, square tiles, or a (w, h) pair); partition=N instead cuts the
        render region into N x N tiles (Table 5b). tiles_in_flight: requests outstanding per
        slave (model 3b). model: "3b" (sender + receiver thread per slave, the default) or "3a"
        (one thread per slave that asks for a tile and waits for it: for comparison).
        payload: "f32" or "f16" (combined and normal as float16); compress: zlib when it pays.
        duplicates: near the end idle slaves take copies of tiles still outstanding elsewhere.
        """
        if self.scene_hash is None:
            raise MasterError("no scene loaded: call load_scene first")
        if model not in protocol.MODELS:
            raise MasterError(f"model must be one of {protocol.MODELS}, got {model!r}")
        if not 1 <= tiles_in_flight <= MAX_TILES_IN_FLIGHT:
            raise MasterError(f"tiles in flight must be 1 to {MAX_TILES_IN_FLIGHT}, "
                              f"got {tiles_in_flight}")
        if payload not in protocol.PAYLOADS:
            raise MasterError(f"payload must be one of {protocol.PAYLOADS}, got {payload!r}")
        try:
            dims = partition_tile_size(view.region, partition) if partition else tile_dims(tile_size)
        except ValueError as exc:
            raise MasterError(str(exc)) from None
        if not all(1 <= d <= protocol.MAX_TILE_SIZE for d in dims):
            raise MasterError(f"tile size must be 1 to {protocol.MAX_TILE_SIZE}, got {dims}")
        if self._job is not None:
            self._job.wait()  # one receiver per socket: the previous job's threads must be gone
        if not self.slaves:
            raise MasterError("no slaves connected")
        self._job = RenderJob(self.slaves, view, dims, int(tiles_in_flight),
                              self.scene_hash, model=model, payload=payload,
                              compress=bool(compress), duplicates=duplicates,
                              slave_timeout=self.slave_timeout)
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
    """One slave's part in one job: its threads (model 3b: a sender and a receiver; model 3a:
    one that does both) and its tiles in flight."""

    def __init__(self, job: "RenderJob", connection: SlaveConnection):
        self.job, self.connection = job, connection
        self.in_flight: set = set()
        self.alive = True
        self.cancel_deadline = None     # set while waiting for the slave to confirm a cancel
        self.last_heard = time.monotonic()
        self.tiles_done = 0
        self.state = threading.Condition()
        label = connection.label
        if job.model == "3a":
            self.threads = [threading.Thread(target=self._simple_loop, name=f"slave {label}",
                                             daemon=True)]
        else:
            self.threads = [
                threading.Thread(target=self._send_loop, name=f"send {label}", daemon=True),
                threading.Thread(target=self._receive_loop, name=f"recv {label}", daemon=True)]

    # -- model 3b

    def _frame_start(self) -> None:
        job = self.job
        self.connection.send(MsgType.FRAME_START, {
            "frame_id": job.frame_id, "scene_hash": job.scene_hash, "view": job.view.to_dict(),
            "tile_size": job.tile_w, "tile_height": job.tile_h, "model": job.model,
            "payload": job.payload, "compress": job.compress})

    def _take(self) -> int | None:
        job = self.job
        index = job.pool.take(POLL_S, holder=self, duplicates=job.duplicates)
        if index is None:
            return None
        with self.state:
            if not self.alive:
                job.pool.put_back(index, self)
                return None
            if not self.in_flight:
                self.last_heard = time.monotonic()  # the deadline runs from the first request
            self.in_flight.add(index)
        return index

    def _send_loop(self) -> None:
        job = self.job
        try:
            self._frame_start()
            while self.alive and not job.over:
                with self.state:
                    if not self.state.wait_for(
                            lambda: len(self.in_flight) < job.tiles_in_flight or not self.alive,
                            POLL_S):
                        continue
                index = self._take()
                if index is not None:
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
                    if job.over and self.in_flight and self.cancel_deadline is None:
                        stale = True    # copies of tiles another slave finished first
                    else:
                        stale = False
                if stale:
                    self.cancel()
                self._check_deadlines(waiting)
                # Wait for data with a timeout, then read a whole message: a timeout inside a
                # message would desynchronise the stream.
                if not select.select([sock], [], [], POLL_S)[0]:
                    continue
                self._handle(self.connection.recv(job.limits))
        except _SlaveTimeout as exc:
            self.lose(str(exc))
        except (ProtocolError, OSError, ValueError) as exc:
            self.lose(_describe(exc))

    def _check_deadlines(self, waiting) -> None:
        now = time.monotonic()
        if self.cancel_deadline is not None and now > self.cancel_deadline:
            raise _SlaveTimeout("did not confirm the cancel")
        if waiting and now - self.last_heard > self.job.slave_timeout:
            raise _SlaveTimeout(f"did not answer within {self.job.slave_timeout:g} s")

    # -- model 3a

    def _simple_loop(self) -> None:
        """Fig. 3a: ask for one tile, wait for it, deliver it, ask for the next."""
        job, sock = self.job, self.connection.sock
        try:
            self._frame_start()
            while self.alive and not job.over:
                index = self._take()
                if index is None:
                    continue
                self.connection.send(MsgType.TILE_REQUEST, {"frame_id": job.frame_id, "tile": index})
                while self.alive and index in self.in_flight:
                    if job.over and self.cancel_deadline is None:
                        self.cancel()
                    self._check_deadlines(True)
                    if select.select([sock], [], [], POLL_S)[0]:
                        self._handle(self.connection.recv(job.limits))
            while self.alive and self.cancel_deadline is not None:  # a cancel being confirmed
                self._check_deadlines(True)
                if select.select([sock], [], [], POLL_S)[0]:
                    self._handle(self.connection.recv(job.limits))
        except _SlaveTimeout as exc:
            self.lose(str(exc))
        except (ProtocolError, OSError, ValueError) as exc:
            self.lose(_describe(exc))

    # -- both

    def _handle(self, msg: protocol.Message) -> None:
        job, h = self.job, msg.header
        self.last_heard = time.monotonic()
        if msg.type == MsgType.CANCEL:
            if h.get("frame_id") == job.frame_id:
                with self.state:
                    self.cancel_deadline = None
                    for index in self.in_flight:  # the slave dropped what it had not rendered
                        job.pool.put_back(index, self)
                    self.in_flight.clear()
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
        passes = protocol.decode_tile(h, msg.arrays, w, h_, job.payload)
        render_ms = protocol.get_float(h, "render_ms")
        with self.state:
            self.in_flight.discard(index)
            self.state.notify_all()
        if job.cancelled:
            return
        if job.pool.mark_done(index):
            self.tiles_done += 1
            job._deliver(TileResult(index, x, y, w, h_, passes, self.connection.name,
                                    self.connection.id, render_ms))

    def cancel(self) -> None:
        with self.state:
            if not self.alive or self.cancel_deadline is not None:
                return
            self.cancel_deadline = time.monotonic() + self.job.slave_timeout
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
            self.job.pool.put_back(index, self)
        self.job._slave_lost(self, reason)


class _SlaveTimeout(Exception):
    pass


def _describe(exc: Exception) -> str:
    if isinstance(exc, protocol.ConnectionClosed):
        return "disconnected"
    if isinstance(exc, OSError):
        return f"connection lost ({_reason(exc)})"
    return str(exc)


class RenderJob:
    """One frame in progress. Thread-safe; the caller polls next_result()."""

    def __init__(self, connections: list, view: View, tile_dims: tuple, tiles_in_flight: int,
                 scene_hash: str, model: str = protocol.DEFAULT_MODEL, payload: str = "f32",
                 compress: bool = False, duplicates: bool = True,
                 slave_timeout: float = SLAVE_TIMEOUT_S):
        self.view, self.tiles_in_flight = view, tiles_in_flight
        self.tile_w, self.tile_h = tile_dims
        self.model, self.payload, self.compress = model, payload, compress
        self.duplicates, self.slave_timeout = duplicates, slave_timeout
        self.scene_hash = scene_hash
        self.frame_id = uuid.uuid4().int >> 65   # unique across masters and renders; fits JSON ints
        self.tiles = tile_grid(view.region, tile_dims)
        self.pool = TilePool(len(self.tiles), max_copies=2 if duplicates else 1)
        self.limits = protocol.Limits(max_tile_pixels=self.tile_w * self.tile_h)
        self.errors: list = []       # every problem, including slaves lost and recovered from
        self.error: str | None = None  # set when the frame cannot be finished
        self.cancelled = False
        self.started = time.monotonic()
        self.first_tile_s: float | None = None   # seconds from start to the first result
        self.elapsed_s: float | None = None      # seconds from start to the last tile
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
            now = time.monotonic() - self.started
            if self.first_tile_s is None:
                self.first_tile_s = now
        self._results.put(result)
        if self.pool.all_done:
            self.elapsed_s = now
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
