"""Blender material node trees -> core.scene material parameters and closures.

material_closures maps the closures a material's surface mixes (Principled BSDF; the Diffuse,
Glossy, Glass, Translucent, Transparent and Emission BSDFs; Holdout; through Mix and Add
Shaders) onto core.scene's material parameters (docs/shading.md); the node graphs linked to
their inputs go to a NodeProgram (node_program.py). Here too: the helpers that read nodes
(socket_value, input_value, cycles_output, mapping_affine). What cannot be mapped is named in
the returned problems.
"""
from __future__ import annotations

import numpy as np

from ..core.layout import CLOSURE_CODES, MAX_CLOSURES
from ..core.scene.model import DEFAULT_MATERIAL_PARAMS, MATERIAL_PARAMS


# What Cycles renders where there is no material: a default Principled BSDF.
PRINCIPLED_DEFAULTS = {"metallic": 0.0, "roughness": 0.5, "ior": 1.5, "specular": 0.5}


# Principled BSDF input -> our parameter; inputs not listed here are ignored silently when at
# their defaults and with a warning when linked.
_PRINCIPLED = {"Metallic": "metallic", "Roughness": "roughness", "IOR": "ior",
               "Transmission Weight": "transmission", "Specular IOR Level": "specular",
               "Coat Weight": "coat_weight", "Coat Roughness": "coat_roughness",
               "Coat IOR": "coat_ior"}


_NODE_OUTPUTS = {"metallic": "METALLIC", "roughness": "ROUGHNESS", "ior": "IOR",
                 "transmission": "TRANSMISSION", "specular": "SPECULAR",
                 "coat_weight": "COAT_WEIGHT", "coat_roughness": "COAT_ROUGHNESS",
                 "coat_ior": "COAT_IOR"}


def _plain_image_node(node) -> bool:
    """An Image Texture as the material's texture lookup does it: flat, repeat, bilinear (Cubic
    and Smart too: approximated); the others go through a node program, or are warned."""
    return node.projection == "FLAT" and node.extension == "REPEAT" and \
        node.interpolation != "Closest"


def cycles_output(tree, kind: str = "OUTPUT_MATERIAL"):
    """The output node (of type `kind`: material, world or light) that Cycles renders, as
    Blender picks it for the Cycles target (ntreeShaderOutputNode): one targeting Cycles before
    one targeting All, the active one among equals; outputs for EEVEE only are never used.
    None without one."""
    best = None
    for node in tree.nodes:
        if node.type != kind or node.target not in ("ALL", "CYCLES"):
            continue
        if best is None or (best.target == "ALL" and node.target == "CYCLES") or \
                (best.target == node.target and node.is_active_output and not best.is_active_output):
            best = node
    return best


def _surface_node(material):
    """The node linked to the Surface of the Material Output Cycles renders, or None."""
    output = cycles_output(material.node_tree)
    if output is None or not output.inputs["Surface"].is_linked:
        return None
    return output.inputs["Surface"].links[0].from_node


def mapping_affine(vector_type: str, location, rotation, scale) -> tuple:
    """The Mapping node as an affine map (3 x 3 matrix, offset) of its Vector, as Cycles'
    svm_mapping computes it: Point R (v s) + L, Texture (R^T (v - L)) / s, Vector R (v s),
    Normal R (v / s) (then normalised); R the XYZ Euler rotation, a division by a scale of 0
    gives 0 (safe_divide)."""
    from mathutils import Euler
    rotation = np.array(Euler([float(r) for r in rotation], "XYZ").to_matrix(), np.float64)
    scale, location = np.asarray(scale, np.float64), np.asarray(location, np.float64)
    inverse = np.divide(1.0, scale, out=np.zeros(3), where=scale != 0)
    if vector_type == "TEXTURE":
        matrix = np.diag(inverse) @ rotation.T
        return matrix, -matrix @ location
    if vector_type == "NORMAL":
        return rotation @ np.diag(inverse), np.zeros(3)
    matrix = rotation @ np.diag(scale)
    return matrix, (location if vector_type == "POINT" else np.zeros(3))


