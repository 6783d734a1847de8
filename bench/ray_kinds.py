"""The rays a renderer traces, our tracer against Embree (embreex), one core each.

    .venv/bin/python bench/ray_kinds.py [--scenes dragon architecture dragons12] [--size 512]
        [--repeat 3] [--mode ours] [--out bench/out]

Per scene, from the camera of bench/kdtree_tables.py's Table 3 (the dragon from the front; the
architecture from inside a ground-floor room): primary rays in row order and in the tracer's
tile order (16 x 16 blocks, Morton inside: slave.tracer.tile_pixel_order); then, at the primary
hits, the secondary rays a path tracer makes, the same rays for both tracers:
- diffuse: one cosine-distributed bounce per hit, in random order (what a wavefront of bounces
  looks like without sorting);
- shadow_point: towards a point light, any hit up to the light;
- shadow_area: towards a random point of a square area light, any hit;
- glossy: a GGX reflection (roughness 0.3) per hit, in pixel order.
Embree answers shadow rays with its occluded query; ours with `Tracer.occluded` where the tracer
has one, else with a nearest-hit query up to the light (printed). Times are process CPU time,
best of --repeat, with the process pinned to one CPU (PoCL then runs one thread, and Embree's
threads share that core). Ratios are ours/Embree in rays per second; agreement counts rays with
the same answer (same triangle or t within 1e-5 relative; same occlusion).
"""
from __future__ import annotations

import argparse
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
from bench.trace_vs_embree import best_cpu_time, cpu_model  # noqa: E402

KINDS = ("primary_rows", "primary_tiles", "diffuse", "shadow_point", "shadow_area", "glossy")
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
    if shadow and hasattr(tracer, "occluded"):
        return tracer.occluded(origins, directions, tmax=tmax)
    hits = tracer.intersect(origins, directions, tmax=tmax)
    return hits.triangle >= 0 if shadow else hits


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
    """The compact tree of the scene (the numpy build cached as .npz under `cache`)."""
    from core.accel.compact import compact_tree
    from core.accel.kdtree import KDTree, build_kdtree
    path = cache / f"{name}.npz"
    if path.exists():
        with np.load(path) as data:
            tree = KDTree(data["nodes"], data["leaf_indices"], data["bounds"])
    else:
        started = time.perf_counter()
        tree = build_kdtree(vertices, triangles)
        print(f"  kd-tree build {time.perf_counter() - started:.1f} s", flush=True)
        np.savez(path, nodes=tree.nodes, leaf_indices=tree.leaf_indices, bounds=tree.bounds)
    return compact_tree(tree, len(triangles), mode)


def run_scene(name, args, cache, tracer):
    from core.scene.model import Geometry
    from core.scene.scene import Scene
    from slave.tracer import tile_pixel_order
    vertices, triangles = load_scene(name)
    print(f"\n{name}: {len(triangles):,} triangles", flush=True)
    tree = tree_for(name, vertices, triangles, args.mode, cache)
    tracer.load(Scene.from_parts(Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16)),
                                 tree))
    embree = embree_scene(vertices, triangles)
    view = table3_view(name, vertices, args.size)
    origins, directions = camera_rays(view)
    order = tile_pixel_order(args.size, args.size)
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
    results = {}
    for kind in KINDS:
        o, d, tmax = rays[kind]
        shadow = kind in SHADOW_KINDS
        # Untimed first runs: PoCL compiles a kernel again for each new launch size.
        ours_query(tracer, o, d, tmax, shadow)
        embree_query(embree, o[:1024], d[:1024], tmax, shadow)
        ours_s, ours = best_cpu_time(lambda: ours_query(tracer, o, d, tmax, shadow), args.repeat)
        embree_s, ref = best_cpu_time(lambda: embree_query(embree, o, d, tmax, shadow),
                                      args.repeat)
        results[kind] = {"rays": len(o), "ours_mrays": len(o) / ours_s / 1e6,
                         "embree_mrays": len(o) / embree_s / 1e6, "ratio": embree_s / ours_s,
                         "agreement": agreement(ours, ref, shadow)}
        r = results[kind]
        print(f"  {kind:14s} {r['rays']:>9,} rays  ours {r['ours_mrays']:6.2f} Mrays/s  "
              f"Embree {r['embree_mrays']:6.2f} Mrays/s  ratio {r['ratio']:.3f}  "
              f"agreement {100 * r['agreement']:.3f} %", flush=True)
    return {"triangles": len(triangles), "mode": args.mode, "kinds": results}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["dragon", "architecture"],
                        help="dragon, architecture, dragons12")
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--mode", default="ours", choices=("standard", "choi", "ours"))
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    args = parser.parse_args()
    out = pathlib.Path(args.out)
    cache = out / "ray_kinds_trees"
    cache.mkdir(parents=True, exist_ok=True)
    try:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
        pinned = "pinned to one CPU"
    except (AttributeError, OSError):
        pinned = "NOT pinned (no sched_setaffinity)"
    from slave.tracer import Tracer
    tracer = Tracer("cpu")
    print("command:", " ".join([os.path.basename(sys.executable)] + sys.argv))
    print("machine:", cpu_model(), f"({os.cpu_count()} logical CPUs); process {pinned}")
    print("device:", tracer.device_info["name"], "| shadow rays, ours:",
          "any hit (occluded)" if hasattr(tracer, "occluded") else "nearest hit up to the light")
    report = {"command": sys.argv, "machine": cpu_model(), "size": args.size,
              "scenes": {name: run_scene(name, args, cache, tracer) for name in args.scenes}}
    (out / "ray_kinds.json").write_text(json.dumps(report, indent=1))
    print(f"\nwrote {out / 'ray_kinds.json'}")


if __name__ == "__main__":
    main()
