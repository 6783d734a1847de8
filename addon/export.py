"""Blender's evaluated depsgraph -> core.scene (Geometry, Shading, View).

The only module that reads Blender scene data. Mesh data is read with foreach_get into numpy
(no Python loop per vertex or face); meshes shared by several instances are read once.
"""
from __future__ import annotations

import math
import time

import numpy as np

from ..core.scene import Camera, Geometry, Light, MAX_MATERIALS, SceneError, Shading, View

DEFAULT_COLOR = (0.8, 0.8, 0.8, 1.0)


def export_view(depsgraph) -> tuple[Geometry, View, dict]:
    """Export everything a render needs. Returns (geometry, view, timings)."""
    started = time.perf_counter()
    scene = depsgraph.scene
    materials = _MaterialTable()
    geometry = _export_geometry(depsgraph, materials)
    exported = time.perf_counter()
    shading = Shading(materials.colors(), _export_lights(depsgraph), _world_color(scene))
    view = View(_export_camera(depsgraph), *render_size(scene), shading, render_region(scene))
    return geometry, view, {"export_seconds": exported - started}


def render_size(scene) -> tuple[int, int]:
    """The image size in pixels after the resolution percentage."""
    r = scene.render
    return (max(1, r.resolution_x * r.resolution_percentage // 100),
            max(1, r.resolution_y * r.resolution_percentage // 100))


def render_region(scene) -> tuple[int, int, int, int]:
    """The render border as (x0, y0, x1, y1) pixels, top-left origin; the whole image without one."""
    width, height = render_size(scene)
    r = scene.render
    if not r.use_border:
        return (0, 0, width, height)
    x0, x1 = int(r.border_min_x * width), int(r.border_max_x * width)
    # Blender's border is measured from the bottom; ours from the top.
    y0, y1 = height - int(r.border_max_y * height), height - int(r.border_min_y * height)
    if x1 <= x0 or y1 <= y0:
        raise SceneError("the render border is empty")
    return (x0, y0, x1, y1)


class _MaterialTable:
    """Maps Blender materials to indices into one table of base colours."""

    def __init__(self):
        self._index = {None: 0}
        self._colors = [DEFAULT_COLOR]

    def index(self, material) -> int:
        key = material.name_full if material is not None else None
        if key not in self._index:
            if len(self._colors) >= MAX_MATERIALS:
                raise SceneError(f"the scene uses more than {MAX_MATERIALS} materials")
            self._index[key] = len(self._colors)
            self._colors.append(base_color(material))
        return self._index[key]

    def colors(self) -> np.ndarray:
        return np.array(self._colors, np.float32)


def base_color(material) -> tuple:
    """The Principled BSDF's base colour (unlinked input), else the viewport colour."""
    if material.use_nodes and material.node_tree:
        for node in material.node_tree.nodes:
            if node.type == "BSDF_PRINCIPLED":
                return tuple(node.inputs["Base Color"].default_value)
    return tuple(material.diffuse_color)


def _mesh_arrays(mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (V,3) float32, triangles (T,3) uint32 and per-triangle slot indices of a mesh."""
    mesh.calc_loop_triangles()
    vertices = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", vertices)
    triangles = np.empty(len(mesh.loop_triangles) * 3, np.int32)
    mesh.loop_triangles.foreach_get("vertices", triangles)
    slots = np.empty(len(mesh.loop_triangles), np.int32)
    mesh.loop_triangles.foreach_get("material_index", slots)
    return vertices.reshape(-1, 3), triangles.reshape(-1, 3), slots


def _export_geometry(depsgraph, materials: _MaterialTable) -> Geometry:
    """All visible mesh geometry (objects and instances) as world-space triangles."""
    mesh_cache = {}  # evaluated mesh pointer -> arrays, so instances of one mesh are read once
    parts_v, parts_t, parts_m = [], [], []
    vertex_count = 0
    for instance in depsgraph.object_instances:
        obj = instance.object
        if obj.type != "MESH" or not instance.show_self:
            continue
        mesh = obj.data
        key = mesh.as_pointer()
        if key not in mesh_cache:
            mesh_cache[key] = _mesh_arrays(mesh)
        vertices, triangles, slots = mesh_cache[key]
        if len(triangles) == 0:
            continue
        matrix = np.array(instance.matrix_world, np.float64)
        world = vertices.astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
        if not np.isfinite(world).all():
            raise SceneError(f"object '{obj.name}' has vertices that are NaN or infinite")
        slot_materials = np.array(
            [materials.index(slot.material) for slot in obj.material_slots] or [0], np.uint16)
        parts_v.append(world.astype(np.float32))
        parts_t.append(triangles.astype(np.uint32) + vertex_count)
        parts_m.append(slot_materials[np.clip(slots, 0, len(slot_materials) - 1)])
        vertex_count += len(vertices)
    if not parts_t:
        return Geometry(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32),
                        np.zeros(0, np.uint16))
    return Geometry(np.concatenate(parts_v), np.concatenate(parts_t), np.concatenate(parts_m))


def _export_camera(depsgraph) -> Camera:
    scene = depsgraph.scene
    if scene.camera is None:
        raise SceneError("the scene has no active camera")
    camera = scene.camera.evaluated_get(depsgraph)
    width, height = render_size(scene)
    r = scene.render
    # Blender's own projection already holds sensor fit, shift and pixel aspect.
    projection = np.array(camera.calc_matrix_camera(
        depsgraph, x=width, y=height, scale_x=r.pixel_aspect_x, scale_y=r.pixel_aspect_y))
    data = camera.data
    sx, sy = 1.0 / projection[0, 0], 1.0 / projection[1, 1]
    if data.type == "ORTHO":
        kind, offset = "ORTHO", (-projection[0, 3] * sx, -projection[1, 3] * sy)
    elif data.type == "PERSP":
        kind, offset = "PERSP", (projection[0, 2] * sx, projection[1, 2] * sy)
    else:
        raise SceneError(f"camera type {data.type} is not supported (use perspective or orthographic)")
    to_world = np.array(camera.matrix_world.normalized(), np.float64)
    return Camera(kind, to_world, (sx, sy), offset, data.clip_start, data.clip_end)


def _export_lights(depsgraph) -> list:
    lights = []
    for instance in depsgraph.object_instances:
        obj = instance.object
        if obj.type != "LIGHT" or not instance.show_self:
            continue
        data = obj.data
        matrix = np.array(instance.matrix_world, np.float64)
        axes = matrix[:3, :3] / np.maximum(np.linalg.norm(matrix[:3, :3], axis=0), 1e-30)
        scale = np.linalg.norm(matrix[:3, :3], axis=0)
        light = Light(kind=data.type, color=tuple(data.color), power=float(data.energy),
                      position=tuple(matrix[:3, 3]), direction=tuple(-axes[:, 2]),
                      axis_u=tuple(axes[:, 0]), axis_v=tuple(axes[:, 1]))
        if data.type in ("POINT", "SPOT"):
            light.radius = float(data.shadow_soft_size)
        if data.type == "SUN":
            light.radius = float(data.angle)
        if data.type == "SPOT":
            light.spot_size, light.spot_blend = float(data.spot_size), float(data.spot_blend)
        if data.type == "AREA":
            light.shape = data.shape
            light.size_u = float(data.size) * scale[0]
            light.size_v = float(data.size_y if data.shape in ("RECTANGLE", "ELLIPSE") else data.size) * scale[1]
        if not all(math.isfinite(v) for v in light.position + light.direction):
            raise SceneError(f"light '{obj.name}' has a position or direction that is not finite")
        lights.append(light)
    return lights


def _world_color(scene) -> tuple:
    """The world's background colour times strength (node Background), else its viewport colour."""
    world = scene.world
    if world is None:
        return (0.0, 0.0, 0.0)
    if world.use_nodes and world.node_tree:
        for node in world.node_tree.nodes:
            if node.type == "BACKGROUND":
                color, strength = node.inputs["Color"].default_value, node.inputs["Strength"].default_value
                return tuple(float(c) * strength for c in color[:3])
    return tuple(world.color)
