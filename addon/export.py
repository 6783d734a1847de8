"""Blender's evaluated depsgraph -> core.scene (Geometry, Shading, View): the entry points
(export_view, export_instanced_view), the view's settings, and the depsgraph's mesh objects and
instances gathered into geometry (docs/instances.md).

The export's other jobs have modules of their own: meshes.py (a mesh's arrays, gathered into one
Geometry), materials.py (the material table, placements), nodes.py and node_program.py
(material node trees), lighting.py (lights, the world), camera.py (the camera, the image size
and border), motion.py (the shutter). Meshes shared by several instances are read once.
Warnings (what of a material, light, world or camera is not rendered, and cleaned geometry:
skipped empty meshes, dropped zero-area faces) are returned in the info dict under "warnings"
for the render engine to report. Optional geometry arrays (corner normals, UVs, textures) are
exported only when the scene needs them (core/scene/features.py).
"""
from __future__ import annotations

import dataclasses
import numpy as np

from ..core.frame.exported import InstancedExport
from ..core.layout import VISIBILITY_CODES
from ..core.scene.instances import blend_stays_invertible
from ..core.scene.spatial_order import spatial_order
from ..core.scene.features import needed_arrays, scene_features, strip_geometry
from ..core.scene.model import MIST, MIST_FALLOFFS, Geometry, RenderSettings, Shading, View
from .camera import export_camera, render_region, render_size
from .lighting import export_lights, export_world
from .materials import MaterialTable, Placement, object_random_id
from .meshes import MeshParts, mesh_arrays, render_uv_layer
from .motion import is_animated, motion_warnings, over_shutter


def export_view(depsgraph) -> tuple[Geometry, View, dict]:
    """Export everything a render needs, every instance realised in world space. Returns
    (geometry, view, info): info has "warnings" (a list of messages for the user)."""
    geometry, view, warnings, _ = _export(depsgraph, instanced=False)
    # Only what the scene needs travels (and the kernel compiles only that).
    geometry = strip_geometry(geometry, scene_features(geometry, view))
    return geometry, view, {"warnings": warnings}


def export_instanced_view(depsgraph, every_object: bool = False, viewport=None
                          ) -> tuple[InstancedExport, View, dict]:
    """export_view with the instances of shared meshes kept as instances (each mesh
    exported once, in object space). `every_object` (an animation render): an object of its
    own mesh is an instance too, so when it only moves its mesh and kd-tree stay the same.
    With Motion Blur on, an object whose transform changes over the shutter is an instance
    with its transforms at shutter open and close (docs/instances.md, object motion blur).
    `viewport`: (camera, width, height) of a 3D viewport, seen instead of the scene camera
    (addon/viewport.py)."""
    (meshes, instance_mesh, to_world, to_world_end), view, warnings, materials = _export(
        depsgraph, True, every_object, viewport)
    texels, sizes = materials.texture_arrays()
    features = frozenset().union(*(scene_features(
        Geometry(m.vertices, m.triangles, m.material_ids, m.normals, m.uvs, texels, sizes), view)
        for m in meshes))
    if "texels" not in needed_arrays(features):
        texels = sizes = None
    return (InstancedExport([strip_geometry(m, features) for m in meshes], instance_mesh,
                            to_world, texels, sizes, to_world_end), view, {"warnings": warnings})


def _export(depsgraph, instanced: bool, every_object: bool = False, viewport=None):
    scene = depsgraph.scene
    warnings = []
    materials = MaterialTable(warnings)
    # The world first: its Environment Texture joins the material textures in one table.
    world_color, world_texture = export_world(scene, materials, warnings)
    motion_handled = set()   # objects whose motion the geometry blurred (or warned of)
    geometry = _export_geometry(depsgraph, materials, warnings, instanced, every_object,
                                motion_handled)
    shading = Shading(materials.colors(), export_lights(depsgraph, warnings), world_color,
                      materials.params(), world_texture, np.array(materials.node_rows, np.float32))
    if viewport is None:
        view = View(export_camera(depsgraph, warnings), *render_size(scene), shading,
                    render_region(scene), render_settings(scene),
                    bool(scene.render.film_transparent), mist_settings(scene))
    else:
        camera, width, height = viewport
        view = View(camera, width, height, shading, (0, 0, width, height),
                    render_settings(scene), bool(scene.render.film_transparent))
    motion_warnings(depsgraph, warnings, motion_handled)
    _missing_warnings(scene, warnings)
    return geometry, view, warnings, materials


