"""Blender's evaluated depsgraph -> core.scene (Geometry, Shading, View).

The only module that reads Blender scene data. Mesh data is read with foreach_get into numpy
(no Python loop per vertex or face); meshes shared by several instances are read once.

Materials map onto core.scene's material parameters and node programs through addon/nodes.py
(docs/shading.md); a node setup that cannot be mapped falls back to its base colour with one
warning per material. Warnings (that, and cleaned geometry: skipped empty meshes, dropped
zero-area faces) are returned in the info dict under "warnings" for the render engine to report. Optional geometry arrays (corner normals, UVs, textures) are
exported only when the scene needs them (core/scene/features.py).
"""
from __future__ import annotations

import dataclasses
import math
import numpy as np

from ..core.frame.exported import InstancedExport
from ..core.layout import VISIBILITY_CODES, VISIBLE_TO_ALL
from ..core.scene.instances import blend_stays_invertible
from ..core.scene.sky import (HOSEK_STAND_IN, SUPPORTED_TYPES as SKY_SUPPORTED_TYPES,
                              SkyParams, sky_image)
from ..core.scene.spatial_order import spatial_order
from ..core.scene.features import needed_arrays, scene_features, strip_geometry
from ..core.scene.model import (DEFAULT_MATERIAL_PARAMS, MATERIAL_PARAMS, MIST, MIST_FALLOFFS,
                                Camera, Geometry, Light, MAX_MATERIALS, RenderSettings,
                                SceneError, Shading, View, WorldTexture)
from .nodes import (PRINCIPLED_DEFAULTS, NodeProgram, cycles_output, input_value, mapping_affine,
                    material_closures, socket_value)

