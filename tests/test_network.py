"""The network runtime end to end: real `python -m kdtrace.slave` processes on 127.0.0.1, the real
Tracer and build_kdtree, discovery over zeroconf on loopback, and a misbehaving master."""
from __future__ import annotations

import math
import os
import queue
import re
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from kdtrace.core.net import protocol
from kdtrace.core.net.discovery import SlaveBrowser, browse_slaves
from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.net.master import Master, MasterError
from kdtrace.core.net.protocol import HEADER, MAGIC, MsgType
from kdtrace.core.scene.model import Camera, Geometry, Light, RenderSettings, Shading, View
from kdtrace.core.scene.scene import Scene
from tests.conftest import ROOT
from tests.meshes import grid_plane, merge, uv_sphere
from tests.processes import SlaveProcess
from tests.tls_peers import tls_exchange


@pytest.fixture(scope="module")
def slaves():
    started = []
    try:
        # Names unique to this run: zeroconf would report another run's slaves of the same name.
        for name in (f"kdt-test-a-{os.getpid()}", f"kdt-test-b-{os.getpid()}"):
            started.append(SlaveProcess(name))
        yield started
    finally:
        for slave in started:
            slave.stop()
    # Every misbehaving master was handled: logged, never an unexpected exception; and on
    # loopback there was nothing to warn about.
    for slave in started:
        log = slave.log
        assert "Traceback" not in log and "unexpected error" not in log, log


def make_scene(sphere_center=(0.0, 0.0, 1.0)):
    sphere = uv_sphere(24, 12, 1.0, sphere_center)
    vertices, triangles = merge(sphere, grid_plane(8.0, 8, 0.0))
    material_ids = np.r_[np.zeros(len(sphere[1])), np.ones(128)].astype(np.uint16)
    geometry = Geometry(vertices, triangles, material_ids)
    return geometry, build_kdtree(geometry.vertices, geometry.triangles)


def network_settings(samples_per_axis=1, light_samples_per_axis=2) -> RenderSettings:
    """Uniform sampling (never adaptive: its pixels depend on the tiling), direct light plus
    mirror bounces: cheap frames whose pixels are the same in every tiling, so a tiled render
    must equal the one-piece render bit for bit."""
    return RenderSettings(samples_per_axis=samples_per_axis, adaptive=False, max_bounces=8,
                          diffuse_bounces=0, light_samples_per_axis=light_samples_per_axis)


def make_view(width=64, height=48, region=None):
    m = np.eye(4)
    m[:3, 3] = (0, -6, 3)
    angle = math.radians(65)
    m[:3, :3] = [[1, 0, 0], [0, math.cos(angle), -math.sin(angle)],
                 [0, math.sin(angle), math.cos(angle)]]
    lights = [Light("POINT", (1, 1, 1), 500.0, (2, -2, 4)),
              Light("SUN", (1, 0.9, 0.8), 2.0, direction=(-0.3, 0.2, -1))]
    shading = Shading(np.array([[0.8, 0.2, 0.2, 1], [0.7, 0.7, 0.7, 1]], np.float32), lights,
                      (0.05, 0.05, 0.05))
    return View(Camera("PERSP", m, (0.6, 0.45), (0.05, 0), 0.1, 100), width, height, shading, region,
                network_settings())


def render_all(job, timeout=60.0):
    """Collect every tile of `job` into full-size images (NaN where no tile came)."""
    view = job.view
    images = {"combined": np.full((view.height, view.width, 4), np.nan, np.float32),
              "depth": np.full((view.height, view.width), np.nan, np.float32),
              "normal": np.full((view.height, view.width, 3), np.nan, np.float32)}
    results, deadline = [], time.monotonic() + timeout
    while not job.finished:
        assert time.monotonic() < deadline, "render did not finish in time"
        result = job.next_result(0.1)
        if result is not None:
            results.append(result)
            for name, image in images.items():
                image[result.y:result.y + result.h, result.x:result.x + result.w] = result.passes[name]
    return images, results


@pytest.fixture(scope="module")
def reference():
    """The full image from the real Tracer in this process."""
    from kdtrace.slave.tracer import Tracer
    geometry, tree = make_scene()
    tracer = Tracer()
    tracer.load(Scene.from_parts(geometry, tree))
    view = make_view()
    return tracer.render_tile(view, 0, 0, view.width, view.height)


def assert_images_equal(images, expected):
    for name in ("combined", "depth", "normal"):
        np.testing.assert_array_equal(images[name], expected[name], err_msg=name)


