"""The wire protocol between the master and the slaves.

A message is a fixed header `!4sHHIQ` (magic b"KDTR", protocol version, message type, JSON
length, payload length), a UTF-8 JSON object, then the payload: raw little-endian arrays listed
in the JSON under "arrays": [{"name", "dtype", "shape"}], concatenated in that order.

Nothing received is unpickled or evaluated: the JSON is parsed with the json module, arrays are
built with numpy.frombuffer from an allow-listed set of dtypes, and every length is checked
against a per-type limit *before* anything is allocated. See docs/protocol.md.

A `Channel` is one peer connection as both sides use it after connecting: every message, sent
or received, has a deadline for the whole message (a grace, then a minimum average rate). After
the plaintext OPEN exchange (versions) the channel runs over TLS 1.3 with both identities
pinned (core/net/secure.py, core/net/identity.py): TLS encrypts and authenticates every byte,
so the messages carry no MACs of their own.
"""
from __future__ import annotations

import contextlib
import enum
import functools
import json
import math
import select
import socket
import ssl
import struct
import sys
import threading
import time
import zlib
from dataclasses import dataclass, field

import numpy as np

from ..scene.instances import MAX_INSTANCES, MAX_MESHES

# 2: HMAC handshake, float16/zlib tiles, N x M tiles; 3: compact kd-tree arrays; 4: HEARTBEAT,
# heartbeat_s in HELLO, "busy" refusals, session MACs after an authenticated handshake;
# 5: FRAME_START "passes" (a tile carries only those) and the 8-bit preview payload "u8";
# 6: SCENE_QUERY "meshes_hash" and mesh_hashes, SCENE_READY "meshes_present" and mesh_held,
# SCENE_INSTANCES and SCENE_MESHES; at most 20 arrays a message; 7: OPEN then TLS 1.3 with
# pinned identities (no CHALLENGE/AUTH, no MACs), farm and pairing proofs in HELLO/WELCOME,
# holder proofs for cached scenes.
PROTOCOL_VERSION = 7
MAGIC = b"KDTR"
HEADER = struct.Struct("!4sHHIQ")
DEFAULT_PORT = 47600
SERVICE_TYPE = "_kdtrace._tcp.local."

# Only these dtypes may appear on the wire; all little-endian.
ALLOWED_DTYPES = {name: np.dtype("<" + name) for name in ("f4", "f2", "u4", "u2", "u1", "i4")}
MAX_ARRAYS = 20
MAX_DIMS = 4
MAX_TILE_SIZE = 1024
MAX_FRAME_TILES = 1 << 20       # tiles of one frame (65536 x 65536 pixels in 64-pixel tiles)
MAX_TILES_IN_FLIGHT = 16        # tile requests a master may have outstanding on one slave
# A frame's work (docs/protocol.md, "Frame"; counted as View.tile_rays counts it, in Python
# integers): its largest tile at most MAX_TILE_RAYS (a master cuts smaller tiles where its own
# would be larger: tiles.fit_tile_work), one camera sample at most MAX_SAMPLE_RAYS (the least
# a slave's launch can trace, so what bounds the time a cancel waits for).
MAX_TILE_RAYS = 1 << 40
MAX_SAMPLE_RAYS = 1 << 22

# Liveness (docs/protocol.md, "Liveness and deadlines"). A busy slave sends HEARTBEAT at least
# every heartbeat_s (the master asks for its interval in HELLO); a peer that owes an answer and
# says nothing for SILENCE_S is lost. Every message, either way, must arrive or leave within
# SILENCE_S plus its size at MIN_RATE_BPS: a stalled or dribbling peer cannot hold a thread.
HEARTBEAT_S = 2.0
HEARTBEAT_RANGE_S = (0.05, 30.0)
SILENCE_S = 10.0
# A slave closes a master connection that has no work there and says nothing for IDLE_S (its
# slot goes back); a master in a frame that has nothing left for a slave (its last tiles are
# elsewhere) sends HEARTBEAT when it has sent nothing for KEEPALIVE_S.
IDLE_S = 300.0
KEEPALIVE_S = 30.0
MIN_RATE_BPS = 256 * 1024
RECV_BUFFER_BYTES = 64 * 1024   # a channel's receive buffer at first (it grows to fit messages)
RECV_KEEP_BYTES = 2 << 20       # messages up to this size are received in that buffer (tiles up
                                # to 256 x 256 with every pass); larger ones in their own
PREALLOCATE_BYTES = 8 << 20     # such a message's own buffer is allocated at once up to this size
LOW_WATER_BYTES = 256 * 1024    # a long read wakes when this much (or the rest) has arrived
POLL_S = 0.25                   # how often a blocked send or receive looks at its deadline
TLS_RECORD_BYTES = 16384 + 256  # a TLS record's plaintext at most, with its overhead
SLAVE_STATES = ("idle", "loading", "compiling", "waiting", "rendering")
# How master and slave exchange a frame's tiles (FRAME_START "model"): the paper's Fig. 3a (one
# thread per slave asks for a tile and waits for it) and Fig. 3b (requests and results overlap).
MODELS = ("3a", "3b")
DEFAULT_MODEL = "3b"


class MsgType(enum.IntEnum):
    HELLO = 1          # master -> slave: versions, master name
    WELCOME = 2        # slave -> master: versions, slave name/id, device, compute units, memory
    SCENE_QUERY = 3    # master -> slave: scene hash; the slave answers SCENE_READY
    SCENE_UPLOAD = 4   # master -> slave: scene hash + geometry and tree arrays
    SCENE_READY = 5    # slave -> master: scene hash, present (bool)
    FRAME_START = 6    # master -> slave: frame id, scene hash, view, tile size
    TILE_REQUEST = 7   # master -> slave: frame id, tile index
    TILE_RESULT = 8    # slave -> master: frame id, tile index, x/y/w/h, render ms + passes
    CANCEL = 9         # master -> slave: frame id; the slave answers CANCEL once the frame is quiet
    ERROR = 10         # either way: message (+ frame id when it concerns a frame)
    BYE = 11           # master -> slave: closing
    # 12 and 13 (CHALLENGE, AUTH) were protocol 6's secret handshake: TLS replaced them.
    HEARTBEAT = 14     # slave -> master: what a busy slave is doing (state, frame id, tile);
                       # master -> slave: it is still in a frame that has nothing for the slave
    SCENE_INSTANCES = 15   # master -> slave: scene hash, meshes hash + the instance arrays
                           # alone (the slave holds the meshes); the slave answers SCENE_READY
    SCENE_MESHES = 16      # master -> slave: scene hash + the meshes the slave lacks, every
                           # mesh's hash, textures, instances; the slave answers SCENE_READY
    OPEN = 17          # either way, in plaintext, first: the versions; TLS begins after it


