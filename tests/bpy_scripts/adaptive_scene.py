"""bench/adaptive_samples.py's Blender side: the demo scene (blender_setup.build_demo_scene)
rendered by Cycles with adaptive sampling (its Noise Threshold, Max Samples, Min Samples 0 =
automatic, no denoising), with the Debug Sample Count pass; and the same scene exported for KD
Trace (core/frame/exported.py) with the same threshold and max samples. Writes
cycles-samples.npy (the pass: samples per pixel / the samples the render ran, the most any pixel
took; rows top first), cycles.npy
(Combined) and export.npz;
returns Cycles' render seconds."""
import importlib
import os
import time

import bpy
import numpy as np

from blender_setup import arguments, build_demo_scene, exr_passes, install_extension, write_result

args, result_path = arguments()
addon = install_extension(args["zip"])
exported_module = importlib.import_module("bl_ext.user_default.kdtrace.core.frame.exported")
scene = build_demo_scene()
scene.render.resolution_x, scene.render.resolution_y = args["width"], args["height"]
scene.render.resolution_percentage = 100
scene.view_settings.view_transform = "Standard"
scene.render.engine = "CYCLES"
cycles = scene.cycles
cycles.device, cycles.seed = "CPU", 1
cycles.samples = args["samples_per_axis"] ** 2
cycles.use_adaptive_sampling, cycles.adaptive_threshold = True, args["threshold"]
cycles.adaptive_min_samples = 0
cycles.use_denoising = False
bpy.context.view_layer.cycles.pass_debug_sample_count = True
settings = scene.render.image_settings
settings.media_type, settings.file_format = "MULTI_LAYER_IMAGE", "OPEN_EXR_MULTILAYER"
settings.color_depth = "32"
scene.render.filepath = os.path.join(args["out"], "cycles.exr")
started = time.perf_counter()
bpy.ops.render.render(write_still=True)
seconds = time.perf_counter() - started
passes = exr_passes(scene.render.filepath)
count = passes["Debug Sample Count"]
np.save(os.path.join(args["out"], "cycles-samples.npy"), next(iter(count.values())))
combined = passes["Combined"]
np.save(os.path.join(args["out"], "cycles.npy"), np.stack([combined[c] for c in "RGBA"], -1))

props = scene.kdtrace
props.samples_per_axis, props.adaptive = args["samples_per_axis"], True
props.adaptive_threshold = args["threshold"]
exported, view, _ = addon.addon.export.export_instanced_view(bpy.context.evaluated_depsgraph_get())
exported_module.save_export(os.path.join(args["out"], "export.npz"), exported, view)
write_result(result_path, {"cycles_seconds": seconds})