# -- discovery --------------------------------------------------------------------------------
def test_slave_browser_reports_both_slaves_as_events(slaves):
    wanted = {s.name: s.port for s in slaves}
    browser = SlaveBrowser(interfaces=["127.0.0.1"])
    seen = {}
    try:
        deadline = time.monotonic() + 10
        while set(seen) != set(wanted) and time.monotonic() < deadline:
            try:
                event = browser.events.get(timeout=0.2)  # what a bpy.app.timers function drains
            except queue.Empty:
                continue
            if event.kind == "added" and event.name in wanted:
                seen[event.name] = event.info.port
        assert seen == wanted
        assert {s.name for s in browser.slaves()} >= set(wanted)
    finally:
        browser.close()


def test_discovery_finds_both_slaves_on_loopback(slaves):
    wanted = {s.name: s.port for s in slaves}
    found = {}
    for _ in range(3):  # mDNS answers may take a moment after start-up
        found.update({s.name: s for s in browse_slaves(2.0, interfaces=["127.0.0.1"])
                      if s.name in wanted})
        if len(found) == len(wanted):
            break
    assert sorted(found) == sorted(wanted)
    for name, info in found.items():
        assert (info.host, info.port) == ("127.0.0.1", wanted[name])
        assert info.properties["protocol"] == str(protocol.PROTOCOL_VERSION)
        assert info.properties["name"] == name
        assert info.properties["device"] and int(info.properties["compute_units"]) >= 1
        assert int(info.properties["memory"]) > 0


# -- rendering --------------------------------------------------------------------------------
def test_two_slaves_render_the_same_pixels_as_one_and_as_the_tracer(slaves, reference):
    geometry, tree = make_scene()
    view = make_view()
    with Master([s.endpoint for s in slaves], name="test") as master:
        master.connect()
        assert sorted(c.name for c in master.slaves) == sorted(s.name for s in slaves)
        assert all(c.device and c.compute_units >= 1 and c.memory > 0 for c in master.slaves)
        master.load_scene(Scene.from_parts(geometry, tree))
        job = master.render(view, tile_size=16)
        two, results = render_all(job)
        assert job.error is None and job.errors == []
        assert sorted(r.index for r in results) == list(range(len(job.tiles))) == list(range(12))
        assert all(r.render_ms >= 0 and r.slave_id for r in results)
        # Which slave renders how many is dynamic (a slave still compiling its kernel may lose
        # all its tiles to duplicates); every tile is delivered once.
        assert sum(job.tiles_by_slave.values()) == len(job.tiles), job.tiles_by_slave
    with Master([slaves[0].endpoint]) as master:
        master.connect()
        master.load_scene(Scene.from_parts(geometry, tree))
        one, _ = render_all(master.render(view, tile_size=16))
    assert_images_equal(two, one)
    assert_images_equal(two, reference)


def test_compressed_kdtree_renders_the_same_pixels_over_the_network(slaves, reference):
    """Mode "compressed" (triangle references in inner nodes, 2-byte leaves) travels to real slaves,
    gets its own scene hash (another upload), and renders what the standard tree renders."""
    from kdtrace.core.accel.compact import compact_tree
    geometry, tree = make_scene()
    ours = compact_tree(tree, geometry.triangle_count, "compressed")
    assert ours.stats["inner_references"] > 0 and ours.stats["leaves_16bit"] > 0
    view = make_view()
    with Master([s.endpoint for s in slaves]) as master:
        master.connect()
        standard_hash = Scene.from_parts(geometry, tree).hash
        ours_hash = master.load_scene(Scene.from_parts(geometry, ours))
        assert ours_hash != standard_hash
        images, _ = render_all(master.render(view, tile_size=16))
    assert_images_equal(images, reference)


def test_render_border_region_and_odd_tile_size(slaves, reference):
    geometry, tree = make_scene()
    view = make_view(region=(5, 7, 50, 40))
    with Master([s.endpoint for s in slaves]) as master:
        master.connect()
        master.load_scene(Scene.from_parts(geometry, tree))
        images, results = render_all(master.render(view, tile_size=13, tiles_in_flight=1))
    assert {(r.x, r.y) for r in results} >= {(5, 7), (44, 33)}
    for name in images:
        np.testing.assert_array_equal(images[name][7:40, 5:50], reference[name][7:40, 5:50])
        assert np.isnan(images[name][:7]).all() and np.isnan(images[name][:, :5]).all()


def test_scene_is_uploaded_once_per_hash(slaves):
    geometry, tree = make_scene(sphere_center=(0.5, 0.25, 1.0))  # a scene no slave has seen
    with Master([s.endpoint for s in slaves]) as master:
        master.connect()
        master.load_scene(Scene.from_parts(geometry, tree))
        assert len(master.uploaded_to) == 2
        first, _ = render_all(master.render(make_view(), tile_size=32))
        master.load_scene(Scene.from_parts(geometry, tree))  # same master again: nothing to send
        assert master.uploaded_to == []
    with Master([s.endpoint for s in slaves]) as master:  # a new session
        master.connect()
        master.load_scene(Scene.from_parts(geometry, tree))
        assert master.uploaded_to == []
        second, _ = render_all(master.render(make_view(), tile_size=32))
    assert_images_equal(first, second)


