"""The traversal kernels of kernels/ against another copy of them, side by side in one process.

    .venv/bin/python bench/kernels_side_by_side.py --old /tmp/old_kernels [--new kernels]
        [--size 1024] [--rays 250000] [--repeat 7] [--mode compressed] [--cases "camera, packets" ...]

`--old` is a copy of the kernels/ folder (e.g. `cp -r kernels /tmp/old_kernels` before a
change), `--new` another (default: kernels/). Both are built on the same CPU device and run with
Tracer.intersect's arguments on the same rays and dragon tree (one set of scene buffers): camera
rays through the pixel centres of bench/kdtree_tables.py's Table 3 view in the render kernel's
tile order (16 x 16 blocks, Morton inside), with 8-ray packets and with one ray per work-item,
and incoherent rays (uniformly random directions from random points on the surface, offset off
it), both ways. Old and new alternate within each repeat (which goes first alternates too);
times are process CPU time of one intersect call (buffers, kernel, copies) with PoCL on one
thread. Prints old/new of the medians and of the best times over the repeats (above 1: the new
kernels are faster) and whether both gave the same bits.
"""
from __future__ import annotations

import argparse
import hashlib
import os
import pathlib
import statistics
import sys
import tempfile
import time

os.environ["POCL_MAX_PTHREAD_COUNT"] = "1"      # before pyopencl loads PoCL
ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from bench.kdtree_tables import load_scene, table3_view  # noqa: E402
from bench.ray_kinds import camera_rays, tree_for  # noqa: E402
from bench.machine import cpu_model  # noqa: E402
from kdtrace.core.opencl import Programs  # noqa: E402
from kdtrace.slave.buffers import pack_bounds, pack_triangles  # noqa: E402


def surface_rays(vertices, triangles, count, seed):
    """`count` rays from random points of random triangles in uniformly random directions,
    the origins moved off the surface to the side the ray leaves to."""
    rng = np.random.default_rng(seed)
    corners = vertices.astype(np.float64)[triangles[rng.integers(0, len(triangles), count)]]
    w = rng.dirichlet(np.ones(3), count)
    points = np.einsum("rk,rkd->rd", w, corners)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    side = np.sign(np.sum(normals * directions, 1, keepdims=True))
    extent = float(np.max(vertices.max(0) - vertices.min(0)))
    origins = points + side * normals * (1e-5 * extent)
    return origins.astype(np.float32), directions.astype(np.float32)


def kernel_source_from(folder: pathlib.Path) -> str:
    """The tracer's kernel files from `folder`, after the layout header if they use it. (In
    copies from before intersect.cl held the packet kernel, packet.cl used intersect.cl's
    load_ray and came after it.)"""
    from kdtrace.core.layout import c_header
    from kdtrace.slave.tracer import KERNEL_FILES
    files = list(KERNEL_FILES)
    if "load_ray(" in (folder / "trace/packet.cl").read_text():
        files.remove("trace/packet.cl")
        files.insert(files.index("trace/intersect.cl") + 1, "trace/packet.cl")
    text = "\n".join((folder / name).read_text() for name in files)
    return (c_header() + "\n" + text) if "KD_TAG(" in text else text


def digest(hits) -> str:
    h = hashlib.sha256()
    for array in hits:
        h.update(np.ascontiguousarray(array).tobytes())
    return h.hexdigest()[:12]


def scene_buffers(tracer, scene):
    """The tree and triangle arguments of the intersect kernels, uploaded once for both copies
    (separate copies of the 60 MB made the first-built copy a few percent faster)."""
    import pyopencl as cl
    tree = scene.tree

    def upload(array):
        array = np.ascontiguousarray(array)
        if array.nbytes == 0:
            array = np.zeros(1, array.dtype)
        return cl.Buffer(tracer.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                         hostbuf=array)

    return (upload(tree.nodes), upload(tree.leaf_index32), upload(tree.leaf_index16),
            np.uint32(tree.leaf_shift), upload(pack_triangles(scene.geometry)),
            upload(pack_bounds(tree.bounds)))


