"""Image error against run time, and what kernel specialisation saves.

For two scenes (glass + mirrors with soft lights; a diffuse bunny under an area light and a soft
point light), render a converged reference, then sweep samples per pixel (1, 4, 16, 64 uniform),
adaptive sampling (several thresholds), and the bounce depth; report RMSE/PSNR against the
reference and wall time as a table, a JSON file and a PNG plot (PSNR against time, written with
numpy + zlib). Then render each scene with the specialised kernel and with the kernel that
compiles every feature (all optional arrays loaded) and report kernel time and scene bytes.

    .venv/bin/python bench/image_error.py [--size 160x120] [--out bench/out] [--reference-axis 16]
"""
from __future__ import annotations

import argparse
import json
import math
import pathlib
import struct
import sys
import time
import zlib

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from core.scene.features import full_geometry, scene_features, strip_geometry  # noqa: E402
from core.accel.kdtree import build_kdtree  # noqa: E402
from core.scene.model import (Camera, Geometry, Light, RenderSettings, Shading, View,  # noqa: E402
                        default_material_params)
from core.scene.scene import Scene  # noqa: E402
from slave.tracer import Tracer  # noqa: E402
from tests.meshes import grid_plane, load_bunny, look_at, merge, uv_sphere  # noqa: E402


def smooth_normals(vertices, triangles):
    """Area-weighted vertex normals at each corner (for the smooth spheres)."""
    corners = vertices[triangles].astype(np.float64)
    face = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    acc = np.zeros((len(vertices), 3))
    for k in range(3):
        np.add.at(acc, triangles[:, k], face)
    acc /= np.linalg.norm(acc, axis=1, keepdims=True)
    return acc[triangles].reshape(-1, 3)


def glass_scene():
    """A floor, a glass sphere (IOR 1.5), a mirror sphere, a diffuse sphere; area + soft sun."""
    parts = [grid_plane(12.0, 4, 0.0), uv_sphere(48, 24, 0.9, (-1.2, 0.2, 0.9)),
             uv_sphere(48, 24, 0.8, (1.0, 0.9, 0.8)), uv_sphere(32, 16, 0.5, (0.3, -1.0, 0.5))]
    vertices, triangles = merge(*parts)
    ids = np.concatenate([np.full(len(p[1]), i) for i, p in enumerate(parts)]).astype(np.uint16)
    normals = np.concatenate([smooth_normals(*p) if i else
                              np.tile([0, 0, 1.0], (3 * len(p[1]), 1)) for i, p in enumerate(parts)])
    params = default_material_params(4)
    params[1] = [0, 0.0, 1.0, 1.5, 0, 0, 0, 0.5, -1]       # glass
    params[2] = [1, 0.02, 0, 1.5, 0, 0, 0, 0.5, -1]        # mirror
    params[3] = [0, 0.4, 0, 1.5, 0, 0, 0, 0.5, -1]         # glossy plastic
    colours = np.array([[0.7, 0.7, 0.65, 1], [1, 1, 1, 1], [0.9, 0.9, 0.9, 1], [0.8, 0.2, 0.1, 1]],
                       np.float32)
    lights = [Light("AREA", (1, 1, 1), 400.0, (0.0, -2.0, 4.0), (0, 0.4, -1), shape="DISK",
                    size_u=1.5, size_v=1.5),
              Light("SUN", (1, 0.95, 0.9), 1.5, direction=(-0.4, 0.5, -1), radius=math.radians(5))]
    camera = Camera("PERSP", look_at((0.5, -6.5, 3.2), (0, 0, 0.7)), (0.5, 0.375), (0, 0), 0.1, 100)
    geometry = Geometry(vertices, triangles, ids, normals=normals)
    return geometry, camera, Shading(colours, lights, (0.2, 0.25, 0.3), params)


def bunny_scene():
    """The bunny on a floor under an area light and a soft point light (diffuse + soft shadows)."""
    bv, bt = load_bunny()
    bv = bv[:, [0, 2, 1]] * np.array([0.25, -0.25, 0.25], np.float32)
    bv[:, 2] -= bv[:, 2].min()
    parts = [grid_plane(12.0, 4, 0.0), (bv.astype(np.float32), bt[:, ::-1].copy())]
    vertices, triangles = merge(*parts)
    ids = np.concatenate([np.full(len(p[1]), i) for i, p in enumerate(parts)]).astype(np.uint16)
    colours = np.array([[0.7, 0.7, 0.7, 1], [0.85, 0.6, 0.4, 1]], np.float32)
    lights = [Light("AREA", (1, 1, 1), 500.0, (-1.5, -1.0, 3.5), (0.4, 0.2, -1), shape="RECTANGLE",
                    size_u=2.0, size_v=1.0),
              Light("POINT", (1, 0.9, 0.8), 300.0, (2.5, -2.0, 3.0), radius=0.4)]
    camera = Camera("PERSP", look_at((0.0, -6.0, 2.6), (0, 0, 1.0)), (0.45, 0.34), (0, 0), 0.1, 100)
    return Geometry(vertices, triangles, ids), camera, Shading(colours, lights, (0.05, 0.05, 0.06))


