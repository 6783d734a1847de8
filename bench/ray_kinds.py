"""The rays a renderer traces, our tracer against Embree (embreex), one core each.

    .venv/bin/python bench/ray_kinds.py [--scenes dragon architecture dragons12] [--size 512]
        [--repeat 3] [--mode compressed] [--variant LABEL=SPEC ...] [--out bench/out]

Per scene, from the camera of bench/kdtree_tables.py's Table 3 (the dragon from the front; the
architecture from inside a ground-floor room): primary rays in row order and in the tracer's
tile order (16 x 16 blocks, Morton inside: slave.tracer.tile_pixel_order); then, at the primary
hits, the secondary rays a path tracer makes, the same rays for both tracers:
- diffuse: one cosine-distributed bounce per hit, in random order (what a wavefront of bounces
  looks like without sorting);
- diffuse_pixels: the same bounces in pixel order (what the render kernel traces: each
  work-item follows its pixel's path);
- shadow_point: towards a point light, any hit up to the light;
- shadow_area: towards a random point of a square area light, any hit;
- glossy: a GGX reflection (roughness 0.3) per hit, in pixel order.
Then the render kernel on the whole view (render_tile: the scene's shading, trace_ray for every
ray), each tracer's best time and whether their passes are identical (no Embree counterpart).
Shadow rays are any-hit queries: Embree's occluded query, our `Tracer.occluded`. Times are
process CPU time, best of --repeat, the tracers and Embree alternating within each repeat, with
the process pinned to one CPU (PoCL then runs one thread, and Embree's threads share that
core). Ratios are ours/Embree in rays per second; agreement counts rays with the same answer
(same triangle or t within 1e-5 relative; same occlusion). `--variant` times other tracers
beside the current one on the same rays (make_tracer: other kernel files, rays in the given
order, one ray per work-item), e.g. the tracer before a change.
"""
from __future__ import annotations

import argparse
import functools
import json
import os
import pathlib
import sys
import time

os.environ["POCL_MAX_PTHREAD_COUNT"] = "1"      # before pyopencl loads PoCL
ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from bench.kdtree_tables import load_scene, table3_view  # noqa: E402
from bench.machine import cpu_model  # noqa: E402

KINDS = ("primary_rows", "primary_tiles", "diffuse", "diffuse_pixels", "shadow_point",
         "shadow_area", "glossy")
SHADOW_KINDS = ("shadow_point", "shadow_area")


def camera_rays(view):
    """One ray through each pixel centre of `view` (core.scene.model.View), rows top first."""
    cam = view.camera
    w, h = view.width, view.height
    x = (2 * (np.arange(w) + 0.5) / w - 1) * cam.ndc_scale[0] + cam.ndc_offset[0]
    y = (1 - 2 * (np.arange(h) + 0.5) / h) * cam.ndc_scale[1] + cam.ndc_offset[1]
    gx, gy = np.meshgrid(x, y)
    local = np.stack([gx, gy, -np.ones_like(gx)], -1).reshape(-1, 3)
    directions = local @ cam.to_world[:3, :3].T
    origins = np.broadcast_to(cam.to_world[:3, 3], directions.shape)
    return np.ascontiguousarray(origins, np.float32), np.ascontiguousarray(directions, np.float32)


