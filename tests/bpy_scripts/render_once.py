"""Install the extension into a fresh Blender, apply the given KD Trace settings (none: the
defaults) and slave hosts, press F12 once; return what the add-on recorded about the render
(which slaves rendered, why local ones were started) and the local slaves running."""
import bpy

from blender_setup import arguments, build_test_scene, install_extension, write_result

args, result_path = arguments()
addon = install_extension(args["zip"])
scene = build_test_scene(args["width"], args["height"])
scene.render.engine = "KDTRACE"
for name, value in args.get("settings", {}).items():
    setattr(scene.kdtrace, name, value)
for host, port in args.get("hosts", []):
    entry = scene.kdtrace.hosts.add()
    entry.host, entry.port = host, port
bpy.ops.render.render()
state = addon.addon.session.current()
write_result(result_path, {**state.last_render, "local_slave_pids": state.local_slaves.pids()})
