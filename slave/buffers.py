"""The tracer's scene buffers: materials, lights, the camera, the world, the emissive triangles,
the tree bounds and the triangle corners packed into the records of core/layout.py (MATERIAL,
LIGHT, CAMERA, WORLD, EMITTER, BOUNDS, TRIANGLE), which the kernels read through the names of
the generated header; and the world texture's importance map.

What a slave computes here from the scene (importance map, alias table) uses only operations
that IEEE arithmetic rounds the same everywhere (+ - * / sqrt, sequential sums), so every slave
samples the same lights with the same probabilities and renders the same bits."""
from __future__ import annotations

import math

import numpy as np

from ..core.layout import (AREA_SHAPE_CODES, BOUNDS, CAMERA, CAMERA_CODES, EMITTER,
                           FILTER_TABLE_SIZE, INSTANCE, INTERPOLATION_CODES, LIGHT, LIGHT_CODES,
                           MATERIAL, PIXEL_FILTER_CODES, PROJECTION_CODES, TRIANGLE, WORLD)
from ..core.scene.model import MATERIAL_PARAMS, View

# The world texture's importance map has at most this many columns (rows: half); larger
# textures are averaged over square blocks of texels.
MAX_IMPORTANCE_WIDTH = 1024


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
    for name in ("metallic", "roughness", "transmission", "ior", "specular", "texture", "visibility",
                 "weight", "kind", "translucent", "coat_weight", "coat_roughness", "coat_ior"):
        MATERIAL.put(records, name, params[:, MATERIAL_PARAMS.index(name)])
    # A material's closures never reach past the records (validated on the wire; clamped here
    # as well, since the kernel reads them without a bound).
    closures = params[:, MATERIAL_PARAMS.index("closures")]
    MATERIAL.put(records, "closures", np.clip(closures, 1, n - np.arange(n)))
    emission = [MATERIAL_PARAMS.index(f"emission_{c}") for c in "rgb"]
    MATERIAL.put(records, "emission", params[:, emission])
    MATERIAL.put(records, "coat_tint", params[:, [MATERIAL_PARAMS.index(f"coat_tint_{c}") for c in "rgb"]])
    MATERIAL.put(records, "texture_alpha", 1.0)
    # The node programs follow the records; a material's program slot is its absolute row.
    program = params[:, MATERIAL_PARAMS.index("program")]
    MATERIAL.put(records, "program", np.where(program >= 0, program + len(out) * MATERIAL.size, -1.0))
    return np.concatenate([out.reshape(-1, 4), shading.node_program.astype(np.float32)])


def filter_table(kind: str, width: float, size: int = FILTER_TABLE_SIZE) -> np.ndarray:
    """The pixel filter's inverse CDF at `size` evenly spaced u in [0, 1]: a camera sample's
    offset from the pixel centre in pixels, as Cycles importance-samples its filter (film.cpp
    filter_table: Gaussian exp(-2 (6 v / 3w)^2) over 3 w, Blackman-Harris over 2 w, i.e. to
    +-w). Symmetric, and exactly 0 at u = 1/2 (the middle entry)."""
    span = {"GAUSSIAN": 3.0, "BLACKMAN_HARRIS": 2.0}[kind] * width
    v = np.linspace(-span / 2, span / 2, 4097)
    if kind == "GAUSSIAN":
        density = np.exp(-2.0 * (v * 6.0 / span) ** 2)
    else:
        a = 2.0 * np.pi * (v / span + 0.5)
        density = 0.35875 - 0.48829 * np.cos(a) + 0.14128 * np.cos(2 * a) - 0.01168 * np.cos(3 * a)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (density[1:] + density[:-1]) * np.diff(v))])
    inverse = np.interp(np.linspace(0.0, 1.0, size), cdf / cdf[-1], v)
    return 0.5 * (inverse - inverse[::-1])          # exactly antisymmetric: 0 in the middle


def pack_camera(view: View) -> np.ndarray:
    """The camera buffer: one CAMERA record, then the pixel filter's table (filter_table, in
    float4 rows) unless it is a box."""
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
    CAMERA.put(out, "aperture", cam.aperture)
    CAMERA.put(out, "focus_distance", cam.focus_distance)
    CAMERA.put(out, "blades", cam.blades)
    CAMERA.put(out, "blade_rotation", cam.blade_rotation)
    CAMERA.put(out, "to_world_end", (m if cam.to_world_end is None else cam.to_world_end)[:3])
    settings = view.settings
    CAMERA.put(out, "filter", PIXEL_FILTER_CODES[settings.pixel_filter])
    CAMERA.put(out, "filter_width", settings.filter_width)
    start, depth, falloff = view.mist
    CAMERA.put(out, "mist_start", start)
    CAMERA.put(out, "mist_inv_depth", 1.0 / depth if depth > 0 else 0.0)
    CAMERA.put(out, "mist_falloff", falloff)
    if settings.pixel_filter == "BOX":
        return out.astype(np.float32)
    table = np.zeros(-(-FILTER_TABLE_SIZE // 4) * 4)
    table[:FILTER_TABLE_SIZE] = filter_table(settings.pixel_filter, settings.filter_width)
    return np.concatenate([out, table.reshape(-1, 4)]).astype(np.float32)


def pack_bounds(bounds) -> np.ndarray:
    """The bounds buffer: one BOUNDS record, with the scene's extent (max |coordinate|) for the
    traversal's tie tolerance."""
    bounds = np.asarray(bounds, np.float32)
    out = np.zeros((BOUNDS.size, 4), np.float32)
    BOUNDS.put(out, "min", bounds[0])
    BOUNDS.put(out, "max", bounds[1])
    BOUNDS.put(out, "extent", np.abs(bounds).max())
    return out


def pack_instances(instances) -> dict:
    """An instanced scene's top-level buffers (core/scene/instances.py InstanceSet): the
    TOPLEVEL nodes, the INSTANCE records in the top level's leaf order, the MESH rows and one
    BOUNDS record per mesh."""
    order = instances.toplevel.order
    records = np.zeros((len(order), INSTANCE.size, 4), np.float32)
    INSTANCE.put(records, "to_object", instances.to_object[order])
    INSTANCE.put(records, "to_world", instances.to_world[order])
    end = instances.to_world if instances.to_world_end is None else instances.to_world_end
    INSTANCE.put(records, "to_world_end", end[order])
    INSTANCE.put(records, "mesh", instances.mesh[order].view(np.float32))
    INSTANCE.put(records, "key_base", instances.key_base[order].view(np.float32))
    INSTANCE.put(records, "visibility", instances.visibility[order].astype(np.float32))
    det = np.linalg.det(instances.to_world[order, :, :3].astype(np.float64))
    INSTANCE.put(records, "orientation", np.where(det < 0, -1.0, 1.0))
    return {"toplevel": instances.toplevel.nodes, "instances": records,
            "meshes": np.ascontiguousarray(instances.mesh_table, np.uint32),
            "mesh_bounds": np.concatenate([pack_bounds(b) for b in instances.mesh_bounds])}


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
        # As in Cycles, an area light without area (a size or scale of 0) emits nothing.
        dark = light.kind == "AREA" and not light.size_u * light.size_v > 0
        LIGHT.put(record, "intensity", (0.0, 0.0, 0.0) if dark else light_intensity(light))
        LIGHT.put(record, "sun_cos_half_angle", 1.0)
        if light.kind == "SPOT":
            cos_half = math.cos(light.spot_size / 2)
            LIGHT.put(record, "spot_cos_half", cos_half)
            # Cycles: smoothstep((cos - cos_half) / ((1 - cos_half) * blend)); 0 = hard edge.
            span = (1.0 - cos_half) * light.spot_blend
            LIGHT.put(record, "spot_smooth", 1.0 / span if span > 0 else 0.0)
        if light.kind in ("POINT", "SPOT"):
            LIGHT.put(record, "radius", light.radius)
            LIGHT.put(record, "sphere", 0.0 if light.soft_falloff or not light.radius > 0 else 1.0)
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


def _cos_taylor(x: np.ndarray) -> np.ndarray:
    """cos of x in [-pi/2, pi/2] from its Taylor series (to x^22, error below 1e-16): the same
    bits on every machine, unlike libm's cos."""
    x2 = np.asarray(x, np.float64) ** 2
    term, total = np.ones_like(x2), np.ones_like(x2)
    for k in range(1, 12):
        term = term * (-x2) / ((2 * k - 1) * (2 * k))
        total = total + term
    return total


def world_importance(geometry, world_texture):
    """The importance map of the world texture: (cdf float32, width, height), cdf = the
    marginal CDF over rows (height + 1 values) then each row's CDF (width + 1 values each).
    A cell's weight is the mean colour of its texels (each the brightest of its 3 x 3) times the
    solid angle it covers per unit of uv (equirectangular: the cosine of its elevation; mirror
    ball: 1 inside the ball, 0 outside); the kernel's world_pdf divides by the same Jacobian,
    exactly."""
    offset, width, height = (int(v) for v in geometry.texture_sizes[world_texture.texture])
    texels = geometry.texels[offset:offset + width * height].astype(np.float64)
    value = np.maximum((texels[:, 0] + texels[:, 1] + texels[:, 2]) / 3.0, 0.0).reshape(height, width)
    # A texel's area sees its neighbours through the bilinear filter: weigh it by the brightest
    # of the 3 x 3 around it, so no direction is bright where its density is small (a sun's
    # rim would be fireflies).
    wide = np.pad(value, 1, mode="wrap")
    value = wide[1:-1, 1:-1]
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            value = np.maximum(value, wide[dy:dy + height, dx:dx + width])
    block = max(1, -(-width // MAX_IMPORTANCE_WIDTH), -(-height // (MAX_IMPORTANCE_WIDTH // 2)))
    w, h = -(-width // block), -(-height // block)
    padded = np.zeros((h * block, w * block))
    padded[:height, :width] = value
    count = np.zeros_like(padded)
    count[:height, :width] = 1.0
    cells, cell_count = np.zeros((h, w)), np.zeros((h, w))
    for dy in range(block):             # block sums as element-wise adds (fixed order)
        for dx in range(block):
            cells = cells + padded[dy::block, dx::block]
            cell_count = cell_count + count[dy::block, dx::block]
    cells = cells / np.maximum(cell_count, 1.0)
    v = (np.arange(h) + 0.5) / h
    u = (np.arange(w) + 0.5) / w
    if world_texture.projection == "MIRROR_BALL":
        x, z = 2 * u[None, :] - 1, 2 * v[:, None] - 1
        cells = np.where(x * x + z * z <= 1.0, cells, 0.0)
    else:
        cells = cells * _cos_taylor(np.pi * (v - 0.5))[:, None]
    rows = np.cumsum(cells, axis=1)
    row_total = rows[:, -1]
    conditional = np.zeros((h, w + 1))
    conditional[:, 1:] = np.where(row_total[:, None] > 0, rows / np.where(row_total > 0, row_total, 1)[:, None],
                                  np.arange(1, w + 1) / w)
    marginal = np.zeros(h + 1)
    marginal[1:] = np.cumsum(row_total)
    total = marginal[-1]
    marginal = marginal / total if total > 0 else np.arange(h + 1) / h
    conditional[:, -1] = 1.0
    marginal[-1] = 1.0
    cdf = np.concatenate([marginal, conditional.reshape(-1)]).astype(np.float32)
    return cdf, w, h


def pack_world(shading, cdf_size=(0, 0)) -> np.ndarray:
    """The world buffer: one WORLD record (the texture's mapping, projection and importance map
    size; the constant colour is the camera's CAMERA_WORLD_COLOR)."""
    out = np.zeros((WORLD.size, 4), np.float64)
    texture = shading.world_texture
    matrix = np.eye(3) if texture is None else texture.to_texture
    WORLD.put(out, "to_texture", np.c_[matrix, np.zeros(3)])
    WORLD.put(out, "from_texture", np.c_[np.linalg.inv(matrix), np.zeros(3)])
    WORLD.put(out, "texture", -1 if texture is None else texture.texture)
    WORLD.put(out, "projection", PROJECTION_CODES[texture.projection] if texture else 0)
    WORLD.put(out, "interpolation", INTERPOLATION_CODES[texture.interpolation] if texture else 0)
    WORLD.put(out, "det", abs(np.linalg.det(matrix)))
    WORLD.put(out, "cdf_width", cdf_size[0])
    WORLD.put(out, "cdf_height", cdf_size[1])
    return out.astype(np.float32)


def material_emission(shading) -> np.ndarray:
    """Per material (as the first of its closures): the mean emission colour of its closures,
    each times its weight (a stand-in where a program sets either), float64: the emitter's
    power per unit area that kernels/shade/lights.cl emitter_pdf computes the same way."""
    emission = np.stack([shading.param(f"emission_{c}") for c in "rgb"], axis=1).astype(np.float64)
    strength = (emission[:, 0] + emission[:, 1] + emission[:, 2]) / 3.0
    return shading.per_material(strength * shading.param("weight").astype(np.float64))


def emitter_powers(geometry, shading, triangles=None):
    """(emissive triangle indices, their power: mean emission colour x area, float64)."""
    strength = material_emission(shading)
    ids = geometry.material_ids.astype(np.int64)
    valid = ids < len(strength)
    emissive = np.flatnonzero(valid & (strength[np.minimum(ids, len(strength) - 1)] > 0))
    corners = geometry.vertices[geometry.triangles[emissive]].astype(np.float64)
    c = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = 0.5 * np.sqrt(c[:, 0] * c[:, 0] + c[:, 1] * c[:, 1] + c[:, 2] * c[:, 2])
    power = strength[ids[emissive]] * area
    keep = power > 0
    return emissive[keep], power[keep]


def alias_table(weights):
    """Vose's alias table of `weights` (float64): (threshold float64, alias int) per entry.
    Entry i is kept with probability threshold[i], else alias[i] is taken; each index comes
    out with probability weights / sum. A fixed sequence of exact steps (same everywhere)."""
    n = len(weights)
    scaled = [float(w) for w in np.asarray(weights, np.float64) * (n / float(np.cumsum(weights)[-1]))]
    threshold = [1.0] * n
    alias = list(range(n))
    small = [i for i in range(n) if scaled[i] < 1.0]
    large = [i for i in range(n) if scaled[i] >= 1.0]
    while small and large:
        s, l = small.pop(), large.pop()
        threshold[s], alias[s] = scaled[s], l
        scaled[l] = (scaled[l] + scaled[s]) - 1.0
        (small if scaled[l] < 1.0 else large).append(l)
    return np.array(threshold), np.array(alias, np.int64)


def pack_emitters(geometry, shading):
    """The emitter buffer (EMITTER records, at least one) and (count, total power)."""
    triangles, power = emitter_powers(geometry, shading)
    out = np.zeros((max(len(triangles), 1), EMITTER.size, 4), np.float32)
    if len(triangles) == 0:
        return out.reshape(-1, 4), 0, 0.0
    total = float(np.cumsum(power)[-1])
    threshold, alias = alias_table(power)
    records = out[:len(triangles)]
    EMITTER.put(records, "threshold", threshold)
    EMITTER.put(records, "pmf", power / total)
    bits = records.view(np.uint32)
    EMITTER.put(bits, "triangle", triangles.astype(np.uint32))
    EMITTER.put(bits, "alias", alias.astype(np.uint32))
    return out.reshape(-1, 4), len(triangles), total
