"""Distributed runtime benchmarks (Tables 4, 5a, 5b of Seo, Kim & Ihm 2017) on emulated links.

Slaves are local `python -m kdtrace.slave` processes, each pinned to its own core (taskset) with one
PoCL thread; the master runs in this process. Every master-slave connection goes through
tests.linkemu.LinkEmulator (per connection and direction: latency + bandwidth), e.g. 802.11ac-like
3 ms / 300 Mbit/s, or "loopback" (no emulation). Results go to stdout as Markdown and to --json.

    .venv/bin/python bench/network_scaling.py [--size 1024] [--reps 3] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import math
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

from kdtrace.core.accel.kdtree import build_kdtree  # noqa: E402
from tests.linkemu import LinkEmulator  # noqa: E402
from kdtrace.core.net.master import Master  # noqa: E402
from kdtrace.core.net.protocol import ALL_PASSES, tile_bytes_per_pixel  # noqa: E402
from kdtrace.core.scene.model import Geometry  # noqa: E402
from kdtrace.core.scene.scene import Scene  # noqa: E402
from tests.meshes import grid_plane, load_bunny, merge, uv_sphere  # noqa: E402
from tests.test_network import make_view  # noqa: E402
from bench.farm import bench_farm  # noqa: E402

LINKS = {"wifi": (0.003, 300e6), "loopback": (0.0, None)}


def bench_scene(copies: int = 1):
    v, t = load_bunny()
    bunny = (v[:, [0, 2, 1]] * np.array([0.2, -0.2, 0.2], np.float32)).astype(np.float32)
    meshes = [grid_plane(8.0, 8, 0.0), uv_sphere(24, 12, 0.6, (1.8, 0.5, 0.6))]
    for i in range(copies):
        shift = np.array([(i % 4) * 0.05, (i // 4) * 0.05, 0.0], np.float32)
        meshes.append((bunny + shift, t))
    vertices, triangles = merge(*meshes)
    material_ids = np.zeros(len(triangles), np.uint16)
    material_ids[:128] = 1
    geometry = Geometry(vertices, triangles, material_ids)
    return geometry, build_kdtree(geometry.vertices, geometry.triangles)


class Slaves:
    def __init__(self, count: int):
        self.procs, self.endpoints = [], []
        cores = os.cpu_count() or 1
        for i in range(count):
            env = dict(os.environ, POCL_MAX_PTHREAD_COUNT="1", PYTHONUNBUFFERED="1")
            cmd = [sys.executable, "-m", "kdtrace.slave", "--port", "0", "--bind", "127.0.0.1",
                   "--no-zeroconf", "--name", f"bench-{i}"]
            if cores > 1:
                cmd = ["taskset", "-c", str(i % cores)] + cmd
            proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, text=True)
            line = proc.stdout.readline()
            port = int(line.split("listening on 127.0.0.1:")[1].split()[0])
            self.procs.append(proc)
            self.endpoints.append(("127.0.0.1", port))

    def close(self):
        for proc in self.procs:
            proc.terminate()
            proc.wait(10)


def run_frame(master, view, **options):
    job = master.render(view, **options)
    results = []
    while not job.finished:
        result = job.next_result(0.05)
        if result is not None:
            results.append(result)
    assert job.error is None and len(results) == len(job.tiles), job.error
    job.wait(30)
    return job, results


class Session:
    """S slaves behind emulated links and one master connected through them."""

    def __init__(self, slaves: Slaves, count: int, link: str, scene):
        latency, bandwidth = LINKS[link]
        self.links = [LinkEmulator(ep, latency, bandwidth).start() for ep in slaves.endpoints[:count]]
        self.master = Master([l.endpoint for l in self.links], name="bench")
        self.master.connect()
        start = time.perf_counter()
        self.master.load_scene(Scene.from_parts(*scene))
        self.load_s = time.perf_counter() - start

    def close(self):
        self.master.close()
        for link in self.links:
            link.close()


def timed(session, view, reps, **options):
    run_frame(session.master, view, **options)  # warm: kernels, device upload
    times, per_tile = [], []
    for _ in range(reps):
        job, results = run_frame(session.master, view, **options)
        times.append(job.elapsed_s)
        per_tile = [(r.index, r.w * r.h, r.render_ms) for r in results]
    return statistics.median(times), per_tile, job


def simulate(tile_ms, tile_bytes, slaves, link_latency_s, bandwidth_bps, in_flight=2,
             master_ms_per_mib=0.0, shared_bps=None, cheap_prefetch=False):
    """Event model of model 3b: tiles handed out in the given order to the slave whose request
    arrives first (each slave keeps `in_flight` requests outstanding; with `cheap_prefetch`, as
    the master does when it knows the tiles' costs and gets them most expensive first, the
    requests beyond a slave's first at the start of the frame take the last tiles of the order
    instead); per slave the device
    renders its tiles back to back; a finished tile goes out over the slave's own link
    (serialised per link) while the next renders; a request costs one latency; the master
    handles tiles one at a time in arrival order (master_ms_per_mib); shared_bps: one medium
    shared by all slaves instead of a link each, serialised in time order. Events are
    processed in time order. Returns the frame time in seconds."""
    import heapq
    n = len(tile_ms)
    device_free = [0.0] * slaves
    link_free = [0.0] * slaves
    medium_free = master_free = finish = 0.0
    # (time, kind, slave, tile): kind 0 = a request reaches the slave (tile -2: one of the
    # first fill beyond the first), 1 = its device is done with the tile, 2 = the tile has
    # reached the master
    events = [(link_latency_s, 0, s, -2 if k else -1) for s in range(slaves)
              for k in range(in_flight)]
    heapq.heapify(events)
    first, last = 0, n     # tiles first..last-1 of the order are pending
    while events:
        t, kind, s, index = heapq.heappop(events)
        if kind == 0:
            if first == last:
                continue
            if cheap_prefetch and index == -2:
                last -= 1
                index = last
            else:
                index, first = first, first + 1
            device_free[s] = max(t, device_free[s]) + tile_ms[index] / 1000.0
            heapq.heappush(events, (device_free[s], 1, s, index))
        elif kind == 1:
            seconds = tile_bytes[index] * 8.0 / (shared_bps or bandwidth_bps or math.inf)
            if shared_bps:
                medium_free = sent = max(t, medium_free) + seconds
            else:
                link_free[s] = sent = max(t, link_free[s]) + seconds
            heapq.heappush(events, (sent + link_latency_s, 2, s, index))
        else:
            master_free = max(t, master_free) + master_ms_per_mib * tile_bytes[index] / 2 ** 20 / 1000
            finish = max(finish, master_free)
            heapq.heappush(events, (master_free + link_latency_s, 0, s, -1))  # the next request
    return finish


def main():
    bench_farm()      # one farm secret for the master and every slave of the run
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=1024, help="image width and height")
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--slaves", type=int, default=min(os.cpu_count() or 1, 8))
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    out = {"machine": f"{platform.node()} {platform.processor() or platform.machine()}, "
                      f"{os.cpu_count()} cores, Python {platform.python_version()}",
           "size": args.size}
    view = make_view(args.size, args.size)
    scene = bench_scene()
    print(f"scene: {scene[0].triangle_count} triangles; image {args.size}x{args.size}; "
          f"{args.slaves} slave(s)", flush=True)
    slaves = Slaves(args.slaves)
    try:
        # -- Table 5a: efficiency over S, per link and partition
        rows, tiles_1 = [], {}
        for link in ("wifi", "loopback"):
            for part in (4, 8):
                tau1 = None
                for count in range(1, args.slaves + 1):
                    session = Session(slaves, count, link, scene)
                    tau, per_tile, job = timed(session, view, args.reps, partition=part)
                    session.close()
                    tau1 = tau if count == 1 else tau1
                    if count == 1:
                        tiles_1[(link, part)] = per_tile
                    eff = tau1 / (count * tau)
                    rows.append({"link": link, "partition": part, "S": count, "tau_ms": tau * 1e3,
                                 "efficiency": eff})
                    print(f"5a {link:8s} {part}x{part} S={count}: {tau*1e3:8.1f} ms  eff {eff:.3f}",
                          flush=True)
        out["table5a"] = rows

        # -- Table 5b: partitions, wifi link
        rows = []
        for count in sorted({1, args.slaves}):
            session = Session(slaves, count, "wifi", scene)
            for part in (2, 4, 8, 16):
                tau, per_tile, _ = timed(session, view, args.reps, partition=part)
                tiles_1.setdefault(("wifi", part), per_tile) if count == 1 else None
                rows.append({"S": count, "partition": part, "tau_ms": tau * 1e3})
                print(f"5b wifi S={count} {part}x{part}: {tau*1e3:8.1f} ms", flush=True)
            session.close()
        out["table5b"] = rows

        # -- Table 4: model 3a vs 3b, wifi, 4x4
        rows = []
        for count in sorted({1, args.slaves}):
            session = Session(slaves, count, "wifi", scene)
            for part in (4, 8):
                ta, _, _ = timed(session, view, args.reps, partition=part, model="3a")
                tb, _, _ = timed(session, view, args.reps, partition=part, model="3b")
                rows.append({"S": count, "partition": part, "3a_ms": ta * 1e3, "3b_ms": tb * 1e3})
                print(f"4  wifi S={count} {part}x{part}: 3a {ta*1e3:8.1f} ms  3b {tb*1e3:8.1f} ms "
                      f"({tb/ta*100:.1f} %)", flush=True)
            session.close()
        out["table4"] = rows

        # -- payloads: float32 / float16 / + zlib, wifi, all slaves, 8x8
        rows = []
        session = Session(slaves, args.slaves, "wifi", scene)
        reference = None
        for payload, compress in (("f32", False), ("f32", True), ("f16", False), ("f16", True)):
            tau, _, _ = timed(session, view, args.reps, partition=8, payload=payload, compress=compress)
            job, results = run_frame(session.master, view, partition=8, payload=payload, compress=compress)
            image = np.zeros((args.size, args.size, 4), np.float32)
            for r in results:
                image[r.y:r.y + r.h, r.x:r.x + r.w] = r.passes["combined"]
            reference = image if reference is None else reference
            err = np.abs(image - reference)
            link_bytes = sum(d.bytes for l in session.links for d in l.directions)
            rows.append({"payload": payload, "zlib": compress, "tau_ms": tau * 1e3,
                         "max_abs_err": float(err.max()), "mean_abs_err": float(err.mean())})
            print(f"payload {payload} zlib={compress}: {tau*1e3:8.1f} ms  max err {err.max():.2e} "
                  f"mean err {err.mean():.2e}", flush=True)
        session.close()
        out["payload"] = rows

        # -- scene upload and time to first tile with a cached scene (wifi, one slave)
        rows = []
        for copies in (1, 8):
            big = bench_scene(copies)
            session = Session(slaves, 1, "wifi", big)      # uploads (a new scene for this slave)
            upload_s = session.load_s
            session.close()
            start = time.perf_counter()
            session = Session(slaves, 1, "wifi", big)      # a second master: cached
            job = session.master.render(view, partition=8)
            while job.next_result(0.01) is None:
                pass
            first = time.perf_counter() - start
            job.cancel()
            job.wait(30)
            session.close()
            nbytes = sum(a.nbytes for a in Scene.from_parts(*big).wire_arrays().values())
            rows.append({"triangles": big[0].triangle_count, "bytes": nbytes, "upload_s": upload_s,
                         "cached_connect_to_first_tile_s": first})
            print(f"scene {big[0].triangle_count} tris {nbytes/2**20:.1f} MiB: upload+load {upload_s*1e3:.0f} ms; "
                  f"cached: connect..first tile {first*1e3:.0f} ms", flush=True)
        out["scene"] = rows

        # -- the model, fed with the one-slave per-tile compute times
        rows = []
        latency, bandwidth = LINKS["wifi"]
        for part in (4, 8, 16):
            per_tile = sorted(tiles_1[("wifi", part)])
            ms = [p[2] for p in per_tile]
            nbytes = [p[1] * tile_bytes_per_pixel("f32", ALL_PASSES) for p in per_tile]
            t1 = simulate(ms, nbytes, 1, latency, bandwidth)
            for count in (1, 2, 6, 16, 64):
                ts = simulate(ms, nbytes, count, latency, bandwidth)
                shared = simulate(ms, nbytes, count, latency, bandwidth, shared_bps=bandwidth)
                shared1 = simulate(ms, nbytes, 1, latency, bandwidth, shared_bps=bandwidth)
                measured = next((r["tau_ms"] for r in out["table5a"]
                                 if r["link"] == "wifi" and r["partition"] == part and r["S"] == count), None)
                rows.append({"partition": part, "S": count, "predicted_ms": ts * 1e3,
                             "efficiency": t1 / (count * ts),
                             "efficiency_shared_medium": shared1 / (count * shared),
                             "measured_ms": measured})
                print(f"model {part}x{part} S={count}: {ts*1e3:8.1f} ms eff {t1/(count*ts):.3f} "
                      f"(shared medium {shared1/(count*shared):.3f})"
                      + (f"  measured {measured:.1f} ms" if measured else ""), flush=True)
        out["model"] = rows
    finally:
        slaves.close()
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
