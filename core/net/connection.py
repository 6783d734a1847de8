"""A connection to one slave: its socket and protocol channel, the handshake (with the shared
secret's challenge-response), and the errors a user reads when a slave cannot be used. The
master's frame loop reads a connection while a frame runs, its other threads between frames
(connecting, uploading a scene)."""
from __future__ import annotations

import socket
import time

from . import protocol
from .protocol import MsgType, ProtocolError
from ..scene.model import SCENE_FORMAT_VERSION


class MasterError(Exception):
    """Something the user should read: an unreachable slave, a refused handshake, no slaves."""


class SlaveBusy(MasterError):
    """The slave serves as many masters as it can; worth trying again later."""


class SlaveConnection:
    """A connected, handshaken slave. Sends are serialised by the channel; one thread receives."""

    def __init__(self, host: str, port: int, channel: protocol.Channel, welcome: dict):
        self.host, self.port, self.channel = host, port, channel
        self.name = protocol.get_str(welcome, "name", 64)
        self.id = protocol.get_str(welcome, "id", 64)
        self.device = protocol.get_str(welcome, "device", 256)
        self.compute_units = protocol.get_int(welcome, "compute_units")
        self.memory = protocol.get_int(welcome, "memory")
        self.scene_hash: str | None = None   # the scene this master made present there
        self.closed = False

    @property
    def endpoint(self) -> tuple:
        return (self.host, self.port)

    @property
    def label(self) -> str:
        return f"{self.name} ({self.host}:{self.port})"

    def send(self, msg_type: MsgType, header: dict | None = None, arrays: dict | None = None) -> None:
        self.channel.send(msg_type, header, arrays)

    def recv(self, limits: protocol.Limits = protocol.DEFAULT_LIMITS,
             wait: float | None = None) -> protocol.Message | None:
        """The next message (None if none began within `wait` s), whole-message deadline."""
        return self.channel.recv(limits, protocol.SLAVE_TO_MASTER, wait=wait)

    def close(self, say_bye: bool = False) -> None:
        if self.closed:
            return
        self.closed = True
        if say_bye:
            try:
                self.send(MsgType.BYE)
            except (OSError, ProtocolError):
                pass
        self.channel.close()


def _reason(exc: OSError) -> str:
    if isinstance(exc, ConnectionRefusedError):
        return "connection refused"
    if isinstance(exc, socket.timeout):
        return "timed out"
    return exc.strerror or str(exc) or type(exc).__name__


def _handshake(channel: protocol.Channel, host: str, port: int, master_name: str,
               secret: bytes | None, heartbeat_s: float, deadline: float) -> dict:
    """HELLO, the HMAC challenge-response when the slave asks for it, WELCOME; returns the
    WELCOME header. MasterError names what went wrong (SlaveBusy for a slave at capacity)."""
    nonce = protocol.new_nonce()
    channel.send(MsgType.HELLO, {
        "protocol_version": protocol.PROTOCOL_VERSION,
        "scene_format_version": SCENE_FORMAT_VERSION, "name": master_name, "nonce": nonce,
        "heartbeat_s": heartbeat_s})
    expect = {MsgType.WELCOME, MsgType.ERROR, MsgType.CHALLENGE}
    reply = channel.recv(protocol.DEFAULT_LIMITS, expect, deadline=deadline)
    if reply.type == MsgType.CHALLENGE:
        if secret is None:
            raise MasterError(f"slave {host}:{port} requires a shared secret and this master has "
                              f"none (set {protocol.SECRET_ENV} or a secret file)")
        slave_nonce = protocol.check_hex(reply.header.get("nonce"), protocol.NONCE_HEX, "slave nonce")
        if not protocol.proof_ok(secret, "slave", nonce, slave_nonce, reply.header.get("proof")):
            raise MasterError(f"slave {host}:{port} failed authentication "
                              f"(its shared secret differs from the master's)")
        channel.send(MsgType.AUTH, {"proof": protocol.auth_proof(secret, "master", nonce, slave_nonce)})
        # From here on every message carries a MAC; only a refusal may come without one.
        channel.authenticate(protocol.session_key(secret, nonce, slave_nonce))
        reply = channel.recv(protocol.DEFAULT_LIMITS, {MsgType.WELCOME, MsgType.ERROR},
                             deadline=deadline, unauthenticated=frozenset({MsgType.ERROR}))
    elif reply.type == MsgType.WELCOME and secret is not None:
        raise MasterError(f"slave {host}:{port} does not authenticate (no shared secret "
                          f"configured on the slave); refused")
    if reply.type == MsgType.ERROR:
        message = protocol.get_str(reply.header, "message", 4096)
        if reply.header.get("busy") is True:
            raise SlaveBusy(f"slave {host}:{port} is busy: {message}")
        raise MasterError(f"slave {host}:{port} refused the connection: {message}")
    theirs = reply.header.get("scene_format_version")
    if theirs != SCENE_FORMAT_VERSION:
        raise MasterError(f"slave {host}:{port}: scene format version mismatch: slave uses "
                          f"version {theirs}, master uses version {SCENE_FORMAT_VERSION}")
    return reply.header


def connect_slave(host: str, port: int, timeout: float = 3.0, master_name: str = "master",
                  secret: bytes | None = None, heartbeat_s: float = protocol.HEARTBEAT_S,
                  silence_s: float = protocol.SILENCE_S) -> SlaveConnection:
    """Connect and handshake (the whole handshake within `timeout` + `silence_s`); MasterError
    with a readable message on any failure."""
    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except OSError as exc:
        raise MasterError(f"cannot reach slave {host}:{port} ({_reason(exc)})") from None
    try:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # tile requests are tiny
        channel = protocol.Channel(sock, "master", grace_s=silence_s)
        welcome = _handshake(channel, host, port, master_name, secret, heartbeat_s,
                             time.monotonic() + timeout + silence_s)
        return SlaveConnection(host, port, channel, welcome)
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


def describe(exc: Exception) -> str:
    """Why a slave was dropped, for the user: a lost connection, what it sent, or a bug."""
    if isinstance(exc, protocol.ConnectionClosed):
        return "disconnected"
    if isinstance(exc, OSError):
        return f"connection lost ({_reason(exc)})"
    if isinstance(exc, (ProtocolError, MasterError)):
        return str(exc)
    return f"internal error ({type(exc).__name__}: {exc})"
