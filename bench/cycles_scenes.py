"""Issue 14's scenes (tests/bpy_scripts/cycles_scenes.py) rendered larger and with more samples
than the test renders them, with Cycles and with KD Trace (inside Blender, the installed
add-on and two local slaves, on the same cores): a PSNR table and, for docs/cycles_features.md,
side-by-side images (Cycles left, KD Trace right).

    .venv/bin/python bench/cycles_scenes.py [--size 160x120] [--out bench/out/cycles_scenes]
        [--images docs/images]
"""
from __future__ import annotations

import argparse
import pathlib
import platform
import shutil
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests.blender import build_extension, run_bpy_script  # noqa: E402
from tests.test_cycles_scenes import MATCHED, SCENES, psnr  # noqa: E402

IMAGES = ("world_color", "world_hdri", "emission_room", "glass")   # shown in the docs


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--samples-scale", type=float, default=1.5,
                        help="samples per axis of each scene relative to the test's")
    parser.add_argument("--out", default=str(ROOT / "bench" / "out" / "cycles_scenes"))
    parser.add_argument("--images", default=str(ROOT / "docs" / "images"))
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"command: {' '.join(sys.argv)}\nmachine: {platform.processor() or platform.machine()}, "
          f"{platform.system()}")
    axis = {name: max(1, round(n * args.samples_scale)) for name, (n, _) in SCENES.items()}
    result = run_bpy_script("cycles_scenes", out, timeout=7200,
                            zip=str(build_extension(out / "dist")), out=str(out),
                            scenes=list(SCENES), width=width, height=height, kdtrace=MATCHED,
                            per_scene={name: {"samples_per_axis": n} for name, n in axis.items()},
                            side_by_side=True)
    print(f"\n{width}x{height}, uniform sampling, Cycles' Light Paths defaults for both\n")
    print("| scene | samples | PSNR dB | mean KD Trace / Cycles | KD Trace s | Cycles s |")
    print("|---|---|---|---|---|---|")
    for name in SCENES:
        cycles, ours = (np.load(out / f"{name}-{who}.npy") for who in ("cycles", "kdtrace"))
        print(f"| {name} | {axis[name] ** 2} | {psnr(ours, cycles):.2f} | "
              f"{ours[..., :3].mean() / cycles[..., :3].mean():.4f} | "
              f"{result['timings'][name + '-kdtrace']:.1f} | {result['timings'][name + '-cycles']:.1f} |")
    images = pathlib.Path(args.images)
    images.mkdir(parents=True, exist_ok=True)
    for name in IMAGES:
        shutil.copyfile(out / f"{name}.png", images / f"cycles_{name}.png")
    print(f"\nwrote {', '.join(f'cycles_{n}.png' for n in IMAGES)} to {images}")


if __name__ == "__main__":
    main()