SCENES = {"glass_mirrors": glass_scene, "bunny_soft": bunny_scene}


def psnr(image, reference):
    mse = float(np.mean((np.clip(image, 0, 1) - np.clip(reference, 0, 1)) ** 2))
    return math.sqrt(mse), (float("inf") if mse == 0 else 10 * math.log10(1 / mse))


def timed_render(tracer, view, repeat=1):
    best, image = float("inf"), None
    for _ in range(repeat):
        started = time.perf_counter()
        image = tracer.render_tile(view, 0, 0, view.width, view.height)["combined"][..., :3]
        best = min(best, time.perf_counter() - started)
    return image, best, tracer.last_render["samples"] / (view.width * view.height)


# -- PNG plot with numpy + zlib ----------------------------------------------------------------
COLOURS = {"uniform": (31, 119, 180), "adaptive": (214, 39, 40), "bounces": (44, 160, 44)}
FONT = {  # 3x5 digits for axis labels
    "0": "111101101101111", "1": "010110010010111", "2": "111001111100111", "3": "111001111001111",
    "4": "101101111001001", "5": "111100111001111", "6": "111100111101111", "7": "111001001001001",
    "8": "111101111101111", "9": "111101111001111", ".": "000000000000010", "-": "000000111000000"}


def write_png(path, pixels):
    h, w, _ = pixels.shape
    raw = b"".join(b"\x00" + pixels[y].astype(np.uint8).tobytes() for y in range(h))

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b"")
    pathlib.Path(path).write_bytes(png)


def draw_text(canvas, x, y, text, scale=2):
    for i, ch in enumerate(text):
        bits = FONT.get(ch)
        if bits is None:
            continue
        for k, bit in enumerate(bits):
            if bit == "1":
                r, c = divmod(k, 3)
                y0, x0 = y + r * scale, x + (i * 4 + c) * scale
                canvas[y0:y0 + scale, x0:x0 + scale] = 0


