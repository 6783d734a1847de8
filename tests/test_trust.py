"""Issue 39, "Safe on any network": identities, pairing and TLS (findings 2, 3, 4 and the
hygiene items of 7), each shown by the safe behaviour (docs/protocol.md, "Identities and
trust"). Slaves are `python -m kdtrace.slave` processes on loopback (what their owner sees: the log,
--status, the zeroconf record) or SlaveServers in this process (what crosses the wire)."""
from __future__ import annotations

import logging
import os
import re
import socket
import ssl
import threading
import time
import urllib.request

import numpy as np
import pytest

from kdtrace.core.net import protocol, secure, trust
from kdtrace.core.net.channel import Channel
from kdtrace.core.net.discovery import SlaveBrowser
from kdtrace.core.net.identity import Identity, short_id
from kdtrace.core.net.master import MAX_SLAVES, Master, MasterError
from kdtrace.core.net.protocol import MsgType
from kdtrace.core.private import NotPrivate
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.scene_cache import SceneCache
from kdtrace.slave.server import SlaveServer
from tests import tls_peers
from tests.conftest import FARM_SECRET
from tests.processes import ChildProcess, SlaveProcess
from tests.test_network import make_scene, make_view, render_all

NO_FARM = {"KDTRACE_SECRET": None}       # a slave of its own: no farm secret in its environment


class _NoDevice:
    device_info = {"name": "none", "compute_units": 1, "memory": 0, "platform": "test"}
    build_seconds = 0.0


@pytest.fixture(scope="module")
def scene():
    return Scene.from_parts(*make_scene())


@pytest.fixture(scope="module")
def tracer():
    from kdtrace.slave.tracer import Tracer
    return Tracer()


def own_slave(tmp_path, name, *extra) -> SlaveProcess:
    """A slave as its owner first starts it: its own identity folder, no farm secret."""
    return SlaveProcess(name, "--identity-dir", str(tmp_path / f"{name}-identity"), *extra,
                        env=NO_FARM)


# -- finding 2: a slave serves nobody until its owner says whom ---------------------------------
def test_a_new_slave_serves_nobody_and_tells_its_owner_how_to_pair(tmp_path, scene):
    master = Identity.ephemeral("master")
    slave = own_slave(tmp_path, "kdt-trust-new")
    try:
        time.sleep(0.3)
        code = re.search(r"enter the pairing code ([A-Z2-7]{4}-[A-Z2-7]{4})", slave.log)
        assert code, slave.log
        assert f"ID {short_id(slave.id)}" in slave.log
        assert "--allow MASTER-ID" in slave.log and "--new-secret FILE" in slave.log
        # Any master, with or without a farm secret of its own, is refused before a WELCOME.
        for secret in (None, FARM_SECRET):
            channel, reply = tls_peers.handshaken(slave.endpoint, secret=secret, who=master)
            channel.close()
            assert reply.type == MsgType.ERROR, reply
            assert f"does not serve master ID {short_id(master.id)}" in reply.header["message"]
        assert f"refused: this slave does not serve master ID {short_id(master.id)}" in slave.log
        # The owner pairs one master with the code: it is allowed from then on, and the code
        # is used up (a second master cannot use it).
        with Master([slave.endpoint], secret=None, identity=master,
                    pairing={slave.id: code[1].lower()}) as paired:
            paired.connect()
            assert paired.slaves[0].trusted_by == "paired"
            paired.load_scene(scene)
        with pytest.raises(MasterError, match="pairing failed"):
            Master([slave.endpoint], secret=None, pairing={slave.id: code[1]}).connect()
    finally:
        slave.stop()
    # Restarted, the slave still serves the paired master (allowed-masters.txt), no other,
    # and shows no pairing code any more.
    slave = own_slave(tmp_path, "kdt-trust-new")
    try:
        time.sleep(0.3)
        assert "pairing code" not in slave.log
        with Master([slave.endpoint], secret=None, identity=master,
                    approved_slaves=[slave.id[:16]]) as again:
            assert again.connect()[0].trusted_by == "approved"
        with pytest.raises(MasterError, match="does not serve master ID"):
            Master([slave.endpoint], secret=None, approved_slaves=[slave.id]).connect()
    finally:
        slave.stop()


