"""Issue 35's benchmark: the viewport's Rendered mode through local slaves (core/frame/viewport.py,
the session the add-on's view_update and view_draw drive), without Blender.

    .venv/bin/python bench/viewport.py [--scenes dragon dragons12] [--slaves 2] [--changes 60]
                                       [--width 960 --height 540] [--samples 4]
                                       [--standin N ... [--hosts 4] [--link link|loopback]]

For each scene: the session's first image after the scene is given (kd-tree and upload
included); a scripted orbit of --changes view changes (3 degrees each; each change made once
the previous one's first image is drawn, as a user dragging the view sees it): the latency from
a change to the first image of the new view, median and 95th percentile; once still, the
samples per pixel per second while it refines to --samples x --samples; and the paper's
figure, frames per second of a 1024 x 1024 image at one sample (camera and shadow rays, a sun)
through the same slaves. The dragon is the Stanford dragon (npm); dragons12 is 12 of them in
one mesh (10.5 M triangles), on a 4 x 3 grid. Local slaves share this machine's cores.

More slaves than this machine has cores: --standin 8 64 drives the same ViewportSession and
the same orbit against N stand-in slaves instead, each N on slaves and links of its own (no
frames per second of 1024 x 1024; figures in docs/viewport.md):

    flock /tmp/bench.lock .venv/bin/python bench/viewport.py --scenes dragon --standin 8 64

What is real: the master, the session (passes, cancels and their confirmations, what it draws),
the protocol, the sockets, the scene's upload to every slave (each receives, checks and keeps
it as a slave does), and the links: each slave behind an emulated link of its own
(bench/many_slaves.py's "link": 3 ms, 300 Mbit/s each way, tests/linkemu.py, in a process of
its own; --link loopback: none); the slaves are real `SlaveServer`s, in --hosts processes
beside this one. What is modelled: the tracer (bench/standin.py's PassStandInTracer). Once per
scene, size and samples (cached in bench/out/), the real tracer renders each pass of the
orbit's first view (the 160 x 90 preview at one sample, the full view at 1, 4, ... samples)
with one PoCL thread, timing every 64 x 64 tile in CPU time; a stand-in slave answers a tile of
a pass by sleeping that tile's time (a slave as fast as one core of this machine, a core of its
own each; it stops between 0.1 s sleeps when cancelled, as the tracer between launches) and
sending that tile's real bytes. So every view of the orbit costs, tile by tile, what its first
view cost (the orbit turns the camera round the same object at the same distance), and the
pixels drawn are the first view's; the scene's load onto the device and kernel compiles, which
a real slave pays once per scene and settings, are not modelled. Not as on a farm: the slaves'
servers and the links run on this machine's cores beside the master (the run prints their CPU
time during the orbit).
"""
import argparse
import os
import pathlib
import statistics
import subprocess
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from bench.machine import cpu_model  # noqa: E402
from kdtrace.core.frame.exported import InstancedExport  # noqa: E402
from kdtrace.core.frame.options import FrameOptions  # noqa: E402
from kdtrace.core.frame.render import FrameHost, Steps, frame_scene, master_for  # noqa: E402
from kdtrace.core.frame.session import FrameSession  # noqa: E402
from kdtrace.core.frame.viewport import ViewportSession, passes  # noqa: E402
from kdtrace.core.scene.model import (Camera, Geometry, Light, RenderSettings,  # noqa: E402
                                      Shading, View, default_material_params)
from tests.meshes import load_dragon, look_at  # noqa: E402

OUT = ROOT / "bench" / "out"
STANDIN_TILE = 64       # the tile size of the runs (FrameOptions.tile_size) and of calibration