def input_value(node, name, problems, program=None, output=None):
    """The unlinked value of input `name`; a linked one goes through the node program (as
    BSDF input `output`, a NODE_OUT_CODES name) when it can, else its value with a problem."""
    socket = node.inputs.get(name)
    if socket is None:
        return None
    if socket.is_linked:
        if program is not None and output is not None and program.output(socket, output, problems):
            return _linked_stand_in(output, socket_value(socket))
        if program is None or output is None:
            problems.append(f"input '{name}' of '{node.name}' is linked; using its value "
                            f"{socket_value(socket)}")
    return socket_value(socket)


def _linked_stand_in(output, value):
    """The constant a material keeps for an input its node program sets: one that switches on
    the kernel features the input may need (core/scene/features.py)."""
    return {"METALLIC": 0.5, "TRANSMISSION": 0.5, "SPECULAR": max(value, 0.5),
            "ALPHA": 0.5, "COAT_WEIGHT": 0.5}.get(output, value)


def _emission(node, color_name, strength_name, params, problems, program):
    """Emission colour x strength into params: through the node program when either input is
    linked (the params keep a stand-in that makes the object a light), else constants."""
    color, strength = node.inputs[color_name], node.inputs[strength_name]
    if program is not None and (color.is_linked or strength.is_linked) and \
            program.output(color, "EMISSION", problems, strength):
        value = socket_value(color)[:3] if not color.is_linked else (1.0, 1.0, 1.0)
        scale = socket_value(strength) if not strength.is_linked else 1.0
        params["emission_r"], params["emission_g"], params["emission_b"] = (
            max(0.0, c * scale) for c in value)
        return
    emission, _ = _color_input(node, color_name, problems)
    strength = input_value(node, strength_name, problems) or 0.0
    params["emission_r"], params["emission_g"], params["emission_b"] = (
        max(0.0, c * strength) for c in emission[:3])


def _coat_tint(node, params, problems, program):
    """Principled's Coat Tint (a constant, or through the node program) and Coat Normal (KD
    Trace's coat takes the BSDF's normal: a linked one is named)."""
    tint = node.inputs.get("Coat Tint")
    if tint is not None and tint.is_linked and program is not None and \
            program.output(tint, "COAT_TINT", problems):
        pass
    elif tint is not None:
        for c, v in zip("rgb", socket_value(tint)[:3]):
            params[f"coat_tint_{c}"] = max(0.0, v)
    normal = node.inputs.get("Coat Normal")
    coated = params.get("coat_weight", 0.0) > 0 or node.inputs["Coat Weight"].is_linked
    if normal is not None and normal.is_linked and coated:
        problems.append("'Coat Normal' is linked; the coat uses the BSDF's normal")


def _subsurface(node, problems):
    """Principled's Subsurface: rendered as the diffuse it replaces (Cycles' random walk
    scatters the light under the surface over Radius x Scale: softer, tinted edges); named with
    the radius it leaves out."""
    weight = node.inputs.get("Subsurface Weight")
    if weight is None or not (weight.is_linked or socket_value(weight) > 0):
        return
    radius = tuple(round(v, 4) for v in socket_value(node.inputs["Subsurface Radius"])[:3])
    scale = socket_value(node.inputs["Subsurface Scale"])
    amount = "linked" if weight.is_linked else f"{socket_value(weight):g}"
    problems.append(f"'Subsurface Weight' ({amount}) is rendered as diffuse, without the light "
                    f"scattered under the surface (Subsurface Radius {radius} x Scale {scale:g})")


def _normal_input(node, problems, program):
    """A linked Normal input through the node program (Normal Map, Bump)."""
    socket = node.inputs.get("Normal")
    if socket is None or not socket.is_linked:
        return
    if program is None:
        problems.append(f"input 'Normal' of '{node.name}' is linked, which KD Trace does not "
                        "evaluate here; ignored")
    else:
        program.output(socket, "NORMAL", problems)


