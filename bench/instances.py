"""Issue 15's benchmark: a forest of Stanford dragons as instances of one mesh, at 1024x1024.

    .venv/bin/python bench/instances.py [--instances 1000] [--realised 4] [--size 1024]
    .venv/bin/python bench/instances.py --animation [--frames 24] [--instances 1000] [--size 256]

The dragon's kd-tree is built once (mode compressed) and placed --instances times on a grid (random
turns and scales, every third mirrored); the top level is built over them. Recorded: the build
times, the bytes a slave is sent (the scene's wire arrays), the memory report (triangles
referenced vs stored, bytes per level) and a render (primary rays, one sun's shadow rays,
diffuse shading: max_bounces 0, one sample per pixel, one PoCL thread). The realised
equivalent (every dragon's triangles in world space, one kd-tree) is built and rendered side
by side for the first --realised dragons, where it fits; the instanced scene of those same
dragons is rendered in the same run for the ratio.

--animation: the forest through a real slave (`python -m kdtrace.slave` on loopback, one PoCL
thread) and the master, --frames frames in which every dragon turns and drifts: frame 0 uploads the
whole scene, each later frame sends only the instances (SCENE_INSTANCES). Per frame: the
master's Scene.moved, load_scene (send, the slave's check and top level) and the render, and
the bytes sent on the socket.
"""
import argparse
import os
import pathlib
import sys
import time

os.environ["POCL_MAX_PTHREAD_COUNT"] = "1"  # before pyopencl loads PoCL
ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from bench.machine import cpu_model  # noqa: E402
from bench.trace_vs_embree import best_time  # noqa: E402
from kdtrace.core.accel.compact import compact_tree  # noqa: E402
from kdtrace.core.accel.binned import build_standard  # noqa: E402
from kdtrace.core.accel.toplevel import build_toplevel  # noqa: E402
from kdtrace.core.scene.model import (Camera, Geometry, Light, RenderSettings,  # noqa: E402
                                      Shading, View)
from kdtrace.core.scene.scene import Scene, memory_report, memory_summary  # noqa: E402
from tests.meshes import load_dragon, look_at  # noqa: E402


def forest(count: int, size: float, seed: int = 0) -> np.ndarray:
    """(count, 4, 4) transforms on a square grid of cells `size` wide, z up."""
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(count)))
    out = np.zeros((count, 4, 4))
    for i in range(count):
        angle, scale = rng.uniform(0, 2 * np.pi), rng.uniform(0.7, 1.3)
        c, s = np.cos(angle), np.sin(angle)
        linear = scale * np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        if i % 3 == 0:
            linear = linear @ np.diag([1.0, -1.0, 1.0])
        out[i, :3, :3] = linear
        out[i, :3, 3] = ((i % side) * size, (i // side) * size, 0.0)
        out[i, 3, 3] = 1.0
    return out


def build_tree(geometry):
    """The compact tree (mode compressed) as the add-on builds it: on the PoCL CPU device."""
    tree, builder = build_standard(geometry.vertices, geometry.triangles, "cpu")
    return compact_tree(tree, geometry.triangle_count, "compressed", device=builder)


def wire_bytes(scene) -> int:
    return sum(a.nbytes for a in scene.wire_arrays().values())


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--instances", type=int, default=1000)
    parser.add_argument("--realised", type=int, default=4,
                        help="dragons also realised in world space for the comparison (0: none)")
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--animation", action="store_true",
                        help="frames of moving instances through a real slave (see above)")
    parser.add_argument("--frames", type=int, default=24)
    args = parser.parse_args()
    print("command:", " ".join(["python"] + sys.argv))
    print("machine:", cpu_model(), f"({os.cpu_count()} logical CPUs); one PoCL thread;",
          "load", " ".join(f"{v:.1f}" for v in os.getloadavg()))

    vertices, triangles = load_dragon()
    vertices = vertices[:, [0, 2, 1]] * np.array([1, -1, 1], np.float32)      # z up
    vertices = (vertices - vertices.min(0) * np.array([0.5, 0.5, 1.0])
                - vertices.max(0) * np.array([0.5, 0.5, 0.0])).astype(np.float32)
    mesh = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16))
    extent = float(np.ptp(vertices[:, :2], axis=0).max())
    build_s, tree = best_time(lambda: build_tree(mesh), 1)
    print(f"dragon: {mesh.triangle_count:,} triangles; kd-tree (ours) build + compaction "
          f"{build_s:.2f} s, {tree.nbytes / 2**20:.1f} MiB")

    matrices = forest(args.instances, 1.3 * extent)
    side = int(np.ceil(np.sqrt(args.instances))) * 1.3 * extent
    scene_s, scene = best_time(lambda: Scene.from_instances([(mesh, tree)], np.zeros(
        args.instances, int), matrices), 3)
    inst = scene.instances
    top_s, _ = best_time(lambda: build_toplevel(inst.world_bounds[:, 0], inst.world_bounds[:, 1]), 5)
    print(f"{args.instances} instances: top level {top_s * 1e3:.1f} ms ({len(inst.toplevel.nodes):,} "
          f"nodes, depth {inst.toplevel.depth}); Scene.from_instances {scene_s:.2f} s (with the "
          f"validation of the dragon's tree)")
    print(f"sent to each slave: {wire_bytes(scene) / 2**20:.1f} MiB")
    print("memory:", memory_summary(memory_report(scene)))

    shading = Shading(np.array([[0.8, 0.8, 0.8, 1.0]], np.float32),
                      [Light("SUN", (1.0, 1.0, 1.0), 3.0, direction=(-0.4, -0.3, -1.0))],
                      (0.05, 0.05, 0.08))
    settings = RenderSettings(samples_per_axis=1, adaptive=False, max_bounces=0)

    def view_of(count):
        """Looking over the first `count` dragons' field from a corner, above."""
        far = int(np.ceil(np.sqrt(count))) * 1.3 * extent if count < args.instances else side
        eye = (-0.15 * far, -0.15 * far, 0.35 * far)
        camera = Camera("PERSP", look_at(eye, (0.5 * far, 0.5 * far, 0.0)), ndc_scale=(0.6, 0.6))
        return View(camera, args.size, args.size, shading, settings=settings)

    from kdtrace.slave.tracer import Tracer
    tracer = Tracer("cpu")

    def render(scene, view):
        tracer.load(scene)
        # The best of two: PoCL specialises kernels at their first launches of a size.
        seconds, passes = best_time(lambda: tracer.render_tile(view, 0, 0, args.size, args.size), 2)
        return seconds, (passes["depth"] < 1e9).mean(), passes

    if args.animation:
        animate(scene, matrices, view_of(args.instances), args.frames, 1.3 * extent)
        return
    render_s, hit, _ = render(scene, view_of(args.instances))
    print(f"render {args.size}x{args.size}, {args.instances} instances: {render_s:.2f} s "
          f"({hit:.1%} of pixels hit)")

    if args.realised:
        count = min(args.realised, args.instances)
        few = matrices[:count]
        placed = [(mesh.vertices.astype(np.float64) @ m[:3, :3].T + m[:3, 3]).astype(np.float32)
                  for m in few]
        realised_geometry = Geometry(
            np.concatenate(placed),
            np.concatenate([mesh.triangles + np.uint32(k * len(vertices)) for k in range(count)]),
            np.zeros(count * mesh.triangle_count, np.uint16))
        real_build_s, real_tree = best_time(lambda: build_tree(realised_geometry), 1)
        realised = Scene.from_parts(realised_geometry, real_tree)
        instanced = Scene.from_instances([(mesh, tree)], np.zeros(count, int), few)
        view = view_of(count)
        real_s, real_hit, a = render(realised, view)
        inst_s, inst_hit, b = render(instanced, view)
        diff = np.abs(a["combined"] - b["combined"]).max(axis=2)
        print(f"{count} dragons side by side: realised tree build {real_build_s:.2f} s, "
              f"{wire_bytes(realised) / 2**20:.1f} MiB sent, render {real_s:.2f} s; "
              f"instanced {wire_bytes(instanced) / 2**20:.1f} MiB sent, render {inst_s:.2f} s "
              f"({inst_s / real_s:.2f}x the realised); {real_hit:.1%} of pixels hit; pixels "
              f"within 1e-3: {(diff < 1e-3).mean():.2%}")


