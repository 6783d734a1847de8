"""Scenes of issue 14 rendered with Cycles and with KD Trace (the installed add-on, local
slaves) at matched settings: the world (a colour; a procedural HDRI as equirectangular and as
mirror ball, through a Mapping node), an emission-lit room, the BSDF nodes and Principled
inputs, glass under an area light. Writes <scene>-cycles.npy and <scene>-kdtrace.npy (Combined,
rows top first), <scene>-features.json (the features of the exported scene) and the export
itself (<scene>-scene.npz, <scene>-view.json) per scene; the result lists the warnings of each
export and the seconds each render took.

The HDRI is made here: a sky gradient with a small bright sun disc, written as a float image
and saved as OpenEXR in the output folder (then loaded back from the file)."""
import json
import math

import bpy
import numpy as np

from blender_setup import arguments, install_extension, write_result

args, result_path = arguments()
install_extension(args["zip"])
import importlib
export = importlib.import_module("bl_ext.user_default.kdtrace.addon.export")
Scene = importlib.import_module("bl_ext.user_default.kdtrace.core.scene.scene").Scene
kdtree = importlib.import_module("bl_ext.user_default.kdtrace.core.accel.kdtree")


def rendered_scene(depsgraph):
    """What the render exports (export_instanced_view): the scene, its view and warnings.
    Its features do not depend on the kd-trees: one level each is enough (and quick)."""
    exported, view, info = export.export_instanced_view(depsgraph)
    shallow = kdtree.KDTreeParams(max_depth=1)
    meshes = [(m, kdtree.build_kdtree(m.vertices, m.triangles, shallow)) for m in exported.meshes]
    scene = Scene.from_instances(meshes, exported.instance_mesh, exported.to_world,
                                 texels=exported.texels, texture_sizes=exported.texture_sizes,
                                 to_world_end=exported.to_world_end)
    return scene, view, info
OUT = args["out"]
SUN = (math.radians(40), math.radians(35))      # azimuth, elevation of the HDRI's sun


def sky(d):
    """Radiance of the procedural sky in unit directions d (..., 3): zenith-to-horizon
    gradient, darker ground, a sun disc of 5 degrees radius."""
    z = d[..., 2]
    t = np.clip(z, 0, 1)[..., None]
    colour = (1 - t) * np.array([0.9, 0.85, 0.8]) + t * np.array([0.15, 0.3, 0.8])
    colour = np.where(z[..., None] < 0, np.array([0.25, 0.2, 0.15]), colour)
    sun = np.array([math.cos(SUN[1]) * math.cos(SUN[0]), math.cos(SUN[1]) * math.sin(SUN[0]),
                    math.sin(SUN[1])])
    disc = (d @ sun) > math.cos(math.radians(5))
    return np.where(disc[..., None], np.array([24.0, 22.0, 18.0]), colour)


def hdri(projection):
    """The sky as an image in Cycles' projection, saved to .exr and loaded back."""
    if projection == "EQUIRECTANGULAR":
        w, h = 256, 128
        u = (np.arange(w) + 0.5) / w
        v = (np.arange(h) + 0.5) / h
        phi = 2 * np.pi * (0.5 - u)[None, :]
        elevation = np.pi * (v - 0.5)[:, None]
        d = np.stack(np.broadcast_arrays(np.cos(elevation) * np.cos(phi),
                                         np.cos(elevation) * np.sin(phi), np.sin(elevation)), -1)
        rgb = sky(d)
    else:
        w = h = 192
        x = 2 * (np.arange(w) + 0.5) / w - 1
        z = 2 * (np.arange(h) + 0.5) / h - 1
        x, z = np.meshgrid(x, z)
        r2 = x * x + z * z
        s = 2 * np.sqrt(np.maximum(1 - r2, 0))
        d = np.stack([s * x, 2 * r2 - 1, s * z], -1)
        rgb = np.where((r2 <= 1)[..., None], sky(d), 0.0)
    pixels = np.concatenate([rgb, np.ones((h, w, 1))], -1)
    # OpenEXR keeps the linear values (Blender writes .hdr through the display transform).
    return saved_image(f"sky-{projection.lower()}.exr", pixels)


def saved_image(file_name, pixels, non_color=False):
    """The RGBA pixels (rows bottom first) as an image saved to OUT/file_name (.exr: float,
    OpenEXR; .png: 8-bit PNG) and loaded back from the file."""
    h, w = pixels.shape[:2]
    exr = file_name.endswith(".exr")
    image = bpy.data.images.new(file_name, w, h, float_buffer=exr)
    image.pixels.foreach_set(pixels.astype(np.float32).ravel())
    path = f"{OUT}/{file_name}"
    image.filepath_raw = path
    image.file_format = "OPEN_EXR" if exr else "PNG"
    image.save()
    bpy.data.images.remove(image)
    image = bpy.data.images.load(path)
    if non_color:
        image.colorspace_settings.name = "Non-Color"
    return image


def data_image():
    """A 64 x 64 Non-Color image: red = u, green = v, blue = a 4 x 4 checker; saved as PNG and
    loaded back."""
    n = 64
    u, v = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n)
    checker = ((np.floor(4 * u) + np.floor(4 * v)) % 2)
    return saved_image("data.png", np.stack([u, v, checker, np.ones_like(u)], -1), non_color=True)


