"""Render 5 frames: the sphere moves over frames 1-3, the camera over frames 3-5, and at frame 5
a shape key lifts a corner of the plane (its mesh changes). Record per frame whether a kd-tree
was rebuilt, whether the scene was uploaded and the bytes sent to each slave for it; then
render frames 2 and 5 again as stills to compare with the animation's frames."""
import bpy
import numpy as np

from blender_setup import arguments, build_test_scene, install_extension, write_result

args, result_path = arguments()
addon = install_extension(args["zip"])
scene = build_test_scene(args["width"], args["height"])
scene.render.engine = "KDTRACE"
scene.kdtrace.use_zeroconf = False
scene.kdtrace.local_slaves = 2
scene.kdtrace.tile_size = 32
scene.frame_start, scene.frame_end = 1, 5

sphere = bpy.data.objects["Sphere"]
for frame, x in ((1, -1.6), (3, -0.6)):
    sphere.location.x = x
    sphere.keyframe_insert("location", frame=frame)
for frame, x in ((3, 0.5), (5, 1.5)):
    scene.camera.location.x = x
    scene.camera.keyframe_insert("location", frame=frame)
plane = bpy.data.objects["Plane"]
plane.shape_key_add(name="Basis")
lift = plane.shape_key_add(name="Lift")
lift.data[0].co.z += 1.0
for frame, value in ((4, 0.0), (5, 1.0)):
    lift.value = value
    lift.keyframe_insert("value", frame=frame)

frames = []


def record(scene, *_):
    report = dict(addon.addon.session.current().last_render)
    frames.append({"frame": scene.frame_current, "tree_built": report.get("tree_built"),
                   "uploaded_to": report.get("uploaded_to"), "tiles": report.get("tiles_per_slave"),
                   "scene_bytes": report.get("scene_bytes"),
                   "hashes_reused": report.get("mesh_hashes_reused"),
                   "builds": addon.addon.session.current().trees.builds - builds_before})


bpy.app.handlers.render_post.append(record)
state = addon.addon.session.current()
builds_before = state.trees.builds
scene.render.image_settings.file_format = "PNG"
scene.render.filepath = args["out"] + "/anim_"
bpy.ops.render.render(animation=True)
builds = state.trees.builds - builds_before
bpy.app.handlers.render_post.remove(record)
stills = []

for frame in (2, 5):
    scene.frame_set(frame)
    scene.render.filepath = f"{args['out']}/still_{frame:04d}.png"
    bpy.ops.render.render(write_still=True)
    report = addon.addon.session.current().last_render
    stills.append((report["tree_built"], report["mesh_hashes_reused"]))
for name in [f"anim_{f:04d}" for f in range(1, 6)] + ["still_0002", "still_0005"]:
    image = bpy.data.images.load(f"{args['out']}/{name}.png")
    np.save(f"{args['out']}/{name}.npy", np.array(image.pixels[:], np.float32))
write_result(result_path, {"frames": frames, "builds": builds, "stills_built": stills})