def test_allow_and_status_and_zeroconf_show_the_slaves_id(tmp_path):
    master = Identity.ephemeral("master")
    slave = own_slave(tmp_path, "kdt-trust-allow", "--allow", short_id(master.id), "--status-port", "0")
    try:
        time.sleep(0.3)
        assert "pairing code" not in slave.log    # allowed masters: no code unless --pair
        with Master([slave.endpoint], secret=None, identity=master,
                    approved_slaves=[slave.id]) as allowed:
            assert allowed.connect()[0].trusted_by == "approved"
        port = int(re.search(r"--status --status-port (\d+)", slave.log)[1])
        status = ChildProcess(["-m", "kdtrace.slave", "--status", "--status-port", str(port)])
        status.proc.wait(30)
        assert f"(ID {short_id(slave.id)})" in "".join(status.lines), status.lines
        browser = SlaveBrowser(interfaces=["127.0.0.1"])
        try:
            deadline, found = time.monotonic() + 10, None
            while found is None and time.monotonic() < deadline:
                found = next((s for s in browser.slaves() if s.name == slave.name), None)
                time.sleep(0.1)
        finally:
            browser.close()
        assert found is not None and found.properties["id"] == slave.id
        assert found.properties["farm"] == "0" and found.properties["pairing"] == "0"
    finally:
        slave.stop()


def test_a_pairing_code_is_retired_after_five_wrong_tries():
    code = trust.PairingCode()
    server = SlaveServer(_NoDevice(), "kdt-pair", bind="127.0.0.1", port=0, pairing=code)
    server.start()
    try:
        for attempt in range(trust.PAIRING_TRIES):
            with pytest.raises(MasterError, match="pairing failed: wrong pairing code"):
                Master([server.address], secret=None, pairing={server.slave_id: "AAAA-AAAA"}).connect()
        assert not code.active
        with pytest.raises(MasterError, match="pairing failed"):     # even the right one now
            Master([server.address], secret=None, pairing={server.slave_id: code.code}).connect()
        assert server.serves_nobody
    finally:
        server.close()


# -- finding 3: scenes go only to approved slaves -----------------------------------------------
class RecordingSlave:
    """A slave with an identity of its own (not approved anywhere) that completes TLS and
    records every byte that arrives inside it."""

    def __init__(self):
        self.identity = Identity.ephemeral("slave")
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.endpoint = self.listener.getsockname()[:2]
        self.received, self.connections = bytearray(), 0
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self):
        while True:
            try:
                sock, _ = self.listener.accept()
            except OSError:
                return
            self.connections += 1
            try:
                tls, _ = secure.open_server(sock, self.identity, time.monotonic() + 10)
                channel = Channel(tls, "slave")
                while chunk := tls_peers.read_all(channel, 3):
                    self.received += chunk
            except (OSError, protocol.ProtocolError):
                pass

    def close(self):
        self.listener.close()


def test_an_unapproved_slave_receives_no_scene_byte(scene, tracer):
    stranger = RecordingSlave()
    server = SlaveServer(tracer, "kdt-approved", bind="127.0.0.1", port=0,
                         allowed=trust.AllowList())
    server.start()
    try:
        master = Master([server.address], secret=None, approved_slaves=[server.slave_id])
        server.allowed.add(master.identity.id)
        with master:
            master.connect()
            master.load_scene(scene)
            job = master.render(make_view(), tile_size=16)
            master.join(*stranger.endpoint)       # found mid-frame (as by zeroconf)
            render_all(job)
            deadline = time.monotonic() + 5
            while stranger.connections == 0 and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(0.5)
            assert stranger.connections >= 1          # it was tried (TLS, its ID read) ...
            assert bytes(stranger.received) == b""    # ... and sent nothing, not even a HELLO
            assert master.unapproved == {stranger.endpoint: stranger.identity.id}
            states = {(s.host, s.port): s for s in master.slave_states()}
            assert "is not approved" in states[stranger.endpoint].reason
            assert [s.endpoint for s in master.slaves] == [server.address]
        # With the farm secret the stranger gets a HELLO (with the master's proof, bound to
        # both IDs and worth nothing elsewhere), still no scene: it proves no secret back.
        with pytest.raises(MasterError, match="failed the handshake"):
            Master([stranger.endpoint], secret=FARM_SECRET, connect_timeout=1,
                   silence_timeout=2, heartbeat_s=1).connect()
        deadline = time.monotonic() + 10      # the recorder's thread may not have read it yet
        while b'"proof"' not in bytes(stranger.received) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert b'"proof"' in bytes(stranger.received)          # the HELLO came ...
        assert b"scene_hash" not in bytes(stranger.received)   # ... and nothing after it
    finally:
        stranger.close()
        server.close()


