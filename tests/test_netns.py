"""Multi-host tests: every slave in a Linux network namespace of its own ("a host"), joined by a
bridge in the root namespace (one veth pair per host); the master runs in this process in the
root namespace. zeroconf multicast crosses the bridge. Needs root and iproute2 (`ip`); CI runs
as root. Names are unique per run and everything is removed in the fixture's finally.
"""
from __future__ import annotations

import os
import random
import re
import shutil
import subprocess
import sys
import time
import uuid

import numpy as np
import pytest

from kdtrace.core.net import protocol
from kdtrace.core.net.discovery import SlaveBrowser
from kdtrace.core.net.master import Master, MasterError
from kdtrace.core.net.protocol import HEADER, MAGIC, MsgType
from kdtrace.core.net.trust import new_farm_secret
from kdtrace.core.scene.scene import Scene
from tests.conftest import FARM_SECRET
from tests.processes import ChildProcess
from tests.test_network import (assert_images_equal, make_scene, make_view, raw_exchange,
                                render_all)
from tests.tls_peers import tls_exchange

pytestmark = pytest.mark.skipif(
    os.geteuid() != 0 or shutil.which("ip") is None,
    reason="network-namespace tests need root and iproute2's `ip` (CI runs them as root)")

PORT = 47600


def ip(*args, check=True):
    return subprocess.run(["ip", *args], check=check, capture_output=True, text=True, timeout=30)


class Lan:
    """A bridge with one namespace per host: host i has address 10.<net>.0.<i + 2>."""

    def __init__(self, hosts: int):
        tag = uuid.uuid4().hex[:6]
        self.net = random.randint(100, 250)
        self.bridge = f"kdbr{tag}"
        self.master_ip = f"10.{self.net}.0.1"
        self.namespaces, self.addresses = [], []
        try:
            ip("link", "add", self.bridge, "type", "bridge")
            ip("addr", "add", f"{self.master_ip}/24", "dev", self.bridge)
            ip("link", "set", self.bridge, "up")
            for i in range(hosts):
                ns, root_end = f"kdt{tag}h{i}", f"kdv{tag}{i}"
                ip("netns", "add", ns)
                self.namespaces.append(ns)
                ip("link", "add", root_end, "type", "veth", "peer", "name", "eth0", "netns", ns)
                ip("link", "set", root_end, "master", self.bridge)
                ip("link", "set", root_end, "up")
                address = f"10.{self.net}.0.{i + 2}"
                ip("-n", ns, "addr", "add", f"{address}/24", "dev", "eth0")
                ip("-n", ns, "link", "set", "eth0", "up")
                ip("-n", ns, "link", "set", "lo", "up")
                self.addresses.append(address)
        except BaseException:
            self.close()
            raise

    def close(self):
        for ns in self.namespaces:   # deleting a namespace deletes its veth pair
            ip("netns", "del", ns, check=False)
        ip("link", "del", self.bridge, check=False)


def HostProcess(ns: str, argv: list, env: dict | None = None) -> ChildProcess:
    """A process inside a host namespace; `ip netns exec` execs, so our pid is its pid."""
    return ChildProcess(argv, wrapper=("ip", "netns", "exec", ns), env=env)


def start_slave(lan: Lan, host: int, name: str, *extra, port=PORT, env=None) -> HostProcess:
    address = lan.addresses[host]
    slave = HostProcess(lan.namespaces[host], ["-m", "kdtrace.slave", "--bind", address,
                                               "--port", str(port), "--name", name, *extra],
                        env=env)
    line = slave.wait_line(f"KD Trace slave {name} listening on {address}:{port}")
    slave.name, slave.endpoint = name, (address, port)
    slave.id = line.split(" id ")[1].split()[0]
    return slave


