"""Each pass beside the image is computed and sent only when a frame asks for it: a real slave
(the OpenCL tracer in a SlaveServer) behind a link that counts bytes renders a frame with
Combined alone and with each other pass; the bytes per pixel on the wire grow by exactly the
pass's size in each payload, and the slave's kernel compiles the pass's feature only for that
frame (protocol TILE_PASSES, PASS_CODING; core/scene/features.py pass_features)."""
from __future__ import annotations

import numpy as np
import pytest

from kdtrace.core.net import protocol
from kdtrace.core.net.master import Master
from kdtrace.core.scene.features import PASS_FEATURES
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.server import SlaveServer
from kdtrace.slave.tracer import Tracer
from tests.conftest import FARM_SECRET
from tests.linkemu import LinkEmulator
from tests.test_network import make_scene, make_view
from tests.test_scale import render

WIDTH, HEIGHT, TILE = 64, 48, 32
PIXELS = WIDTH * HEIGHT
OVERHEAD = 6 * 1024       # headers, JSON, heartbeats of 6 tiles: well under 1 KiB a tile


class RecordingTracer(Tracer):
    """The real tracer, noting the kernel features of every tile it renders."""

    def __init__(self):
        super().__init__("cpu")
        self.features = []

    def render_tile(self, *args, **kwargs):
        passes = super().render_tile(*args, **kwargs)
        self.features.append(set(self.last_render["features"]))
        return passes


@pytest.fixture(scope="module")
def slave():
    tracer = RecordingTracer()
    server = SlaveServer(tracer, "wire", bind="127.0.0.1", port=0, secret=FARM_SECRET)
    server.start()
    link = LinkEmulator(server.address).start()
    geometry, tree = make_scene()
    with Master([link.endpoint], retry_delays=()) as master:
        master.connect()
        master.load_scene(Scene.from_parts(geometry, tree))
        yield master, link, tracer
    link.close()
    server.close()


def frame_bytes(slave, passes, payload="f32") -> tuple:
    """(bytes the slave sent for one frame asking `passes`, the frame's image, the features
    its tiles were rendered with)."""
    master, link, tracer = slave
    tracer.features.clear()
    before = sum(d.bytes for d in link.directions[1::2])        # slave -> master
    job, _ = render(master, make_view(WIDTH, HEIGHT), tile_size=TILE, passes=passes,
                    payload=payload)
    image = {name: job.image[name].copy() for name in job.passes}
    sent = sum(d.bytes for d in link.directions[1::2]) - before
    return sent, image, set.union(*tracer.features)


FILM_PASSES = [name for name in protocol.TILE_PASSES if name in PASS_FEATURES]


def pass_bytes(payload: str, name: str) -> int:
    """Bytes a pixel of pass `name` takes on the wire in `payload`."""
    return (protocol.tile_bytes_per_pixel(payload, ["combined", name])
            - protocol.tile_bytes_per_pixel(payload, ["combined"]))


def test_every_film_pass_is_a_protocol_pass():
    assert set(PASS_FEATURES) == set(FILM_PASSES)
    assert set(protocol.ALL_PASSES) == {"combined", "depth", "normal"}


@pytest.mark.parametrize("payload", ["f32", "f16", "u8"])
def test_each_pass_costs_its_bytes_and_its_work_only_when_asked(slave, payload):
    base, image, features = frame_bytes(slave, ["combined"], payload)
    combined = protocol.tile_bytes_per_pixel(payload, ["combined"])
    assert PIXELS * combined <= base < PIXELS * combined + OVERHEAD, base
    assert "FILM" not in features and set(image) == {"combined"}
    for name in FILM_PASSES:
        sent, image, features = frame_bytes(slave, ["combined", name], payload)
        per_pixel = pass_bytes(payload, name)
        extra = sent - base
        # exactly the pass's bytes a pixel (f32: 4 a channel; f16 2, u8 1, exact passes 4)
        assert abs(extra - PIXELS * per_pixel) < OVERHEAD, (name, extra / PIXELS, per_pixel)
        assert set(PASS_FEATURES[name]) <= features, (name, features)
        others = {f for n in FILM_PASSES if n != name and
                  set(PASS_FEATURES[n]) != set(PASS_FEATURES[name]) for f in PASS_FEATURES[n]}
        assert not (others - {"FILM"}) & features, (name, features)
        assert set(image) == {"combined", name} and np.isfinite(image[name]).all()


def test_bytes_per_pixel_of_each_pass():
    """What each pass costs a pixel, as docs/distributed.md lists it."""
    table = {name: [pass_bytes(p, name) for p in ("f32", "f16", "u8")]
             for name in protocol.TILE_PASSES if name != "combined"}
    assert table == {"depth": [4, 4, 4], "normal": [12, 6, 3], "albedo": [12, 6, 3],
                     "denoising_normal": [12, 6, 3], "mist": [4, 4, 4],
                     "emission": [12, 6, 3], "diffuse_color": [12, 6, 3],
                     "glossy_color": [12, 6, 3]}
