"""Cycles' own Sky Texture seen by an equirectangular panoramic camera (looking along +Y, +Z
up), one world per case of Sky Texture settings (Blender's names); writes <case>.npy (RGB,
rows bottom first) in the output folder. Box filter of 0.01 px: each pixel is its centre."""
import math

import bpy
import numpy as np

from blender_setup import arguments, cycles_at_pixel_centres, write_result

args, result_path = arguments()
bpy.ops.wm.read_factory_settings(use_empty=True)
scene = bpy.context.scene
data = bpy.data.cameras.new("panorama")
data.type = "PANO"
data.panorama_type = "EQUIRECTANGULAR"
camera = bpy.data.objects.new("panorama", data)
camera.rotation_euler = (math.pi / 2, 0.0, 0.0)
scene.collection.objects.link(camera)
scene.camera = camera
width, height = args["width"], args["height"]
scene.render.resolution_x, scene.render.resolution_y = width, height
scene.render.resolution_percentage = 100
cycles_at_pixel_centres(scene, samples=4)
scene.view_settings.view_transform = "Standard"
scene.view_settings.look = "None"
scene.render.image_settings.file_format = "OPEN_EXR"
scene.render.image_settings.color_depth = "32"
for name, settings in args["cases"].items():
    world = bpy.data.worlds.new(name)
    world.use_nodes = True
    sky = world.node_tree.nodes.new("ShaderNodeTexSky")
    for key, value in settings.items():
        setattr(sky, key, value)
    world.node_tree.links.new(sky.outputs["Color"], world.node_tree.nodes["Background"].inputs["Color"])
    scene.world = world
    path = f"{args['out']}/{name}.exr"
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)
    image = bpy.data.images.load(path)
    pixels = np.array(image.pixels[:], np.float32).reshape(height, width, 4)
    np.save(f"{args['out']}/{name}.npy", pixels[..., :3])
    bpy.data.images.remove(image)
write_result(result_path, {"cases": list(args["cases"])})