def test_discovered_slaves_and_a_masters_endpoints_are_bounded(monkeypatch):
    with pytest.raises(MasterError, match=f"at most {MAX_SLAVES}"):
        Master([("127.0.0.1", 1000 + i) for i in range(MAX_SLAVES + 1)], secret=None)
    master = Master([("127.0.0.1", 1000 + i) for i in range(MAX_SLAVES)], secret=None,
                    retry_delays=())
    master.join("127.0.0.1", 999)
    assert master.errors[-1].endswith(f"this master has {MAX_SLAVES} slaves already")
    assert ("127.0.0.1", 999) not in master.endpoints
    master.close()
    # A browser keeps at most MAX_DISCOVERED slaves (here 2 of 3 advertised).
    import kdtrace.core.net.discovery as discovery
    monkeypatch.setattr(discovery, "MAX_DISCOVERED", 2)
    adverts = [discovery.advertise(f"kdt-bound-{os.getpid()}-{i}", 40000 + i, {"id": "x"},
                                   ["127.0.0.1"], ["127.0.0.1"], instance=f"b{i}")
               for i in range(3)]
    browser = SlaveBrowser(interfaces=["127.0.0.1"])
    try:
        deadline = time.monotonic() + 10
        while browser.ignored == 0 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(browser.slaves()) <= 2 and browser.ignored >= 1
    finally:
        browser.close()
        for advert in adverts:
            advert.close()


def test_a_frame_uses_only_approved_lan_slaves():
    """core/frame's choice of LAN slaves: by the advertised ID (checked again in TLS), all of
    them only with the farm secret; the others wait in the panel, unconnected."""
    from kdtrace.core.frame.session import FrameSession
    from kdtrace.core.net.discovery import SlaveInfo
    session = FrameSession()
    known, other = "A" * 52, "B" * 52
    slaves = [SlaveInfo("a", "10.0.0.2", 47600, {"id": known}),
              SlaveInfo("b", "10.0.0.3", 47600, {"id": other})]
    session.discovered_slaves = lambda: slaves
    assert session.trusted_lan_endpoints(trust.AllowList([known[:16]]), False) == [("10.0.0.2", 47600)]
    assert session.unapproved == {("10.0.0.3", 47600): other}
    assert len(session.trusted_lan_endpoints(trust.AllowList(), True)) == 2


