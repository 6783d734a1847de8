"""Opening a connection: the plaintext OPEN exchange, then TLS 1.3 with both identities.

    master                              slave
    OPEN (plaintext header: version) ->
                                     <- OPEN, or ERROR naming both versions, and close
    TLS 1.3 handshake: both present an identity certificate (core/net/identity.py)
    ... every later byte inside TLS: HELLO, WELCOME, scenes, tiles

OPEN carries nothing but the protocol version in its header (and an empty JSON object), so a
peer of another version is told so by name, before any TLS, on both sides; everything else
travels encrypted. Each function keeps an absolute deadline for its whole part (a peer that
dribbles its handshake is cut off at the deadline, not per read).
"""
from __future__ import annotations

import socket
import ssl
import time

from . import channel, protocol
from .identity import Identity, peer_id
from .protocol import HEADER, MsgType, ProtocolError

OPEN_LIMITS = protocol.Limits(max_json=256)


def _send_plain(sock: socket.socket, msg_type: MsgType, header: dict, deadline: float) -> None:
    data = b"".join(bytes(b) for b in protocol.encode_message(msg_type, header))
    sock.settimeout(max(0.01, deadline - time.monotonic()))
    sock.sendall(data)


def _recv_plain(sock: socket.socket, allowed, deadline: float) -> protocol.Message:
    """One plaintext message (OPEN, or a refusal), within `deadline`."""
    def exactly(count: int, what: str, allow_eof=False) -> bytes:
        data = bytearray()
        while len(data) < count:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise protocol.PeerTooSlow(f"the opening did not arrive in time ({what}: "
                                           f"{len(data)} of {count} bytes)")
            sock.settimeout(min(remaining, channel.POLL_S))
            try:
                chunk = sock.recv(count - len(data))
            except socket.timeout:
                continue
            if not chunk:
                if allow_eof and not data:
                    raise protocol.ConnectionClosed("connection closed by peer")
                raise protocol.ConnectionBroken(f"connection closed in the middle of a message "
                                                f"({what}: {len(data)} of {count} bytes)")
            data += chunk
        return bytes(data)

    head = exactly(HEADER.size, "header", allow_eof=True)
    msg_type, json_length, payload_length = protocol.check_header(head, OPEN_LIMITS, allowed)
    text = exactly(json_length, "JSON")
    payload = exactly(payload_length, "payload")
    return protocol.parse_body(msg_type, text, payload)


def _handshake(tls: ssl.SSLSocket, deadline: float) -> None:
    """The TLS handshake, non-blocking, within `deadline`."""
    tls.settimeout(0.0)
    while True:
        try:
            tls.do_handshake()
            return
        except ssl.SSLWantReadError:
            writing = False
        except ssl.SSLWantWriteError:
            writing = True
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise protocol.PeerTooSlow("the TLS handshake did not finish in time")
        channel.socket_ready(tls, writing, min(remaining, channel.POLL_S))


def open_client(sock: socket.socket, identity: Identity, deadline: float) -> tuple:
    """The master's side: OPEN both ways, then TLS. Returns (TLS socket, the slave's ID).
    VersionMismatch (the slave's OPEN or refusal is of another version), MasterRefusal-like
    ProtocolError carrying the slave's ERROR text, ssl.SSLError (TLS failed), OSError."""
    _send_plain(sock, MsgType.OPEN, {}, deadline)
    reply = _recv_plain(sock, {MsgType.OPEN, MsgType.ERROR}, deadline)
    if reply.type == MsgType.ERROR:
        raise Refused(protocol.get_str(reply.header, "message", 4096),
                      reply.header.get("busy") is True)
    tls = identity.client_context().wrap_socket(sock, do_handshake_on_connect=False)
    _handshake(tls, deadline)
    return tls, peer_id(tls)


def open_server(sock: socket.socket, identity: Identity, deadline: float) -> tuple:
    """The slave's side: OPEN both ways (a peer of another version gets an ERROR naming both
    versions, in plaintext, before anything else), then TLS. Returns (TLS socket, the master's
    ID). ProtocolError / VersionMismatch for a bad opening (the caller refuses in plaintext),
    ssl.SSLError for a failed TLS handshake (no certificate, not an identity), OSError."""
    _recv_plain(sock, {MsgType.OPEN}, deadline)
    _send_plain(sock, MsgType.OPEN, {}, deadline)
    tls = identity.server_context().wrap_socket(sock, server_side=True,
                                                do_handshake_on_connect=False)
    _handshake(tls, deadline)
    return tls, peer_id(tls)


class Refused(ProtocolError):
    """The slave refused the connection in plaintext (ERROR instead of OPEN)."""

    def __init__(self, message: str, busy: bool = False):
        super().__init__(message)
        self.busy = busy