MASTER_TO_SLAVE = frozenset({MsgType.HELLO, MsgType.SCENE_QUERY, MsgType.SCENE_UPLOAD,
                             MsgType.SCENE_INSTANCES, MsgType.SCENE_MESHES, MsgType.FRAME_START,
                             MsgType.TILE_REQUEST, MsgType.CANCEL,
                             MsgType.ERROR, MsgType.BYE, MsgType.HEARTBEAT})
SLAVE_TO_MASTER = frozenset({MsgType.WELCOME, MsgType.SCENE_READY, MsgType.TILE_RESULT,
                             MsgType.CANCEL, MsgType.ERROR, MsgType.HEARTBEAT})

# Tile passes: name -> channels; (h, w) or (h, w, channels). Beyond the image, depth and normal:
# the denoising guides (Blender's Denoising Albedo and Denoising Normal, Cycles' camera space)
# and the data passes, computed by the slave only when a frame asks (slave/film.py).
TILE_PASSES = {"combined": 4, "depth": 1, "normal": 3, "albedo": 3, "denoising_normal": 3,
               "mist": 1, "emission": 3, "diffuse_color": 3, "glossy_color": 3}
# How a pass travels in the small payloads (f16, u8): "rgba" and "color" as colour, "direction"
# as a unit vector's codes, "exact" always float32.
PASS_CODING = {"combined": "rgba", "depth": "exact", "normal": "direction", "albedo": "color",
               "denoising_normal": "direction", "mist": "exact", "emission": "color",
               "diffuse_color": "color", "glossy_color": "color"}
TILE_BYTES_PER_PIXEL = 4 * sum(TILE_PASSES.values())   # the most a tile pixel may take
# The most an instance takes on the wire: its mesh (u4), 3x4 transforms at shutter open and
# close (f4; the close one only with motion blur) and visibility (u1).
INSTANCE_WIRE_BYTES = 4 + 2 * 12 * 4 + 1
MESH_HASH_BYTES = 16

class ProtocolError(Exception):
    """The peer sent something that is not a valid message; the connection cannot go on."""


class ConnectionClosed(ProtocolError):
    """The peer closed the connection cleanly between two messages."""


class ConnectionBroken(ProtocolError):
    """The connection ended in the middle of a message."""


class PeerTooSlow(ProtocolError):
    """A message did not arrive (or could not leave) within its deadline."""


def is_transient(exc: Exception) -> bool:
    """The connection failed, not the peer's logic: worth reconnecting."""
    return isinstance(exc, (OSError, ConnectionClosed, ConnectionBroken, PeerTooSlow))


class VersionMismatch(ProtocolError):
    """The peer speaks another protocol version."""

    def __init__(self, peer_version: int):
        self.peer_version = peer_version
        super().__init__(f"protocol version mismatch: peer speaks version {peer_version}, "
                         f"this side speaks version {PROTOCOL_VERSION}")


@dataclass
class Limits:
    """Upper bounds on what one message may carry, checked before anything is read."""

    max_json: int = 64 * 1024                 # control messages
    max_frame_json: int = 16 * 1024 * 1024    # FRAME_START carries the shading (materials, lights)
    max_scene_bytes: int = 4 * 1024 ** 3      # SCENE_UPLOAD payload
    max_tile_pixels: int = MAX_TILE_SIZE * MAX_TILE_SIZE
    tile_bytes_per_pixel: int = TILE_BYTES_PER_PIXEL   # the frame's passes and payload

    def json_limit(self, msg_type: MsgType) -> int:
        return self.max_frame_json if msg_type == MsgType.FRAME_START else self.max_json

    def payload_limit(self, msg_type: MsgType) -> int:
        if msg_type in (MsgType.SCENE_UPLOAD, MsgType.SCENE_MESHES):
            return self.max_scene_bytes
        if msg_type == MsgType.SCENE_INSTANCES:
            return MAX_INSTANCES * INSTANCE_WIRE_BYTES
        if msg_type == MsgType.SCENE_QUERY:
            return MAX_MESHES * MESH_HASH_BYTES      # mesh_hashes
        if msg_type == MsgType.SCENE_READY:
            return MAX_MESHES                        # mesh_held
        if msg_type == MsgType.TILE_RESULT:
            return self.max_tile_pixels * self.tile_bytes_per_pixel
        return 0  # control messages carry no arrays


DEFAULT_LIMITS = Limits()


@dataclass
class Message:
    type: MsgType
    header: dict
    arrays: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------- encoding

# One encoder and one decoder for every message (json.dumps/loads with options build new ones
# per call: a tenth of the master's cost per tile).
_JSON_ENCODER = json.JSONEncoder(separators=(",", ":"), allow_nan=False)


def encode_message(msg_type: MsgType, header: dict | None = None, arrays: dict | None = None) -> list:
    """The message as a list of buffers (header+JSON bytes, then one buffer per array)."""
    header = dict(header or {})
    specs, buffers = [], []
    for name, array in (arrays or {}).items():
        array = np.asarray(array)
        dtype = array.dtype.newbyteorder("<") if array.dtype.byteorder == ">" else array.dtype
        code = dtype.str.lstrip("<|=")
        if code not in ALLOWED_DTYPES:
            raise ValueError(f"array {name!r}: dtype {array.dtype} cannot be sent")
        array = np.ascontiguousarray(array, dtype=ALLOWED_DTYPES[code])
        specs.append({"name": name, "dtype": code, "shape": list(array.shape)})
        buffers.append(memoryview(array.reshape(-1).view(np.uint8)))
    header["arrays"] = specs
    text = _JSON_ENCODER.encode(header).encode("utf-8")
    payload_length = sum(len(b) for b in buffers)
    head = HEADER.pack(MAGIC, PROTOCOL_VERSION, int(msg_type), len(text), payload_length)
    return [head + text] + buffers