# -- finding 4: encrypted, and nothing offline-guessable leaves either side ---------------------
class Recorder:
    """A TCP relay that keeps a copy of every byte either way (a capture of the stream)."""

    def __init__(self, target):
        self.target, self.captured = target, bytearray()
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.endpoint = self.listener.getsockname()[:2]
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self):
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            server = socket.create_connection(self.target)
            for a, b in ((client, server), (server, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    def _pump(self, source, sink):
        try:
            while data := source.recv(65536):
                self.captured += data
                sink.sendall(data)
        except OSError:
            pass
        for sock in (source, sink):
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def close(self):
        self.listener.close()


def test_a_scenes_bytes_are_not_in_a_capture_of_the_stream(scene, tracer):
    server = SlaveServer(tracer, "kdt-capture", bind="127.0.0.1", port=0, secret=FARM_SECRET)
    server.start()
    recorder = Recorder(server.address)
    try:
        with Master([recorder.endpoint], secret=FARM_SECRET, name="capture-probe") as master:
            master.connect()
            master.load_scene(scene)
            images, _ = render_all(master.render(make_view(), tile_size=16))
        time.sleep(0.3)
        captured = bytes(recorder.captured)
        assert len(captured) > scene.geometry.vertices.nbytes     # the upload went through
        # What the scene and the frame are made of, as the protocol carries them: in the clear
        # they are in the message bytes; in the capture, nowhere.
        vertices = scene.geometry.vertices.tobytes()
        triangles = scene.geometry.triangles.tobytes()
        uploaded = [vertices[i:i + 48] for i in range(0, len(vertices) - 48, len(vertices) // 8)]
        uploaded += [triangles[:48], scene.hash.encode()]
        plain = b"".join(bytes(b) for b in protocol.encode_message(
            MsgType.SCENE_UPLOAD, {"scene_hash": scene.hash}, scene.wire_arrays()))
        assert all(piece in plain for piece in uploaded)
        known = uploaded + [images["combined"][20, 20:24].tobytes(), b"capture-probe", FARM_SECRET]
        found = [piece[:16] for piece in known if piece in captured]
        assert found == [], found
        assert b"TLS" not in captured[:64] and captured[:4] == protocol.MAGIC   # only OPEN is plain
    finally:
        recorder.close()
        server.close()


def test_an_anonymous_connection_gets_nothing_derived_from_the_secret():
    """The master proves first: a connection without the farm secret (its own identity, no
    proof or a wrong one) is refused with words only; no WELCOME, no slave proof, no nonce to
    test guesses against."""
    server = SlaveServer(_NoDevice(), "kdt-anon", bind="127.0.0.1", port=0, secret=FARM_SECRET)
    server.start()
    try:
        for changes in ({"secret": None}, {"proof": "0" * 64}, {"proof": None}):
            secret = changes.pop("secret", FARM_SECRET)
            who = Identity.ephemeral("master")
            channel, slave_id = tls_peers.open_tls(server.address, who)
            fields = tls_peers.hello_fields(who, slave_id, secret, **changes)
            fields = {k: v for k, v in fields.items() if v is not None}
            channel.send(MsgType.HELLO, fields)
            everything = tls_peers.read_all(channel, 5)
            channel.close()
            assert everything[:4] == protocol.MAGIC and b'"message"' in everything   # ERROR
            assert b'"proof"' not in everything and b'"nonce"' not in everything
            assert b"protocol_version" not in everything     # no WELCOME
        # A typed password is no farm secret: refused on both sides before any connection.
        with pytest.raises(MasterError, match="does not hold a generated farm secret"):
            Master([server.address], secret="hunter2")
        with pytest.raises(trust.AuthError, match="does not hold a generated farm secret"):
            SlaveServer(_NoDevice(), "kdt-typed", bind="127.0.0.1", port=0, secret=b"hunter2")
    finally:
        server.close()


def test_a_wrong_or_missing_identity_is_refused_on_both_sides(caplog):
    server = SlaveServer(_NoDevice(), "kdt-ids", bind="127.0.0.1", port=0, secret=FARM_SECRET)
    server.start()
    try:
        with caplog.at_level(logging.WARNING, logger="kdtrace.slave"):
            # No certificate, or one that is no KD Trace identity: TLS fails at the slave.
            for context in (_plain_client(), _foreign_client()):
                sock = socket.create_connection(server.address, timeout=5)
                secure._send_plain(sock, MsgType.OPEN, {}, time.monotonic() + 5)
                secure._recv_plain(sock, {MsgType.OPEN}, time.monotonic() + 5)
                with pytest.raises((ssl.SSLError, OSError)):
                    tls = context.wrap_socket(sock)
                    tls.recv(1)
                sock.close()
            time.sleep(0.3)
        assert caplog.text.count("TLS handshake failed") == 2, caplog.text
        # The master pins the slave's ID: an approved ID that is not the one presented, and
        # no farm secret, gives nothing.
        with pytest.raises(MasterError, match="is not approved"):
            Master([server.address], secret=None, approved_slaves=["A" * 52]).connect()
        # A slave that allows master X refuses master Y, whatever Y says its name is.
        x, y = Identity.ephemeral("master"), Identity.ephemeral("master")
        picky = SlaveServer(_NoDevice(), "kdt-picky", bind="127.0.0.1", port=0,
                            allowed=trust.AllowList([x.id]))
        picky.start()
        try:
            with Master([picky.address], secret=None, identity=x, approved_slaves=[picky.slave_id]) as ok:
                assert ok.connect()
            with pytest.raises(MasterError, match=f"does not serve master ID {short_id(y.id)}"):
                Master([picky.address], secret=None, identity=y, name=x.short_id,
                       approved_slaves=[picky.slave_id]).connect()
        finally:
            picky.close()
        # A master meets a "slave" whose certificate is no identity: refused in TLS.
        foreign = socket.create_server(("127.0.0.1", 0))

        def serve():
            sock, _ = foreign.accept()
            secure._recv_plain(sock, {MsgType.OPEN}, time.monotonic() + 5)
            secure._send_plain(sock, MsgType.OPEN, {}, time.monotonic() + 5)
            try:
                _foreign_server().wrap_socket(sock, server_side=True)
            except (ssl.SSLError, OSError):
                pass
            sock.close()
        threading.Thread(target=serve, daemon=True).start()
        with pytest.raises(MasterError, match="TLS failed"):
            Master([foreign.getsockname()[:2]], secret=FARM_SECRET).connect()
        foreign.close()
    finally:
        server.close()


def _foreign_identity():
    """A certificate and key of an issuer of its own (not the KD Trace issuer)."""
    import datetime
    import tempfile
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "KD Trace master")])
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name)
            .public_key(key.public_key()).serial_number(7)
            .not_valid_before(datetime.datetime(2024, 1, 1))
            .not_valid_after(datetime.datetime(2099, 1, 1)).sign(key, hashes.SHA256()))
    folder = tempfile.mkdtemp()
    with open(f"{folder}/c.pem", "wb") as f:
        f.write(cert.public_bytes(serialization.Encoding.PEM))
    with open(f"{folder}/k.pem", "wb") as f:
        f.write(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                  serialization.NoEncryption()))
    return f"{folder}/c.pem", f"{folder}/k.pem"