def ripple_normals():
    """A 64 x 64 tangent-space normal map (Non-Color, OpenEXR) of the height
    0.04 sin(2 pi 3 u) sin(2 pi 2 v): n = normalize(-dh/du, -dh/dv, 1) as 0.5 n + 0.5."""
    n = 64
    u, v = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n)
    k = 0.04 * 2 * np.pi
    normal = np.stack([-k * 3 * np.cos(6 * np.pi * u) * np.sin(4 * np.pi * v),
                       -k * 2 * np.sin(6 * np.pi * u) * np.cos(4 * np.pi * v), np.ones_like(u)], -1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return saved_image("ripples.exr", np.concatenate([0.5 * normal + 0.5, np.ones_like(u)[..., None]], -1),
                       non_color=True)


def vector_math(nodes, links, operation, vector, scale=None, second=None):
    """A Vector Math node of `vector` (a socket); its Vector output."""
    node = nodes.new("ShaderNodeVectorMath")
    node.operation = operation
    links.new(vector, node.inputs[0])
    if scale is not None:
        node.inputs["Scale"].default_value = scale
    if second is not None:
        node.inputs[1].default_value = second
    return node.outputs["Vector"]


def node_material(name):
    """A Principled material and its node tree's (nodes, links, principled)."""
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    nodes, links = m.node_tree.nodes, m.node_tree.links
    return m, nodes, links, nodes["Principled BSDF"]


def clear():
    for collection in (bpy.data.objects, bpy.data.meshes, bpy.data.materials, bpy.data.lights,
                       bpy.data.cameras, bpy.data.worlds, bpy.data.images, bpy.data.curves,
                       bpy.data.metaballs):
        for item in list(collection):
            collection.remove(item)


def material(name, kind="PRINCIPLED", color=(0.8, 0.8, 0.8), **inputs):
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    nodes = m.node_tree.nodes
    out = nodes["Material Output"]
    if kind == "PRINCIPLED":
        node = nodes["Principled BSDF"]
        node.inputs["Base Color"].default_value = (*color, 1)
    else:
        nodes.remove(nodes["Principled BSDF"])
        node = nodes.new({"DIFFUSE": "ShaderNodeBsdfDiffuse", "GLOSSY": "ShaderNodeBsdfGlossy",
                          "GLASS": "ShaderNodeBsdfGlass", "EMISSION": "ShaderNodeEmission",
                          "TRANSLUCENT": "ShaderNodeBsdfTranslucent",
                          "TRANSPARENT": "ShaderNodeBsdfTransparent"}[kind])
        node.inputs["Color"].default_value = (*color, 1)
        m.node_tree.links.new(node.outputs[0], out.inputs["Surface"])
    for key, value in inputs.items():
        node.inputs[key].default_value = value
    return m


def add(op, mat, smooth=False, **kw):
    op(**kw)
    obj = bpy.context.object
    obj.data.materials.append(mat)
    if smooth:
        bpy.ops.object.shade_smooth()
    return obj


def sphere(mat, location, radius=0.6):
    return add(bpy.ops.mesh.primitive_uv_sphere_add, mat, smooth=True, radius=radius,
               location=location, segments=48, ring_count=24)


def camera(location, target, lens=35.0):
    from mathutils import Vector
    data = bpy.data.cameras.new("camera")
    data.lens = lens
    obj = bpy.data.objects.new("camera", data)
    obj.location = location
    obj.rotation_euler = (Vector(target) - Vector(location)).to_track_quat("-Z", "Y").to_euler()
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.scene.camera = obj


def light(kind, location, target, **props):
    from mathutils import Vector
    data = bpy.data.lights.new(kind.lower(), kind)
    for key, value in props.items():
        setattr(data, key, value)
    obj = bpy.data.objects.new(kind.lower(), data)
    obj.location = location
    obj.rotation_euler = (Vector(target) - Vector(location)).to_track_quat("-Z", "Y").to_euler()
    bpy.context.scene.collection.objects.link(obj)


def world(color=(0.0, 0.0, 0.0), strength=1.0, image=None, rotation=None):
    w = bpy.data.worlds.new("world")
    w.use_nodes = True
    nodes = w.node_tree.nodes
    background = nodes["Background"]
    background.inputs["Color"].default_value = (*color, 1)
    background.inputs["Strength"].default_value = strength
    if image is not None:
        env = nodes.new("ShaderNodeTexEnvironment")
        env.image = image
        env.projection = "MIRROR_BALL" if image.name.startswith("sky-mirror") else "EQUIRECTANGULAR"
        w.node_tree.links.new(env.outputs["Color"], background.inputs["Color"])
        if rotation is not None:
            coords = nodes.new("ShaderNodeTexCoord")
            mapping = nodes.new("ShaderNodeMapping")
            mapping.inputs["Rotation"].default_value = rotation
            w.node_tree.links.new(coords.outputs["Generated"], mapping.inputs["Vector"])
            w.node_tree.links.new(mapping.outputs["Vector"], env.inputs["Vector"])
    bpy.context.scene.world = w


def sky_world(strength, rotation=None, **settings):
    """A world of a Sky Texture (its settings, Blender's names) times `strength`; through a
    Mapping node of `rotation` from Generated coordinates when given."""
    w = bpy.data.worlds.new("sky")
    w.use_nodes = True
    nodes, links = w.node_tree.nodes, w.node_tree.links
    sky_node = nodes.new("ShaderNodeTexSky")
    for key, value in settings.items():
        setattr(sky_node, key, value)
    links.new(sky_node.outputs["Color"], nodes["Background"].inputs["Color"])
    nodes["Background"].inputs["Strength"].default_value = strength
    if rotation is not None:
        coords, mapping = nodes.new("ShaderNodeTexCoord"), nodes.new("ShaderNodeMapping")
        mapping.inputs["Rotation"].default_value = rotation
        links.new(coords.outputs["Generated"], mapping.inputs["Vector"])
        links.new(mapping.outputs["Vector"], sky_node.inputs["Vector"])
    bpy.context.scene.world = w


def sky_scene():
    """What the sky scenes light: a floor reaching almost to the horizon, a ball, a box and a
    metal ball; the camera looks across the sun's light (the sun itself out of view) with the
    sky above the horizon in the top of the image."""
    floor(size=400.0)
    sphere(material("clay", "DIFFUSE", (0.8, 0.55, 0.4)), (-0.6, 0.6, 0.6))
    add(bpy.ops.mesh.primitive_cube_add, material("grey", color=(0.7, 0.7, 0.7)), size=0.8,
        location=(0.7, 0.2, 0.4))
    sphere(material("metal", color=(0.9, 0.9, 0.9), Metallic=1.0, Roughness=0.2),
           (0.3, -0.9, 0.35), radius=0.35)
    camera((4.5, -2.0, 1.6), (0.0, 0.5, 0.6))


def floor(mat=None, size=12.0):
    return add(bpy.ops.mesh.primitive_plane_add, mat or material("floor", "DIFFUSE", (0.6, 0.6, 0.6)),
               size=size)


def keyframes(obj, path, values):
    """Linear keyframes of obj.<path> at the given {frame: value}."""
    bpy.context.preferences.edit.keyframe_new_interpolation_type = "LINEAR"
    for frame, value in values.items():
        setattr(obj, path, value)
        obj.keyframe_insert(path, frame=frame)


def build(name):
    clear()
    scene = bpy.context.scene
    scene.render.film_transparent = False
    scene.render.use_motion_blur = False
    scene.frame_set(1)
    if name == "world_color":
        # Sky fill: a sun's shadows are lit by the world colour.
        world((0.35, 0.45, 0.6))
        floor()
        sphere(material("red", "DIFFUSE", (0.8, 0.25, 0.2)), (-0.7, 0.3, 0.6))
        add(bpy.ops.mesh.primitive_cube_add, material("grey", color=(0.7, 0.7, 0.7)), size=0.9,
            location=(0.8, 0.5, 0.45))
        light("SUN", (0, 0, 5), (0.5, 1.5, 0), energy=2.0, angle=math.radians(3))
        camera((0.0, -4.5, 2.4), (0, 0.3, 0.4))
    elif name in ("world_hdri", "world_mirror_ball"):
        image = hdri("EQUIRECTANGULAR" if name == "world_hdri" else "MIRROR_BALL")
        world(image=image, strength=1.0, rotation=(0.0, 0.0, math.radians(50)))
        floor()
        sphere(material("diffuse", "DIFFUSE", (0.8, 0.8, 0.8)), (-0.8, 0.3, 0.6))
        sphere(material("metal", color=(0.9, 0.75, 0.5), Metallic=1.0, Roughness=0.25),
               (0.8, 0.3, 0.6))
        camera((0.0, -3.8, 2.0), (0, 0.4, 0.6), lens=30)
    elif name == "emission_room":
        # A closed room lit only by an emissive ceiling panel (diffuse bounces matter).
        walls = material("walls", "DIFFUSE", (0.75, 0.75, 0.72))
        add(bpy.ops.mesh.primitive_cube_add, walls, size=4.0, location=(0, 0, 2.0))
        bpy.ops.object.mode_set(mode="EDIT")
        bpy.ops.mesh.flip_normals()
        bpy.ops.object.mode_set(mode="OBJECT")
        red = material("red wall", "DIFFUSE", (0.7, 0.15, 0.1))
        add(bpy.ops.mesh.primitive_plane_add, red, size=3.98, location=(-1.99, 0, 2.0),
            rotation=(0, math.radians(90), 0))
        add(bpy.ops.mesh.primitive_plane_add, material("lamp", "EMISSION", (1.0, 0.9, 0.8),
                                                       Strength=12.0),
            size=1.0, location=(0, 0.3, 3.98))
        add(bpy.ops.mesh.primitive_cube_add, material("box", color=(0.8, 0.8, 0.8)), size=1.0,
            location=(0.7, 0.6, 0.5))
        sphere(material("ball", "DIFFUSE", (0.2, 0.4, 0.8)), (-0.6, 0.2, 0.5), radius=0.5)
        camera((0.0, -1.95, 1.6), (0, 1.0, 1.3), lens=18)
    elif name == "materials":
        world((0.25, 0.25, 0.3))
        floor(material("floor", "DIFFUSE", (0.5, 0.5, 0.5)))
        spheres = [
            material("metal", color=(0.95, 0.7, 0.4), Metallic=1.0, Roughness=0.35),
            material("plastic", color=(0.8, 0.15, 0.1), Roughness=0.3),
            material("rough glass", color=(1.0, 1.0, 1.0),
                     **{"Transmission Weight": 1.0, "Roughness": 0.25, "IOR": 1.5}),
            material("glossy", "GLOSSY", (1.0, 1.0, 1.0), Roughness=0.2),
            material("glass", "GLASS", (1.0, 1.0, 1.0), Roughness=0.0, IOR=1.45),
            material("diffuse", "DIFFUSE", (0.3, 0.7, 0.3)),
        ]
        for k, mat in enumerate(spheres):
            sphere(mat, (-2.0 + 0.8 * k, 0.4 * (k % 2), 0.35), radius=0.35)
        add(bpy.ops.mesh.primitive_cube_add, material("emitter", "EMISSION", (0.4, 0.8, 1.0),
                                                      Strength=4.0),
            size=0.3, location=(1.9, -0.4, 0.15))
        light("AREA", (0.5, -2.0, 3.0), (0, 0, 0), energy=150.0, size=1.5)
        camera((0.0, -5.5, 2.2), (0, 0.2, 0.3), lens=40)
    elif name == "glass":
        # Glass under an area light: its highlight in the glass, caustics, the shadow.
        world((0.2, 0.22, 0.25))
        floor(material("floor", "DIFFUSE", (0.7, 0.7, 0.7)))
        sphere(material("glass", "GLASS", (1.0, 1.0, 1.0), IOR=1.5, Roughness=0.0),
               (-0.6, 0.0, 0.6))
        sphere(material("rough glass", color=(0.9, 1.0, 0.9),
                        **{"Transmission Weight": 1.0, "Roughness": 0.3, "IOR": 1.5}),
               (0.7, 0.3, 0.6))
        light("AREA", (1.6, -2.2, 3.0), (0, 0, 0.5), energy=250.0, size=1.0)
        camera((0.0, -4.0, 1.5), (0, 0.2, 0.6), lens=40)
    elif name == "interior":
        # A room with a window onto the HDRI sky (sun through the window) and an emissive
        # ceiling panel: both kinds of light indoors, diffuse bounces doing the rest.
        world(image=hdri("EQUIRECTANGULAR"), strength=1.0, rotation=(0.0, 0.0, math.radians(-50)))
        wall = material("plaster", "DIFFUSE", (0.7, 0.68, 0.62))
        planes = [((0, 0, 0), (0, 0, 0), (4, 4)), ((0, 0, 3), (math.pi, 0, 0), (4, 4)),
                  ((-2, 0, 1.5), (0, math.pi / 2, 0), (3, 4)), ((2, 0, 1.5), (0, -math.pi / 2, 0), (3, 4)),
                  ((0, -2, 1.5), (-math.pi / 2, 0, 0), (4, 3)),
                  # the window wall (+Y): a 1.6 x 1.2 opening, sill at 0.9
                  ((-1.4, 2, 1.5), (math.pi / 2, 0, 0), (1.2, 3)), ((1.4, 2, 1.5), (math.pi / 2, 0, 0), (1.2, 3)),
                  ((0, 2, 0.45), (math.pi / 2, 0, 0), (1.6, 0.9)), ((0, 2, 2.55), (math.pi / 2, 0, 0), (1.6, 0.9))]
        for location, rotation, (sx, sy) in planes:
            obj = add(bpy.ops.mesh.primitive_plane_add, wall, size=1.0, location=location,
                      rotation=rotation)
            obj.scale = (sx, sy, 1)
        add(bpy.ops.mesh.primitive_plane_add, material("panel", "EMISSION", (1.0, 0.95, 0.85),
                                                       Strength=6.0),
            size=0.8, location=(-0.8, -0.6, 2.98), rotation=(math.pi, 0, 0))
        add(bpy.ops.mesh.primitive_cube_add, material("table", color=(0.55, 0.35, 0.2),
                                                      Roughness=0.6), size=0.8,
            location=(0.7, 0.4, 0.4))
        sphere(material("chrome", color=(0.9, 0.9, 0.9), Metallic=1.0, Roughness=0.15),
               (-0.6, 0.6, 0.4), radius=0.4)
        camera((-0.2, -1.9, 1.4), (0.1, 1.5, 1.1), lens=16)
    elif name == "film_holdout":
        # Film > Transparent: the world lights but is not seen; a holdout cube punches a hole
        # (also through a cut-out), seen normally in the mirror ball.
        scene.render.film_transparent = True
        world((0.3, 0.35, 0.45))
        floor(material("floor", "DIFFUSE", (0.6, 0.6, 0.6)), size=3.0)
        sphere(material("mirror", color=(0.9, 0.9, 0.9), Metallic=1.0, Roughness=0.05),
               (-0.7, 0.4, 0.6))
        holdout = add(bpy.ops.mesh.primitive_cube_add, material("grey", color=(0.7, 0.7, 0.7)),
                      size=0.8, location=(0.6, 0.0, 0.4))
        holdout.is_holdout = True
        leaf = material("leaf", color=(0.2, 0.7, 0.2), Alpha=0.5)
        add(bpy.ops.mesh.primitive_plane_add, leaf, size=0.6, location=(0.5, -1.0, 0.5),
            rotation=(math.radians(90), 0, 0))
        light("AREA", (1.0, -2.0, 3.0), (0, 0, 0), energy=120.0, size=1.0)
        camera((0.0, -4.0, 1.8), (0, 0.2, 0.4), lens=35)
    elif name == "ray_visibility":
        # Each object hidden from one kind of ray (Object > Visibility > Ray Visibility).
        world((0.2, 0.22, 0.25))
        floor(material("floor", "DIFFUSE", (0.6, 0.6, 0.6)))
        ghost = sphere(material("ghost", "DIFFUSE", (0.8, 0.3, 0.2)), (-1.2, 0.2, 0.5), radius=0.45)
        ghost.visible_camera = False            # unseen, but casts its shadow
        no_shadow = add(bpy.ops.mesh.primitive_cube_add, material("no shadow", color=(0.3, 0.5, 0.8)),
                        size=0.7, location=(0.0, -0.2, 0.35))
        no_shadow.visible_shadow = False
        sphere(material("mirror", color=(0.9, 0.9, 0.9), Metallic=1.0, Roughness=0.0),
               (1.1, 0.6, 0.6), radius=0.55)
        vampire = add(bpy.ops.mesh.primitive_cube_add, material("vampire", color=(0.8, 0.7, 0.2)),
                      size=0.5, location=(1.2, -0.6, 0.25))
        vampire.visible_glossy = False          # not in the mirror
        wall = add(bpy.ops.mesh.primitive_plane_add, material("wall", "DIFFUSE", (0.9, 0.9, 0.9)),
                   size=2.0, location=(-0.6, 1.6, 1.0), rotation=(math.radians(90), 0, 0))
        wall.visible_diffuse = False            # lights no bounce, but is seen
        light("SUN", (0, 0, 5), (0.8, 1.2, 0), energy=3.0, angle=math.radians(2))
        camera((0.0, -4.5, 2.2), (0, 0.3, 0.4), lens=35)
    elif name == "depth_of_field":
        # A thin lens focused on the middle sphere (focus object), hexagonal aperture.
        world((0.25, 0.28, 0.32))
        floor(material("floor", "DIFFUSE", (0.55, 0.55, 0.55)))
        colours = [(0.8, 0.2, 0.2), (0.2, 0.7, 0.3), (0.2, 0.3, 0.8)]
        for k, (y, colour) in enumerate(zip((-1.2, 0.4, 2.4), colours)):
            target = sphere(material(f"ball {k}", "DIFFUSE", colour), (-0.8 + 0.8 * k, y, 0.4),
                            radius=0.4)
            if k == 1:
                focus = target
        light("AREA", (1.5, -2.0, 3.0), (0, 0, 0), energy=200.0, size=1.0)
        camera((0.0, -4.0, 1.2), (0, 0.6, 0.4), lens=50)
        data = bpy.context.scene.camera.data
        data.dof.use_dof = True
        data.dof.focus_object = focus
        data.dof.aperture_fstop = 0.35
        data.dof.aperture_blades = 6
        data.dof.aperture_rotation = math.radians(20)
    elif name == "camera_motion":
        # The camera moves sideways while the shutter is open (half a frame, centred).
        world((0.25, 0.28, 0.32))
        floor(material("floor", "DIFFUSE", (0.55, 0.55, 0.55)))
        sphere(material("ball", "DIFFUSE", (0.8, 0.3, 0.2)), (-0.5, 0.2, 0.5), radius=0.5)
        add(bpy.ops.mesh.primitive_cube_add, material("box", "DIFFUSE", (0.2, 0.5, 0.8)),
            size=0.8, location=(0.8, 0.4, 0.4))
        light("SUN", (0, 0, 5), (0.8, 1.2, 0), energy=3.0, angle=math.radians(2))
        camera((0.0, -4.0, 1.8), (0, 0.3, 0.4), lens=35)
        keyframes(bpy.context.scene.camera, "location", {0: (-0.8, -4.0, 1.8), 2: (0.8, -4.0, 1.8)})
        scene.render.use_motion_blur = True
        scene.render.motion_blur_shutter = 0.5
        scene.render.motion_blur_position = "CENTER"
        scene.frame_set(1)
    elif name == "object_motion":
        # A cube slides sideways and turns a little while the shutter is open (half a frame,
        # centred); the ball and the camera stay.
        world((0.25, 0.28, 0.32))
        floor(material("floor", "DIFFUSE", (0.55, 0.55, 0.55)))
        sphere(material("ball", "DIFFUSE", (0.8, 0.3, 0.2)), (-0.9, 0.4, 0.5), radius=0.5)
        box = add(bpy.ops.mesh.primitive_cube_add, material("box", "DIFFUSE", (0.2, 0.5, 0.8)),
                  size=0.7, location=(0.0, -0.2, 0.35))
        keyframes(box, "location", {0: (-0.6, -0.2, 0.35), 2: (1.4, -0.2, 0.35)})
        keyframes(box, "rotation_euler", {0: (0.0, 0.0, 0.0), 2: (0.0, 0.0, 0.4)})
        light("SUN", (0, 0, 5), (0.8, 1.2, 0), energy=3.0, angle=math.radians(2))
        camera((0.0, -4.0, 1.8), (0, 0.3, 0.4), lens=35)
        scene.render.use_motion_blur = True
        scene.render.motion_blur_shutter = 0.5
        scene.render.motion_blur_position = "CENTER"
        scene.frame_set(1)
    elif name == "nodes":
        # Shader nodes evaluated per hit: Checker through a Mix (Multiply) on the floor; an
        # image's channels (Separate Color) as Roughness and, through Math, Metallic, its red
        # through a Color Ramp as the base colour; Invert and Combine Color on the third.
        world((0.3, 0.32, 0.36))
        data = data_image()
        m, nodes, links, bsdf = node_material("checker floor")
        uv = nodes.new("ShaderNodeTexCoord")
        checker = nodes.new("ShaderNodeTexChecker")
        checker.inputs["Scale"].default_value = 6.0
        checker.inputs["Color1"].default_value = (0.8, 0.2, 0.15, 1)
        checker.inputs["Color2"].default_value = (0.9, 0.9, 0.9, 1)
        links.new(uv.outputs["UV"], checker.inputs["Vector"])
        mix = nodes.new("ShaderNodeMix")
        mix.data_type = "RGBA"
        mix.blend_type = "MULTIPLY"
        mix.inputs["Factor"].default_value = 0.7
        links.new(checker.outputs["Color"], mix.inputs[6])
        mix.inputs[7].default_value = (0.9, 0.8, 0.6, 1)
        links.new(mix.outputs[2], bsdf.inputs["Base Color"])
        links.new(checker.outputs["Fac"], bsdf.inputs["Roughness"])
        floor(m, size=6.0)
        m, nodes, links, bsdf = node_material("image channels")
        image = nodes.new("ShaderNodeTexImage")
        image.image = data
        separate = nodes.new("ShaderNodeSeparateColor")
        links.new(image.outputs["Color"], separate.inputs["Color"])
        links.new(separate.outputs["Green"], bsdf.inputs["Roughness"])
        math_node = nodes.new("ShaderNodeMath")
        math_node.operation = "MULTIPLY"
        math_node.inputs[1].default_value = 0.9
        links.new(separate.outputs["Blue"], math_node.inputs[0])
        links.new(math_node.outputs[0], bsdf.inputs["Metallic"])
        ramp = nodes.new("ShaderNodeValToRGB")
        ramp.color_ramp.elements[0].color = (0.1, 0.2, 0.8, 1)
        ramp.color_ramp.elements[1].color = (0.9, 0.7, 0.2, 1)
        middle = ramp.color_ramp.elements.new(0.5)
        middle.color = (0.2, 0.8, 0.3, 1)
        links.new(separate.outputs["Red"], ramp.inputs["Fac"])
        links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
        sphere(m, (-0.8, 0.3, 0.6))
        m, nodes, links, bsdf = node_material("inverted")
        image = nodes.new("ShaderNodeTexImage")
        image.image = data
        invert = nodes.new("ShaderNodeInvert")
        invert.inputs["Fac"].default_value = 0.8
        links.new(image.outputs["Color"], invert.inputs["Color"])
        combine = nodes.new("ShaderNodeCombineColor")
        separate = nodes.new("ShaderNodeSeparateColor")
        links.new(invert.outputs["Color"], separate.inputs["Color"])
        links.new(separate.outputs["Blue"], combine.inputs["Red"])
        links.new(separate.outputs["Red"], combine.inputs["Green"])
        power = nodes.new("ShaderNodeMath")
        power.operation = "POWER"
        power.inputs[1].default_value = 2.0
        links.new(separate.outputs["Green"], power.inputs[0])
        links.new(power.outputs[0], combine.inputs["Blue"])
        links.new(combine.outputs["Color"], bsdf.inputs["Base Color"])
        bsdf.inputs["Roughness"].default_value = 0.4
        sphere(m, (0.8, 0.3, 0.6))
        light("AREA", (1.0, -2.0, 3.0), (0, 0, 0), energy=150.0, size=1.0)
        camera((0.0, -4.0, 2.0), (0, 0.3, 0.4), lens=35)
    elif name == "nodes_more":
        # Vector Math, Gradient, Map Range, Hue/Saturation and the legacy MixRGB.
        world((0.3, 0.32, 0.36))
        data = data_image()
        m, nodes, links, bsdf = node_material("radial floor")
        uv = nodes.new("ShaderNodeTexCoord")
        centre = nodes.new("ShaderNodeVectorMath")
        centre.operation = "SUBTRACT"
        centre.inputs[1].default_value = (0.5, 0.5, 0.0)
        links.new(uv.outputs["UV"], centre.inputs[0])
        radial = nodes.new("ShaderNodeTexGradient")
        radial.gradient_type = "RADIAL"
        links.new(centre.outputs["Vector"], radial.inputs["Vector"])
        remap = nodes.new("ShaderNodeMapRange")
        remap.inputs["From Min"].default_value = 0.2
        remap.inputs["From Max"].default_value = 0.8
        remap.inputs["To Min"].default_value = 0.1
        remap.inputs["To Max"].default_value = 0.9
        links.new(radial.outputs["Fac"], remap.inputs["Value"])
        ramp = nodes.new("ShaderNodeValToRGB")
        ramp.color_ramp.elements[0].color = (0.8, 0.3, 0.1, 1)
        ramp.color_ramp.elements[1].color = (0.2, 0.5, 0.9, 1)
        links.new(remap.outputs["Result"], ramp.inputs["Fac"])
        links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
        distance = nodes.new("ShaderNodeVectorMath")
        distance.operation = "LENGTH"
        links.new(centre.outputs["Vector"], distance.inputs[0])
        links.new(distance.outputs["Value"], bsdf.inputs["Roughness"])
        floor(m, size=6.0)
        m, nodes, links, bsdf = node_material("hue shifted")
        image = nodes.new("ShaderNodeTexImage")
        image.image = data
        image.extension = "CLIP"            # UVs scaled past the image: black outside
        uv = nodes.new("ShaderNodeTexCoord")
        stretch = nodes.new("ShaderNodeVectorMath")
        stretch.operation = "SCALE"
        stretch.inputs["Scale"].default_value = 1.6
        links.new(uv.outputs["UV"], stretch.inputs[0])
        links.new(stretch.outputs["Vector"], image.inputs["Vector"])
        hsv = nodes.new("ShaderNodeHueSaturation")
        hsv.inputs["Hue"].default_value = 0.3
        hsv.inputs["Saturation"].default_value = 1.5
        hsv.inputs["Value"].default_value = 0.9
        links.new(image.outputs["Color"], hsv.inputs["Color"])
        links.new(hsv.outputs["Color"], bsdf.inputs["Base Color"])
        sphere(m, (-0.8, 0.3, 0.6))
        m, nodes, links, bsdf = node_material("spherical")
        uv = nodes.new("ShaderNodeTexCoord")
        scaled = vector_math(nodes, links, "SCALE", uv.outputs["UV"], scale=2.0)
        shifted = vector_math(nodes, links, "SUBTRACT", scaled, second=(1.0, 1.0, 0.0))
        ball = nodes.new("ShaderNodeTexGradient")
        ball.gradient_type = "SPHERICAL"
        links.new(shifted, ball.inputs["Vector"])
        lighten = nodes.new("ShaderNodeMixRGB")
        lighten.blend_type = "LIGHTEN"
        lighten.inputs["Fac"].default_value = 0.9
        lighten.inputs["Color1"].default_value = (0.3, 0.1, 0.4, 1)
        links.new(ball.outputs["Color"], lighten.inputs["Color2"])
        links.new(lighten.outputs["Color"], bsdf.inputs["Base Color"])
        sphere(m, (0.8, 0.3, 0.6))
        m, nodes, links, bsdf = node_material("extended")
        image = nodes.new("ShaderNodeTexImage")
        image.image = data
        image.extension = "EXTEND"
        image.interpolation = "Closest"
        coords = nodes.new("ShaderNodeTexCoord")
        links.new(coords.outputs["Generated"], image.inputs["Vector"])
        links.new(image.outputs["Color"], bsdf.inputs["Base Color"])
        add(bpy.ops.mesh.primitive_cube_add, m, size=0.5, location=(0.0, -0.8, 0.25))
        light("AREA", (1.0, -2.0, 3.0), (0, 0, 0), energy=150.0, size=1.0)
        camera((0.0, -4.0, 2.0), (0, 0.3, 0.4), lens=35)
    elif name == "generated":
        # Procedural textures at their default coordinates (Generated: the object's texture
        # space), one material on two objects of different sizes; Object coordinates.
        world((0.3, 0.32, 0.36))
        m, nodes, links, bsdf = node_material("checker box")
        checker = nodes.new("ShaderNodeTexChecker")
        checker.inputs["Scale"].default_value = 3.0
        checker.inputs["Color1"].default_value = (0.8, 0.2, 0.15, 1)
        links.new(checker.outputs["Color"], bsdf.inputs["Base Color"])
        box = add(bpy.ops.mesh.primitive_cube_add, m, size=0.8, location=(-0.9, 0.3, 0.4),
                  rotation=(0, 0, math.radians(30)))
        add(bpy.ops.mesh.primitive_cube_add, m, size=0.5, location=(0.2, -0.4, 0.25))
        box.scale = (1.0, 1.5, 1.0)
        m, nodes, links, bsdf = node_material("gradient ball")
        gradient = nodes.new("ShaderNodeTexGradient")
        gradient.gradient_type = "QUADRATIC_SPHERE"
        links.new(gradient.outputs["Color"], bsdf.inputs["Base Color"])
        sphere(m, (0.9, 0.4, 0.6))
        m, nodes, links, bsdf = node_material("object checker")
        coords = nodes.new("ShaderNodeTexCoord")
        checker = nodes.new("ShaderNodeTexChecker")
        checker.inputs["Scale"].default_value = 1.0
        links.new(coords.outputs["Object"], checker.inputs["Vector"])
        links.new(checker.outputs["Color"], bsdf.inputs["Base Color"])
        floor(m, size=6.0)
        light("AREA", (1.0, -2.0, 3.0), (0, 0, 0), energy=150.0, size=1.0)
        camera((0.0, -4.0, 2.0), (0, 0.3, 0.4), lens=35)
    elif name == "mapping":
        # What Blender's glTF importer builds for texture transforms: an image through a
        # Mapping node (Point: location, rotation, scale) from a UV Map node; a Texture mapping
        # of Object coordinates into a checker; UVs flipped through Separate XYZ, Math and
        # Combine XYZ; a Normal mapping's result as a colour; a Vector mapping into a gradient.
        world((0.3, 0.32, 0.36))
        data = data_image()
        m, nodes, links, bsdf = node_material("mapped image")
        uv_map = nodes.new("ShaderNodeUVMap")
        uv_map.uv_map = "UVMap"            # named, as the importer does: the cube's only one
        mapping = nodes.new("ShaderNodeMapping")
        mapping.inputs["Location"].default_value = (0.25, -0.1, 0.0)
        mapping.inputs["Rotation"].default_value = (0.0, 0.0, math.radians(30))
        mapping.inputs["Scale"].default_value = (2.0, 1.5, 1.0)
        image = nodes.new("ShaderNodeTexImage")
        image.image = data
        links.new(uv_map.outputs["UV"], mapping.inputs["Vector"])
        links.new(mapping.outputs["Vector"], image.inputs["Vector"])
        links.new(image.outputs["Color"], bsdf.inputs["Base Color"])
        add(bpy.ops.mesh.primitive_cube_add, m, size=0.8, location=(-0.9, 0.3, 0.4),
            rotation=(0, 0, math.radians(25)))
        m, nodes, links, bsdf = node_material("texture mapping")
        coords = nodes.new("ShaderNodeTexCoord")
        mapping = nodes.new("ShaderNodeMapping")
        mapping.vector_type = "TEXTURE"
        mapping.inputs["Location"].default_value = (0.3, 0.0, 0.1)
        mapping.inputs["Rotation"].default_value = (math.radians(20), 0.0, math.radians(45))
        mapping.inputs["Scale"].default_value = (0.5, 0.5, 1.0)
        checker = nodes.new("ShaderNodeTexChecker")
        checker.inputs["Scale"].default_value = 2.0
        links.new(coords.outputs["Object"], mapping.inputs["Vector"])
        links.new(mapping.outputs["Vector"], checker.inputs["Vector"])
        links.new(checker.outputs["Color"], bsdf.inputs["Base Color"])
        sphere(m, (0.9, 0.4, 0.6))
        m, nodes, links, bsdf = node_material("flipped uvs")
        coords = nodes.new("ShaderNodeTexCoord")
        separate = nodes.new("ShaderNodeSeparateXYZ")
        flip = nodes.new("ShaderNodeMath")
        flip.operation = "SUBTRACT"
        flip.inputs[0].default_value = 1.0
        combine = nodes.new("ShaderNodeCombineXYZ")
        image = nodes.new("ShaderNodeTexImage")
        image.image = data
        links.new(coords.outputs["UV"], separate.inputs["Vector"])
        links.new(separate.outputs["X"], combine.inputs["X"])
        links.new(separate.outputs["Y"], flip.inputs[1])
        links.new(flip.outputs[0], combine.inputs["Y"])
        links.new(combine.outputs["Vector"], image.inputs["Vector"])
        links.new(image.outputs["Color"], bsdf.inputs["Base Color"])
        floor(m, size=6.0)
        m, nodes, links, bsdf = node_material("normal mapping")
        coords = nodes.new("ShaderNodeTexCoord")
        mapping = nodes.new("ShaderNodeMapping")
        mapping.vector_type = "NORMAL"
        mapping.inputs["Rotation"].default_value = (0.0, math.radians(40), 0.0)
        mapping.inputs["Scale"].default_value = (1.0, 2.0, 0.5)
        absolute = vector_math(nodes, links, "ABSOLUTE", mapping.outputs["Vector"])
        links.new(coords.outputs["Object"], mapping.inputs["Vector"])
        links.new(absolute, bsdf.inputs["Base Color"])
        add(bpy.ops.mesh.primitive_cube_add, m, size=0.5, location=(0.2, -0.6, 0.25))
        m, nodes, links, bsdf = node_material("vector mapping")
        coords = nodes.new("ShaderNodeTexCoord")
        mapping = nodes.new("ShaderNodeMapping")
        mapping.vector_type = "VECTOR"
        mapping.inputs["Rotation"].default_value = (0.0, 0.0, math.radians(60))
        mapping.inputs["Scale"].default_value = (3.0, 1.0, 1.0)
        gradient = nodes.new("ShaderNodeTexGradient")
        links.new(coords.outputs["Generated"], mapping.inputs["Vector"])
        links.new(mapping.outputs["Vector"], gradient.inputs["Vector"])
        links.new(gradient.outputs["Color"], bsdf.inputs["Base Color"])
        sphere(m, (-0.1, 0.9, 0.4), radius=0.35)
        light("AREA", (1.0, -2.0, 3.0), (0, 0, 0), energy=150.0, size=1.0)
        camera((0.0, -4.0, 2.0), (0, 0.3, 0.4), lens=35)
    elif name == "outputs":
        # Two Material Outputs, one for EEVEE (active, a bright emission) and one for Cycles
        # (a diffuse surface), as Blender's versioning leaves old files and users make them;
        # a world with an active All output and a Cycles one.
        m = bpy.data.materials.new("two outputs")
        m.use_nodes = True
        nodes, links = m.node_tree.nodes, m.node_tree.links
        nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.2, 0.6, 0.3, 1)
        cycles_out = nodes["Material Output"]
        cycles_out.target = "CYCLES"
        eevee_out = nodes.new("ShaderNodeOutputMaterial")
        eevee_out.target = "EEVEE"
        glow = nodes.new("ShaderNodeEmission")
        glow.inputs["Strength"].default_value = 5.0
        links.new(glow.outputs[0], eevee_out.inputs["Surface"])
        nodes.active = eevee_out
        eevee_out.is_active_output = True
        sphere(m, (-0.6, 0.3, 0.6))
        w = bpy.data.worlds.new("two outputs world")
        w.use_nodes = True
        wnodes, wlinks = w.node_tree.nodes, w.node_tree.links
        wnodes["Background"].inputs["Color"].default_value = (1.0, 0.2, 0.2, 1)
        wnodes["World Output"].target = "ALL"
        cycles_world = wnodes.new("ShaderNodeOutputWorld")
        cycles_world.target = "CYCLES"
        sky_fill = wnodes.new("ShaderNodeBackground")
        sky_fill.inputs["Color"].default_value = (0.3, 0.32, 0.36, 1)
        wlinks.new(sky_fill.outputs[0], cycles_world.inputs["Surface"])
        wnodes["World Output"].is_active_output = True
        bpy.context.scene.world = w
        floor()
        light("AREA", (1.0, -2.0, 3.0), (0, 0, 0), energy=150.0, size=1.0)
        camera((0.0, -4.0, 2.0), (0, 0.3, 0.4), lens=35)
    elif name == "degenerate":
        # Odd input Blender holds: a box flattened to a square (scale z = 0) with a checker in
        # Object coordinates (the inverse of a singular transform), a ball scaled to nothing,
        # a text object, a bevelled curve, a metaball, an image that cannot be loaded
        # (magenta), an area light flattened to a line.
        world((0.3, 0.32, 0.36))
        m, nodes, links, bsdf = node_material("flat checker")
        coords = nodes.new("ShaderNodeTexCoord")
        checker = nodes.new("ShaderNodeTexChecker")
        checker.inputs["Scale"].default_value = 2.0
        links.new(coords.outputs["Object"], checker.inputs["Vector"])
        links.new(checker.outputs["Color"], bsdf.inputs["Base Color"])
        flat = add(bpy.ops.mesh.primitive_plane_add, m, size=1.2, location=(-0.8, 0.2, 0.3),
                   rotation=(math.radians(-30), 0.0, 0.0))
        flat.scale = (1.0, 1.0, 0.0)
        sphere(material("gone"), (0.0, 0.0, 0.5)).scale = (0.0, 0.0, 0.0)
        bpy.ops.object.text_add(location=(-1.2, -0.9, 0.01))
        bpy.context.object.data.materials.append(material("letters", color=(0.2, 0.5, 0.8)))
        bpy.ops.curve.primitive_bezier_circle_add(radius=0.4, location=(0.9, 0.5, 0.3))
        bpy.context.object.data.bevel_depth = 0.1
        bpy.ops.object.metaball_add(radius=0.6, location=(0.2, 0.8, 0.4))
        m, nodes, links, bsdf = node_material("lost texture")
        texture = nodes.new("ShaderNodeTexImage")
        texture.image = bpy.data.images.new("lost", 4, 4)
        texture.image.source, texture.image.filepath = "FILE", f"{OUT}/does-not-exist.png"
        texture.image.reload()
        links.new(texture.outputs["Color"], bsdf.inputs["Base Color"])
        add(bpy.ops.mesh.primitive_cube_add, m, size=0.5, location=(1.0, -0.6, 0.25))
        floor(size=6.0)
        light("AREA", (1.0, -2.0, 3.0), (0, 0, 0), energy=150.0, size=1.0)
        light("AREA", (-1.0, -1.0, 2.0), (0, 0, 0), energy=300.0, size=1.0)
        bpy.data.objects["area.001"].scale = (0.0, 1.0, 1.0)
        camera((0.0, -4.0, 2.0), (0, 0.3, 0.4), lens=35)
    elif name == "procedural":
        # Cycles' Noise Texture (its own Perlin noise and fBm): Color at the default Generated
        # coordinates, with distortion and a fractional detail; Fac through a Color Ramp at
        # Object coordinates, and as Roughness; Bump and Normal Map (tangent, object space);
        # node-driven emission.
        world((0.3, 0.32, 0.36))
        m, nodes, links, bsdf = node_material("noise colour")
        noise = nodes.new("ShaderNodeTexNoise")
        noise.inputs["Scale"].default_value = 4.0
        noise.inputs["Detail"].default_value = 3.5
        noise.inputs["Distortion"].default_value = 0.3
        links.new(noise.outputs["Color"], bsdf.inputs["Base Color"])
        sphere(m, (-0.7, 0.3, 0.6))
        m, nodes, links, bsdf = node_material("noise floor")
        coords = nodes.new("ShaderNodeTexCoord")
        noise = nodes.new("ShaderNodeTexNoise")
        noise.inputs["Scale"].default_value = 1.5
        noise.inputs["Roughness"].default_value = 0.7
        noise.inputs["Lacunarity"].default_value = 2.5
        links.new(coords.outputs["Object"], noise.inputs["Vector"])
        ramp = nodes.new("ShaderNodeValToRGB")
        ramp.color_ramp.elements[0].position = 0.35
        ramp.color_ramp.elements[0].color = (0.6, 0.15, 0.1, 1)
        ramp.color_ramp.elements[1].position = 0.65
        ramp.color_ramp.elements[1].color = (0.9, 0.85, 0.6, 1)
        links.new(noise.outputs["Fac"], ramp.inputs["Fac"])
        links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
        links.new(noise.outputs["Fac"], bsdf.inputs["Roughness"])
        floor(m, size=6.0)
        # Bump: a noise height at Generated coordinates on a smooth sphere.
        m, nodes, links, bsdf = node_material("bumpy")
        bsdf.inputs["Base Color"].default_value = (0.7, 0.7, 0.75, 1)
        bsdf.inputs["Roughness"].default_value = 0.35
        noise = nodes.new("ShaderNodeTexNoise")
        noise.inputs["Scale"].default_value = 6.0
        bump = nodes.new("ShaderNodeBump")
        bump.inputs["Distance"].default_value = 0.3
        links.new(noise.outputs["Fac"], bump.inputs["Height"])
        links.new(bump.outputs["Normal"], bsdf.inputs["Normal"])
        sphere(m, (0.75, 0.35, 0.6))
        # Normal Map, tangent space: ripples from an image on the UV map of a turned cube (its
        # colour a 2D ridged multifractal noise of the UVs).
        m, nodes, links, bsdf = node_material("rippled")
        flat = nodes.new("ShaderNodeTexNoise")          # 2D ridged noise of the UVs as the colour
        flat.noise_dimensions = "2D"
        flat.noise_type = "RIDGED_MULTIFRACTAL"
        flat.inputs["Offset"].default_value = 0.8
        flat.inputs["Scale"].default_value = 4.0
        links.new(nodes.new("ShaderNodeTexCoord").outputs["UV"], flat.inputs["Vector"])
        links.new(flat.outputs["Color"], bsdf.inputs["Base Color"])
        image = nodes.new("ShaderNodeTexImage")
        image.image = ripple_normals()
        mapped = nodes.new("ShaderNodeNormalMap")
        links.new(image.outputs["Color"], mapped.inputs["Color"])
        links.new(mapped.outputs["Normal"], bsdf.inputs["Normal"])
        add(bpy.ops.mesh.primitive_cube_add, m, size=0.6, location=(0.05, -0.75, 0.3),
            rotation=(0, 0, math.radians(35)))
        # Normal Map, object space at Strength 0.8: a flat-shaded, turned ball's own object-space
        # normals (its normalised Object coordinates as a colour) mixed with a noise colour.
        m, nodes, links, bsdf = node_material("object normals")
        coords = nodes.new("ShaderNodeTexCoord")
        unit = vector_math(nodes, links, "NORMALIZE", coords.outputs["Object"])
        half = vector_math(nodes, links, "SCALE", unit, scale=0.5)
        colour = vector_math(nodes, links, "ADD", half, second=(0.5, 0.5, 0.5))
        noise = nodes.new("ShaderNodeTexNoise")
        noise.inputs["Scale"].default_value = 3.0
        mix = nodes.new("ShaderNodeMixRGB")
        mix.inputs["Fac"].default_value = 0.3
        links.new(colour, mix.inputs["Color1"])
        links.new(noise.outputs["Color"], mix.inputs["Color2"])
        mapped = nodes.new("ShaderNodeNormalMap")
        mapped.space = "OBJECT"
        mapped.inputs["Strength"].default_value = 0.8
        links.new(mix.outputs["Color"], mapped.inputs["Color"])
        links.new(mapped.outputs["Normal"], bsdf.inputs["Normal"])
        add(bpy.ops.mesh.primitive_ico_sphere_add, m, radius=0.3, subdivisions=2,
            location=(1.25, -0.6, 0.3), rotation=(math.radians(40), 0, math.radians(-25)))
        # Emission driven by nodes: a 4D noise colour, its Fac through Math as the strength.
        m, nodes, links, bsdf = node_material("noise glow")
        nodes.remove(bsdf)
        glow = nodes.new("ShaderNodeEmission")
        links.new(glow.outputs[0], nodes["Material Output"].inputs["Surface"])
        noise = nodes.new("ShaderNodeTexNoise")
        noise.noise_dimensions = "4D"
        noise.inputs["W"].default_value = 0.7
        noise.inputs["Scale"].default_value = 3.0
        strength = nodes.new("ShaderNodeMath")
        strength.operation = "MULTIPLY"
        strength.inputs[1].default_value = 1.5
        links.new(noise.outputs["Fac"], strength.inputs[0])
        links.new(noise.outputs["Color"], glow.inputs["Color"])
        links.new(strength.outputs["Value"], glow.inputs["Strength"])
        add(bpy.ops.mesh.primitive_cube_add, m, size=0.35, location=(-1.45, -0.5, 0.18))
        light("AREA", (1.0, -2.0, 3.0), (0, 0, 0), energy=150.0, size=1.0)
        camera((0.0, -4.0, 2.0), (0, 0.3, 0.4), lens=35)
    elif name == "closures":
        # Mix Shader and Add Shader (issue 38): closures mixed by a constant, by Fresnel, by
        # Layer Weight and by a checker; Transparent, Holdout and Emission inside mixes; on a
        # transparent film (alpha: the holdout's share, what transparency lets through).
        scene.render.film_transparent = True
        world((0.3, 0.32, 0.36))
        floor(material("floor", "DIFFUSE", (0.6, 0.6, 0.6)), size=8.0)

        def shader_mix(name, first, second, fac=None, add=False):
            """A material mixing (or adding) two shader nodes made by first(nodes) and
            second(nodes); fac: a constant or a function making the Fac socket's source."""
            m = bpy.data.materials.new(name)
            m.use_nodes = True
            nodes, links = m.node_tree.nodes, m.node_tree.links
            nodes.remove(nodes["Principled BSDF"])
            mix = nodes.new("ShaderNodeAddShader" if add else "ShaderNodeMixShader")
            offset = 0 if add else 1
            links.new(first(nodes).outputs[0], mix.inputs[offset])
            links.new(second(nodes).outputs[0], mix.inputs[offset + 1])
            if callable(fac):
                links.new(fac(nodes, links), mix.inputs[0])
            elif fac is not None:
                mix.inputs[0].default_value = fac
            links.new(mix.outputs[0], nodes["Material Output"].inputs["Surface"])
            return m

        def bsdf(kind, color=None, **inputs):
            def make(nodes):
                node = nodes.new(kind)
                if color is not None:
                    node.inputs["Color"].default_value = (*color, 1)
                for key, value in inputs.items():
                    node.inputs[key].default_value = value
                return node
            return make

        def fresnel(nodes, links):
            node = nodes.new("ShaderNodeFresnel")
            node.inputs["IOR"].default_value = 1.6
            return node.outputs["Fac"]

        def facing(nodes, links):
            node = nodes.new("ShaderNodeLayerWeight")
            node.inputs["Blend"].default_value = 0.3
            return node.outputs["Facing"]

        def checker(nodes, links):
            node = nodes.new("ShaderNodeTexChecker")
            node.inputs["Scale"].default_value = 4.0
            return node.outputs["Fac"]

        sphere(shader_mix("constant mix", bsdf("ShaderNodeBsdfDiffuse", (0.8, 0.2, 0.1)),
                          bsdf("ShaderNodeBsdfGlossy", (0.9, 0.9, 0.9), Roughness=0.2), 0.3),
               (-1.5, 0.3, 0.45), radius=0.45)
        sphere(shader_mix("fresnel mix", bsdf("ShaderNodeBsdfDiffuse", (0.1, 0.3, 0.8)),
                          bsdf("ShaderNodeBsdfGlossy", (1.0, 1.0, 1.0), Roughness=0.1), fresnel),
               (-0.5, 0.6, 0.45), radius=0.45)
        sphere(shader_mix("glowing rim", bsdf("ShaderNodeBsdfPrincipled"),
                          bsdf("ShaderNodeEmission", (1.0, 0.6, 0.2), Strength=3.0), facing),
               (0.5, 0.6, 0.45), radius=0.45)
        sphere(shader_mix("holey", bsdf("ShaderNodeBsdfDiffuse", (0.9, 0.8, 0.3)),
                          bsdf("ShaderNodeBsdfTransparent", (1.0, 1.0, 1.0)), checker),
               (1.5, 0.3, 0.45), radius=0.45)
        add(bpy.ops.mesh.primitive_plane_add,
            shader_mix("tinted glass pane", bsdf("ShaderNodeBsdfDiffuse", (0.2, 0.2, 0.2)),
                       bsdf("ShaderNodeBsdfTransparent", (0.3, 0.8, 0.4)), add=True),
            size=0.8, location=(-0.9, -0.7, 0.4), rotation=(math.radians(90), 0, 0))
        half = add(bpy.ops.mesh.primitive_cube_add,
                   shader_mix("half holdout", bsdf("ShaderNodeHoldout"),
                              bsdf("ShaderNodeBsdfDiffuse", (0.8, 0.8, 0.8)), 0.5),
                   size=0.5, location=(0.6, -0.6, 0.25))
        half.visible_shadow = False     # its records copied whole for its ray visibility
        light("AREA", (1.0, -2.0, 3.0), (0, 0, 0), energy=150.0, size=1.0)
        camera((0.0, -4.0, 2.0), (0, 0.3, 0.4), lens=35)
    elif name == "translucent":
        # Translucent BSDF (issue 38): a lampshade lit from behind by an area light, a ball
        # mixing Translucent and Diffuse in front of a lamp, a green Transparent pane alone.
        world((0.05, 0.05, 0.06))
        floor(material("floor", "DIFFUSE", (0.5, 0.5, 0.5)), size=8.0)
        shade = material("shade", "TRANSLUCENT", (0.9, 0.7, 0.4))
        add(bpy.ops.mesh.primitive_plane_add, shade, size=1.4, location=(-0.7, 0.3, 0.8),
            rotation=(math.radians(90), 0, 0))
        leaf = bpy.data.materials.new("leaf")
        leaf.use_nodes = True
        nodes, links = leaf.node_tree.nodes, leaf.node_tree.links
        nodes.remove(nodes["Principled BSDF"])
        through = nodes.new("ShaderNodeBsdfTranslucent")
        through.inputs["Color"].default_value = (0.3, 0.8, 0.2, 1)
        back = nodes.new("ShaderNodeBsdfDiffuse")
        back.inputs["Color"].default_value = (0.2, 0.5, 0.1, 1)
        mix = nodes.new("ShaderNodeMixShader")
        mix.inputs[0].default_value = 0.6
        links.new(back.outputs[0], mix.inputs[1])
        links.new(through.outputs[0], mix.inputs[2])
        links.new(mix.outputs[0], nodes["Material Output"].inputs["Surface"])
        sphere(leaf, (0.7, 0.4, 0.6), radius=0.45)
        pane = material("green pane", "TRANSPARENT", (0.4, 0.9, 0.5))
        add(bpy.ops.mesh.primitive_plane_add, pane, size=0.7, location=(0.3, -0.8, 0.35),
            rotation=(math.radians(90), 0, 0))
        light("AREA", (-0.7, 2.0, 1.2), (-0.7, 0.3, 0.8), energy=25.0, size=0.8)
        light("AREA", (1.2, 2.0, 1.0), (0.7, 0.4, 0.6), energy=60.0, size=0.6)
        light("AREA", (1.0, -2.0, 3.0), (0, 0, 0), energy=40.0, size=1.0)
        camera((0.0, -4.0, 1.6), (0, 0.3, 0.5), lens=35)
    elif name == "sky_multiple":
        # Blender 5.0's default Sky Texture (Multiple Scattering, sun disc on, 15 degrees up).
        sky_world(0.1)
        sky_scene()
    elif name == "sky_single":
        # Single Scattering, the sun higher and turned, thinner air, more aerosols, a bigger
        # sun disc (a sky with its sun disc has no Vector input).
        sky_world(0.025, sky_type="SINGLE_SCATTERING", sun_elevation=math.radians(35),
                  sun_rotation=math.radians(40), air_density=0.7, aerosol_density=2.0,
                  sun_size=math.radians(1.5))
        sky_scene()
    elif name == "sky_preetham":
        # Preetham's sky of a sun direction (no sun disc in Cycles' Preetham), through a
        # Mapping node.
        sky_world(1.0, rotation=(0.0, math.radians(10), math.radians(-40)), sky_type="PREETHAM",
                  sun_direction=(0.4, 0.5, 0.77), turbidity=3.0)
        sky_scene()
    elif name == "textures":
        # Voronoi, Wave, Magic, Brick and White Noise (issue 38) at their default Generated
        # coordinates and through Object coordinates.
        world((0.3, 0.32, 0.36))

        def textured(name, kind, output, socket="Base Color", vector=None, **settings):
            m, nodes, links, bsdf = node_material(name)
            node = nodes.new(kind)
            for key, value in settings.items():
                if key.startswith("in_"):
                    node.inputs[key[3:].replace("_", " ")].default_value = value
                else:
                    setattr(node, key, value)
            if vector is not None:
                links.new(vector(nodes, links), node.inputs["Vector"])
            links.new(node.outputs[output], bsdf.inputs[socket])
            return m, nodes, links, bsdf

        bricks, *_ = textured("bricks", "ShaderNodeTexBrick", "Color", in_Scale=4.0,
                              in_Mortar_Smooth=0.3, offset=0.4, squash=1.4, squash_frequency=3)
        floor(bricks, size=6.0)
        cells, *_ = textured("cells", "ShaderNodeTexVoronoi", "Color", in_Scale=6.0)
        sphere(cells, (-1.4, 0.3, 0.5), radius=0.5)
        smooth, nodes, links, bsdf = textured("smooth cells", "ShaderNodeTexVoronoi", "Distance",
                                              socket="Roughness", feature="SMOOTH_F1",
                                              distance="MANHATTAN", in_Scale=5.0, in_Detail=1.5)
        edges = nodes.new("ShaderNodeTexVoronoi")
        edges.feature = "DISTANCE_TO_EDGE"
        edges.inputs["Scale"].default_value = 4.0
        ramp = nodes.new("ShaderNodeValToRGB")
        ramp.color_ramp.elements[0].color = (0.05, 0.05, 0.05, 1)
        ramp.color_ramp.elements[1].position = 0.15
        ramp.color_ramp.elements[1].color = (0.9, 0.6, 0.2, 1)
        links.new(edges.outputs["Distance"], ramp.inputs["Fac"])
        links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
        sphere(smooth, (-0.45, 0.6, 0.5), radius=0.5)
        waves, *_ = textured("waves", "ShaderNodeTexWave", "Color", wave_type="RINGS",
                             wave_profile="SAW", in_Scale=2.0, in_Distortion=4.0, in_Detail=2.0)
        add(bpy.ops.mesh.primitive_cube_add, waves, size=0.8, location=(0.55, 0.6, 0.4),
            rotation=(0, 0, math.radians(25)))
        magic, *_ = textured("magic", "ShaderNodeTexMagic", "Color", turbulence_depth=3,
                             in_Scale=3.0, in_Distortion=1.5)
        sphere(magic, (1.5, 0.3, 0.5), radius=0.5)

        def snapped(nodes, links):
            coords = nodes.new("ShaderNodeTexCoord")
            return vector_math(nodes, links, "SNAP", coords.outputs["Object"], second=(0.25,) * 3)
        speckle, *_ = textured("speckle", "ShaderNodeTexWhiteNoise", "Color", vector=snapped)
        add(bpy.ops.mesh.primitive_cube_add, speckle, size=0.6, location=(-0.5, -0.8, 0.3))
        light("AREA", (1.0, -2.0, 3.0), (0, 0, 0), energy=150.0, size=1.0)
        camera((0.0, -4.0, 2.0), (0, 0.3, 0.4), lens=35)
    elif name == "attributes":
        # Color Attribute, Attribute, Object Info, Geometry and Light Path (issue 38).
        world((0.3, 0.32, 0.36))
        floor(size=6.0)
        m, nodes, links, bsdf = node_material("painted")
        links.new(nodes.new("ShaderNodeVertexColor").outputs["Color"], bsdf.inputs["Base Color"])
        painted = add(bpy.ops.mesh.primitive_cube_add, m, size=0.7, location=(-1.3, 0.3, 0.35),
                      rotation=(0, 0, math.radians(30)))
        colours = painted.data.color_attributes.new("paint", "BYTE_COLOR", "CORNER")
        for k, corner in enumerate(colours.data):
            corner.color = ((k * 0.37) % 1, (k * 0.61) % 1, (k * 0.13) % 1, 1.0)
        m, nodes, links, bsdf = node_material("heights")
        attribute = nodes.new("ShaderNodeAttribute")
        attribute.attribute_name = "height"
        ramp = nodes.new("ShaderNodeValToRGB")
        ramp.color_ramp.elements[0].color = (0.1, 0.2, 0.8, 1)
        ramp.color_ramp.elements[1].color = (0.9, 0.8, 0.1, 1)
        links.new(attribute.outputs["Fac"], ramp.inputs["Fac"])
        links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
        ball = sphere(m, (-0.3, 0.6, 0.5), radius=0.5)
        heights = ball.data.attributes.new("height", "FLOAT", "POINT")
        for k, vertex in enumerate(ball.data.vertices):
            heights.data[k].value = 0.5 + 0.5 * vertex.co.z / 0.5
        m, nodes, links, bsdf = node_material("object info")
        info = nodes.new("ShaderNodeObjectInfo")
        links.new(info.outputs["Color"], bsdf.inputs["Base Color"])
        links.new(info.outputs["Random"], bsdf.inputs["Roughness"])
        for k, colour in enumerate(((0.9, 0.3, 0.2, 1), (0.2, 0.8, 0.3, 1), (0.3, 0.4, 0.9, 1))):
            box = add(bpy.ops.mesh.primitive_cube_add, m, size=0.3, location=(0.4 + 0.35 * k, -0.7, 0.15))
            box.color = colour
        m, nodes, links, bsdf = node_material("normals")
        geometry = nodes.new("ShaderNodeNewGeometry")
        half = vector_math(nodes, links, "SCALE", geometry.outputs["Normal"], scale=0.5)
        links.new(vector_math(nodes, links, "ADD", half, second=(0.5, 0.5, 0.5)),
                  bsdf.inputs["Base Color"])
        sphere(m, (0.8, 0.6, 0.5), radius=0.5)
        # Light Path: a panel that glows for the camera only, and a ball whose shadow lets
        # light through (Transparent for shadow rays) and that grows rough in reflections.
        m, nodes, links, bsdf = node_material("camera glow")
        nodes.remove(bsdf)
        glow = nodes.new("ShaderNodeEmission")
        glow.inputs["Color"].default_value = (1.0, 0.5, 0.2, 1)
        path = nodes.new("ShaderNodeLightPath")
        strength = nodes.new("ShaderNodeMath")
        strength.operation = "MULTIPLY"
        strength.inputs[1].default_value = 3.0
        links.new(path.outputs["Is Camera Ray"], strength.inputs[0])
        links.new(strength.outputs[0], glow.inputs["Strength"])
        links.new(glow.outputs[0], nodes["Material Output"].inputs["Surface"])
        add(bpy.ops.mesh.primitive_plane_add, m, size=0.6, location=(1.6, 0.9, 0.5),
            rotation=(math.radians(90), 0, 0))
        m, nodes, links, bsdf = node_material("no shadow")
        bsdf.inputs["Base Color"].default_value = (0.8, 0.7, 0.3, 1)
        path = nodes.new("ShaderNodeLightPath")
        see_through = nodes.new("ShaderNodeBsdfTransparent")
        mix = nodes.new("ShaderNodeMixShader")
        links.new(path.outputs["Is Shadow Ray"], mix.inputs[0])
        links.new(bsdf.outputs[0], mix.inputs[1])
        links.new(see_through.outputs[0], mix.inputs[2])
        links.new(mix.outputs[0], nodes["Material Output"].inputs["Surface"])
        depth = nodes.new("ShaderNodeMath")
        depth.operation = "MINIMUM"
        depth.inputs[1].default_value = 1.0
        links.new(path.outputs["Ray Depth"], depth.inputs[0])
        links.new(depth.outputs[0], bsdf.inputs["Roughness"])
        sphere(m, (-1.2, -0.6, 0.3), radius=0.3)
        light("AREA", (1.0, -2.0, 3.0), (0, 0, 0), energy=150.0, size=1.0)
        camera((0.0, -4.0, 2.0), (0, 0.3, 0.4), lens=35)
    elif name == "coat":
        # Principled Coat (issue 38) as Cycles layers it: over a red plastic, a tinted coat of
        # IOR 1.6 over a metal, a rough coat over a diffuse, a coat weighted by a checker.
        world((0.3, 0.32, 0.36))
        floor(material("floor", "DIFFUSE", (0.5, 0.5, 0.5)), size=8.0)
        sphere(material("coated plastic", color=(0.8, 0.1, 0.05), Roughness=0.6,
                        **{"Coat Weight": 1.0, "Coat Roughness": 0.05}), (-1.5, 0.3, 0.45),
               radius=0.45)
        sphere(material("tinted coat", color=(0.9, 0.8, 0.6), Metallic=1.0, Roughness=0.4,
                        **{"Coat Weight": 0.8, "Coat IOR": 1.6, "Coat Tint": (0.3, 0.5, 0.9, 1.0),
                           "Coat Roughness": 0.1}), (-0.5, 0.6, 0.45), radius=0.45)
        sphere(material("rough coat", color=(0.2, 0.6, 0.3), Roughness=1.0,
                        **{"Coat Weight": 1.0, "Coat Roughness": 0.35, "Coat IOR": 1.45}),
               (0.5, 0.6, 0.45), radius=0.45)
        m, nodes, links, bsdf = node_material("checkered coat")
        bsdf.inputs["Base Color"].default_value = (0.1, 0.2, 0.7, 1)
        bsdf.inputs["Coat Roughness"].default_value = 0.02
        checker = nodes.new("ShaderNodeTexChecker")
        checker.inputs["Scale"].default_value = 3.0
        links.new(checker.outputs["Fac"], bsdf.inputs["Coat Weight"])
        sphere(m, (1.5, 0.3, 0.45), radius=0.45)
        light("AREA", (1.0, -2.0, 3.0), (0, 0, 0), energy=150.0, size=1.0)
        camera((0.0, -4.0, 2.0), (0, 0.3, 0.4), lens=35)
    elif name == "soft_falloff":
        # Point and spot lights with Soft Falloff off (issue 38): spheres of light, near a
        # floor and a ball, beside a point light with it on.
        world((0.05, 0.05, 0.06))
        floor(material("floor", "DIFFUSE", (0.6, 0.6, 0.6)), size=8.0)
        sphere(material("ball", "DIFFUSE", (0.7, 0.5, 0.3)), (0.0, 0.4, 0.4), radius=0.4)
        light("POINT", (-1.2, 0.0, 0.7), (-1.2, 0.0, 0.0), energy=60.0, shadow_soft_size=0.5,
              use_soft_falloff=False)
        light("SPOT", (1.0, -0.2, 0.9), (1.0, 0.3, 0.0), energy=80.0, shadow_soft_size=0.3,
              spot_size=math.radians(70), use_soft_falloff=False)
        light("POINT", (0.0, 1.5, 1.2), (0.0, 1.5, 0.0), energy=30.0, shadow_soft_size=0.4)
        camera((0.0, -4.0, 2.0), (0, 0.3, 0.4), lens=35)
    elif name == "warned":
        # Things KD Trace does not render, each to be named in a warning (export only).
        w = bpy.data.worlds.new("sky world")
        w.use_nodes = True
        sky_node = w.node_tree.nodes.new("ShaderNodeTexSky")
        sky_node.sky_type = "HOSEK_WILKIE"              # the one model KD Trace lacks
        w.node_tree.links.new(sky_node.outputs["Color"], w.node_tree.nodes["Background"].inputs["Color"])
        bpy.context.scene.world = w
        coat = material("brushed", color=(0.5, 0.5, 0.8), **{"Anisotropic": 0.5,
                                                             "Subsurface Weight": 0.3,
                                                             "Sheen Weight": 0.4})
        bump = coat.node_tree.nodes.new("ShaderNodeBump")
        cells = coat.node_tree.nodes.new("ShaderNodeTexGabor")       # a height not evaluated
        coat.node_tree.links.new(cells.outputs["Value"], bump.inputs["Height"])
        coat.node_tree.links.new(bump.outputs["Normal"],
                                 coat.node_tree.nodes["Principled BSDF"].inputs["Normal"])
        sphere(coat, (0, 0, 0.5), radius=0.5).name = "brushed ball"
        toon = bpy.data.materials.new("toon")
        toon.use_nodes = True
        node = toon.node_tree.nodes.new("ShaderNodeBsdfToon")
        toon.node_tree.links.new(node.outputs[0], toon.node_tree.nodes["Material Output"].inputs["Surface"])
        floor(toon).name = "toon floor"
        noisy, nodes, links, bsdf = node_material("noisy")
        gabor = nodes.new("ShaderNodeTexGabor")
        links.new(gabor.outputs["Value"], bsdf.inputs["Base Color"])
        fog = nodes.new("ShaderNodeVolumePrincipled")      # a volume and a displacement: named
        links.new(fog.outputs[0], nodes["Material Output"].inputs["Volume"])
        lift = nodes.new("ShaderNodeDisplacement")
        links.new(gabor.outputs["Value"], lift.inputs["Height"])
        links.new(lift.outputs[0], nodes["Material Output"].inputs["Displacement"])
        add(bpy.ops.mesh.primitive_cube_add, noisy, size=0.4, location=(-1.5, 0.0, 0.2)).name = "noisy cube"
        light("AREA", (0, 0, 3), (0, 0, 0), energy=100.0, size=1.0, spread=math.radians(60))
        bpy.data.objects["area"].name = "narrow area"
        # A UV Map node naming a second UV map (KD Trace carries one per mesh).
        second, nodes, links, bsdf = node_material("second uvs")
        uv_map = nodes.new("ShaderNodeUVMap")
        uv_map.uv_map = "second"
        checker = nodes.new("ShaderNodeTexChecker")
        links.new(uv_map.outputs["UV"], checker.inputs["Vector"])
        links.new(checker.outputs["Color"], bsdf.inputs["Base Color"])
        two_maps = add(bpy.ops.mesh.primitive_cube_add, second, size=0.3, location=(0.8, -0.8, 0.15))
        two_maps.name = "two maps"
        two_maps.data.uv_layers.new(name="second")
        # Motion blur of an object moved by its parent is named, not rendered.
        mover = add(bpy.ops.mesh.primitive_cube_add, material("box"), size=0.5,
                    location=(1.5, 0.0, 0.25))
        mover.name = "moving box"
        bpy.ops.object.empty_add(location=(0.0, 0.0, 0.0))
        carrier = bpy.context.object
        mover.parent = carrier
        keyframes(carrier, "location", {0: (0.0, 0.0, 0.0), 2: (0.0, 1.0, 0.0)})
        # A half turn within the shutter (frames 0.75 to 1.25, keyed at both): its linear
        # blend would pass a singular matrix.
        spinner = add(bpy.ops.mesh.primitive_cube_add, material("box"), size=0.3,
                      location=(-0.8, 0.8, 0.15))
        spinner.name = "spinning box"
        keyframes(spinner, "rotation_euler", {0.75: (0.0, 0.0, 0.0), 1.25: (0.0, 0.0, math.pi)})
        scene.render.use_motion_blur = True
        scene.render.motion_blur_shutter = 0.5
        scene.render.motion_blur_position = "CENTER"
        scene.frame_set(1)
        camera((0.0, -4.0, 1.5), (0, 0, 0.5))
    bpy.context.view_layer.update()


