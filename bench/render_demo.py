"""The main job: a real render through the installed add-on, headless, with local slaves.

Builds the extension zip, installs it into a private Blender user folder, builds a demo scene
(the Stanford dragon on a ground plane with a sphere and a cube), renders it with KD Trace on
local slaves (PoCL CPU device unless a GPU is found), writes the PNG and prints timings.

    .venv/bin/python bench/render_demo.py [--out bench/out/demo.png] [--width 960 --height 540] [--slaves 2] [--samples 4]

The demo renders at most 4 x 4 samples per pixel (adaptive): the panel's defaults are Cycles'
final-render ones (up to 64 x 64), minutes on two CPU cores instead of seconds. As with every
F12 at the panel's defaults, the master denoises the finished image (Open Image Denoise, as
Cycles; docs/denoising.md).

Outputs go under bench/out/ by default, which git ignores and the extension zips leave out.
"""
import argparse
import os
import pathlib
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
DEFAULT_OUT = ROOT / "bench" / "out" / "demo.png"
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "bpy_scripts"))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(DEFAULT_OUT), help="PNG to write (default: %(default)s)")
    parser.add_argument("--width", type=int, default=960)
    parser.add_argument("--height", type=int, default=540)
    parser.add_argument("--slaves", type=int, default=2, help="local slaves to start")
    parser.add_argument("--tile-size", type=int, default=64)
    parser.add_argument("--samples", type=int, default=4,
                        help="Max Samples per axis (N x N per pixel, adaptive; default %(default)s)")
    parser.add_argument("--slave-map", help="also write this PNG: the render beside its Slave "
                        "pass (each tile tinted with the colour of the slave that rendered it)")
    args = parser.parse_args()

    work = pathlib.Path(tempfile.mkdtemp(prefix="kdtrace-demo-"))
    # Blender reads its user folder once, when bpy is imported.
    os.environ["BLENDER_USER_RESOURCES"] = str(work / "blender-user")
    from tests.blender import build_extension
    zip_path = build_extension(work / "dist")

    import bpy
    from blender_setup import build_demo_scene, install_extension
    addon = install_extension(str(zip_path))

    scene = build_demo_scene()
    scene.render.engine = "KDTRACE"
    scene.render.resolution_x, scene.render.resolution_y = args.width, args.height
    scene.render.resolution_percentage = 100
    scene.kdtrace.use_zeroconf = False
    scene.kdtrace.local_slaves = args.slaves
    scene.kdtrace.tile_size = args.tile_size
    scene.kdtrace.samples_per_axis = args.samples
    scene.render.image_settings.file_format = "PNG"
    out = pathlib.Path(args.out).resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    scene.render.filepath = str(out)

    started = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    wall = time.perf_counter() - started
    if args.slave_map:
        write_slave_map(scene, work, args.out, args.slave_map)
    report = addon.addon.session.current().last_render
    if not report:
        sys.exit("the render failed: see the messages above")
    stats = report["tree_stats"]
    print(f"\nKD Trace demo: {report['triangles']:,} triangles, {args.width}x{args.height}, "
          f"{args.slaves} local slave(s)")
    print(f"  export  {report['export_seconds']:7.2f} s")
    print(f"  kd-tree {report['tree_seconds']:7.2f} s  ({stats['nodes']:,} nodes, "
          f"{stats['bytes'] / 2**20:.1f} MiB)")
    print(f"  render  {report['render_seconds']:7.2f} s  (slave start-up included on the first render)")
    if report.get("denoised"):
        print(f"  of which denoising {report['denoise_seconds']:7.2f} s  ({report['denoise_note']})")
    print(f"  total   {wall:7.2f} s")
    from kdtrace.core.net.slave_colors import ansi_swatch, slave_color
    for name, count in sorted(report["tiles_per_slave"].items()):
        hex_color = "#" + "".join(f"{round(c * 255):02x}" for c in slave_color(name))
        print(f"  {ansi_swatch(name)} {hex_color} tiles from {name}: {count}")
    print(f"  wrote {scene.render.filepath}" + (f" and {args.slave_map}" if args.slave_map else ""))


def write_slave_map(scene, work, render_png, out_png):
    """The render (as displayed) beside the same image tinted by the Slave pass."""
    import bpy
    import numpy as np
    from blender_setup import exr_passes
    settings = scene.render.image_settings
    settings.media_type, settings.file_format = "MULTI_LAYER_IMAGE", "OPEN_EXR_MULTILAYER"
    exr = str(work / "passes.exr")
    bpy.data.images["Render Result"].save_render(filepath=exr)
    slave = np.stack([exr_passes(exr)["Slave"][c] for c in "RGB"], -1)
    shown = bpy.data.images.load(str(pathlib.Path(render_png).resolve()))
    width, height = shown.size
    pixels = np.array(shown.pixels[:], np.float32).reshape(height, width, 4)[::-1, :, :3]
    tinted = 0.45 * pixels + 0.55 * slave
    both = np.concatenate([pixels, np.ones((height, 8, 3), np.float32), tinted], axis=1)
    image = bpy.data.images.new("slave-map", both.shape[1], height)
    rgba = np.concatenate([both, np.ones((height, both.shape[1], 1), np.float32)], -1)
    image.pixels.foreach_set(rgba[::-1].ravel())
    image.filepath_raw, image.file_format = str(pathlib.Path(out_png).resolve()), "PNG"
    image.save()


if __name__ == "__main__":
    main()
