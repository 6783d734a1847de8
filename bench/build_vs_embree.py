"""The kd-tree build and compaction in OpenCL kernels against Embree's BVH build (issue 11).

    .venv/bin/python bench/build_vs_embree.py [--scenes bunny dragon dragons4 dragons12]
        [--numpy bunny dragon] [--render dragon] [--rounds 5] [--mode compressed]

For every scene, each in a child process of its own (so that its peak memory is its own):
- ours: core.accel.kdtree_cl's build on PoCL's CPU device (all its threads), then compact_tree
  (--mode) on the same device; wall and process CPU seconds (PoCL's threads included), peak
  RSS (mesh included), the longest stretch between two progress calls (how long Esc can take);
  every kernel is compiled in every variant the timed runs launch by two builds first
  (warm_up), timed apart;
- Embree: the BVH build of the same triangles (embreex: the scene's first ray query commits
  it), on the same threads (Embree's default: every hardware thread);
- numpy (--numpy scenes): core.accel.kdtree.build_kdtree and compact_tree without a device,
  whose results must equal ours bit for bit (checked);
- render (--render scenes): render_tile of the Table 3 view (bench/kdtree_tables.py) with
  the compact trees of both builders, in turn over --rounds rounds, one PoCL thread;
- tune (--tune scene, --subtree-refs sizes): the build with each subtree threshold in turn over
  --rounds rounds in one process (the trees must be the same bits), medians;
- first use (--first-use scenes): build and compaction twice in one process on an empty PoCL
  cache, then twice in a second process on the cache the first filled: user, system seconds
  and minor page faults of each (PoCL compiles a kernel variant at its first launch of a kind;
  warm_up);
- profile (--profile scenes): after the timed run, build and compaction again on a queue with
  event profiling: device seconds per kernel, and wall seconds per host step (between two
  distinct progress messages, numbers left out), so the host's share is the rest.
The 4- and 12-dragon scenes are copies of the dragon side by side, as bench/kdtree_tables.py
makes them. Ratios: our build (and build + compaction) over Embree's build of the same triangles.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import pathlib
import re
import resource
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from bench.kdtree_tables import cpu_model  # noqa: E402


def warm_up(builder, mode):
    """Compile every kernel the timed runs launch, in every variant. PoCL compiles a kernel at
    its first launch of each kind: work-group size, zero or non-zero global offset, and under
    or over 65,536 work-items ("goffs0", "smallgrid" in its cache); a big scene's first
    compaction otherwise compiles some 40 variants (about 2.6 s CPU on a cold cache). So the
    warm-up builds and compacts two scenes: a sphere of 8,064 triangles (more references than
    a subtree: every kernel, small launches at zero offset), and one with more nodes,
    references, triangles and lifted references than twice 65,536 (thin triangles: many
    references each) and a degenerate triangle (the kept ones are moved), its launches in
    small pieces (non-zero offsets; the tree does not depend on them)."""
    import core.accel.kdtree_cl as kcl
    from core.accel.compact import compact_tree
    from tests.meshes import uv_sphere
    ball = uv_sphere(64, 64)
    assert len(ball[1]) > builder.subtree_refs
    compact_tree(builder.build(*ball), len(ball[1]), mode, device=builder)
    vertices, triangles = uv_sphere(1000, 80)        # 158,000 triangles, 84 K lifted
    triangles = np.vstack([triangles, triangles[:1, [0, 0, 1]]]).astype(np.uint32)
    assert len(triangles) > 2 * 65536
    pieces = kcl.PIECE_REFS, kcl.PIECE_ITEMS
    kcl.PIECE_REFS, kcl.PIECE_ITEMS = 8 * builder.chunk_refs, 65536
    try:
        compact_tree(builder.build(vertices, triangles), len(triangles), mode, device=builder)
    finally:
        kcl.PIECE_REFS, kcl.PIECE_ITEMS = pieces


def load_scene(name):
    from bench.kdtree_tables import load_scene as tables_scene
    from tests.meshes import load_bunny, load_dragon
    if name == "bunny":
        return load_bunny()
    if name == "dragons4":
        v, t = load_dragon()
        size = v.max(0) - v.min(0)
        vertices = [v + np.array([k * size[0] * 1.1, 0, 0], np.float32) for k in range(4)]
        triangles = [t.astype(np.int64) + k * len(v) for k in range(4)]
        return np.vstack(vertices), np.vstack(triangles).astype(np.uint32)
    return tables_scene(name)


def peak_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def digest(*arrays):
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def timed(fn):
    wall, cpu = time.perf_counter(), time.process_time()
    value = fn()
    return value, time.perf_counter() - wall, time.process_time() - cpu


class ProgressGaps:
    """The longest time between two progress calls (and from the start to the first)."""

    def __init__(self):
        self.last = time.perf_counter()
        self.longest = 0.0
        self.where = ""

    def __call__(self, fraction, message):
        now = time.perf_counter()
        if now - self.last > self.longest:
            self.longest, self.where = now - self.last, message
        self.last = now


class StepTimes:
    """Wall seconds per step: the time up to each new progress message goes to that message
    (digits left out, so the levels of one stage add up); heartbeats repeat the last message."""

    def __init__(self):
        self.last, self.message, self.steps = time.perf_counter(), None, {}

    def __call__(self, fraction, message):
        if message == self.message:
            return
        now, key = time.perf_counter(), re.sub(r"\d[\d,]*", "#", message)
        self.steps[key] = self.steps.get(key, 0.0) + now - self.last
        self.last, self.message = now, message


def stage_profile(name, mode):
    """Where the time goes: kernels by device time, host steps by wall time."""
    from core.accel.compact import compact_tree
    from core.accel.kdtree_cl import KDTreeBuilderCL
    vertices, triangles = load_scene(name)
    builder = KDTreeBuilderCL("cpu", profile_kernels=True)
    warm_up(builder, mode)
    builder.kernel_times()
    result = {}
    for stage, run in (("build", lambda p: builder.build(vertices, triangles, progress=p)),
                       ("compaction", lambda p: compact_tree(tree, len(triangles), mode,
                                                             device=builder, progress=p))):
        steps = StepTimes()
        value, wall, cpu = timed(lambda: run(steps))
        if stage == "build":
            tree = value
        result[stage] = {"wall": wall, "cpu": cpu, "kernels": builder.kernel_times(),
                         "steps": steps.steps}
    return result


def stage_first_use(name, mode):
    """Build and compaction twice, no warm-up: user / system s and minor faults of each."""
    from core.accel.compact import compact_tree
    from core.accel.kdtree_cl import KDTreeBuilderCL
    vertices, triangles = load_scene(name)
    builder = KDTreeBuilderCL("cpu")

    def usage():
        r = resource.getrusage(resource.RUSAGE_SELF)
        return np.array([r.ru_utime, r.ru_stime, r.ru_minflt])

    runs = []
    for _ in range(2):
        start = usage()
        tree = builder.build(vertices, triangles)
        built = usage()
        compact_tree(tree, len(triangles), mode, device=builder)
        runs.append({"build": (built - start).tolist(), "compaction": (usage() - built).tolist()})
        del tree
    return runs


def stage_tune(name, sizes, rounds):
    """The build with each subtree threshold in turn (same process, same trees)."""
    from core.accel.kdtree_cl import KDTreeBuilderCL
    from tests.meshes import uv_sphere
    vertices, triangles = load_scene(name)
    builders = {size: KDTreeBuilderCL("cpu", subtree_refs=size) for size in sizes}
    ball = uv_sphere(128, 64)                 # compile: more references than the thresholds
    assert len(ball[1]) > max(sizes)
    for b in builders.values():
        b.build(*ball)
    times, trees = {size: [] for size in sizes}, set()
    for _ in range(rounds):
        for size, b in builders.items():
            tree, wall, cpu = timed(lambda: b.build(vertices, triangles))
            times[size].append((wall, cpu))
            trees.add(digest(tree.nodes, tree.leaf_indices))
            del tree
    return {"same_trees": len(trees) == 1, "times": {
        str(size): [float(np.median([w for w, _ in t])), float(np.median([c for _, c in t]))]
        for size, t in times.items()}}


def stage_ours(name, mode):
    from core.accel.compact import compact_tree
    from core.accel.kdtree_cl import KDTreeBuilderCL
    vertices, triangles = load_scene(name)
    mesh_mb = peak_mb()
    builder = KDTreeBuilderCL("cpu")
    _, compile_wall, _ = timed(lambda: warm_up(builder, mode))
    gaps = ProgressGaps()
    tree, build_wall, build_cpu = timed(lambda: builder.build(vertices, triangles, progress=gaps))
    build_gap = (gaps.longest, gaps.where)
    gaps = ProgressGaps()
    ct, compact_wall, compact_cpu = timed(
        lambda: compact_tree(tree, len(triangles), mode, device=builder, progress=gaps))
    return {"triangles": len(triangles), "mesh_mb": mesh_mb, "peak_mb": peak_mb(),
            "compile_s": compile_wall, "build_wall": build_wall, "build_cpu": build_cpu,
            "compact_wall": compact_wall, "compact_cpu": compact_cpu,
            "longest_gap_s": max(build_gap[0], gaps.longest),
            "longest_gap_at": build_gap[1] if build_gap[0] >= gaps.longest else gaps.where,
            "threads": int(builder.device.max_compute_units), "device": builder.device_name,
            "stats": {k: v for k, v in tree.stats.items() if k != "device"},
            "compact_bytes": ct.nbytes, "profile": {k: v for k, v in builder.last_profile.items()},
            "tree": digest(tree.nodes, tree.leaf_indices),
            "compact": digest(ct.nodes, ct.leaf_index32, ct.leaf_index16)}


def stage_embree(name):
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh
    vertices, triangles = load_scene(name)
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, vertices, triangles.astype(np.int32))
    origin, direction = np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32)
    _, wall, cpu = timed(lambda: scene.run(origin, direction))     # commits: the BVH build
    return {"build_wall": wall, "build_cpu": cpu, "peak_mb": peak_mb()}


def stage_numpy(name, mode):
    from core.accel.compact import compact_tree
    from core.accel.kdtree import build_kdtree
    vertices, triangles = load_scene(name)
    tree, build_wall, build_cpu = timed(lambda: build_kdtree(vertices, triangles))
    ct, compact_wall, compact_cpu = timed(lambda: compact_tree(tree, len(triangles), mode))
    return {"build_wall": build_wall, "build_cpu": build_cpu, "compact_wall": compact_wall,
            "compact_cpu": compact_cpu, "peak_mb": peak_mb(),
            "tree": digest(tree.nodes, tree.leaf_indices),
            "compact": digest(ct.nodes, ct.leaf_index32, ct.leaf_index16)}


def stage_render(name, mode, rounds, size):
    """Render time of the compact trees from both builders, in turn (one PoCL thread)."""
    from bench.kdtree_tables import table3_view
    from core.accel.compact import compact_tree
    from core.accel.kdtree import build_kdtree
    from core.accel.kdtree_cl import KDTreeBuilderCL
    from core.scene.model import Geometry
    from core.scene.scene import Scene
    from slave.tracer import Tracer
    vertices, triangles = load_scene(name)
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16))
    builder = KDTreeBuilderCL("cpu")
    trees = {"numpy": build_kdtree(vertices, triangles), "opencl": builder.build(vertices, triangles)}
    view = table3_view(name, vertices, size)
    tracers, images, times = {}, {}, {}
    for label, tree in trees.items():
        tracers[label] = Tracer("cpu")
        tracers[label].load(Scene.from_parts(geometry, compact_tree(tree, len(triangles), mode)))
        images[label] = tracers[label].render_tile(view, 0, 0, size, size)    # warm-up, build
        times[label] = []
    for _ in range(rounds):
        for label in trees:
            start = time.perf_counter()
            tracers[label].render_tile(view, 0, 0, size, size)
            times[label].append(time.perf_counter() - start)
    same = all(np.array_equal(images["numpy"][k], images["opencl"][k]) for k in images["numpy"])
    return {"numpy_s": float(np.median(times["numpy"])), "opencl_s": float(np.median(times["opencl"])),
            "rounds": {k: [round(t, 4) for t in v] for k, v in times.items()},
            "identical_images": same, "size": size}


def child(*args, env=None):
    out = subprocess.run([sys.executable, __file__, "--child", *args], check=True,
                         stdout=subprocess.PIPE, text=True, env=env)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["bunny", "dragon", "dragons4", "dragons12"])
    parser.add_argument("--numpy", nargs="*", default=["bunny", "dragon"],
                        help="scenes also built with the numpy builder (checked identical)")
    parser.add_argument("--render", nargs="*", default=["dragon"],
                        help="scenes whose render time is compared (numpy tree vs ours)")
    parser.add_argument("--profile", nargs="*", default=["dragon"],
                        help="scenes built again with kernel event profiling")
    parser.add_argument("--first-use", nargs="*", default=[],
                        help="scenes built and compacted on an empty PoCL cache, then on the filled one")
    parser.add_argument("--tune", nargs="*", default=[],
                        help="scenes built with each --subtree-refs threshold in turn")
    parser.add_argument("--subtree-refs", nargs="+", type=int, default=[512, 2048, 8192])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--mode", default="compressed", choices=("standard", "choi", "compressed"))
    parser.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        stage, name = args.child[:2]
        result = {"compressed": lambda: stage_ours(name, args.mode), "embree": lambda: stage_embree(name),
                  "numpy": lambda: stage_numpy(name, args.mode),
                  "profile": lambda: stage_profile(name, args.mode),
                  "first_use": lambda: stage_first_use(name, args.mode),
                  "tune": lambda: stage_tune(name, args.subtree_refs, args.rounds),
                  "render": lambda: stage_render(name, args.mode, args.rounds, args.size)}[stage]()
        print(json.dumps(result, default=float))
        return

    print("command:", " ".join(["python"] + sys.argv))
    print("machine:", cpu_model(), f"({os.cpu_count()} logical CPUs),",
          f"{os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2**30:.0f} GiB RAM;",
          f"load average {os.getloadavg()[0]:.1f} at the start")
    rows = {}
    for name in args.scenes:
        print(f"{name} ...", file=sys.stderr, flush=True)
        ours = child("compressed", name, "--mode", args.mode)
        embree = child("embree", name)
        numpy_run = child("numpy", name, "--mode", args.mode) if name in args.numpy else None
        rows[name] = (ours, embree, numpy_run)
        print(f"  {name}: ours build {ours['build_wall']:.2f} s, compaction "
              f"{ours['compact_wall']:.2f} s; Embree {embree['build_wall']:.2f} s"
              + (f"; numpy {numpy_run['build_wall']:.1f} + {numpy_run['compact_wall']:.1f} s"
                 if numpy_run else ""), file=sys.stderr, flush=True)
    print(f"\nkd-tree build + '{args.mode}' compaction on {ours['device']} "
          f"({ours['threads']} threads) against Embree's BVH build (wall / process CPU s)")
    print("| scene | triangles | our build | our compaction | build + compaction | peak MB "
          "(mesh) | Embree build | ratio build (build + compaction) | longest Esc wait |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, (ours, embree, _) in rows.items():
        total = ours["build_wall"] + ours["compact_wall"]
        print(f"| {name} | {ours['triangles']:,} | {ours['build_wall']:.2f} / {ours['build_cpu']:.2f} | "
              f"{ours['compact_wall']:.2f} / {ours['compact_cpu']:.2f} | {total:.2f} / "
              f"{ours['build_cpu'] + ours['compact_cpu']:.2f} | {ours['peak_mb']:,.0f} "
              f"({ours['mesh_mb']:,.0f}) | {embree['build_wall']:.2f} / {embree['build_cpu']:.2f} | "
              f"{ours['build_wall'] / embree['build_wall']:.1f}x ({total / embree['build_wall']:.1f}x) | "
              f"{ours['longest_gap_s']:.2f} s |")
    if any(n for _, _, n in rows.values()):
        print("\nThe numpy builder and compaction on the same scenes (wall / CPU s); trees equal bit for bit:")
        print("| scene | numpy build | numpy compaction | ours / numpy (build + compaction, wall) | "
              "same tree | same compact tree |")
        print("|---|---|---|---|---|---|")
        for name, (ours, _, numpy_run) in rows.items():
            if numpy_run is None:
                continue
            ratio = ((ours["build_wall"] + ours["compact_wall"])
                     / (numpy_run["build_wall"] + numpy_run["compact_wall"]))
            print(f"| {name} | {numpy_run['build_wall']:.2f} / {numpy_run['build_cpu']:.2f} | "
                  f"{numpy_run['compact_wall']:.2f} / {numpy_run['compact_cpu']:.2f} | "
                  f"{ratio:.3f} | {ours['tree'] == numpy_run['tree']} | "
                  f"{ours['compact'] == numpy_run['compact']} |")
    print("\nTree stats (ours) and where the build's time went (wall, CPU s):")
    for name, (ours, _, _) in rows.items():
        s = ours["stats"]
        print(f"  {name}: {s['nodes']:,} nodes, depth {s['depth']}, {s['refs_per_triangle']:.2f} "
              f"refs/triangle, SAH {s['sah_cost']:.3f}; compact {ours['compact_bytes'] / 1e6:.1f} MB; "
              f"kernels compiled in {ours['compile_s']:.2f} s (apart); longest Esc wait at "
              f"'{ours['longest_gap_at']}'; {ours['profile']}")
    for name in args.profile:
        p = child("profile", name, "--mode", args.mode)
        print(f"\nProfile of {name} (a second run, on a profiling queue; wall / CPU s):")
        for stage, r in p.items():
            kernel_total = sum(t for t, _ in r["kernels"].values())
            print(f"  {stage}: {r['wall']:.2f} / {r['cpu']:.2f} s; kernels {kernel_total:.2f} s of "
                  f"device time, the rest ({r['wall'] - kernel_total:.2f} s) host steps and waits")
            top = sorted(r["kernels"].items(), key=lambda kv: -kv[1][0])
            print("    kernels (device s, launches): " + ", ".join(
                f"{k} {t:.3f} ({n})" for k, (t, n) in top if t >= 0.005))
            print("    steps (wall s, up to the message): " + "; ".join(
                f"'{k}' {t:.3f}" for k, t in sorted(r["steps"].items(), key=lambda kv: -kv[1])
                if t >= 0.005))
    for name in args.first_use:
        with tempfile.TemporaryDirectory() as cache:
            env = dict(os.environ, POCL_CACHE_DIR=cache)
            runs = [child("first_use", name, "--mode", args.mode, env=env) for _ in range(2)]
        print(f"\nFirst use of {name} (no warm-up; user / system s, minor page faults; process 1 "
              f"on an empty PoCL cache, process 2 on the cache process 1 filled):")
        for p, process in enumerate(runs, 1):
            for k, run in enumerate(process, 1):
                print(f"  process {p}, run {k}: " + "; ".join(
                    f"{stage} {u:.2f} / {sy:.2f} s, {int(faults):,} faults"
                    for stage, (u, sy, faults) in run.items()))
    for name in args.tune:
        r = child("tune", name, "--subtree-refs", *map(str, args.subtree_refs),
                  "--rounds", str(args.rounds))
        print(f"\nBuild of {name} by subtree threshold ({args.rounds} rounds in turn, median wall / "
              f"CPU s; same trees: {r['same_trees']}): " + ", ".join(
                  f"{k}: {w:.2f} / {c:.2f}" for k, (w, c) in r["times"].items()))
    env = dict(os.environ, POCL_MAX_PTHREAD_COUNT="1")
    for name in args.render:
        r = child("render", name, "--mode", args.mode, "--rounds", str(args.rounds),
                  "--size", str(args.size), env=env)
        print(f"\nRender {name} ({r['size']}x{r['size']}, '{args.mode}' tree, one PoCL thread, "
              f"{args.rounds} rounds in turn, median): numpy tree {r['numpy_s']:.3f} s, ours "
              f"{r['opencl_s']:.3f} s ({100 * r['opencl_s'] / r['numpy_s']:.1f} %); identical images: "
              f"{r['identical_images']}; rounds {r['rounds']}")


if __name__ == "__main__":
    main()