def _coalesce(buffers: list) -> list:
    # Small messages go out in one write: several small writes meet Nagle's algorithm and
    # delayed ACKs (40 ms stalls).
    if len(buffers) > 1 and sum(len(b) for b in buffers) <= 1 << 20:
        return [b"".join(buffers)]
    return buffers


def send_message(sock: socket.socket, msg_type: MsgType, header: dict | None = None,
                 arrays: dict | None = None) -> None:
    """Send one message on a plain blocking socket, unauthenticated (tests, tools); peers talk
    through a Channel."""
    for buffer in _coalesce(encode_message(msg_type, header, arrays)):
        if len(buffer):
            sock.sendall(buffer)


# ----------------------------------------------------------------------------- decoding

def _recv_exactly(sock: socket.socket, count: int, what: str, allow_eof: bool = False) -> bytearray:
    # Grow the buffer as data arrives, so a lying length costs nothing until bytes really come.
    buffer = bytearray()
    while len(buffer) < count:
        chunk = sock.recv(min(count - len(buffer), 1 << 20))
        if not chunk:
            if allow_eof and not buffer:
                raise ConnectionClosed("connection closed by peer")
            raise ConnectionBroken(f"connection closed in the middle of a message ({what}: "
                                   f"{len(buffer)} of {count} bytes)")
        buffer += chunk
    return buffer


def _reject_constant(name):
    raise ValueError(f"{name} is not allowed")


def _parse_arrays(specs, payload: bytearray) -> dict:
    if not isinstance(specs, list) or len(specs) > MAX_ARRAYS:
        raise ProtocolError(f"'arrays' must be a list of at most {MAX_ARRAYS} entries")
    arrays, offset = {}, 0
    for spec in specs:
        if not isinstance(spec, dict):
            raise ProtocolError("an 'arrays' entry is not an object")
        name, code, shape = spec.get("name"), spec.get("dtype"), spec.get("shape")
        if not isinstance(name, str) or not name or len(name) > 64 or name in arrays:
            raise ProtocolError(f"bad or duplicate array name {name!r}")
        if not isinstance(code, str) or code not in ALLOWED_DTYPES:
            raise ProtocolError(f"array {name!r}: dtype {str(code)[:32]!r} not allowed "
                                f"(allowed: {', '.join(ALLOWED_DTYPES)})")
        if (not isinstance(shape, list) or len(shape) > MAX_DIMS
                or not all(isinstance(n, int) and not isinstance(n, bool) and 0 <= n < 2 ** 40
                           for n in shape)):
            raise ProtocolError(f"array {name!r}: bad shape {str(shape)[:64]}")
        dtype = ALLOWED_DTYPES[code]
        size = math.prod(shape) * dtype.itemsize
        if offset + size > len(payload):
            raise ProtocolError(f"array sizes do not match the payload: {name!r} needs "
                                f"{size} bytes at offset {offset}, payload has {len(payload)}")
        arrays[name] = np.frombuffer(payload, dtype, math.prod(shape), offset).reshape(shape)
        offset += size
    if offset != len(payload):
        raise ProtocolError(f"array sizes do not match the payload: arrays take {offset} bytes, "
                            f"payload has {len(payload)}")
    return arrays


def _check_header(head, limits: Limits, allowed) -> tuple:
    """(type, JSON length, payload length) of a header, checked before anything else is read."""
    magic, version, type_code, json_length, payload_length = HEADER.unpack(head)
    if magic != MAGIC:
        raise ProtocolError(f"not a KD Trace message (magic {bytes(magic)!r}, expected {MAGIC!r})")
    if version != PROTOCOL_VERSION:
        raise VersionMismatch(version)
    try:
        msg_type = MsgType(type_code)
    except ValueError:
        raise ProtocolError(f"unknown message type {type_code}") from None
    if allowed is not None and msg_type not in allowed:
        raise ProtocolError(f"unexpected message type {msg_type.name}")
    if json_length > limits.json_limit(msg_type):
        raise ProtocolError(f"{msg_type.name} JSON of {json_length} bytes exceeds the limit of "
                            f"{limits.json_limit(msg_type)}")
    if payload_length > limits.payload_limit(msg_type):
        raise ProtocolError(f"{msg_type.name} payload of {payload_length} bytes exceeds the limit "
                            f"of {limits.payload_limit(msg_type)}")
    return msg_type, json_length, payload_length


_JSON_DECODER = json.JSONDecoder(parse_constant=_reject_constant)


