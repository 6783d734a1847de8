"""Peers by hand for the network tests: a master's or a slave's side of a connection, opened
as the protocol opens it (plaintext OPEN, TLS 1.3 with an identity; core/net/secure.py), then
driven message by message or byte by byte to misbehave. They hold the tests' farm secret
(tests/conftest.py) unless told otherwise."""
from __future__ import annotations

import socket
import time

from kdtrace.core.net import protocol, secure, trust
from kdtrace.core.net.channel import Channel
from kdtrace.core.net.identity import Identity
from kdtrace.core.net.protocol import MsgType
from kdtrace.core.scene.model import SCENE_FORMAT_VERSION
from tests.conftest import FARM_SECRET

_IDENTITIES: dict = {}


def identity(role: str = "master") -> Identity:
    """One identity per role for the whole test run (making one costs a few ms)."""
    if role not in _IDENTITIES:
        _IDENTITIES[role] = Identity.ephemeral(role)
    return _IDENTITIES[role]


def open_tls(endpoint, who: Identity | None = None, timeout: float = 10.0):
    """(channel, slave ID) of a new connection, TLS up, nothing sent inside it yet."""
    if isinstance(endpoint, int):
        endpoint = ("127.0.0.1", endpoint)
    sock = socket.create_connection(tuple(endpoint), timeout=timeout)
    tls, slave_id = secure.open_client(sock, who or identity(), time.monotonic() + timeout)
    return Channel(tls, "master"), slave_id


def hello_fields(who: Identity, slave_id: str, secret: bytes | None = FARM_SECRET,
                 **changes) -> dict:
    """A HELLO that proves the farm secret (or not: secret=None), with `changes`."""
    nonce = trust.new_nonce()
    fields = {"protocol_version": protocol.PROTOCOL_VERSION,
              "scene_format_version": SCENE_FORMAT_VERSION, "name": "probe", "nonce": nonce}
    if secret is not None:
        fields["proof"] = trust.master_farm_proof(secret, nonce, who.id, slave_id)
    fields.update(changes)
    return fields


def handshaken(endpoint, secret: bytes | None = FARM_SECRET, who: Identity | None = None,
               timeout: float = 10.0, **changes):
    """(channel, reply to HELLO): a master's connection after its HELLO (WELCOME or ERROR)."""
    who = who or identity()
    channel, slave_id = open_tls(endpoint, who, timeout)
    channel.send(MsgType.HELLO, hello_fields(who, slave_id, secret, **changes))
    return channel, channel.recv(allowed=protocol.SLAVE_TO_MASTER, wait=timeout)


def read_all(channel: Channel, timeout: float = 10.0) -> bytes:
    """Every byte the peer sends inside TLS until it closes (or `timeout`)."""
    chunks, deadline = [], time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            chunk = channel._read(lambda: channel.sock.recv(65536))
        except socket.timeout:
            continue
        except OSError:
            break
        if not chunk:
            break
        chunks.append(chunk)
    return b"".join(chunks)


def tls_exchange(endpoint, data: bytes = b"", hello: bool = True, timeout: float = 10.0,
                 **changes) -> bytes:
    """Inside TLS: a valid HELLO (unless hello=False; `changes` alter it), then raw `data`;
    returns every byte the slave sent back until it closed (WELCOME included)."""
    who = identity()
    channel, slave_id = open_tls(endpoint, who)
    try:
        if hello:
            channel.send(MsgType.HELLO, hello_fields(who, slave_id, **changes))
        if data:
            channel.send_bytes(data)
        return read_all(channel, timeout)
    finally:
        channel.close()


def serve_as_slave(sock: socket.socket, name: str, who: Identity | None = None,
                   secret: bytes | None = FARM_SECRET, timeout: float = 10.0):
    """A fake slave's side of the handshake on an accepted socket: OPEN, TLS, the master's
    HELLO, a WELCOME that proves the farm secret. Returns (channel, HELLO header)."""
    who = who or identity("slave")
    tls, master_id = secure.open_server(sock, who, time.monotonic() + timeout)
    channel = Channel(tls, "slave")
    hello = channel.recv(allowed={MsgType.HELLO}, wait=timeout)
    nonce = trust.new_nonce()
    welcome = {"protocol_version": protocol.PROTOCOL_VERSION,
               "scene_format_version": SCENE_FORMAT_VERSION, "name": name, "id": who.id,
               "nonce": nonce, "device": "none", "compute_units": 1, "memory": 1,
               "platform": "", "admitted_by": "farm secret"}
    if secret is not None:
        welcome["proof"] = trust.slave_farm_proof(secret, hello.header["nonce"], nonce,
                                                  master_id, who.id)
    channel.send(MsgType.WELCOME, welcome)
    return channel, hello.header
