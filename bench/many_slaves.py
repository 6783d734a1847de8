"""Many slaves on one machine: the master, the protocol and emulated links at S = 1..64.

Each slave is a real `slave.server.SlaveServer` with its own listening socket, whose tracer is
the calibrated stand-in of bench/standin.py (it sleeps the real tracer's measured time for each
tile and returns the real tile's bytes). 64 slave processes would not fit this machine, so the
servers run as threads in a few host processes (--hosts). Every connection goes through an
emulated link (tests/linkemu.py) in a network process of its own: "link" = 802.11ac-like link
per slave (3 ms, 300 Mbit/s each way), "shared" = the same latency and one 300 Mbit/s medium for
the traffic of all slaves, both directions. The master runs alone in this process, so its CPU
time (time.process_time) is the master's own.

    flock /tmp/bench.lock .venv/bin/python bench/many_slaves.py [--json out.json] [--png plot.png]
    flock /tmp/bench.lock .venv/bin/python bench/many_slaves.py --counts 64 --profile auto

Calibration (once, cached in bench/out/): the real tracer renders the bench frame with one PoCL
thread at each tile size, timing every tile in CPU time.

The master's denoising (issue 40): the master denoises a frame after its last tile, alone, so
its time adds to the frame's at any S. --denoise-share times Open Image Denoise (core/denoise.py,
Blender's library) on a 1920 x 1080 frame here, for each prefilter and quality, and puts it into
the model's efficiency at 16 and 64 slaves (1920 x 1080 frames of the bench frame's cost per
pixel, and of a given --denoise-spp):

    flock /tmp/bench.lock .venv/bin/python bench/many_slaves.py --denoise-share [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import statistics
import subprocess
import sys
import threading
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench.network_scaling import bench_scene, simulate  # noqa: E402
from bench.standin import (Calibration, HostProcess, StandInTracer, calibrate,  # noqa: E402
                           serve_tracers)
from kdtrace.core.net import protocol  # noqa: E402
from kdtrace.core.net.master import Master  # noqa: E402
from kdtrace.core.net.tiles import TileGrid  # noqa: E402
from kdtrace.core.scene.scene import Scene  # noqa: E402
from tests.linkemu import LinkEmulator, SharedMedium  # noqa: E402
from tests.test_network import make_view, network_settings  # noqa: E402
from bench.farm import bench_farm  # noqa: E402

SIZE = 1024
SAMPLES_PER_AXIS = 4            # 16 samples per pixel: ~25 s of one core per frame
TILE_SIZES = (32, 64, 128, 256)     # calibrated; the master's "auto" picks among these here
LATENCY_S, BANDWIDTH_BPS = 0.003, 300e6
COUNTS = (1, 2, 4, 6, 8, 16, 32, 64)
OUT = ROOT / "bench" / "out"


def bench_view():
    import dataclasses
    return dataclasses.replace(make_view(SIZE, SIZE),
                               settings=network_settings(samples_per_axis=SAMPLES_PER_AXIS))


def calibration_path() -> pathlib.Path:
    return OUT / f"standin_{SIZE}_spa{SAMPLES_PER_AXIS}.npz"


def missing_tile_sizes() -> list:
    path = calibration_path()
    have = Calibration.load(path).tile_sizes() if path.exists() else []
    return [(s, s) for s in TILE_SIZES if (s, s) not in have]


def run_calibration() -> None:
    """Calibrate the tile sizes not yet in the cached file (the frame's pixels are the same
    whatever the tiling, so a new size only adds its tile times)."""
    os.environ["POCL_MAX_PTHREAD_COUNT"] = "1"   # before PoCL starts: one core, as a slave
    from kdtrace.slave.tracer import Tracer
    scene = Scene.from_parts(*bench_scene())
    started = time.perf_counter()
    result = calibrate(Tracer(), scene, bench_view(), missing_tile_sizes())
    if calibration_path().exists():
        cached = Calibration.load(calibration_path())
        cached.tile_ms.update(result.tile_ms)
        result = cached
    OUT.mkdir(parents=True, exist_ok=True)
    result.save(calibration_path())
    for size in TILE_SIZES:
        print(f"calibrated {size}x{size}: {sum(result.frame_ms((size, size))) / 1000:.1f} s of "
              f"one core per frame", flush=True)
    print(f"calibration took {time.perf_counter() - started:.0f} s", flush=True)


# -- child processes: slave hosts and the network

def serve_slaves(count: int, first: int, speeds: list) -> None:
    calibration = Calibration.load(calibration_path())
    serve_tracers({f"standin-{i}": StandInTracer(calibration, speeds[i % len(speeds)],
                                                 f"standin-{i}")
                   for i in range(first, first + count)})


def serve_network(kind: str, ports: list) -> None:
    """One emulated link per slave (kind "link") or one shared medium (kind "shared")."""
    medium = SharedMedium(BANDWIDTH_BPS) if kind == "shared" else None
    links = [LinkEmulator(("127.0.0.1", port), LATENCY_S,
                          None if medium else BANDWIDTH_BPS, medium=medium).start()
             for port in ports]
    print(json.dumps([link.endpoint[1] for link in links]), flush=True)
    sys.stdin.read()
    for link in links:
        link.close()


# -- the master's side

def run_frame(master, view, release=True, **options):
    """One frame, results taken as the add-on's render thread does; with `release` its image
    goes back to the master for the next frame (RenderJob.release)."""
    job = master.render(view, **options)
    count = 0
    while not job.finished:
        count += len(job.next_results(0.05))
    assert job.error is None and count == len(job.tiles), job.error
    job.wait(30)
    if release:
        job.release()
    return job


def measure(endpoints, scene, view, reps, options, warm=True) -> dict:
    """Median frame time and the master's CPU per frame over `reps` frames, after one warm-up
    frame (`warm`): the master learns the slaves' speeds ("auto" sizes) and the tiles' costs
    (it hands out the most expensive first) from it, as it does from one frame to the next."""
    with Master([("127.0.0.1", p) for p in endpoints], name="bench") as master:
        master.connect()
        master.load_scene(scene)
        if warm:
            run_frame(master, view, **options)
        times, cpu, copies = [], [], []
        for _ in range(reps):
            c0 = time.process_time()
            job = run_frame(master, view, **options)
            cpu.append(time.process_time() - c0)
            times.append(job.elapsed_s)
            copies.append(job.duplicates_handed_out)
            tiles = len(job.tiles)
            tile_size = (job.tile_w, job.tile_h)
            windows = sorted({w.window for w in job._workers})
    frame_bytes = SIZE * SIZE * protocol.tile_bytes_per_pixel(options.get("payload", "f32"),
                                                             options.get("passes", ["combined"]))
    return {"tau_s": statistics.median(times), "master_cpu_s": statistics.median(cpu),
            "tiles": tiles, "tile_size": tile_size, "windows": windows, "frame_bytes": frame_bytes,
            "copies": statistics.median(copies)}


def model(calibration, tile_size, count, frame_bytes_per_pixel, shared: bool, in_flight=2) -> float:
    """The event model of bench/network_scaling.py fed with the calibrated tile times, handed
    out as the master does after a first frame: the most expensive first, the cheapest to the
    slots beside each slave's first at the start."""
    grid = TileGrid((0, 0, SIZE, SIZE), tile_size)
    tiles = sorted(zip(calibration.frame_ms(tile_size),
                       [w * h * frame_bytes_per_pixel for (_, _, w, h) in grid]), reverse=True)
    return simulate([t[0] for t in tiles], [t[1] for t in tiles], count, LATENCY_S,
                    BANDWIDTH_BPS, in_flight, shared_bps=BANDWIDTH_BPS if shared else None,
                    cheap_prefetch=True)