def orthonormal(n):
    """Two unit vectors perpendicular to each unit row of n (Duff et al. 2017)."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], 1)
    s = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], 1)
    return t, s


def secondary_rays(hit_points, normals, incoming, light, area_axes, extent, rng):
    """The secondary rays of each kind (float32 origins, directions, tmax) at the hits."""
    offset = hit_points + normals * (1e-5 * extent)
    t, s = orthonormal(normals)
    n = len(hit_points)
    out = {}
    # Cosine-distributed bounce, random order.
    r1, r2 = rng.random(n), rng.random(n)
    phi, sin_t = 2 * np.pi * r1, np.sqrt(r2)
    d = (np.cos(phi) * sin_t)[:, None] * t + (np.sin(phi) * sin_t)[:, None] * s \
        + np.sqrt(1 - r2)[:, None] * normals
    order = rng.permutation(n)
    out["diffuse"] = (offset[order], d[order], np.inf)
    out["diffuse_pixels"] = (offset, d, np.inf)
    # Shadow rays: the light at t = 1 (direction = light - origin), stopping just short of it.
    out["shadow_point"] = (offset, light[None] - offset, 1 - 1e-4)
    u, v = rng.random(n) - 0.5, rng.random(n) - 0.5
    points = light[None] + u[:, None] * area_axes[0] + v[:, None] * area_axes[1]
    out["shadow_area"] = (offset, points - offset, 1 - 1e-4)
    # GGX (alpha = roughness^2 = 0.09): a half-vector about the normal, the view reflected on it.
    alpha = 0.09
    r1, r2 = rng.random(n), rng.random(n)
    cos_h = np.sqrt((1 - r2) / (1 + (alpha ** 2 - 1) * r2))
    sin_h, phi = np.sqrt(1 - cos_h ** 2), 2 * np.pi * r1
    half = (np.cos(phi) * sin_h)[:, None] * t + (np.sin(phi) * sin_h)[:, None] * s \
        + cos_h[:, None] * normals
    d = incoming - 2 * np.sum(incoming * half, 1, keepdims=True) * half
    below = np.sum(d * normals, 1) <= 0
    mirror = incoming - 2 * np.sum(incoming * normals, 1, keepdims=True) * normals
    d[below] = mirror[below]
    out["glossy"] = (offset, d, np.inf)
    return {kind: (np.ascontiguousarray(o, np.float32), np.ascontiguousarray(d, np.float32), tmax)
            for kind, (o, d, tmax) in out.items()}


def embree_scene(vertices, triangles):
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh
    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, vertices[triangles])
    return scene


def embree_query(scene, origins, directions, tmax, shadow):
    dists = None if not np.isfinite(tmax) else np.full(len(origins), tmax, np.float32)
    if shadow:
        return scene.run(origins, directions, dists=dists, query="OCCLUDED") >= 0
    out = scene.run(origins, directions, dists=dists, output=1)
    return out


def ours_query(tracer, origins, directions, tmax, shadow):
    if not shadow:
        return tracer.intersect(origins, directions, tmax=tmax)
    if "occluded_rays" in tracer._source:
        return tracer.occluded(origins, directions, tmax=tmax)
    return tracer.intersect(origins, directions, tmax=tmax).triangle >= 0   # older kernels


def make_tracer(spec):
    """A Tracer on the CPU device as `spec` says: "current", or "+"-joined settings:
    kernels:DIR (the kernel files of another copy of kernels/), given-order (scattered rays
    not reordered), one-ray (one ray per work-item, no packets), local:N (work-groups of N
    work-items, not the driver's choice)."""
    from kdtrace.slave.tracer import Tracer
    settings = [] if spec == "current" else spec.split("+")
    kernels = [x.split(":", 1)[1] for x in settings if x.startswith("kernels:")]
    tracer = Tracer("cpu", kernel_dir=kernels[0] if kernels else None)
    for setting in settings:
        if setting == "given-order":
            tracer.reorder_rays = False
        elif setting == "one-ray":
            tracer.packet = 0
        elif setting.startswith("local:"):
            tracer.local_size = int(setting.split(":", 1)[1])
        elif not setting.startswith("kernels:"):
            raise SystemExit(f"unknown tracer setting {setting!r} in {spec!r}")
    return tracer


def agreement(ours, embree, shadow):
    if shadow:
        return float(np.mean(ours == embree))
    ref_i = np.asarray(embree["primID"], np.int64)
    ref_t = np.where(ref_i >= 0, np.asarray(embree["tfar"], np.float32), np.inf)
    ours_hit, ref_hit = ours.triangle >= 0, ref_i >= 0
    same = (ours_hit == ref_hit) & (~ours_hit | (ours.triangle == ref_i)
                                    | np.isclose(ours.t, ref_t, rtol=1e-5))
    return float(same.mean())


def tree_for(name, vertices, triangles, mode, cache):
    """The compact tree of the scene in treelets, as a master sends it (the standard tree
    cached as .npz under `cache`)."""
    from kdtrace.core.accel.binned import build_standard
    from kdtrace.core.accel.compact import compact_tree
    from kdtrace.core.accel.kdtree import KDTree
    from kdtrace.core.accel.reorder import treelet_order
    path = cache / f"{name}.npz"
    if path.exists():
        with np.load(path) as data:
            tree = KDTree(data["nodes"], data["leaf_indices"], data["bounds"])
    else:
        started = time.perf_counter()
        tree, _ = build_standard(vertices, triangles, "cpu")
        print(f"  kd-tree build {time.perf_counter() - started:.1f} s "
              f"({tree.stats['builder']})", flush=True)
        np.savez(path, nodes=tree.nodes, leaf_indices=tree.leaf_indices, bounds=tree.bounds)
    return treelet_order(compact_tree(tree, len(triangles), mode))


def scene_rays(name, vertices, triangles, size, embree):
    """The rays of every kind for scene `name` from its Table 3 view at size x size: a dict
    kind -> (origins, directions, tmax), float32, the secondary rays at Embree's primary hits."""
    from kdtrace.slave.tracer import tile_pixel_order
    view = table3_view(name, vertices, size)
    origins, directions = camera_rays(view)
    order = tile_pixel_order(size, size)
    rays = {"primary_rows": (origins, directions, np.inf),
            "primary_tiles": (origins[order], directions[order], np.inf)}
    # The hits of the primary rays in tile order (a renderer's pixel order) start the rest.
    primary = embree_query(embree, *rays["primary_tiles"], shadow=False)
    hit = np.asarray(primary["primID"]) >= 0
    o64, d64 = rays["primary_tiles"][0][hit].astype(np.float64), rays["primary_tiles"][1][hit]
    d64 = d64.astype(np.float64) / np.linalg.norm(d64, axis=1, keepdims=True)
    t = np.asarray(primary["tfar"], np.float64)[hit] * np.linalg.norm(
        rays["primary_tiles"][1][hit].astype(np.float64), axis=1)
    points = o64 + t[:, None] * d64
    normals = np.asarray(primary["Ng"], np.float64)[hit]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals *= -np.sign(np.sum(normals * d64, 1, keepdims=True))       # facing the camera
    lo, hi = vertices.min(0).astype(np.float64), vertices.max(0).astype(np.float64)
    extent = float(np.max(hi - lo))
    light = np.asarray(view.shading.lights[0].position, np.float64)
    towards = (lo + hi) / 2 - light
    axes = orthonormal((towards / np.linalg.norm(towards))[None])
    area = np.stack([axes[0][0], axes[1][0]]) * (0.25 * extent)
    rays.update(secondary_rays(points, normals, d64, light, area, extent,
                               np.random.default_rng(1)))
    return rays


def render_times(tracers, view, repeat):
    """The render kernel (render_tile of the whole view: trace_ray for every ray) through each
    tracer, alternating; best process CPU time of each, and whether their passes agree."""
    passes = {label: tracer.render_tile(view, 0, 0, view.width, view.height)   # compiles
              for label, tracer in tracers.items()}
    first = next(iter(passes.values()))
    identical = all(np.array_equal(p[name], first[name]) for p in passes.values() for name in first)
    times = {label: [] for label in tracers}
    for r in range(repeat):
        for label in (list(tracers) if r % 2 == 0 else list(tracers)[::-1]):
            started = time.process_time()
            tracers[label].render_tile(view, 0, 0, view.width, view.height)
            times[label].append(time.process_time() - started)
    best = {label: min(t) for label, t in times.items()}
    print(f"  render {view.width}x{view.height}  " + "  ".join(
        f"{label} {seconds:.3f} s" for label, seconds in best.items())
        + f"  (passes {'identical' if identical else 'DIFFER'})", flush=True)
    return {"seconds": best, "identical": identical}


def run_scene(name, args, cache, tracers):
    """Every ray kind of scene `name` through each of `tracers` (label -> Tracer) and Embree,
    alternating in every repeat; best process CPU time of each."""
    from kdtrace.core.scene.model import Geometry
    from kdtrace.core.scene.scene import Scene
    vertices, triangles = load_scene(name)
    print(f"\n{name}: {len(triangles):,} triangles", flush=True)
    tree = tree_for(name, vertices, triangles, args.mode, cache)
    scene = Scene.from_parts(Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16)),
                             tree)
    load_s = {}
    for label, tracer in tracers.items():
        started = time.process_time()
        tracer.load(scene)
        load_s[label] = time.process_time() - started
    print("  load (process s): " + ", ".join(f"{k} {v:.2f}" for k, v in load_s.items()))
    # What the reorderings cost: the treelet node order (the master's, once per tree), the
    # ray order once per query of scattered rays (here the diffuse bounces in random order).
    from kdtrace.core.accel.reorder import treelet_order
    from kdtrace.slave.tracer import ray_order
    started = time.process_time()
    treelet_order(tree)
    treelet_s = time.process_time() - started
    embree = embree_scene(vertices, triangles)
    rays = scene_rays(name, vertices, triangles, args.size, embree)
    started = time.process_time()
    ray_order(rays["diffuse"][0], tree.bounds)
    sort_s = time.process_time() - started
    print(f"  treelet_order {treelet_s:.3f} s per tree (master); ray_order {sort_s:.3f} s for "
          f"{len(rays['diffuse'][0]):,} diffuse rays", flush=True)
    results = {}
    for kind in KINDS:
        o, d, tmax = rays[kind]
        shadow = kind in SHADOW_KINDS
        runs = {label: functools.partial(ours_query, tracer, o, d, tmax, shadow)
                for label, tracer in tracers.items()}
        runs["Embree"] = functools.partial(embree_query, embree, o, d, tmax, shadow)
        answers = {label: run() for label, run in runs.items()}   # untimed: PoCL compiles
        times = {label: [] for label in runs}                     # per launch size
        for r in range(args.repeat):
            for label in (list(runs) if r % 2 == 0 else list(runs)[::-1]):
                started = time.process_time()
                runs[label]()
                times[label].append(time.process_time() - started)
        best = {label: min(t) for label, t in times.items()}
        row = {"rays": len(o), "embree_mrays": len(o) / best["Embree"] / 1e6}
        for label in tracers:
            row[label] = {"mrays": len(o) / best[label] / 1e6, "ratio": best["Embree"] / best[label],
                          "agreement": agreement(answers[label], answers["Embree"], shadow)}
        results[kind] = row
        print(f"  {kind:14s} {len(o):>9,} rays  Embree {row['embree_mrays']:6.2f} Mrays/s  " + "  ".join(
            f"{label} {row[label]['mrays']:6.2f} ({row[label]['ratio']:.3f}, "
            f"{100 * row[label]['agreement']:.2f} %)" for label in tracers), flush=True)
    render = render_times(tracers, table3_view(name, vertices, args.size), args.repeat)
    return {"triangles": len(triangles), "mode": args.mode, "kinds": results, "render": render,
            "treelet_order_s": treelet_s, "ray_order_s": sort_s, "load_s": load_s}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["dragon", "architecture"],
                        help="dragon, architecture, dragons12")
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--mode", default="compressed", choices=("standard", "choi", "compressed"))
    parser.add_argument("--variant", action="append", default=[], metavar="LABEL=SPEC",
                        help="another tracer timed beside the current one (make_tracer's SPEC), "
                             "e.g. previous=kernels:/tmp/old/kernels+breadth-first+given-order")
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    args = parser.parse_args()
    out = pathlib.Path(args.out)
    cache = ROOT / "bench" / "out" / "ray_kinds_trees"     # shared by every --out: 12 dragons take a minute
    cache.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    try:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
        pinned = "pinned to one CPU"
    except (AttributeError, OSError):
        pinned = "NOT pinned (no sched_setaffinity)"
    specs = {"compressed": "current", **dict(v.split("=", 1) for v in args.variant)}
    tracers = {label: make_tracer(spec) for label, spec in specs.items()}
    print("command:", " ".join([os.path.basename(sys.executable)] + sys.argv))
    print("machine:", cpu_model(), f"({os.cpu_count()} logical CPUs); process {pinned}; "
          f"load average {os.getloadavg()[0]:.1f}")
    print("device:", tracers["compressed"].device_info["name"], "| tracers:",
          ", ".join(f"{label} = {spec}" for label, spec in specs.items()))
    print("per kind: Mrays/s of each, (ratio to Embree in rays/s, agreement with Embree)")
    report = {"command": sys.argv, "machine": cpu_model(), "size": args.size, "tracers": specs,
              "scenes": {name: run_scene(name, args, cache, tracers) for name in args.scenes}}
    (out / "ray_kinds.json").write_text(json.dumps(report, indent=1))
    print(f"\nwrote {out / 'ray_kinds.json'}")


if __name__ == "__main__":
    main()
