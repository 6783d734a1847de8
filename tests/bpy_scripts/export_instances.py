"""Export a scene of modifiers and instances with the installed add-on's exporter and report
what came out: triangle count and the bounds of every group of triangles."""
import bpy
import numpy as np

from blender_setup import arguments, install_extension, write_result

args, result_path = arguments()
addon = install_extension(args["zip"])
scene = bpy.context.scene

# A cube with an array modifier: 3 cubes side by side (36 triangles).
bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0, 0, 0))
arrayed = bpy.context.object
arrayed.modifiers.new("array", "ARRAY").count = 3

# A collection holding one small cube, instanced twice by empties (2 x 12 triangles).
collection = bpy.data.collections.new("instanced")
cube = bpy.data.objects.new("instanced-cube", bpy.data.meshes.new("instanced-cube"))
cube.data.from_pydata([(x, y, z) for x in (0, 0.5) for y in (0, 0.5) for z in (0, 0.5)], [],
                      [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)])
collection.objects.link(cube)
for x in (10.0, 20.0):
    empty = bpy.data.objects.new(f"instancer-{x}", None)
    empty.instance_type, empty.instance_collection = "COLLECTION", collection
    empty.location = (x, 0, 0)
    scene.collection.objects.link(empty)

# Particle instances: 5 copies of an ico sphere (20 triangles each) on a plane whose own faces
# are hidden in renders.
bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=1, radius=0.1, location=(0, 0, -50))
ico = bpy.context.object
ico.hide_render = True
bpy.ops.mesh.primitive_plane_add(size=2.0, location=(0, 10, 0))
emitter = bpy.context.object
emitter.modifiers.new("particles", "PARTICLE_SYSTEM")
settings = emitter.particle_systems[0].settings
settings.count, settings.frame_start, settings.frame_end = 5, 1, 1
settings.render_type, settings.instance_object = "OBJECT", ico
settings.physics_type = "NO"
# The test exports the viewport depsgraph (a render uses the render one): hide it in both.
emitter.show_instancer_for_render = emitter.show_instancer_for_viewport = False

# Nested collection instances (y < -20): a collection "inner" of one cube (rotated, scaled
# with a mirror), instanced twice in "outer", which is instanced twice: 4 copies of one mesh.
inner = bpy.data.collections.new("inner")
nested = bpy.data.objects.new("nested-cube", bpy.data.meshes.new("nested-cube"))
bpy.ops.mesh.primitive_cube_add(size=1.0)
nested.data = bpy.context.object.data
bpy.data.objects.remove(bpy.context.object)
nested.rotation_euler = (0.3, 0.5, 0.2)
nested.scale = (1.0, -0.6, 1.3)
inner.objects.link(nested)
outer = bpy.data.collections.new("outer")
for k, x in enumerate((0.0, 2.5)):
    empty = bpy.data.objects.new(f"inner-instancer-{k}", None)
    empty.instance_type, empty.instance_collection = "COLLECTION", inner
    empty.location = (x, 0.0, 0.5 * k)
    outer.objects.link(empty)
for k, x in enumerate((0.0, 6.0)):
    empty = bpy.data.objects.new(f"outer-instancer-{k}", None)
    empty.instance_type, empty.instance_collection = "COLLECTION", outer
    empty.location, empty.rotation_euler = (x, -30.0, 0.0), (0.0, 0.0, 0.4 * k)
    scene.collection.objects.link(empty)
# Geometry-nodes instances (y > 90): Instance on Points puts 6 copies of a small cube (hidden
# in renders, at z -80 in the viewport) on a 3 x 2 grid; the host plane itself has no faces then.
bpy.ops.mesh.primitive_cube_add(size=0.2, location=(0, 0, -80))
scattered = bpy.context.object
scattered.hide_render = True
bpy.ops.mesh.primitive_plane_add(size=2.0, location=(0, 100, 0))
host = bpy.context.object
tree = bpy.data.node_groups.new("scatter", "GeometryNodeTree")
tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
grid = tree.nodes.new("GeometryNodeMeshGrid")
grid.inputs["Vertices X"].default_value, grid.inputs["Vertices Y"].default_value = 3, 2
info = tree.nodes.new("GeometryNodeObjectInfo")
info.inputs["Object"].default_value = scattered
on_points = tree.nodes.new("GeometryNodeInstanceOnPoints")
tree.links.new(grid.outputs["Mesh"], on_points.inputs["Points"])
tree.links.new(info.outputs["Geometry"], on_points.inputs["Instance"])
tree.links.new(on_points.outputs["Instances"], tree.nodes.new("NodeGroupOutput").inputs["Geometry"])
host.modifiers.new("scatter", "NODES").node_group = tree

floor = bpy.data.objects.new("floor", bpy.data.meshes.new("floor"))
floor.data.from_pydata([(-5, -36, -1.5), (14, -36, -1.5), (14, -24, -1.5), (-5, -24, -1.5)], [],
                       [(0, 1, 2, 3)])
scene.collection.objects.link(floor)
sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
sun.rotation_euler = (0.5, 0.3, 0.0)
scene.collection.objects.link(sun)

camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
camera.location, camera.rotation_euler = (4.0, -44.0, 7.0), (1.1, 0.0, 0.0)
scene.collection.objects.link(camera)
scene.camera = camera
scene.render.resolution_x, scene.render.resolution_y = 64, 48
scene.frame_set(1)
depsgraph = bpy.context.evaluated_depsgraph_get()
geometry, view, _ = addon.addon.export.export_view(depsgraph)
instanced = addon.addon.export.export_instanced_view(depsgraph)[0]
v = geometry.vertices[geometry.triangles].reshape(-1, 3, 3)
centres = v.mean(axis=1)
groups = {"arrayed": (centres[:, 0] < 5) & (np.abs(centres[:, 1]) < 5) & (centres[:, 2] > -10),
          "instances": (centres[:, 0] > 5) & (centres[:, 1] > -10),
          "particles": (centres[:, 1] > 5) & (centres[:, 1] < 90),
          "instanced object": (centres[:, 2] < -10) & (centres[:, 2] > -60),
          "scattered": centres[:, 1] > 90,
          "nested": centres[:, 1] < -20}


def arrays(g):
    return {"vertices": g.vertices.tolist(), "triangles": g.triangles.tolist(),
            "material_ids": g.material_ids.tolist(),
            "normals": None if g.normals is None else g.normals.tolist()}
write_result(result_path, {
    "triangles": int(geometry.triangle_count),
    "groups": {name: {"triangles": int(mask.sum()),
                      "min": v[mask].reshape(-1, 3).min(0).tolist() if mask.any() else None,
                      "max": v[mask].reshape(-1, 3).max(0).tolist() if mask.any() else None}
               for name, mask in groups.items()},
    "realised": arrays(geometry), "view": view.to_dict(),
    "meshes": [arrays(m) for m in instanced.meshes],
    "instance_mesh": instanced.instance_mesh.tolist(),
    "to_world": instanced.to_world.tolist()})
