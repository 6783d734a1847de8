"""NodeProgram: the node graphs linked to a material's BSDF inputs compiled into a program for
the kernel (core/layout.py NODE_OP_CODES, nodes.cl run_nodes). A node it cannot evaluate
raises inside the compiler; the input then keeps its value and the problem names the node."""
from __future__ import annotations

import numpy as np

from ..core.layout import (NODE_ATTRIBUTE_CODES, NODE_EXTENSION_CODES,
                           NODE_GEOMETRY_CODES, NODE_GRADIENT_CODES, NODE_LIGHT_PATH_CODES,
                           NODE_OBJECT_INFO_CODES,
                           NODE_LAYER_WEIGHT_CODES, NODE_MATH_CODES, NODE_MIX_CODES,
                           NODE_NOISE_TYPE_CODES, NODE_NORMAL_SPACE_CODES,
                           NODE_OBJECT_NORMAL_SPACES, NODE_OP_CODES,
                           NODE_OUT_CODES, NODE_RAMP_SIZE, NODE_REF_REGISTER, NODE_REGISTERS,
                           NODE_TRANSFORM_SIZE, NODE_VECTOR_MATH_CODES,
                           NODE_VORONOI_FEATURE_CODES, NODE_VORONOI_METRIC_CODES,
                           NODE_VORONOI_OUTPUT_CODES, NODE_WAVE_BANDS_CODES,
                           NODE_WAVE_PROFILE_CODES, NODE_WAVE_RINGS_CODES, NODE_WAVE_TYPE_CODES)
from .nodes import mapping_affine, socket_value


def _named_input(node, name):
    """The input called `name`, also where the node hides it (Noise's W in 2D and 3D, Offset
    and Gain in fBm: inputs[name] does not find those)."""
    return next(socket for socket in node.inputs if socket.name == name)


class _Unsupported(Exception):
    """A node (or a setting of one) the node program cannot evaluate."""


class NodeProgram:
    """Compiles the node graphs linked to a material's BSDF inputs into one program for the
    kernel (core/layout.py NODE_OP_CODES; shading.cl run_nodes): each node once, into a
    register; constants for unlinked inputs. Nodes: Image Texture (UV, Linear/Closest,
    Repeat), Texture Coordinate and UV Map (UV), Separate/Combine Color (RGB) and XYZ, Mix
    (float, colour and vector; Mix, Add, Multiply, Subtract, Screen, Difference, Darken,
    Lighten), Math (the NODE_MATH_CODES operations), Mapping (Point, Texture, Vector, Normal),
    Invert, Checker Texture, Noise Texture (every
    type, 1D to 4D), Color Ramp, Value and RGB; into a BSDF's Normal: Normal Map (tangent, object, world
    space) and Bump; emission as colour x strength. Another node makes its input keep its value, and the problem names it."""

    def __init__(self, texture_index, attribute_index=None, pass_index=0):
        self._texture_index = texture_index     # image -> texture table index
        self._attribute_index = attribute_index     # mesh attribute name -> its corners' texture
        self._pass_index = pass_index           # the material's pass index (Object Info)
        self._code = []                         # instructions: (op, dst, a, b, c, p0, p1, p2)
        self._ramps = []                        # (instruction index, table rows)
        self._values = {}                       # (node name, output) -> operand
        self._kinds = {}                        # operand -> its socket's type (RGBA, VECTOR)
        self._next = 0
        self.outputs = []
        self.transforms = []                    # (instruction index, "OBJECT", "GENERATED" or
        #                                         "INFO": Placement.matrices' tables)
        self.uv_maps = set()                    # UV maps UV Map nodes name ("": the default)
        self._step = 0                          # compiling a Bump's height: its step 0, 1, 2

    @property
    def reads_uv(self) -> bool:
        """Whether the program reads the UV map (UV coordinates, a tangent-space normal map)."""
        tangent = float(NODE_NORMAL_SPACE_CODES["TANGENT"])
        return any(op == "UV" or (op == "NORMAL_MAP" and params[1] == tangent)
                   for op, _, _, _, _, params in self._code)

    def output(self, socket, field, problems, strength=None) -> bool:
        """Evaluate the graph linked to `socket` into BSDF input `field` (times the socket
        `strength`, linked or not, when given: emission); False (with a problem naming the
        node) when it cannot."""
        saved = (list(self._code), list(self._ramps), dict(self._values), dict(self._kinds),
                 self._next, list(self.transforms))
        try:
            ref = self._operand(socket)
            if strength is not None:
                scale = self._as_float(self._operand(strength))
                register = self._register()
                self._emit("VECTOR_MATH", register, ref, 0, scale,
                           params=(NODE_VECTOR_MATH_CODES["SCALE"],))
                ref = self._whole(register)
        except _Unsupported as error:
            self._code, self._ramps, self._values, self._kinds, self._next, self.transforms = saved
            keeps = "the surface's own normal" if field == "NORMAL" else f"its value {socket_value(socket)}"
            problems.append(f"input '{socket.name}': {error}; using {keeps}")
            return False
        if field not in ("BASE_COLOR", "NORMAL", "EMISSION", "COAT_TINT"):
            ref = self._as_float(ref)
        self._emit("OUT", 0, ref, params=(NODE_OUT_CODES[field],))
        self.outputs.append(field)
        return True

    def weight(self, factors, constant, problems) -> bool:
        """The closure's weight as its program's WEIGHT output: `constant` times each linked
        Mix Shader factor (Fac, or 1 - Fac for the Mix Shader's first input), each clamped to
        [0, 1] as Cycles clamps it. False (with a problem naming the node) when a factor's
        graph cannot be evaluated: the weight is then a stand-in."""
        saved = (list(self._code), list(self._ramps), dict(self._values), dict(self._kinds),
                 self._next, list(self.transforms))
        try:
            ref = self._constant(float(constant))
            one = self._constant(1.0)
            clamp = (NODE_MATH_CODES["MAXIMUM"], NODE_MATH_CODES["MINIMUM"])
            for socket, inverted in factors:
                fac = self._as_float(self._operand(socket))
                low = self._register()
                self._emit("MATH", low, fac, self._constant(0.0), 0, params=(clamp[0], 1.0))
                fac = self._lane(low, 0)
                if inverted:
                    register = self._register()
                    self._emit("MATH", register, one, fac, 0,
                               params=(NODE_MATH_CODES["SUBTRACT"], 0.0))
                    fac = self._lane(register, 0)
                register = self._register()
                self._emit("MATH", register, ref, fac, 0,
                           params=(NODE_MATH_CODES["MULTIPLY"], 0.0))
                ref = self._lane(register, 0)
        except _Unsupported as error:
            self._code, self._ramps, self._values, self._kinds, self._next, self.transforms = saved
            problems.append(f"a Mix Shader's Fac: {error}; using 0.5")
            return False
        self._emit("OUT", 0, ref, params=(NODE_OUT_CODES["WEIGHT"],))
        self.outputs.append("WEIGHT")
        return True

    def rows(self, matrices=None) -> list:
        """The program's float4 rows: its instructions, END, then its tables (colour ramps,
        the coordinate transforms: `matrices` as Placement's; identity without one)."""
        code = self._code + [("END", 0, 0, 0, 0, (0.0, 0.0, 0.0))]
        identity = np.eye(4)[:3]
        tables = list(self._ramps) + [
            (index, [tuple(r) for r in (identity if matrices is None else matrices[kind])]
             + [(0.0, 0.0, 0.0, 0.0)] * (NODE_TRANSFORM_SIZE - 3))
            for index, kind in self.transforms]
        rows = []
        table_row = 2 * len(code)
        offsets = {}
        for index, table in tables:
            offsets[index] = table_row - 2 * index      # relative to the instruction
            table_row += len(table)
        for index, (op, dst, a, b, c, params) in enumerate(code):
            params = tuple(params) + (0.0,) * (3 - len(params))
            if index in offsets:            # RAMP, TRANSFORM, object space NORMAL_MAP
                params = (float(offsets[index]),) + params[1:]
            if op == "CONST":
                rows += [(NODE_OP_CODES[op], dst, 0, 0), tuple(a)]
            else:
                rows += [(NODE_OP_CODES[op], dst, a, b), (c,) + params]
        for _, table in tables:
            rows += [tuple(float(v) for v in r) for r in table]
        return rows

    # -- compiling ---------------------------------------------------------------------------
    def _register(self) -> int:
        if self._next >= NODE_REGISTERS:
            raise _Unsupported("the node graph needs more than "
                               f"{NODE_REGISTERS} values")
        self._next += 1
        return self._next - 1

    def _emit(self, op, dst, a=0, b=0, c=0, params=()):
        self._code.append((op, dst, a, b, c, params))

    def _whole(self, register):
        return register * NODE_REF_REGISTER + 4

    def _lane(self, register, lane):
        return register * NODE_REF_REGISTER + lane

    def _constant(self, value):
        """A register holding `value` (one per distinct value: a Bump compiles its height three
        times)."""
        key = ("constant", value if isinstance(value, tuple) else float(value))
        if key in self._values:
            return self._values[key]
        register = self._register()
        if not isinstance(value, tuple):
            self._code.append(("CONST", register, (float(value),) * 4, 0, 0, ()))
            self._values[key] = self._lane(register, 0)
            return self._values[key]
        self._kinds[self._whole(register)] = "RGBA" if len(value) == 4 else "VECTOR"
        value = tuple(float(v) for v in value) + (1.0,) * (4 - len(value))
        self._code.append(("CONST", register, value, 0, 0, ()))
        self._values[key] = self._whole(register)
        return self._values[key]

    def _input(self, node, key):
        """The operand of a node's input (by name or index), converted as Blender converts
        between colours, vectors and values."""
        socket = node.inputs[key]
        ref = self._operand(socket)
        return self._as_float(ref) if socket.type == "VALUE" else ref

    def _operand(self, socket):
        """The operand of a socket: the graph linked to it, or its own value."""
        return self._linked(socket) if socket.is_linked else self._constant(socket_value(socket))

    def _as_float(self, ref):
        """A single value from `ref`: a colour's luminance (Rec. 709, Cycles' conversion), a
        vector's mean."""
        if ref % NODE_REF_REGISTER != 4:
            return ref
        register = self._register()
        weights = (0.2126, 0.7152, 0.0722) if self._kinds.get(ref) == "RGBA" else (1 / 3,) * 3
        self._emit("DOT", register, ref, params=weights)
        return self._lane(register, 0)

    def _enabled_input(self, node, name):
        """The operand of the enabled input called `name` (the Mix node has one per type)."""
        for socket in node.inputs:
            if socket.name == name and socket.enabled:
                ref = self._linked(socket) if socket.is_linked else self._constant(socket_value(socket))
                return self._as_float(ref) if socket.type == "VALUE" else ref
        raise _Unsupported(f"node '{node.name}' has no input '{name}'")

    def _linked(self, socket):
        link = socket.links[0]
        if not link.is_valid or link.is_muted:
            raise _Unsupported(f"its link is muted or invalid")
        node, out = link.from_node, link.from_socket
        while node.type == "REROUTE":
            if not node.inputs[0].is_linked:
                return self._constant(socket_value(node.inputs[0]))
            link = node.inputs[0].links[0]
            node, out = link.from_node, link.from_socket
        key = (node.name, out.identifier, self._step)
        if key not in self._values:
            self._values[key] = self._node(node, out)
            self._kinds[self._values[key]] = out.type
        return self._values[key]

    def _node(self, node, out):
        # By identifier: Blender 5.0 shows the Fac outputs as "Factor" (their identifier is "Fac").
        kind, name = node.type, out.identifier
        if kind in ("TEX_COORD", "UVMAP") and name == "UV":
            if kind == "UVMAP" and node.uv_map:
                self.uv_maps.add(node.uv_map)
            return self._uv()
        if kind == "TEX_COORD" and name in ("Generated", "Object") and node.object is None:
            return self._coordinates(name.upper())
        if kind == "VALUE":
            return self._constant(float(out.default_value))
        if kind == "RGB":
            return self._constant(tuple(out.default_value))
        if kind == "TEX_IMAGE" and node.image is not None and node.projection == "FLAT" and \
                node.extension in NODE_EXTENSION_CODES:     # Cubic, Smart: bilinear
            vector = self._input(node, "Vector") if node.inputs["Vector"].is_linked else None
            if vector is None:
                vector = self._uv()
            register = self._register()
            self._emit("IMAGE", register, vector,
                       params=(self._texture_index(node.image), float(node.interpolation == "Closest"),
                               float(NODE_EXTENSION_CODES[node.extension])))
            return self._lane(register, 3) if name == "Alpha" else self._whole(register)
        if kind in ("SEPARATE_COLOR", "SEPRGB", "SEPXYZ") and \
                getattr(node, "mode", "RGB") == "RGB":
            source = self._input(node, 0)
            register = source // NODE_REF_REGISTER
            if source % NODE_REF_REGISTER != 4:        # a single value: all lanes alike
                return source
            lanes = {"Red": 0, "Green": 1, "Blue": 2, "R": 0, "G": 1, "B": 2, "X": 0, "Y": 1, "Z": 2}
            return self._lane(register, lanes[name])
        if kind in ("COMBINE_COLOR", "COMBRGB", "COMBXYZ") and \
                getattr(node, "mode", "RGB") == "RGB":
            a, b, c = (self._input(node, k) for k in range(3))
            register = self._register()
            self._emit("COMBINE", register, a, b, c)
            return self._whole(register)
        if kind == "MIX" and node.blend_type in NODE_MIX_CODES:
            if node.data_type == "VECTOR" and node.factor_mode != "UNIFORM":
                raise _Unsupported(f"node '{node.name}' (Mix, non-uniform factor) is not evaluated")
            fac = self._enabled_input(node, "Factor")
            if node.clamp_factor is False:
                raise _Unsupported(f"node '{node.name}' (Mix without Clamp Factor) is not evaluated")
            a, b = self._enabled_input(node, "A"), self._enabled_input(node, "B")
            register = self._register()
            mode = node.blend_type if node.data_type == "RGBA" else "MIX"
            self._emit("MIX", register, fac, a, b,
                       params=(NODE_MIX_CODES[mode], float(node.data_type == "RGBA" and node.clamp_result)))
            return self._whole(register)
        if kind == "MIX_RGB" and node.blend_type in NODE_MIX_CODES:
            fac, a, b = (self._input(node, k) for k in range(3))
            register = self._register()
            self._emit("MIX", register, fac, a, b,
                       params=(NODE_MIX_CODES[node.blend_type], float(node.use_clamp)))
            return self._whole(register)
        if kind == "MATH" and node.operation in NODE_MATH_CODES:
            a, b, c = (self._input(node, k) for k in range(3))
            register = self._register()
            self._emit("MATH", register, a, b, c,
                       params=(NODE_MATH_CODES[node.operation], float(node.use_clamp)))
            return self._lane(register, 0)
        if kind == "INVERT":
            fac, color = self._input(node, "Fac"), self._input(node, "Color")
            register = self._register()
            self._emit("INVERT", register, fac, color)
            return self._whole(register)
        if kind == "TEX_CHECKER":
            vector = self._input(node, "Vector") if node.inputs["Vector"].is_linked \
                else self._coordinates("GENERATED")
            c1, c2 = self._input(node, "Color1"), self._input(node, "Color2")
            scale = node.inputs["Scale"]
            if scale.is_linked:
                raise _Unsupported(f"node '{node.name}' (Checker Texture, linked Scale) is not evaluated")
            register = self._register()
            self._emit("CHECKER", register, vector, c1, c2, params=(float(scale.default_value),))
            return self._lane(register, 3) if name == "Fac" else self._whole(register)
        if kind == "VALTORGB":
            ramp = node.color_ramp
            if ramp.color_mode != "RGB" or ramp.interpolation not in ("LINEAR", "CONSTANT"):
                raise _Unsupported(f"node '{node.name}' (Color Ramp, {ramp.color_mode} "
                                   f"{ramp.interpolation}) is not evaluated")
            fac = self._input(node, "Fac")
            register = self._register()
            table = [tuple(ramp.evaluate(i / (NODE_RAMP_SIZE - 1))) for i in range(NODE_RAMP_SIZE)]
            self._ramps.append((len(self._code), table))
            self._emit("RAMP", register, fac,
                       params=(0.0, float(ramp.interpolation != "CONSTANT")))
            return self._lane(register, 3) if name == "Alpha" else self._whole(register)
        if kind == "MAP_RANGE" and node.data_type == "FLOAT" and node.interpolation_type == "LINEAR":
            value, lo, hi, to_lo, to_hi = (self._input(node, k) for k in
                                           ("Value", "From Min", "From Max", "To Min", "To Max"))
            ranges = self._register()
            self._emit("COMBINE", ranges, lo, hi, to_lo)
            register = self._register()
            self._emit("MAP_RANGE", register, value, self._whole(ranges), to_hi,
                       params=(0.0, float(node.clamp)))
            return self._lane(register, 0)
        if kind == "VECT_MATH" and node.operation in NODE_VECTOR_MATH_CODES:
            a, b = self._vector_input(node, 0), self._vector_input(node, 1)
            if node.operation in ("SCALE", "REFRACT"):
                third = self._enabled_input(node, "Scale")
            else:
                third = self._vector_input(node, 2)
            register = self._register()
            self._emit("VECTOR_MATH", register, a, b, third,
                       params=(NODE_VECTOR_MATH_CODES[node.operation],))
            return self._lane(register, 3) if out.type == "VALUE" else self._whole(register)
        if kind == "HUE_SAT":
            hue, saturation, value, fac, color = (self._input(node, k) for k in
                                                  ("Hue", "Saturation", "Value", "Fac", "Color"))
            hsv = self._register()
            self._emit("COMBINE", hsv, hue, saturation, value)
            register = self._register()
            self._emit("HSV", register, fac, color, self._whole(hsv))
            return self._whole(register)
        if kind == "TEX_GRADIENT" and node.gradient_type in NODE_GRADIENT_CODES:
            vector = self._input(node, "Vector") if node.inputs["Vector"].is_linked \
                else self._coordinates("GENERATED")
            register = self._register()
            self._emit("GRADIENT", register, vector,
                       params=(NODE_GRADIENT_CODES[node.gradient_type],))
            return self._lane(register, 0) if name == "Fac" else self._whole(register)
        if kind == "TEX_NOISE":
            return self._noise(node, name)
        if kind == "TEX_VORONOI":
            return self._voronoi(node, name)
        if kind == "TEX_WAVE":
            settings = self._pack(node, ("Scale", "Distortion", "Detail"))
            more = self._pack(node, ("Detail Scale", "Detail Roughness", "Phase Offset"))
            register = self._register()
            flags = NODE_WAVE_TYPE_CODES[node.wave_type] + 2 * NODE_WAVE_BANDS_CODES[
                node.bands_direction] + 8 * NODE_WAVE_RINGS_CODES[node.rings_direction] + \
                32 * NODE_WAVE_PROFILE_CODES[node.wave_profile]
            self._emit("WAVE", register, self._texture_vector(node), settings, more,
                       params=(float(flags),))
            return self._lane(register, 0) if name == "Fac" else self._whole(register)
        if kind == "TEX_MAGIC":
            register = self._register()
            self._emit("MAGIC", register, self._texture_vector(node),
                       self._pack(node, ("Scale", "Distortion")),
                       params=(float(node.turbulence_depth),))
            return self._lane(register, 3) if name == "Fac" else self._whole(register)
        if kind == "TEX_BRICK":
            return self._brick(node, name)
        if kind == "TEX_WHITE_NOISE":
            dims = int(node.noise_dimensions[0])
            w = _named_input(node, "W")
            register = self._register()
            self._emit("WHITE_NOISE", register,
                       self._texture_vector(node) if dims > 1 else 0,
                       self._as_float(self._operand(w)) if dims in (1, 4) else 0,
                       params=(float(dims + 8 * (name == "Color")),))
            return self._whole(register) if name == "Color" else self._lane(register, 0)
        if kind == "NORMAL_MAP":
            colour, strength = self._input(node, "Color"), self._input(node, "Strength")
            register = self._register()
            if node.space in NODE_OBJECT_NORMAL_SPACES:
                self.transforms.append((len(self._code), "OBJECT"))     # its normal matrix
            self._emit("NORMAL_MAP", register, colour, strength,
                       params=(0.0, float(NODE_NORMAL_SPACE_CODES[node.space])))
            return self._whole(register)
        if kind == "BUMP":
            return self._bump(node)
        if kind == "MAPPING":
            return self._mapping(node)
        if kind == "LIGHT_PATH":
            code = NODE_LIGHT_PATH_CODES[name.upper().replace(" ", "_")]
            register = self._register()
            self._emit("LIGHT_PATH", register, params=(float(code),))
            return self._lane(register, 0)
        if kind == "NEW_GEOMETRY" and name.upper().replace(" ", "_") in NODE_GEOMETRY_CODES:
            code = NODE_GEOMETRY_CODES[name.upper().replace(" ", "_")]
            register = self._register()
            self._emit("GEOMETRY", register, params=(float(code), float(self._step)))
            if name == "Backfacing":
                return self._lane(register, 0)
            self._kinds[self._whole(register)] = "VECTOR"
            return self._whole(register)
        if kind == "OBJECT_INFO":
            if name == "Material Index":
                return self._constant(float(self._pass_index))
            register = self._register()
            self.transforms.append((len(self._code), "INFO"))
            self._emit("OBJECT_INFO", register,
                       params=(0.0, float(NODE_OBJECT_INFO_CODES[name.upper().replace(" ", "_")])))
            return self._whole(register) if name in ("Location", "Color") else self._lane(register, 0)
        if kind in ("VERTEX_COLOR", "ATTRIBUTE") and self._attribute_index is not None and \
                getattr(node, "attribute_type", "GEOMETRY") == "GEOMETRY":
            attribute = node.layer_name if kind == "VERTEX_COLOR" else node.attribute_name
            register = self._register()
            code = {"Alpha": "ALPHA", "Fac": "FAC"}.get(name, "COLOR")
            self._emit("ATTRIBUTE", register, params=(float(self._attribute_index(attribute)),
                                                      float(NODE_ATTRIBUTE_CODES[code])))
            return self._whole(register) if code == "COLOR" else self._lane(register, 0)
        if kind in ("FRESNEL", "LAYER_WEIGHT"):
            value = self._input(node, "IOR" if kind == "FRESNEL" else "Blend")
            normal = node.inputs["Normal"]
            normal_ref = self._input(node, "Normal") if normal.is_linked else 0
            register = self._register()
            code = NODE_LAYER_WEIGHT_CODES.get(name.upper(), 0)
            self._emit(kind, register, value, normal_ref,
                       params=(float(code), float(normal.is_linked)))
            return self._lane(register, 0)
        raise _Unsupported(f"node '{node.name}' ({node.bl_idname}) is not evaluated")

    def _noise(self, node, name):
        """Noise Texture (every type, 1D to 4D): one instruction for both outputs; its Color
        (two more fractal sums) only when that output is linked."""
        dims = int(node.noise_dimensions[0])
        distortion = node.inputs["Distortion"]
        w = _named_input(node, "W")
        for socket in (distortion, w):
            if socket.is_linked and (socket is distortion or dims in (1, 4)):
                raise _Unsupported(f"node '{node.name}' (Noise Texture, linked {socket.name}) "
                                   "is not evaluated")
        key = (node.name, "noise", self._step)
        if key not in self._values:
            vector = 0
            if dims > 1:
                vector = self._input(node, "Vector") if node.inputs["Vector"].is_linked \
                    else self._coordinates("GENERATED")
            settings = self._pack(node, ("Detail", "Roughness", "Lacunarity"))
            scale = self._pack(node, ("Scale", "Offset", "Gain"))
            register = self._register()
            flags = int(node.normalize) + 2 * int(node.outputs["Color"].is_linked) + 4 * dims \
                + 32 * NODE_NOISE_TYPE_CODES[node.noise_type]
            self._emit("NOISE", register, vector, settings, scale,
                       params=(float(flags), float(distortion.default_value), float(w.default_value)))
            self._values[key] = register
        register = self._values[key]
        return self._lane(register, 0) if name == "Fac" else self._whole(register)

    def _texture_vector(self, node):
        """A texture's Vector: its link, else the Generated coordinates (Cycles' default)."""
        return self._input(node, "Vector") if node.inputs["Vector"].is_linked \
            else self._coordinates("GENERATED")

    def _voronoi(self, node, name):
        """Voronoi Texture (every feature and metric, 1D to 4D, fractal detail): one
        instruction per output (Distance or Radius, Color, Position with W in its last lane)."""
        dims = int(node.voronoi_dimensions[0])
        for socket in (_named_input(node, "W"), _named_input(node, "Randomness")):
            if socket.is_linked:
                raise _Unsupported(f"node '{node.name}' (Voronoi Texture, linked {socket.name}) "
                                   "is not evaluated")
        output = {"Color": "COLOR", "Position": "POSITION", "W": "POSITION"}.get(name, "DISTANCE")
        key = (node.name, "voronoi", output, self._step)
        if key not in self._values:
            vector = self._texture_vector(node) if dims > 1 else 0
            settings = self._pack(node, ("Scale", "Detail", "Roughness"))
            more = self._pack(node, ("Lacunarity", "Smoothness", "Exponent"))
            register = self._register()
            flags = dims + 8 * NODE_VORONOI_FEATURE_CODES[node.feature] + \
                64 * NODE_VORONOI_METRIC_CODES[node.distance] + 512 * int(node.normalize) + \
                1024 * NODE_VORONOI_OUTPUT_CODES[output]
            self._emit("VORONOI", register, vector, settings, more,
                       params=(float(flags), float(_named_input(node, "Randomness").default_value),
                               float(_named_input(node, "W").default_value)))
            self._values[key] = register
        register = self._values[key]
        if name in ("Color", "Position"):
            return self._whole(register)
        return self._lane(register, 3 if name == "W" else 0)

    def _brick(self, node, name):
        """Brick Texture: BRICK gives (tint, mortar); the colour is two Mix instructions, as
        Cycles blends Color1 to Color2 by the tint, then to Mortar by the mortar."""
        key = (node.name, "brick", self._step)
        if key not in self._values:
            register = self._register()
            self._emit("BRICK", register, self._texture_vector(node),
                       self._pack(node, ("Scale", "Mortar Size", "Mortar Smooth")),
                       self._pack(node, ("Bias", "Brick Width", "Row Height")),
                       params=(float(node.offset_frequency + 256 * node.squash_frequency),
                               float(node.offset), float(node.squash)))
            self._values[key] = register
        register = self._values[key]
        if name == "Fac":
            return self._lane(register, 1)
        c1, c2, mortar = (self._input(node, k) for k in ("Color1", "Color2", "Mortar"))
        tinted = self._register()
        self._emit("MIX", tinted, self._lane(register, 0), c1, c2,
                   params=(NODE_MIX_CODES["MIX"], 0.0))
        colour = self._register()
        self._emit("MIX", colour, self._lane(register, 1), self._whole(tinted), mortar,
                   params=(NODE_MIX_CODES["MIX"], 0.0))
        return self._whole(colour)

    def _bump(self, node):
        """Bump: its height compiled three times, at the hit and at two steps along the surface
        (UV and TRANSFORM read the moved point), as Cycles evaluates it."""
        if self._step:
            raise _Unsupported(f"node '{node.name}' (a Bump in a Bump's height) is not evaluated")
        heights = []
        try:
            for step in (0, 1, 2):
                self._step = step
                heights.append(self._input(node, "Height"))
        finally:
            self._step = 0
        combined = self._register()
        self._emit("COMBINE", combined, *heights)
        normal = node.inputs["Normal"]
        normal_ref = self._input(node, "Normal") if normal.is_linked else 0
        settings = self._pack(node, ("Strength", "Distance"))
        register = self._register()
        self._emit("BUMP", register, self._whole(combined), normal_ref, settings,
                   params=(float(node.invert), float(normal.is_linked)))
        return self._whole(register)

    def _mapping(self, node):
        """Mapping (Point, Texture, Vector, Normal) with unlinked Location, Rotation and Scale:
        three dot products with the rows of its matrix, its offset added, combined (and
        normalised for Normal)."""
        values = {}
        for name, default in (("Location", (0.0,) * 3), ("Rotation", (0.0,) * 3),
                              ("Scale", (1.0,) * 3)):
            socket = node.inputs.get(name)
            if socket is None or not socket.enabled:
                values[name] = default
                continue
            if socket.is_linked:
                raise _Unsupported(f"node '{node.name}' (Mapping, linked {name}) is not evaluated")
            values[name] = tuple(socket_value(socket))[:3]
        matrix, offset = mapping_affine(node.vector_type, values["Location"], values["Rotation"],
                                        values["Scale"])
        vector = self._input(node, "Vector")
        axes = []
        for row, add in zip(matrix, offset):
            register = self._register()
            self._emit("DOT", register, vector, params=tuple(float(v) for v in row))
            axis = self._lane(register, 0)
            if add:
                total = self._register()
                self._emit("MATH", total, axis, self._constant(float(add)), 0,
                           params=(NODE_MATH_CODES["ADD"], 0.0))
                axis = self._lane(total, 0)
            axes.append(axis)
        register = self._register()
        self._emit("COMBINE", register, *axes)
        if node.vector_type == "NORMAL":
            normal = self._register()
            self._emit("VECTOR_MATH", normal, self._whole(register), 0, 0,
                       params=(NODE_VECTOR_MATH_CODES["NORMALIZE"],))
            register = normal
        self._kinds[self._whole(register)] = "VECTOR"
        return self._whole(register)

    def _pack(self, node, names):
        """Up to three float inputs in the lanes of one register: a constant when none is
        linked."""
        sockets = [_named_input(node, k) for k in names]
        if not any(socket.is_linked for socket in sockets):
            return self._constant(tuple(socket_value(socket) for socket in sockets)
                                  + (0.0,) * (3 - len(names)))
        a, b, c = [self._as_float(self._operand(socket)) for socket in sockets] \
            + [self._constant(0.0)] * (3 - len(names))
        register = self._register()
        self._emit("COMBINE", register, a, b, c)
        return self._whole(register)

    def _uv(self):
        """The hit's UVs (at the Bump step being compiled)."""
        key = ("uv", self._step)
        if key not in self._values:
            register = self._register()
            self._emit("UV", register, params=(float(self._step),))
            self._values[key] = self._whole(register)
        return self._values[key]

    def _coordinates(self, kind):
        """The hit point in Generated or Object coordinates (the unlinked default of the
        procedural textures is Generated)."""
        key = ("coordinates", kind, self._step)
        if key not in self._values:
            register = self._register()
            self.transforms.append((len(self._code), kind))
            self._emit("TRANSFORM", register, params=(0.0, float(self._step)))
            self._values[key] = self._whole(register)
            self._kinds[self._whole(register)] = "VECTOR"
        return self._values[key]

    def _vector_input(self, node, index):
        """Vector Math's vector input `index` (the node has three called Vector; those its
        operation does not use are disabled: register 0, never read)."""
        vectors = [s for s in node.inputs if s.name == "Vector"]
        socket = vectors[index]
        if not socket.enabled:
            return 0
        return self._linked(socket) if socket.is_linked else self._constant(socket_value(socket))
