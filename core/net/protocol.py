"""The wire protocol between the master and the slaves.

A message is a fixed header `!4sHHIQ` (magic b"KDTR", protocol version, message type, JSON
length, payload length), a UTF-8 JSON object, then the payload: raw little-endian arrays listed
in the JSON under "arrays": [{"name", "dtype", "shape"}], concatenated in that order.

Nothing received is unpickled or evaluated: the JSON is parsed with the json module, arrays are
built with numpy.frombuffer from an allow-listed set of dtypes, and every length is checked
against a per-type limit *before* anything is allocated. See docs/protocol.md.

Here: the message types, the header, the versions, the limits, the encoding and the checks of
a message (send_message and recv_message on a plain socket, for tests and tools), the field
helpers and the passes and payloads a frame may ask for. Peers talk through a `Channel`
(core/net/channel.py: every message with a deadline); a tile's passes are encoded and checked
in core/net/tile_payloads.py. After the plaintext OPEN exchange (versions) the channel runs
over TLS 1.3 with both identities pinned (core/net/secure.py, core/net/identity.py): TLS
encrypts and authenticates every byte, so the messages carry no MACs of their own.
"""
from __future__ import annotations

import enum
import functools
import json
import math
import socket
import struct
import sys
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
# SILENCE_S plus its size at channel.MIN_RATE_BPS: a stalled or dribbling peer cannot hold a thread.
HEARTBEAT_S = 2.0
HEARTBEAT_RANGE_S = (0.05, 30.0)
SILENCE_S = 10.0
# A slave closes a master connection that has no work there and says nothing for IDLE_S (its
# slot goes back); a master in a frame that has nothing left for a slave (its last tiles are
# elsewhere) sends HEARTBEAT when it has sent nothing for KEEPALIVE_S.
IDLE_S = 300.0
KEEPALIVE_S = 30.0
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


def coalesce(buffers: list) -> list:
    # Small messages go out in one write: several small writes meet Nagle's algorithm and
    # delayed ACKs (40 ms stalls).
    if len(buffers) > 1 and sum(len(b) for b in buffers) <= 1 << 20:
        return [b"".join(buffers)]
    return buffers


def send_message(sock: socket.socket, msg_type: MsgType, header: dict | None = None,
                 arrays: dict | None = None) -> None:
    """Send one message on a plain blocking socket, unauthenticated (tests, tools); peers talk
    through a Channel."""
    for buffer in coalesce(encode_message(msg_type, header, arrays)):
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


def check_header(head, limits: Limits, allowed) -> tuple:
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


def parse_body(msg_type: MsgType, text, payload) -> Message:
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
    msg_type, json_length, payload_length = check_header(head, limits, allowed)
    text = _recv_exactly(sock, json_length, "JSON")
    payload = _recv_exactly(sock, payload_length, "payload")
    return parse_body(msg_type, text, payload)


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


# ----------------------------------------------------------------------------- a frame's passes
#
# A frame asks for the passes it needs (FRAME_START "passes": combined, plus the others only
# when the view layer shows them or the master denoises) in one payload of PAYLOADS; how each
# payload codes a pass, and the encoding and check of a tile: tile_payloads.py.

PAYLOADS = ("f32", "f16", "u8")
# The passes a frame asks for unless it says: the image, depth and normal (the others cost the
# slave work: only a frame that needs them asks).
ALL_PASSES = ("combined", "depth", "normal")


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
def _pass_dtypes(payload: str, passes: tuple) -> tuple:
    small = {"f32": "<f4", "f16": "<f2", "u8": "|u1"}[payload]
    return tuple((name, np.dtype("<f4" if PASS_CODING[name] == "exact" else small))
                 for name in passes)


def tile_bytes_per_pixel(payload: str, passes=ALL_PASSES) -> int:
    return sum(TILE_PASSES[name] * dtype.itemsize for name, dtype in pass_dtypes(payload, passes).items())
