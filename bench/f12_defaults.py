"""F12 at each engine's own defaults, as a user presses it (issue 40): Cycles (its final-render
defaults: adaptive sampling at a Noise Threshold of 0.01 up to 4096 samples, Open Image Denoise)
against KD Trace (the panel's defaults, which follow Cycles': the same adaptive schedule, the
master's Open Image Denoise) with its local slaves on the same cores, each timed whole
(Blender's render call: export, kd-tree or BVH, sampling, denoising, the image) and compared
with a many-sample Cycles reference (uniform, not denoised, another seed).

Each engine renders each scene once first at one sample a pixel (started: KD Trace's local
slaves, their kernels, the kd-tree on disk; Cycles' kernels), then --repeat timed F12s (the
fastest counts), the two alternating. Beside the wall time, each render's CPU time on the
machine: Cycles' is Blender's process (its render threads); KD Trace's is Blender's process
(the export, the master, the denoising) plus its local slaves' processes (from /proc). On a
machine that other jobs load, wall times stretch with the load; CPU times much less. Scenes: the README's demo (tests/bpy_scripts/blender_setup.py build_demo_scene:
the dragon, a sphere, a cube, a sun, a lamp, a sky colour) and issue 14's interior (an HDRI
through a window, an emissive panel, a chrome ball: bench/image_error.py's builders).

    flock /tmp/bench.lock .venv/bin/python bench/f12_defaults.py [--size 240x135]
        [--scenes demo interior] [--reference-spp 1024] [--repeat 1] [--slaves 2]
        [--out bench/out/f12_defaults]

Prints a table (seconds, PSNR against the reference, KD Trace's denoise seconds, KD Trace /
Cycles time) and writes <out>/f12_defaults.json and the images as .npy.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "bpy_scripts"))

import numpy as np  # noqa: E402


def psnr(image, reference) -> float:
    from tests.test_cycles_scenes import psnr as psnr_db
    return psnr_db(image, reference)


def build(name, builders, width, height):
    import bpy
    from bench.image_error import build_scene
    if name == "demo":
        from blender_setup import build_demo_scene
        builders["clear"]()
        scene = build_demo_scene()
        r = scene.render
        r.resolution_x, r.resolution_y, r.resolution_percentage = width, height, 100
        scene.view_settings.view_transform, scene.view_settings.look = "Standard", "None"
        r.image_settings.file_format, r.image_settings.color_depth = "OPEN_EXR", "32"
    else:
        build_scene(builders, name, width, height)
    return bpy.context.scene


def defaults(scene, engine, slaves, seed=1):
    """`engine` at its own final-render defaults (only the device, the seed and, for KD Trace,
    how slaves are found set)."""
    scene.render.engine = engine
    if engine == "CYCLES":
        c = scene.cycles
        for name in ("samples", "use_adaptive_sampling", "adaptive_threshold", "adaptive_min_samples",
                     "use_denoising", "denoiser", "denoising_prefilter", "denoising_quality",
                     "max_bounces", "diffuse_bounces", "glossy_bounces", "transmission_bounces",
                     "transparent_max_bounces", "sample_clamp_direct", "sample_clamp_indirect",
                     "blur_glossy", "pixel_filter_type", "filter_width"):
            c.property_unset(name)
        c.device, c.seed = "CPU", seed
        scene.render.threads_mode = "AUTO"
    else:
        props = scene.kdtrace
        for name in props.bl_rna.properties.keys():
            if name not in ("rna_type", "hosts", "active_host"):
                props.property_unset(name)
        props.use_zeroconf, props.local_slaves = False, slaves


def reference(scene, spp):
    """Cycles, uniform `spp` samples, not denoised, another seed, at the same light paths."""
    defaults(scene, "CYCLES", 0, seed=2)
    c = scene.cycles
    c.samples, c.use_adaptive_sampling, c.use_denoising = spp, False, False


def cpu_seconds(pids) -> float:
    """CPU seconds (user + system) of this process and the processes `pids` so far."""
    total = sum(os.times()[:2])
    for pid in pids:
        try:
            fields = pathlib.Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return total


def render(scene, path, slave_pids=lambda: []):
    """(the image, wall seconds, CPU seconds of Blender and the local slaves) of one F12."""
    import bpy
    scene.render.filepath = str(path)
    pids = slave_pids()
    cpu = cpu_seconds(pids)
    started = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    seconds = time.perf_counter() - started
    cpu = cpu_seconds(pids or slave_pids()) - cpu
    image = bpy.data.images.load(str(path))
    w, h = image.size
    pixels = np.array(image.pixels[:], np.float32).reshape(h, w, 4)[::-1]
    bpy.data.images.remove(image)
    path.unlink()
    return pixels, seconds, cpu


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="240x135")
    parser.add_argument("--scenes", nargs="+", default=["demo", "interior"],
                        choices=["demo", "interior", "dragon", "engine"])
    parser.add_argument("--reference-spp", type=int, default=1024)
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--slaves", type=int, default=2, help="KD Trace's local slaves")
    parser.add_argument("--out", default=str(ROOT / "bench" / "out" / "f12_defaults"))
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    out = pathlib.Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    print(f"command: {' '.join([os.path.basename(sys.executable)] + sys.argv)}")
    print(f"{os.cpu_count()} logical CPUs, load average {os.getloadavg()[0]:.1f}", flush=True)
    work = pathlib.Path(tempfile.mkdtemp(prefix="kdtrace-f12-"))
    os.environ["BLENDER_USER_RESOURCES"] = str(work / "blender-user")   # before bpy
    from tests.blender import build_extension
    zip_path = build_extension(work / "dist")
    from blender_setup import install_extension
    addon = install_extension(str(zip_path))
    from bench.image_error import issue14_builders
    builders = issue14_builders(str(out))
    report = {"command": sys.argv, "size": [width, height], "reference_spp": args.reference_spp,
              "load_average_start": os.getloadavg(), "scenes": {}}
    for name in args.scenes:
        scene = build(name, builders, width, height)
        reference(scene, args.reference_spp)
        ref, ref_s, _ = render(scene, out / f"{name}-reference.exr")
        np.save(out / f"{name}-reference.npy", ref)
        print(f"\n{name}: {width}x{height}; reference Cycles {args.reference_spp} spp "
              f"{ref_s:.1f} s", flush=True)
        rows = {}

        def slave_pids():
            return addon.addon.session.current().local_slaves.pids()
        for engine, who in (("CYCLES", "cycles"), ("KDTRACE", "kdtrace")):
            defaults(scene, engine, args.slaves)
            if engine == "CYCLES":
                scene.cycles.samples = 1
            else:
                scene.kdtrace.samples_per_axis = 1
            _, first, _ = render(scene, out / f"{name}-{who}-first.exr")
            print(f"  {who} first F12 at 1 sample (start-up): {first:.1f} s", flush=True)
            rows[who] = {"first_s": first, "seconds": math.inf}
        for _ in range(args.repeat):
            for engine, who in (("CYCLES", "cycles"), ("KDTRACE", "kdtrace")):
                defaults(scene, engine, args.slaves)
                image, seconds, cpu = render(scene, out / f"{name}-{who}.exr",
                                             slave_pids if engine == "KDTRACE" else lambda: [])
                if seconds < rows[who]["seconds"]:
                    rows[who].update(seconds=seconds, cpu_s=cpu, psnr=psnr(image, ref))
                    np.save(out / f"{name}-{who}.npy", image)
                    if who == "kdtrace":
                        last = addon.addon.session.current().last_render
                        rows[who].update(denoise_s=last.get("denoise_seconds"),
                                         render_s=last.get("render_seconds"),
                                         steps=last.get("steps"))
                print(f"  {who}: {seconds:.1f} s, CPU {cpu:.1f} s, load "
                      f"{os.getloadavg()[0]:.1f}", flush=True)
        c, k = rows["cycles"], rows["kdtrace"]
        print("| engine | F12 s | CPU s | PSNR dB | denoise s |")
        print("|---|---|---|---|---|")
        print(f"| Cycles | {c['seconds']:.1f} | {c['cpu_s']:.1f} | {c['psnr']:.2f} | (inside) |")
        print(f"| KD Trace | {k['seconds']:.1f} | {k['cpu_s']:.1f} | {k['psnr']:.2f} | "
              f"{k['denoise_s']:.2f} |")
        print(f"KD Trace / Cycles: time {k['seconds'] / c['seconds']:.2f}, CPU "
              f"{k['cpu_s'] / c['cpu_s']:.2f}, PSNR {k['psnr'] - c['psnr']:+.2f} dB", flush=True)
        report["scenes"][name] = {"reference_s": ref_s, **rows}
        (out / "f12_defaults.json").write_text(json.dumps(report, indent=1, default=str))
    report["load_average_end"] = os.getloadavg()
    (out / "f12_defaults.json").write_text(json.dumps(report, indent=1, default=str))
    print(f"\nload average at the end {os.getloadavg()[0]:.1f}; wrote {out / 'f12_defaults.json'}")


if __name__ == "__main__":
    main()
