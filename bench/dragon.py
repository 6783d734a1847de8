"""Issue 2's benchmark: the Stanford dragon at 1024x1024 through the whole pipeline, against Embree.

    .venv/bin/python bench/dragon.py [--size 1024] [--repeat 3] [--mode compressed]

Export (the installed add-on's exporter on Blender's evaluated depsgraph, in a Blender process of
its own: tests/bpy_scripts/export_dragon.py), kd-tree build, a full
render of the image (primary rays, shadow rays to each light, diffuse shading) on the OpenCL
tracer, and the camera's primary rays through our intersect() and through Embree (embreex), one
core each (PoCL limited to one thread, the process pinned to one CPU for Embree). The render uses
the compact tree of --mode (the add-on's default, "compressed"); the primary rays are timed on both the
"standard" and the "compressed" tree, with intersect()'s 8-ray packets (the CPU default) and with one
ray per work-item. Ray timings are process CPU time (the best of --repeat), so other jobs on the
machine do not count.
"""
import argparse
import os
import pathlib
import sys
import tempfile

os.environ["POCL_MAX_PTHREAD_COUNT"] = "1"  # before pyopencl loads PoCL
ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from kdtrace.core.scene.scene import Scene  # noqa: E402

from bench.machine import cpu_model  # noqa: E402
from bench.trace_vs_embree import best_cpu_time, best_time  # noqa: E402


def camera_rays(view):
    """The primary rays of every pixel, as the kernel makes them (pixel centres, top row first)."""
    camera = view.camera
    px, py = np.meshgrid(np.arange(view.width) + 0.5, np.arange(view.height) + 0.5)
    x = px / view.width * 2 - 1
    y = 1 - py / view.height * 2
    local = np.stack([x * camera.ndc_scale[0] + camera.ndc_offset[0],
                      y * camera.ndc_scale[1] + camera.ndc_offset[1],
                      np.full_like(x, -1.0)], -1).reshape(-1, 3)
    rotation, eye = camera.to_world[:3, :3], camera.to_world[:3, 3]
    directions = local @ rotation.T
    origins = np.broadcast_to(eye, directions.shape)
    return (np.ascontiguousarray(origins, np.float32), np.ascontiguousarray(directions, np.float32))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--mode", choices=("compressed", "standard", "choi"), default="compressed",
                        help="compact kd-tree mode of the render (the add-on's default: ours)")
    args = parser.parse_args()
    print("command:", " ".join(["python"] + sys.argv))
    print("machine:", cpu_model(), f"({os.cpu_count()} logical CPUs); one core for each tracer")

    work = pathlib.Path(tempfile.mkdtemp(prefix="kdtrace-bench-"))
    # Blender exports in a process of its own; this one runs core and the slave's tracer.
    from tests.blender import build_extension, run_bpy_script
    from kdtrace.core.frame.exported import load_export
    export_s = run_bpy_script("export_dragon", work, zip=str(build_extension(work / "dist")),
                              out=str(work / "dragon.npz"), size=args.size,
                              repeat=args.repeat)["export_seconds"]
    exported, view = load_export(work / "dragon.npz")
    geometry = exported.meshes[0]       # the dragon, placed by the identity
    print(f"dragon: {geometry.triangle_count:,} triangles, {args.size}x{args.size}")
    print(f"export:        {export_s:8.3f} s")

    from kdtrace.core.accel.kdtree import build_kdtree
    build_s, tree = best_time(lambda: build_kdtree(geometry.vertices, geometry.triangles), 1)
    stats = tree.stats
    print(f"kd-tree build: {build_s:8.3f} s  {stats['nodes']:,} nodes, {stats['leaves']:,} leaves, "
          f"depth {stats['depth']}, {stats['refs_per_triangle']:.2f} refs/triangle, "
          f"{tree.nbytes / 2**20:.1f} MiB")

    from kdtrace.core.accel.compact import compact_tree
    modes = [args.mode] + [m for m in ("compressed", "standard") if m != args.mode]
    compact = {}
    for mode in modes:
        compact_s, compact[mode] = best_time(
            lambda: compact_tree(tree, geometry.triangle_count, mode), 1)
        print(f"compact tree:  {compact_s:8.3f} s  {mode}: {compact[mode].nbytes / 2**20:.1f} MiB")

    from kdtrace.slave.tracer import Tracer
    tracer = Tracer("cpu")
    tracer.load(Scene.from_parts(geometry, compact[args.mode]))
    tracer.render_tile(view, 0, 0, 16, 16)  # build the kernels outside the timing
    render_s, passes = best_time(lambda: tracer.render_tile(view, 0, 0, view.width, view.height),
                                 args.repeat)
    hit_fraction = (passes["depth"] < 1e9).mean()
    soft = "SOFT_LIGHTS" in tracer.last_render["features"]
    shadow = view.settings.light_samples_per_axis ** 2 if soft else 1
    print(f"render:        {render_s:8.3f} s  ({hit_fraction:.1%} of pixels hit; primary + "
          f"{len(view.shading.lights)} light(s) x {shadow} shadow ray(s) per hit, diffuse shading; "
          f"{args.mode} tree)")

    origins, directions = camera_rays(view)
    # intersect() with 8-ray packets (CPU devices' default) and with one ray per work-item.
    kernels = {"packets": tracer.packet, "one ray": 0}
    ours = {}
    for mode in modes:
        tracer.load(Scene.from_parts(geometry, compact[mode]))
        for kernel, packet in kernels.items():
            tracer.packet = packet
            tracer.intersect(origins[:1024], directions[:1024])
            ours[mode, kernel] = best_cpu_time(lambda: tracer.intersect(origins, directions),
                                               args.repeat)

    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    embree = rtcore_scene.EmbreeScene()
    TriangleMesh(embree, geometry.vertices[geometry.triangles])
    embree.run(origins[:1024], directions[:1024], output=1)
    embree_s, reference = best_cpu_time(lambda: embree.run(origins, directions, output=1),
                                        args.repeat)
    embree_hit = np.asarray(reference["primID"]) >= 0

    rays = len(origins)
    print(f"primary rays (CPU time): Embree {rays / embree_s / 1e6:6.2f} Mrays/s ({embree_s:.3f} s)")
    for (mode, kernel), (ours_s, hits) in ours.items():
        agree = ((hits.triangle >= 0) == embree_hit).mean()
        label = f"{mode} tree, {kernel}:"
        print(f"  ours, {label:24s} {rays / ours_s / 1e6:6.2f} Mrays/s ({ours_s:.3f} s)  "
              f"ratio ours/Embree per core {embree_s / ours_s:.3f}  (hit/miss agreement {agree:.4%})")


if __name__ == "__main__":
    main()
