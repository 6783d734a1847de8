"""Render with slaves that cannot work (dead, empty or mismatched hosts, a local slave on a
missing OpenCL device): the user must get a message in Blender's report, not a traceback."""
import bpy

from blender_setup import arguments, build_test_scene, install_extension, write_result

args, result_path = arguments()
addon = install_extension(args["zip"])
bpy.context.preferences.addons["bl_ext.user_default.kdtrace"].preferences.slave_device = \
    args.get("slave_device", "auto")
scene = build_test_scene(32, 24)
scene.render.engine = "KDTRACE"
scene.kdtrace.use_zeroconf = False
scene.kdtrace.local_slaves = args.get("local_slaves", 0)
for host, port in args.get("hosts", []):
    entry = scene.kdtrace.hosts.add()
    entry.host, entry.port = host, port
try:
    bpy.ops.render.render()
    outcome = "finished"
except RuntimeError as error:  # the operator turns the engine's error into this
    outcome = str(error)
write_result(result_path, {"outcome": outcome, "last_render": addon.addon.session.current().last_render})
