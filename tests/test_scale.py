"""Many slaves at once, and what a tile carries (issue 18): real SlaveServers and the real
master over real sockets, with the calibrated stand-in of bench/standin.py as the tracer (it
sleeps a fixed time per tile and returns the real tracer's tile bytes)."""
from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from bench.standin import StandInTracer, calibrate
from kdtrace.core.net.master import Master, auto_tile_size
from kdtrace.core.net.render_job import DEPTH_MISS, RESULTS_EVERY_S
from kdtrace.core.net.tile_payloads import decode_tile, encode_tile
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.server import SlaveServer
from tests.linkemu import LinkEmulator
from tests.test_network import make_scene, make_view
from tests.conftest import FARM_SECRET

TILE = 16
TILE_MS = 50.0       # what every stand-in tile takes


@pytest.fixture(scope="module")
def scene():
    return Scene.from_parts(*make_scene())


@pytest.fixture(scope="module")
def calibration(scene):
    """The real tracer's frame (128 x 96, 48 tiles of 16 x 16), checked against its one-piece
    render; the stand-ins then answer every tile with its real bytes in TILE_MS."""
    from kdtrace.slave.tracer import Tracer
    tracer = Tracer()
    view = make_view(128, 96)
    result = calibrate(tracer, scene, view, [(TILE, TILE)])
    whole = tracer.render_tile(view, 0, 0, view.width, view.height)
    for name, image in whole.items():
        np.testing.assert_array_equal(result.image[name], image, err_msg=name)
    result.tile_ms = dict.fromkeys(result.tile_ms, TILE_MS)
    return result


class StandIns:
    """`count` stand-in slaves in this process, each a SlaveServer with its own socket."""

    def __init__(self, calibration, count: int, speeds=(1.0,)):
        self.servers = []
        for i in range(count):
            server = SlaveServer(StandInTracer(calibration, speeds[i % len(speeds)]),
                                 f"standin-{i}", bind="127.0.0.1", port=0, secret=FARM_SECRET)
            server.start()
            self.servers.append(server)
        self.endpoints = [s.address for s in self.servers]

    def close(self):
        for server in self.servers:
            server.close()


def render(master, view, timeout=60.0, **options):
    job = master.render(view, **options)
    results, deadline = [], time.monotonic() + timeout
    while not job.finished:
        assert time.monotonic() < deadline, "frame did not finish in time"
        result = job.next_result(0.1)
        if result is not None:
            results.append(result)
    assert job.error is None, job.error
    assert job.wait(30)
    return job, results


def test_32_stand_in_slaves_finish_a_frame_with_every_tile_once(scene, calibration):
    slaves = StandIns(calibration, 32)
    try:
        with Master(slaves.endpoints, retry_delays=()) as master:
            master.connect()
            assert len(master.slaves) == 32
            master.load_scene(scene)
            view = make_view(128, 96)
            job, results = render(master, view, tile_size=TILE, tiles_in_flight=1)
            assert sorted(r.index for r in results) == list(range(len(job.tiles))) == list(range(48))
            # each tile delivered once, its passes a window of job.image; most slaves took part
            # (on a loaded machine the last workers may start after the first ones are done)
            assert len(job.tiles_by_slave) == 32 and sum(job.tiles_by_slave.values()) == 48
            assert sum(n > 0 for n in job.tiles_by_slave.values()) >= 16, job.tiles_by_slave
            for name, image in calibration.image.items():
                np.testing.assert_array_equal(job.image[name], image, err_msg=name)
            for r in results:
                assert np.shares_memory(r.passes["combined"], job.image["combined"])
            # 48 tiles of 50 ms on 32 slaves: two rounds (0.1 s), far from 48 x 50 ms
            assert job.elapsed_s < 48 * TILE_MS / 1000 / 4, job.elapsed_s
            # The next frame starts no thread, here or in the slaves: one frame loop serves
            # all 32 slaves, frame after frame.
            before = set(threading.enumerate())
            job = master.render(view, tile_size=TILE, tiles_in_flight=1)
            assert job.next_result(30) is not None
            assert set(threading.enumerate()) <= before
            assert [t.name for t in before if t.name.startswith("frames of")] == ["frames of master"]
            assert job.wait(30) and job.error is None
    finally:
        slaves.close()