# A stand-in slave that handshakes correctly (TLS, the tests' farm secret, which it inherits)
# and then misbehaves. Run with `python -c`.
FAKE_SLAVE = r"""
import os, socket, sys, threading, time
import numpy
from kdtrace.core.net import protocol
from kdtrace.core.net.protocol import MsgType, HEADER, MAGIC
from tests.tls_peers import serve_as_slave
mode, host, port = sys.argv[1], sys.argv[2], int(sys.argv[3])

def serve(sock):
    if mode == "newer":           # answers the opening as a slave of the next version would
        sock.recv(65536)
        text = b'{"message":"hello from the future"}'
        sock.sendall(HEADER.pack(MAGIC, protocol.PROTOCOL_VERSION + 1, MsgType.ERROR, len(text), 0) + text)
        time.sleep(5); return
    channel, _ = serve_as_slave(sock, "fake-" + mode)
    frame = None
    while True:
        msg = channel.recv(protocol.Limits())
        if msg.type == MsgType.SCENE_QUERY:
            channel.send(MsgType.SCENE_READY, {"scene_hash": msg.header["scene_hash"], "present": True})
        elif msg.type == MsgType.FRAME_START:
            frame = msg.header
        elif msg.type == MsgType.TILE_REQUEST:
            if mode == "hang":
                continue              # reads on, answers nothing, never closes
            if mode == "garbage":
                channel.send_bytes(os.urandom(4096)); continue
            w, h = frame["tile_size"], frame.get("tile_height", frame["tile_size"])
            if mode == "half":        # half a valid TILE_RESULT, then silence (connection open)
                zeros = {"combined": numpy.zeros((h, w, 4), "f4"), "depth": numpy.zeros((h, w), "f4"),
                         "normal": numpy.zeros((h, w, 3), "f4")}
                data = b"".join(bytes(b) for b in protocol.encode_message(MsgType.TILE_RESULT,
                    {"frame_id": frame["frame_id"], "tile": msg.header["tile"]}, zeros))
                channel.send_bytes(data[:len(data) // 2])
                while True:           # reads on, sends nothing more, never closes
                    try:
                        if not channel._read(lambda: channel.sock.recv(65536)):
                            return
                    except socket.timeout:
                        pass
            bad = {"combined": numpy.full((h, w, 4), float("nan"), "f4"),
                   "depth": numpy.zeros((h, w), "f4"), "normal": numpy.zeros((h, w, 3), "f4")}
            tile = msg.header["tile"] if mode == "nan" else msg.header["tile"] + 1
            channel.send(MsgType.TILE_RESULT, {"frame_id": frame["frame_id"],
                "tile": tile, "x": 0, "y": 0, "w": w, "h": h, "render_ms": 1.0}, bad)
        elif msg.type == MsgType.BYE:
            return

def guarded(sock):
    try:
        serve(sock)
    except Exception:
        pass

listener = socket.create_server((host, port))
print("fake slave ready", flush=True)
while True:
    conn, _ = listener.accept()
    threading.Thread(target=guarded, args=(conn,), daemon=True).start()
"""


def start_fake(lan: Lan, host: int, mode: str, port: int) -> HostProcess:
    fake = HostProcess(lan.namespaces[host], ["-c", FAKE_SLAVE, mode, lan.addresses[host], str(port)])
    fake.wait_line("fake slave ready")
    fake.endpoint = (lan.addresses[host], port)
    return fake


@pytest.fixture(scope="module")
def lan():
    network = Lan(4)
    try:
        yield network
    finally:
        network.close()


@pytest.fixture(scope="module")
def slaves(lan):
    started = []
    try:
        for i in range(3):
            started.append(start_slave(lan, i, f"kdt-host-{i}"))
        yield started
    finally:
        for slave in started:
            slave.stop()
    for slave in started:
        assert "Traceback" not in slave.log and "unexpected error" not in slave.log, slave.log


@pytest.fixture(scope="module")
def scene():
    return make_scene()


@pytest.fixture(scope="module")
def one_slave_image(slaves, scene):
    """The reference: the whole frame rendered by one slave over the LAN."""
    with Master([slaves[0].endpoint]) as master:
        master.connect()
        master.load_scene(Scene.from_parts(*scene))
        images, _ = render_all(master.render(make_view(), tile_size=16))
    return images