class Kernels:
    """One copy of the kernels on the device, tracing rays with Tracer.intersect's arguments
    against the scene buffers both copies share, by whichever name the copy gives its packet
    kernel."""

    def __init__(self, tracer, source, scene_args, stack_size):
        import pyopencl as cl
        from kdtrace.slave.tracer import kernel_options
        self.cl, self.tracer, self.scene_args = cl, tracer, scene_args
        exact = cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT
        features = {"stack_size": stack_size,
                    "correct_divide_sqrt": bool(tracer.device.single_fp_config & exact)}
        programs = Programs(cl, tracer.context, tracer.device)
        self.one_ray = programs.kernels(source, kernel_options(features))["intersect_rays"]
        packets = programs.kernels(source, kernel_options(dict(features, packet=8)))
        self.packets = packets.get("intersect_packets", packets["intersect_rays"])

    def intersect(self, origins, directions, packet):
        cl, queue, n = self.cl, self.tracer.queue, len(origins)
        mf = cl.mem_flags
        ctx = self.tracer.context
        rays = [cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)
                for a in (origins, directions)]
        out = [np.empty(n, dtype) for dtype in (np.float32, np.int32, np.float32, np.float32)]
        out_bufs = [cl.Buffer(ctx, mf.WRITE_ONLY, a.nbytes) for a in out]
        kernel = self.packets if packet else self.one_ray
        kernel(queue, (-(-n // packet) if packet else n,), None, *rays, np.float32(0.0),
               np.float32(np.inf), np.uint32(n), *self.scene_args, *out_bufs)
        for host, buf in zip(out, out_bufs):
            cl.enqueue_copy(queue, host, buf)
        queue.finish()
        return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--old", type=pathlib.Path, required=True)
    parser.add_argument("--new", type=pathlib.Path, default=ROOT / "kernels")
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--rays", type=int, default=250_000)
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--mode", default="compressed")
    parser.add_argument("--cases", nargs="*", help="only these cases (default: all four)")
    args = parser.parse_args()
    from kdtrace.core.scene.model import Geometry
    from kdtrace.core.scene.scene import Scene
    from kdtrace.slave.tracer import Tracer, tile_pixel_order

    print(" ".join([".venv/bin/python", *sys.argv]))
    print(f"machine: {cpu_model()}, {os.cpu_count()} logical CPUs; PoCL 1 thread")
    vertices, triangles = load_scene("dragon")
    cache = pathlib.Path(tempfile.gettempdir()) / "kdtrace-bench"
    cache.mkdir(exist_ok=True)
    scene = Scene.from_parts(Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16)),
                             tree_for("dragon", vertices, triangles, args.mode, cache))
    tracer = Tracer("cpu")      # the device, context and queue both copies run on
    scene_args = scene_buffers(tracer, scene)
    stack_size = max(32, -(-(scene.depth + 1) // 16) * 16)
    kernels = {"old": Kernels(tracer, kernel_source_from(args.old), scene_args, stack_size),
               "new": Kernels(tracer, kernel_source_from(args.new), scene_args, stack_size)}
    origins, directions = camera_rays(table3_view("dragon", vertices, args.size))
    order = tile_pixel_order(args.size, args.size)
    camera = (origins[order], directions[order])
    incoherent = surface_rays(vertices, triangles, args.rays, seed=1)
    cases = {"camera, packets": (camera, 8), "camera, one ray": (camera, 0),
             "incoherent, packets": (incoherent, 8), "incoherent, one ray": (incoherent, 0)}
    cases = {case: rays for case, rays in cases.items() if not args.cases or case in args.cases}
    print(f"dragon {len(triangles):,} triangles, tree {args.mode}; camera {len(order):,} rays "
          f"({args.size}x{args.size}), incoherent {args.rays:,} rays; {args.repeat} repeats")
    times = {(case, label): [] for case in cases for label in kernels}
    digests = {}
    for case, (rays, packet) in cases.items():      # untimed first runs (PoCL's launch setup)
        for label, copy in kernels.items():
            digests[case, label] = digest(copy.intersect(*rays, packet))
    for r in range(args.repeat):
        for case, (rays, packet) in cases.items():
            for label in (("old", "new") if r % 2 == 0 else ("new", "old")):
                started = time.process_time()
                kernels[label].intersect(*rays, packet)
                times[case, label].append(time.process_time() - started)
    for case, ((o, _), _) in cases.items():
        old, new = (statistics.median(times[case, label]) for label in ("old", "new"))
        old_min, new_min = (min(times[case, label]) for label in ("old", "new"))
        same = "same bits" if digests[case, "old"] == digests[case, "new"] else "DIFFERENT bits"
        print(f"  {case:20s} median old {old:.4f} s new {new:.4f} s, old/new {old / new:.3f}; "
              f"best {old_min / new_min:.3f}  ({len(o) / new / 1e6:.2f} Mrays/s new; {same})",
              flush=True)


if __name__ == "__main__":
    main()
