"""The wire protocol between the master and the slaves.

A message is a fixed header `!4sHHIQ` (magic b"KDTR", protocol version, message type, JSON
length, payload length), a UTF-8 JSON object, then the payload: raw little-endian arrays listed
in the JSON under "arrays": [{"name", "dtype", "shape"}], concatenated in that order.

Nothing received is unpickled or evaluated: the JSON is parsed with the json module, arrays are
built with numpy.frombuffer from an allow-listed set of dtypes, and every length is checked
against a per-type limit *before* anything is allocated. See docs/protocol.md.
"""
from __future__ import annotations

import enum
import hashlib
import hmac
import json
import math
import os
import secrets
import socket
import struct
import zlib
from dataclasses import dataclass, field

import numpy as np


PROTOCOL_VERSION = 3   # 2: HMAC handshake, float16/zlib tiles, N x M tiles; 3: compact kd-tree arrays
MAGIC = b"KDTR"
HEADER = struct.Struct("!4sHHIQ")
DEFAULT_PORT = 47600
SERVICE_TYPE = "_kdtrace._tcp.local."

# Only these dtypes may appear on the wire; all little-endian.
ALLOWED_DTYPES = {name: np.dtype("<" + name) for name in ("f4", "f2", "u4", "u2", "u1", "i4")}
MAX_ARRAYS = 16
MAX_DIMS = 4
MAX_TILE_SIZE = 1024
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
    CHALLENGE = 12     # slave -> master: slave nonce + the slave's proof (only with a shared secret)
    AUTH = 13          # master -> slave: the master's proof; WELCOME follows if it is right


MASTER_TO_SLAVE = frozenset({MsgType.HELLO, MsgType.SCENE_QUERY, MsgType.SCENE_UPLOAD,
                             MsgType.FRAME_START, MsgType.TILE_REQUEST, MsgType.CANCEL,
                             MsgType.ERROR, MsgType.BYE, MsgType.AUTH})
SLAVE_TO_MASTER = frozenset({MsgType.WELCOME, MsgType.SCENE_READY, MsgType.TILE_RESULT,
                             MsgType.CANCEL, MsgType.ERROR, MsgType.CHALLENGE})

# Tile passes: name -> (channels, dtype); (h, w) or (h, w, channels).
TILE_PASSES = {"combined": 4, "depth": 1, "normal": 3}
TILE_BYTES_PER_PIXEL = 4 * sum(TILE_PASSES.values())

class ProtocolError(Exception):
    """The peer sent something that is not a valid message; the connection cannot go on."""


class ConnectionClosed(ProtocolError):
    """The peer closed the connection cleanly between two messages."""


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

    def json_limit(self, msg_type: MsgType) -> int:
        return self.max_frame_json if msg_type == MsgType.FRAME_START else self.max_json

    def payload_limit(self, msg_type: MsgType) -> int:
        if msg_type == MsgType.SCENE_UPLOAD:
            return self.max_scene_bytes
        if msg_type == MsgType.TILE_RESULT:
            return self.max_tile_pixels * TILE_BYTES_PER_PIXEL
        return 0  # control messages carry no arrays


DEFAULT_LIMITS = Limits()


@dataclass
class Message:
    type: MsgType
    header: dict
    arrays: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------- encoding

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
    text = json.dumps(header, separators=(",", ":"), allow_nan=False).encode("utf-8")
    payload_length = sum(len(b) for b in buffers)
    head = HEADER.pack(MAGIC, PROTOCOL_VERSION, int(msg_type), len(text), payload_length)
    return [head + text] + buffers


