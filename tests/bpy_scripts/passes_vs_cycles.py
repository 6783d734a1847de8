"""KD Trace's passes beside Cycles' on one scene (issue 40): a diffuse floor, a mirror-like
metal sphere, a glass sphere, a red Diffuse BSDF cube, an emitting cube (a lone Emission
shader), a world colour, a sun; World > Mist from 3 over 15 units, linear. Both engines render
the same samples (Blackman-Harris, denoising off) with Denoising Data, Mist, Emission, Diffuse
Color and Glossy Color on, to multilayer EXR; every pass is saved as <engine>-<pass>.npy.

Then the compositor: Render Layers -> Denoise (Image, Denoising Albedo, Denoising Normal) ->
Group Output, on a KD Trace render of `noisy_samples_per_axis`^2 samples, saved with the node
working (composite-denoised.npy) and muted (composite-muted.npy). Last, that render with KD
Trace's own denoising (F12's default): its Combined and Noisy Image passes
(denoised-Combined.npy, denoised-Noisy Image.npy)."""
import math

import bpy
import numpy as np

from blender_setup import arguments, exr_passes, install_extension, write_result

args, result_path = arguments()
install_extension(args["zip"])
OUT = args["out"]
PASSES = {"Combined": "RGBA", "Denoising Albedo": "RGB", "Denoising Normal": "XYZ", "Mist": "Z",
          "Emission": "RGB", "Diffuse Color": "RGB", "Glossy Color": "RGB",
          "Noisy Image": "RGBA"}


def material(name, node_type, **inputs):
    m = bpy.data.materials.new(name)
    tree = m.node_tree
    for node in list(tree.nodes):
        if node.type != "OUTPUT_MATERIAL":
            tree.nodes.remove(node)
    shader = tree.nodes.new(node_type)
    for key, value in inputs.items():
        shader.inputs[key].default_value = value
    tree.links.new(shader.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
    return m


def add(obj, m):
    obj.data.materials.append(m)
    return obj


def build():
    scene = bpy.context.scene
    bpy.ops.mesh.primitive_plane_add(size=14.0)
    add(bpy.context.object, material("floor", "ShaderNodeBsdfPrincipled",
                                     **{"Base Color": (0.6, 0.6, 0.55, 1), "Roughness": 0.6}))
    bpy.ops.mesh.primitive_uv_sphere_add(radius=1.0, location=(-1.6, 0.8, 1.0), segments=48,
                                         ring_count=24)
    bpy.ops.object.shade_smooth()
    add(bpy.context.object, material("metal", "ShaderNodeBsdfPrincipled", **{
        "Base Color": (0.9, 0.75, 0.45, 1), "Metallic": 1.0, "Roughness": 0.05}))
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.9, location=(0.9, -0.6, 0.9), segments=48,
                                         ring_count=24)
    bpy.ops.object.shade_smooth()
    add(bpy.context.object, material("glass", "ShaderNodeBsdfPrincipled", **{
        "Base Color": (0.8, 0.95, 1.0, 1), "Transmission Weight": 1.0, "Roughness": 0.0,
        "IOR": 1.45}))
    bpy.ops.mesh.primitive_cube_add(size=1.2, location=(2.6, 1.6, 0.6))
    add(bpy.context.object, material("red", "ShaderNodeBsdfDiffuse",
                                     Color=(0.8, 0.15, 0.1, 1)))
    bpy.ops.mesh.primitive_cube_add(size=0.8, location=(-3.2, -0.6, 0.4))
    add(bpy.context.object, material("glow", "ShaderNodeEmission",
                                     Color=(1.0, 0.6, 0.3, 1), Strength=3.0))
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    camera.location, camera.rotation_euler = (0.0, -9.0, 3.5), (math.radians(72), 0.0, 0.0)
    scene.collection.objects.link(camera)
    scene.camera = camera
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy, sun.rotation_euler = 3.0, (0.6, 0.2, 0.5)
    scene.collection.objects.link(sun)
    scene.world = bpy.data.worlds.new("sky")
    scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.3, 0.4, 0.5, 1)
    mist = scene.world.mist_settings
    mist.start, mist.depth, mist.falloff = 3.0, 15.0, "LINEAR"
    scene.render.resolution_x, scene.render.resolution_y = args["width"], args["height"]
    scene.render.resolution_percentage = 100
    scene.view_settings.view_transform = "Standard"
    layer = bpy.context.view_layer
    for name in ("use_pass_mist", "use_pass_emit", "use_pass_diffuse_color",
                 "use_pass_glossy_color"):
        setattr(layer, name, True)
    return scene, layer


