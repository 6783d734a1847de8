"""The kd-tree build and compaction in OpenCL kernels against Embree's BVH build, and against
the trees of an earlier version of KD Trace, side by side in one run (issue 36).

    .venv/bin/python bench/build_vs_embree.py [--scenes bunny dragon dragons4 dragons12]
        [--before DIR] [--render dragon] [--load dragons12] [--profile dragon]
        [--rounds 3] [--size 512] [--mode compressed]

Every measurement runs in a child process of its own (so that its peak memory is its own):
- ours: core.accel.binned's build on PoCL's CPU device (all its threads), compact_tree (--mode)
  on the same device, then the treelet order the master sends (core/accel/reorder.py); wall and
  process CPU seconds (PoCL's threads included), peak RSS (mesh included), the longest stretch
  between two progress calls (how long Esc can take), the tree's stats. The kernels are
  compiled first by a build and compaction of two spheres (warm_up), timed apart;
- Embree: the BVH build of the same triangles (embreex: the scene's first ray query commits
  it), on the same threads (Embree's default: every hardware thread);
- before (--before DIR: a checkout of the earlier version, with this repository's assets/ and
  .venv beside its own): that version's own benchmark child (its build and compaction, the
  same warm-up), so the figures of both versions come from the same minutes of this machine;
- render (--render scenes, needs --before): the earlier version's compact tree and ours, both
  in treelets (the earlier slave laid trees out in treelets as it loaded them; ours come so
  from the master), traced with the current tracer on every ray kind of bench/ray_kinds.py
  (the same rays; Embree's primary hits start the secondary rays) and through the render
  kernel, one PoCL thread, the two trees alternating; best process CPU time of --rounds;
- load (--load scenes): what a slave does with a scene that arrives: Scene.from_wire (every
  check of the geometry and the tree) and Tracer.load (the upload), for our tree and, with
  --before, the earlier version's slave on its own tree (which laid it out in treelets here);
- profile (--profile scenes): build and compaction again on a queue with event profiling:
  device seconds per kernel.
Ratios: our build + compaction over Embree's build of the same triangles (so per triangle).
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import resource
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from bench.machine import cpu_model  # noqa: E402

KINDS = ("primary_rows", "primary_tiles", "diffuse", "diffuse_pixels", "shadow_point",
         "shadow_area", "glossy")


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


def timed(fn):
    wall, cpu = time.perf_counter(), time.process_time()
    value = fn()
    return value, time.perf_counter() - wall, time.process_time() - cpu


class ProgressGaps:
    """The longest time between two progress calls (and from the start to the first)."""

    def __init__(self):
        self.last = time.perf_counter()
        self.longest, self.where = 0.0, ""

    def __call__(self, fraction, message):
        now = time.perf_counter()
        if now - self.last > self.longest:
            self.longest, self.where = now - self.last, message
        self.last = now


def warm_up(builder, mode):
    """Compile every kernel variant the timed runs launch (PoCL compiles a kernel at its first
    launch of each work-group size, offset and size class): a sphere of 8,064 triangles, then
    one of 158,001 with a degenerate triangle, its launches in small pieces."""
    import kdtrace.core.accel.binned as binned
    from kdtrace.core.accel.compact import compact_tree
    from tests.meshes import uv_sphere
    ball = uv_sphere(64, 64)
    compact_tree(builder.build(*ball), len(ball[1]), mode, device=builder)
    vertices, triangles = uv_sphere(1000, 80)
    triangles = np.vstack([triangles, triangles[:1, [0, 0, 1]]]).astype(np.uint32)
    pieces = binned.PIECE_NODES, binned.PIECE_REFS
    binned.PIECE_NODES, binned.PIECE_REFS = 4096, 8 * builder.chunk_refs
    try:
        compact_tree(builder.build(vertices, triangles), len(triangles), mode, device=builder)
    finally:
        binned.PIECE_NODES, binned.PIECE_REFS = pieces


def build_ours(builder, vertices, triangles, mode, progress=None):
    """The master's work on a mesh: build, compaction, treelets (TreeCache.get's steps)."""
    from kdtrace.core.accel.compact import compact_tree
    from kdtrace.core.accel.reorder import treelet_order
    tree = builder.build(vertices, triangles, progress=progress)
    ct = compact_tree(tree, len(triangles), mode, device=builder, progress=progress)
    return tree, ct, treelet_order(ct, heartbeat=lambda: progress and progress(1.0, "treelets"))


def stage_ours(name, mode):
    from kdtrace.core.accel.binned import BinnedBuilder
    from kdtrace.core.accel.compact import compact_tree
    from kdtrace.core.accel.reorder import treelet_order
    vertices, triangles = load_scene(name)
    mesh_mb = peak_mb()
    builder = BinnedBuilder("cpu")
    _, compile_wall, _ = timed(lambda: warm_up(builder, mode))
    gaps = ProgressGaps()
    tree, build_wall, build_cpu = timed(lambda: builder.build(vertices, triangles, progress=gaps))
    ct, compact_wall, compact_cpu = timed(
        lambda: compact_tree(tree, len(triangles), mode, device=builder, progress=gaps))
    _, treelet_wall, treelet_cpu = timed(
        lambda: treelet_order(ct, heartbeat=lambda: gaps(1.0, "treelets")))
    return {"triangles": len(triangles), "mesh_mb": mesh_mb, "peak_mb": peak_mb(),
            "compile_s": compile_wall, "build_wall": build_wall, "build_cpu": build_cpu,
            "compact_wall": compact_wall, "compact_cpu": compact_cpu,
            "treelet_wall": treelet_wall, "treelet_cpu": treelet_cpu,
            "longest_gap_s": gaps.longest, "longest_gap_at": gaps.where,
            "threads": builder.compute_units, "device": builder.device_name,
            "stats": {k: v for k, v in tree.stats.items() if k != "device"},
            "compact_bytes": ct.nbytes, "compact_nodes": len(ct.nodes)}


def stage_embree(name):
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh
    vertices, triangles = load_scene(name)
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, vertices, triangles.astype(np.int32))
    origin, direction = np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32)
    _, wall, cpu = timed(lambda: scene.run(origin, direction))     # commits: the BVH build
    return {"build_wall": wall, "build_cpu": cpu, "peak_mb": peak_mb()}


def stage_profile(name, mode):
    from kdtrace.core.accel.binned import BinnedBuilder
    vertices, triangles = load_scene(name)
    builder = BinnedBuilder("cpu", profile_kernels=True)
    warm_up(builder, mode)
    builder.kernel_times()
    from kdtrace.core.accel.compact import compact_tree
    tree, wall, cpu = timed(lambda: builder.build(vertices, triangles))
    out = {"build": {"wall": wall, "cpu": cpu, "kernels": builder.kernel_times()}}
    _, wall, cpu = timed(lambda: compact_tree(tree, len(triangles), mode, device=builder))
    out["compaction"] = {"wall": wall, "cpu": cpu, "kernels": builder.kernel_times()}
    return out


def scene_of(vertices, triangles, tree):
    from kdtrace.core.scene.model import Geometry
    from kdtrace.core.scene.scene import Scene
    return Scene.from_parts(Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16)),
                            tree)


def stage_load(name, mode, tree_path=None):
    """A slave's load of the scene (from_wire's checks and the upload), best of 3."""
    from kdtrace.core.scene.scene import Scene
    from kdtrace.slave.tracer import Tracer
    vertices, triangles = load_scene(name)
    if tree_path:
        tree = _read_tree(tree_path)
    else:
        from kdtrace.core.accel.binned import BinnedBuilder
        tree = build_ours(BinnedBuilder("cpu"), vertices, triangles, mode)[2]
    arrays = scene_of(vertices, triangles, tree).wire_arrays()
    tracer, times = Tracer("cpu"), []
    for _ in range(3):
        scene, check_wall, _ = timed(lambda: Scene.from_wire(dict(arrays)))
        _, load_wall, _ = timed(lambda: tracer.load(scene))
        times.append((check_wall + load_wall, check_wall, load_wall))
    total, check, load = min(times)
    return {"total": total, "check": check, "upload": load, "nodes": len(tree.nodes)}


def stage_render(name, mode, rounds, size, before_tree):
    """Every ray kind and the render kernel through our tree and the earlier version's (both
    in treelets), the same rays, one PoCL thread; best process CPU time of each."""
    from bench.kdtree_tables import table3_view
    from bench.ray_kinds import embree_scene, ours_query, scene_rays
    from kdtrace.core.accel.binned import BinnedBuilder
    from kdtrace.core.accel.reorder import treelet_order
    from kdtrace.slave.tracer import Tracer
    vertices, triangles = load_scene(name)
    ours = build_ours(BinnedBuilder("cpu"), vertices, triangles, mode)[2]
    trees = {"before": treelet_order(_read_tree(before_tree)), "ours": ours}
    tracers = {}
    for label, tree in trees.items():
        tracers[label] = Tracer("cpu")
        tracers[label].load(scene_of(vertices, triangles, tree))
    rays = scene_rays(name, vertices, triangles, size, embree_scene(vertices, triangles))
    view = table3_view(name, vertices, size)
    out = {}
    for kind in KINDS + ("render",):
        if kind == "render":
            run = {k: (lambda t=t: t.render_tile(view, 0, 0, size, size)) for k, t in tracers.items()}
        else:
            o, d, tmax = rays[kind]
            shadow = kind.startswith("shadow")
            run = {k: (lambda t=t: ours_query(t, o, d, tmax, shadow)) for k, t in tracers.items()}
        answers = {k: f() for k, f in run.items()}             # also compiles
        times = {k: [] for k in run}
        for r in range(rounds):
            for k in (list(run) if r % 2 == 0 else list(run)[::-1]):
                times[k].append(timed(run[k])[2])
        a, b = answers["before"], answers["ours"]
        if kind == "render":
            same = all(np.array_equal(a[n], b[n]) for n in a)
        elif kind.startswith("shadow"):
            same = bool(np.array_equal(a, b))
        else:
            same = bool(np.array_equal(a.triangle, b.triangle) and np.array_equal(a.t, b.t))
        out[kind] = {"before": min(times["before"]), "ours": min(times["ours"]), "same": same}
    return out


def _read_tree(path):
    from kdtrace.core.accel.compact import CompactTree
    with np.load(path) as data:
        return CompactTree(data["nodes"], data["leaf_index32"], data["leaf_index16"],
                           data["bounds"], int(data["leaf_shift"]))


# The earlier version's compact tree of a scene, built with its own code (run in its checkout).
BEFORE_TREE = """
import sys, numpy as np
sys.path.insert(0, {root!r})
from bench.build_vs_embree import load_scene
from core.accel.compact import compact_tree
from core.accel.kdtree_cl import KDTreeBuilderCL
v, t = load_scene({name!r})
b = KDTreeBuilderCL("cpu")
ct = compact_tree(b.build(v, t), len(t), {mode!r}, device=b)
np.savez({path!r}, nodes=ct.nodes, leaf_index32=ct.leaf_index32, leaf_index16=ct.leaf_index16,
         bounds=ct.bounds, leaf_shift=ct.leaf_shift)
