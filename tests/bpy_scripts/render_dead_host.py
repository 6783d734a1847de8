"""Render with only a dead or empty host listed: the user must get a message, not a traceback."""
import bpy

from blender_setup import arguments, build_test_scene, install_extension, write_result

args, result_path = arguments()
addon = install_extension(args["zip"])
scene = build_test_scene(32, 24)
scene.render.engine = "KDTRACE"
scene.kdtrace.use_zeroconf = False
scene.kdtrace.local_slaves = 0
for host, port in args["hosts"]:
    entry = scene.kdtrace.hosts.add()
    entry.host, entry.port = host, port
try:
    bpy.ops.render.render()
    outcome = "finished"
except RuntimeError as error:  # the operator turns the engine's error into this
    outcome = str(error)
write_result(result_path, {"outcome": outcome, "last_render": addon.addon.session.current().last_render})
