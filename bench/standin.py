"""A calibrated stand-in for the slave's tracer: many slaves on one machine, for benchmarks and
tests of the master, the protocol and the links at scale.

It is not a slave mode and cannot be picked from the slave's command line: a bench or test
process plugs it in as the tracer object of a `slave.server.SlaveServer` (the way the tests
plug in fakes), so the server, the protocol, the sockets and the master are the real ones.

A `Calibration` holds, for one scene and view, the frame the real tracer rendered (every tile a
real slave sends is a window of it, bit for bit: pixels do not depend on the tiling, which the
network tests check) and the render time it measured for every tile of each calibrated tile
size. `StandInTracer.render_tile` sleeps that time (divided by the slave's `speed`) and returns
the tile's window, so the server encodes and sends the same bytes a real slave would.
"""
from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from kdtrace.core.net.tiles import TileGrid
from kdtrace.slave.tracer import RenderStopped

STOP_POLL_S = 0.1       # how often a tile's sleep looks at its stop (the tracer: each launch)


@dataclass
class Calibration:
    region: tuple                       # (x0, y0, x1, y1) of the frame
    image: dict                         # pass name -> float32 frame (the real tracer's)
    tile_ms: dict = field(default_factory=dict)   # (x, y, w, h) -> measured render ms

    def tile_sizes(self) -> list:
        return sorted({(w, h) for (x, y, w, h) in self.tile_ms if x == self.region[0]
                       and y == self.region[1]})

    def frame_ms(self, tile_size) -> list:
        """The measured ms of every tile of a frame cut into `tile_size` tiles, in grid order."""
        return [self.tile_ms[tile] for tile in TileGrid(self.region, tile_size)]

    def save(self, path) -> None:
        tiles = np.array(sorted(self.tile_ms), np.int64).reshape(-1, 4)
        np.savez(path, region=np.array(self.region), tiles=tiles,
                 ms=np.array([self.tile_ms[tuple(t)] for t in tiles.tolist()], np.float64),
                 **{f"pass_{name}": image for name, image in self.image.items()})

    @classmethod
    def load(cls, path) -> "Calibration":
        with np.load(pathlib.Path(path), allow_pickle=False) as data:
            image = {key[5:]: data[key] for key in data.files if key.startswith("pass_")}
            tile_ms = {tuple(t): float(ms) for t, ms in zip(data["tiles"].tolist(), data["ms"])}
            return cls(tuple(int(v) for v in data["region"]), image, tile_ms)


def calibrate(tracer, scene, view, tile_sizes, clock=time.process_time) -> Calibration:
    """Render the frame with the real `tracer` once per tile size, timing every tile with
    `clock`; the frame's passes are those of the first tile size (the others give the same
    bits). The default clock is this process's CPU time: with one PoCL thread
    (POCL_MAX_PTHREAD_COUNT=1) that is the tile's time on a core of its own, also on a machine
    that others load."""
    tracer.load(scene)
    tracer.prepare(view)
    x0, y0, x1, y1 = view.region
    image = None
    tile_ms = {}
    for size in tile_sizes:
        tracer.render_tile(view, x0, y0, min(16, x1 - x0), min(16, y1 - y0))  # warm: kernels
        for x, y, w, h in TileGrid(view.region, size):
            start = clock()
            passes = tracer.render_tile(view, x, y, w, h)
            tile_ms[(x, y, w, h)] = (clock() - start) * 1000.0
            if image is None:
                image = {name: np.zeros((y1 - y0, x1 - x0) + a.shape[2:], np.float32)
                         for name, a in passes.items()}
            if size == tile_sizes[0]:
                for name, array in passes.items():
                    image[name][y - y0:y - y0 + h, x - x0:x - x0 + w] = array
    return Calibration((x0, y0, x1, y1), image, tile_ms)


class StandInTracer:
    """The tracer interface SlaveServer uses (device_info, build_seconds, load, prepare,
    render_tile), answered from a Calibration: sleeps the measured time / `speed`."""

    build_seconds = 0.0

    def __init__(self, calibration: Calibration, speed: float = 1.0, name: str = "stand-in"):
        self.calibration, self.speed = calibration, float(speed)
        self.device_info = {"name": f"{name} (calibrated stand-in, x{speed:g})",
                            "compute_units": 1, "memory": 1 << 30, "platform": "bench"}

    def load(self, scene) -> None:
        pass

    def prepare(self, view, passes=()) -> None:
        pass

    def calibration_for(self, view) -> Calibration:
        """The Calibration that answers `view`'s tiles: the one given, whatever the view."""
        return self.calibration

    def render_tile(self, view, x: int, y: int, w: int, h: int, passes=(), stop=None) -> dict:
        calibration = self.calibration_for(view)
        ms = calibration.tile_ms.get((x, y, w, h))
        if ms is None:
            raise ValueError(f"tile {(x, y, w, h)} was not calibrated (tile sizes: "
                             f"{calibration.tile_sizes()})")
        end = time.monotonic() + ms / 1000.0 / self.speed
        while (left := end - time.monotonic()) > 0:     # stops between "launches", as the tracer
            if stop is not None and stop():
                raise RenderStopped("stopped between launches")
            time.sleep(min(left, STOP_POLL_S))
        x0, y0 = calibration.region[:2]
        return {name: image[y - y0:y - y0 + h, x - x0:x - x0 + w].copy()
                for name, image in calibration.image.items()}


def pass_key(view) -> tuple:
    """What tells a view's passes apart for PassStandInTracer: (width, height, samples per
    axis)."""
    return (view.width, view.height, view.settings.samples_per_axis)


class PassStandInTracer(StandInTracer):
    """A StandInTracer for frames of several sizes and sample counts (the viewport's passes):
    one Calibration per pass_key, each the real tracer's frame of one view at that size and
    those samples. Any view of that size and those samples is answered from it (its camera
    is not looked at)."""

    def __init__(self, calibrations: dict, speed: float = 1.0, name: str = "stand-in"):
        super().__init__(next(iter(calibrations.values())), speed, name)
        self.calibrations = dict(calibrations)

    def calibration_for(self, view) -> Calibration:
        calibration = self.calibrations.get(pass_key(view))
        if calibration is None:
            raise ValueError(f"no calibration for a {pass_key(view)} frame (width, height, "
                             f"samples per axis); calibrated: {sorted(self.calibrations)}")
        return calibration


# -- host processes: many stand-in slaves (and the emulated network) in a few processes

def serve_tracers(tracers: dict) -> None:
    """In a host process: a SlaveServer on loopback for each name -> tracer, with the bench's
    farm secret; prints their ports as one JSON line, serves until stdin closes."""
    from bench.farm import bench_farm
    from kdtrace.slave.server import SlaveServer
    servers = []
    for name, tracer in tracers.items():
        server = SlaveServer(tracer, name, bind="127.0.0.1", port=0, secret=bench_farm())
        server.start()
        servers.append(server)
    print(json.dumps([s.address[1] for s in servers]), flush=True)
    sys.stdin.read()
    for server in servers:
        server.close()


class HostProcess:
    """A child process `script args...` that prints its ports as one JSON line (serve_tracers,
    the network emulation) and runs until its stdin closes."""

    def __init__(self, script, *args):
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        root = pathlib.Path(__file__).resolve().parent.parent
        self.proc = subprocess.Popen([sys.executable, str(script), *map(str, args)], cwd=root,
                                     env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     text=True)
        self.ports = json.loads(self.proc.stdout.readline())

    def cpu_seconds(self) -> float:
        """CPU time of the child so far (user + system, from /proc)."""
        fields = pathlib.Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait(30)