def plot_png(path, rows) -> None:
    """Efficiency against S (log2 axis, labelled 1..64) for both link kinds: measured (thick,
    dots) beside the model (thin, paler); blue: a link per slave, red: shared medium; grid
    lines at every 0.1 of efficiency (labelled every 0.2)."""
    from bench.image_error import FONT, write_png
    w, h, margin = 640, 400, 40

    def label(x, y, text, scale=2):
        for k, char in enumerate(text):
            bits = FONT[char]
            for i in range(5):
                for j in range(3):
                    if bits[i * 3 + j] == "1":
                        x0, y0 = x + (k * 4 + j) * scale, y + i * scale
                        img[y0:y0 + scale, x0:x0 + scale] = 0

    img = np.full((h, w, 3), 255, np.uint8)
    xs = lambda s: margin + (np.log2(s) / 6.0) * (w - 2 * margin)
    ys = lambda e: h - margin - min(max(e, 0.0), 1.05) / 1.05 * (h - 2 * margin)
    for e in np.arange(0, 1.01, 0.1):
        img[int(ys(e)), margin:w - margin] = (220, 220, 220) if round(e * 10) % 5 else (150, 150, 150)
    for s in (1, 2, 4, 8, 16, 32, 64):
        img[margin:h - margin, int(xs(s))] = (200, 200, 200)
        label(int(xs(s)) - 4 * len(str(s)), h - margin + 8, str(s))
    for e in (0.0, 0.2, 0.4, 0.6, 0.8, 1.0):
        label(4, int(ys(e)) - 5, f"{e:.1f}")

    def line(points, color, width):
        for (x0, y0), (x1, y1) in zip(points, points[1:]):
            for t in np.linspace(0, 1, 200):
                x, y = int(x0 + t * (x1 - x0)), int(y0 + t * (y1 - y0))
                img[max(0, y - width):y + width + 1, max(0, x - width):x + width + 1] = color

    colors = {"link": (30, 90, 200), "shared": (210, 60, 30)}
    for kind, color in colors.items():
        mine = [r for r in rows if r["link"] == kind]
        measured = [(xs(r["S"]), ys(r["efficiency"])) for r in mine]
        modelled = [(xs(r["S"]), ys(r["model_efficiency"])) for r in mine]
        line(modelled, tuple(int(c + (255 - c) * 0.55) for c in color), 0)
        line(measured, color, 1)
        for x, y in measured:
            img[int(y) - 3:int(y) + 4, int(x) - 3:int(x) + 4] = color
    write_png(path, img)