def read_exr(path, width, height):
    image = bpy.data.images.load(path)
    pixels = np.array(image.pixels[:], np.float32).reshape(height, width, 4)[::-1]
    bpy.data.images.remove(image)
    return pixels


def save_side_by_side(name, width, height):
    """<scene>.png: Cycles left, KD Trace right, as the Standard view transform shows them."""
    linear = np.concatenate([np.load(f"{OUT}/{name}-{who}.npy")[..., :3]
                             for who in ("cycles", "kdtrace")], axis=1)
    c = np.clip(linear, 0, 1)
    srgb = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)
    rgba = np.concatenate([srgb, np.ones(srgb.shape[:2] + (1,))], -1)[::-1]   # bottom row first
    image = bpy.data.images.new(f"{name}-side-by-side", 2 * width, height)
    image.pixels.foreach_set(rgba.astype(np.float32).ravel())
    image.filepath_raw = f"{OUT}/{name}.png"
    image.file_format = "PNG"
    image.save()
    bpy.data.images.remove(image)


scene = bpy.context.scene
width, height = args["width"], args["height"]
warnings, timings = {}, {}
for name in args["scenes"]:
    build(name)
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    settings = dict(args["kdtrace"], **args.get("per_scene", {}).get(name, {}))
    geometry, view, _ = export.export_view(bpy.context.evaluated_depsgraph_get())
    rendered, rendered_view, info = rendered_scene(bpy.context.evaluated_depsgraph_get())
    warnings[name] = info["warnings"]
    with open(f"{OUT}/{name}-features.json", "w") as f:
        json.dump(sorted(rendered.features(rendered_view)), f)
    np.savez(f"{OUT}/{name}-scene.npz", **geometry.arrays())
    with open(f"{OUT}/{name}-view.json", "w") as f:
        json.dump(view.to_dict(), f)
    if name == "warned":
        continue

    scene.render.engine = "CYCLES"
    cycles = scene.cycles
    cycles.device = "CPU"
    cycles.samples = settings["samples_per_axis"] ** 2      # the same samples as ours
    cycles.use_adaptive_sampling = False
    cycles.use_denoising = False
    cycles.pixel_filter_type = settings["pixel_filter"]     # Cycles' default, as ours
    cycles.filter_width = settings["filter_width"]
    cycles.seed = 1
    cycles.max_bounces = settings["max_bounces"]
    cycles.diffuse_bounces = settings["diffuse_bounces"]
    cycles.glossy_bounces = settings["glossy_bounces"]
    cycles.transmission_bounces = settings["transmission_bounces"]
    cycles.transparent_max_bounces = settings["transparent_bounces"]
    cycles.sample_clamp_direct = settings["clamp_direct"]
    cycles.sample_clamp_indirect = settings["clamp_indirect"]
    cycles.blur_glossy = settings["filter_glossy"]
    import time
    started = time.perf_counter()
    scene.render.filepath = f"{OUT}/{name}-cycles.exr"
    bpy.ops.render.render(write_still=True)
    timings[f"{name}-cycles"] = time.perf_counter() - started
    np.save(f"{OUT}/{name}-cycles.npy", read_exr(f"{OUT}/{name}-cycles.exr", width, height))

    scene.render.engine = "KDTRACE"
    props = scene.kdtrace
    props.use_zeroconf = False
    props.local_slaves = 2
    props.tile_size = 32
    props.use_denoising = False         # as Cycles here
    for key, value in settings.items():
        setattr(props, key, value)
    started = time.perf_counter()
    scene.render.filepath = f"{OUT}/{name}-kdtrace.exr"
    bpy.ops.render.render(write_still=True)
    timings[f"{name}-kdtrace"] = time.perf_counter() - started
    np.save(f"{OUT}/{name}-kdtrace.npy", read_exr(f"{OUT}/{name}-kdtrace.exr", width, height))
    if args.get("side_by_side"):
        save_side_by_side(name, width, height)
write_result(result_path, {"warnings": warnings, "timings": timings})
