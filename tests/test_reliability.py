"""Reliability (docs/distributed.md, "Liveness, bounds and authentication"): a slow tile is not a
dead slave, and no peer can stall, flood or lock out the other side.

Real `python -m kdtrace.slave` processes on 127.0.0.1 and the real tracer; misbehaving masters are
raw sockets, misbehaving slaves are fakes in this process, and a splicing proxy injects and replays
messages. Each numbered case of issue 13 has a test here that shows the good behaviour: the
slave alive and serving a real render afterwards, memory under a stated bound, an honest master
admitted while hostile sockets are held, the render returning with the bad slave named, the bad
frame refused when it starts, forged messages refused.

The 2-minute-tile render runs with KDTRACE_LONG_TESTS=1 (bench/soak.py runs it); the suite runs
the same path with tiles longer than the silence timeout.
"""
from __future__ import annotations

import os
import socket
import ssl
import threading
import time

import numpy as np
import pytest

from kdtrace.core.net import protocol, secure, trust
from kdtrace.core.net import channel as channel_module
from kdtrace.core.net.channel import Channel
from kdtrace.core.net.master import Master, MasterError, SlaveBusy, TileBudget, connect_slave
from kdtrace.core.net.protocol import HEADER, MAGIC, MsgType, ProtocolError
from kdtrace.core.net.tiles import TileGrid, TilePool, tile_grid
from kdtrace.core.scene.model import (MATERIAL_PARAMS, SCENE_FORMAT_VERSION, Light, SceneError,
                                      View, default_material_params)
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.queues import Outbox, WorkQueue
from tests import tls_peers
from tests.conftest import FARM_SECRET
from tests.processes import SlaveProcess
from tests.test_network import (assert_images_equal, make_scene, make_view, reference,  # noqa: F401
                                network_settings, render_all, slaves)

LONG_TESTS = os.environ.get("KDTRACE_LONG_TESTS") == "1"
TEXTURE = MATERIAL_PARAMS.index("texture")


# -- helpers ----------------------------------------------------------------------------------
def rss_mib(pid: int) -> float:
    with open(f"/proc/{pid}/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def hello(name="probe", nonce=None) -> bytes:
    fields = {"protocol_version": protocol.PROTOCOL_VERSION,
              "scene_format_version": SCENE_FORMAT_VERSION, "name": name}
    if nonce:
        fields["nonce"] = nonce
    return message(MsgType.HELLO, fields)


def message(msg_type, header=None, arrays=None) -> bytes:
    return b"".join(bytes(b) for b in protocol.encode_message(msg_type, header, arrays))


class RawMaster:
    """A master's side of a connection, message by message or byte by byte, with no manners
    (it holds the farm secret: it gets in)."""

    def __init__(self, endpoint, timeout=10.0, receive_buffer=None):
        sock = socket.socket()
        sock.settimeout(timeout)
        if receive_buffer:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, receive_buffer)
        sock.connect(endpoint)
        who = tls_peers.identity()
        tls, slave_id = secure.open_client(sock, who, time.monotonic() + timeout)
        self.channel = Channel(tls, "master")
        self.channel.send(MsgType.HELLO, tls_peers.hello_fields(who, slave_id))
        self.welcome = self.recv()
        assert self.welcome.type == MsgType.WELCOME, self.welcome

    def send(self, msg_type, header=None, arrays=None):
        self.channel.send(msg_type, header, arrays)

    def send_bytes(self, data: bytes):
        self.channel.send_bytes(data)

    def recv(self, wait=10.0):
        msg = self.channel.recv(protocol.Limits(), protocol.SLAVE_TO_MASTER, wait=wait)
        if msg is None:
            raise socket.timeout("nothing came")
        return msg

    def query(self, scene):
        """SCENE_QUERY for `scene`, proving that this master holds it."""
        self.send(MsgType.SCENE_QUERY, {"scene_hash": scene.hash,
                                        **trust.scene_proofs(scene, self.welcome.header["nonce"])})

    def hold(self, scene):
        """Make `scene` usable on this connection: proved if the slave holds it, else uploaded."""
        self.query(scene)
        if not self.recv().header["present"]:
            self.send(MsgType.SCENE_UPLOAD, {"scene_hash": scene.hash}, scene.wire_arrays())
            assert self.recv().header["present"]

    def close(self):
        self.channel.close()


def frame_reply(peer: RawMaster, scene, view: View, frame_id: int, **fields):
    """What the slave answers a FRAME_START of `view` (and `fields`) on `peer`, which comes to
    hold `scene` first."""
    peer.hold(scene)
    peer.send(MsgType.FRAME_START, {"frame_id": frame_id, "scene_hash": scene.hash,
                                    "view": view.to_dict(), **fields})
    return peer.recv()


def slow_view(width=64, height=48, samples_per_axis=32, region=None) -> View:
    """The test view with an area light, 1024 samples per pixel and 16 shadow samples: seconds
    per tile on one core here, a real heavy render (no test-only slowdown in the slave)."""
    view = make_view(width, height, region)
    view.shading.lights.append(Light("AREA", (1, 1, 1), 300.0, (0, 0, 4), size_u=1, size_v=1))
    view.settings = network_settings(samples_per_axis, light_samples_per_axis=4)
    return view


@pytest.fixture(scope="module")
def scene():
    return Scene.from_parts(*make_scene())


@pytest.fixture(scope="module")
def slow_reference(scene):
    """The slow view rendered by the tracer in this process, in one piece."""
    from kdtrace.slave.tracer import Tracer
    tracer = Tracer()
    tracer.load(scene)
    view = slow_view()
    return tracer.render_tile(view, 0, 0, view.width, view.height)


def real_render_works(endpoint, scene, reference_image):
    with Master([endpoint]) as master:
        master.connect()
        master.load_scene(scene)
        images, _ = render_all(master.render(make_view(), tile_size=32))
    assert_images_equal(images, reference_image)


