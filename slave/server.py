"""The slave's TCP server: one handler per master connection, the paper's Fig. 3b on this side.

Per connection three threads:
- the reader receives messages; it answers scene queries/uploads, validates frames, and puts
  tile requests (and cancels) on the work queue at once, so a cancel is seen while a tile renders;
- the connection's main thread renders tiles from the work queue (the one OpenCL device is
  shared by all connections: render calls are serialised with a lock);
- the sender transmits finished tiles and replies, so rendering never waits on the network.

A misbehaving master (garbage, truncated or oversized frames) gets an ERROR message if possible
and its connection is closed with a logged reason; the server keeps serving the others.
"""
from __future__ import annotations

import collections
import logging
import queue
import socket
import threading
import time
import uuid
from dataclasses import dataclass, field

from core.net import protocol
from core.net.protocol import MsgType, ProtocolError
from core.net.tiles import tile_grid
from core.scene.model import SCENE_FORMAT_VERSION, SceneError, View
from core.scene.scene import Scene

from .activity import Activity
from .scene_cache import SceneCache

log = logging.getLogger("kdtrace.slave")

HANDSHAKE_TIMEOUT = 10.0   # seconds a new connection may take to say HELLO
MAX_CONNECTIONS = 16


@dataclass
class Frame:
    frame_id: int
    scene: Scene
    view: View
    tiles: list
    model: str = protocol.DEFAULT_MODEL   # "3a": the render thread sends each tile itself
    payload: str = "f32"
    compress: bool = False
    cancelled: bool = False


class WorkQueue:
    """Tile requests in arrival order; a cancel removes the frame's queued tiles at once."""

    def __init__(self):
        self._items = collections.deque()
        self._ready = threading.Condition()

    def put(self, item) -> None:
        with self._ready:
            self._items.append(item)
            self._ready.notify()

    def cancel(self, frame: Frame | None, frame_id: int) -> None:
        with self._ready:
            if frame is not None:
                frame.cancelled = True
                self._items = collections.deque(
                    i for i in self._items if not (i[0] == "tile" and i[1] is frame))
            # The ack goes through the render loop, so it leaves after the tile being rendered.
            self._items.append(("cancel_ack", frame_id))
            self._ready.notify()

    def get(self):
        with self._ready:
            self._ready.wait_for(lambda: self._items)
            return self._items.popleft()