def test_cancel_mid_frame_reaches_every_slave(slaves, reference):
    geometry, tree = make_scene()
    view = make_view(128, 96)
    with Master([s.endpoint for s in slaves]) as master:
        master.connect()
        master.load_scene(Scene.from_parts(geometry, tree))
        job = master.render(view, tile_size=4)   # 768 tiny tiles
        assert job.next_result(30) is not None
        job.cancel()
        assert job.cancelled and job.over
        assert job.wait(15), "slaves did not confirm the cancel"
        while not job.finished:
            job.next_result(0.1)
        done, total = job.progress
        assert done < total
        # Every slave confirmed (none was dropped) and the connections are still usable.
        assert job.errors == [] and len(master.slaves) == 2
        images, _ = render_all(master.render(make_view(), tile_size=16))
    assert_images_equal(images, reference)


def test_frame_completes_when_a_slave_is_killed(slaves, reference):
    victim = SlaveProcess("kdt-test-victim")
    try:
        geometry, tree = make_scene()
        view = make_view()
        with Master([slaves[0].endpoint, victim.endpoint]) as master:
            master.connect()
            master.load_scene(Scene.from_parts(geometry, tree))
            job = master.render(view, tile_size=4)    # 192 tiles
            victim_label = f"{victim.name} (127.0.0.1:{victim.port})"
            images = {"combined": np.zeros((48, 64, 4), np.float32),
                      "depth": np.zeros((48, 64), np.float32),
                      "normal": np.zeros((48, 64, 3), np.float32)}
            deadline = time.monotonic() + 60
            while not job.finished:
                assert time.monotonic() < deadline
                # Killed while it holds tiles: once it renders (it says so in its heartbeats)
                # or has delivered a tile, whichever is seen first.
                rendering = any(s.name == victim.name and s.state == "rendering"
                                for s in master.slave_states())
                if victim.alive() and (rendering or job.tiles_by_slave.get(victim_label)):
                    victim.kill()
                result = job.next_result(0.02)
                if result is None:
                    continue
                for name, image in images.items():
                    image[result.y:result.y + result.h, result.x:result.x + result.w] = result.passes[name]
            assert not victim.alive()
            assert job.error is None
            assert any(victim.name in e for e in job.errors), job.errors
            assert job.progress == (192, 192)
        assert_images_equal(images, reference)
    finally:
        victim.stop()


def test_job_fails_clearly_when_every_slave_is_lost(slaves):
    victim = SlaveProcess("kdt-test-lonely")
    try:
        geometry, tree = make_scene()
        with Master([victim.endpoint], retry_delays=(0.2, 0.4)) as master:
            master.connect()
            master.load_scene(Scene.from_parts(geometry, tree))
            job = master.render(make_view(128, 96), tile_size=4)
            assert job.next_result(30) is not None
            victim.kill()
            deadline = time.monotonic() + 30
            while not job.finished:
                assert time.monotonic() < deadline
                job.next_result(0.1)
            # Only after the reconnection attempts, with each slave and why.
            assert job.error and job.error.startswith("all slaves lost")
            assert re.search(r"slave kdt-test-lonely \(.*\) lost: (disconnected|connection lost)",
                             job.error), job.error
            assert f"reconnecting to 127.0.0.1:{victim.port} failed: cannot reach" in job.error
            assert "connection refused" in job.error
            with pytest.raises(MasterError, match="no slaves connected"):
                master.render(make_view(), tile_size=16)
    finally:
        victim.stop()


# -- misbehaving peers --------------------------------------------------------------------------
def raw_exchange(endpoint, data: bytes, read=True, half_close=False) -> bytes:
    """Send raw bytes to a slave and read what it answers until it closes. half_close ends the
    stream after `data`, whatever the frame header promised."""
    if isinstance(endpoint, int):
        endpoint = ("127.0.0.1", endpoint)
    with socket.create_connection(endpoint, timeout=10) as sock:
        sock.sendall(data)
        if half_close:
            sock.shutdown(socket.SHUT_WR)
        if not read:
            return b""
        chunks = []
        try:
            while chunk := sock.recv(65536):
                chunks.append(chunk)
        except (ConnectionResetError, TimeoutError):
            pass
        return b"".join(chunks)