def send_message(sock: socket.socket, msg_type: MsgType, header: dict | None = None,
                 arrays: dict | None = None) -> None:
    """Send one message (the caller serialises senders on one socket). Small messages go out
    in one write: several small writes meet Nagle's algorithm and delayed ACKs (40 ms stalls)."""
    buffers = encode_message(msg_type, header, arrays)
    if len(buffers) > 1 and sum(len(b) for b in buffers) <= 1 << 20:
        buffers = [b"".join(buffers)]
    for buffer in buffers:
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
            raise ProtocolError(f"connection closed in the middle of a message ({what}: "
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
        if code not in ALLOWED_DTYPES:
            raise ProtocolError(f"array {name!r}: dtype {code!r} not allowed "
                                f"(allowed: {', '.join(ALLOWED_DTYPES)})")
        if (not isinstance(shape, list) or len(shape) > MAX_DIMS
                or not all(isinstance(n, int) and not isinstance(n, bool) and 0 <= n < 2 ** 40
                           for n in shape)):
            raise ProtocolError(f"array {name!r}: bad shape {shape!r}")
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


def recv_message(sock: socket.socket, limits: Limits = DEFAULT_LIMITS,
                 allowed: frozenset | None = None) -> Message:
    """Receive and validate one message; raise ProtocolError (ConnectionClosed on a clean EOF)."""
    head = _recv_exactly(sock, HEADER.size, "header", allow_eof=True)
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
    text = _recv_exactly(sock, json_length, "JSON")
    try:
        header = json.loads(text.decode("utf-8"), parse_constant=_reject_constant)
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise ProtocolError(f"{msg_type.name}: invalid JSON ({exc})") from None
    if not isinstance(header, dict):
        raise ProtocolError(f"{msg_type.name}: JSON is not an object")
    payload = _recv_exactly(sock, payload_length, "payload")
    arrays = _parse_arrays(header.pop("arrays", []), payload)
    return Message(msg_type, header, arrays)


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
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ProtocolError(f"field {key!r} must be a finite number, got {value!r}")
    return float(value)


def check_scene_hash(value) -> str:
    if not isinstance(value, str) or len(value) != 32 or any(c not in "0123456789abcdef" for c in value):
        raise ProtocolError(f"bad scene hash {value!r}")
    return value


# ----------------------------------------------------------------------------- tile payloads
#
# A TILE_RESULT carries the passes as float32 (default) or, with payload "f16", combined and
# normal as float16 (depth stays float32: its miss value 1e10 and far distances do not fit
# float16). With compression on, the slave deflates the passes (zlib level 1) and sends one u1
# array "zlib" instead, but only when that saves at least 10 %; the master inflates it with a
# bound of exactly the expected size, so a "zip bomb" costs nothing.

PAYLOADS = ("f32", "f16")
F16_PASSES = ("combined", "normal")
F16_MAX = 65504.0


def pass_dtypes(payload: str) -> dict:
    if payload not in PAYLOADS:
        raise ValueError(f"payload must be one of {PAYLOADS}, got {payload!r}")
    return {name: np.dtype("<f2") if payload == "f16" and name in F16_PASSES else np.dtype("<f4")
            for name in TILE_PASSES}


def _pass_shape(name: str, w: int, h: int) -> tuple:
    return (h, w) if TILE_PASSES[name] == 1 else (h, w, TILE_PASSES[name])


def encode_tile(passes: dict, payload: str = "f32", compress: bool = False) -> tuple:
    """(header fields, arrays) of a TILE_RESULT for float32 `passes`."""
    dtypes = pass_dtypes(payload)
    arrays = {}
    for name, dtype in dtypes.items():
        array = np.asarray(passes[name], np.float32)
        if dtype.itemsize == 2:
            array = np.clip(array, -F16_MAX, F16_MAX)
        arrays[name] = np.ascontiguousarray(array, dtype)
    fields = {"payload": payload, "compression": "none"}
    if compress:
        raw = b"".join(a.tobytes() for a in arrays.values())
        packed = zlib.compress(raw, 1)
        if len(packed) <= 0.9 * len(raw):
            fields["compression"] = "zlib"
            arrays = {"zlib": np.frombuffer(packed, np.uint8)}
    return fields, arrays


def decode_tile(header: dict, arrays: dict, w: int, h: int, payload: str) -> dict:
    """The float32 passes of a w x h TILE_RESULT sent with `payload`; ProtocolError if anything
    is off (format, names, shapes, dtypes, sizes, NaN or infinity)."""
    if header.get("payload", "f32") != payload:
        raise ProtocolError(f"tile payload {header.get('payload')!r}, expected {payload!r}")
    dtypes = pass_dtypes(payload)
    compression = header.get("compression", "none")
    if compression == "zlib":
        packed = arrays.get("zlib")
        if set(arrays) != {"zlib"} or packed.dtype != np.uint8 or packed.ndim != 1:
            raise ProtocolError("a zlib tile must carry exactly one u1 array 'zlib'")
        expected = sum(math.prod(_pass_shape(n, w, h)) * d.itemsize for n, d in dtypes.items())
        inflater = zlib.decompressobj()
        try:
            raw = inflater.decompress(packed.tobytes(), expected)
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
    if set(arrays) != set(TILE_PASSES):
        raise ProtocolError(f"tile passes must be {sorted(TILE_PASSES)}, got {sorted(arrays)}")
    passes = {}
    for name, dtype in dtypes.items():
        shape, array = _pass_shape(name, w, h), arrays[name]
        if array.dtype != dtype or array.shape != shape:
            raise ProtocolError(f"pass {name!r} must be {dtype.str} {shape}, "
                                f"got {array.dtype.str} {array.shape}")
        array = array.astype(np.float32)
        if not np.isfinite(array).all():
            raise ProtocolError(f"pass {name!r} contains NaN or infinity")
        passes[name] = array
    return passes


# ----------------------------------------------------------------------------- authentication
#
# With a shared secret the handshake is a mutual HMAC-SHA256 challenge-response:
#   HELLO(nonce_m) -> CHALLENGE(nonce_s, proof_s) -> AUTH(proof_m) -> WELCOME
# proof_s = HMAC(secret, "kdtrace-slave" | nonce_m | nonce_s), proof_m the same with
# "kdtrace-master". Different labels keep one side's proof from being replayed as the other's;
# fresh nonces on both sides keep old proofs useless. The secret never travels.

SECRET_ENV = "KDTRACE_SECRET"
NONCE_HEX = 64      # 32 random bytes
PROOF_HEX = 64      # SHA-256


class AuthError(Exception):
    """A secret could not be read, or a proof was wrong."""


def load_secret(secret_file: str | None = None, env: str = SECRET_ENV) -> bytes | None:
    """The shared secret: the file's contents (stripped) if a file is given, else the environment
    variable, else None (no authentication). An empty secret is an error, not 'no secret'."""
    if secret_file:
        try:
            with open(secret_file, "rb") as handle:
                data = handle.read(65536).strip()
        except OSError as exc:
            raise AuthError(f"cannot read secret file {secret_file}: {exc.strerror or exc}") from None
        if not data:
            raise AuthError(f"secret file {secret_file} is empty")
        return data
    value = os.environ.get(env)
    if value is None:
        return None
    if not value.strip():
        raise AuthError(f"environment variable {env} is set but empty")
    return value.strip().encode("utf-8")


def new_nonce() -> str:
    return secrets.token_hex(NONCE_HEX // 2)


def check_hex(value, length: int, what: str) -> str:
    if not isinstance(value, str) or len(value) != length or any(c not in "0123456789abcdef" for c in value):
        raise ProtocolError(f"bad {what}")
    return value


def auth_proof(secret: bytes, role: str, master_nonce: str, slave_nonce: str) -> str:
    label = {"slave": b"kdtrace-slave", "master": b"kdtrace-master"}[role]
    message = b"|".join((label, master_nonce.encode(), slave_nonce.encode()))
    return hmac.new(secret, message, hashlib.sha256).hexdigest()


def proof_ok(secret: bytes, role: str, master_nonce: str, slave_nonce: str, proof) -> bool:
    if not isinstance(proof, str) or len(proof) != PROOF_HEX:
        return False
    return hmac.compare_digest(auth_proof(secret, role, master_nonce, slave_nonce), proof)