def test_namespaces_are_separate_hosts(lan):
    out = ip("-n", lan.namespaces[0], "-4", "-o", "addr", "show").stdout
    assert lan.addresses[0] in out and lan.addresses[1] not in out


def test_discovery_of_several_slaves_across_hosts(lan, slaves):
    wanted = {s.name: s.endpoint for s in slaves}
    browser = SlaveBrowser(interfaces=[lan.master_ip])
    try:
        deadline = time.monotonic() + 15
        found = {}
        while set(found) != set(wanted) and time.monotonic() < deadline:
            found = {s.name: s.endpoint for s in browser.slaves() if s.name in wanted}
            time.sleep(0.2)
    finally:
        browser.close()
    assert found == wanted


def test_render_across_hosts_equals_one_slave(slaves, scene, one_slave_image):
    with Master([s.endpoint for s in slaves]) as master:
        master.connect()
        master.load_scene(Scene.from_parts(*scene))
        for model in ("3b", "3a"):
            job = master.render(make_view(), partition=4, model=model)
            images, results = render_all(job)
            assert job.error is None and job.errors == []
            assert len(results) == 16
            assert_images_equal(images, one_slave_image)
        # float16 + zlib: close to float32, depth exact.
        images, _ = render_all(master.render(make_view(), tile_size=16, payload="f16", compress=True))
        np.testing.assert_array_equal(images["depth"], one_slave_image["depth"])
        assert np.abs(images["combined"] - one_slave_image["combined"]).max() < 2e-3


def test_slave_killed_at_random_moments(lan, slaves, scene, one_slave_image):
    seed = random.randrange(1 << 30)
    rng = random.Random(seed)
    for attempt, port in enumerate((47611, 47612, 47613)):
        victim = start_slave(lan, 3, f"kdt-victim-{attempt}", port=port)
        try:
            with Master([slaves[0].endpoint, slaves[1].endpoint, victim.endpoint]) as master:
                master.connect()
                master.load_scene(Scene.from_parts(*scene))
                job = master.render(make_view(), tile_size=4)   # 192 tiles
                kill_at = time.monotonic() + rng.uniform(0.0, 0.6)
                images = {k: np.full_like(v, np.nan) for k, v in one_slave_image.items()}
                deadline = time.monotonic() + 60
                while not job.finished:
                    assert time.monotonic() < deadline, "frame did not finish"
                    if victim.alive() and time.monotonic() >= kill_at:
                        victim.kill()
                    result = job.next_result(0.02)
                    if result is not None:
                        for name, image in images.items():
                            image[result.y:result.y + result.h, result.x:result.x + result.w] = result.passes[name]
                victim.kill()
                assert job.error is None, (seed, job.error)
                assert job.progress == (192, 192)
            assert_images_equal(images, one_slave_image)
        finally:
            victim.stop()


@pytest.mark.parametrize("duplicates", [True, False])
def test_slave_that_hangs_without_closing(lan, slaves, scene, one_slave_image, duplicates):
    fake = start_fake(lan, 3, "hang", 47620 + duplicates)
    try:
        with Master([slaves[0].endpoint, fake.endpoint], silence_timeout=2.0,
                    heartbeat_s=0.5) as master:
            master.connect()
            master.load_scene(Scene.from_parts(*scene))
            start = time.monotonic()
            job = master.render(make_view(), tile_size=16, duplicates=duplicates)
            images, _ = render_all(job, timeout=30)
            assert job.error is None and job.progress == (12, 12)
            assert time.monotonic() - start < 15
            assert job.wait(10)
            assert any("fake-hang" in e and "did not answer" in e
                       for e in job.errors), job.errors
        assert_images_equal(images, one_slave_image)
    finally:
        fake.stop()


# badindex answers each request with the next tile's index at the first tile's rectangle.
@pytest.mark.parametrize("mode, reason", [
    ("garbage", "not a KD Trace message"), ("nan", "NaN"),
    ("badindex", "which was not asked of it|has the wrong rectangle|'tile' must be an integer")])
