"""Issue 35's benchmark: the viewport's Rendered mode through local slaves (core/frame/viewport.py,
the session the add-on's view_update and view_draw drive), without Blender.

    .venv/bin/python bench/viewport.py [--scenes dragon dragons12] [--slaves 2] [--changes 60]
                                       [--width 960 --height 540] [--samples 4]

For each scene: the session's first image after the scene is given (kd-tree and upload
included); a scripted orbit of --changes view changes (3 degrees each; each change made once
the previous one's first image is drawn, as a user dragging the view sees it): the latency from
a change to the first image of the new view, median and 95th percentile; once still, the
samples per pixel per second while it refines to --samples x --samples; and the paper's
figure, frames per second of a 1024 x 1024 image at one sample (camera and shadow rays, a sun)
through the same slaves. The dragon is the Stanford dragon (npm); dragons12 is 12 of them in
one mesh (10.5 M triangles), on a 4 x 3 grid. Local slaves share this machine's cores.
"""
import argparse
import dataclasses
import os
import pathlib
import statistics
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from bench.trace_vs_embree import cpu_model  # noqa: E402
from core.frame.exported import InstancedExport  # noqa: E402
from core.frame.options import FrameOptions  # noqa: E402
from core.frame.render import FrameHost, Steps, frame_scene, master_for  # noqa: E402
from core.frame.session import FrameSession  # noqa: E402
from core.frame.viewport import ViewportSession, passes  # noqa: E402
from core.scene.model import (Camera, Geometry, Light, RenderSettings, Shading, View,  # noqa: E402
                              default_material_params)
from tests.meshes import load_dragon, look_at  # noqa: E402


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


def viewport_figures(name, exported, centre, radius, args, session, options):
    settings = RenderSettings(samples_per_axis=args.samples, adaptive=False)
    viewport = ViewportSession(session, options, samples_per_axis=args.samples)
    try:
        started = time.perf_counter()
        epoch = viewport.update(orbit_view(centre, radius, 0, args.width, args.height, settings),
                                exported)
        wait_for(lambda: (viewport.image() or None) and viewport.image().epoch == epoch)
        first = time.perf_counter() - started
        latencies = []
        for step in range(1, args.changes + 1):
            view = orbit_view(centre, radius, 3.0 * step, args.width, args.height, settings)
            changed = time.perf_counter()
            epoch = viewport.update(view)
            wait_for(lambda: viewport.image().epoch == epoch)
            latencies.append(time.perf_counter() - changed)
        still = time.perf_counter()
        wait_for(viewport.done)
        refine = time.perf_counter() - still
        assert not viewport.error, viewport.error
        samples = sum(v.settings.samples_per_axis ** 2 for v in passes(view, args.samples)
                      if v.width == view.width)       # the full-resolution passes' samples
        latencies.sort()
        p95 = latencies[min(len(latencies) - 1, int(round(0.95 * len(latencies))) - 1)]
        print(f"{name}: first image {first:.2f} s (kd-tree and upload included); "
              f"{len(latencies)} changes: latency median {statistics.median(latencies) * 1e3:.0f} "
              f"ms, 95th percentile {p95 * 1e3:.0f} ms, max {latencies[-1] * 1e3:.0f} ms; once "
              f"still: {samples} samples per pixel in {refine:.2f} s = {samples / refine:.1f} "
              f"samples per pixel per second at {args.width}x{args.height}; cancels confirmed "
              f"in median {statistics.median(viewport.cancel_seconds or [0]) * 1e3:.0f} ms")
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


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["dragon", "dragons12"])
    parser.add_argument("--slaves", type=int, default=2)
    parser.add_argument("--changes", type=int, default=60)
    parser.add_argument("--width", type=int, default=960)
    parser.add_argument("--height", type=int, default=540)
    parser.add_argument("--samples", type=int, default=4, help="the viewport's N (N x N)")
    args = parser.parse_args()
    print("command:", " ".join(["python"] + sys.argv))
    print("machine:", cpu_model(), f"({os.cpu_count()} logical CPUs), {args.slaves} local "
          "slave(s) on them")
    session = FrameSession()
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