def save(engine, path):
    for name, channels in exr_passes(path).items():
        if name in PASSES:
            np.save(f"{OUT}/{engine}-{name}.npy",
                    np.stack([channels[c] for c in PASSES[name]], -1))


scene, layer = build()
settings = scene.render.image_settings
settings.media_type = "MULTI_LAYER_IMAGE"
settings.file_format = "OPEN_EXR_MULTILAYER"
settings.color_depth = "32"
n = args["samples_per_axis"]

scene.render.engine = "CYCLES"
cycles = scene.cycles
cycles.device, cycles.samples, cycles.seed = "CPU", n * n, 1
cycles.use_adaptive_sampling = cycles.use_denoising = False
layer.cycles.denoising_store_passes = True
scene.render.filepath = f"{OUT}/cycles.exr"
bpy.ops.render.render(write_still=True)
save("cycles", scene.render.filepath)

scene.render.engine = "KDTRACE"
props = scene.kdtrace
props.use_zeroconf, props.local_slaves, props.tile_size = False, 2, 32
props.samples_per_axis, props.adaptive, props.use_denoising = n, False, False
layer.kdtrace.denoising_store_passes = True
scene.render.filepath = f"{OUT}/kdtrace.exr"
bpy.ops.render.render(write_still=True)
save("kdtrace", scene.render.filepath)
passes_shown = sorted(exr_passes(scene.render.filepath))

# The compositor's Denoise node on a noisy KD Trace render, working and muted.
props.samples_per_axis = args["noisy_samples_per_axis"]
tree = bpy.data.node_groups.new("denoise", "CompositorNodeTree")
tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
scene.compositing_node_group = tree
layers = tree.nodes.new("CompositorNodeRLayers")
denoise = tree.nodes.new("CompositorNodeDenoise")
output = tree.nodes.new("NodeGroupOutput")
tree.links.new(layers.outputs["Image"], denoise.inputs["Image"])
tree.links.new(layers.outputs["Denoising Albedo"], denoise.inputs["Albedo"])
tree.links.new(layers.outputs["Denoising Normal"], denoise.inputs["Normal"])
tree.links.new(denoise.outputs["Image"], output.inputs["Image"])
settings.media_type = "IMAGE"
settings.file_format = "OPEN_EXR"
scene.render.use_compositing = True
for state in ("denoised", "muted"):
    denoise.mute = state == "muted"
    scene.render.filepath = f"{OUT}/composite-{state}.exr"
    bpy.ops.render.render(write_still=True)
    [channels] = exr_passes(scene.render.filepath).values()
    np.save(f"{OUT}/composite-{state}.npy", np.stack([channels[c] for c in "RGB"], -1))
outputs = [o.name for o in layers.outputs if o.enabled]

scene.render.use_compositing = False
layer.kdtrace.denoising_store_passes = False
for name in ("use_pass_mist", "use_pass_emit", "use_pass_diffuse_color", "use_pass_glossy_color"):
    setattr(layer, name, False)
props.use_denoising = True
settings.media_type = "MULTI_LAYER_IMAGE"
settings.file_format = "OPEN_EXR_MULTILAYER"
scene.render.filepath = f"{OUT}/denoised.exr"
bpy.ops.render.render(write_still=True)
save("denoised", scene.render.filepath)
denoised_passes = sorted(exr_passes(scene.render.filepath))
write_result(result_path, {"kdtrace_passes": passes_shown, "denoised_passes": denoised_passes,
                           "render_layer_outputs": outputs})
