"""Build a shading test scene, export it with the add-on's exporter (all optional arrays kept)
and, when asked, render it with Cycles (direct light only). Writes scene.npz (geometry arrays),
view.json, warnings in the result, and cycles.npy (rows top first)."""
import json
import math

import bpy
import numpy as np

from blender_setup import arguments, install_extension, write_result

args, result_path = arguments()
install_extension(args["zip"])
import importlib
export = importlib.import_module("bl_ext.user_default.kdtrace.addon.export")

scene = bpy.context.scene
scene.render.resolution_x, scene.render.resolution_y = args["width"], args["height"]
scene.render.resolution_percentage = 100
world = bpy.data.worlds.new("world")
world.use_nodes = True
world.node_tree.nodes["Background"].inputs["Color"].default_value = (*args.get("world", (0, 0, 0)), 1)
scene.world = world


def material(name, kind="DIFFUSE", color=(0.8, 0.8, 0.8), **inputs):
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    nodes = m.node_tree.nodes
    out = nodes["Material Output"]
    if kind == "DIFFUSE":
        node = nodes.new("ShaderNodeBsdfDiffuse")
        node.inputs["Color"].default_value = (*color, 1)
        m.node_tree.links.new(node.outputs["BSDF"], out.inputs["Surface"])
    elif kind == "PRINCIPLED":
        node = nodes["Principled BSDF"]
        node.inputs["Base Color"].default_value = (*color, 1)
        for key, value in inputs.items():
            node.inputs[key].default_value = value
    elif kind == "TOON":      # something KD Trace cannot map
        node = nodes.new("ShaderNodeBsdfToon")
        m.node_tree.links.new(node.outputs["BSDF"], out.inputs["Surface"])
    return m


def add(obj_op, mat, smooth=False, **kw):
    obj_op(**kw)
    obj = bpy.context.object
    obj.data.materials.append(mat)
    if smooth:
        bpy.ops.object.shade_smooth()
    return obj


def light(name, kind, location, rotation=(0, 0, 0), **props):
    data = bpy.data.lights.new(name, kind)
    for key, value in props.items():
        setattr(data, key, value)
    if hasattr(data, "use_soft_falloff"):
        data.use_soft_falloff = False
    obj = bpy.data.objects.new(name, data)
    obj.location = location
    obj.rotation_euler = [math.radians(r) for r in rotation]
    scene.collection.objects.link(obj)


camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
camera.location, camera.rotation_euler = (0.0, -7.0, 4.0), (math.radians(60), 0, 0)
scene.collection.objects.link(camera)
scene.camera = camera

if args["scene"] == "lights":
    grey = material("grey", color=(0.8, 0.8, 0.8))
    add(bpy.ops.mesh.primitive_plane_add, grey, size=14.0)
    add(bpy.ops.mesh.primitive_uv_sphere_add, material("red", color=(0.8, 0.3, 0.2)),
        smooth=True, radius=0.9, location=(-1.2, 0.5, 0.9), segments=48, ring_count=24)
    add(bpy.ops.mesh.primitive_cube_add, material("blue", color=(0.2, 0.4, 0.8)), size=1.4,
        location=(1.5, 0.8, 0.7))
    light("point", "POINT", (2.5, -2.0, 3.0), energy=300.0, shadow_soft_size=0.15)
    light("sun", "SUN", (0, 0, 5), (35, 10, 30), energy=1.5, angle=math.radians(4))
    light("spot", "SPOT", (-2.5, -1.5, 4.0), (30, -25, 0), energy=600.0, shadow_soft_size=0.1,
          spot_size=math.radians(60), spot_blend=0.3)
    light("area", "AREA", (0.0, 2.5, 3.5), (-35, 0, 0), energy=250.0, shape="DISK", size=1.0)