"""

# The earlier version's slave loading that tree (its Scene checks and its Tracer.load, which
# laid the tree out in treelets), best of 3.
BEFORE_LOAD = """
import sys, time, json, numpy as np
sys.path.insert(0, {root!r})
from bench.build_vs_embree import load_scene
from core.accel.compact import CompactTree
from core.scene.model import Geometry
from core.scene.scene import Scene
from slave.tracer import Tracer
v, t = load_scene({name!r})
with np.load({path!r}) as d:
    tree = CompactTree(d["nodes"], d["leaf_index32"], d["leaf_index16"], d["bounds"], int(d["leaf_shift"]))
arrays = Scene.from_parts(Geometry(v, t, np.zeros(len(t), np.uint16)), tree).wire_arrays()
tracer, best = Tracer("cpu"), None
for _ in range(3):
    w = time.perf_counter(); scene = Scene.from_wire(dict(arrays)); c = time.perf_counter() - w
    w = time.perf_counter(); tracer.load(scene); u = time.perf_counter() - w
    best = min(best or (1e9,), (c + u, c, u))
print(json.dumps({{"total": best[0], "check": best[1], "upload": best[2], "nodes": len(tree.nodes)}}))
"""


def child(*args, env=None, cwd=None):
    script = pathlib.Path(cwd or ROOT) / "bench" / "build_vs_embree.py"
    out = subprocess.run([sys.executable, str(script), "--child", *args], check=True,
                         stdout=subprocess.PIPE, text=True, env=env, cwd=cwd)
    return json.loads(out.stdout.strip().splitlines()[-1])


def run_script(text, cwd, env=None):
    out = subprocess.run([sys.executable, "-c", text], check=True, stdout=subprocess.PIPE,
                         text=True, cwd=cwd, env=env)
    lines = out.stdout.strip().splitlines()
    return json.loads(lines[-1]) if lines else None


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["bunny", "dragon", "dragons4", "dragons12"])
    parser.add_argument("--before", help="a checkout of the earlier version to compare with")
    parser.add_argument("--render", nargs="*", default=["dragon"])
    parser.add_argument("--load", nargs="*", default=["dragons12"])
    parser.add_argument("--profile", nargs="*", default=["dragon"])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--mode", default="compressed", choices=("standard", "choi", "compressed"))
    parser.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        stage, name, *rest = args.child
        result = {"compressed": lambda: stage_ours(name, args.mode),
                  "embree": lambda: stage_embree(name),
                  "profile": lambda: stage_profile(name, args.mode),
                  "load": lambda: stage_load(name, args.mode, *rest),
                  "render": lambda: stage_render(name, args.mode, args.rounds, args.size,
                                                 *rest)}[stage]()
        print(json.dumps(result, default=float))
        return

    print("command:", " ".join(["python"] + sys.argv))
    print("machine:", cpu_model(), f"({os.cpu_count()} logical CPUs),",
          f"{os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2**30:.0f} GiB RAM;",
          f"load average {os.getloadavg()[0]:.1f} at the start")
    before = pathlib.Path(args.before).resolve() if args.before else None
    if before:
        commit = subprocess.run(["git", "-C", str(before), "log", "-1", "--format=%h %s"],
                                capture_output=True, text=True).stdout.strip()
        print(f"before: {before} at {commit[:72]}")
    temp = pathlib.Path(tempfile.mkdtemp(prefix="kdtrace-bench-"))
    rows = {}
    for name in args.scenes:
        print(f"{name} ...", file=sys.stderr, flush=True)
        ours = child("compressed", name, "--mode", args.mode)
        then = child("compressed", name, "--mode", args.mode, cwd=before) if before else None
        embree = child("embree", name)
        rows[name] = (ours, then, embree)
        print(f"  {name}: ours {ours['build_wall']:.2f} + {ours['compact_wall']:.2f} s; Embree "
              f"{embree['build_wall']:.2f} s" + (f"; before {then['build_wall']:.2f} + "
                                                 f"{then['compact_wall']:.2f} s" if then else ""),
              file=sys.stderr, flush=True)
    threads = next(iter(rows.values()))[0]["threads"]
    print(f"\nkd-tree build + '{args.mode}' compaction on PoCL's CPU device ({threads} threads) "
          "against Embree's BVH build of the same triangles (wall / process CPU s)")
    print("| scene | triangles | version | build | compaction | build + compaction | treelets "
          "(master) | peak MB (mesh) | Embree build | ratio (build + compaction) | longest Esc "
          "wait | nodes | SAH cost |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, (ours, then, embree) in rows.items():
        for label, r in (("before", then), ("now", ours)):
            if r is None:
                continue
            total = r["build_wall"] + r["compact_wall"]
            treelets = (f"{r['treelet_wall']:.2f}" if "treelet_wall" in r else "(slave)")
            print(f"| {name} | {r['triangles']:,} | {label} | {r['build_wall']:.2f} / "
                  f"{r['build_cpu']:.2f} | {r['compact_wall']:.2f} / {r['compact_cpu']:.2f} | "
                  f"{total:.2f} / {r['build_cpu'] + r['compact_cpu']:.2f} | {treelets} | "
                  f"{r['peak_mb']:,.0f} ({r['mesh_mb']:,.0f}) | {embree['build_wall']:.2f} / "
                  f"{embree['build_cpu']:.2f} | {total / embree['build_wall']:.1f}x | "
                  f"{r['longest_gap_s']:.2f} s | {r['stats']['nodes']:,} | "
                  f"{r['stats']['sah_cost']:.1f} |")
    print("\nTree stats (now):")
    for name, (ours, then, _) in rows.items():
        s = ours["stats"]
        line = (f"  {name}: {s['nodes']:,} nodes, depth {s['depth']}, {s['refs_per_triangle']:.2f} "
                f"refs/triangle, SAH {s['sah_cost']:.1f}")
        if then:
            line += f" ({100 * s['sah_cost'] / then['stats']['sah_cost']:.1f} % of before's)"
        print(line + f"; compact {ours['compact_bytes'] / 1e6:.1f} MB, {ours['compact_nodes']:,} "
              f"nodes; kernels compiled in {ours['compile_s']:.2f} s (apart); longest Esc wait "
              f"at '{ours['longest_gap_at']}'")
    for name in args.profile:
        p = child("profile", name, "--mode", args.mode)
        print(f"\nProfile of {name} (a second run on a profiling queue; wall / CPU s):")
        for stage, r in p.items():
            kernel_total = sum(t for t, _ in r["kernels"].values())
            top = sorted(r["kernels"].items(), key=lambda kv: -kv[1][0])
            print(f"  {stage}: {r['wall']:.2f} / {r['cpu']:.2f} s; kernels {kernel_total:.2f} s: "
                  + ", ".join(f"{k} {t:.3f} ({n})" for k, (t, n) in top if t >= 0.005))
    saved = {}
    if before:
        for name in sorted(set(args.render) | set(args.load)):
            saved[name] = str(temp / f"{name}.npz")
            run_script(BEFORE_TREE.format(root=str(before), name=name, mode=args.mode,
                                          path=saved[name]), before)
    one_thread = dict(os.environ, POCL_MAX_PTHREAD_COUNT="1")
    for name in args.render if before else []:
        r = child("render", name, saved[name], "--mode", args.mode, "--rounds", str(args.rounds),
                  "--size", str(args.size), env=one_thread)
        print(f"\nRays of {name} ({args.size}x{args.size} view of bench/ray_kinds.py, '{args.mode}' "
              f"trees in treelets, one PoCL thread, best of {args.rounds}; process CPU s):")
        print("| ray kind | before's tree | our tree | ours / before | same answers |")
        print("|---|---|---|---|---|")
        for kind, x in r.items():
            print(f"| {kind} | {x['before']:.3f} | {x['ours']:.3f} | "
                  f"{100 * x['ours'] / x['before']:.1f} % | {x['same']} |")
    for name in args.load:
        now = child("load", name, "--mode", args.mode)
        line = (f"\nSlave load of {name} (Scene.from_wire's checks + Tracer.load; wall s, best of "
                f"3): now {now['total']:.2f} (checks {now['check']:.2f}, upload {now['upload']:.2f}; "
                f"{now['nodes']:,} nodes)")
        if before:
            then = run_script(BEFORE_LOAD.format(root=str(before), name=name, path=saved[name]),
                              before)
            line += (f"; before {then['total']:.2f} (checks {then['check']:.2f}, treelets and "
                     f"upload {then['upload']:.2f}; {then['nodes']:,} nodes)")
        print(line)


if __name__ == "__main__":
    main()