DENOISE_SIZE = (1920, 1080)
DENOISE_COUNTS = (1, 16, 64)


def denoise_seconds(width: int, height: int, repeat: int = 3) -> dict:
    """Open Image Denoise's time on a width x height frame here, per (prefilter, quality): the
    bench frame's image (the calibration's Combined, repeated to size) with a grey albedo and
    its normals as guides; the fastest of `repeat` (the device is made before, as the master's
    session keeps it)."""
    from kdtrace.core.denoise import PREFILTERS, QUALITIES, Denoiser
    image = Calibration.load(calibration_path()).image
    reps = (-(-height // SIZE), -(-width // SIZE), 1)
    colour = np.tile(image["combined"], reps)[:height, :width]
    normal = np.tile(image["normal"], reps)[:height, :width]
    albedo = np.full((height, width, 3), 0.6, np.float32)
    seconds = {}
    with Denoiser() as denoiser:
        denoiser.denoise(colour[:64, :64], albedo[:64, :64], normal[:64, :64])
        for prefilter in PREFILTERS[::-1]:
            for quality in QUALITIES:
                times = []
                for _ in range(repeat):
                    started = time.perf_counter()
                    denoiser.denoise(colour, albedo, normal, prefilter=prefilter, quality=quality)
                    times.append(time.perf_counter() - started)
                seconds[f"{prefilter}/{quality}"] = min(times)
                print(f"OIDN {width}x{height} {prefilter:8s} {quality:8s} {min(times):6.2f} s",
                      flush=True)
    return seconds


def denoise_share(args) -> dict:
    """--denoise-share (module docstring): the model's frame time tau_S of a 1920 x 1080 frame
    (the calibrated frame's tile times scaled by the pixels, auto tile size, a link per slave,
    Combined and the guides in f32: 40 bytes a pixel) with and without the master's denoising
    at its default (prefilter Accurate, quality High) and fastest settings; efficiency
    tau_1 / (S tau_S), the denoising in both."""
    from kdtrace.core.net.master import auto_tile_size
    width, height = DENOISE_SIZE
    scale = width * height / (SIZE * SIZE)
    calibration = Calibration.load(calibration_path())
    seconds = denoise_seconds(width, height)
    bpp = protocol.tile_bytes_per_pixel("f32", ["combined", "albedo", "denoising_normal"])
    per_pixel_spp = SAMPLES_PER_AXIS ** 2
    rows = []
    for spp in (per_pixel_spp, args.denoise_spp):
        for count in DENOISE_COUNTS:
            edge = auto_tile_size((0, 0, SIZE, SIZE), count)[0]   # on the calibrated frame
            size = min(TILE_SIZES, key=lambda s: abs(s - edge))
            work = scale * spp / per_pixel_spp
            tau = {s: model(calibration, (size, size), s, bpp, False) * work for s in (1, count)}
            row = {"spp": spp, "S": count, "tile": size, "tau_s": tau[count]}
            for setting in ("ACCURATE/HIGH", "FAST/FAST"):
                dn = seconds[setting]
                row[f"share {setting}"] = dn / (tau[count] + dn)
                row[f"efficiency {setting}"] = (tau[1] + dn) / (count * (tau[count] + dn))
            row["efficiency"] = tau[1] / (count * tau[count])
            rows.append(row)
            print(f"{spp:4d} spp S={count:2d} tile {size:3d}: frame {tau[count]:8.2f} s; "
                  f"denoise share {row['share ACCURATE/HIGH'] * 100:5.1f} % (Accurate/High), "
                  f"{row['share FAST/FAST'] * 100:5.1f} % (Fast/Fast); efficiency "
                  f"{row['efficiency']:.3f} -> {row['efficiency ACCURATE/HIGH']:.3f} "
                  f"({row['efficiency FAST/FAST']:.3f})", flush=True)
    with open("/proc/loadavg") as handle:
        load = handle.read().split()[:3]
    out = {"command": " ".join([os.path.relpath(sys.executable, ROOT)] + sys.argv),
           "machine": f"{platform.node()}, {os.cpu_count()} cores", "load_average": load,
           "size": [width, height], "oidn_seconds": seconds, "rows": rows}
    save(args.json, out)
    return out


def master_cost(scene, view, reps, ports) -> list:
    """The master's CPU per frame at 64 slaves (per-link) with 16, 64, 256 and 1024 tiles: a
    fixed part per frame and a part per tile (least squares)."""
    rows = []
    for size in (256, 128, 64, 32):
        options = {"tile_size": size, "tiles_in_flight": 2, "passes": ["combined"],
                   "payload": "f32"}
        r = measure(ports, scene, view, reps, options)
        rows.append(r)
        print(f"master cost, 64 slaves, {r['tiles']} tiles of {size}: "
              f"{r['master_cpu_s'] * 1e3:.1f} ms CPU/frame, frame {r['tau_s'] * 1e3:.1f} ms",
              flush=True)
    tiles = np.array([r["tiles"] for r in rows], float)
    cpu = np.array([r["master_cpu_s"] for r in rows])
    per_tile, per_frame = np.polyfit(tiles, cpu, 1)
    print(f"master CPU = {per_frame * 1e3:.1f} ms per frame + {per_tile * 1e6:.0f} us per tile",
          flush=True)
    return {"rows": rows, "per_frame_s": per_frame, "per_tile_s": per_tile}


def thread_stat(native_id: int) -> tuple:
    """(user s, system s, minor page faults) of one thread of this process, from /proc."""
    fields = pathlib.Path(f"/proc/self/task/{native_id}/stat").read_text().rsplit(")", 1)[1].split()
    tick = os.sysconf("SC_CLK_TCK")
    return int(fields[11]) / tick, int(fields[12]) / tick, int(fields[7])


def profile_loop(ports, scene, view, reps, tile_size) -> None:
    """The frame loop's own CPU per frame (time.thread_time on its thread; user and system
    time, in 10 ms ticks, and minor page faults from /proc: medians over the frames), frames
    written into the released image of the frame before alternating with frames written into
    a new image, then a cProfile of
    it in thread CPU time (which inflates Python calls about 2.5 x)."""
    import cProfile
    import pstats
    options = {"tile_size": tile_size, "tiles_in_flight": 2, "passes": ["combined"],
               "payload": "f32"}
    profile = cProfile.Profile(time.thread_time)
    with Master([("127.0.0.1", p) for p in ports], name="bench") as master:
        master.connect()
        master.load_scene(scene)
        run_frame(master, view, release=False, **options)
        loop = master._frame_loop()

        def on_loop(function):
            done = threading.Event()
            box = []
            loop.call(lambda: (box.append(function()), done.set()))
            done.wait()
            return box[0]

        # frames written into the image of the frame before (RenderJob.release) alternate
        # with frames written into a new one, side by side
        cpu, stats = {True: [], False: []}, {True: [], False: []}
        for rep in range(2 * reps):
            reused = rep % 2 == 1        # the frame before released its image
            c0, s0 = on_loop(time.thread_time), thread_stat(loop.thread.native_id)
            job = run_frame(master, view, release=not reused, **options)
            cpu[reused].append(on_loop(time.thread_time) - c0)
            stats[reused].append([b - a for a, b in zip(s0, thread_stat(loop.thread.native_id))])
            last = stats[reused][-1]
            print(f"{len(ports)} slaves, {len(job.tiles)} tiles of {job.tile_w}, "
                  f"{'image reused' if reused else 'new image'}: frame {job.elapsed_s * 1e3:.0f} ms, "
                  f"frame loop CPU {cpu[reused][-1] * 1e3:.1f} ms (user {last[0] * 1e3:.0f}, "
                  f"system {last[1] * 1e3:.0f} ms, {last[2]} minor faults)", flush=True)
        for reused in (False, True):
            mine = stats[reused]
            print(f"{'image reused' if reused else 'new image'}, median of {reps}: frame loop CPU "
                  f"{statistics.median(cpu[reused]) * 1e3:.1f} ms a frame, user "
                  f"{statistics.median(s[0] for s in mine) * 1e3:.0f} ms, system "
                  f"{statistics.median(s[1] for s in mine) * 1e3:.0f} ms, "
                  f"{statistics.median(s[2] for s in mine):.0f} minor faults", flush=True)
        on_loop(profile.enable)
        for _ in range(reps):
            run_frame(master, view, **options)
        on_loop(profile.disable)
    pstats.Stats(profile).sort_stats("tottime").print_stats(30)


def mixed_speeds(scene, view, reps, count=16) -> list:
    """Half the slaves three times as fast as the others (per-link emulation): fixed tile
    size and tiles in flight against the master's choices from the slaves' speeds. Efficiency
    here: the ideal time (all work spread in proportion to speed) over the measured."""
    speeds = [1.0, 3.0]
    calibration = Calibration.load(calibration_path())
    host = HostProcess(__file__, "--serve", count, 0, "--speeds", ",".join(map(str, speeds)))
    network = HostProcess(__file__, "--network", "link", *map(str, host.ports))
    rows = []
    try:
        total_speed = sum(speeds[i % 2] for i in range(count))
        for tile_size in (128, "auto"):
            for in_flight in (2, "auto"):
                options = {"tile_size": tile_size, "tiles_in_flight": in_flight,
                           "passes": ["combined"], "payload": "f32"}
                r = measure(network.ports, scene, view, reps, options)
                size = r["tile_size"][0]
                ideal = sum(calibration.frame_ms((size, size))) / 1000 / total_speed
                r.update(tile_option=tile_size, in_flight_option=in_flight,
                         efficiency=ideal / r["tau_s"])
                rows.append(r)
                print(f"mixed speeds 1/3 x{count}: tile {tile_size} ({size}), in flight "
                      f"{in_flight} {r['windows']}: {r['tau_s'] * 1e3:.1f} ms, efficiency "
                      f"{r['efficiency']:.3f}, master CPU {r['master_cpu_s'] * 1e3:.1f} ms/frame",
                      flush=True)
    finally:
        network.close()
        host.close()
    return rows


def markdown(out) -> str:
    """The tables of docs/distributed.md ("Many slaves") from a --json result."""
    lines = ["| link | payload | S | tile | tiles in flight | frame ms | efficiency | model ms | "
             "model efficiency | tiles/s | master CPU ms/frame | us/tile | ms/MiB | % of a core |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in out["rows"]:
        lines.append(
            f"| {r['link']} | {r['payload']} | {r['S']} | {r['tile_size'][0]} | "
            f"{min(r['windows'])}-{max(r['windows'])} | {r['tau_s'] * 1e3:.0f} | "
            f"{r['efficiency']:.2f} | {r['model_tau_s'] * 1e3:.0f} | {r['model_efficiency']:.2f} | "
            f"{r['tiles_per_s']:.0f} | {r['master_cpu_s'] * 1e3:.0f} | "
            f"{r['master_cpu_per_tile_us']:.0f} | {r['master_cpu_per_mib_ms']:.1f} | "
            f"{r['master_cpu_share'] * 100:.1f} |")
    if "master_cost" in out:
        lines += ["", "| tiles (64 slaves) | tile | master CPU ms/frame | frame ms |", "|---|---|---|---|"]
        for r in out["master_cost"]["rows"]:
            lines.append(f"| {r['tiles']} | {r['tile_size'][0]} | {r['master_cpu_s'] * 1e3:.0f} | "
                         f"{r['tau_s'] * 1e3:.0f} |")
        cost = out["master_cost"]
        lines.append(f"\nfit: {cost['per_frame_s'] * 1e3:.1f} ms per frame + "
                     f"{cost['per_tile_s'] * 1e6:.0f} us per tile")
    if "mixed" in out:
        lines += ["", "| tile size | tiles in flight | tile | windows | frame ms | efficiency | copies |",
                  "|---|---|---|---|---|---|---|"]
        for r in out["mixed"]:
            lines.append(f"| {r['tile_option']} | {r['in_flight_option']} | {r['tile_size'][0]} | "
                         f"{min(r['windows'])}-{max(r['windows'])} | {r['tau_s'] * 1e3:.0f} | "
                         f"{r['efficiency']:.2f} | {r['copies']:.0f} |")
    return "\n".join(lines)


def save(path, out) -> None:
    if path:
        pathlib.Path(path).write_text(json.dumps(out, indent=1))


def main():
    bench_farm()      # one farm secret for the master and every slave of the run
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=2)
    parser.add_argument("--hosts", type=int, default=4, help="slave host processes")
    parser.add_argument("--counts", default=",".join(map(str, COUNTS)))
    parser.add_argument("--no-mixed", action="store_true", help="skip the mixed-speed runs")
    parser.add_argument("--json", default=None)
    parser.add_argument("--png", default=None)
    parser.add_argument("--table", default=None, help="print the Markdown tables of a --json file")
    parser.add_argument("--profile", default=None, metavar="TILE",
                        help="only profile the frame loop at the largest count, tile size TILE")
    parser.add_argument("--calibrate", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--serve", nargs=2, type=int, help=argparse.SUPPRESS)
    parser.add_argument("--speeds", default="1")
    parser.add_argument("--denoise-share", action="store_true",
                        help="the master's denoising of a 1920 x 1080 frame in the efficiency")
    parser.add_argument("--denoise-spp", type=int, default=256,
                        help="with --denoise-share: also frames of this many samples a pixel")
    parser.add_argument("--network", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.table:
        return print(markdown(json.loads(pathlib.Path(args.table).read_text())))
    if args.calibrate:
        return run_calibration()
    if args.serve:
        return serve_slaves(*args.serve, [float(s) for s in args.speeds.split(",")])
    if args.network:
        return serve_network(args.network[0], [int(p) for p in args.network[1:]])
    if args.denoise_share:
        return denoise_share(args)

    counts = [int(c) for c in args.counts.split(",")]
    if missing_tile_sizes():
        subprocess.run([sys.executable, __file__, "--calibrate"], cwd=ROOT, check=True)
    calibration = Calibration.load(calibration_path())
    scene, view = Scene.from_parts(*bench_scene()), bench_view()
    with open("/proc/loadavg") as handle:
        load = handle.read().split()[:3]
    out = {"command": " ".join([os.path.relpath(sys.executable, ROOT)] + sys.argv),
           "machine": f"{platform.node()}, {os.cpu_count()} cores, Python {platform.python_version()}",
           "load_average_at_start": load, "size": SIZE, "samples_per_axis": SAMPLES_PER_AXIS,
           "one_core_frame_s": {s: sum(calibration.frame_ms((s, s))) / 1000 for s in TILE_SIZES}}
    print(json.dumps(out), flush=True)
    most = max(counts)
    per_host = -(-most // args.hosts)
    hosts = [HostProcess(__file__, "--serve", min(per_host, most - i), i, "--speeds", args.speeds)
             for i in range(0, most, per_host)]
    ports = [p for host in hosts for p in host.ports]
    if args.profile:
        network = HostProcess(__file__, "--network", "link", *map(str, ports))
        try:
            size = args.profile if args.profile == "auto" else int(args.profile)
            return profile_loop(network.ports, scene, view, args.reps, size)
        finally:
            network.close()
            for host in hosts:
                host.close()
    # tau_1: one slave, float32, its own link, at its tile size; at another tile size scaled by
    # the calibrated work of that tiling (the calibrated frames differ by some % between tile
    # sizes: per-tile costs and timing noise), so that efficiency compares like with like
    one_core = {(s, s): sum(calibration.frame_ms((s, s))) for s in TILE_SIZES}
    rows, base = [], None
    try:
        for kind in ("link", "shared"):
            network = HostProcess(__file__, "--network", kind, *map(str, ports))
            try:
                for count in counts:
                    if kind == "shared" and count == 1:
                        continue    # one slave alone: the medium is its link (measured above)
                    for payload in (("f32", "u8") if kind == "shared" else ("f32",)):
                        options = {"tile_size": "auto", "tiles_in_flight": 2,
                                   "passes": ["combined"], "payload": payload}
                        net0 = network.cpu_seconds()
                        # one slave: no warm-up (nothing to learn), one frame (~30 s)
                        r = measure(network.ports[:count], scene, view,
                                    1 if count <= 2 else args.reps, options, warm=count > 1)
                        r["network_cpu_s_total"] = network.cpu_seconds() - net0
                        if count == 1:
                            base = r["tau_s"] / one_core[tuple(r["tile_size"])]
                        tau_1 = base * one_core[tuple(r["tile_size"])] if base else float("nan")
                        bpp = protocol.tile_bytes_per_pixel(payload, ["combined"])
                        m1 = model(calibration, r["tile_size"], 1, bpp, kind == "shared")
                        ms = model(calibration, r["tile_size"], count, bpp, kind == "shared")
                        r.update(link=kind, S=count, payload=payload, tau_1_s=tau_1,
                                 efficiency=tau_1 / (count * r["tau_s"]),
                                 model_tau_s=ms, model_efficiency=m1 / (count * ms),
                                 master_cpu_per_tile_us=r["master_cpu_s"] / r["tiles"] * 1e6,
                                 master_cpu_per_mib_ms=r["master_cpu_s"] / (r["frame_bytes"] / 2 ** 20) * 1e3,
                                 tiles_per_s=r["tiles"] / r["tau_s"],
                                 master_cpu_share=r["master_cpu_s"] / r["tau_s"])
                        rows.append(r)
                        save(args.json, dict(out, rows=rows))
                        print(f"{kind:6s} {payload} S={count:2d} tile {r['tile_size'][0]:3d} "
                              f"windows {r['windows']} copies {r['copies']}: "
                              f"{r['tau_s'] * 1e3:8.1f} ms "
                              f"eff {r['efficiency']:.3f} (model {r['model_efficiency']:.3f}, "
                              f"{ms * 1e3:.1f} ms)  master CPU {r['master_cpu_s'] * 1e3:.1f} ms/frame "
                              f"= {r['master_cpu_per_tile_us']:.0f} us/tile, "
                              f"{r['master_cpu_per_mib_ms']:.2f} ms/MiB, "
                              f"{r['master_cpu_share'] * 100:.1f} % of a core", flush=True)
                if kind == "link" and most >= 64:
                    out["master_cost"] = master_cost(scene, view, args.reps, network.ports[:64])
            finally:
                network.close()
    finally:
        for host in hosts:
            host.close()
    out["rows"] = rows
    save(args.json, out)
    if not args.no_mixed:
        out["mixed"] = mixed_speeds(scene, view, args.reps)
    save(args.json, out)
    if args.png:
        plot_png(args.png, [r for r in rows if r["payload"] == "f32"])


if __name__ == "__main__":
    main()