def _unhandled_links(node, handled, problems):
    """A problem for the first linked input of `node` that the mapping does not read (a
    Normal map, a Coat Normal, ...)."""
    for socket in node.inputs:
        if socket.is_linked and socket.name not in handled and socket.enabled:
            problems.append(f"input '{socket.name}' of '{node.name}' is linked, which KD Trace "
                            "does not evaluate; ignored")
            return


def socket_value(socket):
    value = socket.default_value
    try:
        return tuple(float(v) for v in value)
    except TypeError:
        return float(value)


def _color_input(node, name, problems, program=None):
    """(colour RGBA, image or None): an unlinked colour, one linked straight to an Image
    Texture (through the active UV map), or (with `program`) any node graph the program
    evaluates."""
    socket = node.inputs[name]
    if socket.is_linked:
        source = socket.links[0].from_node
        if source.type == "TEX_IMAGE" and source.image is not None and \
                _plain_image_node(source) and not source.inputs["Vector"].is_linked and \
                socket.links[0].from_socket.name == "Color":
            return (1.0, 1.0, 1.0, 1.0), source.image
        if program is not None and program.output(socket, "BASE_COLOR", problems):
            return (1.0, 1.0, 1.0, 1.0), None
        if program is None:
            problems.append(f"input '{name}' is linked to '{source.name}', which KD Trace cannot "
                            f"evaluate; using its value")
    value = socket_value(socket)
    return tuple(value) + (1.0,) * (4 - len(value)), None


def material_parameters(material, program=None):
    """(base colour RGBA, params dict, image or None, problems) of a Blender material of one
    closure (its first, for a material of several: material_closures).
    `program`: a NodeProgram that takes the node graphs linked to the BSDF's inputs (without
    one, linked inputs other than a plain Image Texture keep their values, with a problem)."""
    closures, problems = material_closures(material, lambda: program)
    first = closures[0]
    return first.color, first.params, first.image, problems


class Closure:
    """One closure of a material (core/layout.py CLOSURE_CODES): its base colour RGBA, its
    parameters (MATERIAL_PARAMS names), its image texture or None and its NodeProgram (which
    may have no outputs)."""

    def __init__(self, color, params, image, program):
        self.color, self.params, self.image, self.program = color, params, image, program


def material_closures(material, new_program) -> tuple:
    """([Closure], problems) of a Blender material: the closures its surface mixes (Mix Shader,
    Add Shader), at most MAX_CLOSURES, each with its weight: the product of the Mix Shader
    factors on its path (Add: 1), a constant or set by its program when a factor is linked
    (compiled into it). `new_program()`: a NodeProgram for the next closure (or None).
    One closure, as before there were several, for a material of one BSDF."""
    problems = []
    fallback = tuple(material.diffuse_color) if material is not None else (0.8, 0.8, 0.8, 1.0)
    if material is None or not (material.use_nodes and material.node_tree):
        params = dict(zip(MATERIAL_PARAMS, DEFAULT_MATERIAL_PARAMS), **PRINCIPLED_DEFAULTS)
        if material is not None:
            # Cycles renders a material without nodes as a Principled BSDF of its viewport values.
            params.update(metallic=float(material.metallic), roughness=float(material.roughness),
                          specular=float(material.specular_intensity))
        return [Closure(fallback, params, None, new_program())], problems
    leaves = []
    node = _surface_node(material)
    output = cycles_output(material.node_tree)
    for socket, what in (("Volume", "its Volume shader is not rendered"),
                         ("Displacement", "its Displacement is not rendered (Cycles: as bump or "
                                          "true displacement)")):
        linked = output.inputs.get(socket) if output is not None else None
        if linked is not None and linked.is_linked:
            problems.append(what)
    if node is not None:
        _collect_closures(node, 1.0, [], leaves, problems)
    params = dict(zip(MATERIAL_PARAMS, DEFAULT_MATERIAL_PARAMS), **PRINCIPLED_DEFAULTS)
    if node is None:
        return [Closure(fallback, params, None, new_program())], [
            "its surface is nothing, which KD Trace cannot map; rendering its base colour"]
    if not leaves:
        # Mix / Add Shaders with no shader linked: no closure, black in Cycles.
        return [Closure((0.0, 0.0, 0.0, 1.0), dict(params, specular=0.0), None,
                        new_program())], problems
    if len(leaves) > MAX_CLOSURES:
        leaves.sort(key=lambda leaf: -leaf[1] * 0.5 ** len(leaf[2]))
        problems.append(f"it mixes {len(leaves)} shaders, KD Trace at most {MAX_CLOSURES}: "
                        + ", ".join(f"'{leaf[0].name}'" for leaf in leaves[MAX_CLOSURES:])
                        + " left out")
        leaves = leaves[:MAX_CLOSURES]
    mixed = len(leaves) > 1 or leaves[0][1] != 1.0 or leaves[0][2]
    closures = []
    for leaf, weight, factors in leaves:
        program = new_program()
        closure = _closure(leaf, program, problems, fallback, mixed)
        stand_in = weight * 0.5 ** len(factors)
        if factors and program is not None:
            program.weight(factors, weight, problems)
        elif factors:
            problems.append("a Mix Shader's Fac is linked; using 0.5")
            weight = stand_in
        closure.params["weight"] = stand_in if factors else weight
        closures.append(closure)
    return closures, problems