def mist_settings(scene) -> tuple:
    """World > Mist Pass as core's View.mist: (start, depth, falloff power); Blender's defaults
    without a world, as Cycles."""
    if scene.world is None:
        return MIST
    mist = scene.world.mist_settings
    return float(mist.start), float(mist.depth), MIST_FALLOFFS[mist.falloff]


def _missing_warnings(scene, warnings: list) -> None:
    """One warning naming the objects that are placeholders of linked data Blender could not
    load (a missing library file): they are not rendered, as in Cycles."""
    missing = sorted(obj.name for obj in scene.objects
                     if obj.is_missing or (obj.data is not None and obj.data.is_missing))
    if missing:
        warnings.append("linked from a missing library, not rendered: "
                        + ", ".join(f"object '{name}'" for name in missing))


def render_settings(scene) -> RenderSettings:
    """Sampling and bounces from the KD Trace panel (scene.kdtrace): every RenderSettings field
    is a property of the same name there (tests/bpy_scripts/draw_panels.py checks it)."""
    props = scene.kdtrace
    return RenderSettings(**{name: getattr(props, name) for name in RenderSettings().to_dict()})


def _export_geometry(depsgraph, materials: MaterialTable, warnings: list,
                     instanced: bool = False, every_object: bool = False, motion_handled=None):
    """All visible mesh geometry (objects and instances). NaN/inf vertices are rejected
    (naming the object); empty meshes are skipped and zero-area faces dropped, each with a
    warning naming the object.

    Not `instanced`: one Geometry of world-space triangles. `instanced` (docs/instances.md):
    (meshes, instance_mesh, to_world, to_world_end): the instances of one evaluated mesh with the same
    materials share one object-space Geometry (read and exported once); mesh 0 holds the
    world-space triangles of everything realised (placed by the identity): meshes used by one
    instance only (unless `every_object`), and objects whose materials need world space
    (MaterialTable.world_space: emission, node programs). The textures are in none of the
    meshes. With Motion Blur on, objects whose own transform changes over the shutter are
    instances (even of a mesh used once) with their transforms at shutter open and close
    (to_world_end; None when nothing moves), their names added to `motion_handled` (and the
    names of those it cannot blend, with a warning)."""
    mesh_cache = {}  # evaluated mesh pointer -> arrays, so instances of one mesh are read once
    warned = set()
    placed = []      # (object name, arrays, slot materials, matrix, end matrix or None, textured,
    #                   shared key or None)
    scene = depsgraph.scene
    blur = instanced and motion_handled is not None and scene.render.use_motion_blur
    for instance in depsgraph.object_instances:
        obj = instance.object
        if obj.type != "MESH" or not instance.show_self:
            continue
        mesh, name = obj.data, _instance_name(instance)
        matrix = np.array(instance.matrix_world, np.float64)
        if not np.isfinite(matrix).all():
            if name not in warned:
                warned.add(name)
                warnings.append(f"object '{name}' has a transform that is NaN or infinite; "
                                "skipped")
            continue
        visibility = object_visibility(obj)
        placement = Placement(matrix, mesh.texspace_location, mesh.texspace_size, obj,
                              instance.random_id if instance.is_instance else object_random_id(obj.name))
        slot_materials = np.array(
            [materials.index(slot.material, name, visibility, placement)
             for slot in obj.material_slots]
            or [materials.index(None, name, visibility)], np.uint16)
        textured = any(materials.uses_texture(slot.material) for slot in obj.material_slots)
        _warn_other_uv_maps(obj, mesh, name, materials, warnings, warned)
        key = (mesh.as_pointer(), textured, tuple(materials.attributes))
        if key not in mesh_cache:
            mesh_cache[key] = mesh_arrays(mesh, True, textured, materials.attributes)
        arrays = mesh_cache[key]
        if len(arrays["triangles"]) == 0:
            if name not in warned:
                warned.add(name)
                warnings.append(f"object '{name}' has no faces; skipped")
            continue
        shareable = instanced and abs(np.linalg.det(matrix[:3, :3])) > 0 and \
            not any(materials.world_space(i) for i in slot_materials)
        end = None
        if blur and shareable and not instance.is_instance and is_animated(obj):
            ends, _ = over_shutter(scene, obj)     # a problem: warned (motion_warnings)
            if ends is not None and not np.allclose(ends[0], ends[1], rtol=0, atol=1e-9):
                if blend_stays_invertible(ends[0][None], ends[1][None])[0]:
                    matrix, end = ends
                    motion_handled.add(obj.name)
                else:
                    warnings.append(f"object '{obj.name}': motion blur is not rendered (it "
                                    "turns or scales through zero within the shutter)")
                    motion_handled.add(obj.name)       # warned here, not again
        placed.append((name, arrays, slot_materials, matrix, end, textured,
                       (key, slot_materials.tobytes()) if shareable else None))
    uses = {}
    for *_, shared in placed:
        uses[shared] = uses.get(shared, 0) + 1
    world = MeshParts(warnings, warned)
    meshes, instance_mesh, to_world, to_world_end = {}, [], [], []   # shared key -> its parts
    for name, arrays, slot_materials, matrix, end, textured, shared in placed:
        if shared is None or (uses[shared] < (1 if every_object else 2) and end is None):
            world.add(name, arrays, slot_materials, matrix, textured)
            continue
        if shared not in meshes:
            meshes[shared] = MeshParts(warnings, warned)
            meshes[shared].add(name, arrays, slot_materials, np.eye(4), textured)
        if not meshes[shared].empty:
            instance_mesh.append(shared)
            to_world.append(matrix)
            to_world_end.append(matrix if end is None else end)
    with_uvs = bool(materials.textures) or bool(materials.node_rows)  # textures, node programs
    realised = world.geometry(with_uvs)
    # Color Attribute / Attribute nodes read the realised triangles' corners (node programs put
    # their objects there: mesh 0 of an instanced export) by triangle index: those triangles go
    # in spatial order here already (the frame session finds them sorted and keeps the order,
    # core/scene/spatial_order.py), so that the corner arrays stay with their triangles.
    corners = world.corner_attributes(materials.attributes)
    if corners:
        realised, order = spatial_order(realised)
        corners = {name: values if order is None else values[order]
                   for name, values in corners.items()}
    materials.fill_attributes(corners)
    texels, sizes = materials.texture_arrays()
    if not instanced:
        return dataclasses.replace(realised, texels=texels, texture_sizes=sizes)
    kept = {k: i for i, k in enumerate(k for k, parts in meshes.items() if not parts.empty)}
    instance_mesh = [kept[k] for k in instance_mesh]
    out = [meshes[k].geometry(with_uvs) for k in kept]
    if not world.empty or not out:      # the realised triangles: mesh 0, placed by the identity
        out.insert(0, realised)
        instance_mesh = [0] + [m + 1 for m in instance_mesh]
        to_world = [np.eye(4)] + to_world
        to_world_end = [np.eye(4)] + to_world_end
    moving = any(end is not None for _, _, _, _, end, _, _ in placed)
    ends = np.array(to_world_end, np.float64).reshape(-1, 4, 4) if moving else None
    return out, np.array(instance_mesh, np.int64), np.array(to_world, np.float64).reshape(-1, 4, 4), \
        ends


