"""The material table: Blender materials -> core.scene's material records (base colours,
parameters, the node programs' rows) and the textures they read (images, mesh attributes);
and where an object instance is (Placement, its Object Info) for node programs that read it.

Materials map onto material parameters and node programs through nodes.py and
node_program.py (docs/shading.md); a node setup that cannot be mapped falls back to its base
colour with one warning per material.
"""
from __future__ import annotations

import numpy as np

from ..core.layout import VISIBLE_TO_ALL
from ..core.scene.model import DEFAULT_MATERIAL_PARAMS, MATERIAL_PARAMS, MAX_MATERIALS, SceneError
from .node_program import NodeProgram
from .nodes import PRINCIPLED_DEFAULTS, material_closures


DEFAULT_COLOR = (0.8, 0.8, 0.8, 1.0)


HALF_MAX = 65504.0          # the largest float16: texels travel as half floats


MISSING_IMAGE_RGBA = (1.0, 0.0, 1.0, 1.0)   # Cycles' colour of an image it cannot load


class MaterialTable:
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
