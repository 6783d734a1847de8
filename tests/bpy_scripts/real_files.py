"""Real files nobody on this project made (tests/real_files.md: where each comes from, its
licence), opened or imported as a user would (glTF 2.0 and OBJ through Blender's importers, old
.blend files through File > Open) and rendered by Cycles and by KD Trace (the installed add-on,
local slaves) at matched settings. A file without a camera gets one that frames its meshes, one
without lights a sun and a grey world, as a user would add them. Writes <name>-cycles.npy and
<name>-kdtrace.npy (Combined, rows top first); returns each file's export warnings and render
seconds."""
import json
import math
import os
import time

import bpy
import numpy as np

from blender_setup import arguments, install_extension, write_result

args, result_path = arguments()
install_extension(args["zip"])
import importlib
export = importlib.import_module("bl_ext.user_default.kdtrace.addon.export")
OUT = args["out"]


def clear():
    for collection in (bpy.data.objects, bpy.data.meshes, bpy.data.materials, bpy.data.lights,
                       bpy.data.cameras, bpy.data.worlds, bpy.data.images, bpy.data.node_groups):
        for item in list(collection):
            collection.remove(item)


def load(path):
    if path.endswith(".blend"):
        bpy.ops.wm.open_mainfile(filepath=path, load_ui=False)
        return
    clear()
    if path.endswith((".gltf", ".glb")):
        bpy.ops.import_scene.gltf(filepath=path)
    elif path.endswith(".obj"):
        bpy.ops.wm.obj_import(filepath=path)
    else:
        raise ValueError(path)


def frame_meshes(scene):
    """A camera that sees every visible mesh from the front, a little from above and the side."""
    from mathutils import Vector
    corners = [obj.matrix_world @ Vector(c) for obj in scene.objects
               if obj.type == "MESH" and obj.visible_get() for c in obj.bound_box]
    lo = Vector([min(c[i] for c in corners) for i in range(3)])
    hi = Vector([max(c[i] for c in corners) for i in range(3)])
    centre, radius = (lo + hi) / 2, max((hi - lo).length / 2, 1e-3)
    data = bpy.data.cameras.new("framing camera")
    data.lens = 35
    camera = bpy.data.objects.new("framing camera", data)
    direction = Vector((0.6, -1.0, 0.5)).normalized()
    camera.location = centre + direction * radius * 2.6
    camera.rotation_euler = (-direction).to_track_quat("-Z", "Y").to_euler()
    data.clip_start, data.clip_end = radius * 0.01, radius * 100
    scene.collection.objects.link(camera)
    scene.camera = camera


def light_if_dark(scene):
    if not any(obj.type == "LIGHT" for obj in scene.objects):
        sun = bpy.data.objects.new("added sun", bpy.data.lights.new("added sun", "SUN"))
        sun.data.energy = 3.0
        sun.rotation_euler = (math.radians(40), math.radians(15), math.radians(30))
        scene.collection.objects.link(sun)
    if scene.world is None:
        world = bpy.data.worlds.new("added world")
        world.use_nodes = True
        world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.4, 0.42, 0.45, 1)
        scene.world = world


def read_exr(path, width, height):
    image = bpy.data.images.load(path)
    pixels = np.array(image.pixels[:], np.float32).reshape(height, width, 4)[::-1]
    bpy.data.images.remove(image)
    return pixels


width, height, samples = args["width"], args["height"], args["samples_per_axis"]
warnings, timings = {}, {}
for name, path in args["files"].items():
    load(path)
    scene = bpy.context.scene
    if scene.camera is None:
        frame_meshes(scene)
    light_if_dark(scene)
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.use_border = False
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.render.film_transparent = False
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    _, _, info = export.export_view(bpy.context.evaluated_depsgraph_get())
    warnings[name] = info["warnings"]

    scene.render.engine = "CYCLES"
    cycles = scene.cycles
    cycles.device = "CPU"
    cycles.samples = samples ** 2
    cycles.use_adaptive_sampling = False
    cycles.use_denoising = False
    cycles.pixel_filter_type = args["kdtrace"]["pixel_filter"]     # Cycles' default, as ours
    cycles.filter_width = args["kdtrace"]["filter_width"]
    cycles.seed = 1
    for key, value in args["cycles"].items():
        setattr(cycles, key, value)
    started = time.perf_counter()
    scene.render.filepath = f"{OUT}/{name}-cycles.exr"
    bpy.ops.render.render(write_still=True)
    timings[f"{name}-cycles"] = time.perf_counter() - started
    np.save(f"{OUT}/{name}-cycles.npy", read_exr(scene.render.filepath, width, height))

    scene.render.engine = "KDTRACE"
    props = scene.kdtrace
    props.use_zeroconf, props.local_slaves, props.tile_size = False, 2, 32
    props.samples_per_axis, props.adaptive = samples, False
    props.use_denoising = False         # as Cycles here
    for key, value in args["kdtrace"].items():
        setattr(props, key, value)
    started = time.perf_counter()
    scene.render.filepath = f"{OUT}/{name}-kdtrace.exr"
    bpy.ops.render.render(write_still=True)
    timings[f"{name}-kdtrace"] = time.perf_counter() - started
    np.save(f"{OUT}/{name}-kdtrace.npy", read_exr(scene.render.filepath, width, height))
write_result(result_path, {"warnings": warnings, "timings": timings})