def _plain_client():
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname, context.verify_mode = False, ssl.CERT_NONE
    return context


def _foreign_client():
    context = _plain_client()
    context.load_cert_chain(*_foreign_identity())
    return context


def _foreign_server():
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(*_foreign_identity())
    return context


# -- finding 7: hygiene --------------------------------------------------------------------------
def test_a_masters_name_cannot_forge_log_lines(caplog):
    server = SlaveServer(_NoDevice(), "kdt-names", bind="127.0.0.1", port=0, secret=FARM_SECRET)
    server.start()
    try:
        with caplog.at_level(logging.INFO, logger="kdtrace.slave"):
            forged = "m\n2026-01-01 00:00:00 kdtrace-slave INFO: master root connected\x1b[2J"
            channel, reply = tls_peers.handshaken(server.address, name=forged[:64])
            assert reply.type == MsgType.WELCOME
            channel.close()
            time.sleep(0.3)
        lines = [r.getMessage() for r in caplog.records]
        assert any("m?2026-01-01 00:00:00 kdtrace-slave INFO: master root connected" in line
                   for line in lines), lines
        assert all("\n" not in line and "\x1b" not in line for line in lines)
    finally:
        server.close()


def test_caches_and_identities_are_private(tmp_path, scene):
    cache = SceneCache(2, tmp_path / "scenes", 1 << 30)
    cache.put(scene)
    assert (tmp_path / "scenes").stat().st_mode & 0o777 == 0o700
    identity = Identity.load_or_create(tmp_path / "id")
    assert (tmp_path / "id").stat().st_mode & 0o777 == 0o700
    assert (tmp_path / "id" / "identity-key.pem").stat().st_mode & 0o777 == 0o600
    wide = tmp_path / "wide"
    wide.mkdir(mode=0o755)
    os.chmod(wide, 0o755)
    SceneCache(2, wide, 1 << 30)
    assert wide.stat().st_mode & 0o777 == 0o700       # narrowed
    if os.geteuid() == 0:     # a folder another user made (root can hand it over): refused
        planted = tmp_path / "planted"
        planted.mkdir()
        os.chown(planted, 65534, 65534)
        with pytest.raises(NotPrivate, match="belongs to another user"):
            SceneCache(2, planted, 1 << 30)
        with pytest.raises(OSError, match="belongs to another user"):
            Identity.load_or_create(planted)
    assert identity.id == Identity(tmp_path / "id").id


