"""The fixed cost of a KD Trace render (issue 12): a repeated F12 of an unchanged scene at 1 spp,
step by step, beside Cycles' render of the same scene.

Inside Blender (the bpy module, in a child process, as bench/image_error.py --against-cycles:
the same scene builders and render settings), the dragon scene of the Cycles comparison (871k
triangles, 96x72) is rendered once by each renderer to start what later renders reuse (KD
Trace: the local slave, its kernels, the kd-tree in the add-on's cache), then --renders times
each at 1 spp, alternating. It prints the first KD Trace render's steps, and per KD Trace
render the wall time of Blender's render call and the add-on's steps (addon/render.py
`Steps`: export, the kd-tree cache, the scene, the slaves' connection, the scene query, the
frame's start, its first tile, the rest of the tiles, the image, the master's close) and the
slave's own render time of the tiles; medians over the renders.

With --compare REV the same child runs also on the add-on of git revision REV (its zip built
from `git archive`), the two alternating --rounds times: before and after in one run.

Each round starts with no kd-tree on disk (the add-on's cache in its user folder,
core/scene/tree_files.py, is emptied). With --restarts N, N more Blender processes follow each
child on the same user folder, each timing only its first renders: F12 after Blender restarts.

    flock /tmp/bench.lock .venv/bin/python bench/render_fixed_cost.py [--renders 5]
        [--compare main] [--rounds 2] [--restarts 1] [--profile] [--scene dragon]
        [--size 96x72]
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench.image_error import (CYCLES_SCENES, build_scene, issue14_builders,  # noqa: E402
                               kdtrace_settings, start_run, use_renderer, without_trees_on_disk)


def child(arguments: dict, result_path: str) -> None:
    """In a process that imports bpy: the renders of the module docstring; writes their times."""
    sys.path.insert(0, str(ROOT / "tests" / "bpy_scripts"))
    import importlib

    import bpy
    from blender_setup import install_extension
    install_extension(arguments["zip"])
    session = importlib.import_module("bl_ext.user_default.kdtrace.addon.session")
    out = pathlib.Path(arguments["out"])
    name = arguments["scene"]
    build_scene(issue14_builders(str(out)), name, arguments["width"], arguments["height"])
    scene = bpy.context.scene
    settings = dict(CYCLES_SCENES[name].settings, **arguments["kdtrace"])

    def render(engine: str, profile=None) -> float:
        use_renderer(scene, engine, 1, settings)
        scene.render.filepath = str(out / f"fixed-{engine.lower()}.exr")
        started = time.perf_counter()
        if profile is not None:
            profile.enable()
        bpy.ops.render.render(write_still=True)
        if profile is not None:
            profile.disable()
        return time.perf_counter() - started

    result = {"first": {engine: render(engine) for engine in ("CYCLES", "KDTRACE")},
              "cycles": [], "kdtrace": [], "reports": [],
              "first_steps": dict(session.current().last_render.get("steps") or {})}
    for i in range(arguments["renders"]):
        order = ("CYCLES", "KDTRACE") if i % 2 == 0 else ("KDTRACE", "CYCLES")
        for engine in order:
            seconds = render(engine)
            result[engine.lower()].append(seconds)
            if engine == "KDTRACE":
                last = session.current().last_render
                result["reports"].append({key: last.get(key) for key in (
                    "export_seconds", "tree_seconds", "render_seconds", "steps",
                    "tile_render_ms", "tiles_per_slave")})
    if arguments["profile"]:
        import cProfile
        import io
        import pstats
        profile = cProfile.Profile()
        render("KDTRACE", profile)
        text = io.StringIO()
        pstats.Stats(profile, stream=text).sort_stats("cumulative").print_stats(40)
        result["profile"] = text.getvalue()
    pathlib.Path(result_path).write_text(json.dumps(result))


def build_zip(source: pathlib.Path, out: pathlib.Path) -> pathlib.Path:
    """The extension zip of the checkout at `source` (tests/blender.py's build, another root)."""
    from tests.blender import blender_ext_tool
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("kdtrace-*.zip"):
        old.unlink()
    subprocess.run([sys.executable, str(blender_ext_tool()), "build", "--source-dir", str(source),
                    "--output-dir", str(out)], check=True, capture_output=True, text=True)
    [zip_path] = out.glob("kdtrace-*.zip")
    return zip_path


def revision_zip(revision: str, out: pathlib.Path) -> pathlib.Path:
    """The extension zip of git revision `revision` of this repository."""
    source = pathlib.Path(tempfile.mkdtemp(prefix="kdtrace-rev-", dir=out))
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", revision], check=True,
                             capture_output=True).stdout
    tar_path = source / "rev.tar"
    tar_path.write_bytes(archive)
    with tarfile.open(tar_path) as tar:
        tar.extractall(source, filter="data")
    tar_path.unlink()
    return build_zip(source, out / "dist-rev")


