"""Render the test scene with Cycles and with KD Trace (through the installed add-on and local
slaves) to multilayer EXR; return both Depth passes and the Normal passes."""
import bpy
import numpy as np

from blender_setup import (arguments, build_test_scene, cycles_at_pixel_centres, exr_passes,
                           install_extension, write_result)

args, result_path = arguments()
install_extension(args["zip"])
scene = build_test_scene(args["width"], args["height"])
camera = scene.camera.data
camera.shift_x, camera.shift_y = args.get("shift", (0.0, 0.0))
camera.type = args.get("camera_type", "PERSP")
camera.sensor_fit = args.get("sensor_fit", "AUTO")
camera.ortho_scale = 9.0
view_layer = bpy.context.view_layer
view_layer.use_pass_z = True
view_layer.use_pass_normal = True
settings = scene.render.image_settings
settings.media_type = "MULTI_LAYER_IMAGE"
settings.file_format = "OPEN_EXR_MULTILAYER"
settings.color_depth = "32"

# Cycles, one sample per pixel at the pixel centre (box filter of tiny width).
cycles_at_pixel_centres(scene)
scene.render.filepath = args["out"] + "/cycles.exr"
bpy.ops.render.render(write_still=True)

scene.render.engine = "KDTRACE"
scene.kdtrace.use_zeroconf = False
scene.kdtrace.local_slaves = 2
scene.kdtrace.tile_size = 32
scene.render.filepath = args["out"] + "/kdtrace.exr"
bpy.ops.render.render(write_still=True)

cycles, ours = exr_passes(args["out"] + "/cycles.exr"), exr_passes(args["out"] + "/kdtrace.exr")
np.save(args["out"] + "/cycles_depth.npy", cycles["Depth"]["Z"])
np.save(args["out"] + "/kdtrace_depth.npy", ours["Depth"]["Z"])
np.save(args["out"] + "/cycles_normal.npy", np.stack([cycles["Normal"][c] for c in "XYZ"], -1))
np.save(args["out"] + "/kdtrace_normal.npy", np.stack([ours["Normal"][c] for c in "XYZ"], -1))
write_result(result_path, {"passes": sorted(ours)})