def _shader_link(socket):
    """The node linked to a shader socket (through reroutes), or None."""
    while socket.is_linked:
        link = socket.links[0]
        if not link.is_valid or link.is_muted:
            return None
        node = link.from_node
        if node.type != "REROUTE":
            return node
        socket = node.inputs[0]
    return None


def _collect_closures(node, weight, factors, leaves, problems, depth=0):
    """The closures under shader node `node`: (node, constant weight, linked factors) for each
    BSDF, emission, transparent or holdout node; a factor is (Fac socket, whether it is taken
    as 1 - Fac: the Mix Shader's first input)."""
    if depth > 64:
        return
    if node.type == "MIX_SHADER":
        fac = node.inputs[0]
        for first, socket in ((True, node.inputs[1]), (False, node.inputs[2])):
            source = _shader_link(socket)
            if source is None:
                continue
            if fac.is_linked:
                _collect_closures(source, weight, factors + [(fac, first)], leaves, problems,
                                  depth + 1)
                continue
            f = min(max(float(fac.default_value), 0.0), 1.0)
            w = weight * ((1.0 - f) if first else f)
            if w > 0.0:
                _collect_closures(source, w, factors, leaves, problems, depth + 1)
        return
    if node.type == "ADD_SHADER":
        for socket in node.inputs[:2]:
            source = _shader_link(socket)
            if source is not None:
                _collect_closures(source, weight, factors, leaves, problems, depth + 1)
        return
    leaves.append((node, weight, factors))