def test_garbage_never_crashes_a_slave(slaves, reference):
    port = slaves[0].port
    # Not our protocol at all: the slave answers with an ERROR (in plaintext: TLS has not
    # begun) and closes.
    reply = raw_exchange(port, b"GET / HTTP/1.1\r\nHost: x\r\n\r\n" + os.urandom(64))
    assert reply[:4] == MAGIC and b"not a KD Trace message" in reply
    # A truncated header, a huge claimed length in the opening; TLS garbage after it.
    raw_exchange(port, HEADER.pack(MAGIC, 1, 1, 5, 0)[:7], read=False)
    assert b"exceeds" in raw_exchange(port, HEADER.pack(MAGIC, protocol.PROTOCOL_VERSION,
                                                        MsgType.OPEN, 1 << 31, 1 << 60))
    opening = protocol.encode_message(MsgType.OPEN, {})[0]
    assert raw_exchange(port, opening + os.urandom(512)).startswith(opening[:4])   # OPEN, then TLS refused
    # Inside TLS, after a valid HELLO: a huge claimed length, a lying array list.
    assert b"exceeds" in tls_exchange(port, HEADER.pack(MAGIC, protocol.PROTOCOL_VERSION,
                                                        MsgType.SCENE_QUERY, 1 << 31, 1 << 60))
    liar = protocol.encode_message(MsgType.SCENE_UPLOAD, {"scene_hash": "0" * 32},
                                   {"vertices": np.zeros((3, 3), np.float32)})[0]
    liar = liar.replace(b'"shape":[3,3]', b'"shape":[9,9]')
    assert b"do not match" in tls_exchange(port, liar + b"\0" * 36)
    # A valid scene announced under another hash: the slave checks what it received.
    geometry, tree = make_scene()
    upload = b"".join(bytes(b) for b in protocol.encode_message(
        MsgType.SCENE_UPLOAD, {"scene_hash": "0" * 32}, Scene.from_parts(geometry, tree).wire_arrays()))
    assert b"scene upload hash mismatch" in tls_exchange(port, upload)
    # A frame before any scene, a tile for no frame: an ERROR for the frame, no crash.
    frame = protocol.encode_message(MsgType.FRAME_START, {
        "frame_id": 1, "scene_hash": "f" * 32, "view": make_view().to_dict(), "tile_size": 16})[0]
    reply = tls_exchange(port, frame + protocol.encode_message(
        MsgType.TILE_REQUEST, {"frame_id": 1, "tile": 0})[0] + protocol.encode_message(MsgType.BYE)[0])
    assert b"is not loaded on this slave" in reply
    assert slaves[0].alive()
    # ... and the slave still serves the next master.
    geometry, tree = make_scene()
    with Master([slaves[0].endpoint]) as master:
        master.connect()
        master.load_scene(Scene.from_parts(geometry, tree))
        images, _ = render_all(master.render(make_view(), tile_size=32))
    assert_images_equal(images, reference)


def test_version_mismatch_is_explained_to_both_sides(slaves):
    # Any message of another version (protocol 6's HELLO, a newer OPEN) is answered in
    # plaintext, before TLS, with both versions named.
    for kind in (MsgType.HELLO, MsgType.OPEN):
        newer = HEADER.pack(MAGIC, protocol.PROTOCOL_VERSION + 1, kind, 2, 0) + b"{}"
        text = raw_exchange(slaves[0].port, newer).decode("utf-8", "replace")
        assert (f"master speaks version {protocol.PROTOCOL_VERSION + 1}, slave speaks version "
                f"{protocol.PROTOCOL_VERSION}") in text
    text = tls_exchange(slaves[0].port, scene_format_version=99).decode("utf-8", "replace")
    assert "scene format version mismatch: master uses version 99, slave uses version 1" in text


def test_master_pointed_at_a_dead_port_says_so(slaves):
    with socket.socket() as probe:  # a port that nobody listens on
        probe.bind(("127.0.0.1", 0))
        dead = probe.getsockname()[1]
    master = Master([("127.0.0.1", dead)], connect_timeout=2)
    with pytest.raises(MasterError, match=rf"cannot reach slave 127\.0\.0\.1:{dead} \(connection refused\)"):
        master.connect()
    # One dead endpoint among live ones is reported and skipped.
    master = Master([("127.0.0.1", dead), slaves[1].endpoint])
    assert [c.name for c in master.connect()] == [slaves[1].name]
    assert master.errors == [f"cannot reach slave 127.0.0.1:{dead} (connection refused)"]
    master.close()


@pytest.mark.parametrize("args, message", [
    (["--port", "70000"], "port must be 0-65535"),
    (["--bind", "not-an-ip"], "not an IPv4 address"),
    (["--device", "fastest"], "device must be auto, cpu, gpu or P:D"),
    (["--name", "bad.name!"], "name must be"),
    (["--frobnicate"], "unrecognized arguments"),
    (["--device", "9:9", "--no-zeroconf", "--port", "0"], "cannot use OpenCL device '9:9'"),
])
def test_bad_command_lines_exit_2_with_one_line(args, message):
    proc = subprocess.run([sys.executable, "-m", "kdtrace.slave", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=60, env=dict(os.environ, POCL_MAX_PTHREAD_COUNT="1"))
    assert proc.returncode == 2
    assert proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr
