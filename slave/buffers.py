"""The tracer's scene buffers: materials, lights, the camera, the tree bounds and the triangle
corners packed into the records of core/layout.py (MATERIAL, LIGHT, CAMERA, BOUNDS, TRIANGLE),
which the kernels read through the names of the generated header."""
from __future__ import annotations

import math

import numpy as np

from core.layout import (AREA_SHAPE_CODES, BOUNDS, CAMERA, CAMERA_CODES, LIGHT, LIGHT_CODES,
                         MATERIAL, TRIANGLE)
from core.scene.model import MATERIAL_PARAMS, View


class BufferError(ValueError):
    """A scene part that cannot be packed (a camera whose view axis is degenerate)."""


def pack_materials(shading) -> np.ndarray:
    """The material buffer: one MATERIAL record per material (at least one)."""
    params = shading.material_params
    n = len(params)
    out = np.zeros((max(n, 1), MATERIAL.size, 4), np.float32)
    records = out[:n]
    MATERIAL.put(records, "base_color", shading.materials[:, :3])
    MATERIAL.put(records, "alpha", shading.materials[:, 3])
    for name in ("metallic", "roughness", "transmission", "ior", "specular", "texture"):
        MATERIAL.put(records, name, params[:, MATERIAL_PARAMS.index(name)])
    emission = [MATERIAL_PARAMS.index(f"emission_{c}") for c in "rgb"]
    MATERIAL.put(records, "emission", params[:, emission])
    MATERIAL.put(records, "texture_alpha", 1.0)
    return out.reshape(-1, 4)


def pack_camera(view: View) -> np.ndarray:
    """The camera buffer: one CAMERA record."""
    cam = view.camera
    m = cam.to_world
    forward = m[:3, :3] @ np.array([0.0, 0.0, -1.0])
    length = np.linalg.norm(forward)
    if not length > 0:
        raise BufferError("camera to_world maps the view axis to zero")
    out = np.zeros((CAMERA.size, 4), np.float64)
    CAMERA.put(out, "to_world", m[:3])
    CAMERA.put(out, "ndc_scale", cam.ndc_scale)
    CAMERA.put(out, "ndc_offset", cam.ndc_offset)
    CAMERA.put(out, "view_axis", forward / length)
    CAMERA.put(out, "kind", CAMERA_CODES[cam.kind])
    CAMERA.put(out, "clip_start", cam.clip_start)
    CAMERA.put(out, "clip_end", min(cam.clip_end, 3e38))
    CAMERA.put(out, "width", view.width)
    CAMERA.put(out, "height", view.height)
    CAMERA.put(out, "world_color", view.shading.world_color)
    return out.astype(np.float32)


def pack_bounds(bounds) -> np.ndarray:
    """The bounds buffer: one BOUNDS record, with the scene's extent (max |coordinate|) for the
    traversal's tie tolerance."""
    bounds = np.asarray(bounds, np.float32)
    out = np.zeros((BOUNDS.size, 4), np.float32)
    BOUNDS.put(out, "min", bounds[0])
    BOUNDS.put(out, "max", bounds[1])
    BOUNDS.put(out, "extent", np.abs(bounds).max())
    return out


def pack_triangles(geometry) -> np.ndarray:
    """The triangle buffer: one TRIANGLE record (three float4 corners) per triangle, so the
    kernel gathers a triangle in one place (at least one record)."""
    n = geometry.triangle_count
    out = np.zeros((max(n, 1), TRIANGLE.size, 4), np.float32)
    corners = geometry.vertices[geometry.triangles]
    for k, corner in enumerate(("v0", "v1", "v2")):
        TRIANGLE.put(out[:n], corner, corners[:, k])
    return out


def light_intensity(light) -> tuple:
    """The unit factor of each light kind (docs/tracer.md), times its colour.

    POINT/SPOT: W -> W/sr over the full sphere (P / 4 pi); SUN: W/m^2 as is; AREA: a one-sided
    Lambertian emitter of power P has peak intensity P / pi (W/sr along its axis).
    """
    factor = {"POINT": 1.0 / (4.0 * math.pi), "SPOT": 1.0 / (4.0 * math.pi),
              "SUN": 1.0, "AREA": 1.0 / math.pi}[light.kind]
    return tuple(c * light.power * factor for c in light.color)


def pack_lights(lights) -> np.ndarray:
    """The light buffer: one LIGHT record per light (at least one)."""
    out = np.zeros((max(len(lights), 1), LIGHT.size, 4), np.float64)
    for light, record in zip(lights, out):
        direction = np.asarray(light.direction, np.float64)
        norm = np.linalg.norm(direction)
        direction = direction / norm if norm > 0 else np.array([0.0, 0.0, -1.0])
        LIGHT.put(record, "position", light.position)
        LIGHT.put(record, "kind", LIGHT_CODES[light.kind])
        LIGHT.put(record, "direction", direction)
        LIGHT.put(record, "intensity", light_intensity(light))
        LIGHT.put(record, "sun_cos_half_angle", 1.0)
        if light.kind == "SPOT":
            cos_half = math.cos(light.spot_size / 2)
            LIGHT.put(record, "spot_cos_half", cos_half)
            # Cycles: smoothstep((cos - cos_half) / ((1 - cos_half) * blend)); 0 = hard edge.
            span = (1.0 - cos_half) * light.spot_blend
            LIGHT.put(record, "spot_smooth", 1.0 / span if span > 0 else 0.0)
        if light.kind in ("POINT", "SPOT"):
            LIGHT.put(record, "radius", light.radius)
        if light.kind == "SUN":
            LIGHT.put(record, "sun_cos_half_angle", math.cos(min(light.radius, math.pi) / 2))
        if light.kind == "AREA":
            u, v = _unit(light.axis_u, (1, 0, 0)), _unit(light.axis_v, (0, 1, 0))
            LIGHT.put(record, "area_u", u * light.size_u)
            LIGHT.put(record, "area_v", v * light.size_v)
            shape = "ELLIPSE" if light.shape in ("DISK", "ELLIPSE") else "RECTANGLE"
            LIGHT.put(record, "area_shape", AREA_SHAPE_CODES[shape])
    return out.reshape(-1, 4).astype(np.float32)


def _unit(vector, fallback) -> np.ndarray:
    vector = np.asarray(vector, np.float64)
    norm = np.linalg.norm(vector)
    return vector / norm if norm > 0 else np.asarray(fallback, np.float64)