DEFAULT_COLOR = (0.8, 0.8, 0.8, 1.0)
HALF_MAX = 65504.0          # the largest float16: texels travel as half floats
MISSING_IMAGE_RGBA = (1.0, 0.0, 1.0, 1.0)   # Cycles' colour of an image it cannot load


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
    materials = _MaterialTable(warnings)
    # The world first: its Environment Texture joins the material textures in one table.
    world_color, world_texture = export_world(scene, materials, warnings)
    motion_handled = set()   # objects whose motion the geometry blurred (or warned of)
    geometry = _export_geometry(depsgraph, materials, warnings, instanced, every_object,
                                motion_handled)
    shading = Shading(materials.colors(), _export_lights(depsgraph, warnings), world_color,
                      materials.params(), world_texture, np.array(materials.node_rows, np.float32))
    if viewport is None:
        view = View(_export_camera(depsgraph, warnings), *render_size(scene), shading,
                    render_region(scene), render_settings(scene),
                    bool(scene.render.film_transparent), mist_settings(scene))
    else:
        camera, width, height = viewport
        view = View(camera, width, height, shading, (0, 0, width, height),
                    render_settings(scene), bool(scene.render.film_transparent))
    _motion_warnings(depsgraph, warnings, motion_handled)
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
    """Maps Blender materials to indices into one table of base colours and parameters, and
    collects the image textures they use."""

    def __init__(self, warnings: list):
        self._index = {None: 0}
        self._colors = [DEFAULT_COLOR]
        self._params = [tuple(dict(zip(MATERIAL_PARAMS, DEFAULT_MATERIAL_PARAMS),
                                   **PRINCIPLED_DEFAULTS)[name] for name in MATERIAL_PARAMS)]
        self._warnings = warnings
        self._images = {}           # image name -> texture index
        self.textures = []          # (texels (N, 4) float16, width, height)
        self.node_rows = []         # the node programs of all materials, float4 rows
        self._spatial = {}          # material key -> its NodeProgram reading the hit's position
        self._uv_programs = set()   # keys of the materials whose node program reads UVs
        self.named_uv_maps = {}     # material key -> UV maps its UV Map nodes name
        self.attributes = {}        # mesh attribute name -> its corners' texture (a placeholder
        #                             in self.textures until fill_attributes)

    def index(self, material, obj_name: str | None = None,
              visibility: int = VISIBLE_TO_ALL, placement=None) -> int:
        """The material's index (the first record of its closures); `obj_name`: the object
        that uses it (named in warnings). `visibility`: the object's ray visibility and holdout
        (core/layout.py VISIBILITY_CODES); other than the default, the material gets records
        of its own with it. `placement` (a Placement): where the object is, for a node program
        that reads Generated or Object coordinates (then each placement gets records and
        programs of its own)."""
        key = material.name_full if material is not None else None
        if visibility != VISIBLE_TO_ALL or placement is not None:
            base = self.index(material, obj_name)
            programs = self._spatial.get(key)
            where = placement.key if programs is not None and placement is not None else None
            variant = (key, visibility, where)
            if variant == (key, VISIBLE_TO_ALL, None):
                return base
            if variant not in self._index:
                count = int(self._params[base][MATERIAL_PARAMS.index("closures")])
                self._index[variant] = self._reserve(count)
                for k in range(count):      # every closure of the material, in order
                    self._colors.append(self._colors[base + k])
                    params = list(self._params[base + k])
                    params[MATERIAL_PARAMS.index("visibility")] = float(visibility)
                    if where is not None and programs[k] is not None:
                        params[MATERIAL_PARAMS.index("program")] = float(len(self.node_rows))
                        self.node_rows += programs[k].rows(placement.matrices)
                    self._params.append(tuple(params))
            return self._index[variant]
        if key not in self._index:
            owner = f"material '{material.name}'" if material is not None else "material"
            closures, problems = material_closures(
                material, lambda: NodeProgram(lambda image: self.texture(image, owner),
                                              self.attribute, getattr(material, "pass_index", 0)))
            self._index[key] = self._reserve(len(closures))
            spatial = []
            for k, closure in enumerate(closures):
                params, program = closure.params, closure.program
                if k == 0:
                    params["closures"] = float(len(closures))
                if closure.image is not None:
                    params["texture"] = float(self.texture(closure.image, owner))
                if program.outputs:
                    params["program"] = float(len(self.node_rows))
                    self.node_rows += program.rows()
                    if program.reads_uv:
                        self._uv_programs.add(key)
                    if program.uv_maps:
                        self.named_uv_maps.setdefault(key, set()).update(program.uv_maps)
                spatial.append(program if program.outputs and program.transforms else None)
                self._colors.append(closure.color)
                self._params.append(tuple(params[name] for name in MATERIAL_PARAMS))
            if any(p is not None for p in spatial):
                self._spatial[key] = spatial
            if problems:        # one warning per material, naming everything it lacks
                on = f" (on object '{obj_name}')" if obj_name else ""
                self._warnings.append(f"material '{material.name}'{on}: " + "; ".join(problems))
        return self._index[key]

    def _reserve(self, count: int) -> int:
        """The index the next `count` records will have (a SceneError past MAX_MATERIALS)."""
        if len(self._colors) + count > MAX_MATERIALS:
            raise SceneError(f"the scene uses more than {MAX_MATERIALS} materials")
        return len(self._colors)

    def world_space(self, index: int) -> bool:
        """Whether the material at record `index` needs its triangles in world space: a
        closure emits (emitters are sampled as lights there) or runs a node program (which
        reads the hit's position and the triangle's frame)."""
        count = int(self._params[index][MATERIAL_PARAMS.index("closures")])
        return any(params[MATERIAL_PARAMS.index("program")] >= 0 or
                   any(params[MATERIAL_PARAMS.index(f"emission_{c}")] > 0 for c in "rgb")
                   for params in self._params[index:index + count])

    def uses_texture(self, material) -> bool:
        """Whether the material reads UVs (an image texture, or a node program that does)."""
        key = material.name_full if material is not None else None
        if key not in self._index:
            return False
        index = self._index[key]
        count = int(self._params[index][MATERIAL_PARAMS.index("closures")])
        return key in self._uv_programs or any(
            params[MATERIAL_PARAMS.index("texture")] >= 0
            for params in self._params[index:index + count])

    def texture(self, image, owner: str) -> int:
        """The index of `image` in the texture table (added on first use); `owner` names the
        material or world that uses it, for messages."""
        if image.name_full not in self._images:
            width, height = image.size
            if width == 0 or height == 0 or image.channels == 0:
                # Cycles renders an image it cannot load in magenta.
                self._warnings.append(f"{owner}: image '{image.name}' could not be loaded "
                                      f"(missing or unreadable file '{image.filepath}'); "
                                      "rendered magenta as in Cycles")
                self._images[image.name_full] = len(self.textures)
                self.textures.append((np.array([MISSING_IMAGE_RGBA], np.float16), 1, 1))
                return self._images[image.name_full]
            pixels = np.empty(width * height * image.channels, np.float32)
            image.pixels.foreach_get(pixels)
            pixels = pixels.reshape(-1, image.channels)
            rgba = np.ones((len(pixels), 4), np.float32)
            rgba[:, :min(4, image.channels)] = pixels[:, :4]
            if image.channels < 3:
                rgba[:, 1:3] = rgba[:, :1]
            # 8-bit images hold sRGB-encoded values; the renderer works in linear RGB.
            if not image.is_float and image.colorspace_settings.name == "sRGB":
                c = rgba[:, :3]
                rgba[:, :3] = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
            rgba = np.nan_to_num(rgba, posinf=HALF_MAX, neginf=0.0)
            if rgba.max() > HALF_MAX:
                self._warnings.append(f"{owner}: image '{image.name}' has values above "
                                      f"{HALF_MAX:g}, clamped (texels are half floats)")
                rgba = np.minimum(rgba, HALF_MAX)
            self._images[image.name_full] = len(self.textures)
            self.textures.append((rgba.astype(np.float16), width, height))
        return self._images[image.name_full]

    def colors(self) -> np.ndarray:
        return np.array(self._colors, np.float32)

    def params(self) -> np.ndarray:
        return np.array(self._params, np.float32)

    def attribute(self, name: str) -> int:
        """The texture that will hold mesh attribute `name`'s value at every triangle corner
        ("": the default colour attribute) for Color Attribute and Attribute nodes."""
        if name not in self.attributes:
            self.attributes[name] = len(self.textures)
            self.textures.append(None)
        return self.attributes[name]

    def fill_attributes(self, corners: dict) -> None:
        """Each attribute's corner values (name -> (T, 3, 4) float32, the realised triangles in
        order; missing: zeros) as a texture of 4096 texels a row (corner 3 t + k at texel
        3 t + k), half floats."""
        count = next((len(v) for v in corners.values()), 0)
        for name, index in self.attributes.items():
            values = corners.get(name)
            flat = np.zeros((max(3 * count, 1), 4), np.float32)
            if values is not None:
                flat[:3 * count] = np.clip(np.nan_to_num(values.reshape(-1, 4)), -HALF_MAX, HALF_MAX)
            width = min(len(flat), 4096)
            height = -(-len(flat) // width)
            texels = np.zeros((width * height, 4), np.float16)
            texels[:len(flat)] = flat
            self.textures[index] = (texels, width, height)

    def texture_arrays(self):
        if not self.textures:
            return None, None
        sizes, offset = [], 0
        for texels, width, height in self.textures:
            sizes.append((offset, width, height))
            offset += len(texels)
        return np.concatenate([t[0] for t in self.textures]), np.array(sizes, np.uint32)


def object_inverse(matrix: np.ndarray) -> np.ndarray:
    """The inverse of a finite 4 x 4 object transform as Cycles takes it (util/transform.cpp,
    projection_inverse): a singular one (an axis scaled to 0) is inverted with 1e-8 added to
    its diagonal, and one that still cannot be inverted is taken as the identity."""
    try:
        return np.linalg.inv(matrix)
    except np.linalg.LinAlgError:
        pass
    try:
        return np.linalg.inv(matrix + np.diag([1e-8, 1e-8, 1e-8, 0.0]))
    except np.linalg.LinAlgError:
        return np.eye(4)


def normal_matrix(linear: np.ndarray) -> np.ndarray:
    """The 3 x 3 map of normals under the linear part of an object transform: the inverse
    transpose, or for a singular one (an axis scaled to 0) its cofactor matrix, which takes a
    flattened object's normals onto the flattened axis (normals are normalised after)."""
    with np.errstate(all="ignore"):
        try:
            inverse_transpose = np.linalg.inv(linear).T.astype(np.float32)
            if np.isfinite(inverse_transpose).all():
                return inverse_transpose
        except np.linalg.LinAlgError:
            pass
    a, b, c = linear.T
    return np.stack([np.cross(b, c), np.cross(c, a), np.cross(a, b)], axis=1).astype(np.float32)


def object_random_id(name: str) -> int:
    """Cycles' random id of an object that is not an instance (Object Info's Random): Bob
    Jenkins' lookup3 (hash_uint2) of its name's hash_string (i = 37 i + byte) and 0."""
    def rot(x, k):
        return ((x << k) | (x >> (32 - k))) & 0xFFFFFFFF
    i = 0
    for byte in name.encode():
        i = (i * 37 + byte) & 0xFFFFFFFF
    a = b = c = (0xDEADBEEF + (2 << 2) + 13) & 0xFFFFFFFF
    a = (a + i) & 0xFFFFFFFF
    for x, y, k in (("c", "b", 14), ("a", "c", 11), ("b", "a", 25), ("c", "b", 16), ("a", "c", 4),
                    ("b", "a", 14), ("c", "b", 24)):
        v = {"a": a, "b": b, "c": c}
        v[x] = ((v[x] ^ v[y]) - rot(v[y], k)) & 0xFFFFFFFF
        a, b, c = v["a"], v["b"], v["c"]
    return c


class Placement:
    """Where an object instance is, for node programs: `matrices` maps "OBJECT" and
    "GENERATED" to 3 x 4 world -> coordinates matrices (Object: the inverse of its world
    matrix; Generated: then Cycles' texture space map, (P - location) / (2 size) + 0.5 per
    axis, 0.5 where a size is 0); `key` tells placements apart."""

    def __init__(self, matrix_world, texspace_location, texspace_size, obj=None, random_id=0):
        to_object = object_inverse(np.asarray(matrix_world, np.float64))[:3]
        size = np.asarray(texspace_size, np.float64)
        scale = np.where(size != 0, 0.5 / np.where(size != 0, size, 1.0), 0.0)
        offset = 0.5 - np.asarray(texspace_location, np.float64) * scale
        generated = scale[:, None] * to_object
        generated[:, 3] += offset
        # Object Info (Cycles' object data): location and Random (random_id / 2^32 - 1, as
        # Cycles), colour and alpha, pass index.
        colour = tuple(obj.color) if obj is not None else (1.0, 1.0, 1.0, 1.0)
        info = np.array([[*np.asarray(matrix_world, np.float64)[:3, 3],
                          float(np.float32(random_id & 0xFFFFFFFF) * np.float32(1.0 / 0xFFFFFFFF))],
                         colour, [float(getattr(obj, "pass_index", 0)), 0.0, 0.0, 0.0]])
        self.matrices = {"OBJECT": to_object, "GENERATED": generated, "INFO": info}
        self.key = np.concatenate([to_object.ravel(), generated.ravel(), info.ravel()]).tobytes()



def _mesh_arrays(mesh, want_normals: bool, want_uvs: bool, attributes=()) -> dict:
    """Vertices (V,3) float32, triangles (T,3), per-triangle slot indices, and when asked and
    present: corner normals (T,3,3) (only if some face is smooth) and corner UVs (T,3,2).

    Read from Blender's attribute arrays (position, the corners' vertices, material_index,
    corner normals, the UV map: a copy each), each triangle's corners picked from them with
    numpy; per-element reads (loop_triangles' vertices, material_index, split_normals) take
    20 to 400 times longer (docs/benchmarks.md, "Fixed cost of a render"). A mesh of
    triangles only needs no loop triangles: its triangle i is face i, corners 3i to 3i+2."""
    if not len(mesh.polygons):   # no corners (and an empty mesh has no positions either)
        return {"vertices": np.zeros((0, 3), np.float32), "triangles": np.zeros((0, 3), np.int32),
                "slots": np.zeros(0, np.int32), "normals": None, "uvs": None, "attributes": {}}
    vertices = _attribute(mesh, "position", np.float32, 3)
    corner_vertex = _attribute(mesh, ".corner_vert", np.int32)
    if len(mesh.loops) == 3 * len(mesh.polygons):   # every face a triangle (>= 3 corners each)
        corners = triangle_face = None
    else:
        mesh.calc_loop_triangles()
        tris = mesh.loop_triangles
        corners = np.empty(len(tris) * 3, np.int32)
        tris.foreach_get("loops", corners)
        triangle_face = np.empty(len(tris), np.int32)
        mesh.loop_triangle_polygons.foreach_get("value", triangle_face)

    def per_corner(values):     # a per-corner array's values at each triangle's corners
        return values if corners is None else values.take(corners, axis=0)
    triangles = per_corner(corner_vertex).reshape(-1, 3)
    if _attribute_of(mesh, "material_index", "FACE", "INT") is not None:
        slots = _attribute(mesh, "material_index", np.int32)
        slots = slots if triangle_face is None else slots[triangle_face]
    else:
        slots = np.zeros(len(triangles), np.int32)
    out = {"vertices": vertices, "triangles": triangles,
           "slots": slots, "normals": None, "uvs": None, "attributes": {}}
    for name in attributes:             # Color Attribute / Attribute nodes' values per corner
        values = _corner_attribute(mesh, name, corner_vertex)
        if values is not None:
            out["attributes"][name] = per_corner(values).reshape(-1, 3, 4)
    if want_normals and len(triangles) and (mesh.has_custom_normals or _has_smooth_faces(mesh)):
        normals = np.empty(len(mesh.loops) * 3, np.float32)
        mesh.corner_normals.foreach_get("vector", normals)
        out["normals"] = per_corner(normals.reshape(-1, 3)).reshape(-1, 3, 3)
    layer = render_uv_layer(mesh)
    if want_uvs and len(triangles) and layer is not None:
        if _attribute_of(mesh, layer.name, "CORNER", "FLOAT2") is not None:
            uv = _attribute(mesh, layer.name, np.float32, 2)
        else:
            uv = np.empty(len(mesh.loops) * 2, np.float32)
            layer.uv.foreach_get("vector", uv)
            uv = uv.reshape(-1, 2)
        out["uvs"] = per_corner(uv).reshape(-1, 3, 2)
    return out


def _corner_attribute(mesh, name: str, corner_vertex):
    """Mesh attribute `name` ("": the colour attribute Cycles renders by default) as RGBA per
    face corner (float32; colours linear, a value in all three, a vector's xyz; alpha 1), from
    its point, corner or face domain; None without one."""
    if not name:
        name = mesh.color_attributes.default_color_name or ""
    attribute = mesh.attributes.get(name) if name else None
    if attribute is None or attribute.domain not in ("POINT", "CORNER", "FACE"):
        return None
    width = {"FLOAT_COLOR": 4, "BYTE_COLOR": 4, "FLOAT_VECTOR": 3, "FLOAT2": 2, "FLOAT": 1,
             "INT": 1, "BOOLEAN": 1}.get(attribute.data_type)
    if width is None:
        return None
    prop = "color" if width == 4 else "vector" if width > 1 else "value"
    raw = np.empty(len(attribute.data) * width, np.float32 if prop != "value" or
                   attribute.data_type == "FLOAT" else np.int32)
    attribute.data.foreach_get(prop, raw)
    raw = raw.astype(np.float32).reshape(-1, width)
    rgba = np.ones((len(raw), 4), np.float32)
    rgba[:, :min(width, 3) if width < 4 else 4] = raw[:, :4]
    if width == 1:
        rgba[:, 1:3] = rgba[:, :1]
    elif width == 2:
        rgba[:, 2] = 0.0
    if attribute.domain == "POINT":
        rgba = rgba[corner_vertex]
    elif attribute.domain == "FACE":        # each corner of a face: the face's value
        starts = np.empty(len(mesh.polygons), np.int32)
        mesh.polygons.foreach_get("loop_start", starts)
        rgba = rgba[np.searchsorted(starts, np.arange(len(mesh.loops)), side="right") - 1]
    return rgba


def render_uv_layer(mesh):
    """The UV map Cycles reads where a material names none: the one active for rendering
    (the camera icon in the UV Maps list), else the active one; None without UVs."""
    return next((layer for layer in mesh.uv_layers if layer.active_render),
                mesh.uv_layers.active)


def _attribute_of(mesh, name: str, domain: str, data_type: str):
    """The mesh attribute `name` if it has that domain and data type, else None."""
    attribute = mesh.attributes.get(name)
    if attribute is None or attribute.domain != domain or attribute.data_type != data_type:
        return None
    return attribute


def _attribute(mesh, name: str, dtype, width: int = 0) -> np.ndarray:
    """The values of mesh attribute `name` (Blender's built-in ones: "position", ".corner_vert",
    "material_index"), (N,) or (N, width)."""
    attribute = mesh.attributes[name]
    values = np.empty(len(attribute.data) * max(width, 1), dtype)
    attribute.data.foreach_get("vector" if width else "value", values)
    return values.reshape(-1, width) if width else values


def _nonzero_area(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Whether each triangle's edge cross product, in float32, is not zero (np.cross's
    arithmetic, by coordinate, from np.take's gathers: a third of its time on the dragon)."""
    x, y, z = (np.ascontiguousarray(vertices[:, k]).take(triangles) for k in range(3))
    ax, ay, az = x[:, 1] - x[:, 0], y[:, 1] - y[:, 0], z[:, 1] - z[:, 0]
    bx, by, bz = x[:, 2] - x[:, 0], y[:, 2] - y[:, 0], z[:, 2] - z[:, 0]
    return ((ay * bz - az * by) != 0) | ((az * bx - ax * bz) != 0) | ((ax * by - ay * bx) != 0)


def _has_smooth_faces(mesh) -> bool:
    """Whether some face is smooth-shaded: Blender stores flat faces in the boolean face
    attribute "sharp_face" (absent: every face is smooth)."""
    sharp = mesh.attributes.get("sharp_face")
    if sharp is None or sharp.domain != "FACE":
        return True
    values = np.empty(len(mesh.polygons), bool)
    sharp.data.foreach_get("value", values)
    return not values.all()


class _MeshParts:
    """Triangles gathered from objects into one Geometry: the world-space triangles of the
    realised objects, or one mesh in object space. `add` drops zero-area faces (in float32,
    in the space stored: what the kernel sees, never hit, only noise), with a warning.
    The kept triangles' rows are copied once, by np.take into the joined arrays (a boolean
    mask's copy takes 2-3 times as long); a single object that keeps every triangle keeps
    its arrays."""

    def __init__(self, warnings: list, warned: set):
        self.parts = []     # per object: its arrays as placed, and the kept triangles
        self.vertex_count = 0
        self.warnings, self.warned = warnings, warned

    def add(self, name, arrays, slot_materials, matrix, textured) -> None:
        vertices, triangles, slots = arrays["vertices"], arrays["triangles"], arrays["slots"]
        if np.array_equal(matrix, np.eye(4)):    # the same points (the product only makes -0 +0)
            placed32 = vertices
        else:
            placed32 = (vertices.astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]).astype(
                np.float32)
        if not np.isfinite(placed32).all():
            self._warn(name, f"object '{name}' has vertices that are NaN or infinite "
                            "where placed; skipped")
            return
        keep = _nonzero_area(placed32, triangles)
        if keep.all():
            keep = None
        else:
            self._warn(name, f"object '{name}': {int((~keep).sum())} zero-area face(s) dropped")
            if not keep.any():
                return
            keep = np.flatnonzero(keep)
        normals = arrays["normals"]
        if normals is not None:
            normals_map = normal_matrix(matrix[:3, :3])
            if not np.allclose(normals_map, np.eye(3)):
                n = normals.reshape(-1, 3) @ normals_map.T
                length = np.sqrt(np.einsum("ij,ij->i", n, n))[:, None]
                normals = (n / np.where(length > 0, length, 1.0)).reshape(-1, 3, 3)
        if textured and arrays["uvs"] is None:
            self._warn(name, f"object '{name}' has a textured material but no UV map")
        # triangles.view: the corners' int32 vertex indices (>= 0) as the uint32 stored.
        self.parts.append({"v": placed32, "t": triangles.view(np.uint32), "keep": keep,
                           "base": self.vertex_count, "m": slot_materials.take(slots, mode="clip"),
                           "n": normals, "uv": arrays["uvs"], "attr": arrays["attributes"]})
        self.vertex_count += len(vertices)

    def _warn(self, name, message):
        if name not in self.warned:
            self.warned.add(name)
            self.warnings.append(message)

    @property
    def empty(self) -> bool:
        return not self.parts

    def corner_attributes(self, names) -> dict:
        """The gathered triangles' attribute values per corner (name -> (T, 3, 4) float32;
        zeros where an object has none), in the order geometry() keeps the triangles."""
        keeps = [p["keep"] for p in self.parts]
        return {name: _kept([p["attr"].get(name, np.zeros((len(p["t"]), 3, 4), np.float32))
                             for p in self.parts], keeps) for name in names} if self.parts else {}

    def geometry(self, with_uvs: bool, texels=None, sizes=None) -> Geometry:
        """The gathered triangles; `with_uvs`: UVs for every triangle (zeros where an object
        has none: textures and node programs read them)."""
        parts = self.parts
        if not parts:
            return Geometry(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32),
                            np.zeros(0, np.uint16), texels=texels, texture_sizes=sizes)
        keeps = [p["keep"] for p in parts]
        triangles = _kept([p["t"] for p in parts], keeps)
        counts = [len(p["t"]) if p["keep"] is None else len(p["keep"]) for p in parts]
        for part, start, count in zip(parts, np.cumsum([0] + counts[:-1]), counts):
            if part["base"]:    # (a part of its own, base 0, may be the mesh's array)
                triangles[start:start + count] += np.uint32(part["base"])
        normals = None
        if any(p["n"] is not None for p in parts):
            normals = _kept([p["n"] if p["n"] is not None else _flat_normals(p["v"], p["t"])
                             for p in parts], keeps).reshape(-1, 3)
        uvs = None
        if with_uvs:
            uvs = _kept([p["uv"] if p["uv"] is not None else
                         np.zeros((len(p["t"]), 3, 2), np.float32) for p in parts],
                        keeps).reshape(-1, 2)
        vertices = parts[0]["v"] if len(parts) == 1 else np.concatenate([p["v"] for p in parts])
        return Geometry(vertices, triangles, _kept([p["m"] for p in parts], keeps), normals,
                        uvs, texels, sizes)


