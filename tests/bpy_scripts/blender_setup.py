"""Shared by the bpy scripts: install the extension, build test scenes, read EXR passes.

Runs inside a process that imports bpy (started by tests/blender.py).
"""
import json
import sys

import bpy
import numpy as np


def arguments() -> tuple[dict, str]:
    """The JSON arguments and the path to write the JSON result to."""
    return json.loads(sys.argv[1]), sys.argv[2]


def write_result(path: str, result: dict):
    with open(path, "w") as f:
        json.dump(result, f)


def cycles_at_pixel_centres(scene, samples=1):
    """Cycles on the CPU with `samples` per pixel, all at the pixel centre (a box filter of tiny
    width), neither adaptive sampling nor denoising."""
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.cycles.pixel_filter_type = "BOX"
    scene.cycles.filter_width = 0.01


def install_extension(zip_path: str):
    """Install and enable the built zip into the isolated user repository; return the add-on module."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    outcome = bpy.ops.extensions.package_install_files(
        filepath=zip_path, repo="user_default", enable_on_install=True)
    assert outcome == {"FINISHED"}, outcome
    import importlib
    return importlib.import_module("bl_ext.user_default.kdtrace")


def mesh_object(name, vertices, triangles, location=(0, 0, 0), color=(0.8, 0.8, 0.8, 1.0)):
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(vertices))
    mesh.vertices.foreach_set("co", np.asarray(vertices, np.float32).ravel())
    mesh.loops.add(len(triangles) * 3)
    mesh.loops.foreach_set("vertex_index", np.asarray(triangles, np.int32).ravel())
    mesh.polygons.add(len(triangles))
    mesh.polygons.foreach_set("loop_start", np.arange(0, len(triangles) * 3, 3, dtype=np.int32))
    mesh.update()
    mesh.validate()
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    bpy.context.scene.collection.objects.link(obj)
    material = bpy.data.materials.new(name + "-material")
    material.diffuse_color = color
    if material.node_tree:  # new materials have a Principled BSDF in Blender 5
        material.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = color
    obj.data.materials.append(material)
    return obj


def build_test_scene(width=160, height=120):
    """A UV sphere, the Stanford bunny and a ground plane, a camera and a sun and point light;
    KD Trace set to one sample per pixel."""
    from tests.meshes import load_bunny
    scene = bpy.context.scene
    bpy.ops.mesh.primitive_uv_sphere_add(radius=1.0, location=(-1.6, 0.5, 1.0), segments=48, ring_count=24)
    bpy.ops.object.shade_smooth()  # interpolated normals on the sphere; the rest is flat
    bpy.ops.mesh.primitive_plane_add(size=12.0, location=(0, 0, 0))
    vertices, triangles = load_bunny()
    # The bunny is y-up and about 10 units tall: stand it on the plane, 2 units tall.
    vertices = vertices[:, [0, 2, 1]] * np.array([0.2, -0.2, 0.2], np.float32)
    bunny = mesh_object("bunny", vertices, triangles[:, ::-1], location=(1.2, 0.0, 0.0),
                        color=(0.9, 0.6, 0.4, 1.0))
    bunny.rotation_euler = (0.0, 0.0, 0.4)
    camera_data = bpy.data.cameras.new("camera")
    camera = bpy.data.objects.new("camera", camera_data)
    camera.location = (0.5, -7.5, 3.2)
    camera.rotation_euler = (1.2, 0.0, 0.05)
    scene.collection.objects.link(camera)
    scene.camera = camera
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = 2.0
    sun.rotation_euler = (0.6, 0.2, 0.3)
    scene.collection.objects.link(sun)
    lamp = bpy.data.objects.new("lamp", bpy.data.lights.new("lamp", "POINT"))
    lamp.data.energy = 300.0
    lamp.location = (2.0, -3.0, 4.0)
    scene.collection.objects.link(lamp)
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    if hasattr(scene, "kdtrace"):
        # One sample per pixel, direct light and mirrors: quick renders for the tests of the
        # pipeline (the default is Cycles' clean, slow final render).
        settings = scene.kdtrace
        settings.samples_per_axis, settings.adaptive, settings.light_samples_per_axis = 1, False, 2
        settings.max_bounces, settings.diffuse_bounces = 8, 0
    return scene


def build_demo_scene():
    """The README's demo (bench/render_demo.py): the Stanford dragon on a ground plane with a
    sphere and a cube, a sun, a point lamp and a blue-grey world; the camera looks at it from
    the front. The caller sets the engine and resolution."""
    from tests.meshes import load_dragon
    scene = bpy.context.scene
    vertices, triangles = load_dragon()
    # The dragon is y-up and 0.2 units long: make it z-up and about 4 units long.
    vertices = vertices[:, [0, 2, 1]] * [20.0, -20.0, 20.0]
    vertices[:, 2] -= vertices[:, 2].min()
    mesh_object("dragon", vertices, triangles, color=(0.85, 0.55, 0.25, 1.0))
    bpy.ops.mesh.primitive_plane_add(size=20.0)
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.8, location=(-2.8, 1.5, 0.8))
    bpy.ops.object.shade_smooth()
    bpy.ops.mesh.primitive_cube_add(size=1.2, location=(2.8, 1.2, 0.6))
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    camera.location, camera.rotation_euler = (0.0, -11.5, 3.2), (1.407, 0.0, 0.0)
    scene.collection.objects.link(camera)
    scene.camera = camera
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy, sun.rotation_euler = 3.0, (0.5, 0.3, 0.6)
    scene.collection.objects.link(sun)
    lamp = bpy.data.objects.new("lamp", bpy.data.lights.new("lamp", "POINT"))
    lamp.data.energy, lamp.location = 400.0, (-3.0, -3.0, 5.0)
    scene.collection.objects.link(lamp)
    scene.world = bpy.data.worlds.new("sky")
    scene.world.color = (0.35, 0.45, 0.6)
    if scene.world.node_tree:  # new worlds have a Background node in Blender 5
        scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.35, 0.45, 0.6, 1)
    return scene


def exr_passes(path: str) -> dict:
    """Every pass of a multilayer EXR as float32 arrays (rows top first), by pass name."""
    import os
    site = os.path.join(bpy.utils.resource_path("LOCAL"), "python", "lib", "python3.11", "site-packages")
    sys.path.append(site)
    import OpenImageIO as oiio
    image = oiio.ImageInput.open(path)
    assert image, f"cannot read {path}"
    passes = {}
    subimage = 0
    while image.seek_subimage(subimage, 0):
        spec = image.spec()
        pixels = image.read_image(subimage, 0, 0, spec.nchannels, "float")
        for channel, name in enumerate(spec.channelnames):
            layer_pass, _, component = name.rpartition(".")
            passes.setdefault(layer_pass.split(".")[-1], {})[component] = pixels[:, :, channel]
        subimage += 1
    image.close()
    return passes
