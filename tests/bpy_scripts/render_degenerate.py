"""F12 (with write_still, as `blender -b -f` renders) on scenes with odd input that Blender holds
without complaint: an object scaled to 0 on one axis and on all axes, a NaN transform, a mesh
without faces, an empty mesh, a text object, a curve and a metaball, a missing image, a missing
linked library, and lights that are flattened or not finite. Then a render that raises inside
the frame (after export, with tiles arriving), and a normal render after it: Blender must
report the error and live on. Returns per case: the operator's outcome, the export's warnings,
the image's mean colour and whether the still was written."""
import math
import os

import bpy
import numpy as np

from blender_setup import arguments, install_extension, write_result

args, result_path = arguments()
addon = install_extension(args["zip"])
render_module = addon.addon.render
OUT = args["out"]


def clear():
    for collection in (bpy.data.objects, bpy.data.meshes, bpy.data.materials, bpy.data.lights,
                       bpy.data.cameras, bpy.data.images, bpy.data.curves, bpy.data.metaballs):
        for item in list(collection):
            collection.remove(item)


def base_scene():
    """A floor, a unit cube, a camera and a point light; KD Trace at one sample, one local slave."""
    clear()
    scene = bpy.context.scene
    bpy.ops.mesh.primitive_plane_add(size=10.0)
    bpy.context.object.name = "floor"
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0.0, 0.0, 0.5))
    bpy.context.object.name = "cube"
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    camera.location = (0.0, -6.0, 3.0)
    camera.rotation_euler = (math.radians(65), 0.0, 0.0)
    scene.collection.objects.link(camera)
    scene.camera = camera
    lamp = bpy.data.objects.new("lamp", bpy.data.lights.new("lamp", "POINT"))
    lamp.data.energy = 500.0
    lamp.location = (1.0, -2.0, 4.0)
    scene.collection.objects.link(lamp)
    scene.render.resolution_x, scene.render.resolution_y = 32, 24
    scene.render.resolution_percentage = 100
    scene.render.engine = "KDTRACE"
    settings = scene.kdtrace
    settings.use_zeroconf, settings.local_slaves = False, 1
    settings.samples_per_axis, settings.adaptive = 1, False
    return scene


def object_coordinates_material(name):
    """A material whose colour reads Object coordinates (a node program placed per object:
    the exporter inverts the object's transform for it)."""
    m = bpy.data.materials.new(name)
    nodes, links = m.node_tree.nodes, m.node_tree.links
    coords = nodes.new("ShaderNodeTexCoord")
    checker = nodes.new("ShaderNodeTexChecker")
    links.new(coords.outputs["Object"], checker.inputs["Vector"])
    links.new(checker.outputs["Color"], nodes["Principled BSDF"].inputs["Base Color"])
    return m


def flat_axis():
    cube = bpy.data.objects["cube"]
    cube.scale = (1.0, 1.0, 0.0)
    cube.data.materials.append(object_coordinates_material("object checker"))


def flat_all():
    bpy.data.objects["cube"].scale = (0.0, 0.0, 0.0)


def nan_transform():
    bpy.data.objects["cube"].location = (float("nan"), 0.0, 0.0)


def no_faces():
    mesh = bpy.data.meshes.new("edges only")
    mesh.from_pydata([(0, 0, 0), (1, 0, 0), (1, 1, 1)], [(0, 1), (1, 2)], [])
    bpy.context.scene.collection.objects.link(bpy.data.objects.new("wire", mesh))
    empty = bpy.data.meshes.new("nothing")
    bpy.context.scene.collection.objects.link(bpy.data.objects.new("hollow", empty))


def text_curve_metaball():
    bpy.ops.object.text_add(location=(-2.0, 0.0, 0.1))
    bpy.context.object.name = "words"
    bpy.ops.curve.primitive_bezier_circle_add(location=(2.0, 0.0, 0.5))
    bpy.context.object.data.bevel_depth = 0.2
    bpy.ops.object.metaball_add(location=(0.0, 1.5, 0.5))


def missing_image():
    m = bpy.data.materials.new("lost texture")
    nodes = m.node_tree.nodes
    texture = nodes.new("ShaderNodeTexImage")
    image = bpy.data.images.new("lost", 4, 4)      # then pointed at a file that is not there
    image.source, image.filepath = "FILE", os.path.join(OUT, "does-not-exist.png")
    image.reload()
    texture.image = image
    m.node_tree.links.new(texture.outputs["Color"], nodes["Principled BSDF"].inputs["Base Color"])
    bpy.data.objects["cube"].data.materials.append(m)


def odd_lights():
    flat = bpy.data.objects.new("flat area", bpy.data.lights.new("flat area", "AREA"))
    flat.location, flat.scale = (0.0, 0.0, 3.0), (0.0, 1.0, 1.0)
    bpy.context.scene.collection.objects.link(flat)
    lost = bpy.data.objects.new("lost sun", bpy.data.lights.new("lost sun", "SUN"))
    lost.location = (0.0, float("nan"), 0.0)
    bpy.context.scene.collection.objects.link(lost)


def missing_library():
    """An object linked from a library file that is then deleted: Blender opens the file with
    the object's placeholder."""
    library = os.path.join(OUT, "library.blend")
    bpy.data.libraries.write(library, {bpy.data.objects["cube"]})
    bpy.data.objects.remove(bpy.data.objects["cube"])
    with bpy.data.libraries.load(library, link=True) as (source, target):
        target.objects = ["cube"]
    for obj in target.objects:
        bpy.context.scene.collection.objects.link(obj)
    main = os.path.join(OUT, "main.blend")
    bpy.ops.wm.save_as_mainfile(filepath=main)
    os.remove(library)
    bpy.ops.wm.open_mainfile(filepath=main)


CASES = {"flat_axis": flat_axis, "flat_all": flat_all, "nan_transform": nan_transform,
         "no_faces": no_faces, "text_curve_metaball": text_curve_metaball,
         "missing_image": missing_image, "odd_lights": odd_lights,
         "missing_library": missing_library}


def press_f12(name):
    scene = bpy.context.scene
    scene.render.filepath = os.path.join(OUT, f"{name}.exr")
    scene.render.image_settings.file_format = "OPEN_EXR"
    addon.addon.session.current().last_warnings = []
    try:
        bpy.ops.render.render(write_still=True)
        outcome = "finished"
    except RuntimeError as error:     # the operator turns the engine's error into this
        outcome = str(error)
    path = scene.render.filepath
    mean = None
    if os.path.exists(path):
        image = bpy.data.images.load(path)
        mean = float(np.array(image.pixels[:], np.float32).reshape(-1, 4)[:, :3].mean())
        bpy.data.images.remove(image)
    return {"outcome": outcome, "written": os.path.exists(path), "mean": mean,
            "warnings": list(addon.addon.session.current().last_warnings)}


results = {}
for name in args.get("cases", list(CASES)):
    base_scene()
    CASES[name]()
    results[name] = press_f12(name)

# An exception inside the frame, after the first tile: an error report, not a dead Blender.
base_scene()
real_add = render_module.TileCanvas.add


def failing_add(canvas, tile):
    real_add(canvas, tile)
    raise ValueError("a defect planted by the test")


render_module.TileCanvas.add = failing_add
results["exception_in_frame"] = press_f12("exception_in_frame")
render_module.TileCanvas.add = real_add
results["after_the_exception"] = press_f12("after_the_exception")
write_result(result_path, results)
