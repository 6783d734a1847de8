"""Light units and falloff measured against Cycles.

Cycles (inside the bpy module, in a subprocess: bpy can be imported once per process) renders a
diffuse plane lit by one light of each kind with direct light only and a black world; our
render_tile renders the same numbers; lit pixels must agree within a few percent.
"""
from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from kdtrace.core.accel.kdtree import KDTree
from kdtrace.core.scene.model import Camera, Geometry, Light, RenderSettings, Shading, View
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.tracer import Tracer
from tests.meshes import grid_plane

SIZE = 32               # image side in pixels
ORTHO_SCALE = 8.0       # the camera sees an 8 x 8 m square of the plane
ALBEDO = 0.8
PLANE = 20.0

# name -> Blender light settings (type, location, rotation in degrees, data properties)
LIGHTS = {
    "POINT": ("POINT", (0.5, 0.3, 1.5), (0, 0, 0), {"energy": 100.0}),
    "SUN": ("SUN", (0, 0, 5), (30, 20, 0), {"energy": 3.0, "angle": 0.0}),
    "SPOT": ("SPOT", (0.2, -0.1, 2.5), (15, 0, 0),
             {"energy": 200.0, "spot_size": math.radians(70), "spot_blend": 0.4}),
    "AREA": ("AREA", (0.3, 0.0, 2.0), (20, 0, 0),
             {"energy": 60.0, "shape": "SQUARE", "size": 0.05}),
}

CYCLES_SCRIPT = textwrap.dedent("""
    import json, sys
    import bpy
    import numpy as np
    name, kind, location, rotation, props, out = json.loads(sys.argv[1])
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 64
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = 0                # direct light only
    scene.cycles.pixel_filter_type = "BOX"
    scene.cycles.filter_width = 0.01            # sample at the pixel centre
    scene.render.resolution_x = scene.render.resolution_y = %(size)d
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = False
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    world = bpy.data.worlds.new("black")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    scene.world = world

    bpy.ops.mesh.primitive_plane_add(size=%(plane)r, location=(0, 0, 0))
    material = bpy.data.materials.new("diffuse")
    material.use_nodes = True
    nodes = material.node_tree.nodes
    nodes.clear()
    diffuse = nodes.new("ShaderNodeBsdfDiffuse")
    diffuse.inputs["Color"].default_value = (%(albedo)r, %(albedo)r, %(albedo)r, 1.0)
    output = nodes.new("ShaderNodeOutputMaterial")
    material.node_tree.links.new(diffuse.outputs["BSDF"], output.inputs["Surface"])
    bpy.context.object.data.materials.append(material)

    camera_data = bpy.data.cameras.new("camera")
    camera_data.type = "ORTHO"
    camera_data.ortho_scale = %(ortho)r
    camera = bpy.data.objects.new("camera", camera_data)
    camera.location = (0, 0, 5)
    scene.collection.objects.link(camera)
    scene.camera = camera

    light_data = bpy.data.lights.new("light", kind)
    for key, value in props.items():
        setattr(light_data, key, value)
    if kind in ("POINT", "SPOT"):
        light_data.shadow_soft_size = 0.0       # a true point light
        if hasattr(light_data, "use_soft_falloff"):
            light_data.use_soft_falloff = False
    light = bpy.data.objects.new("light", light_data)
    light.location = location
    light.rotation_euler = [r * 3.141592653589793 / 180 for r in rotation]
    scene.collection.objects.link(light)
    bpy.context.view_layer.update()
    direction = light.matrix_world.to_3x3() @ __import__("mathutils").Vector((0, 0, -1))

    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = out + ".exr"
    bpy.ops.render.render(write_still=True)
    image = bpy.data.images.load(out + ".exr")
    pixels = np.array(image.pixels[:], np.float32).reshape(%(size)d, %(size)d, 4)[::-1]
    np.save(out + ".npy", pixels)               # rows top first, as ours
    with open(out + ".json", "w") as f:
        json.dump({"position": list(light.matrix_world.translation),
                   "direction": list(direction.normalized())}, f)
""") % {"size": SIZE, "plane": PLANE, "albedo": ALBEDO, "ortho": ORTHO_SCALE}


def render_cycles(name, tmp_path):
    kind, location, rotation, props = LIGHTS[name]
    out = str(tmp_path / name)
    args = json.dumps([name, kind, location, rotation, props, out])
    result = subprocess.run([sys.executable, "-c", CYCLES_SCRIPT, args], capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    with open(out + ".json") as f:
        placed = json.load(f)
    return np.load(out + ".npy"), placed


def render_ours(tracer, name, placed, supersample=8):
    """Our render averaged over supersample^2 points per pixel: Cycles' pixels average over
    the pixel's area, which matters where the light changes fast (the spot cone's edge)."""
    kind, _, _, props = LIGHTS[name]
    light = Light(kind, (1.0, 1.0, 1.0), props["energy"], tuple(placed["position"]),
                  tuple(placed["direction"]), spot_size=props.get("spot_size", math.pi),
                  spot_blend=props.get("spot_blend", 0.0), size_u=props.get("size", 1.0),
                  size_v=props.get("size", 1.0))
    to_world = np.eye(4)
    to_world[2, 3] = 5.0
    camera = Camera("ORTHO", to_world, (ORTHO_SCALE / 2, ORTHO_SCALE / 2), (0, 0), 0.1, 100.0)
    side = SIZE * supersample
    view = View(camera, side, side, Shading(np.array([[ALBEDO, ALBEDO, ALBEDO, 1]], np.float32),
                                            [light], (0.0, 0.0, 0.0)),
                settings=RenderSettings(samples_per_axis=1, adaptive=False))
    image = tracer.render_tile(view, 0, 0, side, side)["combined"]
    return image.reshape(SIZE, supersample, SIZE, supersample, 4).mean(axis=(1, 3))


@pytest.fixture(scope="module")
def plane_tracer():
    vertices, triangles = grid_plane(PLANE, 1, 0.0)
    tracer = Tracer()
    # Two triangles: a single leaf is the whole tree.
    tree = KDTree(np.array([[(2 << 2) | 3, 0]], np.uint32), np.arange(2, dtype=np.uint32),
                  np.array([vertices.min(0), vertices.max(0)], np.float32))
    tracer.load(Scene.from_parts(Geometry(vertices, triangles, np.zeros(2, np.uint16)), tree))
    return tracer


@pytest.mark.parametrize("name", list(LIGHTS))
def test_light_matches_cycles(plane_tracer, name, tmp_path):
    cycles, placed = render_cycles(name, tmp_path)
    ours = render_ours(plane_tracer, name, placed)
    assert np.isfinite(ours).all()
    ref, got = cycles[..., 0], ours[..., 0]
    lit = ref > 0.05 * ref.max()
    assert lit.sum() > 50, "the light should light a good part of the image"
    ratio = got[lit] / ref[lit]
    print(f"{name}: {lit.sum()} lit pixels, ours/Cycles median {np.median(ratio):.4f}, "
          f"range {ratio.min():.4f}..{ratio.max():.4f}")
    assert np.median(np.abs(ratio - 1)) < 0.02, f"{name}: median ratio {np.median(ratio):.4f}"
    assert np.mean(np.abs(ratio - 1) < 0.04) > 0.95, (
        f"{name}: ratio range {ratio.min():.4f}..{ratio.max():.4f}")
    # Unlit stays dark in both.
    if (~lit).any():
        assert np.abs(got[~lit] - ref[~lit]).max() < 0.1 * ref.max()