def _closure(node, program, problems, fallback, mixed) -> Closure:
    """The closure of one shader node (`mixed`: inside a Mix or Add Shader, where an Emission
    is a closure of its own kind)."""
    params = dict(zip(MATERIAL_PARAMS, DEFAULT_MATERIAL_PARAMS), **PRINCIPLED_DEFAULTS)
    kind = node.type
    image = None
    if kind == "BSDF_PRINCIPLED":
        color, image = _color_input(node, "Base Color", problems, program)
        for socket_name, name in _PRINCIPLED.items():
            value = input_value(node, socket_name, problems, program, _NODE_OUTPUTS[name])
            if value is not None:
                params[name] = value
        alpha = input_value(node, "Alpha", problems, program, "ALPHA")
        color = color[:3] + (alpha if alpha is not None else 1.0,)
        _emission(node, "Emission Color", "Emission Strength", params, problems, program)
        _coat_tint(node, params, problems, program)
        _subsurface(node, problems)
        for other in ("Sheen Weight", "Anisotropic", "Diffuse Roughness", "Thin Film Thickness"):
            socket = node.inputs.get(other)
            if socket is not None and (socket.is_linked or socket_value(socket) > 0):
                problems.append(f"'{other}' is not supported and is ignored")
        tint = node.inputs.get("Specular Tint")
        if tint is not None and (tint.is_linked or min(socket_value(tint)[:3]) < 1.0):
            problems.append("'Specular Tint' is not supported; rendering white")
        _normal_input(node, problems, program)
        _unhandled_links(node, ("Base Color", "Alpha", "Emission Color", "Emission Strength",
                                "Normal", "Coat Tint", "Coat Normal", *_PRINCIPLED), problems)
    elif kind == "BSDF_DIFFUSE":
        color, image = _color_input(node, "Color", problems, program)
        params["roughness"], params["specular"] = 1.0, 0.0
        roughness = input_value(node, "Roughness", problems)
        if roughness:
            problems.append("Oren-Nayar roughness is rendered as Lambertian diffuse")
        _normal_input(node, problems, program)
        _unhandled_links(node, ("Color", "Roughness", "Normal"), problems)
    elif kind in ("BSDF_GLOSSY", "BSDF_ANISOTROPIC"):
        color, image = _color_input(node, "Color", problems, program)
        params["metallic"] = 1.0
        params["roughness"] = input_value(node, "Roughness", problems, program, "ROUGHNESS") or 0.0
        anisotropy = node.inputs.get("Anisotropy")
        if anisotropy is not None and (anisotropy.is_linked or socket_value(anisotropy) != 0):
            problems.append("'Anisotropy' is not supported and is ignored")
        _normal_input(node, problems, program)
        _unhandled_links(node, ("Color", "Roughness", "Anisotropy", "Normal"), problems)
    elif kind == "BSDF_GLASS":
        color, image = _color_input(node, "Color", problems)
        # The Glass BSDF tints every refraction by its colour; Principled (the kernel) by the
        # square root of the base colour.
        color = tuple(c * c for c in color[:3]) + color[3:]
        params["transmission"], params["specular"] = 1.0, 0.5
        params["roughness"] = input_value(node, "Roughness", problems) or 0.0
        params["ior"] = input_value(node, "IOR", problems) or 1.45
        _unhandled_links(node, ("Color", "Roughness", "IOR"), problems)
    elif kind == "EMISSION":
        _emission(node, "Color", "Strength", params, problems, program)
        color = (0.0, 0.0, 0.0, 1.0)
        params["specular"] = 0.0
        if mixed:
            params["kind"] = float(CLOSURE_CODES["EMISSION"])
    elif kind == "BSDF_TRANSLUCENT":
        color, image = _color_input(node, "Color", problems, program)
        params["translucent"], params["specular"] = 1.0, 0.0
        _normal_input(node, problems, program)
        _unhandled_links(node, ("Color", "Normal"), problems)
    elif kind == "BSDF_TRANSPARENT":
        color, image = _color_input(node, "Color", problems, program)
        params["kind"] = float(CLOSURE_CODES["TRANSPARENT"])
        _unhandled_links(node, ("Color",), problems)
    elif kind == "HOLDOUT":
        color = (0.0, 0.0, 0.0, 1.0)
        params["kind"] = float(CLOSURE_CODES["HOLDOUT"])
    else:
        problems.append(f"'{node.name}' ({node.bl_idname}) is not supported; rendering the "
                        "material's base colour there")
        return Closure(fallback, params, None, program)
    params["ior"] = min(max(params["ior"], 0.01), 100.0)
    params["coat_ior"] = min(max(params["coat_ior"], 1.0), 100.0)
    for name in ("metallic", "roughness", "transmission", "coat_weight", "coat_roughness"):
        params[name] = min(max(params[name], 0.0), 1.0)
    params["specular"] = min(max(params["specular"], 0.0), 1000.0)
    color = tuple(min(max(c, 0.0), 1e6) for c in color[:3]) + (min(max(color[3], 0.0), 1.0),)
    return Closure(color, params, image, program)
