"""The LAN browser follows the render engine (addon/browsing.py): off while another engine is
selected, on while KD Trace is, off again when discovery is turned off. Returns what it saw
while on, before any F12. (In the UI a message-bus subscription calls update_browsing when the
engine changes; a background Blender runs none, so this calls it as the subscription would.)"""
import time

import bpy

from blender_setup import arguments, install_extension, write_result

args, result_path = arguments()
addon = install_extension(args["zip"]).addon
state, scene = addon.session.current(), bpy.context.scene
steps = {}
scene.render.engine = "CYCLES"
addon.browsing.update_browsing(scene)
steps["cycles"] = state.browsing
scene.render.engine = "KDTRACE"
addon.browsing.update_browsing(scene)
steps["kdtrace"] = state.browsing
deadline = time.monotonic() + args["wait_seconds"]
while not any(s.name == args["slave"] for s in state.discovered_slaves()) and time.monotonic() < deadline:
    time.sleep(0.05)
seen = [s.name for s in state.discovered_slaves()]
scene.kdtrace.use_zeroconf = False
addon.browsing.update_browsing(scene)
steps["discovery off"] = state.browsing
write_result(result_path, {"steps": steps, "seen": seen})
