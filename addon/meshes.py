"""Blender meshes -> numpy arrays, and the triangles of several objects gathered into one
Geometry. Mesh data is read with foreach_get from Blender's attribute arrays (no Python loop per
vertex or face); zero-area faces are dropped with a warning."""
from __future__ import annotations

import numpy as np

from ..core.scene.model import Geometry


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


def mesh_arrays(mesh, want_normals: bool, want_uvs: bool, attributes=()) -> dict:
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


class MeshParts:
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


def _flat_normals(vertices, triangles) -> np.ndarray:
    """(T, 3, 3) float32: face normals repeated at each corner, for flat objects in a scene that
    has smooth ones."""
    corners = vertices[triangles].astype(np.float64)
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = (n / np.where(length > 0, length, 1.0)).astype(np.float32)
    return np.repeat(n[:, None], 3, axis=1)