class MasterConnection:
    """One master's connection; run() is its main (render) thread."""

    def __init__(self, server: "SlaveServer", sock: socket.socket, peer: str):
        self.server, self.sock, self.peer = server, sock, peer
        self.work = WorkQueue()
        self.outbox: queue.Queue = queue.Queue()
        self.frame: Frame | None = None
        self._send_lock = threading.Lock()

    # -- threads

    def run(self) -> None:
        sender = threading.Thread(target=self._send_loop, name=f"send {self.peer}", daemon=True)
        try:
            if not self._handshake():
                return
            sender.start()
            threading.Thread(target=self._read_loop, name=f"read {self.peer}", daemon=True).start()
            self._render_loop()
        except Exception:  # never let one connection take the server down
            log.exception("master %s: unexpected error", self.peer)
        finally:
            self.outbox.put(None)
            if sender.is_alive():
                sender.join(timeout=10)
            self._close_socket()
            self.server.activity.master_left(self.peer)
            self.server._connection_closed(self)

    def _handshake(self) -> bool:
        self.sock.settimeout(HANDSHAKE_TIMEOUT)
        try:
            msg = protocol.recv_message(self.sock, self.server.limits, {MsgType.HELLO})
            peer_scene = msg.header.get("scene_format_version")
            if peer_scene != SCENE_FORMAT_VERSION:
                raise ProtocolError(f"scene format version mismatch: master uses version "
                                    f"{peer_scene}, slave uses version {SCENE_FORMAT_VERSION}")
            self.peer = f"{protocol.get_str(msg.header, 'name', 64) or '?'}@{self.peer}"
            if self.server.secret is not None and not self._authenticate(msg.header.get("nonce")):
                return False
        except protocol.VersionMismatch as exc:
            return self._refuse(f"protocol version mismatch: master speaks version "
                                f"{exc.peer_version}, slave speaks version {protocol.PROTOCOL_VERSION}")
        except (ProtocolError, OSError) as exc:
            return self._refuse(str(exc) or type(exc).__name__)
        self.sock.settimeout(None)  # masters stay connected, idle, between renders
        info = self.server.device_info
        protocol.send_message(self.sock, MsgType.WELCOME, {
            "protocol_version": protocol.PROTOCOL_VERSION,
            "scene_format_version": SCENE_FORMAT_VERSION,
            "name": self.server.name, "id": self.server.slave_id,
            "device": info["name"], "compute_units": info["compute_units"],
            "memory": info["memory"], "platform": info.get("platform", ""),
            "authenticated": self.server.secret is not None})
        log.info("master %s connected", self.peer)
        self.server.activity.master_connected(self.peer)
        return True

    def _authenticate(self, master_nonce) -> bool:
        """The HMAC challenge-response (see core.net.protocol); nothing else is accepted before it."""
        if master_nonce is None:
            return self._refuse("this slave requires authentication: the master sent no nonce")
        master_nonce = protocol.check_hex(master_nonce, protocol.NONCE_HEX, "master nonce")
        secret, nonce = self.server.secret, protocol.new_nonce()
        protocol.send_message(self.sock, MsgType.CHALLENGE, {
            "nonce": nonce, "proof": protocol.auth_proof(secret, "slave", master_nonce, nonce)})
        try:
            reply = protocol.recv_message(self.sock, protocol.DEFAULT_LIMITS, {MsgType.AUTH})
        except protocol.ConnectionClosed:
            log.warning("master %s refused: it left during authentication (no or another "
                        "secret)", self.peer)
            return False
        if not protocol.proof_ok(secret, "master", master_nonce, nonce, reply.header.get("proof")):
            time.sleep(0.2)  # a little friction for guessers
            return self._refuse("authentication failed: wrong shared secret")
        return True

    def _refuse(self, reason: str) -> bool:
        log.warning("master %s refused: %s", self.peer, reason)
        try:
            protocol.send_message(self.sock, MsgType.ERROR, {"message": reason})
        except OSError:
            pass
        return False

    def _read_loop(self) -> None:
        try:
            while True:
                msg = protocol.recv_message(self.sock, self.server.limits, protocol.MASTER_TO_SLAVE)
                if msg.type == MsgType.BYE:
                    log.info("master %s said bye", self.peer)
                    return
                if msg.type == MsgType.ERROR:
                    log.warning("master %s reported: %s", self.peer, msg.header.get("message"))
                    return
                self._handle(msg)
        except protocol.ConnectionClosed:
            log.info("master %s disconnected", self.peer)
        except ProtocolError as exc:
            log.warning("master %s: closing connection: %s", self.peer, exc)
            self.outbox.put((MsgType.ERROR, {"message": str(exc)}, None))
        except OSError as exc:
            log.info("master %s: connection lost: %s", self.peer, exc)
        except Exception:  # a bug or MemoryError: end this connection, keep the server
            log.exception("master %s: unexpected error", self.peer)
            self.outbox.put((MsgType.ERROR, {"message": "internal error in the slave"}, None))
        finally:
            self.work.put(None)  # stops the render loop, which stops the sender

    def _render_loop(self) -> None:
        while True:
            item = self.work.get()
            if item is None:
                return
            if item[0] == "cancel_ack":
                self.outbox.put((MsgType.CANCEL, {"frame_id": item[1]}, None))
                continue
            _, frame, index = item
            if frame.cancelled:
                continue
            x, y, w, h = frame.tiles[index]
            start, built_before = time.perf_counter(), self.server.tracer.build_seconds
            try:
                passes = self.server.render_tile(frame, x, y, w, h)
            except Exception as exc:  # a tracer failure ends this frame, not the slave
                log.exception("master %s: rendering tile %d failed", self.peer, index)
                frame.cancelled = True
                self.outbox.put((MsgType.ERROR, {"frame_id": frame.frame_id,
                                                 "message": f"rendering failed: {exc}"}, None))
                continue
            ms = (time.perf_counter() - start) * 1000.0
            self.server.activity.tile_rendered(self.peer, frame.frame_id, ms,
                                               self.server.tracer.build_seconds - built_before)
            tile = ("tile", frame, {"frame_id": frame.frame_id, "tile": index, "x": x, "y": y,
                                    "w": w, "h": h, "render_ms": round(ms, 3)}, passes)
            if frame.model == "3a":
                # Fig. 3a: this thread transmits the tile itself before it renders the next.
                try:
                    self._send(tile)
                except OSError as exc:
                    log.info("master %s: send failed: %s", self.peer, exc)
                    self._close_socket()
                    return
            else:
                self.outbox.put(tile)

    def _send(self, item) -> None:
        if item[0] == "tile":  # encoding (float16, zlib) happens here, off the render thread in 3b
            _, frame, header, passes = item
            fields, arrays = protocol.encode_tile(passes, frame.payload, frame.compress)
            item = (MsgType.TILE_RESULT, {**header, **fields}, arrays)
            self.server.activity.sent(self.peer, frame.frame_id,
                                      sum(a.nbytes for a in arrays.values()))
        with self._send_lock:
            protocol.send_message(self.sock, *item)

    def _send_loop(self) -> None:
        while True:
            item = self.outbox.get()
            if item is None:
                return
            try:
                self._send(item)
            except OSError as exc:
                log.info("master %s: send failed: %s", self.peer, exc)
                self._close_socket()  # wakes the reader, which winds the connection down
                return

    def _close_socket(self) -> None:
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()

    # -- messages (reader thread)

    def _handle(self, msg: protocol.Message) -> None:
        h = msg.header
        if msg.type == MsgType.SCENE_QUERY:
            scene_hash = protocol.check_scene_hash(h.get("scene_hash"))
            present = self.server.scenes.get(scene_hash) is not None
            self.outbox.put((MsgType.SCENE_READY, {"scene_hash": scene_hash, "present": present}, None))
        elif msg.type == MsgType.SCENE_UPLOAD:
            scene_hash = protocol.check_scene_hash(h.get("scene_hash"))
            try:
                scene = Scene.from_wire(msg.arrays)
            except SceneError as exc:
                raise ProtocolError(f"invalid scene upload: {exc}") from None
            if scene.hash != scene_hash:
                raise ProtocolError(f"scene upload hash mismatch: announced {scene_hash}, "
                                    f"content hashes to {scene.hash}")
            self.server.scenes.put(scene)
            log.info("master %s uploaded scene %s (%d triangles)", self.peer, scene_hash,
                     scene.geometry.triangle_count)
            self.outbox.put((MsgType.SCENE_READY, {"scene_hash": scene_hash, "present": True}, None))
        elif msg.type == MsgType.FRAME_START:
            self._start_frame(h)
        elif msg.type == MsgType.TILE_REQUEST:
            frame_id = protocol.get_int(h, "frame_id")
            frame = self.frame
            # Requests for a frame that failed to start or was cancelled are dropped quietly:
            # the master pipelines them before it can know.
            if frame is None or frame.frame_id != frame_id or frame.cancelled:
                return
            index = protocol.get_int(h, "tile", 0, len(frame.tiles) - 1)
            self.work.put(("tile", frame, index))
        elif msg.type == MsgType.CANCEL:
            frame_id = protocol.get_int(h, "frame_id")
            frame = self.frame if self.frame and self.frame.frame_id == frame_id else None
            self.work.cancel(frame, frame_id)
            self.server.activity.frame_over(self.peer)
        else:
            raise ProtocolError(f"unexpected {msg.type.name} after the handshake")

    def _start_frame(self, h: dict) -> None:
        frame_id = protocol.get_int(h, "frame_id")
        if self.frame is not None:
            self.frame.cancelled = True  # a new frame supersedes the old one
        self.frame = None
        try:
            scene_hash = protocol.check_scene_hash(h.get("scene_hash"))
            scene = self.server.scenes.get(scene_hash)
            if scene is None:
                raise SceneError(f"scene {scene_hash} is not loaded on this slave")
            view = View.from_dict(h.get("view"))
            scene.check_view(view)
            tile_w = protocol.get_int(h, "tile_size", 1, protocol.MAX_TILE_SIZE)
            tile_h = protocol.get_int(h, "tile_height", 1, protocol.MAX_TILE_SIZE) \
                if "tile_height" in h else tile_w
            model = h.get("model", protocol.DEFAULT_MODEL)
            payload = h.get("payload", "f32")
            compress = h.get("compress", False)
            if model not in protocol.MODELS or payload not in protocol.PAYLOADS \
                    or not isinstance(compress, bool):
                raise ProtocolError("bad model, payload or compress field")
        except (SceneError, ProtocolError) as exc:
            log.warning("master %s: frame %d refused: %s", self.peer, frame_id, exc)
            self.outbox.put((MsgType.ERROR, {"frame_id": frame_id, "message": str(exc)}, None))
            return
        self.frame = Frame(frame_id, scene, view, tile_grid(view.region, (tile_w, tile_h)),
                           model, payload, compress)
        self.server.activity.frame_started(self.peer, frame_id, scene_hash, len(self.frame.tiles))