@pytest.mark.skipif(os.geteuid() != 0, reason="planting a folder of another user needs root")
def test_pocl_cache_folder_of_another_user_is_not_used(tmp_path, monkeypatch):
    from kdtrace.core import opencl
    cache, temporary = tmp_path / "cache", tmp_path / "tmp"
    for folder in (cache / "kdtrace" / "pocl", temporary / f"kdtrace-pocl-{os.getuid()}"):
        folder.mkdir(parents=True)
        os.chown(folder, 65534, 65534)     # planted by another user
    monkeypatch.delenv("POCL_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(cache))
    monkeypatch.setattr(opencl.tempfile, "gettempdir", lambda: str(temporary))
    opencl.ensure_pocl_cache_dir()
    assert "POCL_CACHE_DIR" not in os.environ
    os.chown(temporary / f"kdtrace-pocl-{os.getuid()}", os.getuid(), os.getgid())
    opencl.ensure_pocl_cache_dir()
    assert os.environ["POCL_CACHE_DIR"] == str(temporary / f"kdtrace-pocl-{os.getuid()}")
    assert (temporary / f"kdtrace-pocl-{os.getuid()}").stat().st_mode & 0o777 == 0o700


def test_status_checks_the_host_and_shows_no_scene_hash():
    from kdtrace.slave.activity import Activity
    from kdtrace.slave.status import StatusServer
    activity = Activity()
    activity.master_connected("m")
    activity.frame_started("m", 1, "ab" * 16, 4)
    server = StatusServer(0, activity.status)
    try:
        with urllib.request.urlopen(server.url, timeout=5) as reply:
            body = reply.read().decode()
        assert "abababab" in body and "ab" * 16 not in body
        request = urllib.request.Request(server.url, headers={"Host": f"attacker.example:{server.port}"})
        with pytest.raises(urllib.error.HTTPError, match="421"):
            urllib.request.urlopen(request, timeout=5)
    finally:
        server.close()


def test_a_connection_renders_only_scenes_it_uploaded_or_proved(scene, tracer):
    server = SlaveServer(tracer, "kdt-grants", bind="127.0.0.1", port=0, secret=FARM_SECRET)
    server.start()
    try:
        with Master([server.address], secret=FARM_SECRET) as owner:     # uploads the scene
            owner.connect()
            owner.load_scene(scene)
        frame = {"frame_id": 1, "scene_hash": scene.hash, "view": make_view().to_dict(),
                 "tile_size": 16}
        # Another master that knows only the hash: the scene is "not loaded" for it, and a
        # query with a wrong proof says it is not present (it would have to upload it).
        channel, welcome = tls_peers.handshaken(server.address)
        channel.send(MsgType.FRAME_START, frame)
        reply = channel.recv(allowed=protocol.SLAVE_TO_MASTER, wait=10)
        assert reply.type == MsgType.ERROR and "is not loaded on this slave" in reply.header["message"]
        channel.send(MsgType.SCENE_QUERY, {"scene_hash": scene.hash, "holds": "0" * 64})
        assert channel.recv(allowed=protocol.SLAVE_TO_MASTER, wait=10).header["present"] is False
        # One that holds the content proves it and renders without uploading anything.
        channel.send(MsgType.SCENE_QUERY, {"scene_hash": scene.hash,
                                           **trust.scene_proofs(scene, welcome.header["nonce"])})
        assert channel.recv(allowed=protocol.SLAVE_TO_MASTER, wait=10).header["present"] is True
        channel.send(MsgType.FRAME_START, dict(frame, frame_id=2))
        channel.send(MsgType.TILE_REQUEST, {"frame_id": 2, "tile": 0})
        reply = channel.recv(allowed=protocol.SLAVE_TO_MASTER, wait=30)
        while reply.type == MsgType.HEARTBEAT:
            reply = channel.recv(allowed=protocol.SLAVE_TO_MASTER, wait=30)
        assert reply.type == MsgType.TILE_RESULT
        channel.close()
    finally:
        server.close()
