"""Enable, render (which starts local slaves and the LAN browser), disable, reload: three times.
After each disable, nothing of the add-on may be left: classes, properties, panel entries,
threads or child processes. The kd-trees stay on disk: the second render reads the tree from
there (the third is given a cache folder that cannot be made, and builds)."""
import os
import threading

import bpy
import addon_utils  # Blender's module: importable once bpy is

from blender_setup import arguments, build_test_scene, install_extension, write_result

MODULE = "bl_ext.user_default.kdtrace"

args, result_path = arguments()
install_extension(args["zip"])


def leftovers(pids) -> list:
    found = []
    engines = bpy.types.RenderEngine.__subclasses__()
    if any(getattr(e, "bl_idname", "") == "KDTRACE" and e.is_registered for e in engines):
        found.append("render engine still registered")
    if hasattr(bpy.types.Scene, "kdtrace"):
        found.append("Scene.kdtrace still registered")
    if any("KDTRACE" in getattr(p, "COMPAT_ENGINES", ()) and p.is_registered
           for p in bpy.types.Panel.__subclasses__()):
        found.append("a Blender panel still lists KDTRACE")
    threads = [t.name for t in threading.enumerate() if t is not threading.main_thread()]
    if threads:
        found.append(f"threads left: {threads}")
    for pid in pids:
        try:
            os.kill(pid, 0)
            found.append(f"local slave {pid} still running")
        except ProcessLookupError:
            pass
    return found


rounds = []
for round_number in range(3):
    scene = build_test_scene(32, 24) if round_number == 0 else bpy.context.scene
    scene.render.engine = "KDTRACE"
    scene.kdtrace.use_zeroconf = True
    scene.kdtrace.discovery_seconds = 0.2
    scene.kdtrace.local_slaves = 1
    scene.kdtrace.use_local_slaves_always = True
    if round_number == 2:   # a cache folder that cannot be made: the render goes on without
        prefs = __import__(MODULE, fromlist=["addon"]).addon.properties.preferences(bpy.context)
        open("not-a-folder", "w").close()
        prefs.tree_cache_folder = str(os.path.abspath("not-a-folder"))
    bpy.ops.render.render()
    addon = __import__(MODULE, fromlist=["addon"]).addon
    pids = addon.session.current().local_slaves.pids()
    rendered = dict(addon.session.current().last_render)
    addon_utils.disable(MODULE, default_set=True)
    rounds.append({"rendered": bool(rendered), "local_slaves": len(pids), "leftovers": leftovers(pids),
                   "tree_sources": rendered.get("tree_sources"),
                   "tree_nodes": rendered.get("tree_stats", {}).get("nodes")})
    addon_utils.enable(MODULE, default_set=True)
    bpy.ops.script.reload()
# The preferences' button empties the kd-tree cache, on disk and in memory.
addon = __import__(MODULE, fromlist=["addon"]).addon
prefs = addon.properties.preferences(bpy.context)
prefs.tree_cache_folder = ""
before = addon.properties.tree_folder_usage(prefs)
cleared = bpy.ops.kdtrace.clear_tree_cache()
write_result(result_path, {"rounds": rounds, "cleared": sorted(cleared),
                           "usage": [list(before), list(addon.properties.tree_folder_usage(prefs))],
                           "in_memory": len(addon.session.current().trees._trees)})