def test_slave_that_returns_garbage(lan, slaves, scene, one_slave_image, mode, reason):
    fake = start_fake(lan, 3, mode, 47630 + len(mode))
    try:
        with Master([fake.endpoint, slaves[1].endpoint]) as master:
            master.connect()
            master.load_scene(Scene.from_parts(*scene))
            job = master.render(make_view(), tile_size=16)
            images, _ = render_all(job, timeout=30)
            assert job.error is None and job.progress == (12, 12)
            assert any(f"fake-{mode}" in e and re.search(reason, e) for e in job.errors), job.errors
        assert_images_equal(images, one_slave_image)
    finally:
        fake.stop()


def test_bad_frames_to_a_slave_then_a_real_master(slaves, scene, one_slave_image):
    host, port = slaves[2].endpoint

    def exchange(data: bytes) -> bytes:
        return raw_exchange((host, port), data, half_close=True)

    assert b"not a KD Trace message" in exchange(os.urandom(512))
    # Truncated header, then a truncated JSON body: the slave says why and closes.
    assert b"in the middle of a message" in exchange(
        HEADER.pack(MAGIC, protocol.PROTOCOL_VERSION, MsgType.OPEN, 40, 0)[:9])
    assert b"in the middle of a message" in exchange(
        HEADER.pack(MAGIC, protocol.PROTOCOL_VERSION, MsgType.OPEN, 40, 0) + b'{"proto')
    assert b"exceeds" in exchange(HEADER.pack(MAGIC, protocol.PROTOCOL_VERSION, MsgType.OPEN,
                                              1 << 30, 1 << 40))
    # Inside TLS: a header past the limits is refused at once; a message that stops half
    # way (the connection left open) at its deadline, with why.
    assert b"exceeds" in tls_exchange((host, port), HEADER.pack(
        MAGIC, protocol.PROTOCOL_VERSION, MsgType.SCENE_QUERY, 1 << 30, 1 << 40))
    started = time.monotonic()
    reply = tls_exchange((host, port), HEADER.pack(
        MAGIC, protocol.PROTOCOL_VERSION, MsgType.SCENE_QUERY, 40, 0) + b'{"proto', timeout=20)
    assert b"message arrived too slowly" in reply, reply[-300:]
    assert time.monotonic() - started < 20
    with Master([slaves[2].endpoint]) as master:
        master.connect()
        master.load_scene(Scene.from_parts(*scene))
        images, _ = render_all(master.render(make_view(), tile_size=16))
    assert_images_equal(images, one_slave_image)


def test_farm_secret(lan, scene, one_slave_image, tmp_path):
    """Across hosts: the farm secret admits a master; another secret, none, or a HELLO that
    skips its proof and sends scene data anyway gets nothing but a refusal, and never a proof
    from the slave (the master proves first)."""
    secret_file = tmp_path / "secret"
    secret_file.write_bytes(FARM_SECRET)
    slave = start_slave(lan, 3, "kdt-secret", "--secret-file", str(secret_file), port=47640,
                        env={"KDTRACE_SECRET": None})
    open_slave = start_slave(lan, 3, "kdt-open", port=47641, env={"KDTRACE_SECRET": None})
    try:
        with Master([slave.endpoint], secret=FARM_SECRET) as master:
            master.connect()
            assert master.slaves[0].trusted_by == "farm secret"
            master.load_scene(Scene.from_parts(*scene))
            images, _ = render_all(master.render(make_view(), tile_size=16))
        assert_images_equal(images, one_slave_image)
        with pytest.raises(MasterError, match="authentication failed: wrong farm secret"):
            Master([slave.endpoint], secret=new_farm_secret()).connect()
        with pytest.raises(MasterError, match=r"ID [A-Z2-7-]{19}\) is not approved: this master has no farm secret"):
            Master([slave.endpoint], secret=None).connect()
        with pytest.raises(MasterError, match="does not serve master ID"):
            Master([open_slave.endpoint], secret=FARM_SECRET).connect()
        # A master that skips the proof and sends scene data anyway is refused before it is read.
        query = protocol.encode_message(MsgType.SCENE_QUERY, {"scene_hash": "0" * 32})[0]
        reply = tls_exchange(slave.endpoint, query, secret=None)
        assert b"does not serve master ID" in reply and b"SCENE_READY" not in reply
        # A master that proves a wrong secret: refused, and no WELCOME (no slave proof) at all.
        reply = tls_exchange(slave.endpoint, query, proof="0" * 64)
        assert b"authentication failed: wrong farm secret" in reply
        assert b"SCENE_READY" not in reply and b"WELCOME" not in reply and b'"proof"' not in reply
        assert slave.alive()
        time.sleep(0.3)
        assert "wrong farm secret" in slave.log and "does not serve master ID" in slave.log
        assert "Traceback" not in slave.log
    finally:
        slave.stop()
        open_slave.stop()


