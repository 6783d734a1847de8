"""How many samples each engine's adaptive sampling takes per pixel at the same Noise
Threshold (issue 40): Cycles (its Debug Sample Count pass) against KD Trace (each pixel's
samples), on the README's demo scene, and what each costs.

    .venv/bin/python bench/adaptive_samples.py [--width 240 --height 135] [--threshold 0.01]
                                               [--samples 32] [--out bench/out/adaptive]

Cycles renders in a Blender process of its own (tests/bpy_scripts/adaptive_scene.py), on every
core, with Min Samples 0 (automatic, Cycles' default); KD Trace's tracer renders the exported
scene in this process on PoCL's CPU device (every core), in the frame's tiles (64 x 64), with
the panel's defaults for what the bench does not set. Prints the mean, median and 90th
percentile of samples per pixel and the seconds of each; writes <out>/samples.png (Cycles left,
KD Trace right, black 0 to white the most samples either took).
"""
import argparse
import os
import pathlib
import struct
import sys
import tempfile
import time
import zlib

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from bench.machine import cpu_model  # noqa: E402

from kdtrace.core.net.master import DEFAULT_TILE_SIZE as TILE  # noqa: E402


def cycles_sample_counts(values: np.ndarray) -> np.ndarray:
    """Samples per pixel from Cycles' Debug Sample Count pass. The pass holds each pixel's
    samples over the samples the render ran (film_get_pass_pixel_sample_count's scale), which
    with adaptive sampling is the most any pixel took, not Max Samples; pixels stop at multiples
    of the adaptive step (16), so the smallest step between the pass's values is 16 over it."""
    values = np.asarray(values, np.float64)
    steps = np.diff(np.unique(values))
    if not len(steps):
        raise ValueError("every pixel took the same samples: the pass cannot say how many")
    ran = round(16.0 / steps.min())
    counts = values * ran
    if not np.allclose(counts, np.round(counts), atol=1e-2) or np.round(counts).max() != ran:
        raise ValueError(f"the Debug Sample Count pass is not a count over {ran} samples")
    return np.round(counts)


def write_png(path, grey):
    """An 8-bit greyscale PNG of `grey` (h, w) in [0, 1], top row first."""
    rows = (np.clip(grey, 0, 1) * 255).astype(np.uint8)
    raw = b"".join(b"\x00" + row.tobytes() for row in rows)

    def chunk(kind, data):
        return struct.pack("!I", len(data)) + kind + data + struct.pack("!I", zlib.crc32(kind + data))
    header = struct.pack("!IIBBBBB", rows.shape[1], rows.shape[0], 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw))
                     + chunk(b"IEND", b""))


def kdtrace_samples(export_path):
    """KD Trace's samples per pixel (0 where undersampling filled a pixel) and render
    seconds."""
    from kdtrace.core.accel.compact import compact_tree
    from kdtrace.core.accel.binned import build_standard
    from kdtrace.core.frame.exported import load_export
    from kdtrace.core.scene.scene import Scene
    from kdtrace.slave.tracer import Tracer
    exported, view = load_export(export_path)
    [geometry] = exported.meshes
    tree, builder = build_standard(geometry.vertices, geometry.triangles, "cpu")
    compact = compact_tree(tree, geometry.triangle_count, device=builder)
    tracer = Tracer("cpu")
    tracer.load(Scene.from_parts(geometry, compact))
    tracer.render_tile(view, 0, 0, TILE, TILE)      # the kernels built outside the timing
    samples = np.zeros((view.height, view.width), np.float32)
    started = time.perf_counter()
    for y in range(0, view.height, TILE):
        for x in range(0, view.width, TILE):
            w, h = min(TILE, view.width - x), min(TILE, view.height - y)
            tracer.render_tile(view, x, y, w, h)
            counts = tracer.last_render["pixel_samples"]
            samples[y:y + h, x:x + w] = np.where(counts > 1, counts, 0)   # 1: filled
    return samples, time.perf_counter() - started, view


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=240)
    parser.add_argument("--height", type=int, default=135)
    parser.add_argument("--threshold", type=float, default=0.01)
    parser.add_argument("--samples", type=int, default=32, help="Max Samples per axis (N x N)")
    parser.add_argument("--out", default=str(ROOT / "bench" / "out" / "adaptive"))
    args = parser.parse_args()
    print("command:", " ".join(["python"] + sys.argv))
    print("machine:", cpu_model(), f"({os.cpu_count()} logical CPUs); Cycles and KD Trace on every core")
    out = pathlib.Path(args.out).resolve()   # the Blender child runs in another folder
    out.mkdir(parents=True, exist_ok=True)
    work = pathlib.Path(tempfile.mkdtemp(prefix="kdtrace-adaptive-"))
    from tests.blender import build_extension, run_bpy_script
    cycles_s = run_bpy_script(
        "adaptive_scene", work, timeout=3600, zip=str(build_extension(work / "dist")),
        out=str(out), width=args.width, height=args.height, threshold=args.threshold,
        samples_per_axis=args.samples)["cycles_seconds"]
    most = args.samples ** 2
    cycles = cycles_sample_counts(np.load(out / "cycles-samples.npy"))
    ours, ours_s, view = kdtrace_samples(out / "export.npz")
    print(f"demo scene {args.width}x{args.height}, Noise Threshold {args.threshold}, "
          f"Max Samples {most}; KD Trace's Min Samples {view.settings.adaptive_min_samples}, "
          f"Cycles' automatic")
    for name, spp, seconds in (("Cycles", cycles, cycles_s), ("KD Trace", ours, ours_s)):
        print(f"  {name:9s} samples per pixel: mean {spp.mean():7.1f}, median "
              f"{np.median(spp):7.1f}, 90th percentile {np.percentile(spp, 90):7.1f}, "
              f"at the max {np.mean(spp >= most):.1%}; {seconds:6.1f} s "
              f"({seconds / spp.sum() * 1e6:.2f} us per sample)")
    print(f"  mean samples KD Trace / Cycles {ours.mean() / cycles.mean():.2f}")
    top = max(cycles.max(), ours.max())
    write_png(out / "samples.png", np.concatenate([cycles, np.full((len(ours), 4), top), ours], 1) / top)
    print(f"  wrote {out / 'samples.png'}")


if __name__ == "__main__":
    main()
