"""Primary-ray throughput of our intersect() against Embree (embreex), both on ONE core.

    python bench/trace_vs_embree.py [--size 1024] [--repeat 3]

Dragon (871,414 triangles), size x size pinhole rays from a camera framing it. Reports rays/s
for both, the ratio, and how many rays agree (same hit/miss; same triangle or the same t).
"""
from __future__ import annotations

import argparse
import os
import pathlib
import sys
import time

# One PoCL thread: must be set before pyopencl loads the platform.
os.environ["POCL_MAX_PTHREAD_COUNT"] = "1"
ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from bench.machine import cpu_model  # noqa: E402
from kdtrace.core.scene.scene import Scene  # noqa: E402


def camera_rays(vertices, size):
    """Pinhole rays through pixel centres from a camera in front of the mesh, framing it."""
    lo, hi = vertices.min(0).astype(np.float64), vertices.max(0).astype(np.float64)
    centre, radius = (lo + hi) / 2, np.linalg.norm(hi - lo) / 2
    eye = centre + np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0]) * radius * 2.2
    forward = (centre - eye) / np.linalg.norm(centre - eye)
    right = np.cross(forward, [0, 1, 0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    half = np.tan(np.radians(25))           # 50 degree field of view
    s = (np.arange(size) + 0.5) / size * 2 - 1
    x, y = np.meshgrid(s, -s)
    dirs = forward + half * (x[..., None] * right + y[..., None] * up)
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    origins = np.broadcast_to(eye, dirs.shape)
    return (np.ascontiguousarray(origins.reshape(-1, 3), np.float32),
            np.ascontiguousarray(dirs.reshape(-1, 3), np.float32))


def best_time(fn, repeat, clock=time.perf_counter):
    """The fastest of `repeat` runs of fn by `clock`, and fn's result."""
    times, result = [], None
    for _ in range(repeat):
        start = clock()
        result = fn()
        times.append(clock() - start)
    return min(times), result


def best_cpu_time(fn, repeat):
    """best_time in process CPU time: other jobs on the machine do not count (each tracer runs
    on one core here, so CPU time is its running time)."""
    return best_time(fn, repeat, time.process_time)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()

    from kdtrace.core.accel.kdtree import build_kdtree
    from kdtrace.core.scene.model import Geometry
    from kdtrace.slave.tracer import Tracer
    from tests.meshes import load_dragon
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    print("command:", " ".join([os.path.basename(sys.executable)] + sys.argv))
    print("machine:", cpu_model(), f"({os.cpu_count()} logical CPUs); one core for each tracer")
    vertices, triangles = load_dragon()
    origins, dirs = camera_rays(vertices, args.size)
    n = len(origins)
    print(f"dragon: {len(triangles):,} triangles; {n:,} primary rays")

    start = time.perf_counter()
    tree = build_kdtree(vertices, triangles)
    print(f"kd-tree build: {time.perf_counter() - start:.2f} s, {len(tree.nodes):,} nodes")
    tracer = Tracer("cpu")
    tracer.load(Scene.from_parts(Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16)), tree))
    print("device:", tracer.device_info)
    tracer.intersect(origins[:1024], dirs[:1024])          # build the kernel first
    ours_s, hits = best_cpu_time(lambda: tracer.intersect(origins, dirs), args.repeat)

    # Embree: scene build outside the timing; its single-ray path via run(). embreex has no
    # thread-count option: limit the process to one CPU so Embree's threads share one core.
    try:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    except (AttributeError, OSError):
        print("note: could not pin Embree to one core")
    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, vertices[triangles])
    scene.run(origins[:1024], dirs[:1024], output=1)
    embree_s, ref = best_cpu_time(lambda: scene.run(origins, dirs, output=1), args.repeat)
    ref_t, ref_i = np.asarray(ref["tfar"], np.float32), np.asarray(ref["primID"], np.int64)
    ref_hit = ref_i >= 0
    ref_t = np.where(ref_hit, ref_t, np.inf)

    our_hit = hits.triangle >= 0
    same = (our_hit == ref_hit) & (~our_hit | (hits.triangle == ref_i)
                                   | np.isclose(hits.t, ref_t, rtol=1e-5))
    print(f"ours (PoCL, 1 thread):  {n / ours_s / 1e6:6.3f} Mrays/s ({ours_s:.3f} s)")
    print(f"Embree (1 core):        {n / embree_s / 1e6:6.3f} Mrays/s ({embree_s:.3f} s)")
    print(f"ratio ours/Embree:      {embree_s / ours_s:6.3f}")
    print(f"agreement: {same.mean() * 100:.4f} % of rays ({(~same).sum()} differ); "
          f"hits: ours {our_hit.mean() * 100:.2f} %, Embree {ref_hit.mean() * 100:.2f} %")


if __name__ == "__main__":
    main()