class LoopbackServer:
    """Accepts on 127.0.0.1 and hands each connection to self.serve(sock) on a thread."""

    def __init__(self):
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.endpoint = self.listener.getsockname()[:2]
        self.sockets, self.closed = [], threading.Event()
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self):
        while True:
            try:
                sock, _ = self.listener.accept()
            except OSError:
                return
            self.sockets.append(sock)
            threading.Thread(target=self.serve, args=(sock,), daemon=True).start()

    def close(self):
        self.closed.set()
        self.listener.close()
        for sock in self.sockets:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()


class FakeSlave(LoopbackServer):
    """A slave in this process that handshakes (no secret) and then misbehaves on every tile
    request: "half" sends half a TILE_RESULT and stalls; "baddtype" sends a result whose array
    dtype is a list; "heartbeat" says it is rendering, forever, and never delivers; or on a
    scene: "slowload" takes it and validates it forever (it says it is loading, never that the
    scene is ready: a slow slave that would hold up load_scene)."""

    def __init__(self, mode: str):
        self.mode = mode
        super().__init__()

    def serve(self, sock):
        try:
            channel, _ = tls_peers.serve_as_slave(sock, f"fake-{self.mode}")
            frame = None
            while True:
                msg = channel.recv(protocol.Limits())
                if msg.type == MsgType.SCENE_QUERY:
                    channel.send(MsgType.SCENE_READY, {
                        "scene_hash": msg.header["scene_hash"],
                        "present": self.mode != "slowload"})
                elif msg.type == MsgType.SCENE_UPLOAD:
                    while not self.closed.wait(0.5):
                        channel.send(MsgType.HEARTBEAT, {"state": "loading"})
                elif msg.type == MsgType.FRAME_START:
                    frame = msg.header
                elif msg.type == MsgType.TILE_REQUEST:
                    self._misbehave(channel, frame, msg.header["tile"])
        except (OSError, ProtocolError):
            pass

    def _misbehave(self, channel, frame, index):
        tile = TileGrid(frame["view"]["region"], (frame["tile_size"], frame["tile_height"]))[index]
        x, y, w, h = tile
        header = {"frame_id": frame["frame_id"], "tile": index, "x": x, "y": y, "w": w, "h": h,
                  "render_ms": 1.0}
        passes = {"combined": np.zeros((h, w, 4), np.float32),
                  "depth": np.zeros((h, w), np.float32), "normal": np.zeros((h, w, 3), np.float32)}
        if self.mode == "half":
            data = message(MsgType.TILE_RESULT, header, passes)
            channel.send_bytes(data[:len(data) // 2])
        elif self.mode == "baddtype":
            data = message(MsgType.TILE_RESULT, header, passes)
            body = data[HEADER.size:].replace(b'"dtype":"f4"', b'"dtype":["f4"]', 1)
            channel.send_bytes(_with_json_length(data, +2) + body)
            return
        elif self.mode == "heartbeat":
            pass
        # Stay connected, read on, say nothing more (heartbeat: say only that it is busy).
        while not self.closed.is_set():
            if self.mode == "heartbeat":
                channel.send(MsgType.HEARTBEAT, {
                    "state": "rendering", "frame_id": frame["frame_id"], "tile": index})
            try:
                if channel._read(lambda: channel.sock.recv(65536), 0.3) == b"":
                    return
            except socket.timeout:
                pass


def _with_json_length(data: bytes, delta: int) -> bytes:
    magic, version, kind, json_length, payload_length = HEADER.unpack(data[:HEADER.size])
    return HEADER.pack(magic, version, kind, json_length + delta, payload_length)


# -- units: the bounded structures and the channel ---------------------------------------------
def test_tile_grid_is_lazy_and_matches_the_list():
    grid = TileGrid((0, 0, 65536, 65536), 1)
    assert len(grid) == 65536 ** 2 and grid[-1] == (65535, 65535, 1, 1)
    small = TileGrid((3, 2, 13, 9), (4, 3))
    assert list(small) == tile_grid((3, 2, 13, 9), (4, 3)) and small[5] == (11, 5, 2, 3)
    with pytest.raises(IndexError):
        small[len(small)]
    pool = TilePool(len(grid))      # a pool of 4 G tiles costs nothing until they are taken
    assert [pool.take(0), pool.take(0)] == [0, 1]
    pool.put_back(0)
    assert pool.take(0) == 0 and pool.take(0) == 2


def test_work_queue_refuses_duplicates_and_floods():
    scene_frame = type("F", (), {"frame_id": 7, "cancelled": False})()
    work = WorkQueue(capacity=3)
    work.request(scene_frame, 0)
    with pytest.raises(ProtocolError, match="tile 0 requested again while it is in flight"):
        work.request(scene_frame, 0)
    work.request(scene_frame, 1)
    work.request(scene_frame, 2)
    with pytest.raises(ProtocolError, match="more than 3 tiles requested at once"):
        work.request(scene_frame, 3)
    assert work.get()[2] == 0
    work.done(scene_frame, 0)          # sent back: the slot is free again
    work.request(scene_frame, 3)
    work.cancel(scene_frame, 7)        # the queued tiles go at once, the ack stays
    assert work.get() == ("cancel_ack", 7)
    outbox = Outbox()
    assert outbox.put("t1", is_tile=True) and outbox.put("t2", is_tile=True)
    assert not outbox.put("t3", is_tile=True, block=False)   # full: the render loop would wait
    assert outbox.put("reply")                               # replies have room of their own
    outbox.close()
    assert [outbox.get(), outbox.get(), outbox.get(), outbox.get()] == ["t1", "t2", "reply", None]


def test_tls_refuses_injected_replayed_and_reordered_records():
    """TLS (not a MAC layer of our own) authenticates every byte: a TLS record injected,
    replayed or reordered on the wire ends the connection on the receiving side."""
    def tapped():
        """A master's TLS channel and a slave's, with the test's hands on the bytes between."""
        a, tap = socket.socketpair()
        feed, d = socket.socketpair()
        result = {}

        def accept():
            result["slave"] = secure.open_server(d, tls_peers.identity("slave"),
                                                 time.monotonic() + 10)[0]
        relay = [threading.Thread(target=_copy, args=(tap, feed), daemon=True),
                 threading.Thread(target=_copy, args=(feed, tap), daemon=True)]
        for thread in relay:
            thread.start()
        server = threading.Thread(target=accept)
        server.start()
        master = secure.open_client(a, tls_peers.identity(), time.monotonic() + 10)[0]
        server.join()
        stop.set()
        for thread in relay:
            thread.join()
        stop.clear()
        for sock in (tap, feed):
            sock.settimeout(2)
        return Channel(master, "master"), Channel(result["slave"], "slave"), tap, feed

    stop = threading.Event()

    def _copy(source, sink):   # relays the handshake, then hands the bytes to the test
        source.settimeout(0.05)
        while not stop.is_set():
            try:
                data = source.recv(65536)
            except socket.timeout:
                continue
            sink.sendall(data)
        source.settimeout(None)

    def record(tap) -> bytes:
        head = protocol._recv_exactly(tap, 5, "record header")
        return bytes(head + protocol._recv_exactly(tap, int.from_bytes(head[3:5], "big"), "record"))

    master, slave, tap, feed = tapped()
    for tile in (0, 1):
        master.send(MsgType.TILE_REQUEST, {"frame_id": 1, "tile": tile})
        feed.sendall(record(tap))
        assert slave.recv(wait=2).header["tile"] == tile
    # Injected: a plaintext message where a TLS record belongs, then a forged record.
    feed.sendall(bytes([23, 3, 3, 0, 40]) + os.urandom(40))
    with pytest.raises(ssl.SSLError):
        slave.recv(wait=2)
    # Replayed: a real record sent twice.
    master, slave, tap, feed = tapped()
    master.send(MsgType.TILE_REQUEST, {"frame_id": 1, "tile": 0})
    data = record(tap)
    feed.sendall(data)
    assert slave.recv(wait=2).header["tile"] == 0
    feed.sendall(data)
    with pytest.raises(ssl.SSLError):
        slave.recv(wait=2)
    # Reordered: two real records, swapped.
    master, slave, tap, feed = tapped()
    master.send(MsgType.TILE_REQUEST, {"frame_id": 1, "tile": 0})
    master.send(MsgType.TILE_REQUEST, {"frame_id": 1, "tile": 1})
    first, second = record(tap), record(tap)
    feed.sendall(second + first)
    with pytest.raises(ssl.SSLError):
        slave.recv(wait=2)


def test_channel_deadlines_for_whole_messages(monkeypatch):
    monkeypatch.setattr(channel_module, "MIN_RATE_BPS", 1000)
    a, b = socket.socketpair()
    sender, receiver = Channel(a, "slave"), Channel(b, "master", grace_s=0.5)
    assert receiver.recv(wait=0.3) is None            # nothing began: no deadline, no error
    data = message(MsgType.TILE_REQUEST, {"frame_id": 1, "tile": 0, "pad": "x" * 4000})
    started = time.monotonic()
    a.sendall(data[:30])                              # half a message, then silence
    with pytest.raises(protocol.PeerTooSlow, match="arrived too slowly: 30 of"):
        receiver.recv(wait=5)
    assert time.monotonic() - started < 3
    # A peer that never reads: the send gives up (the stream is then unusable: closed).
    monkeypatch.setattr(channel_module, "MIN_RATE_BPS", 10 ** 7)
    sending_end, deaf_end = socket.socketpair()
    slow_sender = Channel(sending_end, "slave", grace_s=0.5)
    big = {"combined": np.zeros((512, 512, 4), np.float32)}
    started = time.monotonic()
    with pytest.raises(protocol.PeerTooSlow, match="the peer stopped reading"):
        slow_sender.send(MsgType.TILE_RESULT, {}, big)
    assert time.monotonic() - started < 3
    deaf_end.close()
    # The handshake: one absolute deadline, however the bytes dribble.
    a2, b2 = socket.socketpair()
    channel = Channel(b2, "slave", grace_s=100)
    for byte in hello()[:5]:
        a2.send(bytes([byte]))
    with pytest.raises(protocol.PeerTooSlow, match="before the deadline"):
        channel.recv(deadline=time.monotonic() + 0.6)


# -- case 5: any exception while handling a peer drops that peer, never leaves a frame waiting
def test_array_spec_with_a_list_or_object_dtype_is_refused(slaves, scene, reference):
    for spec_dtype in ([["f4"]], [{"x": 1}]):
        specs = [{"name": "a", "dtype": spec_dtype[0], "shape": [2]}]
        text = protocol.json.dumps({"arrays": specs}).encode()
        a, b = socket.socketpair()
        a.sendall(HEADER.pack(MAGIC, protocol.PROTOCOL_VERSION, MsgType.TILE_RESULT, len(text), 8)
                  + text + b"\0" * 8)
        with pytest.raises(ProtocolError, match="not allowed"):
            protocol.recv_message(b)
    # A slave that sends one: the master names it and the other slave finishes the frame.
    fake = FakeSlave("baddtype")
    try:
        with Master([fake.endpoint, slaves[0].endpoint], retry_delays=()) as master:
            master.connect()
            master.load_scene(scene)
            job = master.render(make_view(), tile_size=16)
            images, _ = render_all(job, timeout=60)
            assert job.error is None and job.progress == (12, 12)
            assert job.wait(10)
            assert any("fake-baddtype" in e and "dtype" in e and "not allowed" in e
                       for e in job.errors), job.errors
        assert_images_equal(images, reference)
    finally:
        fake.close()


def test_an_exception_while_handling_a_slave_drops_that_slave(slaves, scene, reference, monkeypatch):
    from kdtrace.core.net import slave_worker
    real_handle = slave_worker.SlaveWorker._handle
    victim_port = slaves[1].port

    def handle(worker, msg):
        if worker.connection.port == victim_port and msg.type == MsgType.TILE_RESULT:
            raise RuntimeError("a bug in the master")
        return real_handle(worker, msg)

    monkeypatch.setattr(slave_worker.SlaveWorker, "_handle", handle)
    with Master([s.endpoint for s in slaves], retry_delays=()) as master:
        master.connect()
        master.load_scene(scene)
        # No copies: the victim's tiles are its own to deliver (a copy finished elsewhere
        # would cancel its tile, which it would then stop, and the bug would never be met).
        job = master.render(make_view(), tile_size=16, duplicates=False)
        images, _ = render_all(job, timeout=60)
        assert job.error is None, job.error
        assert job.wait(30)
        assert any(slaves[1].name in e and "internal error (RuntimeError: a bug in the master)"
                   in e for e in job.errors), job.errors
    assert_images_equal(images, reference)


# -- case 4: a slave that stops in the middle of a message -----------------------------------
def test_slave_that_sends_half_a_tile_and_stops(slaves, scene, reference):
    fake = FakeSlave("half")
    try:
        with Master([fake.endpoint, slaves[0].endpoint], silence_timeout=1.0,
                    heartbeat_s=0.25, retry_delays=(0.2,)) as master:
            master.connect()
            master.load_scene(scene)
            job = master.render(make_view(), tile_size=16)
            images, _ = render_all(job, timeout=30)
            assert job.error is None and job.progress == (12, 12)
            assert job.wait(10)     # copies may complete the frame first
            assert any("fake-half" in e and "arrived too slowly" in e for e in job.errors), job.errors
        assert_images_equal(images, reference)
        # Alone, the render returns with the error, naming the slave and why.
        with Master([fake.endpoint], silence_timeout=1.0, heartbeat_s=0.25,
                    retry_delays=(0.2,)) as master:
            master.connect()
            master.load_scene(scene)
            started = time.monotonic()
            job = master.render(make_view(), tile_size=16)
            render_all(job, timeout=20)
            assert time.monotonic() - started < 15
            assert job.error.startswith("all slaves lost")
            assert "fake-half" in job.error and "arrived too slowly" in job.error, job.error
    finally:
        fake.close()


# -- liveness: busy is not silent, and the budget still ends a slave that never finishes -----
def test_tiles_longer_than_the_silence_timeout(slaves, scene, slow_reference):
    """The path of the 2-minute tiles, scaled down: two slaves, tiles that take several
    silence timeouts each (and a kernel build for the first), heartbeats in between."""
    region = (16, 12, 48, 36)        # the middle of the picture: sphere and shadows
    with Master([s.endpoint for s in slaves], silence_timeout=0.5,
                heartbeat_s=0.1) as master:
        master.connect()
        master.load_scene(scene)
        job = master.render(slow_view(region=region), tile_size=(16, 24), tiles_in_flight=1,
                            duplicates=False)
        images, results = render_all(job, timeout=240)
        assert job.error is None and job.errors == [], job.errors
        assert len({r.slave_id for r in results}) == 2
        assert min(r.render_ms for r in results) > 1000, [r.render_ms for r in results]
    window = np.s_[12:36, 16:48]
    for name, image in images.items():
        np.testing.assert_array_equal(image[window], slow_reference[name][window], err_msg=name)


def test_a_slave_with_nothing_left_stays_in_a_long_frame(scene, reference, monkeypatch):
    """The last tile of a frame takes longer than the slave's idle deadline: the other slave,
    which has nothing left to render, is kept in the frame by the master's HEARTBEAT, not
    closed as an idle master (2 tiles, one slave much slower; deadlines scaled down)."""
    from kdtrace.slave.server import SlaveServer
    from kdtrace.slave.tracer import Tracer

    class SlowTracer(Tracer):
        def render_tile(self, *args, **kwargs):
            time.sleep(3.0)
            return super().render_tile(*args, **kwargs)

    def frame(keepalive_s):
        monkeypatch.setattr(protocol, "IDLE_S", 1.0)
        monkeypatch.setattr(protocol, "KEEPALIVE_S", keepalive_s)
        servers = [SlaveServer(tracer, name, bind="127.0.0.1", port=0, secret=FARM_SECRET)
                   for tracer, name in ((Tracer(), "kdt-quick"), (SlowTracer(), "kdt-slow"))]
        for server in servers:
            server.start()
        try:
            with Master([s.address for s in servers], retry_delays=()) as master:
                master.connect()
                master.load_scene(scene)
                job = master.render(make_view(), tile_size=(32, 48), tiles_in_flight=1,
                                    duplicates=False)
                images, results = render_all(job, timeout=60)
                return job, images, results
        finally:
            for server in servers:
                server.close()

    # Without the master's HEARTBEAT the quick slave closes the connection as idle.
    job, _, _ = frame(keepalive_s=1e9)
    assert any("idle" in e for e in job.errors), job.errors
    job, images, results = frame(keepalive_s=0.3)
    assert job.error is None and job.errors == [], job.errors
    assert len({r.slave_id for r in results}) == 2
    assert_images_equal(images, reference)


@pytest.mark.skipif(not LONG_TESTS, reason="2-minute tiles take minutes: bench/soak.py runs "
                                           "this with KDTRACE_LONG_TESTS=1")
def test_two_minute_tiles_with_the_default_deadlines(scene):
    """Tiles of about 2 minutes each on this machine's cores, default heartbeat and silence."""
    from kdtrace.slave.tracer import Tracer
    view = slow_view(64, 32, samples_per_axis=64)
    view.settings.light_samples_per_axis = 10
    started = [SlaveProcess(name) for name in ("kdt-long-a", "kdt-long-b")]
    try:
        with Master([s.endpoint for s in started]) as master:
            master.connect()
            master.load_scene(scene)
            job = master.render(view, tile_size=32, duplicates=False)
            images, results = render_all(job, timeout=1800)
            assert job.error is None and job.errors == [], job.errors
            assert min(r.render_ms for r in results) > 90_000, [r.render_ms for r in results]
            print("tile ms:", [round(r.render_ms) for r in results])
    finally:
        for slave in started:
            slave.stop()
    tracer = Tracer()
    tracer.load(scene)
    assert_images_equal(images, tracer.render_tile(view, 0, 0, view.width, view.height))


def test_a_slave_that_heartbeats_forever_is_dropped_by_its_tile_budget(slaves, scene, reference):
    fake = FakeSlave("heartbeat")
    try:
        with Master([fake.endpoint, slaves[0].endpoint], silence_timeout=1.0,
                    heartbeat_s=0.25, tile_budget=TileBudget(base_s=3.0, s_per_ray=0.0),
                    retry_delays=()) as master:
            master.connect()
            master.load_scene(scene)
            job = master.render(make_view(), tile_size=16, duplicates=False)
            images, _ = render_all(job, timeout=60)
            assert job.error is None and job.progress == (12, 12)
            # Busy, so not silent: only the budget ends it.
            assert any("fake-heartbeat" in e and "took longer than its budget of 3 s" in e
                       for e in job.errors), job.errors
            assert not any("did not answer" in e for e in job.errors)
        assert_images_equal(images, reference)
    finally:
        fake.close()


def test_killed_slave_rejoins_and_a_late_slave_takes_tiles(slaves, scene, slow_reference):
    """Slave B is killed while it renders and restarted on its port: the master reconnects,
    uploads the scene to the new process and B takes tiles again; slave C, running but unknown
    to the master, is joined mid-frame (as discovery would) and takes tiles (started before
    the frame: a fast machine finishes the frame in about 5 s, in which a slave process could
    start, join, load the scene and compile, but only just). The image is the one-piece
    render's."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    b = SlaveProcess("kdt-rel-bounce", "--port", str(port))
    c = SlaveProcess("kdt-rel-late")
    seen = []
    try:
        with Master([slaves[0].endpoint, b.endpoint], silence_timeout=2.0,
                    heartbeat_s=0.25) as master:
            real_set_state = master._set_state
            master._set_state = lambda endpoint, state, reason="", connection=None: (
                seen.append((endpoint, state)), real_set_state(endpoint, state, reason, connection))
            master.connect()
            first_b = next(conn.id for conn in master.slaves if conn.name == b.name)
            master.load_scene(scene)
            job = master.render(slow_view(), tile_size=8)     # 48 tiles, ~0.5 s each
            images = {k: np.full_like(v, np.nan) for k, v in slow_reference.items()}
            results, killed, started = [], False, time.monotonic()
            while not job.finished:
                assert time.monotonic() < started + 240, "frame did not finish"
                # While it holds tiles: once it renders, or after 3 s of compiling or waiting.
                if not killed and ((b.endpoint, "rendering") in seen
                                   or time.monotonic() > started + 3):
                    b.kill()
                    killed = True
                    b = SlaveProcess("kdt-rel-bounce", "--port", str(port))
                    master.join(*c.endpoint)
                result = job.next_result(0.05)
                if result is not None:
                    results.append(result)
                    for name, image in images.items():
                        image[result.y:result.y + result.h, result.x:result.x + result.w] = \
                            result.passes[name]
            assert job.error is None, job.error
            assert killed and any(b.name in e for e in job.errors), job.errors
            by_instance = {(r.slave_name, r.slave_id) for r in results}
            assert any(name == b.name and sid != first_b for name, sid in by_instance), by_instance
            assert any(name == c.name for name, _ in by_instance), by_instance
            states = {state for endpoint, state in seen if endpoint == b.endpoint}
            assert {"rendering", "lost", "reconnecting", "uploading"} <= states, states
        assert_images_equal(images, slow_reference)
    finally:
        b.stop()
        c.stop()


# -- case 1: work proportional to a peer's numbers --------------------------------------------
def test_huge_view_with_tiny_tiles_costs_nothing(slaves, scene, reference):
    slave = slaves[0]
    real_render_works(slave.endpoint, scene, reference)   # the scene is on the slave
    before = rss_mib(slave.proc.pid)
    peer = RawMaster(slave.endpoint)
    try:
        peer.hold(scene)        # proved: the slave holds it already
        view = make_view(65536, 65536).to_dict()
        started = time.monotonic()
        peer.send(MsgType.FRAME_START, {"frame_id": 5, "scene_hash": scene.hash, "view": view,
                                        "tile_size": 1})
        peer.query(scene)       # to know it went on
        reply = peer.recv()
        assert reply.type == MsgType.ERROR and reply.header["frame_id"] == 5
        assert "4294967296 tiles in the frame, at most 1048576" in reply.header["message"]
        assert peer.recv().type == MsgType.SCENE_READY
        assert time.monotonic() - started < 2
        # A million 64-pixel tiles is a valid frame: accepted lazily, its last tile renders.
        peer.send(MsgType.FRAME_START, {"frame_id": 6, "scene_hash": scene.hash, "view": view,
                                        "tile_size": 64})
        peer.send(MsgType.TILE_REQUEST, {"frame_id": 6, "tile": 1024 * 1024 - 1})
        reply = peer.recv()
        while reply.type == MsgType.HEARTBEAT:
            reply = peer.recv()
        assert reply.type == MsgType.TILE_RESULT and \
            [reply.header[k] for k in "xywh"] == [65472, 65472, 64, 64]
        assert time.monotonic() - started < 20
        assert rss_mib(slave.proc.pid) - before < 30
    finally:
        peer.close()
    assert slave.alive()
    real_render_works(slave.endpoint, scene, reference)


# -- case 2: a master that asks and never reads ------------------------------------------------
def test_master_that_floods_requests_and_never_reads(slaves, scene, reference):
    slave = slaves[1]
    real_render_works(slave.endpoint, scene, reference)
    before = rss_mib(slave.proc.pid)
    frame = {"frame_id": 9, "scene_hash": scene.hash, "view": make_view(1024, 1024).to_dict(),
             "tile_size": 256}
    # The same tile again and again, nothing read: refused at the second request, the
    # connection closed (it grew without bound: 30 MiB/s).
    peer = RawMaster(slave.endpoint)
    peer.hold(scene)
    peer.send(MsgType.FRAME_START, frame)
    request = message(MsgType.TILE_REQUEST, {"frame_id": 9, "tile": 0})
    started, closed = time.monotonic(), False
    try:
        while time.monotonic() - started < 10:
            peer.send_bytes(request * 100)
    except (OSError, ProtocolError):
        closed = True
    peer.close()
    assert closed, "the slave never refused"
    assert "tile 0 requested again while it is in flight" in slave.log
    assert rss_mib(slave.proc.pid) - before < 30
    # Sixteen big tiles in flight (the most a master may have), then nothing read, for good:
    # the slave renders what fits in its outbox and the socket buffers, waits, and closes the
    # connection once the send deadline has passed. Its memory stays bounded meanwhile.
    peer = RawMaster(slave.endpoint, receive_buffer=4096)
    peer.hold(scene)
    peer.send(MsgType.FRAME_START, frame)
    for tile in range(16):
        peer.send(MsgType.TILE_REQUEST, {"frame_id": 9, "tile": tile})
    peak, started = 0.0, time.monotonic()
    while time.monotonic() - started < 60 and "the peer stopped reading" not in slave.log:
        peak = max(peak, rss_mib(slave.proc.pid))
        time.sleep(0.25)
    assert "the peer stopped reading" in slave.log, slave.log[-2000:]
    peer.close()
    assert peak - before < 64, (before, peak)
    assert slave.alive()
    real_render_works(slave.endpoint, scene, reference)


# -- case 3: idle and dribbling connections cannot lock honest masters out ---------------------
def test_idle_connections_cannot_lock_out_an_honest_master(slaves, scene, reference):
    slave = slaves[0]
    idle = [RawMaster(slave.endpoint) for _ in range(16)]   # handshaken, then silent
    try:
        # At once: every slot is taken by masters that were just active: "busy", with why.
        with pytest.raises(SlaveBusy, match="is busy: slave busy: 16 masters connected"):
            connect_slave(*slave.endpoint, secret=FARM_SECRET, identity=tls_peers.identity())
        started = time.monotonic()
        with Master([slave.endpoint]) as master:
            master.connect()           # asks again after back-off; an idle slot is freed
            assert time.monotonic() - started < 15
            master.load_scene(scene)
            images, _ = render_all(master.render(make_view(), tile_size=32))
        assert_images_equal(images, reference)
        evicted = []
        for peer in idle:
            try:
                evicted.append(peer.recv(wait=0.5).header.get("message", ""))
            except (OSError, ProtocolError):
                pass
        assert any("another master needs the slot" in m for m in evicted), evicted
    finally:
        for peer in idle:
            peer.close()


def test_heartbeating_connections_cannot_lock_out_an_honest_master(slaves, scene, reference):
    """Issue 39, finding 6: 16 admitted masters that send only HEARTBEAT every 2 s hold every
    slot; an honest master is admitted within 15 s all the same (a heartbeat keeps a
    connection open, not a slot: after EVICTABLE_AFTER_S of heartbeats alone a master gives
    its slot to one that comes to work), renders, and the heartbeaters are told why."""
    slave = slaves[1]
    stop = threading.Event()
    beaters = [RawMaster(slave.endpoint) for _ in range(16)]

    def beat():
        while not stop.wait(2.0):
            for peer in beaters:
                try:
                    peer.send(MsgType.HEARTBEAT)
                except (OSError, ProtocolError):
                    pass
    threading.Thread(target=beat, daemon=True).start()
    try:
        with pytest.raises(SlaveBusy, match="16 masters connected"):
            connect_slave(*slave.endpoint, secret=FARM_SECRET, identity=tls_peers.identity())
        started = time.monotonic()
        with Master([slave.endpoint]) as master:
            master.connect()           # asks again after back-off
            assert time.monotonic() - started < 15
            master.load_scene(scene)
            images, _ = render_all(master.render(make_view(), tile_size=32))
        assert_images_equal(images, reference)
        stop.set()
        told = []
        for peer in beaters:
            try:
                while (msg := peer.recv(wait=0.5)).type == MsgType.HEARTBEAT:
                    pass
                told.append(msg.header.get("message", ""))
            except (OSError, ProtocolError):
                pass
        assert any("another master needs the slot" in m for m in told), told
    finally:
        stop.set()
        for peer in beaters:
            peer.close()


def test_dribbled_handshakes_cannot_lock_out_an_honest_master(tmp_path, scene, reference):
    secret_file = tmp_path / "secret"
    secret_file.write_bytes(FARM_SECRET)
    slave = SlaveProcess("kdt-rel-secret", "--secret-file", str(secret_file))
    dribblers = []
    stop = threading.Event()

    def dribble(sock):
        data = message(MsgType.OPEN, {"padding": "x" * 40})
        for i in range(len(data)):
            if stop.wait(2.0):
                return
            try:
                sock.send(data[i:i + 1])
            except OSError:
                return

    try:
        for _ in range(40):      # more than the handshake pool: the oldest give way
            sock = socket.create_connection(slave.endpoint, timeout=10)
            dribblers.append(sock)
            threading.Thread(target=dribble, args=(sock,), daemon=True).start()
        time.sleep(1.0)
        started = time.monotonic()
        with Master([slave.endpoint]) as master:
            master.connect()
            assert time.monotonic() - started < 15
            master.load_scene(scene)
            images, _ = render_all(master.render(make_view(), tile_size=32))
        assert_images_equal(images, reference)
        # Each dribbler is cut off at the handshake deadline (10 s), not served byte by byte.
        time.sleep(max(0.0, 12 - (time.monotonic() - started)))
        for sock in dribblers[-16:]:
            sock.settimeout(2)
            reply = b""
            try:
                while chunk := sock.recv(65536):
                    reply += chunk
            except OSError:
                pass
            assert b"did not arrive in time" in reply or reply == b"", reply
        assert slave.alive()
    finally:
        stop.set()
        for sock in dribblers:
            sock.close()
        slave.stop()
    assert "Traceback" not in slave.log


# -- case 6: a frame is validated completely when it starts -----------------------------------
@pytest.mark.parametrize("change, reason", [
    (lambda v: v.shading.material_params.__setitem__((0, TEXTURE), 0.0),
     "uses texture 0, the geometry has 0"),
    (lambda v: v.shading.material_params.__setitem__((0, TEXTURE), 0.5), "not a whole number"),
    (lambda v: setattr(v.shading, "materials", v.shading.materials[:1]) or
     setattr(v.shading, "material_params", default_material_params(1)), "uses 2 materials"),
    (lambda v: v.camera.to_world.__setitem__((slice(0, 3), 2), 0.0), "view axis to zero"),
])
def test_bad_frame_is_refused_at_frame_start(slaves, scene, reference, change, reason):
    view = make_view()
    change(view)
    with pytest.raises(SceneError, match=reason):
        scene.check_view(view)
    peer = RawMaster(slaves[0].endpoint)
    try:
        reply = frame_reply(peer, scene, view, 11, tile_size=16)
        assert reply.type == MsgType.ERROR and reply.header["frame_id"] == 11
        assert reason.split(",")[0] in reply.header["message"], reply.header
    finally:
        peer.close()
    with Master([slaves[0].endpoint]) as master:   # the master checks it too
        master.connect()
        master.load_scene(scene)
        with pytest.raises(MasterError, match="the frame cannot be rendered"):
            master.render(view, tile_size=16)
        images, _ = render_all(master.render(make_view(), tile_size=32))
    assert_images_equal(images, reference)


# -- issue 39, finding 5: work within a budget ---------------------------------------------------
def heavy_view() -> View:
    """slow_view at 4096 samples per pixel with 16 shadow samples: 12.6 million camera samples
    in its one 64 x 48 tile, tens of seconds on a core here."""
    return slow_view(samples_per_axis=64)


def test_cancel_stops_a_heavy_tile_within_a_launch(slaves, scene, reference):
    """A tile of tens of seconds is rendering when CANCEL comes: the slave confirms within
    1 s (CANCEL_BOUND_S; it stops between two launches of about 20 ms, LAUNCH_SECONDS), sends
    nothing of the tile, and renders the next frame."""
    peer = RawMaster(slaves[0].endpoint)
    try:
        peer.hold(scene)
        peer.send(MsgType.FRAME_START, {"frame_id": 5, "scene_hash": scene.hash,
                                        "view": heavy_view().to_dict(), "tile_size": 64,
                                        "tile_height": 48})
        peer.send(MsgType.TILE_REQUEST, {"frame_id": 5, "tile": 0})
        deadline = time.monotonic() + 120      # the first build of this kernel may take long
        while True:
            beat = peer.recv(wait=30)
            assert beat.type == MsgType.HEARTBEAT, beat
            if beat.header.get("state") == "rendering":
                break
            assert time.monotonic() < deadline, "the tile never started rendering"
        time.sleep(1.0)
        sent = time.monotonic()
        peer.send(MsgType.CANCEL, {"frame_id": 5})
        while (msg := peer.recv(wait=30)).type == MsgType.HEARTBEAT:
            pass
        waited = time.monotonic() - sent
        assert msg.type == MsgType.CANCEL and msg.header["frame_id"] == 5, msg
        assert waited < CANCEL_BOUND_S, waited
    finally:
        peer.close()
    real_render_works(slaves[0].endpoint, scene, reference)


CANCEL_BOUND_S = 1.0


@pytest.mark.parametrize("change, words", [
    # 1024 x 1024 tiles of 4096 samples through 1033 path vertices: 2^50 rays a tile
    (lambda v: setattr(v.settings, "max_bounces", 1024), "tile may trace"),
    # 14 lights x 256 shadow samples at each of 2049 vertices: 7.3 million rays a sample
    (lambda v: (v.shading.lights.extend([v.shading.lights[0]] * 10),
                setattr(v.settings, "light_samples_per_axis", 16),
                setattr(v.settings, "max_bounces", 1024),
                setattr(v.settings, "transparent_bounces", 1024)), "one camera sample may trace"),
])
def test_an_over_budget_frame_is_refused_and_a_master_cuts_smaller_tiles(
        slaves, scene, reference, change, words, monkeypatch):
    """A frame whose tiles are over the work budget (protocol.MAX_TILE_RAYS, View.tile_rays:
    pixels x samples x shadow rays x path vertices, in Python integers) or whose camera sample
    is (MAX_SAMPLE_RAYS) is refused at FRAME_START with the numbers; the master cuts a
    frame's tiles smaller until they are within it, and refuses a sample over budget itself."""
    view = make_view(1024, 1024)
    view.settings = network_settings(samples_per_axis=64)
    change(view)
    peer = RawMaster(slaves[0].endpoint)
    try:
        reply = frame_reply(peer, scene, view, 3, tile_size=1024)
        assert reply.type == MsgType.ERROR and reply.header["frame_id"] == 3, reply
        assert "over the work budget" in reply.header["message"] and words in reply.header["message"]
        peer.send(MsgType.TILE_REQUEST, {"frame_id": 3, "tile": 0})     # ignored: no frame
        peer.send(MsgType.HEARTBEAT)
        with pytest.raises(socket.timeout):
            peer.recv(wait=1.0)
    finally:
        peer.close()
    from kdtrace.core.net.tiles import fit_tile_work
    if words == "tile may trace":
        w, h = fit_tile_work(view, 1024, protocol.MAX_TILE_RAYS, protocol.MAX_SAMPLE_RAYS)
        assert view.tile_rays(w, h) <= protocol.MAX_TILE_RAYS < view.tile_rays(2 * w, h)
    else:
        with pytest.raises(ValueError, match=words):
            fit_tile_work(view, 1024, protocol.MAX_TILE_RAYS, protocol.MAX_SAMPLE_RAYS)
    # A master splits: with a budget of a 16 x 16 tile of the test view, 64 x 48 tiles become
    # 16 x 12, and the image is the same.
    small = make_view()
    monkeypatch.setattr(protocol, "MAX_TILE_RAYS", small.tile_rays(16, 16))
    with Master([slaves[0].endpoint]) as master:
        master.connect()
        master.load_scene(scene)
        if words != "tile may trace":
            with pytest.raises(MasterError, match=words):
                master.render(view, tile_size=64)
        job = master.render(small, tile_size=(64, 48))
        images, _ = render_all(job)
        assert (job.tile_w, job.tile_h) == (16, 12)
    assert_images_equal(images, reference)


def test_uploads_in_progress_share_one_memory_budget(scene):
    """Large messages being received by all connections hold at most the slave's upload
    budget: a second upload that does not fit beside one in progress waits, then is refused
    ("slave busy: uploads in progress ..."); the budget comes back when an upload ends,
    whole or not, and a real upload goes through."""
    from kdtrace.slave.server import SlaveServer
    server = SlaveServer(_NoTracer(), "kdt-budget", bind="127.0.0.1", port=0,
                         secret=FARM_SECRET, upload_bytes=3 << 20)
    server.uploads.wait_s = 0.5
    server.start()
    big = message(MsgType.SCENE_UPLOAD, {"scene_hash": scene.hash},
                  {"vertices": np.zeros((200_000, 3), np.float32)})     # 2.3 MiB
    first = second = None
    try:
        first = RawMaster(server.address)
        first.send_bytes(big[:1 << 20])          # under way: holds its 2.3 MiB
        deadline = time.monotonic() + 10
        while server.uploads.used == 0:
            assert time.monotonic() < deadline
            time.sleep(0.02)
        assert server.uploads.used == len(big)
        second = RawMaster(server.address)
        second.send_bytes(big[:1 << 20])
        while (reply := second.recv()).type == MsgType.HEARTBEAT:
            pass
        assert reply.type == MsgType.ERROR, reply
        assert "slave busy: uploads in progress hold 2 of the 3 MiB" in reply.header["message"]
        first.close()                            # gone half-way: its share comes back
        deadline = time.monotonic() + 10
        while server.uploads.used:
            assert time.monotonic() < deadline, server.uploads.used
            time.sleep(0.02)
        third = RawMaster(server.address)
        third.hold(scene)                        # a real (small) upload
        third.close()
        assert server.uploads.used == 0
    finally:
        for peer in (first, second):
            if peer is not None:
                peer.close()
        server.close()


class _NoTracer:
    device_info = {"name": "none", "compute_units": 1, "memory": 0, "platform": "test"}
    build_seconds = 0.0


def test_a_slow_slave_is_dropped_at_its_upload_deadline_and_esc_stops_the_upload(
        slaves, scene, reference, monkeypatch):
    """A slave that takes longer than its upload deadline (UPLOAD_BASE_S + the bytes at
    UPLOAD_MIN_BPS) to make the scene present is dropped, named, and the frame renders on
    the others; alone, a load_scene whose `cancelled` says so (Esc) returns within a poll with
    LoadCancelled."""
    from kdtrace.core.net import master as master_module
    from kdtrace.core.net.master import LoadCancelled
    monkeypatch.setattr(master_module, "UPLOAD_BASE_S", 2.0)
    slow = FakeSlave("slowload")
    try:
        with Master([slaves[0].endpoint, slow.endpoint]) as master:
            master.connect()
            started = time.monotonic()
            master.load_scene(scene)
            assert time.monotonic() - started < 5
            assert any("did not take the scene within its upload deadline" in e
                       for e in master.errors), master.errors
            images, _ = render_all(master.render(make_view(), tile_size=32))
        assert_images_equal(images, reference)
        monkeypatch.setattr(master_module, "UPLOAD_BASE_S", 600.0)
        with Master([slow.endpoint]) as master:
            master.connect()
            started = time.monotonic()
            with pytest.raises(LoadCancelled):
                master.load_scene(scene, cancelled=lambda: time.monotonic() > started + 1.0)
            assert time.monotonic() - started < 2.0
            assert master.slave_states()[0].state == "lost"
    finally:
        slow.close()


# -- case 7: after the handshake, every byte is authenticated (TLS) ----------------------------
class Splicer(LoopbackServer):
    """A TCP proxy between a master and a slave that passes the plaintext OPEN messages, then
    follows the TLS records and can inject a forged record or replay a real one: `action(
    direction, record)` returns the bytes to forward in place of `record` (a whole TLS record,
    header included)."""

    def __init__(self, target, action):
        self.target, self.action = target, action
        super().__init__()

    def serve(self, client):
        server = socket.create_connection(self.target)
        self.sockets.append(server)
        threading.Thread(target=self._pump, args=(server, client, "S>M"), daemon=True).start()
        self._pump(client, server, "M>S")

    def _pump(self, source, sink, direction):
        try:
            head = protocol._recv_exactly(source, HEADER.size, "header")   # OPEN
            sink.sendall(head + protocol._recv_exactly(source, HEADER.unpack(head)[3], "JSON"))
            while True:
                head = protocol._recv_exactly(source, 5, "record header", allow_eof=True)
                data = bytes(head + protocol._recv_exactly(
                    source, int.from_bytes(head[3:5], "big"), "record"))
                sink.sendall(self.action(direction, data))
        except (OSError, ProtocolError):
            for sock in (source, sink):
                try:
                    sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass


def test_injected_or_replayed_records_after_the_handshake_are_refused(tmp_path, scene, reference):
    slave = SlaveProcess("kdt-rel-mac")
    done = set()

    def once(what, change):
        def act(direction, record):
            # The first full-size record from the master is the scene upload's.
            if direction == "M>S" and len(record) >= 16384 and what not in done:
                done.add(what)
                return change(record)
            return record
        return act
    forged = bytes([23, 3, 3, 1, 0]) + os.urandom(256)
    actions = {   # the slave has not seen the scene yet: each case starts an upload
        "inject to the slave": once("inject", lambda record: record + forged),
        "replay to the slave": once("replay", lambda record: record + record),
        "flip a bit": once("flip", lambda record: record[:100] + bytes([record[100] ^ 1])
                           + record[101:]),
        "pass": lambda direction, record: record,
    }
    try:
        for what, action in actions.items():
            splicer = Splicer(slave.endpoint, action)
            try:
                with Master([splicer.endpoint], retry_delays=()) as master:
                    master.connect()
                    if what == "pass":      # the proxy itself changes nothing
                        master.load_scene(scene)
                        images, _ = render_all(master.render(make_view(), tile_size=32))
                        assert_images_equal(images, reference)
                        continue
                    with pytest.raises(MasterError, match="no slave could load the scene"):
                        master.load_scene(scene)
            finally:
                splicer.close()
        time.sleep(0.5)
        assert slave.log.count("TLS refused what arrived") == 3, slave.log
        assert "SCENE_READY" not in slave.log and slave.alive()
        with Master([slave.endpoint]) as master:
            master.connect()
            master.load_scene(scene)
            images, _ = render_all(master.render(make_view(), tile_size=32))
        assert_images_equal(images, reference)
    finally:
        slave.stop()