def test_next_results_takes_the_tiles_that_came_meanwhile_at_a_steady_pace(scene, calibration):
    """32 slaves deliver 32 tiles at about the same moment: a caller showing tiles wakes for
    them a few times, not 32, and every tile comes once; while the frame goes on the calls
    return at least RESULTS_EVERY_S apart."""
    slaves = StandIns(calibration, 32)
    try:
        with Master(slaves.endpoints, retry_delays=()) as master:
            master.connect()
            master.load_scene(scene)
            job = master.render(make_view(128, 96), tile_size=TILE, tiles_in_flight=1)
            batches, returned, deadline = [], [], time.monotonic() + 60
            while not job.finished:
                assert time.monotonic() < deadline, "frame did not finish in time"
                batch = job.next_results(0.1)
                if batch:
                    batches.append(batch)
                    returned.append((time.monotonic(), job.over))
            assert job.error is None, job.error
            assert sorted(r.index for b in batches for r in b) == list(range(48))
            assert len(batches) < 48 and max(map(len, batches)) > 1, [len(b) for b in batches]
            for (before, _), (after, over) in zip(returned, returned[1:]):
                assert over or after - before >= RESULTS_EVERY_S * 0.99
            assert job.wait(30)
    finally:
        slaves.close()


def _address(image: dict) -> int:
    return image["combined"].__array_interface__["data"][0]


def _empty_or_rendered(job, reference: dict) -> list:
    """Per tile of `job`: True where it holds the reference's pixels, False where it is
    empty (zero colour and normal, no surface); AssertionError if it is anything else."""
    states = []
    for x, y, w, h in job.tiles:
        window = job.windows(x, y, w, h)
        rendered = all(np.array_equal(window[n], reference[n][y:y + h, x:x + w]) for n in window)
        empty = all(np.all(window[n] == (DEPTH_MISS if n == "depth" else 0.0)) for n in window)
        assert rendered or empty, (x, y)
        states.append(rendered)
    return states


def test_a_released_frame_is_written_again_from_empty(scene, calibration):
    """RenderJob.release(): the next frame of the same size and passes is written into the
    same memory, from empty (a cancelled frame shows no pixel of the frame before), and only
    once the released frame is quiet; a frame not released is never written again."""
    slaves = StandIns(calibration, 8)
    try:
        with Master(slaves.endpoints, retry_delays=()) as master:
            master.connect()
            master.load_scene(scene)
            view = make_view(128, 96)
            first = master.render(view, tile_size=TILE)
            first.release()                  # while it renders: handed back once quiet
            assert first.next_result(30) is not None and first.image is not None
            assert first.wait(30) and first.image is None
            job, _ = render(master, view, tile_size=TILE)
            reused = _address(job.image)
            for name, image in calibration.image.items():
                np.testing.assert_array_equal(job.image[name], image, err_msg=name)
            kept, _ = render(master, view, tile_size=TILE)     # job not released: new memory
            assert _address(kept.image) != reused
            for image in job.image.values():     # the caller's until released
                image[...] = 7.0
            job.release()
            cancelled = master.render(view, tile_size=TILE)
            assert cancelled.next_result(30) is not None
            cancelled.cancel()
            assert cancelled.wait(30) and cancelled.error is None
            assert _address(cancelled.image) == reused
            states = _empty_or_rendered(cancelled, calibration.image)
            assert 1 <= sum(states) < len(states), sum(states)
            np.testing.assert_array_equal(kept.image["combined"], calibration.image["combined"])
            other, _ = render(master, make_view(128, 96), tile_size=TILE, passes=["combined"])
            assert _address(other.image) != reused          # other passes: not that frame
    finally:
        slaves.close()


def _bytes_sent_by_slave(calibration, scene, **options) -> tuple:
    """(bytes the slave sent through the link, tiles) for one frame with `options`."""
    slaves = StandIns(calibration, 1)
    link = LinkEmulator(slaves.endpoints[0]).start()
    try:
        with Master([link.endpoint], retry_delays=()) as master:
            master.connect()
            master.load_scene(scene)
            base = sum(d.bytes for d in link.directions[1::2])      # slave -> master so far
            job, _ = render(master, make_view(128, 96), tile_size=TILE, **options)
            passes = {name: job.image[name] for name in job.passes}
        return sum(d.bytes for d in link.directions[1::2]) - base, len(job.tiles), passes
    finally:
        link.close()
        slaves.close()


def test_passes_not_enabled_are_not_sent(scene, calibration):
    pixels = 128 * 96
    overhead = 48 * 1024 + 16 * 1024   # headers, JSON, heartbeats, the cancel answer: < 1 KiB a tile
    sent, tiles, passes = _bytes_sent_by_slave(calibration, scene, passes=["combined"])
    assert set(passes) == {"combined"}
    assert pixels * 16 <= sent < pixels * 16 + overhead, sent       # combined: 4 x float32
    np.testing.assert_array_equal(passes["combined"], calibration.image["combined"])
    sent_all, _, passes = _bytes_sent_by_slave(calibration, scene)  # the default: every pass
    assert pixels * 32 <= sent_all < pixels * 32 + overhead, sent_all
    assert sent_all - sent >= pixels * 16                           # depth + normal: 16 bytes a pixel
    sent_u8, _, passes = _bytes_sent_by_slave(calibration, scene, passes=["combined"], payload="u8")
    assert pixels * 4 <= sent_u8 < pixels * 4 + overhead, sent_u8   # combined: 4 bytes
    np.testing.assert_array_equal(          # the master composes exactly what decoding gives
        passes["combined"],
        decode_tile(*encode_tile(calibration.image, "u8", False, ["combined"]),
                    128, 96, "u8", ["combined"])["combined"])