def _kept(arrays: list, keeps: list) -> np.ndarray:
    """Each part's kept rows (`keeps`: row indices, or None for every row) one after another:
    one copy, by np.take into the joined array, and none for a single part that keeps all."""
    if len(arrays) == 1 and keeps[0] is None:
        return arrays[0]
    counts = [len(a) if k is None else len(k) for a, k in zip(arrays, keeps)]
    out = np.empty((sum(counts),) + arrays[0].shape[1:], np.result_type(*arrays))
    at = 0
    for array, keep, count in zip(arrays, keeps, counts):
        if keep is None:
            out[at:at + count] = array
        else:
            np.take(array, keep, axis=0, out=out[at:at + count], mode="clip")
        at += count
    return out


def _export_geometry(depsgraph, materials: _MaterialTable, warnings: list,
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
            mesh_cache[key] = _mesh_arrays(mesh, True, textured, materials.attributes)
        arrays = mesh_cache[key]
        if len(arrays["triangles"]) == 0:
            if name not in warned:
                warned.add(name)
                warnings.append(f"object '{name}' has no faces; skipped")
            continue
        shareable = instanced and abs(np.linalg.det(matrix[:3, :3])) > 0 and \
            not any(materials.world_space(i) for i in slot_materials)
        end = None
        if blur and shareable and not instance.is_instance and _is_animated(obj):
            ends, _ = _over_shutter(scene, obj)     # a problem: warned (_motion_warnings)
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
    world = _MeshParts(warnings, warned)
    meshes, instance_mesh, to_world, to_world_end = {}, [], [], []   # shared key -> its parts
    for name, arrays, slot_materials, matrix, end, textured, shared in placed:
        if shared is None or (uses[shared] < (1 if every_object else 2) and end is None):
            world.add(name, arrays, slot_materials, matrix, textured)
            continue
        if shared not in meshes:
            meshes[shared] = _MeshParts(warnings, warned)
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


def _motion_warnings(depsgraph, warnings: list, motion_handled: set) -> None:
    """With motion blur on: objects that move over the shutter and are not in `motion_handled`
    (moved by parents, constraints or drivers, lights, realised objects) are named, and so
    are meshes that deform (only an object's transform is blurred)."""
    scene = depsgraph.scene
    if not scene.render.use_motion_blur:
        return
    for obj in scene.objects:
        if obj.type in ("MESH", "CURVE", "FONT", "SURFACE", "META", "LIGHT") and \
                _is_animated(obj) and obj.name not in motion_handled:
            _, problem = _over_shutter(scene, obj)
            warnings.append(f"object '{obj.name}': " + (
                problem or "object motion blur is not rendered (the object is rendered where "
                           "it is at the frame)"))
        elif obj.type == "MESH" and _deforms(obj):
            warnings.append(f"object '{obj.name}': its deformation over the shutter is not "
                            "blurred (only the object's transform)")


def _deforms(obj) -> bool:
    """Whether the mesh may deform over time: animated shape keys or an armature."""
    keys = obj.data.shape_keys
    return (keys is not None and keys.animation_data is not None) or \
        any(m.type == "ARMATURE" for m in obj.modifiers)


def _is_animated(obj) -> bool:
    """Whether the object's transform is animated (keyframes or drivers, its own or a parent's)."""
    while obj is not None:
        anim = obj.animation_data
        if anim is not None and (anim.action is not None or len(anim.drivers)):
            return True
        obj = obj.parent
    return False


def _flat_normals(vertices, triangles) -> np.ndarray:
    """(T, 3, 3) float32: face normals repeated at each corner, for flat objects in a scene that
    has smooth ones."""
    corners = vertices[triangles].astype(np.float64)
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = (n / np.where(length > 0, length, 1.0)).astype(np.float32)
    return np.repeat(n[:, None], 3, axis=1)


def _export_camera(depsgraph, warnings: list) -> Camera:
    """The scene camera: projection, thin lens (depth of field) and, with motion blur on, its
    transform at the shutter's close. What is not rendered of it gets one warning."""
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
    if data.type not in ("ORTHO", "PERSP"):
        raise SceneError(f"camera type {data.type} is not supported (use perspective or orthographic)")
    kind = data.type
    (sx, sy), offset = projection_ndc(kind, projection)
    to_world = np.array(camera.matrix_world.normalized(), np.float64)
    if not (np.isfinite(to_world).all() and
            np.allclose(np.linalg.norm(to_world[:3, :3], axis=0), 1.0, atol=1e-4)):
        raise SceneError(f"camera '{scene.camera.name}' has a transform that is NaN, infinite "
                         "or scaled to 0 on an axis: it has no view to render")
    problems = []
    lens = {}
    dof = data.dof
    if dof.use_dof:
        if kind != "PERSP":
            problems.append("depth of field of an orthographic camera is not rendered")
        else:
            # Cycles' thin lens: radius = focal length / (2 f-stop), in metres (mm / 1000).
            lens["aperture"] = data.lens * 1e-3 / (2.0 * max(dof.aperture_fstop, 1e-5))
            lens["focus_distance"] = max(_focus_distance(camera, dof), 1e-6)
            lens["blades"] = int(dof.aperture_blades) if dof.aperture_blades >= 3 else 0
            lens["blade_rotation"] = float(dof.aperture_rotation)
            if abs(dof.aperture_ratio - 1.0) > 1e-6:
                problems.append(f"aperture ratio {dof.aperture_ratio:g} is rendered as 1")
    end = None
    if scene.render.use_motion_blur:
        shutter, problem = _over_shutter(scene, scene.camera)
        if problem:
            problems.append(problem)
        if shutter is not None:
            to_world, end = (_normalized(m) for m in shutter)
    if problems:
        warnings.append(f"camera '{scene.camera.name}': " + "; ".join(problems))
    return Camera(kind, to_world, (sx, sy), offset, data.clip_start, data.clip_end,
                  to_world_end=end, **lens)


def projection_ndc(kind: str, projection: np.ndarray) -> tuple:
    """(ndc_scale, ndc_offset) of core.scene.model.Camera from an OpenGL projection matrix of
    Blender's (a camera's calc_matrix_camera, a viewport's window_matrix): sensor fit, shift
    and aspect are in it."""
    sx, sy = 1.0 / projection[0, 0], 1.0 / projection[1, 1]
    if kind == "ORTHO":
        return (sx, sy), (-projection[0, 3] * sx, -projection[1, 3] * sy)
    return (sx, sy), (projection[0, 2] * sx, projection[1, 2] * sy)


def _focus_distance(camera, dof) -> float:
    """Distance of the plane in focus along the view axis (Cycles': to the focus object's
    origin, else the Focus Distance)."""
    if dof.focus_object is None:
        return float(dof.focus_distance)
    m = camera.matrix_world.normalized()
    view_axis = np.array(m.col[2][:3])
    target = np.array(dof.focus_object.matrix_world.translation)
    return float(abs(view_axis @ (np.array(m.translation) - target)))


def _over_shutter(scene, obj):
    """((matrix_world at the shutter's open, at its close) or None when the object (a
    camera too) does not move, a problem or None). The shutter is open for Motion Blur >
    Shutter frames, starting at, centred on or ending at the frame (Position); the object's own
    keyframed location, rotation and scale are evaluated at both ends (parents, constraints
    and drivers are not)."""
    if not _is_animated(obj):
        return None, None
    anim = obj.animation_data
    if obj.parent is not None or len(obj.constraints) or \
            anim is None or anim.action is None or len(anim.drivers):
        return None, "motion blur from parents, constraints or drivers is not rendered"
    r = scene.render
    frame = scene.frame_current + scene.frame_subframe
    shutter = r.motion_blur_shutter
    start = {"START": frame, "CENTER": frame - 0.5 * shutter, "END": frame - shutter}[
        r.motion_blur_position]
    ends = [_animated_matrix(obj, anim.action, t) for t in (start, start + shutter)]
    if ends[0] is None:
        return None, "motion blur from this animation (delta transforms, axis-angle) is not rendered"
    return tuple(ends), None


def _normalized(matrix: np.ndarray) -> np.ndarray:
    """The 4x4 matrix with unit axes (a camera's transform without its scale)."""
    from mathutils import Matrix
    return np.array(Matrix(matrix.tolist()).normalized(), np.float64)


def _animated_matrix(obj, action, time):
    """The object's matrix_world at `time` from its action's location, rotation (Euler or
    quaternion) and scale curves and its current values for the others; None when the action
    animates something else of the transform (delta transforms, axis-angle)."""
    from mathutils import Euler, Matrix, Quaternion, Vector
    values = {"location": list(obj.location), "rotation_euler": list(obj.rotation_euler),
              "rotation_quaternion": list(obj.rotation_quaternion), "scale": list(obj.scale)}
    for curve in _action_curves(action, obj):
        if curve.data_path not in values:
            if curve.data_path.startswith(("delta_", "rotation_axis_angle")):
                return None
            continue
        values[curve.data_path][curve.array_index] = curve.evaluate(time)
    if obj.rotation_mode == "QUATERNION":
        rotation = Quaternion(values["rotation_quaternion"]).normalized().to_matrix()
    elif obj.rotation_mode == "AXIS_ANGLE":
        return None
    else:
        rotation = Euler(values["rotation_euler"], obj.rotation_mode).to_matrix()
    return np.array(Matrix.LocRotScale(Vector(values["location"]), rotation,
                                       Vector(values["scale"])), np.float64)


def _action_curves(action, obj):
    """The F-curves of an action (layered actions of Blender 4.4+ too)."""
    curves = getattr(action, "fcurves", None)
    if curves is not None and len(curves):
        return list(curves)
    out = []
    for layer in getattr(action, "layers", ()):
        for strip in layer.strips:
            slot = obj.animation_data.action_slot
            bag = strip.channelbag(slot) if slot is not None else None
            if bag is not None:
                out += list(bag.fcurves)
    return out


def _export_lights(depsgraph, warnings: list) -> list:
    """Blender's lights. Portals (which only guide Cycles' sampling of the world) are left
    out; what KD Trace does not render of a light gets one warning naming it."""
    lights = []
    warned = set()
    for instance in depsgraph.object_instances:
        obj = instance.object
        if obj.type != "LIGHT" or not instance.show_self:
            continue
        data = obj.data
        if data.type == "AREA" and getattr(getattr(data, "cycles", None), "is_portal", False):
            continue
        problem = None
        if getattr(data, "use_nodes", False) and data.node_tree and any(
                n.type not in ("EMISSION", "OUTPUT_LIGHT") for n in data.node_tree.nodes):
            problem = "its shader nodes are not evaluated; rendering its colour"
        elif data.type == "AREA" and data.spread < math.pi - 1e-6:
            problem = "area light spread is not supported (rendered as 180 degrees)"
        if problem and obj.name not in warned:
            warned.add(obj.name)
            warnings.append(f"light '{obj.name}': {problem}")
        matrix = np.array(instance.matrix_world, np.float64)
        if not np.isfinite(matrix).all():
            if obj.name not in warned:
                warned.add(obj.name)
                warnings.append(f"light '{obj.name}' has a transform that is NaN or infinite; "
                                "skipped")
            continue
        axes = matrix[:3, :3] / np.maximum(np.linalg.norm(matrix[:3, :3], axis=0), 1e-30)
        scale = np.linalg.norm(matrix[:3, :3], axis=0)
        # Blender 4.2+: Exposure scales the power by 2^exposure; Temperature tints the colour.
        color = np.array(data.color, np.float64)
        if getattr(data, "use_temperature", False):
            color = color * np.array(data.temperature_color, np.float64)
        power = float(data.energy) * 2.0 ** float(getattr(data, "exposure", 0.0))
        if not getattr(data, "normalize", True) and problem is None and obj.name not in warned:
            warned.add(obj.name)
            warnings.append(f"light '{obj.name}': Normalize off is not supported (rendered as on)")
        light = Light(kind=data.type, color=tuple(color), power=power,
                      position=tuple(matrix[:3, 3]), direction=tuple(-axes[:, 2]),
                      axis_u=tuple(axes[:, 0]), axis_v=tuple(axes[:, 1]))
        if data.type in ("POINT", "SPOT"):
            light.radius = float(data.shadow_soft_size)
            light.soft_falloff = bool(getattr(data, "use_soft_falloff", True))
        if data.type == "SUN":
            light.radius = float(data.angle)
        if data.type == "SPOT":
            light.spot_size, light.spot_blend = float(data.spot_size), float(data.spot_blend)
        if data.type == "AREA":
            light.shape = data.shape
            light.size_u = float(data.size) * scale[0]
            light.size_v = float(data.size_y if data.shape in ("RECTANGLE", "ELLIPSE") else data.size) * scale[1]
        lights.append(light)
    return lights


def export_world(scene, textures: _MaterialTable, warnings: list):
    """(world colour, WorldTexture or None) of the scene's world: a Background (or Emission)
    shader's Color x Strength, or an Environment Texture (equirectangular or mirror ball,
    through a Mapping node from Generated or Object coordinates) times Strength. What cannot
    be mapped gets one warning naming the world and the node, and renders its plain value."""
    world = scene.world
    if world is None:
        return (0.0, 0.0, 0.0), None
    name = f"world '{world.name}'"
    if not (world.use_nodes and world.node_tree):
        return tuple(float(c) for c in world.color), None
    problems = []
    output = cycles_output(world.node_tree, "OUTPUT_WORLD")
    node = None
    if output is not None and output.inputs["Surface"].is_linked:
        node = output.inputs["Surface"].links[0].from_node
    if node is None or node.type not in ("BACKGROUND", "EMISSION"):
        if node is not None:
            problems.append(f"its surface is '{node.name}' ({node.bl_idname}), which KD Trace "
                            "cannot map; rendering the first Background's colour")
        node = next((n for n in world.node_tree.nodes if n.type == "BACKGROUND"), None)
    if node is None:
        if problems:
            warnings.append(f"{name}: " + "; ".join(problems))
        return (0.0, 0.0, 0.0), None
    strength = input_value(node, "Strength", problems)
    strength = max(float(strength if strength is not None else 1.0), 0.0)
    color_socket = node.inputs["Color"]
    texture = None
    if color_socket.is_linked:
        source = color_socket.links[0].from_node
        if source.type == "TEX_ENVIRONMENT" and color_socket.links[0].from_socket.name == "Color":
            texture = _environment(source, textures, name, problems)
        elif source.type == "TEX_SKY":
            texture, scale = _sky(source, textures, problems)
            strength *= scale
        else:
            problems.append(f"'Color' is linked to '{source.name}', which KD Trace cannot "
                            "evaluate; using its value")
    if texture is not None:
        color = (strength,) * 3
    else:
        color = tuple(float(c) * strength for c in socket_value(color_socket)[:3])
    if problems:            # one warning for the world, naming everything it lacks
        warnings.append(f"{name}: " + "; ".join(dict.fromkeys(problems)))
    return tuple(min(max(c, 0.0), 1e30) for c in color), texture


def _environment(node, textures: _MaterialTable, name: str, problems: list):
    """The WorldTexture of an Environment Texture node, or None (with a problem) without an
    image."""
    if node.image is None:
        problems.append(f"'{node.name}' has no image; rendering black")
        return None
    interpolation = "CLOSEST" if node.interpolation == "Closest" else "LINEAR"
    if node.interpolation not in ("Linear", "Closest"):
        problems.append(f"'{node.name}': interpolation {node.interpolation} is rendered as Linear")
    matrix = _world_vector_map(node, problems)
    index = textures.texture(node.image, name)
    return WorldTexture(index, node.projection if node.projection in ("EQUIRECTANGULAR", "MIRROR_BALL")
                        else "EQUIRECTANGULAR", matrix, interpolation)


def _sky(node, textures: _MaterialTable, problems: list):
    """(WorldTexture, scale) of a Sky Texture node: core/scene/sky.py's image of the sky (kept
    by its parameters), added to the texture table; the texels are the colour over `scale`.
    Hosek / Wilkie is rendered as Preetham's sky of the same sun and turbidity, dimmed to
    Hosek's typical energy (sky.HOSEK_STAND_IN), warned."""
    settings = {name: getattr(node, name) for name in (
        "sky_type", "sun_disc", "sun_size", "sun_intensity", "sun_elevation", "sun_rotation",
        "altitude", "air_density", "aerosol_density", "ozone_density", "turbidity",
        "ground_albedo")}
    settings["sun_direction"] = tuple(node.sun_direction)
    dimmed = 1.0
    if settings["sky_type"] not in SKY_SUPPORTED_TYPES:
        problems.append(f"'{node.name}': the {settings['sky_type']} sky model is not computed "
                        "by KD Trace (it needs Hosek and Wilkie's data set); rendering Preetham's "
                        "sky of the same sun direction and turbidity, dimmed to Hosek's energy")
        settings["sky_type"], dimmed = "PREETHAM", HOSEK_STAND_IN
    matrix = _world_vector_map(node, problems)
    rgba, scale = sky_image(SkyParams(**settings))
    scale *= dimmed
    height, width = rgba.shape[:2]
    textures.textures.append((rgba.reshape(-1, 4).astype(np.float16), width, height))
    return WorldTexture(len(textures.textures) - 1, "EQUIRECTANGULAR", matrix, "LINEAR"), scale


def _world_vector_map(node, problems: list) -> np.ndarray:
    """The 3 x 3 map of world directions into a world texture node's own (the Vector input:
    a Mapping node from Generated or Object coordinates, or those coordinates; else the
    identity, warned). A Sky Texture with its sun disc has no Vector input (Blender makes it
    unavailable, and Cycles ignores a link to it)."""
    matrix = np.eye(3)
    vector = next((s for s in node.inputs if s.identifier == "Vector"), None)
    if vector is not None and vector.enabled and vector.is_linked:
        source = vector.links[0].from_node
        if source.type == "MAPPING":
            matrix = _mapping_matrix(source, problems)
            inner = source.inputs["Vector"]
            source = inner.links[0].from_node if inner.is_linked else None
            socket = inner.links[0].from_socket.name if inner.is_linked else "Generated"
        else:
            socket = vector.links[0].from_socket.name
        if source is not None and not (source.type == "TEX_COORD"
                                       and socket in ("Generated", "Object")):
            problems.append(f"the vector of '{node.name}' comes from '{source.name}', which "
                            "KD Trace cannot evaluate; using the view direction")
    if not abs(np.linalg.det(matrix)) > 1e-9 * float(np.abs(matrix).max()) ** 3:
        problems.append(f"the mapping of '{node.name}' is singular; ignored")
        matrix = np.eye(3)
    return matrix


def _mapping_matrix(node, problems: list) -> np.ndarray:
    """The Mapping node's map of a direction (its linear part, nodes.mapping_affine), as 3x3
    for world directions into texture directions; a location on a Point mapping is not used
    (directions)."""
    values = {}
    for socket_name in ("Location", "Rotation", "Scale"):
        socket = node.inputs.get(socket_name)
        if socket is None:
            values[socket_name] = np.zeros(3) if socket_name != "Scale" else np.ones(3)
            continue
        if socket.is_linked:
            problems.append(f"input '{socket_name}' of '{node.name}' is linked; using its value")
        values[socket_name] = np.array(socket_value(socket), np.float64)
    if node.vector_type == "POINT" and np.abs(values["Location"]).max() > 0:
        problems.append(f"the Location of '{node.name}' moves points, not directions; ignored")
    return mapping_affine(node.vector_type, values["Location"], values["Rotation"],
                          values["Scale"])[0]
