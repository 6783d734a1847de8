"""The Stanford dragon scene of bench/dragon.py (a sun, a camera framing the dragon, size x size
pixels) exported by the installed add-on (the fastest of `repeat` exports) and kept in a file
(core/frame/exported.py), so that the benchmark runs everything after the export without
Blender. Returns the export's seconds."""
import importlib
import time

import bpy
import numpy as np

from blender_setup import arguments, install_extension, mesh_object, write_result
from tests.meshes import load_dragon

args, result_path = arguments()
addon = install_extension(args["zip"])
exported_module = importlib.import_module("bl_ext.user_default.kdtrace.core.frame.exported")
vertices, triangles = load_dragon()
vertices = vertices[:, [0, 2, 1]] * np.array([1, -1, 1], np.float32)  # z up
mesh_object("dragon", vertices, triangles)
scene = bpy.context.scene
# Frame the dragon: look at its centre from the front, slightly from above.
centre = (vertices.min(0) + vertices.max(0)) / 2
camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
camera.location = centre + np.array([0.0, -0.24, 0.05])
camera.rotation_euler = (np.pi / 2 - 0.2, 0.0, 0.0)
camera.data.lens = 35
scene.collection.objects.link(camera)
scene.camera = camera
sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
sun.rotation_euler = (0.6, 0.2, 0.3)
scene.collection.objects.link(sun)
scene.render.resolution_x = scene.render.resolution_y = args["size"]
scene.render.resolution_percentage = 100
depsgraph = bpy.context.evaluated_depsgraph_get()
seconds = []
for _ in range(args["repeat"]):
    started = time.perf_counter()
    exported, view, _ = addon.addon.export.export_instanced_view(depsgraph)
    seconds.append(time.perf_counter() - started)
exported_module.save_export(args["out"], exported, view)
write_result(result_path, {"export_seconds": min(seconds)})