def scene(name):
    """(InstancedExport, the scene's centre, its radius): the dragon, z up, about 4 units long,
    or 12 of them in one mesh on a 4 x 3 grid."""
    vertices, triangles = load_dragon()
    vertices = vertices[:, [0, 2, 1]] * np.array([20.0, -20.0, 20.0], np.float32)
    vertices[:, 2] -= vertices[:, 2].min()
    if name == "dragons12":
        offsets = [(5.0 * (i % 4), 3.5 * (i // 4), 0.0) for i in range(12)]
        triangles = np.concatenate([triangles + i * len(vertices) for i in range(12)])
        vertices = np.concatenate([vertices + np.float32(o) for o in offsets])
    mesh = Geometry(vertices.astype(np.float32), triangles.astype(np.uint32),
                    np.zeros(len(triangles), np.uint16))
    lo, hi = vertices.min(0), vertices.max(0)
    exported = InstancedExport([mesh], np.zeros(1, np.int64), np.eye(4)[None], None, None)
    return exported, (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2


def orbit_view(centre, radius, angle, width, height, settings):
    """The camera `angle` degrees round the scene, 20 degrees up, a 50 degree field of view."""
    a, up = np.radians(angle), np.radians(20)
    eye = centre + 2.2 * radius * np.array([np.cos(a) * np.cos(up), np.sin(a) * np.cos(up),
                                            np.sin(up)])
    half = np.tan(np.radians(25))
    camera = Camera("PERSP", look_at(eye, centre), (half, half * height / width), (0, 0), 0.01,
                    100 * radius)
    params = default_material_params(1)
    shading = Shading(np.array([[0.8, 0.6, 0.4, 1.0]], np.float32),
                      [Light("SUN", (1, 1, 1), 3.0, direction=(-0.4, -0.3, -0.85))],
                      (0.3, 0.35, 0.4), params)
    return View(camera, width, height, shading, settings=settings)


def wait_for(predicate, seconds=600):
    deadline = time.monotonic() + seconds
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError("the viewport did not answer")
        time.sleep(0.002)


def viewport_figures(name, exported, centre, radius, args, session, options,
                     first_is="kd-tree and upload included", other_cpu=None) -> dict:
    """The first image, the orbit's latencies and the samples per pixel per second once
    still; with `other_cpu` (a function: the CPU seconds of the other processes so far), the
    CPU time of this process and of the others during the orbit."""
    settings = RenderSettings(samples_per_axis=args.samples, adaptive=False)
    viewport = ViewportSession(session, options, samples_per_axis=args.samples)
    try:
        started = time.perf_counter()
        epoch = viewport.update(orbit_view(centre, radius, 0, args.width, args.height, settings),
                                exported)
        wait_for(lambda: (viewport.image() or None) and viewport.image().epoch == epoch)
        first = time.perf_counter() - started
        latencies = []
        cpu = (time.process_time(), other_cpu() if other_cpu else 0.0)
        for step in range(1, args.changes + 1):
            view = orbit_view(centre, radius, 3.0 * step, args.width, args.height, settings)
            changed = time.perf_counter()
            epoch = viewport.update(view)
            wait_for(lambda: viewport.image().epoch == epoch)
            latencies.append(time.perf_counter() - changed)
        cpu = (time.process_time() - cpu[0], (other_cpu() if other_cpu else 0.0) - cpu[1])
        still = time.perf_counter()
        wait_for(viewport.done)
        refine = time.perf_counter() - still
        assert not viewport.error, viewport.error
        samples = sum(v.settings.samples_per_axis ** 2 for v in passes(view, args.samples)
                      if v.width == view.width)       # the full-resolution passes' samples
        latencies.sort()
        p95 = latencies[min(len(latencies) - 1, int(round(0.95 * len(latencies))) - 1)]
        print(f"{name}: first image {first:.2f} s ({first_is}); "
              f"{len(latencies)} changes: latency median {statistics.median(latencies) * 1e3:.0f} "
              f"ms, 95th percentile {p95 * 1e3:.0f} ms, max {latencies[-1] * 1e3:.0f} ms; once "
              f"still: {samples} samples per pixel in {refine:.2f} s = {samples / refine:.1f} "
              f"samples per pixel per second at {args.width}x{args.height}; cancels confirmed "
              f"in median {statistics.median(viewport.cancel_seconds or [0]) * 1e3:.0f} ms"
              + (f"; CPU during the orbit: this process (master, session) {cpu[0]:.2f} s, "
                 f"slave hosts and links {cpu[1]:.2f} s, in {sum(latencies):.2f} s"
                 if other_cpu else ""), flush=True)
        return {"first_s": first, "median_s": statistics.median(latencies), "p95_s": p95,
                "max_s": latencies[-1], "spp_per_s": samples / refine,
                "cancel_median_s": statistics.median(viewport.cancel_seconds or [0]),
                "orbit_s": sum(latencies), "cpu_s": cpu}
    finally:
        viewport.close()


def frames_per_second(name, exported, centre, radius, session, options, frames=8):
    """1024 x 1024 at one sample (camera and shadow rays) through the same slaves."""
    settings = RenderSettings(samples_per_axis=1, adaptive=False, max_bounces=0)
    steps = Steps(time.perf_counter())
    scene_, *_ = frame_scene(session, exported, options, FrameHost(), steps)
    with master_for(session, options, FrameHost()) as master:
        master.load_scene(scene_)
        times = []
        for i in range(frames + 1):
            view = orbit_view(centre, radius, 5.0 * i, 1024, 1024, settings)
            started = time.perf_counter()
            job = master.render(view, **options.job_options())
            while not job.finished:
                job.next_results(0.01)
            times.append(time.perf_counter() - started)
    best = statistics.median(times[1:])      # the first builds the frame's kernels
    print(f"{name}: 1024x1024, one sample: {1 / best:.2f} frames per second "
          f"(median frame {best * 1e3:.0f} ms over {frames})")


# -- stand-in slaves (--standin; the module's docstring says what is modelled)

def standin_calibrations(name, args) -> dict:
    """pass_key -> the cached calibration file of that pass of the orbit's first view."""
    from bench.standin import pass_key
    settings = RenderSettings(samples_per_axis=args.samples, adaptive=False)
    view = orbit_view(np.zeros(3), 1.0, 0, args.width, args.height, settings)
    return {pass_key(v): OUT / f"viewport_standin_{name}_{v.width}x{v.height}_spa"
            f"{v.settings.samples_per_axis}_tile{STANDIN_TILE}.npz"
            for v in passes(view, args.samples)}


def calibrate_standin(args) -> None:
    """--calibrate-standin: the real tracer, one PoCL thread, renders each pass of the orbit's
    first view of --scenes[0] (bench/standin.py calibrate: every tile timed in CPU time)."""
    os.environ["POCL_MAX_PTHREAD_COUNT"] = "1"   # before PoCL starts: one core, as a slave
    from bench.standin import calibrate, pass_key
    from kdtrace.slave.tracer import Tracer
    name = args.scenes[0]
    exported, centre, radius = scene(name)
    session = FrameSession()
    try:
        scene_, *_ = frame_scene(session, exported, standin_options([]), FrameHost(),
                                 Steps(time.perf_counter()))
    finally:
        session.close()
    settings = RenderSettings(samples_per_axis=args.samples, adaptive=False)
    view = orbit_view(centre, radius, 0, args.width, args.height, settings)
    paths = standin_calibrations(name, args)
    tracer = Tracer()
    for pass_view in passes(view, args.samples):
        path = paths[pass_key(pass_view)]
        if path.exists():
            continue
        calibration = calibrate(tracer, scene_, pass_view, [(STANDIN_TILE, STANDIN_TILE)])
        OUT.mkdir(parents=True, exist_ok=True)
        calibration.save(path)
        frame_ms = calibration.frame_ms((STANDIN_TILE, STANDIN_TILE))
        print(f"calibrated {name} {pass_key(pass_view)}: {len(frame_ms)} tiles, "
              f"{sum(frame_ms) / 1000:.2f} s of one core (tile max {max(frame_ms):.0f} ms)",
              flush=True)


def serve_standins(count, first, args) -> None:
    """--serve-standins: host `count` stand-in slaves of --scenes[0]'s calibrations; print
    their ports; run until stdin closes (as bench/many_slaves.py's hosts)."""
    import logging
    from bench.standin import Calibration, PassStandInTracer, serve_tracers
    logging.basicConfig(level=logging.WARNING)
    calibrations = {key: Calibration.load(path)
                    for key, path in standin_calibrations(args.scenes[0], args).items()}
    serve_tracers({f"standin-{i}": PassStandInTracer(calibrations, 1.0, f"standin-{i}")
                   for i in range(first, first + count)})


def standin_host(count, first, name, args):
    """A child process of this script hosting stand-in slaves (--serve-standins)."""
    from bench.standin import HostProcess
    return HostProcess(__file__, "--serve-standins", count, first, "--scenes", name,
                       "--width", args.width, "--height", args.height, "--samples", args.samples)


def standin_options(endpoints) -> FrameOptions:
    """The stand-ins' frames: listed hosts only (their links), the bench's farm secret."""
    from bench.farm import bench_farm
    return FrameOptions(use_zeroconf=False, local_slaves=0, hosts=list(endpoints),
                        secret=bench_farm(), tile_size=STANDIN_TILE)


def standin_figures(name, exported, centre, radius, args, session) -> list:
    """The orbit through each --standin count of stand-in slaves, each count on slaves and
    links of its own (every slave gets the scene anew); the kd-tree is built before (the
    first image is then connect, upload and the first pass)."""
    from bench.standin import HostProcess
    many_slaves = ROOT / "bench" / "many_slaves.py"
    if not all(path.exists() for path in standin_calibrations(name, args).values()):
        subprocess.run([sys.executable, __file__, "--calibrate-standin", "--scenes", name,
                        "--width", str(args.width), "--height", str(args.height),
                        "--samples", str(args.samples)], cwd=ROOT, check=True)
    frame_scene(session, exported, standin_options([]), FrameHost(), Steps(time.perf_counter()))
    rows = []
    for count in args.standin:
        per_host = -(-count // args.hosts)
        hosts = []
        network = None
        try:
            for first in range(0, count, per_host):
                hosts.append(standin_host(min(per_host, count - first), first, name, args))
            ports = [port for host in hosts for port in host.ports]
            if args.link == "link":
                network = HostProcess(many_slaves, "--network", "link", *ports)
                ports = network.ports
            options = standin_options([("127.0.0.1", port) for port in ports])
            children = hosts + ([network] if network else [])
            row = viewport_figures(f"{name}, {count} stand-in slaves", exported, centre, radius,
                                   args, session, options, "connect, upload to every slave, "
                                   "the first pass; the kd-tree built before",
                                   lambda: sum(child.cpu_seconds() for child in children))
            rows.append(dict(row, slaves=count))
        finally:
            if network is not None:
                network.close()
            for host in hosts:
                host.close()
    return rows


def load_average() -> str:
    with open("/proc/loadavg") as handle:
        return " ".join(handle.read().split()[:3])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["dragon", "dragons12"])
    parser.add_argument("--slaves", type=int, default=2)
    parser.add_argument("--changes", type=int, default=60)
    parser.add_argument("--width", type=int, default=960)
    parser.add_argument("--height", type=int, default=540)
    parser.add_argument("--samples", type=int, default=4, help="the viewport's N (N x N)")
    parser.add_argument("--standin", type=int, nargs="+", metavar="N",
                        help="N calibrated stand-in slaves instead of --slaves local ones")
    parser.add_argument("--hosts", type=int, default=4, help="with --standin: host processes")
    parser.add_argument("--link", choices=("link", "loopback"), default="link",
                        help="with --standin: an emulated link per slave (3 ms, 300 Mbit/s) "
                        "or plain loopback")
    parser.add_argument("--calibrate-standin", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--serve-standins", nargs=2, type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.calibrate_standin:
        return calibrate_standin(args)
    if args.serve_standins:
        return serve_standins(*args.serve_standins, args)
    print("command:", " ".join(["python"] + sys.argv))
    slaves = (f"stand-in slaves ({', '.join(map(str, args.standin))}) in {args.hosts} host "
              f"processes" if args.standin else f"{args.slaves} local slave(s) on them")
    print("machine:", cpu_model(), f"({os.cpu_count()} logical CPUs), {slaves}; load average "
          f"{load_average()}", flush=True)
    session = FrameSession()
    if args.standin:
        from bench.farm import bench_farm
        bench_farm()      # one farm secret for the master and every slave of the run
        try:
            for name in args.scenes:
                exported, centre, radius = scene(name)
                for row in standin_figures(name, exported, centre, radius, args, session):
                    print(f"| {name} | {row['slaves']} | {row['first_s']:.2f} s | "
                          f"{row['median_s'] * 1e3:.0f} ms | {row['p95_s'] * 1e3:.0f} ms | "
                          f"{row['max_s'] * 1e3:.0f} ms | {row['spp_per_s']:.1f} | "
                          f"{row['cancel_median_s'] * 1e3:.0f} ms | "
                          f"{row['cpu_s'][0] / row['orbit_s'] * 100:.0f} % | "
                          f"{row['cpu_s'][1] / row['orbit_s'] * 100:.0f} % |")
        finally:
            session.close()
            print("load average at the end:", load_average())
        return
    options = FrameOptions(use_zeroconf=False, local_slaves=args.slaves, local_slaves_always=True,
                           tile_size=64)
    try:
        for name in args.scenes:
            exported, centre, radius = scene(name)
            viewport_figures(name, exported, centre, radius, args, session, options)
            frames_per_second(name, exported, centre, radius, session, options)
    finally:
        session.close()


if __name__ == "__main__":
    main()