def _srgb(linear: float) -> float:
    return 12.92 * linear if linear <= 0.0031308 else 1.055 * linear ** (1 / 2.4) - 0.055


def _linear(srgb: float) -> float:
    return srgb / 12.92 if srgb <= 0.04045 else ((srgb + 0.055) / 1.055) ** 2.4


def test_8_bit_preview_is_exact_to_its_quantisation():
    """Each colour channel travels as the 8-bit sRGB code nearest the value (clipped to 0..1)
    and decodes to exactly that code's linear value; alpha and normal as linear codes. The
    reference is computed independently, per value, with the sRGB formulas in float64."""
    rng = np.random.default_rng(18)
    h, w = 16, 24
    combined = np.concatenate([rng.random((h, w // 2, 4)) ** 3,          # dark values too
                               rng.uniform(-0.2, 1.3, (h, w // 2, 4))], axis=1).astype(np.float32)
    normal = rng.uniform(-1.1, 1.1, (h, w, 3)).astype(np.float32)
    passes = {"combined": combined, "depth": rng.random((h, w)).astype(np.float32) * 50,
              "normal": normal}
    fields, arrays = encode_tile(passes, "u8")
    assert {n: a.dtype.str for n, a in arrays.items()} == {"combined": "|u1", "depth": "<f4",
                                                           "normal": "|u1"}
    decoded = decode_tile(fields, arrays, w, h, "u8")
    np.testing.assert_array_equal(decoded["depth"], passes["depth"])        # depth stays exact
    for (y, x, c), value in np.ndenumerate(combined):
        v = min(max(float(value), 0.0), 1.0)
        if c < 3:
            code = math.floor(_srgb(v) * 255 + 0.5)
            expected = np.float32(_linear(code / 255))
            # the code is the nearest: the value's sRGB is within half a code of it
            assert abs(_srgb(float(decoded["combined"][y, x, c])) - _srgb(v)) <= 0.5 / 255 + 1e-6
        else:
            code = math.floor(v * 255 + 0.5)
            expected = np.float32(code / 255)
        assert arrays["combined"][y, x, c] == code, (y, x, c, value)
        assert decoded["combined"][y, x, c] == expected, (y, x, c, value)
    for (y, x, c), value in np.ndenumerate(normal):
        code = math.floor((min(max(float(value), -1.0), 1.0) + 1) * 127.5 + 0.5)
        assert arrays["normal"][y, x, c] == code
        assert decoded["normal"][y, x, c] == np.float32(code / 127.5 - 1)
    # compressed, the same values
    fields, packed = encode_tile(passes, "u8", True)
    again = decode_tile(fields, packed, w, h, "u8")
    for name in decoded:
        np.testing.assert_array_equal(again[name], decoded[name])


def test_auto_tile_size_gives_each_slave_about_eight_tiles_and_a_frame_at_most_256():
    region = (0, 0, 1024, 1024)
    assert [auto_tile_size(region, n) for n in (1, 2, 4, 8, 16, 32, 64, 256, 4096)] == \
        [(256, 256)] * 2 + [(128, 128)] * 2 + [(64, 64)] * 5
    assert auto_tile_size((0, 0, 1920, 1080), 64) == (128, 128)   # 135 tiles; 64 px: 510
    assert auto_tile_size((0, 0, 64, 64), 8) == (32, 32)       # never below the smallest


def test_faster_slaves_get_more_tiles_in_flight(scene, calibration):
    """tiles_in_flight="auto": behind links of 20 ms each way, a slave eight times as fast as
    the other (12.5 ms tiles against 100) keeps more requests ahead; the slow one keeps 2. (With
    50 ms tiles the slow one's round trip, 40 ms plus this machine's delays, now and then
    exceeded a tile and gave it 3.)"""
    slaves = StandIns(calibration, 2, speeds=(0.5, 4.0))
    links = [LinkEmulator(endpoint, latency_s=0.02).start() for endpoint in slaves.endpoints]
    try:
        with Master([link.endpoint for link in links], retry_delays=()) as master:
            master.connect()
            master.load_scene(scene)
            job, _ = render(master, make_view(128, 96), tile_size=TILE, tiles_in_flight="auto")
            fast, slow = (next(w for w in job._workers if w.connection.name == name)
                          for name in ("standin-1", "standin-0"))
            assert slow.window == 2 and fast.window > 4, (fast.window, slow.window)
            assert fast.round_trip_s >= 0.04 and fast.tiles_done > 2 * slow.tiles_done
    finally:
        for link in links:
            link.close()
        slaves.close()
