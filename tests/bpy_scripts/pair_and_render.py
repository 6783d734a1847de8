"""A new user's first render on a slave of another machine, step by step as the user takes
them (README, "First run"): select KD Trace; the Slaves panel lists the slave found on the LAN
with its ID, beside Pair; click Pair and type the code the slave printed; press F12. Returns
what the panel showed, what pairing reported and what the render used. (A background Blender
runs no message bus: this calls update_browsing as the engine's subscription would, and the
operator as its button would after the code was typed.)"""
import time

import bpy

from blender_setup import arguments, build_test_scene, install_extension, write_result

args, result_path = arguments()
addon = install_extension(args["zip"]).addon
state = addon.session.current()
scene = build_test_scene(args["width"], args["height"])

# Step 1: KD Trace as the render engine (the LAN browser starts, this computer's ID is made).
scene.render.engine = "KDTRACE"
addon.browsing.update_browsing(scene)
deadline = time.monotonic() + 20
while time.monotonic() < deadline and not any(s.name == args["slave"] for s in state.discovered_slaves()):
    time.sleep(0.05)
found = next(s for s in state.discovered_slaves() if s.name == args["slave"])
slave_id = found.properties["id"]
panel = f"{found.name}  {found.host}:{found.port}  ID {slave_id[:4]}-{slave_id[4:8]}-{slave_id[8:12]}-{slave_id[12:16]}"

# Step 2: Pair, with the code from the slave's log.
prefs = bpy.context.preferences.addons[addon.properties.KDTracePreferences.bl_idname].preferences
wrong = None
if args.get("try_wrong_code"):   # a typo first: the operator reports the error (bpy raises it)
    try:
        wrong = bpy.ops.kdtrace.slave_pair("EXEC_DEFAULT", host=found.host, port=found.port,
                                           slave_id=slave_id, name=found.name, code="AAAA-AAAA")
    except RuntimeError as error:
        wrong = {"CANCELLED"} if "wrong pairing code" in str(error) else {str(error)}
approved_after_wrong = [s.slave_id for s in prefs.approved_slaves]
paired = bpy.ops.kdtrace.slave_pair("EXEC_DEFAULT", host=found.host, port=found.port,
                                    slave_id=slave_id, name=found.name, code=args["code"])

# Step 3: F12.
bpy.ops.render.render()
write_result(result_path, {
    "panel": panel, "master_id": state.identity_if_loaded().id,
    "wrong_code": sorted(wrong) if wrong else None, "approved_after_wrong": approved_after_wrong,
    "paired": sorted(paired), "approved": [s.slave_id for s in prefs.approved_slaves],
    "tiles_per_slave": state.last_render.get("tiles_per_slave", {}),
    "local_slave_pids": state.local_slaves.pids(), "local_reason": state.local_reason})