def _warn_other_uv_maps(obj, mesh, name, materials, warnings, warned) -> None:
    """One warning for an object whose material's UV Map node names a UV map other than the
    one exported (render_uv_layer): KD Trace carries one UV map per mesh."""
    layer = render_uv_layer(mesh)
    for slot in obj.material_slots:
        key = slot.material.name_full if slot.material is not None else None
        other = sorted(m for m in materials.named_uv_maps.get(key, ()) if
                       layer is None or m != layer.name)
        if other and (name, "uv") not in warned:
            warned.add((name, "uv"))
            warnings.append(f"object '{name}': material '{slot.material.name}' reads UV map(s) "
                            f"{', '.join(repr(m) for m in other)}; KD Trace renders one UV map "
                            f"per mesh, {layer.name if layer else 'none'!r}")


def _instance_name(instance) -> str:
    """The name warnings give an instance: its object's, else (the evaluated mesh of a
    metaball or curve can have none) the name of the object that makes it."""
    name = instance.object.name
    if not name and instance.parent is not None:
        name = instance.parent.name
    return name or "(unnamed)"


def object_visibility(obj) -> int:
    """The object's ray visibility (Object > Visibility > Ray Visibility) and holdout as
    core/layout.py VISIBILITY_CODES bits."""
    bits = 0
    for ray in ("camera", "diffuse", "glossy", "transmission", "shadow"):
        if getattr(obj, f"visible_{ray}", True):
            bits |= VISIBILITY_CODES[ray.upper()]
    if getattr(obj, "is_holdout", False):
        bits |= VISIBILITY_CODES["HOLDOUT"]
    return bits