def _parse_body(msg_type: MsgType, text, payload) -> Message:
    try:
        header = _JSON_DECODER.decode(str(text, "utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise ProtocolError(f"{msg_type.name}: invalid JSON ({exc})") from None
    if not isinstance(header, dict):
        raise ProtocolError(f"{msg_type.name}: JSON is not an object")
    arrays = _parse_arrays(header.pop("arrays", []), payload)
    return Message(msg_type, header, arrays)


def recv_message(sock: socket.socket, limits: Limits = DEFAULT_LIMITS,
                 allowed: frozenset | None = None) -> Message:
    """Receive and validate one unauthenticated message from a plain blocking socket, without
    deadlines (tests, tools); raise ProtocolError (ConnectionClosed on a clean EOF)."""
    head = _recv_exactly(sock, HEADER.size, "header", allow_eof=True)
    msg_type, json_length, payload_length = _check_header(head, limits, allowed)
    text = _recv_exactly(sock, json_length, "JSON")
    payload = _recv_exactly(sock, payload_length, "payload")
    return _parse_body(msg_type, text, payload)


# ----------------------------------------------------------------------------- channels

def end_writing(sock: socket.socket) -> None:
    """End our direction of the stream, so that the peer reads our last message and then the
    end. Only on a plain socket: over TLS, a TCP half-close without TLS's close_notify is an
    unexpected end that OpenSSL treats as fatal (the peer could not answer any more), and
    Python's ssl sends close_notify only by waiting for the peer's. A TLS connection is
    closed whole instead, after its peer has closed (Channel.drain) or a moment has passed."""
    if not isinstance(sock, ssl.SSLSocket):
        socket.socket.shutdown(sock, socket.SHUT_WR)


def _wait(sock: socket.socket, for_write: bool, timeout: float) -> bool:
    """Whether `sock` became readable (writable) within `timeout` seconds; OSError once another
    thread has closed it (eviction, the server closing)."""
    if sock.fileno() < 0:
        raise OSError(9, "the connection was closed")
    if hasattr(select, "poll"):
        poller = select.poll()
        poller.register(sock, select.POLLOUT if for_write else select.POLLIN)
        return bool(poller.poll(timeout * 1000))
    wanted = ([], [sock], []) if for_write else ([sock], [], [])
    return any(select.select(*wanted, timeout))


def transfer_deadline(nbytes: int, grace_s: float = SILENCE_S) -> float:
    """Seconds a message of `nbytes` may take to arrive or leave: the grace, then MIN_RATE_BPS."""
    return grace_s + nbytes / MIN_RATE_BPS


class _Incoming:
    """The message being received, once its header is in: its type and length, and, for a
    message too large for the channel's buffer, the rest of it in a buffer of its own."""

    def __init__(self, started: float, msg_type: MsgType, json_length: int, payload_length: int):
        self.started = started          # its first byte
        self.msg_type = msg_type
        self.sizes = (json_length, payload_length)
        self.total = HEADER.size + json_length + payload_length
        self.own: bytearray | None = None   # the bytes after the header, if not in the buffer
        self.head = b""                 # the header's bytes then
        self.filled = 0                 # of them so far
        self.in_place = False           # own preallocated (else grown as data arrives)

    def take_own(self, first) -> None:
        """Receive the rest in a buffer of its own, starting with `first` (bytes after the
        header already read): preallocated up to PREALLOCATE_BYTES, beyond that grown as
        data arrives, so that a lying length costs nothing until bytes really come."""
        rest = self.total - HEADER.size
        self.in_place = rest <= PREALLOCATE_BYTES
        self.own = bytearray(rest) if self.in_place else bytearray()
        self.add(first)

    def add(self, piece) -> None:
        if self.in_place:
            self.own[self.filled:self.filled + len(piece)] = piece
        else:
            self.own += piece
        self.filled += len(piece)

    def where(self, received: int) -> str:
        """Which part `received` bytes of the message end in, for errors."""
        offset = received - HEADER.size
        for what, size in zip(("JSON", "payload"), self.sizes):
            if offset < size:
                return f"{what}: {offset} of {size} bytes"
            offset -= size
        return f"{received} of {self.total} bytes"


class Channel:
    """One peer connection, for one sending thread at a time (sends are locked) and one
    receiving thread. `role` is this side ("master" or "slave"). `grace_s`: how long a message
    may be silent before it must flow at MIN_RATE_BPS on average.

    Over TLS (an ssl.SSLSocket) the socket is non-blocking and every TLS call holds one lock:
    OpenSSL does not allow one connection's reads and writes on two threads at once, and the
    slave reads on one thread while it sends on another. Nobody waits while holding it: a
    thread waits for the socket (poll) first, then reads or writes what is there."""

    def __init__(self, sock: socket.socket, role: str, grace_s: float = SILENCE_S,
                 budget=None):
        """`budget` (the slave's: slave.server.UploadBudget): a message larger than the
        channel's buffer takes its length from it (take(n), which may refuse with
        ProtocolError) when its header is in, and gives it back (give(n)) at the next
        receive or at close."""
        self.sock, self.role, self.grace_s = sock, role, grace_s
        self.budget, self._budgeted = budget, 0
        self._budget_lock = threading.Lock()     # the receiver gives back, or close()
        self.tls = isinstance(sock, ssl.SSLSocket)
        self._tls_lock = threading.Lock()
        # Blocked calls wake up to look at their deadline; a TLS socket never blocks.
        sock.settimeout(0.0 if self.tls else POLL_S)
        # Received bytes not yet parsed: _buffer[_start:_end]. One buffer per channel, reused
        # message after message (messages up to RECV_KEEP_BYTES are received and parsed in
        # it; larger ones go to a buffer of their own, _Incoming.own).
        self._buffer = bytearray(RECV_BUFFER_BYTES)
        self._start = self._end = 0
        self._began: float | None = None          # the first byte of a message with no header yet
        self._incoming: _Incoming | None = None   # the message under way, its header in
        self._rcvlowat = 1
        self._send_lock = threading.RLock()   # re-entered by sends inside batch()
        self._batch: list | None = None        # buffers of a batch() under way
        self.last_sent = self.last_received = time.monotonic()
        self.bytes_sent = 0     # every byte this side has written to the socket
        self.closed = False

    # -- sending

    def send(self, msg_type: MsgType, header: dict | None = None, arrays: dict | None = None) -> None:
        self.send_encoded(encode_message(msg_type, header, arrays))

    def send_encoded(self, buffers: list) -> None:
        """Send a message as encode_message returned it (one encoding for many peers: the
        master's FRAME_START)."""
        with self._send_lock:
            self._send_locked(buffers)

    def send_bytes(self, data: bytes) -> None:
        """Raw bytes, as they are (tests of peers that misbehave)."""
        with self._send_lock:
            self._write([data])

    def try_send(self, msg_type: MsgType, header: dict | None = None) -> bool:
        """Send unless another send is under way (then bytes are flowing anyway): heartbeats."""
        if not self._send_lock.acquire(blocking=False):
            return False
        try:
            self._send_locked(encode_message(msg_type, header))
        finally:
            self._send_lock.release()
        return True

    @contextlib.contextmanager
    def batch(self):
        """The messages this thread sends inside go out together in one write at the end (one
        system call and one push instead of one each: a frame's start on many slaves)."""
        with self._send_lock:
            self._batch = []
            try:
                yield
            finally:
                buffers, self._batch = self._batch, None
                self._write(buffers)

    def _send_locked(self, buffers: list) -> None:
        if self._batch is not None:
            self._batch += buffers
        else:
            self._write(buffers)

    def _write(self, buffers: list) -> None:
        total = sum(len(b) for b in buffers)
        started, sent = time.monotonic(), 0
        for buffer in _coalesce(buffers):
            view = memoryview(buffer).cast("B")
            while len(view):
                count = self._send_some(view[:1 << 20])
                view, sent = view[count:], sent + count
                self.bytes_sent += count
                if len(view):
                    self._check_rate(started, sent, total, "sent", "the peer stopped reading")
        self.last_sent = time.monotonic()

    def _send_some(self, view) -> int:
        """Bytes of `view` written now (0 after waiting POLL_S for room)."""
        if not self.tls:
            try:
                return self.sock.send(view)
            except socket.timeout:
                return 0
        with self._tls_lock:
            try:
                # OpenSSL (no partial writes) sends all of `view` or asks to be called again
                # with the same bytes, which the caller does.
                return self.sock.send(view)
            except (ssl.SSLWantWriteError, ssl.SSLWantReadError):
                pass
        _wait(self.sock, True, POLL_S)
        return 0

    def _check_rate(self, started, done, total, verb, what) -> None:
        elapsed = time.monotonic() - started
        if elapsed > self.grace_s and done < (elapsed - self.grace_s) * MIN_RATE_BPS:
            raise PeerTooSlow(f"{what}: {done} of {total} bytes {verb} after {elapsed:.1f} s")

    # -- receiving
    #
    # One code path serves a thread that blocks in recv() (the slave, the handshakes) and the
    # master's single receiving thread, which reads what a readable socket holds
    # (recv_available) and checks the deadline of a message under way (incoming_due). Bytes
    # are read into the channel's buffer, as many as are there (several messages, or the
    # start of the next, in one system call), and messages are parsed where they lie.

    def recv(self, limits: Limits = DEFAULT_LIMITS, allowed: frozenset | None = None,
             wait: float | None = None, deadline: float | None = None) -> Message | None:
        """The next message, validated; None if none began within `wait` seconds (None: wait
        as long as it takes). Once a message begins it must arrive within its transfer
        deadline, and before the absolute `deadline` (time.monotonic()) if given.
        ProtocolError on anything else. Its arrays are its own."""
        self._give_budget()         # the message before is handled
        waited_from = time.monotonic()
        while True:
            msg = self._parse(limits, allowed, borrow=False)
            if msg is not None:
                self._low_water(self._wake_bytes())
                return msg
            if self._start == self._end and self._incoming is None:  # nothing owed yet
                if deadline is not None and time.monotonic() > deadline:
                    raise PeerTooSlow("nothing arrived before the deadline")
            else:
                self.check_incoming(deadline)
            try:
                self._fill()
            except socket.timeout:
                if (self._start == self._end and self._incoming is None and wait is not None
                        and time.monotonic() - waited_from >= wait):
                    return None

    def recv_available(self, limits: Limits = DEFAULT_LIMITS,
                       allowed: frozenset | None = None) -> list:
        """The messages that what the socket holds now completes (one read: call it when the
        socket is readable, e.g. from a selector); [] if none is complete yet. Their arrays
        are views of the channel's buffer, valid until the next receive on this channel:
        handle (or copy) them first. Afterwards the socket signals readable again only when
        the next read can make progress (see _low_water). Deadlines: see incoming_due."""
        try:
            self._fill(wait=0.0)    # the socket is readable: never wait here
        except socket.timeout:      # woken for nothing
            pass
        messages = []
        while (msg := self._parse(limits, allowed, borrow=True)) is not None:
            messages.append(msg)
        self._low_water(self._wake_bytes())
        return messages

    def has_pending(self) -> bool:
        """Bytes wait inside TLS, decrypted: a selector does not see them (the socket is not
        readable for them), so whoever reads by selector reads again at once."""
        if not self.tls:
            return False
        with self._tls_lock:
            try:
                return self.sock.pending() > 0
            except (ValueError, OSError):     # closed
                return False

    def _received(self) -> int:
        """Bytes of the message under way so far."""
        incoming = self._incoming
        if incoming is not None and incoming.own is not None:
            return HEADER.size + incoming.filled
        return self._end - self._start

    def incoming_due(self) -> float | None:
        """When the message under way arrives too slowly (time.monotonic()) unless more of it
        comes first; None when none is under way."""
        incoming = self._incoming
        started = self._began if incoming is None else incoming.started
        if started is None:
            return None
        return started + self.grace_s + self._received() / MIN_RATE_BPS

    def check_incoming(self, deadline: float | None = None) -> None:
        """PeerTooSlow if the message under way is past its transfer deadline (or `deadline`)."""
        incoming = self._incoming
        started = self._began if incoming is None else incoming.started
        if started is None:
            return
        received = self._received()
        total = HEADER.size if incoming is None else incoming.total
        if deadline is not None and time.monotonic() > deadline:
            where = f"header: {received} of {total} bytes" if incoming is None else incoming.where(received)
            raise PeerTooSlow(f"message not complete before the deadline ({where})")
        self._check_rate(started, received, total, "received", "message arrived too slowly")

    def _parse(self, limits: Limits, allowed, borrow: bool) -> Message | None:
        """The next message if its bytes are all in, else None (what is there waits)."""
        incoming = self._incoming
        if incoming is None:
            have = self._end - self._start
            if have < HEADER.size:
                if have == 0:
                    self._start = self._end = 0     # all parsed: the buffer is free again
                elif self._began is None:
                    self._began = time.monotonic()
                return None
            # The header: checked before anything else is read.
            msg_type, json_length, payload_length = _check_header(
                memoryview(self._buffer)[self._start:self._start + HEADER.size], limits, allowed)
            incoming = self._incoming = _Incoming(
                self._began or time.monotonic(), msg_type, json_length, payload_length)
            self._began = None
            if incoming.total > RECV_KEEP_BYTES:
                if self.budget is not None:
                    self._give_budget()
                    self.budget.take(incoming.total)
                    with self._budget_lock:
                        self._budgeted = incoming.total
                    if self.closed:         # closed meanwhile: nobody gives it back else
                        self._give_budget()
                # (the buffer, at most RECV_KEEP_BYTES, holds nothing beyond this message)
                with memoryview(self._buffer) as view:
                    incoming.head = bytes(view[self._start:self._start + HEADER.size])
                    incoming.take_own(view[self._start + HEADER.size:self._end])
                self._start = self._end = 0
        if incoming.own is not None:
            if incoming.filled < incoming.total - HEADER.size:
                return None
            body, head = memoryview(incoming.own), incoming.head
            borrow = True            # its own buffer: nobody else's to share
        else:
            if self._end - self._start < incoming.total:
                return None
            start = self._start
            self._start += incoming.total
            with memoryview(self._buffer) as view:
                head = view[start:start + HEADER.size]
                body = view[start + HEADER.size:start + incoming.total]
                if not borrow:
                    body = memoryview(bytearray(body))
        self._incoming = None
        return self._finish(incoming, head, body)

    def _make_room(self, total: int) -> None:
        """The buffer holds the message of `total` bytes that starts at _start: the bytes
        still to parse move to its front, into a larger buffer where it is too small. Only
        at a read (_fill): messages parsed before it were lent views of the buffer until
        then, and moving bytes in place would overwrite them."""
        if self._start + total <= len(self._buffer):
            return
        have = self._end - self._start
        if total > len(self._buffer):
            fresh = bytearray(total)
            fresh[:have] = memoryview(self._buffer)[self._start:self._end]
            self._buffer = fresh
        else:
            self._buffer[:have] = memoryview(self._buffer)[self._start:self._end]
        self._start, self._end = 0, have

    def _finish(self, incoming: _Incoming, head, body) -> Message:
        json_length, payload_length = incoming.sizes
        text = body[:json_length]
        payload = body[json_length:json_length + payload_length]
        self.last_received = time.monotonic()
        return _parse_body(incoming.msg_type, text, payload)

    def _wake_bytes(self) -> int:
        """What the next read waits for: once the header is in, the rest of the message (up to
        LOW_WATER_BYTES), so that a tile arriving over a slow link wakes the reader once or
        twice, not for every segment; before, any byte."""
        incoming = self._incoming
        if incoming is None:
            return 1
        return max(1, min(incoming.total - self._received(), LOW_WATER_BYTES))

    def _fill(self, wait: float = POLL_S) -> None:
        """One read from the socket: into the channel's buffer, as much as it has room for
        (made room for the rest of the message under way first), or into the message's
        own buffer (at most its rest: bytes after it go to the channel's buffer on the next
        read). socket.timeout when nothing came. Over TLS a read returns one record (16 KiB
        at most): then it reads on what has arrived, as long as there is room, so that a tile
        wakes its reader once or twice and not once a record."""
        self._low_water(self._wake_bytes())
        if self._read_once(wait, make_room=True) == 0:
            incoming = self._incoming
            if incoming is None and self._start == self._end:
                raise ConnectionClosed("connection closed by peer")
            where = (f"header: {self._received()} of {HEADER.size} bytes" if incoming is None
                     else incoming.where(self._received()))
            raise ConnectionBroken(f"connection closed in the middle of a message ({where})")
        while self.tls and self._room() >= TLS_RECORD_BYTES:
            try:
                if self._read_once(0.0, make_room=False) == 0:
                    return          # the end: the next read says so
            except socket.timeout:
                return

    def _room(self) -> int:
        """What the next read may take without making room."""
        incoming = self._incoming
        if incoming is not None and incoming.own is not None:
            return incoming.total - HEADER.size - incoming.filled
        return len(self._buffer) - self._end

    def _read_once(self, wait: float, make_room: bool) -> int:
        """One read where _fill says; the bytes it took."""
        incoming = self._incoming
        if incoming is not None and incoming.own is not None:
            rest = incoming.total - HEADER.size - incoming.filled
            if incoming.in_place:
                with memoryview(incoming.own) as view:
                    got = self._read(lambda: self.sock.recv_into(view[incoming.filled:],
                                                                 min(rest, 1 << 20)), wait)
                incoming.filled += got
            else:
                chunk = self._read(lambda: self.sock.recv(min(rest, 1 << 20)), wait)
                got = len(chunk)
                incoming.add(chunk)
            return got
        if make_room:
            # Room for the rest of the message under way, or for a header after the bytes
            # still to parse.
            self._make_room(incoming.total if incoming is not None
                            else self._end - self._start + HEADER.size)
        with memoryview(self._buffer) as view:
            got = self._read(lambda: self.sock.recv_into(view[self._end:]), wait)
        self._end += got
        return got

    def _read(self, read, wait: float = POLL_S):
        """read() on the socket; socket.timeout when nothing came within `wait` s. Over TLS: wait
        for the socket (unless TLS holds decrypted bytes, or wait is 0: the caller knows it is
        readable), then read under the lock; a record not complete yet is also 'nothing
        came'."""
        if not self.tls:
            return read()
        if wait > 0:
            with self._tls_lock:
                ready = self.sock.pending() > 0
            if not ready and not _wait(self.sock, False, wait):
                raise socket.timeout("nothing to read")
        with self._tls_lock:
            try:
                return read()
            except (ssl.SSLWantReadError, ssl.SSLWantWriteError):
                raise socket.timeout("a TLS record is not complete yet") from None

    def _low_water(self, nbytes: int) -> None:
        """SO_RCVLOWAT: poll() (so a receive with a timeout, and a selector) wakes once this
        much is there, or at the end of the stream or the timeout. Over TLS, a record's worth
        less: TLS may hold the start of a record already (taken from the socket, not yet
        complete), and the kernel must not wait for bytes that never come; what is still to
        arrive is at least the rest of the message less that record."""
        if self.tls:
            nbytes = max(1, nbytes - TLS_RECORD_BYTES)
        if nbytes != self._rcvlowat and hasattr(socket, "SO_RCVLOWAT"):
            try:
                self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVLOWAT, nbytes)
                self._rcvlowat = nbytes
            except OSError:
                pass

    def drain(self, seconds: float) -> None:
        """Read and drop what the peer still sends, until it closes or `seconds` pass (so
        that closing does not reset a connection whose peer has not read our last words)."""
        deadline = time.monotonic() + seconds
        try:
            while time.monotonic() < deadline:
                try:
                    if not self._read(lambda: self.sock.recv(65536)):
                        return
                except socket.timeout:
                    pass
        except (OSError, ValueError):
            pass

    def _give_budget(self) -> None:
        with self._budget_lock:
            budgeted, self._budgeted = self._budgeted, 0
        if budgeted:
            self.budget.give(budgeted)

    def close(self) -> None:
        """Shut the connection down (wakes a thread blocked on it) and close it."""
        self.closed = True
        self._give_budget()
        try:
            socket.socket.shutdown(self.sock, socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()


# ----------------------------------------------------------------------------- field helpers

def get_int(header: dict, key: str, low: int = 0, high: int = 2 ** 63 - 1) -> int:
    value = header.get(key)
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ProtocolError(f"field {key!r} must be an integer in [{low}, {high}], got {value!r}")
    return value


def get_str(header: dict, key: str, max_length: int = 256) -> str:
    value = header.get(key)
    if not isinstance(value, str) or len(value) > max_length:
        raise ProtocolError(f"field {key!r} must be a string of at most {max_length} characters")
    return value


def get_float(header: dict, key: str) -> float:
    value = header.get(key)
    # Compared, not converted: an integer past float's range (JSON has them) is refused, not an
    # OverflowError; NaN and infinities fail the comparison.
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
            -sys.float_info.max <= value <= sys.float_info.max):
        raise ProtocolError(f"field {key!r} must be a finite number, got {repr(value)[:64]}")
    return float(value)


def check_scene_hash(value) -> str:
    if not isinstance(value, str) or len(value) != 32 or any(c not in "0123456789abcdef" for c in value):
        raise ProtocolError(f"bad scene hash {value!r}")
    return value


# ----------------------------------------------------------------------------- tile payloads
#
# A frame asks for the passes it needs (FRAME_START "passes": combined, plus the others only
# when the view layer shows them or the master denoises) in one payload:
#   f32  every pass float32 (exact);
#   f16  float16 but the "exact" passes (PASS_CODING), float32 (depth's miss value 1e10 does
#        not fit float16);
#   u8   an 8-bit preview: combined's colour and the colour passes as sRGB codes, its alpha and
#        the normals linear codes, the exact passes float32. Decoding is a table lookup, so a
#        decoded value is exactly the centre of its code (PREVIEW_* tables below): "exact to
#        its quantisation".
# With compression on, the slave deflates the passes (zlib level 1) and sends one u1 array
# "zlib" instead, but only when that saves at least 10 %; the master inflates it with a bound
# of exactly the expected size, so a "zip bomb" costs nothing. The master checks a tile (names,
# shapes, dtypes, finite values) before it writes it straight into the frame (decode_tile's
# `out`): no intermediate float32 copy per tile.

PAYLOADS = ("f32", "f16", "u8")
# The passes a frame asks for unless it says: the image, depth and normal (the others cost the
# slave work: only a frame that needs them asks).
ALL_PASSES = ("combined", "depth", "normal")
F16_MAX = 65504.0


def _srgb_to_linear(code: np.ndarray) -> np.ndarray:
    c = code / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


# The 8-bit preview's codes. Colour: code k decodes to PREVIEW_COLOR[k] = the linear value of
# sRGB k/255; a value encodes to the code whose sRGB interval holds it, found by comparison
# against float64 bounds (no transcendental on the slave, so every slave gives the same codes).
# Alpha and normal: linear codes, rounded in float64.
PREVIEW_COLOR = _srgb_to_linear(np.arange(256.0)).astype(np.float32)
PREVIEW_COLOR_BOUNDS = _srgb_to_linear(np.arange(255.0) + 0.5)          # code k below bound k
PREVIEW_ALPHA = (np.arange(256.0) / 255.0).astype(np.float32)
PREVIEW_NORMAL = (np.arange(256.0) / 127.5 - 1.0).astype(np.float32)
# combined's four channels in one lookup: code + 256 x channel indexes this table
_PREVIEW_RGBA = np.concatenate([PREVIEW_COLOR] * 3 + [PREVIEW_ALPHA])
_RGBA_OFFSETS = (np.arange(4) * 256).astype(np.uint16)


def check_passes(passes) -> tuple:
    """The passes a frame asks for, in wire order; combined is always one of them."""
    if (not isinstance(passes, (list, tuple)) or not all(isinstance(p, str) for p in passes)
            or not set(passes) <= set(TILE_PASSES) or len(set(passes)) != len(passes)
            or "combined" not in passes):
        raise ValueError(f"passes must be combined plus any of "
                         f"{', '.join(name for name in TILE_PASSES if name != 'combined')}, "
                         f"got {passes!r}")
    return tuple(name for name in TILE_PASSES if name in passes)


def pass_dtypes(payload: str, passes=ALL_PASSES) -> dict:
    """name -> wire dtype of each pass the frame asks for, in wire order."""
    if payload not in PAYLOADS:
        raise ValueError(f"payload must be one of {PAYLOADS}, got {payload!r}")
    return dict(_pass_dtypes(payload, check_passes(passes)))


@functools.lru_cache(maxsize=64)
def _checked_pass_dtypes(payload: str, passes: tuple) -> dict:
    # decode_tile's dtypes: checked once per frame format, not once per tile (read only)
    return pass_dtypes(payload, passes)


@functools.lru_cache(maxsize=64)
def _pass_dtypes(payload: str, passes: tuple) -> tuple:
    small = {"f32": "<f4", "f16": "<f2", "u8": "|u1"}[payload]
    return tuple((name, np.dtype("<f4" if PASS_CODING[name] == "exact" else small))
                 for name in passes)


def tile_bytes_per_pixel(payload: str, passes=ALL_PASSES) -> int:
    return sum(TILE_PASSES[name] * dtype.itemsize for name, dtype in pass_dtypes(payload, passes).items())


def _pass_shape(name: str, w: int, h: int) -> tuple:
    return (h, w) if TILE_PASSES[name] == 1 else (h, w, TILE_PASSES[name])


def _encode_pass(name: str, array: np.ndarray, dtype: np.dtype) -> np.ndarray:
    if dtype.kind == "f":
        if dtype.itemsize == 2:
            array = np.clip(array, -F16_MAX, F16_MAX)
        return np.ascontiguousarray(array, dtype)
    if PASS_CODING[name] == "direction":
        return np.rint((np.clip(array, -1.0, 1.0, dtype=np.float64) + 1.0) * 127.5).astype(np.uint8)
    if PASS_CODING[name] == "color":
        return np.searchsorted(PREVIEW_COLOR_BOUNDS, array, side="right").astype(np.uint8)
    codes = np.empty(array.shape, np.uint8)
    codes[..., :3] = np.searchsorted(PREVIEW_COLOR_BOUNDS, array[..., :3], side="right")
    codes[..., 3] = np.rint(np.clip(array[..., 3], 0.0, 1.0, dtype=np.float64) * 255.0)
    return codes


def encode_tile(passes: dict, payload: str = "f32", compress: bool = False,
                names=ALL_PASSES) -> tuple:
    """(header fields, arrays) of a TILE_RESULT carrying the passes `names` of the float32
    `passes` as `payload`."""
    arrays = {name: _encode_pass(name, np.asarray(passes[name], np.float32), dtype)
              for name, dtype in pass_dtypes(payload, names).items()}
    fields = {"payload": payload, "compression": "none"}
    if compress:
        raw = b"".join(memoryview(a).cast("B") for a in arrays.values())
        packed = zlib.compress(raw, 1)
        if len(packed) <= 0.9 * len(raw):
            fields["compression"] = "zlib"
            arrays = {"zlib": np.frombuffer(packed, np.uint8)}
    return fields, arrays


def _all_finite(array: np.ndarray) -> bool:
    # np.isfinite(...).all(): 2-3 x faster here than a float64 sum of the tile (measured on
    # 64- and 256-pixel float32 tiles), the master's largest cost per byte.
    return array.dtype.kind != "f" or bool(np.isfinite(array).all())


def decode_tile(header: dict, arrays: dict, w: int, h: int, payload: str, passes=ALL_PASSES,
                out: dict | None = None) -> dict:
    """Check a w x h TILE_RESULT sent with `payload` and `passes` and return its passes as
    float32; with `out` (name -> float32 array of the tile's shape, e.g. a window of the frame)
    write them there instead and return `out`. ProtocolError if anything is off (format, names,
    shapes, dtypes, sizes, NaN or infinity); nothing is written then."""
    if header.get("payload", "f32") != payload:
        raise ProtocolError(f"tile payload {header.get('payload')!r}, expected {payload!r}")
    try:
        dtypes = _checked_pass_dtypes(payload, tuple(passes))
    except TypeError:        # unhashable: not passes at all, pass_dtypes says why
        dtypes = pass_dtypes(payload, passes)
    compression = header.get("compression", "none")
    if compression == "zlib":
        packed = arrays.get("zlib")
        if set(arrays) != {"zlib"} or packed.dtype != np.uint8 or packed.ndim != 1:
            raise ProtocolError("a zlib tile must carry exactly one u1 array 'zlib'")
        expected = sum(math.prod(_pass_shape(n, w, h)) * d.itemsize for n, d in dtypes.items())
        inflater = zlib.decompressobj()
        try:
            raw = inflater.decompress(packed, expected)
        except zlib.error as exc:
            raise ProtocolError(f"tile does not inflate: {exc}") from None
        if len(raw) != expected or inflater.unconsumed_tail or not inflater.eof:
            raise ProtocolError("inflated tile has the wrong size")
        arrays, offset = {}, 0
        for name, dtype in dtypes.items():
            shape = _pass_shape(name, w, h)
            arrays[name] = np.frombuffer(raw, dtype, math.prod(shape), offset).reshape(shape)
            offset += math.prod(shape) * dtype.itemsize
    elif compression != "none":
        raise ProtocolError(f"unknown tile compression {compression!r}")
    if set(arrays) != set(dtypes):
        raise ProtocolError(f"tile passes must be {sorted(dtypes)}, got {sorted(arrays)}")
    for name, dtype in dtypes.items():
        shape, array = _pass_shape(name, w, h), arrays[name]
        if array.dtype != dtype or array.shape != shape:
            raise ProtocolError(f"pass {name!r} must be {dtype.str} {shape}, "
                                f"got {array.dtype.str} {array.shape}")
        if not _all_finite(array):
            raise ProtocolError(f"pass {name!r} contains NaN or infinity")
    if out is None:
        out = {name: np.empty(_pass_shape(name, w, h), np.float32) for name in dtypes}
    for name, dtype in dtypes.items():
        source, target = arrays[name], out[name]
        if dtype.kind == "f":
            np.copyto(target, source)
        elif PASS_CODING[name] == "direction":
            target[...] = PREVIEW_NORMAL.take(source)
        elif PASS_CODING[name] == "color":
            target[...] = PREVIEW_COLOR.take(source)
        else:
            codes = source.astype(np.uint16)
            codes += _RGBA_OFFSETS
            np.take(_PREVIEW_RGBA, codes, out=target, mode="clip")
    return out
