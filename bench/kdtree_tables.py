"""The paper's Tables 1, 2a and 2b (Seo, Kim, Ihm 2017) for our scenes, with build time and peak
memory per kd-tree mode (standard, choi, ours), and an optional threshold sweep.

    .venv/bin/python bench/kdtree_tables.py [--scenes dragon architecture dragons12]
        [--sweep] [--check-rays N] [--table3] [--collapse-sweep K_T ...] [--repeats R]
        [--size S] [--reuse] [--skip-tables]

Each scene's standard tree is built once in a child process (its time and peak RSS reported),
saved under --cache, and every mode is compacted from it in its own child process (time and peak
RSS of that process, tree loading included). A mode's build time is build + compaction; its peak
memory is the larger of the two processes' peaks.

--table3: render time per mode (Table 3): render_tile of an S x S image (1 sample per pixel, one
point light: primary and shadow rays) on PoCL with POCL_MAX_PTHREAD_COUNT=1, the three modes
side by side in one process, R rounds (each round renders every mode once, in turn), median
reported. --collapse-sweep K_T... renders "compressed" with those collapse traversal costs beside
standard the same way (tree bytes and render time as % of standard). --check-rays N also runs N random rays through the OpenCL kernel for every mode: the
three must agree exactly, and a sample of them with the kernel's own brute force (one leaf
holding every triangle).
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import resource
import subprocess
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from bench.machine import cpu_model  # noqa: E402
from kdtrace.core.scene.scene import Scene  # noqa: E402

MODES = ("standard", "choi", "compressed")
MB = 1e6


def load_scene(name):
    from tests.meshes import load_dragon
    from tests.scenes_architecture import architecture_scene
    if name == "dragon":
        return load_dragon()
    if name == "architecture":
        return architecture_scene(rooms=(12, 10), floors=3, seed=7)
    if name == "architecture_small":
        return architecture_scene(rooms=(3, 2), floors=2, seed=3)
    if name == "dragons12":
        # 12 realised (not instanced) copies in a 4 x 3 grid, each shifted by its box size.
        v, t = load_dragon()
        size = v.max(0) - v.min(0)
        vertices, triangles = [], []
        for k in range(12):
            shift = np.array([(k % 4) * size[0] * 1.1, (k // 4) * size[1] * 1.1, 0], np.float32)
            vertices.append(v + shift)
            triangles.append(t.astype(np.int64) + k * len(v))
        return np.vstack(vertices), np.vstack(triangles).astype(np.uint32)
    raise SystemExit(f"unknown scene {name}")


def peak_rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0   # KiB on Linux


def stage_build(name, cache):
    from kdtrace.core.accel.kdtree import build_kdtree
    vertices, triangles = load_scene(name)
    before = peak_rss_mb()
    started = time.perf_counter()
    last = [0.0]

    def progress(fraction, message):
        now = time.perf_counter() - started
        if now - last[0] > 10 or fraction >= 1.0:
            last[0] = now
            print(f"  [{name} {now:6.1f} s] {fraction:4.0%} {message}", file=sys.stderr, flush=True)

    tree = build_kdtree(vertices, triangles, progress=progress)
    seconds = time.perf_counter() - started
    np.savez(cache / f"{name}.npz", nodes=tree.nodes, leaf_indices=tree.leaf_indices,
             bounds=tree.bounds)
    stats = {k: v for k, v in tree.stats.items()}
    return {"triangles": len(triangles), "vertices": len(vertices), "build_s": seconds,
            "peak_mb": peak_rss_mb(), "mesh_mb": before, "tree_bytes": tree.nbytes,
            "stats": stats}


def stage_compact(name, cache, mode, options):
    from kdtrace.core.accel.kdtree import KDTree
    from kdtrace.core.accel.compact import compact_tree
    data = np.load(cache / f"{name}.npz")
    tree = KDTree(data["nodes"], data["leaf_indices"], data["bounds"])
    triangle_count = int(options.pop("triangles"))
    started = time.perf_counter()
    ct = compact_tree(tree, triangle_count, mode, **options)
    seconds = time.perf_counter() - started
    stats = {k: v for k, v in ct.stats.items() if k != "node_kinds"}
    return {"compact_s": seconds, "peak_mb": peak_rss_mb(), "bytes": ct.nbytes,
            "parts": ct.nbytes_by_part(), "stats": stats}


def child(cache, *args):
    out = subprocess.run([sys.executable, __file__, "--cache", str(cache), "--child", *args],
                         check=True,
                         stdout=subprocess.PIPE, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def percent(x, base):
    return f"{x / MB:,.1f} ({100 * x / base:.1f}%)"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["dragon", "architecture"])
    parser.add_argument("--cache", default="/tmp/kdtrace-tables")
    parser.add_argument("--reuse", action="store_true", help="reuse cached standard trees")
    parser.add_argument("--sweep", action="store_true", help="tau_occu / tau_freq sweep (bytes)")
    parser.add_argument("--check-rays", type=int, default=0,
                        help="compare every mode with brute force on this many random rays")
    parser.add_argument("--table3", action="store_true", help="render time per mode")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--collapse-sweep", type=float, nargs="+", metavar="K_T",
                        help="ours at these collapse traversal costs: tree bytes and render time")
    parser.add_argument("--skip-tables", action="store_true",
                        help="only --table3 / --check-rays (standard trees from --cache)")
    parser.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    cache = pathlib.Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    if args.child:
        stage, name = args.child[:2]
        if stage == "build":
            result = stage_build(name, cache)
        else:
            result = stage_compact(name, cache, args.child[2], json.loads(args.child[3]))
        print(json.dumps(result, default=float))
        return

    if args.table3 or args.collapse_sweep:
        os.environ["POCL_MAX_PTHREAD_COUNT"] = "1"   # before the OpenCL platform loads
    from kdtrace.core.accel.compact import geometry_nbytes
    print("command:", " ".join(["python"] + sys.argv))
    print("machine:", cpu_model(), f"({os.cpu_count()} logical CPUs),",
          f"{os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2**30:.0f} GiB RAM,",
          f"numpy {np.__version__}")
    if args.skip_tables:
        for name in args.scenes:
            if not (cache / f"{name}.npz").exists():
                raise SystemExit(f"no standard tree for {name} in {cache}: run without "
                                 "--skip-tables first")
        if args.table3:
            table3(args.scenes, cache, args.repeats, args.size)
        if args.collapse_sweep:
            collapse_sweep(args.scenes, cache, args.collapse_sweep, args.repeats, args.size)
        if args.check_rays:
            check_kernel(args.scenes, cache, args.check_rays)
        return
    results = {}
    for name in args.scenes:
        meta = cache / f"{name}.json"
        if args.reuse and meta.exists() and (cache / f"{name}.npz").exists():
            built = json.loads(meta.read_text())
        else:
            print(f"building {name} ...", flush=True)
            built = child(cache, "build", name)
            meta.write_text(json.dumps(built))
        modes = {}
        for mode in MODES:
            modes[mode] = child(cache, "compact", name, mode,
                                json.dumps({"triangles": built["triangles"]}))
            print(f"  {name} {mode}: {modes[mode]['compact_s']:.1f} s, "
                  f"{modes[mode]['bytes'] / MB:.1f} MB", flush=True)
        results[name] = (built, modes)

    print("\nTable 1: scenes (geometry: float32 vertices, 16/32-bit vertex indices; one material)")
    print("| scene | triangles (K) | vertices (K) | geometry MB | standard kd-tree MB |")
    print("|---|---|---|---|---|")
    for name, (built, modes) in results.items():
        geometry = geometry_nbytes(built["vertices"], built["triangles"])["total"]
        print(f"| {name} | {built['triangles'] / 1e3:,.1f} | {built['vertices'] / 1e3:,.1f} | "
              f"{geometry / MB:,.1f} | {modes['standard']['bytes'] / MB:,.1f} |")

    print("\nTable 2a: kd-tree MB (% of standard)")
    print("| scene | standard | choi | ours |")
    print("|---|---|---|---|")
    for name, (built, modes) in results.items():
        base = modes["standard"]["bytes"]
        print(f"| {name} | " + " | ".join(percent(modes[m]["bytes"], base) for m in MODES) + " |")

    print("\nTable 2b: total scene MB = geometry + kd-tree (% of standard)")
    print("| scene | standard | choi | ours |")
    print("|---|---|---|---|")
    for name, (built, modes) in results.items():
        geometry = geometry_nbytes(built["vertices"], built["triangles"])["total"]
        base = geometry + modes["standard"]["bytes"]
        print(f"| {name} | " + " | ".join(percent(geometry + modes[m]["bytes"], base)
                                          for m in MODES) + " |")

    print("\nBuild time (s: standard build + compaction) and peak RSS (MB, largest process)")
    print("| scene | mode | build s | of which compaction s | peak MB | nodes | T-ref slots | "
          "inner refs | lifted tris | leaf refs removed | 2-byte leaves | 4-byte leaves | "
          "max refs/path |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, (built, modes) in results.items():
        for m in MODES:
            r, s = modes[m], modes[m]["stats"]
            print(f"| {name} | {m} | {built['build_s'] + r['compact_s']:.1f} | "
                  f"{r['compact_s']:.1f} | {max(built['peak_mb'], r['peak_mb']):,.0f} | "
                  f"{s['nodes']:,} | {s['tref_nodes']:,} | {s['inner_references']:,} | "
                  f"{s['lifted_triangles']:,} | {s['references_removed']:,} | "
                  f"{s['leaves_16bit']:,} | {s['leaves_32bit']:,} | {s['max_refs_on_path']} |")
    print("\nParts (bytes): ")
    for name, (built, modes) in results.items():
        for m in MODES:
            print(f"  {name} {m}: {modes[m]['parts']}")

    if args.sweep:
        sweep(results, cache)
    if args.check_rays:
        check(args.scenes, cache, args.check_rays)
        check_kernel(args.scenes, cache, args.check_rays)
    if args.table3:
        table3(args.scenes, cache, args.repeats, args.size)
    if args.collapse_sweep:
        collapse_sweep(args.scenes, cache, args.collapse_sweep, args.repeats, args.size)


SWEEP = [
    ("tau_occu", [0.125, 0.25, 0.5, 1.0, 2.0, 4.0], {"tau_freq": 0.4}),
    ("tau_freq", [0.1, 0.2, 0.4, 0.6, 0.8, 1.0], {"tau_occu": 0.5}),
]
ABLATIONS = [
    ("standard + collapse + empty elision + 2-byte leaves (no lifting)",
     "compressed", {"refs_per_node": 0}),
    ("ours without collapse", "compressed", {"collapse": False}),
    ("ours without empty-leaf elision", "compressed", {"elide_empty": False}),
    ("ours without 2-byte leaves", "compressed", {"leaf16": False}),
    ("ours, 2 refs/node, no path limit", "compressed", {"refs_per_path": None}),
]


def sweep(results, cache):
    print("\nThreshold sweep (mode compressed; tree MB as % of standard, inner references, "
          "leaf references removed)")
    for name, (built, modes) in results.items():
        base = modes["standard"]["bytes"]
        for param, values, fixed in SWEEP:
            print(f"\n{name}: {param} (with {fixed})")
            print(f"| {param} | tree MB (%) | inner refs | T-ref slots | leaf refs removed | "
                  f"collapsed subtrees | compaction s |")
            print("|---|---|---|---|---|---|---|")
            for value in values:
                r = child(cache, "compact", name, "compressed", json.dumps(
                    {"triangles": built["triangles"], param: value, **fixed}))
                s = r["stats"]
                print(f"| {value} | {percent(r['bytes'], base)} | {s['inner_references']:,} | "
                      f"{s['tref_nodes']:,} | {s['references_removed']:,} | "
                      f"{s['collapsed_subtrees']:,} | {r['compact_s']:.1f} |", flush=True)
        print(f"\n{name}: ablations")
        print("| variant | tree MB (%) |")
        print("|---|---|")
        for label, mode, options in ABLATIONS:
            r = child(cache, "compact", name, mode, json.dumps({"triangles": built["triangles"],
                                                         **options}))
            print(f"| {label} | {percent(r['bytes'], base)} |", flush=True)


def check(names, cache, count):
    """Nearest triangle and distance of every mode against brute force (float64)."""
    from kdtrace.core.accel.kdtree import KDTree
    from kdtrace.core.accel.compact import compact_tree
    from tests.test_kdtree_compact import brute_force, random_rays, trace_compact
    print(f"\nCorrectness: {count:,} random rays per scene, every mode against brute force")
    for name in names:
        vertices, triangles = load_scene(name)
        corners = vertices.astype(np.float64)[triangles.astype(np.int64)]
        data = np.load(cache / f"{name}.npz")
        tree = KDTree(data["nodes"], data["leaf_indices"], data["bounds"])
        origins, directions = random_rays(corners, count, seed=11)
        started = time.perf_counter()
        bt, btri = brute_force(corners, origins, directions)
        print(f"  {name}: brute force {time.perf_counter() - started:.0f} s, "
              f"{np.isfinite(bt).mean():.1%} of rays hit", flush=True)
        for mode in MODES:
            ct = compact_tree(tree, len(triangles), mode)
            t, tri, visits = np.empty(count), np.empty(count, np.int64), 0
            for start in range(0, count, 100_000):
                part = slice(start, start + 100_000)
                t[part], tri[part], v = trace_compact(ct, corners, origins[part], directions[part])
                visits += v
            print(f"  {name} {mode}: {int((tri != btri).sum())} rays with another triangle, "
                  f"{int((t != bt).sum())} with another distance; {visits / count:.1f} node "
                  f"visits per ray", flush=True)


def _compact_trees(name, cache, triangle_count):
    from kdtrace.core.accel.kdtree import KDTree
    from kdtrace.core.accel.compact import compact_tree
    data = np.load(cache / f"{name}.npz")
    tree = KDTree(data["nodes"], data["leaf_indices"], data["bounds"])
    return {mode: compact_tree(tree, triangle_count, mode) for mode in MODES}


def table3_view(name, vertices, size):
    """The Table 3 camera: the dragon seen from the front; the architecture from inside a room
    of the ground floor, looking diagonally through the doors. One point light, diffuse grey."""
    from kdtrace.core.scene.model import Camera, Light, RenderSettings, Shading, View
    from tests.meshes import look_at
    lo, hi = vertices.min(0).astype(np.float64), vertices.max(0).astype(np.float64)
    centre, extent = (lo + hi) / 2, hi - lo
    if name.startswith("architecture"):
        eye = lo + np.array([8.5, 7.0, 1.6])
        target = eye + np.array([6.0, 4.0, -0.4])
        light = eye + np.array([0.5, 0.3, 0.8])
        up = (0.0, 0.0, 1.0)
    else:   # the Stanford models are y-up and face +z
        eye = centre + np.array([0.0, 0.15 * extent[1], 0.5 * extent[2] + 0.95 * extent[0]])
        target = centre
        light = eye + 0.5 * np.array([extent[0], extent[1], 0.0])
        up = (0.0, 1.0, 0.0)
    camera = Camera("PERSP", look_at(eye, target, up), (0.6, 0.6), (0.0, 0.0), 1e-3, 1e5)
    power = float(4 * np.pi * (np.linalg.norm(target - eye) ** 2)) * 2.0
    shading = Shading(np.array([[0.7, 0.7, 0.7, 1.0]], np.float32),
                      [Light("POINT", (1.0, 1.0, 1.0), power, tuple(light))], (0.1, 0.1, 0.1))
    settings = RenderSettings(samples_per_axis=1, max_bounces=0, light_samples_per_axis=1)
    return View(camera, size, size, shading, settings=settings)


def render_times(name, cache, variants, repeats, size):
    """Render time of one scene per tree variant ({label: (mode, compact_tree options)}): the
    variants in turn within each round, median over the rounds. Returns {label: (median s,
    min s, tree bytes)}; prints the hit rate and whether all variants give identical images."""
    from kdtrace.core.accel.kdtree import KDTree
    from kdtrace.core.accel.compact import compact_tree
    from kdtrace.core.scene.model import Geometry
    from kdtrace.slave.tracer import Tracer
    vertices, triangles = load_scene(name)
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16))
    data = np.load(cache / f"{name}.npz")
    tree = KDTree(data["nodes"], data["leaf_indices"], data["bounds"])
    view = table3_view(name, vertices, size)
    tracers, images, nbytes = {}, {}, {}
    for label, (mode, options) in variants.items():
        compact = compact_tree(tree, len(triangles), mode, **options)
        nbytes[label] = compact.nbytes
        tracers[label] = Tracer("cpu")
        tracers[label].load(geometry, compact)
        images[label] = tracers[label].render_tile(view, 0, 0, size, size)   # warm-up, build
    first = images[next(iter(variants))]
    depth = first["depth"]
    hit_depth = depth[depth < 1e10]
    spread = (f"depth quartiles {np.percentile(hit_depth, [25, 50, 75]).round(2).tolist()}"
              if len(hit_depth) else "no hits")
    same = all(np.array_equal(images[label][k], first[k]) for label in variants for k in first)
    times = {label: [] for label in variants}
    for _ in range(repeats):
        for label in variants:
            started = time.perf_counter()
            tracers[label].render_tile(view, 0, 0, size, size)
            times[label].append(time.perf_counter() - started)
    print(f"  {name}: {(depth < 1e10).mean():.1%} of pixels hit ({spread}), images identical "
          f"across variants: {same}; " + ", ".join(
              f"{label} " + " ".join(f"{t:.3f}" for t in times[label]) for label in variants),
          flush=True)
    return {label: (float(np.median(times[label])), min(times[label]), nbytes[label])
            for label in variants}


def table3(names, cache, repeats, size):
    """Render time per mode (Table 3)."""
    print(f"\nTable 3: render time, {size}x{size}, 1 sample/pixel + 1 shadow ray, "
          f"POCL_MAX_PTHREAD_COUNT={os.environ.get('POCL_MAX_PTHREAD_COUNT')}, "
          f"{repeats} rounds (median; min in brackets)")
    rows = [(name, render_times(name, cache, {m: (m, {}) for m in MODES}, repeats, size))
            for name in names]
    print("| scene | standard s | choi s (% of standard) | ours s (% of standard) |")
    print("|---|---|---|---|")
    for name, r in rows:
        base = r["standard"][0]
        print(f"| {name} | {base:.3f} [{r['standard'][1]:.3f}] | "
              + " | ".join(f"{r[m][0]:.3f} [{r[m][1]:.3f}] ({100 * r[m][0] / base:.1f} %)"
                           for m in ("choi", "compressed")) + " |")


def collapse_sweep(names, cache, costs, repeats, size):
    """What the collapse's traversal cost K_T trades in mode compressed: tree bytes against render
    time, both as % of standard, rendered side by side."""
    print(f"\nCollapse sweep (mode compressed, K_I = 20): {size}x{size} render as Table 3, {repeats} "
          "rounds (median)")
    print("| scene | collapse K_T | tree MB (% of standard) | render s (% of standard) |")
    print("|---|---|---|---|")
    for name in names:
        variants = {"standard": ("standard", {})}
        variants.update({f"K_T {k:g}": ("compressed", {"traversal_cost": k}) for k in costs})
        r = render_times(name, cache, variants, repeats, size)
        base_s, base_bytes = r["standard"][0], r["standard"][2]
        for k in costs:
            s, _, nbytes = r[f"K_T {k:g}"]
            print(f"| {name} | {k:g} | {percent(nbytes, base_bytes)} | {s:.3f} "
                  f"({100 * s / base_s:.1f} %) |", flush=True)


def check_kernel(names, cache, count, brute_sample=1000):
    """The OpenCL kernel on `count` random rays: the three modes agree exactly (triangle, t, u,
    v); the first `brute_sample` rays also against the kernel's brute force (one leaf)."""
    from kdtrace.core.accel.compact import CompactTree
    from kdtrace.core.scene.model import Geometry
    from kdtrace.slave.tracer import Tracer
    from tests.test_kdtree_compact import random_rays
    print(f"\nKernel check: {count:,} random rays per scene through the OpenCL tracer")
    for name in names:
        vertices, triangles = load_scene(name)
        T = len(triangles)
        geometry = Geometry(vertices, triangles, np.zeros(T, np.uint16))
        corners = vertices.astype(np.float64)[triangles.astype(np.int64)]
        origins, directions = random_rays(corners, count, seed=11)
        origins, directions = origins.astype(np.float32), directions.astype(np.float32)
        del corners
        tracer = Tracer("cpu")
        hits = {}
        for mode, ct in _compact_trees(name, cache, T).items():
            tracer.load(Scene.from_parts(geometry, ct))
            started = time.perf_counter()
            hits[mode] = tracer.intersect(origins, directions)
            print(f"  {name} {mode}: {time.perf_counter() - started:.1f} s, "
                  f"{np.isfinite(hits[mode].t).mean():.1%} hit", flush=True)
        for mode in ("choi", "compressed"):
            diff_tri = int((hits[mode].triangle != hits["standard"].triangle).sum())
            diff_t = int((hits[mode].t != hits["standard"].t).sum())
            print(f"  {name} {mode} vs standard: {diff_tri} rays with another triangle, "
                  f"{diff_t} with another distance", flush=True)
        one_leaf = CompactTree(np.array([[3 | (T << 3), 0]], np.uint32),
                               np.arange(T, dtype=np.uint32), np.zeros(0, np.uint16),
                               np.array([vertices.min(0), vertices.max(0)], np.float32), 0)
        tracer.load(Scene.from_parts(geometry, one_leaf))
        k = min(brute_sample, count)
        started = time.perf_counter()
        ref = tracer.intersect(origins[:k], directions[:k])
        for mode in MODES:
            bad = int(((hits[mode].triangle[:k] != ref.triangle)
                       | (hits[mode].t[:k] != ref.t)).sum())
            print(f"  {name} {mode} vs kernel brute force on the first {k:,} rays: {bad} differ "
                  f"({time.perf_counter() - started:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
