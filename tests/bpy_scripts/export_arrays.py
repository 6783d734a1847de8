"""The installed add-on's mesh reader (meshes.mesh_arrays, Blender's attribute arrays) against
Blender's per-element reads of the same evaluated meshes (loop_triangles' vertices,
material_index, split_normals, and the UV map at each triangle's loops): meshes of quads and
an n-gon, of triangles only, with material slots per face, custom normals, flat and smooth
faces and a UV map. Reports, per mesh, whether each array is equal and its shape, and the
lengths of what it reads from a mesh of edges only."""
import importlib

import bpy
import bmesh     # (after bpy: the bpy module provides it)
import numpy as np

from blender_setup import arguments, install_extension, write_result

args, result_path = arguments()
install_extension(args["zip"])
meshes = importlib.import_module("bl_ext.user_default.kdtrace.addon.meshes")
scene = bpy.context.scene


def add_mesh(name, build):
    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    build(bm)
    bm.to_mesh(mesh)
    bm.free()
    obj = bpy.data.objects.new(name, mesh)
    scene.collection.objects.link(obj)
    for k in range(3):
        obj.data.materials.append(bpy.data.materials.new(f"{name}-{k}"))
    return obj


def quads_and_ngon(bm):
    bmesh.ops.create_cube(bm, size=1.0)
    bmesh.ops.create_circle(bm, cap_ends=True, segments=9, radius=0.7)   # one 9-gon
    bmesh.ops.translate(bm, verts=bm.verts[-9:], vec=(0, 0, 2))


def triangles_only(bm):
    bmesh.ops.create_icosphere(bm, subdivisions=2, radius=1.0)


objects = [add_mesh("quads", quads_and_ngon), add_mesh("triangles", triangles_only),
           add_mesh("custom", triangles_only)]
rng = np.random.default_rng(1)
for obj in objects:
    mesh = obj.data
    mesh.uv_layers.new(name="uv")
    uv = rng.random(len(mesh.loops) * 2).astype(np.float32)
    mesh.uv_layers["uv"].uv.foreach_set("vector", uv)
    mesh.polygons.foreach_set("material_index", rng.integers(0, 3, len(mesh.polygons)).astype(np.int32))
    mesh.polygons.foreach_set("use_smooth", (np.arange(len(mesh.polygons)) % 3 != 0))
    mesh.update()
custom = objects[2].data
normals = rng.normal(size=(len(custom.vertices), 3))
custom.normals_split_custom_set_from_vertices((normals / np.linalg.norm(normals, axis=1)[:, None]).tolist())

depsgraph = bpy.context.evaluated_depsgraph_get()
result = {}
for obj in objects:
    mesh = obj.evaluated_get(depsgraph).data
    ours = meshes.mesh_arrays(mesh, True, True)
    mesh.calc_loop_triangles()
    tris = mesh.loop_triangles

    def per_triangle(attribute, width, dtype, collection=tris):
        values = np.empty(len(collection) * width, dtype)
        collection.foreach_get(attribute, values)
        return values
    loops = per_triangle("loops", 3, np.int32)
    uv = np.empty(len(mesh.loops) * 2, np.float32)
    mesh.uv_layers.active.uv.foreach_get("vector", uv)
    reference = {
        "vertices": per_triangle("co", 3, np.float32, mesh.vertices).reshape(-1, 3),
        "triangles": per_triangle("vertices", 3, np.int32).reshape(-1, 3),
        "slots": per_triangle("material_index", 1, np.int32),
        "normals": per_triangle("split_normals", 9, np.float32).reshape(-1, 3, 3),
        "uvs": uv.reshape(-1, 2)[loops].reshape(-1, 3, 2)}
    result[obj.name] = {
        name: {"equal": bool(ours[name] is not None and ours[name].shape == ref.shape
                             and np.array_equal(ours[name], ref)),
               "shape": list(ref.shape), "distinct": len(np.unique(ref))}
        for name, ref in reference.items()}
    result[obj.name]["all_triangles"] = len(mesh.loops) == 3 * len(mesh.polygons)
# A mesh of vertices and edges only has no corner attributes: no triangles.
wire = bpy.data.meshes.new("wire")
wire.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [(0, 1), (1, 2)], [])
result["wire"] = {name: len(value) for name, value in meshes.mesh_arrays(wire, True, True).items()
                  if value is not None}
write_result(result_path, result)
