"""Install the extension, render the test scene with slaves found by zeroconf (local slaves off),
write the PNG; return what the add-on recorded about the render."""
import bpy

from blender_setup import arguments, build_test_scene, install_extension, write_result

args, result_path = arguments()
addon = install_extension(args["zip"])
scene = build_test_scene(args["width"], args["height"])
scene.render.engine = "KDTRACE"
scene.kdtrace.use_zeroconf = True
scene.kdtrace.discovery_seconds = args["discovery_seconds"]
scene.kdtrace.local_slaves = 0
scene.kdtrace.tile_size = args["tile_size"]
scene.kdtrace.samples_per_axis = args["samples_per_axis"]
scene.render.image_settings.file_format = "PNG"
scene.render.filepath = args["png"]
bpy.ops.render.render(write_still=True)
write_result(result_path, dict(addon.addon.session.current().last_render))
