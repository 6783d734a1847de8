"""Install a zip built with its wheels; report what Blender installed from them, and render with
a local slave."""
import os
import sys

import bpy

from blender_setup import arguments, build_test_scene, install_extension, write_result

args, result_path = arguments()
addon = install_extension(args["zip"])
wheel_dirs = [p for p in sys.path if "extensions" in p and p.endswith("site-packages")]
scene = build_test_scene(32, 24)
scene.render.engine = "KDTRACE"
scene.kdtrace.use_zeroconf = False
scene.kdtrace.local_slaves = 1
bpy.ops.render.render()
write_result(result_path, {"wheel_dirs": wheel_dirs,
                           "installed": sorted(os.listdir(wheel_dirs[0])) if wheel_dirs else [],
                           "rendered": bool(addon.addon.session.current().last_render)})