def plot(path, panels):
    """One panel per scene: PSNR (y) against log10 time (x); blue uniform, red adaptive,
    green bounce sweep. Axis ticks are labelled with numbers (seconds, dB)."""
    pw, ph, margin = 420, 300, 50
    canvas = np.full((ph + 2 * margin, len(panels) * (pw + 2 * margin), 3), 255, np.uint8)
    for p, (name, rows) in enumerate(panels.items()):
        ox = p * (pw + 2 * margin) + margin
        times = np.array([r["seconds"] for r in rows])
        values = np.array([min(r["psnr"], 60) for r in rows])
        lx0, lx1 = math.floor(np.log10(times.min()) * 2) / 2, math.ceil(np.log10(times.max()) * 2) / 2
        y0, y1 = math.floor(values.min() / 5) * 5, math.ceil(values.max() / 5) * 5
        lx1, y1 = max(lx1, lx0 + 0.5), max(y1, y0 + 5)

        def to_px(t, v):
            return (ox + (np.log10(t) - lx0) / (lx1 - lx0) * pw,
                    margin + ph - (v - y0) / (y1 - y0) * ph)
        canvas[margin:margin + ph + 1, ox] = 0
        canvas[margin + ph, ox:ox + pw + 1] = 0
        for v in range(int(y0), int(y1) + 1, 5):
            _, yy = to_px(1.0, v)
            canvas[int(yy), ox:ox + pw] = 220
            draw_text(canvas, ox - 30, int(yy) - 5, f"{v}")
        for e in np.arange(lx0, lx1 + 1e-9, 0.5):
            xx, _ = to_px(10 ** e, y0)
            canvas[margin:margin + ph, int(xx)] = np.minimum(canvas[margin:margin + ph, int(xx)], 220)
            draw_text(canvas, int(xx) - 10, margin + ph + 8, f"{10 ** e:.2g}")
        for series, colour in COLOURS.items():
            pts = sorted((r["seconds"], min(r["psnr"], 60)) for r in rows if r["series"] == series)
            pts = [to_px(t, v) for t, v in pts]
            for (xa, ya), (xb, yb) in zip(pts, pts[1:]):
                n = int(max(abs(xb - xa), abs(yb - ya))) + 1
                xs, ys = np.linspace(xa, xb, n).astype(int), np.linspace(ya, yb, n).astype(int)
                for d in (-1, 0, 1):
                    canvas[np.clip(ys + d, 0, canvas.shape[0] - 1), xs] = colour
            for x, y in pts:
                canvas[int(y) - 3:int(y) + 4, int(x) - 3:int(x) + 4] = colour
    write_png(path, canvas)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    parser.add_argument("--reference-axis", type=int, default=16, help="reference: N x N samples")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tracer = Tracer()
    print(f"device: {tracer.device_info['name']}, image {width}x{height}")
    results, specialisation = {}, {}
    for name, build in SCENES.items():
        geometry, camera, shading = build()
        tree = build_kdtree(geometry.vertices, geometry.triangles)
        tracer.load(Scene.from_parts(geometry, tree))

        def view(**settings):
            return View(camera, width, height, shading, settings=RenderSettings(**settings))
        started = time.perf_counter()
        reference, _, _ = timed_render(tracer, view(samples_per_axis=args.reference_axis,
                                                    light_samples_per_axis=2, max_bounces=8))
        print(f"{name}: reference {args.reference_axis ** 2} spp x 4 light samples in "
              f"{time.perf_counter() - started:.1f} s")
        np.save(out / f"{name}-reference.npy", reference)
        rows = []

        def measure(series, label, **settings):
            timed_render(tracer, view(**settings))            # compile / warm up
            image, seconds, spp = timed_render(tracer, view(**settings), repeat=3)
            rmse, value = psnr(image, reference)
            rows.append({"series": series, "config": label, "seconds": seconds, "rmse": rmse,
                         "psnr": value, "mean_spp": spp})
            print(f"  {series:9s} {label:28s} {seconds:7.3f} s  {spp:6.2f} spp  RMSE {rmse:.5f}  "
                  f"PSNR {value:6.2f} dB")
        for n in (1, 2, 4, 8):
            measure("uniform", f"{n * n} spp", samples_per_axis=n, light_samples_per_axis=1)
        for n, threshold in ((4, 0.02), (8, 0.03), (8, 0.02), (8, 0.017), (8, 0.015), (8, 0.0125),
                             (8, 0.01), (16, 0.015)):
            measure("adaptive", f"<= {n * n} spp, threshold {threshold}", samples_per_axis=n,
                    adaptive=True, adaptive_threshold=threshold, adaptive_min_samples=4,
                    light_samples_per_axis=1)
        for bounces in (0, 1, 2, 4, 8):
            measure("bounces", f"16 spp, {bounces} bounces", samples_per_axis=4,
                    light_samples_per_axis=1, max_bounces=bounces)
        uniform16 = next(r for r in rows if r["series"] == "uniform" and r["config"] == "16 spp")
        good = [r for r in rows if r["series"] == "adaptive" and r["psnr"] >= uniform16["psnr"]]
        best = min(good, key=lambda r: r["seconds"]) if good else None
        results[name] = {"rows": rows, "uniform16": uniform16, "best_adaptive": best,
                         "time_ratio": best["seconds"] / uniform16["seconds"] if best else None}
        print(f"  adaptive reaching uniform-16 PSNR ({uniform16['psnr']:.2f} dB): "
              + (f"{best['config']} in {best['seconds']:.3f} s = "
                 f"{100 * best['seconds'] / uniform16['seconds']:.0f} % of {uniform16['seconds']:.3f} s"
                 if best else "none"))

        # Specialisation: the kernel compiled for this scene vs one with every feature.
        stripped = strip_geometry(geometry, scene_features(geometry, view()))
        full = full_geometry(geometry)
        entry = {"features": sorted(scene_features(stripped, view(samples_per_axis=4))),
                 "scene_bytes_specialised": stripped.nbytes, "scene_bytes_full": full.nbytes}
        for label, geo, special in (("specialised", stripped, True), ("full", full, False)):
            tracer.specialise = special
            tracer.load(Scene.from_parts(geo, tree))
            timed_render(tracer, view(samples_per_axis=4, light_samples_per_axis=1))
            _, seconds, _ = timed_render(tracer, view(samples_per_axis=4, light_samples_per_axis=1),
                                         repeat=3)
            entry[f"kernel_seconds_{label}"] = seconds
        tracer.specialise = True
        specialisation[name] = entry
        print(f"  specialisation: features {entry['features']}; kernel "
              f"{entry['kernel_seconds_specialised']:.3f} s vs {entry['kernel_seconds_full']:.3f} s "
              f"(all features); scene {entry['scene_bytes_specialised']:,} vs "
              f"{entry['scene_bytes_full']:,} bytes")
    plot(out / "image_error.png", {name: r["rows"] for name, r in results.items()})
    (out / "image_error.json").write_text(json.dumps(
        {"device": tracer.device_info, "size": [width, height], "scenes": results,
         "specialisation": specialisation}, indent=1))
    print(f"wrote {out / 'image_error.png'} and {out / 'image_error.json'}")


if __name__ == "__main__":
    main()
