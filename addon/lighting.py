"""Blender's lights as core.scene Lights, and the world: its background colour, or an Environment
Texture or a Sky Texture (core/scene/sky.py's image) as a WorldTexture. What cannot be mapped
gets one warning naming the light or the world."""
from __future__ import annotations

import math
import numpy as np

from ..core.scene.sky import (HOSEK_STAND_IN, SUPPORTED_TYPES as SKY_SUPPORTED_TYPES,
                              SkyParams, sky_image)
from ..core.scene.model import Light, WorldTexture
from .materials import MaterialTable
from .nodes import cycles_output, input_value, mapping_affine, socket_value


def export_lights(depsgraph, warnings: list) -> list:
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


def export_world(scene, textures: MaterialTable, warnings: list):
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


def _environment(node, textures: MaterialTable, name: str, problems: list):
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


def _sky(node, textures: MaterialTable, problems: list):
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