def animate(scene, matrices, view, frames, cell):
    """Frames of the forest in which every dragon turns and circles within its grid cell (`cell`
    wide), on a real slave; prints per frame the seconds of each step and the bytes sent."""
    from kdtrace.core.net.master import Master
    from tests.processes import SlaveProcess
    slave = SlaveProcess(f"bench-animation-{os.getpid()}")
    rng = np.random.default_rng(1)
    spin = rng.uniform(-0.05, 0.05, len(matrices))             # radians per frame
    phase = rng.uniform(0, 2 * np.pi, len(matrices))
    rows = []
    try:
        with Master([slave.endpoint]) as master:
            master.connect()
            for frame in range(frames):
                started = time.perf_counter()
                if frame:
                    c, s = np.cos(spin * frame), np.sin(spin * frame)
                    turn = np.zeros((len(matrices), 4, 4))
                    turn[:, 0, 0], turn[:, 0, 1], turn[:, 1, 0], turn[:, 1, 1] = c, -s, s, c
                    turn[:, 2, 2] = turn[:, 3, 3] = 1.0
                    moved = matrices @ turn
                    angle = phase + 2 * np.pi * frame / frames
                    moved[:, 0, 3] += 0.15 * cell * (np.cos(angle) - np.cos(phase))
                    moved[:, 1, 3] += 0.15 * cell * (np.sin(angle) - np.sin(phase))
                    scene = scene.moved(moved)
                placed = time.perf_counter()
                master.load_scene(scene)
                loaded = time.perf_counter()
                job = master.render(view, tile_size=64)
                while not job.finished:
                    job.next_result(0.5)
                if job.error:
                    raise RuntimeError(job.error)
                done = time.perf_counter()
                sent = sum(master.scene_bytes.values())
                rows.append((placed - started, loaded - placed, done - loaded, sent))
                print(f"frame {frame:2d}: moved {1e3 * rows[-1][0]:7.1f} ms, load_scene "
                      f"{1e3 * rows[-1][1]:8.1f} ms, render {rows[-1][2]:.2f} s "
                      f"({(job.image['depth'] < 1e9).mean():.1%} of pixels hit), {sent:,} bytes "
                      f"sent" + (" (whole scene)" if master.uploaded_to else ""), flush=True)
    finally:
        slave.stop()
    later = np.array(rows[1:])
    if len(later):
        first = rows[0]
        print(f"frames 1-{frames - 1} (median): moved {1e3 * np.median(later[:, 0]):.1f} ms, "
              f"load_scene {1e3 * np.median(later[:, 1]):.1f} ms, render "
              f"{np.median(later[:, 2]):.2f} s, {int(np.median(later[:, 3])):,} bytes a frame; "
              f"frame 0 (whole upload): load_scene {first[1]:.2f} s, {first[3]:,} bytes "
              f"({first[3] / np.median(later[:, 3]):,.0f}x the bytes, "
              f"{first[1] / np.median(later[:, 1]):.0f}x the load time)")


if __name__ == "__main__":
    main()