def test_version_mismatch_reported_by_name_on_both_sides(lan, slaves):
    newer = protocol.PROTOCOL_VERSION + 1
    text = raw_exchange(slaves[0].endpoint, HEADER.pack(MAGIC, newer, MsgType.HELLO, 2, 0) + b"{}")
    assert (f"protocol version mismatch: master speaks version {newer}, slave speaks version "
            f"{protocol.PROTOCOL_VERSION}").encode() in text
    fake = start_fake(lan, 3, "newer", 47650)
    try:
        with pytest.raises(MasterError, match=f"protocol version mismatch: slave speaks version "
                                              f"{newer}, master speaks version {protocol.PROTOCOL_VERSION}"):
            Master([fake.endpoint]).connect()
    finally:
        fake.stop()


def test_a_slave_that_trusts_nobody_yet_tells_its_owner_how_to_pair(lan, slaves):
    """The slaves of this module (farm secret) say whom they serve and show no pairing code;
    a first start with no secret and no allowed master shows one code and how to pair, and
    serves nobody else (its port is open, its scenes and device are not)."""
    for slave in slaves:
        assert "serves masters that prove the farm secret" in slave.log, slave.log
        assert "pairing code" not in slave.log
    fresh = start_slave(lan, 3, "kdt-fresh", port=47660,
                        env={"KDTRACE_SECRET": None, "KDTRACE_SLAVE_HOME": None,
                             "XDG_CONFIG_HOME": str(lan_home(lan))})
    try:
        time.sleep(0.5)
        assert fresh.log.count("enter the pairing code") == 1, fresh.log
        assert f"click Pair beside kdt-fresh (ID {fresh.id[:4]}-" in fresh.log
        assert "--allow MASTER-ID" in fresh.log and "--new-secret FILE" in fresh.log
        with pytest.raises(MasterError, match="does not serve master ID"):
            Master([fresh.endpoint], secret=FARM_SECRET).connect()
    finally:
        fresh.stop()


def lan_home(lan) -> str:
    """A configuration folder of its own for a slave of this LAN (its identity goes there)."""
    import tempfile
    return tempfile.mkdtemp(prefix=f"kdtrace-{lan.bridge}-")


def test_half_a_tile_then_silence_across_hosts(lan, slaves, scene, one_slave_image):
    """A slave on another host that stops in the middle of a TILE_RESULT: the master drops it
    within the message deadline, names it, and the others finish the frame."""
    fake = start_fake(lan, 3, "half", 47670)
    try:
        with Master([fake.endpoint, slaves[1].endpoint], silence_timeout=1.0,
                    heartbeat_s=0.25, retry_delays=(0.2,)) as master:
            master.connect()
            master.load_scene(Scene.from_parts(*scene))
            started = time.monotonic()
            job = master.render(make_view(), tile_size=16)
            images, _ = render_all(job, timeout=30)
            assert job.error is None and job.progress == (12, 12)
            assert job.wait(10) and time.monotonic() - started < 15
            assert any("fake-half" in e and "arrived too slowly" in e for e in job.errors), job.errors
        assert_images_equal(images, one_slave_image)
    finally:
        fake.stop()
