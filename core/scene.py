"""The scene model shared by the add-on (which fills it), the master and the slaves.

Plain Python + numpy. Arrays travel over the network as raw little-endian buffers; the small
parts (camera, lights, materials, world) travel as JSON. Everything built from network data goes
through the `from_dict` constructors here, which validate types, shapes and ranges.

Conventions (Blender's): world space is right-handed, Z up. The camera looks along its local -Z
with +Y up. Image pixels are addressed top-left first (row 0 is the top row); the add-on flips
rows when it writes into Blender's bottom-left-origin buffers.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field

import numpy as np

SCENE_FORMAT_VERSION = 1

# Dtypes of the geometry arrays, fixed so both sides agree on the wire and in the kernel.
VERTEX_DTYPE = np.dtype("<f4")
INDEX_DTYPE = np.dtype("<u4")
MATERIAL_ID_DTYPE = np.dtype("<u2")
MAX_MATERIALS = 65535
MAX_LIGHTS = 4096


class SceneError(ValueError):
    """Scene content that cannot be rendered; the message names the problem."""


def _finite_floats(value, count: int, what: str) -> tuple:
    try:
        numbers = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise SceneError(f"{what} must be {count} numbers") from None
    if len(numbers) != count or not all(math.isfinite(v) for v in numbers):
        raise SceneError(f"{what} must be {count} finite numbers")
    return numbers


def _finite_float(value, what: str, low: float = -math.inf, high: float = math.inf) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise SceneError(f"{what} must be a number") from None
    if not math.isfinite(number) or not low <= number <= high:
        raise SceneError(f"{what} must be a finite number in [{low}, {high}], got {value!r}")
    return number


def _int(value, what: str, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise SceneError(f"{what} must be an integer in [{low}, {high}], got {value!r}")
    return value


@dataclass
class Geometry:
    """Triangles in world space: the part of the scene that the kd-tree is built over."""

    vertices: np.ndarray      # (V, 3) float32
    triangles: np.ndarray     # (T, 3) uint32, indices into vertices
    material_ids: np.ndarray  # (T,) uint16, indices into Shading.materials

    def __post_init__(self):
        self.vertices = np.ascontiguousarray(self.vertices, dtype=VERTEX_DTYPE).reshape(-1, 3)
        self.triangles = np.ascontiguousarray(self.triangles, dtype=INDEX_DTYPE).reshape(-1, 3)
        self.material_ids = np.ascontiguousarray(self.material_ids, dtype=MATERIAL_ID_DTYPE).reshape(-1)

    def validate(self, material_count: int | None = None) -> None:
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

    @property
    def triangle_count(self) -> int:
        return len(self.triangles)

    def content_hash(self) -> str:
        digest = hashlib.blake2b(digest_size=16)
        for array in (self.vertices, self.triangles, self.material_ids):
            digest.update(str(array.shape).encode())
            digest.update(array.tobytes())
        return digest.hexdigest()


@dataclass
class Camera:
    """A pinhole or orthographic camera.

    For a pixel centre at normalised device coordinates (x, y) in [-1, 1] (x right, y up), the
    camera-space point (x * ndc_scale[0] + ndc_offset[0], y * ndc_scale[1] + ndc_offset[1]) lies
    on the plane z = -1 (perspective: the ray goes from the origin through it) or z = 0
    (orthographic: the ray starts there and goes along -Z). Sensor fit, shift and aspect are
    folded into these four numbers by the exporter.
    """

    kind: str                           # "PERSP" or "ORTHO"
    to_world: np.ndarray                # (4, 4) float64, camera space -> world space
    ndc_scale: tuple = (1.0, 1.0)
    ndc_offset: tuple = (0.0, 0.0)
    clip_start: float = 0.0
    clip_end: float = 1e30

    def __post_init__(self):
        self.to_world = np.asarray(self.to_world, dtype=np.float64).reshape(4, 4)

    def to_dict(self) -> dict:
        return {"kind": self.kind, "to_world": self.to_world.reshape(-1).tolist(),
                "ndc_scale": list(self.ndc_scale), "ndc_offset": list(self.ndc_offset),
                "clip_start": self.clip_start, "clip_end": self.clip_end}

    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        if not isinstance(d, dict):
            raise SceneError("camera must be an object")
        kind = d.get("kind")
        if kind not in ("PERSP", "ORTHO"):
            raise SceneError(f"camera kind must be PERSP or ORTHO, got {kind!r}")
        clip_start = _finite_float(d.get("clip_start"), "camera clip_start", 0.0)
        clip_end = _finite_float(d.get("clip_end"), "camera clip_end", clip_start)
        scale = _finite_floats(d.get("ndc_scale"), 2, "camera ndc_scale")
        if scale[0] == 0.0 or scale[1] == 0.0:
            raise SceneError("camera ndc_scale must not be zero")
        return cls(kind, np.array(_finite_floats(d.get("to_world"), 16, "camera to_world")),
                   scale, _finite_floats(d.get("ndc_offset"), 2, "camera ndc_offset"),
                   clip_start, clip_end)


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
        return cls(
            kind=kind,
            color=_finite_floats(d.get("color"), 3, "light color"),
            power=_finite_float(d.get("power"), "light power", 0.0),
            position=_finite_floats(d.get("position"), 3, "light position"),
            direction=_finite_floats(d.get("direction"), 3, "light direction"),
            axis_u=_finite_floats(d.get("axis_u"), 3, "light axis_u"),
            axis_v=_finite_floats(d.get("axis_v"), 3, "light axis_v"),
            radius=_finite_float(d.get("radius"), "light radius", 0.0),
            spot_size=_finite_float(d.get("spot_size"), "spot size", 0.0, math.pi),
            spot_blend=_finite_float(d.get("spot_blend"), "spot blend", 0.0, 1.0),
            shape=shape,
            size_u=_finite_float(d.get("size_u"), "area light size", 0.0),
            size_v=_finite_float(d.get("size_v"), "area light size", 0.0),
        )


@dataclass
class Shading:
    """What colours the geometry: materials, lights and the world. Small; sent with each frame."""

    materials: np.ndarray = field(default_factory=lambda: np.array([[0.8, 0.8, 0.8, 1.0]], np.float32))
    lights: list = field(default_factory=list)
    world_color: tuple = (0.05, 0.05, 0.05)

    def __post_init__(self):
        self.materials = np.ascontiguousarray(self.materials, dtype=np.float32).reshape(-1, 4)

    def to_dict(self) -> dict:
        return {"materials": self.materials.tolist(), "lights": [l.to_dict() for l in self.lights],
                "world_color": list(self.world_color)}

    @classmethod
    def from_dict(cls, d: dict) -> "Shading":
        if not isinstance(d, dict):
            raise SceneError("shading must be an object")
        materials, lights = d.get("materials"), d.get("lights")
        if not isinstance(materials, list) or not 1 <= len(materials) <= MAX_MATERIALS:
            raise SceneError(f"materials must be a list of 1 to {MAX_MATERIALS} colours")
        if not isinstance(lights, list) or len(lights) > MAX_LIGHTS:
            raise SceneError(f"lights must be a list of at most {MAX_LIGHTS} lights")
        colours = [_finite_floats(m, 4, "material colour") for m in materials]
        return cls(np.array(colours, np.float32), [Light.from_dict(l) for l in lights],
                   _finite_floats(d.get("world_color"), 3, "world colour"))


MAX_IMAGE_SIDE = 65536


@dataclass
class View:
    """One frame to render: camera, image size, the region to render, and the shading.

    `region` is (x0, y0, x1, y1) in pixels of the full image, top-left origin, x1/y1 exclusive;
    it is the render border, or the whole image.
    """

    camera: Camera
    width: int
    height: int
    shading: Shading
    region: tuple = None

    def __post_init__(self):
        if self.region is None:
            self.region = (0, 0, self.width, self.height)
        self.region = tuple(int(v) for v in self.region)

    def to_dict(self) -> dict:
        return {"camera": self.camera.to_dict(), "width": self.width, "height": self.height,
                "region": list(self.region), "shading": self.shading.to_dict()}

    @classmethod
    def from_dict(cls, d: dict) -> "View":
        if not isinstance(d, dict):
            raise SceneError("view must be an object")
        width = _int(d.get("width"), "image width", 1, MAX_IMAGE_SIDE)
        height = _int(d.get("height"), "image height", 1, MAX_IMAGE_SIDE)
        region = d.get("region")
        if not isinstance(region, list) or len(region) != 4:
            raise SceneError("region must be [x0, y0, x1, y1]")
        x0 = _int(region[0], "region x0", 0, width - 1)
        y0 = _int(region[1], "region y0", 0, height - 1)
        x1 = _int(region[2], "region x1", x0 + 1, width)
        y1 = _int(region[3], "region y1", y0 + 1, height)
        return cls(Camera.from_dict(d.get("camera")), width, height,
                   Shading.from_dict(d.get("shading")), (x0, y0, x1, y1))
