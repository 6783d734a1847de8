"""The scene model shared by the add-on (which fills it), the master and the slaves.

Plain Python + numpy. Arrays travel over the network as raw little-endian buffers; the small
parts (camera, lights, materials, world) travel as JSON. Everything built from network data goes
through the `from_dict` constructors here, which validate types, shapes and ranges (with the
checks and limits of core/scene/checks.py).

Conventions (Blender's): world space is right-handed, Z up. The camera looks along its local -Z
with +Y up. Image pixels are addressed top-left first (row 0 is the top row); the add-on flips
rows when it writes into Blender's bottom-left-origin buffers.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field

import numpy as np

from ..layout import CLOSURE_CODES, MAX_CLOSURES, PIXEL_FILTER_CODES, VISIBLE_TO_ALL
from .checks import (MAX_IMAGE_SIDE, MAX_LIGHTS, MAX_MATERIALS, MAX_NODE_ROWS, MAX_RADIANCE,
                     MAX_TEXTURE_SIDE, MAX_TEXTURES, MAX_TRIANGLES, SceneError, check_node_program,
                     checked_int, finite_float, finite_floats, same_arrays)

SCENE_FORMAT_VERSION = 1

# Dtypes of the geometry arrays, fixed so both sides agree on the wire and in the kernel.
VERTEX_DTYPE = np.dtype("<f4")
INDEX_DTYPE = np.dtype("<u4")
MATERIAL_ID_DTYPE = np.dtype("<u2")
NORMAL_DTYPE = np.dtype("<f4")
UV_DTYPE = np.dtype("<f4")
TEXEL_DTYPE = np.dtype("<f2")      # linear RGBA, half precision
TEXTURE_SIZE_DTYPE = np.dtype("<u4")


@dataclass
class Geometry:
    """Triangles in world space: the part of the scene that the kd-tree is built over.

    The optional arrays are None when the scene does not need them (core/scene/features.py decides):
    - normals (3T, 3) float32: unit world-space shading normal of each triangle corner (corner
      k of triangle t is row 3t + k); present when some face is smooth-shaded.
    - uvs (3T, 2) float32: the active UV map at each triangle corner; present with textures.
    - texels (N, 4) float16: linear RGBA of all image textures, concatenated; each texture's
      rows bottom row first (Blender's order, so uv (0, 0) is texel 0).
    - texture_sizes (K, 3) uint32: (offset into texels, width, height) of each texture.
    """

    vertices: np.ndarray      # (V, 3) float32
    triangles: np.ndarray     # (T, 3) uint32, indices into vertices
    material_ids: np.ndarray  # (T,) uint16, indices into Shading.materials
    normals: np.ndarray | None = None
    uvs: np.ndarray | None = None
    texels: np.ndarray | None = None
    texture_sizes: np.ndarray | None = None
    _content_hash: str | None = field(default=None, init=False, repr=False, compare=False)

    OPTIONAL = {"normals": (NORMAL_DTYPE, 3), "uvs": (UV_DTYPE, 2), "texels": (TEXEL_DTYPE, 4),
                "texture_sizes": (TEXTURE_SIZE_DTYPE, 3)}

    def __post_init__(self):
        self.vertices = np.ascontiguousarray(self.vertices, dtype=VERTEX_DTYPE).reshape(-1, 3)
        self.triangles = np.ascontiguousarray(self.triangles, dtype=INDEX_DTYPE).reshape(-1, 3)
        self.material_ids = np.ascontiguousarray(self.material_ids, dtype=MATERIAL_ID_DTYPE).reshape(-1)
        for name, (dtype, width) in self.OPTIONAL.items():
            value = getattr(self, name)
            if value is not None:
                setattr(self, name, np.ascontiguousarray(value, dtype=dtype).reshape(-1, width))

    def arrays(self) -> dict:
        """Every array that is present, by name (the optional ones only when not None)."""
        out = {"vertices": self.vertices, "triangles": self.triangles,
               "material_ids": self.material_ids}
        out.update({name: getattr(self, name) for name in self.OPTIONAL
                    if getattr(self, name) is not None})
        return out

    @property
    def texture_count(self) -> int:
        return 0 if self.texture_sizes is None else len(self.texture_sizes)

    def validate(self, material_count: int | None = None) -> None:
        """SceneError unless every index and size lies inside its array: bounds on the arrays'
        numbers in Python integers (numpy's wrap), each size capped first."""
        if len(self.triangles) > MAX_TRIANGLES:
            raise SceneError(f"{len(self.triangles)} triangles, at most {MAX_TRIANGLES}")
        if len(self.material_ids) != len(self.triangles):
            raise SceneError(
                f"{len(self.material_ids)} material ids for {len(self.triangles)} triangles")
        if len(self.triangles) and int(self.triangles.max()) >= len(self.vertices):
            raise SceneError("a triangle refers to a vertex that does not exist")
        if not np.isfinite(self.vertices).all():
            raise SceneError("vertex coordinates contain NaN or infinity")
        if material_count is not None and len(self.material_ids) \
                and int(self.material_ids.max()) >= material_count:
            raise SceneError("a triangle refers to a material that does not exist")
        for name in ("normals", "uvs"):
            value = getattr(self, name)
            if value is not None:
                if len(value) != 3 * len(self.triangles):
                    raise SceneError(f"{name} must have 3 rows per triangle, got {len(value)} "
                                     f"for {len(self.triangles)} triangles")
                if not np.isfinite(value).all():
                    raise SceneError(f"{name} contain NaN or infinity")
        if (self.texels is None) != (self.texture_sizes is None):
            raise SceneError("texels and texture_sizes come together")
        if self.texture_sizes is not None:
            if len(self.texture_sizes) > MAX_TEXTURES:
                raise SceneError(f"{len(self.texture_sizes)} textures, at most {MAX_TEXTURES}")
            texel_count = len(self.texels)
            for k, (offset, width, height) in enumerate(self.texture_sizes.tolist()):
                if not (1 <= width <= MAX_TEXTURE_SIDE and 1 <= height <= MAX_TEXTURE_SIDE):
                    raise SceneError(f"texture {k} is {width} x {height} texels; each side must "
                                     f"be 1 to {MAX_TEXTURE_SIDE}")
                if offset + width * height > texel_count:
                    raise SceneError(f"texture {k} ({width} x {height} texels from texel "
                                     f"{offset}) reaches past the end of the {texel_count} texels")
            if not np.isfinite(self.texels).all():
                raise SceneError("texels contain NaN or infinity")

    @property
    def triangle_count(self) -> int:
        return len(self.triangles)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.arrays().values())

    def used_material_ids(self) -> np.ndarray:
        """The sorted material ids some triangle uses (np.unique's result, by counting: the ids
        are 16-bit, and sorting 871k of them takes 20 ms)."""
        return np.flatnonzero(np.bincount(self.material_ids)).astype(self.material_ids.dtype)

    def content_hash(self) -> str:
        """32 hex digits over every array present; computed once (a Geometry's arrays are not
        changed after it is made)."""
        if self._content_hash is None:
            digest = hashlib.blake2b(digest_size=16)
            for name, array in self.arrays().items():
                if name not in ("vertices", "triangles", "material_ids"):
                    digest.update(name.encode())    # the three base arrays hash as before
                digest.update(str(array.shape).encode())
                digest.update(array.tobytes())
            self._content_hash = digest.hexdigest()
        return self._content_hash

    def take_hash(self, digest: str, held: dict) -> bool:
        """Take `digest` as this geometry's content hash where `held` (name -> array), the
        arrays of the geometry that hashed to `digest`, are this geometry's bit for bit (the
        same names, dtypes, shapes and bytes: hashing would give `digest`). Comparing reads the
        arrays several times faster than blake2b hashes them. Whether it was taken."""
        if not same_arrays(self.arrays(), held):
            return False
        self._content_hash = digest
        return True


@dataclass
class Camera:
    """A pinhole or orthographic camera.

    For a pixel centre at normalised device coordinates (x, y) in [-1, 1] (x right, y up), the
    camera-space point (x * ndc_scale[0] + ndc_offset[0], y * ndc_scale[1] + ndc_offset[1]) lies
    on the plane z = -1 (perspective: the ray goes from the origin through it) or z = 0
    (orthographic: the ray starts there and goes along -Z). Sensor fit, shift and aspect are
    folded into these four numbers by the exporter.

    Depth of field (Cycles' thin lens): `aperture` is the lens radius in world units (0: a
    pinhole), `focus_distance` the distance along the view axis that is sharp, `blades` the
    aperture's polygon (fewer than 3: a disc) turned by `blade_rotation` radians. Motion blur:
    `to_world_end` is the transform at the shutter's close (to_world at its open); a camera
    sample at time t in [0, 1) uses their blend (None: no motion).
    """

    kind: str                           # "PERSP" or "ORTHO"
    to_world: np.ndarray                # (4, 4) float64, camera space -> world space
    ndc_scale: tuple = (1.0, 1.0)
    ndc_offset: tuple = (0.0, 0.0)
    clip_start: float = 0.0
    clip_end: float = 1e30
    aperture: float = 0.0
    focus_distance: float = 10.0
    blades: int = 0
    blade_rotation: float = 0.0
    to_world_end: np.ndarray | None = None

    def __post_init__(self):
        self.to_world = np.asarray(self.to_world, dtype=np.float64).reshape(4, 4)
        if self.to_world_end is not None:
            self.to_world_end = np.asarray(self.to_world_end, dtype=np.float64).reshape(4, 4)

    def to_dict(self) -> dict:
        return {"kind": self.kind, "to_world": self.to_world.reshape(-1).tolist(),
                "ndc_scale": list(self.ndc_scale), "ndc_offset": list(self.ndc_offset),
                "clip_start": self.clip_start, "clip_end": self.clip_end,
                "aperture": self.aperture, "focus_distance": self.focus_distance,
                "blades": self.blades, "blade_rotation": self.blade_rotation,
                "to_world_end": None if self.to_world_end is None
                else self.to_world_end.reshape(-1).tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        if not isinstance(d, dict):
            raise SceneError("camera must be an object")
        kind = d.get("kind")
        if kind not in ("PERSP", "ORTHO"):
            raise SceneError(f"camera kind must be PERSP or ORTHO, got {kind!r}")
        clip_start = finite_float(d.get("clip_start"), "camera clip_start", 0.0)
        clip_end = finite_float(d.get("clip_end"), "camera clip_end", clip_start)
        scale = finite_floats(d.get("ndc_scale"), 2, "camera ndc_scale")
        if scale[0] == 0.0 or scale[1] == 0.0:
            raise SceneError("camera ndc_scale must not be zero")
        end = d.get("to_world_end")
        return cls(kind, np.array(finite_floats(d.get("to_world"), 16, "camera to_world")),
                   scale, finite_floats(d.get("ndc_offset"), 2, "camera ndc_offset"),
                   clip_start, clip_end,
                   finite_float(d.get("aperture", 0.0), "camera aperture", 0.0, 1e6),
                   finite_float(d.get("focus_distance", 10.0), "camera focus distance", 1e-6),
                   checked_int(d.get("blades", 0), "camera blades", 0, 100),
                   finite_float(d.get("blade_rotation", 0.0), "camera blade rotation"),
                   None if end is None else np.array(finite_floats(end, 16, "camera to_world_end")))


LIGHT_KINDS = ("POINT", "SUN", "SPOT", "AREA")
AREA_SHAPES = ("SQUARE", "RECTANGLE", "DISK", "ELLIPSE")


@dataclass
class Light:
    """A Blender light. `power` is in watts (for SUN: strength in W/m^2), as Blender shows it.

    `direction` is the way the light points (its local -Z in world space); `axis_u`/`axis_v` are
    its local X and Y in world space (for area lights), unit length.
    """

    kind: str
    color: tuple
    power: float
    position: tuple = (0.0, 0.0, 0.0)
    direction: tuple = (0.0, 0.0, -1.0)
    axis_u: tuple = (1.0, 0.0, 0.0)
    axis_v: tuple = (0.0, 1.0, 0.0)
    radius: float = 0.0          # point/spot soft radius; sun: angular diameter in radians
    spot_size: float = math.pi   # full cone angle in radians
    spot_blend: float = 0.0
    shape: str = "SQUARE"        # area lights
    size_u: float = 1.0
    size_v: float = 1.0
    soft_falloff: bool = True    # point/spot: Blender's Soft Falloff (off: a sphere of light)

    def to_dict(self) -> dict:
        return dict(self.__dict__)

    @classmethod
    def from_dict(cls, d: dict) -> "Light":
        if not isinstance(d, dict):
            raise SceneError("light must be an object")
        kind = d.get("kind")
        if kind not in LIGHT_KINDS:
            raise SceneError(f"light kind must be one of {LIGHT_KINDS}, got {kind!r}")
        shape = d.get("shape", "SQUARE")
        if shape not in AREA_SHAPES:
            raise SceneError(f"area light shape must be one of {AREA_SHAPES}, got {shape!r}")
        soft_falloff = d.get("soft_falloff", True)
        if not isinstance(soft_falloff, bool):
            raise SceneError("light soft_falloff must be true or false")
        return cls(
            kind=kind,
            color=finite_floats(d.get("color"), 3, "light color"),
            power=finite_float(d.get("power"), "light power", 0.0),
            position=finite_floats(d.get("position"), 3, "light position"),
            direction=finite_floats(d.get("direction"), 3, "light direction"),
            axis_u=finite_floats(d.get("axis_u"), 3, "light axis_u"),
            axis_v=finite_floats(d.get("axis_v"), 3, "light axis_v"),
            radius=finite_float(d.get("radius"), "light radius", 0.0),
            spot_size=finite_float(d.get("spot_size"), "spot size", 0.0, math.pi),
            spot_blend=finite_float(d.get("spot_blend"), "spot blend", 0.0, 1.0),
            shape=shape,
            size_u=finite_float(d.get("size_u"), "area light size", 0.0),
            size_v=finite_float(d.get("size_v"), "area light size", 0.0),
            soft_falloff=soft_falloff,
        )


# Per-material surface parameters beside the base colour (Shading.material_params columns).
# visibility: the VISIBILITY_<RAY> bits (core/layout.py) of the rays that see the surface, and
# VISIBILITY_HOLDOUT; the exporter gives an object with other than the default its own records.
# program: the row of the material's shader node program in Shading.node_program, -1 = none.
# A row is one closure (Mix Shader, Add Shader: docs/shading.md, Closures): closures, on a
# material's first row, how many rows (this and the next) its closures take (1 to
# MAX_CLOSURES); weight, the closure's (its program may set it); kind, a CLOSURE_CODES code.
# translucent: the share of a diffuse transmission lobe (the Translucent BSDF: 1). coat_*:
# Principled's Coat (weight 0: none).
MATERIAL_PARAMS = ("metallic", "roughness", "transmission", "ior", "emission_r", "emission_g",
                   "emission_b", "specular", "texture", "visibility", "program", "closures",
                   "weight", "kind", "translucent", "coat_weight", "coat_roughness", "coat_ior",
                   "coat_tint_r", "coat_tint_g", "coat_tint_b")
DEFAULT_MATERIAL_PARAMS = (0.0, 0.5, 0.0, 1.5, 0.0, 0.0, 0.0, 0.0, -1.0, float(VISIBLE_TO_ALL),
                           -1.0, 1.0, 1.0, float(CLOSURE_CODES["PRINCIPLED"]), 0.0, 0.0, 0.03, 1.5,
                           1.0, 1.0, 1.0)
# name -> (low, high) accepted from the network; texture is an index, -1 = none.
_PARAM_RANGES = {"metallic": (0.0, 1.0), "roughness": (0.0, 1.0), "transmission": (0.0, 1.0),
                 "ior": (0.01, 100.0), "emission_r": (0.0, 1e30), "emission_g": (0.0, 1e30),
                 "emission_b": (0.0, 1e30), "specular": (0.0, 1000.0),
                 "texture": (-1.0, MAX_TEXTURES - 1.0), "visibility": (0.0, 63.0),
                 "program": (-1.0, MAX_NODE_ROWS - 1.0), "closures": (1.0, float(MAX_CLOSURES)),
                 "weight": (0.0, 1.0), "kind": (0.0, float(max(CLOSURE_CODES.values()))),
                 "translucent": (0.0, 1.0), "coat_weight": (0.0, 1.0), "coat_roughness": (0.0, 1.0),
                 "coat_ior": (1.0, 100.0), "coat_tint_r": (0.0, 1000.0),
                 "coat_tint_g": (0.0, 1000.0), "coat_tint_b": (0.0, 1000.0)}
_WHOLE_PARAMS = ("visibility", "program", "closures", "kind")


def default_material_params(count: int) -> np.ndarray:
    return np.tile(np.array(DEFAULT_MATERIAL_PARAMS, np.float32), (count, 1))


PROJECTIONS = ("EQUIRECTANGULAR", "MIRROR_BALL")
INTERPOLATIONS = ("LINEAR", "CLOSEST")


@dataclass
class WorldTexture:
    """An Environment Texture behind the world colour: the world's radiance in direction d is
    world_color x texture(lookup of A d), A = `to_texture` (3x3: the Mapping node's rotation and
    scale, world direction -> the texture's direction). `texture` indexes Geometry's texture
    table (texels, texture_sizes), where the exporter puts the image.

    Projections as Cycles': EQUIRECTANGULAR u = 0.5 - atan2(y, x) / 2 pi, v = 0.5 + asin(z) / pi;
    MIRROR_BALL the ball seen along +Y (u, v = (x, z) / sqrt(2 (1 - y)) / 2 + 0.5)."""

    texture: int
    projection: str = "EQUIRECTANGULAR"
    to_texture: np.ndarray = field(default_factory=lambda: np.eye(3))
    interpolation: str = "LINEAR"

    def __post_init__(self):
        self.to_texture = np.asarray(self.to_texture, dtype=np.float64).reshape(3, 3)

    def to_dict(self) -> dict:
        return {"texture": self.texture, "projection": self.projection,
                "to_texture": self.to_texture.reshape(-1).tolist(),
                "interpolation": self.interpolation}

    @classmethod
    def from_dict(cls, d) -> "WorldTexture":
        if not isinstance(d, dict):
            raise SceneError("world_texture must be an object")
        projection, interpolation = d.get("projection"), d.get("interpolation")
        if projection not in PROJECTIONS:
            raise SceneError(f"world projection must be one of {PROJECTIONS}, got {projection!r}")
        if interpolation not in INTERPOLATIONS:
            raise SceneError(f"world interpolation must be one of {INTERPOLATIONS}, "
                             f"got {interpolation!r}")
        matrix = np.array(finite_floats(d.get("to_texture"), 9, "world to_texture")).reshape(3, 3)
        det = abs(float(np.linalg.det(matrix)))
        scale = float(np.abs(matrix).max())
        if not det > 1e-9 * scale ** 3:
            raise SceneError("the world's mapping is singular (a scale of zero)")
        return cls(checked_int(d.get("texture"), "world texture", 0, MAX_TEXTURES - 1), projection,
                   matrix, interpolation)


@dataclass
class Shading:
    """What colours the geometry: materials, lights and the world. Small; sent with each frame.

    materials: (M, 4) float32 base colour RGB and alpha (alpha < 1: cut-out, stochastic).
    material_params: (M, len(MATERIAL_PARAMS)) float32, the Principled BSDF's other inputs
    (docs/shading.md); None means the defaults: a pure diffuse surface (specular 0).
    world_color: the world's radiance (Background colour x strength), seen by rays that leave
    the scene and lighting it; with `world_texture`, the factor of the texture's colour.
    """

    materials: np.ndarray = field(default_factory=lambda: np.array([[0.8, 0.8, 0.8, 1.0]], np.float32))
    lights: list = field(default_factory=list)
    world_color: tuple = (0.05, 0.05, 0.05)
    material_params: np.ndarray | None = None
    world_texture: WorldTexture | None = None
    node_program: np.ndarray | None = None      # (P, 4) float32 rows of the node programs

    def __post_init__(self):
        self.materials = np.ascontiguousarray(self.materials, dtype=np.float32).reshape(-1, 4)
        if self.material_params is None:
            self.material_params = default_material_params(len(self.materials))
        self.material_params = np.ascontiguousarray(
            self.material_params, dtype=np.float32).reshape(-1, len(MATERIAL_PARAMS))
        if len(self.material_params) != len(self.materials):
            raise SceneError(f"{len(self.material_params)} material parameter rows for "
                             f"{len(self.materials)} materials")
        self.node_program = np.ascontiguousarray(
            np.zeros((0, 4)) if self.node_program is None else self.node_program,
            dtype=np.float32).reshape(-1, 4)

    def param(self, name: str) -> np.ndarray:
        return self.material_params[:, MATERIAL_PARAMS.index(name)]

    def closure_rows(self, ids) -> np.ndarray:
        """The rows of the closures of materials `ids` (first rows): each id and the rows after
        it that its closures take, sorted, once each."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        ids = ids[(ids >= 0) & (ids < len(self.materials))]
        counts = np.clip(self.param("closures")[ids].astype(np.int64), 1, MAX_CLOSURES)
        rows = [ids + k for k in range(MAX_CLOSURES)]
        keep = [k < counts for k in range(MAX_CLOSURES)]
        out = np.concatenate([r[m] for r, m in zip(rows, keep)])
        return np.unique(out[out < len(self.materials)])

    def per_material(self, values) -> np.ndarray:
        """For each row as a material's first: `values` (one per row, bool or float) summed
        over its closures' rows (a bool: whether any has it)."""
        values = np.asarray(values)
        counts = np.clip(self.param("closures").astype(np.int64), 1, MAX_CLOSURES)
        n = len(values)
        total = np.zeros(n, np.float64 if values.dtype != bool else bool)
        for k in range(min(MAX_CLOSURES, n)):
            shifted = np.zeros_like(total)
            shifted[:n - k] = values[k:]
            mask = k < counts
            total = (total | (shifted & mask)) if values.dtype == bool else \
                total + np.where(mask, shifted, 0.0)
        return total

    @property
    def world_lights(self) -> bool:
        """Whether the world gives light (a colour that is not black)."""
        return max(self.world_color) > 0

    def to_dict(self) -> dict:
        return {"materials": self.materials.tolist(), "lights": [l.to_dict() for l in self.lights],
                "world_color": list(self.world_color),
                "material_params": self.material_params.tolist(),
                "world_texture": None if self.world_texture is None else self.world_texture.to_dict(),
                "node_program": self.node_program.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "Shading":
        if not isinstance(d, dict):
            raise SceneError("shading must be an object")
        materials, lights = d.get("materials"), d.get("lights")
        if not isinstance(materials, list) or not 1 <= len(materials) <= MAX_MATERIALS:
            raise SceneError(f"materials must be a list of 1 to {MAX_MATERIALS} colours")
        if not isinstance(lights, list) or len(lights) > MAX_LIGHTS:
            raise SceneError(f"lights must be a list of at most {MAX_LIGHTS} lights")
        colours = [finite_floats(m, 4, "material colour") for m in materials]
        params = d.get("material_params")
        if params is not None:
            if not isinstance(params, list) or len(params) != len(materials):
                raise SceneError("material_params must be a list with one row per material")
            rows = []
            for row in params:
                row = finite_floats(row, len(MATERIAL_PARAMS), "material parameters")
                for name, value in zip(MATERIAL_PARAMS, row):
                    low, high = _PARAM_RANGES[name]
                    if not low <= value <= high:
                        raise SceneError(f"material {name} must be in [{low}, {high}], got {value}")
                    if name in _WHOLE_PARAMS and value != round(value):
                        raise SceneError(f"material {name} must be a whole number, got {value}")
                rows.append(row)
            # A material's closures are the rows from its own: none past the table (Python
            # integers; the kernel reads the records id .. id + closures - 1).
            count = MATERIAL_PARAMS.index("closures")
            for k, row in enumerate(rows):
                if k + int(row[count]) > len(rows):
                    raise SceneError(f"material {k} has {int(row[count])} closures, past the "
                                     f"{len(rows)} rows")
            params = np.array(rows, np.float32)
        world = finite_floats(d.get("world_color"), 3, "world colour")
        if min(world) < 0 or max(world) > MAX_RADIANCE:
            raise SceneError(f"world colour must be in [0, {MAX_RADIANCE}], got {world}")
        texture = d.get("world_texture")
        starts = [] if params is None else params[:, MATERIAL_PARAMS.index("program")]
        program = check_node_program(d.get("node_program") or [], starts)
        return cls(np.array(colours, np.float32), [Light.from_dict(l) for l in lights], world,
                   params, None if texture is None else WorldTexture.from_dict(texture), program)


@dataclass
class RenderSettings:
    """How a frame is sampled; travels with the View so every slave renders the same pixels.
    The defaults are Cycles' final-render defaults (Sampling, Light Paths), so that F12 gives a
    clean image; docs/shading.md says what each does.

    samples_per_axis N: at most N x N stratified samples per pixel (1: one ray through the pixel
    centre); 64 = Cycles' 4096 Max Samples.
    adaptive: as Cycles' adaptive sampling: every pixel gets adaptive_min_samples (0: Cycles'
    automatic count, `min_samples`), then ADAPTIVE_STEP more at a time (up to N x N) while its
    noise, measured as Cycles measures it, exceeds adaptive_threshold (Cycles' Noise
    Threshold) or a neighbour's does (slave/adaptive.py).
    undersample: with adaptive, KD Trace's adaptive undersampling (after Kim et al. 2016): a
    pixel between converged neighbours that agree is their average and traces nothing. Fewer
    samples than Cycles' adaptive sampling at the same threshold, and a little more error;
    off by default, so that a Noise Threshold means what it does in Cycles.
    max_bounces: scattering events after the camera hit (0: direct light only); of them at most
    diffuse_bounces diffuse, glossy_bounces glossy reflections, transmission_bounces
    refractions; transparent_bounces: alpha cut-outs a path passes through (not bounces).
    clamp_direct / clamp_indirect: the largest mean of RGB one sample may add through the first
    surface / after a bounce (0: no clamping), as Cycles' Clamping.
    filter_glossy: Cycles' Filter Glossy: after wide BSDF samples sharp glossy lobes are
    blurred (fewer caustic fireflies; 0: off).
    light_samples_per_axis L: L x L stratified shadow samples per soft light, a textured world
    and the emissive meshes, per camera sample.
    pixel_filter, filter_width: Cycles' Film > Pixel Filter (PIXEL_FILTERS; Blackman-Harris of
    1.5 pixels by default, as Cycles): where in and around its pixel each camera sample goes.
    """

    samples_per_axis: int = 64
    adaptive: bool = True
    adaptive_threshold: float = 0.01
    adaptive_min_samples: int = 0
    undersample: bool = False
    max_bounces: int = 12
    diffuse_bounces: int = 4
    glossy_bounces: int = 4
    transmission_bounces: int = 12
    transparent_bounces: int = 8
    clamp_direct: float = 0.0
    clamp_indirect: float = 10.0
    filter_glossy: float = 1.0
    light_samples_per_axis: int = 1
    seed: int = 0
    pixel_filter: str = "BLACKMAN_HARRIS"
    filter_width: float = 1.5

    @property
    def max_samples(self) -> int:
        return self.samples_per_axis ** 2

    @property
    def noise_threshold(self) -> float:
        """adaptive_threshold, or for 0 Cycles' automatic one: max(0.001, 1 / max samples)."""
        return self.adaptive_threshold or max(0.001, 1.0 / self.max_samples)

    @property
    def min_samples(self) -> int:
        """The samples every pixel gets before adaptive sampling decides: adaptive_min_samples,
        or for 0 Cycles' automatic count, max(4, ceil(16 / threshold^0.3)) (64 at 0.01)."""
        if self.adaptive_min_samples > 0:
            return self.adaptive_min_samples
        return max(4, math.ceil(16.0 / self.noise_threshold ** 0.3))

    def to_dict(self) -> dict:
        return dict(self.__dict__)

    @classmethod
    def from_dict(cls, d) -> "RenderSettings":
        if d is None:
            return cls()
        if not isinstance(d, dict):
            raise SceneError("render settings must be an object")
        unknown = set(d) - set(RENDER_SETTING_LIMITS) - set(SWITCHES) - {"pixel_filter"}
        if unknown:
            raise SceneError(f"unknown render settings {sorted(unknown)}")
        out = cls()
        for name, (low, high) in RENDER_SETTING_LIMITS.items():
            if name not in d:
                continue
            if isinstance(low, int):
                setattr(out, name, checked_int(d[name], f"render setting {name}", low, high))
            else:
                setattr(out, name, finite_float(d[name], f"render setting {name}", low, high))
        for name in SWITCHES:
            if name in d:
                if not isinstance(d[name], bool):
                    raise SceneError(f"render setting {name} must be true or false")
                setattr(out, name, d[name])
        if "pixel_filter" in d:
            if d["pixel_filter"] not in PIXEL_FILTERS:
                raise SceneError(f"pixel filter must be one of {PIXEL_FILTERS}, "
                                 f"got {d['pixel_filter']!r}")
            out.pixel_filter = d["pixel_filter"]
        return out


# The range of every numeric render setting: what a view from the network may ask for, and what
# the add-on's panel offers (addon/properties.py reads it).
RENDER_SETTING_LIMITS = {
    "samples_per_axis": (1, 64), "adaptive_threshold": (0.0, 1.0),
    "adaptive_min_samples": (0, 4096), "max_bounces": (0, 1024), "diffuse_bounces": (0, 1024),
    "glossy_bounces": (0, 1024), "transmission_bounces": (0, 1024),
    "transparent_bounces": (0, 1024), "clamp_direct": (0.0, 1e6), "clamp_indirect": (0.0, 1e6),
    "filter_glossy": (0.0, 10.0),
    "light_samples_per_axis": (1, 16), "seed": (0, 2 ** 31 - 1), "filter_width": (0.01, 10.0),
}
PIXEL_FILTERS = tuple(PIXEL_FILTER_CODES)
SWITCHES = ("adaptive", "undersample")      # the render settings that are on or off


# The Mist pass (World > Mist Pass, as Cycles): the distance where mist starts, the depth over
# which it reaches 1, and the falloff as a power (Blender's Quadratic 2, Linear 1, Inverse
# Quadratic 0.5).
MIST = (5.0, 25.0, 2.0)
MIST_FALLOFFS = {"QUADRATIC": 2.0, "LINEAR": 1.0, "INVERSE_QUADRATIC": 0.5}


@dataclass
class View:
    """One frame to render: camera, image size, the region to render, and the shading.

    `region` is (x0, y0, x1, y1) in pixels of the full image, top-left origin, x1/y1 exclusive;
    it is the render border, or the whole image. `film_transparent` (Blender's Film >
    Transparent): camera rays that leave the scene, or reach a holdout, give alpha 0 and no
    colour (the world still lights the scene). `mist`: the Mist pass's (start, depth, falloff
    power) (MIST).
    """

    camera: Camera
    width: int
    height: int
    shading: Shading
    region: tuple = None
    settings: RenderSettings = field(default_factory=RenderSettings)
    film_transparent: bool = False
    mist: tuple = MIST

    def __post_init__(self):
        if self.region is None:
            self.region = (0, 0, self.width, self.height)
        self.region = tuple(int(v) for v in self.region)

    def rays_per_sample(self) -> int:
        """The rays one camera sample may trace at most, as a work count (Python integer):
        every path vertex (1 + max_bounces + transparent_bounces: a transparent surface is
        passed by a vertex of its own) traces its continuation and L x L shadow rays per light,
        plus L x L each for the world and the emissive triangles. Not exact (a shadow ray may
        pass through several surfaces, a path usually ends early): the unit of the tile work
        budget and of the tracer's launch sizes, proportional to the work a tile may cost."""
        s = self.settings
        shadow = (len(self.shading.lights) + 2) * int(s.light_samples_per_axis) ** 2
        return (1 + shadow) * (1 + int(s.max_bounces) + int(s.transparent_bounces))

    def tile_rays(self, w: int, h: int) -> int:
        """The work of a w x h tile of this view: pixels x max samples x rays_per_sample()."""
        return int(w) * int(h) * int(self.settings.samples_per_axis) ** 2 * self.rays_per_sample()

    def to_dict(self) -> dict:
        return {"camera": self.camera.to_dict(), "width": self.width, "height": self.height,
                "region": list(self.region), "shading": self.shading.to_dict(),
                "settings": self.settings.to_dict(), "film_transparent": self.film_transparent,
                "mist": [float(v) for v in self.mist]}

    @classmethod
    def from_dict(cls, d: dict) -> "View":
        if not isinstance(d, dict):
            raise SceneError("view must be an object")
        width = checked_int(d.get("width"), "image width", 1, MAX_IMAGE_SIDE)
        height = checked_int(d.get("height"), "image height", 1, MAX_IMAGE_SIDE)
        region = d.get("region")
        if not isinstance(region, list) or len(region) != 4:
            raise SceneError("region must be [x0, y0, x1, y1]")
        x0 = checked_int(region[0], "region x0", 0, width - 1)
        y0 = checked_int(region[1], "region y0", 0, height - 1)
        x1 = checked_int(region[2], "region x1", x0 + 1, width)
        y1 = checked_int(region[3], "region y1", y0 + 1, height)
        transparent = d.get("film_transparent", False)
        if not isinstance(transparent, bool):
            raise SceneError("film_transparent must be true or false")
        mist = finite_floats(d.get("mist", list(MIST)), 3, "mist")
        if mist[1] < 0 or mist[2] not in MIST_FALLOFFS.values():
            raise SceneError(f"mist must be [start, depth >= 0, falloff in "
                             f"{sorted(MIST_FALLOFFS.values())}], got {list(mist)}")
        return cls(Camera.from_dict(d.get("camera")), width, height,
                   Shading.from_dict(d.get("shading")), (x0, y0, x1, y1),
                   RenderSettings.from_dict(d.get("settings")), transparent, mist)
