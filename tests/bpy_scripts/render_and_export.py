"""F12 of the test scene through the installed add-on (local slaves, write_still to a 32-bit
OpenEXR), and the same scene's export kept in a file (core/frame/exported.py), for a test that
renders it through the core frame session without Blender."""
import importlib
import os

import bpy

from blender_setup import arguments, build_test_scene, install_extension, write_result

args, result_path = arguments()
addon = install_extension(args["zip"])
exported_module = importlib.import_module("bl_ext.user_default.kdtrace.core.frame.exported")
scene = build_test_scene(args["width"], args["height"])
scene.render.engine = "KDTRACE"
for name, value in args["settings"].items():
    setattr(scene.kdtrace, name, value)
scene.render.image_settings.file_format = "OPEN_EXR"
scene.render.image_settings.color_depth = "32"
scene.render.filepath = os.path.join(args["out"], "f12.exr")
bpy.ops.render.render(write_still=True)
exported, view, _ = addon.addon.export.export_instanced_view(bpy.context.evaluated_depsgraph_get())
exported_module.save_export(os.path.join(args["out"], "export.npz"), exported, view)
image = bpy.data.images.load(scene.render.filepath)
import numpy as np
pixels = np.array(image.pixels[:], np.float32).reshape(view.height, view.width, 4)[::-1]
np.save(os.path.join(args["out"], "f12.npy"), pixels)
write_result(result_path, {"last_render": addon.addon.session.current().last_render})