def median(values):
    return statistics.median(values) if values else float("nan")


def first_renders(label: str, results: list) -> None:
    """The first renders of each child, with the KD Trace render's steps."""
    print(f"\n{label}: first renders KD Trace "
          + ", ".join(f"{r['first']['KDTRACE']:.1f}" for r in results) + " s, Cycles "
          + ", ".join(f"{r['first']['CYCLES']:.2f}" for r in results) + " s")
    for r in results:
        print("    the first KD Trace render's steps: " + ", ".join(
            f"{step} {seconds:.2f}" for step, seconds in r.get("first_steps", {}).items()))


def summary(label: str, results: list) -> None:
    """Medians of every child's renders of one add-on, with its steps."""
    cycles = [s for r in results for s in r["cycles"]]
    ours = [s for r in results for s in r["kdtrace"]]
    reports = [rep for r in results for rep in r["reports"]]
    first_renders(f"{label}, {len(ours)} renders each", results)
    print(f"  Cycles render call    {median(cycles):6.3f} s  (min {min(cycles):.3f})")
    print(f"  KD Trace render call  {median(ours):6.3f} s  (min {min(ours):.3f})  "
          f"KD Trace / Cycles {median(ours) / median(cycles):.2f}")
    steps = {}
    for report in reports:
        for step, seconds in (report.get("steps") or {}).items():
            steps.setdefault(step, []).append(seconds)
    for step, values in steps.items():
        print(f"    {step:18s} {median(values) * 1000:7.1f} ms")
    if steps:
        inside = [sum((rep.get("steps") or {}).values()) for rep in reports]
        print(f"    {'(add-on total)':18s} {median(inside) * 1000:7.1f} ms; Blender's own part of "
              f"the call {(median(ours) - median(inside)) * 1000:.1f} ms")
    else:
        print("    add-on report: export {:.3f} s, kd-tree {:.3f} s, render {:.3f} s".format(
            *(median([rep[k] for rep in reports]) for k in
              ("export_seconds", "tree_seconds", "render_seconds"))))
    tile_ms = [rep["tile_render_ms"] for rep in reports if rep.get("tile_render_ms") is not None]
    if tile_ms:
        print(f"    slave's tile render time, all tiles: {median(tile_ms):.1f} ms")
    for r in results:
        if r.get("profile"):
            print(r["profile"])


def main():
    if len(sys.argv) == 4 and sys.argv[1] == "--bpy-child":
        child(json.loads(sys.argv[2]), sys.argv[3])
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="dragon", choices=list(CYCLES_SCENES))
    parser.add_argument("--size", default="96x72", help="WxH")
    parser.add_argument("--renders", type=int, default=5, help="timed renders of each renderer")
    parser.add_argument("--compare", metavar="REV", help="also the add-on of this git revision")
    parser.add_argument("--rounds", type=int, default=1, help="with --compare: alternations")
    parser.add_argument("--restarts", type=int, default=0,
                        help="Blender processes after each child that time only their first "
                             "renders, with the kd-trees the child left on disk")
    parser.add_argument("--profile", action="store_true",
                        help="cProfile one more KD Trace render (the render thread)")
    parser.add_argument("--out", default=str(ROOT / "bench" / "out" / "render_fixed_cost"))
    args = parser.parse_args()
    width, height, out = start_run(args)
    zips = {"this checkout": build_zip(ROOT, out / "dist")}
    if args.compare:
        zips = {args.compare: revision_zip(args.compare, out), **zips}
    results = {label: [] for label in zips}
    restarted = {label: [] for label in zips}
    for _ in range(args.rounds if args.compare else 1):
        for label, zip_path in zips.items():
            # The round starts with no tree on disk.
            user = without_trees_on_disk(out / f"blender-user-{list(zips).index(label)}")
            for restart in range(1 + args.restarts):
                arguments = {"zip": str(zip_path), "out": str(out), "scene": args.scene,
                             "width": width, "height": height,
                             "renders": 0 if restart else args.renders,
                             "kdtrace": kdtrace_settings(), "profile": args.profile and not restart}
                result_path = out / "child-result.json"
                env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1",
                           BLENDER_USER_RESOURCES=str(user))
                subprocess.run([sys.executable, __file__, "--bpy-child", json.dumps(arguments),
                                str(result_path)], env=env, check=True, cwd=out)
                (restarted if restart else results)[label].append(
                    json.loads(result_path.read_text()))
    print(f"\n{args.scene} {width}x{height}, 1 spp; load average after {os.getloadavg()[0]:.1f}")
    for label, runs in results.items():
        summary(label, runs)
        if restarted[label]:
            first_renders(f"{label}, after Blender restarted", restarted[label])


if __name__ == "__main__":
    main()