class SlaveServer:
    """Listens for masters; one MasterConnection (thread) per master; one shared Tracer."""

    def __init__(self, tracer, name: str, bind: str = "0.0.0.0", port: int = 0,
                 limits: protocol.Limits = protocol.DEFAULT_LIMITS, cache_size: int = 2,
                 secret: bytes | None = None, cache_dir=None,
                 cache_disk_bytes: int = 2 * 1024 ** 3):
        """`secret`: masters must pass the HMAC challenge-response (None: anyone may connect).
        `cache_dir`: also keep scenes on disk there, up to `cache_disk_bytes`."""
        self.tracer, self.name = tracer, name
        self.device_info = dict(tracer.device_info)
        self.slave_id = uuid.uuid4().hex[:12]
        self.limits = limits
        self.secret = secret
        self.scenes = SceneCache(cache_size, cache_dir, cache_disk_bytes)
        self.activity = Activity()
        self._device_lock = threading.Lock()
        self._loaded_hash = None
        self._connections = set()
        self._connections_lock = threading.Lock()
        self._listener = socket.create_server((bind, port), reuse_port=False)
        self.address = self._listener.getsockname()[:2]
        self._accept_thread = None

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
            with self._connections_lock:
                busy = len(self._connections) >= MAX_CONNECTIONS
                if not busy:
                    connection = MasterConnection(self, sock, peer)
                    self._connections.add(connection)
            if busy:
                log.warning("refusing master %s: %d connections already", peer, MAX_CONNECTIONS)
                sock.close()
                continue
            threading.Thread(target=connection.run, name=f"master {peer}", daemon=True).start()

    def _connection_closed(self, connection: MasterConnection) -> None:
        with self._connections_lock:
            self._connections.discard(connection)

    def render_tile(self, frame: Frame, x: int, y: int, w: int, h: int) -> dict:
        # One device for all masters: loading and rendering are serialised.
        with self._device_lock:
            if self._loaded_hash != frame.scene.hash:
                self._loaded_hash = None
                self.tracer.load(frame.scene)
                self._loaded_hash = frame.scene.hash
            return self.tracer.render_tile(frame.view, x, y, w, h)

    def close(self) -> None:
        self._listener.close()
        with self._connections_lock:
            connections = list(self._connections)
        for connection in connections:
            connection._close_socket()