elif args["scene"] == "materials":
    image = bpy.data.images.new("checker", 8, 8)
    checker = (np.indices((8, 8)).sum(0) % 2).astype(np.float32)
    pixels = np.stack([checker, 0.5 * np.ones_like(checker), 1 - checker, np.ones_like(checker)], -1)
    image.pixels.foreach_set(pixels.ravel())
    textured = material("textured", "PRINCIPLED", Roughness=0.8)
    tex = textured.node_tree.nodes.new("ShaderNodeTexImage")
    tex.image = image
    textured.node_tree.links.new(tex.outputs["Color"],
                                 textured.node_tree.nodes["Principled BSDF"].inputs["Base Color"])
    add(bpy.ops.mesh.primitive_plane_add, textured, size=10.0)
    add(bpy.ops.mesh.primitive_uv_sphere_add, material("glass", "PRINCIPLED", (1, 1, 1),
        **{"Transmission Weight": 1.0, "IOR": 1.5, "Roughness": 0.0}), smooth=True,
        radius=0.8, location=(-1.5, 0, 0.8))
    add(bpy.ops.mesh.primitive_uv_sphere_add, material("mirror", "PRINCIPLED", (0.9, 0.9, 0.9),
        Metallic=1.0, Roughness=0.02), smooth=True, radius=0.8, location=(0.3, 0.8, 0.8))
    add(bpy.ops.mesh.primitive_cube_add, material("lamp", "PRINCIPLED", (0, 0, 0),
        **{"Emission Color": (1, 0.8, 0.5, 1), "Emission Strength": 5.0}), size=0.5,
        location=(1.8, -0.5, 0.25))
    add(bpy.ops.mesh.primitive_cube_add, material("toon", "TOON"), size=0.6, location=(2.2, 1.5, 0.3))
    add(bpy.ops.mesh.primitive_plane_add, material("cutout", "PRINCIPLED", (0.2, 0.8, 0.2),
        Alpha=0.0), size=1.0, location=(0.0, -1.5, 0.6), rotation=(math.radians(90), 0, 0))
    light("sun", "SUN", (0, 0, 5), (35, 10, 30), energy=3.0, angle=math.radians(2))
    light("point", "POINT", (2.0, -2.0, 3.0), energy=300.0, shadow_soft_size=0.2)

elif args["scene"] == "bad":
    from blender_setup import mesh_object
    mesh_object("good", [[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    # Two collinear (zero-area) faces beside a good one.
    mesh_object("degenerate", [[0, 0, 1], [1, 0, 1], [0, 1, 1], [2, 0, 1], [3, 0, 1]],
                [[0, 1, 2], [0, 1, 3], [1, 3, 4]])
    bpy.data.objects["degenerate"].data.shade_smooth()    # corner normals beside flat ones
    mesh_object("empty", np.zeros((0, 3)), np.zeros((0, 3), np.int32))
    light("sun", "SUN", (0, 0, 5), energy=1.0)
    bpy.context.view_layer.update()
    geometry, view, info = export.export_view(bpy.context.evaluated_depsgraph_get())
    triangles = geometry.triangle_count
    arrays = {"vertices": geometry.vertices.tolist(), "triangles": geometry.triangles.tolist(),
              "normals": None if geometry.normals is None else geometry.normals.tolist()}
    bad = bpy.data.objects["good"].data
    bad.vertices[1].co = (float("nan"), 0.0, 0.0)
    bad.update()
    bpy.context.view_layer.update()
    nan_geometry, _, nan_info = export.export_view(bpy.context.evaluated_depsgraph_get())
    write_result(result_path, {"warnings": info["warnings"], "triangles": triangles,
                               "arrays": arrays, "nan_warnings": nan_info["warnings"],
                               "nan_triangles": nan_geometry.triangle_count})
    raise SystemExit(0)

bpy.context.view_layer.update()
depsgraph = bpy.context.evaluated_depsgraph_get()
geometry, view, info = export.export_view(depsgraph)
np.savez(args["out"] + "/scene.npz", **geometry.arrays())
with open(args["out"] + "/view.json", "w") as f:
    json.dump(view.to_dict(), f)

if args.get("cycles_samples"):
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = args["cycles_samples"]
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = 0
    scene.cycles.seed = 1
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = args["out"] + "/cycles.exr"
    bpy.ops.render.render(write_still=True)
    image = bpy.data.images.load(args["out"] + "/cycles.exr")
    w, h = args["width"], args["height"]
    pixels = np.array(image.pixels[:], np.float32).reshape(h, w, 4)[::-1]
    np.save(args["out"] + "/cycles.npy", pixels)
write_result(result_path, {"warnings": info["warnings"]})
