"""A connection to one slave: its TLS socket and protocol channel, the handshake (OPEN, TLS
with both identities, HELLO with the master's proofs, WELCOME with the slave's), the decision
whether this master may send the slave anything (docs/protocol.md, "Identities and trust"),
and the errors a user reads when a slave cannot be used. The master's frame loop reads a
connection while a frame runs, its other threads between frames (connecting, uploading a
scene)."""
from __future__ import annotations

import socket
import ssl
import time

from . import protocol, secure, trust
from .channel import Channel
from .identity import Identity, short_id
from .protocol import MsgType, ProtocolError
from .trust import AllowList
from ..scene.model import SCENE_FORMAT_VERSION


class MasterError(Exception):
    """Something the user should read: an unreachable slave, a refused handshake, no slaves."""


class SlaveBusy(MasterError):
    """The slave serves as many masters as it can; worth trying again later."""


class SlaveNotApproved(MasterError):
    """The slave is neither approved by the user nor proves the farm secret: it gets nothing
    (not even a HELLO when this master has no secret). Not worth retrying."""

    def __init__(self, host: str, port: int, slave_id: str, why: str):
        self.host, self.port, self.slave_id = host, port, slave_id
        super().__init__(f"slave {host}:{port} (ID {short_id(slave_id)}) is not approved: {why}; "
                         f"approve it in the Slaves panel once you have checked that its log "
                         f"shows this ID, or give both sides the farm secret")


class SlaveConnection:
    """A connected, handshaken slave. Sends are serialised by the channel; one thread receives."""

    def __init__(self, host: str, port: int, channel: Channel, welcome: dict,
                 slave_id: str = "", trusted_by: str = ""):
        self.host, self.port, self.channel = host, port, channel
        self.name = trust.sanitize(protocol.get_str(welcome, "name", 64))
        self.id = slave_id                   # pinned in the TLS handshake
        self.trusted_by = trusted_by         # "approved", "paired" or "farm secret"
        # Which slave process (slaves of one owner may share an identity, so their ID)
        self.instance = protocol.get_str(welcome, "instance", 64) if "instance" in welcome \
            else slave_id
        self.slave_nonce = protocol.get_str(welcome, "nonce", trust.NONCE_HEX)
        self.device = trust.sanitize(protocol.get_str(welcome, "device", 256), 256)
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
    if isinstance(exc, ssl.SSLError):
        return f"TLS failed ({exc.reason or exc})"
    return exc.strerror or str(exc) or type(exc).__name__


def _handshake(channel: Channel, host: str, port: int, master_name: str,
               identity: Identity, slave_id: str, secret: bytes | None, approved: bool,
               pairing_code: str | None, heartbeat_s: float, deadline: float) -> tuple:
    """HELLO (with the farm proof and the pairing proof where this master has them), WELCOME;
    returns (WELCOME header, why the slave is trusted). MasterError names what went wrong
    (SlaveBusy for a slave at capacity, SlaveNotApproved for one that is not trusted)."""
    nonce = trust.new_nonce()
    hello = {"protocol_version": protocol.PROTOCOL_VERSION,
             "scene_format_version": SCENE_FORMAT_VERSION, "name": master_name, "nonce": nonce,
             "heartbeat_s": heartbeat_s}
    if secret is not None:
        hello["proof"] = trust.master_farm_proof(secret, nonce, identity.id, slave_id)
    if pairing_code is not None:
        hello["pairing"] = trust.pairing_proof(pairing_code, nonce, identity.id, slave_id)
    channel.send(MsgType.HELLO, hello)
    reply = channel.recv(protocol.DEFAULT_LIMITS, {MsgType.WELCOME, MsgType.ERROR},
                         deadline=deadline)
    if reply.type == MsgType.ERROR:
        message = protocol.get_str(reply.header, "message", 4096)
        if reply.header.get("busy") is True:
            raise SlaveBusy(f"slave {host}:{port} is busy: {message}")
        raise MasterError(f"slave {host}:{port} refused the connection: {message}")
    theirs = reply.header.get("scene_format_version")
    if theirs != SCENE_FORMAT_VERSION:
        raise MasterError(f"slave {host}:{port}: scene format version mismatch: slave uses "
                          f"version {theirs}, master uses version {SCENE_FORMAT_VERSION}")
    slave_nonce = protocol.get_str(reply.header, "nonce", trust.NONCE_HEX)
    if pairing_code is not None and reply.header.get("admitted_by") == "pairing":
        return reply.header, "paired"
    if approved:
        return reply.header, "approved"
    if secret is not None and trust.proof_ok(
            trust.slave_farm_proof(secret, nonce, slave_nonce, identity.id, slave_id),
            reply.header.get("proof")):
        return reply.header, "farm secret"
    raise SlaveNotApproved(host, port, slave_id, "it does not prove the farm secret")


def connect_slave(host: str, port: int, timeout: float = 3.0, master_name: str = "master",
                  secret: bytes | None = None, heartbeat_s: float = protocol.HEARTBEAT_S,
                  silence_s: float = protocol.SILENCE_S, *, identity: Identity,
                  approved: AllowList | None = None, pairing: dict | None = None) -> SlaveConnection:
    """Connect, open TLS with `identity` and handshake (all within `timeout` + `silence_s`).
    The slave must be `approved` (IDs the user approved), named in `pairing` (slave ID ->
    the pairing code its owner gave: the user picked that slave) or prove `secret`; a slave
    that is none of these gets nothing and SlaveNotApproved names its ID. MasterError with a
    readable message on any failure."""
    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except OSError as exc:
        raise MasterError(f"cannot reach slave {host}:{port} ({_reason(exc)})") from None
    try:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # tile requests are tiny
        deadline = time.monotonic() + timeout + silence_s
        tls, slave_id = secure.open_client(sock, identity, deadline)
        sock = tls
        code = (pairing or {}).get(slave_id)
        is_approved = approved is not None and approved.allows(slave_id)
        if not is_approved and code is None and secret is None:
            # Not even a HELLO: an unknown machine learns nothing from this master.
            raise SlaveNotApproved(host, port, slave_id, "this master has no farm secret")
        channel = Channel(tls, "master", grace_s=silence_s)
        welcome, trusted_by = _handshake(channel, host, port, master_name, identity, slave_id,
                                         secret, is_approved, code, heartbeat_s, deadline)
        return SlaveConnection(host, port, channel, welcome, slave_id, trusted_by)
    except SlaveNotApproved:
        sock.close()
        raise
    except secure.Refused as exc:
        sock.close()
        if exc.busy:
            raise SlaveBusy(f"slave {host}:{port} is busy: {exc}") from None
        raise MasterError(f"slave {host}:{port} refused the connection: {exc}") from None
    except protocol.VersionMismatch as exc:
        sock.close()
        raise MasterError(f"slave {host}:{port}: protocol version mismatch: slave speaks version "
                          f"{exc.peer_version}, master speaks version {protocol.PROTOCOL_VERSION}") from None
    except MasterError:
        sock.close()
        raise
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
