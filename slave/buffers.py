"""The tracer's scene buffers: materials, lights and the camera packed into the float4 slots
the render kernel reads (kernels/shade/shading.cl and render.cl document the slots)."""
from __future__ import annotations

import math

import numpy as np

from core.scene.model import MATERIAL_PARAMS, View

LIGHT_CODES = {"POINT": 0, "SUN": 1, "SPOT": 2, "AREA": 3}
LIGHT_FLOAT4S = 6           # float4 slots per light in the kernel's light buffer
MATERIAL_FLOAT4S = 4
CAMERA_FLOAT4S = 7


class BufferError(ValueError):
    """A scene part that cannot be packed (a camera whose view axis is degenerate)."""


def pack_materials(shading) -> np.ndarray:
    """The material buffer laid out as kernels/shading.cl documents it."""
    params = shading.material_params
    col = {name: params[:, i] for i, name in enumerate(MATERIAL_PARAMS)}
    out = np.zeros((max(len(params), 1), MATERIAL_FLOAT4S, 4), np.float32)
    out[:len(params), 0] = shading.materials
    out[:len(params), 1] = np.stack([col["metallic"], col["roughness"], col["transmission"],
                                     col["ior"]], -1)
    out[:len(params), 2] = np.stack([col["emission_r"], col["emission_g"], col["emission_b"],
                                     col["specular"]], -1)
    out[:len(params), 3, 0] = col["texture"]
    out[:len(params), 3, 1] = 1.0           # texture alpha drives alpha (1 = yes)
    return out.reshape(-1, 4)


def pack_camera(view: View) -> np.ndarray:
    """The camera buffer laid out as kernels/render.cl documents it."""
    cam = view.camera
    m = cam.to_world
    forward = m[:3, :3] @ np.array([0.0, 0.0, -1.0])
    length = np.linalg.norm(forward)
    if not length > 0:
        raise BufferError("camera to_world maps the view axis to zero")
    out = np.zeros((CAMERA_FLOAT4S, 4), np.float64)
    out[0:3] = m[:3]
    out[3] = (cam.ndc_scale[0], cam.ndc_scale[1], cam.ndc_offset[0], cam.ndc_offset[1])
    out[4, :3] = forward / length
    out[4, 3] = 0.0 if cam.kind == "PERSP" else 1.0
    out[5] = (cam.clip_start, min(cam.clip_end, 3e38), view.width, view.height)
    out[6, :3] = view.shading.world_color
    return out.astype(np.float32)


def light_intensity(light) -> tuple:
    """The unit factor of each light kind (docs/tracer.md), times its colour.

    POINT/SPOT: W -> W/sr over the full sphere (P / 4 pi); SUN: W/m^2 as is; AREA: a one-sided
    Lambertian emitter of power P has peak intensity P / pi (W/sr along its axis).
    """
    factor = {"POINT": 1.0 / (4.0 * math.pi), "SPOT": 1.0 / (4.0 * math.pi),
              "SUN": 1.0, "AREA": 1.0 / math.pi}[light.kind]
    return tuple(c * light.power * factor for c in light.color)


def pack_lights(lights) -> np.ndarray:
    """The light buffer laid out as kernels/shading.cl documents it."""
    out = np.zeros((max(len(lights), 1) * LIGHT_FLOAT4S, 4), np.float64)
    for i, light in enumerate(lights):
        row = out[i * LIGHT_FLOAT4S:(i + 1) * LIGHT_FLOAT4S]
        direction = np.asarray(light.direction, np.float64)
        norm = np.linalg.norm(direction)
        direction = direction / norm if norm > 0 else np.array([0.0, 0.0, -1.0])
        row[0] = (*light.position, LIGHT_CODES[light.kind])
        row[1, :3] = direction
        row[2, :3] = light_intensity(light)
        row[5, 0] = 1.0
        if light.kind == "SPOT":
            cos_half = math.cos(light.spot_size / 2)
            row[1, 3] = cos_half
            # Cycles: smoothstep((cos - cos_half) / ((1 - cos_half) * blend)); 0 = hard edge.
            span = (1.0 - cos_half) * light.spot_blend
            row[2, 3] = 1.0 / span if span > 0 else 0.0
        if light.kind in ("POINT", "SPOT"):
            row[3, 3] = light.radius
        if light.kind == "SUN":
            row[5, 0] = math.cos(min(light.radius, math.pi) / 2)
        if light.kind == "AREA":
            u, v = _unit(light.axis_u, (1, 0, 0)), _unit(light.axis_v, (0, 1, 0))
            row[3, :3] = u * light.size_u
            row[4, :3] = v * light.size_v
            row[4, 3] = 1.0 if light.shape in ("DISK", "ELLIPSE") else 0.0
    return out.astype(np.float32)


def _unit(vector, fallback) -> np.ndarray:
    vector = np.asarray(vector, np.float64)
    norm = np.linalg.norm(vector)
    return vector / norm if norm > 0 else np.asarray(fallback, np.float64)
